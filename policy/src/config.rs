//! Model dimensions: the `config.json` schema of the fixtures (top-level fields) and named presets
//! for real openpi / LeRobot checkpoints that ship no config.

use std::path::Path;

use serde::{Deserialize, Serialize};

use crate::error::PolicyError;

/// π0 (state token in the suffix) or π0.5 (adaRMS action expert, discrete state in the prompt).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
pub enum ModelKind {
    /// π0.
    Pi0,
    /// π0.5.
    Pi05,
}

/// π0.5 checkpoints have `time_mlp_in`; π0 ones `state_proj` (tensor names → shapes). Here,
/// below both the checkpoint reader and the layout, which ask it.
pub fn detect_kind(t: &std::collections::HashMap<String, Vec<usize>>) -> Option<ModelKind> {
    if t.contains_key("time_mlp_in.weight") {
        Some(ModelKind::Pi05)
    } else if t.contains_key("state_proj.weight") {
        Some(ModelKind::Pi0)
    } else {
        None
    }
}

impl ModelKind {
    /// `pi0` / `pi05`.
    pub fn name(self) -> &'static str {
        match self {
            ModelKind::Pi0 => "pi0",
            ModelKind::Pi05 => "pi05",
        }
    }
}

/// SigLIP vision tower dimensions.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct VisionDims {
    /// Width `Dv`.
    pub hidden_size: usize,
    /// Encoder layers.
    pub num_hidden_layers: usize,
    /// Attention heads.
    pub num_attention_heads: usize,
    /// MLP width.
    pub intermediate_size: usize,
    /// Patch size (14).
    pub patch_size: usize,
    /// Square input resolution (224).
    pub image_size: usize,
    /// LayerNorm epsilon.
    #[serde(default = "default_ln_eps")]
    pub layer_norm_eps: f64,
}

fn default_ln_eps() -> f64 {
    1e-6
}

impl VisionDims {
    /// Tokens per camera (`(image_size / patch_size)^2`).
    pub fn num_tokens(&self) -> usize {
        let side = self.image_size / self.patch_size.max(1);
        side * side
    }
}

/// One Gemma expert (the VLM language model or the action expert).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct GemmaDims {
    /// Width `W`.
    pub width: usize,
    /// Layers.
    pub depth: usize,
    /// MLP width.
    pub mlp_dim: usize,
    /// Query heads.
    pub num_heads: usize,
    /// Key/value heads (GQA).
    pub num_kv_heads: usize,
    /// Head dimension.
    pub head_dim: usize,
}

/// Everything needed to build a π0 / π0.5 model.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct ModelConfig {
    /// π0 or π0.5.
    pub kind: ModelKind,
    /// SigLIP.
    pub vision: VisionDims,
    /// PaliGemma language model (prefix expert).
    pub paligemma: GemmaDims,
    /// Action expert (suffix).
    pub action_expert: GemmaDims,
    /// Token vocabulary (taken from the embedding tensor's shape when loading).
    pub vocab_size: usize,
    /// Model action dimension `A` (state and actions are padded to it).
    pub action_dim: usize,
    /// Action horizon `H`.
    pub action_horizon: usize,
    /// Prompt length in tokens.
    pub max_token_len: usize,
    /// Cameras in prefix order.
    pub cameras: Vec<String>,
    /// Default number of denoising steps.
    pub num_denoise_steps: usize,
    /// Gemma RMSNorm epsilon.
    pub rms_norm_eps: f64,
    /// RoPE base.
    pub rope_theta: f64,
    /// Sinusoidal time embedding periods.
    pub time_min_period: f64,
    /// Sinusoidal time embedding periods.
    pub time_max_period: f64,
    /// Action dims the model predicts relative to the observed state (openpi's `DeltaActions`
    /// transform: the robot gets `state + action` on these dims, the action itself on the rest).
    /// Empty: every dim is absolute. At most `action_dim` entries; dims past the end are absolute.
    pub delta_action_mask: Vec<bool>,
    /// The checkpoint declares that its prompts were tokenized by the byte stand-in (`config.json`
    /// `"tokenizer": "byte_stand_in"`, or the fixtures' "STAND-IN ..." description), so no
    /// `tokenizer.json` is needed. Without it a missing `tokenizer.json` is a load error.
    pub byte_tokenizer: bool,
    /// Training-time real-time chunking (`config.json` `"rtc_prefix_max"`): the model was trained
    /// with a clean prefix of up to this many committed actions at flow time 0, so it can be
    /// given the actions the robot will execute while it computes and continue them
    /// (`PiModel::denoise_committed`). 0 (the default): trained without, and it cannot.
    pub rtc_prefix_max: usize,
    /// Image inputs that are an earlier frame of another camera (`config.json`
    /// `"delayed_views"`): each is one of [`Self::cameras`], and whoever builds the observation
    /// (the controller's edge, the task simulator, the dataset recorder) fills it with the
    /// frame its camera took `delay_ms` before the newest one. Two frames apart in time show
    /// which way the scene moves; one frame cannot. Empty (the default): every image is a live
    /// camera.
    #[serde(default)]
    pub delayed_views: Vec<DelayedView>,
}

