//! The inference benchmark (core of `benches/inference.rs`): random weights built in-process from
//! the bench configurations, p50 / p99 (hdrhistogram) of each phase, cached vs uncached, GFLOP/s.

use std::time::Instant;

use candle_core::{DType, Device, Tensor};
use candle_nn::{VarBuilder, VarMap};
use hdrhistogram::Histogram;

use super::config::{GemmaDims, ModelConfig};
use super::model::{ModelInputs, PiModel};
use super::openpi::{OpenpiInfo, OpenpiSetup, OpenpiWorker};
use super::PolicyError;

/// The bench configurations (same schema as the fixtures' `config.json`).
pub const CONFIGS: [(&str, &str); 2] = [
    (
        "pi0_bench",
        include_str!("../../benches/data/pi0_bench.json"),
    ),
    (
        "pi05_bench",
        include_str!("../../benches/data/pi05_bench.json"),
    ),
];

/// Where [`OPENPI_SAMPLE_S`] were measured: they are stored figures, not this run's.
pub const OPENPI_SAMPLE_CPU: &str =
    "stored, not this run: 2-core AMD EPYC Zen 4 VM (AVX-512), 2 threads, PyTorch f32";

/// openpi's PyTorch medians (s): π0, π0.5, measured as [`OPENPI_SAMPLE_CPU`] says.
pub const OPENPI_SAMPLE_S: [(&str, f64); 2] = [("pi0_bench", 0.4073), ("pi05_bench", 0.5219)];

/// Timing of one phase.
#[derive(Debug, Clone)]
pub struct Phase {
    /// Phase name.
    pub name: String,
    /// Samples.
    pub n: u64,
    /// Median (ms).
    pub p50_ms: f64,
    /// 99th percentile (ms).
    pub p99_ms: f64,
    /// Analytic matmul FLOPs of one run.
    pub flops: f64,
    /// Median process CPU time of one run (ms, all threads): robust to a loaded machine.
    pub cpu_ms: f64,
    /// Wall time of every run (ns), for the interval log and the plot.
    pub hist_ns: Histogram<u64>,
}

impl Phase {
    /// Achieved GFLOP/s at the median.
    pub fn gflops(&self) -> f64 {
        self.flops / (self.p50_ms * 1e-3) / 1e9
    }
}

/// Results for one configuration.
#[derive(Debug, Clone)]
pub struct ConfigReport {
    /// Configuration name.
    pub name: String,
    /// Phases.
    pub phases: Vec<Phase>,
    /// openpi's median for the full sample (s).
    pub openpi_s: f64,
    /// `f32` or `bf16` (the experts' and SigLIP's matrix products in bf16: AMX or AVX512-BF16).
    pub precision: &'static str,
    /// Kernels of the matrix products: `f32 packed (avx-512)`, `candle f32`, or the bf16 backend
    /// (`amx`, `avx512-bf16`).
    pub kernels: &'static str,
    /// bf16 only: max |bf16 − f32| over the sampled actions (model space, same weights, inputs
    /// and noise), divided by the RMS of the f32 actions.
    pub bf16_rel_action_diff: Option<f64>,
    /// Denoising steps of a sample.
    pub steps: usize,
    /// openpi's `sample_actions` timed in this run, interleaved with the variants' full samples
    /// (phase `sample`), and what its worker reported; `None`: the stored figure
    /// [`ConfigReport::openpi_s`] is the reference.
    pub openpi_same_run: Option<(Phase, OpenpiInfo)>,
}

impl ConfigReport {
    /// (vision + prefix + steps × cached step, the full cached sample), p50 ms: whether the
    /// phases account for the sample.
    pub fn phase_sum_ms(&self) -> Option<(f64, f64)> {
        let p = |n: &str| self.phase(n).map(|p| p.p50_ms);
        Some((
            p("vision")? + p("prefix")? + self.steps as f64 * p("step_cached")?,
            p("sample_cached")?,
        ))
    }

    /// A short name of the variant: `f32`, `bf16` or `f32_candle` (the in-run baseline).
    pub fn tag(&self) -> String {
        if self.kernels.contains("baseline") {
            format!("{}_candle", self.precision)
        } else {
            self.precision.to_string()
        }
    }

    /// A phase by name.
    pub fn phase(&self, name: &str) -> Option<&Phase> {
        self.phases.iter().find(|p| p.name == name)
    }

    /// openpi's median for the full sample (s): this run's when measured, else the stored one.
    pub fn openpi_reference_s(&self) -> f64 {
        match &self.openpi_same_run {
            Some((p, _)) => p.p50_ms * 1e-3,
            None => self.openpi_s,
        }
    }

    /// openpi median / our full cached sample median (same run when measured).
    pub fn speedup_vs_openpi(&self) -> f64 {
        self.phase("sample_cached")
            .map(|p| self.openpi_reference_s() / (p.p50_ms * 1e-3))
            .unwrap_or(0.0)
    }

    /// Uncached step median / cached step median.
    pub fn step_ratio(&self) -> f64 {
        match (self.phase("step_uncached"), self.phase("step_cached")) {
            (Some(u), Some(c)) => u.p50_ms / c.p50_ms,
            _ => 0.0,
        }
    }
}

/// The whole report.
#[derive(Debug, Clone)]
pub struct BenchReport {
    /// Per configuration.
    pub configs: Vec<ConfigReport>,
    /// candle's CPU thread count.
    pub threads: usize,
    /// This machine's CPU ([`cpu_model`]).
    pub cpu: String,
}

