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
    pub fn velocity_uncached(
        &self,
        inp: &ModelInputs,
        prefix_embs: &Tensor,
        x_t: &Tensor,
        t: &[f32],
        diff: bool,
    ) -> Result<Tensor, PolicyError> {
        let (_, so) = self.joint_forward(inp, prefix_embs, x_t, t, diff)?;
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
