//! Time-optimal speed along a joint-space path under joint velocity and acceleration limits.
//!
//! Along the path, `q̇ = q'(s)·v` and `q̈ = q''(s)·v² + q'(s)·a` with `v = ds/dt`, `a = dv/dt`.
//! The speed is planned on the path's nodes in `v²` (constant `a` between nodes makes `v²`
//! linear in `s`): a forward pass takes the largest admissible acceleration, a backward pass
//! the largest admissible deceleration, each capped by the node's speed limit — the numerical
//! integration scheme of time-optimal path parameterisation. Joint limits are applied with a
//! safety factor so the constraint also holds between nodes, where `q'`, `q''` vary.

use crate::path::Joints;

/// Limits of one joint.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct JointLimits {
    /// |q̇| bound (rad/s or m/s).
    pub velocity: f64,
    /// |q̈| bound (rad/s² or m/s²).
    pub acceleration: f64,
    /// Largest instantaneous velocity change at a corner between moves (rad/s or m/s) — the
    /// "jerk" of Marlin-style planners, which lets the machine go round corners without
    /// stopping.
    pub velocity_jump: f64,
    /// Position range (m for prismatic joints); `None` for the continuous bed.
    pub position: Option<(f64, f64)>,
}

/// What the speed planner needs to know of one node.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct SpeedNode {
    /// Path length from the previous node (0 at a corner between moves).
    pub ds: f64,
    pub dq: Joints,
    pub ddq: Joints,
    /// Speed cap at this node, squared (feedrate, joint velocities, corner).
    pub vmax2: f64,
}

/// The limits the planner applies, already scaled by the safety factor.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct SpeedLimits {
    pub joint_velocity: Joints,
    pub joint_acceleration: Joints,
    pub tool_acceleration: f64,
}

impl SpeedLimits {
    /// Speed cap² from joint velocities and from the curvature term `q''v²` (kept within half
    /// the acceleration limit, so a range of admissible `a` always remains).
    pub fn vmax2(&self, dq: &Joints, ddq: &Joints, feed: f64) -> f64 {
        let mut v2 = feed * feed;
        for j in 0..3 {
            if dq[j].abs() > 1e-15 {
                v2 = v2.min((self.joint_velocity[j] / dq[j]).powi(2));
            }
            if ddq[j].abs() > 1e-15 {
                v2 = v2.min(0.5 * self.joint_acceleration[j] / ddq[j].abs());
            }
        }
        v2
    }

    /// The admissible path acceleration `[lo, hi]` at a node moving at speed² `v2`.
    pub fn accel_range(&self, n: &SpeedNode, v2: f64) -> (f64, f64) {
        let (mut lo, mut hi) = (-self.tool_acceleration, self.tool_acceleration);
        for j in 0..3 {
            let qd = n.dq[j];
            if qd.abs() < 1e-15 {
                continue;
            }
            let c = n.ddq[j] * v2;
            let amax = self.joint_acceleration[j];
            let (mut l, mut h) = ((-amax - c) / qd, (amax - c) / qd);
            if qd < 0.0 {
                std::mem::swap(&mut l, &mut h);
            }
            lo = lo.max(l);
            hi = hi.min(h);
        }
        (lo, hi)
    }
}

