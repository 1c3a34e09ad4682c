//! Checkpoints as openpi and LeRobot ship them: the same tiny π0.5 (`tests/data/pi05_tiny`'s
//! weights) in openpi's converted layout and in LeRobot's (`tests/data/lerobot_pi05_tiny`, its
//! config and processor files written by LeRobot's own classes), sampled against the same model
//! in chunkrt's layout, with the tiny SentencePiece tokenizer of `tests/data/tokenizer`.

use std::path::{Path, PathBuf};

use chunkrt_policy::layout::LayoutOptions;
use chunkrt_policy::{Conditioning, LoadOptions, Policy, RawObservation};

#[path = "common/fixture.rs"]
mod fixture;

const TOKENIZER: &str = "tokenizer/paligemma_tiny.model";
const PROMPT: &str = "pick up the red block";

/// A fresh temporary directory (tests run in parallel: each call gets its own).
fn tmp(tag: &str) -> PathBuf {
    static N: std::sync::atomic::AtomicUsize = std::sync::atomic::AtomicUsize::new(0);
    let n = N.fetch_add(1, std::sync::atomic::Ordering::Relaxed);
    let d = std::env::temp_dir().join(format!("chunkrt_layout_{tag}_{}_{n}", std::process::id()));
    let _ = std::fs::remove_dir_all(&d);
    std::fs::create_dir_all(&d).unwrap();
    d
}

/// Normalisation statistics for the tiny model: state of the fixture's 6 joints, actions of 8.
fn norm_stats_json() -> String {
    let stats = |n: usize, scale: f32| {
        let v = |f: &dyn Fn(usize) -> f32| (0..n).map(f).collect::<Vec<f32>>();
        serde_json::json!({
            "mean": v(&|i| 0.05 * i as f32),
            "std": v(&|i| scale * (0.5 + 0.1 * i as f32)),
            "q01": v(&|i| -scale * (1.0 + 0.1 * i as f32)),
            "q99": v(&|i| scale * (1.2 + 0.05 * i as f32)),
        })
    };
    serde_json::json!({"norm_stats": {"state": stats(6, 1.0), "actions": stats(8, 0.5)}})
        .to_string()
}

/// A tiny fixture's `config.json` without its byte stand-in declaration: the dimensions only.
fn tiny_dimensions(name: &str) -> String {
    let src = fixture::data(name);
    let mut cfg: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(src.join("config.json")).unwrap()).unwrap();
    cfg.as_object_mut().unwrap().remove("tokenizer");
    cfg.to_string()
}

/// A tiny fixture in chunkrt's layout with the SentencePiece tokenizer and statistics.
fn chunkrt_layout_of(name: &str) -> PathBuf {
    let src = fixture::data(name);
    let d = tmp("chunkrt");
    std::fs::copy(src.join("model.safetensors"), d.join("model.safetensors")).unwrap();
    std::fs::write(d.join("config.json"), tiny_dimensions(name)).unwrap();
    std::fs::write(d.join("norm_stats.json"), norm_stats_json()).unwrap();
    std::fs::copy(
        fixture::data(TOKENIZER),
        d.join("paligemma_tokenizer.model"),
    )
    .unwrap();
    d
}

/// The same model as openpi's converter writes it: `config.json` with the variant names,
/// `assets/<asset_id>/norm_stats.json`, no tokenizer (openpi downloads it separately). The tiny
/// model's dimensions, which openpi's variant names cannot express, are in `chunkrt.json`.
fn openpi_layout(asset_ids: &[&str]) -> PathBuf {
    openpi_layout_of("pi05_tiny", asset_ids)
}

fn chunkrt_layout() -> PathBuf {
    chunkrt_layout_of("pi05_tiny")
}

