//! The chunk executor: one call per control tick turns the chunks received so far into one
//! joint command — sampled at the tick's own time, blended according to the transition
//! strategy, smoothed and limited by ruckig, guarded by the safety state machine — and says
//! when the next inference should start.
//!
//! Everything is allocated in [`Executor::new`]; [`Executor::tick`],
//! [`Executor::record_timing`] and [`Executor::fill_status`] never allocate, lock or do I/O.

use std::collections::VecDeque;

use chunkrt_ipc::config::Config;
use chunkrt_ipc::{
    ControllerStatus, JointCommand, JointState, COMMAND_MODE_HOLD, COMMAND_MODE_POSITION, MAX_DOF,
};

use super::handoff::{self, ChunkReceiver, ChunkSender, RequestReceiver, RequestSender};
use super::interp::{self, Coverage, Interpolation, Sample};
use super::otg::{
    Otg, OtgError, OtgInput, OtgOutput, OtgResult, CONTROL_POSITION, CONTROL_VELOCITY,
};
use super::rtc::{guidance_weights, DelayEstimator, Schedule, MAX_HORIZON};
use super::safety::{event_ring, Event, EventReader, EventWriter, Reason, State};
use super::timing::TickTiming;
use crate::chunk::{ActionChunk, ChunkError};

/// How consecutive chunks take over from each other.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Strategy {
    /// Switch at the first action of the new chunk that is not yet due.
    Replace,
    /// Blend old → new over `crossfade_ms`, starting where `Replace` would switch.
    Crossfade,
    /// ACT's temporal ensemble: exponentially weighted average of every chunk covering now.
    TemporalEnsemble,
    /// Real-time chunking: switch at once, at the index real time has reached.
    Rtc,
}

impl Strategy {
    /// Parses a config name.
    pub fn parse(name: &str) -> Option<Self> {
        match name {
            "replace" => Some(Self::Replace),
            "crossfade" => Some(Self::Crossfade),
            "temporal_ensemble" => Some(Self::TemporalEnsemble),
            "rtc" => Some(Self::Rtc),
            _ => None,
        }
    }
}

/// When the next inference is requested.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Trigger {
    /// Once `execute_horizon` (s) actions of the newest chunk are due.
    AfterS,
    /// As soon as the previous inference landed.
    Continuous,
}

