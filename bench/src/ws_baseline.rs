//! openpi's transport as the baseline of `ipc_latency`: websocket + msgpack-numpy over loopback,
//! driven by the Python scripts in `tools/python/openpi_baseline/` (the `openpi-client` package
//! from PyPI on the client side, a minimal openpi-style server on the other).
//!
//! Without a Python that can run those scripts, [`run`] falls back to an equivalent Rust
//! websocket + msgpack pair ([`super::ws_rust`]) and names the fallback in
//! [`Baseline::transport`] and [`Baseline::substitution`]. `$CHUNKRT_WS_BASELINE` picks the
//! driver: `auto` (default), `python` (no fallback) or `rust` (force the fallback).

use std::io::{BufRead, BufReader};
use std::path::PathBuf;
use std::process::{Child, Command, Stdio};
use std::time::{Duration, Instant};

use hdrhistogram::Histogram;

use super::BenchError;
use crate::report::latency_histogram;

pub use super::ws::{Baseline, Case, CaseResult};

/// Folder of the Python scripts.
pub fn script_dir() -> PathBuf {
    crate::workspace_root().join("tools/python/openpi_baseline")
}

/// The Python interpreter: `$CHUNKRT_PYTHON`, else `python3`.
pub fn python() -> String {
    std::env::var("CHUNKRT_PYTHON").unwrap_or_else(|_| "python3".to_string())
}

struct KillOnDrop(Child);

impl Drop for KillOnDrop {
    fn drop(&mut self) {
        let _ = self.0.kill();
        let _ = self.0.wait();
    }
}

fn proc_err(what: &str, reason: impl std::fmt::Display) -> BenchError {
    BenchError::Process {
        what: what.to_string(),
        reason: reason.to_string(),
    }
}

/// Environment variable that picks the baseline's driver: `auto`, `python` or `rust`.
pub const DRIVER_ENV: &str = "CHUNKRT_WS_BASELINE";

/// Who drives the websocket baseline.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum Driver {
    /// The Python scripts (openpi-client, or its mirror in `transport.py`).
    Python {
        /// Chosen explicitly (`$CHUNKRT_WS_BASELINE=python`): a failure is not papered over.
        forced: bool,
    },
    /// The Rust pair, and why.
    Rust {
        /// Why Python is not used.
        reason: String,
    },
}

/// Picks the driver from the `$CHUNKRT_WS_BASELINE` setting; `auto` asks `probe` whether the
/// Python side can run.
pub fn choose(
    setting: Option<&str>,
    probe: impl FnOnce() -> Result<(), String>,
) -> Result<Driver, BenchError> {
    match setting.map(str::trim) {
        None | Some("") | Some("auto") => Ok(match probe() {
            Ok(()) => Driver::Python { forced: false },
            Err(why) => Driver::Rust {
                reason: format!("Python/openpi-client unavailable: {why}"),
            },
        }),
        Some("python") => Ok(Driver::Python { forced: true }),
        Some("rust") => Ok(Driver::Rust {
            reason: format!("forced by {DRIVER_ENV}=rust"),
        }),
        Some(other) => Err(BenchError::Option(format!(
            "{DRIVER_ENV}={other}: expected auto, python or rust"
        ))),
    }
}

/// Whether the Python scripts can run: the interpreter starts and imports what `transport.py`
/// (openpi-client, or numpy + msgpack + websockets for its mirror) and `server.py` need.
pub fn probe_python() -> Result<(), String> {
    let py = python();
    let out = Command::new(&py)
        .args(["-c", "import transport, websockets.asyncio.server"])
        .current_dir(script_dir())
        .stdin(Stdio::null())
        .stdout(Stdio::null())
        .stderr(Stdio::piped())
        .output()
        .map_err(|e| format!("cannot start {py}: {e}"))?;
    if out.status.success() {
        return Ok(());
    }
    let stderr = String::from_utf8_lossy(&out.stderr);
    let last = stderr.lines().rev().find(|l| !l.trim().is_empty());
    Err(format!(
        "{py} cannot import the baseline's modules ({})",
        last.unwrap_or("no error output").trim()
    ))
}

/// Runs the websocket baseline with the driver `$CHUNKRT_WS_BASELINE` picks (see [`choose`]):
/// Python when it can run, else the Rust pair. In `auto` mode a failed Python run also falls back.
pub fn run(
    cases: &[Case],
    iters: usize,
    warmup: usize,
    gap: Duration,
    timeout: Duration,
) -> Result<Baseline, BenchError> {
    let setting = std::env::var(DRIVER_ENV).ok();
    let fallback = |reason: String| {
        println!("websocket baseline: {}", super::ws_rust::transport(&reason));
        super::ws_rust::run(cases, iters, warmup, gap, timeout, &reason)
    };
    match choose(setting.as_deref(), probe_python)? {
        Driver::Python { forced: true } => run_python(cases, iters, warmup, gap, timeout),
        Driver::Python { forced: false } => match run_python(cases, iters, warmup, gap, timeout) {
            Ok(b) => Ok(b),
            Err(e) => fallback(format!("Python baseline failed: {e}")),
        },
        Driver::Rust { reason } => fallback(reason),
    }
}

