//! The fixed-size payload types every chunkrt process exchanges.
//!
//! Rules (checked at compile time below, and against the C header and the Python mirror by the
//! test suite):
//! - `#[repr(C)]`, fixed size, no pointers, no `bool`, no Rust enums: codes are `u32` constants.
//! - Every type name carries the contract version (`.v1`); a changed layout gets a new name, so
//!   mismatched processes refuse to connect instead of misreading each other.
//! - Timestamps are CLOCK_MONOTONIC nanoseconds (`u64`), see [`crate::clock::monotonic_ns`].
//! - Joint arrays have room for [`MAX_DOF`] joints; only the first `n_dof` entries are meaningful.

use iceoryx2::prelude::*;

/// Largest number of joints a message can carry.
pub const MAX_DOF: usize = 16;

/// Version of the message contract; part of every type name.
pub const CONTRACT_VERSION: u32 = 1;

// ---------------------------------------------------------------------------------------------
// Camera frames
// ---------------------------------------------------------------------------------------------

/// 8-bit RGB, 3 bytes per pixel.
pub const ENCODING_RGB8: u32 = 1;
/// 8-bit BGR, 3 bytes per pixel.
pub const ENCODING_BGR8: u32 = 2;
/// 8-bit grey, 1 byte per pixel.
pub const ENCODING_MONO8: u32 = 3;

/// The iceoryx2 type name of a message type (its `#[type_name]`, e.g.
/// `chunkrt.ControllerStatus.v4`): what a service compares when a port connects.
pub fn type_name_of<T: ZeroCopySend>() -> &'static str {
    // SAFETY: reading the name is safe; `type_name` is unsafe to *implement* (the implementor
    // guarantees the layout the name stands for), which the derive does for our types.
    unsafe { <T as ZeroCopySend>::type_name() }
}

/// Bytes per pixel of a known encoding, `None` for an unknown code.
pub const fn bytes_per_pixel(encoding: u32) -> Option<u32> {
    match encoding {
        ENCODING_RGB8 | ENCODING_BGR8 => Some(3),
        ENCODING_MONO8 => Some(1),
        _ => None,
    }
}

/// Human-readable name of an encoding code.
pub const fn encoding_name(encoding: u32) -> &'static str {
    match encoding {
        ENCODING_RGB8 => "rgb8",
        ENCODING_BGR8 => "bgr8",
        ENCODING_MONO8 => "mono8",
        _ => "unknown",
    }
}

/// User header of a camera frame sample; the pixels are the sample's `[u8]` payload
/// (`stride * height` bytes, rows top to bottom).
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, ZeroCopySend)]
#[type_name("chunkrt.CameraFrameHeader.v1")]
#[repr(C)]
pub struct CameraFrameHeader {
    /// Frame counter of this camera, increasing by one per frame.
    pub seq: u64,
    /// When the image was exposed (monotonic ns).
    pub capture_time_ns: u64,
    /// When the sample was handed to iceoryx2 (monotonic ns).
    pub publish_time_ns: u64,
    /// Index of the camera in the robot's configuration.
    pub camera_id: u32,
    /// One of the `ENCODING_*` codes.
    pub encoding: u32,
    /// Pixels per row.
    pub width: u32,
    /// Rows.
    pub height: u32,
    /// Bytes per row (≥ width × bytes per pixel).
    pub stride: u32,
    /// Zero; keeps the size a multiple of 8 and leaves room for a later field.
    pub reserved: u32,
}

// ---------------------------------------------------------------------------------------------
// Joint state (robot → controller)
// ---------------------------------------------------------------------------------------------

