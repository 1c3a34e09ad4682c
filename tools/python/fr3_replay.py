#!/usr/bin/env python3
"""Replays a command stream recorded by `chunkrt franka --record FILE` through the official
libfranka (PyPI pylibfranka 0.21.3), as a cross-check that no one here wrote: the same joint
positions, one per robot cycle, sent by Franka's own client to a robot (franka-sim with its
checks enforced).

  $CHUNKRT_FRANKA_PYTHON tools/python/fr3_replay.py --host 127.0.0.x --stream FILE

The stream must start where the robot is (a fresh franka-sim starts where the recording's did).
It holds a line per cycle of the recorded robot, the cycles that robot continued on its own
without an answer included (the driver writes its continuation), so a line a cycle keeps time.
When the robot reports more than one cycle since the last (this client stalled and the robot went
on without an answer, at constant acceleration) the replay skips as many lines, so the positions
stay on the robot's time, and from then on holds each line within the robot's acceleration and
jerk from the reference the robot reports (q_d, dq_d, ddq_d: libfranka's limitRate rule, 0.9 of
the limits, which leaves room for the f32 report): a stall of this Python client is not the stream's fault, and the robot's extrapolation parts from
the recorded line by micro-radians. Prints
"fr3-replay summary: cycles=N sent=N skipped=N reflexes=R since_skip=K success_rate_mean=X error=..."
(since_skip: commands sent since this client's last stall, -1 if it never stalled) and
exits 1 on a reflex or an error.
"""
import argparse
import os
import statistics
import sys

import pylibfranka as pf


ACCELERATION, JERK, DT = 0.9 * 10.0, 0.9 * 5000.0, 1e-3


def within(state, line):
    """The line held within ACCELERATION and JERK from the robot's reported reference (per joint:
    the positions whose second and third differences from q_d, dq_d, ddq_d keep within them);
    and whether that changed it."""
    out, changed = list(line), False
    for j in range(7):
        q, v, a = state.q_d[j], state.dq_d[j], state.ddq_d[j]
        glide = q + v * DT
        p = glide + a * DT * DT
        lo = max(p - JERK * DT ** 3, glide - ACCELERATION * DT * DT)
        hi = min(p + JERK * DT ** 3, glide + ACCELERATION * DT * DT)
        x = min(max(line[j], lo), hi) if lo <= hi else p
        if x != line[j]:
            out[j], changed = x, True
    return out, changed


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--host", required=True)
    ap.add_argument("--stream", required=True)
    ap.add_argument("--realtime", type=int, default=0, metavar="PRIO",
                    help="SCHED_FIFO priority PRIO for this client (1..99; 0: no), as libfranka's "
                         "kEnforce asks of a real robot PC; refused, said on stdout")
    args = ap.parse_args()
    if args.realtime:
        try:
            os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(args.realtime))
            print(f"fr3-replay: SCHED_FIFO priority {args.realtime}", flush=True)
        except (OSError, AttributeError, ValueError) as e:
            print(f"fr3-replay: NOT real-time ({e}): a loaded machine can stall this client",
                  flush=True)
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
    i = sent = skipped = limited = 0
    last_skip = -1  # the command count at this client's last stall (-1: none)
    catching_up = False
    rates, error, reflexes = [], "none", 0
    try:
        while i < len(rows):
            state, dur = ctrl.readOnce()
            steps = max(1, round(dur.to_sec() * 1e3)) if sent else 1
            if steps > 1:
                skipped += steps - 1
                i += steps - 1
                last_skip = sent
            i = min(i, len(rows) - 1)
            if sent > 100:
                rates.append(state.control_command_success_rate)
            line = rows[i]
            if steps > 1:
                catching_up = True
            if catching_up:
                line, changed = within(state, line)
                limited += changed
            cmd = pf.JointPositions(line)
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
    since_skip = sent - last_skip if last_skip >= 0 else -1
    print(f"fr3-replay summary: cycles={len(rows)} sent={sent} skipped={skipped} limited={limited} "
          f"reflexes={reflexes} since_skip={since_skip} "
          f"success_rate_mean={mean:.5f} error={error}", flush=True)
    sys.exit(1 if reflexes else 0)


if __name__ == "__main__":
    main()