/// The executor could not be built.
#[derive(Debug, thiserror::Error)]
pub enum ExecutorError {
    #[error("execution.{key} = {value:?}: {allowed}")]
    Config {
        key: &'static str,
        value: String,
        allowed: &'static str,
    },
    #[error(transparent)]
    Generator(#[from] OtgError),
}

/// What one tick did (the command itself is written into the caller's `JointCommand`).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct TickReport {
    /// State after this tick.
    pub state: State,
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

/// The answer to [`Executor::rearm`].
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Rearm {
    /// FAULT → STARTING.
    Accepted,
    /// Not in FAULT (the state it is in).
    NotInFault(State),
    /// An input is still bad.
    InputsBad(Reason),
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
}

struct Slot {
    chunk: ActionChunk,
    /// From when the chunk is in effect (ns).
    active_from: i64,
}

/// Robot limits and execution settings, resolved from the config once.
#[derive(Debug, Clone)]
struct Settings {
    n: usize,
    step: [bool; MAX_DOF],
    vmax: [f64; MAX_DOF],
    amax: [f64; MAX_DOF],
    jmax: [f64; MAX_DOF],
    pmin: [f64; MAX_DOF],
    pmax: [f64; MAX_DOF],
    strategy: Strategy,
    interp: Interpolation,
    trigger: Trigger,
    schedule: Schedule,
    offset_ns: i64,
    control_period_ns: u64,
    action_period_ns: u64,
    crossfade_ns: i64,
    tracking_gain: f64,
    future_state: bool,
    ensemble_decay: f64,
    s: usize,
    beta: f64,
    deadline_ns: u64,
    js_max_age_ns: u64,
    hold_to_fault_ns: u64,
    overrun_streak: u32,
    inference_timeout_ns: u64,
}

const CHUNK_SLOTS: usize = 16;
/// ruckig's `Synchronization::None`.
const SYNC_NONE: i32 = 3;
const GRAVEYARD: usize = 32;
/// After a gap in the joint state, and when leaving HOLD, a measured position further than this
/// from the generator's own (a robot that restarted or was moved) restarts the generator from
/// the measured state (rad or unit).
const RESUME_TOLERANCE: f64 = 0.01;

/// Velocity below which a braking joint counts as stopped (per second).
const STOPPED_VELOCITY: f64 = 1e-6;
/// Acceleration below which a braking joint counts as stopped (per second²).
const STOPPED_ACCELERATION: f64 = 1e-6;

/// The control tick. See the module documentation; built once with [`Executor::new`].
pub struct Executor {
    cfg: Settings,
    otg: Otg,
    otg_in: OtgInput,
    otg_out: OtgOutput,
    state: State,
    initialized: bool,
    hold_since_ns: u64,
    /// Reason of the last transition.
    state_reason: Option<Reason>,
    /// The problem the last tick saw (None: inputs good).
    last_problem: Option<Reason>,
    chunks: VecDeque<Slot>,
    graveyard: Vec<ActionChunk>,
    had_chunk: bool,
    bad_input: Option<Reason>,
    /// See [`InferenceLink::stale_cameras`].
    stale_cameras: std::sync::Arc<std::sync::atomic::AtomicU64>,
    /// Its value at the last tick (for the status).
    stale_seen: u64,
    /// The joint state was missing or stale at some tick since the last fresh one (a robot
    /// restart, a stalled driver): on the next fresh state the generator may have to re-sync.
    js_gap: bool,
    chunk_rx: ChunkReceiver,
    chunk_tx: ChunkSender,
    req_tx: RequestSender,
    req_rx: RequestReceiver,
    events_w: EventWriter,
    events_r: EventReader,
    delay: DelayEstimator,
    outstanding_since: Option<u64>,
    next_request_id: u64,
    timing: TickTiming,
    target: Sample,
    scratch: Sample,
    last_primary: u64,
    seq: u64,
    ticks: u64,
    chunks_received: u64,
    chunks_rejected: u64,
    hold_entries: u64,
    last_inference_latency_ns: u64,
    joint_state_age_ns: u64,
    limit_warnings: u64,
}

fn parse<T>(
    key: &'static str,
    v: &str,
    f: impl Fn(&str) -> Option<T>,
    allowed: &'static str,
) -> Result<T, ExecutorError> {
    f(v).ok_or_else(|| ExecutorError::Config {
        key,
        value: v.to_string(),
        allowed,
    })
}

fn ms_to_ns(ms: f64) -> u64 {
    (ms * 1e6).max(0.0).round() as u64
}

impl Executor {
    /// Builds the executor for a validated configuration; allocates everything it will need.
    pub fn new(config: &Config) -> Result<Self, ExecutorError> {
        let e = &config.execution;
        let n = config.n_dof().min(MAX_DOF);
        let mut cfg = Settings {
            n,
            step: [false; MAX_DOF],
            vmax: [1.0; MAX_DOF],
            amax: [1.0; MAX_DOF],
            jmax: [1.0; MAX_DOF],
            pmin: [f64::NEG_INFINITY; MAX_DOF],
            pmax: [f64::INFINITY; MAX_DOF],
            strategy: parse(
                "strategy",
                &e.strategy,
                Strategy::parse,
                "replace, crossfade, temporal_ensemble or rtc",
            )?,
            interp: parse(
                "interpolation",
                &e.interpolation,
                Interpolation::parse,
                "cubic or linear",
            )?,
            trigger: parse(
                "trigger",
                &e.trigger,
                |s| match s {
                    "after_s" => Some(Trigger::AfterS),
                    "continuous" => Some(Trigger::Continuous),
                    _ => None,
                },
                "after_s or continuous",
            )?,
            schedule: parse(
                "rtc_schedule",
                &e.rtc_schedule,
                Schedule::parse,
                "exp, linear, ones or zeros",
            )?,
            offset_ns: (e.offset_ms * 1e6).round() as i64,
            control_period_ns: config.control_period_ns().max(1),
            action_period_ns: ((1e9 / config.policy.action_rate_hz).round() as u64).max(1),
            crossfade_ns: ms_to_ns(e.crossfade_ms) as i64,
            tracking_gain: e.tracking_gain,
            future_state: e.future_state,
            ensemble_decay: e.ensemble_decay,
            s: e.execute_horizon.max(1),
            beta: e.guidance_beta,
            deadline_ns: ms_to_ns(config.control.command_deadline_ms),
            js_max_age_ns: ms_to_ns(config.control.joint_state_max_age_ms),
            hold_to_fault_ns: ms_to_ns(e.hold_to_fault_ms),
            overrun_streak: e.overrun_streak.max(1),
            inference_timeout_ns: ms_to_ns(e.inference_timeout_ms),
        };
        for (i, j) in config.robot.joints.iter().take(n).enumerate() {
            cfg.step[i] = j.step;
            cfg.vmax[i] = j.max_velocity;
            cfg.amax[i] = j.max_acceleration;
            cfg.jmax[i] = j.max_jerk;
            cfg.pmin[i] = j.position_min;
            cfg.pmax[i] = j.position_max;
        }
        let otg = Otg::new(cfg.control_period_ns as f64 * 1e-9)?;
        let mut otg_in = OtgInput {
            dofs: n as u32,
            ..Default::default()
        };
        // Every joint is tracked on its own (time-optimal per joint): a time-synchronised
        // generator would slow every joint down to the slowest one (e.g. a gripper step).
        otg_in.synchronization = SYNC_NONE;
        otg_in.max_velocity = cfg.vmax;
        otg_in.max_acceleration = cfg.amax;
        otg_in.max_jerk = cfg.jmax;
        otg_in.min_position = cfg.pmin;
        otg_in.max_position = cfg.pmax;
        let (chunk_tx, chunk_rx) = handoff::channel(1, 64);
        let (req_tx, req_rx) = handoff::request_channel();
        let (events_w, events_r) = event_ring(1024);
        Ok(Self {
            delay: DelayEstimator::new(e.delay_buffer, e.initial_delay_steps),
            cfg,
            otg,
            otg_in,
            otg_out: OtgOutput::default(),
            state: State::Starting,
            initialized: false,
            hold_since_ns: 0,
            state_reason: None,
            last_problem: None,
            chunks: VecDeque::with_capacity(CHUNK_SLOTS),
            graveyard: Vec::with_capacity(GRAVEYARD),
            had_chunk: false,
            bad_input: None,
            stale_cameras: Default::default(),
            stale_seen: 0,
            js_gap: false,
            chunk_rx,
            chunk_tx,
            req_tx,
            req_rx,
            events_w,
            events_r,
            outstanding_since: None,
            next_request_id: 1,
            timing: TickTiming::new(),
            target: Sample::default(),
            scratch: Sample::default(),
            last_primary: 0,
            seq: 0,
            ticks: 0,
            chunks_received: 0,
            chunks_rejected: 0,
            hold_entries: 0,
            last_inference_latency_ns: 0,
            joint_state_age_ns: 0,
            limit_warnings: 0,
        })
    }

