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
                configs: c,
                threads: candle_core::utils::get_num_threads(),
            }
        }),
        None => chunkrt::policy::bench::run(quick),
    };
    match res {
        Ok(r) => {
            print!("{r}");
            // interval log, plot and table under target/chunkrt-bench/inference/
            let series: Vec<chunkrt::report::Series> = r
                .configs
                .iter()
                .flat_map(|c| {
                    c.phases.iter().map(move |p| {
                        chunkrt::report::Series::new(
                            format!("{}_{}_{}", c.name, c.tag(), p.name),
                            p.hist_ns.clone(),
                        )
                    })
                })
                .collect();
            let table = chunkrt::report::LatencyTable::from_series(
                format!("inference ({} threads)", r.threads),
                &series,
            );
            let names: Vec<String> = series.iter().map(|s| s.name.clone()).collect();
            match chunkrt::bench::write_outputs(
                &chunkrt::bench::output_root().join("inference"),
                "inference",
                &table,
                &series,
                &[("inference", "policy phases by percentile", names)],
                std::time::Duration::from_secs(1),
                "chunkrt inference bench",
            ) {
                Ok(o) => println!("{o}"),
                Err(e) => eprintln!("inference: no log/plot: {e}"),
            }
        }
        Err(e) => {
            eprintln!("bench failed: {e}");
            std::process::exit(1);
        }
    }
}
