//! The Gemma dual-expert transformer of π0 / π0.5.
//!
//! Two experts (the PaliGemma language model for prefix tokens, the action expert for suffix
//! tokens) each have their own norms, Q/K/V/O projections and MLP; at every layer one masked
//! attention runs over the concatenation of the streams that are present. GQA with any number of
//! kv heads (kv-head-major), RoPE rotate-half, Gemma RMSNorm `(1 + w)`, and for π0.5's action
//! expert adaRMSNorm `norm(x) * (1 + scale) + shift` with gated residuals.
//!
//! Every op has a fast path (candle's fused CPU kernels) and a differentiable path built from
//! differentiable compositions, selected per call with `diff`.

use candle_core::{DType, Module, Tensor, D};
use candle_nn::{Linear, VarBuilder};

use super::config::GemmaDims;
use super::fastops;
use super::packed::{PackedRhs, Precision};

mod norm;

pub use norm::{gated_residual, Norm, Rope};

/// Additive attention mask value used by openpi (not `-inf`).
pub const MASK_VALUE: f32 = -2.381_976_3e38;

/// One expert layer: norms, attention projections and the gelu-tanh gated MLP.
#[derive(Debug, Clone)]
pub struct ExpertLayer {
    input_norm: Norm,
    post_norm: Norm,
    q: Linear,
    k: Linear,
    v: Linear,
    o: Linear,
    gate: Linear,
    up: Linear,
    down: Linear,
    /// Fast path of inference models (weights that are not trainable variables): the Q/K/V
    /// projections side by side, [W, qd + 2 kvd] row-major, and gate/up, [W, 2 mlp]. `q`..`up`
    /// are views into these, so the memory is not doubled.
    qkv: Option<Tensor>,
    gate_up: Option<Tensor>,
    /// The same weights packed for [`PackedRhs`] (f32 by default, bf16 with
    /// `policy.precision = "bf16"`, [`Expert::pack`]).
    packed: Option<Box<PackedLayer>>,
}

/// The fast-path weights of one layer packed for [`PackedRhs::matmul`].
#[derive(Debug, Clone)]
struct PackedLayer {
    qkv: PackedRhs,
    /// The K/V columns of `qkv` alone (the prefix's last layer needs only its K/V).
    kv: PackedRhs,
    o: PackedRhs,
    gate_up: PackedRhs,
    down: PackedRhs,
}

/// `x · w` with the packed weight when there is one (fast path), else `None`.
fn packed_mm(x: &Tensor, w: Option<&PackedRhs>, diff: bool) -> candle_core::Result<Option<Tensor>> {
    match (diff, w) {
        (false, Some(w)) => w.matmul(x),
        _ => Ok(None),
    }
}

/// `x` [.., K] times `w` [K, N] (any strides) as one 2-D matmul: [.., N].
fn matmul_2d(x: &Tensor, w: &Tensor) -> candle_core::Result<Tensor> {
    let dims = x.dims();
    let k = dims.last().copied().unwrap_or(1);
    let rows = x.elem_count() / k.max(1);
    let y = x.contiguous()?.reshape((rows, k))?.matmul(w)?;
    let mut shape = dims.to_vec();
    if let Some(last) = shape.last_mut() {
        *last = w.dim(1)?;
    }
    y.reshape(shape)
}

/// The weights `[N, K]` of `ls` stacked as one row-major `[K, sum N]` matrix, and each `Linear`
/// rebuilt as a (column-major) view into it. gemm then reads the weights with unit stride along N
/// and skips the repacking a row-major `[N, K]` weight needs, and the projections of one input
/// become one matmul.
fn fuse(ls: &mut [&mut Linear]) -> candle_core::Result<Tensor> {
    let ts: Vec<Tensor> = ls
        .iter()
        .map(|l| l.weight().t())
        .collect::<Result<_, _>>()?;
    let w = Tensor::cat(&ts, 1)?;
    let mut off = 0;
    for l in ls.iter_mut() {
        let n = l.weight().dim(0)?;
        **l = Linear::new(w.narrow(1, off, n)?.t()?, l.bias().cloned());
        off += n;
    }
    Ok(w)
}

