//! Pre/post-processing, checkpoints, the runtime API and the CLI, against the fixtures.

use std::collections::HashMap;
use std::path::PathBuf;

use candle_core::{DType, Device, Tensor};
use chunkrt_policy::checkpoint;
use chunkrt_policy::preprocess::{
    discretize_state, normalize, pi05_prompt, resize_with_pad, unnormalize, NormMode,
    PromptTokenizer, Stats,
};
use chunkrt_policy::{Conditioning, ConfigOverrides, RawFrame, RawObservation};

#[path = "common/fixture.rs"]
mod fixture;
use fixture::maxdiff;

fn data(name: &str) -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR"))
        .join("tests/data")
        .join(name)
}

fn inputs(name: &str) -> HashMap<String, Tensor> {
    candle_core::safetensors::load(data(name).join("inputs.safetensors"), &Device::Cpu).unwrap()
}

#[test]
fn resize_with_pad_matches_openpi_within_one_level() {
    let inp = inputs("pi0_tiny");
    for cam in ["base_0_rgb", "left_wrist_0_rgb", "right_wrist_0_rgb"] {
        let raw = &inp[&format!("image_raw_uint8.{cam}")];
        let (_, h, w, _) = raw.dims4().unwrap();
        let px = raw.flatten_all().unwrap().to_vec1::<u8>().unwrap();
        let ours = resize_with_pad(&px, h, w, 224, 224).unwrap();
        let theirs = inp[&format!("image_resized_uint8.{cam}")]
            .flatten_all()
            .unwrap()
            .to_vec1::<u8>()
            .unwrap();
        let max = ours
            .iter()
            .zip(&theirs)
            .map(|(a, b)| (*a as i32 - *b as i32).abs())
            .max()
            .unwrap();
        let off = ours.iter().zip(&theirs).filter(|(a, b)| a != b).count();
        println!(
            "{cam} {h}x{w}: max level diff {max}, {off} of {} values differ",
            ours.len()
        );
        assert!(max <= 1, "{cam}: max diff {max}");
    }
    // bad buffers are errors, not panics
    assert!(resize_with_pad(&[0u8; 5], 2, 2, 224, 224).is_err());
}

#[test]
fn pi05_state_discretisation_prompt_and_tokens() {
    let inp = inputs("pi05_tiny");
    let state: Vec<f32> = inp["state_unpadded.0"].to_vec1().unwrap();
    let bins = discretize_state(&state);
    let want: Vec<i64> = inp["state_discretized.0"].to_vec1().unwrap();
    assert_eq!(bins, want);
    let prompt = pi05_prompt(" pick_up the red block\n", &bins);
    assert_eq!(
        prompt,
        "Task: pick up the red block , State: -1 255 128 19 143 178;\nAction: ".replace(" ,", ",")
    );
    let tok = PromptTokenizer::ByteStandIn;
    let (ids, mask) = tok
        .tokenize("pick up the red block", Some(&bins), 200)
        .unwrap();
    let want_ids: Vec<i64> = inp["tokenized_prompt"]
        .flatten_all()
        .unwrap()
        .to_vec1()
        .unwrap();
    assert_eq!(ids.iter().map(|&x| x as i64).collect::<Vec<_>>(), want_ids);
    let want_mask: Vec<u8> = inp["tokenized_prompt_mask"]
        .flatten_all()
        .unwrap()
        .to_vec1()
        .unwrap();
    assert_eq!(mask.iter().map(|&m| m as u8).collect::<Vec<_>>(), want_mask);
    // edges: below -1 -> -1, 1.0 -> 255, 0 -> 128
    assert_eq!(
        discretize_state(&[-1.5, -1.0, 0.0, 0.9921875, 1.0, 3.0]),
        vec![-1, 0, 128, 255, 255, 255]
    );
}

#[test]
fn pi0_prompt_tokens_match_fixture() {
    let inp = inputs("pi0_tiny");
    let (ids, _) = PromptTokenizer::ByteStandIn
        .tokenize("pick up the red block", None, 48)
        .unwrap();
    let want: Vec<i64> = inp["tokenized_prompt"]
        .flatten_all()
        .unwrap()
        .to_vec1()
        .unwrap();
    assert_eq!(ids.iter().map(|&x| x as i64).collect::<Vec<_>>(), want);
}