/// The CPU model (`/proc/cpuinfo`'s first `model name`) and the core count.
pub fn cpu_model() -> String {
    let model = std::fs::read_to_string("/proc/cpuinfo")
        .ok()
        .and_then(|s| {
            s.lines()
                .find(|l| l.starts_with("model name"))
                .and_then(|l| l.split(':').nth(1))
                .map(|m| m.trim().to_string())
        })
        .unwrap_or_else(|| "unknown CPU".into());
    let cores = std::thread::available_parallelism()
        .map(|n| n.get())
        .unwrap_or(1);
    format!("{model}, {cores} cores")
}

impl BenchReport {
    /// The in-run baseline (candle's kernels) of configuration `name`.
    pub fn baseline(&self, name: &str) -> Option<&ConfigReport> {
        self.configs
            .iter()
            .find(|c| c.name == name && c.kernels.contains("baseline"))
    }
}

impl std::fmt::Display for BenchReport {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        writeln!(
            f,
            "cpu: {}; f32 kernel: {}; threads: {}",
            self.cpu,
            super::packed::support().f32_kernel(),
            self.threads
        )?;
        for c in &self.configs {
            writeln!(f, "== {} ({}, {}) ==", c.name, c.precision, c.kernels)?;
            writeln!(
                f,
                "{:<16} {:>5} {:>10} {:>10} {:>9} {:>10} {:>12}",
                "phase", "n", "p50 ms", "p99 ms", "GFLOP/s", "cpu ms", "GFLOP/cpu-s"
            )?;
            for p in &c.phases {
                writeln!(
                    f,
                    "{:<16} {:>5} {:>10.2} {:>10.2} {:>9.1} {:>10.2} {:>12.1}",
                    p.name,
                    p.n,
                    p.p50_ms,
                    p.p99_ms,
                    p.gflops(),
                    p.cpu_ms,
                    p.flops / (p.cpu_ms * 1e-3) / 1e9
                )?;
            }
            if let Some((sum, total)) = c.phase_sum_ms() {
                writeln!(
                    f,
                    "phases: vision + prefix + {} x cached step = {sum:.1} ms of the sample's {total:.1} ms ({:+.1} ms outside every phase)",
                    c.steps,
                    total - sum
                )?;
            }
            if let Some((p, info)) = &c.openpi_same_run {
                writeln!(
                    f,
                    "{:<16} {:>5} {:>10.2} {:>10.2} {:>9} {:>10.2}   (openpi PyTorch, this run: torch {}, {} threads, {:.1} M parameters)",
                    "openpi sample",
                    p.n,
                    p.p50_ms,
                    p.p99_ms,
                    "",
                    p.cpu_ms,
                    info.torch,
                    info.threads,
                    info.params as f64 / 1e6
                )?;
            }
            writeln!(
                f,
                "full sample (cached) vs openpi PyTorch {:.3} s ({}): {:.2}x faster; uncached/cached step: {:.1}x",
                c.openpi_reference_s(),
                if c.openpi_same_run.is_some() { "this run" } else { "stored" },
                c.speedup_vs_openpi(),
                c.step_ratio()
            )?;
            if let Some(d) = c.bf16_rel_action_diff {
                writeln!(
                    f,
                    "bf16 vs f32 actions (same weights, inputs, noise): max difference {d:.4} of the actions' RMS"
                )?;
            }
        }
        writeln!(f, "== full cached sample, p50 (interleaved rounds) ==")?;
        if self.configs.iter().all(|c| c.openpi_same_run.is_some()) {
            writeln!(
                f,
                "openpi: measured in this run, interleaved with chunkrt's calls on {}",
                self.cpu
            )?;
        } else {
            writeln!(
                f,
                "openpi: fell back to stored figures ({OPENPI_SAMPLE_CPU}), not this CPU ({}); \
                 for a same-run baseline pass --openpi DIR (scripts/openpi-env.sh); on another CPU \
                 compare with the in-run candle baseline",
                self.cpu
            )?;
        }
        for c in &self.configs {
            let base = self.baseline(&c.name);
            let vs_base = match (base, c.phase("sample_cached")) {
                (Some(b), Some(p)) if !std::ptr::eq(b, c) => format!(
                    "; {:.2}x the in-run candle baseline",
                    b.phase("sample_cached").map_or(0.0, |bp| bp.p50_ms) / p.p50_ms
                ),
                _ => String::new(),
            };
            writeln!(
                f,
                "{:<11} {:<5} {:<30} {:>8.1} ms: {:.2}x openpi's {:.3} s ({}){vs_base}",
                c.name,
                c.precision,
                c.kernels,
                c.phase("sample_cached").map_or(0.0, |p| p.p50_ms),
                c.speedup_vs_openpi(),
                c.openpi_reference_s(),
                if c.openpi_same_run.is_some() {
                    "same run"
                } else {
                    "stored"
                }
            )?;
        }
        Ok(())
    }
}

/// FLOPs of one Gemma layer for `l` queries over `t` keys.
fn layer_flops(d: &GemmaDims, l: usize, t: usize) -> f64 {
    let (w, qd, kvd) = (
        d.width,
        d.num_heads * d.head_dim,
        d.num_kv_heads * d.head_dim,
    );
    let l = l as f64;
    2.0 * l * (w * (qd + 2 * kvd) + qd * w + 3 * w * d.mlp_dim) as f64
        + 4.0 * l * t as f64 * qd as f64
}

fn vision_flops(c: &ModelConfig) -> f64 {
    let v = &c.vision;
    let t = v.num_tokens() as f64;
    let dv = v.hidden_size as f64;
    let per_layer =
        2.0 * t * (4.0 * dv * dv + 2.0 * dv * v.intermediate_size as f64) + 4.0 * t * t * dv;
    let per_image = per_layer * v.num_hidden_layers as f64
        + 2.0 * t * dv * (3 * v.patch_size * v.patch_size) as f64
        + 2.0 * t * dv * c.paligemma.width as f64;
    per_image * c.cameras.len() as f64
}

