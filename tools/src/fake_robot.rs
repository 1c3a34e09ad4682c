//! `fake-robot`: a simulated N-DoF arm behind the real joint state / joint command services.
//!
//! Every joint is a unit-inertia double integrator driven by a critically damped tracking law
//! with the command's velocity and acceleration as feed-forward:
//!
//! ```text
//! a = a_cmd + ω²·(p_cmd − p) + 2ω·(v_cmd − v),   |a| ≤ max_acceleration
//! v ← v + a·dt,                                  |v| ≤ max_velocity
//! p ← p + v·dt,                                  position_min ≤ p ≤ position_max
//! ```
//!
//! A watchdog decides what is tracked: the newest valid command while its deadline has not
//! passed; otherwise the arm brakes to a hold at the position where the hold began, and the
//! published `status_flags` say why (`JOINT_STATUS_*`). The reported effort is the applied
//! acceleration (unit inertia).

use std::sync::atomic::Ordering;

use anyhow::Context;
use chunkrt_ipc::config::JointConfig;
use chunkrt_ipc::services;
use chunkrt_ipc::*;
use rand::{Rng, SeedableRng};

use crate::common::{check_rate, end_time_ns, open_node, sleep_until_or_stop, CommonArgs};
use crate::intake::CommandIntake;
use crate::shutdown;

/// Command-line arguments.
#[derive(Debug, Clone, PartialEq, clap::Args)]
pub struct Args {
    #[command(flatten)]
    pub common: CommonArgs,
    /// Joint state publish (and simulation) rate; default `robot.joint_state_rate_hz`.
    #[arg(long, value_name = "HZ")]
    pub rate_hz: Option<f64>,
    /// Seed of the measurement noise (only used with `--noise`).
    #[arg(long, default_value_t = 0)]
    pub seed: u64,
    /// Uniform measurement noise added to published positions, ± this amplitude.
    #[arg(long, default_value_t = 0.0)]
    pub noise: f64,
    /// Stop after this many seconds (default: run until SIGINT / SIGTERM).
    #[arg(long, value_name = "SECONDS")]
    pub duration: Option<f64>,
    /// Hold (and flag `COMMAND_TIMEOUT`) when no command arrived for this long.
    #[arg(long, value_name = "MS", default_value_t = 50.0)]
    pub command_timeout_ms: f64,
    /// Natural frequency of the tracking law (rad/s).
    #[arg(long, value_name = "RAD_PER_S", default_value_t = 60.0)]
    pub omega: f64,
    /// Initial positions, comma separated (default: `initial_position` of each joint).
    #[arg(long, value_name = "P0,P1,...", value_delimiter = ',')]
    pub initial: Option<Vec<f64>>,
    /// Whose commands are obeyed. `controller`: only the command publisher that the
    /// controller's status announces (session binding; nothing before the first status, nothing
    /// while a second status publisher speaks). `first`: the first command publisher heard
    /// (for a test or driver that commands the robot without a controller).
    #[arg(long, value_enum, default_value_t = Session::Controller)]
    pub session: Session,
    /// Bumpless hand-over: the first command of a session, and the first after the robot held,
    /// must start within this distance of the measured position (rad or m on every joint);
    /// a command further away is refused (flag `COMMAND_FAR`) and the robot keeps holding.
    #[arg(long, value_name = "RAD", default_value_t = 0.05)]
    pub bind_tolerance: f64,
}

/// How the robot picks the command publisher it obeys (`--session`).
#[derive(Debug, Clone, Copy, PartialEq, Eq, clap::ValueEnum)]
pub enum Session {
    /// The publisher announced in the controller's status ([`SessionGate`]).
    Controller,
    /// The first publisher heard ([`StreamGuard`] binding only).
    First,
}

/// Status silence after which another controller may bind the robot's session.
pub const SESSION_TIMEOUT_NS: u64 = 500_000_000;

impl Default for Args {
    /// The same values as an empty command line.
    fn default() -> Self {
        Self {
            common: CommonArgs::default(),
            rate_hz: None,
            seed: 0,
            noise: 0.0,
            duration: None,
            command_timeout_ms: 50.0,
            omega: 60.0,
            initial: None,
            session: Session::Controller,
            bind_tolerance: 0.05,
        }
    }
}

