//! `chunkrt demo`: the whole system on the reach task. The simulated robot, the fake camera
//! (rendering the arm and two targets from the robot's joint states) and the controller (with
//! the trained π0.5) run as separate processes over real iceoryx2 services. One episode per
//! prompt: the controller is started with the prompt, a live status line shows its state, chunk
//! latency, tick p99 and the distance to the prompted target, and the episode ends on reaching
//! the target (or at the time limit). Then a report: success, time to target, latency
//! percentiles, and a PNG of the joint trajectories with chunk boundaries marked.
//!
//! With `policy.kind = "hold"` (or a configuration that is not the reach task) the processes
//! simply run for `--duration` and the summary shows what the controller did. With the SO-101's
//! configuration (`config/so101.toml`) the robot is the MuJoCo arm ([`so101`]).

use std::fs::File;
use std::io::Write;
use std::path::{Path, PathBuf};
use std::process::{Child, Command, Stdio};
use std::time::{Duration, Instant};

use anyhow::Context;

use chunkrt_ipc::services;
use chunkrt_ipc::{
    controller_state_name, ControllerStatus, JointCommand, JointState, RejectReason,
};

use crate::report::{fmt_us, latency_histogram};
use chunkrt_learn::task::{ReachScene, TargetColor, REACH_TOLERANCE};

mod franka;
mod ros2;
pub mod so101;

/// `chunkrt demo`.
#[derive(Debug, clap::Args)]
pub struct DemoArgs {
    /// The processes: configuration, scene, namespace, logs, remote policy.
    #[command(flatten)]
    pub stack: StackArgs,
    /// Seconds to run without a task policy (Ctrl-C stops earlier).
    #[arg(long, default_value_t = 6.0)]
    pub duration: f64,
    /// Prompts, one episode each (comma separated).
    #[arg(
        long,
        value_delimiter = ',',
        default_value = "reach the red target,reach the blue target"
    )]
    pub prompts: Vec<String>,
    /// Time limit of an episode (s).
    #[arg(long, default_value_t = 10.0)]
    pub episode_seconds: f64,
    /// SO-101 episodes (`--config config/so101.toml`), seeds `--seed` onwards: where the
    /// package puts the block and the goal.
    #[arg(long, default_value_t = 3)]
    pub episodes: usize,
    /// Where the report (demo.md) and plot (demo.png) go.
    #[arg(long, default_value = "target/chunkrt-demo")]
    pub out: PathBuf,
}

/// What `chunkrt demo` and `chunkrt soak` share: the stack of processes they start.
#[derive(Debug, Clone, clap::Args)]
pub struct StackArgs {
    /// Configuration file (default: the embedded demo robot and its reach policy).
    #[arg(long)]
    pub config: Option<PathBuf>,
    /// Scene seed of the reach task's camera: where the two targets are.
    #[arg(long, default_value_t = 7)]
    pub seed: u64,
    /// Service namespace (default: `<robot.namespace>-<tag>-<pid>`, so the stack never collides
    /// with another running chunkrt).
    #[arg(long)]
    pub namespace: Option<String>,
    /// Where the processes' logs go (default: a temporary folder).
    #[arg(long)]
    pub log_dir: Option<PathBuf>,
    /// Take the chunks from an openpi-protocol server at this `ws://host:port` (e.g. `chunkrt
    /// serve --checkpoint models/reach_pi05` on a GPU machine) instead of running the policy in
    /// the controller (`chunkrt run --remote`).
    #[arg(long, value_name = "URL")]
    pub remote: Option<String>,
    /// Record the run into this Rerun file (`chunkrt record`: a process of its own; needs
    /// `bash scripts/rerun-env.sh`; open it with `rerun FILE`).
    #[arg(long, value_name = "FILE")]
    pub record: Option<PathBuf>,
}

/// A prepared stack: its configuration (in its own namespace), the executable, where the logs
/// go, and the arguments every process gets.
pub(crate) struct Stack {
    pub(crate) cfg: chunkrt_controller::config::Config,
    pub(crate) ns: String,
    pub(crate) exe: PathBuf,
    pub(crate) log_dir: PathBuf,
    /// Whether the configuration runs the reach task (a camera and a policy).
    pub(crate) task: bool,
    common: Vec<String>,
    seed: u64,
    remote: Option<String>,
    record: Option<PathBuf>,
}

