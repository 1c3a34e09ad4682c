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

use std::sync::atomic::Ordering;
use std::sync::Arc;
use std::thread::JoinHandle;
use std::time::Duration;

use anyhow::Context;
use hdrhistogram::Histogram;

use crate::config::Config;
use chunkrt_ipc::services;
use chunkrt_ipc::{controller_state_name, monotonic_ns, sleep_until_ns, RejectReason};

pub use crate::contract::{ChunkSource, HoldSource};
use crate::control::{EventReader, Executor, InferenceLink};
use crate::control_loop::control_thread;
pub use crate::control_loop::Summary;
pub use crate::control_loop::{ControlLoop, ControlTick, RearmAnswer, TickHistograms};
use crate::edge::history::FrameHistory;
use crate::edge::{
    event_ring, CameraInput, Counters, EdgeEvent, JointStateInput, Observation, Source, StatusWatch,
};
use crate::rt;
pub use crate::shared::Shared;
use crate::worker::{Delivery, InferenceWorker, Turn};

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
        if !source.produces_chunks() {
            executor.without_chunk_source();
        }
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
                .spawn(move || observation_thread(&cfg, &shared, source.as_mut(), link, ready))
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
                        let line = || {
                            format!(
                                "re-arm request {seq}: {}{}",
                                chunkrt_ipc::rearm_result_name(result),
                                if reason != 0 {
                                    format!(" ({})", chunkrt_ipc::state_reason_name(reason))
                                } else {
                                    String::new()
                                }
                            )
                        };
                        // refusals are rate-limited like rejections (a flood of requests)
                        if self.log_limit.admit("re-arm refused", line, now) {
                            tracing::warn!("{}", line());
                        }
                    }
                }
                EdgeEvent::Following { following } => {
                    let line = || {
                        if following {
                            "the robot follows this controller's commands again".to_string()
                        } else {
                            "NOT FOLLOWED: the robot's driver leads the arm, not this \
                             controller's commands (state: not followed)"
                                .to_string()
                        }
                    };
                    if self.log_limit.admit("robot following", line, now) {
                        if following {
                            tracing::info!("{}", line());
                        } else {
                            tracing::warn!("{}", line());
                        }
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
    link: InferenceLink,
    ready: crossbeam::channel::Sender<anyhow::Result<()>>,
) -> anyhow::Result<()> {
    let ns = cfg.namespace();
    // every chunk on NS/chunks for recorders and viewers (this thread, never the control tick;
    // a namespace whose chunk service cannot be opened only loses the recording); the node
    // outlives the worker that holds its publisher
    let chunk_node = services::node("chunkrt-chunks");
    let mut worker = InferenceWorker::new(link, Delivery::Immediate);
    match chunk_node
        .as_ref()
        .map_err(|e| anyhow::anyhow!("{e}"))
        .and_then(|node| {
            let svc = services::chunk_service(node, &ns.chunks())?;
            Ok(services::publisher(&svc)?)
        }) {
        Ok(publisher) => worker.set_tap(Box::new(chunk_publisher(publisher))),
        Err(e) => tracing::warn!("chunks are not published on '{}': {e:#}", ns.chunks()),
    }
    // the inference thread gets a core of its own when there is one besides the control core
    let control_core = cfg.control.cpu.unwrap_or_else(rt::default_control_core);
    if rt::available_cores() > 1 {
        let core = if control_core == 0 { 1 } else { 0 };
        match rt::pin_current_thread(core) {
            Ok(c) => tracing::info!("observation/inference thread: pinned to core {c}"),
            Err(e) => tracing::warn!("observation/inference thread not pinned: {e}"),
        }
    }
    let setup = || -> anyhow::Result<_> {
        let node = services::node("chunkrt-observe")?;
        let cams = CameraInput::new(&node, &ns, cfg)?;
        let js = JointStateInput::new(&node, &ns, cfg)?;
        let history = FrameHistory::new(cfg, source.delayed_views())?;
        let statuses = StatusWatch::new(&node, &ns)?;
        Ok((node, cams, js, history, statuses))
    };
    let (_node, mut cams, mut js, mut history, statuses) = match setup() {
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
    for v in source.delayed_views() {
        tracing::info!(
            "policy image input {}: camera {}'s frame of {} ms before (delayed view)",
            v.name,
            v.camera,
            v.delay_ms
        );
    }
    let mut obs = Observation::with_views(cfg, source.delayed_views());
    let n_cams = cfg.cameras.len();
    let poll_period_ns = 2_000_000;
    let mut next = monotonic_ns();
    let frame_max_age_ns = (cfg.control.frame_max_age_ms * 1e6) as u64;
    let watch_cameras = source.uses_cameras();
    let mut stale_before = 0u64;
    let mut foreign = ForeignStatusLog::default();
    while !shared.stop.load(Ordering::Relaxed) {
        next += poll_period_ns;
        sleep_until_ns(next);
        cams.poll(&mut obs.frames[..n_cams], &shared.counters, &shared.events);
        history.update(&mut obs.frames);
        let now = monotonic_ns();
        // freshness at the time of use: a camera that stopped sending stops the policy (the
        // control tick sees the mask and holds), and the policy resumes when it is back
        let stale = if watch_cameras {
            stale_cameras(&obs.frames[..n_cams], now, frame_max_age_ns)
        } else {
            0
        };
        worker.link().stale_cameras.store(stale, Ordering::Relaxed);
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
        if let Some(id) = statuses.poll(shared.status_publisher(), &shared.counters) {
            foreign.name(id, &ns, &shared.counters);
        }
        worker.poll(now);
        // a second joint-state publisher: nothing trusted, no observation from a forged state
        let Some(state) = js.trusted(now) else {
            continue;
        };
        if stale != 0 {
            continue;
        }
        let Some(request) = worker.next_request() else {
            continue;
        };
        obs.joint_state = *state;
        obs.assembled_ns = now;
        match worker.answer(now, request, source, &obs) {
            Turn::Chunk { latency_ns } => {
                shared.chunks.fetch_add(1, Ordering::Relaxed);
                shared
                    .last_inference_latency_ns
                    .store(latency_ns, Ordering::Relaxed);
            }
            Turn::Failed(e) => {
                let failures = worker.stats().failures;
                if failures.is_power_of_two() {
                    tracing::error!(
                        "chunk source '{}' failed ({failures} times so far): {e:#}",
                        source.name()
                    );
                }
            }
            Turn::Idle | Turn::Nothing => {}
        }
        if now > next + 100 * poll_period_ns {
            next = now; // the source took long: do not try to catch up
        }
    }
    Ok(())
}

/// Publishes each chunk as an [`chunkrt_ipc::ActionChunkMsg`] (the first
/// [`chunkrt_ipc::MAX_CHUNK_HORIZON`] actions); a refused loan loses that chunk's record only.
fn chunk_publisher(
    publisher: iceoryx2::port::publisher::Publisher<services::Ipc, chunkrt_ipc::ActionChunkMsg, ()>,
) -> impl FnMut(&crate::chunk::ActionChunk, usize) {
    let mut seq = 0u64;
    move |chunk, delay_steps| {
        let Ok(sample) = publisher.loan_uninit() else {
            return;
        };
        seq += 1;
        let n = chunk.n_dof.min(chunkrt_ipc::MAX_DOF);
        let h = chunk.horizon().min(chunkrt_ipc::MAX_CHUNK_HORIZON);
        let mut m = chunkrt_ipc::ActionChunkMsg {
            seq,
            publish_time_ns: monotonic_ns(),
            chunk_id: chunk.id,
            observation_seq: chunk.observation_seq,
            observation_time_ns: chunk.t_obs_ns,
            ready_time_ns: chunk.ready_ns,
            start_shift_ns: chunk.start_shift_ns,
            period_ns: chunk.period_ns,
            delay_steps: delay_steps.min(u32::MAX as usize) as u32,
            horizon: h as u32,
            n_dof: n as u32,
            ..Default::default()
        };
        for (k, row) in m.actions.iter_mut().enumerate().take(h) {
            row[..n].copy_from_slice(&chunk.action(k)[..n]);
        }
        let _ = sample.write_payload(m).send();
    }
}

fn us(ns: u64) -> f64 {
    ns as f64 / 1e3
}

/// Names a second status publisher in the log: at once for a new one, then once every 10 s
/// while it keeps speaking (a forger cannot flood the log).
#[derive(Default)]
struct ForeignStatusLog {
    last: Option<(u128, std::time::Instant)>,
}

impl ForeignStatusLog {
    fn name(&mut self, id: u128, ns: &chunkrt_ipc::Namespace, counters: &Counters) {
        let now = std::time::Instant::now();
        let due = match self.last {
            Some((last, at)) => last != id || now.duration_since(at) >= Duration::from_secs(10),
            None => true,
        };
        if due {
            self.last = Some((id, now));
            tracing::warn!(
                "a second status publisher {id:#x} on '{}' (another controller in this \
                 namespace, or a forger): a robot that binds sessions holds while it speaks; \
                 {} foreign statuses so far",
                ns.status(),
                counters.foreign_statuses.load(Ordering::Relaxed)
            );
        }
    }
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
         lateness p50/p99/max={:.0}/{:.0}/{:.0} us tick p50/p99/max={:.1}/{:.1}/{:.1} us rejected=[{}] \
         rearm_throttled={} foreign_statuses={}",
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
        shared.counters.rearm_throttled.load(Ordering::Relaxed),
        shared.counters.foreign_statuses.load(Ordering::Relaxed),
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
