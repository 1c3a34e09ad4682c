//! π0 / π0.5: prefix and suffix embeddings, masks and positions, the prefix KV cache, the
//! flow-matching sampler (openpi `PI0Pytorch`). The prefix cache and its host half live in
//! [`prefix`], the sampler (the Euler loop written once) in [`sampler`], the training loss in
//! [`loss`], the flow times and time embedding in [`times`], openpi's attention masks in
//! [`masks`].
//!
//! Shapes: B batch, C cameras, T tokens per camera, Lt prompt tokens, P = C*T + Lt prefix length,
//! H horizon, A action dim, S suffix length (π0: 1 + H, π0.5: H), W / We widths of the VLM /
//! action expert.

use std::collections::HashMap;

use candle_core::{DType, Device, Module, Tensor};
use candle_nn::{Linear, VarBuilder};

use super::config::{ModelConfig, ModelKind};
use super::gemma::{joint_layer, kv_only_layer, Expert, KvMode, Rope, Stream, MASK_VALUE};
use super::packed::Precision;
use super::siglip::Vision;
use crate::error::PolicyError;

mod action_time;
mod loss;
mod masks;
mod prefix;
mod sampler;
mod times;

use action_time::ActionTimeMlp;
pub use loss::LossOutput;
pub use masks::att_2d_mask;
use masks::bias_tensor;
pub use prefix::{PrefixCache, PrefixLayout, PrefixStatics};
pub use sampler::{euler, SampleOutput};
use times::free_mask;
pub use times::{time_embedding, FlowTimes};

/// Model-ready inputs (what openpi's `sample_actions` takes).
#[derive(Debug, Clone)]
pub struct ModelInputs {
    /// Per camera (config order): [B, 3, S, S] f32 in [-1, 1].
    pub images: Vec<Tensor>,
    /// Per camera: [B] validity.
    pub image_masks: Vec<Vec<bool>>,
    /// [B, Lt] token ids (u32 or i64).
    pub tokens: Tensor,
    /// [B][Lt] validity of the tokens.
    pub token_mask: Vec<Vec<bool>>,
    /// [B, A] normalised, zero-padded state (π0: state token; π0.5: unused).
    pub state: Tensor,
}

impl ModelInputs {
    /// The same inputs on `device` (images, tokens and state; masks are host data).
    pub fn to_device(&self, device: &Device) -> candle_core::Result<Self> {
        Ok(Self {
            images: self
                .images
                .iter()
                .map(|t| t.to_device(device))
                .collect::<candle_core::Result<_>>()?,
            image_masks: self.image_masks.clone(),
            tokens: self.tokens.to_device(device)?,
            token_mask: self.token_mask.clone(),
            state: self.state.to_device(device)?,
        })
    }

    /// Batch size.
    pub fn batch(&self) -> usize {
        self.token_mask.len()
    }
}

/// Kind-specific suffix heads.
#[derive(Debug, Clone)]
enum SuffixHeads {
    Pi0 {
        state_proj: Linear,
        mlp_in: Linear,
        mlp_out: Linear,
        /// The same MLP split for inference (`None` when trainable).
        split: Option<Box<ActionTimeMlp>>,
    },
    Pi05 {
        time_in: Linear,
        time_out: Linear,
    },
}

/// π0 / π0.5.
#[derive(Debug, Clone)]
pub struct PiModel {
    /// Dimensions.
    pub cfg: ModelConfig,
    vision: Vision,
    /// Token embedding [V, W] (tied with the LM head).
    embed_tokens: Tensor,
    vlm: Expert,
    expert: Expert,
    action_in_proj: Linear,
    action_out_proj: Linear,
    heads: SuffixHeads,
    device: Device,
    /// The dtype of the weights, activations and KV cache (f32, or bf16 on a GPU); the sampler
    /// state and the returned velocities stay f32.
    dtype: DType,
    /// [`Self::time_features`] by (time bits, batch), made once and kept.
    time_table: TimeTable,
    /// The prefix cache's fixed-shape step layout ([`Self::set_fixed_step_shapes`]).
    fixed_step_shapes: bool,
}

/// What the suffix needs of the flow times ([`PiModel::time_features`]).
#[derive(Debug, Clone)]
struct TimeFeatures {
    /// The sinusoidal time embedding [B, We] (or per token [B, H, We]).
    te: Tensor,
    /// π0.5's adaRMS condition, same shape.
    cond: Option<Tensor>,
    /// π0's time half of the action-time MLP ([`ActionTimeMlp::time_term`]), same shape.
    mlp_time: Option<Tensor>,
}

