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
//! training loss. This is how the 2026-11-22 diagnosis found that the earlier 3-layer policy
//! sampled chunks from the state alone. Each effect is shown beside the expert's (fresh plans
//! from the same joints in the other scene / for the other target): what it should be.
//!
//! A policy with a delayed view (an earlier frame beside the newest) gets the newest frame as
//! its earlier one there (nothing moved); [`motion_probe`] asks whether it reads the motion.

use chunkrt_controller::config::Config;

use super::expert::{Profile, Reach};
use super::sim::EpisodeSpec;
use super::{inverse_kinematics, task_camera, ReachScene, ARM_JOINTS, TASK_DOF};
use chunkrt_policy::runtime::{Conditioning, Policy, RawFrame, RawObservation};

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
    // a delayed view (an earlier frame) gets the same image: nothing moved
    let views: Vec<String> = policy
        .delayed_views()
        .iter()
        .map(|v| v.name.clone())
        .collect();
    let infer = |policy: &mut Policy, data: &[u8], q: &[f64], prompt: &str| {
        let frame = |camera| super::rgb_frame(camera, width, height, data);
        let frames: Vec<RawFrame> = std::iter::once(frame(camera))
            .chain(views.iter().map(|v| frame(v.as_str())))
            .collect();
        policy.infer(
            &RawObservation {
                frames: &frames,
                joint_positions: q,
                prompt,
            },
            &Conditioning::Fresh,
        )
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

/// One regime of [`motion_probe`]: angles of the end effector about the robot's base at the
/// chunk's last action (rad; positive: counter-clockwise).
#[derive(Debug, Clone, Default, PartialEq)]
pub struct MotionLead {
    /// Mean of (chunk end after a counter-clockwise motion) − (after a clockwise one).
    pub lead: f64,
    /// Share of the observations where that difference is positive.
    pub share: f64,
    /// The same difference for the tracking expert ([`super::expert::track`], the labels of
    /// the moving-target data) given the targets' true motion: what it should be.
    pub expert: f64,
    /// Mean |difference| between the chunk after no motion (the earlier frame equal to the
    /// newest) and after a clockwise one, same noise: how far the earlier frame moves the chunk
    /// at all, for scale.
    pub still_vs_cw: f64,
}

/// What [`motion_probe`] measured.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct MotionProbe {
    /// Observations probed (each in both regimes).
    pub observations: usize,
    /// The robot at rest at the episode's start pose, in both frames.
    pub reaching: MotionLead,
    /// The robot on the prompted target, and in the earlier frame on where the target was
    /// then (it has been following it), gripper closed.
    pub following: MotionLead,
}

impl std::fmt::Display for MotionProbe {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        writeln!(
            f,
            "motion probe, {} observations: the chunk's end after the targets came from the \
             clockwise side minus after they came from the other (rad about the base)",
            self.observations
        )?;
        writeln!(
            f,
            "| regime | policy | positive in | tracking expert | still vs clockwise |\n\
             |---|---:|---:|---:|---:|"
        )?;
        for (name, m) in [
            ("reaching (start pose)", &self.reaching),
            ("following (on the target)", &self.following),
        ] {
            writeln!(
                f,
                "| {name} | {:+.3} | {:.0} % | {:+.3} | {:.3} |",
                m.lead,
                100.0 * m.share,
                m.expert,
                m.still_vs_cw
            )?;
        }
        Ok(())
    }
}

