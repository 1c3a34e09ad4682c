//! What the driver sends the FR3 every cycle: the controller's position when it keeps within the
//! robot's limits, the nearest that does when it would not, a continuation when the controller's
//! answer is late, and a jerk-limited stop when the controller is gone.
//!
//! The robot judges the commanded positions by their differences over its 1 ms cycle: velocity
//! within the position-dependent envelope, acceleration and jerk within their limits
//! ([`crate::limits`]). Every path here keeps those differences within the limits:
//! - [`Guard::follow`]: a desired position passes unchanged when its differences are within
//!   `margin` × the limits; otherwise the guard moves towards the desired position and velocity
//!   with a jerk-limited trajectory generator (ruckig's position interface, the generator chunkrt's
//!   controller shapes with) inside a slower set of limits, so the robot sees a continuous motion
//!   that converges onto the controller's.
//! - [`Guard::extrapolate`]: one cycle at constant acceleration (what the robot itself assumes
//!   for a lost packet) when that stays within the limits, else the stop.
//! - [`Guard::brake`]: one cycle of the time-optimal stop to rest (ruckig's velocity interface).
//!
//! The generator's limits leave room for what differencing at 1 kHz adds to its own (0.8 × the
//! robot's acceleration and jerk, positions 0.15 rad inside the envelope's limits; every step
//! passes `enforce`, which holds the acceleration in the band that keeps the velocity under the
//! envelope). [`Motion`] holds what the robot computes: differences of the commanded positions.
//! No allocation after [`Guard::new`].

use chunkrt_rt::otg::{Otg, OtgInput, OtgOutput, OtgResult, CONTROL_POSITION, CONTROL_VELOCITY};

use crate::limits::{
    DDDQ_MAX, DDQ_MAX, DQ_MAX, ENVELOPE_DECEL, ENVELOPE_EPS, ENVELOPE_OFFSET, ENVELOPE_Q_MAX,
    ENVELOPE_Q_MIN, JOINTS, Q_MAX, Q_MIN,
};

/// The motion commanded last as the robot sees it: positions and their first and second
/// differences over the cycle.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Motion {
    /// Commanded positions (rad).
    pub q: [f64; JOINTS],
    /// Their velocity over the last cycle (rad/s).
    pub dq: [f64; JOINTS],
    /// Their acceleration over the last cycle (rad/s²).
    pub ddq: [f64; JOINTS],
}

impl Motion {
    /// At rest at `q`.
    pub fn rest(q: [f64; JOINTS]) -> Self {
        Self {
            q,
            dq: [0.0; JOINTS],
            ddq: [0.0; JOINTS],
        }
    }

    /// Whether every joint is at rest.
    pub fn at_rest(&self) -> bool {
        self.dq.iter().chain(&self.ddq).all(|v| v.abs() < 1e-9)
    }

    /// The motion that reaches `q` one cycle of `dt` after `prev`, as the robot differences it.
    pub fn after(prev: &Motion, q: &[f64; JOINTS], dt: f64) -> Motion {
        let mut m = *prev;
        for (j, &q) in q.iter().enumerate() {
            let v = (q - prev.q[j]) / dt;
            m.ddq[j] = (v - prev.dq[j]) / dt;
            m.dq[j] = v;
            m.q[j] = q;
        }
        m
    }

    /// The velocity and acceleration at the last position of a motion at constant acceleration
    /// whose differences these are: a backward difference lags the velocity by half a cycle's
    /// acceleration. A plan that took the difference for the velocity (a restart of the guard's
    /// offset after a late cycle did) halves the acceleration on its first step: a jerk of
    /// `ddq / (2 dt)`, 3 800 rad/s³ at 7.6 rad/s², too much for the next answer to pass from
    /// both histories should that step go out late ([`Guard::hedge`]).
    pub fn rates(&self, dt: f64) -> ([f64; JOINTS], [f64; JOINTS]) {
        let mut v = self.dq;
        for (j, v) in v.iter_mut().enumerate() {
            *v += 0.5 * self.ddq[j] * dt;
        }
        (v, self.ddq)
    }

    /// The robot's own next cycle when no command came: the last command continued at constant
    /// acceleration (FCI's rule for a lost motion-generator packet).
    pub fn continued(&self, dt: f64) -> Motion {
        let mut q = self.q;
        for (j, q) in q.iter_mut().enumerate() {
            *q += (self.dq[j] + self.ddq[j] * dt) * dt;
        }
        Motion::after(self, &q, dt)
    }
}

/// How the robot's own report of its reference was taken ([`reconcile`]).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Reference {
    /// It is the candidate of this index, exactly (the robot's f32 report agrees with it).
    Candidate(usize),
    /// Its position is the candidate of this index (exact), its velocity and acceleration the
    /// robot's report (they disagree with the candidate's: the robot differenced against
    /// another history than the one this driver assumed).
    Corrected(usize),
    /// No candidate's position agrees with the report within `ADOPT_RAD`: the report itself
    /// (f32-rounded).
    Adopted,
    /// The report is not finite or lies further than `ADOPT_RAD` from every candidate: the
    /// first candidate, the robot's report set aside (counted; it should not happen).
    Kept,
}

/// How far a report may lie from this driver's own candidates and still be taken (rad): a lost
/// or late answer parts the robot from a candidate by micro-radians; more is not a reference
/// this driver can reason about.
pub const ADOPT_RAD: f64 = 1e-3;

/// Whether an f64 value and the robot's f32 report of the same quantity agree: the value
/// rounds to the report, or to within `ulps` f32 steps of it, or lies within `slack` of it.
fn agrees(exact: f64, reported: f64, ulps: u32, slack: f64) -> bool {
    let (a, b) = (exact as f32, reported as f32);
    if a == b || (exact - reported).abs() <= slack {
        return true;
    }
    if !a.is_finite() || !b.is_finite() || a.is_sign_negative() != b.is_sign_negative() {
        return false;
    }
    a.to_bits().abs_diff(b.to_bits()) <= ulps
}

/// Whether a motion's velocity and acceleration and the robot's f32 report of them agree: within
/// 1e-7 rad/s and 1e-4 rad/s² (1e-4 rad/s² and 0.1 rad/s³ in the next command), or two f32 steps.
fn derivatives_agree(exact: &Motion, reported: &Motion) -> bool {
    (0..JOINTS).all(|j| {
        agrees(exact.dq[j], reported.dq[j], 2, 1e-7)
            && agrees(exact.ddq[j], reported.ddq[j], 2, 1e-4)
    })
}

/// The robot's reference (the motion it will judge the next command against) from its report
/// (`q_d`, `dq_d`, `ddq_d`: on FCI 10 f32, the last command the robot applied and its
/// differences, the extrapolated one after a lost packet) and this driver's exact candidates
/// for it (what it believes the robot applied: its own answer, or the reference continued when
/// the answer was dropped). A candidate the report agrees with is taken exactly: the report's
/// f32 positions alone would misstate the next command's acceleration by up to 0.1 rad/s² and
/// its jerk by 100 rad/s³. One whose position agrees but whose derivatives do not keeps its
/// exact position with the report's derivatives (their f32 error is below 1e-3 rad/s³ of jerk).
/// libfranka's `limitRate` limits every command against the same three fields.
pub fn reconcile(reported: &Motion, candidates: &[Motion]) -> (Motion, Reference) {
    let finite = reported
        .q
        .iter()
        .chain(&reported.dq)
        .chain(&reported.ddq)
        .all(|x| x.is_finite());
    let Some(first) = candidates.first() else {
        return (*reported, Reference::Adopted);
    };
    if !finite {
        return (*first, Reference::Kept);
    }
    // a position must round to the report: one f32 step at 2 rad is 2.4e-7 rad, which is
    // 0.24 rad/s² in the next command's acceleration
    let q_agrees = |c: &Motion| (0..JOINTS).all(|j| agrees(c.q[j], reported.q[j], 0, 0.0));
    let all_agree = |c: &Motion| q_agrees(c) && derivatives_agree(c, reported);
    if let Some(i) = candidates.iter().position(all_agree) {
        return (candidates[i], Reference::Candidate(i));
    }
    if let Some(i) = candidates.iter().position(q_agrees) {
        let m = Motion {
            q: candidates[i].q,
            dq: reported.dq,
            ddq: reported.ddq,
        };
        return (m, Reference::Corrected(i));
    }
    let near = candidates
        .iter()
        .any(|c| (0..JOINTS).all(|j| (c.q[j] - reported.q[j]).abs() <= ADOPT_RAD));
    if near {
        (*reported, Reference::Adopted)
    } else {
        (*first, Reference::Kept)
    }
}

/// Whether a report that moved to a candidate's position still carries `before`'s velocity and
/// acceleration (the reference of the cycle before, the one the last answer was computed
/// against): a state packed between the robot's update of `q_d` and of its derivatives. The
/// FCI's reports are consistent; franka-sim's publish thread packs such a state when its drain
/// gate gives up on a starved machine. Taken as the robot's derivatives, they are a cycle old:
/// the next answer continued the old velocity, a jerk of `ddq / dt` against the robot's own
/// history (8 300 rad/s³ at 8.3 rad/s², twice in a loaded run). Only where the candidate's own
/// derivatives differ (a report that agrees with a candidate is taken as it is).
pub fn torn(reported: &Motion, before: &Motion) -> bool {
    derivatives_agree(before, reported)
        && (0..JOINTS).any(|j| (reported.q[j] - before.q[j]).abs() > 1e-9)
}

/// The limits a command passes unchanged within: `margin` × the FR3's acceleration, jerk and
/// velocity envelope, inside the stricter of the datasheet's and the envelope's position range.
#[derive(Debug, Clone, Copy)]
pub struct GuardLimits {
    /// Acceleration limit (rad/s²).
    pub ddq: f64,
    /// Jerk limit (rad/s³).
    pub dddq: f64,
    /// Velocity limit per joint (rad/s).
    pub dq: [f64; JOINTS],
    /// Position range per joint (rad).
    pub q_min: [f64; JOINTS],
    /// Position range per joint (rad).
    pub q_max: [f64; JOINTS],
}

