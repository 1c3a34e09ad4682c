//! openpi's training configs that ship checkpoints, served as openpi serves them.
//!
//! openpi's `Policy` wraps the model in transforms that belong to the training config, not to
//! the checkpoint (`src/openpi/training/config.py`, `src/openpi/policies/*_policy.py` at
//! 15a9616): the robot's state goes through the robot's input transform (ALOHA's joint sign
//! flips and its gripper converted to pi0's angular space), is normalised (z-score for π0,
//! quantiles for π0.5), padded and, for π0.5 with `discrete_state_input`, written into the
//! prompt; the model's actions are unnormalised, made absolute on the config's delta dims
//! (`AbsoluteActions`: the model-space state added), and go through the robot's output
//! transform (the flips again, the grippers from angular, and the columns the robot takes: 14
//! for ALOHA, 7 for LIBERO, 8 for DROID). The converted checkpoint's `config.json` carries
//! none of this, so each config is a row of [`CONFIGS`], selected by name
//! (`--openpi-config`, `[policy] openpi_config`) or recognised from the checkpoint's folder
//! name or its assets.
//!
//! [`model_state`] and [`robot_actions`] are the whole pipeline around the model; the policy
//! runtime calls them, and `tests/openpi_transforms.rs` checks them against what openpi's own
//! transform code makes of the same inputs (`tests/data/openpi_transforms/`).

use std::path::Path;

use crate::config::ModelKind;
use crate::error::PolicyError;
use crate::preprocess::{normalize, normalize_f64, unnormalize, NormMode, NormStats, Stats};

/// The robot a config's transforms are for.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Robot {
    /// `AlohaInputs` / `AlohaOutputs` (`adapt_to_pi`: the joint flips and the gripper
    /// conversions; every shipped ALOHA config sets it). State `[left 6 joints, left gripper,
    /// right 6 joints, right gripper]`, 14 columns out.
    Aloha {
        /// openpi's `adapt_to_pi`.
        adapt_to_pi: bool,
    },
    /// `LiberoInputs` / `LiberoOutputs`: state (end effector position 3, axis-angle 3,
    /// gripper 2) as is, the first 7 columns out.
    Libero,
    /// `DroidInputs` / `DroidOutputs`: joint positions 7 and the gripper position, 8 columns out.
    Droid,
}

impl Robot {
    /// The request layout of openpi's example client for this robot (`chunkrt-openpi`'s preset).
    pub fn layout(self) -> &'static str {
        match self {
            Robot::Aloha { .. } => "aloha",
            Robot::Libero => "libero",
            Robot::Droid => "droid",
        }
    }

    /// State values the robot sends.
    pub fn state_dim(self) -> usize {
        match self {
            Robot::Aloha { .. } => 14,
            Robot::Libero | Robot::Droid => 8,
        }
    }

    /// Action columns the robot gets back.
    pub fn action_dim(self) -> usize {
        match self {
            Robot::Aloha { .. } => 14,
            Robot::Libero => 7,
            Robot::Droid => 8,
        }
    }

    /// What the state holds, for errors.
    fn state_text(self) -> &'static str {
        match self {
            Robot::Aloha { .. } => {
                "left arm 6 joints, left gripper, right arm 6 joints, right gripper"
            }
            Robot::Libero => "end effector position 3, axis-angle 3, gripper 2",
            Robot::Droid => "joint positions 7, gripper position 1",
        }
    }
}

/// One openpi training config, as far as inference goes.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct OpenpiConfig {
    /// openpi's name (`pi05_libero`, ...).
    pub name: &'static str,
    /// π0 or π0.5 (the checkpoint's weights must be this kind).
    pub kind: ModelKind,
    /// Actions a chunk has (`Pi0Config.action_horizon`).
    pub action_horizon: usize,
    /// Prompt tokens (`Pi0Config.max_token_len`: 48 for π0, 200 for π0.5).
    pub max_token_len: usize,
    /// π0.5: the normalised state is written into the prompt (`discrete_state_input`; false
    /// for `pi05_libero`, whose model sees no state at all).
    pub discrete_state_input: bool,
    /// `assets/<asset_id>/norm_stats.json` in the checkpoint (nested where the id has a `/`).
    pub asset_id: &'static str,
    /// The robot transforms.
    pub robot: Robot,
    /// `make_bool_mask(...)` of the config's `DeltaActions` / `AbsoluteActions` (empty: none).
    pub delta_mask: &'static [bool],
    /// The config's `default_prompt` (a request's prompt, then the server's, come first).
    pub default_prompt: Option<&'static str>,
    /// The config's `policy_metadata` `reset_pose` (the ALOHA towel and tupperware configs):
    /// the server's metadata carries it, and openpi's ALOHA client resets the arms to it.
    pub reset_pose: Option<&'static [f64]>,
}

