; The cell's top step rates on the RP2040 (tests/firmware/run.sh): circles about the bed's
; centre at 5 mm radius, fast enough that the bed turns at its 6 rad/s limit (30,558
; steps/s at 5,093 steps/rad), then the arm out and back at its 0.2 m/s limit (16,000
; steps/s at 80,000 steps/m), then both at once on a spiral.
G21
G90
M83
G28
G4 P500 ; half a second at rest first: the pin opens 0.25 s before the first extrusion
G1 X5 Y0 F3000
G2 X5 Y0 I-5 J0 E1 F6000
G2 X5 Y0 I-5 J0 E1
G2 X5 Y0 I-5 J0 E1
G1 X100 Y0 F12000
G1 X5 Y0
G1 X100 Y0
G1 X5 Y0
G2 X-20 Y0 I-12.5 J0 E1 F12000
G2 X30 Y0 I25 J0 E1
