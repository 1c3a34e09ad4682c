//! # chunkrt-openpi
//!
//! openpi's policy protocol, the one openpi's `serve_policy.py`, the `openpi-client` package,
//! SGLang and vLLM-Omni speak: a websocket whose binary messages are msgpack-numpy maps. On
//! connect the server sends its metadata; then every observation the client sends is answered
//! with an action chunk; an error is a text frame followed by a close with code 1011.
//!
//! - [`msgpack`]: the codec (`openpi_client.msgpack_numpy`), decoding bounded and borrowed.
//! - [`layout`]: which key of a request feeds which image input, the state and the prompt,
//!   with presets for openpi's LIBERO, ALOHA and DROID clients.
//! - [`message`]: the request (with chunkrt's optional real-time-chunking keys), the reply and
//!   the metadata as typed values.
//! - [`server`]: a server (`chunkrt serve`); [`client`]: a client (the controller's remote
//!   chunk source).
//!
//! Owns: the wire. Must not depend on: the policy, the controller, the IPC contract (the
//! composition roots wire them to it).

pub mod client;
pub mod layout;
pub mod message;
pub mod msgpack;
pub mod server;

pub use client::{Client, ClientConfig, ClientError};
pub use layout::{ActionSpace, KeyPath, Layout, LayoutConfig, Preset, DROID_MAX_JOINT_DELTA};
pub use message::{
    clip_text, ChunkrtMetadata, Image, ImageRef, Outgoing, Reply, Request, RequestError,
};
pub use msgpack::{decode, DType, Limits, NdArray, Value, Writer};
pub use server::{Failure, Server, ServerConfig, ServerStats};
