//! The IPC edge: subscribers, validation at the boundary, observation assembly, publishing.
//!
//! Every message that enters the controller passes through here: it is validated, and a bad
//! one is dropped, counted by reason in [`Counters`] and reported as an [`EdgeEvent`] (the
//! control thread cannot log, so events go through a lock-free ring that a non-real-time thread
//! drains and logs). Nothing in the receive or publish paths allocates once the ports exist.

use std::sync::atomic::{AtomicU64, Ordering};

use crossbeam::queue::ArrayQueue;
use iceoryx2::port::publisher::Publisher;
use iceoryx2::port::subscriber::Subscriber;
use iceoryx2::prelude::*;

pub mod history;

use crate::config::Config;
use chunkrt_ipc::services::{self, Ipc, IpcError};
use chunkrt_ipc::{
    monotonic_ns, validate_frame, validate_joint_state, validate_rearm, CameraFrameHeader,
    ControllerStatus, Freshness, JointCommand, JointState, Namespace, RearmRequest, RejectReason,
    StreamGuard, ValidationError, REJECT_REASON_COUNT,
};

/// Cameras with a counter of their own in [`Counters::frames_per_camera`].
pub const MAX_COUNTED_CAMERAS: usize = 8;

/// Counters shared by every thread of the controller (atomics only: no locks).
#[derive(Debug, Default)]
pub struct Counters {
    /// Rejected messages by [`RejectReason`] code.
    pub rejected: [AtomicU64; REJECT_REASON_COUNT],
    /// Joint states accepted (control thread's subscriber).
    pub joint_states: AtomicU64,
    /// Camera frames accepted (all cameras).
    pub frames: AtomicU64,
    /// Camera frames accepted, per camera (configuration order; cameras past
    /// [`MAX_COUNTED_CAMERAS`] count only in `frames`).
    pub frames_per_camera: [AtomicU64; MAX_COUNTED_CAMERAS],
    /// Receive errors reported by iceoryx2 itself.
    pub receive_errors: AtomicU64,
    /// Publish errors reported by iceoryx2 itself.
    pub publish_errors: AtomicU64,
    /// Valid re-arm requests not answered because they came faster than one per status period
    /// (a flood: the answers and their log lines are bounded; the newest is answered later).
    pub rearm_throttled: AtomicU64,
    /// Statuses received on this controller's own status service from another publisher
    /// ([`StatusWatch`]): a second controller in the namespace, or a forger.
    pub foreign_statuses: AtomicU64,
    /// The newest such publisher's id, low and high word (0: none seen).
    pub foreign_status_publisher: [AtomicU64; 2],
}

impl Counters {
    /// Counts one rejection.
    pub fn reject(&self, reason: RejectReason) {
        self.rejected[reason.code()].fetch_add(1, Ordering::Relaxed);
    }

    /// Snapshot of the rejection counters.
    pub fn rejected_snapshot(&self) -> [u64; REJECT_REASON_COUNT] {
        std::array::from_fn(|i| self.rejected[i].load(Ordering::Relaxed))
    }

    /// Total rejected messages.
    pub fn rejected_total(&self) -> u64 {
        self.rejected_snapshot().iter().sum()
    }
}

/// Which input a message came from.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Source {
    /// The joint state service.
    JointState,
    /// The camera with this index in the configuration.
    Camera(usize),
    /// The re-arm request service.
    Rearm,
}

/// Something worth a log line, produced where logging is not allowed.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum EdgeEvent {
    /// A message was rejected.
    Rejected {
        source: Source,
        error: ValidationError,
    },
    /// iceoryx2 reported an error on a port.
    PortError { source: Source, publish: bool },
    /// A re-arm request was answered (`REARM_*` result, `STATE_REASON_*` of a bad input).
    RearmAnswered { seq: u64, result: u32, reason: u32 },
    /// The robot stopped (`following: false`) or resumed following this controller's commands
    /// (`JOINT_STATUS_NOT_FOLLOWING` in its joint state) while the controller runs.
    Following { following: bool },
}

/// Lock-free, fixed-capacity ring of events (a full ring drops the newest; the counters still
/// count everything).
pub type EventRing = ArrayQueue<EdgeEvent>;

