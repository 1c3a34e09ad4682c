//! `replace`: a new chunk takes over at its first action that is not yet due.

use super::{first_due, Sampling, Transition};
use crate::chunk::ActionChunk;

pub(crate) struct Replace;

impl Transition for Replace {
    fn active_from(&self, chunk: &ActionChunk, now: i64, s: &Sampling) -> i64 {
        first_due(chunk, now, s)
    }
}