#[test]
fn hf_tokenizer_json_is_used_with_bos() {
    let dir = std::env::temp_dir().join(format!("chunkrt_tok_{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    let json = r#"{"version":"1.0","truncation":null,"padding":null,"added_tokens":[],
      "normalizer":null,"pre_tokenizer":{"type":"Whitespace"},"post_processor":null,"decoder":null,
      "model":{"type":"WordLevel","vocab":{"<pad>":0,"<eos>":1,"<bos>":2,"<unk>":3,"pick":4,"up":5,"the":6,"block":7,"Task":8,":":9,",":10,"State":11,";":12,"Action":13,"1":14,"2":15},"unk_token":"<unk>"}}"#;
    let path = dir.join("tokenizer.json");
    std::fs::write(&path, json).unwrap();
    let tok = PromptTokenizer::from_file(&path).unwrap();
    let (ids, mask) = tok.tokenize("pick up the block", None, 8).unwrap();
    assert_eq!(&ids[..5], &[2, 4, 5, 6, 7]);
    assert_eq!(
        mask.iter().filter(|m| **m).count(),
        5,
        "newline has no token in this vocab"
    );
    let (ids, _) = tok.tokenize("pick up", Some(&[1, 2]), 16).unwrap();
    assert_eq!(&ids[..13], &[2, 8, 9, 4, 5, 10, 11, 9, 14, 15, 12, 13, 9]);
    let (ids, mask) = tok.tokenize("pick up the block", None, 3).unwrap();
    assert_eq!((ids.len(), mask.iter().all(|m| *m)), (3, true), "truncated");
    assert!(PromptTokenizer::from_file(&dir.join("missing.json")).is_err());
    std::fs::remove_dir_all(&dir).ok();
}

#[test]
fn normalisation_round_trips() {
    let st = Stats {
        mean: vec![1.0, -2.0],
        std: vec![0.5, 2.0],
        q01: Some(vec![0.0, -4.0]),
        q99: Some(vec![2.0, 4.0]),
    };
    for mode in [NormMode::ZScore, NormMode::Quantile] {
        let mut x = vec![1.5f32, 0.0, 7.0];
        normalize(&mut x, &st, mode).unwrap();
        if mode == NormMode::Quantile {
            assert!((x[0] - 0.5).abs() < 1e-5 && (x[1] - 0.0).abs() < 1e-5);
        } else {
            assert!((x[0] - 1.0).abs() < 1e-5 && (x[1] - 1.0).abs() < 1e-5);
        }
        assert_eq!(x[2], 7.0, "dims beyond the stats are untouched");
        unnormalize(&mut x, &st, mode).unwrap();
        assert!((x[0] - 1.5).abs() < 1e-5 && x[1].abs() < 1e-5);
    }
    let no_q = Stats {
        mean: vec![0.0],
        std: vec![1.0],
        q01: None,
        q99: None,
    };
    assert!(normalize(&mut [0.0], &no_q, NormMode::Quantile).is_err());
}

#[test]
fn checkpoint_errors_list_every_bad_tensor_and_lerobot_prefix_and_bf16_load() {
    let dir = data("pi05_tiny");
    let (mut t, dt) = checkpoint::load_tensors(&dir.join("model.safetensors")).unwrap();
    assert_eq!(dt, vec![DType::F32]);
    let cfg = checkpoint::resolve_config(
        &dir,
        &checkpoint::shapes_of(&t),
        &ConfigOverrides::default(),
    )
    .unwrap();
    assert_eq!(cfg.vocab_size, 1024);
    checkpoint::check_tensors(&cfg, &checkpoint::shapes_of(&t)).unwrap();
    t.remove("action_in_proj.weight");
    t.insert(
        "time_mlp_in.bias".into(),
        Tensor::zeros(7, DType::F32, &Device::Cpu).unwrap(),
    );
    let e = checkpoint::check_tensors(&cfg, &checkpoint::shapes_of(&t))
        .unwrap_err()
        .to_string();
    println!("{e}");
    assert!(e.contains("2 problem(s)"), "{e}");
    assert!(e.contains("missing action_in_proj.weight [32, 8]"), "{e}");
    assert!(
        e.contains("mismatched time_mlp_in.bias: found [7], expected [32]"),
        "{e}"
    );

    // LeRobot naming (model. prefix) in bf16 loads to the same model (within bf16 rounding)
    let tmp = std::env::temp_dir().join(format!("chunkrt_lerobot_{}", std::process::id()));
    std::fs::create_dir_all(&tmp).unwrap();
    let (orig, _) = checkpoint::load_tensors(&dir.join("model.safetensors")).unwrap();
    let lerobot: HashMap<String, Tensor> = orig
        .iter()
        .map(|(k, v)| (format!("model.{k}"), v.to_dtype(DType::BF16).unwrap()))
        .collect();
    candle_core::safetensors::save(&lerobot, tmp.join("model.safetensors")).unwrap();
    std::fs::copy(dir.join("config.json"), tmp.join("config.json")).unwrap();
    let loaded = checkpoint::load(&tmp, &ConfigOverrides::default()).unwrap();
    assert_eq!(loaded.stored_dtypes, vec![DType::BF16]);
    let report = checkpoint::inspect(&tmp, &Default::default()).unwrap();
    assert!(report.contains("kind: pi05"), "{report}");
    assert!(report.contains("missing: none"), "{report}");
    // no config.json: the preset (gemma_2b ...) does not fit a tiny checkpoint -> a listed error
    std::fs::remove_file(tmp.join("config.json")).unwrap();
    let e = checkpoint::load(&tmp, &ConfigOverrides::default())
        .err()
        .expect("preset must not fit");
    assert!(
        e.to_string().contains("width is 2048") || e.to_string().contains("problem(s)"),
        "{e}"
    );
    std::fs::remove_dir_all(&tmp).ok();
}

#[test]
fn runtime_prepares_fixture_inputs_and_infers() {
    let dir = data("pi05_tiny");
    let pc = chunkrt_controller::config::PolicyConfig::default();
    let mut policy = chunkrt_controller::inference::load_policy(&dir, &pc).unwrap();
    let inp = inputs("pi05_tiny");
    let (frames, state) =
        fixture::raw_observation("pi05_tiny", &["base_0_rgb", "left_wrist_0_rgb"]);
    let raw = fixture::raw_frames(&frames);
    let obs = RawObservation {
        frames: &raw,
        joint_positions: &state,
        prompt: "pick up the red block",
    };
    let prepared = policy.prepare(&obs).unwrap();
    let ids: Vec<u32> = prepared.tokens.flatten_all().unwrap().to_vec1().unwrap();
    let want: Vec<i64> = inp["tokenized_prompt"]
        .flatten_all()
        .unwrap()
        .to_vec1()
        .unwrap();
    assert_eq!(ids.iter().map(|&x| x as i64).collect::<Vec<_>>(), want);
    assert_eq!(
        prepared.image_masks,
        vec![vec![true], vec![true], vec![false]]
    );
    let img = &prepared.images[0];
    let d = maxdiff(img, &inp["image.base_0_rgb"]);
    assert!(d <= 2.0 / 255.0 + 1e-6, "model image differs by {d}");
    let acts = policy.infer(&obs, &Conditioning::Fresh).unwrap();
    assert_eq!(acts.len(), 10 * 6);
    assert!(acts.iter().all(|a| a.is_finite()));
    // the cache buffers survive across calls and bad input is an error
    let acts2 = policy.infer(&obs, &Conditioning::Fresh).unwrap();
    assert_eq!(acts2.len(), acts.len());
    let bad = RawFrame {
        stride: 3,
        ..raw[0]
    };
    let frames_bad = [bad];
    assert!(policy
        .infer(
            &RawObservation {
                frames: &frames_bad,
                ..obs
            },
            &Conditioning::Fresh
        )
        .is_err());
    assert!(policy
        .infer(
            &RawObservation {
                joint_positions: &[f64::NAN],
                ..obs
            },
            &Conditioning::Fresh
        )
        .is_err());
    assert!(policy
        .infer(
            &RawObservation {
                joint_positions: &[0.0; 9],
                ..obs
            },
            &Conditioning::Fresh
        )
        .is_err());
}

#[test]
fn cli_sample_and_inspect() {
    let exe = env!("CARGO_BIN_EXE_chunkrt");
    let dir = data("pi0_tiny");
    let out =
        std::env::temp_dir().join(format!("chunkrt_sample_{}.safetensors", std::process::id()));
    for extra in [&[][..], &["--no-cache"][..]] {
        let st = std::process::Command::new(exe)
            .args(["sample", "--checkpoint"])
            .arg(&dir)
            .arg("--inputs")
            .arg(dir.join("inputs.safetensors"))
            .arg("--output")
            .arg(&out)
            .args(extra)
            .output()
            .unwrap();
        assert!(
            st.status.success(),
            "{}",
            String::from_utf8_lossy(&st.stderr)
        );
        let got = candle_core::safetensors::load(&out, &Device::Cpu).unwrap();
        let want =
            candle_core::safetensors::load(dir.join("outputs.safetensors"), &Device::Cpu).unwrap();
        let d = maxdiff(&got["actions"], &want["actions"]);
        assert!(d < 5e-4, "cli actions {extra:?} differ by {d}");
        assert_eq!(got["v_t_step0"].dims(), &[1, 10, 8]);
    }
    std::fs::remove_file(&out).ok();
    let st = std::process::Command::new(exe)
        .arg("inspect")
        .arg(&dir)
        .output()
        .unwrap();
    let s = String::from_utf8_lossy(&st.stdout);
    assert!(
        st.status.success() && s.contains("kind: pi0") && s.contains("missing: none"),
        "{s}"
    );
    let st = std::process::Command::new(exe)
        .arg("inspect")
        .arg(data("nope"))
        .output()
        .unwrap();
    assert!(!st.status.success());
}

#[test]
fn presets_have_openpi_dimensions_and_parameter_counts() {
    use chunkrt_policy::config::{ModelConfig, ModelKind};
    let count = |cfg: &ModelConfig| -> f64 {
        checkpoint::expected_tensors(cfg)
            .iter()
            .map(|(_, s)| s.iter().product::<usize>() as f64)
            .sum()
    };
    let pi0 = ModelConfig::preset("pi0").unwrap();
    let pi05 = ModelConfig::preset("pi05").unwrap();
    assert_eq!(pi0.kind, ModelKind::Pi0);
    assert_eq!(pi05.kind, ModelKind::Pi05);
    for c in [&pi0, &pi05] {
        // SigLIP So400m/14 at 224, gemma_2b + gemma_300m, 50 x 32 actions
        assert_eq!(
            (
                c.vision.hidden_size,
                c.vision.num_hidden_layers,
                c.vision.num_tokens()
            ),
            (1152, 27, 256)
        );
        assert_eq!(
            (c.paligemma.width, c.paligemma.depth, c.paligemma.mlp_dim),
            (2048, 18, 16_384)
        );
        assert_eq!(
            (c.action_expert.width, c.action_expert.mlp_dim),
            (1024, 4096)
        );
        assert_eq!(
            (c.action_horizon, c.action_dim, c.vocab_size),
            (50, 32, 257_152)
        );
        c.validate().unwrap();
    }
    assert_eq!((pi0.max_token_len, pi05.max_token_len), (48, 200));
    // openpi's π0 has about 3.3 B parameters (PaliGemma 2.9 B + the 300 M action expert)
    let n = count(&pi0);
    assert!((3.2e9..3.6e9).contains(&n), "{n}");
    let n05 = count(&pi05);
    assert!((3.2e9..3.7e9).contains(&n05), "{n05}");
    assert!(ModelConfig::preset("pi1").is_err());
}

#[test]
fn toml_model_overrides_reach_the_loaded_model() {
    let text = std::fs::read_to_string(
        PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("config/pi05_tiny.toml"),
    )
    .unwrap()
    .replace(
        "[execution]",
        "[policy.model]\naction_horizon = 6\ncameras = [\"base_0_rgb\", \"left_wrist_0_rgb\"]\n\n[execution]",
    );
    let dir = std::env::temp_dir().join(format!("chunkrt-ovr-{}", std::process::id()));
    std::fs::create_dir_all(dir.join("config")).unwrap();
    let path = dir.join("config/over.toml");
    std::fs::write(&path, &text).unwrap();
    let mut cfg = chunkrt_controller::config::Config::load(&path).unwrap();
    cfg.policy.checkpoint = Some(data("pi05_tiny"));
    let p = chunkrt_controller::inference::load_policy(&data("pi05_tiny"), &cfg.policy).unwrap();
    assert_eq!(p.horizon(), 6);
    assert_eq!(p.model().cfg.cameras.len(), 2);
    // out-of-range values are rejected at the boundary, naming the key
    let bad = text.replace("action_horizon = 6", "action_horizon = 0");
    std::fs::write(&path, &bad).unwrap();
    let e = chunkrt_controller::config::Config::load(&path)
        .unwrap_err()
        .to_string();
    assert!(e.contains("policy.model.action_horizon"), "{e}");
    let bad = text.replace("action_horizon = 6", "horizon = 6");
    std::fs::write(&path, &bad).unwrap();
    assert!(chunkrt_controller::config::Config::load(&path).is_err());
    std::fs::remove_dir_all(&dir).ok();
}

/// The fixture's unpadded robot state.
fn fixture_state(name: &str) -> Vec<f64> {
    inputs(name)["state_unpadded.0"]
        .to_vec1::<f32>()
        .unwrap()
        .iter()
        .map(|&x| x as f64)
        .collect()
}

/// `delta_action_mask` (config.json or `[policy.model]`): the model's actions on those dims are
/// relative to the observed state, so the runtime adds the state there and nowhere else. Same
/// checkpoint, same noise seed, with and without the mask: the difference is the state.
#[test]
fn delta_action_mask_adds_the_observed_state_on_its_dims() {
    let dir = data("pi05_tiny");
    let state: Vec<f64> = fixture_state("pi05_tiny")
        .iter()
        .map(|x| x + 0.25)
        .collect();
    let n = state.len();
    let obs = RawObservation {
        frames: &[],
        joint_positions: &state,
        prompt: "pick up the red block",
    };
    let absolute = chunkrt_controller::config::PolicyConfig::default();
    let mut delta = absolute.clone();
    let mask: Vec<bool> = (0..n).map(|d| d % 2 == 0).collect();
    delta.model.delta_action_mask = Some(mask.clone());
    let a = chunkrt_controller::inference::load_policy(&dir, &absolute)
        .unwrap()
        .infer(&obs, &Conditioning::Fresh)
        .unwrap();
    let mut p = chunkrt_controller::inference::load_policy(&dir, &delta).unwrap();
    assert_eq!(p.model().cfg.delta_action_mask, mask);
    let b = p.infer(&obs, &Conditioning::Fresh).unwrap();
    assert_eq!(a.len(), b.len());
    for (i, (x, y)) in a.iter().zip(&b).enumerate() {
        let d = i % n;
        let want = if mask[d] { state[d] } else { 0.0 };
        assert!(
            (y - x - want).abs() < 1e-9,
            "action {i}: {y} - {x} != {want}"
        );
    }
    // a mask longer than the model's action dim is rejected when loading
    delta.model.delta_action_mask = Some(vec![true; 64]);
    assert!(chunkrt_controller::inference::load_policy(&dir, &delta).is_err());
}

/// `policy.precision = "bf16"`: the matrix products run in bf16 (Intel AMX or AVX512-BF16); the
/// actions stay within bf16 rounding of the f32 ones (same checkpoint, observation and noise
/// seed). Where the CPU has neither, the setting falls back to f32 and the actions are equal.
#[test]
fn bf16_precision_stays_close_to_f32() {
    let dir = data("pi05_tiny");
    let state = fixture_state("pi05_tiny");
    let obs = RawObservation {
        frames: &[],
        joint_positions: &state,
        prompt: "pick up the red block",
    };
    let f32_cfg = chunkrt_controller::config::PolicyConfig::default();
    let mut bf16_cfg = f32_cfg.clone();
    bf16_cfg.precision = chunkrt_controller::config::Precision::Bf16;
    let a = chunkrt_controller::inference::load_policy(&dir, &f32_cfg)
        .unwrap()
        .infer(&obs, &Conditioning::Fresh)
        .unwrap();
    let b = chunkrt_controller::inference::load_policy(&dir, &bf16_cfg)
        .unwrap()
        .infer(&obs, &Conditioning::Fresh)
        .unwrap();
    let rms = (a.iter().map(|x| x * x).sum::<f64>() / a.len() as f64).sqrt();
    let worst = a
        .iter()
        .zip(&b)
        .map(|(x, y)| (x - y).abs())
        .fold(0.0, f64::max);
    println!("bf16 vs f32: max |diff| {worst:.5}, actions RMS {rms:.4}");
    if chunkrt_policy::packed::bf16_backend().is_none() {
        eprintln!("no bf16 kernel here: bf16 fell back to f32");
        assert_eq!(worst, 0.0);
        return;
    }
    assert!(
        worst > 0.0,
        "bf16 gave bit-identical actions: the bf16 kernels were not taken"
    );
    assert!(
        worst < 0.05 * rms.max(1e-6),
        "bf16 differs by {worst} (RMS {rms})"
    );
}

/// A checkpoint's config.json cannot crash the controller or make it allocate without bound:
/// each out-of-range size is a load error that names its key (issue 16 point 7), and `chunkrt
/// sample` exits non-zero with it.
#[test]
fn config_json_sizes_are_bounded_with_the_key_named() {
    let dir = data("pi05_tiny");
    let base: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(dir.join("config.json")).unwrap()).unwrap();
    let tmp = std::env::temp_dir().join(format!("chunkrt_cfg_bounds_{}", std::process::id()));
    std::fs::create_dir_all(&tmp).unwrap();
    std::fs::copy(dir.join("model.safetensors"), tmp.join("model.safetensors")).unwrap();
    let cases: [(&[&str], serde_json::Value, &str); 6] = [
        (&["vision", "image_size"], 0.into(), "vision.image_size = 0"),
        (
            &["paligemma", "depth"],
            1_000_000_000u64.into(),
            "paligemma.depth",
        ),
        (
            &["action_horizon"],
            10_000_000_000u64.into(),
            "action_horizon",
        ),
        (
            &["max_token_len"],
            10_000_000_000u64.into(),
            "max_token_len",
        ),
        (
            &["num_denoise_steps"],
            1_000_000_000_000u64.into(),
            "num_denoise_steps",
        ),
        (&["rope_theta"], (-1.0).into(), "rope_theta"),
    ];
    for (path, value, want) in cases {
        let mut cfg = base.clone();
        let mut node = &mut cfg;
        for k in &path[..path.len() - 1] {
            node = &mut node[*k];
        }
        node[path[path.len() - 1]] = value;
        std::fs::write(tmp.join("config.json"), cfg.to_string()).unwrap();
        let e = checkpoint::load(&tmp, &ConfigOverrides::default())
            .err()
            .unwrap_or_else(|| panic!("{path:?} loaded"))
            .to_string();
        assert!(e.contains(want), "{path:?}: {e}");
    }
    // the CLI: a clear error and a non-zero exit
    let st = std::process::Command::new(env!("CARGO_BIN_EXE_chunkrt"))
        .arg("inspect")
        .arg(&tmp)
        .output()
        .unwrap();
    assert!(!st.status.success());
    assert!(
        String::from_utf8_lossy(&st.stderr).contains("rope_theta"),
        "{}",
        String::from_utf8_lossy(&st.stderr)
    );
    std::fs::remove_dir_all(&tmp).ok();
}

/// `execution.execute_horizon` longer than the loaded policy's chunk is refused at load (it
/// made the controller stop and go, HOLDing every 0.9 s).
#[test]
fn execute_horizon_beyond_the_chunk_is_refused() {
    let path = concat!(env!("CARGO_MANIFEST_DIR"), "/config/pi05_tiny.toml");
    let mut cfg = chunkrt_controller::config::Config::load(std::path::Path::new(path)).unwrap();
    cfg.execution.execute_horizon = 1000;
    let e = chunkrt_controller::inference::PolicySource::load(&cfg)
        .err()
        .expect("refused")
        .to_string();
    assert!(e.contains("execution.execute_horizon = 1000"), "{e}");
}

/// norm_stats.json is checked at load, not at the first inference: pi0.5 needs q01/q99 (it was
/// found missing only at each inference, the controller stuck in STARTING), and statistics
/// shorter than the robot's joints are refused (they were accepted).
#[test]
fn norm_stats_are_checked_at_load() {
    let src = std::path::PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("models/reach_pi05");
    let tmp = std::env::temp_dir().join(format!("chunkrt_norm_{}", std::process::id()));
    std::fs::create_dir_all(&tmp).unwrap();
    for f in ["config.json", "model.safetensors", "tokenizer.json"] {
        std::fs::copy(src.join(f), tmp.join(f)).unwrap();
    }
    let base: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(src.join("norm_stats.json")).unwrap())
            .unwrap();
    let mut cfg = chunkrt_controller::config::Config::embedded_default();
    cfg.policy.checkpoint = Some(tmp.clone());
    let load = |ns: &serde_json::Value| {
        std::fs::write(tmp.join("norm_stats.json"), ns.to_string()).unwrap();
        chunkrt_controller::inference::PolicySource::load(&cfg)
            .err()
            .map(|e| format!("{e:#}"))
    };
    assert_eq!(load(&base), None, "the committed statistics load");
    let mut no_q = base.clone();
    no_q["norm_stats"]["actions"]
        .as_object_mut()
        .unwrap()
        .remove("q01");
    let e = load(&no_q).expect("missing q01 refused");
    assert!(e.contains("norm_stats actions") && e.contains("q01"), "{e}");
    let mut short = base.clone();
    for k in ["mean", "std", "q01", "q99"] {
        let v = short["norm_stats"]["state"][k].as_array_mut().unwrap();
        v.truncate(2);
    }
    let e = load(&short).expect("short statistics refused");
    assert!(
        e.contains("norm_stats state: 2 values, the robot has 4 joints"),
        "{e}"
    );
    std::fs::remove_dir_all(&tmp).ok();
}

