//! Rust mirrors of the `.msg` files, field by field in file order (CDR is positional).

use serde::{Deserialize, Serialize};

use crate::schema::{self, MsgType};
use crate::RosMessage;

macro_rules! ros_message {
    ($ty:ident => $def:path) => {
        impl RosMessage for $ty {
            const TYPE: &'static MsgType = &$def;
        }
    };
}

// ---------------------------------------------------------------- builtin_interfaces

/// `builtin_interfaces/msg/Time`.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, PartialOrd, Ord, Serialize, Deserialize)]
pub struct Time {
    pub sec: i32,
    pub nanosec: u32,
}
ros_message!(Time => schema::TIME);

impl Time {
    /// From nanoseconds since the epoch (or since any origin).
    pub fn from_nanos(nanos: i64) -> Self {
        Time {
            sec: nanos.div_euclid(1_000_000_000) as i32,
            nanosec: nanos.rem_euclid(1_000_000_000) as u32,
        }
    }
    /// `seconds` after the stamp `base_nanos`, to the nearest nanosecond: how the nodes stamp
    /// plan time (seconds since the plan's start) on the wall clock.
    pub fn after(base_nanos: i64, seconds: f64) -> Self {
        Time::from_nanos(base_nanos + (seconds * 1e9).round() as i64)
    }
    pub fn as_nanos(&self) -> i64 {
        self.sec as i64 * 1_000_000_000 + self.nanosec as i64
    }
    /// The wall clock now.
    pub fn now() -> Self {
        let since_epoch = std::time::SystemTime::now()
            .duration_since(std::time::UNIX_EPOCH)
            .unwrap_or_default();
        Self::from_nanos(since_epoch.as_nanos() as i64)
    }
}

/// `builtin_interfaces/msg/Duration`.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, PartialOrd, Ord, Serialize, Deserialize)]
pub struct Duration {
    pub sec: i32,
    pub nanosec: u32,
}
ros_message!(Duration => schema::DURATION);

impl Duration {
    /// From seconds, rounded to the nearest nanosecond.
    pub fn from_secs_f64(seconds: f64) -> Self {
        let nanos = (seconds * 1e9).round() as i64;
        Duration {
            sec: nanos.div_euclid(1_000_000_000) as i32,
            nanosec: nanos.rem_euclid(1_000_000_000) as u32,
        }
    }
    pub fn as_secs_f64(&self) -> f64 {
        self.sec as f64 + self.nanosec as f64 * 1e-9
    }
    pub fn as_nanos(&self) -> i64 {
        i64::from(self.sec) * 1_000_000_000 + i64::from(self.nanosec)
    }
}

// ---------------------------------------------------------------- std_msgs

/// `std_msgs/msg/Header`.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct Header {
    pub stamp: Time,
    pub frame_id: String,
}
ros_message!(Header => schema::HEADER);

/// `std_msgs/msg/String`.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct StringMsg {
    pub data: String,
}
ros_message!(StringMsg => schema::STRING);

// ---------------------------------------------------------------- sensor_msgs

/// `sensor_msgs/msg/JointState`.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct JointState {
    pub header: Header,
    pub name: Vec<String>,
    pub position: Vec<f64>,
    pub velocity: Vec<f64>,
    pub effort: Vec<f64>,
}
ros_message!(JointState => schema::JOINT_STATE);

// ---------------------------------------------------------------- trajectory_msgs

/// `trajectory_msgs/msg/JointTrajectoryPoint`.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct JointTrajectoryPoint {
    pub positions: Vec<f64>,
    pub velocities: Vec<f64>,
    pub accelerations: Vec<f64>,
    pub effort: Vec<f64>,
    pub time_from_start: Duration,
}
ros_message!(JointTrajectoryPoint => schema::JOINT_TRAJECTORY_POINT);

/// `trajectory_msgs/msg/JointTrajectory`.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct JointTrajectory {
    pub header: Header,
    pub joint_names: Vec<String>,
    pub points: Vec<JointTrajectoryPoint>,
}
ros_message!(JointTrajectory => schema::JOINT_TRAJECTORY);

/// How far a planned message's stamp may be from where the one before it ended (ns): the same
/// plan time, rounded to a nanosecond separately; anything lost leaves a gap of its length.
pub const TIMELINE_TOLERANCE_NS: i64 = 1_000;

