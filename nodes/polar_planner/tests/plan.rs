//! The planner on real and synthetic G-code, judged by the independent checks in `check`.

use gcode_streamer::{parse_all, GcodeMove, InterpreterOptions};
use polar_planner::check::{limit_usage, path_deviation};
use polar_planner::steps::{decode, StepGenerator, StepOptions};
use polar_planner::{PlannedMove, Planner, PlannerOptions};

fn moves_of(src: &[u8]) -> Vec<GcodeMove> {
    parse_all(src, "test", InterpreterOptions::default())
        .unwrap()
        .0
}

fn fixture(name: &str) -> Vec<GcodeMove> {
    let path = format!(
        "{}/../../../shared/fixtures/gcode/{name}",
        env!("CARGO_MANIFEST_DIR")
    );
    moves_of(&std::fs::read(path).unwrap())
}

fn plan(moves: &[GcodeMove], options: PlannerOptions) -> Vec<PlannedMove> {
    let mut planner = Planner::new(options).unwrap();
    let mut out = Vec::new();
    for m in moves {
        planner.push(m, &mut out).unwrap();
    }
    planner.flush(&mut out);
    out
}

fn assert_plan_ok(name: &str, moves: &[GcodeMove], options: &PlannerOptions) -> Vec<PlannedMove> {
    let planned = plan(moves, options.clone());
    assert_eq!(planned.len(), moves.len(), "{name}: one plan per move");
    for (m, p) in moves.iter().zip(&planned) {
        assert_eq!(m.sequence, p.sequence, "{name}: in order");
        assert!(!p.points.is_empty());
    }
    let path = path_deviation(moves, &planned, [0.0; 3], 20);
    assert!(
        path.max_deviation_m <= options.path_tolerance_m,
        "{name}: {path:?}"
    );
    let limits = limit_usage(moves, &planned, options);
    assert!(limits.worst() <= 1.0 + 1e-9, "{name}: {limits:?}");
    assert_eq!(limits.out_of_range, 0);
    assert_eq!(limits.time_reversals, 0);
    eprintln!(
        "{name}: {} moves, {:.1} s, max deviation {:.3} µm, worst limit {:.3}",
        planned.len(),
        planned.last().unwrap().end_time(),
        path.max_deviation_m * 1e6,
        limits.worst()
    );
    planned
}

/// An arm that reaches 150 mm on both sides of the centre, crossing it with a negative r.
fn crossing_options() -> PlannerOptions {
    let mut options = PlannerOptions {
        allow_negative_r: true,
        ..PlannerOptions::default()
    };
    options.joints[1].position = Some((-0.15, 0.15));
    options
}

/// The shipped arm stops at the centre: crossing it is refused where the planner is made,
/// naming the joint and its limits, not found out on the first line through the centre.
#[test]
fn negative_radii_need_an_arm_that_reaches_past_the_centre() {
    let options = PlannerOptions {
        allow_negative_r: true,
        ..PlannerOptions::default()
    };
    let error = Planner::new(options).err().expect("refused").to_string();
    assert!(
        error.contains("arm_r") && error.contains("[0, 0.15]"),
        "{error}"
    );
    assert!(Planner::new(crossing_options()).is_ok());
}

#[test]
fn both_fixtures_plan_within_tolerance_and_limits() {
    for name in ["finger.gcode", "polartest.gcode"] {
        for options in [PlannerOptions::default(), crossing_options()] {
            assert_plan_ok(name, &fixture(name), &options);
        }
    }
}

#[test]
fn theta_stays_continuous_over_many_turns_both_ways() {
    // Ten turns counter-clockwise, then ten clockwise, on a 20 mm circle of short chords.
    let mut src = String::from("G1 X20 Y0 F6000\n");
    for dir in [1.0f64, -1.0] {
        for i in 1..=3600 {
            let a = dir * i as f64 * std::f64::consts::TAU / 360.0;
            src.push_str(&format!(
                "G1 X{:.4} Y{:.4}\n",
                20.0 * a.cos(),
                20.0 * a.sin()
            ));
        }
    }
    let moves = moves_of(src.as_bytes());
    let planned = assert_plan_ok("turns", &moves, &PlannerOptions::default());
    let thetas: Vec<f64> = planned
        .iter()
        .flat_map(|p| p.points.iter().map(|q| q.q[0]))
        .collect();
    let max_theta = thetas.iter().cloned().fold(f64::MIN, f64::max);
    let last = *thetas.last().unwrap();
    assert!(
        (max_theta - 10.0 * std::f64::consts::TAU).abs() < 1e-6,
        "{max_theta}"
    );
    assert!(last.abs() < 1e-6, "back to 0, not re-based: {last}");
    for w in thetas.windows(2) {
        assert!((w[1] - w[0]).abs() < 0.1, "jump {} -> {}", w[0], w[1]);
    }
}

#[test]
fn lines_through_the_centre_turn_or_cross() {
    let src = b"G1 X30 Y10 F3000\nG1 X-30 Y-10\nG1 X10 Y30\nG1 X-10 Y-30.0000001\n";
    let moves = moves_of(src);
    // Without negative radii: stop at the centre, turn by pi, go on.
    let planned = assert_plan_ok("through, turn", &moves, &PlannerOptions::default());
    let through = &planned[1];
    let at_centre: Vec<_> = through
        .points
        .iter()
        .filter(|p| p.q[1].abs() < 1e-12)
        .collect();
    assert!(at_centre.len() >= 2, "stops at the centre while turning");
    let turn = at_centre.last().unwrap().q[0] - at_centre.first().unwrap().q[0];
    assert!((turn.abs() - std::f64::consts::PI).abs() < 1e-9, "{turn}");
    assert!(at_centre
        .iter()
        .all(|p| p.qd[1] == 0.0 && p.tool_speed == 0.0));
    // With them: the arm crosses with theta held.
    let planned = assert_plan_ok("through, cross", &moves, &crossing_options());
    let thetas: Vec<f64> = planned[1].points.iter().map(|p| p.q[0]).collect();
    assert!(
        thetas.iter().all(|t| (t - thetas[0]).abs() < 1e-12),
        "theta held"
    );
    let radii: Vec<f64> = planned[1].points.iter().map(|p| p.q[1]).collect();
    assert!(radii.first().unwrap() > &0.0 && radii.last().unwrap() < &0.0);
}

