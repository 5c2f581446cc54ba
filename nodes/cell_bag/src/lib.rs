//! rosbag2-compatible MCAP, as `ros2 bag record -s mcap` writes it (SPEC §6).
//!
//! * Header profile `ros2`; one schema per message type, encoding `ros2msg`, whose data is the
//!   full `.msg` text with dependencies ([`polar_cell_msgs::MsgType::schema_text`]).
//! * One channel per topic, message encoding `cdr`, metadata `offered_qos_profiles` (rosbag2's
//!   YAML with integer enums) and `topic_type_hash`.
//! * Messages: log time = receive time (ns), data = CDR with its 4-byte encapsulation header.
//! * Chunked (zstd or lz4) with message indexes, chunk indexes and statistics — without message
//!   indexes `rosbags` silently reads nothing.
//!
//! The writer works on any `Write + Seek`; the caller owns the file. [`metadata_yaml`] renders
//! the `metadata.yaml` of a bag directory from a finished bag's summary.

pub mod credit;
pub mod gaps;
mod meta;
mod qos;
mod reader;
mod recover;
#[cfg(feature = "node")]
pub mod repeats;
mod writer;

pub use meta::{
    bag_information, metadata_yaml, RecordedTopic, TopicStats, METADATA_VERSION, ROS_DISTRO,
};
pub use qos::{Durability, QosRecord, Reliability};
pub use reader::{read_bag, BagContents, BagInfo, BagMessage, TopicInfo};
pub use recover::{is_finished, recover, Recovery, RecoveryEnd};
pub use writer::{BagWriter, ChannelId, Compression, WriterOptions};

/// Anything that can go wrong writing or reading a bag.
#[derive(Debug, thiserror::Error)]
pub enum BagError {
    #[error("MCAP: {0}")]
    Mcap(#[from] mcap::McapError),
    #[error("schema of {type_name}: {source}")]
    Schema {
        type_name: String,
        source: polar_cell_msgs::SchemaError,
    },
    #[error("topic {topic} is already recorded with type {existing}, not {requested}")]
    TopicTypeConflict {
        topic: String,
        existing: String,
        requested: String,
    },
    #[error("unknown channel id {0}")]
    UnknownChannel(u16),
    #[error("message on {topic} is {len} bytes, too short for the CDR encapsulation header")]
    ShortMessage { topic: String, len: usize },
    #[error("not a rosbag2 MCAP file: {0}")]
    NotRos2(String),
    #[error("bag has no summary section (was finish() called?)")]
    NoSummary,
    #[error(
        "the bag was not finished: it ends after {len} bytes without its summary and closing \
         magic (its writer stopped before closing it, killed or crashed); `polar-cell bag \
         recover IN OUT` salvages its messages"
    )]
    Unfinished { len: usize },
    /// The `mcap` crate (0.26) panics on some malformed records instead of returning an
    /// error (found by fuzzing, `tests/fuzz`); the reader turns that into this error.
    #[error("malformed MCAP while {while_doing}: {detail}")]
    Malformed {
        while_doing: &'static str,
        detail: String,
    },
}

#[cfg(feature = "node")]
pub mod node;
