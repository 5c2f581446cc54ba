use super::*;
use crate::{read_bag, BagWriter, Compression, QosRecord};
use polar_cell_msgs::{GcodeProgress, Header, JointState, RosMessage, StringMsg, Time};
use proptest::prelude::*;

/// A bag of `n` messages on three topics, in chunks of `chunk_size_bytes`.
fn bag(n: usize, chunk_size_bytes: u64, compression: Compression) -> Vec<u8> {
    let options = WriterOptions {
        compression,
        chunk_size_bytes,
    };
    let mut writer = BagWriter::new(std::io::Cursor::new(Vec::new()), &options).unwrap();
    let q = QosRecord::ROS_DEFAULT;
    let states = writer
        .add_topic("/joint_states", JointState::TYPE, q)
        .unwrap();
    let text = writer.add_topic("/text", StringMsg::TYPE, q).unwrap();
    let progress = writer
        .add_topic("/gcode/progress", GcodeProgress::TYPE, q)
        .unwrap();
    for k in 0..n {
        let t = 1_000_000_000 + k as u64 * 20_000_000;
        match k % 3 {
            0 => writer.write_message(
                states,
                t,
                &JointState {
                    header: Header {
                        stamp: Time::after(0, t as f64 * 1e-9),
                        frame_id: String::new(),
                    },
                    name: vec!["bed_theta".into(), "arm_r".into()],
                    position: vec![k as f64 * 1e-3, 0.1],
                    velocity: vec![0.0, 0.0],
                    effort: vec![],
                },
            ),
            1 => writer.write_message(
                text,
                t,
                &StringMsg {
                    data: format!("message {k}: {}", "x".repeat(k % 50)),
                },
            ),
            _ => writer.write_message(
                progress,
                t,
                &GcodeProgress {
                    lines_read: k as u32,
                    ..GcodeProgress::default()
                },
            ),
        }
        .unwrap();
    }
    writer.finish().unwrap().0.into_inner()
}

/// (topic, log time, data) of every message, in file order.
fn messages(bytes: &[u8]) -> Vec<(String, u64, Vec<u8>)> {
    read_bag(bytes)
        .unwrap()
        .messages()
        .unwrap()
        .map(|m| {
            let m = m.unwrap();
            (m.topic, m.log_time_ns, m.data.into_owned())
        })
        .collect()
}

fn recovered(bytes: &[u8]) -> (Recovery, Vec<u8>) {
    let mut out = std::io::Cursor::new(Vec::new());
    let recovery = recover(bytes, &mut out, &WriterOptions::default()).unwrap();
    (recovery, out.into_inner())
}

/// Where each chunk record ends in a finished bag, and the messages up to each.
fn chunk_ends(bytes: &[u8]) -> Vec<(usize, u64)> {
    let summary = mcap::Summary::read(bytes).unwrap().unwrap();
    summary
        .chunk_indexes
        .iter()
        .map(|c| {
            let end = (c.chunk_start_offset + c.chunk_length) as usize;
            (end, 0)
        })
        .collect()
}

#[test]
fn a_finished_bag_comes_back_whole() {
    let bytes = bag(3000, 8 * 1024, Compression::Zstd);
    let (recovery, out) = recovered(&bytes);
    assert_eq!(recovery.end, RecoveryEnd::Complete);
    assert_eq!(recovery.messages, 3000);
    assert_eq!(recovery.partial_chunk_messages, 0);
    assert!(recovery.complete_chunks > 10, "{recovery:?}");
    assert_eq!(messages(&out), messages(&bytes));
    // The copy is a finished rosbag2 bag with statistics.
    let info = read_bag(&out).unwrap().info;
    assert_eq!(info.message_count, 3000);
    assert_eq!(info.topics.len(), 3);
    assert!(is_finished(&out) && is_finished(&bytes));
    // With rosbag2's metadata record, as the recorder writes it (rosbag2 takes the metadata
    // version from it), counting what was recovered.
    let summary = mcap::read::Summary::read(&out).unwrap().unwrap();
    let records: Vec<_> = summary
        .metadata_indexes
        .iter()
        .map(|index| mcap::read::metadata(&out, index).unwrap())
        .filter(|m| m.name == "rosbag2")
        .collect();
    assert_eq!(records.len(), 1);
    let information: yaml_serde::Value =
        yaml_serde::from_str(&records[0].metadata["serialized_metadata"]).unwrap();
    assert_eq!(information["version"].as_u64(), Some(8));
    assert_eq!(information["message_count"].as_u64(), Some(3000));
    assert_eq!(
        information["topics_with_message_count"]
            .as_sequence()
            .map(Vec::len),
        Some(3)
    );
}

