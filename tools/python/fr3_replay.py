#!/usr/bin/env python3
"""Replays a command stream recorded by `chunkrt franka --record FILE` through the official
libfranka (PyPI pylibfranka 0.21.3), as a cross-check that no one here wrote: the same joint
positions, one per robot cycle, sent by Franka's own client to a robot (franka-sim with its
checks enforced).

  $CHUNKRT_FRANKA_PYTHON tools/python/fr3_replay.py --host 127.0.0.x --stream FILE

The stream must start where the robot is (a fresh franka-sim starts where the recording's did).
It holds a line per cycle of the recorded robot, the cycles that robot continued on its own
without an answer included (the driver writes its continuation), so a line a cycle keeps time.
When the robot reports more than one cycle since the last (it went on without an answer) the
replay skips as many lines, so the positions stay on the robot's time. Prints
"fr3-replay summary: cycles=N sent=N skipped=N reflexes=R success_rate_mean=X error=..." and
exits 1 on a reflex or an error.
"""
import argparse
import statistics
import sys

import pylibfranka as pf


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--host", required=True)
    ap.add_argument("--stream", required=True)
    args = ap.parse_args()
    rows = []
    with open(args.stream) as f:
        for line in f:
            v = [float(x) for x in line.split()]
            if len(v) != 7:
                sys.exit(f"fr3_replay.py: {args.stream}: a line of {len(v)} values, not 7")
            rows.append(v)
    if not rows:
        sys.exit(f"fr3_replay.py: {args.stream} is empty")

    robot = pf.Robot(args.host, pf.RealtimeConfig.kIgnore)
    start = list(robot.read_once().q)
    gap = max(abs(a - b) for a, b in zip(start, rows[0]))
    if gap > 1e-3:
        sys.exit(f"fr3_replay.py: the robot is {gap:.4f} rad from the stream's start: restart the simulator")
    ctrl = robot.start_joint_position_control(pf.ControllerMode.JointImpedance)
    i = sent = skipped = 0
    rates, error, reflexes = [], "none", 0
    try:
        while i < len(rows):
            state, dur = ctrl.readOnce()
            steps = max(1, round(dur.to_sec() * 1e3)) if sent else 1
            if steps > 1:
                skipped += steps - 1
                i += steps - 1
            i = min(i, len(rows) - 1)
            if sent > 100:
                rates.append(state.control_command_success_rate)
            cmd = pf.JointPositions(rows[i])
            if i == len(rows) - 1:
                cmd.motion_finished = True
            ctrl.writeOnce(cmd)
            sent += 1
            if cmd.motion_finished:
                break
            i += 1
    except (pf.ControlException, pf.CommandException) as e:
        reflexes, error = 1, str(e).replace("\n", " ")[:300]
    mean = statistics.mean(rates) if rates else 0.0
    print(f"fr3-replay summary: cycles={len(rows)} sent={sent} skipped={skipped} reflexes={reflexes} "
          f"success_rate_mean={mean:.5f} error={error}", flush=True)
    sys.exit(1 if reflexes else 0)


if __name__ == "__main__":
    main()