/// Creates an event ring of the given capacity.
pub fn event_ring(capacity: usize) -> EventRing {
    ArrayQueue::new(capacity.max(1))
}

/// Freshness limits of joint states from the configuration.
pub fn joint_state_freshness(cfg: &Config) -> Freshness {
    Freshness {
        max_age_ns: (cfg.control.joint_state_max_age_ms * 1e6) as u64,
        max_future_ns: (cfg.control.max_future_ms * 1e6) as u64,
    }
}

/// Freshness limits of camera frames from the configuration.
pub fn frame_freshness(cfg: &Config) -> Freshness {
    Freshness {
        max_age_ns: (cfg.control.frame_max_age_ms * 1e6) as u64,
        max_future_ns: (cfg.control.max_future_ms * 1e6) as u64,
    }
}

/// The next sample of `sub`; None when it is drained, or on a port error (counted and
/// reported). No allocation.
fn next_sample<T: std::fmt::Debug + iceoryx2::prelude::ZeroCopySend>(
    sub: &Subscriber<Ipc, T, ()>,
    counters: &Counters,
    events: &EventRing,
    source: Source,
) -> Option<iceoryx2::sample::Sample<Ipc, T, ()>> {
    match sub.receive() {
        Ok(sample) => sample,
        Err(_) => {
            counters.receive_errors.fetch_add(1, Ordering::Relaxed);
            let _ = events.push(EdgeEvent::PortError {
                source,
                publish: false,
            });
            None
        }
    }
}

/// Joint-state input: keeps the newest valid joint state.
pub struct JointStateInput {
    sub: Subscriber<Ipc, JointState, ()>,
    guard: StreamGuard,
    freshness: Freshness,
    n_dof: u32,
    latest: JointState,
    has_latest: bool,
    /// A second joint-state publisher spoke: the stream is ambiguous until then (ns).
    ambiguous_until_ns: u64,
    /// When the last poll ran (ns; 0: none yet).
    last_poll_ns: u64,
}

impl JointStateInput {
    /// Subscribes to `<ns>/joint_state`. Creates the port: call in the thread that uses it.
    pub fn new(node: &Node<Ipc>, ns: &Namespace, cfg: &Config) -> Result<Self, IpcError> {
        let name = ns.joint_state();
        let factory = services::joint_state_service(node, &name)?;
        Ok(Self {
            sub: services::subscriber(&factory)?,
            guard: StreamGuard::new(),
            freshness: joint_state_freshness(cfg),
            n_dof: cfg.n_dof() as u32,
            latest: JointState::default(),
            has_latest: false,
            ambiguous_until_ns: 0,
            last_poll_ns: 0,
        })
    }

    /// Drains the subscriber; returns how many new valid states arrived. No allocation.
    ///
    /// Each sample's timestamp is checked against the clock read when that sample is taken,
    /// not against the tick's wake time: a tick that woke late must not see a state measured
    /// after its wake-up as coming "from the future".
    pub fn poll(&mut self, counters: &Counters, events: &EventRing) -> usize {
        let mut accepted = 0;
        let now_ns = monotonic_ns();
        if self.last_poll_ns != 0
            && now_ns.saturating_sub(self.last_poll_ns) > self.freshness.max_age_ns
        {
            // this process stood still longer than a state may age: the robot was not silent,
            // this side was deaf; no other publisher binds on what piled up meanwhile
            self.guard.deaf_until(now_ns);
        }
        self.last_poll_ns = now_ns;
        while let Some(sample) = next_sample(&self.sub, counters, events, Source::JointState) {
            let now_ns = monotonic_ns();
            let msg: &JointState = sample.payload();
            let publisher = sample.header().publisher_id().value();
            let result = validate_joint_state(msg, Some(self.n_dof)).and_then(|()| {
                self.guard.check(
                    publisher,
                    msg.seq,
                    msg.measurement_time_ns,
                    now_ns,
                    self.freshness,
                )
            });
            match result {
                Ok(()) => {
                    self.latest = *msg;
                    self.has_latest = true;
                    accepted += 1;
                    counters.joint_states.fetch_add(1, Ordering::Relaxed);
                }
                Err(error) => {
                    if matches!(error, ValidationError::ForeignPublisher { .. }) {
                        // two publishers of joint state: which one is the robot cannot be
                        // told apart, so none is trusted until the second has been quiet
                        // for the channel's maximum age
                        self.ambiguous_until_ns = now_ns.saturating_add(self.freshness.max_age_ns);
                    }
                    counters.reject(error.reason());
                    let _ = events.push(EdgeEvent::Rejected {
                        source: Source::JointState,
                        error,
                    });
                }
            }
        }
        accepted
    }