fn openpi_layout_of(name: &str, asset_ids: &[&str]) -> PathBuf {
    let src = fixture::data(name);
    let d = tmp(&format!("openpi{}", asset_ids.len()));
    std::fs::copy(src.join("model.safetensors"), d.join("model.safetensors")).unwrap();
    let openpi = serde_json::json!({
        "action_dim": 8,
        "action_horizon": 10,
        "paligemma_variant": "gemma_2b",
        "action_expert_variant": "gemma_300m",
        "precision": "float32",
    });
    std::fs::write(d.join("config.json"), openpi.to_string()).unwrap();
    std::fs::write(d.join("chunkrt.json"), tiny_dimensions(name)).unwrap();
    for id in asset_ids {
        let a = d.join("assets").join(id);
        std::fs::create_dir_all(&a).unwrap();
        std::fs::write(a.join("norm_stats.json"), norm_stats_json()).unwrap();
    }
    d
}

fn load(dir: &Path, layout: LayoutOptions) -> Result<Policy, String> {
    let opts = LoadOptions {
        layout,
        ..Default::default()
    };
    Policy::load(dir, &opts).map_err(|e| e.to_string())
}

fn with_tokenizer() -> LayoutOptions {
    LayoutOptions {
        tokenizer: Some(fixture::data(TOKENIZER)),
        asset_id: None,
        openpi_config: None,
    }
}

/// One chunk from the fixture's observation (two of its three cameras, its 6-joint state).
fn sample(p: &mut Policy) -> Vec<f64> {
    sample_of("pi05_tiny", p)
}

fn sample_of(name: &str, p: &mut Policy) -> Vec<f64> {
    with_observation(name, |obs| p.infer(obs, &Conditioning::Fresh).unwrap())
}

/// `f` on fixture `name`'s observation: two of its three cameras, its state, [`PROMPT`].
fn with_observation<R>(name: &str, f: impl FnOnce(&RawObservation) -> R) -> R {
    let (frames, state) = fixture::raw_observation(name, &["base_0_rgb", "left_wrist_0_rgb"]);
    let raw = fixture::raw_frames(&frames);
    f(&RawObservation {
        frames: &raw,
        joint_positions: &state,
        prompt: PROMPT,
    })
}

fn max_diff(a: &[f64], b: &[f64]) -> f64 {
    assert_eq!(a.len(), b.len());
    a.iter()
        .zip(b)
        .map(|(x, y)| (x - y).abs())
        .fold(0.0, f64::max)
}

#[test]
fn an_openpi_checkpoint_samples_as_the_same_model_in_chunkrts_layout() {
    let reference = chunkrt_layout();
    let mut want = load(&reference, LayoutOptions::default()).unwrap();
    let a = sample(&mut want);
    let dir = openpi_layout(&["tiny_robot"]);
    let mut got = load(&dir, with_tokenizer()).unwrap();
    let b = sample(&mut got);
    let d = max_diff(&a, &b);
    eprintln!(
        "openpi layout vs chunkrt layout: {} actions, max diff {d:.2e}",
        a.len()
    );
    assert!(d <= 1e-6, "max diff {d}");
    // it is not the same as without the statistics (they are used)
    let bare = tmp("bare");
    for f in [
        "model.safetensors",
        "config.json",
        "paligemma_tokenizer.model",
    ] {
        std::fs::copy(reference.join(f), bare.join(f)).unwrap();
    }
    let c = sample(&mut load(&bare, LayoutOptions::default()).unwrap());
    assert!(max_diff(&a, &c) > 1e-3, "the statistics changed nothing");
    let report = chunkrt_policy::checkpoint::inspect(&dir, &with_tokenizer()).unwrap();
    eprintln!("{report}");
    for want in [
        "layout: openpi",
        "assets/tiny_robot/norm_stats.json",
        "chunkrt.json",
        "paligemma_tiny.model",
        "action_dim 8, action_horizon 10: openpi's config.json",
    ] {
        assert!(report.contains(want), "{want:?} not in\n{report}");
    }
    for d in [reference, dir, bare] {
        std::fs::remove_dir_all(d).ok();
    }
}

