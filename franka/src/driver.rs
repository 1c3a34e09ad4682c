//! The driver process: FCI on one side, chunkrt's services on the other ([`crate`]).

use std::path::PathBuf;
use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
use std::sync::Arc;
use std::time::Duration;

use anyhow::Context;
use chunkrt_ipc::services::{self, Ipc};
use chunkrt_ipc::*;
use chunkrt_tools::common::{end_time_ns, open_node, CommonArgs};
use chunkrt_tools::intake::CommandIntake;
use chunkrt_tools::shutdown;
use franka::{
    FrankaError, Gripper, JointPositions, MoveControllerMode, RealtimeConfig, Robot, RobotMode,
    RobotState,
};
use hdrhistogram::Histogram;
use iceoryx2::port::listener::Listener;
use iceoryx2::port::notifier::Notifier;
use iceoryx2::port::publisher::Publisher;
use iceoryx2::port::subscriber::Subscriber;

use crate::guard::{reconcile, Guard, GuardLimits, Motion, Reference};
use crate::limits::{CYCLE_S, JOINTS};

/// Half the FCI's cycle (ns): a state sooner than this after the last is a short cycle.
const HALF_CYCLE_NS: u64 = (CYCLE_S * 0.5e9) as u64;

/// A read of the robot's state that returns sooner than this (ns) found it already queued.
const QUEUED_NS: u64 = 15_000;

/// Answers withheld in a row after which one whose state was queued, or whose next state has
/// come, goes out all the same (the FCI stops the motion at 20 lost in a row).
const MAX_WITHHELD_RUN: u32 = 3;

/// An answer ready this long after its state came (ns) misses the robot's cycle: withheld.
const LATE_NS: u64 = 900_000;

/// Fresh cycles in a row the guard's own generator led the arm before the joint state says the
/// robot does not follow the controller (`JOINT_STATUS_NOT_FOLLOWING`; 10 ms: a lost cycle's
/// recovery, 1-3 cycles, is not an episode).
const NOT_FOLLOWING_CYCLES: u64 = 10;

/// Command-line arguments.
#[derive(Debug, Clone, clap::Args)]
pub struct Args {
    #[command(flatten)]
    pub common: CommonArgs,
    /// The robot's FCI address: the control box's host name or IP (franka-sim: its loopback
    /// address, 127.0.0.x).
    #[arg(long, value_name = "HOST")]
    pub robot: String,
    /// The Franka Hand's address (default: the robot's); `none`: no hand (the gripper channel,
    /// if configured, reports 0).
    #[arg(long, value_name = "HOST")]
    pub gripper: Option<String>,
    /// How long a cycle waits for the controller's answer to its state (µs) before it answers
    /// the robot without it. FCI allows a cycle about 300 µs of user time on a real arm.
    #[arg(long, value_name = "US", default_value_t = 400.0)]
    pub answer_budget_us: f64,
    /// No accepted command for this long: stop to rest (ms).
    #[arg(long, value_name = "MS", default_value_t = 20.0)]
    pub command_timeout_ms: f64,
    /// Bumpless hand-over: the first command of a session, and the first after a stop, must
    /// start within this distance of the measured position (rad); a command further away is
    /// refused (flag `COMMAND_FAR`) and the controller re-seeds from the arm.
    #[arg(long, value_name = "RAD", default_value_t = 0.02)]
    pub bind_tolerance: f64,
    /// Late cycles continued at constant acceleration before the stop to rest begins.
    #[arg(long, value_name = "N", default_value_t = 5)]
    pub extrapolate_cycles: u32,
    /// Fraction of the FR3's velocity, acceleration and jerk limits the guard keeps to: 0.83
    /// passes chunkrt's own shaping (0.8, config/franka_fr3.toml) and keeps a robot up to
    /// 15 % stricter than the datasheet out of its reflexes.
    #[arg(long, value_name = "F", default_value_t = 0.83)]
    pub limit_margin: f64,
    /// Send the controller's positions unchanged (no guard): what the robot's own checks make of
    /// an unguarded command stream. For tests; never on a real arm.
    #[arg(long)]
    pub no_guard: bool,
    /// The box (base frame, m: "xmin,ymin,zmin,xmax,ymax,zmax") the flange and the hand's tip
    /// are held within: a command whose stop would leave it is refused and the arm braked
    /// before the robot's own reflex. The default keeps them above the base's plane.
    #[arg(
        long,
        value_name = "M,M,M,M,M,M",
        default_value = "-0.9,-0.9,0.05,0.9,0.9,1.3"
    )]
    pub workspace_box: String,
    /// The hand past the flange along its axis (m; 0.1034: the Franka Hand's fingertips).
    #[arg(long, value_name = "M", default_value_t = 0.1034)]
    pub hand_length: f64,
    /// Clearance kept between links that can meet (m), past the driver's own capsules around
    /// them (`franka/src/geometry.rs`): a command that would fold the arm closer is refused.
    #[arg(long, value_name = "M", default_value_t = 0.05)]
    pub link_clearance: f64,
    /// Following error bound (rad): a joint of the arm further than this from the robot's
    /// reference (a contact, an obstacle, a person holding it) stops the command: every command
    /// that would take that joint further from the arm is refused and the arm braked, so the
    /// joint's servo cannot snap it across the gap at speed when it comes free. The arm lags
    /// its reference by ~0.01 rad at speed.
    #[arg(long, value_name = "RAD", default_value_t = 0.1)]
    pub follow_bound: f64,
    /// Real-time scheduling of the FCI thread: `enforce` (a real arm: a PREEMPT_RT kernel and
    /// SCHED_FIFO are required) or `ignore` (a simulator on an ordinary kernel).
    #[arg(long, value_enum, default_value_t = Realtime::Enforce)]
    pub realtime: Realtime,
    /// Core to pin the FCI thread to.
    #[arg(long)]
    pub cpu: Option<usize>,
    /// SCHED_FIFO priority of the FCI thread when permitted (0: none).
    #[arg(long, default_value_t = 90)]
    pub priority: i32,
    /// Stop after this many seconds (default: until SIGINT / SIGTERM).
    #[arg(long, value_name = "SECONDS")]
    pub duration: Option<f64>,
    /// Write every commanded position (a line of 7 per robot cycle, the cycles the robot
    /// continued on its own without an answer included) to this file at the end: the command
    /// stream to replay through another client (tools/python/fr3_replay.py).
    #[arg(long, value_name = "FILE")]
    pub record: Option<PathBuf>,
    /// Write a trace of the last 120 s of cycles (CSV, at the end): the robot's measured position, the
    /// controller's desired position and velocity, the position sent, and how it was made
    /// (`pass`, `offset`, `restart`, `generator`, `late`, `brake`, `rest`, `unguarded`): what to
    /// read when the guard acted.
    #[arg(long, value_name = "FILE")]
    pub trace: Option<PathBuf>,
    /// End at the first reflex instead of recovering and starting a new motion.
    #[arg(long)]
    pub stop_on_reflex: bool,
    /// A reflex on purpose, once, this many seconds after the start: one answer with a step
    /// of 0.01 rad on joint 7 past the guard (10 rad/s in one cycle), which the robot aborts.
    /// For tests of the recovery (wherever the arm is then); never on a real arm.
    #[arg(long, value_name = "S")]
    pub inject_reflex_at: Option<f64>,
    /// Give up (exit with an error, the arm at rest in the robot's own stop) after this many
    /// reflexes within `--reflex-window-s`: a robot that keeps tripping needs a person, not
    /// another automatic recovery.
    #[arg(long, value_name = "N", default_value_t = 3)]
    pub max_reflexes: u32,
    /// The window of `--max-reflexes` (s).
    #[arg(long, value_name = "SECONDS", default_value_t = 10.0)]
    pub reflex_window_s: f64,
    /// Wait up to this long for the robot to accept the first connection (s; 0: fail at once).
    #[arg(long, value_name = "SECONDS", default_value_t = 0.0)]
    pub wait_for_robot: f64,
    /// Print a status line (`franka status: ...`: cycles, the robot's command success rate,
    /// reflexes, late and guarded cycles, the share the controller led) every this many seconds
    /// (0: none).
    #[arg(long, value_name = "SECONDS", default_value_t = 0.0)]
    pub status_every: f64,
    /// Withhold this fraction of the answers to the robot, at random (0..=0.05): a lost packet on
    /// purpose, what a dropped UDP datagram is on a real arm. For tests; the robot continues
    /// each withheld cycle on its own and reports the reference it used.
    #[arg(long, value_name = "P", default_value_t = 0.0)]
    pub drop_answers: f64,
    /// Seed of `--drop-answers`' choice.
    #[arg(long, value_name = "N", default_value_t = 1)]
    pub drop_seed: u64,
}

/// What the FCI thread shares with the status line (relaxed atomics: one store each a cycle).
#[derive(Default)]
struct Live {
    cycles: AtomicU64,
    success_rate: AtomicU64,
    reflexes: AtomicU64,
    late: AtomicU64,
    clamped: AtomicU64,
    braking: AtomicU64,
    /// Fresh cycles, and those the controller's motion led.
    fresh: AtomicU64,
    led: AtomicU64,
    /// The longest stretch of fresh cycles the controller did not lead (cycles = ms).
    not_led_longest: AtomicU64,
}

/// `--realtime`.
#[derive(Debug, Clone, Copy, PartialEq, Eq, clap::ValueEnum)]
pub enum Realtime {
    /// A real arm: real-time scheduling is required.
    Enforce,
    /// A simulator: run without it.
    Ignore,
}