#[test]
fn near_the_centre_the_bed_speed_limits_the_tool_smoothly() {
    // A line passing 0.1 mm from the centre: v <= omega_max * d there.
    let src = b"G1 X20 Y0.1 F6000\nG1 X-20 Y0.1\n";
    let moves = moves_of(src);
    let options = PlannerOptions::default();
    let planned = assert_plan_ok("near centre", &moves, &options);
    let omega = options.joints[0].velocity;
    let closest = planned[1]
        .points
        .iter()
        .min_by(|a, b| a.q[1].abs().total_cmp(&b.q[1].abs()))
        .unwrap();
    assert!(
        closest.tool_speed <= omega * 1e-4 * (1.0 + 1e-9),
        "{}",
        closest.tool_speed
    );
    assert!(
        closest.tool_speed > 0.5 * omega * 1e-4,
        "slows to the limit, not to a stop"
    );
}

#[test]
fn starfish_with_sharp_radial_spikes() {
    let mut src = String::from("G1 X5 Y0 F4000\n");
    for i in 0..=50 {
        let a = i as f64 * std::f64::consts::TAU / 50.0;
        let r = if i % 2 == 0 { 5.0 } else { 45.0 };
        src.push_str(&format!(
            "G1 X{:.4} Y{:.4} E{}\n",
            r * a.cos(),
            r * a.sin(),
            i
        ));
    }
    assert_plan_ok(
        "starfish",
        &moves_of(src.as_bytes()),
        &PlannerOptions::default(),
    );
}

#[test]
fn z_e_only_dwell_home_and_set_position() {
    let src = b"G1 X10 Y10 F3000\nG1 Z5 F600\nG1 E-1 F1800\nG4 P500\nG92 E0\nG28\n";
    let moves = moves_of(src);
    let planned = assert_plan_ok("misc", &moves, &PlannerOptions::default());
    let dur = |p: &PlannedMove| p.end_time() - p.start_time();
    assert!(
        (dur(&planned[2]) - 0.001 / 0.03).abs() < 1e-12,
        "E-only takes |dE|/F"
    );
    assert!((dur(&planned[3]) - 0.5).abs() < 1e-12);
    assert_eq!(dur(&planned[4]), 0.0);
    let home = planned[5].points.last().unwrap();
    assert!(home.q[1].abs() < 1e-12 && home.q[2].abs() < 1e-12);
}

#[test]
fn out_of_range_targets_are_errors() {
    let moves = moves_of(b"G1 X200 Y0 F3000\n");
    let mut planner = Planner::new(PlannerOptions::default()).unwrap();
    let err = planner.push(&moves[0], &mut Vec::new()).unwrap_err();
    assert!(
        err.to_string().contains("arm_r would reach 0.200000"),
        "{err}"
    );
    let bad = PlannerOptions {
        center_radius_m: 1e-3,
        ..PlannerOptions::default()
    };
    assert!(Planner::new(bad).is_err());
}

/// An arm that cannot reach the centre (lower limit 5 mm): a line whose ends are both in
/// reach but which passes the centre closer than that is refused, naming how near it comes;
/// one that stays out of that circle is planned.
#[test]
fn a_line_passing_closer_to_the_centre_than_the_arm_reaches_is_refused() {
    let mut options = PlannerOptions {
        initial_joints: [0.0, 0.02, 0.0],
        ..PlannerOptions::default()
    };
    options.joints[1].position = Some((0.005, 0.15));
    // From (20, 0) mm: to (-20, 3) passes 1.5 mm from the centre; to (0, 20) 14.1 mm.
    let moves = moves_of(b"G1 X-20 Y3 F3000\nG1 X0 Y20 F3000\n");
    let mut planner = Planner::new(options.clone()).unwrap();
    let err = planner.push(&moves[0], &mut Vec::new()).unwrap_err();
    assert!(
        err.to_string().contains("arm_r would reach 0.0014"),
        "{err}"
    );
    let mut planner = Planner::new(options).unwrap();
    let mut out = Vec::new();
    planner.push(&moves[1], &mut out).unwrap();
    planner.flush(&mut out);
    let nearest = out
        .iter()
        .flat_map(|m| &m.points)
        .map(|p| p.q[1])
        .fold(f64::INFINITY, f64::min);
    // 14.1 mm at the line's closest point, a node spacing's sagitta more at the nearest point.
    assert!((0.01414..0.0145).contains(&nearest), "{nearest}");
}

