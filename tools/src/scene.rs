//! The reach task: a planar 3-link arm seen from above, two coloured targets placed at random per
//! episode, and a prompt naming the one to reach ("reach the red target").
//!
//! Everything here is a pure function of (episode seed, joint positions): the fake camera renders
//! it live from the simulated robot's joint states, and `chunkrt train` / `chunkrt eval` render
//! the same pixels in-process, so the policy sees the same images in training, evaluation and
//! the demo.
//!
//! Geometry (metres, radians): the base is at the origin, joint `i` rotates link `i` relative to
//! link `i − 1`, links are 0.45 / 0.35 / 0.15 m long, and the end effector is the tip of the last
//! link. The image shows the square [−1.05, 1.05]² with +y up.

use rand::{Rng, SeedableRng};

/// Link lengths (m).
pub const LINKS: [f64; 3] = [0.45, 0.35, 0.15];
/// Radius of a target disk (m).
pub const TARGET_RADIUS: f64 = 0.1;
/// Radius of the rendered end-effector (gripper) marker (m).
pub const END_EFFECTOR_RADIUS: f64 = 0.045;
/// A target counts as reached when the gripper marker touches its disk: the end effector is
/// within this distance of the target's centre (m).
pub const REACH_TOLERANCE: f64 = TARGET_RADIUS + END_EFFECTOR_RADIUS;
/// Half-width of the square the camera sees (m).
pub const VIEW_HALF_WIDTH: f64 = 1.05;
/// Joint ranges a solution must stay inside (rad), with margin to the robot's limits.
pub const JOINT_RANGE: [(f64, f64); 3] = [(-2.6, 2.6), (0.15, 2.45), (-2.4, 2.4)];

/// Which target.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub enum TargetColor {
    Red,
    Blue,
}

impl TargetColor {
    /// Both colours, in prompt order.
    pub const ALL: [TargetColor; 2] = [TargetColor::Red, TargetColor::Blue];

    /// The colour's name in prompts.
    pub fn name(self) -> &'static str {
        match self {
            TargetColor::Red => "red",
            TargetColor::Blue => "blue",
        }
    }

    /// The other target.
    pub fn other(self) -> Self {
        match self {
            TargetColor::Red => TargetColor::Blue,
            TargetColor::Blue => TargetColor::Red,
        }
    }

    /// The prompt asking for this target.
    pub fn prompt(self) -> &'static str {
        match self {
            TargetColor::Red => "reach the red target",
            TargetColor::Blue => "reach the blue target",
        }
    }

    /// The target a prompt asks for (`None` if it names neither colour).
    pub fn from_prompt(prompt: &str) -> Option<Self> {
        let p = prompt.to_ascii_lowercase();
        match (p.contains("red"), p.contains("blue")) {
            (true, false) => Some(TargetColor::Red),
            (false, true) => Some(TargetColor::Blue),
            _ => None,
        }
    }

    fn rgb(self) -> [f32; 3] {
        match self {
            TargetColor::Red => [225.0, 45.0, 40.0],
            TargetColor::Blue => [40.0, 95.0, 235.0],
        }
    }
}

/// One episode's scene: where the targets are.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct ReachScene {
    /// Target centres (m), indexed like [`TargetColor::ALL`].
    pub targets: [[f64; 2]; 2],
}

/// Wraps an angle to (−π, π].
pub fn wrap(a: f64) -> f64 {
    let mut x = (a + std::f64::consts::PI).rem_euclid(2.0 * std::f64::consts::PI);
    if x == 0.0 {
        x = 2.0 * std::f64::consts::PI;
    }
    x - std::f64::consts::PI
}

/// Joint positions (link 0 start, then the end of each link) of the first three joints of `q`.
pub fn forward_kinematics(q: &[f64]) -> [[f64; 2]; 4] {
    let mut pts = [[0.0; 2]; 4];
    let mut a = 0.0;
    for i in 0..3 {
        a += q.get(i).copied().unwrap_or(0.0);
        pts[i + 1] = [
            pts[i][0] + LINKS[i] * a.cos(),
            pts[i][1] + LINKS[i] * a.sin(),
        ];
    }
    pts
}

/// End-effector position (m).
pub fn end_effector(q: &[f64]) -> [f64; 2] {
    forward_kinematics(q)[3]
}

