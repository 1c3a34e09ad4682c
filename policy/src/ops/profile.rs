//! Where the inference path's time goes, by op kind: with [`enable`]`(true)` every outermost
//! call into the seam ([`super`]) adds its wall time to its kind's counter (an op that calls
//! another op counts once, as the outer one). For the bench's split of a cached step on the
//! CPU; on a GPU the calls only queue kernels, so the counters say nothing there. Off (the
//! default), a call costs one relaxed atomic load.

use std::cell::Cell;
use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
use std::time::Instant;

/// The op kinds the split reports.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Kind {
    /// Matrix products against weights (with a dense layer's bias and activation).
    Products,
    /// Attention (scores, mask, softmax, values).
    Attention,
    /// Norms with the gated residual before them.
    Norms,
    /// Residual adds outside a norm.
    Residuals,
    /// Head split, RoPE and the K/V cache write.
    Heads,
    /// gelu and gelu·up.
    Activations,
}

impl Kind {
    /// Every kind, in report order.
    pub const ALL: [Kind; 6] = [
        Kind::Products,
        Kind::Attention,
        Kind::Norms,
        Kind::Residuals,
        Kind::Heads,
        Kind::Activations,
    ];

    /// Its name in the report.
    pub fn name(self) -> &'static str {
        match self {
            Kind::Products => "products",
            Kind::Attention => "attention",
            Kind::Norms => "norms",
            Kind::Residuals => "residual adds",
            Kind::Heads => "heads + RoPE",
            Kind::Activations => "activations",
        }
    }
}

static ON: AtomicBool = AtomicBool::new(false);
static NS: [AtomicU64; 6] = [const { AtomicU64::new(0) }; 6];
static CALLS: [AtomicU64; 6] = [const { AtomicU64::new(0) }; 6];

thread_local! {
    /// Seam calls open on this thread (only the outermost one counts).
    static DEPTH: Cell<u32> = const { Cell::new(0) };
}

/// Turns the counters on or off for the whole process.
pub fn enable(on: bool) {
    ON.store(on, Ordering::Relaxed);
}

/// Zeroes the counters.
pub fn reset() {
    for c in NS.iter().chain(&CALLS) {
        c.store(0, Ordering::Relaxed);
    }
}

/// (kind, total ns, calls) since the last [`reset`].
pub fn snapshot() -> Vec<(Kind, u64, u64)> {
    Kind::ALL
        .iter()
        .enumerate()
        .map(|(i, &k)| {
            (
                k,
                NS[i].load(Ordering::Relaxed),
                CALLS[i].load(Ordering::Relaxed),
            )
        })
        .collect()
}

/// An open seam call; records on drop.
pub(crate) struct Span {
    /// (kind, start) for an outermost call while profiling; `None` otherwise.
    start: Option<(Kind, Instant)>,
    /// This span raised the thread's depth.
    counted: bool,
}

/// Opens a seam call of `kind`.
#[inline]
pub(crate) fn span(kind: Kind) -> Span {
    if !ON.load(Ordering::Relaxed) {
        return Span {
            start: None,
            counted: false,
        };
    }
    let outer = DEPTH.with(|d| {
        let v = d.get();
        d.set(v + 1);
        v == 0
    });
    Span {
        start: outer.then(|| (kind, Instant::now())),
        counted: true,
    }
}

impl Drop for Span {
    fn drop(&mut self) {
        if let Some((kind, t0)) = self.start {
            let i = Kind::ALL.iter().position(|&k| k == kind).unwrap_or(0);
            NS[i].fetch_add(t0.elapsed().as_nanos() as u64, Ordering::Relaxed);
            CALLS[i].fetch_add(1, Ordering::Relaxed);
        }
        if self.counted {
            DEPTH.with(|d| d.set(d.get().saturating_sub(1)));
        }
    }
}
