//! Any bytes as a CDR sample of each message type the nodes subscribe to: decoded or an
//! error, never a panic or an allocation the input's length cannot back.
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
    drop(cdr::decode::<StepSegment>(bytes));
    drop(cdr::decode::<ScrewCommand>(bytes));
    drop(cdr::decode::<PoseStamped>(bytes));
    drop(cdr::decode::<DiagnosticArray>(bytes));
    drop(cdr::decode::<Log>(bytes));
    drop(cdr::decode::<StringMsg>(bytes));
});
