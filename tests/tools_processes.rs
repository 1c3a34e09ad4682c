//! The companion tools as real processes over real iceoryx2 services: `chunkrt fake-robot`
//! follows commands published by this test and holds when they stop or are late; `chunkrt
//! fake-camera` frames arrive with valid headers at the requested rate; `chunkrt monitor`
//! lists and measures them.

use std::time::{Duration, Instant};

use chunkrt_ipc::services::{self, Ipc};
use chunkrt_ipc::SharedConfig as Config;
use chunkrt_ipc::*;
use chunkrt_tools::fake_camera::read_seq_stamp;
use chunkrt_tools::testing::{summary_value, unique_namespace, ChildGuard};
use iceoryx2::port::publisher::Publisher;
use iceoryx2::port::subscriber::Subscriber;

const BIN: &str = env!("CARGO_BIN_EXE_chunkrt");

fn node(tag: &str) -> iceoryx2::prelude::Node<Ipc> {
    let n = services::node(&format!("tools-test-{tag}")).expect("test node");
    services::cleanup_dead_nodes(&n);
    n
}

/// The newest joint state, waiting up to `timeout` for one.
fn latest_state(sub: &Subscriber<Ipc, JointState, ()>, timeout: Duration) -> Option<JointState> {
    let end = Instant::now() + timeout;
    loop {
        let mut last = None;
        while let Ok(Some(s)) = sub.receive() {
            last = Some(*s.payload());
        }
        if last.is_some() || Instant::now() > end {
            return last;
        }
        std::thread::sleep(Duration::from_millis(1));
    }
}

fn send(publisher: &Publisher<Ipc, JointCommand, ()>, cmd: JointCommand) {
    let sample = publisher.loan_uninit().expect("loan");
    sample.write_payload(cmd).send().expect("send");
}

fn command(seq: u64, n_dof: u32, position: &[f64], deadline_after_ns: u64) -> JointCommand {
    let now = monotonic_ns();
    let mut c = JointCommand {
        seq,
        publish_time_ns: now,
        deadline_ns: now + deadline_after_ns,
        n_dof,
        mode: COMMAND_MODE_POSITION,
        ..Default::default()
    };
    c.position[..position.len()].copy_from_slice(position);
    c
}

/// Waits until a state satisfies `pred`, returning it (or the last one seen on timeout).
fn wait_state(
    sub: &Subscriber<Ipc, JointState, ()>,
    timeout: Duration,
    pred: impl Fn(&JointState) -> bool,
) -> (bool, Option<JointState>) {
    let end = Instant::now() + timeout;
    let mut last = None;
    while Instant::now() < end {
        while let Ok(Some(s)) = sub.receive() {
            let st = *s.payload();
            last = Some(st);
            if pred(&st) {
                return (true, last);
            }
        }
        std::thread::sleep(Duration::from_millis(1));
    }
    (false, last)
}

