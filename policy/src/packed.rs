//! Matrix products against a right-hand side packed once: `y = x · W`, `x` [M, K] f32 row-major,
//! `W` [K, N] packed at load time (weights) or once per attention call (a layer's keys and
//! values, shared by every query head of a kv group).
//!
//! Why: the `gemm` crate behind candle's matmul repacks its right-hand side on every call. For a
//! denoising step (50 rows against 256..2048-wide weights) that repacking took 40 % of the step's
//! time on the 2-core AMD EPYC VM, more than the products themselves.
//!
//! Backends, picked at run time:
//! - `F32` on AVX-512F: `W` in panels of [`NR`] = 32 columns, [N/32][K][32] f32, and a 12 × 32
//!   register tile (24 zmm accumulators) of FMAs. Same precision as candle's matmul (only the
//!   summation order differs); the default.
//! - `F32` on AVX2 + FMA (no AVX-512: AMD Zen 1-3, Intel desktop parts): the same packing, each
//!   panel taken as two halves of 16 columns by a 6 × 16 register tile (12 ymm accumulators, two
//!   for the panel's row, one broadcast: 15 of the 16 ymm registers).
//! - `Bf16` on AVX512-BF16 (AMD Zen 4, Intel Cooper Lake and later): `W` rounded to bf16 once,
//!   in panels [N/32][K/2][32][2] (the pair order `vdpbf16ps` reads); `x` rounded per call;
//!   products accumulated in f32.
//! - `Amx`: bf16 on Intel AMX tiles ([`super::amx`]), preferred for bf16 where it runs.
//!
//! Without AVX-512 or AVX2 + FMA nothing is packed ([`PackedRhs::pack`] returns `None`) and
//! callers keep candle's matmul (the portable fallback; [`set_enabled`]`(false)` forces it).
//!
//! Blocking (GotoBLAS-style): the K dimension in blocks of [`KC_F32`] (f32) or [`KC_BF16`] (bf16)
//! values, so one panel's slice of `W` (32 KB) stays in L1 while every row block of `x` passes
//! over it, and `x`'s K-slice stays in L2 across the panels. Work is split by panels over the
//! threads; each thread owns its columns of `y`.

use candle_core::{DType, Device, Storage, Tensor};

use super::amx;

/// Columns per panel (two zmm registers of f32).
pub const NR: usize = 32;
/// Rows per register tile.
pub const MR: usize = 12;
/// Rows per register tile of the AVX2 kernel.
pub const MR_AVX2: usize = 6;
/// K block of the f32 kernel (values).
pub const KC_F32: usize = 256;
/// K block of the bf16 kernel (values; an even number).
pub const KC_BF16: usize = 512;

/// Arithmetic of the packed products.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Precision {
    /// f32 inputs and accumulation (the reference).
    F32,
    /// bf16 inputs (8 significant bits), f32 accumulation.
    Bf16,
}

/// Which kernels this CPU runs.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Support {
    /// AVX-512F (the f32 kernel).
    pub avx512: bool,
    /// AVX2 and FMA (the f32 kernel without AVX-512).
    pub avx2_fma: bool,
    /// AVX512-BF16 (`vdpbf16ps`).
    pub avx512_bf16: bool,
    /// AMX-BF16 with the kernel's permission ([`amx::available`]).
    pub amx: bool,
}

/// Environment variable that caps the instruction sets the CPU kernels use: `avx2` (as on a CPU
/// without AVX-512: AVX2 + FMA kernels, no bf16 backend) or `baseline` (neither: candle's
/// kernels and the portable small ops). To measure or test another CPU's paths on this one.
pub const ISA_ENV: &str = "CHUNKRT_CPU_ISA";

/// What this CPU supports (detected once), capped by [`ISA_ENV`].
pub fn support() -> Support {
    use std::sync::OnceLock;
    static S: OnceLock<Support> = OnceLock::new();
    *S.get_or_init(|| {
        let cap = std::env::var(ISA_ENV).unwrap_or_default();
        let detected = detect();
        match cap.as_str() {
            "avx2" => Support {
                avx2_fma: detected.avx2_fma,
                ..Support::NONE
            },
            "baseline" | "none" => Support::NONE,
            _ => detected,
        }
    })
}

