//! Validation of every message at the boundary, with typed errors and counter codes.
//!
//! Structural checks (`validate_*`) need only the message. Stream checks (sequence increasing,
//! time not going backwards, neither from the future nor stale) need the previous message of
//! the same publisher and the receiver's clock: [`StreamGuard`] keeps that state without
//! allocating, so it can run inside the control tick.

use crate::messages::*;

/// Why a message was rejected; the code indexes [`ControllerStatus::rejected`].
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
#[repr(u32)]
pub enum RejectReason {
    /// `n_dof` is 0, above `MAX_DOF`, or not the robot's number of joints.
    NDof = 0,
    /// A NaN or infinite number.
    NonFinite = 1,
    /// Image geometry inconsistent (stride, width, height, payload length, size limits).
    FrameGeometry = 2,
    /// Unknown image encoding or command mode code.
    UnknownCode = 3,
    /// Sequence number not increasing, or measurement time going backwards.
    OutOfOrder = 4,
    /// Timestamp ahead of the receiver's clock.
    FromFuture = 5,
    /// Timestamp older than the allowed age.
    Stale = 6,
    /// Any other problem (e.g. wrong camera id).
    Other = 7,
    /// A second publisher on a channel whose bound publisher is alive (one writer per channel).
    ForeignPublisher = 8,
}

impl RejectReason {
    /// Every reason, in code order.
    pub const ALL: [RejectReason; REJECT_REASON_COUNT] = [
        RejectReason::NDof,
        RejectReason::NonFinite,
        RejectReason::FrameGeometry,
        RejectReason::UnknownCode,
        RejectReason::OutOfOrder,
        RejectReason::FromFuture,
        RejectReason::Stale,
        RejectReason::Other,
        RejectReason::ForeignPublisher,
    ];

    /// Index into the rejection counters.
    pub const fn code(self) -> usize {
        self as usize
    }

    /// Short name for logs and tables.
    pub const fn name(self) -> &'static str {
        match self {
            RejectReason::NDof => "n_dof",
            RejectReason::NonFinite => "non_finite",
            RejectReason::FrameGeometry => "frame_geometry",
            RejectReason::UnknownCode => "unknown_code",
            RejectReason::OutOfOrder => "out_of_order",
            RejectReason::FromFuture => "from_future",
            RejectReason::Stale => "stale",
            RejectReason::Other => "other",
            RejectReason::ForeignPublisher => "foreign_publisher",
        }
    }
}

