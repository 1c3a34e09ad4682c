//! Checkpoint layouts: where a checkpoint directory keeps its configuration, tokenizer and
//! normalisation statistics. Three are read as they are shipped:
//!
//! - **chunkrt's** (what `chunkrt train` writes and the fixtures use): `config.json` in
//!   chunkrt's schema, `tokenizer.json`, `norm_stats.json`.
//! - **openpi's**, converted to PyTorch by openpi's `convert_jax_model_to_pytorch.py`:
//!   `config.json` with `paligemma_variant`, `action_expert_variant`, `action_dim`,
//!   `action_horizon`; the statistics under `assets/<asset_id>/norm_stats.json`; the PaliGemma
//!   SentencePiece model (`paligemma_tokenizer.model`), which openpi downloads separately and
//!   keeps in `~/.cache/openpi/big_vision/`.
//! - **LeRobot's** `pi0` / `pi05`: `config.json` in LeRobot's schema (`type`, `chunk_size`,
//!   `max_action_dim`, `max_state_dim`, `tokenizer_max_length`, …), the statistics in the
//!   normaliser steps of `policy_preprocessor.json` / `policy_postprocessor.json` (their
//!   safetensors state files), and the Hugging Face PaliGemma `tokenizer.json`.
//!
//! The model's dimensions come from the layout's variant names (`gemma_2b`, `gemma_300m`: the
//! real checkpoints' presets), or, for a model those names do not describe (a small test model),
//! from a `chunkrt.json` beside them in chunkrt's schema; the layout's own values (horizon,
//! action dimension, prompt length) then apply on top. [`Layout::report`] says what was taken
//! from where and what is missing (`chunkrt inspect`).

use std::collections::HashMap;
use std::path::{Path, PathBuf};

use serde::de::{Deserializer, IgnoredAny, MapAccess, Visitor};
use serde::Deserialize;

use crate::config::{detect_kind, ModelConfig, ModelKind};
use crate::error::PolicyError;
use crate::files::read_side_file;
use crate::openpi_config::OpenpiConfig as TrainingConfig;
use crate::preprocess::{NormStats, PromptStyle, Stats};

/// Which layout a checkpoint directory has.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum LayoutKind {
    /// chunkrt's own.
    Chunkrt,
    /// openpi's, converted to PyTorch.
    Openpi,
    /// LeRobot's `pi0` / `pi05`.
    LeRobot,
}

impl LayoutKind {
    /// The name `inspect` prints.
    pub fn name(self) -> &'static str {
        match self {
            LayoutKind::Chunkrt => "chunkrt",
            LayoutKind::Openpi => "openpi (converted to PyTorch)",
            LayoutKind::LeRobot => "LeRobot",
        }
    }
}

/// Choices a layout may need from the user.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct LayoutOptions {
    /// The tokenizer file (`tokenizer.json`, or a SentencePiece `.model`) when it is not in the
    /// checkpoint directory.
    pub tokenizer: Option<PathBuf>,
    /// openpi: which `assets/<asset_id>/norm_stats.json` (needed when there are several).
    pub asset_id: Option<String>,
    /// openpi's training config whose transforms wrap the model (`pi05_libero`, ...;
    /// [`crate::openpi_config`]). `None`: recognised from an openpi checkpoint's folder name
    /// or assets where it can be, else none.
    pub openpi_config: Option<String>,
}

/// The tokenizer a layout uses.
#[derive(Debug, Clone, PartialEq)]
pub enum TokenizerFile {
    /// A Hugging Face `tokenizer.json`.
    Json(PathBuf),
    /// A SentencePiece `.model`.
    SentencePiece(PathBuf),
    /// The fixtures' byte stand-in (declared in chunkrt's `config.json`).
    ByteStandIn,
    /// None found; the message says where it was looked for and what to do.
    Missing(String),
}