fn detect() -> Support {
    #[cfg(target_arch = "x86_64")]
    {
        let avx512 = std::arch::is_x86_feature_detected!("avx512f");
        Support {
            avx512,
            avx2_fma: std::arch::is_x86_feature_detected!("avx2")
                && std::arch::is_x86_feature_detected!("fma"),
            avx512_bf16: avx512 && std::arch::is_x86_feature_detected!("avx512bf16"),
            amx: amx::available(),
        }
    }
    #[cfg(not(target_arch = "x86_64"))]
    {
        Support::NONE
    }
}

impl Support {
    /// No kernel at all.
    pub const NONE: Support = Support {
        avx512: false,
        avx2_fma: false,
        avx512_bf16: false,
        amx: false,
    };

    /// Some f32 kernel runs here (AVX-512F or AVX2 + FMA).
    pub fn f32_packed(&self) -> bool {
        self.avx512 || self.avx2_fma
    }

    /// Name of the f32 kernel in use: "avx-512", "avx2", or "none" (candle's matmul).
    pub fn f32_kernel(&self) -> &'static str {
        if self.avx512 && !AVX512_OFF.load(std::sync::atomic::Ordering::Relaxed) {
            "avx-512"
        } else if self.avx2_fma {
            "avx2"
        } else {
            "none"
        }
    }
}

static DISABLED: std::sync::atomic::AtomicBool = std::sync::atomic::AtomicBool::new(false);
static AVX512_OFF: std::sync::atomic::AtomicBool = std::sync::atomic::AtomicBool::new(false);

/// Runs the f32 products on the AVX2 kernel even where AVX-512 exists (`true`), for tests and
/// benchmarks of that path on an AVX-512 machine; both read the same packing. No effect on a
/// CPU without AVX2 + FMA.
pub fn force_avx2(on: bool) {
    AVX512_OFF.store(on, std::sync::atomic::Ordering::Relaxed);
}

fn use_avx512() -> bool {
    support().avx512 && !AVX512_OFF.load(std::sync::atomic::Ordering::Relaxed)
}

/// Turns the packed kernels off (`false`) or back on for the whole process: products against
/// packed weights and the packed attention then report `None` and callers run candle's matmul
/// and the `gemm` crate, as before these kernels existed. For benchmarks that measure that
/// baseline in the same run; the default is on.
pub fn set_enabled(on: bool) {
    DISABLED.store(!on, std::sync::atomic::Ordering::Relaxed);
}

/// Whether the packed kernels are in use ([`set_enabled`]).
pub fn enabled() -> bool {
    !DISABLED.load(std::sync::atomic::Ordering::Relaxed)
}

/// The bf16 backend this CPU would use: "amx", "avx512-bf16", or `None`.
pub fn bf16_backend() -> Option<&'static str> {
    let s = support();
    if s.amx {
        Some("amx")
    } else if s.avx512_bf16 {
        Some("avx512-bf16")
    } else {
        None
    }
}

#[derive(Debug, Clone)]
enum Data {
    /// [N/32][K][32].
    F32(Vec<f32>),
    /// [N/32][Kp/2][32][2], Kp = K rounded up to even.
    Bf16(Vec<u16>),
    Amx(amx::PackedWeight),
}

/// A right-hand side `W` [K, N] packed for one of the kernels.
#[derive(Debug, Clone)]
pub struct PackedRhs {
    k: usize,
    n: usize,
    data: Data,
    /// Added to every output row ([`Self::with_bias`]), in the kernel's first store.
    bias: Option<Vec<f32>>,
}

fn panels(n: usize) -> usize {
    n.div_ceil(NR)
}

