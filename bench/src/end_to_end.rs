//! `end_to_end`: fake camera + simulated robot + controller with the real model, as three
//! processes over iceoryx2, watched from a fourth.
//!
//! The model is the π0.5 bench configuration (`benches/data/pi05_bench.json`: SigLIP 224/14 on
//! two cameras, Gemma 512 ×6, action expert 256, H = 50 at 50 Hz) with random weights written as
//! a checkpoint; `--small` uses the committed reach-task policy instead. Measured from the
//! published messages:
//! - the age of the observation behind each command: command publish time − measurement time of
//!   the joint state the chunk was computed from (the observation's capture time);
//! - chunk latency (observation → chunk ready, from the controller's status);
//! - commands per second (from the commands' own sequence numbers and clock);
//! - the share of commands served by a live chunk (position mode, chunk id set), and the share
//!   of status samples in HOLD.
//!
//! The summary line relates the commands per second to the configured control rate and the
//! observation age to the chunk latency, both measured in the same run.

use std::collections::{HashMap, VecDeque};
use std::path::PathBuf;
use std::time::{Duration, Instant};

use candle_nn::VarMap;

use chunkrt_ipc::services;
use chunkrt_ipc::{
    ControllerStatus, JointCommand, JointState, COMMAND_MODE_POSITION, CONTROLLER_STATE_HOLD,
};

use super::{write_outputs, BenchError, BenchOpts, Outputs};
use crate::report::{latency_histogram, LatencyTable, Series};

/// Options of one run.
#[derive(Debug, Clone)]
pub struct Options {
    pub bench: BenchOpts,
    /// The `chunkrt` executable (multi-call: fake-robot, fake-camera, run).
    pub exe: PathBuf,
    /// How long to measure after the first chunk.
    pub duration: Duration,
    /// Use the committed reach-task policy (64×64, one camera, 10 Hz) instead of the bench model.
    pub small: bool,
}

impl Options {
    /// 60 s (quick: 12 s) with the bench-sized model.
    pub fn new(bench: BenchOpts, exe: PathBuf) -> Self {
        let d = Duration::from_secs(if bench.quick { 12 } else { 60 });
        Self {
            bench,
            exe,
            duration: d,
            small: false,
        }
    }
}

/// What one run measured.
#[derive(Debug, Clone)]
pub struct Summary {
    pub model: String,
    pub control_rate_hz: f64,
    pub commands_per_s: f64,
    pub live_share: f64,
    pub hold_share: f64,
    pub chunks: u64,
    pub observation_age: crate::report::LatencyRow,
    pub chunk_latency: crate::report::LatencyRow,
    pub outputs: Outputs,
}

impl std::fmt::Display for Summary {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(
            f,
            "end_to_end ({}): {:.1} commands/s = {:.3}x the {:.0} Hz control rate; {:.1} % of commands \
             from a live chunk, {:.1} % of the time in HOLD; observation age p50 {:.1} ms = {:.2}x the \
             chunk latency p50 {:.1} ms ({} chunks)",
            self.model,
            self.commands_per_s,
            self.commands_per_s / self.control_rate_hz,
            self.control_rate_hz,
            100.0 * self.live_share,
            100.0 * self.hold_share,
            self.observation_age.p50_ns as f64 / 1e6,
            self.observation_age.p50_ns as f64 / self.chunk_latency.p50_ns.max(1) as f64,
            self.chunk_latency.p50_ns as f64 / 1e6,
            self.chunks
        )
    }
}

fn perr(what: &str, e: impl std::fmt::Display) -> BenchError {
    BenchError::Process {
        what: what.into(),
        reason: e.to_string(),
    }
}

