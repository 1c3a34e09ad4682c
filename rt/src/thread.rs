//! Thread set-up for real time: pinning, SCHED_FIFO, mlockall, the CPUs' wake-up latency, and
//! the periodic loop.
//!
//! Each step is attempted and its outcome reported; none is fatal, because a development
//! machine or a container often forbids SCHED_FIFO and mlockall. The control thread then runs
//! as an ordinary pinned thread, and the log says so in one line.

use std::fmt;

/// What [`make_current_thread_realtime`] achieved.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct RtOutcome {
    /// Core the thread is pinned to, or why not.
    pub pinned: Result<usize, String>,
    /// SCHED_FIFO priority set, or why not (`Err("disabled")` when priority 0 was asked).
    pub fifo: Result<i32, String>,
    /// mlockall outcome.
    pub locked: Result<(), String>,
    /// The CPUs' wake-up latency held at 0 µs (`/dev/cpu_dma_latency`), or why not.
    pub wakeup: Result<(), String>,
}

impl RtOutcome {
    /// True when every real-time measure took effect.
    pub fn fully_realtime(&self) -> bool {
        self.pinned.is_ok() && self.fifo.is_ok() && self.locked.is_ok()
    }
}

impl fmt::Display for RtOutcome {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match &self.pinned {
            Ok(c) => write!(f, "pinned to core {c}")?,
            Err(e) => write!(f, "not pinned ({e})")?,
        }
        match &self.fifo {
            Ok(p) => write!(f, ", SCHED_FIFO priority {p}")?,
            Err(e) => write!(f, ", SCHED_OTHER ({e})")?,
        }
        match &self.locked {
            Ok(()) => write!(f, ", memory locked")?,
            Err(e) => write!(f, ", memory not locked ({e})")?,
        }
        match &self.wakeup {
            Ok(()) => write!(f, ", CPU wake-up latency held at 0 µs"),
            Err(e) => write!(f, ", CPU idle states left as they are ({e})"),
        }
    }
}

/// Number of cores this process may run on.
pub fn available_cores() -> usize {
    core_affinity::get_core_ids().map(|c| c.len()).unwrap_or(1)
}

/// The core the control thread uses by default: the last one (the first usually takes
/// interrupts and housekeeping).
pub fn default_control_core() -> usize {
    available_cores().saturating_sub(1)
}

/// Pins the calling thread to `core` (an index into the allowed cores).
pub fn pin_current_thread(core: usize) -> Result<usize, String> {
    let ids = core_affinity::get_core_ids().ok_or("cannot list cores")?;
    let id = ids
        .get(core)
        .copied()
        .ok_or_else(|| format!("core {core} not available ({} cores)", ids.len()))?;
    if core_affinity::set_for_current(id) {
        Ok(id.id)
    } else {
        Err(format!("sched_setaffinity to core {} refused", id.id))
    }
}

fn errno_string() -> String {
    std::io::Error::last_os_error().to_string()
}

/// Sets SCHED_FIFO with `priority` for the calling thread.
pub fn set_current_thread_fifo(priority: i32) -> Result<i32, String> {
    if priority <= 0 {
        return Err("disabled in config".to_string());
    }
    let param = libc::sched_param {
        sched_priority: priority,
    };
    // SAFETY: plain syscall wrapper on the calling thread with a valid parameter struct.
    let rc = unsafe { libc::pthread_setschedparam(libc::pthread_self(), libc::SCHED_FIFO, &param) };
    if rc == 0 {
        Ok(priority)
    } else {
        Err(format!(
            "SCHED_FIFO refused: {}",
            std::io::Error::from_raw_os_error(rc)
        ))
    }
}

/// Locks current and future pages in RAM so page faults cannot stall the control thread.
pub fn lock_memory() -> Result<(), String> {
    // SAFETY: mlockall has no memory-safety preconditions.
    let rc = unsafe { libc::mlockall(libc::MCL_CURRENT | libc::MCL_FUTURE) };
    if rc == 0 {
        Ok(())
    } else {
        Err(format!("mlockall refused: {}", errno_string()))
    }
}

