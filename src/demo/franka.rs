//! `chunkrt demo --config config/franka_fr3.toml`: the Franka FR3 through FCI, everything
//! started here as its own process: franka-sim (the FR3 in MuJoCo behind libfranka's wire
//! protocol, both FCI checks enforced: `tools/python/fr3_sim.py`), the driver (`chunkrt franka`),
//! the DROID camera views rendered from the joint states (`tools/python/franka_camera.py`), a
//! scripted DROID policy behind openpi's own server (`tools/python/droid_scripted.py`, a test
//! double; or `--remote URL` for a real π0.5-DROID server) and the controller (`chunkrt run`,
//! robot-clocked). A live line shows the controller's state and chunks beside the robot's
//! command success rate and its reflexes (the driver's and the simulator's own count); at the
//! end a table, `demo.md`, and `demo.png` (every joint's commanded and measured position, the
//! chunk switches).

use std::path::{Path, PathBuf};
use std::time::{Duration, Instant};

use chunkrt_ipc::services;
use chunkrt_ipc::{controller_state_name, ControllerStatus};
use chunkrt_tools::testing::summary_value;

use iceoryx2::node::Node;

use super::{live, spawn, stop, DemoArgs, Ports, Proc, Stack};

/// A configuration of the FR3: joints `fr3_joint1` … `fr3_joint7` (and the hand).
pub fn is_franka(cfg: &chunkrt_controller::config::Config) -> bool {
    let j = &cfg.robot.joints;
    (j.len() == 7 || j.len() == 8) && (0..7).all(|i| j[i].name == format!("fr3_joint{}", i + 1))
}

/// The franka venv's python and the offline FR3 model (scripts/franka-env.sh).
fn franka_env() -> anyhow::Result<(PathBuf, PathBuf)> {
    let (prefix, py) = crate::args::venv_python(
        "CHUNKRT_FRANKA_PREFIX",
        "chunkrt-franka",
        "CHUNKRT_FRANKA_PYTHON",
    );
    let model = std::env::var("FR3_MJCF")
        .map(PathBuf::from)
        .unwrap_or_else(|_| prefix.join("fr3_model/fr3.xml"));
    anyhow::ensure!(
        py.is_file() && model.is_file(),
        "the FR3 demo needs franka-sim and the FR3 model: bash scripts/franka-env.sh (looked for \
         {} and {})",
        py.display(),
        model.display()
    );
    Ok((py, model))
}

fn script(name: &str) -> PathBuf {
    chunkrt_learn::task::so101::sim_script().with_file_name(name)
}

/// The time series the plot draws: (s, commanded, measured) per joint.
#[derive(Default)]
struct Trace {
    t: Vec<f64>,
    cmd: Vec<[f64; 7]>,
    meas: Vec<[f64; 7]>,
    switches: Vec<f64>,
}

/// Runs the FR3 demo on `stack` for `args.episodes × args.episode_seconds`.
pub(crate) fn run(args: &DemoArgs, stack: &Stack) -> anyhow::Result<()> {
    let stop_flag = chunkrt_tools::shutdown::flag();
    let config = args.stack.config.as_ref().ok_or_else(|| {
        anyhow::anyhow!("the FR3 demo needs its configuration: --config config/franka_fr3.toml")
    })?;
    let (py, model) = franka_env()?;
    let seconds = args.episode_seconds * args.episodes.max(1) as f64;
    let host = "127.0.0.2";
    println!(
        "chunkrt demo: the Franka FR3 through FCI (franka-sim on {host}, both checks enforced), \
         {seconds:.0} s, namespace '{}', logs in {}",
        stack.ns,
        stack.log_dir.display()
    );
    let mut procs = start(stack, &py, &model, config, host)?;
    let node = services::node(&format!("chunkrt-demo-{}", std::process::id()))?;
    let mut watch = Watch::new(&node, stack)?;
    watch.run(seconds, stop_flag, &mut procs)?;
    let outs = stop_all(&mut procs);
    report(args, &outs, &watch.st, &watch.trace)
}

/// Starts franka-sim, the driver, the camera, the scripted DROID policy (unless the run has
/// `--remote`) and the controller, in this order; on a failure, stops those started.
fn start(
    stack: &Stack,
    py: &Path,
    model: &Path,
    config: &Path,
    host: &str,
) -> anyhow::Result<Vec<Proc>> {
    let mut procs: Vec<Proc> = Vec::new();
    if let Err(e) = spawn_all(&mut procs, stack, py, model, config, host) {
        for p in procs.iter_mut().rev() {
            stop(p, Duration::from_secs(3));
        }
        return Err(e);
    }
    Ok(procs)
}

