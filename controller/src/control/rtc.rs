//! Real-time chunking (Black, Galliker, Levine 2025), control side: the soft guidance mask,
//! the inference-delay estimator and the request handed to the guided sampler.
//!
//! Notation (action steps): H is the chunk horizon, s the actions executed before the next
//! inference starts, d the inference delay. The previous chunk's remaining actions Y (right-
//! padded to H) guide the new chunk with weights
//!
//! ```text
//! W_i = 1                                   for i < d
//! W_i = c_i (e^{c_i} − 1) / (e − 1)         for d ≤ i < H − s,  c_i = (H − s − i) / (H − s − d + 1)
//! W_i = 0                                   for i ≥ H − s
//! ```

use chunkrt_ipc::MAX_DOF;

/// Largest chunk horizon a request can carry.
pub const MAX_HORIZON: usize = 128;

pub use crate::config::Schedule;

/// Writes the guidance weights W_0..W_{H−1} into `out[..h]` (pure; no allocation).
/// `d` and `s` are clamped so that `d ≤ H − s` holds.
pub fn guidance_weights(h: usize, s: usize, d: usize, schedule: Schedule, out: &mut [f64]) {
    let h = h.min(out.len());
    let overlap = h.saturating_sub(s); // H − s
    let d = d.min(overlap);
    let denom = (overlap - d + 1) as f64;
    for (i, w) in out.iter_mut().enumerate().take(h) {
        *w = if i < d {
            1.0
        } else if i < overlap {
            let c = (overlap - i) as f64 / denom;
            match schedule {
                Schedule::Exp => c * (c.exp() - 1.0) / (std::f64::consts::E - 1.0),
                Schedule::Linear => c,
                Schedule::Ones => 1.0,
                Schedule::Zeros => 0.0,
            }
        } else {
            0.0
        };
    }
}

/// Estimates the inference delay d as the maximum of the last b observed delays (action steps).
/// Fixed capacity, no allocation after construction.
#[derive(Debug, Clone)]
pub struct DelayEstimator {
    ring: Vec<usize>,
    len: usize,
    next: usize,
    initial: usize,
}

impl DelayEstimator {
    /// `b` delays are kept (b ≥ 1); `initial` is the estimate before any observation.
    pub fn new(b: usize, initial: usize) -> Self {
        Self {
            ring: vec![0; b.max(1)],
            len: 0,
            next: 0,
            initial,
        }
    }

    /// Records one observed delay (action steps).
    pub fn observe(&mut self, d: usize) {
        self.ring[self.next] = d;
        self.next = (self.next + 1) % self.ring.len();
        self.len = (self.len + 1).min(self.ring.len());
    }

    /// Current estimate: max of the last b delays, or the initial guess.
    pub fn estimate(&self) -> usize {
        if self.len == 0 {
            self.initial
        } else {
            self.ring[..self.len]
                .iter()
                .copied()
                .max()
                .unwrap_or(self.initial)
        }
    }

    /// Number of delays observed (saturates at b).
    pub fn observed(&self) -> usize {
        self.len
    }
}

/// How the requested chunk should continue the one the robot is executing.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub enum Continuation {
    /// Not at all: plain sampling (and the first request of a run, with no chunk yet).
    #[default]
    Fresh,
    /// Inference-time RTC (`rtc`): the sampler is guided towards `prefix` with `weights`.
    Guided,
    /// Training-time RTC (`rtc_trained`): the chunk starts with the first `delay_steps` rows of
    /// `prefix` (the actions executed meanwhile), given to a policy trained with a committed
    /// prefix, and continues them.
    Committed,
}

