//! The one `main` of the standalone tool binaries (`fake-camera`, `fake-robot`, `monitor`):
//! parse the tool's clap `Args`, log to stderr (`RUST_LOG`, default `info`), run, and exit 1
//! with the error chain on failure.

use clap::Args;

/// Runs tool `name` (its `about` line for `--help`) with `run`.
pub fn main_of<A: Args>(name: &'static str, about: &'static str, run: fn(A) -> anyhow::Result<()>) {
    // the about line after the args: their doc comment would replace it
    let cmd = A::augment_args(clap::Command::new(name))
        .version(env!("CARGO_PKG_VERSION"))
        .about(about);
    let args = A::from_arg_matches(&cmd.get_matches()).unwrap_or_else(|e| e.exit());
    tracing_subscriber::fmt()
        .with_env_filter(
            tracing_subscriber::EnvFilter::try_from_default_env()
                .unwrap_or_else(|_| tracing_subscriber::EnvFilter::new("info")),
        )
        .with_writer(std::io::stderr)
        .init();
    if let Err(e) = run(args) {
        eprintln!("{name}: error: {e:#}");
        std::process::exit(1);
    }
}
