//! Unit tests of `config` (kept apart so the module reads on its own).
use super::*;

#[test]
fn embedded_default_is_valid() {
    let c = Config::embedded_default();
    assert!(c.n_dof() >= 2);
    assert!(!c.cameras.is_empty());
    assert_eq!(c.control_period_ns(), 1_000_000);
}

fn with(edit: impl Fn(&mut toml::Table)) -> Result<Config, ConfigError> {
    let mut t: toml::Table = toml::from_str(DEFAULT_TOML).unwrap();
    edit(&mut t);
    Config::parse(&toml::to_string(&t).unwrap(), "test.toml")
}

#[test]
fn errors_name_file_key_and_range() {
    let e = with(|t| {
        t["control"]["rate_hz"] = toml::Value::Float(-3.0);
    })
    .unwrap_err()
    .to_string();
    assert!(e.contains("test.toml"), "{e}");
    assert!(e.contains("control.rate_hz"), "{e}");
    assert!(e.contains("10..=10000"), "{e}");

    let e = with(|t| {
        t["robot"]["joints"][1]["max_velocity"] = toml::Value::Float(f64::NAN);
    })
    .unwrap_err()
    .to_string();
    assert!(e.contains("robot.joints[1].max_velocity"), "{e}");

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
        t["control"]
            .as_table_mut()
            .unwrap()
            .insert("rate_hzz".into(), toml::Value::Float(1.0));
    })
    .unwrap_err()
    .to_string();
    assert!(e.contains("rate_hzz"), "{e}");
}

#[test]
fn position_limits_must_be_ordered() {
    let e = with(|t| {
        t["robot"]["joints"][0]["position_max"] = toml::Value::Float(-10.0);
    })
    .unwrap_err()
    .to_string();
    assert!(e.contains("position_max") && e.contains("greater"), "{e}");
}