impl ExpertLayer {
    /// Packs the fused fast-path weights for `precision`. Returns false (and keeps what was
    /// packed before) when this CPU has no kernel for it or the layer has no fused weights.
    fn pack(&mut self, precision: Precision) -> candle_core::Result<bool> {
        let (Some(qkv), Some(gu)) = (&self.qkv, &self.gate_up) else {
            return Ok(false);
        };
        let qd = self.q.weight().dim(0)?;
        let kvd = self.k.weight().dim(0)?;
        let p = |w: &Tensor| PackedRhs::pack(w, precision);
        let pw = |w: &Tensor| PackedRhs::pack_weight(w, precision);
        let (Some(qkv_p), Some(kv), Some(o), Some(gate_up), Some(down)) = (
            p(qkv)?,
            p(&qkv.narrow(1, qd, 2 * kvd)?)?,
            pw(self.o.weight())?,
            p(gu)?,
            pw(self.down.weight())?,
        ) else {
            return Ok(false);
        };
        self.packed = Some(Box::new(PackedLayer {
            qkv: qkv_p,
            kv,
            o,
            gate_up,
            down,
        }));
        Ok(true)
    }

    /// Builds the fused fast-path weights unless the weights are trainable variables (a `VarMap`
    /// model: the copies would go stale when an optimiser updates the variables).
    fn with_fused(mut self) -> candle_core::Result<Self> {
        if self.q.weight().is_variable() {
            return Ok(self);
        }
        self.qkv = Some(fuse(&mut [&mut self.q, &mut self.k, &mut self.v])?);
        self.gate_up = Some(fuse(&mut [&mut self.gate, &mut self.up])?);
        fuse(&mut [&mut self.o])?;
        fuse(&mut [&mut self.down])?;
        self.pack(Precision::F32)?;
        Ok(self)
    }
}

/// One Gemma expert (`layers.i.*` and the final `norm`).
#[derive(Debug, Clone)]
pub struct Expert {
    /// Layers.
    pub layers: Vec<ExpertLayer>,
    /// Final norm.
    pub norm: Norm,
    /// Dimensions.
    pub dims: GemmaDims,
}

impl Expert {
    /// Runs the fast path's matrix products with weights packed for `precision` from now on.
    /// Returns false when this CPU has no kernel for it (layers keep their previous packing).
    pub fn pack(&mut self, precision: Precision) -> candle_core::Result<bool> {
        let mut ok = true;
        for l in &mut self.layers {
            ok &= l.pack(precision)?;
        }
        Ok(ok)
    }

    /// `vb` at `...language_model` / `...gemma_expert.model`.
    pub fn new(dims: &GemmaDims, ada: bool, eps: f64, vb: VarBuilder) -> candle_core::Result<Self> {
        let w = dims.width;
        let qd = dims.num_heads * dims.head_dim;
        let kvd = dims.num_kv_heads * dims.head_dim;
        let mut layers = Vec::with_capacity(dims.depth);
        for i in 0..dims.depth {
            let vb = vb.pp(format!("layers.{i}"));
            let a = vb.pp("self_attn");
            let m = vb.pp("mlp");
            layers.push(
                ExpertLayer {
                    input_norm: Norm::new(w, ada, eps, vb.pp("input_layernorm"))?,
                    post_norm: Norm::new(w, ada, eps, vb.pp("post_attention_layernorm"))?,
                    q: candle_nn::linear_no_bias(w, qd, a.pp("q_proj"))?,
                    k: candle_nn::linear_no_bias(w, kvd, a.pp("k_proj"))?,
                    v: candle_nn::linear_no_bias(w, kvd, a.pp("v_proj"))?,
                    o: candle_nn::linear_no_bias(qd, w, a.pp("o_proj"))?,
                    gate: candle_nn::linear_no_bias(w, dims.mlp_dim, m.pp("gate_proj"))?,
                    up: candle_nn::linear_no_bias(w, dims.mlp_dim, m.pp("up_proj"))?,
                    down: candle_nn::linear_no_bias(dims.mlp_dim, w, m.pp("down_proj"))?,
                    qkv: None,
                    gate_up: None,
                    packed: None,
                }
                .with_fused()?,
            );
        }
        let norm = Norm::new(w, ada, eps, vb.pp("norm"))?;
        Ok(Expert {
            layers,
            norm,
            dims: dims.clone(),
        })
    }
}

