//! Target shaping: turns the strategy's target (position, velocity, acceleration of the
//! executed chunk at the tick) into ruckig's target for this tick, inside the joint limits.
//!
//! Owns: the tracking law and the limit rules. Must not depend on: chunks, the safety state
//! machine, IPC.

use crate::config::Config;
use chunkrt_ipc::MAX_DOF;

use super::interp::Sample;
use super::otg::{OtgInput, CONTROL_POSITION, CONTROL_VELOCITY};

/// The robot's limits, resolved from the config once.
#[derive(Debug, Clone)]
pub(crate) struct Limits {
    pub n: usize,
    pub step: [bool; MAX_DOF],
    pub vmax: [f64; MAX_DOF],
    pub amax: [f64; MAX_DOF],
    pub jmax: [f64; MAX_DOF],
    pub pmin: [f64; MAX_DOF],
    pub pmax: [f64; MAX_DOF],
    /// Tracking: the most the position-error term may add to the chunk's velocity (rad/s).
    pub correction: [f64; MAX_DOF],
    /// The control period (s): how far the generator moves before the next tick looks again.
    pub dt: f64,
}

impl Limits {
    /// The first `n` joints of `config.robot`.
    pub fn new(config: &Config, n: usize) -> Self {
        let mut l = Self {
            n,
            step: [false; MAX_DOF],
            vmax: [1.0; MAX_DOF],
            amax: [1.0; MAX_DOF],
            jmax: [1.0; MAX_DOF],
            pmin: [f64::NEG_INFINITY; MAX_DOF],
            pmax: [f64::INFINITY; MAX_DOF],
            correction: [1.0; MAX_DOF],
            dt: config.control_period_ns().max(1) as f64 * 1e-9,
        };
        for (i, j) in config.robot.joints.iter().take(n).enumerate() {
            l.step[i] = j.step;
            l.vmax[i] = j.max_velocity;
            l.amax[i] = j.max_acceleration;
            l.jmax[i] = j.max_jerk;
            l.pmin[i] = j.position_min;
            l.pmax[i] = j.position_max;
            l.correction[i] = config.execution.correction_speed * j.max_velocity;
        }
        l
    }
}

