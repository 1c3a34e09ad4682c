//! The Gemma dual-expert transformer of π0 / π0.5.
//!
//! Two experts (the PaliGemma language model for prefix tokens, the action expert for suffix
//! tokens) each have their own norms, Q/K/V/O projections and MLP; at every layer one masked
//! attention runs over the concatenation of the streams that are present. GQA with any number of
//! kv heads (kv-head-major), RoPE rotate-half, Gemma RMSNorm `(1 + w)`, and for π0.5's action
//! expert adaRMSNorm `norm(x) * (1 + scale) + shift` with gated residuals.
//!
//! Every op has an inference path (no backward: [`ops`], which picks the device's kernel and
//! falls back to candle's composition) and a differentiable path built from differentiable
//! compositions, selected per call with `diff`. One stream on the inference path (the prefix
//! pass, a denoising step) runs [`stream_layer`] on every device.

use candle_core::{Module, Tensor, D};
use candle_nn::{Linear, VarBuilder};

use super::config::GemmaDims;
use super::ops::{self, Gate};
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

    /// Whether the inference path's fused layer runs this layer (a trainable model's layers
    /// have no fused weights and take the general path).
    pub fn is_fused(&self) -> bool {
        self.qkv.is_some() && self.gate_up.is_some()
    }

    /// The arithmetic of this layer's attention products on the CPU: bf16 where its weights are
    /// packed in bf16 (a native bf16 kernel then runs them), else f32.
    pub fn attention_arith(&self) -> Precision {
        self.packed
            .as_ref()
            .map_or(Precision::F32, |a| a.o.precision())
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
    /// A gated residual not yet added ([`stream_layer`]): the hidden states are `x + m · gate`.
    /// The next layer adds it with its first norm ([`ops::add_norm`], one kernel on a GPU);
    /// [`Stream::settle`] adds it for anything else. Construct with `None`.
    pub pending: Option<(Tensor, Gate)>,
}

impl Stream<'_> {
    /// Adds a pending gated residual into `x`.
    pub fn settle(&mut self) -> candle_core::Result<()> {
        if let Some((m, gate)) = self.pending.take() {
            self.x = ops::gated_add(&self.x, &m, &gate)?;
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
        /// The cache's keys/values before `offset`, packed once for the CPU attention kernel
        /// ([`ops::PackedKv`]; None: the kernel packs them itself).
        packed: Option<&'a ops::PackedKv>,
    },
}

/// Attention `softmax(scale q k^T + bias) v` with GQA.
/// `q` [B, nH, L, hd], `k`, `v` [B, nKV, T, hd], `bias` [B, 1, L or 1, T].
/// Returns [B, L, nH*hd] ([`ops::attention`]; `diff`: candle's ops with a backward).
pub fn attention(
    q: &Tensor,
    k: &Tensor,
    v: &Tensor,
    bias: &Tensor,
    scale: f64,
    diff: bool,
) -> candle_core::Result<Tensor> {
    if diff {
        ops::attention_composed(q, k, v, Some(bias), scale, true)
    } else {
        ops::attention(q, k, v, Some(bias), scale, Precision::F32)
    }
}

/// `down(gelu_tanh(gate(x)) * up(x))`.
fn mlp(layer: &ExpertLayer, x: &Tensor, diff: bool) -> candle_core::Result<Tensor> {
    if diff {
        let g = layer.gate.forward(x)?;
        return layer.down.forward(&(g.gelu()? * layer.up.forward(x)?)?);
    }
    let a = layer.packed.as_deref();
    let h = match &layer.gate_up {
        Some(gu) => ops::gelu_mul(&ops::matmul(x, gu, a.map(|a| &a.gate_up))?, gu.dim(1)? / 2)?,
        None => ops::gelu_mul_pair(&layer.gate.forward(x)?, &layer.up.forward(x)?)?,
    };
    ops::matmul(&h, &layer.down.weight().t()?, a.map(|a| &a.down))
}

/// `[B, L, n*hd]` -> `[B, n, L, hd]`.
fn heads(x: &Tensor, n: usize, hd: usize) -> candle_core::Result<Tensor> {
    let (b, l, _) = x.dims3()?;
    x.reshape((b, l, n, hd))?.transpose(1, 2)?.contiguous()
}

/// Head layout of `d`'s fused Q/K/V product (`with_q` false: only its K/V columns).
fn heads_of(d: &GemmaDims, with_q: bool) -> ops::Heads {
    ops::Heads {
        q: if with_q { d.num_heads } else { 0 },
        kv: d.num_kv_heads,
        dim: d.head_dim,
    }
}

