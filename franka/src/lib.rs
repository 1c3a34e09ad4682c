//! `chunkrt franka`: a Franka FR3 (or FER) as a chunkrt robot process.
//!
//! The robot's clock runs the process: every FCI cycle (one robot state per millisecond) the
//! driver publishes the state as a `JointState` (the 7 joints, then the Franka Hand's width as
//! the gripper channel; the robot's errors in the flags) and notifies the controller
//! (`[control] clock = "robot"`), waits up to `--answer-budget-us` for the command that answers
//! this state (`JointCommand.state_seq`), and answers the robot within the cycle:
//!
//! - the controller's position, when its command is fresh and keeps the motion within the
//!   FR3's limits ([`guard::Guard::follow`]; otherwise the nearest that does, counted);
//! - a continuation at constant acceleration when the answer is late (never a repeated
//!   position while moving; counted);
//! - a jerk-limited stop to rest when no command is live (the controller stopped, stalled, died
//!   or handed over), then rest at that position.
//!
//! Commands are obeyed under chunkrt's session, deadline and hand-over rules
//! ([`chunkrt_tools::intake`]). A reflex ends the robot's motion: it is counted and named, the
//! robot is recovered (`automatic_error_recovery`) and a new motion starts from rest. On SIGINT,
//! SIGTERM or `--duration` the arm is brought to rest and the motion finished cleanly. The hand
//! is driven from the gripper channel on its own connection and thread, at its own pace.

pub mod driver;
pub mod geometry;
pub mod guard;
pub mod limits;

pub use driver::{run, Args, Summary};
