//! The controller process (`chunkrt run`): threads, real-time set-up, status.
//!
//! ```text
//!  observation thread:  cameras + joint state ─▶ Observation ─▶ ChunkSource ─▶ chunk hand-off
//!  control thread:      joint state ─▶ ControlTick (every period, absolute deadline) ─▶ command
//!  main thread:         logs events, prints the periodic status line, stops everything
//! ```
//!
//! Each thread creates its own iceoryx2 node and ports. Threads share only atomics and
//! lock-free queues; the control thread never waits for anything but its next deadline.

use std::path::PathBuf;
use std::sync::atomic::{AtomicBool, AtomicU32, AtomicU64, Ordering};
use std::sync::Arc;
use std::thread::JoinHandle;
use std::time::Duration;

use anyhow::Context;
use hdrhistogram::Histogram;

use chunkrt_ipc::config::{PolicyDevice, PolicyKind};
use chunkrt_ipc::services;
use chunkrt_ipc::{
    controller_state_name, monotonic_ns, sleep_until_ns, Config, ControllerStatus, JointCommand,
    JointState, RejectReason, CONTROLLER_STATE_HOLD, CONTROLLER_STATE_STARTING,
    CONTROLLER_STATE_STOPPED,
};

use crate::chunk::ActionChunk;
use crate::control::{EventReader, Executor, InferenceLink, InferenceRequest};
use crate::edge::{
    event_ring, CameraInput, CommandOutput, Counters, EdgeEvent, EventRing, JointStateInput,
    Observation, RearmInput, Source, StatusOutput,
};
use crate::rt;

/// `chunkrt run`.
#[derive(Debug, Clone, clap::Args)]
pub struct RunArgs {
    /// Configuration file (TOML). Default: the embedded demo robot (`config/default.toml`).
    #[arg(long)]
    pub config: Option<PathBuf>,
    /// Override `robot.namespace` (service names become `<NS>/joint_state`, ...).
    #[arg(long)]
    pub namespace: Option<String>,
    /// Stop after this many seconds (default: run until SIGINT / SIGTERM).
    #[arg(long)]
    pub duration: Option<f64>,
    /// Seconds between status log lines (0: none).
    #[arg(long, default_value_t = 1.0)]
    pub log_every: f64,
    /// On exit, write the lateness and tick-time histograms to this HdrHistogram interval log
    /// (render with `chunkrt report DIR`).
    #[arg(long, value_name = "FILE")]
    pub histogram_log: Option<PathBuf>,
    /// Override `policy.prompt` (the task the policy is asked to do).
    #[arg(long)]
    pub prompt: Option<String>,
    /// Override `policy.kind`: hold, pi0 or pi05 (`hold` runs without a model: the robot is
    /// held where it is).
    #[arg(long)]
    pub policy: Option<PolicyKind>,
    /// Override `policy.device`: cpu, cuda or cuda:N (a GPU needs a build with `--features cuda`).
    #[arg(long)]
    pub device: Option<PolicyDevice>,
}

/// Loads the configuration named by `--config` (or the embedded default) and applies
/// `--namespace`.
pub fn load_config(config: Option<&PathBuf>, namespace: Option<&str>) -> anyhow::Result<Config> {
    let mut cfg = match config {
        Some(p) => Config::load(p)?,
        None => Config::embedded_default(),
    };
    if let Some(ns) = namespace {
        cfg.robot.namespace = ns.to_string();
        let file = cfg.source.display().to_string();
        cfg.validate(&format!("{file} (with --namespace)"))?;
    }
    Ok(cfg)
}

/// Produces action chunks from observations; runs in the observation/inference thread when
/// the control side asks for one (an [`InferenceRequest`]: when to start, and for real-time
/// chunking the previous chunk's remaining actions and their weights). The policy implements
/// it; tests use scripted sources.
pub trait ChunkSource: Send {
    /// Name for logs.
    fn name(&self) -> &str;
    /// Computes the next chunk for `obs`; `Ok(None)` when the source has nothing to execute.
    fn compute(
        &mut self,
        obs: &Observation,
        request: &InferenceRequest,
    ) -> anyhow::Result<Option<ActionChunk>>;
    /// Whether the chunks depend on the camera frames: then a missing or stale frame stops
    /// the source (and the controller holds) until every camera is fresh again.
    fn uses_cameras(&self) -> bool {
        false
    }
}

