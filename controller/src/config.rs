//! The controller's whole configuration: one TOML file per robot. Each section is typed by the
//! crate that owns it — `[robot]`, `[control]` and `[[cameras]]` by `chunkrt-ipc` (every
//! process of the robot reads them), `[policy]` here with the policy crate's own types
//! (precision, device, model overrides: [`PolicyConfig::load_options`]), `[execution]` here (the
//! control tick's), `[openpi]` by `chunkrt-openpi` (the request layout of `chunkrt serve` and
//! of a remote policy).
//!
//! Every error names the file, the key and what is allowed, e.g.
//! `config/robot.toml: robot.joints[2].max_velocity = -1: must be in 0.001..=100`.
//! Unknown keys are errors too (a typo must not silently fall back to a default).

use std::path::{Path, PathBuf};

use serde::{Deserialize, Serialize};

pub use chunkrt_ipc::config::ros2::Ros2Config;
pub use chunkrt_ipc::config::{
    CameraConfig, Checker, ConfigError, ControlConfig, JointConfig, RobotConfig, SharedConfig,
    DEFAULT_TOML,
};
use chunkrt_openpi::LayoutConfig;
use chunkrt_policy::config::ConfigOverrides;
pub use chunkrt_policy::{DeviceSpec, Jacobian, LoadOptions, ModelKind, Precision};

/// Whole controller configuration.
#[derive(Debug, Clone, Deserialize, Serialize, PartialEq)]
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
    /// The openpi protocol's request layout (`chunkrt serve`, `policy.source = "remote"`).
    #[serde(default)]
    pub openpi: LayoutConfig,
    /// `chunkrt serve`'s connection limits.
    #[serde(default)]
    pub serve: ServeSettings,
    /// `chunkrt ros2`'s topics, joints, command mode and QoS (the bridge reads it; not used here).
    #[serde(default)]
    pub ros2: Ros2Config,
    /// Where the configuration came from (not part of the file).
    #[serde(skip)]
    pub source: PathBuf,
}

/// `[serve]`: how many connections `chunkrt serve` holds and for how long (its flags override).
#[derive(Debug, Clone, Deserialize, Serialize, PartialEq)]
#[serde(deny_unknown_fields)]
pub struct ServeSettings {
    /// Websockets open at once (a new one takes the slot of the longest-idle; HTTP 503 when all
    /// are in use).
    #[serde(default = "default_max_connections")]
    pub max_connections: usize,
    /// Connections one peer address may hold at once.
    #[serde(default = "default_max_per_address")]
    pub max_per_address: usize,
    /// Seconds a connection has to complete its HTTP request and websocket handshake.
    #[serde(default = "default_handshake_timeout_s")]
    pub handshake_timeout_s: f64,
    /// Seconds a websocket may go without a request before it is closed.
    #[serde(default = "default_idle_timeout_s")]
    pub idle_timeout_s: f64,
}

fn default_max_connections() -> usize {
    16
}
fn default_max_per_address() -> usize {
    4
}
fn default_handshake_timeout_s() -> f64 {
    2.0
}
fn default_idle_timeout_s() -> f64 {
    30.0
}

impl Default for ServeSettings {
    fn default() -> Self {
        Self {
            max_connections: default_max_connections(),
            max_per_address: default_max_per_address(),
            handshake_timeout_s: default_handshake_timeout_s(),
            idle_timeout_s: default_idle_timeout_s(),
        }
    }
}

chunkrt_ipc::config_enum! {
    /// `policy.source`: where the chunks come from.
    pub enum PolicySource ("policy source") {
        /// The policy runs in this process (`policy.checkpoint`).
        #[default]
        Local = "local",
        /// An openpi-protocol server on another machine (`policy.url`): `chunkrt serve`,
        /// openpi's `serve_policy.py`, SGLang, vLLM-Omni.
        Remote = "remote",
        /// A **test double**, no model: chunks of a known smooth trajectory around each joint's
        /// `initial_position`, landing `[policy.scripted] latency_ms` after their observation
        /// (`chunkrt run --scripted`): for bringing a robot up and for the tests.
        Scripted = "scripted",
    }
}

