//! The `mechanism_kin` node: `/mechanism/tool_pose` in, `/mechanism/joint_states` (every URDF
//! joint, so RViz shows the closed mechanism) and `/robot_description` (transient local) out.
//!
//! It also publishes the mechanism's transforms itself, as the cell's machine does: the fixed
//! joints on `/tf_static` once, the moving ones on `/tf` with each answer and `rate_hz` times
//! a second, stamped with the current time. A pose is commanded once and then held, and
//! tf2 listeners forget transforms older than their buffer (10 s by default), so the current
//! pose is repeated for RViz and Foxglove as a joint state publisher would; the joint states
//! themselves are not repeated, one answers each pose. `frame_prefix` (e.g. `head/`) keeps
//! the head's frames apart from the cell's, which also has a `base_link`.
//!
//! A tool pose is the tool tip in the workpiece (`table`) frame, in metres, and an orientation
//! whose z axis is the tool axis pointing spindle-ward; rotation about the tool axis is free
//! (a ball end mill). Each pose is solved, checked by forward kinematics and through the URDF
//! tree, and reported on `/diagnostics`; an unreachable pose is an error diagnostic and no
//! joint state.

use anyhow::{anyhow, Context};
use cell_runtime::tf::TfTree;
use cell_runtime::topics::publisher_qos;
use cell_runtime::{reliable_qos, CellNode, LogLevel, ParamSpec, ParamValue};
use nalgebra::Vector3;
use polar_cell_msgs::{
    Header, JointState, Point, Pose, PoseStamped, Quaternion, StringMsg, TFMessage, Time,
};

use crate::kinematics::{ForwardSolver, ToolTarget};
use crate::report::{evaluate, Evaluation};
use crate::urdf::joint_names;

/// Default node name.
pub const NODE_NAME: &str = "mechanism_kin";

pub fn param_specs() -> Vec<ParamSpec> {
    vec![
        ParamSpec::new(
            "urdf_path",
            ParamValue::String(String::new()),
            "URDF of the mechanism (empty: the built-in urdf/hybrid_pkm.urdf)",
        ),
        ParamSpec::new(
            "publish_home",
            ParamValue::Bool(true),
            "publish the home pose's joint states at start so the model shows closed at once",
        ),
        ParamSpec::new(
            "rate_hz",
            ParamValue::Double(10.0),
            "/tf of the current pose per second, stamped now (0: only with each answer)",
        )
        .range(0.0, 1000.0),
        ParamSpec::new(
            "frame_prefix",
            ParamValue::String(String::new()),
            "put before every frame name in /tf and /tf_static (e.g. head/), as robot_state_publisher does",
        ),
    ]
}

/// The target a tool pose message asks for (mm, unit axis).
pub fn target_from_pose(msg: &PoseStamped) -> ToolTarget {
    let p = &msg.pose.position;
    let q = &msg.pose.orientation;
    let norm = (q.x * q.x + q.y * q.y + q.z * q.z + q.w * q.w).sqrt();
    let (x, y, z, w) = (q.x / norm, q.y / norm, q.z / norm, q.w / norm);
    // R(q)·ẑ
    let axis = Vector3::new(
        2.0 * (x * z + w * y),
        2.0 * (y * z - w * x),
        1.0 - 2.0 * (x * x + y * y),
    );
    ToolTarget {
        tip_mm: Vector3::new(p.x, p.y, p.z) * 1e3,
        axis,
    }
}

/// The PoseStamped asking for `target`: tip in metres, orientation the shortest turn of ẑ onto
/// the tool axis (what the node reads back as the axis).
pub fn pose_message(target: &ToolTarget, stamp: Time) -> PoseStamped {
    let a = target.axis.normalize();
    let (w, x, y) = (1.0 + a.z, -a.y, a.x);
    let norm = (w * w + x * x + y * y).sqrt();
    PoseStamped {
        header: Header {
            stamp,
            frame_id: "table".into(),
        },
        pose: Pose {
            position: Point {
                x: target.tip_mm.x * 1e-3,
                y: target.tip_mm.y * 1e-3,
                z: target.tip_mm.z * 1e-3,
            },
            orientation: Quaternion {
                x: x / norm,
                y: y / norm,
                z: 0.0,
                w: w / norm,
            },
        },
    }
}