/// An image input that shows an earlier frame of a live camera ([`ModelConfig::delayed_views`]).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct DelayedView {
    /// The image input's name (one of the model's cameras).
    pub name: String,
    /// The live camera it is an earlier frame of.
    pub camera: String,
    /// How much earlier than the camera's newest frame (ms).
    pub delay_ms: f64,
}

impl DelayedView {
    /// The delay in nanoseconds.
    pub fn delay_ns(&self) -> u64 {
        (self.delay_ms * 1e6) as u64
    }
}

/// The fixtures' `config.json` (only the fields we read; everything else is ignored).
#[derive(Debug, Deserialize)]
struct FileConfig {
    vision: FileVision,
    paligemma: GemmaDims,
    action_expert: GemmaDims,
    #[serde(default)]
    vocab_size: Option<usize>,
    action_dim: usize,
    action_horizon: usize,
    max_token_len: usize,
    #[serde(default)]
    pi05: Option<bool>,
    #[serde(default)]
    model_kind: Option<String>,
    #[serde(default)]
    image_keys_in_order: Option<Vec<String>>,
    #[serde(default)]
    cameras: Option<Vec<String>>,
    #[serde(default)]
    num_denoise_steps: Option<usize>,
    #[serde(default)]
    rms_norm_eps: Option<f64>,
    #[serde(default)]
    rope_theta: Option<f64>,
    #[serde(default)]
    delta_action_mask: Option<Vec<bool>>,
    #[serde(default)]
    tokenizer: Option<serde_json::Value>,
    #[serde(default)]
    rtc_prefix_max: usize,
    #[serde(default)]
    delayed_views: Vec<DelayedView>,
}

#[derive(Debug, Deserialize)]
struct FileVision {
    hidden_size: usize,
    num_hidden_layers: usize,
    num_attention_heads: usize,
    intermediate_size: usize,
    patch_size: usize,
    image_size: usize,
    #[serde(default = "default_ln_eps")]
    layer_norm_eps: f64,
}

/// openpi's default camera order.
pub const DEFAULT_CAMERAS: [&str; 3] = ["base_0_rgb", "left_wrist_0_rgb", "right_wrist_0_rgb"];

impl ModelConfig {
    /// Parses a `config.json` in the fixtures' schema.
    pub fn from_json_str(s: &str) -> Result<Self, PolicyError> {
        let f: FileConfig = serde_json::from_str(s)
            .map_err(|e| PolicyError::Config(format!("config.json: {e}")))?;
        let kind = match (f.model_kind.as_deref(), f.pi05) {
            (Some("pi05"), _) | (None, Some(true)) => ModelKind::Pi05,
            (Some("pi0"), _) | (None, Some(false)) | (None, None) => ModelKind::Pi0,
            (Some(other), _) => {
                return Err(PolicyError::Config(format!(
                    "config.json: unknown model_kind {other:?} (pi0 or pi05)"
                )))
            }
        };
        let cameras = f
            .image_keys_in_order
            .or(f.cameras)
            .unwrap_or_else(|| DEFAULT_CAMERAS.iter().map(|s| s.to_string()).collect());
        let cfg = ModelConfig {
            kind,
            vision: VisionDims {
                hidden_size: f.vision.hidden_size,
                num_hidden_layers: f.vision.num_hidden_layers,
                num_attention_heads: f.vision.num_attention_heads,
                intermediate_size: f.vision.intermediate_size,
                patch_size: f.vision.patch_size,
                image_size: f.vision.image_size,
                layer_norm_eps: f.vision.layer_norm_eps,
            },
            paligemma: f.paligemma,
            action_expert: f.action_expert,
            vocab_size: f.vocab_size.unwrap_or(257_152),
            action_dim: f.action_dim,
            action_horizon: f.action_horizon,
            max_token_len: f.max_token_len,
            cameras,
            num_denoise_steps: f.num_denoise_steps.unwrap_or(10),
            rms_norm_eps: f.rms_norm_eps.unwrap_or(1e-6),
            rope_theta: f.rope_theta.unwrap_or(10_000.0),
            time_min_period: 4e-3,
            time_max_period: 4.0,
            delta_action_mask: f.delta_action_mask.unwrap_or_default(),
            byte_tokenizer: f
                .tokenizer
                .as_ref()
                .and_then(|t| t.as_str())
                .is_some_and(|t| t == "byte_stand_in" || t.starts_with("STAND-IN")),
            rtc_prefix_max: f.rtc_prefix_max,
            delayed_views: f.delayed_views,
        };
        cfg.validate()?;
        Ok(cfg)
    }