    /// The inference thread's ends of the hand-offs (call once per inference thread).
    pub fn connect(&self) -> InferenceLink {
        InferenceLink {
            chunks: self.chunk_tx.clone(),
            requests: self.req_rx.clone(),
            stale_cameras: self.stale_cameras.clone(),
        }
    }

    /// Reader of the state-transition events (drain and log them off the control thread).
    pub fn events(&self) -> EventReader {
        self.events_r.clone()
    }

    /// Current state.
    pub fn state(&self) -> State {
        self.state
    }

    /// Tick timing histograms (read them off the tick, e.g. for the exit summary).
    pub fn timing(&self) -> &TickTiming {
        &self.timing
    }

    /// The current inference-delay estimate d (action steps).
    pub fn delay_estimate(&self) -> usize {
        self.delay.estimate()
    }

    /// Chunks accepted / rejected so far.
    pub fn chunk_counts(&self) -> (u64, u64) {
        (self.chunks_received, self.chunks_rejected)
    }

    /// Leaves FAULT for STARTING (the generator is re-initialised from the next fresh joint
    /// state; RUNNING follows once a chunk arrives and the inputs are good). Refused in any other
    /// state, and while an input from outside is still bad at the last tick (joint state missing,
    /// stale or not matching the robot, a stale camera): the reason says which. No allocation.
    pub fn rearm(&mut self, now_ns: u64) -> Rearm {
        if self.state != State::Fault {
            return Rearm::NotInFault(self.state);
        }
        if let Some(r @ (Reason::BadJointState | Reason::StaleJointState | Reason::StaleCamera)) =
            self.last_problem
        {
            return Rearm::InputsBad(r);
        }
        self.transition(now_ns, State::Starting, Reason::Rearm);
        self.initialized = false;
        self.bad_input = None;
        self.outstanding_since = None;
        Rearm::Accepted
    }

    /// Why the executor is in its current state (the reason of the last transition).
    pub fn state_reason(&self) -> Option<Reason> {
        self.state_reason
    }

