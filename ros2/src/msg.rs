//! The ROS 2 messages the bridge speaks, laid out field for field as ROS 2's own definitions
//! (`builtin_interfaces`, `std_msgs`, `sensor_msgs`, `trajectory_msgs`; the same in Humble and
//! Jazzy). CDR encodes a struct as its fields in order, so these serde types are the wire format;
//! tests/ros2_bridge.rs checks them against Cyclone DDS and rosbags' type store.

use serde::{Deserialize, Serialize};

/// `builtin_interfaces/Time`: seconds and nanoseconds since the epoch of the publisher's clock.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, Serialize, Deserialize)]
pub struct Time {
    pub sec: i32,
    pub nanosec: u32,
}

impl Time {
    /// Nanoseconds since the epoch; `None` for a negative or out-of-range time.
    pub fn as_ns(&self) -> Option<u64> {
        if self.sec < 0 || self.nanosec >= 1_000_000_000 {
            return None;
        }
        Some(self.sec as u64 * 1_000_000_000 + self.nanosec as u64)
    }

    /// The time `ns` nanoseconds after the epoch (saturating at `i32::MAX` seconds).
    pub fn from_ns(ns: u64) -> Self {
        Self {
            sec: (ns / 1_000_000_000).min(i32::MAX as u64) as i32,
            nanosec: (ns % 1_000_000_000) as u32,
        }
    }
}

/// `builtin_interfaces/Duration`.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, Serialize, Deserialize)]
pub struct Duration {
    pub sec: i32,
    pub nanosec: u32,
}

impl Duration {
    /// A non-negative duration of `ns` nanoseconds.
    pub fn from_ns(ns: u64) -> Self {
        Self {
            sec: (ns / 1_000_000_000).min(i32::MAX as u64) as i32,
            nanosec: (ns % 1_000_000_000) as u32,
        }
    }
}

/// `std_msgs/Header`.
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
pub struct Header {
    pub stamp: Time,
    pub frame_id: String,
}

/// `sensor_msgs/JointState`: names, and positions / velocities / efforts either empty or one per
/// name.
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
pub struct JointState {
    pub header: Header,
    pub name: Vec<String>,
    pub position: Vec<f64>,
    pub velocity: Vec<f64>,
    pub effort: Vec<f64>,
}

/// `std_msgs/MultiArrayDimension`.
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
pub struct MultiArrayDimension {
    pub label: String,
    pub size: u32,
    pub stride: u32,
}

/// `std_msgs/MultiArrayLayout`.
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
pub struct MultiArrayLayout {
    pub dim: Vec<MultiArrayDimension>,
    pub data_offset: u32,
}

/// `std_msgs/Float64MultiArray`: what ros2_control's `forward_command_controller` takes, one
/// value per joint in the controller's `joints` order, no layout.
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
pub struct Float64MultiArray {
    pub layout: MultiArrayLayout,
    pub data: Vec<f64>,
}

/// `trajectory_msgs/JointTrajectoryPoint`.
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
pub struct JointTrajectoryPoint {
    pub positions: Vec<f64>,
    pub velocities: Vec<f64>,
    pub accelerations: Vec<f64>,
    pub effort: Vec<f64>,
    pub time_from_start: Duration,
}

/// `trajectory_msgs/JointTrajectory`: `joint_trajectory_controller`'s command, and how the
/// bridge shows a predicted chunk.
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
pub struct JointTrajectory {
    pub header: Header,
    pub joint_names: Vec<String>,
    pub points: Vec<JointTrajectoryPoint>,
}

/// `std_msgs/String`: the controller's status as one line.
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
pub struct StringMsg {
    pub data: String,
}

/// `sensor_msgs/Image`: `height` rows of `step` bytes, top to bottom.
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
pub struct Image {
    pub header: Header,
    pub height: u32,
    pub width: u32,
    pub encoding: String,
    pub is_bigendian: u8,
    pub step: u32,
    pub data: Vec<u8>,
}

/// `sensor_msgs/CompressedImage`: `format` says the codec (`jpeg`, `png`, or image_transport's
/// `"rgb8; jpeg compressed bgr8"`).
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
pub struct CompressedImage {
    pub header: Header,
    pub format: String,
    pub data: Vec<u8>,
}

/// ROS 2 package and type names of the messages above.
pub mod types {
    pub const JOINT_STATE: (&str, &str) = ("sensor_msgs", "JointState");
    pub const FLOAT64_MULTI_ARRAY: (&str, &str) = ("std_msgs", "Float64MultiArray");
    pub const JOINT_TRAJECTORY: (&str, &str) = ("trajectory_msgs", "JointTrajectory");
    pub const STRING: (&str, &str) = ("std_msgs", "String");
    pub const IMAGE: (&str, &str) = ("sensor_msgs", "Image");
    pub const COMPRESSED_IMAGE: (&str, &str) = ("sensor_msgs", "CompressedImage");
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn time_round_trips_and_rejects_what_is_not_a_time() {
        let t = Time::from_ns(1_700_000_000_123_456_789);
        assert_eq!(t.as_ns(), Some(1_700_000_000_123_456_789));
        assert_eq!(
            Time {
                sec: -1,
                nanosec: 0
            }
            .as_ns(),
            None
        );
        assert_eq!(
            Time {
                sec: 1,
                nanosec: 1_000_000_000
            }
            .as_ns(),
            None
        );
    }
}
