//! Inference benchmark: `cargo bench --bench inference [-- --quick] [--config pi05_bench]`
//! (or in the dev profile: `cargo test --bench inference -- --quick`).
//!
//! Random weights built in-process from `benches/data/*_bench.json`, 2 CPU threads (override with
//! `RAYON_NUM_THREADS`), p50 / p99 of the vision pass, the prefix pass, one denoising step cached
//! and uncached, and the full sample, with achieved GFLOP/s; compared with openpi's PyTorch
//! figures in `benches/data/openpi_cpu_reference.json`.

fn main() {
    if std::env::var_os("RAYON_NUM_THREADS").is_none() {
        std::env::set_var("RAYON_NUM_THREADS", "2");
    }
    let args: Vec<String> = std::env::args().collect();
    let quick = args.iter().any(|a| a == "--quick");
    // `--config NAME`: only one configuration (pi0_bench / pi05_bench)
    let only = args
        .iter()
        .position(|a| a == "--config")
        .and_then(|i| args.get(i + 1).cloned());
    let res = match only {
        Some(name) => chunkrt::policy::bench::run_named(&name, quick).map(|c| {
            chunkrt::policy::bench::BenchReport {
                configs: vec![c],
                threads: candle_core::utils::get_num_threads(),
            }
        }),
        None => chunkrt::policy::bench::run(quick),
    };
    match res {
        Ok(r) => print!("{r}"),
        Err(e) => {
            eprintln!("bench failed: {e}");
            std::process::exit(1);
        }
    }
}
