//! `[ros2]`: the ROS 2 bridge's section (`chunkrt ros2`, the crate chunkrt-ros2, which reads and
//! uses it). Its types live here, with the other sections every process of a robot may read, so
//! that the controller accepts the same file without depending on the bridge (and on DDS).
//! Unknown keys are errors; [`Ros2Config::finish`] fills the defaults that depend on `[robot]` and
//! checks every key.

use serde::{Deserialize, Serialize};

use super::{Checker, ConfigError, SharedConfig};

crate::config_enum! {
    /// `ros2.command`: which ros2_control controller takes the commands.
    pub enum CommandMode ("ros2 command mode") {
        /// `std_msgs/Float64MultiArray` to a `forward_command_controller` (e.g.
        /// `forward_position_controller`): one position per joint, in `ros2.joints` order.
        #[default]
        Forward = "forward",
        /// `trajectory_msgs/JointTrajectory` to `joint_trajectory_controller`: the command's
        /// position, velocity and acceleration as one point `trajectory_lead_ms` ahead.
        Trajectory = "trajectory",
    }
}

crate::config_enum! {
    /// `ros2.send`: when a command goes out.
    pub enum SendOn ("ros2 send") {
        /// After each joint state received from the robot: the newest live command of the
        /// controller (one command per robot state; the rate the robot's controller runs at).
        #[default]
        State = "state",
        /// Every controller tick's command as it arrives.
        Tick = "tick",
    }
}

crate::config_enum! {
    /// A topic's quality of service, as ROS 2's profiles name them.
    pub enum QosKind ("ros2 QoS") {
        /// `rclcpp::SensorDataQoS`: best effort, keep last 5, volatile.
        #[default]
        SensorData = "sensor_data",
        /// ROS 2's default for topics: reliable, keep last 10, volatile.
        Reliable = "reliable",
    }
}

crate::config_enum! {
    /// `ros2.stamp`: the time a joint state was measured.
    pub enum StampSource ("ros2 stamp") {
        /// `header.stamp` (the robot's system clock), mapped onto this machine's monotonic clock;
        /// a zero stamp falls back to the receive time.
        #[default]
        Header = "header",
        /// The time the bridge received the message (a robot whose clock is not this machine's).
        Receive = "receive",
    }
}

fn default_node_name() -> String {
    "chunkrt_bridge".to_string()
}
fn default_joint_states_topic() -> String {
    "/joint_states".to_string()
}
fn default_command_topic() -> String {
    String::new()
}
fn default_status_topic() -> String {
    "/chunkrt/status".to_string()
}
fn default_chunk_topic() -> String {
    "/chunkrt/predicted_chunk".to_string()
}
fn default_state_qos() -> QosKind {
    QosKind::SensorData
}
fn default_command_qos() -> QosKind {
    QosKind::Reliable
}
fn default_bind_tolerance() -> f64 {
    0.05
}
fn default_command_timeout_ms() -> f64 {
    50.0
}
fn default_trajectory_lead_ms() -> f64 {
    20.0
}
fn default_max_stamp_skew_ms() -> f64 {
    5.0
}
fn default_peer_silence_ms() -> f64 {
    200.0
}

