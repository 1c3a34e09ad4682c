//! The scripted expert: inverse kinematics to the prompted target, then a minimum-jerk motion in
//! joint space from the current position, the gripper closing on arrival.

use super::{inverse_kinematics, ReachScene, TargetColor, ARM_JOINTS, TASK_DOF};

/// Peak joint velocity of the expert's motion (rad/s); the duration follows from the largest
/// joint displacement.
pub const PEAK_VELOCITY: f64 = 1.2;
/// Shortest motion (s).
pub const MIN_DURATION: f64 = 0.8;

/// `s³ (10 − 15 s + 6 s²)`: minimum-jerk progress for `s` in [0, 1].
pub fn min_jerk(s: f64) -> f64 {
    let s = s.clamp(0.0, 1.0);
    s * s * s * (10.0 - 15.0 * s + 6.0 * s * s)
}

/// Time constant of the distance-paced profile's final approach (s).
pub const APPROACH_TAU: f64 = 0.4;
/// The distance-paced motion counts as arrived within this (rad, largest joint).
pub const ARRIVED: f64 = 0.01;

/// How the expert moves along the joint-space line to its goal.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, clap::ValueEnum)]
pub enum Profile {
    /// Minimum jerk from rest to rest (`s³ (10 − 15 s + 6 s²)`).
    MinJerk,
    /// The speed depends only on the distance left, `min(v_peak, d / τ)` (largest joint), so the
    /// motion seen from any pose does not depend on where it started: the demonstrations' chunk
    /// is a function of the observation. It starts at full speed; the executor's jerk-limited
    /// generator smooths the start. What the embedded policy is trained on.
    #[default]
    DistancePaced,
}

impl Profile {
    /// The name on the command line and in dataset files.
    pub fn name(self) -> &'static str {
        match self {
            Profile::MinJerk => "min-jerk",
            Profile::DistancePaced => "distance-paced",
        }
    }
}

/// One planned reach: from `start` at time `t0` to `goal` in `duration`.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Reach {
    pub start: [f64; TASK_DOF],
    pub goal: [f64; TASK_DOF],
    pub t0: f64,
    pub duration: f64,
    pub profile: Profile,
}

impl Reach {
    /// Plans the reach for `color` from joint positions `q` at time `t0`; `None` if the target
    /// has no inverse-kinematics solution.
    pub fn plan(q: &[f64], scene: &ReachScene, color: TargetColor, t0: f64) -> Option<Self> {
        let ik = inverse_kinematics(scene.target(color))?;
        let mut start = [0.0; TASK_DOF];
        start.copy_from_slice(&q[..TASK_DOF]);
        let mut goal = start;
        goal[..ARM_JOINTS].copy_from_slice(&ik);
        goal[ARM_JOINTS] = 1.0;
        let d = (0..ARM_JOINTS)
            .map(|j| (goal[j] - start[j]).abs())
            .fold(0.0, f64::max);
        // min-jerk peak velocity is 1.875 · distance / duration
        let duration = (1.875 * d / PEAK_VELOCITY).max(MIN_DURATION);
        Some(Reach {
            start,
            goal,
            t0,
            duration,
            profile: Profile::MinJerk,
        })
    }

    /// [`Self::plan`] with the given profile.
    pub fn plan_with(
        q: &[f64],
        scene: &ReachScene,
        color: TargetColor,
        t0: f64,
        profile: Profile,
    ) -> Option<Self> {
        let mut r = Self::plan(q, scene, color, t0)?;
        if profile == Profile::DistancePaced {
            let (cruise, knee) = r.cruise();
            r.duration = cruise + APPROACH_TAU * (knee / ARRIVED).max(1.0).ln();
            r.profile = profile;
        }
        Some(r)
    }

    /// Distance-paced profile: the time at full speed (s) and the distance left when it ends (rad).
    fn cruise(&self) -> (f64, f64) {
        let d = self.distance();
        let knee = PEAK_VELOCITY * APPROACH_TAU;
        (((d - knee) / PEAK_VELOCITY).max(0.0), d.min(knee))
    }

    /// Largest joint displacement of the reach (rad).
    fn distance(&self) -> f64 {
        (0..ARM_JOINTS)
            .map(|j| (self.goal[j] - self.start[j]).abs())
            .fold(0.0, f64::max)
    }

    /// Progress along the line (0 at the start, 1 at the goal) at `t`.
    fn progress(&self, t: f64) -> f64 {
        let tau = (t - self.t0).max(0.0);
        match self.profile {
            Profile::MinJerk => min_jerk(tau / self.duration),
            Profile::DistancePaced => {
                let d = self.distance();
                if d <= 0.0 {
                    return 1.0;
                }
                // distance left: linear at v_peak down to the knee, then d' = −d / τ
                let (cruise, knee) = self.cruise();
                let left = if tau <= cruise {
                    d - PEAK_VELOCITY * tau
                } else {
                    knee * (-(tau - cruise) / APPROACH_TAU).exp()
                };
                if tau >= self.duration {
                    1.0
                } else {
                    (1.0 - left / d).clamp(0.0, 1.0)
                }
            }
        }
    }

    /// Arrival time.
    pub fn end(&self) -> f64 {
        self.t0 + self.duration
    }

    /// The expert's joint positions at time `t`: the arm on the min-jerk path, the gripper open
    /// (0) while moving and closed (1) from arrival on.
    pub fn at(&self, t: f64) -> [f64; TASK_DOF] {
        let s = self.progress(t);
        let mut q = [0.0; TASK_DOF];
        for (j, v) in q.iter_mut().enumerate().take(ARM_JOINTS) {
            *v = self.start[j] + (self.goal[j] - self.start[j]) * s;
        }
        q[ARM_JOINTS] = if t >= self.end() { 1.0 } else { 0.0 };
        q
    }
}

