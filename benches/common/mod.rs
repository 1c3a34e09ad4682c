//! Shared `main` plumbing of the chunkrt benches (harness off): options, the single-thread
//! candle setting, exit codes.

use chunkrt_bench::{BenchError, BenchOpts};

/// Keeps candle's matmuls in the calling thread (one core per load generator / inference
/// thread) unless the user chose otherwise. Call first thing in `main`, before any thread exists.
#[allow(dead_code)]
pub fn single_threaded_candle() {
    if std::env::var_os("RAYON_NUM_THREADS").is_none() {
        std::env::set_var("RAYON_NUM_THREADS", "1");
    }
}

/// Parses `--quick` / `--out DIR` (ignoring cargo's `--bench`), runs `f`, exits 1 on error.
pub fn main(name: &str, f: impl FnOnce(BenchOpts) -> Result<(), BenchError>) {
    let result = BenchOpts::from_args(name, std::env::args().skip(1)).and_then(f);
    if let Err(e) = result {
        eprintln!("{name}: error: {e}");
        std::process::exit(1);
    }
}
