//! `chunkrt train`: trains the reach task's π0.5 with chunkrt's own flow-matching loss.
//!
//! 1. The dataset (expert demonstrations, `task::dataset`) is loaded, or recorded when missing.
//! 2. openpi's recipe: the arm joints' actions relative to the observed state (openpi's
//!    `DeltaActions`, from the model config's `delta_action_mask`; the gripper stays absolute),
//!    quantile norm stats of state and actions, the π0.5 prompt with the discretised state
//!    (the 256 state-bin token embeddings start as Fourier features of the bin value), t ~ Beta(1.5, 1)·0.999 + 0.001, x_t = t·ε + (1 − t)·a, loss
//!    ‖(ε − a) − v(x_t, t)‖², AdamW with warm-up, cosine decay and gradient clipping at 1.
//!    Every op runs in its differentiable form (SigLIP, both experts, the heads). The state is
//!    augmented: the gripper's state flipped in 30 % of the samples (the robot's gripper is not
//!    always where the expert's was) and N(0, 0.01) on the arm joints' normalised state.
//!    Two auxiliary heads train with the model and are not saved (`--aux-weight`, `--goal-weight`):
//!    the targets' positions from the pooled image tokens, and the prompted target's joint solution
//!    from the VLM's hidden state. Without them the small model learned to ignore its image and
//!    prompt (`BENCHMARKS.md` §6).
//! 3. Every `--val-every-min` minutes the weights are written as a checkpoint (openpi key names,
//!    `config.json`, `norm_stats.json`, the task's `tokenizer.json`) and driven closed-loop
//!    through held-out episodes by the real executor (`task::sim`). `--out` gets the last
//!    checkpoint (`--keep last`, the default) or the best by validation (`--keep best`).
//!
//! A progress line shows step, loss, samples/s, time and the last validation.

use std::io::{IsTerminal, Write};
use std::path::{Path, PathBuf};
use std::time::Instant;

use anyhow::Context;
use candle_core::backprop::GradStore;
use candle_core::{DType, Device, Tensor, Var};
use candle_nn::{AdamW, Optimizer, ParamsAdamW, VarBuilder, VarMap};
use rand::{Rng, SeedableRng};

use chunkrt_controller::config::{CameraConfig, Config};

use crate::task::dataset::{
    gaussian, random_start, Dataset, DatasetSpec, DriftMix, TRAIN_SEED_BASE,
};
use crate::task::sim::{run_episode, EpisodeSpec, SimSettings};
use crate::task::{home_pose, task_camera, vocab, TargetColor, TASK_DOF};
use chunkrt_controller::inference::PolicySource;
use chunkrt_policy::config::ModelConfig;
use chunkrt_policy::model::{ModelInputs, PiModel};
use chunkrt_policy::preprocess::{
    discretize_state, normalize, resize_with_pad, to_model_chw, NormMode, NormStats,
    PromptTokenizer, Stats,
};

mod args;
mod data;

pub use args::{BinInit, Keep, TaskKind, TrainArgs};

use data::*;
pub use data::{column_stats, model_space_actions, AUX_OUTPUTS, GOAL_OUTPUTS};

/// The model configuration of the embedded default policy.
pub const MODEL_CONFIG: &str = include_str!("../../config/reach_model.json");
/// The model configuration of the SO-101 policy (`chunkrt train --task so101`).
pub const SO101_MODEL_CONFIG: &str = include_str!("../../config/so101_model.json");
/// Episode seeds of the SO-101's held-out loss data (training records from 100, validation
/// runs from [`crate::task::so101::VAL_SEED_BASE`], `chunkrt eval` from
/// [`crate::task::so101::EVAL_SEED_BASE`]).
pub const SO101_LOSS_SEED_BASE: u64 = 5_000;

/// Writes Fourier features of the bin value into the embedding rows of the 256 state-bin
/// tokens (ids `SPECIALS.len()..+256`, `task::vocab`): row k holds sin / cos(π·2^(7j/(W/2))·k/255),
/// j < W/2, scaled so each entry has the RMS of the N(0, 1/W) init. A learned table starts with
/// no notion that bin 120 lies between 119 and 121; this one does, and training refines it.
pub fn init_state_bin_embeddings(vm: &VarMap) -> anyhow::Result<()> {
    let data = vm
        .data()
        .lock()
        .map_err(|_| anyhow::anyhow!("the VarMap lock is poisoned"))?;
    let var = [
        chunkrt_policy::checkpoint::EMBED,
        chunkrt_policy::checkpoint::LM_HEAD,
    ]
    .iter()
    .find_map(|n| data.get(*n))
    .context("the model has no token embedding")?;
    let mut rows = var.as_tensor().to_vec2::<f32>()?;
    let first = vocab::SPECIALS.len();
    anyhow::ensure!(
        rows.len() >= first + 256,
        "vocabulary too small for 256 bins"
    );
    let w = rows[0].len();
    let half = w / 2;
    let amp = (1.0 / w as f64).sqrt() * std::f64::consts::SQRT_2;
    for (k, row) in rows[first..first + 256].iter_mut().enumerate() {
        let v = k as f64 / 255.0;
        for j in 0..half {
            let f = std::f64::consts::PI * 2f64.powf(7.0 * j as f64 / half as f64);
            row[2 * j] = (amp * (f * v).sin()) as f32;
            row[2 * j + 1] = (amp * (f * v).cos()) as f32;
        }
    }
    let t = Tensor::new(rows, var.device())?;
    var.set(&t)?;
    Ok(())
}

/// What `chunkrt train` records: `scenes` scenes from seed `scene_base`, the expert moving with
/// `expert`, `keep_share` of each episode's steps, frames of the task camera, and `drift`'s
/// share of moving-target episodes.
#[allow(clippy::too_many_arguments)]
pub fn dataset_spec(
    cfg: &Config,
    mcfg: &ModelConfig,
    scenes: usize,
    scene_base: u64,
    seed: u64,
    keep_share: f64,
    expert: crate::task::expert::Profile,
    drift: Option<DriftMix>,
) -> anyhow::Result<DatasetSpec> {
    let cam = task_camera(cfg)?;
    let history_steps = history_steps(cfg, mcfg)?;
    Ok(DatasetSpec {
        scenes,
        scene_base,
        seed,
        horizon: mcfg.action_horizon,
        action_rate_hz: cfg.policy.action_rate_hz,
        camera: cam.name.clone(),
        width: cam.width as usize,
        height: cam.height as usize,
        hold_steps: 5,
        perturb_share: 0.5,
        perturb_std: 0.2,
        home: home_pose(cfg),
        keep_share,
        profile: expert,
        drift,
        history_steps,
    })
}

