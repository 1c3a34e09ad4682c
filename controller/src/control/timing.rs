//! Tick timing: wake-up lateness and compute time in fixed-bound HdrHistograms (no
//! auto-resize, so recording never allocates), overrun counting, summaries and the
//! HdrHistogram interval log.

use hdrhistogram::serialization::interval_log::{IntervalLogWriterBuilder, Tag};
use hdrhistogram::serialization::V2Serializer;
use hdrhistogram::Histogram;

/// Largest recordable value (ns): 10 s. Larger values are saturated to it.
pub const HIST_MAX_NS: u64 = 10_000_000_000;

/// Lateness / compute histograms of the control loop.
#[derive(Debug, Clone)]
pub struct TickTiming {
    /// Wake-up lateness (ns).
    pub lateness: Histogram<u64>,
    /// Compute time of a tick (ns).
    pub compute: Histogram<u64>,
    /// Ticks whose work ended after the next tick's scheduled time.
    pub overruns: u64,
    /// Current run of consecutive overruns.
    pub overrun_streak: u32,
    /// When the first timing was recorded (ns; interval log start).
    pub started_ns: u64,
    /// When the last timing was recorded (ns).
    pub last_ns: u64,
}

/// p50 / p99 / max of one histogram (ns).
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct Quantiles {
    pub p50: u64,
    pub p99: u64,
    pub max: u64,
}

impl Quantiles {
    fn of(h: &Histogram<u64>) -> Self {
        if h.is_empty() {
            return Self::default();
        }
        Self {
            p50: h.value_at_quantile(0.5),
            p99: h.value_at_quantile(0.99),
            max: h.max(),
        }
    }
}

impl TickTiming {
    /// Allocates both histograms (1 ns .. 10 s, 3 significant digits).
    pub fn new() -> Self {
        let mk = || {
            let mut h = Histogram::<u64>::new_with_bounds(1, HIST_MAX_NS, 3)
                .expect("constant, valid histogram bounds");
            h.auto(false);
            h
        };
        Self {
            lateness: mk(),
            compute: mk(),
            overruns: 0,
            overrun_streak: 0,
            started_ns: 0,
            last_ns: 0,
        }
    }

    /// Records one tick: it was scheduled for `scheduled_ns`, woke at `woke_ns` and finished
    /// its work (including publishing) at `done_ns`; the next tick is due at
    /// `scheduled_ns + period_ns`. Returns whether the tick overran. No allocation.
    pub fn record(
        &mut self,
        scheduled_ns: u64,
        woke_ns: u64,
        done_ns: u64,
        period_ns: u64,
    ) -> bool {
        if self.started_ns == 0 {
            self.started_ns = scheduled_ns;
        }
        self.last_ns = done_ns;
        self.lateness
            .saturating_record(woke_ns.saturating_sub(scheduled_ns).clamp(1, HIST_MAX_NS));
        self.compute
            .saturating_record(done_ns.saturating_sub(woke_ns).clamp(1, HIST_MAX_NS));
        let overrun = done_ns > scheduled_ns.saturating_add(period_ns);
        if overrun {
            self.overruns += 1;
            self.overrun_streak = self.overrun_streak.saturating_add(1);
        } else {
            self.overrun_streak = 0;
        }
        overrun
    }

    /// Lateness p50 / p99 / max (ns).
    pub fn lateness_quantiles(&self) -> Quantiles {
        Quantiles::of(&self.lateness)
    }

    /// Compute-time p50 / p99 / max (ns).
    pub fn compute_quantiles(&self) -> Quantiles {
        Quantiles::of(&self.compute)
    }

    /// One log line (allocates; call it off the tick).
    pub fn summary_line(&self) -> String {
        let l = self.lateness_quantiles();
        let c = self.compute_quantiles();
        format!(
            "ticks={} lateness p50/p99/max = {:.1}/{:.1}/{:.1} us, compute p50/p99/max = {:.1}/{:.1}/{:.1} us, overruns={}",
            self.lateness.len(),
            l.p50 as f64 / 1e3,
            l.p99 as f64 / 1e3,
            l.max as f64 / 1e3,
            c.p50 as f64 / 1e3,
            c.p99 as f64 / 1e3,
            c.max as f64 / 1e3,
            self.overruns
        )
    }

    /// Writes both histograms as an HdrHistogram interval log (tags `lateness` and `compute`,
    /// values in ns) covering the whole run.
    pub fn write_interval_log<W: std::io::Write>(&self, w: &mut W) -> std::io::Result<()> {
        let mut ser = V2Serializer::new();
        let mut log = IntervalLogWriterBuilder::new()
            .add_comment("chunkrt control loop: wake-up lateness and compute time, ns")
            .with_max_value_divisor(1.0)
            .begin_log_with(w, &mut ser)?;
        let dur = std::time::Duration::from_nanos(self.last_ns.saturating_sub(self.started_ns));
        let st = std::time::Duration::from_nanos(self.started_ns);
        for (name, h) in [("lateness", &self.lateness), ("compute", &self.compute)] {
            let tag = Tag::new(name); // names without spaces or commas: always Some
            log.write_histogram(h, st, dur, tag)
                .map_err(|e| std::io::Error::other(format!("{e:?}")))?;
        }
        Ok(())
    }
}

impl Default for TickTiming {
    fn default() -> Self {
        Self::new()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn records_quantiles_and_overruns() {
        let mut t = TickTiming::new();
        let p = 1_000_000;
        for i in 0..100u64 {
            let s = i * p;
            let over = t.record(s, s + 10_000 + i, s + 50_000, p);
            assert!(!over);
        }
        assert!(t.record(200 * p, 200 * p + 1000, 202 * p, p));
        assert!(t.record(201 * p, 201 * p + 1000, 203 * p, p));
        assert_eq!(t.overruns, 2);
        assert_eq!(t.overrun_streak, 2);
        t.record(300 * p, 300 * p, 300 * p + 1, p);
        assert_eq!(t.overrun_streak, 0);
        let l = t.lateness_quantiles();
        assert!((10_000..=10_200).contains(&l.p50), "{l:?}");
        let c = t.compute_quantiles();
        assert!(c.max >= 2 * p - 1000 - 2000, "{c:?}");
        assert!(t.summary_line().contains("overruns=2"));
        // huge values saturate instead of failing
        t.record(0, u64::MAX / 2, u64::MAX / 2, p);
        let mut buf = Vec::new();
        t.write_interval_log(&mut buf).expect("in-memory write");
        let text = String::from_utf8(buf).expect("ascii log");
        assert!(
            text.contains("Tag=lateness") && text.contains("Tag=compute"),
            "{text}"
        );
    }
}
