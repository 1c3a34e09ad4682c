//! The per-token ops around Gemma's attention: RMSNorm `(1 + w)` and π0.5's adaRMSNorm
//! (scale, shift, gate), the gated residual, and RoPE (rotate-half) tables.

use candle_core::{DType, Device, Module, Tensor, D};
use candle_nn::VarBuilder;

use super::*;

/// Gemma RMSNorm, plain (`1 + w`) or adaptive (π0.5 action expert).
#[derive(Debug, Clone)]
pub enum Norm {
    /// `x * rsqrt(mean(x^2) + eps) * (1 + w)`.
    Rms {
        /// `w` [W] (a trainable variable in a training model).
        weight: Tensor,
        /// `1 + w` [W], precomputed for inference models only: a training model derives it from
        /// `weight` at every forward, or the optimiser's updates of `weight` would never reach the
        /// forward pass (and the saved checkpoint would compute another function than the one
        /// trained).
        alpha: Option<Tensor>,
        /// eps.
        eps: f64,
    },
    /// `(scale, shift, gate) = chunk(dense(cond), 3)`; `y = norm(x) * (1 + scale) + shift`.
    Ada {
        /// Linear(W_cond -> 3 W, bias).
        dense: Linear,
        /// Ones [W] (alpha of the fused kernel).
        ones: Tensor,
        /// eps.
        eps: f64,
        /// `dense(cond)` [B, 3W] f32 by condition tensor (inference models): the condition
        /// depends on the time only, the sampler's times repeat, so a denoising step runs no
        /// modulation product ([`Norm::modulation`]).
        mods: ModulationCache,
    },
}

use crate::ops::FusedNorm;

/// [`Norm::Ada`]'s modulations by condition tensor.
pub type ModulationCache =
    std::sync::Arc<std::sync::Mutex<std::collections::HashMap<candle_core::TensorId, Tensor>>>;

/// `x * rsqrt(mean(x^2) + eps)` without weight; `x` [.., W].
fn rms_plain(x: &Tensor, ones: &Tensor, eps: f64, diff: bool) -> candle_core::Result<Tensor> {
    if diff {
        let ms = x.sqr()?.mean_keepdim(D::Minus1)?;
        x.broadcast_div(&(ms + eps)?.sqrt()?)
    } else {
        candle_nn::ops::rms_norm(&x.contiguous()?, ones, eps as f32)
    }
}

impl Norm {
    /// Loads `input_layernorm` & co. Plain norms read `weight` [W]; adaptive ones read
    /// `dense.{weight,bias}` [3W, W]. Their weights stay f32 whatever the model's dtype (as
    /// openpi keeps them), and they compute in f32.
    pub fn new(width: usize, ada: bool, eps: f64, vb: VarBuilder) -> candle_core::Result<Self> {
        let vb = vb.set_dtype(DType::F32);
        if ada {
            let dense = candle_nn::linear(width, 3 * width, vb.pp("dense"))?;
            let ones = Tensor::ones(width, DType::F32, vb.device())?;
            Ok(Norm::Ada {
                dense,
                ones,
                eps,
                mods: Default::default(),
            })
        } else {
            let w = vb.get_with_hints(width, "weight", candle_nn::Init::Const(0.0))?;
            let alpha = if w.is_variable() {
                None
            } else {
                Some((&w + 1.0)?)
            };
            Ok(Norm::Rms {
                weight: w,
                alpha,
                eps,
            })
        }
    }

    /// AdaRMSNorm's `dense(cond)` [B, 3W] f32 (scale, shift, gate), kept per condition tensor
    /// when the dense layer is not being trained (the time features that make `cond` are kept
    /// per model and time, so the same tensor comes back at every step at that time).
    pub fn modulation(&self, cond: &Tensor) -> candle_core::Result<Option<Tensor>> {
        let Norm::Ada { dense, mods, .. } = self else {
            return Ok(None);
        };
        let cacheable = !dense.weight().is_variable();
        if cacheable {
            if let Some(m) = mods.lock().ok().and_then(|m| m.get(&cond.id()).cloned()) {
                return Ok(Some(m));
            }
        }
        let m = dense.forward(&cond.to_dtype(DType::F32)?)?.contiguous()?;
        if cacheable {
            if let Ok(mut c) = mods.lock() {
                // the sampler's handful of times (and committed prefix lengths) in practice;
                // bounded whatever a caller does
                if c.len() >= 512 {
                    c.clear();
                }
                c.insert(cond.id(), m.clone());
            }
        }
        Ok(Some(m))
    }