impl StackArgs {
    /// Loads the configuration into a namespace of its own (`tag` in its default name) and
    /// makes the log folder; `exe` replaces this binary for the processes.
    pub(crate) fn prepare(&self, tag: &str, exe: Option<&PathBuf>) -> anyhow::Result<Stack> {
        let base = crate::args::load_config(self.config.as_ref(), None)?;
        let ns = self
            .namespace
            .clone()
            .unwrap_or_else(|| format!("{}-{tag}-{}", base.robot.namespace, std::process::id()));
        let cfg = crate::args::load_config(self.config.as_ref(), Some(&ns))?;
        let exe = match exe {
            Some(p) => p.clone(),
            None => std::env::current_exe().context("cannot find the chunkrt executable")?,
        };
        let log_dir = self.log_dir.clone().unwrap_or_else(|| {
            std::env::temp_dir().join(format!("chunkrt-{tag}-{}", std::process::id()))
        });
        std::fs::create_dir_all(&log_dir)
            .with_context(|| format!("cannot create {}", log_dir.display()))?;
        let task = chunkrt_learn::task::task_camera(&cfg).is_ok() && cfg.policy.kind.is_some();
        let mut common = vec!["--namespace".to_string(), ns.clone()];
        if let Some(c) = &self.config {
            common.extend(["--config".to_string(), c.display().to_string()]);
        }
        Ok(Stack {
            cfg,
            ns,
            exe,
            log_dir,
            task,
            common,
            seed: self.seed,
            remote: self.remote.clone(),
            record: self.record.clone(),
        })
    }
}

impl Stack {
    /// The arguments of subcommand `sub` (namespace and configuration).
    pub(crate) fn args(&self, sub: &str) -> Vec<String> {
        let mut v = vec![sub.to_string()];
        v.extend(self.common.iter().cloned());
        v
    }

    /// The camera's arguments: the reach scene of the seed when the task runs.
    pub(crate) fn camera_args(&self) -> Vec<String> {
        let mut v = self.args("fake-camera");
        if self.task {
            v.extend([
                "--scene".into(),
                "reach".into(),
                "--scene-seed".into(),
                self.seed.to_string(),
            ]);
        }
        v
    }

    /// The controller's arguments (no periodic log; the remote policy when one is given).
    pub(crate) fn run_args(&self) -> Vec<String> {
        let mut v = self.args("run");
        v.extend(["--log-every".into(), "0".into()]);
        if let Some(url) = &self.remote {
            v.extend(["--remote".into(), url.clone()]);
        }
        v
    }

    /// The scene seed.
    pub(crate) fn seed(&self) -> u64 {
        self.seed
    }

    /// The recorder (`--record FILE`), started before the controller so that it sees the run
    /// from its first command; None without `--record`.
    pub(crate) fn spawn_recorder(&self, prompt: &str) -> anyhow::Result<Option<Proc>> {
        let Some(out) = &self.record else {
            return Ok(None);
        };
        let cameras: Vec<String> = self.cfg.cameras.iter().map(|c| c.name.clone()).collect();
        let mut extra = vec!["--prompt".to_string(), prompt.to_string()];
        if let Some(i) = self.common.iter().position(|a| a == "--config") {
            extra.extend(["--config".into(), self.common[i + 1].clone()]);
        }
        extra.extend([
            "--property".into(),
            format!("chunkrt={}", env!("CARGO_PKG_VERSION")),
            "--property".into(),
            format!("robot={}", self.cfg.robot.name),
            "--property".into(),
            format!("policy={}", self.cfg.policy.kind_name()),
        ]);
        let log = self.log_dir.join("recorder.log");
        let file =
            File::create(&log).with_context(|| format!("cannot create {}", log.display()))?;
        let child = crate::record::recorder_command(&self.ns, out, &cameras, &extra)?
            .stdout(file.try_clone()?)
            .stderr(file)
            .spawn()
            .context("cannot start the recorder")?;
        let mut p = Proc {
            name: "recorder",
            child,
            log,
        };
        // the run starts once the recorder has subscribed (its first line; importing rerun
        // takes about a second), so that it sees the controller's first chunks
        let t0 = Instant::now();
        loop {
            let text = std::fs::read_to_string(&p.log).unwrap_or_default();
            if text.contains("chunkrt_record: recording") {
                break;
            }
            if !matches!(p.child.try_wait(), Ok(None)) || t0.elapsed() > Duration::from_secs(30) {
                let _ = stop(&mut p, Duration::from_secs(1));
                anyhow::bail!(
                    "the recorder did not start; its log {}:\n{}",
                    p.log.display(),
                    text.trim()
                );
            }
            std::thread::sleep(Duration::from_millis(50));
        }
        println!(
            "recording into {} (recorder log {})",
            out.display(),
            p.log.display()
        );
        Ok(Some(p))
    }
}

