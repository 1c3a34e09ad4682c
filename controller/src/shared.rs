//! State shared by the controller's threads: counters, the edge's event ring, the stop flag,
//! the state and the latest status figures (atomics and lock-free queues only).
//!
//! Owns: nothing but the shared cells. Must not depend on: the threads that use it.

use std::sync::atomic::{AtomicBool, AtomicU32, AtomicU64, Ordering};

use chunkrt_ipc::CONTROLLER_STATE_STARTING;

use crate::edge::{event_ring, Counters, EventRing};

/// State shared by the controller's threads.
pub struct Shared {
    /// Message counters.
    pub counters: Counters,
    /// Events to log (written by the real-time threads, drained by the main thread).
    pub events: EventRing,
    /// Set to stop every thread.
    pub stop: AtomicBool,
    /// `CONTROLLER_STATE_*`.
    pub state: AtomicU32,
    /// Ticks executed.
    pub ticks: AtomicU64,
    /// Ticks that ended after the next deadline.
    pub overruns: AtomicU64,
    /// Commands published.
    pub commands: AtomicU64,
    /// Chunks produced by the source.
    pub chunks: AtomicU64,
    /// Latency of the last chunk (observation → chunk ready), ns.
    pub last_inference_latency_ns: AtomicU64,
    /// Transitions into HOLD.
    pub hold_entries: AtomicU64,
    /// Cameras the policy would use with a missing or stale frame (bit i = camera i), as the
    /// observation thread last saw them.
    pub stale_cameras: AtomicU64,
    /// Latest status as published (for the periodic log line).
    pub lateness_p50_ns: AtomicU64,
    pub lateness_p99_ns: AtomicU64,
    pub lateness_max_ns: AtomicU64,
    pub compute_p50_ns: AtomicU64,
    pub compute_p99_ns: AtomicU64,
    pub compute_max_ns: AtomicU64,
    /// This controller's status publisher id, low and high word (0: not created yet), so the
    /// observation thread can tell its own statuses from another publisher's.
    pub status_publisher: [AtomicU64; 2],
}

impl Default for Shared {
    fn default() -> Self {
        Self::new()
    }
}

impl Shared {
    /// Fresh counters and state.
    pub fn new() -> Self {
        Self {
            counters: Counters::default(),
            events: event_ring(1024),
            stop: AtomicBool::new(false),
            state: AtomicU32::new(CONTROLLER_STATE_STARTING),
            ticks: AtomicU64::new(0),
            overruns: AtomicU64::new(0),
            commands: AtomicU64::new(0),
            chunks: AtomicU64::new(0),
            last_inference_latency_ns: AtomicU64::new(0),
            hold_entries: AtomicU64::new(0),
            stale_cameras: AtomicU64::new(0),
            lateness_p50_ns: AtomicU64::new(0),
            lateness_p99_ns: AtomicU64::new(0),
            lateness_max_ns: AtomicU64::new(0),
            compute_p50_ns: AtomicU64::new(0),
            compute_p99_ns: AtomicU64::new(0),
            compute_max_ns: AtomicU64::new(0),
            status_publisher: Default::default(),
        }
    }
}

impl Shared {
    /// Records this controller's status publisher id.
    pub fn set_status_publisher(&self, id: u128) {
        self.status_publisher[0].store(id as u64, Ordering::Relaxed);
        self.status_publisher[1].store((id >> 64) as u64, Ordering::Relaxed);
    }

    /// This controller's status publisher id (0: not created yet).
    pub fn status_publisher(&self) -> u128 {
        (self.status_publisher[0].load(Ordering::Relaxed) as u128)
            | ((self.status_publisher[1].load(Ordering::Relaxed) as u128) << 64)
    }
}