#[test]
fn tools_fake_robot_follows_commands_and_holds() {
    let cfg = Config::embedded_default();
    let n = cfg.n_dof();
    let initial: Vec<f64> = cfg
        .robot
        .joints
        .iter()
        .map(|j| j.initial_position)
        .collect();
    let ns_str = unique_namespace("robot");
    let ns = Namespace::new(&ns_str).unwrap();
    let node = node("robot");
    let st_factory = services::joint_state_service(&node, &ns.joint_state()).unwrap();
    let st_sub = services::subscriber(&st_factory).unwrap();
    let cmd_factory = services::joint_command_service(&node, &ns.joint_command()).unwrap();
    let cmd_pub = services::publisher(&cmd_factory).unwrap();

    let robot = ChildGuard::spawn(
        BIN,
        &[
            "fake-robot",
            "--namespace",
            &ns_str,
            "--duration",
            "20",
            "--command-timeout-ms",
            "100",
            // this test is the controller: obey the first command publisher, and its first
            // command is a deliberate step of 0.5 rad (no bumpless hand-over check)
            "--session",
            "first",
            "--bind-tolerance",
            "10",
        ],
    )
    .expect("spawn chunkrt fake-robot");

    // 1. Before any command: at the configured initial positions, holding.
    let first = latest_state(&st_sub, Duration::from_secs(30)).expect("no joint state in 30 s");
    validate_joint_state(&first, Some(n as u32)).expect("valid joint state");
    assert_ne!(first.status_flags & JOINT_STATUS_HOLDING, 0, "{first:?}");
    for (p, p0) in first.position.iter().zip(&initial) {
        assert!((p - p0).abs() < 1e-9, "{first:?}");
    }

    // 2. Stream commands at 1 kHz: shoulder to 0.5, elbow to 1.0, until the arm is there and
    //    follows (not holding) -- the contract is that it follows, not that it is there at a
    //    given instant on a loaded machine.
    let mut target = initial.clone();
    target[0] = 0.5;
    target[1] = 1.0;
    let mut seq = 0;
    let period = 1_000_000;
    let mut next = monotonic_ns();
    let start = next;
    let mut last_seen = None;
    let s = loop {
        seq += 1;
        send(&cmd_pub, command(seq, n as u32, &target, 20_000_000));
        next += period;
        sleep_until_ns(next);
        if seq % 50 == 0 {
            if let Some(s) = latest_state(&st_sub, Duration::ZERO) {
                // there and settled
                let tracking = (s.position[0] - 0.5).abs() < 0.01
                    && (s.position[1] - 1.0).abs() < 0.01
                    && s.velocity[0].abs() < 0.01
                    && s.velocity[1].abs() < 0.01;
                if tracking && s.status_flags & JOINT_STATUS_HOLDING == 0 {
                    break s;
                }
                last_seen = Some(s);
            }
        }
        assert!(
            monotonic_ns() < start + 10_000_000_000,
            "the arm did not follow the commands in 10 s: {last_seen:?}"
        );
    };

    // 3. Commands stop: hold, flagged, after the 100 ms command timeout at the latest.
    let (ok, last) = wait_state(&st_sub, Duration::from_secs(3), |s| {
        s.status_flags & JOINT_STATUS_HOLDING != 0
    });
    assert!(ok, "no HOLDING after commands stopped: {last:?}");
    let (ok, last) = wait_state(&st_sub, Duration::from_secs(3), |s| {
        s.status_flags & (JOINT_STATUS_HOLDING | JOINT_STATUS_COMMAND_TIMEOUT)
            == JOINT_STATUS_HOLDING | JOINT_STATUS_COMMAND_TIMEOUT
    });
    assert!(ok, "no COMMAND_TIMEOUT flag: {last:?}");
    let held = last.unwrap();
    // On the robot's own clock: `s` was following a live command, received at or after
    // `s.t - 20 ms` (its deadline), so the 100 ms timeout cannot come before `s.t + 80 ms`.
    let waited_ns = held.measurement_time_ns - s.measurement_time_ns;
    assert!(
        waited_ns >= 80_000_000,
        "timeout {waited_ns} ns after a live command"
    );
    assert!((held.position[0] - 0.5).abs() < 0.01, "{held:?}");

    // 4. A command already past its deadline is ignored and flagged.
    seq += 1;
    let mut late = command(seq, n as u32, &initial, 0);
    late.deadline_ns = late.publish_time_ns - 1_000_000;
    send(&cmd_pub, late);
    let (ok, last) = wait_state(&st_sub, Duration::from_secs(3), |s| {
        s.status_flags & JOINT_STATUS_COMMAND_EXPIRED != 0
    });
    assert!(ok, "no COMMAND_EXPIRED flag: {last:?}");
    assert!((last.unwrap().position[0] - 0.5).abs() < 0.01);

    // 5. An invalid command (NaN) is rejected and flagged.
    seq += 1;
    let mut bad = command(seq, n as u32, &target, 20_000_000);
    bad.position[2] = f64::NAN;
    send(&cmd_pub, bad);
    let (ok, last) = wait_state(&st_sub, Duration::from_secs(3), |s| {
        s.status_flags & JOINT_STATUS_COMMAND_REJECTED != 0
    });
    assert!(ok, "no COMMAND_REJECTED flag: {last:?}");

    // 6. SIGTERM: clean exit with a summary.
    let out = robot.terminate(Duration::from_secs(5));
    assert_eq!(out.code, Some(0), "exit: {out:?}");
    let v = |k: &str| {
        summary_value(&out.stdout, k).unwrap_or_else(|| panic!("no {k} in {:?}", out.stdout))
    };
    eprintln!("{}", out.stdout.trim());
    assert!(v("commands_applied") >= 100.0, "{}", out.stdout);
    assert!(v("commands_expired") >= 1.0, "{}", out.stdout);
    assert!(v("commands_rejected") >= 1.0, "{}", out.stdout);
    assert!(v("holds") >= 1.0, "{}", out.stdout);
    assert!(v("states_published") >= 100.0, "{}", out.stdout);
    assert!(v("max_tracking_error") < 1.0, "{}", out.stdout);
}