/// Per-time suffix tensors: (time bits, batch, committed prefix length) -> time features.
type TimeTable = std::sync::Arc<std::sync::Mutex<HashMap<(u32, usize, usize), TimeFeatures>>>;

impl PiModel {
    /// Builds the model from a `VarBuilder` at the checkpoint root (openpi key names). With a
    /// `VarMap`-backed builder the weights are trainable variables.
    pub fn new(cfg: &ModelConfig, vb: VarBuilder) -> Result<Self, PolicyError> {
        cfg.validate()?;
        let w = cfg.paligemma.width;
        let we = cfg.action_expert.width;
        let a = cfg.action_dim;
        let eps = cfg.rms_norm_eps;
        let pg = vb.pp("paligemma_with_expert.paligemma");
        let vision = Vision::new(&cfg.vision, w, pg.pp("model"))?;
        let init = candle_nn::Init::Randn {
            mean: 0.0,
            stdev: 1.0 / (w as f64).sqrt(),
        };
        let embed_tokens = if pg.contains_tensor("model.language_model.embed_tokens.weight") {
            pg.get_with_hints(
                (cfg.vocab_size, w),
                "model.language_model.embed_tokens.weight",
                init,
            )?
        } else {
            pg.get_with_hints((cfg.vocab_size, w), "lm_head.weight", init)?
        };
        let vlm = Expert::new(&cfg.paligemma, false, eps, pg.pp("model.language_model"))?;
        let pi05 = cfg.kind == ModelKind::Pi05;
        let expert = Expert::new(
            &cfg.action_expert,
            pi05,
            eps,
            vb.pp("paligemma_with_expert.gemma_expert.model"),
        )?;
        // The action/state projections and the time MLPs live outside openpi's
        // `paligemma_with_expert` and stay f32 there whatever the model's dtype; so here.
        let vf = vb.clone().set_dtype(DType::F32);
        let action_in_proj = candle_nn::linear(a, we, vf.pp("action_in_proj"))?;
        let action_out_proj = candle_nn::linear(we, a, vf.pp("action_out_proj"))?;
        let heads = match cfg.kind {
            ModelKind::Pi0 => {
                let mlp_in = candle_nn::linear(2 * we, we, vf.pp("action_time_mlp_in"))?;
                let mlp_out = candle_nn::linear(we, we, vf.pp("action_time_mlp_out"))?;
                SuffixHeads::Pi0 {
                    state_proj: candle_nn::linear(a, we, vf.pp("state_proj"))?,
                    split: ActionTimeMlp::new(&mlp_in, &mlp_out)?.map(Box::new),
                    mlp_in,
                    mlp_out,
                }
            }
            ModelKind::Pi05 => SuffixHeads::Pi05 {
                time_in: candle_nn::linear(we, we, vf.pp("time_mlp_in"))?,
                time_out: candle_nn::linear(we, we, vf.pp("time_mlp_out"))?,
            },
        };
        Ok(PiModel {
            cfg: cfg.clone(),
            vision,
            embed_tokens,
            vlm,
            expert,
            action_in_proj,
            action_out_proj,
            heads,
            device: vb.device().clone(),
            dtype: vb.dtype(),
            time_table: TimeTable::default(),
            fixed_step_shapes: !vb.device().is_cpu(),
        })
    }

    /// The device.
    pub fn device(&self) -> &Device {
        &self.device
    }

    /// The dtype of weights, activations and the KV cache.
    pub fn dtype(&self) -> DType {
        self.dtype
    }

    /// RoPE tables for positions `pos[b][l]` on the model's device, in its dtype (both experts
    /// share the head dimension).
    fn rope(&self, pos: &[Vec<i64>]) -> candle_core::Result<Rope> {
        Rope::new(
            pos,
            self.cfg.paligemma.head_dim,
            self.cfg.rope_theta,
            &self.device,
            self.dtype,
        )
    }