const T: bool = true;
const F: bool = false;
/// `make_bool_mask(6, -1, 6, -1)`: both arms' joints relative, the grippers absolute.
const ALOHA_DELTA: &[bool] = &[T, T, T, T, T, T, F, T, T, T, T, T, T, F];
/// `make_bool_mask(6, -1)`: the end effector pose relative, the gripper absolute.
const LIBERO_DELTA: &[bool] = &[T, T, T, T, T, T, F];
const ALOHA: Robot = Robot::Aloha { adapt_to_pi: true };
/// `policy_metadata={"reset_pose": [0, -1.5, 1.5, 0, 0, 0]}` of the ALOHA towel and
/// tupperware configs.
const ALOHA_RESET_POSE: &[f64] = &[0.0, -1.5, 1.5, 0.0, 0.0, 0.0];

/// The configs of openpi (15a9616) that ship a checkpoint or that its examples serve.
pub const CONFIGS: [OpenpiConfig; 9] = [
    OpenpiConfig {
        name: "pi0_aloha_towel",
        kind: ModelKind::Pi0,
        action_horizon: 50,
        max_token_len: 48,
        discrete_state_input: false,
        asset_id: "trossen",
        robot: ALOHA,
        delta_mask: ALOHA_DELTA,
        default_prompt: Some("fold the towel"),
        reset_pose: Some(ALOHA_RESET_POSE),
    },
    OpenpiConfig {
        name: "pi0_aloha_tupperware",
        kind: ModelKind::Pi0,
        action_horizon: 50,
        max_token_len: 48,
        discrete_state_input: false,
        asset_id: "trossen",
        robot: ALOHA,
        delta_mask: ALOHA_DELTA,
        default_prompt: Some("open the tupperware and put the food on the plate"),
        reset_pose: Some(ALOHA_RESET_POSE),
    },
    OpenpiConfig {
        name: "pi0_aloha_pen_uncap",
        kind: ModelKind::Pi0,
        action_horizon: 50,
        max_token_len: 48,
        discrete_state_input: false,
        asset_id: "trossen",
        robot: ALOHA,
        delta_mask: ALOHA_DELTA,
        default_prompt: Some("uncap the pen"),
        reset_pose: None,
    },
    OpenpiConfig {
        name: "pi05_aloha_pen_uncap",
        kind: ModelKind::Pi05,
        action_horizon: 50,
        max_token_len: 200,
        discrete_state_input: true,
        asset_id: "trossen",
        robot: ALOHA,
        delta_mask: ALOHA_DELTA,
        default_prompt: Some("uncap the pen"),
        reset_pose: None,
    },
    OpenpiConfig {
        name: "pi0_aloha_sim",
        kind: ModelKind::Pi0,
        action_horizon: 50,
        max_token_len: 48,
        discrete_state_input: false,
        asset_id: "lerobot/aloha_sim_transfer_cube_human",
        robot: ALOHA,
        delta_mask: &[],
        default_prompt: Some("Transfer cube"),
        reset_pose: None,
    },
    OpenpiConfig {
        name: "pi0_libero",
        kind: ModelKind::Pi0,
        action_horizon: 50,
        max_token_len: 48,
        discrete_state_input: false,
        asset_id: "physical-intelligence/libero",
        robot: Robot::Libero,
        delta_mask: LIBERO_DELTA,
        default_prompt: None,
        reset_pose: None,
    },
    OpenpiConfig {
        name: "pi05_libero",
        kind: ModelKind::Pi05,
        action_horizon: 10,
        max_token_len: 200,
        discrete_state_input: false,
        asset_id: "physical-intelligence/libero",
        robot: Robot::Libero,
        delta_mask: &[],
        default_prompt: None,
        reset_pose: None,
    },
    OpenpiConfig {
        name: "pi0_droid",
        kind: ModelKind::Pi0,
        action_horizon: 10,
        max_token_len: 48,
        discrete_state_input: false,
        asset_id: "droid",
        robot: Robot::Droid,
        delta_mask: &[],
        default_prompt: None,
        reset_pose: None,
    },
    OpenpiConfig {
        name: "pi05_droid",
        kind: ModelKind::Pi05,
        action_horizon: 15,
        max_token_len: 200,
        discrete_state_input: true,
        asset_id: "droid",
        robot: Robot::Droid,
        delta_mask: &[],
        default_prompt: None,
        reset_pose: None,
    },
];

