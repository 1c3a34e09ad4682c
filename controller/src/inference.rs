//! The policy as a chunk source: observation (IPC frames + joint state) → action chunk.
//!
//! Runs in the observation/inference thread, never in the control thread.

use std::sync::atomic::{AtomicU64, Ordering};

use anyhow::Context;

use crate::config::{Config, PolicyConfig};
use chunkrt_ipc::{monotonic_ns, ENCODING_BGR8, ENCODING_MONO8, ENCODING_RGB8};

use crate::chunk::ActionChunk;
use crate::conditioning::Conditioner;
use crate::contract::ChunkSource;
use crate::control::InferenceRequest;
use crate::edge::Observation;
use crate::policy::runtime::{Policy, RawFrame, RawObservation};
use crate::policy::Encoding;

static NEXT_CHUNK_ID: AtomicU64 = AtomicU64::new(1);

/// A unique, increasing chunk id (never 0).
pub fn next_chunk_id() -> u64 {
    NEXT_CHUNK_ID.fetch_add(1, Ordering::Relaxed)
}

/// Loads the policy of a `[policy]` section from `dir` (call it inside [`policy_pool`]'s
/// `install` so the packing at load runs on the policy's threads too).
pub fn load_policy(dir: &std::path::Path, cfg: &PolicyConfig) -> anyhow::Result<Policy> {
    Policy::load(dir, &cfg.load_options())
        .with_context(|| format!("cannot load the policy from {}", dir.display()))
}

/// The robot's joints' position ranges, which a policy's action statistics are held against
/// at load ([`chunkrt_policy::openpi_config::check_action_ranges`]).
pub fn joint_ranges(cfg: &Config) -> Vec<chunkrt_policy::openpi_config::JointRange> {
    cfg.robot
        .joints
        .iter()
        .map(|j| chunkrt_policy::openpi_config::JointRange {
            name: j.name.clone(),
            min: j.position_min,
            max: j.position_max,
        })
        .collect()
}

/// The policy's own thread pool: `policy.threads` workers (0: one per core), named
/// `chunkrt-policy-N`. Everything the policy computes runs inside its `install` (candle's CPU
/// ops and chunkrt's kernels split their work over the current rayon pool), so the process's
/// global pool and environment stay untouched and the pool's size is the configured one.
pub fn policy_pool(cfg: &PolicyConfig) -> anyhow::Result<rayon::ThreadPool> {
    rayon::ThreadPoolBuilder::new()
        .num_threads(cfg.threads)
        .thread_name(|i| format!("chunkrt-policy-{i}"))
        .build()
        .context("cannot start the policy's thread pool")
}

/// The policy's pixel layout for an IPC `ENCODING_*` code (the edge has validated it).
pub fn frame_encoding(code: u32) -> anyhow::Result<Encoding> {
    match code {
        ENCODING_RGB8 => Ok(Encoding::Rgb8),
        ENCODING_BGR8 => Ok(Encoding::Bgr8),
        ENCODING_MONO8 => Ok(Encoding::Mono8),
        other => anyhow::bail!("unknown frame encoding {other}"),
    }
}

/// π0 / π0.5 loaded from the configured checkpoint.
pub struct PolicySource {
    policy: Policy,
    pool: rayon::ThreadPool,
    prompt: String,
    period_ns: u64,
    conditioner: Conditioner,
}

impl PolicySource {
    /// Loads `policy.checkpoint` (relative to the configuration file).
    pub fn load(cfg: &Config) -> anyhow::Result<Self> {
        let dir = cfg
            .policy
            .checkpoint
            .as_ref()
            .map(|p| cfg.resolve(p))
            .context("policy.checkpoint is not set")?;
        let pool = policy_pool(&cfg.policy)?;
        let mut pc = cfg.policy.clone();
        pc.tokenizer = pc.tokenizer.map(|t| cfg.resolve(&t));
        let policy = pool.install(|| load_policy(&dir, &pc))?;
        policy
            .check_dof(cfg.n_dof())
            .with_context(|| format!("{}: norm_stats.json", dir.display()))?;
        policy
            .check_action_ranges(&joint_ranges(cfg))
            .with_context(|| {
                format!(
                    "{}: norm_stats.json against the joint ranges of robot '{}' ({})",
                    dir.display(),
                    cfg.robot.name,
                    cfg.source.display()
                )
            })?;
        if let Some(c) = policy.openpi_config() {
            anyhow::ensure!(
                policy.action_width(cfg.n_dof()) == cfg.n_dof(),
                "openpi config {} answers {} action columns for {} state values: the \
                 controller drives one joint per column, so it cannot run it in-process \
                 (serve it to its own client: chunkrt serve --openpi-config {})",
                c.name,
                policy.action_width(cfg.n_dof()),
                cfg.n_dof(),
                c.name
            );
            anyhow::ensure!(
                !matches!(
                    cfg.execution.strategy,
                    crate::config::Strategy::Rtc | crate::config::Strategy::RtcTrained
                ),
                "openpi config {}: execution.strategy = {:?} conditions a chunk on the \
                 previous one (RTC), which chunkrt does not do through the robot's \
                 transforms: use replace, crossfade or temporal_ensemble",
                c.name,
                cfg.execution.strategy
            );
        }
        anyhow::ensure!(
            cfg.execution.strategy != crate::config::Strategy::RtcTrained
                || policy.committed_max() > 0,
            "execution.strategy = \"rtc_trained\" needs a policy trained with a committed \
             action prefix, and {} was not (no rtc_prefix_max in its config.json): train one \
             with `chunkrt train --rtc-prefix N`, or use strategy \"rtc\"",
            dir.display()
        );
        anyhow::ensure!(
            cfg.execution.execute_horizon <= policy.horizon(),
            "execution.execute_horizon = {} exceeds the policy's action horizon {} (a chunk \
             would run out before the next one is asked for: stop-and-go HOLDs)",
            cfg.execution.execute_horizon,
            policy.horizon()
        );
        let mut me = Self {
            policy,
            pool,
            prompt: cfg.policy.prompt.clone(),
            period_ns: (1e9 / cfg.policy.action_rate_hz).round() as u64,
            conditioner: Conditioner::new(cfg),
        };
        me.warm_up(cfg)
            .with_context(|| format!("{}: the policy's first chunk", dir.display()))?;
        Ok(me)
    }

