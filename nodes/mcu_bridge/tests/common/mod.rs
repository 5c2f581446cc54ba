//! What the bridge's integration tests share: the emulated MCU in the same process behind
//! the link (80 ppm crystal, its own clock offset), and the start of finger.gcode planned.

#![allow(dead_code)]

use std::convert::Infallible;

use cell_firmware_core::StepEdge;
use gcode_streamer::{parse_all, GcodeMove, InterpreterOptions};
use mcu_bridge::{McuLink, McuMachine, McuSession, SessionOptions};
use mcu_emulator::{Crystal, Emulator, EmulatorOptions};
use polar_cell_msgs::{StepSegment, Time};
use polar_planner::steps::StepOptions;
use polar_planner::{plan_program, PlannerOptions};

/// The emulator as the line: what the host writes arrives at once; reading runs the MCU to
/// the host's time.
pub struct InProcess {
    pub mcu: Emulator,
    pub edges: Vec<StepEdge>,
}

impl InProcess {
    /// An MCU just powered up with these options, no edges yet.
    pub fn new(options: EmulatorOptions) -> InProcess {
        InProcess {
            mcu: Emulator::new(options),
            edges: Vec::new(),
        }
    }
}

impl McuLink for InProcess {
    type Error = Infallible;
    fn read(&mut self, now_ns: i64, into: &mut Vec<u8>) -> Result<(), Infallible> {
        let edges = &mut self.edges;
        self.mcu
            .run_until(now_ns as f64 * 1e-9, &mut |e| edges.push(e), into);
        Ok(())
    }
    fn write(&mut self, now_ns: i64, bytes: &[u8]) -> Result<(), Infallible> {
        self.mcu.receive(bytes, now_ns as f64 * 1e-9);
        Ok(())
    }
}

pub const EPOCH_NS: i64 = 1_700_000_000_000_000_000;

/// Every move of finger.gcode.
pub fn finger_moves() -> Vec<GcodeMove> {
    let path = concat!(
        env!("CARGO_MANIFEST_DIR"),
        "/../../../shared/fixtures/gcode/finger.gcode"
    );
    let src = std::fs::read(path).unwrap();
    parse_all(&src, "finger.gcode", InterpreterOptions::default())
        .unwrap()
        .0
}

pub fn finger_start(moves: usize) -> Vec<StepSegment> {
    let mut all = finger_moves();
    all.truncate(moves);
    let mut segments = plan_program(&all, PlannerOptions::default(), StepOptions::default())
        .unwrap()
        .segments;
    stamp(&mut segments, EPOCH_NS);
    segments
}

/// Stamp each segment with its start on the producers' clock, as the planner does.
pub fn stamp(segments: &mut [StepSegment], epoch_ns: i64) {
    let mut start_s = 0.0;
    for s in segments {
        s.header.stamp = Time::after(epoch_ns, start_s);
        start_s += s.duration_s;
    }
}

/// Where the plan ends, in steps.
pub fn end_steps(segments: &[StepSegment]) -> [i64; 3] {
    let mut steps = [0i64; 3];
    for s in segments {
        for (k, step) in steps.iter_mut().enumerate() {
            *step += s.step_counts[k] as i64 * s.directions[k] as i64;
        }
    }
    steps
}

/// The MCU machine on an in-process emulator (1 MHz timer, 80 ppm fast, offset), as the
/// node builds it: the planner's steps and accelerations, a 0.25 s pin delay, 64 places, a
/// 2 s horizon.
pub fn mcu_machine(emulator: EmulatorOptions) -> McuMachine<InProcess> {
    mcu_machine_with_crystal(
        Crystal {
            timer_hz: 1e6,
            offset_ticks: 123_456_789,
            rate_ppm: 80.0,
            drift_ppm_per_s: 0.0,
        },
        emulator,
    )
}

/// [`mcu_machine`] with the MCU's crystal as given.
pub fn mcu_machine_with_crystal(
    crystal: Crystal,
    emulator: EmulatorOptions,
) -> McuMachine<InProcess> {
    mcu_machine_with(
        session_options(),
        EmulatorOptions {
            crystal,
            ..emulator
        },
    )
}

/// The session as the node builds it by default: the planner's steps and accelerations, a
/// 0.25 s pin delay.
pub fn session_options() -> SessionOptions {
    SessionOptions::new(
        StepOptions::default().steps_per_unit,
        std::array::from_fn(|j| PlannerOptions::default().joints[j].acceleration),
        0.25,
    )
}

/// The MCU machine with these session options on this in-process emulator: 64 places, a 2 s
/// horizon.
pub fn mcu_machine_with(
    options: SessionOptions,
    emulator: EmulatorOptions,
) -> McuMachine<InProcess> {
    mcu_machine_on(options, InProcess::new(emulator))
}

/// The MCU machine with these session options on `link`: 64 places, the session's horizon.
pub fn mcu_machine_on<L: McuLink>(options: SessionOptions, link: L) -> McuMachine<L> {
    let horizon_s = options.horizon_s;
    McuMachine::new(McuSession::new(options, 0x5EED), link, 64, horizon_s)
}
