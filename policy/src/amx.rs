//! bf16 matrix products on Intel AMX (`policy.precision = "bf16"`).
//!
//! `y = x · W` with `x` [M, K] f32 and a weight `W` [K, N] packed once at load time into bf16
//! tiles; `x` is rounded to bf16 on the fly and every product is accumulated in f32 by the
//! `tdpbf16ps` tile instruction (16×16 outputs × 32 products per instruction). Rounding the inputs
//! to bf16 (8 significant bits) changes the results by ~0.3 % relative; the f32 path stays the
//! default and the reference for the parity tests.
//!
//! Layouts:
//! - A (activations): bf16 tiles like B's, [Mp / 16][Kp / 32][16 rows][32], Mp = M rounded up to 32,
//!   Kp = K rounded up to 32, zero padded: every tile load reads 1 KB in one piece.
//! - B (weights): for each block of 16 output columns and each block of 32 inputs, one 16 × 64-byte
//!   tile in the "VNNI" order the instruction reads — row r holds, for each of the 16 columns, the
//!   pair (W[2r][n], W[2r + 1][n]); N is rounded up to 32.
//! - C: f32 tiles stored straight into an [Mp, Np] buffer, then the [M, N] part is copied out.
//!
//! Each call computes 32 × 32 blocks (2 × 2 accumulator tiles, tmm0..3; A in tmm4/5, B in tmm6/7),
//! the column blocks split over the worker threads. Linux grants a process the AMX tile state on
//! request (`arch_prctl(ARCH_REQ_XCOMP_PERM, XFEATURE_XTILEDATA)`); [`available`] asks once and
//! reports whether the CPU and kernel allow it.

use std::sync::OnceLock;

/// Rows / columns of one accumulator tile, and inputs per tile product.
const T: usize = 16;
const TK: usize = 32;

/// Whether AMX-BF16 can be used by this process (CPU flags and the kernel's permission).
pub fn available() -> bool {
    static OK: OnceLock<bool> = OnceLock::new();
    *OK.get_or_init(|| {
        #[cfg(target_arch = "x86_64")]
        {
            // CPUID leaf 7: EDX bit 22 AMX-BF16, bit 24 AMX-TILE (std's feature detection for
            // AMX is not stable yet)
            let edx = std::arch::x86_64::__cpuid_count(7, 0).edx;
            if edx & (1 << 22) == 0 || edx & (1 << 24) == 0 {
                return false;
            }
            // ARCH_REQ_XCOMP_PERM = 0x1023, XFEATURE_XTILEDATA = 18; returns 0 on success
            let ret: i64;
            // SAFETY: the arch_prctl syscall with these arguments only changes this process's
            // permitted XSAVE features; rcx/r11 are clobbered by `syscall`.
            unsafe {
                std::arch::asm!(
                    "syscall",
                    inlateout("rax") 158i64 => ret,
                    in("rdi") 0x1023i64,
                    in("rsi") 18i64,
                    lateout("rcx") _,
                    lateout("r11") _,
                    options(nostack)
                );
            }
            ret == 0
        }
        #[cfg(not(target_arch = "x86_64"))]
        {
            false
        }
    })
}

/// f32 → bf16, round to nearest even (NaN stays NaN). Branch-free, so loops over it vectorise.
#[inline]
pub fn bf16(x: f32) -> u16 {
    let b = x.to_bits();
    let nan = (b & 0x7fff_ffff) > 0x7f80_0000;
    let rounded = b.wrapping_add(0x7fff + ((b >> 16) & 1)) >> 16;
    (if nan { (b >> 16) | 0x40 } else { rounded }) as u16
}

/// bf16 → f32.
#[inline]
pub fn f32_of(h: u16) -> f32 {
    f32::from_bits((h as u32) << 16)
}

fn round_up(x: usize, m: usize) -> usize {
    x.div_ceil(m) * m
}

/// A weight [K, N] packed into bf16 tiles.
#[derive(Debug, Clone)]
pub struct PackedWeight {
    k: usize,
    n: usize,
    kp: usize,
    np: usize,
    /// [Np / 16][Kp / 32][16 rows][32 bf16]
    tiles: Vec<u16>,
}

impl PackedWeight {
    /// Packs `w`, an element accessor of the [K, N] weight (`w(k, n)`).
    pub fn pack(k: usize, n: usize, w: impl Fn(usize, usize) -> f32) -> Self {
        let (kp, np) = (round_up(k, TK), round_up(n, 2 * T));
        let (nbs, kbs) = (np / T, kp / TK);
        let mut tiles = vec![0u16; nbs * kbs * T * TK];
        for nb in 0..nbs {
            for kb in 0..kbs {
                let tile = &mut tiles[(nb * kbs + kb) * T * TK..][..T * TK];
                for r in 0..T {
                    for c in 0..T {
                        let col = nb * T + c;
                        for e in 0..2 {
                            let row = kb * TK + 2 * r + e;
                            if row < k && col < n {
                                tile[r * TK + 2 * c + e] = bf16(w(row, col));
                            }
                        }
                    }
                }
            }
        }
        PackedWeight {
            k,
            n,
            kp,
            np,
            tiles,
        }
    }