/// The robot's watchdog holds position (no fresh, in-deadline command).
pub const JOINT_STATUS_HOLDING: u32 = 1 << 0;
/// The last command arrived after its deadline and was ignored.
pub const JOINT_STATUS_COMMAND_EXPIRED: u32 = 1 << 1;
/// No command arrived for longer than the robot's command timeout.
pub const JOINT_STATUS_COMMAND_TIMEOUT: u32 = 1 << 2;
/// The last command failed validation (bad n_dof, non-finite values, unknown mode).
pub const JOINT_STATUS_COMMAND_REJECTED: u32 = 1 << 3;
/// A commanded value was outside the robot's limits and was clamped.
pub const JOINT_STATUS_LIMIT_CLAMPED: u32 = 1 << 4;
/// `session` is set: the robot says which command publisher it obeys (0: none). A controller
/// that is not the one named holds and tracks the measured position (bumpless hand-over). A
/// driver without the flag is trusted to obey (no check possible).
pub const JOINT_STATUS_SESSION_REPORTED: u32 = 1 << 5;
/// The last command was refused because it started too far from the measured position (the
/// first command of a session, or after the robot held): a bumpless hand-over was refused.
pub const JOINT_STATUS_COMMAND_FAR: u32 = 1 << 6;
/// The robot itself reports an error or a reflex (its own safety stopped the motion; e.g. the
/// Franka's `robot_mode` Reflex): it is recovering and follows no command until it clears.
pub const JOINT_STATUS_ROBOT_ERROR: u32 = 1 << 7;
/// The driver holds the arm still at its own commanded position (its commanded velocity and
/// acceleration are zero): a controller that starts from this state starts at rest, whatever the
/// measured velocity's noise says (franka-sim's joint 7: ±0.08 rad/s at rest). Unlike
/// `JOINT_STATUS_HOLDING`, which a robot may report while its arm still settles.
pub const JOINT_STATUS_AT_REST: u32 = 1 << 8;
/// The robot does not follow the controller's commands although it receives them: the driver's
/// own fallback leads the arm (the FR3 driver's guard after commands it could not pass within the
/// robot's limits, for 10 or more cycles in a row). The controller then reports
/// `CONTROLLER_STATE_NOT_FOLLOWED`, not RUNNING.
pub const JOINT_STATUS_NOT_FOLLOWING: u32 = 1 << 9;

/// Measured joint state published by the robot driver.
#[derive(Debug, Clone, Copy, PartialEq, ZeroCopySend)]
#[type_name("chunkrt.JointState.v2")]
#[repr(C)]
pub struct JointState {
    /// Message counter of this publisher, increasing by one per message.
    pub seq: u64,
    /// When the joints were measured (monotonic ns).
    pub measurement_time_ns: u64,
    /// Number of valid joints, 1 ..= MAX_DOF.
    pub n_dof: u32,
    /// `JOINT_STATUS_*` bits.
    pub status_flags: u32,
    /// Joint positions (rad or m).
    pub position: [f64; MAX_DOF],
    /// Joint velocities (per second).
    pub velocity: [f64; MAX_DOF],
    /// Joint efforts (N·m or N).
    pub effort: [f64; MAX_DOF],
    /// With `JOINT_STATUS_SESSION_REPORTED`: iceoryx2's id of the command publisher the robot
    /// obeys (the session it is bound to; 0: none, it holds), low word first. Since
    /// `JointState.v2`.
    pub session_publisher_id: [u64; 2],
}

impl JointState {
    /// The command publisher the robot obeys, if it reports one (`None`: the driver does not
    /// report sessions; `Some(0)`: it obeys nobody).
    pub const fn obeyed_publisher(&self) -> Option<u128> {
        if self.status_flags & JOINT_STATUS_SESSION_REPORTED == 0 {
            None
        } else {
            Some(
                (self.session_publisher_id[0] as u128)
                    | ((self.session_publisher_id[1] as u128) << 64),
            )
        }
    }

    /// Reports that the robot obeys command publisher `id` (0: none).
    pub fn set_obeyed_publisher(&mut self, id: u128) {
        self.status_flags |= JOINT_STATUS_SESSION_REPORTED;
        self.session_publisher_id = [id as u64, (id >> 64) as u64];
    }
}

