//! `ScriptedChunkSource`: a **test double** for the policy (no model). It answers inference
//! requests with chunks that follow a known smooth reference trajectory plus a per-chunk bias
//! (so consecutive chunks disagree by a configurable jump), lands them after a configurable
//! latency, and — when a request is guided (RTC) — emulates guidance by blending the chunk
//! towards the request's prefix with the request's weights (W = 1 ⇒ the first d actions equal
//! what was executed). Used by the control tests and the benches, through the controller's
//! [`InferenceWorker`] like any chunk source.

use chunkrt_ipc::MAX_DOF;

use chunkrt_controller::chunk::ActionChunk;
use chunkrt_controller::contract::{ChunkSource, Observation};
use chunkrt_controller::control::{
    Continuation, Executor, ExecutorError, InferenceRequest, TickReport,
};
use chunkrt_controller::worker::{Delivery, InferenceWorker};

use crate::metrics::Trace;

/// Settings of the scripted source.
#[derive(Debug, Clone)]
pub struct ScriptedConfig {
    /// Joints per action.
    pub n_dof: usize,
    /// Actions per chunk (H).
    pub horizon: usize,
    /// Action period (ns).
    pub period_ns: u64,
    /// Observation → chunk ready (ns).
    pub latency_ns: u64,
    /// When not empty: chunk i lands after `latency_cycle_ns[i % len]` instead (a sweep of
    /// delays in one run).
    pub latency_cycle_ns: Vec<u64>,
    /// Bias of chunk c is `(-1)^c · jump` (rad) on every continuous joint.
    pub jump: f64,
    /// Joints that are step channels (toggle 0/1 every `step_period_s`).
    pub step: [bool; MAX_DOF],
    /// Period of the step channels' toggling (s).
    pub step_period_s: f64,
    /// The two values a step channel toggles between (default 0 and 1).
    pub step_low: [f64; MAX_DOF],
    pub step_high: [f64; MAX_DOF],
    /// Centre, amplitude (rad) and frequency (Hz) of each joint's sinusoid.
    pub centre: [f64; MAX_DOF],
    pub amplitude: [f64; MAX_DOF],
    pub frequency: [f64; MAX_DOF],
    /// Honour requests to continue the previous chunk (RTC emulation: guidance blends towards
    /// the prefix by its weights; a committed prefix is copied and the rows after it blended
    /// alike).
    pub emulate_guidance: bool,
}

impl ScriptedConfig {
    /// A source for the demo robot of `config/default.toml` (3 joints + gripper).
    pub fn demo(latency_ns: u64, jump: f64) -> Self {
        let mut c = Self {
            n_dof: 4,
            horizon: 50,
            period_ns: 20_000_000,
            latency_ns,
            latency_cycle_ns: Vec::new(),
            jump,
            step: [false; MAX_DOF],
            step_period_s: 1.3,
            step_low: [0.0; MAX_DOF],
            step_high: [1.0; MAX_DOF],
            centre: [0.0; MAX_DOF],
            amplitude: [0.0; MAX_DOF],
            frequency: [0.0; MAX_DOF],
            emulate_guidance: true,
        };
        c.step[3] = true;
        c.centre[..3].copy_from_slice(&[0.0, 1.2, 0.6]);
        c.amplitude[..3].copy_from_slice(&[0.5, 0.4, 0.6]);
        c.frequency[..3].copy_from_slice(&[0.3, 0.45, 0.6]);
        c
    }
}

/// The scripted policy (test double).
#[derive(Debug)]
pub struct ScriptedChunkSource {
    cfg: ScriptedConfig,
    next_id: u64,
    /// When set, the next chunk produced carries a NaN (watchdog tests).
    pub inject_nan: bool,
    /// While false, requests are ignored (missing-chunk tests).
    pub enabled: bool,
}

impl ScriptedChunkSource {
    /// A new source.
    pub fn new(cfg: ScriptedConfig) -> Self {
        Self {
            cfg,
            next_id: 1,
            inject_nan: false,
            enabled: true,
        }
    }