fn spawn_all(
    procs: &mut Vec<Proc>,
    stack: &Stack,
    py: &Path,
    model: &Path,
    config: &Path,
    host: &str,
) -> anyhow::Result<()> {
    let s = |x: &Path| x.display().to_string();
    procs.push(spawn(
        py,
        "franka-sim",
        &[
            s(&script("fr3_sim.py")),
            "--host".into(),
            host.into(),
            "--model".into(),
            s(model),
        ],
        &stack.log_dir,
    )?);
    let drv = driver_args(stack, host);
    procs.push(spawn(&stack.exe, "franka-driver", &drv, &stack.log_dir)?);
    procs.push(spawn(
        py,
        "franka-camera",
        &[
            s(&script("franka_camera.py")),
            "--config".into(),
            s(config),
            "--namespace".into(),
            stack.ns.clone(),
            "--model".into(),
            s(model),
        ],
        &stack.log_dir,
    )?);
    let mut run_args = stack.run_args();
    if !run_args.iter().any(|a| a == "--remote") {
        let port = std::net::TcpListener::bind("127.0.0.1:0")?
            .local_addr()?
            .port();
        procs.push(spawn(
            Path::new("python3"),
            "droid-policy",
            &[
                s(&script("droid_scripted.py")),
                "--port".into(),
                port.to_string(),
            ],
            &stack.log_dir,
        )?);
        run_args.extend(["--remote".into(), format!("ws://127.0.0.1:{port}")]);
    }
    // the robot's first states (the simulator loads its model) before the controller
    std::thread::sleep(Duration::from_secs(3));
    procs.push(spawn(&stack.exe, "controller", &run_args, &stack.log_dir)?);
    Ok(())
}

/// `chunkrt franka`'s arguments: the robot at `host`, its status line every 0.5 s, its trace
/// in the log folder.
fn driver_args(stack: &Stack, host: &str) -> Vec<String> {
    let mut drv = stack.args("franka");
    drv.extend(
        [
            "--robot",
            host,
            "--realtime",
            "ignore",
            "--wait-for-robot",
            "30",
            "--status-every",
            "0.5",
        ]
        .map(String::from),
    );
    drv.extend([
        "--trace".into(),
        stack.log_dir.join("franka-trace.csv").display().to_string(),
    ]);
    drv
}

/// What the demo sees while it runs: the controller's status, the commanded and measured
/// joints (the plot's trace) and the chunk switches.
struct Watch {
    ports: Ports,
    st: ControllerStatus,
    trace: Trace,
    cmd: [f64; 7],
    meas: [f64; 7],
    chunk: u64,
}

impl Watch {
    fn new(node: &Node<services::Ipc>, stack: &Stack) -> anyhow::Result<Self> {
        let nsp = stack.cfg.namespace();
        let ports = Ports {
            status: services::subscriber(&services::status_service(node, &nsp.status())?)?,
            js: services::subscriber(&services::joint_state_service(node, &nsp.joint_state())?)?,
            cmd: services::subscriber(&services::joint_command_service(
                node,
                &nsp.joint_command(),
            )?)?,
        };
        Ok(Self {
            ports,
            st: ControllerStatus::default(),
            trace: Trace::default(),
            cmd: [0.0; 7],
            meas: [0.0; 7],
            chunk: 0,
        })
    }

    /// For `seconds` or until a stop: the live line; Err when a process exits early (every
    /// process stopped then).
    fn run(
        &mut self,
        seconds: f64,
        stop_flag: &std::sync::atomic::AtomicBool,
        procs: &mut [Proc],
    ) -> anyhow::Result<()> {
        let tty = std::io::IsTerminal::is_terminal(&std::io::stdout());
        let t0 = Instant::now();
        let mut last_line = -1.0;
        let driver_log = procs[1].log.clone();
        let sim_log = procs[0].log.clone();
        while t0.elapsed().as_secs_f64() < seconds
            && !stop_flag.load(std::sync::atomic::Ordering::Relaxed)
        {
            std::thread::sleep(Duration::from_millis(10));
            let now = t0.elapsed().as_secs_f64();
            self.receive(now);
            let line = self.line(now, &driver_log, &sim_log);
            live(&line, tty, &mut last_line, now);
            stop_if_one_exited(procs)?;
        }
        if tty {
            println!();
        }
        Ok(())
    }

