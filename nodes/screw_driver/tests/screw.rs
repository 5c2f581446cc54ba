//! Screw commands against hand-computed values and against the G-code's material, through
//! the same path the node takes: plan -> JointTrajectory -> TimedMove -> commands.

mod common;

use gcode_streamer::{parse_all, GcodeMove, InterpreterOptions};
use polar_planner::PlannerOptions;
use screw_driver::fir::FILTER_1;
use screw_driver::screw::{
    as_fed, breakpoints, integral, integral_held, smooth, Command, PinStrategy, RpmModel,
    ScrewOptions, TimedMove,
};

const E_PER_REV: f64 = 0.002; // ScrewOptions::default()

fn fixture(name: &str) -> Vec<GcodeMove> {
    common::fixture(name)
}

fn timed(moves: &[GcodeMove], dwell: f64) -> Vec<TimedMove> {
    let options = PlannerOptions {
        pin_open_dwell_s: dwell,
        ..PlannerOptions::default()
    };
    common::plan_and_time(moves, options).0
}

fn deposited_m(rpm_s: f64) -> f64 {
    rpm_s / 60.0 * E_PER_REV
}

/// Seed eq. (9) by hand: from (10, 0) to (10, 2) mm at F600, ΔE 0.1 mm, γ 0.5:
/// r at the middle √101 mm, SNW = 0.5·600·√101·0.1/2 = 15·√101 rpm.
#[test]
fn radius_model_matches_equation_9_by_hand() {
    let moves = parse_all(
        b"G1 X10 Y0 F600\nG1 X10 Y2 E0.1\n",
        "h",
        InterpreterOptions::default(),
    )
    .unwrap()
    .0;
    let options = ScrewOptions {
        model: RpmModel::Radius { gamma: 0.5 },
        max_rpm: 1000.0,
        max_rpm_per_s: f64::INFINITY,
        ..ScrewOptions::default()
    };
    let commands = breakpoints(&timed(&moves, 0.0), &options);
    let expected = 15.0 * 101f64.sqrt();
    let moving: Vec<&Command> = commands.iter().filter(|c| c.rpm > 0.0).collect();
    assert!(!moving.is_empty());
    for c in moving {
        assert!((c.rpm - expected).abs() < 1e-9, "{} vs {expected}", c.rpm);
    }
}

/// polar_speed feeds each move's ΔE within 1 % (exactly, up to the rate limit).
#[test]
fn polar_speed_feeds_each_move_its_material() {
    for name in ["finger.gcode", "polartest.gcode"] {
        let moves = timed(&fixture(name), 0.0);
        let commands = breakpoints(&moves, &ScrewOptions::default());
        let needed = moves
            .iter()
            .filter(|m| m.extrude && m.length_m > 0.0)
            .flat_map(|m| {
                m.speed
                    .iter()
                    .map(move |v| 60.0 * v * m.delta_e_m / m.length_m / E_PER_REV)
            })
            .fold(0.0f64, f64::max);
        eprintln!("{name}: highest rpm asked along a path {needed:.1}");
        let mut worst: f64 = 0.0;
        let mut checked = 0;
        // Moves along a path (a prime in place asks for more than max_rpm and is clamped).
        for m in moves
            .iter()
            .filter(|m| m.extrude && m.delta_e_m > 1e-7 && m.length_m > 0.0)
        {
            let (a, b) = (m.motion_start_s, *m.t.last().unwrap());
            let fed = deposited_m(integral(&commands, a, b));
            let error = (fed - m.delta_e_m).abs() / m.delta_e_m;
            worst = worst.max(error);
            checked += 1;
        }
        eprintln!("{name}: {checked} extruding moves, worst relative error {worst:.2e}");
        assert!(checked > 1500);
        assert!(worst < 0.01, "{name}: {worst}");
        // Never turning with the pin closed.
        for w in commands.windows(2) {
            if !w[0].pin_open {
                assert!(w[0].rpm == 0.0);
            }
        }
    }
}

