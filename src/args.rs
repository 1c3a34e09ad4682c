//! What the commands share, below all of them: the checkpoint-file flags (`LayoutArgs`: `run`,
//! `serve`, `sample`, `inspect`) and loading the configuration a command names.

use std::path::PathBuf;

use anyhow::Context;

use chunkrt_controller::config::Config;

/// A tool's own virtual environment (the FR3 simulator's, the recorder's): its prefix
/// (`$prefix_var`, else `~/.cache/<default_dir>`) and its interpreter (`$python_var`, else
/// `<prefix>/venv/bin/python`).
pub fn venv_python(prefix_var: &str, default_dir: &str, python_var: &str) -> (PathBuf, PathBuf) {
    let prefix = std::env::var(prefix_var)
        .map(PathBuf::from)
        .unwrap_or_else(|_| {
            PathBuf::from(std::env::var("HOME").unwrap_or_default())
                .join(".cache")
                .join(default_dir)
        });
    let py = std::env::var(python_var)
        .map(PathBuf::from)
        .unwrap_or_else(|_| prefix.join("venv/bin/python"));
    (prefix, py)
}

/// Where a checkpoint's tokenizer and statistics are when its directory does not say
/// (`chunkrt run`, `serve`, `sample`, `inspect`).
#[derive(Debug, Clone, Default, clap::Args)]
pub struct LayoutArgs {
    /// The prompt tokenizer when the checkpoint directory has none: openpi's
    /// `paligemma_tokenizer.model` (SentencePiece; openpi keeps it in
    /// ~/.cache/openpi/big_vision/, where it is also looked for) or a Hugging Face
    /// `tokenizer.json` (google/paligemma-3b-pt-224's, as LeRobot uses).
    #[arg(long, value_name = "FILE")]
    pub tokenizer: Option<PathBuf>,
    /// openpi checkpoints: which `assets/<ID>/norm_stats.json` to use when there are several
    /// (one per robot the model was trained on).
    #[arg(long, value_name = "ID")]
    pub asset_id: Option<String>,
    /// openpi's training config whose transforms wrap the model, as openpi's server applies
    /// them: pi0_aloha_towel, pi0_aloha_tupperware, pi0_aloha_pen_uncap, pi05_aloha_pen_uncap,
    /// pi0_aloha_sim, pi0_libero, pi05_libero, pi0_droid, pi05_droid (default: recognised from
    /// an openpi checkpoint's folder name or assets).
    #[arg(long, value_name = "NAME")]
    pub openpi_config: Option<String>,
}

impl LayoutArgs {
    /// Sets `policy.tokenizer` (made absolute: a path on the command line is relative to the
    /// current directory, not to the configuration) and `policy.asset_id`.
    pub fn apply(&self, p: &mut chunkrt_controller::config::PolicyConfig) -> anyhow::Result<()> {
        if let Some(t) = &self.tokenizer {
            p.tokenizer = Some(
                std::path::absolute(t).with_context(|| format!("--tokenizer {}", t.display()))?,
            );
        }
        if let Some(id) = &self.asset_id {
            p.asset_id = Some(id.clone());
        }
        if let Some(c) = &self.openpi_config {
            p.openpi_config = Some(c.clone());
        }
        Ok(())
    }

    /// The policy crate's layout options.
    pub fn options(&self) -> chunkrt_policy::layout::LayoutOptions {
        chunkrt_policy::layout::LayoutOptions {
            tokenizer: self.tokenizer.clone(),
            asset_id: self.asset_id.clone(),
            openpi_config: self.openpi_config.clone(),
        }
    }
}

/// Loads the configuration named by `--config` (or the embedded default) and applies
/// `--namespace`.
pub fn load_config(config: Option<&PathBuf>, namespace: Option<&str>) -> anyhow::Result<Config> {
    let mut cfg = match config {
        Some(p) => Config::load(p)?,
        None => Config::embedded_default(),
    };
    if let Some(ns) = namespace {
        cfg.robot.namespace = ns.to_string();
        let file = cfg.source.display().to_string();
        cfg.validate(&format!("{file} (with --namespace)"))?;
    }
    Ok(cfg)
}