/// A rejected message: what was wrong, with the offending values.
#[derive(Debug, Clone, Copy, PartialEq, thiserror::Error)]
pub enum ValidationError {
    #[error("n_dof {n_dof} outside 1..={max}")]
    NDofOutOfRange { n_dof: u32, max: u32 },
    #[error("n_dof {n_dof} but the robot has {expected} joints")]
    NDofMismatch { n_dof: u32, expected: u32 },
    #[error("{field}[{index}] is not finite ({value})")]
    NonFinite {
        field: &'static str,
        index: usize,
        value: f64,
    },
    #[error("unknown image encoding code {0}")]
    UnknownEncoding(u32),
    #[error("unknown command mode code {0}")]
    UnknownMode(u32),
    #[error("frame {width}x{height} exceeds the configured maximum {max_width}x{max_height}")]
    FrameTooLarge {
        width: u32,
        height: u32,
        max_width: u32,
        max_height: u32,
    },
    #[error("frame stride {stride} is below width {width} x {bytes_per_pixel} bytes per pixel")]
    StrideTooSmall {
        stride: u32,
        width: u32,
        bytes_per_pixel: u32,
    },
    #[error(
        "frame stride {stride} is above {max} (2 x width {width} x {bytes_per_pixel} bytes per \
         pixel + {STRIDE_ALIGN_SLACK} bytes of row alignment)"
    )]
    StrideTooLarge {
        stride: u32,
        width: u32,
        bytes_per_pixel: u32,
        max: u64,
    },
    #[error(
        "frame payload has {payload_len} bytes, stride {stride} x height {height} needs {expected}"
    )]
    PayloadLength {
        payload_len: usize,
        stride: u32,
        height: u32,
        expected: u64,
    },
    #[error("frame has zero width or height")]
    EmptyFrame,
    #[error("re-arm request with seq 0 or a non-zero reserved field")]
    MalformedRearm,
    #[error("camera id {got}, expected {expected}")]
    WrongCamera { got: u32, expected: u32 },
    #[error("seq {got} does not follow {previous}")]
    SeqNotIncreasing { previous: u64, got: u64 },
    #[error("timestamp {got_ns} ns is before the previous {previous_ns} ns")]
    TimeWentBackwards { previous_ns: u64, got_ns: u64 },
    #[error("timestamp {ahead_ns} ns in the future")]
    FromFuture { ahead_ns: u64 },
    #[error("message is {age_ns} ns old, the limit is {max_age_ns} ns")]
    Stale { age_ns: u64, max_age_ns: u64 },
    #[error(
        "a second publisher on this channel while the bound one is alive (last message {silent_ns} ns ago)"
    )]
    ForeignPublisher { silent_ns: u64 },
    #[error("command from publisher {publisher:#x}, which is not the controller of this session ({session})")]
    NotSessionPublisher {
        publisher: u128,
        /// What the receiver's session is: "none yet", "ambiguous: two status publishers",
        /// or the bound controller's publisher id.
        session: SessionState,
    },
}

/// A robot's view of its session with a controller (see [`SessionGate`]).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum SessionState {
    /// No controller status received yet: no command is obeyed.
    None,
    /// A second status publisher spoke while the bound one is alive: no command is obeyed
    /// until it has been quiet for the gate's timeout.
    Ambiguous,
    /// Commands from this publisher id (announced in the bound controller's status) are obeyed.
    Bound(u128),
}

impl std::fmt::Display for SessionState {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            SessionState::None => write!(f, "no controller status yet"),
            SessionState::Ambiguous => write!(f, "ambiguous: a second status publisher"),
            SessionState::Bound(id) => write!(f, "bound to command publisher {id:#x}"),
        }
    }
}

impl ValidationError {
    /// The counter this error is counted under.
    pub const fn reason(&self) -> RejectReason {
        match self {
            ValidationError::NDofOutOfRange { .. } | ValidationError::NDofMismatch { .. } => {
                RejectReason::NDof
            }
            ValidationError::NonFinite { .. } => RejectReason::NonFinite,
            ValidationError::UnknownEncoding(_) | ValidationError::UnknownMode(_) => {
                RejectReason::UnknownCode
            }
            ValidationError::FrameTooLarge { .. }
            | ValidationError::StrideTooSmall { .. }
            | ValidationError::StrideTooLarge { .. }
            | ValidationError::PayloadLength { .. }
            | ValidationError::EmptyFrame => RejectReason::FrameGeometry,
            ValidationError::WrongCamera { .. } | ValidationError::MalformedRearm => {
                RejectReason::Other
            }
            ValidationError::SeqNotIncreasing { .. }
            | ValidationError::TimeWentBackwards { .. } => RejectReason::OutOfOrder,
            ValidationError::FromFuture { .. } => RejectReason::FromFuture,
            ValidationError::Stale { .. } => RejectReason::Stale,
            ValidationError::ForeignPublisher { .. }
            | ValidationError::NotSessionPublisher { .. } => RejectReason::ForeignPublisher,
        }
    }
}

fn check_n_dof(n_dof: u32, expected: Option<u32>) -> Result<usize, ValidationError> {
    if n_dof == 0 || n_dof as usize > MAX_DOF {
        return Err(ValidationError::NDofOutOfRange {
            n_dof,
            max: MAX_DOF as u32,
        });
    }
    if let Some(expected) = expected {
        if n_dof != expected {
            return Err(ValidationError::NDofMismatch { n_dof, expected });
        }
    }
    Ok(n_dof as usize)
}

