//! Unit tests of `config` (kept apart so the module reads on its own).
use super::*;

#[test]
fn embedded_default_is_valid() {
    let c = Config::embedded_default();
    assert_eq!(c.policy.kind, Some(ModelKind::Pi05));
    assert_eq!(c.shared().n_dof(), c.n_dof());
}

fn with(edit: impl Fn(&mut toml::Table)) -> Result<Config, ConfigError> {
    let mut t: toml::Table = toml::from_str(DEFAULT_TOML).unwrap();
    edit(&mut t);
    Config::parse(&toml::to_string(&t).unwrap(), "test.toml")
}

#[test]
fn errors_name_file_key_and_range() {
    // the shared sections' errors are chunkrt-ipc's (its tests); these are the owned sections'
    let e = with(|t| {
        t["execution"]
            .as_table_mut()
            .unwrap()
            .insert("strategy".into(), toml::Value::String("magic".into()));
    })
    .unwrap_err()
    .to_string();
    // serde names the line, the key and the allowed set
    assert!(
        e.contains("strategy") && e.contains("magic") && e.contains("temporal_ensemble"),
        "{e}"
    );
}

#[test]
fn policy_enums_parse_and_unknown_values_name_the_allowed_set() {
    let set = |k: &str, v: &str| {
        with(|t| {
            t["policy"]
                .as_table_mut()
                .unwrap()
                .insert(k.into(), toml::Value::String(v.into()));
        })
    };
    let c = set("device", "cuda:1").unwrap();
    assert_eq!(c.policy.device, DeviceSpec::Cuda(1));
    assert_eq!(
        set("device", "cuda").unwrap().policy.device,
        DeviceSpec::Cuda(0)
    );
    assert_eq!(
        set("precision", "bf16").unwrap().policy.precision,
        Precision::Bf16
    );
    assert_eq!(
        set("kind", "pi0").unwrap().policy.kind,
        Some(ModelKind::Pi0)
    );
    assert_eq!(set("kind", "hold").unwrap().policy.kind, None);
    for (k, v, allowed) in [
        ("device", "gpu", "\"cuda:N\""),
        ("device", "cuda:x", "\"cuda:N\""),
        ("precision", "fp16", "bf16"),
        ("kind", "pi1", "pi05"),
    ] {
        let e = set(k, v).unwrap_err().to_string();
        assert!(e.contains(v) && e.contains(allowed), "{k} = {v}: {e}");
    }
}

#[test]
fn policy_threads_are_bounded_by_the_cores() {
    let cores = std::thread::available_parallelism().map_or(1, |n| n.get());
    let e = with(|t| {
        t["policy"]
            .as_table_mut()
            .unwrap()
            .insert("threads".into(), toml::Value::Integer(cores as i64 + 1));
    })
    .unwrap_err()
    .to_string();
    assert!(e.contains("policy.threads"), "{e}");
}

#[test]
fn unknown_keys_are_rejected() {
    let e = with(|t| {
        t["execution"]
            .as_table_mut()
            .unwrap()
            .insert("strategyy".into(), toml::Value::String("rtc".into()));
    })
    .unwrap_err()
    .to_string();
    assert!(e.contains("strategyy"), "{e}");
    let e = Config::parse("[nonsense]\n", "x.toml")
        .unwrap_err()
        .to_string();
    assert!(e.contains("nonsense") || e.contains("missing"), "{e}");
}

#[test]
fn a_remote_policy_needs_a_ws_url() {
    let set = |k: &str, v: &str| {
        with(|t| {
            let p = t["policy"].as_table_mut().unwrap();
            p.insert("source".into(), toml::Value::String("remote".into()));
            if !k.is_empty() {
                p.insert(k.into(), toml::Value::String(v.into()));
            }
        })
    };
    assert!(set("", "").unwrap_err().to_string().contains("policy.url"));
    let e = set("url", "http://gpu:8000").unwrap_err().to_string();
    assert!(e.contains("ws://host:port"), "{e}");
    let c = set("url", "ws://gpu-box:8000").unwrap();
    assert_eq!(c.policy.source, PolicySource::Remote);
    let e = with(|t| {
        t.insert("openpi".into(), toml::Value::Table(toml::Table::new()));
        t["openpi"]
            .as_table_mut()
            .unwrap()
            .insert("preset".into(), toml::Value::String("ur5".into()));
    })
    .unwrap_err()
    .to_string();
    assert!(e.contains("ur5") && e.contains("libero"), "{e}");
}