/// What the driver did, printed on exit (`franka summary: key=value ...`).
#[derive(Debug, Clone, Default)]
pub struct Summary {
    /// Robot cycles answered.
    pub cycles: u64,
    /// Joint states published.
    pub states_published: u64,
    /// Cycles answered with a fresh command of the controller.
    pub fresh: u64,
    /// Of those, commands the guard had to change to keep within the limits.
    pub clamped: u64,
    /// Cycles whose answer was late: the motion continued at constant acceleration.
    pub late: u64,
    /// Cycles of a stop to rest (no live command).
    pub braking: u64,
    /// Robot cycles that passed without an answer from this driver (the robot continued the
    /// motion on its own).
    pub missed: u64,
    /// Cycles at rest without a command.
    pub rest: u64,
    /// States that came less than half a cycle after the one before: the robot (or the
    /// network, or a simulator catching up) left the answer less time than a cycle, and an
    /// answer can then miss its cycle with none missed here.
    pub short_cycles: u64,
    /// Cycles whose command the controller answered within the budget.
    pub answered: u64,
    /// Motions started (one, plus one per recovery).
    pub motions: u64,
    /// Reflexes the robot reported (its motion aborted).
    pub reflexes: u64,
    /// The errors of the first reflexes.
    pub reflex_errors: String,
    /// Lowest `control_command_success_rate` the robot reported during a motion (after its
    /// first 100 cycles).
    pub success_rate_min: f64,
    /// Its mean over the same cycles.
    pub success_rate_mean: f64,
    /// Connections made again after the robot went away.
    pub reconnects: u64,
    /// Round trip state published → answering command received (µs).
    pub round_trip_us: [f64; 3],
    /// Commands: accepted, expired, rejected, unbound, far.
    pub commands: [u64; 5],
    /// Hand moves commanded.
    pub gripper_moves: u64,
    /// Largest |commanded − measured| joint position while following fresh commands (rad).
    pub max_tracking_error: f64,
    /// Why the guard acted on a fresh command, by limit ([`crate::guard::Broken`]).
    pub guard_acted: [u64; 5],
    /// Answers withheld on purpose (`--drop-answers`).
    pub dropped: u64,
    /// Answers withheld because they were ready too late for their cycle (the machine stalled
    /// the driver between the state and the answer).
    pub withheld_late: u64,
    /// Short cycles answered with the reference's continuation instead of the controller's
    /// command (an answer that may come after the next state).
    pub short_continued: u64,
    /// Cycles continued at constant acceleration after the controller's last command expired
    /// (it answered nothing in time): the first `--extrapolate-cycles` of each such run.
    pub expired_continued: u64,
    /// Reports whose position had moved to a candidate's and whose velocity and acceleration
    /// were the cycle before's ([`crate::guard::torn`]): taken as that candidate.
    pub torn_reports: u64,
    /// Late answers the robot's later report shows it applied after all (a simulator does; the
    /// FCI drops them).
    pub late_applied: u64,
    /// Answers that went out more than `LATE_NS` after their state came although the cycle had
    /// found them in time (the machine stalled the driver between the two).
    pub late_at_send: u64,
    /// Sends that themselves took over half a cycle (the driver stalled inside one).
    pub slow_send: u64,
    /// Answers withheld because the robot's next state had already come when they were ready
    /// (they would miss their cycle).
    pub withheld_next_state: u64,
    /// States read and passed over because a newer one had come (after a stall).
    pub stale_states: u64,
    /// Answers withheld because their state was already queued when read (its age unknown).
    pub withheld_queued: u64,
    /// Reports that showed the robot's history lagging (it applied a late answer and rewound),
    /// answered over the cycles it differences them over.
    pub lagging: u64,
    /// Answers sent that the robot did not apply (its report shows the reference continued: the
    /// answer came too late), and the next commands hedged to pass from either reference.
    pub unapplied: u64,
    pub hedged: u64,
    /// How the robot's reported reference was taken, by [`Reference`]: an exact candidate,
    /// corrected derivatives, adopted as reported, set aside; and reports that had not moved
    /// since the last state while the reference was moving (stale: the answer stands).
    pub reference: [u64; 5],
    /// Of the fresh cycles, those whose command was the controller's motion (passed, or plus a
    /// shrinking offset): the controller led. The rest the guard's generator led.
    pub led: u64,
    /// The longest stretch of fresh cycles the controller did not lead (ms).
    pub not_led_longest_ms: u64,
    /// |measured - the controller's command| over fresh cycles (rad): p99 and max.
    pub controller_tracking: [f64; 2],
    /// Fresh cycles whose command was refused for the arm's geometry (its stop would leave the
    /// workspace box or bring links closer than the clearance): the arm braked instead.
    pub workspace_refused: u64,
    /// The last limit a refused command ran into.
    pub workspace_limit: Option<crate::geometry::Limit>,
    /// Cycles whose command was refused because a joint of the arm was further than
    /// `--follow-bound` from the reference and the command took it further: the arm braked.
    pub blocked: u64,
    /// The joint (1..7) that last did not follow (0: none) and its largest error (rad).
    pub blocked_joint: usize,
    pub blocked_error_max: f64,
}

impl std::fmt::Display for Summary {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(
            f,
            "franka summary: cycles={} states_published={} fresh={} clamped={} late={} \
             braking={} missed={} rest={} short_cycles={} answered={} motions={} reconnects={} reflexes={} \
             success_rate_min={:.4} success_rate_mean={:.5} \
             round_trip_p50_us={:.1} round_trip_p99_us={:.1} round_trip_max_us={:.1} \
             commands_applied={} commands_expired={} commands_rejected={} commands_unbound={} \
             commands_far={} gripper_moves={} max_tracking_error={:.5} guard_acted={} \
             dropped={} withheld_late={} short_continued={} expired_continued={} torn_reports={} unapplied={} late_applied={} late_at_send={} slow_send={} withheld_next_state={} stale_states={} withheld_queued={} lagging={} \
             hedged={} reference_exact={} reference_corrected={} \
             reference_adopted={} reference_kept={} reference_stale={} led_share={:.5} not_led_longest_ms={} \
             controller_tracking_p99={:.5} controller_tracking_max={:.5} workspace_refused={} \
             workspace_limit={} blocked={} blocked_joint={} blocked_error_max={:.4} \
             reflex_errors={}",
            self.cycles,
            self.states_published,
            self.fresh,
            self.clamped,
            self.late,
            self.braking,
            self.missed,
            self.rest,
            self.short_cycles,
            self.answered,
            self.motions,
            self.reconnects,
            self.reflexes,
            self.success_rate_min,
            self.success_rate_mean,
            self.round_trip_us[0],
            self.round_trip_us[1],
            self.round_trip_us[2],
            self.commands[0],
            self.commands[1],
            self.commands[2],
            self.commands[3],
            self.commands[4],
            self.gripper_moves,
            self.max_tracking_error,
            {
                let v: Vec<String> = crate::guard::Broken::NAMES
                    .iter()
                    .zip(self.guard_acted)
                    .filter(|(_, n)| *n > 0)
                    .map(|(name, n)| format!("{name}:{n}"))
                    .collect();
                if v.is_empty() {
                    "none".to_string()
                } else {
                    v.join(",")
                }
            },
            self.dropped,
            self.withheld_late,
            self.short_continued,
            self.expired_continued,
            self.torn_reports,
            self.unapplied,
            self.late_applied,
            self.late_at_send,
            self.slow_send,
            self.withheld_next_state,
            self.stale_states,
            self.withheld_queued,
            self.lagging,
            self.hedged,
            self.reference[0],
            self.reference[1],
            self.reference[2],
            self.reference[3],
            self.reference[4],
            if self.fresh > 0 {
                self.led as f64 / self.fresh as f64
            } else {
                1.0
            },
            self.not_led_longest_ms,
            self.controller_tracking[0],
            self.controller_tracking[1],
            self.workspace_refused,
            self.workspace_limit
                .map_or("none".to_string(), |l| l.to_string().replace(' ', "_")),
            self.blocked,
            self.blocked_joint,
            self.blocked_error_max,
            if self.reflex_errors.is_empty() {
                "none"
            } else {
                &self.reflex_errors
            },
        )
    }
}

/// Connects to the FR3 at `addr` and checks that it is one (FCI version 10).
/// The workspace of `--workspace-box`, `--hand-length` and `--link-clearance`, checked.
fn workspace(args: &Args) -> anyhow::Result<crate::geometry::Workspace> {
    let v: Vec<f64> = args
        .workspace_box
        .split(',')
        .map(|x| x.trim().parse::<f64>())
        .collect::<Result<_, _>>()
        .map_err(|e| anyhow::anyhow!("--workspace-box {:?}: {e}", args.workspace_box))?;
    anyhow::ensure!(
        v.len() == 6
            && v.iter().all(|x| x.is_finite() && x.abs() <= 3.0)
            && (0..3).all(|i| v[i] + 0.1 <= v[i + 3]),
        "--workspace-box {:?}: six numbers xmin,ymin,zmin,xmax,ymax,zmax (m, within 3 m of the \
         base, each max at least 0.1 above its min)",
        args.workspace_box
    );
    anyhow::ensure!(
        args.hand_length.is_finite() && (0.0..=0.5).contains(&args.hand_length),
        "--hand-length {}: must be within 0..=0.5 m",
        args.hand_length
    );
    anyhow::ensure!(
        args.link_clearance.is_finite() && (0.0..=0.2).contains(&args.link_clearance),
        "--link-clearance {}: must be within 0..=0.2 m",
        args.link_clearance
    );
    Ok(crate::geometry::Workspace {
        min: [v[0], v[1], v[2]],
        max: [v[3], v[4], v[5]],
        hand_length: args.hand_length,
        clearance: args.link_clearance,
    })
}

/// The process's IPv4 / IPv6 datagram sockets (descriptor numbers).
fn inet_datagram_fds() -> Vec<i32> {
    let Ok(dir) = std::fs::read_dir("/proc/self/fd") else {
        return Vec::new();
    };
    dir.flatten()
        .filter_map(|e| e.file_name().to_str()?.parse::<i32>().ok())
        .filter(|&fd| {
            let mut ty: libc::c_int = 0;
            let mut len = std::mem::size_of::<libc::c_int>() as libc::socklen_t;
            // SAFETY: getsockopt / getsockname write at most `len` bytes into the buffers
            // given; a descriptor that is no socket (or closed meanwhile) answers an error
            let ok = unsafe {
                libc::getsockopt(
                    fd,
                    libc::SOL_SOCKET,
                    libc::SO_TYPE,
                    (&mut ty as *mut libc::c_int).cast(),
                    &mut len,
                )
            } == 0;
            if !ok || ty != libc::SOCK_DGRAM {
                return false;
            }
            // SAFETY: as above; sockaddr_storage is plain data, zero is a valid value
            let mut addr: libc::sockaddr_storage = unsafe { std::mem::zeroed() };
            let mut alen = std::mem::size_of::<libc::sockaddr_storage>() as libc::socklen_t;
            let ok = unsafe {
                libc::getsockname(
                    fd,
                    (&mut addr as *mut libc::sockaddr_storage).cast(),
                    &mut alen,
                )
            } == 0;
            ok && matches!(i32::from(addr.ss_family), libc::AF_INET | libc::AF_INET6)
        })
        .collect()
}

/// Whether a datagram waits on `fd` (on the robot's state socket: the next state has come).
fn datagram_waiting(fd: i32) -> bool {
    let mut b = [0u8; 1];
    // SAFETY: recv writes at most one byte into `b`; MSG_PEEK leaves the datagram queued for
    // franka-rs, MSG_DONTWAIT never blocks
    unsafe {
        libc::recv(
            fd,
            b.as_mut_ptr().cast(),
            1,
            libc::MSG_PEEK | libc::MSG_DONTWAIT,
        ) >= 0
    }
}

