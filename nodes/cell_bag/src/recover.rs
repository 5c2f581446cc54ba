//! Salvaging a bag whose writer died: every message of every complete chunk, and what is
//! intact of a chunk cut short, into a new, finished bag.
//!
//! An MCAP file is a sequence of records (opcode, length, body) between two magic strings;
//! its summary (indexes, statistics) is written last, so a killed recorder leaves a file
//! without one — and without the closing magic, which is what readers check first. Reading
//! from the front instead, record by record, finds every schema, channel and chunk up to
//! where the file ends. A chunk is one compressed stream; one cut short still decompresses
//! up to where its bytes stop (zstd and lz4 frames decode block by block), and the records in
//! that prefix that are whole are kept. The recorder closes a chunk every `flush_period_s`,
//! so at most that much of a print lives only in memory.
//!
//! Sans I/O: bytes in, a bag written to any `Write + Seek` out.

use std::collections::HashMap;
use std::io::{Read, Seek, Write};

use mcap::records::{op, MessageHeader, Record};

use crate::meta::{RecordedTopic, TopicStats};
use crate::qos::QosRecord;
use crate::writer::{write_rosbag2_record, WriterOptions};
use crate::BagError;

/// How the salvage ended.
#[derive(Clone, Debug, PartialEq, Eq)]
pub enum RecoveryEnd {
    /// The data section ended properly (the file had only lost its summary, or nothing).
    Complete,
    /// The file stops inside a record at this offset.
    Truncated { at: u64 },
    /// A record at this offset cannot be read.
    Damaged { at: u64, what: String },
}

/// What [`recover`] found and kept.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct Recovery {
    pub messages: u64,
    /// Chunks read whole.
    pub complete_chunks: u64,
    /// Messages kept from a chunk cut short or damaged.
    pub partial_chunk_messages: u64,
    /// Messages whose channel record was lost (not kept).
    pub orphan_messages: u64,
    /// Bytes of the input up to the end of the last record read whole.
    pub intact_bytes: u64,
    pub end: RecoveryEnd,
}

const CHUNK_LIMIT_BYTES: u64 = 1 << 30;

/// Copies schemas, channels and messages into the new bag, renumbering nothing the reader
/// would see: topics, schemas, metadata, times and sequence numbers are kept.
struct Copier<W: Write + Seek> {
    out: mcap::Writer<W>,
    schemas: HashMap<u16, u16>,
    channels: HashMap<u16, u16>,
    /// Channels whose schema was not (yet) seen.
    waiting: HashMap<u16, mcap::records::Channel>,
    /// The output's schemas' names (message types), by output schema id.
    schema_names: HashMap<u16, String>,
    /// What the new bag's `rosbag2` metadata record lists, by output channel id.
    topics: HashMap<u16, RecordedTopic>,
    messages: u64,
    orphans: u64,
}

impl<W: Write + Seek> Copier<W> {
    /// Take one record of the data section (or of a chunk).
    fn take(&mut self, record: Record<'_>) -> Result<(), BagError> {
        match record {
            Record::Schema { header, data } => {
                let id = self.out.add_schema(&header.name, &header.encoding, &data)?;
                self.schemas.insert(header.id, id);
                self.schema_names.insert(id, header.name.clone());
                let ready: Vec<u16> = self
                    .waiting
                    .iter()
                    .filter(|(_, c)| c.schema_id == header.id)
                    .map(|(&k, _)| k)
                    .collect();
                for k in ready {
                    let channel = self.waiting.remove(&k).expect("just listed");
                    self.add_channel(channel)?;
                }
            }
            Record::Channel(channel) => {
                if channel.schema_id == 0 || self.schemas.contains_key(&channel.schema_id) {
                    self.add_channel(channel)?;
                } else {
                    self.waiting.insert(channel.id, channel);
                }
            }
            Record::Message { header, data } => match self.channels.get(&header.channel_id) {
                Some(&channel_id) => {
                    self.out.write_to_known_channel(
                        &MessageHeader {
                            channel_id,
                            ..header
                        },
                        &data,
                    )?;
                    self.messages += 1;
                    if let Some(topic) = self.topics.get_mut(&channel_id) {
                        topic.stats.record(header.log_time);
                    }
                }
                None => self.orphans += 1,
            },
            _ => {}
        }
        Ok(())
    }

