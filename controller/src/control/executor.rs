//! The chunk executor: one call per control tick turns the chunks received so far into one
//! joint command. A short pipeline of stages, each owning its state (allocated in
//! [`Executor::new`]):
//!
//! 1. the chunk timeline (`timeline.rs`): receive, validate and place chunks (the strategy, one
//!    file each under `strategy/`), prune them, sample the target at the tick;
//! 2. input checks: joint state (shape, age, re-sync after a gap), cameras, the chunk's verdict;
//! 3. the safety state machine (`safety::Safety`) takes the tick's worst problem and moves;
//! 4. target shaping (`shaping.rs`): the target becomes ruckig's target within the limits (or a
//!    brake);
//! 5. ruckig, then the command (and a FAULT if ruckig cannot go on);
//! 6. the inference trigger (`request.rs`).
//!
//! [`Executor::tick`], [`Executor::record_timing`] and [`Executor::fill_status`] never allocate,
//! lock or do I/O.
//!
//! Owns: the order of the stages and the generator's state. Must not depend on: IPC services,
//! the policy, threads.

use crate::config::Config;
use chunkrt_ipc::{
    ControllerStatus, JointCommand, JointState, COMMAND_MODE_HOLD, COMMAND_MODE_POSITION, MAX_DOF,
};

use super::handoff::{self, ChunkSender, RequestReceiver};
use super::interp::Sample;
use super::ms_to_ns;
use super::otg::{Otg, OtgError, OtgInput, OtgOutput, OtgResult};
use super::request::Requests;
use super::safety::{EventReader, Reason, Safety, State};
use super::shaping::{self, Limits};
use super::timeline::Timeline;
use super::timing::TickTiming;
use crate::chunk::ActionChunk;

pub use super::safety::Rearm;
pub use crate::config::{Strategy, Trigger};

/// The executor could not be built.
#[derive(Debug, thiserror::Error)]
pub enum ExecutorError {
    #[error(transparent)]
    Generator(#[from] OtgError),
}

/// What one tick did (the command itself is written into the caller's `JointCommand`).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct TickReport {
    /// State after this tick.
    pub state: State,
    /// Why the executor is in that state (the reason of the last transition; None: none yet).
    pub reason: Option<Reason>,
    /// False only before the first joint state ever arrived (nothing sensible to command).
    pub publish: bool,
    /// Chunk the command was sampled from (0: none).
    pub chunk_id: u64,
    /// A different chunk took effect this tick.
    pub switched: bool,
    /// An inference request was published this tick.
    pub requested: bool,
    /// Interpolated, blended target before ruckig (positions; meaningful when RUNNING).
    pub target: [f64; MAX_DOF],
    /// ruckig's result for this tick.
    pub generator: OtgResult,
}

/// Both ends the inference thread needs: where to send chunks, where to read requests, and
/// where to say which cameras are stale.
#[derive(Clone)]
pub struct InferenceLink {
    /// Chunks, inference → control.
    pub chunks: ChunkSender,
    /// Inference requests, control → inference.
    pub requests: RequestReceiver,
    /// Cameras the policy would use with a missing or too old frame (bit i = camera i), set by
    /// the inference thread at every poll; the control tick holds while it is non-zero.
    pub stale_cameras: std::sync::Arc<std::sync::atomic::AtomicU64>,
    /// Requests answered without a chunk because the source failed (a remote server that is
    /// down, an inference error), counted by the inference side: the control tick asks again
    /// at its next tick instead of waiting out `execution.inference_timeout_ms`.
    pub failed_requests: std::sync::Arc<std::sync::atomic::AtomicU64>,
}

/// ruckig's `Synchronization::None`.
const SYNC_NONE: i32 = 3;
/// After a gap in the joint state, and when leaving HOLD, a measured position further than this
/// from the generator's own (a robot that restarted or was moved) restarts the generator from
/// the measured state (rad or unit).
const RESUME_TOLERANCE: f64 = 0.01;
/// The least tracking gain (1/s) of a rejoin (a controller the robot does not obey following
/// the measured arm): also with the fixed-target chase (`tracking_gain` 0).
const REJOIN_GAIN: f64 = 10.0;
/// The longest hold (ns) after which a robot that says it followed through a gap in its states
/// resumes from this generator's own stream ([`Executor::followed_through_gap`]).
const FOLLOWED_HOLD_NS: u64 = 5_000_000;
/// A gap between two ticks longer than this (ns) means the controller itself stood still (a
/// SIGSTOP, a swapped-out process): the robot did not wait for it.
const STALL_NS: u64 = 50_000_000;

