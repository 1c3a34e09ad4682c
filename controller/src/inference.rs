//! The policy as a chunk source: observation (IPC frames + joint state) → action chunk.
//!
//! Runs in the observation/inference thread, never in the control thread.

use std::sync::atomic::{AtomicU64, Ordering};

use anyhow::Context;

use chunkrt_ipc::config::{PolicyConfig, PolicyDevice, PolicyKind, PolicyPrecision, RtcJacobian};
use chunkrt_ipc::{monotonic_ns, Config, ENCODING_BGR8, ENCODING_MONO8, ENCODING_RGB8};

use crate::chunk::ActionChunk;
use crate::contract::ChunkSource;
use crate::control::{Continuation, InferenceRequest};
use crate::edge::Observation;
use crate::policy::config::ConfigOverrides;
use crate::policy::rtc::{Guidance, Jacobian};
use crate::policy::runtime::{LoadOptions, Policy, RawFrame, RawObservation};
use crate::policy::{DeviceSpec, Encoding, ModelKind, Precision};

static NEXT_CHUNK_ID: AtomicU64 = AtomicU64::new(1);

/// A unique, increasing chunk id (never 0).
pub fn next_chunk_id() -> u64 {
    NEXT_CHUNK_ID.fetch_add(1, Ordering::Relaxed)
}

/// The policy crate's load options for a `[policy]` section (the composition root's
/// translation from the controller's configuration to the policy's own types).
pub fn load_options(cfg: &PolicyConfig) -> LoadOptions {
    LoadOptions {
        kind: match cfg.kind {
            PolicyKind::Hold => None,
            PolicyKind::Pi0 => Some(ModelKind::Pi0),
            PolicyKind::Pi05 => Some(ModelKind::Pi05),
        },
        num_steps: cfg.num_steps,
        precision: match cfg.precision {
            PolicyPrecision::F32 => Precision::F32,
            PolicyPrecision::Bf16 => Precision::Bf16,
        },
        device: match cfg.device {
            PolicyDevice::Cpu => DeviceSpec::Cpu,
            PolicyDevice::Cuda(n) => DeviceSpec::Cuda(n as usize),
        },
        overrides: ConfigOverrides {
            action_horizon: cfg.model.action_horizon,
            action_dim: cfg.model.action_dim,
            max_token_len: cfg.model.max_token_len,
            cameras: cfg.model.cameras.clone(),
            num_denoise_steps: Some(cfg.num_steps),
            delta_action_mask: cfg.model.delta_action_mask.clone(),
        },
        cuda_graph: true,
    }
}