impl JointTrajectory {
    /// Stamps of its start and of its last point (ns): a planned move's place on the timeline.
    pub fn span_ns(&self) -> (i64, i64) {
        let start = self.header.stamp.as_nanos();
        let last = self
            .points
            .last()
            .map_or(0, |p| p.time_from_start.as_nanos());
        (start, start + last)
    }
}

// ---------------------------------------------------------------- geometry_msgs

/// `geometry_msgs/msg/Point`.
#[derive(Clone, Copy, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct Point {
    pub x: f64,
    pub y: f64,
    pub z: f64,
}
ros_message!(Point => schema::POINT);

/// `geometry_msgs/msg/Quaternion` (default: identity, as in the `.msg` defaults).
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct Quaternion {
    pub x: f64,
    pub y: f64,
    pub z: f64,
    pub w: f64,
}
ros_message!(Quaternion => schema::QUATERNION);

impl Default for Quaternion {
    fn default() -> Self {
        Quaternion {
            x: 0.0,
            y: 0.0,
            z: 0.0,
            w: 1.0,
        }
    }
}

/// `geometry_msgs/msg/Pose`.
#[derive(Clone, Copy, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct Pose {
    pub position: Point,
    pub orientation: Quaternion,
}
ros_message!(Pose => schema::POSE);

/// `geometry_msgs/msg/PoseStamped`.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct PoseStamped {
    pub header: Header,
    pub pose: Pose,
}
ros_message!(PoseStamped => schema::POSE_STAMPED);

/// `geometry_msgs/msg/Vector3`.
#[derive(Clone, Copy, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct Vector3 {
    pub x: f64,
    pub y: f64,
    pub z: f64,
}
ros_message!(Vector3 => schema::VECTOR3);

/// `geometry_msgs/msg/Transform`.
#[derive(Clone, Copy, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct Transform {
    pub translation: Vector3,
    pub rotation: Quaternion,
}
ros_message!(Transform => schema::TRANSFORM);

/// `geometry_msgs/msg/TransformStamped`.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct TransformStamped {
    pub header: Header,
    pub child_frame_id: String,
    pub transform: Transform,
}
ros_message!(TransformStamped => schema::TRANSFORM_STAMPED);

// ---------------------------------------------------------------- tf2_msgs

/// `tf2_msgs/msg/TFMessage` (what `/tf` and `/tf_static` carry).
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct TFMessage {
    pub transforms: Vec<TransformStamped>,
}
ros_message!(TFMessage => schema::TF_MESSAGE);

// ---------------------------------------------------------------- std_srvs

/// The request of `std_srvs/srv/Trigger` (`ros_std/std_srvs/srv/Trigger.srv`): an empty
/// request, which rosidl gives one placeholder byte.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
pub struct TriggerRequest {
    pub structure_needs_at_least_one_member: u8,
}

/// The response of `std_srvs/srv/Trigger`.
#[derive(Clone, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
pub struct TriggerResponse {
    pub success: bool,
    pub message: String,
}

/// The definition of `std_srvs/srv/Trigger`.
pub const TRIGGER_SRV: &str = include_str!("../ros_std/std_srvs/srv/Trigger.srv");

// ---------------------------------------------------------------- diagnostic_msgs

/// `diagnostic_msgs/msg/KeyValue`.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct KeyValue {
    pub key: String,
    pub value: String,
}
ros_message!(KeyValue => schema::KEY_VALUE);

/// `diagnostic_msgs/msg/DiagnosticStatus`.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct DiagnosticStatus {
    pub level: u8,
    pub name: String,
    pub message: String,
    pub hardware_id: String,
    pub values: Vec<KeyValue>,
}
ros_message!(DiagnosticStatus => schema::DIAGNOSTIC_STATUS);

impl DiagnosticStatus {
    pub const OK: u8 = 0;
    pub const WARN: u8 = 1;
    pub const ERROR: u8 = 2;
    pub const STALE: u8 = 3;
}

/// `diagnostic_msgs/msg/DiagnosticArray`.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct DiagnosticArray {
    pub header: Header,
    pub status: Vec<DiagnosticStatus>,
}
ros_message!(DiagnosticArray => schema::DIAGNOSTIC_ARRAY);

