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
//! robot's acceleration and jerk; per joint no more acceleration than the envelope's deceleration,
//! and positions 0.06 rad inside the envelope's limits, so its braking curve stays under the
//! envelope). [`Motion`] holds what the robot computes: differences of the commanded positions.
//! No allocation after [`Guard::new`].

use chunkrt_controller::control::otg::{CONTROL_POSITION, CONTROL_VELOCITY};
use chunkrt_controller::control::{Otg, OtgInput, OtgOutput, OtgResult};

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
        for j in 0..JOINTS {
            let v = (q[j] - prev.q[j]) / dt;
            m.ddq[j] = (v - prev.dq[j]) / dt;
            m.dq[j] = v;
            m.q[j] = q[j];
        }
        m
    }
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
const GENERATOR_POSITION_MARGIN: f64 = 0.06;
/// Fraction of the robot's acceleration and jerk the generator plans with.
const GENERATOR_MARGIN: f64 = 0.8;

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

    /// The envelope's highest velocity at `q` against this range (rad/s).
    pub fn upper(&self, j: usize, q: f64) -> f64 {
        let room = (2.0 * ENVELOPE_DECEL[j] * (self.q_max[j] - q))
            .max(0.0)
            .sqrt();
        self.dq[j].min((room - ENVELOPE_OFFSET[j]).max(0.0)) - ENVELOPE_EPS
    }

    /// The envelope's lowest velocity at `q` against this range (rad/s).
    pub fn lower(&self, j: usize, q: f64) -> f64 {
        let room = (2.0 * ENVELOPE_DECEL[j] * (q - self.q_min[j]))
            .max(0.0)
            .sqrt();
        (-self.dq[j]).max((ENVELOPE_OFFSET[j] - room).min(0.0)) + ENVELOPE_EPS
    }

    /// Whether reaching `q` from `prev` in one cycle keeps joint `j` within these limits.
    fn passes(&self, j: usize, prev: &Motion, q: f64, dt: f64) -> bool {
        let v = (q - prev.q[j]) / dt;
        let a = (v - prev.dq[j]) / dt;
        let jerk = (a - prev.ddq[j]) / dt;
        q.is_finite()
            && jerk.abs() <= self.dddq
            && a.abs() <= self.ddq
            && (self.lower(j, prev.q[j])..=self.upper(j, prev.q[j])).contains(&v)
            && ((self.q_min[j]..=self.q_max[j]).contains(&q) || (q - prev.q[j]).abs() < 1e-12)
    }
}

