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

use chunkrt_controller::config::{Config, Jacobian};

use crate::task::sim::{run_episode, EpisodeOutcome, EpisodeSpec, SimSettings};
use crate::task::so101::{Physics, So101Plant};
use crate::train::held_out_episodes;
use chunkrt_controller::config::PolicySource;
use chunkrt_controller::contract::ChunkSource;
use chunkrt_controller::inference::PolicySource as LocalPolicy;
use chunkrt_controller::remote::RemoteSource;

mod report;
mod switch;

use report::summarise;
pub use report::{markdown, p90, plot, wilson, Cell, EpisodeRow};

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
    /// The task: `reach` (the embedded demo's planar arm) or `so101` (the SO-101 pick-and-place
    /// in MuJoCo, scored by the package's own success check; episodes from seed 10 000, the
    /// physics in `tools/python/so101_sim.py`; defaults to `--config config/so101.toml`,
    /// `--checkpoint models/so101_pi05`, 12-s episodes, and strategies without sync).
    #[arg(long, value_enum, default_value_t = crate::task::TaskKind::Reach)]
    pub task: crate::task::TaskKind,
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
    /// Strategies, comma separated (default: sync, replace, crossfade, temporal_ensemble, rtc;
    /// without sync for the SO-101) (sync, replace, crossfade, temporal_ensemble, rtc, and
    /// rtc_trained with a checkpoint trained for it, e.g. `models/reach_pi05_rtc`); any but sync
    /// with `/measured` appended runs without future-state inference (e.g. `rtc/measured`;
    /// rtc_trained observes the measured state while its committed rows cover the delay, and a
    /// future state beyond: `InferenceRequest::committed_rows`); `rtc/vjp` and `rtc/identity` pick
    /// the guidance's Jacobian (`execution.rtc_jacobian`; the default `identity` has no backward
    /// pass; also `rtc/vjp/measured`).
    #[arg(long, value_delimiter = ',')]
    pub strategies: Vec<String>,
    /// Episodes per cell.
    #[arg(long, default_value_t = 30)]
    pub episodes: usize,
    /// Episode time limit (s; default 8, 12 for the SO-101).
    #[arg(long)]
    pub max_seconds: Option<f64>,
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
    /// Take every chunk from an openpi-protocol server at this `ws://host:port` instead of
    /// the policy in process (`chunkrt serve --checkpoint models/reach_pi05`; a chunkrt server
    /// is reseeded per episode, so the sweep sees the same noise as in process).
    #[arg(long, value_name = "URL")]
    pub remote: Option<String>,
    /// `--task so101`: instead of a policy, each episode's plan of the package's scripted expert
    /// (`tools/python/so101_plan.py record`: the joint targets it commanded in its own run in
    /// simulated time) replayed by the observation's time, a TEST DOUBLE: whether the
    /// controller, under the configured limits, carries out a plan that succeeds.
    #[arg(long, conflicts_with_all = ["remote", "checkpoint"])]
    pub expert_plan: bool,
    /// `--task so101`: the episodes' seeds, `A..B` (B excluded), instead of `--episodes` from
    /// seed 10 000: e.g. `--seeds 8200..8250`.
    #[arg(long, value_name = "A..B", value_parser = parse_seeds)]
    pub seeds: Option<std::ops::Range<u64>>,
}

/// `A..B` (B excluded, B > A, at most 100 000 seeds) as a range.
pub fn parse_seeds(text: &str) -> Result<std::ops::Range<u64>, String> {
    let (a, b) = text
        .split_once("..")
        .ok_or_else(|| format!("{text:?}: seeds are A..B (B excluded), e.g. 8200..8250"))?;
    let a: u64 = a
        .trim()
        .parse()
        .map_err(|e| format!("{text:?}: the first seed: {e}"))?;
    let b: u64 = b
        .trim()
        .parse()
        .map_err(|e| format!("{text:?}: the end seed: {e}"))?;
    if b <= a {
        return Err(format!(
            "{text:?}: no seeds (the end, excluded, is not after the start)"
        ));
    }
    if b - a > 100_000 {
        return Err(format!("{text:?}: {} seeds; at most 100 000", b - a));
    }
    Ok(a..b)
}

