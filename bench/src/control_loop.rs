//! `control_loop`: the control thread's wake-up lateness and tick compute time at 500 Hz and
//! 1 kHz, idle and with a candle matmul load saturating the other core, next to `cyclictest` on
//! the same core under the same load (the platform's floor).
//!
//! The schedule is the controller's own ([`chunkrt_controller::rt::run_periodic`]). The tick body is
//! pluggable ([`TickFactory`]). By default it is the controller's real tick, [`ControllerTick`]:
//! [`ControlLoop::step`] with its iceoryx2 ports and the executor (chunk timeline, rtc
//! transitions, ruckig, safety state machine) of the embedded demo robot, a robot that follows
//! the commands and a scripted chunk source (a test double of the policy, named as such) on
//! another thread over the same services and hand-off channels. [`SyntheticTick`] (a few hundred
//! flops) remains as the floor.

use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::Arc;
use std::time::{Duration, Instant};

use super::cyclictest::{self, CyclictestConfig};
use super::load::MatmulLoad;
use super::periodic::{run_periodic, PeriodicConfig, SyntheticTick, TickBody};
use super::{geomean, write_outputs, BenchError, BenchOpts, Outputs};
use crate::report::{fmt_us, LatencyRow, LatencyTable, Series};
use crate::scripted::{ScriptedChunkSource, ScriptedConfig};
use chunkrt_controller::control::Executor;
use chunkrt_controller::controller::{ControlLoop, Shared};
use chunkrt_controller::edge::Observation;
use chunkrt_controller::worker::{Delivery, InferenceWorker};
use chunkrt_ipc::services;
use chunkrt_ipc::JointState;

/// Makes a fresh tick body for each scenario, on the ticking thread.
pub type TickFactory = Arc<dyn Fn() -> Result<Box<dyn TickBody>, BenchError> + Send + Sync>;

impl TickBody for Box<dyn TickBody> {
    fn tick(&mut self, index: u64, deadline_ns: u64) {
        (**self).tick(index, deadline_ns)
    }

    fn report(&self) -> String {
        (**self).report()
    }
}

/// Options of one `control_loop` run.
pub struct Options {
    /// Output folder and quick mode.
    pub bench: BenchOpts,
    /// Control rates to measure (Hz).
    pub rates_hz: Vec<f64>,
    /// How long each scenario runs (60 s; quick 10 s; the test uses ~1 s).
    pub duration: Duration,
    /// How long cyclictest runs per scenario.
    pub cyclictest_duration: Duration,
    /// Core of the control thread (and cyclictest).
    pub control_core: usize,
    /// Core of the load generator.
    pub load_core: usize,
    /// Matmul size of the load.
    pub load_size: usize,
    /// SCHED_FIFO priority for the control thread and cyclictest (None: SCHED_OTHER).
    pub fifo_priority: Option<i32>,
    /// Run cyclictest when installed.
    pub cyclictest: bool,
    /// The tick body.
    pub tick: TickFactory,
}

impl Options {
    /// Defaults: 500 Hz and 1 kHz, 60 s per scenario (quick: 10 s), cyclictest a third of that
    /// (quick: the same), control on core 1, load on core 0, SCHED_FIFO 80, the executor tick.
    pub fn new(bench: BenchOpts) -> Self {
        let quick = bench.quick;
        let d = Duration::from_secs(if quick { 10 } else { 60 });
        Self {
            bench,
            rates_hz: vec![500.0, 1000.0],
            duration: d,
            cyclictest_duration: if quick { d } else { d / 3 },
            control_core: 1,
            load_core: 0,
            load_size: 256,
            fifo_priority: Some(80),
            cyclictest: true,
            // the robot/chunk thread on the load core, off the control core
            tick: Arc::new(|| Ok(Box::new(ControllerTick::new(Some(0))?) as Box<dyn TickBody>)),
        }
    }

    /// The same with the synthetic tick body (the floor of the harness itself).
    pub fn synthetic(mut self) -> Self {
        self.tick = Arc::new(|| Ok(Box::new(SyntheticTick::default())));
        self
    }
}

/// The controller's control tick as its control thread runs it: [`ControlLoop::step`] (joint
/// state received and validated over a real iceoryx2 service, the executor with chunk timeline,
/// rtc transitions, ruckig and safety state machine, the command published, the status every
/// status period) on the embedded demo robot (rtc, 50 Hz chunks of 50 actions, s = 25). A
/// thread of its own plays both other sides over the same services and hand-off: a robot that
/// follows every command exactly (publishing joint states every 250 µs) and a
/// [`ScriptedChunkSource`] (test double of the policy, 5 ms latency).
pub struct ControllerTick {
    _node: iceoryx2::prelude::Node<chunkrt_ipc::services::Ipc>,
    lp: ControlLoop,
    shared: Shared,
    exec: Executor,
    was_running: bool,
    stop: Arc<AtomicBool>,
    server: Option<std::thread::JoinHandle<()>>,
}

