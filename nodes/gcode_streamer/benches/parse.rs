//! Parse + interpret throughput on real slicer output, ours and the `gcode` crate (0.6) side
//! by side on the same bytes: both fixtures (Simplify3D output from the polar printer), repeated
//! to ~6 MB.
//!
//! The `gcode` crate only parses, so its side gets the interpretation the cell needs too:
//! absolute/relative X Y Z E and F tracked per G0/G1, one move produced per motion command.

use criterion::{black_box, criterion_group, criterion_main, Criterion, Throughput};
use gcode_streamer::{GcodeReader, Interpreter, InterpreterOptions, LineOutput};

fn slicer_output() -> Vec<u8> {
    let dir = concat!(
        env!("CARGO_MANIFEST_DIR"),
        "/../../../shared/fixtures/gcode/"
    );
    let mut one = std::fs::read(format!("{dir}finger.gcode")).expect("fixture");
    one.extend(std::fs::read(format!("{dir}polartest.gcode")).expect("fixture"));
    let mut all = Vec::new();
    while all.len() < 6 << 20 {
        all.extend_from_slice(&one);
    }
    all
}

/// Minimal interpretation over the `gcode` crate: what our interpreter does for G0/G1/G90/G91/
/// M82/M83/G92/G28, producing the same count of moves (asserted before measuring).
fn gcode_crate_interpret(text: &str) -> (usize, f64) {
    let mut pos = [0.0f64; 4];
    let mut relative = false;
    let mut relative_e = false;
    let mut feed = 1500.0f64;
    let mut moves = 0usize;
    for code in gcode::parse(text) {
        match (code.mnemonic(), code.major_number()) {
            // gcode 0.6 repeats the previous command without arguments after many lines (an
            // extra `G1`, `G92`); the fixtures have no bare G0/G1/G92, so skip those.
            (gcode::Mnemonic::General, 0 | 1 | 92) if code.arguments().is_empty() => {}
            (gcode::Mnemonic::General, 0 | 1) => {
                for (i, letter) in ['X', 'Y', 'Z', 'E'].iter().enumerate() {
                    if let Some(v) = code.value_for(*letter) {
                        let rel = if i == 3 { relative_e } else { relative };
                        pos[i] = if rel { pos[i] + v as f64 } else { v as f64 };
                    }
                }
                if let Some(f) = code.value_for('F') {
                    feed = f as f64;
                }
                moves += 1;
            }
            (gcode::Mnemonic::General, 90) => (relative, relative_e) = (false, false),
            (gcode::Mnemonic::General, 91) => (relative, relative_e) = (true, true),
            (gcode::Mnemonic::Miscellaneous, 82) => relative_e = false,
            (gcode::Mnemonic::Miscellaneous, 83) => relative_e = true,
            (gcode::Mnemonic::General, 92 | 28) => moves += 1,
            _ => {}
        }
    }
    (moves, pos[0] + pos[3] + feed)
}

fn ours(bytes: &[u8]) -> usize {
    let mut moves = 0;
    for event in GcodeReader::new(bytes, "bench", InterpreterOptions::default()) {
        if let Ok(gcode_streamer::Event::Move(m)) = event {
            black_box(&m);
            moves += 1;
        }
    }
    moves
}

fn ours_lines(bytes: &[u8]) -> usize {
    let mut interp = Interpreter::new("bench", InterpreterOptions::default());
    let mut out = LineOutput::default();
    let mut moves = 0;
    for (i, line) in bytes.split(|&b| b == b'\n').enumerate() {
        if interp.feed_line(i as u32 + 1, line, &mut out).is_ok() {
            moves += out.moves.len();
            black_box(&out.moves);
        }
        out.moves.clear();
        out.warnings.clear();
    }
    moves
}

fn bench(c: &mut Criterion) {
    let bytes = slicer_output();
    let text = std::str::from_utf8(&bytes).expect("ASCII fixtures");
    let (theirs_moves, _) = gcode_crate_interpret(text);
    let our_moves = ours(&bytes);
    eprintln!(
        "input {} bytes; moves: ours {our_moves}, gcode 0.6 {theirs_moves}",
        bytes.len()
    );
    assert_eq!(our_moves, theirs_moves, "both sides must do the same job");
    let mut group = c.benchmark_group("parse_interpret");
    group.throughput(Throughput::Bytes(bytes.len() as u64));
    group.sample_size(20);
    group.bench_function("polar_cell_reader", |b| b.iter(|| ours(black_box(&bytes))));
    group.bench_function("polar_cell_interpreter", |b| {
        b.iter(|| ours_lines(black_box(&bytes)))
    });
    group.bench_function("gcode_0_6", |b| {
        b.iter(|| gcode_crate_interpret(black_box(text)))
    });
    group.finish();
}

criterion_group!(benches, bench);
criterion_main!(benches);