    fn add_channel(&mut self, channel: mcap::records::Channel) -> Result<(), BagError> {
        let schema = match channel.schema_id {
            0 => 0,
            id => self.schemas[&id],
        };
        let id = self.out.add_channel(
            schema,
            &channel.topic,
            &channel.message_encoding,
            &channel.metadata,
        )?;
        self.channels.insert(channel.id, id);
        self.topics.insert(
            id,
            RecordedTopic {
                topic: channel.topic.clone(),
                type_name: self.schema_names.get(&schema).cloned().unwrap_or_default(),
                qos: channel
                    .metadata
                    .get("offered_qos_profiles")
                    .and_then(|q| QosRecord::from_yaml(q))
                    .unwrap_or(QosRecord::ROS_DEFAULT),
                stats: TopicStats::default(),
            },
        );
        Ok(())
    }

    /// The `rosbag2` metadata record, as [`crate::BagWriter::finish`] writes it, then the
    /// summary.
    fn finish(mut self) -> Result<(), BagError> {
        let mut topics: Vec<RecordedTopic> = self.topics.into_values().collect();
        topics.sort_by(|a, b| a.topic.cmp(&b.topic));
        write_rosbag2_record(&mut self.out, &topics)?;
        self.out.finish()?;
        Ok(())
    }
}

/// One record's opcode and body at `at`, if the bytes hold it whole; else how much of its
/// body there is.
fn record_at(bytes: &[u8], at: usize) -> Result<(u8, &[u8]), &[u8]> {
    let rest = &bytes[at.min(bytes.len())..];
    if rest.len() < 9 {
        return Err(&[]);
    }
    let len = u64::from_le_bytes(rest[1..9].try_into().expect("8 bytes"));
    let body = &rest[9..];
    match usize::try_from(len) {
        Ok(len) if len <= body.len() => Ok((rest[0], &body[..len])),
        _ => Err(body),
    }
}

/// A chunk body (whole or cut short): its records' bytes, decompressed as far as they go.
fn chunk_records(body: &[u8]) -> Result<Vec<u8>, String> {
    let mut cursor = std::io::Cursor::new(body);
    let read_u64 = |c: &mut std::io::Cursor<&[u8]>| -> Result<u64, String> {
        let mut b = [0u8; 8];
        c.read_exact(&mut b).map_err(|_| "chunk header cut short")?;
        Ok(u64::from_le_bytes(b))
    };
    let _start = read_u64(&mut cursor)?;
    let _end = read_u64(&mut cursor)?;
    let uncompressed_size = read_u64(&mut cursor)?.min(CHUNK_LIMIT_BYTES);
    let mut crc_and_len = [0u8; 8];
    cursor
        .read_exact(&mut crc_and_len)
        .map_err(|_| "chunk header cut short")?;
    let name_len = u32::from_le_bytes(crc_and_len[4..8].try_into().expect("4 bytes")) as usize;
    let mut name = vec![0u8; name_len.min(64)];
    if name_len > 64 {
        return Err(format!("compression name of {name_len} bytes"));
    }
    cursor
        .read_exact(&mut name)
        .map_err(|_| "chunk header cut short")?;
    let records_len = read_u64(&mut cursor)?;
    let start = cursor.position() as usize;
    let available = &body[start..];
    let compressed = &available[..available.len().min(records_len as usize)];
    let limit = uncompressed_size;
    let mut out = Vec::new();
    let mut drain = |reader: &mut dyn Read| {
        // Decode until the stream ends or breaks off: what came out before stays.
        let mut buf = [0u8; 64 * 1024];
        while (out.len() as u64) < limit {
            match reader.read(&mut buf) {
                Ok(0) | Err(_) => break,
                Ok(n) => out.extend_from_slice(&buf[..n]),
            }
        }
    };
    match name.as_slice() {
        b"" => out.extend_from_slice(compressed),
        b"zstd" => {
            let mut decoder = zstd::stream::read::Decoder::with_buffer(compressed)
                .map_err(|e| format!("zstd: {e}"))?;
            drain(&mut decoder);
        }
        b"lz4" => {
            let mut decoder = lz4::Decoder::new(compressed).map_err(|e| format!("lz4: {e}"))?;
            drain(&mut decoder);
        }
        other => {
            return Err(format!(
                "unknown chunk compression {:?}",
                String::from_utf8_lossy(other)
            ))
        }
    }
    out.truncate(limit as usize);
    Ok(out)
}

