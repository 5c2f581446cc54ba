//! Any text as each of the mechanism's and the printer's text inputs: a CL file (and its
//! post-processing), a measurement CSV, and a URDF for the machining head and for the printer.
//! Each is read or refused with an error naming a line of the input.
#![no_main]

use libfuzzer_sys::fuzz_target;
use mechanism_kin::calib::measurements;
use mechanism_kin::cl::{self, PostOptions};

fuzz_target!(|bytes: &[u8]| {
    let text = String::from_utf8_lossy(bytes);
    let lines = text.lines().count().max(1);
    let opts = PostOptions::default();
    match cl::parse("fuzz.cl", &text, &opts) {
        Ok(points) => {
            let geometry = mechanism_kin::Geometry::default();
            if let Ok(commands) = cl::post_process("fuzz.cl", &geometry, &points, &opts) {
                for c in &commands {
                    let s = &c.solution;
                    assert!(
                        s.ik.legs_mm
                            .iter()
                            .chain(&s.table_mm)
                            .all(|v| v.is_finite()),
                        "{c:?}"
                    );
                }
            }
        }
        Err(e) => {
            let shown = e.to_string();
            assert!(shown.starts_with("fuzz.cl:"), "{shown}");
            let line: usize = shown["fuzz.cl:".len()..]
                .split(':')
                .next()
                .and_then(|n| n.parse().ok())
                .unwrap_or(0);
            assert!((1..=lines).contains(&line), "{shown}");
        }
    }
    drop(measurements::parse("fuzz.csv", &text));
    drop(mechanism_kin::urdf::load(&text));
    drop(polar_planner::urdf::joint_limits(&text));
});
