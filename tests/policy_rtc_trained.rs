//! Training-time real-time chunking (`PiModel::denoise_committed`, `loss_multi` with a committed
//! prefix, `Policy::infer_committed`) on the real openpi fixture checkpoints: the committed
//! actions come back exactly, reach the generated ones through the bidirectional action
//! attention, no prefix is plain sampling bit for bit, the per-token flow times agree between
//! the cached step and the full joint forward (π0's time MLP and π0.5's adaRMSNorm), the loss
//! leaves the committed actions out, and a checkpoint not trained for it is refused.

use candle_core::{DType, Device, Tensor};
use chunkrt_policy::model::{FlowTimes, PrefixCache};
use chunkrt_policy::{Conditioning, RawObservation};

#[path = "common/fixture.rs"]
mod fixture;
use fixture::{data, maxdiff, raw_frames};

/// Deterministic values in [-1, 1) [1, H, A].
fn values(h: usize, a: usize, seed: u64) -> Tensor {
    let v: Vec<f32> = (0..h * a)
        .map(|i| ((i as u64 * 2654435761 + seed * 97) % 2000) as f32 / 1000.0 - 1.0)
        .collect();
    Tensor::from_vec(v, (1, h, a), &Device::Cpu).unwrap()
}

fn rows(t: &Tensor, lo: usize, n: usize) -> Tensor {
    t.narrow(1, lo, n).unwrap()
}

/// Fixture `name` with its prefix cache filled.
fn cached(name: &str) -> (fixture::Fixture, PrefixCache) {
    let f = fixture::load(name);
    let mut cache = None;
    f.model.fill_cache(&f.inputs, &mut cache, false).unwrap();
    (f, cache.expect("a filled cache"))
}

#[test]
fn committed_actions_come_back_exactly_and_steer_the_rest() {
    for name in ["pi05_tiny", "pi0_tiny"] {
        let (f, cache) = cached(name);
        let (m, c) = (&f.model, &cache);
        let (h, a) = (m.cfg.action_horizon, m.cfg.action_dim);
        let noise = values(h, a, 1);
        let y = values(h, a, 2);
        let plain = m.denoise(c, &noise, 10).unwrap().actions;
        // no committed prefix: the plain sampler, bit for bit
        let zero = m
            .denoise_committed(c, &noise, 10, &y, &[0])
            .unwrap()
            .actions;
        assert_eq!(maxdiff(&plain, &zero), 0.0, "{name}: d = 0");
        let d = 3;
        let out = m
            .denoise_committed(c, &noise, 10, &y, &[d])
            .unwrap()
            .actions;
        // the committed rows are returned as given
        assert_eq!(maxdiff(&rows(&out, 0, d), &rows(&y, 0, d)), 0.0, "{name}");
        // and the generated rows see them (bidirectional attention among action tokens)
        let moved = maxdiff(&rows(&out, d, h - d), &rows(&plain, d, h - d));
        assert!(moved > 1e-4, "{name}: generated rows moved {moved}");
        // the rows past the prefix in y are ignored
        let y2 = Tensor::cat(&[&rows(&y, 0, d), &rows(&values(h, a, 9), d, h - d)], 1).unwrap();
        let out2 = m
            .denoise_committed(c, &noise, 10, &y2, &[d])
            .unwrap()
            .actions;
        assert_eq!(maxdiff(&out, &out2), 0.0, "{name}");
        // bad shapes are errors, not panics
        assert!(m.denoise_committed(c, &noise, 10, &y, &[h]).is_err());
        assert!(m.denoise_committed(c, &noise, 10, &y, &[1, 1]).is_err());
        let short = rows(&y, 0, h - 1);
        assert!(m.denoise_committed(c, &noise, 10, &short, &[1]).is_err());
    }
}

#[test]
fn per_token_times_agree_between_cached_step_and_joint_forward() {
    for name in ["pi05_tiny", "pi0_tiny"] {
        let (f, cache) = cached(name);
        let (m, c) = (&f.model, &cache);
        let (h, a) = (m.cfg.action_horizon, m.cfg.action_dim);
        let x = values(h, a, 3);
        let t = [0.6f32];
        // an all-zero prefix is the per-row time
        let none = m.velocity_at(c, &x, &t, false).unwrap();
        let zeros = FlowTimes {
            t: &t,
            committed: Some(&[0]),
        };
        assert_eq!(
            maxdiff(&none, &m.velocity_at(c, &x, zeros, false).unwrap()),
            0.0
        );
        let times = FlowTimes {
            t: &t,
            committed: Some(&[4]),
        };
        let cached = m.velocity_at(c, &x, times, false).unwrap();
        let diffable = m.velocity_at(c, &x, times, true).unwrap();
        let embs = m.embed_prefix(&f.inputs).unwrap();
        let full = m
            .velocity_uncached(&f.inputs, &embs, &x, times, false)
            .unwrap();
        let e = maxdiff(&cached, &full);
        assert!(e < 1e-4, "{name}: cached vs joint forward {e}");
        let e = maxdiff(&cached, &diffable);
        assert!(e < 1e-4, "{name}: fast vs differentiable {e}");
        // the clean tokens' time reaches the output
        assert!(maxdiff(&cached, &none) > 1e-4, "{name}");
    }
}

