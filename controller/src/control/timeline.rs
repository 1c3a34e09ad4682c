//! The chunk timeline: chunks received from the inference thread, validated, placed in time by
//! the strategy, pruned when expired or superseded, and handed back to the inference thread
//! for reuse (allocation-free hand-off). Also the inference-delay estimate, observed as chunks
//! land.
//!
//! Owns: the chunks in effect and the strategy. Must not depend on: the safety state machine,
//! ruckig, IPC.

use std::collections::VecDeque;

use crate::config::Config;
use chunkrt_ipc::MAX_DOF;

use super::handoff::ChunkReceiver;
use super::interp::{self, Sample};
use super::rtc::DelayEstimator;
use super::safety::Reason;
use super::strategy::{current, Sampling, Slot, Transitions};
use crate::chunk::{ActionChunk, ChunkError};

const CHUNK_SLOTS: usize = 16;
const GRAVEYARD: usize = 32;

pub(crate) struct Timeline {
    slots: VecDeque<Slot>,
    /// Chunks the inference side could not take back yet (its recycling queue was full).
    graveyard: Vec<ActionChunk>,
    rx: ChunkReceiver,
    transitions: Transitions,
    pub sampling: Sampling,
    delay: DelayEstimator,
    /// Chunks accepted / rejected so far.
    pub received: u64,
    pub rejected: u64,
    /// A chunk was ever accepted.
    pub had_chunk: bool,
    /// The last chunk was rejected (why); cleared by the next good one.
    pub bad_input: Option<Reason>,
    /// Observation → chunk ready of the last accepted chunk (ns).
    pub last_inference_latency_ns: u64,
}

impl Timeline {
    /// An empty timeline for `config`'s first `n` joints (`step`: their step channels),
    /// receiving from `rx`; allocates everything it will need.
    pub fn new(config: &Config, n: usize, step: [bool; MAX_DOF], rx: ChunkReceiver) -> Self {
        let e = &config.execution;
        Self {
            slots: VecDeque::with_capacity(CHUNK_SLOTS),
            graveyard: Vec::with_capacity(GRAVEYARD),
            rx,
            transitions: Transitions::new(config),
            sampling: Sampling {
                n,
                offset_ns: (e.offset_ms * 1e6).round() as i64,
                interp: e.interpolation,
                step,
            },
            delay: DelayEstimator::new(e.delay_buffer, e.initial_delay_steps),
            received: 0,
            rejected: 0,
            had_chunk: false,
            bad_input: None,
            last_inference_latency_ns: 0,
        }
    }

    /// Takes in every chunk the inference thread sent, then drops expired and superseded ones.
    /// True when a chunk (good or bad) arrived.
    pub fn receive(&mut self, now_ns: u64) -> bool {
        self.flush_graveyard();
        let mut arrived = false;
        while let Some(c) = self.rx.try_recv() {
            self.accept(c, now_ns);
            arrived = true;
        }
        self.prune(now_ns as i64);
        arrived
    }

    /// Samples the strategy's target at `now` into `target`; returns the primary chunk's
    /// (id, observation_seq).
    pub fn evaluate(
        &self,
        now: i64,
        target: &mut Sample,
        scratch: &mut Sample,
    ) -> Option<(u64, u64)> {
        self.transitions
            .get()
            .evaluate(&self.slots, now, &self.sampling, target, scratch)
    }

    /// The newest chunk received.
    pub fn newest(&self) -> Option<&ActionChunk> {
        self.slots.back().map(|s| &s.chunk)
    }

    /// How requests ask the next chunk to continue the current one.
    pub fn continuation(&self) -> super::rtc::Continuation {
        self.transitions.get().continuation()
    }

    /// The current inference-delay estimate d (action steps).
    pub fn delay_estimate(&self) -> usize {
        self.delay.estimate()
    }

    /// Validates `chunk` and places it in time according to the strategy. A bad chunk is
    /// counted, remembered as the input problem, and nothing before it is executed either.
    pub fn accept(&mut self, chunk: ActionChunk, now_ns: u64) {
        let verdict = if chunk.n_dof == self.sampling.n {
            chunk.validate()
        } else {
            Err(ChunkError::NDof(chunk.n_dof))
        };
        if let Err(e) = verdict {
            self.rejected += 1;
            self.bad_input = Some(match e {
                ChunkError::NonFinite { .. } => Reason::NonFiniteAction,
                _ => Reason::BadChunk,
            });
            self.dispose(chunk);
            while let Some(s) = self.slots.pop_front() {
                self.dispose(s.chunk);
            }
            return;
        }
        self.received += 1;
        self.had_chunk = true;
        self.bad_input = None;
        let now = now_ns as i64;
        let off = self.sampling.offset_ns;
        // the delay is counted from the observation, not from a future-state chunk's start
        let age = (now - (chunk.t_obs_ns as i64 + off)).max(0) as u64;
        self.delay.observe(age.div_ceil(chunk.period_ns) as usize);
        self.last_inference_latency_ns = chunk.ready_ns.saturating_sub(chunk.t_obs_ns);
        let active_from = if chunk.start_shift_ns > 0 {
            // a future-state chunk was made to start where the robot is when it lands: at once
            now.max(interp::start_ns(&chunk, off))
        } else {
            self.transitions
                .get()
                .active_from(&chunk, now, &self.sampling)
        };
        if self.slots.len() == self.slots.capacity().min(CHUNK_SLOTS) {
            if let Some(old) = self.slots.pop_front() {
                self.dispose(old.chunk);
            }
        }
        self.slots.push_back(Slot { chunk, active_from });
    }

    fn prune(&mut self, now: i64) {
        // Expired chunks go first.
        let mut i = 0;
        while i < self.slots.len() {
            if interp::end_ns(&self.slots[i].chunk, self.sampling.offset_ns) < now {
                if let Some(s) = self.slots.remove(i) {
                    self.dispose(s.chunk);
                }
            } else {
                i += 1;
            }
        }
        // Then the chunks superseded by the one in effect, but those the strategy keeps.
        let Some(ic) = current(&self.slots, now) else {
            return;
        };
        let Some(keep) = self.transitions.get().keep_before(&self.slots[ic], now) else {
            return;
        };
        for _ in 0..ic.saturating_sub(keep) {
            if let Some(s) = self.slots.pop_front() {
                self.dispose(s.chunk);
            }
        }
    }

    fn dispose(&mut self, c: ActionChunk) {
        if let Err(c) = self.rx.recycle(c) {
            if self.graveyard.len() < self.graveyard.capacity() {
                self.graveyard.push(c);
            }
            // else: dropped here (frees) — only if the inference side stopped recycling.
        }
    }

    fn flush_graveyard(&mut self) {
        while let Some(c) = self.graveyard.pop() {
            if let Err(c) = self.rx.recycle(c) {
                self.graveyard.push(c);
                break;
            }
        }
    }
}