impl PackedRhs {
    /// Packs `w(k, n)` [K, N] for `precision`; `None` when this CPU has no kernel for it.
    pub fn pack_with(
        k: usize,
        n: usize,
        precision: Precision,
        w: impl Fn(usize, usize) -> f32,
    ) -> Option<Self> {
        let s = support();
        let data = match precision {
            Precision::F32 if s.f32_packed() => {
                let mut d = vec![0f32; panels(n) * k * NR];
                for (p, panel) in d.chunks_exact_mut(k * NR).enumerate() {
                    for (kk, row) in panel.chunks_exact_mut(NR).enumerate() {
                        for (c, v) in row.iter_mut().enumerate() {
                            let col = p * NR + c;
                            if col < n {
                                *v = w(kk, col);
                            }
                        }
                    }
                }
                Data::F32(d)
            }
            Precision::Bf16 if s.amx => Data::Amx(amx::PackedWeight::pack(k, n, w)),
            Precision::Bf16 if s.avx512_bf16 => {
                let kp = k.div_ceil(2);
                let mut d = vec![0u16; panels(n) * kp * NR * 2];
                for (p, panel) in d.chunks_exact_mut(kp * NR * 2).enumerate() {
                    for (pair, row) in panel.chunks_exact_mut(NR * 2).enumerate() {
                        for c in 0..NR {
                            let col = p * NR + c;
                            for e in 0..2 {
                                let kk = 2 * pair + e;
                                if col < n && kk < k {
                                    row[2 * c + e] = amx::bf16(w(kk, col));
                                }
                            }
                        }
                    }
                }
                Data::Bf16(d)
            }
            _ => return None,
        };
        Some(PackedRhs {
            k,
            n,
            data,
            bias: None,
        })
    }

    /// The same product plus `bias` [N] on every row (a dense layer's bias, fused into the
    /// kernel's first store instead of a separate pass over the output).
    ///
    /// # Panics
    /// When `bias` does not have N values.
    pub fn with_bias(mut self, bias: Vec<f32>) -> Self {
        assert_eq!(
            bias.len(),
            self.n,
            "packed: bias of {} for N {}",
            bias.len(),
            self.n
        );
        self.bias = Some(bias);
        self
    }

    /// Packs a [K, N] tensor (any strides); `None` when this CPU has no kernel for `precision`,
    /// or the tensor is not an f32 tensor on the CPU (a GPU model keeps its weights where they
    /// are: nothing is copied to the host).
    pub fn pack(w: &Tensor, precision: Precision) -> candle_core::Result<Option<Self>> {
        if !w.device().is_cpu() || w.dtype() != DType::F32 {
            return Ok(None);
        }
        let (k, n) = w.dims2()?;
        let v = w
            .to_dtype(DType::F32)?
            .contiguous()?
            .flatten_all()?
            .to_vec1::<f32>()?;
        Ok(Self::pack_with(k, n, precision, |i, j| v[i * n + j]))
    }

    /// Packs a layer weight [N, K] (a `Linear`'s) as the [K, N] right-hand side.
    pub fn pack_weight(w: &Tensor, precision: Precision) -> candle_core::Result<Option<Self>> {
        Self::pack(&w.t()?, precision)
    }

    /// Inputs K.
    pub fn k(&self) -> usize {
        self.k
    }

    /// Outputs N.
    pub fn n(&self) -> usize {
        self.n
    }

    /// The arithmetic of this packing.
    pub fn precision(&self) -> Precision {
        match self.data {
            Data::F32(_) => Precision::F32,
            Data::Bf16(_) | Data::Amx(_) => Precision::Bf16,
        }
    }

    /// Bytes held.
    pub fn bytes(&self) -> usize {
        match &self.data {
            Data::F32(d) => d.len() * 4,
            Data::Bf16(d) => d.len() * 2,
            Data::Amx(w) => w.bytes(),
        }
    }

    /// `x` [.., K] (f32, on the CPU) · W → [.., N]; `None` when `x` does not fit (the caller
    /// falls back to candle).
    pub fn matmul(&self, x: &Tensor) -> candle_core::Result<Option<Tensor>> {
        if !enabled() || x.dtype() != DType::F32 || !x.device().is_cpu() {
            return Ok(None);
        }
        let dims = x.dims().to_vec();
        if dims.last() != Some(&self.k) || self.k == 0 {
            return Ok(None);
        }
        let m = x.elem_count() / self.k;
        let x = x.contiguous()?;
        let out = {
            let (st, layout) = x.storage_and_layout();
            let Storage::Cpu(cpu) = &*st else {
                return Ok(None);
            };
            let Some((lo, hi)) = layout.contiguous_offsets() else {
                return Ok(None);
            };
            let data = &cpu.as_slice::<f32>()?[lo..hi];
            let mut out = vec![0f32; m * self.n];
            self.matmul_into(
                data,
                m,
                self.k,
                &mut out,
                self.n,
                auto_threads(m, self.k, self.n),
            );
            out
        };
        let mut shape = dims;
        if let Some(last) = shape.last_mut() {
            *last = self.n;
        }
        Ok(Some(Tensor::from_vec(out, shape, &Device::Cpu)?))
    }