/// `[policy.scripted]`: the scripted test double's chunks.
#[derive(Debug, Clone, Deserialize, Serialize, PartialEq)]
#[serde(deny_unknown_fields)]
pub struct ScriptedSettings {
    /// Observation → chunk ready (ms): the delay a real policy's inference would add.
    #[serde(default = "default_scripted_latency_ms")]
    pub latency_ms: f64,
    /// When not empty: the chunks land after these many action periods in turn (a sweep of
    /// delays in one run; `latency_ms` is then unused).
    #[serde(default)]
    pub delays: Vec<u32>,
    /// Amplitude of each joint's sinusoid around its initial position (rad; at most a quarter
    /// of the joint's range).
    #[serde(default = "default_scripted_amplitude")]
    pub amplitude: f64,
    /// Frequency of joint 1's sinusoid (Hz; each next joint's 15 % higher).
    #[serde(default = "default_scripted_frequency_hz")]
    pub frequency_hz: f64,
    /// Consecutive chunks disagree by ±this much (rad): what a chunk switch must absorb.
    #[serde(default)]
    pub jump: f64,
    /// Actions per chunk.
    #[serde(default = "default_scripted_horizon")]
    pub horizon: usize,
    /// Step channels (a gripper) toggle every this many seconds.
    #[serde(default = "default_scripted_step_period_s")]
    pub step_period_s: f64,
}

impl Default for ScriptedSettings {
    fn default() -> Self {
        Self {
            latency_ms: default_scripted_latency_ms(),
            delays: Vec::new(),
            amplitude: default_scripted_amplitude(),
            frequency_hz: default_scripted_frequency_hz(),
            jump: 0.0,
            horizon: default_scripted_horizon(),
            step_period_s: default_scripted_step_period_s(),
        }
    }
}

fn default_scripted_latency_ms() -> f64 {
    50.0
}
fn default_scripted_amplitude() -> f64 {
    0.15
}
fn default_scripted_frequency_hz() -> f64 {
    0.2
}
fn default_scripted_horizon() -> usize {
    50
}
fn default_scripted_step_period_s() -> f64 {
    2.0
}

/// `policy.kind`: `"hold"` (no policy: the controller holds the robot where it is; the
/// default), `"pi0"` or `"pi05"`.
fn hold_or_kind<'de, D: serde::Deserializer<'de>>(d: D) -> Result<Option<ModelKind>, D::Error> {
    match String::deserialize(d)?.as_str() {
        "hold" => Ok(None),
        "pi0" => Ok(Some(ModelKind::Pi0)),
        "pi05" => Ok(Some(ModelKind::Pi05)),
        other => Err(serde::de::Error::custom(format!(
            "policy kind {other:?}: must be one of hold, pi0, pi05"
        ))),
    }
}

/// `policy.kind` as the file writes it (`--print-config`).
fn kind_or_hold<S: serde::Serializer>(k: &Option<ModelKind>, s: S) -> Result<S::Ok, S::Error> {
    s.serialize_str(match k {
        None => "hold",
        Some(ModelKind::Pi0) => "pi0",
        Some(ModelKind::Pi05) => "pi05",
    })
}

