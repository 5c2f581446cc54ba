//! The parser against hand-computed values, the real fixtures, and arbitrary bytes.

use gcode_streamer::{parse_all, ErrorKind, GcodeMove, InterpreterOptions};
use proptest::prelude::*;

fn parse(src: &str) -> Vec<GcodeMove> {
    let (moves, warnings) = parse_all(src.as_bytes(), "t.gcode", InterpreterOptions::default())
        .unwrap_or_else(|e| panic!("{e}"));
    assert!(warnings.is_empty(), "{warnings:?}");
    moves
}

fn close(a: f64, b: f64, tol: f64) -> bool {
    (a - b).abs() <= tol
}

fn fixture(name: &str) -> Vec<u8> {
    let path = format!(
        "{}/../../../shared/fixtures/gcode/{name}",
        env!("CARGO_MANIFEST_DIR")
    );
    std::fs::read(&path).unwrap_or_else(|e| panic!("{path}: {e}"))
}

#[test]
fn units_modes_and_feedrate_in_si() {
    let m = parse("G21 G90\nG1 X10 Y-20 Z0.3 E1.5 F1200\nG91\nG1 X1 E.5\nG20\nG1 Y1 F60\n");
    assert_eq!(m.len(), 3);
    assert_eq!((m[0].x_m, m[0].y_m, m[0].z_m), (0.010, -0.020, 0.0003));
    assert_eq!(m[0].feedrate_m_per_s, 1200.0 / 60_000.0);
    assert!(close(m[0].e_m, 0.0015, 1e-15) && m[0].extrude);
    // G91 makes E relative too (Marlin).
    assert!(close(m[1].x_m, 0.011, 1e-15));
    assert!(close(m[1].e_m, 0.002, 1e-15));
    assert!(close(m[1].delta_e_m, 0.0005, 1e-15));
    // One inch in Y, F60 inch/min = 25.4 mm/s.
    assert!(close(m[2].y_m, -0.020 + 0.0254, 1e-15));
    assert!(close(m[2].feedrate_m_per_s, 0.0254, 1e-15));
    assert_eq!(m.iter().map(|m| m.sequence).collect::<Vec<_>>(), [0, 1, 2]);
    assert_eq!(
        m.iter().map(|m| m.source_line).collect::<Vec<_>>(),
        [2, 4, 6]
    );
}

#[test]
fn m82_m83_retraction_and_g92() {
    let m = parse("M83\nG1 X1 E2\nG1 E-1\nM82\nG92 E10\nG1 X2 E10.5\nG92\nG1 X1\n");
    assert_eq!(m[1].kind, GcodeMove::KIND_LINEAR);
    assert!(close(m[1].delta_e_m, -0.001, 1e-15) && !m[1].extrude);
    assert_eq!(m[2].kind, GcodeMove::KIND_SET_POSITION);
    assert_eq!(m[2].axes, GcodeMove::AXIS_E);
    assert!(close(m[2].e_m, 0.010, 1e-15));
    assert!(close(m[3].delta_e_m, 0.0005, 1e-15));
    // G92 with no words zeroes every axis: X1 afterwards is 1 mm beyond the machine's 2 mm.
    assert_eq!(m[4].axes, 15);
    assert!(close(m[5].x_m, 0.003, 1e-15));
}

#[test]
fn home_dwell_and_tool() {
    let m = parse("G1 X5 Y5 Z5\nG92 X0\nG28 X\nG4 P250\nG4 S2\nT1\nG1 X1\n");
    assert_eq!(m[2].kind, GcodeMove::KIND_HOME);
    // Polar practice: `G28 X` homes the whole XY mechanism (bed angle and arm), Z stays.
    assert_eq!(m[2].axes, GcodeMove::AXIS_X | GcodeMove::AXIS_Y);
    assert_eq!((m[2].x_m, m[2].y_m, m[2].z_m), (0.0, 0.0, 0.005));
    assert_eq!(m[3].kind, GcodeMove::KIND_DWELL);
    assert_eq!(m[3].dwell_s, 0.25);
    assert_eq!(m[4].dwell_s, 2.0);
    assert_eq!(m[5].tool, 1);
    // Homing cleared the X offset of G92 X0.
    assert!(close(m[5].x_m, 0.001, 1e-15));
}

