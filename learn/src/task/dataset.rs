//! Expert demonstrations of the reach task, recorded at the policy rate as chunks.
//!
//! Every scene (two targets, a random start pose) gives two episodes, one per prompt, so the
//! data shows the same picture with both instructions. At each policy step `k` the recorder
//! stores what the robot would send the policy (the rendered camera frame, the joint positions,
//! the prompt) and the expert's next `H` positions as the action chunk (action 0 is the
//! position at the observed instant, as on the controller's chunk timeline). A share of the
//! episodes is knocked off the expert's path once (joint noise, then a new plan from there), so
//! the data also shows how to recover.
//!
//! File format (`dataset.safetensors`, documented in `docs/dataset.md`): N samples, E episodes,
//! image H×W, horizon Hz, D joints.
//! - `image` u8 [N, H, W, 3] (RGB rows), `state` f32 [N, D], `actions` f32 [N, Hz, D],
//!   `episode` u32 [N] (index into the episode tensors);
//! - `episode_scene_seed` u64 [E], `episode_color` u8 [E] (0 red, 1 blue);
//! - metadata: `format` = `chunkrt.reach_dataset.v1`, `action_rate_hz`, `camera`, `prompts`
//!   (JSON list indexed by colour).
//! - `targets` f32 [N, 4]: where the red and the blue target are at the sample's time (x, y
//!   each, m), and `target_velocity` f32 [N, 4] their velocities (m/s; 0 unless they drift).
//!   Files without them (before 96eef33) had static targets only: they are derived from the
//!   scene seeds.
//! - with a frame history (`history_steps` > 0 in the metadata): `image_prev` u8 [N, H, W, 3],
//!   the frame the camera took `history_steps` policy steps before each sample's (before the
//!   episode: the robot at its start pose, the targets where they were then).

use std::collections::HashMap;
use std::path::Path;

use rand::{Rng, SeedableRng};

use super::expert::Reach;
use super::{ReachScene, TargetColor, ARM_JOINTS, TASK_DOF};

/// Points the localisation head places in the image (x, y each): the reach task's two targets
/// and the gripper; the SO-101's block, goal and jaw.
pub const AUX_POINTS: usize = 3;

/// Format tag in the file's metadata.
pub const FORMAT: &str = "chunkrt.reach_dataset.v1";
/// Scene seeds of the training data start here; held-out scenes (validation, evaluation, the
/// demo) use seeds below it.
pub const TRAIN_SEED_BASE: u64 = 1 << 32;

/// What to record.
#[derive(Debug, Clone, PartialEq)]
pub struct DatasetSpec {
    /// Scenes (two episodes each): seeds `scene_base..scene_base + scenes`.
    pub scenes: usize,
    /// First scene seed: [`TRAIN_SEED_BASE`] for training data; below it for held-out data.
    pub scene_base: u64,
    /// Seed of the start poses and perturbations.
    pub seed: u64,
    /// Actions per chunk.
    pub horizon: usize,
    /// Policy rate (Hz).
    pub action_rate_hz: f64,
    /// Camera name and frame size.
    pub camera: String,
    pub width: usize,
    pub height: usize,
    /// Steps recorded after arrival (the robot holding on the target).
    pub hold_steps: usize,
    /// Share of episodes perturbed once.
    pub perturb_share: f64,
    /// Joint noise of a perturbation (rad, standard deviation).
    pub perturb_std: f64,
    /// The robot's home pose (some episodes start there, like the demo).
    pub home: [f64; TASK_DOF],
    /// Share of an episode's policy steps recorded (the first and last always are). Below 1,
    /// more scenes fit in the same number of samples: the policy sees more target layouts.
    pub keep_share: f64,
    /// The expert's speed profile.
    pub profile: super::expert::Profile,
    /// Moving-target episodes (`None`: every target stays where the scene puts it).
    pub drift: Option<DriftMix>,
    /// Also record the frame this many policy steps before each sample's (0: none).
    pub history_steps: usize,
}

/// A share of the episodes in which the targets swing about the robot's base (the drifting
/// variant of [`super::sim`]), each with its own amplitude, frequency and phase. The tracking
/// expert ([`super::expert::track`]) labels them: every chunk catches up with the prompted
/// target and moves with it, while the recorded states come from a pursuit that trails the
/// target by a random share of its lag (feed-forward drawn in [0, 1) per episode) — so the data
/// shows states behind a moving target, which reveal where it is going, labelled with the
/// motion that keeps up with it.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct DriftMix {
    /// Share of the episodes whose targets swing.
    pub share: f64,
    /// Largest swing amplitude (rad; drawn uniformly from a third of it).
    pub max_amplitude_rad: f64,
    /// Highest swing frequency (Hz; drawn uniformly from a third of it).
    pub max_frequency_hz: f64,
    /// Recorded after the end effector first got within half the reach tolerance (s).
    pub follow_s: f64,
    /// Longest episode (s).
    pub max_seconds: f64,
}

