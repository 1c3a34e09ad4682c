//! Runs the `end_to_end` bench briefly so it cannot rot: the committed reach policy (fast to
//! load) for a few seconds, checking every figure is measured and sane.

use std::time::Duration;

use chunkrt_bench::end_to_end::{self, Options};
use chunkrt_bench::{output_root, BenchOpts};

#[test]
fn end_to_end_quick() {
    let mut o = Options::new(
        BenchOpts {
            quick: true,
            out_dir: output_root().join("test").join("end_to_end"),
        },
        env!("CARGO_BIN_EXE_chunkrt").into(),
    );
    o.small = true;
    o.duration = Duration::from_secs(4);
    let s = end_to_end::run(&o).unwrap_or_else(|e| panic!("end_to_end failed: {e}"));
    // commands at no more than the control rate (a late tick is skipped, which only lowers
    // it on a loaded machine), and flowing
    let r = s.commands_per_s / s.control_rate_hz;
    assert!((0.2..=1.05).contains(&r), "{} commands/s", s.commands_per_s);
    assert!(s.chunks >= 2, "{s}");
    assert!(s.observation_age.count > 100, "{s}");
    // a command is never older than its chunk's latency plus the chunk's length (1 s at 10 Hz)
    assert!(
        s.observation_age.p50_ns >= s.chunk_latency.p50_ns / 2,
        "{s}"
    );
    assert!(s.observation_age.max_ns < 10_000_000_000, "{s}");
    assert!(s.live_share > 0.5, "{s}");
    assert!(s.outputs.hlog.exists() && s.outputs.md.exists());
}
