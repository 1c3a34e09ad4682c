#!/usr/bin/env python3
"""The recorder styles its series in the recording itself: tools/python/chunkrt_record.py's
Recorder is fed a short run in-process (a status, chunks, joint states and commands, with their
iceoryx2 origins, as its main loop would feed them), writes a real .rrd, and
tools/python/rrd_check.py reads the styles back with Rerun's own SDK.

Holds: command, measured and target each carry a static ``SeriesLines`` with a colour and width
of their own (three different colours; measured wider than the command, and translucent: the
viewer draws it over the command); every
predicted chunk carries the one grey, thin style named ``predicted chunk`` (one legend name, not
an entry each), and its id stays in its entity path.

    python record_styles.py OUT_DIR [RECORDER_DIR]

RECORDER_DIR (default tools/python) holds the chunkrt_record.py to test (an older one shows the
test failing).

Prints the styles read back, then "ok" or the failures; exits 1 on a failure.
"""

import argparse
import json
import os
import subprocess
import sys
import time

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
ROBOT_PUB = 0x70
N = 2  # joints
H = 10  # actions per chunk
PERIOD = 20_000_000
CHUNKS = 6


def main():
    out = sys.argv[1]
    os.makedirs(out, exist_ok=True)
    path = os.path.join(out, "styled.rrd")
    args = argparse.Namespace(max_mb=100.0, max_chunk_series=30000, frame_every=1, out=path)
    rr.init("chunkrt", recording_id="styles", spawn=False)
    rr.save(path)
    rec = R.Recorder(args)
    t0 = time.monotonic_ns() - 2_000_000_000  # the run lies in the past (the recorder's check)

    st = c.ControllerStatus(seq=1, publish_time_ns=t0, state=c.CONTROLLER_STATE_RUNNING, n_dof=N)
    st.command_publisher_id[0] = COMMAND_PUB
    rec.take("status", rec.status, st, STATUS_PUB, CONTROLLER_PID)
    seq = 0
    for k in range(CHUNKS):
        t = t0 + k * 5 * PERIOD
        m = c.ActionChunkMsg(seq=k + 1, publish_time_ns=t, chunk_id=k + 1, observation_seq=1,
                             observation_time_ns=t, ready_time_ns=t, start_shift_ns=0,
                             period_ns=PERIOD, delay_steps=0, horizon=H, n_dof=N)
        for i in range(H):
            for j in range(N):
                m.actions[i][j] = 0.01 * (5 * k + i) + j
        rec.take("chunks", rec.chunk, m, CHUNK_PUB, CONTROLLER_PID)
        for ms in range(100):  # 1 kHz between this chunk and the next
            seq += 1
            tt = t + ms * 1_000_000
            js = c.JointState(seq=seq, measurement_time_ns=tt, n_dof=N)
            cmd = c.JointCommand(seq=seq, publish_time_ns=tt, n_dof=N, chunk_id=k + 1,
                                 mode=c.COMMAND_MODE_POSITION)
            for j in range(N):
                js.position[j] = 0.01 * (5 * k + ms / 20) + j
                cmd.position[j] = js.position[j]
            rec.take("js", rec.joint_state, js, ROBOT_PUB, 1)
            rec.take("cmd", rec.command, cmd, COMMAND_PUB, CONTROLLER_PID)
    rec.flush()
    rr.disconnect()

    failures = []

    def expect(cond, what):
        if not cond:
            failures.append(what)

    expect(rec.counts["rejected"] == 0 and rec.counts["errors"] == 0 and rec.counts["foreign"] == 0,
           f"the run fed was not taken whole: {rec.counts}")
    check = subprocess.run([sys.executable, os.path.join(ROOT, "tools", "python", "rrd_check.py"), path],
                           capture_output=True, text=True)
    expect(check.returncode == 0, f"rrd_check.py: {check.stderr}")
    v = json.loads(check.stdout.strip().splitlines()[-1])
    styles = {}
    for j in range(N):
        for kind in ("command", "measured", "target"):
            s = v["series"].get(f"joints/{j}/{kind}", {}).get("style")
            print(f"joints/{j}/{kind}: {s}")
            expect(s is not None and s["color"] and s["width"], f"joints/{j}/{kind} has no style: {s}")
            expect(s is None or s["name"] == kind, f"joints/{j}/{kind} is named {s and s['name']}")
            styles.setdefault(kind, set()).add(json.dumps(s, sort_keys=True))
    for kind, ss in styles.items():
        expect(len(ss) == 1, f"{kind}: a style per joint, not one: {ss}")
    got = {k: json.loads(next(iter(ss))) for k, ss in styles.items() if len(ss) == 1}
    got = {k: s for k, s in got.items() if s}
    if len(got) == 3:
        colours = {got[k]["color"] for k in got}
        expect(len(colours) == 3, f"command, measured and target share a colour: {got}")
        expect(got["measured"]["width"] > got["command"]["width"],
               f"measured is not wider than the command it lies under: {got}")
        # the viewer draws measured over the command: a translucent band lets the command show
        m = got["measured"]["color"]
        expect(len(m) == 9 and int(m[7:9], 16) < 200, f"measured is opaque and hides the command: {m}")
    print(f"chunk styles: {v['chunk_styles']}")
    expect(v["chunk_series"] == CHUNKS * N, f"{v['chunk_series']} chunk series, fed {CHUNKS * N}")
    expect(len(v["chunk_styles"]) == 1, f"the chunks do not share one style: {v['chunk_styles']}")
    if v["chunk_styles"]:
        s = v["chunk_styles"][0]["style"] or {}
        expect(v["chunk_styles"][0]["series"] == CHUNKS * N, f"not every chunk styled: {v['chunk_styles']}")
        rgb = s.get("color") or "#000000"
        r, g, b = (int(rgb[i:i + 2], 16) for i in (1, 3, 5))
        expect(r == g == b and 64 <= r <= 224, f"a chunk's colour is not a grey: {rgb}")
        expect(bool(got) and (s.get("width") or 9) < min(x["width"] for x in got.values()),
               f"a chunk's line is not thinner than command, measured and target: {s}, {got}")
        expect(s.get("name") == "predicted chunk", f"a chunk's name: {s.get('name')}")
    print("\n".join(failures) if failures else "ok")
    return 1 if failures else 0


if __name__ == "__main__":
    sys.exit(main())
