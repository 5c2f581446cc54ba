//! The fixtures planned and cut into step segments as the planner node does, and a player
//! set up as the cell's.

// Each test binary uses part of this module.
#![allow(dead_code)]

use cell_executor::{Edge, Player, PlayerOptions, PlayerState, SegmentJob};
use gcode_streamer::{parse_all, InterpreterOptions};
use polar_cell_msgs::{GcodeMove, StepSegment};
use polar_planner::steps::StepOptions;
use polar_planner::{plan_program, PlannedMove, PlannerOptions};

pub struct Fixture {
    pub moves: Vec<GcodeMove>,
    pub planned: Vec<PlannedMove>,
    pub segments: Vec<StepSegment>,
    /// Where the steps end (the generator's absolute position).
    pub end_steps: [i64; 3],
}

/// `name` from `shared/fixtures/gcode`, planned with the default options.
pub fn plan_fixture(name: &str) -> Fixture {
    let path = format!(
        "{}/../../../shared/fixtures/gcode/{name}",
        env!("CARGO_MANIFEST_DIR")
    );
    let src = std::fs::read(path).unwrap();
    let moves = parse_all(&src, name, InterpreterOptions::default())
        .unwrap()
        .0;
    let program = plan_program(&moves, PlannerOptions::default(), StepOptions::default()).unwrap();
    Fixture {
        moves,
        planned: program.planned,
        segments: program.segments,
        end_steps: program.end_steps,
    }
}

/// The planner's default joint accelerations: the limits a hold keeps to.
pub fn acceleration_limits() -> [f64; 3] {
    std::array::from_fn(|k| PlannerOptions::default().joints[k].acceleration)
}

/// The player as the cell runs it: default steps, the planner's limits, a 0.25 s pin, room
/// for 1024 segments, starting where the planner starts.
pub fn player_options() -> PlayerOptions {
    let steps = StepOptions::default();
    let initial_steps = std::array::from_fn(|k| {
        (PlannerOptions::default().initial_joints[k] * steps.steps_per_unit[k]).round() as i64
    });
    PlayerOptions {
        queue_capacity: 1024,
        initial_steps,
        ..PlayerOptions::new(steps, acceleration_limits(), 0.25)
    }
}

/// Play `segments` to the end in 1 ms periods, keeping the queue topped up, handing every
/// edge to `on_edge` and calling `each_ms(player, ms)` after each period.
pub fn play_all(
    segments: &[StepSegment],
    mut on_edge: impl FnMut(Edge),
    mut each_ms: impl FnMut(&mut Player, u64),
) -> Player {
    let mut player = Player::new(player_options());
    let timer_hz = player.options().steps.timer_hz;
    let mut feed = segments
        .iter()
        .map(|s| SegmentJob::from_message(s, timer_hz).unwrap())
        .peekable();
    for ms in 0u64.. {
        while player.free_slots() > 0 {
            match feed.next() {
                Some(job) => player.push(job).unwrap(),
                None => {
                    player.finish_input();
                    break;
                }
            }
        }
        player
            .advance_to(u128::from(ms * 1000) << 32, &mut on_edge)
            .unwrap();
        each_ms(&mut player, ms);
        if ms > 0 && player.state() == PlayerState::Idle && feed.peek().is_none() {
            break;
        }
    }
    player
}
