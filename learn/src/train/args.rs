//! `chunkrt train`'s command line: what to record, how long and how to train, what to keep.

use std::path::PathBuf;

pub use crate::task::TaskKind;

/// `chunkrt train`.
#[derive(Debug, Clone, clap::Args)]
pub struct TrainArgs {
    /// The task: `reach` (the embedded demo's planar arm, recorded in process) or `so101` (the
    /// SO-101 pick-and-place in MuJoCo: demonstrations of the package's expert recorded by
    /// `tools/python/so101_sim.py`, validation closed-loop in its physics; defaults to
    /// `--config config/so101.toml`, `--model-config config/so101_model.json`, `--out
    /// models/so101_pi05`).
    #[arg(long, value_enum, default_value_t = TaskKind::Reach)]
    pub task: TaskKind,
    /// Robot / control configuration (default: the embedded demo robot).
    #[arg(long)]
    pub config: Option<PathBuf>,
    /// Model dimensions, a `config.json` in the fixtures' schema (default:
    /// `config/reach_model.json`, embedded).
    #[arg(long, value_name = "FILE")]
    pub model_config: Option<PathBuf>,
    /// Where the checkpoint goes (default: `models/reach_pi05`, `models/so101_pi05` for the SO-101).
    #[arg(long)]
    pub out: Option<PathBuf>,
    /// Dataset file; recorded with `--scenes` scenes when missing (default:
    /// `target/chunkrt-train/dataset.safetensors`, `so101_dataset.safetensors` for the SO-101).
    #[arg(long)]
    pub dataset: Option<PathBuf>,
    /// Scenes to record when the dataset is missing (reach: two episodes each, default 20 000;
    /// SO-101: episodes, default 300).
    #[arg(long)]
    pub scenes: Option<usize>,
    /// Share of each episode's policy steps recorded (first and last always): 20 000 scenes at
    /// 0.05 give 150 k samples from 40 000 start poses and 20 000 target layouts (recorded in
    /// about 80 s; 1.8 GB in memory).
    #[arg(long, default_value_t = 0.05)]
    pub keep_share: f64,
    /// Which checkpoint ends up in `--out`: `last` (the end of the schedule) or `best` (highest
    /// validation success so far; with tens of episodes the noise is ±15 points).
    #[arg(long, value_enum, default_value_t = Keep::Last)]
    pub keep: Keep,
    /// The expert's speed profile when recording. `distance-paced` (the default): the chunk is a
    /// function of the pose and the target alone. `min-jerk` starts every motion from rest, so
    /// the same pose has different chunks depending on when the motion started, and the policy
    /// learns a wide distribution that it samples afresh at every chunk.
    #[arg(long, value_enum, default_value_t = crate::task::expert::Profile::DistancePaced)]
    pub expert: crate::task::expert::Profile,
    /// Training time budget (minutes).
    #[arg(long, default_value_t = 25.0)]
    pub minutes: f64,
    /// Stop after this many optimiser steps.
    #[arg(long, default_value_t = 1_000_000)]
    pub max_steps: usize,
    /// Batch size.
    #[arg(long, default_value_t = 32)]
    pub batch: usize,
    /// Peak learning rate.
    #[arg(long, default_value_t = 1e-3)]
    pub lr: f64,
    /// Validate (and checkpoint) every this many minutes.
    #[arg(long, default_value_t = 4.0)]
    pub val_every_min: f64,
    /// Held-out closed-loop episodes per validation.
    #[arg(long, default_value_t = 24)]
    pub val_episodes: usize,
    /// Seed of the initialisation, batches and noise.
    #[arg(long, default_value_t = 0)]
    pub seed: u64,
    /// Data-parallel training workers (threads), each running candle on one core.
    #[arg(long, default_value_t = 2)]
    pub threads: usize,
    /// Initial embeddings of the 256 state-bin tokens: `fourier` gives bin k the sines and
    /// cosines of k/255 at geometric frequencies, so neighbouring bins start close and the
    /// state's value is readable from the first step; `random` is the usual N(0, 1/W).
    #[arg(long, value_enum, default_value_t = BinInit::Fourier)]
    pub state_embedding: BinInit,
    /// Weight of the auxiliary localisation loss: a linear head on the image tokens regresses
    /// the two targets' and the gripper's positions in the image plane, so the vision tower
    /// gets a direct signal instead of only the flow-matching gradient. The head is not part
    /// of the checkpoint. 0 turns it off.
    #[arg(long, default_value_t = 1.0)]
    pub aux_weight: f64,
    /// Weight of the auxiliary goal loss: a linear head on the language model's hidden states at
    /// the input of its last layer (whose keys and values the action expert reads), averaged over
    /// the valid prefix tokens, regresses the prompted target's inverse-kinematics joint angles,
    /// position and velocity (where it is and where it is going at the sample's time; the
    /// velocity is 0 unless it drifts). It asks the prefix to do what the prompt says (pick the named target) in a
    /// form the action expert can read. Not part of the checkpoint; 0 turns it off.
    #[arg(long, default_value_t = 1.0)]
    pub goal_weight: f64,
    /// Noise / time samples of the flow-matching loss per observation. They share one pass of
    /// the prefix (SigLIP and the language model, most of a step's cost) and each runs the
    /// action expert, so k samples cost far less than k observations and average out the
    /// loss's sampling noise.
    /// At 1 (the default) every observation gets one sample, as in openpi: in an 8-minute A/B
    /// on the reach task, 4 samples per observation reached 14/24 validation episodes against
    /// 22/24 for 1 (more optimiser steps in the same time won).
    #[arg(long, default_value_t = 1)]
    pub samples_per_obs: usize,
    /// Training-time real-time chunking (Black et al. 2025, arXiv 2512.05964): each sample's
    /// first d actions, d uniform in 0..=N, are given to the model clean (flow time 0) and left
    /// out of the loss, so at run time the actions the robot executes while the model computes
    /// can be given and the chunk continues them (`strategy = "rtc_trained"`). The checkpoint's
    /// `config.json` records N as `rtc_prefix_max`. 0 (the default) trains without.
    #[arg(long, default_value_t = 0, value_name = "N")]
    pub rtc_prefix: usize,
    /// Share of the recorded episodes whose targets swing about the base (the drifting variant
    /// of `chunkrt eval --drift-hz`; `task::dataset::DriftMix`): the tracking expert labels them
    /// with chunks that catch up with the target and move with it. 0 (the default) records the
    /// static task only. A dataset file recorded with another share is refused.
    #[arg(long, default_value_t = 0.0, value_name = "F")]
    pub drift_share: f64,
    /// A frame history: the model gets, beside the task camera's frame, the frame the camera
    /// took this long before it (an image input `<camera>_prev`, `config.json`
    /// `delayed_views`), so it can see which way the targets move. A multiple of the policy
    /// period (100 ms at 10 Hz); 0 (the default) trains without. The dataset records the
    /// earlier frames too; a dataset file recorded with another history is refused.
    #[arg(long, default_value_t = 0.0, value_name = "MS")]
    pub history_ms: f64,
    /// Start from this checkpoint's weights instead of a fresh initialisation (fine-tuning;
    /// its dimensions must be the model configuration's), keeping its `norm_stats.json`.
    #[arg(long, value_name = "DIR")]
    pub init: Option<PathBuf>,
    /// A smoke run: 3 scenes, 6 steps, 1 validation episode (for the tests).
    #[arg(long)]
    pub quick: bool,
}

/// Which checkpoint `chunkrt train` leaves in `--out`.
#[derive(Debug, Clone, Copy, PartialEq, Eq, clap::ValueEnum)]
pub enum Keep {
    Last,
    Best,
}

/// How the state-bin token embeddings start.
#[derive(Debug, Clone, Copy, PartialEq, Eq, clap::ValueEnum)]
pub enum BinInit {
    Fourier,
    Random,
}
