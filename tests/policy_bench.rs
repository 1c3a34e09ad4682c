//! Runs the inference benchmark's quick mode once (structure and sanity, not a timed test).

/// Part of the default run (issue: every bench's quick mode runs once in the suite): about 40 s
/// on the 2-core machine since the fused kernels landed.
#[test]
fn bench_quick_mode_runs_and_reports_every_phase() {
    if std::env::var_os("RAYON_NUM_THREADS").is_none() {
        std::env::set_var("RAYON_NUM_THREADS", "2");
    }
    let r = chunkrt::policy::bench::run(true).expect("bench runs");
    println!("{r}");
    // π0 and π0.5, each in f32, in bf16 where the CPU has AMX or AVX512-BF16, and on candle's
    // kernels (the in-run baseline) where the packed f32 kernel runs
    let per_model = 1
        + chunkrt::policy::packed::bf16_backend().is_some() as usize
        + chunkrt::policy::packed::support().f32_packed() as usize;
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
        // the phase sum is reported (vision + prefix + steps x cached step vs the sample); no
        // bound on it here: in a debug build on a loaded machine the medians of a few samples
        // were 0.6x-1.7x the sample (the figure is the bench's, in release)
        let (sum, total) = c.phase_sum_ms().expect("phase sum");
        assert!(
            sum > 0.0 && total > 0.0,
            "{} {}: {sum} / {total}",
            c.name,
            c.kernels
        );
    }
}
