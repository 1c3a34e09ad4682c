//! openpi's per-config transforms, exact: what chunkrt makes of a robot's state (the model's
//! state input, the state a π0.5 prompt carries) and of a model's output (the actions a client
//! gets) against what openpi's own transform code makes of the same values
//! (`tests/data/openpi_transforms/transforms.json`, made by
//! `scripts/fixtures/make_openpi_transforms_fixture.py` from openpi 15a9616's `transforms.py` and
//! `policies/*_policy.py`, run unchanged): ALOHA's joint flips and gripper conversions, the delta
//! dims made absolute with the model-space state, z-score and quantile statistics, LIBERO's 7
//! columns out of an 8-value state.

use chunkrt_policy::openpi_config::{by_name, model_state, robot_actions};
use chunkrt_policy::preprocess::{NormMode, NormStats, Stats};
use serde_json::Value;

const FIXTURE: &str = concat!(
    env!("CARGO_MANIFEST_DIR"),
    "/tests/data/openpi_transforms/transforms.json"
);

fn vec(v: &Value) -> Vec<f64> {
    v.as_array()
        .unwrap()
        .iter()
        .map(|x| x.as_f64().unwrap())
        .collect()
}

fn stats(v: &Value) -> Stats {
    let f = |k: &str| {
        vec(&v[k])
            .into_iter()
            .map(|x| x as f32)
            .collect::<Vec<f32>>()
    };
    Stats {
        mean: f("mean"),
        std: f("std"),
        q01: Some(f("q01")),
        q99: Some(f("q99")),
    }
}

#[test]
fn every_config_transforms_as_openpi_does() {
    let text = std::fs::read_to_string(FIXTURE).expect("the fixture");
    let doc: Value = serde_json::from_str(&text).unwrap();
    let action_dim = doc["action_dim"].as_u64().unwrap() as usize;
    let cases = doc["cases"].as_array().unwrap();
    assert!(cases.len() >= 21, "{} cases", cases.len());
    let mut seen = std::collections::BTreeMap::<String, (usize, f64, f64)>::new();
    for case in cases {
        let name = case["config"].as_str().unwrap();
        let cfg = by_name(name).unwrap();
        let mode = if case["use_quantiles"].as_bool().unwrap() {
            NormMode::Quantile
        } else {
            NormMode::ZScore
        };
        assert_eq!(
            mode == NormMode::Quantile,
            cfg.kind == chunkrt_policy::ModelKind::Pi05,
            "{name}: openpi normalises π0.5 by quantiles, π0 by z-score"
        );
        let ns = NormStats {
            state: stats(&case["norm_stats"]["state"]),
            actions: stats(&case["norm_stats"]["actions"]),
        };
        cfg.check_stats(&ns, action_dim).unwrap();
        let raw = vec(&case["raw_state"]);
        cfg.check_state(raw.len()).unwrap();

        // the way in
        let m = model_state(Some(cfg), &[], Some(&ns), mode, &raw, action_dim).unwrap();
        let (state, prompt_state, offsets) = (m.state, m.prompt_state, m.offsets);
        let want_state = vec(&case["model_state"]);
        let want_prompt = vec(&case["normalised_state"]);
        assert_eq!(state.len(), want_state.len(), "{name}");
        let mut err_in: f64 = 0.0;
        for (i, (a, b)) in state.iter().zip(&want_state).enumerate() {
            let e = (*a as f64 - b).abs();
            assert!(
                e <= 2e-6 * b.abs().max(1.0),
                "{name}: model state [{i}] {a} vs openpi {b}"
            );
            err_in = err_in.max(e);
        }
        assert_eq!(
            prompt_state.len(),
            want_prompt.len(),
            "{name}: the prompt's state"
        );
        for (a, b) in prompt_state.iter().zip(&want_prompt) {
            assert!((*a - b).abs() <= 2e-6 * b.abs().max(1.0), "{name}");
        }

        // the way out
        let y: Vec<Vec<f32>> = case["model_output"]
            .as_array()
            .unwrap()
            .iter()
            .map(|r| vec(r).into_iter().map(|x| x as f32).collect())
            .collect();
        let horizon = y.len();
        assert_eq!(horizon, cfg.action_horizon, "{name}: the config's horizon");
        let mut got = Vec::new();
        robot_actions(Some(cfg), Some(&ns), mode, y, &offsets, &mut got).unwrap();
        let want: Vec<Vec<f64>> = case["actions"]
            .as_array()
            .unwrap()
            .iter()
            .map(vec)
            .collect();
        let width = want[0].len();
        assert_eq!(
            width,
            cfg.robot.action_dim(),
            "{name}: openpi's columns out"
        );
        assert_eq!(got.len(), horizon * width, "{name}: chunkrt's columns out");
        let mut err_out: f64 = 0.0;
        for (h, row) in want.iter().enumerate() {
            for (j, b) in row.iter().enumerate() {
                let a = got[h * width + j];
                let e = (a - b).abs();
                assert!(
                    e <= 1e-5 * b.abs().max(1.0),
                    "{name}: action [{h}][{j}] {a} vs openpi {b}"
                );
                err_out = err_out.max(e);
            }
        }
        let s = seen.entry(name.to_string()).or_default();
        s.0 += 1;
        s.1 = s.1.max(err_in);
        s.2 = s.2.max(err_out);
    }
    for (name, (n, ein, eout)) in &seen {
        println!("{name}: {n} cases, max |diff| model state {ein:.2e}, actions {eout:.2e}");
    }
    assert_eq!(seen.len(), 7, "every config in the fixture");
}

#[test]
fn a_wrong_config_for_the_statistics_or_the_state_is_said() {
    let libero = by_name("pi05_libero").unwrap();
    let aloha_stats = NormStats {
        state: Stats {
            mean: vec![0.0; 14],
            std: vec![1.0; 14],
            q01: Some(vec![-1.0; 14]),
            q99: Some(vec![1.0; 14]),
        },
        actions: Stats {
            mean: vec![0.0; 14],
            std: vec![1.0; 14],
            q01: Some(vec![-1.0; 14]),
            q99: Some(vec![1.0; 14]),
        },
    };
    let e = libero
        .check_stats(&aloha_stats, 32)
        .unwrap_err()
        .to_string();
    assert!(
        e.contains("14 state and 14 action values") && e.contains("pi05_libero"),
        "{e}"
    );
    let e = libero.check_state(14).unwrap_err().to_string();
    assert!(e.contains("takes 8 state values"), "{e}");
    assert!(by_name("pi0_aloha_sim")
        .unwrap()
        .check_stats(&aloha_stats, 32)
        .is_ok());
}