#[test]
fn an_openpi_checkpoint_with_several_robots_needs_an_asset_id() {
    let dir = openpi_layout(&["aloha", "droid"]);
    let e = load(&dir, with_tokenizer()).err().expect("refused");
    assert!(
        e.contains("--asset-id") && e.contains("aloha, droid"),
        "{e}"
    );
    let mut opts = with_tokenizer();
    opts.asset_id = Some("droid".into());
    load(&dir, opts.clone()).expect("loads with an asset id");
    let report = chunkrt_policy::checkpoint::inspect(&dir, &opts).unwrap();
    assert!(report.contains("assets/droid/norm_stats.json"), "{report}");
    opts.asset_id = Some("libero".into());
    let e = load(&dir, opts).err().expect("refused");
    assert!(e.contains("aloha, droid"), "{e}");
    // no tokenizer: the error says where it looked and what to pass
    let no_tokenizer = LayoutOptions {
        tokenizer: None,
        asset_id: Some("droid".into()),
        openpi_config: None,
    };
    let e = load(&dir, no_tokenizer).err().expect("refused");
    assert!(
        e.contains("--tokenizer") && e.contains("paligemma_tokenizer.model"),
        "{e}"
    );
    // the real variant names without chunkrt.json: the preset, which these weights do not fit
    std::fs::remove_file(dir.join("chunkrt.json")).unwrap();
    let mut opts = with_tokenizer();
    opts.asset_id = Some("droid".into());
    let e = load(&dir, opts).err().expect("refused");
    assert!(
        e.contains("width is 2048") || e.contains("problem(s)"),
        "{e}"
    );
    std::fs::remove_dir_all(dir).ok();
}

/// A copy of the LeRobot fixture, its pre-processor's prompt step given `max_state_dim` (as a
/// LeRobot user may set it) when `prompt_state_dim` is some.
fn lerobot_copy(tag: &str, prompt_state_dim: Option<usize>) -> PathBuf {
    let src = fixture::data("lerobot_pi05_tiny");
    let d = tmp(tag);
    for e in std::fs::read_dir(&src).unwrap() {
        let p = e.unwrap().path();
        std::fs::copy(&p, d.join(p.file_name().unwrap())).unwrap();
    }
    if let Some(n) = prompt_state_dim {
        let path = d.join("policy_preprocessor.json");
        let mut pre: serde_json::Value =
            serde_json::from_str(&std::fs::read_to_string(&path).unwrap()).unwrap();
        let step = pre["steps"]
            .as_array_mut()
            .unwrap()
            .iter_mut()
            .find(|s| s["registry_name"] == "pi05_prepare_state_tokenizer_processor_step")
            .expect("LeRobot's pi05 prompt step");
        step["config"]["max_state_dim"] = n.into();
        std::fs::write(&path, pre.to_string()).unwrap();
    }
    d
}

#[test]
fn a_lerobot_checkpoint_samples_as_the_same_model_in_chunkrts_layout() {
    let reference = chunkrt_layout();
    let a = sample(&mut load(&reference, LayoutOptions::default()).unwrap());
    // the prompt step padding to the robot's 6 values: the same prompt as openpi's
    let dir = lerobot_copy("lerobot6", Some(6));
    let b = sample(&mut load(&dir, with_tokenizer()).unwrap());
    let d = max_diff(&a, &b);
    eprintln!(
        "LeRobot layout vs chunkrt layout: {} actions, max diff {d:.2e}",
        a.len()
    );
    assert!(d <= 1e-6, "max diff {d}");
    for d in [reference, dir] {
        std::fs::remove_dir_all(d).ok();
    }
}

