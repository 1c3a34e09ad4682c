//! # chunkrt-ipc: the message contract every chunkrt process shares
//!
//! Fixed-size `#[repr(C)]` payloads sent over iceoryx2 shared memory, the service names and
//! quality of service, and the validation every receiver applies at the boundary.
//!
//! The same layouts exist as a C header (`ipc/include/chunkrt_ipc.h`) and a Python ctypes
//! mirror (`ipc/python/chunkrt_ipc.py`); the test suite compiles and runs both and compares
//! every size and field offset with [`messages::layouts`].
//!
//! Owns: the messages, services and QoS, validation, the clock, the TOML configuration. Must not
//! depend on: any other chunkrt crate, the policy, candle.

pub mod clock;
pub mod config;
pub mod messages;
pub mod services;
pub mod validate;

pub use clock::{monotonic_ns, sleep_until_ns};
pub use config::{ConfigError, SharedConfig};
pub use messages::*;
pub use services::{IpcError, Namespace};
pub use validate::{
    validate_frame, validate_joint_command, validate_joint_state, validate_rearm, Freshness,
    RejectReason, SessionGate, SessionState, StreamGuard, ValidationError, STRIDE_ALIGN_SLACK,
};