    /// The newest valid joint state, if any arrived yet (it may have aged since: check
    /// `measurement_time_ns`).
    pub fn latest(&self) -> Option<&JointState> {
        self.has_latest.then_some(&self.latest)
    }

    /// The newest valid joint state unless the stream is ambiguous at `now_ns` (a second
    /// publisher spoke within `joint_state_max_age_ms`): then none, and the controller holds
    /// as for a missing state. Covers a forger that bound first as well as one that came
    /// second.
    pub fn trusted(&self, now_ns: u64) -> Option<&JointState> {
        if now_ns < self.ambiguous_until_ns {
            None
        } else {
            self.latest()
        }
    }

    /// While the stream is ambiguous, the bound publisher's newest state if it is fresh at
    /// `now_ns` (within the channel's maximum age): not trusted to lead the robot, but where a
    /// hold holds.
    pub fn bound_fresh(&self, now_ns: u64) -> Option<&JointState> {
        self.latest().filter(|s| {
            self.ambiguous(now_ns)
                && now_ns.saturating_sub(s.measurement_time_ns) <= self.freshness.max_age_ns
        })
    }

    /// True while a second joint-state publisher makes the stream ambiguous.
    pub fn ambiguous(&self, now_ns: u64) -> bool {
        now_ns < self.ambiguous_until_ns
    }
}

/// The newest frame of one camera, copied out of shared memory into a buffer owned by the
/// observation (allocated once for the camera's configured maximum size).
#[derive(Debug, Clone)]
pub struct Frame {
    /// Camera name from the configuration.
    pub name: String,
    /// Header of the newest valid frame (all zero until one arrived).
    pub header: CameraFrameHeader,
    /// Pixels: `header.stride * header.height` bytes at the front of `data`.
    pub data: Vec<u8>,
    /// A frame has arrived.
    pub valid: bool,
}

impl Frame {
    /// Bytes a frame buffer of a `width` × `height` camera holds: the largest frame validation
    /// accepts (the widest row padding allowed).
    pub fn capacity(width: u32, height: u32) -> usize {
        (2 * width as usize * 3 + chunkrt_ipc::STRIDE_ALIGN_SLACK as usize) * height as usize
    }

    /// An empty buffer named `name` for a `width` × `height` camera.
    fn empty(name: &str, width: u32, height: u32) -> Self {
        Frame {
            name: name.to_string(),
            header: CameraFrameHeader::default(),
            data: vec![0; Self::capacity(width, height)],
            valid: false,
        }
    }

    /// Makes this an rgb8 frame of `width` × `height` (tightly packed rows) captured at
    /// `capture_time_ns`, and returns its pixel bytes to be written: a frame that did not come
    /// over IPC (a simulator renders it, a remote client sends it). `None` when the buffer is
    /// smaller than the frame.
    pub fn write_rgb8(
        &mut self,
        width: u32,
        height: u32,
        capture_time_ns: u64,
    ) -> Option<&mut [u8]> {
        let n = 3 * width as usize * height as usize;
        if n > self.data.len() {
            return None;
        }
        self.header = CameraFrameHeader {
            capture_time_ns,
            encoding: chunkrt_ipc::ENCODING_RGB8,
            width,
            height,
            stride: 3 * width,
            ..Default::default()
        };
        self.valid = true;
        Some(&mut self.data[..n])
    }

    /// The image bytes of the newest frame.
    pub fn pixels(&self) -> &[u8] {
        let n = (self.header.stride as usize) * (self.header.height as usize);
        &self.data[..n.min(self.data.len())]
    }
}

