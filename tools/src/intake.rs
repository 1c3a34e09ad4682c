//! The robot's side of chunkrt's command contract, for every robot process written in Rust
//! (`fake-robot`, the Franka driver): which commands it obeys and when it stops obeying.
//!
//! In order, for each received command: boundary validation; the session (only the command
//! publisher the controller's status announces, [`SessionGate`], or with no session the first
//! publisher heard); the stream (increasing `seq`, nothing from the future, one publisher at a
//! time, [`StreamGuard`]); the deadline; and the bumpless rule — the first command of a session,
//! and the first after the robot held, must start within `bind_tolerance` of the measured
//! position (else `COMMAND_FAR`: the controller re-seeds from the measured position). A command
//! is live while its deadline has not passed and no command timeout has elapsed.
//! No allocation.

use chunkrt_ipc::{
    validate_joint_command, ControllerStatus, Freshness, JointCommand, SessionGate, SessionState,
    StreamGuard, ValidationError, JOINT_STATUS_COMMAND_EXPIRED, JOINT_STATUS_COMMAND_FAR,
    JOINT_STATUS_COMMAND_REJECTED, JOINT_STATUS_COMMAND_TIMEOUT,
};

/// What the intake counted.
#[derive(Debug, Clone, Copy, Default, PartialEq)]
pub struct IntakeCounters {
    /// Commands accepted.
    pub commands_applied: u64,
    /// Commands received after their deadline (ignored).
    pub commands_expired: u64,
    /// Commands that failed validation, arrived out of order or came from a publisher other
    /// than the session's controller.
    pub commands_rejected: u64,
    /// Commands ignored while the robot has no session (before the first status, or while a
    /// second status publisher made it ambiguous).
    pub commands_unbound: u64,
    /// Commands refused for starting further than the bind tolerance from the arm.
    pub commands_far: u64,
    /// Controller statuses refused.
    pub status_rejected: u64,
    /// Largest distance between an accepted command's position and the measured position when
    /// it was accepted (any joint).
    pub max_command_offset: f64,
}

/// One robot's command intake.
#[derive(Debug, Clone)]
pub struct CommandIntake {
    n_dof: usize,
    command_timeout_ns: u64,
    max_future_ns: u64,
    guard: StreamGuard,
    session: Option<SessionGate>,
    session_id: Option<u128>,
    armed: bool,
    bind_tolerance: f64,
    active: Option<JointCommand>,
    last_command_ns: u64,
    /// Sticky flags of the last received command (`EXPIRED`, `REJECTED`, `FAR`).
    command_flags: u32,
    /// The name the intake logs under.
    who: &'static str,
    /// Counters.
    pub counters: IntakeCounters,
}

impl CommandIntake {
    /// An intake for `n_dof` joints; `now_ns` starts the command timeout.
    pub fn new(
        who: &'static str,
        n_dof: usize,
        command_timeout_ns: u64,
        max_future_ns: u64,
        now_ns: u64,
    ) -> Self {
        Self {
            n_dof,
            command_timeout_ns,
            max_future_ns,
            // one controller at a time: another command publisher is refused while the bound
            // one is alive; after a command timeout of silence (the robot holds) one may bind
            guard: StreamGuard::with_rebind_after(command_timeout_ns),
            session: None,
            session_id: None,
            armed: false,
            bind_tolerance: f64::INFINITY,
            active: None,
            last_command_ns: now_ns,
            command_flags: 0,
            who,
            counters: IntakeCounters::default(),
        }
    }

    /// Obeys only the command publisher announced by the controller's status from now on.
    pub fn bind_to_controller(&mut self, timeout_ns: u64) {
        self.session = Some(SessionGate::new(timeout_ns, self.max_future_ns));
    }

    /// Refuses the first command of a session, and the first after a hold, when it starts
    /// further than `tolerance` from the measured position (bumpless hand-over).
    pub fn set_bind_tolerance(&mut self, tolerance: f64) {
        self.bind_tolerance = tolerance;
    }

    /// The command publisher the robot obeys, as its joint state reports it: the session's
    /// controller (or, with no session, the bound publisher); 0 while none.
    pub fn obeyed_publisher(&self, now_ns: u64) -> u128 {
        match &self.session {
            Some(gate) => match gate.state(now_ns) {
                SessionState::Bound(id) => id,
                _ => 0,
            },
            None => self.guard.bound().unwrap_or(0),
        }
    }

    /// Handles one controller status from publisher `origin` (session binding).
    pub fn on_status(&mut self, status: &ControllerStatus, origin: u128, now_ns: u64) {
        let Some(gate) = self.session.as_mut() else {
            return;
        };
        if let Err(e) = gate.on_status(status, origin, now_ns) {
            self.counters.status_rejected += 1;
            if self.counters.status_rejected <= 10 {
                tracing::warn!(
                    "{}: controller status from publisher {origin:#x} rejected: {e}",
                    self.who
                );
            }
        }
        if let SessionState::Bound(id) = gate.state(now_ns) {
            if self.session_id != Some(id) {
                // a new controller: its command stream starts afresh
                tracing::info!("{}: session bound to command publisher {id:#x}", self.who);
                self.session_id = Some(id);
                self.armed = false;
                self.guard = StreamGuard::with_rebind_after(self.command_timeout_ns);
            }
        }
    }

