//! The FR3's geometry, as far as the driver needs it to stop a command before the robot's own
//! reflex: the forward kinematics of the arm (Franka's published Denavit-Hartenberg table, in
//! Craig's convention), the links as capsules, the clearance between links that can meet, and a
//! workspace box for the flange and the hand.
//!
//! The capsules are this crate's own, sized around the arm's covers (deliberately generous: the
//! robot's own model is itself inflated, and its self-collision reflex fires with a margin still
//! standing); they are checked in `tests/franka_sim.rs` against franka-sim's reflex with DROID
//! chunks that drive every joint to -1 and to +1. No allocation: the 1 kHz cycle calls it.

use crate::limits::JOINTS;

/// Franka's DH table (Craig's convention): per joint (a_{i-1} m, d_i m, alpha_{i-1} rad).
const DH: [(f64, f64, f64); JOINTS] = [
    (0.0, 0.333, 0.0),
    (0.0, 0.0, -std::f64::consts::FRAC_PI_2),
    (0.0, 0.316, std::f64::consts::FRAC_PI_2),
    (0.0825, 0.0, std::f64::consts::FRAC_PI_2),
    (-0.0825, 0.384, -std::f64::consts::FRAC_PI_2),
    (0.0, 0.0, std::f64::consts::FRAC_PI_2),
    (0.088, 0.0, std::f64::consts::FRAC_PI_2),
];
/// The flange along joint 7's axis (m).
const FLANGE_D: f64 = 0.107;

type V3 = [f64; 3];

/// A rigid transform: rotation (rows) and translation.
#[derive(Clone, Copy)]
struct Frame {
    r: [[f64; 3]; 3],
    p: V3,
}

impl Frame {
    const IDENTITY: Frame = Frame {
        r: [[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]],
        p: [0.0; 3],
    };

    /// This frame followed by the DH step (a, d, alpha, theta): RotX(alpha) TransX(a) RotZ(theta)
    /// TransZ(d).
    fn dh(&self, a: f64, d: f64, alpha: f64, theta: f64) -> Frame {
        let (sa, ca) = alpha.sin_cos();
        let (st, ct) = theta.sin_cos();
        // the step's own rotation and translation
        let r = [
            [ct, -st, 0.0],
            [st * ca, ct * ca, -sa],
            [st * sa, ct * sa, ca],
        ];
        let p = [a, -sa * d, ca * d];
        let mut out = Frame::IDENTITY;
        for (i, row) in out.r.iter_mut().enumerate() {
            for (k, v) in row.iter_mut().enumerate() {
                *v = (0..3).map(|m| self.r[i][m] * r[m][k]).sum();
            }
            out.p[i] = self.p[i] + (0..3).map(|m| self.r[i][m] * p[m]).sum::<f64>();
        }
        out
    }

    /// A point given in this frame, in the base frame.
    fn point(&self, x: V3) -> V3 {
        let mut out = self.p;
        for (i, o) in out.iter_mut().enumerate() {
            *o += self.r[i][0] * x[0] + self.r[i][1] * x[1] + self.r[i][2] * x[2];
        }
        out
    }
}

/// Points along the arm (base frame, m) from which the capsules are spanned.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Skeleton {
    /// Joint 2's and 1's origin (the shoulder, 0.333 m above the base).
    pub shoulder: V3,
    /// Joint 4's origin (the elbow).
    pub elbow: V3,
    /// The forearm's kink (joint 4 back along its x by 0.0825 m).
    pub kink: V3,
    /// Joint 5's and 6's origin (the wrist).
    pub wrist: V3,
    /// Joint 7's origin.
    pub j7: V3,
    /// The flange.
    pub flange: V3,
    /// The hand's tip (`hand_length` past the flange along its axis).
    pub tip: V3,
}