pub(crate) struct Proc {
    pub(crate) name: &'static str,
    pub(crate) child: Child,
    pub(crate) log: PathBuf,
}

pub(crate) fn spawn(
    exe: &Path,
    name: &'static str,
    args: &[String],
    log_dir: &Path,
) -> anyhow::Result<Proc> {
    let log = log_dir.join(format!("{name}.log"));
    let out = File::create(&log).with_context(|| format!("cannot create {}", log.display()))?;
    let err = out.try_clone()?;
    let child = Command::new(exe)
        .args(args)
        .stdin(Stdio::null())
        .stdout(out)
        .stderr(err)
        .spawn()
        .with_context(|| format!("cannot start {name} ({})", exe.display()))?;
    Ok(Proc { name, child, log })
}

pub(crate) fn stop(p: &mut Proc, timeout: Duration) -> String {
    // SIGINT first: every chunkrt process stops cleanly on it and prints its summary
    // SAFETY: plain kill(2) on our own child's pid.
    unsafe { libc::kill(p.child.id() as libc::pid_t, libc::SIGINT) };
    let t0 = Instant::now();
    loop {
        match p.child.try_wait() {
            Ok(Some(st)) => {
                return if st.success() {
                    "exited cleanly".into()
                } else {
                    format!("exited with {st}")
                }
            }
            Ok(None) if t0.elapsed() < timeout => std::thread::sleep(Duration::from_millis(20)),
            _ => {
                let _ = p.child.kill();
                let _ = p.child.wait();
                return "killed after timeout".into();
            }
        }
    }
}

/// One episode as the demo saw it over IPC.
#[derive(Debug, Clone, Default)]
pub struct EpisodeReport {
    pub prompt: String,
    /// The end effector reached the prompted target.
    pub success: bool,
    /// From the first command sampled from a chunk to reaching the target (s).
    pub time_to_target: Option<f64>,
    /// When the target was reached, since the controller started (s).
    pub reached_at: Option<f64>,
    /// Closest approach to the prompted target (m).
    pub min_distance: f64,
    /// Per-chunk inference latency (observation → chunk ready), as the status reports it (ns).
    pub chunk_latency_ns: Vec<u64>,
    /// The controller's last status (tick quantiles, overruns, hold entries, ...).
    pub status: ControllerStatus,
    /// Time since the episode started (s) and joint positions.
    pub trajectory: Vec<(f64, Vec<f64>)>,
    /// Times (s) the command switched to a new chunk.
    pub switches: Vec<f64>,
    /// How the controller process ended.
    pub controller_exit: String,
}

struct Ports {
    status: iceoryx2::port::subscriber::Subscriber<services::Ipc, ControllerStatus, ()>,
    js: iceoryx2::port::subscriber::Subscriber<services::Ipc, JointState, ()>,
    cmd: iceoryx2::port::subscriber::Subscriber<services::Ipc, JointCommand, ()>,
}

fn live(line: &str, tty: bool, last: &mut f64, now: f64) {
    if tty {
        print!("\r{line}\x1b[K");
        let _ = std::io::stdout().flush();
    } else if now - *last >= 1.0 {
        println!("{line}");
        *last = now;
    }
}

