//! `rtc`: real-time chunking. A new chunk takes over at once, at the index real time has
//! reached; continuity comes from the guided sampler (the request carries the actions still to
//! be executed and the guidance weights), not from a blend.

use std::collections::VecDeque;

use super::{sample_current, Sampling, Slot, Transition};
use crate::chunk::ActionChunk;
use crate::control::interp::Sample;

pub(crate) struct Rtc;

impl Transition for Rtc {
    fn active_from(&self, _chunk: &ActionChunk, now: i64, _s: &Sampling) -> i64 {
        now
    }

    fn evaluate(
        &self,
        slots: &VecDeque<Slot>,
        now: i64,
        s: &Sampling,
        target: &mut Sample,
        _scratch: &mut Sample,
    ) -> Option<(u64, u64)> {
        sample_current(slots, now, s, target).map(|(_, primary)| primary)
    }

    fn guided(&self) -> bool {
        true
    }
}
