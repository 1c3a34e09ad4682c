//! # chunkrt-bench
//!
//! Measurement, kept out of the runtime crates: the benches' library code (so that the test
//! suite can run each bench's quick mode in the dev profile and the benches stay thin `main`s),
//! latency histograms, interval logs and plots ([`histlog`], [`report`]: `chunkrt report`), the
//! inference bench against openpi ([`inference`], [`openpi`]: `chunkrt bench-inference`), the
//! closed-loop metrics of the evaluation ([`metrics`]) and the scripted chunk source, a test
//! double of the policy ([`scripted`]). Depends on the controller and the policy crates, never
//! on the `chunkrt` application.
//!
//! - [`ipc_latency`]: publish → receive latency between two processes over iceoryx2, against
//!   openpi's websocket + msgpack-numpy transport ([`ws_baseline`]; Rust fallback [`ws_rust`])
//!   in the same run.
//! - [`control_loop`]: wake-up lateness and compute time of a periodic control thread
//!   ([`periodic`]), idle and under a candle matmul load ([`load`]), against `cyclictest`
//!   ([`cyclictest`]) in the same run.
//!
//! Every bench writes its histograms under [`output_root`] (`target/chunkrt-bench/<bench>/`):
//! an HdrHistogram interval log (`.hlog`), a PNG plot and a Markdown table, through
//! [`chunkrt::report`].

pub mod control_loop;
pub mod cyclictest;
pub mod end_to_end;
pub mod histlog;
pub mod inference;
pub mod ipc_latency;
pub mod load;
pub mod metrics;
pub mod openpi;
pub mod periodic;
pub mod report;
pub mod scripted;
pub mod ws;
pub mod ws_baseline;
pub mod ws_rust;

use std::path::{Path, PathBuf};
use std::time::Duration;

use crate::report::{LatencyTable, Series};

