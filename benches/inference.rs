//! Inference benchmark: `cargo bench --bench inference [-- --quick]`.
//!
//! Random weights built in-process from `benches/data/*_bench.json`, 2 CPU threads (override with
//! `RAYON_NUM_THREADS`), p50 / p99 of the vision pass, the prefix pass, one denoising step cached
//! and uncached, and the full sample, with achieved GFLOP/s; compared with openpi's PyTorch
//! figures in `benches/data/openpi_cpu_reference.json`.

fn main() {
    if std::env::var_os("RAYON_NUM_THREADS").is_none() {
        std::env::set_var("RAYON_NUM_THREADS", "2");
    }
    let quick = std::env::args().any(|a| a == "--quick");
    match chunkrt::policy::bench::run(quick) {
        Ok(r) => print!("{r}"),
        Err(e) => {
            eprintln!("bench failed: {e}");
            std::process::exit(1);
        }
    }
}