impl ControllerTick {
    /// Creates the ports on a namespace of its own and starts the robot/chunk thread, pinned to
    /// `helper_core` if given (the robot is another process on another core in a deployment;
    /// here it should not share the control thread's core). Call on the thread that will tick.
    pub fn new(helper_core: Option<usize>) -> Result<Self, BenchError> {
        static INSTANCE: std::sync::atomic::AtomicU64 = std::sync::atomic::AtomicU64::new(0);
        let err = |e: &dyn std::fmt::Display| BenchError::Thread(format!("controller tick: {e}"));
        let mut cfg = chunkrt_controller::config::Config::embedded_default();
        cfg.robot.namespace = format!(
            "chunkrt/bench-{}-{}",
            std::process::id(),
            INSTANCE.fetch_add(1, Ordering::Relaxed)
        );
        cfg.policy.action_rate_hz = 50.0;
        cfg.execution.execute_horizon = 25;
        cfg.execution.initial_delay_steps = 1;
        let node = services::node("chunkrt-bench-control").map_err(|e| err(&e))?;
        let lp = ControlLoop::new(&node, &cfg).map_err(|e| err(&e))?;
        let exec = Executor::new(&cfg).map_err(|e| err(&e))?;
        let link = exec.connect();
        let stop = Arc::new(AtomicBool::new(false));
        let stop2 = stop.clone();
        let (ready_tx, ready_rx) = crossbeam::channel::bounded(1);
        let server = std::thread::Builder::new()
            .name("bench-robot-chunks".into())
            .spawn(move || {
                if let Some(c) = helper_core {
                    let _ = chunkrt_controller::rt::pin_current_thread(c);
                }
                let ns = cfg.namespace();
                let ports = services::node("chunkrt-bench-robot").and_then(|node| {
                    let js = services::publisher(&services::joint_state_service(
                        &node,
                        &ns.joint_state(),
                    )?)?;
                    let cmd = services::subscriber(&services::joint_command_service(
                        &node,
                        &ns.joint_command(),
                    )?)?;
                    Ok((node, js, cmd))
                });
                let (_node, js_pub, cmd_sub) = match ports {
                    Ok(p) => {
                        let _ = ready_tx.send(Ok(()));
                        p
                    }
                    Err(e) => {
                        let _ = ready_tx.send(Err(e.to_string()));
                        return;
                    }
                };
                let mut js = JointState {
                    n_dof: cfg.n_dof() as u32,
                    ..Default::default()
                };
                for (i, j) in cfg.robot.joints.iter().enumerate() {
                    js.position[i] = j.initial_position;
                }
                let mut src = ScriptedChunkSource::new(ScriptedConfig::demo(5_000_000, 0.02));
                let mut worker = InferenceWorker::new(link, Delivery::AtReady);
                let obs = Observation::new(&cfg);
                while !stop2.load(Ordering::Relaxed) {
                    // the robot: follows the newest command exactly
                    while let Ok(Some(c)) = cmd_sub.receive() {
                        js.position = c.payload().position;
                    }
                    js.seq += 1;
                    js.measurement_time_ns = chunkrt_ipc::monotonic_ns();
                    let _ = js_pub.send_copy(js);
                    // the policy: scripted chunks through the controller's inference worker
                    worker.step(chunkrt_ipc::monotonic_ns(), &mut src, &obs);
                    std::thread::sleep(Duration::from_micros(250));
                }
            })
            .map_err(|e| err(&e))?;
        match ready_rx.recv_timeout(Duration::from_secs(10)) {
            Ok(Ok(())) => {}
            Ok(Err(e)) => return Err(err(&e)),
            Err(e) => return Err(err(&e)),
        }
        Ok(Self {
            _node: node,
            lp,
            shared: Shared::new(),
            exec,
            was_running: false,
            stop,
            server: Some(server),
        })
    }
}

impl Drop for ControllerTick {
    fn drop(&mut self) {
        self.stop.store(true, Ordering::Relaxed);
        if let Some(h) = self.server.take() {
            let _ = h.join();
        }
    }
}

impl TickBody for ControllerTick {
    fn tick(&mut self, _index: u64, deadline_ns: u64) {
        let wake = chunkrt_ipc::monotonic_ns();
        self.lp
            .step(deadline_ns, wake, &self.shared, &mut self.exec);
        self.was_running |= self.exec.state() == chunkrt_controller::control::State::Running;
    }