/// The joint state message of an evaluation.
pub fn joint_state(e: &Evaluation, stamp: Time) -> JointState {
    JointState {
        header: Header {
            stamp,
            frame_id: String::new(),
        },
        name: joint_names(),
        position: e.joint_values_si.clone(),
        velocity: vec![],
        effort: vec![],
    }
}

/// The moving joints' transforms for joint values in [`joint_names`] order.
pub fn transforms(tree: &TfTree, joint_values_si: &[f64], stamp: Time) -> TFMessage {
    let names = joint_names();
    TFMessage {
        transforms: tree.moving_transforms(stamp, |joint| {
            names
                .iter()
                .position(|n| n == joint)
                .and_then(|k| joint_values_si.get(k).copied())
        }),
    }
}

/// Diagnostic key/values of an evaluation.
pub fn diagnostic_values(e: &Evaluation) -> Vec<(&'static str, String)> {
    let legs = e.solution.ik.legs_mm;
    vec![
        (
            "leg_lengths_mm",
            format!("{:.6} {:.6} {:.6}", legs[0], legs[1], legs[2]),
        ),
        (
            "table_mm",
            format!(
                "{:.6} {:.6}",
                e.solution.table_mm[0], e.solution.table_mm[1]
            ),
        ),
        ("fk_residual_m", format!("{:.3e}", e.fk_residual_mm * 1e-3)),
        ("fk_iterations", e.fk_iterations.to_string()),
        (
            "loop_closure_residual_m",
            format!("{:.3e}", e.loop_closure_residual_m),
        ),
        ("io_ratio", format!("{:.6}", e.io_ratio)),
        ("leg_margin_m", format!("{:.6}", e.leg_margin_mm * 1e-3)),
        ("swing_margin_rad", format!("{:.6}", e.swing_margin_rad)),
        ("table_margin_m", format!("{:.6}", e.table_margin_mm * 1e-3)),
    ]
}

