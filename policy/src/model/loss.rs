//! The flow-matching training loss (openpi `PI0Pytorch.forward`): noisy actions at random
//! times, the joint forward without a cache, `(u − v)²`; with taps for auxiliary losses.
//! Inference never calls into this module.

use candle_core::{DType, Module, Tensor};

use super::*;

/// Result of [`PiModel::loss`].
#[derive(Debug, Clone)]
pub struct LossOutput {
    /// `(u - v)^2` [B, H, A].
    pub per_element: Tensor,
    /// Mean of `per_element` (scalar).
    pub mean: Tensor,
    /// Model velocity [B, H, A].
    pub v_t: Tensor,
}

impl PiModel {
    /// Flow-matching training loss: `x_t = t*noise + (1-t)*actions`, `u = noise - actions`,
    /// `(u - v(x_t, t))^2` per element (joint forward, no cache). `time` [B] f32.
    /// With `diff` every op has a backward (train with a `VarMap`-backed model).
    pub fn loss(
        &self,
        inp: &ModelInputs,
        actions: &Tensor,
        noise: &Tensor,
        time: &Tensor,
        diff: bool,
    ) -> Result<LossOutput, PolicyError> {
        let embs = self.embed_prefix_inner(inp, false, diff)?;
        Ok(self
            .loss_tap(inp, &embs, actions, noise, time, diff, None)?
            .0)
    }

    /// [`Self::loss`] on prefix embeddings already computed ([`Self::embed_prefix_with`]), also
    /// returning the prefix hidden states at the input of layer
    /// `tap` ([`Self::joint_forward_tap`]).
    #[allow(clippy::too_many_arguments)]
    pub fn loss_tap(
        &self,
        inp: &ModelInputs,
        embs: &Tensor,
        actions: &Tensor,
        noise: &Tensor,
        time: &Tensor,
        diff: bool,
        tap: Option<usize>,
    ) -> Result<(LossOutput, Option<Tensor>), PolicyError> {
        let (tv, x_t, u) = noisy_actions(actions, noise, time, None)?;
        let (_, so, tapped) = self.joint_forward_tap(inp, embs, &x_t, &tv, diff, tap)?;
        Ok((self.flow_loss(&so, &u)?, tapped))
    }

    /// The flow-matching loss from the action expert's output `so` [B, S, w] (its last H tokens
    /// are the actions') and the target velocity `u` = ε − a [B, H, A].
    fn flow_loss(&self, so: &Tensor, u: &Tensor) -> Result<LossOutput, PolicyError> {
        let s = so.dim(1)?;
        let h = self.cfg.action_horizon;
        let v_t = self
            .action_out_proj
            .forward(&so.narrow(1, s - h, h)?.to_dtype(DType::F32)?)?;
        let per_element = (u - &v_t)?.sqr()?;
        let mean = per_element.mean_all()?;
        Ok(LossOutput {
            per_element,
            mean,
            v_t,
        })
    }