/// The latency histogram of the bench's interval logs and plots: ns, 1 ns .. 60 s, 3 digits
/// (the same bounds as the controller's report, so the logs merge).
pub fn latency_histogram_ns() -> Histogram<u64> {
    Histogram::new_with_bounds(1, 60_000_000_000, 3)
        .expect("constant bounds 1..60e9 with 3 significant digits are valid")
}

fn histogram() -> Result<Histogram<u64>, PolicyError> {
    Histogram::<u64>::new_with_bounds(1, 600_000_000, 3)
        .map_err(|e| PolicyError::Config(format!("histogram: {e}")))
}

/// Process CPU time (all threads) in microseconds.
fn cpu_us() -> u64 {
    let mut ts = libc::timespec {
        tv_sec: 0,
        tv_nsec: 0,
    };
    // SAFETY: clock_gettime writes into the timespec we own; CLOCK_PROCESS_CPUTIME_ID is valid.
    let rc = unsafe { libc::clock_gettime(libc::CLOCK_PROCESS_CPUTIME_ID, &mut ts) };
    if rc != 0 {
        return 0;
    }
    ts.tv_sec as u64 * 1_000_000 + ts.tv_nsec as u64 / 1000
}

fn time_phase(
    name: &str,
    n: usize,
    flops: f64,
    mut f: impl FnMut() -> Result<(), PolicyError>,
) -> Result<Phase, PolicyError> {
    f()?; // warm-up
    let (mut wall, mut cpu) = (Vec::with_capacity(n), Vec::with_capacity(n));
    for _ in 0..n {
        let (t0, c0) = (Instant::now(), cpu_us());
        f()?;
        wall.push(t0.elapsed().as_micros().max(1) as u64);
        cpu.push(cpu_us().saturating_sub(c0).max(1));
    }
    phase_from(name, flops, &wall, &cpu)
}

/// A model with random weights (a `VarMap`) for `cfg`.
pub fn random_model(cfg: &ModelConfig) -> Result<(PiModel, VarMap), PolicyError> {
    let vm = VarMap::new();
    let vb = VarBuilder::from_varmap(&vm, DType::F32, &Device::Cpu);
    let m = PiModel::new(cfg, vb)?;
    Ok((m, vm))
}

/// A model with random weights held the way a loaded checkpoint holds them (plain tensors, not
/// trainable variables), so the inference fast path (fused projections) is the one measured.
pub fn random_inference_model(cfg: &ModelConfig) -> Result<PiModel, PolicyError> {
    let (_, vm) = random_model(cfg)?;
    let tensors: std::collections::HashMap<String, Tensor> = vm
        .data()
        .lock()
        .map_err(|_| PolicyError::Config("poisoned VarMap".into()))?
        .iter()
        .map(|(k, v)| (k.clone(), v.as_detached_tensor()))
        .collect();
    PiModel::new(
        cfg,
        VarBuilder::from_tensors(tensors, DType::F32, &Device::Cpu),
    )
}

/// Random model-ready inputs with `valid_tokens` valid prompt tokens.
pub fn random_inputs(
    cfg: &ModelConfig,
    batch: usize,
    valid_tokens: usize,
    seed: u64,
) -> Result<ModelInputs, PolicyError> {
    let dev = Device::Cpu;
    let s = cfg.vision.image_size;
    let mut images = Vec::new();
    for i in 0..cfg.cameras.len() {
        let _ = (seed, i);
        images.push(Tensor::rand(-1f32, 1f32, (batch, 3, s, s), &dev)?);
    }
    let lt = cfg.max_token_len;
    let ids: Vec<u32> = (0..batch * lt)
        .map(|i| {
            if i % lt < valid_tokens {
                (i * 7919 % cfg.vocab_size) as u32
            } else {
                0
            }
        })
        .collect();
    Ok(ModelInputs {
        images,
        image_masks: vec![vec![true; batch]; cfg.cameras.len()],
        tokens: Tensor::from_vec(ids, (batch, lt), &dev)?,
        token_mask: vec![(0..lt).map(|i| i < valid_tokens).collect(); batch],
        state: Tensor::randn(0f32, 1f32, (batch, cfg.action_dim), &dev)?,
    })
}

/// A bench configuration (the fixtures' schema) and its `valid_prompt_tokens` (default: all).
fn config_and_valid_tokens(json: &str) -> Result<(ModelConfig, usize), PolicyError> {
    let cfg = ModelConfig::from_json_str(json)?;
    let v: serde_json::Value =
        serde_json::from_str(json).map_err(|e| PolicyError::Config(e.to_string()))?;
    let valid = v["valid_prompt_tokens"]
        .as_u64()
        .unwrap_or(cfg.max_token_len as u64) as usize;
    Ok((cfg, valid))
}

/// One way of running the model in the bench.
struct Variant<'a> {
    model: &'a PiModel,
    precision: &'static str,
    kernels: &'static str,
    /// The packed kernels on (`packed::set_enabled`); off: candle's kernels, the in-run baseline.
    packed: bool,
}

impl Variant<'_> {
    /// Runs `f` with this variant's kernels, restoring the packed kernels afterwards.
    fn with<R>(&self, f: impl FnOnce(&PiModel) -> R) -> R {
        super::packed::set_enabled(self.packed);
        let r = f(self.model);
        super::packed::set_enabled(true);
        r
    }
}

