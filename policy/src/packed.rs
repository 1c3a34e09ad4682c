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
//! - `Bf16Wide` on AVX2 + FMA (bf16 without AVX512-BF16): `W` rounded to bf16 once, in the f32
//!   panel layout [N/32][K][32] at half the bytes, widened to f32 in the kernel (two shifts per
//!   16 values); `x` stays f32, products in f32. The AVX2 f32 tile otherwise.
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

/// Held by the unit tests that flip [`force_avx2`] and by those whose checks need one kernel
/// choice for their whole run: the choice is process-wide and the test harness runs tests on
/// parallel threads (a flip between two calls of the attention test once compared an
/// AVX512-BF16 result with an f32 one).
#[cfg(test)]
pub(crate) fn kernel_choice_lock() -> std::sync::MutexGuard<'static, ()> {
    static LOCK: std::sync::Mutex<()> = std::sync::Mutex::new(());
    // a failed test poisons it; the next one still needs the exclusion, not the state
    LOCK.lock().unwrap_or_else(|e| e.into_inner())
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

/// The bf16 backend this CPU would use: "amx", "avx512-bf16", "avx2, bf16 weights" (the
/// weights in bf16, widened to f32 in the kernel), or `None`.
pub fn bf16_backend() -> Option<&'static str> {
    let s = support();
    let wide = use_avx512();
    if s.amx && wide {
        Some("amx")
    } else if s.avx512_bf16 && wide {
        Some("avx512-bf16")
    } else if s.avx2_fma {
        Some("avx2, bf16 weights")
    } else {
        None
    }
}

/// Rows of the register tile the packed products run for `arith` on this CPU (the AVX-512
/// and AVX512-BF16 kernels' 12, AVX2's 6).
pub fn tile_rows(arith: Precision) -> usize {
    if use_avx512() || (arith == Precision::Bf16 && bf16_native()) {
        MR
    } else {
        MR_AVX2
    }
}

/// Whether bf16 products run on native bf16 arithmetic here (AMX or AVX512-BF16), not on
/// bf16 weights widened to f32: only then do bf16 activations (the attention's) pay off.
pub fn bf16_native() -> bool {
    matches!(bf16_backend(), Some("amx" | "avx512-bf16"))
}

#[derive(Debug, Clone)]
enum Data {
    /// [N/32][K][32].
    F32(Vec<f32>),
    /// [N/32][Kp/2][32][2], Kp = K rounded up to even.
    Bf16(Vec<u16>),
    Amx(amx::PackedWeight),
    /// [N/32][K][32] bf16, widened to f32 by the AVX2 kernel.
    Bf16Wide(Vec<u16>),
}

/// How a right-hand side `W` [K, N] lies in memory ([`PackedRhs::pack_strided`]).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Stored {
    /// `W[k][n]` at `src[k * ld + n]`.
    Rows,
    /// `W[k][n]` at `src[n * ld + k]`.
    Cols,
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

/// `w(k, n)` [K, N] in panels [N/32][K][32] (zero past column N): the f32 kernels' layout,
/// in f32 or in bf16.
fn panel_layout<T: Copy + Default>(k: usize, n: usize, w: &impl Fn(usize, usize) -> T) -> Vec<T> {
    let mut d = vec![T::default(); panels(n) * k * NR];
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
    d
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
            Precision::F32 if s.f32_packed() => Data::F32(panel_layout(k, n, &w)),
            Precision::Bf16 if s.amx && use_avx512() => Data::Amx(amx::PackedWeight::pack(k, n, w)),
            Precision::Bf16 if s.avx512_bf16 && use_avx512() => {
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
            Precision::Bf16 if s.avx2_fma => {
                Data::Bf16Wide(panel_layout(k, n, &|kk, col| amx::bf16(w(kk, col))))
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

    /// Packs `W` [K, N] read from `src` with stride `ld` as `stored` says (an attention's V
    /// [T, hd] by rows with T as K, its Kᵀ [hd, T] by columns from K [T, hd]) for `precision`
    /// (f32: straight copies; bf16: through [`Self::pack_with`]). `None` when this CPU has no kernel for it, or `src` is
    /// shorter than the extent.
    pub fn pack_strided(
        k: usize,
        n: usize,
        src: &[f32],
        ld: usize,
        stored: Stored,
        precision: Precision,
    ) -> Option<Self> {
        let (outer, inner) = match stored {
            Stored::Rows => (k, n),
            Stored::Cols => (n, k),
        };
        if outer > 0 && inner > 0 && src.len() < (outer - 1) * ld + inner {
            return None;
        }
        let at = |kk: usize, col: usize| match stored {
            Stored::Rows => kk * ld + col,
            Stored::Cols => col * ld + kk,
        };
        if precision != Precision::F32 || !support().f32_packed() {
            // the bf16 layouts (one conversion per value dominates): through the closure
            return Self::pack_with(k, n, precision, |kk, col| src[at(kk, col)]);
        }
        // the f32 panels [N/32][K][32], each row (column) of `src` read once, contiguously
        let mut d = vec![0f32; panels(n) * k * NR];
        for (p, panel) in d.chunks_exact_mut(k * NR).enumerate() {
            let w = NR.min(n - p * NR);
            match stored {
                Stored::Rows => {
                    for (kk, row) in panel.chunks_exact_mut(NR).enumerate() {
                        let i = at(kk, p * NR);
                        row[..w].copy_from_slice(&src[i..i + w]);
                    }
                }
                Stored::Cols => {
                    for c in 0..w {
                        let i = at(0, p * NR + c);
                        for (kk, &v) in src[i..i + k].iter().enumerate() {
                            panel[kk * NR + c] = v;
                        }
                    }
                }
            }
        }
        Some(PackedRhs {
            k,
            n,
            data: Data::F32(d),
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
            Data::Bf16(_) | Data::Amx(_) | Data::Bf16Wide(_) => Precision::Bf16,
        }
    }

    /// Bytes held.
    pub fn bytes(&self) -> usize {
        match &self.data {
            Data::F32(d) => d.len() * 4,
            Data::Bf16(d) | Data::Bf16Wide(d) => d.len() * 2,
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
            Data::Bf16Wide(d) => {
                let job = job(a.as_ptr(), lda, d.as_ptr() as *const u8);
                split_panels(job, threads, |j, r| {
                    // SAFETY: Bf16Wide data exists only where AVX2 + FMA runs; as above.
                    unsafe { x86::bf16w_panels_avx2(j, r) }
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
mod x86;

#[cfg(not(target_arch = "x86_64"))]
mod x86 {
    use super::Job;
    pub(super) unsafe fn f32_panels(_: Job, _: std::ops::Range<usize>) {}
    pub(super) unsafe fn f32_panels_avx2(_: Job, _: std::ops::Range<usize>) {}
    pub(super) unsafe fn bf16_panels(_: Job, _: std::ops::Range<usize>) {}
    pub(super) unsafe fn bf16w_panels_avx2(_: Job, _: std::ops::Range<usize>) {}
}

#[cfg(test)]
mod tests;
