//! Closed-loop episodes of the reach task in simulated time: the real executor (chunk timeline,
//! transition strategy, ruckig, safety state machine) ticks at the control rate, the real
//! policy computes every chunk from the rendered frame and joint state, and each chunk is
//! delivered `delay_steps` action periods after its observation — so the figures measure the
//! strategies, not this machine's load. The robot follows the command exactly.
//!
//! `synchronous` reproduces openpi's `ActionChunkBroker`: the robot executes `s` actions of a
//! chunk, then stands still while the next chunk is computed (no overlap, no blending).

use chunkrt_controller::config::Config;
use chunkrt_ipc::{JointCommand, JointState};

use super::{task_camera, ReachScene, TargetColor, TASK_DOF};
use chunkrt_bench::metrics::{Smoothness, Trace};
use chunkrt_controller::contract::{ChunkSource, Observation};
use chunkrt_controller::control::{Executor, InferenceRequest, State};
use chunkrt_controller::worker::{Delivery, InferenceWorker, Turn};

/// Simulated time starts here (ns), far from 0 so no timestamp saturates.
const START_NS: u64 = 1_000_000_000;

/// One episode to run.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct EpisodeSpec {
    /// Scene seed (target placement).
    pub scene_seed: u64,
    /// Prompted target.
    pub color: TargetColor,
    /// Start joint positions.
    pub start: [f64; TASK_DOF],
}

/// How the episode is run.
#[derive(Debug, Clone, PartialEq)]
pub struct SimSettings {
    /// Inference delay in action steps (observation → chunk available).
    pub delay_steps: u64,
    /// Give up after this long (s).
    pub max_seconds: f64,
    /// Synchronous execution instead of the configured strategy.
    pub synchronous: bool,
    /// Keep the joint trajectory and chunk switch times.
    pub record: bool,
    /// The dynamic variant: at this time (s) the prompt switches to the other target, which then
    /// is the one to reach (the prompted target jumps); `None`: the static task.
    pub retarget_at: Option<f64>,
    /// The drifting variant: the targets move while the robot reaches (`None`: they stay).
    pub drift: Option<Drift>,
}

/// The targets swing about the robot's base: both are rotated by `amplitude_rad ·
/// sin(2π · frequency_hz · t + phase_rad)` (their distance to the base and to each other stays, so they
/// stay as reachable as they were), and the prompted one must be reached where it is and
/// followed: the episode succeeds once the end effector has stayed on it for `follow_s`.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Drift {
    /// Largest rotation either side of the start (rad).
    pub amplitude_rad: f64,
    /// Swings per second.
    pub frequency_hz: f64,
    /// Phase of the swing at t = 0 (rad; 0: the targets start where the scene puts them).
    pub phase_rad: f64,
    /// How long the end effector must stay on the moving target (s; 0: touching it is enough).
    pub follow_s: f64,
}

impl Drift {
    /// The rotation at `t` (s).
    pub fn angle(&self, t: f64) -> f64 {
        self.amplitude_rad * (std::f64::consts::TAU * self.frequency_hz * t + self.phase_rad).sin()
    }

    /// The scene's targets `start` (where the scene puts them) at `t` (s).
    pub fn targets_at(&self, start: &[[f64; 2]; 2], t: f64) -> [[f64; 2]; 2] {
        let (sin, cos) = self.angle(t).sin_cos();
        start.map(|p| [cos * p[0] - sin * p[1], sin * p[0] + cos * p[1]])
    }

    /// The targets' velocities at `t` (m/s): the rotation's rate times the perpendicular of
    /// where [`Self::targets_at`] has them.
    pub fn velocities_at(&self, start: &[[f64; 2]; 2], t: f64) -> [[f64; 2]; 2] {
        let w = std::f64::consts::TAU * self.frequency_hz;
        let rate = self.amplitude_rad * w * (w * t + self.phase_rad).cos();
        self.targets_at(start, t)
            .map(|p| [-rate * p[1], rate * p[0]])
    }
}

