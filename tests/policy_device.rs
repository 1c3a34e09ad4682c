//! The device-generic policy path.
//!
//! On every machine (CI included):
//! - the candle compositions a GPU model runs, held to openpi's fixtures on the CPU with
//!   chunkrt's CPU kernels turned off (`set_cpu_fast_paths(false)`, for those tests only:
//!   [`GenericPaths`]);
//! - the bf16 dtype path (what `precision = "bf16"` stores on a GPU) run on the CPU, against f32.
//!
//! With a GPU (a build with `--features cuda` on a machine with an NVIDIA GPU): the fixtures on
//! CUDA in f32 within the fixtures' tolerances, and CUDA bf16 actions within 3 % of the f32
//! actions' RMS. A build without the feature reports those tests as ignored, with the reason; a
//! build with it on a machine without a GPU skips them loudly.

use std::sync::{Mutex, MutexGuard};

use candle_core::{DType, Device, Tensor};

#[path = "common/fixture.rs"]
mod fixture;
use fixture::{load_on, maxdiff, rel_maxdiff, Fixture};

const FIXTURES: [&str; 2] = ["pi05_tiny", "pi0_tiny"];

/// The CPU fast paths are one process-wide switch, and the harness runs tests on parallel
/// threads: every test that computes on the CPU holds this lock, so none sees the switch flip
/// between two of its calls.
fn cpu_paths() -> MutexGuard<'static, ()> {
    static CPU_PATHS: Mutex<()> = Mutex::new(());
    // a failed test poisons it; the next one still needs the exclusion
    CPU_PATHS.lock().unwrap_or_else(|e| e.into_inner())
}

/// chunkrt's CPU kernels off (the candle compositions a GPU runs) while it lives, under
/// [`cpu_paths`]; back on when dropped.
struct GenericPaths {
    _lock: MutexGuard<'static, ()>,
}

impl GenericPaths {
    fn on() -> Self {
        let lock = cpu_paths();
        chunkrt_policy::set_cpu_fast_paths(false);
        GenericPaths { _lock: lock }
    }
}

impl Drop for GenericPaths {
    fn drop(&mut self) {
        chunkrt_policy::set_cpu_fast_paths(true);
    }
}

/// Cached and uncached actions, and the first velocity, of a fixture's model on its device.
fn sample(f: &Fixture) -> (Tensor, Tensor, Tensor) {
    let dev = f.model.device().clone();
    let noise = f.raw["noise"].to_device(&dev).unwrap();
    let steps = f.model.cfg.num_denoise_steps;
    let mut cache = None;
    let c = f
        .model
        .sample(&f.inputs, &noise, steps, Some(&mut cache))
        .unwrap();
    let u = f.model.sample(&f.inputs, &noise, steps, None).unwrap();
    let cpu = |t: &Tensor| t.to_device(&Device::Cpu).unwrap();
    (cpu(&c.actions), cpu(&u.actions), cpu(&c.v_t_step0))
}

/// The fixture's f32 tolerances (tests/data/*/README.md): actions 5e-4, first velocity 3e-4.
fn assert_matches_openpi(name: &str, f: &Fixture, what: &str) {
    let (cached, uncached, v0) = sample(f);
    for (label, got, want, tol) in [
        ("actions (cached)", &cached, &f.out["actions"], 5e-4f32),
        ("actions (uncached)", &uncached, &f.out["actions"], 5e-4),
        ("v_t_step0", &v0, &f.out["v_t_step0"], 3e-4),
    ] {
        let d = maxdiff(got, want);
        println!("{name} {what} {label}: max |diff| {d:.2e} (tol {tol:.0e})");
        assert!(d <= tol, "{name} {what} {label}: {d} > {tol}");
    }
}

#[test]
fn generic_path_matches_openpi_on_the_cpu() {
    let _generic = GenericPaths::on();
    for name in FIXTURES {
        let f = load_on(name, &Device::Cpu, DType::F32);
        assert_matches_openpi(name, &f, "cpu generic");
    }
}