/// Velocity below which a braking joint counts as stopped (per second).
const STOPPED_VELOCITY: f64 = 1e-6;
/// Acceleration below which a braking joint counts as stopped (per second²).
const STOPPED_ACCELERATION: f64 = 1e-6;

/// The joint state as this tick sees it.
#[derive(Debug, Clone, Copy)]
struct JointCheck {
    /// Present and of the configured robot's shape.
    bad: bool,
    /// Present, good and younger than `joint_state_max_age_ms`.
    fresh: bool,
    /// The robot obeys this executor's commands (or does not report whom it obeys).
    obeyed: bool,
}

/// The control tick. See the module documentation; built once with [`Executor::new`].
pub struct Executor {
    limits: Limits,
    timeline: Timeline,
    safety: Safety,
    requests: Requests,
    otg: Otg,
    otg_in: OtgInput,
    otg_out: OtgOutput,
    /// The generator has a state to move from (a fresh joint state was seen).
    initialized: bool,
    /// The problem the last tick saw (None: inputs good).
    last_problem: Option<Reason>,
    /// See [`InferenceLink::stale_cameras`].
    stale_cameras: std::sync::Arc<std::sync::atomic::AtomicU64>,
    /// The id of the command publisher the commands leave by ([`Self::set_command_publisher`]).
    command_publisher: Option<u128>,
    /// See [`InferenceLink::failed_requests`], and its value at the last tick.
    failed_requests: std::sync::Arc<std::sync::atomic::AtomicU64>,
    failed_seen: u64,
    /// The source failed since the last chunk arrived.
    source_failing: bool,
    /// Its value at the last tick (for the status).
    stale_seen: u64,
    /// The joint state was missing or stale at some tick since the last fresh one (a robot
    /// restart, a stalled driver): on the next fresh state the generator may have to re-sync.
    js_gap: bool,
    /// When the last tick ran (ns; 0: none yet), and the generator re-seeds after a stall of
    /// the controller itself.
    last_tick_ns: u64,
    /// Re-seeds from the robot's measured state after a stall of this process.
    pub stall_reseeds: u64,
    chunk_tx: ChunkSender,
    req_rx: RequestReceiver,
    timing: TickTiming,
    target: Sample,
    scratch: Sample,
    /// While the robot obeys another controller (or nobody yet): the measured state the
    /// generator tracks instead of stepping to it, so that this controller's own command stream
    /// stays continuous and, when the robot binds it, starts near the arm.
    rejoin: Sample,
    rejoining: bool,
    /// `execution.stale_hold = "last_state"`: while the joint states stop, the generator goes
    /// to `last_state` (the last fresh measured position), at rest, instead of braking on past
    /// it; at the first fresh state after, it takes the robot's velocity.
    hold_last_state: bool,
    last_state: Sample,
    have_last_state: bool,
    /// This tick's [`Executor::hold_at`] state (the bound robot's, while the stream is
    /// ambiguous): after a stall of this process the generator re-seeds there.
    bound: Option<JointState>,
    /// The range each command may take: the configured position range, widened to an arm seeded
    /// outside it (a reflex in an extreme pose, a person who moved the arm) and narrowed back as
    /// the commands return inside (never further out than the range or the arm was).
    range_lo: [f64; MAX_DOF],
    range_hi: [f64; MAX_DOF],
    last_primary: u64,
    tracking_gain: f64,
    control_period_ns: u64,
    js_max_age_ns: u64,
    overrun_streak: u32,
    ticks: u64,
    joint_state_age_ns: u64,
    limit_warnings: u64,
    /// Generator steps of the next tick ([`Self::set_cycles`]).
    cycles: u32,
}