/// A checkpoint without tokenizer.json no longer falls back silently to the byte stand-in (a
/// real policy's arm went to its joint limit): it must declare the stand-in in config.json.
#[test]
fn a_missing_tokenizer_is_an_error_unless_declared() {
    let dir = data("pi05_tiny");
    let tmp = std::env::temp_dir().join(format!("chunkrt_tok_{}", std::process::id()));
    std::fs::create_dir_all(&tmp).unwrap();
    std::fs::copy(dir.join("model.safetensors"), tmp.join("model.safetensors")).unwrap();
    let mut cfg: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(dir.join("config.json")).unwrap()).unwrap();
    let opts = chunkrt_policy::LoadOptions::default();
    // the fixture declares its stand-in ("STAND-IN ..."): loads
    std::fs::write(tmp.join("config.json"), cfg.to_string()).unwrap();
    chunkrt_policy::Policy::load(&tmp, &opts).expect("declared stand-in loads");
    cfg.as_object_mut().unwrap().remove("tokenizer");
    std::fs::write(tmp.join("config.json"), cfg.to_string()).unwrap();
    let e = chunkrt_policy::Policy::load(&tmp, &opts)
        .err()
        .expect("refused")
        .to_string();
    assert!(
        e.contains("no tokenizer") && e.contains("--tokenizer"),
        "{e}"
    );
    cfg["tokenizer"] = "byte_stand_in".into();
    std::fs::write(tmp.join("config.json"), cfg.to_string()).unwrap();
    chunkrt_policy::Policy::load(&tmp, &opts).expect("declared stand-in loads");
    std::fs::remove_dir_all(&tmp).ok();
}

