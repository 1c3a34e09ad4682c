//! fake_camera

/// Command-line arguments.
#[derive(Debug, clap::Args)]
pub struct Args {}

/// Runs until SIGINT / SIGTERM.
pub fn run(_args: Args) -> anyhow::Result<()> {
    anyhow::bail!("not implemented yet")
}