impl Executor {
    /// Builds the executor for a validated configuration; allocates everything it will need.
    pub fn new(config: &Config) -> Result<Self, ExecutorError> {
        let e = &config.execution;
        let n = config.n_dof().min(MAX_DOF);
        let limits = Limits::new(config, n);
        let control_period_ns = config.control_period_ns().max(1);
        let otg = Otg::new(control_period_ns as f64 * 1e-9)?;
        let mut otg_in = OtgInput {
            dofs: n as u32,
            ..Default::default()
        };
        // Every joint is tracked on its own (time-optimal per joint): a time-synchronised
        // generator would slow every joint down to the slowest one (e.g. a gripper step).
        otg_in.synchronization = SYNC_NONE;
        otg_in.max_velocity = limits.vmax;
        otg_in.max_acceleration = limits.amax;
        otg_in.max_jerk = limits.jmax;
        otg_in.min_position = limits.pmin;
        otg_in.max_position = limits.pmax;
        let (chunk_tx, chunk_rx) = handoff::channel(1, 64);
        let (req_tx, req_rx) = handoff::request_channel();
        Ok(Self {
            timeline: Timeline::new(config, n, limits.step, chunk_rx),
            limits,
            safety: Safety::new(ms_to_ns(e.hold_to_fault_ms)),
            requests: Requests::new(config, req_tx),
            otg,
            otg_in,
            otg_out: OtgOutput::default(),
            initialized: false,
            last_problem: None,
            stale_cameras: Default::default(),
            command_publisher: None,
            failed_requests: Default::default(),
            failed_seen: 0,
            source_failing: false,
            stale_seen: 0,
            js_gap: false,
            last_tick_ns: 0,
            stall_reseeds: 0,
            chunk_tx,
            req_rx,
            timing: TickTiming::new(),
            target: Sample::default(),
            scratch: Sample::default(),
            rejoin: Sample::default(),
            rejoining: false,
            hold_last_state: e.stale_hold == crate::config::StaleHold::LastState,
            last_state: Sample::default(),
            have_last_state: false,
            bound: None,
            range_lo: otg_in.min_position,
            range_hi: otg_in.max_position,
            last_primary: 0,
            tracking_gain: e.tracking_gain,
            control_period_ns,
            js_max_age_ns: ms_to_ns(config.control.joint_state_max_age_ms),
            overrun_streak: e.overrun_streak.max(1),
            ticks: 0,
            joint_state_age_ns: 0,
            limit_warnings: 0,
            cycles: 1,
        })
    }

    /// The inference thread's ends of the hand-offs (call once per inference thread).
    pub fn connect(&self) -> InferenceLink {
        InferenceLink {
            chunks: self.chunk_tx.clone(),
            requests: self.req_rx.clone(),
            stale_cameras: self.stale_cameras.clone(),
            failed_requests: self.failed_requests.clone(),
        }
    }

    /// The iceoryx2 id of the publisher the commands leave by. From then on a robot that reports
    /// the session it obeys (`JOINT_STATUS_SESSION_REPORTED`) is checked at every tick: when it
    /// obeys another publisher or none, or refused the last command as too far from where it
    /// is, the executor holds ([`Reason::NotObeyed`]) and its generator tracks the measured arm
    /// (a refused command: steps to it), so the hand-over is bumpless when the robot binds it and
    /// the command stream stays continuous. No allocation.
    pub fn set_command_publisher(&mut self, id: u128) {
        self.command_publisher = Some(id);
    }

    /// The next tick advances the generator by `cycles` control periods (0..=50): on a robot's
    /// clock, the cycles the robot ran since the last tick, so that a tick that missed one
    /// continues where the robot is in time instead of a period behind, and a tick while the
    /// robot is quiet does not advance at all. No allocation.
    pub fn set_cycles(&mut self, cycles: u32) {
        self.cycles = cycles.min(50);
    }

    /// The bound robot's newest state while the joint-state stream is ambiguous (another
    /// publisher spoke: none is trusted to lead): where the robot is, so that a hold at the
    /// robot's last state (`stale_hold = "last_state"`) holds there, not where the arm was when
    /// the trusted states stopped (after this controller stalled for 1.5 s while a forger
    /// spoke, that was 0.04 rad from the arm). Never leads. No allocation.
    pub fn hold_at(&mut self, js: &JointState) {
        if !self.hold_last_state {
            return;
        }
        for j in 0..self.limits.n {
            let p = js.position[j];
            if p.is_finite() {
                self.last_state.position[j] = p;
            }
        }
        self.have_last_state = true;
        self.bound = Some(*js);
    }

    /// Runs without a chunk source (`policy.kind = "hold"`): waiting for a chunk in STARTING is
    /// the plan, not a stuck state, so it does not escalate to FAULT.
    pub fn without_chunk_source(&mut self) {
        self.safety.set_escalation(false);
    }

    /// Reader of the state-transition events (drain and log them off the control thread).
    pub fn events(&self) -> EventReader {
        self.safety.events()
    }

    /// Current state.
    pub fn state(&self) -> State {
        self.safety.state()
    }

    /// Tick timing histograms (read them off the tick, e.g. for the exit summary).
    pub fn timing(&self) -> &TickTiming {
        &self.timing
    }

    /// The current inference-delay estimate d (action steps).
    pub fn delay_estimate(&self) -> usize {
        self.timeline.delay_estimate()
    }

    /// Chunks accepted / rejected so far.
    pub fn chunk_counts(&self) -> (u64, u64) {
        (self.timeline.received, self.timeline.rejected)
    }

