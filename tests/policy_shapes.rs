//! Shapes the fixtures do not cover (batch > 1, num_kv_heads > 1), with random weights:
//! cached == uncached, batch rows == single runs, differentiable ops == fast ops, gradients flow.

use candle_core::{Device, Tensor, Var};
use chunkrt_bench::inference::{random_inference_model, random_model};
use chunkrt_policy::model::{ModelInputs, PiModel};
use chunkrt_policy::ModelConfig;

#[path = "common/fixture.rs"]
mod fixture;
use fixture::{absmax, maxdiff};

fn small_config(pi05: bool) -> ModelConfig {
    ModelConfig::from_json_str(&small_config_json(pi05)).expect("valid test config")
}

fn small_config_json(pi05: bool) -> String {
    format!(
        r#"{{
        "vision": {{"hidden_size": 16, "num_hidden_layers": 1, "num_attention_heads": 2,
                    "intermediate_size": 32, "patch_size": 14, "image_size": 28}},
        "paligemma": {{"width": 32, "depth": 2, "mlp_dim": 64, "num_heads": 4, "num_kv_heads": 2, "head_dim": 8}},
        "action_expert": {{"width": 24, "depth": 2, "mlp_dim": 48, "num_heads": 4, "num_kv_heads": 2, "head_dim": 8}},
        "vocab_size": 50, "action_dim": 5, "action_horizon": 4, "max_token_len": 6,
        "pi05": {pi05}, "cameras": ["base_0_rgb", "left_wrist_0_rgb"], "num_denoise_steps": 5
    }}"#
    )
}

fn inputs(cfg: &ModelConfig) -> ModelInputs {
    let dev = Device::Cpu;
    let s = cfg.vision.image_size;
    let b = 2;
    let images = (0..cfg.cameras.len())
        .map(|_| Tensor::rand(-1f32, 1f32, (b, 3, s, s), &dev).unwrap())
        .collect();
    let ids: Vec<u32> = (0..b * cfg.max_token_len)
        .map(|i| (i * 7 % 50) as u32)
        .collect();
    ModelInputs {
        images,
        // row 1 has its wrist camera masked
        image_masks: vec![vec![true, true], vec![true, false]],
        tokens: Tensor::from_vec(ids, (b, cfg.max_token_len), &dev).unwrap(),
        token_mask: vec![
            vec![true, true, true, true, false, false],
            vec![true, true, false, false, false, false],
        ],
        state: Tensor::randn(0f32, 1f32, (b, cfg.action_dim), &dev).unwrap(),
    }
}

fn row(inp: &ModelInputs, i: usize) -> ModelInputs {
    ModelInputs {
        images: inp
            .images
            .iter()
            .map(|t| t.narrow(0, i, 1).unwrap())
            .collect(),
        image_masks: inp.image_masks.iter().map(|m| vec![m[i]]).collect(),
        tokens: inp.tokens.narrow(0, i, 1).unwrap(),
        token_mask: vec![inp.token_mask[i].clone()],
        state: inp.state.narrow(0, i, 1).unwrap(),
    }
}

/// max |a - b| over the larger of 1 and max |b|.
fn scaled_maxdiff(a: &Tensor, b: &Tensor) -> f32 {
    maxdiff(a, b) / absmax(b).max(1.0)
}