/// A checkpoint directory read for its layout.
#[derive(Debug, Clone)]
pub struct Layout {
    /// Which layout.
    pub kind: LayoutKind,
    /// The model's configuration (before the user's overrides).
    pub config: ModelConfig,
    /// The prompt tokenizer.
    pub tokenizer: TokenizerFile,
    /// Normalisation statistics, if the checkpoint has them.
    pub norm: Option<NormStats>,
    /// π0.5: the state is padded to this many values before it is discretised into the prompt
    /// (LeRobot pads to `max_state_dim`; openpi discretises the robot's values only).
    pub state_prompt_dim: Option<usize>,
    /// What was taken from where (one line each).
    pub notes: Vec<String>,
    /// What is missing and what that means (one line each).
    pub missing: Vec<String>,
    /// A choice the statistics need before the policy can load (several openpi asset ids).
    pub norm_problem: Option<String>,
    /// How π0 prompts are built (LeRobot's pi0 differs from openpi's).
    pub prompt_style: PromptStyle,
    /// openpi's training config whose transforms wrap the model, and how it was chosen.
    pub openpi: Option<(&'static TrainingConfig, String)>,
}

/// The variant names of the real checkpoints (openpi's `gemma_2b` / `gemma_300m`, LoRA or not).
fn check_variants(paligemma: Option<&str>, expert: Option<&str>) -> Result<(), String> {
    let ok = |v: Option<&str>, want: &str| {
        v.is_none_or(|v| v == want || v.strip_suffix("_lora") == Some(want))
    };
    if ok(paligemma, "gemma_2b") && ok(expert, "gemma_300m") {
        Ok(())
    } else {
        Err(format!(
            "variants {} / {} are not the real checkpoints' gemma_2b / gemma_300m: put a \
             chunkrt.json (chunkrt's config.json schema) beside them with the model's dimensions",
            paligemma.unwrap_or("?"),
            expert.unwrap_or("?")
        ))
    }
}

/// The keys of a JSON object in document order (serde_json's map is sorted).
struct OrderedKeys(Vec<String>);

impl<'de> Deserialize<'de> for OrderedKeys {
    fn deserialize<D: Deserializer<'de>>(d: D) -> Result<Self, D::Error> {
        struct V;
        impl<'de> Visitor<'de> for V {
            type Value = OrderedKeys;
            fn expecting(&self, f: &mut std::fmt::Formatter) -> std::fmt::Result {
                f.write_str("an object")
            }
            fn visit_map<A: MapAccess<'de>>(self, mut m: A) -> Result<OrderedKeys, A::Error> {
                let mut keys = Vec::new();
                while let Some((k, _)) = m.next_entry::<String, IgnoredAny>()? {
                    keys.push(k);
                }
                Ok(OrderedKeys(keys))
            }
        }
        d.deserialize_map(V)
    }
}

/// The fields of openpi's converted `config.json`.
#[derive(Deserialize)]
struct OpenpiConfig {
    action_dim: Option<usize>,
    action_horizon: Option<usize>,
    paligemma_variant: Option<String>,
    action_expert_variant: Option<String>,
}

/// The fields of LeRobot's `pi0` / `pi05` `config.json` that chunkrt uses.
#[derive(Deserialize)]
struct LeRobotConfig {
    #[serde(rename = "type")]
    kind: String,
    chunk_size: Option<usize>,
    n_action_steps: Option<usize>,
    max_state_dim: Option<usize>,
    max_action_dim: Option<usize>,
    tokenizer_max_length: Option<usize>,
    num_inference_steps: Option<usize>,
    paligemma_variant: Option<String>,
    action_expert_variant: Option<String>,
    input_features: Option<OrderedKeys>,
}

/// One step of a LeRobot processor pipeline file.
#[derive(Deserialize)]
struct LeRobotStep {
    registry_name: Option<String>,
    state_file: Option<String>,
    #[serde(default)]
    config: serde_json::Value,
}

/// The registry name of LeRobot's pi05 state-into-prompt step, and the `max_state_dim` it pads
/// to when its saved configuration does not say (LeRobot 0.4 saves it as `{}`: the step's
/// default is what runs).
const LEROBOT_PI05_PROMPT_STEP: &str = "pi05_prepare_state_tokenizer_processor_step";
const LEROBOT_PI05_PROMPT_STEP_DEFAULT_DIM: usize = 32;