/// A start a rounding below r = 0 (within the slack a stop position from steps may have) is
/// the centre: the path after it keeps r ≥ 0 (it used to take the sign of that -5 µm and
/// drive the arm to -50 mm, past its stop, with negative radii not allowed).
#[test]
fn a_start_a_rounding_below_the_centre_plans_positive_radii() {
    let options = PlannerOptions {
        initial_joints: [0.0, -5e-6, 0.0],
        ..PlannerOptions::default()
    };
    let moves = moves_of(b"G1 X0 Y50 F1800\nG1 X30 Y40 F1800\n");
    let planned = plan(&moves, options.clone());
    let radii: Vec<f64> = planned
        .iter()
        .flat_map(|m| &m.points)
        .map(|p| p.q[1])
        .collect();
    assert!(radii.iter().all(|r| *r >= 0.0), "{radii:?}");
    let end = planned.last().unwrap().points.last().unwrap().q;
    assert!((end[1] - 0.05).abs() < 1e-12, "{end:?}");
    assert_eq!(limit_usage(&moves, &planned, &options).out_of_range, 0);
}

/// A slow move at a fast step clock (0.5 mm/s at 1 GHz: each 2 mm of its cruise is 4·10⁹
/// ticks, past the 2³¹ a machine can time in one segment) comes in segments a machine can
/// play; its steps still add up to the target and keep their pace across the cuts.
#[test]
fn a_slow_move_at_a_fast_step_clock_comes_in_playable_segments() {
    let moves = moves_of(b"G1 X50 F1800\nG1 X60 F30\n");
    let steps = StepOptions {
        timer_hz: 1e9,
        ..StepOptions::default()
    };
    let program = polar_planner::plan_program(&moves, PlannerOptions::default(), steps).unwrap();
    let mut t0 = 0.0;
    let mut arm_steps = 0i64;
    let mut crawl_pulses = Vec::new();
    for seg in &program.segments {
        assert!(seg.duration_s * 1e9 < (1u64 << 31) as f64, "{seg:?}");
        let mut pulses = Vec::new();
        decode(seg, &mut pulses).unwrap();
        for p in pulses.iter().filter(|p| p.axis == 1) {
            arm_steps += seg.directions[1] as i64;
            if seg.move_sequence == 1 {
                crawl_pulses.push(t0 + p.t);
            }
        }
        t0 += seg.duration_s;
    }
    assert_eq!(arm_steps, 4800, "60 mm at 80 steps/mm");
    let crawl_segments = program
        .segments
        .iter()
        .filter(|s| s.move_sequence == 1)
        .count();
    assert!(crawl_segments >= 20, "{crawl_segments} segments for 24 s");
    // 800 steps; the first 8 mm cruise at 25 ms a step (0.5 mm/s at 80 steps/mm), cuts or
    // not (the last 2 mm slow to rest).
    assert_eq!(crawl_pulses.len(), 800);
    let worst = crawl_pulses[..640]
        .windows(2)
        .map(|w| ((w[1] - w[0]) - 0.025).abs())
        .fold(0.0, f64::max);
    assert!(worst < 1e-6, "a step off the cruise's pace by {worst} s");
}

/// Found by fuzzing (tests/fuzz, target move_stream): a G28 whose X was NaN was planned into
/// NaN joint positions. A move from any publisher with a non-finite number is refused, and
/// the planner goes on planning the moves after it.
#[test]
fn non_finite_moves_are_errors_that_name_the_field() {
    let mut moves = moves_of(b"G28\nG1 X10 Y10 F3000\n");
    let good = moves.clone();
    moves[0].x_m = f64::NAN;
    let mut planner = Planner::new(PlannerOptions::default()).unwrap();
    let mut out = Vec::new();
    let err = planner.push(&moves[0], &mut out).unwrap_err();
    assert!(
        err.to_string().contains("x_m is NaN, not a finite number"),
        "{err}"
    );
    moves[1].feedrate_m_per_s = f64::INFINITY;
    let err = planner.push(&moves[1], &mut out).unwrap_err();
    assert!(err.to_string().contains("feedrate_m_per_s is inf"), "{err}");
    // and a feed so small that the move's duration would overflow (found the same way)
    moves[1].feedrate_m_per_s = 1.6e-316;
    let err = planner.push(&moves[1], &mut out).unwrap_err();
    assert!(err.to_string().contains("below the 1e-6 m/s"), "{err}");
    // an extruder-only move whose rest overflows, and a kind no streamer sends
    let mut prime = good[1].clone();
    (prime.x_m, prime.y_m, prime.delta_e_m) = (0.0, 0.0, -1.4e306);
    let err = planner.push(&prime, &mut out).unwrap_err();
    assert!(err.to_string().contains("longer than the 1e6 s"), "{err}");
    prime.kind = 7;
    let err = planner.push(&prime, &mut out).unwrap_err();
    assert!(err.to_string().contains("unknown move kind 7"), "{err}");
    for m in &good {
        planner.push(m, &mut out).unwrap();
    }
    planner.flush(&mut out);
    assert_eq!(out.len(), 2);
    assert!(out
        .iter()
        .flat_map(|p| &p.points)
        .all(|p| p.t.is_finite() && p.q.iter().all(|q| q.is_finite())));
}

#[test]
fn steps_land_exactly_on_the_final_position() {
    let moves = fixture("polartest.gcode");
    let options = PlannerOptions::default();
    let planned = plan(&moves, options.clone());
    let step_options = StepOptions::default();
    let mut generator = StepGenerator::new(step_options.clone(), options.initial_joints);
    let mut segments = Vec::new();
    for p in &planned {
        generator.segments(p, &mut segments);
    }
    // Regenerate every pulse and integrate the step positions.
    let mut position = [0i64; 3];
    let mut pulses = Vec::new();
    let mut total_time = 0.0;
    for seg in &segments {
        pulses.clear();
        decode(seg, &mut pulses).unwrap();
        for (k, &count) in seg.step_counts.iter().enumerate() {
            let made = pulses.iter().filter(|p| p.axis == k).count() as u32;
            assert_eq!(made, count, "segment ends on its counts");
            position[k] += seg.directions[k] as i64 * count as i64;
        }
        if let Some(last) = pulses.last() {
            assert!(
                last.t <= seg.duration_s * 1.005 + 1e-9,
                "{} > {}",
                last.t,
                seg.duration_s
            );
        }
        total_time += seg.duration_s;
    }
    let end = planned.last().unwrap().points.last().unwrap().q;
    for k in 0..3 {
        let expected = (end[k] * step_options.steps_per_unit[k]).round() as i64;
        assert_eq!(position[k], expected, "axis {k}");
    }
    assert_eq!(position, generator.position());
    let plan_time = planned.last().unwrap().end_time();
    assert!((total_time - plan_time).abs() < 1e-6 * plan_time);
}