    /// The denoising steps' layout in the prefix cache. Compact (the CPU's default): a step
    /// attends over the valid prefix tokens and the suffix only, so its shapes change with the
    /// prompt's length. Fixed (the GPU's default): the suffix sits after all P prefix slots with
    /// the unused ones masked, and the step's mask and RoPE tables are refilled in place: every
    /// observation runs the same shapes on the same buffers (a captured CUDA graph replays it).
    /// Both compute the same actions.
    pub fn set_fixed_step_shapes(&mut self, fixed: bool) {
        self.fixed_step_shapes = fixed;
    }

    /// Whether the prefix cache uses the fixed-shape step layout.
    pub fn fixed_step_shapes(&self) -> bool {
        self.fixed_step_shapes
    }

    /// Runs the inference fast path's matrix products (experts and SigLIP) with weights packed
    /// for `precision`: f32 (the default of inference models, where AVX-512 runs) or bf16 with
    /// f32 accumulation (`policy.precision = "bf16"`: Intel AMX, else AVX512-BF16). Returns false
    /// where this CPU has no kernel for it; the model then keeps its previous packing.
    /// Trainable (VarMap) models have no fast path and are unaffected.
    pub fn set_precision(&mut self, precision: Precision) -> Result<bool, PolicyError> {
        let ok = self.vlm.pack(precision)? & self.expert.pack(precision)?;
        Ok(ok & self.vision.pack(precision)?)
    }

    /// `set_precision(Precision::Bf16)`.
    pub fn use_bf16(&mut self) -> Result<bool, PolicyError> {
        self.set_precision(Precision::Bf16)
    }

    fn check_inputs(&self, inp: &ModelInputs) -> Result<usize, PolicyError> {
        let b = inp.batch();
        let c = self.cfg.cameras.len();
        let s = self.cfg.vision.image_size;
        let bad = |m: String| Err(PolicyError::Input(m));
        if b == 0 {
            return bad("empty batch".into());
        }
        if inp.images.len() != c || inp.image_masks.len() != c {
            return bad(format!(
                "expected {c} cameras, got {} images / {} masks",
                inp.images.len(),
                inp.image_masks.len()
            ));
        }
        for (i, im) in inp.images.iter().enumerate() {
            if im.dims() != [b, 3, s, s] {
                return bad(format!(
                    "image {i}: shape {:?}, expected [{b}, 3, {s}, {s}]",
                    im.dims()
                ));
            }
            if inp.image_masks[i].len() != b {
                return bad(format!(
                    "image mask {i}: {} entries for batch {b}",
                    inp.image_masks[i].len()
                ));
            }
        }
        let lt = self.cfg.max_token_len;
        if inp.tokens.dims() != [b, lt] || inp.token_mask.iter().any(|m| m.len() != lt) {
            return bad(format!(
                "tokens: shape {:?}, expected [{b}, {lt}]",
                inp.tokens.dims()
            ));
        }
        if inp.state.dims() != [b, self.cfg.action_dim] {
            return bad(format!(
                "state: shape {:?}, expected [{b}, {}]",
                inp.state.dims(),
                self.cfg.action_dim
            ));
        }
        Ok(b)
    }

    /// Validity and positions of the prefix tokens.
    pub fn prefix_layout(&self, inp: &ModelInputs) -> PrefixLayout {
        let t = self.cfg.vision.num_tokens();
        let b = inp.batch();
        let mut pad = Vec::with_capacity(b);
        let mut pos = Vec::with_capacity(b);
        let mut n_valid = Vec::with_capacity(b);
        for bi in 0..b {
            let mut row = Vec::with_capacity(self.cfg.prefix_len());
            for cm in &inp.image_masks {
                row.extend(std::iter::repeat_n(cm[bi], t));
            }
            row.extend_from_slice(&inp.token_mask[bi]);
            let mut c = 0i64;
            let p: Vec<i64> = row
                .iter()
                .map(|&v| {
                    c += v as i64;
                    c - 1
                })
                .collect();
            n_valid.push(c as usize);
            pad.push(row);
            pos.push(p);
        }
        PrefixLayout { pad, pos, n_valid }
    }

    /// SigLIP last hidden states and image embeddings per camera ([B, T, Dv], [B, T, W]).
    pub fn vision(&self, inp: &ModelInputs) -> Result<(Vec<Tensor>, Vec<Tensor>), PolicyError> {
        let b = self.check_inputs(inp)?;
        // all cameras in one pass: [C*B, 3, S, S]
        let all = Tensor::cat(&inp.images, 0)?;
        let hidden = self.vision.tower(&all)?;
        let emb = self.vision.forward_projector(&hidden)?;
        let mut hs = Vec::new();
        let mut es = Vec::new();
        for c in 0..inp.images.len() {
            hs.push(hidden.narrow(0, c * b, b)?);
            es.push(emb.narrow(0, c * b, b)?);
        }
        Ok((hs, es))
    }

