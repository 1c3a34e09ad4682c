#!/usr/bin/env python3
"""A scripted DROID policy behind openpi's own websocket server: a **test double** (no model).

openpi's `WebsocketPolicyServer` (PyPI openpi-server) answers DROID-layout requests as a
pi05_droid server would shape them: it checks the observation a DROID client sends
(`observation/exterior_image_1_left` and `observation/wrist_image_left` as HxWx3 uint8,
`observation/joint_position` (7), `observation/gripper_position` (1), `prompt`) and replies with
`actions` of shape (H, 8): 7 joint velocities in [-1, 1] and the gripper's position in [0, 1]
(DROID's `joint_velocity` / `position` action spaces).

  --mode waypoints   velocities that carry the arm between waypoints around its start pose
                     (what DROID's robot environment integrates: target = q + 0.2 v per step),
                     the gripper closing and opening every few chunks (the demo's source)
  --mode random      random velocities in [-1, 1] and a random gripper (the hostile test)
  --mode constant    every joint velocity at --value (-1 or +1: the arm driven into its own
                     joint limits, its links or the floor; the driver's geometry test), the
                     arm back to its start pose --flip-after-s seconds after the first request
                     (a policy that turns back; by the clock, not by a count of requests, which a
                     loaded machine makes fewer)

Every answer waits --latency-ms first (a GPU server's inference time). Prints one line per 50
requests and, on SIGTERM / SIGINT, "droid-scripted summary: requests=N bad=N turned_back_at=N"
(the request that turned back, 0: none).
"""
import argparse
import signal
import sys
import threading
import time

import numpy as np

JOINT_KEYS = ("observation/joint_position", "observation/gripper_position")
IMAGE_KEYS = ("observation/exterior_image_1_left", "observation/wrist_image_left")
# around the FR3's start pose of franka-sim (rad): joint offsets the waypoints visit
WAYPOINTS = np.array([
    [0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0],
    [0.35, -0.2, 0.2, 0.25, 0.3, -0.25, 0.4],
    [-0.3, 0.25, -0.25, -0.2, -0.35, 0.2, -0.4],
    [0.2, 0.3, 0.3, -0.3, 0.2, 0.3, -0.2],
])
MAX_JOINT_DELTA = 0.2


class ScriptedDroidPolicy:
    def __init__(self, mode, horizon, latency_s, seed, value=0.0, flip_after_s=0.0):
        self.mode, self.horizon, self.latency_s, self.value = mode, horizon, latency_s, value
        self.flip_after_s = flip_after_s
        self.first_request = None
        self.flipped_at = None
        self.rng = np.random.default_rng(seed)
        self.home = None
        self.requests = self.bad = 0
        self.lock = threading.Lock()

    def check(self, obs):
        for k in IMAGE_KEYS:
            img = obs.get(k)
            if not (isinstance(img, np.ndarray) and img.ndim == 3 and img.shape[2] == 3 and img.dtype == np.uint8):
                raise ValueError(f"{k}: expected an HxWx3 uint8 image, got {type(img).__name__} "
                                 f"{getattr(img, 'shape', None)} {getattr(img, 'dtype', None)}")
        q = np.asarray(obs.get("observation/joint_position"), dtype=np.float64).reshape(-1)
        g = np.asarray(obs.get("observation/gripper_position"), dtype=np.float64).reshape(-1)
        if q.shape != (7,) or g.shape != (1,) or not np.all(np.isfinite(q)) or not (0.0 <= g[0] <= 1.0):
            raise ValueError(f"joint_position {q.shape} / gripper_position {g} is not DROID's (7 joints, "
                             "gripper in [0, 1])")
        if not isinstance(obs.get("prompt"), str):
            raise ValueError("prompt: expected a string")
        return q, g[0]

    def infer(self, obs):
        t0 = time.monotonic()
        with self.lock:
            self.requests += 1
            n = self.requests
            try:
                q, g = self.check(obs)
            except ValueError:
                self.bad += 1
                raise
            if self.home is None:
                self.home = q.copy()
                self.first_request = t0
            h = self.horizon
            actions = np.zeros((h, 8), dtype=np.float32)
            flipped = (self.mode == "constant" and self.flip_after_s > 0
                       and t0 - self.first_request >= self.flip_after_s)
            if flipped and self.flipped_at is None:
                self.flipped_at = n
                print(f"droid-scripted: turned back at request {n}, "
                      f"{t0 - self.first_request:.2f} s after the first", flush=True)
            if self.mode == "constant" and not flipped:
                actions[:, :7] = self.value
                actions[:, 7] = 0.0
            elif flipped:
                # back to where the arm started, at 0.4 of the speed (a policy that turns back)
                pos = q.copy()
                for k in range(h):
                    v = np.clip((self.home - pos) / MAX_JOINT_DELTA, -0.4, 0.4)
                    actions[k, :7] = v
                    pos = pos + MAX_JOINT_DELTA * v
            elif self.mode == "random":
                actions[:, :7] = self.rng.uniform(-1.0, 1.0, size=(h, 7))
                actions[:, 7] = self.rng.uniform(0.0, 1.0)
            else:
                target = self.home + WAYPOINTS[(n // 6) % len(WAYPOINTS)]
                pos = q.copy()
                for k in range(h):
                    v = np.clip((target - pos) / MAX_JOINT_DELTA, -0.4, 0.4)
                    actions[k, :7] = v
                    pos = pos + MAX_JOINT_DELTA * v
                actions[:, 7] = 1.0 if (n // 10) % 2 else 0.0
            if n % 50 == 0:
                print(f"droid-scripted: {n} requests ({self.bad} bad), gripper in {g:.2f}", flush=True)
        left = self.latency_s - (time.monotonic() - t0)
        if left > 0:
            time.sleep(left)
        return {"actions": actions, "policy_timing": {"infer_ms": (time.monotonic() - t0) * 1e3}}


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--port", type=int, required=True)
    ap.add_argument("--mode", choices=["waypoints", "random", "constant"], default="waypoints")
    ap.add_argument("--horizon", type=int, default=15, help="actions per chunk (pi05_droid: 15)")
    ap.add_argument("--latency-ms", type=float, default=60.0)
    ap.add_argument("--seed", type=int, default=7)
    ap.add_argument("--value", type=float, default=-1.0,
                    help="--mode constant: every joint velocity (DROID's normalised, in [-1, 1])")
    ap.add_argument("--flip-after-s", type=float, default=0.0,
                    help="--mode constant: this many seconds after the first request, back to the "
                         "start pose (0: never)")
    args = ap.parse_args()
    from openpi_server import WebsocketPolicyServer

    policy = ScriptedDroidPolicy(args.mode, args.horizon, args.latency_ms / 1e3, args.seed, args.value,
                                 args.flip_after_s)

    def stop(*_):
        print(f"droid-scripted summary: requests={policy.requests} bad={policy.bad} "
              f"turned_back_at={policy.flipped_at or 0}", flush=True)
        sys.exit(0)

    signal.signal(signal.SIGTERM, stop)
    signal.signal(signal.SIGINT, stop)
    server = WebsocketPolicyServer(policy, host="127.0.0.1", port=args.port,
                                   metadata={"scripted_droid": args.mode})
    print(f"droid-scripted ({args.mode}, test double) on ws://127.0.0.1:{args.port}", flush=True)
    server.serve_forever()


if __name__ == "__main__":
    main()
