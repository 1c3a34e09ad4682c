//! The safety state machine (`Safety`: the state, its transitions and why), its vocabulary,
//! and its preallocated event ring.
//!
//! ```text
//! STARTING ──fresh joint state + valid chunk──▶ RUNNING ──bad input──▶ HOLD ──hold_to_fault──▶ FAULT
//!                                                  ▲                     │                       │
//!                                                  └──── inputs good ────┘          rearm() ─────┘─▶ STARTING
//!                                                                      (refused while an input is bad)
//! ```
//! Owns: the state and every transition. Must not depend on: chunks, ruckig, IPC (the executor
//! tells it the tick's worst input problem and whether the generator is ready).
//!
//! Transitions are recorded (never logged) inside the tick, into a bounded lock-free ring that
//! another thread drains ([`EventReader::drain`]) and logs.

use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::Arc;

use chunkrt_ipc::{
    CONTROLLER_STATE_FAULT, CONTROLLER_STATE_HOLD, CONTROLLER_STATE_RUNNING,
    CONTROLLER_STATE_STARTING,
};
use crossbeam::queue::ArrayQueue;

/// Controller state.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum State {
    /// Waiting for a fresh joint state (and a first chunk); commands hold the measured pose.
    Starting,
    /// Executing chunks.
    Running,
    /// Braking to zero velocity (jerk-limited) and holding.
    Hold,
    /// Braking and holding until [`crate::control::Executor::rearm`].
    Fault,
}

impl State {
    /// The `CONTROLLER_STATE_*` code published in the status.
    pub fn code(self) -> u32 {
        match self {
            Self::Starting => CONTROLLER_STATE_STARTING,
            Self::Running => CONTROLLER_STATE_RUNNING,
            Self::Hold => CONTROLLER_STATE_HOLD,
            Self::Fault => CONTROLLER_STATE_FAULT,
        }
    }
}

/// Why a transition happened.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Reason {
    /// A fresh joint state and a valid chunk: executing.
    InputsGood,
    /// No joint state yet, or the newest is older than `joint_state_max_age_ms`.
    StaleJointState,
    /// No chunk has arrived yet.
    NoChunk,
    /// A camera the policy uses has no frame, or its newest frame is older than
    /// `frame_max_age_ms` (which: the status's `stale_cameras`).
    StaleCamera,
    /// Every chunk's last action is in the past.
    ChunkExpired,
    /// A chunk (or the sampled target) contained a non-finite value.
    NonFiniteAction,
    /// A chunk had the wrong shape (joint count, empty, zero period).
    BadChunk,
    /// `overrun_streak` consecutive ticks overran.
    Overruns,
    /// HOLD lasted `hold_to_fault_ms`.
    HoldTimeout,
    /// The joint state does not match the configured robot (unrecoverable).
    BadJointState,
    /// ruckig rejected its input (unrecoverable).
    GeneratorError,
    /// Explicit re-arm.
    Rearm,
    /// The chunk source failed (and no chunk came since).
    InferenceError,
    /// The robot obeys another command publisher, or none yet.
    NotObeyed,
}

impl Reason {
    /// A problem that waiting in STARTING does not cure by itself: the policy side or the robot's
    /// session, not an input that is still coming up. After `hold_to_fault_ms` of it, STARTING
    /// goes to FAULT with it as the reason.
    pub fn stuck_in_starting(self) -> bool {
        matches!(
            self,
            Self::NoChunk
                | Self::NonFiniteAction
                | Self::BadChunk
                | Self::ChunkExpired
                | Self::InferenceError
                | Self::NotObeyed
        )
    }
}

impl Reason {
    /// The `STATE_REASON_*` code published in the status.
    pub fn code(self) -> u32 {
        use chunkrt_ipc::*;
        match self {
            Self::InputsGood => STATE_REASON_INPUTS_GOOD,
            Self::StaleJointState => STATE_REASON_STALE_JOINT_STATE,
            Self::NoChunk => STATE_REASON_NO_CHUNK,
            Self::StaleCamera => STATE_REASON_STALE_CAMERA,
            Self::ChunkExpired => STATE_REASON_CHUNK_EXPIRED,
            Self::NonFiniteAction => STATE_REASON_NON_FINITE_ACTION,
            Self::BadChunk => STATE_REASON_BAD_CHUNK,
            Self::Overruns => STATE_REASON_OVERRUNS,
            Self::HoldTimeout => STATE_REASON_HOLD_TIMEOUT,
            Self::BadJointState => STATE_REASON_BAD_JOINT_STATE,
            Self::GeneratorError => STATE_REASON_GENERATOR_ERROR,
            Self::Rearm => STATE_REASON_REARM,
            Self::InferenceError => STATE_REASON_INFERENCE_ERROR,
            Self::NotObeyed => STATE_REASON_NOT_OBEYED,
        }
    }
}

