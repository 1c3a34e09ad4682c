//! `chunkrt sample` and `chunkrt inspect`.

use std::path::PathBuf;

/// `chunkrt sample`: run the policy on a safetensors file of inputs.
#[derive(Debug, clap::Args)]
pub struct SampleArgs {
    /// Checkpoint directory (config.json + model.safetensors).
    #[arg(long)]
    pub checkpoint: PathBuf,
}

/// `chunkrt inspect`: describe a checkpoint.
#[derive(Debug, clap::Args)]
pub struct InspectArgs {
    /// Checkpoint directory.
    pub dir: PathBuf,
}

pub fn sample(_args: SampleArgs) -> anyhow::Result<()> {
    anyhow::bail!("chunkrt sample: not implemented yet")
}

pub fn inspect(_args: InspectArgs) -> anyhow::Result<()> {
    anyhow::bail!("chunkrt inspect: not implemented yet")
}