    /// Takes what has arrived (a new chunk id is a switch at `now`) and samples the trace
    /// every 20 ms.
    fn receive(&mut self, now: f64) {
        while let Ok(Some(x)) = self.ports.status.receive() {
            self.st = *x.payload();
        }
        while let Ok(Some(x)) = self.ports.js.receive() {
            self.meas.copy_from_slice(&x.payload().position[..7]);
        }
        while let Ok(Some(x)) = self.ports.cmd.receive() {
            let c = x.payload();
            self.cmd.copy_from_slice(&c.position[..7]);
            if c.chunk_id != self.chunk && c.chunk_id != 0 {
                if self.chunk != 0 {
                    self.trace.switches.push(now);
                }
                self.chunk = c.chunk_id;
            }
        }
        let trace = &mut self.trace;
        if trace.t.last().is_none_or(|t| now - t >= 0.02) {
            trace.t.push(now);
            trace.cmd.push(self.cmd);
            trace.meas.push(self.meas);
        }
    }

    /// The live line: the controller's state and chunks, the driver's success rate, reflexes
    /// and guarded cycles, the simulator's reflexes.
    fn line(&self, now: f64, driver_log: &Path, sim_log: &Path) -> String {
        let st = &self.st;
        let drv = last_line_with(driver_log, "franka status:");
        let sim_reflexes = std::fs::read_to_string(sim_log)
            .map(|l| l.lines().filter(|l| l.contains("REFLEX")).count())
            .unwrap_or(0);
        format!(
            "[{now:>5.1}s] {:<8} chunks {:>3}  chunk latency {:>6.1} ms  success rate {:.3}  reflexes {} (simulator {})  guarded {}",
            controller_state_name(st.state),
            st.chunks,
            st.last_inference_latency_ns as f64 / 1e6,
            summary_value(&drv, "success_rate").unwrap_or(0.0),
            summary_value(&drv, "reflexes").unwrap_or(0.0),
            sim_reflexes,
            summary_value(&drv, "guarded").unwrap_or(0.0),
        )
    }
}

/// Err when a process has exited: every process stopped, the error quoting its log.
fn stop_if_one_exited(procs: &mut [Proc]) -> anyhow::Result<()> {
    let exited = procs
        .iter_mut()
        .position(|p| !matches!(p.child.try_wait(), Ok(None)));
    if let Some(i) = exited {
        let (name, log) = (procs[i].name, procs[i].log.clone());
        for p in procs.iter_mut().rev() {
            stop(p, Duration::from_secs(3));
        }
        anyhow::bail!(
            "{name} exited early; its log: {}\n{}",
            log.display(),
            std::fs::read_to_string(&log).unwrap_or_default()
        );
    }
    Ok(())
}

/// Stops every process: each one's name, how it stopped and its log.
fn stop_all(procs: &mut [Proc]) -> Vec<(&'static str, String, String)> {
    // the controller first (the driver stops the arm to rest), then the driver, then the rest
    let mut outs = Vec::new();
    for i in [4, 1, 2, 3, 0] {
        if let Some(p) = procs.get_mut(i) {
            let how = stop(p, Duration::from_secs(10));
            outs.push((
                p.name,
                how,
                std::fs::read_to_string(&p.log).unwrap_or_default(),
            ));
        }
    }
    outs
}