/// Run the node until an error.
pub async fn run(node: &mut CellNode) -> anyhow::Result<()> {
    let path = node.params.string("urdf_path").to_string();
    let text = if path.is_empty() {
        crate::BUILTIN_URDF.to_string()
    } else {
        std::fs::read_to_string(&path).with_context(|| format!("reading URDF {path}"))?
    };
    let (tree, geom) = crate::urdf::load(&text).map_err(|e| {
        anyhow!(
            "{}: {e}",
            if path.is_empty() {
                "built-in URDF"
            } else {
                &path
            }
        )
    })?;
    let frames = TfTree::from_urdf(&text)
        .map_err(|e| anyhow!("{e}"))?
        .with_frame_prefix(node.params.string("frame_prefix"));
    let rate_hz = node.params.f64("rate_hz");
    let description =
        node.publisher::<StringMsg>("/robot_description", &publisher_qos("/robot_description"))?;
    description
        .publish(StringMsg { data: text })
        .map_err(|e| anyhow!("/robot_description: {e:?}"))?;
    node.keep(description);
    let tf_static = node.publisher::<TFMessage>("/tf_static", &publisher_qos("/tf_static"))?;
    tf_static
        .publish(TFMessage {
            transforms: frames.static_transforms(now()),
        })
        .map_err(|e| anyhow!("/tf_static: {e:?}"))?;
    node.keep(tf_static);
    let tf = node.publisher::<TFMessage>("/tf", &publisher_qos("/tf"))?;
    let states = node.publisher::<JointState>(
        "/mechanism/joint_states",
        &publisher_qos("/mechanism/joint_states"),
    )?;
    let poses = node.subscription::<PoseStamped>("/mechanism/tool_pose", &reliable_qos(100))?;
    let mut fk = ForwardSolver::default();
    cell_runtime::cell_log!(
        node,
        LogLevel::Info,
        "3-RPS + XY table: R_in {} mm, R_out {} mm, tool {} mm",
        geom.base_radius_mm,
        geom.platform_radius_mm,
        geom.tool_length_mm
    );
    // The joint values of the pose the mechanism holds (none until one is solved).
    let mut holding: Option<Vec<f64>> = None;
    if node.params.bool("publish_home") {
        // Home: platform flat at the seed's Z = 393 mm, table centred under the tool.
        let home = ToolTarget {
            tip_mm: Vector3::new(0.0, 0.0, 393.0 - geom.tool_length_mm),
            axis: Vector3::z(),
        };
        match evaluate(&geom, &tree, &mut fk, &home) {
            Ok(e) => {
                let stamp = now();
                let _ = tf.publish(transforms(&frames, &e.joint_values_si, stamp));
                cell_runtime::publish(
                    &states,
                    joint_state(&e, stamp),
                    std::time::Duration::from_secs(5),
                )
                .await?;
                holding = Some(e.joint_values_si);
            }
            Err(err) => cell_runtime::cell_log!(
                node,
                LogLevel::Warn,
                "home pose (Z 393 mm, flat) not reachable with this URDF: {err}"
            ),
        }
    }
    let mut repeat = (rate_hz > 0.0).then(|| {
        let mut every = tokio::time::interval(std::time::Duration::from_secs_f64(1.0 / rate_hz));
        every.set_missed_tick_behavior(tokio::time::MissedTickBehavior::Delay);
        every
    });
    let mut undecodable = cell_runtime::Undecodable::default();
    loop {
        let msg = tokio::select! {
            taken = poses.async_take() => match undecodable.take(node, "/mechanism/tool_pose", taken)? {
                Some((pose, _)) => pose,
                None => continue,
            },
            _ = async { repeat.as_mut().unwrap().tick().await }, if repeat.is_some() => {
                if let Some(values) = &holding {
                    let _ = tf.publish(transforms(&frames, values, now()));
                }
                continue;
            }
        };
        let target = target_from_pose(&msg);
        match evaluate(&geom, &tree, &mut fk, &target) {
            Ok(e) => {
                // Stamped now, as the repeats are: the pose's own stamp may be a replayed
                // bag's, which tf2 would take as older than the repeats and drop.
                let _ = tf.publish(transforms(&frames, &e.joint_values_si, now()));
                cell_runtime::publish(
                    &states,
                    joint_state(&e, msg.header.stamp),
                    std::time::Duration::from_secs(5),
                )
                .await?;
                node.diagnose(0, "tool pose solved", &diagnostic_values(&e));
                holding = Some(e.joint_values_si);
            }
            Err(err) => {
                let text = format!(
                    "tool pose tip ({:.6}, {:.6}, {:.6}) m unreachable: {err}",
                    msg.pose.position.x, msg.pose.position.y, msg.pose.position.z
                );
                cell_runtime::cell_log!(node, LogLevel::Warn, "{}", text);
                node.diagnose(2, &text, &[]);
            }
        }
    }
}

fn now() -> Time {
    Time::from_nanos(cell_runtime::now_ns() as i64)
}