/// Policy steps between the task camera's frame and the model's delayed view of it (0: the
/// model has none). The view must be of the task camera, one at most, its delay a whole number
/// of policy periods (the recorder renders at the policy rate).
pub fn history_steps(cfg: &Config, mcfg: &ModelConfig) -> anyhow::Result<usize> {
    let cam = task_camera(cfg)?;
    match mcfg.delayed_views.as_slice() {
        [] => Ok(0),
        [v] => {
            anyhow::ensure!(
                v.camera == cam.name,
                "the model's delayed view {:?} is of camera {:?}; the reach task records {}",
                v.name,
                v.camera,
                cam.name
            );
            let steps = v.delay_ms * 1e-3 * cfg.policy.action_rate_hz;
            anyhow::ensure!(
                steps >= 0.5 && (steps - steps.round()).abs() < 1e-6,
                "the model's delayed view {:?}: {} ms is not a whole number of policy periods \
                 ({} ms at {} Hz)",
                v.name,
                v.delay_ms,
                1e3 / cfg.policy.action_rate_hz,
                cfg.policy.action_rate_hz
            );
            Ok(steps.round() as usize)
        }
        _ => anyhow::bail!("the reach task records one delayed view at most"),
    }
}

/// The model configuration `json` with a delayed view of `camera`, `delay_ms` earlier, as its
/// second image input `<camera>_prev` (unchanged when `delay_ms` is 0). The vision tower is
/// shared by every image, so the weights do not change: a checkpoint trained without a history
/// can be fine-tuned with one.
pub fn with_history(json: &str, camera: &str, delay_ms: f64) -> anyhow::Result<String> {
    if delay_ms == 0.0 {
        return Ok(json.to_string());
    }
    let view = format!("{camera}_prev");
    edit_model_json(
        json,
        &[
            ("image_keys_in_order", serde_json::json!([camera, view])),
            (
                "delayed_views",
                serde_json::json!([{ "name": view, "camera": camera, "delay_ms": delay_ms }]),
            ),
        ],
        &format!(
            " Sees a frame history: beside {camera}'s newest frame, the one it took {delay_ms} \
             ms before (`chunkrt train --history-ms {delay_ms}`)."
        ),
    )
}

/// `json` (a model configuration) with `entries` set and `about` appended to its description.
fn edit_model_json(
    json: &str,
    entries: &[(&str, serde_json::Value)],
    about: &str,
) -> anyhow::Result<String> {
    let mut v: serde_json::Value =
        serde_json::from_str(json).context("the model configuration is not JSON")?;
    let obj = v
        .as_object_mut()
        .context("the model configuration is not a JSON object")?;
    for (key, value) in entries {
        obj.insert(key.to_string(), value.clone());
    }
    if let Some(serde_json::Value::String(text)) = obj.get_mut("about") {
        text.push_str(about);
    }
    Ok(serde_json::to_string_pretty(&v)? + "\n")
}

/// One data-parallel worker's share of a step: gradients, flow-matching loss, the auxiliary
/// heads' losses (localisation, goal) and its number of samples.
type WorkerResult = (GradStore, f64, [f64; 2], usize);

/// Scene seeds of the held-out loss data (below the training seeds, apart from validation
/// 1000.., `chunkrt eval` 2000.. and the open-loop probe 4000..).
pub const LOSS_SCENE_BASE: u64 = 6_000;
/// Noise levels at which the held-out loss is reported: t near 1 is almost pure noise (the
/// model must commit to a chunk from the observation alone: which target, how far), t near 0
/// is almost the chunk itself (fine detail).
pub const LOSS_TIMES: [f32; 4] = [0.1, 0.4, 0.7, 0.95];

/// Writes a checkpoint directory: `model.safetensors` (openpi key names), `config.json`,
/// `norm_stats.json`, `tokenizer.json`.
pub fn write_checkpoint(
    dir: &Path,
    vm: &VarMap,
    model_config_json: &str,
    norm: &NormStats,
) -> anyhow::Result<()> {
    std::fs::create_dir_all(dir).with_context(|| format!("cannot create {}", dir.display()))?;
    vm.save(dir.join("model.safetensors"))?;
    std::fs::write(dir.join("config.json"), model_config_json)?;
    std::fs::write(dir.join("norm_stats.json"), norm.to_json())?;
    std::fs::write(dir.join("tokenizer.json"), vocab::tokenizer_json())?;
    Ok(())
}

/// Held-out validation / evaluation episodes: scenes `first..first + n`, alternating prompts,
/// start poses from `seed`.
pub fn held_out_episodes(cfg: &Config, first: u64, n: usize, seed: u64) -> Vec<EpisodeSpec> {
    let home = home_pose(cfg);
    let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(seed);
    (0..n)
        .map(|i| EpisodeSpec {
            scene_seed: first + (i / 2) as u64,
            color: TargetColor::ALL[i % 2],
            start: random_start(&mut rng, &home),
        })
        .collect()
}

/// Closed-loop success of the checkpoint in `dir` over `episodes` (strategy `replace`, no
/// delay, at most `max_seconds` each). Returns (successes, mean time to target of successes).
pub fn validate(
    cfg: &Config,
    dir: &Path,
    episodes: &[EpisodeSpec],
    max_seconds: f64,
) -> anyhow::Result<(usize, f64)> {
    let (c, mut policy) = validation_policy(cfg, dir)?;
    let settings = SimSettings::validation(max_seconds);
    let mut ok = 0;
    let mut t = 0.0;
    for e in episodes {
        let r = run_episode(&c, &mut policy, e, &settings)?;
        if r.success {
            ok += 1;
            t += r.time_to_target.unwrap_or(0.0);
        }
    }
    Ok((ok, if ok > 0 { t / ok as f64 } else { f64::NAN }))
}