/// One stream entering a joint layer: its tokens, expert, adaRMS condition and RoPE tables.
pub struct Stream<'a> {
    /// Hidden states [B, L, W].
    pub x: Tensor,
    /// The expert that owns these tokens.
    pub expert: &'a Expert,
    /// adaRMS condition [B, Wc], or per token [B, L, Wc] (π0.5 action expert only).
    pub cond: Option<&'a Tensor>,
    /// RoPE tables for this stream's positions.
    pub rope: &'a Rope,
    /// A gated residual not yet added (fused path): the hidden states are
    /// `x + m * gmod[.., 2W..3W]` (`gmod` None: `x + m`). The next fused layer adds it inside its
    /// first norm's kernel; [`Stream::settle`] adds it for anything else. Construct with `None`.
    pub pending: Option<(Tensor, Option<Tensor>)>,
}

impl Stream<'_> {
    /// Adds a pending gated residual into `x`.
    pub fn settle(&mut self) -> candle_core::Result<()> {
        if let Some((m, gmod)) = self.pending.take() {
            self.x = match super::kernels::gated_add(&self.x, &m, gmod.as_ref())? {
                Some(x) => x,
                None => {
                    let w = self.x.dim(D::Minus1)?;
                    let gate = match &gmod {
                        Some(g) => Some(
                            g.narrow(1, 2 * w, w)?
                                .unsqueeze(1)?
                                .to_dtype(self.x.dtype())?,
                        ),
                        None => None,
                    };
                    gated_residual(&self.x, &m, gate.as_ref(), false)?
                }
            };
        }
        Ok(())
    }
}

/// Where the keys/values of a layer come from.
#[derive(Clone, Copy)]
pub enum KvMode<'a> {
    /// Keys/values are only those of the streams (prefix pass, joint pass). When `store` is
    /// given, the (post-RoPE) K/V are written there at sequence offset 0.
    Own {
        /// Cache buffers `[B, nKV, T, hd]` to fill.
        store: Option<(&'a Tensor, &'a Tensor)>,
    },
    /// Keys/values = a cached buffer `[B, nKV, T, hd]` with the streams' K/V written at `offset`
    /// (fast path: in place; differentiable path: concatenated after `cache[..offset]`); the
    /// attention covers the first `bias.dim(3)` keys.
    Cached {
        /// K buffer.
        k: &'a Tensor,
        /// V buffer.
        v: &'a Tensor,
        /// Where the streams' tokens go.
        offset: usize,
    },
}

/// Attention `softmax(scale q k^T + bias) v` with GQA.
/// `q` [B, nH, L, hd], `k`, `v` [B, nKV, T, hd], `bias` [B, 1, L or 1, T].
/// Returns [B, L, nH*hd]. The fast path is one fused kernel ([`fastops::attention`]).
pub fn attention(
    q: &Tensor,
    k: &Tensor,
    v: &Tensor,
    bias: &Tensor,
    scale: f64,
    diff: bool,
) -> candle_core::Result<Tensor> {
    if !diff {
        if let Some(o) = fastops::attention(q, k, v, bias, scale as f32)? {
            return Ok(o);
        }
    }
    let q = (q * scale)?;
    let (b, nh, l, hd) = q.dims4()?;
    let nkv = k.dim(1)?;
    let t = k.dim(2)?;
    let g = nh / nkv;
    // [B, nKV, g*L, hd]: query heads are kv-head-major, so this is a free reshape
    let q = q.reshape((b, nkv, g * l, hd))?;
    // [B, nKV, g*L, T]
    let s = q.matmul(&k.t()?)?;
    let bl = bias.dim(2)?;
    // [B, nKV, g, L, T] + [B, 1, 1, L|1, T], masked and normalised in f32 (openpi's softmax
    // runs in f32 whatever the model's dtype), probabilities back in the model's dtype
    let s = s
        .reshape((b, nkv, g, l, t))?
        .to_dtype(DType::F32)?
        .broadcast_add(&bias.to_dtype(DType::F32)?.reshape((b, 1, 1, bl, t))?)?;
    let p = if diff {
        candle_nn::ops::softmax(&s, D::Minus1)?
    } else {
        candle_nn::ops::softmax_last_dim(&s)?
    }
    .to_dtype(v.dtype())?;
    // [B, nKV, g*L, hd] -> [B, nH, L, hd] -> [B, L, nH*hd]
    let o = p.reshape((b, nkv, g * l, t))?.matmul(v)?;
    o.reshape((b, nh, l, hd))?
        .transpose(1, 2)?
        .reshape((b, l, nh * hd))
}