/// Runs one episode: starts the controller with `prompt`, follows it until the target is
/// reached (plus a short settle) or `limit_s`, stops it.
#[allow(clippy::too_many_arguments)]
fn episode(
    exe: &Path,
    run_args: &[String],
    log_dir: &Path,
    ports: &Ports,
    scene: Option<&ReachScene>,
    prompt: &str,
    limit_s: f64,
    label: &str,
    stop_flag: &std::sync::atomic::AtomicBool,
) -> anyhow::Result<EpisodeReport> {
    let mut args = run_args.to_vec();
    args.extend(["--prompt".to_string(), prompt.to_string()]);
    let mut ctl = spawn(exe, "controller", &args, log_dir)?;
    let color = TargetColor::from_prompt(prompt);
    let t0 = Instant::now();
    let tty = std::io::IsTerminal::is_terminal(&std::io::stdout());
    let mut rep = EpisodeReport {
        prompt: prompt.to_string(),
        min_distance: f64::INFINITY,
        ..Default::default()
    };
    let mut js = JointState::default();
    let mut last_chunk = 0u64;
    let mut last_chunks_count = 0u64;
    let mut motion_start: Option<f64> = None;
    let mut settle_until: Option<f64> = None;
    let mut last_line = -1.0;
    let mut dist = f64::NAN;
    loop {
        std::thread::sleep(Duration::from_millis(2));
        let now = t0.elapsed().as_secs_f64();
        while let Ok(Some(s)) = ports.status.receive() {
            let st = *s.payload();
            if st.chunks > last_chunks_count && st.last_inference_latency_ns > 0 {
                rep.chunk_latency_ns.push(st.last_inference_latency_ns);
            }
            last_chunks_count = st.chunks;
            rep.status = st;
        }
        while let Ok(Some(s)) = ports.cmd.receive() {
            let c = s.payload();
            if c.chunk_id != 0 && c.chunk_id != last_chunk {
                if last_chunk != 0 {
                    rep.switches.push(now);
                }
                last_chunk = c.chunk_id;
                motion_start.get_or_insert(now);
            }
        }
        let mut fresh = false;
        while let Ok(Some(s)) = ports.js.receive() {
            js = *s.payload();
            fresh = true;
        }
        let n = (js.n_dof as usize).min(chunkrt_ipc::MAX_DOF);
        if fresh && n > 0 {
            let q = js.position[..n].to_vec();
            if let (Some(sc), Some(c)) = (scene, color) {
                dist = sc.distance(&q, c);
                rep.min_distance = rep.min_distance.min(dist);
                if dist <= REACH_TOLERANCE && !rep.success {
                    rep.success = true;
                    rep.time_to_target = Some(now - motion_start.unwrap_or(now));
                    rep.reached_at = Some(now);
                    settle_until = Some(now + 0.8);
                }
            }
            if rep.trajectory.last().is_none_or(|(t, _)| now - t >= 0.01) {
                rep.trajectory.push((now, q));
            }
        }
        let st = &rep.status;
        let line = format!(
            "[{label} {now:>4.1}s] {:<8} chunks {:>3}  chunk latency {:>5.1} ms  tick p99 {:>6} us  lateness p99 {:>6} us  distance to {} {:.3} m{}",
            controller_state_name(st.state),
            st.chunks,
            st.last_inference_latency_ns as f64 / 1e6,
            fmt_us(st.compute_p99_ns),
            fmt_us(st.lateness_p99_ns),
            color.map(|c| c.name()).unwrap_or("target"),
            dist,
            if rep.success { "  REACHED" } else { "" }
        );
        live(&line, tty, &mut last_line, now);
        if !matches!(ctl.child.try_wait(), Ok(None)) {
            rep.controller_exit = stop(&mut ctl, Duration::from_secs(1));
            anyhow::bail!(
                "the controller exited early ({}); its log: {}\n{}",
                rep.controller_exit,
                ctl.log.display(),
                std::fs::read_to_string(&ctl.log).unwrap_or_default()
            );
        }
        if settle_until.is_some_and(|t| now >= t)
            || now >= limit_s
            || stop_flag.load(std::sync::atomic::Ordering::Relaxed)
        {
            break;
        }
    }
    if tty {
        println!();
    }
    rep.controller_exit = stop(&mut ctl, Duration::from_secs(5));
    Ok(rep)
}

