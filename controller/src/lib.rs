//! # chunkrt-controller
//!
//! The real-time controller: it runs a chunk source (the π0 / π0.5 policy of `chunkrt-policy`,
//! or a test double) next to a robot and turns its action chunks into a joint command every
//! control period.
//!
//! ```text
//!  cameras, robot driver ──iceoryx2──▶ edge ─▶ observation ─▶ inference thread (ChunkSource)
//!  joint commands ◀────────────────── edge ◀── control thread (chunk executor, ruckig, watchdog)
//! ```
//!
//! Modules, one concern each:
//! - [`contract`]: the thread contract — [`contract::ChunkSource`], the inference request, the
//!   action chunk.
//! - [`edge`]: the IPC edge — subscribers, validation, observation assembly, command publishing.
//! - [`chunk`]: the action chunk handed from inference to control.
//! - [`control`]: the control tick — chunk timeline and strategies, interpolation, target
//!   shaping, ruckig, the safety state machine, measurement.
//! - [`control_loop`]: the control thread — one tick over IPC, the periodic loop.
//! - [`controller`]: the process's threads, start/stop, status; [`shared`]: what they share.
//! - [`conditioning`]: request → the state the policy observes and how its chunk is conditioned.
//! - [`worker`]: the inference protocol once (request → chunk source → hand-off → recycling).
//! - [`inference`]: the policy as a chunk source (`PolicySource`); [`remote`]: a policy behind
//!   an openpi-protocol server (`RemoteSource`).
//! - [`rt`]: real-time set-up (pinning, SCHED_FIFO, memory locking, the periodic loop: those
//!   from `chunkrt-rt`, which the drivers share) and the process's logging.
//!
//! Must not depend on: the reach task, training, evaluation, benches, plotting, the fake
//! devices (the binary's composition root in the `chunkrt` crate wires those up).

pub mod chunk;
pub mod conditioning;
pub mod config;
pub mod contract;
pub mod control;
pub mod control_loop;
pub mod controller;
pub mod edge;
pub mod inference;
pub mod log_limit;
pub mod remote;
pub mod rt;
pub mod shared;
pub mod worker;

pub use chunkrt_ipc as ipc;
pub use chunkrt_policy as policy;
