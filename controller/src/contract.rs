//! The thread contract between the controller's threads: what the control thread asks for
//! ([`InferenceRequest`]), what the observation/inference thread answers with ([`ActionChunk`]),
//! and what produces chunks ([`ChunkSource`]: the policy, a scripted test double, or
//! [`HoldSource`]).
//!
//! Owns: the trait and the message types' home. Must not depend on: the policy crate, IPC
//! services, threads.

pub use crate::chunk::ActionChunk;
pub use crate::control::InferenceRequest;
pub use crate::edge::Observation;

/// Produces action chunks from observations; runs in the observation/inference thread when
/// the control side asks for one (an [`InferenceRequest`]: when to start, and for real-time
/// chunking the previous chunk's remaining actions and their weights). The policy implements
/// it; tests use scripted sources.
pub trait ChunkSource: Send {
    /// Name for logs.
    fn name(&self) -> &str;
    /// Computes the next chunk for `obs`; `Ok(None)` when the source has nothing to execute.
    fn compute(
        &mut self,
        obs: &Observation,
        request: &InferenceRequest,
    ) -> anyhow::Result<Option<ActionChunk>>;
    /// Whether the chunks depend on the camera frames: then a missing or stale frame stops
    /// the source (and the controller holds) until every camera is fresh again.
    fn uses_cameras(&self) -> bool {
        false
    }
    /// Image inputs that are an earlier frame of a camera: the observation carries them after
    /// the cameras' frames ([`crate::edge::history::FrameHistory`]).
    fn delayed_views(&self) -> &[chunkrt_policy::DelayedView] {
        &[]
    }
    /// Whether the source produces chunks at all (`HoldSource` does not: the controller then
    /// holds in STARTING by design instead of escalating to FAULT).
    fn produces_chunks(&self) -> bool {
        true
    }
    /// Sets the prompt of the chunks from now on (a source without one ignores it).
    fn set_prompt(&mut self, _prompt: &str) {}
    /// Restarts the source's noise sequence from `seed`, where it has one it controls (the
    /// in-process policy; a remote server's noise is its own): an evaluation then gives every
    /// strategy and delay the same noise.
    fn reseed(&mut self, _seed: u64) {}
}

/// A source's answer when it made no request this time: a remote source waiting out the
/// backoff after a failed request ([`crate::remote::RemoteSource`]). Not a failure of its own
/// (the worker counts failed requests, not the polls made while a source backs off); the
/// control side asks again. The text names the cause of the failure being waited out.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct NotAsked(pub String);

impl std::fmt::Display for NotAsked {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(&self.0)
    }
}

impl std::error::Error for NotAsked {}

/// The source used when no policy is configured: it never produces a chunk, so the
/// controller holds the robot where it is.
pub struct HoldSource;

impl ChunkSource for HoldSource {
    fn name(&self) -> &str {
        "hold"
    }
    fn produces_chunks(&self) -> bool {
        false
    }
    fn compute(
        &mut self,
        _obs: &Observation,
        _request: &InferenceRequest,
    ) -> anyhow::Result<Option<ActionChunk>> {
        Ok(None)
    }
}