    /// Records the timing of the tick just finished: scheduled for `scheduled_ns`, woke at
    /// `woke_ns`, done (command published) at `done_ns`. A streak of overruns puts the
    /// executor in HOLD at the next tick. No allocation.
    pub fn record_timing(&mut self, scheduled_ns: u64, woke_ns: u64, done_ns: u64) -> bool {
        self.timing
            .record(scheduled_ns, woke_ns, done_ns, self.cfg.control_period_ns)
    }

    /// Fills the executor's part of the status: state, n_dof, ticks, overruns, chunks,
    /// inference latency, lateness / compute quantiles, joint-state age, hold entries.
    /// (seq, publish time, joint_states, frames and rejected are the caller's.) No allocation.
    pub fn fill_status(&self, st: &mut ControllerStatus) {
        st.state = self.state.code();
        st.n_dof = self.cfg.n as u32;
        st.ticks = self.ticks;
        st.overruns = self.timing.overruns;
        st.chunks = self.chunks_received;
        st.last_inference_latency_ns = self.last_inference_latency_ns;
        let l = self.timing.lateness_quantiles();
        let c = self.timing.compute_quantiles();
        st.lateness_p50_ns = l.p50;
        st.lateness_p99_ns = l.p99;
        st.lateness_max_ns = l.max;
        st.compute_p50_ns = c.p50;
        st.compute_p99_ns = c.p99;
        st.compute_max_ns = c.max;
        st.joint_state_age_ns = self.joint_state_age_ns;
        st.hold_entries = self.hold_entries;
        st.stale_cameras = self.stale_seen;
    }