/// The Leib recurrence and pulse distribution exactly as `StepSegment.msg` documents them, in
/// `f64`: the reference the fixed-point step core (used by the planner's decoder, the executor
/// and the firmware) must reproduce.
fn reference_pulses(seg: &polar_cell_msgs::StepSegment) -> Vec<(usize, f64)> {
    let n = seg.accelerate_steps + seg.cruise_steps + seg.decelerate_steps;
    let dominant = seg.dominant_axis as usize;
    let total = seg.step_counts[dominant] as u64;
    let mut done = [0u64; 3];
    let mut p = if seg.cruise_steps == n {
        seg.cruise_period_ticks
    } else {
        seg.first_period_ticks
    };
    let (mut ticks, mut out) = (0.0, Vec::new());
    for i in 1..=n as u64 {
        ticks += p;
        out.push((dominant, ticks));
        for k in (0..3).filter(|&k| k != dominant) {
            if seg.step_counts[k] as u64 * i >= total * (done[k] + 1) {
                done[k] += 1;
                out.push((k, ticks));
            }
        }
        let m = if i < seg.accelerate_steps as u64 {
            -seg.ramp_r
        } else if i < (seg.accelerate_steps + seg.cruise_steps) as u64 {
            0.0
        } else {
            seg.ramp_r
        };
        let mp2 = m * p * p;
        p *= 1.0 + mp2 + 1.5 * mp2 * mp2;
    }
    out
}

/// Every step edge of both fixtures, regenerated by the shared fixed-point core, lands on the
/// timer tick the floating-point recurrence gives (within one tick, rounding included), and
/// every segment makes exactly its step counts.
#[test]
fn the_fixed_point_core_steps_every_fixture_segment_within_a_tick_of_the_recurrence() {
    for name in ["polartest.gcode", "finger.gcode"] {
        let options = PlannerOptions::default();
        let planned = plan(&fixture(name), options.clone());
        let mut generator = StepGenerator::new(StepOptions::default(), options.initial_joints);
        let mut segments = Vec::new();
        for p in &planned {
            generator.segments(p, &mut segments);
        }
        let (mut edges, mut worst_ticks, mut worst_rounded) = (0usize, 0.0f64, 0.0f64);
        let mut pulses = Vec::new();
        for seg in &segments {
            pulses.clear();
            decode(seg, &mut pulses).unwrap();
            let reference = reference_pulses(seg);
            assert_eq!(
                pulses.len(),
                reference.len(),
                "{name}: line {}",
                seg.source_line
            );
            for (p, &(axis, ticks)) in pulses.iter().zip(&reference) {
                assert_eq!(p.axis, axis);
                let core_ticks = p.t * seg.timer_frequency_hz;
                worst_ticks = worst_ticks.max((core_ticks - ticks).abs());
                // What a timer fires at: the nearest whole tick.
                worst_rounded = worst_rounded.max((core_ticks.round() - ticks).abs());
            }
            for k in 0..3 {
                let made = pulses.iter().filter(|p| p.axis == k).count() as u32;
                assert_eq!(made, seg.step_counts[k], "{name}: line {}", seg.source_line);
            }
            edges += pulses.len();
        }
        eprintln!(
            "{name}: {} segments, {edges} step edges; worst |core − f64| {worst_ticks:.2e} ticks, \
             worst |fired tick − f64| {worst_rounded:.4} ticks",
            segments.len()
        );
        assert!(edges > 100_000, "{name}: {edges}");
        // The fixed-point arithmetic and the rounding of the first period and ramp term to the
        // wire's 26 significant bits (step_core::round_significant) together: 1.7e-3 ticks on
        // polartest and finger.
        assert!(worst_ticks < 5e-3, "{name}: {worst_ticks}");
        assert!(worst_rounded <= 0.5 + 1e-3, "{name}: {worst_rounded}");
    }
}

