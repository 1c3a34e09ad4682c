#!/usr/bin/env python3
"""Measures the touch distances of `franka/src/geometry.rs` against the FR3 model franka-sim runs.

The driver models the FR3's links as segments between points of its forward kinematics
(Franka's DH table) and calls two links near when their segments come closer than a distance
per pair. This script samples random poses within the FR3's joint ranges, computes each pair's
segment distance (the same construction as geometry.rs) and the surface distance of the links'
collision meshes in the MJCF model (MuJoCo's `mj_geomDistance`, the links three or more apart
along the chain, as the robot's self-collision model monitors them), and prints, per pair, the
largest (segment distance - surface distance) among poses whose links lie within 0.2 m, then
climbs from the worst of them (poses within --within, 0.1 m: near the clearance, where it matters) (random joint steps kept while the gap grows): the distance at
which the links can touch. geometry.rs uses the sampled figures of 2026-11-27 (6 000 samples,
poses within 0.2 m) plus 1 cm; the climbed ones are 1-4 cm higher (benches/data/franka/
2026-11-28-geometry/README.md says what that means). The flange's segment (link 7 on its own)
is measured here but not in geometry.rs yet.

Run it in the Franka venv (scripts/franka-env.sh):
  ~/.cache/chunkrt-franka/venv/bin/python tools/python/fr3_geometry.py --samples 6000
"""
import argparse
import os

import mujoco
import numpy as np

DH = [(0.0, 0.333, 0.0), (0.0, 0.0, -np.pi / 2), (0.0, 0.316, np.pi / 2), (0.0825, 0.0, np.pi / 2),
      (-0.0825, 0.384, -np.pi / 2), (0.0, 0.0, np.pi / 2), (0.088, 0.0, np.pi / 2)]
FLANGE_D, FOREARM_START, FOREARM_SHORT = 0.107, 0.12, 0.08
Q_MIN = np.array([-2.7437, -1.7837, -2.9007, -3.0421, -2.8065, 0.5445, -3.0159])
Q_MAX = np.array([2.7437, 1.7837, 2.9007, -0.1518, 2.8065, 4.5169, 3.0159])
NAMES = ["base", "upper arm", "elbow", "forearm", "wrist", "hand", "flange"]
# which of the model's links each segment stands for (link 7 is the flange's: joint 7 to the
# flange; the hand past it is not a link of the model and franka-sim does not monitor it)
LINKS = {0: [0, 1], 1: [2, 3], 2: [3, 4], 3: [5], 4: [6], 5: [7], 6: [7]}
PAIRS = [(0, 2), (0, 3), (0, 4), (0, 5), (1, 4), (1, 5), (2, 5), (0, 6), (1, 6), (2, 6)]


def dh_step(a, d, alpha, theta):
    sa, ca, st, ct = np.sin(alpha), np.cos(alpha), np.sin(theta), np.cos(theta)
    t = np.eye(4)
    t[:3, :3] = [[ct, -st, 0.0], [st * ca, ct * ca, -sa], [st * sa, ct * sa, ca]]
    t[:3, 3] = [a, -sa * d, ca * d]
    return t


def segments(q, hand_length=0.1034):
    t, frames = np.eye(4), []
    for j in range(7):
        t = t @ dh_step(*DH[j], q[j])
        frames.append(t.copy())
    point = lambda f, x: (f @ np.array([*x, 1.0]))[:3]
    shoulder, elbow, wrist, j7 = frames[1][:3, 3], frames[3][:3, 3], frames[4][:3, 3], frames[6][:3, 3]
    kink = point(frames[4], [0.0, 0.0, -DH[4][1]])
    along = wrist - kink
    length = np.linalg.norm(along)
    return [(np.zeros(3), shoulder), (shoulder, elbow), (elbow, kink),
            (kink + along * FOREARM_START / length, kink + along * (1 - FOREARM_SHORT / length)),
            (wrist, j7), (point(frames[6], [0, 0, FLANGE_D]), point(frames[6], [0, 0, FLANGE_D + hand_length])),
            (j7, point(frames[6], [0, 0, FLANGE_D]))]


