//! ROS 2 message types of the polar printing cell.
//!
//! One source of truth: every type here mirrors, field by field and in order, a `.msg` file.
//! Our own types live in `msg/` (which together with `package.xml` and `CMakeLists.txt` is the
//! colcon-buildable interface package `polar_cell_msgs`); the standard ROS types the suite uses
//! live in `ros_std/<package>/msg/`. The same files are compiled in with `include_str!` and become
//! the `ros2msg` schema text written into MCAP bags (see [`MsgType::schema_text`]).
//!
//! Serialization is CDR little-endian, as on the wire (see [`cdr`]).

pub mod cdr;
pub mod checkpoint;
mod schema;
mod types;

pub use schema::{find, MsgType, SchemaError, ALL_TYPES};
pub use types::*;

/// A Rust type that mirrors a ROS 2 message definition.
pub trait RosMessage:
    serde::Serialize + serde::de::DeserializeOwned + Clone + std::fmt::Debug + Send + Sync + 'static
{
    /// The definition this type mirrors.
    const TYPE: &'static MsgType;
}