/// With the seed's filter No.1, material per 10 mm of path stays within 1 %, also in windows
/// holding a prime in place (E without motion after a retraction), which smoothing spreads
/// into the first millimetres of the path. A window the unsmoothed commands cannot feed (a
/// prime above max_rpm) is excluded and counted.
#[test]
fn smoothed_commands_feed_each_10_mm_within_1_percent() {
    for name in ["finger.gcode", "polartest.gcode"] {
        let moves = timed(&fixture(name), 0.0);
        let raw = breakpoints(&moves, &ScrewOptions::default());
        let held = smooth(&raw, &FILTER_1.taps(), 0.001);
        let (mut window_start, mut length, mut expected, mut primed) = (None, 0.0, 0.0, false);
        let (mut worst, mut worst_primed): (f64, f64) = (0.0, 0.0);
        let (mut windows, mut primed_windows, mut clamped) = (0, 0, 0);
        // What each move feeds: its ΔE net of what a retraction before it took.
        for m in &as_fed(&moves) {
            if !m.extrude {
                // An instant without material (the G92 E0 after each prime) is no break.
                if m.t.first() != m.t.last() {
                    (window_start, length, expected, primed) = (None, 0.0, 0.0, false);
                }
                continue;
            }
            let opened = raw
                .iter()
                .find(|c| c.pin_open && c.sequence == m.sequence)
                .map_or(m.motion_start_s, |c| c.t);
            let start = *window_start.get_or_insert(opened.min(m.motion_start_s));
            length += m.length_m;
            expected += m.delta_e_m;
            primed |= m.length_m == 0.0;
            if length >= 0.010 {
                let end = *m.t.last().unwrap();
                let fed = deposited_m(integral_held(&held, start, end));
                let deliverable = deposited_m(integral(&raw, start, end));
                let error = (fed - expected).abs() / expected;
                if (deliverable - expected).abs() > 1e-6 * expected {
                    clamped += 1; // a prime above max_rpm: not deliverable, smoothed or not
                } else if primed {
                    worst_primed = worst_primed.max(error);
                    primed_windows += 1;
                } else {
                    worst = worst.max(error);
                    windows += 1;
                }
                (window_start, length, expected, primed) = (None, 0.0, 0.0, false);
            }
        }
        eprintln!(
            "{name}: {windows} windows of 10 mm, worst {worst:.2e}; {primed_windows} holding a prime, worst {worst_primed:.2e}; {clamped} above max_rpm"
        );
        assert!(windows > 20);
        assert!(worst < 0.01, "{name}: {worst}");
        assert!(worst_primed < 0.01, "{name}: {worst_primed}");
        assert!(clamped <= 1);
    }
}

/// lookahead opens the pin exactly pin_open_delay before each extruding run starts to move.
#[test]
fn lookahead_opens_the_pin_exactly_the_delay_ahead() {
    let moves = timed(&fixture("polartest.gcode"), 0.0);
    let options = ScrewOptions::default();
    let commands = breakpoints(&moves, &options);
    let mut runs = 0;
    let (mut extruding, mut closed_at) = (false, f64::NEG_INFINITY);
    for m in moves.iter().filter(|m| !m.t.is_empty()) {
        if m.extrude && !extruding && m.motion_start_s - options.pin_open_delay_s >= closed_at {
            let open = commands
                .iter()
                .find(|c| c.pin_open && c.source_line == m.source_line)
                .expect("an opening command");
            assert!((m.motion_start_s - open.t - options.pin_open_delay_s).abs() < 1e-12);
            runs += 1;
        }
        if extruding && !m.extrude {
            closed_at = m.t[0];
        }
        extruding = m.extrude;
    }
    assert!(runs > 5, "{runs}");
}

