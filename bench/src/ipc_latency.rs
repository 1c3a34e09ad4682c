//! `ipc_latency`: publish → receive latency between two processes over iceoryx2, for joint
//! states and for camera frames of 64×64, 224×224 and 640×480 RGB (1 and 3 cameras), against
//! openpi's websocket + msgpack-numpy transport ([`super::ws_baseline`]) in the same run. Where
//! Python / openpi-client cannot run (or `CHUNKRT_WS_BASELINE=rust`), the baseline is an
//! equivalent Rust websocket + msgpack pair ([`super::ws_rust`]) and the output says so.
//!
//! How one sample is measured (ping-pong, one sample in flight):
//!
//! ```text
//!  bench process                                   peer process (`PeerArgs`)
//!  t0 = now; loan; write header (+ copy pixels);
//!  send ───────── iceoryx2 shared memory ───────▶  receive (polling), validate, read the pixels
//!                                                  t1 = now  (all cameras of this seq received)
//!  receive ack ◀──────── `<ns>/bench_ack` ───────  publish ack {seq, t1}
//!  one-way = t1 - t0 (same CLOCK_MONOTONIC),  round trip = now - t0
//! ```
//!
//! By default ([`Wake::Event`]) each side blocks on an iceoryx2 event that the other side
//! notifies right after sending, so a figure includes the receiver's wake-up, like the websocket
//! baseline's blocking `recv` (openpi's server). [`Wake::Poll`] spins on `receive()` instead.
//! The publisher writes the pixels into the loaned shared-memory sample (a camera driver has to
//! put them somewhere), the receiver reads them in place (zero copy).

use std::path::PathBuf;
use std::process::{Child, Command, Stdio};
use std::time::{Duration, Instant};

use chunkrt_ipc::services::{self, Namespace};
use chunkrt_ipc::{
    monotonic_ns, sleep_until_ns, validate_frame, validate_joint_state, CameraFrameHeader,
    JointState, ENCODING_RGB8, MAX_DOF,
};
use hdrhistogram::Histogram;

use super::ws_baseline::{self, Case};
use super::{geomean, write_outputs, BenchError, BenchOpts, Outputs};
use crate::report::{fmt_us, latency_histogram, LatencyRow, LatencyTable, Series};

mod peer;

use peer::*;
pub use peer::{peer_from_args, peer_main, PeerArgs};

/// Sequence number that tells the peer to exit.
const STOP_SEQ: u64 = u64::MAX;

/// The peer process: `<program> <args…> --namespace NS --cameras N --width W --height H`.
#[derive(Debug, Clone)]
pub struct PeerCommand {
    /// Executable.
    pub program: PathBuf,
    /// Arguments before the peer's own (e.g. a subcommand name).
    pub args: Vec<String>,
}

/// Options of one `ipc_latency` run.
#[derive(Debug, Clone)]
pub struct Options {
    /// Output folder and quick mode.
    pub bench: BenchOpts,
    /// How to start the receiving process.
    pub peer: PeerCommand,
    /// Measured samples per case (default: 2000, quick 150).
    pub iters: usize,
    /// Unmeasured samples per case before measuring.
    pub warmup: usize,
    /// Pause between samples (observations arrive at a rate, not back to back).
    pub gap: Duration,
    /// Run the websocket baseline.
    pub baseline: bool,
    /// How the receiver learns that a sample arrived.
    pub wake: Wake,
}

/// How a receiver waits for samples.
#[derive(Debug, Clone, Copy, PartialEq, Eq, clap::ValueEnum)]
pub enum Wake {
    /// Block on an iceoryx2 event the publisher notifies after sending (like a socket read).
    Event,
    /// Spin on `receive()` with `yield_now` (lowest latency on an idle core; suffers when the
    /// core is shared with other runnable threads).
    Poll,
}

