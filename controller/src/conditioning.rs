//! From the control side's [`InferenceRequest`] to what a policy is asked: the joint state it
//! observes and how its chunk is conditioned on the chunk the robot is executing
//! ([`Conditioning`]). Written once, for every chunk source that runs a policy: in this process
//! ([`crate::inference::PolicySource`]) or behind the openpi protocol
//! ([`crate::remote::RemoteSource`]).
//!
//! Owns: future-state inference (which state the policy observes, and the chunk's start shift),
//! step-channel snapping, and the request → conditioning mapping. Allocates only its buffers'
//! growth (it runs in the inference thread, never in the control thread).

use crate::config::Config;
use chunkrt_ipc::JointState;
use chunkrt_policy::{Conditioning, Guidance};

use crate::control::{Continuation, InferenceRequest};

/// What a policy is asked for one request: the state to observe, the conditioning, and where
/// the chunk starts relative to the observation.
#[derive(Debug, Clone, Copy)]
pub struct Ask<'a> {
    /// The joint state the policy observes (robot units, the robot's joints): the measured one,
    /// or with future-state inference where the current chunk will have taken the robot; step
    /// channels snapped to their nearer end.
    pub state: &'a [f64],
    /// How the chunk continues the one being executed.
    pub conditioning: Conditioning<'a>,
    /// The chunk's action 0 is for `t_obs + offset + start_shift_ns` ([`crate::chunk`]).
    pub start_shift_ns: u64,
}

/// Turns requests into [`Ask`]s, with buffers kept across calls.
#[derive(Debug, Clone)]
pub struct Conditioner {
    n_dof: usize,
    /// Per joint: `Some((open, closed))` for step channels, `None` for ordinary joints.
    step_ends: Vec<Option<(f64, f64)>>,
    state: Vec<f64>,
    rows: Vec<f64>,
    weights: Vec<f32>,
}

impl Conditioner {
    /// For the robot of `cfg`.
    pub fn new(cfg: &Config) -> Self {
        Self {
            n_dof: cfg.n_dof(),
            step_ends: cfg
                .robot
                .joints
                .iter()
                .map(|j| j.step.then_some((j.position_min, j.position_max)))
                .collect(),
            state: Vec::new(),
            rows: Vec::new(),
            weights: Vec::new(),
        }
    }