fn check_kind(pi05: bool) {
    let cfg = small_config(pi05);
    // held as a checkpoint holds its weights: the inference path (fused and packed) runs
    let model: PiModel = random_inference_model(&cfg).unwrap();
    let inp = inputs(&cfg);
    let noise = Tensor::randn(
        0f32,
        1f32,
        (2, cfg.action_horizon, cfg.action_dim),
        &Device::Cpu,
    )
    .unwrap();
    let mut cache = None;
    let cached = model.sample(&inp, &noise, 5, Some(&mut cache)).unwrap();
    let uncached = model.sample(&inp, &noise, 5, None).unwrap();
    // the weights and inputs are random per run, and so is the outputs' scale (actions up to ~20
    // here): the two paths' rounding is bounded relative to it (over 400 draws of each kind the
    // worst was 4e-6 of the scale for the actions, 3.4e-6 for the velocity below; absolute, up
    // to 4.4e-5 and 2.2e-5)
    let d = scaled_maxdiff(&cached.actions, &uncached.actions);
    println!("pi05={pi05}: cached vs uncached {d:.2e} of the scale");
    assert!(d < 1e-4, "cached vs uncached {d}");
    assert!(
        cached
            .actions
            .abs()
            .unwrap()
            .max_keepdim(2)
            .unwrap()
            .sum_all()
            .unwrap()
            .to_scalar::<f32>()
            .unwrap()
            > 0.0
    );
    // the cache buffers are reused across observations
    let k0 = cache.as_ref().unwrap().k[0].clone();
    let again = model.sample(&inp, &noise, 5, Some(&mut cache)).unwrap();
    assert!(
        cache.as_ref().unwrap().k[0].id() == k0.id(),
        "cache buffers reallocated"
    );
    assert!(maxdiff(&again.actions, &cached.actions) < 1e-6);
    // the prefix K/V packed once per observation for the CPU attention kernel: present where
    // that kernel runs, and a new observation through the reused cache repacks it (a stale
    // prefix would give the first observation's actions)
    let depth = cfg.action_expert.depth;
    let packs = chunkrt_policy::packed::support().f32_packed();
    let panels = cache.as_ref().unwrap().packed_prefix();
    assert_eq!(panels.as_ref().map(|p| p.len()), packs.then_some(depth));
    let offset = cache.as_ref().unwrap().action_offset;
    assert!(panels
        .iter()
        .flat_map(|p| p.iter())
        .all(|p| p.keys() == offset));
    let mut other = inp.clone();
    other.images = inp.images.iter().map(|t| (t * -0.5).unwrap()).collect();
    other.state = (&inp.state * 2.0).unwrap();
    let reused = model.sample(&other, &noise, 5, Some(&mut cache)).unwrap();
    let fresh = model.sample(&other, &noise, 5, Some(&mut None)).unwrap();
    assert!(
        maxdiff(&reused.actions, &fresh.actions) < 1e-6,
        "stale prefix"
    );
    assert!(maxdiff(&reused.actions, &cached.actions) > 1e-3);
    let _ = model.sample(&inp, &noise, 5, Some(&mut cache)).unwrap();
    for i in 0..2 {
        let single = model
            .sample(
                &row(&inp, i),
                &noise.narrow(0, i, 1).unwrap(),
                5,
                Some(&mut None),
            )
            .unwrap();
        let d = maxdiff(&single.actions, &cached.actions.narrow(0, i, 1).unwrap());
        println!("pi05={pi05}: row {i} vs single {d:.2e}");
        assert!(d < 1e-4, "row {i} vs single run {d}");
    }
    // differentiable path == fast path, and a VJP through the action expert works
    let c = cache.as_ref().unwrap();
    let t = Tensor::new(&[0.7f32, 0.3], &Device::Cpu).unwrap();
    let fast = model.velocity(c, &noise, &t, false).unwrap();
    let x = Var::from_tensor(&noise).unwrap();
    let slow = model.velocity(c, x.as_tensor(), &t, true).unwrap();
    let d = scaled_maxdiff(&fast, &slow);
    assert!(d < 3e-5, "differentiable vs fast velocity {d} of the scale");
    // clean estimate A = x - t v; VJP with a ones cotangent
    let t3 = t.reshape((2, 1, 1)).unwrap();
    let a_hat = (x.as_tensor() - slow.broadcast_mul(&t3).unwrap()).unwrap();
    let grads = a_hat.sum_all().unwrap().backward().unwrap();
    let g = grads.get(x.as_tensor()).expect("gradient w.r.t. x_t");
    assert_eq!(g.dims(), noise.dims());
    // finite differences of every entry (the fast, packed path evaluates f): a VJP that misses
    // the path through the velocity (analytic 1 everywhere) fails on most entries. Central
    // differences at one step h miss by O(h^2) times the third derivative, and this tiny random
    // model is curved enough that h = 1e-2 missed by up to 0.2 on about one random draw in 300
    // (the analytic value was right: smaller steps converged to it). Richardson's
    // (4 D(h/2) - D(h)) / 3 cancels the h^2 term: over 600 draws of both kinds its worst miss
    // was 1.3e-3, 15x inside the bound.
    let h = 1e-2f32;
    let f = |xx: &Tensor| -> f64 {
        let v = model.velocity(c, xx, &t, false).unwrap();
        (xx - v.broadcast_mul(&t3).unwrap())
            .unwrap()
            .sum_all()
            .unwrap()
            .to_scalar::<f32>()
            .unwrap() as f64
    };
    let x0 = noise.flatten_all().unwrap().to_vec1::<f32>().unwrap();
    let an = g.flatten_all().unwrap().to_vec1::<f32>().unwrap();
    let (mut worst, mut through_v) = (0f64, 0f64);
    for i in 0..x0.len() {
        let at = |d: f32| {
            let mut x = x0.clone();
            x[i] += d;
            f(&Tensor::from_vec(x, noise.dims(), &Device::Cpu).unwrap())
        };
        let central = |e: f32| (at(e) - at(-e)) / (2.0 * e as f64);
        let fd = (4.0 * central(h / 2.0) - central(h)) / 3.0;
        let a = an[i] as f64;
        worst = worst.max((a - fd).abs() / (1.0 + fd.abs()));
        through_v = through_v.max((fd - 1.0).abs());
    }
    println!(
        "pi05={pi05}: vjp vs finite differences, worst {worst:.2e} (|fd - 1| up to {through_v:.2})"
    );
    assert!(
        through_v > 0.05,
        "the velocity barely depends on x_t: the check is void"
    );
    assert!(worst < 2e-2, "vjp vs finite differences {worst}");
}