/// `down(gelu_tanh(gate(x)) * up(x))`.
fn mlp(layer: &ExpertLayer, x: &Tensor, diff: bool) -> candle_core::Result<Tensor> {
    let a = layer.packed.as_deref();
    if let (false, Some(gu)) = (diff, &layer.gate_up) {
        let y = match packed_mm(x, a.map(|a| &a.gate_up), diff)? {
            Some(y) => y,
            None => matmul_2d(x, gu)?,
        };
        if let Some(h) = fastops::gelu_mul_fused(&y, gu.dim(1)? / 2)? {
            if let Some(o) = packed_mm(&h, a.map(|a| &a.down), diff)? {
                return Ok(o);
            }
            return layer.down.forward(&h);
        }
    }
    let g = layer.gate.forward(x)?;
    let u = layer.up.forward(x)?;
    if !diff {
        if let Some(h) = fastops::gelu_mul(&g, &u)? {
            return layer.down.forward(&h);
        }
    }
    layer.down.forward(&(g.gelu()? * u)?)
}

/// `[B, L, n*hd]` -> `[B, n, L, hd]`.
fn heads(x: &Tensor, n: usize, hd: usize) -> candle_core::Result<Tensor> {
    let (b, l, _) = x.dims3()?;
    x.reshape((b, l, n, hd))?.transpose(1, 2)?.contiguous()
}

/// Fast path: Q, K, V heads [B, n, L, hd] of the normed `h` [B, L, W] from the fused projection
/// (Q and K rotated; `with_q` false skips Q). `None` when the layer has no fused weights.
#[allow(clippy::type_complexity)]
fn qkv_fused(
    layer: &ExpertLayer,
    d: &GemmaDims,
    h: &Tensor,
    rope: &Rope,
    with_q: bool,
) -> candle_core::Result<Option<(Option<Tensor>, Tensor, Tensor)>> {
    let Some(w) = &layer.qkv else {
        return Ok(None);
    };
    let qd = d.num_heads * d.head_dim;
    let kvd = d.num_kv_heads * d.head_dim;
    let packed = match (&layer.packed, with_q) {
        (Some(a), true) => a.qkv.matmul(h)?.map(|y| (y, qd)),
        (Some(a), false) => a.kv.matmul(h)?.map(|y| (y, 0)),
        (None, _) => None,
    };
    let (y, kcol) = match packed {
        Some(yk) => yk,
        None if with_q => (matmul_2d(h, w)?, qd),
        None => (matmul_2d(h, &w.narrow(1, qd, 2 * kvd)?)?, 0),
    };
    let cs = Some((&rope.cos, &rope.sin));
    let q = if with_q {
        match fastops::split_heads(&y, 0, d.num_heads, d.head_dim, cs)? {
            Some(q) => Some(q),
            None => return Ok(None),
        }
    } else {
        None
    };
    let k = fastops::split_heads(&y, kcol, d.num_kv_heads, d.head_dim, cs)?;
    let v = fastops::split_heads(&y, kcol + kvd, d.num_kv_heads, d.head_dim, None)?;
    Ok(match (k, v) {
        (Some(k), Some(v)) => Some((q, k, v)),
        _ => None,
    })
}