// ---------------------------------------------------------------- rosgraph_msgs, rcl_interfaces

/// `rosgraph_msgs/msg/Clock`.
#[derive(Clone, Copy, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct Clock {
    pub clock: Time,
}
ros_message!(Clock => schema::CLOCK);

/// `rcl_interfaces/msg/Log` (what `/rosout` carries).
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct Log {
    pub stamp: Time,
    pub level: u8,
    pub name: String,
    pub msg: String,
    pub file: String,
    pub function: String,
    pub line: u32,
}
ros_message!(Log => schema::LOG);

impl Log {
    pub const DEBUG: u8 = 10;
    pub const INFO: u8 = 20;
    pub const WARN: u8 = 30;
    pub const ERROR: u8 = 40;
    pub const FATAL: u8 = 50;
}

// ---------------------------------------------------------------- polar_cell_msgs

/// `polar_cell_msgs/msg/GcodeMove`: one motion command in SI units.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct GcodeMove {
    pub sequence: u64,
    pub source_line: u32,
    pub kind: u8,
    pub segment_index: u32,
    pub segment_count: u32,
    pub x_m: f64,
    pub y_m: f64,
    pub z_m: f64,
    pub e_m: f64,
    pub delta_e_m: f64,
    pub feedrate_m_per_s: f64,
    pub extrude: bool,
    pub dwell_s: f64,
    pub axes: u8,
    pub tool: u8,
}
ros_message!(GcodeMove => schema::GCODE_MOVE);

impl GcodeMove {
    /// A move whose target is closer than this (1 nm) to where it starts goes nowhere: a
    /// start position converted between mm and m differs from the same point computed in m
    /// in the last bit, and a prime there became a 1e-19 m line planned in no time (and fed
    /// at an rpm without bound). Far below any step.
    pub const NO_PATH_M: f64 = 1e-9;
    pub const KIND_RAPID: u8 = 0;
    pub const KIND_LINEAR: u8 = 1;
    pub const KIND_ARC_CW: u8 = 2;
    pub const KIND_ARC_CCW: u8 = 3;
    pub const KIND_DWELL: u8 = 4;
    pub const KIND_HOME: u8 = 5;
    pub const KIND_SET_POSITION: u8 = 6;
    pub const AXIS_X: u8 = 1;
    pub const AXIS_Y: u8 = 2;
    pub const AXIS_Z: u8 = 4;
    pub const AXIS_E: u8 = 8;
}

/// `polar_cell_msgs/msg/GcodeAck`: cumulative flow-control acknowledgement.
#[derive(Clone, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
pub struct GcodeAck {
    pub consumer: String,
    pub next_expected: u64,
    pub resume: bool,
    pub received_until: u64,
    pub resume_state: Vec<u8>,
}
ros_message!(GcodeAck => schema::GCODE_ACK);

/// `polar_cell_msgs/msg/GcodeProgress`.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct GcodeProgress {
    pub header: Header,
    pub file: String,
    pub bytes_read: u64,
    pub bytes_total: u64,
    pub lines_read: u32,
    pub moves_published: u64,
    pub moves_acknowledged: u64,
    pub warnings: u32,
    pub consumers: Vec<String>,
    pub consumer_next_expected: Vec<u64>,
    pub finished: bool,
    pub consumer_resume_states: Vec<u8>,
    pub consumer_resume_state_ends: Vec<u32>,
    pub end_of_file: bool,
    pub moves_waiting: bool,
}
ros_message!(GcodeProgress => schema::GCODE_PROGRESS);

/// `polar_cell_msgs/msg/StepSegment`.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct StepSegment {
    pub header: Header,
    pub move_sequence: u64,
    pub source_line: u32,
    pub axis_names: Vec<String>,
    pub step_counts: Vec<u32>,
    pub directions: Vec<i8>,
    pub dominant_axis: u8,
    pub timer_frequency_hz: f64,
    pub first_period_ticks: f64,
    pub ramp_r: f64,
    pub cruise_period_ticks: f64,
    pub accelerate_steps: u32,
    pub cruise_steps: u32,
    pub decelerate_steps: u32,
    pub duration_s: f64,
    pub ends_at_rest: bool,
}
ros_message!(StepSegment => schema::STEP_SEGMENT);

