//! chunkrt's own fused CUDA kernels (`kernels/ops.cu`, compiled to PTX by `build.rs` with the
//! `cuda` feature and loaded into candle's CUDA device at first use).
//!
//! Candle runs one kernel per op, and at batch 1 a transformer layer of the action expert is
//! dominated by the small ones between the matrix products: casts, broadcasts, copies for
//! strides. These kernels replace those chains on the inference path (`diff = false`):
//!
//! | kernel | replaces |
//! |---|---|
//! | [`add_norm`] | gated residual + RMSNorm `(1 + w)` / AdaRMSNorm with its scale and shift (f32 statistics) |
//! | [`gated_add`] | `x + y * gate` |
//! | [`qkv_rope`] | head split of the fused Q/K/V product, RoPE on Q and K, the KV-cache write |
//! | [`gelu_mul`] | `gelu_tanh(gate) * up` of the fused gate/up product |
//! | [`softmax_bias`] | scale, additive mask, f32 softmax and the casts around it (in place) |
//!
//! Each function returns `Ok(None)` where the kernels do not apply (a CPU tensor, a build
//! without `cuda`, a dtype other than f32/bf16, or [`set_enabled`]`(false)`). Only the seam
//! ([`crate::ops`]) calls them; it then runs candle's ops, which stay the reference the kernels
//! are checked against (the fixtures on the GPU, `scripts/gpu-run.sh`).

use std::sync::atomic::{AtomicBool, Ordering};

use candle_core::{Result, Tensor};

static ENABLED: AtomicBool = AtomicBool::new(true);

/// Turns the fused kernels on or off (on by default; off: candle's op-by-op path, for A/B
/// benchmarks and for checking the kernels against it).
pub fn set_enabled(on: bool) {
    ENABLED.store(on, Ordering::Relaxed);
}

/// Whether the fused kernels run for tensors on `dev`.
pub fn enabled(dev: &candle_core::Device) -> bool {
    cfg!(feature = "cuda") && dev.is_cuda() && ENABLED.load(Ordering::Relaxed)
}

#[cfg(feature = "cuda")]
mod imp {
    use candle_core::backend::BackendStorage;
    use candle_core::cuda_backend::cudarc::driver::{DevicePtr, LaunchConfig, PushKernelArg};
    use candle_core::cuda_backend::{CudaDevice, CudaStorage};
    use candle_core::op::BackpropOp;
    use candle_core::{bail, DType, Result, Shape, Storage, Tensor};

    const PTX: &str = include_str!(concat!(env!("OUT_DIR"), "/ops.ptx"));
    const MODULE: &str = "chunkrt_ops";