    /// Leaves FAULT for STARTING (the generator is re-initialised from the next fresh joint
    /// state; RUNNING follows once a chunk arrives and the inputs are good). Refused in any other
    /// state, and while an input from outside is still bad at the last tick (joint state missing,
    /// stale or not matching the robot, a stale camera): the reason says which. No allocation.
    pub fn rearm(&mut self, now_ns: u64) -> Rearm {
        let answer = self.safety.rearm(now_ns, self.last_problem);
        if answer == Rearm::Accepted {
            self.initialized = false;
            self.timeline.bad_input = None;
            self.requests.landed();
        }
        answer
    }

    /// Why the executor is in its current state (the reason of the last transition).
    pub fn state_reason(&self) -> Option<Reason> {
        self.safety.reason()
    }

    /// Records the timing of the tick just finished: scheduled for `scheduled_ns`, woke at
    /// `woke_ns`, done (command published) at `done_ns`. A streak of overruns puts the
    /// executor in HOLD at the next tick. No allocation.
    pub fn record_timing(&mut self, scheduled_ns: u64, woke_ns: u64, done_ns: u64) -> bool {
        self.timing
            .record(scheduled_ns, woke_ns, done_ns, self.control_period_ns)
    }

    /// Fills the executor's part of the status: state, n_dof, ticks, overruns, chunks,
    /// inference latency, lateness / compute quantiles, joint-state age, hold entries.
    /// (seq, publish time, joint_states, frames and rejected are the caller's.) No allocation.
    pub fn fill_status(&self, st: &mut ControllerStatus) {
        st.state = self.safety.state().code();
        st.n_dof = self.limits.n as u32;
        st.ticks = self.ticks;
        st.overruns = self.timing.overruns;
        st.chunks = self.timeline.received;
        st.last_inference_latency_ns = self.timeline.last_inference_latency_ns;
        let l = self.timing.lateness_quantiles();
        let c = self.timing.compute_quantiles();
        st.lateness_p50_ns = l.p50;
        st.lateness_p99_ns = l.p99;
        st.lateness_max_ns = l.max;
        st.compute_p50_ns = c.p50;
        st.compute_p99_ns = c.p99;
        st.compute_max_ns = c.max;
        st.joint_state_age_ns = self.joint_state_age_ns;
        st.hold_entries = self.safety.hold_entries();
        st.stale_cameras = self.stale_seen;
    }

    /// Hands a chunk to the executor directly (instead of through [`Executor::connect`]);
    /// the chunk is validated and takes effect according to the strategy.
    pub fn offer_chunk(&mut self, chunk: ActionChunk, now_ns: u64) {
        self.timeline.accept(chunk, now_ns);
        self.requests.landed();
    }

    /// One control tick at time `now_ns` (the tick's scheduled time, monotonic ns).
    /// `joint_state` is the newest joint state that passed boundary validation (None if none
    /// yet). Writes the command to publish into `command` and returns what happened.
    /// No allocation, no locks, no I/O.
    pub fn tick(
        &mut self,
        now_ns: u64,
        joint_state: Option<&JointState>,
        command: &mut JointCommand,
    ) -> TickReport {
        self.ticks += 1;
        let stalled = self.last_tick_ns != 0 && now_ns.saturating_sub(self.last_tick_ns) > STALL_NS;
        self.last_tick_ns = now_ns;
        if self.timeline.receive(now_ns) {
            self.requests.landed();
            self.source_failing = false;
        }
        let failed = self
            .failed_requests
            .load(std::sync::atomic::Ordering::Relaxed);
        if failed != self.failed_seen {
            // the request in flight came back without a chunk: ask again now
            self.failed_seen = failed;
            self.source_failing = true;
            self.requests.landed();
        }
        let js = self.check_joint_state(now_ns, joint_state);
        self.stale_seen = self
            .stale_cameras
            .load(std::sync::atomic::Ordering::Relaxed);
        let primary = self
            .timeline
            .evaluate(now_ns as i64, &mut self.target, &mut self.scratch);
        let problem = self.problem(js, primary);
        self.last_problem = problem;
        if let (State::Starting, true, false, Some(js)) =
            (self.safety.state(), js.fresh, self.initialized, joint_state)
        {
            self.init_generator(js);
        }
        // this process stood still (SIGSTOP, swapped out): the robot did not, and the
        // generator's state is where the controller left it. Its first command now starts from
        // where the robot is, not a step there after the robot refused the stale ones: the
        // command stream stays continuous across the gap (0.17 rad in one tick before).
        if stalled {
            // one period from here, not the stall's cycles at once, whether or not a trusted
            // state came with it (a forger speaking meanwhile leaves none: the generator then
            // jumped the stall's cycles in one command, 12 x a joint's velocity limit)
            self.cycles = 1;
        }
        // no trusted state (another publisher spoke meanwhile): the bound robot's newest one
        // is where the robot is, and the hold starts there (a forger speaking during the stall
        // kept the generator where the arm had been: 0.04 rad off)
        let bound = self.bound.take();
        if let (true, true, None, Some(b)) = (stalled, self.initialized, joint_state, bound) {
            let at_rest = b.status_flags & chunkrt_ipc::JOINT_STATUS_AT_REST != 0;
            if self.away_from(&b) || at_rest {
                self.init_generator(&b);
                self.stall_reseeds += 1;
            }
        }
        if let (true, true, true, Some(js)) = (stalled, js.fresh, self.initialized, joint_state) {
            // the robot ran on meanwhile; a robot whose driver holds it at rest was stopped by
            // its driver, whatever our generator was doing when this process stood still
            let at_rest = js.status_flags & chunkrt_ipc::JOINT_STATUS_AT_REST != 0;
            if self.away_from(js) || at_rest {
                self.init_generator(js);
                self.stall_reseeds += 1;
            }
        }
        if let (Some(State::Hold), Some(js)) = (
            self.safety.step(now_ns, problem, self.initialized),
            joint_state,
        ) {
            // Resume from where the robot is, not from where the controller last commanded it
            // (after a robot restart they can be far apart). A robot that followed the braking
            // keeps the generator's own (continuous) state.
            // (a robot whose driver says it followed through the hold: see `check_joint_state`)
            if self.safety.state() == State::Running
                && !self.followed_through_gap(js, now_ns)
                && self.away_from(js)
            {
                self.init_generator(js);
            }
        }
        let mut report = self.report(primary);
        if self.initialized {
            let mode = self.step_generator(now_ns, &mut report);
            self.write_command(command, mode, &mut report, primary);
        } else {
            self.write_idle_command(command);
        }
        self.request(now_ns, &mut report);
        report
    }