/// `[ros2]`.
#[derive(Debug, Clone, Serialize, Deserialize, PartialEq)]
#[serde(deny_unknown_fields)]
pub struct Ros2Config {
    /// The DDS domain (`ROS_DOMAIN_ID`, 0..=232). Absent: the `ROS_DOMAIN_ID` environment
    /// variable, else 0. `chunkrt ros2 --domain-id` overrides both.
    #[serde(default)]
    pub domain_id: Option<u16>,
    /// The bridge's ROS 2 node name.
    #[serde(default = "default_node_name")]
    pub node_name: String,
    /// `sensor_msgs/JointState` topic (ros2_control's `joint_state_broadcaster`).
    #[serde(default = "default_joint_states_topic")]
    pub joint_states_topic: String,
    /// The ROS 2 names of the robot's joints, in `[[robot.joints]]` order (default: those
    /// joints' names). Joint states are matched to them by name; extra joints are ignored.
    #[serde(default)]
    pub joints: Vec<String>,
    /// Which controller takes the commands (`forward` or `trajectory`).
    #[serde(default)]
    pub command: CommandMode,
    /// The command topic (default: `/forward_position_controller/commands`, or
    /// `/joint_trajectory_controller/joint_trajectory` with `command = "trajectory"`).
    #[serde(default = "default_command_topic")]
    pub command_topic: String,
    /// When a command goes out: per received `state` or per controller `tick`.
    #[serde(default)]
    pub send: SendOn,
    /// QoS of the joint states (ROS 2's sensor data: best effort).
    #[serde(default = "default_state_qos")]
    pub state_qos: QosKind,
    /// QoS of the commands (ROS 2's default: reliable).
    #[serde(default = "default_command_qos")]
    pub command_qos: QosKind,
    /// Which time a joint state carries: its `header` stamp or the `receive` time.
    #[serde(default)]
    pub stamp: StampSource,
    /// A stamp more than this ahead of this machine's clock is not trusted (the receive time is
    /// used, counted) (ms).
    #[serde(default = "default_max_stamp_skew_ms")]
    pub max_stamp_skew_ms: f64,
    /// With `command = "trajectory"`: the point's `time_from_start` (ms).
    #[serde(default = "default_trajectory_lead_ms")]
    pub trajectory_lead_ms: f64,
    /// The controller's status as a `std_msgs/String` line ("": none).
    #[serde(default = "default_status_topic")]
    pub status_topic: String,
    /// Every predicted chunk as a `trajectory_msgs/JointTrajectory` ("": none).
    #[serde(default = "default_chunk_topic")]
    pub chunk_topic: String,
    /// The first command of a session, and the first after a hold, must start within this
    /// distance of the measured position (rad or m).
    #[serde(default = "default_bind_tolerance")]
    pub bind_tolerance: f64,
    /// No accepted command for this long: hold (ms).
    #[serde(default = "default_command_timeout_ms")]
    pub command_timeout_ms: f64,
    /// No joint state from the robot for this long: the robot is gone (said once, counted) (ms).
    #[serde(default = "default_peer_silence_ms")]
    pub peer_silence_ms: f64,
    /// Cameras from ROS 2 image topics, each to the `[[cameras]]` entry of the same name.
    #[serde(default)]
    pub cameras: Vec<Ros2Camera>,
    /// The gripper on a topic of its own ("": none): the `step = true` joints (in
    /// `[[robot.joints]]` order) go out as a `std_msgs/Float64MultiArray` on it when their value
    /// changes, and are left out of the arm's command.
    #[serde(default)]
    pub gripper_topic: String,
}

/// `[[ros2.cameras]]`: one camera's ROS 2 topic.
#[derive(Debug, Clone, Serialize, Deserialize, PartialEq)]
#[serde(deny_unknown_fields)]
pub struct Ros2Camera {
    /// The `[[cameras]]` entry it feeds (the policy's image key).
    pub name: String,
    /// A `sensor_msgs/Image` topic (`rgb8`, `bgr8` or `mono8`, any `step`), or with `compressed`
    /// a `sensor_msgs/CompressedImage` one.
    pub topic: String,
    /// The topic carries `sensor_msgs/CompressedImage` (JPEG or PNG).
    #[serde(default)]
    pub compressed: bool,
}

impl Default for Ros2Config {
    fn default() -> Self {
        Self {
            domain_id: None,
            node_name: default_node_name(),
            joint_states_topic: default_joint_states_topic(),
            joints: Vec::new(),
            command: CommandMode::Forward,
            command_topic: default_command_topic(),
            send: SendOn::State,
            state_qos: default_state_qos(),
            command_qos: default_command_qos(),
            stamp: StampSource::Header,
            max_stamp_skew_ms: default_max_stamp_skew_ms(),
            trajectory_lead_ms: default_trajectory_lead_ms(),
            status_topic: default_status_topic(),
            chunk_topic: default_chunk_topic(),
            bind_tolerance: default_bind_tolerance(),
            command_timeout_ms: default_command_timeout_ms(),
            peer_silence_ms: default_peer_silence_ms(),
            cameras: Vec::new(),
            gripper_topic: String::new(),
        }
    }
}

/// A ROS 2 topic name: absolute, `[A-Za-z0-9_/]`, no `//`, no trailing `/`, no leading digit in
/// a token.
pub fn check_topic(c: &Checker<'_>, key: &str, t: &str) -> Result<(), ConfigError> {
    let ok = t.len() >= 2
        && t.len() <= 200
        && t.starts_with('/')
        && !t.ends_with('/')
        && !t.contains("//")
        && t.chars()
            .all(|ch| ch.is_ascii_alphanumeric() || ch == '_' || ch == '/')
        && t.split('/')
            .all(|tok| !tok.starts_with(|ch: char| ch.is_ascii_digit()));
    if ok {
        Ok(())
    } else {
        Err(c.fail(
            key,
            format!("{t:?}"),
            "must be an absolute ROS 2 topic name: '/' then tokens of [A-Za-z0-9_] (not starting \
             with a digit) separated by single '/'",
        ))
    }
}