/// Counters printed on exit.
#[derive(Debug, Clone, Copy, Default, PartialEq)]
pub struct Summary {
    /// Joint states published.
    pub states_published: u64,
    /// Commands accepted for tracking.
    pub commands_applied: u64,
    /// Commands received after their deadline (ignored).
    pub commands_expired: u64,
    /// Commands that failed validation, arrived out of order or came from a publisher other
    /// than the session's controller.
    pub commands_rejected: u64,
    /// Commands ignored while the robot has no session: before the first controller status
    /// reached it (a controller's first commands can arrive before its status does), or while
    /// a second status publisher made the session ambiguous.
    pub commands_unbound: u64,
    /// Commands refused because they started further than `--bind-tolerance` from the measured
    /// position (the first of a session, or the first after a hold).
    pub commands_far: u64,
    /// Controller statuses refused (a second status publisher, out of order).
    pub status_rejected: u64,
    /// Largest distance between an applied command's position and the measured position when it
    /// was applied (on any joint): what a hand-over or a resume asked the arm to jump.
    pub max_command_offset: f64,
    /// Transitions into the watchdog hold.
    pub holds: u64,
    /// Ticks spent in the watchdog hold.
    pub hold_ticks: u64,
    /// Largest |commanded − simulated| position while tracking a position command.
    pub max_tracking_error: f64,
    /// Largest wake-up lateness of the simulation loop (ns).
    pub max_lateness_ns: u64,
}

impl std::fmt::Display for Summary {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(
            f,
            "fake-robot summary: states_published={} commands_applied={} commands_expired={} \
             commands_rejected={} commands_unbound={} commands_far={} status_rejected={} holds={} \
             hold_ticks={} max_tracking_error={:.6} max_command_offset={:.6} max_lateness_us={:.1}",
            self.states_published,
            self.commands_applied,
            self.commands_expired,
            self.commands_rejected,
            self.commands_unbound,
            self.commands_far,
            self.status_rejected,
            self.holds,
            self.hold_ticks,
            self.max_tracking_error,
            self.max_command_offset,
            self.max_lateness_ns as f64 / 1e3
        )
    }
}

/// Limits of one simulated joint.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct JointLimits {
    pub position_min: f64,
    pub position_max: f64,
    pub max_velocity: f64,
    pub max_acceleration: f64,
}

impl From<&JointConfig> for JointLimits {
    fn from(j: &JointConfig) -> Self {
        Self {
            position_min: j.position_min,
            position_max: j.position_max,
            max_velocity: j.max_velocity,
            max_acceleration: j.max_acceleration,
        }
    }
}

/// What the arm tracks in one step.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Target {
    pub position: [f64; MAX_DOF],
    pub velocity: [f64; MAX_DOF],
    pub acceleration: [f64; MAX_DOF],
}

/// The simulated arm (state and limits; no I/O, no allocation).
#[derive(Debug, Clone)]
pub struct Arm {
    n: usize,
    limits: [JointLimits; MAX_DOF],
    omega: f64,
    /// Simulated positions.
    pub position: [f64; MAX_DOF],
    /// Simulated velocities.
    pub velocity: [f64; MAX_DOF],
    /// Acceleration applied in the last step.
    pub acceleration: [f64; MAX_DOF],
}