/// First scene seed of the open-loop probe's episodes.
pub const PROBE_SCENE_BASE: u64 = 4_000;

/// How fast the motion probe's targets turn about the base (rad/s): about half the top speed of
/// the eval's default swing (±0.3 rad at 0.25 Hz: 0.47 rad/s).
pub const MOTION_PROBE_RATE_RAD_S: f64 = 0.25;

/// `chunkrt eval --open-loop`.
fn run_probe(cfg: &Config, args: &EvalArgs) -> anyhow::Result<()> {
    let dir = cfg.resolve(
        cfg.policy
            .checkpoint
            .as_ref()
            .context("the configuration names no policy checkpoint")?,
    );
    let pool = chunkrt_controller::inference::policy_pool(&cfg.policy)?;
    let mut policy =
        pool.install(|| chunkrt_controller::inference::load_policy(&dir, &cfg.policy))?;
    let n = if args.quick { 4 } else { args.episodes };
    let eps = held_out_episodes(cfg, PROBE_SCENE_BASE, n, 9);
    let t0 = Instant::now();
    let r = pool.install(|| crate::task::probe::probe(&mut policy, cfg, &eps, args.expert))?;
    let mut text = format!(
        "checkpoint {}, {} held-out episodes (scenes {PROBE_SCENE_BASE}..), expert {}, {:.1} s\n\n{r}",
        dir.display(),
        eps.len(),
        args.expert.name(),
        t0.elapsed().as_secs_f64()
    );
    if !policy.delayed_views().is_empty() {
        let m = pool.install(|| {
            crate::task::probe::motion_probe(&mut policy, cfg, &eps, MOTION_PROBE_RATE_RAD_S)
        })?;
        text.push_str(&format!(
            "\nthe targets turning at {MOTION_PROBE_RATE_RAD_S} rad/s: {m}\n"
        ));
    }
    println!("{text}");
    std::fs::create_dir_all(&args.out)
        .with_context(|| format!("cannot create {}", args.out.display()))?;
    let md = args.out.join("probe.md");
    std::fs::write(&md, format!("# Open-loop probe\n\n{text}\n"))?;
    println!("wrote {}", md.display());
    Ok(())
}

/// Suffix of a strategy name that runs it without future-state inference (`rtc/measured`).
pub const MEASURED: &str = "/measured";

/// Suffixes of `rtc` that pick the guidance's Jacobian (`execution.rtc_jacobian`): `rtc/vjp`,
/// `rtc/identity`; before `/measured` where both apply.
pub const JACOBIANS: [(&str, Jacobian); 2] =
    [("/identity", Jacobian::Identity), ("/vjp", Jacobian::Vjp)];

/// A sweep's strategy name taken apart.
#[derive(Debug, Clone, Copy, PartialEq)]
struct Variant<'a> {
    /// The strategy (or `sync`).
    base: &'a str,
    /// Without future-state inference.
    measured: bool,
    /// `rtc` with this Jacobian (None: the configured one).
    jacobian: Option<Jacobian>,
}

/// The strategy name and its variant suffixes.
fn split_variant(s: &str) -> Variant<'_> {
    let (s, measured) = match s.strip_suffix(MEASURED) {
        Some(rest) => (rest, true),
        None => (s, false),
    };
    for (suffix, j) in JACOBIANS {
        if let Some(base) = s.strip_suffix(suffix) {
            return Variant {
                base,
                measured,
                jacobian: Some(j),
            };
        }
    }
    Variant {
        base: s,
        measured,
        jacobian: None,
    }
}