impl DriftMix {
    /// What `chunkrt train --drift-share` records: swings up to 0.35 rad at up to 0.3 Hz (the
    /// eval's default drift, 0.3 rad at 0.25 Hz, lies inside), 1 s of following, 8 s at most.
    pub fn with_share(share: f64) -> Self {
        DriftMix {
            share,
            max_amplitude_rad: 0.35,
            max_frequency_hz: 0.3,
            follow_s: 1.0,
            max_seconds: 8.0,
        }
    }
}

/// Recorded samples (see the module documentation for the layout).
#[derive(Debug, Clone, Default, PartialEq)]
pub struct Dataset {
    pub width: usize,
    pub height: usize,
    pub horizon: usize,
    pub n_dof: usize,
    pub action_rate_hz: f64,
    pub camera: String,
    pub image: Vec<u8>,
    pub state: Vec<f32>,
    pub actions: Vec<f32>,
    pub episode: Vec<u32>,
    pub episode_scene_seed: Vec<u64>,
    pub episode_color: Vec<u8>,
    /// Per sample, the targets where they are at the sample's time (red x, y, blue x, y; m).
    pub targets: Vec<f32>,
    /// Per sample, the targets' velocities (same layout; m/s).
    pub target_velocity: Vec<f32>,
    /// The expert's speed profile the chunks follow (metadata `expert`; files without it, written
    /// before a925468, were recorded with the minimum-jerk expert).
    pub expert: super::expert::Profile,
    /// Share of the episodes recorded with drifting targets (metadata `drift_share`; 0 without).
    pub drift_share: f64,
    /// Policy steps between a sample's frame and its `image_prev` (metadata `history_steps`; 0:
    /// no earlier frames recorded).
    pub history_steps: usize,
    /// The earlier frames (same layout as `image`; empty without a history).
    pub image_prev: Vec<u8>,
    /// The task the episodes are of (metadata `task`; files without it are the reach task's):
    /// [`REACH_TASK`], or `so101` for the SO-101 pick-and-place recorded by
    /// `tools/python/so101_sim.py record`.
    pub task: String,
    /// The prompts, indexed by `episode_color` (metadata `prompts`).
    pub prompts: Vec<String>,
    /// Per sample, the localisation head's targets recorded with it (tensor `aux`, `[n, 6]`:
    /// three points in the image over its half width); empty: computed from the reach scene.
    pub aux: Vec<f32>,
}

/// The reach task's name in a dataset's metadata.
pub const REACH_TASK: &str = "reach";

/// A standard normal sample (Box-Muller).
pub fn gaussian(rng: &mut impl Rng) -> f64 {
    let u1: f64 = rng.gen_range(f64::MIN_POSITIVE..1.0);
    let u2: f64 = rng.gen();
    (-2.0 * u1.ln()).sqrt() * (2.0 * std::f64::consts::PI * u2).cos()
}

/// A start pose: random over the workspace, or the home pose (one in five).
pub fn random_start(rng: &mut impl Rng, home: &[f64; TASK_DOF]) -> [f64; TASK_DOF] {
    if rng.gen_bool(0.2) {
        return *home;
    }
    [
        rng.gen_range(-2.2..2.2),
        rng.gen_range(0.2..2.3),
        rng.gen_range(-1.8..1.8),
        if rng.gen_bool(0.5) { 0.0 } else { 1.0 },
    ]
}

impl Dataset {
    /// Samples.
    pub fn len(&self) -> usize {
        self.episode.len()
    }

    /// No samples.
    pub fn is_empty(&self) -> bool {
        self.episode.is_empty()
    }

    /// Episodes.
    pub fn episodes(&self) -> usize {
        self.episode_color.len()
    }

    /// Colour of sample `i`'s target.
    pub fn color(&self, i: usize) -> TargetColor {
        TargetColor::ALL[self.episode_color[self.episode[i] as usize] as usize % 2]
    }

    /// The prompt of sample `i`'s episode.
    pub fn prompt(&self, i: usize) -> &str {
        let c = self.episode_color[self.episode[i] as usize] as usize;
        match self.prompts.get(c) {
            Some(p) => p,
            None => self.color(i).prompt(),
        }
    }

    /// The reach task's episodes (not another task's).
    pub fn is_reach(&self) -> bool {
        self.task == REACH_TASK
    }

    /// RGB frame of sample `i`.
    pub fn frame(&self, i: usize) -> &[u8] {
        let n = self.width * self.height * 3;
        &self.image[i * n..(i + 1) * n]
    }

    /// The earlier frame of sample `i` (RGB rows; [`Self::history_steps`] > 0).
    pub fn frame_prev(&self, i: usize) -> &[u8] {
        let n = self.width * self.height * 3;
        &self.image_prev[i * n..(i + 1) * n]
    }

