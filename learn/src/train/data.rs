//! What the training step eats: batches of observations and chunks with augmentation, the
//! targets of the auxiliary heads, normalisation statistics, and the held-out loss by time.

use candle_core::{Device, Tensor};
use candle_nn::VarBuilder;
use rand::SeedableRng;

use super::*;

/// The flow-matching loss of `model` on every sample of `batcher` at each noise level of
/// `times` (fixed noise from `seed`), without gradients: one mean per time.
pub(super) fn loss_by_time(
    model: &PiModel,
    batcher: &Batcher,
    times: &[f32],
    seed: u64,
) -> anyhow::Result<Vec<f64>> {
    let (h, a) = (batcher.cfg.action_horizon, batcher.cfg.action_dim);
    let n = batcher.ds.len();
    let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(seed);
    let idx: Vec<usize> = (0..n).collect();
    let mut out = Vec::with_capacity(times.len());
    for &t in times {
        let (mut sum, mut count) = (0f64, 0usize);
        for chunk in idx.chunks(64) {
            let (inp, actions, _, _) = batcher.batch(chunk, &[])?;
            let b = chunk.len();
            let noise: Vec<f32> = (0..b * h * a).map(|_| gaussian(&mut rng) as f32).collect();
            let noise = Tensor::from_vec(noise, (b, h, a), &Device::Cpu)?;
            let time = Tensor::from_vec(vec![t; b], b, &Device::Cpu)?;
            let l = model.loss(&inp, &actions, &noise, &time, false)?.mean;
            sum += l.to_scalar::<f32>()? as f64 * b as f64;
            count += b;
        }
        out.push(sum / count.max(1) as f64);
    }
    Ok(out)
}

/// Held-out data for [`loss_by_time`]: `scenes` scenes from [`LOSS_SCENE_BASE`], recorded like
/// the training data.
pub(super) fn held_out_dataset(
    cfg: &Config,
    mcfg: &ModelConfig,
    scenes: usize,
    expert: crate::task::expert::Profile,
) -> anyhow::Result<Dataset> {
    let spec = dataset_spec(cfg, mcfg, scenes, LOSS_SCENE_BASE, 77, 0.2, expert, None)?;
    Ok(Dataset::generate(&spec, |_, _| {}))
}

/// The dataset's action chunks as the model predicts them: on the dims of `delta_mask` relative
/// to the sample's state (openpi's `DeltaActions`; the runtime adds the observed state back),
/// absolute elsewhere. Same layout as `Dataset::actions`.
pub fn model_space_actions(ds: &Dataset, delta_mask: &[bool]) -> Vec<f32> {
    let d = ds.n_dof;
    let stride = ds.horizon * d;
    let mut out = ds.actions.clone();
    for i in 0..ds.len() {
        let s = ds.state_of(i);
        for (j, v) in out[i * stride..(i + 1) * stride].iter_mut().enumerate() {
            if delta_mask.get(j % d).copied().unwrap_or(false) {
                *v -= s[j % d];
            }
        }
    }
    out
}

/// Mean, std and 1 % / 99 % quantiles of each of `dim` columns of row-major `values`.
pub fn column_stats(values: &[f32], dim: usize) -> Stats {
    let mut st = Stats {
        mean: Vec::with_capacity(dim),
        std: Vec::with_capacity(dim),
        q01: Some(Vec::with_capacity(dim)),
        q99: Some(Vec::with_capacity(dim)),
    };
    for j in 0..dim {
        let mut col: Vec<f32> = values.iter().skip(j).step_by(dim).copied().collect();
        let n = col.len().max(1) as f64;
        let mean = col.iter().map(|&v| v as f64).sum::<f64>() / n;
        let var = col.iter().map(|&v| (v as f64 - mean).powi(2)).sum::<f64>() / n;
        col.sort_by(|a, b| a.total_cmp(b));
        let q = |p: f64| col[((p * (col.len() - 1) as f64).round() as usize).min(col.len() - 1)];
        st.mean.push(mean as f32);
        st.std.push(var.sqrt() as f32);
        if let (Some(a), Some(b)) = (st.q01.as_mut(), st.q99.as_mut()) {
            a.push(q(0.01));
            b.push(q(0.99));
        }
    }
    st
}

