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
        };
        for (i, j) in config.robot.joints.iter().take(n).enumerate() {
            l.step[i] = j.step;
            l.vmax[i] = j.max_velocity;
            l.amax[i] = j.max_acceleration;
            l.jmax[i] = j.max_jerk;
            l.pmin[i] = j.position_min;
            l.pmax[i] = j.position_max;
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
            // closes without overshoot)
            // (at a = a_max / 2, after ramping the acceleration at the jerk limit:
            // |e| = v²/2a + v·a/2j solved for v)
            let e = p - from;
            let (ab, jm) = (0.5 * l.amax[j], l.jmax[j]);
            let lag = ab * ab / (2.0 * jm);
            let brake = (lag * lag + 2.0 * ab * e.abs()).sqrt() - lag;
            v += (gain * e).clamp(-brake, brake);
        }
        // Towards a limit the target may only move as fast as the generator can still stop
        // before it (|v| <= sqrt(2 · a_stop · distance left)); at the limit, not at all.
        // Otherwise tracking a target that runs into a limit overshoots it.
        let a_stop = 0.5 * l.amax[j];
        let up = (2.0 * a_stop * (hi - from)).max(0.0).sqrt();
        let down = (2.0 * a_stop * (from - lo)).max(0.0).sqrt();
        if v >= up {
            v = up;
            a = a.min(0.0);
        } else if v <= -down {
            v = -down;
            a = a.max(0.0);
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

/// HOLD, FAULT, STARTING: brake to zero velocity (jerk-limited) where the joints are.
pub(crate) fn brake(n: usize, inp: &mut OtgInput) {
    inp.control_interface = CONTROL_VELOCITY;
    inp.target_velocity[..n].fill(0.0);
    inp.target_acceleration[..n].fill(0.0);
}