/// Joint trajectories of every episode, one panel each, with chunk switches as thin vertical
/// lines and the moment the target was reached as a thick one.
pub fn plot_episodes(path: &Path, joints: &[String], eps: &[EpisodeReport]) -> anyhow::Result<()> {
    use plotters::prelude::*;
    if let Some(d) = path.parent() {
        std::fs::create_dir_all(d)?;
    }
    let err = |e: &dyn std::fmt::Display| anyhow::anyhow!("plot {}: {e}", path.display());
    let h = 300 * eps.len().max(1) as u32;
    let root = BitMapBackend::new(path, (1000, h)).into_drawing_area();
    root.fill(&WHITE).map_err(|e| err(&e))?;
    let panels = root.split_evenly((eps.len().max(1), 1));
    for (ep, area) in eps.iter().zip(panels.iter()) {
        let t_end = ep.trajectory.last().map(|p| p.0).unwrap_or(1.0).max(0.5);
        let (lo, hi) = ep
            .trajectory
            .iter()
            .flat_map(|(_, q)| q.iter().copied())
            .fold((f64::MAX, f64::MIN), |(a, b), v| (a.min(v), b.max(v)));
        let (lo, hi) = if lo <= hi {
            (lo - 0.2, hi + 0.2)
        } else {
            (-1.0, 1.0)
        };
        let title = format!(
            "\"{}\": {}",
            ep.prompt,
            match ep.time_to_target {
                Some(t) if ep.success => format!("reached in {t:.2} s"),
                _ => format!("not reached (closest {:.3} m)", ep.min_distance),
            }
        );
        let mut chart = ChartBuilder::on(area)
            .caption(title, ("sans-serif", 18))
            .margin(10)
            .x_label_area_size(35)
            .y_label_area_size(50)
            .build_cartesian_2d(0f64..t_end, lo..hi)
            .map_err(|e| err(&e))?;
        chart
            .configure_mesh()
            .x_desc("time since the controller started (s)")
            .y_desc("position (rad / gripper 0..1)")
            .draw()
            .map_err(|e| err(&e))?;
        chart
            .draw_series(ep.switches.iter().map(|&t| {
                PathElement::new(vec![(t, lo), (t, hi)], BLACK.mix(0.25).stroke_width(1))
            }))
            .map_err(|e| err(&e))?
            .label("chunk switch")
            .legend(|(x, y)| PathElement::new(vec![(x, y), (x + 20, y)], BLACK.mix(0.25)));
        let n = ep.trajectory.first().map(|p| p.1.len()).unwrap_or(0);
        for j in 0..n {
            let color = Palette99::pick(j).to_rgba();
            let name = joints
                .get(j)
                .cloned()
                .unwrap_or_else(|| format!("joint {j}"));
            chart
                .draw_series(LineSeries::new(
                    ep.trajectory.iter().map(|(t, q)| (*t, q[j])),
                    color.stroke_width(2),
                ))
                .map_err(|e| err(&e))?
                .label(name)
                .legend(move |(x, y)| {
                    PathElement::new(vec![(x, y), (x + 20, y)], color.stroke_width(2))
                });
        }
        if let Some(t) = ep.reached_at {
            chart
                .draw_series(std::iter::once(PathElement::new(
                    vec![(t, lo), (t, hi)],
                    GREEN.mix(0.8).stroke_width(3),
                )))
                .map_err(|e| err(&e))?
                .label("target reached")
                .legend(|(x, y)| {
                    PathElement::new(vec![(x, y), (x + 20, y)], GREEN.stroke_width(3))
                });
        }
        chart
            .configure_series_labels()
            .position(SeriesLabelPosition::UpperRight)
            .background_style(WHITE.mix(0.85))
            .border_style(BLACK)
            .label_font(("sans-serif", 13))
            .draw()
            .map_err(|e| err(&e))?;
    }
    root.present().map_err(|e| err(&e))?;
    Ok(())
}

