//! Runs `ipc_latency`'s quick mode in the dev profile so the bench cannot rot (harness off: this
//! binary is also the bench's receiving process, started with `--peer`). First checks the Rust
//! fallback of the websocket baseline on two small cases (`CHUNKRT_WS_BASELINE=rust`); the full
//! quick run then uses whatever driver the environment gives (set `CHUNKRT_WS_BASELINE=rust` to
//! run it all on the fallback).

use std::time::Duration;

use chunkrt_bench::ipc_latency::{self, Options, PeerCommand};
use chunkrt_bench::ws_baseline;
use chunkrt_bench::{output_root, BenchOpts};

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
    forced_rust_fallback();
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
    if std::env::var(ws_baseline::DRIVER_ENV).as_deref() == Ok("rust") {
        assert!(
            s.baseline_note
                .contains("Rust tungstenite + rmp fallback: forced by CHUNKRT_WS_BASELINE=rust"),
            "forced fallback not named: {}",
            s.baseline_note
        );
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

/// `CHUNKRT_WS_BASELINE=rust` makes `ws_baseline::run` use the Rust websocket + msgpack pair and
/// say so; it measures every sample of a joint-state and a 64×64 camera case.
fn forced_rust_fallback() {
    let before = std::env::var_os(ws_baseline::DRIVER_ENV);
    std::env::set_var(ws_baseline::DRIVER_ENV, "rust");
    let cases: Vec<_> = ipc_latency::cases()
        .into_iter()
        .filter(|c| c.name == "joint_state" || c.name == "cam1_64x64")
        .collect();
    let b = ws_baseline::run(
        &cases,
        50,
        5,
        Duration::from_micros(200),
        Duration::from_secs(30),
    );
    match before {
        Some(v) => std::env::set_var(ws_baseline::DRIVER_ENV, v),
        None => std::env::remove_var(ws_baseline::DRIVER_ENV),
    }
    let b = b.unwrap_or_else(|e| panic!("forced Rust websocket baseline failed: {e}"));
    assert!(
        b.transport
            .contains("Rust tungstenite + rmp fallback: forced by CHUNKRT_WS_BASELINE=rust"),
        "transport does not name the fallback: {}",
        b.transport
    );
    assert!(
        b.substitution.is_some(),
        "fallback without substitution note"
    );
    assert_eq!(b.cases.len(), 2);
    for c in &b.cases {
        assert_eq!(c.one_way.len(), 50, "{}: one-way samples", c.name);
        assert_eq!(c.rtt.len(), 50, "{}: round-trip samples", c.name);
        assert!(c.one_way.min() > 0, "{}: zero latency", c.name);
        println!(
            "rust websocket fallback {}: one way p50/p99 {}/{} ns, rtt p50 {} ns",
            c.name,
            c.one_way.value_at_quantile(0.5),
            c.one_way.value_at_quantile(0.99),
            c.rtt.value_at_quantile(0.5)
        );
    }
}
