//! `chunkrt ros2`: any ros2_control robot as a chunkrt robot process.
//!
//! ROS 2 on one side, chunkrt's iceoryx2 services on the other, one configuration file
//! (`[ros2]`, [`config::Ros2Config`]):
//!
//! - the robot's `sensor_msgs/JointState` (ros2_control's `joint_state_broadcaster`) matched by
//!   name to the configured joints, checked ([`boundary`]), its `header.stamp` kept as the
//!   measurement time, published as chunkrt's joint state (and, with `[control] clock =
//!   "robot"`, the controller ticked by it);
//! - chunkrt's commands, under the robot side's session, deadline and bumpless rules
//!   ([`chunkrt_tools::intake`]), clamped into the configured limits, out as a
//!   `std_msgs/Float64MultiArray` to a `forward_command_controller` or a
//!   `trajectory_msgs/JointTrajectory` to `joint_trajectory_controller`; with no live command
//!   the last position sent is held;
//! - the controller's status (`std_msgs/String`) and every predicted chunk
//!   (`trajectory_msgs/JointTrajectory`) on topics of their own, for RViz and Foxglove.
//!
//! DDS through the pure-Rust `ros2-client` (RustDDS): no ROS 2 install to build or run. The
//! controller's control tick never touches the network: this process does, on its own threads.

pub mod boundary;
pub mod bridge;
pub mod camera;
pub mod config;
pub mod msg;

pub use bridge::{run, Args, Summary};
