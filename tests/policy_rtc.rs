//! Real-time chunking guidance (`chunkrt_policy::rtc`) on the real pi05_tiny fixture checkpoint:
//! β = 0 / W = 0 equal the unguided sampler, guidance pulls the frozen steps onto the previous
//! chunk, the VJP matches finite differences, and the guided step's cost relative to a plain one.

use std::time::Instant;

use candle_core::{Device, Tensor};
use chunkrt_policy::rtc::{
    clean_estimate_vjp, guidance_scale, guided_velocity, weight_mask, Guidance, GuidanceTarget,
    Jacobian,
};
use chunkrt_policy::{Conditioning, Policy, RawObservation};

#[path = "common/fixture.rs"]
mod fixture;
use fixture::{absmax, data, maxdiff, raw_frames, Frame};

/// Camera frames and the unpadded state of the pi05_tiny fixture.
fn fixture() -> (Vec<Frame>, Vec<f64>) {
    fixture::raw_observation("pi05_tiny", &["base_0_rgb", "left_wrist_0_rgb"])
}

fn policy() -> Policy {
    let pc = chunkrt_controller::config::PolicyConfig::default();
    chunkrt_controller::inference::load_policy(&data("pi05_tiny"), &pc).unwrap()
}

/// The fixture observation with its prompt.
fn observation<'a>(
    raw: &'a [chunkrt_policy::RawFrame<'a>],
    state: &'a [f64],
) -> RawObservation<'a> {
    RawObservation {
        frames: raw,
        joint_positions: state,
        prompt: "pick up the red block",
    }
}

/// A policy and the fixture observation as model inputs (for tests that drive the model
/// directly), with the unpadded state.
fn prepared() -> (Policy, chunkrt_policy::ModelInputs, Vec<f64>) {
    let (frames, state) = fixture();
    let raw = raw_frames(&frames);
    let obs = observation(&raw, &state);
    let mut p = policy();
    let inputs = p.prepare(&obs).unwrap();
    (p, inputs, state)
}

/// Deterministic N(0,1)-ish noise (sum of uniforms from a fixed LCG) [1, H, A].
fn noise(h: usize, a: usize, seed: u64) -> Tensor {
    let mut s = seed;
    let mut next = || {
        s = s
            .wrapping_mul(6364136223846793005)
            .wrapping_add(1442695040888963407);
        (s >> 40) as f32 / (1u64 << 24) as f32
    };
    let v: Vec<f32> = (0..h * a)
        .map(|_| (0..12).map(|_| next()).sum::<f32>() - 6.0)
        .collect();
    Tensor::from_vec(v, (1, h, a), &Device::Cpu).unwrap()
}

