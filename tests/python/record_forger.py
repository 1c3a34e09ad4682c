#!/usr/bin/env python3
"""A forger on a namespace's chunk service (NS/chunks), from a process of its own: a chunk whose
times are at 2^63 and past, then a flood of tiny chunks whose ids go down, at most RATE a second.
What a recorder must not record (tests/record_rerun.rs).

    python record_forger.py NAMESPACE SECONDS [RATE]
"""

import os
import sys
import time

sys.path.insert(0, os.path.join(os.path.dirname(os.path.abspath(__file__)), "..", "..", "ipc", "python"))
import chunkrt_ipc as c  # noqa: E402


def main():
    ns, seconds = sys.argv[1], float(sys.argv[2])
    rate = float(sys.argv[3]) if len(sys.argv) > 3 else 500.0
    node = c.node(f"chunkrt-forger-{os.getpid()}")
    pub = c.publisher(c.typed_service(node, c.chunks_name(ns), c.ActionChunkMsg))
    sent = 0

    def send(m):
        nonlocal sent
        sample = pub.loan_uninit()
        sample = sample.write_payload(m)
        sample.send()
        sent += 1

    huge = (1 << 64) - 1
    send(c.ActionChunkMsg(seq=1, publish_time_ns=1 << 63, chunk_id=1, observation_time_ns=huge,
                          ready_time_ns=huge, start_shift_ns=huge, period_ns=huge, horizon=2, n_dof=1))
    start = time.monotonic()
    k = 0
    while time.monotonic() - start < seconds:
        k += 1
        now = time.monotonic_ns()
        m = c.ActionChunkMsg(seq=k + 1, publish_time_ns=now, chunk_id=1_000_000_000 - k,
                             observation_time_ns=now, ready_time_ns=now, period_ns=20_000_000,
                             horizon=1, n_dof=1)
        m.actions[0][0] = 3.0
        send(m)
        time.sleep(max(0.0, start + k / rate - time.monotonic()))
    print(f"record_forger: sent={sent}", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