    /// `embed_prefix`: concat(image embeddings per camera, embed(ids) * sqrt(W)) [B, P, W].
    pub fn embed_prefix(&self, inp: &ModelInputs) -> Result<Tensor, PolicyError> {
        self.embed_prefix_inner(inp, false, false)
    }

    /// [`Self::embed_prefix`]; `diff` selects ops with a backward (training).
    pub fn embed_prefix_with(&self, inp: &ModelInputs, diff: bool) -> Result<Tensor, PolicyError> {
        self.embed_prefix_inner(inp, false, diff)
    }

    /// `skip_masked`: cameras masked in every batch row get zeros instead of a vision pass (their
    /// tokens are padding and never reach valid tokens).
    fn embed_prefix_inner(
        &self,
        inp: &ModelInputs,
        skip_masked: bool,
        diff: bool,
    ) -> Result<Tensor, PolicyError> {
        let b = self.check_inputs(inp)?;
        let run: Vec<usize> = (0..inp.images.len())
            .filter(|&c| !skip_masked || inp.image_masks[c].iter().any(|&m| m))
            .collect();
        let t = self.cfg.vision.num_tokens();
        let w = self.cfg.paligemma.width;
        // all cameras in one pass: [C*B, 3, S, S] -> [C*B, T, W]
        let emb = if run.is_empty() {
            None
        } else {
            let imgs: Vec<&Tensor> = run.iter().map(|&c| &inp.images[c]).collect();
            Some(
                self.vision
                    .forward_with(&Tensor::cat(&imgs, 0)?, diff)?
                    .to_dtype(self.dtype)?,
            )
        };
        let mut parts = Vec::with_capacity(inp.images.len() + 1);
        for c in 0..inp.images.len() {
            match (run.iter().position(|&r| r == c), &emb) {
                (Some(i), Some(e)) => parts.push(e.narrow(0, i * b, b)?),
                _ => parts.push(Tensor::zeros((b, t, w), self.dtype, &self.device)?),
            }
        }
        let lt = self.cfg.max_token_len;
        let ids = inp.tokens.flatten_all()?;
        let ids = if ids.dtype() == DType::I64 || ids.dtype() == DType::U32 {
            ids
        } else {
            ids.to_dtype(DType::U32)?
        };
        let vocab = self.embed_tokens.dim(0)?;
        let max_id = ids.to_dtype(DType::F64)?.max(0)?.to_scalar::<f64>()?;
        let min_id = ids.to_dtype(DType::F64)?.min(0)?.to_scalar::<f64>()?;
        if min_id < 0.0 || max_id >= vocab as f64 {
            return Err(PolicyError::Input(format!(
                "token ids must be in [0, {vocab}), got [{min_id}, {max_id}]"
            )));
        }
        let text = self
            .embed_tokens
            .index_select(&ids, 0)?
            .reshape((b, lt, w))?;
        parts.push((text * (w as f64).sqrt())?);
        Ok(Tensor::cat(&parts, 1)?)
    }

    /// Additive prefix self-attention bias [B, 1, P, P].
    fn prefix_bias(&self, layout: &PrefixLayout) -> candle_core::Result<Tensor> {
        let b = layout.pad.len();
        let p = layout.pad.first().map(|r| r.len()).unwrap_or(0);
        let mut vis = Vec::with_capacity(b * p * p);
        for row in &layout.pad {
            for &qi in row {
                for &kj in row {
                    vis.push(qi && kj);
                }
            }
        }
        bias_tensor(vis, (b, 1, p, p), &self.device)
    }

    /// Suffix ar flags (π0: `[1, 1, 0, ..]`, π0.5: `[1, 0, ..]`).
    pub fn suffix_ar(&self) -> Vec<bool> {
        let h = self.cfg.action_horizon;
        let mut ar = Vec::with_capacity(h + 1);
        if self.cfg.kind == ModelKind::Pi0 {
            ar.push(true);
        }
        ar.push(true);
        ar.extend(std::iter::repeat_n(false, h - 1));
        ar
    }