#[test]
fn beta_zero_or_zero_weights_equal_unguided_exactly() {
    let (frames, state) = fixture();
    let raw = raw_frames(&frames);
    let obs = observation(&raw, &state);
    // two policies with the same seed draw the same noise sequence
    let mut plain = policy();
    let mut guided = policy();
    let h = plain.horizon();
    let n = state.len();
    let prefix: Vec<f64> = (0..h * n).map(|i| (i as f64 * 0.37).sin()).collect();
    let ones = vec![1.0f32; h];
    let zeros = vec![0.0f32; h];
    let cases = [
        ("None", None),
        (
            "beta = 0",
            Some(Guidance {
                prefix: &prefix,
                weights: &ones,
                beta: 0.0,
                jacobian: Jacobian::Vjp,
            }),
        ),
        (
            "W = 0",
            Some(Guidance {
                prefix: &prefix,
                weights: &zeros,
                beta: 5.0,
                jacobian: Jacobian::Vjp,
            }),
        ),
    ];
    for (name, g) in cases {
        let a = plain.infer(&obs, &Conditioning::Fresh).unwrap();
        let b = guided
            .infer(
                &obs,
                &g.as_ref()
                    .map_or(Conditioning::Fresh, |g| Conditioning::Guided(*g)),
            )
            .unwrap();
        assert_eq!(a.len(), h * n);
        assert_eq!(a, b, "{name}: guided differs from infer");
    }
    // with guidance on, the same noise gives a different chunk
    let a = plain.infer(&obs, &Conditioning::Fresh).unwrap();
    let b = guided
        .infer(
            &obs,
            &Conditioning::Guided(Guidance {
                prefix: &prefix,
                weights: &ones,
                beta: 5.0,
                jacobian: Jacobian::Vjp,
            }),
        )
        .unwrap();
    let d = a
        .iter()
        .zip(&b)
        .map(|(x, y)| (x - y).abs())
        .fold(0.0, f64::max);
    println!("beta = 5, W = 1: max |guided - unguided| = {d:.3}");
    assert!(d > 1e-2, "guidance had no effect ({d})");

    // model level: with W = 0 the VJP is exactly zero and v' = v
    let inputs = guided.prepare(&obs).unwrap();
    let model = guided.model();
    let mut cache = None;
    model.fill_cache(&inputs, &mut cache, false).unwrap();
    let c = cache.as_ref().unwrap();
    let (hh, aa) = (model.cfg.action_horizon, model.cfg.action_dim);
    let target = GuidanceTarget {
        y: noise(hh, aa, 9),
        w: weight_mask(&zeros, n, aa, &Device::Cpu).unwrap(),
        beta: 5.0,
        jacobian: Jacobian::Vjp,
    };
    for jacobian in [Jacobian::Vjp, Jacobian::Identity] {
        let target = GuidanceTarget {
            jacobian,
            ..target.clone()
        };
        let gv = guided_velocity(model, c, &noise(hh, aa, 1), 0.5, &target).unwrap();
        // exact zeros: β = 0 / W = 0 must give the unguided velocity bit for bit
        assert_eq!(absmax(&gv.g), 0.0, "{jacobian:?}");
        assert_eq!(maxdiff(&gv.v_guided, &gv.v), 0.0, "{jacobian:?}");
    }
    // the identity Jacobian's gradient is the weighted error itself
    let target = GuidanceTarget {
        w: weight_mask(&vec![1.0f32; hh], n, aa, &Device::Cpu).unwrap(),
        jacobian: Jacobian::Identity,
        ..target
    };
    let gv = guided_velocity(model, c, &noise(hh, aa, 1), 0.5, &target).unwrap();
    let want = ((&target.y - &gv.a_hat).unwrap()
        * &target.w.broadcast_as(gv.a_hat.shape()).unwrap())
        .unwrap();
    assert_eq!(maxdiff(&gv.g, &want), 0.0);
    assert!(absmax(&gv.g) > 0.0);
}

#[test]
fn guidance_pulls_the_frozen_steps_onto_the_previous_chunk() {
    guidance_pulls(None, Jacobian::Vjp);
}

/// The identity Jacobian (no backward pass) pulls too.
#[test]
fn identity_jacobian_guidance_pulls_the_frozen_steps_onto_the_previous_chunk() {
    guidance_pulls(None, Jacobian::Identity);
}

/// With delta actions the previous chunk (robot units, absolute) is made relative to the new
/// observation's state before it guides: the guided chunk still lands on it.
#[test]
fn guidance_with_delta_actions_pulls_onto_the_absolute_previous_chunk() {
    guidance_pulls(
        Some(vec![true, true, false, true, false, true]),
        Jacobian::Vjp,
    );
}

fn guidance_pulls(delta_action_mask: Option<Vec<bool>>, jacobian: Jacobian) {
    let mut pc = chunkrt_controller::config::PolicyConfig::default();
    pc.model.delta_action_mask = delta_action_mask;
    let policy = || chunkrt_controller::inference::load_policy(&data("pi05_tiny"), &pc).unwrap();
    let (frames, state) = fixture();
    let raw = raw_frames(&frames);
    let obs = observation(&raw, &state);
    let mut plain = policy();
    let mut guided = policy();
    let h = plain.horizon();
    let n = state.len();
    // the unguided chunk for the first noise draw
    let unguided = plain.infer(&obs, &Conditioning::Fresh).unwrap();
    // a previous chunk that disagrees with it by ~0.5 on every joint
    let prefix: Vec<f64> = unguided
        .iter()
        .enumerate()
        .map(|(i, &u)| u + 0.5 * if (i / n + i % n) % 2 == 0 { 1.0 } else { -1.0 })
        .collect();
    // W: 1 on the first d steps (executed during inference), linear decay over the next 3, then 0
    let d = 4;
    let weights: Vec<f32> = (0..h)
        .map(|i| {
            if i < d {
                1.0
            } else {
                (1.0 - (i - d + 1) as f32 / 4.0).max(0.0)
            }
        })
        .collect();
    let g = Guidance {
        prefix: &prefix,
        weights: &weights,
        beta: 5.0,
        jacobian,
    };
    let out = guided.infer(&obs, &Conditioning::Guided(g)).unwrap();
    assert!(out.iter().all(|x| x.is_finite()));
    let err = |a: &[f64], rows: std::ops::Range<usize>| -> f64 {
        let mut s = 0.0;
        let mut k = 0;
        for r in rows {
            for j in 0..n {
                s += (a[r * n + j] - prefix[r * n + j]).powi(2);
                k += 1;
            }
        }
        (s / k as f64).sqrt()
    };
    let e_un = err(&unguided, 0..d);
    let e_g = err(&out, 0..d);
    let tail_un = err(&unguided, d + 3..h);
    let tail_g = err(&out, d + 3..h);
    println!(
        "{jacobian:?}: first {d} steps: RMS error to the previous chunk unguided {e_un:.4}, guided {e_g:.4} ({:.1}x); \
         unweighted tail: {tail_un:.4} -> {tail_g:.4}",
        e_un / e_g
    );
    assert!(
        e_g * 5.0 <= e_un,
        "guidance reduced the error only {:.2}x",
        e_un / e_g
    );
}