impl Options {
    /// Defaults for a bench run (`quick` from `bench`).
    pub fn new(bench: BenchOpts, peer: PeerCommand) -> Self {
        let quick = bench.quick;
        Self {
            bench,
            peer,
            iters: if quick { 150 } else { 2000 },
            warmup: if quick { 20 } else { 100 },
            gap: Duration::from_millis(1),
            baseline: true,
            wake: Wake::Event,
        }
    }
}

/// Result of one case.
#[derive(Debug, Clone)]
pub struct CaseSummary {
    /// Case name (`joint_state`, `cam1_64x64`, …).
    pub name: String,
    /// Bytes published per observation (all cameras).
    pub bytes: usize,
    /// iceoryx2 one-way latency.
    pub ours: LatencyRow,
    /// iceoryx2 round trip.
    pub ours_rtt: LatencyRow,
    /// Samples that got no answer within 1 s.
    pub lost: u64,
    /// Websocket baseline one-way latency (if it ran).
    pub baseline: Option<LatencyRow>,
}

/// What `ipc_latency` measured.
#[derive(Debug, Clone)]
pub struct Summary {
    /// Per case.
    pub cases: Vec<CaseSummary>,
    /// The baseline's transport, or why it did not run.
    pub baseline_note: String,
    /// Geometric mean over cases of baseline p50 / ours p50 (None without baseline).
    pub p50_ratio: Option<f64>,
    /// Same for p99.
    pub p99_ratio: Option<f64>,
    /// The one-line summary printed last.
    pub line: String,
    /// Files written.
    pub outputs: Outputs,
}

/// The cases measured: joint state, then 1 and 3 cameras at each frame size.
pub fn cases() -> Vec<Case> {
    let mut v = vec![Case {
        name: "joint_state".into(),
        cameras: 0,
        width: 0,
        height: 0,
    }];
    for (w, h) in [(64u32, 64u32), (224, 224), (640, 480)] {
        for cams in [1u32, 3] {
            v.push(Case {
                name: format!("cam{cams}_{w}x{h}"),
                cameras: cams,
                width: w,
                height: h,
            });
        }
    }
    v
}

struct PeerProcess(Child);

impl Drop for PeerProcess {
    fn drop(&mut self) {
        // The peer exits on STOP_SEQ; this is the fallback when the bench fails midway.
        let deadline = Instant::now() + Duration::from_secs(2);
        while Instant::now() < deadline {
            if let Ok(Some(_)) = self.0.try_wait() {
                return;
            }
            std::thread::sleep(Duration::from_millis(10));
        }
        let _ = self.0.kill();
        let _ = self.0.wait();
    }
}

/// One-way and round-trip histograms of one case, plus lost samples.
struct Measured {
    one_way: Histogram<u64>,
    rtt: Histogram<u64>,
    lost: u64,
    bytes: usize,
}