/// The screw's limit slows an extruding move to exactly the usable rpm, lengthens a prime to
/// what the screw can feed, and leaves moves within the limit alone.
#[test]
fn the_screw_limit_slows_moves_that_would_need_more_rpm() {
    use polar_planner::ScrewLimits;
    let screw = ScrewLimits {
        usable_rpm: 270.0,
        e_per_rev_m: 0.002,
        flow_tau_s: 0.03,
    };
    // 40 mm at 3000 mm/min feeding 8 mm: 60·0.05·0.2/0.002 = 300 rpm > 270 → slowed to 45 mm/s.
    // Then a 25 mm prime at 300 mm/min (5 s): the screw needs 60·0.025/(270·0.002) = 2.78 s
    // and 5τ = 0.15 s for the flow → not slowed; at 3000 mm/min (0.5 s) → 2.93 s. Then a slow
    // move, not slowed.
    let src = b"G1 X50 Y0 F3000\nG1 X90 E8 F3000\nG1 E33 F300\nG1 E58 F3000\nG1 X80 E59 F600\n";
    let moves = moves_of(src);
    let options = PlannerOptions {
        screw: Some(screw),
        ..PlannerOptions::default()
    };
    let planned = plan(&moves, options);
    let rpm_of = |k: usize| -> f64 {
        let m = &planned[k];
        let ratio = m.delta_e_m / m.length_m;
        m.points
            .iter()
            .map(|p| 60.0 * p.tool_speed * ratio / 0.002)
            .fold(0.0, f64::max)
    };
    assert!((rpm_of(1) - 270.0).abs() < 1e-6, "{}", rpm_of(1));
    assert!((planned[1].slowed_for_screw.unwrap() - 300.0 / 270.0).abs() < 1e-9);
    assert_eq!(planned[2].slowed_for_screw, None);
    let prime = planned[3].end_time() - planned[3].start_time();
    assert!(
        (prime - (60.0 * 0.025 / (270.0 * 0.002) + 0.15)).abs() < 1e-9,
        "{prime}"
    );
    assert!((planned[3].slowed_for_screw.unwrap() - prime / 0.5).abs() < 1e-9);
    assert_eq!(planned[4].slowed_for_screw, None);
    assert!(rpm_of(4) < 270.0);
    // Without the screw the first extruding move runs at its feed.
    let free = plan(&moves, PlannerOptions::default());
    assert!(
        free[1].end_time() - free[1].start_time() < planned[1].end_time() - planned[1].start_time()
    );
}

/// `ends_at_rest` marks exactly the segments that end where the plan's joint velocity is
/// zero (looked up by time in the plan, not by the generator's own bookkeeping), and the last
/// segment of a file.
#[test]
fn segments_ending_at_rest_are_marked_and_only_those() {
    for name in ["polartest.gcode", "finger.gcode"] {
        let program = polar_planner::plan_program(
            &fixture(name),
            PlannerOptions::default(),
            StepOptions::default(),
        )
        .unwrap();
        // Every plan point with its time: the velocity a segment arrives with is the first
        // point at its end time (a corner repeats the time with the next move's velocity).
        let points: Vec<_> = program
            .planned
            .iter()
            .flat_map(|p| p.points.iter())
            .collect();
        let mut t = points[0].t;
        let mut marked = 0;
        for seg in &program.segments {
            t += seg.duration_s;
            let i = points.partition_point(|p| p.t < t - 1e-9);
            let at = points[i.min(points.len() - 1)];
            let ends_on_point = (at.t - t).abs() < 1e-6;
            let resting = ends_on_point && at.qd.iter().all(|v| *v == 0.0);
            if seg.ends_at_rest {
                marked += 1;
                assert!(
                    resting,
                    "{name}: marked at {t} s but the plan moves: {:?}",
                    at.qd
                );
            } else {
                assert!(!resting, "{name}: at rest at {t} s but not marked");
            }
        }
        assert!(program.segments.last().unwrap().ends_at_rest, "{name}");
        eprintln!(
            "{name}: {marked} of {} segments end at rest",
            program.segments.len()
        );
    }
}

/// Plans `moves` as the node does (one push at a time) and returns, after each push that
/// emitted something, the sequence after the last move emitted so far: the points a node
/// acknowledges, and so where a restarted planner resumes.
fn plan_with_batches(
    moves: &[GcodeMove],
    options: &PlannerOptions,
) -> (Vec<PlannedMove>, Vec<usize>) {
    let mut planner = Planner::new(options.clone()).unwrap();
    let (mut out, mut batch_ends) = (Vec::new(), Vec::new());
    for m in moves {
        let before = out.len();
        planner.push(m, &mut out).unwrap();
        if out.len() > before {
            batch_ends.push(out.len());
        }
    }
    planner.flush(&mut out);
    (out, batch_ends)
}

/// A planner resumed where another acknowledged (after a batch it published) and fed the
/// moves after that plans them exactly as the other one did: same times, joints, rates and
/// resume points, bit for bit — the timeline a restarted planner node continues.
#[test]
fn a_resumed_planner_continues_the_same_plan_bit_for_bit() {
    let dwell = PlannerOptions {
        pin_open_dwell_s: 0.05,
        ..PlannerOptions::default()
    };
    // A spiral with a zero-time move after every line (a feed change, a G92), queued between
    // the lines of every batch.
    let mut spiral = String::from("G28\nG1 X20 Y0 Z0.2 F3000\n");
    for k in 0..600 {
        let a = k as f64 * 0.3;
        let r = 20.0 + k as f64 * 0.05;
        spiral += &format!(
            "G1 X{:.3} Y{:.3} E{:.4}\n",
            r * a.cos(),
            r * a.sin(),
            0.02 * k as f64
        );
        spiral += if k % 2 == 0 {
            "G1 F2400\n"
        } else {
            "G92 E0\nG1 F3000\n"
        };
    }
    let cases = [
        (
            "finger.gcode",
            fixture("finger.gcode"),
            PlannerOptions::default(),
        ),
        ("finger.gcode", fixture("finger.gcode"), dwell.clone()),
        ("polartest.gcode", fixture("polartest.gcode"), dwell),
        (
            "spiral",
            moves_of(spiral.as_bytes()),
            PlannerOptions::default(),
        ),
    ];
    for (name, moves, options) in cases {
        let mut moving = 0;
        let mut went_back = 0;
        let (whole, batch_ends) = plan_with_batches(&moves, &options);
        assert_eq!(whole.len(), moves.len());
        let mut checked = 0;
        for &batch_end in &batch_ends {
            // A node acknowledges through the last move published that takes time (a
            // consumer tells moves apart by their times; see polar_planner::node).
            let Some(done) = (1..=batch_end)
                .rev()
                .find(|&k| whole[k - 1].end_time() > whole[k - 1].start_time())
            else {
                continue;
            };
            went_back += usize::from(done < batch_end);
            let at = whole[done - 1].resume;
            moving += usize::from(at.path_speed2 > 0.0);
            assert_eq!(
                at.t_s,
                whole[done - 1].end_time(),
                "{name}: resume at the move's end"
            );
            let mut resumed = Planner::resume(options.clone(), &at).unwrap();
            let mut out = Vec::new();
            // Only the next 400 moves: far past any lookahead.
            let until = (done + 400).min(moves.len());
            for m in &moves[done..until] {
                resumed.push(m, &mut out).unwrap();
            }
            if until == moves.len() {
                resumed.flush(&mut out);
            }
            assert!(
                !out.is_empty() || until == done,
                "{name}: resumed after move {done}"
            );
            for (k, plan) in out.iter().enumerate() {
                assert_eq!(
                    plan,
                    &whole[done + k],
                    "{name}: resumed after {done} moves, move {} differs",
                    done + k
                );
            }
            checked += 1;
        }
        assert!(checked >= 10, "{name}: {checked} resume points checked");
        assert!(moving >= 5, "{name}: only {moving} resume points in motion");
        eprintln!("{name}: {checked} resume points ({moving} in motion, {went_back} before zero-time moves) continue bit for bit");
        if name == "polartest.gcode" {
            // Queues flushed to a stop before a G92 or feed change: the zero-time case.
            assert!(
                went_back >= 5,
                "{name}: the zero-time case ran {went_back} times"
            );
        }
    }
}

