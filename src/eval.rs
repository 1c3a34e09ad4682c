//! `chunkrt eval`: the closed-loop delay sweep of the RTC paper, on the reach task.
//!
//! For each injected inference delay d = 0 … N action steps and each way of executing chunks
//! (`replace`, `crossfade`, `temporal_ensemble`, `rtc`, and `sync`: the robot waits for every
//! chunk, as openpi's `ActionChunkBroker`), the same K held-out episodes run in simulated time
//! (`task::sim`: real executor, real policy, real ruckig). Reported per cell: success rate with
//! a 95 % Wilson interval, mean time to target of the successes, the largest jump of the target
//! at a chunk switch, and the RMS jerk of the command — as a table (stdout and Markdown), a CSV
//! and a PNG; `episodes.csv` has every episode (closest approach, wrong target, time).

use std::io::{IsTerminal, Write};
use std::path::{Path, PathBuf};
use std::time::Instant;

use anyhow::Context;

use chunkrt_ipc::config::Config;

use crate::inference::PolicySource;
use crate::task::sim::{run_episode, EpisodeOutcome, EpisodeSpec, SimSettings};
use crate::train::held_out_episodes;

mod switch;

/// Every way of executing chunks the sweep knows.
pub const STRATEGIES: [&str; 6] = [
    "sync",
    "replace",
    "crossfade",
    "temporal_ensemble",
    "rtc",
    "rtc_trained",
];
/// First scene seed of the evaluation episodes (validation uses 1000.., training ≥ 2³²).
pub const EVAL_SCENE_BASE: u64 = 2_000;

/// `chunkrt eval`.
#[derive(Debug, Clone, clap::Args)]
pub struct EvalArgs {
    /// Robot / execution configuration (default: the embedded demo robot).
    #[arg(long)]
    pub config: Option<PathBuf>,
    /// Checkpoint (default: the configuration's `policy.checkpoint`).
    #[arg(long)]
    pub checkpoint: Option<PathBuf>,
    /// Largest injected delay (action steps); the sweep runs 0..=N.
    #[arg(long, default_value_t = 4)]
    pub max_delay: u64,
    /// Only these delays (action steps, comma separated) instead of 0..=--max-delay: e.g.
    /// `--delays 0,4,8 --episodes 100` for tighter intervals where they matter.
    #[arg(long, value_delimiter = ',', value_name = "D,D,..")]
    pub delays: Vec<u64>,
    /// Strategies, comma separated (sync, replace, crossfade, temporal_ensemble, rtc, and
    /// rtc_trained with a checkpoint trained for it, e.g. `models/reach_pi05_rtc`); any but sync
    /// with `/measured` appended runs without future-state inference (e.g. `rtc/measured`;
    /// rtc_trained observes the measured state while its committed rows cover the delay, and a
    /// future state beyond: `InferenceRequest::committed_rows`); `rtc/identity` guides with the
    /// identity Jacobian (`execution.rtc_jacobian = "identity"`: no backward pass; also
    /// `rtc/identity/measured`).
    #[arg(
        long,
        value_delimiter = ',',
        default_value = "sync,replace,crossfade,temporal_ensemble,rtc"
    )]
    pub strategies: Vec<String>,
    /// Episodes per cell.
    #[arg(long, default_value_t = 30)]
    pub episodes: usize,
    /// Episode time limit (s).
    #[arg(long, default_value_t = 8.0)]
    pub max_seconds: f64,
    /// Output folder (eval.md, eval.csv, episodes.csv: one row per episode, eval.png).
    #[arg(long, default_value = "target/chunkrt-eval")]
    pub out: PathBuf,
    /// A smoke run: delays 0 and 2, 2 episodes per cell, 3 s limit.
    #[arg(long)]
    pub quick: bool,
    /// Also draw the target and the command around a chunk switch, one panel per strategy, on
    /// the first held-out episode at this delay (action steps): `switch.png` in --out.
    #[arg(long, value_name = "DELAY")]
    pub switch_plot: Option<u64>,
    /// The dynamic variant: at this time (s) the prompt switches to the other target, which is
    /// then the one to reach; the table adds the reaction time (until the end effector turned
    /// 1 cm away from the first target).
    #[arg(long, value_name = "SECONDS")]
    pub retarget_at: Option<f64>,
    /// The drifting variant: both targets swing about the robot's base at this many swings per
    /// second (`--drift-amplitude` either side), and the prompted one must be touched where it
    /// is. Combines with `--retarget-at`.
    #[arg(long, value_name = "HZ")]
    pub drift_hz: Option<f64>,
    /// The drift's largest rotation either side of the start (rad).
    #[arg(long, default_value_t = 0.3, value_name = "RAD")]
    pub drift_amplitude: f64,
    /// With a drift: how long the end effector must stay on the moving target for success
    /// (s; 0: touching it once).
    #[arg(long, default_value_t = 1.0, value_name = "SECONDS")]
    pub follow: f64,
    /// Instead of the closed-loop sweep, the open-loop probe (`task::probe`) over `--episodes`
    /// held-out episodes: how well the chunks point at the prompted target, and how much they
    /// depend on the image and the prompt against the sampling noise. Writes probe.md.
    #[arg(long)]
    pub open_loop: bool,
    /// The expert the open-loop probe compares with (the one the policy was trained on).
    #[arg(long, value_enum, default_value_t = crate::task::expert::Profile::DistancePaced)]
    pub expert: crate::task::expert::Profile,
}

