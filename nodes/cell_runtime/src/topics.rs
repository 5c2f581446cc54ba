//! The suite's topics: name, message type, and the QoS their publishers offer — one table, so
//! that what a node publishes with and what a bag says it was published with cannot differ.
//!
//! Every topic is reliable. The machine's live state never waits for a subscriber (a viewer
//! that hangs must not hold up the machine) and keeps enough history that a recorder or a
//! viewer a moment behind still gets every sample; flow-controlled links keep as much as their
//! window; latched topics (`/robot_description`, `/tf_static`) are transient-local with depth
//! 1, and `/polar/trajectory` keeps its history for a restarted screw driver. `/rosout` is as
//! ros2-client publishes it (rclcpp's own is transient-local too).

use ros2_client::QosProfile;

use crate::dds::{reliable_qos, transient_local_qos};

/// What a topic's publishers offer.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct TopicQos {
    /// Late joiners get the last `depth` samples (transient-local), or nothing (volatile).
    pub transient_local: bool,
    /// Keep-last depth.
    pub depth: usize,
    /// The publisher never waits for a subscriber's acknowledgements: it keeps its newest
    /// `depth` samples for repair, and a subscriber that fell further behind (or hangs) loses
    /// the older ones. Without it, a subscriber that stops acknowledging holds the writer up
    /// once 8192 samples are unacknowledged (RustDDS's send window), then every write waits
    /// 100 ms (patches/rustdds/PATCH.md §4).
    pub never_wait: bool,
}

impl TopicQos {
    pub const fn reliable(depth: usize) -> TopicQos {
        TopicQos {
            transient_local: false,
            depth,
            never_wait: false,
        }
    }

    /// Reliable, and the publisher never waits (see [`TopicQos::never_wait`]).
    pub const fn live(depth: usize) -> TopicQos {
        TopicQos {
            transient_local: false,
            depth,
            never_wait: true,
        }
    }

    pub const fn latched(depth: usize) -> TopicQos {
        TopicQos {
            transient_local: true,
            depth,
            never_wait: false,
        }
    }

    /// The DDS profile. Never waiting is a reliable writer's `max_blocking_time` of 0 with
    /// keep-last history, which our RustDDS reads as "keep the newest".
    pub fn profile(&self) -> QosProfile {
        use ros2_client::qos::{Reliability, WhenFull};
        let profile = if self.transient_local {
            transient_local_qos(self.depth)
        } else {
            reliable_qos(self.depth)
        };
        if self.never_wait {
            profile.reliability(Reliability::Reliable {
                when_full: WhenFull::Fail,
            })
        } else {
            profile
        }
    }
}

/// One topic of the suite.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct SuiteTopic {
    pub name: &'static str,
    pub type_name: &'static str,
    pub qos: TopicQos,
}

/// The streamer's default send window: the depth of `/gcode/moves` (its publisher keeps as
/// many moves as may be unacknowledged; a changed `window` changes it).
pub const DEFAULT_MOVE_WINDOW: usize = 4096;

/// What the planner's `/polar/trajectory` writer keeps for a restarted screw driver: the
/// default window and a quarter (a screw driver acknowledges at most a window behind the
/// planner; with a larger `window`, a restart further behind is refused as a gap).
pub const TRAJECTORY_HISTORY: usize = DEFAULT_MOVE_WINDOW + DEFAULT_MOVE_WINDOW / 4;

/// Depth of the live-state writers (`/joint_states`, `/tf`, the planned joint states). The
/// machine's state never waits for a subscriber, so this is what it can still repair: 20 s of
/// 50 Hz at 1x, 0.5 s at 40x (a lost sample is asked for again within milliseconds, on the
/// heartbeat that ends each datagram). RustDDS also keeps this many samples after every
/// reader acknowledged them: about 0.5 MB for `/joint_states` and `/tf` together.
pub const LIVE_STATE_HISTORY: usize = 1000;

const fn topic(name: &'static str, type_name: &'static str, qos: TopicQos) -> SuiteTopic {
    SuiteTopic {
        name,
        type_name,
        qos,
    }
}

