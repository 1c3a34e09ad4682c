//! Controller configuration: TOML → typed structs, validated on load.
//!
//! Every error names the file, the key and what is allowed, e.g.
//! `config/robot.toml: robot.joints[2].max_velocity = -1: must be in 0.001..=100`.
//! Unknown keys are errors too (a typo must not silently fall back to a default).

use std::path::{Path, PathBuf};

use crate::MAX_DOF;
use serde::{Deserialize, Serialize};

/// The configuration embedded in the binary (`config/default.toml`): the demo robot.
pub const DEFAULT_TOML: &str = include_str!("../../config/default.toml");

/// A configuration problem, pointing at the file and key.
#[derive(Debug, thiserror::Error)]
pub enum ConfigError {
    #[error("{file}: cannot read: {error}")]
    Read { file: String, error: std::io::Error },
    #[error("{file}: {message}")]
    Parse { file: String, message: String },
    #[error("{file}: {key} = {value}: {allowed}")]
    Invalid {
        file: String,
        key: String,
        value: String,
        allowed: String,
    },
}

/// What every process of a robot shares: the robot (namespace, joints), the timing and the
/// cameras. A robot driver, a camera or the monitor reads only this; the controller's whole
/// configuration (`chunkrt_controller::config::Config`) adds `[policy]`, `[execution]` and
/// `[openpi]`, each owned by the crate that uses it. Other sections of the file are left to
/// their owners (here they are not read); these three are checked strictly.
#[derive(Debug, Clone, Serialize, Deserialize, PartialEq)]
pub struct SharedConfig {
    pub robot: RobotConfig,
    pub control: ControlConfig,
    #[serde(default)]
    pub cameras: Vec<CameraConfig>,
    /// Where the configuration came from (not part of the file).
    #[serde(skip)]
    pub source: PathBuf,
}

/// The robot: namespace of its services and its joints.
#[derive(Debug, Clone, Serialize, Deserialize, PartialEq)]
#[serde(deny_unknown_fields)]
pub struct RobotConfig {
    /// Robot name (used in logs and node names).
    pub name: String,
    /// Service namespace, e.g. `chunkrt/demo` → `chunkrt/demo/joint_state`.
    pub namespace: String,
    /// Rate at which the robot driver publishes joint state (Hz); used for freshness checks.
    #[serde(default = "default_joint_state_rate")]
    pub joint_state_rate_hz: f64,
    /// One entry per joint, in command order.
    pub joints: Vec<JointConfig>,
}

fn default_joint_state_rate() -> f64 {
    1000.0
}

/// Limits of one joint (SI units: rad or m, per second).
#[derive(Debug, Clone, Serialize, Deserialize, PartialEq)]
#[serde(deny_unknown_fields)]
pub struct JointConfig {
    /// Joint name (logs, plots).
    pub name: String,
    /// Lower position limit (rad, or m for a linear joint); commands are kept inside.
    pub position_min: f64,
    /// Upper position limit (rad or m).
    pub position_max: f64,
    /// Velocity limit of the command (per second), enforced by ruckig.
    pub max_velocity: f64,
    /// Acceleration limit of the command (per second²).
    pub max_acceleration: f64,
    /// Jerk limit of the command (per second³).
    pub max_jerk: f64,
    /// Position at start-up of simulated robots.
    #[serde(default)]
    pub initial_position: f64,
    /// A discrete channel (gripper open/close): stepped, never interpolated or blended.
    #[serde(default)]
    pub step: bool,
}