    /// Stage 2: the joint state's shape and age; after a gap, a fresh state away from the
    /// generator re-syncs it (a restarted robot must never be commanded back).
    fn check_joint_state(&mut self, now_ns: u64, joint_state: Option<&JointState>) -> JointCheck {
        let mut check = JointCheck {
            bad: false,
            fresh: false,
            obeyed: true,
        };
        if let Some(js) = joint_state {
            if js.n_dof as usize != self.limits.n {
                check.bad = true;
            } else {
                self.joint_state_age_ns = now_ns.saturating_sub(js.measurement_time_ns);
                check.fresh = self.joint_state_age_ns <= self.js_max_age_ns;
            }
        }
        if let (true, Some(js), Some(me)) = (check.fresh, joint_state, self.command_publisher) {
            // a robot that says whom it obeys: not us (another controller, nobody yet), or our
            // last command refused as too far from where it is
            let ours = js.obeyed_publisher().is_none_or(|id| id == me);
            let far = js.status_flags & chunkrt_ipc::JOINT_STATUS_COMMAND_FAR != 0;
            check.obeyed = ours && !far;
            let was_rejoining = std::mem::replace(&mut self.rejoining, false);
            // an arm outside this controller's position range (a reflex in an extreme pose, a
            // person who moved it): a rejoin that tracks it within the range never reaches it,
            // and the robot would refuse every command as far (11 190 in a row once, then FAULT)
            let outside = (0..self.limits.n).any(|j| {
                let p = js.position[j];
                p.is_finite() && !(self.limits.pmin[j]..=self.limits.pmax[j]).contains(&p)
            });
            if (far && (!was_rejoining || outside)) || (!check.obeyed && !self.initialized) {
                // our command was refused as too far from the arm (after the robot held): the
                // next one starts where the robot is (a step, into a refusal: the robot moved
                // nothing). (A continuous rejoin of such a stream once reached the FR3 moving and
                // tripped a reflex.) A rejoin already under way goes on instead: the robot
                // stopped the arm it tracked (the other controller died), and the tracking
                // brakes onto it within the limits, refused until it is near.
                self.init_generator(js);
            } else if !check.obeyed {
                // another controller moves the arm, or nobody yet: the generator tracks the
                // measured state within the limits, so nothing accumulates, this controller's
                // own stream stays continuous (it stepped to each measured state before, up to
                // 2.3 x a joint's velocity limit in one tick), and the hand-over, when the robot
                // binds it, starts near the arm. The tracking ends the tick the robot obeys (a
                // rejoin that kept following a sagging arm after that made the SO-101 drift).
                self.rejoining = true;
                // a robot its driver holds at rest: at rest (its velocity is noise)
                let at_rest = js.status_flags & chunkrt_ipc::JOINT_STATUS_AT_REST != 0;
                for j in 0..self.limits.n {
                    let (p, v) = (js.position[j], if at_rest { 0.0 } else { js.velocity[j] });
                    self.rejoin.position[j] = if p.is_finite() { p } else { 0.0 };
                    self.rejoin.velocity[j] = if v.is_finite() { v } else { 0.0 };
                    self.rejoin.acceleration[j] = 0.0;
                }
            }
        }
        if let (true, Some(js)) = (check.fresh, joint_state) {
            // where the robot last was (a robot whose states stop holds there: stale_hold)
            for j in 0..self.limits.n {
                let p = js.position[j];
                if p.is_finite() {
                    self.last_state.position[j] = p;
                }
            }
            self.have_last_state = true;
        }
        if !check.fresh {
            self.js_gap = true;
        } else if self.js_gap {
            self.js_gap = false;
            if let Some(js) = joint_state {
                let running = self.safety.state() == State::Running;
                // a robot whose driver says it went on following this controller through the
                // gap (bound to its commands, neither holding nor refusing them): its reference
                // is this generator's stream continued, and the measured state is not (the
                // arm's tracking lag, a simulator's velocity after its physics caught up).
                // Re-seeded from it after franka-sim went silent for 20 ms, the generator took
                // a measured 0.47 rad/s for the commanded 0.96, and the driver's guard carried
                // that step as an offset it could not close while the controller accelerated:
                // 0.10-0.15 rad from the controller's command
                let followed = self.followed_through_gap(js, now_ns);
                if self.initialized && !running && !followed && self.away_from(js) {
                    self.init_generator(js);
                } else if self.initialized && !running && !followed && self.hold_last_state {
                    // after a hold at the robot's last state (stale_hold) the robot comes back
                    // where it stopped, maybe with the momentum it froze with (a simulator, the
                    // fake robot): the generator takes its velocity, not its position (a step of
                    // the arm's few ticks of motion), so that the command moves with the arm
                    // (held at rest, the fake robot overshot its command by 0.053 rad)
                    self.join_velocity(js);
                }
            }
        }
        check
    }