/// First scene seed of the open-loop probe's episodes.
pub const PROBE_SCENE_BASE: u64 = 4_000;

/// `chunkrt eval --open-loop`.
fn run_probe(cfg: &Config, args: &EvalArgs) -> anyhow::Result<()> {
    let dir = cfg.resolve(
        cfg.policy
            .checkpoint
            .as_ref()
            .context("the configuration names no policy checkpoint")?,
    );
    let pool = crate::inference::policy_pool(&cfg.policy)?;
    let mut policy = pool.install(|| crate::inference::load_policy(&dir, &cfg.policy))?;
    let n = if args.quick { 4 } else { args.episodes };
    let eps = held_out_episodes(cfg, PROBE_SCENE_BASE, n, 9);
    let t0 = Instant::now();
    let r = pool.install(|| crate::task::probe::probe(&mut policy, cfg, &eps, args.expert))?;
    let text = format!(
        "checkpoint {}, {} held-out episodes (scenes {PROBE_SCENE_BASE}..), expert {}, {:.1} s\n\n{r}",
        dir.display(),
        eps.len(),
        args.expert.name(),
        t0.elapsed().as_secs_f64()
    );
    println!("{text}");
    std::fs::create_dir_all(&args.out)
        .with_context(|| format!("cannot create {}", args.out.display()))?;
    let md = args.out.join("probe.md");
    std::fs::write(&md, format!("# Open-loop probe\n\n{text}\n"))?;
    println!("wrote {}", md.display());
    Ok(())
}

/// One cell of the sweep.
#[derive(Debug, Clone, PartialEq)]
pub struct Cell {
    pub strategy: String,
    pub delay: u64,
    pub episodes: usize,
    pub successes: usize,
    /// 95 % Wilson interval of the success rate.
    pub ci: (f64, f64),
    /// Mean time to target of the successes (s; NaN when none).
    pub time_to_target: f64,
    /// Largest target jump at a chunk switch over the cell's episodes (rad).
    pub max_jump: f64,
    /// 90th percentile over the cell's episodes of each episode's largest switch jump (rad): the
    /// maximum over 30 episodes is one episode's outlier; this is the typical bad case.
    pub p90_jump: f64,
    /// Mean over episodes of the command's RMS jerk (rad/s³).
    pub rms_jerk: f64,
    /// Mean share of ticks in HOLD.
    pub hold_ticks: f64,
    /// Dynamic variant: mean reaction time of the episodes that reacted (s; NaN: static task or
    /// none reacted), and how many reacted.
    pub reaction_time: f64,
    pub reacted: usize,
    /// The cell ran the dynamic variant.
    pub dynamic: bool,
}

