//! Real-time chunking (Black, Galliker, Levine 2025): inference-time guidance of the flow-matching
//! sampler towards the actions of the previous chunk that will still be executed while the new
//! chunk is computed ("inpainting" with a soft mask), in our convention. (Training-time RTC,
//! where a model trained for it is given those actions directly, is
//! [`PiModel::denoise_committed`]; both bring the previous chunk into the model's space with
//! [`model_space_actions`].)
//!
//! Convention: t = 1 is noise, t = 0 data, Euler `x <- x + dt * v` with `dt = -1/N`; τ = 1 − t.
//! Per denoising step, with the previous chunk Y [B, H, A] and the weights W [B or 1, H, A]
//! (already zero beyond the robot's DoF and in the model's normalised space):
//!
//! ```text
//! v  = v(x_t, t)                      action expert against the fixed prefix KV cache
//! Â  = x_t − t·v                      clean estimate
//! g  = (∂Â/∂x_t)ᵀ (W ⊙ (Y − Â))       one vector-Jacobian product (candle autograd)
//! r² = (1 − τ)² / (τ² + (1 − τ)²)
//! c  = min(β, (1 − τ) / (τ·r²))       (β where the ratio is unbounded: τ → 0 or τ → 1)
//! v' = v − c·g;   x <- x + dt·v'
//! ```
//!
//! The VJP runs the action expert in its differentiable mode (compositions with a backward), so
//! a guided step costs one differentiable forward and one backward instead of one fast forward.
//! [`Jacobian::Identity`] takes ∂Â/∂x_t ≈ I instead (g = W ⊙ (Y − Â)): one fast forward per step,
//! as unguided sampling, at the price of steering the estimate without the model's sensitivity.

use candle_core::{DType, Device, Tensor, Var};

use super::config::ModelConfig;
use super::model::{euler, ModelInputs, PiModel, PrefixCache, SampleOutput};
use super::preprocess::{normalize, NormMode, Stats};
use crate::error::PolicyError;

/// How the guidance gradient g = (∂Â/∂x_t)ᵀ (W ⊙ (Y − Â)) treats the Jacobian of the clean
/// estimate (`execution.rtc_jacobian`: `identity` or `vjp`).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, Default)]
pub enum Jacobian {
    /// The exact vector-Jacobian product (the paper's): a differentiable forward and a backward
    /// through the action expert per step.
    Vjp,
    /// ∂Â/∂x_t ≈ I, so g = W ⊙ (Y − Â): one fast forward per step, as an unguided step. Exact
    /// where the velocity does not depend on x_t; otherwise the pull on Â is not shaped by the
    /// model's sensitivity (stronger at high noise, where the true Jacobian is small). The
    /// default: on the reach sweep it also switches 10x more smoothly than the VJP, whose pull
    /// is weak where the policy's chunk hardly depends on the noise (BENCHMARKS.md §5).
    #[default]
    Identity,
}

impl Jacobian {
    /// Every value.
    pub const ALL: [Jacobian; 2] = [Jacobian::Identity, Jacobian::Vjp];

    /// `identity` / `vjp`.
    pub fn name(self) -> &'static str {
        match self {
            Jacobian::Vjp => "vjp",
            Jacobian::Identity => "identity",
        }
    }
}

impl std::fmt::Display for Jacobian {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(self.name())
    }
}

impl std::str::FromStr for Jacobian {
    type Err = PolicyError;

    fn from_str(s: &str) -> Result<Self, PolicyError> {
        match s {
            "identity" => Ok(Jacobian::Identity),
            "vjp" => Ok(Jacobian::Vjp),
            _ => Err(PolicyError::Config(format!(
                "rtc jacobian {s:?}: must be one of identity, vjp"
            ))),
        }
    }
}

crate::device::serde_by_name!(Jacobian);

/// Guidance towards the previous chunk (robot units, [H][n_dof] row-major, right-padded by the
/// caller): [`crate::Conditioning::Guided`].
#[derive(Debug, Clone, Copy)]
pub struct Guidance<'a> {
    /// Previous chunk's remaining actions, `[H][n_dof]` row-major in robot units.
    pub prefix: &'a [f64],
    /// Soft-mask weight per action step, length H, each ≥ 0 (typically 1 on the steps executed
    /// during inference, decaying to 0).
    pub weights: &'a [f32],
    /// Guidance clip β (≥ 0; 0 disables guidance).
    pub beta: f32,
    /// The exact VJP or the identity approximation.
    pub jacobian: Jacobian,
}