/// The end: how each process stopped, the summaries of the driver, the simulator and the
/// camera, the table (printed and `demo.md`) and `demo.png`.
fn report(
    args: &DemoArgs,
    outs: &[(&'static str, String, String)],
    st: &ControllerStatus,
    trace: &Trace,
) -> anyhow::Result<()> {
    let find = |name: &str, prefix: &str| {
        outs.iter()
            .find(|(n, _, _)| *n == name)
            .and_then(|(_, _, log)| {
                log.lines()
                    .rev()
                    .find(|l| l.starts_with(prefix))
                    .map(String::from)
            })
            .unwrap_or_default()
    };
    let drv = find("franka-driver", "franka summary:");
    let sim = find("franka-sim", "franka-sim summary:");
    let cam = find("franka-camera", "franka-camera summary:");
    for (name, how, _) in outs {
        println!("-- {name}: {how}");
    }
    println!("   {drv}\n   {sim}\n   {cam}");
    let md = table(st, &drv, &sim);
    println!("\n{md}");
    std::fs::create_dir_all(&args.out)?;
    std::fs::write(args.out.join("demo.md"), &md)?;
    let png = args.out.join("demo.png");
    let reflexes = summary_value(&drv, "reflexes").unwrap_or(f64::NAN);
    match plot(&png, trace, reflexes) {
        Ok(()) => println!(
            "report: {}  plot: {}",
            args.out.join("demo.md").display(),
            png.display()
        ),
        Err(e) => println!("no plot: {}", chunkrt_bench::report::plot_error_text(&e)),
    }
    anyhow::ensure!(!drv.is_empty(), "the driver printed no summary");
    Ok(())
}

/// The end's table (markdown) from the driver's and the simulator's summary lines.
fn table(st: &ControllerStatus, drv: &str, sim: &str) -> String {
    let v = |k: &str| summary_value(drv, k).unwrap_or(f64::NAN);
    format!(
        "| chunks | robot cycles | command success rate (mean / min) | reflexes (driver / simulator) | late / braking / guarded cycles | round trip p50 / p99 / max (µs) | tracking error max (rad) |\n\
         |---:|---:|---|---|---|---|---:|\n\
         | {} | {} | {:.5} / {:.3} | {} / {} | {} / {} / {} | {:.1} / {:.1} / {:.1} | {:.4} |\n",
        st.chunks,
        v("cycles"),
        v("success_rate_mean"),
        v("success_rate_min"),
        v("reflexes"),
        summary_value(sim, "reflexes").unwrap_or(f64::NAN),
        v("late"),
        v("braking"),
        v("clamped"),
        v("round_trip_p50_us"),
        v("round_trip_p99_us"),
        v("round_trip_max_us"),
        v("max_tracking_error"),
    )
}

/// The last line of `path` starting with `prefix` (empty if none yet).
fn last_line_with(path: &Path, prefix: &str) -> String {
    std::fs::read_to_string(path)
        .ok()
        .and_then(|l| {
            l.lines()
                .rev()
                .find(|l| l.starts_with(prefix))
                .map(String::from)
        })
        .unwrap_or_default()
}

/// Every joint's commanded (thin) and measured (thick) position, and the chunk switches.
fn plot(path: &Path, tr: &Trace, reflexes: f64) -> anyhow::Result<()> {
    use plotters::prelude::*;
    let err = |e: &dyn std::fmt::Display| anyhow::anyhow!("plot {}: {e}", path.display());
    let root = BitMapBackend::new(path, (1100, 520)).into_drawing_area();
    root.fill(&WHITE).map_err(|e| err(&e))?;
    let t_end = tr.t.last().copied().unwrap_or(1.0).max(1.0);
    let (lo, hi) = tr
        .meas
        .iter()
        .chain(&tr.cmd)
        .flat_map(|q| q.iter().copied())
        .filter(|v| *v != 0.0)
        .fold((f64::MAX, f64::MIN), |(a, b), v| (a.min(v), b.max(v)));
    let (lo, hi) = if lo < hi {
        (lo - 0.1, hi + 0.1)
    } else {
        (-3.0, 3.0)
    };
    let mut chart = ChartBuilder::on(&root)
        .caption(
            format!("FR3 through FCI (franka-sim, checks enforced): commanded (thin) and measured, {reflexes} reflexes"),
            ("sans-serif", 18),
        )
        .margin(10)
        .x_label_area_size(35)
        .y_label_area_size(50)
        .build_cartesian_2d(0f64..t_end, lo..hi)
        .map_err(|e| err(&e))?;
    chart
        .configure_mesh()
        .x_desc("time (s)")
        .y_desc("position (rad)")
        .draw()
        .map_err(|e| err(&e))?;
    chart
        .draw_series(
            tr.switches.iter().map(|&t| {
                PathElement::new(vec![(t, lo), (t, hi)], BLACK.mix(0.15).stroke_width(1))
            }),
        )
        .map_err(|e| err(&e))?
        .label("chunk switch")
        .legend(|(x, y)| PathElement::new(vec![(x, y), (x + 20, y)], BLACK.mix(0.3)));
    for j in 0..7 {
        let color = Palette99::pick(j).to_rgba();
        let pts = |q: &Vec<[f64; 7]>| -> Vec<(f64, f64)> {
            tr.t.iter()
                .zip(q)
                .filter(|(_, q)| q[j] != 0.0 || j == 0)
                .map(|(t, q)| (*t, q[j]))
                .collect()
        };
        chart
            .draw_series(LineSeries::new(pts(&tr.meas), color.stroke_width(3)))
            .map_err(|e| err(&e))?
            // Franka's own names (A1..A7); plotters 0.3.7 draws no 'j' in DejaVu Sans
            .label(format!("A{}", j + 1))
            .legend(move |(x, y)| {
                PathElement::new(vec![(x, y), (x + 20, y)], color.stroke_width(3))
            });
        chart
            .draw_series(LineSeries::new(
                pts(&tr.cmd),
                BLACK.mix(0.6).stroke_width(1),
            ))
            .map_err(|e| err(&e))?;
    }
    chart
        .configure_series_labels()
        .position(SeriesLabelPosition::UpperRight)
        .background_style(WHITE.mix(0.85))
        .border_style(BLACK)
        .label_font(("sans-serif", 12))
        .draw()
        .map_err(|e| err(&e))?;
    root.present().map_err(|e| err(&e))?;
    Ok(())
}