/// The robot has reacted to a retarget once its end effector is this much further from the
/// first target than at the retarget (m): it turned away.
pub const REACTION_DISTANCE: f64 = 0.01;

/// The joint trajectory of an episode (every `stride` ticks) and when chunks took effect.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct Recording {
    /// Time (s) and joint positions.
    pub samples: Vec<(f64, [f64; TASK_DOF])>,
    /// Times (s) a new chunk took effect.
    pub switches: Vec<f64>,
    /// Every RUNNING tick: time (s), the executor's target and the command.
    pub ticks: Vec<(f64, [f64; TASK_DOF], [f64; TASK_DOF])>,
}

/// What happened.
#[derive(Debug, Clone, PartialEq)]
pub struct EpisodeOutcome {
    /// The end effector reached the prompted target within the time limit.
    pub success: bool,
    /// When it first got there (s).
    pub time_to_target: Option<f64>,
    /// It touched the other target first.
    pub wrong_target: bool,
    /// Closest approach to the prompted target (m).
    pub min_distance: f64,
    /// Switch jumps and jerk of the command while RUNNING.
    pub smoothness: Smoothness,
    /// Chunks computed.
    pub chunks: usize,
    /// Ticks spent in HOLD.
    pub hold_ticks: u64,
    /// Dynamic variant: time from the retarget until the end effector turned away from the first
    /// target by [`REACTION_DISTANCE`] (s; None: it never did, or no retarget).
    pub reaction_time: Option<f64>,
    /// Trajectory, when recorded.
    pub recording: Option<Recording>,
}

impl EpisodeOutcome {
    /// Nothing happened yet (with a recording when `record`).
    pub fn start(record: bool) -> Self {
        EpisodeOutcome {
            success: false,
            time_to_target: None,
            wrong_target: false,
            min_distance: f64::INFINITY,
            smoothness: Smoothness::default(),
            chunks: 0,
            hold_ticks: 0,
            reaction_time: None,
            recording: record.then(Recording::default),
        }
    }

    /// Counts the chunk of an answered request; an inference error ends the episode.
    pub fn count_turn(&mut self, turn: Turn) -> anyhow::Result<()> {
        match turn {
            Turn::Chunk { .. } => self.chunks += 1,
            Turn::Failed(e) => return Err(e),
            Turn::Idle | Turn::Nothing => {}
        }
        Ok(())
    }

    /// A tick outside RUNNING: not recorded (the metrics must not difference across it), and
    /// counted when it holds.
    pub fn off_tick(&mut self, trace: &mut Trace, state: State) {
        trace.gap();
        if state == State::Hold {
            self.hold_ticks += 1;
        }
    }
}

impl SimSettings {
    /// A training validation's episodes: the configured strategy, no delay, nothing recorded,
    /// nothing moving, at most `max_seconds` each.
    pub fn validation(max_seconds: f64) -> Self {
        SimSettings {
            delay_steps: 0,
            max_seconds,
            synchronous: false,
            record: false,
            retarget_at: None,
            drift: None,
        }
    }
}

