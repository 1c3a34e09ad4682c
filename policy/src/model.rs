//! π0 / π0.5: prefix and suffix embeddings, masks and positions, the prefix KV cache, the
//! flow-matching sampler and the training loss (openpi `PI0Pytorch`).
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
use super::PolicyError;

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

/// Host-side prefix layout: validity and RoPE positions of each prefix token.
#[derive(Debug, Clone, PartialEq)]
pub struct PrefixLayout {
    /// [B][P] valid tokens (camera mask expanded + token mask).
    pub pad: Vec<Vec<bool>>,
    /// [B][P] `cumsum(pad) - 1`.
    pub pos: Vec<Vec<i64>>,
    /// [B] number of valid prefix tokens (= first suffix position).
    pub n_valid: Vec<usize>,
}

/// Post-RoPE K/V of the prefix (and, for π0, of the state token) for every layer, in buffers of
/// length `P + S` that are reused across denoising steps and observations, and the device copies
/// of everything else a prefix pass and a denoising step read ([`PrefixStatics`]).
#[derive(Debug)]
pub struct PrefixCache {
    /// Per layer [B, nKV, P + S, hd].
    pub k: Vec<Tensor>,
    /// Per layer [B, nKV, P + S, hd].
    pub v: Vec<Tensor>,
    /// The observation's tensors on the device (refilled in place in the fixed layout).
    pub statics: PrefixStatics,
    /// Cameras run through the vision tower (compact layout: those valid in some batch row).
    pub cams: Vec<usize>,
    /// Compaction: per batch row, the prefix slots computed, in order (empty: all P slots).
    pub rows: Vec<Tensor>,
    /// Sequence index of the first action token (`Pc + state_tokens`, fixed layout
    /// `P + state_tokens`).
    pub action_offset: usize,
    /// Prefix layout the cache was built from.
    pub layout: PrefixLayout,
    /// Batch size.
    pub batch: usize,
}

impl PrefixCache {
    /// Additive mask for action queries over the keys they see [B, 1, 1, Pc + S].
    pub fn step_bias(&self) -> &Tensor {
        &self.statics.step_bias
    }

    /// RoPE tables of the action tokens.
    pub fn action_rope(&self) -> &Rope {
        &self.statics.action_rope
    }
}

/// One observation's tensors as the prefix pass and the denoising steps read them. In the fixed
/// layout their shapes do not depend on the observation, and [`PiModel::prepare_prefix`]
/// copies each new observation into the same buffers.
#[derive(Debug)]
pub struct PrefixStatics {
    /// The cameras that run the vision tower, batched [C·B, 3, S, S] f32.
    pub images: Tensor,
    /// Token ids [B · Lt] u32.
    pub ids: Tensor,
    /// State [B, A] f32.
    pub state: Tensor,
    /// Validity of the prefix slots computed [B, Pc] f32 (1 valid, 0 padding): the prefix
    /// self-attention mask is made from it on the device ([`PiModel::run_prefix`]), not uploaded
    /// as a [B, 1, Pc, Pc] table.
    pub prefix_valid: Tensor,
    /// RoPE positions of the prefix slots computed [B, Pc] f32 (the tables are made on the
    /// device).
    pub prefix_pos: Tensor,
    /// Additive mask for action queries [B, 1, 1, Pc + S] f32: the prefix slots computed
    /// (padding masked), then the suffix (fixed layout: rounded up to a multiple of 8 slots,
    /// the extra ones masked).
    pub step_bias: Tensor,
    /// RoPE tables of the action tokens.
    pub action_rope: Rope,
    /// π0's state token: its mask [B, 1, 1, Pc + 1] and RoPE tables.
    pub state_bias: Option<Tensor>,
    /// See `state_bias`.
    pub state_rope: Option<Rope>,
}

impl PrefixStatics {
    /// `new` copied into `self`'s buffers where every shape and dtype matches (fixed layout:
    /// the buffers keep their addresses), else `new` itself.
    fn refill(self, new: PrefixStatics) -> candle_core::Result<PrefixStatics> {
        fn same(a: &Tensor, b: &Tensor) -> bool {
            a.dims() == b.dims() && a.dtype() == b.dtype()
        }
        let ropes = |a: &Rope, b: &Rope| same(&a.cos, &b.cos) && same(&a.sin, &b.sin);
        let fits = same(&self.images, &new.images)
            && same(&self.ids, &new.ids)
            && same(&self.state, &new.state)
            && same(&self.prefix_valid, &new.prefix_valid)
            && same(&self.prefix_pos, &new.prefix_pos)
            && same(&self.step_bias, &new.step_bias)
            && ropes(&self.action_rope, &new.action_rope)
            && match (&self.state_bias, &new.state_bias) {
                (Some(a), Some(b)) => same(a, b),
                (None, None) => true,
                _ => false,
            }
            && match (&self.state_rope, &new.state_rope) {
                (Some(a), Some(b)) => ropes(a, b),
                (None, None) => true,
                _ => false,
            };
        if !fits {
            return Ok(new);
        }
        let pairs = [
            (&self.images, &new.images),
            (&self.ids, &new.ids),
            (&self.state, &new.state),
            (&self.prefix_valid, &new.prefix_valid),
            (&self.prefix_pos, &new.prefix_pos),
            (&self.step_bias, &new.step_bias),
            (&self.action_rope.cos, &new.action_rope.cos),
            (&self.action_rope.sin, &new.action_rope.sin),
        ];
        for (dst, src) in pairs {
            dst.slice_set(&src.contiguous()?, 0, 0)?;
        }
        if let (Some(a), Some(b)) = (&self.state_bias, &new.state_bias) {
            a.slice_set(&b.contiguous()?, 0, 0)?;
        }
        if let (Some(a), Some(b)) = (&self.state_rope, &new.state_rope) {
            a.cos.slice_set(&b.cos.contiguous()?, 0, 0)?;
            a.sin.slice_set(&b.sin.contiguous()?, 0, 0)?;
        }
        Ok(self)
    }