impl Default for JointState {
    fn default() -> Self {
        Self {
            seq: 0,
            measurement_time_ns: 0,
            n_dof: 0,
            status_flags: 0,
            position: [0.0; MAX_DOF],
            velocity: [0.0; MAX_DOF],
            effort: [0.0; MAX_DOF],
            session_publisher_id: [0; 2],
        }
    }
}

// ---------------------------------------------------------------------------------------------
// Joint command (controller → robot)
// ---------------------------------------------------------------------------------------------

/// Track position, with velocity and acceleration as feed-forward.
pub const COMMAND_MODE_POSITION: u32 = 1;
/// Hold the commanded position (velocity and acceleration are zero).
pub const COMMAND_MODE_HOLD: u32 = 2;

/// Command published by the controller every control tick.
#[derive(Debug, Clone, Copy, PartialEq, ZeroCopySend)]
#[type_name("chunkrt.JointCommand.v2")]
#[repr(C)]
pub struct JointCommand {
    /// Message counter, increasing by one per tick.
    pub seq: u64,
    /// When the command was published (monotonic ns).
    pub publish_time_ns: u64,
    /// The robot must not apply this command after this time (monotonic ns).
    pub deadline_ns: u64,
    /// `seq` of the joint state behind the observation that produced the chunk (0: none).
    pub observation_seq: u64,
    /// Id of the action chunk this command was sampled from (0: none, e.g. hold).
    pub chunk_id: u64,
    /// `seq` of the newest joint state the tick that made this command had received (0: none):
    /// a robot that clocks the controller (`[control] clock = "robot"`) matches its answer by it.
    pub state_seq: u64,
    /// Number of valid joints.
    pub n_dof: u32,
    /// One of the `COMMAND_MODE_*` codes.
    pub mode: u32,
    /// Target positions.
    pub position: [f64; MAX_DOF],
    /// Target velocities.
    pub velocity: [f64; MAX_DOF],
    /// Target accelerations.
    pub acceleration: [f64; MAX_DOF],
}

impl Default for JointCommand {
    fn default() -> Self {
        Self {
            seq: 0,
            publish_time_ns: 0,
            deadline_ns: 0,
            observation_seq: 0,
            chunk_id: 0,
            state_seq: 0,
            n_dof: 0,
            mode: COMMAND_MODE_HOLD,
            position: [0.0; MAX_DOF],
            velocity: [0.0; MAX_DOF],
            acceleration: [0.0; MAX_DOF],
        }
    }
}

// ---------------------------------------------------------------------------------------------
// Controller status (controller → anyone)
// ---------------------------------------------------------------------------------------------

/// Waiting for a fresh joint state.
pub const CONTROLLER_STATE_STARTING: u32 = 0;
/// Holding or braking: no valid chunk, stale inputs, or overruns.
pub const CONTROLLER_STATE_HOLD: u32 = 1;
/// Executing action chunks.
pub const CONTROLLER_STATE_RUNNING: u32 = 2;
/// Needs an explicit re-arm or restart.
pub const CONTROLLER_STATE_FAULT: u32 = 3;
/// The controller's last status when it stops cleanly: the robot's session with it ends at
/// once (a robot holds until the next controller's status binds it).
pub const CONTROLLER_STATE_STOPPED: u32 = 4;
/// Executing chunks, but the robot says its driver's own fallback leads the arm
/// (`JOINT_STATUS_NOT_FOLLOWING`): the arm is not where this controller's commands put it.
pub const CONTROLLER_STATE_NOT_FOLLOWED: u32 = 5;

/// Name of a `CONTROLLER_STATE_*` code.
pub const fn controller_state_name(state: u32) -> &'static str {
    match state {
        CONTROLLER_STATE_STARTING => "starting",
        CONTROLLER_STATE_HOLD => "hold",
        CONTROLLER_STATE_RUNNING => "running",
        CONTROLLER_STATE_FAULT => "fault",
        CONTROLLER_STATE_STOPPED => "stopped",
        CONTROLLER_STATE_NOT_FOLLOWED => "not followed",
        _ => "unknown",
    }
}