/// Salvage the bag in `bytes` into `out` (written as [`crate::BagWriter`] writes, with
/// `options`), and say what was kept.
pub fn recover<W: Write + Seek>(
    bytes: &[u8],
    out: W,
    options: &WriterOptions,
) -> Result<Recovery, BagError> {
    if !bytes.starts_with(mcap::MAGIC) {
        return Err(BagError::NotRos2("no MCAP magic at the start".into()));
    }
    let profile = match record_at(bytes, mcap::MAGIC.len()) {
        Ok((op::HEADER, body)) => match parse(op::HEADER, body)? {
            Record::Header(h) => h.profile,
            _ => unreachable!("parsed as a header"),
        },
        _ => return Err(BagError::NotRos2("no MCAP header record".into())),
    };
    // What is not a rosbag2 bag is not salvaged into one (the reader would refuse it).
    if profile != "ros2" {
        return Err(BagError::NotRos2(format!(
            "header profile is `{profile}`, not `ros2`"
        )));
    }
    let writer = crate::writer::mcap_options(
        options,
        &profile,
        concat!("polar-cell ", env!("CARGO_PKG_VERSION"), " (recovered)"),
    )
    .create(out)?;
    let mut copier = Copier {
        out: writer,
        schemas: HashMap::new(),
        channels: HashMap::new(),
        waiting: HashMap::new(),
        schema_names: HashMap::new(),
        topics: HashMap::new(),
        messages: 0,
        orphans: 0,
    };
    let mut at = mcap::MAGIC.len();
    let mut complete_chunks = 0;
    let mut partial_chunk_messages = 0;
    let end = loop {
        let (opcode, body, whole) = match record_at(bytes, at) {
            Ok((opcode, body)) => (opcode, body, true),
            Err(_) if at == bytes.len() => break RecoveryEnd::Truncated { at: at as u64 },
            Err(partial) => (bytes[at], partial, false),
        };
        if opcode == op::DATA_END {
            break RecoveryEnd::Complete;
        }
        if opcode == op::CHUNK {
            let decompressed = chunk_records(body);
            let mut inner_at = 0;
            let before = copier.messages;
            let mut intact = true;
            if let Ok(records) = &decompressed {
                while inner_at < records.len() {
                    let Ok((inner_op, inner_body)) = record_at(records, inner_at) else {
                        intact = false;
                        break;
                    };
                    match parse(inner_op, inner_body) {
                        Ok(record) => copier.take(record)?,
                        Err(_) => {
                            intact = false;
                            break;
                        }
                    }
                    inner_at += 9 + inner_body.len();
                }
            }
            if whole && intact && decompressed.is_ok() {
                complete_chunks += 1;
            } else {
                partial_chunk_messages += copier.messages - before;
            }
            if !whole {
                break RecoveryEnd::Truncated { at: at as u64 };
            }
            if let Err(what) = decompressed {
                break RecoveryEnd::Damaged {
                    at: at as u64,
                    what,
                };
            }
        } else if !whole {
            break RecoveryEnd::Truncated { at: at as u64 };
        } else {
            match parse(opcode, body) {
                Ok(record) => copier.take(record)?,
                Err(e) => {
                    break RecoveryEnd::Damaged {
                        at: at as u64,
                        what: e.to_string(),
                    }
                }
            }
        }
        at += 9 + body.len();
    };
    let intact_bytes = match &end {
        RecoveryEnd::Complete => at as u64,
        RecoveryEnd::Truncated { at } | RecoveryEnd::Damaged { at, .. } => *at,
    };
    let (messages, orphans) = (copier.messages, copier.orphans);
    copier.finish()?;
    Ok(Recovery {
        messages,
        complete_chunks,
        partial_chunk_messages,
        orphan_messages: orphans,
        intact_bytes,
        end,
    })
}

/// One record, parsed; the `mcap` crate's panics on malformed records (see
/// [`crate::reader`]) answered as errors.
fn parse(opcode: u8, body: &[u8]) -> Result<Record<'_>, BagError> {
    crate::reader::guarded("parsing a record", || {
        Ok(mcap::read::parse_record(opcode, body)?)
    })
}

/// Whether `bytes` end as a finished MCAP file does (the closing magic after a footer).
pub fn is_finished(bytes: &[u8]) -> bool {
    bytes.len() >= 2 * mcap::MAGIC.len() && bytes.ends_with(mcap::MAGIC)
}

#[cfg(test)]
mod tests;