impl Arm {
    /// An arm at rest at `initial` (within the limits). `limits.len()` must be 1..=MAX_DOF.
    pub fn new(limits: &[JointLimits], initial: &[f64], omega: f64) -> anyhow::Result<Self> {
        let n = limits.len();
        anyhow::ensure!(
            (1..=MAX_DOF).contains(&n),
            "{n} joints, must be 1..={MAX_DOF}"
        );
        anyhow::ensure!(
            initial.len() == n,
            "{} initial positions for {n} joints",
            initial.len()
        );
        anyhow::ensure!(
            omega.is_finite() && (0.1..=10_000.0).contains(&omega),
            "--omega {omega}: must be in 0.1..=10000"
        );
        let mut arm = Self {
            n,
            limits: [limits[0]; MAX_DOF],
            omega,
            position: [0.0; MAX_DOF],
            velocity: [0.0; MAX_DOF],
            acceleration: [0.0; MAX_DOF],
        };
        for i in 0..n {
            let l = &limits[i];
            anyhow::ensure!(
                initial[i].is_finite() && (l.position_min..=l.position_max).contains(&initial[i]),
                "initial position {i} = {}: must be in {}..={}",
                initial[i],
                l.position_min,
                l.position_max
            );
            arm.limits[i] = *l;
            arm.position[i] = initial[i];
        }
        Ok(arm)
    }

    /// Number of joints.
    pub fn n_dof(&self) -> usize {
        self.n
    }

    /// Clamps `target.position` into the joint limits; true if anything changed.
    pub fn clamp_target(&self, target: &mut Target) -> bool {
        let mut clamped = false;
        for i in 0..self.n {
            let l = &self.limits[i];
            let p = target.position[i].clamp(l.position_min, l.position_max);
            if p != target.position[i] {
                clamped = true;
                target.position[i] = p;
            }
        }
        clamped
    }

    /// Advances the simulation by `dt` seconds towards `target` (positions within limits).
    pub fn step(&mut self, target: &Target, dt: f64) {
        let w = self.omega;
        for i in 0..self.n {
            let l = &self.limits[i];
            let a = target.acceleration[i]
                + w * w * (target.position[i] - self.position[i])
                + 2.0 * w * (target.velocity[i] - self.velocity[i]);
            let a = a.clamp(-l.max_acceleration, l.max_acceleration);
            let mut v = (self.velocity[i] + a * dt).clamp(-l.max_velocity, l.max_velocity);
            let mut p = self.position[i] + v * dt;
            if p <= l.position_min || p >= l.position_max {
                p = p.clamp(l.position_min, l.position_max);
                v = 0.0;
            }
            self.acceleration[i] = a;
            self.velocity[i] = v;
            self.position[i] = p;
        }
    }
}

/// The watchdog and bookkeeping around the arm: what to track, flags, counters.
#[derive(Debug, Clone)]
pub struct Robot {
    /// The simulated arm.
    pub arm: Arm,
    /// Which commands are obeyed ([`crate::intake`]).
    pub intake: CommandIntake,
    holding: bool,
    hold_target: Target,
    /// Flags of the last step.
    pub status_flags: u32,
    /// The robot's own counters (the intake's are in [`Self::summary`]).
    pub counts: Summary,
}

impl Robot {
    /// A robot that starts holding at the arm's position; `now_ns` starts the command timeout.
    pub fn new(arm: Arm, command_timeout_ns: u64, max_future_ns: u64, now_ns: u64) -> Self {
        let hold_target = Target {
            position: arm.position,
            velocity: [0.0; MAX_DOF],
            acceleration: [0.0; MAX_DOF],
        };
        let intake = CommandIntake::new(
            "fake-robot",
            arm.n_dof(),
            command_timeout_ns,
            max_future_ns,
            now_ns,
        );
        Self {
            arm,
            intake,
            holding: true,
            hold_target,
            status_flags: JOINT_STATUS_HOLDING,
            counts: Summary::default(),
        }
    }

    /// Obeys only the command publisher announced by the controller's status from now on.
    pub fn bind_to_controller(&mut self, timeout_ns: u64) {
        self.intake.bind_to_controller(timeout_ns);
    }

    /// Refuses the first command of a session, and the first after a hold, when it starts
    /// further than `tolerance` from the measured position (bumpless hand-over).
    pub fn set_bind_tolerance(&mut self, tolerance: f64) {
        self.intake.set_bind_tolerance(tolerance);
    }

    /// The command publisher the robot obeys, as its joint state reports it; 0 while none.
    pub fn obeyed_publisher(&self, now_ns: u64) -> u128 {
        self.intake.obeyed_publisher(now_ns)
    }