/// Positions the generator keeps inside the envelope's limits (rad).
const GENERATOR_POSITION_MARGIN: f64 = 0.15;
/// Room kept below the robot's velocity envelope near a position limit (rad/s), and the share of
/// the envelope commanded at most: the robot judges the arm's *measured* velocity against it,
/// and the measured velocity runs past the commanded one by an amount that grows with it.
/// franka-sim: 0.15 rad/s when a joint brakes along the envelope at speed under gravity
/// (`joint_velocity_violation`, joint 2 at 1.35 rad/s against 1.20, DROID's all -1); half the
/// commanded velocity for a few cycles after its physics loop ran a few milliseconds late on a
/// loaded machine (joint 3 at 2.01 rad/s for 1.32 commanded; a fresh-clone CI: joint 4 at 1.70
/// against 1.54 at the rectangular range's 1.125). At 0.6 the arm may run 1.67 times the command.
const ENVELOPE_TRACKING: f64 = 0.25;
const ENVELOPE_SHARE: f64 = 0.6;
/// Fraction of the robot's acceleration the generator (and the stop) plans with.
const GENERATOR_MARGIN: f64 = 0.7;
/// Fraction of the robot's jerk the generator plans with: the controller's own (0.5,
/// config/franka_fr3.toml), under 2/3 of the guard's, so that the answer after one of its steps
/// that went out late can still pass from both histories ([`Guard::hedge`]; at 0.7 a stop's
/// steps jerked at up to 2 917 rad/s³, past the 2 767 that leaves).
const GENERATOR_JERK: f64 = 0.5;

impl GuardLimits {
    /// The FR3's limits scaled by `margin` (0 < margin ≤ 1), positions `position_margin` inside.
    pub fn fr3(margin: f64, position_margin: f64) -> Self {
        let mut l = Self {
            ddq: DDQ_MAX * margin,
            dddq: DDDQ_MAX * margin,
            dq: [0.0; JOINTS],
            q_min: [0.0; JOINTS],
            q_max: [0.0; JOINTS],
        };
        for j in 0..JOINTS {
            l.dq[j] = DQ_MAX[j] * margin;
            l.q_min[j] = Q_MIN[j].max(ENVELOPE_Q_MIN[j]) + position_margin;
            l.q_max[j] = Q_MAX[j].min(ENVELOPE_Q_MAX[j]) - position_margin;
        }
        l
    }

    /// The envelope's highest velocity at `q` against this range (rad/s), with a deceleration of
    /// at most 0.6 × this guard's acceleration limit: the tables give joints 5 and 7 17 rad/s²,
    /// more than any command may slow down, and an envelope that closes as fast as the motion
    /// can brake cannot be followed under the jerk limit. Stricter than the robot's, never looser.
    pub fn upper(&self, j: usize, q: f64) -> f64 {
        let room = (2.0 * ENVELOPE_DECEL[j].min(0.6 * self.ddq) * (self.q_max[j] - q))
            .max(0.0)
            .sqrt();
        self.dq[j].min(Self::kept_below(j, room)) - ENVELOPE_EPS
    }

    /// The envelope's lowest velocity at `q` against this range (rad/s).
    pub fn lower(&self, j: usize, q: f64) -> f64 {
        let room = (2.0 * ENVELOPE_DECEL[j].min(0.6 * self.ddq) * (q - self.q_min[j]))
            .max(0.0)
            .sqrt();
        -self.dq[j].min(Self::kept_below(j, room)) + ENVELOPE_EPS
    }

    /// The speed commanded at most where the envelope's speed is `room - offset`: its share,
    /// and at least the tracking room below it.
    fn kept_below(j: usize, room: f64) -> f64 {
        let v = room - ENVELOPE_OFFSET[j];
        (v - ENVELOPE_TRACKING.max((1.0 - ENVELOPE_SHARE) * v)).max(0.0)
    }

    /// How fast the envelope's upper bound closes (rad/s²) for joint `j` at `q` moving at `v`
    /// (towards the upper limit: `v > 0`), and the lower bound's, as the band must anticipate.
    fn closing(&self, j: usize, q: f64, v: f64) -> (f64, f64) {
        let d = ENVELOPE_DECEL[j].min(0.6 * self.ddq);
        let rate = |room: f64, speed: f64| {
            // (the envelope's own rate bounds its share's)
            if speed <= 0.0 || Self::kept_below(j, room) >= self.dq[j] {
                0.0
            } else {
                d * speed / room.max(1e-3)
            }
        };
        let up = rate((2.0 * d * (self.q_max[j] - q)).max(0.0).sqrt(), v);
        let down = rate((2.0 * d * (q - self.q_min[j])).max(0.0).sqrt(), -v);
        (up, down)
    }

    /// The acceleration band at joint `j`'s state (`q`, `v`): the accelerations from which the
    /// velocity can still be kept inside the envelope under the jerk limit, its closing
    /// anticipated.
    fn band(&self, j: usize, q: f64, v: f64) -> (f64, f64) {
        let k = self.dddq / self.ddq;
        let (up, down) = self.closing(j, q, v);
        (
            k * (self.lower(j, q) - v) + down,
            k * (self.upper(j, q) - v) - up,
        )
    }

    /// Which limit reaching `q` from `prev` in one cycle breaks for joint `j`
    /// ([`Broken`]), or `None`.
    fn broken(&self, j: usize, prev: &Motion, q: f64, dt: f64) -> Option<Broken> {
        let v = (q - prev.q[j]) / dt;
        let a = (v - prev.dq[j]) / dt;
        let jerk = (a - prev.ddq[j]) / dt;
        // the velocity inside the envelope, and an acceleration from which it can stay inside
        // under the jerk limit (the band every path keeps to, so that a later one can always
        // continue)
        let (lo, hi) = self.band(j, prev.q[j], v);
        let velocity_ok = (self.lower(j, prev.q[j])..=self.upper(j, prev.q[j])).contains(&v)
            && a <= hi + 1e-9
            && a >= lo - 1e-9;
        if !q.is_finite() {
            Some(Broken::NotFinite)
        } else if !((self.q_min[j]..=self.q_max[j]).contains(&q) || (q - prev.q[j]).abs() < 1e-12) {
            Some(Broken::Position)
        } else if !velocity_ok {
            Some(Broken::Velocity)
        } else if a.abs() > self.ddq {
            Some(Broken::Acceleration)
        } else if jerk.abs() > self.dddq {
            Some(Broken::Jerk)
        } else {
            None
        }
    }

    fn passes(&self, j: usize, prev: &Motion, q: f64, dt: f64) -> bool {
        self.broken(j, prev, q, dt).is_none()
    }
}

/// The limit a desired position would break (what the guard counts when it acts).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Broken {
    /// Not a number.
    NotFinite = 0,
    /// Outside the position range.
    Position = 1,
    /// Outside the velocity envelope.
    Velocity = 2,
    /// Acceleration past the limit.
    Acceleration = 3,
    /// Jerk past the limit.
    Jerk = 4,
}

impl Broken {
    /// Names, by code.
    pub const NAMES: [&'static str; 5] =
        ["not_finite", "position", "velocity", "acceleration", "jerk"];
}

/// The per-cycle guard. One per driver (it owns the trajectory generator of its fallbacks).
pub struct Guard {
    limits: GuardLimits,
    dt: f64,
    otg: Otg,
    input: OtgInput,
    out: OtgOutput,
    /// Why [`Self::follow`] acted, counted by [`Broken`] code (the first limit a desired position broke).
    pub acted: [u64; 5],
    /// The generator's own state after its last step (position, velocity, acceleration): the
    /// next step continues from it when the motion is still the one it made (the differences
    /// the robot sees lag it by half a cycle, and restarting from them would slow it).
    planned: Option<([f64; JOINTS], [f64; JOINTS], [f64; JOINTS])>,
    /// The brake's own plan, which a `follow` in the same cycle (its command then refused, the
    /// arm braked instead: the driver's geometry and following checks) does not overwrite:
    /// restarted each cycle from the robot's differences, which lag by half a cycle, the
    /// brake's deceleration would settle at a sixth of its jerk per cycle (1.2 rad/s²).
    brake_plan: Option<([f64; JOINTS], [f64; JOINTS], [f64; JOINTS])>,
    /// The offset between the stream sent and the controller's motion while it is taken out
    /// ([`Self::follow`]): its own generator, its state.
    offset_otg: Otg,
    offset_in: OtgInput,
    offset_out: OtgOutput,
    offset: Option<Offset>,
    /// The first limit the last [`Self::follow`]'s candidate command broke, as (joint, code
    /// of [`Broken`]), when one did: the desired position's, else the offset's (diagnostics).
    pub broke: Option<(u8, u8)>,
    /// Which path the last [`Self::follow`] took: 0 passed, 1 offset, 2 offset started,
    /// 3 generator (for tests and diagnostics). 0–2: the controller's motion leads.
    pub path: u8,
    /// The last desired position and its difference velocity: what the next desired velocity
    /// field is checked against.
    desired: Option<([f64; JOINTS], [f64; JOINTS])>,
    /// The generator leads ([`Self::follow`]'s last resort: a desired position that is not a
    /// number, or one further than `TAKE_OVER_RAD` from the stream) until an offset from the
    /// stream to the controller's motion is within `HAND_BACK_RAD`.
    generating: bool,
    /// Offset steps [`Self::enforce`] had to hold within the limits (the offset then goes on
    /// from what was sent).
    pub enforced: u64,
    /// This cycle's desired velocity and acceleration agreed with the desired positions'
    /// differences (no jump, no noise).
    fields_agree: bool,
    /// This cycle's desired positions' own first and second differences (the velocity and
    /// acceleration fields where there is no earlier desired position).
    desired_diff: ([f64; JOINTS], [f64; JOINTS]),
    /// The controller's acceleration (as taken) at the last [`Self::follow`], and its jerk
    /// since the one before (zero where there was none): what the offset's jerk leaves.
    desired_a: Option<[f64; JOINTS]>,
    desired_jerk: [f64; JOINTS],
}

/// The largest of a joint vector's magnitudes.
fn size(x: &[f64; JOINTS]) -> f64 {
    x.iter().fold(0.0, |m, v| m.max(v.abs()))
}

/// An offset (stream minus the controller's motion): position, velocity, acceleration.
type Offset = ([f64; JOINTS], [f64; JOINTS], [f64; JOINTS]);

/// The largest offset (rad, any joint) the controller's motion plus a correction carries: past
/// it (a jump no lost cycle makes) the generator leads, and hands back below `HAND_BACK_RAD`.
const TAKE_OVER_RAD: f64 = 0.15;
const HAND_BACK_RAD: f64 = 0.1;

/// The share of the guard's jerk limit its own steps keep to ([`Guard::enforce`]): an answer
/// that went out late and that the robot (a simulator) applied after all leaves two histories,
/// the robot's continuation and that answer, parted by three times its jerk, and the next answer
/// must pass from both within the guard's limits ([`Guard::hedge`]): possible under 2/3. At the
/// full limit an offset's steps after a restart jerked at 4 150 rad/s³ (the unit test below; a
/// fresh-clone CI's trace: 4 000-4 849 in its offset phases).
const HEDGEABLE_JERK: f64 = 2.0 / 3.0 * (1.0 - 1e-3);

/// The offset's limits, as fractions of the robot's: what the controller's own motion leaves
/// when it keeps to 0.8 of them (config/franka_fr3.toml), less the guard's margin.
const OFFSET_VELOCITY: f64 = 0.1;
const OFFSET_ACCELERATION: f64 = 0.12;
const OFFSET_JERK: f64 = 0.12;

impl Guard {
    /// A guard with `limits` for a cycle of `dt` seconds.
    pub fn new(limits: GuardLimits, dt: f64) -> anyhow::Result<Self> {
        let otg = Otg::new(dt).map_err(|e| anyhow::anyhow!("trajectory generator: {e:?}"))?;
        let mut input = OtgInput {
            dofs: JOINTS as u32,
            // every joint on its own, as fast as it can
            synchronization: 3,
            ..OtgInput::default()
        };
        for j in 0..JOINTS {
            // half speed: the fallback of a faulty stream never reaches the envelope's fast
            // regime; the robot's own acceleration less a margin, so that it brakes as hard as a
            // controller may (its steps pass `enforce`, which keeps them to the envelope's band)
            input.max_velocity[j] = limits.dq[j] * 0.5;
            input.max_acceleration[j] = DDQ_MAX * GENERATOR_MARGIN;
            input.max_jerk[j] = DDDQ_MAX * GENERATOR_JERK;
            input.min_position[j] = ENVELOPE_Q_MIN[j].max(Q_MIN[j]) + GENERATOR_POSITION_MARGIN;
            input.max_position[j] = ENVELOPE_Q_MAX[j].min(Q_MAX[j]) - GENERATOR_POSITION_MARGIN;
        }
        let offset_otg =
            Otg::new(dt).map_err(|e| anyhow::anyhow!("trajectory generator: {e:?}"))?;
        let mut offset_in = OtgInput {
            dofs: JOINTS as u32,
            control_interface: CONTROL_POSITION,
            synchronization: 3,
            ..OtgInput::default()
        };
        for (j, vmax) in DQ_MAX.iter().enumerate() {
            offset_in.max_velocity[j] = vmax * OFFSET_VELOCITY;
            offset_in.max_acceleration[j] = DDQ_MAX * OFFSET_ACCELERATION;
            offset_in.max_jerk[j] = DDDQ_MAX * OFFSET_JERK;
        }
        Ok(Self {
            limits,
            dt,
            otg,
            input,
            out: OtgOutput::default(),
            acted: [0; 5],
            planned: None,
            brake_plan: None,
            offset_otg,
            offset_in,
            offset_out: OtgOutput::default(),
            offset: None,
            path: 0,
            broke: None,
            desired: None,
            generating: false,
            enforced: 0,
            fields_agree: true,
            desired_diff: ([0.0; JOINTS], [0.0; JOINTS]),
            desired_a: None,
            desired_jerk: [0.0; JOINTS],
        })
    }

