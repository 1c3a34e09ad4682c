//! Open-loop probe of a reach policy: does it act on what it sees and what it is told?
//!
//! On held-out scenes, observations are taken on the expert's path (at 0, 0.5 and 1 s of each
//! reach). For each one the policy computes four chunks:
//! - the chunk itself, compared with the expert's (error of the last action, and whether the
//!   move points at the prompted target or at the other one: the cosine, in joint space, between
//!   the chunk's move and the straight line to each target's inverse-kinematics solution);
//! - the same inputs with fresh noise: the **noise floor**, how much two samples of the same
//!   observation differ;
//! - the image of another scene (same joints, same prompt): the **image effect**;
//! - the other prompt (same image): the **prompt effect**.
//!
//! A policy that ignores its image or prompt has effects at the noise floor, however small its
//! training loss. This is how the session-4 diagnosis found that the earlier 3-layer policy
//! sampled chunks from the state alone. Each effect is shown beside the expert's (fresh plans
//! from the same joints in the other scene / for the other target): what it should be.

use chunkrt_ipc::config::Config;

use super::expert::{Profile, Reach};
use super::sim::EpisodeSpec;
use super::{inverse_kinematics, task_camera, ReachScene, ARM_JOINTS, TASK_DOF};
use crate::policy::runtime::{Policy, RawFrame, RawObservation};

/// Scene seeds of the swapped images are the episode's plus this (still held out).
const SWAP_SCENE_OFFSET: u64 = 100_000;

/// Averages over the probe's observations (distances: mean over the arm joints of the absolute
/// difference of the chunks' last actions, rad).
#[derive(Debug, Clone, Default, PartialEq)]
pub struct ProbeReport {
    /// Observations probed.
    pub observations: usize,
    /// Last action against the expert's, per arm joint (rad).
    pub last_action_error: [f64; ARM_JOINTS],
    /// Cosine between the chunk's move and the line to the prompted target's solution.
    pub cos_prompted: f64,
    /// The same for the other target.
    pub cos_other: f64,
    /// The expert's cosine with the other target (the geometry's share of `cos_other`).
    pub expert_cos_other: f64,
    /// Two samples of the same observation.
    pub noise_floor: f64,
    /// The image of another scene.
    pub image_effect: f64,
    /// The expert's difference between the two scenes.
    pub expert_image_effect: f64,
    /// The other prompt.
    pub prompt_effect: f64,
    /// The expert's difference between the two targets.
    pub expert_prompt_effect: f64,
}

impl std::fmt::Display for ProbeReport {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        let e = &self.last_action_error;
        writeln!(f, "open-loop probe, {} observations", self.observations)?;
        writeln!(
            f,
            "| measure | policy | expert |\n|---|---:|---:|\n\
             | last action error, shoulder / elbow / wrist (rad) | {:.3} / {:.3} / {:.3} | 0 |\n\
             | cos(move, line to the prompted target) | {:.3} | 1 |\n\
             | cos(move, line to the other target) | {:.3} | {:.3} |\n\
             | noise floor: same observation, new noise (rad) | {:.3} | 0 |\n\
             | image effect: another scene's image (rad) | {:.3} | {:.3} |\n\
             | prompt effect: the other target's prompt (rad) | {:.3} | {:.3} |",
            e[0],
            e[1],
            e[2],
            self.cos_prompted,
            self.cos_other,
            self.expert_cos_other,
            self.noise_floor,
            self.image_effect,
            self.expert_image_effect,
            self.prompt_effect,
            self.expert_prompt_effect
        )
    }
}

/// Mean over the arm joints of |a − b|.
fn dist(a: &[f64], b: &[f64]) -> f64 {
    (0..ARM_JOINTS).map(|j| (a[j] - b[j]).abs()).sum::<f64>() / ARM_JOINTS as f64
}

/// Cosine between the arm-joint parts of `a` and `b`.
fn cosine(a: &[f64], b: &[f64]) -> f64 {
    let dot: f64 = (0..ARM_JOINTS).map(|j| a[j] * b[j]).sum();
    let n = |x: &[f64]| (0..ARM_JOINTS).map(|j| x[j] * x[j]).sum::<f64>().sqrt();
    dot / (n(a) * n(b)).max(1e-12)
}

