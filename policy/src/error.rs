//! The policy's error type, at the bottom of the crate: every module imports it from here.

/// Errors of the policy.
#[derive(Debug, thiserror::Error)]
pub enum PolicyError {
    /// Bad or inconsistent configuration.
    #[error("policy config: {0}")]
    Config(String),
    /// Missing or mismatched checkpoint tensors (one line each).
    #[error("checkpoint: {0}")]
    Checkpoint(String),
    /// File system.
    #[error("io: {0}")]
    Io(String),
    /// Bad input data (shapes, ranges, encodings).
    #[error("policy input: {0}")]
    Input(String),
    /// Tokenizer.
    #[error("tokenizer: {0}")]
    Tokenizer(String),
    /// Tensor library.
    #[error("candle: {0}")]
    Candle(#[from] candle_core::Error),
}