/// Connects to the robot; returns it and its state socket when that can be told apart (the
/// one datagram socket the connection opened).
fn connect(addr: &str, realtime: RealtimeConfig) -> anyhow::Result<(Robot, Option<i32>)> {
    let before = inet_datagram_fds();
    let robot = Robot::new(addr, realtime).map_err(|e| {
        anyhow::anyhow!(
            "franka: cannot connect to the robot at {addr}: {e} (a real arm: FCI enabled in Desk, \
             the brakes open, this PC on its network; the simulator: is it running on that \
             address?)"
        )
    })?;
    let version = robot.server_version();
    anyhow::ensure!(
        version == 10,
        "franka: the robot at {addr} speaks FCI version {version}: this driver keeps the FR3's \
         limits (FCI 10); an FER / Panda (FCI 5) has other limits and is not supported"
    );
    let opened: Vec<i32> = inet_datagram_fds()
        .into_iter()
        .filter(|fd| !before.contains(fd))
        .collect();
    let state_fd = match opened[..] {
        [fd] => Some(fd),
        _ => {
            tracing::warn!(
                "franka: the robot's state socket cannot be told apart ({} new datagram sockets): \
                 an answer is withheld only by its own lateness, not when the next state has come",
                opened.len()
            );
            None
        }
    };
    tracing::info!("franka: connected to the FR3 at {addr} (FCI {version})");
    Ok((robot, state_fd))
}

/// Runs until SIGINT / SIGTERM or `--duration`; prints the [`Summary`] on stdout.
pub fn run(args: Args) -> anyhow::Result<()> {
    let summary = drive(&args)?;
    println!("{summary}");
    Ok(())
}

/// What the hand thread shares with the FCI thread: measured width, target width (f64 bits;
/// NaN: none), moves made.
struct Hand {
    width: AtomicU64,
    target: AtomicU64,
    moves: AtomicU64,
}

/// The ports and state of one cycle. Everything is allocated before the first cycle.
struct Core {
    n_dof: usize,
    intake: CommandIntake,
    guard: Guard,
    /// The robot's reference at this cycle's state (what the answer is judged against), and the
    /// answer: the next state tells which the robot applied.
    reference: Motion,
    last: Motion,
    /// Whether the last answer went out (`--drop-answers` withholds some).
    sent_last: bool,
    /// This cycle's answer is to be withheld (`--drop-answers`).
    withhold: bool,
    /// `--drop-answers`: the probability and the generator's state (xorshift64).
    drop_p: f64,
    rng: u64,
    /// The current stretch of fresh cycles the controller did not lead.
    not_led_run: u64,
    /// This cycle's `TraceRow::notes`.
    notes: u8,
    /// The other reference of an ambiguous cycle (the answer before went out late): the next
    /// state tells which the robot judged this cycle's answer against.
    ambiguous: Option<Motion>,
    /// This robot has applied an answer that its next report showed as not applied.
    late_applied_seen: bool,
    /// The histories a robot that applies late answers may still judge the coming answers
    /// against, each the motion at the robot cycle (`seq`) of an answer sent: franka-sim, when a
    /// late answer comes, rewinds the cycles it had continued on its own and differences that
    /// answer and the next one over all the cycles since, so that its history parts from the
    /// one its earlier report showed (traced: an answer after a 3-cycle stall judged at 5 463
    /// rad/s³ against that history, within the limits from the reported one). Each answer is
    /// hedged to pass from all of them; they merge with the reported one two answers later.
    alts: [Option<(Motion, u64)>; ALTS],
    /// The history before the first late answer of a run (motion, `seq`): the newest answer
    /// absorbed straight against it (the simulator takes only the newest datagram waiting) is
    /// one more such history.
    alt_base: Option<(Motion, u64)>,
    /// The robot cycle (`seq`) of the last answer sent (0: none yet in this motion), and the
    /// motion it made from the reference it was computed against.
    last_sent_seq: u64,
    last_sent: Motion,
    /// The cycles the robot differences this cycle's answer over (1; more after it applied a
    /// late answer and rewound its own continuation: [`Core::take_reference`]).
    lag: u64,
    /// The robot's state socket (found when the connection opened it), to see whether the next
    /// state has come before an answer goes out; none when it could not be told apart.
    state_fd: Option<i32>,
    /// This cycle's state was already queued when read ([`QUEUED_NS`]).
    state_queued: bool,
    /// Answers withheld in a row.
    withheld_run: u32,
    /// Answers sent since the alternatives last grew (they are dropped after `ALT_CYCLES`).
    alt_age: u32,
    /// |measured - the controller's command| over fresh cycles (µrad).
    tracking: Histogram<u64>,
    seq: u64,
    state_pub: Publisher<Ipc, JointState, ()>,
    state_event: Notifier<Ipc>,
    cmd_sub: Subscriber<Ipc, JointCommand, ()>,
    cmd_event: Listener<Ipc>,
    status_sub: Subscriber<Ipc, ControllerStatus, ()>,
    budget_ns: u64,
    last_cmd_seq: u64,
    late_run: u32,
    /// When the last state came (monotonic ns; 0 before the first).
    last_state_ns: u64,
    extrapolate_cycles: u32,
    no_guard: bool,
    workspace: crate::geometry::Workspace,
    /// `--follow-bound` (rad).
    follow_bound: f64,
    clamped_last: bool,
    refused_last: bool,
    /// The last cycle was the driver's own stop or hold (brake, rest): the state says HOLDING.
    holding: bool,
    /// The last cycle held the arm at rest at the driver's own command: AT_REST.
    at_rest: bool,
    motion_cycles: u64,
    end_ns: u64,
    /// `--inject-reflex-at`, as a monotonic time (0: none, or done).
    inject_reflex_ns: u64,
    stop: &'static AtomicBool,
    hand: Arc<Hand>,
    live: Arc<Live>,
    round_trip: Histogram<u64>,
    record: Option<Vec<[f64; JOINTS]>>,
    /// `--trace`: the last TRACE_CYCLES rows (a ring, allocated once) and the next slot.
    trace: Option<(Vec<TraceRow>, usize)>,
    rate_sum: f64,
    rate_n: u64,
    s: Summary,
}

/// How many other histories the driver hedges against at most ([`Core::alts`]).
const ALTS: usize = 4;
/// Answers after which the other histories are let go: past FCI's 20 lost cycles the robot
/// has stopped the motion in any history.
const ALT_CYCLES: u32 = 25;

/// Cycles `--trace` keeps (the last 120 s).
const TRACE_CYCLES: usize = 120_000;

/// One cycle of `--trace`.
#[derive(Clone, Copy)]
struct TraceRow {
    seq: u64,
    path: u8,
    /// What this cycle knew of the robot's reference and did with the answer ([`TRACE_NOTES`]).
    notes: u8,
    /// The guard's first broken limit that cycle: (joint, code), or none.
    broke: Option<(u8, u8)>,
    /// The robot's clock (ms) and the arm's measured positions and velocities: the robot judges
    /// the measured velocity against its envelope.
    robot_ms: u64,
    measured: [f64; JOINTS],
    measured_dq: [f64; JOINTS],
    /// The robot's reported reference (`q_d`) and the one this cycle's answer was computed
    /// against.
    reported: [f64; JOINTS],
    reference: [f64; JOINTS],
    /// The robot's reported `dq_d`, `ddq_d`, and the reference's velocity and acceleration as
    /// this driver took them ([`crate::guard::reconcile`]): a report whose derivatives disagree
    /// with its positions shows here.
    reported_dq: [f64; JOINTS],
    reported_ddq: [f64; JOINTS],
    reference_dq: [f64; JOINTS],
    reference_ddq: [f64; JOINTS],
    desired: [f64; JOINTS],
    desired_v: [f64; JOINTS],
    sent: [f64; JOINTS],
}

/// What one cycle makes of the controller's answer: the motion sent, the path that made it
/// ([`TRACE_PATHS`]), and what the counters and the trace want of it.
#[derive(Clone, Copy)]
struct Step {
    motion: Motion,
    path: u8,
    clamped: bool,
    /// The controller's command (positions, velocities) when it answered this state (NaN: not).
    desired: ([f64; JOINTS], [f64; JOINTS]),
    /// The guard's first broken limit: (joint, code).
    broke: Option<(u8, u8)>,
}

/// `TraceRow::notes` bits, by name: the answer withheld (`--drop-answers`), the last answer
/// not applied by the robot, this one hedged, the robot's reference taken from its report
/// (corrected or adopted), a reflex ended the motion after this cycle.
const TRACE_NOTES: [&str; 5] = ["withheld", "unapplied", "hedged", "reported", "reflex"];

/// `TraceRow::path` names (0..=3: the guard's own paths).
const TRACE_PATHS: [&str; 10] = [
    "pass",
    "offset",
    "restart",
    "generator",
    "late",
    "brake",
    "rest",
    "unguarded",
    "workspace",
    "blocked",
];

/// The joints' deceleration the stop is predicted with (rad/s²): the guard's own brake plans at
/// 0.7 of its limits (0.83 of the FR3's 10 rad/s²: 5.8).
const STOP_DECEL: f64 = 5.0;
/// Time the stop takes to start (s): the brake's jerk-limited ramp, and a cycle.
const STOP_DELAY_S: f64 = 0.004;

impl Core {
    /// Whether the stop of `next` (each joint braked at `STOP_DECEL` from its velocity) lies
    /// inside a limit of the workspace, further in than the arm's reference is now (a pose
    /// already inside may move out, never deeper, limit by limit).
    fn beyond_workspace(&mut self, next: &Motion) -> bool {
        let mut stop = next.q;
        for (j, q) in stop.iter_mut().enumerate() {
            let v = next.dq[j];
            *q += v * v.abs() / (2.0 * STOP_DECEL) + v * STOP_DELAY_S;
        }
        let at_stop = self.workspace.margins(&stop);
        if at_stop.iter().all(|&m| m >= 0.0) {
            return false;
        }
        let now = self.workspace.margins(&self.reference.q);
        for k in 0..at_stop.len() {
            if at_stop[k] < 0.0 && at_stop[k] < now[k] - 1e-9 {
                self.s.workspace_limit = Some(crate::geometry::Workspace::limit(k));
                return true;
            }
        }
        false
    }

    /// One more history a late answer may have made (the oldest is let go when all are taken).
    fn push_alt(&mut self, alt: (Motion, u64)) {
        let slot = self
            .alts
            .iter()
            .position(Option::is_none)
            .unwrap_or_else(|| {
                self.alts.rotate_left(1);
                ALTS - 1
            });
        self.alts[slot] = Some(alt);
    }

    /// The answer `sent` (the motion it makes from the reported reference) went out at robot
    /// cycle `seq`: each other history takes it too, differenced over the cycles since its own
    /// last answer, and the base of a run gives one more (this answer absorbed straight against
    /// it). A history that has become the reported one's is let go.
    fn advance_alts(&mut self, seq: u64, sent: &Motion) {
        let dt = |p: u64| seq.saturating_sub(p).max(1) as f64 * CYCLE_S;
        for alt in self.alts.iter_mut().flatten() {
            *alt = (Motion::after(&alt.0, &sent.q, dt(alt.1)), seq);
        }
        if let Some((b, p)) = self.alt_base.take() {
            self.push_alt((Motion::after(&b, &sent.q, dt(p)), seq));
        }
        self.alt_age += 1;
        let same = |m: &Motion| {
            (0..JOINTS).all(|j| {
                (m.q[j] - sent.q[j]).abs() <= 1e-12
                    && (m.dq[j] - sent.dq[j]).abs() <= 1e-9
                    && (m.ddq[j] - sent.ddq[j]).abs() <= 1e-6
            })
        };
        for alt in &mut self.alts {
            if self.alt_age > ALT_CYCLES || alt.is_some_and(|(m, _)| same(&m)) {
                *alt = None;
            }
        }
    }

