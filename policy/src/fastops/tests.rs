//! Unit tests of `fastops` (kept apart so the module reads on its own).
use super::*;
use candle_core::D;

fn maxdiff(a: &Tensor, b: &Tensor) -> f32 {
    (a - b)
        .unwrap()
        .abs()
        .unwrap()
        .flatten_all()
        .unwrap()
        .max(0)
        .unwrap()
        .to_scalar::<f32>()
        .unwrap()
}

#[test]
fn exp_matches_libm() {
    // with and without fused multiply-adds (the vector variants and the baseline)
    fn check<const FMA: bool>() {
        let mut worst = 0f32;
        let mut x = -87.0f32;
        while x < 88.0 {
            let (a, b) = (exp_f32::<FMA>(x), x.exp());
            worst = worst.max(((a - b) / b).abs());
            x += 0.013;
        }
        assert!(worst < 4e-7, "FMA {FMA}: relative error {worst}");
        assert_eq!(exp_f32::<FMA>(-1e30), 0.0);
        assert_eq!(exp_f32::<FMA>(f32::NEG_INFINITY), 0.0);
    }
    check::<false>();
    check::<true>();
}

#[test]
fn add_matches_candle_with_and_without_broadcast() {
    let dev = Device::Cpu;
    let a = Tensor::randn(0f32, 1f32, (3, 300, 257), &dev).unwrap();
    let b = Tensor::randn(0f32, 1f32, (3, 300, 257), &dev).unwrap();
    let p = Tensor::randn(0f32, 1f32, (300, 257), &dev).unwrap();
    let got = add(&a, &b).unwrap().unwrap();
    assert_eq!(maxdiff(&(&a + &b).unwrap(), &got), 0.0);
    let got = add(&a, &p).unwrap().unwrap();
    assert_eq!(maxdiff(&a.broadcast_add(&p).unwrap(), &got), 0.0);
    // shapes that do not broadcast this way fall back
    let q = Tensor::randn(0f32, 1f32, (3, 1, 257), &dev).unwrap();
    assert!(add(&a, &q).unwrap().is_none());
}

#[test]
fn gelu_mul_matches_candle() {
    let dev = Device::Cpu;
    let g = (Tensor::randn(0f32, 3f32, (3, 70_001), &dev).unwrap() * 1.0).unwrap();
    let u = Tensor::randn(0f32, 1f32, (3, 70_001), &dev).unwrap();
    let want = (g.gelu().unwrap() * &u).unwrap();
    let got = gelu_mul(&g, &u).unwrap().unwrap();
    assert!(maxdiff(&want, &got) < 1e-5);
}

#[test]
fn fused_gelu_and_heads_match_candle() {
    let dev = Device::Cpu;
    let y = Tensor::randn(0f32, 2f32, (2, 7, 2 * 24), &dev).unwrap();
    let g = y.narrow(2, 0, 24).unwrap();
    let u = y.narrow(2, 24, 24).unwrap();
    let want = (g.gelu().unwrap() * &u).unwrap();
    let got = gelu_mul_fused(&y, 24).unwrap().unwrap();
    assert!(maxdiff(&want, &got) < 1e-5);
    // heads with and without rope from a strided (narrowed) input
    let x = Tensor::randn(0f32, 1f32, (2, 7, 3 * 16 + 8), &dev).unwrap();
    let cos = Tensor::rand(-1f32, 1f32, (2, 7, 4), &dev).unwrap();
    let sin = Tensor::rand(-1f32, 1f32, (2, 7, 4), &dev).unwrap();
    let part = x.narrow(2, 8, 16).unwrap();
    let heads = part
        .reshape((2, 7, 2, 8))
        .unwrap()
        .transpose(1, 2)
        .unwrap()
        .contiguous()
        .unwrap();
    let got = split_heads(&x, 8, 2, 8, None).unwrap().unwrap();
    assert_eq!(maxdiff(&heads, &got), 0.0);
    let want = candle_nn::rotary_emb::rope(&heads, &cos, &sin).unwrap();
    let got = split_heads(&x, 8, 2, 8, Some((&cos, &sin)))
        .unwrap()
        .unwrap();
    assert_eq!(maxdiff(&want, &got), 0.0);
}

#[test]
fn attention_matches_candle() {
    let _choice = crate::packed::kernel_choice_lock();
    let dev = Device::Cpu;
    for &(b, nh, nkv, l, t, bl) in &[(2, 8, 2, 5, 37, 5), (1, 4, 1, 50, 70, 1)] {
        let q = Tensor::randn(0f32, 1f32, (b, nh, l, 16), &dev).unwrap();
        let kf = Tensor::randn(0f32, 1f32, (b, nkv, t + 3, 16), &dev).unwrap();
        let vf = Tensor::randn(0f32, 1f32, (b, nkv, t + 3, 16), &dev).unwrap();
        // a narrow over T, as with the cache buffers
        let k = kf.narrow(2, 0, t).unwrap();
        let v = vf.narrow(2, 0, t).unwrap();
        let mask = Tensor::rand(0f32, 1f32, (b, 1, bl, t), &dev).unwrap();
        let bias = mask
            .ge(0.3)
            .unwrap()
            .where_cond(
                &Tensor::zeros((b, 1, bl, t), candle_core::DType::F32, &dev).unwrap(),
                &Tensor::full(-2.381_976_3e38f32, (b, 1, bl, t), &dev).unwrap(),
            )
            .unwrap();
        let scale = 0.25f32;
        let g = nh / nkv;
        let qs = (&q * scale as f64)
            .unwrap()
            .reshape((b, nkv, g * l, 16))
            .unwrap();
        let s = qs.matmul(&k.t().unwrap()).unwrap();
        let s = s
            .reshape((b, nkv, g, l, t))
            .unwrap()
            .broadcast_add(&bias.reshape((b, 1, 1, bl, t)).unwrap())
            .unwrap();
        let p = candle_nn::ops::softmax(&s, D::Minus1).unwrap();
        let o = p
            .reshape((b, nkv, g * l, t))
            .unwrap()
            .matmul(&v.contiguous().unwrap())
            .unwrap();
        let want = o
            .reshape((b, nh, l, 16))
            .unwrap()
            .transpose(1, 2)
            .unwrap()
            .reshape((b, l, nh * 16))
            .unwrap();
        let got = attention(&q, &k, &v, &bias, scale, Precision::F32, None)
            .unwrap()
            .unwrap();
        let d = maxdiff(&want, &got);
        assert!(d < 1e-5, "attention {d}");
        // bf16 products where the CPU has native bf16 arithmetic (8 significant bits in q, k,
        // v and the probabilities), else the same f32 result
        let got = attention(&q, &k, &v, &bias, scale, Precision::Bf16, None)
            .unwrap()
            .unwrap();
        let d16 = maxdiff(&want, &got);
        if crate::packed::bf16_native() && crate::packed::enabled() {
            assert!(d16 > 0.0 && d16 < 3e-2, "bf16 attention {d16}");
        } else {
            assert!(d16 < 1e-5, "bf16 attention without a bf16 kernel {d16}");
        }
    }
}