    /// Packs a row-major [K, N] tensor.
    pub fn from_matrix(w: &candle_core::Tensor) -> candle_core::Result<Self> {
        let (k, n) = w.dims2()?;
        let v = w.contiguous()?.flatten_all()?.to_vec1::<f32>()?;
        Ok(Self::pack(k, n, |i, j| v[i * n + j]))
    }

    /// Packs a layer weight [N, K] (a `Linear`'s, any strides) as the [K, N] right-hand side.
    pub fn from_weight(w: &candle_core::Tensor) -> candle_core::Result<Self> {
        Self::from_matrix(&w.t()?)
    }

    /// Inputs K.
    pub fn k(&self) -> usize {
        self.k
    }

    /// Outputs N.
    pub fn n(&self) -> usize {
        self.n
    }

    /// Bytes held.
    pub fn bytes(&self) -> usize {
        self.tiles.len() * 2
    }
}

#[repr(C, align(64))]
struct TileConfig {
    palette: u8,
    start_row: u8,
    reserved: [u8; 14],
    colsb: [u16; 16],
    rows: [u8; 16],
}

impl TileConfig {
    /// tmm0..7 all 16 rows × 64 bytes.
    fn full() -> Self {
        let mut c = TileConfig {
            palette: 1,
            start_row: 0,
            reserved: [0; 14],
            colsb: [0; 16],
            rows: [0; 16],
        };
        for i in 0..8 {
            c.colsb[i] = 64;
            c.rows[i] = T as u8;
        }
        c
    }
}

/// Raw pointers handed to worker threads (each writes a disjoint set of column blocks).
#[derive(Clone, Copy)]
struct Ptrs {
    a: *const u16,
    b: *const u16,
    c: *mut f32,
}
// SAFETY: the buffers outlive the scoped workers and each worker writes disjoint columns of C.
unsafe impl Send for Ptrs {}
unsafe impl Sync for Ptrs {}

/// Column blocks `nb2_lo..nb2_hi` (pairs of 16-column blocks) of C = A · B.
///
/// # Safety
/// AMX must be [`available`]; `p.a` points to the [mp / 16][kp / 32] A tiles, `p.b` to the
/// packed tiles of a weight with `kp` inputs, `p.c` to [mp, np] f32; mp a multiple of 32.
#[cfg(target_arch = "x86_64")]
unsafe fn kernel(p: Ptrs, mp: usize, kp: usize, np: usize, nb2: std::ops::Range<usize>) {
    use std::arch::asm;
    let cfg = TileConfig::full();
    let kbs = kp / TK;
    let c_stride = np * 4; // bytes per C row
    let b_tile = T * TK; // u16 per B tile
    asm!("ldtilecfg [{}]", in(reg) &cfg, options(nostack));
    for j in nb2 {
        let b0 = p.b.add(2 * j * kbs * b_tile);
        let b1 = p.b.add((2 * j + 1) * kbs * b_tile);
        for i in (0..mp).step_by(2 * T) {
            let a0 = p.a.add(i / T * kbs * b_tile);
            let a1 = p.a.add((i / T + 1) * kbs * b_tile);
            asm!(
                "tilezero tmm0",
                "tilezero tmm1",
                "tilezero tmm2",
                "tilezero tmm3",
                options(nostack)
            );
            for kb in 0..kbs {
                asm!(
                    // loads interleaved with the products: tile registers are not renamed,
                    // so a load waits for the products still reading its register
                    "tileloadd tmm4, [{a0} + {sa}*1]",
                    "tileloadd tmm6, [{b0} + {sb}*1]",
                    "tdpbf16ps tmm0, tmm4, tmm6",
                    "tileloadd tmm7, [{b1} + {sb}*1]",
                    "tdpbf16ps tmm1, tmm4, tmm7",
                    "tileloadd tmm5, [{a1} + {sa}*1]",
                    "tdpbf16ps tmm2, tmm5, tmm6",
                    "tdpbf16ps tmm3, tmm5, tmm7",
                    a0 = in(reg) a0.add(kb * b_tile),
                    a1 = in(reg) a1.add(kb * b_tile),
                    b0 = in(reg) b0.add(kb * b_tile),
                    b1 = in(reg) b1.add(kb * b_tile),
                    sa = in(reg) 64usize,
                    sb = in(reg) 64usize,
                    options(nostack)
                );
            }
            let c00 = p.c.add(i * np + 2 * j * T);
            let c10 = p.c.add((i + T) * np + 2 * j * T);
            asm!(
                "tilestored [{c00} + {sc}*1], tmm0",
                "tilestored [{c01} + {sc}*1], tmm1",
                "tilestored [{c10} + {sc}*1], tmm2",
                "tilestored [{c11} + {sc}*1], tmm3",
                c00 = in(reg) c00,
                c01 = in(reg) c00.add(T),
                c10 = in(reg) c10,
                c11 = in(reg) c10.add(T),
                sc = in(reg) c_stride,
                options(nostack)
            );
        }
    }
    asm!("tilerelease", options(nostack));
}