/// Cut anywhere: what comes back is the original's first messages, in order, and at least
/// every message of the chunks that ended before the cut.
#[test]
fn a_cut_bag_keeps_every_whole_chunk_and_what_is_intact_of_the_last() {
    for compression in [Compression::Zstd, Compression::Lz4] {
        let bytes = bag(3000, 16 * 1024, compression);
        let all = messages(&bytes);
        let ends = chunk_ends(&bytes);
        for (k, &(end, _)) in ends.iter().enumerate() {
            for cut in [
                end,
                end + 1,
                end + 40,
                (end + ends.get(k + 1).map_or(end, |e| e.0)) / 2,
            ] {
                if cut >= bytes.len() {
                    continue;
                }
                let (recovery, out) = recovered(&bytes[..cut]);
                assert!(!is_finished(&bytes[..cut]));
                let got = messages(&out);
                assert_eq!(got[..], all[..got.len()], "cut at {cut}");
                assert!(
                    recovery.complete_chunks > k as u64,
                    "cut at {cut}: {recovery:?}"
                );
                assert!(matches!(recovery.end, RecoveryEnd::Truncated { .. }));
            }
        }
    }
}

/// The recorder's chunks are megabytes, many compressed blocks each: a chunk cut in the
/// middle gives back its messages up to about the cut.
#[test]
fn a_big_chunk_cut_in_the_middle_gives_back_its_first_half() {
    for compression in [Compression::Zstd, Compression::Lz4] {
        let bytes = bag(30_000, 4 << 20, compression);
        let all = messages(&bytes);
        let ends = chunk_ends(&bytes);
        assert_eq!(ends.len(), 1, "one chunk");
        let cut = ends[0].0 / 2;
        let (recovery, out) = recovered(&bytes[..cut]);
        let got = messages(&out);
        assert_eq!(got[..], all[..got.len()]);
        assert_eq!(recovery.complete_chunks, 0);
        assert_eq!(recovery.partial_chunk_messages, got.len() as u64);
        // Half the compressed bytes hold about half the messages, less a block or two.
        assert!(
            got.len() > 10_000 && got.len() < 20_000,
            "{compression:?}: {} of 30000",
            got.len()
        );
    }
}

#[test]
fn not_an_mcap_file_is_refused() {
    let mut out = std::io::Cursor::new(Vec::new());
    let err = recover(
        b"hello, world, not a bag",
        &mut out,
        &WriterOptions::default(),
    );
    assert!(err.is_err());
}

proptest! {
    /// Any cut and any damage: an answer, never a panic, and a bag that reads.
    #[test]
    fn damaged_bags_never_panic(cut in 0usize..60_000, flips in proptest::collection::vec((0usize..60_000, any::<u8>()), 0..4)) {
        let bytes = bag(600, 4 * 1024, Compression::Zstd);
        let mut damaged = bytes[..cut.min(bytes.len())].to_vec();
        for (at, byte) in flips {
            if at < damaged.len() {
                damaged[at] ^= byte;
            }
        }
        let mut out = std::io::Cursor::new(Vec::new());
        if let Ok(recovery) = recover(&damaged, &mut out, &WriterOptions::default()) {
            let out = out.into_inner();
            let info = read_bag(&out).unwrap().info;
            prop_assert_eq!(info.message_count, recovery.messages);
        }
    }
}
