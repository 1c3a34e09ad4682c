//! The x86-64 micro-kernels of `packed` (AVX-512 and AVX2 + FMA register tiles), picked at run
//! time by the parent module.
use super::{Job, KC_BF16, KC_F32, MR, MR_AVX2, NR};
use std::arch::x86_64::*;

/// Column masks of the two zmm halves of a panel with `ncols` valid columns.
#[inline(always)]
fn masks(ncols: usize) -> (u16, u16) {
    let lo = if ncols >= 16 {
        0xffff
    } else {
        ((1u32 << ncols) - 1) as u16
    };
    let hi = if ncols >= 32 {
        0xffff
    } else if ncols > 16 {
        ((1u32 << (ncols - 16)) - 1) as u16
    } else {
        0
    };
    (lo, hi)
}

/// Stores (or adds into) the `R` × 32 tile at `c`; the first K block adds `bias` (the
/// panel's 32 values, or null).
#[inline(always)]
#[allow(clippy::too_many_arguments)]
unsafe fn store<const R: usize>(
    acc0: &[__m512; R],
    acc1: &[__m512; R],
    c: *mut f32,
    ldc: usize,
    ncols: usize,
    first: bool,
    bias: *const f32,
) {
    let (m0, m1) = masks(ncols);
    let (b0, b1) = if first && !bias.is_null() {
        (
            _mm512_maskz_loadu_ps(m0, bias),
            _mm512_maskz_loadu_ps(m1, bias.add(16)),
        )
    } else {
        (_mm512_setzero_ps(), _mm512_setzero_ps())
    };
    for i in 0..R {
        let cp = c.add(i * ldc);
        let (mut r0, mut r1) = (acc0[i], acc1[i]);
        if first {
            r0 = _mm512_add_ps(r0, b0);
            r1 = _mm512_add_ps(r1, b1);
        } else {
            r0 = _mm512_add_ps(r0, _mm512_maskz_loadu_ps(m0, cp));
            r1 = _mm512_add_ps(r1, _mm512_maskz_loadu_ps(m1, cp.add(16)));
        }
        _mm512_mask_storeu_ps(cp, m0, r0);
        _mm512_mask_storeu_ps(cp.add(16), m1, r1);
    }
}

/// `R` rows × 32 columns over `kc` values of K: `b` the panel's rows, `a` row-major.
#[target_feature(enable = "avx512f")]
#[inline]
#[allow(clippy::too_many_arguments)]
unsafe fn tile_f32<const R: usize>(
    kc: usize,
    a: *const f32,
    lda: usize,
    b: *const f32,
    c: *mut f32,
    ldc: usize,
    ncols: usize,
    first: bool,
    bias: *const f32,
) {
    let mut acc0 = [_mm512_setzero_ps(); R];
    let mut acc1 = [_mm512_setzero_ps(); R];
    for p in 0..kc {
        let b0 = _mm512_loadu_ps(b.add(p * NR));
        let b1 = _mm512_loadu_ps(b.add(p * NR + 16));
        for i in 0..R {
            let av = _mm512_set1_ps(*a.add(i * lda + p));
            acc0[i] = _mm512_fmadd_ps(av, b0, acc0[i]);
            acc1[i] = _mm512_fmadd_ps(av, b1, acc1[i]);
        }
    }
    store(&acc0, &acc1, c, ldc, ncols, first, bias);
}

/// `R` rows × 32 columns over `kp` pairs of K in bf16: `a` bf16 pairs, row-major.
#[target_feature(enable = "avx512f,avx512bf16")]
#[inline]
#[allow(clippy::too_many_arguments)]
unsafe fn tile_bf16<const R: usize>(
    kp: usize,
    a: *const u32,
    lda: usize,
    b: *const u16,
    c: *mut f32,
    ldc: usize,
    ncols: usize,
    first: bool,
    bias: *const f32,
) {
    let mut acc0 = [_mm512_setzero_ps(); R];
    let mut acc1 = [_mm512_setzero_ps(); R];
    for p in 0..kp {
        let b0: __m512bh = std::mem::transmute(_mm512_loadu_si512(b.add(p * 2 * NR) as _));
        let b1: __m512bh = std::mem::transmute(_mm512_loadu_si512(b.add(p * 2 * NR + NR) as _));
        for i in 0..R {
            let av: __m512bh = std::mem::transmute(_mm512_set1_epi32(*a.add(i * lda + p) as i32));
            acc0[i] = _mm512_dpbf16_ps(acc0[i], av, b0);
            acc1[i] = _mm512_dpbf16_ps(acc1[i], av, b1);
        }
    }
    store(&acc0, &acc1, c, ldc, ncols, first, bias);
}

/// The bias values of panel `p`, or null.
#[inline(always)]
unsafe fn panel_bias(j: &Job, p: usize) -> *const f32 {
    if j.bias.is_null() {
        j.bias
    } else {
        j.bias.add(p * NR)
    }
}