/// A print started where another stopped: axes the first moves leave out stay where the
/// tool stands, relative moves count from there, and G28 still goes home.
#[test]
fn a_start_position_is_where_moves_begin() {
    let options = InterpreterOptions {
        start_position_mm: [30.0, -20.0, 2.0],
        ..InterpreterOptions::default()
    };
    let src = "G1 Z0.3 F600\nG91\nG1 X5\nG90\nG28\n";
    let (m, _) = parse_all(src.as_bytes(), "t.gcode", options).unwrap();
    let at = |k: usize, x: f64, y: f64, z: f64| {
        close(m[k].x_m, x, 1e-15) && close(m[k].y_m, y, 1e-15) && close(m[k].z_m, z, 1e-15)
    };
    assert!(at(0, 0.03, -0.02, 0.0003), "{:?}", m[0]);
    assert!(at(1, 0.035, -0.02, 0.0003), "{:?}", m[1]);
    assert!(at(2, 0.0, 0.0, 0.0), "{:?}", m[2]);
}

#[test]
fn homing_follows_polar_practice() {
    // Y alone homes X too; Z alone only Z; nothing named homes everything.
    let m = parse("G1 X5 Y6 Z7\nG28 Y\nG1 X5 Y6 Z7\nG28 Z\nG1 X5 Y6 Z7\nG28\n");
    assert_eq!(m[1].axes, GcodeMove::AXIS_X | GcodeMove::AXIS_Y);
    assert_eq!((m[1].x_m, m[1].y_m, m[1].z_m), (0.0, 0.0, 0.007));
    assert_eq!(m[3].axes, GcodeMove::AXIS_Z);
    assert_eq!((m[3].x_m, m[3].y_m, m[3].z_m), (0.005, 0.006, 0.0));
    assert_eq!(
        m[5].axes,
        GcodeMove::AXIS_X | GcodeMove::AXIS_Y | GcodeMove::AXIS_Z
    );
    assert_eq!((m[5].x_m, m[5].y_m, m[5].z_m), (0.0, 0.0, 0.0));
}

#[test]
fn ij_arc_chords_lie_on_the_circle_within_tolerance() {
    // Quarter circle of radius 10 around (10, 0), counter-clockwise from (0,0) to (10,10)... no:
    // from (0,0) CCW around (10,0) goes downwards; G2 (CW) goes up to (10,10).
    let m = parse("G1 X0 Y0\nG2 X10 Y10 I10 J0 E1\n");
    let chords = &m[1..];
    let n = chords.len();
    // Chord count from the sagitta bound: ceil((pi/2) / (2 acos(1 - 0.002/10))).
    let expected = ((std::f64::consts::FRAC_PI_2) / (2.0 * (1.0 - 0.002f64 / 10.0).acos())).ceil();
    assert_eq!(n, expected as usize);
    for (i, c) in chords.iter().enumerate() {
        assert_eq!(c.kind, GcodeMove::KIND_ARC_CW);
        assert_eq!((c.segment_index, c.segment_count), (i as u32, n as u32));
        let r = (c.x_m - 0.010).hypot(c.y_m);
        assert!(close(r, 0.010, 1e-12), "chord end off the circle: {r}");
        assert!(
            c.y_m >= -1e-15,
            "clockwise from (0,0) about (10,0) goes through y > 0"
        );
    }
    let last = chords.last().unwrap();
    assert_eq!((last.x_m, last.y_m), (0.010, 0.010));
    let e_sum: f64 = chords.iter().map(|c| c.delta_e_m).sum();
    assert!(close(e_sum, 0.001, 1e-15));
}

#[test]
fn r_arcs_pick_short_and_long_sides() {
    // From (0,0) to (10,0) with R5: a half circle; G3 (CCW) short arc centre (5,0) -> passes y<0.
    let m = parse("G3 X10 Y0 R5\n");
    assert!(m
        .iter()
        .all(|c| (c.x_m - 0.005).hypot(c.y_m) - 0.005 < 1e-12));
    assert!(m.iter().any(|c| c.y_m < -0.004));
    // R10 from (0,0) to (10,0): centre at (5, ±8.660); CW short arc bulges to +y.
    let m = parse("G2 X10 Y0 R10\n");
    let cy = -(100.0f64 - 25.0).sqrt() / 1000.0;
    assert!(m
        .iter()
        .all(|c| ((c.x_m - 0.005).hypot(c.y_m - cy) - 0.010).abs() < 1e-12));
    assert!(m.iter().any(|c| c.y_m > 0.001));
    // Negative R: the long way round (300 degrees), about the other centre, over the top.
    let m = parse("G2 X10 Y0 R-10\n");
    assert!(m
        .iter()
        .all(|c| ((c.x_m - 0.005).hypot(c.y_m + cy) - 0.010).abs() < 1e-12));
    assert!(m.iter().any(|c| c.y_m > 0.018));
}

