//! # chunkrt-learn
//!
//! The policies' side of chunkrt: the tasks they are trained and judged on, the training, and
//! the closed-loop sweep. The `chunkrt` command runs [`train`] and [`eval`] (`chunkrt train`,
//! `chunkrt eval`); its applications (`run`, `serve`, `demo`, `soak`, `record`) take only the
//! reach scene and the SO-101's scripts from [`task`].
//!
//! Modules:
//! - [`task`]: the reach task (expert, dataset, closed-loop episodes in simulated time, the
//!   open-loop probe) and the SO-101's episodes against its physics process.
//! - [`train`]: `chunkrt train`.
//! - [`eval`]: `chunkrt eval`, the closed-loop delay sweep.
//!
//! Depends on the controller, the policy, the ipc crate, the fake devices' scene and the
//! benches' metrics; never on the `chunkrt` application crate.

pub mod eval;
pub mod task;
pub mod train;
