//! One process-wide shutdown flag, set by SIGINT / SIGTERM.

use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::OnceLock;

static FLAG: OnceLock<&'static AtomicBool> = OnceLock::new();

/// The process's shutdown flag; the first call installs the SIGINT / SIGTERM handler.
pub fn flag() -> &'static AtomicBool {
    FLAG.get_or_init(|| {
        let flag: &'static AtomicBool = Box::leak(Box::new(AtomicBool::new(false)));
        if let Err(e) = ctrlc::set_handler(move || flag.store(true, Ordering::SeqCst)) {
            tracing::warn!("cannot install the SIGINT/SIGTERM handler: {e}");
        }
        flag
    })
}

/// True once SIGINT / SIGTERM was received (or [`request`] was called).
pub fn requested() -> bool {
    flag().load(Ordering::Relaxed)
}

/// Asks every loop of this process to stop.
pub fn request() {
    flag().store(true, Ordering::SeqCst)
}