    /// `c` [m, ldc] ← `a` [m, lda] (first K columns) · W, into columns 0..N of `c`, on `threads`
    /// workers (rayon's pool).
    ///
    /// # Panics
    /// When the slices are shorter than the shapes say.
    pub fn matmul_into(
        &self,
        a: &[f32],
        m: usize,
        lda: usize,
        c: &mut [f32],
        ldc: usize,
        threads: usize,
    ) {
        if m == 0 || self.n == 0 {
            return;
        }
        assert!(
            ldc >= self.n && c.len() >= (m - 1) * ldc + self.n,
            "packed: c too short"
        );
        // SAFETY: `c` holds the m rows of ldc (checked), and `&mut` makes it exclusive.
        unsafe { self.matmul_ptr(a, m, lda, c.as_mut_ptr(), ldc, threads) }
    }

    /// [`Self::matmul_into`] writing through a raw pointer, for callers whose threads fill
    /// interleaved blocks of one output (attention heads).
    ///
    /// # Safety
    /// `c` must be valid for writes of rows `0..m` × columns `0..N` at row stride `ldc`, and no
    /// one else may access those elements during the call.
    ///
    /// # Panics
    /// When `a` is shorter than the shape says.
    pub unsafe fn matmul_ptr(
        &self,
        a: &[f32],
        m: usize,
        lda: usize,
        c: *mut f32,
        ldc: usize,
        threads: usize,
    ) {
        if m == 0 || self.n == 0 {
            return;
        }
        assert!(
            lda >= self.k && a.len() >= (m - 1) * lda + self.k,
            "packed: a too short"
        );
        let job = |a: *const f32, lda: usize, b: *const u8| Job {
            a,
            lda,
            m,
            k: self.k,
            n: self.n,
            b,
            c,
            ldc,
            bias: self.bias.as_ref().map_or(std::ptr::null(), |b| b.as_ptr()),
        };
        match &self.data {
            Data::F32(d) => {
                let job = job(a.as_ptr(), lda, d.as_ptr() as *const u8);
                let wide = use_avx512();
                split_panels(job, threads, |j, r| {
                    // SAFETY: `pack_with` builds F32 data only where AVX-512F or AVX2 + FMA
                    // runs, and `wide` picks AVX-512 only where it runs; the job's pointers
                    // cover the shapes (asserted, and the caller's contract for `c`); the panel
                    // ranges are disjoint.
                    unsafe {
                        if wide {
                            x86::f32_panels(j, r)
                        } else {
                            x86::f32_panels_avx2(j, r)
                        }
                    }
                });
            }
            Data::Bf16(d) => {
                // x rounded to bf16 once, rows padded to an even K
                let kp2 = self.k.div_ceil(2) * 2;
                A_BF16.with(|buf| {
                    let mut fresh = Vec::new();
                    let mut guard = buf.try_borrow_mut();
                    let abuf: &mut Vec<u16> = match guard.as_deref_mut() {
                        Ok(v) => v,
                        Err(_) => &mut fresh,
                    };
                    abuf.clear();
                    abuf.resize(m * kp2, 0);
                    for (r, row) in abuf.chunks_exact_mut(kp2).enumerate() {
                        for (d, &v) in row.iter_mut().zip(&a[r * lda..r * lda + self.k]) {
                            *d = amx::bf16(v);
                        }
                    }
                    let job = job(
                        abuf.as_ptr() as *const f32,
                        kp2 / 2,
                        d.as_ptr() as *const u8,
                    );
                    split_panels(job, threads, |j, r| {
                        // SAFETY: Bf16 data exists only where AVX512-BF16 runs; as above.
                        unsafe { x86::bf16_panels(j, r) }
                    });
                });
            }
            Data::Amx(w) => {
                let mut packed = Vec::with_capacity(m * self.k);
                for r in 0..m {
                    packed.extend_from_slice(&a[r * lda..r * lda + self.k]);
                }
                let mut out = Vec::new();
                if amx::matmul_with(&packed, m, w, &mut out, threads) {
                    for r in 0..m {
                        // SAFETY: row r of `c` has N writable elements (the caller's contract).
                        let dst = unsafe { std::slice::from_raw_parts_mut(c.add(r * ldc), self.n) };
                        dst.copy_from_slice(&out[r * self.n..(r + 1) * self.n]);
                        if let Some(b) = &self.bias {
                            for (d, b) in dst.iter_mut().zip(b) {
                                *d += b;
                            }
                        }
                    }
                }
            }
        }
    }
}

