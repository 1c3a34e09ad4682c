//! `cargo bench --bench ipc_latency [-- --quick]`: iceoryx2 publish → receive latency between
//! processes vs openpi's websocket + msgpack-numpy. See `chunkrt_bench::ipc_latency`.
//!
//! The receiving process is this binary again, started with `--peer`.

mod common;

use chunkrt_bench::ipc_latency::{self, Options, PeerCommand};
use chunkrt_bench::BenchError;

fn main() {
    iceoryx2::prelude::set_log_level(iceoryx2::prelude::LogLevel::Error);
    let args: Vec<String> = std::env::args().skip(1).collect();
    if args.first().map(String::as_str) == Some("--peer") {
        if let Err(e) = ipc_latency::peer_from_args(args.into_iter().skip(1)) {
            eprintln!("ipc_latency peer: {e}");
            std::process::exit(1);
        }
        return;
    }
    common::main("ipc_latency", |opts| {
        let program = std::env::current_exe().map_err(|e| BenchError::Process {
            what: "current_exe".into(),
            reason: e.to_string(),
        })?;
        let peer = PeerCommand {
            program,
            args: vec!["--peer".into()],
        };
        ipc_latency::run(&Options::new(opts, peer)).map(|_| ())
    });
}