    /// Reads `dir/config.json`.
    pub fn from_file(path: &Path) -> Result<Self, PolicyError> {
        let s = crate::files::read_side_file(path)?;
        Self::from_json_str(&s)
            .and_then(|c| c.validate().map(|()| c))
            .map_err(|e| PolicyError::Config(format!("{}: {e}", path.display())))
    }

    /// Named presets for real checkpoints: `pi0` / `pi05` (PaliGemma gemma_2b + gemma_300m action
    /// expert, SigLIP So400m/14 at 224, openpi's horizons: 50 actions of dim 32; prompt 48 / 200).
    pub fn preset(name: &str) -> Result<Self, PolicyError> {
        let kind = match name {
            "pi0" => ModelKind::Pi0,
            "pi05" | "pi0.5" => ModelKind::Pi05,
            other => return Err(PolicyError::Config(format!("unknown preset {other:?}"))),
        };
        Ok(ModelConfig {
            kind,
            vision: VisionDims {
                hidden_size: 1152,
                num_hidden_layers: 27,
                num_attention_heads: 16,
                intermediate_size: 4304,
                patch_size: 14,
                image_size: 224,
                layer_norm_eps: 1e-6,
            },
            // gemma_2b
            paligemma: GemmaDims {
                width: 2048,
                depth: 18,
                mlp_dim: 16_384,
                num_heads: 8,
                num_kv_heads: 1,
                head_dim: 256,
            },
            // gemma_300m
            action_expert: GemmaDims {
                width: 1024,
                depth: 18,
                mlp_dim: 4096,
                num_heads: 8,
                num_kv_heads: 1,
                head_dim: 256,
            },
            vocab_size: 257_152,
            action_dim: 32,
            action_horizon: 50,
            max_token_len: if kind == ModelKind::Pi05 { 200 } else { 48 },
            cameras: DEFAULT_CAMERAS.iter().map(|s| s.to_string()).collect(),
            num_denoise_steps: 10,
            rms_norm_eps: 1e-6,
            rope_theta: 10_000.0,
            time_min_period: 4e-3,
            time_max_period: 4.0,
            delta_action_mask: Vec::new(),
            byte_tokenizer: false,
            rtc_prefix_max: 0,
            delayed_views: Vec::new(),
        })
    }