#[derive(Deserialize)]
struct LeRobotPipeline {
    steps: Vec<LeRobotStep>,
}

impl LeRobotPipeline {
    /// `dir/name` if it exists (read once, used for the prompt step and the statistics).
    fn read(dir: &Path, name: &str) -> Result<Option<(PathBuf, Self)>, PolicyError> {
        let p = dir.join(name);
        if !p.exists() {
            return Ok(None);
        }
        let pl = serde_json::from_str(&read_side_file(&p)?).map_err(|e| config_err(&p, e))?;
        Ok(Some((p, pl)))
    }

    /// The step registered as `name`.
    fn step(&self, name: &str) -> Option<&LeRobotStep> {
        self.steps
            .iter()
            .find(|s| s.registry_name.as_deref() == Some(name))
    }
}

fn config_err(path: &Path, e: impl std::fmt::Display) -> PolicyError {
    PolicyError::Config(format!("{}: {e}", path.display()))
}

/// Where openpi keeps the downloaded PaliGemma tokenizer (`$OPENPI_DATA_HOME`, default
/// `~/.cache/openpi`, then the bucket path of `gs://big_vision/paligemma_tokenizer.model`).
fn openpi_cached_tokenizer() -> Option<PathBuf> {
    let home = std::env::var_os("OPENPI_DATA_HOME")
        .map(PathBuf::from)
        .or_else(|| std::env::var_os("HOME").map(|h| PathBuf::from(h).join(".cache/openpi")))?;
    Some(home.join("big_vision/paligemma_tokenizer.model"))
}

impl Layout {
    /// Reads `dir` (its weights' `tensors` already indexed) for its layout.
    pub fn read(
        dir: &Path,
        tensors: &HashMap<String, Vec<usize>>,
        opts: &LayoutOptions,
    ) -> Result<Self, PolicyError> {
        let cfg_path = dir.join("config.json");
        let raw = if cfg_path.exists() {
            Some(read_side_file(&cfg_path)?)
        } else {
            None
        };
        let value: Option<serde_json::Value> = match &raw {
            Some(s) => Some(serde_json::from_str(s).map_err(|e| config_err(&cfg_path, e))?),
            None => None,
        };
        let has = |k: &str| value.as_ref().is_some_and(|v| v.get(k).is_some());
        let kind = if has("type") || dir.join("policy_preprocessor.json").exists() {
            LayoutKind::LeRobot
        } else if has("paligemma_variant")
            || (!has("paligemma") && !has("model_kind") && dir.join("assets").is_dir())
        {
            LayoutKind::Openpi
        } else {
            LayoutKind::Chunkrt
        };
        let mut me = Layout {
            kind,
            config: ModelConfig::preset("pi0")?,
            tokenizer: TokenizerFile::ByteStandIn,
            norm: None,
            state_prompt_dim: None,
            notes: Vec::new(),
            missing: Vec::new(),
            norm_problem: None,
            prompt_style: PromptStyle::Openpi,
            openpi: None,
        };
        match kind {
            LayoutKind::Chunkrt => me.read_chunkrt(dir, tensors, raw.as_deref())?,
            LayoutKind::Openpi => me.read_openpi(dir, tensors, raw.as_deref(), opts)?,
            LayoutKind::LeRobot => me.read_lerobot(dir, tensors, raw.as_deref())?,
        }
        me.apply_openpi_config(dir, opts)?;
        me.find_tokenizer(dir, opts);
        Ok(me)
    }