/// A copy of the committed reach checkpoint in a temporary folder of its own.
fn reach_copy(tag: &str) -> std::path::PathBuf {
    let src = std::path::PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("models/reach_pi05");
    let tmp = std::env::temp_dir().join(format!("chunkrt_{tag}_{}", std::process::id()));
    std::fs::create_dir_all(&tmp).unwrap();
    for f in [
        "config.json",
        "model.safetensors",
        "tokenizer.json",
        "norm_stats.json",
    ] {
        std::fs::copy(src.join(f), tmp.join(f)).unwrap();
    }
    tmp
}

fn load_reach(dir: &std::path::Path) -> Option<String> {
    let mut cfg = chunkrt_controller::config::Config::embedded_default();
    cfg.policy.checkpoint = Some(dir.to_path_buf());
    chunkrt_controller::inference::PolicySource::load(&cfg)
        .err()
        .map(|e| format!("{e:#}"))
}

/// Statistics without spread on a robot joint (q01 == q99, or std 0) divide by ~1e-6: they drove
/// the arm to its limits. Refused at load, naming the joints.
#[test]
fn flat_norm_stats_are_refused_naming_the_joints() {
    let tmp = reach_copy("flat");
    let mut ns: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(tmp.join("norm_stats.json")).unwrap())
            .unwrap();
    let q01 = ns["norm_stats"]["actions"]["q01"][2].clone();
    ns["norm_stats"]["actions"]["q99"][2] = q01;
    std::fs::write(tmp.join("norm_stats.json"), ns.to_string()).unwrap();
    let e = load_reach(&tmp).expect("flat statistics refused");
    assert!(e.contains("joint(s) [2] have no spread"), "{e}");
    std::fs::remove_dir_all(&tmp).ok();
}