    /// The ask for `request`, given the measured `joint_state` observed at `t_obs_ns`, for a
    /// policy whose chunks have `horizon` actions.
    ///
    /// - Training-time RTC (`Committed`): the chunk starts with the actions the robot executes
    ///   until it lands (`c` prefix rows from row `shift`, [`InferenceRequest::committed_rows`]).
    /// - Future-state inference (VLASH): the policy observes where the current chunk will have
    ///   taken the robot when the new chunk lands (`prefix[d]`, d the estimated delay) and the
    ///   new chunk starts there, so it continues the motion instead of restarting it from the
    ///   stale measured state. (With a committed prefix: where the committed rows start.)
    /// - Inference-time RTC (`Guided`, β > 0): guided towards what the robot executes meanwhile;
    ///   with a future state the new chunk's action i is the old one's i + shift.
    /// - A step channel (a gripper) is open or closed: the policy sees it as one of its two
    ///   ends, as in its training data, not the in-between values a real gripper passes through.
    pub fn ask(
        &mut self,
        request: &InferenceRequest,
        joint_state: &JointState,
        t_obs_ns: u64,
        horizon: usize,
    ) -> Ask<'_> {
        let n = self.n_dof.min(joint_state.n_dof as usize);
        let usable = request.horizon > 0 && request.n_dof >= n;
        let committed = request.continuation == Continuation::Committed && usable;
        let (shift, c) = if committed {
            request.committed_rows()
        } else if request.future_state && usable {
            (request.delay_steps.min(request.horizon - 1), 0)
        } else {
            (0, 0)
        };
        // (a committed prefix that starts at the request goes with the measured state there)
        let from_prefix = usable && request.future_state && (!committed || shift > 0);
        let (observed, start_shift_ns) = if from_prefix {
            let start = request.t_ref_ns + shift as u64 * request.period_ns;
            (&request.prefix[shift][..n], start.saturating_sub(t_obs_ns))
        } else {
            (&joint_state.position[..n], 0)
        };
        self.state.clear();
        for (i, &v) in observed.iter().enumerate() {
            self.state
                .push(match self.step_ends.get(i).copied().flatten() {
                    Some((lo, hi)) => {
                        if v >= 0.5 * (lo + hi) {
                            hi
                        } else {
                            lo
                        }
                    }
                    None => v,
                });
        }
        self.rows.clear();
        self.weights.clear();
        let guided = !committed
            && request.continuation == Continuation::Guided
            && request.beta > 0.0
            && horizon > 0;
        if committed {
            for row in &request.prefix[shift..(shift + c).min(request.horizon)] {
                self.rows.extend_from_slice(&row[..n]);
            }
        } else if guided {
            let h = horizon.min(request.horizon.max(1));
            for i in 0..horizon {
                let k = i + shift;
                let row = &request.prefix[k.min(h - 1)];
                self.rows.extend_from_slice(&row[..n]);
                self.weights.push(if k < h {
                    request.weights[k] as f32
                } else {
                    0.0
                });
            }
        }
        let conditioning = if committed {
            Conditioning::Committed(&self.rows)
        } else if guided {
            Conditioning::Guided(Guidance {
                prefix: &self.rows,
                weights: &self.weights,
                beta: request.beta as f32,
                jacobian: request.jacobian,
            })
        } else {
            Conditioning::Fresh
        };
        Ask {
            state: &self.state,
            conditioning,
            start_shift_ns,
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn request(continuation: Continuation, future_state: bool, d: usize) -> InferenceRequest {
        let mut r = InferenceRequest {
            t_ref_ns: 1_000,
            period_ns: 20,
            horizon: 10,
            n_dof: 4,
            execute_horizon: 5,
            delay_steps: d,
            beta: 10.0,
            continuation,
            future_state,
            ..Default::default()
        };
        for i in 0..10 {
            r.prefix[i][..4].copy_from_slice(&[i as f64, 10.0 + i as f64, 0.0, 0.2]);
            r.weights[i] = 1.0 - i as f64 / 10.0;
        }
        r
    }

    fn measured() -> JointState {
        let mut js = JointState {
            n_dof: 4,
            ..Default::default()
        };
        js.position[..4].copy_from_slice(&[-1.0, -2.0, -3.0, 0.8]);
        js
    }

    #[test]
    fn fresh_observes_the_measured_state_with_the_gripper_snapped() {
        let cfg = Config::embedded_default();
        let mut c = Conditioner::new(&cfg);
        let a = c.ask(
            &request(Continuation::Fresh, false, 3),
            &measured(),
            900,
            10,
        );
        assert!(matches!(a.conditioning, Conditioning::Fresh));
        let hi = cfg.robot.joints[3].position_max;
        assert_eq!(a.state, &[-1.0, -2.0, -3.0, hi]);
        assert_eq!(a.start_shift_ns, 0);
    }

    #[test]
    fn future_state_observes_the_prefix_at_the_delay_and_shifts_the_guidance() {
        let cfg = Config::embedded_default();
        let mut c = Conditioner::new(&cfg);
        let a = c.ask(
            &request(Continuation::Guided, true, 3),
            &measured(),
            900,
            10,
        );
        assert_eq!(&a.state[..2], &[3.0, 13.0]);
        // prefix row 3 is for t_ref + 3 periods = 1060; observed at 900
        assert_eq!(a.start_shift_ns, 160);
        let Conditioning::Guided(g) = a.conditioning else {
            panic!("not guided")
        };
        assert_eq!(g.prefix.len(), 40);
        assert_eq!(g.prefix[0], 3.0); // the new chunk's action 0 is the old one's 3
        assert_eq!(g.prefix[36], 9.0); // padded with the last row
        assert_eq!(g.weights[0], 0.7);
        assert_eq!(g.weights[9], 0.0);
        assert_eq!(g.beta, 10.0);
    }

    #[test]
    fn committed_gives_the_rows_executed_meanwhile() {
        let cfg = Config::embedded_default();
        let mut c = Conditioner::new(&cfg);
        let a = c.ask(
            &request(Continuation::Committed, true, 3),
            &measured(),
            1_000,
            10,
        );
        let Conditioning::Committed(rows) = a.conditioning else {
            panic!("not committed")
        };
        assert_eq!(rows.len(), 3 * 4);
        assert_eq!(rows[4], 1.0);
        // the committed rows start at the request: the measured state there
        assert_eq!(a.state[0], -1.0);
        // β = 0 guides nothing: a fresh chunk
        let mut r = request(Continuation::Guided, false, 3);
        r.beta = 0.0;
        assert!(matches!(
            c.ask(&r, &measured(), 1_000, 10).conditioning,
            Conditioning::Fresh
        ));
    }
}
