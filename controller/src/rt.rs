//! Real-time set-up: the thread measures and the periodic loop of [`chunkrt_rt::thread`]
//! (pinning, SCHED_FIFO, mlockall, the CPUs' wake-up latency, `run_periodic`), re-exported so
//! `chunkrt_controller::rt::...` keeps working, and the process's logging set-up.

pub use chunkrt_rt::thread::*;

/// Logs to stderr (colours only on a terminal); `RUST_LOG` filters (default `info`).
/// iceoryx2's own log is limited to errors unless `IOX2_LOG_LEVEL` says otherwise (its
/// "no config file, using defaults" warning is expected: chunkrt sets QoS per service).
pub fn init_logging() {
    use std::io::IsTerminal;
    iceoryx2::prelude::set_log_level_from_env_or(iceoryx2::prelude::LogLevel::Error);
    let _ = tracing_subscriber::fmt()
        .with_env_filter(
            tracing_subscriber::EnvFilter::try_from_default_env()
                .unwrap_or_else(|_| tracing_subscriber::EnvFilter::new("info")),
        )
        .with_ansi(std::io::stderr().is_terminal())
        .with_writer(std::io::stderr)
        .try_init();
}
