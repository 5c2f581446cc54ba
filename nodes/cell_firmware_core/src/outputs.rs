//! From step edges to pin levels: the output stage of each axis.
//!
//! The cell drives its steppers through step/dir drivers; seed 001's bench rig drives three
//! 28BYJ-48 motors through ULN2003 boards, four coil inputs per axis, in two-phase
//! excitation. Which one an axis has is a build-time profile of the firmware; this module
//! turns a [`StepEdge`] into the GPIO writes for either, so the RP2040 build only writes
//! registers and the host tests check the sequences.
//!
//! Pins are bit positions of the RP2040's SIO GPIO registers (GP0 = bit 0).

use step_core::MAX_AXES;

use crate::machine::StepEdge;

/// Two-phase excitation of a 28BYJ-48 turning clockwise, coil inputs IN1..IN4 of its ULN2003
/// board per step (seed 001, table 3: IN1 HLLH, IN2 HHLL, IN3 LHHL, IN4 LLHH). The seed's
/// Arduino `Stepper(2048, 0, 2, 1, 3)` lists GP0, GP2, GP1, GP3 because that library's
/// sequence has IN2 and IN3 swapped; driving IN1..IN4 from this table needs no swap.
pub const TWO_PHASE_SEQUENCE: [[bool; 4]; 4] = [
    [true, true, false, false],
    [false, true, true, false],
    [false, false, true, true],
    [true, false, false, true],
];

/// How one axis is driven.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum OutputStage {
    /// A step/dir driver: a pulse on `step_pin` per step, `dir_pin` high for positive steps
    /// (inverted by `dir_inverted`).
    StepDir {
        step_pin: u8,
        dir_pin: u8,
        dir_inverted: bool,
    },
    /// A unipolar motor's four coil inputs IN1..IN4, stepped through
    /// [`TWO_PHASE_SEQUENCE`] (forward = clockwise).
    FourCoil { pins: [u8; 4] },
    /// Not connected.
    None,
}

impl OutputStage {
    fn mask(&self) -> u32 {
        match *self {
            OutputStage::StepDir {
                step_pin, dir_pin, ..
            } => (1 << step_pin) | (1 << dir_pin),
            OutputStage::FourCoil { pins } => pins.iter().fold(0, |m, &p| m | (1 << p)),
            OutputStage::None => 0,
        }
    }

    fn coil_levels(pins: [u8; 4], phase: u8) -> u32 {
        let row = TWO_PHASE_SEQUENCE[(phase & 3) as usize];
        (0..4).fold(0, |m, i| if row[i] { m | (1 << pins[i]) } else { m })
    }
}

/// The register writes for one edge, in the order a driver needs them.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct EdgeWrites {
    /// Direction pins to set, then to clear, before the step pulse (a driver's set-up time).
    pub dir_set: u32,
    pub dir_clear: u32,
    /// Step pins to raise for the edge (and to bring low again after the pulse width).
    /// Raised, not toggled: a step whose predecessor's pulse has not ended keeps it high.
    pub step_set: u32,
    /// Coil inputs that change for the edge (exactly those: toggling them moves the phase).
    pub coil_toggle: u32,
}

/// The output stages of all axes and the coil phases they are at.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct Outputs {
    stages: [OutputStage; MAX_AXES],
    phases: [u8; MAX_AXES],
    /// Levels of the direction pins now, so that unchanged ones are not rewritten.
    dir_levels: u32,
}

impl Outputs {
    /// Stages of each axis; coils start at phase `step position mod 4`, so that a motor left
    /// energised keeps its phase across a firmware restart that keeps positions.
    pub fn new(stages: [OutputStage; MAX_AXES], initial_steps: [i32; MAX_AXES]) -> Outputs {
        Outputs {
            stages,
            phases: core::array::from_fn(|a| initial_steps[a].rem_euclid(4) as u8),
            dir_levels: 0,
        }
    }

    /// Every pin the stages drive.
    pub fn mask(&self) -> u32 {
        self.stages.iter().fold(0, |m, s| m | s.mask())
    }

    /// Levels to drive at start (and to energise the coils again after a stop): step pins
    /// low, directions low, coils at their phase.
    pub fn initial_levels(&self) -> u32 {
        self.stages
            .iter()
            .zip(self.phases)
            .fold(0, |m, (stage, phase)| match *stage {
                OutputStage::FourCoil { pins } => m | OutputStage::coil_levels(pins, phase),
                _ => m,
            })
    }

