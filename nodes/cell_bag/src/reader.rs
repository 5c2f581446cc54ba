//! Reading rosbag2 MCAP bags: summary information and the message stream.

use std::borrow::Cow;

use crate::qos::QosRecord;
use crate::BagError;

/// One topic of a bag, from its summary.
#[derive(Clone, Debug, PartialEq)]
pub struct TopicInfo {
    pub name: String,
    pub type_name: String,
    pub message_count: u64,
    pub qos: Option<QosRecord>,
    /// The channel's `ros2msg` schema text.
    pub schema_text: String,
}

/// What `bag info` prints.
#[derive(Clone, Debug, PartialEq)]
pub struct BagInfo {
    pub profile: String,
    pub message_count: u64,
    pub start_ns: u64,
    pub end_ns: u64,
    pub chunk_count: usize,
    pub compression: Vec<String>,
    pub topics: Vec<TopicInfo>,
}

impl BagInfo {
    pub fn duration_s(&self) -> f64 {
        self.end_ns.saturating_sub(self.start_ns) as f64 * 1e-9
    }
}

/// One recorded message.
#[derive(Clone, Debug)]
pub struct BagMessage<'a> {
    pub topic: String,
    pub type_name: String,
    pub log_time_ns: u64,
    pub publish_time_ns: u64,
    pub sequence: u32,
    /// CDR with its encapsulation header.
    pub data: Cow<'a, [u8]>,
}

/// A bag in memory: its info and access to its messages.
pub struct BagContents<'a> {
    bytes: &'a [u8],
    pub info: BagInfo,
}

/// Run `read`, a call into the `mcap` crate on untrusted bytes, turning a panic of that crate
/// into [`BagError::Malformed`]. (`polar-cell` keeps such a panic off the terminal: the error
/// says it.)
pub(crate) fn guarded<T>(
    while_doing: &'static str,
    read: impl FnOnce() -> Result<T, BagError>,
) -> Result<T, BagError> {
    std::panic::catch_unwind(std::panic::AssertUnwindSafe(read)).unwrap_or_else(|payload| {
        let detail = payload
            .downcast_ref::<&str>()
            .map(|s| s.to_string())
            .or_else(|| payload.downcast_ref::<String>().cloned())
            .unwrap_or_else(|| "the MCAP reader failed".to_string());
        Err(BagError::Malformed {
            while_doing,
            detail,
        })
    })
}

/// The message counts and times of a bag whose summary has no Statistics record, from its
/// messages (chunk by chunk: memory does not grow with the bag).
fn count_messages(bytes: &[u8]) -> Result<mcap::records::Statistics, BagError> {
    let mut stats = mcap::records::Statistics {
        message_start_time: u64::MAX,
        ..Default::default()
    };
    for message in mcap::read::RawMessageStream::new(bytes)? {
        let header = message?.header;
        stats.message_count += 1;
        stats.message_start_time = stats.message_start_time.min(header.log_time);
        stats.message_end_time = stats.message_end_time.max(header.log_time);
        *stats
            .channel_message_counts
            .entry(header.channel_id)
            .or_default() += 1;
    }
    if stats.message_count == 0 {
        stats.message_start_time = 0;
    }
    Ok(stats)
}

/// Read a bag's summary (the bytes of the whole file).
pub fn read_bag(bytes: &[u8]) -> Result<BagContents<'_>, BagError> {
    guarded("reading the summary", || read_summary(bytes))
}

fn read_summary(bytes: &[u8]) -> Result<BagContents<'_>, BagError> {
    let header_profile = read_profile(bytes)?;
    if !crate::is_finished(bytes) {
        return Err(BagError::Unfinished { len: bytes.len() });
    }
    if header_profile != "ros2" {
        return Err(BagError::NotRos2(format!(
            "header profile is `{header_profile}`, not `ros2`"
        )));
    }
    let summary = mcap::Summary::read(bytes)?.ok_or(BagError::NoSummary)?;
    // The Statistics record is optional in MCAP: without it the messages are counted, not
    // taken for none.
    let stats = match summary.stats.clone() {
        Some(stats) => stats,
        None => count_messages(bytes)?,
    };
    let mut topics: Vec<TopicInfo> = summary
        .channels
        .values()
        .map(|c| {
            let (type_name, schema_text) = match &c.schema {
                Some(s) => (
                    s.name.clone(),
                    String::from_utf8_lossy(&s.data).into_owned(),
                ),
                None => (String::new(), String::new()),
            };
            TopicInfo {
                name: c.topic.clone(),
                type_name,
                message_count: stats
                    .channel_message_counts
                    .get(&c.id)
                    .copied()
                    .unwrap_or(0),
                qos: c
                    .metadata
                    .get("offered_qos_profiles")
                    .and_then(|y| QosRecord::from_yaml(y)),
                schema_text,
            }
        })
        .collect();
    topics.sort_by(|a, b| a.name.cmp(&b.name));
    let mut compression: Vec<String> = summary
        .chunk_indexes
        .iter()
        .map(|c| c.compression.clone())
        .collect();
    compression.sort();
    compression.dedup();
    Ok(BagContents {
        bytes,
        info: BagInfo {
            profile: header_profile,
            message_count: stats.message_count,
            start_ns: stats.message_start_time,
            end_ns: stats.message_end_time,
            chunk_count: summary.chunk_indexes.len(),
            compression,
            topics,
        },
    })
}

fn read_profile(bytes: &[u8]) -> Result<String, BagError> {
    let mut records = mcap::read::LinearReader::new(bytes)?;
    match records.next() {
        Some(Ok(mcap::records::Record::Header(h))) => Ok(h.profile),
        Some(Err(e)) => Err(e.into()),
        _ => Err(BagError::NotRos2("no MCAP header record".into())),
    }
}

impl<'a> BagContents<'a> {
    /// Every message in file order (the recorder writes in receive order).
    pub fn messages(
        &self,
    ) -> Result<impl Iterator<Item = Result<BagMessage<'a>, BagError>> + 'a, BagError> {
        let mut stream = Some(guarded("opening the message stream", || {
            Ok(mcap::MessageStream::new(self.bytes)?)
        })?);
        Ok(std::iter::from_fn(move || {
            let next = guarded("reading a message", || {
                Ok(stream.as_mut().and_then(Iterator::next))
            });
            match next {
                Ok(m) => m.map(|m| m.map_err(BagError::from)),
                // The stream's state is unknown after a panic: end it after the error.
                Err(e) => stream.take().map(|_| Err(e)),
            }
        })
        .map(|m: Result<mcap::Message<'a>, BagError>| {
            let m = m?;
            Ok(BagMessage {
                topic: m.channel.topic.clone(),
                type_name: m
                    .channel
                    .schema
                    .as_ref()
                    .map(|s| s.name.clone())
                    .unwrap_or_default(),
                log_time_ns: m.log_time,
                publish_time_ns: m.publish_time,
                sequence: m.sequence,
                data: m.data,
            })
        }))
    }
}
