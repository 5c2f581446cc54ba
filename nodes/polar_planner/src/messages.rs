//! Plans as ROS messages.

use polar_cell_msgs::{
    Duration as RosDuration, Header, JointTrajectory, JointTrajectoryPoint, Time,
};

use crate::{PlannedMove, JOINT_NAMES};

/// The `/polar/trajectory` message of one planned move: stamped at its start, points at their
/// offsets, joints `bed_theta`, `arm_r`, `z` in SI units.
pub fn trajectory_message(plan: &PlannedMove, epoch_ns: i64) -> JointTrajectory {
    let t0 = plan.start_time();
    JointTrajectory {
        header: Header {
            stamp: Time::after(epoch_ns, t0),
            frame_id: "base_link".into(),
        },
        joint_names: JOINT_NAMES.iter().map(|s| s.to_string()).collect(),
        points: plan
            .points
            .iter()
            .map(|p| JointTrajectoryPoint {
                positions: p.q.to_vec(),
                velocities: p.qd.to_vec(),
                accelerations: p.qdd.to_vec(),
                effort: vec![],
                time_from_start: RosDuration::from_secs_f64(p.t - t0),
            })
            .collect(),
    }
}