/// Closed-loop success of the SO-101 checkpoint in `dir` over episodes `seeds` in the package's
/// physics (strategy `replace`, no delay).
pub fn validate_so101(
    cfg: &Config,
    dir: &Path,
    seeds: std::ops::Range<u64>,
    max_seconds: f64,
) -> anyhow::Result<(usize, f64)> {
    let (c, mut policy) = validation_policy(cfg, dir)?;
    crate::task::so101::success_rate(&c, &mut policy, seeds, max_seconds)
}

/// The configuration a validation runs (the π0.5 checkpoint in `dir`, strategy `replace`) and
/// its policy, loaded.
fn validation_policy(cfg: &Config, dir: &Path) -> anyhow::Result<(Config, PolicySource)> {
    let mut c = cfg.clone();
    c.policy.checkpoint = Some(std::fs::canonicalize(dir)?);
    c.policy.kind = Some(chunkrt_controller::config::ModelKind::Pi05);
    c.execution.strategy = chunkrt_controller::config::Strategy::Replace;
    let policy = PolicySource::load(&c)?;
    Ok((c, policy))
}

/// The recorded state of every step channel (a gripper, the SO-101's jaw) snapped to the nearer
/// end of its range, as the controller shows it to the policy (`Conditioner::ask`): the jaw
/// closed on a block reads as closed, not as the in-between angle the block leaves it at.
pub fn snap_step_channels(ds: &mut Dataset, cfg: &Config) {
    let d = ds.n_dof;
    for (j, joint) in cfg.robot.joints.iter().enumerate().take(d) {
        if !joint.step {
            continue;
        }
        let (lo, hi) = (joint.position_min as f32, joint.position_max as f32);
        let mid = 0.5 * (lo + hi);
        for v in ds.state.iter_mut().skip(j).step_by(d) {
            *v = if *v >= mid { hi } else { lo };
        }
    }
}

/// An SO-101 dataset fits the configuration: its task, joints, frame size and rate.
fn check_so101_dataset(
    ds: &Dataset,
    path: &Path,
    cam: &chunkrt_controller::config::CameraConfig,
    cfg: &Config,
) -> anyhow::Result<()> {
    anyhow::ensure!(
        ds.task == "so101",
        "{} holds the {} task's episodes, not the SO-101's",
        path.display(),
        ds.task
    );
    anyhow::ensure!(
        ds.n_dof == cfg.n_dof()
            && (ds.width, ds.height) == (cam.width as usize, cam.height as usize),
        "{}: {} joints and {}x{} frames; the configuration has {} joints and a {}x{} camera: \
         delete it to record it anew",
        path.display(),
        ds.n_dof,
        ds.width,
        ds.height,
        cfg.n_dof(),
        cam.width,
        cam.height
    );
    Ok(())
}

/// The model configuration `json` with `rtc_prefix_max` set to `n` (left out when 0).
pub fn with_rtc_prefix(json: &str, n: usize) -> anyhow::Result<String> {
    if n == 0 {
        return Ok(json.to_string());
    }
    edit_model_json(
        json,
        &[("rtc_prefix_max", n.into())],
        &format!(
            " Trained with a committed action prefix of up to {n} actions (training-time RTC, \
             `chunkrt train --rtc-prefix {n}`): runs strategy rtc_trained."
        ),
    )
}

fn fmt_min(s: f64) -> String {
    format!("{}:{:02}", (s / 60.0) as u64, (s % 60.0) as u64)
}
/// Runs `chunkrt train`.
pub fn run(args: TrainArgs) -> anyhow::Result<()> {
    // Data parallel over `--threads` workers, each running candle single-threaded: the model's
    // matrices are too small for candle's spinning thread pool to pay (5x slower per step with
    // 2 pool threads than with 1 on this 2-core machine under load).
    std::env::set_var("RAYON_NUM_THREADS", "1");
    let plan = Plan::resolve(args)?;

    // 1. data
    let ds = load_or_record_dataset(&plan)?;

    // 2. normalisation, tokenizer, model
    let actions = model_space_actions(&ds, &plan.mcfg.delta_action_mask);
    let norm = normalisation(&plan.args, &ds, &actions)?;
    let tok = task_tokenizer()?;
    let batcher = Batcher::new(&ds, &actions, &plan.mcfg, &norm, &tok)?;
    drop(actions);
    let mut trainer = Trainer::new(&plan)?;
    let held = held_out_data(&plan)?;
    let val = Validation::new(&plan, &held, &norm, &tok)?;
    let mut log = TrainLog::create(&plan.dataset_path)?;

    // 3. training, validated and checkpointed every --val-every-min minutes
    let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(plan.args.seed);
    let mut progress = Progress::start(plan.args.val_every_min);
    loop {
        let elapsed = progress.t0.elapsed().as_secs_f64();
        let done =
            progress.step >= plan.max_steps || (plan.budget_s > 0.0 && elapsed >= plan.budget_s);
        if done || elapsed >= progress.next_val {
            val.validate_and_checkpoint(&trainer, &mut log, &mut progress, elapsed)?;
            if done {
                break;
            }
        }
        let lr = learning_rate(
            plan.args.lr,
            progress.step,
            plan.max_steps,
            elapsed,
            plan.budget_s,
        );
        trainer.opt.set_learning_rate(lr);
        let draw = sample_batch(&mut rng, &plan, ds.len());
        let losses = trainer.train_step(&batcher, &draw, &plan)?;
        let (l, step) = (losses[0], progress.step);
        anyhow::ensure!(l.is_finite(), "loss became {l} at step {step}");
        progress.advance(losses, lr, &mut log, &plan)?;
    }
    std::fs::remove_dir_all(&plan.candidate).ok();
    eprintln!(
        "[train] done: {} steps in {}, best validation {}/{} episodes; checkpoint {}; log {}",
        progress.step,
        fmt_min(progress.t0.elapsed().as_secs_f64()),
        progress.best.unwrap_or(0),
        val.count,
        plan.out_dir.display(),
        log.path.display()
    );
    Ok(())
}