/// Loads the policy of a `[policy]` section from `dir` (call it inside [`policy_pool`]'s
/// `install` so the packing at load runs on the policy's threads too).
pub fn load_policy(dir: &std::path::Path, cfg: &PolicyConfig) -> anyhow::Result<Policy> {
    Policy::load(dir, &load_options(cfg))
        .with_context(|| format!("cannot load the policy from {}", dir.display()))
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
    n_dof: usize,
    prefix: Vec<f64>,
    weights: Vec<f32>,
    /// Per joint: `Some((open, closed))` for step channels (their state is snapped to the
    /// nearer end before it reaches the policy), `None` for ordinary joints.
    step_ends: Vec<Option<(f64, f64)>>,
    state: Vec<f64>,
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
        let policy = pool.install(|| load_policy(&dir, &cfg.policy))?;
        policy
            .check_dof(cfg.n_dof())
            .with_context(|| format!("{}: norm_stats.json", dir.display()))?;
        anyhow::ensure!(
            cfg.execution.strategy != chunkrt_ipc::config::Strategy::RtcTrained
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
        Ok(Self {
            policy,
            pool,
            prompt: cfg.policy.prompt.clone(),
            period_ns: (1e9 / cfg.policy.action_rate_hz).round() as u64,
            n_dof: cfg.n_dof(),
            prefix: Vec::new(),
            weights: Vec::new(),
            step_ends: cfg
                .robot
                .joints
                .iter()
                .map(|j| j.step.then_some((j.position_min, j.position_max)))
                .collect(),
            state: Vec::new(),
        })
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

    /// One chunk from frames and a joint state observed at `t_obs_ns`, guided by `request` when
    /// it asks for real-time chunking. (The inference thread's `compute`, and in-process
    /// closed-loop evaluation.)
    pub fn infer_chunk(
        &mut self,
        frames: &[RawFrame<'_>],
        joint_state: &chunkrt_ipc::JointState,
        t_obs_ns: u64,
        request: &InferenceRequest,
    ) -> anyhow::Result<ActionChunk> {
        let n = self.n_dof.min(joint_state.n_dof as usize);
        let usable = request.horizon > 0 && request.n_dof >= n;
        // Training-time RTC: the chunk starts with the actions the robot executes until it
        // lands (`c` prefix rows from row `shift`, [`InferenceRequest::committed_rows`]).
        let committed = request.continuation == Continuation::Committed && usable;
        // Future-state inference (VLASH): the policy observes where the current chunk will have
        // taken the robot when the new chunk lands (`prefix[d]`, d the estimated delay) and the
        // new chunk starts there, so it continues the motion instead of restarting it from the
        // stale measured state. (With a committed prefix: where the committed rows start.)
        let (shift, c) = if committed {
            request.committed_rows()
        } else if request.future_state && usable {
            (request.delay_steps.min(request.horizon - 1), 0)
        } else {
            (0, 0)
        };
        // (a committed prefix that starts at the request goes with the measured state there)
        let from_prefix = usable && request.future_state && (!committed || shift > 0);
        let (observed, start_shift_ns) = if from_prefix {
            let start = request.t_ref_ns + shift as u64 * request.period_ns;
            (&request.prefix[shift][..n], start.saturating_sub(t_obs_ns))
        } else {
            (&joint_state.position[..n], 0)
        };
        // A step channel (a gripper) is open or closed: the policy sees it as one of its two
        // ends, as in its training data, not the in-between values a real gripper passes through.
        self.state.clear();
        for (i, &v) in observed.iter().enumerate() {
            self.state
                .push(match self.step_ends.get(i).copied().flatten() {
                    Some((lo, hi)) => {
                        if v >= 0.5 * (lo + hi) {
                            hi
                        } else {
                            lo
                        }
                    }
                    None => v,
                });
        }
        let raw = RawObservation {
            frames,
            joint_positions: &self.state,
            prompt: &self.prompt,
        };
        let actions = if committed {
            self.prefix.clear();
            for row in &request.prefix[shift..(shift + c).min(request.horizon)] {
                self.prefix.extend_from_slice(&row[..n]);
            }
            let (policy, prefix) = (&mut self.policy, &self.prefix);
            self.pool.install(|| policy.infer_committed(&raw, prefix))?
        } else if request.continuation == Continuation::Guided && request.beta > 0.0 {
            // real-time chunking: guide towards what the robot will execute meanwhile
            let h = self.policy.horizon().min(request.horizon.max(1));
            let full_h = self.policy.horizon();
            self.prefix.clear();
            self.weights.clear();
            // (with a future state the new chunk's action i is the old one's i + shift)
            for i in 0..full_h {
                let k = i + shift;
                let row = &request.prefix[k.min(h - 1)];
                self.prefix.extend_from_slice(&row[..n]);
                self.weights.push(if k < h {
                    request.weights[k] as f32
                } else {
                    0.0
                });
            }
            let g = Guidance {
                prefix: &self.prefix,
                weights: &self.weights,
                beta: request.beta as f32,
                jacobian: match request.jacobian {
                    RtcJacobian::Vjp => Jacobian::Vjp,
                    RtcJacobian::Identity => Jacobian::Identity,
                },
            };
            let policy = &mut self.policy;
            self.pool.install(|| policy.infer_guided(&raw, Some(&g)))?
        } else {
            let policy = &mut self.policy;
            self.pool.install(|| policy.infer(&raw))?
        };
        let chunk = ActionChunk {
            id: next_chunk_id(),
            observation_seq: joint_state.seq,
            t_obs_ns,
            period_ns: self.period_ns,
            n_dof: n,
            actions,
            ready_ns: monotonic_ns(),
            start_shift_ns,
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