impl Cell {
    /// Success rate.
    pub fn rate(&self) -> f64 {
        self.successes as f64 / self.episodes.max(1) as f64
    }
}

/// The mean of `v`; NaN when empty.
fn mean(v: impl Iterator<Item = f64>) -> f64 {
    let (sum, n) = v.fold((0.0, 0usize), |(s, n), x| (s + x, n + 1));
    if n == 0 {
        f64::NAN
    } else {
        sum / n as f64
    }
}

/// The 90th percentile (nearest rank) of `v`; 0 when empty.
pub fn p90(v: impl Iterator<Item = f64>) -> f64 {
    let mut v: Vec<f64> = v.collect();
    if v.is_empty() {
        return 0.0;
    }
    v.sort_by(f64::total_cmp);
    v[((0.9 * v.len() as f64).ceil() as usize).clamp(1, v.len()) - 1]
}

/// 95 % Wilson score interval of `k` successes in `n` trials.
pub fn wilson(k: usize, n: usize) -> (f64, f64) {
    if n == 0 {
        return (0.0, 1.0);
    }
    let (n, p, z) = (n as f64, k as f64 / n as f64, 1.96f64);
    let den = 1.0 + z * z / n;
    let centre = (p + z * z / (2.0 * n)) / den;
    let half = z * (p * (1.0 - p) / n + z * z / (4.0 * n * n)).sqrt() / den;
    ((centre - half).max(0.0), (centre + half).min(1.0))
}

fn summarise(strategy: &str, delay: u64, outs: &[EpisodeOutcome], dynamic: bool) -> Cell {
    let n = outs.len();
    let k = outs.iter().filter(|o| o.success).count();
    let t: Vec<f64> = outs.iter().filter_map(|o| o.time_to_target).collect();
    Cell {
        strategy: strategy.to_string(),
        delay,
        episodes: n,
        successes: k,
        ci: wilson(k, n),
        time_to_target: if t.is_empty() {
            f64::NAN
        } else {
            t.iter().sum::<f64>() / t.len() as f64
        },
        max_jump: outs
            .iter()
            .map(|o| o.smoothness.max_switch_jump_target)
            .fold(0.0, f64::max),
        p90_jump: p90(outs.iter().map(|o| o.smoothness.max_switch_jump_target)),
        rms_jerk: outs.iter().map(|o| o.smoothness.rms_jerk).sum::<f64>() / n.max(1) as f64,
        hold_ticks: outs.iter().map(|o| o.hold_ticks as f64).sum::<f64>() / n.max(1) as f64,
        reaction_time: mean(outs.iter().filter_map(|o| o.reaction_time)),
        reacted: outs.iter().filter(|o| o.reaction_time.is_some()).count(),
        dynamic,
    }
}

/// One episode of a sweep, for `episodes.csv`.
#[derive(Debug, Clone, PartialEq)]
pub struct EpisodeRow {
    pub strategy: String,
    pub delay: u64,
    pub spec: EpisodeSpec,
    pub outcome: EpisodeOutcome,
}

/// The Markdown table of a sweep.
pub fn markdown(cells: &[Cell]) -> String {
    // the dynamic variant adds the reaction to the retarget
    let dynamic = cells.iter().any(|c| c.dynamic);
    let mut s = String::from(
        "| strategy | delay (steps) | success | 95 % CI | time to target (s) | max switch jump (rad) | p90 switch jump (rad) | RMS jerk (rad/s³) |",
    );
    s.push_str(if dynamic {
        " reaction (s) |\n|---|---:|---:|---|---:|---:|---:|---:|---:|\n"
    } else {
        "\n|---|---:|---:|---|---:|---:|---:|---:|\n"
    });
    for c in cells {
        s.push_str(&format!(
            "| {} | {} | {}/{} ({:.0} %) | {:.0}–{:.0} % | {:.2} | {:.4} | {:.4} | {:.0} |",
            c.strategy,
            c.delay,
            c.successes,
            c.episodes,
            100.0 * c.rate(),
            100.0 * c.ci.0,
            100.0 * c.ci.1,
            c.time_to_target,
            c.max_jump,
            c.p90_jump,
            c.rms_jerk
        ));
        if dynamic {
            s.push_str(&format!(
                " {:.3} ({}/{}) |",
                c.reaction_time, c.reacted, c.episodes
            ));
        }
        s.push('\n');
    }
    s
}

