//! The bridge process: ROS 2 topics on one side, chunkrt's services on the other ([`crate`]).
//!
//! One thread owns every port (iceoryx2's are not thread-safe, RustDDS does its networking on
//! threads of its own) and sleeps in one `epoll` on the joint state reader, the reader that
//! watches the command topic, and (with `[control] clock = "robot"`) the controller's command
//! event. The controller's control tick talks to it through iceoryx2 only.

use std::sync::atomic::Ordering;
use std::time::Duration;

use anyhow::Context as _;
use chunkrt_ipc::services::{self, Ipc};
use chunkrt_ipc::*;
use chunkrt_tools::common::{end_time_ns, open_node, CommonArgs};
use chunkrt_tools::intake::CommandIntake;
use chunkrt_tools::shutdown;
use hdrhistogram::Histogram;
use iceoryx2::port::listener::Listener;
use iceoryx2::port::notifier::Notifier;
use iceoryx2::port::publisher::Publisher as IoxPublisher;
use iceoryx2::port::subscriber::Subscriber as IoxSubscriber;
use iceoryx2::prelude::FileDescriptorBased;
use mio::{Events, Interest, Poll, Token};
use ros2_client::{
    Context, ContextOptions, MessageTypeName, Name, NodeName, NodeOptions, Publisher, QosProfile,
    Subscription,
};

use crate::boundary::{ErrorCounters, ErrorKind, JointMap};
use crate::config::{BridgeConfig, CommandMode, QosKind, SendOn, StampSource};
use crate::{camera, msg};

/// Status silence after which another controller may bind the robot's session (as fake-robot).
const SESSION_TIMEOUT_NS: u64 = 500_000_000;
/// Samples taken from one reader per wake-up: a flood is drained over several wake-ups instead
/// of starving the other readers.
const MAX_TAKE_PER_WAKE: usize = 64;
/// A command from another publisher on the command topic holds the bridge for this long (ns).
const FOREIGN_HOLD_NS: u64 = 1_000_000_000;

const TOKEN_STATES: Token = Token(0);
const TOKEN_ECHO: Token = Token(1);
const TOKEN_COMMAND_EVENT: Token = Token(2);

/// Command-line arguments.
#[derive(Debug, Clone, clap::Args)]
pub struct Args {
    #[command(flatten)]
    pub common: CommonArgs,
    /// The DDS domain (`ROS_DOMAIN_ID`), overriding `ros2.domain_id` and the environment.
    #[arg(long, value_name = "ID")]
    pub domain_id: Option<u16>,
    /// Stop after this many seconds (default: until SIGINT / SIGTERM).
    #[arg(long, value_name = "SECONDS")]
    pub duration: Option<f64>,
    /// Print a status line (`ros2 status: ...`) every this many seconds (0: none).
    #[arg(long, value_name = "SECONDS", default_value_t = 0.0)]
    pub status_every: f64,
}

/// What the bridge counted, printed on exit (`ros2 summary: key=value ...`).
#[derive(Debug, Clone, Default)]
pub struct Summary {
    /// `JointState`s taken from the robot's topic.
    pub states_received: u64,
    /// Joint states published to chunkrt (the received ones that passed the checks).
    pub states_published: u64,
    /// Commands published on the ROS 2 command topic from the controller's commands.
    pub commands_sent: u64,
    /// Hold commands published (no live controller command: the last position sent, again).
    pub holds_sent: u64,
    /// Gripper commands published on `gripper_topic` (on change).
    pub gripper_sent: u64,
    /// Commands the intake accepted / refused (session, order, deadline, bumpless rule).
    pub commands_applied: u64,
    pub commands_rejected: u64,
    pub commands_expired: u64,
    pub commands_unbound: u64,
    pub commands_far: u64,
    /// Commands whose position was clamped into the configured joint limits.
    pub clamped: u64,
    /// Controller statuses and chunks republished on ROS 2.
    pub statuses_out: u64,
    pub chunks_out: u64,
    /// Robot state received → the command answering it published (µs): p50, p99, max, count.
    pub latency_p50_us: f64,
    pub latency_p99_us: f64,
    pub latency_max_us: f64,
    pub latency_count: u64,
    /// Every boundary error, by kind.
    pub errors: ErrorCounters,
    /// The bridge's CPU time over its run time (both threads of RustDDS included).
    pub cpu_share: f64,
    /// The process's peak resident memory (kB).
    pub max_rss_kb: u64,
    /// Camera frames published to chunkrt (all cameras), and images taken but superseded by a
    /// newer one in the same wake-up (newest only).
    pub frames_out: u64,
    pub frames_superseded: u64,
    /// An image's age when its frame was published (its stamp to the frame, µs): p50, p99.
    pub frame_age_p50_us: f64,
    pub frame_age_p99_us: f64,
    /// chunkrt's own hop in the same run: joint state published on iceoryx2 -> the command
    /// answering it received on iceoryx2 (µs), p50 and p99.
    pub iox_p50_us: f64,
    pub iox_p99_us: f64,
}

impl std::fmt::Display for Summary {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(
            f,
            "ros2 summary: states_received={} states_published={} commands_sent={} \
             holds_sent={} gripper_sent={} commands_applied={} commands_rejected={} commands_expired={} \
             commands_unbound={} commands_far={} clamped={} statuses_out={} chunks_out={} \
             latency_p50_us={:.1} latency_p99_us={:.1} latency_max_us={:.1} latency_count={} \
             cpu_share={:.3} max_rss_kb={} frames_out={} frames_superseded={} \
             frame_age_p50_us={:.1} frame_age_p99_us={:.1} iox_p50_us={:.1} iox_p99_us={:.1} {}",
            self.states_received,
            self.states_published,
            self.commands_sent,
            self.holds_sent,
            self.gripper_sent,
            self.commands_applied,
            self.commands_rejected,
            self.commands_expired,
            self.commands_unbound,
            self.commands_far,
            self.clamped,
            self.statuses_out,
            self.chunks_out,
            self.latency_p50_us,
            self.latency_p99_us,
            self.latency_max_us,
            self.latency_count,
            self.cpu_share,
            self.max_rss_kb,
            self.frames_out,
            self.frames_superseded,
            self.frame_age_p50_us,
            self.frame_age_p99_us,
            self.iox_p50_us,
            self.iox_p99_us,
            self.errors.summary(),
        )
    }
}

