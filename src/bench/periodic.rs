//! A periodic thread on absolute deadlines that measures itself: wake-up lateness (how long after
//! its deadline the thread ran) and compute time (how long the tick body took), into histograms
//! allocated before the loop starts. The tick body is pluggable ([`TickBody`]); the control
//! thread's real tick plugs in here when it lands.

use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::Arc;

use chunkrt_ipc::{monotonic_ns, sleep_until_ns};
use hdrhistogram::Histogram;

use super::BenchError;
use crate::report::latency_histogram;

/// The work done every tick. Must not allocate, lock or do I/O other than IPC (rule 2).
pub trait TickBody: Send {
    /// Runs tick `index`, whose deadline (wake-up time) was `deadline_ns` (monotonic).
    fn tick(&mut self, index: u64, deadline_ns: u64);
}

impl<F: FnMut(u64, u64) + Send> TickBody for F {
    fn tick(&mut self, index: u64, deadline_ns: u64) {
        self(index, deadline_ns)
    }
}

/// How the periodic thread runs.
#[derive(Debug, Clone)]
pub struct PeriodicConfig {
    /// Tick period (ns), e.g. 1_000_000 for 1 kHz.
    pub period_ns: u64,
    /// How long to run (ns).
    pub duration_ns: u64,
    /// Core to pin the thread to (None: leave it to the scheduler).
    pub core: Option<usize>,
    /// SCHED_FIFO priority to ask for (None: SCHED_OTHER). Falls back to SCHED_OTHER when refused.
    pub fifo_priority: Option<i32>,
}

/// What the periodic thread measured.
#[derive(Debug, Clone)]
pub struct PeriodicStats {
    /// Wake-up lateness: actual wake-up − deadline (ns).
    pub lateness: Histogram<u64>,
    /// Tick body duration (ns).
    pub compute: Histogram<u64>,
    /// Ticks run.
    pub ticks: u64,
    /// Ticks whose work ended after the next tick's deadline.
    pub overruns: u64,
    /// Deadlines skipped because an overrun passed them.
    pub skipped: u64,
    /// Whether pinning to the requested core worked.
    pub pinned: bool,
    /// `SCHED_FIFO(prio)` or `SCHED_OTHER`.
    pub policy: String,
}

/// Asks for SCHED_FIFO at `prio` for the calling thread; returns the policy in effect.
pub fn set_fifo(prio: Option<i32>) -> String {
    let Some(prio) = prio else {
        return "SCHED_OTHER".into();
    };
    let param = libc::sched_param {
        sched_priority: prio,
    };
    // SAFETY: pthread_self() is the calling thread; `param` is a valid sched_param.
    let rc = unsafe { libc::pthread_setschedparam(libc::pthread_self(), libc::SCHED_FIFO, &param) };
    if rc == 0 {
        format!("SCHED_FIFO({prio})")
    } else {
        "SCHED_OTHER (SCHED_FIFO refused)".into()
    }
}

/// Pins the calling thread to `core`; false if that core does not exist or pinning failed.
pub fn pin_to(core: usize) -> bool {
    core_affinity::get_core_ids()
        .and_then(|ids| ids.into_iter().find(|c| c.id == core))
        .is_some_and(core_affinity::set_for_current)
}

