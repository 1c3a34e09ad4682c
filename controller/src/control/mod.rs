//! The control tick: turns action chunks into a smooth, limit-respecting command stream.
//! [`executor`] runs the stages in order — `timeline` (with one file per transition strategy
//! under `strategy`), input checks, [`safety`], `shaping`, ruckig ([`otg`]), `request` — and
//! [`interp`], [`rtc`] (guidance weights, delay estimate), [`handoff`] (the lock-free channels to
//! the inference thread) and [`timing`] serve them.
//!
//! Owns: everything a tick does. Must not depend on: IPC services, threads, the policy (the
//! inference thread reaches it only through [`InferenceLink`]).
//!
//! How the controller uses it:
//!
//! ```no_run
//! use chunkrt_controller::control::Executor;
//! use chunkrt_controller::ipc::{JointCommand, ControllerStatus};
//! # fn main() -> anyhow::Result<()> {
//! let config = chunkrt_controller::config::Config::embedded_default();
//! // Built once, off the real-time path: allocates everything it will ever need.
//! let mut exec = Executor::new(&config)?;
//! // Inference thread: takes requests, sends chunks (lock-free, newest wins).
//! let link = exec.connect();
//! let events = exec.events(); // drained and logged by a non-RT thread
//! # let (now_ns, latest_joint_state) = (0u64, None);
//! let mut command = JointCommand::default();
//! // Every tick, in the pinned control thread:
//! let report = exec.tick(now_ns, latest_joint_state, &mut command);
//! if report.publish { /* publish `command` */ }
//! exec.record_timing(now_ns, now_ns + 20_000, now_ns + 80_000);
//! let mut status = ControllerStatus::default();
//! exec.fill_status(&mut status);
//! // Inference thread:
//! if let Some(req) = link.requests.try_recv() {
//!     // ... run the policy (continuing req.prefix as req.continuation says) ...
//!     link.requests.done(req);
//! }
//! events.drain(|e| tracing::info!("controller {e}"));
//! # Ok(()) }
//! ```

/// Milliseconds from the configuration as non-negative nanoseconds.
pub(crate) fn ms_to_ns(ms: f64) -> u64 {
    (ms * 1e6).max(0.0).round() as u64
}

pub mod executor;
pub mod handoff;
pub mod interp;
mod request;
pub mod rtc;
pub mod safety;
mod shaping;
mod strategy;
mod timeline;
pub mod timing;

/// ruckig through the allocation-free C shim: `chunkrt-rt`'s, which the robot drivers use without
/// the controller.
pub use chunkrt_rt::otg;

pub use executor::{Executor, ExecutorError, InferenceLink, Rearm, Strategy, TickReport, Trigger};
pub use handoff::{channel, request_channel, ChunkReceiver, ChunkSender, RequestReceiver};
pub use interp::{Interpolation, Sample};
pub use otg::{cxx_allocations, Otg, OtgInput, OtgOutput, OtgResult, OtgState};
pub use rtc::{
    guidance_weights, Continuation, DelayEstimator, InferenceRequest, Schedule, MAX_HORIZON,
};
pub use safety::{Event, EventReader, Reason, State};
pub use timing::{Quantiles, TickTiming};

// The generator's joint arrays and the messages' have the same length.
const _: () = assert!(otg::MAX_DOF == chunkrt_ipc::MAX_DOF);