fn check_finite(field: &'static str, values: &[f64]) -> Result<(), ValidationError> {
    match values.iter().position(|v| !v.is_finite()) {
        None => Ok(()),
        Some(index) => Err(ValidationError::NonFinite {
            field,
            index,
            value: values[index],
        }),
    }
}

/// Structural check of a joint state; `expected_dof` is the robot's joint count if known.
pub fn validate_joint_state(
    msg: &JointState,
    expected_dof: Option<u32>,
) -> Result<(), ValidationError> {
    let n = check_n_dof(msg.n_dof, expected_dof)?;
    check_finite("position", &msg.position[..n])?;
    check_finite("velocity", &msg.velocity[..n])?;
    check_finite("effort", &msg.effort[..n])
}

/// Structural check of a joint command; `expected_dof` is the robot's joint count if known.
pub fn validate_joint_command(
    msg: &JointCommand,
    expected_dof: Option<u32>,
) -> Result<(), ValidationError> {
    let n = check_n_dof(msg.n_dof, expected_dof)?;
    if msg.mode != COMMAND_MODE_POSITION && msg.mode != COMMAND_MODE_HOLD {
        return Err(ValidationError::UnknownMode(msg.mode));
    }
    check_finite("position", &msg.position[..n])?;
    check_finite("velocity", &msg.velocity[..n])?;
    check_finite("acceleration", &msg.acceleration[..n])
}

/// Check of a re-arm request at `now_ns`: a non-zero `seq`, zero `reserved`, published at most
/// [`REARM_MAX_AGE_NS`] ago and at most `max_future_ns` ahead of `now_ns`.
pub fn validate_rearm(
    msg: &RearmRequest,
    now_ns: u64,
    max_future_ns: u64,
) -> Result<(), ValidationError> {
    if msg.seq == 0 || msg.reserved != 0 {
        return Err(ValidationError::MalformedRearm);
    }
    if msg.publish_time_ns > now_ns.saturating_add(max_future_ns) {
        return Err(ValidationError::FromFuture {
            ahead_ns: msg.publish_time_ns - now_ns,
        });
    }
    let age_ns = now_ns.saturating_sub(msg.publish_time_ns);
    if age_ns > REARM_MAX_AGE_NS {
        return Err(ValidationError::Stale {
            age_ns,
            max_age_ns: REARM_MAX_AGE_NS,
        });
    }
    Ok(())
}

/// Structural check of a camera frame header against its payload length and the configured
/// maximum resolution.
pub fn validate_frame(
    header: &CameraFrameHeader,
    payload_len: usize,
    max_width: u32,
    max_height: u32,
) -> Result<(), ValidationError> {
    let bpp = bytes_per_pixel(header.encoding)
        .ok_or(ValidationError::UnknownEncoding(header.encoding))?;
    if header.width == 0 || header.height == 0 {
        return Err(ValidationError::EmptyFrame);
    }
    if header.width > max_width || header.height > max_height {
        return Err(ValidationError::FrameTooLarge {
            width: header.width,
            height: header.height,
            max_width,
            max_height,
        });
    }
    if (header.stride as u64) < header.width as u64 * bpp as u64 {
        return Err(ValidationError::StrideTooSmall {
            stride: header.stride,
            width: header.width,
            bytes_per_pixel: bpp,
        });
    }
    // Rows may be padded (alignment), not padded without bound: a 64x64 frame with a 16 MiB
    // stride would make every reader copy and keep megabytes per frame.
    let max = 2 * header.width as u64 * bpp as u64 + STRIDE_ALIGN_SLACK;
    if header.stride as u64 > max {
        return Err(ValidationError::StrideTooLarge {
            stride: header.stride,
            width: header.width,
            bytes_per_pixel: bpp,
            max,
        });
    }
    let expected = header.stride as u64 * header.height as u64;
    if payload_len as u64 != expected {
        return Err(ValidationError::PayloadLength {
            payload_len,
            stride: header.stride,
            height: header.height,
            expected,
        });
    }
    Ok(())
}

