//! The device bench: full-size presets (or the bench configurations) on any device and dtype,
//! with weights made on the fly ([`RandomWeights`]).

use std::time::Instant;

use candle_core::{DType, Device, Tensor};
use candle_nn::VarBuilder;

use super::*;

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

    /// The wall-time p50s (ms) of phases `a` and `b`, when both ran.
    fn p50s(&self, a: &str, b: &str) -> Option<(f64, f64)> {
        let p50 = |p: &DevicePhase| quantile(&p.wall_ms, 0.5);
        Some((p50(self.phase(a)?), p50(self.phase(b)?)))
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
            "{:<20} {:>6} {:>34} {:>34}",
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
                "{:<20} {:>6} {:>34} {:>34}",
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
        if let Some((g50, u50)) = self.p50s("step_guided", "step_cached") {
            writeln!(
                f,
                "RTC guided step (forward + vector-Jacobian product) p50 {g50:.2} ms = {:.1}x an unguided step ({u50:.2} ms, both eager)",
                g50 / u50.max(1e-9)
            )?;
        }
        if let Some((g50, u50)) = self.p50s("step_guided_identity", "step_cached") {
            writeln!(
                f,
                "RTC guided step with the identity Jacobian (rtc_jacobian = \"identity\") p50 {g50:.2} ms = {:.2}x an unguided step",
                g50 / u50.max(1e-9)
            )?;
        }
        if let Some((c50, u50)) = self.p50s("sample_committed", "sample") {
            writeln!(
                f,
                "training-time RTC sample (a quarter of the chunk committed) p50 {c50:.2} ms = {:.2}x an unguided sample ({u50:.2} ms, both eager)",
                c50 / u50.max(1e-9)
            )?;
        }
        if let Some(g) = &self.graph {
            writeln!(f, "sample as one CUDA graph: {g}")?;
        }
        if let Some((g50, u50)) = self.p50s("sample_graph_guided", "sample_graph") {
            writeln!(
                f,
                "RTC-guided sample (identity Jacobian) as one CUDA graph p50 {g50:.2} ms = {:.2}x the plain graph",
                g50 / u50.max(1e-9)
            )?;
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
    /// Skip the eager phases (vision, prefix, steps, eager samples): only the graphs and the
    /// accuracy check.
    pub graphs_only: bool,
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
    let mem_model = chunkrt_policy::gpu::memory(dev);
    let steps = cfg.num_denoise_steps;
    let mut cache = None;
    model.fill_cache(&inp, &mut cache, false)?;
    let mut phases = Vec::new();
    if opts.profile {
        model.sample(&inp, &noise, steps, Some(&mut cache))?;
        dev.synchronize()?;
        chunkrt_policy::gpu::profiler(true);
        model.sample(&inp, &noise, steps, Some(&mut cache))?;
        dev.synchronize()?;
        chunkrt_policy::gpu::profiler(false);
        return Ok(DeviceReport {
            name: format!("{} (profiled one sample)", opts.preset),
            device: chunkrt_policy::DeviceSpec::of(dev).to_string(),
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
            let ev = chunkrt_policy::gpu::EventTimer::start(dev);
            f()?;
            let e = ev.stop_ms();
            dev.synchronize()?;
            p.wall_ms.push(w0.elapsed().as_secs_f64() * 1e3);
            p.event_ms.extend(e);
        }
        phases.push(p);
        Ok::<(), PolicyError>(())
    };
    if !opts.graphs_only {
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
            let target = chunkrt_policy::rtc::GuidanceTarget {
                y: noise.zeros_like()?,
                w: Tensor::ones((1, cfg.action_horizon, cfg.action_dim), DType::F32, dev)?,
                beta: 5.0,
                jacobian: chunkrt_policy::rtc::Jacobian::Vjp,
            };
            time("step_guided", opts.calls, &mut || {
                chunkrt_policy::rtc::guided_velocity(&model, c, &noise, 0.5, &target)?;
                Ok(())
            })?;
            // the same with ∂Â/∂x_t ≈ I: one fast forward and a few element-wise ops
            let target = chunkrt_policy::rtc::GuidanceTarget {
                jacobian: chunkrt_policy::rtc::Jacobian::Identity,
                ..target
            };
            time("step_guided_identity", opts.calls * 10, &mut || {
                chunkrt_policy::rtc::guided_velocity(&model, c, &noise, 0.5, &target)?;
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
        // training-time RTC: the same sample with a quarter of the chunk given as committed actions
        // (per-token flow times; what `strategy = "rtc_trained"` runs)
        let committed = (cfg.action_horizon / 4).max(1);
        time("sample_committed", opts.calls, &mut || {
            model.fill_cache(&inp, &mut scache, false)?;
            let c = scache
                .as_ref()
                .ok_or_else(|| PolicyError::Config("no cache after the prefix pass".into()))?;
            let out = model.denoise_committed(c, &noise, steps, &noise, &[committed])?;
            out.actions.flatten_all()?.to_vec1::<f32>()?;
            Ok(())
        })?;
    }
    let mut scache = None;
    // the whole sample as one captured CUDA graph (GPU), a new observation every call: two
    // observations alternate, and the replay for the second is checked against the eager run
    let mut graph_note = None;
    let inp2 = random_inputs_on(&cfg, valid, 12, dev)?;
    let c = model.prepare_prefix(&inp, &mut scache, true)?;
    match chunkrt_policy::graph::SampleGraph::capture(&model, c, &noise, steps) {
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
            if let Some(pg) = chunkrt_policy::graph::PrefixGraph::capture(&model, c)? {
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
    // RTC's guided sample (identity Jacobian, the default) as one captured graph, with the
    // first half of the chunk guided towards a previous chunk; its target is rewritten before
    // every replay, as the runtime does
    let mut w = vec![0f32; cfg.action_horizon];
    for (i, w) in w.iter_mut().enumerate().take(cfg.action_horizon / 2) {
        *w = 1.0 - i as f32 / cfg.action_horizon as f32;
    }
    let target = chunkrt_policy::rtc::GuidanceTarget {
        y: noise.zeros_like()?,
        w: chunkrt_policy::rtc::weight_mask(&w, cfg.action_dim, cfg.action_dim, dev)?,
        beta: 10.0,
        jacobian: chunkrt_policy::rtc::Jacobian::Identity,
    };
    let c = model.prepare_prefix(&inp, &mut scache, true)?;
    match chunkrt_policy::graph::SampleGraph::capture_guided(&model, c, &noise, steps, &target) {
        Ok((_, Some(g))) => {
            let mut flip = false;
            time("sample_graph_guided", opts.calls, &mut || {
                flip = !flip;
                model.prepare_prefix(if flip { &inp2 } else { &inp }, &mut scache, true)?;
                let out = g.run_guided(&noise, &target)?;
                out.actions.flatten_all()?.to_vec1::<f32>()?;
                Ok(())
            })?;
            // the guided graph against RTC's eager guided loop on another observation
            let c = model.prepare_prefix(&inp2, &mut scache, true)?;
            let replay = g.run_guided(&noise, &target)?.actions;
            model.run_prefix(c, None, false)?;
            let eager =
                chunkrt_policy::rtc::denoise_guided(&model, c, &noise, steps, &target)?.actions;
            let (d, rms) = diff_rms(&replay, &eager)?;
            let note = graph_note.get_or_insert_with(String::new);
            note.push_str(&format!(
                "; guided graph vs the eager guided loop on another observation: max |diff| {d:.3e}, {:.4} % of the RMS",
                100.0 * d / rms.max(1e-30)
            ));
        }
        Ok((_, None)) => {}
        Err(e) => {
            let note = graph_note.get_or_insert_with(String::new);
            note.push_str(&format!("; guided capture failed: {e}"));
        }
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
    let params = chunkrt_policy::checkpoint::expected_tensors(&cfg)
        .iter()
        .map(|(_, s)| s.iter().product::<usize>())
        .sum();
    let device = match (
        chunkrt_policy::DeviceSpec::of(dev),
        chunkrt_policy::gpu::name(dev),
    ) {
        (d, Some(n)) => format!("{d} ({n})"),
        (d, None) => d.to_string(),
    };
    Ok(DeviceReport {
        name: opts.preset.clone(),
        device,
        dtype: opts.dtype,
        params,
        phases,
        memory: match (mem_model, chunkrt_policy::gpu::memory(dev)) {
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

/// The initialisation a random checkpoint gives tensor `name` (openpi's key names): biases 0,
/// SigLIP's LayerNorm weights 1, Gemma's RMSNorm weights 0 (the norm scales by `1 + w`), every
/// other weight uniform with Kaiming's variance over its last dimension.
fn checkpoint_init(name: &str) -> candle_nn::Init {
    let layer_norm = name.contains("layer_norm") || name.contains("post_layernorm");
    if name.ends_with(".bias") {
        candle_nn::Init::Const(0.0)
    } else if name.contains("vision_tower") && layer_norm && name.ends_with(".weight") {
        candle_nn::Init::Const(1.0)
    } else if name.ends_with("norm.weight") {
        candle_nn::Init::Const(0.0)
    } else {
        candle_nn::init::DEFAULT_KAIMING_NORMAL
    }
}

/// Writes a checkpoint directory of preset `preset` (`pi0`, `pi05`) with random weights in
/// `dtype`: `model.safetensors` under openpi's key names, a `config.json` in the fixtures'
/// schema with the byte stand-in tokenizer (no tokenizer file, no statistics: actions come back
/// un-normalised). For running `chunkrt serve` and `run` at full size where no real checkpoint
/// can be downloaded (the GPU machine has no network). Returns (tensors, bytes written).
pub fn write_random_checkpoint(
    preset: &str,
    dir: &std::path::Path,
    dtype: DType,
    seed: u64,
) -> Result<(usize, u64), PolicyError> {
    let (cfg, _) = device_bench_config(preset)?;
    std::fs::create_dir_all(dir)
        .map_err(|e| PolicyError::Config(format!("cannot create {}: {e}", dir.display())))?;
    let rw = RandomWeights::new(seed);
    let mut tensors = std::collections::HashMap::new();
    let mut bytes = 0u64;
    for (name, shape) in chunkrt_policy::checkpoint::expected_tensors(&cfg) {
        let v = rw.values(&name, &shape, checkpoint_init(&name));
        let t = Tensor::from_vec(v, shape.as_slice(), &Device::Cpu)?.to_dtype(dtype)?;
        bytes += (t.elem_count() * dtype.size_in_bytes()) as u64;
        tensors.insert(name, t);
    }
    let n = tensors.len();
    candle_core::safetensors::save(&tensors, dir.join("model.safetensors"))?;
    let config = serde_json::json!({
        "name": format!("{preset}_random"),
        "about": "random weights written by `chunkrt bench-inference --write-checkpoint` (not a trained policy)",
        "model_kind": if cfg.kind == chunkrt_policy::ModelKind::Pi05 { "pi05" } else { "pi0" },
        "vision": {
            "hidden_size": cfg.vision.hidden_size,
            "num_hidden_layers": cfg.vision.num_hidden_layers,
            "num_attention_heads": cfg.vision.num_attention_heads,
            "intermediate_size": cfg.vision.intermediate_size,
            "patch_size": cfg.vision.patch_size,
            "image_size": cfg.vision.image_size,
            "layer_norm_eps": cfg.vision.layer_norm_eps,
        },
        "paligemma": cfg.paligemma,
        "action_expert": cfg.action_expert,
        "vocab_size": cfg.vocab_size,
        "action_dim": cfg.action_dim,
        "action_horizon": cfg.action_horizon,
        "max_token_len": cfg.max_token_len,
        "image_keys_in_order": cfg.cameras,
        "num_denoise_steps": cfg.num_denoise_steps,
        "tokenizer": "byte_stand_in",
    });
    let text = serde_json::to_string_pretty(&config)
        .map_err(|e| PolicyError::Config(format!("config.json: {e}")))?;
    std::fs::write(dir.join("config.json"), text)
        .map_err(|e| PolicyError::Config(format!("cannot write config.json: {e}")))?;
    Ok((n, bytes))
}