    /// The fused kernel's operands: (`1 + w`, modulation); None where the kernel does not
    /// apply (a training model's plain norm derives `1 + w` at every forward).
    fn fused_operands_of(
        &self,
        cond: Option<&Tensor>,
    ) -> candle_core::Result<Option<FusedNorm<'_>>> {
        match self {
            Norm::Rms {
                alpha: Some(a),
                eps,
                ..
            } => Ok(Some((Some(a), None, *eps))),
            Norm::Rms { alpha: None, .. } => Ok(None),
            Norm::Ada { eps, .. } => {
                let cond = cond.ok_or_else(|| {
                    candle_core::Error::Msg("adaRMSNorm needs a condition".into())
                })?;
                // the fused kernel takes one modulation per batch row, not per token
                // (training-time RTC's committed prefix): those take the composed ops
                if cond.rank() != 2 {
                    return Ok(None);
                }
                Ok(Some((None, self.modulation(cond)?, *eps)))
            }
        }
    }

    /// `x` [B, L, W], `cond` [B, Wc] or per token [B, L, Wc] f32 (adaptive only). Returns the
    /// normed `x` and the gate [B, 1, W] or [B, L, W] (adaptive only), both in `x`'s dtype; the
    /// statistics, the `(1 + w)` scaling and the adaptive modulation are computed in f32
    /// (openpi's `GemmaRMSNorm`). The inference path (`diff` false) goes through
    /// [`ops::add_norm`](crate::ops::add_norm), which picks the device's kernel.
    pub fn forward(
        &self,
        x: &Tensor,
        cond: Option<&Tensor>,
        diff: bool,
    ) -> candle_core::Result<(Tensor, Option<Tensor>)> {
        if diff {
            return self.composed_with(x, cond, true);
        }
        let (_, h, gate) = crate::ops::add_norm(x, None, self, cond)?;
        Ok((h, gate.tensor(x.dim(D::Minus1)?, x.dtype())?))
    }

    /// [`Self::forward`] in candle's ops (`diff`: with a backward).
    fn composed_with(
        &self,
        x: &Tensor,
        cond: Option<&Tensor>,
        diff: bool,
    ) -> candle_core::Result<(Tensor, Option<Tensor>)> {
        let dtype = x.dtype();
        let x = &x.to_dtype(DType::F32)?;
        match self {
            Norm::Rms { weight, alpha, eps } => {
                let derived;
                let alpha = match alpha {
                    Some(a) => a,
                    None => {
                        derived = (weight + 1.0)?;
                        &derived
                    }
                };
                let y = if diff {
                    let ms = x.sqr()?.mean_keepdim(D::Minus1)?;
                    let y = x.broadcast_div(&(ms + *eps)?.sqrt()?)?;
                    y.broadcast_mul(alpha)?
                } else {
                    candle_nn::ops::rms_norm(&x.contiguous()?, alpha, *eps as f32)?
                };
                Ok((y.to_dtype(dtype)?, None))
            }
            Norm::Ada {
                dense, ones, eps, ..
            } => {
                let cond = cond.ok_or_else(|| {
                    candle_core::Error::Msg("adaRMSNorm needs a condition".into())
                })?;
                // [B, 3W] -> [B, 1, 3W] (one per row), or per token [B, L, 3W] as it is
                let m = if diff {
                    dense.forward(&cond.to_dtype(DType::F32)?)?
                } else {
                    self.modulation(cond)?
                        .ok_or_else(|| candle_core::Error::Msg("no modulation".into()))?
                };
                let m = if m.rank() == 2 { m.unsqueeze(1)? } else { m };
                let w = m.dim(D::Minus1)? / 3;
                let scale = m.narrow(D::Minus1, 0, w)?;
                let shift = m.narrow(D::Minus1, w, w)?;
                let gate = m.narrow(D::Minus1, 2 * w, w)?;
                let y = rms_plain(x, ones, *eps, diff)?;
                let y = y.broadcast_mul(&(scale + 1.0)?)?.broadcast_add(&shift)?;
                Ok((y.to_dtype(dtype)?, Some(gate.to_dtype(dtype)?)))
            }
        }
    }
}

impl crate::ops::NormOp for Norm {
    fn fused_operands(&self, cond: Option<&Tensor>) -> candle_core::Result<Option<FusedNorm<'_>>> {
        self.fused_operands_of(cond)
    }

    fn composed(
        &self,
        x: &Tensor,
        cond: Option<&Tensor>,
    ) -> candle_core::Result<(Tensor, Option<Tensor>)> {
        self.composed_with(x, cond, false)
    }
}