    /// The scripted test double for this robot (`policy.source = "scripted"`): each continuous
    /// joint a sinusoid around its initial position (amplitude at most a quarter of its range
    /// and inside it), step joints toggling between their limits' ends.
    pub fn for_robot(cfg: &chunkrt_controller::config::Config) -> Self {
        let s = &cfg.policy.scripted;
        let n = cfg.n_dof().min(MAX_DOF);
        let mut c = ScriptedConfig::demo((s.latency_ms * 1e6) as u64, s.jump);
        c.n_dof = n;
        c.horizon = s.horizon;
        c.period_ns = (1e9 / cfg.policy.action_rate_hz).round() as u64;
        c.latency_cycle_ns = s.delays.iter().map(|&d| d as u64 * c.period_ns).collect();
        c.step_period_s = s.step_period_s;
        c.step = [false; MAX_DOF];
        c.centre = [0.0; MAX_DOF];
        c.amplitude = [0.0; MAX_DOF];
        c.frequency = [0.0; MAX_DOF];
        for (j, joint) in cfg.robot.joints.iter().enumerate().take(n) {
            if joint.step {
                c.step[j] = true;
                c.step_low[j] = joint.position_min;
                c.step_high[j] = joint.position_max;
                continue;
            }
            let (lo, hi) = (joint.position_min, joint.position_max);
            let centre = joint.initial_position.clamp(lo, hi);
            let room = (centre - lo).min(hi - centre);
            c.centre[j] = centre;
            c.amplitude[j] = s.amplitude.min(0.25 * (hi - lo)).min(0.8 * room).max(0.0);
            c.frequency[j] = s.frequency_hz * (1.0 + 0.15 * j as f64);
        }
        Self::new(c)
    }

    /// The intended (reference) position of joint `j` at time `t_ns`.
    pub fn reference(&self, t_ns: u64, j: usize) -> f64 {
        let t = t_ns as f64 * 1e-9;
        if self.cfg.step[j] {
            if (t / self.cfg.step_period_s).floor() as i64 % 2 == 0 {
                self.cfg.step_low[j]
            } else {
                self.cfg.step_high[j]
            }
        } else {
            self.cfg.centre[j]
                + self.cfg.amplitude[j]
                    * (2.0 * std::f64::consts::PI * self.cfg.frequency[j] * t).sin()
        }
    }

    /// The reference of every joint at `t_ns`.
    pub fn reference_row(&self, t_ns: u64) -> [f64; MAX_DOF] {
        let mut r = [0.0; MAX_DOF];
        for (j, v) in r.iter_mut().enumerate().take(self.cfg.n_dof) {
            *v = self.reference(t_ns, j);
        }
        r
    }

    /// The "inference" for `req` with the observation captured at `req.t_ref_ns`; the chunk is
    /// ready `latency_ns` later (`ready_ns`: deliver it with [`crate::worker::Delivery::AtReady`]).
    /// None while disabled.
    pub fn chunk_for(&mut self, req: &InferenceRequest) -> Option<ActionChunk> {
        if !self.enabled {
            return None;
        }
        let (n, h, p) = (self.cfg.n_dof, self.cfg.horizon, self.cfg.period_ns);
        let t_obs = req.t_ref_ns;
        let id = self.next_id;
        self.next_id += 1;
        let bias = if id.is_multiple_of(2) {
            self.cfg.jump
        } else {
            -self.cfg.jump
        };
        let mut actions = vec![0.0; h * n];
        for k in 0..h {
            let t = t_obs + k as u64 * p;
            for j in 0..n {
                let mut v = self.reference(t, j);
                if !self.cfg.step[j] {
                    v += bias;
                    if self.cfg.emulate_guidance && k < req.horizon {
                        match req.continuation {
                            // a policy trained with a committed prefix starts with it
                            Continuation::Committed if k < req.delay_steps => {
                                v = req.prefix[k][j];
                            }
                            // guidance, and a trained policy's continuation of its committed
                            // prefix, emulated alike: a blend by the soft mask
                            Continuation::Guided | Continuation::Committed => {
                                let w = req.weights[k].clamp(0.0, 1.0);
                                v = w * req.prefix[k][j] + (1.0 - w) * v;
                            }
                            Continuation::Fresh => {}
                        }
                    }
                }
                actions[k * n + j] = v;
            }
        }
        if self.inject_nan {
            self.inject_nan = false;
            actions[n * (h / 2)] = f64::NAN;
        }
        Some(ActionChunk {
            id,
            observation_seq: id,
            t_obs_ns: t_obs,
            period_ns: p,
            n_dof: n,
            actions,
            ready_ns: t_obs
                + match self.cfg.latency_cycle_ns.len() {
                    0 => self.cfg.latency_ns,
                    n => self.cfg.latency_cycle_ns[(id as usize - 1) % n],
                },
            start_shift_ns: 0,
        })
    }
}