/// Run the node from its own command line until SIGINT/SIGTERM.
pub async fn main_with_args(argv: Vec<String>) -> anyhow::Result<()> {
    let mut node = CellNode::start_from_argv(NODE_NAME, &param_specs(), &argv)?;
    tokio::select! {
        result = run(&mut node) => result,
        _ = cell_runtime::shutdown_signal() => Ok(()),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The transforms the node publishes, composed by hand from the table to the tool tip,
    /// put the tip on the commanded target and the tip frame's z on the tool axis; chains 2
    /// and 3 end on the platform's sphere points, so the loops close in RViz too.
    #[test]
    fn published_transforms_put_the_tool_on_its_target() {
        let text = crate::BUILTIN_URDF;
        let (tree, geom) = crate::urdf::load(text).unwrap();
        let frames = TfTree::from_urdf(text).unwrap().with_frame_prefix("head/");
        let target = ToolTarget {
            tip_mm: Vector3::new(5.0, -10.0, 240.0),
            axis: Vector3::new(0.0, -(12f64.to_radians().sin()), 12f64.to_radians().cos()),
        };
        let e = evaluate(&geom, &tree, &mut ForwardSolver::default(), &target).unwrap();
        let stamp = Time::from_nanos(7);
        let mut all = frames.static_transforms(stamp);
        let moving = transforms(&frames, &e.joint_values_si, stamp).transforms;
        assert_eq!(moving.len(), 17);
        assert!(moving.iter().all(|t| t.header.stamp == stamp));
        all.extend(moving);
        let in_base = |frame: &str| {
            let mut pose = nalgebra::Isometry3::identity();
            let mut at = frame.to_string();
            while at != "head/base_link" {
                let t = all.iter().find(|t| t.child_frame_id == at).unwrap();
                let (v, q) = (t.transform.translation, t.transform.rotation);
                let step = nalgebra::Isometry3::from_parts(
                    nalgebra::Translation3::new(v.x, v.y, v.z),
                    nalgebra::UnitQuaternion::from_quaternion(nalgebra::Quaternion::new(
                        q.w, q.x, q.y, q.z,
                    )),
                );
                pose = step * pose;
                at = t.header.frame_id.clone();
            }
            pose
        };
        let tip_in_table = in_base("head/table").inverse() * in_base("head/tool_tip");
        let tip_m = tip_in_table.translation.vector;
        assert!((tip_m - target.tip_mm * 1e-3).amax() < 1e-9, "{tip_m}");
        let axis = tip_in_table.rotation * Vector3::z();
        assert!((axis - target.axis).amax() < 1e-9, "{axis}");
        let platform = in_base("head/platform");
        for chain in [2, 3] {
            let ball = in_base(&format!("head/chain{chain}_ball"))
                .translation
                .vector;
            let on_platform = platform.inverse() * nalgebra::Point3::from(ball);
            let radius_mm = on_platform.coords.xy().norm() * 1e3;
            assert!(
                (radius_mm - geom.platform_radius_mm).abs() < 1e-6,
                "{radius_mm}"
            );
            assert!(on_platform.z.abs() < 1e-9, "{}", on_platform.z);
        }
    }

    #[test]
    fn quaternion_z_axis_is_the_tool_axis() {
        // 10° about x: z axis → (0, −sin 10°, cos 10°)
        let h = 5f64.to_radians();
        let msg = PoseStamped {
            header: Header::default(),
            pose: Pose {
                position: Point {
                    x: 0.01,
                    y: 0.02,
                    z: 0.25,
                },
                orientation: Quaternion {
                    x: h.sin(),
                    y: 0.0,
                    z: 0.0,
                    w: h.cos(),
                },
            },
        };
        let t = target_from_pose(&msg);
        assert!(
            (t.axis - Vector3::new(0.0, -(10f64.to_radians().sin()), 10f64.to_radians().cos()))
                .amax()
                < 1e-15
        );
        assert!((t.tip_mm - Vector3::new(10.0, 20.0, 250.0)).amax() < 1e-12);
        // and the message the CLI writes for a target reads back as that target
        let back = target_from_pose(&pose_message(&t, Time::default()));
        assert!((back.axis - t.axis).amax() < 1e-15 && (back.tip_mm - t.tip_mm).amax() < 1e-12);
    }
}