/// `[policy]`: which chunk source feeds the control loop, and how the policy is loaded. The
/// loading options are the policy crate's own types ([`Self::load_options`]).
#[derive(Debug, Clone, Deserialize, Serialize, PartialEq)]
#[serde(deny_unknown_fields)]
pub struct PolicyConfig {
    /// `hold` (None: no policy, the controller holds), `pi0`, `pi05`.
    #[serde(
        default,
        deserialize_with = "hold_or_kind",
        serialize_with = "kind_or_hold"
    )]
    pub kind: Option<ModelKind>,
    /// `local` (the checkpoint in this process) or `remote` (a server at `url`).
    #[serde(default)]
    pub source: PolicySource,
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
    #[serde(default = "default_precision")]
    pub precision: Precision,
    /// Where the model runs: `cpu` (default), `cuda` or `cuda:N`.
    #[serde(default)]
    pub device: DeviceSpec,
    /// Overrides of the checkpoint's model dimensions (`[policy.model]`).
    #[serde(default)]
    pub model: ConfigOverrides,
    /// The prompt tokenizer when the checkpoint directory has none: openpi's
    /// `paligemma_tokenizer.model` (SentencePiece) or a Hugging Face `tokenizer.json`; relative
    /// to the config.
    #[serde(default)]
    pub tokenizer: Option<PathBuf>,
    /// openpi checkpoints: which `assets/<asset_id>/norm_stats.json` (when there are several).
    #[serde(default)]
    pub asset_id: Option<String>,
    /// openpi's training config whose transforms wrap the model (`pi05_libero`,
    /// `pi0_aloha_sim`, ...: the robot's input and output transforms, delta dims, default
    /// prompt, horizon; `chunkrt inspect` prints them). Unset: recognised from an openpi
    /// checkpoint's folder name or assets where it can be.
    #[serde(default)]
    pub openpi_config: Option<String>,
    /// `source = "remote"`: the server, `ws://host:port[/path]`.
    #[serde(default)]
    pub url: Option<String>,
    /// `source = "remote"`: sent as `Authorization: Api-Key …` (default: the environment
    /// variable `CHUNKRT_API_KEY`, so the key need not sit in a file).
    #[serde(default)]
    pub api_key: Option<String>,
    /// `source = "remote"`: TCP connect, handshake and metadata (ms).
    #[serde(default = "default_connect_timeout_ms")]
    pub connect_timeout_ms: f64,
    /// `source = "remote"`: a server whose actions have more columns than the robot has joints
    /// (a padded 32-dim reply) is cut to the robot's; off, such a reply is an error.
    #[serde(default)]
    pub truncate_actions: bool,
    /// `source = "scripted"`: the test double's chunks.
    #[serde(default)]
    pub scripted: ScriptedSettings,
}

fn default_steps() -> usize {
    10
}
fn default_action_rate_hz() -> f64 {
    50.0
}
fn default_precision() -> Precision {
    Precision::F32
}
fn default_connect_timeout_ms() -> f64 {
    2_000.0
}

impl Default for PolicyConfig {
    fn default() -> Self {
        Self {
            kind: None,
            source: PolicySource::Local,
            checkpoint: None,
            prompt: String::new(),
            num_steps: default_steps(),
            action_rate_hz: default_action_rate_hz(),
            threads: 0,
            precision: default_precision(),
            device: DeviceSpec::Cpu,
            model: ConfigOverrides::default(),
            tokenizer: None,
            asset_id: None,
            openpi_config: None,
            url: None,
            api_key: None,
            connect_timeout_ms: default_connect_timeout_ms(),
            truncate_actions: false,
            scripted: ScriptedSettings::default(),
        }
    }
}

impl PolicyConfig {
    /// The policy crate's load options for this section (`tokenizer` as given: resolve it
    /// against the configuration first, [`Config::resolve`]).
    pub fn load_options(&self) -> LoadOptions {
        let mut overrides = self.model.clone();
        overrides.num_denoise_steps = Some(self.num_steps);
        LoadOptions {
            kind: self.kind,
            num_steps: self.num_steps,
            precision: self.precision,
            device: self.device,
            overrides,
            cuda_graph: true,
            layout: chunkrt_policy::layout::LayoutOptions {
                tokenizer: self.tokenizer.clone(),
                asset_id: self.asset_id.clone(),
                openpi_config: self.openpi_config.clone(),
            },
        }
    }

    /// `kind` as the configuration spells it.
    pub fn kind_name(&self) -> &'static str {
        self.kind.map_or("hold", |k| k.name())
    }
}

