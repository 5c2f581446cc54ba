//! Planning speed and plan quality on the real fixtures and on a generated print of a million
//! short moves (a spiral vase of 0.3–0.6 mm chords around and through the centre region):
//! moves/s on one core, planning time against print duration, largest path deviation, and the
//! largest fraction of any joint limit used.
//!
//! Inputs under 200,000 moves are timed as the best of 20 runs.
//!
//!     cargo run --release -p polar_planner --example plan_stats

use std::time::Instant;

use gcode_streamer::{parse_all, GcodeMove, InterpreterOptions};
use polar_planner::check::{limit_usage, path_deviation};
use polar_planner::{Planner, PlannerOptions};

/// Best of `repeats` timed runs of the whole plan (small inputs take milliseconds).
fn best_time(moves: &[GcodeMove], repeats: usize) -> f64 {
    (0..repeats)
        .map(|_| {
            let mut planner = Planner::new(PlannerOptions::default()).unwrap();
            let mut out = Vec::new();
            let start = Instant::now();
            for m in moves {
                planner.push(m, &mut out).unwrap();
                out.clear();
            }
            planner.flush(&mut out);
            start.elapsed().as_secs_f64()
        })
        .fold(f64::INFINITY, f64::min)
}

fn report(name: &str, moves: &[GcodeMove], check: bool) {
    let options = PlannerOptions::default();
    let mut planner = Planner::new(options.clone()).unwrap();
    let mut out = Vec::new();
    let mut kept = Vec::new();
    let mut points = 0usize;
    let start = Instant::now();
    for m in moves {
        planner.push(m, &mut out).unwrap();
        points += out.iter().map(|p| p.points.len()).sum::<usize>();
        if check {
            kept.append(&mut out);
        } else {
            out.clear();
        }
    }
    planner.flush(&mut out);
    let elapsed = if moves.len() < 200_000 {
        best_time(moves, 20)
    } else {
        start.elapsed().as_secs_f64()
    };
    points += out.iter().map(|p| p.points.len()).sum::<usize>();
    kept.append(&mut out);
    let print_s = planner.time_emitted();
    print!(
        "{name}: {} moves, {points} points planned in {:.4} s = {:.0} moves/s ({:.2} µs/move); print {:.1} s; planning/print = {:.2e}",
        moves.len(),
        elapsed,
        moves.len() as f64 / elapsed,
        elapsed / moves.len() as f64 * 1e6,
        print_s,
        elapsed / print_s
    );
    if check {
        let path = path_deviation(moves, &kept, [0.0; 3], 20);
        let limits = limit_usage(moves, &kept, &options);
        print!(
            "; max deviation {:.3} µm; worst limit usage {:.4}",
            path.max_deviation_m * 1e6,
            limits.worst()
        );
    }
    println!();
}

fn spiral(count: u64) -> Vec<GcodeMove> {
    let mut moves = Vec::with_capacity(count as usize);
    let mut e = 0.0;
    for i in 0..count {
        // Radius breathing between 3 and 60 mm, 0.3-0.6 mm chords, slowly rising z.
        let a = i as f64 * 0.02;
        let r = 0.0315 + 0.0285 * (i as f64 * 1e-4).sin();
        e += 2e-5;
        moves.push(GcodeMove {
            sequence: i,
            source_line: i as u32 + 1,
            kind: GcodeMove::KIND_LINEAR,
            segment_count: 1,
            x_m: r * a.cos(),
            y_m: r * a.sin(),
            z_m: 0.0002 + i as f64 * 2e-7,
            e_m: e,
            delta_e_m: 2e-5,
            feedrate_m_per_s: 0.05,
            extrude: true,
            ..Default::default()
        });
    }
    moves
}

fn main() {
    for name in ["finger.gcode", "polartest.gcode"] {
        let path = format!(
            "{}/../../../shared/fixtures/gcode/{name}",
            env!("CARGO_MANIFEST_DIR")
        );
        let moves = parse_all(
            &std::fs::read(&path).unwrap(),
            name,
            InterpreterOptions::default(),
        )
        .unwrap()
        .0;
        report(name, &moves, true);
    }
    report("spiral 100k (checked)", &spiral(100_000), true);
    report("spiral 1M", &spiral(1_000_000), false);
}