impl StepSegment {
    /// The fields the pulses depend on, for the shared step core; refuses a segment whose axis
    /// arrays are not exactly the core's three axes.
    pub fn step_fields(&self) -> Result<step_core::SegmentFields, step_core::SegmentError> {
        use step_core::{SegmentError, MAX_AXES};
        let axes = |field, len| {
            if len == MAX_AXES {
                Ok(())
            } else {
                Err(SegmentError::AxisCount { field, len })
            }
        };
        axes("step_counts", self.step_counts.len())?;
        axes("directions", self.directions.len())?;
        Ok(step_core::SegmentFields {
            step_counts: std::array::from_fn(|k| self.step_counts[k]),
            directions: std::array::from_fn(|k| self.directions[k]),
            dominant_axis: self.dominant_axis,
            first_period_ticks: self.first_period_ticks,
            ramp_r: self.ramp_r,
            cruise_period_ticks: self.cruise_period_ticks,
            accelerate_steps: self.accelerate_steps,
            cruise_steps: self.cruise_steps,
            decelerate_steps: self.decelerate_steps,
        })
    }

    /// The segment in the step core's fixed-point form, validated.
    pub fn compile(&self) -> Result<step_core::Segment, step_core::SegmentError> {
        step_core::Segment::from_fields(&self.step_fields()?)
    }

    /// What a machine whose step timer runs at `timer_hz` plays: the compiled segment and its
    /// length in (fractional) ticks. Step counts and ramps are in ticks of the segment's timer,
    /// so it must be the machine's; the length must fit the step core (2³¹ ticks).
    pub fn playable(&self, timer_hz: f64) -> Result<(step_core::Segment, f64), UnplayableSegment> {
        let (move_sequence, source_line) = (self.move_sequence, self.source_line);
        let segment = self
            .compile()
            .map_err(|source| UnplayableSegment::Invalid {
                move_sequence,
                source_line,
                source,
            })?;
        if segment.dominant_steps() > 0 && self.timer_frequency_hz != timer_hz {
            return Err(UnplayableSegment::TimerMismatch {
                move_sequence,
                source_line,
                segment_hz: self.timer_frequency_hz,
                timer_hz,
            });
        }
        let ticks = self.duration_s * timer_hz;
        if !(ticks.is_finite() && ticks >= 0.0 && ticks < (1u64 << 31) as f64) {
            return Err(UnplayableSegment::BadDuration {
                move_sequence,
                source_line,
                duration_s: self.duration_s,
            });
        }
        Ok((segment, ticks))
    }
}

/// Why a machine cannot play a `StepSegment`, with the move and line it came from.
#[derive(Clone, Debug, PartialEq, thiserror::Error)]
pub enum UnplayableSegment {
    #[error("step segment of move {move_sequence} (line {source_line}): {source}")]
    Invalid {
        move_sequence: u64,
        source_line: u32,
        source: step_core::SegmentError,
    },
    #[error(
        "step segment of move {move_sequence} (line {source_line}) is timed for a \
         {segment_hz} Hz timer; this machine's timer runs at {timer_hz} Hz"
    )]
    TimerMismatch {
        move_sequence: u64,
        source_line: u32,
        segment_hz: f64,
        timer_hz: f64,
    },
    #[error(
        "step segment of move {move_sequence} (line {source_line}) lasts {duration_s} s: \
         must be finite, ≥ 0 and under 2^31 timer ticks"
    )]
    BadDuration {
        move_sequence: u64,
        source_line: u32,
        duration_s: f64,
    },
}

/// How rpm runs between two consecutive `ScrewCommand`s: what the screw driver publishes and
/// what the drive (the executor, the joint angle) must follow.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Hold {
    /// Linear between breakpoints (raw commands).
    FirstOrder,
    /// Constant until the next command (smoothed, resampled or flow-compensated commands).
    ZeroOrder,
}

/// `polar_cell_msgs/msg/ScrewCommand`.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct ScrewCommand {
    pub header: Header,
    pub rpm: f64,
    pub pin_open: bool,
    pub source_line: u32,
    pub model: String,
    pub sequence: u64,
}
ros_message!(ScrewCommand => schema::SCREW_COMMAND);

/// The goal of `polar_cell_msgs/action/Print` (`action/Print.action`).
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct PrintGoal {
    pub gcode_file: String,
    pub speed: f64,
}