fn measure_case(opts: &Options, case: &Case, index: usize) -> Result<Measured, BenchError> {
    let ns = Namespace::new(&format!("chunkrt/bench/ipc{}/c{index}", std::process::id()))?;
    let node = services::node("chunkrt-bench-ipc")?;
    let (notifier, listener) = event_ports(&node, &ns, false)?;
    let ack_name = ack_service_name(&ns);
    let ack_svc = services::joint_state_service(&node, &ack_name)?;
    let ack_sub = services::subscriber(&ack_svc)?;

    enum Pubs {
        Joint(iceoryx2::port::publisher::Publisher<services::Ipc, JointState, ()>),
        Cams(Vec<iceoryx2::port::publisher::Publisher<services::Ipc, [u8], CameraFrameHeader>>),
    }
    let frame_bytes = (case.width * case.height * 3) as usize;
    let pubs = if case.cameras == 0 {
        let name = ns.joint_state();
        let svc = services::joint_state_service(&node, &name)?;
        Pubs::Joint(services::publisher(&svc)?)
    } else {
        let mut v = Vec::new();
        for i in 0..case.cameras {
            let name = ns.camera(&format!("cam{i}"));
            let svc = services::camera_service(&node, &name)?;
            v.push(services::camera_publisher(&svc, frame_bytes)?);
        }
        Pubs::Cams(v)
    };
    // One synthetic frame per camera, prepared once (the camera driver's buffer).
    let frames: Vec<Vec<u8>> = (0..case.cameras)
        .map(|c| {
            (0..frame_bytes)
                .map(|i| (i as u32).wrapping_mul(2_654_435_761).wrapping_add(c) as u8)
                .collect()
        })
        .collect();
    let bytes = if case.cameras == 0 {
        std::mem::size_of::<JointState>()
    } else {
        frame_bytes * case.cameras as usize
    };

    let publish = |seq: u64| -> Result<(), BenchError> {
        let now = monotonic_ns();
        match &pubs {
            Pubs::Joint(p) => {
                let mut msg = JointState {
                    seq,
                    measurement_time_ns: now,
                    n_dof: MAX_DOF as u32,
                    ..JointState::default()
                };
                for j in 0..MAX_DOF {
                    msg.position[j] = j as f64 * 0.1;
                }
                p.send_copy(msg)
                    .map_err(|e| port_err("send")(format!("{e:?}")))?;
            }
            Pubs::Cams(ps) => {
                for (i, p) in ps.iter().enumerate() {
                    let mut s = p
                        .loan_slice_uninit(frame_bytes)
                        .map_err(|e| port_err("loan")(format!("{e:?}")))?;
                    *s.user_header_mut() = CameraFrameHeader {
                        seq,
                        capture_time_ns: now,
                        publish_time_ns: monotonic_ns(),
                        camera_id: i as u32,
                        encoding: ENCODING_RGB8,
                        width: case.width,
                        height: case.height,
                        stride: case.width * 3,
                        reserved: 0,
                    };
                    let s = s.write_from_slice(&frames[i]);
                    s.send().map_err(|e| port_err("send")(format!("{e:?}")))?;
                }
            }
        }
        if opts.wake == Wake::Event {
            notifier
                .notify()
                .map_err(|e| port_err("notify")(format!("{e:?}")))?;
        }
        Ok(())
    };
    let wait_ack = |seq: u64, timeout_ns: u64| -> Result<Option<u64>, BenchError> {
        let start = monotonic_ns();
        loop {
            while let Some(s) = ack_sub
                .receive()
                .map_err(|e| port_err("ack receive")(format!("{e:?}")))?
            {
                if s.payload().seq >= seq {
                    return Ok(Some(s.payload().measurement_time_ns));
                }
            }
            let waited = monotonic_ns() - start;
            if waited > timeout_ns {
                return Ok(None);
            }
            wait_for_more(
                opts.wake,
                &listener,
                Duration::from_nanos((timeout_ns - waited).min(100_000_000)),
            )?;
        }
    };

    let mut cmd = Command::new(&opts.peer.program);
    cmd.args(&opts.peer.args)
        .args(["--namespace", ns.as_str()])
        .args(["--cameras", &case.cameras.to_string()])
        .args(["--width", &case.width.to_string()])
        .args(["--height", &case.height.to_string()])
        .args([
            "--wake",
            match opts.wake {
                Wake::Event => "event",
                Wake::Poll => "poll",
            },
        ])
        .stdin(Stdio::null())
        .stdout(Stdio::null())
        .stderr(Stdio::inherit());
    let child = cmd.spawn().map_err(|e| BenchError::Process {
        what: format!("peer {}", opts.peer.program.display()),
        reason: e.to_string(),
    })?;
    let mut peer = PeerProcess(child);

    // Handshake: publish until the peer's subscribers are connected and answer.
    let mut seq = 0u64;
    let t_start = Instant::now();
    loop {
        seq += 1;
        publish(seq)?;
        if wait_ack(seq, 5_000_000)?.is_some() {
            break;
        }
        if let Ok(Some(status)) = peer.0.try_wait() {
            return Err(BenchError::Process {
                what: "ipc_latency peer".into(),
                reason: format!("exited early with {status}"),
            });
        }
        if t_start.elapsed() > Duration::from_secs(20) {
            return Err(BenchError::Timeout(
                "peer did not connect within 20 s".into(),
            ));
        }
    }

    let mut one_way = latency_histogram();
    let mut rtt = latency_histogram();
    let mut lost = 0u64;
    let gap = opts.gap.as_nanos() as u64;
    let mut next = monotonic_ns();
    for i in 0..(opts.warmup + opts.iters) {
        seq += 1;
        next += gap;
        sleep_until_ns(next);
        let t0 = monotonic_ns();
        publish(seq)?;
        match wait_ack(seq, 1_000_000_000)? {
            Some(t1) => {
                let t2 = monotonic_ns();
                if i >= opts.warmup {
                    one_way.saturating_record(t1.saturating_sub(t0));
                    rtt.saturating_record(t2 - t0);
                }
            }
            None => lost += 1,
        }
        next = next.max(monotonic_ns());
    }
    publish(STOP_SEQ)?;
    let deadline = Instant::now() + Duration::from_secs(2);
    while Instant::now() < deadline {
        if let Ok(Some(_)) = peer.0.try_wait() {
            break;
        }
        std::thread::sleep(Duration::from_millis(5));
    }
    drop(peer);
    Ok(Measured {
        one_way,
        rtt,
        lost,
        bytes,
    })
}

