//! What the websocket baseline measures and reports, shared by its two drivers (the Python
//! scripts of [`super::ws_baseline`] and the Rust pair of [`super::ws_rust`]); depends on
//! neither.

use hdrhistogram::Histogram;

/// One observation shape: `cameras == 0` is a joint-state observation.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Case {
    /// Series name, e.g. `cam3_224x224`.
    pub name: String,
    /// Number of RGB cameras (0: joint state only).
    pub cameras: u32,
    /// Frame width in pixels.
    pub width: u32,
    /// Frame height in pixels.
    pub height: u32,
}

/// Measured baseline of one case (ns).
#[derive(Debug, Clone)]
pub struct CaseResult {
    /// Case name.
    pub name: String,
    /// Client send start → server finished unpacking.
    pub one_way: Histogram<u64>,
    /// Client send start → reply unpacked.
    pub rtt: Histogram<u64>,
}

/// The whole baseline run.
#[derive(Debug, Clone)]
pub struct Baseline {
    /// What was measured, e.g. "websocket + msgpack-numpy (openpi-client 0.1.2)".
    pub transport: String,
    /// Set when openpi-client could not be used and its format was mirrored.
    pub substitution: Option<String>,
    /// Per case.
    pub cases: Vec<CaseResult>,
}