/// A resume point that is not a plan state is refused with the values, not planned from.
#[test]
fn a_resume_point_with_non_finite_values_is_refused() {
    let at = polar_planner::ResumePoint {
        path_speed2: f64::NAN,
        ..Default::default()
    };
    let e = Planner::resume(PlannerOptions::default(), &at)
        .err()
        .unwrap();
    assert!(e.to_string().contains("resume point"), "{e}");
}

/// The plan messages of `plans` as the node publishes them: each move's trajectory, then its
/// segments, stamped from `epoch_ns`.
fn published(
    plans: &[PlannedMove],
    steps: &mut StepGenerator,
    epoch_ns: i64,
) -> Vec<(
    polar_cell_msgs::JointTrajectory,
    Vec<polar_cell_msgs::StepSegment>,
)> {
    plans
        .iter()
        .map(|plan| {
            let mut segments = Vec::new();
            steps.segments(plan, &mut segments);
            for s in &mut segments {
                s.header.stamp = polar_cell_msgs::Time::after(epoch_ns, plan.start_time());
            }
            (
                polar_planner::messages::trajectory_message(plan, epoch_ns),
                segments,
            )
        })
        .collect()
}

/// A planner killed anywhere after its last acknowledgement — between two moves or inside
/// one's segments — and resumed at that acknowledgement from its checkpoint publishes again
/// what it had published since; the consumers' filters (`cell_runtime::replay`, keyed as the
/// machine, the screw driver and the recorder key them) drop exactly those repeats, and what
/// comes through is the uninterrupted plan, message for message.
#[test]
fn a_killed_and_resumed_planner_with_its_repeats_dropped_is_the_uninterrupted_plan() {
    use cell_runtime::replay::{Admit, Joined, ReplayFilter, StepsJoin};
    use polar_planner::resume::{options_digest, Checkpoint};
    let options = PlannerOptions::default();
    let step_options = StepOptions::default();
    let digest = options_digest(&options, &step_options);
    let epoch_ns = 1_790_000_000_000_000_000;
    let moves = fixture("polartest.gcode");
    let (whole, batch_ends) = plan_with_batches(&moves, &options);
    let reference = published(
        &whole,
        &mut StepGenerator::new(step_options.clone(), [0.0; 3]),
        epoch_ns,
    );
    let mut kills = 0;
    for pair in batch_ends.windows(2).step_by(3) {
        // Acknowledged: through the last timed move of the earlier batch. Published when
        // killed: part of the next batch, cut inside a move's segments.
        let acked = (1..=pair[0])
            .rev()
            .find(|&k| whole[k - 1].end_time() > whole[k - 1].start_time())
            .unwrap();
        let cut_move = (pair[0] + pair[1]) / 2;
        let cut_segment = reference[cut_move].1.len() / 2;
        let mut joined_steps = Vec::new();
        let mut joined_trajectories = Vec::new();
        let mut join = StepsJoin::new();
        let mut trajectories = ReplayFilter::new();
        let mut take = |writer: u8,
                        (trajectory, segments): (
            &polar_cell_msgs::JointTrajectory,
            &[polar_cell_msgs::StepSegment],
        )| {
            if trajectories.admit(trajectory.span_ns(), writer) == Admit::New {
                joined_trajectories.push(trajectory.clone());
            }
            for s in segments {
                match join.take(s, writer) {
                    Joined::New => joined_steps.push(s.clone()),
                    Joined::Repeat => {}
                    gap => panic!("{gap:?}"),
                }
            }
        };
        for (k, (t, s)) in reference[..=cut_move].iter().enumerate() {
            let s = if k == cut_move {
                &s[..cut_segment]
            } else {
                &s[..]
            };
            take(1, (t, s));
        }
        // The checkpoint the acknowledgement carried, through its bytes.
        let mut steps_then = StepGenerator::new(step_options.clone(), [0.0; 3]);
        let _ = published(&whole[..acked], &mut steps_then, epoch_ns);
        let bytes = Checkpoint::new(
            acked as u64,
            digest,
            epoch_ns,
            &whole[acked - 1].resume,
            steps_then.position(),
            0.0,
            acked as u64,
        )
        .to_bytes();
        let checkpoint = Checkpoint::from_bytes(&bytes, acked as u64, digest).unwrap();
        let mut resumed = Planner::resume(options.clone(), &checkpoint.resume_point()).unwrap();
        let mut plans = Vec::new();
        for m in &moves[acked..] {
            resumed.push(m, &mut plans).unwrap();
        }
        resumed.flush(&mut plans);
        let mut steps = StepGenerator::at_position(step_options.clone(), checkpoint.step_position);
        for (t, s) in published(&plans, &mut steps, checkpoint.plan_epoch_ns) {
            take(2, (&t, &s));
        }
        let expected_steps: Vec<_> = reference
            .iter()
            .flat_map(|(_, s)| s.iter().cloned())
            .collect();
        let expected_trajectories: Vec<_> = reference.iter().map(|(t, _)| t.clone()).collect();
        assert_eq!(
            joined_trajectories.len(),
            expected_trajectories.len(),
            "killed in move {cut_move}, resumed at {acked}"
        );
        assert!(
            joined_trajectories == expected_trajectories,
            "killed in move {cut_move}, resumed at {acked}"
        );
        assert_eq!(
            joined_steps.len(),
            expected_steps.len(),
            "killed in move {cut_move}, resumed at {acked}"
        );
        assert!(
            joined_steps == expected_steps,
            "killed in move {cut_move}, resumed at {acked}"
        );
        assert!(
            join.repeats() > 0,
            "killed in move {cut_move}: something was repeated"
        );
        kills += 1;
    }
    assert!(kills >= 5, "{kills} kills");
    eprintln!("polartest: {kills} kills, each resumed plan joined exactly");
}

