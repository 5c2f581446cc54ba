//! Any bytes as a bag: `read_bag` and its message iterator answer with contents or an error,
//! and each recorded message decodes as its type or fails to; `recover` salvages the bytes
//! into a bag that reads, with the count it reports.
#![no_main]

use cell_bag::{read_bag, recover, WriterOptions};
use libfuzzer_sys::fuzz_target;
use polar_cell_msgs::{cdr, GcodeMove, JointState, JointTrajectory, ScrewCommand};

fuzz_target!(
    init: {
        // The reader catches the `mcap` crate's panics on malformed records and answers with
        // BagError::Malformed (tested in cell_bag); libFuzzer's hook would count them as
        // crashes. Any other panic still aborts.
        let libfuzzer_hook = std::panic::take_hook();
        std::panic::set_hook(Box::new(move |info| {
            if !info.location().is_some_and(|l| l.file().contains("/mcap-")) {
                libfuzzer_hook(info);
            }
        }));
    },
    |bytes: &[u8]| {
    let mut out = std::io::Cursor::new(Vec::new());
    if let Ok(recovery) = recover(bytes, &mut out, &WriterOptions::default()) {
        let out = out.into_inner();
        let info = read_bag(&out).expect("a recovered bag reads").info;
        assert_eq!(info.message_count, recovery.messages);
    }
    let Ok(contents) = read_bag(bytes) else {
        return;
    };
    let Ok(messages) = contents.messages() else {
        return;
    };
    for message in messages.take(1000) {
        let Ok(m) = message else {
            continue;
        };
        match m.type_name.as_str() {
            "polar_cell_msgs/msg/GcodeMove" => drop(cdr::decode::<GcodeMove>(&m.data)),
            "polar_cell_msgs/msg/ScrewCommand" => drop(cdr::decode::<ScrewCommand>(&m.data)),
            "sensor_msgs/msg/JointState" => drop(cdr::decode::<JointState>(&m.data)),
            "trajectory_msgs/msg/JointTrajectory" => {
                drop(cdr::decode::<JointTrajectory>(&m.data))
            }
            _ => {}
        }
    }
    }
);
