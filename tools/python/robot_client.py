#!/usr/bin/env python3
"""A robot-side chunkrt client in Python: a simulated arm on real iceoryx2 services.

Publishes ``JointState`` on ``NS/joint_state`` at ``--rate-hz`` and follows the ``JointCommand``s
that arrive on ``NS/joint_command`` (e.g. from ``chunkrt run``), using the PyPI ``iceoryx2``
package (0.10.0) and the ctypes mirror ``ipc/python/chunkrt_ipc.py``.

The arm moves every joint towards the newest valid, in-deadline command at a limited speed.
A command received after its deadline is a deadline miss and is not applied; with no live command
the arm holds and says so in ``status_flags``.

The summary also reports what a robot can check of the controller's side of the contract:
commands whose ``seq`` did not increase (``out_of_order``), commands with no deadline or one more
than a second after their publish time (``bad_deadlines``; a deadline already past at publish is
a late command, discarded like any other), and the controller's
publish rate from the first and last command's ``seq`` and ``publish_time_ns``
(``publish_rate_hz``, independent of how promptly this process drained its queue).

On exit it prints one summary line (``key=value`` tokens) and exits with 1 if it received no
command at all, 2 if iceoryx2 is missing, 0 otherwise.

    pip install iceoryx2==0.10.0
    python3 tools/python/robot_client.py --namespace chunkrt/demo --duration 2 --n-dof 4
"""

import argparse
import os
import signal
import sys
import time

HERE = os.path.dirname(os.path.abspath(__file__))
sys.path.insert(0, os.path.join(HERE, "..", "..", "ipc", "python"))

import chunkrt_ipc as c  # noqa: E402

try:
    import iceoryx2 as iox2
except ImportError as e:  # pragma: no cover - depends on the environment
    print(
        "robot_client: cannot import iceoryx2 (%s); install it: pip install iceoryx2==0.10.0" % e,
        file=sys.stderr,
    )
    sys.exit(2)


def parse_args(argv):
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--namespace", default="chunkrt/demo", help="service namespace")
    p.add_argument("--duration", type=float, default=2.0, help="seconds to run")
    p.add_argument("--n-dof", type=int, default=4, help="number of joints (1..16)")
    p.add_argument("--rate-hz", type=float, default=500.0, help="joint state rate")
    p.add_argument(
        "--max-velocity", type=float, default=2.0, help="joint speed limit (per second)"
    )
    p.add_argument(
        "--command-timeout-ms",
        type=float,
        default=50.0,
        help="hold when no command arrived for this long",
    )
    p.add_argument(
        "--initial", type=float, nargs="*", default=None, help="initial positions"
    )
    a = p.parse_args(argv)
    if not 1 <= a.n_dof <= c.MAX_DOF:
        p.error("--n-dof %d: must be in 1..=%d" % (a.n_dof, c.MAX_DOF))
    if not (0 < a.duration <= 1e6):
        p.error("--duration must be in (0, 1e6] seconds")
    if not (1 <= a.rate_hz <= 5000):
        p.error("--rate-hz must be in 1..=5000")
    if a.initial is not None and len(a.initial) != a.n_dof:
        p.error("--initial needs %d values" % a.n_dof)
    return a


def main(argv):
    args = parse_args(argv)
    n = args.n_dof
    stop = []
    signal.signal(signal.SIGINT, lambda *_: stop.append(1))
    signal.signal(signal.SIGTERM, lambda *_: stop.append(1))

    node = c.node("chunkrt-py-robot")
    node.try_cleanup_dead_nodes()
    state_pub = c.publisher(
        c.typed_service(node, c.joint_state_name(args.namespace), c.JointState)
    )
    cmd_sub = c.subscriber(
        c.typed_service(node, c.joint_command_name(args.namespace), c.JointCommand)
    )

    position = list(args.initial) if args.initial is not None else [0.0] * n
    velocity = [0.0] * n
    period_ns = int(1e9 / args.rate_hz)
    dt = period_ns * 1e-9
    timeout_ns = int(args.command_timeout_ms * 1e6)

    received = valid = misses = rejected = published = 0
    out_of_order = bad_deadlines = 0
    first_cmd = None
    last_cmd = None
    live = None
    last_cmd_time = c.monotonic_ns()
    seq = 0
    start = c.monotonic_ns()
    end = start + int(args.duration * 1e9)
    next_tick = start

    while not stop:
        now = c.monotonic_ns()
        if now >= end:
            break
        # Drain every command that arrived since the last tick.
        while True:
            sample = cmd_sub.receive()
            if sample is None:
                break
            cmd = c.JointCommand.from_buffer_copy(sample.payload().contents)
            sample.delete()
            received += 1
            t = c.monotonic_ns()
            problem = c.validate_joint_command(cmd, n)
            if problem is not None:
                rejected += 1
                continue
            if first_cmd is None:
                first_cmd = cmd
            if last_cmd is not None and cmd.seq <= last_cmd.seq:
                out_of_order += 1
            if cmd.deadline_ns == 0 or cmd.deadline_ns > cmd.publish_time_ns + 10**9:
                bad_deadlines += 1
            last_cmd = cmd
            if cmd.deadline_ns < t:
                misses += 1
                continue
            valid += 1
            live = cmd
            last_cmd_time = t

        now = c.monotonic_ns()
        flags = 0
        if live is not None and (live.deadline_ns < now or now - last_cmd_time > timeout_ns):
            live = None
        if live is None:
            flags |= c.JOINT_STATUS_HOLDING
            if now - last_cmd_time > timeout_ns:
                flags |= c.JOINT_STATUS_COMMAND_TIMEOUT
            target = position
        else:
            target = list(live.position[:n])
        step = args.max_velocity * dt
        for i in range(n):
            d = max(-step, min(step, target[i] - position[i]))
            velocity[i] = d / dt
            position[i] += d

        seq += 1
        msg = c.JointState(seq=seq, measurement_time_ns=now, n_dof=n, status_flags=flags)
        for i in range(n):
            msg.position[i] = position[i]
            msg.velocity[i] = velocity[i]
        state_pub.send_copy(msg)
        published += 1

        next_tick += period_ns
        delay = next_tick - c.monotonic_ns()
        if delay > 0:
            time.sleep(delay * 1e-9)
        elif -delay > 10 * period_ns:
            next_tick = c.monotonic_ns()  # far behind: restart the schedule

    last = "none"
    if last_cmd is not None:
        last = "seq:%d,chunk:%d,mode:%d,pos:%s" % (
            last_cmd.seq,
            last_cmd.chunk_id,
            last_cmd.mode,
            "/".join(repr(x) for x in last_cmd.position[:n]),
        )
    rate = 0.0
    if first_cmd is not None and last_cmd.publish_time_ns > first_cmd.publish_time_ns:
        rate = (last_cmd.seq - first_cmd.seq) * 1e9 / (
            last_cmd.publish_time_ns - first_cmd.publish_time_ns
        )
    print(
        "robot_client summary: states_published=%d commands_received=%d commands_valid=%d "
        "deadline_misses=%d commands_rejected=%d out_of_order=%d bad_deadlines=%d "
        "publish_rate_hz=%.1f last_command=%s"
        % (
            published,
            received,
            valid,
            misses,
            rejected,
            out_of_order,
            bad_deadlines,
            rate,
            last,
        ),
        flush=True,
    )
    if received == 0:
        print("robot_client: received no command", file=sys.stderr)
        return 1
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