thread_local! {
    /// bf16 copy of the left-hand side, reused across calls on this thread.
    static A_BF16: std::cell::RefCell<Vec<u16>> = const { std::cell::RefCell::new(Vec::new()) };
}

/// Threads worth using for an [m, k] · [k, n] product: one below about a million
/// multiply-adds (a hand-off to the pool costs more than it saves), else rayon's pool.
pub fn auto_threads(m: usize, k: usize, n: usize) -> usize {
    if m * k * n < 1 << 20 {
        1
    } else {
        rayon::current_num_threads().max(1)
    }
}

/// One product's operands as raw pointers, shared by the workers (each writes its own panels'
/// columns of `c`). For bf16, `a` points to bf16 pairs and `lda` counts pairs.
#[derive(Clone, Copy)]
struct Job {
    a: *const f32,
    lda: usize,
    m: usize,
    k: usize,
    n: usize,
    b: *const u8,
    c: *mut f32,
    ldc: usize,
    /// [N] added to every row, or null.
    bias: *const f32,
}
// SAFETY: the buffers outlive the workers (scoped), and workers write disjoint columns of `c`.
unsafe impl Send for Job {}
unsafe impl Sync for Job {}

/// Runs `f` over the panels split into `threads` contiguous ranges (the calling thread takes
/// the first).
fn split_panels(job: Job, threads: usize, f: impl Fn(Job, std::ops::Range<usize>) + Sync) {
    let np = panels(job.n);
    let t = threads.clamp(1, np);
    if t == 1 {
        f(job, 0..np);
        return;
    }
    let per = np.div_ceil(t);
    rayon::scope(|s| {
        for i in 1..t {
            let r = (i * per).min(np)..((i + 1) * per).min(np);
            let f = &f;
            s.spawn(move |_| f(job, r));
        }
        f(job, 0..per.min(np));
    });
}

