//! `chunkrt soak`: the demo stack (simulated robot, fake camera, controller with the
//! configured policy) for a long run, and the figures to check before trusting the controller
//! on an arm: commands per second, overruns, wake-up lateness percentiles, HOLD entries,
//! rejected messages by reason, and each process's resident memory and open file descriptors
//! at the start and at the end.
//!
//! Every process runs as in `chunkrt demo`; the controller keeps computing chunks for the
//! whole run (its inference load is what the control thread has to withstand). In a soak
//! nothing is malformed or forged, so every rejection counts as a false one.

use std::path::PathBuf;
use std::time::{Duration, Instant};

use anyhow::Context;

use chunkrt_ipc::services;
use chunkrt_ipc::{controller_state_name, ControllerStatus, JointCommand, RejectReason};

use crate::demo::{spawn, stop, Proc};
use crate::report::fmt_us;

/// `chunkrt soak`.
#[derive(Debug, clap::Args)]
pub struct SoakArgs {
    /// The processes: configuration, scene, namespace, logs, remote policy.
    #[command(flatten)]
    pub stack: crate::demo::StackArgs,
    /// Seconds to run after the warm-up (Ctrl-C ends earlier and still prints the summary).
    #[arg(long, default_value_t = 600.0)]
    pub duration: f64,
    /// Seconds after the controller is RUNNING before the start figures (RSS, fds, counters)
    /// are taken: loading and first allocations are not growth.
    #[arg(long, default_value_t = 5.0)]
    pub warmup: f64,
    /// Prompt (default: the configuration's).
    #[arg(long)]
    pub prompt: Option<String>,
    /// Where the summary (soak.md) and the controller's histogram log go.
    #[arg(long, default_value = "target/chunkrt-soak")]
    pub out: PathBuf,
    /// The chunkrt binary whose robot, camera and controller are soaked (default: this one),
    /// to compare two builds on the same machine with the same measurement.
    #[arg(long, value_name = "PATH")]
    pub exe: Option<PathBuf>,
    /// Seconds of `cyclictest` right after the soak, on the control thread's core at its
    /// priority and rate, with the whole stack still running: the platform's floor in the same
    /// hour, against which the soak's overruns are a ratio (0: none; skipped with a note when
    /// cyclictest is not installed).
    #[arg(long, value_name = "SECONDS", default_value_t = 120.0)]
    pub floor: f64,
}

/// `cyclictest` beside the soak ([`SoakArgs::floor`]).
#[derive(Debug, Clone, Default)]
pub struct Floor {
    /// Wake-ups measured.
    pub loops: u64,
    /// Wake-ups a period or more late (the ones that would be an overrun).
    pub late: u64,
    /// Wake-up latency p99 / max (µs).
    pub p99_us: f64,
    pub max_us: f64,
    /// The command that ran.
    pub command: String,
}

impl Floor {
    /// Late share of the wake-ups (%).
    pub fn late_percent(&self) -> f64 {
        100.0 * self.late as f64 / self.loops.max(1) as f64
    }
}

/// Resident memory and descriptors of one process, from `/proc`.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct ProcStats {
    /// Resident set size (kB).
    pub rss_kb: u64,
    /// Open file descriptors.
    pub fds: usize,
    /// Threads.
    pub threads: u64,
}

/// Reads `/proc/<pid>/status` and `/proc/<pid>/fd`; `None` once the process is gone.
pub fn proc_stats(pid: u32) -> Option<ProcStats> {
    let status = std::fs::read_to_string(format!("/proc/{pid}/status")).ok()?;
    let field = |key: &str| {
        status
            .lines()
            .find_map(|l| l.strip_prefix(key))
            .and_then(|v| v.split_whitespace().next())
            .and_then(|v| v.parse::<u64>().ok())
    };
    let fds = std::fs::read_dir(format!("/proc/{pid}/fd")).ok()?.count();
    Some(ProcStats {
        rss_kb: field("VmRSS:")?,
        fds,
        threads: field("Threads:").unwrap_or(0),
    })
}