/// A request from the control thread to start the next inference (fixed size, no heap).
///
/// For `rtc`, `prefix[i]` (row i, `n_dof` values) is the previous chunk sampled at
/// `t_ref_ns + i·period_ns` (Y, right-padded to `horizon` with its last action), and
/// `weights[i]` the soft mask W_i. The policy should observe as close to `t_ref_ns` as it can;
/// if its observation is captured at `t_obs`, it may shift the prefix by
/// `round((t_obs − t_ref_ns) / period_ns)` rows. For the other strategies `guided` is false and
/// only the trigger matters. For `rtc_trained` (`continuation` [`Continuation::Committed`]) the
/// chunk starts with the prefix rows [`Self::committed_rows`] names.
#[derive(Debug, Clone, PartialEq)]
pub struct InferenceRequest {
    /// Increasing id (1, 2, ...).
    pub id: u64,
    /// When the request was made (monotonic ns): the time the prefix starts at.
    pub t_ref_ns: u64,
    /// Action period of the prefix (ns).
    pub period_ns: u64,
    /// H, rows of `prefix` / entries of `weights` that are meaningful.
    pub horizon: usize,
    /// Joints per row.
    pub n_dof: usize,
    /// s.
    pub execute_horizon: usize,
    /// d, the estimated delay in action steps.
    pub delay_steps: usize,
    /// β, the guidance weight clip.
    pub beta: f64,
    /// `rtc`: the guidance's Jacobian (exact VJP or identity).
    pub jacobian: chunkrt_policy::Jacobian,
    /// How the chunk continues the previous one (guided for `rtc`, committed for `rtc_trained`;
    /// fresh for the other strategies and while no previous chunk exists).
    pub continuation: Continuation,
    /// Future-state inference (`execution.future_state`, VLASH): the policy should observe the
    /// state `prefix[delay_steps]` (where the current chunk will have taken the robot when the
    /// new chunk lands) instead of the measured one, and its chunk starts there (for
    /// `rtc_trained`: at the row [`Self::committed_rows`] names).
    pub future_state: bool,
    /// Y, row-major `[MAX_HORIZON][MAX_DOF]`; rows `..horizon`, columns `..n_dof` are used.
    pub prefix: [[f64; MAX_DOF]; MAX_HORIZON],
    /// W, `..horizon` used.
    pub weights: [f64; MAX_HORIZON],
}

impl Default for InferenceRequest {
    fn default() -> Self {
        Self {
            id: 0,
            t_ref_ns: 0,
            period_ns: 0,
            horizon: 0,
            n_dof: 0,
            execute_horizon: 0,
            delay_steps: 0,
            beta: 0.0,
            jacobian: Default::default(),
            continuation: Continuation::Fresh,
            future_state: false,
            prefix: [[0.0; MAX_DOF]; MAX_HORIZON],
            weights: [0.0; MAX_HORIZON],
        }
    }
}

impl InferenceRequest {
    /// Training-time RTC's plan, `(shift, c)`: the chunk starts at prefix row `shift` (its
    /// observed state is that row's) and its first `c` actions are prefix rows
    /// `shift..shift + c`, the actions the robot executes from the chunk's start until it
    /// lands. `c` is the delay d, but at most H − s (the rows the previous chunk vouches for:
    /// RTC's hard mask) and at most H − 2 − d (the chunk's last row, H − 1 steps after its
    /// start, must be due after the next chunk lands, d steps and a tick or so after this one:
    /// one inference is in flight; one row of slack). With future-state inference the delay
    /// beyond `c` moves the start (`shift = d − c`); without, the chunk starts at the request
    /// (`shift = 0`) and the switch may land past its committed rows.
    pub fn committed_rows(&self) -> (usize, usize) {
        let (h, s, d) = (self.horizon, self.execute_horizon, self.delay_steps);
        let c = d.min(h.saturating_sub(s)).min(h.saturating_sub(2 + d));
        let shift = if self.future_state {
            (d - c).min(h.saturating_sub(1))
        } else {
            0
        };
        (shift, c)
    }