/// Row padding a frame may carry beyond twice its pixel bytes (a row aligned to 256 bytes, as
/// camera drivers and GPU buffers do, fits).
pub const STRIDE_ALIGN_SLACK: u64 = 256;

/// Time limits applied by [`StreamGuard`].
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Freshness {
    /// Oldest accepted message age.
    pub max_age_ns: u64,
    /// How far ahead of the receiver's clock a timestamp may be (clock granularity, skew).
    pub max_future_ns: u64,
}

/// Per-stream ordering and freshness check, bound to one publisher at a time. Messages from
/// another publisher are rejected ([`ValidationError::ForeignPublisher`]) while the bound one is
/// alive, i.e. while its newest message is younger than the channel's maximum age; after that
/// silence (a restarted process) the next publisher binds and starts a new stream, whose
/// sequence numbers may begin again from zero. So two interleaved publishers cannot both pass
/// as new streams, and a rogue second writer is counted, not obeyed.
#[derive(Debug, Clone, Copy, Default)]
pub struct StreamGuard {
    publisher: Option<u128>,
    last_seq: u64,
    last_time_ns: u64,
    /// Silence of the bound publisher after which another may bind (None: the channel's
    /// maximum age).
    rebind_after_ns: Option<u64>,
    /// Until when this side heard nothing (see [`Self::deaf_until`]): the bound publisher's
    /// silence counts from here at the earliest.
    deaf_until_ns: u64,
}

impl StreamGuard {
    /// A guard that has seen nothing yet.
    pub const fn new() -> Self {
        Self {
            publisher: None,
            last_seq: 0,
            last_time_ns: 0,
            rebind_after_ns: None,
            deaf_until_ns: 0,
        }
    }

    /// A guard whose bound publisher may be replaced after `ns` of silence (for a channel
    /// whose messages have no maximum age, e.g. commands that carry their own deadline).
    pub const fn with_rebind_after(ns: u64) -> Self {
        Self {
            rebind_after_ns: Some(ns),
            ..Self::new()
        }
    }

    /// The publisher this stream is bound to, if any.
    pub const fn bound(&self) -> Option<u128> {
        self.publisher
    }

    /// This side heard nothing until `now_ns` (its own process stood still: SIGSTOP, swapped
    /// out): the bound publisher was not silent, the listener was deaf, so another publisher
    /// may bind only after the bound one's silence counted from here. (A forger speaking while
    /// a controller stalled bound its joint state the moment the controller woke, before the
    /// robot's own states were read: 8 x a joint's velocity limit in one command.)
    pub fn deaf_until(&mut self, now_ns: u64) {
        self.deaf_until_ns = self.deaf_until_ns.max(now_ns);
    }

    /// Checks one message and, if accepted, remembers it. `publisher` identifies the sending
    /// port (iceoryx2's unique publisher id), `time_ns` is the message's own timestamp.
    pub fn check(
        &mut self,
        publisher: u128,
        seq: u64,
        time_ns: u64,
        now_ns: u64,
        limits: Freshness,
    ) -> Result<(), ValidationError> {
        if time_ns > now_ns.saturating_add(limits.max_future_ns) {
            return Err(ValidationError::FromFuture {
                ahead_ns: time_ns - now_ns,
            });
        }
        let age_ns = now_ns.saturating_sub(time_ns);
        if age_ns > limits.max_age_ns {
            return Err(ValidationError::Stale {
                age_ns,
                max_age_ns: limits.max_age_ns,
            });
        }
        if self.publisher.is_some_and(|p| p != publisher) {
            let silent_ns = now_ns.saturating_sub(self.last_time_ns.max(self.deaf_until_ns));
            if silent_ns <= self.rebind_after_ns.unwrap_or(limits.max_age_ns) {
                return Err(ValidationError::ForeignPublisher { silent_ns });
            }
        }
        if self.publisher == Some(publisher) {
            if seq <= self.last_seq {
                return Err(ValidationError::SeqNotIncreasing {
                    previous: self.last_seq,
                    got: seq,
                });
            }
            if time_ns < self.last_time_ns {
                return Err(ValidationError::TimeWentBackwards {
                    previous_ns: self.last_time_ns,
                    got_ns: time_ns,
                });
            }
        }
        self.publisher = Some(publisher);
        self.last_seq = seq;
        self.last_time_ns = time_ns;
        Ok(())
    }
}