    /// openpi's training config ([`crate::openpi_config`]): named, or recognised from an openpi
    /// checkpoint. It sets the horizon, the prompt length, the delta dims and the statistics'
    /// asset id as the config does, and checks the statistics' widths against its robot.
    fn apply_openpi_config(&mut self, dir: &Path, opts: &LayoutOptions) -> Result<(), PolicyError> {
        let chosen = match &opts.openpi_config {
            Some(n) => Some((
                crate::openpi_config::by_name(n)?,
                "named (--openpi-config / policy.openpi_config)".to_string(),
            )),
            None if self.kind == LayoutKind::Openpi => {
                crate::openpi_config::recognise(dir, self.config.kind)
            }
            None => None,
        };
        let Some((c, how)) = chosen else {
            return Ok(());
        };
        if c.kind != self.config.kind {
            return Err(PolicyError::Config(format!(
                "openpi config {} is a {} config, but {} holds a {} model",
                c.name,
                c.kind.name(),
                dir.display(),
                self.config.kind.name()
            )));
        }
        if self.kind == LayoutKind::Openpi && opts.asset_id.is_none() {
            let p = dir.join("assets").join(c.asset_id).join("norm_stats.json");
            if p.is_file() {
                self.norm = Some(NormStats::from_file(&p)?);
                self.norm_problem = None;
                self.missing
                    .retain(|m| !m.contains("norm stats") && !m.contains("norm_stats.json"));
                self.notes.retain(|n| !n.starts_with("normalisation:"));
                self.notes.push(format!(
                    "normalisation: assets/{}/norm_stats.json (the config's asset id)",
                    c.asset_id
                ));
            }
        }
        if let Some(ns) = &self.norm {
            c.check_stats(ns, self.config.action_dim)?;
        }
        if self.config.action_horizon != c.action_horizon {
            self.notes.push(format!(
                "action_horizon {} (the config's; the checkpoint said {})",
                c.action_horizon, self.config.action_horizon
            ));
        }
        self.config.action_horizon = c.action_horizon;
        self.config.max_token_len = c.max_token_len;
        self.config.delta_action_mask = c.delta_mask.to_vec();
        self.notes.push(format!(
            "openpi config {} ({how}): {} transforms, {} state values in, {} action columns out, \
             delta dims {}, state in the prompt: {}, default prompt {}",
            c.name,
            c.robot.layout(),
            c.robot.state_dim(),
            c.robot.action_dim(),
            if c.delta_mask.is_empty() {
                "none".to_string()
            } else {
                format!(
                    "{:?}",
                    c.delta_mask.iter().map(|&m| m as u8).collect::<Vec<_>>()
                )
            },
            c.kind == ModelKind::Pi05 && c.discrete_state_input,
            c.default_prompt
                .map_or("none".to_string(), |p| format!("{p:?}")),
        ));
        self.openpi = Some((c, how));
        Ok(())
    }

    /// The base dimensions of a foreign layout: `chunkrt.json` if present, else the preset of
    /// `kind` (the real checkpoints' dimensions) after checking the variant names.
    fn base_config(
        &mut self,
        dir: &Path,
        kind: ModelKind,
        variants: (Option<&str>, Option<&str>),
        source: &str,
    ) -> Result<ModelConfig, PolicyError> {
        let arch = dir.join("chunkrt.json");
        if arch.exists() {
            let cfg = ModelConfig::from_file(&arch)?;
            if cfg.kind != kind {
                return Err(config_err(
                    &arch,
                    format!(
                        "says {} but the checkpoint is {}",
                        cfg.kind.name(),
                        kind.name()
                    ),
                ));
            }
            self.notes
                .push("model dimensions: chunkrt.json (beside the layout's files)".into());
            Ok(cfg)
        } else {
            check_variants(variants.0, variants.1)
                .map_err(|e| config_err(&dir.join("config.json"), e))?;
            self.notes.push(format!(
                "model dimensions: the {} preset (gemma_2b + gemma_300m, SigLIP So400m/14 at \
                 224), as {source} names them",
                kind.name()
            ));
            ModelConfig::preset(kind.name())
        }
    }

