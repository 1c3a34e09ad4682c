//! `chunkrt sample` and `chunkrt inspect`.

use std::collections::HashMap;
use std::path::PathBuf;

use anyhow::Context;
use candle_core::{DType, Device, Tensor};

use chunkrt_policy::checkpoint;
use chunkrt_policy::config::ConfigOverrides;
use chunkrt_policy::model::ModelInputs;
use chunkrt_policy::preprocess::{resize_with_pad, to_model_chw};
use chunkrt_policy::{model_dtype, DeviceSpec, Precision};

/// `chunkrt sample`: run the policy on a safetensors file of inputs.
#[derive(Debug, clap::Args)]
pub struct SampleArgs {
    /// Checkpoint directory (config.json + model.safetensors).
    #[arg(long)]
    pub checkpoint: PathBuf,
    /// Inputs (safetensors named like the fixtures: `image.<camera>` f32 NCHW or
    /// `image_raw_uint8.<camera>` HWC, `image_mask.<camera>`, `tokenized_prompt`,
    /// `tokenized_prompt_mask`, `state`, `noise`).
    #[arg(long, required_unless_present = "request", conflicts_with = "request")]
    pub inputs: Option<PathBuf>,
    /// Instead of `--inputs`: an openpi request (a msgpack-numpy observation, as an openpi
    /// client sends it) answered exactly as `chunkrt serve` answers it, in this process; the
    /// output is the reply (msgpack-numpy). Its `chunkrt/reseed` seeds the noise.
    #[arg(long)]
    pub request: Option<PathBuf>,
    /// With `--request`: the robot configuration whose `[openpi]` layout and default prompt the
    /// server would use (default: the embedded demo robot's).
    #[arg(long, requires = "request")]
    pub config: Option<PathBuf>,
    /// Output: safetensors (`actions` [B, H, A], `v_t_step0`); with `--request` the reply.
    #[arg(long)]
    pub output: PathBuf,
    /// Denoising steps (default: the checkpoint's).
    #[arg(long)]
    pub steps: Option<usize>,
    /// Run the full joint forward at every step instead of using the prefix KV cache.
    #[arg(long)]
    pub no_cache: bool,
    /// Where to run: cpu, cuda or cuda:N (a GPU needs a build with `--features cuda`).
    #[arg(long, default_value = "cpu")]
    pub device: DeviceSpec,
    /// f32 or bf16 (on a GPU: the model's tensors in bf16; on a CPU: bf16 matrix products where
    /// the CPU has them).
    #[arg(long, default_value = "f32")]
    pub precision: Precision,
    /// Run candle's op-by-op path instead of chunkrt's fused CUDA kernels (to compare them).
    #[arg(long)]
    pub unfused: bool,
    #[command(flatten)]
    pub layout: LayoutArgs,
    /// Compare the output with these outputs (safetensors with `actions`, `v_t_step0`, e.g. a
    /// fixture's openpi outputs): print each tensor's max difference relative to the expected
    /// RMS and fail when one exceeds --rel-tol.
    #[arg(long, value_name = "FILE")]
    pub compare: Option<PathBuf>,
    /// With --compare: the largest max |difference| / RMS accepted.
    #[arg(long, default_value_t = 1e-4, requires = "compare")]
    pub rel_tol: f64,
    /// With --compare: hold only the actions to --rel-tol (v_t_step0 is printed).
    #[arg(long, requires = "compare")]
    pub actions_only: bool,
}

pub use crate::args::LayoutArgs;

/// `chunkrt inspect`: describe a checkpoint.
#[derive(Debug, clap::Args)]
pub struct InspectArgs {
    /// Checkpoint directory.
    pub dir: PathBuf,
    #[command(flatten)]
    pub layout: LayoutArgs,
    /// Also say whether the model fits on this device (cpu, cuda, cuda:N) in `--precision`.
    #[arg(long)]
    pub device: Option<DeviceSpec>,
    /// Precision for `--device`.
    #[arg(long, default_value = "bf16")]
    pub precision: Precision,
    /// Also hold the action statistics against this robot configuration's joint ranges, as
    /// `run` does at load (the embedded demo robot's with `--config default`).
    #[arg(long, value_name = "FILE")]
    pub config: Option<PathBuf>,
}