/// The result of `polar_cell_msgs/action/Print`.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct PrintResult {
    pub ended: String,
    pub message: String,
    pub moves_executed: u64,
    pub machine_time_s: f64,
    pub stop_position: Vec<f64>,
    pub bag: String,
}

/// The feedback of `polar_cell_msgs/action/Print`.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct PrintFeedback {
    pub line: u32,
    pub move_sequence: u64,
    pub percent: f32,
    pub elapsed_s: f64,
    pub remaining_s: f64,
    pub state: String,
}

/// The definition of `polar_cell_msgs/action/Print`.
pub const PRINT_ACTION: &str = include_str!("../action/Print.action");

/// `polar_cell_msgs/msg/PlanCredit`.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct PlanCredit {
    pub header: Header,
    pub executor: String,
    pub executed_until: Time,
    pub accept_until: Time,
    pub horizon_s: f64,
    pub closed: bool,
}
ros_message!(PlanCredit => schema::PLAN_CREDIT);

#[cfg(test)]
mod tests {
    use super::*;
    use crate::cdr;

    /// Bytes computed by hand from the CDR rules (little-endian, natural alignment counted from
    /// the start of the body, strings as u32 length including the NUL), not by the encoder.
    #[test]
    fn gcode_ack_encodes_to_hand_computed_cdr() {
        let ack = GcodeAck {
            consumer: "/p".into(),
            next_expected: 0x0102030405060708,
            resume: true,
            received_until: 0x1112131415161718,
            resume_state: vec![0xAA, 0xBB],
        };
        let bytes = cdr::encode(&ack).unwrap();
        let expected: Vec<u8> = [
            &[0u8, 1, 0, 0][..],
            &[3, 0, 0, 0, b'/', b'p', 0],
            &[0],
            &[8, 7, 6, 5, 4, 3, 2, 1],
            &[1],
            &[0; 7],
            &[0x18, 0x17, 0x16, 0x15, 0x14, 0x13, 0x12, 0x11],
            &[2, 0, 0, 0, 0xAA, 0xBB],
        ]
        .concat();
        assert_eq!(bytes, expected);
        assert_eq!(cdr::decode::<GcodeAck>(&bytes).unwrap(), ack);
    }

    #[test]
    fn every_type_round_trips_and_names_its_definition() {
        let js = JointState {
            header: Header {
                stamp: Time::from_nanos(1_500_000_001),
                frame_id: "base".into(),
            },
            name: vec!["bed_theta".into(), "arm_r".into()],
            position: vec![1.5, -0.25],
            velocity: vec![],
            effort: vec![0.0, 1.0],
        };
        assert_eq!(
            cdr::decode::<JointState>(&cdr::encode(&js).unwrap()).unwrap(),
            js
        );
        assert_eq!(JointState::TYPE.full_name(), "sensor_msgs/msg/JointState");
        assert_eq!(GcodeMove::TYPE.full_name(), "polar_cell_msgs/msg/GcodeMove");
        assert_eq!(js.header.stamp.sec, 1);
        assert_eq!(js.header.stamp.nanosec, 500_000_001);
    }

    #[test]
    fn time_and_duration_conversions() {
        assert_eq!(
            Time::from_nanos(-1),
            Time {
                sec: -1,
                nanosec: 999_999_999
            }
        );
        assert_eq!(Time::from_nanos(-1).as_nanos(), -1);
        let d = Duration::from_secs_f64(2.75);
        assert_eq!((d.sec, d.nanosec), (2, 750_000_000));
        assert!((d.as_secs_f64() - 2.75).abs() < 1e-12);
    }

    /// The Trigger types mirror the `.srv` file: an empty request (rosidl's placeholder
    /// byte), a response of `bool success`, `string message`; the CDR is the bytes rosidl
    /// writes.
    #[test]
    fn trigger_mirrors_its_srv_file() {
        let (request, response) = TRIGGER_SRV.split_once("---").unwrap();
        assert_eq!(request.trim(), "");
        assert_eq!(
            response.split_whitespace().collect::<Vec<_>>(),
            ["bool", "success", "string", "message"]
        );
        let bytes = cdr::encode(&TriggerRequest::default()).unwrap();
        assert_eq!(bytes, [0, 1, 0, 0, 0]);
        let reply = TriggerResponse {
            success: true,
            message: "ok".into(),
        };
        let bytes = cdr::encode(&reply).unwrap();
        assert_eq!(bytes, [0, 1, 0, 0, 1, 0, 0, 0, 3, 0, 0, 0, b'o', b'k', 0]);
    }