    fn read_chunkrt(
        &mut self,
        dir: &Path,
        tensors: &HashMap<String, Vec<usize>>,
        raw: Option<&str>,
    ) -> Result<(), PolicyError> {
        let cfg_path = dir.join("config.json");
        self.config = match raw {
            Some(s) => {
                let c = ModelConfig::from_json_str(s).map_err(|e| config_err(&cfg_path, e))?;
                self.notes
                    .push("model configuration: config.json (chunkrt's schema)".into());
                c
            }
            None => {
                let kind = detect_kind(tensors).ok_or_else(|| {
                    PolicyError::Checkpoint(
                        "no config.json and neither state_proj (pi0) nor time_mlp_in (pi05) \
                         found"
                            .into(),
                    )
                })?;
                self.notes.push(format!(
                    "model configuration: no config.json, the {} preset (detected from the \
                     weights)",
                    kind.name()
                ));
                ModelConfig::preset(kind.name())?
            }
        };
        let ns = dir.join("norm_stats.json");
        if ns.exists() {
            self.norm = Some(NormStats::from_file(&ns)?);
            self.notes.push("normalisation: norm_stats.json".into());
        } else {
            self.missing
                .push("norm_stats.json: state and actions are not normalised".into());
        }
        Ok(())
    }

    fn read_openpi(
        &mut self,
        dir: &Path,
        tensors: &HashMap<String, Vec<usize>>,
        raw: Option<&str>,
        opts: &LayoutOptions,
    ) -> Result<(), PolicyError> {
        let cfg_path = dir.join("config.json");
        let oc: OpenpiConfig = match raw {
            Some(s) => serde_json::from_str(s).map_err(|e| config_err(&cfg_path, e))?,
            None => OpenpiConfig {
                action_dim: None,
                action_horizon: None,
                paligemma_variant: None,
                action_expert_variant: None,
            },
        };
        let kind = detect_kind(tensors).ok_or_else(|| {
            PolicyError::Checkpoint(
                "openpi layout, but neither state_proj (pi0) nor time_mlp_in (pi05) is in \
                 model.safetensors"
                    .into(),
            )
        })?;
        self.notes.push(format!(
            "kind: {} (openpi's config.json does not say; detected from the weights)",
            kind.name()
        ));
        let mut cfg = self.base_config(
            dir,
            kind,
            (
                oc.paligemma_variant.as_deref(),
                oc.action_expert_variant.as_deref(),
            ),
            "openpi's config.json",
        )?;
        if let Some(v) = oc.action_dim {
            cfg.action_dim = v;
        }
        if let Some(v) = oc.action_horizon {
            cfg.action_horizon = v;
        }
        self.notes.push(format!(
            "action_dim {}, action_horizon {}: openpi's config.json; max_token_len {}: openpi's \
             default for {}",
            cfg.action_dim,
            cfg.action_horizon,
            cfg.max_token_len,
            kind.name()
        ));
        self.config = cfg;
        // the statistics: assets/<asset_id>/norm_stats.json
        let assets = dir.join("assets");
        // asset ids one or two folders deep (`droid`, `physical-intelligence/libero`)
        let mut found: Vec<String> = Vec::new();
        let names = |p: &Path| -> Vec<String> {
            std::fs::read_dir(p)
                .map(|rd| {
                    rd.filter_map(|e| e.ok())
                        .filter(|e| e.path().is_dir())
                        .filter_map(|e| e.file_name().to_str().map(str::to_string))
                        .collect()
                })
                .unwrap_or_default()
        };
        for a in names(&assets) {
            if assets.join(&a).join("norm_stats.json").is_file() {
                found.push(a);
                continue;
            }
            for b in names(&assets.join(&a)) {
                if assets.join(&a).join(&b).join("norm_stats.json").is_file() {
                    found.push(format!("{a}/{b}"));
                }
            }
        }
        found.sort();
        let id = match (&opts.asset_id, found.as_slice()) {
            (Some(id), _) => Some(id.clone()),
            (None, [one]) => Some(one.clone()),
            (None, []) => None,
            (None, many) => {
                let msg = format!(
                    "{}: norm stats for several robots ({}): choose one with --asset-id (or \
                     policy.asset_id)",
                    assets.display(),
                    many.join(", ")
                );
                self.missing.push(msg.clone());
                self.norm_problem = Some(msg);
                None
            }
        };
        match id {
            _ if self.norm_problem.is_some() => {}
            Some(id) => {
                let p = assets.join(&id).join("norm_stats.json");
                if !p.is_file() {
                    return Err(PolicyError::Config(format!(
                        "{}: no such file (asset ids here: {})",
                        p.display(),
                        if found.is_empty() {
                            "none".to_string()
                        } else {
                            found.join(", ")
                        }
                    )));
                }
                self.norm = Some(NormStats::from_file(&p)?);
                self.notes
                    .push(format!("normalisation: assets/{id}/norm_stats.json"));
            }
            None => self.missing.push(
                "assets/<asset_id>/norm_stats.json: state and actions are not normalised \
                 (openpi's converter copies the training assets; copy them from the JAX \
                 checkpoint's assets/)"
                    .into(),
            ),
        }
        Ok(())
    }

