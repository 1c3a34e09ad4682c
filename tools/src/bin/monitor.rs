use clap::Parser;

#[derive(Debug, Parser)]
#[command(
    version,
    about = "Live rates, latencies and values of chunkrt services"
)]
struct Cli {
    #[command(flatten)]
    args: chunkrt_tools::monitor::Args,
}

fn main() {
    tracing_subscriber::fmt()
        .with_env_filter(
            tracing_subscriber::EnvFilter::try_from_default_env()
                .unwrap_or_else(|_| tracing_subscriber::EnvFilter::new("info")),
        )
        .with_writer(std::io::stderr)
        .init();
    if let Err(e) = chunkrt_tools::monitor::run(Cli::parse().args) {
        eprintln!("monitor: error: {e:#}");
        std::process::exit(1);
    }
}