/// Asks the kernel to keep every CPU's wake-up latency at 0 µs while this process lives (PM QoS:
/// `/dev/cpu_dma_latency` holds while the file is open), as `cyclictest` does by default: no
/// deep idle state, and in a virtual machine no halted vCPU that the host has to schedule again
/// before the control thread can run. Without it the control thread was late by ≥ 1 period 0.014 %
/// of its ticks where `cyclictest` beside it was late 0–0.002 % (BENCHMARKS §2b).
fn hold_wakeup_latency() -> Result<(), String> {
    use std::io::Write;
    static HELD: std::sync::OnceLock<std::fs::File> = std::sync::OnceLock::new();
    if HELD.get().is_some() {
        return Ok(());
    }
    let mut f = std::fs::OpenOptions::new()
        .write(true)
        .open("/dev/cpu_dma_latency")
        .map_err(|e| format!("/dev/cpu_dma_latency: {e}"))?;
    f.write_all(&0i32.to_ne_bytes())
        .map_err(|e| format!("/dev/cpu_dma_latency: {e}"))?;
    let _ = HELD.set(f);
    Ok(())
}

/// Touches `bytes` of stack so the control thread never faults a stack page mid-tick.
#[inline(never)]
pub fn prefault_stack(bytes: usize) {
    const CHUNK: usize = 16 * 1024;
    fn touch(depth: usize) {
        let mut buf = [0u8; CHUNK];
        // volatile write: the compiler must not remove the buffer
        // SAFETY: `buf` is a valid local array.
        unsafe { std::ptr::write_volatile(buf.as_mut_ptr(), 1) };
        if depth > 1 {
            touch(depth - 1);
        }
        std::hint::black_box(&buf);
    }
    touch(bytes.div_ceil(CHUNK).max(1));
}

/// Applies every real-time measure to the calling thread and reports what took effect.
pub fn make_current_thread_realtime(core: Option<usize>, priority: i32, lock: bool) -> RtOutcome {
    let pinned = pin_current_thread(core.unwrap_or_else(default_control_core));
    let fifo = set_current_thread_fifo(priority);
    let locked = if lock {
        lock_memory()
    } else {
        Err("disabled in config".to_string())
    };
    prefault_stack(256 * 1024);
    let wakeup = if priority > 0 {
        hold_wakeup_latency()
    } else {
        Err("not real-time".to_string())
    };
    RtOutcome {
        pinned,
        fifo,
        locked,
        wakeup,
    }
}

/// CLOCK_MONOTONIC now, in nanoseconds: the time base of every chunkrt message
/// (`chunkrt_ipc::monotonic_ns`, the same clock; repeated here so that this crate needs no IPC).
fn monotonic_ns() -> u64 {
    let mut ts = libc::timespec {
        tv_sec: 0,
        tv_nsec: 0,
    };
    // SAFETY: `ts` is a valid, writable timespec; CLOCK_MONOTONIC always exists on Linux.
    unsafe { libc::clock_gettime(libc::CLOCK_MONOTONIC, &mut ts) };
    ts.tv_sec as u64 * 1_000_000_000 + ts.tv_nsec as u64
}

/// Sleeps until the absolute CLOCK_MONOTONIC time `deadline_ns` (`chunkrt_ipc::sleep_until_ns`,
/// repeated here for the same reason).
fn sleep_until_ns(deadline_ns: u64) {
    let ts = libc::timespec {
        tv_sec: (deadline_ns / 1_000_000_000) as libc::time_t,
        tv_nsec: (deadline_ns % 1_000_000_000) as libc::c_long,
    };
    loop {
        // SAFETY: `ts` is a valid timespec; the remaining-time pointer may be null with
        // TIMER_ABSTIME.
        let rc = unsafe {
            libc::clock_nanosleep(
                libc::CLOCK_MONOTONIC,
                libc::TIMER_ABSTIME,
                &ts,
                core::ptr::null_mut(),
            )
        };
        if rc != libc::EINTR {
            break;
        }
    }
}