    /// The flow-matching loss with `k` noise / time samples per observation that share one
    /// prefix pass: the prefix never attends to the suffix, so the language model runs once over
    /// the B prefixes (keeping each layer's keys and values), and the action expert runs over
    /// the B·k suffixes against those keys and values. `actions` [B, H, A]; `noise` [B·k, H, A]
    /// and `time` [B·k] (sample j of observation b at row b·k + j). Equal to [`Self::loss_tap`]
    /// on the observations repeated k times. Also returns the prefix hidden states at the
    /// input of layer `tap`.
    ///
    /// Training-time real-time chunking: with `committed` [B·k], the first `committed[r]`
    /// actions of sample r are given clean (flow time 0, `x = a`), as the sampler gives the
    /// actions the robot executes meanwhile ([`Self::denoise_committed`]), and the loss is the
    /// mean over the other actions only.
    #[allow(clippy::too_many_arguments)]
    pub fn loss_multi(
        &self,
        inp: &ModelInputs,
        embs: &Tensor,
        actions: &Tensor,
        noise: &Tensor,
        time: &Tensor,
        committed: Option<&[usize]>,
        k: usize,
        diff: bool,
        tap: Option<usize>,
    ) -> Result<(LossOutput, Option<Tensor>), PolicyError> {
        let b = self.check_inputs(inp)?;
        let k = k.max(1);
        let bk = b * k;
        if noise.dim(0)? != bk || time.dim(0)? != bk || actions.dim(0)? != b {
            return Err(PolicyError::Input(format!(
                "loss_multi: {b} observations x {k} samples need noise / time rows {bk}, got {} / {}",
                noise.dim(0)?,
                time.dim(0)?
            )));
        }
        // row b·k + j of every per-sample tensor belongs to observation b
        let rep_idx: Vec<u32> = (0..bk).map(|r| (r / k) as u32).collect();
        let rep_idx = Tensor::new(rep_idx.as_slice(), &self.device)?;
        let rep = |x: &Tensor| x.index_select(&rep_idx, 0);
        let h = self.cfg.action_horizon;
        if let Some(c) = committed {
            if c.len() != bk || c.iter().any(|&n| n >= h) {
                return Err(PolicyError::Input(format!(
                    "loss_multi: {} committed prefix lengths for {bk} samples, each below H = {h}",
                    c.len()
                )));
            }
        }
        let committed = committed.filter(|c| c.iter().any(|&n| n > 0));
        // 1 on the actions to generate, 0 on the committed ones [B·k, H, 1]
        let free = committed
            .map(|c| free_mask(c, h, &self.device))
            .transpose()?;
        let (tv, x_t, u) = noisy_actions(&rep(actions)?, noise, time, free.as_ref())?;

        // prefix: the VLM expert alone, keeping each layer's K/V
        let layout = self.prefix_layout(inp);
        let p = self.cfg.prefix_len();
        let d = &self.cfg.paligemma;
        let prope = self.rope(&layout.pos)?;
        let pbias = self.prefix_bias(&layout)?;
        let mut prefix = [Stream {
            x: embs.clone(),
            expert: &self.vlm,
            cond: None,
            rope: &prope,
            pending: None,
        }];
        let mut kvs = Vec::with_capacity(d.depth);
        let mut tapped = None;
        for li in 0..d.depth {
            if tap == Some(li) {
                tapped = Some(prefix[0].x.clone());
            }
            kvs.push(joint_layer(
                li,
                &mut prefix,
                &pbias,
                KvMode::Own { store: None },
                diff,
            )?);
        }

        // suffix: B·k rows against the repeated prefix K/V
        let state = rep(&inp.state)?;
        let times = FlowTimes { t: &tv, committed };
        let (suffix, cond) = self.embed_suffix(&state, &x_t, times, true, diff)?;
        let s = suffix.dim(1)?;
        let ar_s = self.suffix_ar();
        let mut vis = Vec::with_capacity(bk * s * (p + s));
        let mut spos = Vec::with_capacity(bk);
        for r in 0..bk {
            let bi = r / k;
            let mut pad = layout.pad[bi].clone();
            pad.extend(std::iter::repeat_n(true, s));
            let mut ar = vec![false; p];
            ar.extend_from_slice(&ar_s);
            let m = att_2d_mask(&pad, &ar);
            for qi in p..p + s {
                vis.extend_from_slice(&m[qi * (p + s)..(qi + 1) * (p + s)]);
            }
            let n = layout.n_valid[bi] as i64;
            spos.push((0..s as i64).map(|i| n + i).collect::<Vec<_>>());
        }
        let sbias = bias_tensor(vis, (bk, 1, s, p + s), &self.device)?;
        let srope = self.rope(&spos)?;
        let mut st = [Stream {
            x: suffix,
            expert: &self.expert,
            cond: cond.as_ref(),
            rope: &srope,
            pending: None,
        }];
        for (li, (kp, vp)) in kvs.iter().enumerate() {
            let (mut kr, mut vr) = if k == 1 {
                (kp.clone(), vp.clone())
            } else {
                (rep(kp)?, rep(vp)?)
            };
            if !diff {
                // the fast path writes the suffix K/V into the buffer after the prefix
                let pad = |x: &Tensor| -> candle_core::Result<Tensor> {
                    let (n, h, _, hd) = x.dims4()?;
                    let z = Tensor::zeros((n, h, s, hd), DType::F32, &self.device)?;
                    Tensor::cat(&[x, &z], 2)
                };
                kr = pad(&kr)?;
                vr = pad(&vr)?;
            }
            joint_layer(
                li,
                &mut st,
                &sbias,
                KvMode::Cached {
                    k: &kr,
                    v: &vr,
                    offset: p,
                    packed: None,
                },
                diff,
            )?;
        }
        let so = self.expert.norm.forward(&st[0].x, cond.as_ref(), diff)?.0;
        let mut out = self.flow_loss(&so, &u)?;
        if let Some(free) = &free {
            // the committed actions are inputs, not predictions: the mean over the others
            out.per_element = out.per_element.broadcast_mul(free)?;
            let n = free.sum_all()?.to_scalar::<f32>()? as f64 * self.cfg.action_dim as f64;
            out.mean = (out.per_element.sum_all()? / n.max(1.0))?;
        }
        Ok((out, tapped))
    }
}

/// Flow matching's interpolation: the times `t` as a vector, `x_t = t·ε + (1 − t)·a` and the
/// target velocity `u = ε − a`, for `actions` a and `noise` ε [B, H, A] and `time` [B]; with
/// `free` [B, H, 1] the time is `t·free` per action (0, clean, where `free` is 0).
fn noisy_actions(
    actions: &Tensor,
    noise: &Tensor,
    time: &Tensor,
    free: Option<&Tensor>,
) -> Result<(Vec<f32>, Tensor, Tensor), PolicyError> {
    let time = time.to_dtype(DType::F32)?;
    let tv = time.to_vec1::<f32>()?;
    let t3 = time.reshape((tv.len(), 1, 1))?;
    let t3 = match free {
        Some(f) => t3.broadcast_mul(f)?,
        None => t3,
    };
    let x_t = (noise.broadcast_mul(&t3)? + actions.broadcast_mul(&(t3.neg()? + 1.0)?)?)?;
    let u = (noise - actions)?;
    Ok((tv, x_t, u))
}
