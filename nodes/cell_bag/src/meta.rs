//! Per-topic statistics and the `metadata.yaml` of a rosbag2 bag directory.

use crate::qos::QosRecord;

/// One recorded topic: what `metadata.yaml` lists for it.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct RecordedTopic {
    pub topic: String,
    pub type_name: String,
    pub qos: QosRecord,
    pub stats: TopicStats,
}

/// Count and time span of one topic's messages.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct TopicStats {
    pub message_count: u64,
    pub first_ns: u64,
    pub last_ns: u64,
}

impl TopicStats {
    pub(crate) fn record(&mut self, t_ns: u64) {
        if self.message_count == 0 || t_ns < self.first_ns {
            self.first_ns = t_ns;
        }
        if self.message_count == 0 || t_ns > self.last_ns {
            self.last_ns = t_ns;
        }
        self.message_count += 1;
    }
}

/// The metadata version written: 8, the last whose `offered_qos_profiles` is a YAML string
/// with integer policies. Version 9 (Jazzy's own) makes it a nested list with policy names
/// ("reliable"); Humble reads only the integer form, and Jazzy reads a version-8 bag's
/// integers correctly, so version 8 is what both play. (Declaring 9 over the version-8
/// layout made Jazzy fail to read the list and take every policy as "unknown".)
pub const METADATA_VERSION: u32 = 8;

/// The ROS 2 distribution our bags say they were recorded with.
pub const ROS_DISTRO: &str = "jazzy";

/// `metadata.yaml` (rosbag2_bagfile_information, version [`METADATA_VERSION`]) for a
/// directory holding one MCAP file named `file_name`, with exactly the channels of the bag.
pub fn metadata_yaml(file_name: &str, topics: &[RecordedTopic], ros_distro: &str) -> String {
    let mut y = String::from("rosbag2_bagfile_information:\n");
    for line in bag_information(Some(file_name), topics, ros_distro).lines() {
        y.push_str("  ");
        y.push_str(line);
        y.push('\n');
    }
    y
}

/// rosbag2's bag information (the body of `metadata.yaml`, or the `serialized_metadata` of
/// the `rosbag2` metadata record rosbag2 puts in an MCAP file, from which its MCAP reader
/// takes the metadata version). `file_name`: the MCAP file's name where known.
pub fn bag_information(
    file_name: Option<&str>,
    topics: &[RecordedTopic],
    ros_distro: &str,
) -> String {
    let recorded: Vec<_> = topics
        .iter()
        .filter(|t| t.stats.message_count > 0)
        .collect();
    let start = recorded.iter().map(|t| t.stats.first_ns).min().unwrap_or(0);
    let end = recorded.iter().map(|t| t.stats.last_ns).max().unwrap_or(0);
    let count: u64 = topics.iter().map(|t| t.stats.message_count).sum();
    let duration = end.saturating_sub(start);
    let mut y = String::new();
    y.push_str(&format!("version: {METADATA_VERSION}\n"));
    y.push_str("storage_identifier: mcap\n");
    y.push_str(&format!("duration:\n  nanoseconds: {duration}\n"));
    y.push_str(&format!(
        "starting_time:\n  nanoseconds_since_epoch: {start}\n"
    ));
    y.push_str(&format!("message_count: {count}\n"));
    y.push_str("topics_with_message_count:\n");
    for RecordedTopic {
        topic: name,
        type_name,
        qos,
        stats,
    } in topics
    {
        y.push_str("  - topic_metadata:\n");
        y.push_str(&format!("      name: {}\n", yaml_string(name)));
        y.push_str(&format!("      type: {}\n", yaml_string(type_name)));
        y.push_str("      serialization_format: cdr\n");
        y.push_str(&format!(
            "      offered_qos_profiles: {}\n",
            yaml_string(&qos.to_yaml())
        ));
        y.push_str("      type_description_hash: \"\"\n");
        y.push_str(&format!("    message_count: {}\n", stats.message_count));
    }
    y.push_str("compression_format: \"\"\n");
    y.push_str("compression_mode: \"\"\n");
    match file_name {
        Some(file_name) => {
            y.push_str(&format!(
                "relative_file_paths:\n  - {}\n",
                yaml_string(file_name)
            ));
            y.push_str("files:\n");
            y.push_str(&format!("  - path: {}\n", yaml_string(file_name)));
            y.push_str(&format!(
                "    starting_time:\n      nanoseconds_since_epoch: {start}\n"
            ));
            y.push_str(&format!("    duration:\n      nanoseconds: {duration}\n"));
            y.push_str(&format!("    message_count: {count}\n"));
        }
        None => y.push_str("relative_file_paths: []\nfiles: []\n"),
    }
    y.push_str("custom_data: ~\n");
    y.push_str(&format!("ros_distro: {}\n", yaml_string(ros_distro)));
    y
}

