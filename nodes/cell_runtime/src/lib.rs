//! The runtime every node of the cell shares.
//!
//! Pure parts (unit-tested without DDS): [`args`] (the ROS command line), [`params`] (typed,
//! validated parameters from files and overrides), [`names`] (expansion and remapping).
//! DDS parts: [`dds`] (participant on loopback, ROS-default QoS, node with declared parameters,
//! diagnostics, rosout, shutdown on SIGINT/SIGTERM).

pub mod args;
pub mod dds;
pub mod names;
pub mod params;

pub use args::{ArgsError, RosArgs};
pub use dds::{
    now_ns, reliable_qos, ros_default_qos, shutdown_signal, transient_local_qos, CellNode, Network,
};
pub use names::{NameError, NameResolver};
pub use params::{ParamError, ParamSpec, ParamValue, Params};
pub use ros2_client::ros2::LogLevel;

/// Why a node could not start.
#[derive(Debug, thiserror::Error)]
pub enum RuntimeError {
    #[error("command line: {0}")]
    Args(#[from] ArgsError),
    #[error("parameters: {0}")]
    Params(#[from] ParamError),
    #[error("{0}")]
    Name(#[from] NameError),
    #[error("--params-file {path}: {problem}")]
    ParamsFile { path: String, problem: String },
    #[error("environment variable {variable}: {problem}")]
    Environment {
        variable: &'static str,
        problem: String,
    },
    #[error("DDS: {0}")]
    Dds(String),
}
