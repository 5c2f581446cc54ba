//! The built-in demo part: what `polar-cell print` prints when it is given no file, so the
//! cell runs from a clone alone.
//!
//! Written for a polar machine: a spiral vase (one continuous extrusion rising 0.3 mm per
//! turn: the bed turns, the arm stays put, the motion polar printers are best at) and, on
//! top, a five-line star whose lines all pass through the bed's centre, where the polar
//! kinematics is singular (the planner's centre handling). About a minute of machine time.

use std::f64::consts::TAU;
use std::fmt::Write as _;

/// Name under which the demo appears in messages and bags.
pub const DEMO_NAME: &str = "demo-vase-and-star.gcode";

/// Filament-equivalent length per mm of path for a 0.4 mm line of 0.3 mm layers from
/// 1.75 mm filament (area ratio).
const E_PER_MM: f64 = 0.4 * 0.3 / (std::f64::consts::PI * 0.875 * 0.875);

/// The demo's G-code.
pub fn demo_gcode() -> String {
    let mut g = String::new();
    let mut e = 0.0;
    let mut at: (f64, f64);
    let mut extrude_to =
        |g: &mut String, x: f64, y: f64, z: f64, feed: f64, at: &mut (f64, f64)| {
            e += (x - at.0).hypot(y - at.1) * E_PER_MM;
            *at = (x, y);
            writeln!(g, "G1 X{x:.3} Y{y:.3} Z{z:.3} E{e:.5} F{feed:.0}").expect("a String");
        };
    g.push_str(
        "; polar-cell demo: a spiral vase and a star through the centre (written by polar-cell)\n\
         G21 ; millimetres\nG90 ; absolute\nM82 ; absolute E\nG28 ; home\nG92 E0\n",
    );
    // Spiral vase: radius 20 mm, 10 turns from z 0.3 mm, 72 points a turn.
    let (radius, turns, points) = (20.0, 10, 72);
    writeln!(g, "G0 X{radius:.3} Y0 Z0.300 F3000").expect("a String");
    at = (radius, 0.0);
    for i in 1..=turns * points {
        let a = TAU * i as f64 / points as f64;
        let z = 0.3 + 0.3 * i as f64 / points as f64;
        extrude_to(
            &mut g,
            radius * a.cos(),
            radius * a.sin(),
            z,
            1800.0,
            &mut at,
        );
    }
    // A star over the top: five lines across the bed, each through its centre.
    let top = 0.3 + 0.3 * turns as f64 + 0.3;
    writeln!(g, "G0 Z{top:.3} F600").expect("a String");
    for k in 0..5 {
        let a = TAU * k as f64 / 10.0;
        let (x, y) = (radius * a.cos(), radius * a.sin());
        writeln!(g, "G0 X{x:.3} Y{y:.3} F3000").expect("a String");
        at = (x, y);
        extrude_to(&mut g, -x, -y, top, 1200.0, &mut at);
    }
    g.push_str("G0 Z20 F600\nM84 ; motors off\n");
    g
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The demo parses without a warning, stays within the arm's reach and the bed, and its
    /// star lines pass through the centre.
    #[test]
    fn the_demo_is_a_clean_polar_part() {
        let text = demo_gcode();
        let mut reader = gcode_streamer::GcodeReader::new(
            std::io::Cursor::new(text.clone().into_bytes()),
            DEMO_NAME,
            gcode_streamer::InterpreterOptions::default(),
        );
        let mut moves = 0;
        for event in reader.by_ref() {
            match event.unwrap() {
                gcode_streamer::Event::Move(_) => moves += 1,
                gcode_streamer::Event::Warning(w) => panic!("{w}"),
            }
        }
        assert!(moves > 700, "{moves}");
        let star: Vec<&str> = text.lines().filter(|l| l.ends_with("F1200")).collect();
        assert_eq!(star.len(), 5);
        for line in text
            .lines()
            .filter(|l| l.starts_with("G1") || l.starts_with("G0 X"))
        {
            let word = |c: char| {
                line.split_whitespace()
                    .find_map(|w| w.strip_prefix(c).map(|v| v.parse::<f64>().unwrap()))
            };
            if let (Some(x), Some(y)) = (word('X'), word('Y')) {
                assert!(x.hypot(y) <= 20.0 + 1e-3, "{line}");
            }
        }
    }
}