/// A YAML double-quoted scalar (escapes quotes, backslashes and newlines).
fn yaml_string(s: &str) -> String {
    let mut out = String::with_capacity(s.len() + 2);
    out.push('"');
    for c in s.chars() {
        match c {
            '"' => out.push_str("\\\""),
            '\\' => out.push_str("\\\\"),
            '\n' => out.push_str("\\n"),
            c => out.push(c),
        }
    }
    out.push('"');
    out
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn metadata_parses_and_matches_channels() {
        let mut a = TopicStats::default();
        a.record(200);
        a.record(100);
        let mut b = TopicStats::default();
        b.record(150);
        b.record(400);
        b.record(300);
        let topic = |name: &str, type_name: &str, stats| RecordedTopic {
            topic: name.into(),
            type_name: type_name.into(),
            qos: QosRecord::ROS_DEFAULT,
            stats,
        };
        let topics = vec![
            topic("/a", "std_msgs/msg/String", a),
            topic("/b", "sensor_msgs/msg/JointState", b),
        ];
        let yaml = metadata_yaml("bag_0.mcap", &topics, "jazzy");
        let v: yaml_serde::Value = yaml_serde::from_str(&yaml).unwrap();
        let info = &v["rosbag2_bagfile_information"];
        assert_eq!(info["message_count"].as_u64(), Some(5));
        assert_eq!(info["duration"]["nanoseconds"].as_u64(), Some(300));
        assert_eq!(
            info["starting_time"]["nanoseconds_since_epoch"].as_u64(),
            Some(100)
        );
        let t = &info["topics_with_message_count"];
        assert_eq!(
            t[1]["topic_metadata"]["type"].as_str(),
            Some("sensor_msgs/msg/JointState")
        );
        assert_eq!(t[1]["message_count"].as_u64(), Some(3));
        let qos = t[0]["topic_metadata"]["offered_qos_profiles"]
            .as_str()
            .unwrap();
        assert_eq!(QosRecord::from_yaml(qos), Some(QosRecord::ROS_DEFAULT));
        assert_eq!(info["relative_file_paths"][0].as_str(), Some("bag_0.mcap"));
        // Version 8: the layout written (a QoS string with integer policies). Jazzy reads a
        // version-9 file's `offered_qos_profiles` as a list and fails on this string.
        assert_eq!(info["version"].as_u64(), Some(8));
        assert!(info["custom_data"].is_null());
        assert_eq!(info["ros_distro"].as_str(), Some(ROS_DISTRO));

        // The MCAP's own record: the same information at top level, no file named.
        let record: yaml_serde::Value =
            yaml_serde::from_str(&bag_information(None, &topics, ROS_DISTRO)).unwrap();
        assert_eq!(record["version"].as_u64(), Some(8));
        assert_eq!(record["message_count"].as_u64(), Some(5));
        assert_eq!(
            record["relative_file_paths"].as_sequence().map(Vec::len),
            Some(0)
        );
        assert_eq!(
            record["topics_with_message_count"],
            info["topics_with_message_count"]
        );
    }
}
