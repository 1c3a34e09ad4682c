//! `cargo bench --bench remote [-- --quick]`: a chunk's latency with the policy behind `chunkrt
//! serve` (loopback, an emulated LAN) against the same policy in process. See `measure.rs`.

#[path = "../common/mod.rs"]
mod common;
mod measure;

fn main() {
    common::main("remote", |opts| {
        let exe = Some(std::path::PathBuf::from(env!("CARGO_BIN_EXE_chunkrt")));
        measure::run(&measure::Options::new(opts, exe)).map(|_| ())
    });
}
