//! Fuzz (issue 16, bounded inputs): hostile values at every boundary parser and validator — IPC
//! message validation and the per-publisher stream guard, the TOML configuration, a checkpoint's
//! `config.json`, `norm_stats.json` and `tokenizer.json`, and `chunkrt report`'s histogram-log reader — give an
//! `Ok` or a typed error, never a panic. proptest with fixed seeds: a short run in the default
//! suite, 40x longer with `cargo test --test fuzz_inputs -- --ignored`.

use std::path::PathBuf;

use chunkrt_controller::config::Config;
use chunkrt_ipc::{
    validate_frame, validate_joint_command, validate_joint_state, CameraFrameHeader, Freshness,
    JointCommand, JointState, StreamGuard, MAX_DOF,
};
use chunkrt_policy::config::ModelConfig;
use chunkrt_policy::preprocess::{NormMode, NormStats, PromptTokenizer};
use proptest::prelude::*;
use proptest::test_runner::{Config as RunConfig, RngAlgorithm, TestRng, TestRunner};

const SHORT: u32 = 96;
const LONG: u32 = SHORT * 40;

fn runner(cases: u32, seed: u8) -> TestRunner {
    TestRunner::new_with_rng(
        RunConfig {
            cases,
            failure_persistence: None,
            ..RunConfig::default()
        },
        TestRng::from_seed(RngAlgorithm::ChaCha, &[seed; 32]),
    )
}

/// Any f64, NaN and infinities included.
fn any_f64() -> impl Strategy<Value = f64> {
    prop_oneof![
        Just(f64::NAN),
        Just(f64::INFINITY),
        Just(f64::NEG_INFINITY),
        Just(0.0),
        -1e3f64..1e3,
        any::<f64>(),
    ]
}

fn messages(cases: u32) {
    let arrays = prop::collection::vec(any_f64(), 3 * MAX_DOF);
    let strategy = (
        any::<u32>(),
        prop::option::of(0u32..40),
        any::<u32>(),
        arrays,
        any::<u64>(),
    );
    runner(cases, 1)
        .run(&strategy, |(n_dof, expected, mode, v, seq)| {
            let mut js = JointState {
                seq,
                n_dof,
                ..Default::default()
            };
            js.position.copy_from_slice(&v[..MAX_DOF]);
            js.velocity.copy_from_slice(&v[MAX_DOF..2 * MAX_DOF]);
            js.effort.copy_from_slice(&v[2 * MAX_DOF..]);
            let ok = validate_joint_state(&js, expected).is_ok();
            // accepted only with a valid joint count and finite numbers where they count
            if ok {
                let n = n_dof as usize;
                prop_assert!((1..=MAX_DOF).contains(&n));
                prop_assert!(js.position[..n].iter().all(|x| x.is_finite()));
            }
            let mut c = JointCommand {
                seq,
                n_dof,
                mode,
                ..Default::default()
            };
            c.position.copy_from_slice(&v[..MAX_DOF]);
            let _ = validate_joint_command(&c, expected);
            Ok(())
        })
        .unwrap();
    let header = (
        any::<[u32; 6]>(),
        any::<[u64; 3]>(),
        0usize..(1 << 40),
        any::<u32>(),
        any::<u32>(),
    );
    runner(cases, 2)
        .run(&header, |(u, t, payload, max_w, max_h)| {
            let h = CameraFrameHeader {
                seq: t[0],
                capture_time_ns: t[1],
                publish_time_ns: t[2],
                camera_id: u[0],
                encoding: u[1] % 8,
                width: u[2] % 5000,
                height: u[3] % 5000,
                stride: u[4],
                reserved: u[5],
            };
            if validate_frame(&h, payload, max_w, max_h).is_ok() {
                // an accepted frame fits what the controller preallocates
                prop_assert!(h.width <= max_w && h.height <= max_h);
                prop_assert!(payload as u64 == h.stride as u64 * h.height as u64);
            }
            Ok(())
        })
        .unwrap();
    let stream = prop::collection::vec((0u128..3, any::<u64>(), any::<u64>(), any::<u64>()), 1..64);
    runner(cases, 3)
        .run(&stream, |msgs| {
            let mut g = StreamGuard::new();
            let lim = Freshness {
                max_age_ns: 1_000_000,
                max_future_ns: 1_000,
            };
            for (p, seq, t, now) in msgs {
                let _ = g.check(p, seq, t, now, lim);
            }
            Ok(())
        })
        .unwrap();
}