    /// `--record`: the recording holds a line per robot cycle, what the robot applied, so that a
    /// replay at one line a cycle does not take the next answer a cycle early (a velocity step):
    /// the cycles the robot continued on its own, `e` of them since the last state (and the
    /// last answer's own, when it was not applied); where the reference `r` came from the robot's
    /// report, the last lines end the way the robot moved (its position and the two before it
    /// that its reported velocity and acceleration imply).
    fn record_what_the_robot_did(&mut self, unapplied: bool, e: u64, how: Reference, r: &Motion) {
        let Some(rec) = &mut self.record else {
            return;
        };
        let mut m = if unapplied { self.reference } else { self.last };
        if unapplied {
            m = m.continued(CYCLE_S);
            if let Some(line) = rec.last_mut() {
                *line = m.q;
            }
        }
        for _ in 1..e {
            m = m.continued(CYCLE_S);
            if rec.len() < rec.capacity() {
                rec.push(m.q);
            }
        }
        if matches!(how, Reference::Corrected(_) | Reference::Adopted) {
            let n = rec.len();
            let q1: [f64; JOINTS] = std::array::from_fn(|j| r.q[j] - r.dq[j] * CYCLE_S);
            let q2: [f64; JOINTS] =
                std::array::from_fn(|j| q1[j] - (r.dq[j] - r.ddq[j] * CYCLE_S) * CYCLE_S);
            for (back, q) in [r.q, q1, q2].iter().enumerate() {
                if let Some(line) = n.checked_sub(back + 1).and_then(|i| rec.get_mut(i)) {
                    *line = *q;
                }
            }
        }
    }

    /// Whether `reported` is the last answer sent, continued by the robot for fewer cycles than
    /// have passed since (`e` of them since the last state): that history, and the cycles the
    /// robot will difference this cycle's answer over (2 or more).
    fn lagging_report(&self, reported: &Motion, e: u64) -> Option<(Motion, u64)> {
        if self.last_sent_seq == 0 {
            return None;
        }
        let now_seq = self.seq + e;
        let (mut m, mut at) = (self.last_sent, self.last_sent_seq);
        while at + 1 < now_seq && now_seq - at <= 20 {
            if matches!(reconcile(reported, &[m]).1, Reference::Candidate(0)) {
                return Some((m, now_seq - at));
            }
            m = m.continued(CYCLE_S);
            at += 1;
        }
        None
    }

    /// A new motion starts from rest at the robot's position.
    fn begin_motion(&mut self, q: [f64; JOINTS]) {
        self.not_led_run = 0;
        self.last = Motion::rest(q);
        self.reference = self.last;
        self.sent_last = true;
        self.ambiguous = None;
        self.alts = [None; ALTS];
        self.alt_base = None;
        self.alt_age = 0;
        self.last_sent_seq = 0;
        self.last_sent = self.last;
        self.lag = 1;
        self.withheld_run = 0;
        self.motion_cycles = 0;
        self.late_run = 0;
        self.intake.disarm();
        self.s.motions += 1;
    }

    /// What the robot did since the last answer, from its report (`q_d`, `dq_d`, `ddq_d`): it
    /// applied the answer, or (withheld, or too late: the FCI drops it) continued the reference
    /// it had; and it continued on its own for each cycle that had no answer (the FCI's rule for
    /// a lost packet: the last command at constant acceleration). Sets `self.reference` to the
    /// motion the robot judges this cycle's answer against. Returns the other reference to hedge
    /// this answer against when the last one went out and the robot did not apply it in its
    /// cycle: the FCI dropped it, a simulator may apply it late.
    fn take_reference(&mut self, st: &RobotState, elapsed: u64) -> Option<(Motion, u64)> {
        let e = elapsed.clamp(1, 20);
        self.s.missed += e - 1;
        if self.motion_cycles == 0 {
            // the motion's first state: at rest where the arm is (begin_motion)
            self.reference = self.last;
            return None;
        }
        let mut applied = self.last;
        for _ in 1..e {
            applied = applied.continued(CYCLE_S);
        }
        let mut skipped = self.reference;
        for _ in 0..e {
            skipped = skipped.continued(CYCLE_S);
        }
        let reported = Motion {
            q: st.q_d,
            dq: st.dq_d,
            ddq: st.ddq_d,
        };
        // after a cycle that was ambiguous (the answer before went out late), the history the
        // robot judged the last answer against: the reference the driver believed, or the other
        // one (a robot that applies a late answer: a simulator)
        let other = match self.ambiguous {
            Some(o) if e == 1 => Motion::after(&o, &self.last.q, CYCLE_S),
            _ => applied,
        };
        self.ambiguous = None;
        let candidates = [applied, skipped, self.reference, other];
        let (mut r, mut how) = reconcile(&reported, &candidates);
        if let (Reference::Corrected(i), 1) = (how, e) {
            if crate::guard::torn(&reported, &self.reference) {
                // the report's position is this candidate's, its derivatives the cycle before's
                // (a half-written state): the candidate as it is
                self.s.torn_reports += 1;
                (r, how) = (candidates[i], Reference::Candidate(i));
            }
        }
        if matches!(how, Reference::Candidate(3) | Reference::Corrected(3))
            && !matches!(reconcile(&reported, &[applied]).1, Reference::Candidate(0))
        {
            // this robot applied an answer its report had shown as not applied: from now on,
            // when an answer went out and the next report shows the reference continued, the
            // driver believes the robot will still apply it
            self.s.late_applied += 1;
            self.late_applied_seen = true;
        }
        // a report that is the last answer sent, continued by the robot for fewer cycles than
        // have passed since: a robot that applied that answer late (franka-sim rewinds the
        // cycles it had continued on its own, then goes on one cycle a state) and differences the
        // next answer over all the cycles between (traced: an answer 1 cycle on from such a
        // report judged over 3, 23.6 rad/s^2)
        self.lag = 1;
        if matches!(how, Reference::Corrected(_) | Reference::Adopted) {
            if let Some((m, lag)) = self.lagging_report(&reported, e) {
                self.lag = lag;
                self.s.lagging += 1;
                (r, how) = (m, Reference::Candidate(0));
            }
        }
        // a report that moved less than a tenth of the way the reference went in the cycle (a
        // state franka-sim's publish thread packed while its reference was half updated: it
        // moved 7e-7 rad where the answer moved 1.9e-4, and judged the next answer against the
        // answer applied: 181 rad/s^2 when taken as the reference)
        let barely_moved = self.lag == 1 && matches!(how, Reference::Adopted) && {
            let span = |m: &Motion| {
                (0..JOINTS).fold(0.0f64, |x, j| x.max((m.q[j] - self.reference.q[j]).abs()))
            };
            let expected = span(&applied);
            expected > 1e-5 && span(&reported) < 0.1 * expected
        };
        if (matches!(how, Reference::Candidate(2) | Reference::Corrected(2)) || barely_moved)
            && !self.reference.at_rest()
        {
            // the report has not moved since the last state although the reference was moving:
            // a state from before the robot took the answer (franka-sim's publish thread can
            // pack one; the FCI's control never holds a moving reference): the answer stands
            self.s.reference[4] += 1;
            (r, how) = (applied, Reference::Candidate(0));
        } else {
            self.s.reference[match how {
                Reference::Candidate(_) => 0,
                Reference::Corrected(_) => 1,
                Reference::Adopted => 2,
                Reference::Kept => 3,
            }] += 1;
        }
        let unapplied = matches!(how, Reference::Candidate(1) | Reference::Corrected(1));
        self.notes = if unapplied { 2 } else { 0 }
            | if matches!(how, Reference::Corrected(_) | Reference::Adopted) {
                8
            } else {
                0
            };
        self.record_what_the_robot_did(unapplied, e, how, &r);
        let alt = if unapplied && self.sent_last {
            self.s.unapplied += 1;
            // the answer may still be applied late: its history (against the reference it was
            // computed against, one cycle back) is one the next answers may be judged against,
            // and the history before it the base of a run of them
            let m = self.last_sent_seq;
            if self.alt_base.is_none() && self.alts.iter().all(Option::is_none) {
                self.alt_base = Some((self.reference, m.saturating_sub(1)));
            }
            self.push_alt((self.last, m));
            self.alt_age = 0;
            Some((self.last, e))
        } else {
            None
        };
        self.reference = r;
        match alt {
            // a robot seen to apply late answers will apply this one: it is the reference, the
            // report's continuation the other
            Some((late, 1)) if self.late_applied_seen => {
                self.reference = late;
                self.ambiguous = Some(r);
                Some((r, 1))
            }
            Some((late, k)) => {
                if k == 1 {
                    self.ambiguous = Some(late);
                }
                Some((late, k))
            }
            None => None,
        }
    }

    /// One FCI cycle, `elapsed` robot cycles after the last (1; more when the robot went on
    /// without an answer): the state out, the controller's answer in, the command back.
    fn cycle(&mut self, st: &RobotState, elapsed: u64) -> JointPositions {
        let now = monotonic_ns();
        let short = self.begin_cycle(now);
        let hedge_from = self.take_reference(st, elapsed);
        self.note_success_rate(st);
        let stopping = self.stop.load(Ordering::Relaxed) || now >= self.end_ns;
        let (seq, measured) = self.publish_state(st, now, elapsed);
        self.await_answer(seq, now, &measured);
        let live = if stopping {
            None
        } else {
            self.intake.live(monotonic_ns()).copied()
        };
        let step = self.next_step(live.as_ref(), seq, short, stopping);
        let step = self.first_at_rest(step);
        let step = self.within_workspace(step);
        let step = self.within_following(st, step);
        // every answer is hedged, whichever path made it: a brake for the geometry or the
        // following bound too (planned from one reference, it ramps its jerk at 0.5 of the
        // robot's, and may not pass from a history a late answer made)
        let step = self.hedged(step, hedge_from, seq);
        self.account(st, &step, live.is_some());
        self.trace_row(st, seq, &step);
        self.decide_withhold(now, stopping);
        if self.sent_last {
            self.last_sent_seq = seq;
            self.last_sent = step.motion;
            self.advance_alts(seq, &step.motion);
        }
        self.answer(&step.motion, now, stopping)
    }

