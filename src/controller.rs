//! The controller process (`chunkrt run`).

use std::path::PathBuf;

/// `chunkrt run`.
#[derive(Debug, clap::Args)]
pub struct RunArgs {
    /// Configuration file (TOML). Default: the embedded demo robot.
    #[arg(long)]
    pub config: Option<PathBuf>,
}

pub fn run(_args: RunArgs) -> anyhow::Result<()> {
    anyhow::bail!("not implemented yet")
}