    /// Coil inputs to release at a stop (the ULN2003 sinks current through a held coil; a
    /// stopped bench rig must not cook its motors). Step/dir drivers have their own enable.
    pub fn coil_mask(&self) -> u32 {
        self.stages.iter().fold(0, |m, s| match s {
            OutputStage::FourCoil { .. } => m | s.mask(),
            _ => m,
        })
    }

    /// Take the state back from the pins' `levels` (the SIO output register): after a stop
    /// dropped edges whose writes were computed but never made, the direction pins and coil
    /// phases are what the pins show, not what the dropped edges would have made them.
    /// Coils showing no phase (released) keep the phase they had.
    pub fn resync(&mut self, levels: u32) {
        self.dir_levels = 0;
        for (axis, stage) in self.stages.iter().enumerate() {
            match *stage {
                OutputStage::StepDir { dir_pin, .. } => {
                    self.dir_levels |= levels & (1 << dir_pin);
                }
                OutputStage::FourCoil { pins } => {
                    if let Some(phase) = coil_phase(levels, pins) {
                        self.phases[axis] = phase;
                    }
                }
                OutputStage::None => {}
            }
        }
    }

    /// The writes for `edge`, advancing the coil phases.
    pub fn edge(&mut self, edge: StepEdge) -> EdgeWrites {
        let mut w = EdgeWrites::default();
        for axis in 0..MAX_AXES {
            if edge.axes & (1 << axis) == 0 {
                continue;
            }
            let negative = edge.negative & (1 << axis) != 0;
            match self.stages[axis] {
                OutputStage::StepDir {
                    step_pin,
                    dir_pin,
                    dir_inverted,
                } => {
                    let dir_bit = 1 << dir_pin;
                    if negative == dir_inverted {
                        w.dir_set |= dir_bit & !self.dir_levels;
                        self.dir_levels |= dir_bit;
                    } else {
                        w.dir_clear |= dir_bit & self.dir_levels;
                        self.dir_levels &= !dir_bit;
                    }
                    w.step_set |= 1 << step_pin;
                }
                OutputStage::FourCoil { pins } => {
                    let from = self.phases[axis];
                    let to = if negative {
                        from.wrapping_sub(1) & 3
                    } else {
                        (from + 1) & 3
                    };
                    self.phases[axis] = to;
                    w.coil_toggle |=
                        OutputStage::coil_levels(pins, from) ^ OutputStage::coil_levels(pins, to);
                }
                OutputStage::None => {}
            }
        }
        w
    }
}

