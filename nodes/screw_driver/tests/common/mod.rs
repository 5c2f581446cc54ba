//! What the screw driver's integration tests share: the fixtures, and moves planned and timed
//! as the nodes do it (plan → JointTrajectory → TimedMove).

use gcode_streamer::{parse_all, GcodeMove, InterpreterOptions};
use polar_planner::messages::trajectory_message;
use polar_planner::{PlannedMove, Planner, PlannerOptions};
use screw_driver::screw::{position_after, TimedMove};

/// A G-code file of `../shared/fixtures/gcode/`, interpreted.
pub fn fixture(name: &str) -> Vec<GcodeMove> {
    let path = format!(
        "{}/../../../shared/fixtures/gcode/{name}",
        env!("CARGO_MANIFEST_DIR")
    );
    parse_all(
        &std::fs::read(path).unwrap(),
        name,
        InterpreterOptions::default(),
    )
    .unwrap()
    .0
}

/// `moves` planned with `options`, as the screw driver receives them, and the plans.
#[allow(dead_code)] // not every test file that shares this module plans
pub fn plan_and_time(
    moves: &[GcodeMove],
    options: PlannerOptions,
) -> (Vec<TimedMove>, Vec<PlannedMove>) {
    let mut planner = Planner::new(options).unwrap();
    let mut plans = Vec::new();
    for m in moves {
        planner.push(m, &mut plans).unwrap();
    }
    planner.flush(&mut plans);
    let mut from = [0.0; 3];
    let timed = moves
        .iter()
        .zip(&plans)
        .map(|(m, p)| {
            // A wall-clock epoch, as the node sees: times must stay exact relative to it.
            let epoch: i64 = 1_795_318_512_024_268_371;
            let t = TimedMove::from_trajectory(m, from, &trajectory_message(p, epoch), epoch);
            from = position_after(m, from);
            t
        })
        .collect();
    (timed, plans)
}