/// The expert's inverse kinematics: the last link points radially outward (away from the base),
/// the elbow bends positive. `None` when the point is out of reach or the solution leaves
/// [`JOINT_RANGE`].
pub fn inverse_kinematics(target: [f64; 2]) -> Option<[f64; 3]> {
    let [x, y] = target;
    let r = x.hypot(y);
    if !(1e-6..=LINKS.iter().sum::<f64>()).contains(&r) {
        return None;
    }
    let phi = y.atan2(x);
    // wrist centre
    let (cx, cy) = (x - LINKS[2] * phi.cos(), y - LINKS[2] * phi.sin());
    let rc2 = cx * cx + cy * cy;
    let c2 = (rc2 - LINKS[0].powi(2) - LINKS[1].powi(2)) / (2.0 * LINKS[0] * LINKS[1]);
    if !(-1.0..=1.0).contains(&c2) {
        return None;
    }
    let q2 = c2.acos();
    let q1 = wrap(cy.atan2(cx) - (LINKS[1] * q2.sin()).atan2(LINKS[0] + LINKS[1] * q2.cos()));
    let q3 = wrap(phi - q1 - q2);
    let q = [q1, q2, q3];
    q.iter()
        .zip(JOINT_RANGE.iter())
        .all(|(v, (lo, hi))| (*lo..=*hi).contains(v))
        .then_some(q)
}

impl ReachScene {
    /// The scene of episode `seed`: two targets at least 0.4 m apart, each reachable by
    /// [`inverse_kinematics`], between 0.4 and 0.85 m from the base.
    pub fn from_seed(seed: u64) -> Self {
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(seed ^ 0x7a3e_91c4_d2b8_5f06);
        let sample = |rng: &mut rand_chacha::ChaCha8Rng| loop {
            let r = rng.gen_range(0.4..0.85);
            let a = rng.gen_range(-std::f64::consts::PI..std::f64::consts::PI);
            let p = [r * a.cos(), r * a.sin()];
            if inverse_kinematics(p).is_some() {
                return p;
            }
        };
        let a = sample(&mut rng);
        let b = loop {
            let b = sample(&mut rng);
            if (a[0] - b[0]).hypot(a[1] - b[1]) >= 0.4 {
                break b;
            }
        };
        ReachScene { targets: [a, b] }
    }

    /// Centre of a target (m).
    pub fn target(&self, c: TargetColor) -> [f64; 2] {
        match c {
            TargetColor::Red => self.targets[0],
            TargetColor::Blue => self.targets[1],
        }
    }

    /// Distance from the end effector at `q` to target `c` (m).
    pub fn distance(&self, q: &[f64], c: TargetColor) -> f64 {
        let e = end_effector(q);
        let t = self.target(c);
        (e[0] - t[0]).hypot(e[1] - t[1])
    }

    /// Renders the view at joint positions `q` (3 arm joints, then the gripper 0 open .. 1
    /// closed) into packed RGB8 rows: `out` holds `height` rows of `stride` bytes. No allocation.
    pub fn render_rgb(
        &self,
        q: &[f64],
        width: usize,
        height: usize,
        stride: usize,
        out: &mut [u8],
    ) {
        if width == 0 || height == 0 || stride < 3 * width || out.len() < stride * height {
            return;
        }
        let pts = forward_kinematics(q);
        let grip = q.get(3).copied().unwrap_or(0.0).clamp(0.0, 1.0) as f32;
        // pixels per metre and the pixel centre of the origin
        let scale = width.min(height) as f64 / (2.0 * VIEW_HALF_WIDTH);
        let (ox, oy) = (width as f64 / 2.0, height as f64 / 2.0);
        let to_px = |p: [f64; 2]| [ox + p[0] * scale, oy - p[1] * scale];
        let px: [[f64; 2]; 4] = [to_px(pts[0]), to_px(pts[1]), to_px(pts[2]), to_px(pts[3])];
        let tpx = [to_px(self.targets[0]), to_px(self.targets[1])];
        let r_target = TARGET_RADIUS * scale;
        let half_link = 0.028 * scale;
        let r_joint = 0.04 * scale;
        let r_ee = END_EFFECTOR_RADIUS * scale;
        let ee_rgb = [240.0, 215.0 - 110.0 * grip, 60.0 + 20.0 * grip];
        for y in 0..height {
            let row = &mut out[y * stride..y * stride + 3 * width];
            for x in 0..width {
                let p = [x as f64 + 0.5, y as f64 + 0.5];
                // background: a dark table with a faint ring at the arm's reach
                let rr = (p[0] - ox).hypot(p[1] - oy) / scale;
                let ring = (1.0 - ((rr - 0.95).abs() * scale)).clamp(0.0, 1.0) as f32;
                let mut c = [34.0 + 14.0 * ring, 36.0 + 14.0 * ring, 40.0 + 14.0 * ring];
                for (i, col) in TargetColor::ALL.iter().enumerate() {
                    let d = (p[0] - tpx[i][0]).hypot(p[1] - tpx[i][1]);
                    blend(&mut c, col.rgb(), coverage(d, r_target));
                }
                for i in 0..3 {
                    let d = segment_distance(p, px[i], px[i + 1]);
                    blend(&mut c, [190.0, 190.0, 196.0], coverage(d, half_link));
                }
                for j in px.iter().take(3) {
                    let d = (p[0] - j[0]).hypot(p[1] - j[1]);
                    blend(&mut c, [120.0, 124.0, 132.0], coverage(d, r_joint));
                }
                let d = (p[0] - px[3][0]).hypot(p[1] - px[3][1]);
                blend(&mut c, ee_rgb, coverage(d, r_ee));
                for (k, v) in c.iter().enumerate() {
                    row[3 * x + k] = v.round().clamp(0.0, 255.0) as u8;
                }
            }
        }
    }
}