#[test]
fn a_lerobot_checkpoint_as_written_pads_the_state_in_the_prompt_and_says_where_things_came_from() {
    use chunkrt_policy::preprocess::{
        discretize_state, normalize, NormMode, NormStats, PromptTokenizer,
    };
    let dir = lerobot_copy("lerobot", None);
    let report = chunkrt_policy::checkpoint::inspect(&dir, &with_tokenizer()).unwrap();
    eprintln!("{report}");
    for want in [
        "layout: LeRobot",
        "action_horizon 10 (chunk_size)",
        "action_dim 8 (max_action_dim)",
        "max_token_len 200 (tokenizer_max_length)",
        "cameras [\"base_0_rgb\", \"left_wrist_0_rgb\", \"right_wrist_0_rgb\"]",
        "padded to 32 values",
        "observation.state from policy_preprocessor_step_2_normalizer_processor.safetensors",
        "action from policy_postprocessor_step_0_unnormalizer_processor.safetensors",
        "chunkrt.json",
    ] {
        assert!(report.contains(want), "{want:?} not in\n{report}");
    }
    // the tokens: LeRobot's prompt, the normalised state padded with zeros to 32 before binning
    let mut policy = load(&dir, with_tokenizer()).unwrap();
    let (got, state): (Vec<u32>, Vec<f64>) = with_observation("pi05_tiny", |obs| {
        let tokens = policy.prepare(obs).unwrap().tokens;
        let ids = tokens.flatten_all().unwrap().to_vec1().unwrap();
        (ids, obs.joint_positions.to_vec())
    });
    let stats: serde_json::Value = serde_json::from_str(&norm_stats_json()).unwrap();
    let stats: NormStats = serde_json::from_value(stats["norm_stats"].clone()).unwrap();
    let mut s: Vec<f32> = state.iter().map(|&x| x as f32).collect();
    normalize(&mut s, &stats.state, NormMode::Quantile).unwrap();
    s.resize(32, 0.0);
    let tok = PromptTokenizer::from_sentencepiece(&fixture::data(TOKENIZER)).unwrap();
    let (want, _) = tok
        .tokenize(PROMPT, Some(&discretize_state(&s)), 200)
        .unwrap();
    assert_eq!(got, want);
    // and differs from openpi's prompt of the 6 values
    let mut s6 = s.clone();
    s6.truncate(6);
    let (openpi, _) = tok
        .tokenize(PROMPT, Some(&discretize_state(&s6)), 200)
        .unwrap();
    assert_ne!(got, openpi);
    // a LeRobot checkpoint without its processor files loads with a warning, not normalised
    for f in ["policy_preprocessor.json", "policy_postprocessor.json"] {
        std::fs::remove_file(dir.join(f)).unwrap();
    }
    let report = chunkrt_policy::checkpoint::inspect(&dir, &with_tokenizer()).unwrap();
    assert!(
        report.contains("MISSING: policy_preprocessor.json"),
        "{report}"
    );
    std::fs::remove_dir_all(dir).ok();
}

/// π0 (z-score statistics, the state as a token of the action expert) in openpi's layout.
#[test]
fn an_openpi_pi0_checkpoint_samples_as_the_same_model_in_chunkrts_layout() {
    let reference = chunkrt_layout_of("pi0_tiny");
    let a = sample_of(
        "pi0_tiny",
        &mut load(&reference, LayoutOptions::default()).unwrap(),
    );
    let dir = openpi_layout_of("pi0_tiny", &["tiny_robot"]);
    let mut got = load(&dir, with_tokenizer()).unwrap();
    let b = sample_of("pi0_tiny", &mut got);
    let d = max_diff(&a, &b);
    eprintln!("pi0, openpi layout vs chunkrt layout: max diff {d:.2e}");
    assert!(d <= 1e-6, "max diff {d}");
    let report = chunkrt_policy::checkpoint::inspect(&dir, &with_tokenizer()).unwrap();
    assert!(
        report.contains("kind: pi0 (openpi's config.json does not say"),
        "{report}"
    );
    for d in [reference, dir] {
        std::fs::remove_dir_all(d).ok();
    }
}

/// LIBERO's statistics (state 8, actions 7) under `assets/physical-intelligence/libero`, nested
/// as openpi writes an asset id with a slash.
fn libero_stats_json() -> String {
    let stats = |n: usize| {
        serde_json::json!({
            "mean": vec![0.1f32; n], "std": vec![0.5f32; n],
            "q01": vec![-1.0f32; n], "q99": vec![1.0f32; n],
        })
    };
    serde_json::json!({"norm_stats": {"state": stats(8), "actions": stats(7)}}).to_string()
}

