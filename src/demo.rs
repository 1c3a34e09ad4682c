//! `chunkrt demo`: starts the fake camera, the simulated robot and the controller as separate
//! processes over real iceoryx2 services, shows a live status line, and stops them cleanly
//! after `--duration` or Ctrl-C with a summary.

use std::fs::File;
use std::io::Write;
use std::path::{Path, PathBuf};
use std::process::{Child, Command, Stdio};
use std::time::{Duration, Instant};

use anyhow::Context;

use chunkrt_ipc::services;
use chunkrt_ipc::{
    controller_state_name, monotonic_ns, ControllerStatus, JointState, RejectReason,
};

/// `chunkrt demo`.
#[derive(Debug, clap::Args)]
pub struct DemoArgs {
    /// Configuration file (default: the embedded demo robot).
    #[arg(long)]
    pub config: Option<PathBuf>,
    /// Seconds to run (Ctrl-C stops earlier).
    #[arg(long, default_value_t = 6.0)]
    pub duration: f64,
    /// Service namespace (default: `<robot.namespace>-<pid>`, so a demo never collides with
    /// another running chunkrt).
    #[arg(long)]
    pub namespace: Option<String>,
    /// Where the processes' logs go (default: a temporary folder).
    #[arg(long)]
    pub log_dir: Option<PathBuf>,
}

struct Proc {
    name: &'static str,
    child: Child,
    log: PathBuf,
}

fn spawn(exe: &Path, name: &'static str, args: &[String], log_dir: &Path) -> anyhow::Result<Proc> {
    let log = log_dir.join(format!("{name}.log"));
    let out = File::create(&log).with_context(|| format!("cannot create {}", log.display()))?;
    let err = out.try_clone()?;
    let child = Command::new(exe)
        .args(args)
        .stdin(Stdio::null())
        .stdout(out)
        .stderr(err)
        .spawn()
        .with_context(|| format!("cannot start {name} ({})", exe.display()))?;
    Ok(Proc { name, child, log })
}

fn stop(p: &mut Proc, timeout: Duration) -> String {
    // SIGINT first: every chunkrt process stops cleanly on it and prints its summary
    // SAFETY: plain kill(2) on our own child's pid.
    unsafe { libc::kill(p.child.id() as libc::pid_t, libc::SIGINT) };
    let t0 = Instant::now();
    loop {
        match p.child.try_wait() {
            Ok(Some(st)) => {
                return if st.success() {
                    "exited cleanly".into()
                } else {
                    format!("exited with {st}")
                }
            }
            Ok(None) if t0.elapsed() < timeout => std::thread::sleep(Duration::from_millis(20)),
            _ => {
                let _ = p.child.kill();
                let _ = p.child.wait();
                return "killed after timeout".into();
            }
        }
    }
}