    /// The tick's worst input problem, most severe first (None: inputs good).
    fn problem(&self, js: JointCheck, primary: Option<(u64, u64)>) -> Option<Reason> {
        let n = self.limits.n;
        let t = &self.target;
        let finite = t.position[..n].iter().all(|v| v.is_finite())
            && t.velocity[..n].iter().all(|v| v.is_finite())
            && t.acceleration[..n].iter().all(|v| v.is_finite());
        if js.bad {
            Some(Reason::BadJointState)
        } else if !js.fresh {
            Some(Reason::StaleJointState)
        } else if !js.obeyed {
            Some(Reason::NotObeyed)
        } else if self.stale_seen != 0 {
            Some(Reason::StaleCamera)
        } else if let Some(r) = self.timeline.bad_input {
            Some(r)
        } else if primary.is_none() {
            Some(if self.source_failing {
                Reason::InferenceError
            } else if self.timeline.had_chunk {
                Reason::ChunkExpired
            } else {
                Reason::NoChunk
            })
        } else if !finite {
            Some(Reason::NonFiniteAction)
        } else if self.timing.overrun_streak >= self.overrun_streak {
            Some(Reason::Overruns)
        } else {
            None
        }
    }

    fn report(&mut self, primary: Option<(u64, u64)>) -> TickReport {
        let mut report = TickReport {
            state: self.safety.state(),
            reason: self.safety.reason(),
            publish: self.initialized,
            chunk_id: 0,
            switched: false,
            requested: false,
            target: self.target.position,
            generator: OtgResult::Working,
        };
        let primary_id = primary.map(|(id, _)| id).unwrap_or(0);
        if primary_id != 0 && primary_id != self.last_primary {
            report.switched = self.last_primary != 0;
            self.last_primary = primary_id;
        }
        report
    }

