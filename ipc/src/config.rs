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

/// Whole controller configuration.
#[derive(Debug, Clone, Serialize, Deserialize, PartialEq)]
#[serde(deny_unknown_fields)]
pub struct Config {
    pub robot: RobotConfig,
    pub control: ControlConfig,
    #[serde(default)]
    pub cameras: Vec<CameraConfig>,
    #[serde(default)]
    pub policy: PolicyConfig,
    #[serde(default)]
    pub execution: ExecutionConfig,
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
    pub name: String,
    pub position_min: f64,
    pub position_max: f64,
    pub max_velocity: f64,
    pub max_acceleration: f64,
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
pub use enums::*;

/// Which chunk source feeds the control loop.
#[derive(Debug, Clone, Serialize, Deserialize, PartialEq)]
#[serde(deny_unknown_fields)]
pub struct PolicyConfig {
    /// `hold` (no policy: the controller holds), `pi0`, `pi05`.
    #[serde(default)]
    pub kind: PolicyKind,
    /// Checkpoint directory (`config.json`, `model.safetensors`, ...); relative to the config.
    #[serde(default)]
    pub checkpoint: Option<PathBuf>,
    /// Prompt given to the policy.
    #[serde(default)]
    pub prompt: String,
    /// Flow-matching denoising steps.
    #[serde(default = "default_steps")]
    pub num_steps: usize,
    /// Action rate of the policy (Hz); the chunk's action period is its inverse.
    #[serde(default = "default_action_rate_hz")]
    pub action_rate_hz: f64,
    /// Threads of the policy's own pool (0: one per core; the control thread, pinned and
    /// SCHED_FIFO, preempts them on its core).
    #[serde(default)]
    pub threads: usize,
    /// Arithmetic of the model's matrix products: `f32` (the reference) or `bf16` (inputs
    /// rounded to bf16, f32 accumulation: on a CPU with Intel AMX or AVX512-BF16, else f32 with a
    /// warning; on a GPU the model's tensors are bf16).
    #[serde(default)]
    pub precision: PolicyPrecision,
    /// Where the model runs: `cpu` (default), `cuda` or `cuda:N`.
    #[serde(default)]
    pub device: PolicyDevice,
    /// Overrides of the checkpoint's model dimensions (`[policy.model]`), for real openpi /
    /// LeRobot checkpoints that ship no `config.json` (their dimensions come from the preset of
    /// the detected kind).
    #[serde(default)]
    pub model: ModelOverrides,
}

/// `[policy.model]`: what may differ from the checkpoint's `config.json` or preset.
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct ModelOverrides {
    /// Actions per chunk the checkpoint was trained with.
    pub action_horizon: Option<usize>,
    /// Padded action dimension.
    pub action_dim: Option<usize>,
    /// Prompt length in tokens.
    pub max_token_len: Option<usize>,
    /// Image keys in the model's order (config cameras are matched by name).
    pub cameras: Option<Vec<String>>,
    /// Joints whose actions the checkpoint predicts relative to the observed state (openpi's
    /// `DeltaActions`), in robot joint order; the rest are absolute.
    pub delta_action_mask: Option<Vec<bool>>,
}

fn default_steps() -> usize {
    10
}
fn default_action_rate_hz() -> f64 {
    50.0
}

impl Default for PolicyConfig {
    fn default() -> Self {
        Self {
            kind: PolicyKind::Hold,
            checkpoint: None,
            prompt: String::new(),
            num_steps: default_steps(),
            action_rate_hz: default_action_rate_hz(),
            threads: 0,
            precision: PolicyPrecision::F32,
            device: PolicyDevice::Cpu,
            model: ModelOverrides::default(),
        }
    }
}

/// How chunks are executed (transitions, real-time chunking, watchdog). Owned by `control`.
#[derive(Debug, Clone, Serialize, Deserialize, PartialEq)]
#[serde(deny_unknown_fields)]
pub struct ExecutionConfig {
    /// `replace`, `crossfade`, `temporal_ensemble` or `rtc`.
    #[serde(default)]
    pub strategy: Strategy,
    /// Execution offset added to every action time (ms; see `chunk`).
    #[serde(default)]
    pub offset_ms: f64,
    /// `cubic` (velocity-continuous Hermite) or `linear`.
    #[serde(default)]
    pub interpolation: Interpolation,
    /// Time in HOLD before FAULT (ms).
    #[serde(default = "default_hold_to_fault_ms")]
    pub hold_to_fault_ms: f64,
    /// `crossfade`: blend window from the old to the new chunk (ms).
    #[serde(default = "default_crossfade_ms")]
    pub crossfade_ms: f64,
    /// Tracking (1/s): the jerk-limited generator follows the executed chunk's velocity and
    /// acceleration (its preview) plus this gain times the position error, instead of chasing
    /// the chunk's state at the tick as a fixed target. 0: the fixed-target chase.
    #[serde(default = "default_tracking_gain")]
    pub tracking_gain: f64,
    /// Future-state inference (VLASH): the policy observes the joint state the current chunk
    /// will have reached when the new chunk lands (rolled forward by the estimated delay), not
    /// the measured one, and the new chunk continues from there.
    #[serde(default)]
    pub future_state: bool,
    /// `temporal_ensemble`: ACT's weight decay m (the i-th oldest chunk covering a time gets
    /// weight exp(-m·i)).
    #[serde(default = "default_ensemble_decay")]
    pub ensemble_decay: f64,
    /// Inference trigger: `after_s` (start the next inference once `execute_horizon` actions of
    /// the newest chunk are due) or `continuous` (start it as soon as the previous one landed).
    #[serde(default)]
    pub trigger: Trigger,
    /// s: actions of a chunk executed before the next inference starts.
    #[serde(default = "default_execute_horizon")]
    pub execute_horizon: usize,
    /// `rtc`: b, the number of observed inference delays whose maximum estimates the delay d.
    #[serde(default = "default_delay_buffer")]
    pub delay_buffer: usize,
    /// `rtc`: the delay d (action steps) assumed before any inference has been observed.
    #[serde(default = "default_initial_delay_steps")]
    pub initial_delay_steps: usize,
    /// `rtc`: β, the guidance weight clip handed to the guided sampler.
    #[serde(default = "default_guidance_beta")]
    pub guidance_beta: f64,
    /// `rtc`: soft-mask schedule between d and H − s: `exp` (the paper's), `linear`, `ones`, `zeros`.
    #[serde(default)]
    pub rtc_schedule: Schedule,
    /// `rtc`: the guidance's Jacobian: `identity` (∂Â/∂x_t ≈ I, as cheap as an unguided step;
    /// the default) or `vjp` (exact, a backward pass per step).
    #[serde(default)]
    pub rtc_jacobian: RtcJacobian,
    /// Consecutive overrunning ticks that put the controller in HOLD.
    #[serde(default = "default_overrun_streak")]
    pub overrun_streak: u32,
    /// An inference that has not landed after this long is given up and requested again (ms).
    #[serde(default = "default_inference_timeout_ms")]
    pub inference_timeout_ms: f64,
}

fn default_hold_to_fault_ms() -> f64 {
    10_000.0
}
fn default_crossfade_ms() -> f64 {
    200.0
}
fn default_tracking_gain() -> f64 {
    10.0
}
fn default_ensemble_decay() -> f64 {
    0.01
}
fn default_execute_horizon() -> usize {
    25
}
fn default_delay_buffer() -> usize {
    10
}
fn default_initial_delay_steps() -> usize {
    5
}
fn default_guidance_beta() -> f64 {
    10.0
}
fn default_overrun_streak() -> u32 {
    10
}
fn default_inference_timeout_ms() -> f64 {
    5_000.0
}

impl Default for ExecutionConfig {
    fn default() -> Self {
        Self {
            strategy: Default::default(),
            offset_ms: 0.0,
            interpolation: Default::default(),
            hold_to_fault_ms: default_hold_to_fault_ms(),
            crossfade_ms: default_crossfade_ms(),
            tracking_gain: default_tracking_gain(),
            future_state: false,
            ensemble_decay: default_ensemble_decay(),
            trigger: Default::default(),
            execute_horizon: default_execute_horizon(),
            delay_buffer: default_delay_buffer(),
            initial_delay_steps: default_initial_delay_steps(),
            guidance_beta: default_guidance_beta(),
            rtc_schedule: Default::default(),
            rtc_jacobian: Default::default(),
            overrun_streak: default_overrun_streak(),
            inference_timeout_ms: default_inference_timeout_ms(),
        }
    }
}

/// Collects the checks of one file.
struct Checker<'a> {
    file: &'a str,
}

