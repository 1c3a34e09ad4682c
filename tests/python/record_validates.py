#!/usr/bin/env python3
"""What tools/python/chunkrt_record.py does with hostile input, without a controller: its Recorder
is fed messages as its main loop would feed them (with their iceoryx2 origin: publisher id and
process id) and writes a real .rrd, read back with Rerun's own SDK.

    python record_validates.py OUT_DIR [RECORDER_DIR]

RECORDER_DIR (default tools/python) holds the chunkrt_record.py to test (an older one measures
the "before"). Prints one JSON line of figures, then "ok" or the failures; exits 1 on a failure.
"""

import argparse
import inspect
import json
import os
import sys
import time

import numpy as np
import rerun as rr

HERE = os.path.dirname(os.path.abspath(__file__))
ROOT = os.path.join(HERE, "..", "..")
sys.path.insert(0, os.path.join(ROOT, "ipc", "python"))
sys.path.insert(0, sys.argv[2] if len(sys.argv) > 2 else os.path.join(ROOT, "tools", "python"))
import chunkrt_record as R  # noqa: E402

c = R.c
CONTROLLER_PID = 4242
STATUS_PUB = 0x51
COMMAND_PUB = 0xC0
CHUNK_PUB = 0xC1
FORGER_PID = 666
failures = []


def expect(cond, what):
    if not cond:
        failures.append(what)


def feed(rec, handler, msg, origin, pid):
    """One message as the main loop gives it; 'crash' when it escapes (the old recorder died)."""
    if hasattr(rec, "take"):
        rec.take("msg", handler, msg, origin, pid)
        return "ok"
    try:
        if len(inspect.signature(handler).parameters) >= 3:
            handler(msg, origin, pid)
        else:
            handler(msg)
        return "ok"
    except Exception as e:  # noqa: BLE001
        return f"crash: {type(e).__name__}: {e}"


def status(seq, t):
    st = c.ControllerStatus(seq=seq, publish_time_ns=t, state=c.CONTROLLER_STATE_RUNNING, n_dof=2)
    st.command_publisher_id[0] = COMMAND_PUB
    return st


def chunk(seq, chunk_id, t, h=4, n=2, **kw):
    m = c.ActionChunkMsg(seq=seq, publish_time_ns=t, chunk_id=chunk_id, observation_seq=1,
                         observation_time_ns=t - 1000, ready_time_ns=t, start_shift_ns=0,
                         period_ns=20_000_000, delay_steps=1, horizon=h, n_dof=n)
    for k in range(h):
        for j in range(n):
            m.actions[k][j] = 0.1 * k + j
    for key, v in kw.items():
        setattr(m, key, v)
    return m


def recorder(path, max_mb, series=30000):
    args = argparse.Namespace(max_mb=max_mb, max_chunk_series=series, frame_every=1, out=path)
    rr.init("chunkrt", recording_id=os.path.basename(path), spawn=False)
    rr.save(path)
    return R.Recorder(args)


def close(rec, path):
    if hasattr(rec, "flush"):
        rec.flush()
    else:
        rec.cols.flush()
    rr.disconnect()
    return os.path.getsize(path)


def readable(path):
    try:
        reader = rr.chunk.RrdReader(path)
        paths = {ch.entity_path for ch in reader.stream()}
        return len(paths), ""
    except Exception as e:  # noqa: BLE001
        return -1, f"{type(e).__name__}: {e}"