    /// Hands a chunk to the executor directly (instead of through [`Executor::connect`]);
    /// the chunk is validated and takes effect according to the strategy.
    pub fn offer_chunk(&mut self, chunk: ActionChunk, now_ns: u64) {
        self.accept(chunk, now_ns);
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
        let now = now_ns as i64;
        self.flush_graveyard();
        while let Some(c) = self.chunk_rx.try_recv() {
            self.accept(c, now_ns);
        }
        self.prune(now);

        // Joint state.
        let mut js_fresh = false;
        let mut js_bad = false;
        if let Some(js) = joint_state {
            if js.n_dof as usize != self.cfg.n {
                js_bad = true;
            } else {
                self.joint_state_age_ns = now_ns.saturating_sub(js.measurement_time_ns);
                js_fresh = self.joint_state_age_ns <= self.cfg.js_max_age_ns;
            }
        }

        // A fresh state after a gap: the robot may have restarted or been moved meanwhile. If it
        // is away from the generator, brake (and later resume) from where it is, not from where
        // the controller last commanded it (a restarted robot must never be commanded back).
        if !js_fresh {
            self.js_gap = true;
        } else if self.js_gap {
            self.js_gap = false;
            if let Some(js) = joint_state {
                if self.initialized && self.state != State::Running && self.away_from(js) {
                    self.init_generator(js);
                }
            }
        }

        // Cameras (the inference thread's verdict, one atomic load).
        self.stale_seen = self
            .stale_cameras
            .load(std::sync::atomic::Ordering::Relaxed);

        // Target.
        let primary = self.evaluate(now);
        let n = self.cfg.n;
        let finite = primary.is_some()
            && self.target.position[..n].iter().all(|v| v.is_finite())
            && self.target.velocity[..n].iter().all(|v| v.is_finite())
            && self.target.acceleration[..n].iter().all(|v| v.is_finite());
        let problem = if js_bad {
            Some(Reason::BadJointState)
        } else if !js_fresh {
            Some(Reason::StaleJointState)
        } else if self.stale_seen != 0 {
            Some(Reason::StaleCamera)
        } else if let Some(r) = self.bad_input {
            Some(r)
        } else if primary.is_none() {
            Some(if self.had_chunk {
                Reason::ChunkExpired
            } else {
                Reason::NoChunk
            })
        } else if !finite {
            Some(Reason::NonFiniteAction)
        } else if self.timing.overrun_streak >= self.cfg.overrun_streak {
            Some(Reason::Overruns)
        } else {
            None
        };
        self.last_problem = problem;

        // Safety state machine.
        match self.state {
            State::Starting => {
                if js_bad {
                    self.transition(now_ns, State::Fault, Reason::BadJointState);
                } else {
                    if js_fresh && !self.initialized {
                        if let Some(js) = joint_state {
                            self.init_generator(js);
                        }
                    }
                    if self.initialized && problem.is_none() {
                        self.transition(now_ns, State::Running, Reason::InputsGood);
                    }
                }
            }
            State::Running => match problem {
                Some(Reason::BadJointState) => {
                    self.transition(now_ns, State::Fault, Reason::BadJointState)
                }
                Some(r) => self.transition(now_ns, State::Hold, r),
                None => {}
            },
            State::Hold => {
                if js_bad {
                    self.transition(now_ns, State::Fault, Reason::BadJointState);
                } else if now_ns.saturating_sub(self.hold_since_ns) >= self.cfg.hold_to_fault_ns {
                    self.transition(now_ns, State::Fault, Reason::HoldTimeout);
                } else if problem.is_none() {
                    // Resume from where the robot is, not from where the controller last
                    // commanded it: after a robot restart they can be far apart, and the
                    // generator then moves from the measured state within the limits. A robot
                    // that followed the braking keeps the generator's own (continuous) state.
                    if let Some(js) = joint_state {
                        if self.away_from(js) {
                            self.init_generator(js);
                        }
                    }
                    self.transition(now_ns, State::Running, Reason::InputsGood);
                }
            }
            State::Fault => {}
        }

        let mut report = TickReport {
            state: self.state,
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
        if !self.initialized {
            *command = JointCommand {
                seq: self.seq,
                publish_time_ns: now_ns,
                deadline_ns: now_ns + self.cfg.deadline_ns,
                n_dof: n as u32,
                ..JointCommand::default()
            };
            self.maybe_request(now_ns, &mut report);
            return report;
        }

        // Trajectory generator: track the target while RUNNING, brake otherwise.
        //
        // Tracking (`tracking_gain` > 0): the generator follows a velocity, the executed chunk's
        // own velocity and acceleration (its preview) plus the gain times the command's
        // position error; it never targets a fixed state, so it never has to loop back to hit
        // a moving target "on time" (what a fixed-target chase does whenever the command is a
        // hair behind and a bit slow). Without a gain, the chunk's state at the tick is the
        // generator's position target.
        let running = self.state == State::Running;
        if running {
            let gain = self.cfg.tracking_gain;
            self.otg_in.control_interface = if gain > 0.0 {
                CONTROL_VELOCITY
            } else {
                CONTROL_POSITION
            };
            for j in 0..n {
                let margin = 1e-9 * (self.cfg.pmax[j] - self.cfg.pmin[j]);
                let (lo, hi) = (self.cfg.pmin[j] + margin, self.cfg.pmax[j] - margin);
                let p = self.target.position[j].clamp(lo, hi);
                self.otg_in.target_position[j] = p;
                let (mut v, mut a) = if self.cfg.step[j] {
                    (0.0, 0.0)
                } else {
                    (self.target.velocity[j], self.target.acceleration[j])
                };
                // where the limit rule below measures from: the target (position interface) or
                // the command itself (tracking)
                let mut from = p;
                if gain > 0.0 {
                    from = self.otg_in.current_position[j].clamp(lo, hi);
                    // proportional near the chunk; further out, no faster than the joint can
                    // still brake to the error's end at half its acceleration (a large error
                    // after a switch closes without overshoot)
                    // (at a = a_max / 2, after ramping the acceleration at the jerk limit:
                    // |e| = v²/2a + v·a/2j solved for v)
                    let e = p - from;
                    let (ab, jm) = (0.5 * self.cfg.amax[j], self.cfg.jmax[j]);
                    let lag = ab * ab / (2.0 * jm);
                    let brake = (lag * lag + 2.0 * ab * e.abs()).sqrt() - lag;
                    v += (gain * e).clamp(-brake, brake);
                }
                // Towards a limit the target may only move as fast as the generator can still
                // stop before it (|v| <= sqrt(2 · a_stop · distance left)); at the limit, not at
                // all. Otherwise tracking a target that runs into a limit overshoots it.
                let a_stop = 0.5 * self.cfg.amax[j];
                let up = (2.0 * a_stop * (hi - from)).max(0.0).sqrt();
                let down = (2.0 * a_stop * (from - lo)).max(0.0).sqrt();
                if v >= up {
                    v = up;
                    a = a.min(0.0);
                } else if v <= -down {
                    v = -down;
                    a = a.max(0.0);
                }
                let vl = 0.99 * self.cfg.vmax[j];
                let v = v.clamp(-vl, vl);
                // ruckig rejects a target state that would have to exceed the velocity limit
                // while its acceleration is ramped to zero at the jerk limit:
                // |v| + a^2 / (2 j) <= v_max, so bound |a| accordingly (and by a_max)
                let al = (0.99 * self.cfg.amax[j])
                    .min((2.0 * 0.99 * self.cfg.jmax[j] * (vl - v.abs()).max(0.0)).sqrt());
                self.otg_in.target_velocity[j] = v;
                self.otg_in.target_acceleration[j] = a.clamp(-al, al);
            }
        } else {
            self.otg_in.control_interface = CONTROL_VELOCITY;
            self.otg_in.target_velocity[..n].fill(0.0);
            self.otg_in.target_acceleration[..n].fill(0.0);
        }
        let r = self.otg.update(&self.otg_in, &mut self.otg_out);
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
        let mode;
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
            mode = if running || !stopped {
                COMMAND_MODE_POSITION
            } else {
                COMMAND_MODE_HOLD
            };
        } else {
            // Cannot brake smoothly any more: hold the last commanded position.
            if self.state != State::Fault {
                self.transition(now_ns, State::Fault, Reason::GeneratorError);
                report.state = self.state;
            }
            self.otg_in.current_velocity[..n].fill(0.0);
            self.otg_in.current_acceleration[..n].fill(0.0);
            self.otg.reset();
            mode = COMMAND_MODE_HOLD;
        }
        self.seq += 1;
        command.seq = self.seq;
        command.publish_time_ns = now_ns;
        command.deadline_ns = now_ns + self.cfg.deadline_ns;
        let (cid, oseq) = if running {
            primary.unwrap_or((0, 0))
        } else {
            (0, 0)
        };
        command.chunk_id = cid;
        command.observation_seq = oseq;
        command.n_dof = n as u32;
        command.mode = mode;
        command.position = [0.0; MAX_DOF];
        command.velocity = [0.0; MAX_DOF];
        command.acceleration = [0.0; MAX_DOF];
        command.position[..n].copy_from_slice(&self.otg_in.current_position[..n]);
        // backstop: a command never leaves the joint limits (counted with the limit warnings)
        for j in 0..n {
            let p = command.position[j].clamp(self.cfg.pmin[j], self.cfg.pmax[j]);
            if p != command.position[j] {
                command.position[j] = p;
                self.limit_warnings += 1;
            }
        }
        if mode == COMMAND_MODE_POSITION {
            command.velocity[..n].copy_from_slice(&self.otg_in.current_velocity[..n]);
            command.acceleration[..n].copy_from_slice(&self.otg_in.current_acceleration[..n]);
        }
        report.chunk_id = cid;
        self.maybe_request(now_ns, &mut report);
        report
    }