    fn read_lerobot(
        &mut self,
        dir: &Path,
        tensors: &HashMap<String, Vec<usize>>,
        raw: Option<&str>,
    ) -> Result<(), PolicyError> {
        let cfg_path = dir.join("config.json");
        let raw = raw.ok_or_else(|| {
            PolicyError::Config(format!(
                "{}: missing (LeRobot's policy configuration)",
                cfg_path.display()
            ))
        })?;
        let lc: LeRobotConfig = serde_json::from_str(raw).map_err(|e| config_err(&cfg_path, e))?;
        let pre = LeRobotPipeline::read(dir, "policy_preprocessor.json")?;
        let kind = match lc.kind.as_str() {
            "pi0" => ModelKind::Pi0,
            "pi05" => ModelKind::Pi05,
            other => {
                return Err(config_err(
                    &cfg_path,
                    format!("LeRobot policy type {other:?}; chunkrt runs pi0 and pi05"),
                ))
            }
        };
        if let Some(found) = detect_kind(tensors) {
            if found != kind {
                return Err(config_err(
                    &cfg_path,
                    format!("says {} but the weights are {}", kind.name(), found.name()),
                ));
            }
        }
        let mut cfg = self.base_config(
            dir,
            kind,
            (
                lc.paligemma_variant.as_deref(),
                lc.action_expert_variant.as_deref(),
            ),
            "LeRobot's config.json",
        )?;
        let mut took = Vec::new();
        if let Some(v) = lc.chunk_size {
            cfg.action_horizon = v;
            took.push(format!("action_horizon {v} (chunk_size)"));
        }
        if let Some(v) = lc.max_action_dim {
            cfg.action_dim = v;
            took.push(format!("action_dim {v} (max_action_dim)"));
        }
        if let Some(v) = lc.tokenizer_max_length {
            cfg.max_token_len = v;
            took.push(format!("max_token_len {v} (tokenizer_max_length)"));
        }
        if let Some(v) = lc.num_inference_steps {
            cfg.num_denoise_steps = v;
            took.push(format!(
                "num_inference_steps {v} (chunkrt runs policy.num_steps)"
            ));
        }
        let cameras: Vec<String> = lc
            .input_features
            .map(|k| {
                k.0.iter()
                    .filter_map(|n| n.strip_prefix("observation.images."))
                    .map(str::to_string)
                    .collect()
            })
            .unwrap_or_default();
        if !cameras.is_empty() {
            took.push(format!("cameras {cameras:?} (input_features)"));
            cfg.cameras = cameras;
        }
        if kind == ModelKind::Pi05 {
            // what LeRobot's pre-processor, loaded from its file, pads the state to
            let step = pre
                .as_ref()
                .and_then(|(_, pl)| pl.step(LEROBOT_PI05_PROMPT_STEP));
            let (n, from) = match step {
                Some(s) => match s.config.get("max_state_dim").and_then(|v| v.as_u64()) {
                    Some(n) => (n as usize, "its pre-processor's prompt step".to_string()),
                    None => (
                        LEROBOT_PI05_PROMPT_STEP_DEFAULT_DIM,
                        "the default of its pre-processor's prompt step, whose saved \
                         configuration is empty"
                            .to_string(),
                    ),
                },
                None => (
                    lc.max_state_dim
                        .unwrap_or(LEROBOT_PI05_PROMPT_STEP_DEFAULT_DIM),
                    "max_state_dim".to_string(),
                ),
            };
            if n > 1024 {
                return Err(config_err(&cfg_path, format!("max_state_dim {n}")));
            }
            self.state_prompt_dim = Some(n);
            took.push(format!(
                "the state padded to {n} values in the prompt ({from}, as LeRobot does)"
            ));
        }
        if kind == ModelKind::Pi0 {
            self.prompt_style = PromptStyle::LeRobot;
            took.push(
                "the prompt as LeRobot's pi0 builds it (the task with a newline, tokenised whole)"
                    .into(),
            );
        }
        if let Some(n) = lc.n_action_steps {
            took.push(format!(
                "n_action_steps {n} (informational: chunkrt's execution settings decide)"
            ));
        }
        self.notes
            .push(format!("LeRobot's config.json: {}", took.join(", ")));
        cfg.validate()?;
        self.config = cfg;
        let post = LeRobotPipeline::read(dir, "policy_postprocessor.json")?;
        self.read_lerobot_stats(dir, kind, pre, post)
    }

