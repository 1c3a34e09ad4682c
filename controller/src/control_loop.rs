//! The control thread: its ports, one control tick over IPC ([`ControlLoop::step`]), and the
//! loop around it (`control_thread`): absolute deadlines of its own timer through
//! [`crate::rt::run_periodic`] (`[control] clock = "timer"`), or one tick per robot state, woken
//! by the robot's event, with the timer taking over while the robot is quiet
//! ([`run_robot_clocked`], `clock = "robot"`).
//!
//! Owns: the command and status publishing, tick timing. Must not depend on: the policy, the
//! observation thread.

use std::sync::atomic::{AtomicU64, Ordering};

use hdrhistogram::Histogram;

use crate::config::Config;
use chunkrt_ipc::config::ControlClock;
use chunkrt_ipc::services;
use chunkrt_ipc::{
    monotonic_ns, ControllerStatus, JointCommand, JointState, CONTROLLER_STATE_HOLD,
    CONTROLLER_STATE_NOT_FOLLOWED, CONTROLLER_STATE_RUNNING, CONTROLLER_STATE_STARTING,
    CONTROLLER_STATE_STOPPED,
};

use crate::control::{Executor, TickReport};
use crate::edge::{CommandOutput, JointStateInput, RearmInput, StatusOutput};
use crate::rt;
use crate::shared::Shared;

/// The answer to a re-arm request: (`REARM_*` code, `STATE_REASON_*` of the bad input or 0).
pub type RearmAnswer = (u32, u32);

/// The work of one control tick, separated from the thread and the IPC ports so that it can
/// be tested alone. Must not allocate, block or do I/O.
pub trait ControlTick: Send {
    /// Computes the command for `now_ns` from the newest valid joint state (if any).
    fn tick(
        &mut self,
        now_ns: u64,
        joint_state: Option<&JointState>,
        cmd: &mut JointCommand,
    ) -> TickReport;

    /// An operator asks to leave FAULT (`chunkrt rearm`). The default refuses: nothing to
    /// re-arm. Must not allocate, block or do I/O.
    fn rearm(&mut self, _now_ns: u64) -> RearmAnswer {
        (chunkrt_ipc::REARM_REFUSED_NOT_IN_FAULT, 0)
    }

    /// The iceoryx2 id of the command publisher this tick's commands leave by: a robot that
    /// reports the session it obeys tells the tick whether it is obeyed. Default: ignored.
    fn set_command_publisher(&mut self, _id: u128) {}

    /// How many control periods the next tick advances the motion by (1 on the timer; with a
    /// robot clock, the robot cycles since the last tick, so that the command stays on the
    /// robot's time when a tick missed a cycle). Default: ignored.
    fn set_cycles(&mut self, _cycles: u32) {}

    /// The bound robot's newest state while the stream is ambiguous (not trusted to lead):
    /// where a hold holds. Default: ignored. Must not allocate, block or do I/O.
    fn hold_at(&mut self, _joint_state: &JointState) {}
}

impl ControlTick for Executor {
    fn tick(
        &mut self,
        now_ns: u64,
        joint_state: Option<&JointState>,
        cmd: &mut JointCommand,
    ) -> TickReport {
        Executor::tick(self, now_ns, joint_state, cmd)
    }

    fn set_command_publisher(&mut self, id: u128) {
        Executor::set_command_publisher(self, id);
    }

    fn hold_at(&mut self, joint_state: &JointState) {
        Executor::hold_at(self, joint_state);
    }

    fn set_cycles(&mut self, cycles: u32) {
        Executor::set_cycles(self, cycles);
    }

    fn rearm(&mut self, now_ns: u64) -> RearmAnswer {
        use crate::control::Rearm;
        match Executor::rearm(self, now_ns) {
            Rearm::Accepted => (chunkrt_ipc::REARM_ACCEPTED, 0),
            Rearm::NotInFault(_) => (chunkrt_ipc::REARM_REFUSED_NOT_IN_FAULT, 0),
            Rearm::InputsBad(r) => (chunkrt_ipc::REARM_REFUSED_INPUTS, r.code()),
        }
    }
}

/// Latency histograms of the control thread (fixed bounds: recording never allocates).
pub struct TickHistograms {
    /// Wake-up lateness (ns).
    pub lateness: Histogram<u64>,
    /// Tick compute time (ns).
    pub compute: Histogram<u64>,
}

impl TickHistograms {
    /// Histograms from 1 ns to 10 s at 3 significant digits.
    pub fn new() -> Self {
        let h = || {
            Histogram::new_with_bounds(1, 10_000_000_000, 3)
                .expect("constant histogram bounds are valid")
        };
        Self {
            lateness: h(),
            compute: h(),
        }
    }
}

impl Default for TickHistograms {
    fn default() -> Self {
        Self::new()
    }
}

