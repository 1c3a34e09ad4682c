//! Runs `ipc_latency`'s quick mode in the dev profile so the bench cannot rot (harness off: this
//! binary is also the bench's receiving process, started with `--peer`).

use chunkrt::bench::ipc_latency::{self, Options, PeerCommand};
use chunkrt::bench::{output_root, BenchOpts};

const NAME: &str = "ipc_latency_quick";

fn main() {
    iceoryx2::prelude::set_log_level(iceoryx2::prelude::LogLevel::Error);
    let args: Vec<String> = std::env::args().skip(1).collect();
    if args.first().map(String::as_str) == Some("--peer") {
        if let Err(e) = ipc_latency::peer_from_args(args.into_iter().skip(1)) {
            eprintln!("peer: {e}");
            std::process::exit(1);
        }
        return;
    }
    if args.iter().any(|a| a == "--list") {
        println!("{NAME}: test");
        return;
    }
    if let Some(filter) = args.iter().find(|a| !a.starts_with('-')) {
        if !NAME.contains(filter.as_str()) {
            println!("running 0 tests (filtered out)");
            return;
        }
    }
    let t0 = std::time::Instant::now();
    let exe = std::env::current_exe().expect("the test binary knows its own path");
    let bench = BenchOpts {
        quick: true,
        out_dir: output_root().join("test").join("ipc_latency"),
    };
    let mut opts = Options::new(
        bench,
        PeerCommand {
            program: exe,
            args: vec!["--peer".into()],
        },
    );
    opts.iters = 100;
    opts.warmup = 10;
    let s = ipc_latency::run(&opts).unwrap_or_else(|e| panic!("ipc_latency quick run failed: {e}"));

    assert_eq!(s.cases.len(), 7, "joint state + 3 sizes x (1, 3) cameras");
    for c in &s.cases {
        assert_eq!(c.lost, 0, "{}: lost samples", c.name);
        assert_eq!(c.ours.count, 100, "{}: sample count", c.name);
        assert!(c.ours.p50_ns > 0, "{}: zero latency is impossible", c.name);
        assert!(
            c.ours.p50_ns <= c.ours_rtt.p50_ns,
            "{}: one way > round trip",
            c.name
        );
    }
    let js = &s.cases[0];
    assert!(
        js.ours.p50_ns < 1_000_000,
        "joint state p50 {} ns: iceoryx2 should be well under 1 ms",
        js.ours.p50_ns
    );
    let big = s
        .cases
        .iter()
        .find(|c| c.name == "cam3_640x480")
        .expect("case exists");
    assert_eq!(big.bytes, 3 * 640 * 480 * 3);
    match (s.p50_ratio, &s.cases[0].baseline) {
        (Some(r), Some(_)) => {
            assert!(
                r > 1.0,
                "websocket+msgpack faster than shared memory? ratio {r}"
            );
            assert!(s
                .cases
                .iter()
                .all(|c| c.baseline.as_ref().is_some_and(|b| b.count == 100)));
        }
        _ => assert!(
            s.baseline_note.contains("did not run"),
            "no baseline and no reason: {}",
            s.baseline_note
        ),
    }
    assert!(s.line.starts_with("ipc_latency: "));
    assert!(s.outputs.hlog.exists() && s.outputs.md.exists());
    assert_eq!(
        s.outputs.pngs.len(),
        if s.p50_ratio.is_some() { 2 } else { 1 }
    );
    let back = chunkrt::report::read_interval_log(&s.outputs.hlog).expect("log reads back");
    assert_eq!(back[0].name, "joint_state");
    assert_eq!(back[0].hist.len(), 100);
    println!("test {NAME} ... ok ({:.1} s)", t0.elapsed().as_secs_f64());
}
