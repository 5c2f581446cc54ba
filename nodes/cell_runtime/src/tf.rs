//! The cell's transforms from its URDF, so RViz and Foxglove show the executed machine without
//! `robot_state_publisher`: one transform per joint, parent link → child link, that is the
//! joint's origin followed by its motion about (revolute, continuous) or along (prismatic)
//! its axis. Fixed joints go to `/tf_static` once; moving joints to `/tf` at every sample.

use nalgebra::{Isometry3, Translation3, Unit, UnitQuaternion, Vector3};
use polar_cell_msgs::{Header, Quaternion, Time, Transform, TransformStamped};

/// What a URDF the transforms cannot be made from lacks.
#[derive(Clone, Debug, PartialEq, thiserror::Error)]
pub enum TfError {
    #[error("URDF: {0}")]
    Urdf(String),
    #[error("URDF joint {joint}: type {kind} has no single-coordinate transform")]
    UnsupportedJoint { joint: String, kind: String },
    #[error("URDF joint {joint}: axis {axis:?} has no direction")]
    ZeroAxis { joint: String, axis: [f64; 3] },
    #[error("URDF joint {joint}: mimics {mimicked}, which is not a moving joint of its own")]
    BadMimic { joint: String, mimicked: String },
    #[error(
        "URDF: its moving joints {found:?} are not the cell's {expected:?} (a joint the \
         machine does not drive would stand still at 0; one it drives would not be shown)"
    )]
    JointsDiffer {
        found: Vec<String>,
        expected: Vec<String>,
    },
}

#[derive(Clone, Copy, Debug, PartialEq)]
enum Motion {
    Fixed,
    Rotate,
    Slide,
}

#[derive(Clone, Debug)]
struct JointFrame {
    name: String,
    parent: String,
    child: String,
    origin: Isometry3<f64>,
    axis: Unit<Vector3<f64>>,
    motion: Motion,
    /// `<mimic>`: this joint's position is `multiplier · q + offset` of that joint's `q`
    /// (as robot_state_publisher computes it); it is not in `/joint_states`.
    mimic: Option<(String, f64, f64)>,
}

/// The joints of a URDF as transforms.
#[derive(Clone, Debug)]
pub struct TfTree {
    joints: Vec<JointFrame>,
}

impl TfTree {
    pub fn from_urdf(text: &str) -> Result<TfTree, TfError> {
        let robot = urdf_rs::read_from_string(text).map_err(|e| TfError::Urdf(e.to_string()))?;
        let mut joints = Vec::with_capacity(robot.joints.len());
        for j in &robot.joints {
            let motion = match j.joint_type {
                urdf_rs::JointType::Fixed => Motion::Fixed,
                urdf_rs::JointType::Revolute | urdf_rs::JointType::Continuous => Motion::Rotate,
                urdf_rs::JointType::Prismatic => Motion::Slide,
                ref other => {
                    return Err(TfError::UnsupportedJoint {
                        joint: j.name.clone(),
                        kind: format!("{other:?}"),
                    })
                }
            };
            let axis = *j.axis.xyz;
            let unit = Unit::try_new(Vector3::from(axis), 1e-12);
            let axis = match (unit, motion) {
                (Some(u), _) => u,
                (None, Motion::Fixed) => Vector3::z_axis(),
                (None, _) => {
                    return Err(TfError::ZeroAxis {
                        joint: j.name.clone(),
                        axis,
                    })
                }
            };
            let [x, y, z] = *j.origin.xyz;
            let [roll, pitch, yaw] = *j.origin.rpy;
            joints.push(JointFrame {
                name: j.name.clone(),
                parent: j.parent.link.clone(),
                child: j.child.link.clone(),
                origin: Isometry3::from_parts(
                    Translation3::new(x, y, z),
                    UnitQuaternion::from_euler_angles(roll, pitch, yaw),
                ),
                axis,
                motion,
                mimic: j.mimic.as_ref().map(|m| {
                    (
                        m.joint.clone(),
                        m.multiplier.unwrap_or(1.0),
                        m.offset.unwrap_or(0.0),
                    )
                }),
            });
        }
        let tree = TfTree { joints };
        for j in &tree.joints {
            if let Some((mimicked, _, _)) = &j.mimic {
                if !tree.moving_joints().any(|name| name == mimicked) {
                    return Err(TfError::BadMimic {
                        joint: j.name.clone(),
                        mimicked: mimicked.clone(),
                    });
                }
            }
        }
        Ok(tree)
    }