/// Writes the bench-sized checkpoint (random weights) and the controller configuration; returns
/// the configuration path.
fn prepare(opts: &Options) -> Result<(PathBuf, String), BenchError> {
    let dir = &opts.bench.out_dir;
    std::fs::create_dir_all(dir).map_err(|e| perr("out dir", e))?;
    let mut t: toml::Table =
        toml::from_str(chunkrt_ipc::config::DEFAULT_TOML).map_err(|e| perr("default config", e))?;
    let model = if opts.small {
        let ck = crate::workspace_root().join("models/reach_pi05");
        t["policy"]["checkpoint"] = toml::Value::String(ck.display().to_string());
        "reach_pi05 (committed, 1.4 M parameters)".to_string()
    } else {
        let (_, json) = crate::inference::CONFIGS
            .iter()
            .find(|(n, _)| *n == "pi05_bench")
            .ok_or_else(|| perr("bench config", "pi05_bench missing"))?;
        let cfg = chunkrt_policy::config::ModelConfig::from_json_str(json)
            .map_err(|e| perr("pi05_bench.json", e))?;
        let ck = dir.join("ckpt_pi05_bench");
        std::fs::create_dir_all(&ck).map_err(|e| perr("checkpoint dir", e))?;
        let (_, vm): (_, VarMap) =
            crate::inference::random_model(&cfg).map_err(|e| perr("random model", e))?;
        vm.save(ck.join("model.safetensors"))
            .map_err(|e| perr("model.safetensors", e))?;
        std::fs::write(ck.join("config.json"), json).map_err(|e| perr("config.json", e))?;
        t["policy"]["checkpoint"] = toml::Value::String(ck.display().to_string());
        t["policy"]["action_rate_hz"] = toml::Value::Float(50.0);
        t["execution"]["execute_horizon"] = toml::Value::Integer(25);
        let cam = |name: &str| {
            let mut c = toml::Table::new();
            c.insert("name".into(), name.into());
            c.insert("width".into(), 224.into());
            c.insert("height".into(), 224.into());
            c.insert("fps".into(), 30.0.into());
            c.insert("encoding".into(), "rgb8".into());
            toml::Value::Table(c)
        };
        t["cameras"] = toml::Value::Array(vec![cam("base_0_rgb"), cam("left_wrist_0_rgb")]);
        format!(
            "pi05_bench (random weights, {:.1} M parameters)",
            vm.all_vars().iter().map(|v| v.elem_count()).sum::<usize>() as f64 / 1e6
        )
    };
    // late chunks must show up as HOLD time, not end the run in FAULT
    t["execution"]["hold_to_fault_ms"] = toml::Value::Float(600_000.0);
    t["execution"]["inference_timeout_ms"] = toml::Value::Float(60_000.0);
    let path = dir.join("end_to_end.toml");
    std::fs::write(&path, toml::to_string(&t).map_err(|e| perr("config", e))?)
        .map_err(|e| perr("end_to_end.toml", e))?;
    Ok((path, model))
}

