//! The one seam between the model's layers and the kernels.
//!
//! Each function here is one op kind of the inference path (no backward). It runs the fast
//! kernel for the device its tensors live on — chunkrt's CPU kernels ([`super::fastops`],
//! [`super::packed`], which picks AMX / AVX-512 / AVX2 itself) or its CUDA kernels
//! ([`super::kernels`]) — and where none applies (another device or dtype, a layout the kernel
//! does not take, the kernels switched off) it falls back to candle's composition, here and
//! nowhere else. The layers (SigLIP, Gemma) call these and never a kernel module directly; the
//! differentiable path (training) calls candle's ops, which have a backward.
//!
//! | op | CPU | CUDA | fallback |
//! |---|---|---|---|
//! | [`matmul`] | packed weights | — | one 2-D matmul |
//! | [`dense`] | packed weights, bias fused; [`gelu`], [`add`] | `bias_act` after the product | matmul, bias, gelu, add |
//! | [`add_norm`] | — | `add_norm` | [`gated_add`], then the norm's composition |
//! | [`gated_add`] | `add` (no gate) | `gated_add` | `x + y · gate` |
//! | [`qkv_rope`] | `split_heads` (+ RoPE) | `qkv_rope` (+ cache write) | narrow, heads, RoPE |
//! | [`split_qkv`] | `split_heads` | `split_qkv` | reshape, transpose |
//! | [`attention`], [`attention_cached`] | `attention` (+ a prefix packed once) | products + `softmax_bias` | [`attention_composed`] |
//! | [`gelu_mul`] | `gelu_mul_fused` | `gelu_mul` | narrow, gelu, mul |
//! | [`gelu`], [`add`] | `gelu`, `add` | — | candle |
//!
//! Depends on no layer module (the layers depend on it): a norm comes in as a [`NormOp`], RoPE
//! as its (cos, sin) tables.

use candle_core::{DType, Result, Tensor, D};

use super::fastops;
pub use super::fastops::PackedKv;
use super::kernels;
pub use super::kernels::Heads;
use super::packed::{PackedRhs, Precision};

pub mod profile;
use profile::{span, Kind};

/// RoPE's tables (cos, sin) [B, L, hd/2] (rotate-half).
pub type RopeTables<'a> = (&'a Tensor, &'a Tensor);

/// A norm as [`add_norm`] takes it (Gemma's RMSNorm `(1 + w)` and π0.5's AdaRMSNorm,
/// `gemma::Norm`).
pub trait NormOp {
    /// The CUDA kernel's operands for condition `cond`: `1 + w` [W] f32 (None: 1), the adaptive
    /// modulation [B, 3W] f32, eps; `None` where the kernel does not apply.
    fn fused_operands(&self, cond: Option<&Tensor>) -> Result<Option<FusedNorm<'_>>>;
    /// The norm in candle's ops: the normed `x` and the gate for the residual that follows
    /// (adaptive norms), both in `x`'s dtype.
    fn composed(&self, x: &Tensor, cond: Option<&Tensor>) -> Result<(Tensor, Option<Tensor>)>;
}

/// A norm as the CUDA kernel takes it: `1 + w`, the modulation, eps.
pub type FusedNorm<'a> = (Option<&'a Tensor>, Option<Tensor>, f64);

/// The gate of a gated residual `x + y · gate`.
#[derive(Debug, Clone)]
pub enum Gate {
    /// No gate: `x + y`.
    One,
    /// AdaRMSNorm's modulation [B, 3W] f32 (scale, shift, gate): the gate is its last third,
    /// one per batch row (the form the CUDA kernels take).
    Modulation(Tensor),
    /// A gate broadcastable over [B, L, W] ([B, 1, W] or [B, L, W]) in `x`'s dtype.
    Tensor(Tensor),
}

impl Gate {
    /// `Gate::Tensor` of a norm's gate, `Gate::One` without one.
    pub fn from_tensor(g: Option<Tensor>) -> Self {
        g.map_or(Gate::One, Gate::Tensor)
    }

    /// The gate as a tensor over `w` columns in `dtype` (None: no gate).
    pub fn tensor(&self, w: usize, dtype: DType) -> Result<Option<Tensor>> {
        match self {
            Gate::One => Ok(None),
            Gate::Modulation(m) => Ok(Some(m.narrow(1, 2 * w, w)?.unsqueeze(1)?.to_dtype(dtype)?)),
            Gate::Tensor(g) => Ok(Some(g.clone())),
        }
    }

