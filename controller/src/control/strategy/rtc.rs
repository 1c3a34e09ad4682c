//! `rtc` and `rtc_trained`: real-time chunking. A new chunk takes over at once, at the index
//! real time has reached; continuity comes from the policy, not from a blend: the request
//! carries the actions still to be executed, which guide the sampler (`rtc`) or are given to a
//! policy trained to continue them (`rtc_trained`).

use super::{Sampling, Transition};
use crate::chunk::ActionChunk;
use crate::control::rtc::Continuation;

pub(crate) struct Rtc {
    /// Training-time RTC (`rtc_trained`) instead of guidance.
    pub trained: bool,
}

impl Transition for Rtc {
    fn active_from(&self, _chunk: &ActionChunk, now: i64, _s: &Sampling) -> i64 {
        now
    }

    fn continuation(&self) -> Continuation {
        if self.trained {
            Continuation::Committed
        } else {
            Continuation::Guided
        }
    }
}