    /// Suffix tokens and the adaRMS condition at time `t` [B]: tokens [B, S or H, We].
    /// `with_state`: prepend π0's state token. `committed` (training-time RTC, [`FlowTimes`]):
    /// the first `committed[b]` action tokens of row b are at flow time 0, and the condition
    /// is per token [B, H, We]. `diff`: candle's ops with a backward (π0's action-time MLP
    /// concatenated, not split onto the packed kernels, which have none).
    fn embed_suffix(
        &self,
        state: &Tensor,
        x_t: &Tensor,
        times: FlowTimes<'_>,
        with_state: bool,
        diff: bool,
    ) -> candle_core::Result<(Tensor, Option<Tensor>)> {
        let we = self.cfg.action_expert.width;
        let TimeFeatures { te, cond, mlp_time } = self.time_features(times)?;
        // [B, H, We], in f32 like the heads; the tokens enter the expert in the model's dtype
        let a = self.action_in_proj.forward(&x_t.to_dtype(DType::F32)?)?;
        match &self.heads {
            SuffixHeads::Pi0 {
                state_proj,
                mlp_in,
                mlp_out,
                split,
            } => {
                let at = match (split, &mlp_time, diff) {
                    (Some(mlp), Some(tt), false) => mlp.forward(&a, tt)?,
                    _ => {
                        let (b, h, _) = a.dims3()?;
                        // per batch row [B, We] or already per token [B, H, We]
                        let te = if te.rank() == 2 {
                            te.unsqueeze(1)?.broadcast_as((b, h, we))?
                        } else {
                            te
                        };
                        let at = Tensor::cat(&[&a, &te], 2)?;
                        mlp_out.forward(&mlp_in.forward(&at)?.silu()?)?
                    }
                };
                if with_state {
                    // [B, 1, We]
                    let s = state_proj
                        .forward(&state.to_dtype(DType::F32)?)?
                        .unsqueeze(1)?;
                    Ok((Tensor::cat(&[&s, &at], 1)?.to_dtype(self.dtype)?, None))
                } else {
                    Ok((at.to_dtype(self.dtype)?, None))
                }
            }
            SuffixHeads::Pi05 { .. } => Ok((a.to_dtype(self.dtype)?, cond)),
        }
    }

    /// What the suffix needs of the flow times: the sinusoidal embedding and, for π0.5, the
    /// adaRMS condition (the time MLP of it; f32, the norms' dense layers are f32), [B, We] for
    /// one time per row, [B, H, We] per token with a committed prefix. Neither depends on the
    /// observation, so for a batch at one time (and one prefix length) they are made once per
    /// model and time and kept on the device: a denoising step uploads nothing and runs no time
    /// MLP. (Not for a model whose time MLP is being trained: its weights change.)
    fn time_features(&self, times: FlowTimes<'_>) -> candle_core::Result<TimeFeatures> {
        let t = times.t;
        let b = t.len();
        let h = self.cfg.action_horizon;
        let committed = match times.committed {
            Some(c) if c.len() != b => {
                candle_core::bail!("{} committed prefix lengths for batch {b}", c.len())
            }
            Some(c) if c.iter().any(|&n| n > 0) => Some(c),
            _ => None,
        };
        let trainable = match &self.heads {
            SuffixHeads::Pi0 { .. } => false,
            SuffixHeads::Pi05 { time_in, .. } => time_in.weight().is_variable(),
        };
        let n0 = committed.and_then(|c| c.first().copied()).unwrap_or(0);
        let key = match t.first() {
            Some(t0)
                if !trainable
                    && t.iter().all(|x| x == t0)
                    && committed.is_none_or(|c| c.iter().all(|&n| n == n0)) =>
            {
                Some((t0.to_bits(), b, n0))
            }
            _ => None,
        };
        if let Some(k) = key {
            if let Some(v) = self.time_table.lock().ok().and_then(|m| m.get(&k).cloned()) {
                return Ok(v);
            }
        }
        // one time per row, or per token with the committed ones at 0
        let per_token: Vec<f32> = match committed {
            None => t.to_vec(),
            Some(c) => (0..b * h)
                .map(|i| if i % h < c[i / h] { 0.0 } else { t[i / h] })
                .collect(),
        };
        let width = self.cfg.action_expert.width;
        let te = time_embedding(
            &per_token,
            width,
            self.cfg.time_min_period,
            self.cfg.time_max_period,
            &self.device,
        )?;
        let te = match committed {
            Some(_) => te.reshape((b, h, width))?,
            None => te,
        };
        let (cond, mlp_time) = match &self.heads {
            SuffixHeads::Pi0 { split, .. } => {
                (None, split.as_ref().map(|m| m.time_term(&te)).transpose()?)
            }
            SuffixHeads::Pi05 { time_in, time_out } => (
                Some(time_out.forward(&time_in.forward(&te)?.silu()?)?.silu()?),
                None,
            ),
        };
        let f = TimeFeatures { te, cond, mlp_time };
        if let (Some(k), Ok(mut m)) = (key, self.time_table.lock()) {
            // a handful of step counts and prefix lengths in practice; bounded whatever a
            // caller does
            if m.len() >= 4096 {
                m.clear();
            }
            m.insert(k, f.clone());
        }
        Ok(f)
    }

