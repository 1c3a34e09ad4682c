//! The device-generic policy path.
//!
//! On every machine (CI included):
//! - the candle compositions a GPU model runs, held to openpi's fixtures on the CPU with
//!   chunkrt's CPU kernels turned off (`set_cpu_fast_paths(false)`: this test binary only);
//! - the bf16 dtype path (what `precision = "bf16"` stores on a GPU) run on the CPU, against f32.
//!
//! With a GPU (a build with `--features cuda` on a machine with an NVIDIA GPU; skipped loudly
//! otherwise): the fixtures on CUDA in f32 within the fixtures' tolerances, and CUDA bf16 actions
//! within 3 % of the f32 actions' RMS.

use candle_core::{DType, Device, Tensor};

#[path = "common/fixture.rs"]
mod fixture;
use fixture::{load_on, maxdiff, rel_maxdiff, Fixture};

const FIXTURES: [&str; 2] = ["pi05_tiny", "pi0_tiny"];

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
    chunkrt::policy::set_cpu_fast_paths(false);
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
    chunkrt::policy::set_cpu_fast_paths(false);
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
    match chunkrt::policy::DeviceSpec::Cuda(0).open() {
        Ok(d) => Some(d),
        Err(e) => {
            eprintln!("!!! policy_device: GPU tests SKIPPED: {e}");
            None
        }
    }
}

#[test]
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
