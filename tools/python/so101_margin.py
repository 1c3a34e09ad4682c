#!/usr/bin/env python3
"""How much room the SO-101 expert's grasp leaves (a diagnostic; docs/status.md, issue 54 §5):
on the way down the fixed jaw's pad (geom ``fixed_jaw_pad``) passes the block's top edge by
less than a millimetre, and often touches it; where it lands on the edge the arm rests on the
block with the grasp point ~26 mm above the block's centre, the closed-loop expert waits until it
slides off, and an open-loop replay of its plan closes the jaw there on schedule.

    contact  the expert's own runs on --seeds A..B: per seed the deepest pad / block penetration
             before the jaw closes and how long the grasp point stood 24-29 mm above the block's
             centre (the pad on the block's top; passing takes ~50 ms)
    perturb  the block moved --dy mm along y (--axis) after the reset: the closed-loop expert,
             and its plan of the unmoved block (its exact joint targets, open loop, no chunkrt)
             replayed on the moved block; the grasp point's height when the jaw closes
    trace    the same figures for chunkrt's episodes logged by CHUNKRT_SO101_TRACE=DIR
             (`chunkrt eval --task so101 ...`; files so101_trace_<seed>_<strategy>_d<delay>.csv)

    python3 tools/python/so101_margin.py perturb --seeds 8200..8250 --dy -0.25
"""

import argparse
import glob
import os
import re
import sys

os.environ.setdefault("MUJOCO_GL", "egl")

import mujoco  # noqa: E402
import numpy as np  # noqa: E402
from lerobot_env_so101.pick_place_env import SO101PickPlaceGymEnv  # noqa: E402
from lerobot_env_so101.policy import DEFAULT_ACTION_SCALE  # noqa: E402
from lerobot_env_so101.scripted.pick_place import Phase, PickPlaceController  # noqa: E402

JOINTS = ("shoulder_pan", "shoulder_lift", "elbow_flex", "wrist_flex", "wrist_roll", "gripper")
CARRY_RISE = 0.03  # the package's _MIN_CARRY_RISE
JAW_OPEN, JAW_MID = 1.2, 0.785  # rad: the jaw seen open, then closed past the middle of its range


class Scene:
    def __init__(self):
        self.env = SO101PickPlaceGymEnv(
            seed=0, random_block_position=True, action_scale=DEFAULT_ACTION_SCALE
        )
        m = self.m = self.env.model
        self.d = self.env.data
        self.act = [m.actuator(j).id for j in JOINTS]
        self.qadr = [m.joint(j).qposadr[0] for j in JOINTS]
        self.pad = m.geom("fixed_jaw_pad").id
        self.block = m.geom("block").id
        self.block_qadr = m.jnt_qposadr[m.body("block").jntadr[0]]
        self.block_pos = self.d.sensor("block_pos").data

    def reset(self, seed, shift=None):
        self.env.reset(seed=seed)
        if shift is not None:
            self.d.qpos[self.block_qadr:self.block_qadr + 3] += shift
            mujoco.mj_forward(self.m, self.d)
        self.z0 = float(self.block_pos[2])
        self.watch = Watch()

    def pad_distance(self):
        """Signed distance (mm) of the fixed jaw's pad to the block (< 0: in contact)."""
        ft = np.zeros(6)
        return 1e3 * mujoco.mj_geomDistance(self.m, self.d, self.pad, self.block, 0.05, ft)

    def height(self):
        """The grasp point's height above the block's centre (mm)."""
        return 1e3 * (self.env.ik_point_pos[2] - self.d.geom_xpos[self.block][2])

    def success(self):
        env = self.env
        env._was_carried = env._was_carried or float(self.block_pos[2]) - env._z_init > CARRY_RISE
        return bool(env._is_success())


class Watch:
    """Per physics step until the jaw closes: the deepest pad contact, the time spent 24-29 mm
    above the block, and the height at which the jaw closed."""

    def __init__(self):
        self.deepest, self.stood, self.close_height, self.opened = np.inf, 0, None, False

    def see(self, scene, jaw):
        if self.close_height is not None:
            return
        self.opened |= jaw > JAW_OPEN
        if self.opened and jaw < JAW_MID:
            self.close_height = scene.height()
            return
        if self.opened:
            self.deepest = min(self.deepest, scene.pad_distance())
            self.stood += 24.0 <= scene.height() <= 29.0

    def line(self, dt):
        h = "never" if self.close_height is None else f"{self.close_height:.1f} mm"
        return (f"pad / block {self.deepest:+.2f} mm at the deepest, stood on the block's top "
                f"{self.stood * dt * 1e3:.0f} ms, jaw closed with the grasp point {h} above "
                "the block's centre")