#[test]
fn vjp_matches_finite_differences_and_guided_step_cost() {
    let (p, inputs, state) = prepared();
    let model = p.model();
    let mut cache = None;
    model.fill_cache(&inputs, &mut cache, false).unwrap();
    let c = cache.as_ref().unwrap();
    let (h, a) = (model.cfg.action_horizon, model.cfg.action_dim);
    let dev = Device::Cpu;
    let x = noise(h, a, 3);
    let t = 0.6f32;
    let cot = noise(h, a, 4);
    let (_, _, g) = clean_estimate_vjp(model, c, &x, &[t], &cot).unwrap();
    // f(x) = <cot, Â(x)> with the fast (non-differentiable) velocity; ∂f/∂x_j = g_j
    let f = |xx: &Tensor| -> f64 {
        let v = model.velocity_at(c, xx, &[t], false).unwrap();
        let a_hat = (xx - (v * t as f64).unwrap()).unwrap();
        let s: f32 = (a_hat * &cot)
            .unwrap()
            .sum_all()
            .unwrap()
            .to_scalar()
            .unwrap();
        s as f64
    };
    let eps = 1e-2f32;
    for (i, j) in [(0usize, 0usize), (3, 5), (9, 2)] {
        let mut bump = vec![0.0f32; h * a];
        bump[i * a + j] = eps;
        let bump = Tensor::from_vec(bump, (1, h, a), &dev).unwrap();
        let fd = (f(&(&x + &bump).unwrap()) - f(&(&x - &bump).unwrap())) / (2.0 * eps as f64);
        let an = g
            .get(0)
            .unwrap()
            .get(i)
            .unwrap()
            .get(j)
            .unwrap()
            .to_scalar::<f32>()
            .unwrap() as f64;
        println!("vjp [{i},{j}]: analytic {an:.5}, finite difference {fd:.5}");
        assert!(
            (an - fd).abs() < 2e-2 * (1.0 + fd.abs()),
            "vjp [{i},{j}]: {an} vs {fd}"
        );
    }
    // the guidance scale: β at the first step (τ = 0), the bound (τ²+(1−τ)²)/(τ(1−τ)) inside
    assert_eq!(guidance_scale(1.0, 5.0), 5.0);
    assert_eq!(guidance_scale(0.0, 5.0), 5.0);
    assert!((guidance_scale(0.5, 5.0) - 2.0).abs() < 1e-6);
    assert!((guidance_scale(0.5, 1.0) - 1.0).abs() < 1e-6);

    // cost of a guided step relative to a plain one: 15 interleaved pairs after a warm-up, so
    // a change in the machine's load hits both alike; the median of the pair ratios
    let target = GuidanceTarget {
        y: noise(h, a, 5),
        w: weight_mask(&[1.0; 10], state.len(), a, &dev).unwrap(),
        beta: 5.0,
        jacobian: Jacobian::Vjp,
    };
    let time = |f: &mut dyn FnMut()| {
        let t0 = Instant::now();
        f();
        t0.elapsed().as_secs_f64()
    };
    let mut plain_step = || {
        model.velocity_at(c, &x, &[t], false).unwrap();
    };
    let mut guided_step = || {
        guided_velocity(model, c, &x, t, &target).unwrap();
    };
    plain_step();
    guided_step();
    let mut pairs: Vec<(f64, f64)> = (0..15)
        .map(|_| (time(&mut plain_step), time(&mut guided_step)))
        .collect();
    let mut ratios: Vec<f64> = pairs.iter().map(|(p, g)| g / p).collect();
    ratios.sort_by(f64::total_cmp);
    pairs.sort_by(|a, b| a.0.total_cmp(&b.0));
    let plain = pairs[pairs.len() / 2].0;
    let ratio = ratios[ratios.len() / 2];
    let guided = plain * ratio;
    println!(
        "step cost: unguided {:.3} ms, guided {:.3} ms, ratio {:.2}x",
        plain * 1e3,
        guided * 1e3,
        guided / plain
    );
    assert!(ratio > 1.0 && ratio < 50.0, "guided/plain {ratio:.2}");
}