/// Does a policy with a delayed view ([`chunkrt_policy::DelayedView`]) read the motion in it?
/// For each of `episodes`, the newest frame is the scene as seeded and the earlier frame shows
/// both targets rotated about the base one way or the other by what turning at `rate_rad_s`
/// covers in the view's delay (they came from there: they move counter- or clockwise), or not
/// at all; the three chunks share their noise. Two regimes: the robot at rest at the start pose
/// (reaching), and the robot on the prompted target having followed it (following). A policy
/// that leads a moving target ends the counter-clockwise chunk further counter-clockwise, as
/// the tracking expert does; one that ignores the earlier frame gives the same chunk three
/// times.
pub fn motion_probe(
    policy: &mut Policy,
    cfg: &Config,
    episodes: &[EpisodeSpec],
    rate_rad_s: f64,
) -> anyhow::Result<MotionProbe> {
    let cam = task_camera(cfg)?;
    let (width, height) = (cam.width as usize, cam.height as usize);
    let (view, delay_s) = match policy.delayed_views() {
        [v] if v.camera == cam.name => (v.name.clone(), v.delay_ms * 1e-3),
        _ => anyhow::bail!(
            "the motion probe needs a policy with one delayed view of {}",
            cam.name
        ),
    };
    let dt = 1.0 / cfg.policy.action_rate_hz;
    let h = policy.horizon();
    let swing_rad = rate_rad_s * delay_s;
    let (mut now_img, mut before_img) =
        (vec![0u8; width * height * 3], vec![0u8; width * height * 3]);
    // the chunk's end angle for the newest frame (scene, pose) and an earlier one
    let mut infer = |policy: &mut Policy,
                     seed,
                     now: (&ReachScene, &[f64; TASK_DOF]),
                     before: (&ReachScene, &[f64; TASK_DOF]),
                     prompt| {
        now.0
            .render_rgb(now.1, width, height, 3 * width, &mut now_img);
        before
            .0
            .render_rgb(before.1, width, height, 3 * width, &mut before_img);
        let frame = |camera, data| super::rgb_frame(camera, width, height, data);
        let frames = [
            frame(cam.name.as_str(), &now_img),
            frame(view.as_str(), &before_img),
        ];
        policy.reseed(seed);
        let a = policy.infer(
            &RawObservation {
                frames: &frames,
                joint_positions: now.1,
                prompt,
            },
            &Conditioning::Fresh,
        )?;
        let h = a.len() / TASK_DOF;
        anyhow::Ok(angle(&a[(h - 1) * TASK_DOF..h * TASK_DOF]))
    };
    let rotated = |scene: &ReachScene, by: f64| {
        let (s, c) = by.sin_cos();
        ReachScene {
            targets: scene
                .targets
                .map(|p| [c * p[0] - s * p[1], s * p[0] + c * p[1]]),
        }
    };
    let mut r = MotionProbe::default();
    let mut positive = [0usize; 2];
    for (i, e) in episodes.iter().enumerate() {
        let scene = ReachScene::from_seed(e.scene_seed);
        let on = |sc: &ReachScene| -> Option<[f64; TASK_DOF]> {
            let g = inverse_kinematics(sc.target(e.color))?;
            Some([g[0], g[1], g[2], 1.0])
        };
        let (ccw_scene, cw_scene) = (rotated(&scene, -swing_rad), rotated(&scene, swing_rad));
        let (Some(on_now), Some(on_ccw), Some(on_cw)) = (on(&scene), on(&ccw_scene), on(&cw_scene))
        else {
            continue;
        };
        let prompt = e.color.prompt();
        let seed = 77 + i as u64;
        // (the robot's pose now, and then after a ccw / a cw / no motion)
        let regimes = [
            (e.start, [e.start, e.start, e.start]),
            (on_now, [on_ccw, on_cw, on_now]),
        ];
        for (k, (q, [q_ccw, q_cw, q_still])) in regimes.into_iter().enumerate() {
            let ccw = infer(policy, seed, (&scene, &q), (&ccw_scene, &q_ccw), prompt)?;
            let cw = infer(policy, seed, (&scene, &q), (&cw_scene, &q_cw), prompt)?;
            let still = infer(policy, seed, (&scene, &q), (&scene, &q_still), prompt)?;
            let m = if k == 0 {
                &mut r.reaching
            } else {
                &mut r.following
            };
            let lead = wrap(ccw - cw);
            m.lead += lead;
            positive[k] += usize::from(lead > 0.0);
            m.still_vs_cw += wrap(still - cw).abs();
            if let (Some(a), Some(b)) = (
                expert_end(&scene, e.color, &q, rate_rad_s, dt, h),
                expert_end(&scene, e.color, &q, -rate_rad_s, dt, h),
            ) {
                m.expert += wrap(a - b);
            }
        }
        r.observations += 1;
    }
    let n = r.observations.max(1) as f64;
    for (m, p) in [&mut r.reaching, &mut r.following]
        .into_iter()
        .zip(positive)
    {
        m.lead /= n;
        m.share = p as f64 / n;
        m.still_vs_cw /= n;
        m.expert /= n;
    }
    Ok(r)
}

/// The end effector's angle about the base at joint positions `q` (rad).
fn angle(q: &[f64]) -> f64 {
    let p = super::end_effector(q);
    p[1].atan2(p[0])
}

/// `x` wrapped into (−π, π].
fn wrap(x: f64) -> f64 {
    (x + std::f64::consts::PI).rem_euclid(std::f64::consts::TAU) - std::f64::consts::PI
}

/// The end angle of the tracking expert's chunk (`h` actions `dt` apart) from `q` with the
/// prompted target of `scene` turning about the base at `omega` (rad/s); `None` where the
/// target leaves the arm's reach.
fn expert_end(
    scene: &ReachScene,
    color: super::TargetColor,
    q: &[f64; TASK_DOF],
    omega: f64,
    dt: f64,
    h: usize,
) -> Option<f64> {
    // the joint-space goal on a dt/10 grid, linear in between
    let target = scene.target(color);
    let goals: Vec<[f64; ARM_JOINTS]> = (0..=10 * h)
        .map(|i| {
            let (s, c) = (omega * i as f64 * dt / 10.0).sin_cos();
            inverse_kinematics([c * target[0] - s * target[1], s * target[0] + c * target[1]])
        })
        .collect::<Option<_>>()?;
    let goal_at = |t: f64| {
        let x = (t / dt * 10.0).clamp(0.0, (10 * h - 1) as f64);
        let i = x.floor() as usize;
        let f = x - i as f64;
        std::array::from_fn(|j| goals[i][j] + (goals[i + 1][j] - goals[i][j]) * f)
    };
    let mut a = *q;
    for i in 0..h - 1 {
        super::expert::track(&mut a, i as f64 * dt, dt, 1.0, &goal_at);
    }
    Some(angle(&a))
}