def expert_run(scene, seed, shift=None, max_steps=120):
    """The closed-loop expert: (success, its joint targets per 0.1-s step)."""
    scene.reset(seed, shift)
    ex = PickPlaceController(DEFAULT_ACTION_SCALE)
    ex.reset()
    rows, ok = [], False
    step = mujoco.mj_step

    def watched(m, d, *a):
        step(m, d, *a)
        scene.watch.see(scene, d.qpos[scene.qadr[-1]])

    mujoco.mj_step = watched
    try:
        for _ in range(max_steps):
            a = ex.act(scene.env.ik_point_pos, scene.block_pos.copy(), scene.env.goal_pos)
            _, _, terminated, _, info = scene.env.step(a)
            rows.append(scene.d.ctrl[scene.act].copy())
            ok = bool(info["succeed"])
            if terminated or ex.phase is Phase.DONE:
                break
    finally:
        mujoco.mj_step = step
    return ok, rows


def plan_run(scene, seed, rows, shift=None, tail=30):
    """The expert's joint targets `rows` replayed open loop (each for its 0.1-s step)."""
    scene.reset(seed, shift)
    for r in list(rows) + [rows[-1]] * tail:
        scene.d.ctrl[scene.act] = r
        for _ in range(scene.env._n_substeps):
            mujoco.mj_step(scene.m, scene.d)
            scene.watch.see(scene, scene.d.qpos[scene.qadr[-1]])
        if scene.success():
            return True
    return False


def seeds_of(text):
    a, _, b = text.partition("..")
    return range(int(a), int(b))


def contact(args):
    scene = Scene()
    dt = scene.m.opt.timestep
    for seed in seeds_of(args.seeds):
        ok, _ = expert_run(scene, seed)
        print(f"seed {seed}: expert {'success' if ok else 'failure'}; {scene.watch.line(dt)}",
              flush=True)
    return 0


def perturb(args):
    scene = Scene()
    dt = scene.m.opt.timestep
    shift = np.zeros(3)
    shift[args.axis] = args.dy * 1e-3
    n = e_ok = p_ok = 0
    heights = []
    for seed in seeds_of(args.seeds):
        _, rows = expert_run(scene, seed)
        e = expert_run(scene, seed, shift)[0]
        p = plan_run(scene, seed, rows, shift)
        n, e_ok, p_ok = n + 1, e_ok + e, p_ok + p
        heights.append(scene.watch.close_height or np.nan)
        if args.verbose or not (e and p):
            print(f"seed {seed}: expert {'success' if e else 'failure'}, its plan open loop "
                  f"{'success' if p else 'failure'}; the plan: {scene.watch.line(dt)}", flush=True)
    print(f"block moved {args.dy:+.2f} mm along axis {args.axis}: the expert {e_ok} / {n}, its "
          f"plan of the unmoved block open loop {p_ok} / {n} (jaw closed at a median "
          f"{np.nanmedian(heights):.1f} mm above the block's centre)")
    return 0


def trace(args):
    scene = Scene()
    files = sorted(glob.glob(os.path.join(args.dir, "so101_trace_*.csv")))
    for path in files:
        seed = int(re.search(r"so101_trace_(\d+)_", os.path.basename(path)).group(1))
        scene.reset(seed)
        t = np.genfromtxt(path, delimiter=",", names=True)
        q = np.stack([t[f"q{j}"] for j in range(6)], 1)
        block = np.stack([t[f"block{j}"] for j in range(3)], 1)
        w = Watch()
        for i in range(len(t)):
            # the logged pose (the block's orientation as at the reset)
            scene.d.qpos[scene.qadr] = q[i]
            scene.d.qpos[scene.block_qadr:scene.block_qadr + 3] = block[i]
            mujoco.mj_kinematics(scene.m, scene.d)
            w.see(scene, q[i, -1])
        dt = float(t["t"][1] - t["t"][0])
        print(f"{os.path.basename(path)}: {w.line(dt)}", flush=True)
    return 0 if files else 1


def main(argv):
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    sub = ap.add_subparsers(dest="cmd", required=True)
    c = sub.add_parser("contact")
    c.add_argument("--seeds", default="8200..8250")
    p = sub.add_parser("perturb")
    p.add_argument("--seeds", default="8200..8250")
    p.add_argument("--dy", type=float, default=-0.25, help="mm")
    p.add_argument("--axis", type=int, default=1, help="0: x, 1: y, 2: z")
    p.add_argument("--verbose", action="store_true", help="every seed, not only the misses")
    t = sub.add_parser("trace")
    t.add_argument("dir", help="CHUNKRT_SO101_TRACE's folder")
    args = ap.parse_args(argv)
    return {"contact": contact, "perturb": perturb, "trace": trace}[args.cmd](args)


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