/// Suffix of a strategy name that runs it without future-state inference (`rtc/measured`).
pub const MEASURED: &str = "/measured";

/// Suffix of `rtc` that guides with the identity Jacobian (`rtc/identity`,
/// `execution.rtc_jacobian = "identity"`); before `/measured` where both apply.
pub const IDENTITY: &str = "/identity";

/// A sweep's strategy name taken apart.
#[derive(Debug, Clone, Copy, PartialEq)]
struct Variant<'a> {
    /// The strategy (or `sync`).
    base: &'a str,
    /// Without future-state inference.
    measured: bool,
    /// `rtc` with the identity Jacobian.
    identity: bool,
}

/// The strategy name and its variant suffixes.
fn split_variant(s: &str) -> Variant<'_> {
    let (s, measured) = match s.strip_suffix(MEASURED) {
        Some(rest) => (rest, true),
        None => (s, false),
    };
    let (base, identity) = match s.strip_suffix(IDENTITY) {
        Some(rest) => (rest, true),
        None => (s, false),
    };
    Variant {
        base,
        measured,
        identity,
    }
}

/// What moves during the sweep's episodes (the dynamic variants); the default: nothing.
#[derive(Debug, Clone, Copy, Default, PartialEq)]
pub struct World {
    /// The prompt switches to the other target at this time (s).
    pub retarget_at: Option<f64>,
    /// The targets swing about the base.
    pub drift: Option<crate::task::sim::Drift>,
}

/// The configuration of a cell: strategy `s` (a sweep name, `sync` keeping the configured one
/// for the broker, `/measured` turning future-state inference off, `/identity` the identity
/// Jacobian) at `delay` steps, the
/// executor's delay estimate starting at the injected delay. Returns it and whether `s` is sync.
fn cell_config(cfg: &Config, s: &str, delay: u64) -> anyhow::Result<(Config, bool)> {
    let mut c = cfg.clone();
    let v = split_variant(s);
    let sync = v.base == "sync";
    if !sync {
        c.execution.strategy = v.base.parse().map_err(anyhow::Error::msg)?;
    }
    if v.measured {
        c.execution.future_state = false;
    }
    if v.identity {
        c.execution.rtc_jacobian = chunkrt_ipc::config::RtcJacobian::Identity;
    }
    c.execution.initial_delay_steps = delay as usize;
    Ok((c, sync))
}

