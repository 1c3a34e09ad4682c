//! The runtime API for the controller's inference thread: load once, then
//! `infer(&RawObservation, &Conditioning) -> [H][n_dof]` actions in robot units. The prefix KV cache buffers are
//! kept across calls.

use std::path::Path;

use candle_core::Tensor;
use rand::{Rng, SeedableRng};

use super::checkpoint;
use super::config::{ConfigOverrides, ModelKind};
use super::device::{DeviceSpec, Precision};
use super::graph::SampleGraph;
use super::layout::{LayoutOptions, TokenizerFile};
use super::model::{ModelInputs, PiModel, PrefixCache};
use super::openpi_config::{model_state, robot_actions, ModelState, OpenpiConfig};
use super::preprocess::{
    discretize_state, resize_with_pad, to_model_chw, to_rgb, Encoding, NormMode, NormStats,
    PromptStyle, PromptTokenizer,
};
pub use super::rtc::Guidance;
use super::rtc::{check_target, denoise_guided, model_space_actions, GuidanceTarget, Jacobian};
use crate::error::PolicyError;

/// One camera frame as received over IPC (fields as in `CameraFrameHeader`).
#[derive(Debug, Clone, Copy)]
pub struct RawFrame<'a> {
    /// Camera name (the policy's image key, e.g. `base_0_rgb`).
    pub camera: &'a str,
    /// Pixels per row.
    pub width: u32,
    /// Rows.
    pub height: u32,
    /// Bytes per row.
    pub stride: u32,
    /// Pixel layout.
    pub encoding: Encoding,
    /// Pixel bytes.
    pub data: &'a [u8],
}

/// One observation: frames by camera name (missing cameras are embedded black and masked), the
/// joint positions (robot DoF, robot units) and the prompt.
#[derive(Debug, Clone, Copy)]
pub struct RawObservation<'a> {
    /// Frames.
    pub frames: &'a [RawFrame<'a>],
    /// Joint positions.
    pub joint_positions: &'a [f64],
    /// Task prompt.
    pub prompt: &'a str,
}