/// Model-ready training data: everything but the images is precomputed.
pub(super) struct Batcher<'a> {
    pub(super) ds: &'a Dataset,
    pub(super) cfg: ModelConfig,
    pub(super) tok: &'a PromptTokenizer,
    /// Normalised, unpadded state per sample.
    pub(super) norm_state: Vec<f32>,
    pub(super) tokens: Vec<u32>,
    pub(super) token_mask: Vec<bool>,
    pub(super) state: Vec<f32>,
    pub(super) actions: Vec<f32>,
    /// Localisation targets per sample ([`AUX_OUTPUTS`]): red, blue and gripper (x, y) over the
    /// view's half width, so in [-1, 1].
    pub(super) aux: Vec<f32>,
    /// Goal targets per sample ([`GOAL_OUTPUTS`]).
    pub(super) goal: Vec<f32>,
}

/// Outputs of the auxiliary goal head: the prompted target's inverse-kinematics joint angles
/// (over π), its (x, y) (over the view's half width) and its velocity (x, y; view half widths
/// per second: 0 for a target that stays).
pub const GOAL_OUTPUTS: usize = 7;

/// The goal targets of a sample whose scene is `scene` (the targets where they are then),
/// moving at `velocity`, with prompt `color` ([`GOAL_OUTPUTS`] values).
pub(super) fn goal_targets(
    scene: &crate::task::ReachScene,
    velocity: &[[f64; 2]; 2],
    color: TargetColor,
) -> [f32; GOAL_OUTPUTS] {
    let s = chunkrt_tools::scene::VIEW_HALF_WIDTH;
    let t = scene.target(color);
    let v = velocity[color as usize];
    let q = crate::task::inverse_kinematics(t).unwrap_or([0.0; 3]);
    let pi = std::f64::consts::PI;
    [
        q[0] / pi,
        q[1] / pi,
        q[2] / pi,
        t[0] / s,
        t[1] / s,
        v[0] / s,
        v[1] / s,
    ]
    .map(|v| v as f32)
}

/// Outputs of the auxiliary localisation head: (x, y) of the red target, the blue target and
/// the gripper.
pub const AUX_OUTPUTS: usize = 6;

/// The localisation targets of a scene seen at joint positions `q` ([`AUX_OUTPUTS`] values).
pub(super) fn localisation_targets(
    scene: &crate::task::ReachScene,
    q: &[f64],
) -> [f32; AUX_OUTPUTS] {
    let s = chunkrt_tools::scene::VIEW_HALF_WIDTH;
    let e = crate::task::end_effector(q);
    let [r, b] = scene.targets;
    [r[0], r[1], b[0], b[1], e[0], e[1]].map(|v| (v / s) as f32)
}

/// State augmentation of one sample: the gripper state flipped to its other end (the robot's
/// gripper is not always where the expert's was: the policy must not rely on it), and noise
/// on the arm joints' normalised state.
#[derive(Debug, Clone, Copy, Default)]
pub(super) struct Augment {
    pub(super) flip_gripper: bool,
    pub(super) noise: [f32; TASK_DOF],
}

impl<'a> Batcher<'a> {
    /// `actions`: the dataset's chunks in the model's action space ([`model_space_actions`]).
    pub(super) fn new(
        ds: &'a Dataset,
        actions: &[f32],
        cfg: &ModelConfig,
        norm: &NormStats,
        tok: &'a PromptTokenizer,
    ) -> anyhow::Result<Self> {
        let (d, a, h, l) = (
            ds.n_dof,
            cfg.action_dim,
            cfg.action_horizon,
            cfg.max_token_len,
        );
        anyhow::ensure!(
            d <= a && ds.horizon >= h,
            "dataset has {d} joints and horizon {}; the model takes ≤ {a} joints and horizon {h}",
            ds.horizon
        );
        let n = ds.len();
        let mut b = Batcher {
            ds,
            cfg: cfg.clone(),
            tok,
            norm_state: Vec::with_capacity(n * d),
            tokens: Vec::with_capacity(n * l),
            token_mask: Vec::with_capacity(n * l),
            state: Vec::with_capacity(n * a),
            actions: Vec::with_capacity(n * h * a),
            aux: Vec::with_capacity(n * AUX_OUTPUTS),
            goal: Vec::with_capacity(n * GOAL_OUTPUTS),
        };
        for i in 0..n {
            // the targets where they are at the sample's time (they may drift)
            let sc = crate::task::ReachScene {
                targets: ds.targets_of(i),
            };
            let q: Vec<f64> = ds.state_of(i).iter().map(|&v| v as f64).collect();
            if ds.aux.is_empty() {
                b.aux.extend(localisation_targets(&sc, &q));
            } else {
                b.aux
                    .extend_from_slice(&ds.aux[i * AUX_OUTPUTS..(i + 1) * AUX_OUTPUTS]);
            }
            if ds.is_reach() {
                b.goal
                    .extend(goal_targets(&sc, &ds.target_velocity_of(i), ds.color(i)));
            } else {
                // (the goal head is the reach task's: `chunkrt train` turns it off for others)
                b.goal.extend([0.0; GOAL_OUTPUTS]);
            }
            let mut s = ds.state_of(i).to_vec();
            normalize(&mut s, &norm.state, NormMode::Quantile)?;
            b.norm_state.extend_from_slice(&s);
            let bins = discretize_state(&s);
            let (ids, mask) = tok.tokenize(ds.prompt(i), Some(&bins), l)?;
            b.tokens.extend(ids);
            b.token_mask.extend(mask);
            s.resize(a, 0.0);
            b.state.extend(s);
            let stride = ds.horizon * d;
            let acts = &actions[i * stride..(i + 1) * stride];
            for k in 0..h {
                let mut row = acts[k * d..(k + 1) * d].to_vec();
                normalize(&mut row, &norm.actions, NormMode::Quantile)?;
                row.resize(a, 0.0);
                b.actions.extend(row);
            }
        }
        Ok(b)
    }

