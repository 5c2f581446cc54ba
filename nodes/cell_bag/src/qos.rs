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

    /// Read back the first profile of an `offered_qos_profiles` YAML list.
    pub fn from_yaml(text: &str) -> Option<QosRecord> {
        let list: Vec<yaml_serde::Value> = yaml_serde::from_str(text).ok()?;
        let first = list.first()?;
        let int = |key: &str| first.get(key).and_then(|v| v.as_u64());
        Some(QosRecord {
            reliability: match int("reliability")? {
                2 => Reliability::BestEffort,
                _ => Reliability::Reliable,
            },
            durability: match int("durability")? {
                1 => Durability::TransientLocal,
                _ => Durability::Volatile,
            },
            depth: int("depth").unwrap_or(10) as u32,
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
}