/// The arm's points at joint positions `q`, with a hand `hand_length` m long past the flange.
pub fn skeleton(q: &[f64; JOINTS], hand_length: f64) -> Skeleton {
    let mut f = Frame::IDENTITY;
    let mut origins = [[0.0; 3]; JOINTS];
    let mut frames = [Frame::IDENTITY; JOINTS];
    for j in 0..JOINTS {
        let (a, d, alpha) = DH[j];
        f = f.dh(a, d, alpha, q[j]);
        origins[j] = f.p;
        frames[j] = f;
    }
    Skeleton {
        shoulder: origins[1],
        elbow: origins[3],
        kink: frames[4].point([0.0, 0.0, -DH[4].1]),
        wrist: origins[4],
        j7: origins[6],
        flange: frames[6].point([0.0, 0.0, FLANGE_D]),
        tip: frames[6].point([0.0, 0.0, FLANGE_D + hand_length]),
    }
}

fn sub(a: V3, b: V3) -> V3 {
    [a[0] - b[0], a[1] - b[1], a[2] - b[2]]
}

fn dot(a: V3, b: V3) -> f64 {
    a[0] * b[0] + a[1] * b[1] + a[2] * b[2]
}

/// The distance between segments p0-p1 and q0-q1 (closest points by clamped parameters).
pub fn segment_distance(p0: V3, p1: V3, q0: V3, q1: V3) -> f64 {
    let (d1, d2, r) = (sub(p1, p0), sub(q1, q0), sub(p0, q0));
    let (a, e, f) = (dot(d1, d1), dot(d2, d2), dot(d2, r));
    let (mut s, mut t);
    if a <= 1e-12 && e <= 1e-12 {
        return dot(r, r).sqrt();
    }
    if a <= 1e-12 {
        s = 0.0;
        t = (f / e).clamp(0.0, 1.0);
    } else {
        let c = dot(d1, r);
        if e <= 1e-12 {
            t = 0.0;
            s = (-c / a).clamp(0.0, 1.0);
        } else {
            let b = dot(d1, d2);
            let denom = a * e - b * b;
            s = if denom > 1e-12 {
                ((b * f - c * e) / denom).clamp(0.0, 1.0)
            } else {
                0.0
            };
            t = (b * s + f) / e;
            if t < 0.0 {
                t = 0.0;
                s = (-c / a).clamp(0.0, 1.0);
            } else if t > 1.0 {
                t = 1.0;
                s = ((b - c) / a).clamp(0.0, 1.0);
            }
        }
    }
    let cp = [p0[0] + d1[0] * s, p0[1] + d1[1] * s, p0[2] + d1[2] * s];
    let cq = [q0[0] + d2[0] * t, q0[1] + d2[1] * t, q0[2] + d2[2] * t];
    let d = sub(cp, cq);
    dot(d, d).sqrt()
}

/// The link segments, named; their points come from [`Skeleton`] in [`capsules`].
pub const CAPSULE_NAMES: [&str; 6] = ["base", "upper arm", "elbow", "forearm", "wrist", "hand"];
/// Segment pairs that can meet, and the distance between their segments (m) at which the links
/// around them can touch: the links three or more apart along the chain, as the robot's own
/// self-collision model monitors them (the hand, one wrist from the forearm, passes close to it
/// by design; the upper arm and the forearm, whose segments meet at the elbow by construction,
/// are left to joint 4's range: not covered). The distances were measured, not guessed: over 6 000 random poses within the
/// FR3's joint ranges, the largest of (segment distance - the surface distance of the links'
/// collision meshes in the FR3 model franka-sim runs, MuJoCo's `mj_geomDistance`) among poses
/// whose links lay within 0.2 m, plus 1 cm (`tools/python/fr3_geometry.py`; its output in
/// `benches/data/franka/2026-11-27-geometry/`). So a segment distance above this plus the
/// clearance keeps the links at least the clearance apart, in every pose sampled.
const PAIRS: [(usize, usize, f64); 7] = [
    (0, 2, 0.226),
    (0, 3, 0.305),
    (0, 4, 0.238),
    (0, 5, 0.256),
    (1, 4, 0.213),
    (1, 5, 0.229),
    (2, 5, 0.240),
];

/// How far short of the wrist the forearm's segment ends (m): the wrist's own segment covers the
/// joint, and the hand, 0.088 m off the forearm's axis, passes close to its end by design.
const FOREARM_SHORT: f64 = 0.08;
/// How far past the elbow's kink the forearm's segment starts (m): the elbow's covers that.
const FOREARM_START: f64 = 0.12;