    /// The targets of sample `i` where they are then: [red, blue] (x, y).
    pub fn targets_of(&self, i: usize) -> [[f64; 2]; 2] {
        let t = &self.targets[4 * i..4 * i + 4];
        [[t[0] as f64, t[1] as f64], [t[2] as f64, t[3] as f64]]
    }

    /// The targets' velocities at sample `i`: [red, blue] (x, y; m/s).
    pub fn target_velocity_of(&self, i: usize) -> [[f64; 2]; 2] {
        let t = &self.target_velocity[4 * i..4 * i + 4];
        [[t[0] as f64, t[1] as f64], [t[2] as f64, t[3] as f64]]
    }

    /// Joint positions of sample `i`.
    pub fn state_of(&self, i: usize) -> &[f32] {
        &self.state[i * self.n_dof..(i + 1) * self.n_dof]
    }

    /// Action chunk of sample `i`, row-major [horizon][n_dof].
    pub fn actions_of(&self, i: usize) -> &[f32] {
        let n = self.horizon * self.n_dof;
        &self.actions[i * n..(i + 1) * n]
    }

    /// Records the expert. `progress(done, total)` is called after each scene.
    pub fn generate(spec: &DatasetSpec, mut progress: impl FnMut(usize, usize)) -> Self {
        let mut ds = Dataset {
            width: spec.width,
            height: spec.height,
            horizon: spec.horizon,
            n_dof: TASK_DOF,
            action_rate_hz: spec.action_rate_hz,
            camera: spec.camera.clone(),
            expert: spec.profile,
            drift_share: spec.drift.map_or(0.0, |m| m.share),
            history_steps: spec.history_steps,
            task: REACH_TASK.to_string(),
            prompts: TargetColor::ALL
                .iter()
                .map(|c| c.prompt().to_string())
                .collect(),
            ..Default::default()
        };
        let dt = 1.0 / spec.action_rate_hz;
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(spec.seed);
        for si in 0..spec.scenes {
            let seed = spec.scene_base + si as u64;
            let scene = ReachScene::from_seed(seed);
            let q0 = random_start(&mut rng, &spec.home);
            for (ci, color) in TargetColor::ALL.iter().enumerate() {
                // (no draw without a drift mix: the static datasets stay as they were)
                if let Some(mix) = spec.drift.filter(|m| rng.gen_bool(m.share.clamp(0.0, 1.0))) {
                    ds.record_tracking(spec, &mix, &scene, seed, *color, q0, &mut rng);
                    continue;
                }
                let Some(mut reach) = Reach::plan_with(&q0, &scene, *color, 0.0, spec.profile)
                else {
                    continue;
                };
                let ep = ds.episode_color.len() as u32;
                ds.episode_scene_seed.push(seed);
                ds.episode_color.push(ci as u8);
                let steps = (reach.duration / dt).ceil() as usize + spec.hold_steps;
                let perturb_at = (steps > 6 && rng.gen_bool(spec.perturb_share))
                    .then(|| rng.gen_range(1..steps - 4));
                let hold = spec.hold_steps as f64 * dt;
                // the pose at every step so far (the history's frames)
                let mut poses: Vec<[f64; TASK_DOF]> = Vec::new();
                let mut k = 0;
                loop {
                    let t = k as f64 * dt;
                    if Some(k) == perturb_at {
                        let mut q = reach.at(t);
                        for v in q.iter_mut().take(ARM_JOINTS) {
                            *v += spec.perturb_std * gaussian(&mut rng);
                        }
                        q[1] = q[1].clamp(0.05, 2.5);
                        if let Some(r) = Reach::plan_with(&q, &scene, *color, t, spec.profile) {
                            reach = r;
                        }
                    }
                    poses.push(reach.at(t));
                    // until the (possibly re-planned) reach has arrived and held
                    let last = t >= reach.end() + hold - 1e-9;
                    let keep = k == 0 || last || rng.gen_bool(spec.keep_share.clamp(0.0, 1.0));
                    k += 1;
                    if !keep {
                        continue;
                    }
                    let then = poses[(k - 1).saturating_sub(spec.history_steps)];
                    let still = [[0.0; 2]; 2];
                    ds.push_sample(
                        spec,
                        (&scene, still),
                        &reach.at(t),
                        (&scene, &then),
                        ep,
                        |i| reach.at(t + i as f64 * dt),
                    );
                    if last {
                        break;
                    }
                }
            }
            progress(si + 1, spec.scenes);
        }
        ds
    }

