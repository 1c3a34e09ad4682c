#!/usr/bin/env python3
"""Replays a physics trace of the SO-101 robot process in simulated time and shows its grasp beside
the package's expert's own.

``so101_robot.py --trace FILE.npz`` writes the servo targets every physics step saw; replaying them
in a fresh episode of the same seed reproduces the run (the script checks that the joints match the
traced ones), so what the run did can be looked at step by step, without the real-time process.
For the first close of the jaw it prints where the grasp point was against the block's centre (mm)
and how far the block was tilted (a pad that landed on it tilts it), for the run and for the
expert's plan of the same seed stepped as the package steps it (each target held for its 0.1 s).

    python3 tools/python/so101_trace.py /tmp/so101_trace_3.npz
"""

import argparse
import os
import sys

HERE = os.path.dirname(os.path.abspath(__file__))
sys.path.insert(0, HERE)

import mujoco  # noqa: E402
import numpy as np  # noqa: E402
from lerobot_env_so101.pick_place_env import SO101PickPlaceGymEnv  # noqa: E402
from lerobot_env_so101.policy import DEFAULT_ACTION_SCALE  # noqa: E402

from so101_plan import JOINTS, record_plan  # noqa: E402

CARRY_RISE = 0.03  # the package's _MIN_CARRY_RISE


def replay(seed, ctrls):
    """Steps a fresh episode `seed` with the targets `ctrls` (one row per 2-ms step)."""
    env = SO101PickPlaceGymEnv(
        seed=seed, random_block_position=True, action_scale=DEFAULT_ACTION_SCALE
    )
    env.reset(seed=seed)
    m, d = env.model, env.data
    act = [m.actuator(j).id for j in JOINTS]
    qadr = [m.joint(j).qposadr[0] for j in JOINTS]
    block = d.sensor("block_pos").data
    block_body = m.body("block").id
    z0 = float(block[2])
    log = dict(q=[], grasp=[], block=[], tilt=[])
    carried, success = False, None
    for i, c in enumerate(ctrls):
        d.ctrl[act] = c
        log["q"].append(d.qpos[qadr].copy())
        log["grasp"].append(env.ik_point_pos.copy())
        log["block"].append(block.copy())
        w = min(1.0, abs(float(d.xquat[block_body][0])))
        log["tilt"].append(np.degrees(2.0 * np.arccos(w)))
        mujoco.mj_step(m, d)
        carried = carried or float(block[2]) - z0 > CARRY_RISE
        env._was_carried = carried
        if success is None and env._is_success():
            success = (i + 1) * m.opt.timestep
    return {k: np.asarray(v) for k, v in log.items()}, carried, success, m.opt.timestep


def grasp(log, ctrls, dt):
    """The first close of the jaw: where the grasp point was, and the block's tilt."""
    jaw = np.asarray(ctrls)[:, -1]
    opened = int(np.argmax(jaw > 1.7))
    if jaw[opened] <= 1.7:
        return "the jaw never opened"
    close = opened + int(np.argmax(jaw[opened:] < 1.7))
    if jaw[close] >= 1.7:
        return "the jaw never closed"
    off = (log["grasp"][close] - log["block"][close]) * 1e3
    return (f"the jaw starts closing at {close * dt:.2f} s, the grasp point "
            f"({off[0]:+.1f}, {off[1]:+.1f}, {off[2]:+.1f}) mm from the block's centre, the "
            f"block tilted {log['tilt'][close]:.1f} deg")


def main(argv):
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("trace", help="a so101_robot.py --trace file (.npz)")
    args = ap.parse_args(argv)
    tr = np.load(args.trace)
    seed = int(tr["seed"])
    ctrls = tr["ctrl"]
    log, carried, success, dt = replay(seed, ctrls)
    dev = float(np.abs(log["q"] - tr["qpos"]).max()) if len(ctrls) else 0.0
    print(f"trace of seed {seed}: {len(ctrls)} physics steps ({int(tr['steps_dropped'])} dropped "
          f"in the run), replayed: joints within {dev:.1e} rad of the traced ones, block carried "
          f"{carried}, success {'at %.2f s' % success if success else 'no'}")
    print("  the run:   ", grasp(log, ctrls, dt))
    plan = record_plan(seed, 150)
    rows = np.asarray(plan["rows"])
    per_row = int(round(plan["dt"] / dt))
    steps = len(rows) * per_row
    expert = rows[np.minimum(np.arange(steps) // per_row + 1, len(rows) - 1)]
    elog, carried, success, _ = replay(seed, expert)
    print(f"  the expert ({'placed' if success else 'did not place'} in simulated time):",
          grasp(elog, expert, dt))
    return 0 if dev < 1e-9 else 1


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
