//! `crossfade`: a new chunk takes over where `replace` would switch, blended in from the old
//! one over a window with a smoothstep weight (position, velocity and acceleration of the blend
//! are exact: the weight is differentiated twice).

use std::collections::VecDeque;

use super::{first_due, sample_current, Sampling, Slot, Transition};
use crate::chunk::ActionChunk;
use crate::control::interp::{Coverage, Sample};

pub(crate) struct Crossfade {
    /// Blend window (ns).
    pub window_ns: i64,
}

impl Transition for Crossfade {
    fn active_from(&self, chunk: &ActionChunk, now: i64, s: &Sampling) -> i64 {
        first_due(chunk, now, s)
    }

    /// The predecessor stays during the blend window.
    fn keep_before(&self, current: &Slot, now: i64) -> Option<usize> {
        Some(usize::from(now < current.active_from + self.window_ns))
    }

    #[allow(clippy::needless_range_loop)] // joints index several parallel arrays
    fn evaluate(
        &self,
        slots: &VecDeque<Slot>,
        now: i64,
        s: &Sampling,
        target: &mut Sample,
        scratch: &mut Sample,
    ) -> Option<(u64, u64)> {
        let (ic, primary) = sample_current(slots, now, s, target)?;
        let since = now - slots[ic].active_from;
        if ic == 0 || self.window_ns <= 0 || since >= self.window_ns {
            return Some(primary);
        }
        if s.sample(&slots[ic - 1].chunk, now, scratch) != Coverage::Inside {
            return Some(primary);
        }
        let x = since as f64 / self.window_ns as f64;
        let period = self.window_ns as f64 * 1e-9;
        // smoothstep w and its time derivatives
        let w = x * x * (3.0 - 2.0 * x);
        let dw = 6.0 * x * (1.0 - x) / period;
        let ddw = 6.0 * (1.0 - 2.0 * x) / (period * period);
        let (t, p) = (target, &*scratch);
        for j in 0..s.n {
            if s.step[j] {
                continue; // step channels come from the new chunk
            }
            // p + w·d with d = new − old, differentiated twice
            let d = t.position[j] - p.position[j];
            let dv = t.velocity[j] - p.velocity[j];
            let da = t.acceleration[j] - p.acceleration[j];
            t.position[j] = p.position[j] + w * d;
            t.velocity[j] = p.velocity[j] + w * dv + dw * d;
            t.acceleration[j] = p.acceleration[j] + w * da + 2.0 * dw * dv + ddw * d;
        }
        Some(primary)
    }
}
