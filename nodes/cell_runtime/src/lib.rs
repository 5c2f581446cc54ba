//! The runtime every node of the cell shares.
//!
//! Pure parts (unit-tested without DDS): [`args`] (the ROS command line), [`params`] (typed,
//! validated parameters from files and overrides), [`names`] (expansion and remapping),
//! [`flow`] (lossless flow control of a pipeline link), [`throttle`] (repeated log lines),
//! [`tf`] (a URDF's joints as `/tf` transforms, for the cell and the machining head alike).
//! DDS parts: [`dds`] (participant on loopback, ROS-default QoS, node with declared parameters,
//! diagnostics, rosout, shutdown on SIGINT/SIGTERM), [`service`] (replies that wait for their
//! client's reader).

pub mod args;
pub mod dds;
pub mod delivery;
pub mod flow;
pub mod graph;
pub mod names;
pub mod params;
pub mod replay;
pub mod service;
pub mod tf;
pub mod throttle;
pub mod topics;

pub use args::{ArgsError, RosArgs};
pub use dds::{
    best_effort_qos, now_ns, parse_service_mapping, publish, reliable_qos, resolve_node,
    ros_default_qos, shutdown_signal, transient_local_qos, wait_delivered, CellNode, Network,
    Offered, ServiceMapping, ShutdownSignal, ShutdownSignals, Undecodable, Wire, PUBLISH_PATIENCE,
};
pub use delivery::Undelivered;
pub use names::{NameError, NameResolver};
pub use params::{ParamError, ParamSpec, ParamValue, Params};
pub use ros2_client::ros2::LogLevel;
/// What arrives with a message (its publisher's [`Gid`] among it), for nodes that name a sender.
pub use ros2_client::{Gid, MessageInfo};

/// Log to stderr through `tracing`, filtered by `RUST_LOG` or else `default_filter`. RustDDS's
/// own warnings are errors-only by default, and its multicast-join complaints on a loopback
/// without multicast are silenced.
pub fn init_logging(default_filter: &str) {
    let filter = tracing_subscriber::EnvFilter::try_from_default_env().unwrap_or_else(|_| {
        format!(
            "{default_filter},rustdds=error,rustdds::network::udp_listener=off,ros2_client=error"
        )
        .into()
    });
    tracing_subscriber::fmt()
        .with_env_filter(filter)
        .with_writer(std::io::stderr)
        .init();
}

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
