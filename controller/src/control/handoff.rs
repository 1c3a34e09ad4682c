//! Lock-free hand-offs between the inference thread and the control thread.
//!
//! - [`channel`]: chunks, inference → control. The newest chunk wins (a chunk the control
//!   thread has not taken yet is displaced back to the sender). The control side never
//!   allocates or frees: it moves chunks in, and hands chunks it is done with back through a
//!   bounded recycling queue, where the inference thread reuses (or drops) them.
//! - [`request_channel`]: inference requests, control → inference, single slot, newest wins,
//!   with a pool of preallocated boxes so the control side never allocates.
//!
//! Both are built on `crossbeam::queue::ArrayQueue` (bounded, preallocated, lock-free).

use std::sync::Arc;

use crossbeam::queue::ArrayQueue;

use super::rtc::InferenceRequest;
use crate::chunk::ActionChunk;

struct ChunkShared {
    ready: ArrayQueue<ActionChunk>,
    recycled: ArrayQueue<ActionChunk>,
}

/// Inference side of the chunk hand-off (cloneable).
#[derive(Clone)]
pub struct ChunkSender {
    shared: Arc<ChunkShared>,
}

/// Control side of the chunk hand-off.
pub struct ChunkReceiver {
    shared: Arc<ChunkShared>,
}

/// Creates a chunk hand-off. `capacity` (≥ 1) chunks can wait for the control thread
/// (1 = single-slot exchange); `recycle_capacity` bounds the chunks on their way back.
pub fn channel(capacity: usize, recycle_capacity: usize) -> (ChunkSender, ChunkReceiver) {
    let shared = Arc::new(ChunkShared {
        ready: ArrayQueue::new(capacity.max(1)),
        recycled: ArrayQueue::new(recycle_capacity.max(1)),
    });
    (
        ChunkSender {
            shared: shared.clone(),
        },
        ChunkReceiver { shared },
    )
}

impl ChunkSender {
    /// Hands a chunk to the control thread; never blocks. If the queue is full the oldest
    /// waiting chunk is displaced and returned (it was never executed).
    pub fn send(&self, chunk: ActionChunk) -> Option<ActionChunk> {
        self.shared.ready.force_push(chunk)
    }

    /// A chunk the control thread is done with (reuse its buffer or drop it here).
    pub fn take_recycled(&self) -> Option<ActionChunk> {
        self.shared.recycled.pop()
    }
}

impl ChunkReceiver {
    /// The oldest waiting chunk, if any; never blocks, never allocates.
    pub fn try_recv(&self) -> Option<ActionChunk> {
        self.shared.ready.pop()
    }

    /// Gives a chunk back to the inference side without freeing it here. Returns the chunk if
    /// the recycling queue is full (the caller keeps it and tries again later).
    pub fn recycle(&self, chunk: ActionChunk) -> Result<(), ActionChunk> {
        self.shared.recycled.push(chunk)
    }
}

struct RequestShared {
    ready: ArrayQueue<Box<InferenceRequest>>,
    pool: ArrayQueue<Box<InferenceRequest>>,
}

/// Control side of the request hand-off (held by the executor).
pub struct RequestSender {
    shared: Arc<RequestShared>,
}

/// Inference side of the request hand-off.
#[derive(Clone)]
pub struct RequestReceiver {
    shared: Arc<RequestShared>,
}

/// Creates the request hand-off with its preallocated pool (allocates here, never later).
pub fn request_channel() -> (RequestSender, RequestReceiver) {
    const POOL: usize = 4;
    let shared = Arc::new(RequestShared {
        ready: ArrayQueue::new(1),
        pool: ArrayQueue::new(POOL),
    });
    for _ in 0..POOL {
        // The pool was created with exactly POOL slots.
        let _ = shared.pool.push(Box::default());
    }
    (
        RequestSender {
            shared: shared.clone(),
        },
        RequestReceiver { shared },
    )
}

impl RequestSender {
    /// Fills a pooled request with `fill` and publishes it (a request still waiting is
    /// displaced back into the pool). Returns false if no pooled request was free (the
    /// inference side holds them all); nothing is allocated either way.
    pub fn publish(&self, fill: impl FnOnce(&mut InferenceRequest)) -> bool {
        let Some(mut req) = self.shared.pool.pop() else {
            return false;
        };
        fill(&mut req);
        if let Some(old) = self.shared.ready.force_push(req) {
            // The pool has room for every box: one was just taken out of it.
            let _ = self.shared.pool.push(old);
        }
        true
    }
}

impl RequestReceiver {
    /// The waiting request, if any (never blocks). Give it back with [`RequestReceiver::done`].
    pub fn try_recv(&self) -> Option<Box<InferenceRequest>> {
        self.shared.ready.pop()
    }

    /// Returns a request to the pool once the inference has used it.
    pub fn done(&self, req: Box<InferenceRequest>) {
        let _ = self.shared.pool.push(req);
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn chunk(id: u64) -> ActionChunk {
        ActionChunk {
            id,
            observation_seq: id,
            t_obs_ns: 0,
            period_ns: 20_000_000,
            n_dof: 1,
            actions: vec![0.0; 4],
            ready_ns: 0,
            start_shift_ns: 0,
        }
    }

    #[test]
    fn newest_chunk_wins_and_buffers_come_back() {
        let (tx, rx) = channel(1, 4);
        assert!(tx.send(chunk(1)).is_none());
        let displaced = tx.send(chunk(2)).expect("slot was full");
        assert_eq!(displaced.id, 1);
        let c = rx.try_recv().expect("chunk 2 waits");
        assert_eq!(c.id, 2);
        assert!(rx.try_recv().is_none());
        rx.recycle(c).expect("room");
        assert_eq!(tx.take_recycled().map(|c| c.id), Some(2));
    }

    #[test]
    fn requests_are_pooled() {
        let (tx, rx) = request_channel();
        assert!(tx.publish(|r| r.id = 1));
        assert!(tx.publish(|r| r.id = 2));
        let r = rx.try_recv().expect("newest request");
        assert_eq!(r.id, 2);
        assert!(rx.try_recv().is_none());
        rx.done(r);
        for i in 0..10 {
            assert!(tx.publish(|r| r.id = i));
        }
    }
}