fn repo(path: &str) -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR")).join(path)
}

/// Values a careless or hostile file might hold in place of a number.
fn hostile_value() -> impl Strategy<Value = String> {
    prop_oneof![
        Just("0".to_string()),
        Just("-1".to_string()),
        Just("1e308".to_string()),
        Just("-1e308".to_string()),
        Just("nan".to_string()),
        Just("inf".to_string()),
        Just("18446744073709551615".to_string()),
        Just("10000000000".to_string()),
        Just("\"x\"".to_string()),
        Just("[]".to_string()),
        Just("true".to_string()),
        any::<i64>().prop_map(|v| v.to_string()),
        any::<f64>().prop_map(|v| format!("{v:?}")),
    ]
}

fn config_toml(cases: u32) {
    let text = std::fs::read_to_string(repo("config/default.toml")).unwrap();
    let lines: Vec<String> = text.lines().map(str::to_string).collect();
    let assignments: Vec<usize> = lines
        .iter()
        .enumerate()
        .filter(|(_, l)| !l.trim_start().starts_with('#') && l.contains(" = "))
        .map(|(i, _)| i)
        .collect();
    let strategy = (
        prop::collection::vec((0..assignments.len(), hostile_value()), 1..4),
        ".{0,64}",
    );
    runner(cases, 4)
        .run(&strategy, |(edits, junk)| {
            let mut l = lines.clone();
            for (k, v) in edits {
                let i = assignments[k];
                let key = l[i].split(" = ").next().unwrap_or("").to_string();
                l[i] = format!("{key} = {v}");
            }
            let _ = Config::parse(&l.join("\n"), "fuzz.toml");
            let _ = Config::parse(&junk, "junk.toml");
            Ok(())
        })
        .unwrap();
}

/// Sets the `k`-th numeric leaf of `v` (depth-first) to `new`; returns how many there are.
fn set_number(v: &mut serde_json::Value, k: &mut usize, new: &serde_json::Value) -> bool {
    match v {
        serde_json::Value::Number(_) => {
            if *k == 0 {
                *v = new.clone();
                return true;
            }
            *k -= 1;
            false
        }
        serde_json::Value::Array(a) => a.iter_mut().any(|x| set_number(x, k, new)),
        serde_json::Value::Object(o) => o.values_mut().any(|x| set_number(x, k, new)),
        _ => false,
    }
}

