//! openpi's transport as the baseline of `ipc_latency`: websocket + msgpack-numpy over loopback,
//! driven by the Python scripts in `tools/python/openpi_baseline/` (the `openpi-client` package
//! from PyPI on the client side, a minimal openpi-style server on the other).

use std::io::{BufRead, BufReader};
use std::path::{Path, PathBuf};
use std::process::{Child, Command, Stdio};
use std::time::{Duration, Instant};

use hdrhistogram::Histogram;

use super::BenchError;
use crate::report::latency_histogram;

/// One observation shape: `cameras == 0` is a joint-state observation.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Case {
    /// Series name, e.g. `cam3_224x224`.
    pub name: String,
    /// Number of RGB cameras (0: joint state only).
    pub cameras: u32,
    /// Frame width in pixels.
    pub width: u32,
    /// Frame height in pixels.
    pub height: u32,
}

/// Measured baseline of one case (ns).
#[derive(Debug, Clone)]
pub struct CaseResult {
    /// Case name.
    pub name: String,
    /// Client send start → server finished unpacking.
    pub one_way: Histogram<u64>,
    /// Client send start → reply unpacked.
    pub rtt: Histogram<u64>,
}

/// The whole baseline run.
#[derive(Debug, Clone)]
pub struct Baseline {
    /// What was measured, e.g. "websocket + msgpack-numpy (openpi-client 0.1.2)".
    pub transport: String,
    /// Set when openpi-client could not be used and its format was mirrored.
    pub substitution: Option<String>,
    /// Per case.
    pub cases: Vec<CaseResult>,
}

/// Folder of the Python scripts.
pub fn script_dir() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("tools/python/openpi_baseline")
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

/// Runs the websocket baseline: starts the server on a loopback port, runs the client for every
/// case (`iters` measured round trips after `warmup`, `gap` apart), and reads the latencies.
pub fn run(
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
}