    /// Handles one controller status from publisher `origin` (session binding).
    pub fn on_status(&mut self, status: &ControllerStatus, origin: u128, now_ns: u64) {
        self.intake.on_status(status, origin, now_ns);
    }

    /// Handles one received command from publisher `origin`.
    pub fn on_command(&mut self, cmd: &JointCommand, origin: u128, now_ns: u64) {
        let n = self.arm.n_dof();
        self.intake
            .on_command(cmd, origin, now_ns, &self.arm.position[..n]);
    }

    /// Every counter: the robot's and its intake's.
    pub fn summary(&self) -> Summary {
        let c = &self.intake.counters;
        Summary {
            commands_applied: c.commands_applied,
            commands_expired: c.commands_expired,
            commands_rejected: c.commands_rejected,
            commands_unbound: c.commands_unbound,
            commands_far: c.commands_far,
            status_rejected: c.status_rejected,
            max_command_offset: c.max_command_offset,
            ..self.counts
        }
    }

    /// Runs the watchdog and advances the arm by `dt` seconds at time `now_ns`; returns the
    /// status flags of this step.
    pub fn step(&mut self, now_ns: u64, dt: f64) -> u32 {
        let mut flags = self.intake.flags(now_ns);
        let live = self.intake.live(now_ns).copied();
        let target = match live {
            Some(cmd) => {
                self.holding = false;
                let mut t = Target {
                    position: cmd.position,
                    velocity: cmd.velocity,
                    acceleration: cmd.acceleration,
                };
                if cmd.mode == COMMAND_MODE_HOLD {
                    t.velocity = [0.0; MAX_DOF];
                    t.acceleration = [0.0; MAX_DOF];
                }
                if self.arm.clamp_target(&mut t) {
                    flags |= JOINT_STATUS_LIMIT_CLAMPED;
                }
                t
            }
            None => {
                if !self.holding {
                    self.holding = true;
                    self.intake.disarm();
                    self.counts.holds += 1;
                    self.hold_target.position = self.arm.position;
                }
                self.counts.hold_ticks += 1;
                flags |= JOINT_STATUS_HOLDING;
                self.hold_target
            }
        };
        self.arm.step(&target, dt);
        if live.is_some() {
            for i in 0..self.arm.n_dof() {
                let e = (target.position[i] - self.arm.position[i]).abs();
                if e > self.counts.max_tracking_error {
                    self.counts.max_tracking_error = e;
                }
            }
        }
        self.status_flags = flags;
        flags
    }
}

/// Runs until SIGINT / SIGTERM or `--duration`; prints the [`Summary`] on stdout.
pub fn run(args: Args) -> anyhow::Result<()> {
    let summary = simulate(&args)?;
    println!("{summary}");
    Ok(())
}