    fn suffix(dt: DType) -> Result<&'static str> {
        match dt {
            DType::F32 => Ok("f32"),
            DType::BF16 => Ok("bf16"),
            d => bail!("fused kernels: unsupported dtype {d:?}"),
        }
    }

    /// The CUDA device of `t`.
    pub fn device(t: &Tensor) -> Result<CudaDevice> {
        Ok(t.device().as_cuda_device()?.clone())
    }

    /// Device address of `t`'s first element (`t` contiguous, f32 or bf16). The address stays
    /// valid while `t` lives; kernels are ordered on candle's one stream.
    pub fn ptr(t: &Tensor, dev: &CudaDevice) -> Result<u64> {
        let (st, l) = t.storage_and_layout();
        if !l.is_contiguous() {
            bail!("fused kernels: a non-contiguous operand {:?}", t.dims());
        }
        let Storage::Cuda(cs) = &*st else {
            bail!("fused kernels: a tensor that is not on a CUDA device");
        };
        let stream = dev.cuda_stream();
        let off = l.start_offset() as u64;
        Ok(match t.dtype() {
            DType::F32 => cs.as_cuda_slice::<f32>()?.device_ptr(&stream).0 + 4 * off,
            DType::BF16 => cs.as_cuda_slice::<half::bf16>()?.device_ptr(&stream).0 + 2 * off,
            d => bail!("fused kernels: unsupported dtype {d:?}"),
        })
    }

    /// An uninitialised tensor (every element is written by the kernel that fills it).
    pub fn alloc(dev: &CudaDevice, shape: Shape, dt: DType) -> Result<Tensor> {
        let n = shape.elem_count();
        let storage = match dt {
            // SAFETY: the kernel launched next writes every element before anything reads it.
            DType::F32 => {
                CudaStorage::wrap_cuda_slice(unsafe { dev.alloc::<f32>(n)? }, dev.clone())
            }
            DType::BF16 => {
                CudaStorage::wrap_cuda_slice(unsafe { dev.alloc::<half::bf16>(n)? }, dev.clone())
            }
            d => bail!("fused kernels: unsupported dtype {d:?}"),
        };
        debug_assert_eq!(storage.dtype(), dt);
        Ok(Tensor::from_storage(
            Storage::Cuda(storage),
            shape,
            BackpropOp::none(),
            false,
        ))
    }

    /// Launches `name_<dtype>` with `args` (device addresses and scalars, in order).
    pub fn launch(
        dev: &CudaDevice,
        name: &str,
        dt: DType,
        cfg: LaunchConfig,
        args: &[Arg],
    ) -> Result<()> {
        let f = dev.get_or_load_custom_func(&format!("{name}_{}", suffix(dt)?), MODULE, PTX)?;
        let mut b = f.builder();
        for a in args {
            match a {
                Arg::U64(v) => b.arg(v),
                Arg::I32(v) => b.arg(v),
                Arg::F32(v) => b.arg(v),
            };
        }
        // SAFETY: the argument lists match the kernels' signatures in kernels/ops.cu (checked
        // by the GPU fixtures), every pointer is a live allocation of the size the kernel
        // indexes (checked by the callers against the tensors' shapes).
        unsafe { b.launch(cfg) }
            .map(|_| ())
            .map_err(|e| candle_core::Error::Msg(format!("{name}: {e}")))
    }

    /// A kernel argument.
    pub enum Arg {
        U64(u64),
        I32(i32),
        F32(f32),
    }
}

#[cfg(feature = "cuda")]
use imp::Arg;

/// Checks and converts a dimension for a kernel's `int` parameter.
#[cfg(feature = "cuda")]
fn int(v: usize) -> Result<i32> {
    i32::try_from(v).map_err(|_| candle_core::Error::Msg(format!("dimension {v} exceeds i32")))
}

/// Optional device address (0 = null in the kernel).
#[cfg(feature = "cuda")]
fn opt_ptr(t: Option<&Tensor>, dev: &candle_core::cuda_backend::CudaDevice) -> Result<u64> {
    t.map_or(Ok(0), |t| imp::ptr(t, dev))
}

/// Threads per block for row kernels over `w` elements: a multiple of 32, at most 1024.
#[cfg(feature = "cuda")]
fn row_threads(w: usize) -> u32 {
    (w.div_ceil(4).next_multiple_of(32)).clamp(32, 1024) as u32
}