/// The per-cycle guard. One per driver (it owns the trajectory generator of its fallbacks).
pub struct Guard {
    limits: GuardLimits,
    dt: f64,
    otg: Otg,
    input: OtgInput,
    out: OtgOutput,
    /// The generator's own state after its last step (position, velocity, acceleration): the
    /// next step continues from it when the motion is still the one it made (the differences
    /// the robot sees lag it by half a cycle, and restarting from them would slow it).
    planned: Option<([f64; JOINTS], [f64; JOINTS], [f64; JOINTS])>,
}

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
            input.max_velocity[j] = limits.dq[j] * GENERATOR_MARGIN;
            input.max_acceleration[j] = (DDQ_MAX.min(ENVELOPE_DECEL[j])) * GENERATOR_MARGIN;
            input.max_jerk[j] = DDDQ_MAX * GENERATOR_MARGIN;
            input.min_position[j] = ENVELOPE_Q_MIN[j].max(Q_MIN[j]) + GENERATOR_POSITION_MARGIN;
            input.max_position[j] = ENVELOPE_Q_MAX[j].min(Q_MAX[j]) - GENERATOR_POSITION_MARGIN;
        }
        Ok(Self {
            limits,
            dt,
            otg,
            input,
            out: OtgOutput::default(),
            planned: None,
        })
    }

    /// The limits in force.
    pub fn limits(&self) -> &GuardLimits {
        &self.limits
    }

    /// The command for this cycle towards the desired position `q` and velocity `v`: `q`
    /// itself when it keeps the motion within the limits (returns false), else the generator's
    /// next step towards (`q`, `v`) (true).
    pub fn follow(
        &mut self,
        prev: &Motion,
        q: &[f64; JOINTS],
        v: &[f64; JOINTS],
    ) -> (Motion, bool) {
        let passes = (0..JOINTS).all(|j| self.limits.passes(j, prev, q[j], self.dt));
        // once the generator is engaged it stays until it has caught the desired motion (a
        // switch back and forth would restart it from the robot's lagging differences)
        let caught = match &self.planned {
            Some((pq, pv, _)) if pq == &prev.q => (0..JOINTS).all(|j| {
                let want_v = if v[j].is_finite() { v[j] } else { 0.0 };
                (pv[j] - want_v).abs() < 1e-3 && (q[j] - (pq[j] + pv[j] * self.dt)).abs() < 1e-5
            }),
            _ => true,
        };
        if passes && caught {
            self.planned = None;
            return (Motion::after(prev, q, self.dt), false);
        }
        self.input.control_interface = CONTROL_POSITION;
        for j in 0..JOINTS {
            let (lo, hi) = (self.input.min_position[j], self.input.max_position[j]);
            let vmax = self.input.max_velocity[j];
            self.input.target_position[j] = if q[j].is_finite() {
                q[j].clamp(lo, hi)
            } else {
                prev.q[j].clamp(lo, hi)
            };
            self.input.target_velocity[j] = if v[j].is_finite() {
                v[j].clamp(-vmax, vmax)
            } else {
                0.0
            };
            self.input.target_acceleration[j] = 0.0;
        }
        (self.generate(prev), true)
    }

    /// One cycle without a new command: constant acceleration from `prev` when that keeps
    /// within the limits, else the stop's first cycle.
    pub fn extrapolate(&mut self, prev: &Motion) -> Motion {
        let mut q = prev.q;
        for (j, q) in q.iter_mut().enumerate() {
            *q += (prev.dq[j] + prev.ddq[j] * self.dt) * self.dt;
        }
        if (0..JOINTS).all(|j| self.limits.passes(j, prev, q[j], self.dt)) {
            Motion::after(prev, &q, self.dt)
        } else {
            self.brake(prev).0
        }
    }

    /// One cycle of the time-optimal stop from `prev` (velocity and acceleration to zero).
    /// Returns the motion and whether it is at rest.
    pub fn brake(&mut self, prev: &Motion) -> (Motion, bool) {
        if prev.at_rest() {
            return (Motion::rest(prev.q), true);
        }
        self.input.control_interface = CONTROL_VELOCITY;
        for j in 0..JOINTS {
            self.input.target_velocity[j] = 0.0;
            self.input.target_acceleration[j] = 0.0;
        }
        let m = self.generate(prev);
        (m, m.at_rest())
    }

    /// One step of the generator from `prev` towards the input's targets, as the robot sees it.
    fn generate(&mut self, prev: &Motion) -> Motion {
        let continued = match &self.planned {
            Some((q, _, _)) => q == &prev.q,
            None => false,
        };
        for j in 0..JOINTS {
            let vmax = self.input.max_velocity[j];
            let amax = self.input.max_acceleration[j];
            let (v, a) = match (&self.planned, continued) {
                (Some((_, v, a)), true) => (v[j], a[j]),
                _ => (prev.dq[j], prev.ddq[j]),
            };
            self.input.current_position[j] = prev.q[j];
            self.input.current_velocity[j] = v.clamp(-vmax, vmax);
            self.input.current_acceleration[j] = a.clamp(-amax, amax);
        }
        let r = self.otg.update(&self.input, &mut self.out);
        if !r.is_ok() && r != OtgResult::Error(-102) {
            // outside what the generator can plan from: keep the velocity's decay gentle
            self.planned = None;
            let mut q = prev.q;
            for (j, q) in q.iter_mut().enumerate() {
                *q += 0.5 * prev.dq[j] * self.dt;
            }
            return Motion::after(prev, &q, self.dt);
        }
        let st = &self.out.state;
        let (mut q, mut v, mut a) = ([0.0; JOINTS], [0.0; JOINTS], [0.0; JOINTS]);
        q.copy_from_slice(&st.position[..JOINTS]);
        v.copy_from_slice(&st.velocity[..JOINTS]);
        a.copy_from_slice(&st.acceleration[..JOINTS]);
        self.planned = Some((q, v, a));
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
            let (next, clamped) = g.follow(&m, &q, &[0.0; JOINTS]);
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
            let (next, c) = g.follow(&m, &target, &[0.0; JOINTS]);
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
        // 1.5 rad/s with a jerk-limited deceleration of ~9.5 rad/s²: a few hundred cycles
        assert!(k < 400, "{k} cycles");
        assert!(m.at_rest());
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
        for _ in 0..4000 {
            m = g.follow(&m, &target, &[0.0; JOINTS]).0;
            seq.push(m);
        }
        check(&seq);
        assert!(
            seq.iter().all(|m| m.q[1] <= l.q_max[1] + 1e-9),
            "{}",
            m.q[1]
        );
        assert!(m.q[1] > l.q_max[1] - 0.1, "it gets close: {}", m.q[1]);
        assert!(m.at_rest() || m.dq[1].abs() < 1e-3);
    }
}