/// Probes `policy` on `episodes` (their scene, prompt and start pose), the expert moving with
/// `profile`; the camera and the policy rate come from `cfg`.
pub fn probe(
    policy: &mut Policy,
    cfg: &Config,
    episodes: &[EpisodeSpec],
    profile: Profile,
) -> anyhow::Result<ProbeReport> {
    let cam = task_camera(cfg)?;
    let (camera, width, height) = (cam.name.as_str(), cam.width as usize, cam.height as usize);
    let dt = 1.0 / cfg.policy.action_rate_hz;
    let mut img = vec![0u8; width * height * 3];
    let mut img_swap = vec![0u8; width * height * 3];
    let mut r = ProbeReport::default();
    let infer = |policy: &mut Policy, data: &[u8], q: &[f64], prompt: &str| {
        let frames = [RawFrame {
            camera,
            width: width as u32,
            height: height as u32,
            stride: 3 * width as u32,
            encoding: crate::policy::Encoding::Rgb8,
            data,
        }];
        policy.infer(&RawObservation {
            frames: &frames,
            joint_positions: q,
            prompt,
        })
    };
    for e in episodes {
        let scene = ReachScene::from_seed(e.scene_seed);
        let swap = ReachScene::from_seed(e.scene_seed + SWAP_SCENE_OFFSET);
        let other = e.color.other();
        let (Some(reach), Some(goal), Some(goal_other)) = (
            Reach::plan_with(&e.start, &scene, e.color, 0.0, profile),
            inverse_kinematics(scene.target(e.color)),
            inverse_kinematics(scene.target(other)),
        ) else {
            continue;
        };
        for t in [0.0, 0.5, 1.0] {
            if t >= reach.end() {
                continue;
            }
            let q = reach.at(t);
            scene.render_rgb(&q, width, height, 3 * width, &mut img);
            swap.render_rgb(&q, width, height, 3 * width, &mut img_swap);
            let a = infer(policy, &img, &q, e.color.prompt())?;
            let a_again = infer(policy, &img, &q, e.color.prompt())?;
            let a_image = infer(policy, &img_swap, &q, e.color.prompt())?;
            let a_prompt = infer(policy, &img, &q, other.prompt())?;
            let h = a.len() / TASK_DOF;
            let last = |x: &[f64]| x[(h - 1) * TASK_DOF..h * TASK_DOF].to_vec();
            let (l, l_again, l_image, l_prompt) =
                (last(&a), last(&a_again), last(&a_image), last(&a_prompt));
            let ahead = (h - 1) as f64 * dt;
            let want = reach.at(t + ahead);
            for (j, err) in r.last_action_error.iter_mut().enumerate() {
                *err += (l[j] - want[j]).abs();
            }
            let mv: Vec<f64> = (0..ARM_JOINTS).map(|j| l[j] - q[j]).collect();
            let expert_mv: Vec<f64> = (0..ARM_JOINTS).map(|j| want[j] - q[j]).collect();
            let to: Vec<f64> = (0..ARM_JOINTS).map(|j| goal[j] - q[j]).collect();
            let to_other: Vec<f64> = (0..ARM_JOINTS).map(|j| goal_other[j] - q[j]).collect();
            r.cos_prompted += cosine(&mv, &to);
            r.cos_other += cosine(&mv, &to_other);
            r.expert_cos_other += cosine(&expert_mv, &to_other);
            r.noise_floor += dist(&l, &l_again);
            r.image_effect += dist(&l, &l_image);
            r.prompt_effect += dist(&l, &l_prompt);
            // what the inputs should change: fresh plans from q in the other scene / to the
            // other target, against one from q to the prompted target
            let fresh = Reach::plan_with(&q, &scene, e.color, 0.0, profile).map(|p| p.at(ahead));
            let fresh_swap =
                Reach::plan_with(&q, &swap, e.color, 0.0, profile).map(|p| p.at(ahead));
            let fresh_other =
                Reach::plan_with(&q, &scene, other, 0.0, profile).map(|p| p.at(ahead));
            if let (Some(f), Some(fs), Some(fo)) = (fresh, fresh_swap, fresh_other) {
                r.expert_image_effect += dist(&f, &fs);
                r.expert_prompt_effect += dist(&f, &fo);
            }
            r.observations += 1;
        }
    }
    let n = r.observations.max(1) as f64;
    for v in r.last_action_error.iter_mut() {
        *v /= n;
    }
    for v in [
        &mut r.cos_prompted,
        &mut r.cos_other,
        &mut r.expert_cos_other,
        &mut r.noise_floor,
        &mut r.image_effect,
        &mut r.expert_image_effect,
        &mut r.prompt_effect,
        &mut r.expert_prompt_effect,
    ] {
        *v /= n;
    }
    Ok(r)
}