/// stop: exactly one rest of pin_open_delay per off -> on transition, and the pin opens when
/// the rest begins.
#[test]
fn stop_rests_once_per_off_on_transition() {
    let gcode = fixture("polartest.gcode");
    let delay = 0.25;
    let moves = timed(&gcode, delay);
    let transitions = gcode
        .iter()
        .filter(|m| matches!(m.kind, GcodeMove::KIND_LINEAR | GcodeMove::KIND_RAPID))
        .scan(false, |previous, m| {
            let on = m.extrude && !*previous;
            *previous = m.extrude;
            Some(on)
        })
        .filter(|&on| on)
        .count();
    // A rest: the trajectory opens with `delay` at rest (before a path or a prime in place).
    let rested = |m: &TimedMove| {
        m.t.len() > 1 && (m.t[1] - m.t[0] - delay).abs() < 1e-9 && m.speed[1] == 0.0
    };
    let rests = moves.iter().filter(|m| rested(m)).count();
    assert_eq!(rests, transitions);
    let options = ScrewOptions {
        strategy: PinStrategy::Stop,
        ..ScrewOptions::default()
    };
    let commands = breakpoints(&moves, &options);
    // Lines and primes in place alike (a prime turned the screw through its rest once),
    // those that feed after what a retraction took.
    let mut primes = 0;
    for m in as_fed(&moves).iter().filter(|m| rested(m) && m.extrude) {
        let open = commands
            .iter()
            .find(|c| c.pin_open && c.source_line == m.source_line)
            .unwrap();
        assert_eq!(open.t, m.t[0]);
        // No material during the rest.
        assert_eq!(
            integral(&commands, m.t[0], m.t[1]),
            0.0,
            "line {}",
            m.source_line
        );
        primes += usize::from(m.length_m == 0.0);
    }
    assert!(primes > 0);
}

/// Over a whole print the screw feeds every positive ΔE less what the retractions before it
/// took — the G-code's net E: polartest's seven `G1 E-1` are each repaid by the next
/// unretraction (which fed its whole 1.1 mm before: 51.337 mm for a net 44.337), finger's
/// one likewise. Planned with the screw's limits, as the node plans, so that every prime can
/// be fed.
#[test]
fn a_print_feeds_its_extrusion_net_of_retractions() {
    let screw = ScrewOptions::default();
    let options = PlannerOptions {
        screw: Some(polar_planner::ScrewLimits {
            usable_rpm: 0.9 * screw.max_rpm,
            e_per_rev_m: E_PER_REV,
            flow_tau_s: 0.0,
        }),
        ..PlannerOptions::default()
    };
    for (name, repaid_mm) in [("polartest.gcode", 7.0), ("finger.gcode", 1.0)] {
        let moves = common::plan_and_time(&fixture(name), options.clone()).0;
        let commands = breakpoints(&moves, &screw);
        let positive_m: f64 = moves.iter().map(|m| m.delta_e_m.max(0.0)).sum();
        let fed_m: f64 = as_fed(&moves).iter().map(|m| m.delta_e_m.max(0.0)).sum();
        let turned_m = deposited_m(integral(
            &commands,
            commands[0].t,
            commands.last().unwrap().t,
        ));
        eprintln!(
            "{name}: positive ΔE {:.3} mm, fed {:.3} mm, the screw turned {:.3} mm",
            positive_m * 1e3,
            fed_m * 1e3,
            turned_m * 1e3
        );
        assert!(
            ((positive_m - fed_m) * 1e3 - repaid_mm).abs() < 1e-9,
            "{name}"
        );
        assert!(
            (turned_m - fed_m).abs() < 1e-9 * fed_m,
            "{name}: {turned_m} vs {fed_m}"
        );
        let net_m: f64 = moves.iter().map(|m| m.delta_e_m).sum();
        assert!(
            (fed_m - net_m).abs() < 1e-12,
            "{name}: every retraction was repaid"
        );
    }
}

/// At a fixed command rate (an identity "filter" on the grid), each held command feeds exactly
/// what the breakpoints feed over its interval.
#[test]
fn fixed_rate_commands_keep_the_material() {
    let moves = timed(&fixture("polartest.gcode"), 0.0);
    let raw = breakpoints(&moves, &ScrewOptions::default());
    // Periods shorter and longer than the pin's delay (0.25 s): an interval in which the
    // pin opens and the move starts carries that move's first material (it was dropped
    // when the interval took the closed pin it began with).
    for period_s in [0.01, 0.5, 1.0] {
        let held = smooth(&raw, &[1.0], period_s);
        assert!(held
            .windows(2)
            .all(|w| (w[1].t - w[0].t - period_s).abs() < 1e-9));
        let total_raw = integral(&raw, raw[0].t, raw.last().unwrap().t);
        let total_held = integral_held(&held, held[0].t, held.last().unwrap().t);
        assert!(
            (total_raw - total_held).abs() < 1e-9 * total_raw,
            "{period_s} s: {total_held} of {total_raw}"
        );
        // Material turns only with the pin open.
        assert!(held.iter().all(|c| c.pin_open || c.rpm == 0.0));
    }
}