/// CPU time the hypervisor gave to other guests (`steal` in `/proc/stat`, clock ticks) and
/// the total of all CPU time fields: a wake-up that is late while steal rises was delayed
/// outside this machine.
pub fn cpu_steal_ticks() -> Option<(u64, u64)> {
    let stat = std::fs::read_to_string("/proc/stat").ok()?;
    let line = stat.lines().find(|l| l.starts_with("cpu "))?;
    let v: Vec<u64> = line
        .split_whitespace()
        .skip(1)
        .filter_map(|x| x.parse().ok())
        .collect();
    Some((*v.get(7)?, v.iter().sum()))
}

/// Involuntary context switches of the thread called `name` in process `pid` (how often
/// something took its core away from it).
pub fn thread_preemptions(pid: u32, name: &str) -> Option<u64> {
    for t in std::fs::read_dir(format!("/proc/{pid}/task"))
        .ok()?
        .flatten()
    {
        let comm = std::fs::read_to_string(t.path().join("comm")).unwrap_or_default();
        if comm.trim() == name {
            let status = std::fs::read_to_string(t.path().join("status")).ok()?;
            return status
                .lines()
                .find_map(|l| l.strip_prefix("nonvoluntary_ctxt_switches:"))
                .and_then(|v| v.trim().parse().ok());
        }
    }
    None
}

/// Counters of the run between the start and the end snapshot.
#[derive(Debug, Clone, Default)]
pub struct SoakFigures {
    /// Seconds between the snapshots.
    pub seconds: f64,
    /// Commands the controller published (its sequence numbers) and the soak received.
    pub commands_published: u64,
    /// Commands that reached the soak's own subscriber.
    pub commands_received: u64,
    /// Control ticks and overruns.
    pub ticks: u64,
    /// See `ticks`.
    pub overruns: u64,
    /// HOLD entries.
    pub holds: u64,
    /// Chunks computed.
    pub chunks: u64,
    /// Rejections by reason code.
    pub rejected: [u64; chunkrt_ipc::REJECT_REASON_COUNT],
    /// The controller's status at the end (lateness and tick quantiles over the whole run).
    pub status: ControllerStatus,
    /// Share of all CPU time stolen by the hypervisor during the run (%), if known.
    pub steal_percent: Option<f64>,
    /// Involuntary context switches of the control thread during the run, if known.
    pub control_preemptions: Option<u64>,
    /// The platform's floor measured right after ([`SoakArgs::floor`]), or why not.
    pub floor: Option<Result<Floor, String>>,
}

impl SoakFigures {
    fn between(a: &ControllerStatus, b: &ControllerStatus, seconds: f64) -> Self {
        let mut rejected = [0; chunkrt_ipc::REJECT_REASON_COUNT];
        for (i, r) in rejected.iter_mut().enumerate() {
            *r = b.rejected[i].saturating_sub(a.rejected[i]);
        }
        Self {
            seconds,
            ticks: b.ticks.saturating_sub(a.ticks),
            overruns: b.overruns.saturating_sub(a.overruns),
            holds: b.hold_entries.saturating_sub(a.hold_entries),
            chunks: b.chunks.saturating_sub(a.chunks),
            rejected,
            status: *b,
            ..Default::default()
        }
    }

    /// Overrun share of the ticks (%).
    pub fn overrun_percent(&self) -> f64 {
        100.0 * self.overruns as f64 / self.ticks.max(1) as f64
    }
}

struct Watch {
    status: iceoryx2::port::subscriber::Subscriber<services::Ipc, ControllerStatus, ()>,
    cmd: iceoryx2::port::subscriber::Subscriber<services::Ipc, JointCommand, ()>,
    last: ControllerStatus,
    first_cmd_seq: Option<u64>,
    last_cmd_seq: u64,
    received: u64,
}

