//! The inference protocol, written once: take the control side's request, ask the chunk source
//! for a chunk, hand the chunk over, recycle the buffers the control thread is done with.
//!
//! Every driver of a chunk source goes through [`InferenceWorker`]: the controller's
//! observation thread (real time, over IPC), the closed-loop episodes in simulated time (which
//! add their delivery delay, [`Delivery::After`]), the control-loop bench and the scripted test
//! harness. A new chunk source — the in-process policy, a remote openpi-protocol server, a test
//! double — plugs in here by implementing [`ChunkSource`].
//!
//! Runs in the inference thread (or a simulation's loop), never in the control thread.

use crate::chunk::ActionChunk;
use crate::contract::{ChunkSource, InferenceRequest, Observation};
use crate::control::InferenceLink;

/// When a computed chunk reaches the control side.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Delivery {
    /// As soon as it is computed (a real inference thread: the computation is the delay).
    Immediate,
    /// This long after the time of the request's turn, on the caller's clock (simulated time:
    /// the inference delay is set, not measured). The chunk's `ready_ns` is that time.
    After(u64),
    /// When the chunk's own `ready_ns` has come (a source that models its latency, as the
    /// scripted test double does).
    AtReady,
}

/// What one turn did.
#[derive(Debug)]
pub enum Turn {
    /// No request was pending.
    Idle,
    /// A chunk was computed (and handed over or queued for its delivery time).
    Chunk {
        /// Observation → chunk ready (ns).
        latency_ns: u64,
    },
    /// The source had nothing to execute, or made no request at all
    /// ([`crate::contract::NotAsked`]: a remote source waiting out its backoff; counted in
    /// [`WorkerStats::not_asked`], and the control side asks again).
    Nothing,
    /// The source failed; the request is answered (the control side asks again).
    Failed(anyhow::Error),
}

/// Counters of a worker.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct WorkerStats {
    /// Chunks computed.
    pub chunks: u64,
    /// Failed computations (requests a source made and that failed).
    pub failures: u64,
    /// Requests answered without asking the source's policy ([`crate::contract::NotAsked`]:
    /// a remote source backing off after a failure); not failures.
    pub not_asked: u64,
    /// Observation → ready of the newest chunk (ns).
    pub last_latency_ns: u64,
}

/// Sees every chunk a worker computes, with the inference delay (actions) its request was made
/// with, before the chunk is handed over (the controller publishes it on `NS/chunks`).
pub type ChunkTap = Box<dyn FnMut(&ActionChunk, usize)>;

/// The inference side of a controller's hand-offs.
pub struct InferenceWorker {
    link: InferenceLink,
    tap: Option<ChunkTap>,
    delivery: Delivery,
    /// Chunks waiting for their delivery time ([`Delivery::After`]), oldest first.
    pending: Vec<ActionChunk>,
    stats: WorkerStats,
}

impl InferenceWorker {
    /// A worker answering the requests of `link`.
    pub fn new(link: InferenceLink, delivery: Delivery) -> Self {
        Self {
            link,
            tap: None,
            delivery,
            pending: Vec::new(),
            stats: WorkerStats::default(),
        }
    }

    /// Shows every computed chunk to `tap` ([`ChunkTap`]).
    pub fn set_tap(&mut self, tap: ChunkTap) {
        self.tap = Some(tap);
    }

    /// The link (for its stale-camera mask).
    pub fn link(&self) -> &InferenceLink {
        &self.link
    }

    /// Counters so far.
    pub fn stats(&self) -> WorkerStats {
        self.stats
    }

    /// The next pending request, if any; answer it with [`Self::answer`] (a caller that has to
    /// prepare its observation first — render a frame — asks here before it does).
    pub fn next_request(&mut self) -> Option<Box<InferenceRequest>> {
        self.link.requests.try_recv()
    }

    /// Drops every pending request unanswered but acknowledged (a driver that asks on its own
    /// schedule, as openpi's synchronous broker does).
    pub fn discard_requests(&mut self) {
        while let Some(r) = self.link.requests.try_recv() {
            self.link.requests.done(r);
        }
    }

    /// Answers `request` at `now_ns`: the source computes a chunk for `obs`, which is handed
    /// over ([`Delivery`]); the request is acknowledged in every case.
    pub fn answer(
        &mut self,
        now_ns: u64,
        request: Box<InferenceRequest>,
        source: &mut dyn ChunkSource,
        obs: &Observation,
    ) -> Turn {
        let result = source.compute(obs, &request);
        let delay_steps = request.delay_steps;
        self.link.requests.done(request);
        match result {
            Ok(Some(chunk)) => {
                if let Some(tap) = self.tap.as_mut() {
                    tap(&chunk, delay_steps);
                }
                self.deliver(now_ns, chunk)
            }
            Ok(None) => Turn::Nothing,
            Err(e) => {
                // the control side asks again either way
                self.link
                    .failed_requests
                    .fetch_add(1, std::sync::atomic::Ordering::Relaxed);
                if e.downcast_ref::<crate::contract::NotAsked>().is_some() {
                    self.stats.not_asked += 1;
                    return Turn::Nothing;
                }
                self.stats.failures += 1;
                Turn::Failed(e)
            }
        }
    }

    /// One turn at `now_ns`: answers the pending request, if any ([`Self::answer`]), then hands
    /// over what is due and recycles ([`Self::poll`]).
    pub fn step(&mut self, now_ns: u64, source: &mut dyn ChunkSource, obs: &Observation) -> Turn {
        let turn = match self.next_request() {
            Some(r) => self.answer(now_ns, r, source, obs),
            None => Turn::Idle,
        };
        self.poll(now_ns);
        turn
    }

    /// Hands `chunk`, computed at `now_ns`, to the control side as [`Delivery`] says.
    pub fn deliver(&mut self, now_ns: u64, mut chunk: ActionChunk) -> Turn {
        if let Delivery::After(delay_ns) = self.delivery {
            chunk.ready_ns = now_ns + delay_ns;
        }
        let latency_ns = self.count(&chunk);
        match self.delivery {
            // a displaced, never-executed chunk comes back here and is dropped here
            Delivery::Immediate => drop(self.link.chunks.send(chunk)),
            Delivery::After(_) | Delivery::AtReady => self.pending.push(chunk),
        }
        Turn::Chunk { latency_ns }
    }

    /// Whether a computed chunk waits for its delivery time.
    pub fn has_pending(&self) -> bool {
        !self.pending.is_empty()
    }

    /// Queues `chunk` for delivery at its own `ready_ns` (a driver that sets the time itself).
    pub fn deliver_at_ready(&mut self, chunk: ActionChunk) {
        self.count(&chunk);
        self.pending.push(chunk);
    }

    /// Counts a chunk handed over; returns its latency (observation → ready, ns).
    fn count(&mut self, chunk: &ActionChunk) -> u64 {
        self.stats.chunks += 1;
        self.stats.last_latency_ns = chunk.ready_ns.saturating_sub(chunk.t_obs_ns);
        self.stats.last_latency_ns
    }

    /// Hands over the queued chunks that are due at `now_ns`, in the order they were queued,
    /// and drops the chunk buffers the control thread is done with (off the real-time path).
    pub fn poll(&mut self, now_ns: u64) {
        while let Some(i) = self.pending.iter().position(|c| c.ready_ns <= now_ns) {
            let c = self.pending.remove(i);
            drop(self.link.chunks.send(c));
        }
        while self.link.chunks.take_recycled().is_some() {}
    }
}
