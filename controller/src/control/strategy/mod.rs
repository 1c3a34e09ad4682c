//! How consecutive chunks take over from each other: one file per strategy behind the
//! [`Transition`] trait, and the one place that dispatches on the configured strategy
//! ([`Transitions::get`]). A new strategy is a new file, a variant of
//! [`crate::config::Strategy`] and one arm in [`Transitions::new`] and [`Transitions::get`].
//!
//! Owns: when a chunk takes effect, which older chunks stay, and the target sampled from them.
//! Must not depend on: the safety state machine, ruckig, IPC.

use std::collections::VecDeque;

use crate::config::{Config, Interpolation, Strategy};
use chunkrt_ipc::MAX_DOF;

use super::interp::{self, Coverage, Sample};
use super::rtc::Continuation;
use crate::chunk::ActionChunk;

mod crossfade;
mod ensemble;
mod replace;
mod rtc;

pub(crate) use crossfade::Crossfade;
pub(crate) use ensemble::TemporalEnsemble;
pub(crate) use replace::Replace;
pub(crate) use rtc::Rtc;

/// A chunk in the executor's timeline.
pub(crate) struct Slot {
    pub chunk: ActionChunk,
    /// From when the chunk is in effect (ns).
    pub active_from: i64,
}

/// How chunks are sampled (the same for every strategy).
#[derive(Debug, Clone, Copy)]
pub(crate) struct Sampling {
    pub n: usize,
    pub offset_ns: i64,
    pub interp: Interpolation,
    /// Step channels (e.g. a gripper): sampled, never blended.
    pub step: [bool; MAX_DOF],
}

impl Sampling {
    /// Samples `chunk` at `now` into `out`.
    pub fn sample(&self, chunk: &ActionChunk, now: i64, out: &mut Sample) -> Coverage {
        interp::sample(chunk, now, self.offset_ns, self.interp, &self.step, out)
    }
}

/// Time of the first action of `chunk` due at or after `now` (where `replace` and `crossfade`
/// switch).
pub(super) fn first_due(chunk: &ActionChunk, now: i64, s: &Sampling) -> i64 {
    let k = interp::first_due_at_or_after(chunk, now, s.offset_ns);
    interp::start_ns(chunk, s.offset_ns) + k as i64 * chunk.period_ns as i64
}

/// One chunk-transition strategy. Called from the control tick: no allocation, no locks.
pub(crate) trait Transition {
    /// From when a newly accepted chunk is in effect (`now`: the tick's time, ns).
    fn active_from(&self, chunk: &ActionChunk, now: i64, s: &Sampling) -> i64;

    /// How many chunks before the one in effect at `now` stay in the timeline (`None`: every
    /// chunk stays until it expires).
    fn keep_before(&self, current: &Slot, now: i64) -> Option<usize> {
        let _ = (current, now);
        Some(0)
    }

    /// Samples the target at `now` from the timeline (oldest first) into `target`; returns the
    /// primary chunk's (id, observation_seq), or `None` when nothing covers `now`. Default: the
    /// chunk in effect alone.
    fn evaluate(
        &self,
        slots: &VecDeque<Slot>,
        now: i64,
        s: &Sampling,
        target: &mut Sample,
        _scratch: &mut Sample,
    ) -> Option<(u64, u64)> {
        sample_current(slots, now, s, target).map(|(_, primary)| primary)
    }

    /// How inference requests ask the next chunk to continue the current one.
    fn continuation(&self) -> Continuation {
        Continuation::Fresh
    }
}

/// The configured strategy (enum dispatch: no allocation, one `match`).
pub(crate) enum Transitions {
    Replace(Replace),
    Crossfade(Crossfade),
    TemporalEnsemble(TemporalEnsemble),
    Rtc(Rtc),
}

impl Transitions {
    /// The strategy of `config.execution`.
    pub fn new(config: &Config) -> Self {
        let e = &config.execution;
        match e.strategy {
            Strategy::Replace => Self::Replace(Replace),
            Strategy::Crossfade => Self::Crossfade(Crossfade {
                window_ns: super::ms_to_ns(e.crossfade_ms) as i64,
            }),
            Strategy::TemporalEnsemble => Self::TemporalEnsemble(TemporalEnsemble {
                decay: e.ensemble_decay,
            }),
            Strategy::Rtc => Self::Rtc(Rtc { trained: false }),
            Strategy::RtcTrained => Self::Rtc(Rtc { trained: true }),
        }
    }

    /// The strategy behind the trait.
    pub fn get(&self) -> &dyn Transition {
        match self {
            Self::Replace(t) => t,
            Self::Crossfade(t) => t,
            Self::TemporalEnsemble(t) => t,
            Self::Rtc(t) => t,
        }
    }
}