    /// One chunk on a synthetic observation (grey frames of every camera, the joints at their
    /// initial positions) before the controller starts: a policy that cannot produce a usable
    /// chunk (non-finite weights, a broken tokenizer) fails here, at load, with the reason —
    /// not later as a controller that never leaves STARTING. (It also pays the first call's
    /// one-off costs: packing, graph capture.) The noise sequence is restarted after it.
    fn warm_up(&mut self, cfg: &Config) -> anyhow::Result<()> {
        let pixels: Vec<(String, u32, u32, Vec<u8>)> = cfg
            .cameras
            .iter()
            .map(|c| {
                let n = 3 * c.width as usize * c.height as usize;
                (c.name.clone(), c.width, c.height, vec![128u8; n])
            })
            .collect();
        let frames: Vec<RawFrame<'_>> = pixels
            .iter()
            .map(|(name, w, h, data)| RawFrame {
                camera: name,
                width: *w,
                height: *h,
                stride: 3 * *w,
                encoding: Encoding::Rgb8,
                data,
            })
            .collect();
        let mut js = chunkrt_ipc::JointState {
            n_dof: cfg.n_dof() as u32,
            ..Default::default()
        };
        for (i, j) in cfg.robot.joints.iter().enumerate() {
            js.position[i] = j.initial_position;
        }
        let chunk = self.infer_chunk(&frames, &js, 0, &InferenceRequest::default())?;
        anyhow::ensure!(chunk.horizon() > 0, "an empty chunk");
        self.policy.reseed(crate::policy::runtime::DEFAULT_SEED);
        Ok(())
    }

    /// Action horizon of the loaded model.
    pub fn horizon(&self) -> usize {
        self.policy.horizon()
    }

    /// The largest committed prefix the policy was trained with (0: none; `rtc_trained` needs
    /// one).
    pub fn committed_max(&self) -> usize {
        self.policy.committed_max()
    }

    /// Image inputs of the loaded model that are an earlier frame of a camera.
    pub fn delayed_views(&self) -> &[chunkrt_policy::DelayedView] {
        self.policy.delayed_views()
    }

    /// Restarts the policy's noise sequence from `seed` ([`Policy::reseed`]).
    pub fn reseed(&mut self, seed: u64) {
        self.policy.reseed(seed);
    }

    /// Sets the prompt given to the policy from now on.
    pub fn set_prompt(&mut self, prompt: &str) {
        self.prompt = prompt.to_string();
    }

    /// One chunk from frames and a joint state observed at `t_obs_ns`, conditioned as
    /// `request` asks ([`Conditioner::ask`]). (The inference thread's `compute`, and in-process
    /// closed-loop evaluation.)
    pub fn infer_chunk(
        &mut self,
        frames: &[RawFrame<'_>],
        joint_state: &chunkrt_ipc::JointState,
        t_obs_ns: u64,
        request: &InferenceRequest,
    ) -> anyhow::Result<ActionChunk> {
        let horizon = self.policy.horizon();
        let ask = self
            .conditioner
            .ask(request, joint_state, t_obs_ns, horizon);
        let raw = RawObservation {
            frames,
            joint_positions: ask.state,
            prompt: &self.prompt,
        };
        let policy = &mut self.policy;
        let actions = self
            .pool
            .install(|| policy.infer(&raw, &ask.conditioning))?;
        let chunk = ActionChunk {
            id: next_chunk_id(),
            observation_seq: joint_state.seq,
            t_obs_ns,
            period_ns: self.period_ns,
            n_dof: ask.state.len(),
            actions,
            ready_ns: monotonic_ns(),
            start_shift_ns: ask.start_shift_ns,
        };
        chunk.validate()?;
        Ok(chunk)
    }
}

/// The policy's view of an observation: borrowed frames, no copies. (The edge accepts only
/// known encodings; a frame with another would be left out, i.e. seen as a missing camera.)
pub fn raw_frames(obs: &Observation) -> Vec<RawFrame<'_>> {
    obs.frames
        .iter()
        .filter(|f| f.valid)
        .filter_map(|f| {
            Some(RawFrame {
                camera: &f.name,
                width: f.header.width,
                height: f.header.height,
                stride: f.header.stride,
                encoding: frame_encoding(f.header.encoding).ok()?,
                data: f.pixels(),
            })
        })
        .collect()
}

impl ChunkSource for PolicySource {
    fn name(&self) -> &str {
        "policy"
    }

    fn uses_cameras(&self) -> bool {
        true
    }

    fn delayed_views(&self) -> &[chunkrt_policy::DelayedView] {
        self.policy.delayed_views()
    }

    fn set_prompt(&mut self, prompt: &str) {
        PolicySource::set_prompt(self, prompt);
    }

    fn reseed(&mut self, seed: u64) {
        PolicySource::reseed(self, seed);
    }

    fn compute(
        &mut self,
        obs: &Observation,
        request: &InferenceRequest,
    ) -> anyhow::Result<Option<ActionChunk>> {
        let frames = raw_frames(obs);
        Ok(Some(self.infer_chunk(
            &frames,
            &obs.joint_state,
            obs.t_obs_ns(),
            request,
        )?))
    }
}
