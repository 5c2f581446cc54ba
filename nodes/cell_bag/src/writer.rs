//! The MCAP writer with rosbag2's conventions.

use std::collections::{BTreeMap, HashMap};
use std::io::{Seek, Write};

use mcap::records::MessageHeader;
use polar_cell_msgs::{MsgType, RosMessage};

use crate::meta::{bag_information, RecordedTopic, TopicStats, ROS_DISTRO};
use crate::qos::QosRecord;
use crate::BagError;

/// Chunk compression; rosbag2 readers accept these two.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Compression {
    Zstd,
    Lz4,
}

/// How the bag is written.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct WriterOptions {
    pub compression: Compression,
    /// Uncompressed bytes per chunk; larger compresses better, smaller loses less on a crash.
    pub chunk_size_bytes: u64,
}

impl Default for WriterOptions {
    fn default() -> Self {
        WriterOptions {
            compression: Compression::Zstd,
            chunk_size_bytes: 4 * 1024 * 1024,
        }
    }
}

/// A recorded topic's channel.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
pub struct ChannelId(pub u16);

struct ChannelState {
    topic: String,
    type_name: String,
    qos: QosRecord,
    sequence: u32,
    stats: TopicStats,
}

/// Writes a rosbag2-compatible MCAP bag. Call [`BagWriter::finish`] explicitly: the summary
/// (statistics, indexes) is written there, and a bag without it reads as empty in `rosbags`.
pub struct BagWriter<W: Write + Seek> {
    inner: mcap::Writer<W>,
    schemas: HashMap<String, u16>,
    channels: HashMap<u16, ChannelState>,
    by_topic: HashMap<String, u16>,
}

/// How every bag of ours is written (`profile`, `library` in its header): chunked as
/// `options` say, with the statistics and indexes rosbag2 readers need.
pub(crate) fn mcap_options(
    options: &WriterOptions,
    profile: &str,
    library: &str,
) -> mcap::WriteOptions {
    let compression = match options.compression {
        Compression::Zstd => mcap::Compression::Zstd,
        Compression::Lz4 => mcap::Compression::Lz4,
    };
    mcap::WriteOptions::new()
        .profile(profile)
        .library(library)
        .compression(Some(compression))
        // One compressor on the writer's thread: zstd's multithreaded context takes 50 MB
        // (a third of a dry run's peak memory), and the graph's other threads have the cores.
        .compression_threads(0)
        .chunk_size(Some(options.chunk_size_bytes))
        .emit_statistics(true)
        .emit_message_indexes(true)
        .emit_chunk_indexes(true)
        .emit_summary_offsets(true)
}

impl<W: Write + Seek> BagWriter<W> {
    pub fn new(sink: W, options: &WriterOptions) -> Result<Self, BagError> {
        let inner = mcap_options(
            options,
            "ros2",
            concat!("polar-cell ", env!("CARGO_PKG_VERSION")),
        )
        .create(sink)?;
        Ok(BagWriter {
            inner,
            schemas: HashMap::new(),
            channels: HashMap::new(),
            by_topic: HashMap::new(),
        })
    }

    /// Register a topic of a known message type (idempotent for the same topic and type).
    pub fn add_topic(
        &mut self,
        topic: &str,
        msg_type: &MsgType,
        qos: QosRecord,
    ) -> Result<ChannelId, BagError> {
        let type_name = msg_type.full_name();
        if let Some(&id) = self.by_topic.get(topic) {
            let existing = &self.channels[&id].type_name;
            if *existing != type_name {
                return Err(BagError::TopicTypeConflict {
                    topic: topic.to_string(),
                    existing: existing.clone(),
                    requested: type_name,
                });
            }
            return Ok(ChannelId(id));
        }
        let schema_id = match self.schemas.get(&type_name) {
            Some(&id) => id,
            None => {
                let text = msg_type.schema_text().map_err(|source| BagError::Schema {
                    type_name: type_name.clone(),
                    source,
                })?;
                let id = self
                    .inner
                    .add_schema(&type_name, "ros2msg", text.as_bytes())?;
                self.schemas.insert(type_name.clone(), id);
                id
            }
        };
        let metadata = BTreeMap::from([
            ("offered_qos_profiles".to_string(), qos.to_yaml()),
            ("topic_type_hash".to_string(), String::new()),
        ]);
        let id = self.inner.add_channel(schema_id, topic, "cdr", &metadata)?;
        self.by_topic.insert(topic.to_string(), id);
        self.channels.insert(
            id,
            ChannelState {
                topic: topic.to_string(),
                type_name,
                qos,
                sequence: 0,
                stats: TopicStats::default(),
            },
        );
        Ok(ChannelId(id))
    }