/// Benchmarks one configuration (`json` in the fixtures' schema), from the same random weights,
/// inputs and noise: f32 on the packed kernels, bf16 where a bf16 kernel runs (with the
/// difference of its actions from f32's), and f32 on candle's own kernels (the in-run baseline
/// of the speed ratios). The phases of each variant are timed one after the other; the full
/// sample, the headline figure, is timed in interleaved rounds (one run of each variant per
/// round, and one of openpi's `sample_actions` when `openpi` is given), so that a slow period of
/// this shared VM slows every program alike.
pub fn run_configs(
    name: &str,
    json: &str,
    quick: bool,
    openpi: Option<&OpenpiSetup>,
) -> Result<Vec<ConfigReport>, PolicyError> {
    let (cfg, valid) = config_and_valid_tokens(json)?;
    let steps = cfg.num_denoise_steps;
    let m32 = random_inference_model(&cfg)?;
    let mut m16 = m32.clone();
    let has_bf16 = super::packed::bf16_backend().is_some() && m16.use_bf16()?;
    let inp = random_inputs(&cfg, 1, valid, 1)?;
    let noise = Tensor::randn(
        0f32,
        1f32,
        (1, cfg.action_horizon, cfg.action_dim),
        &Device::Cpu,
    )?;
    let mut variants = vec![Variant {
        model: &m32,
        precision: "f32",
        kernels: match super::packed::support().f32_kernel() {
            "avx-512" => "packed f32, avx-512",
            "avx2" => "packed f32, avx2",
            _ => "candle f32",
        },
        packed: true,
    }];
    let mut rel_diff = None;
    if has_bf16 {
        let a32 = m32.sample(&inp, &noise, steps, None)?.actions;
        let a16 = m16.sample(&inp, &noise, steps, None)?.actions;
        let d = (&a16 - &a32)?.abs()?.max_all()?.to_scalar::<f32>()? as f64;
        let rms = a32.sqr()?.mean_all()?.to_scalar::<f32>()?.sqrt() as f64;
        rel_diff = Some(d / rms.max(1e-12));
        variants.push(Variant {
            model: &m16,
            precision: "bf16",
            kernels: super::packed::bf16_backend().unwrap_or("bf16"),
            packed: true,
        });
    }
    if super::packed::support().f32_packed() {
        variants.push(Variant {
            model: &m32,
            precision: "f32",
            kernels: "candle f32 (in-run baseline)",
            packed: false,
        });
    }
    let (n_fast, n_slow, rounds) = if quick { (3, 1, 3) } else { (20, 5, 20) };
    let p = cfg.prefix_len();
    let s = cfg.suffix_len();
    let prefix_flops = layer_flops(&cfg.paligemma, p, p) * cfg.paligemma.depth as f64;
    let step_flops =
        layer_flops(&cfg.action_expert, cfg.action_horizon, p + s) * cfg.action_expert.depth as f64;
    let unc_step =
        prefix_flops + layer_flops(&cfg.action_expert, s, p + s) * cfg.action_expert.depth as f64;
    let vis = vision_flops(&cfg);
    let total = vis + prefix_flops + steps as f64 * step_flops;
    let openpi_s = OPENPI_SAMPLE_S
        .iter()
        .find(|(n, _)| *n == name)
        .map(|x| x.1)
        .unwrap_or(0.0);
    let mut reports = Vec::new();
    for var in &variants {
        let mut phases = Vec::new();
        var.with(|model| -> Result<(), PolicyError> {
            phases.push(time_phase("vision", n_fast, vis, || {
                model.embed_prefix(&inp)?;
                Ok(())
            })?);
            let embs = model.embed_prefix(&inp)?;
            let mut cache = None;
            phases.push(time_phase("prefix", n_fast, prefix_flops, || {
                model.fill_cache_from_embs(&inp, &embs, &mut cache, false)?;
                Ok(())
            })?);
            let c = cache
                .as_ref()
                .ok_or_else(|| PolicyError::Config("no cache after the prefix pass".into()))?;
            phases.push(time_phase("step_cached", n_fast * 10, step_flops, || {
                model.velocity_at(c, &noise, &[0.5], false)?;
                Ok(())
            })?);
            phases.push(time_phase("step_uncached", n_slow, unc_step, || {
                model.velocity_uncached(&inp, &embs, &noise, &[0.5], false)?;
                Ok(())
            })?);
            if !quick {
                phases.push(time_phase(
                    "sample_uncached",
                    2,
                    vis + steps as f64 * unc_step,
                    || {
                        model.sample(&inp, &noise, steps, None)?;
                        Ok(())
                    },
                )?);
            }
            Ok(())
        })?;
        reports.push(ConfigReport {
            name: name.to_string(),
            phases,
            openpi_s,
            precision: var.precision,
            kernels: var.kernels,
            bf16_rel_action_diff: if var.precision == "bf16" {
                rel_diff
            } else {
                None
            },
            steps,
            openpi_same_run: None,
        });
    }
    // openpi's worker builds and warms up its model before the first round
    let mut worker = match openpi {
        Some(setup) => Some(OpenpiWorker::spawn(setup, name, json)?),
        None => None,
    };
    let (mut op_wall, mut op_cpu) = (Vec::new(), Vec::new());
    // the headline: the full cached sample, interleaved rounds over the variants
    let mut full: Vec<Vec<u64>> = vec![Vec::new(); variants.len()];
    let mut cpu: Vec<Vec<u64>> = vec![Vec::new(); variants.len()];
    let mut caches: Vec<_> = variants.iter().map(|_| None).collect();
    for round in 0..=rounds {
        for (i, var) in variants.iter().enumerate() {
            let (t0, c0) = (Instant::now(), cpu_us());
            var.with(|model| model.sample(&inp, &noise, steps, Some(&mut caches[i])))?;
            // round 0 warms the caches up and is not counted
            if round > 0 {
                full[i].push(t0.elapsed().as_micros().max(1) as u64);
                cpu[i].push(cpu_us().saturating_sub(c0).max(1));
            }
        }
        if let Some(w) = worker.as_mut() {
            // each program starts on idle cores: the other's worker threads (rayon's, OpenMP's)
            // may still spin for a moment after its call
            std::thread::sleep(std::time::Duration::from_millis(20));
            let (wall, cpu) = w.sample()?;
            std::thread::sleep(std::time::Duration::from_millis(20));
            if round > 0 {
                op_wall.push(wall);
                op_cpu.push(cpu);
            }
        }
    }
    if let Some(w) = worker.take() {
        let phase = phase_from("sample", total, &op_wall, &op_cpu)?;
        for r in reports.iter_mut() {
            r.openpi_same_run = Some((phase.clone(), w.info.clone()));
        }
    }
    for (r, (wall, cpu)) in reports.iter_mut().zip(full.iter().zip(&cpu)) {
        r.phases
            .push(phase_from("sample_cached", total, wall, cpu)?);
    }
    Ok(reports)
}