chunkrt_ipc::config_enum! {
    /// `execution.strategy`: how consecutive chunks take over from each other.
    pub enum Strategy ("strategy") {
        /// Switch at the first action of the new chunk that is not yet due.
        Replace = "replace",
        /// Blend old → new over `crossfade_ms`, starting where `Replace` would switch.
        Crossfade = "crossfade",
        /// ACT's temporal ensemble: exponentially weighted average of every chunk covering now.
        TemporalEnsemble = "temporal_ensemble",
        /// Real-time chunking: switch at once, at the index real time has reached; the sampler
        /// is guided towards the actions still to be executed.
        #[default]
        Rtc = "rtc",
        /// Training-time real-time chunking: switch at once like `Rtc`; a policy trained with a
        /// committed prefix (`chunkrt train --rtc-prefix`) is given the actions still to be
        /// executed and continues them (no guidance pass).
        RtcTrained = "rtc_trained",
    }
}

chunkrt_ipc::config_enum! {
    /// `execution.interpolation` between a chunk's actions.
    pub enum Interpolation ("interpolation") {
        /// Velocity-continuous cubic Hermite.
        #[default]
        Cubic = "cubic",
        /// Piecewise linear.
        Linear = "linear",
    }
}

chunkrt_ipc::config_enum! {
    /// `execution.trigger`: when the next inference is requested.
    pub enum Trigger ("trigger") {
        /// Once `execute_horizon` actions of the newest chunk are due.
        #[default]
        AfterS = "after_s",
        /// As soon as the previous inference landed.
        Continuous = "continuous",
    }
}

chunkrt_ipc::config_enum! {
    /// `execution.stale_hold`: where the arm is held while the robot's joint states stop.
    pub enum StaleHold ("stale hold") {
        /// Where the robot last was: its last fresh state, reached within the limits. A robot
        /// whose process stops stops its arm with its states (a simulator, a servo bus that
        /// holds its last setpoint); its first command back is then where it is.
        #[default]
        LastState = "last_state",
        /// Brake from the generator's own motion: a robot whose arm goes on without its states
        /// (the FR3's FCI continues and stops a stalled driver's motion itself).
        Brake = "brake",
    }
}

chunkrt_ipc::config_enum! {
    /// `execution.rtc_schedule`: RTC's soft-mask schedule between d and H − s.
    pub enum Schedule ("rtc schedule") {
        /// The paper's exponential decay `c (e^c − 1)/(e − 1)`.
        #[default]
        Exp = "exp",
        /// Linear decay `c`.
        Linear = "linear",
        /// 1 everywhere before H − s (hard prefix over the whole overlap).
        Ones = "ones",
        /// 0 from d on (hard prefix of d actions only).
        Zeros = "zeros",
    }
}

