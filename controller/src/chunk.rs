//! The chunk timeline: what the inference side hands to the control loop.
//!
//! Convention: action `k` of a chunk is meant for time `t_obs_ns + offset_ns + k * period_ns`,
//! where `t_obs_ns` is the capture time of the observation the chunk was computed from
//! (the joint state's measurement time) and `offset_ns` is the configured execution offset
//! (0 by default: action 0 is the action for the observed instant).
//!
//! Chunks are allocated by the inference thread and moved to the control thread whole; the
//! control thread never allocates for them (see `control`).

use chunkrt_ipc::MAX_DOF;

/// One action chunk in robot units (un-normalised, the robot's joint count).
#[derive(Debug, Clone, PartialEq)]
pub struct ActionChunk {
    /// Increasing id, unique within a controller run (0 is never used).
    pub id: u64,
    /// `seq` of the joint state behind the observation.
    pub observation_seq: u64,
    /// Capture time of the observation (monotonic ns).
    pub t_obs_ns: u64,
    /// Time between consecutive actions (ns), e.g. 20 ms at 50 Hz.
    pub period_ns: u64,
    /// Joints per action.
    pub n_dof: usize,
    /// Actions, row-major `[horizon][n_dof]`.
    pub actions: Vec<f64>,
    /// When the chunk became ready (monotonic ns).
    pub ready_ns: u64,
    /// Future-state inference: the chunk continues from the state the robot was predicted to
    /// reach this long after the observation, so its action 0 is for
    /// `t_obs_ns + offset + start_shift_ns` (0: from the observation itself).
    pub start_shift_ns: u64,
}

impl ActionChunk {
    /// Number of actions.
    pub fn horizon(&self) -> usize {
        self.actions.len().checked_div(self.n_dof).unwrap_or(0)
    }

    /// Action `k` (`n_dof` values).
    pub fn action(&self, k: usize) -> &[f64] {
        &self.actions[k * self.n_dof..(k + 1) * self.n_dof]
    }

    /// Time action `k` is meant for.
    pub fn time_of(&self, k: usize, offset_ns: i64) -> u64 {
        (self.t_obs_ns as i64
            + self.start_shift_ns as i64
            + offset_ns
            + k as i64 * self.period_ns as i64)
            .max(0) as u64
    }

    /// Checks the chunk's shape and numbers before it reaches the control loop.
    pub fn validate(&self) -> Result<(), ChunkError> {
        if self.n_dof == 0 || self.n_dof > MAX_DOF {
            return Err(ChunkError::NDof(self.n_dof));
        }
        if self.actions.is_empty() || !self.actions.len().is_multiple_of(self.n_dof) {
            return Err(ChunkError::Shape {
                len: self.actions.len(),
                n_dof: self.n_dof,
            });
        }
        if self.period_ns == 0 {
            return Err(ChunkError::ZeroPeriod);
        }
        if let Some(i) = self.actions.iter().position(|a| !a.is_finite()) {
            return Err(ChunkError::NonFinite {
                step: i / self.n_dof,
                joint: i % self.n_dof,
            });
        }
        Ok(())
    }
}

/// A chunk that must not be executed.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
pub enum ChunkError {
    #[error("chunk has {0} joints per action (1..={MAX_DOF} allowed)")]
    NDof(usize),
    #[error("chunk has {len} values, not a multiple of {n_dof} joints")]
    Shape { len: usize, n_dof: usize },
    #[error("chunk has a zero action period")]
    ZeroPeriod,
    #[error("chunk action {step}, joint {joint} is not finite")]
    NonFinite { step: usize, joint: usize },
}

#[cfg(test)]
mod tests {
    use super::*;

    fn chunk(actions: Vec<f64>, n_dof: usize) -> ActionChunk {
        ActionChunk {
            id: 1,
            observation_seq: 1,
            t_obs_ns: 1_000,
            period_ns: 20,
            n_dof,
            actions,
            ready_ns: 2_000,
            start_shift_ns: 0,
        }
    }

    #[test]
    fn timeline_and_validation() {
        let c = chunk(vec![0.0, 1.0, 2.0, 3.0, 4.0, 5.0], 2);
        assert_eq!(c.horizon(), 3);
        assert_eq!(c.action(1), &[2.0, 3.0]);
        assert_eq!(c.time_of(2, 0), 1_040);
        assert_eq!(c.time_of(0, -5), 995);
        assert!(c.validate().is_ok());
        assert_eq!(
            chunk(vec![0.0; 5], 2).validate(),
            Err(ChunkError::Shape { len: 5, n_dof: 2 })
        );
        assert_eq!(
            chunk(vec![0.0, f64::NAN], 2).validate(),
            Err(ChunkError::NonFinite { step: 0, joint: 1 })
        );
        assert_eq!(chunk(vec![], 0).validate(), Err(ChunkError::NDof(0)));
    }
}