    /// Forgets the motion it followed (a new motion starts from rest): no offset, no generator
    /// leading, no plan of its own or of the brake, no desired state to difference against.
    /// The robot takes a motion's first command as its start, at rest: an offset carried over
    /// from a motion a reflex ended moved the first command 2.8e-6 rad, and the next one's
    /// acceleration then read 8.3 rad/s² in one cycle (8 292 rad/s³, a reflex at the restart).
    pub fn reset(&mut self) {
        self.offset = None;
        self.generating = false;
        self.planned = None;
        self.brake_plan = None;
        self.desired = None;
        self.desired_a = None;
        self.broke = None;
        self.path = 0;
    }

    /// The limits in force.
    pub fn limits(&self) -> &GuardLimits {
        &self.limits
    }

    /// The command for this cycle towards the desired state (`q`, `v`, `a`: the controller's
    /// position and its generator's velocity and acceleration). Returns it and whether the guard
    /// changed anything.
    ///
    /// A desired position within the limits from the last command passes unchanged. One that is
    /// not (a jump: the measured pose the controller started from against the commanded one, a
    /// late answer after a continuation, a new controller) starts an offset: the state the
    /// stream would have reached minus the desired state. The command is then the desired
    /// position plus that offset, and the offset goes to zero on its own jerk-limited
    /// trajectory within small limits, so the robot sees the controller's motion plus a slow,
    /// smooth correction, and then the controller's motion alone. Should even that break a
    /// limit (the controller's own motion does), the generator steps towards the desired state
    /// within its slower limits instead.
    pub fn follow(
        &mut self,
        prev: &Motion,
        q: &[f64; JOINTS],
        v: &[f64; JOINTS],
        a: &[f64; JOINTS],
    ) -> (Motion, bool) {
        let fin = |x: &[f64; JOINTS]| {
            let mut o = [0.0; JOINTS];
            for (o, x) in o.iter_mut().zip(x) {
                *o = if x.is_finite() { *x } else { 0.0 };
            }
            o
        };
        let (mut vd, mut ad) = (fin(v), fin(a));
        self.broke = None;
        self.fields_agree = true;
        self.desired_diff = (vd, ad);
        // the velocity and acceleration fields are trusted only where they agree with the
        // desired positions' own differences (else those differences stand in for them)
        if let Some((pq, pv)) = self.desired {
            for j in 0..JOINTS {
                if !q[j].is_finite() || !pq[j].is_finite() {
                    continue;
                }
                let v_fd = (q[j] - pq[j]) / self.dt;
                let a_fd = (v_fd - pv[j]) / self.dt;
                self.desired_diff.0[j] = v_fd;
                self.desired_diff.1[j] = a_fd;
                if (vd[j] - v_fd).abs() > self.limits.ddq * self.dt + 1e-3 {
                    vd[j] = v_fd;
                    self.fields_agree = false;
                }
                if (ad[j] - a_fd).abs() > 0.5 * self.limits.ddq {
                    ad[j] = a_fd.clamp(-self.limits.ddq, self.limits.ddq);
                    self.fields_agree = false;
                }
            }
        }
        self.desired_jerk = match self.desired_a {
            Some(pa) => std::array::from_fn(|j| (ad[j] - pa[j]) / self.dt),
            None => [0.0; JOINTS],
        };
        self.desired_a = Some(ad);
        let mut v_fd = [0.0; JOINTS];
        if let Some((pq, _)) = self.desired {
            for j in 0..JOINTS {
                v_fd[j] = if q[j].is_finite() && pq[j].is_finite() {
                    (q[j] - pq[j]) / self.dt
                } else {
                    0.0
                };
            }
        }
        self.desired = if q.iter().all(|x| x.is_finite()) {
            Some((*q, v_fd))
        } else {
            None
        };
        // a desired position outside the range is not one to go to: its nearest inside is
        let mut inside = *q;
        for (j, x) in inside.iter_mut().enumerate() {
            if x.is_finite() {
                *x = x.clamp(self.input.min_position[j], self.input.max_position[j]);
            }
        }
        let q = &inside;
        let finite = q.iter().all(|x| x.is_finite());
        if self.offset.is_none() && !self.generating {
            match (0..JOINTS).find_map(|j| {
                self.limits
                    .broken(j, prev, q[j], self.dt)
                    .map(|b| (j as u8, b))
            }) {
                None => {
                    self.planned = Some((*q, vd, ad));
                    self.path = 0;
                    return (Motion::after(prev, q, self.dt), false);
                }
                Some((j, b)) => {
                    self.acted[b as usize] += 1;
                    self.broke = Some((j, b as u8));
                }
            }
        }
        if finite {
            // the offset this cycle: the running one's next step, or (the controller's motion
            // does not pass from the stream: a lost or late answer, a jump, a new controller)
            // a new one, whose first step is the stream's own continuation
            let (o, done, path) = match self.offset {
                Some(o) => match self.offset_step(o, &ad) {
                    Some((o, done)) => (Some(o), done, 1),
                    None => (None, false, 3),
                },
                None => (Some(self.offset_from(prev, q, &vd, &ad)), false, 2),
            };
            // the generator leads while the stream is far from the controller's motion, and
            // hands back once it is near (hysteresis)
            let reach = if self.generating {
                HAND_BACK_RAD
            } else {
                TAKE_OVER_RAD
            };
            if let Some(o) = o.filter(|o| size(&o.0) <= reach) {
                self.generating = false;
                self.path = path;
                return (self.apply_offset(prev, q, &vd, &ad, o, done), true);
            }
        }
        // the desired position is not a number, or lies further from the stream than an offset
        // should carry: the generator steps towards it (or holds) within slower limits
        self.offset = None;
        self.generating = true;
        self.path = 3;
        self.input.control_interface = CONTROL_POSITION;
        for (j, &x) in q.iter().enumerate() {
            let (lo, hi) = (self.input.min_position[j], self.input.max_position[j]);
            self.input.target_position[j] = if x.is_finite() { x } else { prev.q[j] }.clamp(lo, hi);
            // at rest there: a target moving on at a velocity would be chased (each cycle's plan
            // passes the point it aims at, and the next cycle's point has moved on)
            self.input.target_velocity[j] = 0.0;
            self.input.target_acceleration[j] = 0.0;
        }
        (self.generate(prev), true)
    }

    /// A new offset: the stream continued one cycle at constant acceleration from its own
    /// state, minus the controller's desired state (`q`, `vd`, `ad`).
    fn offset_from(
        &self,
        prev: &Motion,
        q: &[f64; JOINTS],
        vd: &[f64; JOINTS],
        ad: &[f64; JOINTS],
    ) -> Offset {
        let (sq, sv, sa) = self.stream_state(prev);
        let dt = self.dt;
        let mut o = ([0.0; JOINTS], [0.0; JOINTS], [0.0; JOINTS]);
        for j in 0..JOINTS {
            o.0[j] = sq[j] + sv[j] * dt + 0.5 * sa[j] * dt * dt - q[j];
            o.1[j] = sv[j] + sa[j] * dt - vd[j];
            o.2[j] = sa[j] - ad[j];
        }
        o
    }

