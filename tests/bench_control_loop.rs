//! Runs `control_loop` briefly (~1 s per scenario) in the dev profile so the bench cannot rot.

use std::time::Duration;

use chunkrt_bench::control_loop::{self, Options};
use chunkrt_bench::{cyclictest, output_root, BenchOpts};

#[test]
fn control_loop_quick() {
    if std::env::var_os("RAYON_NUM_THREADS").is_none() {
        // Only this test runs in this binary; keep candle's load on its own core.
        std::env::set_var("RAYON_NUM_THREADS", "1");
    }
    let mut opts = Options::new(BenchOpts {
        quick: true,
        out_dir: output_root().join("test").join("control_loop"),
    });
    opts.duration = Duration::from_secs(1);
    opts.cyclictest_duration = Duration::from_millis(500);
    opts.load_size = 128;
    let s = control_loop::run(&opts).unwrap_or_else(|e| panic!("control_loop failed: {e}"));

    assert_eq!(s.scenarios.len(), 4, "500 Hz / 1 kHz x idle / loaded");
    for sc in &s.scenarios {
        // Every deadline of the 1 s is either run or skipped (a tick that wakes too late skips
        // the deadlines it passed, on a loaded machine too), never run twice; and the loop ran.
        let expected = sc.rate_hz;
        let deadlines = (sc.ticks + sc.skipped) as f64;
        assert!(
            (expected - 1.0..=expected + 1.0).contains(&deadlines)
                && sc.ticks as f64 <= expected + 1.0
                && sc.ticks as f64 >= 0.1 * expected,
            "{}: {} ticks + {} skipped for {expected} deadlines",
            sc.name,
            sc.ticks,
            sc.skipped
        );
        assert_eq!(sc.lateness.count, sc.ticks);
        assert_eq!(sc.compute.count, sc.ticks);
        // The executor tick (interpolation, blending, ruckig) takes microseconds (release
        // 9-18 µs): it fits its period with room to spare, even in this dev build under load.
        assert!(sc.compute.p50_ns < (1e9 / sc.rate_hz) as u64 / 2, "{sc:?}");
        assert_eq!(sc.loaded, sc.load_gflops.is_some());
        // the controller's own tick ran: the executor reached RUNNING on scripted chunks, with
        // joint states over iceoryx2 (it may hold at the end if the robot thread was starved on
        // a loaded machine), and published commands
        assert!(
            sc.body.contains("reached RUNNING: yes"),
            "{}: {}",
            sc.name,
            sc.body
        );
        let published: u64 = sc
            .body
            .split(' ')
            .next()
            .and_then(|n| n.parse().ok())
            .unwrap_or(0);
        assert!(published > sc.ticks / 2, "{}: {}", sc.name, sc.body);
        if cyclictest::available() {
            let c = sc.cyclictest.as_ref().expect("cyclictest ran");
            assert!(c.count as f64 >= sc.rate_hz * 0.5 * 0.9, "{c:?}");
        }
    }
    if cyclictest::available() {
        assert!(s.p99_ratio.is_some_and(|r| r > 0.0));
    } else {
        assert!(s.cyclictest_note.contains("not installed"));
    }
    assert!(s.line.starts_with("control_loop: "));
    assert!(s.outputs.hlog.exists());
    assert_eq!(s.outputs.pngs.len(), 2);
}