    /// Appends a recorded RGB frame to `out` as the model's CHW input (resized with padding
    /// when the recording's size is not the model's).
    fn model_image(&self, f: &[u8], out: &mut Vec<f32>) -> anyhow::Result<()> {
        let s = self.cfg.vision.image_size;
        if self.ds.height == s && self.ds.width == s {
            to_model_chw(f, s, s, out);
        } else {
            let r = resize_with_pad(f, self.ds.height, self.ds.width, s, s)?;
            to_model_chw(&r, s, s, out);
        }
        Ok(())
    }

    /// Inputs, normalised actions [B, H, A], localisation targets [B, AUX_OUTPUTS] and goal
    /// targets [B, GOAL_OUTPUTS] of samples `idx`.
    pub(super) fn batch(
        &self,
        idx: &[usize],
        aug: &[Augment],
    ) -> anyhow::Result<(ModelInputs, Tensor, Tensor, Tensor)> {
        let dev = Device::Cpu;
        let c = &self.cfg;
        let (s, l, a, h) = (
            c.vision.image_size,
            c.max_token_len,
            c.action_dim,
            c.action_horizon,
        );
        let b = idx.len();
        let mut img = Vec::with_capacity(b * 3 * s * s);
        // the earlier frames, when the model's second image input is a delayed view of the first
        let history = c.cameras.len() > 1
            && self.ds.history_steps > 0
            && c.delayed_view(&c.cameras[1])
                .is_some_and(|v| v.camera == c.cameras[0]);
        let mut img_prev = Vec::with_capacity(if history { b * 3 * s * s } else { 0 });
        let (mut ids, mut st, mut acts) = (
            Vec::with_capacity(b * l),
            Vec::with_capacity(b * a),
            Vec::with_capacity(b * h * a),
        );
        let mut masks = Vec::with_capacity(b);
        let mut aux = Vec::with_capacity(b * AUX_OUTPUTS);
        let mut goal = Vec::with_capacity(b * GOAL_OUTPUTS);
        let d = self.ds.n_dof;
        for (bi, &i) in idx.iter().enumerate() {
            self.model_image(self.ds.frame(i), &mut img)?;
            if history {
                self.model_image(self.ds.frame_prev(i), &mut img_prev)?;
            }
            match aug.get(bi) {
                Some(g) if g.flip_gripper || g.noise.iter().any(|v| *v != 0.0) => {
                    let mut s = self.norm_state[i * d..(i + 1) * d].to_vec();
                    for (j, v) in s.iter_mut().enumerate() {
                        if j + 1 == d && g.flip_gripper {
                            // normalised gripper ends are -1 (open) and 1 (closed)
                            *v = if *v > 0.0 { -1.0 } else { 1.0 };
                        } else if j + 1 < d {
                            *v += g.noise[j.min(TASK_DOF - 1)];
                        }
                    }
                    let (t, m) =
                        self.tok
                            .tokenize(self.ds.prompt(i), Some(&discretize_state(&s)), l)?;
                    ids.extend(t);
                    masks.push(m);
                    s.resize(a, 0.0);
                    st.extend(s);
                }
                _ => {
                    ids.extend_from_slice(&self.tokens[i * l..(i + 1) * l]);
                    masks.push(self.token_mask[i * l..(i + 1) * l].to_vec());
                    st.extend_from_slice(&self.state[i * a..(i + 1) * a]);
                }
            }
            acts.extend_from_slice(&self.actions[i * h * a..(i + 1) * h * a]);
            aux.extend_from_slice(&self.aux[i * AUX_OUTPUTS..(i + 1) * AUX_OUTPUTS]);
            goal.extend_from_slice(&self.goal[i * GOAL_OUTPUTS..(i + 1) * GOAL_OUTPUTS]);
        }
        let mut images = vec![Tensor::from_vec(img, (b, 3, s, s), &dev)?];
        let mut image_masks = vec![vec![true; b]];
        if history {
            images.push(Tensor::from_vec(img_prev, (b, 3, s, s), &dev)?);
            image_masks.push(vec![true; b]);
        }
        // cameras the task does not have: black and masked, as at inference
        for _ in images.len()..c.cameras.len() {
            images.push(Tensor::full(-1f32, (b, 3, s, s), &dev)?);
            image_masks.push(vec![false; b]);
        }
        Ok((
            ModelInputs {
                images,
                image_masks,
                tokens: Tensor::from_vec(ids, (b, l), &dev)?,
                token_mask: masks,
                state: Tensor::from_vec(st, (b, a), &dev)?,
            },
            Tensor::from_vec(acts, (b, h, a), &dev)?,
            Tensor::from_vec(aux, (b, AUX_OUTPUTS), &dev)?,
            Tensor::from_vec(goal, (b, GOAL_OUTPUTS), &dev)?,
        ))
    }
}