macro_rules! dispatch_rows {
    ($f:ident $(<$t:ty>)?, $r:expr, $($arg:expr),*) => {
        match $r {
            12 => $f::<$($t,)? 12>($($arg),*),
            11 => $f::<$($t,)? 11>($($arg),*),
            10 => $f::<$($t,)? 10>($($arg),*),
            9 => $f::<$($t,)? 9>($($arg),*),
            8 => $f::<$($t,)? 8>($($arg),*),
            7 => $f::<$($t,)? 7>($($arg),*),
            6 => $f::<$($t,)? 6>($($arg),*),
            5 => $f::<$($t,)? 5>($($arg),*),
            4 => $f::<$($t,)? 4>($($arg),*),
            3 => $f::<$($t,)? 3>($($arg),*),
            2 => $f::<$($t,)? 2>($($arg),*),
            _ => $f::<$($t,)? 1>($($arg),*),
        }
    };
}

/// The f32 product for the panels `r`.
///
/// # Safety
/// AVX-512F; `j.b` points to f32 panels [N/32][K][32]; the pointers cover the shapes.
#[target_feature(enable = "avx512f")]
pub(super) unsafe fn f32_panels(j: Job, r: std::ops::Range<usize>) {
    let b = j.b as *const f32;
    let mut k0 = 0;
    while k0 < j.k {
        let kc = KC_F32.min(j.k - k0);
        for p in r.clone() {
            let bp = b.add(p * j.k * NR + k0 * NR);
            let ncols = NR.min(j.n - p * NR);
            let mut m0 = 0;
            while m0 < j.m {
                let rows = MR.min(j.m - m0);
                let a = j.a.add(m0 * j.lda + k0);
                let c = j.c.add(m0 * j.ldc + p * NR);
                dispatch_rows!(
                    tile_f32,
                    rows,
                    kc,
                    a,
                    j.lda,
                    bp,
                    c,
                    j.ldc,
                    ncols,
                    k0 == 0,
                    panel_bias(&j, p)
                );
                m0 += rows;
            }
        }
        k0 += kc;
    }
}

/// Stores (or adds into) the `R` × 16 tile at `c` with `ncols` (1..=16) valid columns; the
/// first K block adds `bias` (the half panel's values, or null).
#[inline(always)]
#[allow(clippy::too_many_arguments)]
unsafe fn store_avx2<const R: usize>(
    acc0: &[__m256; R],
    acc1: &[__m256; R],
    c: *mut f32,
    ldc: usize,
    ncols: usize,
    first: bool,
    bias: *const f32,
) {
    let mut bt = [0f32; 16];
    if first && !bias.is_null() {
        std::ptr::copy_nonoverlapping(bias, bt.as_mut_ptr(), ncols);
    }
    let (b0, b1) = (
        _mm256_loadu_ps(bt.as_ptr()),
        _mm256_loadu_ps(bt.as_ptr().add(8)),
    );
    for i in 0..R {
        let cp = c.add(i * ldc);
        let (mut r0, mut r1) = (acc0[i], acc1[i]);
        if ncols == 16 {
            if first {
                r0 = _mm256_add_ps(r0, b0);
                r1 = _mm256_add_ps(r1, b1);
            } else {
                r0 = _mm256_add_ps(r0, _mm256_loadu_ps(cp));
                r1 = _mm256_add_ps(r1, _mm256_loadu_ps(cp.add(8)));
            }
            _mm256_storeu_ps(cp, r0);
            _mm256_storeu_ps(cp.add(8), r1);
        } else {
            // a ragged last panel: through a small buffer, never past column N
            let mut t = [0f32; 16];
            _mm256_storeu_ps(t.as_mut_ptr(), r0);
            _mm256_storeu_ps(t.as_mut_ptr().add(8), r1);
            for (jj, v) in t.iter().enumerate().take(ncols) {
                let base = if first { bt[jj] } else { *cp.add(jj) };
                *cp.add(jj) = v + base;
            }
        }
    }
}

/// An element of the AVX2 kernel's weight panels: f32, or bf16 widened to f32 as it is loaded
/// (a bf16 is the high half of an f32).
trait PanelElem: Copy {
    /// Eight consecutive values at `p` as f32.
    unsafe fn load8(p: *const Self) -> __m256;
}

impl PanelElem for f32 {
    #[inline(always)]
    unsafe fn load8(p: *const f32) -> __m256 {
        _mm256_loadu_ps(p)
    }
}

impl PanelElem for u16 {
    #[inline(always)]
    unsafe fn load8(p: *const u16) -> __m256 {
        let h = _mm_loadu_si128(p as *const __m128i);
        _mm256_castsi256_ps(_mm256_slli_epi32::<16>(_mm256_cvtepu16_epi32(h)))
    }
}