/// Runs every case over iceoryx2, then the websocket baseline, prints the tables and the
/// one-line summary, and writes the log, plots and table under `opts.bench.out_dir`.
pub fn run(opts: &Options) -> Result<Summary, BenchError> {
    let cases = cases();
    let started = Instant::now();
    let mut series = Vec::new();
    let mut measured = Vec::new();
    for (i, c) in cases.iter().enumerate() {
        let m = measure_case(opts, c, i)?;
        series.push(Series::new(c.name.clone(), m.one_way.clone()));
        measured.push(m);
    }
    let (baseline, baseline_note) = if opts.baseline {
        match ws_baseline::run(
            &cases,
            opts.iters,
            opts.warmup,
            opts.gap,
            Duration::from_secs(if opts.bench.quick { 120 } else { 600 }),
        ) {
            Ok(b) => {
                let note = match &b.substitution {
                    Some(s) => format!("{} [substitution: {s}]", b.transport),
                    None => b.transport.clone(),
                };
                (Some(b), note)
            }
            Err(e) => (None, format!("websocket baseline did not run: {e}")),
        }
    } else {
        (None, "websocket baseline disabled".to_string())
    };
    if let Some(b) = &baseline {
        for c in &b.cases {
            series.push(Series::new(format!("ws_{}", c.name), c.one_way.clone()));
        }
    }

    let mut summaries = Vec::new();
    let mut r50 = Vec::new();
    let mut r99 = Vec::new();
    for (c, m) in cases.iter().zip(&measured) {
        let ours = LatencyRow::from_hist(&c.name, &m.one_way);
        let base = baseline.as_ref().and_then(|b| {
            b.cases
                .iter()
                .find(|x| x.name == c.name)
                .map(|x| LatencyRow::from_hist(&format!("ws_{}", c.name), &x.one_way))
        });
        if let Some(b) = &base {
            r50.push(b.p50_ns as f64 / ours.p50_ns.max(1) as f64);
            r99.push(b.p99_ns as f64 / ours.p99_ns.max(1) as f64);
        }
        summaries.push(CaseSummary {
            name: c.name.clone(),
            bytes: m.bytes,
            ours,
            ours_rtt: LatencyRow::from_hist(&format!("{}_rtt", c.name), &m.rtt),
            lost: m.lost,
            baseline: base,
        });
    }
    let (p50_ratio, p99_ratio) = if r50.is_empty() {
        (None, None)
    } else {
        (Some(geomean(&r50)), Some(geomean(&r99)))
    };

    let table = LatencyTable::from_series(
        format!(
            "ipc_latency: publish → receive, one way ({} samples per case, {} µs apart, receiver \
             wakes by {:?}); ws_* = {baseline_note}",
            opts.iters,
            opts.gap.as_micros(),
            opts.wake
        ),
        &series,
    );
    println!("{table}");
    println!(
        "{:<14} {:>9} {:>12} {:>12} {:>12} {:>12} {:>8}",
        "case", "bytes", "iox2 p50", "iox2 p99", "ws p50", "ws p99", "ws/iox2"
    );
    for s in &summaries {
        let (b50, b99, ratio) = match &s.baseline {
            Some(b) => (
                fmt_us(b.p50_ns),
                fmt_us(b.p99_ns),
                format!("{:.1}x", b.p50_ns as f64 / s.ours.p50_ns.max(1) as f64),
            ),
            None => ("-".into(), "-".into(), "-".into()),
        };
        println!(
            "{:<14} {:>9} {:>12} {:>12} {:>12} {:>12} {:>8}",
            s.name,
            s.bytes,
            fmt_us(s.ours.p50_ns),
            fmt_us(s.ours.p99_ns),
            b50,
            b99,
            ratio
        );
    }
    let lost: u64 = summaries.iter().map(|s| s.lost).sum();
    let growth = match (
        summaries.iter().find(|s| s.name == "cam1_64x64"),
        summaries.iter().find(|s| s.name == "cam3_640x480"),
    ) {
        (Some(a), Some(b)) => format!(
            "; frame size: cam1_64x64 p50 {} µs → cam3_640x480 p50 {} µs ({:.1}x for {}x the bytes)",
            fmt_us(a.ours.p50_ns),
            fmt_us(b.ours.p50_ns),
            b.ours.p50_ns as f64 / a.ours.p50_ns.max(1) as f64,
            b.bytes / a.bytes.max(1)
        ),
        _ => String::new(),
    };
    let js = &summaries[0];
    let line = match (p50_ratio, p99_ratio) {
        (Some(a), Some(b)) => format!(
            "ipc_latency: iceoryx2 joint_state p50/p99 {}/{} µs; websocket+msgpack ({baseline_note}) \
             is {a:.1}x slower at p50 and {b:.1}x at p99 (geomean over {} cases){growth}; lost {lost}",
            fmt_us(js.ours.p50_ns),
            fmt_us(js.ours.p99_ns),
            summaries.len()
        ),
        _ => format!(
            "ipc_latency: iceoryx2 joint_state p50/p99 {}/{} µs; no baseline ratio: {baseline_note}{growth}; lost {lost}",
            fmt_us(js.ours.p50_ns),
            fmt_us(js.ours.p99_ns)
        ),
    };

    let ours_names: Vec<String> = cases.iter().map(|c| c.name.clone()).collect();
    let all_names: Vec<String> = series.iter().map(|s| s.name.clone()).collect();
    let outputs = write_outputs(
        &opts.bench.out_dir,
        "ipc_latency",
        &table,
        &series,
        &[
            (
                "ipc_latency",
                "iceoryx2 publish → receive (one way)",
                ours_names,
            ),
            (
                "ipc_latency_vs_websocket",
                "iceoryx2 vs websocket + msgpack-numpy (one way)",
                all_names,
            ),
        ],
        started.elapsed(),
        &format!(
            "chunkrt ipc_latency on {}\nbaseline: {baseline_note}",
            super::machine_line()
        ),
    )?;
    println!("{outputs}");
    println!("{line}");
    Ok(Summary {
        cases: summaries,
        baseline_note,
        p50_ratio,
        p99_ratio,
        line,
        outputs,
    })
}