/// Runs until SIGINT / SIGTERM or `--duration`; prints the [`Summary`] on stdout.
pub fn run(args: Args) -> anyhow::Result<()> {
    let summary = bridge(&args)?;
    println!("{summary}");
    Ok(())
}

/// `CLOCK_REALTIME` in ns (what ROS 2 stamps with).
pub fn realtime_ns() -> u64 {
    let mut ts = libc::timespec {
        tv_sec: 0,
        tv_nsec: 0,
    };
    // SAFETY: a valid timespec to write into
    unsafe { libc::clock_gettime(libc::CLOCK_REALTIME, &mut ts) };
    (ts.tv_sec.max(0) as u64) * 1_000_000_000 + ts.tv_nsec.max(0) as u64
}

/// The process's peak resident memory (kB).
fn max_rss_kb() -> u64 {
    // SAFETY: getrusage writes into the zeroed struct it is given
    let mut u: libc::rusage = unsafe { std::mem::zeroed() };
    // SAFETY: a valid rusage to write into
    if unsafe { libc::getrusage(libc::RUSAGE_SELF, &mut u) } == 0 {
        u.ru_maxrss.max(0) as u64
    } else {
        0
    }
}

/// The process's CPU time (ns).
fn cpu_ns() -> u64 {
    let mut ts = libc::timespec {
        tv_sec: 0,
        tv_nsec: 0,
    };
    // SAFETY: a valid timespec to write into
    unsafe { libc::clock_gettime(libc::CLOCK_PROCESS_CPUTIME_ID, &mut ts) };
    (ts.tv_sec.max(0) as u64) * 1_000_000_000 + ts.tv_nsec.max(0) as u64
}

fn qos(kind: QosKind) -> QosProfile {
    match kind {
        // rclcpp's SensorDataQoS: best effort, keep last 5, volatile
        QosKind::SensorData => QosProfile::subscription_default()
            .reliability_best_effort()
            .durability(ros2_client::qos::Durability::Volatile)
            .history(ros2_client::qos::History::KeepLast { depth: 5 }),
        // ROS 2's default: reliable, keep last 10, volatile; a full writer drops, never blocks
        QosKind::Reliable => QosProfile::subscription_default()
            .reliability_reliable(ros2_client::qos::WhenFull::Wait(Duration::ZERO))
            .durability(ros2_client::qos::Durability::Volatile)
            .history(ros2_client::qos::History::KeepLast { depth: 10 }),
    }
}

fn topic_name(t: &str) -> anyhow::Result<Name> {
    Name::parse(t).map_err(|e| anyhow::anyhow!("ROS 2 topic {t:?}: {e:?}"))
}

/// The command publisher of either mode.
enum CommandOut {
    Forward(Publisher<msg::Float64MultiArray>),
    Trajectory(Publisher<msg::JointTrajectory>),
}

/// The reader on the command topic that spots other publishers on it.
enum CommandEcho {
    Forward(Subscription<msg::Float64MultiArray>),
    Trajectory(Subscription<msg::JointTrajectory>),
}

/// One camera's ROS 2 reader.
enum CamSub {
    Raw(Subscription<msg::Image>),
    Compressed(Subscription<msg::CompressedImage>),
}

/// One camera: its ROS 2 reader and its chunkrt publisher.
struct Camera {
    name: String,
    id: u32,
    max_w: u32,
    max_h: u32,
    sub: CamSub,
    publisher: IoxPublisher<Ipc, [u8], CameraFrameHeader>,
    seq: u64,
}

/// Compressed images larger than this many times the camera's raw size are refused unread.
const COMPRESSED_CAP_FACTOR: usize = 2;

/// The iceoryx2 side.
struct Iox {
    state_pub: IoxPublisher<Ipc, JointState, ()>,
    cmd_sub: IoxSubscriber<Ipc, JointCommand, ()>,
    status_sub: IoxSubscriber<Ipc, ControllerStatus, ()>,
    chunk_sub: IoxSubscriber<Ipc, ActionChunkMsg, ()>,
    state_event: Option<Notifier<Ipc>>,
    cmd_event: Option<Listener<Ipc>>,
}

/// The whole bridge's state between wake-ups.
struct Bridge {
    cfg: BridgeConfig,
    n: usize,
    map: JointMap,
    intake: CommandIntake,
    errors: ErrorCounters,
    summary: Summary,
    hist: Histogram<u64>,
    frame_hist: Histogram<u64>,
    /// Last joint state published to chunkrt.
    seq: u64,
    measured: [f64; MAX_DOF],
    have_state: bool,
    last_state_ns: u64,
    peer_silent: bool,
    /// (seq, receive time, time published to chunkrt) of the last few states, to time the
    /// answers.
    recent: [(u64, u64, u64); 16],
    /// chunkrt's own hop: joint state published on iceoryx2 -> its command received (ns).
    iox_hist: Histogram<u64>,
    /// The newest robot state whose command's arrival was timed.
    last_iox_timed: u64,
    /// The last position sent on ROS 2 (what a hold repeats).
    last_sent: Option<[f64; MAX_DOF]>,
    /// Seq of the last controller command sent.
    last_cmd_seq: u64,
    /// The newest robot state whose answer was timed.
    last_timed_state: u64,
    /// The newest robot state a command sent answered.
    last_answered_state: u64,
    holding: bool,
    clamped_flag: bool,
    foreign_until: u64,
    out: CommandOut,
    out_gid: ros2_client::Gid,
    status_out: Option<Publisher<msg::StringMsg>>,
    chunk_out: Option<Publisher<msg::JointTrajectory>>,
    robot_clock: bool,
    lead_ns: u64,
    skew_ns: u64,
    silence_ns: u64,
    state_max_age_ns: u64,
    frame_max_age_ns: u64,
    limits: [(f64, f64); MAX_DOF],
    /// Joints commanded on the arm's topic, and (with `gripper_topic`) on the gripper's.
    arm: Vec<usize>,
    gripper: Vec<usize>,
    gripper_out: Option<Publisher<msg::Float64MultiArray>>,
    gripper_sent: Option<Vec<f64>>,
}

