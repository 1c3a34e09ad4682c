//! The `chunkrt` command: the controller, its demo, and the companion tools.

use clap::{Parser, Subcommand};

/// chunkrt — a real-time controller running a π0 / π0.5 policy next to a robot.
#[derive(Debug, Parser)]
#[command(name = "chunkrt", version, about, long_about = None)]
struct Cli {
    #[command(subcommand)]
    command: Command,
}

#[derive(Debug, Subcommand)]
enum Command {
    /// Run the controller on a configuration file.
    Run(chunkrt::run::RunArgs),
    /// Start fake camera, simulated robot and controller as processes and show them working.
    Demo(chunkrt::demo::DemoArgs),
    /// Run the demo stack for a long time (default 10 min): commands/s, overruns, lateness
    /// p50/p99/max, holds, rejections by reason, RSS and fds at start and end.
    Soak(chunkrt::soak::SoakArgs),
    /// Publish synthetic camera frames (same as the `fake-camera` tool).
    FakeCamera(chunkrt_tools::fake_camera::Args),
    /// Simulate an N-DoF arm (same as the `fake-robot` tool).
    FakeRobot(chunkrt_tools::fake_robot::Args),
    /// Drive a Franka FR3 through FCI as a chunkrt robot (real arm or franka-sim): joint
    /// states out at the robot's 1 kHz, the controller's commands in, every command kept within
    /// the FR3's limits, a jerk-limited stop when the controller stops, stalls or dies.
    Franka(chunkrt_franka::Args),
    /// Any ros2_control robot as a chunkrt robot (`[ros2]` of the configuration): its
    /// `JointState`s in, matched by name; the controller's commands out to a forward command or
    /// joint trajectory controller; status and predicted chunks out for RViz / Foxglove.
    Ros2(chunkrt_ros2::Args),
    /// List chunkrt services with live rate, latency and last values (same as `monitor`).
    Monitor(chunkrt_tools::monitor::Args),
    /// Ask the controller to leave FAULT without a restart; prints its answer (refused, with
    /// the reason, while an input is still bad).
    Rearm(chunkrt_tools::rearm::Args),
    /// Serve a checkpoint over openpi's websocket protocol (any openpi client, or a controller
    /// with `policy.source = "remote"` on another machine).
    Serve(chunkrt::serve::ServeArgs),
    /// Compute an action chunk from a safetensors file of inputs.
    Sample(chunkrt::policy_cli::SampleArgs),
    /// Describe a checkpoint: architecture, parameter counts, dtype, what is missing.
    Inspect(chunkrt::policy_cli::InspectArgs),
    /// Time a random model of a preset on a device (GPU or CPU): vision, prefix, one step, the
    /// full sample eager and as a CUDA graph; p50/p90/p99/max by wall clock and CUDA events.
    BenchInference(chunkrt::policy_cli::BenchArgs),
    /// Record a running namespace (joint states, commands, status, chunks, frames) into a
    /// Rerun recording (`rerun FILE` opens it); needs `bash scripts/rerun-env.sh`.
    Record(chunkrt::record::RecordArgs),
    /// Render a folder of HdrHistogram logs into a PNG plot and a Markdown table.
    Report(chunkrt::report::ReportArgs),
    /// Train the reach task's π0.5 with the flow-matching loss (expert demonstrations,
    /// AdamW, closed-loop validation); writes an openpi-format checkpoint.
    Train(chunkrt_learn::train::TrainArgs),
    /// Closed-loop delay sweep of the chunk strategies (and synchronous execution) on the
    /// reach task: success rate, time to target, switch jumps, jerk.
    Eval(chunkrt_learn::eval::EvalArgs),
}

fn main() {
    let cli = Cli::parse();
    if matches!(cli.command, Command::Ros2(_)) && std::env::var_os("RUST_LOG").is_none() {
        // RustDDS logs every discovery step at info: its warnings only, unless RUST_LOG says
        // otherwise (set before any thread starts)
        std::env::set_var(
            "RUST_LOG",
            "info,rustdds=warn,ros2_client=warn,ros2_client::distributions=error",
        );
    }
    chunkrt_policy::keep_freed_memory();
    chunkrt_controller::rt::init_logging();
    let result = match cli.command {
        Command::Run(a) => chunkrt::run::run(a),
        Command::Demo(a) => chunkrt::demo::run(a),
        Command::Soak(a) => chunkrt::soak::run(a),
        Command::FakeCamera(a) => chunkrt_tools::fake_camera::run(a),
        Command::FakeRobot(a) => chunkrt_tools::fake_robot::run(a),
        Command::Franka(a) => chunkrt_franka::run(a),
        Command::Ros2(a) => chunkrt_ros2::run(a),
        Command::Monitor(a) => chunkrt_tools::monitor::run(a),
        Command::Rearm(a) => chunkrt_tools::rearm::run(a),
        Command::Serve(a) => chunkrt::serve::run(a),
        Command::Sample(a) => chunkrt::policy_cli::sample(a),
        Command::Inspect(a) => chunkrt::policy_cli::inspect(a),
        Command::BenchInference(a) => chunkrt::policy_cli::bench(a),
        // a Rerun recording (`chunkrt record`, `--record`) or a folder of HdrHistogram logs
        Command::Report(a) if a.dir.extension().is_some_and(|e| e == "rrd") => {
            chunkrt::record::report(&a.dir, a.png.as_deref(), a.md.as_deref())
        }
        Command::Report(a) => chunkrt::report::run(a),
        Command::Record(a) => chunkrt::record::run(a),
        Command::Train(a) => chunkrt_learn::train::run(a),
        Command::Eval(a) => chunkrt_learn::eval::run(a),
    };
    if let Err(e) = result {
        eprintln!("chunkrt: error: {e:#}");
        std::process::exit(1);
    }
}