    /// The adaRMS condition at time `t` (π0.5; `None` for π0) [B, We].
    pub fn adarms_cond(&self, t: &[f32]) -> candle_core::Result<Option<Tensor>> {
        Ok(self.time_features(FlowTimes::new(t))?.cond)
    }

    /// `embed_suffix` output at time `t` (π0: state token first) [B, S, We].
    pub fn suffix_embeddings(
        &self,
        state: &Tensor,
        x_t: &Tensor,
        t: &[f32],
    ) -> Result<Tensor, PolicyError> {
        Ok(self
            .embed_suffix(state, x_t, FlowTimes::new(t), true, false)?
            .0)
    }

    /// Runs the prefix through the VLM expert only, filling `cache` (reusing its buffers when the
    /// shapes match). In the compact layout only valid prefix tokens are computed: row `b` of the
    /// cache holds the valid tokens in order at `[0, n_valid[b])`. Returns the prefix output
    /// (after the final norm) of the tokens computed [B, Pc, W] when `want_out`.
    ///
    /// Two halves: [`Self::prepare_prefix`] (host work and uploads) and [`Self::run_prefix`]
    /// (device work only, reading the inputs from the cache's buffers: what a captured CUDA
    /// graph replays, [`crate::graph`]).
    pub fn fill_cache(
        &self,
        inp: &ModelInputs,
        cache: &mut Option<PrefixCache>,
        want_out: bool,
    ) -> Result<Option<Tensor>, PolicyError> {
        let c = self.prepare_prefix(inp, cache, !want_out)?;
        self.run_prefix(c, None, want_out)
    }

    /// [`Self::fill_cache`] from precomputed prefix embeddings [B, P, W].
    pub fn fill_cache_from_embs(
        &self,
        inp: &ModelInputs,
        embs: &Tensor,
        cache: &mut Option<PrefixCache>,
        want_out: bool,
    ) -> Result<Option<Tensor>, PolicyError> {
        let c = self.prepare_prefix(inp, cache, false)?;
        self.run_prefix(c, Some(embs), want_out)
    }

    /// One velocity evaluation against the prefix cache: only the action expert runs, over the
    /// H action tokens. `x_t` [B, H, A], `t` [B] f32. Returns `v_t` [B, H, A]. `differentiable`
    /// selects ops with backward (for vector-Jacobian products through the action expert).
    pub fn velocity(
        &self,
        cache: &PrefixCache,
        x_t: &Tensor,
        t: &Tensor,
        differentiable: bool,
    ) -> Result<Tensor, PolicyError> {
        let tv = t.to_dtype(DType::F32)?.to_vec1::<f32>()?;
        self.velocity_at(cache, x_t, &tv, differentiable)
    }

