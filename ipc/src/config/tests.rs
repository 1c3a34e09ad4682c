//! Unit tests of `config` (kept apart so the module reads on its own).
use super::*;

#[test]
fn embedded_default_is_valid() {
    let c = SharedConfig::embedded_default();
    assert!(c.n_dof() >= 2);
    assert!(!c.cameras.is_empty());
    assert_eq!(c.control_period_ns(), 1_000_000);
}

fn with(edit: impl Fn(&mut toml::Table)) -> Result<SharedConfig, ConfigError> {
    let mut t: toml::Table = toml::from_str(DEFAULT_TOML).unwrap();
    edit(&mut t);
    SharedConfig::parse(&toml::to_string(&t).unwrap(), "test.toml")
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
}

#[test]
fn shared_sections_are_strict_and_the_others_left_to_their_owners() {
    let e = with(|t| {
        t["control"]
            .as_table_mut()
            .unwrap()
            .insert("rate_hzz".into(), toml::Value::Float(1.0));
    })
    .unwrap_err()
    .to_string();
    assert!(e.contains("rate_hzz"), "{e}");
    // [policy] and [execution] are the controller's: a robot driver does not read them
    let c = with(|t| {
        t["policy"]
            .as_table_mut()
            .unwrap()
            .insert("anything".into(), toml::Value::Float(1.0));
    });
    assert!(c.is_ok());
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

#[test]
fn only_small_regular_files_are_read() {
    let e = SharedConfig::load(Path::new("/dev/zero"))
        .unwrap_err()
        .to_string();
    assert!(e.contains("not a regular file"), "{e}");
    let dir = std::env::temp_dir().join(format!("chunkrt-cfg-{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    let big = dir.join("big.toml");
    std::fs::write(&big, vec![b'#'; MAX_CONFIG_BYTES as usize + 1]).unwrap();
    let e = SharedConfig::load(&big).unwrap_err().to_string();
    assert!(e.contains("at most"), "{e}");
    let _ = std::fs::remove_dir_all(&dir);
}