impl Bridge {
    /// One `JointState` from the robot, received at `now`.
    fn on_state(&mut self, m: &msg::JointState, now: u64, iox: &Iox) {
        self.summary.states_received += 1;
        let matched = match self.map.map(m) {
            Ok(v) => v,
            Err(e) => {
                let names = self.map.names().to_vec();
                self.errors.count(e.kind(), now, || e.describe(&names, m));
                return;
            }
        };
        let t = self.stamp_time(&m.header.stamp, now, "JointState", self.state_max_age_ns);
        if self.peer_silent {
            tracing::info!("ros2: the robot's joint states are back");
            self.peer_silent = false;
        }
        self.last_state_ns = now;
        self.measured = matched.position;
        self.have_state = true;
        self.seq += 1;
        self.recent[(self.seq % 16) as usize] = (self.seq, now, 0);
        let mut flags = self.intake.flags(now);
        if self.holding || self.intake.live(now).is_none() {
            flags |= JOINT_STATUS_HOLDING;
        }
        if self.clamped_flag {
            flags |= JOINT_STATUS_LIMIT_CLAMPED;
        }
        if now < self.foreign_until {
            // another node commands the arm: this controller's commands are not what it does
            flags |= JOINT_STATUS_NOT_FOLLOWING | JOINT_STATUS_HOLDING;
        }
        let mut js = JointState {
            seq: self.seq,
            measurement_time_ns: t,
            n_dof: self.n as u32,
            status_flags: flags,
            position: matched.position,
            velocity: matched.velocity,
            effort: matched.effort,
            ..Default::default()
        };
        js.set_obeyed_publisher(self.intake.obeyed_publisher(now));
        let sent = match iox.state_pub.loan_uninit() {
            Ok(s) => s.write_payload(js).send().is_ok(),
            Err(_) => false,
        };
        if sent {
            self.summary.states_published += 1;
            self.recent[(self.seq % 16) as usize].2 = monotonic_ns();
            if let Some(ev) = &iox.state_event {
                if ev.notify().is_err() {
                    self.errors.count(ErrorKind::PublishFailed, now, || {
                        "notifying the controller of a joint state failed".into()
                    });
                }
            }
        } else {
            self.errors.count(ErrorKind::PublishFailed, now, || {
                "publishing a joint state to chunkrt failed".into()
            });
        }
    }

    /// The monotonic time of a message stamped `stamp` and received at `now` (the receive time
    /// for a zero stamp, with `stamp = "receive"`, or a stamp too far ahead: counted).
    fn stamp_time(&mut self, stamp: &msg::Time, now: u64, what: &str, max_age_ns: u64) -> u64 {
        if self.cfg.ros2.stamp != StampSource::Header {
            return now;
        }
        let Some(stamp) = stamp.as_ns().filter(|s| *s > 0) else {
            return now;
        };
        let real = realtime_ns();
        if stamp > real.saturating_add(self.skew_ns) {
            self.errors.count(ErrorKind::StampSkew, now, || {
                format!(
                    "{what} stamped {:.3} ms ahead of this machine's clock: the receive time is \
                     used",
                    (stamp - real) as f64 / 1e6
                )
            });
            return now;
        }
        let age = real.saturating_sub(stamp);
        if age > max_age_ns {
            // the controller will find it stale and hold: say why here (a message late on the
            // way, a loaded machine, or a robot clock behind this one's: counted apart from a
            // stamp ahead, which only a clock can cause)
            self.errors.count(ErrorKind::StaleArrival, now, || {
                format!(
                    "{what} stamped {:.1} ms in the past, older than the controller accepts: late \
                     on the way, or the robot's clock is behind this machine's (if every message \
                     is, synchronise the clocks or set ros2.stamp = \"receive\")",
                    age as f64 / 1e6
                )
            });
        }
        // the stamp's age on the system clock, taken off the monotonic receive time
        now.saturating_sub(age)
    }

