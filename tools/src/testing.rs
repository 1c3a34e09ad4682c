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

/// This machine's CPU time counters (`/proc/stat`): how much of it the hypervisor took for
/// other guests (`steal`). On a 2-core VM of the project's CI kind the host took 1 % of the time
/// with nothing running and 35 % while an FR3 test ran (`HostSteal::share_since`): a vCPU taken
/// away for milliseconds, whatever the priority of the thread it was running.
#[derive(Debug, Clone, Copy)]
pub struct HostSteal {
    steal: u64,
    total: u64,
}

/// `/proc/stat`'s line for `cpu` (`None`: the whole machine): (steal, total) in clock ticks.
fn stat_line(text: &str, cpu: Option<usize>) -> Option<(u64, u64)> {
    let name = cpu.map_or("cpu".to_string(), |c| format!("cpu{c}"));
    let line = text
        .lines()
        .find(|l| l.split_whitespace().next() == Some(name.as_str()))?;
    let v: Vec<u64> = line
        .split_whitespace()
        .skip(1)
        .map(|x| x.parse().ok())
        .collect::<Option<_>>()?;
    // user nice system idle iowait irq softirq steal (guest time is within user)
    Some((*v.get(7)?, v.iter().take(8).sum()))
}

impl HostSteal {
    /// The counters now (`None` where `/proc/stat` cannot be read or has no steal column).
    pub fn now() -> Option<Self> {
        let text = std::fs::read_to_string("/proc/stat").ok()?;
        let (steal, total) = stat_line(&text, None)?;
        Some(Self { steal, total })
    }

    /// The share of the machine's CPU time since `self` that the hypervisor took (0..1).
    pub fn share_since(&self) -> Option<f64> {
        let now = Self::now()?;
        let total = now.total.checked_sub(self.total)?;
        (total > 0).then(|| now.steal.saturating_sub(self.steal) as f64 / total as f64)
    }
}

/// `/proc/stat`'s clock ticks per second (`sysconf(_SC_CLK_TCK)`, 100 where it cannot say).
fn clock_ticks_per_s() -> f64 {
    // SAFETY: sysconf has no preconditions.
    let t = unsafe { libc::sysconf(libc::_SC_CLK_TCK) };
    if t > 0 {
        t as f64
    } else {
        100.0
    }
}

/// The time the hypervisor took from one CPU, sampled every few milliseconds in a thread of its
/// own until dropped: what a thread pinned there lost, and when (`/proc/stat` counts it in
/// 10 ms ticks, accounted when the vCPU runs again).
pub struct StealTimeline {
    samples: std::sync::Arc<std::sync::Mutex<Vec<(f64, u64)>>>,
    stop: std::sync::Arc<std::sync::atomic::AtomicBool>,
    thread: Option<std::thread::JoinHandle<()>>,
    /// The CPU sampled.
    pub cpu: usize,
}

impl StealTimeline {
    /// Samples `cpu`'s steal every `period` (`None` where `/proc/stat` has no such line).
    pub fn start(cpu: usize, period: Duration) -> Option<Self> {
        let text = std::fs::read_to_string("/proc/stat").ok()?;
        stat_line(&text, Some(cpu))?;
        let samples = std::sync::Arc::new(std::sync::Mutex::new(Vec::new()));
        let stop = std::sync::Arc::new(std::sync::atomic::AtomicBool::new(false));
        let (s, st) = (samples.clone(), stop.clone());
        let thread = std::thread::spawn(move || {
            while !st.load(Ordering::Relaxed) {
                if let Some((steal, _)) = std::fs::read_to_string("/proc/stat")
                    .ok()
                    .and_then(|t| stat_line(&t, Some(cpu)))
                {
                    let mut v = s.lock().unwrap_or_else(|e| e.into_inner());
                    if v.len() < 1_000_000 {
                        v.push((chunkrt_ipc::monotonic_ns() as f64 * 1e-9, steal));
                    }
                }
                std::thread::sleep(period);
            }
        });
        Some(Self {
            samples,
            stop,
            thread: Some(thread),
            cpu,
        })
    }

    /// The steal counted on the CPU between the monotonic times `from` and `to` (seconds), in
    /// milliseconds (whole clock ticks: 10 ms where `getconf CLK_TCK` is 100).
    pub fn stolen_ms(&self, from: f64, to: f64) -> f64 {
        let v = self.samples.lock().unwrap_or_else(|e| e.into_inner());
        let before = v.iter().rev().find(|(t, _)| *t <= from).map(|s| s.1);
        let after = v.iter().find(|(t, _)| *t >= to).or(v.last()).map(|s| s.1);
        match (before.or(v.first().map(|s| s.1)), after) {
            (Some(a), Some(b)) => b.saturating_sub(a) as f64 * 1e3 / clock_ticks_per_s(),
            _ => 0.0,
        }
    }
}

impl Drop for StealTimeline {
    fn drop(&mut self) {
        self.stop.store(true, Ordering::Relaxed);
        if let Some(t) = self.thread.take() {
            let _ = t.join();
        }
    }
}
