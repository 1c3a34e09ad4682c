//! The `control_loop` bench's harness: the controller's periodic loop ([`chunkrt_controller::rt::run_periodic`],
//! the one its control thread runs) on a thread of its own, measuring wake-up lateness (how long
//! after its deadline the thread ran) and compute time (how long the tick body took) into
//! histograms allocated before the loop starts. The tick body is pluggable ([`TickBody`]).

use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::Arc;

use chunkrt_ipc::monotonic_ns;
use hdrhistogram::Histogram;

use super::BenchError;
use crate::report::latency_histogram;
use chunkrt_controller::rt;

/// The work done every tick. Must not allocate, lock or do I/O other than IPC (rule 2). Built
/// on the ticking thread (iceoryx2 ports stay on the thread that made them), so not `Send`.
pub trait TickBody {
    /// Runs tick `index`, whose deadline (wake-up time) was `deadline_ns` (monotonic).
    fn tick(&mut self, index: u64, deadline_ns: u64);

    /// A line on what the body did, read after the last tick (default: nothing).
    fn report(&self) -> String {
        String::new()
    }
}

impl<F: FnMut(u64, u64)> TickBody for F {
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
    /// The body's [`TickBody::report`] after the last tick.
    pub body: String,
}

/// Builds a body with `make` in a new thread (pinned, SCHED_FIFO if allowed), runs it every
/// `period_ns` on absolute deadlines for `duration_ns` and returns the measurements. `stop`
/// ends it early. The
/// schedule is the controller's own ([`chunkrt_controller::rt::run_periodic`]), and so are the pinning and
/// the SCHED_FIFO request ([`chunkrt_controller::rt`]); this harness adds only the histograms.
pub fn run_periodic<T: TickBody>(
    cfg: &PeriodicConfig,
    make: impl FnOnce() -> Result<T, BenchError> + Send + 'static,
    stop: Arc<AtomicBool>,
) -> Result<PeriodicStats, BenchError> {
    if cfg.period_ns == 0 {
        return Err(BenchError::Option("period must be > 0".into()));
    }
    let cfg = cfg.clone();
    let handle = std::thread::Builder::new()
        .name("chunkrt-periodic".into())
        .spawn(move || {
            let pinned = cfg.core.is_some_and(|c| rt::pin_current_thread(c).is_ok());
            let policy = match cfg.fifo_priority.map(rt::set_current_thread_fifo) {
                Some(Ok(p)) => format!("SCHED_FIFO({p})"),
                Some(Err(_)) => "SCHED_OTHER (SCHED_FIFO refused)".to_string(),
                None => "SCHED_OTHER".to_string(),
            };
            // Everything the loop touches is allocated here, before the first deadline.
            let mut body = make()?;
            let mut lateness = latency_histogram();
            let mut compute = latency_histogram();
            let mut index = 0u64;
            let first = monotonic_ns() + cfg.period_ns;
            let counts = rt::run_periodic(
                cfg.period_ns,
                first,
                first + cfg.duration_ns,
                || !stop.load(Ordering::Relaxed),
                |deadline, woke| {
                    lateness.saturating_record(woke.saturating_sub(deadline));
                    body.tick(index, deadline);
                    index += 1;
                    let done = monotonic_ns();
                    compute.saturating_record(done - woke);
                    done
                },
            );
            Ok(PeriodicStats {
                lateness,
                compute,
                ticks: counts.ticks,
                overruns: counts.overruns,
                skipped: counts.skipped,
                pinned,
                policy,
                body: body.report(),
            })
        })
        .map_err(|e| BenchError::Thread(e.to_string()))?;
    handle
        .join()
        .map_err(|_| BenchError::Thread("periodic thread panicked".into()))?
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
        let out = Arc::new(std::sync::Mutex::new(0.0f64));
        let out2 = out.clone();
        let st = run_periodic(
            &cfg,
            move || {
                let mut t = SyntheticTick::default();
                Ok(move |i: u64, d: u64| {
                    t.tick(i, d);
                    *out2.lock().unwrap() = t.out[3];
                })
            },
            stop.clone(),
        )
        .expect("thread runs");
        // every one of the 100 deadlines is run or skipped (a loaded 2-core machine may miss
        // wake-ups), none twice, and the loop really ran
        assert!(
            (99..=101).contains(&(st.ticks + st.skipped)) && st.ticks <= 100 && st.ticks >= 5,
            "{st:?}"
        );
        assert_eq!(st.lateness.len(), st.ticks);
        assert!(*out.lock().unwrap() != 0.0, "the body ran");
        // A body slower than the period overruns every tick and skips deadlines.
        let slow = |_: u64, _: u64| std::thread::sleep(std::time::Duration::from_millis(5));
        let cfg = PeriodicConfig {
            duration_ns: 100_000_000,
            ..cfg
        };
        let st = run_periodic(&cfg, move || Ok(slow), stop).expect("thread runs");
        assert_eq!(st.overruns, st.ticks);
        assert!(st.skipped >= st.ticks, "{st:?}");
    }
}