/// RUNNING: sets ruckig's target to follow `target`.
///
/// Tracking (`gain` > 0): the generator follows a velocity, the executed chunk's own velocity
/// and acceleration (its preview) plus the gain times the command's position error; it never
/// targets a fixed state, so it never has to loop back to hit a moving target "on time" (what a
/// fixed-target chase does whenever the command is a hair behind and a bit slow). Without a
/// gain, the chunk's state at the tick is the generator's position target.
pub(crate) fn track(l: &Limits, gain: f64, target: &Sample, inp: &mut OtgInput) {
    inp.control_interface = if gain > 0.0 {
        CONTROL_VELOCITY
    } else {
        CONTROL_POSITION
    };
    for j in 0..l.n {
        let margin = 1e-9 * (l.pmax[j] - l.pmin[j]);
        let (lo, hi) = (l.pmin[j] + margin, l.pmax[j] - margin);
        let p = target.position[j].clamp(lo, hi);
        inp.target_position[j] = p;
        let (mut v, mut a) = if l.step[j] {
            (0.0, 0.0)
        } else {
            (target.velocity[j], target.acceleration[j])
        };
        // where the limit rule below measures from: the target (position interface) or the
        // command itself (tracking)
        let mut from = p;
        if gain > 0.0 {
            from = inp.current_position[j].clamp(lo, hi);
            // proportional near the chunk; further out, no faster than the joint can still
            // brake to the error's end at half its acceleration (a large error after a switch
            // closes without overshoot), and no faster than `correction_speed` allows
            let e = p - from;
            let brake = stop_speed(0.5 * l.amax[j], l.jmax[j], e.abs()).min(l.correction[j]);
            v += (gain * e).clamp(-brake, brake);
        }
        // Towards a limit the target may only move as fast as the generator can still stop
        // before it at a_stop = a_max / 2, its acceleration ramped at the jerk limit (the
        // jerk-aware `stop_speed`); at the limit, not at all. Otherwise tracking a target that
        // runs into a limit overshoots it.
        let (a_stop, jm) = (0.5 * l.amax[j], l.jmax[j]);
        let up = stop_speed(a_stop, jm, hi - from);
        let down = stop_speed(a_stop, jm, from - lo);
        if v >= up {
            v = up;
            a = a.min(0.0);
        } else if v <= -down {
            v = -down;
            a = a.max(0.0);
        }
        if gain <= 0.0 {
            // The position interface arrives at the target moving at its velocity: arriving
            // near a limit moving away from it means having turned round past it, so the speed
            // is bounded both ways.
            let s = up.min(down);
            v = v.clamp(-s, s);
        }
        // The guarantee: the soft rule above still lets the generator's own lag carry the
        // command past a limit, where the backstop clamp in the executor would kink it (jerk
        // spikes of 1e5 rad/s³ on the SO-101's wrist). Whenever one more tick of the hardest
        // push ruckig may make would leave the joint unable to stop (at the full acceleration
        // and jerk limits) before the limit, it stops now: ruckig's velocity interface with a
        // zero target is exactly that time-optimal stop, so the command ends at the limit or
        // short of it, within every limit. The target acceleration is zero: a target that
        // arrives at rest while still braking would first have to speed up (seen: 7e-4 rad
        // past the limit). (The position interface is given the stop's end, or a target short
        // of it, at rest.)
        let (cp, cv, ca) = (
            inp.current_position[j],
            inp.current_velocity[j],
            inp.current_acceleration[j],
        );
        let (am, dt) = (l.amax[j], l.dt);
        if must_stop(am, jm, dt, hi - cp, cv, ca) {
            if gain > 0.0 {
                (v, a) = (v.min(0.0), 0.0);
            } else {
                inp.target_position[j] = p.min(cp + stop_distance(am, jm, cv, ca));
                (v, a) = (0.0, 0.0);
            }
        }
        if must_stop(am, jm, dt, cp - lo, -cv, -ca) {
            if gain > 0.0 {
                (v, a) = (v.max(0.0), 0.0);
            } else {
                inp.target_position[j] = p.max(cp - stop_distance(am, jm, -cv, -ca));
                (v, a) = (0.0, 0.0);
            }
        }
        let vl = 0.99 * l.vmax[j];
        let v = v.clamp(-vl, vl);
        // ruckig rejects a target state that would have to exceed the velocity limit while its
        // acceleration is ramped to zero at the jerk limit: |v| + a^2 / (2 j) <= v_max, so
        // bound |a| accordingly (and by a_max)
        let al = (0.99 * l.amax[j]).min((2.0 * 0.99 * l.jmax[j] * (vl - v.abs()).max(0.0)).sqrt());
        inp.target_velocity[j] = v;
        inp.target_acceleration[j] = a.clamp(-al, al);
    }
}

/// The fastest a joint at `distance` (≥ 0) from a limit may move towards it and still stop
/// there decelerating at `a_stop`, its acceleration first ramped at the jerk limit `jmax`
/// (|d| = v²/2a + v·a/2j solved for v); 0 at or past the limit.
fn stop_speed(a_stop: f64, jmax: f64, distance: f64) -> f64 {
    let lag = a_stop * a_stop / (2.0 * jmax);
    ((lag * lag + 2.0 * a_stop * distance.max(0.0)).sqrt() - lag).max(0.0)
}