    /// Appends one sample: the frame of `scene` seen at pose `q`, the pose, with a history the
    /// earlier frame of `then` (the scene and pose `history_steps` before), and the chunk whose
    /// row i is `chunk(i)` (called for i = 0..H in order), in episode `ep`.
    fn push_sample(
        &mut self,
        spec: &DatasetSpec,
        (scene, velocity): (&ReachScene, [[f64; 2]; 2]),
        q: &[f64; TASK_DOF],
        then: (&ReachScene, &[f64; TASK_DOF]),
        ep: u32,
        mut chunk: impl FnMut(usize) -> [f64; TASK_DOF],
    ) {
        let n = spec.width * spec.height * 3;
        let start = self.image.len();
        self.image.resize(start + n, 0);
        scene.render_rgb(
            q,
            spec.width,
            spec.height,
            3 * spec.width,
            &mut self.image[start..],
        );
        if spec.history_steps > 0 {
            let start = self.image_prev.len();
            self.image_prev.resize(start + n, 0);
            then.0.render_rgb(
                then.1,
                spec.width,
                spec.height,
                3 * spec.width,
                &mut self.image_prev[start..],
            );
        }
        self.state.extend(q.iter().map(|&v| v as f32));
        self.targets
            .extend(scene.targets.iter().flatten().map(|&v| v as f32));
        self.target_velocity
            .extend(velocity.iter().flatten().map(|&v| v as f32));
        for i in 0..spec.horizon {
            self.actions.extend(chunk(i).iter().map(|&v| v as f32));
        }
        self.episode.push(ep);
    }

    /// Records one episode of [`DriftMix`] (nothing if the target leaves the arm's reach or its
    /// inverse kinematics jumps on the way).
    #[allow(clippy::too_many_arguments)]
    fn record_tracking(
        &mut self,
        spec: &DatasetSpec,
        mix: &DriftMix,
        scene: &ReachScene,
        seed: u64,
        color: TargetColor,
        q0: [f64; TASK_DOF],
        rng: &mut impl Rng,
    ) {
        let drift = super::sim::Drift {
            amplitude_rad: rng.gen_range(mix.max_amplitude_rad / 3.0..=mix.max_amplitude_rad),
            frequency_hz: rng.gen_range(mix.max_frequency_hz / 3.0..=mix.max_frequency_hz),
            phase_rad: rng.gen_range(0.0..std::f64::consts::TAU),
            follow_s: mix.follow_s,
        };
        let feedforward = rng.gen_range(0.0..1.0);
        let dt = 1.0 / spec.action_rate_hz;
        let steps = (mix.max_seconds / dt).ceil() as usize;
        let perturb_at =
            (steps > 6 && rng.gen_bool(spec.perturb_share)).then(|| rng.gen_range(1..steps - 4));
        let keep_draws: Vec<bool> = (0..steps)
            .map(|_| rng.gen_bool(spec.keep_share.clamp(0.0, 1.0)))
            .collect();
        // the joint-space goal on a 10 ms grid (linear in between) over the episode and the
        // last chunk's horizon; it must exist and move continuously
        const GRID: f64 = 0.01;
        let ci = color as usize;
        let n = ((mix.max_seconds + (spec.horizon + 1) as f64 * dt) / GRID).ceil() as usize;
        let mut table: Vec<[f64; ARM_JOINTS]> = Vec::with_capacity(n + 1);
        for i in 0..=n {
            let p = drift.targets_at(&scene.targets, i as f64 * GRID)[ci];
            let Some(g) = super::inverse_kinematics(p) else {
                return;
            };
            if let Some(prev) = table.last() {
                if (0..ARM_JOINTS).any(|j| (g[j] - prev[j]).abs() > 0.05) {
                    return;
                }
            }
            table.push(g);
        }
        let goal_at = |t: f64| -> [f64; ARM_JOINTS] {
            let x = (t / GRID).clamp(0.0, n as f64);
            let i = (x.floor() as usize).min(n - 1);
            let f = x - i as f64;
            std::array::from_fn(|j| table[i][j] + (table[i + 1][j] - table[i][j]) * f)
        };
        let ep = self.episode_color.len() as u32;
        self.episode_scene_seed.push(seed);
        self.episode_color.push(ci as u8);
        let follow_steps = (mix.follow_s / dt).ceil() as usize;
        let mut q = q0;
        q[ARM_JOINTS] = 0.0; // open while reaching, as the static expert
        let mut on_at = None;
        // the observed pose at every step so far (the history's frames)
        let mut poses: Vec<[f64; TASK_DOF]> = Vec::with_capacity(steps);
        for (k, keep_draw) in keep_draws.into_iter().enumerate() {
            let t = k as f64 * dt;
            if Some(k) == perturb_at {
                for v in q.iter_mut().take(ARM_JOINTS) {
                    *v += spec.perturb_std * gaussian(rng);
                }
                q[1] = q[1].clamp(0.05, 2.5);
            }
            let now = ReachScene {
                targets: drift.targets_at(&scene.targets, t),
            };
            poses.push(q);
            if on_at.is_none() && now.distance(&q, color) <= 0.5 * super::REACH_TOLERANCE {
                on_at = Some(k);
            }
            let last = k + 1 == steps || on_at.is_some_and(|k0| k >= k0 + follow_steps);
            if k == 0 || last || keep_draw {
                // the chunk: the tracking expert from the observed pose, action 0 the pose
                let mut a = q;
                let before = ReachScene {
                    targets: drift.targets_at(
                        &scene.targets,
                        // (exactly the earlier step's time once there is one)
                        (k as f64 - spec.history_steps as f64) * dt,
                    ),
                };
                let then = poses[k.saturating_sub(spec.history_steps)];
                let velocity = drift.velocities_at(&scene.targets, t);
                self.push_sample(spec, (&now, velocity), &q, (&before, &then), ep, |i| {
                    let row = a;
                    super::expert::track(&mut a, t + i as f64 * dt, dt, 1.0, &goal_at);
                    row
                });
            }
            if last {
                break;
            }
            super::expert::track(&mut q, t, dt, feedforward, &goal_at);
        }
    }