impl Checker<'_> {
    fn fail(&self, key: &str, value: impl std::fmt::Display, allowed: &str) -> ConfigError {
        ConfigError::Invalid {
            file: self.file.to_string(),
            key: key.to_string(),
            value: value.to_string(),
            allowed: allowed.to_string(),
        }
    }

    fn range(&self, key: &str, v: f64, lo: f64, hi: f64) -> Result<(), ConfigError> {
        if v.is_finite() && v >= lo && v <= hi {
            Ok(())
        } else {
            Err(self.fail(key, v, &format!("must be in {lo}..={hi}")))
        }
    }

    fn one_of(&self, key: &str, v: &str, allowed: &[&str]) -> Result<(), ConfigError> {
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

    fn name(&self, key: &str, v: &str) -> Result<(), ConfigError> {
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

impl Config {
    /// Reads and validates a TOML file.
    pub fn load(path: &Path) -> Result<Self, ConfigError> {
        let file = path.display().to_string();
        let text = std::fs::read_to_string(path).map_err(|error| ConfigError::Read {
            file: file.clone(),
            error,
        })?;
        let mut cfg = Self::parse(&text, &file)?;
        cfg.source = path.to_path_buf();
        Ok(cfg)
    }

    /// The embedded default configuration (the demo robot).
    /// Relative paths in it (the policy checkpoint) resolve against the repository's `config/`
    /// folder this binary was built from.
    pub fn embedded_default() -> Self {
        let mut cfg = Self::parse(DEFAULT_TOML, "config/default.toml (embedded)")
            .expect("the embedded default configuration is valid (checked by tests)");
        cfg.source = PathBuf::from(concat!(
            env!("CARGO_MANIFEST_DIR"),
            "/../config/default.toml"
        ));
        cfg
    }

    /// Parses and validates TOML text; `file` names it in errors.
    pub fn parse(text: &str, file: &str) -> Result<Self, ConfigError> {
        let cfg: Config = toml::from_str(text).map_err(|e| ConfigError::Parse {
            file: file.to_string(),
            message: e.to_string().trim_end().to_string(),
        })?;
        cfg.validate(file)?;
        Ok(cfg)
    }

    /// Checks every value against its allowed range.
    pub fn validate(&self, file: &str) -> Result<(), ConfigError> {
        let c = Checker { file };
        c.name("robot.name", &self.robot.name)?;
        crate::Namespace::new(&self.robot.namespace).map_err(|e| {
            c.fail(
                "robot.namespace",
                format!("{:?}", self.robot.namespace),
                &e.to_string(),
            )
        })?;
        c.range(
            "robot.joint_state_rate_hz",
            self.robot.joint_state_rate_hz,
            1.0,
            10_000.0,
        )?;
        let n = self.robot.joints.len();
        if n == 0 || n > MAX_DOF {
            return Err(c.fail(
                "robot.joints",
                format!("{n} joints"),
                &format!("must list 1..={MAX_DOF} joints"),
            ));
        }
        for (i, j) in self.robot.joints.iter().enumerate() {
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
        let ctl = &self.control;
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
        let mut names = std::collections::HashSet::new();
        for (i, cam) in self.cameras.iter().enumerate() {
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
        let p = &self.policy;
        if p.kind != PolicyKind::Hold && p.checkpoint.is_none() {
            return Err(c.fail(
                "policy.checkpoint",
                "(missing)",
                "a checkpoint directory is required for pi0 / pi05",
            ));
        }
        c.range("policy.num_steps", p.num_steps as f64, 1.0, 1000.0)?;
        c.range("policy.action_rate_hz", p.action_rate_hz, 1.0, 1000.0)?;
        // more model threads than cores only starves the robot (1024 on 2 cores: 1028 threads,
        // never RUNNING); 0 leaves candle's default
        let cores = std::thread::available_parallelism().map_or(1, |n| n.get());
        c.range("policy.threads", p.threads as f64, 0.0, cores as f64)?;
        if let Some(v) = p.model.action_horizon {
            c.range("policy.model.action_horizon", v as f64, 1.0, 1000.0)?;
        }
        if let Some(v) = p.model.action_dim {
            c.range("policy.model.action_dim", v as f64, 1.0, 1024.0)?;
        }
        if let Some(v) = p.model.max_token_len {
            c.range("policy.model.max_token_len", v as f64, 1.0, 8192.0)?;
        }
        if let Some(cams) = &p.model.cameras {
            if cams.is_empty() {
                return Err(c.fail("policy.model.cameras", "[]", "at least one camera"));
            }
            for n in cams {
                c.name("policy.model.cameras", n)?;
            }
        }
        if let Some(m) = &p.model.delta_action_mask {
            c.range(
                "policy.model.delta_action_mask (length)",
                m.len() as f64,
                0.0,
                1024.0,
            )?;
        }
        let e = &self.execution;
        c.range("execution.offset_ms", e.offset_ms, -1000.0, 1000.0)?;
        c.range(
            "execution.hold_to_fault_ms",
            e.hold_to_fault_ms,
            1.0,
            3_600_000.0,
        )?;
        c.range("execution.crossfade_ms", e.crossfade_ms, 0.0, 10_000.0)?;
        c.range("execution.tracking_gain", e.tracking_gain, 0.0, 200.0)?;
        c.range("execution.ensemble_decay", e.ensemble_decay, 0.0, 10.0)?;
        c.range(
            "execution.execute_horizon",
            e.execute_horizon as f64,
            1.0,
            1000.0,
        )?;
        c.range("execution.delay_buffer", e.delay_buffer as f64, 1.0, 1000.0)?;
        c.range(
            "execution.initial_delay_steps",
            e.initial_delay_steps as f64,
            0.0,
            1000.0,
        )?;
        c.range("execution.guidance_beta", e.guidance_beta, 0.0, 1000.0)?;
        c.range(
            "execution.overrun_streak",
            e.overrun_streak as f64,
            1.0,
            1_000_000.0,
        )?;
        c.range(
            "execution.inference_timeout_ms",
            e.inference_timeout_ms,
            1.0,
            600_000.0,
        )?;
        Ok(())
    }

    /// Number of joints.
    pub fn n_dof(&self) -> usize {
        self.robot.joints.len()
    }

    /// The service namespace (validated on load).
    pub fn namespace(&self) -> crate::Namespace {
        crate::Namespace::new(&self.robot.namespace).expect("namespace validated on load")
    }

    /// A path from the configuration, resolved relative to the configuration file.
    pub fn resolve(&self, p: &Path) -> PathBuf {
        if p.is_absolute() {
            p.to_path_buf()
        } else {
            self.source
                .parent()
                .map(|d| d.join(p))
                .unwrap_or_else(|| p.to_path_buf())
        }
    }

    /// Control period in ns.
    pub fn control_period_ns(&self) -> u64 {
        (1e9 / self.control.rate_hz).round() as u64
    }
}

#[cfg(test)]
mod tests;