/// A phase from recorded wall and CPU times (µs).
fn phase_from(name: &str, flops: f64, wall: &[u64], cpu: &[u64]) -> Result<Phase, PolicyError> {
    let mut h = histogram()?;
    let mut c = histogram()?;
    let mut hist_ns = latency_histogram_ns();
    for (&w, &u) in wall.iter().zip(cpu) {
        let w = w.min(600_000_000);
        h.record(w)
            .map_err(|e| PolicyError::Config(format!("histogram: {e}")))?;
        c.record(u.clamp(1, 600_000_000))
            .map_err(|e| PolicyError::Config(format!("histogram: {e}")))?;
        let _ = hist_ns.record(w * 1000);
    }
    Ok(Phase {
        name: name.to_string(),
        n: h.len(),
        p50_ms: h.value_at_quantile(0.5) as f64 / 1e3,
        p99_ms: h.value_at_quantile(0.99) as f64 / 1e3,
        flops,
        cpu_ms: c.value_at_quantile(0.5) as f64 / 1e3,
        hist_ns,
    })
}

/// Runs one configuration by name (`pi0_bench` / `pi05_bench`): every variant of
/// [`run_configs`].
pub fn run_named(
    name: &str,
    quick: bool,
    openpi: Option<&OpenpiSetup>,
) -> Result<Vec<ConfigReport>, PolicyError> {
    let (n, json) = CONFIGS
        .iter()
        .find(|(n, _)| *n == name)
        .ok_or_else(|| PolicyError::Config(format!("unknown bench config {name}")))?;
    run_configs(n, json, quick, openpi)
}

/// Runs both bench configurations (`quick`: few iterations, no uncached full sample), each in f32
/// and, where a bf16 kernel runs, in bf16.
pub fn run(quick: bool, openpi: Option<&OpenpiSetup>) -> Result<BenchReport, PolicyError> {
    let mut configs = Vec::new();
    for (name, _) in CONFIGS {
        configs.extend(run_named(name, quick, openpi)?);
    }
    Ok(BenchReport {
        configs,
        threads: candle_core::utils::get_num_threads(),
        cpu: cpu_model(),
    })
}

// ---------------------------------------------------------------------------------------------
// The device bench: full-size presets (or the bench configurations) on any device and dtype.

/// Weights made on the fly for any model: deterministic per tensor name and seed, generated on
/// the host one tensor at a time (in parallel chunks) and copied straight to the device in the
/// requested dtype, so the same seed gives the same model on the CPU and on a GPU, in f32 and in
/// bf16 (before rounding). Values follow the `VarBuilder`'s init hints with matching variance
/// (uniform instead of normal: for timing and precision comparisons the shape is what counts).
pub struct RandomWeights {
    seed: u64,
}

impl RandomWeights {
    /// Weights from `seed`.
    pub fn new(seed: u64) -> Self {
        Self { seed }
    }

    fn values(&self, name: &str, dims: &[usize], init: candle_nn::Init) -> Vec<f32> {
        use rayon::prelude::*;
        let n: usize = dims.iter().product();
        // (offset, half-width) of a uniform distribution with the init's mean and variance
        let (mean, half) = match init {
            candle_nn::Init::Const(v) => (v as f32, 0.0),
            candle_nn::Init::Randn { mean, stdev } => (mean as f32, (stdev * 3f64.sqrt()) as f32),
            candle_nn::Init::Uniform { lo, up } => {
                (((lo + up) / 2.0) as f32, ((up - lo) / 2.0) as f32)
            }
            // Kaiming over the fan-in (a linear's [out, in] weight: the last dim)
            candle_nn::Init::Kaiming { .. } => {
                let fan_in = dims.last().copied().unwrap_or(1).max(1) as f64;
                (0.0, (3.0 / fan_in).sqrt() as f32)
            }
        };
        let mut out = vec![mean; n];
        if half == 0.0 {
            return out;
        }
        let base = name
            .bytes()
            .fold(self.seed ^ 0xcbf2_9ce4_8422_2325, |h, b| {
                (h ^ b as u64).wrapping_mul(0x100_0000_01b3)
            });
        const CHUNK: usize = 1 << 16;
        out.par_chunks_mut(CHUNK).enumerate().for_each(|(ci, c)| {
            let mut s = base ^ (ci as u64).wrapping_mul(0x9e37_79b9_7f4a_7c15);
            for v in c.iter_mut() {
                // splitmix64
                s = s.wrapping_add(0x9e37_79b9_7f4a_7c15);
                let mut z = s;
                z = (z ^ (z >> 30)).wrapping_mul(0xbf58_476d_1ce4_e5b9);
                z = (z ^ (z >> 27)).wrapping_mul(0x94d0_49bb_1331_11eb);
                z ^= z >> 31;
                let u = (z >> 40) as f32 / (1u64 << 24) as f32; // [0, 1)
                *v = mean + half * (2.0 * u - 1.0);
            }
        });
        out
    }
}