/// The config called `name`.
pub fn by_name(name: &str) -> Result<&'static OpenpiConfig, PolicyError> {
    CONFIGS.iter().find(|c| c.name == name).ok_or_else(|| {
        PolicyError::Config(format!(
            "openpi config {name:?}: not one chunkrt knows ({}; pi0_fast_droid needs the FAST \
             model, which chunkrt does not run)",
            CONFIGS.map(|c| c.name).join(", ")
        ))
    })
}

/// The config a checkpoint directory gives away without being told: its own folder name or a
/// parent's (openpi's checkpoints download to `.../checkpoints/<config>/...`), else, when its
/// assets hold statistics for one robot only (`assets/<asset_id>/norm_stats.json`), the config
/// of this model kind they belong to (the ALOHA configs on `trossen` differ only in their
/// default prompt: the first is taken, with a note). `None`: nothing recognised (the
/// checkpoint is served without robot transforms, as before).
pub fn recognise(dir: &Path, kind: ModelKind) -> Option<(&'static OpenpiConfig, String)> {
    for d in dir.ancestors().take(4) {
        let name = d.file_name().and_then(|n| n.to_str()).unwrap_or("");
        if let Some(c) = CONFIGS.iter().find(|c| c.name == name && c.kind == kind) {
            return Some((c, format!("from the folder name {name:?}")));
        }
    }
    // only a checkpoint with statistics for one robot gives its config away (a base model's
    // assets hold several: the user chooses)
    if stats_files(&dir.join("assets")) != 1 {
        return None;
    }
    let held: Vec<&'static OpenpiConfig> = CONFIGS
        .iter()
        .filter(|c| c.kind == kind)
        .filter(|c| {
            dir.join("assets")
                .join(c.asset_id)
                .join("norm_stats.json")
                .is_file()
        })
        .collect();
    let first = *held.first()?;
    let how =
        if held.len() == 1 {
            format!("from assets/{}", first.asset_id)
        } else {
            format!(
            "from assets/{} (also {}: the same transforms, another default prompt; choose with \
             --openpi-config)",
            first.asset_id,
            held[1..].iter().map(|c| c.name).collect::<Vec<_>>().join(", ")
        )
        };
    Some((first, how))
}

/// `norm_stats.json` files one or two folders under `assets`.
fn stats_files(assets: &Path) -> usize {
    let dirs = |p: &Path| -> Vec<std::path::PathBuf> {
        std::fs::read_dir(p)
            .map(|rd| {
                rd.filter_map(|e| e.ok())
                    .map(|e| e.path())
                    .filter(|p| p.is_dir())
                    .collect()
            })
            .unwrap_or_default()
    };
    let mut n = 0;
    for a in dirs(assets) {
        n += a.join("norm_stats.json").is_file() as usize;
        for b in dirs(&a) {
            n += b.join("norm_stats.json").is_file() as usize;
        }
    }
    n
}