    /// Put `prefix` before every frame name, as robot_state_publisher's `frame_prefix` does
    /// (e.g. `head/`), so two robots with the same link names can share `/tf`.
    pub fn with_frame_prefix(mut self, prefix: &str) -> TfTree {
        if !prefix.is_empty() {
            for j in &mut self.joints {
                j.parent = format!("{prefix}{}", j.parent);
                j.child = format!("{prefix}{}", j.child);
            }
        }
        self
    }

    /// Refuse a tree whose driven joints (moving, not mimicking) are not `expected`, in any
    /// order: the machine publishes those names, and any other would be drawn standing still.
    pub fn check_joints(&self, expected: &[&str]) -> Result<(), TfError> {
        let mut found: Vec<String> = self.moving_joints().map(str::to_string).collect();
        let mut wanted: Vec<String> = expected.iter().map(|s| s.to_string()).collect();
        found.sort();
        wanted.sort();
        if found == wanted {
            Ok(())
        } else {
            Err(TfError::JointsDiffer {
                found,
                expected: wanted,
            })
        }
    }

    /// The fixed joints' transforms (for `/tf_static`).
    pub fn static_transforms(&self, stamp: Time) -> Vec<TransformStamped> {
        self.joints
            .iter()
            .filter(|j| j.motion == Motion::Fixed)
            .map(|j| stamped(j, j.origin, stamp))
            .collect()
    }

    /// The moving joints' transforms at the positions `position(joint name)` (rad or m; a
    /// joint it does not know stays at 0), for `/tf`.
    pub fn moving_transforms(
        &self,
        stamp: Time,
        position: impl Fn(&str) -> Option<f64>,
    ) -> Vec<TransformStamped> {
        self.joints
            .iter()
            .filter(|j| j.motion != Motion::Fixed)
            .map(|j| {
                let q = match &j.mimic {
                    Some((mimicked, multiplier, offset)) => {
                        multiplier * position(mimicked).unwrap_or(0.0) + offset
                    }
                    None => position(&j.name).unwrap_or(0.0),
                };
                let motion = match j.motion {
                    Motion::Rotate => Isometry3::from_parts(
                        Translation3::identity(),
                        UnitQuaternion::from_axis_angle(&j.axis, q),
                    ),
                    _ => Isometry3::from_parts(
                        Translation3::from(j.axis.into_inner() * q),
                        UnitQuaternion::identity(),
                    ),
                };
                stamped(j, j.origin * motion, stamp)
            })
            .collect()
    }

    /// Names of the joints that move of their own (what `/joint_states` must carry; a
    /// mimic joint follows another).
    pub fn moving_joints(&self) -> impl Iterator<Item = &str> {
        self.joints
            .iter()
            .filter(|j| j.motion != Motion::Fixed && j.mimic.is_none())
            .map(|j| j.name.as_str())
    }
}