/// Camera input: one subscriber per configured camera.
pub struct CameraInput {
    subs: Vec<Subscriber<Ipc, [u8], CameraFrameHeader>>,
    guards: Vec<StreamGuard>,
    limits: Vec<(u32, u32)>,
    freshness: Freshness,
}

impl CameraInput {
    /// Subscribes to every configured camera. Creates ports: call in the thread that uses them.
    pub fn new(node: &Node<Ipc>, ns: &Namespace, cfg: &Config) -> Result<Self, IpcError> {
        let mut subs = Vec::new();
        for cam in &cfg.cameras {
            let name = ns.camera(&cam.name);
            let factory = services::camera_service(node, &name)?;
            subs.push(services::camera_subscriber(&factory)?);
        }
        Ok(Self {
            guards: vec![StreamGuard::new(); subs.len()],
            limits: cfg.cameras.iter().map(|c| (c.width, c.height)).collect(),
            subs,
            freshness: frame_freshness(cfg),
        })
    }

    /// Drains every camera, copying the newest valid frame of each into `frames`
    /// (same order as the configuration). Returns the number of frames accepted. Timestamps
    /// are checked against the clock read when each sample is taken.
    pub fn poll(&mut self, frames: &mut [Frame], counters: &Counters, events: &EventRing) -> usize {
        let mut accepted = 0;
        for (i, sub) in self.subs.iter().enumerate() {
            loop {
                let sample = match sub.receive() {
                    Ok(Some(s)) => s,
                    Ok(None) => break,
                    Err(_) => {
                        counters.receive_errors.fetch_add(1, Ordering::Relaxed);
                        let _ = events.push(EdgeEvent::PortError {
                            source: Source::Camera(i),
                            publish: false,
                        });
                        break;
                    }
                };
                let now_ns = monotonic_ns();
                let header = *sample.user_header();
                let payload: &[u8] = sample.payload();
                let (max_w, max_h) = self.limits[i];
                let result = validate_frame(&header, payload.len(), max_w, max_h)
                    .and(if header.camera_id as usize == i {
                        Ok(())
                    } else {
                        Err(ValidationError::WrongCamera {
                            got: header.camera_id,
                            expected: i as u32,
                        })
                    })
                    .and_then(|()| {
                        self.guards[i].check(
                            sample.header().publisher_id().value(),
                            header.seq,
                            header.capture_time_ns,
                            now_ns,
                            self.freshness,
                        )
                    });
                match result {
                    Ok(()) => {
                        let f = &mut frames[i];
                        if f.data.len() < payload.len() {
                            // only if the configured maximum was exceeded, which validation
                            // prevents; kept for safety
                            f.data.resize(payload.len(), 0);
                        }
                        f.data[..payload.len()].copy_from_slice(payload);
                        f.header = header;
                        f.valid = true;
                        accepted += 1;
                        counters.frames.fetch_add(1, Ordering::Relaxed);
                        if let Some(c) = counters.frames_per_camera.get(i) {
                            c.fetch_add(1, Ordering::Relaxed);
                        }
                    }
                    Err(error) => {
                        counters.reject(error.reason());
                        let _ = events.push(EdgeEvent::Rejected {
                            source: Source::Camera(i),
                            error,
                        });
                    }
                }
            }
        }
        accepted
    }
}

/// The newest camera frames and joint state, with their ages: what the policy sees.
#[derive(Debug, Clone)]
pub struct Observation {
    /// Newest valid joint state.
    pub joint_state: JointState,
    /// One entry per configured camera, in configuration order, then one per delayed view of
    /// the policy ([`history::FrameHistory`]).
    pub frames: Vec<Frame>,
    /// When the observation was assembled (monotonic ns).
    pub assembled_ns: u64,
}

impl Observation {
    /// An empty observation with frame buffers sized for the configured cameras.
    pub fn new(cfg: &Config) -> Self {
        Self::with_views(cfg, &[])
    }