/// What a training run works with, resolved from its arguments.
struct Plan {
    /// The arguments (the goal head turned off for the SO-101).
    args: TrainArgs,
    so101: bool,
    /// Data-parallel workers.
    workers: usize,
    cfg: Config,
    /// The task camera.
    cam: CameraConfig,
    out_dir: PathBuf,
    /// Where each validation writes the checkpoint it drives.
    candidate: PathBuf,
    dataset_path: PathBuf,
    /// The model configuration as checkpoints get it, and parsed.
    model_json: String,
    mcfg: ModelConfig,
    /// Scenes to record.
    scenes: usize,
    /// Time budget (s; 0: none).
    budget_s: f64,
    max_steps: usize,
    batch: usize,
    /// Validation episodes.
    val_n: usize,
    drift: Option<DriftMix>,
}

impl Plan {
    fn resolve(mut args: TrainArgs) -> anyhow::Result<Plan> {
        let workers = args.threads.max(1);
        let so101 = args.task == TaskKind::So101;
        let cfg = train_config(&args, so101)?;
        let cam = if so101 {
            crate::task::so101::task_camera(&cfg)?.clone()
        } else {
            task_camera(&cfg)?.clone()
        };
        let out_dir = args.out.clone().unwrap_or_else(|| {
            PathBuf::from(if so101 {
                "models/so101_pi05"
            } else {
                "models/reach_pi05"
            })
        });
        let dataset_path = args.dataset.clone().unwrap_or_else(|| {
            PathBuf::from(if so101 {
                "target/chunkrt-train/so101_dataset.safetensors"
            } else {
                "target/chunkrt-train/dataset.safetensors"
            })
        });
        if so101 {
            anyhow::ensure!(
                args.history_ms == 0.0 && args.drift_share == 0.0,
                "--history-ms and --drift-share are the reach task's"
            );
            if args.goal_weight != 0.0 {
                eprintln!("[train] the goal head is the reach task's: off for the SO-101");
                args.goal_weight = 0.0;
            }
        }
        let (model_json, mcfg) = model_config(&args, so101, &cam)?;
        let (scenes, budget_s, max_steps, batch, val_n) = sizes(&args, so101);
        anyhow::ensure!(batch > 0, "--batch must be > 0");
        anyhow::ensure!(
            (0.0..=1.0).contains(&args.drift_share),
            "--drift-share {}: must be in [0, 1]",
            args.drift_share
        );
        let drift = (args.drift_share > 0.0).then(|| DriftMix::with_share(args.drift_share));
        let candidate = out_dir.with_extension("candidate");
        Ok(Plan {
            args,
            so101,
            workers,
            cfg,
            cam,
            out_dir,
            candidate,
            dataset_path,
            model_json,
            mcfg,
            scenes,
            budget_s,
            max_steps,
            batch,
            val_n,
            drift,
        })
    }
}

/// `--config`, or the task's configuration.
fn train_config(args: &TrainArgs, so101: bool) -> anyhow::Result<Config> {
    Ok(match &args.config {
        Some(p) => Config::load(p)?,
        None if so101 => Config::load(Path::new("config/so101.toml")).context(
            "--task so101 trains for the SO-101's configuration: pass --config config/so101.toml",
        )?,
        None => Config::embedded_default(),
    })
}

/// The model configuration (`--model-config` or the task's) with `--rtc-prefix` and
/// `--history-ms` applied, as JSON and parsed; it must fit the task's vocabulary and camera.
fn model_config(
    args: &TrainArgs,
    so101: bool,
    cam: &CameraConfig,
) -> anyhow::Result<(String, ModelConfig)> {
    let model_json = match &args.model_config {
        Some(p) => {
            std::fs::read_to_string(p).with_context(|| format!("cannot read {}", p.display()))?
        }
        None if so101 => SO101_MODEL_CONFIG.to_string(),
        None => MODEL_CONFIG.to_string(),
    };
    let model_json = with_rtc_prefix(&model_json, args.rtc_prefix)?;
    let model_json = with_history(&model_json, &cam.name, args.history_ms)?;
    let mcfg = ModelConfig::from_json_str(&model_json)?;
    anyhow::ensure!(
        mcfg.vocab_size >= vocab::vocab_len(),
        "model vocab_size {} < the task vocabulary {}",
        mcfg.vocab_size,
        vocab::vocab_len()
    );
    anyhow::ensure!(
        mcfg.cameras.first() == Some(&cam.name),
        "the model's first camera is {:?}, the task camera is {}",
        mcfg.cameras.first(),
        cam.name
    );
    Ok((model_json, mcfg))
}

/// Scenes to record, time budget (s), steps, batch size and validation episodes: the
/// arguments', or `--quick`'s.
fn sizes(args: &TrainArgs, so101: bool) -> (usize, f64, usize, usize, usize) {
    let default_scenes = if so101 { 300 } else { 20_000 };
    if args.quick {
        (
            if so101 { 2 } else { 3 },
            0.0,
            6.min(args.max_steps),
            args.batch.min(4),
            1,
        )
    } else {
        (
            args.scenes.unwrap_or(default_scenes),
            args.minutes * 60.0,
            args.max_steps,
            args.batch,
            args.val_episodes,
        )
    }
}

/// The training data, with its step channels snapped as the policy sees them: the SO-101
/// expert's episodes, or the reach task's loaded from the dataset path or recorded there.
fn load_or_record_dataset(plan: &Plan) -> anyhow::Result<Dataset> {
    let mut ds = if plan.so101 {
        so101_dataset(plan)?
    } else if plan.dataset_path.exists() && !plan.args.quick {
        load_reach_dataset(plan)?
    } else {
        record_reach_dataset(plan)?
    };
    snap_step_channels(&mut ds, &plan.cfg);
    anyhow::ensure!(!ds.is_empty(), "the dataset is empty");
    anyhow::ensure!(
        (ds.action_rate_hz - plan.cfg.policy.action_rate_hz).abs() < 1e-9,
        "dataset recorded at {} Hz, the configuration's policy runs at {} Hz",
        ds.action_rate_hz,
        plan.cfg.policy.action_rate_hz
    );
    Ok(ds)
}