/// A robot's binding to one controller for a session: the robot obeys the command publisher
/// that the controller announces in its own status (`ControllerStatus::command_publisher_id`),
/// not whoever published a command first.
///
/// - The status stream is bound like any stream ([`StreamGuard`]): the first status publisher
///   binds; another one may bind after `timeout_ns` of silence of the bound one (a restarted
///   controller re-binds cleanly after that pause; the robot holds meanwhile).
/// - A second status publisher while the bound one is alive makes the session ambiguous for
///   `timeout_ns` after its last sample: no command is obeyed (the robot holds).
/// - Before the first status, no command is obeyed; a status with state
///   `CONTROLLER_STATE_STOPPED` (a clean stop) ends the session, and the next controller
///   binds only after the same settling time (`timeout_ns`) as after a crash.
///
/// So a rogue that publishes commands before the controller starts, or interleaves with it,
/// moves nothing; a rogue would have to forge the status too, and a forged status next to the
/// real controller's is detected as ambiguous. No allocation; usable in a robot's real-time
/// loop.
#[derive(Debug, Clone, Copy)]
pub struct SessionGate {
    status: StreamGuard,
    timeout_ns: u64,
    max_future_ns: u64,
    controller: Option<u128>,
    ambiguous_until_ns: u64,
    /// After a clean stop nothing binds before this (the same settling time as after a
    /// controller's death: a forged status right after a stop is not obeyed at once).
    released_until_ns: u64,
}

impl SessionGate {
    /// A gate with no session; `timeout_ns` is the status silence after which another
    /// controller may take over (a few status periods: the controller publishes at
    /// `control.status_rate_hz`).
    pub const fn new(timeout_ns: u64, max_future_ns: u64) -> Self {
        Self {
            status: StreamGuard::with_rebind_after(timeout_ns),
            timeout_ns,
            max_future_ns,
            controller: None,
            ambiguous_until_ns: 0,
            released_until_ns: 0,
        }
    }

    /// Takes one controller status from publisher `origin` (iceoryx2's publisher id of the
    /// sample) received at `now_ns`. A rejected status is returned as the error (count it).
    pub fn on_status(
        &mut self,
        status: &ControllerStatus,
        origin: u128,
        now_ns: u64,
    ) -> Result<(), ValidationError> {
        let limits = Freshness {
            max_age_ns: u64::MAX,
            max_future_ns: self.max_future_ns,
        };
        let previous = self.status.bound();
        match self
            .status
            .check(origin, status.seq, status.publish_time_ns, now_ns, limits)
        {
            Ok(()) => {
                if previous != Some(origin) {
                    // a new controller took over after the old one's silence: a new session
                    self.ambiguous_until_ns = 0;
                }
                if status.state == CONTROLLER_STATE_STOPPED {
                    // a clean stop releases the session; the next controller binds after the
                    // same settling time as after a crash
                    self.controller = None;
                    self.status = StreamGuard::with_rebind_after(self.timeout_ns);
                    self.released_until_ns = now_ns.saturating_add(self.timeout_ns);
                    return Ok(());
                }
                let id = status.command_publisher();
                if id != 0 {
                    self.controller = Some(id);
                }
                Ok(())
            }
            Err(e) => {
                if matches!(e, ValidationError::ForeignPublisher { .. }) {
                    self.ambiguous_until_ns = now_ns.saturating_add(self.timeout_ns);
                }
                Err(e)
            }
        }
    }