/// Runs the bench.
pub fn run(opts: &Options) -> Result<Summary, BenchError> {
    let (cfg_path, model) = prepare(opts)?;
    let cfg = chunkrt_controller::config::Config::load(&cfg_path).map_err(|e| perr("config", e))?;
    let ns = format!("chunkrt/bench-e2e-{}", std::process::id());
    let exe = opts.exe.display().to_string();
    let cfg_arg = cfg_path.display().to_string();
    let spawn = |args: &[&str]| -> Result<chunkrt_tools::testing::ChildGuard, BenchError> {
        let mut all: Vec<&str> = args.to_vec();
        all.extend(["--namespace", &ns, "--config", &cfg_arg]);
        chunkrt_tools::testing::ChildGuard::spawn(&exe, &all).map_err(|e| perr(args[0], e))
    };
    let _robot = spawn(&["fake-robot"])?;
    let _camera = spawn(&["fake-camera"])?;
    let _ctl = spawn(&["run", "--log-every", "0"])?;

    let node = services::node(&format!("chunkrt-bench-e2e-{}", std::process::id()))?;
    let nsp = chunkrt_ipc::Namespace::new(&ns)?;
    let status = services::subscriber(&services::status_service(&node, &nsp.status())?)?;
    let js_sub = services::subscriber(&services::joint_state_service(&node, &nsp.joint_state())?)?;
    let cmd_sub = services::subscriber(&services::joint_command_service(
        &node,
        &nsp.joint_command(),
    )?)?;

    let mut measured: HashMap<u64, u64> = HashMap::new();
    let mut order: VecDeque<u64> = VecDeque::new();
    let mut age = latency_histogram();
    let mut latency = latency_histogram();
    let (mut live, mut received) = (0u64, 0u64);
    let (mut hold_samples, mut status_samples) = (0u64, 0u64);
    let mut first_cmd: Option<JointCommand> = None;
    let mut last_cmd: Option<JointCommand> = None;
    let mut last_status = ControllerStatus::default();
    let mut chunks_seen = 0u64;
    let started = Instant::now();
    let mut measuring_since: Option<Instant> = None;
    let warmup_limit = Duration::from_secs(if opts.bench.quick { 120 } else { 300 });
    loop {
        std::thread::sleep(Duration::from_micros(300));
        while let Ok(Some(s)) = js_sub.receive() {
            let m: &JointState = s.payload();
            measured.insert(m.seq, m.measurement_time_ns);
            order.push_back(m.seq);
            if order.len() > 60_000 {
                if let Some(old) = order.pop_front() {
                    measured.remove(&old);
                }
            }
        }
        while let Ok(Some(s)) = status.receive() {
            let st = *s.payload();
            if measuring_since.is_some() {
                status_samples += 1;
                hold_samples += (st.state == CONTROLLER_STATE_HOLD) as u64;
                if st.chunks > last_status.chunks && st.last_inference_latency_ns > 0 {
                    let _ = latency.record(st.last_inference_latency_ns);
                    chunks_seen += st.chunks - last_status.chunks;
                }
            }
            last_status = st;
        }
        while let Ok(Some(s)) = cmd_sub.receive() {
            let c = *s.payload();
            if measuring_since.is_none() {
                if c.chunk_id != 0 {
                    measuring_since = Some(Instant::now());
                    first_cmd = Some(c);
                }
                continue;
            }
            received += 1;
            if c.mode == COMMAND_MODE_POSITION && c.chunk_id != 0 {
                live += 1;
                if let Some(&t) = measured.get(&c.observation_seq) {
                    let _ = age.record(c.publish_time_ns.saturating_sub(t).max(1));
                }
            }
            last_cmd = Some(c);
        }
        match measuring_since {
            None if started.elapsed() > warmup_limit => {
                return Err(BenchError::Timeout(format!(
                    "no chunk from the controller within {} s",
                    warmup_limit.as_secs()
                )))
            }
            Some(t) if t.elapsed() >= opts.duration => break,
            _ => {}
        }
    }
    let (Some(a), Some(b)) = (first_cmd, last_cmd) else {
        return Err(BenchError::Timeout("no commands".into()));
    };
    let secs = b.publish_time_ns.saturating_sub(a.publish_time_ns) as f64 * 1e-9;
    let commands_per_s = (b.seq - a.seq) as f64 / secs.max(1e-9);
    let series = vec![
        Series::new("observation_age", age.clone()),
        Series::new("chunk_latency", latency.clone()),
    ];
    let table = LatencyTable::from_series(
        format!(
            "end_to_end: {model}, {:.0} s, {}",
            opts.duration.as_secs_f64(),
            super::machine_line()
        ),
        &series,
    );
    println!("{table}");
    let outputs = write_outputs(
        &opts.bench.out_dir,
        "end_to_end",
        &table,
        &series,
        &[(
            "end_to_end",
            "end to end: observation age behind each command, chunk latency",
            vec!["observation_age".into(), "chunk_latency".into()],
        )],
        opts.duration,
        &model,
    )?;
    let summary = Summary {
        model,
        control_rate_hz: cfg.control.rate_hz,
        commands_per_s,
        live_share: live as f64 / received.max(1) as f64,
        hold_share: hold_samples as f64 / status_samples.max(1) as f64,
        chunks: chunks_seen,
        observation_age: crate::report::LatencyRow::from_hist("observation_age", &age),
        chunk_latency: crate::report::LatencyRow::from_hist("chunk_latency", &latency),
        outputs,
    };
    println!("{}", summary.outputs);
    println!("{summary}");
    Ok(summary)
}