    /// The measured position is further than [`RESUME_TOLERANCE`] from the generator's.
    fn away_from(&self, js: &JointState) -> bool {
        (0..self.cfg.n)
            .any(|j| (js.position[j] - self.otg_in.current_position[j]).abs() > RESUME_TOLERANCE)
    }

    fn init_generator(&mut self, js: &JointState) {
        let n = self.cfg.n;
        for j in 0..n {
            let p = js.position[j];
            let v = js.velocity[j];
            self.otg_in.current_position[j] = if p.is_finite() { p } else { 0.0 };
            self.otg_in.current_velocity[j] = if v.is_finite() {
                v.clamp(-self.cfg.vmax[j], self.cfg.vmax[j])
            } else {
                0.0
            };
            self.otg_in.current_acceleration[j] = 0.0;
        }
        self.otg.reset();
        self.initialized = js.position[..n].iter().all(|p| p.is_finite());
    }

    fn transition(&mut self, now_ns: u64, to: State, reason: Reason) {
        if to == self.state {
            return;
        }
        if to == State::Hold {
            self.hold_entries += 1;
            self.hold_since_ns = now_ns;
        }
        self.events_w.record(Event {
            t_ns: now_ns,
            from: self.state,
            to,
            reason,
        });
        self.state = to;
        self.state_reason = Some(reason);
    }

    fn dispose(&mut self, c: ActionChunk) {
        if let Err(c) = self.chunk_rx.recycle(c) {
            if self.graveyard.len() < self.graveyard.capacity() {
                self.graveyard.push(c);
            }
            // else: dropped here (frees) — only if the inference side stopped recycling.
        }
    }

    fn flush_graveyard(&mut self) {
        while let Some(c) = self.graveyard.pop() {
            if let Err(c) = self.chunk_rx.recycle(c) {
                self.graveyard.push(c);
                break;
            }
        }
    }