    /// Counts the cycle; whether its state came less than half a cycle after the last.
    fn begin_cycle(&mut self, now: u64) -> bool {
        self.s.cycles += 1;
        let short =
            self.last_state_ns != 0 && now.saturating_sub(self.last_state_ns) < HALF_CYCLE_NS;
        if self.last_state_ns != 0 && self.motion_cycles > 0 {
            // the robot's own silence past a cycle and a half within a motion (a simulator's
            // stall) is not the controller's: it does not count against the command timeout
            let gap = now.saturating_sub(self.last_state_ns);
            if gap > 3 * HALF_CYCLE_NS {
                self.intake.robot_silent(gap - 2 * HALF_CYCLE_NS);
            }
        }
        self.s.short_cycles += short as u64;
        self.last_state_ns = now;
        self.motion_cycles += 1;
        short
    }

    /// The robot's command success rate, from the 100th cycle of a motion.
    fn note_success_rate(&mut self, st: &RobotState) {
        if self.motion_cycles > 100 {
            let r = st.control_command_success_rate;
            self.s.success_rate_min = self.s.success_rate_min.min(r);
            self.rate_sum += r;
            self.rate_n += 1;
        }
    }

    /// The state out, then the event the robot-clocked controller waits on; its seq counts robot
    /// cycles, so that the controller advances as many. Returns the seq and the positions sent.
    fn publish_state(&mut self, st: &RobotState, now: u64, elapsed: u64) -> (u64, [f64; MAX_DOF]) {
        let width = f64::from_bits(self.hand.width.load(Ordering::Relaxed));
        let mut measured = [0.0; MAX_DOF];
        measured[..JOINTS].copy_from_slice(&st.q);
        if self.n_dof > JOINTS {
            measured[JOINTS] = if width.is_finite() { width } else { 0.0 };
        }
        self.seq += elapsed.clamp(1, 20);
        let mut msg = JointState {
            seq: self.seq,
            measurement_time_ns: now,
            n_dof: self.n_dof as u32,
            status_flags: self.state_flags(st, now),
            position: measured,
            ..Default::default()
        };
        msg.velocity[..JOINTS].copy_from_slice(&st.dq);
        msg.effort[..JOINTS].copy_from_slice(&st.tau_J);
        msg.set_obeyed_publisher(self.intake.obeyed_publisher(now));
        if let Ok(sample) = self.state_pub.loan_uninit() {
            if sample.write_payload(msg).send().is_ok() {
                self.s.states_published += 1;
            }
        }
        let _ = self.state_event.notify();
        (self.seq, measured)
    }

    /// The joint state's status flags: the intake's, and what the robot and this driver did.
    fn state_flags(&self, st: &RobotState, now: u64) -> u32 {
        let mut flags = self.intake.flags(now);
        if st.robot_mode == RobotMode::Reflex || st.current_errors.any() {
            flags |= JOINT_STATUS_ROBOT_ERROR;
        }
        if self.clamped_last {
            flags |= JOINT_STATUS_LIMIT_CLAMPED;
        }
        if self.refused_last {
            // the last command was refused for the arm's geometry (the arm braked)
            flags |= JOINT_STATUS_COMMAND_REJECTED;
        }
        if self.holding {
            // the driver's own stop or hold, no controller's motion
            flags |= JOINT_STATUS_HOLDING;
        }
        if self.at_rest {
            // held still at its own command: a controller starts from here at rest
            flags |= JOINT_STATUS_AT_REST;
        }
        if self.not_led_run >= NOT_FOLLOWING_CYCLES {
            // the guard's own generator has led the arm for a while: the controller says so
            flags |= JOINT_STATUS_NOT_FOLLOWING;
        }
        flags
    }

    /// The controller's statuses, then its answer to this state, waited for within the budget.
    fn await_answer(&mut self, seq: u64, now: u64, measured: &[f64; MAX_DOF]) {
        while let Ok(Some(sample)) = self.status_sub.receive() {
            self.intake
                .on_status(sample.payload(), sample.origin().value(), monotonic_ns());
        }
        let mut answered = false;
        loop {
            while let Ok(Some(sample)) = self.cmd_sub.receive() {
                let t = monotonic_ns();
                let c = *sample.payload();
                let ok =
                    self.intake
                        .on_command(&c, sample.origin().value(), t, &measured[..self.n_dof]);
                if ok && c.state_seq >= seq && !answered {
                    answered = true;
                    self.round_trip.saturating_record((t - now).max(1));
                }
            }
            let elapsed = monotonic_ns().saturating_sub(now);
            if answered || elapsed >= self.budget_ns {
                break;
            }
            let _ = services::wait_event(
                &self.cmd_event,
                Duration::from_nanos(self.budget_ns - elapsed),
            );
        }
        self.s.answered += answered as u64;
    }

    /// The motion this cycle's answer makes: the controller's command through the guard when it
    /// answered this state, else the reference continued (a late answer), braked or held.
    ///
    /// A missing answer (late, or none since the last command expired) continues the reference
    /// at constant acceleration for up to `--extrapolate-cycles`, as the robot itself continues
    /// a lost packet; only then, or when the driver stops, does the stop to rest begin. A stop
    /// for every expired cycle (the controller 2 ms late on a loaded machine) took the stream
    /// off the controller's motion by the stop's jerk each time, and the offset that restarted
    /// after it could not close while the controller accelerated at its 8 rad/s² (a stricter
    /// robot's run: 0.13 rad behind the controller after 18 such stops in 600 ms).
    fn next_step(
        &mut self,
        live: Option<&JointCommand>,
        seq: u64,
        short: bool,
        stopping: bool,
    ) -> Step {
        let mut step = Step {
            motion: self.reference,
            path: 4,
            clamped: false,
            desired: ([f64::NAN; JOINTS], [f64::NAN; JOINTS]),
            broke: None,
        };
        step.motion = match live {
            _ if self.lag > 1 && !self.no_guard => {
                self.s.late += 1;
                self.catch_up()
            }
            // the answer to this cycle's state; an answer to an earlier one comes too late (its
            // cycle was already continued) and would move the arm back
            Some(c) if c.seq != self.last_cmd_seq && c.state_seq == seq => {
                self.follow(c, short, &mut step)
            }
            Some(_) if self.late_run < self.extrapolate_cycles => self.continue_late(),
            None if !stopping
                && self.late_run < self.extrapolate_cycles
                && !self.reference.at_rest() =>
            {
                self.s.expired_continued += 1;
                self.continue_late()
            }
            _ if self.reference.at_rest() => {
                self.s.rest += 1;
                step.path = 6;
                Motion::rest(self.reference.q)
            }
            _ => {
                self.s.braking += 1;
                step.path = 5;
                self.guard.brake(&self.reference).0
            }
        };
        step
    }

    /// One cycle without the controller's answer: the reference continued at constant
    /// acceleration (counted in the run `--extrapolate-cycles` bounds).
    fn continue_late(&mut self) -> Motion {
        self.late_run += 1;
        self.s.late += 1;
        self.guard.extrapolate(&self.reference)
    }

    /// The robot differences this answer over `lag` cycles from its report: the reference
    /// continued over them at its acceleration (no jerk in the robot's differences), which puts
    /// its history back in step; the other histories end here.
    fn catch_up(&mut self) -> Motion {
        self.alts = [None; ALTS];
        self.alt_base = None;
        let (r, k) = (self.reference, self.lag as f64 * CYCLE_S);
        let mut m = r;
        for j in 0..JOINTS {
            m.dq[j] = r.dq[j] + r.ddq[j] * k;
            m.q[j] = r.q[j] + m.dq[j] * k;
        }
        m
    }

    /// The controller's fresh command `c` through the guard (its path and what it did in
    /// `step`).
    fn follow(&mut self, c: &JointCommand, short: bool, step: &mut Step) -> Motion {
        self.last_cmd_seq = c.seq;
        self.late_run = 0;
        self.s.fresh += 1;
        if self.n_dof > JOINTS {
            self.hand
                .target
                .store(c.position[JOINTS].to_bits(), Ordering::Relaxed);
        }
        let (mut q, mut v, mut a) = ([0.0; JOINTS], [0.0; JOINTS], [0.0; JOINTS]);
        q.copy_from_slice(&c.position[..JOINTS]);
        v.copy_from_slice(&c.velocity[..JOINTS]);
        a.copy_from_slice(&c.acceleration[..JOINTS]);
        step.desired = (q, v);
        if self.no_guard {
            step.path = 7;
            Motion::after(&self.reference, &q, CYCLE_S)
        } else if short {
            // a state less than half a cycle after the last: the robot (a simulator catching
            // up, a delayed packet) left this answer less than a cycle, and it may arrive after
            // the next state. The reference's own continuation is the one answer that is the
            // same whether the robot takes it or continues without it: no guess about which it
            // did can then be wrong
            self.s.short_continued += 1;
            self.guard.extrapolate(&self.reference)
        } else {
            let (m, clamped) = self.guard.follow(&self.reference, &q, &v, &a);
            step.clamped = clamped;
            step.path = self.guard.path;
            step.broke = self.guard.broke;
            m
        }
    }

    /// An answer the robot did not apply although it went out (late): the FCI dropped it, a
    /// simulator may still apply it, and the answers after it are judged against whichever
    /// history it made: this one passes from all of them where it can.
    fn hedged(&mut self, mut step: Step, hedge_from: Option<(Motion, u64)>, seq: u64) -> Step {
        if self.no_guard || self.lag > 1 {
            return step;
        }
        let mut others = [(Motion::rest(step.motion.q), 0u64); ALTS + 2];
        let mut n = 0;
        for o in hedge_from
            .iter()
            .copied()
            .chain(
                self.alts
                    .iter()
                    .flatten()
                    .map(|&(m, p)| (m, seq.saturating_sub(p))),
            )
            .chain(
                self.alt_base
                    .iter()
                    .map(|&(m, p)| (m, seq.saturating_sub(p))),
            )
        {
            others[n] = o;
            n += 1;
        }
        if n > 0 {
            let (q, changed) = self
                .guard
                .hedge(&self.reference, &others[..n], &step.motion.q);
            self.s.hedged += changed as u64;
            self.notes |= if changed { 4 } else { 0 };
            if changed {
                step.motion = Motion::after(&self.reference, &q, CYCLE_S);
            }
        }
        step
    }

    /// A motion's first answer is where it starts, at rest: the robot takes a motion's first
    /// command as its start (franka-sim records it at rest, whatever it moved), and a first
    /// step of the controller's motion made the second read three times its jerk (a restart
    /// after a reflex: 8 292 rad/s³). The guard starts afresh from it.
    fn first_at_rest(&mut self, step: Step) -> Step {
        if self.motion_cycles != 1 || self.no_guard {
            return step;
        }
        self.guard.reset();
        Step {
            motion: Motion::rest(self.reference.q),
            path: 6,
            clamped: false,
            broke: None,
            ..step
        }
    }

    /// The arm's geometry: a command whose stop (braking from its velocity) would leave the
    /// workspace box or fold links closer than the clearance, further than the arm is now, is
    /// refused and the arm braked (a pose already inside may move out).
    fn within_workspace(&mut self, mut step: Step) -> Step {
        if step.path <= 3 && !self.no_guard && self.beyond_workspace(&step.motion) {
            self.s.workspace_refused += 1;
            step.motion = self.guard.brake(&self.reference).0;
            step.path = 8;
        }
        self.refused_last = step.path == 8;
        step
    }