fn checkpoint_json(cases: u32) {
    let files = [
        (repo("tests/data/pi05_tiny/config.json"), true),
        (repo("tests/data/pi0_tiny/config.json"), true),
        (repo("models/reach_pi05/norm_stats.json"), false),
    ];
    let dir = std::env::temp_dir().join(format!("chunkrt-fuzz-{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    for (fi, (path, is_config)) in files.iter().enumerate() {
        let base: serde_json::Value =
            serde_json::from_str(&std::fs::read_to_string(path).unwrap()).unwrap();
        let number = prop_oneof![
            Just(serde_json::json!(0)),
            Just(serde_json::json!(-1)),
            Just(serde_json::json!(1e300)),
            Just(serde_json::json!(u64::MAX)),
            Just(serde_json::json!(10_000_000_000u64)),
            Just(serde_json::json!("x")),
            Just(serde_json::json!(null)),
            any::<i64>().prop_map(|v| serde_json::json!(v)),
        ];
        let strategy = prop::collection::vec((0usize..4096, number), 1..4);
        let out = dir.join(format!("f{fi}.json"));
        runner(cases, 5 + fi as u8)
            .run(&strategy, |edits| {
                let mut v = base.clone();
                for (k, n) in edits {
                    let mut k = k;
                    set_number(&mut v, &mut k, &n);
                }
                let text = v.to_string();
                if *is_config {
                    let _ = ModelConfig::from_json_str(&text);
                } else {
                    std::fs::write(&out, &text).unwrap();
                    if let Ok(s) = NormStats::from_file(&out) {
                        for n in [0, 1, 4, 8, 1000] {
                            let _ = s.check(NormMode::Quantile, n);
                            let _ = s.check(NormMode::ZScore, n);
                        }
                    }
                }
                Ok(())
            })
            .unwrap();
    }
    std::fs::remove_dir_all(&dir).ok();
}

/// The committed policy's `tokenizer.json` with hostile numbers or strings in its fields (ids,
/// merges, vocabulary entries), or cut short / with bytes overwritten: loading it and
/// tokenizing prompts gives ids or a typed error, never a panic. Ids outside the model's
/// vocabulary are the model's check (`token ids must be in [0, vocab)`), tested in policy_io.
fn tokenizer_json(cases: u32) {
    let base_text = std::fs::read_to_string(repo("models/reach_pi05/tokenizer.json")).unwrap();
    let base: serde_json::Value = serde_json::from_str(&base_text).unwrap();
    let dir = std::env::temp_dir().join(format!("chunkrt-fuzz-tok-{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    let out = dir.join("tokenizer.json");
    let value = prop_oneof![
        Just(serde_json::json!(-1)),
        Just(serde_json::json!(u64::MAX)),
        Just(serde_json::json!(1e300)),
        Just(serde_json::json!(null)),
        Just(serde_json::json!("")),
        Just(serde_json::json!([])),
        any::<i64>().prop_map(|v| serde_json::json!(v)),
        "\\PC{0,12}".prop_map(|v| serde_json::json!(v)),
    ];
    let edit = prop_oneof![
        // a JSON edit: the k-th number replaced
        prop::collection::vec((0usize..4096, value), 1..4).prop_map(Err),
        // a byte-level edit: cut at, or overwrite bytes from, a position
        (
            0usize..8192,
            prop::collection::vec(any::<u8>(), 0..16),
            any::<bool>()
        )
            .prop_map(Ok),
    ];
    let prompts = ["reach the red target", "", "ünïcödé ✓ \n\t", "x"];
    runner(cases, 11)
        .run(&edit, |edit| {
            let bytes = match edit {
                Err(edits) => {
                    let mut v = base.clone();
                    for (k, n) in edits {
                        let mut k = k;
                        set_number(&mut v, &mut k, &n);
                    }
                    v.to_string().into_bytes()
                }
                Ok((at, junk, cut)) => {
                    let mut b = base_text.clone().into_bytes();
                    let at = at.min(b.len());
                    if cut {
                        b.truncate(at);
                    }
                    for (i, x) in junk.iter().enumerate() {
                        if let Some(y) = b.get_mut(at + i) {
                            *y = *x;
                        }
                    }
                    b
                }
            };
            std::fs::write(&out, &bytes).unwrap();
            if let Ok(tok) = PromptTokenizer::from_file(&out) {
                for p in prompts {
                    let _ = tok.tokenize(p, None, 48);
                    let _ = tok.tokenize(p, Some(&[0, 255, 128]), 64);
                }
            }
            Ok(())
        })
        .unwrap();
    std::fs::remove_dir_all(&dir).ok();
}

fn report_logs(cases: u32) {
    let dir = std::env::temp_dir().join(format!("chunkrt-fuzz-log-{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    let path = dir.join("fuzz.hlog");
    let header = "#[StartTime: 1700000000.000 (seconds since epoch)]\n\
                  \"StartTimestamp\",\"Interval_Length\",\"Interval_Max\",\"Interval_Compressed_Histogram\"\n";
    let line = (
        prop::collection::vec(any::<u8>(), 0..512),
        "[A-Za-z0-9+/=,.:\" -]{0,200}",
    );
    runner(cases, 9)
        .run(&line, |(bytes, text)| {
            std::fs::write(&path, &bytes).unwrap();
            let _ = chunkrt::report::read_interval_log(&path);
            std::fs::write(&path, format!("{header}{text}\n")).unwrap();
            let _ = chunkrt::report::read_interval_log(&path);
            Ok(())
        })
        .unwrap();
    std::fs::remove_dir_all(&dir).ok();
}

#[test]
fn fuzz_messages_never_panic() {
    messages(SHORT);
}

#[test]
fn fuzz_config_toml_never_panics() {
    config_toml(SHORT);
}

#[test]
fn fuzz_checkpoint_json_never_panics() {
    checkpoint_json(SHORT);
}

#[test]
fn fuzz_tokenizer_json_never_panics() {
    tokenizer_json(SHORT);
}

#[test]
fn fuzz_report_logs_never_panic() {
    report_logs(SHORT);
}

#[test]
#[ignore = "long fuzz run: cargo test --test fuzz_inputs -- --ignored"]
fn fuzz_long() {
    messages(LONG);
    config_toml(LONG);
    checkpoint_json(LONG);
    tokenizer_json(LONG);
    report_logs(LONG);
}