/// The fused path's attention through cuBLAS products and the in-place softmax kernel:
/// `q` [B, nH, L, hd] against the first `bias.dim(3)` keys of `kb`/`vb`, returned as
/// [B, L, nH·hd]. `None` where the softmax kernel does not apply.
fn attention_matmul(
    q: &Tensor,
    kb: &Tensor,
    vb: &Tensor,
    bias: &Tensor,
    scale: f64,
    (b, l, nh, nkv, hd): (usize, usize, usize, usize, usize),
) -> candle_core::Result<Option<Tensor>> {
    // the keys the bias covers: the streams' own (prefix pass) or the cache's first T
    let t = bias.dim(3)?;
    let keys = kb.narrow(2, 0, t)?;
    let values = vb.narrow(2, 0, t)?;
    let g = nh / nkv;
    // [B, nKV, g L, T]: query heads are kv-head-major
    let scores = q.reshape((b, nkv, g * l, hd))?.matmul(&keys.t()?)?;
    let Some(p) = super::kernels::softmax_bias(&scores, Some(bias), l, scale)? else {
        return Ok(None);
    };
    // [B, nKV, g L, hd] -> [B, L, nH hd]
    Ok(Some(
        p.matmul(&values)?
            .reshape((b, nh, l, hd))?
            .transpose(1, 2)?
            .reshape((b, l, nh * hd))?,
    ))
}

/// [`joint_layer`] for one stream with the fused CUDA kernels ([`super::kernels`]): per layer
/// the norm, the Q/K/V product, head split + RoPE + cache write, scores, softmax, values, the O
/// product, gated residual + norm, the gate/up product, gelu·up, the down product and the gated
/// residual — 13 kernels. `None` where they do not apply (CPU, no fused weights, no cache
/// buffers to write K/V into).
fn joint_layer_fused(
    li: usize,
    s: &mut Stream<'_>,
    bias: &Tensor,
    kv: KvMode<'_>,
) -> candle_core::Result<Option<(Tensor, Tensor)>> {
    use super::kernels;
    let layer = &s.expert.layers[li];
    let d = &s.expert.dims;
    let (Some(wqkv), Some(wgu), true) =
        (&layer.qkv, &layer.gate_up, kernels::enabled(s.x.device()))
    else {
        return Ok(None);
    };
    let (kb, vb, offset) = match kv {
        KvMode::Own {
            store: Some((k, v)),
        } => (k, v, 0),
        KvMode::Cached { k, v, offset } => (k, v, offset),
        KvMode::Own { store: None } => return Ok(None),
    };
    let (Some((alpha1, m1, eps1)), Some((alpha2, m2, eps2))) = (
        layer.input_norm.fused_operands(s.cond)?,
        layer.post_norm.fused_operands(s.cond)?,
    ) else {
        return Ok(None);
    };
    let (b, l, _) = s.x.dims3()?;
    let (nh, nkv, hd) = (d.num_heads, d.num_kv_heads, d.head_dim);
    // the previous layer's gated residual, added in this norm's kernel
    let (x0, h) = {
        let (m0, g0) = match &s.pending {
            Some((m, g)) => (Some(m), g.as_ref()),
            None => (None, None),
        };
        match kernels::add_norm(&s.x, m0, g0, alpha1, m1.as_ref(), eps1, m0.is_some())? {
            Some((Some(x0), h)) => (x0, h),
            Some((None, h)) => (s.x.clone(), h),
            None => return Ok(None),
        }
    };
    s.x = x0;
    s.pending = None;
    // [B, L, (nH + 2 nKV) hd]
    let y = matmul_2d(&h, wqkv)?;
    let heads = kernels::Heads {
        q: nh,
        kv: nkv,
        dim: hd,
    };
    let Some(Some(q)) =
        kernels::qkv_rope(&y, heads, Some((&s.rope.cos, &s.rope.sin)), kb, vb, offset)?
    else {
        return Ok(None);
    };
    let scale = (hd as f64).powf(-0.5);
    let Some(o) = attention_matmul(&q, kb, vb, bias, scale, (b, l, nh, nkv, hd))? else {
        return Ok(None);
    };
    let o = matmul_2d(&o, &layer.o.weight().t()?)?;
    let Some((Some(x1), h2)) =
        kernels::add_norm(&s.x, Some(&o), m1.as_ref(), alpha2, m2.as_ref(), eps2, true)?
    else {
        return Ok(None);
    };
    let f = wgu.dim(1)? / 2;
    let Some(a) = kernels::gelu_mul(&matmul_2d(&h2, wgu)?, f)? else {
        return Ok(None);
    };
    let m = matmul_2d(&a, &layer.down.weight().t()?)?;
    // the gated residual goes to the next layer's first norm (the last layer adds it here, so
    // that whoever reads `x` after the loop reads the final hidden states)
    s.x = x1;
    s.pending = Some((m, m2));
    if li + 1 == s.expert.layers.len() {
        s.settle()?;
    }
    Ok(Some((kb.narrow(2, offset, l)?, vb.narrow(2, offset, l)?)))
}