/// Anti-aliased coverage of a pixel at distance `d` (px) from a shape of radius `r` (px).
fn coverage(d: f64, r: f64) -> f32 {
    (r + 0.5 - d).clamp(0.0, 1.0) as f32
}

fn blend(c: &mut [f32; 3], rgb: [f32; 3], a: f32) {
    if a > 0.0 {
        for k in 0..3 {
            c[k] += (rgb[k] - c[k]) * a;
        }
    }
}

fn segment_distance(p: [f64; 2], a: [f64; 2], b: [f64; 2]) -> f64 {
    let (dx, dy) = (b[0] - a[0], b[1] - a[1]);
    let l2 = dx * dx + dy * dy;
    let t = if l2 > 0.0 {
        (((p[0] - a[0]) * dx + (p[1] - a[1]) * dy) / l2).clamp(0.0, 1.0)
    } else {
        0.0
    };
    (p[0] - a[0] - t * dx).hypot(p[1] - a[1] - t * dy)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn inverse_kinematics_reaches_the_point() {
        let mut n = 0;
        for seed in 0..200 {
            let s = ReachScene::from_seed(seed);
            for c in TargetColor::ALL {
                let q = inverse_kinematics(s.target(c)).expect("scene targets are reachable");
                assert!(
                    s.distance(&q, c) < 1e-9,
                    "seed {seed}: {}",
                    s.distance(&q, c)
                );
                n += 1;
            }
            let [a, b] = s.targets;
            assert!((a[0] - b[0]).hypot(a[1] - b[1]) >= 0.4);
        }
        assert_eq!(n, 400);
        assert!(inverse_kinematics([2.0, 0.0]).is_none());
    }

    #[test]
    fn scenes_are_deterministic_and_differ_by_seed() {
        assert_eq!(ReachScene::from_seed(7), ReachScene::from_seed(7));
        assert_ne!(ReachScene::from_seed(7), ReachScene::from_seed(8));
    }

    #[test]
    fn prompts_round_trip() {
        for c in TargetColor::ALL {
            assert_eq!(TargetColor::from_prompt(c.prompt()), Some(c));
        }
        assert_eq!(TargetColor::from_prompt("reach the green target"), None);
    }

    #[test]
    fn render_shows_targets_and_the_arm() {
        let s = ReachScene::from_seed(3);
        let (w, h) = (64, 64);
        let mut img = vec![0u8; w * h * 3];
        let q = [0.3, 1.0, -0.5, 0.0];
        s.render_rgb(&q, w, h, 3 * w, &mut img);
        let at = |p: [f64; 2]| {
            let scale = w as f64 / (2.0 * VIEW_HALF_WIDTH);
            let x = (w as f64 / 2.0 + p[0] * scale) as usize;
            let y = (h as f64 / 2.0 - p[1] * scale) as usize;
            [
                img[3 * (y * w + x)],
                img[3 * (y * w + x) + 1],
                img[3 * (y * w + x) + 2],
            ]
        };
        let red = at(s.target(TargetColor::Red));
        let blue = at(s.target(TargetColor::Blue));
        assert!(red[0] > 150 && red[2] < 100, "{red:?}");
        assert!(blue[2] > 150 && blue[0] < 100, "{blue:?}");
        let ee = at(end_effector(&q));
        assert!(ee[0] > 200 && ee[1] > 150, "{ee:?}");
        // the arm moves the pixels
        let mut img2 = vec![0u8; w * h * 3];
        s.render_rgb(&[1.3, 1.0, -0.5, 0.0], w, h, 3 * w, &mut img2);
        assert!(img.iter().zip(&img2).filter(|(a, b)| a != b).count() > 50);
    }
}