/// Cameras whose frame is missing or older than `max_age_ns` at `now_ns` (bit i = camera i).
pub fn stale_cameras(frames: &[crate::edge::Frame], now_ns: u64, max_age_ns: u64) -> u64 {
    frames
        .iter()
        .enumerate()
        .filter(|(_, f)| !f.valid || now_ns.saturating_sub(f.header.capture_time_ns) > max_age_ns)
        .fold(0, |m, (i, _)| m | 1u64 << i.min(63))
}

/// The names of the cameras in `mask` ("base, wrist").
pub fn camera_names(cfg: &Config, mask: u64) -> String {
    cfg.cameras
        .iter()
        .enumerate()
        .filter(|(i, _)| mask & (1u64 << (*i).min(63)) != 0)
        .map(|(_, c)| c.name.as_str())
        .collect::<Vec<_>>()
        .join(", ")
}

/// The source used when no policy is configured: it never produces a chunk, so the
/// controller holds the robot where it is.
pub struct HoldSource;

impl ChunkSource for HoldSource {
    fn name(&self) -> &str {
        "hold"
    }
    fn compute(
        &mut self,
        _obs: &Observation,
        _request: &InferenceRequest,
    ) -> anyhow::Result<Option<ActionChunk>> {
        Ok(None)
    }
}

/// What one control tick decided.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct TickOutcome {
    /// Publish the command written into `cmd`.
    pub publish: bool,
    /// `CONTROLLER_STATE_*` after the tick.
    pub state: u32,
    /// `STATE_REASON_*`: why the controller is in that state.
    pub reason: u32,
}

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
    ) -> TickOutcome;

    /// An operator asks to leave FAULT (`chunkrt rearm`). The default refuses: nothing to
    /// re-arm. Must not allocate, block or do I/O.
    fn rearm(&mut self, _now_ns: u64) -> RearmAnswer {
        (chunkrt_ipc::REARM_REFUSED_NOT_IN_FAULT, 0)
    }
}