    /// Identities of every buffer (a captured graph checks it still reads the same ones).
    pub fn ids(&self) -> Vec<candle_core::TensorId> {
        let mut v = vec![
            self.images.id(),
            self.ids.id(),
            self.state.id(),
            self.prefix_valid.id(),
            self.prefix_pos.id(),
            self.step_bias.id(),
            self.action_rope.cos.id(),
            self.action_rope.sin.id(),
        ];
        v.extend(self.state_bias.iter().map(|t| t.id()));
        v.extend(
            self.state_rope
                .iter()
                .flat_map(|r| [r.cos.id(), r.sin.id()]),
        );
        v
    }
}

/// Result of [`PiModel::sample`].
#[derive(Debug, Clone)]
pub struct SampleOutput {
    /// x_0 [B, H, A].
    pub actions: Tensor,
    /// Velocity at the first step (t = 1) [B, H, A].
    pub v_t_step0: Tensor,
    /// Time values of the steps (f32 accumulation).
    pub times: Vec<f32>,
}

/// Result of [`PiModel::loss`].
#[derive(Debug, Clone)]
pub struct LossOutput {
    /// `(u - v)^2` [B, H, A].
    pub per_element: Tensor,
    /// Mean of `per_element` (scalar).
    pub mean: Tensor,
    /// Model velocity [B, H, A].
    pub v_t: Tensor,
}