impl Watch {
    fn poll(&mut self) {
        while let Ok(Some(s)) = self.status.receive() {
            self.last = *s.payload();
        }
        while let Ok(Some(s)) = self.cmd.receive() {
            let seq = s.payload().seq;
            self.first_cmd_seq.get_or_insert(seq);
            self.last_cmd_seq = self.last_cmd_seq.max(seq);
            self.received += 1;
        }
    }
}

fn kb_delta(a: u64, b: u64) -> String {
    format!("{:+.1} MB", (b as f64 - a as f64) / 1024.0)
}

/// Runs the soak.
pub fn run(args: SoakArgs) -> anyhow::Result<()> {
    anyhow::ensure!(
        args.duration.is_finite()
            && args.duration > 0.0
            && args.warmup.is_finite()
            && args.warmup >= 0.0,
        "--duration must be > 0 and --warmup >= 0 seconds"
    );
    let stop_flag = chunkrt_tools::shutdown::flag();
    let stack = args.stack.prepare("soak", args.exe.as_ref())?;
    let (cfg, ns, exe, log_dir) = (&stack.cfg, &stack.ns, &stack.exe, &stack.log_dir);
    std::fs::create_dir_all(&args.out)
        .with_context(|| format!("cannot create {}", args.out.display()))?;
    let hlog = args.out.join("soak.hlog");
    let cam_args = stack.camera_args();
    let mut run_args = stack.run_args();
    run_args.extend(["--histogram-log".into(), hlog.display().to_string()]);
    if let Some(p) = &args.prompt {
        run_args.extend(["--prompt".into(), p.clone()]);
    }
    println!(
        "chunkrt soak: robot '{}' at {} Hz, policy '{}' on {}, {:.0} s after {:.0} s warm-up, namespace '{ns}', logs in {}",
        cfg.robot.name,
        cfg.control.rate_hz,
        cfg.policy.kind_name(),
        cfg.policy.device,
        args.duration,
        args.warmup,
        log_dir.display()
    );
    let mut procs: Vec<Proc> = vec![
        spawn(exe, "fake-robot", &stack.args("fake-robot"), log_dir)?,
        spawn(exe, "fake-camera", &cam_args, log_dir)?,
    ];
    // stopped last (the list is stopped from its end), started before the controller
    if let Some(r) = stack.spawn_recorder(args.prompt.as_deref().unwrap_or(&cfg.policy.prompt))? {
        procs.insert(0, r);
    }
    procs.push(spawn(exe, "controller", &run_args, log_dir)?);
    let result = follow(&args, cfg, &mut procs, stop_flag);
    let mut outcomes = Vec::new();
    // the controller first, so its summary and histogram log are complete
    for p in procs.iter_mut().rev() {
        outcomes.push((p.name, stop(p, Duration::from_secs(10)), p.log.clone()));
    }
    let (figures, stats) = match result {
        Ok(v) => v,
        Err(e) => {
            for (name, how, log) in &outcomes {
                eprintln!("-- {name}: {how} (log {})", log.display());
            }
            return Err(e);
        }
    };
    let md = summary_markdown(cfg, &figures, &stats, &outcomes);
    println!("\n{md}");
    std::fs::write(args.out.join("soak.md"), &md)?;
    println!(
        "summary: {}  histograms (chunkrt report): {}",
        args.out.join("soak.md").display(),
        hlog.display()
    );
    Ok(())
}

