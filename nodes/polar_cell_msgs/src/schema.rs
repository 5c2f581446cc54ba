//! Message definitions as data: names, `.msg` text, and the full `ros2msg` schema text with
//! dependencies that rosbag2 (and therefore `rosbags`, `mcap-ros2-support`, Foxglove) expects.

use std::collections::HashSet;

/// One ROS 2 message definition, `package/msg/name`, with its `.msg` text.
#[derive(Debug, PartialEq, Eq)]
pub struct MsgType {
    pub package: &'static str,
    pub name: &'static str,
    /// The `.msg` file's text, verbatim.
    pub text: &'static str,
}

/// A field type in a `.msg` text that names no known message.
#[derive(Debug, thiserror::Error, PartialEq, Eq)]
#[error("{package}/msg/{name}: field type `{field_type}` names no known message definition")]
pub struct SchemaError {
    pub package: String,
    pub name: String,
    pub field_type: String,
}

const PRIMITIVES: &[&str] = &[
    "bool", "byte", "char", "float32", "float64", "int8", "uint8", "int16", "uint16", "int32",
    "uint32", "int64", "uint64", "string", "wstring",
];

impl MsgType {
    /// `package/msg/Name`, the ROS 2 type name used by `ros2 topic` and in bags.
    pub fn full_name(&self) -> String {
        format!("{}/msg/{}", self.package, self.name)
    }

    /// `package::msg::dds_::Name_`, the DDS type name on the wire.
    pub fn dds_name(&self) -> String {
        format!("{}::msg::dds_::{}_", self.package, self.name)
    }

    /// The message types this definition's fields name directly, in field order.
    pub fn direct_dependencies(&self) -> Result<Vec<&'static MsgType>, SchemaError> {
        let mut deps = Vec::new();
        for line in self.text.lines() {
            let line = line.split('#').next().unwrap_or("").trim();
            let Some(type_token) = line.split_whitespace().next() else {
                continue;
            };
            // Constants (`uint8 A=1`) have primitive types and need no resolution.
            let base = type_token
                .split('[')
                .next()
                .unwrap_or(type_token)
                .split("<=")
                .next()
                .unwrap_or(type_token);
            if PRIMITIVES.contains(&base) {
                continue;
            }
            let (package, name) = match base.split_once('/') {
                Some((package, name)) => (package, name.trim_start_matches("msg/")),
                None => (self.package, base),
            };
            let found = ALL_TYPES
                .iter()
                .find(|t| t.package == package && t.name == name)
                .ok_or_else(|| SchemaError {
                    package: self.package.to_string(),
                    name: self.name.to_string(),
                    field_type: type_token.to_string(),
                })?;
            deps.push(*found);
        }
        Ok(deps)
    }

    /// The full schema text: this `.msg` text, then every dependency (depth-first, each once)
    /// after a line of 80 `=` and a `MSG: package/Name` line — the rosbag2 `ros2msg` encoding.
    pub fn schema_text(&self) -> Result<String, SchemaError> {
        let mut out = String::from(self.text.trim_end());
        out.push('\n');
        let mut seen = HashSet::new();
        self.append_dependencies(&mut out, &mut seen)?;
        Ok(out)
    }

    fn append_dependencies(
        &self,
        out: &mut String,
        seen: &mut HashSet<(&'static str, &'static str)>,
    ) -> Result<(), SchemaError> {
        for dep in self.direct_dependencies()? {
            if !seen.insert((dep.package, dep.name)) {
                continue;
            }
            out.push_str(&"=".repeat(80));
            out.push('\n');
            out.push_str(&format!("MSG: {}/{}\n", dep.package, dep.name));
            out.push_str(dep.text.trim_end());
            out.push('\n');
            dep.append_dependencies(out, seen)?;
        }
        Ok(())
    }
}

macro_rules! msg_types {
    ($($ident:ident = $package:literal / $name:literal @ $path:literal;)*) => {
        $(
            #[doc = concat!("`", $package, "/msg/", $name, "`")]
            pub static $ident: MsgType = MsgType {
                package: $package,
                name: $name,
                text: include_str!(concat!("../", $path)),
            };
        )*
        /// Every definition this crate knows, ours and the standard ones.
        pub static ALL_TYPES: &[&MsgType] = &[$(&$ident),*];
    };
}