/// A prefix packed once ([`PackedKv`]) gives the attention over the whole cache, and the kernel
/// reads the prefix from its panels: after the cache's prefix is overwritten, the result holds.
#[test]
fn attention_reads_a_prepacked_prefix() {
    let _choice = crate::packed::kernel_choice_lock();
    if !(crate::packed::support().f32_packed() && crate::packed::enabled()) {
        eprintln!("skipped: no packed f32 kernel on this CPU");
        return;
    }
    let dev = Device::Cpu;
    for &(b, nh, nkv, l, t, tp) in &[(1, 8, 1, 50, 97, 41), (2, 4, 2, 7, 40, 40)] {
        let q = Tensor::randn(0f32, 1f32, (b, nh, l, 16), &dev).unwrap();
        let kf = Tensor::randn(0f32, 1f32, (b, nkv, t + 5, 16), &dev).unwrap();
        let vf = Tensor::randn(0f32, 1f32, (b, nkv, t + 5, 16), &dev).unwrap();
        let (k, v) = (kf.narrow(2, 0, t).unwrap(), vf.narrow(2, 0, t).unwrap());
        // the last key of the first batch row masked
        let mut bias = vec![0f32; b * t];
        bias[t - 1] = -2.381_976_3e38;
        let bias = Tensor::from_vec(bias, (b, 1, 1, t), &dev).unwrap();
        for arith in [Precision::F32, Precision::Bf16] {
            let want = attention(&q, &k, &v, &bias, 0.25, arith, None)
                .unwrap()
                .unwrap();
            let pk = PackedKv::pack(&k, &v, tp, arith).unwrap().unwrap();
            assert_eq!(pk.keys(), tp);
            let got = attention(&q, &k, &v, &bias, 0.25, arith, Some(&pk))
                .unwrap()
                .unwrap();
            // the split changes only the order of the P·V sums
            let d = maxdiff(&want, &got);
            assert!(d < 1e-5, "{arith:?} t {t} tp {tp}: {d}");
            // the cache's prefix overwritten: the panels still give the same result, the
            // cache read directly does not
            let (k2, v2) = (kf.copy().unwrap(), vf.copy().unwrap());
            let zeros = Tensor::zeros((b, nkv, tp, 16), candle_core::DType::F32, &dev).unwrap();
            k2.slice_set(&zeros, 2, 0).unwrap();
            v2.slice_set(&zeros, 2, 0).unwrap();
            let (k2, v2) = (k2.narrow(2, 0, t).unwrap(), v2.narrow(2, 0, t).unwrap());
            let got = attention(&q, &k2, &v2, &bias, 0.25, arith, Some(&pk))
                .unwrap()
                .unwrap();
            assert!(
                maxdiff(&want, &got) < 1e-5,
                "{arith:?}: prefix not read from the panels"
            );
            let plain = attention(&q, &k2, &v2, &bias, 0.25, arith, None)
                .unwrap()
                .unwrap();
            assert!(maxdiff(&want, &plain) > 1e-2);
            // panels that do not fit the call (another batch size) are ignored
            let other = PackedKv::pack(
                &k.narrow(0, 0, 1).unwrap(),
                &v.narrow(0, 0, 1).unwrap(),
                tp,
                arith,
            )
            .unwrap()
            .unwrap();
            if b > 1 {
                let got = attention(&q, &k, &v, &bias, 0.25, arith, Some(&other))
                    .unwrap()
                    .unwrap();
                assert_eq!(maxdiff(&want, &got), 0.0);
            }
        }
    }
}

/// A head's query rows split into balanced blocks of at most `ATT_ROWS`, in whole register tiles
/// where that adds no block, covering every row once.
#[test]
fn query_blocks_cover_the_rows_in_whole_tiles() {
    use super::{query_blocks, ATT_ROWS};
    assert_eq!(query_blocks(50, 6), (2, 30));
    assert_eq!(query_blocks(50, 12), (2, 36));
    assert_eq!(query_blocks(816, 12), (17, 48));
    assert_eq!(query_blocks(1, 12), (1, 12));
    for l in 1..400 {
        for mr in [6, 12] {
            let (blocks, rows) = query_blocks(l, mr);
            assert!(rows <= ATT_ROWS && rows * blocks >= l && rows * (blocks - 1) < l);
            assert_eq!(blocks, l.div_ceil(ATT_ROWS), "l {l} mr {mr}");
        }
    }
}