/// `chunkrt bench-inference` (also `cargo bench --bench inference -- --device ...`).
#[derive(Debug, clap::Args)]
pub struct BenchArgs {
    /// Where to run: cpu, cuda or cuda:N.
    #[arg(long, default_value = "cuda")]
    pub device: DeviceSpec,
    /// pi0, pi05 (openpi's full size), pi0_bench or pi05_bench; default: pi05 then pi0.
    #[arg(long)]
    pub preset: Option<String>,
    /// f32 or bf16 (the model's dtype on a GPU).
    #[arg(long, default_value = "bf16")]
    pub precision: Precision,
    /// Timed calls per phase (a cached step: 10x as many).
    #[arg(long, default_value_t = 30, value_parser = clap::value_parser!(u32).range(1..=10_000))]
    pub calls: u32,
    /// Untimed calls before each phase.
    #[arg(long, default_value_t = 5, value_parser = clap::value_parser!(u32).range(0..=1000))]
    pub warmup: u32,
    /// Run candle's op-by-op path instead of chunkrt's fused CUDA kernels (to compare them).
    #[arg(long)]
    pub unfused: bool,
    /// Also build the model in f32 with the same weights and report how far the --precision
    /// actions are from its actions (needs the memory of both models).
    #[arg(long)]
    pub check_f32: bool,
    /// Profile one eager sample and stop: run under `ncu --profile-from-start off`.
    #[arg(long)]
    pub profile: bool,
    /// Only the sample graphs and the accuracy check (skip the eager phases).
    #[arg(long)]
    pub graphs_only: bool,
    /// Instead of benchmarking: write a checkpoint of --preset (pi0 or pi05) with random
    /// weights in --precision to this directory (model.safetensors, config.json with the byte
    /// stand-in tokenizer), to run `serve` or `run` at full size without a download.
    #[arg(long, value_name = "DIR")]
    pub write_checkpoint: Option<PathBuf>,
}

/// `chunkrt bench-inference`: [`chunkrt_bench::inference::run_device`] for each preset.
pub fn bench(args: BenchArgs) -> anyhow::Result<()> {
    if let Some(dir) = &args.write_checkpoint {
        let preset = args.preset.as_deref().unwrap_or("pi05");
        let dtype = match args.precision {
            Precision::Bf16 => DType::BF16,
            Precision::F32 => DType::F32,
        };
        let t = std::time::Instant::now();
        let (n, bytes) = chunkrt_bench::inference::write_random_checkpoint(preset, dir, dtype, 7)?;
        println!(
            "wrote {} ({preset}, random weights, {n} tensors, {:.2} GB, {dtype:?}) in {:.1} s",
            dir.display(),
            bytes as f64 / 1e9,
            t.elapsed().as_secs_f64()
        );
        return Ok(());
    }
    let device = args.device.open()?;
    chunkrt_policy::kernels::set_enabled(!args.unfused);
    if !device.is_cpu() {
        println!(
            "kernels: {}",
            if args.unfused {
                "candle's op by op (--unfused)"
            } else {
                "chunkrt's fused CUDA kernels"
            }
        );
    }
    let presets = match &args.preset {
        Some(p) => vec![p.clone()],
        None => vec!["pi05".to_string(), "pi0".to_string()],
    };
    for preset in presets {
        let opts = chunkrt_bench::inference::DeviceBenchOptions {
            preset,
            dtype: model_dtype(&device, args.precision),
            device: device.clone(),
            calls: args.calls as usize,
            warmup: args.warmup as usize,
            check_f32: args.check_f32,
            profile: args.profile,
            graphs_only: args.graphs_only,
        };
        println!("{}", chunkrt_bench::inference::run_device(&opts)?);
    }
    Ok(())
}

fn mask_rows(t: &Tensor) -> anyhow::Result<Vec<bool>> {
    Ok(t.flatten_all()?
        .to_dtype(DType::F32)?
        .to_vec1::<f32>()?
        .into_iter()
        .map(|v| v != 0.0)
        .collect())
}