/// Why the controller is in its state (`ControllerStatus::state_reason`, `rearm_reason`).
/// Nothing recorded yet.
pub const STATE_REASON_NONE: u32 = 0;
/// A fresh joint state and a valid chunk: executing.
pub const STATE_REASON_INPUTS_GOOD: u32 = 1;
/// No joint state, or the newest is too old (or two publishers send it).
pub const STATE_REASON_STALE_JOINT_STATE: u32 = 2;
/// No chunk has arrived yet.
pub const STATE_REASON_NO_CHUNK: u32 = 3;
/// A camera the policy uses has no fresh frame (which: `stale_cameras`).
pub const STATE_REASON_STALE_CAMERA: u32 = 4;
/// Every chunk's last action is in the past.
pub const STATE_REASON_CHUNK_EXPIRED: u32 = 5;
/// A chunk or the sampled target had a non-finite value.
pub const STATE_REASON_NON_FINITE_ACTION: u32 = 6;
/// A chunk had the wrong shape.
pub const STATE_REASON_BAD_CHUNK: u32 = 7;
/// A streak of overrunning ticks.
pub const STATE_REASON_OVERRUNS: u32 = 8;
/// HOLD lasted `hold_to_fault_ms`.
pub const STATE_REASON_HOLD_TIMEOUT: u32 = 9;
/// The joint state does not match the configured robot.
pub const STATE_REASON_BAD_JOINT_STATE: u32 = 10;
/// The trajectory generator rejected its input.
pub const STATE_REASON_GENERATOR_ERROR: u32 = 11;
/// An operator re-armed the controller.
pub const STATE_REASON_REARM: u32 = 12;
/// The chunk source failed (an inference error, a remote server that does not answer).
pub const STATE_REASON_INFERENCE_ERROR: u32 = 13;
/// The robot obeys another command publisher (its joint state names the session it is bound
/// to), or none yet: this controller's commands are not applied.
pub const STATE_REASON_NOT_OBEYED: u32 = 14;
/// The robot receives this controller's commands but its driver's own fallback leads the arm
/// (`JOINT_STATUS_NOT_FOLLOWING`).
pub const STATE_REASON_ROBOT_NOT_FOLLOWING: u32 = 15;

/// Text of a `STATE_REASON_*` code.
pub const fn state_reason_name(code: u32) -> &'static str {
    match code {
        STATE_REASON_NONE => "none",
        STATE_REASON_INPUTS_GOOD => "inputs good",
        STATE_REASON_STALE_JOINT_STATE => "joint state missing or stale",
        STATE_REASON_NO_CHUNK => "no chunk yet",
        STATE_REASON_STALE_CAMERA => "camera frames missing or stale",
        STATE_REASON_CHUNK_EXPIRED => "chunk expired",
        STATE_REASON_NON_FINITE_ACTION => "non-finite action",
        STATE_REASON_BAD_CHUNK => "malformed chunk",
        STATE_REASON_OVERRUNS => "streak of overruns",
        STATE_REASON_HOLD_TIMEOUT => "too long in hold",
        STATE_REASON_BAD_JOINT_STATE => "joint state does not match the robot",
        STATE_REASON_GENERATOR_ERROR => "trajectory generator error",
        STATE_REASON_REARM => "re-armed",
        STATE_REASON_INFERENCE_ERROR => "the chunk source failed",
        STATE_REASON_NOT_OBEYED => "the robot does not obey this controller",
        STATE_REASON_ROBOT_NOT_FOLLOWING => "the robot's driver leads the arm, not this controller",
        _ => "unknown",
    }
}

/// `ControllerStatus::rearm_result`: no request answered yet.
pub const REARM_NONE: u32 = 0;
/// Re-armed: FAULT → STARTING (RUNNING follows once the inputs are good and a chunk arrives).
pub const REARM_ACCEPTED: u32 = 1;
/// Refused: the controller is not in FAULT (nothing to re-arm).
pub const REARM_REFUSED_NOT_IN_FAULT: u32 = 2;
/// Refused: an input is still bad (`rearm_reason` says which).
pub const REARM_REFUSED_INPUTS: u32 = 3;

