//! The inference trigger: decides at each tick whether the next inference starts, and fills the
//! request (for `rtc`: the actions still to be executed and the guidance weights).
//!
//! Owns: the request hand-off's sending end and the outstanding request. Must not depend on:
//! the safety state machine, ruckig, IPC.

use crate::config::{Config, Jacobian, Schedule, Trigger};

use super::handoff::RequestSender;
use super::interp::Sample;
use super::rtc::{guidance_weights, Continuation, MAX_HORIZON};
use super::strategy::Sampling;
use crate::chunk::ActionChunk;

pub(crate) struct Requests {
    tx: RequestSender,
    trigger: Trigger,
    schedule: Schedule,
    /// s: actions of a chunk executed before the next inference starts.
    s: usize,
    beta: f64,
    jacobian: Jacobian,
    future_state: bool,
    action_period_ns: u64,
    timeout_ns: u64,
    /// When the request in flight was published (None: none in flight).
    outstanding_since: Option<u64>,
    next_id: u64,
}

impl Requests {
    /// The trigger of `config.execution`, publishing into `tx`.
    pub fn new(config: &Config, tx: RequestSender) -> Self {
        let e = &config.execution;
        Self {
            tx,
            trigger: e.trigger,
            schedule: e.rtc_schedule,
            s: e.execute_horizon.max(1),
            beta: e.guidance_beta,
            jacobian: e.rtc_jacobian,
            future_state: e.future_state,
            action_period_ns: ((1e9 / config.policy.action_rate_hz).round() as u64).max(1),
            timeout_ns: super::ms_to_ns(e.inference_timeout_ms),
            outstanding_since: None,
            next_id: 1,
        }
    }

    /// The request in flight was answered (a chunk arrived) or is void (re-arm).
    pub fn landed(&mut self) {
        self.outstanding_since = None;
    }

    /// Publishes the next request if it is due at `now_ns`: none in flight (or the one in
    /// flight timed out) and the trigger says so. `newest`: the newest chunk received; `d`: the
    /// delay estimate; `continuation`: how the strategy wants the chunk to continue the
    /// previous one. True if published.
    pub fn maybe_request(
        &mut self,
        now_ns: u64,
        newest: Option<&ActionChunk>,
        d: usize,
        continuation: Continuation,
        sampling: &Sampling,
    ) -> bool {
        if let Some(t) = self.outstanding_since {
            if now_ns.saturating_sub(t) < self.timeout_ns {
                return false;
            }
            self.outstanding_since = None;
        }
        let due = match (self.trigger, newest) {
            (Trigger::Continuous, _) | (_, None) => true,
            // s actions after the newest chunk's observation (not after its start: a
            // future-state chunk starts a delay later, and the next one would land too late)
            (Trigger::AfterS, Some(c)) => {
                now_ns as i64
                    >= super::interp::start_ns(c, sampling.offset_ns) - c.start_shift_ns as i64
                        + (self.s as i64) * c.period_ns as i64
            }
        };
        if !due {
            return false;
        }
        let id = self.next_id;
        let published = self.tx.publish(|r| {
            r.id = id;
            r.t_ref_ns = now_ns;
            r.n_dof = sampling.n;
            r.execute_horizon = self.s;
            r.delay_steps = d;
            r.beta = self.beta;
            r.jacobian = self.jacobian;
            match newest {
                Some(c) => {
                    let h = c.horizon().min(MAX_HORIZON);
                    r.horizon = h;
                    r.period_ns = c.period_ns;
                    r.continuation = continuation;
                    r.future_state = self.future_state;
                    let mut s = Sample::default();
                    for i in 0..h {
                        let t = now_ns as i64 + i as i64 * c.period_ns as i64;
                        sampling.sample(c, t, &mut s);
                        r.prefix[i][..sampling.n].copy_from_slice(&s.position[..sampling.n]);
                    }
                    // RTC's hard mask covers the d actions executed while the chunk is computed;
                    // with a future state the new chunk starts at the next one (prefix row d), so
                    // that row is held too: the chunk's first action is where the switch happens
                    let held = if self.future_state { d + 1 } else { d };
                    guidance_weights(h, self.s, held, self.schedule, &mut r.weights);
                }
                None => {
                    r.horizon = 0;
                    r.period_ns = self.action_period_ns;
                    r.continuation = Continuation::Fresh;
                    r.future_state = false;
                }
            }
        });
        if published {
            self.next_id += 1;
            self.outstanding_since = Some(now_ns);
        }
        published
    }
}
