//! chunkrt's companion processes: a fake camera, a simulated robot and a monitor.
//! Each is a module with clap `Args` and a `run` function, used by the standalone binaries and
//! by the `chunkrt` multi-call binary (so `chunkrt demo` can start them as processes).
//!
//! Owns: the stand-ins for a robot driver and a camera, and the operator's tools (`monitor`,
//! `rearm`). Must not depend on: the controller or the policy (they talk to it over IPC only).

pub mod cli;
pub mod common;
pub mod fake_camera;
pub mod fake_robot;
pub mod intake;
pub mod monitor;
pub mod rearm;
pub mod scene;
pub mod shutdown;
pub mod testing;