#[test]
fn pi05_batch2_gqa2_cached_uncached_rows_and_vjp() {
    check_kind(true);
}

#[test]
fn pi0_batch2_gqa2_cached_uncached_rows_and_vjp() {
    check_kind(false);
}

#[test]
fn loss_is_differentiable_end_to_end_through_vision_and_transformer() {
    let cfg = small_config(true);
    let (model, vm) = random_model(&cfg).unwrap();
    let inp = inputs(&cfg);
    let dev = Device::Cpu;
    let actions = Tensor::randn(0f32, 1f32, (2, cfg.action_horizon, cfg.action_dim), &dev).unwrap();
    let noise = Tensor::randn(0f32, 1f32, (2, cfg.action_horizon, cfg.action_dim), &dev).unwrap();
    let time = Tensor::new(&[0.4f32, 0.9], &dev).unwrap();
    let fast = model.loss(&inp, &actions, &noise, &time, false).unwrap();
    let diff = model.loss(&inp, &actions, &noise, &time, true).unwrap();
    // the same math by other ops: f32 rounding relative to the loss's size (random weights)
    let scale = absmax(&diff.per_element);
    let d = maxdiff(&fast.per_element, &diff.per_element);
    assert!(
        d <= 2e-5 * scale.max(1.0),
        "fast vs differentiable loss {d} (scale {scale})"
    );
    let grads = diff.mean.backward().unwrap();
    let vars = vm.data().lock().unwrap();
    let with_grad = vars
        .iter()
        .filter(|(k, _)| {
            k.contains("gemma_expert")
                || k.starts_with("action")
                || k.starts_with("time_mlp")
                || k.contains("language_model.layers.0.")
                || k.contains("vision_tower")
                || k.contains("multi_modal_projector")
        })
        .filter(|(_, v)| grads.get(v.as_tensor()).is_some())
        .count();
    let total = vars
        .keys()
        .filter(|k| {
            k.contains("gemma_expert")
                || k.starts_with("action")
                || k.starts_with("time_mlp")
                || k.contains("language_model.layers.0.")
                || k.contains("vision_tower")
                || k.contains("multi_modal_projector")
        })
        .count();
    println!(
        "vision / projector / first VLM layer / action expert / heads parameters with a gradient: \
         {with_grad}/{total}"
    );
    assert_eq!(with_grad, total);
}