/// Every topic the suite publishes (or, for `/mechanism/tool_pose`, takes: its publishers are
/// the user's, at ROS's default depth).
pub const SUITE_TOPICS: &[SuiteTopic] = &[
    topic(
        "/gcode/moves",
        "polar_cell_msgs/msg/GcodeMove",
        TopicQos::reliable(DEFAULT_MOVE_WINDOW),
    ),
    topic(
        "/gcode/progress",
        "polar_cell_msgs/msg/GcodeProgress",
        TopicQos::reliable(10),
    ),
    topic(
        "/gcode/ack",
        "polar_cell_msgs/msg/GcodeAck",
        TopicQos::reliable(1000),
    ),
    // Transient-local: a restarted screw driver gets again the plans published since its
    // last acknowledgement (never more than the move window behind the planner). The writer
    // keeps them all the time: a window and a quarter, not more (memory).
    topic(
        "/polar/trajectory",
        "trajectory_msgs/msg/JointTrajectory",
        TopicQos::latched(TRAJECTORY_HISTORY),
    ),
    topic(
        "/polar/steps",
        "polar_cell_msgs/msg/StepSegment",
        TopicQos::reliable(10_000),
    ),
    topic(
        "/joint_states",
        "sensor_msgs/msg/JointState",
        TopicQos::live(LIVE_STATE_HISTORY),
    ),
    topic(
        "/polar/planned_joint_states",
        "sensor_msgs/msg/JointState",
        TopicQos::reliable(LIVE_STATE_HISTORY),
    ),
    topic(
        "/tf",
        "tf2_msgs/msg/TFMessage",
        TopicQos::live(LIVE_STATE_HISTORY),
    ),
    topic("/tf_static", "tf2_msgs/msg/TFMessage", TopicQos::latched(1)),
    topic(
        "/cell/plan_credit",
        "polar_cell_msgs/msg/PlanCredit",
        TopicQos::live(100),
    ),
    topic(
        "/screw/command",
        "polar_cell_msgs/msg/ScrewCommand",
        TopicQos::reliable(10_000),
    ),
    topic(
        "/mechanism/joint_states",
        "sensor_msgs/msg/JointState",
        TopicQos::reliable(100),
    ),
    topic(
        "/mechanism/tool_pose",
        "geometry_msgs/msg/PoseStamped",
        TopicQos::reliable(10),
    ),
    topic(
        "/robot_description",
        "std_msgs/msg/String",
        TopicQos::latched(1),
    ),
    topic(
        "/diagnostics",
        "diagnostic_msgs/msg/DiagnosticArray",
        TopicQos::reliable(10),
    ),
    topic("/rosout", "rcl_interfaces/msg/Log", TopicQos::latched(1)),
];

/// The suite topic called `name`.
pub fn suite_topic(name: &str) -> Option<&'static SuiteTopic> {
    SUITE_TOPICS.iter().find(|t| t.name == name)
}

/// The profile the suite publishes `name` with.
///
/// # Panics
/// If `name` is not in [`SUITE_TOPICS`]: a node publishing a topic the table does not know
/// is a programming error, caught by its first test.
pub fn publisher_qos(name: &str) -> QosProfile {
    suite_topic(name)
        .unwrap_or_else(|| panic!("{name} is not in cell_runtime::topics::SUITE_TOPICS"))
        .qos
        .profile()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn every_topic_is_listed_once_with_a_depth() {
        for (i, t) in SUITE_TOPICS.iter().enumerate() {
            assert!(t.qos.depth >= 1, "{}", t.name);
            assert!(t.name.starts_with('/') && t.type_name.contains("/msg/"));
            assert!(
                SUITE_TOPICS[i + 1..].iter().all(|u| u.name != t.name),
                "{} twice",
                t.name
            );
        }
        assert_eq!(suite_topic("/joint_states").unwrap().qos.depth, 1000);
        assert!(suite_topic("/joint_states").unwrap().qos.never_wait);
        assert!(!suite_topic("/polar/steps").unwrap().qos.never_wait);
        assert!(suite_topic("/tf_static").unwrap().qos.transient_local);
        assert!(suite_topic("/nope").is_none());
    }

    #[test]
    fn live_state_publishers_never_wait_and_the_others_wait_100_ms() {
        use ros2_client::qos::{Reliability, WhenFull};
        let live = TopicQos::live(10).profile();
        assert_eq!(
            live.reliability,
            Reliability::Reliable {
                when_full: WhenFull::Fail
            }
        );
        let waits = TopicQos::reliable(10).profile();
        assert_eq!(
            waits.reliability,
            Reliability::Reliable {
                when_full: WhenFull::DEFAULT
            }
        );
    }
}
