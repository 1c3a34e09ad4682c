//! # chunkrt
//!
//! A real-time controller that runs a π0 / π0.5 vision-language-action policy next to a robot.
//! This crate is the `chunkrt` command and the applications around the controller; the
//! controller itself is `chunkrt-controller`, the policy `chunkrt-policy`, the message contract
//! `chunkrt-ipc`, the fake devices `chunkrt-tools`, the benches `chunkrt-bench`: each is used by
//! its own name (this crate re-exports none of them, so every module has one name).
//!
//! Modules of this crate:
//! - [`run`]: `chunkrt run`, the composition root (config → executor + chunk source →
//!   controller).
//! - [`policy_cli`]: `chunkrt sample` / `inspect` / `bench-inference`.
//! - [`report`]: percentile plots and `chunkrt report` (on the controller's histograms).
//! - [`demo`]: starts the fake devices and the controller as processes; [`soak`]: the same
//!   stack for a long run, with overruns, lateness, holds, rejections, RSS and fds.
//!
//! The reach and SO-101 tasks, `chunkrt train` and `chunkrt eval` are `chunkrt-learn`.
//!
//! Must not be depended on by the controller, the policy or the ipc crate.

pub mod args;
pub mod config_print;
pub mod demo;
pub mod policy_cli;
pub mod record;
pub mod report;
pub mod run;
pub mod serve;
pub mod soak;
