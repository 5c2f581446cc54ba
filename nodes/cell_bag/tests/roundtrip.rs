//! Write a bag, read it back with our reader (the independent Python readers check the same
//! files in the repository's integration tests).

use std::io::Cursor;

use cell_bag::{
    read_bag, BagWriter, Compression, Durability, QosRecord, Reliability, WriterOptions,
};
use polar_cell_msgs::{cdr, GcodeMove, JointState, RosMessage, StringMsg};

fn write_sample(compression: Compression) -> Vec<u8> {
    let options = WriterOptions {
        compression,
        chunk_size_bytes: 4096,
    };
    let mut bag = BagWriter::new(Cursor::new(Vec::new()), &options).unwrap();
    let moves = bag
        .add_topic("/gcode/moves", GcodeMove::TYPE, QosRecord::ROS_DEFAULT)
        .unwrap();
    let latched = QosRecord {
        reliability: Reliability::Reliable,
        durability: Durability::TransientLocal,
        depth: 1,
    };
    let desc = bag
        .add_topic("/robot_description", StringMsg::TYPE, latched)
        .unwrap();
    assert_eq!(
        bag.add_topic("/gcode/moves", GcodeMove::TYPE, QosRecord::ROS_DEFAULT)
            .unwrap(),
        moves
    );
    assert!(bag
        .add_topic("/gcode/moves", JointState::TYPE, QosRecord::ROS_DEFAULT)
        .is_err());
    for i in 0..1000u64 {
        let m = GcodeMove {
            sequence: i,
            x_m: i as f64 * 1e-3,
            ..Default::default()
        };
        bag.write_message(moves, 1_000_000_000 + i * 1000, &m)
            .unwrap();
    }
    bag.write_message(
        desc,
        1_000_000_500,
        &StringMsg {
            data: "<robot/>".into(),
        },
    )
    .unwrap();
    assert!(
        bag.write(moves, 0, 0, &[0, 1]).is_err(),
        "short CDR is refused"
    );
    let (cursor, topics) = bag.finish().unwrap();
    assert_eq!(topics.len(), 2);
    assert_eq!(topics[0].stats.message_count, 1000);
    cursor.into_inner()
}

#[test]
fn bag_round_trips_with_summary_and_qos() {
    for compression in [Compression::Zstd, Compression::Lz4] {
        let bytes = write_sample(compression);
        let bag = read_bag(&bytes).unwrap();
        assert_eq!(bag.info.profile, "ros2");
        assert_eq!(bag.info.message_count, 1001);
        assert!(bag.info.chunk_count > 1, "small chunks: several chunks");
        let expected_compression = match compression {
            Compression::Zstd => "zstd",
            Compression::Lz4 => "lz4",
        };
        assert_eq!(bag.info.compression, [expected_compression]);
        assert_eq!(bag.info.start_ns, 1_000_000_000);
        assert_eq!(bag.info.end_ns, 1_000_999_000);
        let moves = &bag.info.topics[0];
        assert_eq!(moves.name, "/gcode/moves");
        assert_eq!(moves.type_name, "polar_cell_msgs/msg/GcodeMove");
        assert_eq!(moves.message_count, 1000);
        assert_eq!(moves.schema_text, GcodeMove::TYPE.schema_text().unwrap());
        assert_eq!(
            bag.info.topics[1].qos.unwrap().durability,
            Durability::TransientLocal
        );
        let mut seqs = Vec::new();
        for m in bag.messages().unwrap() {
            let m = m.unwrap();
            if m.topic == "/gcode/moves" {
                let mv: GcodeMove = cdr::decode(&m.data).unwrap();
                assert_eq!(m.log_time_ns, 1_000_000_000 + mv.sequence * 1000);
                assert_eq!(m.sequence as u64, mv.sequence);
                seqs.push(mv.sequence);
            }
        }
        assert_eq!(seqs, (0..1000).collect::<Vec<_>>());
    }
}

#[test]
fn non_ros2_and_truncated_files_are_errors() {
    let bytes = write_sample(Compression::Zstd);
    assert!(read_bag(&bytes[..bytes.len() / 2]).is_err());
    assert!(read_bag(b"not an mcap file at all").is_err());
}

/// Found by fuzzing (tests/fuzz, target bag): an MCAP file whose header's profile is not
/// `ros2` was "recovered" into a bag with that profile, which the reader then refused. It is
/// refused at once, with the profile.
#[test]
fn recovering_a_file_that_is_no_ros2_bag_is_an_error() {
    let input = b"\x89MCAP0\r\n\x01\x26\0\0\0\0\0\0\0\0\0\0\0\0\0\0\0\0\0\0\0\0\0\0\0\0\0\0\0\0\0\0\0\0\0\0\0\0\0\0\0\xff\0\xe7\xe5\xe5P#####0\r\n\x06&#\0\0\0\0\xff\0\xe7\xe5\xe5P#####0\r\n\x06&#";
    let mut out = std::io::Cursor::new(Vec::new());
    let error = cell_bag::recover(input, &mut out, &cell_bag::WriterOptions::default())
        .expect_err("no ros2 bag")
        .to_string();
    assert!(
        error.contains("header profile is ``, not `ros2`"),
        "{error}"
    );
    // A ros2 bag cut in half is still salvaged into one that reads.
    let bytes = write_sample(Compression::Zstd);
    let mut out = std::io::Cursor::new(Vec::new());
    cell_bag::recover(
        &bytes[..bytes.len() / 2],
        &mut out,
        &cell_bag::WriterOptions::default(),
    )
    .unwrap();
    read_bag(&out.into_inner()).unwrap();
}