#[test]
fn the_loss_leaves_committed_actions_out() {
    let f = fixture::load("pi05_tiny");
    let m = &f.model;
    let (h, a) = (m.cfg.action_horizon, m.cfg.action_dim);
    let actions = values(h, a, 4);
    let noise = values(h, a, 5);
    let time = Tensor::new(&[0.7f32], &Device::Cpu).unwrap();
    let embs = m.embed_prefix(&f.inputs).unwrap();
    let run = |committed: Option<&[usize]>| {
        m.loss_multi(
            &f.inputs, &embs, &actions, &noise, &time, committed, 1, false, None,
        )
        .unwrap()
        .0
    };
    let plain = run(None);
    let zero = run(Some(&[0]));
    assert_eq!(maxdiff(&plain.per_element, &zero.per_element), 0.0);
    let d = 4;
    let out = run(Some(&[d]));
    let pe = out.per_element.to_dtype(DType::F32).unwrap();
    assert_eq!(
        rows(&pe, 0, d)
            .abs()
            .unwrap()
            .sum_all()
            .unwrap()
            .to_scalar::<f32>()
            .unwrap(),
        0.0
    );
    let free_sum = rows(&pe, d, h - d)
        .sum_all()
        .unwrap()
        .to_scalar::<f32>()
        .unwrap();
    let mean = out.mean.to_scalar::<f32>().unwrap();
    let want = free_sum / ((h - d) * a) as f32;
    assert!(
        (mean - want).abs() <= 1e-6 * want.abs().max(1.0),
        "{mean} vs {want}"
    );
    // the differentiable form computes the same loss
    let diff = m
        .loss_multi(
            &f.inputs,
            &embs,
            &actions,
            &noise,
            &time,
            Some(&[d]),
            1,
            true,
            None,
        )
        .unwrap()
        .0;
    let e = (diff.mean.to_scalar::<f32>().unwrap() - mean).abs();
    assert!(e < 1e-4 * mean.abs().max(1.0), "{e}");
    // bad lengths are errors
    assert!(m
        .loss_multi(
            &f.inputs,
            &embs,
            &actions,
            &noise,
            &time,
            Some(&[h]),
            1,
            false,
            None
        )
        .is_err());
}

/// The pi05_tiny fixture checkpoint copied to a temporary directory with `rtc_prefix_max` set
/// in its config.json.
fn trained_copy(max: usize) -> std::path::PathBuf {
    let src = data("pi05_tiny");
    let dir =
        std::env::temp_dir().join(format!("chunkrt-rtc-trained-{}-{max}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    for e in std::fs::read_dir(&src).unwrap() {
        let p = e.unwrap().path();
        std::fs::copy(&p, dir.join(p.file_name().unwrap())).unwrap();
    }
    let cfg = std::fs::read_to_string(src.join("config.json")).unwrap();
    let mut v: serde_json::Value = serde_json::from_str(&cfg).unwrap();
    v["rtc_prefix_max"] = max.into();
    std::fs::write(dir.join("config.json"), v.to_string()).unwrap();
    dir
}

#[test]
fn the_runtime_gives_the_committed_actions_in_robot_units() {
    let (frames, state) =
        fixture::raw_observation("pi05_tiny", &["base_0_rgb", "left_wrist_0_rgb"]);
    let raw = raw_frames(&frames);
    let obs = RawObservation {
        frames: &raw,
        joint_positions: &state,
        prompt: "pick up the red block",
    };
    let pc = chunkrt_controller::config::PolicyConfig::default();
    let n = state.len();
    // a checkpoint not trained for it refuses, with the reason
    let mut plain = chunkrt_controller::inference::load_policy(&data("pi05_tiny"), &pc).unwrap();
    assert_eq!(plain.committed_max(), 0);
    let err = plain
        .infer(&obs, &Conditioning::Committed(&state))
        .unwrap_err()
        .to_string();
    assert!(err.contains("rtc_prefix_max"), "{err}");

    let dir = trained_copy(3);
    let mut p = chunkrt_controller::inference::load_policy(&dir, &pc).unwrap();
    let mut fresh = chunkrt_controller::inference::load_policy(&dir, &pc).unwrap();
    assert_eq!(p.committed_max(), 3);
    let h = p.horizon();
    // the previous chunk: a ramp away from the state, in robot units
    let prev: Vec<f64> = (0..h * n)
        .map(|i| state[i % n] + 0.01 * (i / n) as f64 * if i % 2 == 0 { 1.0 } else { -1.0 })
        .collect();
    // no rows: plain sampling (same seed, same noise)
    assert_eq!(
        p.infer(&obs, &Conditioning::Committed(&[])).unwrap(),
        fresh.infer(&obs, &Conditioning::Fresh).unwrap()
    );
    // 5 rows given, the checkpoint's maximum 3 kept: the chunk starts with exactly those
    let out = p
        .infer(&obs, &Conditioning::Committed(&prev[..5 * n]))
        .unwrap();
    for i in 0..3 * n {
        let e = (out[i] - prev[i]).abs();
        // normalised and un-normalised in f32
        assert!(
            e < 1e-5 * prev[i].abs().max(1.0),
            "row {} joint {}: {e}",
            i / n,
            i % n
        );
    }
    assert!((3 * n..4 * n).any(|i| (out[i] - prev[i]).abs() > 1e-4));
    assert!(p
        .infer(&obs, &Conditioning::Committed(&prev[..n + 1]))
        .is_err());
    let mut bad = prev.clone();
    bad[0] = f64::NAN;
    assert!(p.infer(&obs, &Conditioning::Committed(&bad[..n])).is_err());
    std::fs::remove_dir_all(&dir).ok();
}