/// `chunkrt sample --request`: one openpi request answered by [`crate::serve::answer`] in this
/// process (the same code `chunkrt serve` runs), the reply written as msgpack-numpy.
fn sample_request(args: &SampleArgs, path: &std::path::Path) -> anyhow::Result<()> {
    let mut cfg = crate::args::load_config(args.config.as_ref(), None)?;
    cfg.policy.device = args.device;
    cfg.policy.precision = args.precision;
    if let Some(s) = args.steps {
        cfg.policy.num_steps = s;
    }
    args.layout.apply(&mut cfg.policy)?;
    let layout = crate::serve::layout_of(&cfg, None)?;
    let pool = chunkrt_controller::inference::policy_pool(&cfg.policy)?;
    let mut opts = cfg.policy.load_options();
    opts.kind = None;
    let mut policy = pool.install(|| chunkrt_policy::Policy::load(&args.checkpoint, &opts))?;
    let bytes = chunkrt_policy::checkpoint::read_bounded(path, 256 << 20)
        .with_context(|| format!("reading {}", path.display()))?;
    let msg = chunkrt_openpi::decode(&bytes, chunkrt_openpi::Limits::default())
        .with_context(|| format!("{}: not msgpack-numpy", path.display()))?;
    let req = chunkrt_openpi::Request::parse(&msg, &layout, &policy.model().cfg.cameras)
        .with_context(|| format!("{}: not an observation", path.display()))?;
    let reply = crate::serve::answer(&mut policy, &pool, &cfg.policy.prompt, &req)
        .map_err(anyhow::Error::msg)?;
    let mut w = chunkrt_openpi::Writer::new();
    reply.write(&mut w);
    std::fs::write(&args.output, &w.buf)
        .with_context(|| format!("writing {}", args.output.display()))?;
    println!(
        "actions [{}, {}] in {:.1} ms -> {}",
        reply.horizon,
        reply.dims,
        reply.policy_infer_ms.unwrap_or(0.0),
        args.output.display()
    );
    Ok(())
}

/// Builds model inputs from a fixture-style safetensors map.
pub fn inputs_from_map(
    cfg: &chunkrt_policy::ModelConfig,
    m: &HashMap<String, Tensor>,
) -> anyhow::Result<(ModelInputs, Option<Tensor>)> {
    let dev = Device::Cpu;
    let tokens = m
        .get("tokenized_prompt")
        .context("inputs: missing tokenized_prompt")?;
    let (b, lt) = tokens.dims2().context("tokenized_prompt must be [B, L]")?;
    anyhow::ensure!(
        lt == cfg.max_token_len,
        "tokenized_prompt has {lt} tokens, the model takes {}",
        cfg.max_token_len
    );
    let tokens = match tokens.dtype() {
        DType::I64 | DType::U32 => tokens.clone(),
        d => anyhow::bail!("tokenized_prompt must be I64 or U32, got {d:?}"),
    };
    let token_mask = match m.get("tokenized_prompt_mask") {
        Some(t) => {
            anyhow::ensure!(
                t.dims() == [b, lt],
                "tokenized_prompt_mask must be [{b}, {lt}]"
            );
            let f = mask_rows(t)?;
            (0..b).map(|i| f[i * lt..(i + 1) * lt].to_vec()).collect()
        }
        None => vec![vec![true; lt]; b],
    };
    let s = cfg.vision.image_size;
    let mut images = Vec::new();
    let mut image_masks = Vec::new();
    for cam in &cfg.cameras {
        let (img, present) = if let Some(t) = m.get(&format!("image.{cam}")) {
            anyhow::ensure!(
                t.dims() == [b, 3, s, s],
                "image.{cam} must be [{b}, 3, {s}, {s}]"
            );
            (t.to_dtype(DType::F32)?, true)
        } else if let Some(t) = m.get(&format!("image_raw_uint8.{cam}")) {
            let (tb, h, w, c) = t.dims4().context("image_raw_uint8 must be [B, H, W, 3]")?;
            anyhow::ensure!(
                tb == b && c == 3 && t.dtype() == DType::U8,
                "image_raw_uint8.{cam} must be U8 [{b}, H, W, 3]"
            );
            let mut out = Vec::with_capacity(b * 3 * s * s);
            for bi in 0..b {
                let px = t.get(bi)?.flatten_all()?.to_vec1::<u8>()?;
                let r = resize_with_pad(&px, h, w, s, s)?;
                to_model_chw(&r, s, s, &mut out);
            }
            (Tensor::from_vec(out, (b, 3, s, s), &dev)?, true)
        } else {
            (Tensor::full(-1f32, (b, 3, s, s), &dev)?, false)
        };
        let mask = match m.get(&format!("image_mask.{cam}")) {
            Some(t) => {
                let v = mask_rows(t)?;
                anyhow::ensure!(v.len() == b, "image_mask.{cam} must have {b} entries");
                v.into_iter().map(|x| x && present).collect()
            }
            None => vec![present; b],
        };
        images.push(img);
        image_masks.push(mask);
    }
    let a = cfg.action_dim;
    let state = match m.get("state") {
        Some(t) => {
            let (sb, sd) = t.dims2().context("state must be [B, D]")?;
            anyhow::ensure!(sb == b && sd <= a, "state must be [{b}, <= {a}]");
            let t = t.to_dtype(DType::F32)?;
            if sd < a {
                t.pad_with_zeros(1, 0, a - sd)?
            } else {
                t
            }
        }
        None => Tensor::zeros((b, a), DType::F32, &dev)?,
    };
    let noise = m.get("noise").map(|t| t.to_dtype(DType::F32)).transpose()?;
    Ok((
        ModelInputs {
            images,
            image_masks,
            tokens,
            token_mask,
            state,
        },
        noise,
    ))
}