/// The SO-101 expert's episodes (seeds 100..), recorded when the file is missing, and always
/// anew (into a temporary file) with `--quick`.
fn so101_dataset(plan: &Plan) -> anyhow::Result<Dataset> {
    let (args, scenes) = (&plan.args, plan.scenes);
    let path = if args.quick {
        std::env::temp_dir().join(format!(
            "chunkrt-so101-quick-{}.safetensors",
            std::process::id()
        ))
    } else {
        plan.dataset_path.clone()
    };
    if args.quick || !path.exists() {
        eprintln!(
            "[train] recording the SO-101 expert: {scenes} episodes (seeds 100..) -> {}",
            path.display()
        );
        crate::task::so101::record(
            &path,
            100..100 + scenes as u64,
            plan.mcfg.action_horizon,
            plan.cam.width as usize,
            plan.workers,
        )?;
    }
    eprintln!("[train] dataset {}", path.display());
    let ds = Dataset::load(&path)?;
    if args.quick {
        std::fs::remove_file(&path).ok();
    }
    check_so101_dataset(&ds, &path, &plan.cam, &plan.cfg)?;
    Ok(ds)
}

/// The reach task's recorded dataset, which must have been recorded as this run asks.
fn load_reach_dataset(plan: &Plan) -> anyhow::Result<Dataset> {
    let (args, dataset_path) = (&plan.args, &plan.dataset_path);
    eprintln!("[train] dataset {}", dataset_path.display());
    let ds = Dataset::load(dataset_path)?;
    anyhow::ensure!(
        ds.is_reach(),
        "{} holds the {} task's episodes; pass --task {}",
        dataset_path.display(),
        ds.task,
        ds.task
    );
    anyhow::ensure!(
        ds.expert == args.expert,
        "{} was recorded with the {} expert, training asks for {}: delete the file to record \
         it anew, or pass --expert {}",
        dataset_path.display(),
        ds.expert.name(),
        args.expert.name(),
        ds.expert.name()
    );
    anyhow::ensure!(
        ds.drift_share == args.drift_share,
        "{} was recorded with --drift-share {}, training asks for {}: delete the file to \
         record it anew, or pass --drift-share {}",
        dataset_path.display(),
        ds.drift_share,
        args.drift_share,
        ds.drift_share
    );
    let steps = history_steps(&plan.cfg, &plan.mcfg)?;
    anyhow::ensure!(
        ds.history_steps == steps,
        "{} was recorded with a frame history of {} policy steps, the model takes {steps}: \
         delete the file to record it anew",
        dataset_path.display(),
        ds.history_steps
    );
    Ok(ds)
}

/// Records the reach task's expert demonstrations and saves them at the dataset path.
fn record_reach_dataset(plan: &Plan) -> anyhow::Result<Dataset> {
    let args = &plan.args;
    let spec = dataset_spec(
        &plan.cfg,
        &plan.mcfg,
        plan.scenes,
        TRAIN_SEED_BASE,
        args.seed,
        args.keep_share,
        args.expert,
        plan.drift,
    )?;
    let t0 = Instant::now();
    let ds = Dataset::generate(&spec, |done, total| {
        if done % 50 == 0 || done == total {
            eprint!("\r[train] recording expert demonstrations: {done}/{total} scenes");
        }
    });
    eprintln!(
        "\n[train] {} samples from {} episodes in {:.1} s",
        ds.len(),
        ds.episodes(),
        t0.elapsed().as_secs_f64()
    );
    ds.save(&plan.dataset_path)?;
    eprintln!("[train] dataset written to {}", plan.dataset_path.display());
    Ok(ds)
}

/// Quantile statistics of the dataset's state and of its `actions` in the model's space.
fn normalisation(args: &TrainArgs, ds: &Dataset, actions: &[f32]) -> anyhow::Result<NormStats> {
    // fine-tuning keeps the normalisation its weights were trained with
    let init_norm = args
        .init
        .as_ref()
        .map(|d| d.join("norm_stats.json"))
        .filter(|p| p.exists());
    Ok(match &init_norm {
        Some(p) => {
            eprintln!("[train] norm stats of {}", p.display());
            NormStats::from_file(p)?
        }
        None => NormStats {
            state: column_stats(&ds.state, ds.n_dof),
            actions: column_stats(actions, ds.n_dof),
        },
    })
}

/// The task's prompt tokenizer, loaded from a temporary `tokenizer.json`.
fn task_tokenizer() -> anyhow::Result<PromptTokenizer> {
    let tok_dir = std::env::temp_dir().join(format!("chunkrt-tok-{}", std::process::id()));
    std::fs::create_dir_all(&tok_dir)?;
    std::fs::write(tok_dir.join("tokenizer.json"), vocab::tokenizer_json())?;
    let tok = PromptTokenizer::from_file(&tok_dir.join("tokenizer.json"))?;
    std::fs::remove_dir_all(&tok_dir).ok();
    Ok(tok)
}

/// Held-out loss data: scenes no training sample comes from, step channels snapped.
fn held_out_data(plan: &Plan) -> anyhow::Result<Dataset> {
    let (args, cfg) = (&plan.args, &plan.cfg);
    let mut held = if plan.so101 {
        let path = plan.dataset_path.with_extension("heldout.safetensors");
        let n = if args.quick { 1 } else { 10 };
        if args.quick || !path.exists() {
            crate::task::so101::record(
                &path,
                SO101_LOSS_SEED_BASE..SO101_LOSS_SEED_BASE + n,
                plan.mcfg.action_horizon,
                plan.cam.width as usize,
                1,
            )?;
        }
        let held = Dataset::load(&path)?;
        if args.quick {
            std::fs::remove_file(&path).ok();
        }
        check_so101_dataset(&held, &path, &plan.cam, cfg)?;
        held
    } else {
        held_out_dataset(
            cfg,
            &plan.mcfg,
            if args.quick { 1 } else { 60 },
            args.expert,
        )?
    };
    snap_step_channels(&mut held, cfg);
    Ok(held)
}