/// Plan `v²` at every node: starting at `entry_v2`, ending at rest. `out` gets one value per
/// node. The entry may only be lowered if it was infeasible (it then reports false).
pub fn plan_speeds(
    nodes: &[SpeedNode],
    entry_v2: f64,
    limits: &SpeedLimits,
    out: &mut Vec<f64>,
) -> bool {
    out.clear();
    if nodes.is_empty() {
        return true;
    }
    out.extend(nodes.iter().map(|n| n.vmax2));
    out[0] = out[0].min(entry_v2);
    let last = nodes.len() - 1;
    out[last] = 0.0;
    // Forward: accelerate as hard as the node we leave and the node we reach allow.
    for i in 1..nodes.len() {
        let ds = nodes[i].ds;
        if ds == 0.0 {
            out[i] = out[i].min(out[i - 1]);
            continue;
        }
        let a_leave = limits.accel_range(&nodes[i - 1], out[i - 1]).1.max(0.0);
        let mut v2 = out[i].min(out[i - 1] + 2.0 * a_leave * ds);
        for _ in 0..2 {
            let a = (v2 - out[i - 1]) / (2.0 * ds);
            let hi = limits.accel_range(&nodes[i], v2).1.max(0.0);
            if a <= hi {
                break;
            }
            v2 = out[i - 1] + 2.0 * hi * ds;
        }
        out[i] = v2;
    }
    // Backward: decelerate as hard as both nodes allow, so the path ends at rest.
    for i in (0..last).rev() {
        let ds = nodes[i + 1].ds;
        if ds == 0.0 {
            out[i] = out[i].min(out[i + 1]);
            continue;
        }
        let d_reach = (-limits.accel_range(&nodes[i + 1], out[i + 1]).0).max(0.0);
        let mut v2 = out[i].min(out[i + 1] + 2.0 * d_reach * ds);
        for _ in 0..2 {
            let a = (out[i + 1] - v2) / (2.0 * ds);
            let lo = limits.accel_range(&nodes[i], v2).0.min(0.0);
            if a >= lo {
                break;
            }
            v2 = out[i + 1] - 2.0 * lo * ds;
        }
        out[i] = out[i].min(v2);
    }
    out[0] >= entry_v2 * (1.0 - 1e-9) - 1e-18
}

#[cfg(test)]
mod tests {
    use super::*;

    fn straight(n: usize, ds: f64, feed: f64) -> Vec<SpeedNode> {
        (0..n)
            .map(|i| SpeedNode {
                ds: if i == 0 { 0.0 } else { ds },
                dq: [0.0, 1.0, 0.0],
                ddq: [0.0; 3],
                vmax2: feed * feed,
            })
            .collect()
    }

    fn limits() -> SpeedLimits {
        SpeedLimits {
            joint_velocity: [10.0, 0.2, 0.1],
            joint_acceleration: [10.0, 2.0, 1.0],
            tool_acceleration: 100.0,
        }
    }

    /// A straight radial move is a trapezoid: v² rises at 2a, cruises, falls at 2a.
    #[test]
    fn straight_move_is_a_trapezoid_in_v_squared() {
        let nodes = straight(101, 0.001, 0.05);
        let mut v2 = Vec::new();
        assert!(plan_speeds(&nodes, 0.0, &limits(), &mut v2));
        // a = 2 m/s² (arm limit): v² = 2·a·s until 0.05² = 0.0025 at s = 0.625 mm.
        assert!((v2[0]).abs() < 1e-15);
        assert!((v2[1] - 4.0 * 0.001 * 0.5).abs() < 1e-12 || (v2[1] - 0.0025).abs() < 1e-12);
        assert!((v2[50] - 0.0025).abs() < 1e-12);
        assert_eq!(v2[100], 0.0);
        for w in v2.windows(2) {
            let a = (w[1] - w[0]) / (2.0 * 0.001);
            assert!(a.abs() <= 2.0 + 1e-9, "acceleration {a}");
        }
    }

    #[test]
    fn short_move_peaks_without_reaching_the_feed() {
        let nodes = straight(3, 0.0005, 1.0);
        let mut v2 = Vec::new();
        plan_speeds(&nodes, 0.0, &limits(), &mut v2);
        assert!((v2[1] - 2.0 * 2.0 * 0.0005).abs() < 1e-12);
        assert_eq!((v2[0], v2[2]), (0.0, 0.0));
    }

    #[test]
    fn infeasible_entry_is_reported() {
        let nodes = straight(3, 0.0001, 1.0);
        let mut v2 = Vec::new();
        assert!(!plan_speeds(&nodes, 0.04, &limits(), &mut v2));
    }
}
