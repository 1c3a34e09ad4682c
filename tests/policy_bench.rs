//! Runs the inference benchmark's quick mode once (structure and sanity, not a timed test).

/// Part of the default run (issue: every bench's quick mode runs once in the suite): about 40 s
/// on the 2-core machine since the fused kernels landed.
#[test]
fn bench_quick_mode_runs_and_reports_every_phase() {
    if std::env::var_os("RAYON_NUM_THREADS").is_none() {
        std::env::set_var("RAYON_NUM_THREADS", "2");
    }
    let r = chunkrt_bench::inference::run(true, None).expect("bench runs");
    let text = r.to_string();
    println!("{text}");
    // without a same-run openpi the summary says where its figures come from, and this CPU
    assert!(
        text.contains("fell back to stored figures") && text.contains(&r.cpu),
        "{text}"
    );
    // π0 and π0.5, each in f32, in bf16 where the CPU has AMX or AVX512-BF16, and on candle's
    // kernels (the in-run baseline) where the packed f32 kernel runs
    let per_model = 1
        + chunkrt_policy::packed::bf16_backend().is_some() as usize
        + chunkrt_policy::packed::support().f32_packed() as usize;
    assert_eq!(r.configs.len(), 2 * per_model);
    for c in &r.configs {
        if c.precision == "bf16" {
            // bf16 inputs carry 8 significant bits: the actions must stay close to f32's
            let d = c.bf16_rel_action_diff.expect("bf16 reports its difference");
            assert!(
                d < 0.1,
                "{}: bf16 actions differ by {d} of their RMS",
                c.name
            );
        }
        for name in [
            "vision",
            "prefix",
            "step_cached",
            "step_uncached",
            "sample_cached",
        ] {
            let p = c
                .phase(name)
                .unwrap_or_else(|| panic!("{}: phase {name} missing", c.name));
            assert!(
                p.n > 0 && p.p50_ms > 0.0 && p.p99_ms >= p.p50_ms,
                "{}: {p:?}",
                c.name
            );
            assert!(p.gflops() > 0.0);
        }
        // the packed kernels are not far slower than candle's (same run, interleaved rounds;
        // release 0.60-0.65x): a bound with room for the quick mode's few samples in a dev
        // build on a shared machine; the speed figure itself is the bench's
        if let (Some(base), Some(p)) = (r.baseline(&c.name), c.phase("sample_cached")) {
            let b = base.phase("sample_cached").expect("baseline sample").p50_ms;
            assert!(
                p.p50_ms < 2.0 * b,
                "{} {}: {:.1} ms vs the candle baseline's {b:.1} ms",
                c.name,
                c.kernels,
                p.p50_ms
            );
        }
        // a cached step runs the action expert over H tokens only; an uncached one re-runs the
        // whole prefix: it must be clearly cheaper even on a loaded machine
        assert!(
            c.step_ratio() > 2.0,
            "{}: uncached/cached step ratio {}",
            c.name,
            c.step_ratio()
        );
        assert!(c.openpi_s > 0.0);
        // the full samples are split into vision, prefix pass and loop, timed inside the same
        // samples: the parts account for the sample (all but the few microseconds between the
        // timer reads; 0.8 leaves room for a preemption there on a loaded machine)
        // a cached step split by op kind at the seam: the products take time, and the kinds
        // (outermost calls only) never add up to more than the steps they were counted in
        // (the prefix pass the same way, where the attention also takes time)
        for (what, split) in [("step", &c.step_split), ("prefix pass", &c.prefix_split)] {
            let (kinds, total) = split.as_ref().expect("the split");
            let kind = |name: &str| kinds.iter().find(|k| k.0 == name).map_or(0.0, |k| k.1);
            let inside: f64 = kinds.iter().map(|k| k.1).sum();
            assert!(
                kind("products") > 0.0 && kind("attention") > 0.0 && inside <= total * 1.0001,
                "{} {}: {kinds:?} in a {total} ms {what}",
                c.name,
                c.kernels
            );
        }
        let [v, p, l, total] = c.split_ms.expect("the samples' split");
        assert!(
            v > 0.0
                && p > 0.0
                && l > 0.0
                && v + p + l <= total * 1.0001
                && v + p + l >= 0.8 * total,
            "{} {}: vision {v} + prefix {p} + loop {l} vs {total}",
            c.name,
            c.kernels
        );
    }
}

/// The same-run openpi baseline fails with a clear error when the checkout is not there (the
/// worker runs with the system Python; it exits before importing torch).
#[test]
fn openpi_baseline_without_a_checkout_is_a_clear_error() {
    let setup = chunkrt_bench::openpi::OpenpiSetup {
        dir: std::path::PathBuf::from("/nonexistent/openpi"),
        python: std::path::PathBuf::from("python3"),
        threads: 1,
    };
    let json = chunkrt_bench::inference::CONFIGS[0].1;
    match chunkrt_bench::openpi::OpenpiWorker::spawn(&setup, "pi0_bench", json) {
        Ok(_) => panic!("a worker started without an openpi checkout"),
        Err(e) => {
            let msg = e.to_string();
            assert!(
                msg.contains("openpi baseline") && msg.contains("exited"),
                "{msg}"
            );
        }
    }
}

/// openpi's PyTorch model through the worker, one sample, when a setup is given
/// (`CHUNKRT_OPENPI`, `CHUNKRT_OPENPI_PYTHON`; see scripts/openpi-env.sh). Not in the default run:
/// it needs torch (a ~3 GB install).
#[test]
#[ignore = "needs openpi and torch: CHUNKRT_OPENPI=DIR CHUNKRT_OPENPI_PYTHON=PY cargo test --test policy_bench -- --ignored"]
fn openpi_worker_samples() {
    let Some(setup) = chunkrt_bench::openpi::OpenpiSetup::from_args_or_env(None, 2) else {
        panic!("CHUNKRT_OPENPI is not set");
    };
    for (name, json) in chunkrt_bench::inference::CONFIGS {
        let mut w =
            chunkrt_bench::openpi::OpenpiWorker::spawn(&setup, name, json).expect("worker starts");
        // the sizes of the bench configuration (not openpi's full model): ~33-35 M parameters
        assert!(
            (20_000_000..60_000_000).contains(&w.info.params),
            "{name}: {:?}",
            w.info
        );
        let (wall, cpu) = w.sample().expect("one sample");
        println!(
            "{name}: openpi sample {wall} us wall, {cpu} us cpu, {:?}",
            w.info
        );
        assert!(wall > 0 && cpu > 0);
    }
}