/// The control thread.
#[derive(Debug, Clone, Serialize, Deserialize, PartialEq)]
#[serde(deny_unknown_fields)]
pub struct ControlConfig {
    /// Control rate (Hz).
    pub rate_hz: f64,
    /// Core to pin the control thread to (default: the last core).
    #[serde(default)]
    pub cpu: Option<usize>,
    /// SCHED_FIFO priority when permitted (1..=99; 0 disables the attempt).
    #[serde(default = "default_rt_priority")]
    pub realtime_priority: i32,
    /// Lock memory (mlockall) when permitted.
    #[serde(default = "default_true")]
    pub lock_memory: bool,
    /// How long after publishing a command the robot may still apply it (ms).
    #[serde(default = "default_command_deadline_ms")]
    pub command_deadline_ms: f64,
    /// Joint states older than this are stale (ms).
    #[serde(default = "default_joint_state_max_age_ms")]
    pub joint_state_max_age_ms: f64,
    /// Camera frames older than this are stale (ms).
    #[serde(default = "default_frame_max_age_ms")]
    pub frame_max_age_ms: f64,
    /// Timestamps up to this far ahead of our clock are tolerated (ms).
    #[serde(default = "default_max_future_ms")]
    pub max_future_ms: f64,
    /// Controller status publish rate (Hz).
    #[serde(default = "default_status_rate_hz")]
    pub status_rate_hz: f64,
    /// What clocks the control tick: its own timer (default), or the robot's joint states
    /// (`robot`: the tick runs when the robot's state arrives, woken by its event; the timer
    /// takes over when the robot is quiet for `robot_clock_timeout_ms`).
    #[serde(default)]
    pub clock: ControlClock,
    /// With `clock = "robot"`: after this long without a robot state the timer ticks (ms).
    #[serde(default = "default_robot_clock_timeout_ms")]
    pub robot_clock_timeout_ms: f64,
}

crate::config_enum! {
    /// `control.clock`: what clocks the control tick.
    pub enum ControlClock ("control clock") {
        /// Absolute deadlines of the control thread's own timer, `control.rate_hz`.
        #[default]
        Timer = "timer",
        /// The robot's joint states: one tick per state, woken by the robot's event on
        /// `NS/joint_state` (a robot whose own clock sets the cycle, such as the Franka's FCI).
        Robot = "robot",
    }
}

fn default_robot_clock_timeout_ms() -> f64 {
    3.0
}

fn default_rt_priority() -> i32 {
    80
}
fn default_true() -> bool {
    true
}
fn default_command_deadline_ms() -> f64 {
    5.0
}
fn default_joint_state_max_age_ms() -> f64 {
    50.0
}
fn default_frame_max_age_ms() -> f64 {
    500.0
}
fn default_max_future_ms() -> f64 {
    1.0
}
fn default_status_rate_hz() -> f64 {
    10.0
}

/// One camera.
#[derive(Debug, Clone, Serialize, Deserialize, PartialEq)]
#[serde(deny_unknown_fields)]
pub struct CameraConfig {
    /// Camera name; also the policy's image key (e.g. `base_0_rgb`).
    pub name: String,
    /// Largest frame the camera will publish (the publisher is sized for it).
    pub width: u32,
    pub height: u32,
    /// Frame rate of fake cameras (Hz).
    #[serde(default = "default_fps")]
    pub fps: f64,
    /// `rgb8`, `bgr8` or `mono8`.
    #[serde(default = "default_encoding")]
    pub encoding: String,
}

fn default_fps() -> f64 {
    30.0
}
fn default_encoding() -> String {
    "rgb8".to_string()
}

impl CameraConfig {
    /// The `ENCODING_*` code of this camera.
    pub fn encoding_code(&self) -> u32 {
        match self.encoding.as_str() {
            "bgr8" => crate::ENCODING_BGR8,
            "mono8" => crate::ENCODING_MONO8,
            _ => crate::ENCODING_RGB8,
        }
    }
}

mod enums;
pub mod ros2;

/// Collects the checks of one file: each names the file, the key and what is allowed (used by
/// the crates that own the other sections too).
pub struct Checker<'a> {
    /// The file's name in errors.
    pub file: &'a str,
}