/// Only the post-RoPE K/V of layer `li` for one stream (the last prefix layer: its attention
/// output and MLP feed nothing the sampler uses), written to `kb` / `vb` at offset 0.
pub fn kv_only_layer(
    li: usize,
    s: &Stream<'_>,
    kb: &Tensor,
    vb: &Tensor,
) -> candle_core::Result<()> {
    let layer = &s.expert.layers[li];
    let d = &s.expert.dims;
    let settled;
    let x = match &s.pending {
        None => &s.x,
        Some((m, g)) => {
            settled = match super::kernels::gated_add(&s.x, m, g.as_ref())? {
                Some(x) => x,
                None => candle_core::bail!(
                    "kv_only_layer: a pending residual without the fused kernels"
                ),
            };
            &settled
        }
    };
    let (h, _) = layer.input_norm.forward(x, s.cond, false)?;
    if let (Some(w), true) = (&layer.qkv, super::kernels::enabled(h.device())) {
        let (qd, kvd) = (d.num_heads * d.head_dim, d.num_kv_heads * d.head_dim);
        let y = matmul_2d(&h, &w.narrow(1, qd, 2 * kvd)?)?;
        let heads = super::kernels::Heads {
            q: 0,
            kv: d.num_kv_heads,
            dim: d.head_dim,
        };
        if super::kernels::qkv_rope(&y, heads, Some((&s.rope.cos, &s.rope.sin)), kb, vb, 0)?
            .is_some()
        {
            return Ok(());
        }
    }
    if let Some((_, k, v)) = qkv_fused(layer, d, &h, s.rope, false)? {
        kb.slice_set(&k, 2, 0)?;
        return vb.slice_set(&v, 2, 0);
    }
    let k = heads(&layer.k.forward(&h)?, d.num_kv_heads, d.head_dim)?;
    let k = s.rope.apply(&k, false)?;
    let v = heads(&layer.v.forward(&h)?, d.num_kv_heads, d.head_dim)?;
    kb.slice_set(&k.contiguous()?, 2, 0)?;
    vb.slice_set(&v, 2, 0)
}

