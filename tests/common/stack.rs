//! The process stack of the end-to-end tests: `chunkrt` subcommands as child processes (one at
//! a time: the tests share two cores), and a watcher of the robot's services in the test
//! process itself.

#![allow(dead_code)]

use std::time::{Duration, Instant};

use chunkrt_ipc::services::{self, Ipc};
use chunkrt_ipc::{monotonic_ns, ControllerStatus, JointCommand, JointState, Namespace};
use chunkrt_tools::testing::ChildGuard;
use iceoryx2::prelude::*;

pub const EXE: &str = env!("CARGO_BIN_EXE_chunkrt");

/// The process tests share two cores: one at a time, so rate assertions measure chunkrt and
/// not the other tests.
pub static SERIAL: std::sync::Mutex<()> = std::sync::Mutex::new(());

pub fn serial() -> std::sync::MutexGuard<'static, ()> {
    SERIAL.lock().unwrap_or_else(|e| e.into_inner())
}

pub fn start(sub: &str, ns: &str, extra: &[&str]) -> ChildGuard {
    let mut args = vec![sub, "--namespace", ns];
    args.extend_from_slice(extra);
    ChildGuard::spawn(EXE, &args).expect("spawn chunkrt")
}

/// Holding without a policy: STARTING (generator initialised, no chunk yet) or HOLD.
pub fn holding(s: &ControllerStatus) -> bool {
    s.seq > 0
        && (s.state == chunkrt_ipc::CONTROLLER_STATE_STARTING
            || s.state == chunkrt_ipc::CONTROLLER_STATE_HOLD)
}

/// The newest status says RUNNING.
pub fn running(w: &Watch) -> bool {
    w.last_status.state == chunkrt_ipc::CONTROLLER_STATE_RUNNING
}

/// SIGKILL: the process gets no chance to clean up its iceoryx2 resources.
pub fn kill9(g: ChildGuard) {
    // SAFETY: kill(2) on our own child.
    unsafe { libc::kill(g.id() as libc::pid_t, libc::SIGKILL) };
    drop(g);
}

/// A valid-looking command from a rogue publisher: shoulder to 2.5 rad, live for 50 ms.
pub fn rogue_command(seq: u64, n_dof: u32) -> JointCommand {
    let now = monotonic_ns();
    let mut c = JointCommand {
        seq,
        publish_time_ns: now,
        deadline_ns: now + 50_000_000,
        n_dof,
        mode: chunkrt_ipc::COMMAND_MODE_POSITION,
        ..Default::default()
    };
    c.position[0] = 2.5;
    c
}

/// Waits until `server` (a child process) accepts connections on 127.0.0.1:`port`, up to 30 s;
/// fails at once, by name, if it exits first. A fixed sleep instead raced a Python server's
/// first start on a fresh machine (its imports compiled cold, a busy loop beside it).
pub fn wait_listening(port: u16, server: &mut ChildGuard, what: &str) {
    let t0 = Instant::now();
    while std::net::TcpStream::connect(("127.0.0.1", port)).is_err() {
        assert!(
            server.running(),
            "{what} exited before it listened on {port}"
        );
        assert!(
            t0.elapsed() < Duration::from_secs(30),
            "{what}: nothing listened on {port} after 30 s"
        );
        std::thread::sleep(Duration::from_millis(50));
    }
}

/// Receives everything the test needs to watch, from the test process itself.
pub struct Watch {
    pub _node: Node<Ipc>,
    pub status: iceoryx2::port::subscriber::Subscriber<Ipc, ControllerStatus, ()>,
    pub js: iceoryx2::port::subscriber::Subscriber<Ipc, JointState, ()>,
    pub cmd: iceoryx2::port::subscriber::Subscriber<Ipc, JointCommand, ()>,
    pub last_status: ControllerStatus,
    /// The robot's newest joint-state seq seen when `last_status` arrived (aligns windows).
    pub js_seq_at_status: u64,
    pub last_js: JointState,
    pub commands: Vec<JointCommand>,
    /// The iceoryx2 publisher of each of `commands`.
    pub origins: Vec<u128>,
    /// Statuses from this publisher are not the controller's (a forger the test runs itself).
    pub ignore_status_from: u128,
}

impl Watch {
    pub fn new(ns: &str) -> Self {
        let ns = Namespace::new(ns).unwrap();
        let node = services::node(&format!("test-watch-{}", std::process::id())).unwrap();
        let status =
            services::subscriber(&services::status_service(&node, &ns.status()).unwrap()).unwrap();
        let js =
            services::subscriber(&services::joint_state_service(&node, &ns.joint_state()).unwrap())
                .unwrap();
        let cmd = services::subscriber(
            &services::joint_command_service(&node, &ns.joint_command()).unwrap(),
        )
        .unwrap();
        Self {
            _node: node,
            status,
            js,
            cmd,
            last_status: ControllerStatus::default(),
            js_seq_at_status: 0,
            last_js: JointState::default(),
            commands: Vec::new(),
            origins: Vec::new(),
            ignore_status_from: 0,
        }
    }

    /// Polls every ~0.5 ms for `d`.
    pub fn pump(&mut self, d: Duration) {
        let t0 = Instant::now();
        while t0.elapsed() < d {
            while let Ok(Some(s)) = self.js.receive() {
                self.last_js = *s.payload();
            }
            while let Ok(Some(s)) = self.status.receive() {
                if s.origin().value() == self.ignore_status_from {
                    continue;
                }
                self.last_status = *s.payload();
                self.js_seq_at_status = self.last_js.seq;
            }
            while let Ok(Some(s)) = self.cmd.receive() {
                self.commands.push(*s.payload());
                self.origins.push(s.origin().value());
            }
            std::thread::sleep(Duration::from_micros(500));
        }
    }

    pub fn wait_for(&mut self, timeout: Duration, what: &str, mut f: impl FnMut(&Self) -> bool) {
        let t0 = Instant::now();
        while !f(self) {
            assert!(
                t0.elapsed() < timeout,
                "timed out waiting for {what} (the last status: state {} reason {} chunks {} \
                 holds {} stale cameras {} inference {:.0} ms)",
                self.last_status.state,
                chunkrt_ipc::state_reason_name(self.last_status.state_reason),
                self.last_status.chunks,
                self.last_status.hold_entries,
                self.last_status.stale_cameras,
                self.last_status.last_inference_latency_ns as f64 / 1e6
            );
            self.pump(Duration::from_millis(20));
        }
    }
}
