//! `replace`: a new chunk takes over at its first action that is not yet due.

use super::{Sampling, Transition};
use crate::chunk::ActionChunk;
use crate::control::interp;

pub(crate) struct Replace;

/// Time of the first action of `chunk` due at or after `now`.
pub(super) fn first_due(chunk: &ActionChunk, now: i64, s: &Sampling) -> i64 {
    let k = interp::first_due_at_or_after(chunk, now, s.offset_ns);
    interp::start_ns(chunk, s.offset_ns) + k as i64 * chunk.period_ns as i64
}

impl Transition for Replace {
    fn active_from(&self, chunk: &ActionChunk, now: i64, s: &Sampling) -> i64 {
        first_due(chunk, now, s)
    }
}
