//! Smoothness metrics of a command trace: discontinuity at chunk switches, jerk, and tracking
//! error to the intended trajectory. Used by the tests, the evaluation and the benches.

use chunkrt_ipc::MAX_DOF;

/// A recorded run of the control loop, one row per tick (allocates; not for the tick itself).
#[derive(Debug, Clone, Default)]
pub struct Trace {
    /// Control period (s).
    pub dt: f64,
    /// Joints in use.
    pub n_dof: usize,
    /// Joints excluded from the metrics (step channels such as a gripper).
    pub skip: [bool; MAX_DOF],
    /// Interpolated target before the trajectory generator.
    pub target: Vec<[f64; MAX_DOF]>,
    /// Commanded position (after the generator).
    pub command: Vec<[f64; MAX_DOF]>,
    /// Intended trajectory (what the chunks were trying to follow), if known.
    pub reference: Vec<[f64; MAX_DOF]>,
    /// Ticks at which a new chunk took effect.
    pub switches: Vec<usize>,
    /// Ticks that start a new stretch after a gap (e.g. RUNNING again after a HOLD that was not
    /// recorded): differences are never taken across them.
    pub breaks: Vec<usize>,
}

/// Smoothness of one trace. Jumps are the deviation of a position from its linear
/// extrapolation of the two previous ticks, `|x_k − 2x_{k−1} + x_{k−2}|` (a step of size D
/// gives D; a smooth curve gives ≈ a·dt²), maximised over joints and switch ticks (the tick of
/// the switch and the next one).
#[derive(Debug, Clone, Copy, Default, PartialEq)]
pub struct Smoothness {
    /// Largest jump of the interpolated target at a chunk switch.
    pub max_switch_jump_target: f64,
    /// Largest jump of the command at a chunk switch.
    pub max_switch_jump_command: f64,
    /// RMS of the command's jerk (third difference / dt³) over all ticks and joints.
    pub rms_jerk: f64,
    /// Largest |jerk| of the command.
    pub max_jerk: f64,
    /// RMS of command − reference (0 when no reference).
    pub tracking_rms: f64,
    /// Largest |command − reference|.
    pub tracking_max: f64,
    /// RMS of command − target: how closely the command follows the executed chunk (the
    /// interpolated, blended target it was generated from).
    pub follow_rms: f64,
    /// Largest |command − target| within [`LAG_WINDOW_S`] after a switch: the lag a switch
    /// leaves behind.
    pub max_lag_after_switch: f64,
    /// Number of switches seen.
    pub switches: usize,
}

impl Trace {
    /// An empty trace.
    pub fn new(dt: f64, n_dof: usize) -> Self {
        Self {
            dt,
            n_dof: n_dof.min(MAX_DOF),
            ..Default::default()
        }
    }

    /// Appends one tick.
    pub fn push(
        &mut self,
        target: &[f64; MAX_DOF],
        command: &[f64; MAX_DOF],
        reference: Option<&[f64; MAX_DOF]>,
        switched: bool,
    ) {
        if switched {
            self.switches.push(self.command.len());
        }
        self.target.push(*target);
        self.command.push(*command);
        if let Some(r) = reference {
            self.reference.push(*r);
        }
    }

    /// Marks a gap: the next tick pushed starts a new stretch (idempotent).
    pub fn gap(&mut self) {
        let k = self.command.len();
        if k > 0 && self.breaks.last() != Some(&k) {
            self.breaks.push(k);
        }
    }

    /// Ticks `k − span ..= k` lie in one stretch (no break after `k − span`).
    fn contiguous(&self, k: usize, span: usize) -> bool {
        k >= span && !self.breaks.iter().any(|&b| b > k - span && b <= k)
    }

    /// Computes the metrics.
    pub fn smoothness(&self) -> Smoothness {
        smoothness(self)
    }
}

fn second_diff(x: &[[f64; MAX_DOF]], k: usize, j: usize) -> f64 {
    x[k][j] - 2.0 * x[k - 1][j] + x[k - 2][j]
}

/// RMS and largest |a − b| over the rows both have and the given joints ((0, 0) for none).
fn rms_and_max<I: Iterator<Item = usize>>(
    a: &[[f64; MAX_DOF]],
    b: &[[f64; MAX_DOF]],
    joints: impl Fn() -> I,
) -> (f64, f64) {
    let (mut sum, mut cnt, mut max) = (0.0, 0usize, 0.0f64);
    for (x, y) in a.iter().zip(b) {
        for j in joints() {
            let e = x[j] - y[j];
            sum += e * e;
            cnt += 1;
            max = max.max(e.abs());
        }
    }
    if cnt == 0 {
        (0.0, 0.0)
    } else {
        ((sum / cnt as f64).sqrt(), max)
    }
}