#[test]
fn tools_fake_camera_frames_are_valid_and_on_rate() {
    let cfg = Config::embedded_default();
    let ns_str = unique_namespace("camera");
    let ns = Namespace::new(&ns_str).unwrap();
    let node = node("camera");
    let fps = 40.0;
    let mut subs = Vec::new();
    for cam in &cfg.cameras {
        let name = ns.camera(&cam.name);
        let f = services::camera_service(&node, &name).unwrap();
        subs.push(services::camera_subscriber(&f).unwrap());
    }
    let camera = ChildGuard::spawn(
        BIN,
        &[
            "fake-camera",
            "--namespace",
            &ns_str,
            "--fps",
            "40",
            "--seed",
            "3",
            "--duration",
            "20",
        ],
    )
    .expect("spawn chunkrt fake-camera");

    // (first seq, first capture time, last seq, last capture time, received)
    type Seen = Option<(u64, u64, u64, u64, u64)>;
    let mut seen: Vec<Seen> = vec![None; subs.len()];
    let mut first_rx: Option<Instant> = None;
    let deadline = Instant::now() + Duration::from_secs(12);
    let measure = Duration::from_secs(2);
    while Instant::now() < deadline {
        if first_rx.is_some_and(|t| t.elapsed() >= measure) {
            break;
        }
        for (i, sub) in subs.iter().enumerate() {
            while let Ok(Some(sample)) = sub.receive() {
                let now = monotonic_ns();
                let h = *sample.user_header();
                let cam = &cfg.cameras[i];
                validate_frame(&h, sample.payload().len(), cam.width, cam.height)
                    .unwrap_or_else(|e| panic!("camera {i}: invalid frame {h:?}: {e}"));
                assert_eq!(h.camera_id, i as u32);
                assert_eq!(h.encoding, ENCODING_RGB8);
                assert_eq!((h.width, h.height), (cam.width, cam.height));
                assert_eq!(h.stride, cam.width * 3);
                assert_eq!(h.reserved, 0);
                assert!(h.capture_time_ns <= h.publish_time_ns && h.publish_time_ns <= now);
                assert_eq!(read_seq_stamp(sample.payload()), Some(h.seq));
                first_rx.get_or_insert_with(Instant::now);
                seen[i] = Some(match seen[i] {
                    None => (h.seq, h.capture_time_ns, h.seq, h.capture_time_ns, 1),
                    Some((s0, t0, last, _, count)) => {
                        assert!(h.seq > last, "camera {i}: seq {} after {last}", h.seq);
                        (s0, t0, h.seq, h.capture_time_ns, count + 1)
                    }
                });
            }
        }
        std::thread::sleep(Duration::from_millis(1));
    }
    for (i, s) in seen.iter().enumerate() {
        let (s0, t0, s1, t1, count) = s.unwrap_or_else(|| panic!("camera {i}: no frames"));
        let rate = (s1 - s0) as f64 / ((t1 - t0) as f64 * 1e-9);
        eprintln!(
            "camera {i}: {count} frames received, seq {s0}..{s1}, rate {rate:.2} Hz (asked {fps})"
        );
        // on schedule: never more frames than the schedule plus its bounded catch-up burst
        // (10 frames), and alive (late frames on a loaded machine only lower the rate)
        assert!(
            (s1 - s0) as f64 <= fps * (t1 - t0) as f64 * 1e-9 + 11.0 && rate >= 0.5 * fps,
            "camera {i}: {rate:.2} Hz, asked {fps}"
        );
        // in order and delivered (the subscriber keeps the newest 2 frames, so a reader that
        // stalls skips some by design; `seq` increasing is asserted for every frame above)
        assert!(count >= 2, "camera {i}: {count} frames");
    }
    let out = camera.terminate(Duration::from_secs(5));
    assert_eq!(out.code, Some(0), "exit: {out:?}");
    assert!(out.stdout.contains("fake-camera summary:"), "{out:?}");
    assert_eq!(summary_value(&out.stdout, "failures"), Some(0.0), "{out:?}");
}

