//! The flow-matching sampler, written once: [`euler`] integrates from t = 1 (noise) to t = 0
//! (data); plain sampling against the prefix KV cache ([`PiModel::denoise`]), uncached sampling
//! (the full joint forward every step) and RTC's guided sampling (`crate::rtc`) all run it.

use candle_core::{DType, Module, Tensor};

use super::*;

/// Result of [`PiModel::sample`].
#[derive(Debug, Clone)]
pub struct SampleOutput {
    /// x_0 [B, H, A].
    pub actions: Tensor,
    /// Velocity at the first step (t = 1) [B, H, A].
    pub v_t_step0: Tensor,
    /// Time values of the steps (f32 accumulation).
    pub times: Vec<f32>,
}

/// The flow-matching sampler's integration, written once for the plain, uncached and guided
/// samplers: Euler from t = 1 (noise) to t = 0 (data) with `dt = -1/steps`, time accumulated in
/// f32 and the loop running while `t >= -dt/2` (openpi's grid), `x <- x + dt * v(x, t)` with the
/// state `x` in f32. `noise` [B, H, A].
pub fn euler(
    noise: &Tensor,
    steps: usize,
    mut velocity: impl FnMut(&Tensor, f32) -> Result<Tensor, PolicyError>,
) -> Result<SampleOutput, PolicyError> {
    if steps == 0 {
        return Err(PolicyError::Input("steps must be > 0".into()));
    }
    let dt = -1.0f32 / steps as f32;
    let mut time = 1.0f32;
    let mut x = noise.to_dtype(DType::F32)?;
    let mut v0 = None;
    let mut times = Vec::with_capacity(steps);
    while time >= -dt / 2.0 {
        let v = velocity(&x, time)?;
        x = (x + (&v * dt as f64)?)?;
        if v0.is_none() {
            v0 = Some(v);
        }
        times.push(time);
        time += dt;
    }
    let v_t_step0 = v0.ok_or_else(|| PolicyError::Input("no denoising step ran".into()))?;
    Ok(SampleOutput {
        actions: x,
        v_t_step0,
        times,
    })
}

impl PiModel {
    /// Velocity from the joint forward (no cache) [B, H, A].
    pub fn velocity_uncached<'t>(
        &self,
        inp: &ModelInputs,
        prefix_embs: &Tensor,
        x_t: &Tensor,
        times: impl Into<FlowTimes<'t>>,
        diff: bool,
    ) -> Result<Tensor, PolicyError> {
        let (_, so) = self.joint_forward(inp, prefix_embs, x_t, times, diff)?;
        let s = so.dim(1)?;
        let h = self.cfg.action_horizon;
        Ok(self
            .action_out_proj
            .forward(&so.narrow(1, s - h, h)?.to_dtype(DType::F32)?)?)
    }

    /// Flow-matching sampler: Euler from t = 1 (noise) with `dt = -1/steps`, time accumulated in
    /// f32, loop while `t >= -dt/2`. `noise` [B, H, A]. With `cache` the prefix runs once and each
    /// step only runs the action expert (buffers in `cache` are reused); without, every step runs
    /// the full joint forward.
    pub fn sample(
        &self,
        inp: &ModelInputs,
        noise: &Tensor,
        steps: usize,
        cache: Option<&mut Option<PrefixCache>>,
    ) -> Result<SampleOutput, PolicyError> {
        let b = self.check_inputs(inp)?;
        let want = [b, self.cfg.action_horizon, self.cfg.action_dim];
        if noise.dims() != want {
            return Err(PolicyError::Input(format!(
                "noise: shape {:?}, expected {want:?}",
                noise.dims()
            )));
        }
        match cache {
            Some(cache) => {
                self.fill_cache(inp, cache, false)?;
                let c = cache.as_ref().expect("fill_cache stores the cache");
                self.denoise(c, noise, steps)
            }
            None => {
                let embs = self.embed_prefix(inp)?;
                euler(noise, steps, |x, t| {
                    self.velocity_uncached(inp, &embs, x, &vec![t; b], false)
                })
            }
        }
    }

    /// The denoising loop against a filled prefix cache: [`euler`] with the cached velocity.
    /// `noise` [B, H, A].
    pub fn denoise(
        &self,
        cache: &PrefixCache,
        noise: &Tensor,
        steps: usize,
    ) -> Result<SampleOutput, PolicyError> {
        let b = cache.batch;
        euler(noise, steps, |x, t| {
            self.velocity_at(cache, x, &vec![t; b], false)
        })
    }
}