    fn accept(&mut self, chunk: ActionChunk, now_ns: u64) {
        let verdict = if chunk.n_dof == self.cfg.n {
            chunk.validate()
        } else {
            Err(ChunkError::NDof(chunk.n_dof))
        };
        if let Err(e) = verdict {
            self.chunks_rejected += 1;
            self.bad_input = Some(match e {
                ChunkError::NonFinite { .. } => Reason::NonFiniteAction,
                _ => Reason::BadChunk,
            });
            self.dispose(chunk);
            // Execute nothing of what came before the bad chunk either.
            while let Some(s) = self.chunks.pop_front() {
                self.dispose(s.chunk);
            }
            self.outstanding_since = None;
            return;
        }
        self.chunks_received += 1;
        self.had_chunk = true;
        self.bad_input = None;
        self.outstanding_since = None;
        let now = now_ns as i64;
        let t0 = interp::start_ns(&chunk, self.cfg.offset_ns);
        // the delay is counted from the observation, not from a future-state chunk's start
        let age = (now - (chunk.t_obs_ns as i64 + self.cfg.offset_ns)).max(0) as u64;
        self.delay.observe(age.div_ceil(chunk.period_ns) as usize);
        self.last_inference_latency_ns = chunk.ready_ns.saturating_sub(chunk.t_obs_ns);
        let active_from = match self.cfg.strategy {
            // a future-state chunk was made to start where the robot is when it lands: at once
            _ if chunk.start_shift_ns > 0 => now.max(t0),
            Strategy::Replace | Strategy::Crossfade => {
                let k = interp::first_due_at_or_after(&chunk, now, self.cfg.offset_ns);
                t0 + k as i64 * chunk.period_ns as i64
            }
            Strategy::Rtc | Strategy::TemporalEnsemble => now,
        };
        if self.chunks.len() == self.chunks.capacity().min(CHUNK_SLOTS) {
            if let Some(old) = self.chunks.pop_front() {
                self.dispose(old.chunk);
            }
        }
        self.chunks.push_back(Slot { chunk, active_from });
    }

    /// Index of the newest chunk in effect at `now`.
    fn current(&self, now: i64) -> Option<usize> {
        (0..self.chunks.len())
            .rev()
            .find(|&i| self.chunks[i].active_from <= now)
    }

    fn prune(&mut self, now: i64) {
        // Expired chunks go first.
        let mut i = 0;
        while i < self.chunks.len() {
            if interp::end_ns(&self.chunks[i].chunk, self.cfg.offset_ns) < now {
                if let Some(s) = self.chunks.remove(i) {
                    self.dispose(s.chunk);
                }
            } else {
                i += 1;
            }
        }
        if self.cfg.strategy == Strategy::TemporalEnsemble {
            return;
        }
        // Chunks superseded by the one in effect (crossfade keeps its predecessor during the
        // blend window).
        if let Some(ic) = self.current(now) {
            let keep_prev = self.cfg.strategy == Strategy::Crossfade
                && now < self.chunks[ic].active_from + self.cfg.crossfade_ns;
            let first_kept = if keep_prev { ic.saturating_sub(1) } else { ic };
            for _ in 0..first_kept {
                if let Some(s) = self.chunks.pop_front() {
                    self.dispose(s.chunk);
                }
            }
        }
    }