impl Guidance<'_> {
    /// The model-space target: Y normalised with the action `stats` / `mode` (as the actions
    /// are un-normalised) and zero-padded to the action dim, W masked beyond `n_dof`.
    /// `offsets` (n_dof values, or empty for none) are subtracted first: the observed state on
    /// the model's delta-action dims, so Y is in the model's own (relative) action space.
    pub fn target(
        &self,
        cfg: &ModelConfig,
        n_dof: usize,
        stats: Option<&Stats>,
        mode: NormMode,
        offsets: &[f64],
        dev: &Device,
    ) -> Result<GuidanceTarget, PolicyError> {
        let (h, a) = (cfg.action_horizon, cfg.action_dim);
        if n_dof == 0 || n_dof > a {
            return Err(PolicyError::Input(format!(
                "guidance: {n_dof} DoF; the model takes 1..={a}"
            )));
        }
        if self.prefix.len() != h * n_dof || self.weights.len() != h {
            return Err(PolicyError::Input(format!(
                "guidance: prefix of {} values and {} weights; expected {h}x{n_dof} and {h}",
                self.prefix.len(),
                self.weights.len()
            )));
        }
        if self.prefix.iter().any(|x| !x.is_finite()) {
            return Err(PolicyError::Input(
                "guidance: non-finite prefix value".into(),
            ));
        }
        if self.weights.iter().any(|w| !w.is_finite() || *w < 0.0) {
            return Err(PolicyError::Input(
                "guidance: weights must be finite and >= 0".into(),
            ));
        }
        if !self.beta.is_finite() || self.beta < 0.0 {
            return Err(PolicyError::Input(format!(
                "guidance: beta {} must be finite and >= 0",
                self.beta
            )));
        }
        if !offsets.is_empty() && offsets.len() != n_dof {
            return Err(PolicyError::Input(format!(
                "guidance: {} offsets for {n_dof} DoF",
                offsets.len()
            )));
        }
        Ok(GuidanceTarget {
            y: model_space_actions(self.prefix, n_dof, cfg, stats, mode, offsets, dev)?,
            w: weight_mask(self.weights, n_dof, a, dev)?,
            beta: self.beta,
            jacobian: self.jacobian,
        })
    }
}

/// Action rows in robot units (`[rows][n_dof]` row-major, at most H rows) as the model sees
/// them: `offsets` (the observed state on the delta-action dims, or empty) subtracted,
/// normalised with the action `stats` / `mode`, zero-padded to the action dim and to H rows.
/// Returns [1, H, A].
pub fn model_space_actions(
    rows: &[f64],
    n_dof: usize,
    cfg: &ModelConfig,
    stats: Option<&Stats>,
    mode: NormMode,
    offsets: &[f64],
    dev: &Device,
) -> Result<Tensor, PolicyError> {
    let (h, a) = (cfg.action_horizon, cfg.action_dim);
    if n_dof == 0 || n_dof > a || !rows.len().is_multiple_of(n_dof) || rows.len() > h * n_dof {
        return Err(PolicyError::Input(format!(
            "{} action values for {n_dof} DoF: at most {h} whole rows of 1..={a} DoF",
            rows.len()
        )));
    }
    if rows.iter().any(|x| !x.is_finite()) {
        return Err(PolicyError::Input("non-finite action value".into()));
    }
    let mut y = Vec::with_capacity(h * a);
    let mut row = Vec::with_capacity(a);
    for r in rows.chunks_exact(n_dof) {
        row.clear();
        row.extend(
            r.iter()
                .enumerate()
                .map(|(d, &x)| (x - offsets.get(d).copied().unwrap_or(0.0)) as f32),
        );
        if let Some(s) = stats {
            normalize(&mut row, s, mode)?;
        }
        row.resize(a, 0.0);
        y.extend_from_slice(&row);
    }
    y.resize(h * a, 0.0);
    Ok(Tensor::from_vec(y, (1, h, a), dev)?)
}

/// Guidance target in the model's space: what [`sample_guided`] pulls the chunk towards.
#[derive(Debug, Clone)]
pub struct GuidanceTarget {
    /// Previous chunk Y [B, H, A], normalised and zero-padded beyond the robot's DoF.
    pub y: Tensor,
    /// Weights W broadcastable to [B, H, A] (e.g. [1, H, A] from [`weight_mask`]); zero on the
    /// action dims that carry no real data.
    pub w: Tensor,
    /// Guidance clip β (≥ 0); 0 disables guidance.
    pub beta: f32,
    /// The exact VJP or the identity approximation.
    pub jacobian: Jacobian,
}

/// Result of one guided velocity evaluation ([`guided_velocity`]).
#[derive(Debug, Clone)]
pub struct GuidedVelocity {
    /// Guided velocity v' [B, H, A].
    pub v_guided: Tensor,
    /// Model velocity v [B, H, A] (differentiable mode).
    pub v: Tensor,
    /// Clean estimate Â = x_t − t·v [B, H, A].
    pub a_hat: Tensor,
    /// VJP g = (∂Â/∂x_t)ᵀ (W ⊙ (Y − Â)) [B, H, A].
    pub g: Tensor,
    /// Guidance scale c = min(β, (1 − τ)/(τ·r²)).
    pub scale: f32,
}