    /// Takes each camera's images: the newest valid one of this wake-up becomes a frame.
    fn take_images(&mut self, cams: &mut [Camera]) {
        for cam in cams.iter_mut() {
            let mut newest: Option<(msg::Header, camera::Packed, Option<Vec<u8>>, msg::Image)> =
                None;
            for _ in 0..MAX_TAKE_PER_WAKE {
                let now = monotonic_ns();
                let got = match &cam.sub {
                    CamSub::Raw(s) => match s.take() {
                        Ok(Some((m, _))) => Some(
                            camera::check_image(&m, cam.max_w, cam.max_h)
                                .map(|p| (m.header.clone(), p, None, m)),
                        ),
                        Ok(None) => None,
                        Err(e) => Some(Err(camera::ImageError::Decode(format!("{e:?}")))),
                    },
                    CamSub::Compressed(s) => match s.take() {
                        Ok(Some((m, _))) => {
                            let cap =
                                cam.max_w as usize * cam.max_h as usize * 3 * COMPRESSED_CAP_FACTOR;
                            Some(
                                camera::decode(&m, cam.max_w, cam.max_h, cap).map(|(p, px)| {
                                    (m.header.clone(), p, Some(px), msg::Image::default())
                                }),
                            )
                        }
                        Ok(None) => None,
                        Err(e) => Some(Err(camera::ImageError::Decode(format!("{e:?}")))),
                    },
                };
                match got {
                    None => break,
                    Some(Ok(v)) => {
                        if newest.is_some() {
                            self.summary.frames_superseded += 1;
                        }
                        newest = Some(v);
                    }
                    Some(Err(e)) => {
                        let name = cam.name.clone();
                        self.errors.count(ErrorKind::ImageRejected, now, || {
                            format!("camera {name}: an image refused: {e}")
                        });
                    }
                }
            }
            let Some((header, p, decoded, raw)) = newest else {
                continue;
            };
            let now = monotonic_ns();
            let capture = self.stamp_time(&header.stamp, now, "Image", self.frame_max_age_ns);
            match cam.publisher.loan_slice(p.len()) {
                Ok(mut sample) => {
                    match &decoded {
                        Some(px) => sample.payload_mut().copy_from_slice(&px[..p.len()]),
                        None => camera::pack(&raw, &p, sample.payload_mut()),
                    }
                    cam.seq += 1;
                    *sample.user_header_mut() = CameraFrameHeader {
                        seq: cam.seq,
                        capture_time_ns: capture,
                        publish_time_ns: monotonic_ns(),
                        camera_id: cam.id,
                        encoding: p.encoding,
                        width: p.width,
                        height: p.height,
                        stride: p.width * p.bpp,
                        reserved: 0,
                    };
                    if sample.send().is_ok() {
                        self.summary.frames_out += 1;
                        if let Some(stamp) = header.stamp.as_ns().filter(|s| *s > 0) {
                            let age = realtime_ns().saturating_sub(stamp);
                            self.frame_hist.saturating_record(age.max(1));
                        }
                    } else {
                        self.errors.count(ErrorKind::PublishFailed, now, || {
                            format!("publishing a frame of camera {} failed", cam.name)
                        });
                    }
                }
                Err(e) => {
                    self.errors.count(ErrorKind::PublishFailed, now, || {
                        format!("loaning a frame of camera {}: {e:?}", cam.name)
                    });
                }
            }
        }
    }

    /// Takes the controller's statuses and commands from iceoryx2.
    fn take_commands(&mut self, iox: &Iox) -> bool {
        while let Ok(Some(s)) = iox.status_sub.receive() {
            let now = monotonic_ns();
            self.intake.on_status(s.payload(), s.origin().value(), now);
            if let Some(p) = &self.status_out {
                let st = s.payload();
                let line = format!(
                    "state={} reason={:?} ticks={} overruns={} chunks={} joint_states={} \
                     hold_entries={} rejected={:?}",
                    controller_state_name(st.state),
                    state_reason_name(st.state_reason),
                    st.ticks,
                    st.overruns,
                    st.chunks,
                    st.joint_states,
                    st.hold_entries,
                    st.rejected
                );
                if p.publish(msg::StringMsg { data: line }).is_ok() {
                    self.summary.statuses_out += 1;
                }
            }
        }
        let mut fresh = false;
        loop {
            match iox.cmd_sub.receive() {
                Ok(Some(s)) => {
                    let now = monotonic_ns();
                    let st = s.payload().state_seq;
                    if st > self.last_iox_timed {
                        let (seq, _, published) = self.recent[(st % 16) as usize];
                        if seq == st && published > 0 {
                            self.iox_hist
                                .saturating_record(now.saturating_sub(published).max(1));
                        }
                        self.last_iox_timed = st;
                    }
                    let before = self.intake.counters.commands_applied;
                    let n = self.n;
                    self.intake.on_command(
                        s.payload(),
                        s.origin().value(),
                        now,
                        &self.measured[..n],
                    );
                    if self.intake.counters.commands_applied > before {
                        fresh = true;
                    }
                }
                Ok(None) => break,
                Err(e) => {
                    self.errors
                        .count(ErrorKind::CommandRefused, monotonic_ns(), || {
                            format!("receiving the controller's command failed: {e:?}")
                        });
                    break;
                }
            }
        }
        fresh
    }

    /// Republishes the controller's predicted chunks as `JointTrajectory`s.
    fn take_chunks(&mut self, iox: &Iox) {
        while let Ok(Some(s)) = iox.chunk_sub.receive() {
            let Some(p) = &self.chunk_out else { continue };
            let c = s.payload();
            let h = (c.horizon as usize).min(MAX_CHUNK_HORIZON);
            let n = (c.n_dof as usize).min(self.n);
            let now_mono = monotonic_ns();
            // the observation's time on the system clock
            let obs_real = realtime_ns()
                .saturating_sub(now_mono.saturating_sub(c.observation_time_ns))
                .saturating_add(c.start_shift_ns);
            let traj = msg::JointTrajectory {
                header: msg::Header {
                    stamp: msg::Time::from_ns(obs_real),
                    frame_id: format!("chunk_{}", c.chunk_id),
                },
                joint_names: self.map.names()[..n].to_vec(),
                points: (0..h)
                    .map(|i| msg::JointTrajectoryPoint {
                        positions: c.actions[i][..n].to_vec(),
                        time_from_start: msg::Duration::from_ns(
                            c.period_ns.saturating_mul(i as u64),
                        ),
                        ..Default::default()
                    })
                    .collect(),
            };
            if p.publish(traj).is_ok() {
                self.summary.chunks_out += 1;
            }
        }
    }