    /// Stages 4–5: track the target while RUNNING, brake otherwise; one ruckig step. A
    /// generator that cannot go on puts the executor in FAULT and holds the last position.
    /// Returns the command mode.
    fn step_generator(&mut self, now_ns: u64, report: &mut TickReport) -> u32 {
        let n = self.limits.n;
        let running = self.safety.state() == State::Running;
        let mut r = OtgResult::Working;
        for _ in 0..std::mem::replace(&mut self.cycles, 1) {
            if running {
                shaping::track(
                    &self.limits,
                    self.tracking_gain,
                    &self.target,
                    &mut self.otg_in,
                );
            } else if self.rejoining {
                shaping::track(
                    &self.limits,
                    self.tracking_gain.max(REJOIN_GAIN),
                    &self.rejoin,
                    &mut self.otg_in,
                );
            } else if self.hold_last_state && self.js_gap && self.have_last_state {
                // the robot's states stopped: back to where it last was, within the limits, not
                // braking on past it (a robot that froze with its states refuses those commands
                // when it returns, and the re-seed at the arm is then a step: 0.12 rad in a tick)
                // (ruckig's position interface: time-optimal there, arriving at rest)
                shaping::track(&self.limits, 0.0, &self.last_state, &mut self.otg_in);
            } else {
                shaping::brake(n, &mut self.otg_in);
            }
            r = self.otg.update(&self.otg_in, &mut self.otg_out);
            let out = &self.otg_out.state;
            if !r.is_ok() || matches!(r, OtgResult::Error(-102)) {
                break;
            }
            // the next period starts where this one ended
            self.otg_in.current_position = out.position;
            self.otg_in.current_velocity = out.velocity;
            self.otg_in.current_acceleration = out.acceleration;
        }
        report.generator = r;
        let ok = match r {
            OtgResult::Working | OtgResult::Finished => true,
            OtgResult::Error(-102) => {
                self.limit_warnings += 1;
                true
            }
            OtgResult::Error(_) => false,
        };
        let out = &self.otg_out.state;
        let out_finite = out.position[..n].iter().all(|v| v.is_finite())
            && out.velocity[..n].iter().all(|v| v.is_finite())
            && out.acceleration[..n].iter().all(|v| v.is_finite());
        if ok && out_finite {
            self.otg_in.current_position = out.position;
            self.otg_in.current_velocity = out.velocity;
            self.otg_in.current_acceleration = out.acceleration;
            let stopped = self.otg_in.current_velocity[..n]
                .iter()
                .all(|v| v.abs() < STOPPED_VELOCITY)
                && self.otg_in.current_acceleration[..n]
                    .iter()
                    .all(|a| a.abs() < STOPPED_ACCELERATION);
            return if running || !stopped {
                COMMAND_MODE_POSITION
            } else {
                COMMAND_MODE_HOLD
            };
        }
        // Cannot brake smoothly any more: hold the last commanded position.
        if self.safety.state() != State::Fault {
            self.safety.fault(now_ns, Reason::GeneratorError);
            report.state = self.safety.state();
            report.reason = self.safety.reason();
        }
        self.otg_in.current_velocity[..n].fill(0.0);
        self.otg_in.current_acceleration[..n].fill(0.0);
        self.otg.reset();
        COMMAND_MODE_HOLD
    }

    /// The generator's state as the command, inside the joint limits (a backstop, counted
    /// with the limit warnings).
    fn write_command(
        &mut self,
        command: &mut JointCommand,
        mode: u32,
        report: &mut TickReport,
        primary: Option<(u64, u64)>,
    ) {
        let n = self.limits.n;
        let running = self.safety.state() == State::Running;
        let (cid, oseq) = if running {
            primary.unwrap_or((0, 0))
        } else {
            (0, 0)
        };
        // the motion only: the header (seq, deadline, publish time) is the output's to stamp
        *command = JointCommand {
            chunk_id: cid,
            observation_seq: oseq,
            n_dof: n as u32,
            mode,
            ..JointCommand::default()
        };
        command.position[..n].copy_from_slice(&self.otg_in.current_position[..n]);
        for j in 0..n {
            let (lo, hi) = (self.range_lo[j], self.range_hi[j]);
            let p = command.position[j].clamp(lo, hi);
            if p != command.position[j] {
                command.position[j] = p;
                self.limit_warnings += 1;
            }
            // back inside the range: the range narrows to it again (one way only)
            self.range_lo[j] = self.limits.pmin[j].min(lo.max(p));
            self.range_hi[j] = self.limits.pmax[j].max(hi.min(p));
            self.otg_in.min_position[j] = self.range_lo[j];
            self.otg_in.max_position[j] = self.range_hi[j];
        }
        if mode == COMMAND_MODE_POSITION {
            command.velocity[..n].copy_from_slice(&self.otg_in.current_velocity[..n]);
            command.acceleration[..n].copy_from_slice(&self.otg_in.current_acceleration[..n]);
        }
        report.chunk_id = cid;
    }

    /// Before the first fresh joint state: nothing to command (the caller does not publish).
    fn write_idle_command(&self, command: &mut JointCommand) {
        *command = JointCommand {
            n_dof: self.limits.n as u32,
            ..JointCommand::default()
        };
    }