    /// [`Self::velocity`] with host time values.
    pub fn velocity_at<'t>(
        &self,
        cache: &PrefixCache,
        x_t: &Tensor,
        times: impl Into<FlowTimes<'t>>,
        differentiable: bool,
    ) -> Result<Tensor, PolicyError> {
        let times = times.into();
        let t = times.t;
        let (b, h, a) = x_t.dims3()?;
        if b != cache.batch
            || h != self.cfg.action_horizon
            || a != self.cfg.action_dim
            || t.len() != b
        {
            return Err(PolicyError::Input(format!(
                "x_t {:?} / t [{}] do not match the cache (batch {}, H {}, A {})",
                x_t.dims(),
                t.len(),
                cache.batch,
                self.cfg.action_horizon,
                self.cfg.action_dim
            )));
        }
        // the state token (π0) is already in the cache; `state` is unused without it
        let (tokens, cond) = self.embed_suffix(x_t, x_t, times, false, differentiable)?;
        let mut st = [Stream {
            x: tokens,
            expert: &self.expert,
            cond: cond.as_ref(),
            rope: cache.action_rope(),
            pending: None,
        }];
        // the prefix's K/V as packed once for this observation (the CPU kernel's fast path)
        let packed = cache.packed_prefix();
        for li in 0..self.cfg.action_expert.depth {
            joint_layer(
                li,
                &mut st,
                cache.step_bias(),
                KvMode::Cached {
                    k: &cache.k[li],
                    v: &cache.v[li],
                    offset: cache.action_offset,
                    packed: packed.as_ref().and_then(|p| p.get(li)),
                },
                differentiable,
            )?;
        }
        let out = self
            .expert
            .norm
            .forward(&st[0].x, cond.as_ref(), differentiable)?
            .0;
        // velocities in f32 whatever the model's dtype (f32 head): the sampler state is f32
        Ok(self.action_out_proj.forward(&out.to_dtype(DType::F32)?)?)
    }

    /// The full joint forward (no cache; training and the uncached sampler): prefix tokens through
    /// the VLM expert and suffix tokens through the action expert with one attention per layer.
    /// Returns (prefix_out [B, P, W], suffix_out [B, S, We]).
    pub fn joint_forward<'t>(
        &self,
        inp: &ModelInputs,
        prefix_embs: &Tensor,
        x_t: &Tensor,
        times: impl Into<FlowTimes<'t>>,
        diff: bool,
    ) -> Result<(Tensor, Tensor), PolicyError> {
        let (po, so, _) = self.joint_forward_tap(inp, prefix_embs, x_t, times, diff, None)?;
        Ok((po, so))
    }

    /// [`Self::joint_forward`], also returning the prefix hidden states [B, P, W] at the input
    /// of layer `tap` (training's auxiliary losses read them).
    pub fn joint_forward_tap<'t>(
        &self,
        inp: &ModelInputs,
        prefix_embs: &Tensor,
        x_t: &Tensor,
        times: impl Into<FlowTimes<'t>>,
        diff: bool,
        tap: Option<usize>,
    ) -> Result<(Tensor, Tensor, Option<Tensor>), PolicyError> {
        let b = self.check_inputs(inp)?;
        let layout = self.prefix_layout(inp);
        let (suffix, cond) = self.embed_suffix(&inp.state, x_t, times.into(), true, diff)?;
        let s = suffix.dim(1)?;
        let p = self.cfg.prefix_len();
        let ar_s = self.suffix_ar();
        let mut vis = Vec::with_capacity(b * (p + s) * (p + s));
        let mut spos = Vec::with_capacity(b);
        for bi in 0..b {
            let mut pad = layout.pad[bi].clone();
            pad.extend(std::iter::repeat_n(true, s));
            let mut ar = vec![false; p];
            ar.extend_from_slice(&ar_s);
            vis.extend(att_2d_mask(&pad, &ar));
            let n = layout.n_valid[bi] as i64;
            spos.push((0..s as i64).map(|i| n + i).collect::<Vec<_>>());
        }
        let bias = bias_tensor(vis, (b, 1, p + s, p + s), &self.device)?;
        let d = &self.cfg.paligemma;
        let prope = self.rope(&layout.pos)?;
        let srope = self.rope(&spos)?;
        let mut streams = [
            Stream {
                x: prefix_embs.clone(),
                expert: &self.vlm,
                cond: None,
                rope: &prope,
                pending: None,
            },
            Stream {
                x: suffix,
                expert: &self.expert,
                cond: cond.as_ref(),
                rope: &srope,
                pending: None,
            },
        ];
        let mut tapped = None;
        for li in 0..d.depth {
            if tap == Some(li) {
                tapped = Some(streams[0].x.clone());
            }
            joint_layer(li, &mut streams, &bias, KvMode::Own { store: None }, diff)?;
        }
        let po = self.vlm.norm.forward(&streams[0].x, None, diff)?.0;
        let so = self
            .expert
            .norm
            .forward(&streams[1].x, cond.as_ref(), diff)?
            .0;
        Ok((po, so, tapped))
    }
}