/// The `key=value` token of a monitor line.
fn token<'a>(line: &'a str, key: &str) -> Option<&'a str> {
    let pat = format!("{key}=");
    line.split_whitespace()
        .find_map(|w| w.strip_prefix(pat.as_str()))
}

#[test]
fn tools_monitor_lists_and_measures_services() {
    let ns = unique_namespace("monitor");
    let _robot = ChildGuard::spawn(BIN, &["fake-robot", "--namespace", &ns, "--duration", "20"])
        .expect("spawn fake-robot");
    let _camera = ChildGuard::spawn(
        BIN,
        &[
            "fake-camera",
            "--namespace",
            &ns,
            "--fps",
            "50",
            "--duration",
            "20",
        ],
    )
    .expect("spawn fake-camera");
    // Let both create their services.
    let cfg = Config::embedded_default();
    let node = node("monitor");
    let nsv = Namespace::new(&ns).unwrap();
    let st = services::joint_state_service(&node, &nsv.joint_state()).unwrap();
    let sub = services::subscriber(&st).unwrap();
    latest_state(&sub, Duration::from_secs(10)).expect("fake-robot is not publishing");
    let cam = services::camera_service(&node, &nsv.camera(&cfg.cameras[0].name)).unwrap();
    let cam_sub = services::camera_subscriber(&cam).unwrap();
    let end = Instant::now() + Duration::from_secs(10);
    while !matches!(cam_sub.receive(), Ok(Some(_))) {
        assert!(Instant::now() < end, "fake-camera is not publishing");
        std::thread::sleep(Duration::from_millis(5));
    }

    let monitor = ChildGuard::spawn(
        BIN,
        &["monitor", "--namespace", &ns, "--once", "--interval", "1.5"],
    )
    .expect("spawn monitor");
    let out = monitor.finish(Duration::from_secs(15));
    eprintln!("{}", out.stdout);
    assert_eq!(out.code, Some(0), "{out:?}");
    let lines: Vec<&str> = out
        .stdout
        .lines()
        .filter(|l| !l.trim().is_empty())
        .collect();
    for l in &lines {
        assert!(
            l.starts_with(&format!("{ns}/")),
            "foreign service listed: {l}"
        );
        assert_eq!(token(l, "invalid"), Some("0"), "{l}");
    }
    let find = |name: String| {
        *lines
            .iter()
            .find(|l| l.split_whitespace().next() == Some(name.as_str()))
            .unwrap_or_else(|| panic!("{name} not listed in {lines:?}"))
    };
    let rate = |l: &str| -> f64 {
        token(l, "rate_hz")
            .and_then(|r| r.parse().ok())
            .unwrap_or_else(|| panic!("no rate in {l}"))
    };
    let js = find(nsv.joint_state());
    assert!(js.contains("JointState") && js.contains("n_dof=4"), "{js}");
    let r = rate(js);
    // alive and never much faster than 1 kHz (the rate arithmetic is unit-tested in monitor)
    assert!((200.0..=1100.0).contains(&r), "joint_state rate {r}: {js}");
    let lat: f64 = token(js, "latency_avg_us").unwrap().parse().unwrap();
    assert!(lat > 0.0 && lat < 100_000.0, "{js}");
    let jc = find(nsv.joint_command());
    assert!(jc.contains("(no data)"), "{jc}");
    for c in &cfg.cameras {
        let l = find(nsv.camera(&c.name));
        let r = rate(l);
        assert!((25.0..=55.0).contains(&r), "camera rate {r}: {l}");
        assert!(l.contains(&format!("{}x{}", c.width, c.height)), "{l}");
    }
}