/// What moves during the sweep's episodes (the dynamic variants); the default: nothing.
#[derive(Debug, Clone, Copy, Default, PartialEq)]
pub struct World {
    /// The prompt switches to the other target at this time (s).
    pub retarget_at: Option<f64>,
    /// The targets swing about the base.
    pub drift: Option<crate::task::sim::Drift>,
    /// The SO-101 pick-and-place instead of the reach task.
    pub so101: bool,
    /// The SO-101 expert's plans replayed instead of the policy (`EvalArgs::expert_plan`).
    pub expert_plan: bool,
    /// The SO-101's first episode seed (`EvalArgs::seeds`; default
    /// [`crate::task::so101::EVAL_SEED_BASE`]).
    pub first_seed: Option<u64>,
}

/// The configuration of a cell: strategy `s` (a sweep name, `sync` keeping the configured one
/// for the broker, `/measured` turning future-state inference off, `/vjp` or `/identity` the
/// guidance's Jacobian) at `delay` steps, the
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
    if let Some(j) = v.jacobian {
        c.execution.rtc_jacobian = j;
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
    check_strategies(strategies)?;
    let specs = episode_specs(cfg, strategies, episodes, &world)?;
    let mut plant = if world.so101 {
        let cam = crate::task::so101::task_camera(cfg)?;
        Some(crate::task::so101::So101Plant::spawn(
            cam.width as usize,
            cam.height as usize,
        )?)
    } else {
        None
    };
    let (mut policy, committed_max) = chunk_source(cfg, &world, &specs)?;
    check_rtc_trained(cfg, strategies, committed_max)?;
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
            let (outs, physics) = run_cell(
                &c,
                policy.as_mut(),
                plant.as_mut(),
                &specs,
                &settings,
                || {
                    done += 1;
                    progress(done, total, s, d);
                },
            )?;
            cells.push(summarise(s, d, &outs, world.retarget_at.is_some()));
            rows.extend(
                specs
                    .iter()
                    .zip(outs)
                    .zip(physics)
                    .map(|((e, o), p)| EpisodeRow {
                        strategy: s.clone(),
                        delay: d,
                        spec: *e,
                        outcome: o,
                        physics: p,
                    }),
            );
        }
    }
    Ok((cells, rows))
}

/// Err naming the strategies the sweep knows when one of `strategies` is none of them.
fn check_strategies(strategies: &[String]) -> anyhow::Result<()> {
    for s in strategies {
        let v = split_variant(s);
        anyhow::ensure!(
            STRATEGIES.contains(&v.base)
                && !(v.measured && v.base == "sync")
                && !(v.jacobian.is_some() && v.base != "rtc"),
            "unknown strategy {s:?}: one of {}, and any but sync with {MEASURED:?} appended (the \
             policy observes the measured state instead of the future one), rtc with /vjp or \
             /identity (the guidance's Jacobian)",
            STRATEGIES.join(", ")
        );
    }
    Ok(())
}

/// The episodes every cell runs: the SO-101's seeds from `world.first_seed`, or the reach
/// task's held-out scenes. Err for a variant the SO-101 has not.
fn episode_specs(
    cfg: &Config,
    strategies: &[String],
    episodes: usize,
    world: &World,
) -> anyhow::Result<Vec<EpisodeSpec>> {
    if !world.so101 {
        return Ok(held_out_episodes(cfg, EVAL_SCENE_BASE, episodes, 0xe7a1));
    }
    anyhow::ensure!(
        world.retarget_at.is_none() && world.drift.is_none(),
        "the SO-101 has no retarget or drift variant"
    );
    anyhow::ensure!(
        !strategies.iter().any(|s| split_variant(s).base == "sync"),
        "the SO-101 sweep does not model the synchronous broker: leave out sync"
    );
    // (the episode's seed is the scene seed; color and start are the reach task's)
    Ok((0..episodes as u64)
        .map(|i| EpisodeSpec {
            scene_seed: world
                .first_seed
                .unwrap_or(crate::task::so101::EVAL_SEED_BASE)
                + i,
            color: crate::task::TargetColor::Red,
            start: [0.0; crate::task::TASK_DOF],
        })
        .collect())
}

