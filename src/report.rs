//! Latency histograms → HdrHistogram interval logs, percentile tables and PNG plots.

use std::path::PathBuf;

/// `chunkrt report DIR`.
#[derive(Debug, clap::Args)]
pub struct ReportArgs {
    /// Folder of HdrHistogram interval logs.
    pub dir: PathBuf,
}

pub fn run(_args: ReportArgs) -> anyhow::Result<()> {
    anyhow::bail!("chunkrt report: not implemented yet")
}