/// Reusable buffers of [`matmul`].
#[derive(Debug, Default)]
pub struct Scratch {
    a: Vec<u16>,
    c: Vec<f32>,
}

/// `x` [.., K] (contiguous f32 on the CPU) · `w` → [.., N]; `None` when AMX is not available or
/// `x` is not such a tensor (the caller falls back to f32). Products with 64k outputs or more are
/// split over rayon's threads.
pub fn matmul_tensor(
    x: &candle_core::Tensor,
    w: &PackedWeight,
) -> candle_core::Result<Option<candle_core::Tensor>> {
    use candle_core::{DType, Device, Storage, Tensor};
    if !available() || x.dtype() != DType::F32 || !x.device().is_cpu() {
        return Ok(None);
    }
    let dims = x.dims().to_vec();
    let k = dims.last().copied().unwrap_or(0);
    if k != w.k {
        return Ok(None);
    }
    let m = x.elem_count() / k.max(1);
    let x = x.contiguous()?;
    let (st, layout) = x.storage_and_layout();
    let Storage::Cpu(cpu) = &*st else {
        return Ok(None);
    };
    let data = cpu.as_slice::<f32>()?;
    let Some((lo, hi)) = layout.contiguous_offsets() else {
        return Ok(None);
    };
    let mut out = Vec::new();
    let ok = matmul_auto(&data[lo..hi], m, w, &mut out);
    drop(st);
    if !ok {
        return Ok(None);
    }
    let mut shape = dims;
    if let Some(last) = shape.last_mut() {
        *last = w.n;
    }
    Ok(Some(Tensor::from_vec(out, shape, &Device::Cpu)?))
}

/// [`matmul`] with this thread's scratch buffers and the thread count picked by size.
pub fn matmul_auto(x: &[f32], m: usize, w: &PackedWeight, out: &mut Vec<f32>) -> bool {
    // measured on the 2-core VM: two workers pay from about 64k outputs (50 x 2048: 0.16 ->
    // 0.12 ms), below that the hand-off costs more than it saves (50 x 256: 0.09 -> 0.13 ms)
    let threads = if m * w.n >= 1 << 16 {
        rayon::current_num_threads()
    } else {
        1
    };
    matmul_with(x, m, w, out, threads)
}

/// [`matmul`] with this thread's scratch buffers on `threads` workers.
pub fn matmul_with(
    x: &[f32],
    m: usize,
    w: &PackedWeight,
    out: &mut Vec<f32>,
    threads: usize,
) -> bool {
    thread_local! {
        static SCRATCH: std::cell::RefCell<Scratch> = std::cell::RefCell::new(Scratch::default());
    }
    SCRATCH.with(|s| match s.try_borrow_mut() {
        Ok(mut s) => matmul(x, m, w, out, threads, &mut s),
        // re-entered on this thread (a pool thread that picked up another product while it
        // waited): fresh buffers
        Err(_) => matmul(x, m, w, out, threads, &mut Scratch::default()),
    })
}