/// The gated residual and norm of a layer in one kernel, over `x` [B, L, W] (contiguous):
/// `x1 = x + y * gate` (`y` None: `x1 = x`; `gmod` None: no gate; gate = `gmod[b, 2W..3W]`),
/// then `h = x1 * rsqrt(mean(x1²) + eps) * alpha`, and with `modulation` [B, 3W] f32
/// (AdaRMSNorm) `h = h * (1 + scale) + shift`. `alpha` [W] f32 (None: 1). Returns
/// (`x1` when `want_x1`, `h`), both in `x`'s dtype.
#[allow(unused_variables)]
pub fn add_norm(
    x: &Tensor,
    y: Option<&Tensor>,
    gmod: Option<&Tensor>,
    alpha: Option<&Tensor>,
    modulation: Option<&Tensor>,
    eps: f64,
    want_x1: bool,
) -> Result<Option<(Option<Tensor>, Tensor)>> {
    if !enabled(x.device()) {
        return Ok(None);
    }
    #[cfg(feature = "cuda")]
    {
        use candle_core::cuda_backend::cudarc::driver::LaunchConfig;
        let dev = imp::device(x)?;
        let dims = x.dims();
        let (Some(&w), true) = (dims.last(), dims.len() == 3) else {
            candle_core::bail!("add_norm: x must be [B, L, W], got {dims:?}");
        };
        let (b, l) = (dims[0], dims[1]);
        if let Some(y) = y {
            if y.dims() != dims || y.dtype() != x.dtype() {
                candle_core::bail!("add_norm: y {:?} does not match x {dims:?}", y.dims());
            }
        }
        for m in [gmod, modulation].into_iter().flatten() {
            if m.dims() != [b, 3 * w] || m.dtype() != candle_core::DType::F32 {
                candle_core::bail!(
                    "add_norm: modulation must be [B, 3W] f32, got {:?}",
                    m.dims()
                );
            }
        }
        if let Some(a) = alpha {
            if a.dims() != [w] || a.dtype() != candle_core::DType::F32 {
                candle_core::bail!("add_norm: alpha must be [W] f32, got {:?}", a.dims());
            }
        }
        let x = x.contiguous()?;
        let y = y.map(|y| y.contiguous()).transpose()?;
        let x1 = if want_x1 {
            Some(imp::alloc(&dev, x.shape().clone(), x.dtype())?)
        } else {
            None
        };
        let h = imp::alloc(&dev, x.shape().clone(), x.dtype())?;
        let threads = row_threads(w);
        let cfg = LaunchConfig {
            grid_dim: (int(b * l)? as u32, 1, 1),
            block_dim: (threads, 1, 1),
            shared_mem_bytes: ((w + 32) * 4) as u32,
        };
        imp::launch(
            &dev,
            "add_norm",
            x.dtype(),
            cfg,
            &[
                Arg::U64(imp::ptr(&x, &dev)?),
                Arg::U64(opt_ptr(y.as_ref(), &dev)?),
                Arg::U64(opt_ptr(gmod, &dev)?),
                Arg::U64(opt_ptr(x1.as_ref(), &dev)?),
                Arg::U64(imp::ptr(&h, &dev)?),
                Arg::U64(opt_ptr(alpha, &dev)?),
                Arg::U64(opt_ptr(modulation, &dev)?),
                Arg::I32(int(w)?),
                Arg::I32(int(l)?),
                Arg::F32(eps as f32),
            ],
        )?;
        Ok(Some((x1, h)))
    }
    #[cfg(not(feature = "cuda"))]
    Ok(None)
}

/// `x + y * gate` over [B, L, W] with gate = `gmod[b, 2W..3W]` (f32; None: `x + y`).
#[allow(unused_variables)]
pub fn gated_add(x: &Tensor, y: &Tensor, gmod: Option<&Tensor>) -> Result<Option<Tensor>> {
    if !enabled(x.device()) {
        return Ok(None);
    }
    #[cfg(feature = "cuda")]
    {
        use candle_core::cuda_backend::cudarc::driver::LaunchConfig;
        let dev = imp::device(x)?;
        let (b, l, w) = x.dims3()?;
        if y.dims() != x.dims() || y.dtype() != x.dtype() {
            candle_core::bail!(
                "gated_add: y {:?} does not match x {:?}",
                y.dims(),
                x.dims()
            );
        }
        if let Some(m) = gmod {
            if m.dims() != [b, 3 * w] || m.dtype() != candle_core::DType::F32 {
                candle_core::bail!(
                    "gated_add: modulation must be [B, 3W] f32, got {:?}",
                    m.dims()
                );
            }
        }
        let (x, y) = (x.contiguous()?, y.contiguous()?);
        let out = imp::alloc(&dev, x.shape().clone(), x.dtype())?;
        let cfg = LaunchConfig {
            grid_dim: (int(b * l)? as u32, 1, 1),
            block_dim: (row_threads(w), 1, 1),
            shared_mem_bytes: 0,
        };
        imp::launch(
            &dev,
            "gated_add",
            x.dtype(),
            cfg,
            &[
                Arg::U64(imp::ptr(&x, &dev)?),
                Arg::U64(imp::ptr(&y, &dev)?),
                Arg::U64(opt_ptr(gmod, &dev)?),
                Arg::U64(imp::ptr(&out, &dev)?),
                Arg::I32(int(w)?),
                Arg::I32(int(l)?),
            ],
        )?;
        Ok(Some(out))
    }
    #[cfg(not(feature = "cuda"))]
    Ok(None)
}