/// Runs `body` every `period_ns` on absolute deadlines for `duration_ns` in a new thread (pinned,
/// SCHED_FIFO if allowed) and returns the measurements and the body. `stop` ends it early.
pub fn run_periodic<T: TickBody + 'static>(
    cfg: &PeriodicConfig,
    mut body: T,
    stop: Arc<AtomicBool>,
) -> Result<(PeriodicStats, T), BenchError> {
    if cfg.period_ns == 0 {
        return Err(BenchError::Option("period must be > 0".into()));
    }
    let cfg = cfg.clone();
    let handle = std::thread::Builder::new()
        .name("chunkrt-periodic".into())
        .spawn(move || {
            let pinned = cfg.core.is_some_and(pin_to);
            let policy = set_fifo(cfg.fifo_priority);
            // Everything the loop touches is allocated here, before the first deadline.
            let mut lateness = latency_histogram();
            let mut compute = latency_histogram();
            let (mut ticks, mut overruns, mut skipped) = (0u64, 0u64, 0u64);
            let period = cfg.period_ns;
            let start = monotonic_ns() + period;
            let end = start + cfg.duration_ns;
            let mut deadline = start;
            while deadline < end && !stop.load(Ordering::Relaxed) {
                sleep_until_ns(deadline);
                let woke = monotonic_ns();
                lateness.saturating_record(woke.saturating_sub(deadline));
                body.tick(ticks, deadline);
                let done = monotonic_ns();
                compute.saturating_record(done - woke);
                ticks += 1;
                deadline += period;
                if done > deadline {
                    overruns += 1;
                    // Deadlines already passed are skipped, not run back to back.
                    let behind = (done - deadline) / period;
                    // only the deadlines inside the window count: a late last tick must not
                    // skip deadlines the window never had
                    let left = end.saturating_sub(deadline).div_ceil(period);
                    skipped += behind.min(left);
                    deadline += behind * period;
                }
            }
            (
                PeriodicStats {
                    lateness,
                    compute,
                    ticks,
                    overruns,
                    skipped,
                    pinned,
                    policy,
                },
                body,
            )
        })
        .map_err(|e| BenchError::Thread(e.to_string()))?;
    handle
        .join()
        .map_err(|_| BenchError::Thread("periodic thread panicked".into()))
}

/// A scripted test double of a control tick (until the real one lands): evaluates a cubic
/// between two 16-joint waypoints and clamps it to limits — a few hundred flops, no allocation.
#[derive(Debug, Clone)]
pub struct SyntheticTick {
    a: [f64; chunkrt_ipc::MAX_DOF],
    b: [f64; chunkrt_ipc::MAX_DOF],
    /// Last computed command (kept so the work is not optimised away).
    pub out: [f64; chunkrt_ipc::MAX_DOF],
}

impl Default for SyntheticTick {
    fn default() -> Self {
        let mut a = [0.0; chunkrt_ipc::MAX_DOF];
        let mut b = [0.0; chunkrt_ipc::MAX_DOF];
        for j in 0..chunkrt_ipc::MAX_DOF {
            a[j] = j as f64 * 0.1;
            b[j] = -(j as f64) * 0.05 + 0.3;
        }
        Self {
            a,
            b,
            out: [0.0; chunkrt_ipc::MAX_DOF],
        }
    }
}

impl TickBody for SyntheticTick {
    fn tick(&mut self, index: u64, _deadline_ns: u64) {
        let s = (index % 20) as f64 / 20.0;
        let h = s * s * (3.0 - 2.0 * s);
        for j in 0..chunkrt_ipc::MAX_DOF {
            let v = self.a[j] + (self.b[j] - self.a[j]) * h;
            self.out[j] = std::hint::black_box(v.clamp(-2.5, 2.5));
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn runs_on_deadlines_and_counts_overruns() {
        let stop = Arc::new(AtomicBool::new(false));
        let cfg = PeriodicConfig {
            period_ns: 2_000_000,
            duration_ns: 200_000_000,
            core: None,
            fifo_priority: None,
        };
        let (st, body) =
            run_periodic(&cfg, SyntheticTick::default(), stop.clone()).expect("thread runs");
        // every one of the 100 deadlines is run or skipped (a loaded 2-core machine may miss
        // wake-ups), none twice, and the loop really ran
        assert!(
            (99..=101).contains(&(st.ticks + st.skipped)) && st.ticks <= 100 && st.ticks >= 5,
            "{st:?}"
        );
        assert_eq!(st.lateness.len(), st.ticks);
        assert!(body.out.iter().any(|v| *v != 0.0));
        // A body slower than the period overruns every tick and skips deadlines.
        let slow = |_: u64, _: u64| std::thread::sleep(std::time::Duration::from_millis(5));
        let cfg = PeriodicConfig {
            duration_ns: 100_000_000,
            ..cfg
        };
        let (st, _) = run_periodic(&cfg, slow, stop).expect("thread runs");
        assert_eq!(st.overruns, st.ticks);
        assert!(st.skipped >= st.ticks, "{st:?}");
    }
}