#[cfg(target_arch = "x86_64")]
mod x86 {
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
                let av: __m512bh =
                    std::mem::transmute(_mm512_set1_epi32(*a.add(i * lda + p) as i32));
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
        ($f:ident, $r:expr, $($arg:expr),*) => {
            match $r {
                12 => $f::<12>($($arg),*),
                11 => $f::<11>($($arg),*),
                10 => $f::<10>($($arg),*),
                9 => $f::<9>($($arg),*),
                8 => $f::<8>($($arg),*),
                7 => $f::<7>($($arg),*),
                6 => $f::<6>($($arg),*),
                5 => $f::<5>($($arg),*),
                4 => $f::<4>($($arg),*),
                3 => $f::<3>($($arg),*),
                2 => $f::<2>($($arg),*),
                _ => $f::<1>($($arg),*),
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

    /// `R` rows × 16 columns (half a panel: `b` at the half's first column, rows [`NR`] apart)
    /// over `kc` values of K, with AVX2 + FMA.
    #[target_feature(enable = "avx2,fma")]
    #[inline]
    #[allow(clippy::too_many_arguments)]
    unsafe fn tile_f32_avx2<const R: usize>(
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
        let mut acc0 = [_mm256_setzero_ps(); R];
        let mut acc1 = [_mm256_setzero_ps(); R];
        for p in 0..kc {
            let b0 = _mm256_loadu_ps(b.add(p * NR));
            let b1 = _mm256_loadu_ps(b.add(p * NR + 8));
            for i in 0..R {
                let av = _mm256_broadcast_ss(&*a.add(i * lda + p));
                acc0[i] = _mm256_fmadd_ps(av, b0, acc0[i]);
                acc1[i] = _mm256_fmadd_ps(av, b1, acc1[i]);
            }
        }
        store_avx2(&acc0, &acc1, c, ldc, ncols, first, bias);
    }

    /// The f32 product for the panels `r` with AVX2 + FMA (the same packing as the AVX-512
    /// kernel; each panel as two halves of 16 columns).
    ///
    /// # Safety
    /// AVX2 and FMA; `j.b` points to f32 panels [N/32][K][32]; the pointers cover the shapes.
    #[target_feature(enable = "avx2,fma")]
    pub(super) unsafe fn f32_panels_avx2(j: Job, r: std::ops::Range<usize>) {
        let b = j.b as *const f32;
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
                            tile_f32_avx2,
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
}

#[cfg(not(target_arch = "x86_64"))]
mod x86 {
    use super::Job;
    pub(super) unsafe fn f32_panels(_: Job, _: std::ops::Range<usize>) {}
    pub(super) unsafe fn f32_panels_avx2(_: Job, _: std::ops::Range<usize>) {}
    pub(super) unsafe fn bf16_panels(_: Job, _: std::ops::Range<usize>) {}
}

#[cfg(test)]
mod tests {
    use super::amx::tests::lcg;
    use super::*;

    /// Odd sizes (tails in every dimension, several K blocks, row strides) against an f64
    /// product; for bf16, of the bf16-rounded inputs.
    #[test]
    fn packed_products_match_a_reference() {
        let s = support();
        // the AVX-512 kernel where it runs, and the AVX2 one (forced there, the only one elsewhere)
        for (prec, avx2) in [
            (Precision::F32, false),
            (Precision::F32, true),
            (Precision::Bf16, false),
        ] {
            if avx2 && !s.avx2_fma {
                continue;
            }
            force_avx2(avx2);
            for &(m, k, n, lda, ldc, threads) in &[
                (1, 3, 5, 3, 5, 1),
                (13, 37, 33, 40, 35, 2),
                (50, 600, 70, 600, 70, 2),
                (7, 300, 48, 300, 50, 1),
                (9, 257, 20, 260, 21, 2),
                (25, 1030, 64, 1030, 64, 1),
            ] {
                let mut r = lcg((m * k * n) as u64);
                let a: Vec<f32> = (0..m * lda).map(|_| r()).collect();
                let w: Vec<f32> = (0..k * n).map(|_| r()).collect();
                let Some(p) = PackedRhs::pack_with(k, n, prec, |i, j| w[i * n + j]) else {
                    eprintln!("{prec:?}: no kernel on this CPU ({s:?}): skipped");
                    continue;
                };
                // every other case with a bias
                let bias: Vec<f32> = (0..n).map(|j| (j as f32) * 0.25 - 1.0).collect();
                let with_bias = m % 2 == 1;
                let p = if with_bias {
                    p.with_bias(bias.clone())
                } else {
                    p
                };
                let mut c = vec![7f32; m * ldc];
                p.matmul_into(&a, m, lda, &mut c, ldc, threads);
                let round = |v: f32| match prec {
                    Precision::F32 => v as f64,
                    Precision::Bf16 => amx::f32_of(amx::bf16(v)) as f64,
                };
                let mut worst = 0f64;
                for i in 0..m {
                    for jj in 0..n {
                        let want: f64 = (0..k)
                            .map(|l| round(a[i * lda + l]) * round(w[l * n + jj]))
                            .sum::<f64>()
                            + if with_bias { bias[jj] as f64 } else { 0.0 };
                        worst = worst.max((c[i * ldc + jj] as f64 - want).abs());
                    }
                    // columns past N untouched
                    for jj in n..ldc {
                        assert_eq!(c[i * ldc + jj], 7.0);
                    }
                }
                assert!(
                    worst < 2e-6 * k as f64,
                    "{prec:?} (avx2 {avx2}) {m}x{k}x{n}: max error {worst}"
                );
            }
            force_avx2(false);
        }
    }

    #[test]
    fn tensor_products_match_candle() {
        let dev = Device::Cpu;
        let x = Tensor::randn(0f32, 1f32, (2, 9, 48), &dev).unwrap();
        let w = Tensor::randn(0f32, 1f32, (40, 48), &dev).unwrap(); // [N, K]
        let Some(p) = PackedRhs::pack_weight(&w, Precision::F32).unwrap() else {
            eprintln!("no AVX-512: skipped");
            return;
        };
        let got = p.matmul(&x).unwrap().unwrap();
        let want = x.broadcast_matmul(&w.t().unwrap()).unwrap();
        let d = (got - want)
            .unwrap()
            .abs()
            .unwrap()
            .max_all()
            .unwrap()
            .to_scalar::<f32>()
            .unwrap();
        assert!(d < 1e-4, "{d}");
    }
}