/// `chunkrt sample`.
pub fn sample(args: SampleArgs) -> anyhow::Result<()> {
    if let Some(req) = &args.request {
        return sample_request(&args, req);
    }
    let inputs_path = args
        .inputs
        .clone()
        .context("--inputs or --request is required")?;
    let device = args.device.open()?;
    chunkrt_policy::kernels::set_enabled(!args.unfused);
    let dtype = model_dtype(&device, args.precision);
    let loaded = checkpoint::load_with(
        &args.checkpoint,
        &ConfigOverrides::default(),
        &args.layout.options(),
        &device,
        dtype,
    )?;
    let mut model = loaded.model;
    if device.is_cpu() && args.precision == Precision::Bf16 && !model.use_bf16()? {
        eprintln!("sample: this CPU has no bf16 kernel (AMX / AVX512-BF16): running f32");
    }
    let m = candle_core::safetensors::load(&inputs_path, &Device::Cpu)
        .with_context(|| format!("reading {}", inputs_path.display()))?;
    let (inputs, noise) = inputs_from_map(&model.cfg, &m)?;
    let inputs = inputs.to_device(&device)?;
    let b = inputs.batch();
    let noise = match noise {
        Some(n) => n,
        None => Tensor::randn(
            0f32,
            1f32,
            (b, model.cfg.action_horizon, model.cfg.action_dim),
            &Device::Cpu,
        )?,
    }
    .to_device(&device)?;
    let steps = args.steps.unwrap_or(model.cfg.num_denoise_steps);
    let t0 = std::time::Instant::now();
    let out = if args.no_cache {
        model.sample(&inputs, &noise, steps, None)?
    } else {
        let mut cache = None;
        model.sample(&inputs, &noise, steps, Some(&mut cache))?
    };
    let dt = t0.elapsed();
    let actions = out.actions.to_device(&Device::Cpu)?;
    let finite = actions
        .flatten_all()?
        .to_vec1::<f32>()?
        .iter()
        .all(|x| x.is_finite());
    anyhow::ensure!(
        finite,
        "the model produced non-finite actions (NaN or inf): check the checkpoint's weights \
         (nothing written to {})",
        args.output.display()
    );
    let mut save = HashMap::new();
    save.insert("actions".to_string(), actions);
    save.insert(
        "v_t_step0".to_string(),
        out.v_t_step0.to_device(&Device::Cpu)?,
    );
    candle_core::safetensors::save(&save, &args.output)
        .with_context(|| format!("writing {}", args.output.display()))?;
    println!(
        "sampled {:?} actions on {} ({:?}) in {:.1} ms ({} steps, {}) -> {}",
        out.actions.dims(),
        args.device,
        dtype,
        dt.as_secs_f64() * 1e3,
        steps,
        if args.no_cache {
            "no cache"
        } else {
            "prefix KV cache"
        },
        args.output.display()
    );
    if let Some(expected) = &args.compare {
        compare_outputs(expected, &save, args.rel_tol, args.actions_only)?;
    }
    Ok(())
}