type Stats = Vec<(&'static str, ProcStats, ProcStats)>;

fn follow(
    args: &SoakArgs,
    cfg: &chunkrt_controller::config::Config,
    procs: &mut [Proc],
    stop_flag: &std::sync::atomic::AtomicBool,
) -> anyhow::Result<(SoakFigures, Stats)> {
    let node = services::node(&format!("chunkrt-soak-{}", std::process::id()))?;
    let nsp = cfg.namespace();
    let mut w = Watch {
        status: services::subscriber(&services::status_service(&node, &nsp.status())?)?,
        cmd: services::subscriber(&services::joint_command_service(
            &node,
            &nsp.joint_command(),
        )?)?,
        last: ControllerStatus::default(),
        first_cmd_seq: None,
        last_cmd_seq: 0,
        received: 0,
    };
    let tty = std::io::IsTerminal::is_terminal(&std::io::stdout());
    let t0 = Instant::now();
    let exited = |procs: &mut [Proc]| {
        procs
            .iter_mut()
            .find_map(|p| (!matches!(p.child.try_wait(), Ok(None))).then_some(p.name))
    };
    // warm-up: until the controller runs, then `warmup` seconds more
    let mut running_at: Option<Instant> = None;
    loop {
        std::thread::sleep(Duration::from_millis(2));
        w.poll();
        if let Some(p) = exited(procs) {
            anyhow::bail!("{p} exited during the warm-up; see its log");
        }
        if stop_flag.load(std::sync::atomic::Ordering::Relaxed) {
            anyhow::bail!("interrupted during the warm-up");
        }
        if running_at.is_none() && w.last.state == chunkrt_ipc::CONTROLLER_STATE_RUNNING {
            running_at = Some(Instant::now());
        }
        if running_at.is_some_and(|t| t.elapsed().as_secs_f64() >= args.warmup) {
            break;
        }
        anyhow::ensure!(
            t0.elapsed() < Duration::from_secs(120),
            "the controller did not reach RUNNING within 120 s (state {})",
            controller_state_name(w.last.state)
        );
    }
    let start_stats: Vec<ProcStats> = procs
        .iter()
        .map(|p| proc_stats(p.child.id()).unwrap_or_default())
        .collect();
    let ctl_pid = procs.last().map(|p| p.child.id()).unwrap_or(0);
    let start_steal = cpu_steal_ticks();
    let start_preempt = thread_preemptions(ctl_pid, "chunkrt-control");
    let start_status = w.last;
    let start_seq = w.last_cmd_seq;
    let start_received = w.received;
    let t_start = Instant::now();
    let mut last_line = Instant::now();
    let mut last_seq = start_seq;
    loop {
        std::thread::sleep(Duration::from_millis(2));
        w.poll();
        let el = t_start.elapsed().as_secs_f64();
        if last_line.elapsed() >= Duration::from_secs(1) {
            let rate = (w.last_cmd_seq - last_seq) as f64 / last_line.elapsed().as_secs_f64();
            last_seq = w.last_cmd_seq;
            last_line = Instant::now();
            let st = &w.last;
            let ctl = procs
                .last()
                .and_then(|p| proc_stats(p.child.id()))
                .unwrap_or_default();
            let line = format!(
                "[{el:>5.0}/{:.0} s] {:<8} {rate:>6.0} cmd/s  overruns {} ({:.3} %)  lateness p99 {} us max {} us  holds {}  chunks {}  rejected {}  controller RSS {:.1} MB fds {}",
                args.duration,
                controller_state_name(st.state),
                st.overruns.saturating_sub(start_status.overruns),
                100.0 * st.overruns.saturating_sub(start_status.overruns) as f64
                    / st.ticks.saturating_sub(start_status.ticks).max(1) as f64,
                fmt_us(st.lateness_p99_ns),
                fmt_us(st.lateness_max_ns),
                st.hold_entries.saturating_sub(start_status.hold_entries),
                st.chunks,
                st.rejected.iter().sum::<u64>() - start_status.rejected.iter().sum::<u64>(),
                ctl.rss_kb as f64 / 1024.0,
                ctl.fds
            );
            if tty {
                print!("\r{line}\x1b[K");
                let _ = std::io::Write::flush(&mut std::io::stdout());
            } else if (el as u64).is_multiple_of(10) {
                println!("{line}");
            }
        }
        if let Some(p) = exited(procs) {
            anyhow::bail!("{p} exited during the soak after {el:.0} s; see its log");
        }
        if el >= args.duration || stop_flag.load(std::sync::atomic::Ordering::Relaxed) {
            break;
        }
    }
    if tty {
        println!();
    }
    let end_stats: Vec<ProcStats> = procs
        .iter()
        .map(|p| proc_stats(p.child.id()).unwrap_or_default())
        .collect();
    let seconds = t_start.elapsed().as_secs_f64();
    let mut fig = SoakFigures::between(&start_status, &w.last, seconds);
    if let (Some((s0, t0)), Some((s1, t1))) = (start_steal, cpu_steal_ticks()) {
        fig.steal_percent =
            Some(100.0 * s1.saturating_sub(s0) as f64 / t1.saturating_sub(t0).max(1) as f64);
    }
    if let (Some(a), Some(b)) = (
        start_preempt,
        thread_preemptions(ctl_pid, "chunkrt-control"),
    ) {
        fig.control_preemptions = Some(b.saturating_sub(a));
    }
    fig.commands_published = w.last_cmd_seq.saturating_sub(start_seq);
    fig.commands_received = w.received - start_received;
    if args.floor > 0.0 && !stop_flag.load(std::sync::atomic::Ordering::Relaxed) {
        fig.floor = Some(platform_floor(cfg, args.floor));
    }
    let stats = procs
        .iter()
        .zip(start_stats.into_iter().zip(end_stats))
        .map(|(p, (a, b))| (p.name, a, b))
        .collect();
    Ok((fig, stats))
}

/// `cyclictest` on the control thread's core, at its priority and period, for `seconds`, while
/// the stack runs on: the share of wake-ups a period or more late, the figure a soak's overrun
/// share is compared with.
fn platform_floor(cfg: &chunkrt_controller::config::Config, seconds: f64) -> Result<Floor, String> {
    if !chunkrt_bench::cyclictest::available() {
        return Err("cyclictest is not installed (apt-get install rt-tests)".into());
    }
    let period_us = (1e6 / cfg.control.rate_hz).round().max(1.0) as u64;
    let core = cfg
        .control
        .cpu
        .unwrap_or_else(chunkrt_controller::rt::default_control_core);
    let loops = ((seconds * 1e6) / period_us as f64).round().max(1.0) as u64;
    println!(
        "platform floor: cyclictest on core {core} at SCHED_FIFO {} every {period_us} µs for {seconds:.0} s, the stack still running ...",
        cfg.control.realtime_priority
    );
    let r = chunkrt_bench::cyclictest::run(&chunkrt_bench::cyclictest::CyclictestConfig {
        interval_us: period_us,
        loops,
        core: Some(core),
        priority: (cfg.control.realtime_priority > 0).then_some(cfg.control.realtime_priority),
        hist_max_us: period_us,
    })
    .map_err(|e| e.to_string())?;
    let measured = r.latency.len().max(1);
    Ok(Floor {
        loops: measured,
        late: r.overflows,
        p99_us: r.latency.value_at_quantile(0.99) as f64 / 1e3,
        max_us: r.max_us as f64,
        command: r.command,
    })
}

fn summary_markdown(
    cfg: &chunkrt_controller::config::Config,
    f: &SoakFigures,
    stats: &Stats,
    outcomes: &[(&'static str, String, PathBuf)],
) -> String {
    let st = &f.status;
    let mut md = format!(
        "## chunkrt soak: {:.0} s, robot '{}' at {} Hz, policy '{}' ({})\n\n",
        f.seconds,
        cfg.robot.name,
        cfg.control.rate_hz,
        cfg.policy.kind_name(),
        cfg.policy.device
    );
    md.push_str("| figure | value |\n|---|---:|\n");
    let mut row = |k: &str, v: String| md.push_str(&format!("| {k} | {v} |\n"));
    row(
        "commands/s (published / received by the soak)",
        format!(
            "{:.1} / {:.1}",
            f.commands_published as f64 / f.seconds,
            f.commands_received as f64 / f.seconds
        ),
    );
    row("ticks", f.ticks.to_string());
    row(
        "overruns",
        format!("{} ({:.3} %)", f.overruns, f.overrun_percent()),
    );
    row(
        "lateness p50 / p99 / max (µs, whole run)",
        format!(
            "{} / {} / {}",
            fmt_us(st.lateness_p50_ns),
            fmt_us(st.lateness_p99_ns),
            fmt_us(st.lateness_max_ns)
        ),
    );
    row(
        "tick p50 / p99 / max (µs, whole run)",
        format!(
            "{} / {} / {}",
            fmt_us(st.compute_p50_ns),
            fmt_us(st.compute_p99_ns),
            fmt_us(st.compute_max_ns)
        ),
    );
    row("HOLD entries", f.holds.to_string());
    row("chunks", f.chunks.to_string());
    let rejected: Vec<String> = RejectReason::ALL
        .iter()
        .filter(|r| f.rejected[r.code()] > 0)
        .map(|r| format!("{}={}", r.name(), f.rejected[r.code()]))
        .collect();
    row(
        "rejected (all false in a soak)",
        if rejected.is_empty() {
            "0".to_string()
        } else {
            rejected.join(" ")
        },
    );
    row(
        "control thread preempted (involuntary switches)",
        f.control_preemptions
            .map(|v| v.to_string())
            .unwrap_or_else(|| "unknown".into()),
    );
    row(
        "CPU time stolen by the hypervisor",
        f.steal_percent
            .map(|v| format!("{v:.3} %"))
            .unwrap_or_else(|| "unknown".into()),
    );
    match &f.floor {
        Some(Ok(fl)) => {
            row(
                "platform floor: cyclictest late ≥ 1 period, same core, stack running",
                format!(
                    "{} of {} ({:.3} %), p99 {:.0} µs, max {:.0} µs",
                    fl.late,
                    fl.loops,
                    fl.late_percent(),
                    fl.p99_us,
                    fl.max_us
                ),
            );
            row(
                "overruns / floor (target ≤ 1.5)",
                if fl.late == 0 {
                    format!("floor 0: {} overruns against none", f.overruns)
                } else {
                    format!("{:.2}", f.overrun_percent() / fl.late_percent())
                },
            );
        }
        Some(Err(why)) => row("platform floor", format!("not measured: {why}")),
        None => {}
    }
    row("final state", controller_state_name(st.state).to_string());
    md.push_str(
        "\n| process | RSS start → end | growth | fds start → end | threads | ended |\n|---|---:|---:|---:|---:|---|\n",
    );
    for (name, a, b) in stats {
        let ended = outcomes
            .iter()
            .find(|o| o.0 == *name)
            .map(|o| o.1.as_str())
            .unwrap_or("?");
        md.push_str(&format!(
            "| {name} | {:.1} → {:.1} MB | {} | {} → {} | {} | {ended} |\n",
            a.rss_kb as f64 / 1024.0,
            b.rss_kb as f64 / 1024.0,
            kb_delta(a.rss_kb, b.rss_kb),
            a.fds,
            b.fds,
            b.threads
        ));
    }
    md
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn proc_stats_reads_this_process() {
        let s = proc_stats(std::process::id()).expect("/proc of this process");
        assert!(s.rss_kb > 0 && s.fds >= 3 && s.threads >= 1, "{s:?}");
        assert!(proc_stats(u32::MAX).is_none());
        let (steal, total) = cpu_steal_ticks().expect("/proc/stat");
        assert!(total > 0 && steal <= total);
        assert!(thread_preemptions(std::process::id(), "no-such-thread").is_none());
    }

    #[test]
    fn figures_are_differences_of_the_two_snapshots() {
        let a = ControllerStatus {
            ticks: 100,
            overruns: 2,
            hold_entries: 1,
            ..Default::default()
        };
        let mut b = ControllerStatus {
            ticks: 1100,
            overruns: 3,
            hold_entries: 1,
            ..Default::default()
        };
        b.rejected[2] = 5;
        let f = SoakFigures::between(&a, &b, 1.0);
        assert_eq!(
            (f.ticks, f.overruns, f.holds, f.rejected[2]),
            (1000, 1, 0, 5)
        );
        assert!((f.overrun_percent() - 0.1).abs() < 1e-12);
    }
}