impl Checker<'_> {
    /// The error for `key` = `value`.
    pub fn fail(&self, key: &str, value: impl std::fmt::Display, allowed: &str) -> ConfigError {
        ConfigError::Invalid {
            file: self.file.to_string(),
            key: key.to_string(),
            value: value.to_string(),
            allowed: allowed.to_string(),
        }
    }

    /// `v` must be finite and within `lo..=hi`.
    pub fn range(&self, key: &str, v: f64, lo: f64, hi: f64) -> Result<(), ConfigError> {
        if v.is_finite() && v >= lo && v <= hi {
            Ok(())
        } else {
            Err(self.fail(key, v, &format!("must be in {lo}..={hi}")))
        }
    }

    /// `v` must be one of `allowed`.
    pub fn one_of(&self, key: &str, v: &str, allowed: &[&str]) -> Result<(), ConfigError> {
        if allowed.contains(&v) {
            Ok(())
        } else {
            Err(self.fail(
                key,
                format!("{v:?}"),
                &format!("must be one of {}", allowed.join(", ")),
            ))
        }
    }

    /// `v` must be a name of 1..=64 `[A-Za-z0-9_-]`.
    pub fn name(&self, key: &str, v: &str) -> Result<(), ConfigError> {
        if !v.is_empty()
            && v.len() <= 64
            && v.chars()
                .all(|c| c.is_ascii_alphanumeric() || c == '_' || c == '-')
        {
            Ok(())
        } else {
            Err(self.fail(
                key,
                format!("{v:?}"),
                "must be 1..=64 characters of [A-Za-z0-9_-]",
            ))
        }
    }
}

impl SharedConfig {
    /// Reads and validates a TOML file.
    pub fn load(path: &Path) -> Result<Self, ConfigError> {
        let file = path.display().to_string();
        let text = read_config_file(path)?;
        let mut cfg = Self::parse(&text, &file)?;
        cfg.source = path.to_path_buf();
        Ok(cfg)
    }

    /// The embedded default configuration (the demo robot).
    pub fn embedded_default() -> Self {
        let mut cfg = Self::parse(DEFAULT_TOML, "config/default.toml (embedded)")
            .expect("the embedded default configuration is valid (checked by tests)");
        cfg.source = embedded_source();
        cfg
    }

    /// Parses and validates TOML text; `file` names it in errors.
    pub fn parse(text: &str, file: &str) -> Result<Self, ConfigError> {
        let cfg: SharedConfig = toml::from_str(text).map_err(|e| ConfigError::Parse {
            file: file.to_string(),
            message: e.to_string().trim_end().to_string(),
        })?;
        validate_shared(&cfg.robot, &cfg.control, &cfg.cameras, &Checker { file })?;
        Ok(cfg)
    }

    /// Number of joints.
    pub fn n_dof(&self) -> usize {
        self.robot.joints.len()
    }

    /// The service namespace (validated on load).
    pub fn namespace(&self) -> crate::Namespace {
        crate::Namespace::new(&self.robot.namespace).expect("namespace validated on load")
    }

    /// Control period in ns.
    pub fn control_period_ns(&self) -> u64 {
        (1e9 / self.control.rate_hz).round() as u64
    }
}

/// Where the embedded default configuration's relative paths resolve: the repository's
/// `config/` folder this binary was built from.
pub fn embedded_source() -> PathBuf {
    PathBuf::from(concat!(
        env!("CARGO_MANIFEST_DIR"),
        "/../config/default.toml"
    ))
}

/// The largest configuration file read (a TOML of a robot is a few kB).
pub const MAX_CONFIG_BYTES: u64 = 1 << 20;

/// Reads a configuration file: a regular file of at most [`MAX_CONFIG_BYTES`].
pub fn read_config_file(path: &Path) -> Result<String, ConfigError> {
    let file = path.display().to_string();
    let fail = |error: std::io::Error| ConfigError::Read {
        file: file.clone(),
        error,
    };
    let meta = std::fs::metadata(path).map_err(fail)?;
    if !meta.is_file() {
        return Err(fail(std::io::Error::other("not a regular file")));
    }
    if meta.len() > MAX_CONFIG_BYTES {
        return Err(fail(std::io::Error::other(format!(
            "{} bytes; a configuration is at most {MAX_CONFIG_BYTES}",
            meta.len()
        ))));
    }
    let mut text = String::new();
    use std::io::Read;
    std::fs::File::open(path)
        .map_err(fail)?
        .take(MAX_CONFIG_BYTES)
        .read_to_string(&mut text)
        .map_err(fail)?;
    Ok(text)
}

/// A path from a configuration, resolved relative to the configuration file `source`.
pub fn resolve_relative(source: &Path, p: &Path) -> PathBuf {
    if p.is_absolute() {
        p.to_path_buf()
    } else {
        source
            .parent()
            .map(|d| d.join(p))
            .unwrap_or_else(|| p.to_path_buf())
    }
}