/// `R` rows × 16 columns (half a panel: `b` at the half's first column, rows [`NR`] apart)
/// over `kc` values of K, with AVX2 + FMA.
#[target_feature(enable = "avx2,fma")]
#[inline]
#[allow(clippy::too_many_arguments)]
unsafe fn tile_avx2<T: PanelElem, const R: usize>(
    kc: usize,
    a: *const f32,
    lda: usize,
    b: *const T,
    c: *mut f32,
    ldc: usize,
    ncols: usize,
    first: bool,
    bias: *const f32,
) {
    let mut acc0 = [_mm256_setzero_ps(); R];
    let mut acc1 = [_mm256_setzero_ps(); R];
    for p in 0..kc {
        let b0 = T::load8(b.add(p * NR));
        let b1 = T::load8(b.add(p * NR + 8));
        for i in 0..R {
            let av = _mm256_broadcast_ss(&*a.add(i * lda + p));
            acc0[i] = _mm256_fmadd_ps(av, b0, acc0[i]);
            acc1[i] = _mm256_fmadd_ps(av, b1, acc1[i]);
        }
    }
    store_avx2(&acc0, &acc1, c, ldc, ncols, first, bias);
}

/// The product for the panels `r` with AVX2 + FMA over weight panels [N/32][K][32] of `T`
/// (the AVX-512 kernel's f32 packing, or its bf16 copy); each panel as two halves of 16
/// columns.
#[target_feature(enable = "avx2,fma")]
unsafe fn panels_avx2<T: PanelElem>(j: Job, r: std::ops::Range<usize>) {
    let b = j.b as *const T;
    let mut k0 = 0;
    while k0 < j.k {
        let kc = KC_F32.min(j.k - k0);
        for p in r.clone() {
            let ncols = NR.min(j.n - p * NR);
            for half in 0..2 {
                let cols = ncols.saturating_sub(16 * half).min(16);
                if cols == 0 {
                    break;
                }
                let bp = b.add(p * j.k * NR + k0 * NR + 16 * half);
                let bias = panel_bias(&j, p);
                let bias = if bias.is_null() {
                    bias
                } else {
                    bias.add(16 * half)
                };
                let mut m0 = 0;
                while m0 < j.m {
                    let rows = MR_AVX2.min(j.m - m0);
                    let a = j.a.add(m0 * j.lda + k0);
                    let c = j.c.add(m0 * j.ldc + p * NR + 16 * half);
                    dispatch_rows!(
                        tile_avx2<T>,
                        rows,
                        kc,
                        a,
                        j.lda,
                        bp,
                        c,
                        j.ldc,
                        cols,
                        k0 == 0,
                        bias
                    );
                    m0 += rows;
                }
            }
        }
        k0 += kc;
    }
}

/// The f32 product for the panels `r` with AVX2 + FMA (the same packing as the AVX-512
/// kernel).
///
/// # Safety
/// AVX2 and FMA; `j.b` points to f32 panels [N/32][K][32]; the pointers cover the shapes.
#[target_feature(enable = "avx2,fma")]
pub(super) unsafe fn f32_panels_avx2(j: Job, r: std::ops::Range<usize>) {
    panels_avx2::<f32>(j, r)
}

/// The product against bf16 weights for the panels `r` with AVX2 + FMA: `x` in f32, the
/// weights widened to f32 in the kernel.
///
/// # Safety
/// AVX2 and FMA; `j.a` points to f32 rows, `j.b` to bf16 panels [N/32][K][32]; the pointers
/// cover the shapes.
#[target_feature(enable = "avx2,fma")]
pub(super) unsafe fn bf16w_panels_avx2(j: Job, r: std::ops::Range<usize>) {
    panels_avx2::<u16>(j, r)
}

/// The bf16 product for the panels `r`.
///
/// # Safety
/// AVX512-BF16; `j.a` points to bf16 pairs [M][lda], `j.b` to bf16 panels
/// [N/32][Kp/2][32][2]; the pointers cover the shapes.
#[target_feature(enable = "avx512f,avx512bf16")]
pub(super) unsafe fn bf16_panels(j: Job, r: std::ops::Range<usize>) {
    let b = j.b as *const u16;
    let a = j.a as *const u32;
    let pairs = j.k.div_ceil(2);
    let mut q0 = 0;
    while q0 < pairs {
        let qc = (KC_BF16 / 2).min(pairs - q0);
        for p in r.clone() {
            let bp = b.add((p * pairs + q0) * 2 * NR);
            let ncols = NR.min(j.n - p * NR);
            let mut m0 = 0;
            while m0 < j.m {
                let rows = MR.min(j.m - m0);
                let ap = a.add(m0 * j.lda + q0);
                let c = j.c.add(m0 * j.ldc + p * NR);
                dispatch_rows!(
                    tile_bf16,
                    rows,
                    qc,
                    ap,
                    j.lda,
                    bp,
                    c,
                    j.ldc,
                    ncols,
                    q0 == 0,
                    panel_bias(&j, p)
                );
                m0 += rows;
            }
        }
        q0 += qc;
    }
}