/// Training's multi-sample loss (one prefix pass, k suffixes per observation) equals the joint
/// loss on the observations repeated k times, for π0 (state token) and π0.5, with both op sets.
#[test]
fn multi_sample_loss_equals_the_joint_loss_on_repeated_inputs() {
    for pi05 in [false, true] {
        let cfg = small_config(pi05);
        let (model, _vm) = random_model(&cfg).unwrap();
        let inp = inputs(&cfg);
        let (b, k) = (2usize, 3usize);
        let dev = Device::Cpu;
        let (h, a) = (cfg.action_horizon, cfg.action_dim);
        let actions = Tensor::randn(0f32, 1f32, (b, h, a), &dev).unwrap();
        let noise = Tensor::randn(0f32, 1f32, (b * k, h, a), &dev).unwrap();
        let time = Tensor::new(&[0.9f32, 0.5, 0.1, 0.7, 0.3, 0.99], &dev).unwrap();
        // the observations repeated k times, row b·k + j = observation b
        let idx = Tensor::new(&[0u32, 0, 0, 1, 1, 1], &dev).unwrap();
        let rep = ModelInputs {
            images: inp
                .images
                .iter()
                .map(|t| t.index_select(&idx, 0).unwrap())
                .collect(),
            image_masks: inp
                .image_masks
                .iter()
                .map(|m| vec![m[0], m[0], m[0], m[1], m[1], m[1]])
                .collect(),
            tokens: inp.tokens.index_select(&idx, 0).unwrap(),
            token_mask: (0..b * k).map(|r| inp.token_mask[r / k].clone()).collect(),
            state: inp.state.index_select(&idx, 0).unwrap(),
        };
        let rep_actions = actions.index_select(&idx, 0).unwrap();
        for diff in [false, true] {
            let embs = model.embed_prefix_with(&inp, diff).unwrap();
            let (multi, _) = model
                .loss_multi(&inp, &embs, &actions, &noise, &time, None, k, diff, None)
                .unwrap();
            let rembs = model.embed_prefix_with(&rep, diff).unwrap();
            let (joint, _) = model
                .loss_tap(&rep, &rembs, &rep_actions, &noise, &time, diff, None)
                .unwrap();
            // the same sums in another order: f32 rounding relative to the loss's size (random
            // weights make it vary from run to run; an absolute 1e-4 failed at 2.1e-4)
            let d = maxdiff(&multi.per_element, &joint.per_element);
            let scale = absmax(&joint.per_element);
            println!("pi05 {pi05} diff {diff}: max |diff| {d:.2e}, loss scale {scale:.2e}");
            assert!(
                d <= 2e-5 * scale.max(1.0),
                "pi05 {pi05} diff {diff}: {d} (scale {scale})"
            );
        }
        // gradients reach the vision tower through the shared prefix
        let embs = model.embed_prefix_with(&inp, true).unwrap();
        let (multi, _) = model
            .loss_multi(&inp, &embs, &actions, &noise, &time, None, k, true, None)
            .unwrap();
        let grads = multi.mean.backward().unwrap();
        let g = _vm
            .all_vars()
            .iter()
            .filter_map(|v| grads.get(v.as_tensor()))
            .count();
        assert!(g > 10, "only {g} variables got a gradient");
    }
}

/// A checkpoint computes the function that was trained: after optimiser steps on a trainable
/// (VarMap) model, the loss of the model as trained equals the loss of its saved checkpoint
/// loaded as the runtime loads it (fused, packed inference model). Before 4d5b2df two tensors were
/// derived from trainable variables once at construction (Gemma's RMSNorm `1 + w`, SigLIP's
/// stacked Q/K/V): the optimiser moved the variables but the forward pass kept the stale copies,
/// so deployed policies computed another function than the one trained.
#[test]
fn a_saved_checkpoint_computes_what_was_trained() {
    use candle_nn::{AdamW, Optimizer, ParamsAdamW};
    for pi05 in [false, true] {
        let cfg = small_config(pi05);
        let (model, vm) = random_model(&cfg).unwrap();
        let inp = inputs(&cfg);
        let dev = Device::Cpu;
        let (h, a) = (cfg.action_horizon, cfg.action_dim);
        let actions = Tensor::randn(0f32, 1f32, (2, h, a), &dev).unwrap();
        let noise = Tensor::randn(0f32, 1f32, (2, h, a), &dev).unwrap();
        let time = Tensor::new(&[0.8f32, 0.3], &dev).unwrap();
        let loss = |m: &PiModel, diff: bool| {
            m.loss(&inp, &actions, &noise, &time, diff)
                .unwrap()
                .mean
                .to_scalar::<f32>()
                .unwrap()
        };
        let before = loss(&model, true);
        let mut opt = AdamW::new(
            vm.all_vars(),
            ParamsAdamW {
                lr: 0.02,
                ..Default::default()
            },
        )
        .unwrap();
        for _ in 0..8 {
            let l = model
                .loss(&inp, &actions, &noise, &time, true)
                .unwrap()
                .mean;
            opt.backward_step(&l).unwrap();
        }
        let trained = loss(&model, true);
        assert!(
            trained < 0.8 * before,
            "training did not move: {before} -> {trained}"
        );
        // every norm and projection moved, so stale copies would show
        let dir = std::env::temp_dir().join(format!(
            "chunkrt-ckpt-roundtrip-{pi05}-{}",
            std::process::id()
        ));
        std::fs::create_dir_all(&dir).unwrap();
        vm.save(dir.join("model.safetensors")).unwrap();
        std::fs::write(dir.join("config.json"), small_config_json(pi05)).unwrap();
        let loaded = chunkrt_policy::checkpoint::load(&dir, &Default::default())
            .unwrap()
            .model;
        let (fast, slow) = (loss(&loaded, false), loss(&loaded, true));
        std::fs::remove_dir_all(&dir).ok();
        for (what, l) in [("fast ops", fast), ("differentiable ops", slow)] {
            assert!(
                (l - trained).abs() <= 1e-4 * trained.abs().max(1.0),
                "pi05 {pi05}: trained model's loss {trained}, its checkpoint's ({what}) {l}"
            );
        }
    }
}
