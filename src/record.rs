//! `chunkrt record` and `--record FILE` on `demo` and `soak`: a run into a Rerun recording.
//!
//! The recorder is a process of its own (`tools/python/chunkrt_record.py`, in the virtual
//! environment of `scripts/rerun-env.sh`: PyPI's rerun-sdk, whose `rerun` is also the viewer). It
//! subscribes to the namespace's services, so the controller does no work for it; the chunks come
//! from the controller's `NS/chunks` service.

use std::path::{Path, PathBuf};
use std::process::{Command, Stdio};

use anyhow::Context;

/// `chunkrt record`: everything a namespace carries into an `.rrd` file, until Ctrl-C.
#[derive(Debug, clap::Args)]
pub struct RecordArgs {
    /// The run's service namespace (`chunkrt monitor` lists them).
    #[arg(long)]
    pub namespace: String,
    /// The Rerun recording to write (open it with `rerun FILE`).
    #[arg(long, value_name = "FILE")]
    pub out: PathBuf,
    /// Camera names to record, comma separated (none: no frames).
    #[arg(long, default_value = "")]
    pub cameras: String,
    /// Keep one camera frame in N.
    #[arg(long, value_name = "N", default_value_t = 1)]
    pub frame_every: u32,
    /// Seconds to record (0: until Ctrl-C / SIGTERM).
    #[arg(long, default_value_t = 0.0)]
    pub duration: f64,
    /// Megabytes of data to record at most (then the recorder says so and records no more).
    #[arg(long, value_name = "MB", default_value_t = 500.0)]
    pub max_mb: f64,
}

/// The interpreter of the recorder's virtual environment: `CHUNKRT_RERUN_PYTHON`, else
/// `CHUNKRT_RERUN_PREFIX` (default `~/.cache/chunkrt-rerun`)`/venv/bin/python`.
pub fn rerun_python() -> anyhow::Result<PathBuf> {
    let (_, py) = crate::args::venv_python(
        "CHUNKRT_RERUN_PREFIX",
        "chunkrt-rerun",
        "CHUNKRT_RERUN_PYTHON",
    );
    anyhow::ensure!(
        py.is_file(),
        "recording needs PyPI's rerun-sdk in its own environment: bash scripts/rerun-env.sh \
         (looked for {})",
        py.display()
    );
    Ok(py)
}

/// The recorder script beside the other Python tools.
pub fn recorder_script() -> PathBuf {
    crate::task::so101::sim_script().with_file_name("chunkrt_record.py")
}

/// The recorder's command line for `ns` into `out`.
pub fn recorder_command(
    ns: &str,
    out: &Path,
    cameras: &[String],
    extra: &[String],
) -> anyhow::Result<Command> {
    let py = rerun_python()?;
    let script = recorder_script();
    anyhow::ensure!(
        script.is_file(),
        "the recorder {} is missing",
        script.display()
    );
    if let Some(dir) = out.parent().filter(|d| !d.as_os_str().is_empty()) {
        std::fs::create_dir_all(dir).with_context(|| format!("cannot create {}", dir.display()))?;
    }
    let mut cmd = Command::new(py);
    cmd.arg(script)
        .args(["--namespace", ns, "--out"])
        .arg(out)
        .args(["--cameras", &cameras.join(",")])
        .args(extra)
        .stdin(Stdio::null());
    Ok(cmd)
}

/// `chunkrt record`.
pub fn run(args: RecordArgs) -> anyhow::Result<()> {
    anyhow::ensure!(
        args.frame_every >= 1,
        "--frame-every {}: must be at least 1",
        args.frame_every
    );
    anyhow::ensure!(
        args.max_mb.is_finite() && args.max_mb > 0.0,
        "--max-mb {}: must be positive",
        args.max_mb
    );
    anyhow::ensure!(
        args.duration.is_finite() && args.duration >= 0.0,
        "--duration {}: must be 0 or more",
        args.duration
    );
    let cameras: Vec<String> = args
        .cameras
        .split(',')
        .filter(|s| !s.is_empty())
        .map(String::from)
        .collect();
    let extra = vec![
        "--frame-every".to_string(),
        args.frame_every.to_string(),
        "--duration".into(),
        args.duration.to_string(),
        "--max-mb".into(),
        args.max_mb.to_string(),
    ];
    // Ctrl-C reaches the recorder too (same process group): this process waits for it to
    // close the file instead of dying first
    let _stop = chunkrt_tools::shutdown::flag();
    let status = recorder_command(&args.namespace, &args.out, &cameras, &extra)?
        .status()
        .context("cannot start the recorder")?;
    anyhow::ensure!(status.success(), "the recorder ended with {status}");
    Ok(())
}