impl OpenpiConfig {
    /// Checks the statistics against the robot: a state or action width that does not belong
    /// to it (14 ALOHA columns under a LIBERO config) is a wrong config, said at load.
    /// Statistics padded to the model's action dim are accepted.
    pub fn check_stats(&self, ns: &NormStats, action_dim: usize) -> Result<(), PolicyError> {
        let (s, a) = (ns.state.mean.len(), ns.actions.mean.len());
        let (want_s, want_a) = (self.robot.state_dim(), self.model_action_width());
        let fits = |have: usize, want: usize| have == want || have >= action_dim;
        if !fits(s, want_s) || !fits(a, want_a) {
            return Err(PolicyError::Config(format!(
                "openpi config {}: its statistics hold {s} state and {a} action values, but \
                 the config's robot ({}) has {want_s} and {want_a}: these statistics belong \
                 to another config (--openpi-config, --asset-id)",
                self.name,
                self.robot.layout(),
            )));
        }
        Ok(())
    }

    /// Action columns in the model's space that the robot's output transform reads (ALOHA 14,
    /// LIBERO 7, DROID 8).
    pub fn model_action_width(&self) -> usize {
        self.robot.action_dim()
    }

    /// Checks a request's state width.
    pub fn check_state(&self, n: usize) -> Result<(), PolicyError> {
        let want = self.robot.state_dim();
        if n != want {
            return Err(PolicyError::Input(format!(
                "openpi config {} takes {want} state values ({}); the request has {n}",
                self.name,
                self.robot.state_text()
            )));
        }
        Ok(())
    }

    /// The robot's state in the model's space (the robot input transform, before Normalize):
    /// ALOHA's joints flipped and its grippers converted to pi0's angular space.
    pub fn state_in(&self, raw: &[f64]) -> Vec<f64> {
        let mut s = raw.to_vec();
        if let Robot::Aloha { adapt_to_pi: true } = self.robot {
            for (x, f) in s.iter_mut().zip(ALOHA_FLIP) {
                *x *= f;
            }
            for g in [6, 13] {
                if let Some(x) = s.get_mut(g) {
                    *x = gripper_to_angular(*x);
                }
            }
        }
        s
    }

    /// One action row in the model's space (unnormalised, absolute) to the robot's columns
    /// (the robot output transform): `out` gets [`Robot::action_dim`] values.
    pub fn action_out(&self, row: &[f64], out: &mut Vec<f64>) {
        let n = self.robot.action_dim().min(row.len());
        let start = out.len();
        out.extend_from_slice(&row[..n]);
        if let Robot::Aloha { adapt_to_pi: true } = self.robot {
            let r = &mut out[start..];
            for (x, f) in r.iter_mut().zip(ALOHA_FLIP) {
                *x *= f;
            }
            for g in [6, 13] {
                if let Some(x) = r.get_mut(g) {
                    *x = gripper_from_angular(*x);
                }
            }
        }
    }
}

/// openpi's `_joint_flip_mask`: ALOHA's joints 2 and 3 of each arm turn the other way in pi0's
/// convention.
const ALOHA_FLIP: [f64; 14] = [
    1.0, -1.0, -1.0, 1.0, 1.0, 1.0, 1.0, 1.0, -1.0, -1.0, 1.0, 1.0, 1.0, 1.0,
];

fn to_unit(x: f64, lo: f64, hi: f64) -> f64 {
    (x - lo) / (hi - lo)
}

fn from_unit(x: f64, lo: f64, hi: f64) -> f64 {
    x * (hi - lo) + lo
}

/// openpi's `_gripper_to_angular` (the state): ALOHA's normalised linear gripper position to
/// metres (0.01844..0.05800), through the Interbotix horn's geometry (arm 0.036 m, horn
/// 0.022 m) to radians, normalised over pi0's range 0.5476..1.6296.
pub fn gripper_to_angular(v: f64) -> f64 {
    let p = from_unit(v, 0.01844, 0.05800);
    let (arm, horn) = (0.036f64, 0.022f64);
    let s = (horn * horn + p * p - arm * arm) / (2.0 * horn * p);
    to_unit(s.clamp(-1.0, 1.0).asin(), 0.5476, 1.6296)
}

