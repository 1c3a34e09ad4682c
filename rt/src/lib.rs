//! # chunkrt-rt
//!
//! chunkrt's real-time parts that the controller and the robot drivers share:
//!
//! - [`otg`]: jerk-limited online trajectory generation — the official ruckig C++ library
//!   through an allocation-free C shim (`ffi/`, built by `build.rs`).
//! - [`thread`]: real-time thread set-up — pinning, SCHED_FIFO, memory locking, the CPUs'
//!   wake-up latency, and the periodic loop on absolute CLOCK_MONOTONIC deadlines.
//!
//! Must not depend on: IPC, the policy, the model (a driver that needs only these parts must not
//! build candle, the policy or openpi).

pub mod otg;
pub mod thread;