fn quantiles_line(name: &str, values: &[u64]) -> String {
    let mut h = latency_histogram();
    for &v in values {
        let _ = h.record(v.max(1));
    }
    if h.is_empty() {
        return format!("{name}: no samples");
    }
    let ms = |v: u64| v as f64 / 1e6;
    format!(
        "{name}: n {}  p50 {:.1} ms  p99 {:.1} ms  max {:.1} ms",
        h.len(),
        ms(h.value_at_quantile(0.5)),
        ms(h.value_at_quantile(0.99)),
        ms(h.max())
    )
}

/// Runs the demo.
pub fn run(args: DemoArgs) -> anyhow::Result<()> {
    let stack = args.stack.prepare("demo", None)?;
    if so101::is_so101(&stack.cfg) {
        return so101::run(&args, &stack);
    }
    if franka::is_franka(&stack.cfg) {
        return franka::run(&args, &stack);
    }
    let stop_flag = chunkrt_tools::shutdown::flag();
    let (cfg, ns, exe, log_dir, task) = (
        &stack.cfg,
        &stack.ns,
        &stack.exe,
        &stack.log_dir,
        stack.task,
    );
    let scene = task.then(|| ReachScene::from_seed(stack.seed()));
    println!(
        "chunkrt demo: robot '{}' ({} joints), {} camera(s), policy '{}', namespace '{ns}', logs in {}",
        cfg.robot.name,
        cfg.n_dof(),
        cfg.cameras.len(),
        cfg.policy.kind_name(),
        log_dir.display()
    );
    if let Some(sc) = &scene {
        println!(
            "scene {}: red target at ({:+.2}, {:+.2}) m, blue target at ({:+.2}, {:+.2}) m",
            stack.seed(),
            sc.targets[0][0],
            sc.targets[0][1],
            sc.targets[1][0],
            sc.targets[1][1]
        );
    }
    // a configuration with [ros2]: a ros2_control robot over ROS 2 (peer and bridge)
    let mut procs = if ros2::is_ros2(&stack) {
        ros2::spawn_robot(&stack)?
    } else {
        vec![spawn(
            exe,
            "fake-robot",
            &stack.args("fake-robot"),
            log_dir,
        )?]
    };
    procs.push(spawn(exe, "fake-camera", &stack.camera_args(), log_dir)?);
    // stopped last (the list is stopped from its end): it records the controller's end too
    let prompt_all = args.prompts.join(" | ");
    if let Some(r) = stack.spawn_recorder(&prompt_all)? {
        procs.insert(0, r);
    }
    let node = services::node(&format!("chunkrt-demo-{}", std::process::id()))?;
    let nsp = cfg.namespace();
    let ports = Ports {
        status: services::subscriber(&services::status_service(&node, &nsp.status())?)?,
        js: services::subscriber(&services::joint_state_service(&node, &nsp.joint_state())?)?,
        cmd: services::subscriber(&services::joint_command_service(
            &node,
            &nsp.joint_command(),
        )?)?,
    };
    let run_args = stack.run_args();
    let started = Instant::now();
    let prompts: Vec<String> = if task {
        args.prompts.clone()
    } else {
        vec![cfg.policy.prompt.clone()]
    };
    let limit = if task {
        args.episode_seconds
    } else {
        args.duration
    };
    let mut reports = Vec::new();
    let mut failure = None;
    for (i, p) in prompts.iter().enumerate() {
        if stop_flag.load(std::sync::atomic::Ordering::Relaxed) {
            break;
        }
        if task {
            println!("-- episode {}/{}: \"{p}\"", i + 1, prompts.len());
        }
        let label = format!("{}/{}", i + 1, prompts.len());
        match episode(
            exe,
            &run_args,
            log_dir,
            &ports,
            scene.as_ref(),
            p,
            limit,
            &label,
            stop_flag,
        ) {
            Ok(r) => reports.push(r),
            Err(e) => {
                failure = Some(e);
                break;
            }
        }
        if let Some(p) = procs
            .iter_mut()
            .find_map(|p| (!matches!(p.child.try_wait(), Ok(None))).then_some(p.name))
        {
            failure = Some(anyhow::anyhow!("{p} exited early; see its log"));
            break;
        }
    }
    let mut outcomes = Vec::new();
    for p in procs.iter_mut().rev() {
        let how = stop(p, Duration::from_secs(5));
        outcomes.push((p.name, how, p.log.clone()));
    }
    println!("\n== summary ({:.1} s) ==", started.elapsed().as_secs_f64());
    for (name, how, log) in &outcomes {
        println!("-- {name}: {how}");
        let text = std::fs::read_to_string(log).unwrap_or_default();
        for line in text.lines().filter(|l| {
            !l.contains(" INFO ") || l.contains("summary") || l.contains("control thread")
        }) {
            println!("   {line}");
        }
    }
    let mut md = String::from(
        "| episode | prompt | result | time to target | chunks | chunk latency | tick p50 / p99 / max (µs) | lateness p99 (µs) | overruns | hold entries |\n\
         |---:|---|---|---:|---:|---|---|---:|---:|---:|\n",
    );
    let mut all_latency = Vec::new();
    for (i, r) in reports.iter().enumerate() {
        let st = &r.status;
        let lat = quantiles_line("", &r.chunk_latency_ns);
        all_latency.extend_from_slice(&r.chunk_latency_ns);
        let result = if !task {
            controller_state_name(st.state).to_string()
        } else if r.success {
            "reached".to_string()
        } else {
            format!("not reached ({:.3} m)", r.min_distance)
        };
        md.push_str(&format!(
            "| {} | {} | {} | {} | {} | {} | {} / {} / {} | {} | {} | {} |\n",
            i + 1,
            r.prompt,
            result,
            r.time_to_target
                .map(|t| format!("{t:.2} s"))
                .unwrap_or_else(|| "-".into()),
            st.chunks,
            lat.trim_start_matches(": "),
            fmt_us(st.compute_p50_ns),
            fmt_us(st.compute_p99_ns),
            fmt_us(st.compute_max_ns),
            fmt_us(st.lateness_p99_ns),
            st.overruns,
            st.hold_entries
        ));
        let rejected: u64 = st.rejected.iter().sum();
        if rejected > 0 {
            println!(
                "episode {}: rejected inputs: {}",
                i + 1,
                RejectReason::ALL
                    .iter()
                    .map(|r| format!("{}={}", r.name(), st.rejected[r.code()]))
                    .collect::<Vec<_>>()
                    .join(" ")
            );
        }
    }
    println!("\n{md}");
    println!(
        "{}",
        quantiles_line("chunk latency (all episodes)", &all_latency)
    );
    if task && !reports.is_empty() {
        let ok = reports.iter().filter(|r| r.success).count();
        println!("success: {ok}/{} episodes", reports.len());
    }
    std::fs::create_dir_all(&args.out)
        .with_context(|| format!("cannot create {}", args.out.display()))?;
    std::fs::write(args.out.join("demo.md"), &md)?;
    let png = args.out.join("demo.png");
    let names: Vec<String> = cfg.robot.joints.iter().map(|j| j.name.clone()).collect();
    match plot_episodes(&png, &names, &reports) {
        Ok(()) => println!(
            "report: {}  plot: {}",
            args.out.join("demo.md").display(),
            png.display()
        ),
        Err(e) => println!("no plot: {}", chunkrt_bench::report::plot_error_text(&e)),
    }
    // with --record, the recording's own plot and tracking table beside the demo's
    if let Some(rrd) = &args.stack.record {
        let (png, md) = (
            args.out.join("recording.png"),
            args.out.join("recording.md"),
        );
        if let Err(e) = crate::record::report(rrd, Some(&png), Some(&md)) {
            println!("no report from the recording {}: {e:#}", rrd.display());
        }
    }
    if let Some(e) = failure {
        return Err(e);
    }
    Ok(())
}