/// A tokenizer whose ids run past the model's embedding table is refused at load (token ids
/// beyond the vocabulary left the controller in STARTING for as long as it ran).
#[test]
fn a_tokenizer_beyond_the_vocabulary_is_refused() {
    let tmp = reach_copy("vocab");
    let mut tok: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(tmp.join("tokenizer.json")).unwrap())
            .unwrap();
    let vocab = tok["model"]["vocab"].as_object_mut().unwrap();
    for i in 0..50 {
        let n = vocab.len();
        vocab.insert(format!("extra{i}"), serde_json::Value::from(n));
    }
    std::fs::write(tmp.join("tokenizer.json"), tok.to_string()).unwrap();
    let e = load_reach(&tmp).expect("refused");
    assert!(e.contains("embedding has 288 rows"), "{e}");
    std::fs::remove_dir_all(&tmp).ok();
}

/// Non-finite weights: the first chunk, computed at load on a synthetic observation, is not
/// finite, and the load says so (the controller stayed in STARTING with reason 0).
#[test]
fn non_finite_weights_fail_at_load() {
    let tmp = reach_copy("nan");
    let path = tmp.join("model.safetensors");
    let mut m = candle_core::safetensors::load(&path, &candle_core::Device::Cpu).unwrap();
    let (name, t) = m
        .iter()
        .find(|(k, _)| k.contains("action_out_proj.weight"))
        .map(|(k, t)| (k.clone(), t.clone()))
        .expect("the action head");
    let nan = (t.ones_like().unwrap() * f64::NAN).unwrap();
    m.insert(name, nan);
    candle_core::safetensors::save(&m, &path).unwrap();
    let e = load_reach(&tmp).expect("refused");
    assert!(e.contains("first chunk") && e.contains("non-finite"), "{e}");
    std::fs::remove_dir_all(&tmp).ok();
}