/// Head layout of a fused Q/K/V product for [`qkv_rope`].
#[derive(Debug, Clone, Copy)]
pub struct Heads {
    /// Query heads (0: no Q in `y`, none returned).
    pub q: usize,
    /// Key/value heads.
    pub kv: usize,
    /// Head dimension (even).
    pub dim: usize,
}

/// Splits `y` [B, L, (q + 2 kv) · hd] (Q columns first unless `heads.q == 0`, then K, V) into
/// heads, rotates Q and K with `rope` = (cos, sin) [B, L, hd/2] (rotate-half RoPE; None: no
/// rotation), writes K and V into the buffers `k_dst`/`v_dst` [B, kv, T, hd] at sequence
/// `offset` and returns Q [B, q, L, hd] (None when `heads.q == 0`).
#[allow(unused_variables)]
pub fn qkv_rope(
    y: &Tensor,
    heads: Heads,
    rope: Option<(&Tensor, &Tensor)>,
    k_dst: &Tensor,
    v_dst: &Tensor,
    offset: usize,
) -> Result<Option<Option<Tensor>>> {
    if !enabled(y.device()) {
        return Ok(None);
    }
    #[cfg(feature = "cuda")]
    {
        use candle_core::cuda_backend::cudarc::driver::LaunchConfig;
        let dev = imp::device(y)?;
        let (b, l, ncols) = y.dims3()?;
        let hd = heads.dim;
        let half = hd / 2;
        if !hd.is_multiple_of(2) || ncols != (heads.q + 2 * heads.kv) * hd {
            candle_core::bail!("qkv_rope: {ncols} columns do not hold {heads:?}");
        }
        if let Some((cos, sin)) = rope {
            if cos.dims() != [b, l, half] || sin.dims() != cos.dims() || cos.dtype() != y.dtype() {
                candle_core::bail!(
                    "qkv_rope: rope tables {:?} for [{b}, {l}, {half}]",
                    cos.dims()
                );
            }
        }
        let t = k_dst.dim(2)?;
        if k_dst.dims() != [b, heads.kv, t, hd]
            || v_dst.dims() != k_dst.dims()
            || k_dst.dtype() != y.dtype()
            || offset + l > t
        {
            candle_core::bail!(
                "qkv_rope: cache {:?} cannot take {l} tokens at {offset}",
                k_dst.dims()
            );
        }
        let y = y.contiguous()?;
        let rope = match rope {
            Some((c, s)) => Some((c.contiguous()?, s.contiguous()?)),
            None => None,
        };
        let q = if heads.q > 0 {
            Some(imp::alloc(&dev, (b, heads.q, l, hd).into(), y.dtype())?)
        } else {
            None
        };
        let qc = 0;
        let kc = heads.q * hd;
        let vc = kc + heads.kv * hd;
        let pairs = (heads.q + 2 * heads.kv) * half;
        let cfg = LaunchConfig {
            grid_dim: (int(b * l)? as u32, 1, 1),
            block_dim: (pairs.next_multiple_of(32).clamp(32, 256) as u32, 1, 1),
            shared_mem_bytes: 0,
        };
        imp::launch(
            &dev,
            "qkv_rope",
            y.dtype(),
            cfg,
            &[
                Arg::U64(imp::ptr(&y, &dev)?),
                Arg::I32(int(ncols)?),
                Arg::U64(opt_ptr(q.as_ref(), &dev)?),
                Arg::U64(imp::ptr(k_dst, &dev)?),
                Arg::U64(imp::ptr(v_dst, &dev)?),
                Arg::U64(opt_ptr(rope.as_ref().map(|r| &r.0), &dev)?),
                Arg::U64(opt_ptr(rope.as_ref().map(|r| &r.1), &dev)?),
                Arg::I32(int(l)?),
                Arg::I32(int(heads.q)?),
                Arg::I32(int(heads.kv)?),
                Arg::I32(int(hd)?),
                Arg::I32(qc),
                Arg::I32(int(kc)?),
                Arg::I32(int(vc)?),
                Arg::I32(int(t)?),
                Arg::I32(int(offset)?),
            ],
        )?;
        Ok(Some(q))
    }
    #[cfg(not(feature = "cuda"))]
    Ok(None)
}