    /// Publishes `position` (clamped into the limits) on the command topic.
    fn publish(&mut self, cmd: &JointCommand, now: u64) -> bool {
        let n = self.n;
        let mut pos = [0.0; MAX_DOF];
        let mut clamped = false;
        for ((p, &(lo, hi)), &v) in pos.iter_mut().zip(&self.limits).zip(&cmd.position).take(n) {
            let c = v.clamp(lo, hi);
            clamped |= c != v;
            *p = c;
        }
        if clamped {
            self.summary.clamped += 1;
        }
        self.clamped_flag = clamped;
        let arm_pos: Vec<f64> = self.arm.iter().map(|&j| pos[j]).collect();
        let ok = match &self.out {
            CommandOut::Forward(p) => p
                .publish(msg::Float64MultiArray {
                    layout: msg::MultiArrayLayout::default(),
                    data: arm_pos,
                })
                .is_ok(),
            CommandOut::Trajectory(p) => {
                let hold = cmd.mode == COMMAND_MODE_HOLD;
                p.publish(msg::JointTrajectory {
                    // a zero stamp: start at once
                    header: msg::Header::default(),
                    joint_names: self
                        .arm
                        .iter()
                        .map(|&j| self.map.names()[j].clone())
                        .collect(),
                    points: vec![msg::JointTrajectoryPoint {
                        positions: arm_pos,
                        velocities: self
                            .arm
                            .iter()
                            .map(|&j| if hold { 0.0 } else { cmd.velocity[j] })
                            .collect(),
                        time_from_start: msg::Duration::from_ns(self.lead_ns),
                        ..Default::default()
                    }],
                })
                .is_ok()
            }
        };
        if let Some(g) = &self.gripper_out {
            let grip: Vec<f64> = self.gripper.iter().map(|&j| pos[j]).collect();
            if self.gripper_sent.as_ref() != Some(&grip) {
                if g.publish(msg::Float64MultiArray {
                    layout: msg::MultiArrayLayout::default(),
                    data: grip.clone(),
                })
                .is_ok()
                {
                    self.gripper_sent = Some(grip);
                    self.summary.gripper_sent += 1;
                } else {
                    self.errors.count(ErrorKind::PublishFailed, now, || {
                        "publishing a gripper command on ROS 2 failed".into()
                    });
                }
            }
        }
        if !ok {
            self.errors.count(ErrorKind::PublishFailed, now, || {
                "publishing a command on ROS 2 failed".into()
            });
            return false;
        }
        self.last_sent = Some(pos);
        true
    }

    /// Sends the controller's newest live command if it is new, else (no live command) the hold.
    /// `on_state`: called for a received robot state (sends at most one command per state).
    fn send(&mut self, now: u64, on_state: bool) {
        if now < self.foreign_until {
            return;
        }
        if let Some(cmd) = self.intake.live(now).copied() {
            let new = cmd.seq != self.last_cmd_seq;
            if !(new || on_state) {
                return;
            }
            if !on_state
                && self.robot_clock
                && self.cfg.ros2.send == SendOn::State
                && cmd.state_seq <= self.last_answered_state
            {
                // one command per robot state: a timer tick's command while the robot is quiet
                // answers no new state
                return;
            }
            if self.holding {
                tracing::info!("ros2: following the controller's commands");
                self.holding = false;
            }
            if self.publish(&cmd, now) {
                self.last_cmd_seq = cmd.seq;
                self.last_answered_state = self.last_answered_state.max(cmd.state_seq);
                self.summary.commands_sent += 1;
                // timed once per robot state: its first answer (a timer tick's command for an
                // older state answers nothing new)
                if cmd.state_seq > self.last_timed_state {
                    let (seq, at, _) = self.recent[(cmd.state_seq % 16) as usize];
                    if seq == cmd.state_seq {
                        self.hist.saturating_record(now.saturating_sub(at).max(1));
                    }
                    self.last_timed_state = cmd.state_seq;
                }
            }
        } else if on_state {
            if !self.holding {
                self.holding = true;
                self.intake.disarm();
                if self.last_sent.is_some() {
                    tracing::info!(
                        "ros2: no live command from the controller: holding at the last position \
                         sent"
                    );
                }
            }
            if let Some(pos) = self.last_sent {
                let hold = JointCommand {
                    mode: COMMAND_MODE_HOLD,
                    position: pos,
                    ..Default::default()
                };
                if self.publish(&hold, now) {
                    self.summary.holds_sent += 1;
                }
            }
        }
    }

    fn on_echo(&mut self, gid: ros2_client::Gid, now: u64) {
        if gid == self.out_gid {
            return;
        }
        if now >= self.foreign_until {
            tracing::warn!(
                "ros2: another publisher ({gid:?}) commands {}: holding (not sending) until it \
                 has been quiet for {} ms",
                self.cfg.ros2.command_topic,
                FOREIGN_HOLD_NS / 1_000_000
            );
            self.intake.disarm();
        }
        self.errors.count(ErrorKind::ForeignCommander, now, || {
            format!(
                "a command on {} from publisher {gid:?}, not this bridge",
                self.cfg.ros2.command_topic
            )
        });
        self.foreign_until = now + FOREIGN_HOLD_NS;
    }

    fn check_silence(&mut self, now: u64) {
        if self.have_state
            && !self.peer_silent
            && now.saturating_sub(self.last_state_ns) > self.silence_ns
        {
            self.peer_silent = true;
            let ms = self.silence_ns as f64 / 1e6;
            let topic = self.cfg.ros2.joint_states_topic.clone();
            self.errors.count(ErrorKind::PeerSilent, now, || {
                format!(
                    "no valid joint state on {topic} for {ms} ms: the robot is gone or silent \
                     (the controller holds on stale states)"
                )
            });
        }
    }
}