/// The whole process: returns the counters instead of printing them.
pub fn simulate(args: &Args) -> anyhow::Result<Summary> {
    let stop = shutdown::flag();
    let (cfg, ns) = args.common.load()?;
    let rate_hz = check_rate(
        "--rate-hz",
        args.rate_hz.unwrap_or(cfg.robot.joint_state_rate_hz),
        1.0,
        10_000.0,
    )?;
    let timeout_ms = args.command_timeout_ms;
    anyhow::ensure!(
        timeout_ms.is_finite() && (0.1..=3_600_000.0).contains(&timeout_ms),
        "--command-timeout-ms {timeout_ms}: must be in 0.1..=3600000"
    );
    anyhow::ensure!(
        args.noise.is_finite() && (0.0..=1.0).contains(&args.noise),
        "--noise {}: must be in 0..=1",
        args.noise
    );
    let limits: Vec<JointLimits> = cfg.robot.joints.iter().map(JointLimits::from).collect();
    let initial: Vec<f64> = match &args.initial {
        Some(v) => v.clone(),
        None => cfg
            .robot
            .joints
            .iter()
            .map(|j| j.initial_position)
            .collect(),
    };
    let arm = Arm::new(&limits, &initial, args.omega).context("fake-robot")?;
    let n_dof = arm.n_dof();

    let node = open_node("chunkrt-fake-robot")?;
    let state_name = ns.joint_state();
    let cmd_name = ns.joint_command();
    let state_service = services::joint_state_service(&node, &state_name)?;
    let state_pub = services::publisher(&state_service)?;
    let cmd_service = services::joint_command_service(&node, &cmd_name)?;
    let cmd_sub = services::subscriber(&cmd_service)?;
    let status_name = ns.status();
    let status_sub = services::subscriber(&services::status_service(&node, &status_name)?)?;
    tracing::info!(
        "fake-robot: {n_dof} joints at {rate_hz} Hz, publishing '{state_name}', \
         following '{cmd_name}' (command timeout {timeout_ms} ms; {})",
        match args.session {
            Session::Controller =>
                "obeying the command publisher announced in the controller's status",
            Session::First => "obeying the first command publisher heard",
        }
    );

    let period_ns = (1e9 / rate_hz).round() as u64;
    let dt = period_ns as f64 * 1e-9;
    let start = monotonic_ns();
    let end = end_time_ns(start, args.duration)?;
    let max_future_ns = (cfg.control.max_future_ms * 1e6) as u64;
    let mut robot = Robot::new(arm, (timeout_ms * 1e6) as u64, max_future_ns, start);
    if args.session == Session::Controller {
        robot.bind_to_controller(SESSION_TIMEOUT_NS);
    }
    anyhow::ensure!(
        args.bind_tolerance.is_finite() && args.bind_tolerance > 0.0,
        "--bind-tolerance {}: must be > 0",
        args.bind_tolerance
    );
    robot.set_bind_tolerance(args.bind_tolerance);
    let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(args.seed);
    let mut seq = 0u64;
    let mut next = start;
    let mut receive_errors = 0u64;

    // The loop: no allocation, no locks, IPC only, absolute deadlines.
    while !stop.load(Ordering::Relaxed) {
        let now = monotonic_ns();
        if now >= end {
            break;
        }
        while let Ok(Some(sample)) = status_sub.receive() {
            robot.on_status(sample.payload(), sample.origin().value(), monotonic_ns());
        }
        loop {
            match cmd_sub.receive() {
                Ok(Some(sample)) => {
                    robot.on_command(sample.payload(), sample.origin().value(), monotonic_ns())
                }
                Ok(None) => break,
                Err(e) => {
                    receive_errors += 1;
                    if receive_errors <= 10 {
                        tracing::warn!("fake-robot: receive failed: {e:?}");
                    }
                    break;
                }
            }
        }
        let now = monotonic_ns();
        let flags = robot.step(now, dt);

        seq += 1;
        let mut msg = JointState {
            seq,
            measurement_time_ns: now,
            n_dof: n_dof as u32,
            status_flags: flags,
            position: robot.arm.position,
            velocity: robot.arm.velocity,
            effort: robot.arm.acceleration,
            ..Default::default()
        };
        msg.set_obeyed_publisher(robot.obeyed_publisher(now));
        if args.noise > 0.0 {
            for p in msg.position.iter_mut().take(n_dof) {
                *p += rng.gen_range(-args.noise..=args.noise);
            }
        }
        match state_pub.loan_uninit() {
            Ok(sample) => match sample.write_payload(msg).send() {
                Ok(_) => robot.counts.states_published += 1,
                Err(e) => tracing::warn!("fake-robot: send failed: {e:?}"),
            },
            Err(e) => tracing::warn!("fake-robot: loan failed: {e:?}"),
        }

        next += period_ns;
        let after = monotonic_ns();
        if after > next {
            let late = after - next;
            robot.counts.max_lateness_ns = robot.counts.max_lateness_ns.max(late);
            if late > 10 * period_ns {
                // Far behind (suspended, overloaded): restart the schedule instead of bursting.
                next = after;
            }
        }
        // Absolute deadline (`sleep_until_ns`), in ≤ 50 ms slices so SIGTERM is seen promptly.
        if !sleep_until_or_stop(next, stop) {
            break;
        }
    }
    tracing::info!("fake-robot: stopping");
    Ok(robot.summary())
}

#[cfg(test)]
mod tests;