#[test]
fn full_circle_with_ij() {
    let m = parse("G1 X10 Y0\nG3 X10 Y0 I-10 J0\n");
    let chords = &m[1..];
    assert!(chords.len() > 100);
    assert!(chords.iter().any(|c| c.x_m < -0.0099));
    let last = chords.last().unwrap();
    assert_eq!((last.x_m, last.y_m), (0.010, 0.0));
}

/// A circle that starts where atan2 answers -π (a start Y of -0.000 straight left of the
/// centre) or a hair off the start (G91 sums that do not cancel in binary) is still one whole
/// turn, clockwise or not: not lost to a zero sweep, not doubled to two turns.
#[test]
fn full_circles_are_one_turn_wherever_atan2_puts_the_start() {
    let path_length_m = |chords: &[GcodeMove], from: (f64, f64)| {
        let mut at = from;
        let mut length = 0.0;
        for c in chords {
            length += (c.x_m - at.0).hypot(c.y_m - at.1);
            at = (c.x_m, c.y_m);
        }
        length
    };
    let circumference_m = std::f64::consts::TAU * 0.010;
    for (src, turn_at_x_m) in [
        ("G1 X0 Y-0.000\nG2 X0 Y0 I10 J0\n", 0.020),
        ("G1 X0 Y-0.000\nG3 X0 Y0 I10 J0\n", 0.020),
        (
            "G91\nG1 X0.1\nG1 X0.2\nG1 X-0.3\nG90\nG2 X0 Y0 I10 J0\n",
            0.020,
        ),
        ("G1 X20 Y-0.000\nG3 X20 Y0 I-10 J0\n", 0.0),
    ] {
        let m = parse(src);
        let first_chord = m.iter().position(|c| c.segment_count > 1).unwrap();
        let start = &m[first_chord - 1];
        let chords = &m[first_chord..];
        let length = path_length_m(chords, (start.x_m, start.y_m));
        assert!(
            close(length, circumference_m, 2e-5),
            "{src:?}: {length} m of arc, a turn is {circumference_m} m"
        );
        assert!(
            chords.iter().any(|c| close(c.x_m, turn_at_x_m, 1e-5)),
            "{src:?} never reaches the far side"
        );
    }
}

fn error_of(src: &str) -> gcode_streamer::GcodeError {
    parse_all(src.as_bytes(), "bad.gcode", InterpreterOptions::default()).unwrap_err()
}

#[test]
fn errors_name_file_line_column_and_expectation() {
    let e = error_of("G1 X1\nG1 X2 Y\n");
    assert_eq!((e.line, e.column), (2, 8));
    assert_eq!(e.kind, ErrorKind::ExpectedNumberAfter('Y'));
    assert_eq!(e.to_string(), "bad.gcode:2:8: expected a number after `Y`");
    let e = error_of("G1 X1 X2\n");
    assert_eq!(
        (e.line, e.column, e.kind),
        (1, 7, ErrorKind::DuplicateWord { letter: 'X' })
    );
    let e = error_of("G2 X1 Y1\n");
    assert!(matches!(e.kind, ErrorKind::InvalidArc(_)), "{e}");
    let e = error_of("G2 X10 Y0 R2\n");
    assert!(e.to_string().contains("smaller than half the chord"), "{e}");
    let e = error_of("G1 F0\n");
    assert!(e.to_string().contains("feedrate must be > 0"), "{e}");
    let e = error_of("G18\nG2 X1 I1\n");
    assert!(e.to_string().contains("XY plane"), "{e}");
    let e = error_of(&format!("{}\n", "G1 X1 ".repeat(20_000)));
    assert_eq!(e.kind, ErrorKind::LineTooLong { limit: 65536 });
}

