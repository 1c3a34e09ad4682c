//! π0 / π0.5 policies in candle.

pub mod cli;
