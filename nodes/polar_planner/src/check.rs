//! Independent checks of a plan, from its published points only: how far the executed joint
//! path (linear between points, as a joint trajectory is followed) strays from the commanded
//! lines, and how much of each limit the plan uses.

use polar_cell_msgs::GcodeMove;

use crate::path::{distance_to_segment, forward};
use crate::planner::{PlannedMove, PlannerOptions};

/// Largest distance of the executed path from the commanded segments.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct PathReport {
    pub max_deviation_m: f64,
    pub worst_sequence: u64,
    pub samples: u64,
}

/// Sample every piece between consecutive points `samples_per_piece` times, map the joints
/// back to Cartesian space, and measure the distance to the move's commanded segment (from
/// the previous move's target, starting at `start`, to this move's target).
pub fn path_deviation(
    commanded: &[GcodeMove],
    planned: &[PlannedMove],
    start: [f64; 3],
    samples_per_piece: usize,
) -> PathReport {
    let mut report = PathReport::default();
    let mut from = start;
    for (cmd, plan) in commanded.iter().zip(planned) {
        let to = [cmd.x_m, cmd.y_m, cmd.z_m];
        for w in plan.points.windows(2) {
            for k in 0..=samples_per_piece {
                let f = k as f64 / samples_per_piece as f64;
                let q = [
                    w[0].q[0] + (w[1].q[0] - w[0].q[0]) * f,
                    w[0].q[1] + (w[1].q[1] - w[0].q[1]) * f,
                    w[0].q[2] + (w[1].q[2] - w[0].q[2]) * f,
                ];
                let d = distance_to_segment(forward(q), from, to);
                report.samples += 1;
                if d > report.max_deviation_m {
                    report.max_deviation_m = d;
                    report.worst_sequence = cmd.sequence;
                }
            }
        }
        if let Some(p) = plan.points.last() {
            let d = distance_to_segment(forward(p.q), from, to);
            if d > report.max_deviation_m {
                report.max_deviation_m = d;
                report.worst_sequence = cmd.sequence;
            }
        }
        from = to;
    }
    report
}

/// Fractions of each limit used (1.0 = at the limit), per joint `[bed, arm, z]`.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct LimitReport {
    /// max |q̇| / limit at the points.
    pub velocity: [f64; 3],
    /// max |q̈| / limit at the points.
    pub acceleration: [f64; 3],
    /// max |Δq̇/Δt| / limit between consecutive points.
    pub mean_acceleration: [f64; 3],
    /// max |Δq/Δt| / velocity limit between consecutive points.
    pub mean_velocity: [f64; 3],
    /// max velocity jump at equal times (a corner) / allowed jump.
    pub velocity_jump: [f64; 3],
    /// max tool speed / commanded feedrate.
    pub feedrate: f64,
    /// Position range violations (count).
    pub out_of_range: u64,
    /// Points whose time goes backwards (count).
    pub time_reversals: u64,
}

impl LimitReport {
    /// Largest fraction of any limit.
    pub fn worst(&self) -> f64 {
        let all = [
            self.velocity,
            self.acceleration,
            self.mean_acceleration,
            self.mean_velocity,
            self.velocity_jump,
        ];
        all.iter()
            .flat_map(|a| a.iter().copied())
            .fold(self.feedrate, f64::max)
    }
}

pub fn limit_usage(
    commanded: &[GcodeMove],
    planned: &[PlannedMove],
    options: &PlannerOptions,
) -> LimitReport {
    let mut r = LimitReport::default();
    let mut previous: Option<crate::planner::TrajPoint> = None;
    for (cmd, plan) in commanded.iter().zip(planned) {
        let feed = if cmd.kind == GcodeMove::KIND_HOME {
            options.homing_speed_m_per_s
        } else {
            cmd.feedrate_m_per_s
        };
        for p in &plan.points {
            if feed > 0.0 {
                r.feedrate = r.feedrate.max(p.tool_speed / feed);
            }
            for j in 0..3 {
                let l = &options.joints[j];
                r.velocity[j] = r.velocity[j].max(p.qd[j].abs() / l.velocity);
                r.acceleration[j] = r.acceleration[j].max(p.qdd[j].abs() / l.acceleration);
                if l.position.is_some() {
                    let (min, max) = crate::planner::position_range(options, j);
                    if p.q[j] < min - 1e-12 || p.q[j] > max + 1e-12 {
                        r.out_of_range += 1;
                    }
                }
            }
            if let Some(prev) = previous {
                let dt = p.t - prev.t;
                if dt < -1e-12 {
                    r.time_reversals += 1;
                }
                for j in 0..3 {
                    let l = &options.joints[j];
                    if dt > 1e-9 {
                        r.mean_acceleration[j] = r.mean_acceleration[j]
                            .max((p.qd[j] - prev.qd[j]).abs() / dt / l.acceleration);
                        r.mean_velocity[j] =
                            r.mean_velocity[j].max((p.q[j] - prev.q[j]).abs() / dt / l.velocity);
                    } else {
                        // A corner: any jump over a limit of 0 is a violation.
                        let jump = (p.qd[j] - prev.qd[j]).abs();
                        let usage = if l.velocity_jump > 0.0 {
                            jump / l.velocity_jump
                        } else if jump > 1e-9 * l.velocity {
                            f64::INFINITY
                        } else {
                            0.0
                        };
                        r.velocity_jump[j] = r.velocity_jump[j].max(usage);
                    }
                }
            }
            previous = Some(*p);
        }
    }
    r
}