    /// The following error: a joint of the arm further than `--follow-bound` from the robot's
    /// reference does not follow (something holds it); a command that would take it further
    /// is refused and the arm braked (the brake plans from the reference, within the limits).
    /// The joint's servo then closes a gap of the bound plus the brake's travel when the joint
    /// comes free, not one as wide as the command ran on meanwhile.
    fn within_following(&mut self, st: &RobotState, mut step: Step) -> Step {
        if step.path > 3 || self.no_guard {
            return step;
        }
        for j in 0..JOINTS {
            let e = (st.q[j] - self.reference.q[j]).abs();
            if e > self.follow_bound && (step.motion.q[j] - st.q[j]).abs() > e {
                self.s.blocked += 1;
                self.s.blocked_joint = j + 1;
                self.s.blocked_error_max = self.s.blocked_error_max.max(e);
                step.motion = self.guard.brake(&self.reference).0;
                step.path = 9;
                break;
            }
        }
        step
    }

    /// Who led, the tracking, the live counters; the motion becomes the last answer.
    fn account(&mut self, st: &RobotState, step: &Step, live: bool) {
        if step.desired.0[0].is_finite() {
            // a fresh command: who led, and how far the arm is from the controller's command
            let led = step.path <= 2;
            self.s.led += led as u64;
            if led {
                self.not_led_run = 0;
            } else {
                self.not_led_run += 1;
                self.s.not_led_longest_ms = self.s.not_led_longest_ms.max(self.not_led_run);
            }
            let e = (0..JOINTS).fold(0.0f64, |m, j| m.max((st.q[j] - step.desired.0[j]).abs()));
            if e.is_finite() {
                self.tracking.saturating_record((e * 1e6) as u64);
            }
        }
        self.s.clamped += step.clamped as u64;
        let l = &self.live;
        l.cycles.store(self.s.cycles, Ordering::Relaxed);
        l.success_rate
            .store(st.control_command_success_rate.to_bits(), Ordering::Relaxed);
        l.late.store(self.s.late + self.s.missed, Ordering::Relaxed);
        l.clamped.store(self.s.clamped, Ordering::Relaxed);
        l.braking.store(self.s.braking, Ordering::Relaxed);
        l.fresh.store(self.s.fresh, Ordering::Relaxed);
        l.led.store(self.s.led, Ordering::Relaxed);
        l.not_led_longest
            .store(self.s.not_led_longest_ms, Ordering::Relaxed);
        if self.last_cmd_seq != 0 && live {
            for j in 0..JOINTS {
                let e = (self.last.q[j] - st.q[j]).abs();
                if e > self.s.max_tracking_error {
                    self.s.max_tracking_error = e;
                }
            }
        }
        self.clamped_last = step.clamped;
        self.holding = step.path == 5 || step.path == 6;
        self.at_rest = step.path == 6;
        self.last = step.motion;
        if let Some(r) = &mut self.record {
            if r.len() < r.capacity() {
                r.push(step.motion.q);
            }
        }
    }

    /// `--trace`: this cycle's row in the ring.
    fn trace_row(&mut self, st: &RobotState, seq: u64, step: &Step) {
        if let Some((rows, next_slot)) = &mut self.trace {
            let row = TraceRow {
                seq,
                path: step.path,
                notes: self.notes,
                broke: step.broke,
                robot_ms: st.time.as_millis(),
                measured: st.q,
                measured_dq: st.dq,
                reported: st.q_d,
                reference: self.reference.q,
                reported_dq: st.dq_d,
                reported_ddq: st.ddq_d,
                reference_dq: self.reference.dq,
                reference_ddq: self.reference.ddq,
                desired: step.desired.0,
                desired_v: step.desired.1,
                sent: step.motion.q,
            };
            if rows.len() < rows.capacity() {
                rows.push(row);
            } else {
                rows[*next_slot] = row;
            }
            *next_slot = (*next_slot + 1) % TRACE_CYCLES;
        }
    }

    /// Whether this answer goes out. One this late (the machine stalled the driver after the
    /// state came), or whose next state has already come (the robot went on: a simulator
    /// catching up, a stall), misses its cycle: the FCI would drop it, a simulator might apply
    /// it late and judge the next answers against a history its reports never showed; withheld,
    /// the robot continues its reference as for any lost packet, and says so in the next state.
    /// Decided as late as it can be, just before the answer goes out.
    fn decide_withhold(&mut self, now: u64, stopping: bool) {
        self.withhold = monotonic_ns().saturating_sub(now) > LATE_NS;
        self.s.withheld_late += self.withhold as u64;
        // (a few in a row at most: a robot whose states come in a burst, a simulator catching up
        // after a stall of its own, would otherwise lose 20 in a row and stop the motion; past
        // them the answer goes out, late, and the hedge covers it)
        let may_withhold = self.withheld_run < MAX_WITHHELD_RUN;
        if !self.withhold && may_withhold && self.state_fd.is_some_and(datagram_waiting) {
            self.withhold = true;
            self.s.withheld_next_state += 1;
        }
        if !self.withhold && may_withhold && self.state_queued && !stopping {
            // a state of unknown age (it was queued: the driver stalled, or the robot's states
            // came in a burst): its answer may reach the robot after the next state, which a
            // simulator applies late; withheld, the next state (waited for) is answered in time
            self.withhold = true;
            self.s.withheld_queued += 1;
        }
        // --drop-answers: this answer is lost on purpose (never the one that ends the motion)
        if self.drop_p > 0.0 && !stopping {
            self.rng ^= self.rng << 13;
            self.rng ^= self.rng >> 7;
            self.rng ^= self.rng << 17;
            let drop = ((self.rng >> 11) as f64 / (1u64 << 53) as f64) < self.drop_p;
            self.s.dropped += (drop && !self.withhold) as u64;
            self.withhold |= drop;
        }
        self.notes |= self.withhold as u8;
        if let Some((rows, next_slot)) = &mut self.trace {
            let i = (*next_slot + TRACE_CYCLES - 1) % TRACE_CYCLES;
            if let Some(r) = rows.get_mut(i) {
                r.notes |= self.withhold as u8;
            }
        }
        self.sent_last = !self.withhold;
        self.withheld_run = if self.withhold {
            self.withheld_run + 1
        } else {
            0
        };
    }

    /// The command to the robot (`--inject-reflex-at` steps it on purpose once); the motion
    /// finishes when the driver stops at rest.
    fn answer(&mut self, next: &Motion, now: u64, stopping: bool) -> JointPositions {
        let mut sent = next.q;
        if self.inject_reflex_ns != 0 && now >= self.inject_reflex_ns && !stopping {
            // --inject-reflex-at: a step the robot must abort (a test of the recovery)
            self.inject_reflex_ns = 0;
            sent[JOINTS - 1] += 0.01;
            tracing::warn!("franka: --inject-reflex-at: a 0.01 rad step on joint 7, on purpose");
        }
        let mut out = JointPositions::new(sent);
        if stopping && next.at_rest() {
            out.motion_finished = true;
        }
        out
    }
}

/// One FCI motion at 1 kHz on the robot's clock: each state in, the cycle, the answer out
/// (unless withheld on purpose); until the motion finishes or the robot ends it.
fn one_motion(robot: &Robot, core: &mut Core) -> Result<(), FrankaError> {
    let mut motion = robot.start_joint_position_control(MoveControllerMode::JointImpedance)?;
    loop {
        // franka-rs drains the states already queued only before it blocks: after a stall (the
        // driver's thread stopped while it waited) it returns the first state that came and
        // leaves the newer ones queued. An answer to it would miss its cycle: read on to the
        // newest, counting the robot cycles between
        let t0 = monotonic_ns();
        let (mut state, period) = motion.read_once()?;
        // a state that was queued before the read (it returned without waiting) came at a time
        // this driver did not see: its cycle may be nearly over
        core.state_queued = monotonic_ns().saturating_sub(t0) < QUEUED_NS;
        let mut elapsed = period.as_millis().max(1);
        // (at most a gap's worth: past 20 lost cycles the robot has stopped the motion)
        for _ in 0..20 {
            if !core.state_fd.is_some_and(datagram_waiting) {
                break;
            }
            let (newer, period) = motion.read_once()?;
            state = newer;
            elapsed += period.as_millis().max(1);
            core.s.stale_states += 1;
            core.state_queued = true;
        }
        let answer = core.cycle(&state, elapsed);
        if core.withhold && !answer.motion_finished {
            continue;
        }
        let t0 = monotonic_ns();
        core.s.late_at_send += (t0.saturating_sub(core.last_state_ns) > LATE_NS) as u64;
        motion.write_once(&answer, None)?;
        core.s.slow_send += (monotonic_ns().saturating_sub(t0) > HALF_CYCLE_NS) as u64;
        if answer.motion_finished {
            return Ok(());
        }
    }
}

/// The whole process; returns the counters instead of printing them.
pub fn drive(args: &Args) -> anyhow::Result<Summary> {
    let stop = shutdown::flag();
    let (cfg, ns) = args.common.load()?;
    let setup = Setup::check(args, &cfg)?;
    let realtime = match args.realtime {
        Realtime::Enforce => RealtimeConfig::Enforce,
        Realtime::Ignore => RealtimeConfig::Ignore,
    };
    let (robot, state_fd) = first_connection(args, realtime, stop)?;
    let node = open_node("chunkrt-franka")?;
    let hand = Arc::new(Hand {
        width: AtomicU64::new(f64::NAN.to_bits()),
        target: AtomicU64::new(f64::NAN.to_bits()),
        moves: AtomicU64::new(0),
    });
    let hand_thread = spawn_hand(args, setup.n_dof, &hand, stop)?;
    let live = Arc::new(Live::default());
    let status_thread = spawn_status(args, &live, stop)?;
    let outcome = chunkrt_rt::thread::make_current_thread_realtime(
        args.cpu,
        args.priority,
        args.realtime == Realtime::Enforce,
    );
    tracing::info!("franka: FCI thread: {outcome}");
    let parts = Parts {
        setup,
        state_fd,
        stop,
        hand: hand.clone(),
        live,
    };
    let mut core = Core::new(args, &ns, &node, parts)?;
    let failure = run_motions(args, &mut core, robot, realtime);
    stop.store(true, Ordering::SeqCst);
    if let Some(t) = hand_thread {
        let _ = t.join();
    }
    if let Some(t) = status_thread {
        let _ = t.join();
    }
    core.finish_summary(&hand);
    write_outputs(args, &core)?;
    if let Some(e) = failure {
        println!("{}", core.s);
        return Err(e);
    }
    Ok(core.s)
}

/// The arguments and configuration checked, and what the run derives from them.
struct Setup {
    n_dof: usize,
    budget_us: f64,
    timeout_ms: f64,
    max_future_ms: f64,
    workspace: crate::geometry::Workspace,
    start: u64,
    end_ns: u64,
}