/// `N` line numbers are checked as a firmware checks a host's stream: each numbered line
/// follows the last by one (unnumbered lines between are not counted), so a line lost
/// between two numbered ones — each with a good checksum — is an error naming where;
/// `M110 N…` sets the number the next one follows.
#[test]
fn numbered_lines_follow_each_other_and_m110_sets_the_number() {
    fn checked(line: &str) -> String {
        let sum = line.bytes().fold(0u8, |a, b| a ^ b);
        format!("{line}*{sum}\n")
    }
    let ok = [checked("N1 G1 X1"), "G1 X2\n".into(), checked("N2 G1 X3")].concat();
    assert_eq!(parse(&ok).len(), 3);
    let lost = [checked("N1 G1 X1"), checked("N3 G1 X2")].concat();
    let e = error_of(&lost);
    assert_eq!(
        (e.line, e.column, e.kind.clone()),
        (
            2,
            1,
            ErrorKind::LineNumberOutOfOrder {
                expected: 2,
                found: 3
            }
        )
    );
    assert_eq!(
        e.to_string(),
        "bad.gcode:2:1: line number N3 out of order: expected N2"
    );
    let repeated = [checked("N5 G1 X1"), checked("N5 G1 X2")].concat();
    assert!(matches!(
        error_of(&repeated).kind,
        ErrorKind::LineNumberOutOfOrder {
            expected: 6,
            found: 5
        }
    ));
    // A host's reset of the numbering, and the line's own number as well.
    let reset = [
        checked("N7 G1 X1"),
        "M110 N0\n".into(),
        checked("N1 G1 X2"),
        checked("N40 M110"),
        checked("N41 G1 X3"),
    ]
    .concat();
    assert_eq!(parse(&reset).len(), 3);
}

#[test]
fn unknown_commands_warn_with_their_line() {
    let (moves, warnings) = parse_all(
        b"G1 X1\nM999\nG77 X1\nMaterial cost: 4.75\nM104 S200\n",
        "w.gcode",
        InterpreterOptions::default(),
    )
    .unwrap();
    assert_eq!(moves.len(), 1);
    let lines: Vec<u32> = warnings.iter().map(|w| w.line).collect();
    assert_eq!(lines, [2, 3, 4]);
    assert!(warnings[0].message.contains("M999"));
}

/// Lines real slicers write (Cura's Creality end code, PrusaSlicer's machine limits, object
/// labels and printer checks) load: flags of skipped commands, `T` as an M code's parameter.
#[test]
fn slicer_preambles_and_end_codes_load() {
    let src = "\u{feff}M862.3 P \"MK3S\" ; printer model check\n\
               M115 U3.13.2\n\
               M204 P1250 R1250 T1250\n\
               M104 S200 T0\n\
               G28 X Y\n\
               M486 S0\n\
               M486 AShape-Box\n\
               M221 T0 S95\n\
               G1 X10 E1 F600\n\
               M486 T3\n\
               M84 X Y E ;Disable all steppers but Z\n";
    let (m, warnings) = parse_all(
        src.as_bytes(),
        "slicer.gcode",
        InterpreterOptions::default(),
    )
    .unwrap();
    // Only the model check is unknown (warned); nothing else changed the tool.
    assert_eq!(warnings.len(), 1, "{warnings:?}");
    assert!(warnings[0].message.contains("M862.3"), "{warnings:?}");
    assert_eq!(warnings[0].line, 1);
    assert_eq!(m.len(), 2);
    assert_eq!(m[0].kind, GcodeMove::KIND_HOME);
    assert_eq!(m[0].axes, GcodeMove::AXIS_X | GcodeMove::AXIS_Y);
    assert_eq!(m[1].tool, 0);
    // M221 T0 S95 scaled the current tool's flow.
    assert!(close(m[1].delta_e_m, 0.00095, 1e-15), "{:?}", m[1]);
    // A factor for another tool is not applied, and said.
    let (m, warnings) = parse_all(
        b"M221 T1 S50\nG1 X10 E1 F600\n",
        "t.gcode",
        InterpreterOptions::default(),
    )
    .unwrap();
    assert!(close(m[0].delta_e_m, 0.001, 1e-15), "{:?}", m[0]);
    assert!(warnings[0].message.contains("tool 1"), "{warnings:?}");
    // A byte-order mark is only skipped where a file starts.
    let e = error_of("G1 X1\n\u{feff}G1 X2\n");
    assert_eq!((e.line, e.column), (2, 1));
    // An acted-on command still refuses a flag.
    let e = error_of("G28 X Y\nG1 X Y\n");
    assert_eq!((e.line, e.kind), (2, ErrorKind::ExpectedNumberAfter('X')));
}

