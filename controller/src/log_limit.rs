//! Rate-limited logging of repeated events: the first event of a kind in a window is logged in
//! full, the rest of that window are counted, and one summary line per kind says how many were
//! held back (and the last of them). A flood of malformed messages at 10 kHz then costs one or
//! two lines per reason per second, not a thousand.

use std::collections::HashMap;
use std::time::{Duration, Instant};

/// Per-kind windows of held-back events.
#[derive(Debug)]
pub struct LogLimiter {
    window: Duration,
    kinds: HashMap<String, Held>,
}

#[derive(Debug)]
struct Held {
    since: Instant,
    count: u64,
    last: String,
}

/// Kinds remembered at most (a hostile peer cannot grow the table without bound).
const MAX_KINDS: usize = 256;

impl LogLimiter {
    /// One full line per kind per `window`.
    pub fn new(window: Duration) -> Self {
        Self {
            window,
            kinds: HashMap::new(),
        }
    }

    /// Whether an event of `kind` at `now` is logged in full (`true`), or held back and counted
    /// with `message` as the latest (`false`).
    pub fn admit(&mut self, kind: &str, message: impl FnOnce() -> String, now: Instant) -> bool {
        match self.kinds.get_mut(kind) {
            Some(h) if now.duration_since(h.since) < self.window => {
                h.count += 1;
                h.last = message();
                false
            }
            Some(h) if h.count > 0 => {
                // the window is over but not yet flushed: held back with it
                h.count += 1;
                h.last = message();
                false
            }
            Some(h) => {
                // a new window, its first event in full
                h.since = now;
                true
            }
            None => {
                if self.kinds.len() < MAX_KINDS {
                    self.kinds.insert(
                        kind.to_string(),
                        Held {
                            since: now,
                            count: 0,
                            last: String::new(),
                        },
                    );
                }
                true
            }
        }
    }

    /// Calls `emit(kind, held_back, last)` for every kind whose window has ended with events
    /// held back, and starts its next window.
    pub fn flush(&mut self, now: Instant, mut emit: impl FnMut(&str, u64, &str)) {
        for (kind, h) in self.kinds.iter_mut() {
            if h.count > 0 && now.duration_since(h.since) >= self.window {
                emit(kind, h.count, &h.last);
                h.count = 0;
                h.since = now;
            }
        }
        // kinds quiet for a while are forgotten (their next event is logged in full)
        let window = self.window;
        self.kinds
            .retain(|_, h| h.count > 0 || now.duration_since(h.since) < 10 * window);
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_flood_is_one_line_and_a_summary_per_kind_and_window() {
        let mut l = LogLimiter::new(Duration::from_secs(1));
        let t0 = Instant::now();
        let mut logged = 0;
        // 1000 events of one kind and 10 of another within 0.5 s
        for i in 0..1000u64 {
            let now = t0 + Duration::from_micros(i * 500);
            logged += l.admit("stale", || format!("stale #{i}"), now) as u32;
            if i % 100 == 0 {
                logged += l.admit("nan", || "nan".into(), now) as u32;
            }
        }
        assert_eq!(logged, 2, "one full line per kind");
        let mut summaries = Vec::new();
        l.flush(t0 + Duration::from_millis(600), |k, n, _| {
            summaries.push((k.to_string(), n))
        });
        assert!(summaries.is_empty(), "the window is not over yet");
        l.flush(t0 + Duration::from_millis(1001), |k, n, last| {
            summaries.push((k.to_string(), n));
            if k == "stale" {
                assert_eq!(last, "stale #999");
            }
        });
        summaries.sort();
        assert_eq!(
            summaries,
            vec![("nan".to_string(), 9), ("stale".to_string(), 999)]
        );
        // the next window holds back again, after its first event... which was summarised,
        // so a new event right after the flush is held until that window ends
        assert!(!l.admit("stale", || "x".into(), t0 + Duration::from_millis(1002)));
        // a kind quiet for longer than a window is logged in full again
        let late = t0 + Duration::from_secs(30);
        l.flush(late, |_, _, _| {});
        assert!(l.admit("stale", || "y".into(), late + Duration::from_secs(1)));
    }
}
