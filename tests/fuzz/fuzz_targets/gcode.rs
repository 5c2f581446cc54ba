//! Any bytes as a G-code file: the reader yields moves, warnings or one error naming a line of
//! the input, and every move it yields is finite.
#![no_main]

use gcode_streamer::{parse_all, InterpreterOptions};
use libfuzzer_sys::fuzz_target;

fuzz_target!(|bytes: &[u8]| {
    let lines = bytes.split(|&b| b == b'\n').count() as u32;
    match parse_all(bytes, "fuzz.gcode", InterpreterOptions::default()) {
        Ok((moves, warnings)) => {
            for m in &moves {
                let values = [m.x_m, m.y_m, m.z_m, m.e_m, m.delta_e_m, m.feedrate_m_per_s];
                assert!(values.iter().all(|v| v.is_finite()), "{m:?}");
                assert!(m.dwell_s.is_finite() && m.dwell_s >= 0.0, "{m:?}");
            }
            assert!(warnings.iter().all(|w| w.line >= 1 && w.line <= lines));
        }
        Err(e) => assert!(e.line >= 1 && e.line <= lines, "{e}"),
    }
});