    /// Checks the invariants the model code relies on.
    pub fn validate(&self) -> Result<(), PolicyError> {
        let mut errs = Vec::new();
        let (p, e) = (&self.paligemma, &self.action_expert);
        if p.depth != e.depth
            || p.num_heads != e.num_heads
            || p.num_kv_heads != e.num_kv_heads
            || p.head_dim != e.head_dim
        {
            errs.push("both experts must share depth, num_heads, num_kv_heads and head_dim".into());
        }
        for (n, g) in [("paligemma", p), ("action_expert", e)] {
            if g.num_kv_heads == 0 || g.num_heads % g.num_kv_heads != 0 {
                errs.push(format!(
                    "{n}: num_heads must be a multiple of num_kv_heads (>0)"
                ));
            }
            if g.head_dim == 0 || g.head_dim % 2 != 0 {
                errs.push(format!("{n}: head_dim must be even and > 0"));
            }
            if g.width == 0 || g.depth == 0 || g.mlp_dim == 0 {
                errs.push(format!("{n}: zero width/depth/mlp_dim"));
            }
        }
        let v = &self.vision;
        if v.num_attention_heads == 0 || !v.hidden_size.is_multiple_of(v.num_attention_heads) {
            errs.push("vision: hidden_size must be a multiple of num_attention_heads".into());
        }
        if v.patch_size == 0 || !v.image_size.is_multiple_of(v.patch_size) {
            errs.push("vision: image_size must be a multiple of patch_size".into());
        }
        if self.action_dim == 0 || self.action_horizon == 0 || self.max_token_len == 0 {
            errs.push("action_dim, action_horizon and max_token_len must be > 0".into());
        }
        if !self.action_expert.width.is_multiple_of(2) {
            errs.push("action expert width must be even (sin/cos time embedding)".into());
        }
        if self.cameras.is_empty() {
            errs.push("at least one camera is required".into());
        }
        // Sane limits, each naming its key: a checkpoint's config.json must not be able to ask
        // for multi-GB allocations (depth 1e9, horizon 1e10) or make pre-processing panic
        // (image_size 0). The bounds are far above openpi's largest models.
        let mut bound = |key: &str, v: usize, lo: usize, hi: usize| {
            if !(lo..=hi).contains(&v) {
                errs.push(format!("{key} = {v} is outside {lo}..={hi}"));
            }
        };
        bound("vision.hidden_size", v.hidden_size, 1, 8192);
        bound("vision.num_hidden_layers", v.num_hidden_layers, 1, 128);
        bound("vision.num_attention_heads", v.num_attention_heads, 1, 128);
        bound("vision.intermediate_size", v.intermediate_size, 1, 65_536);
        bound("vision.patch_size", v.patch_size, 1, 64);
        bound("vision.image_size", v.image_size, v.patch_size.max(1), 1024);
        for (n, g) in [("paligemma", p), ("action_expert", e)] {
            bound(&format!("{n}.width"), g.width, 1, 16_384);
            bound(&format!("{n}.depth"), g.depth, 1, 128);
            bound(&format!("{n}.mlp_dim"), g.mlp_dim, 1, 131_072);
            bound(&format!("{n}.num_heads"), g.num_heads, 1, 256);
            bound(&format!("{n}.num_kv_heads"), g.num_kv_heads, 1, 256);
            bound(&format!("{n}.head_dim"), g.head_dim, 2, 1024);
        }
        bound("vocab_size", self.vocab_size, 1, 1 << 20);
        bound("action_dim", self.action_dim, 1, 1024);
        bound("action_horizon", self.action_horizon, 1, 1000);
        bound("max_token_len", self.max_token_len, 1, 8192);
        bound("num_denoise_steps", self.num_denoise_steps, 1, 1000);
        bound("cameras", self.cameras.len(), 1, 16);
        for (key, x) in [
            ("rms_norm_eps", self.rms_norm_eps),
            ("rope_theta", self.rope_theta),
            ("time_min_period", self.time_min_period),
            ("time_max_period", self.time_max_period),
        ] {
            if !(x.is_finite() && x > 0.0) {
                errs.push(format!("{key} = {x} must be finite and > 0"));
            }
        }
        if self.time_min_period >= self.time_max_period {
            errs.push("time_min_period must be below time_max_period".into());
        }
        if self.delta_action_mask.len() > self.action_dim {
            errs.push(format!(
                "delta_action_mask has {} entries, more than action_dim {}",
                self.delta_action_mask.len(),
                self.action_dim
            ));
        }
        if self.rtc_prefix_max >= self.action_horizon {
            errs.push(format!(
                "rtc_prefix_max = {} must be below action_horizon {} (a committed prefix leaves \
                 at least one action to generate)",
                self.rtc_prefix_max, self.action_horizon
            ));
        }
        for v in &self.delayed_views {
            if !self.cameras.contains(&v.name) {
                errs.push(format!(
                    "delayed view {:?} is not one of the cameras {:?}",
                    v.name, self.cameras
                ));
            }
            if v.camera == v.name
                || !self.cameras.contains(&v.camera)
                || self.delayed_views.iter().any(|w| w.name == v.camera)
            {
                errs.push(format!(
                    "delayed view {:?}: its camera {:?} must be another, live one of the cameras",
                    v.name, v.camera
                ));
            }
            if !(v.delay_ms.is_finite() && v.delay_ms > 0.0 && v.delay_ms <= 10_000.0) {
                errs.push(format!(
                    "delayed view {:?}: delay_ms = {} must be in (0, 10000]",
                    v.name, v.delay_ms
                ));
            }
            if self
                .delayed_views
                .iter()
                .filter(|w| w.name == v.name)
                .count()
                > 1
            {
                errs.push(format!("delayed view {:?} is listed twice", v.name));
            }
        }
        if errs.is_empty() {
            Ok(())
        } else {
            Err(PolicyError::Config(errs.join("; ")))
        }
    }