    /// The modulation for a CUDA kernel: `Some(None)` no gate, `Some(Some(m))` the modulation,
    /// `None` a gate tensor (the kernels do not take one).
    fn modulation(&self) -> Option<Option<&Tensor>> {
        match self {
            Gate::One => Some(None),
            Gate::Modulation(m) => Some(Some(m)),
            Gate::Tensor(_) => None,
        }
    }
}

/// `x` [.., K] times `w` [K, N] (any strides) as one 2-D matmul: [.., N].
pub fn matmul_2d(x: &Tensor, w: &Tensor) -> Result<Tensor> {
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

/// `x` [.., K] · `w` [K, N]: the packed product where `packed` (the same weight packed for
/// this CPU) applies, else [`matmul_2d`].
pub fn matmul(x: &Tensor, w: &Tensor, packed: Option<&PackedRhs>) -> Result<Tensor> {
    let _span = span(Kind::Products);
    if let Some(p) = packed {
        if let Some(y) = p.matmul(x)? {
            return Ok(y);
        }
    }
    matmul_2d(x, w)
}

/// `x @ w^T + b` over the last dim, any leading dims (one 2-D matmul); `w` [O, K], `b` [O].
pub fn linear(x: &Tensor, w: &Tensor, b: &Tensor) -> Result<Tensor> {
    matmul_2d(x, &w.t()?)?.broadcast_add(b)
}

/// A dense layer with bias: `act(x · wᵀ + b) + residual`, `w` [O, K], `b` [O], `act` gelu-tanh
/// when `gelu` (else identity), `residual` shaped as the output (None: none). `packed`: `w`
/// packed with `b` fused ([`PackedRhs::with_bias`]).
pub fn dense(
    x: &Tensor,
    w: &Tensor,
    b: &Tensor,
    packed: Option<&PackedRhs>,
    gelu_act: bool,
    residual: Option<&Tensor>,
) -> Result<Tensor> {
    let _span = span(Kind::Products);
    let y = match packed.map(|p| p.matmul(x)).transpose()?.flatten() {
        Some(y) => y,
        None => {
            if kernels::enabled(x.device()) {
                let y = matmul_2d(x, &w.t()?)?;
                if let Some(y) = kernels::bias_act(&y, Some(b), gelu_act, residual)? {
                    return Ok(y);
                }
            }
            linear(x, w, b)?
        }
    };
    let y = if gelu_act { gelu(&y)? } else { y };
    match residual {
        Some(r) => add(r, &y),
        None => Ok(y),
    }
}

/// gelu-tanh.
pub fn gelu(x: &Tensor) -> Result<Tensor> {
    let _span = span(Kind::Activations);
    match fastops::gelu(x)? {
        Some(y) => Ok(y),
        None => x.gelu(),
    }
}

/// `a + b`, `b` broadcast over `a`'s leading dimensions.
pub fn add(a: &Tensor, b: &Tensor) -> Result<Tensor> {
    let _span = span(Kind::Residuals);
    fastops::add_or_broadcast(a, b, false)
}

/// `x + y · gate` over [B, L, W].
pub fn gated_add(x: &Tensor, y: &Tensor, gate: &Gate) -> Result<Tensor> {
    let _span = span(Kind::Residuals);
    if let (3, Some(gmod)) = (x.rank(), gate.modulation()) {
        if let Some(x1) = kernels::gated_add(x, y, gmod)? {
            return Ok(x1);
        }
    }
    match gate.tensor(x.dim(D::Minus1)?, x.dtype())? {
        None => add(x, y),
        Some(g) => x + y.broadcast_mul(&g)?,
    }
}

/// A layer's gated residual and the norm after it: `x1 = x + y · gate` (`residual` None:
/// `x1 = x`), `h = norm(x1)` with `cond` for an adaptive norm. Returns `x1`, `h` (both in `x`'s
/// dtype) and the norm's gate for the residual that follows (adaptive norms; `Gate::One` else).
pub fn add_norm(
    x: &Tensor,
    residual: Option<(&Tensor, &Gate)>,
    norm: &impl NormOp,
    cond: Option<&Tensor>,
) -> Result<(Tensor, Tensor, Gate)> {
    let _span = span(Kind::Norms);
    if x.rank() == 3 && kernels::enabled(x.device()) {
        let gmod = match residual {
            None => Some(None),
            Some((_, g)) => g.modulation(),
        };
        if let (Some(gmod), Some((alpha, m, eps))) = (gmod, norm.fused_operands(cond)?) {
            let y = residual.map(|(y, _)| y);
            if let Some((x1, h)) =
                kernels::add_norm(x, y, gmod, alpha, m.as_ref(), eps, y.is_some())?
            {
                let x1 = x1.unwrap_or_else(|| x.clone());
                return Ok((x1, h, m.map_or(Gate::One, Gate::Modulation)));
            }
        }
    }
    let x1 = match residual {
        Some((y, g)) => gated_add(x, y, g)?,
        None => x.clone(),
    };
    let (h, gate) = norm.composed(&x1, cond)?;
    Ok((x1, h, Gate::from_tensor(gate)))
}

/// Splits `y` [B, L, (q + 2 kv) · hd] (Q columns first unless `heads.q == 0`, then K, V) into
/// heads, Q and K rotated with `rope`: Q [B, q, L, hd] (None when `heads.q == 0`), K and V
/// [B, kv, L, hd]. With `cache` = (K buffer, V buffer [B, kv, T, hd], offset) K and V are also
/// written there at sequence `offset`.
pub fn qkv_rope(
    y: &Tensor,
    heads: Heads,
    rope: RopeTables<'_>,
    cache: Option<(&Tensor, &Tensor, usize)>,
) -> Result<(Option<Tensor>, Tensor, Tensor)> {
    let _span = span(Kind::Heads);
    let l = y.dim(1)?;
    let cs = Some(rope);
    if let Some((kb, vb, offset)) = cache {
        if let Some(q) = kernels::qkv_rope(y, heads, cs, kb, vb, offset)? {
            return Ok((q, kb.narrow(2, offset, l)?, vb.narrow(2, offset, l)?));
        }
    }
    let (qd, kvd, hd) = (heads.q * heads.dim, heads.kv * heads.dim, heads.dim);
    let fast = || -> Result<Option<(Option<Tensor>, Tensor, Tensor)>> {
        if !y.device().is_cpu() {
            return Ok(None);
        }
        let q = match heads.q {
            0 => None,
            n => match fastops::split_heads(y, 0, n, hd, cs)? {
                Some(q) => Some(q),
                None => return Ok(None),
            },
        };
        let k = fastops::split_heads(y, qd, heads.kv, hd, cs)?;
        let v = fastops::split_heads(y, qd + kvd, heads.kv, hd, None)?;
        Ok(k.zip(v).map(|(k, v)| (q, k, v)))
    };
    let (q, k, v) = match fast()? {
        Some(qkv) => qkv,
        None => qkv_rope_composed(y, heads, rope)?,
    };
    if let Some((kb, vb, offset)) = cache {
        kb.slice_set(&k.contiguous()?, 2, offset)?;
        vb.slice_set(&v.contiguous()?, 2, offset)?;
    }
    Ok((q, k, v))
}

/// [`qkv_rope`]'s split and rotation in candle's ops (no cache write).
fn qkv_rope_composed(
    y: &Tensor,
    heads: Heads,
    rope: RopeTables<'_>,
) -> Result<(Option<Tensor>, Tensor, Tensor)> {
    let (b, l, _) = y.dims3()?;
    let (qd, kvd, hd) = (heads.q * heads.dim, heads.kv * heads.dim, heads.dim);
    // columns col .. col + n hd as [B, n, L, hd]
    let part = |col: usize, n: usize| -> Result<Tensor> {
        y.narrow(2, col, n * hd)?
            .contiguous()?
            .reshape((b, l, n, hd))?
            .transpose(1, 2)?
            .contiguous()
    };
    let rotate = |x: Tensor| candle_nn::rotary_emb::rope(&x, rope.0, rope.1);
    let q = match heads.q {
        0 => None,
        n => Some(rotate(part(0, n)?)?),
    };
    let k = rotate(part(qd, heads.kv)?)?;
    Ok((q, k, part(qd + kvd, heads.kv)?))
}

/// SigLIP's fused Q/K/V output `y` [N, T, 3 · n · hd] as three [N, n, T, hd] heads, unrotated.
pub fn split_qkv(y: &Tensor, n: usize, hd: usize) -> Result<(Tensor, Tensor, Tensor)> {
    let _span = span(Kind::Heads);
    if let Some(qkv) = kernels::split_qkv(y, n, hd)? {
        return Ok(qkv);
    }
    let d = n * hd;
    if !y.device().is_cpu() {
        return split_qkv_composed(y, n, hd);
    }
    if let (Some(q), Some(k), Some(v)) = (
        fastops::split_heads(y, 0, n, hd, None)?,
        fastops::split_heads(y, d, n, hd, None)?,
        fastops::split_heads(y, 2 * d, n, hd, None)?,
    ) {
        return Ok((q, k, v));
    }
    split_qkv_composed(y, n, hd)
}

/// [`split_qkv`] in candle's ops (differentiable).
pub fn split_qkv_composed(y: &Tensor, n: usize, hd: usize) -> Result<(Tensor, Tensor, Tensor)> {
    let (b, t, _) = y.dims3()?;
    // [N, T, 3, nH, hd] -> 3 x [N, nH, T, hd]
    let y = y.reshape((b, t, 3, n, hd))?;
    let head = |i: usize| -> Result<Tensor> {
        y.narrow(2, i, 1)?.squeeze(2)?.transpose(1, 2)?.contiguous()
    };
    Ok((head(0)?, head(1)?, head(2)?))
}

/// Attention `softmax(scale q kᵀ + bias) v` with GQA: `q` [B, nH, L, hd] (query heads
/// kv-head-major), `k`, `v` [B, nKV, T, hd], `bias` [B, 1, L or 1, T] f32 (None: no mask).
/// Returns [B, L, nH · hd]. The softmax runs in f32 whatever the model's dtype (openpi's).
/// `arith`: the CPU kernel's products in bf16 where the CPU has native bf16 arithmetic (the
/// layer's weights are packed in bf16); a GPU follows the tensors' dtype.
pub fn attention(
    q: &Tensor,
    k: &Tensor,
    v: &Tensor,
    bias: Option<&Tensor>,
    scale: f64,
    arith: Precision,
) -> Result<Tensor> {
    attention_cached(q, k, v, bias, scale, arith, None)
}

/// [`attention`] over a KV cache whose keys `0..prefix.keys()` the CPU kernel has packed
/// already ([`PackedKv`], once per observation): it packs only the keys after them. `prefix`
/// is ignored where it does not apply (another device, the kernels off, other shapes).
pub fn attention_cached(
    q: &Tensor,
    k: &Tensor,
    v: &Tensor,
    bias: Option<&Tensor>,
    scale: f64,
    arith: Precision,
    prefix: Option<&PackedKv>,
) -> Result<Tensor> {
    let _span = span(Kind::Attention);
    if q.device().is_cpu() {
        let zeros;
        let b = match bias {
            Some(b) => b,
            None => {
                let (n, t) = (k.dim(0)?, k.dim(2)?);
                zeros = Tensor::zeros((n, 1, 1, t), DType::F32, q.device())?;
                &zeros
            }
        };
        if let Some(o) = fastops::attention(q, k, v, b, scale as f32, arith, prefix)? {
            return Ok(o);
        }
    }
    if kernels::enabled(q.device()) {
        let (b, nh, l, hd) = q.dims4()?;
        let nkv = k.dim(1)?;
        let g = nh / nkv.max(1);
        // [B, nKV, g L, T]
        let scores = q.reshape((b, nkv, g * l, hd))?.matmul(&k.t()?)?;
        if let Some(p) = kernels::softmax_bias(&scores, bias, l, scale)? {
            // [B, nKV, g L, hd] -> [B, L, nH hd]
            return p
                .matmul(v)?
                .reshape((b, nh, l, hd))?
                .transpose(1, 2)?
                .reshape((b, l, nh * hd));
        }
    }
    attention_composed(q, k, v, bias, scale, false)
}

/// [`attention`] in candle's ops; `diff`: the softmax with a backward.
pub fn attention_composed(
    q: &Tensor,
    k: &Tensor,
    v: &Tensor,
    bias: Option<&Tensor>,
    scale: f64,
    diff: bool,
) -> Result<Tensor> {
    let q = (q * scale)?;
    let (b, nh, l, hd) = q.dims4()?;
    let nkv = k.dim(1)?;
    let t = k.dim(2)?;
    let g = nh / nkv.max(1);
    // [B, nKV, g*L, hd]: query heads are kv-head-major, so this is a free reshape
    let q = q.reshape((b, nkv, g * l, hd))?;
    // [B, nKV, g*L, T], masked and normalised in f32, probabilities back in the model's dtype
    let s = q.matmul(&k.t()?)?.to_dtype(DType::F32)?;
    let s = match bias {
        Some(bias) => {
            let bl = bias.dim(2)?;
            // [B, nKV, g, L, T] + [B, 1, 1, L|1, T]
            s.reshape((b, nkv, g, l, t))?
                .broadcast_add(&bias.to_dtype(DType::F32)?.reshape((b, 1, 1, bl, t))?)?
        }
        None => s,
    };
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

/// `gelu_tanh(y[.., :f]) * y[.., f:]` for the output `y` [.., 2f] of a fused gate/up product.
pub fn gelu_mul(y: &Tensor, f: usize) -> Result<Tensor> {
    let _span = span(Kind::Activations);
    if let Some(h) = fastops::gelu_mul_fused(y, f)? {
        return Ok(h);
    }
    if let Some(h) = kernels::gelu_mul(y, f)? {
        return Ok(h);
    }
    let last = y.rank().saturating_sub(1);
    y.narrow(last, 0, f)?.gelu()? * y.narrow(last, f, f)?
}

/// `gelu_tanh(g) * u` for separate gate and up outputs (layers without a fused product).
pub fn gelu_mul_pair(g: &Tensor, u: &Tensor) -> Result<Tensor> {
    let _span = span(Kind::Activations);
    match fastops::gelu_mul(g, u)? {
        Some(h) => Ok(h),
        None => g.gelu()? * u,
    }
}

#[cfg(test)]
mod tests {
    //! The seam's CPU kernels against its own fallback compositions (the ops a GPU falls back
    //! to): the same numbers to float rounding.
    use super::*;
    use candle_core::Device;

    fn rand(shape: &[usize], seed: u64) -> Tensor {
        let n: usize = shape.iter().product();
        let mut s = seed
            .wrapping_mul(6364136223846793005)
            .wrapping_add(1442695040888963407);
        let v: Vec<f32> = (0..n)
            .map(|_| {
                s = s
                    .wrapping_mul(6364136223846793005)
                    .wrapping_add(1442695040888963407);
                ((s >> 40) as f32 / (1u64 << 24) as f32) * 2.0 - 1.0
            })
            .collect();
        Tensor::from_vec(v, shape, &Device::Cpu).expect("shape")
    }

    fn maxdiff(a: &Tensor, b: &Tensor) -> f32 {
        assert_eq!(a.dims(), b.dims());
        (a - b)
            .and_then(|d| d.abs()?.flatten_all()?.max(0)?.to_scalar::<f32>())
            .expect("diff")
    }

    #[test]
    fn attention_kernel_matches_the_composition_with_and_without_mask() {
        // GQA: 4 query heads over 2 kv heads, a mask hiding the last two keys of row 0
        let (q, k, v) = (
            rand(&[1, 4, 5, 8], 1),
            rand(&[1, 2, 7, 8], 2),
            rand(&[1, 2, 7, 8], 3),
        );
        let mut b = vec![0f32; 5 * 7];
        // openpi's mask value
        b[5] = -2.381_976_3e38;
        b[6] = -2.381_976_3e38;
        let bias = Tensor::from_vec(b, (1, 1, 5, 7), &Device::Cpu).expect("bias");
        for mask in [Some(&bias), None] {
            let fast = attention(&q, &k, &v, mask, 0.35, Precision::F32).expect("fast");
            let comp = attention_composed(&q, &k, &v, mask, 0.35, false).expect("composed");
            assert_eq!(fast.dims(), &[1, 5, 32]);
            assert!(maxdiff(&fast, &comp) < 1e-5, "{}", maxdiff(&fast, &comp));
        }
        // the mask matters: row 0 differs with and without it
        let masked = attention(&q, &k, &v, Some(&bias), 0.35, Precision::F32).expect("masked");
        let open = attention(&q, &k, &v, None, 0.35, Precision::F32).expect("open");
        assert!(maxdiff(&masked, &open) > 1e-3);
    }

    #[test]
    fn head_split_rope_and_cache_write_match_the_composition() {
        let heads = Heads {
            q: 4,
            kv: 2,
            dim: 8,
        };
        let y = rand(&[1, 5, (4 + 2 * 2) * 8], 4);
        // tables of positions 3..8 ([1, 5, 4]), as gemma::Rope makes them
        let (mut cos, mut sin) = (Vec::new(), Vec::new());
        for p in 3..8 {
            for i in 0..4 {
                let a = p as f32 / 10_000f32.powf(2.0 * i as f32 / 8.0);
                cos.push(a.cos());
                sin.push(a.sin());
            }
        }
        let cos = Tensor::from_vec(cos, (1, 5, 4), &Device::Cpu).expect("cos");
        let sin = Tensor::from_vec(sin, (1, 5, 4), &Device::Cpu).expect("sin");
        let rope = (&cos, &sin);
        let kb = Tensor::zeros((1, 2, 9, 8), DType::F32, &Device::Cpu).expect("kb");
        let vb = Tensor::zeros((1, 2, 9, 8), DType::F32, &Device::Cpu).expect("vb");
        let (q, k, v) = qkv_rope(&y, heads, rope, Some((&kb, &vb, 3))).expect("fast");
        let (cq, ck, cv) = qkv_rope_composed(&y, heads, rope).expect("composed");
        let q = q.expect("q");
        assert!(maxdiff(&q, &cq.expect("q")) < 1e-6);
        assert!(maxdiff(&k, &ck) < 1e-6);
        assert!(maxdiff(&v, &cv) < 1e-6);
        // written at offset 3, nothing before it
        assert!(maxdiff(&kb.narrow(2, 3, 5).expect("narrow"), &ck) < 1e-6);
        assert!(maxdiff(&vb.narrow(2, 3, 5).expect("narrow"), &cv) < 1e-6);
        let head = kb.narrow(2, 0, 3).expect("narrow");
        assert_eq!(maxdiff(&head, &head.zeros_like().expect("zeros")), 0.0);
        // only K/V columns
        let kv = y.narrow(2, 32, 32).expect("kv");
        let kv_heads = Heads { q: 0, ..heads };
        let (none, k2, _) = qkv_rope(&kv, kv_heads, rope, None).expect("kv only");
        assert!(none.is_none());
        assert!(maxdiff(&k2, &ck) < 1e-6);
    }

    #[test]
    fn split_gelu_and_dense_match_the_composition() {
        let y = rand(&[2, 6, 3 * 16], 5);
        let (q, k, v) = split_qkv(&y, 2, 8).expect("fast");
        let (cq, ck, cv) = split_qkv_composed(&y, 2, 8).expect("composed");
        for (a, b) in [(&q, &cq), (&k, &ck), (&v, &cv)] {
            assert_eq!(maxdiff(a, b), 0.0);
        }
        let gu = rand(&[2, 3, 2 * 24], 6);
        let h = gelu_mul(&gu, 24).expect("fast");
        let comp = (gu.narrow(2, 0, 24).and_then(|g| g.gelu()).expect("gelu")
            * gu.narrow(2, 24, 24).expect("up"))
        .expect("mul");
        assert!(maxdiff(&h, &comp) < 1e-5);
        // a dense layer with bias, gelu and residual, packed (where this CPU has the kernel)
        let (x, w, b, r) = (
            rand(&[2, 3, 16], 7),
            rand(&[24, 16], 8),
            rand(&[24], 9),
            rand(&[2, 3, 24], 10),
        );
        let packed = PackedRhs::pack_weight(&w, crate::packed::Precision::F32)
            .expect("pack")
            .map(|p| p.with_bias(b.to_vec1().expect("bias")));
        let fast = dense(&x, &w, &b, packed.as_ref(), true, Some(&r)).expect("dense");
        let comp = (linear(&x, &w, &b).and_then(|y| y.gelu()).expect("linear") + &r).expect("add");
        assert!(maxdiff(&fast, &comp) < 1e-5, "{}", maxdiff(&fast, &comp));
    }
}