#[test]
fn an_openpi_checkpoint_gives_its_config_away_and_answers_its_robots_columns() {
    // by its assets: statistics for one robot only, nested two folders deep
    let dir = openpi_layout(&[]);
    let a = dir.join("assets/physical-intelligence/libero");
    std::fs::create_dir_all(&a).unwrap();
    std::fs::write(a.join("norm_stats.json"), libero_stats_json()).unwrap();
    let report = chunkrt_policy::checkpoint::inspect(&dir, &with_tokenizer()).unwrap();
    eprintln!("{report}");
    for want in [
        "openpi config pi05_libero (from assets/physical-intelligence/libero)",
        "libero transforms, 8 state values in, 7 action columns out",
        "state in the prompt: false",
        "normalisation: assets/physical-intelligence/libero/norm_stats.json",
    ] {
        assert!(report.contains(want), "{want:?} not in\n{report}");
    }
    let mut p = load(&dir, with_tokenizer()).unwrap();
    assert_eq!(p.openpi_config().map(|c| c.name), Some("pi05_libero"));
    assert_eq!(p.action_width(8), 7);
    let (frames, _) = fixture::raw_observation("pi05_tiny", &["base_0_rgb", "left_wrist_0_rgb"]);
    let raw = fixture::raw_frames(&frames);
    let state = [0.1, -0.2, 0.3, 1.0, -1.0, 0.5, 0.02, 0.01];
    let obs = RawObservation {
        frames: &raw,
        joint_positions: &state,
        prompt: PROMPT,
    };
    let actions = p.infer(&obs, &Conditioning::Fresh).unwrap();
    assert_eq!(
        actions.len(),
        10 * 7,
        "LIBERO's 7 columns, the config's 10 actions"
    );
    // the wrong robot's state is refused with what the config takes
    let e = p
        .infer(
            &RawObservation {
                joint_positions: &[0.0; 6],
                ..obs
            },
            &Conditioning::Fresh,
        )
        .err()
        .unwrap()
        .to_string();
    assert!(e.contains("takes 8 state values"), "{e}");

    // by its folder name, over statistics that do not fit it: a clear error at load
    let named = dir
        .parent()
        .unwrap()
        .join(format!("pi05_droid_{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&named);
    std::fs::create_dir_all(&named).unwrap();
    let droid = named.join("pi05_droid");
    std::fs::rename(&dir, &droid).unwrap();
    let e = load(&droid, with_tokenizer()).err().expect("refused");
    assert!(
        e.contains("openpi config pi05_droid") && e.contains("8 state and 7 action values"),
        "{e}"
    );
    // a π0 config on a π0.5 checkpoint, named
    let mut opts = with_tokenizer();
    opts.openpi_config = Some("pi0_libero".into());
    let e = load(&droid, opts).err().expect("refused");
    assert!(
        e.contains("is a pi0 config") && e.contains("pi05 model"),
        "{e}"
    );
    std::fs::remove_dir_all(&named).ok();
}

#[test]
fn absurd_statistics_are_refused_by_run_and_inspect_alike() {
    let dir = chunkrt_layout();
    let mut ns: serde_json::Value = serde_json::from_str(&norm_stats_json()).unwrap();
    // an action range no joint has: the chunk came out at ~1e37 rad before
    ns["norm_stats"]["actions"]["q99"][2] = serde_json::json!(1e38);
    std::fs::write(dir.join("norm_stats.json"), ns.to_string()).unwrap();
    let e = load(&dir, LayoutOptions::default()).err().expect("refused");
    assert!(
        e.contains("dimension(s) [2]") && e.contains("beyond"),
        "{e}"
    );
    let out = std::process::Command::new(env!("CARGO_BIN_EXE_chunkrt"))
        .arg("inspect")
        .arg(&dir)
        .output()
        .unwrap();
    let text = String::from_utf8_lossy(&out.stdout);
    assert!(
        !out.status.success(),
        "inspect accepted what run refuses:\n{text}"
    );
    assert!(
        text.contains("REFUSED at load") && text.contains("dimension(s) [2]"),
        "{text}"
    );
    // and the sound statistics pass both
    std::fs::write(dir.join("norm_stats.json"), norm_stats_json()).unwrap();
    load(&dir, LayoutOptions::default()).expect("loads");
    let out = std::process::Command::new(env!("CARGO_BIN_EXE_chunkrt"))
        .arg("inspect")
        .arg(&dir)
        .output()
        .unwrap();
    assert!(out.status.success());
    assert!(String::from_utf8_lossy(&out.stdout).contains("loads: yes"));
    std::fs::remove_dir_all(&dir).ok();
}