impl PiModel {
    /// Training-time real-time chunking's sampler (Black et al. 2025, arXiv 2512.05964): the
    /// first `committed[b]` actions of row b are given, not generated. They enter as clean
    /// tokens at flow time 0 (`y` [B, H, A], the model's normalised space; rows past the
    /// committed prefix are ignored), keep that time at every step and are never moved, so the
    /// chunk starts with exactly them and the model, trained this way
    /// ([`ModelConfig::rtc_prefix_max`](crate::config::ModelConfig)), continues them. A step
    /// costs what an unguided one does: no backward pass, no second forward. `noise` [B, H, A].
    pub fn denoise_committed(
        &self,
        cache: &PrefixCache,
        noise: &Tensor,
        steps: usize,
        y: &Tensor,
        committed: &[usize],
    ) -> Result<SampleOutput, PolicyError> {
        let b = cache.batch;
        let (h, a) = (self.cfg.action_horizon, self.cfg.action_dim);
        if noise.dims() != [b, h, a] || y.dims() != [b, h, a] {
            return Err(PolicyError::Input(format!(
                "noise {:?} / committed actions {:?}, expected [{b}, {h}, {a}]",
                noise.dims(),
                y.dims()
            )));
        }
        if committed.len() != b || committed.iter().any(|&n| n >= h) {
            return Err(PolicyError::Input(format!(
                "committed prefix lengths {committed:?}: one per batch row ({b}), each below H = {h}"
            )));
        }
        // 1 on the tokens to generate, 0 on the committed ones [B, H, 1]
        let free = free_mask(committed, h, self.device())?;
        let kept = (free.neg()? + 1.0)?;
        // x starts as noise on the free tokens and as the committed actions on the others
        let x0 = (noise.to_dtype(DType::F32)?.broadcast_mul(&free)?
            + y.to_dtype(DType::F32)?.broadcast_mul(&kept)?)?;
        euler(&x0, steps, |x, t| {
            let tv = vec![t; b];
            let times = FlowTimes {
                t: &tv,
                committed: Some(committed),
            };
            // zero velocity on the committed tokens: x + dt·0 keeps them exactly
            Ok(self
                .velocity_at(cache, x, times, false)?
                .broadcast_mul(&free)?)
        })
    }
}

#[cfg(test)]
mod tests {
    use candle_core::Device;

    use super::*;

    #[test]
    fn euler_runs_openpis_grid_from_noise_to_data() {
        let noise = Tensor::new(&[[[1.0f32, -2.0]]], &Device::Cpu).expect("tensor");
        // the flow of a straight path ε → a has the constant velocity u = ε − a: ten Euler steps
        // of dt = −1/10 land exactly on a
        let data = Tensor::new(&[[[0.25f32, 0.5]]], &Device::Cpu).expect("tensor");
        let u = (&noise - &data).expect("u");
        let out = euler(&noise, 10, |_, _| Ok(u.clone())).expect("euler");
        let got = out
            .actions
            .flatten_all()
            .and_then(|t| t.to_vec1::<f32>())
            .expect("vec");
        assert!(
            (got[0] - 0.25).abs() < 1e-6 && (got[1] - 0.5).abs() < 1e-6,
            "{got:?}"
        );
        // t = 1 (noise) first, steps of 1/10 accumulated in f32, t = 0 never evaluated
        assert_eq!(out.times.len(), 10);
        assert_eq!(out.times[0], 1.0);
        assert!((out.times[9] - 0.1).abs() < 1e-6, "{:?}", out.times);
        // the velocity at the first step is kept, and the state is updated x ← x + dt·v(x, t)
        let seen = std::cell::RefCell::new(Vec::new());
        let out = euler(&noise, 2, |x, t| {
            seen.borrow_mut()
                .push((x.flatten_all()?.to_vec1::<f32>()?[0], t));
            Ok((x * 2.0)?)
        })
        .expect("euler");
        assert_eq!(*seen.borrow(), vec![(1.0, 1.0), (0.0, 0.5)]);
        let v0 = out.v_t_step0.flatten_all().and_then(|t| t.to_vec1::<f32>());
        assert_eq!(v0.expect("v0"), vec![2.0, -4.0]);
        assert!(euler(&noise, 0, |x, _| Ok(x.clone())).is_err());
    }
}