/// Runs layer `li` over the streams with one joint masked attention; updates each `x` in place.
/// Returns the streams' own (post-RoPE) keys and values [B, nKV, L, hd] (training runs the
/// prefix once and reuses them for several suffixes).
pub fn joint_layer(
    li: usize,
    streams: &mut [Stream<'_>],
    bias: &Tensor,
    kv: KvMode<'_>,
    diff: bool,
) -> candle_core::Result<(Tensor, Tensor)> {
    if let ([s], false) = (&mut *streams, diff) {
        if let Some(kv) = joint_layer_fused(li, s, bias, kv)? {
            return Ok(kv);
        }
    }
    for s in streams.iter_mut() {
        s.settle()?;
    }
    let mut qs = Vec::with_capacity(streams.len());
    let mut ks = Vec::with_capacity(streams.len());
    let mut vs = Vec::with_capacity(streams.len());
    let mut gates = Vec::with_capacity(streams.len());
    // all streams share the head dimension (one joint attention)
    let hd = streams.first().map_or(1, |s| s.expert.dims.head_dim);
    let scale = (hd as f64).powf(-0.5);
    for s in streams.iter() {
        let layer = &s.expert.layers[li];
        let d = &s.expert.dims;
        let (h, gate) = layer.input_norm.forward(&s.x, s.cond, diff)?;
        gates.push(gate);
        if !diff {
            if let Some((Some(q), k, v)) = qkv_fused(layer, d, &h, s.rope, true)? {
                qs.push(q);
                ks.push(k);
                vs.push(v);
                continue;
            }
        }
        // [B, nH, L, hd], [B, nKV, L, hd]
        let q = heads(&layer.q.forward(&h)?, d.num_heads, d.head_dim)?;
        let q = s.rope.apply(&q, diff)?;
        let k = heads(&layer.k.forward(&h)?, d.num_kv_heads, d.head_dim)?;
        let k = s.rope.apply(&k, diff)?;
        let v = heads(&layer.v.forward(&h)?, d.num_kv_heads, d.head_dim)?;
        qs.push(q);
        ks.push(k);
        vs.push(v);
    }
    let cat = |xs: &[Tensor]| -> candle_core::Result<Tensor> {
        if xs.len() == 1 {
            Ok(xs[0].clone())
        } else {
            Tensor::cat(xs, 2)
        }
    };
    let q = cat(&qs)?;
    let k = cat(&ks)?;
    let v = cat(&vs)?;
    let out = match kv {
        KvMode::Own { store } => {
            if let Some((kb, vb)) = store {
                kb.slice_set(&k.contiguous()?, 2, 0)?;
                vb.slice_set(&v.contiguous()?, 2, 0)?;
            }
            attention(&q, &k, &v, bias, scale, diff)?
        }
        KvMode::Cached {
            k: kb,
            v: vb,
            offset,
        } => {
            if diff {
                let kk = Tensor::cat(&[&kb.narrow(2, 0, offset)?, &k], 2)?;
                let vv = Tensor::cat(&[&vb.narrow(2, 0, offset)?, &v], 2)?;
                // Keys past the streams' tokens are masked anyway; keep T equal to the bias.
                let t = bias.dim(3)?;
                let l = kk.dim(2)?;
                let (kk, vv) = if l < t {
                    (
                        Tensor::cat(&[&kk, &kb.narrow(2, l, t - l)?], 2)?,
                        Tensor::cat(&[&vv, &vb.narrow(2, l, t - l)?], 2)?,
                    )
                } else {
                    (kk, vv)
                };
                attention(&q, &kk, &vv, bias, scale, diff)?
            } else {
                kb.slice_set(&k.contiguous()?, 2, offset)?;
                vb.slice_set(&v.contiguous()?, 2, offset)?;
                // only the keys the bias covers (the cache buffer may be longer)
                let t = bias.dim(3)?;
                attention(
                    &q,
                    &kb.narrow(2, 0, t)?,
                    &vb.narrow(2, 0, t)?,
                    bias,
                    scale,
                    diff,
                )?
            }
        }
    };
    // split the attention output back into the streams
    let mut start = 0;
    for (s, gate) in streams.iter_mut().zip(gates.iter()) {
        let layer = &s.expert.layers[li];
        let l = s.x.dim(1)?;
        let o = if start == 0 && l == out.dim(1)? {
            out.clone()
        } else {
            out.narrow(1, start, l)?
        };
        start += l;
        let o = match packed_mm(&o, layer.packed.as_deref().map(|a| &a.o), diff)? {
            Some(o) => o,
            None => layer.o.forward(&o)?,
        };
        let x1 = gated_residual(&s.x, &o, gate.as_ref(), diff)?;
        let (h, gate2) = layer.post_norm.forward(&x1, s.cond, diff)?;
        let m = mlp(layer, &h, diff)?;
        s.x = gated_residual(&x1, &m, gate2.as_ref(), diff)?;
    }
    Ok((k, v))
}