fn capsules(s: &Skeleton) -> [(V3, V3); 6] {
    let along = sub(s.wrist, s.kink);
    let len = dot(along, along).sqrt().max(1e-9);
    let at = |k: f64| {
        [
            s.kink[0] + along[0] * k,
            s.kink[1] + along[1] * k,
            s.kink[2] + along[2] * k,
        ]
    };
    let (fore_start, fore_end) = (at(FOREARM_START / len), at(1.0 - FOREARM_SHORT / len));
    [
        ([0.0, 0.0, 0.0], s.shoulder),
        (s.shoulder, s.elbow),
        (s.elbow, s.kink),
        (fore_start, fore_end),
        (s.wrist, s.j7),
        (s.flange, s.tip),
    ]
}

/// What the driver holds the arm within: a box for the flange and the hand's tip (base frame,
/// m) and a clearance between links that can meet (m, past the capsules' radii).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Workspace {
    pub min: V3,
    pub max: V3,
    /// Past the flange along its axis (m): 0.1034 for the Franka Hand's fingertips.
    pub hand_length: f64,
    /// Clearance between links past their capsules (m).
    pub clearance: f64,
}

impl Default for Workspace {
    fn default() -> Self {
        Self {
            min: [-0.9, -0.9, 0.05],
            max: [0.9, 0.9, 1.3],
            hand_length: 0.1034,
            clearance: 0.05,
        }
    }
}

/// Why a pose is outside the workspace, with the margin left (negative: by how much it is in).
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum Limit {
    /// Two capsules (indices into [`CAPSULE_NAMES`]) closer than the clearance.
    Links(usize, usize),
    /// The flange (false) or the hand's tip (true) outside the box along an axis (0 x, 1 y, 2 z).
    Box(bool, usize),
}

impl std::fmt::Display for Limit {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match *self {
            Limit::Links(a, b) => write!(f, "{} near {}", CAPSULE_NAMES[a], CAPSULE_NAMES[b]),
            Limit::Box(tip, axis) => write!(
                f,
                "{} outside the workspace box along {}",
                if tip { "the hand" } else { "the flange" },
                ["x", "y", "z"][axis]
            ),
        }
    }
}

/// Margins of a pose, one per limit: [`PAIRS`]'s, then the flange's and the hand's box sides.
pub const LIMITS: usize = PAIRS.len() + 6;

impl Workspace {
    /// The margin of the pose `q` to each limit (m; negative: inside it by that much), in the
    /// order of [`Workspace::limit`]. A pose that is not a number is inside every limit.
    pub fn margins(&self, q: &[f64; JOINTS]) -> [f64; LIMITS] {
        let s = skeleton(q, self.hand_length);
        let caps = capsules(&s);
        let mut out = [0.0; LIMITS];
        for (k, &(a, b, touch)) in PAIRS.iter().enumerate() {
            out[k] = segment_distance(caps[a].0, caps[a].1, caps[b].0, caps[b].1)
                - touch
                - self.clearance;
        }
        for (i, p) in [s.flange, s.tip].into_iter().enumerate() {
            for axis in 0..3 {
                out[PAIRS.len() + 3 * i + axis] =
                    (p[axis] - self.min[axis]).min(self.max[axis] - p[axis]);
            }
        }
        for m in &mut out {
            if !m.is_finite() {
                *m = f64::NEG_INFINITY;
            }
        }
        out
    }

    /// The limit of index `k` of [`Workspace::margins`].
    pub fn limit(k: usize) -> Limit {
        if k < PAIRS.len() {
            Limit::Links(PAIRS[k].0, PAIRS[k].1)
        } else {
            let i = k - PAIRS.len();
            Limit::Box(i >= 3, i % 3)
        }
    }

