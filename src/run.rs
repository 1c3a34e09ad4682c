//! `chunkrt run`: the composition root. Loads the configuration, builds the executor and the
//! chunk source it names (the policy, or [`HoldSource`]), and hands both to the controller.

use std::path::PathBuf;
use std::sync::atomic::Ordering;
use std::time::Duration;

use anyhow::Context;

use chunkrt_bench::scripted::ScriptedChunkSource;
use chunkrt_controller::config::{Config, DeviceSpec, ModelKind, PolicySource};
use chunkrt_controller::control::Executor;
use chunkrt_controller::controller::{
    frames_per_camera, print_summary, status_line, ChunkSource, Controller, HoldSource, Shared,
};

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
    #[arg(long, value_parser = ["hold", "pi0", "pi05"])]
    pub policy: Option<String>,
    /// Override `policy.device`: cpu, cuda or cuda:N (a GPU needs a build with `--features cuda`).
    #[arg(long)]
    pub device: Option<DeviceSpec>,
    /// Take the chunks from an openpi-protocol server (`chunkrt serve`, openpi's
    /// `serve_policy.py`, SGLang, vLLM-Omni) at this `ws://host:port[/path]` instead of running
    /// the policy here (sets `policy.source = "remote"` and `policy.url`).
    #[arg(long, value_name = "URL")]
    pub remote: Option<String>,
    /// Take the chunks from the scripted test double (`policy.source = "scripted"`, no model):
    /// smooth motions around the initial pose landing this many ms after their observation.
    #[arg(long, value_name = "LATENCY_MS", conflicts_with_all = ["remote", "checkpoint"])]
    pub scripted: Option<f64>,
    /// Run this checkpoint (chunkrt's, openpi's converted to PyTorch, or LeRobot's pi0 / pi05
    /// directory as shipped) instead of `policy.checkpoint`; the kind is the checkpoint's
    /// unless `--policy` says otherwise. `chunkrt inspect DIR` shows what it finds there.
    #[arg(long, value_name = "DIR", conflicts_with = "remote")]
    pub checkpoint: Option<PathBuf>,
    #[command(flatten)]
    pub files: crate::args::LayoutArgs,
    /// Print the effective configuration (TOML, each value marked file, default or flag) and
    /// exit without starting anything.
    #[arg(long)]
    pub print_config: bool,
}

pub use crate::args::load_config;

/// The chunk source the configuration names, loaded on a thread of its own so that SIGINT /
/// SIGTERM during a long load (a large checkpoint, a server that does not answer) stops the
/// command at once (`None`) instead of when the load ends.
pub fn load_source(
    cfg: &Config,
    stop: &std::sync::atomic::AtomicBool,
) -> anyhow::Result<Option<Box<dyn ChunkSource>>> {
    if cfg.policy.source == PolicySource::Scripted {
        return Ok(Some(Box::new(ScriptedChunkSource::for_robot(cfg))));
    }
    if cfg.policy.kind.is_none() {
        return Ok(Some(Box::new(HoldSource)));
    }
    let (tx, rx) = crossbeam::channel::bounded(1);
    let c = cfg.clone();
    std::thread::Builder::new()
        .name("chunkrt-load".into())
        .spawn(move || {
            let source: anyhow::Result<Box<dyn ChunkSource>> =
                match c.policy.source {
                    PolicySource::Local => chunkrt_controller::inference::PolicySource::load(&c)
                        .map(|s| Box::new(s) as _),
                    PolicySource::Remote => chunkrt_controller::remote::RemoteSource::connect(&c)
                        .map(|s| Box::new(s) as _),
                    PolicySource::Scripted => Ok(Box::new(ScriptedChunkSource::for_robot(&c)) as _),
                };
            let _ = tx.send(source);
        })
        .context("cannot start the loading thread")?;
    loop {
        match rx.recv_timeout(Duration::from_millis(50)) {
            Ok(source) => return source.map(Some),
            Err(crossbeam::channel::RecvTimeoutError::Timeout) => {
                if stop.load(Ordering::Relaxed) {
                    // the loading thread is left behind: the process ends with this command
                    return Ok(None);
                }
            }
            Err(crossbeam::channel::RecvTimeoutError::Disconnected) => {
                anyhow::bail!("the loading thread panicked")
            }
        }
    }
}

/// `chunkrt run`: the controller until SIGINT / SIGTERM or `--duration`.
pub fn run(args: RunArgs) -> anyhow::Result<()> {
    let mut cfg = load_config(args.config.as_ref(), args.namespace.as_deref())?;
    if let Some(p) = &args.prompt {
        cfg.policy.prompt = p.clone();
    }
    if let Some(k) = &args.policy {
        cfg.policy.kind = match k.as_str() {
            "pi0" => Some(ModelKind::Pi0),
            "pi05" => Some(ModelKind::Pi05),
            _ => None,
        };
    }
    if let Some(d) = args.device {
        cfg.policy.device = d;
    }
    args.files.apply(&mut cfg.policy)?;
    if let Some(dir) = &args.checkpoint {
        let dir = std::path::absolute(dir)?;
        if args.policy.is_none() {
            let opts = cfg.policy.load_options().layout;
            cfg.policy.kind = Some(
                chunkrt_policy::checkpoint::kind_of(&dir, &opts)
                    .with_context(|| format!("--checkpoint {}", dir.display()))?,
            );
        }
        cfg.policy.checkpoint = Some(dir);
        cfg.policy.source = PolicySource::Local;
        let file = cfg.source.display().to_string();
        cfg.validate(&format!("{file} (with --checkpoint)"))?;
    }
    if let Some(url) = &args.remote {
        cfg.policy.source = PolicySource::Remote;
        cfg.policy.url = Some(url.clone());
        if cfg.policy.kind.is_none() {
            cfg.policy.kind = Some(ModelKind::Pi05);
        }
        let file = cfg.source.display().to_string();
        cfg.validate(&format!("{file} (with --remote)"))?;
    }
    if let Some(latency) = args.scripted {
        cfg.policy.source = PolicySource::Scripted;
        cfg.policy.scripted.latency_ms = latency;
        let file = cfg.source.display().to_string();
        cfg.validate(&format!("{file} (with --scripted)"))?;
    }
    if args.print_config {
        let from_file = load_config(args.config.as_ref(), None)?;
        let (text, name) = match &args.config {
            Some(p) => (
                chunkrt_ipc::config::read_config_file(p)?,
                p.display().to_string(),
            ),
            None => (
                chunkrt_controller::config::DEFAULT_TOML.to_string(),
                "config/default.toml (embedded)".to_string(),
            ),
        };
        print!(
            "{}",
            crate::config_print::render(&cfg, &from_file, &text, &name)?
        );
        return Ok(());
    }
    let stop_flag = chunkrt_tools::shutdown::flag();
    tracing::info!(
        "chunkrt run: robot '{}' ({} joints) on '{}', {} camera(s), control at {} Hz, policy '{}'",
        cfg.robot.name,
        cfg.n_dof(),
        cfg.robot.namespace,
        cfg.cameras.len(),
        cfg.control.rate_hz,
        cfg.policy.kind_name()
    );
    let executor = Executor::new(&cfg).context("invalid execution settings")?;
    let Some(source) = load_source(&cfg, stop_flag)? else {
        println!("chunkrt run: stopped while the policy was loading");
        return Ok(());
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
