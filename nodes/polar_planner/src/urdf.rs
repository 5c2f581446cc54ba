//! The printer's joint limits from its URDF (`urdf/polar_cell.urdf`), validated.

use crate::timing::JointLimits;

/// A URDF that does not describe the polar cell as the planner needs it.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum UrdfError {
    #[error("URDF does not parse: {0}")]
    Parse(String),
    #[error("URDF joint `{0}` is missing")]
    MissingJoint(&'static str),
    #[error("URDF joint `{joint}`: expected {expected}, found {found}")]
    Mismatch {
        joint: &'static str,
        expected: String,
        found: String,
    },
}

/// The limits the URDF gives each planned joint: velocity and position. URDF 1.0 has no
/// acceleration, and corner velocity jumps are no URDF notion: both are left at 0 for the
/// caller to fill in from parameters.
pub fn joint_limits(text: &str) -> Result<[JointLimits; 3], UrdfError> {
    let robot = urdf_rs::read_from_string(text).map_err(|e| UrdfError::Parse(e.to_string()))?;
    let spec: [(&'static str, urdf_rs::JointType, [f64; 3]); 3] = [
        (
            "bed_theta",
            urdf_rs::JointType::Continuous,
            [0.0, 0.0, -1.0],
        ),
        ("arm_r", urdf_rs::JointType::Prismatic, [1.0, 0.0, 0.0]),
        ("z", urdf_rs::JointType::Prismatic, [0.0, 0.0, 1.0]),
    ];
    let mut out = [JointLimits {
        velocity: 0.0,
        acceleration: 0.0,
        velocity_jump: 0.0,
        position: None,
    }; 3];
    for (i, (name, kind, axis)) in spec.iter().enumerate() {
        let joint = robot
            .joints
            .iter()
            .find(|j| j.name == *name)
            .ok_or(UrdfError::MissingJoint(name))?;
        if std::mem::discriminant(&joint.joint_type) != std::mem::discriminant(kind) {
            return Err(UrdfError::Mismatch {
                joint: name,
                expected: format!("type {kind:?}"),
                found: format!("type {:?}", joint.joint_type),
            });
        }
        let found_axis = *joint.axis.xyz;
        if found_axis
            .iter()
            .zip(axis)
            .any(|(a, b)| (a - b).abs() > 1e-12)
        {
            return Err(UrdfError::Mismatch {
                joint: name,
                expected: format!("axis {axis:?} (the planner's convention)"),
                found: format!("axis {found_axis:?}"),
            });
        }
        let l = &joint.limit;
        let positive = |what: &str, v: f64| {
            if v.is_finite() && v > 0.0 {
                Ok(v)
            } else {
                Err(UrdfError::Mismatch {
                    joint: name,
                    expected: format!("a finite positive {what} limit"),
                    found: format!("{v}"),
                })
            }
        };
        out[i] = JointLimits {
            velocity: positive("velocity", l.velocity)?,
            acceleration: 0.0,
            velocity_jump: 0.0,
            position: match kind {
                urdf_rs::JointType::Prismatic => {
                    if l.lower.is_nan() || l.upper.is_nan() || l.lower >= l.upper {
                        return Err(UrdfError::Mismatch {
                            joint: name,
                            expected: "lower < upper".into(),
                            found: format!("[{}, {}]", l.lower, l.upper),
                        });
                    }
                    Some((l.lower, l.upper))
                }
                _ => None,
            },
        };
    }
    Ok(out)
}

/// The cell's URDF as shipped (`urdf/polar_cell.urdf`).
pub const POLAR_CELL_URDF: &str = include_str!("../../../urdf/polar_cell.urdf");

#[cfg(test)]
mod tests {
    use super::*;
    use crate::PlannerOptions;

    /// The planner's defaults are the shipped URDF's limits.
    #[test]
    fn shipped_urdf_matches_the_planner_defaults() {
        let limits = joint_limits(POLAR_CELL_URDF).unwrap();
        let defaults = PlannerOptions::default();
        for j in 0..3 {
            assert_eq!(limits[j].velocity, defaults.joints[j].velocity, "joint {j}");
            assert_eq!(limits[j].position, defaults.joints[j].position, "joint {j}");
        }
    }

    #[test]
    fn wrong_urdfs_are_named_errors() {
        assert!(matches!(joint_limits("<robot"), Err(UrdfError::Parse(_))));
        let no_arm = POLAR_CELL_URDF.replace("name=\"arm_r\"", "name=\"arm\"");
        assert_eq!(joint_limits(&no_arm), Err(UrdfError::MissingJoint("arm_r")));
        let flipped = POLAR_CELL_URDF.replace("<axis xyz=\"0 0 -1\"/>", "<axis xyz=\"0 0 1\"/>");
        let err = joint_limits(&flipped).unwrap_err().to_string();
        assert!(err.contains("bed_theta") && err.contains("axis"), "{err}");
    }
}