/// Side files are read only when regular and small: a FIFO as tokenizer.json hung `chunkrt
/// run` forever; /dev/zero as config.json was read to 4.2 GB.
#[test]
fn a_fifo_or_a_huge_side_file_is_a_clear_error() {
    let tmp = reach_copy("fifo");
    let tok = tmp.join("tokenizer.json");
    std::fs::remove_file(&tok).unwrap();
    let c = std::ffi::CString::new(tok.to_str().unwrap()).unwrap();
    // SAFETY: mkfifo(3) on a path we own
    assert_eq!(unsafe { libc::mkfifo(c.as_ptr(), 0o600) }, 0);
    let t0 = std::time::Instant::now();
    let e = load_reach(&tmp).expect("refused");
    assert!(e.contains("not a regular file"), "{e}");
    assert!(t0.elapsed() < std::time::Duration::from_secs(10));
    std::fs::remove_file(&tok).unwrap();
    let f = std::fs::File::create(tmp.join("config.json")).unwrap();
    f.set_len(chunkrt_policy::files::MAX_SIDE_FILE_BYTES + 1)
        .unwrap();
    std::fs::copy(
        std::path::PathBuf::from(env!("CARGO_MANIFEST_DIR"))
            .join("models/reach_pi05/tokenizer.json"),
        &tok,
    )
    .unwrap();
    let e = load_reach(&tmp).expect("refused");
    assert!(e.contains("at most"), "{e}");
    std::fs::remove_dir_all(&tmp).ok();
}