    /// The normaliser's statistics from the pre-processor (state) and the post-processor's
    /// un-normaliser (actions).
    fn read_lerobot_stats(
        &mut self,
        dir: &Path,
        kind: ModelKind,
        pre: Option<(PathBuf, LeRobotPipeline)>,
        post: Option<(PathBuf, LeRobotPipeline)>,
    ) -> Result<(), PolicyError> {
        let state_file = |pipeline: &Option<(PathBuf, LeRobotPipeline)>,
                          step: &str|
         -> Result<Option<PathBuf>, PolicyError> {
            let Some((p, pl)) = pipeline else {
                return Ok(None);
            };
            match pl.step(step).and_then(|s| s.state_file.clone()) {
                // a file name beside the pipeline, nothing else
                Some(f) if !f.contains('/') && !f.contains('\\') && f != ".." => {
                    Ok(Some(dir.join(f)))
                }
                Some(f) => Err(config_err(
                    p,
                    format!("state file {f:?} is not a file name"),
                )),
                None => Ok(None),
            }
        };
        let pre = state_file(&pre, "normalizer_processor")?;
        let post = state_file(&post, "unnormalizer_processor")?;
        let (Some(pre), Some(post)) = (pre, post) else {
            self.missing.push(
                "policy_preprocessor.json / policy_postprocessor.json with their normaliser \
                 steps: state and actions are not normalised"
                    .into(),
            );
            return Ok(());
        };
        let state = lerobot_stats(&pre, "observation.state", kind)?;
        let actions = lerobot_stats(&post, "action", kind)?;
        self.norm = Some(NormStats { state, actions });
        self.notes.push(format!(
            "normalisation: observation.state from {}, action from {}",
            pre.file_name().and_then(|n| n.to_str()).unwrap_or("?"),
            post.file_name().and_then(|n| n.to_str()).unwrap_or("?")
        ));
        Ok(())
    }