    /// Stage 6: the inference trigger (not in FAULT, not before the generator has a state).
    fn request(&mut self, now_ns: u64, report: &mut TickReport) {
        if self.safety.state() == State::Fault || !self.initialized {
            return;
        }
        report.requested = self.requests.maybe_request(
            now_ns,
            self.timeline.newest(),
            self.timeline.delay_estimate(),
            self.timeline.continuation(),
            &self.timeline.sampling,
        );
    }

    /// The measured position is further than [`RESUME_TOLERANCE`] from the generator's.
    /// Whether the robot says it followed this controller's commands through a gap in its
    /// states: its driver reports the session bound to this controller's publisher, and none of
    /// its own hold, a refusal or a fault, and this controller's hold in the gap was short
    /// (`FOLLOWED_HOLD_NS`: its brake then left the robot's stream a few mrad/s; after a
    /// longer one the robot, silent, did not brake with it: a fake robot stopped for 1 s
    /// answered its first state back with the session bound and no flag, 0.06 rad from where
    /// this controller's brake had gone).
    fn followed_through_gap(&self, js: &JointState, now_ns: u64) -> bool {
        if self.safety.hold_lasted(now_ns) > FOLLOWED_HOLD_NS {
            return false;
        }
        let own = chunkrt_ipc::JOINT_STATUS_HOLDING
            | chunkrt_ipc::JOINT_STATUS_AT_REST
            | chunkrt_ipc::JOINT_STATUS_COMMAND_FAR
            | chunkrt_ipc::JOINT_STATUS_COMMAND_TIMEOUT
            | chunkrt_ipc::JOINT_STATUS_COMMAND_REJECTED
            | chunkrt_ipc::JOINT_STATUS_ROBOT_ERROR
            | chunkrt_ipc::JOINT_STATUS_NOT_FOLLOWING;
        match (js.obeyed_publisher(), self.command_publisher) {
            (Some(id), Some(me)) => id == me && js.status_flags & own == 0,
            _ => false,
        }
    }

    fn away_from(&self, js: &JointState) -> bool {
        (0..self.limits.n)
            .any(|j| (js.position[j] - self.otg_in.current_position[j]).abs() > RESUME_TOLERANCE)
    }

    /// The generator keeps its position and takes the robot's measured velocity (within the
    /// limits; at rest for a robot its driver holds still), acceleration zero.
    fn join_velocity(&mut self, js: &JointState) {
        let at_rest = js.status_flags & chunkrt_ipc::JOINT_STATUS_AT_REST != 0;
        for j in 0..self.limits.n {
            let v = js.velocity[j];
            self.otg_in.current_velocity[j] = if v.is_finite() && !at_rest {
                v.clamp(-self.limits.vmax[j], self.limits.vmax[j])
            } else {
                0.0
            };
            self.otg_in.current_acceleration[j] = 0.0;
        }
        self.otg.reset();
    }

    fn init_generator(&mut self, js: &JointState) {
        let n = self.limits.n;
        // a robot whose driver holds it still at its own command (`AT_REST`): its measured
        // velocity is sensor noise (franka-sim's joint 7: ±0.08 rad/s), and a generator seeded
        // moving at it starts with a velocity the robot's stream does not have (the FR3 driver's
        // guard then led the takeover for seconds). (`HOLDING` alone is not enough: the fake
        // robot's arm still settles while it holds, and a seed at rest fell 0.05 rad behind it.)
        let at_rest = js.status_flags & chunkrt_ipc::JOINT_STATUS_AT_REST != 0;
        for j in 0..n {
            let p = js.position[j];
            let v = if at_rest { 0.0 } else { js.velocity[j] };
            self.otg_in.current_position[j] = if p.is_finite() { p } else { 0.0 };
            self.otg_in.current_velocity[j] = if v.is_finite() {
                v.clamp(-self.limits.vmax[j], self.limits.vmax[j])
            } else {
                0.0
            };
            self.otg_in.current_acceleration[j] = 0.0;
            // an arm outside the position range is commanded from where it is, back inside
            let p = self.otg_in.current_position[j];
            self.range_lo[j] = self.limits.pmin[j].min(p);
            self.range_hi[j] = self.limits.pmax[j].max(p);
            self.otg_in.min_position[j] = self.range_lo[j];
            self.otg_in.max_position[j] = self.range_hi[j];
        }
        self.otg.reset();
        // the seed is the robot's state now: one period from it, not the robot cycles missed
        // since the last tick (after a stall those are the stall's, up to 50 periods at once)
        self.cycles = 1;
        self.initialized = js.position[..n].iter().all(|p| p.is_finite());
    }
}