/// Index of the newest chunk in effect at `now`.
pub(crate) fn current(slots: &VecDeque<Slot>, now: i64) -> Option<usize> {
    (0..slots.len())
        .rev()
        .find(|&i| slots[i].active_from <= now)
}

/// Samples the chunk in effect at `now` into `target`: its index and (id, observation_seq),
/// or `None` when no chunk is in effect or it has run out.
pub(crate) fn sample_current(
    slots: &VecDeque<Slot>,
    now: i64,
    s: &Sampling,
    target: &mut Sample,
) -> Option<(usize, (u64, u64))> {
    let ic = current(slots, now)?;
    let c = &slots[ic].chunk;
    if s.sample(c, now, target) == Coverage::After {
        return None;
    }
    Some((ic, (c.id, c.observation_seq)))
}

#[cfg(test)]
mod tests {
    use super::*;

    const MS: i64 = 1_000_000;

    /// A 1-joint chunk observed at `t_obs`, actions every 10 ms at constant `value`.
    fn chunk(id: u64, t_obs: i64, value: f64) -> ActionChunk {
        ActionChunk {
            id,
            observation_seq: id,
            t_obs_ns: t_obs as u64,
            period_ns: (10 * MS) as u64,
            n_dof: 1,
            actions: vec![value; 10],
            ready_ns: t_obs as u64,
            start_shift_ns: 0,
        }
    }

    fn sampling() -> Sampling {
        Sampling {
            n: 1,
            offset_ns: 0,
            interp: Interpolation::Linear,
            step: [false; MAX_DOF],
        }
    }

    #[test]
    fn each_strategy_places_and_samples_chunks_its_own_way() {
        let s = sampling();
        let (old, new) = (chunk(1, 0, 0.0), chunk(2, 20 * MS, 1.0));
        let now = 35 * MS; // between the new chunk's actions 1 (30 ms) and 2 (40 ms)
                           // replace and crossfade switch at the first action not yet due; rtc and the ensemble now
        assert_eq!(Replace.active_from(&new, now, &s), 40 * MS);
        let fade = Crossfade { window_ns: 20 * MS };
        assert_eq!(fade.active_from(&new, now, &s), 40 * MS);
        let (rtc, trained) = (Rtc { trained: false }, Rtc { trained: true });
        assert_eq!(rtc.active_from(&new, now, &s), now);
        assert_eq!(trained.active_from(&new, now, &s), now);
        let ens = TemporalEnsemble { decay: 0.0 };
        assert_eq!(ens.active_from(&new, now, &s), now);
        assert_eq!(rtc.continuation(), Continuation::Guided);
        assert_eq!(trained.continuation(), Continuation::Committed);
        for other in [&Replace as &dyn Transition, &fade, &ens] {
            assert_eq!(other.continuation(), Continuation::Fresh);
        }

        let slots: VecDeque<Slot> = [(old, 0), (new, 40 * MS)]
            .into_iter()
            .map(|(chunk, active_from)| Slot { chunk, active_from })
            .collect();
        let (mut t, mut scratch) = (Sample::default(), Sample::default());
        // before the switch: the old chunk
        assert_eq!(
            Replace.evaluate(&slots, now, &s, &mut t, &mut scratch),
            Some((1, 1))
        );
        assert_eq!(t.position[0], 0.0);
        // half-way through the crossfade window: smoothstep(0.5) = 0.5 of the new chunk
        let mid = 50 * MS;
        assert_eq!(
            fade.evaluate(&slots, mid, &s, &mut t, &mut scratch),
            Some((2, 2))
        );
        assert!((t.position[0] - 0.5).abs() < 1e-12, "{}", t.position[0]);
        assert_eq!(fade.keep_before(&slots[1], mid), Some(1));
        assert_eq!(fade.keep_before(&slots[1], 60 * MS), Some(0));
        assert_eq!(Replace.keep_before(&slots[1], mid), Some(0));
        assert_eq!(ens.keep_before(&slots[1], mid), None);
        // the ensemble with m = 0: the plain mean of both chunks
        assert_eq!(
            ens.evaluate(&slots, mid, &s, &mut t, &mut scratch),
            Some((2, 2))
        );
        assert!((t.position[0] - 0.5).abs() < 1e-12, "{}", t.position[0]);
        // after the old chunk ended, the crossfade is the new chunk alone
        assert_eq!(
            fade.evaluate(&slots, 95 * MS, &s, &mut t, &mut scratch),
            Some((2, 2))
        );
        assert_eq!(t.position[0], 1.0);
    }
}