/// How far a joint moving at `v` with acceleration `a` (positive: towards the limit) travels
/// before it stands still with zero acceleration, braking as fast as `amax` and `jmax` allow:
/// the time-optimal stop (acceleration ramped down at the jerk limit, held at `-amax` if the
/// speed needs it, ramped back to zero).
pub(crate) fn stop_distance(amax: f64, jmax: f64, v: f64, a: f64) -> f64 {
    if v <= 0.0 && a <= 0.0 {
        return 0.0;
    }
    // the deceleration's peak, from v + (a² − peak²)/2j − peak²/2j = 0
    let peak = (jmax * v + 0.5 * a * a).max(0.0).sqrt();
    if peak < -a {
        // already braking harder than needed: it stands still while the acceleration is
        // ramped back to zero, within v·(−a/j)
        return v.max(0.0) * (-a / jmax);
    }
    let (peak, hold) = if peak > amax {
        (
            amax,
            ((v + (a * a - 2.0 * amax * amax) / (2.0 * jmax)) / amax).max(0.0),
        )
    } else {
        (peak, 0.0)
    };
    let (mut p, mut v, mut a) = (0.0, v, a);
    for (jerk, t) in [(-jmax, (a + peak) / jmax), (0.0, hold), (jmax, peak / jmax)] {
        p += v * t + a * t * t / 2.0 + jerk * t * t * t / 6.0;
        v += a * t + jerk * t * t / 2.0;
        a += jerk * t;
    }
    p.max(0.0)
}

/// Whether a joint `room` short of a limit, moving at `v` with acceleration `a` (positive:
/// towards it), must start its stop this tick: after one more tick of the hardest push (jerk
/// +`jmax` for `dt`), its time-optimal stop would no longer end before the limit.
pub(crate) fn must_stop(amax: f64, jmax: f64, dt: f64, room: f64, v: f64, a: f64) -> bool {
    let a1 = (a + jmax * dt).min(amax);
    let p1 = v * dt + a * dt * dt / 2.0 + jmax * dt * dt * dt / 6.0;
    let v1 = v + a * dt + jmax * dt * dt / 2.0;
    p1.max(0.0) + stop_distance(amax, jmax, v1, a1) >= room
}

