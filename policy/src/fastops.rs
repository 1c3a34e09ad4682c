//! Fused CPU kernels for the fast (non-differentiable) inference path.
//!
//! candle's CPU backend runs `gelu` and the softmax `exp` through scalar libm calls and
//! materialises every intermediate (bias-added scores, probabilities, transposed heads). These
//! kernels do the same math on f32 slices in one pass each, vectorised (AVX-512 / AVX2 picked at
//! run time, plain code otherwise), calling the `gemm` crate directly for the matrix products.
//! Results agree with the candle compositions to float rounding (a few ulp); the differentiable
//! path keeps using candle's ops.
//!
//! Every entry point returns `Ok(None)` when its inputs are not contiguous f32 CPU tensors of the
//! expected layout; the seam that calls them ([`crate::ops`]) then falls back to the candle
//! composition.

use candle_core::{CpuStorage, Device, Layout, Result, Storage, Tensor};

use super::packed::Precision;
use rayon::prelude::*;

/// Compiles `$body` three times (AVX-512, AVX2+FMA, baseline) and picks the best variant the CPU
/// supports at run time. The body must only call `#[inline(always)]` helpers so they are compiled
/// with the variant's features. In the body, the const `FMA` says whether the variant has fused
/// multiply-adds (pass it on to [`madd`]'s callers: without the feature `mul_add` is a libm call).
macro_rules! multiversion {
    ($(#[$m:meta])* fn $name:ident($($arg:ident: $ty:ty),* $(,)?) $body:block) => {
        $(#[$m])*
        fn $name($($arg: $ty),*) {
            #[inline(always)]
            fn imp<const FMA: bool>($($arg: $ty),*) $body
            #[cfg(target_arch = "x86_64")]
            {
                #[target_feature(enable = "avx512f,avx512vl,avx2,fma")]
                unsafe fn v4($($arg: $ty),*) {
                    imp::<true>($($arg),*)
                }
                #[target_feature(enable = "avx2,fma")]
                unsafe fn v3($($arg: $ty),*) {
                    imp::<true>($($arg),*)
                }
                let isa = crate::packed::support();
                if isa.avx512 {
                    // SAFETY: the CPU supports the features `v4` is compiled for.
                    return unsafe { v4($($arg),*) };
                }
                if isa.avx2_fma {
                    // SAFETY: the CPU supports the features `v3` is compiled for.
                    return unsafe { v3($($arg),*) };
                }
            }
            imp::<false>($($arg),*)
        }
    };
}

/// `a * b + c`, fused (one rounding, one instruction) where `FMA` says the variant compiled
/// has fused multiply-adds.
#[inline(always)]
fn madd<const FMA: bool>(a: f32, b: f32, c: f32) -> f32 {
    if FMA {
        a.mul_add(b, c)
    } else {
        a * b + c
    }
}

/// Lanes of the explicit reductions (one AVX-512 register of f32).
const LANES: usize = 16;

/// `exp(x)` in f32 (Cephes `expf`: `2^n * p(r)`, |r| <= ln 2 / 2, about 1 ulp); 0 below -87.
/// Branch-free so that loops over it vectorise.
#[inline(always)]
fn exp_f32<const FMA: bool>(x: f32) -> f32 {
    const LOG2E: f32 = std::f32::consts::LOG2_E;
    const LN2_HI: f32 = 0.693_359_4;
    const LN2_LO: f32 = -2.121_944_4e-4;
    // round-to-nearest through the 1.5 * 2^23 trick (no libm `roundf` call)
    const MAGIC: f32 = 12_582_912.0;
    let xc = x.clamp(-87.0, 88.0);
    let t = madd::<FMA>(xc, LOG2E, MAGIC);
    let n = t - MAGIC;
    let r = madd::<FMA>(-n, LN2_LO, madd::<FMA>(-n, LN2_HI, xc));
    let mut p = 1.987_569_1e-4f32;
    p = madd::<FMA>(p, r, 1.398_199_9e-3);
    p = madd::<FMA>(p, r, 8.333_452e-3);
    p = madd::<FMA>(p, r, 4.166_579_6e-2);
    p = madd::<FMA>(p, r, 1.666_666_5e-1);
    p = madd::<FMA>(p, r, 0.5);
    let y = madd::<FMA>(p, r * r, r + 1.0);
    // n in [-126, 127]: the low bits of `t` hold n + 0x40_0000
    let ni = (t.to_bits() as i32).wrapping_sub(0x4B40_0000);
    let scale = f32::from_bits(((ni + 127) << 23) as u32);
    if x < -87.0 {
        0.0
    } else {
        y * scale
    }
}

/// gelu with the tanh approximation, `0.5 x (1 + tanh(u)) = x * sigmoid(2u)`,
/// `u = sqrt(2/pi) (x + 0.044715 x^3)`.
#[inline(always)]
fn gelu_tanh<const FMA: bool>(x: f32) -> f32 {
    const C: f32 = 0.797_884_6;
    let u = C * madd::<FMA>(0.044_715 * x, x * x, x);
    x / (1.0 + exp_f32::<FMA>(-2.0 * u))
}

multiversion! {
    /// `out = gelu_tanh(g) * u`.
    fn gelu_mul_slice(g: &[f32], u: &[f32], out: &mut [f32]) {
        for ((o, &g), &u) in out.iter_mut().zip(g).zip(u) {
            *o = gelu_tanh::<FMA>(g) * u;
        }
    }
}

multiversion! {
    /// `out = gelu_tanh(x)`.
    fn gelu_slice(x: &[f32], out: &mut [f32]) {
        for (o, &x) in out.iter_mut().zip(x) {
            *o = gelu_tanh::<FMA>(x);
        }
    }
}

multiversion! {
    /// Row-wise `exp(scale * s + bias - max)` in place over the `t` columns of `rows` (bias: one
    /// row of `t` shared by all rows when `bias.len() == t`, else one per row), and each row's
    /// `1 / sum` into `inv`: the softmax without its division, which the caller applies to the
    /// attention's output rows (hd values a row instead of T).
    fn softmax_bias_rows(rows: &mut [f32], bias: &[f32], t: usize, scale: f32, inv: &mut [f32]) {
        for ((ri, row), inv) in rows.chunks_exact_mut(t).enumerate().zip(inv.iter_mut()) {
            let b = if bias.len() == t { bias } else { &bias[ri * t..(ri + 1) * t] };
            let mut mx = [f32::NEG_INFINITY; LANES];
            let mut rc = row.chunks_exact_mut(LANES);
            let mut bc = b.chunks_exact(LANES);
            for (r, b) in (&mut rc).zip(&mut bc) {
                for i in 0..LANES {
                    let v = madd::<FMA>(r[i], scale, b[i]);
                    r[i] = v;
                    mx[i] = if v > mx[i] { v } else { mx[i] };
                }
            }
            for (r, b) in rc.into_remainder().iter_mut().zip(bc.remainder()) {
                let v = madd::<FMA>(*r, scale, *b);
                *r = v;
                mx[0] = if v > mx[0] { v } else { mx[0] };
            }
            let m = mx.iter().fold(f32::NEG_INFINITY, |a, &b| if b > a { b } else { a });
            let mut sm = [0f32; LANES];
            let mut rc = row.chunks_exact_mut(LANES);
            for r in &mut rc {
                for i in 0..LANES {
                    let e = exp_f32::<FMA>(r[i] - m);
                    r[i] = e;
                    sm[i] += e;
                }
            }
            for r in rc.into_remainder() {
                let e = exp_f32::<FMA>(*r - m);
                *r = e;
                sm[0] += e;
            }
            *inv = 1.0 / sm.iter().sum::<f32>();
        }
    }
}

/// Scales row `r` of the `rows` × `cols` block at `c` (row stride `ldc`) by `inv[r]`.
///
/// # Safety
/// `c` must be valid for reads and writes of that block, and no one else may access it.
unsafe fn scale_rows(c: *mut f32, rows: usize, cols: usize, ldc: usize, inv: &[f32]) {
    for (r, &f) in inv.iter().enumerate().take(rows) {
        // SAFETY: row r of the block (the caller's contract).
        let row = unsafe { std::slice::from_raw_parts_mut(c.add(r * ldc), cols) };
        for v in row {
            *v *= f;
        }
    }
}

/// Adds the `rows` × `cols` block `part` (contiguous) into the block at `c` (row stride `ldc`).
///
/// # Safety
/// As [`scale_rows`].
unsafe fn add_rows(c: *mut f32, rows: usize, cols: usize, ldc: usize, part: &[f32]) {
    for (r, src) in part.chunks_exact(cols).enumerate().take(rows) {
        // SAFETY: row r of the block (the caller's contract).
        let row = unsafe { std::slice::from_raw_parts_mut(c.add(r * ldc), cols) };
        for (v, a) in row.iter_mut().zip(src) {
            *v += a;
        }
    }
}

/// Number of threads for the fused kernels (candle's setting, `RAYON_NUM_THREADS`).
fn threads() -> usize {
    candle_core::utils::get_num_threads()
}

static DISABLED: std::sync::atomic::AtomicBool = std::sync::atomic::AtomicBool::new(false);

/// Turns these kernels off (`false`) or back on for the whole process; off, every entry point
/// reports `None` and callers run candle's compositions, the same device-generic ops a GPU
/// model runs ([`crate::set_cpu_fast_paths`]).
pub fn set_enabled(on: bool) {
    DISABLED.store(!on, std::sync::atomic::Ordering::Relaxed);
}

/// The f32 data of a CPU tensor from its start offset, with its layout (`None`: not an f32 CPU
/// tensor, or these kernels are off). Every entry point goes through here.
fn cpu_f32<R>(t: &Tensor, f: impl FnOnce(&[f32], &Layout) -> Result<R>) -> Result<Option<R>> {
    if DISABLED.load(std::sync::atomic::Ordering::Relaxed) {
        return Ok(None);
    }
    let (s, l) = t.storage_and_layout();
    match &*s {
        Storage::Cpu(CpuStorage::F32(v)) => Ok(Some(f(&v[l.start_offset()..], l)?)),
        _ => Ok(None),
    }
}

/// `gelu_tanh(x)` for a contiguous f32 CPU tensor (SigLIP's MLP).
pub fn gelu(x: &Tensor) -> Result<Option<Tensor>> {
    if !x.is_contiguous() {
        return Ok(None);
    }
    let n = x.elem_count();
    let r = cpu_f32(x, |xs, _| {
        let mut out = vec![0f32; n];
        let xs = &xs[..n];
        const CHUNK: usize = 1 << 14;
        if threads() > 1 && n > 4 * CHUNK {
            out.par_chunks_mut(CHUNK)
                .zip(xs.par_chunks(CHUNK))
                .for_each(|(o, x)| gelu_slice(x, o));
        } else {
            gelu_slice(xs, &mut out);
        }
        Ok(out)
    })?;
    match r {
        Some(out) => Ok(Some(Tensor::from_vec(out, x.shape(), &Device::Cpu)?)),
        None => Ok(None),
    }
}

multiversion! {
    /// `out = a + b`.
    fn add_slice(a: &[f32], b: &[f32], out: &mut [f32]) {
        for ((o, &a), &b) in out.iter_mut().zip(a).zip(b) {
            *o = a + b;
        }
    }
}

/// `a + b` for contiguous f32 CPU tensors, `b` of `a`'s shape or of its trailing dimensions
/// (broadcast over the leading ones: residual connections, position embeddings), split over
/// rayon's threads when large. candle runs its element-wise ops on a pool of its own whose
/// workers spin after each op, competing with rayon's matrix-product workers for the cores.
pub fn add(a: &Tensor, b: &Tensor) -> Result<Option<Tensor>> {
    let (ad, bd) = (a.dims(), b.dims());
    if bd.len() > ad.len()
        || ad[ad.len() - bd.len()..] != *bd
        || !a.is_contiguous()
        || !b.is_contiguous()
        || b.elem_count() == 0
    {
        return Ok(None);
    }
    let n = a.elem_count();
    let m = b.elem_count();
    let r = cpu_f32(a, |xs, _| {
        cpu_f32(b, |ys, _| {
            let mut out = vec![0f32; n];
            let (xs, ys) = (&xs[..n], &ys[..m]);
            // chunks of whole periods of `b`, about 32k values
            let chunk = m * (1usize << 15).div_ceil(m);
            let run = |o: &mut [f32], x: &[f32]| {
                for (o, x) in o.chunks_mut(m).zip(x.chunks(m)) {
                    add_slice(x, &ys[..x.len()], o);
                }
            };
            if threads() > 1 && n > 2 * chunk {
                out.par_chunks_mut(chunk)
                    .zip(xs.par_chunks(chunk))
                    .for_each(|(o, x)| run(o, x));
            } else {
                run(&mut out, xs);
            }
            Ok(out)
        })
    })?
    .flatten();
    match r {
        Some(out) => Ok(Some(Tensor::from_vec(out, a.shape(), &Device::Cpu)?)),
        None => Ok(None),
    }
}

/// `a + b` with `b` broadcast over `a`'s leading dimensions: [`add`] on the fast path, candle's
/// `broadcast_add` where it does not apply or a backward is needed (`diff`).
pub fn add_or_broadcast(a: &Tensor, b: &Tensor, diff: bool) -> Result<Tensor> {
    if !diff {
        if let Some(s) = add(a, b)? {
            return Ok(s);
        }
    }
    a.broadcast_add(b)
}

/// `gelu_tanh(g) * u` for contiguous f32 CPU tensors of the same shape.
pub fn gelu_mul(g: &Tensor, u: &Tensor) -> Result<Option<Tensor>> {
    if g.dims() != u.dims() || !g.is_contiguous() || !u.is_contiguous() {
        return Ok(None);
    }
    let n = g.elem_count();
    let r = cpu_f32(g, |gs, _| {
        cpu_f32(u, |us, _| {
            let mut out = vec![0f32; n];
            let (gs, us) = (&gs[..n], &us[..n]);
            const CHUNK: usize = 1 << 14;
            if threads() > 1 && n > 4 * CHUNK {
                out.par_chunks_mut(CHUNK)
                    .zip(gs.par_chunks(CHUNK).zip(us.par_chunks(CHUNK)))
                    .for_each(|(o, (g, u))| gelu_mul_slice(g, u, o));
            } else {
                gelu_mul_slice(gs, us, &mut out);
            }
            Ok(out)
        })
    })?
    .flatten();
    match r {
        Some(out) => Ok(Some(Tensor::from_vec(out, g.shape(), &Device::Cpu)?)),
        None => Ok(None),
    }
}

/// `gelu_tanh(y[.., :f]) * y[.., f:]` for a contiguous f32 CPU tensor `y` [.., 2f] (the output
/// of a fused gate/up projection). Returns [.., f].
pub fn gelu_mul_fused(y: &Tensor, f: usize) -> Result<Option<Tensor>> {
    let dims = y.dims();
    if !y.is_contiguous() || dims.last() != Some(&(2 * f)) || f == 0 {
        return Ok(None);
    }
    let rows = y.elem_count() / (2 * f);
    let r = cpu_f32(y, |ys, _| {
        let mut out = vec![0f32; rows * f];
        let ys = &ys[..rows * 2 * f];
        let per = (1 << 14) / f + 1;
        if threads() > 1 && rows * f > 1 << 16 {
            out.par_chunks_mut(per * f)
                .zip(ys.par_chunks(per * 2 * f))
                .for_each(|(o, y)| {
                    for (o, y) in o.chunks_exact_mut(f).zip(y.chunks_exact(2 * f)) {
                        gelu_mul_slice(&y[..f], &y[f..], o);
                    }
                });
        } else {
            for (o, y) in out.chunks_exact_mut(f).zip(ys.chunks_exact(2 * f)) {
                gelu_mul_slice(&y[..f], &y[f..], o);
            }
        }
        Ok(out)
    })?;
    match r {
        Some(out) => {
            let mut shape = dims.to_vec();
            *shape.last_mut().expect("checked rank") = f;
            Ok(Some(Tensor::from_vec(out, shape, &Device::Cpu)?))
        }
        None => Ok(None),
    }
}

/// Columns `col .. col + n * hd` of `x` [B, L, C] (unit column stride, any row stride) as heads
/// [B, n, L, hd], rotated when `rope` = (cos, sin) [B, L, hd / 2] is given (rotate-half, the same
/// arithmetic as `candle_nn::rotary_emb::rope`). Replaces narrow + reshape + transpose +
/// contiguous + rope (three copies) with one pass.
pub fn split_heads(
    x: &Tensor,
    col: usize,
    n: usize,
    hd: usize,
    rope: Option<(&Tensor, &Tensor)>,
) -> Result<Option<Tensor>> {
    let (b, l, c) = x.dims3()?;
    let st = x.stride();
    if st[2] != 1 || col + n * hd > c || !hd.is_multiple_of(2) {
        return Ok(None);
    }
    let (sb, sl) = (st[0], st[1]);
    let half = hd / 2;
    let mut out = vec![0f32; b * n * l * hd];
    let copy = |xs: &[f32], out: &mut [f32], cs: Option<(&[f32], &[f32])>| {
        for bi in 0..b {
            for h in 0..n {
                for li in 0..l {
                    let src = &xs[bi * sb + li * sl + col + h * hd..][..hd];
                    let dst = &mut out[((bi * n + h) * l + li) * hd..][..hd];
                    match cs {
                        None => dst.copy_from_slice(src),
                        Some((cos, sin)) => {
                            let cos = &cos[(bi * l + li) * half..][..half];
                            let sin = &sin[(bi * l + li) * half..][..half];
                            let (d1, d2) = dst.split_at_mut(half);
                            let (s1, s2) = src.split_at(half);
                            for i in 0..half {
                                d1[i] = s1[i] * cos[i] - s2[i] * sin[i];
                                d2[i] = s1[i] * sin[i] + s2[i] * cos[i];
                            }
                        }
                    }
                }
            }
        }
    };
    let done = cpu_f32(x, |xs, _| match rope {
        None => {
            copy(xs, &mut out, None);
            Ok(Some(()))
        }
        Some((cos, sin)) => {
            let want = [b, l, half];
            if cos.dims() != want
                || sin.dims() != want
                || !cos.is_contiguous()
                || !sin.is_contiguous()
            {
                return Ok(None);
            }
            cpu_f32(cos, |cs, _| {
                cpu_f32(sin, |ss, _| {
                    copy(xs, &mut out, Some((cs, ss)));
                    Ok(())
                })
            })
            .map(|r| r.flatten())
        }
    })?;
    if done.flatten().is_none() {
        return Ok(None);
    }
    Ok(Some(Tensor::from_vec(out, (b, n, l, hd), &Device::Cpu)?))
}

/// A raw pointer that may cross threads (each task writes a disjoint part of the buffer).
#[derive(Clone, Copy)]
struct SendPtr(*mut f32);
// SAFETY: only used for disjoint writes, see `attention`.
unsafe impl Send for SendPtr {}
unsafe impl Sync for SendPtr {}

thread_local! {
    static SCORES: std::cell::RefCell<Vec<f32>> = const { std::cell::RefCell::new(Vec::new()) };
}

/// Masked attention `softmax(scale * q k^T + bias) v` with GQA, heads written straight into the
/// token-major output.
///
/// `q` [B, nH, L, hd] contiguous; `k`, `v` [B, nKV, T, hd] with contiguous rows (a narrow over T
/// is fine); `bias` [B, 1, L or 1, T] contiguous; query heads are kv-head-major (head `h` uses kv
/// head `h / (nH / nKV)`). Returns [B, L, nH * hd]. One task per (batch row, head), spread over
/// the threads; each runs two single-threaded gemms and the fused bias + softmax in between.
/// `arith`: [`Precision::Bf16`] runs both products with bf16 inputs (f32 accumulation, the
/// softmax in f32, as openpi's bf16 models do) where the CPU has native bf16 arithmetic
/// ([`super::packed::bf16_native`]); f32 elsewhere.
///
/// `prefix`: keys and values `0..prefix.keys()` already packed ([`PackedKv`], a KV cache's
/// prefix, packed once per observation); the kernel then packs only the keys after them and
/// reads the prefix's from the panels. Ignored where it does not fit (other shapes or
/// arithmetic) or where the packed kernel does not run.
pub fn attention(
    q: &Tensor,
    k: &Tensor,
    v: &Tensor,
    bias: &Tensor,
    scale: f32,
    arith: Precision,
    prefix: Option<&PackedKv>,
) -> Result<Option<Tensor>> {
    let (b, nh, l, hd) = q.dims4()?;
    let (kb, nkv, t, khd) = k.dims4()?;
    if kb != b
        || khd != hd
        || v.dims() != k.dims()
        || nkv == 0
        || nh % nkv != 0
        || !q.is_contiguous()
        || !bias.is_contiguous()
    {
        return Ok(None);
    }
    let (bb, b1, bl, bt) = bias.dims4()?;
    if bb != b || b1 != 1 || (bl != l && bl != 1) || bt != t {
        return Ok(None);
    }
    let (ks, vs) = (k.stride(), v.stride());
    if ks[3] != 1 || vs[3] != 1 {
        return Ok(None);
    }
    if let Some(arith) = packed_arith(arith) {
        return attention_packed(q, k, v, bias, scale, arith, prefix);
    }
    let (k_b, k_h, k_r) = (ks[0], ks[1], ks[2]);
    let (v_b, v_h, v_r) = (vs[0], vs[1], vs[2]);
    let g = nh / nkv;
    let width = nh * hd;
    let mut out = vec![0f32; b * l * width];
    let dst = SendPtr(out.as_mut_ptr());
    let done = cpu_f32(q, |qs, _| {
        cpu_f32(k, |kd, _| {
            cpu_f32(v, |vd, _| {
                cpu_f32(bias, |bs, _| {
                    let task = |i: usize| {
                        let (bi, h) = (i / nh, i % nh);
                        let kv = h / g;
                        let qp = &qs[(bi * nh + h) * l * hd..];
                        let kp = &kd[bi * k_b + kv * k_h..];
                        let vp = &vd[bi * v_b + kv * v_h..];
                        let brow = &bs[bi * bl * t..(bi + 1) * bl * t];
                        SCORES.with(|sc| {
                            let mut sc = sc.borrow_mut();
                            if sc.len() < l * t {
                                sc.resize(l * t, 0.0);
                            }
                            let s = &mut sc[..l * t];
                            // SAFETY: the operands hold the strided extents passed (checked
                            // dims / strides above), `s` is L x T, and the output block of task
                            // (bi, h) (rows of batch bi, columns h*hd..(h+1)*hd) is written by
                            // this task only.
                            unsafe {
                                gemm::gemm(
                                    l,
                                    t,
                                    hd,
                                    s.as_mut_ptr(),
                                    1,
                                    t as isize,
                                    false,
                                    qp.as_ptr(),
                                    1,
                                    hd as isize,
                                    kp.as_ptr(),
                                    k_r as isize,
                                    1,
                                    0.0,
                                    scale,
                                    false,
                                    false,
                                    false,
                                    gemm::Parallelism::None,
                                );
                            }
                            let mut inv = vec![0f32; l];
                            softmax_bias_rows(s, brow, t, 1.0, &mut inv);
                            let d = dst;
                            let c = d.0.wrapping_add(bi * l * width + h * hd);
                            // SAFETY: as above; `c` starts this task's output block (L rows of
                            // hd at stride `width`), which the product and the scaling alone touch.
                            unsafe {
                                gemm::gemm(
                                    l,
                                    hd,
                                    t,
                                    c,
                                    1,
                                    width as isize,
                                    false,
                                    s.as_ptr(),
                                    1,
                                    t as isize,
                                    vp.as_ptr(),
                                    1,
                                    v_r as isize,
                                    0.0,
                                    1.0,
                                    false,
                                    false,
                                    false,
                                    gemm::Parallelism::None,
                                );
                                scale_rows(c, l, hd, width, &inv);
                            }
                        });
                    };
                    if threads() > 1 && b * nh > 1 {
                        (0..b * nh).into_par_iter().for_each(task);
                    } else {
                        (0..b * nh).for_each(task);
                    }
                    Ok(())
                })
            })
        })
    })?;
    if done.flatten().flatten().flatten().is_none() {
        return Ok(None);
    }
    Ok(Some(Tensor::from_vec(out, (b, l, width), &Device::Cpu)?))
}

/// Query rows per attention task: a multiple of the packed kernel's register tile, small enough
/// that a block's scores stay in L2 (48 × 600 keys: 115 KB).
const ATT_ROWS: usize = 48;

/// How [`attention_packed`] splits a head's `l` query rows: `(blocks, rows per block)`, blocks of
/// at most [`ATT_ROWS`] rows, balanced, and in whole register tiles of `mr` rows where that adds
/// no block. A denoising step's 50 action tokens: 30 + 20 with AVX2's 6-row tile, 36 + 14 with
/// AVX-512's 12, not 25 + 25, whose two 1-row tiles cost ~4 % of an AVX2 call.
fn query_blocks(l: usize, mr: usize) -> (usize, usize) {
    let blocks = l.div_ceil(ATT_ROWS).max(1);
    let rows = l.div_ceil(blocks).max(1);
    let tiled = rows.next_multiple_of(mr.max(1));
    let rows = if tiled <= ATT_ROWS { tiled } else { rows };
    (l.div_ceil(rows).max(1), rows)
}

/// The arithmetic of [`attention`]'s packed kernel for the layer's `arith` (bf16 only where
/// the CPU has native bf16 products), `None` where the packed kernels do not run.
fn packed_arith(arith: Precision) -> Option<Precision> {
    if !(super::packed::support().f32_packed() && super::packed::enabled()) {
        return None;
    }
    let native = arith == Precision::Bf16 && super::packed::bf16_native();
    Some([Precision::F32, Precision::Bf16][native as usize])
}

/// Kᵀ [hd, n] and V [n, hd] of keys `from..from + n` of each (batch row, kv head) of `k`, `v`
/// [B, nKV, T, hd] (rows contiguous), packed for `arith` (K and V side by side on the threads);
/// `None` where they cannot be packed.
fn pack_heads(
    k: &Tensor,
    v: &Tensor,
    from: usize,
    n: usize,
    arith: Precision,
) -> Result<Option<Vec<(super::packed::PackedRhs, super::packed::PackedRhs)>>> {
    use super::packed::{PackedRhs, Stored};
    let (b, nkv, _, hd) = k.dims4()?;
    let (ks, vs) = (k.stride(), v.stride());
    let packed = cpu_f32(k, |kd, _| {
        cpu_f32(v, |vd, _| {
            let one = |i: usize| {
                let (bi, kv) = (i / nkv, i % nkv);
                let kp = kd.get(bi * ks[0] + kv * ks[1] + from * ks[2]..)?;
                let vp = vd.get(bi * vs[0] + kv * vs[1] + from * vs[2]..)?;
                match rayon::join(
                    || PackedRhs::pack_strided(hd, n, kp, ks[2], Stored::Cols, arith),
                    || PackedRhs::pack_strided(n, hd, vp, vs[2], Stored::Rows, arith),
                ) {
                    (Some(kt), Some(vv)) => Some((kt, vv)),
                    _ => None,
                }
            };
            Ok((0..b * nkv).map(one).collect::<Option<Vec<_>>>())
        })
    })?;
    Ok(packed.flatten().flatten())
}

/// One layer's keys and values over positions `0..keys` of a KV cache, packed once for
/// [`attention`]'s kernel. The denoising steps of a sample all attend to the same cached
/// prefix; with it packed per observation, a step packs only its own few keys.
#[derive(Debug, Clone)]
pub struct PackedKv {
    keys: usize,
    /// (batch, kv heads, head dim) of the cache it was packed from.
    dims: (usize, usize, usize),
    arith: Precision,
    /// Kᵀ [hd, keys] and V [keys, hd] of every (batch row, kv head).
    heads: Vec<(super::packed::PackedRhs, super::packed::PackedRhs)>,
}

impl PackedKv {
    /// Packs keys and values `0..keys` of `k`, `v` [B, nKV, T, hd] (rows contiguous) for an
    /// attention whose layer runs in `arith`. `None` where [`attention`]'s packed kernel does not
    /// run (not f32 CPU tensors, no packed kernel on this CPU, the kernels off) or the shapes do
    /// not allow it.
    pub fn pack(k: &Tensor, v: &Tensor, keys: usize, arith: Precision) -> Result<Option<Self>> {
        let Some(arith) = packed_arith(arith) else {
            return Ok(None);
        };
        let (b, nkv, t, hd) = k.dims4()?;
        if v.dims() != k.dims() || keys == 0 || keys > t || k.stride()[3] != 1 || v.stride()[3] != 1
        {
            return Ok(None);
        }
        Ok(pack_heads(k, v, 0, keys, arith)?.map(|heads| PackedKv {
            keys,
            dims: (b, nkv, hd),
            arith,
            heads,
        }))
    }

    /// Positions covered: `0..keys`.
    pub fn keys(&self) -> usize {
        self.keys
    }
}

/// [`attention`] on the packed f32 kernel: each kv head's Kᵀ and V are packed into panels once
/// (or taken from `prefix` for its keys) and shared by its query heads; tasks are (batch row,
/// head, block of [`ATT_ROWS`] queries), spread over the threads, each computing its scores,
/// the fused scale + bias + softmax, and its block of the output. Shapes as checked by
/// [`attention`].
fn attention_packed(
    q: &Tensor,
    k: &Tensor,
    v: &Tensor,
    bias: &Tensor,
    scale: f32,
    arith: Precision,
    prefix: Option<&PackedKv>,
) -> Result<Option<Tensor>> {
    let (b, nh, l, hd) = q.dims4()?;
    let (_, nkv, t, _) = k.dims4()?;
    let bl = bias.dim(2)?;
    let g = nh / nkv;
    let width = nh * hd;
    // the prefix's panels where they fit this call, then the keys after them packed here
    let prefix = prefix.filter(|p| p.dims == (b, nkv, hd) && p.keys <= t && p.arith == arith);
    let tp = prefix.map_or(0, |p| p.keys);
    let own = if tp < t {
        match pack_heads(k, v, tp, t - tp, arith)? {
            Some(h) => Some(h),
            None => return Ok(None),
        }
    } else {
        None
    };
    let mut out = vec![0f32; b * l * width];
    let dst = SendPtr(out.as_mut_ptr());
    let (blocks, per_block) = query_blocks(l, super::packed::tile_rows(arith));
    let tasks = b * nh * blocks;
    let done = cpu_f32(q, |qs, _| {
        cpu_f32(bias, |bs, _| {
            let task = |i: usize| {
                let (bi, rest) = (i / (nh * blocks), i % (nh * blocks));
                let (h, blk) = (rest / blocks, rest % blocks);
                let head = bi * nkv + h / g;
                let pre = prefix.map(|p| &p.heads[head]);
                let own = own.as_ref().map(|o| &o[head]);
                let r0 = blk * per_block;
                let rows = per_block.min(l - r0);
                let qp = &qs[((bi * nh + h) * l + r0) * hd..][..rows * hd];
                let brow = if bl == 1 {
                    &bs[bi * t..(bi + 1) * t]
                } else {
                    &bs[(bi * bl + r0) * t..(bi * bl + r0 + rows) * t]
                };
                SCORES.with(|sc| {
                    let mut fresh = Vec::new();
                    let mut guard = sc.try_borrow_mut();
                    let sc: &mut Vec<f32> = match guard.as_deref_mut() {
                        Ok(v) => v,
                        Err(_) => &mut fresh,
                    };
                    // the scores, then (with a prefix) the own keys' share of the output
                    let need = rows * t + if pre.is_some() { rows * hd } else { 0 };
                    if sc.len() < need {
                        sc.resize(need, 0.0);
                    }
                    let (s, part) = sc[..need].split_at_mut(rows * t);
                    if let Some((kt, _)) = pre {
                        kt.matmul_into(qp, rows, hd, s, t, 1);
                    }
                    if let Some((kt, _)) = own {
                        kt.matmul_into(qp, rows, hd, &mut s[tp..], t, 1);
                    }
                    let mut inv = [0f32; ATT_ROWS];
                    softmax_bias_rows(s, brow, t, scale, &mut inv[..rows]);
                    let d = dst;
                    // SAFETY: the output block of this task (rows r0.. of batch bi, columns
                    // h*hd..(h+1)*hd) lies inside `out` and is written by this task only.
                    unsafe {
                        let c = d.0.add((bi * l + r0) * width + h * hd);
                        match (pre, own) {
                            (Some((_, pv)), Some((_, ov))) => {
                                // P·V = P[:, ..tp]·V_prefix + P[:, tp..]·V_own
                                pv.matmul_ptr(s, rows, t, c, width, 1);
                                ov.matmul_into(&s[tp..], rows, t, part, hd, 1);
                                add_rows(c, rows, hd, width, part);
                            }
                            // all T keys in one set of panels
                            (Some((_, vv)), None) | (None, Some((_, vv))) => {
                                vv.matmul_ptr(s, rows, t, c, width, 1)
                            }
                            (None, None) => {}
                        }
                        scale_rows(c, rows, hd, width, &inv[..rows]);
                    }
                });
            };
            if threads() > 1 && tasks > 1 {
                (0..tasks).into_par_iter().for_each(task);
            } else {
                (0..tasks).for_each(task);
            }
            Ok(())
        })
    })?;
    if done.flatten().is_none() {
        return Ok(None);
    }
    Ok(Some(Tensor::from_vec(out, (b, l, width), &Device::Cpu)?))
}

#[cfg(test)]
mod tests;
