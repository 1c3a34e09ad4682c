//! Sampling a chunk at the control loop's own tick time.
//!
//! Action `k` of a chunk is meant for `t0 + k·Δt` (`t0 = t_obs + offset`, see `chunk`). Between
//! two actions the chunk is interpolated without lag: the curve passes through every action at
//! its time. `Cubic` is a velocity-continuous cubic Hermite spline whose tangents are central
//! differences of the neighbouring actions (one-sided at the ends); `Linear` connects the
//! actions with straight segments. Step channels (gripper) hold action `k` from its time until
//! action `k + 1` is due and are never interpolated.

use chunkrt_ipc::MAX_DOF;

use crate::chunk::ActionChunk;

pub use crate::config::Interpolation;

/// Position, velocity and acceleration of every joint at one instant.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Sample {
    pub position: [f64; MAX_DOF],
    pub velocity: [f64; MAX_DOF],
    pub acceleration: [f64; MAX_DOF],
}

impl Default for Sample {
    fn default() -> Self {
        Self {
            position: [0.0; MAX_DOF],
            velocity: [0.0; MAX_DOF],
            acceleration: [0.0; MAX_DOF],
        }
    }
}

/// Where a time falls on a chunk's timeline.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Coverage {
    /// Before action 0 (the sample is action 0, at rest).
    Before,
    /// Between action 0 and the last action (inclusive).
    Inside,
    /// After the last action: the chunk has expired (the sample is the last action, at rest).
    After,
}

/// Time of action 0 of `chunk` with execution offset `offset_ns`, as signed ns.
#[inline]
pub fn start_ns(chunk: &ActionChunk, offset_ns: i64) -> i64 {
    chunk.t_obs_ns as i64 + chunk.start_shift_ns as i64 + offset_ns
}

/// Time of the last action of `chunk`, as signed ns.
#[inline]
pub fn end_ns(chunk: &ActionChunk, offset_ns: i64) -> i64 {
    start_ns(chunk, offset_ns) + (chunk.horizon().saturating_sub(1) as i64) * chunk.period_ns as i64
}

/// Samples `chunk` at time `t_ns` into `out` (`chunk.n_dof` joints; `step[j]` marks step
/// channels). The chunk must be valid (`ActionChunk::validate`). No allocation.
pub fn sample(
    chunk: &ActionChunk,
    t_ns: i64,
    offset_ns: i64,
    mode: Interpolation,
    step: &[bool; MAX_DOF],
    out: &mut Sample,
) -> Coverage {
    let n = chunk.n_dof.min(MAX_DOF);
    let h = chunk.horizon();
    let dt = chunk.period_ns as f64 * 1e-9;
    let t0 = start_ns(chunk, offset_ns);
    let rel = (t_ns - t0) as f64 / chunk.period_ns as f64; // in action steps
    let at_rest = |k: usize, out: &mut Sample| {
        let a = chunk.action(k);
        out.position[..n].copy_from_slice(&a[..n]);
        out.velocity[..n].fill(0.0);
        out.acceleration[..n].fill(0.0);
    };
    if h == 0 || dt <= 0.0 {
        return Coverage::After;
    }
    if rel < 0.0 {
        at_rest(0, out);
        return Coverage::Before;
    }
    let last = (h - 1) as f64;
    if rel > last {
        at_rest(h - 1, out);
        return Coverage::After;
    }
    if h == 1 {
        at_rest(0, out);
        return Coverage::Inside;
    }
    // Segment k..k+1 with local parameter s in [0, 1].
    let k = (rel.floor() as usize).min(h - 2);
    let s = (rel - k as f64).clamp(0.0, 1.0);
    let p0 = chunk.action(k);
    let p1 = chunk.action(k + 1);
    for j in 0..n {
        if step[j] {
            // Action k holds until action k + 1 is due.
            let kk = if s >= 1.0 { k + 1 } else { k };
            out.position[j] = chunk.action(kk)[j];
            out.velocity[j] = 0.0;
            out.acceleration[j] = 0.0;
            continue;
        }
        match mode {
            Interpolation::Linear => {
                out.position[j] = p0[j] + s * (p1[j] - p0[j]);
                out.velocity[j] = (p1[j] - p0[j]) / dt;
                out.acceleration[j] = 0.0;
            }
            Interpolation::Cubic => {
                // Tangents (per step, i.e. Δt·velocity): central differences, one-sided at ends.
                let m0 = tangent(chunk, k, j);
                let m1 = tangent(chunk, k + 1, j);
                let (s2, s3) = (s * s, s * s * s);
                let h00 = 2.0 * s3 - 3.0 * s2 + 1.0;
                let h10 = s3 - 2.0 * s2 + s;
                let h01 = -2.0 * s3 + 3.0 * s2;
                let h11 = s3 - s2;
                out.position[j] = h00 * p0[j] + h10 * m0 + h01 * p1[j] + h11 * m1;
                let d00 = 6.0 * s2 - 6.0 * s;
                let d10 = 3.0 * s2 - 4.0 * s + 1.0;
                let d01 = -6.0 * s2 + 6.0 * s;
                let d11 = 3.0 * s2 - 2.0 * s;
                out.velocity[j] = (d00 * p0[j] + d10 * m0 + d01 * p1[j] + d11 * m1) / dt;
                let a00 = 12.0 * s - 6.0;
                let a10 = 6.0 * s - 4.0;
                let a01 = -12.0 * s + 6.0;
                let a11 = 6.0 * s - 2.0;
                out.acceleration[j] = (a00 * p0[j] + a10 * m0 + a01 * p1[j] + a11 * m1) / (dt * dt);
            }
        }
    }
    Coverage::Inside
}