    fn find_tokenizer(&mut self, dir: &Path, opts: &LayoutOptions) {
        let by_name = |p: PathBuf| {
            if p.extension().is_some_and(|e| e == "json") {
                TokenizerFile::Json(p)
            } else {
                TokenizerFile::SentencePiece(p)
            }
        };
        let mut tried = Vec::new();
        let found = if let Some(p) = &opts.tokenizer {
            Some(by_name(p.clone()))
        } else {
            let mut candidates = vec![
                dir.join("tokenizer.json"),
                dir.join("paligemma_tokenizer.model"),
                dir.join("tokenizer.model"),
            ];
            if self.kind == LayoutKind::Openpi {
                candidates.extend(openpi_cached_tokenizer());
            }
            // whatever is there (a FIFO or a directory is then a clear error when it is read)
            let hit = candidates.iter().find(|p| p.exists()).cloned();
            tried = candidates;
            hit.map(by_name)
        };
        self.tokenizer = match found {
            Some(t) => {
                self.notes.push(format!(
                    "tokenizer: {}",
                    match &t {
                        TokenizerFile::Json(p) | TokenizerFile::SentencePiece(p) =>
                            p.display().to_string(),
                        _ => String::new(),
                    }
                ));
                t
            }
            None if self.config.byte_tokenizer => {
                self.notes
                    .push("tokenizer: the byte stand-in, as config.json declares".into());
                TokenizerFile::ByteStandIn
            }
            None => {
                let looked: Vec<String> = tried.iter().map(|p| p.display().to_string()).collect();
                let msg = format!(
                    "no tokenizer (looked for {}): give the PaliGemma tokenizer with --tokenizer \
                     (policy.tokenizer): openpi's paligemma_tokenizer.model (gs://big_vision/\
                     paligemma_tokenizer.model) or Hugging Face's tokenizer.json of \
                     google/paligemma-3b-pt-224",
                    looked.join(", ")
                );
                self.missing.push(msg.clone());
                TokenizerFile::Missing(msg)
            }
        };
    }

    /// What `inspect` prints: the layout, what came from where, what is missing.
    pub fn report(&self) -> String {
        let mut s = format!("layout: {}\n", self.kind.name());
        for n in &self.notes {
            s.push_str(&format!("  from: {n}\n"));
        }
        for m in &self.missing {
            s.push_str(&format!("  MISSING: {m}\n"));
        }
        s
    }
}

/// One feature's statistics from a LeRobot normaliser state file (`<feature>.<stat>` tensors).
fn lerobot_stats(path: &Path, feature: &str, kind: ModelKind) -> Result<Stats, PolicyError> {
    let bytes = crate::files::read_bounded(path, crate::files::MAX_SIDE_FILE_BYTES)?;
    let st = safetensors::SafeTensors::deserialize(&bytes).map_err(|e| config_err(path, e))?;
    let get = |stat: &str| -> Result<Option<Vec<f32>>, PolicyError> {
        let name = format!("{feature}.{stat}");
        let Ok(t) = st.tensor(&name) else {
            return Ok(None);
        };
        let v: Vec<f32> = match t.dtype() {
            safetensors::Dtype::F32 => t
                .data()
                .chunks_exact(4)
                .map(|b| f32::from_le_bytes([b[0], b[1], b[2], b[3]]))
                .collect(),
            safetensors::Dtype::F64 => t
                .data()
                .chunks_exact(8)
                .map(|b| {
                    f64::from_le_bytes([b[0], b[1], b[2], b[3], b[4], b[5], b[6], b[7]]) as f32
                })
                .collect(),
            other => {
                return Err(config_err(
                    path,
                    format!("{name} is {other:?}, not a float"),
                ))
            }
        };
        Ok(Some(v))
    };
    let (mean, std, q01, q99) = (get("mean")?, get("std")?, get("q01")?, get("q99")?);
    let need_q = kind == ModelKind::Pi05;
    let missing: Vec<&str> = [
        ("mean", mean.is_none() && !need_q),
        ("std", std.is_none() && !need_q),
        ("q01", q01.is_none() && need_q),
        ("q99", q99.is_none() && need_q),
    ]
    .iter()
    .filter(|(_, m)| *m)
    .map(|(n, _)| *n)
    .collect();
    if !missing.is_empty() {
        return Err(config_err(
            path,
            format!("no {feature}.{} statistics", missing.join(", ")),
        ));
    }
    let len = mean
        .as_ref()
        .or(q01.as_ref())
        .map(Vec::len)
        .unwrap_or_default();
    Ok(Stats {
        mean: mean.unwrap_or_else(|| vec![0.0; len]),
        std: std.unwrap_or_else(|| vec![1.0; len]),
        q01,
        q99,
    })
}