impl std::fmt::Display for Reason {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(chunkrt_ipc::state_reason_name(self.code()))
    }
}

/// One state transition.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Event {
    /// Tick time of the transition (monotonic ns).
    pub t_ns: u64,
    /// Previous state.
    pub from: State,
    /// New state.
    pub to: State,
    /// Why.
    pub reason: Reason,
}

impl std::fmt::Display for Event {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(
            f,
            "{} -> {} at {} ns: {}",
            chunkrt_ipc::controller_state_name(self.from.code()),
            chunkrt_ipc::controller_state_name(self.to.code()),
            self.t_ns,
            self.reason
        )
    }
}

/// The answer to a re-arm request ([`crate::control::Executor::rearm`]).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Rearm {
    /// FAULT → STARTING.
    Accepted,
    /// Not in FAULT (the state it is in).
    NotInFault(State),
    /// An input is still bad.
    InputsBad(Reason),
}

/// The safety state machine (see the module documentation). No allocation after `new`.
pub(crate) struct Safety {
    state: State,
    /// Reason of the last transition.
    reason: Option<Reason>,
    hold_since_ns: u64,
    /// How long the last HOLD lasted (ns), once it ended.
    last_hold_ns: u64,
    /// Since when STARTING has had a problem that waiting does not cure (None: it has not).
    stuck_since_ns: Option<u64>,
    /// Whether STARTING escalates (off for a controller that runs without a chunk source).
    escalate: bool,
    hold_to_fault_ns: u64,
    hold_entries: u64,
    events: EventWriter,
    reader: EventReader,
}

impl Safety {
    /// STARTING; HOLD turns into FAULT after `hold_to_fault_ns`.
    pub fn new(hold_to_fault_ns: u64) -> Self {
        let (events, reader) = event_ring(1024);
        Self {
            state: State::Starting,
            reason: None,
            hold_since_ns: 0,
            last_hold_ns: 0,
            stuck_since_ns: None,
            escalate: true,
            hold_to_fault_ns,
            hold_entries: 0,
            events,
            reader,
        }
    }

    pub fn state(&self) -> State {
        self.state
    }

    /// Why the machine is in its state (the reason of the last transition).
    pub fn reason(&self) -> Option<Reason> {
        self.reason
    }

    /// How long HOLD has lasted at `now_ns`, or, out of HOLD, how long the last one lasted.
    pub fn hold_lasted(&self, now_ns: u64) -> u64 {
        if self.state == State::Hold {
            now_ns.saturating_sub(self.hold_since_ns)
        } else {
            self.last_hold_ns
        }
    }

    /// Times HOLD was entered.
    pub fn hold_entries(&self) -> u64 {
        self.hold_entries
    }

    /// Reader of the transition events.
    pub fn events(&self) -> EventReader {
        self.reader.clone()
    }

    /// One tick's transition. `problem`: the worst input problem this tick (None: inputs good;
    /// [`Reason::BadJointState`] is unrecoverable); `ready`: the generator has a state to move
    /// from. Returns the state left, if the state changed.
    pub fn step(&mut self, now_ns: u64, problem: Option<Reason>, ready: bool) -> Option<State> {
        let from = self.state;
        match (self.state, problem) {
            (State::Fault, _) => {}
            (_, Some(Reason::BadJointState)) => {
                self.transition(now_ns, State::Fault, Reason::BadJointState)
            }
            (State::Starting, None) if ready => {
                self.transition(now_ns, State::Running, Reason::InputsGood)
            }
            (State::Starting, Some(r)) if r.stuck_in_starting() && ready && self.escalate => {
                // the status says why it waits; it escalates after hold_to_fault
                self.reason = Some(r);
                let since = *self.stuck_since_ns.get_or_insert(now_ns);
                if now_ns.saturating_sub(since) >= self.hold_to_fault_ns {
                    self.transition(now_ns, State::Fault, r);
                }
            }
            (State::Starting, r) => {
                self.stuck_since_ns = None;
                if r.is_some() {
                    self.reason = r;
                }
            }
            (State::Running, Some(r)) => self.transition(now_ns, State::Hold, r),
            (State::Running, None) => {}
            (State::Hold, _)
                if now_ns.saturating_sub(self.hold_since_ns) >= self.hold_to_fault_ns =>
            {
                self.transition(now_ns, State::Fault, Reason::HoldTimeout)
            }
            (State::Hold, None) => self.transition(now_ns, State::Running, Reason::InputsGood),
            (State::Hold, Some(_)) => {}
        }
        (self.state != from).then_some(from)
    }