impl candle_nn::var_builder::SimpleBackend for RandomWeights {
    fn get(
        &self,
        s: candle_core::Shape,
        name: &str,
        h: candle_nn::Init,
        dtype: DType,
        dev: &Device,
    ) -> candle_core::Result<Tensor> {
        let v = self.values(name, s.dims(), h);
        Tensor::from_vec(v, s, dev)?.to_dtype(dtype)
    }

    fn get_unchecked(&self, name: &str, _: DType, _: &Device) -> candle_core::Result<Tensor> {
        Err(candle_core::Error::Msg(format!(
            "random weights: {name} needs a shape"
        )))
    }

    fn contains_tensor(&self, _name: &str) -> bool {
        // the tied token embedding is read as the LM head; every other name is made on demand
        false
    }
}

/// A model with [`RandomWeights`] on `device` in `dtype` (plain tensors: the inference paths).
pub fn random_model_on(
    cfg: &ModelConfig,
    device: &Device,
    dtype: DType,
    seed: u64,
) -> Result<PiModel, PolicyError> {
    let vb = VarBuilder::from_backend(Box::new(RandomWeights::new(seed)), dtype, device.clone());
    PiModel::new(cfg, vb)
}

/// Model-ready inputs on `device` with `valid_tokens` valid prompt tokens, deterministic in
/// `seed` (images in [-1, 1], state ~ U(-1, 1)).
pub fn random_inputs_on(
    cfg: &ModelConfig,
    valid_tokens: usize,
    seed: u64,
    device: &Device,
) -> Result<ModelInputs, PolicyError> {
    let rw = RandomWeights::new(seed);
    let s = cfg.vision.image_size;
    let u = candle_nn::Init::Uniform { lo: -1.0, up: 1.0 };
    let mut images = Vec::new();
    for c in &cfg.cameras {
        let v = rw.values(&format!("image.{c}"), &[1, 3, s, s], u);
        images.push(Tensor::from_vec(v, (1, 3, s, s), device)?);
    }
    let lt = cfg.max_token_len;
    let ids: Vec<u32> = (0..lt)
        .map(|i| {
            if i < valid_tokens {
                (i * 7919 % cfg.vocab_size) as u32
            } else {
                0
            }
        })
        .collect();
    let state = rw.values("state", &[1, cfg.action_dim], u);
    Ok(ModelInputs {
        images,
        image_masks: vec![vec![true]; cfg.cameras.len()],
        tokens: Tensor::from_vec(ids, (1, lt), device)?,
        token_mask: vec![(0..lt).map(|i| i < valid_tokens).collect()],
        state: Tensor::from_vec(state, (1, cfg.action_dim), device)?,
    })
}

/// A model configuration for the device bench: `pi0` / `pi05` (openpi's full-size presets with
/// the prompt lengths of the openpi H100 reference: 48 tokens, 20 valid / 200 tokens, 60 valid;
/// 3 cameras at 224x224) or a bench configuration (`pi0_bench` / `pi05_bench`). Returns the
/// configuration and its valid prompt tokens.
pub fn device_bench_config(name: &str) -> Result<(ModelConfig, usize), PolicyError> {
    match name {
        "pi0" | "pi05" => {
            let cfg = ModelConfig::preset(name)?;
            let valid = if name == "pi0" { 20 } else { 60 };
            Ok((cfg, valid))
        }
        _ => {
            let (_, json) = CONFIGS.iter().find(|(n, _)| *n == name).ok_or_else(|| {
                PolicyError::Config(format!(
                    "unknown bench preset {name:?}: pi0, pi05, pi0_bench or pi05_bench"
                ))
            })?;
            config_and_valid_tokens(json)
        }
    }
}

/// One phase of the device bench: wall clock around the whole call (device synchronised) and,
/// on a GPU, the device time between two CUDA events around it.
#[derive(Debug, Clone)]
pub struct DevicePhase {
    /// Phase name.
    pub name: String,
    /// Wall time per call (ms), in call order.
    pub wall_ms: Vec<f64>,
    /// Device (CUDA event) time per call (ms); empty on the CPU.
    pub event_ms: Vec<f64>,
}

/// p-quantile (0..=1) of `v` (nearest rank); 0 for an empty slice.
pub fn quantile(v: &[f64], p: f64) -> f64 {
    if v.is_empty() {
        return 0.0;
    }
    let mut s = v.to_vec();
    s.sort_by(f64::total_cmp);
    let i = ((p * s.len() as f64).ceil() as usize).clamp(1, s.len()) - 1;
    s[i]
}

impl DevicePhase {
    /// "p50 / p90 / p99 / max" of the wall times (ms).
    pub fn summary(v: &[f64]) -> String {
        format!(
            "{:.2} / {:.2} / {:.2} / {:.2}",
            quantile(v, 0.5),
            quantile(v, 0.9),
            quantile(v, 0.99),
            quantile(v, 1.0)
        )
    }
}

/// What the device bench measured for one model.
#[derive(Debug, Clone)]
pub struct DeviceReport {
    /// Preset or configuration name.
    pub name: String,
    /// `cpu` or `cuda:N (GPU name)`.
    pub device: String,
    /// Model dtype.
    pub dtype: DType,
    /// Parameters.
    pub params: usize,
    /// Phases: vision, prefix, step, sample.
    pub phases: Vec<DevicePhase>,
    /// Device memory in use after the model was built and at the end (bytes; GPU only).
    pub memory: Option<(u64, u64, u64)>,
    /// Seconds to build the random model.
    pub build_s: f64,
    /// What happened to the CUDA graph of the sample (GPU only), and its check.
    pub graph: Option<String>,
    /// The model dtype's actions against an f32 model's ([`DeviceBenchOptions::check_f32`]).
    pub accuracy: Option<String>,
}

impl DeviceReport {
    /// A phase by name.
    pub fn phase(&self, name: &str) -> Option<&DevicePhase> {
        self.phases.iter().find(|p| p.name == name)
    }
}

