//! `rtc`: real-time chunking. A new chunk takes over at once, at the index real time has
//! reached; continuity comes from the guided sampler (the request carries the actions still to
//! be executed and the guidance weights), not from a blend.

use super::{Sampling, Transition};
use crate::chunk::ActionChunk;

pub(crate) struct Rtc;

impl Transition for Rtc {
    fn active_from(&self, _chunk: &ActionChunk, now: i64, _s: &Sampling) -> i64 {
        now
    }

    fn guided(&self) -> bool {
        true
    }
}