/// What the controller did, printed on exit.
pub struct Summary {
    /// Seconds the control thread ran.
    pub seconds: f64,
    /// Control histograms.
    pub histograms: TickHistograms,
    /// How the control thread's real-time set-up went.
    pub rt: String,
}

/// The control thread's ports and per-tick state: one [`ControlLoop::step`] is one control
/// tick (receive joint states, run the tick, publish the command and, every status period,
/// the status). Public so that tests can drive real ticks over real IPC without the thread.
pub struct ControlLoop {
    js: JointStateInput,
    rearm_in: RearmInput,
    cmd_out: CommandOutput,
    status_out: StatusOutput,
    /// Latency histograms (lateness, tick compute time).
    pub hist: TickHistograms,
    cmd: JointCommand,
    status: ControllerStatus,
    state: u32,
    ticks: u64,
    overruns: u64,
    period_ns: u64,
    status_every: u64,
    /// With a robot clock: the command event the robot waits on, and the newest state seq the
    /// last tick answered.
    command_event: Option<iceoryx2::port::notifier::Notifier<services::Ipc>>,
    answered_seq: u64,
}

impl ControlLoop {
    /// Creates the ports (call in the thread that will tick).
    pub fn new(
        node: &iceoryx2::prelude::Node<services::Ipc>,
        cfg: &Config,
    ) -> anyhow::Result<Self> {
        let ns = cfg.namespace();
        let cmd_out =
            CommandOutput::new(node, &ns, (cfg.control.command_deadline_ms * 1e6) as u64)?;
        let mut status = ControllerStatus {
            n_dof: cfg.n_dof() as u32,
            ..Default::default()
        };
        status.set_command_publisher(cmd_out.id());
        Ok(Self {
            js: JointStateInput::new(node, &ns, cfg)?,
            rearm_in: RearmInput::new(node, &ns, cfg)?,
            cmd_out,
            status_out: StatusOutput::new(node, &ns)?,
            hist: TickHistograms::new(),
            cmd: JointCommand::default(),
            status,
            state: CONTROLLER_STATE_STARTING,
            ticks: 0,
            overruns: 0,
            period_ns: cfg.control_period_ns(),
            status_every: ((cfg.control.rate_hz / cfg.control.status_rate_hz).round() as u64)
                .max(1),
            command_event: match cfg.control.clock {
                ControlClock::Robot => {
                    let name = ns.joint_command();
                    let ev = services::event_service(node, &name)?;
                    Some(services::notifier(&ev)?)
                }
                ControlClock::Timer => None,
            },
            answered_seq: 0,
        })
    }

