//! The 5-DOF hybrid machining head of the polar cell: a 3-RPS parallel mechanism (three
//! ball-screw legs carrying a tilting platform and spindle) over an XY table (SPEC §5, seed 002).
//!
//! The pure core, in millimetres and radians like the seed (ROS units only at the node's edge):
//!
//! - [`geometry`]: the mechanism's dimensions and limits, normally read from its URDF.
//! - [`pose`]: the platform pose in the seed's (Z, θ1, θ2) and roll/pitch forms, and the
//!   non-singular tilt vector used inside.
//! - [`kinematics`]: inverse kinematics (legs, parasitic X_u/Y_u/yaw, table compensation,
//!   tool-tip targets), every passive joint, forward kinematics by Newton–Raphson.
//! - [`jacobian`]: the Jacobian by the inverse-function theorem, input/output ratio,
//!   drive-force/speed evaluation and compliance (seed eq. 2.1–2.43, 4.13–4.22).
//! - [`path`]: control-point placement so that linear leg interpolation stays within a path
//!   tolerance (seed ch. 4.5).
//! - [`cl`]: the CL-data post-processor (seed Fig. 7.10).
//! - [`urdf`]: reading, validating and writing `urdf/hybrid_pkm.urdf`, and FK through its tree.
//! - [`calib`]: the geometric error model, response-surface and Levenberg–Marquardt calibration.
//!
//! `node` (feature `node`) is the ROS 2 node; everything else is data in, data out.

pub mod calib;
pub mod cl;
pub mod error;
pub mod geometry;
pub mod jacobian;
pub mod kinematics;
pub mod path;
pub mod pose;
pub mod report;
pub mod urdf;

#[cfg(feature = "node")]
pub mod node;

pub use error::KinError;
pub use geometry::{Geometry, Limits};
pub use kinematics::{ForwardSolver, IkSolution, JointPositions, ToolTarget};
pub use pose::{Pose, Tilt};

/// The URDF of the mechanism as shipped (`urdf/hybrid_pkm.urdf`), compiled in as the default.
pub const BUILTIN_URDF: &str = include_str!("../../../urdf/hybrid_pkm.urdf");