#[test]
fn bad_guidance_is_an_error_not_a_panic() {
    let (frames, state) = fixture();
    let raw = raw_frames(&frames);
    let obs = observation(&raw, &state);
    let mut p = policy();
    let h = p.horizon();
    let n = state.len();
    let prefix = vec![0.0f64; h * n];
    let w = vec![1.0f32; h];
    let mut nan_prefix = prefix.clone();
    nan_prefix[3] = f64::NAN;
    let mut neg_w = w.clone();
    neg_w[0] = -1.0;
    let bad = [
        Guidance {
            prefix: &prefix[1..],
            weights: &w,
            beta: 1.0,
            jacobian: Jacobian::Vjp,
        },
        Guidance {
            prefix: &prefix,
            weights: &w[1..],
            beta: 1.0,
            jacobian: Jacobian::Vjp,
        },
        Guidance {
            prefix: &nan_prefix,
            weights: &w,
            beta: 1.0,
            jacobian: Jacobian::Vjp,
        },
        Guidance {
            prefix: &prefix,
            weights: &neg_w,
            beta: 1.0,
            jacobian: Jacobian::Vjp,
        },
        Guidance {
            prefix: &prefix,
            weights: &w,
            beta: f32::NAN,
            jacobian: Jacobian::Vjp,
        },
        Guidance {
            prefix: &prefix,
            weights: &w,
            beta: -1.0,
            jacobian: Jacobian::Vjp,
        },
    ];
    for g in &bad {
        assert!(
            p.infer(&obs, &Conditioning::Guided(*g)).is_err(),
            "accepted {g:?}"
        );
    }
    // still usable afterwards
    assert_eq!(
        p.infer(
            &obs,
            &Conditioning::Guided(Guidance {
                prefix: &prefix,
                weights: &w,
                beta: 1.0,
                jacobian: Jacobian::Vjp,
            })
        )
        .unwrap()
        .len(),
        h * n
    );
}

/// What a GPU captures for RTC's guided loop (`SampleGraph::capture_guided`: the prefix pass on
/// the prepared cache, then `rtc::denoise_guided`) is the eager guided sampler, to the last bit;
/// on the CPU no graph is made and the eager result is returned. Another target changes the
/// result (the target is read from its buffers, not baked in). The replay on a GPU is checked
/// in `tests/policy_device.rs`.
#[test]
fn the_guided_loop_a_gpu_captures_is_the_eager_guided_sampler() {
    use chunkrt_policy::graph::SampleGraph;
    use chunkrt_policy::rtc::sample_guided;
    let (p, inputs, state) = prepared();
    let model = p.model();
    let (h, a) = (model.cfg.action_horizon, model.cfg.action_dim);
    let steps = model.cfg.num_denoise_steps;
    let x = noise(h, a, 11);
    let target = |seed: u64| GuidanceTarget {
        y: noise(h, a, seed),
        w: weight_mask(
            &[1.0, 1.0, 1.0, 0.5, 0.2, 0.0, 0.0, 0.0, 0.0, 0.0],
            state.len(),
            a,
            &Device::Cpu,
        )
        .unwrap(),
        beta: 10.0,
        jacobian: Jacobian::Identity,
    };
    let mut cache = None;
    let eager = sample_guided(model, &inputs, &x, steps, &mut cache, &target(12)).unwrap();
    let mut gcache = None;
    let c = model.prepare_prefix(&inputs, &mut gcache, true).unwrap();
    let (out, graph) = SampleGraph::capture_guided(model, c, &x, steps, &target(12)).unwrap();
    assert!(graph.is_none(), "no CUDA graph on the CPU");
    assert_eq!(maxdiff(&out.actions, &eager.actions), 0.0);
    let c = model.prepare_prefix(&inputs, &mut gcache, true).unwrap();
    let (other, _) = SampleGraph::capture_guided(model, c, &x, steps, &target(13)).unwrap();
    let d = maxdiff(&other.actions, &eager.actions);
    println!("guided loop: another target moves the actions by {d:.4}");
    assert!(d > 1e-3, "the target had no effect ({d})");
    // the VJP's backward is not captured
    let vjp = GuidanceTarget {
        jacobian: Jacobian::Vjp,
        ..target(12)
    };
    let c = model.prepare_prefix(&inputs, &mut gcache, true).unwrap();
    assert!(SampleGraph::capture_guided(model, c, &x, steps, &vjp).is_err());
}
