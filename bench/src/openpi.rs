//! openpi's PyTorch implementation as the inference bench's same-run baseline: a Python worker
//! (`scripts/openpi_worker.py`, embedded here and written to a temporary file) that builds
//! openpi's `PI0Pytorch` from a checkout the user points to, at the sizes of a bench
//! configuration, and runs one `sample_actions` per request, so the bench can interleave it with
//! its own calls.

use std::io::{BufRead, BufReader, Write};
use std::path::PathBuf;
use std::process::{Child, ChildStdin, ChildStdout, Command, Stdio};

use chunkrt_policy::PolicyError;

/// The worker script (run with the Python the user names).
pub const WORKER_PY: &str = include_str!("../../scripts/openpi_worker.py");

/// Where openpi and its Python are: `--openpi DIR` / `CHUNKRT_OPENPI`, and
/// `CHUNKRT_OPENPI_PYTHON` (default `python3`; `scripts/openpi-env.sh` makes one).
#[derive(Debug, Clone)]
pub struct OpenpiSetup {
    /// openpi checkout (or its `src/`).
    pub dir: PathBuf,
    /// Python with torch and transformers at openpi's versions.
    pub python: PathBuf,
    /// torch intra-op threads (the bench gives its own thread count).
    pub threads: usize,
}

impl OpenpiSetup {
    /// From `--openpi DIR` or, without it, the environment (`None`: no same-run baseline).
    pub fn from_args_or_env(dir: Option<PathBuf>, threads: usize) -> Option<Self> {
        let dir = dir.or_else(|| std::env::var_os("CHUNKRT_OPENPI").map(PathBuf::from))?;
        let python = std::env::var_os("CHUNKRT_OPENPI_PYTHON")
            .map(PathBuf::from)
            .unwrap_or_else(|| PathBuf::from("python3"));
        Some(Self {
            dir,
            python,
            threads,
        })
    }
}

/// What the worker said once its model was built and warmed up.
#[derive(Debug, Clone, Default)]
pub struct OpenpiInfo {
    /// torch version.
    pub torch: String,
    /// Parameters without the token embeddings.
    pub params: u64,
    /// torch threads.
    pub threads: u64,
    /// ATen's CPU capability (`torch.backends.cpu.get_cpu_capability()`: "AVX2", "AVX512", …).
    pub cpu_capability: String,
}

/// A running worker; killed on drop.
pub struct OpenpiWorker {
    child: Child,
    stdin: ChildStdin,
    stdout: BufReader<ChildStdout>,
    /// What the worker reported at start.
    pub info: OpenpiInfo,
    _files: TempFiles,
}

/// Files removed on drop (the worker's script and configuration).
struct TempFiles(Vec<PathBuf>);

impl Drop for TempFiles {
    fn drop(&mut self) {
        for p in &self.0 {
            let _ = std::fs::remove_file(p);
        }
    }
}

fn err(msg: impl Into<String>) -> PolicyError {
    PolicyError::Config(format!("openpi baseline: {}", msg.into()))
}

impl OpenpiWorker {
    /// Starts the worker for bench configuration `name` (`json`: its text) and waits until it has
    /// built and warmed up openpi's model.
    pub fn spawn(setup: &OpenpiSetup, name: &str, json: &str) -> Result<Self, PolicyError> {
        let tmp = std::env::temp_dir();
        let tag = format!("chunkrt-openpi-{}-{name}", std::process::id());
        let script = tmp.join(format!("{tag}.py"));
        let config = tmp.join(format!("{tag}.json"));
        let files = TempFiles(vec![script.clone(), config.clone()]);
        std::fs::write(&script, WORKER_PY)
            .map_err(|e| err(format!("{}: {e}", script.display())))?;
        std::fs::write(&config, json).map_err(|e| err(format!("{}: {e}", config.display())))?;
        let mut child = Command::new(&setup.python)
            .arg(&script)
            .arg("--openpi")
            .arg(&setup.dir)
            .arg("--config")
            .arg(&config)
            .arg("--threads")
            .arg(setup.threads.to_string())
            .stdin(Stdio::piped())
            .stdout(Stdio::piped())
            .stderr(Stdio::inherit())
            .spawn()
            .map_err(|e| err(format!("cannot start {}: {e}", setup.python.display())))?;
        let (stdin, stdout) = match (child.stdin.take(), child.stdout.take()) {
            (Some(i), Some(o)) => (i, BufReader::new(o)),
            _ => return Err(err("no pipes to the worker")),
        };
        let mut w = Self {
            child,
            stdin,
            stdout,
            info: OpenpiInfo::default(),
            _files: files,
        };
        let hello = w.read_json()?;
        if hello["ready"].as_bool() != Some(true) {
            return Err(err(format!("unexpected first line {hello}")));
        }
        w.info = OpenpiInfo {
            torch: hello["torch"].as_str().unwrap_or("?").to_string(),
            params: hello["params"].as_u64().unwrap_or(0),
            threads: hello["threads"].as_u64().unwrap_or(0),
            cpu_capability: hello["cpu_capability"].as_str().unwrap_or("?").to_string(),
        };
        Ok(w)
    }

    fn read_json(&mut self) -> Result<serde_json::Value, PolicyError> {
        let mut line = String::new();
        let n = self
            .stdout
            .read_line(&mut line)
            .map_err(|e| err(format!("reading the worker: {e}")))?;
        if n == 0 {
            let status = self.child.wait().map(|s| s.to_string()).unwrap_or_default();
            return Err(err(format!(
                "the worker exited ({status}); its errors are above"
            )));
        }
        serde_json::from_str(&line).map_err(|e| err(format!("worker said {line:?}: {e}")))
    }

    /// One `sample_actions` call: (wall µs, process CPU µs), timed inside the worker.
    pub fn sample(&mut self) -> Result<(u64, u64), PolicyError> {
        self.stdin
            .write_all(b"sample\n")
            .and_then(|_| self.stdin.flush())
            .map_err(|e| err(format!("writing to the worker: {e}")))?;
        let v = self.read_json()?;
        match (v["wall_us"].as_u64(), v["cpu_us"].as_u64()) {
            (Some(w), Some(c)) => Ok((w.max(1), c.max(1))),
            _ => Err(err(format!("unexpected answer {v}"))),
        }
    }
}

impl Drop for OpenpiWorker {
    fn drop(&mut self) {
        let _ = self.stdin.write_all(b"quit\n");
        let _ = self.stdin.flush();
        let deadline = std::time::Instant::now() + std::time::Duration::from_secs(5);
        while std::time::Instant::now() < deadline {
            if let Ok(Some(_)) = self.child.try_wait() {
                return;
            }
            std::thread::sleep(std::time::Duration::from_millis(20));
        }
        let _ = self.child.kill();
        let _ = self.child.wait();
    }
}