    /// Writes the dataset as safetensors.
    pub fn save(&self, path: &Path) -> anyhow::Result<()> {
        use safetensors::tensor::{Dtype, TensorView};
        let n = self.len();
        let bytes_f32 = |v: &[f32]| -> Vec<u8> { v.iter().flat_map(|x| x.to_le_bytes()).collect() };
        let state = bytes_f32(&self.state);
        let actions = bytes_f32(&self.actions);
        let episode: Vec<u8> = self.episode.iter().flat_map(|x| x.to_le_bytes()).collect();
        let seeds: Vec<u8> = self
            .episode_scene_seed
            .iter()
            .flat_map(|x| x.to_le_bytes())
            .collect();
        let e = self.episodes();
        let mut views = vec![
            (
                "image",
                TensorView::new(Dtype::U8, vec![n, self.height, self.width, 3], &self.image)?,
            ),
            (
                "state",
                TensorView::new(Dtype::F32, vec![n, self.n_dof], &state)?,
            ),
            (
                "actions",
                TensorView::new(Dtype::F32, vec![n, self.horizon, self.n_dof], &actions)?,
            ),
            ("episode", TensorView::new(Dtype::U32, vec![n], &episode)?),
            (
                "episode_scene_seed",
                TensorView::new(Dtype::U64, vec![e], &seeds)?,
            ),
            (
                "episode_color",
                TensorView::new(Dtype::U8, vec![e], &self.episode_color)?,
            ),
        ];
        let targets = bytes_f32(&self.targets);
        let target_velocity = bytes_f32(&self.target_velocity);
        let aux = bytes_f32(&self.aux);
        views.push((
            "targets",
            TensorView::new(Dtype::F32, vec![n, 4], &targets)?,
        ));
        views.push((
            "target_velocity",
            TensorView::new(Dtype::F32, vec![n, 4], &target_velocity)?,
        ));
        if self.history_steps > 0 {
            views.push((
                "image_prev",
                TensorView::new(
                    Dtype::U8,
                    vec![n, self.height, self.width, 3],
                    &self.image_prev,
                )?,
            ));
        }
        if !self.aux.is_empty() {
            views.push((
                "aux",
                TensorView::new(Dtype::F32, vec![n, AUX_POINTS * 2], &aux)?,
            ));
        }
        let meta: HashMap<String, String> = [
            ("format".to_string(), FORMAT.to_string()),
            ("task".to_string(), self.task.clone()),
            (
                "action_rate_hz".to_string(),
                self.action_rate_hz.to_string(),
            ),
            ("camera".to_string(), self.camera.clone()),
            ("prompts".to_string(), serde_json::to_string(&self.prompts)?),
            ("expert".to_string(), self.expert.name().to_string()),
            ("drift_share".to_string(), self.drift_share.to_string()),
            ("history_steps".to_string(), self.history_steps.to_string()),
        ]
        .into_iter()
        .collect();
        if let Some(dir) = path.parent() {
            std::fs::create_dir_all(dir)?;
        }
        safetensors::tensor::serialize_to_file(views, Some(meta), path)?;
        Ok(())
    }