impl Setup {
    /// Every argument within its range, the configuration an FR3's (7 joints, the hand's width
    /// an 8th; 1 kHz): a clear error otherwise.
    fn check(args: &Args, cfg: &SharedConfig) -> anyhow::Result<Self> {
        let n_dof = cfg.robot.joints.len();
        anyhow::ensure!(
            n_dof == JOINTS || n_dof == JOINTS + 1,
            "the configuration lists {n_dof} joints: an FR3 has {JOINTS}, and the hand's width \
             may be an 8th (config/franka_fr3.toml)"
        );
        anyhow::ensure!(
            (cfg.robot.joint_state_rate_hz - 1000.0).abs() < 1e-9,
            "robot.joint_state_rate_hz is {}: the FCI's cycle is 1 kHz",
            cfg.robot.joint_state_rate_hz
        );
        anyhow::ensure!(
            args.follow_bound.is_finite() && (0.02..=1.0).contains(&args.follow_bound),
            "--follow-bound {}: must be within 0.02..=1 rad (the arm lags its reference by \
             ~0.01 rad at speed)",
            args.follow_bound
        );
        let budget_us = args.answer_budget_us;
        anyhow::ensure!(
            budget_us.is_finite() && (0.0..=900.0).contains(&budget_us),
            "--answer-budget-us {budget_us}: must be within 0..=900 (a cycle is 1000 µs)"
        );
        let timeout_ms = args.command_timeout_ms;
        anyhow::ensure!(
            timeout_ms.is_finite() && (1.0..=10_000.0).contains(&timeout_ms),
            "--command-timeout-ms {timeout_ms}: must be within 1..=10000"
        );
        anyhow::ensure!(
            args.limit_margin.is_finite() && (0.1..=1.0).contains(&args.limit_margin),
            "--limit-margin {}: must be within 0.1..=1",
            args.limit_margin
        );
        let workspace = workspace(args)?;
        anyhow::ensure!(
            args.max_reflexes >= 1
                && args.reflex_window_s.is_finite()
                && (0.1..=3600.0).contains(&args.reflex_window_s),
            "--max-reflexes {} --reflex-window-s {}: at least 1, within 0.1..=3600 s",
            args.max_reflexes,
            args.reflex_window_s
        );
        anyhow::ensure!(
            args.drop_answers.is_finite() && (0.0..=0.05).contains(&args.drop_answers),
            "--drop-answers {}: must be within 0..=0.05 (20 lost in a row stop the robot)",
            args.drop_answers
        );
        if args.drop_answers > 0.0 {
            tracing::warn!(
                "franka: --drop-answers {}: that share of the answers is withheld on purpose",
                args.drop_answers
            );
        }
        anyhow::ensure!(
            args.bind_tolerance.is_finite() && args.bind_tolerance > 0.0,
            "--bind-tolerance {}: must be > 0",
            args.bind_tolerance
        );
        if args.no_guard {
            tracing::warn!(
                "franka: --no-guard: the controller's positions go to the robot unchanged"
            );
        }
        anyhow::ensure!(
            args.wait_for_robot.is_finite() && (0.0..=3600.0).contains(&args.wait_for_robot),
            "--wait-for-robot {}: must be within 0..=3600 s",
            args.wait_for_robot
        );
        anyhow::ensure!(
            args.status_every.is_nan() || args.status_every <= 3600.0,
            "--status-every {}: must be within 0..=3600 s",
            args.status_every
        );
        let start = monotonic_ns();
        Ok(Self {
            n_dof,
            budget_us,
            timeout_ms,
            max_future_ms: cfg.control.max_future_ms,
            workspace,
            start,
            end_ns: end_time_ns(start, args.duration)?,
        })
    }
}

/// The first connection must succeed (a wrong address, FCI off, a wrong model: said at once,
/// or after `--wait-for-robot`).
fn first_connection(
    args: &Args,
    realtime: RealtimeConfig,
    stop: &AtomicBool,
) -> anyhow::Result<(Option<Robot>, Option<i32>)> {
    let until = std::time::Instant::now() + Duration::from_secs_f64(args.wait_for_robot);
    loop {
        match connect(&args.robot, realtime) {
            Ok((r, fd)) => return Ok((Some(r), fd)),
            Err(e) if e.to_string().contains("FCI version") => return Err(e),
            Err(e) => {
                if std::time::Instant::now() >= until || stop.load(Ordering::Relaxed) {
                    return Err(e);
                }
                std::thread::sleep(Duration::from_millis(200));
            }
        }
    }
}

/// The hand's thread (`--gripper`, or the robot's address when the configuration has an 8th
/// joint), or none (its width then reads 0).
fn spawn_hand(
    args: &Args,
    n_dof: usize,
    hand: &Arc<Hand>,
    stop: &'static AtomicBool,
) -> anyhow::Result<Option<std::thread::JoinHandle<()>>> {
    let addr = match args.gripper.as_deref() {
        Some("none") => None,
        Some(a) => Some(a.to_string()),
        None if n_dof > JOINTS => Some(args.robot.clone()),
        None => None,
    };
    let Some(addr) = addr else {
        hand.width.store(0f64.to_bits(), Ordering::Relaxed);
        return Ok(None);
    };
    let hand = hand.clone();
    let gripper = Gripper::new(&addr).map_err(|e| {
        anyhow::anyhow!(
            "franka: cannot connect to the hand at {addr}: {e} (--gripper none: without it)"
        )
    })?;
    Ok(Some(
        std::thread::Builder::new()
            .name("franka-hand".into())
            .spawn(move || hand_loop(&addr, gripper, &hand, stop))
            .context("franka: hand thread")?,
    ))
}

/// `--status-every S`: a line of the live counters every S seconds, from a thread of its own.
fn spawn_status(
    args: &Args,
    live: &Arc<Live>,
    stop: &'static AtomicBool,
) -> anyhow::Result<Option<std::thread::JoinHandle<()>>> {
    if args.status_every <= 0.0 {
        return Ok(None);
    }
    let (live, every) = (live.clone(), Duration::from_secs_f64(args.status_every));
    Ok(Some(
        std::thread::Builder::new()
            .name("franka-status".into())
            .spawn(move || {
                while !stop.load(Ordering::Relaxed) {
                    std::thread::sleep(every);
                    live.print();
                }
            })
            .context("franka: status thread")?,
    ))
}

impl Live {
    /// One `franka status:` line.
    fn print(&self) {
        let g = |a: &AtomicU64| a.load(Ordering::Relaxed);
        let fresh = g(&self.fresh);
        println!(
            "franka status: cycles={} success_rate={:.3} reflexes={} late={} guarded={} \
             braking={} led={:.4} not_led_longest_ms={}",
            g(&self.cycles),
            f64::from_bits(g(&self.success_rate)),
            g(&self.reflexes),
            g(&self.late),
            g(&self.clamped),
            g(&self.braking),
            if fresh > 0 {
                g(&self.led) as f64 / fresh as f64
            } else {
                1.0
            },
            g(&self.not_led_longest)
        );
    }
}

/// What [`Core::new`] takes besides the arguments and the ports.
struct Parts {
    setup: Setup,
    state_fd: Option<i32>,
    stop: &'static AtomicBool,
    hand: Arc<Hand>,
    live: Arc<Live>,
}

impl Core {
    /// The FCI thread's state, every port and buffer allocated here, before the first cycle.
    fn new(
        args: &Args,
        ns: &Namespace,
        node: &iceoryx2::prelude::Node<Ipc>,
        parts: Parts,
    ) -> anyhow::Result<Self> {
        let Parts {
            setup,
            state_fd,
            stop,
            hand,
            live,
        } = parts;
        let (state_name, cmd_name) = (ns.joint_state(), ns.joint_command());
        let state_service = services::joint_state_service(node, &state_name)?;
        let cmd_service = services::joint_command_service(node, &cmd_name)?;
        let state_events = services::event_service(node, &state_name)?;
        let cmd_events = services::event_service(node, &cmd_name)?;
        let mut intake = CommandIntake::new(
            "franka",
            setup.n_dof,
            (setup.timeout_ms * 1e6) as u64,
            (setup.max_future_ms * 1e6) as u64,
            setup.start,
        );
        intake.bind_to_controller(chunkrt_tools::fake_robot::SESSION_TIMEOUT_NS);
        intake.set_bind_tolerance(args.bind_tolerance);
        let record = args.record.as_ref().map(|_| {
            // ten minutes of cycles (or the run's duration), allocated once
            let cycles = args.duration.map_or(600_000.0, |d| d * 1100.0 + 1000.0);
            Vec::with_capacity(cycles.min(4e6) as usize)
        });
        let inject_reflex_ns = match args.inject_reflex_at {
            Some(s) if s.is_finite() && (0.0..=86_400.0).contains(&s) => {
                setup.start + (s * 1e9) as u64
            }
            Some(s) => anyhow::bail!("--inject-reflex-at {s}: must be within 0..=86400 s"),
            None => 0,
        };
        let core = Core {
            n_dof: setup.n_dof,
            intake,
            guard: Guard::new(GuardLimits::fr3(args.limit_margin, 0.02), CYCLE_S)?,
            reference: Motion::rest([0.0; JOINTS]),
            last: Motion::rest([0.0; JOINTS]),
            sent_last: true,
            withhold: false,
            drop_p: args.drop_answers,
            // xorshift64 needs a state other than 0
            rng: args.drop_seed.wrapping_mul(0x9E37_79B9_7F4A_7C15) | 1,
            not_led_run: 0,
            notes: 0,
            ambiguous: None,
            late_applied_seen: false,
            alts: [None; ALTS],
            alt_base: None,
            last_sent_seq: 0,
            last_sent: Motion::rest([0.0; JOINTS]),
            lag: 1,
            alt_age: 0,
            state_fd,
            state_queued: false,
            withheld_run: 0,
            tracking: Histogram::new_with_bounds(1, 100_000_000, 3)
                .expect("constant histogram bounds are valid"),
            seq: 0,
            state_pub: services::publisher(&state_service)?,
            state_event: services::notifier(&state_events)?,
            cmd_sub: services::subscriber(&cmd_service)?,
            cmd_event: services::listener(&cmd_events)?,
            status_sub: services::subscriber(&services::status_service(node, &ns.status())?)?,
            budget_ns: (setup.budget_us * 1e3) as u64,
            last_cmd_seq: 0,
            late_run: 0,
            last_state_ns: 0,
            extrapolate_cycles: args.extrapolate_cycles,
            no_guard: args.no_guard,
            workspace: setup.workspace,
            follow_bound: args.follow_bound,
            clamped_last: false,
            refused_last: false,
            holding: true,
            at_rest: true,
            motion_cycles: 0,
            end_ns: setup.end_ns,
            inject_reflex_ns,
            stop,
            hand,
            live,
            round_trip: Histogram::new_with_bounds(1, 10_000_000_000, 3)
                .expect("constant histogram bounds are valid"),
            record,
            trace: args
                .trace
                .as_ref()
                .map(|_| (Vec::with_capacity(TRACE_CYCLES), 0)),
            rate_sum: 0.0,
            rate_n: 0,
            s: Summary {
                success_rate_min: 1.0,
                ..Summary::default()
            },
        };
        tracing::info!(
            "franka: publishing '{state_name}', following '{cmd_name}' (answer budget {} µs, \
             command timeout {} ms, guard at {} of the FR3's limits{})",
            setup.budget_us,
            setup.timeout_ms,
            args.limit_margin,
            if args.no_guard { ", OFF" } else { "" }
        );
        Ok(core)
    }