/// Hermite tangent at action `k`, joint `j`, in position units per action step.
#[inline]
fn tangent(chunk: &ActionChunk, k: usize, j: usize) -> f64 {
    let h = chunk.horizon();
    if h < 2 {
        0.0
    } else if k == 0 {
        chunk.action(1)[j] - chunk.action(0)[j]
    } else if k + 1 >= h {
        chunk.action(h - 1)[j] - chunk.action(h - 2)[j]
    } else {
        0.5 * (chunk.action(k + 1)[j] - chunk.action(k - 1)[j])
    }
}

/// Index of the first action of `chunk` whose time is at or after `t_ns` (may be `horizon`).
pub fn first_due_at_or_after(chunk: &ActionChunk, t_ns: i64, offset_ns: i64) -> usize {
    let t0 = start_ns(chunk, offset_ns);
    if t_ns <= t0 {
        return 0;
    }
    let p = chunk.period_ns as i64;
    let k = ((t_ns - t0) + p - 1) / p;
    (k as usize).min(chunk.horizon())
}

#[cfg(test)]
mod tests {
    use super::*;

    fn chunk(actions: Vec<f64>, n_dof: usize) -> ActionChunk {
        ActionChunk {
            id: 1,
            observation_seq: 1,
            t_obs_ns: 1_000_000_000,
            period_ns: 20_000_000,
            n_dof,
            actions,
            ready_ns: 1_000_000_000,
            start_shift_ns: 0,
        }
    }

    #[test]
    fn passes_through_actions_without_lag() {
        // x(t) = t^2 sampled every 20 ms; joint 1 is a step channel.
        let mut a = Vec::new();
        for k in 0..10 {
            let t = k as f64 * 0.02;
            a.push(t * t);
            a.push(if k >= 5 { 1.0 } else { 0.0 });
        }
        let c = chunk(a, 2);
        let mut step = [false; MAX_DOF];
        step[1] = true;
        let mut s = Sample::default();
        for mode in [Interpolation::Cubic, Interpolation::Linear] {
            for k in 0..10 {
                let t = c.time_of(k, 0) as i64;
                assert_eq!(sample(&c, t, 0, mode, &step, &mut s), Coverage::Inside);
                let want = (k as f64 * 0.02).powi(2);
                assert!((s.position[0] - want).abs() < 1e-12, "{mode:?} k={k}");
            }
        }
        // Cubic: interior velocity of t^2 is exact with central differences (2t).
        let t = c.time_of(4, 0) as i64 + 10_000_000;
        sample(&c, t, 0, Interpolation::Cubic, &step, &mut s);
        assert!(
            (s.velocity[0] - 2.0 * 0.09).abs() < 1e-9,
            "{}",
            s.velocity[0]
        );
        assert!((s.position[0] - 0.09f64.powi(2)).abs() < 1e-9);
        // Step channel holds action 4 (0) until action 5 is due, then 1.
        assert_eq!(s.position[1], 0.0);
        let t5 = c.time_of(5, 0) as i64;
        sample(&c, t5 - 1, 0, Interpolation::Cubic, &step, &mut s);
        assert_eq!(s.position[1], 0.0);
        sample(&c, t5, 0, Interpolation::Cubic, &step, &mut s);
        assert_eq!(s.position[1], 1.0);
        // Coverage outside.
        assert_eq!(
            sample(
                &c,
                c.t_obs_ns as i64 - 1,
                0,
                Interpolation::Cubic,
                &step,
                &mut s
            ),
            Coverage::Before
        );
        assert_eq!(
            sample(
                &c,
                c.time_of(9, 0) as i64 + 1,
                0,
                Interpolation::Cubic,
                &step,
                &mut s
            ),
            Coverage::After
        );
        // Offset shifts the timeline.
        sample(
            &c,
            c.time_of(3, 0) as i64 + 5_000_000,
            5_000_000,
            Interpolation::Linear,
            &step,
            &mut s,
        );
        assert!((s.position[0] - 0.06f64.powi(2)).abs() < 1e-12);
    }

    #[test]
    fn cubic_is_velocity_continuous_at_knots() {
        let a: Vec<f64> = [0.0, 0.3, -0.2, 0.5, 0.5, 0.1].to_vec();
        let c = chunk(a, 1);
        let step = [false; MAX_DOF];
        let (mut l, mut r) = (Sample::default(), Sample::default());
        for k in 1..5 {
            let t = c.time_of(k, 0) as i64;
            sample(&c, t - 1, 0, Interpolation::Cubic, &step, &mut l);
            sample(&c, t + 1, 0, Interpolation::Cubic, &step, &mut r);
            assert!((l.velocity[0] - r.velocity[0]).abs() < 1e-4, "k={k}");
        }
    }

    #[test]
    fn first_due_index() {
        let c = chunk(vec![0.0; 10], 1);
        let t0 = c.t_obs_ns as i64;
        assert_eq!(first_due_at_or_after(&c, t0 - 5, 0), 0);
        assert_eq!(first_due_at_or_after(&c, t0, 0), 0);
        assert_eq!(first_due_at_or_after(&c, t0 + 1, 0), 1);
        assert_eq!(first_due_at_or_after(&c, t0 + 40_000_000, 0), 2);
        assert_eq!(first_due_at_or_after(&c, t0 + 10_000_000_000, 0), 10);
    }
}