/// Layer `li` for one stream on the inference path, on any device: the norm (with the previous
/// layer's gated residual), the Q/K/V product, head split + RoPE + the K/V write into the cache,
/// attention, the O product, gated residual + norm, the gate/up product, gelu·up and the down
/// product, each one [`ops`] call (13 kernels per layer on a GPU). The gated residual at the end
/// is left in `s.pending` for the next layer's norm (the last layer adds it). Returns the
/// stream's own (post-RoPE) K/V [B, nKV, L, hd]; `None` for a layer without fused weights (a
/// training model), which takes [`joint_layer`]'s general path.
fn stream_layer(
    li: usize,
    s: &mut Stream<'_>,
    bias: &Tensor,
    kv: KvMode<'_>,
) -> candle_core::Result<Option<(Tensor, Tensor)>> {
    let layer = &s.expert.layers[li];
    let d = &s.expert.dims;
    let (Some(wqkv), Some(wgu)) = (&layer.qkv, &layer.gate_up) else {
        return Ok(None);
    };
    let a = layer.packed.as_deref();
    let pending = s.pending.take();
    let residual = pending.as_ref().map(|(m, g)| (m, g));
    let (x0, h, gate1) = ops::add_norm(&s.x, residual, &layer.input_norm, s.cond)?;
    // [B, L, (nH + 2 nKV) hd]
    let y = ops::matmul(&h, wqkv, a.map(|a| &a.qkv))?;
    let cache = match kv {
        KvMode::Own { store } => store.map(|(k, v)| (k, v, 0)),
        KvMode::Cached { k, v, offset, .. } => Some((k, v, offset)),
    };
    let (q, k, v) = ops::qkv_rope(&y, heads_of(d, true), s.rope.tables(), cache)?;
    let q = q.ok_or_else(|| candle_core::Error::Msg("stream_layer: no query heads".into()))?;
    // the keys the bias covers: the stream's own (prefix pass) or the cache's first T
    let (keys, values) = match kv {
        KvMode::Cached { k: kb, v: vb, .. } => {
            let t = bias.dim(3)?;
            (kb.narrow(2, 0, t)?, vb.narrow(2, 0, t)?)
        }
        KvMode::Own { .. } => (k.clone(), v.clone()),
    };
    let scale = (d.head_dim as f64).powf(-0.5);
    // the products in bf16 where the layer's weights are (a native bf16 CPU kernel only)
    let arith = layer.attention_arith();
    let prefix = match kv {
        KvMode::Cached { packed, .. } => packed,
        KvMode::Own { .. } => None,
    };
    let o = ops::attention_cached(&q, &keys, &values, Some(bias), scale, arith, prefix)?;
    let o = ops::matmul(&o, &layer.o.weight().t()?, a.map(|a| &a.o))?;
    let (x1, h2, gate2) = ops::add_norm(&x0, Some((&o, &gate1)), &layer.post_norm, s.cond)?;
    let act = ops::gelu_mul(
        &ops::matmul(&h2, wgu, a.map(|a| &a.gate_up))?,
        wgu.dim(1)? / 2,
    )?;
    let m = ops::matmul(&act, &layer.down.weight().t()?, a.map(|a| &a.down))?;
    s.x = x1;
    s.pending = Some((m, gate2));
    if li + 1 == s.expert.layers.len() {
        // whoever reads `x` after the loop reads the final hidden states
        s.settle()?;
    }
    Ok(Some((k, v)))
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
    let residual = s.pending.as_ref().map(|(m, g)| (m, g));
    let (_, h, _) = ops::add_norm(&s.x, residual, &layer.input_norm, s.cond)?;
    let y = match &layer.qkv {
        Some(w) => {
            let (qd, kvd) = (d.num_heads * d.head_dim, d.num_kv_heads * d.head_dim);
            let a = layer.packed.as_deref();
            ops::matmul(&h, &w.narrow(1, qd, 2 * kvd)?, a.map(|a| &a.kv))?
        }
        None => Tensor::cat(&[layer.k.forward(&h)?, layer.v.forward(&h)?], D::Minus1)?,
    };
    ops::qkv_rope(&y, heads_of(d, false), s.rope.tables(), Some((kb, vb, 0)))?;
    Ok(())
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
        if let Some(kv) = stream_layer(li, s, bias, kv)? {
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
        if let (false, Some(w)) = (diff, &layer.qkv) {
            let y = ops::matmul(&h, w, layer.packed.as_deref().map(|a| &a.qkv))?;
            if let (Some(q), k, v) = ops::qkv_rope(&y, heads_of(d, true), s.rope.tables(), None)? {
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
            ..
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
        let o = if diff {
            layer.o.forward(&o)?
        } else {
            ops::matmul(
                &o,
                &layer.o.weight().t()?,
                layer.packed.as_deref().map(|a| &a.o),
            )?
        };
        let x1 = gated_residual(&s.x, &o, gate.as_ref(), diff)?;
        let (h, gate2) = layer.post_norm.forward(&x1, s.cond, diff)?;
        let m = mlp(layer, &h, diff)?;
        s.x = gated_residual(&x1, &m, gate2.as_ref(), diff)?;
    }
    Ok((k, v))
}