/// A print that starts where a cancelled one stopped (the `initial_joints` a server passes
/// on): the plan begins exactly at that position, goes straight to the first target, keeps
/// every limit, and its steps count from the position's own step counts.
#[test]
fn a_plan_starts_where_the_machine_stands() {
    let moves = moves_of(b"G1 X50 Y0 F3000\nG1 X0 Y50\nG1 X-30 Y-30 Z0.3\n");
    let stop = [1.3 + 4.0 * std::f64::consts::PI, 0.04, 0.002];
    let options = PlannerOptions {
        initial_joints: stop,
        ..PlannerOptions::default()
    };
    let planned = plan(&moves, options.clone());
    assert_eq!(planned.len(), moves.len());
    assert_eq!(planned[0].points[0].q, stop);
    let limits = limit_usage(&moves, &planned, &options);
    assert!(limits.worst() <= 1.0 + 1e-9, "{limits:?}");
    assert_eq!((limits.out_of_range, limits.time_reversals), (0, 0));
    // The path from the stop position to (50, 0) is the commanded straight line.
    let start = polar_planner::path::forward(stop);
    let path = path_deviation(&moves, &planned, start, 20);
    assert!(path.max_deviation_m <= options.path_tolerance_m, "{path:?}");
    // θ stays continuous: (50, 0) is reached at the multiple of 2π nearest the start.
    let first_end = planned[0].points.last().unwrap().q;
    assert!(
        (first_end[0] - 4.0 * std::f64::consts::PI).abs() < 1e-9,
        "{first_end:?}"
    );
    assert!((first_end[1] - 0.05).abs() < 1e-12);
    // Steps: from the stop position's counts to the end's, exactly.
    let step_options = StepOptions::default();
    let counts = |q: [f64; 3]| -> [i64; 3] {
        std::array::from_fn(|k| (q[k] * step_options.steps_per_unit[k]).round() as i64)
    };
    let mut generator = StepGenerator::new(step_options.clone(), stop);
    let mut segments = Vec::new();
    for p in &planned {
        generator.segments(p, &mut segments);
    }
    let mut position = counts(stop);
    for seg in &segments {
        for (k, p) in position.iter_mut().enumerate() {
            *p += seg.directions[k] as i64 * seg.step_counts[k] as i64;
        }
    }
    assert_eq!(
        position,
        counts(planned.last().unwrap().points.last().unwrap().q)
    );
    assert_eq!(position, generator.position());
}

#[test]
fn a_start_outside_the_joint_limits_is_refused_by_name() {
    for (stop, joint) in [([0.0, 0.2, 0.0], "arm_r"), ([0.0, 0.0, -0.01], "z")] {
        let options = PlannerOptions {
            initial_joints: stop,
            ..PlannerOptions::default()
        };
        let error = Planner::new(options).err().expect("refused").to_string();
        assert!(error.contains(joint), "{error}");
    }
    let nan = PlannerOptions {
        initial_joints: [f64::NAN, 0.0, 0.0],
        ..PlannerOptions::default()
    };
    assert!(Planner::new(nan).is_err());
    // A stop read from whole steps, a rounding past the reach, still starts.
    let reach = PlannerOptions::default().joints[1].position.unwrap().1;
    let at_limit = PlannerOptions {
        initial_joints: [0.0, reach + 5e-6, 0.0],
        ..PlannerOptions::default()
    };
    assert!(Planner::new(at_limit).is_ok());
}