    /// One control tick that was due at `scheduled_ns` and woke at `wake_ns`. Returns the
    /// time the tick's work ended, and counts the tick as an overrun when that is after the
    /// next deadline. No allocation but the one iceoryx2 makes per loan.
    pub fn step(
        &mut self,
        scheduled_ns: u64,
        wake_ns: u64,
        shared: &Shared,
        tick: &mut dyn ControlTick,
    ) -> u64 {
        self.hist
            .lateness
            .saturating_record(wake_ns.saturating_sub(scheduled_ns).max(1));
        self.js.poll(&shared.counters, &shared.events);
        let newest_seq = self.js.latest().map_or(0, |s| s.seq);
        if self.command_event.is_some() {
            // on the robot's clock: advance by the robot cycles since the last tick (1 when
            // every state got its tick; a new robot, whose seq restarts, counts 1; none on a
            // timer tick while the robot is quiet: it did not move on, neither does the motion)
            let behind = newest_seq.wrapping_sub(self.answered_seq);
            let cycles = if self.answered_seq == 0 || behind > 50 {
                1
            } else {
                behind as u32
            };
            tick.set_cycles(cycles);
        }
        if self.ticks == 0 {
            // announce the command publisher before the first command, so the robot's
            // session is bound when that command arrives
            shared.set_status_publisher(self.status_out.id());
            self.publish_status(wake_ns, shared);
            tick.set_command_publisher(self.cmd_out.id());
        }
        let mut answered = false;
        if let Some(seq) = self.rearm_in.poll(&shared.counters, &shared.events) {
            let (result, reason) = tick.rearm(wake_ns);
            self.status.rearm_seq = seq;
            self.status.rearm_result = result;
            self.status.rearm_reason = reason;
            let _ = shared.events.push(crate::edge::EdgeEvent::RearmAnswered {
                seq,
                result,
                reason,
            });
            answered = true;
        }
        let js = self.js.trusted(wake_ns);
        if js.is_none() {
            if let Some(bound) = self.js.bound_fresh(wake_ns) {
                tick.hold_at(bound);
            }
        }
        let not_following =
            js.is_some_and(|s| s.status_flags & chunkrt_ipc::JOINT_STATUS_NOT_FOLLOWING != 0);
        let report = tick.tick(wake_ns, js, &mut self.cmd);
        let mut state = report.state.code();
        let mut reason = report.reason.map_or(0, |r| r.code());
        if state == CONTROLLER_STATE_RUNNING && not_following {
            // the robot receives the commands, but its driver's own fallback leads the arm:
            // said as a state of its own (the executor goes on as RUNNING; the driver hands back
            // when this controller's motion passes its limits again)
            state = CONTROLLER_STATE_NOT_FOLLOWED;
            reason = chunkrt_ipc::STATE_REASON_ROBOT_NOT_FOLLOWING;
        }
        self.status.state_reason = reason;
        if report.publish {
            self.cmd.state_seq = newest_seq;
            if self.cmd_out.publish(&self.cmd, wake_ns) {
                shared.commands.fetch_add(1, Ordering::Relaxed);
                if let Some(ev) = &self.command_event {
                    // the robot waits for its answer on this event; a failed notify leaves it
                    // to its own deadline, counted as a publish error
                    if ev.notify().is_err() {
                        shared
                            .counters
                            .publish_errors
                            .fetch_add(1, Ordering::Relaxed);
                    }
                }
            } else {
                shared
                    .counters
                    .publish_errors
                    .fetch_add(1, Ordering::Relaxed);
            }
        }
        if state != self.state {
            if (state == CONTROLLER_STATE_NOT_FOLLOWED)
                != (self.state == CONTROLLER_STATE_NOT_FOLLOWED)
                && (state == CONTROLLER_STATE_RUNNING || state == CONTROLLER_STATE_NOT_FOLLOWED)
            {
                let _ = shared.events.push(crate::edge::EdgeEvent::Following {
                    following: state == CONTROLLER_STATE_RUNNING,
                });
            }
            if state == CONTROLLER_STATE_HOLD {
                shared.hold_entries.fetch_add(1, Ordering::Relaxed);
            }
            self.state = state;
            shared.state.store(self.state, Ordering::Relaxed);
        }
        self.answered_seq = newest_seq;
        self.ticks += 1;
        shared.ticks.store(self.ticks, Ordering::Relaxed);
        if answered || self.ticks.is_multiple_of(self.status_every) {
            // a re-arm is answered at once (the operator's tool waits for it)
            self.publish_status(wake_ns, shared);
        }
        let end = monotonic_ns();
        self.hist
            .compute
            .saturating_record(end.saturating_sub(wake_ns).max(1));
        if end > scheduled_ns + self.period_ns {
            // finished after the next deadline
            self.overruns += 1;
            shared.overruns.store(self.overruns, Ordering::Relaxed);
        }
        end
    }

    /// The last status of a clean stop (`CONTROLLER_STATE_STOPPED`): the robot's session with
    /// this controller ends, and the next controller is obeyed after the robot's settling time
    /// (`SessionGate`).
    pub fn publish_stopped(&mut self, shared: &Shared) {
        self.state = CONTROLLER_STATE_STOPPED;
        self.publish_status(monotonic_ns(), shared);
    }

    fn publish_status(&mut self, wake_ns: u64, shared: &Shared) {
        let h = &self.hist;
        let st = &mut self.status;
        st.seq += 1;
        st.state = self.state;
        st.ticks = self.ticks;
        st.overruns = self.overruns;
        st.chunks = shared.chunks.load(Ordering::Relaxed);
        st.joint_states = shared.counters.joint_states.load(Ordering::Relaxed);
        st.frames = shared.counters.frames.load(Ordering::Relaxed);
        st.rejected = shared.counters.rejected_snapshot();
        st.last_inference_latency_ns = shared.last_inference_latency_ns.load(Ordering::Relaxed);
        st.lateness_p50_ns = h.lateness.value_at_quantile(0.5);
        st.lateness_p99_ns = h.lateness.value_at_quantile(0.99);
        st.lateness_max_ns = h.lateness.max();
        st.compute_p50_ns = h.compute.value_at_quantile(0.5);
        st.compute_p99_ns = h.compute.value_at_quantile(0.99);
        st.compute_max_ns = h.compute.max();
        st.joint_state_age_ns = self
            .js
            .latest()
            .map(|s| wake_ns.saturating_sub(s.measurement_time_ns))
            .unwrap_or(u64::MAX);
        st.hold_entries = shared.hold_entries.load(Ordering::Relaxed);
        st.stale_cameras = shared.stale_cameras.load(Ordering::Relaxed);
        st.foreign_statuses = shared
            .counters
            .foreign_statuses
            .load(Ordering::Relaxed)
            .min(u32::MAX as u64) as u32;
        st.publish_time_ns = monotonic_ns();
        self.status_out.publish(st);
        let store = |a: &AtomicU64, v: u64| a.store(v, Ordering::Relaxed);
        store(&shared.lateness_p50_ns, st.lateness_p50_ns);
        store(&shared.lateness_p99_ns, st.lateness_p99_ns);
        store(&shared.lateness_max_ns, st.lateness_max_ns);
        store(&shared.compute_p50_ns, st.compute_p50_ns);
        store(&shared.compute_p99_ns, st.compute_p99_ns);
        store(&shared.compute_max_ns, st.compute_max_ns);
    }
}