    /// Whether STARTING escalates to FAULT (a controller without a chunk source waits in
    /// STARTING by design, holding the robot).
    pub fn set_escalation(&mut self, on: bool) {
        self.escalate = on;
    }

    /// An unrecoverable problem outside the inputs (the generator failed): FAULT.
    pub fn fault(&mut self, now_ns: u64, reason: Reason) {
        self.transition(now_ns, State::Fault, reason);
    }

    /// FAULT → STARTING, unless not in FAULT or `last_problem` (the last tick's input problem)
    /// is one the robot's side must fix first.
    pub fn rearm(&mut self, now_ns: u64, last_problem: Option<Reason>) -> Rearm {
        if self.state != State::Fault {
            return Rearm::NotInFault(self.state);
        }
        if let Some(r @ (Reason::BadJointState | Reason::StaleJointState | Reason::StaleCamera)) =
            last_problem
        {
            return Rearm::InputsBad(r);
        }
        self.transition(now_ns, State::Starting, Reason::Rearm);
        Rearm::Accepted
    }

    fn transition(&mut self, now_ns: u64, to: State, reason: Reason) {
        if to == self.state {
            return;
        }
        if to == State::Hold {
            self.hold_entries += 1;
            self.hold_since_ns = now_ns;
        }
        if self.state == State::Hold {
            self.last_hold_ns = now_ns.saturating_sub(self.hold_since_ns);
        }
        if to == State::Starting {
            self.stuck_since_ns = None;
        }
        self.events.record(Event {
            t_ns: now_ns,
            from: self.state,
            to,
            reason,
        });
        self.state = to;
        self.reason = Some(reason);
    }
}

struct Ring {
    q: ArrayQueue<Event>,
    dropped: AtomicU64,
}

/// Producer side of the event ring (the control thread).
pub struct EventWriter {
    ring: Arc<Ring>,
}

/// Consumer side of the event ring (a logging thread). Cloneable.
#[derive(Clone)]
pub struct EventReader {
    ring: Arc<Ring>,
}

/// Creates an event ring of `capacity` events (allocated here, never later).
pub fn event_ring(capacity: usize) -> (EventWriter, EventReader) {
    let ring = Arc::new(Ring {
        q: ArrayQueue::new(capacity.max(1)),
        dropped: AtomicU64::new(0),
    });
    (EventWriter { ring: ring.clone() }, EventReader { ring })
}

impl EventWriter {
    /// Records an event; if the ring is full the event is counted as dropped. Lock-free,
    /// no allocation.
    pub fn record(&self, e: Event) {
        if self.ring.q.push(e).is_err() {
            self.ring.dropped.fetch_add(1, Ordering::Relaxed);
        }
    }
}

impl EventReader {
    /// Calls `f` for every waiting event, oldest first.
    pub fn drain(&self, mut f: impl FnMut(Event)) {
        while let Some(e) = self.ring.q.pop() {
            f(e);
        }
    }