/// The tracking expert closes the gripper once every arm joint is this close to its goal (rad).
pub const TRACK_CLOSE: f64 = 0.02;

/// The expert for a moving target: advances `q` from `t` by `dt` (s) tracking the joint-space
/// goal `goal_at(t)` (the inverse kinematics of where the target is at t). Its velocity is
/// `feedforward` times the goal's own velocity plus the distance-paced approach along the line
/// to the goal (`min(v_peak, d / τ)`, d the largest joint's distance: the distance-paced expert
/// re-planned every instant). With feed-forward 1 it catches up and then moves with the
/// target; with 0 it trails a moving target by about its velocity times τ. The gripper closes
/// once within [`TRACK_CLOSE`] of the goal and stays closed.
pub fn track(
    q: &mut [f64; TASK_DOF],
    t: f64,
    dt: f64,
    feedforward: f64,
    goal_at: &impl Fn(f64) -> [f64; ARM_JOINTS],
) {
    // 10 ms sub-steps: explicit Euler of the τ = 0.4 s approach is well inside its stability
    const SUB: usize = 10;
    let h = dt / SUB as f64;
    for i in 0..SUB {
        let ti = t + i as f64 * h;
        let (g, g1) = (goal_at(ti), goal_at(ti + h));
        let e: [f64; ARM_JOINTS] = std::array::from_fn(|j| g[j] - q[j]);
        let d = e.iter().fold(0.0, |m: f64, v| m.max(v.abs()));
        let speed = if d > 0.0 {
            PEAK_VELOCITY.min(d / APPROACH_TAU) / d
        } else {
            0.0
        };
        for j in 0..ARM_JOINTS {
            q[j] += feedforward * (g1[j] - g[j]) + e[j] * speed * h;
        }
        if d <= TRACK_CLOSE {
            q[ARM_JOINTS] = 1.0;
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn distance_paced_speed_depends_on_the_distance_left_only() {
        let scene = ReachScene::from_seed(11);
        let q0 = [0.0, 1.2, 0.6, 0.0];
        let c = TargetColor::Red;
        let a = Reach::plan_with(&q0, &scene, c, 0.0, Profile::DistancePaced).unwrap();
        assert!(scene.distance(&a.at(a.end()), c) < 1e-9);
        // re-planned from a pose on the way, the motion continues as before
        let mid = a.at(0.6);
        let b = Reach::plan_with(&mid, &scene, c, 0.6, Profile::DistancePaced).unwrap();
        for k in 0..10 {
            let t = 0.6 + 0.1 * k as f64;
            for j in 0..3 {
                assert!((a.at(t)[j] - b.at(t)[j]).abs() < 1e-6, "t {t} joint {j}");
            }
        }
        // the min-jerk motion restarts from rest instead
        let m = Reach::plan(&q0, &scene, c, 0.0).unwrap();
        let m2 = Reach::plan(&m.at(0.6), &scene, c, 0.6).unwrap();
        assert!((m.at(0.8)[0] - m2.at(0.8)[0]).abs() > 1e-3);
    }

    #[test]
    fn reach_ends_on_the_target_smoothly() {
        let scene = ReachScene::from_seed(11);
        let q0 = [0.0, 1.2, 0.6, 0.0];
        for c in TargetColor::ALL {
            let r = Reach::plan(&q0, &scene, c, 0.5).unwrap();
            assert_eq!(r.at(0.5)[..3], q0[..3]);
            assert!(scene.distance(&r.at(r.end()), c) < 1e-9);
            assert_eq!(r.at(r.end() - 1e-3)[3], 0.0);
            assert_eq!(r.at(r.end())[3], 1.0);
            // peak velocity within the plan's limit
            let dt = 1e-3;
            let mut vmax = 0.0f64;
            let mut t = r.t0;
            while t < r.end() {
                let (a, b) = (r.at(t), r.at(t + dt));
                for j in 0..3 {
                    vmax = vmax.max((b[j] - a[j]).abs() / dt);
                }
                t += dt;
            }
            assert!(vmax <= PEAK_VELOCITY * 1.001, "{vmax}");
        }
    }

    #[test]
    fn tracking_with_feedforward_stays_on_a_moving_goal_and_without_trails_it() {
        // a goal moving at 0.5 rad/s on the first joint
        let goal = |t: f64| [0.2 + 0.5 * t, 1.0, -0.5];
        let run = |ff: f64| {
            let mut q = [0.0, 1.2, 0.0, 0.0];
            for k in 0..60 {
                track(&mut q, k as f64 * 0.1, 0.1, ff, &goal);
            }
            (q, goal(6.0))
        };
        let (q, g) = run(1.0);
        for j in 0..ARM_JOINTS {
            assert!(
                (q[j] - g[j]).abs() < 1e-6,
                "joint {j}: {} vs {}",
                q[j],
                g[j]
            );
        }
        assert_eq!(q[ARM_JOINTS], 1.0, "the gripper closed on the goal");
        let (q, g) = run(0.0);
        // the distance-paced pursuit trails by about v τ = 0.2 rad
        assert!(
            (g[0] - q[0] - 0.5 * APPROACH_TAU).abs() < 0.01,
            "lag {}",
            g[0] - q[0]
        );
        assert_eq!(
            q[ARM_JOINTS], 0.0,
            "never on the goal: the gripper stays open"
        );
    }
}