/// Text of a `REARM_*` code.
pub const fn rearm_result_name(code: u32) -> &'static str {
    match code {
        REARM_NONE => "none",
        REARM_ACCEPTED => "accepted",
        REARM_REFUSED_NOT_IN_FAULT => "refused: not in fault",
        REARM_REFUSED_INPUTS => "refused: an input is still bad",
        _ => "unknown",
    }
}

// ---------------------------------------------------------------------------------------------
// Re-arm request (operator → controller)
// ---------------------------------------------------------------------------------------------

/// A request to leave FAULT without a restart, on `NS/rearm` (`chunkrt rearm`). The controller
/// answers in its next status (`rearm_seq`, `rearm_result`, `rearm_reason`). Requests older than
/// [`REARM_MAX_AGE_NS`], from the future, with `seq` 0 or a non-zero `reserved` are rejected and
/// counted; a repeated `seq` is answered once.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, ZeroCopySend)]
#[type_name("chunkrt.RearmRequest.v1")]
#[repr(C)]
pub struct RearmRequest {
    /// Non-zero request id, echoed in `ControllerStatus::rearm_seq`.
    pub seq: u64,
    /// When the request was published (monotonic ns).
    pub publish_time_ns: u64,
    /// Zero.
    pub reserved: u64,
}

// ---------------------------------------------------------------------------------------------
// Action chunk (controller → recorders, viewers)
// ---------------------------------------------------------------------------------------------

/// Most actions a published chunk carries (π0 / π0.5: 50; more are cut, `horizon` says how many
/// were kept).
pub const MAX_CHUNK_HORIZON: usize = 128;

/// Every chunk the controller's chunk source delivers, on `NS/chunks`: what the policy predicted,
/// for recorders and viewers. Published by the inference thread when the chunk is handed to the
/// control thread (the control tick does nothing for it); nobody waits for a subscriber.
#[derive(Debug, Clone, Copy, PartialEq, ZeroCopySend)]
#[type_name("chunkrt.ActionChunk.v1")]
#[repr(C)]
pub struct ActionChunkMsg {
    /// Message counter of this publisher, increasing by one per message.
    pub seq: u64,
    /// When the chunk was published (monotonic ns).
    pub publish_time_ns: u64,
    /// The controller's chunk id (`JointCommand::chunk_id` while it executes).
    pub chunk_id: u64,
    /// `seq` of the joint state behind the observation.
    pub observation_seq: u64,
    /// Capture time of the observation (monotonic ns).
    pub observation_time_ns: u64,
    /// When the chunk was ready (monotonic ns): `ready - observation` is its latency.
    pub ready_time_ns: u64,
    /// Action 0 is for `observation_time_ns + start_shift_ns` (future-state inference; 0:
    /// from the observation itself).
    pub start_shift_ns: u64,
    /// Time between consecutive actions (ns).
    pub period_ns: u64,
    /// The inference delay (in actions) the request was made with.
    pub delay_steps: u32,
    /// Actions in `actions` (at most [`MAX_CHUNK_HORIZON`]).
    pub horizon: u32,
    /// Joints per action.
    pub n_dof: u32,
    /// Zero.
    pub reserved: u32,
    /// Actions `[horizon][MAX_DOF]`: rows `..horizon`, columns `..n_dof` are used (rad or m).
    pub actions: [[f64; MAX_DOF]; MAX_CHUNK_HORIZON],
}

impl Default for ActionChunkMsg {
    fn default() -> Self {
        Self {
            seq: 0,
            publish_time_ns: 0,
            chunk_id: 0,
            observation_seq: 0,
            observation_time_ns: 0,
            ready_time_ns: 0,
            start_shift_ns: 0,
            period_ns: 0,
            delay_steps: 0,
            horizon: 0,
            n_dof: 0,
            reserved: 0,
            actions: [[0.0; MAX_DOF]; MAX_CHUNK_HORIZON],
        }
    }
}