/// How chunks are executed (transitions, real-time chunking, watchdog). Owned by `control`.
#[derive(Debug, Clone, Deserialize, Serialize, PartialEq)]
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
    /// While the robot's joint states stop: `last_state` (hold where the robot last was) or
    /// `brake` (brake from the generator's motion, for a robot whose arm goes on without them).
    #[serde(default)]
    pub stale_hold: StaleHold,
    /// `crossfade`: blend window from the old to the new chunk (ms).
    #[serde(default = "default_crossfade_ms")]
    pub crossfade_ms: f64,
    /// Tracking (1/s): the jerk-limited generator follows the executed chunk's velocity and
    /// acceleration (its preview) plus this gain times the position error, instead of chasing
    /// the chunk's state at the tick as a fixed target. 0: the fixed-target chase.
    #[serde(default = "default_tracking_gain")]
    pub tracking_gain: f64,
    /// Tracking: the most the position-error term may add to the chunk's own velocity, as a
    /// fraction of each joint's `max_velocity` (0–1]. Below 1, a large error (a new controller
    /// taking over an arm the chunk starts away from, a re-seed, a switch onto a distant chunk)
    /// closes at this share of the joint's speed instead of at its full speed.
    #[serde(default = "default_correction_speed")]
    pub correction_speed: f64,
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
    pub rtc_jacobian: Jacobian,
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
fn default_correction_speed() -> f64 {
    1.0
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
            stale_hold: Default::default(),
            crossfade_ms: default_crossfade_ms(),
            tracking_gain: default_tracking_gain(),
            correction_speed: default_correction_speed(),
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

impl Config {
    /// Reads and validates a TOML file (a regular file of at most
    /// [`chunkrt_ipc::config::MAX_CONFIG_BYTES`]).
    pub fn load(path: &Path) -> Result<Self, ConfigError> {
        let file = path.display().to_string();
        let text = chunkrt_ipc::config::read_config_file(path)?;
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
        cfg.source = chunkrt_ipc::config::embedded_source();
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

    /// The sections every process shares.
    pub fn shared(&self) -> SharedConfig {
        SharedConfig {
            robot: self.robot.clone(),
            control: self.control.clone(),
            cameras: self.cameras.clone(),
            source: self.source.clone(),
        }
    }

    /// Checks every value against its allowed range.
    pub fn validate(&self, file: &str) -> Result<(), ConfigError> {
        let c = Checker { file };
        chunkrt_ipc::config::validate_shared(&self.robot, &self.control, &self.cameras, &c)?;
        let p = &self.policy;
        if p.source == PolicySource::Scripted {
            let sc = &p.scripted;
            c.range("policy.scripted.latency_ms", sc.latency_ms, 0.0, 60_000.0)?;
            c.range("policy.scripted.amplitude", sc.amplitude, 0.0, 10.0)?;
            c.range("policy.scripted.frequency_hz", sc.frequency_hz, 0.0, 100.0)?;
            c.range("policy.scripted.jump", sc.jump, 0.0, 10.0)?;
            c.range("policy.scripted.horizon", sc.horizon as f64, 1.0, 1000.0)?;
            c.range(
                "policy.scripted.step_period_s",
                sc.step_period_s,
                0.01,
                3600.0,
            )?;
        }
        if p.kind.is_some() && p.source == PolicySource::Local && p.checkpoint.is_none() {
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
        c.range("execution.correction_speed", e.correction_speed, 0.01, 1.0)?;
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
        if p.source == PolicySource::Remote {
            if p.kind.is_none() {
                return Err(c.fail(
                    "policy.kind",
                    "\"hold\"",
                    "a remote policy needs kind = \"pi0\" or \"pi05\" (what the server runs)",
                ));
            }
            match p.url.as_deref() {
                Some(u) if u.starts_with("ws://") && u.len() > 5 && u.len() <= 2048 => {}
                Some(u) => {
                    return Err(c.fail(
                        "policy.url",
                        format!("{u:?}"),
                        "must be ws://host:port[/path] (wss:// is not supported)",
                    ))
                }
                None => {
                    return Err(c.fail(
                        "policy.url",
                        "(missing)",
                        "source = \"remote\" needs the server's ws://host:port",
                    ))
                }
            }
        }
        c.range(
            "policy.connect_timeout_ms",
            p.connect_timeout_ms,
            1.0,
            600_000.0,
        )?;
        chunkrt_openpi::Layout::from_config(&self.openpi).map_err(|e| c.fail("openpi", "", &e))?;
        Ok(())
    }

    /// Number of joints.
    pub fn n_dof(&self) -> usize {
        self.robot.joints.len()
    }

    /// The service namespace (validated on load).
    pub fn namespace(&self) -> chunkrt_ipc::Namespace {
        chunkrt_ipc::Namespace::new(&self.robot.namespace).expect("namespace validated on load")
    }

    /// A path from the configuration, resolved relative to the configuration file.
    pub fn resolve(&self, p: &Path) -> PathBuf {
        chunkrt_ipc::config::resolve_relative(&self.source, p)
    }

    /// Control period in ns.
    pub fn control_period_ns(&self) -> u64 {
        (1e9 / self.control.rate_hz).round() as u64
    }
}

#[cfg(test)]
mod tests;
