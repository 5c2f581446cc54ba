//! Before a node goes away: its subscribers have what it published.
//!
//! A reliable DDS writer repairs a lost sample only while it exists, and RustDDS repairs on
//! its heartbeat, once a second. A node that publishes its last messages and then drops its
//! writers loses them for every reader still waiting for a repair: `bag play` followed by a
//! recorder lost the last 32 moves of a file this way on a loaded machine. So a node that is
//! about to exit waits, bounded, until every matched reliable reader of each of its writers
//! has acknowledged every sample written so far — and when one does not, says which reader
//! (and, from `ros_discovery_info`, which node) held it up.
//!
//! The waiting is blocking (a condition variable inside RustDDS): run it on a blocking
//! thread, as [`crate::CellNode::wait_delivered`] does.

use std::time::{Duration, Instant};

use ros2_client::{Gid, Node};
use rustdds::{Acknowledgments, GUID};

/// One writer of a node, under the (resolved) topic it publishes.
#[derive(Clone)]
pub struct PublishedTopic {
    pub topic: String,
    acknowledgments: Acknowledgments,
}

impl PublishedTopic {
    pub fn new(topic: String, acknowledgments: Acknowledgments) -> PublishedTopic {
        PublishedTopic {
            topic,
            acknowledgments,
        }
    }

    /// The reliable readers the writer has matched now.
    pub fn matched_readers(&self) -> Vec<GUID> {
        self.acknowledgments.matched_readers()
    }
}

/// A matched reader that had not acknowledged everything a writer wrote when the wait ended.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Undelivered {
    pub topic: String,
    /// The reader's GUID, as Cyclone DDS prints one (four 32-bit words in hex).
    pub reader: String,
    /// The ROS node the reader belongs to, from `ros_discovery_info` (a plain DDS reader,
    /// such as a Cyclone DDS application that is not a ROS node, has none).
    pub node: Option<String>,
    /// Samples the writer wrote that the reader had not acknowledged.
    pub samples: i64,
}

impl std::fmt::Display for Undelivered {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(
            f,
            "{}: {} sample{} not acknowledged by reader {} ({})",
            self.topic,
            self.samples,
            if self.samples == 1 { "" } else { "s" },
            self.reader,
            match &self.node {
                Some(node) => format!("node {node}"),
                None => "not a ROS node".to_string(),
            }
        )
    }
}

/// A GUID as Cyclone DDS and `ros2 topic info -v` print it: four 32-bit words in hex.
pub fn guid_text(guid: GUID) -> String {
    let bytes = guid.to_bytes();
    bytes
        .chunks(4)
        .map(|w| format!("{:x}", u32::from_be_bytes([w[0], w[1], w[2], w[3]])))
        .collect::<Vec<_>>()
        .join(":")
}

/// Waits until every matched reliable reader of every writer in `published` has acknowledged
/// every sample written before the call, or until `max_wait` has passed; then lists the
/// readers that had not (empty: all delivered). Blocking.
pub fn wait_acknowledged(
    published: &[PublishedTopic],
    max_wait: Duration,
) -> Vec<(String, GUID, i64)> {
    let deadline = Instant::now() + max_wait;
    // What each writer had written when the wait began: later samples do not extend it.
    let targets: Vec<_> = published
        .iter()
        .map(|p| (p, p.acknowledgments.last_written()))
        .collect();
    for (p, through) in &targets {
        let left = deadline.saturating_duration_since(Instant::now());
        p.acknowledgments.wait_through(*through, left);
    }
    targets
        .iter()
        .flat_map(|(p, through)| {
            p.acknowledgments
                .unacknowledged_readers(*through)
                .into_iter()
                .map(move |(reader, first_missing)| {
                    let samples = i64::from(*through) - i64::from(first_missing) + 1;
                    (p.topic.clone(), reader, samples)
                })
        })
        .collect()
}

/// [`wait_acknowledged`]'s readers, named through `node`'s view of the ROS graph.
pub fn name_readers(node: &Node, lagging: Vec<(String, GUID, i64)>) -> Vec<Undelivered> {
    let announced = node.external_nodes();
    lagging
        .into_iter()
        .map(|(topic, reader, samples)| Undelivered {
            topic,
            reader: guid_text(reader),
            node: crate::graph::node_of_reader(&announced, &Gid::from(reader)),
            samples,
        })
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn guids_read_as_cyclone_prints_them() {
        let guid = GUID::from_bytes([
            0x01, 0x0f, 0x3a, 0x4b, 0x00, 0x00, 0x12, 0x34, 0xde, 0xad, 0xbe, 0xef, 0x00, 0x00,
            0x15, 0x07,
        ]);
        assert_eq!(guid_text(guid), "10f3a4b:1234:deadbeef:1507");
    }

    #[test]
    fn an_undelivered_reader_is_named_with_its_node_or_as_plain_dds() {
        let mut u = Undelivered {
            topic: "/joint_states".into(),
            reader: "10f3a4b:1234:deadbeef:1507".into(),
            node: Some("/foxglove_bridge".into()),
            samples: 3,
        };
        assert_eq!(
            u.to_string(),
            "/joint_states: 3 samples not acknowledged by reader 10f3a4b:1234:deadbeef:1507 \
             (node /foxglove_bridge)"
        );
        u.node = None;
        u.samples = 1;
        assert_eq!(
            u.to_string(),
            "/joint_states: 1 sample not acknowledged by reader 10f3a4b:1234:deadbeef:1507 \
             (not a ROS node)"
        );
    }
}