    /// A reflex ended the motion: counted, named, marked in the trace.
    fn on_reflex(&mut self, e: &franka::ControlException) {
        self.s.reflexes += 1;
        if let Some((rows, next_slot)) = &mut self.trace {
            let i = (*next_slot + TRACE_CYCLES - 1) % TRACE_CYCLES;
            if let Some(r) = rows.get_mut(i) {
                r.notes |= 16;
            }
        }
        self.live.reflexes.store(self.s.reflexes, Ordering::Relaxed);
        let names = e.last_motion_errors.names().join("+");
        tracing::error!(
            "franka: REFLEX: the robot aborted the motion: {} ({})",
            if names.is_empty() {
                "no error named"
            } else {
                &names
            },
            e.message.lines().next().unwrap_or("")
        );
        if self.s.reflex_errors.len() < 400 {
            if !self.s.reflex_errors.is_empty() {
                self.s.reflex_errors.push(',');
            }
            self.s
                .reflex_errors
                .push_str(if names.is_empty() { "unnamed" } else { &names });
        }
    }

    /// The summary's figures that come from histograms and counters kept elsewhere.
    fn finish_summary(&mut self, hand: &Hand) {
        let h = &self.round_trip;
        let us = |q: f64| h.value_at_quantile(q) as f64 / 1e3;
        self.s.round_trip_us = [us(0.5), us(0.99), h.max() as f64 / 1e3];
        let c = &self.intake.counters;
        self.s.commands = [
            c.commands_applied,
            c.commands_expired,
            c.commands_rejected,
            c.commands_unbound,
            c.commands_far,
        ];
        self.s.gripper_moves = hand.moves.load(Ordering::Relaxed);
        self.s.success_rate_mean = if self.rate_n > 0 {
            self.rate_sum / self.rate_n as f64
        } else {
            0.0
        };
        self.s.guard_acted = self.guard.acted;
        let t = &self.tracking;
        self.s.controller_tracking = [t.value_at_quantile(0.99) as f64 / 1e6, t.max() as f64 / 1e6];
    }
}

/// Motions until the run ends: each state read, a robot in a reflex recovered (or, after
/// `--max-reflexes` within `--reflex-window-s`, given up on), a robot gone reconnected. Returns
/// why it gave up, if it did.
fn run_motions(
    args: &Args,
    core: &mut Core,
    mut robot: Option<Robot>,
    realtime: RealtimeConfig,
) -> Option<anyhow::Error> {
    // the times of the reflexes within the window (a few: allocated here, once)
    let window_ns = (args.reflex_window_s * 1e9) as u64;
    let mut recent_reflexes: Vec<u64> = Vec::with_capacity(args.max_reflexes as usize + 1);
    while !core.stop.load(Ordering::Relaxed) && monotonic_ns() < core.end_ns {
        let Some(r) = robot.as_ref() else {
            // the robot went away (a restarted control box or simulator): try again, holding
            // nothing (no state is published, so the controller holds)
            std::thread::sleep(Duration::from_millis(500));
            match connect(&args.robot, realtime) {
                Ok((r, fd)) => {
                    core.s.reconnects += 1;
                    core.state_fd = fd;
                    robot = Some(r);
                }
                Err(e) => tracing::debug!("{e}"),
            }
            continue;
        };
        let state = match r.read_once() {
            Ok(s) => s,
            Err(e) => {
                tracing::warn!("franka: the robot stopped answering ({e}): reconnecting");
                robot = None;
                continue;
            }
        };
        if state.robot_mode == RobotMode::Reflex || state.current_errors.any() {
            tracing::warn!(
                "franka: the robot reports {}: automatic error recovery",
                state.current_errors
            );
            if let Err(e) = r.automatic_error_recovery() {
                return Some(anyhow::anyhow!("franka: error recovery failed: {e}"));
            }
            continue;
        }
        core.begin_motion(state.q);
        match one_motion(r, core) {
            Ok(()) => return None,
            Err(FrankaError::Control(e)) => {
                core.on_reflex(&e);
                if args.stop_on_reflex {
                    return None;
                }
                let t = monotonic_ns();
                recent_reflexes.retain(|&at| t.saturating_sub(at) < window_ns);
                recent_reflexes.push(t);
                if recent_reflexes.len() >= args.max_reflexes as usize {
                    return Some(anyhow::anyhow!(
                        "franka: {} reflexes within {} s ({}): recovery gives up (--max-reflexes, \
                         --reflex-window-s); the robot is in its own stop. Read the reflexes' \
                         names above, then restart the driver",
                        recent_reflexes.len(),
                        args.reflex_window_s,
                        core.s.reflex_errors
                    ));
                }
                if let Err(e) = r.automatic_error_recovery() {
                    tracing::warn!("franka: error recovery failed ({e}): reconnecting");
                    robot = None;
                }
            }
            Err(e) => {
                tracing::warn!("franka: the motion ended ({e}): reconnecting");
                robot = None;
            }
        }
    }
    None
}

/// `--trace` (the ring, oldest first) and `--record` (a line of positions per robot cycle).
fn write_outputs(args: &Args, core: &Core) -> anyhow::Result<()> {
    if let (Some(path), Some((rows, next_slot))) = (&args.trace, &core.trace) {
        let (newer, older) = rows.split_at(*next_slot % rows.len().max(1));
        write_trace(path, older.iter().chain(newer))?;
    }
    if let (Some(path), Some(rec)) = (&args.record, &core.record) {
        let mut text = String::with_capacity(rec.len() * 7 * 20);
        for q in rec {
            for (j, v) in q.iter().enumerate() {
                if j > 0 {
                    text.push(' ');
                }
                text.push_str(&format!("{v:.17e}"));
            }
            text.push('\n');
        }
        std::fs::write(path, text)
            .with_context(|| format!("franka: cannot write {}", path.display()))?;
        tracing::info!(
            "franka: {} commanded positions in {}",
            rec.len(),
            path.display()
        );
    }
    Ok(())
}

/// The hand's own loop: follows the gripper channel's target width (a move, or a grasp when it
/// closes) and reports the measured width. Blocking calls, at the hand's pace.
fn hand_loop(addr: &str, gripper: Gripper, hand: &Hand, stop: &AtomicBool) {
    let mut gripper = Some(gripper);
    let mut commanded = f64::NAN;
    let mut max_width = 0.08;
    let mut errors = 0u32;
    while !stop.load(Ordering::Relaxed) {
        let Some(g) = gripper.as_ref() else {
            // the hand went away with the robot: connect again
            std::thread::sleep(Duration::from_millis(500));
            gripper = Gripper::new(addr).ok();
            commanded = f64::NAN;
            continue;
        };
        let target = f64::from_bits(hand.target.load(Ordering::Relaxed));
        if target.is_finite() && commanded.is_finite() && (target - commanded).abs() > 2e-3 {
            let w = target.clamp(0.0, max_width);
            let r = if w < 0.005 {
                // closing on whatever is between the fingers: a grasp with wide tolerances
                g.grasp(0.0, 0.1, 20.0, max_width, max_width)
            } else {
                g.move_gripper(w, 0.1)
            };
            commanded = target;
            hand.moves.fetch_add(1, Ordering::Relaxed);
            if let Err(e) = r {
                errors += 1;
                if errors <= 5 {
                    tracing::warn!("franka: hand: {e}");
                }
            }
        }
        match g.read_once() {
            Ok(s) => {
                hand.width.store(s.width.to_bits(), Ordering::Relaxed);
                if s.max_width > 0.0 {
                    max_width = s.max_width;
                }
                if !commanded.is_finite() {
                    commanded = s.width;
                }
            }
            Err(e) => {
                errors += 1;
                if errors <= 5 {
                    tracing::warn!("franka: hand state: {e}");
                }
                gripper = None;
            }
        }
    }
}

/// `--trace`: one CSV row per cycle.
fn write_trace<'a>(
    path: &std::path::Path,
    rows: impl Iterator<Item = &'a TraceRow>,
) -> anyhow::Result<()> {
    use std::fmt::Write as _;
    let mut text = String::with_capacity(TRACE_CYCLES * 30 * 12 + 512);
    let mut n = 0usize;
    text.push_str("seq,robot_ms,path,notes,broke");
    for name in [
        "measured",
        "measured_dq",
        "reported",
        "reference",
        "desired",
        "desired_v",
        "sent",
        "reported_dq",
        "reference_dq",
        "reported_ddq",
        "reference_ddq",
    ] {
        for j in 1..=JOINTS {
            let _ = write!(text, ",{name}_{j}");
        }
    }
    text.push('\n');
    for r in rows {
        n += 1;
        let _ = write!(
            text,
            "{},{},{},",
            r.seq,
            r.robot_ms,
            TRACE_PATHS.get(r.path as usize).unwrap_or(&"?")
        );
        for (i, name) in TRACE_NOTES.iter().enumerate() {
            if r.notes & (1 << i) != 0 {
                let _ = write!(text, "{name};");
            }
        }
        text.push(',');
        if let Some((j, b)) = r.broke {
            let name = crate::guard::Broken::NAMES[b as usize % 5];
            let _ = write!(text, "j{}:{name}", j + 1);
        }
        for v in &r.measured {
            let _ = write!(text, ",{v:.6}");
        }
        for v in &r.measured_dq {
            let _ = write!(text, ",{v:.4}");
        }
        // the references and desired positions at a nanoradian too: their differences are what
        // the guard judges
        for x in [&r.reported, &r.reference, &r.desired, &r.desired_v] {
            for v in x {
                let _ = write!(text, ",{v:.9}");
            }
        }
        // the command at a nanoradian: its second and third differences are what the robot
        // checks (1e-9 rad is 1e-3 rad/s² at 1 kHz)
        for v in &r.sent {
            let _ = write!(text, ",{v:.9}");
        }
        for x in [&r.reported_dq, &r.reference_dq] {
            for v in x {
                let _ = write!(text, ",{v:.7}");
            }
        }
        for x in [&r.reported_ddq, &r.reference_ddq] {
            for v in x {
                let _ = write!(text, ",{v:.4}");
            }
        }
        text.push('\n');
    }
    std::fs::write(path, text)
        .with_context(|| format!("franka: cannot write {}", path.display()))?;
    tracing::info!("franka: the last {n} cycles traced in {}", path.display());
    Ok(())
}
