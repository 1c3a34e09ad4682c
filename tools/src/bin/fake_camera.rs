use clap::Parser;

#[derive(Debug, Parser)]
#[command(version, about = "Publishes synthetic camera frames over iceoryx2")]
struct Cli {
    #[command(flatten)]
    args: chunkrt_tools::fake_camera::Args,
}

fn main() {
    tracing_subscriber::fmt()
        .with_env_filter(
            tracing_subscriber::EnvFilter::try_from_default_env()
                .unwrap_or_else(|_| tracing_subscriber::EnvFilter::new("info")),
        )
        .with_writer(std::io::stderr)
        .init();
    if let Err(e) = chunkrt_tools::fake_camera::run(Cli::parse().args) {
        eprintln!("fake_camera: error: {e:#}");
        std::process::exit(1);
    }
}