impl Ros2Config {
    /// Fills the defaults that depend on the rest of the file and checks every key.
    pub fn finish(&mut self, shared: &SharedConfig, c: &Checker<'_>) -> Result<(), ConfigError> {
        if self.joints.is_empty() {
            self.joints = shared.robot.joints.iter().map(|j| j.name.clone()).collect();
        }
        if self.joints.len() != shared.robot.joints.len() {
            return Err(c.fail(
                "ros2.joints",
                format!("{} names", self.joints.len()),
                &format!(
                    "must name each of the {} [[robot.joints]], in their order",
                    shared.robot.joints.len()
                ),
            ));
        }
        let mut seen = std::collections::HashSet::new();
        for (i, j) in self.joints.iter().enumerate() {
            if j.is_empty() || j.len() > 128 || j.chars().any(|ch| ch.is_control()) {
                return Err(c.fail(
                    &format!("ros2.joints[{i}]"),
                    format!("{j:?}"),
                    "must be 1..=128 printable characters",
                ));
            }
            if !seen.insert(j.as_str()) {
                return Err(c.fail(
                    &format!("ros2.joints[{i}]"),
                    format!("{j:?}"),
                    "joint names must be unique",
                ));
            }
        }
        if self.command_topic.is_empty() {
            self.command_topic = match self.command {
                CommandMode::Forward => "/forward_position_controller/commands",
                CommandMode::Trajectory => "/joint_trajectory_controller/joint_trajectory",
            }
            .to_string();
        }
        if let Some(d) = self.domain_id {
            c.range("ros2.domain_id", d as f64, 0.0, 232.0)?;
        }
        let n = &self.node_name;
        if n.is_empty()
            || n.len() > 64
            || n.starts_with(|ch: char| ch.is_ascii_digit())
            || !n.chars().all(|ch| ch.is_ascii_alphanumeric() || ch == '_')
        {
            return Err(c.fail(
                "ros2.node_name",
                format!("{n:?}"),
                "must be 1..=64 characters of [A-Za-z0-9_], not starting with a digit",
            ));
        }
        check_topic(c, "ros2.joint_states_topic", &self.joint_states_topic)?;
        check_topic(c, "ros2.command_topic", &self.command_topic)?;
        if !self.status_topic.is_empty() {
            check_topic(c, "ros2.status_topic", &self.status_topic)?;
        }
        if !self.chunk_topic.is_empty() {
            check_topic(c, "ros2.chunk_topic", &self.chunk_topic)?;
        }
        c.range(
            "ros2.max_stamp_skew_ms",
            self.max_stamp_skew_ms,
            0.0,
            10_000.0,
        )?;
        c.range(
            "ros2.trajectory_lead_ms",
            self.trajectory_lead_ms,
            1.0,
            10_000.0,
        )?;
        c.range("ros2.bind_tolerance", self.bind_tolerance, 1e-4, 10.0)?;
        c.range(
            "ros2.command_timeout_ms",
            self.command_timeout_ms,
            1.0,
            60_000.0,
        )?;
        c.range("ros2.peer_silence_ms", self.peer_silence_ms, 1.0, 60_000.0)?;
        if !self.gripper_topic.is_empty() {
            check_topic(c, "ros2.gripper_topic", &self.gripper_topic)?;
            let steps = shared.robot.joints.iter().filter(|j| j.step).count();
            if steps == 0 || steps == shared.robot.joints.len() {
                return Err(c.fail(
                    "ros2.gripper_topic",
                    format!("{:?}", self.gripper_topic),
                    "needs one or more [[robot.joints]] with step = true (the gripper) and one or \
                     more without",
                ));
            }
        }
        let mut fed = std::collections::HashSet::new();
        for (i, cam) in self.cameras.iter().enumerate() {
            let k = |f: &str| format!("ros2.cameras[{i}].{f}");
            if !shared.cameras.iter().any(|sc| sc.name == cam.name) {
                return Err(c.fail(
                    &k("name"),
                    format!("{:?}", cam.name),
                    "must name one of the [[cameras]]",
                ));
            }
            if !fed.insert(cam.name.as_str()) {
                return Err(c.fail(&k("name"), &cam.name, "one topic per camera"));
            }
            check_topic(c, &k("topic"), &cam.topic)?;
        }
        Ok(())
    }

    /// The domain: this section's, else `ROS_DOMAIN_ID`, else 0.
    pub fn domain(&self) -> Result<u16, String> {
        if let Some(d) = self.domain_id {
            return Ok(d);
        }
        match std::env::var("ROS_DOMAIN_ID") {
            Ok(v) if !v.trim().is_empty() => match v.trim().parse::<u16>() {
                Ok(d) if d <= 232 => Ok(d),
                _ => Err(format!("ROS_DOMAIN_ID={v:?}: must be a number in 0..=232")),
            },
            _ => Ok(0),
        }
    }
}
