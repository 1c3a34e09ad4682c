//! The inference benchmark (core of `benches/inference.rs`): random weights built in-process from
//! the bench configurations, p50 / p99 (hdrhistogram) of each phase, cached vs uncached, GFLOP/s.
//! The device bench (`chunkrt bench-inference`: full-size presets on a GPU or the CPU) is in
//! [`device`].

use std::time::Instant;

use candle_core::{DType, Device, Tensor};
use candle_nn::{VarBuilder, VarMap};
use hdrhistogram::Histogram;

use crate::histlog::write_row;
use crate::openpi::{OpenpiInfo, OpenpiSetup, OpenpiWorker};
use chunkrt_policy::config::{GemmaDims, ModelConfig};
use chunkrt_policy::model::{ModelInputs, PiModel};
use chunkrt_policy::PolicyError;

mod device;

pub use device::*;

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
    /// The interleaved full samples split into their parts, means over the same samples (ms):
    /// vision (image and token embeddings), prefix pass, denoising loop, whole sample.
    pub split_ms: Option<[f64; 4]>,
    /// A cached step split by op kind ([`chunkrt_policy::ops::profile`]): (kind, ms per step), then the
    /// profiled steps' mean (ms); the rest of the step runs outside the seam.
    pub step_split: Option<OpSplit>,
    /// The prefix pass (from the embeddings, as phase `prefix`) split the same way.
    pub prefix_split: Option<OpSplit>,
    /// openpi's `sample_actions` timed in this run, interleaved with the variants' full samples
    /// (phase `sample`), and what its worker reported; `None`: the stored figure
    /// [`ConfigReport::openpi_s`] is the reference.
    pub openpi_same_run: Option<(Phase, OpenpiInfo)>,
}