/// The model in training, its auxiliary heads, and AdamW over both.
struct Trainer {
    /// The model's variables (the heads' are not saved).
    vm: VarMap,
    model: PiModel,
    heads: AuxHeads,
    /// The model's variables, then the heads'.
    vars: Vec<Var>,
    opt: AdamW,
}

impl Trainer {
    /// The model (from `--init`, or new), the auxiliary heads, and the optimizer.
    fn new(plan: &Plan) -> anyhow::Result<Trainer> {
        let args = &plan.args;
        let dev = Device::Cpu;
        let vm = VarMap::new();
        let model = PiModel::new(&plan.mcfg, VarBuilder::from_varmap(&vm, DType::F32, &dev))?;
        match &args.init {
            Some(dir) => {
                let file = dir.join("model.safetensors");
                let mut vm = vm.clone();
                vm.load(&file)
                    .with_context(|| format!("cannot start from {}", file.display()))?;
                eprintln!("[train] starting from {}", file.display());
            }
            None if args.state_embedding == BinInit::Fourier => init_state_bin_embeddings(&vm)?,
            None => {}
        }
        let n_params: usize = vm.all_vars().iter().map(|v| v.elem_count()).sum();
        eprintln!(
            "[train] π0.5 {}: {n_params} parameters ({:.1} MB f32), batch {}, lr {}, budget {}",
            plan.out_dir.display(),
            n_params as f64 * 4.0 / 1e6,
            plan.batch,
            args.lr,
            fmt_min(plan.budget_s)
        );
        // the auxiliary heads live in their own VarMap: trained, never saved
        let aux_vm = VarMap::new();
        let heads = AuxHeads::new(
            &plan.mcfg,
            args,
            VarBuilder::from_varmap(&aux_vm, DType::F32, &dev),
        )?;
        let mut vars = vm.all_vars();
        vars.extend(aux_vm.all_vars());
        let opt = AdamW::new(
            vars.clone(),
            ParamsAdamW {
                lr: args.lr,
                beta1: 0.9,
                beta2: 0.95,
                eps: 1e-8,
                weight_decay: 1e-4,
            },
        )?;
        Ok(Trainer {
            vm,
            model,
            heads,
            vars,
            opt,
        })
    }

    /// One optimizer step on `draw`, data parallel over the plan's workers. Returns the
    /// batch-mean losses: flow matching, localisation, goal.
    fn train_step(
        &mut self,
        batcher: &Batcher,
        draw: &Draw,
        plan: &Plan,
    ) -> anyhow::Result<[f64; 3]> {
        let batch = plan.batch;
        let parts = forward_backward(
            &self.model,
            &self.heads,
            &plan.args,
            batcher,
            draw,
            plan.workers,
        )?;
        // the workers' losses weighted by their shares of the batch
        let batch_mean = |f: fn(&WorkerResult) -> f64| {
            parts.iter().map(|p| f(p) * p.3 as f64).sum::<f64>() / batch as f64
        };
        let losses = [
            batch_mean(|p| p.1),
            batch_mean(|p| p.2[0]),
            batch_mean(|p| p.2[1]),
        ];
        let grads = clipped_mean_gradient(&self.vars, parts, batch)?;
        self.opt.step(&grads)?;
        Ok(losses)
    }
}

/// The learning rate at `step`, `elapsed` s in: linear warm-up, then cosine to 10 % over the
/// budget (`budget_s`, or `max_steps` when that is further along).
fn learning_rate(lr: f64, step: usize, max_steps: usize, elapsed: f64, budget_s: f64) -> f64 {
    let warmup = 200usize;
    let progress = if budget_s > 0.0 {
        (elapsed / budget_s).max(step as f64 / max_steps as f64)
    } else {
        step as f64 / max_steps.max(1) as f64
    }
    .min(1.0);
    if step < warmup {
        lr * (step + 1) as f64 / warmup as f64
    } else {
        lr * (0.1 + 0.9 * 0.5 * (1.0 + (std::f64::consts::PI * progress).cos()))
    }
}

/// One step's random draws: the samples, their augmentation, and per sample `kspo` noises,
/// flow times and committed prefix lengths.
struct Draw {
    idx: Vec<usize>,
    aug: Vec<Augment>,
    /// Noise samples per observation.
    kspo: usize,
    noise: Vec<f32>,
    time: Vec<f32>,
    committed: Vec<usize>,
}

/// Draws a batch from the `n` samples of the dataset.
fn sample_batch(rng: &mut rand_chacha::ChaCha8Rng, plan: &Plan, n: usize) -> Draw {
    let (batch, args) = (plan.batch, &plan.args);
    let idx: Vec<usize> = (0..batch).map(|_| rng.gen_range(0..n)).collect();
    let aug: Vec<Augment> = (0..batch)
        .map(|_| {
            let mut a = Augment {
                // (the SO-101's jaw tells the task's phase: holding the block or not)
                flip_gripper: !plan.so101 && rng.gen_bool(0.3),
                ..Default::default()
            };
            for v in a.noise.iter_mut() {
                *v = 0.01 * gaussian(rng) as f32;
            }
            a
        })
        .collect();
    let (h, a) = (plan.mcfg.action_horizon, plan.mcfg.action_dim);
    // noise and times from the seeded generator (deterministic for a given seed)
    let kspo = args.samples_per_obs.max(1);
    let noise: Vec<f32> = (0..batch * kspo * h * a)
        .map(|_| gaussian(rng) as f32)
        .collect();
    let time: Vec<f32> = (0..batch * kspo)
        .map(|_| {
            let u: f64 = rng.gen_range(f64::MIN_POSITIVE..1.0);
            // Beta(1.5, 1) by inversion: F(x) = x^1.5
            (u.powf(1.0 / 1.5) * 0.999 + 0.001) as f32
        })
        .collect();
    // training-time RTC: the committed prefix length of each sample
    let committed: Vec<usize> = (0..batch * kspo)
        .map(|_| {
            if args.rtc_prefix > 0 {
                rng.gen_range(0..=args.rtc_prefix)
            } else {
                0
            }
        })
        .collect();
    Draw {
        idx,
        aug,
        kspo,
        noise,
        time,
        committed,
    }
}