/// openpi's `_gripper_from_angular` (the actions): pi0's gripper angle shifted by 0.5476 and
/// normalised over ALOHA's joint range -0.6213..1.4910 (deliberately not the inverse of
/// [`gripper_to_angular`]).
pub fn gripper_from_angular(v: f64) -> f64 {
    to_unit(v + 0.5476, -0.6213, 1.4910)
}

/// What the model gets of a robot's state ([`model_state`]).
#[derive(Debug, Clone, PartialEq)]
pub struct ModelState {
    /// The model's state input: normalised, padded to the action dim (f32).
    pub state: Vec<f32>,
    /// The state as it goes into a π0.5 prompt: normalised in f64 as openpi does (numpy on the
    /// client's f64 state), unpadded. (LeRobot's pi05 normalises in f32: `state`'s values.)
    pub prompt_state: Vec<f64>,
    /// What `AbsoluteActions` adds to each action row: the model-space state on the delta
    /// dims, 0 elsewhere (one per state value).
    pub offsets: Vec<f64>,
}

/// What the model gets of the robot's state: the robot's input transform (`cfg`), the
/// normalisation of the unpadded state, padding to `action_dim` ([`ModelState`];
/// `delta_mask` applies where there is no config).
pub fn model_state(
    cfg: Option<&OpenpiConfig>,
    delta_mask: &[bool],
    norm: Option<&NormStats>,
    mode: NormMode,
    raw: &[f64],
    action_dim: usize,
) -> Result<ModelState, PolicyError> {
    let s = match cfg {
        Some(c) => c.state_in(raw),
        None => raw.to_vec(),
    };
    if s.iter().any(|x| !x.is_finite()) {
        return Err(PolicyError::Input(
            "non-finite state (after the robot's input transform)".into(),
        ));
    }
    let mask = cfg.map_or(delta_mask, |c| c.delta_mask);
    let offsets = s
        .iter()
        .enumerate()
        .map(|(d, &x)| {
            if mask.get(d).copied().unwrap_or(false) {
                x
            } else {
                0.0
            }
        })
        .collect();
    let mut state: Vec<f32> = s.iter().map(|&x| x as f32).collect();
    let mut prompt_state = s;
    if let Some(ns) = norm {
        normalize(&mut state, &ns.state, mode)?;
        normalize_f64(&mut prompt_state, &ns.state, mode)?;
    }
    state.resize(action_dim, 0.0);
    Ok(ModelState {
        state,
        prompt_state,
        offsets,
    })
}

/// What the robot gets of the model's actions (`rows`: `[H][action_dim]`, model space): each
/// row unnormalised, the offsets added on the first `n_state` columns, then the robot's output
/// transform (`cfg`; without one, the first `n_state` columns). Appends to `out`.
pub fn robot_actions(
    cfg: Option<&OpenpiConfig>,
    norm: Option<&NormStats>,
    mode: NormMode,
    rows: Vec<Vec<f32>>,
    offsets: &[f64],
    out: &mut Vec<f64>,
) -> Result<(), PolicyError> {
    let n_state = offsets.len();
    let mut row64 = Vec::with_capacity(n_state);
    for mut r in rows {
        if let Some(ns) = norm {
            unnormalize(&mut r, &ns.actions, mode)?;
        }
        row64.clear();
        row64.extend(
            r.iter()
                .zip(offsets)
                .take(n_state)
                .map(|(&x, &o)| x as f64 + o),
        );
        match cfg {
            Some(c) => c.action_out(&row64, out),
            None => out.extend_from_slice(&row64),
        }
    }
    if out.iter().any(|x| !x.is_finite()) {
        return Err(PolicyError::Input(
            "model produced non-finite actions".into(),
        ));
    }
    Ok(())
}

/// A robot joint's position range as the robot's configuration gives it (rad, or m).
#[derive(Debug, Clone, PartialEq)]
pub struct JointRange {
    /// The joint's name (for the refusal).
    pub name: String,
    /// Lower limit.
    pub min: f64,
    /// Upper limit.
    pub max: f64,
}