impl ConfigReport {
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
            chunkrt_policy::packed::support().f32_kernel(),
            self.threads
        )?;
        for c in &self.configs {
            writeln!(f, "== {} ({}, {}) ==", c.name, c.precision, c.kernels)?;
            let widths = [5, 10, 10, 9, 10, 12];
            let head = ["n", "p50 ms", "p99 ms", "GFLOP/s", "cpu ms", "GFLOP/cpu-s"];
            write_row(f, "phase", 16, &head.map(String::from), &widths)?;
            for p in &c.phases {
                let cells = [
                    p.n.to_string(),
                    format!("{:.2}", p.p50_ms),
                    format!("{:.2}", p.p99_ms),
                    format!("{:.1}", p.gflops()),
                    format!("{:.2}", p.cpu_ms),
                    format!("{:.1}", p.flops / (p.cpu_ms * 1e-3) / 1e9),
                ];
                write_row(f, &p.name, 16, &cells, &widths)?;
            }
            for (what, split) in [
                ("a cached step", &c.step_split),
                ("the prefix pass", &c.prefix_split),
            ] {
                let Some((kinds, total)) = split else {
                    continue;
                };
                let inside: f64 = kinds.iter().map(|k| k.1).sum();
                let pct = |ms: f64| 100.0 * ms / total.max(1e-9);
                let parts: Vec<String> = kinds
                    .iter()
                    .map(|(name, ms)| format!("{name} {ms:.2} ({:.0} %)", pct(*ms)))
                    .collect();
                writeln!(
                    f,
                    "{what} by op kind (profiled, ms): {}, outside the seam {:.2} ({:.0} %) = {total:.2}",
                    parts.join(", "),
                    total - inside,
                    pct(total - inside)
                )?;
            }
            if let Some([v, p, l, t]) = c.split_ms {
                let alone = c.phase("step_cached").map_or(0.0, |s| s.p50_ms);
                writeln!(
                    f,
                    "the full samples split (means of the same samples): vision {v:.1} + prefix {p:.1} + {} steps {l:.1} ({:.2} a step; {alone:.2} timed alone) = {:.1} of {t:.1} ms",
                    c.steps,
                    l / c.steps.max(1) as f64,
                    v + p + l,
                )?;
            }
            if let Some((p, info)) = &c.openpi_same_run {
                writeln!(
                    f,
                    "{:<16} {:>5} {:>10.2} {:>10.2} {:>9} {:>10.2}   (openpi PyTorch, this run: torch {} (ATen {}), {} threads, {:.1} M parameters)",
                    "openpi sample",
                    p.n,
                    p.p50_ms,
                    p.p99_ms,
                    "",
                    p.cpu_ms,
                    info.torch,
                    info.cpu_capability,
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
            let torch_wider = self.configs.iter().any(|c| {
                c.openpi_same_run
                    .as_ref()
                    .is_some_and(|(_, i)| i.cpu_capability.starts_with("AVX512"))
            });
            if torch_wider && chunkrt_policy::packed::support().f32_kernel() == "avx2" {
                writeln!(
                    f,
                    "note: chunkrt's kernels are capped to AVX2 but torch runs its AVX512 kernels; \
                     ATEN_CPU_CAPABILITY=avx2 MKL_ENABLE_INSTRUCTIONS=AVX2 ONEDNN_MAX_CPU_ISA=AVX2 \
                     cap it too"
                )?;
            }
        } else {
            writeln!(
                f,
                "openpi: fell back to stored figures ({OPENPI_SAMPLE_CPU}); this run's CPU: {}; \
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

/// A pass's time by op kind: (kind, ms per call), then the profiled calls' mean (ms).
pub type OpSplit = (Vec<(&'static str, f64)>, f64);

/// `n` calls of `f` with each op kind's time counted at the seam ([`chunkrt_policy::ops::profile`]):
/// (kind, ms per call) and the profiled calls' mean (ms).
fn split_by_kind(
    n: usize,
    mut f: impl FnMut() -> Result<(), PolicyError>,
) -> Result<OpSplit, PolicyError> {
    let n = n.max(1);
    chunkrt_policy::ops::profile::reset();
    chunkrt_policy::ops::profile::enable(true);
    let t0 = Instant::now();
    let run = (0..n).try_for_each(|_| f());
    let per_call = t0.elapsed().as_secs_f64() * 1e3 / n as f64;
    chunkrt_policy::ops::profile::enable(false);
    run?;
    let kinds = chunkrt_policy::ops::profile::snapshot()
        .into_iter()
        .map(|(k, ns, _)| (k.name(), ns as f64 * 1e-6 / n as f64))
        .collect();
    Ok((kinds, per_call))
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
        chunkrt_policy::packed::set_enabled(self.packed);
        let r = f(self.model);
        chunkrt_policy::packed::set_enabled(true);
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
    let has_bf16 = chunkrt_policy::packed::bf16_backend().is_some() && m16.use_bf16()?;
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
        kernels: match chunkrt_policy::packed::support().f32_kernel() {
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
            kernels: chunkrt_policy::packed::bf16_backend().unwrap_or("bf16"),
            packed: true,
        });
    }
    if chunkrt_policy::packed::support().f32_packed() {
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
        let (mut step_split, mut prefix_split) = (None, None);
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
            // the same passes again, each op kind's time counted at the seam
            let mut cache2 = None;
            prefix_split = Some(split_by_kind(n_fast, || {
                model.fill_cache_from_embs(&inp, &embs, &mut cache2, false)?;
                Ok(())
            })?);
            step_split = Some(split_by_kind(n_fast * 10, || {
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
            split_ms: None,
            step_split,
            prefix_split,
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
    // per variant, summed over the counted rounds: vision, prefix, loop, whole sample (ms)
    let mut split = vec![[0f64; 4]; variants.len()];
    for round in 0..=rounds {
        for (i, var) in variants.iter().enumerate() {
            let (t0, c0) = (Instant::now(), cpu_us());
            // `PiModel::sample` with a cache, in its three parts, each timed
            let parts = var.with(|model| -> Result<[f64; 3], PolicyError> {
                let embs = model.embed_prefix(&inp)?;
                let t1 = t0.elapsed();
                model.fill_cache_from_embs(&inp, &embs, &mut caches[i], false)?;
                let t2 = t0.elapsed();
                let c = caches[i]
                    .as_ref()
                    .ok_or_else(|| PolicyError::Config("no cache after the prefix pass".into()))?;
                model.denoise(c, &noise, steps)?;
                let t3 = t0.elapsed();
                let ms = |d: std::time::Duration| d.as_secs_f64() * 1e3;
                Ok([ms(t1), ms(t2 - t1), ms(t3 - t2)])
            })?;
            // round 0 warms the caches up and is not counted
            if round > 0 {
                let wall = t0.elapsed();
                full[i].push(wall.as_micros().max(1) as u64);
                cpu[i].push(cpu_us().saturating_sub(c0).max(1));
                for (acc, v) in split[i].iter_mut().zip(parts) {
                    *acc += v;
                }
                split[i][3] += wall.as_secs_f64() * 1e3;
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
    let counted = rounds.max(1) as f64;
    for (r, s) in reports.iter_mut().zip(&split) {
        r.split_ms = Some(s.map(|v| v / counted));
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