/// bf16 storage (the GPU's `precision = "bf16"`) on the CPU: the same dtype handling as on a GPU
/// (norm statistics, softmax, the time embedding and the sampler state in f32), so its distance
/// from f32 is measured here on every machine.
#[test]
fn bf16_dtype_stays_close_to_f32() {
    let _generic = GenericPaths::on();
    for name in FIXTURES {
        let f32m = load_on(name, &Device::Cpu, DType::F32);
        let bf = load_on(name, &Device::Cpu, DType::BF16);
        let (a32, _, _) = sample(&f32m);
        let (a16, u16, _) = sample(&bf);
        let r = rel_maxdiff(&a16, &a32);
        let ru = rel_maxdiff(&u16, &a32);
        println!("{name} bf16 vs f32 actions: max |diff| / RMS = {r:.4} (uncached {ru:.4})");
        assert!(r < BF16_BOUND && ru < BF16_BOUND, "{name}: {r} / {ru}");
    }
}

/// The bound for GPU bf16 (3 % of the f32 actions' RMS).
const BF16_BOUND: f64 = 0.03;

/// A CUDA device, or `None` with a loud note (no `cuda` feature, or no GPU).
fn cuda() -> Option<Device> {
    match chunkrt_policy::DeviceSpec::Cuda(0).open() {
        Ok(d) => Some(d),
        Err(e) => {
            eprintln!("!!! policy_device: GPU tests SKIPPED: {e}");
            None
        }
    }
}

#[test]
#[cfg_attr(
    not(feature = "cuda"),
    ignore = "needs a build with --features cuda and an NVIDIA GPU"
)]
fn cuda_f32_matches_openpi_and_bf16_stays_within_3_percent() {
    let Some(dev) = cuda() else { return };
    for name in FIXTURES {
        let f = load_on(name, &dev, DType::F32);
        assert_matches_openpi(name, &f, "cuda f32");
        let (a32, _, _) = sample(&f);
        let (a16, _, _) = sample(&load_on(name, &dev, DType::BF16));
        let r = rel_maxdiff(&a16, &a32);
        println!("{name} cuda bf16 vs f32 actions: max |diff| / RMS = {r:.4}");
        assert!(r < BF16_BOUND, "{name}: {r}");
    }
}

/// `chunkrt sample` on a device: without a GPU build it says how to get one; with NaN weights it
/// exits non-zero and writes nothing (it used to write NaN actions and exit 0).
#[test]
fn sample_cli_device_errors_and_nan_weights() {
    // a test binary carried to a GPU machine finds the binary it was packed with there
    let exe = std::env::var("CHUNKRT_EXE").unwrap_or_else(|_| env!("CARGO_BIN_EXE_chunkrt").into());
    let dir = fixture::data("pi0_tiny");
    let tmp = std::env::temp_dir().join(format!("chunkrt_device_cli_{}", std::process::id()));
    std::fs::create_dir_all(&tmp).unwrap();
    let out = tmp.join("out.safetensors");
    let sample = |ckpt: &std::path::Path, extra: &[&str]| {
        std::process::Command::new(&exe)
            .args(["sample", "--checkpoint"])
            .arg(ckpt)
            .arg("--inputs")
            .arg(dir.join("inputs.safetensors"))
            .arg("--output")
            .arg(&out)
            .args(extra)
            .output()
            .unwrap()
    };
    if !cfg!(feature = "cuda") {
        let r = sample(&dir, &["--device", "cuda"]);
        let err = String::from_utf8_lossy(&r.stderr);
        assert!(!r.status.success(), "{err}");
        assert!(err.contains("--features cuda"), "{err}");
    }
    let r = sample(&dir, &["--device", "gpu0"]);
    let err = String::from_utf8_lossy(&r.stderr);
    assert!(!r.status.success() && err.contains("\"cuda:N\""), "{err}");

    // one NaN in the action expert's output projection
    let mut t =
        candle_core::safetensors::load(dir.join("model.safetensors"), &Device::Cpu).unwrap();
    let w = &t["action_out_proj.weight"];
    let mut v = w.flatten_all().unwrap().to_vec1::<f32>().unwrap();
    v[3] = f32::NAN;
    let nan = Tensor::from_vec(v, w.shape(), &Device::Cpu).unwrap();
    t.insert("action_out_proj.weight".into(), nan);
    let bad = tmp.join("nan_ckpt");
    std::fs::create_dir_all(&bad).unwrap();
    candle_core::safetensors::save(&t, bad.join("model.safetensors")).unwrap();
    std::fs::copy(dir.join("config.json"), bad.join("config.json")).unwrap();
    std::fs::remove_file(&out).ok();
    let r = sample(&bad, &[]);
    let err = String::from_utf8_lossy(&r.stderr);
    assert!(!r.status.success(), "NaN weights must fail: {err}");
    assert!(err.contains("non-finite actions"), "{err}");
    assert!(!out.exists(), "nothing may be written");
    std::fs::remove_dir_all(&tmp).ok();
}