    /// Handles one received command from publisher `origin`, the arm being at `measured`.
    /// Returns true when the command was accepted.
    pub fn on_command(
        &mut self,
        cmd: &JointCommand,
        origin: u128,
        now_ns: u64,
        measured: &[f64],
    ) -> bool {
        if let Err(e) = validate_joint_command(cmd, Some(self.n_dof as u32)) {
            self.reject(&e);
            return false;
        }
        if let Some(gate) = &self.session {
            match gate.admit(origin, now_ns) {
                Ok(()) => {}
                Err(ValidationError::NotSessionPublisher {
                    session: SessionState::None | SessionState::Ambiguous,
                    ..
                }) => {
                    self.counters.commands_unbound += 1;
                    return false;
                }
                Err(e) => {
                    self.reject(&e);
                    return false;
                }
            }
        }
        let limits = Freshness {
            max_age_ns: u64::MAX,
            max_future_ns: self.max_future_ns,
        };
        if let Err(e) = self
            .guard
            .check(origin, cmd.seq, cmd.publish_time_ns, now_ns, limits)
        {
            self.reject(&e);
            return false;
        }
        if cmd.deadline_ns < now_ns {
            self.counters.commands_expired += 1;
            self.command_flags = JOINT_STATUS_COMMAND_EXPIRED;
            return false;
        }
        let offset = (0..self.n_dof.min(measured.len()))
            .map(|j| (cmd.position[j] - measured[j]).abs())
            .fold(0.0, f64::max);
        if now_ns.saturating_sub(self.last_command_ns) > self.command_timeout_ns {
            // no command accepted for longer than the timeout (the robot held, or this process
            // was stalled and its hold not yet noticed): the next one must start near the arm
            self.armed = false;
        }
        if !self.armed {
            if offset > self.bind_tolerance {
                // a session's first command, or the first after a hold, far from the arm
                self.counters.commands_far += 1;
                self.command_flags = JOINT_STATUS_COMMAND_FAR;
                return false;
            }
            self.armed = true;
        }
        self.counters.max_command_offset = self.counters.max_command_offset.max(offset);
        self.counters.commands_applied += 1;
        self.command_flags = 0;
        self.last_command_ns = now_ns;
        self.active = Some(*cmd);
        true
    }

    fn reject(&mut self, e: &ValidationError) {
        self.counters.commands_rejected += 1;
        self.command_flags = JOINT_STATUS_COMMAND_REJECTED;
        if self.counters.commands_rejected <= 10 {
            tracing::warn!("{}: command rejected: {e}", self.who);
        }
    }

    /// No command accepted for longer than the command timeout.
    pub fn timed_out(&self, now_ns: u64) -> bool {
        now_ns.saturating_sub(self.last_command_ns) > self.command_timeout_ns
    }

    /// The command to follow at `now_ns`: the newest accepted one, while its deadline has not
    /// passed and the command timeout has not elapsed.
    pub fn live(&self, now_ns: u64) -> Option<&JointCommand> {
        match &self.active {
            Some(c) if c.deadline_ns >= now_ns && !self.timed_out(now_ns) => Some(c),
            _ => None,
        }
    }

    /// The newest accepted command, live or not.
    pub fn latest(&self) -> Option<&JointCommand> {
        self.active.as_ref()
    }

    /// The robot itself was silent for `ns` beyond its cycle (a robot-clocked driver that had no
    /// state to answer: a simulator's stall). The command timeout measures the controller's
    /// silence while the robot asks: that time does not count against it. (franka-sim stalled
    /// 16 ms on a loaded machine; the controller's next command, 20 ms after the last the
    /// driver accepted, was taken as a new session's and refused as far from the lagging arm,
    /// and the controller re-seeded from it: 0.19 rad from its own motion after.) A robot that
    /// stopped meanwhile (the FCI's own stop after 20 lost cycles) restarts its motion, which
    /// disarms the intake.
    pub fn robot_silent(&mut self, ns: u64) {
        self.last_command_ns = self.last_command_ns.saturating_add(ns);
    }

    /// The robot began to hold: the next command must start near the arm again.
    pub fn disarm(&mut self) {
        self.armed = false;
    }

    /// The flags the robot reports for its commands at `now_ns`: the last command's
    /// (`EXPIRED`, `REJECTED`, `FAR`) and `COMMAND_TIMEOUT`.
    pub fn flags(&self, now_ns: u64) -> u32 {
        let mut f = self.command_flags;
        if self.timed_out(now_ns) {
            f |= JOINT_STATUS_COMMAND_TIMEOUT;
        }
        f
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn command(seq: u64, t: u64, q0: f64) -> JointCommand {
        let mut c = JointCommand {
            seq,
            publish_time_ns: t,
            deadline_ns: t + 2_000_000,
            n_dof: 2,
            ..Default::default()
        };
        c.position[0] = q0;
        c
    }

    #[test]
    fn a_robots_own_silence_does_not_time_the_controller_out() {
        // a bound, armed session; then 25 ms without a state (the robot's, 24 ms of it beyond
        // its cycle), and the controller's next command 0.05 rad from the lagging arm
        for credited in [true, false] {
            let t0 = 1_000_000_000;
            let mut intake = CommandIntake::new("test", 2, 20_000_000, 5_000_000, t0);
            intake.set_bind_tolerance(0.02);
            assert!(intake.on_command(&command(1, t0, 0.0), 7, t0, &[0.0, 0.0]));
            let t1 = t0 + 25_000_000;
            if credited {
                intake.robot_silent(24_000_000);
            }
            let ok = intake.on_command(&command(2, t1, 0.05), 7, t1, &[0.0, 0.0]);
            assert_eq!(ok, credited, "credited {credited}");
            assert_eq!(intake.counters.commands_far, u64::from(!credited));
        }
    }
}