msg_types! {
    TIME = "builtin_interfaces" / "Time" @ "ros_std/builtin_interfaces/msg/Time.msg";
    DURATION = "builtin_interfaces" / "Duration" @ "ros_std/builtin_interfaces/msg/Duration.msg";
    HEADER = "std_msgs" / "Header" @ "ros_std/std_msgs/msg/Header.msg";
    STRING = "std_msgs" / "String" @ "ros_std/std_msgs/msg/String.msg";
    JOINT_STATE = "sensor_msgs" / "JointState" @ "ros_std/sensor_msgs/msg/JointState.msg";
    JOINT_TRAJECTORY = "trajectory_msgs" / "JointTrajectory" @ "ros_std/trajectory_msgs/msg/JointTrajectory.msg";
    JOINT_TRAJECTORY_POINT = "trajectory_msgs" / "JointTrajectoryPoint" @ "ros_std/trajectory_msgs/msg/JointTrajectoryPoint.msg";
    POINT = "geometry_msgs" / "Point" @ "ros_std/geometry_msgs/msg/Point.msg";
    QUATERNION = "geometry_msgs" / "Quaternion" @ "ros_std/geometry_msgs/msg/Quaternion.msg";
    POSE = "geometry_msgs" / "Pose" @ "ros_std/geometry_msgs/msg/Pose.msg";
    POSE_STAMPED = "geometry_msgs" / "PoseStamped" @ "ros_std/geometry_msgs/msg/PoseStamped.msg";
    VECTOR3 = "geometry_msgs" / "Vector3" @ "ros_std/geometry_msgs/msg/Vector3.msg";
    TRANSFORM = "geometry_msgs" / "Transform" @ "ros_std/geometry_msgs/msg/Transform.msg";
    TRANSFORM_STAMPED = "geometry_msgs" / "TransformStamped" @ "ros_std/geometry_msgs/msg/TransformStamped.msg";
    TF_MESSAGE = "tf2_msgs" / "TFMessage" @ "ros_std/tf2_msgs/msg/TFMessage.msg";
    KEY_VALUE = "diagnostic_msgs" / "KeyValue" @ "ros_std/diagnostic_msgs/msg/KeyValue.msg";
    DIAGNOSTIC_STATUS = "diagnostic_msgs" / "DiagnosticStatus" @ "ros_std/diagnostic_msgs/msg/DiagnosticStatus.msg";
    DIAGNOSTIC_ARRAY = "diagnostic_msgs" / "DiagnosticArray" @ "ros_std/diagnostic_msgs/msg/DiagnosticArray.msg";
    CLOCK = "rosgraph_msgs" / "Clock" @ "ros_std/rosgraph_msgs/msg/Clock.msg";
    LOG = "rcl_interfaces" / "Log" @ "ros_std/rcl_interfaces/msg/Log.msg";
    GCODE_MOVE = "polar_cell_msgs" / "GcodeMove" @ "msg/GcodeMove.msg";
    GCODE_ACK = "polar_cell_msgs" / "GcodeAck" @ "msg/GcodeAck.msg";
    GCODE_PROGRESS = "polar_cell_msgs" / "GcodeProgress" @ "msg/GcodeProgress.msg";
    STEP_SEGMENT = "polar_cell_msgs" / "StepSegment" @ "msg/StepSegment.msg";
    SCREW_COMMAND = "polar_cell_msgs" / "ScrewCommand" @ "msg/ScrewCommand.msg";
    PLAN_CREDIT = "polar_cell_msgs" / "PlanCredit" @ "msg/PlanCredit.msg";
}

/// Look a definition up by `package/msg/Name` (or `package/Name`).
pub fn find(full_name: &str) -> Option<&'static MsgType> {
    let (package, rest) = full_name.split_once('/')?;
    let name = rest.trim_start_matches("msg/");
    ALL_TYPES
        .iter()
        .copied()
        .find(|t| t.package == package && t.name == name)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn every_definition_resolves() {
        for t in ALL_TYPES {
            t.schema_text()
                .unwrap_or_else(|e| panic!("{}: {e}", t.full_name()));
        }
    }

    #[test]
    fn joint_trajectory_schema_lists_dependencies_depth_first_once() {
        let text = JOINT_TRAJECTORY.schema_text().unwrap();
        let msg_lines: Vec<&str> = text.lines().filter(|l| l.starts_with("MSG: ")).collect();
        assert_eq!(
            msg_lines,
            [
                "MSG: std_msgs/Header",
                "MSG: builtin_interfaces/Time",
                "MSG: trajectory_msgs/JointTrajectoryPoint",
                "MSG: builtin_interfaces/Duration",
            ]
        );
        let separators = text.lines().filter(|l| *l == "=".repeat(80)).count();
        assert_eq!(separators, 4);
        assert!(text.starts_with("std_msgs/Header header\nstring[] joint_names\n"));
    }

    #[test]
    fn unknown_field_type_is_reported_with_its_name() {
        static BAD: MsgType = MsgType {
            package: "p",
            name: "Bad",
            text: "float64 ok\nNoSuchType field\n",
        };
        let err = BAD.schema_text().unwrap_err();
        assert_eq!(err.field_type, "NoSuchType");
        assert!(err.to_string().contains("p/msg/Bad"));
    }

    #[test]
    fn lookup_by_either_name_form() {
        assert_eq!(find("sensor_msgs/msg/JointState"), Some(&JOINT_STATE));
        assert_eq!(find("sensor_msgs/JointState"), Some(&JOINT_STATE));
        assert_eq!(find("sensor_msgs/Nope"), None);
        assert_eq!(
            GCODE_MOVE.dds_name(),
            "polar_cell_msgs::msg::dds_::GcodeMove_"
        );
    }
}