    /// The offset's next step towards zero on its own jerk-limited trajectory (within what
    /// the controller's own acceleration `ad` leaves), and whether it got there; `None` when
    /// the generator cannot plan from it.
    fn offset_step(&mut self, o: Offset, ad: &[f64; JOINTS]) -> Option<(Offset, bool)> {
        for (j, a) in ad.iter().enumerate() {
            // the stream's acceleration is the controller's plus the offset's, within 0.9 of the
            // limit: |a| off both ways. An offset faster than its own velocity limit is braked
            // with what the controller's acceleration leaves in the direction it needs, which is
            // more when the controller accelerates the other way (a controller re-seeded at rest
            // behind a stream at 1.4 rad/s and accelerating after it: with |a| off both ways the
            // offset closed at its floor of 1.2 rad/s², the stream ran 0.29 rad past and the
            // generator led; the test below); the other way is left to `enforce`
            let room = 0.9 * self.limits.ddq;
            let fast = o.1[j].abs() > 0.1 * self.offset_in.max_velocity[j];
            let left = if fast {
                (room + o.1[j].signum() * a).min(2.0 * room)
            } else {
                room - a.abs()
            };
            self.offset_in.max_acceleration[j] = left.max(DDQ_MAX * OFFSET_ACCELERATION);
            // the jerk the stream's own steps keep to ([`HEDGEABLE_JERK`]) less the
            // controller's: an offset that leaves its acceleration apart at a fixed 600 rad/s³
            // while the stream could at 2 700 ran on at +4 rad/s² behind a controller braking
            // at 8 after three late cycles (the test below)
            self.offset_in.max_jerk[j] = (self.limits.dddq * HEDGEABLE_JERK
                - self.desired_jerk[j].abs())
            .max(DDDQ_MAX * OFFSET_JERK);
            self.offset_in.current_position[j] = o.0[j];
            self.offset_in.current_velocity[j] = o.1[j];
            self.offset_in.current_acceleration[j] = o.2[j];
            self.offset_in.target_position[j] = 0.0;
            self.offset_in.target_velocity[j] = 0.0;
            self.offset_in.target_acceleration[j] = 0.0;
        }
        let r = self
            .offset_otg
            .update(&self.offset_in, &mut self.offset_out);
        if !r.is_ok() {
            return None;
        }
        let st = &self.offset_out.state;
        let mut n = ([0.0; JOINTS], [0.0; JOINTS], [0.0; JOINTS]);
        n.0.copy_from_slice(&st.position[..JOINTS]);
        n.1.copy_from_slice(&st.velocity[..JOINTS]);
        n.2.copy_from_slice(&st.acceleration[..JOINTS]);
        Some((n, r == OtgResult::Finished))
    }

    /// The command `q + o`, held within the limits from `prev` ([`Self::enforce`]): where it
    /// had to be, the offset from now on starts from the position the stream actually has, so
    /// that the next step closes the distance the limits left. The offset ends when it reached
    /// zero.
    fn apply_offset(
        &mut self,
        prev: &Motion,
        q: &[f64; JOINTS],
        vd: &[f64; JOINTS],
        ad: &[f64; JOINTS],
        o: Offset,
        done: bool,
    ) -> Motion {
        let mut out = [0.0; JOINTS];
        for j in 0..JOINTS {
            out[j] = q[j] + o.0[j];
        }
        let held = self.enforce(prev, &out);
        if held == out {
            let (mut pv, mut pa) = (*vd, *ad);
            for j in 0..JOINTS {
                pv[j] += o.1[j];
                pa[j] += o.2[j];
            }
            self.planned = Some((out, pv, pa));
            self.offset = if done { None } else { Some(o) };
            return Motion::after(prev, &out, self.dt);
        }
        self.enforced += 1;
        // the state the stream has against the controller's motion: its position, and, when the
        // controller's velocity and acceleration agree with its own positions, the difference of
        // the two motions' differences, like against like, carried to the end of the cycle (a
        // backward difference lags the velocity by half a cycle's acceleration); when they do
        // not (a jump, noise), the plan's velocity and acceleration stay (differences against
        // noise would make the plan chase it). The stream's differences against the
        // controller's velocity field (which a generator gives at the end of the cycle) put the
        // offset half a cycle's acceleration off: its next step was clipped again, every cycle,
        // and the stream accelerated at 3-6 rad/s² behind a controller at 8 until the offset
        // reached the generator's take-over (the test below, from a trace)
        //
        // A backward second difference is the acceleration a cycle back, the first difference
        // the velocity half a cycle back: under the offset's own jerk both lag its plan, and
        // taken as they are they gave back each cycle what the plan had taken off (after three
        // late cycles into a controller braking at 8 rad/s², the plan brought the offset's
        // acceleration from 8 to 6.5 and the differences put it back at 7.75, cycle after
        // cycle, while the stream ran 0.17 rad/s too fast: the test below). The plan's own
        // change of acceleration this cycle puts them forward.
        let m = Motion::after(prev, &held, self.dt);
        let (v_fd, a_fd) = self.desired_diff;
        let mut actual = o;
        for j in 0..JOINTS {
            actual.0[j] = held[j] - q[j];
            if self.fields_agree {
                let step = self.offset.map_or(0.0, |p| o.2[j] - p.2[j]);
                let a_back = m.ddq[j] - a_fd[j];
                actual.2[j] = a_back + step;
                actual.1[j] = m.dq[j] - v_fd[j] + 0.5 * (a_back + 0.5 * step) * self.dt;
            }
        }
        self.planned = None;
        self.offset = Some(actual);
        m
    }

    /// `q` when it keeps within the limits from `prev`; else, per joint that does not, the
    /// step the limits allow towards it: the jerk clamped, the acceleration held in the band that
    /// still lets the velocity stop at the envelope, the position integrated (libfranka's own
    /// rule for a rate limiter). The last safeguard of every path: its result always passes.
    fn enforce(&self, prev: &Motion, q: &[f64; JOINTS]) -> [f64; JOINTS] {
        // the guard's own steps within the jerk that leaves the next answer room to pass from
        // both histories should this one go out late ([`HEDGEABLE_JERK`])
        let hedgeable = GuardLimits {
            dddq: self.limits.dddq * HEDGEABLE_JERK,
            ..self.limits
        };
        let (dt, l) = (self.dt, &hedgeable);
        let mut out = *q;
        for j in 0..JOINTS {
            if l.passes(j, prev, q[j], dt) {
                continue;
            }
            let (q0, v0, a0) = (prev.q[j], prev.dq[j], prev.ddq[j]);
            let target = if q[j].is_finite() { q[j] } else { q0 };
            let v = (target - q0) / dt;
            // a hair inside the limits, so that rounding never lands on the wrong side
            let (jm, am) = (l.dddq * (1.0 - 1e-9), l.ddq * (1.0 - 1e-9));
            let jerk = (((v - v0) / dt - a0) / dt).clamp(-jm, jm);
            let (band_lo, band_hi) = l.band(j, q0, v0);
            let a_hi = band_hi.min(am).max(a0 - jm * dt);
            let a_lo = band_lo.max(-am).min(a0 + jm * dt);
            let a = (a0 + jerk * dt).clamp(a_lo.min(a_hi), a_hi.max(a_lo));
            out[j] = q0 + (v0 + a * dt) * dt;
        }
        out
    }

    /// The stream's analytic state after `prev` (the generator's or the controller's), or the
    /// one its differences imply where none is known ([`Motion::rates`]).
    fn stream_state(&self, prev: &Motion) -> ([f64; JOINTS], [f64; JOINTS], [f64; JOINTS]) {
        match &self.planned {
            Some((q, v, a)) if q == &prev.q && self.consistent(prev, v, a) => (*q, *v, *a),
            _ => {
                let (v, a) = prev.rates(self.dt);
                (prev.q, v, a)
            }
        }
    }

    /// Whether an analytic velocity and acceleration agree with the differences the robot saw
    /// (the differences lag by half a cycle: within what the limits allow in it). A velocity
    /// field that disagrees with the positions it came with is not trusted.
    fn consistent(&self, prev: &Motion, v: &[f64; JOINTS], a: &[f64; JOINTS]) -> bool {
        (0..JOINTS).all(|j| {
            (v[j] - prev.dq[j]).abs() <= self.limits.ddq * self.dt + 1e-6
                && (a[j] - prev.ddq[j]).abs() <= self.limits.dddq * self.dt + 1e-6
        })
    }

    /// The command nearest `q` that passes this guard's limits from every reference a robot may
    /// judge it against: `a`, the one `q` was computed against (one cycle back), and each of
    /// `others`, a motion and the cycles back it stands. After an answer that went out late the
    /// FCI dropped it (its report shows the reference continued: `a`), while a simulator may
    /// still apply it and difference the next commands against it over the cycles since (the
    /// others). Per joint, the positions within the velocity envelope, acceleration and jerk
    /// from all; where none is within all, the one within `a`'s nearest to the others' (as
    /// many of them as leave a common range, in order): `a` is the reference the driver
    /// believes. Returns it and whether it changed `q`.
    pub fn hedge(
        &self,
        a: &Motion,
        others: &[(Motion, u64)],
        q: &[f64; JOINTS],
    ) -> ([f64; JOINTS], bool) {
        let l = &self.limits;
        let shrink = 1.0 - 1e-6;
        let range = |r: &Motion, j: usize, h: f64| -> (f64, f64) {
            let glide = r.q[j] + r.dq[j] * h;
            let p = glide + r.ddq[j] * h * h;
            let (jd, ad) = (l.dddq * shrink * h * h * h, l.ddq * shrink * h * h);
            let (mut lo, mut hi) = (l.q_min[j], l.q_max[j]);
            for (lo_k, hi_k) in [
                (p - jd, p + jd),
                (glide - ad, glide + ad),
                (
                    r.q[j] + l.lower(j, r.q[j]) * h,
                    r.q[j] + l.upper(j, r.q[j]) * h,
                ),
            ] {
                lo = lo.max(lo_k);
                hi = hi.min(hi_k);
            }
            (lo, hi)
        };
        let mut out = *q;
        let mut changed = false;
        for j in 0..JOINTS {
            let (alo, ahi) = range(a, j, self.dt);
            if alo > ahi {
                // nothing passes from `a` itself: the guard's own path stands
                continue;
            }
            // `a`'s range narrowed by each other reference in turn, as long as some remains
            let (mut lo, mut hi) = (alo, ahi);
            for (b, cycles) in others {
                let (blo, bhi) = range(b, j, self.dt * (*cycles).max(1) as f64);
                let (nlo, nhi) = (lo.max(blo), hi.min(bhi));
                if nlo <= nhi {
                    (lo, hi) = (nlo, nhi);
                } else {
                    // none within both: within what is left, as near to this one's as it allows
                    let toward = if blo <= bhi {
                        q[j].clamp(blo, bhi)
                    } else {
                        q[j]
                    };
                    let x = toward.clamp(lo, hi);
                    (lo, hi) = (x, x);
                }
            }
            let x = q[j].clamp(lo, hi);
            if x != q[j] {
                changed = true;
                out[j] = x;
            }
        }
        (out, changed)
    }