/// Where the chunks come from (the expert's recorded plans of `specs`' seeds, or the
/// configured policy: in process, remote or scripted) and the longest committed prefix it
/// was trained for (0: none).
fn chunk_source(
    cfg: &Config,
    world: &World,
    specs: &[EpisodeSpec],
) -> anyhow::Result<(Box<dyn ChunkSource>, usize)> {
    if world.expert_plan {
        let seeds = specs.iter().map(|e| e.scene_seed);
        let (a, b) = (
            seeds.clone().min().unwrap_or(0),
            seeds.max().map_or(0, |s| s + 1),
        );
        eprintln!("eval: recording the expert's plans of seeds {a}..{b}");
        return Ok((
            Box::new(crate::task::so101::PlanReplay::record(cfg, a..b)?),
            0,
        ));
    }
    Ok(match cfg.policy.source {
        PolicySource::Local => {
            let p = LocalPolicy::load(cfg)?;
            let max = p.committed_max();
            (Box::new(p), max)
        }
        PolicySource::Remote => {
            let r = RemoteSource::connect(cfg)?;
            let max = r.server().map_or(0, |m| m.rtc_prefix_max);
            (Box::new(r), max)
        }
        PolicySource::Scripted => (
            Box::new(chunkrt_bench::scripted::ScriptedChunkSource::for_robot(cfg)),
            usize::MAX,
        ),
    })
}

/// Err when `rtc_trained` is asked of a policy not trained with a committed prefix.
fn check_rtc_trained(
    cfg: &Config,
    strategies: &[String],
    committed_max: usize,
) -> anyhow::Result<()> {
    if strategies
        .iter()
        .any(|s| split_variant(s).base == "rtc_trained")
    {
        anyhow::ensure!(
            committed_max > 0,
            "strategy rtc_trained needs a checkpoint trained with a committed prefix (`chunkrt \
             train --rtc-prefix N`), and {} is not: pass --checkpoint models/reach_pi05_rtc",
            cfg.policy
                .checkpoint
                .as_ref()
                .map(|p| p.display().to_string())
                .unwrap_or_default()
        );
    }
    Ok(())
}

/// One cell's episodes under `c` and `settings`, on the SO-101's `plant` or the reach task:
/// each one's outcome and the SO-101's physics; `each()` after every episode.
fn run_cell(
    c: &Config,
    policy: &mut dyn ChunkSource,
    mut plant: Option<&mut So101Plant>,
    specs: &[EpisodeSpec],
    settings: &SimSettings,
    mut each: impl FnMut(),
) -> anyhow::Result<(Vec<EpisodeOutcome>, Vec<Option<Physics>>)> {
    let mut outs = Vec::with_capacity(specs.len());
    let mut physics = Vec::with_capacity(specs.len());
    for e in specs {
        match plant.as_deref_mut() {
            Some(plant) => {
                let (o, p) =
                    crate::task::so101::run_episode(c, policy, plant, e.scene_seed, settings)?;
                outs.push(o);
                physics.push(Some(p));
            }
            None => {
                outs.push(run_episode(c, policy, e, settings)?);
                physics.push(None);
            }
        }
        each();
    }
    Ok((outs, physics))
}