    /// The session as of `now_ns`.
    pub fn state(&self, now_ns: u64) -> SessionState {
        if now_ns < self.ambiguous_until_ns {
            SessionState::Ambiguous
        } else if now_ns < self.released_until_ns {
            SessionState::None
        } else {
            match self.controller {
                Some(id) => SessionState::Bound(id),
                None => SessionState::None,
            }
        }
    }

    /// Whether a command from publisher `origin` may be obeyed at `now_ns`.
    pub fn admit(&self, origin: u128, now_ns: u64) -> Result<(), ValidationError> {
        match self.state(now_ns) {
            SessionState::Bound(id) if id == origin => Ok(()),
            session => Err(ValidationError::NotSessionPublisher {
                publisher: origin,
                session,
            }),
        }
    }
}

#[cfg(test)]
mod session_tests {
    use super::*;

    fn status(seq: u64, t: u64, id: u128) -> ControllerStatus {
        let mut s = ControllerStatus {
            seq,
            publish_time_ns: t,
            ..Default::default()
        };
        s.set_command_publisher(id);
        s
    }

    #[test]
    fn the_announced_publisher_is_obeyed_and_nobody_else() {
        let ms = 1_000_000;
        let mut g = SessionGate::new(500 * ms, ms);
        // before any status: nothing is obeyed, not even the first publisher
        assert!(matches!(
            g.admit(7, 10 * ms),
            Err(ValidationError::NotSessionPublisher {
                session: SessionState::None,
                ..
            })
        ));
        g.on_status(&status(1, 10 * ms, 42), 100, 10 * ms).unwrap();
        assert!(g.admit(42, 11 * ms).is_ok());
        assert_eq!(
            g.admit(7, 11 * ms).unwrap_err().reason(),
            RejectReason::ForeignPublisher
        );
        // a forged status next to the live one: ambiguous, nothing obeyed for the timeout
        let e = g
            .on_status(&status(1, 20 * ms, 7), 200, 20 * ms)
            .unwrap_err();
        assert_eq!(e.reason(), RejectReason::ForeignPublisher);
        assert_eq!(g.state(21 * ms), SessionState::Ambiguous);
        assert!(g.admit(42, 21 * ms).is_err() && g.admit(7, 21 * ms).is_err());
        g.on_status(&status(2, 100 * ms, 42), 100, 100 * ms)
            .unwrap();
        assert!(g.admit(42, 519 * ms).is_err(), "still within the timeout");
        assert!(
            g.admit(42, 521 * ms).is_ok(),
            "the forger has been quiet for the timeout"
        );
        // a restarted controller (new status publisher announcing a new command publisher):
        // refused while the old one may be alive, bound after its silence, ambiguity cleared
        assert!(g
            .on_status(&status(1, 550 * ms, 43), 300, 550 * ms)
            .is_err());
        assert!(g.admit(42, 560 * ms).is_err());
        g.on_status(&status(2, 650 * ms, 43), 300, 650 * ms)
            .unwrap();
        assert!(g.admit(43, 651 * ms).is_ok());
        assert!(g.admit(42, 651 * ms).is_err());
        // a clean stop releases the session; the next controller binds after the settling
        // time, as after a crash (a status forged right after the stop is not obeyed at once)
        let mut stopped = status(3, 700 * ms, 43);
        stopped.state = CONTROLLER_STATE_STOPPED;
        g.on_status(&stopped, 300, 700 * ms).unwrap();
        assert_eq!(g.state(701 * ms), SessionState::None);
        assert!(g.admit(43, 701 * ms).is_err());
        g.on_status(&status(1, 710 * ms, 44), 400, 710 * ms)
            .unwrap();
        assert!(g.admit(44, 711 * ms).is_err(), "still settling");
        assert!(g.admit(44, 1_201 * ms).is_ok());
    }
}

#[cfg(test)]
mod tests;