impl std::fmt::Display for DeviceReport {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        writeln!(
            f,
            "== {} on {} ({:?}, {:.2} B parameters, built in {:.1} s) ==",
            self.name,
            self.device,
            self.dtype,
            self.params as f64 / 1e9,
            self.build_s
        )?;
        writeln!(
            f,
            "{:<14} {:>6} {:>34} {:>34}",
            "phase",
            "calls",
            "wall ms p50 / p90 / p99 / max",
            "CUDA events ms p50 / p90 / p99 / max"
        )?;
        for p in &self.phases {
            let ev = if p.event_ms.is_empty() {
                "-".to_string()
            } else {
                DevicePhase::summary(&p.event_ms)
            };
            writeln!(
                f,
                "{:<14} {:>6} {:>34} {:>34}",
                p.name,
                p.wall_ms.len(),
                DevicePhase::summary(&p.wall_ms),
                ev
            )?;
        }
        if let Some((model, end, total)) = self.memory {
            writeln!(
                f,
                "device memory in use: {:.2} GB after building the model, {:.2} GB at the end (of {:.1} GB)",
                model as f64 / 1e9,
                end as f64 / 1e9,
                total as f64 / 1e9
            )?;
        }
        if let (Some(g), Some(u)) = (self.phase("step_guided"), self.phase("step_cached")) {
            let (g50, u50) = (quantile(&g.wall_ms, 0.5), quantile(&u.wall_ms, 0.5));
            writeln!(
                f,
                "RTC guided step (forward + vector-Jacobian product) p50 {g50:.2} ms = {:.1}x an unguided step ({u50:.2} ms, both eager)",
                g50 / u50.max(1e-9)
            )?;
        }
        if let Some(g) = &self.graph {
            writeln!(f, "sample as one CUDA graph: {g}")?;
        }
        if let Some(a) = &self.accuracy {
            writeln!(f, "accuracy: {a}")?;
        }
        for s in ["sample", "sample_graph"]
            .iter()
            .filter_map(|n| self.phase(n))
        {
            let p50 = quantile(&s.wall_ms, 0.5);
            for (label, ms) in OPENPI_H100_SAMPLE_MS
                .iter()
                .filter(|(n, _, _)| *n == self.name)
                .flat_map(|(_, eager, compiled)| {
                    [
                        ("openpi eager", *eager),
                        ("openpi compiled (reduce-overhead)", *compiled),
                    ]
                })
            {
                writeln!(
                    f,
                    "{} p50 {p50:.2} ms vs {label} {ms:.1} ms on an H100: {:.2}x",
                    s.name,
                    ms / p50
                )?;
            }
        }
        Ok(())
    }
}

/// openpi's `sample_actions` p50 on an H100 80GB HBM3 (bf16, batch 1, 3 cameras, 10 steps;
/// `benches/data/openpi_h100.json`): (preset, eager ms, torch.compile reduce-overhead ms).
pub const OPENPI_H100_SAMPLE_MS: [(&str, f64, f64); 2] =
    [("pi0", 327.8, 33.3), ("pi05", 266.3, 36.7)];

/// Options of [`run_device`].
#[derive(Debug, Clone)]
pub struct DeviceBenchOptions {
    /// Preset or bench configuration ([`device_bench_config`]).
    pub preset: String,
    /// Where to run.
    pub device: Device,
    /// Model dtype.
    pub dtype: DType,
    /// Timed calls per phase (the step phase runs 10x as many).
    pub calls: usize,
    /// Untimed calls before.
    pub warmup: usize,
    /// Also build the model in f32 (same weights) and compare its actions (needs the memory
    /// of both models).
    pub check_f32: bool,
    /// Only run one eager sample between profiler start and stop, after one warm-up sample
    /// (`ncu --profile-from-start off`), and return an empty report.
    pub profile: bool,
}