    /// An empty observation with frame buffers for the configured cameras, then one for each
    /// delayed view ([`history::FrameHistory`]; a view of an unknown camera gets none).
    pub fn with_views(cfg: &Config, views: &[chunkrt_policy::DelayedView]) -> Self {
        let cams = cfg
            .cameras
            .iter()
            .map(|c| Frame::empty(&c.name, c.width, c.height));
        let views = views.iter().filter_map(|v| {
            let c = cfg.cameras.iter().find(|c| c.name == v.camera)?;
            Some(Frame::empty(&v.name, c.width, c.height))
        });
        Self {
            joint_state: JointState::default(),
            frames: cams.chain(views).collect(),
            assembled_ns: 0,
        }
    }

    /// Age of the joint state at assembly time (ns).
    pub fn joint_state_age_ns(&self) -> u64 {
        self.assembled_ns
            .saturating_sub(self.joint_state.measurement_time_ns)
    }

    /// Age of camera `i`'s frame at assembly time (ns); `None` if none arrived.
    pub fn frame_age_ns(&self, i: usize) -> Option<u64> {
        let f = self.frames.get(i)?;
        f.valid
            .then(|| self.assembled_ns.saturating_sub(f.header.capture_time_ns))
    }

    /// Capture time of the observation: the joint state's measurement time.
    pub fn t_obs_ns(&self) -> u64 {
        self.joint_state.measurement_time_ns
    }
}

/// Re-arm requests (`<ns>/rearm`): the newest valid request not answered yet.
pub struct RearmInput {
    sub: Subscriber<Ipc, RearmRequest, ()>,
    max_future_ns: u64,
    last_seq: u64,
    /// A request waiting for the next answer slot, and when the last answer was given.
    pending: Option<u64>,
    last_answer_ns: Option<u64>,
    /// The least time between two answers (one status period).
    min_interval_ns: u64,
}

impl RearmInput {
    /// Subscribes to `<ns>/rearm`. Creates the port: call in the thread that uses it.
    pub fn new(node: &Node<Ipc>, ns: &Namespace, cfg: &Config) -> Result<Self, IpcError> {
        let name = ns.rearm();
        let factory = services::rearm_service(node, &name)?;
        Ok(Self {
            sub: services::subscriber(&factory)?,
            max_future_ns: (cfg.control.max_future_ms * 1e6) as u64,
            last_seq: 0,
            pending: None,
            last_answer_ns: None,
            min_interval_ns: (1e9 / cfg.control.status_rate_hz) as u64,
        })
    }

    /// Drains the subscriber; returns the seq of the newest valid request with a seq not seen
    /// before (a client repeats its request until answered), at most one per status period: a
    /// request that comes sooner waits for the next slot (the newest wins) and the ones it
    /// replaces are counted in `rearm_throttled`, so a flood costs at most one answer, one
    /// status and one log line per period. Invalid ones are counted and reported. No
    /// allocation.
    pub fn poll(&mut self, counters: &Counters, events: &EventRing) -> Option<u64> {
        let now = monotonic_ns();
        while let Some(sample) = next_sample(&self.sub, counters, events, Source::Rearm) {
            let msg: &RearmRequest = sample.payload();
            match validate_rearm(msg, monotonic_ns(), self.max_future_ns) {
                Ok(()) if msg.seq != self.last_seq => {
                    self.last_seq = msg.seq;
                    if self.pending.replace(msg.seq).is_some() {
                        counters.rearm_throttled.fetch_add(1, Ordering::Relaxed);
                    }
                }
                Ok(()) => {}
                Err(error) => {
                    counters.reject(error.reason());
                    let _ = events.push(EdgeEvent::Rejected {
                        source: Source::Rearm,
                        error,
                    });
                }
            }
        }
        let due = self
            .last_answer_ns
            .is_none_or(|t| now.saturating_sub(t) >= self.min_interval_ns);
        if due && self.pending.is_some() {
            self.last_answer_ns = Some(now);
            return self.pending.take();
        }
        None
    }
}

/// Publishes joint commands.
pub struct CommandOutput {
    publisher: Publisher<Ipc, JointCommand, ()>,
    /// How long after its tick a command may still be applied (ns).
    deadline_ns: u64,
    /// The last sequence number stamped.
    seq: u64,
}

