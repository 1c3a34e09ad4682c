#!/usr/bin/env python3
"""chunkrt_record: a run, as the controller saw it, into a Rerun recording (``.rrd``).

A process of its own: it subscribes to a namespace's services (joint states, commands, the
controller's status, its chunks, the camera frames) and writes them on one timeline,
``robot_time`` (the CLOCK_MONOTONIC time every chunkrt message carries), so the controller does no
work for it and nobody waits for it (iceoryx2 drops what a full subscriber buffer cannot hold;
it is counted). In the recording:

- ``joints/<j>/measured``, ``joints/<j>/command``, ``joints/<j>/velocity``: per joint;
- ``joints/<j>/target``: the active chunk's action at each command's time (linear
  interpolation, what the controller follows before ruckig);
- ``joints/<j>/chunks/<id>``: every chunk from its first action's time, what the policy
  predicted, and ``chunks/log`` a line per chunk (id, delay, latency);
- ``cameras/<name>``: the frames at their capture times (``--frame-every N`` keeps one in N);
- ``controller/state`` and ``controller/reason`` (codes), ``controller/log`` (changes, holds,
  refusals, re-arms), ``controller/overruns``, ``controller/inference_latency_ms``,
  ``controller/lateness_p99_us``;
- ``properties``: the namespace, prompt, configuration text and versions, as given.

The file carries a default layout (a Rerun blueprint): joints 0 and 1 with their commanded,
measured and target positions and the predicted chunks overlaid, the cameras, the controller's
state and the logs.

Bounded: it stops writing data (and says so) past ``--max-mb`` megabytes of payload, and ends
cleanly on SIGINT / SIGTERM or after ``--duration`` seconds. Open the file with the viewer of the
same rerun-sdk: ``rerun run.rrd``.

    python3 tools/python/chunkrt_record.py --namespace NS --out run.rrd [--cameras a,b]
"""

import argparse
import ctypes
import os
import signal
import sys
import time

import numpy as np
import rerun as rr
import rerun.blueprint as rrb

sys.path.insert(0, os.path.join(os.path.dirname(os.path.abspath(__file__)), "..", "..", "ipc", "python"))
import chunkrt_ipc as c  # noqa: E402

STATE_NAMES = {k: v.upper() for k, v in c.CONTROLLER_STATE_NAMES.items()}


def layout(cameras):
    """The recording's default blueprint: what a robotics engineer looks at first."""
    joints = [
        rrb.TimeSeriesView(origin=f"joints/{j}", contents=["+ $origin/**", "- $origin/velocity"],
                           name=f"joint {j}: command, measured, target, predicted chunks")
        for j in (0, 1)
    ]
    right = [rrb.Spatial2DView(origin=f"cameras/{n}", name=n) for n in cameras]
    right.append(rrb.TimeSeriesView(origin="controller", name="controller"))
    right.append(rrb.TextLogView(origin="/", contents=["+ chunks/log", "+ controller/log"], name="log"))
    return rrb.Blueprint(rrb.Horizontal(rrb.Vertical(*joints), rrb.Vertical(*right), column_shares=[3, 2]))


def secs(ns):
    return np.asarray(ns, dtype=np.float64) * 1e-9


class Columns:
    """Scalars gathered per entity and sent in batches (``rr.send_columns``): one call per
    entity every flush, not one per sample."""

    def __init__(self):
        self.data = {}
        self.bytes = 0

    def add(self, path, t_ns, value):
        ts, vs = self.data.setdefault(path, ([], []))
        ts.append(t_ns)
        vs.append(value)
        self.bytes += 16

    def flush(self):
        for path, (ts, vs) in self.data.items():
            if ts:
                rr.send_columns(
                    path,
                    indexes=[rr.TimeColumn("robot_time", duration=secs(ts))],
                    columns=rr.Scalars.columns(scalars=np.asarray(vs, dtype=np.float64)),
                )
        self.data = {}