/// `act(y + bias) + residual` over `y` [.., N] with `bias` [N] (None: no bias), `gelu`:
/// gelu-tanh as `act` (else identity), `residual` shaped as `y` (None: none). The bias-add,
/// activation and residual of a dense layer with bias (SigLIP) in one kernel.
#[allow(unused_variables)]
pub fn bias_act(
    y: &Tensor,
    bias: Option<&Tensor>,
    gelu: bool,
    residual: Option<&Tensor>,
) -> Result<Option<Tensor>> {
    if !enabled(y.device()) {
        return Ok(None);
    }
    #[cfg(feature = "cuda")]
    {
        use candle_core::cuda_backend::cudarc::driver::LaunchConfig;
        let dev = imp::device(y)?;
        let n = y.dims().last().copied().unwrap_or(0);
        let rows = y.elem_count() / n.max(1);
        if rows > 65_535 || n == 0 {
            return Ok(None);
        }
        if bias.is_some_and(|b| b.dims() != [n] || b.dtype() != y.dtype())
            || residual.is_some_and(|r| r.dims() != y.dims() || r.dtype() != y.dtype())
        {
            candle_core::bail!("bias_act: operands do not match {:?}", y.dims());
        }
        let y = y.contiguous()?;
        let bias = bias.map(|t| t.contiguous()).transpose()?;
        let residual = residual.map(|t| t.contiguous()).transpose()?;
        let out = imp::alloc(&dev, y.shape().clone(), y.dtype())?;
        let cfg = LaunchConfig {
            grid_dim: (n.div_ceil(256).clamp(1, 64) as u32, rows as u32, 1),
            block_dim: (256, 1, 1),
            shared_mem_bytes: 0,
        };
        imp::launch(
            &dev,
            "bias_act",
            y.dtype(),
            cfg,
            &[
                Arg::U64(imp::ptr(&y, &dev)?),
                Arg::U64(opt_ptr(bias.as_ref(), &dev)?),
                Arg::U64(opt_ptr(residual.as_ref(), &dev)?),
                Arg::U64(imp::ptr(&out, &dev)?),
                Arg::I32(int(n)?),
                Arg::I32(gelu as i32),
            ],
        )?;
        Ok(Some(out))
    }
    #[cfg(not(feature = "cuda"))]
    Ok(None)
}

/// Q, K, V heads [B, n, L, hd] of a fused, unrotated Q/K/V product `y` [B, L, 3 n hd] (SigLIP).
#[allow(unused_variables)]
pub fn split_qkv(y: &Tensor, n: usize, hd: usize) -> Result<Option<(Tensor, Tensor, Tensor)>> {
    if !enabled(y.device()) {
        return Ok(None);
    }
    #[cfg(feature = "cuda")]
    {
        let dev = imp::device(y)?;
        let (b, l, _) = y.dims3()?;
        let k = imp::alloc(&dev, (b, n, l, hd).into(), y.dtype())?;
        let v = imp::alloc(&dev, (b, n, l, hd).into(), y.dtype())?;
        let heads = Heads {
            q: n,
            kv: n,
            dim: hd,
        };
        Ok(qkv_rope(y, heads, None, &k, &v, 0)?.and_then(|q| q.map(|q| (q, k, v))))
    }
    #[cfg(not(feature = "cuda"))]
    Ok(None)
}