/// π0.5's prompt state is binned as openpi bins it: openpi normalises the client's f64 state in
/// f64 (numpy), so a state on a bin edge gets openpi's token. pi05_droid with q01 −1 and q99 1:
/// states −0.96875 and −0.9375 (edges 4 and 8 before the 1e-6 in the denominator) are bins 3
/// and 7 in openpi; binned from f32-normalised values they were 4 and 8 (issue 54 §5).
#[test]
fn pi05_prompt_state_is_binned_as_openpi_bins_it_at_the_edges() {
    use chunkrt_policy::openpi_config::{by_name, model_state};
    use chunkrt_policy::preprocess::NormStats;
    let cfg = by_name("pi05_droid").expect("pi05_droid");
    let n = cfg.robot.state_dim();
    let stats = Stats {
        mean: vec![0.0; n],
        std: vec![1.0; n],
        q01: Some(vec![-1.0; n]),
        q99: Some(vec![1.0; n]),
    };
    let ns = NormStats {
        state: stats.clone(),
        actions: stats,
    };
    let mut raw = vec![0.0; n];
    raw[0] = -0.96875;
    raw[1] = -0.9375;
    let m = model_state(Some(cfg), &[], Some(&ns), NormMode::Quantile, &raw, 32).unwrap();
    let bins = discretize_state(&m.prompt_state);
    println!(
        "pi05_droid, q01 -1, q99 1: states {:?} -> normalised {:?} -> bins {:?} (openpi: 3, 7)",
        &raw[..2],
        &m.prompt_state[..2],
        &bins[..2]
    );
    assert_eq!(&bins[..2], &[3, 7]);
}

