//! The `offered_qos_profiles` channel metadata, in rosbag2's YAML form.

/// Reliability, with rosbag2's integer values.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Reliability {
    Reliable = 1,
    BestEffort = 2,
}

/// Durability, with rosbag2's integer values.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Durability {
    TransientLocal = 1,
    Volatile = 2,
}

/// The QoS a publisher offered, as recorded for a channel (history is always keep-last).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct QosRecord {
    pub reliability: Reliability,
    pub durability: Durability,
    pub depth: u32,
}

impl QosRecord {
    /// The ROS default: reliable, volatile, keep-last 10.
    pub const ROS_DEFAULT: QosRecord = QosRecord {
        reliability: Reliability::Reliable,
        durability: Durability::Volatile,
        depth: 10,
    };

    /// rosbag2's YAML list with one profile. Infinite durations are written as rosbag2 does
    /// (`sec: 2147483647, nsec: 4294967295`).
    pub fn to_yaml(&self) -> String {
        let infinite = "\n    sec: 2147483647\n    nsec: 4294967295";
        format!(
            "- history: 1\n  depth: {}\n  reliability: {}\n  durability: {}\n  deadline:{infinite}\n  lifespan:{infinite}\n  liveliness: 1\n  liveliness_lease_duration:{infinite}\n  avoid_ros_namespace_conventions: false",
            self.depth, self.reliability as u8, self.durability as u8
        )
    }

    /// The history a player keeps for late joiners of a transient-local topic that has
    /// `message_count` samples in the bag: the depth recorded, or, where the recorder did not
    /// know it (rosbag2 writes depth 0, history "unknown": discovery does not carry it), every
    /// sample the bag has, up to 10,000.
    pub fn latched_depth(&self, message_count: u64) -> usize {
        match self.depth {
            0 => message_count.clamp(1, 10_000) as usize,
            depth => depth as usize,
        }
    }

    /// Read back the first profile of an `offered_qos_profiles` YAML list: with integer
    /// policies (rosbag2 before metadata version 9, and ours) or named ones ("reliable",
    /// "transient_local": what Jazzy's `ros2 bag record` writes in an MCAP file's channels).
    pub fn from_yaml(text: &str) -> Option<QosRecord> {
        let list: Vec<yaml_serde::Value> = yaml_serde::from_str(text).ok()?;
        let first = list.first()?;
        // The policy's integer, or the integer its name stands for.
        let policy = |key: &str, names: [&str; 2]| -> Option<u64> {
            let value = first.get(key)?;
            value.as_u64().or_else(|| {
                let name = value.as_str()?;
                names.iter().position(|n| *n == name).map(|i| i as u64 + 1)
            })
        };
        Some(QosRecord {
            reliability: match policy("reliability", ["reliable", "best_effort"])? {
                2 => Reliability::BestEffort,
                _ => Reliability::Reliable,
            },
            durability: match policy("durability", ["transient_local", "volatile"])? {
                1 => Durability::TransientLocal,
                _ => Durability::Volatile,
            },
            depth: first.get("depth").and_then(|v| v.as_u64()).unwrap_or(10) as u32,
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn yaml_round_trip_with_integer_enums() {
        let q = QosRecord {
            reliability: Reliability::Reliable,
            durability: Durability::TransientLocal,
            depth: 1,
        };
        let yaml = q.to_yaml();
        let parsed: yaml_serde::Value = yaml_serde::from_str(&yaml).unwrap();
        assert_eq!(parsed[0]["reliability"].as_u64(), Some(1));
        assert_eq!(parsed[0]["durability"].as_u64(), Some(1));
        assert_eq!(parsed[0]["history"].as_u64(), Some(1));
        assert_eq!(parsed[0]["deadline"]["sec"].as_u64(), Some(2147483647));
        assert_eq!(QosRecord::from_yaml(&yaml), Some(q));
        assert_eq!(
            QosRecord::from_yaml(&QosRecord::ROS_DEFAULT.to_yaml()),
            Some(QosRecord::ROS_DEFAULT)
        );
    }

    #[test]
    fn an_unknown_depth_keeps_every_latched_sample_for_late_joiners() {
        let mut q = QosRecord {
            reliability: Reliability::Reliable,
            durability: Durability::TransientLocal,
            depth: 0,
        };
        assert_eq!(q.latched_depth(3), 3);
        assert_eq!(q.latched_depth(0), 1);
        assert_eq!(q.latched_depth(1 << 40), 10_000);
        q.depth = 1;
        assert_eq!(q.latched_depth(3), 1);
        // As Jazzy's `ros2 bag record` writes /tf_static's profile.
        let recorded = "- history: unknown\n  depth: 0\n  reliability: reliable\n  durability: transient_local";
        assert_eq!(QosRecord::from_yaml(recorded).unwrap().latched_depth(2), 2);
    }

    #[test]
    fn named_policies_as_jazzy_writes_them_read_back() {
        let jazzy = "- history: keep_last\n  depth: 1\n  reliability: best_effort\n  durability: transient_local\n  deadline:\n    sec: 9223372036\n    nsec: 854775807\n  lifespan:\n    sec: 9223372036\n    nsec: 854775807\n  liveliness: automatic\n  liveliness_lease_duration:\n    sec: 9223372036\n    nsec: 854775807\n  avoid_ros_namespace_conventions: false";
        assert_eq!(
            QosRecord::from_yaml(jazzy),
            Some(QosRecord {
                reliability: Reliability::BestEffort,
                durability: Durability::TransientLocal,
                depth: 1,
            })
        );
        let reliable_volatile = jazzy
            .replace("best_effort", "reliable")
            .replace("transient_local", "volatile");
        assert_eq!(
            QosRecord::from_yaml(&reliable_volatile),
            Some(QosRecord {
                reliability: Reliability::Reliable,
                durability: Durability::Volatile,
                depth: 1,
            })
        );
        // A policy it cannot read is no profile, not a guessed one.
        assert_eq!(
            QosRecord::from_yaml(&jazzy.replace("transient_local", "sometimes")),
            None
        );
    }
}