/// `x + y * gate` (gate absent: `x + y`); the inference path through
/// [`ops::gated_add`](crate::ops::gated_add).
pub fn gated_residual(
    x: &Tensor,
    y: &Tensor,
    gate: Option<&Tensor>,
    diff: bool,
) -> candle_core::Result<Tensor> {
    match (diff, gate) {
        (false, g) => crate::ops::gated_add(x, y, &crate::ops::Gate::from_tensor(g.cloned())),
        (true, None) => x.broadcast_add(y),
        (true, Some(g)) => x + y.broadcast_mul(g)?,
    }
}

/// RoPE inverse frequencies `theta^(-2i / hd)`, i < hd/2 (HF, f32).
fn inv_freq(head_dim: usize, theta: f64) -> Vec<f32> {
    (0..head_dim / 2)
        .map(|i| 1.0f32 / (theta as f32).powf((2 * i) as f32 / head_dim as f32))
        .collect()
}

/// RoPE tables for one stream: `cos`, `sin` [B, L, head_dim/2] (computed in f32 from positions,
/// stored in the model's dtype).
#[derive(Debug, Clone)]
pub struct Rope {
    /// [B, L, hd/2].
    pub cos: Tensor,
    /// [B, L, hd/2].
    pub sin: Tensor,
}

impl Rope {
    /// (cos, sin), as the kernels take them ([`crate::ops::qkv_rope`]).
    pub fn tables(&self) -> crate::ops::RopeTables<'_> {
        (&self.cos, &self.sin)
    }

    /// Tables from positions `pos[b][l]` (HF: f32 `inv_freq * pos`).
    pub fn new(
        pos: &[Vec<i64>],
        head_dim: usize,
        theta: f64,
        dev: &Device,
        dtype: DType,
    ) -> candle_core::Result<Self> {
        let half = head_dim / 2;
        let inv = inv_freq(head_dim, theta);
        let b = pos.len();
        let l = pos.first().map(|p| p.len()).unwrap_or(0);
        let mut c = Vec::with_capacity(b * l * half);
        let mut s = Vec::with_capacity(b * l * half);
        for row in pos {
            for &p in row {
                for &f in &inv {
                    let a = p as f32 * f;
                    c.push(a.cos());
                    s.push(a.sin());
                }
            }
        }
        Ok(Rope {
            cos: Tensor::from_vec(c, (b, l, half), dev)?.to_dtype(dtype)?,
            sin: Tensor::from_vec(s, (b, l, half), dev)?.to_dtype(dtype)?,
        })
    }

    /// Tables from positions `pos` [B, L] f32 on its device (f32 `inv_freq * pos`, as
    /// [`Rope::new`] computes on the host), stored in `dtype`.
    pub fn from_positions(
        pos: &Tensor,
        head_dim: usize,
        theta: f64,
        dtype: DType,
    ) -> candle_core::Result<Self> {
        let half = head_dim / 2;
        let inv = inv_freq(head_dim, theta);
        let inv = Tensor::from_vec(inv, (1, 1, half), pos.device())?;
        // [B, L, 1] * [1, 1, hd/2]
        let a = pos
            .to_dtype(DType::F32)?
            .unsqueeze(2)?
            .broadcast_mul(&inv)?;
        Ok(Rope {
            cos: a.cos()?.to_dtype(dtype)?,
            sin: a.sin()?.to_dtype(dtype)?,
        })
    }

    /// Applies the rotation to `x` [B, H, L, hd] (contiguous in the fast path).
    pub fn apply(&self, x: &Tensor, diff: bool) -> candle_core::Result<Tensor> {
        if diff {
            // rotate_half: cat(-x2, x1); cos/sin duplicated to hd: [B, 1, L, hd]
            let hd = x.dim(D::Minus1)?;
            let x1 = x.narrow(D::Minus1, 0, hd / 2)?;
            let x2 = x.narrow(D::Minus1, hd / 2, hd / 2)?;
            let rot = Tensor::cat(&[&x2.neg()?, &x1], D::Minus1)?;
            let cos = Tensor::cat(&[&self.cos, &self.cos], D::Minus1)?.unsqueeze(1)?;
            let sin = Tensor::cat(&[&self.sin, &self.sin], D::Minus1)?.unsqueeze(1)?;
            x.broadcast_mul(&cos)? + rot.broadcast_mul(&sin)?
        } else {
            candle_nn::rotary_emb::rope(&x.contiguous()?, &self.cos, &self.sin)
        }
    }
}