impl CommandOutput {
    /// Creates the publisher on `<ns>/joint_command`; commands expire `deadline_ns` after
    /// their tick.
    pub fn new(node: &Node<Ipc>, ns: &Namespace, deadline_ns: u64) -> Result<Self, IpcError> {
        let name = ns.joint_command();
        let factory = services::joint_command_service(node, &name)?;
        Ok(Self {
            publisher: services::publisher(&factory)?,
            deadline_ns,
            seq: 0,
        })
    }

    /// iceoryx2's unique id of the command publisher, announced in the status so that the
    /// robot binds to this controller for the session ([`chunkrt_ipc::SessionGate`]).
    pub fn id(&self) -> u128 {
        self.publisher.id().value()
    }

    /// Publishes the motion in `cmd` of the tick that woke at `tick_ns`, stamping the header —
    /// the one place it is written: the next `seq`, `deadline_ns` = `tick_ns` + the configured
    /// deadline (a tick preempted past it publishes a command the robot discards), and
    /// `publish_time_ns` = now. False if iceoryx2 refused. The loan is the one allocation
    /// iceoryx2 0.10 makes per publish.
    pub fn publish(&mut self, cmd: &JointCommand, tick_ns: u64) -> bool {
        match self.publisher.loan_uninit() {
            Ok(sample) => {
                self.seq += 1;
                let mut c = *cmd;
                c.seq = self.seq;
                c.deadline_ns = tick_ns + self.deadline_ns;
                c.publish_time_ns = monotonic_ns();
                sample.write_payload(c).send().is_ok()
            }
            Err(_) => false,
        }
    }
}

/// Watches this controller's own status service for statuses from another publisher: a second
/// controller in the namespace, or a forger. A robot that binds sessions holds while one speaks
/// (its session is ambiguous, [`chunkrt_ipc::SessionGate`]); this makes the reason visible on
/// the controller's side: counted in the status and named in the log.
pub struct StatusWatch {
    subscriber: Subscriber<Ipc, ControllerStatus, ()>,
}

impl StatusWatch {
    /// Subscribes to `<ns>/status`.
    pub fn new(node: &Node<Ipc>, ns: &Namespace) -> Result<Self, IpcError> {
        let name = ns.status();
        let factory = services::status_service(node, &name)?;
        Ok(Self {
            subscriber: services::subscriber(&factory)?,
        })
    }

    /// Drains the subscriber and counts the statuses whose publisher is not `own` (this
    /// controller's status publisher; 0 while it is not known yet, and nothing is counted).
    /// Returns the newest foreign publisher seen in this poll.
    pub fn poll(&self, own: u128, counters: &Counters) -> Option<u128> {
        let mut newest = None;
        while let Ok(Some(sample)) = self.subscriber.receive() {
            let origin = sample.origin().value();
            if own == 0 || origin == own {
                continue;
            }
            counters.foreign_statuses.fetch_add(1, Ordering::Relaxed);
            counters.foreign_status_publisher[0].store(origin as u64, Ordering::Relaxed);
            counters.foreign_status_publisher[1].store((origin >> 64) as u64, Ordering::Relaxed);
            newest = Some(origin);
        }
        newest
    }
}

/// Publishes the controller status.
pub struct StatusOutput {
    publisher: Publisher<Ipc, ControllerStatus, ()>,
}

impl StatusOutput {
    /// Creates the publisher on `<ns>/status`.
    pub fn new(node: &Node<Ipc>, ns: &Namespace) -> Result<Self, IpcError> {
        let name = ns.status();
        let factory = services::status_service(node, &name)?;
        Ok(Self {
            publisher: services::publisher(&factory)?,
        })
    }

    /// This publisher's iceoryx2 id (the origin of its samples).
    pub fn id(&self) -> u128 {
        self.publisher.id().value()
    }

    /// Publishes one status message; false if iceoryx2 refused.
    pub fn publish(&self, status: &ControllerStatus) -> bool {
        match self.publisher.loan_uninit() {
            Ok(sample) => sample.write_payload(*status).send().is_ok(),
            Err(_) => false,
        }
    }
}