    /// The Print types mirror `action/Print.action` field by field, in order.
    #[test]
    fn print_types_mirror_the_action_file() {
        let sections: Vec<Vec<(String, String)>> = PRINT_ACTION
            .split("\n---\n")
            .map(|part| {
                part.lines()
                    .map(|l| l.split('#').next().unwrap().trim())
                    .filter(|l| !l.is_empty())
                    .map(|l| {
                        let (t, n) = l.split_once(' ').unwrap();
                        (t.to_string(), n.trim().to_string())
                    })
                    .collect()
            })
            .collect();
        let names = |s: &Vec<(String, String)>| s.iter().map(|f| f.1.clone()).collect::<Vec<_>>();
        assert_eq!(sections.len(), 3);
        assert_eq!(names(&sections[0]), ["gcode_file", "speed"]);
        assert_eq!(
            names(&sections[1]),
            [
                "ended",
                "message",
                "moves_executed",
                "machine_time_s",
                "stop_position",
                "bag"
            ]
        );
        assert_eq!(
            names(&sections[2]),
            [
                "line",
                "move_sequence",
                "percent",
                "elapsed_s",
                "remaining_s",
                "state"
            ]
        );
        // Types: the CDR of a value with each field set decodes back (positional order).
        let result = PrintResult {
            ended: "cancelled".into(),
            message: "m".into(),
            moves_executed: 7,
            machine_time_s: 1.5,
            stop_position: vec![1.0, 2.0, 3.0, 4.0],
            bag: "b".into(),
        };
        let bytes = cdr_encoding::to_vec::<_, byteorder::LittleEndian>(&result).unwrap();
        let back: PrintResult = cdr_encoding::from_bytes::<_, byteorder::LittleEndian>(&bytes)
            .unwrap()
            .0;
        assert_eq!(back, result);
        assert_eq!(sections[1][2].0, "uint64");
        assert_eq!(sections[2][2].0, "float32");
    }

    /// Every constant of a `.msg` file has a Rust twin with the same value.
    #[test]
    fn rust_constants_match_msg_constants() {
        let consts = |text: &str| -> Vec<(String, i64)> {
            text.lines()
                .filter_map(|l| {
                    let l = l.split('#').next()?.trim();
                    let (decl, value) = l.split_once('=')?;
                    let name = decl.split_whitespace().nth(1)?;
                    Some((name.to_string(), value.trim().parse().ok()?))
                })
                .collect()
        };
        let gm = consts(GcodeMove::TYPE.text);
        let rust = [
            ("KIND_RAPID", GcodeMove::KIND_RAPID),
            ("KIND_LINEAR", GcodeMove::KIND_LINEAR),
            ("KIND_ARC_CW", GcodeMove::KIND_ARC_CW),
            ("KIND_ARC_CCW", GcodeMove::KIND_ARC_CCW),
            ("KIND_DWELL", GcodeMove::KIND_DWELL),
            ("KIND_HOME", GcodeMove::KIND_HOME),
            ("KIND_SET_POSITION", GcodeMove::KIND_SET_POSITION),
            ("AXIS_X", GcodeMove::AXIS_X),
            ("AXIS_Y", GcodeMove::AXIS_Y),
            ("AXIS_Z", GcodeMove::AXIS_Z),
            ("AXIS_E", GcodeMove::AXIS_E),
        ];
        assert_eq!(gm.len(), rust.len());
        for (name, value) in rust {
            assert!(gm.contains(&(name.to_string(), value as i64)), "{name}");
        }
        let ds = consts(DiagnosticStatus::TYPE.text);
        assert_eq!(
            ds,
            [
                ("OK".into(), 0),
                ("WARN".into(), 1),
                ("ERROR".into(), 2),
                ("STALE".into(), 3)
            ]
        );
        assert_eq!(consts(Log::TYPE.text).len(), 5);
        assert!(consts(Log::TYPE.text).contains(&("WARN".into(), Log::WARN as i64)));
    }
}