/// Runs the Python baseline: starts the server on a loopback port, runs the client for every
/// case (`iters` measured round trips after `warmup`, `gap` apart), and reads the latencies.
pub fn run_python(
    cases: &[Case],
    iters: usize,
    warmup: usize,
    gap: Duration,
    timeout: Duration,
) -> Result<Baseline, BenchError> {
    let dir = script_dir();
    let py = python();
    let server = Command::new(&py)
        .arg(dir.join("server.py"))
        .current_dir(&dir)
        .stdin(Stdio::piped())
        .stdout(Stdio::piped())
        .stderr(Stdio::inherit())
        .spawn()
        .map_err(|e| proc_err(&format!("{py} server.py"), e))?;
    let mut server = KillOnDrop(server);
    let stdout = server
        .0
        .stdout
        .take()
        .ok_or_else(|| proc_err("server.py", "no stdout"))?;
    let mut line = String::new();
    BufReader::new(stdout)
        .read_line(&mut line)
        .map_err(|e| proc_err("server.py", e))?;
    let port: u16 = line.trim().parse().map_err(|_| {
        proc_err(
            "server.py",
            format!("expected a port, got '{}'", line.trim()),
        )
    })?;

    let out = std::env::temp_dir().join(format!(
        "chunkrt-ws-baseline-{}-{}.json",
        std::process::id(),
        port
    ));
    let mut cmd = Command::new(&py);
    cmd.arg(dir.join("client.py"))
        .current_dir(&dir)
        .args(["--port", &port.to_string()])
        .args(["--iters", &iters.to_string()])
        .args(["--warmup", &warmup.to_string()])
        .args(["--gap-us", &gap.as_micros().to_string()])
        .arg("--out")
        .arg(&out)
        .stdin(Stdio::null())
        .stdout(Stdio::inherit())
        .stderr(Stdio::inherit());
    for c in cases {
        cmd.args([
            "--case",
            &format!("{}:{}:{}:{}", c.name, c.cameras, c.width, c.height),
        ]);
    }
    let client = cmd
        .spawn()
        .map_err(|e| proc_err(&format!("{py} client.py"), e))?;
    let mut client = KillOnDrop(client);
    let t0 = Instant::now();
    let status = loop {
        match client.0.try_wait() {
            Ok(Some(s)) => break s,
            Ok(None) if t0.elapsed() > timeout => {
                return Err(BenchError::Timeout(format!(
                    "websocket baseline client still running after {timeout:?}"
                )))
            }
            Ok(None) => std::thread::sleep(Duration::from_millis(20)),
            Err(e) => return Err(proc_err("client.py", e)),
        }
    };
    drop(server);
    if !status.success() {
        return Err(proc_err("client.py", format!("exited with {status}")));
    }
    let text = std::fs::read_to_string(&out).map_err(|e| proc_err("client.py output", e))?;
    let _ = std::fs::remove_file(&out);
    parse_result(&text, cases)
}

/// Parses the client's JSON output into histograms.
pub fn parse_result(text: &str, cases: &[Case]) -> Result<Baseline, BenchError> {
    let bad = |reason: String| BenchError::Parse {
        what: "websocket baseline output",
        reason,
    };
    let v: serde_json::Value = serde_json::from_str(text).map_err(|e| bad(e.to_string()))?;
    let transport = v["transport"]
        .as_str()
        .unwrap_or("websocket + msgpack-numpy")
        .to_string();
    let substitution = v["substitution"].as_str().map(str::to_string);
    let mut out = Vec::new();
    for c in cases {
        let case = &v["cases"][&c.name];
        let hist = |key: &str| -> Result<Histogram<u64>, BenchError> {
            let arr = case[key]
                .as_array()
                .ok_or_else(|| bad(format!("case {}: no '{key}' array", c.name)))?;
            let mut h = latency_histogram();
            for x in arr {
                let ns = x
                    .as_i64()
                    .ok_or_else(|| bad(format!("case {}: non-integer latency", c.name)))?;
                h.saturating_record(ns.max(0) as u64);
            }
            Ok(h)
        };
        out.push(CaseResult {
            name: c.name.clone(),
            one_way: hist("one_way_ns")?,
            rtt: hist("rtt_ns")?,
        });
    }
    Ok(Baseline {
        transport,
        substitution,
        cases: out,
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn parses_client_output() {
        let cases = [Case {
            name: "a".into(),
            cameras: 0,
            width: 0,
            height: 0,
        }];
        let b = parse_result(
            r#"{"transport":"t","substitution":null,"cases":{"a":{"one_way_ns":[1000,2000],"rtt_ns":[3000,4000]}}}"#,
            &cases,
        )
        .expect("valid output");
        assert_eq!(b.cases[0].one_way.len(), 2);
        assert!((4000..4010).contains(&b.cases[0].rtt.max()));
        assert!(b.substitution.is_none());
        assert!(parse_result("{", &cases).is_err());
        assert!(parse_result(r#"{"cases":{}}"#, &cases).is_err());
    }

    #[test]
    fn chooses_driver() {
        let ok = || Ok(());
        let missing = || Err("no numpy".to_string());
        assert_eq!(
            choose(None, ok).expect("valid"),
            Driver::Python { forced: false }
        );
        assert_eq!(
            choose(Some("auto"), missing).expect("valid"),
            Driver::Rust {
                reason: "Python/openpi-client unavailable: no numpy".into()
            }
        );
        assert_eq!(
            choose(Some("python"), missing).expect("valid"),
            Driver::Python { forced: true }
        );
        match choose(Some("rust"), ok).expect("valid") {
            Driver::Rust { reason } => assert!(reason.contains("CHUNKRT_WS_BASELINE=rust")),
            d => panic!("expected the Rust pair, got {d:?}"),
        }
        assert!(choose(Some("java"), ok).is_err());
    }
}