/// Data parallel: each of `workers` threads runs forward + backward on its share of the batch.
fn forward_backward(
    model: &PiModel,
    heads: &AuxHeads,
    args: &TrainArgs,
    batcher: &Batcher,
    draw: &Draw,
    workers: usize,
) -> anyhow::Result<Vec<WorkerResult>> {
    let batch = draw.idx.len();
    let share = batch.div_ceil(workers);
    let results: Vec<anyhow::Result<WorkerResult>> = std::thread::scope(|sc| {
        let handles: Vec<_> = (0..batch)
            .step_by(share)
            .map(|lo| {
                let hi = (lo + share).min(batch);
                sc.spawn(move || worker_step(model, heads, args, batcher, draw, lo..hi))
            })
            .collect();
        handles
            .into_iter()
            .map(|h| {
                h.join()
                    .unwrap_or_else(|_| Err(anyhow::anyhow!("training worker panicked")))
            })
            .collect()
    });
    let mut parts = Vec::with_capacity(results.len());
    for r in results {
        parts.push(r?);
    }
    Ok(parts)
}

/// Forward and backward of samples `range` of `draw`: the flow-matching loss plus the
/// auxiliary heads' losses, weighted.
fn worker_step(
    model: &PiModel,
    heads: &AuxHeads,
    args: &TrainArgs,
    batcher: &Batcher,
    draw: &Draw,
    range: std::ops::Range<usize>,
) -> anyhow::Result<WorkerResult> {
    let (lo, hi, kspo) = (range.start, range.end, draw.kspo);
    let (h, a) = (batcher.cfg.action_horizon, batcher.cfg.action_dim);
    let n = hi - lo;
    let (inp, actions, aux, goal) = batcher.batch(&draw.idx[lo..hi], &draw.aug[lo..hi])?;
    let noise = &draw.noise[lo * kspo * h * a..hi * kspo * h * a];
    let noise = Tensor::from_slice(noise, (n * kspo, h, a), &Device::Cpu)?;
    let time = Tensor::from_slice(&draw.time[lo * kspo..hi * kspo], n * kspo, &Device::Cpu)?;
    let committed = &draw.committed[lo * kspo..hi * kspo];
    let embs = model.embed_prefix_with(&inp, true)?;
    let (flow, hidden) = model.loss_multi(
        &inp,
        &embs,
        &actions,
        &noise,
        &time,
        Some(committed),
        kspo,
        true,
        heads.tap(),
    )?;
    let mut loss = flow.mean;
    let l = loss.to_scalar::<f32>()? as f64;
    let mut extra = [f64::NAN; 2];
    let pad = model.prefix_layout(&inp).pad;
    let parts = [
        (heads.loc_loss(&embs, &aux)?, args.aux_weight),
        (
            heads.goal_loss(hidden.as_ref(), &pad, &goal)?,
            args.goal_weight,
        ),
    ];
    for (k, (part, w)) in parts.into_iter().enumerate() {
        if let Some(part) = part {
            extra[k] = part.to_scalar::<f32>()? as f64;
            loss = (loss + (part * w)?)?;
        }
    }
    Ok((loss.backward()?, l, extra, n))
}

/// The batch-mean gradient of `vars` (each worker's weighted by its share of the batch), then
/// global-norm clipping at 1.
fn clipped_mean_gradient(
    vars: &[Var],
    mut parts: Vec<WorkerResult>,
    batch: usize,
) -> anyhow::Result<GradStore> {
    let mut rest = parts.split_off(1);
    let Some((mut grads, _, _, n0)) = parts.pop() else {
        anyhow::bail!("no training worker ran");
    };
    let mut sq = 0f64;
    for v in vars {
        let Some(g0) = grads.remove(v.as_tensor()) else {
            continue;
        };
        let mut g = (g0 * (n0 as f64 / batch as f64))?;
        for (gs, _, _, n) in rest.iter_mut() {
            if let Some(gi) = gs.remove(v.as_tensor()) {
                g = (g + (gi * (*n as f64 / batch as f64))?)?;
            }
        }
        sq += g.sqr()?.sum_all()?.to_scalar::<f32>()? as f64;
        grads.insert(v.as_tensor(), g);
    }
    let norm_g = sq.sqrt();
    if norm_g > 1.0 {
        for v in vars {
            if let Some(g) = grads.remove(v.as_tensor()) {
                grads.insert(v.as_tensor(), (g / norm_g)?);
            }
        }
    }
    Ok(grads)
}

/// The training's state between steps: what the progress line, the log and the choice of the
/// checkpoint to keep read.
struct Progress {
    t0: Instant,
    tty: bool,
    step: usize,
    /// Smoothed losses: flow matching, localisation, goal (NaN before the first step).
    ema: f64,
    ema_aux: f64,
    ema_goal: f64,
    /// The most validation successes so far.
    best: Option<usize>,
    last_val: String,
    /// When to validate next (s since `t0`).
    next_val: f64,
    last_print: f64,
}

impl Progress {
    fn start(val_every_min: f64) -> Progress {
        Progress {
            t0: Instant::now(),
            tty: std::io::stderr().is_terminal(),
            step: 0,
            ema: f64::NAN,
            ema_aux: f64::NAN,
            ema_goal: f64::NAN,
            best: None,
            last_val: String::from("-"),
            next_val: val_every_min * 60.0,
            last_print: 0.0,
        }
    }