/// Found by fuzzing (tests/fuzz, target bag): an attachment record whose body holds its
/// header but not the CRC after it makes `mcap` 0.26 panic (slice index out of range). The
/// reader answers with an error instead.
#[test]
fn a_record_the_mcap_crate_panics_on_is_an_error() {
    let mut bytes = b"\x89MCAP0\r\n".to_vec();
    bytes.push(0x09); // attachment
    bytes.extend_from_slice(&32u64.to_le_bytes());
    bytes.extend_from_slice(&[0; 32]); // times, empty name and media type, data length 0
    let err = read_bag(&bytes).err().expect("an error");
    assert!(
        err.to_string()
            .starts_with("malformed MCAP while reading the summary: "),
        "{err}"
    );
}

/// rosbag2's MCAP reader takes the metadata version from the file's `rosbag2` metadata record
/// and decodes every channel's `offered_qos_profiles` by it; read here with the mcap crate's
/// own summary, not our reader.
#[test]
fn the_file_carries_rosbag2_metadata_of_the_version_its_qos_is_written_in() {
    let bytes = write_sample(Compression::Zstd);
    let summary = mcap::read::Summary::read(&bytes).unwrap().unwrap();
    let records: Vec<_> = summary
        .metadata_indexes
        .iter()
        .map(|index| mcap::read::metadata(&bytes, index).unwrap())
        .filter(|m| m.name == "rosbag2")
        .collect();
    assert_eq!(records.len(), 1);
    let info: yaml_serde::Value =
        yaml_serde::from_str(&records[0].metadata["serialized_metadata"]).unwrap();
    assert_eq!(info["version"].as_u64(), Some(8));
    assert_eq!(info["message_count"].as_u64(), Some(1001));
    let topics = info["topics_with_message_count"].as_sequence().unwrap();
    assert_eq!(topics.len(), 2);
    for channel in summary.channels.values() {
        // Version 8's form: a YAML string whose policies are integers (1 reliable, 1
        // transient local, 2 volatile).
        let qos: yaml_serde::Value =
            yaml_serde::from_str(&channel.metadata["offered_qos_profiles"]).unwrap();
        let durability = if channel.topic == "/robot_description" {
            1
        } else {
            2
        };
        assert_eq!(qos[0]["reliability"].as_u64(), Some(1), "{}", channel.topic);
        assert_eq!(
            qos[0]["durability"].as_u64(),
            Some(durability),
            "{}",
            channel.topic
        );
    }
}

/// MCAP makes the Statistics record optional: a bag without one (written here by the `mcap`
/// crate itself, not by our writer) reads with its messages counted, not as empty.
#[test]
fn a_bag_without_statistics_is_counted_from_its_messages() {
    let mut writer = mcap::WriteOptions::new()
        .profile("ros2")
        .emit_statistics(false)
        .chunk_size(Some(256))
        .create(Cursor::new(Vec::new()))
        .unwrap();
    let schema = writer
        .add_schema(
            &StringMsg::TYPE.full_name(),
            "ros2msg",
            StringMsg::TYPE.schema_text().unwrap().as_bytes(),
        )
        .unwrap();
    let metadata = Default::default();
    let a = writer.add_channel(schema, "/a", "cdr", &metadata).unwrap();
    let b = writer.add_channel(schema, "/b", "cdr", &metadata).unwrap();
    let data = cdr::encode(&StringMsg { data: "x".into() }).unwrap();
    for (i, channel) in [a, b, a, a, b].into_iter().enumerate() {
        let header = mcap::records::MessageHeader {
            channel_id: channel,
            sequence: i as u32,
            log_time: 5_000 + 10 * i as u64,
            publish_time: 0,
        };
        writer.write_to_known_channel(&header, &data).unwrap();
    }
    writer.finish().unwrap();
    let bytes = writer.into_inner().into_inner();
    let bag = read_bag(&bytes).unwrap();
    assert_eq!(bag.info.message_count, 5);
    assert_eq!((bag.info.start_ns, bag.info.end_ns), (5_000, 5_040));
    let counts: Vec<(&str, u64)> = bag
        .info
        .topics
        .iter()
        .map(|t| (t.name.as_str(), t.message_count))
        .collect();
    assert_eq!(counts, [("/a", 3), ("/b", 2)]);
}