    fn report(&self) -> String {
        format!(
            "{} commands published, executor reached RUNNING: {}, ended {:?}",
            self.shared.commands.load(Ordering::Relaxed),
            if self.was_running { "yes" } else { "no" },
            self.exec.state()
        )
    }
}

/// One rate × load scenario.
#[derive(Debug, Clone)]
pub struct Scenario {
    /// e.g. `1000hz_loaded`.
    pub name: String,
    /// Rate (Hz).
    pub rate_hz: f64,
    /// With the matmul load.
    pub loaded: bool,
    /// Our wake-up lateness.
    pub lateness: LatencyRow,
    /// Our tick compute time.
    pub compute: LatencyRow,
    /// Ticks run.
    pub ticks: u64,
    /// Ticks whose work ended after the next deadline.
    pub overruns: u64,
    /// Deadlines skipped because a late tick passed them (every deadline is run or skipped).
    pub skipped: u64,
    /// cyclictest latency on the same core under the same load.
    pub cyclictest: Option<LatencyRow>,
    /// Load throughput (GFLOP/s) when loaded.
    pub load_gflops: Option<f64>,
    /// What the tick body said at the end (e.g. the executor's state and commands published).
    pub body: String,
}

/// What `control_loop` measured.
#[derive(Debug, Clone)]
pub struct Summary {
    /// Per scenario.
    pub scenarios: Vec<Scenario>,
    /// Scheduling policy the control thread got.
    pub policy: String,
    /// Whether the control thread was pinned.
    pub pinned: bool,
    /// Geometric mean over scenarios of our lateness p99 / cyclictest p99.
    pub p99_ratio: Option<f64>,
    /// Why cyclictest did not run, if it did not.
    pub cyclictest_note: String,
    /// The one-line summary printed last.
    pub line: String,
    /// Files written.
    pub outputs: Outputs,
}