/// Runs `chunkrt eval`.
pub fn run(mut args: EvalArgs) -> anyhow::Result<()> {
    let so101 = args.task == crate::task::TaskKind::So101;
    anyhow::ensure!(
        so101 || args.seeds.is_none(),
        "--seeds chooses the SO-101's episodes: pass --task so101 (the reach task's episodes \
         are its held-out scenes)"
    );
    let cfg = eval_config(&mut args, so101)?;
    anyhow::ensure!(
        so101 || !args.expert_plan,
        "--expert-plan replays the SO-101 expert's plans: pass --task so101"
    );
    if args.open_loop {
        anyhow::ensure!(!so101, "--open-loop probes the reach task");
        anyhow::ensure!(
            args.remote.is_none(),
            "--open-loop probes the policy in process; it does not take --remote"
        );
        return run_probe(&cfg, &args);
    }
    let plan = SweepPlan::resolve(&args, so101)?;
    let t0 = Instant::now();
    let (cells, rows) = sweep_with_progress(&cfg, &args.strategies, &plan, t0)?;
    write_results(&args.out, &cells, &rows, so101)?;
    if let Some(d) = args.switch_plot {
        anyhow::ensure!(!so101, "--switch-plot draws the reach task");
        draw_switch_plot(&cfg, d, &args.strategies, &args.out)?;
    }
    let png = args.out.join("eval.png");
    match plot(&png, &cells) {
        Ok(()) => println!("plot: {}", png.display()),
        Err(e) => eprintln!(
            "[eval] no plot: {}",
            chunkrt_bench::report::plot_error_text(&e)
        ),
    }
    print_headline(&cells, &plan, t0);
    Ok(())
}

/// The configuration the sweep runs: `--config` (for the SO-101 `config/so101.toml`) with
/// `--checkpoint` or `--remote`. Fills in the task's default checkpoint and strategies.
fn eval_config(args: &mut EvalArgs, so101: bool) -> anyhow::Result<Config> {
    let mut cfg = match &args.config {
        Some(p) => Config::load(p)?,
        None if so101 => Config::load(Path::new("config/so101.toml")).context(
            "--task so101 runs the SO-101's configuration: pass --config config/so101.toml",
        )?,
        None => Config::embedded_default(),
    };
    if so101
        && args.checkpoint.is_none()
        && args.remote.is_none()
        && cfg.policy.checkpoint.is_none()
    {
        args.checkpoint = Some(PathBuf::from("models/so101_pi05"));
    }
    if args.strategies.is_empty() {
        args.strategies = if so101 {
            vec!["replace", "crossfade", "temporal_ensemble", "rtc"]
        } else {
            vec!["sync", "replace", "crossfade", "temporal_ensemble", "rtc"]
        }
        .into_iter()
        .map(String::from)
        .collect();
    }
    if let Some(c) = &args.checkpoint {
        cfg.policy.checkpoint = Some(
            std::fs::canonicalize(c)
                .with_context(|| format!("checkpoint {} does not exist", c.display()))?,
        );
        if cfg.policy.kind.is_none() {
            cfg.policy.kind = Some(chunkrt_controller::config::ModelKind::Pi05);
        }
    }
    if let Some(url) = &args.remote {
        cfg.policy.source = chunkrt_controller::config::PolicySource::Remote;
        cfg.policy.url = Some(url.clone());
        if cfg.policy.kind.is_none() {
            cfg.policy.kind = Some(chunkrt_controller::config::ModelKind::Pi05);
        }
    }
    Ok(cfg)
}

/// What the sweep runs, resolved from the arguments.
struct SweepPlan {
    delays: Vec<u64>,
    /// Episodes per cell.
    episodes: usize,
    /// Episode limit (s).
    max_seconds: f64,
    world: World,
}

