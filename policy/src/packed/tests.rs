//! Unit tests of `packed` (kept apart so the module reads on its own).
use super::amx::tests::lcg;
use super::*;

/// Odd sizes (tails in every dimension, several K blocks, row strides) against an f64
/// product; for bf16, of the bf16-rounded inputs.
#[test]
fn packed_products_match_a_reference() {
    let _choice = kernel_choice_lock();
    let s = support();
    // the AVX-512 kernel where it runs, and the AVX2 one (forced there, the only one elsewhere)
    for (prec, avx2) in [
        (Precision::F32, false),
        (Precision::F32, true),
        (Precision::Bf16, false),
        (Precision::Bf16, true),
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
            // the strided packers (the attention's V rows and K columns) lay out the same
            // panels: the same product, bit for bit
            let wt: Vec<f32> = (0..n * k).map(|x| w[(x % k) * n + x / k]).collect();
            for (how, q) in [
                (
                    "rows",
                    PackedRhs::pack_strided(k, n, &w, n, Stored::Rows, prec),
                ),
                (
                    "cols",
                    PackedRhs::pack_strided(k, n, &wt, k, Stored::Cols, prec),
                ),
            ] {
                let q = q.expect("a kernel packs strided too");
                let q = if with_bias {
                    q.with_bias(bias.clone())
                } else {
                    q
                };
                let mut c2 = vec![7f32; m * ldc];
                q.matmul_into(&a, m, lda, &mut c2, ldc, threads);
                assert!(c == c2, "{prec:?} (avx2 {avx2}) {m}x{k}x{n}: {how} differs");
            }
            let round = |v: f32| match prec {
                Precision::F32 => v as f64,
                Precision::Bf16 => amx::f32_of(amx::bf16(v)) as f64,
            };
            // the AVX2 bf16 kernel keeps x in f32 (only the weights are bf16)
            let x_f32 = bf16_backend().is_some_and(|b| b.starts_with("avx2"));
            let round_x = |v: f32| if x_f32 { v as f64 } else { round(v) };
            let mut worst = 0f64;
            for i in 0..m {
                for jj in 0..n {
                    let want: f64 = (0..k)
                        .map(|l| round_x(a[i * lda + l]) * round(w[l * n + jj]))
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
    let _choice = kernel_choice_lock();
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