/// Runs one episode with `policy` under `cfg` (its `execution.strategy` unless synchronous).
/// The policy is any chunk source: the in-process one, or a server behind the openpi protocol
/// (`chunkrt eval --remote`); it answers through the controller's [`InferenceWorker`], which
/// delivers each chunk `delay_steps` action periods after its observation.
pub fn run_episode(
    cfg: &Config,
    policy: &mut dyn ChunkSource,
    spec: &EpisodeSpec,
    settings: &SimSettings,
) -> anyhow::Result<EpisodeOutcome> {
    let cam = task_camera(cfg)?.clone();
    let (w, h) = (cam.width, cam.height);
    let mut scene = ReachScene::from_seed(spec.scene_seed);
    let start_targets = scene.targets;
    // since when the end effector has been on the prompted target
    let mut on_since: Option<f64> = None;
    // the target to reach (the prompted one; after a retarget the other) and the other one
    let (mut goal, mut other) = (spec.color, spec.color.other());
    // the retarget's time and the end effector's distance to the first target then
    let mut retargeted: Option<(f64, f64)> = None;
    let mut cfg = cfg.clone();
    if settings.synchronous {
        cfg.execution.strategy = chunkrt_controller::config::Strategy::Replace;
    }
    let mut exec = Executor::new(&cfg)?;
    let period_ns = (1e9 / cfg.policy.action_rate_hz).round() as u64;
    let control_ns = cfg.control_period_ns();
    let s = cfg.execution.execute_horizon.max(1);
    let delay_ns = settings.delay_steps * period_ns;
    let mut worker = InferenceWorker::new(exec.connect(), Delivery::After(delay_ns));
    policy.set_prompt(spec.color.prompt());
    // the episode's own noise: its chunks do not depend on which episodes ran before it, and
    // every strategy and delay of a sweep sees the same noise (common random numbers)
    policy.reseed(spec.scene_seed ^ ((spec.color as u64) << 32));

    let mut js = JointState {
        n_dof: TASK_DOF as u32,
        ..Default::default()
    };
    js.position[..TASK_DOF].copy_from_slice(&spec.start);
    let mut cmd = JointCommand::default();
    let mut trace = Trace::new(control_ns as f64 * 1e-9, TASK_DOF);
    trace.skip[TASK_DOF - 1] = true; // the gripper is a step channel
                                     // the policy's delayed views (an earlier frame of the task camera): rendered from the
                                     // joint positions of every tick so far (before the episode: the start pose) and the
                                     // targets where they were then
    let views: Vec<u64> = policy
        .delayed_views()
        .iter()
        .map(|v| {
            anyhow::ensure!(
                v.camera == cam.name,
                "the policy's image input {:?} is an earlier frame of camera {:?}; the reach \
                 task has only {:?}",
                v.name,
                v.camera,
                cam.name
            );
            Ok(v.delay_ns() / control_ns.max(1))
        })
        .collect::<anyhow::Result<_>>()?;
    // the observation the policy is given: the camera's frame, then the delayed views
    let mut obs = Observation::with_views(&cfg, policy.delayed_views());
    let mut past: Vec<[f64; TASK_DOF]> = Vec::new();
    let mut next_sync_obs = START_NS;
    let mut out = EpisodeOutcome::start(settings.record);
    let ticks = (settings.max_seconds * 1e9 / control_ns as f64).ceil() as u64;
    for k in 0..ticks {
        let now = START_NS + k * control_ns;
        let t = (now - START_NS) as f64 * 1e-9;
        js.seq += 1;
        js.measurement_time_ns = now;
        if let Some(drift) = &settings.drift {
            scene.targets = drift.targets_at(&start_targets, t);
        }
        if !views.is_empty() {
            past.push(std::array::from_fn(|j| js.position[j]));
        }
        if let (Some(at), None) = (settings.retarget_at, retargeted) {
            if t >= at {
                (goal, other) = (other, goal);
                policy.set_prompt(goal.prompt());
                let d = scene.distance(&js.position[..TASK_DOF], other);
                retargeted = Some((t, d));
            }
        }
        // renders the observation of this tick (only when a chunk is asked for)
        let observe = |obs: &mut Observation| -> anyhow::Result<()> {
            let bad = || anyhow::anyhow!("the task camera's frame buffer is too small");
            let (frame, delayed) = obs.frames.split_first_mut().ok_or_else(bad)?;
            let px = frame.write_rgb8(w, h, now).ok_or_else(bad)?;
            let (wu, hu) = (w as usize, h as usize);
            scene.render_rgb(&js.position[..TASK_DOF], wu, hu, 3 * wu, px);
            for (lag, view) in views.iter().zip(delayed.iter_mut()) {
                let then = ReachScene {
                    targets: match &settings.drift {
                        Some(d) => {
                            d.targets_at(&start_targets, t - *lag as f64 * 1e-9 * control_ns as f64)
                        }
                        None => scene.targets,
                    },
                };
                let q = k.checked_sub(*lag).map_or(spec.start, |i| past[i as usize]);
                let px = view.write_rgb8(w, h, now).ok_or_else(bad)?;
                then.render_rgb(&q, wu, hu, 3 * wu, px);
            }
            obs.joint_state = js;
            obs.assembled_ns = now;
            Ok(())
        };
        if settings.synchronous {
            // the executor's own requests are not used: the broker asks when the robot is done
            worker.discard_requests();
            if now >= next_sync_obs && !worker.has_pending() {
                observe(&mut obs)?;
                let mut c = policy
                    .compute(&obs, &InferenceRequest::default())?
                    .ok_or_else(|| anyhow::anyhow!("the policy gave no chunk"))?;
                out.chunks += 1;
                // the robot waits: the chunk starts when it arrives; s actions, then it holds
                // the last of them until the next chunk (which arrives after the delay)
                let ready = now + delay_ns;
                let keep = s.min(c.horizon());
                let last = c.action(keep - 1).to_vec();
                c.actions.truncate(keep * c.n_dof);
                for _ in 0..settings.delay_steps + 1 {
                    c.actions.extend_from_slice(&last);
                }
                c.t_obs_ns = ready;
                c.ready_ns = ready;
                next_sync_obs = ready + s as u64 * period_ns;
                worker.deliver_at_ready(c);
            }
        } else if let Some(req) = worker.next_request() {
            observe(&mut obs)?;
            // (a future-state chunk keeps its start shift: it was observed at `now` too)
            out.count_turn(worker.answer(now, req, policy, &obs))?;
        }
        worker.poll(now);

        let r = exec.tick(now, Some(&js), &mut cmd);
        if r.publish {
            js.position = cmd.position;
        }
        if r.state == State::Running {
            trace.push(&r.target, &cmd.position, None, r.switched);
        } else {
            out.off_tick(&mut trace, r.state);
        }
        if let Some(rec) = out.recording.as_mut() {
            if k % 10 == 0 {
                let mut q = [0.0; TASK_DOF];
                q.copy_from_slice(&js.position[..TASK_DOF]);
                rec.samples.push((t, q));
            }
            if r.switched {
                rec.switches.push(t);
            }
            if r.state == State::Running {
                let (mut target, mut command) = ([0.0; TASK_DOF], [0.0; TASK_DOF]);
                target.copy_from_slice(&r.target[..TASK_DOF]);
                command.copy_from_slice(&cmd.position[..TASK_DOF]);
                rec.ticks.push((t, target, command));
            }
        }
        let q = &js.position[..TASK_DOF];
        if let (Some((at, d0)), None) = (retargeted, out.reaction_time) {
            if scene.distance(q, other) >= d0 + REACTION_DISTANCE {
                out.reaction_time = Some(t - at);
            }
        }
        let d = scene.distance(q, goal);
        out.min_distance = out.min_distance.min(d);
        // (dynamic variant: only the target prompted after the retarget counts)
        let on =
            d <= super::REACH_TOLERANCE && (settings.retarget_at.is_none() || retargeted.is_some());
        on_since = if on { on_since.or(Some(t)) } else { None };
        let follow = settings.drift.map_or(0.0, |f| f.follow_s);
        if let Some(t0) = on_since.filter(|&t0| t - t0 >= follow) {
            out.success = true;
            // (following a drifting target: when it was reached for good)
            out.time_to_target = Some(t0);
            break;
        }
        if !out.wrong_target && scene.distance(q, other) <= super::REACH_TOLERANCE {
            out.wrong_target = true;
        }
    }
    out.smoothness = trace.smoothness();
    Ok(out)
}