    /// Prefix row `i` (`n_dof` values).
    pub fn prefix_row(&self, i: usize) -> &[f64] {
        &self.prefix[i][..self.n_dof]
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn weights_follow_the_paper() {
        let (h, s, d) = (50, 25, 5);
        let mut w = [0.0; 50];
        guidance_weights(h, s, d, Schedule::Exp, &mut w);
        for (i, &wi) in w.iter().enumerate().take(d) {
            assert_eq!(wi, 1.0, "i={i}");
        }
        // c_d = (H - s - d) / (H - s - d + 1) = 20/21
        let c: f64 = 20.0 / 21.0;
        let expect = c * (c.exp() - 1.0) / (std::f64::consts::E - 1.0);
        assert!((w[d] - expect).abs() < 1e-12);
        // strictly decreasing over the soft region, positive, below 1
        for i in d..(h - s - 1) {
            assert!(w[i] > w[i + 1], "i={i}: {} <= {}", w[i], w[i + 1]);
            assert!(w[i] < 1.0 && w[i] > 0.0);
        }
        // last soft entry: c = 1/21
        let c: f64 = 1.0 / 21.0;
        let expect = c * (c.exp() - 1.0) / (std::f64::consts::E - 1.0);
        assert!((w[h - s - 1] - expect).abs() < 1e-12);
        for &wi in &w[h - s..] {
            assert_eq!(wi, 0.0);
        }
    }

    #[test]
    fn weights_edge_cases() {
        let mut w = [9.0; 10];
        // d larger than the overlap is clamped: all of H - s is hard
        guidance_weights(10, 4, 20, Schedule::Exp, &mut w);
        assert_eq!(&w[..6], &[1.0; 6]);
        assert_eq!(&w[6..], &[0.0; 4]);
        // s >= H: nothing to guide
        guidance_weights(10, 10, 3, Schedule::Exp, &mut w);
        assert_eq!(w, [0.0; 10]);
        guidance_weights(10, 2, 2, Schedule::Ones, &mut w);
        assert_eq!(&w[..8], &[1.0; 8]);
        guidance_weights(10, 2, 2, Schedule::Zeros, &mut w);
        assert_eq!(&w[..3], &[1.0, 1.0, 0.0]);
        guidance_weights(10, 2, 2, Schedule::Linear, &mut w);
        assert!((w[2] - 6.0 / 7.0).abs() < 1e-12);
        assert_eq!("exp".parse(), Ok(Schedule::Exp));
        assert!("nope".parse::<Schedule>().is_err());
    }

    #[test]
    fn committed_rows_fit_the_horizon_and_the_next_landing() {
        let req = |d, future| InferenceRequest {
            horizon: 10,
            execute_horizon: 5,
            delay_steps: d,
            future_state: future,
            ..Default::default()
        };
        // the whole delay while it fits: the chunk starts at the request
        assert_eq!(req(0, true).committed_rows(), (0, 0));
        assert_eq!(req(3, true).committed_rows(), (0, 3));
        assert_eq!(req(4, true).committed_rows(), (0, 4));
        // beyond H - s and H - 2 - d, fewer rows and (future state) a later start: the chunk
        // still runs until the next one lands
        assert_eq!(req(5, true).committed_rows(), (2, 3));
        assert_eq!(req(6, true).committed_rows(), (4, 2));
        assert_eq!(req(8, true).committed_rows(), (8, 0));
        assert_eq!(req(7, false).committed_rows(), (0, 1));
        assert_eq!(req(12, true).committed_rows(), (9, 0));
    }

    #[test]
    fn delay_is_max_of_last_b() {
        let mut e = DelayEstimator::new(3, 7);
        assert_eq!(e.estimate(), 7);
        e.observe(2);
        assert_eq!(e.estimate(), 2);
        e.observe(9);
        e.observe(4);
        assert_eq!(e.estimate(), 9);
        e.observe(3); // 2 drops out
        assert_eq!(e.estimate(), 9);
        e.observe(1); // 9 drops out
        assert_eq!(e.estimate(), 4);
        assert_eq!(e.observed(), 3);
    }
}