/// Oldest re-arm request the controller acts on (ns).
pub const REARM_MAX_AGE_NS: u64 = 1_000_000_000;

/// Number of rejection counters in [`ControllerStatus::rejected`], indexed by
/// [`crate::RejectReason`] codes.
pub const REJECT_REASON_COUNT: usize = 9;

/// Status published by the controller (a few times per second).
#[derive(Debug, Clone, Copy, PartialEq, ZeroCopySend)]
#[type_name("chunkrt.ControllerStatus.v4")]
#[repr(C)]
pub struct ControllerStatus {
    /// Message counter.
    pub seq: u64,
    /// When the status was published (monotonic ns).
    pub publish_time_ns: u64,
    /// One of the `CONTROLLER_STATE_*` codes.
    pub state: u32,
    /// Number of joints controlled.
    pub n_dof: u32,
    /// Control ticks executed.
    pub ticks: u64,
    /// Ticks whose work ended after the next tick's deadline.
    pub overruns: u64,
    /// Action chunks received from the policy.
    pub chunks: u64,
    /// Joint states received and accepted.
    pub joint_states: u64,
    /// Camera frames received and accepted (all cameras).
    pub frames: u64,
    /// Rejected messages, by reason code (see `RejectReason`).
    pub rejected: [u64; REJECT_REASON_COUNT],
    /// Latency of the last inference (observation capture → chunk ready), ns; 0 if none yet.
    pub last_inference_latency_ns: u64,
    /// Wake-up lateness of the control thread, p50 / p99 / max, ns.
    pub lateness_p50_ns: u64,
    /// See `lateness_p50_ns`.
    pub lateness_p99_ns: u64,
    /// See `lateness_p50_ns`.
    pub lateness_max_ns: u64,
    /// Compute time of a control tick, p50 / p99 / max, ns.
    pub compute_p50_ns: u64,
    /// See `compute_p50_ns`.
    pub compute_p99_ns: u64,
    /// See `compute_p50_ns`.
    pub compute_max_ns: u64,
    /// Age of the newest joint state when the last command was computed, ns.
    pub joint_state_age_ns: u64,
    /// Number of state transitions into HOLD.
    pub hold_entries: u64,
    /// Cameras whose newest frame is missing or older than `frame_max_age_ms` when the policy
    /// would use it: bit i = camera i in configuration order (0: all fresh). While any is set,
    /// no chunk is computed and the controller holds.
    pub stale_cameras: u64,
    /// iceoryx2's unique id of the publisher this controller sends its joint commands from
    /// (low 64 bits, high 64 bits; 0: not known yet). A robot obeys commands from this
    /// publisher only (`SessionGate`): the session binding of docs/realtime-and-safety.md ("Session binding").
    pub command_publisher_id: [u64; 2],
    /// `seq` of the last re-arm request the controller answered (0: none yet).
    pub rearm_seq: u64,
    /// Why the controller is in its current state: a `STATE_REASON_*` code.
    pub state_reason: u32,
    /// The answer to request `rearm_seq`: a `REARM_*` code.
    pub rearm_result: u32,
    /// With `REARM_REFUSED_INPUTS`: the input still bad, a `STATE_REASON_*` code (else 0).
    pub rearm_reason: u32,
    /// Statuses this controller received on its own status service from another publisher
    /// (another controller, or a forger), saturating. While one speaks, a robot that binds
    /// sessions holds (`SessionGate`: the session is ambiguous). Was `reserved` (zero) before.
    pub foreign_statuses: u32,
}

impl ControllerStatus {
    /// The announced command publisher id as one number (0: none).
    pub const fn command_publisher(&self) -> u128 {
        (self.command_publisher_id[0] as u128) | ((self.command_publisher_id[1] as u128) << 64)
    }

    /// Announces `id` as the command publisher.
    pub fn set_command_publisher(&mut self, id: u128) {
        self.command_publisher_id = [id as u64, (id >> 64) as u64];
    }
}