    /// Reads a dataset written by [`Self::save`], checking every tensor's type and shape.
    pub fn load(path: &Path) -> anyhow::Result<Self> {
        use safetensors::tensor::Dtype;
        let bytes = std::fs::read(path)
            .map_err(|e| anyhow::anyhow!("cannot read {}: {e}", path.display()))?;
        let st = safetensors::SafeTensors::deserialize(&bytes)
            .map_err(|e| anyhow::anyhow!("{}: not a safetensors file: {e}", path.display()))?;
        let (_, meta) = safetensors::SafeTensors::read_metadata(&bytes)?;
        let meta = meta.metadata().clone().unwrap_or_default();
        anyhow::ensure!(
            meta.get("format").map(String::as_str) == Some(FORMAT),
            "{}: not a {FORMAT} file (format {:?})",
            path.display(),
            meta.get("format")
        );
        let get = |name: &str, dtype: Dtype, rank: usize| -> anyhow::Result<(Vec<usize>, &[u8])> {
            let t = st
                .tensor(name)
                .map_err(|e| anyhow::anyhow!("{}: tensor {name}: {e}", path.display()))?;
            anyhow::ensure!(
                t.dtype() == dtype && t.shape().len() == rank,
                "{}: tensor {name} is {:?} {:?}, expected {dtype:?} of rank {rank}",
                path.display(),
                t.dtype(),
                t.shape()
            );
            Ok((t.shape().to_vec(), t.data()))
        };
        let f32s = |b: &[u8]| -> Vec<f32> {
            b.chunks_exact(4)
                .map(|c| f32::from_le_bytes([c[0], c[1], c[2], c[3]]))
                .collect()
        };
        let (ish, image) = get("image", Dtype::U8, 4)?;
        let (ssh, state) = get("state", Dtype::F32, 2)?;
        let (ash, actions) = get("actions", Dtype::F32, 3)?;
        let (esh, episode) = get("episode", Dtype::U32, 1)?;
        let (_, seeds) = get("episode_scene_seed", Dtype::U64, 1)?;
        let (csh, colors) = get("episode_color", Dtype::U8, 1)?;
        let n = ish[0];
        anyhow::ensure!(
            ssh[0] == n && ash[0] == n && esh[0] == n && ssh[1] == ash[2] && ish[3] == 3,
            "{}: inconsistent shapes image {ish:?} state {ssh:?} actions {ash:?} episode {esh:?}",
            path.display()
        );
        let episode: Vec<u32> = episode
            .chunks_exact(4)
            .map(|c| u32::from_le_bytes([c[0], c[1], c[2], c[3]]))
            .collect();
        anyhow::ensure!(
            episode.iter().all(|&e| (e as usize) < csh[0]),
            "{}: episode index out of range",
            path.display()
        );
        let task = meta
            .get("task")
            .cloned()
            .unwrap_or_else(|| REACH_TASK.to_string());
        let expert = match meta.get("expert") {
            // (another task's expert is named for the record; the reach trainer's check of
            // the profile does not apply to it)
            _ if task != REACH_TASK => super::expert::Profile::default(),
            None => super::expert::Profile::MinJerk,
            Some(name) => <super::expert::Profile as clap::ValueEnum>::from_str(name, false)
                .map_err(|_| anyhow::anyhow!("{}: unknown expert {name:?}", path.display()))?,
        };
        let prompts: Vec<String> = match meta.get("prompts") {
            Some(p) => serde_json::from_str(p)
                .map_err(|e| anyhow::anyhow!("{}: bad prompts {p:?}: {e}", path.display()))?,
            None => TargetColor::ALL
                .iter()
                .map(|c| c.prompt().to_string())
                .collect(),
        };
        anyhow::ensure!(
            !prompts.is_empty() && colors.iter().all(|&c| (c as usize) < prompts.len()),
            "{}: an episode's prompt index is beyond the {} prompts",
            path.display(),
            prompts.len()
        );
        let aux = if st.names().contains(&"aux") {
            let (xsh, x) = get("aux", Dtype::F32, 2)?;
            anyhow::ensure!(
                xsh == [n, AUX_POINTS * 2],
                "{}: aux is {xsh:?}, expected [{n}, {}]",
                path.display(),
                AUX_POINTS * 2
            );
            f32s(x)
        } else {
            anyhow::ensure!(
                task == REACH_TASK,
                "{}: a {task} dataset without its localisation targets (tensor aux)",
                path.display()
            );
            Vec::new()
        };
        let action_rate_hz: f64 = meta
            .get("action_rate_hz")
            .and_then(|s| s.parse().ok())
            .filter(|r: &f64| r.is_finite() && *r > 0.0)
            .ok_or_else(|| anyhow::anyhow!("{}: bad action_rate_hz", path.display()))?;
        let drift_share = match meta.get("drift_share") {
            None => 0.0,
            Some(v) => v
                .parse()
                .ok()
                .filter(|s: &f64| (0.0..=1.0).contains(s))
                .ok_or_else(|| anyhow::anyhow!("{}: bad drift_share {v:?}", path.display()))?,
        };
        let history_steps: usize =
            match meta.get("history_steps") {
                None => 0,
                Some(v) => v.parse().ok().filter(|s| *s <= 1000).ok_or_else(|| {
                    anyhow::anyhow!("{}: bad history_steps {v:?}", path.display())
                })?,
            };
        let image_prev = if history_steps > 0 {
            let (psh, prev) = get("image_prev", Dtype::U8, 4)?;
            anyhow::ensure!(
                psh == ish,
                "{}: image_prev is {psh:?}, image {ish:?}",
                path.display()
            );
            prev.to_vec()
        } else {
            Vec::new()
        };
        let episode_scene_seed: Vec<u64> = seeds
            .chunks_exact(8)
            .map(|c| u64::from_le_bytes(c.try_into().unwrap_or([0; 8])))
            .collect();
        let (targets, target_velocity) = if st.names().contains(&"targets") {
            let (tsh, t) = get("targets", Dtype::F32, 2)?;
            let (vsh, v) = get("target_velocity", Dtype::F32, 2)?;
            anyhow::ensure!(
                tsh == [n, 4] && vsh == [n, 4],
                "{}: targets {tsh:?} / target_velocity {vsh:?}, expected [{n}, 4]",
                path.display()
            );
            (f32s(t), f32s(v))
        } else {
            // (an older file: static targets, where the scene seeds put them)
            anyhow::ensure!(
                drift_share == 0.0,
                "{}: recorded with drifting targets before the targets' positions were stored per \
                 sample: delete it to record it anew",
                path.display()
            );
            let t = episode
                .iter()
                .flat_map(|&e| {
                    let seed = episode_scene_seed.get(e as usize).copied().unwrap_or(0);
                    let sc = ReachScene::from_seed(seed);
                    sc.targets.into_iter().flatten().map(|v| v as f32)
                })
                .collect();
            (t, vec![0.0; 4 * n])
        };
        Ok(Dataset {
            width: ish[2],
            height: ish[1],
            horizon: ash[1],
            n_dof: ssh[1],
            action_rate_hz,
            camera: meta.get("camera").cloned().unwrap_or_default(),
            image: image.to_vec(),
            state: f32s(state),
            actions: f32s(actions),
            episode,
            episode_scene_seed,
            episode_color: colors.to_vec(),
            expert,
            drift_share,
            history_steps,
            image_prev,
            targets,
            target_velocity,
            task,
            prompts,
            aux,
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The tracking expert's fastest joint: the approach plus the fastest swing of the first
    /// joint (0.35 rad · 2π · 0.3 Hz).
    const PEAK_VELOCITY_WITH_SWING: f64 = super::super::expert::PEAK_VELOCITY + 0.67;

    fn spec() -> DatasetSpec {
        DatasetSpec {
            scenes: 6,
            scene_base: TRAIN_SEED_BASE,
            seed: 1,
            horizon: 10,
            action_rate_hz: 10.0,
            camera: "base_0_rgb".into(),
            width: 32,
            height: 32,
            hold_steps: 3,
            perturb_share: 0.5,
            perturb_std: 0.15,
            home: [0.0, 1.2, 0.6, 0.0],
            keep_share: 1.0,
            profile: Default::default(),
            drift: None,
            history_steps: 0,
        }
    }

    #[test]
    fn the_earlier_frame_is_the_one_recorded_history_steps_before() {
        let spec = DatasetSpec {
            drift: Some(DriftMix::with_share(0.5)),
            history_steps: 2,
            ..spec()
        };
        let ds = Dataset::generate(&spec, |_, _| {});
        assert_eq!(ds.image_prev.len(), ds.image.len());
        let (mut checked, mut differ) = (0, 0);
        for e in 0..ds.episodes() {
            // every step is kept (keep_share 1): an episode's samples are its steps in order
            let samples: Vec<usize> = (0..ds.len())
                .filter(|&i| ds.episode[i] as usize == e)
                .collect();
            for (k, &i) in samples.iter().enumerate().skip(2) {
                assert_eq!(
                    ds.frame_prev(i),
                    ds.frame(samples[k - 2]),
                    "episode {e} step {k}"
                );
                checked += 1;
                differ += usize::from(ds.frame_prev(i) != ds.frame(i));
            }
        }
        assert!(checked > 100, "{checked}");
        assert!(
            differ * 2 > checked,
            "{differ} of {checked} earlier frames show motion"
        );
        // kept in the file
        let back = saved_and_loaded(&ds, "hist");
        assert_eq!(back, ds);
    }

    #[test]
    fn chunks_follow_the_expert_and_end_on_the_target() {
        let ds = Dataset::generate(&spec(), |_, _| {});
        assert_eq!(ds.episodes(), 12);
        assert!(ds.len() > 12 * 10, "{}", ds.len());
        for i in 0..ds.len() {
            let s = ds.state_of(i);
            let a = ds.actions_of(i);
            // action 0 is the observed position
            for j in 0..TASK_DOF {
                assert!((a[j] - s[j]).abs() < 1e-6, "sample {i} joint {j}");
            }
        }
        // the last sample of every episode sits on its target with the gripper closed
        for e in 0..ds.episodes() {
            let last = (0..ds.len())
                .rev()
                .find(|&i| ds.episode[i] as usize == e)
                .unwrap();
            let q: Vec<f64> = ds.state_of(last).iter().map(|&v| v as f64).collect();
            let scene = ReachScene::from_seed(ds.episode_scene_seed[e]);
            assert!(scene.distance(&q, ds.color(last)) < 1e-3);
            assert_eq!(q[3], 1.0);
        }
    }

    #[test]
    fn drifting_episodes_follow_the_moving_target() {
        let spec = DatasetSpec {
            drift: Some(DriftMix::with_share(1.0)),
            ..spec()
        };
        let ds = Dataset::generate(&spec, |_, _| {});
        // (an episode whose target would leave the arm's reach is dropped)
        assert!(ds.episodes() >= 8, "{} episodes", ds.episodes());
        assert_eq!(ds.drift_share, 1.0);
        let speed_limit = (PEAK_VELOCITY_WITH_SWING / spec.action_rate_hz) as f32;
        let (mut followed, mut moving) = (0, 0);
        for e in 0..ds.episodes() {
            let samples: Vec<usize> = (0..ds.len())
                .filter(|&i| ds.episode[i] as usize == e)
                .collect();
            for &i in &samples {
                let (s, a) = (ds.state_of(i), ds.actions_of(i));
                for j in 0..TASK_DOF {
                    assert!((a[j] - s[j]).abs() < 1e-6, "action 0 is the observed pose");
                }
                for k in 1..ds.horizon {
                    for j in 0..ARM_JOINTS {
                        let step = (a[k * TASK_DOF + j] - a[(k - 1) * TASK_DOF + j]).abs();
                        assert!(step <= speed_limit, "sample {i} step {k} joint {j}: {step}");
                    }
                }
            }
            // the last sample of an episode that got onto its target: the chunk keeps moving
            // (with the target) and the gripper stays closed
            let last = ds.actions_of(*samples.last().unwrap());
            let h = ds.horizon;
            if last[TASK_DOF + ARM_JOINTS] == 1.0 {
                followed += 1;
                assert!((1..h).all(|k| last[k * TASK_DOF + ARM_JOINTS] == 1.0));
                if (last[(h - 1) * TASK_DOF] - last[0]).abs() > 0.01 {
                    moving += 1;
                }
            }
        }
        assert!(
            followed >= ds.episodes() / 2,
            "{followed} of {} followed",
            ds.episodes()
        );
        assert!(
            moving * 10 >= followed * 8,
            "{moving} of {followed} chunks move with the target"
        );
        // each sample's targets are where the swing has them then: rotated about the base (same
        // distances as the scene's), moving at right angles to their radius, and moving at all
        let mut swinging = 0;
        for i in 0..ds.len() {
            let sc = ReachScene::from_seed(ds.episode_scene_seed[ds.episode[i] as usize]);
            let (p, v) = (ds.targets_of(i), ds.target_velocity_of(i));
            for c in 0..2 {
                let r = |x: [f64; 2]| x[0].hypot(x[1]);
                assert!((r(p[c]) - r(sc.targets[c])).abs() < 1e-5, "sample {i}");
                assert!(
                    (p[c][0] * v[c][0] + p[c][1] * v[c][1]).abs() < 1e-3,
                    "sample {i}"
                );
            }
            swinging += usize::from(v[0][0].hypot(v[0][1]) > 0.01);
        }
        assert!(
            swinging * 2 > ds.len(),
            "{swinging} of {} samples swing",
            ds.len()
        );
        // the share is kept in the file
        let back = saved_and_loaded(&ds, "drift");
        assert_eq!(back.drift_share, 1.0);
        assert_eq!(back.target_velocity, ds.target_velocity);
    }

    #[test]
    fn keep_share_records_fewer_steps_of_the_same_episodes() {
        let all = Dataset::generate(&spec(), |_, _| {});
        let some = Dataset::generate(
            &DatasetSpec {
                keep_share: 0.25,
                ..spec()
            },
            |_, _| {},
        );
        assert_eq!(some.episodes(), all.episodes());
        assert!(
            some.len() * 2 < all.len() && some.len() >= 2 * some.episodes(),
            "{} of {}",
            some.len(),
            all.len()
        );
        // every kept sample still starts its chunk at its state
        for i in 0..some.len() {
            let (s, a) = (some.state_of(i), some.actions_of(i));
            for j in 0..TASK_DOF {
                assert!((a[j] - s[j]).abs() < 1e-6);
            }
        }
    }

    /// `ds` written to a file of its own and read back.
    fn saved_and_loaded(ds: &Dataset, tag: &str) -> Dataset {
        let dir = std::env::temp_dir().join(format!("chunkrt-ds-{tag}-{}", std::process::id()));
        let path = dir.join("d.safetensors");
        ds.save(&path).unwrap();
        let back = Dataset::load(&path).unwrap();
        std::fs::remove_dir_all(&dir).ok();
        back
    }

    #[test]
    fn save_and_load_round_trip() {
        let ds = Dataset::generate(&spec(), |_, _| {});
        let back = saved_and_loaded(&ds, "plain");
        assert_eq!(back, ds);
    }
}
