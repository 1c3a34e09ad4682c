//! # chunkrt
//!
//! A real-time controller that runs a π0 / π0.5 vision-language-action policy next to a robot.
//!
//! ```text
//!  cameras, robot driver ──iceoryx2──▶ edge ─▶ observation ─▶ inference thread (policy)
//!  joint commands ◀────────────────── edge ◀── control thread (chunk executor, ruckig, watchdog)
//! ```
//!
//! Modules, one concern each:
//! - [`edge`]: the IPC edge — subscribers, validation, observation assembly, command publishing.
//! - [`chunk`]: the chunk timeline handed from inference to control.
//! - [`controller`]: the controller process — threads, real-time setup, status.
//! - [`control`]: the control tick — chunk execution, transitions, ruckig, safety, measurement.
//! - [`policy`]: the `chunkrt-policy` crate (π0 / π0.5 in candle, pre/post-processing,
//!   checkpoints), re-exported; [`policy_cli`]: `chunkrt sample` / `chunkrt inspect`.
//! - [`report`]: latency histograms → logs, tables, plots.
//! - [`demo`]: starts the fake devices and the controller as processes; [`soak`]: the same
//!   stack for a long run, with overruns, lateness, holds, rejections, RSS and fds.

pub mod bench;
pub mod chunk;
pub mod control;
pub mod controller;
pub mod demo;
pub mod edge;
pub mod eval;
pub mod inference;
pub mod log_limit;
pub mod policy_cli;
pub mod report;
pub mod rt;
pub mod soak;
pub mod task;
pub mod train;

pub use chunkrt_ipc as ipc;
pub use chunkrt_ipc::config;
pub use chunkrt_policy as policy;