/// The coil phase (0..4) that the levels of `pins` show, if they show one of
/// [`TWO_PHASE_SEQUENCE`]: what a test or a logic analyser decodes a bench-rig recording by.
pub fn coil_phase(levels: u32, pins: [u8; 4]) -> Option<u8> {
    (0..4u8).find(|&phase| {
        let row = TWO_PHASE_SEQUENCE[phase as usize];
        (0..4).all(|i| (levels >> pins[i] & 1 == 1) == row[i])
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    const BENCH: [OutputStage; 3] = [
        OutputStage::FourCoil { pins: [0, 1, 2, 3] },
        OutputStage::FourCoil { pins: [4, 5, 6, 7] },
        OutputStage::FourCoil {
            pins: [8, 9, 10, 11],
        },
    ];

    fn edge(axes: u8, negative: u8) -> StepEdge {
        StepEdge {
            clock: 0,
            axes,
            negative,
        }
    }

    #[test]
    fn the_coil_sequence_is_the_seeds_table() {
        // Table 3 of seed 001, by input: IN1 H L L H, IN2 H H L L, IN3 L H H L, IN4 L L H H.
        let by_input = ["HLLH", "HHLL", "LHHL", "LLHH"];
        for (input, row) in by_input.iter().enumerate() {
            for (step, level) in row.chars().enumerate() {
                assert_eq!(TWO_PHASE_SEQUENCE[step][input], level == 'H');
            }
        }
        // Two coils on at every step, one changing per step: full-step two-phase drive.
        for (step, row) in TWO_PHASE_SEQUENCE.iter().enumerate() {
            let next = &TWO_PHASE_SEQUENCE[(step + 1) % 4];
            assert_eq!(row.iter().filter(|&&on| on).count(), 2);
            let changed = row.iter().zip(next).filter(|(a, b)| a != b).count();
            assert_eq!(changed, 2, "one coil off, the next on");
        }
    }

    #[test]
    fn coil_edges_decode_back_to_the_position() {
        let mut outputs = Outputs::new(BENCH, [0, 5, -3]);
        let mut levels = outputs.initial_levels();
        let mut positions = [0i32, 5, -3];
        let moves: [(u8, u8); 9] = [
            (0b001, 0),
            (0b011, 0b010),
            (0b111, 0b100),
            (0b100, 0b100),
            (0b001, 0b001),
            (0b110, 0),
            (0b111, 0b111),
            (0b010, 0),
            (0b001, 0),
        ];
        for (axes, negative) in moves {
            let w = outputs.edge(edge(axes, negative));
            assert_eq!(w.dir_set | w.dir_clear | w.step_set, 0);
            levels ^= w.coil_toggle;
            for (axis, position) in positions.iter_mut().enumerate() {
                if axes & (1 << axis) != 0 {
                    *position += if negative & (1 << axis) != 0 { -1 } else { 1 };
                }
                let pins = [[0, 1, 2, 3], [4, 5, 6, 7], [8, 9, 10, 11]][axis];
                let phase = coil_phase(levels, pins).expect("a valid phase");
                assert_eq!(phase as i32, position.rem_euclid(4), "axis {axis}");
            }
        }
        assert_eq!(positions, [2, 6, -5]);
    }

    #[test]
    fn step_dir_sets_direction_only_when_it_changes_and_pulses_the_step_pin() {
        let stages = [
            OutputStage::StepDir {
                step_pin: 0,
                dir_pin: 1,
                dir_inverted: false,
            },
            OutputStage::StepDir {
                step_pin: 4,
                dir_pin: 5,
                dir_inverted: true,
            },
            OutputStage::None,
        ];
        let mut outputs = Outputs::new(stages, [0; 3]);
        assert_eq!(outputs.mask(), 0b11_0011);
        assert_eq!(outputs.initial_levels(), 0);
        let w = outputs.edge(edge(0b011, 0b000));
        assert_eq!(
            (w.dir_set, w.dir_clear),
            (1 << 1, 0),
            "axis 1 inverted: stays low"
        );
        assert_eq!((w.step_set, w.coil_toggle), (0b1_0001, 0));
        let w = outputs.edge(edge(0b001, 0));
        assert_eq!((w.dir_set, w.dir_clear), (0, 0), "unchanged");
        let w = outputs.edge(edge(0b011, 0b011));
        assert_eq!((w.dir_set, w.dir_clear), (1 << 5, 1 << 1));
        assert_eq!(outputs.edge(edge(0b100, 0)), EdgeWrites::default());
    }

    #[test]
    fn after_a_stop_the_stage_follows_the_pins_not_the_dropped_edges() {
        let stages = [
            OutputStage::StepDir {
                step_pin: 0,
                dir_pin: 1,
                dir_inverted: false,
            },
            OutputStage::FourCoil { pins: [4, 5, 6, 7] },
            OutputStage::None,
        ];
        let mut outputs = Outputs::new(stages, [0; 3]);
        // Written to the pins: one forward step of each.
        let mut levels = outputs.initial_levels();
        let w = outputs.edge(edge(0b011, 0));
        levels = ((levels | w.dir_set | w.step_set) & !w.dir_clear) ^ w.coil_toggle;
        levels &= !w.step_set; // the pulse ended
        let pins_then = outputs;
        // Computed but dropped at a stop: two backward steps.
        outputs.edge(edge(0b011, 0b011));
        outputs.edge(edge(0b011, 0b011));
        assert_ne!(outputs, pins_then);
        outputs.resync(levels);
        assert_eq!(outputs, pins_then);
        // Released coils show no phase: the phase the stage had stays.
        outputs.edge(edge(0b010, 0));
        let phase_before = outputs;
        outputs.resync(levels & !0xF0);
        assert_eq!(outputs.initial_levels(), phase_before.initial_levels());
    }
}