/// `gelu_tanh(y[.., :F]) * y[.., F:]` of the fused gate/up product `y` [.., 2F].
#[allow(unused_variables)]
pub fn gelu_mul(y: &Tensor, f: usize) -> Result<Option<Tensor>> {
    if !enabled(y.device()) {
        return Ok(None);
    }
    #[cfg(feature = "cuda")]
    {
        use candle_core::cuda_backend::cudarc::driver::LaunchConfig;
        let dev = imp::device(y)?;
        let mut dims = y.dims().to_vec();
        match dims.last_mut() {
            Some(last) if *last == 2 * f => *last = f,
            _ => candle_core::bail!("gelu_mul: {:?} is not [.., 2 * {f}]", y.dims()),
        }
        let rows = y.elem_count() / (2 * f).max(1);
        if rows > 65_535 {
            return Ok(None);
        }
        let y = y.contiguous()?;
        let h = imp::alloc(&dev, dims.into(), y.dtype())?;
        let cfg = LaunchConfig {
            grid_dim: (f.div_ceil(256).clamp(1, 64) as u32, rows.max(1) as u32, 1),
            block_dim: (256, 1, 1),
            shared_mem_bytes: 0,
        };
        imp::launch(
            &dev,
            "gelu_mul",
            y.dtype(),
            cfg,
            &[
                Arg::U64(imp::ptr(&y, &dev)?),
                Arg::U64(imp::ptr(&h, &dev)?),
                Arg::I32(int(f)?),
            ],
        )?;
        Ok(Some(h))
    }
    #[cfg(not(feature = "cuda"))]
    Ok(None)
}

/// In place: attention scores `s` [B, nKV, g·L, n] (query heads kv-head-major, rows of one
/// batch row ordered head, then query) become `softmax(s * scale + bias)` in f32, rounded to
/// `s`'s dtype; `bias` [B, 1, L or 1, n] f32 (None: no mask). Returns `s`.
#[allow(unused_variables)]
pub fn softmax_bias(
    s: &Tensor,
    bias: Option<&Tensor>,
    l: usize,
    scale: f64,
) -> Result<Option<Tensor>> {
    if !enabled(s.device()) {
        return Ok(None);
    }
    #[cfg(feature = "cuda")]
    {
        use candle_core::cuda_backend::cudarc::driver::LaunchConfig;
        let dev = imp::device(s)?;
        let (b, nkv, gl, n) = s.dims4()?;
        let (bb, one, bl, bn) = match bias {
            Some(t) => t.dims4()?,
            None => (b, 1, 1, n),
        };
        if l == 0
            || gl % l != 0
            || bb != b
            || one != 1
            || (bl != l && bl != 1)
            || bn != n
            || bias.is_some_and(|t| t.dtype() != candle_core::DType::F32)
        {
            candle_core::bail!(
                "softmax_bias: scores {:?}, bias {:?}, L {l}",
                s.dims(),
                bias.map(|t| t.dims().to_vec())
            );
        }
        if (n + 32) * 4 > 48 * 1024 {
            return Ok(None);
        }
        let g = nkv * (gl / l);
        let s = s.contiguous()?;
        let bias = bias.map(|t| t.contiguous()).transpose()?;
        let cfg = LaunchConfig {
            grid_dim: (int(b * nkv * gl)? as u32, 1, 1),
            block_dim: (row_threads(n), 1, 1),
            shared_mem_bytes: ((n + 32) * 4) as u32,
        };
        imp::launch(
            &dev,
            "softmax_bias",
            s.dtype(),
            cfg,
            &[
                Arg::U64(imp::ptr(&s, &dev)?),
                Arg::U64(opt_ptr(bias.as_ref(), &dev)?),
                Arg::I32(int(n)?),
                Arg::I32(int(l)?),
                Arg::I32(int(g)?),
                Arg::I32(int(bl)?),
                Arg::F32(scale as f32),
            ],
        )?;
        Ok(Some(s))
    }
    #[cfg(not(feature = "cuda"))]
    Ok(None)
}