/// Runs the sweep; `progress(done, total, cell so far)` after each episode.
pub fn sweep(
    cfg: &Config,
    strategies: &[String],
    delays: &[u64],
    episodes: usize,
    max_seconds: f64,
    world: World,
    mut progress: impl FnMut(usize, usize, &str, u64),
) -> anyhow::Result<(Vec<Cell>, Vec<EpisodeRow>)> {
    for s in strategies {
        let v = split_variant(s);
        anyhow::ensure!(
            STRATEGIES.contains(&v.base)
                && !(v.measured && v.base == "sync")
                && !(v.identity && v.base != "rtc"),
            "unknown strategy {s:?}: one of {}, and any but sync with {MEASURED:?} appended (the \
             policy observes the measured state instead of the future one), rtc with \
             {IDENTITY:?} (guidance with the identity Jacobian)",
            STRATEGIES.join(", ")
        );
    }
    let specs = held_out_episodes(cfg, EVAL_SCENE_BASE, episodes, 0xe7a1);
    let mut policy = PolicySource::load(cfg)?;
    if strategies
        .iter()
        .any(|s| split_variant(s).base == "rtc_trained")
    {
        anyhow::ensure!(
            policy.committed_max() > 0,
            "strategy rtc_trained needs a checkpoint trained with a committed prefix (`chunkrt \
             train --rtc-prefix N`), and {} is not: pass --checkpoint models/reach_pi05_rtc",
            cfg.policy
                .checkpoint
                .as_ref()
                .map(|p| p.display().to_string())
                .unwrap_or_default()
        );
    }
    let total = strategies.len() * delays.len() * episodes;
    let mut done = 0;
    let mut cells = Vec::new();
    let mut rows = Vec::new();
    for &d in delays {
        for s in strategies {
            let (c, sync) = cell_config(cfg, s, d)?;
            let settings = SimSettings {
                delay_steps: d,
                max_seconds,
                synchronous: sync,
                record: false,
                retarget_at: world.retarget_at,
                drift: world.drift,
            };
            let mut outs = Vec::with_capacity(episodes);
            for e in &specs {
                outs.push(run_episode(&c, &mut policy, e, &settings)?);
                done += 1;
                progress(done, total, s, d);
            }
            cells.push(summarise(s, d, &outs, world.retarget_at.is_some()));
            rows.extend(specs.iter().zip(outs).map(|(e, o)| EpisodeRow {
                strategy: s.clone(),
                delay: d,
                spec: *e,
                outcome: o,
            }));
        }
    }
    Ok((cells, rows))
}