/// How far beyond a joint's range the action statistics' extremes may reach, as a fraction of
/// the range's width: a full width either side (q01 / q99 of π0.5, and mean ± 3 std of π0, as a
/// gripper's two modes give a std of half its range). Statistics of ±999 or in degrees lie
/// tens of widths out; a gripper's extremes a little past its range are not refused.
pub const RANGE_MARGIN_QUANTILE: f64 = 1.0;
/// See [`RANGE_MARGIN_QUANTILE`].
pub const RANGE_MARGIN_ZSCORE: f64 = 1.0;

/// Degrees per radian: statistics in degrees are this much too large.
const DEGREES_PER_RAD: f64 = 180.0 / std::f64::consts::PI;

/// What the robot's joints would get from the action statistics' extremes (q01 and q99, or
/// mean ∓ 3 std): each column's lowest and highest, through the same un-normalisation, delta
/// offsets (the robot at the middle of its ranges) and output transform as a chunk. None where
/// that cannot be computed (another check refuses such statistics).
fn action_extremes(
    cfg: Option<&OpenpiConfig>,
    delta_mask: &[bool],
    ns: &NormStats,
    mode: NormMode,
    action_dim: usize,
    joints: &[JointRange],
) -> Option<Vec<(f64, f64)>> {
    let mid: Vec<f64> = joints.iter().map(|j| 0.5 * (j.min + j.max)).collect();
    let m = model_state(cfg, delta_mask, Some(ns), mode, &mid, action_dim).ok()?;
    let k = match mode {
        NormMode::Quantile => 1.0,
        NormMode::ZScore => 3.0,
    };
    let rows = vec![vec![-k; action_dim], vec![k; action_dim]];
    let mut out = Vec::new();
    robot_actions(cfg, Some(ns), mode, rows, &m.offsets, &mut out).ok()?;
    let width = out.len() / 2;
    (width >= joints.len()).then(|| {
        (0..joints.len())
            .map(|j| {
                let (a, b) = (out[j], out[width + j]);
                (a.min(b), a.max(b))
            })
            .collect()
    })
}

/// The joints whose statistics' extremes lie outside their range by more than the margin:
/// (index, lowest, highest).
fn out_of_range(
    extremes: &[(f64, f64)],
    joints: &[JointRange],
    mode: NormMode,
) -> Vec<(usize, f64, f64)> {
    let frac = match mode {
        NormMode::Quantile => RANGE_MARGIN_QUANTILE,
        NormMode::ZScore => RANGE_MARGIN_ZSCORE,
    };
    extremes
        .iter()
        .zip(joints)
        .enumerate()
        .filter(|(_, (&(lo, hi), j))| {
            let margin = frac * (j.max - j.min).abs();
            !(lo >= j.min - margin && hi <= j.max + margin)
        })
        .map(|(i, (&(lo, hi), _))| (i, lo, hi))
        .collect()
}

