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
    /// Per segment: every joint is at rest at its end (a pause, or the end of a move whose
    /// last plan point has no velocity), so execution may stop there without an underrun.
    pub ends_at_rest: Vec<bool>,
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
    let mut ends_at_rest = Vec::new();
    for plan in &planned {
        let first = segments.len();
        generator.segments(plan, &mut segments);
        let stops = plan
            .points
            .last()
            .is_some_and(|p| p.qd.iter().all(|v| *v == 0.0));
        for (k, seg) in segments[first..].iter().enumerate() {
            let last = first + k + 1 == segments.len();
            ends_at_rest.push(seg.step_counts.iter().all(|&c| c == 0) || (last && stops));
        }
    }
    Ok(Program {
        planned,
        segments,
        ends_at_rest,
        end_steps: generator.position(),
    })
}
