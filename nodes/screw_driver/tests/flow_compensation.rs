//! Flow compensation on the real fixtures, through the same path as the nodes: G-code →
//! planner (with the screw's limits) → JointTrajectory → TimedMove → commands → the reduced
//! flow model → material per extruding move.

mod common;

use polar_planner::{PlannerOptions, ScrewLimits};
use screw_driver::compensation::{material_per_move, FlowModel, MoveMaterial};
use screw_driver::screw::{ScrewOptions, TimedMove};

fn timed(name: &str, model: &FlowModel) -> (Vec<TimedMove>, Vec<Option<f64>>) {
    let screw = ScrewOptions::default();
    let options = PlannerOptions {
        screw: Some(ScrewLimits {
            usable_rpm: 0.9 * screw.max_rpm,
            e_per_rev_m: 0.002,
            flow_tau_s: model.tau_s,
        }),
        ..PlannerOptions::default()
    };
    let (timed, plans) = common::plan_and_time(&common::fixture(name), options);
    (timed, plans.iter().map(|p| p.slowed_for_screw).collect())
}

fn beyond(result: &[MoveMaterial], tolerance: f64) -> Vec<&MoveMaterial> {
    result
        .iter()
        .filter(|m| m.error().abs() > tolerance)
        .collect()
}

#[test]
fn compensation_delivers_each_moves_material_where_the_lag_did_not() {
    let model = FlowModel::default_extruder();
    for name in ["finger.gcode", "polartest.gcode"] {
        let (moves, slowed) = timed(name, &model);
        let run = |compensation| {
            material_per_move(
                &moves,
                &ScrewOptions {
                    compensation,
                    ..ScrewOptions::default()
                },
                &model,
                0.002,
            )
        };
        let plain = run(None);
        let shaped = run(Some(model));
        assert!(shaped.len() > 1600, "{name}: {}", shaped.len());
        let (plain_missed, shaped_missed) = (beyond(&plain, 0.01), beyond(&shaped, 0.01));
        eprintln!(
            "{name}: beyond 1 %: uncompensated {}, compensated {} of {}",
            plain_missed.len(),
            shaped_missed.len(),
            shaped.len()
        );
        assert!(plain_missed.len() >= 80, "{name}: the lag shows");
        assert!(
            shaped_missed.len() * 100 <= 2 * shaped.len()
                && shaped_missed.len() * 5 < plain_missed.len(),
            "{name}: {} missed",
            shaped_missed.len()
        );
        // What still misses are fine lines (under 0.02 mm of filament), or short moves the
        // flow cannot change within (a tenth of a millimetre in a quarter of τ), within 5 %.
        for m in &shaped_missed {
            let wanted_mm = m.wanted_rpm_s / 60.0 * 0.002 * 1e3;
            assert!(
                wanted_mm < 0.02 || m.error().abs() < 0.05,
                "{name} line {}: {wanted_mm} mm, {:+.2} %",
                m.source_line,
                m.error() * 100.0
            );
        }
        // Each move fed over the whole print: nothing lost overall.
        let total = |r: &[MoveMaterial]| r.iter().map(|m| m.delivered_rpm_s).sum::<f64>();
        let wanted: f64 = shaped.iter().map(|m| m.wanted_rpm_s).sum();
        assert!((total(&shaped) / wanted - 1.0).abs() < 1e-3, "{name}");
        // Primes the screw cannot feed in their time were lengthened by the planner.
        assert!(slowed.iter().any(|s| s.is_some()), "{name}");
    }
}

/// The planner's default for the flow's time constant is the screw driver's.
#[test]
fn planner_default_flow_tau_matches_the_screw_driver() {
    let specs = polar_planner::node::param_specs();
    let spec = specs
        .iter()
        .find(|s| s.name == "screw_flow_tau_s")
        .expect("declared");
    let cell_runtime::ParamValue::Double(planner_tau) = spec.default else {
        panic!("{:?}", spec.default)
    };
    let tau = FlowModel::default_extruder().tau_s;
    assert!(
        (planner_tau / tau - 1.0).abs() < 0.02,
        "{planner_tau} vs {tau}"
    );
}

/// The node computes commands chunk by chunk (cut at closed-pin gaps): any such cut gives the
/// same material per move as one chunk. (A chunk that began with a pin opening once let
/// material flow during the pin's delay: the state carried the last interval's flow, not the
/// pin.)
#[test]
fn chunking_at_closed_pin_gaps_changes_nothing() {
    use screw_driver::compensation::delivered_in_windows;
    use screw_driver::screw::{chunk_commands, PinState};
    let model = FlowModel::default_extruder();
    let (moves, _) = timed("polartest.gcode", &model);
    let options = ScrewOptions {
        compensation: Some(model),
        ..ScrewOptions::default()
    };
    let windows: Vec<(f64, f64)> = moves
        .windows(2)
        .filter(|w| w[0].extrude && w[0].t.len() > 1)
        .map(|w| (w[0].t[0], w[1].t[0].max(w[0].t[w[0].t.len() - 1])))
        .collect();
    let material = |cuts: &[usize]| {
        let mut pin = PinState::default();
        let mut commands = Vec::new();
        let mut start = 0;
        for &cut in cuts.iter().chain(std::iter::once(&moves.len())) {
            commands.extend(chunk_commands(
                &moves[start..cut],
                &options,
                &mut pin,
                cut == moves.len(),
                0.0,
            ));
            start = cut;
        }
        delivered_in_windows(&commands, &model, options.pin_open_delay_s, &windows)
    };
    let whole = material(&[]);
    // Cuts in the closed-pin gaps before two unretract primes (lines 758 and 1310).
    let prime = moves.iter().position(|m| m.source_line == 758).unwrap();
    let later = moves.iter().position(|m| m.source_line == 1310).unwrap();
    for cuts in [
        vec![prime - 3],
        vec![prime - 1],
        vec![prime],
        vec![prime - 3, later],
    ] {
        let chunked = material(&cuts);
        for (a, b) in whole.iter().zip(&chunked) {
            assert!(
                (a - b).abs() <= 1e-6 * a.abs().max(1.0),
                "cuts {cuts:?}: {a} vs {b}"
            );
        }
    }
}
