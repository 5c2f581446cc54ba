//! Any bytes as a CDR sample of each message type the nodes subscribe to: decoded or an
//! error, never a panic or an allocation the input's length cannot back. A step segment that
//! decodes is compiled for the shared step core and, if valid, stepped (its first 10,000
//! pulses): in strictly increasing time, or to a clean fault.
#![no_main]

use libfuzzer_sys::fuzz_target;
use polar_cell_msgs::{
    cdr, DiagnosticArray, GcodeAck, GcodeMove, GcodeProgress, JointState, JointTrajectory, Log,
    PoseStamped, ScrewCommand, StepSegment, StringMsg,
};

fuzz_target!(|bytes: &[u8]| {
    drop(cdr::decode::<GcodeMove>(bytes));
    drop(cdr::decode::<GcodeAck>(bytes));
    drop(cdr::decode::<GcodeProgress>(bytes));
    drop(cdr::decode::<JointTrajectory>(bytes));
    drop(cdr::decode::<JointState>(bytes));
    if let Ok(segment) = cdr::decode::<StepSegment>(bytes) {
        if let Ok(compiled) = segment.compile() {
            let mut train = step_core::PulseTrain::new(&compiled);
            let mut last_q32 = 0;
            for _ in 0..10_000 {
                match train.next_pulse() {
                    Ok(Some(pulse)) => {
                        assert!(pulse.time_q32 > last_q32, "time went back: {compiled:?}");
                        last_q32 = pulse.time_q32;
                    }
                    Ok(None) | Err(_) => break,
                }
            }
        }
    }
    drop(cdr::decode::<ScrewCommand>(bytes));
    drop(cdr::decode::<PoseStamped>(bytes));
    drop(cdr::decode::<DiagnosticArray>(bytes));
    drop(cdr::decode::<Log>(bytes));
    drop(cdr::decode::<StringMsg>(bytes));
});