/// Kind-specific suffix heads.
#[derive(Debug, Clone)]
enum SuffixHeads {
    Pi0 {
        state_proj: Linear,
        mlp_in: Linear,
        mlp_out: Linear,
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

/// Per-time suffix tensors: (time bits, batch) -> (time embedding, adaRMS condition).
type TimeTable = std::sync::Arc<std::sync::Mutex<HashMap<(u32, usize), (Tensor, Option<Tensor>)>>>;

/// The flow-matching sampler's integration, written once for the plain, uncached and guided
/// samplers: Euler from t = 1 (noise) to t = 0 (data) with `dt = -1/steps`, time accumulated in
/// f32 and the loop running while `t >= -dt/2` (openpi's grid), `x <- x + dt * v(x, t)` with the
/// state `x` in f32. `noise` [B, H, A].
pub fn euler(
    noise: &Tensor,
    steps: usize,
    mut velocity: impl FnMut(&Tensor, f32) -> Result<Tensor, PolicyError>,
) -> Result<SampleOutput, PolicyError> {
    if steps == 0 {
        return Err(PolicyError::Input("steps must be > 0".into()));
    }
    let dt = -1.0f32 / steps as f32;
    let mut time = 1.0f32;
    let mut x = noise.to_dtype(DType::F32)?;
    let mut v0 = None;
    let mut times = Vec::with_capacity(steps);
    while time >= -dt / 2.0 {
        let v = velocity(&x, time)?;
        x = (x + (&v * dt as f64)?)?;
        if v0.is_none() {
            v0 = Some(v);
        }
        times.push(time);
        time += dt;
    }
    let v_t_step0 = v0.ok_or_else(|| PolicyError::Input("no denoising step ran".into()))?;
    Ok(SampleOutput {
        actions: x,
        v_t_step0,
        times,
    })
}

/// Sinusoidal time embedding [B, W] (sin half then cos half), computed in f64 like openpi's
/// PyTorch reference, then cast to f32.
pub fn time_embedding(
    t: &[f32],
    width: usize,
    min_period: f64,
    max_period: f64,
    dev: &Device,
) -> candle_core::Result<Tensor> {
    let half = width / 2;
    let mut out = Vec::with_capacity(t.len() * width);
    for &ti in t {
        let mut sin = Vec::with_capacity(half);
        let mut cos = Vec::with_capacity(half);
        for i in 0..half {
            let frac = if half > 1 {
                i as f64 / (half - 1) as f64
            } else {
                0.0
            };
            let period = min_period * (max_period / min_period).powf(frac);
            let x = (1.0 / period * 2.0 * std::f64::consts::PI) * ti as f64;
            sin.push(x.sin() as f32);
            cos.push(x.cos() as f32);
        }
        out.extend(sin);
        out.extend(cos);
    }
    Tensor::from_vec(out, (t.len(), width), dev)
}

/// Additive bias from a boolean mask: 0 where visible, [`MASK_VALUE`] elsewhere (f32: scores
/// are masked and normalised in f32 whatever the model's dtype).
fn bias_tensor(
    vis: Vec<bool>,
    shape: (usize, usize, usize, usize),
    dev: &Device,
) -> candle_core::Result<Tensor> {
    let v: Vec<f32> = vis
        .into_iter()
        .map(|b| if b { 0.0 } else { MASK_VALUE })
        .collect();
    Tensor::from_vec(v, shape, dev)
}

/// openpi `make_att_2d_masks`: query i sees key j iff `cum[j] <= cum[i]` and both are valid.
pub fn att_2d_mask(pad: &[bool], ar: &[bool]) -> Vec<bool> {
    let n = pad.len();
    let mut cum = Vec::with_capacity(n);
    let mut c = 0u32;
    for &a in ar {
        c += a as u32;
        cum.push(c);
    }
    let mut m = Vec::with_capacity(n * n);
    for i in 0..n {
        for j in 0..n {
            m.push(cum[j] <= cum[i] && pad[i] && pad[j]);
        }
    }
    m
}

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
            ModelKind::Pi0 => SuffixHeads::Pi0 {
                state_proj: candle_nn::linear(a, we, vf.pp("state_proj"))?,
                mlp_in: candle_nn::linear(2 * we, we, vf.pp("action_time_mlp_in"))?,
                mlp_out: candle_nn::linear(we, we, vf.pp("action_time_mlp_out"))?,
            },
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
    /// `with_state`: prepend π0's state token.
    fn embed_suffix(
        &self,
        state: &Tensor,
        x_t: &Tensor,
        t: &[f32],
        with_state: bool,
    ) -> candle_core::Result<(Tensor, Option<Tensor>)> {
        let we = self.cfg.action_expert.width;
        let (te, cond) = self.time_features(t)?;
        // [B, H, We], in f32 like the heads; the tokens enter the expert in the model's dtype
        let a = self.action_in_proj.forward(&x_t.to_dtype(DType::F32)?)?;
        match &self.heads {
            SuffixHeads::Pi0 {
                state_proj,
                mlp_in,
                mlp_out,
            } => {
                let (b, h, _) = a.dims3()?;
                let te = te.unsqueeze(1)?.broadcast_as((b, h, we))?;
                let at = Tensor::cat(&[&a, &te], 2)?;
                let at = mlp_out.forward(&mlp_in.forward(&at)?.silu()?)?;
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

    /// What the suffix needs of the time `t` [B]: the sinusoidal embedding [B, We] and, for
    /// π0.5, the adaRMS condition [B, We] (the time MLP of it; f32, the norms' dense layers are
    /// f32). Neither depends on the observation, so for a batch at one time they are made once
    /// per model and time and kept on the device: a denoising step uploads nothing and runs no
    /// time MLP. (Not for a model whose time MLP is being trained: its weights change.)
    fn time_features(&self, t: &[f32]) -> candle_core::Result<(Tensor, Option<Tensor>)> {
        let b = t.len();
        let trainable = match &self.heads {
            SuffixHeads::Pi0 { .. } => false,
            SuffixHeads::Pi05 { time_in, .. } => time_in.weight().is_variable(),
        };
        let key = match t.first() {
            Some(t0) if !trainable && t.iter().all(|x| x == t0) => Some((t0.to_bits(), b)),
            _ => None,
        };
        if let Some(k) = key {
            if let Some(v) = self.time_table.lock().ok().and_then(|m| m.get(&k).cloned()) {
                return Ok(v);
            }
        }
        let te = time_embedding(
            t,
            self.cfg.action_expert.width,
            self.cfg.time_min_period,
            self.cfg.time_max_period,
            &self.device,
        )?;
        let cond = match &self.heads {
            SuffixHeads::Pi0 { .. } => None,
            SuffixHeads::Pi05 { time_in, time_out } => {
                Some(time_out.forward(&time_in.forward(&te)?.silu()?)?.silu()?)
            }
        };
        if let (Some(k), Ok(mut m)) = (key, self.time_table.lock()) {
            // a handful of step counts in practice; bounded whatever a caller does
            if m.len() >= 4096 {
                m.clear();
            }
            m.insert(k, (te.clone(), cond.clone()));
        }
        Ok((te, cond))
    }

    /// The adaRMS condition at time `t` (π0.5; `None` for π0) [B, We].
    pub fn adarms_cond(&self, t: &[f32]) -> candle_core::Result<Option<Tensor>> {
        Ok(self.time_features(t)?.1)
    }

    /// `embed_suffix` output at time `t` (π0: state token first) [B, S, We].
    pub fn suffix_embeddings(
        &self,
        state: &Tensor,
        x_t: &Tensor,
        t: &[f32],
    ) -> Result<Tensor, PolicyError> {
        Ok(self.embed_suffix(state, x_t, t, true)?.0)
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

    /// The host half of [`Self::fill_cache`]: checks the inputs, plans the prefix layout and
    /// copies everything the device half reads into the cache (allocating it, or reusing its
    /// buffers when the shapes match). In the fixed layout every buffer keeps its address across
    /// observations, so a graph captured over [`Self::run_prefix`] reads the new observation.
    /// `skip_masked`: cameras masked in every batch row skip the vision pass (compact layout only).
    pub fn prepare_prefix<'c>(
        &self,
        inp: &ModelInputs,
        cache: &'c mut Option<PrefixCache>,
        skip_masked: bool,
    ) -> Result<&'c mut PrefixCache, PolicyError> {
        let b = self.check_inputs(inp)?;
        let d = &self.cfg.paligemma;
        let p = self.cfg.prefix_len();
        let ns = self.cfg.state_tokens();
        let fixed = self.fixed_step_shapes;
        // cache length: P + S, in the fixed layout rounded up to a multiple of 8 slots (masked)
        // so that the step's score and probability rows start 16-byte aligned in bf16 (cuBLAS
        // falls back to slow kernels for misaligned leading dimensions)
        let total = if fixed {
            (p + self.cfg.suffix_len()).next_multiple_of(8)
        } else {
            p + self.cfg.suffix_len()
        };
        let tail = total - p - self.cfg.suffix_len();
        // token ids in range (one host read; the embedding lookup would fault otherwise)
        let ids = inp.tokens.flatten_all()?.to_dtype(DType::U32)?;
        let vocab = self.embed_tokens.dim(0)?;
        let id_range = inp.tokens.flatten_all()?.to_dtype(DType::F64)?;
        let (min_id, max_id) = (
            id_range.min(0)?.to_scalar::<f64>()?,
            id_range.max(0)?.to_scalar::<f64>()?,
        );
        if min_id < 0.0 || max_id >= vocab as f64 {
            return Err(PolicyError::Input(format!(
                "token ids must be in [0, {vocab}), got [{min_id}, {max_id}]"
            )));
        }
        let layout = self.prefix_layout(inp);
        // cameras through the vision tower: all in the fixed layout (same work every time)
        let cams: Vec<usize> = (0..inp.images.len())
            .filter(|&c| fixed || !skip_masked || inp.image_masks[c].iter().any(|&m| m))
            .collect();
        // Compaction (compact layout): padding tokens and masked cameras never influence valid
        // tokens (they are masked as keys everywhere), so the prefix pass runs over the valid
        // tokens only, in order, padded per row to the largest valid count `pc` with (masked)
        // filler tokens. The fixed layout runs all P slots, masked the same way.
        let pc = if fixed {
            p
        } else {
            layout.n_valid.iter().copied().max().unwrap_or(0).max(1)
        };
        let mut rows = Vec::with_capacity(b);
        let mut cpad = Vec::with_capacity(b);
        let mut cpos = Vec::with_capacity(b);
        for bi in 0..b {
            let pad = &layout.pad[bi];
            let mut idx: Vec<u32> = (0..p)
                .filter(|&j| fixed || pad[j])
                .map(|j| j as u32)
                .collect();
            idx.extend(
                (0..p)
                    .filter(|&j| !fixed && !pad[j])
                    .take(pc - idx.len().min(pc))
                    .map(|j| j as u32),
            );
            cpad.push(idx.iter().map(|&j| pad[j as usize]).collect::<Vec<_>>());
            cpos.push(
                idx.iter()
                    .map(|&j| layout.pos[bi][j as usize])
                    .collect::<Vec<_>>(),
            );
            rows.push(idx);
        }
        let rows = if pc == p
            && rows
                .iter()
                .all(|r| r.iter().enumerate().all(|(i, &j)| i == j as usize))
        {
            Vec::new()
        } else {
            rows.iter()
                .map(|r| Tensor::new(r.as_slice(), &self.device))
                .collect::<candle_core::Result<Vec<_>>>()?
        };
        let compact = PrefixLayout {
            pad: cpad,
            pos: cpos,
            n_valid: layout.n_valid.clone(),
        };
        // Where the suffix goes in the cache. Compact layout (the CPU's): right after the
        // compacted prefix, at pc, so a denoising step attends over pc + S keys instead of
        // P + S: the padding slots are skipped, not masked. Fixed layout (GPUs'): at P, so a
        // step's shapes, offsets and buffers are the same for every observation.
        // Key visibility for suffix queries: the computed prefix slots (padding masked), then
        // every suffix slot.
        let so = pc;
        let t_step = so + total - p;
        let mut vis = Vec::with_capacity(b * t_step);
        for row in &compact.pad {
            vis.extend_from_slice(row);
            vis.extend(std::iter::repeat_n(true, total - p - tail));
            vis.extend(std::iter::repeat_n(false, tail));
        }
        // positions of the action tokens: n_valid + state_tokens + [0, H)
        let h = self.cfg.action_horizon;
        let apos: Vec<Vec<i64>> = layout
            .n_valid
            .iter()
            .map(|&n| (0..h).map(|i| (n + ns + i) as i64).collect())
            .collect();
        // π0: the state token sees the computed prefix and itself
        let state_part = if ns == 1 {
            let spos: Vec<Vec<i64>> = layout.n_valid.iter().map(|&n| vec![n as i64]).collect();
            let mut svis = Vec::with_capacity(b * (so + 1));
            for row in &compact.pad {
                svis.extend_from_slice(row);
                svis.push(true);
            }
            Some((
                bias_tensor(svis, (b, 1, 1, so + 1), &self.device)?,
                self.rope(&spos)?,
            ))
        } else {
            None
        };
        let images = if cams.is_empty() {
            // every camera masked: no vision pass (their tokens are padding)
            let s = self.cfg.vision.image_size;
            Tensor::zeros((0, 3, s, s), DType::F32, &self.device)?
        } else {
            let imgs: Vec<Tensor> = cams
                .iter()
                .map(|&c| inp.images[c].to_dtype(DType::F32))
                .collect::<candle_core::Result<_>>()?;
            Tensor::cat(&imgs, 0)?
        };
        // own copies: the caller's tensors may be reused or freed (a conversion to the same
        // dtype, or a cat of one camera, would alias them)
        let fresh = PrefixStatics {
            images: images.copy()?,
            ids: ids.copy()?,
            state: inp.state.to_dtype(DType::F32)?.copy()?,
            prefix_valid: {
                let v: Vec<f32> = compact
                    .pad
                    .iter()
                    .flatten()
                    .map(|&m| m as u8 as f32)
                    .collect();
                Tensor::from_vec(v, (b, pc), &self.device)?
            },
            prefix_pos: {
                let v: Vec<f32> = compact.pos.iter().flatten().map(|&p| p as f32).collect();
                Tensor::from_vec(v, (b, pc), &self.device)?
            },
            step_bias: bias_tensor(vis, (b, 1, 1, t_step), &self.device)?,
            action_rope: self.rope(&apos)?,
            state_bias: state_part.as_ref().map(|s| s.0.clone()),
            state_rope: state_part.map(|s| s.1),
        };
        let reuse = matches!(cache, Some(c) if c.batch == b && c.k.first().map(|k| k.dims() == [b, d.num_kv_heads, total, d.head_dim]).unwrap_or(false));
        let c = match cache.take() {
            Some(mut c) if reuse => {
                // fixed layout: the same device buffers as for the previous observation, refilled
                c.statics = if fixed {
                    c.statics.refill(fresh)?
                } else {
                    fresh
                };
                c.cams = cams;
                c.rows = rows;
                c.action_offset = so + ns;
                c.layout = layout;
                c
            }
            _ => {
                let mut ks = Vec::with_capacity(d.depth);
                let mut vs = Vec::with_capacity(d.depth);
                for _ in 0..d.depth {
                    for kv in [&mut ks, &mut vs] {
                        kv.push(Tensor::zeros(
                            (b, d.num_kv_heads, total, d.head_dim),
                            self.dtype,
                            &self.device,
                        )?);
                    }
                }
                PrefixCache {
                    k: ks,
                    v: vs,
                    statics: fresh,
                    cams,
                    rows,
                    action_offset: so + ns,
                    layout,
                    batch: b,
                }
            }
        };
        Ok(cache.insert(c))
    }

    /// The device half of [`Self::fill_cache`]: the vision tower, the embeddings and the VLM
    /// expert over the prefix (and π0's state token through the action expert), K/V into the
    /// cache, reading only the cache's buffers ([`Self::prepare_prefix`] filled them): no host
    /// read or upload of anything observation-dependent. `embs`: precomputed prefix embeddings
    /// [B, P, W] instead of the vision pass.
    pub fn run_prefix(
        &self,
        c: &PrefixCache,
        embs: Option<&Tensor>,
        want_out: bool,
    ) -> Result<Option<Tensor>, PolicyError> {
        let d = &self.cfg.paligemma;
        let b = c.batch;
        let s = &c.statics;
        let embs = match embs {
            Some(e) => e.clone(),
            None => self.embed_from(c)?,
        };
        let x = match c.rows.as_slice() {
            [] => embs,
            [r] if b == 1 => embs.index_select(r, 1)?,
            rs => {
                let mut parts = Vec::with_capacity(b);
                for (bi, r) in rs.iter().enumerate() {
                    parts.push(embs.narrow(0, bi, 1)?.index_select(r, 1)?);
                }
                Tensor::cat(&parts, 0)?
            }
        };
        // the mask [B, 1, Pc, Pc] (0 where both tokens are valid, the mask value elsewhere) and
        // the RoPE tables, made on the device from the observation's validity and positions
        let prefix_bias = {
            let v = &s.prefix_valid;
            let both = v.unsqueeze(2)?.broadcast_mul(&v.unsqueeze(1)?)?;
            ((both - 1.0)? * (-(MASK_VALUE as f64)))?.unsqueeze(1)?
        };
        let prefix_rope = Rope::from_positions(
            &s.prefix_pos,
            self.cfg.paligemma.head_dim,
            self.cfg.rope_theta,
            self.dtype,
        )?;
        let mut streams = [Stream {
            x,
            expert: &self.vlm,
            cond: None,
            rope: &prefix_rope,
            pending: None,
        }];
        for li in 0..d.depth {
            if li + 1 == d.depth && !want_out {
                // the last layer only has to provide K/V
                kv_only_layer(li, &streams[0], &c.k[li], &c.v[li])?;
                continue;
            }
            joint_layer(
                li,
                &mut streams,
                &prefix_bias,
                KvMode::Own {
                    store: Some((&c.k[li], &c.v[li])),
                },
                false,
            )?;
        }
        let out = if want_out {
            Some(self.vlm.norm.forward(&streams[0].x, None, false)?.0)
        } else {
            None
        };
        if let (Some(sbias), Some(srope)) = (&s.state_bias, &s.state_rope) {
            // π0: the state token sees the prefix and itself only, so its K/V do not depend on
            // x_t or t: run it once through the action expert and keep it in the cache at P.
            let SuffixHeads::Pi0 { state_proj, .. } = &self.heads else {
                return Err(PolicyError::Config("pi0 without state_proj".into()));
            };
            let st = state_proj
                .forward(&s.state)?
                .unsqueeze(1)?
                .to_dtype(self.dtype)?;
            let mut st = [Stream {
                x: st,
                expert: &self.expert,
                cond: None,
                rope: srope,
                pending: None,
            }];
            for li in 0..d.depth {
                joint_layer(
                    li,
                    &mut st,
                    sbias,
                    KvMode::Cached {
                        k: &c.k[li],
                        v: &c.v[li],
                        offset: c.action_offset - 1,
                    },
                    false,
                )?;
            }
        }
        Ok(out)
    }

    /// Prefix embeddings [B, P, W] from the cache's images and token ids: image embeddings per
    /// camera (zeros for a camera that skipped the vision pass), then `embed(ids) * sqrt(W)`.
    fn embed_from(&self, c: &PrefixCache) -> Result<Tensor, PolicyError> {
        let b = c.batch;
        let t = self.cfg.vision.num_tokens();
        let w = self.cfg.paligemma.width;
        let emb = if c.cams.is_empty() {
            None
        } else {
            Some(
                self.vision
                    .forward_with(&c.statics.images, false)?
                    .to_dtype(self.dtype)?,
            )
        };
        let mut parts = Vec::with_capacity(self.cfg.cameras.len() + 1);
        for cam in 0..self.cfg.cameras.len() {
            match (c.cams.iter().position(|&r| r == cam), &emb) {
                (Some(i), Some(e)) => parts.push(e.narrow(0, i * b, b)?),
                _ => parts.push(Tensor::zeros((b, t, w), self.dtype, &self.device)?),
            }
        }
        let text = self
            .embed_tokens
            .index_select(&c.statics.ids, 0)?
            .reshape((b, self.cfg.max_token_len, w))?;
        parts.push((text * (w as f64).sqrt())?);
        Ok(Tensor::cat(&parts, 1)?)
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
    pub fn velocity_at(
        &self,
        cache: &PrefixCache,
        x_t: &Tensor,
        t: &[f32],
        differentiable: bool,
    ) -> Result<Tensor, PolicyError> {
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
        let (tokens, cond) = self.embed_suffix(x_t, x_t, t, false)?;
        let mut st = [Stream {
            x: tokens,
            expert: &self.expert,
            cond: cond.as_ref(),
            rope: cache.action_rope(),
            pending: None,
        }];
        for li in 0..self.cfg.action_expert.depth {
            joint_layer(
                li,
                &mut st,
                cache.step_bias(),
                KvMode::Cached {
                    k: &cache.k[li],
                    v: &cache.v[li],
                    offset: cache.action_offset,
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
    pub fn joint_forward(
        &self,
        inp: &ModelInputs,
        prefix_embs: &Tensor,
        x_t: &Tensor,
        t: &[f32],
        diff: bool,
    ) -> Result<(Tensor, Tensor), PolicyError> {
        let (po, so, _) = self.joint_forward_tap(inp, prefix_embs, x_t, t, diff, None)?;
        Ok((po, so))
    }

    /// [`Self::joint_forward`], also returning the prefix hidden states [B, P, W] at the input
    /// of layer `tap` (training's auxiliary losses read them).
    pub fn joint_forward_tap(
        &self,
        inp: &ModelInputs,
        prefix_embs: &Tensor,
        x_t: &Tensor,
        t: &[f32],
        diff: bool,
        tap: Option<usize>,
    ) -> Result<(Tensor, Tensor, Option<Tensor>), PolicyError> {
        let b = self.check_inputs(inp)?;
        let layout = self.prefix_layout(inp);
        let (suffix, cond) = self.embed_suffix(&inp.state, x_t, t, true)?;
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

    /// Velocity from the joint forward (no cache) [B, H, A].
    pub fn velocity_uncached(
        &self,
        inp: &ModelInputs,
        prefix_embs: &Tensor,
        x_t: &Tensor,
        t: &[f32],
        diff: bool,
    ) -> Result<Tensor, PolicyError> {
        let (_, so) = self.joint_forward(inp, prefix_embs, x_t, t, diff)?;
        let s = so.dim(1)?;
        let h = self.cfg.action_horizon;
        Ok(self
            .action_out_proj
            .forward(&so.narrow(1, s - h, h)?.to_dtype(DType::F32)?)?)
    }

    /// Flow-matching sampler: Euler from t = 1 (noise) with `dt = -1/steps`, time accumulated in
    /// f32, loop while `t >= -dt/2`. `noise` [B, H, A]. With `cache` the prefix runs once and each
    /// step only runs the action expert (buffers in `cache` are reused); without, every step runs
    /// the full joint forward.
    pub fn sample(
        &self,
        inp: &ModelInputs,
        noise: &Tensor,
        steps: usize,
        cache: Option<&mut Option<PrefixCache>>,
    ) -> Result<SampleOutput, PolicyError> {
        let b = self.check_inputs(inp)?;
        let want = [b, self.cfg.action_horizon, self.cfg.action_dim];
        if noise.dims() != want {
            return Err(PolicyError::Input(format!(
                "noise: shape {:?}, expected {want:?}",
                noise.dims()
            )));
        }
        match cache {
            Some(cache) => {
                self.fill_cache(inp, cache, false)?;
                let c = cache.as_ref().expect("fill_cache stores the cache");
                self.denoise(c, noise, steps)
            }
            None => {
                let embs = self.embed_prefix(inp)?;
                euler(noise, steps, |x, t| {
                    self.velocity_uncached(inp, &embs, x, &vec![t; b], false)
                })
            }
        }
    }

    /// The denoising loop against a filled prefix cache: [`euler`] with the cached velocity.
    /// `noise` [B, H, A].
    pub fn denoise(
        &self,
        cache: &PrefixCache,
        noise: &Tensor,
        steps: usize,
    ) -> Result<SampleOutput, PolicyError> {
        let b = cache.batch;
        euler(noise, steps, |x, t| {
            self.velocity_at(cache, x, &vec![t; b], false)
        })
    }

    /// Flow-matching training loss: `x_t = t*noise + (1-t)*actions`, `u = noise - actions`,
    /// `(u - v(x_t, t))^2` per element (joint forward, no cache). `time` [B] f32.
    /// With `diff` every op has a backward (train with a `VarMap`-backed model).
    pub fn loss(
        &self,
        inp: &ModelInputs,
        actions: &Tensor,
        noise: &Tensor,
        time: &Tensor,
        diff: bool,
    ) -> Result<LossOutput, PolicyError> {
        let embs = self.embed_prefix_inner(inp, false, diff)?;
        Ok(self
            .loss_tap(inp, &embs, actions, noise, time, diff, None)?
            .0)
    }

    /// [`Self::loss`] on prefix embeddings already computed ([`Self::embed_prefix_with`]), also
    /// returning the prefix hidden states at the input of layer
    /// `tap` ([`Self::joint_forward_tap`]).
    #[allow(clippy::too_many_arguments)]
    pub fn loss_tap(
        &self,
        inp: &ModelInputs,
        embs: &Tensor,
        actions: &Tensor,
        noise: &Tensor,
        time: &Tensor,
        diff: bool,
        tap: Option<usize>,
    ) -> Result<(LossOutput, Option<Tensor>), PolicyError> {
        let (tv, x_t, u) = noisy_actions(actions, noise, time)?;
        let (_, so, tapped) = self.joint_forward_tap(inp, embs, &x_t, &tv, diff, tap)?;
        Ok((self.flow_loss(&so, &u)?, tapped))
    }

    /// The flow-matching loss from the action expert's output `so` [B, S, w] (its last H tokens
    /// are the actions') and the target velocity `u` = ε − a [B, H, A].
    fn flow_loss(&self, so: &Tensor, u: &Tensor) -> Result<LossOutput, PolicyError> {
        let s = so.dim(1)?;
        let h = self.cfg.action_horizon;
        let v_t = self
            .action_out_proj
            .forward(&so.narrow(1, s - h, h)?.to_dtype(DType::F32)?)?;
        let per_element = (u - &v_t)?.sqr()?;
        let mean = per_element.mean_all()?;
        Ok(LossOutput {
            per_element,
            mean,
            v_t,
        })
    }

    /// The flow-matching loss with `k` noise / time samples per observation that share one
    /// prefix pass: the prefix never attends to the suffix, so the language model runs once over
    /// the B prefixes (keeping each layer's keys and values), and the action expert runs over
    /// the B·k suffixes against those keys and values. `actions` [B, H, A]; `noise` [B·k, H, A]
    /// and `time` [B·k] (sample j of observation b at row b·k + j). Equal to [`Self::loss_tap`]
    /// on the observations repeated k times. Also returns the prefix hidden states at the
    /// input of layer `tap`.
    #[allow(clippy::too_many_arguments)]
    pub fn loss_multi(
        &self,
        inp: &ModelInputs,
        embs: &Tensor,
        actions: &Tensor,
        noise: &Tensor,
        time: &Tensor,
        k: usize,
        diff: bool,
        tap: Option<usize>,
    ) -> Result<(LossOutput, Option<Tensor>), PolicyError> {
        let b = self.check_inputs(inp)?;
        let k = k.max(1);
        let bk = b * k;
        if noise.dim(0)? != bk || time.dim(0)? != bk || actions.dim(0)? != b {
            return Err(PolicyError::Input(format!(
                "loss_multi: {b} observations x {k} samples need noise / time rows {bk}, got {} / {}",
                noise.dim(0)?,
                time.dim(0)?
            )));
        }
        // row b·k + j of every per-sample tensor belongs to observation b
        let rep_idx: Vec<u32> = (0..bk).map(|r| (r / k) as u32).collect();
        let rep_idx = Tensor::new(rep_idx.as_slice(), &self.device)?;
        let rep = |x: &Tensor| x.index_select(&rep_idx, 0);
        let (tv, x_t, u) = noisy_actions(&rep(actions)?, noise, time)?;

        // prefix: the VLM expert alone, keeping each layer's K/V
        let layout = self.prefix_layout(inp);
        let p = self.cfg.prefix_len();
        let d = &self.cfg.paligemma;
        let prope = self.rope(&layout.pos)?;
        let pbias = self.prefix_bias(&layout)?;
        let mut prefix = [Stream {
            x: embs.clone(),
            expert: &self.vlm,
            cond: None,
            rope: &prope,
            pending: None,
        }];
        let mut kvs = Vec::with_capacity(d.depth);
        let mut tapped = None;
        for li in 0..d.depth {
            if tap == Some(li) {
                tapped = Some(prefix[0].x.clone());
            }
            kvs.push(joint_layer(
                li,
                &mut prefix,
                &pbias,
                KvMode::Own { store: None },
                diff,
            )?);
        }

        // suffix: B·k rows against the repeated prefix K/V
        let state = rep(&inp.state)?;
        let (suffix, cond) = self.embed_suffix(&state, &x_t, &tv, true)?;
        let s = suffix.dim(1)?;
        let ar_s = self.suffix_ar();
        let mut vis = Vec::with_capacity(bk * s * (p + s));
        let mut spos = Vec::with_capacity(bk);
        for r in 0..bk {
            let bi = r / k;
            let mut pad = layout.pad[bi].clone();
            pad.extend(std::iter::repeat_n(true, s));
            let mut ar = vec![false; p];
            ar.extend_from_slice(&ar_s);
            let m = att_2d_mask(&pad, &ar);
            for qi in p..p + s {
                vis.extend_from_slice(&m[qi * (p + s)..(qi + 1) * (p + s)]);
            }
            let n = layout.n_valid[bi] as i64;
            spos.push((0..s as i64).map(|i| n + i).collect::<Vec<_>>());
        }
        let sbias = bias_tensor(vis, (bk, 1, s, p + s), &self.device)?;
        let srope = self.rope(&spos)?;
        let mut st = [Stream {
            x: suffix,
            expert: &self.expert,
            cond: cond.as_ref(),
            rope: &srope,
            pending: None,
        }];
        for (li, (kp, vp)) in kvs.iter().enumerate() {
            let (mut kr, mut vr) = if k == 1 {
                (kp.clone(), vp.clone())
            } else {
                (rep(kp)?, rep(vp)?)
            };
            if !diff {
                // the fast path writes the suffix K/V into the buffer after the prefix
                let pad = |x: &Tensor| -> candle_core::Result<Tensor> {
                    let (n, h, _, hd) = x.dims4()?;
                    let z = Tensor::zeros((n, h, s, hd), DType::F32, &self.device)?;
                    Tensor::cat(&[x, &z], 2)
                };
                kr = pad(&kr)?;
                vr = pad(&vr)?;
            }
            joint_layer(
                li,
                &mut st,
                &sbias,
                KvMode::Cached {
                    k: &kr,
                    v: &vr,
                    offset: p,
                },
                diff,
            )?;
        }
        let so = self.expert.norm.forward(&st[0].x, cond.as_ref(), diff)?.0;
        Ok((self.flow_loss(&so, &u)?, tapped))
    }
}

/// Flow matching's interpolation: the times `t` as a vector, `x_t = t·ε + (1 − t)·a` and the
/// target velocity `u = ε − a`, for `actions` a and `noise` ε [B, H, A] and `time` [B].
fn noisy_actions(
    actions: &Tensor,
    noise: &Tensor,
    time: &Tensor,
) -> Result<(Vec<f32>, Tensor, Tensor), PolicyError> {
    let time = time.to_dtype(DType::F32)?;
    let tv = time.to_vec1::<f32>()?;
    let t3 = time.reshape((tv.len(), 1, 1))?;
    let x_t = (noise.broadcast_mul(&t3)? + actions.broadcast_mul(&(t3.neg()? + 1.0)?)?)?;
    let u = (noise - actions)?;
    Ok((tv, x_t, u))
}