/// How long after a switch its lag is looked for (s).
pub const LAG_WINDOW_S: f64 = 0.3;

/// Computes [`Smoothness`] of a trace.
pub fn smoothness(tr: &Trace) -> Smoothness {
    let n = tr.n_dof;
    let joints = || (0..n).filter(|&j| !tr.skip[j]);
    let mut m = Smoothness {
        switches: tr.switches.len(),
        ..Default::default()
    };
    for &s in &tr.switches {
        for k in [s, s + 1] {
            if k < tr.command.len() && tr.contiguous(k, 2) {
                for j in joints() {
                    m.max_switch_jump_target = m
                        .max_switch_jump_target
                        .max(second_diff(&tr.target, k, j).abs());
                    m.max_switch_jump_command = m
                        .max_switch_jump_command
                        .max(second_diff(&tr.command, k, j).abs());
                }
            }
        }
    }
    let dt3 = tr.dt * tr.dt * tr.dt;
    let (mut sum, mut cnt) = (0.0, 0usize);
    for k in (3..tr.command.len()).filter(|&k| tr.contiguous(k, 3)) {
        for j in joints() {
            let c = &tr.command;
            let jerk = (c[k][j] - 3.0 * c[k - 1][j] + 3.0 * c[k - 2][j] - c[k - 3][j]) / dt3;
            sum += jerk * jerk;
            cnt += 1;
            m.max_jerk = m.max_jerk.max(jerk.abs());
        }
    }
    if cnt > 0 {
        m.rms_jerk = (sum / cnt as f64).sqrt();
    }
    (m.tracking_rms, m.tracking_max) = rms_and_max(&tr.command, &tr.reference, joints);
    (m.follow_rms, _) = rms_and_max(&tr.command, &tr.target, joints);
    let window = (LAG_WINDOW_S / tr.dt).round() as usize;
    for &s in &tr.switches {
        for k in s..(s + window).min(tr.command.len()) {
            for j in joints() {
                m.max_lag_after_switch = m
                    .max_lag_after_switch
                    .max((tr.command[k][j] - tr.target[k][j]).abs());
            }
        }
    }
    m
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn no_difference_is_taken_across_a_gap() {
        let mut tr = Trace::new(0.001, 1);
        let at = |x: f64| {
            let mut v = [0.0; MAX_DOF];
            v[0] = x;
            v
        };
        for k in 0..10 {
            tr.push(&at(k as f64 * 1e-3), &at(k as f64 * 1e-3), None, false);
        }
        tr.gap();
        tr.gap();
        // a stretch 0.5 rad further on (the robot braked and moved meanwhile)
        for k in 0..10 {
            tr.push(
                &at(0.5 + k as f64 * 1e-3),
                &at(0.5 + k as f64 * 1e-3),
                None,
                k == 0,
            );
        }
        assert_eq!(tr.breaks, vec![10]);
        let m = tr.smoothness();
        assert!(
            m.rms_jerk < 1e-6 && m.max_switch_jump_target < 1e-9,
            "{m:?}"
        );
        // without the gap the same samples are a 0.5 rad step
        tr.breaks.clear();
        assert!(tr.smoothness().max_switch_jump_target > 0.45);
    }

    #[test]
    fn a_step_is_a_jump_and_a_line_is_not() {
        let mut tr = Trace::new(0.001, 1);
        for k in 0..10 {
            let x = if k < 5 {
                k as f64 * 0.01
            } else {
                k as f64 * 0.01 + 0.5
            };
            let mut row = [0.0; MAX_DOF];
            row[0] = x;
            let mut r = [0.0; MAX_DOF];
            r[0] = k as f64 * 0.01;
            tr.push(&row, &row, Some(&r), k == 5);
        }
        let m = tr.smoothness();
        assert!((m.max_switch_jump_target - 0.5).abs() < 1e-12);
        assert!((m.tracking_max - 0.5).abs() < 1e-12);
        assert_eq!(m.switches, 1);
        assert!(m.max_jerk > 1e8);
        let mut tr = Trace::new(0.001, 1);
        for k in 0..10 {
            let mut row = [0.0; MAX_DOF];
            row[0] = k as f64;
            tr.push(&row, &row, None, k == 5);
        }
        let m = tr.smoothness();
        assert!(m.max_switch_jump_target.abs() < 1e-12 && m.rms_jerk.abs() < 1e-6);
    }
}