    /// The delayed view named `camera`, if that image input is one.
    pub fn delayed_view(&self, camera: &str) -> Option<&DelayedView> {
        self.delayed_views.iter().find(|v| v.name == camera)
    }

    /// Prefix length `P = cameras * tokens_per_camera + max_token_len`.
    pub fn prefix_len(&self) -> usize {
        self.cameras.len() * self.vision.num_tokens() + self.max_token_len
    }

    /// Suffix length `S` (π0: state + H actions, π0.5: H actions).
    pub fn suffix_len(&self) -> usize {
        self.action_horizon + self.state_tokens()
    }

    /// 1 for π0 (the state token), 0 for π0.5.
    pub fn state_tokens(&self) -> usize {
        match self.kind {
            ModelKind::Pi0 => 1,
            ModelKind::Pi05 => 0,
        }
    }
}

/// Overrides applied on top of a preset or a `config.json`: a robot configuration's
/// `[policy.model]` deserializes into it (for real openpi / LeRobot checkpoints that ship no
/// `config.json`, whose dimensions come from the preset of the detected kind).
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct ConfigOverrides {
    /// Actions per chunk the checkpoint was trained with.
    #[serde(default)]
    pub action_horizon: Option<usize>,
    /// Padded action dimension.
    #[serde(default)]
    pub action_dim: Option<usize>,
    /// Prompt length in tokens.
    #[serde(default)]
    pub max_token_len: Option<usize>,
    /// Image keys in the model's order (configured cameras are matched by name).
    #[serde(default)]
    pub cameras: Option<Vec<String>>,
    /// Denoising steps (from `policy.num_steps`, not `[policy.model]`).
    #[serde(skip)]
    pub num_denoise_steps: Option<usize>,
    /// Joints whose actions the checkpoint predicts relative to the observed state (openpi's
    /// `DeltaActions`), in robot joint order; the rest are absolute.
    #[serde(default)]
    pub delta_action_mask: Option<Vec<bool>>,
}

impl ConfigOverrides {
    /// Applies the overrides and re-validates.
    pub fn apply(&self, cfg: &mut ModelConfig) -> Result<(), PolicyError> {
        if let Some(v) = self.action_horizon {
            cfg.action_horizon = v;
        }
        if let Some(v) = self.action_dim {
            cfg.action_dim = v;
        }
        if let Some(v) = self.max_token_len {
            cfg.max_token_len = v;
        }
        if let Some(v) = &self.cameras {
            cfg.cameras = v.clone();
        }
        if let Some(v) = self.num_denoise_steps {
            cfg.num_denoise_steps = v;
        }
        if let Some(v) = &self.delta_action_mask {
            cfg.delta_action_mask = v.clone();
        }
        cfg.validate()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn with_view(name: &str, camera: &str, delay_ms: f64) -> Result<ModelConfig, PolicyError> {
        let mut cfg = ModelConfig::preset("pi05")?;
        cfg.cameras = vec!["base_0_rgb".into(), "base_0_rgb_prev".into()];
        cfg.delayed_views = vec![DelayedView {
            name: name.into(),
            camera: camera.into(),
            delay_ms,
        }];
        cfg.validate().map(|()| cfg)
    }

    #[test]
    fn a_delayed_view_must_name_an_image_input_and_another_live_camera() {
        let cfg = with_view("base_0_rgb_prev", "base_0_rgb", 400.0).unwrap();
        assert_eq!(
            cfg.delayed_view("base_0_rgb_prev").unwrap().delay_ns(),
            400_000_000
        );
        assert!(cfg.delayed_view("base_0_rgb").is_none());
        for (name, camera, delay, says) in [
            (
                "wrist_prev",
                "base_0_rgb",
                400.0,
                "is not one of the cameras",
            ),
            ("base_0_rgb_prev", "wrist", 400.0, "another, live one"),
            (
                "base_0_rgb_prev",
                "base_0_rgb_prev",
                400.0,
                "another, live one",
            ),
            (
                "base_0_rgb_prev",
                "base_0_rgb",
                0.0,
                "must be in (0, 10000]",
            ),
            (
                "base_0_rgb_prev",
                "base_0_rgb",
                f64::NAN,
                "must be in (0, 10000]",
            ),
        ] {
            let e = with_view(name, camera, delay).expect_err(name).to_string();
            assert!(e.contains(says), "{name} {camera} {delay}: {e}");
        }
    }
}