/// Independent truth: motion command counts from `grep` over the fixtures
/// (`grep -cE '^G[01]( |$)'`, `grep -c '^G28'`, `grep -c '^G92'`).
#[test]
fn real_fixtures_parse_with_exact_motion_counts() {
    for (name, g0g1, g28, g92, extruding_g1, last_line) in [
        ("finger.gcode", 1761, 2, 15, 1753, 2000),
        ("polartest.gcode", 1728, 2, 36, 1677, 2000),
    ] {
        let bytes = fixture(name);
        let (moves, warnings) = parse_all(&bytes, name, InterpreterOptions::default())
            .unwrap_or_else(|e| panic!("{e}"));
        let count = |k: &[u8]| moves.iter().filter(|m| k.contains(&m.kind)).count();
        assert_eq!(
            count(&[GcodeMove::KIND_RAPID, GcodeMove::KIND_LINEAR]),
            g0g1,
            "{name}"
        );
        assert_eq!(count(&[GcodeMove::KIND_HOME]), g28, "{name}");
        assert_eq!(count(&[GcodeMove::KIND_SET_POSITION]), g92, "{name}");
        assert_eq!(moves.len(), g0g1 + g28 + g92, "{name}");
        // Every G1 that names E feeds material except the retraction/prime G1s without X/Y.
        let feeding = moves.iter().filter(|m| m.extrude).count();
        assert!(feeding <= extruding_g1 + 4, "{name}: {feeding}");
        assert!(feeding > extruding_g1 - 20, "{name}: {feeding}");
        assert!(moves.iter().all(|m| m.source_line <= last_line));
        // The only non-G-code line (finger's last, "   Material cost: 4.75") is a warning.
        assert!(warnings.len() <= 1, "{name}: {warnings:?}");
    }
}

#[test]
fn fixture_spot_values() {
    let bytes = fixture("finger.gcode");
    let (moves, _) = parse_all(&bytes, "finger", InterpreterOptions::default()).unwrap();
    // Line 192: "G0 Z.3 X95 F2000" after two G28 and a G92 Y0.
    let m = moves.iter().find(|m| m.source_line == 192).unwrap();
    assert_eq!(m.kind, GcodeMove::KIND_RAPID);
    assert_eq!((m.x_m, m.y_m, m.z_m), (0.095, 0.0, 0.0003));
    assert!(close(m.feedrate_m_per_s, 2000.0 / 60_000.0, 1e-15));
    // Line 199: "G0 E0" after "G92 E-25": a 25 mm prime.
    let m = moves.iter().find(|m| m.source_line == 199).unwrap();
    assert!(close(m.delta_e_m, 0.025, 1e-15) && m.extrude);
}

proptest! {
    #![proptest_config(ProptestConfig::with_cases(2000))]

    /// Any bytes: an error or moves, never a panic, and every reported place is inside the input.
    #[test]
    fn arbitrary_bytes_never_panic(bytes in proptest::collection::vec(any::<u8>(), 0..400)) {
        let lines = bytes.split(|&b| b == b'\n').count() as u32;
        match parse_all(&bytes, "fuzz", InterpreterOptions::default()) {
            Ok((moves, warnings)) => {
                prop_assert!(moves.iter().all(|m| m.x_m.is_finite() && m.y_m.is_finite()));
                prop_assert!(warnings.iter().all(|w| w.line <= lines));
            }
            Err(e) => prop_assert!(e.line >= 1 && e.line <= lines),
        }
    }

    /// G-code-shaped noise reaches the interpreter's deeper paths (arcs, modes, checksums).
    #[test]
    fn gcode_shaped_noise_never_panics(
        words in proptest::collection::vec(
            (prop::sample::select(&b"GMTXYZEFIJRPSN*;( )\n."[..]),
             prop::sample::select(&["0", "1", "2", "3", "4", "17", "18", "20", "28", "82", "91",
                 "92", "-1", ".5", "1e9", "999999999999999", "-0", "100000"][..])),
            0..60)
    ) {
        let mut src = Vec::new();
        for (letter, number) in words {
            src.push(letter);
            src.extend_from_slice(number.as_bytes());
            src.push(b' ');
        }
        let _ = parse_all(&src, "fuzz", InterpreterOptions::default());
    }

    /// Numbers round-trip exactly through the lexer for any value a slicer can print.
    #[test]
    fn printed_numbers_parse_exactly(v in -1.0e6f64..1.0e6, decimals in 0usize..7) {
        let text = format!("G1 X{v:.decimals$}\n");
        let expected: f64 = format!("{v:.decimals$}").parse().unwrap();
        let (moves, _) = parse_all(text.as_bytes(), "n", InterpreterOptions::default()).unwrap();
        prop_assert_eq!(moves[0].x_m, expected / 1000.0);
    }
}