/// Errors of the benchmark harness.
#[derive(Debug, thiserror::Error)]
pub enum BenchError {
    /// The IPC edge could not be opened.
    #[error(transparent)]
    Ipc(#[from] chunkrt_ipc::IpcError),
    /// An iceoryx2 port failed while running.
    #[error("iceoryx2 {what} failed: {reason}")]
    Port {
        /// Which operation.
        what: &'static str,
        /// The cause.
        reason: String,
    },
    /// A helper process could not be started or misbehaved.
    #[error("{what}: {reason}")]
    Process {
        /// Which process.
        what: String,
        /// What happened.
        reason: String,
    },
    /// The peer never answered.
    #[error("timed out: {0}")]
    Timeout(String),
    /// Writing the report failed.
    #[error(transparent)]
    Report(#[from] report::ReportError),
    /// A thread could not be started or panicked.
    #[error("thread: {0}")]
    Thread(String),
    /// Bad option.
    #[error("invalid option: {0}")]
    Option(String),
    /// candle failed (load generator).
    #[error("candle: {0}")]
    Candle(String),
    /// Output could not be parsed.
    #[error("cannot parse {what}: {reason}")]
    Parse {
        /// What was parsed.
        what: &'static str,
        /// Why it failed.
        reason: String,
    },
}

/// The workspace's root folder (this crate sits in `bench/`).
pub fn workspace_root() -> PathBuf {
    let here = Path::new(env!("CARGO_MANIFEST_DIR"));
    here.parent().unwrap_or(here).to_path_buf()
}

/// `target/chunkrt-bench/` of this workspace (or of `$CARGO_TARGET_DIR` when set at run time).
pub fn output_root() -> PathBuf {
    match std::env::var_os("CARGO_TARGET_DIR") {
        Some(t) => PathBuf::from(t).join("chunkrt-bench"),
        None => workspace_root().join("target").join("chunkrt-bench"),
    }
}

/// Options every bench takes.
#[derive(Debug, Clone)]
pub struct BenchOpts {
    /// Short run (the test suite's mode, and `--quick` on the command line).
    pub quick: bool,
    /// Folder for the logs, plots and tables.
    pub out_dir: PathBuf,
}

impl BenchOpts {
    /// Options from a bench binary's command line: `--quick`, `--out DIR`; cargo's own `--bench`
    /// flag is ignored. Unknown flags are an error.
    pub fn from_args(
        bench: &str,
        args: impl IntoIterator<Item = String>,
    ) -> Result<Self, BenchError> {
        let mut quick = false;
        let mut out_dir = output_root().join(bench);
        let mut it = args.into_iter();
        while let Some(a) = it.next() {
            match a.as_str() {
                "--quick" => quick = true,
                "--bench" => {}
                "--out" => {
                    out_dir = it
                        .next()
                        .map(PathBuf::from)
                        .ok_or_else(|| BenchError::Option("--out needs a folder".into()))?
                }
                other => {
                    return Err(BenchError::Option(format!(
                        "unknown argument '{other}' (use --quick, --out DIR)"
                    )))
                }
            }
        }
        Ok(Self { quick, out_dir })
    }
}

/// Files a bench wrote.
#[derive(Debug, Clone, Default)]
pub struct Outputs {
    /// Interval log.
    pub hlog: PathBuf,
    /// Percentile plots.
    pub pngs: Vec<PathBuf>,
    /// Markdown table.
    pub md: PathBuf,
}

impl std::fmt::Display for Outputs {
    /// `wrote <hlog>, <png>, <png> and <md>`, the line every bench prints.
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(f, "wrote {}", self.hlog.display())?;
        for p in &self.pngs {
            write!(f, ", {}", p.display())?;
        }
        write!(f, " and {}", self.md.display())
    }
}

/// Writes `<out>/<name>.hlog` (all series), `<out>/<name>.md` (the table) and one PNG per
/// `(file stem, title, series names)` plot request.
pub fn write_outputs(
    out_dir: &Path,
    name: &str,
    table: &LatencyTable,
    series: &[Series],
    plots: &[(&str, &str, Vec<String>)],
    duration: Duration,
    comment: &str,
) -> Result<Outputs, BenchError> {
    std::fs::create_dir_all(out_dir).map_err(|source| report::ReportError::Io {
        path: out_dir.to_path_buf(),
        source,
    })?;
    let hlog = out_dir.join(format!("{name}.hlog"));
    report::write_interval_log(&hlog, series, duration, comment)?;
    let md = out_dir.join(format!("{name}.md"));
    let text = format!("## {}\n\n{}\n", table.title, table.to_markdown());
    std::fs::write(&md, text).map_err(|source| report::ReportError::Io {
        path: md.clone(),
        source,
    })?;
    let mut pngs = Vec::new();
    for (stem, title, names) in plots {
        let chosen: Vec<Series> = series
            .iter()
            .filter(|s| names.contains(&s.name))
            .cloned()
            .collect();
        if chosen.is_empty() {
            continue;
        }
        let png = out_dir.join(format!("{stem}.png"));
        report::plot_percentiles(&png, title, &chosen, (1000, 640))?;
        pngs.push(png);
    }
    Ok(Outputs { hlog, pngs, md })
}

/// One line describing this machine: CPU model and core count (from `/proc/cpuinfo`).
pub fn machine_line() -> String {
    crate::inference::cpu_model()
}

/// Geometric mean of positive ratios (1.0 for none).
pub fn geomean(xs: &[f64]) -> f64 {
    let v: Vec<f64> = xs
        .iter()
        .copied()
        .filter(|x| x.is_finite() && *x > 0.0)
        .collect();
    if v.is_empty() {
        return 1.0;
    }
    (v.iter().map(|x| x.ln()).sum::<f64>() / v.len() as f64).exp()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn args() {
        let o = BenchOpts::from_args("x", ["--bench".to_string(), "--quick".to_string()])
            .expect("valid args");
        assert!(o.quick);
        assert!(o.out_dir.ends_with("chunkrt-bench/x"));
        assert!(BenchOpts::from_args("x", ["--nope".to_string()]).is_err());
        assert!(BenchOpts::from_args("x", ["--out".to_string()]).is_err());
    }

    #[test]
    fn geomean_of_ratios() {
        assert!((geomean(&[2.0, 8.0]) - 4.0).abs() < 1e-9);
        assert_eq!(geomean(&[]), 1.0);
    }
}
