//! `cargo bench --bench remote [-- --quick]`: a chunk's latency with the policy behind `chunkrt
//! serve` (loopback, netem) against the same policy in process. See `chunkrt_bench::remote`.

mod common;

use chunkrt_bench::remote::{self, Options};

fn main() {
    common::main("remote", |opts| {
        let exe = Some(std::path::PathBuf::from(env!("CARGO_BIN_EXE_chunkrt")));
        remote::run(&Options::new(opts, exe)).map(|_| ())
    });
}
