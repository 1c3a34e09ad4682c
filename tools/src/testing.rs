//! Helpers for tests that run the tools as real processes: unique namespaces and child
//! processes that are always stopped (SIGTERM, then SIGKILL) and reaped.

use std::io::Read;
use std::process::{Child, Command, Stdio};
use std::sync::atomic::{AtomicU32, Ordering};
use std::time::{Duration, Instant};

/// A namespace no other test (or test run) uses: `chunkrt/test-<pid>-<tag>-<n>`.
pub fn unique_namespace(tag: &str) -> String {
    static N: AtomicU32 = AtomicU32::new(0);
    format!(
        "chunkrt/test-{}-{tag}-{}",
        std::process::id(),
        N.fetch_add(1, Ordering::Relaxed)
    )
}

/// A child process that is stopped and reaped when dropped.
#[derive(Debug)]
pub struct ChildGuard {
    child: Option<Child>,
    name: String,
}

/// What a stopped child printed and how it ended.
#[derive(Debug, Clone)]
pub struct Finished {
    /// Exit code (`None`: killed by a signal).
    pub code: Option<i32>,
    pub stdout: String,
    pub stderr: String,
}

impl ChildGuard {
    /// Starts `program args…` with stdout and stderr captured.
    pub fn spawn(program: &str, args: &[&str]) -> std::io::Result<Self> {
        let child = Command::new(program)
            .args(args)
            .stdin(Stdio::null())
            .stdout(Stdio::piped())
            .stderr(Stdio::piped())
            .spawn()?;
        Ok(Self {
            child: Some(child),
            name: format!("{program} {}", args.join(" ")),
        })
    }

    /// Process id.
    pub fn id(&self) -> u32 {
        self.child.as_ref().map(|c| c.id()).unwrap_or(0)
    }

    /// True while the process runs.
    pub fn running(&mut self) -> bool {
        matches!(self.child.as_mut().map(|c| c.try_wait()), Some(Ok(None)))
    }

    /// Waits up to `timeout` for the process to exit by itself, then SIGTERM, then SIGKILL;
    /// returns its output.
    pub fn finish(mut self, timeout: Duration) -> Finished {
        self.stop(timeout)
    }

    /// Sends SIGTERM now and waits up to `timeout` before SIGKILL; returns its output.
    pub fn terminate(mut self, timeout: Duration) -> Finished {
        if let Some(c) = &self.child {
            // SAFETY: plain kill(2) on our own child's pid.
            unsafe { libc::kill(c.id() as libc::pid_t, libc::SIGTERM) };
        }
        self.stop(timeout)
    }

    fn stop(&mut self, timeout: Duration) -> Finished {
        let Some(mut child) = self.child.take() else {
            return Finished {
                code: None,
                stdout: String::new(),
                stderr: String::new(),
            };
        };
        let wait = |child: &mut Child, t: Duration| {
            let end = Instant::now() + t;
            loop {
                match child.try_wait() {
                    Ok(Some(status)) => return Some(status),
                    Ok(None) if Instant::now() < end => {
                        std::thread::sleep(Duration::from_millis(10))
                    }
                    _ => return None,
                }
            }
        };
        let mut status = wait(&mut child, timeout);
        if status.is_none() {
            // SAFETY: plain kill(2) on our own child's pid.
            unsafe { libc::kill(child.id() as libc::pid_t, libc::SIGTERM) };
            status = wait(&mut child, Duration::from_secs(3));
        }
        if status.is_none() {
            eprintln!("{}: did not stop on SIGTERM, killing it", self.name);
            let _ = child.kill();
            status = child.wait().ok();
        }
        let mut stdout = String::new();
        let mut stderr = String::new();
        if let Some(mut o) = child.stdout.take() {
            let _ = o.read_to_string(&mut stdout);
        }
        if let Some(mut e) = child.stderr.take() {
            let _ = e.read_to_string(&mut stderr);
        }
        Finished {
            code: status.and_then(|s| s.code()),
            stdout,
            stderr,
        }
    }
}

impl Drop for ChildGuard {
    fn drop(&mut self) {
        if self.child.is_some() {
            let _ = self.terminate_in_place();
        }
    }
}

impl ChildGuard {
    fn terminate_in_place(&mut self) -> Finished {
        if let Some(c) = &self.child {
            // SAFETY: plain kill(2) on our own child's pid.
            unsafe { libc::kill(c.id() as libc::pid_t, libc::SIGTERM) };
        }
        self.stop(Duration::from_secs(3))
    }
}

/// The value of `key=<number>` in a summary line, e.g. `summary_value(out, "commands_applied")`.
pub fn summary_value(text: &str, key: &str) -> Option<f64> {
    let pat = format!("{key}=");
    text.split_whitespace()
        .find_map(|w| w.strip_prefix(pat.as_str()))
        .and_then(|v| v.parse().ok())
}

/// This machine's CPU time counters (`/proc/stat`'s first line): how much of it the hypervisor
/// took for other guests (`steal`). On a 2-core VM of the project's CI kind the host took 1 % of
/// the time with nothing running and 35 % while an FR3 test ran (`HostSteal::share_since`): a
/// vCPU taken away for milliseconds, whatever the priority of the thread it was running.
#[derive(Debug, Clone, Copy)]
pub struct HostSteal {
    steal: u64,
    total: u64,
}

impl HostSteal {
    /// The counters now (`None` where `/proc/stat` cannot be read or has no steal column).
    pub fn now() -> Option<Self> {
        let text = std::fs::read_to_string("/proc/stat").ok()?;
        let line = text.lines().find(|l| l.starts_with("cpu "))?;
        let v: Vec<u64> = line
            .split_whitespace()
            .skip(1)
            .map(|x| x.parse().ok())
            .collect::<Option<_>>()?;
        // user nice system idle iowait irq softirq steal (guest time is within user)
        let steal = *v.get(7)?;
        Some(Self {
            steal,
            total: v.iter().take(8).sum(),
        })
    }

    /// The share of the machine's CPU time since `self` that the hypervisor took (0..1).
    pub fn share_since(&self) -> Option<f64> {
        let now = Self::now()?;
        let total = now.total.checked_sub(self.total)?;
        (total > 0).then(|| now.steal.saturating_sub(self.steal) as f64 / total as f64)
    }
}