impl ControlTick for Executor {
    fn tick(
        &mut self,
        now_ns: u64,
        joint_state: Option<&JointState>,
        cmd: &mut JointCommand,
    ) -> TickOutcome {
        let r = Executor::tick(self, now_ns, joint_state, cmd);
        TickOutcome {
            publish: r.publish,
            state: r.state.code(),
            reason: self.state_reason().map_or(0, |r| r.code()),
        }
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

/// State shared by the controller's threads.
pub struct Shared {
    /// Message counters.
    pub counters: Counters,
    /// Events to log (written by the real-time threads, drained by the main thread).
    pub events: EventRing,
    /// Set to stop every thread.
    pub stop: AtomicBool,
    /// `CONTROLLER_STATE_*`.
    pub state: AtomicU32,
    /// Ticks executed.
    pub ticks: AtomicU64,
    /// Ticks that ended after the next deadline.
    pub overruns: AtomicU64,
    /// Commands published.
    pub commands: AtomicU64,
    /// Chunks produced by the source.
    pub chunks: AtomicU64,
    /// Latency of the last chunk (observation → chunk ready), ns.
    pub last_inference_latency_ns: AtomicU64,
    /// Transitions into HOLD.
    pub hold_entries: AtomicU64,
    /// Cameras the policy would use with a missing or stale frame (bit i = camera i), as the
    /// observation thread last saw them.
    pub stale_cameras: AtomicU64,
    /// Latest status as published (for the periodic log line).
    pub lateness_p50_ns: AtomicU64,
    pub lateness_p99_ns: AtomicU64,
    pub lateness_max_ns: AtomicU64,
    pub compute_p50_ns: AtomicU64,
    pub compute_p99_ns: AtomicU64,
    pub compute_max_ns: AtomicU64,
}

impl Default for Shared {
    fn default() -> Self {
        Self::new()
    }
}

impl Shared {
    /// Fresh counters and state.
    pub fn new() -> Self {
        Self {
            counters: Counters::default(),
            events: event_ring(1024),
            stop: AtomicBool::new(false),
            state: AtomicU32::new(CONTROLLER_STATE_STARTING),
            ticks: AtomicU64::new(0),
            overruns: AtomicU64::new(0),
            commands: AtomicU64::new(0),
            chunks: AtomicU64::new(0),
            last_inference_latency_ns: AtomicU64::new(0),
            hold_entries: AtomicU64::new(0),
            stale_cameras: AtomicU64::new(0),
            lateness_p50_ns: AtomicU64::new(0),
            lateness_p99_ns: AtomicU64::new(0),
            lateness_max_ns: AtomicU64::new(0),
            compute_p50_ns: AtomicU64::new(0),
            compute_p99_ns: AtomicU64::new(0),
            compute_max_ns: AtomicU64::new(0),
        }
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

/// A running controller.
pub struct Controller {
    shared: Arc<Shared>,
    executor_events: EventReader,
    /// Repeated rejections: one full line per kind per second, then a count.
    log_limit: crate::log_limit::LogLimiter,
    control: Option<JoinHandle<anyhow::Result<Summary>>>,
    observer: Option<JoinHandle<anyhow::Result<()>>>,
}

impl Controller {
    /// Starts the observation/inference thread (running `source` whenever the executor asks
    /// for a chunk) and the control thread (running the executor every period).
    pub fn start(
        cfg: Config,
        mut executor: Executor,
        mut source: Box<dyn ChunkSource>,
    ) -> anyhow::Result<Self> {
        let link = executor.connect();
        let executor_events = executor.events();
        // clean up shared memory of controllers that died without doing so
        {
            let node = services::node("chunkrt-cleanup")?;
            let n = services::cleanup_dead_nodes(&node);
            if n > 0 {
                tracing::info!("cleaned up {n} dead iceoryx2 node(s)");
            }
        }
        let shared = Arc::new(Shared::new());
        let (ready_tx, ready_rx) = crossbeam::channel::bounded::<anyhow::Result<()>>(2);

        let observer = {
            let cfg = cfg.clone();
            let shared = shared.clone();
            let ready = ready_tx.clone();
            std::thread::Builder::new()
                .name("chunkrt-observe".into())
                .spawn(move || observation_thread(&cfg, &shared, source.as_mut(), &link, ready))
                .context("cannot spawn the observation thread")?
        };
        let control = {
            let shared = shared.clone();
            std::thread::Builder::new()
                .name("chunkrt-control".into())
                .spawn(move || control_thread(&cfg, &shared, &mut executor, ready_tx))
                .context("cannot spawn the control thread")?
        };
        let mut me = Self {
            shared,
            executor_events,
            log_limit: crate::log_limit::LogLimiter::new(Duration::from_secs(1)),
            control: Some(control),
            observer: Some(observer),
        };
        for _ in 0..2 {
            match ready_rx.recv_timeout(Duration::from_secs(10)) {
                Ok(Ok(())) => {}
                Ok(Err(e)) => {
                    me.shared.stop.store(true, Ordering::SeqCst);
                    let _ = me.join();
                    return Err(e);
                }
                Err(_) => {
                    me.shared.stop.store(true, Ordering::SeqCst);
                    anyhow::bail!("controller threads did not start within 10 s");
                }
            }
        }
        Ok(me)
    }

    /// Shared counters and state.
    pub fn shared(&self) -> &Arc<Shared> {
        &self.shared
    }

    /// True while both threads run.
    pub fn is_running(&self) -> bool {
        self.control.as_ref().is_some_and(|h| !h.is_finished())
            && self.observer.as_ref().is_some_and(|h| !h.is_finished())
    }

    /// Logs the events queued by the real-time threads: the first of each kind (source and
    /// reason) per second in full, then one summary line per kind and second with the count
    /// ([`crate::log_limit`]).
    pub fn log_events(&mut self, cfg: &Config) {
        self.executor_events.drain(|e| tracing::info!("state {e}"));
        let now = std::time::Instant::now();
        let source = |s: Source| match s {
            Source::JointState => "joint_state".to_string(),
            Source::Rearm => "rearm".to_string(),
            Source::Camera(i) => format!(
                "camera {}",
                cfg.cameras.get(i).map(|c| c.name.as_str()).unwrap_or("?")
            ),
        };
        while let Some(ev) = self.shared.events.pop() {
            match ev {
                EdgeEvent::Rejected { source: s, error } => {
                    let (src, reason) = (source(s), error.reason().name());
                    let line = || format!("rejected {src} message ({reason}): {error}");
                    if self.log_limit.admit(
                        &format!("rejected {src} message ({reason})"),
                        line,
                        now,
                    ) {
                        tracing::warn!("{}", line());
                    }
                }
                EdgeEvent::RearmAnswered {
                    seq,
                    result,
                    reason,
                } => {
                    if result == chunkrt_ipc::REARM_ACCEPTED {
                        tracing::info!("re-arm request {seq}: accepted");
                    } else {
                        tracing::warn!(
                            "re-arm request {seq}: {}{}",
                            chunkrt_ipc::rearm_result_name(result),
                            if reason != 0 {
                                format!(" ({})", chunkrt_ipc::state_reason_name(reason))
                            } else {
                                String::new()
                            }
                        );
                    }
                }
                EdgeEvent::PortError { source: s, publish } => {
                    let line = || {
                        format!(
                            "iceoryx2 {} error on {}",
                            if publish { "publish" } else { "receive" },
                            source(s)
                        )
                    };
                    let kind = line();
                    if self.log_limit.admit(&kind, line, now) {
                        tracing::warn!("{kind}");
                    }
                }
            }
        }
        self.log_limit.flush(now, |kind, n, last| {
            tracing::warn!(
                "{kind}: {n} more in the last second (counted in the status; last: {last})"
            )
        });
    }

    fn join(&mut self) -> anyhow::Result<Summary> {
        let observed = match self.observer.take().map(|h| h.join()) {
            Some(Ok(r)) => r,
            Some(Err(_)) => Err(anyhow::anyhow!("the observation thread panicked")),
            None => Ok(()),
        };
        let summary = match self.control.take().map(|h| h.join()) {
            Some(Ok(r)) => r,
            Some(Err(_)) => Err(anyhow::anyhow!("the control thread panicked")),
            None => Err(anyhow::anyhow!("the control thread was already joined")),
        };
        observed?;
        summary
    }

    /// Stops both threads and returns the summary.
    pub fn stop(mut self) -> anyhow::Result<Summary> {
        self.shared.stop.store(true, Ordering::SeqCst);
        self.join()
    }
}

impl Drop for Controller {
    fn drop(&mut self) {
        self.shared.stop.store(true, Ordering::SeqCst);
        let _ = self.join();
    }
}

fn observation_thread(
    cfg: &Config,
    shared: &Shared,
    source: &mut dyn ChunkSource,
    link: &InferenceLink,
    ready: crossbeam::channel::Sender<anyhow::Result<()>>,
) -> anyhow::Result<()> {
    // the inference thread gets a core of its own when there is one besides the control core
    let control_core = cfg.control.cpu.unwrap_or_else(rt::default_control_core);
    if rt::available_cores() > 1 {
        let core = if control_core == 0 { 1 } else { 0 };
        match rt::pin_current_thread(core) {
            Ok(c) => tracing::info!("observation/inference thread: pinned to core {c}"),
            Err(e) => tracing::warn!("observation/inference thread not pinned: {e}"),
        }
    }
    let ns = cfg.namespace();
    let setup = || -> anyhow::Result<_> {
        let node = services::node("chunkrt-observe")?;
        let cams = CameraInput::new(&node, &ns, cfg)?;
        let js = JointStateInput::new(&node, &ns, cfg)?;
        Ok((node, cams, js))
    };
    let (_node, mut cams, mut js) = match setup() {
        Ok(v) => {
            let _ = ready.send(Ok(()));
            v
        }
        Err(e) => {
            let _ = ready.send(Err(anyhow::anyhow!("observation thread: {e:#}")));
            return Ok(());
        }
    };
    // this thread's joint-state subscriber is a second reader of the same stream; its
    // rejections are counted by the control thread already, so they go to private counters
    let private = Counters::default();
    let private_events = event_ring(1);
    let mut obs = Observation::new(cfg);
    let poll_period_ns = 2_000_000;
    let mut next = monotonic_ns();
    let mut source_failures = 0u64;
    let frame_max_age_ns = (cfg.control.frame_max_age_ms * 1e6) as u64;
    let watch_cameras = source.uses_cameras();
    let mut stale_before = 0u64;
    while !shared.stop.load(Ordering::Relaxed) {
        next += poll_period_ns;
        sleep_until_ns(next);
        cams.poll(&mut obs.frames, &shared.counters, &shared.events);
        let now = monotonic_ns();
        // freshness at the time of use: a camera that stopped sending stops the policy (the
        // control tick sees the mask and holds), and the policy resumes when it is back
        let stale = if watch_cameras {
            stale_cameras(&obs.frames, now, frame_max_age_ns)
        } else {
            0
        };
        link.stale_cameras.store(stale, Ordering::Relaxed);
        shared.stale_cameras.store(stale, Ordering::Relaxed);
        if stale != stale_before {
            let gone = stale & !stale_before;
            let back = stale_before & !stale;
            if gone != 0 {
                tracing::warn!(
                    "camera {}: no frame newer than {} ms: holding until it is back",
                    camera_names(cfg, gone),
                    cfg.control.frame_max_age_ms
                );
            }
            if back != 0 {
                tracing::info!("camera {}: frames again", camera_names(cfg, back));
            }
            stale_before = stale;
        }
        js.poll(&private, &private_events);
        while private_events.pop().is_some() {}
        // chunk buffers the control thread is done with are dropped here, off the RT path
        while link.chunks.take_recycled().is_some() {}
        // a second joint-state publisher: nothing trusted, no observation from a forged state
        let Some(state) = js.trusted(now) else {
            continue;
        };
        if stale != 0 {
            continue;
        }
        let Some(request) = link.requests.try_recv() else {
            continue;
        };
        obs.joint_state = *state;
        obs.assembled_ns = now;
        let result = source.compute(&obs, &request);
        link.requests.done(request);
        match result {
            Ok(Some(chunk)) => {
                shared.chunks.fetch_add(1, Ordering::Relaxed);
                shared.last_inference_latency_ns.store(
                    chunk.ready_ns.saturating_sub(chunk.t_obs_ns),
                    Ordering::Relaxed,
                );
                // a displaced, never-executed chunk comes back here and is dropped here
                drop(link.chunks.send(chunk));
            }
            Ok(None) => {}
            Err(e) => {
                source_failures += 1;
                if source_failures.is_power_of_two() {
                    tracing::error!(
                        "chunk source '{}' failed ({source_failures} times so far): {e:#}",
                        source.name()
                    );
                }
            }
        }
        if now > next + 100 * poll_period_ns {
            next = now; // the source took long: do not try to catch up
        }
    }
    Ok(())
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
    deadline_ns: u64,
    period_ns: u64,
    status_every: u64,
}

impl ControlLoop {
    /// Creates the ports (call in the thread that will tick).
    pub fn new(
        node: &iceoryx2::prelude::Node<services::Ipc>,
        cfg: &Config,
    ) -> anyhow::Result<Self> {
        let ns = cfg.namespace();
        let cmd_out = CommandOutput::new(node, &ns)?;
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
            deadline_ns: (cfg.control.command_deadline_ms * 1e6) as u64,
            period_ns: cfg.control_period_ns(),
            status_every: ((cfg.control.rate_hz / cfg.control.status_rate_hz).round() as u64)
                .max(1),
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
        if self.ticks == 0 {
            // announce the command publisher before the first command, so the robot's
            // session is bound when that command arrives
            self.publish_status(wake_ns, shared);
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
        let out = tick.tick(wake_ns, self.js.trusted(wake_ns), &mut self.cmd);
        self.status.state_reason = out.reason;
        if out.publish {
            self.cmd.seq += 1;
            self.cmd.deadline_ns = wake_ns + self.deadline_ns;
            if self.cmd_out.publish(&self.cmd, monotonic_ns()) {
                shared.commands.fetch_add(1, Ordering::Relaxed);
            } else {
                shared
                    .counters
                    .publish_errors
                    .fetch_add(1, Ordering::Relaxed);
            }
        }
        if out.state != self.state {
            if out.state == CONTROLLER_STATE_HOLD {
                shared.hold_entries.fetch_add(1, Ordering::Relaxed);
            }
            self.state = out.state;
            shared.state.store(self.state, Ordering::Relaxed);
        }
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
    /// this controller ends at once, so the next controller is obeyed without a pause.
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

fn control_thread(
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
    // absolute deadlines; a tick that ends after the next deadline is counted by `step` and
    // the deadlines it passed are skipped, not burst (the same loop the control_loop bench times)
    rt::run_periodic(
        period,
        start + period,
        u64::MAX,
        || !shared.stop.load(Ordering::Relaxed),
        |deadline, wake| lp.step(deadline, wake, shared, tick),
    );
    lp.publish_stopped(shared);
    Ok(Summary {
        seconds: (monotonic_ns() - start) as f64 / 1e9,
        histograms: lp.hist,
        rt: outcome.to_string(),
    })
}

fn us(ns: u64) -> f64 {
    ns as f64 / 1e3
}

/// One line for the periodic log.
pub fn status_line(shared: &Shared) -> String {
    let rejected: Vec<String> = RejectReason::ALL
        .iter()
        .filter_map(|r| {
            let n = shared.counters.rejected[r.code()].load(Ordering::Relaxed);
            (n > 0).then(|| format!("{}={n}", r.name()))
        })
        .collect();
    format!(
        "state={} ticks={} overruns={} commands={} joint_states={} frames={} chunks={} \
         lateness p50/p99/max={:.0}/{:.0}/{:.0} us tick p50/p99/max={:.1}/{:.1}/{:.1} us rejected=[{}]",
        controller_state_name(shared.state.load(Ordering::Relaxed)),
        shared.ticks.load(Ordering::Relaxed),
        shared.overruns.load(Ordering::Relaxed),
        shared.commands.load(Ordering::Relaxed),
        shared.counters.joint_states.load(Ordering::Relaxed),
        shared.counters.frames.load(Ordering::Relaxed),
        shared.chunks.load(Ordering::Relaxed),
        us(shared.lateness_p50_ns.load(Ordering::Relaxed)),
        us(shared.lateness_p99_ns.load(Ordering::Relaxed)),
        us(shared.lateness_max_ns.load(Ordering::Relaxed)),
        us(shared.compute_p50_ns.load(Ordering::Relaxed)),
        us(shared.compute_p99_ns.load(Ordering::Relaxed)),
        us(shared.compute_max_ns.load(Ordering::Relaxed)),
        rejected.join(" "),
    )
}

/// Prints the exit summary (stdout: it is the command's result).
pub fn print_summary(shared: &Shared, summary: &Summary) {
    let h = &summary.histograms;
    let row = |name: &str, h: &Histogram<u64>| {
        println!(
            "  {name:<10} {:>9} {:>9.1} {:>9.1} {:>9.1} {:>9.1} {:>9.1}",
            h.len(),
            us(h.value_at_quantile(0.5)),
            us(h.value_at_quantile(0.9)),
            us(h.value_at_quantile(0.99)),
            us(h.value_at_quantile(0.999)),
            us(h.max()),
        )
    };
    println!("chunkrt summary: {:.2} s, {}", summary.seconds, summary.rt);
    println!(
        "  {:<10} {:>9} {:>9} {:>9} {:>9} {:>9} {:>9}",
        "us", "count", "p50", "p90", "p99", "p99.9", "max"
    );
    row("lateness", &h.lateness);
    row("tick", &h.compute);
    println!("  {}", status_line(shared));
    let ticks = shared.ticks.load(Ordering::Relaxed) as f64;
    println!(
        "  command rate {:.1} Hz, joint states {:.1} Hz, frames {:.1} Hz, publish errors {}",
        shared.commands.load(Ordering::Relaxed) as f64 / summary.seconds.max(1e-9),
        shared.counters.joint_states.load(Ordering::Relaxed) as f64 / summary.seconds.max(1e-9),
        shared.counters.frames.load(Ordering::Relaxed) as f64 / summary.seconds.max(1e-9),
        shared.counters.publish_errors.load(Ordering::Relaxed),
    );
    if ticks == 0.0 {
        println!("  (no control ticks ran)");
    }
}

/// Per-camera frame counts, `name=count` separated by spaces.
pub fn frames_per_camera(cfg: &Config, shared: &Shared) -> String {
    cfg.cameras
        .iter()
        .zip(shared.counters.frames_per_camera.iter())
        .map(|(c, n)| format!("{}={}", c.name, n.load(Ordering::Relaxed)))
        .collect::<Vec<_>>()
        .join(" ")
}

/// `chunkrt run`: the controller until SIGINT / SIGTERM or `--duration`.
pub fn run(args: RunArgs) -> anyhow::Result<()> {
    let mut cfg = load_config(args.config.as_ref(), args.namespace.as_deref())?;
    if let Some(p) = &args.prompt {
        cfg.policy.prompt = p.clone();
    }
    if let Some(k) = args.policy {
        cfg.policy.kind = k;
    }
    if let Some(d) = args.device {
        cfg.policy.device = d;
    }
    let stop_flag = chunkrt_tools::shutdown::flag();
    tracing::info!(
        "chunkrt run: robot '{}' ({} joints) on '{}', {} camera(s), control at {} Hz, policy '{}'",
        cfg.robot.name,
        cfg.n_dof(),
        cfg.robot.namespace,
        cfg.cameras.len(),
        cfg.control.rate_hz,
        cfg.policy.kind
    );
    let executor = Executor::new(&cfg).context("invalid execution settings")?;
    let source: Box<dyn ChunkSource> = match cfg.policy.kind {
        PolicyKind::Hold => Box::new(HoldSource),
        PolicyKind::Pi0 | PolicyKind::Pi05 => Box::new(crate::inference::PolicySource::load(&cfg)?),
    };
    tracing::info!("chunk source: {}", source.name());
    let mut controller = Controller::start(cfg.clone(), executor, source)?;
    let started = std::time::Instant::now();
    let mut last_log = std::time::Instant::now();
    while !stop_flag.load(Ordering::Relaxed) && controller.is_running() {
        std::thread::sleep(Duration::from_millis(20));
        controller.log_events(&cfg);
        if args.log_every > 0.0 && last_log.elapsed().as_secs_f64() >= args.log_every {
            tracing::info!("{}", status_line(controller.shared()));
            last_log = std::time::Instant::now();
        }
        if args
            .duration
            .is_some_and(|d| started.elapsed().as_secs_f64() >= d)
        {
            break;
        }
    }
    let shared = controller.shared().clone();
    let summary = controller.stop()?;
    controller_log_final(&cfg, &shared);
    print_summary(&shared, &summary);
    println!("  frames per camera: {}", frames_per_camera(&cfg, &shared));
    if let Some(path) = &args.histogram_log {
        let series = [
            crate::report::Series::new("control_lateness", summary.histograms.lateness.clone()),
            crate::report::Series::new("control_tick", summary.histograms.compute.clone()),
        ];
        crate::report::write_interval_log(
            path,
            &series,
            Duration::from_secs_f64(summary.seconds),
            &format!("chunkrt run on '{}': {}", cfg.robot.namespace, summary.rt),
        )?;
        println!("  histograms written to {}", path.display());
    }
    Ok(())
}

fn controller_log_final(cfg: &Config, shared: &Shared) {
    let total = shared.counters.rejected_total();
    if total > 0 {
        tracing::warn!(
            "{total} message(s) rejected on '{}' during the run",
            cfg.robot.namespace
        );
    }
}