/// How a chunk is conditioned on the chunk the robot is executing (real-time chunking): the
/// one public description, for [`Policy::infer`] and for anything that carries the request
/// elsewhere (the openpi protocol's chunkrt keys).
#[derive(Debug, Clone, Copy, Default)]
pub enum Conditioning<'a> {
    /// Not at all: plain sampling.
    #[default]
    Fresh,
    /// Inference-time RTC: the sampler is guided towards the previous chunk's remaining
    /// actions ([`Guidance`]). β = 0 or all-zero weights give exactly the fresh chunk for the
    /// same noise. The prefix is normalised with the action norm stats and padded to the action
    /// dim; the padded dims are not guided.
    Guided(Guidance<'a>),
    /// Training-time RTC: the actions the robot executes while the chunk is computed
    /// (`[d][n_dof]` row-major, robot units, d ≥ 0 rows from where the chunk starts); the chunk
    /// starts with exactly them (to f32 rounding) and continues them. Only for a checkpoint
    /// trained with a committed prefix (`rtc_prefix_max` in its `config.json`; an error
    /// otherwise); d is clipped to that maximum. Costs what a fresh chunk costs.
    Committed(&'a [f64]),
}

/// How a chunk continues the previous one, in the model's space.
#[derive(Clone, Copy)]
enum Continue<'a> {
    /// Not at all: plain sampling.
    Fresh,
    /// Inference-time RTC: guided towards the target.
    Guided(&'a GuidanceTarget),
    /// Training-time RTC: the first d actions given ([1, H, A], model space).
    Committed(&'a Tensor, usize),
}

/// The noise seed a freshly loaded policy starts from ([`Policy::reseed`] restarts it).
pub const DEFAULT_SEED: u64 = 0x5eed;

/// A loaded policy with its reusable buffers.
pub struct Policy {
    model: PiModel,
    tokenizer: PromptTokenizer,
    norm: Option<NormStats>,
    steps: usize,
    cache: Option<PrefixCache>,
    rng: rand_chacha::ChaCha8Rng,
    images: Vec<f32>,
    noise: Vec<f32>,
    /// Added to each action row after un-normalisation: the observed joint position on the
    /// model's delta dims (`ModelConfig::delta_action_mask`), 0 on the others.
    offsets: Vec<f64>,
    /// The captured samples (GPU): [plain, RTC-guided], and whether to (still) try each.
    graph: [Option<SampleGraph>; 2],
    graph_on: [bool; 2],
    /// The last prompt warned about as truncated (one warning per prompt, not per inference).
    truncated_prompt: Option<String>,
    /// π0.5: the state's length in the prompt (LeRobot pads it; `None`: the robot's values).
    state_prompt_dim: Option<usize>,
    /// How π0 prompts are built.
    prompt_style: PromptStyle,
    /// A LeRobot checkpoint: π0.5's prompt state is binned from its f32 normalisation (openpi's
    /// from the f64 one).
    lerobot: bool,
    /// openpi's training config whose transforms wrap the model ([`crate::openpi_config`]).
    openpi: Option<&'static OpenpiConfig>,
}

/// How to load a policy (the controller builds this from its `[policy]` configuration).
#[derive(Debug, Clone)]
pub struct LoadOptions {
    /// The kind the caller expects (`None`: whatever the checkpoint is).
    pub kind: Option<ModelKind>,
    /// Denoising steps.
    pub num_steps: usize,
    /// Arithmetic of the matrix products ([`super::device`]).
    pub precision: Precision,
    /// Where the model, its KV cache and its inputs live.
    pub device: DeviceSpec,
    /// Overrides of the checkpoint's dimensions.
    pub overrides: ConfigOverrides,
    /// On a GPU, replay each sample (prefix pass and denoising loop) as one captured CUDA graph
    /// ([`super::graph`]); it falls back to eager by itself if capture fails or disagrees.
    pub cuda_graph: bool,
    /// Where the tokenizer is when not in the checkpoint, and which openpi asset id.
    pub layout: LayoutOptions,
}

impl Default for LoadOptions {
    fn default() -> Self {
        Self {
            kind: None,
            num_steps: 10,
            precision: Precision::F32,
            device: DeviceSpec::Cpu,
            overrides: ConfigOverrides::default(),
            cuda_graph: true,
            layout: LayoutOptions::default(),
        }
    }
}

impl Policy {
    /// Loads `checkpoint_dir` (`model.safetensors`, `config.json` or a preset by kind, optional
    /// `tokenizer.json` and `norm_stats.json`) onto `opts.device`, each weight read from the
    /// file straight into the model's dtype on that device. Thread pools are the caller's
    /// business: CPU work runs on the current rayon pool (call inside a pool's `install`).
    pub fn load(checkpoint_dir: &Path, opts: &LoadOptions) -> Result<Self, PolicyError> {
        let device = opts.device.open()?;
        let mut overrides = opts.overrides.clone();
        overrides.num_denoise_steps = Some(opts.num_steps);
        let dtype = super::device::model_dtype(&device, opts.precision);
        if let Some((used, total)) = super::gpu::memory(&device) {
            let need = checkpoint::model_bytes(checkpoint_dir, dtype)?;
            let free = total.saturating_sub(used);
            // weights plus a margin for the KV cache, activations and cuBLAS workspaces
            if need + need / 10 + (1 << 30) > free {
                return Err(PolicyError::Config(format!(
                    "the model does not fit on {}: its weights take {:.2} GB in {}, the GPU has \
                     {:.2} GB free of {:.2} GB (try precision = \"bf16\", or free the GPU)",
                    opts.device,
                    need as f64 / 1e9,
                    opts.precision,
                    free as f64 / 1e9,
                    total as f64 / 1e9
                )));
            }
        }
        let loaded =
            checkpoint::load_with(checkpoint_dir, &overrides, &opts.layout, &device, dtype)?;
        let layout = loaded.layout;
        let mut model = loaded.model;
        if device.is_cpu() && opts.precision == Precision::Bf16 && !model.use_bf16()? {
            tracing::warn!("policy.precision = bf16 needs Intel AMX or AVX512-BF16, which this CPU does not offer: running f32");
        }
        if let Some(kind) = opts.kind {
            if kind != model.cfg.kind {
                return Err(PolicyError::Config(format!(
                    "policy.kind = {} but the checkpoint is {}",
                    kind.name(),
                    model.cfg.kind.name()
                )));
            }
        }
        // Every upload of the weights has landed before another thread (the controller's
        // inference thread, with its own per-thread CUDA stream) uses them.
        device.synchronize()?;
        tracing::info!(
            "{}: {} layout",
            checkpoint_dir.display(),
            layout.kind.name()
        );
        for n in &layout.notes {
            tracing::info!("  {n}");
        }
        let tokenizer = match &layout.tokenizer {
            TokenizerFile::Json(p) => PromptTokenizer::from_file(p)?,
            TokenizerFile::SentencePiece(p) => PromptTokenizer::from_sentencepiece(p)?,
            TokenizerFile::ByteStandIn => PromptTokenizer::ByteStandIn,
            // a silent stand-in sent a real policy's arm to its joint limit
            TokenizerFile::Missing(msg) => {
                return Err(PolicyError::Tokenizer(format!(
                    "{}: {msg}",
                    checkpoint_dir.display()
                )))
            }
        };
        // a token id beyond the embedding table is not an error candle reports: it reads past
        // the table or yields NaN; refuse the pair at load
        let (ids, vocab) = (tokenizer.id_bound(), model.cfg.vocab_size);
        if ids > vocab {
            return Err(PolicyError::Tokenizer(format!(
                "{}: the tokenizer has ids up to {} but the model's embedding has {vocab} rows: \
                 they do not belong together",
                checkpoint_dir.display(),
                ids - 1
            )));
        }
        if let Some(problem) = &layout.norm_problem {
            return Err(PolicyError::Config(problem.clone()));
        }
        let norm = match layout.norm {
            Some(ns) => {
                let mode = match model.cfg.kind {
                    ModelKind::Pi0 => NormMode::ZScore,
                    ModelKind::Pi05 => NormMode::Quantile,
                };
                ns.check(mode, 0).map_err(|e| {
                    PolicyError::Config(format!("{}: {e}", checkpoint_dir.display()))
                })?;
                Some(ns)
            }
            None => {
                for m in &layout.missing {
                    tracing::warn!("{}: {m}", checkpoint_dir.display());
                }
                None
            }
        };
        Ok(Policy {
            model,
            tokenizer,
            norm,
            steps: opts.num_steps.max(1),
            cache: None,
            rng: rand_chacha::ChaCha8Rng::seed_from_u64(DEFAULT_SEED),
            images: Vec::new(),
            noise: Vec::new(),
            offsets: Vec::new(),
            graph: [None, None],
            graph_on: [opts.cuda_graph && opts.device.is_cuda(); 2],
            truncated_prompt: None,
            state_prompt_dim: layout.state_prompt_dim,
            prompt_style: layout.prompt_style,
            lerobot: layout.kind == crate::layout::LayoutKind::LeRobot,
            openpi: layout.openpi.map(|(c, _)| c),
        })
    }

    /// The model.
    pub fn model(&self) -> &PiModel {
        &self.model
    }

    /// Whether samples run as a captured CUDA graph (captured at the first call).
    pub fn uses_cuda_graph(&self) -> bool {
        self.graph[0].is_some()
    }

    /// Whether RTC-guided samples run as a captured CUDA graph (captured at the first guided
    /// call; the identity Jacobian only).
    pub fn uses_guided_cuda_graph(&self) -> bool {
        self.graph[1].is_some()
    }

    /// The cached sampler as one CUDA graph ([`super::graph`]): the host half of the prefix
    /// pass copies the observation into the cache's buffers, then one launch runs the vision
    /// tower, the prefix pass and every denoising step (guided towards `guide` when given: RTC
    /// with the identity Jacobian, its target copied into the graph's buffers). The first call
    /// of each kind captures its graph and checks it against the eager run; a failure turns
    /// that kind of graph off for this policy, with a warning, and the eager result is used.
    fn sample_graph(
        &mut self,
        inputs: &ModelInputs,
        noise: &Tensor,
        guide: Option<&GuidanceTarget>,
    ) -> Result<super::model::SampleOutput, PolicyError> {
        let slot = guide.is_some() as usize;
        let what = ["sample", "RTC-guided sample"][slot];
        let cache = self.model.prepare_prefix(inputs, &mut self.cache, true)?;
        if let Some(g) = &self.graph[slot] {
            match guide {
                None if g.fits(cache, self.steps) => return g.run(noise),
                Some(t) if g.fits_guided(cache, self.steps, t) => return g.run_guided(noise, t),
                _ => {}
            }
        }
        self.graph[slot] = None;
        let captured = match guide {
            None => SampleGraph::capture(&self.model, cache, noise, self.steps),
            Some(t) => SampleGraph::capture_guided(&self.model, cache, noise, self.steps, t),
        };
        match captured {
            Ok((eager, Some(g))) => {
                tracing::info!(
                    "policy: {what} (prefix pass and denoising loop) captured as a CUDA graph"
                );
                self.graph[slot] = Some(g);
                Ok(eager)
            }
            Ok((eager, None)) => {
                self.graph_on[slot] = false;
                Ok(eager)
            }
            Err(e) => {
                tracing::warn!(
                    "policy: CUDA graph capture of the {what} failed, running eagerly: {e}"
                );
                self.graph_on[slot] = false;
                self.model.run_prefix(cache, None, false)?;
                match guide {
                    None => self.model.denoise(cache, noise, self.steps),
                    Some(t) => denoise_guided(&self.model, cache, noise, self.steps, t),
                }
            }
        }
    }

    /// Restarts the sampler's noise sequence from `seed` (the same seed, observations and
    /// requests give the same chunks: an evaluation compares strategies on common noise).
    pub fn reseed(&mut self, seed: u64) {
        self.rng = rand_chacha::ChaCha8Rng::seed_from_u64(seed);
    }

    /// Action horizon H.
    pub fn horizon(&self) -> usize {
        self.model.cfg.action_horizon
    }

    /// Checks that the normalisation statistics (if any) cover a robot of `n_dof` joints, and
    /// that an openpi config's robot sends that many state values.
    pub fn check_dof(&self, n_dof: usize) -> Result<(), PolicyError> {
        if let Some(c) = self.openpi {
            c.check_state(n_dof)?;
        }
        match &self.norm {
            Some(ns) => ns.check(
                self.mode(),
                n_dof.min(self.openpi.map_or(n_dof, |c| c.model_action_width())),
            ),
            None => Ok(()),
        }
    }

    /// Holds the action statistics (if any) against the robot's joint ranges
    /// ([`crate::openpi_config::check_action_ranges`]).
    pub fn check_action_ranges(
        &self,
        joints: &[crate::openpi_config::JointRange],
    ) -> Result<(), PolicyError> {
        match &self.norm {
            Some(ns) => crate::openpi_config::check_action_ranges(
                self.openpi,
                &self.model.cfg.delta_action_mask,
                ns,
                self.mode(),
                self.model.cfg.action_dim,
                joints,
            ),
            None => Ok(()),
        }
    }

    /// openpi's training config whose transforms wrap the model, if any.
    pub fn openpi_config(&self) -> Option<&'static OpenpiConfig> {
        self.openpi
    }

    /// Action columns a chunk has for a state of `n_state` values: the openpi config's robot's
    /// (ALOHA 14, LIBERO 7, DROID 8), else one per state value.
    pub fn action_width(&self, n_state: usize) -> usize {
        self.openpi.map_or(n_state, |c| c.robot.action_dim())
    }

    /// The prompt when neither the request nor the server has one: the openpi config's
    /// `default_prompt`.
    pub fn default_prompt(&self) -> Option<&'static str> {
        self.openpi.and_then(|c| c.default_prompt)
    }

    fn mode(&self) -> NormMode {
        match self.model.cfg.kind {
            ModelKind::Pi0 => NormMode::ZScore,
            ModelKind::Pi05 => NormMode::Quantile,
        }
    }

    /// Runs the policy: returns `[H][n_dof]` actions (row-major) in robot units, where `n_dof` is
    /// the number of joint positions given, conditioned on the chunk the robot is executing as
    /// `how` says ([`Conditioning`]). The one entry point for every kind of chunk.
    pub fn infer(
        &mut self,
        obs: &RawObservation<'_>,
        how: &Conditioning<'_>,
    ) -> Result<Vec<f64>, PolicyError> {
        let inputs = self.prepare(obs)?;
        let n_dof = obs.joint_positions.len();
        let stats = self.norm.as_ref().map(|n| &n.actions);
        if let (Some(c), Conditioning::Guided(_) | Conditioning::Committed(_)) = (self.openpi, how)
        {
            return Err(PolicyError::Config(format!(
                "openpi config {}: a chunk conditioned on the previous one (RTC) is not \
                 supported through the robot's transforms; ask for a fresh chunk",
                c.name
            )));
        }
        match how {
            Conditioning::Fresh => self.run(&inputs, n_dof, Continue::Fresh),
            Conditioning::Guided(g) => {
                let target = g.target(
                    &self.model.cfg,
                    n_dof,
                    stats,
                    self.mode(),
                    &self.offsets,
                    self.model.device(),
                )?;
                self.run(&inputs, n_dof, Continue::Guided(&target))
            }
            Conditioning::Committed(committed) => {
                let max = self.model.cfg.rtc_prefix_max;
                if max == 0 {
                    return Err(PolicyError::Config(
                        "this checkpoint was not trained with a committed action prefix (no \
                         rtc_prefix_max in its config.json): it cannot run training-time \
                         real-time chunking (train one with `chunkrt train --rtc-prefix N`, or \
                         use strategy rtc)"
                            .into(),
                    ));
                }
                if !committed.len().is_multiple_of(n_dof) {
                    return Err(PolicyError::Input(format!(
                        "{} committed action values are not whole rows of {n_dof} joints",
                        committed.len()
                    )));
                }
                let d = (committed.len() / n_dof).min(max);
                if d == 0 {
                    return self.run(&inputs, n_dof, Continue::Fresh);
                }
                let y = model_space_actions(
                    &committed[..d * n_dof],
                    n_dof,
                    &self.model.cfg,
                    stats,
                    self.mode(),
                    &self.offsets,
                    self.model.device(),
                )?;
                self.run(&inputs, n_dof, Continue::Committed(&y, d))
            }
        }
    }

    /// Image inputs that are an earlier frame of a camera (`config.json` `delayed_views`): the
    /// observation must carry them under their names, like the cameras.
    pub fn delayed_views(&self) -> &[crate::DelayedView] {
        &self.model.cfg.delayed_views
    }

    /// The largest committed prefix the checkpoint was trained with (0: it was not;
    /// [`Conditioning::Committed`]).
    pub fn committed_max(&self) -> usize {
        self.model.cfg.rtc_prefix_max
    }

    /// Pre-processing only: model-ready inputs (batch 1) for an observation.
    pub fn prepare(&mut self, obs: &RawObservation<'_>) -> Result<ModelInputs, PolicyError> {
        let cfg = self.model.cfg.clone();
        let n_dof = obs.joint_positions.len();
        if n_dof == 0 || n_dof > cfg.action_dim {
            return Err(PolicyError::Input(format!(
                "{n_dof} joints; the model takes 1..={}",
                cfg.action_dim
            )));
        }
        if obs.joint_positions.iter().any(|x| !x.is_finite()) {
            return Err(PolicyError::Input("non-finite joint position".into()));
        }
        let mode = self.mode();
        if let Some(c) = self.openpi {
            c.check_state(n_dof)?;
        }
        // the robot's input transform, the normalisation of the unpadded state, the padding
        let ModelState {
            state,
            prompt_state,
            offsets,
        } = model_state(
            self.openpi,
            &cfg.delta_action_mask,
            self.norm.as_ref(),
            mode,
            obs.joint_positions,
            cfg.action_dim,
        )?;
        self.offsets = offsets;
        let in_prompt = self.openpi.is_none_or(|c| c.discrete_state_input);
        let bins = (cfg.kind == ModelKind::Pi05 && in_prompt).then(|| {
            if self.lerobot {
                // LeRobot's pi05 processor normalises in f32 (torch) and pads the normalised
                // state before discretising it
                let mut padded = state[..prompt_state.len().min(state.len())].to_vec();
                if let Some(n) = self.state_prompt_dim {
                    padded.resize(n.max(padded.len()), 0.0);
                }
                discretize_state(&padded)
            } else {
                // openpi normalises the client's f64 state in f64 (numpy)
                discretize_state(&prompt_state)
            }
        });
        // images in camera order; absent cameras black and masked
        let s = cfg.vision.image_size;
        let dev = self.model.device().clone();
        let mut images = Vec::with_capacity(cfg.cameras.len());
        let mut masks = Vec::with_capacity(cfg.cameras.len());
        for cam in &cfg.cameras {
            self.images.clear();
            match obs.frames.iter().find(|f| f.camera == cam) {
                Some(f) => {
                    let (w, h) = (f.width as usize, f.height as usize);
                    let rgb = to_rgb(f.data, w, h, f.stride as usize, f.encoding)?;
                    let r = resize_with_pad(&rgb, h, w, s, s)?;
                    to_model_chw(&r, s, s, &mut self.images);
                    masks.push(vec![true]);
                }
                None => {
                    self.images.resize(3 * s * s, -1.0);
                    masks.push(vec![false]);
                }
            }
            images.push(Tensor::from_slice(&self.images, (1, 3, s, s), &dev)?);
        }
        let (ids, tmask, full) = self.tokenizer.tokenize_styled(
            obs.prompt,
            bins.as_deref(),
            cfg.max_token_len,
            self.prompt_style,
        )?;
        if full > cfg.max_token_len && self.truncated_prompt.as_deref() != Some(obs.prompt) {
            // once per prompt: a π0.5 prompt's length changes with the state
            self.truncated_prompt = Some(obs.prompt.to_string());
            // the prompt is outside data: its first 120 characters, and its length
            let shown: String = obs.prompt.chars().take(120).collect();
            let more = if shown.len() < obs.prompt.len() {
                format!("… ({} bytes in all)", obs.prompt.len())
            } else {
                String::new()
            };
            tracing::warn!(
                "the prompt {shown:?}{more} is {full} tokens with its state, more than the \
                 model's {}: truncated, so the policy does not see its end (shorten it, or raise \
                 max_token_len if the checkpoint was trained with more)",
                cfg.max_token_len
            );
        }
        let inputs = ModelInputs {
            images,
            image_masks: masks,
            tokens: Tensor::from_vec(ids, (1, cfg.max_token_len), &dev)?,
            token_mask: vec![tmask],
            state: Tensor::from_vec(state, (1, cfg.action_dim), &dev)?,
        };
        Ok(inputs)
    }

    fn run(
        &mut self,
        inputs: &ModelInputs,
        n_dof: usize,
        how: Continue<'_>,
    ) -> Result<Vec<f64>, PolicyError> {
        let cfg = self.model.cfg.clone();
        let mode = self.mode();
        let dev = self.model.device().clone();
        // noise ~ N(0, 1) (Box-Muller)
        let n = cfg.action_horizon * cfg.action_dim;
        self.noise.clear();
        while self.noise.len() < n {
            let u1: f64 = self.rng.gen_range(f64::MIN_POSITIVE..1.0);
            let u2: f64 = self.rng.gen();
            let r = (-2.0 * u1.ln()).sqrt();
            self.noise
                .push((r * (2.0 * std::f64::consts::PI * u2).cos()) as f32);
            self.noise
                .push((r * (2.0 * std::f64::consts::PI * u2).sin()) as f32);
        }
        self.noise.truncate(n);
        let noise = Tensor::from_slice(&self.noise, (1, cfg.action_horizon, cfg.action_dim), &dev)?;
        // RTC guidance that guides nothing (β = 0, all weights zero) is the plain sampler
        let how = match how {
            Continue::Guided(g) if !check_target(&self.model, inputs.batch(), g)? => {
                Continue::Fresh
            }
            how => how,
        };
        let out = match how {
            Continue::Guided(g) if self.graph_on[1] && g.jacobian == Jacobian::Identity => {
                self.sample_graph(inputs, &noise, Some(g))?
            }
            Continue::Guided(g) => {
                // checked above; Y and W are f32 on the device (`Guidance::target`)
                let cache = filled_cache(&self.model, inputs, &mut self.cache)?;
                denoise_guided(&self.model, cache, &noise, self.steps, g)?
            }
            Continue::Committed(y, d) => {
                let cache = filled_cache(&self.model, inputs, &mut self.cache)?;
                self.model
                    .denoise_committed(cache, &noise, self.steps, y, &[d])?
            }
            Continue::Fresh if self.graph_on[0] => self.sample_graph(inputs, &noise, None)?,
            Continue::Fresh => {
                self.model
                    .sample(inputs, &noise, self.steps, Some(&mut self.cache))?
            }
        };
        // the one device -> host copy of the chunk
        let acts = out.actions.squeeze(0)?.to_vec2::<f32>()?;
        let mut res = Vec::with_capacity(cfg.action_horizon * n_dof);
        robot_actions(
            self.openpi,
            self.norm.as_ref(),
            mode,
            acts,
            &self.offsets,
            &mut res,
        )?;
        Ok(res)
    }
}

/// Runs the prefix pass into `cache` (reusing its buffers) and returns it.
fn filled_cache<'c>(
    model: &PiModel,
    inputs: &ModelInputs,
    cache: &'c mut Option<PrefixCache>,
) -> Result<&'c PrefixCache, PolicyError> {
    model.fill_cache(inputs, cache, false)?;
    cache
        .as_ref()
        .ok_or_else(|| PolicyError::Input("the prefix cache was not filled".into()))
}