/// The whole process: returns the counters instead of printing them.
pub fn bridge(args: &Args) -> anyhow::Result<Summary> {
    let stop = shutdown::flag();
    let (shared, ns) = args.common.load()?;
    let mut cfg = match &args.common.config {
        Some(path) => {
            let text = chunkrt_ipc::config::read_config_file(path)?;
            BridgeConfig::from_parts(shared, &text, &path.display().to_string())?
        }
        None => {
            let text = chunkrt_ipc::config::DEFAULT_TOML;
            BridgeConfig::from_parts(shared, text, "config/default.toml (embedded)")?
        }
    };
    if let Some(d) = args.domain_id {
        anyhow::ensure!(d <= 232, "--domain-id {d}: must be in 0..=232");
        cfg.ros2.domain_id = Some(d);
    }
    let domain = cfg.ros2.domain().map_err(anyhow::Error::msg)?;
    let n = cfg.shared.n_dof();
    let robot_clock = cfg.shared.control.clock == chunkrt_ipc::config::ControlClock::Robot;

    // chunkrt's side
    let node = open_node("chunkrt-ros2")?;
    let state_name = ns.joint_state();
    let cmd_name = ns.joint_command();
    let status_name = ns.status();
    let chunk_name = ns.chunks();
    let state_service = services::joint_state_service(&node, &state_name)?;
    let cmd_service = services::joint_command_service(&node, &cmd_name)?;
    let iox = Iox {
        state_pub: services::publisher(&state_service)?,
        cmd_sub: services::subscriber(&cmd_service)?,
        status_sub: services::subscriber(&services::status_service(&node, &status_name)?)?,
        chunk_sub: services::subscriber(&services::chunk_service(&node, &chunk_name)?)?,
        state_event: if robot_clock {
            let ev = services::event_service(&node, &state_name)?;
            Some(services::notifier(&ev)?)
        } else {
            None
        },
        cmd_event: if robot_clock {
            let ev = services::event_service(&node, &cmd_name)?;
            Some(services::listener(&ev)?)
        } else {
            None
        },
    };

    // ROS 2's side
    let r = &cfg.ros2;
    let context = Context::with_options(ContextOptions::new().domain_id(domain))
        .map_err(|e| anyhow::anyhow!("DDS domain {domain}: {e:?}"))?;
    let mut ros = context
        .new_node(
            NodeName::new("/", &r.node_name)
                .map_err(|e| anyhow::anyhow!("ros2.node_name: {e:?}"))?,
            NodeOptions::new().enable_rosout(false),
        )
        .map_err(|e| anyhow::anyhow!("creating the ROS 2 node: {e:?}"))?;
    let (pkg, ty) = msg::types::JOINT_STATE;
    let state_topic = ros
        .create_topic(
            &topic_name(&r.joint_states_topic)?,
            MessageTypeName::new(pkg, ty),
            &qos(r.state_qos),
        )
        .map_err(|e| anyhow::anyhow!("{}: {e:?}", r.joint_states_topic))?;
    let mut states: Subscription<msg::JointState> = ros
        .create_subscription(&state_topic, Some(qos(r.state_qos)))
        .map_err(|e| anyhow::anyhow!("{}: {e:?}", r.joint_states_topic))?;
    let (pkg, ty) = match r.command {
        CommandMode::Forward => msg::types::FLOAT64_MULTI_ARRAY,
        CommandMode::Trajectory => msg::types::JOINT_TRAJECTORY,
    };
    let cmd_topic = ros
        .create_topic(
            &topic_name(&r.command_topic)?,
            MessageTypeName::new(pkg, ty),
            &qos(r.command_qos),
        )
        .map_err(|e| anyhow::anyhow!("{}: {e:?}", r.command_topic))?;
    let cmd_err = |e| anyhow::anyhow!("{}: {e:?}", r.command_topic);
    let (out, mut echo) = match r.command {
        CommandMode::Forward => (
            CommandOut::Forward(
                ros.create_publisher(&cmd_topic, Some(qos(r.command_qos)))
                    .map_err(cmd_err)?,
            ),
            CommandEcho::Forward(
                ros.create_subscription(&cmd_topic, Some(qos(r.command_qos)))
                    .map_err(cmd_err)?,
            ),
        ),
        CommandMode::Trajectory => (
            CommandOut::Trajectory(
                ros.create_publisher(&cmd_topic, Some(qos(r.command_qos)))
                    .map_err(cmd_err)?,
            ),
            CommandEcho::Trajectory(
                ros.create_subscription(&cmd_topic, Some(qos(r.command_qos)))
                    .map_err(cmd_err)?,
            ),
        ),
    };
    let out_gid = match &out {
        CommandOut::Forward(p) => p.gid(),
        CommandOut::Trajectory(p) => p.gid(),
    };
    let status_out = if r.status_topic.is_empty() {
        None
    } else {
        let (pkg, ty) = msg::types::STRING;
        let t = ros
            .create_topic(
                &topic_name(&r.status_topic)?,
                MessageTypeName::new(pkg, ty),
                &qos(QosKind::Reliable),
            )
            .map_err(|e| anyhow::anyhow!("{}: {e:?}", r.status_topic))?;
        Some(
            ros.create_publisher(&t, Some(qos(QosKind::Reliable)))
                .map_err(|e| anyhow::anyhow!("{}: {e:?}", r.status_topic))?,
        )
    };
    let chunk_out = if r.chunk_topic.is_empty() {
        None
    } else {
        let (pkg, ty) = msg::types::JOINT_TRAJECTORY;
        let t = ros
            .create_topic(
                &topic_name(&r.chunk_topic)?,
                MessageTypeName::new(pkg, ty),
                &qos(QosKind::Reliable),
            )
            .map_err(|e| anyhow::anyhow!("{}: {e:?}", r.chunk_topic))?;
        Some(
            ros.create_publisher(&t, Some(qos(QosKind::Reliable)))
                .map_err(|e| anyhow::anyhow!("{}: {e:?}", r.chunk_topic))?,
        )
    };

    let mut cams = Vec::new();
    for rc in &r.cameras {
        let Some((id, sc)) = cfg
            .shared
            .cameras
            .iter()
            .enumerate()
            .find(|(_, c)| c.name == rc.name)
        else {
            anyhow::bail!("ros2.cameras: no [[cameras]] entry {:?}", rc.name);
        };
        let (pkg, ty) = if rc.compressed {
            msg::types::COMPRESSED_IMAGE
        } else {
            msg::types::IMAGE
        };
        let err = |e| anyhow::anyhow!("{}: {e:?}", rc.topic);
        let t = ros
            .create_topic(
                &topic_name(&rc.topic)?,
                MessageTypeName::new(pkg, ty),
                &qos(QosKind::SensorData),
            )
            .map_err(err)?;
        let sub = if rc.compressed {
            CamSub::Compressed(
                ros.create_subscription(&t, Some(qos(QosKind::SensorData)))
                    .map_err(err)?,
            )
        } else {
            CamSub::Raw(
                ros.create_subscription(&t, Some(qos(QosKind::SensorData)))
                    .map_err(err)?,
            )
        };
        let iox_name = ns.camera(&sc.name);
        let factory = services::camera_service(&node, &iox_name)?;
        let publisher =
            services::camera_publisher(&factory, sc.width as usize * sc.height as usize * 3)?;
        tracing::info!(
            "ros2: camera {} from {} ({}, up to {}x{}) → '{iox_name}'",
            sc.name,
            rc.topic,
            if rc.compressed {
                "CompressedImage"
            } else {
                "Image"
            },
            sc.width,
            sc.height
        );
        cams.push(Camera {
            name: sc.name.clone(),
            id: id as u32,
            max_w: sc.width,
            max_h: sc.height,
            sub,
            publisher,
            seq: 0,
        });
    }

    let mut poll = Poll::new().context("epoll")?;
    for (i, cam) in cams.iter_mut().enumerate() {
        let token = Token(10 + i);
        match &mut cam.sub {
            CamSub::Raw(s) => poll.registry().register(s, token, Interest::READABLE),
            CamSub::Compressed(s) => poll.registry().register(s, token, Interest::READABLE),
        }
        .context("registering a camera reader")?;
    }
    poll.registry()
        .register(&mut states, TOKEN_STATES, Interest::READABLE)
        .context("registering the joint state reader")?;
    match &mut echo {
        CommandEcho::Forward(s) => poll.registry().register(s, TOKEN_ECHO, Interest::READABLE),
        CommandEcho::Trajectory(s) => poll.registry().register(s, TOKEN_ECHO, Interest::READABLE),
    }
    .context("registering the command topic reader")?;
    if let Some(l) = &iox.cmd_event {
        // SAFETY: the descriptor stays owned by the listener, which outlives the poll; it is
        // only polled here, never closed or read
        let fd = unsafe { l.file_descriptor().native_handle() };
        poll.registry()
            .register(
                &mut mio::unix::SourceFd(&fd),
                TOKEN_COMMAND_EVENT,
                Interest::READABLE,
            )
            .context("registering the controller's command event")?;
    }

    let start = monotonic_ns();
    let end = end_time_ns(start, args.duration)?;
    let max_future_ns = (cfg.shared.control.max_future_ms * 1e6) as u64;
    let mut intake = CommandIntake::new(
        "ros2",
        n,
        (r.command_timeout_ms * 1e6) as u64,
        max_future_ns,
        start,
    );
    intake.bind_to_controller(SESSION_TIMEOUT_NS);
    intake.set_bind_tolerance(r.bind_tolerance);
    let mut limits = [(0.0, 0.0); MAX_DOF];
    for (l, j) in limits.iter_mut().zip(&cfg.shared.robot.joints) {
        *l = (j.position_min, j.position_max);
    }
    tracing::info!(
        "ros2: {n} joints {:?} from {} (DDS domain {domain}, {} QoS) → '{state_name}'; \
         '{cmd_name}' → {} ({}, {} QoS, one per {}){}",
        r.joints,
        r.joint_states_topic,
        r.state_qos,
        r.command_topic,
        r.command,
        r.command_qos,
        r.send,
        if robot_clock {
            "; the robot's states clock the controller"
        } else {
            ""
        }
    );
    let (arm, gripper): (Vec<usize>, Vec<usize>) = if r.gripper_topic.is_empty() {
        ((0..n).collect(), Vec::new())
    } else {
        (0..n).partition(|&j| !cfg.shared.robot.joints[j].step)
    };
    let gripper_out = if r.gripper_topic.is_empty() {
        None
    } else {
        let (pkg, ty) = msg::types::FLOAT64_MULTI_ARRAY;
        let t = ros
            .create_topic(
                &topic_name(&r.gripper_topic)?,
                MessageTypeName::new(pkg, ty),
                &qos(r.command_qos),
            )
            .map_err(|e| anyhow::anyhow!("{}: {e:?}", r.gripper_topic))?;
        Some(
            ros.create_publisher(&t, Some(qos(r.command_qos)))
                .map_err(|e| anyhow::anyhow!("{}: {e:?}", r.gripper_topic))?,
        )
    };
    let mut b = Bridge {
        n,
        map: JointMap::new(&r.joints),
        intake,
        errors: ErrorCounters::default(),
        summary: Summary::default(),
        hist: Histogram::new_with_bounds(1, 10_000_000_000, 3).context("histogram")?,
        frame_hist: Histogram::new_with_bounds(1, 100_000_000_000, 3).context("histogram")?,
        seq: 0,
        measured: [0.0; MAX_DOF],
        have_state: false,
        last_state_ns: start,
        peer_silent: false,
        recent: [(0, 0, 0); 16],
        iox_hist: Histogram::new_with_bounds(1, 10_000_000_000, 3).context("histogram")?,
        last_iox_timed: 0,
        last_sent: None,
        last_cmd_seq: 0,
        last_timed_state: 0,
        last_answered_state: 0,
        holding: true,
        clamped_flag: false,
        foreign_until: 0,
        out,
        out_gid,
        status_out,
        chunk_out,
        robot_clock,
        lead_ns: (r.trajectory_lead_ms * 1e6) as u64,
        skew_ns: (r.max_stamp_skew_ms * 1e6) as u64,
        silence_ns: (r.peer_silence_ms * 1e6) as u64,
        state_max_age_ns: (cfg.shared.control.joint_state_max_age_ms * 1e6) as u64,
        frame_max_age_ns: (cfg.shared.control.frame_max_age_ms * 1e6) as u64,
        limits,
        arm,
        gripper,
        gripper_out,
        gripper_sent: None,
        cfg: cfg.clone(),
    };
    // commands are polled at the control rate when no event announces them
    let poll_every = if robot_clock {
        Duration::from_millis(20)
    } else {
        Duration::from_nanos(cfg.shared.control_period_ns().clamp(200_000, 20_000_000))
    };
    let status_every_ns = if args.status_every > 0.0 && args.status_every.is_finite() {
        (args.status_every * 1e9) as u64
    } else {
        u64::MAX
    };
    let mut next_status = start.saturating_add(status_every_ns);
    let cpu0 = cpu_ns();
    let mut events = Events::with_capacity(16);
    while !stop.load(Ordering::Relaxed) {
        let now = monotonic_ns();
        if now >= end {
            break;
        }
        if let Err(e) = poll.poll(&mut events, Some(poll_every)) {
            if e.kind() != std::io::ErrorKind::Interrupted {
                return Err(e).context("epoll_wait");
            }
        }
        if let Some(l) = &b.cmd_event_listener(&iox) {
            let _ = l.try_wait(|_| {});
        }
        // the controller's side first: a state's answer must not wait behind the next state
        let fresh = b.take_commands(&iox);
        let now = monotonic_ns();
        if fresh && (b.cfg.ros2.send == SendOn::Tick || b.robot_clock) {
            b.send(now, false);
        }
        // the robot's states: each published to chunkrt; one command per state when asked
        for _ in 0..MAX_TAKE_PER_WAKE {
            match states.take() {
                Ok(Some((m, _info))) => {
                    let now = monotonic_ns();
                    b.on_state(&m, now, &iox);
                    if b.cfg.ros2.send == SendOn::State && !b.robot_clock {
                        b.take_commands(&iox);
                        b.send(now, true);
                    } else if b.intake.live(now).is_none() {
                        b.send(now, true);
                    }
                }
                Ok(None) => break,
                Err(e) => {
                    b.errors.count(ErrorKind::Decode, monotonic_ns(), || {
                        format!("a JointState that does not decode: {e:?}")
                    });
                    break;
                }
            }
        }
        for _ in 0..MAX_TAKE_PER_WAKE {
            let got = match &echo {
                CommandEcho::Forward(s) => s.take().map(|o| o.map(|(_, i)| i.publisher_gid())),
                CommandEcho::Trajectory(s) => s.take().map(|o| o.map(|(_, i)| i.publisher_gid())),
            };
            match got {
                Ok(Some(gid)) => b.on_echo(gid, monotonic_ns()),
                Ok(None) => break,
                Err(e) => {
                    b.errors.count(ErrorKind::Decode, monotonic_ns(), || {
                        format!("a command on the command topic that does not decode: {e:?}")
                    });
                    break;
                }
            }
        }
        b.take_chunks(&iox);
        b.take_images(&mut cams);
        let now = monotonic_ns();
        b.check_silence(now);
        if now >= next_status {
            next_status = now.saturating_add(status_every_ns);
            let s = b.snapshot(now, start, cpu0);
            println!(
                "ros2 status: {}",
                s.to_string().trim_start_matches("ros2 summary: ")
            );
        }
    }
    tracing::info!("ros2: stopping");
    Ok(b.snapshot(monotonic_ns(), start, cpu0))
}