impl Default for ControllerStatus {
    fn default() -> Self {
        Self {
            seq: 0,
            publish_time_ns: 0,
            state: CONTROLLER_STATE_STARTING,
            n_dof: 0,
            ticks: 0,
            overruns: 0,
            chunks: 0,
            joint_states: 0,
            frames: 0,
            rejected: [0; REJECT_REASON_COUNT],
            last_inference_latency_ns: 0,
            lateness_p50_ns: 0,
            lateness_p99_ns: 0,
            lateness_max_ns: 0,
            compute_p50_ns: 0,
            compute_p99_ns: 0,
            compute_max_ns: 0,
            joint_state_age_ns: 0,
            hold_entries: 0,
            stale_cameras: 0,
            command_publisher_id: [0; 2],
            rearm_seq: 0,
            state_reason: STATE_REASON_NONE,
            rearm_result: REARM_NONE,
            rearm_reason: STATE_REASON_NONE,
            foreign_statuses: 0,
        }
    }
}

// ---------------------------------------------------------------------------------------------
// Compile-time layout checks. The C header and the Python mirror are checked by tests.
// ---------------------------------------------------------------------------------------------

const _: () = {
    use core::mem::{align_of, size_of};
    assert!(size_of::<CameraFrameHeader>() == 48);
    assert!(align_of::<CameraFrameHeader>() == 8);
    assert!(size_of::<JointState>() == 24 + 3 * 8 * MAX_DOF + 16);
    assert!(align_of::<JointState>() == 8);
    assert!(size_of::<JointCommand>() == 56 + 3 * 8 * MAX_DOF);
    assert!(align_of::<JointCommand>() == 8);
    assert!(size_of::<ControllerStatus>() == 24 + 5 * 8 + 8 * REJECT_REASON_COUNT + 15 * 8);
    assert!(size_of::<RearmRequest>() == 24);
    assert!(align_of::<ControllerStatus>() == 8);
    assert!(MAX_DOF >= 16);
};

/// A field's name and byte offset, for comparing layouts across languages.
pub type FieldOffset = (&'static str, usize);

macro_rules! layout_of {
    ($ty:ty; $($field:ident),+ $(,)?) => {
        (
            core::mem::size_of::<$ty>(),
            vec![$((stringify!($field), core::mem::offset_of!($ty, $field))),+],
        )
    };
}

/// Size and field offsets of every message type, keyed by the C / Python struct name.
pub fn layouts() -> Vec<(&'static str, (usize, Vec<FieldOffset>))> {
    vec![
        (
            "CameraFrameHeader",
            layout_of!(CameraFrameHeader; seq, capture_time_ns, publish_time_ns, camera_id,
                encoding, width, height, stride, reserved),
        ),
        (
            "JointState",
            layout_of!(JointState; seq, measurement_time_ns, n_dof, status_flags, position,
                velocity, effort, session_publisher_id),
        ),
        (
            "JointCommand",
            layout_of!(JointCommand; seq, publish_time_ns, deadline_ns, observation_seq,
                chunk_id, state_seq, n_dof, mode, position, velocity, acceleration),
        ),
        (
            "ControllerStatus",
            layout_of!(ControllerStatus; seq, publish_time_ns, state, n_dof, ticks, overruns,
                chunks, joint_states, frames, rejected, last_inference_latency_ns,
                lateness_p50_ns, lateness_p99_ns, lateness_max_ns, compute_p50_ns,
                compute_p99_ns, compute_max_ns, joint_state_age_ns, hold_entries, stale_cameras,
                command_publisher_id, rearm_seq, state_reason, rearm_result, rearm_reason,
                foreign_statuses),
        ),
        (
            "RearmRequest",
            layout_of!(RearmRequest; seq, publish_time_ns, reserved),
        ),
        (
            "ActionChunkMsg",
            layout_of!(ActionChunkMsg; seq, publish_time_ns, chunk_id, observation_seq,
                observation_time_ns, ready_time_ns, start_shift_ns, period_ns, delay_steps,
                horizon, n_dof, reserved, actions),
        ),
    ]
}