/// Runs the demo.
pub fn run(args: DemoArgs) -> anyhow::Result<()> {
    let stop_flag = chunkrt_tools::shutdown::flag();
    let cfg = crate::controller::load_config(args.config.as_ref(), None)?;
    let ns = args
        .namespace
        .clone()
        .unwrap_or_else(|| format!("{}-{}", cfg.robot.namespace, std::process::id()));
    let cfg = crate::controller::load_config(args.config.as_ref(), Some(&ns))?;
    let exe = std::env::current_exe().context("cannot find the chunkrt executable")?;
    let log_dir = args.log_dir.clone().unwrap_or_else(|| {
        std::env::temp_dir().join(format!("chunkrt-demo-{}", std::process::id()))
    });
    std::fs::create_dir_all(&log_dir)
        .with_context(|| format!("cannot create {}", log_dir.display()))?;

    let mut common = vec!["--namespace".to_string(), ns.clone()];
    if let Some(c) = &args.config {
        common.extend(["--config".to_string(), c.display().to_string()]);
    }
    let with = |sub: &str| {
        let mut v = vec![sub.to_string()];
        v.extend(common.iter().cloned());
        v
    };
    println!(
        "chunkrt demo: robot '{}' ({} joints), {} camera(s), namespace '{ns}', logs in {}",
        cfg.robot.name,
        cfg.n_dof(),
        cfg.cameras.len(),
        log_dir.display()
    );
    let mut procs = vec![
        spawn(&exe, "fake-robot", &with("fake-robot"), &log_dir)?,
        spawn(&exe, "fake-camera", &with("fake-camera"), &log_dir)?,
    ];
    let mut run_args = with("run");
    run_args.extend(["--log-every".into(), "0".into()]);
    procs.push(spawn(&exe, "controller", &run_args, &log_dir)?);

    let node = services::node(&format!("chunkrt-demo-{}", std::process::id()))?;
    let nsp = cfg.namespace();
    let status_sub = services::subscriber(
        &services::status_service(&node, &nsp.status())?,
        &nsp.status(),
    )?;
    let js_sub = services::subscriber(
        &services::joint_state_service(&node, &nsp.joint_state())?,
        &nsp.joint_state(),
    )?;

    let started = Instant::now();
    let mut status = ControllerStatus::default();
    let mut js = JointState::default();
    let mut first_js: Option<JointState> = None;
    let mut early_exit = None;
    let tty = std::io::IsTerminal::is_terminal(&std::io::stdout());
    let mut last_line = -1.0f64;
    while started.elapsed().as_secs_f64() < args.duration
        && !stop_flag.load(std::sync::atomic::Ordering::Relaxed)
    {
        std::thread::sleep(Duration::from_millis(100));
        while let Ok(Some(s)) = status_sub.receive() {
            status = *s.payload();
        }
        while let Ok(Some(s)) = js_sub.receive() {
            js = *s.payload();
            if first_js.is_none() {
                first_js = Some(js);
            }
        }
        if let Some(p) = procs
            .iter_mut()
            .find_map(|p| (!matches!(p.child.try_wait(), Ok(None))).then_some(p.name))
        {
            early_exit = Some(p);
            break;
        }
        let n = (js.n_dof as usize).min(chunkrt_ipc::MAX_DOF);
        let pos: Vec<String> = js.position[..n]
            .iter()
            .map(|p| format!("{p:+.3}"))
            .collect();
        let age_ms = if js.measurement_time_ns == 0 {
            f64::NAN
        } else {
            monotonic_ns().saturating_sub(js.measurement_time_ns) as f64 / 1e6
        };
        let line = format!(
            "[{:>5.1}s] {:<8} ticks {:>6} overruns {:>3} lateness p99 {:>6.0} us  q=[{}] age {:.1} ms   ",
            started.elapsed().as_secs_f64(),
            controller_state_name(status.state),
            status.ticks,
            status.overruns,
            status.lateness_p99_ns as f64 / 1e3,
            pos.join(" "),
            age_ms,
        );
        if tty {
            print!("\r{line}");
            let _ = std::io::stdout().flush();
        } else if (started.elapsed().as_secs_f64() - last_line).abs() >= 1.0 {
            println!("{line}");
            last_line = started.elapsed().as_secs_f64().floor();
        }
    }
    println!();
    // stop the controller first, so the robot sees commands stop and holds by itself
    let mut outcomes = Vec::new();
    for i in [2usize, 1, 0] {
        let p = &mut procs[i];
        let how = stop(p, Duration::from_secs(5));
        outcomes.push((p.name, how, p.log.clone()));
    }
    println!("\n== summary ({:.1} s) ==", started.elapsed().as_secs_f64());
    for (name, how, log) in &outcomes {
        println!("-- {name}: {how}");
        let text = std::fs::read_to_string(log).unwrap_or_default();
        for line in text.lines().filter(|l| {
            !l.contains(" INFO ") || l.contains("summary") || l.contains("control thread")
        }) {
            println!("   {line}");
        }
    }
    if status.ticks > 0 {
        let rejected: u64 = status.rejected.iter().sum();
        println!(
            "controller: {} ticks, {} overruns, {} joint states, {} frames, {} rejected ({})",
            status.ticks,
            status.overruns,
            status.joint_states,
            status.frames,
            rejected,
            RejectReason::ALL
                .iter()
                .map(|r| format!("{}={}", r.name(), status.rejected[r.code()]))
                .collect::<Vec<_>>()
                .join(" ")
        );
    }
    if let (Some(a), true) = (first_js, js.n_dof > 0) {
        let n = (js.n_dof as usize).min(chunkrt_ipc::MAX_DOF);
        let drift = (0..n)
            .map(|i| (js.position[i] - a.position[i]).abs())
            .fold(0.0, f64::max);
        println!("robot drift while held: {drift:.2e} rad (max over joints)");
    }
    if let Some(name) = early_exit {
        anyhow::bail!("{name} exited early; see its log above");
    }
    Ok(())
}