def segment_distance(p0, p1, q0, q1, steps=61):
    s = np.linspace(0.0, 1.0, steps)[:, None]
    a, b = p0 + (p1 - p0) * s, q0 + (q1 - q0) * s
    return float(np.min(np.linalg.norm(a[:, None, :] - b[None, :, :], axis=2)))


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--model", default=os.environ.get(
        "FR3_MJCF", os.path.expanduser("~/.cache/chunkrt-franka/fr3_model/fr3.xml")))
    ap.add_argument("--samples", type=int, default=6000)
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument("--refine-from", type=int, default=20,
                    help="climb from this many of each pair's worst sampled poses")
    ap.add_argument("--refine-steps", type=int, default=300)
    ap.add_argument("--within", type=float, default=0.1,
                    help="poses whose links lie within this (m) count: the touch distance matters "
                         "where the links come near the clearance (0.05), not 0.2 m apart")
    args = ap.parse_args()
    m = mujoco.MjModel.from_xml_path(args.model)
    d = mujoco.MjData(m)
    bodies = [mujoco.mj_id2name(m, mujoco.mjtObj.mjOBJ_BODY, i) for i in range(m.nbody)]
    geoms = {}
    for g in range(m.ngeom):
        name = bodies[m.geom_bodyid[g]] or ""
        if (m.geom_contype[g] or m.geom_conaffinity[g]) and name.startswith("fr3_link"):
            geoms.setdefault(int(name[-1]), []).append(g)

    def surface(a, b):
        return min(mujoco.mj_geomDistance(m, d, ga, gb, 0.6, np.zeros(6))
                   for ga in geoms[a] for gb in geoms[b])

    # the DH chain against the model's own: joint 7's origin at the zero pose
    d.qpos[:7] = 0.0
    mujoco.mj_forward(m, d)
    j7 = segments(np.zeros(7))[4][1]
    print(f"joint 7 at the zero pose: DH {np.round(j7, 4)}, model {np.round(d.xpos[bodies.index('fr3_link7')], 4)}")
    rng = np.random.default_rng(args.seed)

    def touch(q, a, b):
        """(segment distance - surface distance, surface distance) of pair (a, b) at q."""
        d.qpos[:7] = q
        mujoco.mj_forward(m, d)
        segs = segments(q)
        links = [(x, y) for x in LINKS[a] for y in LINKS[b] if abs(x - y) >= 3]
        t = min(surface(x, y) for x, y in links)
        return segment_distance(*segs[a], *segs[b]) - t, t

    gap = {p: [] for p in PAIRS}
    for _ in range(args.samples):
        q = Q_MIN + (Q_MAX - Q_MIN) * rng.random(7)
        for a, b in PAIRS:
            g, t = touch(q, a, b)
            if t < args.within:
                gap[(a, b)].append((g, q))
    for (a, b), v in gap.items():
        if not v:
            continue
        g = np.array([x for x, _ in v])
        # a sample's largest is not the model's: climb from the worst poses sampled (random
        # steps in the joints, kept while the links stay within --within and the gap grows)
        best = max(g)
        for _, q in sorted(v, key=lambda x: -x[0])[:args.refine_from]:
            cur, _ = touch(q, a, b)
            for step in range(args.refine_steps):
                cand = np.clip(q + rng.normal(0.0, 0.08 if step < args.refine_steps // 2 else 0.02, 7),
                               Q_MIN, Q_MAX)
                c, t = touch(cand, a, b)
                if t < args.within and c > cur:
                    q, cur = cand, c
            best = max(best, cur)
        print(f"{NAMES[a]:>9} / {NAMES[b]:<9} poses within {args.within} m: {len(g):5d}  "
              f"touch distance (max): {max(g):.3f} m  p99: {np.quantile(g, 0.99):.3f} m  "
              f"climbed: {best:.3f} m", flush=True)


if __name__ == "__main__":
    main()