/// Checks the shared sections against their allowed ranges.
pub fn validate_shared(
    robot: &RobotConfig,
    control: &ControlConfig,
    cameras: &[CameraConfig],
    c: &Checker<'_>,
) -> Result<(), ConfigError> {
    c.name("robot.name", &robot.name)?;
    crate::Namespace::new(&robot.namespace).map_err(|e| {
        c.fail(
            "robot.namespace",
            format!("{:?}", robot.namespace),
            &e.to_string(),
        )
    })?;
    c.range(
        "robot.joint_state_rate_hz",
        robot.joint_state_rate_hz,
        1.0,
        10_000.0,
    )?;
    let n = robot.joints.len();
    if n == 0 || n > MAX_DOF {
        return Err(c.fail(
            "robot.joints",
            format!("{n} joints"),
            &format!("must list 1..={MAX_DOF} joints"),
        ));
    }
    for (i, j) in robot.joints.iter().enumerate() {
        let k = |f: &str| format!("robot.joints[{i}].{f}");
        c.name(&k("name"), &j.name)?;
        c.range(&k("position_min"), j.position_min, -1e3, 1e3)?;
        c.range(&k("position_max"), j.position_max, -1e3, 1e3)?;
        if j.position_max <= j.position_min {
            return Err(c.fail(
                &k("position_max"),
                j.position_max,
                &format!("must be greater than position_min ({})", j.position_min),
            ));
        }
        c.range(&k("max_velocity"), j.max_velocity, 1e-3, 100.0)?;
        c.range(&k("max_acceleration"), j.max_acceleration, 1e-3, 1e4)?;
        c.range(&k("max_jerk"), j.max_jerk, 1e-3, 1e6)?;
        c.range(
            &k("initial_position"),
            j.initial_position,
            j.position_min,
            j.position_max,
        )?;
    }
    let ctl = control;
    c.range("control.rate_hz", ctl.rate_hz, 10.0, 10_000.0)?;
    if let Some(cpu) = ctl.cpu {
        c.range("control.cpu", cpu as f64, 0.0, 1023.0)?;
    }
    c.range(
        "control.realtime_priority",
        ctl.realtime_priority as f64,
        0.0,
        99.0,
    )?;
    c.range(
        "control.command_deadline_ms",
        ctl.command_deadline_ms,
        0.1,
        1000.0,
    )?;
    c.range(
        "control.joint_state_max_age_ms",
        ctl.joint_state_max_age_ms,
        1.0,
        10_000.0,
    )?;
    c.range(
        "control.frame_max_age_ms",
        ctl.frame_max_age_ms,
        1.0,
        60_000.0,
    )?;
    c.range("control.max_future_ms", ctl.max_future_ms, 0.0, 1000.0)?;
    c.range("control.status_rate_hz", ctl.status_rate_hz, 0.1, 1000.0)?;
    c.range(
        "control.robot_clock_timeout_ms",
        ctl.robot_clock_timeout_ms,
        0.1,
        1000.0,
    )?;
    if ctl.clock == ControlClock::Robot && (ctl.rate_hz - robot.joint_state_rate_hz).abs() > 1e-9 {
        // the generator steps one control period per robot cycle
        return Err(c.fail(
            "control.rate_hz",
            ctl.rate_hz,
            &format!(
                "must equal robot.joint_state_rate_hz ({}) with control.clock = \"robot\" (one \
                 tick per robot state)",
                robot.joint_state_rate_hz
            ),
        ));
    }
    let mut names = std::collections::HashSet::new();
    for (i, cam) in cameras.iter().enumerate() {
        let k = |f: &str| format!("cameras[{i}].{f}");
        c.name(&k("name"), &cam.name)?;
        if !names.insert(cam.name.as_str()) {
            return Err(c.fail(&k("name"), &cam.name, "camera names must be unique"));
        }
        c.range(&k("width"), cam.width as f64, 1.0, 8192.0)?;
        c.range(&k("height"), cam.height as f64, 1.0, 8192.0)?;
        c.range(&k("fps"), cam.fps, 0.1, 1000.0)?;
        c.one_of(&k("encoding"), &cam.encoding, &["rgb8", "bgr8", "mono8"])?;
    }
    Ok(())
}

#[cfg(test)]
mod tests;