/// The auxiliary heads (trained, never saved):
/// - localisation: one linear map from all image tokens of the first camera (as the language
///   model receives them) to [`AUX_OUTPUTS`] positions;
/// - goal: one linear map from the mean over valid prefix tokens of the language model's hidden
///   states at the input of its last layer to [`GOAL_OUTPUTS`] values.
///
/// Both are trained with an MSE.
pub(super) struct AuxHeads {
    pub(super) loc: Option<candle_nn::Linear>,
    pub(super) goal: Option<candle_nn::Linear>,
    pub(super) tokens: usize,
    /// The layer whose input the goal head reads.
    pub(super) tap: usize,
}

impl AuxHeads {
    pub(super) fn new(cfg: &ModelConfig, args: &TrainArgs, vb: VarBuilder) -> anyhow::Result<Self> {
        let tokens = cfg.vision.num_tokens();
        let w = cfg.paligemma.width;
        let loc = (args.aux_weight > 0.0)
            .then(|| candle_nn::linear(tokens * w, AUX_OUTPUTS, vb.pp("aux")))
            .transpose()?;
        let goal = (args.goal_weight > 0.0)
            .then(|| candle_nn::linear(w, GOAL_OUTPUTS, vb.pp("goal")))
            .transpose()?;
        Ok(AuxHeads {
            loc,
            goal,
            tokens,
            tap: cfg.paligemma.depth.saturating_sub(1),
        })
    }

    /// The tapped layer, when the goal head needs it.
    pub(super) fn tap(&self) -> Option<usize> {
        self.goal.as_ref().map(|_| self.tap)
    }

    /// MSE of the localisation head on the prefix embeddings `embs` [B, P, W] against `target`
    /// [B, AUX_OUTPUTS].
    pub(super) fn loc_loss(
        &self,
        embs: &Tensor,
        target: &Tensor,
    ) -> anyhow::Result<Option<Tensor>> {
        use candle_core::Module;
        let Some(lin) = &self.loc else {
            return Ok(None);
        };
        let img = embs.narrow(1, 0, self.tokens)?.flatten_from(1)?;
        Ok(Some((lin.forward(&img)? - target)?.sqr()?.mean_all()?))
    }

    /// MSE of the goal head on the hidden states `hidden` [B, P, W] (valid tokens `pad` [B][P])
    /// against `target` [B, GOAL_OUTPUTS].
    pub(super) fn goal_loss(
        &self,
        hidden: Option<&Tensor>,
        pad: &[Vec<bool>],
        target: &Tensor,
    ) -> anyhow::Result<Option<Tensor>> {
        use candle_core::Module;
        let (Some(lin), Some(h)) = (&self.goal, hidden) else {
            return Ok(None);
        };
        let (b, p, _) = h.dims3()?;
        let mut m = Vec::with_capacity(b * p);
        for row in pad {
            let n = row.iter().filter(|&&v| v).count().max(1) as f32;
            m.extend(row.iter().map(|&v| if v { 1.0 / n } else { 0.0 }));
        }
        let m = Tensor::from_vec(m, (b, p, 1), h.device())?;
        let pooled = h.broadcast_mul(&m)?.sum(1)?;
        Ok(Some((lin.forward(&pooled)? - target)?.sqr()?.mean_all()?))
    }
}