class Recorder:
    def __init__(self, args):
        self.args = args
        self.cols = Columns()
        self.chunks = {}  # id -> (t0_ns, period_ns, actions[h][n]) of the current controller
        self.session = 0  # a controller's chunk ids start again at 1: a new session
        self.last_chunk_id = 0
        self.counts = dict(joint_states=0, commands=0, statuses=0, chunks=0, frames=0, frames_kept=0,
                           dropped_over_limit=0, joint_states_missed=0, commands_missed=0)
        self.last_seq = {}
        self.last_state = None
        self.last_status = None
        self.full = False
        self.n = None

    def budget(self):
        if self.cols.bytes > self.args.max_mb * 1e6:
            if not self.full:
                print(f"chunkrt_record: {self.args.max_mb} MB written: no more data is recorded",
                      file=sys.stderr, flush=True)
            self.full = True
        return not self.full

    def missed(self, key, seq):
        """Counts the messages a full subscriber buffer dropped (a gap in the publisher's seq)."""
        last = self.last_seq.get(key)
        if last is not None and seq > last + 1:
            self.counts[key + "_missed"] += seq - last - 1
        self.last_seq[key] = seq

    def joint_state(self, js):
        self.counts["joint_states"] += 1
        self.missed("joint_states", js.seq)
        if not self.budget():
            self.counts["dropped_over_limit"] += 1
            return
        n = min(js.n_dof, c.MAX_DOF)
        self.n = n
        t = js.measurement_time_ns
        for j in range(n):
            self.cols.add(f"joints/{j}/measured", t, js.position[j])
            self.cols.add(f"joints/{j}/velocity", t, js.velocity[j])

    def command(self, cmd):
        self.counts["commands"] += 1
        self.missed("commands", cmd.seq)
        if not self.budget():
            self.counts["dropped_over_limit"] += 1
            return
        n = min(cmd.n_dof, c.MAX_DOF)
        t = cmd.publish_time_ns
        for j in range(n):
            self.cols.add(f"joints/{j}/command", t, cmd.position[j])
        ch = self.chunks.get(cmd.chunk_id)
        if ch is not None:
            t0, period, actions = ch
            k = (t - t0) / period
            if 0 <= k <= len(actions) - 1:
                i = int(k)
                f = k - i
                nxt = actions[min(i + 1, len(actions) - 1)]
                row = actions[i] * (1 - f) + nxt * f
                for j in range(min(n, row.shape[0])):
                    self.cols.add(f"joints/{j}/target", t, float(row[j]))

    def chunk(self, m):
        self.counts["chunks"] += 1
        if m.chunk_id <= self.last_chunk_id:
            self.session += 1
            self.chunks.clear()
        self.last_chunk_id = m.chunk_id
        h, n = min(m.horizon, c.MAX_CHUNK_HORIZON), min(m.n_dof, c.MAX_DOF)
        a = np.ctypeslib.as_array(m.actions)[:h, :n].copy()
        t0 = m.observation_time_ns + m.start_shift_ns
        period = max(m.period_ns, 1)
        self.chunks[m.chunk_id] = (t0, period, a)
        if len(self.chunks) > 64:
            self.chunks.pop(next(iter(self.chunks)))
        if not self.budget():
            self.counts["dropped_over_limit"] += 1
            return
        latency_ms = (m.ready_time_ns - m.observation_time_ns) / 1e6
        times = t0 + period * np.arange(h, dtype=np.int64)
        for j in range(n):
            rr.send_columns(
                f"joints/{j}/chunks/{self.chunk_path(m.chunk_id)}",
                indexes=[rr.TimeColumn("robot_time", duration=secs(times))],
                columns=rr.Scalars.columns(scalars=a[:, j]),
            )
        self.cols.bytes += a.nbytes
        rr.set_time("robot_time", duration=m.ready_time_ns * 1e-9)
        rr.log("chunks/log", rr.TextLog(
            f"chunk {self.chunk_path(m.chunk_id)}: {h} x {n}, delay {m.delay_steps}, latency {latency_ms:.1f} ms, "
            f"observation seq {m.observation_seq}"))
        self.cols.add("controller/inference_latency_ms", m.ready_time_ns, latency_ms)

    def chunk_path(self, chunk_id):
        """``<id>``, or ``<session>-<id>`` once a second controller has run."""
        return f"{self.session}-{chunk_id}" if self.session else str(chunk_id)

    def status(self, st):
        self.counts["statuses"] += 1
        t = st.publish_time_ns
        self.cols.add("controller/state", t, st.state)
        self.cols.add("controller/reason", t, st.state_reason)
        self.cols.add("controller/overruns", t, st.overruns)
        self.cols.add("controller/holds", t, st.hold_entries)
        self.cols.add("controller/lateness_p99_us", t, st.lateness_p99_ns / 1e3)
        self.cols.add("controller/rejected", t, sum(st.rejected))
        key = (st.state, st.state_reason, st.rearm_seq)
        if key != self.last_state:
            rr.set_time("robot_time", duration=t * 1e-9)
            name = STATE_NAMES.get(st.state, str(st.state))
            extra = f", re-arm {st.rearm_seq}: result {st.rearm_result}" if st.rearm_seq else ""
            level = "INFO" if st.state == c.CONTROLLER_STATE_RUNNING else "WARN"
            rr.log("controller/log", rr.TextLog(f"{name} (reason {st.state_reason}){extra}", level=level))
            self.last_state = key
        self.last_status = st

    def frame(self, name, header, pixels):
        self.counts["frames"] += 1
        if (self.counts["frames"] - 1) % max(self.args.frame_every, 1) != 0 or not self.budget():
            return
        h, w = header.height, header.width
        channels = 1 if header.encoding == c.ENCODING_MONO8 else 3
        if header.stride < w * channels or len(pixels) < header.stride * h:
            return
        img = np.frombuffer(pixels, dtype=np.uint8, count=header.stride * h).reshape(h, header.stride)
        img = img[:, : w * channels].reshape(h, w, channels)
        if header.encoding == c.ENCODING_BGR8:
            img = img[:, :, ::-1]
        rr.set_time("robot_time", duration=header.capture_time_ns * 1e-9)
        rr.log(f"cameras/{name}", rr.Image(img if channels == 3 else img[:, :, 0]))
        self.counts["frames_kept"] += 1
        self.cols.bytes += img.nbytes


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--namespace", required=True, help="the run's service namespace")
    ap.add_argument("--out", required=True, help="the .rrd file to write")
    ap.add_argument("--cameras", default="", help="camera names to record, comma separated")
    ap.add_argument("--frame-every", type=int, default=1, help="keep one frame in N")
    ap.add_argument("--duration", type=float, default=0.0, help="seconds (0: until SIGINT / SIGTERM)")
    ap.add_argument("--max-mb", type=float, default=500.0, help="payload megabytes to record at most")
    ap.add_argument("--prompt", default="", help="the run's prompt (a property)")
    ap.add_argument("--config", default="", help="the run's configuration file (a property)")
    ap.add_argument("--property", action="append", default=[], metavar="KEY=VALUE",
                    help="another property of the recording (repeatable)")
    args = ap.parse_args()

    stop = []
    signal.signal(signal.SIGINT, lambda *_: stop.append(1))
    signal.signal(signal.SIGTERM, lambda *_: stop.append(1))

    rr.init("chunkrt", recording_id=f"{args.namespace}-{os.getpid()}", spawn=False)
    rr.save(args.out, default_blueprint=layout([n for n in args.cameras.split(",") if n]))
    props = {"namespace": args.namespace, "prompt": args.prompt, "rerun_sdk": rr.__version__,
             "iceoryx2_contract": str(c.CONTRACT_VERSION)}
    for p in args.property:
        k, _, v = p.partition("=")
        props[k] = v
    text = "\n".join(f"- **{k}**: {v}" for k, v in props.items())
    if args.config and os.path.isfile(args.config):
        with open(args.config, encoding="utf-8", errors="replace") as f:
            text += "\n\n```toml\n" + f.read(200_000) + "\n```\n"
    rr.log("properties", rr.TextDocument(text, media_type=rr.MediaType.MARKDOWN), static=True)

    node = c.node(f"chunkrt-record-{os.getpid()}")
    subs = {
        "js": c.subscriber(c.typed_service(node, c.joint_state_name(args.namespace), c.JointState)),
        "cmd": c.subscriber(c.typed_service(node, c.joint_command_name(args.namespace), c.JointCommand)),
        "status": c.subscriber(c.typed_service(node, c.status_name(args.namespace), c.ControllerStatus)),
        "chunks": c.subscriber(c.typed_service(node, c.chunks_name(args.namespace), c.ActionChunkMsg)),
    }
    cams = []
    for name in [n for n in args.cameras.split(",") if n]:
        svc = c.camera_service(node, c.camera_name(args.namespace, name))
        cams.append((name, c.subscriber(svc, c.CAMERA_BUFFER_SIZE)))

    rec = Recorder(args)
    kinds = [("js", c.JointState, rec.joint_state), ("cmd", c.JointCommand, rec.command),
             ("status", c.ControllerStatus, rec.status), ("chunks", c.ActionChunkMsg, rec.chunk)]
    start = time.monotonic()
    last_flush = start
    print(f"chunkrt_record: recording '{args.namespace}' into {args.out}", flush=True)
    while not stop and (args.duration <= 0 or time.monotonic() - start < args.duration):
        # chunks first: a command names the chunk it executes
        for key, ty, handle in sorted(kinds, key=lambda k: k[0] != "chunks"):
            while True:
                sample = subs[key].receive()
                if sample is None:
                    break
                msg = ty.from_buffer_copy(sample.payload().contents)
                sample.delete()
                handle(msg)
        for name, sub in cams:
            while True:
                sample = sub.receive()
                if sample is None:
                    break
                header = c.CameraFrameHeader.from_buffer_copy(sample.user_header().contents)
                pixels = bytes(sample.payload())
                sample.delete()
                rec.frame(name, header, pixels)
        now = time.monotonic()
        if now - last_flush > 0.2:
            rec.cols.flush()
            last_flush = now
        time.sleep(0.0005)
    rec.cols.flush()
    rr.disconnect()
    counts = " ".join(f"{k}={v}" for k, v in rec.counts.items())
    print(f"chunkrt_record summary: {counts} out={args.out}", flush=True)
    return 0 if rec.counts["commands"] > 0 else 1


if __name__ == "__main__":
    sys.exit(main())