/// `out` = [m, N] = `x` [m, K] (row-major f32) · `w`, on `threads` workers (≥ 1, rayon's pool).
/// Returns false (and leaves `out` alone) when AMX is not [`available`] or the sizes do not
/// match.
pub fn matmul(
    x: &[f32],
    m: usize,
    w: &PackedWeight,
    out: &mut Vec<f32>,
    threads: usize,
    s: &mut Scratch,
) -> bool {
    if !available() || x.len() != m * w.k || m == 0 {
        return false;
    }
    #[cfg(target_arch = "x86_64")]
    {
        let (k, kp, np) = (w.k, w.kp, w.np);
        let mp = round_up(m, 2 * T);
        s.a.clear();
        s.a.resize(mp * kp, 0);
        let kbs = kp / TK;
        for (r, row) in x.chunks_exact(k).enumerate() {
            let tile_row = &mut s.a[(r / T) * kbs * T * TK + (r % T) * TK..];
            for (kb, part) in row.chunks(TK).enumerate() {
                let dst = &mut tile_row[kb * T * TK..kb * T * TK + part.len()];
                for (d, &v) in dst.iter_mut().zip(part) {
                    *d = bf16(v);
                }
            }
        }
        // C: straight into `out` when N needs no padding (its rows past m land in spare
        // capacity), else into the scratch and copied. The tile stores write every element.
        let n = w.n;
        let direct = np == n;
        out.clear();
        let c = if direct {
            out.reserve(mp * n);
            out.as_mut_ptr()
        } else {
            if s.c.len() < mp * np {
                s.c.resize(mp * np, 0.0);
            }
            s.c.as_mut_ptr()
        };
        let p = Ptrs {
            a: s.a.as_ptr(),
            b: w.tiles.as_ptr(),
            c,
        };
        let pairs = np / (2 * T);
        let threads = threads.clamp(1, pairs);
        if threads == 1 {
            // SAFETY: checked `available`; the buffers have the documented sizes.
            unsafe { kernel(p, mp, kp, np, 0..pairs) };
        } else {
            let per = pairs.div_ceil(threads);
            rayon::scope(|sc| {
                for t in 1..threads {
                    let r = (t * per).min(pairs)..((t + 1) * per).min(pairs);
                    sc.spawn(move |_| {
                        let p = p;
                        // SAFETY: as above; disjoint column blocks per worker.
                        unsafe { kernel(p, mp, kp, np, r) }
                    });
                }
                // SAFETY: as above.
                unsafe { kernel(p, mp, kp, np, 0..per.min(pairs)) };
            });
        }
        if direct {
            // SAFETY: the kernel wrote all mp·n ≥ m·n elements of the reserved capacity.
            unsafe { out.set_len(m * n) };
        } else {
            out.reserve(m * n);
            for r in 0..m {
                out.extend_from_slice(&s.c[r * np..r * np + n]);
            }
        }
        true
    }
    #[cfg(not(target_arch = "x86_64"))]
    {
        let _ = (threads, s);
        false
    }
}

#[cfg(test)]
pub(super) mod tests {
    use super::*;

    /// Deterministic test values in [-1, 1) (an LCG), shared with the packed kernels' tests.
    pub(crate) fn lcg(seed: u64) -> impl FnMut() -> f32 {
        let mut s = seed;
        move || {
            s = s
                .wrapping_mul(6364136223846793005)
                .wrapping_add(1442695040888963407);
            ((s >> 40) as f32 / (1u64 << 24) as f32) * 2.0 - 1.0
        }
    }

    #[test]
    fn bf16_rounds_to_nearest_even() {
        assert_eq!(bf16(1.0), 0x3f80);
        assert_eq!(f32_of(bf16(1.0 + 1.0 / 256.0)), 1.0); // tie: to even
        assert_eq!(f32_of(bf16(1.0 + 3.0 / 256.0)), 1.0 + 4.0 / 256.0);
        assert!(f32_of(bf16(f32::NAN)).is_nan());
        assert!(f32_of(bf16(-f32::NAN)).is_nan());
        assert_eq!(f32_of(bf16(f32::INFINITY)), f32::INFINITY);
        assert_eq!(f32_of(bf16(f32::MAX)), f32::INFINITY); // rounds up past the largest bf16
        assert_eq!(f32_of(bf16(-2.5)), -2.5);
    }

    /// Odd sizes (padding in every dimension) against an f64 product of the bf16-rounded inputs:
    /// the only difference left is f32 accumulation order.
    #[test]
    fn matches_a_reference_product_of_the_rounded_inputs() {
        if !available() {
            eprintln!("no AMX on this machine: skipped");
            return;
        }
        for &(m, k, n, threads) in &[(1, 3, 5, 1), (50, 256, 640, 2), (37, 588, 96, 2)] {
            let mut r = lcg((m * k * n) as u64);
            let x: Vec<f32> = (0..m * k).map(|_| r()).collect();
            let wt: Vec<f32> = (0..k * n).map(|_| r()).collect();
            let w = PackedWeight::pack(k, n, |i, j| wt[i * n + j]);
            let mut out = Vec::new();
            let mut s = Scratch::default();
            assert!(matmul(&x, m, &w, &mut out, threads, &mut s));
            let mut worst = 0f64;
            for i in 0..m {
                for j in 0..n {
                    let want: f64 = (0..k)
                        .map(|l| {
                            f32_of(bf16(x[i * k + l])) as f64 * f32_of(bf16(wt[l * n + j])) as f64
                        })
                        .sum();
                    worst = worst.max((out[i * n + j] as f64 - want).abs());
                }
            }
            assert!(worst < 1e-4 * k as f64, "{m}x{k}x{n}: max error {worst}");
        }
    }
}