    /// Counts a step with `losses` at learning rate `lr`: the smoothed losses, a log row every
    /// 50 steps, and the progress line (every second on a terminal, else every 30 s).
    fn advance(
        &mut self,
        losses: [f64; 3],
        lr: f64,
        log: &mut TrainLog,
        plan: &Plan,
    ) -> anyhow::Result<()> {
        let smooth = |e: f64, v: f64| if e.is_nan() { v } else { 0.98 * e + 0.02 * v };
        self.ema = smooth(self.ema, losses[0]);
        self.ema_aux = smooth(self.ema_aux, losses[1]);
        self.ema_goal = smooth(self.ema_goal, losses[2]);
        self.step += 1;
        let (step, ema, ema_aux, ema_goal) = (self.step, self.ema, self.ema_aux, self.ema_goal);
        if step.is_multiple_of(50) {
            writeln!(
                log.file,
                "{step},{:.1},{ema:.5},{lr:.6},,,{ema_aux:.5},{ema_goal:.5},,,,",
                self.t0.elapsed().as_secs_f64()
            )?;
        }
        let now = self.t0.elapsed().as_secs_f64();
        if now - self.last_print >= if self.tty { 1.0 } else { 30.0 } {
            self.last_print = now;
            let sps = step as f64 * plan.batch as f64 / now.max(1e-9);
            let last_val = &self.last_val;
            let line = format!(
                "[train] step {step}  loss {ema:.4}  loc {ema_aux:.4}  goal {ema_goal:.4}  lr {lr:.2e}  {sps:.0} samples/s  {} / {}  last validation {last_val}",
                fmt_min(now),
                fmt_min(plan.budget_s)
            );
            if self.tty {
                eprint!("\r{line}\x1b[K");
            } else {
                eprintln!("{line}");
            }
        }
        Ok(())
    }
}

/// `train_log.csv`, beside the dataset.
struct TrainLog {
    path: PathBuf,
    file: std::fs::File,
}

impl TrainLog {
    fn create(dataset_path: &Path) -> anyhow::Result<TrainLog> {
        let log_dir = dataset_path
            .parent()
            .map(Path::to_path_buf)
            .unwrap_or_else(|| PathBuf::from("."));
        std::fs::create_dir_all(&log_dir)?;
        let path = log_dir.join("train_log.csv");
        let mut file = std::fs::File::create(&path)?;
        writeln!(file, "step,elapsed_s,loss,lr,val_success,val_episodes,loc_loss,goal_loss,held_loss_t0.1,held_loss_t0.4,held_loss_t0.7,held_loss_t0.95")?;
        Ok(TrainLog { path, file })
    }
}

/// What each validation checks a checkpoint on: closed-loop episodes (the reach task's
/// held-out scenes or the SO-101's validation seeds) and the held-out loss.
struct Validation<'a> {
    plan: &'a Plan,
    norm: &'a NormStats,
    /// The reach task's episodes (none for the SO-101).
    episodes: Vec<EpisodeSpec>,
    so101_seeds: std::ops::Range<u64>,
    /// Episodes per validation.
    count: usize,
    /// Episode limit (s).
    seconds: f64,
    /// The held-out loss data.
    held: Batcher<'a>,
}

impl<'a> Validation<'a> {
    fn new(
        plan: &'a Plan,
        held: &'a Dataset,
        norm: &'a NormStats,
        tok: &'a PromptTokenizer,
    ) -> anyhow::Result<Validation<'a>> {
        let (so101, val_n) = (plan.so101, plan.val_n);
        let episodes = if so101 {
            Vec::new()
        } else {
            held_out_episodes(&plan.cfg, 1_000, val_n, plan.args.seed ^ 0xbeef)
        };
        let so101_seeds =
            crate::task::so101::VAL_SEED_BASE..crate::task::so101::VAL_SEED_BASE + val_n as u64;
        let count = if so101 { val_n } else { episodes.len() };
        // normalised like the training data
        let held_actions = model_space_actions(held, &plan.mcfg.delta_action_mask);
        let held = Batcher::new(held, &held_actions, &plan.mcfg, norm, tok)?;
        let seconds = match (plan.args.quick, so101) {
            (true, _) => 0.5,
            (false, false) => 6.0,
            (false, true) => crate::task::so101::MAX_SECONDS,
        };
        Ok(Validation {
            plan,
            norm,
            episodes,
            so101_seeds,
            count,
            seconds,
            held,
        })
    }

    /// Writes the candidate checkpoint, validates it, logs the result with the held-out loss,
    /// and writes it to `--out` when it is the best so far or `--keep last`.
    fn validate_and_checkpoint(
        &self,
        trainer: &Trainer,
        log: &mut TrainLog,
        p: &mut Progress,
        elapsed: f64,
    ) -> anyhow::Result<()> {
        let (plan, step, ema) = (self.plan, p.step, p.ema);
        let (candidate, model_json) = (&plan.candidate, &plan.model_json);
        write_checkpoint(candidate, &trainer.vm, model_json, self.norm)?;
        let (ok, ttt) = if plan.so101 {
            validate_so101(&plan.cfg, candidate, self.so101_seeds.clone(), self.seconds)?
        } else {
            validate(&plan.cfg, candidate, &self.episodes, self.seconds)?
        };
        let held_loss = loss_by_time(&trainer.model, &self.held, &LOSS_TIMES, 7)?;
        let hl: Vec<String> = held_loss.iter().map(|v| format!("{v:.4}")).collect();
        p.last_val = format!("{ok}/{} (t {:.2} s)", self.count, ttt);
        eprintln!(
            "{}[train] held-out loss at t = {:?}: {} ({} samples)",
            if p.tty { "\n" } else { "" },
            LOSS_TIMES,
            hl.join(" / "),
            self.held.ds.len()
        );
        writeln!(
            log.file,
            "{step},{elapsed:.1},{ema:.5},,{ok},{},,,{}",
            self.count,
            hl.join(",")
        )?;
        let better = p.best.is_none_or(|b| ok >= b);
        if better {
            p.best = Some(ok);
        }
        let written = better || plan.args.keep == Keep::Last;
        if written {
            write_checkpoint(&plan.out_dir, &trainer.vm, model_json, self.norm)?;
        }
        eprintln!(
            "{}[train] step {step}  {}  loss {ema:.4}  validation: {} success{}",
            if p.tty { "\n" } else { "" },
            fmt_min(elapsed),
            p.last_val,
            if written { "  -> written" } else { "" }
        );
        p.next_val = p.t0.elapsed().as_secs_f64() + plan.args.val_every_min * 60.0;
        Ok(())
    }
}