/// Success rate (with the 95 % intervals), time to target and max switch jump against the delay,
/// one line per strategy.
pub fn plot(path: &Path, cells: &[Cell]) -> anyhow::Result<()> {
    use plotters::prelude::*;
    let strategies: Vec<&str> = {
        let mut v: Vec<&str> = Vec::new();
        for c in cells {
            if !v.contains(&c.strategy.as_str()) {
                v.push(&c.strategy);
            }
        }
        v
    };
    let dmax = cells.iter().map(|c| c.delay).max().unwrap_or(1).max(1) as f64;
    let jmax = cells.iter().map(|c| c.max_jump).fold(1e-3, f64::max) * 1.1;
    let tmax = cells
        .iter()
        .map(|c| c.time_to_target)
        .filter(|t| t.is_finite())
        .fold(0.1, f64::max)
        * 1.1;
    let root = BitMapBackend::new(path, (1500, 460)).into_drawing_area();
    root.fill(&WHITE)?;
    let panels = root.split_evenly((1, 3));
    let (left, middle, right) = (&panels[0], &panels[1], &panels[2]);
    let err = |e: &dyn std::fmt::Display| anyhow::anyhow!("plot {}: {e}", path.display());
    let mut a = ChartBuilder::on(left)
        .caption("success rate vs inference delay", ("sans-serif", 18))
        .margin(10)
        .x_label_area_size(40)
        .y_label_area_size(50)
        .build_cartesian_2d(-0.3f64..dmax + 0.3, 0f64..1.05)
        .map_err(|e| err(&e))?;
    let int_ticks = |x: &f64| {
        if (x - x.round()).abs() < 1e-6 {
            format!("{:.0}", x)
        } else {
            String::new()
        }
    };
    a.configure_mesh()
        .x_label_formatter(&int_ticks)
        .x_desc("inference delay (action steps)")
        .y_desc("success rate (95 % CI)")
        .draw()
        .map_err(|e| err(&e))?;
    let mut m = ChartBuilder::on(middle)
        .caption("time to target (successes)", ("sans-serif", 18))
        .margin(10)
        .x_label_area_size(40)
        .y_label_area_size(50)
        .build_cartesian_2d(-0.3f64..dmax + 0.3, 0f64..tmax)
        .map_err(|e| err(&e))?;
    m.configure_mesh()
        .x_label_formatter(&int_ticks)
        .x_desc("inference delay (action steps)")
        .y_desc("s")
        .draw()
        .map_err(|e| err(&e))?;
    let mut b = ChartBuilder::on(right)
        .caption("largest target jump at a chunk switch", ("sans-serif", 18))
        .margin(10)
        .x_label_area_size(40)
        .y_label_area_size(60)
        .build_cartesian_2d(-0.3f64..dmax + 0.3, 0f64..jmax)
        .map_err(|e| err(&e))?;
    b.configure_mesh()
        .x_label_formatter(&int_ticks)
        .x_desc("inference delay (action steps)")
        .y_desc("rad")
        .draw()
        .map_err(|e| err(&e))?;
    let n = strategies.len().max(1) as f64;
    for (i, s) in strategies.iter().enumerate() {
        let color = Palette99::pick(i).to_rgba();
        // small horizontal offsets keep the error bars apart
        let dx = (i as f64 - (n - 1.0) / 2.0) * 0.06;
        let mine: Vec<&Cell> = cells.iter().filter(|c| c.strategy == *s).collect();
        a.draw_series(LineSeries::new(
            mine.iter().map(|c| (c.delay as f64 + dx, c.rate())),
            color.stroke_width(2),
        ))
        .map_err(|e| err(&e))?
        .label(*s)
        .legend(move |(x, y)| PathElement::new(vec![(x, y), (x + 20, y)], color.stroke_width(2)));
        a.draw_series(mine.iter().map(|c| {
            ErrorBar::new_vertical(
                c.delay as f64 + dx,
                c.ci.0,
                c.rate(),
                c.ci.1,
                color.stroke_width(1),
                6,
            )
        }))
        .map_err(|e| err(&e))?;
        let timed: Vec<&&Cell> = mine
            .iter()
            .filter(|c| c.time_to_target.is_finite())
            .collect();
        m.draw_series(LineSeries::new(
            timed.iter().map(|c| (c.delay as f64, c.time_to_target)),
            color.stroke_width(2),
        ))
        .map_err(|e| err(&e))?;
        m.draw_series(
            timed
                .iter()
                .map(|c| Circle::new((c.delay as f64, c.time_to_target), 3, color.filled())),
        )
        .map_err(|e| err(&e))?;
        b.draw_series(LineSeries::new(
            mine.iter().map(|c| (c.delay as f64, c.max_jump)),
            color.stroke_width(2),
        ))
        .map_err(|e| err(&e))?;
        b.draw_series(
            mine.iter()
                .map(|c| Circle::new((c.delay as f64, c.max_jump), 3, color.filled())),
        )
        .map_err(|e| err(&e))?;
    }
    a.configure_series_labels()
        .position(SeriesLabelPosition::LowerLeft)
        .background_style(WHITE.mix(0.85))
        .border_style(BLACK)
        .label_font(("sans-serif", 14))
        .margin(8)
        .draw()
        .map_err(|e| err(&e))?;
    root.present().map_err(|e| err(&e))?;
    Ok(())
}

