//! Process and thread set-up for real time: logging, pinning, SCHED_FIFO, mlockall.

/// Logs to stderr; `RUST_LOG` filters (default `info`).
pub fn init_logging() {
    let _ = tracing_subscriber::fmt()
        .with_env_filter(
            tracing_subscriber::EnvFilter::try_from_default_env()
                .unwrap_or_else(|_| tracing_subscriber::EnvFilter::new("info")),
        )
        .with_writer(std::io::stderr)
        .try_init();
}
