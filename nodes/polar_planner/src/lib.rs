//! Polar kinematics and motion planning: Cartesian G-code moves in, exact joint trajectories of
//! the polar cell (bed θ, arm r, z) out, with step timing for stepper drivers.
//!
//! * [`path`] — lines as joint-space paths, continuous θ, adaptive subdivision;
//! * [`timing`] — speed planning under joint velocity/acceleration limits;
//! * [`planner`] — the lookahead planner (centre handling, corners, dwells);
//! * [`steps`] — corrected Leib ramp and seed-001 pulse distribution, and their decoder;
//! * [`check`] — independent checks of a plan: path deviation and limits;
//! * [`preflight`] — a whole file planned and cut into steps before anything moves;
//! * [`program`] — a whole program planned into memory, for tests and emulators;
//! * [`urdf`] — the joint limits from the printer's URDF.
//!
//! Pure: no DDS, no files. The node (feature `node`) wires it to topics.

// Joint-indexed formulas (`q[j]`, `limits[j]`) read best with explicit indices.
#![allow(clippy::needless_range_loop)]

pub mod check;
pub mod messages;
pub mod path;
pub mod planner;
pub mod preflight;
pub mod program;
pub mod resume;
pub mod steps;
pub mod timing;
pub mod urdf;

pub use planner::{
    PlanError, PlannedMove, Planner, PlannerOptions, ResumePoint, ScrewLimits, TrajPoint,
    JOINT_NAMES,
};
pub use preflight::{Preflight, PreflightError, PreflightReport};
pub use program::{plan_program, Program};
pub use timing::JointLimits;

#[cfg(feature = "node")]
pub mod node;