impl ChunkSource for ScriptedChunkSource {
    fn name(&self) -> &str {
        "scripted (test double)"
    }

    fn compute(
        &mut self,
        _obs: &Observation,
        request: &InferenceRequest,
    ) -> anyhow::Result<Option<ActionChunk>> {
        Ok(self.chunk_for(request))
    }
}

/// A closed-loop simulation around an [`Executor`] (test harness, allocates freely): the
/// [`ScriptedChunkSource`] plays the inference thread, a perfect robot reports the last command
/// as its joint state, and every tick is recorded into a [`Trace`] and a command log.
pub struct ScriptedSim {
    /// The executor under test.
    pub exec: Executor,
    /// The inference side of its hand-offs.
    pub worker: InferenceWorker,
    /// What the source is given (the scripted source does not look at it).
    pub observation: Observation,
    /// The scripted policy.
    pub source: ScriptedChunkSource,
    /// Joint state reported by the simulated robot.
    pub joint_state: chunkrt_ipc::JointState,
    /// When false, the robot stops reporting (its last state ages).
    pub robot_reports: bool,
    /// Simulated compute time recorded per tick (ns); above the period it counts as overrun.
    pub compute_ns: u64,
    /// Time of the next tick (ns).
    pub now_ns: u64,
    /// Control period (ns).
    pub period_ns: u64,
    /// Every published command.
    pub commands: Vec<chunkrt_ipc::JointCommand>,
    /// Every tick's report.
    pub reports: Vec<TickReport>,
    /// Target / command / reference per tick.
    pub trace: Trace,
}

impl ScriptedSim {
    /// A simulation of `config` fed by a scripted source; the robot starts at its configured
    /// initial positions at time `start_ns`.
    pub fn new(
        config: &chunkrt_controller::config::Config,
        source: ScriptedConfig,
        start_ns: u64,
    ) -> Result<Self, ExecutorError> {
        let exec = Executor::new(config)?;
        let worker = InferenceWorker::new(exec.connect(), Delivery::AtReady);
        let n = config.n_dof();
        let mut js = chunkrt_ipc::JointState {
            n_dof: n as u32,
            measurement_time_ns: start_ns,
            ..Default::default()
        };
        for (j, jc) in config.robot.joints.iter().enumerate().take(MAX_DOF) {
            js.position[j] = jc.initial_position;
        }
        let period_ns = config.control_period_ns();
        let mut trace = Trace::new(period_ns as f64 * 1e-9, n);
        for (j, jc) in config.robot.joints.iter().enumerate().take(MAX_DOF) {
            trace.skip[j] = jc.step;
        }
        Ok(Self {
            exec,
            worker,
            observation: Observation::new(config),
            source: ScriptedChunkSource::new(source),
            joint_state: js,
            robot_reports: true,
            compute_ns: 20_000,
            now_ns: start_ns,
            period_ns,
            commands: Vec::new(),
            reports: Vec::new(),
            trace,
        })
    }

    /// Runs one tick and returns its report.
    pub fn step(&mut self) -> TickReport {
        let now = self.now_ns;
        self.worker.step(now, &mut self.source, &self.observation);
        if self.robot_reports {
            self.joint_state.seq += 1;
            self.joint_state.measurement_time_ns = now;
            if let Some(c) = self.commands.last() {
                self.joint_state.position = c.position;
                self.joint_state.velocity = c.velocity;
            }
        }
        let mut cmd = chunkrt_ipc::JointCommand::default();
        let r = self.exec.tick(now, Some(&self.joint_state), &mut cmd);
        self.exec.record_timing(now, now, now + self.compute_ns);
        if r.publish {
            let reference = self.source.reference_row(now);
            self.trace
                .push(&r.target, &cmd.position, Some(&reference), r.switched);
            self.commands.push(cmd);
        }
        self.reports.push(r);
        self.now_ns += self.period_ns;
        r
    }

    /// Runs `n` ticks.
    pub fn run(&mut self, n: usize) {
        for _ in 0..n {
            self.step();
        }
    }
}