    /// Events lost because the ring was full.
    pub fn dropped(&self) -> u64 {
        self.ring.dropped.load(Ordering::Relaxed)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn machine_moves_only_on_the_documented_edges() {
        let mut m = Safety::new(1_000);
        // STARTING waits for the generator and good inputs
        assert_eq!(m.step(0, None, false), None);
        assert_eq!(m.step(1, Some(Reason::NoChunk), true), None);
        assert_eq!(m.step(2, None, true), Some(State::Starting));
        assert_eq!(m.state(), State::Running);
        // RUNNING → HOLD on any recoverable problem, counted, with the reason
        assert_eq!(
            m.step(3, Some(Reason::StaleCamera), true),
            Some(State::Running)
        );
        assert_eq!(
            (m.state(), m.reason()),
            (State::Hold, Some(Reason::StaleCamera))
        );
        assert_eq!(m.hold_entries(), 1);
        // HOLD → RUNNING when the inputs are good again, → FAULT after hold_to_fault
        assert_eq!(m.step(4, None, true), Some(State::Hold));
        m.step(10, Some(Reason::ChunkExpired), true);
        assert_eq!(m.step(500, Some(Reason::ChunkExpired), true), None);
        assert_eq!(
            m.step(1_010, Some(Reason::ChunkExpired), true),
            Some(State::Hold)
        );
        assert_eq!(
            (m.state(), m.reason()),
            (State::Fault, Some(Reason::HoldTimeout))
        );
        // FAULT stays FAULT whatever the inputs; re-arm is refused while an input is bad
        assert_eq!(m.step(1_011, None, true), None);
        assert_eq!(
            m.rearm(1_012, Some(Reason::StaleJointState)),
            Rearm::InputsBad(Reason::StaleJointState)
        );
        assert_eq!(m.rearm(1_013, Some(Reason::ChunkExpired)), Rearm::Accepted);
        assert_eq!(m.state(), State::Starting);
        assert_eq!(m.rearm(1_014, None), Rearm::NotInFault(State::Starting));
        // a joint state of the wrong robot is unrecoverable from any state but FAULT
        assert_eq!(
            m.step(1_015, Some(Reason::BadJointState), false),
            Some(State::Starting)
        );
        assert_eq!(m.state(), State::Fault);
        let mut events = Vec::new();
        m.events().drain(|e| events.push((e.from, e.to)));
        assert_eq!(events.len(), 7, "{events:?}");
    }

    #[test]
    fn starting_escalates_when_the_policy_never_delivers() {
        let mut m = Safety::new(1_000);
        // no joint state yet: waiting is normal, no escalation, the status says why
        assert_eq!(m.step(0, Some(Reason::StaleJointState), false), None);
        assert_eq!(m.step(5_000, Some(Reason::StaleJointState), false), None);
        assert_eq!(m.reason(), Some(Reason::StaleJointState));
        // the generator is ready but no chunk comes: FAULT after hold_to_fault, naming why
        assert_eq!(m.step(6_000, Some(Reason::NoChunk), true), None);
        assert_eq!(m.reason(), Some(Reason::NoChunk));
        assert_eq!(m.step(6_500, Some(Reason::InferenceError), true), None);
        assert_eq!(m.reason(), Some(Reason::InferenceError));
        assert_eq!(
            m.step(7_000, Some(Reason::InferenceError), true),
            Some(State::Starting)
        );
        assert_eq!(
            (m.state(), m.reason()),
            (State::Fault, Some(Reason::InferenceError))
        );
        // re-armed, the clock starts again
        assert_eq!(m.rearm(7_100, None), Rearm::Accepted);
        assert_eq!(m.step(7_200, Some(Reason::NonFiniteAction), true), None);
        assert_eq!(m.step(8_100, Some(Reason::NonFiniteAction), true), None);
        assert_eq!(
            m.step(8_200, Some(Reason::NonFiniteAction), true),
            Some(State::Starting)
        );
        assert_eq!(m.reason(), Some(Reason::NonFiniteAction));
    }

    #[test]
    fn ring_keeps_order_and_counts_drops() {
        let (w, r) = event_ring(2);
        for i in 0..3 {
            w.record(Event {
                t_ns: i,
                from: State::Running,
                to: State::Hold,
                reason: Reason::ChunkExpired,
            });
        }
        let mut got = Vec::new();
        r.drain(|e| got.push(e.t_ns));
        assert_eq!(got, vec![0, 1]);
        assert_eq!(r.dropped(), 1);
        assert_eq!(State::Fault.code(), CONTROLLER_STATE_FAULT);
        let e = Event {
            t_ns: 5,
            from: State::Running,
            to: State::Hold,
            reason: Reason::StaleJointState,
        };
        assert_eq!(
            e.to_string(),
            "running -> hold at 5 ns: joint state missing or stale"
        );
    }
}