/// The time embedding and π0.5's adaRMS condition depend only on t: made once per time and
/// kept on the device, so a denoising step uploads nothing and runs no time MLP.
#[test]
fn time_features_are_made_once_per_time() {
    let f = load_on("pi05_tiny", &Device::Cpu, DType::F32);
    let a = f.model.adarms_cond(&[0.3]).unwrap().unwrap();
    let b = f.model.adarms_cond(&[0.3]).unwrap().unwrap();
    assert_eq!(a.id(), b.id(), "the same tensor, not a recomputation");
    let c = f.model.adarms_cond(&[0.4]).unwrap().unwrap();
    assert_ne!(a.id(), c.id());
    // rows at different times (training batches) are computed, not looked up
    let d = f.model.adarms_cond(&[0.3, 0.4]).unwrap().unwrap();
    assert_eq!(d.dims()[0], 2);
    assert!(maxdiff(&d.get(0).unwrap(), &a.get(0).unwrap()) == 0.0);
}

/// The GPU's fixed-shape step layout (suffix after all P prefix slots, the gap masked, the step's
/// mask and RoPE tables refilled in place) computes what the compact layout computes: on the
/// fixtures, again on the reused cache, and after the prompt's valid length changes.
#[test]
fn fixed_step_layout_equals_the_compact_one() {
    let _paths = cpu_paths();
    for name in FIXTURES {
        let mut fixed = load_on(name, &Device::Cpu, DType::F32);
        fixed.model.set_fixed_step_shapes(true);
        let compact = load_on(name, &Device::Cpu, DType::F32);
        let noise = &fixed.raw["noise"];
        let steps = fixed.model.cfg.num_denoise_steps;
        let mut fc = None;
        let mut cc = None;
        let mut inputs = fixed.inputs.clone();
        let mut first_ids = None;
        for round in 0..3 {
            if round == 2 {
                // a shorter prompt: fewer valid tokens, a longer masked gap
                let row = &mut inputs.token_mask[0];
                let n = row.iter().filter(|&&v| v).count();
                for v in row.iter_mut().skip(n / 2) {
                    *v = false;
                }
            }
            let a = fixed
                .model
                .sample(&inputs, noise, steps, Some(&mut fc))
                .unwrap()
                .actions;
            let b = compact
                .model
                .sample(&inputs, noise, steps, Some(&mut cc))
                .unwrap()
                .actions;
            let d = maxdiff(&a, &b);
            println!("{name} round {round}: fixed vs compact max |diff| {d:.2e}");
            assert!(d < 1e-5, "{name} round {round}: {d}");
            if round < 2 {
                let r = maxdiff(&a, &fixed.out["actions"]);
                assert!(r < 5e-4, "{name} fixed vs openpi: {r}");
            }
            let c = fc.as_ref().unwrap();
            let ids = (c.statics.ids(), c.k[0].id());
            match &first_ids {
                None => first_ids = Some(ids),
                Some(f) => assert_eq!(f, &ids, "{name}: the step's buffers are refilled in place"),
            }
        }
        let c = fc.unwrap();
        assert_eq!(
            c.step_bias().dims()[3],
            (fixed.model.cfg.prefix_len() + fixed.model.cfg.suffix_len()).next_multiple_of(8),
            "the fixed layout's steps attend over every slot, padded to a multiple of 8"
        );
    }
}