impl Bridge {
    fn cmd_event_listener<'a>(&self, iox: &'a Iox) -> Option<&'a Listener<Ipc>> {
        iox.cmd_event.as_ref()
    }

    fn snapshot(&self, now: u64, start: u64, cpu0: u64) -> Summary {
        let c = &self.intake.counters;
        let us = |q: f64| self.hist.value_at_quantile(q) as f64 / 1e3;
        Summary {
            commands_applied: c.commands_applied,
            commands_rejected: c.commands_rejected,
            commands_expired: c.commands_expired,
            commands_unbound: c.commands_unbound,
            commands_far: c.commands_far,
            latency_p50_us: us(0.5),
            latency_p99_us: us(0.99),
            latency_max_us: self.hist.max() as f64 / 1e3,
            latency_count: self.hist.len(),
            errors: self.errors.clone(),
            cpu_share: (cpu_ns().saturating_sub(cpu0)) as f64
                / (now.saturating_sub(start)).max(1) as f64,
            max_rss_kb: max_rss_kb(),
            frame_age_p50_us: self.frame_hist.value_at_quantile(0.5) as f64 / 1e3,
            frame_age_p99_us: self.frame_hist.value_at_quantile(0.99) as f64 / 1e3,
            iox_p50_us: self.iox_hist.value_at_quantile(0.5) as f64 / 1e3,
            iox_p99_us: self.iox_hist.value_at_quantile(0.99) as f64 / 1e3,
            ..self.summary.clone()
        }
    }
}
