//! `cargo bench --bench end_to_end [-- --quick] [--small]`: fake camera + simulated robot +
//! controller with the real model (the π0.5 bench configuration, random weights; `--small`: the
//! committed reach policy) as processes over iceoryx2. See `chunkrt_bench::end_to_end`.

use chunkrt_bench::end_to_end::{self, Options};

fn main() {
    let small = std::env::args().any(|a| a == "--small");
    let args = std::env::args()
        .skip(1)
        .filter(|a| a != "--small")
        .collect::<Vec<_>>();
    let result = chunkrt_bench::BenchOpts::from_args("end_to_end", args).and_then(|b| {
        let mut o = Options::new(b, env!("CARGO_BIN_EXE_chunkrt").into());
        o.small = small;
        end_to_end::run(&o).map(|_| ())
    });
    if let Err(e) = result {
        eprintln!("end_to_end: error: {e}");
        std::process::exit(1);
    }
}