/// RTC's guided loop (identity Jacobian, the default) as a captured CUDA graph gives the eager
/// guided sampler's actions for a new observation and a new target every call. GPU only.
#[test]
#[cfg_attr(
    not(feature = "cuda"),
    ignore = "needs a build with --features cuda and an NVIDIA GPU"
)]
fn cuda_guided_graph_replays_the_eager_guided_loop() {
    use chunkrt_bench::inference::{device_bench_config, random_inputs_on, random_model_on};
    use chunkrt_policy::graph::SampleGraph;
    use chunkrt_policy::rtc::{sample_guided, weight_mask, GuidanceTarget, Jacobian};
    let Some(dev) = cuda() else { return };
    let (cfg, valid) = device_bench_config("pi05_bench").unwrap();
    let (steps, h, a) = (cfg.num_denoise_steps, cfg.action_horizon, cfg.action_dim);
    let mut w = vec![0.0f32; h];
    for (i, w) in w.iter_mut().enumerate().take(h / 2) {
        *w = 1.0 - i as f32 / h as f32;
    }
    for (dtype, tol) in [(DType::F32, 1e-5), (DType::BF16, 2e-2)] {
        let model = random_model_on(&cfg, &dev, dtype, 7).unwrap();
        let mut cache = None;
        let mut graph: Option<SampleGraph> = None;
        for obs in 0..4u64 {
            let inp = random_inputs_on(&cfg, valid - 3 * obs as usize, 200 + obs, &dev).unwrap();
            let noise = Tensor::randn(0f32, 1f32, (1, h, a), &dev).unwrap();
            let target = GuidanceTarget {
                y: Tensor::randn(0f32, 1f32, (1, h, a), &dev).unwrap(),
                w: weight_mask(&w, a - 1, a, &dev).unwrap(),
                beta: 10.0,
                jacobian: Jacobian::Identity,
            };
            let eager = sample_guided(&model, &inp, &noise, steps, &mut cache, &target).unwrap();
            let c = model.prepare_prefix(&inp, &mut cache, true).unwrap();
            match &graph {
                None => {
                    graph = SampleGraph::capture_guided(&model, c, &noise, steps, &target)
                        .unwrap()
                        .1;
                    assert!(graph.is_some(), "a CUDA model captures its guided sample");
                }
                Some(g) => {
                    assert!(g.fits_guided(c, steps, &target));
                    assert!(!g.fits(c, steps), "a guided graph is not the plain one");
                    let r = g.run_guided(&noise, &target).unwrap();
                    let d = rel_maxdiff(&r.actions, &eager.actions);
                    println!(
                        "{dtype:?} observation {obs}: guided graph vs eager max |diff| / RMS {d:.2e}"
                    );
                    assert!(d < tol, "{dtype:?} observation {obs}: {d}");
                }
            }
        }
    }
}

/// The whole sample as a captured CUDA graph gives the eager run's actions for a new
/// observation every call (new images, a prompt of another length, new noise): nothing stale is
/// captured. GPU only.
#[test]
#[cfg_attr(
    not(feature = "cuda"),
    ignore = "needs a build with --features cuda and an NVIDIA GPU"
)]
fn cuda_graph_replays_the_eager_loop_for_every_observation() {
    use chunkrt_bench::inference::{device_bench_config, random_inputs_on, random_model_on};
    use chunkrt_policy::graph::SampleGraph;
    let Some(dev) = cuda() else { return };
    let (cfg, valid) = device_bench_config("pi05_bench").unwrap();
    let steps = cfg.num_denoise_steps;
    for (dtype, tol) in [(DType::F32, 1e-5), (DType::BF16, 2e-2)] {
        let model = random_model_on(&cfg, &dev, dtype, 7).unwrap();
        assert!(
            model.fixed_step_shapes(),
            "GPU models use the fixed step layout"
        );
        let mut cache = None;
        let mut graph: Option<SampleGraph> = None;
        for obs in 0..4u64 {
            let inp = random_inputs_on(&cfg, valid - 3 * obs as usize, 100 + obs, &dev).unwrap();
            let noise =
                Tensor::randn(0f32, 1f32, (1, cfg.action_horizon, cfg.action_dim), &dev).unwrap();
            let eager = model.sample(&inp, &noise, steps, Some(&mut cache)).unwrap();
            let c = model.prepare_prefix(&inp, &mut cache, true).unwrap();
            match &graph {
                None => {
                    graph = SampleGraph::capture(&model, c, &noise, steps).unwrap().1;
                    assert!(graph.is_some(), "a CUDA model captures its sample");
                }
                Some(g) => {
                    assert!(g.fits(c, steps), "the cache buffers are reused in place");
                    let r = g.run(&noise).unwrap();
                    let d = rel_maxdiff(&r.actions, &eager.actions);
                    println!(
                        "{dtype:?} observation {obs}: graph vs eager max |diff| / RMS {d:.2e}"
                    );
                    assert!(d < tol, "{dtype:?} observation {obs}: {d}");
                }
            }
        }
    }
}