/// Runs every scenario, prints the tables and the summary line, writes log, plot and table.
pub fn run(opts: &Options) -> Result<Summary, BenchError> {
    let started = Instant::now();
    let have_cyclictest = opts.cyclictest && cyclictest::available();
    let cyclictest_note = if !opts.cyclictest {
        "cyclictest disabled".to_string()
    } else if have_cyclictest {
        "cyclictest (rt-tests) on the same core, same load".to_string()
    } else {
        "cyclictest not installed (apt-get install rt-tests): no platform floor".to_string()
    };
    let load_threads = MatmulLoad::threads();
    let mut series = Vec::new();
    let mut scenarios = Vec::new();
    let (mut policy, mut pinned) = (String::new(), false);
    let mut notes = Vec::new();
    for &rate in &opts.rates_hz {
        if !(rate.is_finite() && rate > 0.0 && rate <= 20_000.0) {
            return Err(BenchError::Option(format!("rate {rate} Hz out of range")));
        }
        let period_ns = (1e9 / rate).round() as u64;
        for loaded in [false, true] {
            let name = format!(
                "{}hz_{}",
                rate as u64,
                if loaded { "loaded" } else { "idle" }
            );
            let load = if loaded {
                Some(MatmulLoad::start(Some(opts.load_core), opts.load_size)?)
            } else {
                None
            };
            if loaded {
                // Let the load reach steady state.
                std::thread::sleep(Duration::from_millis(200));
            }
            let cfg = PeriodicConfig {
                period_ns,
                duration_ns: opts.duration.as_nanos() as u64,
                core: Some(opts.control_core),
                fifo_priority: opts.fifo_priority,
            };
            let make = opts.tick.clone();
            let st = run_periodic(&cfg, move || make(), Arc::new(AtomicBool::new(false)))?;
            policy = st.policy.clone();
            pinned = st.pinned;
            let ct = if have_cyclictest {
                let ccfg = CyclictestConfig {
                    interval_us: period_ns / 1000,
                    loops: (opts.cyclictest_duration.as_secs_f64() * rate).max(1.0) as u64,
                    core: Some(opts.control_core),
                    priority: if st.policy.starts_with("SCHED_FIFO") {
                        opts.fifo_priority
                    } else {
                        None
                    },
                    hist_max_us: 20_000,
                };
                match cyclictest::run(&ccfg) {
                    Ok(r) => Some(r),
                    Err(e) => {
                        notes.push(format!("{name}: cyclictest failed: {e}"));
                        None
                    }
                }
            } else {
                None
            };
            let load_gflops = match load {
                Some(l) => Some(l.stop()?.gflops),
                None => None,
            };
            series.push(Series::new(format!("{name}_lateness"), st.lateness.clone()));
            series.push(Series::new(format!("{name}_compute"), st.compute.clone()));
            if let Some(c) = &ct {
                series.push(Series::new(format!("{name}_cyclictest"), c.latency.clone()));
            }
            scenarios.push(Scenario {
                name: name.clone(),
                rate_hz: rate,
                loaded,
                lateness: LatencyRow::from_hist(&format!("{name}_lateness"), &st.lateness),
                compute: LatencyRow::from_hist(&format!("{name}_compute"), &st.compute),
                ticks: st.ticks,
                overruns: st.overruns,
                skipped: st.skipped,
                cyclictest: ct
                    .as_ref()
                    .map(|c| LatencyRow::from_hist(&format!("{name}_cyclictest"), &c.latency)),
                load_gflops,
                body: st.body.clone(),
            });
        }
    }

    let table = LatencyTable::from_series(
        format!(
            "control_loop: wake-up lateness and tick compute, {:.0} s per scenario, control thread \
             on core {} ({policy}{}), load = {}x{} f32 candle matmuls on core {} ({} candle \
             thread{}); {cyclictest_note}",
            opts.duration.as_secs_f64(),
            opts.control_core,
            if pinned { ", pinned" } else { ", not pinned" },
            opts.load_size,
            opts.load_size,
            opts.load_core,
            load_threads,
            if load_threads == 1 { "" } else { "s: set RAYON_NUM_THREADS=1 to confine it" },
        ),
        &series,
    );
    println!("{table}");
    println!(
        "{:<14} {:>8} {:>9} {:>12} {:>12} {:>12} {:>10} {:>8}",
        "scenario",
        "ticks",
        "overruns",
        "late p99 µs",
        "cyc p99 µs",
        "ours/cyc",
        "comp p99",
        "GFLOP/s"
    );
    let mut ratios = Vec::new();
    for s in &scenarios {
        let (cyc, ratio) = match &s.cyclictest {
            Some(c) => {
                let r = s.lateness.p99_ns as f64 / c.p99_ns.max(1) as f64;
                ratios.push(r);
                (fmt_us(c.p99_ns), format!("{r:.2}x"))
            }
            None => ("-".into(), "-".into()),
        };
        println!(
            "{:<14} {:>8} {:>9} {:>12} {:>12} {:>12} {:>10} {:>8}",
            s.name,
            s.ticks,
            s.overruns,
            fmt_us(s.lateness.p99_ns),
            cyc,
            ratio,
            fmt_us(s.compute.p99_ns),
            s.load_gflops
                .map(|g| format!("{g:.1}"))
                .unwrap_or("-".into())
        );
    }
    for n in &notes {
        println!("note: {n}");
    }
    let p99_ratio = if ratios.is_empty() {
        None
    } else {
        Some(geomean(&ratios))
    };
    let overruns: u64 = scenarios.iter().map(|s| s.overruns).sum();
    let ticks: u64 = scenarios.iter().map(|s| s.ticks).sum();
    let worst = scenarios
        .iter()
        .max_by_key(|s| s.lateness.p99_ns)
        .map(|s| format!("{} lateness p99 {} µs", s.name, fmt_us(s.lateness.p99_ns)))
        .unwrap_or_default();
    let line = match p99_ratio {
        Some(r) => format!(
            "control_loop: lateness p99 / cyclictest p99 = {r:.2}x (geomean over {} scenarios); \
             worst {worst}; overruns {overruns} of {ticks} ticks",
            ratios.len()
        ),
        None => format!(
            "control_loop: no cyclictest ratio ({cyclictest_note}); worst {worst}; overruns \
             {overruns} of {ticks} ticks"
        ),
    };
    let lateness_names: Vec<String> = series
        .iter()
        .filter(|s| !s.name.ends_with("_compute"))
        .map(|s| s.name.clone())
        .collect();
    let compute_names: Vec<String> = series
        .iter()
        .filter(|s| s.name.ends_with("_compute"))
        .map(|s| s.name.clone())
        .collect();
    let outputs = write_outputs(
        &opts.bench.out_dir,
        "control_loop",
        &table,
        &series,
        &[
            (
                "control_loop",
                "control thread wake-up lateness vs cyclictest",
                lateness_names,
            ),
            (
                "control_loop_compute",
                "control tick compute time",
                compute_names,
            ),
        ],
        started.elapsed(),
        &format!("chunkrt control_loop on {}", super::machine_line()),
    )?;
    println!("{outputs}");
    println!("{line}");
    Ok(Summary {
        scenarios,
        policy,
        pinned,
        p99_ratio,
        cyclictest_note,
        line,
        outputs,
    })
}