/// A print started away from home (an MCU's reported position, `--start-joints`): the
/// streamer starts from that point in mm, the planner from the same joints in m, and the two
/// differ in the last bit. A prime there is still a prime: the stage rests for ΔE/F (it was
/// planned as a 1e-19 m line over in no time).
#[test]
fn a_prime_where_a_print_starts_away_from_home_rests_for_its_feed() {
    let joints = [0.038, 0.05, 0.0];
    let options = PlannerOptions {
        initial_joints: joints,
        ..PlannerOptions::default()
    };
    let start_m = Planner::start_point(&options).p_m;
    let start_mm = start_m.map(|v| v * 1e3);
    assert!(
        (0..3).any(|j| start_mm[j] / 1e3 != start_m[j]),
        "this start converts exactly: the test shows nothing"
    );
    let interp = InterpreterOptions {
        start_position_mm: start_mm,
        ..InterpreterOptions::default()
    };
    let moves = parse_all(b"M83\nG1 E2 F1800\n", "prime", interp).unwrap().0;
    let planned = plan(&moves, options);
    let prime = planned.iter().find(|p| p.delta_e_m > 0.0).unwrap();
    let duration = prime.end_time() - prime.start_time();
    assert!((duration - 2.0 / 30.0).abs() < 1e-9, "{duration} s");
    assert!(
        prime.points.iter().all(|p| p.q == joints),
        "{:?}",
        prime.points
    );
}

/// With no centre zone (`center_radius_m` 0, in the node's range), a line through the
/// centre whose cross product rounds to a sliver above 0 is still through it: the arm stops
/// at r = 0 and the bed turns, r never negative (it ran the arm out to −r along the line,
/// below the URDF's lower limit, with negative radii not allowed).
#[test]
fn without_a_centre_zone_lines_through_the_centre_never_make_r_negative() {
    let options = PlannerOptions {
        center_radius_m: 0.0,
        ..PlannerOptions::default()
    };
    let mut src = String::from("G90\n");
    for k in 0..60 {
        let phi = k as f64 * 0.1047;
        let (x, y) = (40.0 * phi.cos(), 40.0 * phi.sin());
        src += &format!(
            "G1 X{x:.6} Y{y:.6} F3000\nG1 X{:.6} Y{:.6}\n",
            -0.75 * x,
            -0.75 * y
        );
    }
    let moves = moves_of(src.as_bytes());
    let planned = plan(&moves, options);
    let lowest = planned
        .iter()
        .flat_map(|p| &p.points)
        .map(|p| p.q[1])
        .fold(f64::INFINITY, f64::min);
    assert!(lowest > -1e-12, "r went down to {lowest} m");
}

/// Moves refused (one beyond reach, a prime whose rest would last 2·10⁶ s) leave nothing of
/// themselves behind: no pin-open dwell in the plan, and the next extruding move still gets
/// its dwell (a refused move's dwell was emitted before the check, and it counted as
/// extruding).
#[test]
fn a_refused_move_leaves_no_pin_dwell_and_the_next_extruding_move_gets_its_own() {
    let options = PlannerOptions {
        pin_open_dwell_s: 0.25,
        ..PlannerOptions::default()
    };
    let moves =
        moves_of(b"M83\nG1 X20 Y0 F3000\nG1 E2000 F0.06\nG1 X400 Y0 E5 F3000\nG1 X30 Y0 E1\n");
    let [travel, prime, beyond, extruding] = [&moves[0], &moves[1], &moves[2], &moves[3]];
    assert!(beyond.extrude && prime.extrude && extruding.extrude && !travel.extrude);
    let mut planner = Planner::new(options).unwrap();
    let mut out = Vec::new();
    planner.push(travel, &mut out).unwrap();
    let err = planner.push(prime, &mut out).unwrap_err();
    assert!(err.to_string().contains("longer than the 1e6 s"), "{err}");
    let err = planner.push(beyond, &mut out).unwrap_err();
    assert!(err.to_string().contains("arm_r"), "{err}");
    planner.push(extruding, &mut out).unwrap();
    planner.flush(&mut out);
    assert!(
        out.iter()
            .all(|p| p.sequence != beyond.sequence && p.sequence != prime.sequence),
        "{out:?}"
    );
    let travel_end = out
        .iter()
        .find(|p| p.sequence == travel.sequence)
        .unwrap()
        .end_time();
    let plan = out
        .iter()
        .find(|p| p.sequence == extruding.sequence)
        .unwrap();
    assert!(
        (plan.start_time() - travel_end).abs() < 1e-12,
        "no gap in plan time"
    );
    let rest_s = rest_at_start_s(plan);
    assert!((rest_s - 0.25).abs() < 1e-9, "{rest_s}");
}

/// How long a plan rests where it starts (a pin-open dwell) before it moves.
fn rest_at_start_s(plan: &PlannedMove) -> f64 {
    let rest_end = plan
        .points
        .iter()
        .take_while(|p| p.q == plan.points[0].q)
        .last()
        .unwrap()
        .t;
    rest_end - plan.start_time()
}

/// A feed-rate line between two extruding moves (`G1 F1800`: no path, no E) takes no time and
/// changes nothing of the pin: the second move gets no pin-open dwell (it rested the stage
/// 0.25 s with the pin open and the screw stopped, as the screw driver skips such a line). A
/// travel between them still does.
#[test]
fn a_feed_rate_line_between_extruding_moves_adds_no_pin_dwell() {
    let options = PlannerOptions {
        pin_open_dwell_s: 0.25,
        ..PlannerOptions::default()
    };
    for (between, dwell_s) in [("G1 F1800", 0.0), ("G1 X25 Y5", 0.25)] {
        let src = format!("M83\nG1 X20 Y0 F3000\nG1 X25 Y0 E1\n{between}\nG1 X30 Y0 E1\n");
        let moves = moves_of(src.as_bytes());
        let planned = plan(&moves, options.clone());
        let last = moves.last().unwrap().sequence;
        let plan = planned.iter().find(|p| p.sequence == last).unwrap();
        let rest_s = rest_at_start_s(plan);
        assert!(
            (rest_s - dwell_s).abs() < 1e-9,
            "{between}: rests {rest_s} s"
        );
    }
}