/// Builds a random model of `opts.preset` on the device and times the vision pass, the prefix
/// pass (vision + embeddings + KV cache), one cached denoising step and the full sample.
pub fn run_device(opts: &DeviceBenchOptions) -> Result<DeviceReport, PolicyError> {
    let (cfg, valid) = device_bench_config(&opts.preset)?;
    let dev = &opts.device;
    let t0 = Instant::now();
    let model = random_model_on(&cfg, dev, opts.dtype, 7)?;
    let inp = random_inputs_on(&cfg, valid, 11, dev)?;
    let noise = Tensor::from_vec(
        RandomWeights::new(13).values(
            "noise",
            &[1, cfg.action_horizon, cfg.action_dim],
            candle_nn::Init::Randn {
                mean: 0.0,
                stdev: 1.0,
            },
        ),
        (1, cfg.action_horizon, cfg.action_dim),
        dev,
    )?;
    dev.synchronize()?;
    let build_s = t0.elapsed().as_secs_f64();
    let mem_model = super::gpu::memory(dev);
    let steps = cfg.num_denoise_steps;
    let mut cache = None;
    model.fill_cache(&inp, &mut cache, false)?;
    let mut phases = Vec::new();
    if opts.profile {
        model.sample(&inp, &noise, steps, Some(&mut cache))?;
        dev.synchronize()?;
        super::gpu::profiler(true);
        model.sample(&inp, &noise, steps, Some(&mut cache))?;
        dev.synchronize()?;
        super::gpu::profiler(false);
        return Ok(DeviceReport {
            name: format!("{} (profiled one sample)", opts.preset),
            device: super::DeviceSpec::of(dev).to_string(),
            dtype: opts.dtype,
            params: 0,
            phases,
            memory: None,
            build_s,
            graph: None,
            accuracy: None,
        });
    }
    let mut time = |name: &str, n: usize, f: &mut dyn FnMut() -> Result<(), PolicyError>| {
        for _ in 0..opts.warmup {
            f()?;
        }
        dev.synchronize()?;
        let mut p = DevicePhase {
            name: name.to_string(),
            wall_ms: Vec::with_capacity(n),
            event_ms: Vec::with_capacity(n),
        };
        for _ in 0..n {
            let w0 = Instant::now();
            let ev = super::gpu::EventTimer::start(dev);
            f()?;
            let e = ev.stop_ms();
            dev.synchronize()?;
            p.wall_ms.push(w0.elapsed().as_secs_f64() * 1e3);
            p.event_ms.extend(e);
        }
        phases.push(p);
        Ok::<(), PolicyError>(())
    };
    time("vision", opts.calls, &mut || {
        model.vision(&inp)?;
        Ok(())
    })?;
    time("vision+prefix", opts.calls, &mut || {
        model.fill_cache(&inp, &mut cache, false)?;
        Ok(())
    })?;
    {
        let c = cache
            .as_ref()
            .ok_or_else(|| PolicyError::Config("no cache after the prefix pass".into()))?;
        time("step_cached", opts.calls * 10, &mut || {
            model.velocity_at(c, &noise, &[0.5], false)?;
            Ok(())
        })?;
        // a real-time-chunking guided step: a differentiable forward and one vector-Jacobian
        // product through the action expert (candle autograd, op by op)
        let target = super::rtc::GuidanceTarget {
            y: noise.zeros_like()?,
            w: Tensor::ones((1, cfg.action_horizon, cfg.action_dim), DType::F32, dev)?,
            beta: 5.0,
        };
        time("step_guided", opts.calls, &mut || {
            super::rtc::guided_velocity(&model, c, &noise, 0.5, &target)?;
            Ok(())
        })?;
    }
    let mut scache = None;
    time("sample", opts.calls, &mut || {
        // a new observation every call: the prefix pass runs each time
        let out = model.sample(&inp, &noise, steps, Some(&mut scache))?;
        // the chunk's one device -> host copy, as the runtime makes it
        out.actions
            .to_dtype(DType::F32)?
            .flatten_all()?
            .to_vec1::<f32>()?;
        Ok(())
    })?;
    // the whole sample as one captured CUDA graph (GPU), a new observation every call: two
    // observations alternate, and the replay for the second is checked against the eager run
    let mut graph_note = None;
    let inp2 = random_inputs_on(&cfg, valid, 12, dev)?;
    let c = model.prepare_prefix(&inp, &mut scache, true)?;
    match super::graph::SampleGraph::capture(&model, c, &noise, steps) {
        Ok((_, Some(g))) => {
            let mut flip = false;
            time("sample_graph", opts.calls, &mut || {
                flip = !flip;
                model.prepare_prefix(if flip { &inp2 } else { &inp }, &mut scache, true)?;
                let out = g.run(&noise)?;
                out.actions.flatten_all()?.to_vec1::<f32>()?;
                Ok(())
            })?;
            // the prefix pass alone as a graph: how the captured sample's time splits
            let c = model.prepare_prefix(&inp, &mut scache, true)?;
            if let Some(pg) = super::graph::PrefixGraph::capture(&model, c)? {
                time("prefix_graph", opts.calls, &mut || pg.run())?;
            }
            model.prepare_prefix(&inp2, &mut scache, true)?;
            let replay = g.run(&noise)?.actions;
            let eager = model
                .sample(&inp2, &noise, steps, Some(&mut scache))?
                .actions;
            let (d, rms) = diff_rms(&replay, &eager)?;
            graph_note = Some(format!(
                "captured; replay vs eager on another observation: max |diff| {d:.3e}, {:.4} % of the RMS",
                100.0 * d / rms.max(1e-30)
            ));
        }
        Ok((_, None)) => {}
        Err(e) => graph_note = Some(format!("capture failed: {e}")),
    }
    // bf16 against an f32 model with the same weights (eager, same observation and noise)
    let mut accuracy = None;
    if opts.check_f32 && opts.dtype != DType::F32 {
        let low = model.sample(&inp, &noise, steps, None)?.actions;
        drop(scache);
        drop(model);
        let full = random_model_on(&cfg, dev, DType::F32, 7)?;
        let reference = full.sample(&inp, &noise, steps, None)?.actions;
        let (d, rms) = diff_rms(&low, &reference)?;
        accuracy = Some(format!(
            "{:?} vs f32 actions (same weights, inputs and noise): max |diff| {d:.3e}, {:.2} % of the f32 RMS {rms:.3e}",
            opts.dtype,
            100.0 * d / rms.max(1e-30)
        ));
    }
    let params = super::checkpoint::expected_tensors(&cfg)
        .iter()
        .map(|(_, s)| s.iter().product::<usize>())
        .sum();
    let device = match (super::DeviceSpec::of(dev), super::gpu::name(dev)) {
        (d, Some(n)) => format!("{d} ({n})"),
        (d, None) => d.to_string(),
    };
    Ok(DeviceReport {
        name: opts.preset.clone(),
        device,
        dtype: opts.dtype,
        params,
        phases,
        memory: match (mem_model, super::gpu::memory(dev)) {
            (Some((m, _)), Some((e, t))) => Some((m, e, t)),
            _ => None,
        },
        build_s,
        graph: graph_note,
        accuracy,
    })
}

/// Max |a - b| and the RMS of `b` (both as f32).
fn diff_rms(a: &Tensor, b: &Tensor) -> Result<(f32, f32), PolicyError> {
    let (a, b) = (a.to_dtype(DType::F32)?, b.to_dtype(DType::F32)?);
    let d = (&a - &b)?.abs()?.max_all()?.to_scalar::<f32>()?;
    let rms = b.sqr()?.mean_all()?.to_scalar::<f32>()?.sqrt();
    Ok((d, rms))
}
