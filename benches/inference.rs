//! Inference benchmark: `cargo bench --bench inference [-- --quick] [--config pi05_bench]`
//! (or in the dev profile: `cargo test --bench inference -- --quick`).
//!
//! Device mode, for GPUs (and the CPU): `cargo bench [--features cuda] --bench inference --
//! --device cuda --preset pi05 [--precision bf16] [--calls 30] [--warmup 5]`: a random model of
//! the preset (`pi0` / `pi05`: openpi's full size; `pi0_bench` / `pi05_bench`) made on the device,
//! p50 / p90 / p99 / max of vision, prefix, one cached step and the full sample, by wall clock
//! around the whole call and by CUDA events, the device memory in use, and the ratio to openpi's
//! figures on an H100 (`benches/data/openpi_h100.json`).
//!
//! Random weights built in-process from `benches/data/*_bench.json`, 2 CPU threads (override with
//! `RAYON_NUM_THREADS`), p50 / p99 of the vision pass, the prefix pass, one denoising step cached
//! and uncached, and the full sample, with achieved GFLOP/s and CPU time; compared with openpi's
//! PyTorch `sample_actions` measured in the same run, interleaved with chunkrt's own calls, when
//! `--openpi DIR` (or `CHUNKRT_OPENPI`) names an openpi checkout and `CHUNKRT_OPENPI_PYTHON` a
//! Python with its pinned torch (`bash scripts/openpi-env.sh DIR` makes one); otherwise with the
//! stored figures in `benches/data/openpi_cpu_reference.json`, and it says so.

fn main() {
    if std::env::var_os("RAYON_NUM_THREADS").is_none() {
        std::env::set_var("RAYON_NUM_THREADS", "2");
    }
    chunkrt_policy::keep_freed_memory();
    let args: Vec<String> = std::env::args().collect();
    let quick = args.iter().any(|a| a == "--quick");
    let value = |flag: &str| {
        args.iter()
            .position(|a| a == flag)
            .and_then(|i| args.get(i + 1).cloned())
    };
    if value("--device").is_some() || value("--preset").is_some() {
        std::process::exit(device_mode(&value));
    }
    // `--config NAME`: only one configuration (pi0_bench / pi05_bench)
    let only = args
        .iter()
        .position(|a| a == "--config")
        .and_then(|i| args.get(i + 1).cloned());
    // `--openpi DIR` (or CHUNKRT_OPENPI): openpi's PyTorch model, run by the worker in
    // scripts/openpi_worker.py with CHUNKRT_OPENPI_PYTHON, interleaved with chunkrt's calls
    let openpi = chunkrt_bench::openpi::OpenpiSetup::from_args_or_env(
        value("--openpi").map(std::path::PathBuf::from),
        candle_core::utils::get_num_threads(),
    );
    let res = match only {
        Some(name) => chunkrt_bench::inference::run_named(&name, quick, openpi.as_ref()).map(|c| {
            chunkrt_bench::inference::BenchReport {
                configs: c,
                threads: candle_core::utils::get_num_threads(),
                cpu: chunkrt_bench::inference::cpu_model(),
            }
        }),
        None => chunkrt_bench::inference::run(quick, openpi.as_ref()),
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
            match chunkrt_bench::write_outputs(
                &chunkrt_bench::output_root().join("inference"),
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

/// `--device D --preset P [--precision f32|bf16] [--calls N] [--warmup N] [--unfused]
/// [--check-f32] [--profile]`: the same as `chunkrt bench-inference`; returns the exit code.
fn device_mode(value: &dyn Fn(&str) -> Option<String>) -> i32 {
    let flag = |f: &str| std::env::args().any(|a| a == f);
    let run = || -> anyhow::Result<()> {
        let num = |flag: &str, default: u32| -> anyhow::Result<u32> {
            match value(flag) {
                Some(v) => Ok(v.parse()?),
                None => Ok(default),
            }
        };
        chunkrt::policy_cli::bench(chunkrt::policy_cli::BenchArgs {
            device: value("--device").unwrap_or_else(|| "cpu".into()).parse()?,
            preset: value("--preset"),
            precision: value("--precision")
                .unwrap_or_else(|| "bf16".into())
                .parse()?,
            calls: num("--calls", 30)?.clamp(1, 10_000),
            warmup: num("--warmup", 5)?.min(1000),
            unfused: flag("--unfused"),
            check_f32: flag("--check-f32"),
            profile: flag("--profile"),
            graphs_only: flag("--graphs-only"),
            write_checkpoint: value("--write-checkpoint").map(Into::into),
        })
    };
    match run() {
        Ok(()) => 0,
        Err(e) => {
            eprintln!("inference bench: {e:#}");
            1
        }
    }
}