impl SweepPlan {
    /// `--quick`'s delays, episodes and limit, or the arguments' (`--seeds A..B`: B − A
    /// episodes), and the world the episodes run in.
    fn resolve(args: &EvalArgs, so101: bool) -> anyhow::Result<SweepPlan> {
        let max_seconds_arg = args.max_seconds.unwrap_or(if so101 {
            crate::task::so101::MAX_SECONDS
        } else {
            8.0
        });
        let (delays, episodes, max_seconds): (Vec<u64>, usize, f64) = if args.quick {
            (
                vec![0, 2.min(args.max_delay)],
                2,
                if so101 { 1.0 } else { 3.0 },
            )
        } else {
            (
                if args.delays.is_empty() {
                    (0..=args.max_delay).collect()
                } else {
                    args.delays.clone()
                },
                args.episodes,
                max_seconds_arg,
            )
        };
        // --seeds A..B: B − A episodes from A (a quick run plays the first two)
        let episodes = match &args.seeds {
            Some(r) if args.quick => episodes.min((r.end - r.start) as usize),
            Some(r) => (r.end - r.start) as usize,
            None => episodes,
        };
        anyhow::ensure!(episodes > 0, "--episodes must be > 0");
        let world = world(args, so101, max_seconds)?;
        Ok(SweepPlan {
            delays,
            episodes,
            max_seconds,
            world,
        })
    }
}

/// What moves during the episodes: `--drift-hz` and `--retarget-at`, checked against the
/// episode limit `max_seconds`; and the SO-101's options.
fn world(args: &EvalArgs, so101: bool, max_seconds: f64) -> anyhow::Result<World> {
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
    Ok(World {
        retarget_at: args.retarget_at,
        drift,
        so101,
        expert_plan: args.expert_plan,
        first_seed: args.seeds.as_ref().map(|r| r.start),
    })
}