fn stamped(j: &JointFrame, pose: Isometry3<f64>, stamp: Time) -> TransformStamped {
    let t = pose.translation.vector;
    let q = pose.rotation.into_inner();
    TransformStamped {
        header: Header {
            stamp,
            frame_id: j.parent.clone(),
        },
        child_frame_id: j.child.clone(),
        transform: Transform {
            translation: polar_cell_msgs::Vector3 {
                x: t.x,
                y: t.y,
                z: t.z,
            },
            rotation: Quaternion {
                x: q.i,
                y: q.j,
                z: q.k,
                w: q.w,
            },
        },
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    const URDF: &str = include_str!("../../../urdf/polar_cell.urdf");

    fn find<'a>(ts: &'a [TransformStamped], child: &str) -> &'a TransformStamped {
        ts.iter().find(|t| t.child_frame_id == child).unwrap()
    }

    /// Compose the chain world → nozzle by hand from the transforms and compare with the
    /// polar closed form: the nozzle sits at radius r + 0 along the arm, turned by −θ (the
    /// bed turns about −z, so the tool moves by +θ relative to the bed), at height z + the
    /// fixed offsets of the URDF.
    #[test]
    fn the_nozzle_is_where_polar_kinematics_puts_it() {
        let tree = TfTree::from_urdf(URDF).unwrap();
        let moving: Vec<&str> = tree.moving_joints().collect();
        assert_eq!(moving, ["bed_theta", "z", "arm_r", "screw"]);
        let (theta, r, z) = (0.7, 0.042, 0.013);
        let stamp = Time::from_nanos(5);
        let ts = tree.moving_transforms(stamp, |name| match name {
            "bed_theta" => Some(theta),
            "arm_r" => Some(r),
            "z" => Some(z),
            "screw" => Some(1.0),
            _ => None,
        });
        assert!(ts.iter().all(|t| t.header.stamp == stamp));
        let iso = |t: &TransformStamped| {
            let v = t.transform.translation;
            let q = t.transform.rotation;
            Isometry3::from_parts(
                Translation3::new(v.x, v.y, v.z),
                UnitQuaternion::from_quaternion(nalgebra::Quaternion::new(q.w, q.x, q.y, q.z)),
            )
        };
        // The bed turns by θ about −z: a point fixed on the bed at +x goes to angle −θ.
        let bed = iso(&ts[0]);
        let p = bed * nalgebra::Point3::new(1.0, 0.0, 0.0);
        assert!((p.y - -theta.sin()).abs() < 1e-12 && (p.x - theta.cos()).abs() < 1e-12);
        // The arm slides r along x of its carriage, which rises z.
        let z_t = find(&ts, &ts[1].child_frame_id).transform.translation;
        assert!((z_t.z - z).abs() < 1e-15);
        let arm = ts[2].transform.translation;
        assert!((arm.x - r).abs() < 1e-15 && arm.y == 0.0 && arm.z == 0.0);
        // The screw turns about its own z by its angle.
        let screw = ts[3].transform.rotation;
        assert!((screw.z - 0.5f64.sin()).abs() < 1e-12 && (screw.w - 0.5f64.cos()).abs() < 1e-12);
        let fixed = tree.static_transforms(stamp);
        assert!(fixed.iter().any(|t| t.child_frame_id.contains("nozzle")));
    }

    #[test]
    fn a_floating_joint_is_refused_by_name() {
        let text = r#"<robot name="r"><link name="a"/><link name="b"/>
            <joint name="free" type="floating"><parent link="a"/><child link="b"/></joint></robot>"#;
        assert!(matches!(
            TfTree::from_urdf(text),
            Err(TfError::UnsupportedJoint { joint, .. }) if joint == "free"
        ));
        assert!(matches!(TfTree::from_urdf("<robot"), Err(TfError::Urdf(_))));
    }

    /// A mimic joint follows its joint as robot_state_publisher computes it (multiplier · q +
    /// offset), and is not a joint of its own; a URDF whose driven joints are not the cell's is
    /// refused, naming both lists.
    #[test]
    fn mimic_joints_follow_and_other_joints_are_refused() {
        let urdf = URDF.replace(
            "</robot>",
            r#"<link name="follower"/>
  <joint name="follow" type="revolute">
    <parent link="base_link"/><child link="follower"/>
    <axis xyz="0 0 1"/><limit lower="-10" upper="10" effort="1" velocity="1"/>
    <mimic joint="bed_theta" multiplier="2" offset="0.5"/>
  </joint>
</robot>"#,
        );
        let tree = TfTree::from_urdf(&urdf).unwrap();
        tree.check_joints(&["bed_theta", "arm_r", "z", "screw"])
            .unwrap();
        let ts =
            tree.moving_transforms(Time::default(), |name| (name == "bed_theta").then_some(0.3));
        let q = find(&ts, "follower").transform.rotation;
        let angle = 2.0 * q.z.atan2(q.w);
        assert!((angle - (2.0 * 0.3 + 0.5)).abs() < 1e-12, "{angle}");

        let err = tree.check_joints(&["bed_theta", "arm_r", "z", "screw", "pin"]);
        assert_eq!(
            err.unwrap_err().to_string(),
            "URDF: its moving joints [\"arm_r\", \"bed_theta\", \"screw\", \"z\"] are not \
             the cell's [\"arm_r\", \"bed_theta\", \"pin\", \"screw\", \"z\"] (a joint the \
             machine does not drive would stand still at 0; one it drives would not be shown)"
        );
        let orphan = urdf.replace("joint=\"bed_theta\"", "joint=\"nothing\"");
        assert!(matches!(
            TfTree::from_urdf(&orphan),
            Err(TfError::BadMimic { .. })
        ));
    }
}