/// Holds the action statistics against the robot's joint ranges at load: what a chunk's
/// extremes (q01 / q99 for π0.5, mean ± 3 std for π0) become for each joint, through the same
/// un-normalisation, offsets and output transform as the chunks, must lie within the joint's
/// range widened by [`RANGE_MARGIN_QUANTILE`] / [`RANGE_MARGIN_ZSCORE`] of its width.
/// Statistics of another robot, in other units (degrees: a units hint when ÷57.3 they fit) or
/// with extremes such as ±999 are refused, naming the joints: un-normalised by them, the chunks
/// drive those joints into their limits at full speed.
pub fn check_action_ranges(
    cfg: Option<&OpenpiConfig>,
    delta_mask: &[bool],
    ns: &NormStats,
    mode: NormMode,
    action_dim: usize,
    joints: &[JointRange],
) -> Result<(), PolicyError> {
    if joints.is_empty()
        || joints
            .iter()
            .any(|j| !(j.min.is_finite() && j.max.is_finite()))
    {
        return Ok(());
    }
    let Some(ext) = action_extremes(cfg, delta_mask, ns, mode, action_dim, joints) else {
        return Ok(());
    };
    let bad = out_of_range(&ext, joints, mode);
    if bad.is_empty() {
        return Ok(());
    }
    let what = match mode {
        NormMode::Quantile => "q01 / q99",
        NormMode::ZScore => "mean ± 3 std",
    };
    let list: Vec<String> = bad
        .iter()
        .map(|&(i, lo, hi)| {
            let j = &joints[i];
            format!(
                "{} (column {i}): {lo:.3} .. {hi:.3} against its range {:.3} .. {:.3}",
                j.name, j.min, j.max
            )
        })
        .collect();
    // the same statistics in radians: do they fit?
    let scaled = |st: &Stats| Stats {
        mean: st.mean.iter().map(|x| x / DEGREES_PER_RAD as f32).collect(),
        std: st.std.iter().map(|x| x / DEGREES_PER_RAD as f32).collect(),
        q01: st
            .q01
            .as_ref()
            .map(|v| v.iter().map(|x| x / DEGREES_PER_RAD as f32).collect()),
        q99: st
            .q99
            .as_ref()
            .map(|v| v.iter().map(|x| x / DEGREES_PER_RAD as f32).collect()),
    };
    let radians = NormStats {
        state: scaled(&ns.state),
        actions: scaled(&ns.actions),
    };
    // degrees: every refused joint's extremes some 10 to 300 times its range's reach, and
    // divided by 57.3 they fit
    let scale_like = bad.iter().all(|&(i, lo, hi)| {
        let j = &joints[i];
        let reach = j.min.abs().max(j.max.abs()).max(1e-3);
        (10.0..=300.0).contains(&(lo.abs().max(hi.abs()) / reach))
    });
    let degrees = scale_like
        && action_extremes(cfg, delta_mask, &radians, mode, action_dim, joints).is_some_and(|e| {
            let still = out_of_range(&e, joints, mode);
            bad.iter().all(|b| !still.iter().any(|s| s.0 == b.0))
        });
    let margin = match mode {
        NormMode::Quantile => RANGE_MARGIN_QUANTILE,
        NormMode::ZScore => RANGE_MARGIN_ZSCORE,
    };
    Err(PolicyError::Config(format!(
        "norm_stats actions: the statistics' extremes ({what}) reach beyond the robot's joint \
         ranges (by more than {:.0} % of a range's width): {}; un-normalised by them, the \
         chunks would drive these joints into their limits at full speed. {}",
        margin * 100.0,
        list.join("; "),
        if degrees {
            "They look like degrees (divided by 57.3 they fit): convert the statistics to \
             radians"
        } else {
            "Fix the statistics (recompute them on this robot's data), or the robot's \
             configuration if its ranges are wrong"
        }
    )))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn every_config_is_found_by_name_and_masks_fit_the_robot() {
        for c in &CONFIGS {
            assert_eq!(by_name(c.name).unwrap().name, c.name);
            assert!(c.delta_mask.len() <= c.robot.state_dim());
            assert!(c.robot.action_dim() <= c.robot.state_dim());
        }
        assert!(by_name("pi0_fast_droid").is_err());
    }

    #[test]
    fn aloha_grippers_match_openpi_reference_values() {
        // computed from openpi's formulas (aloha_policy.py at 15a9616) by hand in Python
        for (v, to, from) in [
            (0.0, -1.0798655475, 0.5533778346),
            (0.5, -0.1400559217, 0.7900866354),
            (1.0, 0.9456527974, 1.0267954363),
        ] {
            assert!((gripper_to_angular(v) - to).abs() < 1e-9, "{v}");
            assert!((gripper_from_angular(v) - from).abs() < 1e-9, "{v}");
        }
    }

    #[test]
    fn aloha_flips_joints_two_and_three_of_each_arm() {
        let c = by_name("pi0_aloha_sim").unwrap();
        let s = c.state_in(&[1.0; 14]);
        assert_eq!(s[1], -1.0);
        assert_eq!(s[9], -1.0);
        assert_eq!(s[3], 1.0);
        let mut out = Vec::new();
        c.action_out(&[0.5; 32], &mut out);
        assert_eq!(out.len(), 14);
        assert_eq!(out[2], -0.5);
        assert!((out[6] - gripper_from_angular(0.5)).abs() < 1e-12);
        let mut out = Vec::new();
        by_name("pi05_libero")
            .unwrap()
            .action_out(&[0.5; 32], &mut out);
        assert_eq!(out.len(), 7);
    }
}
