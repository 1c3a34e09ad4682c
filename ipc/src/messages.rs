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

/// Measured joint state published by the robot driver.
#[derive(Debug, Clone, Copy, PartialEq, ZeroCopySend)]
#[type_name("chunkrt.JointState.v1")]
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
#[type_name("chunkrt.JointCommand.v1")]
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

/// Name of a `CONTROLLER_STATE_*` code.
pub const fn controller_state_name(state: u32) -> &'static str {
    match state {
        CONTROLLER_STATE_STARTING => "starting",
        CONTROLLER_STATE_HOLD => "hold",
        CONTROLLER_STATE_RUNNING => "running",
        CONTROLLER_STATE_FAULT => "fault",
        CONTROLLER_STATE_STOPPED => "stopped",
        _ => "unknown",
    }
}

/// Number of rejection counters in [`ControllerStatus::rejected`], indexed by
/// [`crate::RejectReason`] codes.
pub const REJECT_REASON_COUNT: usize = 9;

/// Status published by the controller (a few times per second).
#[derive(Debug, Clone, Copy, PartialEq, ZeroCopySend)]
#[type_name("chunkrt.ControllerStatus.v3")]
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
    /// publisher only (`SessionGate`): the session binding of README section "Isolation".
    pub command_publisher_id: [u64; 2],
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
    assert!(size_of::<JointState>() == 24 + 3 * 8 * MAX_DOF);
    assert!(align_of::<JointState>() == 8);
    assert!(size_of::<JointCommand>() == 48 + 3 * 8 * MAX_DOF);
    assert!(align_of::<JointCommand>() == 8);
    assert!(size_of::<ControllerStatus>() == 24 + 5 * 8 + 8 * REJECT_REASON_COUNT + 12 * 8);
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
                velocity, effort),
        ),
        (
            "JointCommand",
            layout_of!(JointCommand; seq, publish_time_ns, deadline_ns, observation_seq,
                chunk_id, n_dof, mode, position, velocity, acceleration),
        ),
        (
            "ControllerStatus",
            layout_of!(ControllerStatus; seq, publish_time_ns, state, n_dof, ticks, overruns,
                chunks, joint_states, frames, rejected, last_inference_latency_ns,
                lateness_p50_ns, lateness_p99_ns, lateness_max_ns, compute_p50_ns,
                compute_p99_ns, compute_max_ns, joint_state_age_ns, hold_entries, stale_cameras,
                command_publisher_id),
        ),
    ]
}
