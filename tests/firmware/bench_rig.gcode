; Seed 001's bench rig under emulation (tests/firmware/run.sh): a 5 mm square about the bed's
; centre, corners on the axes, then up 0.5 mm and back through the centre. Small enough for
; 28BYJ-48 motors at 500 steps/s: the arm moves 256 steps per mm, the bed 325.9 per rad.
G21
G90
M83
G28
G1 X5 Y0 F300
G1 X0 Y5 E0.2 F300
G1 X-5 Y0 E0.2
G1 X0 Y-5 E0.2
G1 X5 Y0 E0.2
G1 Z0.5 F60
G1 X-2 Y0 F300
