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
        assert!(text.contains(from), "config/ros2_mock.toml has no line {from:?}");
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
    let path = std::env::temp_dir().join(format!(
        "chunkrt-ros2-{}-{tag}.toml",
        std::process::id()
    ));
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
        &[
            "--config",
            cfg,
            "--domain-id",
            &dom,
            "--duration",
            &total,
        ],
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
         through the bridge (state in -> command out) p50/p99/max {:.0}/{:.0}/{:.0} us; bridge CPU \
         {:.1} %; arm range {} rad, max arm step {:.4} rad; first command after {:.3} s",
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
    // best effort on loopback: a loss is possible, a lost half is not
    assert!(
        received >= 0.95 * states,
        "bridge received {received} of {states}\n{d}"
    );
    assert_eq!(
        published, received,
        "a valid state was not published to chunkrt\n{d}"
    );
    // one command per robot state (the controller's answers), reliable on the way back
    assert!(
        sent >= 0.9 * published,
        "bridge sent {sent} commands for {published} states\n{d}"
    );
    assert!(
        commands >= 0.95 * sent,
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
    assert!(r.p("chunks_seen") >= 1.0, "no predicted chunk on ROS 2\n{d}");
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