    /// One cycle without a new command: constant acceleration from `prev` when that keeps
    /// within the limits, else the stop's first cycle.
    pub fn extrapolate(&mut self, prev: &Motion) -> Motion {
        self.offset = None;
        self.generating = false;
        self.desired = None;
        self.desired_a = None;
        let next = prev.continued(self.dt);
        if (0..JOINTS).all(|j| self.limits.passes(j, prev, next.q[j], self.dt)) {
            self.planned = Some((next.q, next.rates(self.dt).0, prev.ddq));
            next
        } else {
            self.brake(prev).0
        }
    }

    /// One cycle of the time-optimal stop from `prev` (velocity and acceleration to zero).
    /// Returns the motion and whether it is at rest.
    pub fn brake(&mut self, prev: &Motion) -> (Motion, bool) {
        self.offset = None;
        self.generating = false;
        self.desired = None;
        self.desired_a = None;
        if prev.at_rest() {
            return (Motion::rest(prev.q), true);
        }
        self.input.control_interface = CONTROL_VELOCITY;
        for j in 0..JOINTS {
            self.input.target_velocity[j] = 0.0;
            self.input.target_acceleration[j] = 0.0;
        }
        if let Some(p) = self
            .brake_plan
            .filter(|(q, v, a)| q == &prev.q && self.consistent(prev, v, a))
        {
            self.planned = Some(p);
        }
        let m = self.generate(prev);
        self.brake_plan = self.planned;
        (m, m.at_rest())
    }