    /// Write one message: `cdr` must start with its 4-byte encapsulation header.
    pub fn write(
        &mut self,
        channel: ChannelId,
        log_time_ns: u64,
        publish_time_ns: u64,
        cdr: &[u8],
    ) -> Result<(), BagError> {
        let state = self
            .channels
            .get_mut(&channel.0)
            .ok_or(BagError::UnknownChannel(channel.0))?;
        if cdr.len() < 4 {
            return Err(BagError::ShortMessage {
                topic: state.topic.clone(),
                len: cdr.len(),
            });
        }
        let header = MessageHeader {
            channel_id: channel.0,
            sequence: state.sequence,
            log_time: log_time_ns,
            publish_time: publish_time_ns,
        };
        state.sequence = state.sequence.wrapping_add(1);
        state.stats.record(log_time_ns);
        self.inner.write_to_known_channel(&header, cdr)?;
        Ok(())
    }

    /// Encode and write a typed message on a registered channel.
    pub fn write_message<T: RosMessage>(
        &mut self,
        channel: ChannelId,
        log_time_ns: u64,
        message: &T,
    ) -> Result<(), BagError> {
        let cdr =
            polar_cell_msgs::cdr::encode(message).map_err(|e| BagError::NotRos2(e.to_string()))?;
        self.write(channel, log_time_ns, log_time_ns, &cdr)
    }

    /// Close the current chunk and flush the sink: everything written so far can be read
    /// back (by `bag recover`) should the process die before [`BagWriter::finish`].
    pub fn flush(&mut self) -> Result<(), BagError> {
        self.inner.flush()?;
        Ok(())
    }

    /// Messages written so far.
    pub fn message_count(&self) -> u64 {
        self.channels.values().map(|c| c.stats.message_count).sum()
    }

    /// Write the summary and return the sink with per-topic statistics (for `metadata.yaml`).
    ///
    /// Like rosbag2, it first writes the `rosbag2` metadata record: rosbag2's MCAP reader takes
    /// the metadata version from it (without it, Jazzy assumes version 9 and reads the
    /// integer QoS policies of `offered_qos_profiles` as unknown ones).
    pub fn finish(mut self) -> Result<(W, Vec<RecordedTopic>), BagError> {
        let mut topics: Vec<_> = self
            .channels
            .into_values()
            .map(|c| RecordedTopic {
                topic: c.topic,
                type_name: c.type_name,
                qos: c.qos,
                stats: c.stats,
            })
            .collect();
        topics.sort_by(|a, b| a.topic.cmp(&b.topic));
        write_rosbag2_record(&mut self.inner, &topics)?;
        self.inner.finish()?;
        Ok((self.inner.into_inner(), topics))
    }
}

/// rosbag2's `rosbag2` metadata record (`serialized_metadata`: the bag information of
/// `topics`), which its MCAP reader takes the metadata version from; for every bag we finish.
pub(crate) fn write_rosbag2_record<W: Write + Seek>(
    out: &mut mcap::Writer<W>,
    topics: &[RecordedTopic],
) -> Result<(), BagError> {
    out.write_metadata(&mcap::records::Metadata {
        name: "rosbag2".into(),
        metadata: [(
            "serialized_metadata".to_string(),
            bag_information(None, topics, ROS_DISTRO),
        )]
        .into(),
    })?;
    Ok(())
}