/// The robot-clocked loop: waits for the robot's state event and runs `step(wake, wake)` at
/// once; when no state came for `quiet_ns`, ticks on the timer (`step(deadline, wake)` every
/// `period_ns`) until the robot speaks again, so that the watchdog, the hold and the status go
/// on without it. Returns the ticks run on the robot's clock and on the timer. No allocation
/// but what iceoryx2's wait makes (measured by the counting-allocator test).
pub fn run_robot_clocked(
    listener: &iceoryx2::port::listener::Listener<services::Ipc>,
    period_ns: u64,
    quiet_ns: u64,
    running: impl Fn() -> bool,
    mut step: impl FnMut(u64, u64) -> u64,
) -> (u64, u64) {
    let (mut on_robot, mut on_timer) = (0u64, 0u64);
    let mut due = monotonic_ns() + quiet_ns.max(1);
    while running() {
        let now = monotonic_ns();
        let mut woke = false;
        if due > now {
            // a failed wait counts as a timeout: the timer ticks
            woke = services::wait_event(
                listener,
                std::time::Duration::from_nanos((due - now).min(50_000_000)),
            )
            .unwrap_or(false);
        }
        let wake = monotonic_ns();
        if woke {
            step(wake, wake);
            on_robot += 1;
            due = monotonic_ns() + quiet_ns.max(1);
        } else if wake >= due {
            step(due, wake);
            on_timer += 1;
            due += period_ns.max(1);
            if due < wake {
                // behind: from now, not a burst
                due = wake + period_ns.max(1);
            }
        }
    }
    (on_robot, on_timer)
}

pub(crate) fn control_thread(
    cfg: &Config,
    shared: &Shared,
    tick: &mut dyn ControlTick,
    ready: crossbeam::channel::Sender<anyhow::Result<()>>,
) -> anyhow::Result<Summary> {
    let outcome = rt::make_current_thread_realtime(
        cfg.control.cpu,
        cfg.control.realtime_priority,
        cfg.control.lock_memory,
    );
    if outcome.fully_realtime() {
        tracing::info!("control thread: {outcome}");
    } else {
        tracing::warn!("control thread not fully real-time: {outcome}");
    }
    let setup = || -> anyhow::Result<_> {
        let node = services::node("chunkrt-control")?;
        let lp = ControlLoop::new(&node, cfg)?;
        Ok((node, lp))
    };
    let (_node, mut lp) = match setup() {
        Ok(v) => {
            let _ = ready.send(Ok(()));
            v
        }
        Err(e) => {
            let msg = format!("control thread: {e:#}");
            let _ = ready.send(Err(anyhow::anyhow!(msg.clone())));
            anyhow::bail!(msg);
        }
    };
    let period = cfg.control_period_ns();
    let start = monotonic_ns();
    let running = || !shared.stop.load(Ordering::Relaxed);
    match cfg.control.clock {
        ControlClock::Timer => {
            // absolute deadlines; a tick that ends after the next deadline is counted by `step`
            // and the deadlines it passed are skipped, not burst (the same loop the
            // control_loop bench times)
            rt::run_periodic(
                period,
                start + period,
                u64::MAX,
                running,
                |deadline, wake| lp.step(deadline, wake, shared, tick),
            );
        }
        ControlClock::Robot => {
            let name = cfg.namespace().joint_state();
            let states =
                services::event_service(&_node, &name).and_then(|ev| services::listener(&ev));
            match states {
                Ok(listener) => {
                    let quiet = (cfg.control.robot_clock_timeout_ms * 1e6) as u64;
                    run_robot_clocked(&listener, period, quiet, running, |scheduled, wake| {
                        lp.step(scheduled, wake, shared, tick)
                    });
                }
                Err(e) => {
                    tracing::error!(
                        "control thread: cannot listen for the robot's states ({e}); \
                         the timer clocks the tick"
                    );
                    rt::run_periodic(period, start + period, u64::MAX, running, |d, w| {
                        lp.step(d, w, shared, tick)
                    });
                }
            }
        }
    }
    lp.publish_stopped(shared);
    Ok(Summary {
        seconds: (monotonic_ns() - start) as f64 / 1e9,
        histograms: lp.hist,
        rt: outcome.to_string(),
    })
}