/// [`sweep`] with a progress line on stderr (redrawn on a terminal, else every 20 s); `t0`:
/// when the run started.
fn sweep_with_progress(
    cfg: &Config,
    strategies: &[String],
    plan: &SweepPlan,
    t0: Instant,
) -> anyhow::Result<(Vec<Cell>, Vec<EpisodeRow>)> {
    let tty = std::io::stderr().is_terminal();
    let mut last = 0.0;
    let (cells, rows) = sweep(
        cfg,
        strategies,
        &plan.delays,
        plan.episodes,
        plan.max_seconds,
        plan.world,
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
    Ok((cells, rows))
}

/// The table on stdout and in `eval.md`, the cells in `eval.csv`, the episodes in
/// `episodes.csv`; for the SO-101 also its physics report and `so101_episodes.csv`.
fn write_results(
    out: &Path,
    cells: &[Cell],
    rows: &[EpisodeRow],
    so101: bool,
) -> anyhow::Result<()> {
    let md = markdown(cells);
    println!("{md}");
    std::fs::create_dir_all(out).with_context(|| format!("cannot create {}", out.display()))?;
    std::fs::write(out.join("eval.md"), &md)?;
    write_cells_csv(&out.join("eval.csv"), cells)?;
    write_episodes_csv(&out.join("episodes.csv"), rows, so101)?;
    if so101 {
        let text = report::so101_physics(cells, rows);
        println!("{text}");
        std::fs::write(out.join("so101_physics.md"), &text)?;
        write_so101_episodes_csv(&out.join("so101_episodes.csv"), rows)?;
    }
    Ok(())
}

/// One row per cell.
fn write_cells_csv(path: &Path, cells: &[Cell]) -> anyhow::Result<()> {
    let mut csv = std::fs::File::create(path)?;
    writeln!(
        csv,
        "strategy,delay_steps,episodes,successes,ci_low,ci_high,time_to_target_s,max_switch_jump_rad,p90_switch_jump_rad,rms_jerk,hold_ticks,reaction_time_s,reacted"
    )?;
    for c in cells {
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
    Ok(())
}

/// One row per episode.
fn write_episodes_csv(path: &Path, rows: &[EpisodeRow], so101: bool) -> anyhow::Result<()> {
    let mut csv = std::fs::File::create(path)?;
    writeln!(
        csv,
        "strategy,delay_steps,scene_seed,color,success,wrong_target,min_distance_m,time_to_target_s,expert_time_s,chunks,max_switch_jump_rad,reaction_time_s"
    )?;
    for r in rows {
        let o = &r.outcome;
        // how long the scripted expert's motion from the same start takes (reach)
        let expert = if so101 {
            f64::NAN
        } else {
            crate::task::expert::Reach::plan(
                &r.spec.start,
                &crate::task::ReachScene::from_seed(r.spec.scene_seed),
                r.spec.color,
                0.0,
            )
            .map_or(f64::NAN, |p| p.duration)
        };
        writeln!(
            csv,
            "{},{},{},{},{},{},{:.4},{},{:.3},{},{:.4},{}",
            r.strategy,
            r.delay,
            r.spec.scene_seed,
            if so101 { "-" } else { r.spec.color.name() },
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
    Ok(())
}

/// One row per SO-101 episode, with its physics.
fn write_so101_episodes_csv(path: &Path, rows: &[EpisodeRow]) -> anyhow::Result<()> {
    let mut csv = std::fs::File::create(path)?;
    writeln!(
        csv,
        "strategy,delay_steps,seed,success,time_to_success_s,carried,min_goal_distance_m,tracking_p50_rad,tracking_p99_rad,tracking_max_rad,jaw_closes,jaw_opens,jaw_flips_at_switch,max_switch_jump_rad,rms_jerk,hold_ticks"
    )?;
    for r in rows {
        let (o, p) = (&r.outcome, r.physics.unwrap_or_default());
        writeln!(
            csv,
            "{},{},{},{},{},{},{:.4},{:.4},{:.4},{:.4},{},{},{},{:.4},{:.1},{}",
            r.strategy,
            r.delay,
            r.spec.scene_seed,
            o.success as u8,
            o.time_to_target
                .map_or(String::new(), |t| format!("{t:.3}")),
            p.carried as u8,
            o.min_distance,
            p.tracking_p50,
            p.tracking_p99,
            p.tracking_max,
            p.jaw_closes,
            p.jaw_opens,
            p.jaw_flips_at_switch,
            o.smoothness.max_switch_jump_target,
            o.smoothness.rms_jerk,
            o.hold_ticks
        )?;
    }
    Ok(())
}

/// `--switch-plot`: `switch.png` in `out`, and its lines on stdout.
fn draw_switch_plot(
    cfg: &Config,
    delay: u64,
    strategies: &[String],
    out: &Path,
) -> anyhow::Result<()> {
    let png = out.join("switch.png");
    for line in switch::switch_plot(cfg, delay, strategies, &png)? {
        println!("{line}");
    }
    println!("switch plot: {}", png.display());
    Ok(())
}

/// One line: the best strategy at the largest delay vs synchronous execution.
fn print_headline(cells: &[Cell], plan: &SweepPlan, t0: Instant) {
    let dmax = *plan.delays.last().unwrap_or(&0);
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
            cells.len() * plan.episodes
        );
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn measured_state_variants_are_named_by_a_suffix() {
        let v = |base, measured, jacobian| Variant {
            base,
            measured,
            jacobian,
        };
        assert_eq!(split_variant("rtc/measured"), v("rtc", true, None));
        assert_eq!(split_variant("rtc"), v("rtc", false, None));
        assert_eq!(
            split_variant("rtc/vjp/measured"),
            v("rtc", true, Some(Jacobian::Vjp))
        );
        let cfg = Config::embedded_default();
        assert_eq!(cfg.execution.rtc_jacobian, Jacobian::Identity);
        let (c, _) = cell_config(&cfg, "rtc/vjp", 2).unwrap();
        assert_eq!(c.execution.rtc_jacobian, Jacobian::Vjp);
        let (c, _) = cell_config(&cfg, "rtc/identity", 2).unwrap();
        assert_eq!(c.execution.rtc_jacobian, Jacobian::Identity);
        for bad in [
            "sync/measured",
            "rtc/future",
            "magic",
            "replace/identity",
            "rtc/measured/vjp",
            "sync/vjp",
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
