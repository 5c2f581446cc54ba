//! A whole program planned at once, kept in memory: for tests, emulators and benchmarks that
//! need every segment of a file together (the nodes and pre-flight stream instead).

use polar_cell_msgs::{GcodeMove, StepSegment};

use crate::planner::{PlanError, PlannedMove, Planner, PlannerOptions};
use crate::steps::{StepGenerator, StepOptions};

/// The plan of a program and its step segments.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct Program {
    pub planned: Vec<PlannedMove>,
    pub segments: Vec<StepSegment>,
    /// Where the steps end (the generator's absolute position).
    pub end_steps: [i64; 3],
}

/// Plan `moves` with `options` and cut the plan into segments timed for `steps`.
pub fn plan_program(
    moves: &[GcodeMove],
    options: PlannerOptions,
    steps: StepOptions,
) -> Result<Program, PlanError> {
    let mut generator = StepGenerator::new(steps, options.initial_joints);
    let mut planner = Planner::new(options)?;
    let mut planned = Vec::new();
    for m in moves {
        planner.push(m, &mut planned)?;
    }
    planner.flush(&mut planned);
    let mut segments = Vec::new();
    for plan in &planned {
        generator.segments(plan, &mut segments);
    }
    Ok(Program {
        planned,
        segments,
        end_steps: generator.position(),
    })
}