def main():
    out = sys.argv[1]
    os.makedirs(out, exist_ok=True)
    fig = {}
    now = time.monotonic_ns()

    # 1. chunks that break the contract, from the bound controller's own process
    path = os.path.join(out, "bad.rrd")
    rec = recorder(path, 100.0)
    feed(rec, rec.status, status(1, now), STATUS_PUB, CONTROLLER_PID)
    bad = {
        "time >= 2^63": chunk(1, 1, now, observation_time_ns=(1 << 63) + 5, ready_time_ns=(1 << 63) + 6),
        "ready 2^64-1": chunk(2, 2, now, ready_time_ns=(1 << 64) - 1),
        "publish 2^63": chunk(3, 3, (1 << 63)),
        "period 2^63": chunk(4, 4, now, period_ns=1 << 63),
        "horizon 0": chunk(5, 5, now, h=0),
        "n_dof 4e9": chunk(6, 6, now, n_dof=4_000_000_000),
        "NaN action": chunk(7, 7, now, actions=type(c.ActionChunkMsg().actions)()),
        "from the future": chunk(8, 8, now + 5_000_000_000),
    }
    bad["NaN action"].actions[0][0] = float("nan")
    results = {k: feed(rec, rec.chunk, m, CHUNK_PUB, CONTROLLER_PID) for k, m in bad.items()}
    fig["bad_chunks"] = results
    fig["bad_chunks_written"] = rec.counts["chunks"]
    for k, r in results.items():
        expect(r == "ok", f"{k}: {r}")
    expect(rec.counts["chunks"] == 0, f"{rec.counts['chunks']} invalid chunks counted as written")
    # a good one from the controller's process is taken; one from another process is not
    feed(rec, rec.chunk, chunk(20, 20, now), CHUNK_PUB, CONTROLLER_PID)
    feed(rec, rec.chunk, chunk(1, 21, now), 0xBAD, FORGER_PID)
    fig["good_then_forged_chunks_written"] = rec.counts["chunks"]
    expect(rec.counts["chunks"] == 1, f"{rec.counts['chunks']} chunks written of 1 good + 1 forged")
    close(rec, path)
    n, err = readable(path)
    expect(n > 0, f"bad.rrd unreadable: {err}")

    # 1b. the controller's last chunk comes after its STOPPED status (its inference thread publishes
    # chunks, the main loop reads statuses first): kept; a forger's after the stop is not
    path = os.path.join(out, "stop.rrd")
    rec = recorder(path, 100.0)
    feed(rec, rec.status, status(1, now), STATUS_PUB, CONTROLLER_PID)
    feed(rec, rec.chunk, chunk(1, 1, now), CHUNK_PUB, CONTROLLER_PID)
    stopped = status(2, now + 1000)
    stopped.state = c.CONTROLLER_STATE_STOPPED
    feed(rec, rec.status, stopped, STATUS_PUB, CONTROLLER_PID)
    feed(rec, rec.chunk, chunk(2, 2, now + 500), CHUNK_PUB, CONTROLLER_PID)
    feed(rec, rec.chunk, chunk(3, 3, now + 600), 0xBAD, FORGER_PID)
    fig["chunks_after_stop_written"] = rec.counts["chunks"]
    expect(rec.counts["chunks"] == 2,
           f"{rec.counts['chunks']} chunks written of 2 from the stopped controller + 1 forged")
    close(rec, path)

    # 2. a flood of tiny chunks with ids going down, and statuses, from the controller itself
    max_mb = 1.0
    path = os.path.join(out, "flood.rrd")
    rec = recorder(path, max_mb, series=300)
    t = now - 30_000_000_000
    feed(rec, rec.status, status(1, t), STATUS_PUB, CONTROLLER_PID)
    crashes = 0
    for k in range(6000):
        t += 1000
        m = chunk(k + 1, 10_000_000 - k, t, h=1, n=1)
        crashes += feed(rec, rec.chunk, m, CHUNK_PUB, CONTROLLER_PID) != "ok"
    for k in range(40000):
        t += 1000
        crashes += feed(rec, rec.status, status(k + 2, t), STATUS_PUB, CONTROLLER_PID) != "ok"
        if k % 2000 == 0 and hasattr(rec, "flush"):
            rec.flush()
        elif k % 2000 == 0:
            rec.cols.flush()
    size = close(rec, path)
    n, err = readable(path)
    fig["flood"] = {"max_mb": max_mb, "file_mb": round(size / 1e6, 3), "ratio": round(size / (max_mb * 1e6), 2),
                    "entity_paths": n, "crashes": crashes}
    # the blueprint and Rerun's file header are not under the recorder's control: 5 % slack
    expect(size <= max_mb * 1e6 * 1.05, f"flood: {size} bytes written under --max-mb {max_mb}")
    expect(0 < n <= 300 + 50, f"flood: {n} entity paths (bound 300 chunk series) {err}")
    expect(crashes == 0, f"flood: {crashes} messages crashed the recorder")

    print(json.dumps(fig))
    if failures:
        for f in failures:
            print("FAIL:", f)
        return 1
    print("ok")
    return 0


if __name__ == "__main__":
    sys.exit(main())