/// Soft-mask weights `[H]` over the first `n_dof` of `action_dim` action dims: [1, H, A] with
/// `w[h]` on dims `< n_dof` and 0 beyond (the padded dims carry no data and are not guided).
pub fn weight_mask(
    weights: &[f32],
    n_dof: usize,
    action_dim: usize,
    dev: &Device,
) -> Result<Tensor, PolicyError> {
    if n_dof == 0 || n_dof > action_dim {
        return Err(PolicyError::Input(format!(
            "{n_dof} DoF; the model takes 1..={action_dim}"
        )));
    }
    let mut m = Vec::with_capacity(weights.len() * action_dim);
    for &w in weights {
        m.extend(std::iter::repeat_n(w, n_dof));
        m.extend(std::iter::repeat_n(0.0f32, action_dim - n_dof));
    }
    Ok(Tensor::from_vec(m, (1, weights.len(), action_dim), dev)?)
}

/// Guidance scale c = min(β, (1 − τ)/(τ·r²)) with r² = (1 − τ)² / (τ² + (1 − τ)²) and τ = 1 − t.
/// Where the ratio is unbounded or undefined (τ → 0 at the first step, τ → 1) it is β.
pub fn guidance_scale(t: f32, beta: f32) -> f32 {
    let tau = 1.0 - t as f64;
    let one_m = 1.0 - tau;
    let r2_den = tau * tau + one_m * one_m;
    // (1 − τ)/(τ·r²) = (τ² + (1 − τ)²) / (τ·(1 − τ))
    let den = tau * one_m;
    if den <= 1e-12 || r2_den <= 0.0 {
        return beta;
    }
    let ratio = r2_den / den;
    if ratio.is_finite() {
        (beta as f64).min(ratio) as f32
    } else {
        beta
    }
}

/// The clean estimate Â = x_t − t·v and its VJP with a fixed `cotangent` [B, H, A]:
/// returns (Â, v, (∂Â/∂x_t)ᵀ·cotangent). `t` [B] host time values.
pub fn clean_estimate_vjp(
    model: &PiModel,
    cache: &PrefixCache,
    x_t: &Tensor,
    t: &[f32],
    cotangent: &Tensor,
) -> Result<(Tensor, Tensor, Tensor), PolicyError> {
    let (a_hat, v, x) = clean_estimate(model, cache, x_t, t)?;
    let g = vjp(&a_hat, &x, cotangent)?;
    Ok((a_hat.detach(), v.detach(), g))
}

/// Â = x − t·v in differentiable mode, with x a fresh `Var` copy of `x_t`.
fn clean_estimate(
    model: &PiModel,
    cache: &PrefixCache,
    x_t: &Tensor,
    t: &[f32],
) -> Result<(Tensor, Tensor, Var), PolicyError> {
    let b = x_t.dim(0)?;
    let x = Var::from_tensor(x_t)?;
    let v = model.velocity_at(cache, x.as_tensor(), t, true)?;
    // t3 [B, 1, 1]
    let t3 = Tensor::from_slice(t, (b, 1, 1), x_t.device())?;
    let a_hat = (x.as_tensor() - v.broadcast_mul(&t3)?)?;
    Ok((a_hat, v, x))
}

/// (∂a_hat/∂x)ᵀ·cotangent through candle autograd: backward of `sum(a_hat ⊙ stopgrad(cot))`.
fn vjp(a_hat: &Tensor, x: &Var, cotangent: &Tensor) -> Result<Tensor, PolicyError> {
    let obj = (a_hat * cotangent.detach())?.sum_all()?;
    let grads = obj.backward()?;
    match grads.get(x.as_tensor()) {
        Some(g) => Ok(g.detach()),
        // x_t reaches the objective through x − t·v; no gradient only if nothing depended on it
        None => Ok(x.as_tensor().zeros_like()?),
    }
}

/// W ⊙ (Y − Â): the VJP's cotangent, and the gradient itself with the identity Jacobian.
fn weighted_error(target: &GuidanceTarget, a_hat: &Tensor) -> candle_core::Result<Tensor> {
    (&target.y - a_hat)?.broadcast_mul(&target.w)
}