    /// The smallest margin of the pose `q` (m; negative: inside a limit by that much) and the
    /// limit it is to.
    pub fn margin(&self, q: &[f64; JOINTS]) -> (f64, Limit) {
        let m = self.margins(q);
        let (k, v) =
            m.iter().enumerate().fold(
                (0, f64::INFINITY),
                |b, (k, &v)| if v < b.1 { (k, v) } else { b },
            );
        (v, Self::limit(k))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn close(a: V3, b: V3) -> bool {
        (0..3).all(|i| (a[i] - b[i]).abs() < 1e-9)
    }

    #[test]
    fn the_zero_pose_puts_the_flange_where_franka_documents_it() {
        // all joints at 0: the flange 0.088 m forward, 0.333 + 0.316 + 0.384 - 0.107 m up
        let s = skeleton(&[0.0; JOINTS], 0.0);
        assert!(close(s.flange, [0.088, 0.0, 0.926]), "{:?}", s.flange);
        assert!(close(s.shoulder, [0.0, 0.0, 0.333]), "{:?}", s.shoulder);
        assert!(close(s.elbow, [0.0825, 0.0, 0.649]), "{:?}", s.elbow);
        assert!(close(s.wrist, [0.0, 0.0, 1.033]), "{:?}", s.wrist);
        // joint 1 turns the whole arm about z
        let mut q = [0.0; JOINTS];
        q[0] = std::f64::consts::FRAC_PI_2;
        let s = skeleton(&q, 0.0);
        assert!(close(s.flange, [0.0, 0.088, 0.926]), "{:?}", s.flange);
    }

    #[test]
    fn the_start_poses_are_clear_and_a_folded_arm_is_not() {
        let w = Workspace::default();
        // franka-sim's start pose (DROID's, [0, -0.785, 0, -2.356, 0, 1.571, 0.785], is clear
        // too, but within 0.4 rad of it the base and the forearm's segments come closer than
        // these conservative distances: a known cost of the model)
        let home = [0.0, 0.0, 0.0, -1.57, 0.0, 1.57, 0.785];
        let (m, l) = w.margin(&home);
        assert!(m > 0.03, "home: {m} to {l}");
        // joint 4 folded to its limit, joint 2 back: the forearm into the base
        let folded = [0.0, -1.7, 0.0, -3.0, 0.0, 1.0, 0.0];
        let (m, l) = w.margin(&folded);
        assert!(m < 0.0, "folded: {m} to {l}");
        // reaching down to 6 cm above the base's plane: outside a box whose floor is at 0.3 m
        let down = [0.0, 1.5, 0.0, -0.3, 0.0, 1.8, 0.0];
        let (m, _) = w.margin(&down);
        assert!(m > 0.0, "down: {m}");
        let table = Workspace {
            min: [-0.9, -0.9, 0.3],
            ..w
        };
        let (m, l) = table.margin(&down);
        assert!(m < 0.0 && matches!(l, Limit::Box(_, 2)), "down: {m} to {l}");
        // where franka-sim tripped link0 / link5 at 48.9 mm (DROID all -1, before this model)
        let tripped = [-2.4228, -1.5127, -2.1551, -2.7612, -2.6163, 0.7940, -2.8165];
        let (m, l) = w.margin(&tripped);
        assert!(m < 0.0, "tripped: {m} to {l}");
        let (m, _) = w.margin(&[f64::NAN; JOINTS]);
        assert!(m < 0.0);
    }

    #[test]
    fn segment_distances() {
        let d = segment_distance([0.0; 3], [1.0, 0.0, 0.0], [0.5, 1.0, 0.0], [0.5, 2.0, 0.0]);
        assert!((d - 1.0).abs() < 1e-12);
        let d = segment_distance([0.0; 3], [1.0, 0.0, 0.0], [2.0, 0.0, 0.0], [3.0, 0.0, 0.0]);
        assert!((d - 1.0).abs() < 1e-12);
        let d = segment_distance([0.0; 3], [0.0; 3], [0.0, 0.0, 1.0], [0.0, 0.0, 1.0]);
        assert!((d - 1.0).abs() < 1e-12);
        let d = segment_distance(
            [-1.0, 0.0, 0.0],
            [1.0, 0.0, 0.0],
            [0.0, -1.0, 0.5],
            [0.0, 1.0, 0.5],
        );
        assert!((d - 0.5).abs() < 1e-12);
    }
}