/// HOLD, FAULT, STARTING: brake to zero velocity (jerk-limited) where the joints are.
pub(crate) fn brake(n: usize, inp: &mut OtgInput) {
    inp.control_interface = CONTROL_VELOCITY;
    inp.target_velocity[..n].fill(0.0);
    inp.target_acceleration[..n].fill(0.0);
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::control::otg::{Otg, OtgOutput, OtgResult};

    const DT: f64 = 1e-3;
    const VMAX: f64 = 2.0;
    const AMAX: f64 = 10.0;
    const JMAX: f64 = 200.0;

    fn one_joint(pmin: f64, pmax: f64) -> Limits {
        let mut l = Limits {
            n: 1,
            step: [false; MAX_DOF],
            vmax: [VMAX; MAX_DOF],
            amax: [AMAX; MAX_DOF],
            jmax: [JMAX; MAX_DOF],
            pmin: [f64::NEG_INFINITY; MAX_DOF],
            pmax: [f64::INFINITY; MAX_DOF],
            correction: [VMAX; MAX_DOF],
            dt: DT,
        };
        l.pmin[0] = pmin;
        l.pmax[0] = pmax;
        l
    }

    fn generator_input(l: &Limits) -> OtgInput {
        let mut inp = OtgInput {
            dofs: 1,
            synchronization: 3,
            ..Default::default()
        };
        inp.max_velocity = l.vmax;
        inp.max_acceleration = l.amax;
        inp.max_jerk = l.jmax;
        inp
    }

    /// `stop_distance` is the stop ruckig itself makes for a zero velocity target: the model
    /// the guard relies on, checked against the real generator.
    #[test]
    fn stop_distance_is_ruckigs_own_stop() {
        let l = one_joint(f64::NEG_INFINITY, f64::INFINITY);
        let mut otg = Otg::new(DT).expect("valid dt");
        let mut out = OtgOutput::default();
        let mut checked = 0;
        for v in [0.0, 0.01, 0.3, 1.0, 1.9] {
            for a in [-9.0, -2.0, 0.0, 0.5, 4.0, 9.5] {
                let mut inp = generator_input(&l);
                inp.control_interface = CONTROL_VELOCITY;
                inp.current_velocity[0] = v;
                inp.current_acceleration[0] = a;
                otg.reset();
                let mut furthest: f64 = 0.0;
                for _ in 0..5000 {
                    let r = otg.update(&inp, &mut out);
                    assert!(r.is_ok(), "v {v} a {a}: {r:?}");
                    inp.current_position = out.state.position;
                    inp.current_velocity = out.state.velocity;
                    inp.current_acceleration = out.state.acceleration;
                    furthest = furthest.max(out.state.position[0]);
                    if r == OtgResult::Finished {
                        break;
                    }
                }
                let model = stop_distance(AMAX, JMAX, v, a);
                // exact where the stop is ruckig's three phases; a bound where the joint is
                // already braking harder than it needs
                let exact = a >= 0.0 || (JMAX * v + 0.5 * a * a).sqrt() >= -a;
                if exact {
                    assert!(
                        (model - furthest).abs() < 1e-6,
                        "v {v} a {a}: model {model} ruckig {furthest}"
                    );
                    checked += 1;
                } else {
                    assert!(
                        model >= furthest - 1e-9,
                        "v {v} a {a}: {model} < {furthest}"
                    );
                }
            }
        }
        assert!(checked >= 20, "{checked}");
    }

    /// Runs `track` + ruckig for `ticks` against `target(k)`; returns the generator's positions.
    fn follow(
        l: &Limits,
        gain: f64,
        start: f64,
        target: impl Fn(usize) -> Sample,
        ticks: usize,
    ) -> Vec<f64> {
        let mut otg = Otg::new(DT).expect("valid dt");
        let mut inp = generator_input(l);
        inp.current_position[0] = start;
        let mut out = OtgOutput::default();
        let mut positions = Vec::with_capacity(ticks);
        for k in 0..ticks {
            track(l, gain, &target(k), &mut inp);
            let r = otg.update(&inp, &mut out);
            assert!(r.is_ok(), "tick {k}: {r:?}");
            inp.current_position = out.state.position;
            inp.current_velocity = out.state.velocity;
            inp.current_acceleration = out.state.acceleration;
            positions.push(out.state.position[0]);
        }
        positions
    }

    /// Asserts that the positions never cross `lo` or `hi` and that their jerk (third
    /// differences) stays within the limit; returns the lowest and highest position.
    fn assert_inside_and_smooth(pos: &[f64], lo: f64, hi: f64, gain: f64) -> (f64, f64) {
        let top = pos.iter().cloned().fold(f64::NEG_INFINITY, f64::max);
        let bottom = pos.iter().cloned().fold(f64::INFINITY, f64::min);
        assert!(
            top <= hi,
            "gain {gain}: crossed the upper limit by {}",
            top - hi
        );
        assert!(
            bottom >= lo,
            "gain {gain}: crossed the lower limit by {}",
            lo - bottom
        );
        let worst = pos
            .windows(4)
            .map(|w| ((w[3] - 3.0 * w[2] + 3.0 * w[1] - w[0]) / (DT * DT * DT)).abs())
            .fold(0.0, f64::max);
        assert!(worst <= JMAX * 1.001, "gain {gain}: jerk {worst}");
        (bottom, top)
    }

    /// A target that runs past a limit at speed (and one that sits past it, as the SO-101's
    /// wrist targets do): the command stops at the limit without crossing it, and its jerk,
    /// from the positions themselves, stays within the limit. Without `must_stop` (the soft rule
    /// alone) the tracked command crossed the upper limit by 6.7e-4 rad, where the executor's
    /// backstop clamp would kink it.
    #[test]
    fn a_target_past_a_limit_stops_the_command_at_the_limit_within_the_jerk_limit() {
        let (lo, hi) = (-0.4, 0.5);
        let l = one_joint(lo, hi);
        // up at 1.5 rad/s to 1.2 (past hi), held there, then down at 1.8 rad/s to -1.0 (past lo)
        let ramp = |k: usize| {
            let t = k as f64 * DT;
            let mut s = Sample::default();
            let (p, v) = if t < 0.8 {
                (1.5 * t, 1.5)
            } else if t < 1.5 {
                (1.2, 0.0)
            } else {
                (
                    (1.2 - 1.8 * (t - 1.5)).max(-1.0),
                    if t < 2.7 { -1.8 } else { 0.0 },
                )
            };
            s.position[0] = p;
            s.velocity[0] = v;
            s
        };
        for gain in [10.0, 0.0] {
            let pos = follow(&l, gain, 0.0, ramp, 3500);
            let (bottom, top) = assert_inside_and_smooth(&pos, lo, hi, gain);
            // it does reach the limits (the guard does not stop it short)
            assert!(top > hi - 2e-3, "gain {gain}: top {top}");
            assert!(bottom < lo + 2e-3, "gain {gain}: bottom {bottom}");
        }
    }

    /// Chunks that keep pushing past either limit with random velocities and accelerations
    /// (a new one every 20 ms, as a chunk's steps do; the SO-101's wrist sits at its limit
    /// this way): in 60 s of ticks on each interface the command never crosses a limit and its
    /// jerk stays within the limit. Before the zero target acceleration at a stop this crossed
    /// by 1.3e-3 rad.
    #[test]
    fn chunks_pushing_past_the_limits_never_carry_the_command_across() {
        let (lo, hi) = (-1.65806, 1.65806);
        let l = one_joint(lo, hi);
        let mut seed: u64 = 0x5eed;
        let mut uniform = move || {
            seed = seed
                .wrapping_mul(6364136223846793005)
                .wrapping_add(1442695040888963407);
            (seed >> 11) as f64 / (1u64 << 53) as f64 * 2.0 - 1.0
        };
        let mut targets = Vec::with_capacity(3000);
        for i in 0..3000 {
            let side = if (i / 150) % 2 == 0 { hi } else { lo };
            let mut s = Sample::default();
            s.position[0] = side + 0.05 * uniform();
            s.velocity[0] = 0.8 * uniform();
            s.acceleration[0] = 5.0 * uniform();
            targets.push(s);
        }
        for gain in [10.0, 0.0] {
            let pos = follow(&l, gain, 0.0, |k| targets[k / 20], 60_000);
            assert_inside_and_smooth(&pos, lo, hi, gain);
        }
    }

    /// A chunk held 1 rad away from the command (a new controller taking over an arm the chunk
    /// starts away from): with `correction_speed` 1 the error closes at the joint's full speed;
    /// with a correction of 0.3 × the joint's speed, never faster than that, and it still closes.
    #[test]
    fn a_large_error_closes_no_faster_than_the_correction_speed() {
        let far = |_: usize| {
            let mut s = Sample::default();
            s.position[0] = 1.0;
            s
        };
        let peak = |pos: &[f64]| {
            pos.windows(2)
                .map(|w| ((w[1] - w[0]) / DT).abs())
                .fold(0.0, f64::max)
        };
        let full = one_joint(-2.0, 2.0);
        let fast = follow(&full, 10.0, 0.0, far, 3000);
        assert!(peak(&fast) > 0.95 * VMAX, "{}", peak(&fast));
        let mut slow_l = one_joint(-2.0, 2.0);
        slow_l.correction[0] = 0.3 * VMAX;
        let slow = follow(&slow_l, 10.0, 0.0, far, 6000);
        assert!(peak(&slow) <= 0.3 * VMAX + 1e-6, "{}", peak(&slow));
        assert!((slow[5999] - 1.0).abs() < 1e-3, "{}", slow[5999]);
        assert_inside_and_smooth(&slow, -2.0, 2.0, 10.0);
    }
}