    /// Samples the strategy's target at `now` into `self.target`; returns the primary chunk's
    /// (id, observation_seq).
    #[allow(clippy::needless_range_loop)] // joints index several parallel arrays
    fn evaluate(&mut self, now: i64) -> Option<(u64, u64)> {
        let n = self.cfg.n;
        let (off, mode, step) = (self.cfg.offset_ns, self.cfg.interp, self.cfg.step);
        match self.cfg.strategy {
            Strategy::Replace | Strategy::Rtc | Strategy::Crossfade => {
                let ic = self.current(now)?;
                let cur = &self.chunks[ic];
                if interp::sample(&cur.chunk, now, off, mode, &step, &mut self.target)
                    == Coverage::After
                {
                    return None;
                }
                if self.cfg.strategy == Strategy::Crossfade && ic > 0 && self.cfg.crossfade_ns > 0 {
                    let since = now - cur.active_from;
                    if since < self.cfg.crossfade_ns {
                        let prev = &self.chunks[ic - 1];
                        if interp::sample(&prev.chunk, now, off, mode, &step, &mut self.scratch)
                            == Coverage::Inside
                        {
                            let x = since as f64 / self.cfg.crossfade_ns as f64;
                            let period = self.cfg.crossfade_ns as f64 * 1e-9;
                            // smoothstep w and its time derivatives
                            let w = x * x * (3.0 - 2.0 * x);
                            let dw = 6.0 * x * (1.0 - x) / period;
                            let ddw = 6.0 * (1.0 - 2.0 * x) / (period * period);
                            let (t, p) = (&mut self.target, &self.scratch);
                            for j in 0..n {
                                if step[j] {
                                    continue; // step channels come from the new chunk
                                }
                                // p + w·d with d = new − old, differentiated twice
                                let d = t.position[j] - p.position[j];
                                let dv = t.velocity[j] - p.velocity[j];
                                let da = t.acceleration[j] - p.acceleration[j];
                                t.position[j] = p.position[j] + w * d;
                                t.velocity[j] = p.velocity[j] + w * dv + dw * d;
                                t.acceleration[j] =
                                    p.acceleration[j] + w * da + 2.0 * dw * dv + ddw * d;
                            }
                        }
                    }
                }
                Some((cur.chunk.id, cur.chunk.observation_seq))
            }
            Strategy::TemporalEnsemble => {
                let mut wsum = 0.0;
                let mut rank = 0usize;
                let mut primary = None;
                let mut acc = Sample::default();
                for i in 0..self.chunks.len() {
                    let c = &self.chunks[i].chunk;
                    if interp::sample(c, now, off, mode, &step, &mut self.scratch)
                        != Coverage::Inside
                    {
                        continue;
                    }
                    // ACT: w_i = exp(-m·i), i = 0 for the oldest prediction.
                    let w = (-self.cfg.ensemble_decay * rank as f64).exp();
                    rank += 1;
                    wsum += w;
                    for j in 0..n {
                        if step[j] {
                            acc.position[j] = self.scratch.position[j]; // newest wins
                            continue;
                        }
                        acc.position[j] += w * self.scratch.position[j];
                        acc.velocity[j] += w * self.scratch.velocity[j];
                        acc.acceleration[j] += w * self.scratch.acceleration[j];
                    }
                    primary = Some((c.id, c.observation_seq));
                }
                if wsum <= 0.0 {
                    return None;
                }
                for j in 0..n {
                    if !step[j] {
                        acc.position[j] /= wsum;
                        acc.velocity[j] /= wsum;
                        acc.acceleration[j] /= wsum;
                    }
                }
                self.target = acc;
                primary
            }
        }
    }

    fn maybe_request(&mut self, now_ns: u64, report: &mut TickReport) {
        if self.state == State::Fault || !self.initialized {
            return;
        }
        if let Some(t) = self.outstanding_since {
            if now_ns.saturating_sub(t) < self.cfg.inference_timeout_ns {
                return;
            }
            self.outstanding_since = None;
        }
        let newest = self.chunks.back().map(|s| &s.chunk);
        let due = match (self.cfg.trigger, newest) {
            (Trigger::Continuous, _) | (_, None) => true,
            // s actions after the newest chunk's observation (not after its start: a
            // future-state chunk starts a delay later, and the next one would land too late)
            (Trigger::AfterS, Some(c)) => {
                now_ns as i64
                    >= interp::start_ns(c, self.cfg.offset_ns) - c.start_shift_ns as i64
                        + (self.cfg.s as i64) * c.period_ns as i64
            }
        };
        if !due {
            return;
        }
        let id = self.next_request_id;
        let cfg = &self.cfg;
        let d = self.delay.estimate();
        let published = self.req_tx.publish(|r| {
            r.id = id;
            r.t_ref_ns = now_ns;
            r.n_dof = cfg.n;
            r.execute_horizon = cfg.s;
            r.delay_steps = d;
            r.beta = cfg.beta;
            match newest {
                Some(c) => {
                    let h = c.horizon().min(MAX_HORIZON);
                    r.horizon = h;
                    r.period_ns = c.period_ns;
                    r.guided = cfg.strategy == Strategy::Rtc;
                    r.future_state = cfg.future_state;
                    let mut s = Sample::default();
                    for i in 0..h {
                        let t = now_ns as i64 + i as i64 * c.period_ns as i64;
                        interp::sample(c, t, cfg.offset_ns, cfg.interp, &cfg.step, &mut s);
                        r.prefix[i][..cfg.n].copy_from_slice(&s.position[..cfg.n]);
                    }
                    guidance_weights(h, cfg.s, d, cfg.schedule, &mut r.weights);
                }
                None => {
                    r.horizon = 0;
                    r.period_ns = cfg.action_period_ns;
                    r.guided = false;
                    r.future_state = false;
                }
            }
        });
        if published {
            self.next_request_id += 1;
            self.outstanding_since = Some(now_ns);
            report.requested = true;
        }
    }
}