/// `sample --compare`: each tensor of `got` that `expected` holds too, as max |difference|
/// relative to the expected tensor's RMS; an error when one held to `rel_tol` exceeds it (NaN
/// fails).
fn compare_outputs(
    expected: &std::path::Path,
    got: &HashMap<String, Tensor>,
    rel_tol: f64,
    actions_only: bool,
) -> anyhow::Result<()> {
    let exp = candle_core::safetensors::load(expected, &Device::Cpu)
        .with_context(|| format!("reading {}", expected.display()))?;
    let mut bad = Vec::new();
    for key in ["actions", "v_t_step0"] {
        let (Some(e), Some(g)) = (exp.get(key), got.get(key)) else {
            continue;
        };
        if e.dims() != g.dims() {
            bad.push(format!(
                "{key}: shape {:?}, expected {:?}",
                g.dims(),
                e.dims()
            ));
            continue;
        }
        let e = e.to_dtype(DType::F64)?;
        let d = (&e - &g.to_dtype(DType::F64)?)?
            .abs()?
            .max_all()?
            .to_scalar::<f64>()?;
        let rms = e.sqr()?.mean_all()?.to_scalar::<f64>()?.sqrt();
        let rel = d / rms.max(1e-30);
        let held = key == "actions" || !actions_only;
        let ok = d.is_finite() && rel <= rel_tol;
        let verdict = match (held, ok) {
            (false, _) => "not held to the tolerance",
            (true, true) => "ok",
            (true, false) => "FAIL",
        };
        println!(
            "{key}: max |diff| {d:.3e}, {:.4} % of the RMS {rms:.3e} ({verdict}, tolerance {:.4} %)",
            100.0 * rel,
            100.0 * rel_tol
        );
        if held && !ok {
            bad.push(format!("{key}: {:.4} % of the RMS", 100.0 * rel));
        }
    }
    anyhow::ensure!(
        bad.is_empty(),
        "the output differs from {}: {}",
        expected.display(),
        bad.join("; ")
    );
    Ok(())
}

/// `chunkrt inspect`.
pub fn inspect(args: InspectArgs) -> anyhow::Result<()> {
    print!(
        "{}",
        checkpoint::inspect(&args.dir, &args.layout.options())?
    );
    // the verdict `run` and `serve` would give at load (with a robot: its joint ranges too)
    let robot = match &args.config {
        Some(p) if p.as_os_str() == "default" => {
            Some(chunkrt_controller::config::Config::embedded_default())
        }
        Some(p) => Some(chunkrt_controller::config::Config::load(p)?),
        None => None,
    };
    let verdict = match &robot {
        Some(cfg) => checkpoint::verdict_for_robot(
            &args.dir,
            &args.layout.options(),
            &chunkrt_controller::inference::joint_ranges(cfg),
        ),
        None => checkpoint::verdict(&args.dir, &args.layout.options()),
    };
    if let Err(e) = verdict {
        println!("REFUSED at load: {e}");
        anyhow::bail!("{}: would not load: {e}", args.dir.display());
    }
    match &robot {
        Some(cfg) => println!(
            "loads: yes (the statistics pass the checks run and serve make, and fit robot \
             '{}''s joint ranges)",
            cfg.robot.name
        ),
        None => println!(
            "loads: yes (the statistics pass the checks run and serve make; --config FILE \
             also holds them against a robot's joint ranges)"
        ),
    }
    if let Some(spec) = args.device {
        let device = spec.open()?;
        let need = checkpoint::model_bytes(&args.dir, model_dtype(&device, args.precision))?;
        print!(
            "on {spec} in {}: weights {:.2} GB",
            args.precision,
            need as f64 / 1e9
        );
        match chunkrt_policy::gpu::memory(&device) {
            Some((used, total)) => {
                let free = total.saturating_sub(used);
                println!(
                    ", device free {:.2} GB of {:.2} GB: {}",
                    free as f64 / 1e9,
                    total as f64 / 1e9,
                    if need < free { "fits" } else { "does NOT fit" }
                );
            }
            None => println!(" (host memory)"),
        }
    }
    Ok(())
}
