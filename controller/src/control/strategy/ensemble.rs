//! `temporal_ensemble`: ACT's temporal ensemble. Every chunk that covers now contributes,
//! the i-th oldest with weight exp(−m·i); step channels take the newest chunk's value.

use std::collections::VecDeque;

use super::{Sampling, Slot, Transition};
use crate::chunk::ActionChunk;
use crate::control::interp::{Coverage, Sample};

pub(crate) struct TemporalEnsemble {
    /// m, the weight decay per older chunk.
    pub decay: f64,
}

impl Transition for TemporalEnsemble {
    fn active_from(&self, _chunk: &ActionChunk, now: i64, _s: &Sampling) -> i64 {
        now
    }

    /// Every chunk stays until it expires.
    fn keep_before(&self, _current: &Slot, _now: i64) -> Option<usize> {
        None
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
        let mut wsum = 0.0;
        let mut rank = 0usize;
        let mut primary = None;
        let mut acc = Sample::default();
        for slot in slots {
            let c = &slot.chunk;
            if s.sample(c, now, scratch) != Coverage::Inside {
                continue;
            }
            // ACT: w_i = exp(-m·i), i = 0 for the oldest prediction.
            let w = (-self.decay * rank as f64).exp();
            rank += 1;
            wsum += w;
            for j in 0..s.n {
                if s.step[j] {
                    acc.position[j] = scratch.position[j]; // newest wins
                    continue;
                }
                acc.position[j] += w * scratch.position[j];
                acc.velocity[j] += w * scratch.velocity[j];
                acc.acceleration[j] += w * scratch.acceleration[j];
            }
            primary = Some((c.id, c.observation_seq));
        }
        if wsum <= 0.0 {
            return None;
        }
        for j in 0..s.n {
            if !s.step[j] {
                acc.position[j] /= wsum;
                acc.velocity[j] /= wsum;
                acc.acceleration[j] /= wsum;
            }
        }
        *target = acc;
        primary
    }
}