/// What [`run_periodic`] counted.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct PeriodicCounts {
    /// Ticks run.
    pub ticks: u64,
    /// Ticks whose work ended after the next tick's deadline.
    pub overruns: u64,
    /// Deadlines skipped because an overrun passed them (only those before `end_ns`).
    pub skipped: u64,
}

/// The control loop's schedule, shared by the controller's control thread and the
/// `control_loop` bench: sleeps to absolute `CLOCK_MONOTONIC` deadlines `first_deadline_ns +
/// k·period_ns` (so lateness never accumulates), calls `step(deadline, wake)` (which returns when
/// its work ended), and after a tick that ended past the next deadline skips the deadlines
/// already missed instead of running them back to back. Runs while `running()` and the next
/// deadline is before `end_ns`. No allocation.
pub fn run_periodic(
    period_ns: u64,
    first_deadline_ns: u64,
    end_ns: u64,
    running: impl Fn() -> bool,
    mut step: impl FnMut(u64, u64) -> u64,
) -> PeriodicCounts {
    let period = period_ns.max(1);
    let mut c = PeriodicCounts::default();
    let mut deadline = first_deadline_ns;
    while deadline < end_ns && running() {
        sleep_until_ns(deadline);
        let wake = monotonic_ns();
        let done = step(deadline, wake);
        c.ticks += 1;
        deadline += period;
        if done > deadline {
            c.overruns += 1;
            let behind = (done - deadline) / period;
            // only the deadlines inside the window count: a late last tick must not skip
            // deadlines the window never had
            let left = end_ns.saturating_sub(deadline).div_ceil(period);
            c.skipped += behind.min(left);
            deadline += behind * period;
        }
    }
    c
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn periodic_runs_on_deadlines_and_counts_overruns() {
        let period = 2_000_000;
        let first = monotonic_ns() + period;
        let end = first + 100 * period;
        let mut deadlines = Vec::with_capacity(200);
        let c = run_periodic(
            period,
            first,
            end,
            || true,
            |d, wake| {
                deadlines.push(d);
                assert!(wake >= d, "woke before its deadline");
                monotonic_ns()
            },
        );
        // every one of the 100 deadlines is run or skipped (a loaded 2-core machine may miss
        // wake-ups), none twice, each on the grid
        assert!(c.ticks + c.skipped == 100 && c.ticks >= 5, "{c:?}");
        assert!(deadlines
            .windows(2)
            .all(|w| w[1] > w[0] && (w[1] - w[0]) % period == 0));
        // a body slower than the period overruns every tick and skips deadlines
        let first = monotonic_ns() + period;
        let c = run_periodic(
            period,
            first,
            first + 50 * period,
            || true,
            |_, _| {
                std::thread::sleep(std::time::Duration::from_millis(5));
                monotonic_ns()
            },
        );
        assert_eq!(c.overruns, c.ticks);
        assert!(c.skipped >= c.ticks && c.ticks + c.skipped <= 50, "{c:?}");
        // `running` ends it
        let c = run_periodic(period, first, u64::MAX, || false, |_, w| w);
        assert_eq!(c, PeriodicCounts::default());
    }

    #[test]
    fn pinning_works_and_bad_core_is_an_error() {
        std::thread::spawn(|| {
            assert!(pin_current_thread(0).is_ok());
            let e = pin_current_thread(100_000).unwrap_err();
            assert!(e.contains("not available"), "{e}");
            assert!(set_current_thread_fifo(0).is_err());
            let out = make_current_thread_realtime(Some(0), 0, false);
            assert!(out.to_string().contains("pinned to core"), "{out}");
        })
        .join()
        .unwrap();
    }
}
