//! What every tool does at start: load the configuration, apply `--namespace`, open a node and
//! clean up after crashed predecessors.

use std::path::PathBuf;

use anyhow::Context;
use chunkrt_ipc::services::{self, Ipc};
use chunkrt_ipc::{Namespace, SharedConfig as Config};
use iceoryx2::prelude::Node;

/// Options shared by every tool: which configuration and which namespace.
#[derive(Debug, Clone, Default, PartialEq, clap::Args)]
pub struct CommonArgs {
    /// Robot / camera description (TOML). Default: the embedded demo configuration.
    #[arg(long, value_name = "FILE")]
    pub config: Option<PathBuf>,
    /// Service namespace, overriding `robot.namespace` (e.g. `chunkrt/test-42`).
    #[arg(long, value_name = "NS")]
    pub namespace: Option<String>,
}

impl CommonArgs {
    /// The configuration with the namespace override applied and validated.
    pub fn load(&self) -> anyhow::Result<(Config, Namespace)> {
        let mut cfg = match &self.config {
            Some(path) => Config::load(path)?,
            None => Config::embedded_default(),
        };
        if let Some(ns) = &self.namespace {
            Namespace::new(ns).context("--namespace")?;
            cfg.robot.namespace = ns.clone();
        }
        let ns = Namespace::new(&cfg.robot.namespace)?;
        Ok((cfg, ns))
    }
}

/// Creates this tool's node and removes the resources of dead nodes (a restart after a crash).
pub fn open_node(tool: &str) -> anyhow::Result<Node<Ipc>> {
    // iceoryx2 warns on stderr that it runs without a config file; keep its warnings for
    // `IOX2_LOG_LEVEL=warn` and show only errors by default.
    iceoryx2::prelude::set_log_level_from_env_or(iceoryx2::prelude::LogLevel::Error);
    let node = services::node(tool)?;
    let cleaned = services::cleanup_dead_nodes(&node);
    if cleaned > 0 {
        tracing::info!("{tool}: cleaned up {cleaned} dead node(s)");
    }
    Ok(node)
}

/// Checks that an optional `--duration` is a finite, non-negative number of seconds and turns
/// it into an absolute end time (monotonic ns), `u64::MAX` when absent.
pub fn end_time_ns(start_ns: u64, duration_s: Option<f64>) -> anyhow::Result<u64> {
    match duration_s {
        None => Ok(u64::MAX),
        Some(d) if d.is_finite() && (0.0..=1e7).contains(&d) => {
            Ok(start_ns.saturating_add((d * 1e9) as u64))
        }
        Some(d) => anyhow::bail!("--duration {d}: must be a number of seconds in 0..=1e7"),
    }
}

/// Checks a rate option (Hz) against its allowed range.
pub fn check_rate(name: &str, hz: f64, lo: f64, hi: f64) -> anyhow::Result<f64> {
    if hz.is_finite() && hz >= lo && hz <= hi {
        Ok(hz)
    } else {
        anyhow::bail!("{name} {hz}: must be in {lo}..={hi}")
    }
}

/// Sleeps until `deadline_ns` (absolute, monotonic) in slices of at most 50 ms, returning
/// early (false) once `stop` is set, so a slow schedule still stops promptly on SIGTERM.
pub fn sleep_until_or_stop(deadline_ns: u64, stop: &std::sync::atomic::AtomicBool) -> bool {
    const SLICE_NS: u64 = 50_000_000;
    loop {
        if stop.load(std::sync::atomic::Ordering::Relaxed) {
            return false;
        }
        let now = chunkrt_ipc::monotonic_ns();
        if now >= deadline_ns {
            return true;
        }
        chunkrt_ipc::sleep_until_ns(deadline_ns.min(now + SLICE_NS));
    }
}
