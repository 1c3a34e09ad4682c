//! `chunkrt report` and the percentile plots: the measurement crate's (`chunkrt_bench::report`),
//! re-exported for the command line and the demo.

pub use chunkrt_bench::report::*;