/// One guided velocity evaluation at time `t` (the same for the whole batch).
pub fn guided_velocity(
    model: &PiModel,
    cache: &PrefixCache,
    x_t: &Tensor,
    t: f32,
    target: &GuidanceTarget,
) -> Result<GuidedVelocity, PolicyError> {
    let b = x_t.dim(0)?;
    let tv = vec![t; b];
    let (a_hat, v, g) = match target.jacobian {
        Jacobian::Vjp => {
            let (a_hat, v, x) = clean_estimate(model, cache, x_t, &tv)?;
            // the cotangent is a constant for the VJP
            let g = vjp(&a_hat, &x, &weighted_error(target, &a_hat.detach())?)?;
            (a_hat.detach(), v.detach(), g)
        }
        Jacobian::Identity => {
            let v = model.velocity_at(cache, x_t, &tv, false)?;
            // one time for the batch: a scalar on the device, nothing uploaded per step
            let a_hat = (x_t - (&v * t as f64)?)?;
            let g = weighted_error(target, &a_hat)?;
            (a_hat, v, g)
        }
    };
    let scale = guidance_scale(t, target.beta);
    let v_guided = (&v - (&g * scale as f64)?)?;
    Ok(GuidedVelocity {
        v_guided,
        v,
        a_hat,
        g,
        scale,
    })
}

/// Checks a guidance target against the sampler's shapes; `Ok(false)` when it guides nothing
/// (β = 0 or all weights zero) so the plain sampler can run.
pub(crate) fn check_target(
    model: &PiModel,
    b: usize,
    target: &GuidanceTarget,
) -> Result<bool, PolicyError> {
    let want = [b, model.cfg.action_horizon, model.cfg.action_dim];
    if target.y.dims() != want {
        return Err(PolicyError::Input(format!(
            "guidance Y: shape {:?}, expected {want:?}",
            target.y.dims()
        )));
    }
    let wd = target.w.dims();
    let ok = wd.len() == 3 && (wd[0] == 1 || wd[0] == b) && wd[1] == want[1] && wd[2] == want[2];
    if !ok {
        return Err(PolicyError::Input(format!(
            "guidance W: shape {wd:?}, expected [1 or {b}, {}, {}]",
            want[1], want[2]
        )));
    }
    if !target.beta.is_finite() || target.beta < 0.0 {
        return Err(PolicyError::Input(format!(
            "guidance beta {} must be finite and >= 0",
            target.beta
        )));
    }
    let w = target
        .w
        .to_dtype(DType::F32)?
        .flatten_all()?
        .to_vec1::<f32>()?;
    let y = target
        .y
        .to_dtype(DType::F32)?
        .flatten_all()?
        .to_vec1::<f32>()?;
    if w.iter().chain(y.iter()).any(|x| !x.is_finite()) {
        return Err(PolicyError::Input(
            "non-finite guidance prefix or weights".into(),
        ));
    }
    if w.iter().any(|&x| x < 0.0) {
        return Err(PolicyError::Input("negative guidance weight".into()));
    }
    Ok(target.beta > 0.0 && w.iter().any(|&x| x != 0.0))
}

/// The RTC-guided flow-matching sampler: like [`PiModel::sample`] with a prefix cache (the prefix
/// runs once into `cache`, reusing its buffers), with each step's velocity replaced by the guided
/// velocity towards `target`. With β = 0 or all-zero weights it is exactly [`PiModel::sample`].
/// `noise` [B, H, A]; returns x_0 [B, H, A] (`v_t_step0` is the guided first velocity).
pub fn sample_guided(
    model: &PiModel,
    inputs: &ModelInputs,
    noise: &Tensor,
    steps: usize,
    cache: &mut Option<PrefixCache>,
    target: &GuidanceTarget,
) -> Result<SampleOutput, PolicyError> {
    let b = inputs.batch();
    if !check_target(model, b, target)? {
        return model.sample(inputs, noise, steps, Some(cache));
    }
    let want = [b, model.cfg.action_horizon, model.cfg.action_dim];
    if noise.dims() != want {
        return Err(PolicyError::Input(format!(
            "noise: shape {:?}, expected {want:?}",
            noise.dims()
        )));
    }
    let y = target.y.to_dtype(DType::F32)?;
    let w = target.w.to_dtype(DType::F32)?;
    let target = GuidanceTarget {
        y,
        w,
        beta: target.beta,
        jacobian: target.jacobian,
    };
    model.fill_cache(inputs, cache, false)?;
    let c = cache.as_ref().expect("fill_cache stores the cache");
    denoise_guided(model, c, noise, steps, &target)
}

/// The guided denoising loop against a filled prefix cache: the same integration as
/// [`PiModel::denoise`] with the guided velocity. `target` checked ([`check_target`]), its Y and
/// W f32 on the model's device. With the identity Jacobian every step stays on the device
/// (no host round trip), so a GPU captures the loop as a graph ([`crate::graph`]).
pub fn denoise_guided(
    model: &PiModel,
    cache: &PrefixCache,
    noise: &Tensor,
    steps: usize,
    target: &GuidanceTarget,
) -> Result<SampleOutput, PolicyError> {
    euler(noise, steps, |x, t| {
        Ok(guided_velocity(model, cache, x, t, target)?.v_guided)
    })
}