/// Action statistics that would throw the arm are refused at load (issue 54 §2): the shipped
/// reach policy with its action q01 / q99 at ±999, or with every statistic in degrees (×57.3),
/// loaded under the demo robot and drove joints into their limits at full speed; now `run`'s
/// load (`PolicySource::load`) and `inspect --config` refuse both, naming the joints, with a
/// units hint for the degrees, and the shipped statistics still load.
#[test]
fn action_statistics_that_would_throw_the_arm_are_refused_at_load() {
    use chunkrt_controller::inference::PolicySource;
    let root = PathBuf::from(env!("CARGO_MANIFEST_DIR"));
    let shipped = root.join("models/reach_pi05");
    let text = std::fs::read_to_string(shipped.join("norm_stats.json")).unwrap();
    let base: serde_json::Value = serde_json::from_str(&text).unwrap();
    let scale = |v: &mut serde_json::Value, k: f64| {
        for part in ["state", "actions"] {
            for stat in ["mean", "std", "q01", "q99"] {
                if let Some(a) = v["norm_stats"][part][stat].as_array_mut() {
                    for x in a {
                        *x = serde_json::json!(x.as_f64().unwrap() * k);
                    }
                }
            }
        }
    };
    let mut wide = base.clone();
    let n = wide["norm_stats"]["actions"]["q01"]
        .as_array()
        .unwrap()
        .len();
    wide["norm_stats"]["actions"]["q01"] = serde_json::json!(vec![-999.0; n]);
    wide["norm_stats"]["actions"]["q99"] = serde_json::json!(vec![999.0; n]);
    let mut degrees = base.clone();
    scale(&mut degrees, 180.0 / std::f64::consts::PI);
    let cases: [(&str, &serde_json::Value, &[&str]); 3] = [
        ("shipped", &base, &[]),
        ("q99_999", &wide, &["shoulder", "elbow", "wrist", "gripper"]),
        ("degrees", &degrees, &["shoulder", "gripper", "degrees"]),
    ];
    for (tag, stats, want) in cases {
        let dir = std::env::temp_dir().join(format!("chunkrt-stats-{tag}-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        for f in ["config.json", "model.safetensors", "tokenizer.json"] {
            std::fs::copy(shipped.join(f), dir.join(f)).unwrap();
        }
        std::fs::write(dir.join("norm_stats.json"), stats.to_string()).unwrap();
        let mut cfg = chunkrt_controller::config::Config::embedded_default();
        cfg.policy.checkpoint = Some(dir.clone());
        let loaded = PolicySource::load(&cfg)
            .map(|_| ())
            .map_err(|e| format!("{e:#}"));
        let inspect = std::process::Command::new(env!("CARGO_BIN_EXE_chunkrt"))
            .arg("inspect")
            .arg(&dir)
            .args(["--config", "default"])
            .output()
            .expect("chunkrt inspect");
        let said = String::from_utf8_lossy(&inspect.stdout).to_string();
        let verdict = said
            .lines()
            .find(|l| l.starts_with("REFUSED") || l.starts_with("loads:"))
            .unwrap_or("")
            .to_string();
        println!("{tag}: run's load: {loaded:?}\n{tag}: inspect: {verdict}");
        let _ = std::fs::remove_dir_all(&dir);
        if want.is_empty() {
            assert!(loaded.is_ok(), "{tag}: {loaded:?}");
            assert!(inspect.status.success(), "{tag}: {said}");
        } else {
            let e = loaded.expect_err(tag);
            assert!(
                !inspect.status.success(),
                "{tag}: inspect said it loads:\n{said}"
            );
            for w in want {
                assert!(
                    e.contains(w),
                    "{tag}: run's refusal does not name {w:?}: {e}"
                );
                assert!(
                    verdict.contains(w),
                    "{tag}: inspect's does not name {w:?}: {verdict}"
                );
            }
        }
    }
}
