//! Pre-flight: the whole file through the planner and the step core before anything moves.
//!
//! A print that would fail at its last move (a point beyond the arm's reach, a feed the planner
//! refuses) must be refused before the first one moves the machine. [`Preflight`] plans every
//! move with the print's own options, cuts the plan into step segments and converts each for
//! the step core, keeping nothing but counters: memory does not grow with the file.

use polar_cell_msgs::{GcodeMove, StepSegment};

use crate::planner::{PlanError, PlannedMove, Planner, PlannerOptions};
use crate::steps::{StepGenerator, StepOptions};

/// What a file asks of the machine, when it passes.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct PreflightReport {
    pub moves: u64,
    /// Machine time of the whole plan (s).
    pub plan_time_s: f64,
    pub segments: u64,
    /// Steps each axis makes (either direction).
    pub steps: [u64; 3],
    /// Range of each joint over the plan: (min, max) of `bed_theta` (rad), `arm_r`, `z` (m).
    pub joint_ranges: [(f64, f64); 3],
}

/// Why a file is refused.
#[derive(Debug, thiserror::Error)]
pub enum PreflightError {
    #[error(transparent)]
    Plan(#[from] PlanError),
    #[error("its steps cannot be played: {0}")]
    Steps(#[from] polar_cell_msgs::UnplayableSegment),
}

/// Plans moves one by one and forgets them.
pub struct Preflight {
    planner: Planner,
    generator: StepGenerator,
    report: PreflightReport,
    planned: Vec<PlannedMove>,
    segments: Vec<StepSegment>,
    /// The step timer the segments are timed for (and must fit).
    timer_hz: f64,
}

impl Preflight {
    pub fn new(options: PlannerOptions, steps: StepOptions) -> Result<Preflight, PlanError> {
        let initial = options.initial_joints;
        let timer_hz = steps.timer_hz;
        Ok(Preflight {
            timer_hz,
            planner: Planner::new(options)?,
            generator: StepGenerator::new(steps, initial),
            report: PreflightReport {
                joint_ranges: std::array::from_fn(|j| (initial[j], initial[j])),
                ..PreflightReport::default()
            },
            planned: Vec::new(),
            segments: Vec::new(),
        })
    }

    /// Check the next move (and whatever the planner finishes with it).
    pub fn push(&mut self, m: &GcodeMove) -> Result<(), PreflightError> {
        self.report.moves += 1;
        self.planner.push(m, &mut self.planned)?;
        self.drain()
    }

    /// Check the end of the plan and report.
    pub fn finish(mut self) -> Result<PreflightReport, PreflightError> {
        self.planner.flush(&mut self.planned);
        self.drain()?;
        Ok(self.report)
    }

    fn drain(&mut self) -> Result<(), PreflightError> {
        for plan in self.planned.drain(..) {
            for p in &plan.points {
                for j in 0..3 {
                    let (lo, hi) = &mut self.report.joint_ranges[j];
                    *lo = lo.min(p.q[j]);
                    *hi = hi.max(p.q[j]);
                }
            }
            self.report.plan_time_s = plan.end_time();
            self.segments.clear();
            self.generator.segments(&plan, &mut self.segments);
            for seg in &self.segments {
                // What the machine will refuse when it gets there: the same check.
                seg.playable(self.timer_hz)?;
                for (total, &count) in self.report.steps.iter_mut().zip(&seg.step_counts) {
                    *total += count as u64;
                }
            }
            self.report.segments += self.segments.len() as u64;
        }
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use polar_cell_msgs::GcodeMove as M;

    fn line(sequence: u64, x_m: f64, y_m: f64, source_line: u32) -> GcodeMove {
        GcodeMove {
            sequence,
            source_line,
            kind: M::KIND_LINEAR,
            x_m,
            y_m,
            feedrate_m_per_s: 0.05,
            axes: M::AXIS_X | M::AXIS_Y,
            ..GcodeMove::default()
        }
    }

    #[test]
    fn a_move_beyond_the_arms_reach_is_refused_with_its_line_joint_and_value() {
        let mut preflight =
            Preflight::new(PlannerOptions::default(), StepOptions::default()).unwrap();
        preflight.push(&line(0, 0.05, 0.0, 3)).unwrap();
        preflight.push(&line(1, 0.0, 0.10, 4)).unwrap();
        let err = preflight.push(&line(2, 0.12, 0.12, 57)).unwrap_err();
        let text = err.to_string();
        // √(0.12² + 0.12²) = 0.1697 m, beyond the URDF's 0.15 m.
        assert!(text.contains("line 57") && text.contains("arm_r"), "{text}");
        assert!(text.contains("0.169706"), "{text}");
    }

    #[test]
    fn a_good_file_reports_its_time_steps_and_ranges() {
        let mut preflight =
            Preflight::new(PlannerOptions::default(), StepOptions::default()).unwrap();
        preflight.push(&line(0, 0.05, 0.0, 1)).unwrap();
        preflight.push(&line(1, -0.05, 0.0, 2)).unwrap();
        let report = preflight.finish().unwrap();
        assert_eq!(report.moves, 2);
        assert!(
            report.plan_time_s > 2.0 && report.plan_time_s < 4.0,
            "{report:?}"
        );
        // Out to r = 50 mm (80 steps/mm: 4000 steps), through the centre and out again: the
        // arm makes 3 × 4000 steps whichever way the centre is crossed.
        assert_eq!(report.steps[1], 12_000, "{report:?}");
        let (lo, hi) = report.joint_ranges[1];
        assert!(lo.abs() < 1e-12 && (hi - 0.05).abs() < 1e-12, "{report:?}");
    }

    /// A step the machine's step clock cannot time (a first period of 2³⁰ ticks: 1.07 s at
    /// 1 GHz) is refused before the print, naming its line, as the machine would refuse it
    /// there. A long dwell, or a slow cruise of many steps, is not: both come in pieces.
    #[test]
    fn a_step_too_long_for_the_step_clock_is_refused_before_the_print() {
        let steps = StepOptions {
            timer_hz: 1e9,
            ..StepOptions::default()
        };
        let mut preflight = Preflight::new(PlannerOptions::default(), steps).unwrap();
        preflight.push(&line(0, 0.05, 0.0, 1)).unwrap();
        let dwell = GcodeMove {
            sequence: 1,
            source_line: 2,
            kind: M::KIND_DWELL,
            dwell_s: 3600.0,
            ..GcodeMove::default()
        };
        preflight.push(&dwell).unwrap();
        // 10 mm at 0.5 mm/s: 20 s of steps 25 ms apart, in pieces under 2.15 s.
        let crawl = GcodeMove {
            feedrate_m_per_s: 5e-4,
            ..line(2, 0.06, 0.0, 3)
        };
        preflight.push(&crawl).unwrap();
        // 0.1 mm at 1 µm/s: steps 12.5 s apart, and slower still to and from rest.
        let creep = GcodeMove {
            feedrate_m_per_s: 1e-6,
            ..line(3, 0.0601, 0.0, 4)
        };
        let text = match preflight
            .push(&creep)
            .and_then(|()| preflight.finish().map(drop))
        {
            Err(e) => e.to_string(),
            Ok(()) => panic!("steps 12.5 s apart at 1 GHz passed"),
        };
        assert!(
            text.contains("line 4") && text.contains("cannot be played"),
            "{text}"
        );
    }
}