#[test]
fn tools_fake_camera_configured_encodings() {
    // the default robot's camera as bgr8, plus a second, mono8 camera
    let toml = chunkrt_ipc::config::DEFAULT_TOML
        .replacen("encoding = \"rgb8\"", "encoding = \"bgr8\"", 1)
        + "\n[[cameras]]\nname = \"left_wrist_0_rgb\"\nwidth = 96\nheight = 64\nfps = 30.0\nencoding = \"mono8\"\n";
    let cfg = Config::parse(&toml, "test").expect("edited config is valid");
    assert_eq!(cfg.cameras[0].encoding, "bgr8");
    assert_eq!(cfg.cameras[1].encoding, "mono8");
    let dir = std::env::temp_dir().join(format!("chunkrt-tools-enc-{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    let path = dir.join("cameras.toml");
    std::fs::write(&path, &toml).unwrap();

    let ns_str = unique_namespace("encodings");
    let ns = Namespace::new(&ns_str).unwrap();
    let node = node("encodings");
    let subs: Vec<_> = cfg
        .cameras
        .iter()
        .map(|c| {
            let name = ns.camera(&c.name);
            let f = services::camera_service(&node, &name).unwrap();
            services::camera_subscriber(&f).unwrap()
        })
        .collect();
    let camera = ChildGuard::spawn(
        BIN,
        &[
            "fake-camera",
            "--config",
            path.to_str().unwrap(),
            "--namespace",
            &ns_str,
            "--fps",
            "20",
            "--duration",
            "20",
        ],
    )
    .expect("spawn fake-camera");
    let expected = [(ENCODING_BGR8, 3), (ENCODING_MONO8, 1)];
    let mut got = [false; 2];
    let end = Instant::now() + Duration::from_secs(10);
    while got.iter().any(|g| !g) && Instant::now() < end {
        for (i, sub) in subs.iter().enumerate() {
            while let Ok(Some(s)) = sub.receive() {
                let h = *s.user_header();
                let c = &cfg.cameras[i];
                validate_frame(&h, s.payload().len(), c.width, c.height).unwrap();
                assert_eq!(h.encoding, expected[i].0, "camera {i}");
                assert_eq!(h.stride, c.width * expected[i].1, "camera {i}");
                assert_eq!(read_seq_stamp(s.payload()), Some(h.seq));
                got[i] = true;
            }
        }
        std::thread::sleep(Duration::from_millis(2));
    }
    let out = camera.terminate(Duration::from_secs(5));
    let _ = std::fs::remove_dir_all(&dir);
    assert_eq!(got, [true, true], "frames of both cameras: {out:?}");
    assert_eq!(out.code, Some(0), "{out:?}");
}