/// Runs `chunkrt eval`.
pub fn run(args: EvalArgs) -> anyhow::Result<()> {
    let mut cfg = match &args.config {
        Some(p) => Config::load(p)?,
        None => Config::embedded_default(),
    };
    if let Some(c) = &args.checkpoint {
        cfg.policy.checkpoint = Some(
            std::fs::canonicalize(c)
                .with_context(|| format!("checkpoint {} does not exist", c.display()))?,
        );
        if cfg.policy.kind == chunkrt_ipc::config::PolicyKind::Hold {
            cfg.policy.kind = chunkrt_ipc::config::PolicyKind::Pi05;
        }
    }
    if args.open_loop {
        return run_probe(&cfg, &args);
    }
    let (delays, episodes, max_seconds): (Vec<u64>, usize, f64) = if args.quick {
        (vec![0, 2.min(args.max_delay)], 2, 3.0)
    } else {
        (
            if args.delays.is_empty() {
                (0..=args.max_delay).collect()
            } else {
                args.delays.clone()
            },
            args.episodes,
            args.max_seconds,
        )
    };
    anyhow::ensure!(episodes > 0, "--episodes must be > 0");
    let drift = match args.drift_hz {
        Some(f) => {
            anyhow::ensure!(
                f.is_finite() && f > 0.0 && f <= 5.0,
                "--drift-hz {f}: must be in (0, 5] swings per second"
            );
            let a = args.drift_amplitude;
            anyhow::ensure!(
                a.is_finite() && a > 0.0 && a <= 1.0,
                "--drift-amplitude {a}: must be in (0, 1] rad"
            );
            anyhow::ensure!(
                args.follow.is_finite() && args.follow >= 0.0 && args.follow < max_seconds,
                "--follow {}: must be at least 0 and below the episode's limit ({max_seconds} s)",
                args.follow
            );
            Some(crate::task::sim::Drift {
                amplitude_rad: a,
                frequency_hz: f,
                phase_rad: 0.0,
                follow_s: args.follow,
            })
        }
        None => None,
    };
    if let Some(t) = args.retarget_at {
        anyhow::ensure!(
            t.is_finite() && t > 0.0 && t < max_seconds,
            "--retarget-at {t}: must be after the start and before the episode's limit ({max_seconds} s)"
        );
    }
    let tty = std::io::stderr().is_terminal();
    let t0 = Instant::now();
    let mut last = 0.0;
    let (cells, rows) = sweep(
        &cfg,
        &args.strategies,
        &delays,
        episodes,
        max_seconds,
        World {
            retarget_at: args.retarget_at,
            drift,
        },
        |done, total, s, d| {
            let now = t0.elapsed().as_secs_f64();
            if done == total || now - last >= if tty { 0.5 } else { 20.0 } {
                last = now;
                let eta = now / done as f64 * (total - done) as f64;
                let line = format!(
                    "[eval] {done}/{total} episodes  now: {s} at delay {d}  elapsed {now:.0} s  eta {eta:.0} s"
                );
                if tty {
                    eprint!("\r{line}\x1b[K");
                } else {
                    eprintln!("{line}");
                }
            }
        },
    )?;
    if tty {
        eprintln!();
    }
    let md = markdown(&cells);
    println!("{md}");
    std::fs::create_dir_all(&args.out)
        .with_context(|| format!("cannot create {}", args.out.display()))?;
    std::fs::write(args.out.join("eval.md"), &md)?;
    let mut csv = std::fs::File::create(args.out.join("eval.csv"))?;
    writeln!(
        csv,
        "strategy,delay_steps,episodes,successes,ci_low,ci_high,time_to_target_s,max_switch_jump_rad,p90_switch_jump_rad,rms_jerk,hold_ticks,reaction_time_s,reacted"
    )?;
    for c in &cells {
        writeln!(
            csv,
            "{},{},{},{},{:.4},{:.4},{:.4},{:.6},{:.6},{:.2},{:.1},{:.4},{}",
            c.strategy,
            c.delay,
            c.episodes,
            c.successes,
            c.ci.0,
            c.ci.1,
            c.time_to_target,
            c.max_jump,
            c.p90_jump,
            c.rms_jerk,
            c.hold_ticks,
            c.reaction_time,
            c.reacted
        )?;
    }
    let mut csv = std::fs::File::create(args.out.join("episodes.csv"))?;
    writeln!(
        csv,
        "strategy,delay_steps,scene_seed,color,success,wrong_target,min_distance_m,time_to_target_s,expert_time_s,chunks,max_switch_jump_rad,reaction_time_s"
    )?;
    for r in &rows {
        let o = &r.outcome;
        // how long the scripted expert's motion from the same start takes
        let expert = crate::task::expert::Reach::plan(
            &r.spec.start,
            &crate::task::ReachScene::from_seed(r.spec.scene_seed),
            r.spec.color,
            0.0,
        )
        .map_or(f64::NAN, |p| p.duration);
        writeln!(
            csv,
            "{},{},{},{},{},{},{:.4},{},{:.3},{},{:.4},{}",
            r.strategy,
            r.delay,
            r.spec.scene_seed,
            r.spec.color.name(),
            o.success as u8,
            o.wrong_target as u8,
            o.min_distance,
            o.time_to_target
                .map_or(String::new(), |t| format!("{t:.3}")),
            expert,
            o.chunks,
            o.smoothness.max_switch_jump_target,
            o.reaction_time.map_or(String::new(), |t| format!("{t:.3}"))
        )?;
    }
    if let Some(d) = args.switch_plot {
        let png = args.out.join("switch.png");
        for line in switch::switch_plot(&cfg, d, &args.strategies, &png)? {
            println!("{line}");
        }
        println!("switch plot: {}", png.display());
    }
    let png = args.out.join("eval.png");
    match plot(&png, &cells) {
        Ok(()) => println!("plot: {}", png.display()),
        Err(e) => eprintln!("[eval] no plot: {e}"),
    }
    // one line: the best strategy at the largest delay vs synchronous execution
    let dmax = *delays.last().unwrap_or(&0);
    let at = |s: &str| cells.iter().find(|c| c.strategy == s && c.delay == dmax);
    if let (Some(rtc), Some(sync)) = (at("rtc"), at("sync")) {
        println!(
            "at delay {dmax}: rtc {}/{} in {:.2} s vs sync {}/{} in {:.2} s ({:.2}x the time); {:.0} s for {} episodes",
            rtc.successes,
            rtc.episodes,
            rtc.time_to_target,
            sync.successes,
            sync.episodes,
            sync.time_to_target,
            sync.time_to_target / rtc.time_to_target,
            t0.elapsed().as_secs_f64(),
            cells.len() * episodes
        );
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn measured_state_variants_are_named_by_a_suffix() {
        let v = |base, measured, identity| Variant {
            base,
            measured,
            identity,
        };
        assert_eq!(split_variant("rtc/measured"), v("rtc", true, false));
        assert_eq!(split_variant("rtc"), v("rtc", false, false));
        assert_eq!(split_variant("rtc/identity/measured"), v("rtc", true, true));
        let (c, _) = cell_config(&Config::embedded_default(), "rtc/identity", 2).unwrap();
        assert_eq!(
            c.execution.rtc_jacobian,
            chunkrt_ipc::config::RtcJacobian::Identity
        );
        let cfg = Config::embedded_default();
        for bad in [
            "sync/measured",
            "rtc/future",
            "magic",
            "replace/identity",
            "rtc/measured/identity",
        ] {
            let e = sweep(
                &cfg,
                &[bad.to_string()],
                &[0],
                1,
                1.0,
                World::default(),
                |_, _, _, _| {},
            )
            .expect_err(bad)
            .to_string();
            assert!(e.contains(bad) && e.contains("/measured"), "{e}");
        }
    }

    #[test]
    fn p90_is_the_nearest_rank() {
        assert_eq!(p90((1..=30).map(f64::from)), 27.0);
        assert_eq!(p90((1..=10).map(f64::from)), 9.0);
        assert_eq!(p90([0.5].into_iter()), 0.5);
        assert_eq!(p90(std::iter::empty()), 0.0);
    }

    #[test]
    fn wilson_interval_matches_known_values() {
        // 8/10: 0.490–0.943 (standard tables)
        let (lo, hi) = wilson(8, 10);
        assert!(
            (lo - 0.490).abs() < 0.002 && (hi - 0.943).abs() < 0.002,
            "{lo} {hi}"
        );
        let (lo, hi) = wilson(0, 20);
        assert!(lo == 0.0 && (hi - 0.161).abs() < 0.002, "{hi}");
        assert_eq!(wilson(0, 0), (0.0, 1.0));
    }
}