    /// One step of the generator from `prev` towards the input's targets, as the robot sees it.
    fn generate(&mut self, prev: &Motion) -> Motion {
        let (_, sv, sa) = self.stream_state(prev);
        for j in 0..JOINTS {
            let vmax = self.input.max_velocity[j];
            let amax = self.input.max_acceleration[j];
            let (v, a) = (sv[j], sa[j]);
            self.input.current_position[j] = prev.q[j];
            self.input.current_velocity[j] = v.clamp(-vmax, vmax);
            self.input.current_acceleration[j] = a.clamp(-amax, amax);
        }
        let r = self.otg.update(&self.input, &mut self.out);
        if !r.is_ok() && r != OtgResult::Error(-102) {
            // outside what the generator can plan from: the velocity decays, one limited step
            self.planned = None;
            let mut q = prev.q;
            for (j, q) in q.iter_mut().enumerate() {
                *q += prev.dq[j] * self.dt;
            }
            return Motion::after(prev, &self.enforce(prev, &q), self.dt);
        }
        let st = &self.out.state;
        let (mut q, mut v, mut a) = ([0.0; JOINTS], [0.0; JOINTS], [0.0; JOINTS]);
        q.copy_from_slice(&st.position[..JOINTS]);
        v.copy_from_slice(&st.velocity[..JOINTS]);
        a.copy_from_slice(&st.acceleration[..JOINTS]);
        let limited = self.enforce(prev, &q);
        if limited != q {
            // a switch between paths left the plan off the stream: the stream's own state now
            self.planned = None;
            q = limited;
        } else {
            self.planned = Some((q, v, a));
        }
        let mut m = Motion::after(prev, &q, self.dt);
        if r == OtgResult::Finished && self.input.control_interface == CONTROL_VELOCITY {
            // at rest: the next cycles repeat this position with zero velocity
            m.dq = [0.0; JOINTS];
            m.ddq = [0.0; JOINTS];
            self.planned = None;
        }
        m
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::limits::{violation, CYCLE_S};

    fn home() -> [f64; JOINTS] {
        [0.0, -0.3, 0.0, -2.0, 0.0, 1.8, 0.785]
    }

    /// The robot's own verdict on a sequence of commands (`violation` of each against the last).
    fn check(seq: &[Motion]) {
        for w in seq.windows(2) {
            if let Some(v) = violation(&w[0].q, &w[0].dq, &w[0].ddq, &w[1].q) {
                panic!("the FR3 would refuse this command: {v:?}");
            }
        }
    }

    #[test]
    fn a_smooth_desired_motion_passes_unchanged() {
        let mut g = Guard::new(GuardLimits::fr3(0.95, 0.02), CYCLE_S).unwrap();
        let mut m = Motion::rest(home());
        let mut seq = vec![m];
        for k in 1..3000 {
            let t = k as f64 * CYCLE_S;
            let mut q = home();
            q[3] += 0.2 * (1.0 - (std::f64::consts::PI * t / 1.5).cos());
            let (next, clamped) = g.follow(&m, &q, &[0.0; JOINTS], &[0.0; JOINTS]);
            assert!(!clamped, "cycle {k}");
            assert_eq!(next.q, q);
            m = next;
            seq.push(m);
        }
        check(&seq);
    }

    #[test]
    fn a_step_is_turned_into_a_motion_the_robot_accepts() {
        let mut g = Guard::new(GuardLimits::fr3(0.95, 0.02), CYCLE_S).unwrap();
        let mut m = Motion::rest(home());
        let mut target = home();
        target[0] += 0.3;
        target[4] -= 0.5;
        let mut seq = vec![m];
        let mut clamped = 0;
        for _ in 0..2000 {
            let (next, c) = g.follow(&m, &target, &[0.0; JOINTS], &[0.0; JOINTS]);
            clamped += c as usize;
            m = next;
            seq.push(m);
        }
        check(&seq);
        assert!(clamped > 0);
        // it gets there and stops
        assert!(
            (m.q[0] - target[0]).abs() < 1e-6 && (m.q[4] - target[4]).abs() < 1e-6,
            "{:?}",
            m.q
        );
    }

    #[test]
    fn late_cycles_continue_the_motion_and_a_stop_ends_at_rest_within_the_limits() {
        let mut g = Guard::new(GuardLimits::fr3(0.95, 0.02), CYCLE_S).unwrap();
        // moving at 1.5 rad/s and accelerating when the controller goes quiet
        let mut m = Motion::rest(home());
        m.dq[0] = 1.5;
        m.ddq[0] = 5.0;
        m.dq[5] = -1.0;
        let mut seq = vec![m];
        for _ in 0..3 {
            m = g.extrapolate(&m);
            seq.push(m);
        }
        // never a repeated position while moving
        assert!(seq.windows(2).all(|w| w[1].q[0] != w[0].q[0]));
        let mut rest_at = None;
        for k in 0..3000 {
            let (next, done) = g.brake(&m);
            m = next;
            seq.push(m);
            if done {
                rest_at = Some(k);
                break;
            }
        }
        check(&seq);
        let k = rest_at.expect("at rest");
        // 1.5 rad/s with a jerk-limited deceleration of up to 8 rad/s² (0.8 x the robot's 10):
        // well under a second
        assert!(k < 800, "{k} cycles");
        assert!(m.at_rest());
    }

    #[test]
    fn a_brake_after_a_refused_command_each_cycle_stops_as_fast_as_a_brake_alone() {
        // The driver's geometry and following checks refuse the guard's answer to the
        // controller and brake instead, every cycle: the brake must keep its own plan (from the
        // robot's differences alone it decelerated at 1.2 rad/s², a sixth of its jerk per cycle)
        let stop = |interleaved: bool| {
            let mut g = Guard::new(GuardLimits::fr3(0.83, 0.02), CYCLE_S).unwrap();
            let mut m = Motion::rest(home());
            m.dq[6] = -1.05;
            let mut d = m.q;
            let mut seq = vec![m];
            for k in 0..3000 {
                if interleaved {
                    // the controller's motion runs on at -1.05 rad/s
                    d[6] -= 1.05e-3;
                    let mut v = [0.0; JOINTS];
                    v[6] = -1.05;
                    let _ = g.follow(&m, &d, &v, &[0.0; JOINTS]);
                }
                let (next, done) = g.brake(&m);
                m = next;
                seq.push(m);
                if done {
                    check(&seq);
                    return (k, m.q[6] - home()[6]);
                }
            }
            panic!("no stop in 3 s (interleaved: {interleaved})");
        };
        let (alone, travel_alone) = stop(false);
        let (k, travel) = stop(true);
        // 1.05 rad/s at 0.7 x 10 rad/s² with the jerk ramp: ~150 cycles, ~8 cm of travel
        assert!(alone < 200, "alone: {alone} cycles");
        assert!(k <= alone + 2, "interleaved: {k} cycles, alone {alone}");
        assert!(
            (travel - travel_alone).abs() < 1e-3,
            "interleaved travel {travel}, alone {travel_alone}"
        );
    }

    #[test]
    fn approaching_a_limit_slows_to_a_stop_inside_it() {
        let l = GuardLimits::fr3(0.95, 0.02);
        let mut g = Guard::new(l, CYCLE_S).unwrap();
        let mut m = Motion::rest(home());
        // a desired position far past joint 2's limit
        let mut target = home();
        target[1] = 3.0;
        let mut seq = vec![m];
        for _ in 0..20_000 {
            m = g.follow(&m, &target, &[0.0; JOINTS], &[0.0; JOINTS]).0;
            seq.push(m);
        }
        check(&seq);
        assert!(
            seq.iter().all(|m| m.q[1] <= l.q_max[1] + 1e-9),
            "{}",
            m.q[1]
        );
        assert!(m.q[1] > l.q_max[1] - 0.2, "it gets close: {}", m.q[1]);
        assert!(m.at_rest() || m.dq[1].abs() < 1e-3);
    }

    #[test]
    fn near_a_limit_an_arm_running_1_6_times_the_command_stays_inside_the_envelope() {
        // The robot judges the *measured* velocity against its envelope; the measured one runs
        // up to half again past the command for a few cycles (franka-sim after its physics loop
        // ran late: joint 4 at 1.70 rad/s against 1.54 in a CI, commanded 1.125 by the
        // controller's rectangular range). Every joint, both ways, from the middle of its range
        // at the controller's speeds and at the guard's own.
        use crate::limits::{lower_velocity, upper_velocity};
        let l = GuardLimits::fr3(0.83, 0.02);
        for j in 0..JOINTS {
            for (sign, speed) in [(1.0, 1.125), (-1.0, 1.125), (1.0, l.dq[j]), (-1.0, l.dq[j])] {
                let mut g = Guard::new(l, CYCLE_S).unwrap();
                let mut start = home();
                start[j] = 0.5 * (l.q_min[j] + l.q_max[j]);
                let mut m = Motion::rest(start);
                let mut desired = start;
                let mut seq = vec![m];
                for _ in 0..6000 {
                    desired[j] += sign * speed * CYCLE_S;
                    let mut v = [0.0; JOINTS];
                    v[j] = sign * speed;
                    m = g.follow(&m, &desired, &v, &[0.0; JOINTS]).0;
                    seq.push(m);
                    let (up, lo) = (upper_velocity(j, m.q[j]), lower_velocity(j, m.q[j]));
                    assert!(
                        1.6 * m.dq[j] <= up.max(0.0) + 1e-9 && 1.6 * m.dq[j] >= lo.min(0.0) - 1e-9,
                        "joint {}: {} rad/s at {} (envelope {lo}..{up})",
                        j + 1,
                        m.dq[j],
                        m.q[j]
                    );
                }
                check(&seq);
            }
        }
    }

    #[test]
    fn whatever_the_controller_sends_the_robot_sees_no_violation() {
        // 40 s of what reaches the driver besides a clean stream: offsets of up to 0.05 rad (a
        // re-seed from the measured pose, a new controller within the bind tolerance), NaN,
        // velocity fields that disagree with the positions, late answers and silences (larger
        // jumps and targets past the limits: the tests above)
        for seed in 0..8 {
            hostile_stream(seed);
        }
    }

    fn hostile_stream(seed: u64) {
        use rand::{Rng, SeedableRng};
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(seed);
        let mut g = Guard::new(GuardLimits::fr3(0.95, 0.02), CYCLE_S).unwrap();
        let mut m = Motion::rest(home());
        let mut seq = vec![m];
        let mut bias = [0.0; JOINTS];
        let mut silent = 0u32;
        let mut ops: Vec<&str> = vec!["start"];
        for k in 0..40_000u32 {
            let t = k as f64 * CYCLE_S;
            if rng.gen_bool(0.002) {
                for b in bias.iter_mut() {
                    *b = rng.gen_range(-0.05..0.05);
                }
            }
            if silent == 0 && rng.gen_bool(0.003) {
                silent = rng.gen_range(1..60);
            }
            if silent > 0 {
                silent -= 1;
                m = if silent > 50 {
                    ops.push("extrapolate");
                    g.extrapolate(&m)
                } else {
                    ops.push("brake");
                    g.brake(&m).0
                };
            } else {
                let mut q = home();
                let mut v = [0.0; JOINTS];
                for j in 0..JOINTS {
                    let w = 1.0 + 0.3 * j as f64;
                    q[j] += bias[j] + 0.4 * (w * t).sin();
                    v[j] = 0.4 * w * (w * t).cos() * if rng.gen_bool(0.01) { 10.0 } else { 1.0 };
                }
                if rng.gen_bool(0.001) {
                    q[rng.gen_range(0..JOINTS)] = f64::NAN;
                }
                if rng.gen_bool(0.001) {
                    // a target far past the limits, for one cycle
                    q[rng.gen_range(0..JOINTS)] = 100.0;
                }
                let (n, _) = g.follow(&m, &q, &v, &[0.0; JOINTS]);

                ops.push(["pass", "offset", "restart", "generator"][g.path as usize]);
                m = n;
            }
            assert!(m.q.iter().all(|x| x.is_finite()), "cycle {k}");
            seq.push(m);
        }
        for (i, w) in seq.windows(2).enumerate() {
            if let Some(v) = violation(&w[0].q, &w[0].dq, &w[0].ddq, &w[1].q) {
                panic!(
                    "seed {seed}, cycle {i}: {v:?}; ops {:?}",
                    &ops[i.saturating_sub(4)..(i + 2).min(ops.len())]
                );
            }
        }
        let l = g.limits();
        for m in &seq {
            for j in 0..JOINTS {
                assert!(m.q[j] >= l.q_min[j] - 1e-9 && m.q[j] <= l.q_max[j] + 1e-9);
            }
        }
    }

    /// The controller's motion on `joint`: up to `vmax` at 8 rad/s², a jump of `jump` at cycle
    /// 350, from cycle 500 a stop at 8 rad/s² entered at once (the acceleration jumps), and
    /// `noise` on every position; returns the guard's largest deviation from it after the
    /// jump, how far the stream passed the stop, and where the stream ended against the stop.
    fn at_speed(joint: usize, vmax: f64, jump: f64, noise: f64) -> (f64, f64, f64) {
        let mut g = Guard::new(GuardLimits::fr3(0.95, 0.02), CYCLE_S).unwrap();
        let mut q = [0.0, -0.3, 0.0, -1.8, 0.0, 2.6, 0.785];
        let mut m = Motion::rest(q);
        let mut seq = vec![m];
        let (mut v, mut a) = (0.0f64, 0.0f64);
        let (mut worst, mut past): (f64, f64) = (0.0, 0.0);
        for k in 0..5000 {
            if k < 500 {
                a = if v <= -vmax {
                    0.0
                } else {
                    (a - 4000.0 * CYCLE_S).max(-8.0)
                };
                v = (v + a * CYCLE_S).max(-vmax);
            } else {
                a = if v < 0.0 { 8.0 } else { 0.0 };
                v = (v + a * CYCLE_S).min(0.0);
            }
            q[joint] += v * CYCLE_S + if k == 350 { jump } else { 0.0 };
            let mut desired = q;
            desired[joint] += noise * ((k * 7919 % 13) as f64 / 13.0 - 0.5);
            let (mut vv, mut aa) = ([0.0; JOINTS], [0.0; JOINTS]);
            vv[joint] = v;
            aa[joint] = a;
            m = g.follow(&m, &desired, &vv, &aa).0;
            seq.push(m);
            if k > 350 {
                worst = worst.max((m.q[joint] - q[joint]).abs());
                past = past.max(q[joint] - m.q[joint]);
            }
        }
        check(&seq);
        (worst, past, m.q[joint] - q[joint])
    }

    #[test]
    fn a_controller_whose_every_position_breaks_a_limit_does_not_carry_the_arm_away() {
        // noise of 2e-5 rad is past the jerk limit every cycle: the offset failed every other
        // cycle and its restarts carried the stream on at its speed, 1.4-3.2 rad past the stop
        for (joint, vmax) in [(5, 2.3), (5, 1.5), (3, 2.0), (6, 2.3)] {
            let (_, past, end) = at_speed(joint, vmax, 0.0, 2e-5);
            assert!(
                past < 0.02,
                "joint {joint} at {vmax} rad/s: {past} rad past the stop"
            );
            assert!(end.abs() < 0.01, "joint {joint}: ended {end} rad off");
        }
    }

    #[test]
    fn a_jump_at_speed_and_an_abrupt_stop_stay_near_the_controller() {
        // (on joint 5, whose envelope leaves 2.4 rad/s unshaped over the whole travel: on joint
        // 6 the guard keeps it to 0.6 of the envelope from 1.6 rad before the limit)
        for (vmax, jump) in [
            (2.3, 0.05),
            (2.3, -0.05),
            (2.3, 0.2),
            (1.0, 0.3),
            (2.4, 0.01),
        ] {
            let (worst, _, end) = at_speed(4, vmax, jump, 0.0);
            assert!(
                worst < jump.abs() + 0.01,
                "{vmax} rad/s, jump {jump}: {worst} rad from the controller"
            );
            assert!(
                end.abs() < 1e-3,
                "{vmax} rad/s, jump {jump}: ended {end} rad off"
            );
        }
    }

    /// A stream of positions differenced by a client that sends one a cycle (a replay).
    fn replayed(positions: &[[f64; JOINTS]]) -> Vec<Motion> {
        let mut m = Motion::rest(positions[0]);
        let mut seq = vec![m];
        for q in &positions[1..] {
            m = Motion::after(&m, q, CYCLE_S);
            seq.push(m);
        }
        seq
    }

    #[test]
    fn cycles_the_robot_continued_on_its_own_belong_in_a_stream_of_one_line_a_cycle() {
        // a guarded motion at about 0.4 rad/s whose answers go missing for two cycles; the
        // robot continues the last command at constant acceleration meanwhile
        let mut g = Guard::new(GuardLimits::fr3(0.95, 0.02), CYCLE_S).unwrap();
        let mut m = Motion::rest(home());
        let (mut with_lost, mut answers) = (vec![m.q], vec![m.q]);
        for k in 1..1500 {
            if (700..702).contains(&k) {
                assert!(m.dq[3] > 0.3, "{}", m.dq[3]);
                m = m.continued(CYCLE_S);
                with_lost.push(m.q);
                continue;
            }
            let t = k as f64 * CYCLE_S;
            let mut q = home();
            q[3] += 0.2 * (1.0 - (std::f64::consts::PI * t / 1.5).cos());
            m = g.follow(&m, &q, &[0.0; JOINTS], &[0.0; JOINTS]).0;
            with_lost.push(m.q);
            answers.push(m.q);
        }
        // the continuation keeps the acceleration: sent one a cycle, the robot accepts it
        check(&replayed(&with_lost));
        // the answers alone, one a cycle, take the motion after the gap a cycle early
        let short = replayed(&answers);
        let refused = short
            .windows(2)
            .any(|w| violation(&w[0].q, &w[0].dq, &w[0].ddq, &w[1].q).is_some());
        assert!(
            refused,
            "a stream without the lost cycles passed the FR3's checks"
        );
    }
    /// A controller's motion that keeps to chunkrt's own shaping (up to 7.4 rad/s² on the
    /// last joint): every joint swings at its own two frequencies.
    fn swinging(k: usize) -> [f64; JOINTS] {
        let mut q = home();
        let t = k as f64 * CYCLE_S;
        for (j, q) in q.iter_mut().enumerate() {
            let w = 2.0 + 0.7 * j as f64;
            *q += 0.12 * (w * t).sin() + 0.01 * (2.7 * w * t).sin();
        }
        q
    }

    #[test]
    fn a_lost_answer_leaves_the_controller_leading_within_a_few_cycles() {
        // 1 % of the cycles lost at random (the robot continues its reference at constant
        // acceleration), 20 s of a controller within chunkrt's shaping: the controller's motion
        // leads every cycle it answers (before this guard's closed-loop offset, one withheld
        // answer in franka-sim handed the arm to the generator for the rest of a run: BENCHMARKS
        // §9)
        use rand::{Rng, SeedableRng};
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(3);
        let mut g = Guard::new(GuardLimits::fr3(0.83, 0.02), CYCLE_S).unwrap();
        let mut m = Motion::rest(swinging(0));
        let mut seq = vec![m];
        let (mut lost, mut led, mut not_led_run, mut longest) = (0, 0, 0, 0);
        for k in 1..20_000 {
            if rng.gen_bool(0.01) {
                m = m.continued(CYCLE_S);
                lost += 1;
            } else {
                m = g.follow(&m, &swinging(k), &[0.0; JOINTS], &[0.0; JOINTS]).0;
                if g.path <= 2 {
                    led += 1;
                    not_led_run = 0;
                } else {
                    not_led_run += 1;
                    longest = longest.max(not_led_run);
                }
            }
            seq.push(m);
        }
        check(&seq);
        assert!(lost > 150, "{lost}");
        assert!(
            led as f64 >= 0.999 * (19_999 - lost) as f64 && longest == 0,
            "led {led} of {}, the generator {longest} cycles in a row",
            19_999 - lost
        );
        // and the stream ends on the controller's motion
        let end = swinging(19_999);
        assert!(
            (0..JOINTS).all(|j| (m.q[j] - end[j]).abs() < 1e-3),
            "{:?}",
            m.q
        );
    }

    #[test]
    fn a_report_whose_derivatives_are_the_cycle_befores_is_torn() {
        // joint 2 of a loaded run's trace (robot cycles 11107 and 11108): the report moved to
        // the answer (0.147553688) and kept the cycle before's -0.5044515 rad/s, -8.3 rad/s²
        let mut before = Motion::rest(home());
        before.q[1] = 0.148066440;
        before.dq[1] = -0.5044515;
        before.ddq[1] = -8.3;
        let answer = Motion::after(
            &before,
            &{
                let mut q = before.q;
                q[1] = 0.147553688;
                q
            },
            CYCLE_S,
        );
        let mut report = answer;
        report.dq = before.dq;
        report.ddq = before.ddq;
        assert!(torn(&report, &before));
        // the same position with the derivatives the robot differenced it with: not torn, and
        // a report that did not move (the answer not applied) is not this either
        assert!(!torn(&answer, &before));
        assert!(!torn(&before, &before));
        // f32-rounded as the FCI sends it: still torn
        let mut f = report;
        for j in 0..JOINTS {
            f.q[j] = f.q[j] as f32 as f64;
            f.dq[j] = f.dq[j] as f32 as f64;
            f.ddq[j] = f.ddq[j] as f32 as f64;
        }
        assert!(torn(&f, &before));
    }

    #[test]
    fn the_robots_report_is_taken_exactly_where_it_rounds_to_a_candidate() {
        let mut a = Motion::rest(home());
        a.dq[3] = 0.5;
        a.ddq[3] = 4.0;
        let applied = Motion::after(
            &a,
            &{
                let mut q = a.q;
                q[3] += 0.000_502_3;
                q
            },
            CYCLE_S,
        );
        let skipped = a.continued(CYCLE_S);
        let f32ed = |m: &Motion| {
            let r = |x: &[f64; JOINTS]| x.map(|v| v as f32 as f64);
            Motion {
                q: r(&m.q),
                dq: r(&m.dq),
                ddq: r(&m.ddq),
            }
        };
        // the robot applied the answer: the exact answer, not its f32 rounding
        let (r, how) = reconcile(&f32ed(&applied), &[applied, skipped]);
        assert_eq!((r, how), (applied, Reference::Candidate(0)));
        // the answer was lost: the exact continuation
        let (r, how) = reconcile(&f32ed(&skipped), &[applied, skipped]);
        assert_eq!((r, how), (skipped, Reference::Candidate(1)));
        // derivatives the driver did not expect: the candidate's position, the report's rates
        let mut other = f32ed(&applied);
        other.ddq[3] += 1.0;
        let (r, how) = reconcile(&other, &[applied, skipped]);
        assert_eq!(how, Reference::Corrected(0));
        assert_eq!((r.q, r.ddq[3]), (applied.q, other.ddq[3]));
        // a report far from every candidate, or not a number, is set aside
        let mut far = f32ed(&applied);
        far.q[0] += 0.01;
        assert_eq!(reconcile(&far, &[applied, skipped]).1, Reference::Kept);
        let mut nan = f32ed(&applied);
        nan.dq[2] = f64::NAN;
        assert_eq!(
            reconcile(&nan, &[applied, skipped]),
            (applied, Reference::Kept)
        );
        // near, but no candidate's position rounds to it: the report as it is
        let mut near = f32ed(&applied);
        near.q[1] += 1e-5;
        assert_eq!(
            reconcile(&near, &[applied, skipped]),
            (near, Reference::Adopted)
        );
    }

    /// The largest jerk (rad/s³) an answer of the guard's own may have against the robot's
    /// reference: should it go out late and be applied after all, the next answer must pass from
    /// both that history and the robot's continuation, and those part by three times its jerk
    /// ([`Guard::hedge`]): possible under 2/3 of the guard's jerk limit.
    fn hedgeable(l: &GuardLimits) -> f64 {
        2.0 / 3.0 * l.dddq
    }

    #[test]
    fn a_restart_after_a_late_cycle_continues_the_stream_and_leaves_the_hedge_room() {
        // The trace of a fresh-clone CI's reflex (benches/data/franka/2026-11-28-suite/c218325/
        // ci2-failure): joint 3 accelerating at 7.6 rad/s², a late cycle (the stream continued),
        // then the controller's answer off the continuation (an offset restarts). The restart's
        // first step took the stream's state as analytic when it was the robot's differences:
        // it halved the acceleration, a jerk of -3 788 rad/s³; that answer went out late, the
        // simulator applied it after all, and no next answer could pass from both histories
        // (11.0 rad/s² from the applied one: `joint_motion_generator_velocity_discontinuity`).
        // The offset's later steps, held to the guard's full jerk, reached 4 150 rad/s³; a stop
        // planned at 0.7 of the robot's jerk, 2 917: each past the 2/3 the hedge needs.
        let mut g = Guard::new(GuardLimits::fr3(0.83, 0.02), CYCLE_S).unwrap();
        let l = *g.limits();
        // joint 3 swinging at 1 Hz, 7.6 rad/s² at its turn (t = 0); joint 4 at 0.7 rad/s
        let (w, a0) = (std::f64::consts::TAU, 7.6);
        let amp = a0 / (w * w);
        let desired = |k: usize, jump: f64| {
            let t = k as f64 * CYCLE_S;
            let mut q = home();
            q[2] += -amp * (w * t).cos() + jump;
            q[3] += 0.7 * t;
            let mut v = [0.0; JOINTS];
            v[2] = amp * w * (w * t).sin();
            v[3] = 0.7;
            let mut a = [0.0; JOINTS];
            a[2] = a0 * (w * t).cos();
            (q, v, a)
        };
        for path_to_the_restart in ["offset", "brake"] {
            // the stream already on the controller's motion: its last three positions
            let p: [[f64; JOINTS]; 3] = std::array::from_fn(|i| desired(i, 0.0).0);
            let v1: [f64; JOINTS] = std::array::from_fn(|j| (p[1][j] - p[0][j]) / CYCLE_S);
            let mut m = Motion::after(
                &Motion {
                    q: p[1],
                    dq: v1,
                    ddq: [0.0; JOINTS],
                },
                &p[2],
                CYCLE_S,
            );
            let mut k = 3;
            while k < 40 {
                let (q, v, a) = desired(k, 0.0);
                m = g.follow(&m, &q, &v, &a).0;
                k += 1;
            }
            assert!(m.ddq[2] > 7.0, "{}", m.ddq[2]);
            // the late cycle: the stream continues at constant acceleration
            m = g.extrapolate(&m);
            k += 1;
            let prev = m;
            let next = if path_to_the_restart == "offset" {
                // the controller's answer, moved on and off the stream: an offset restarts
                let (q, v, a) = desired(k, 5e-3);
                let next = g.follow(&prev, &q, &v, &a).0;
                assert_eq!(g.path, 2, "a restart");
                // and every step of the offset after it (on the robot's verdict too)
                let (mut b, mut seq) = (next, vec![prev, next]);
                let mut worst = (0.0f64, 0usize, 0u8);
                for i in 1..400 {
                    let (q, v, a) = desired(k + i, 5e-3);
                    let n = g.follow(&b, &q, &v, &a).0;
                    for j in 0..JOINTS {
                        let jerk = ((n.ddq[j] - b.ddq[j]) / CYCLE_S).abs();
                        if jerk > worst.0 {
                            worst = (jerk, i, g.path);
                        }
                    }
                    b = n;
                    seq.push(n);
                }
                check(&seq);
                assert!(
                    worst.0 <= hedgeable(&l),
                    "the offset's step {} (path {}) jerks at {:.0} rad/s³ (at most {:.0})",
                    worst.1,
                    worst.2,
                    worst.0,
                    hedgeable(&l)
                );
                assert_eq!(g.path, 0, "the controller leads alone again");
                next
            } else {
                let next = g.brake(&prev).0;
                // and every step of the stop after it
                let mut b = next;
                for _ in 0..400 {
                    // as the robot differences it (a stop at rest reports zero rates)
                    let n = Motion::after(&b, &g.brake(&b).0.q, CYCLE_S);
                    let jerk = (0..JOINTS).fold(0.0f64, |x, j| {
                        x.max(((n.ddq[j] - b.ddq[j]) / CYCLE_S).abs())
                    });
                    assert!(jerk <= hedgeable(&l), "the stop jerks at {jerk:.0} rad/s³");
                    b = n;
                }
                next
            };
            for j in 0..JOINTS {
                let jerk = (next.ddq[j] - prev.ddq[j]) / CYCLE_S;
                assert!(
                    jerk.abs() <= hedgeable(&l),
                    "{path_to_the_restart}: joint {} jerks at {jerk:.0} rad/s³ from the stream \
                     (at most {:.0} leaves the hedge room)",
                    j + 1,
                    hedgeable(&l)
                );
            }
            // that answer went out late: the robot continued, a simulator applies it after all;
            // the next answer, computed against the continuation, passes from both
            let cont = prev.continued(CYCLE_S);
            let q = desired(k + 1, 0.0).0;
            let own = g.follow(&cont, &q, &[0.0; JOINTS], &[0.0; JOINTS]).0;
            let (h, _) = g.hedge(&cont, &[(next, 1)], &own.q);
            for r in [&cont, &next] {
                let m = Motion::after(r, &h, CYCLE_S);
                for j in 0..JOINTS {
                    let jerk = (m.ddq[j] - r.ddq[j]) / CYCLE_S;
                    assert!(
                        m.ddq[j].abs() <= l.ddq * (1.0 + 1e-6)
                            && jerk.abs() <= l.dddq * (1.0 + 1e-6),
                        "{path_to_the_restart}: joint {}: {} rad/s², {jerk:.0} rad/s³",
                        j + 1,
                        m.ddq[j]
                    );
                }
            }
            g = Guard::new(l, CYCLE_S).unwrap();
        }
    }

    #[test]
    fn a_hedged_command_passes_from_both_references_where_it_can() {
        let g = Guard::new(GuardLimits::fr3(0.83, 0.02), CYCLE_S).unwrap();
        let l = *g.limits();
        let mut prev = Motion::rest(home());
        prev.dq[3] = 0.5;
        prev.ddq[3] = 2.0;
        // the late answer moved with a jerk of 1000 rad/s³; the robot continued instead
        let late = Motion::after(
            &prev,
            &{
                let mut q = prev.continued(CYCLE_S).q;
                q[3] += 1e-6;
                q
            },
            CYCLE_S,
        );
        let cont = prev.continued(CYCLE_S);
        // the next command, computed against the continuation, jerks at -3000 rad/s³ from it:
        // from the late answer that is -6000, past the limit
        let mut q = cont.continued(CYCLE_S).q;
        q[3] -= 3e-6;
        let (h, changed) = g.hedge(&cont, &[(late, 1)], &q);
        assert!(changed);
        for r in [&cont, &late] {
            let m = Motion::after(r, &h, CYCLE_S);
            assert!(
                m.ddq[3].abs() <= l.ddq
                    && ((m.ddq[3] - r.ddq[3]) / CYCLE_S).abs() <= l.dddq * (1.0 + 1e-6),
                "{} rad/s², {} rad/s³",
                m.ddq[3],
                (m.ddq[3] - r.ddq[3]) / CYCLE_S
            );
        }
        // a command that passes from both is left alone
        let (same, changed) = g.hedge(&cont, &[(cont, 1)], &q);
        assert!(!changed && same == q);
    }

    #[test]
    fn an_offset_clipped_every_cycle_still_converges_behind_a_hard_acceleration() {
        // A trace (franka/src/testdata/offset_after_restart.csv): after a restart, the
        // controller accelerates joint 7 at 8 rad/s² (0.96 of this guard's 8.3) while the stream
        // still moves back at 0.07 rad/s. Replayed through the guard in closed loop (each answer
        // applied), the offset stays small. Before apply_offset took the offset like against
        // like (it took the clipped step's backward difference against the controller's velocity
        // field, half a cycle's acceleration apart), every step was clipped (`enforce`, the
        // hedgeable jerk), the offset's next step asked for a jump the clip cut again, and the
        // stream accelerated at 3-6 rad/s² behind the controller's 8: the offset reached 0.089
        // rad by the end of this window (in the run: 0.15, the generator's take-over 90 ms
        // later, the led share 0.67). The stream's rates (`Motion::rates`) against the fields
        // fixed this case and broke two above, whose controller's velocity field is its
        // positions' own difference: differences against differences hold for both.
        let (m, last) = replay_keeps_the_controller_leading(
            include_str!("testdata/offset_after_restart.csv"),
            0.0,
        );
        assert!(
            (m.q[6] - last[6]).abs() < 0.01,
            "{} against {}",
            m.q[6],
            last[6]
        );
    }

    #[test]
    fn an_offset_closes_when_the_controller_reseeds_behind_a_fast_stream() {
        // A trace (franka/src/testdata/offset_after_reseed.csv, the strategies test beside a busy
        // loop): the controller re-seeded joint 7 from the arm at rest, 9.5 mrad ahead, while
        // the stream moved at 1.4 rad/s, and then accelerated at 8 rad/s² the same way. The
        // stream must brake: at 0.9 of the robot's acceleration and within its jerk it runs
        // about 0.12 rad past. With the offset's acceleration bounded by 0.9 × the limit less
        // the controller's |8| (floored at 1.2 rad/s²) the stream hardly braked, ran 0.29 rad
        // past and the generator led 212 of these cycles (303 ms in the run).
        let (_, worst, generated, _) =
            replay_closed_loop(include_str!("testdata/offset_after_reseed.csv"), 0.0);
        assert_eq!(generated, 0, "the generator led");
        assert!(
            worst < 0.14,
            "a joint {worst} rad from the controller's position"
        );
    }

    /// A driver trace's rows (seq, desired 1-7, desired_v 1-7, sent 1-7; NaN desired: no
    /// answer that cycle) replayed through a fresh guard in closed loop, each answer applied
    /// and a cycle without one continued as the robot does: the last motion, the largest
    /// distance of any joint from the controller's position from row `from_seq` on, the cycles
    /// the generator led. The robot's verdict on every step is checked.
    fn replay_closed_loop(text: &str, from_seq: f64) -> (Motion, f64, usize, [f64; JOINTS]) {
        let rows: Vec<Vec<f64>> = text
            .lines()
            .filter(|l| !l.starts_with('#'))
            .map(|l| {
                l.split(',')
                    .map(|x| x.parse().unwrap_or(f64::NAN))
                    .collect()
            })
            .collect();
        let cols =
            |r: &Vec<f64>, c0: usize| -> [f64; JOINTS] { std::array::from_fn(|j| r[c0 + j]) };
        // the robot's history: the first three rows' answers
        let mut m = Motion::rest(cols(&rows[0], 15));
        m = Motion::after(&m, &cols(&rows[1], 15), CYCLE_S);
        m = Motion::after(&m, &cols(&rows[2], 15), CYCLE_S);
        let mut g = Guard::new(GuardLimits::fr3(0.83, 0.02), CYCLE_S).unwrap();
        let mut seq = vec![m];
        // the controller's acceleration field: its velocity field's difference (over the cycles
        // since the last answer)
        let mut last_v: Option<([f64; JOINTS], f64)> = None;
        let (mut worst, mut generated): (f64, usize) = (0.0, 0);
        for r in &rows[3..] {
            let (q, v) = (cols(r, 1), cols(r, 8));
            if q[0].is_nan() {
                m = g.extrapolate(&m);
                last_v = last_v.map(|(p, k)| (p, k + 1.0));
            } else {
                let a: [f64; JOINTS] = match last_v {
                    Some((p, k)) => std::array::from_fn(|j| (v[j] - p[j]) / (k * CYCLE_S)),
                    None => [0.0; JOINTS],
                };
                m = g.follow(&m, &q, &v, &a).0;
                last_v = Some((v, 1.0));
                generated += (g.path > 2) as usize;
                if r[0] >= from_seq {
                    worst = (0..JOINTS).fold(worst, |w, j| w.max((m.q[j] - q[j]).abs()));
                }
            }
            seq.push(m);
        }
        check(&seq);
        let last = rows
            .last()
            .map(|r| cols(r, 1))
            .unwrap_or([f64::NAN; JOINTS]);
        (m, worst, generated, last)
    }

    /// [`replay_closed_loop`], asserting the controller led every answered cycle and no joint
    /// went 0.02 rad from its position (from row `from_seq`); the last motion and desired row.
    fn replay_keeps_the_controller_leading(text: &str, from_seq: f64) -> (Motion, [f64; JOINTS]) {
        let (m, worst, generated, last) = replay_closed_loop(text, from_seq);
        assert_eq!(generated, 0, "the generator led");
        assert!(
            worst < 0.02,
            "a joint {worst} rad from the controller's position"
        );
        (m, last)
    }

    #[test]
    fn a_motion_after_a_reset_starts_where_the_arm_rests() {
        // an offset running when a reflex ends the motion (a jump of 0.05 rad at speed): the
        // next motion's first command, from rest, must be that rest; without the reset the old
        // offset's next step moved it (the restart's 8 292 rad/s³ in franka-sim)
        let running = || {
            let mut g = Guard::new(GuardLimits::fr3(0.83, 0.02), CYCLE_S).unwrap();
            let mut m = Motion::rest(home());
            for k in 1..200 {
                let mut q = swinging(k);
                if k > 150 {
                    q[3] += 0.05;
                }
                m = g.follow(&m, &q, &[0.0; JOINTS], &[0.0; JOINTS]).0;
            }
            assert!(g.offset.is_some(), "no offset running");
            (g, Motion::rest(m.q))
        };
        let (mut carried, rest) = running();
        let (first, _) = carried.follow(&rest, &swinging(400), &[0.0; JOINTS], &[0.0; JOINTS]);
        let (mut g, _) = running();
        g.reset();
        let (fresh, _) = g.follow(&rest, &swinging(400), &[0.0; JOINTS], &[0.0; JOINTS]);
        assert!(
            (0..JOINTS).all(|j| (fresh.q[j] - rest.q[j]).abs() < 1e-12),
            "{:?} against {:?}",
            fresh.q,
            rest.q
        );
        // (and the carried-over offset did move it: the test can fail)
        assert!((0..JOINTS).any(|j| (first.q[j] - rest.q[j]).abs() > 1e-9));
    }

    #[test]
    fn an_offset_after_a_late_cycle_at_a_turn_closes_a_trace_it_was_not_fitted_to() {
        // A second trace, from the next CI (franka/src/testdata/offset_after_late_turn.csv),
        // taken after the fix below was made: joint 7 turning from -8 to +8 rad/s² with a
        // late cycle at the turn (seq 639); in the run joint 7's offset grew to 0.149 rad over
        // 480 ms and the generator led 350 ms (the led share 0.926). The window opens with
        // joint 6 0.022 rad off (the run's own offset then), measured from the turn on.
        replay_keeps_the_controller_leading(
            include_str!("testdata/offset_after_late_turn.csv"),
            639.0,
        );
    }

    #[test]
    fn an_offset_after_late_cycles_into_a_hard_deceleration_closes_within_the_robots_jerk() {
        // A trace (franka/src/testdata/offset_after_late_decel.csv): joint 7 accelerating at
        // 8.3 rad/s² when the controller turned to decelerate at 8, three answers late (the
        // robot continued at +5.4 rad/s² while the controller was at -8: an offset 13 rad/s²
        // apart at the restart). The offset's own trajectory took that apart at its jerk of
        // 600 rad/s³ (0.12 of the robot's), and each clipped step's differences gave back what
        // its plan had taken off, so the stream ran on at +4 rad/s² for 60 ms behind a braking
        // controller: 0.7 rad/s too fast, the offset 0.15 rad 250 cycles later and the
        // generator leading 255 cycles (the run's led share 0.917). Replayed here: 0.074 rad
        // before, 0.043 with the jerk the stream leaves, 0.041 with the differences put
        // forward alone, 0.016 with both.
        replay_keeps_the_controller_leading(
            include_str!("testdata/offset_after_late_decel.csv"),
            0.0,
        );
    }
}
