#!/usr/bin/env python3
"""chunkrt_record: a run, as the controller saw it, into a Rerun recording (``.rrd``).

A process of its own: it subscribes to a namespace's services (joint states, commands, the
controller's status, its chunks, the camera frames) and writes them on one timeline,
``robot_time`` (the CLOCK_MONOTONIC time every chunkrt message carries), so the controller does no
work for it and nobody waits for it (iceoryx2 drops what a full subscriber buffer cannot hold;
it is counted: ``joint_states_missed``, ``commands_missed``, and ``chunks_missed``, the
controller's chunks pushed out of the buffer, e.g. by a flood from another publisher). In the
recording:

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

Each joint series carries its own style (Rerun's ``SeriesLines``, logged once and static, so any
view of the file draws it the same): ``command`` red and thin, ``measured`` a wide translucent
blue band (the viewer draws it over the command, which it follows closely: the command shows
through), ``target`` green; every predicted chunk thin and grey, all of them named ``predicted
chunk`` (one name for the legend, not an entry each); a chunk's id is the last part of its
entity path, ``joints/<j>/chunks/<id>``, and its line in ``chunks/log``.

The file carries a default layout (a Rerun blueprint): joints 0 and 1 with their commanded,
measured and target positions and the predicted chunks overlaid, the cameras, the controller's
state and the logs.

It validates what it reads as the controller validates its inputs: every time below 2^63 and
at most a second ahead of this machine's CLOCK_MONOTONIC, joint counts and horizons within the
contract, finite values, sequence numbers that rise per publisher; a message that fails is counted
(``rejected=`` in the summary, a line on stderr at most every 10 s) and not written, and an error
in handling one message loses that message only (``errors=``). It takes the controller's messages
from the controller only, bound as a robot binds a session (``chunkrt_ipc::SessionGate``): the
first status publisher (another may bind after 1 s of its silence or its STOPPED status), the
command publisher that status announces, and chunks only from publishers in that controller's
process; the joint states from the first robot publisher (rebound after 1 s of silence). What
others publish is counted (``foreign=``) and not written.

Bounded: every byte it writes counts against ``--max-mb`` (samples, log lines, images, and
Rerun's own overhead per call, about 1.2 kB, held against the file's size on disk); past it, it
stops writing (and says so). At most ``--max-chunk-series`` predicted-chunk series (one per
chunk and joint) are written, after which a chunk gets its log line only. It ends cleanly on
SIGINT / SIGTERM or after ``--duration`` seconds. Open the file with the viewer of the same
rerun-sdk: ``rerun run.rrd``.

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


#: a message time at or past 2^63 ns is invalid (as the controller holds it: i64 nanoseconds)
TIME_LIMIT_NS = 1 << 63
#: how far ahead of this machine's clock a message time may be (the controller's 1 s allowance)
MAX_FUTURE_NS = 1_000_000_000
#: time between a chunk's actions, at most (ns)
MAX_PERIOD_NS = 1_000_000_000
#: how far after its observation a chunk's first action may be (ns)
MAX_START_SHIFT_NS = 10_000_000_000
#: status (or joint state) silence after which another publisher may bind (ns)
REBIND_NS = 1_000_000_000
#: what Rerun writes per call besides the data (measured on rerun-sdk 0.41: 1.1–1.6 kB per
#: ``send_columns`` call into a file), charged against ``--max-mb``
CALL_BYTES = 1600
#: what one series' style costs in the file (a static ``SeriesLines``: measured on rerun-sdk
#: 0.41, 2.9 kB per entity), charged against ``--max-mb``
STYLE_BYTES = 3200
#: chunks held while no controller is bound yet (the first chunk can precede the first status)
PENDING_CHUNKS = 16
#: image sizes accepted (pixels per side)
MAX_IMAGE_SIDE = 8192


#: each joint series' style: (name, colour RGB or RGBA, line width in UI points); the viewer
#: draws a joint's series in the order of their names (command under measured), so measured is a
#: wide translucent band and the thin command stays visible through it; ``STYLES`` and
#: ``CHUNK_STYLE`` are what ``rrd_check.py`` reports and tests/record_rerun.rs holds them to
STYLES = {
    "command": ("command", (230, 30, 30), 2.0),
    "measured": ("measured", (40, 90, 220, 90), 6.0),  # translucent: the command shows through
    "target": ("target", (30, 160, 60), 1.5),
    "velocity": ("velocity", (120, 60, 170), 1.0),
}
#: every predicted chunk: one name for them all, thin and grey
CHUNK_STYLE = ("predicted chunk", (150, 150, 150), 0.5)


def series_style(path):
    """The style of a joint series or a predicted chunk's path, or None."""
    parts = path.split("/")
    if len(parts) == 3 and parts[0] == "joints":
        return STYLES.get(parts[2])
    if len(parts) == 4 and parts[0] == "joints" and parts[2] == "chunks":
        return CHUNK_STYLE
    return None


def log_style(path):
    """``path``'s style as a static ``SeriesLines`` (one call; nothing for an unstyled path)."""
    style = series_style(path)
    if style is None:
        return False
    name, rgb, width = style
    rr.log(path, rr.SeriesLines(colors=[rgb], widths=[width], names=[name]), static=True)
    return True


class Invalid(Exception):
    """A message that fails validation: counted under ``reason`` and not written."""

    def __init__(self, reason, text):
        super().__init__(text)
        self.reason = reason


def now_ns():
    """CLOCK_MONOTONIC, the clock every chunkrt message is stamped with."""
    return time.monotonic_ns()


def check_time(field, t, now):
    if t >= TIME_LIMIT_NS:
        raise Invalid("time", f"{field} {t} is not below 2^63")
    if t > now + MAX_FUTURE_NS:
        raise Invalid("from_future", f"{field} {t} is {(t - now) / 1e9:.3f} s ahead of this clock")


def check_n(field, n, most):
    if n < 1 or n > most:
        raise Invalid("n_dof", f"{field} {n} is not in 1..{most}")
    return n


def check_finite(field, values):
    v = np.asarray(values, dtype=np.float64)
    if not np.all(np.isfinite(v)):
        raise Invalid("non_finite", f"{field} is not finite")


def validate_joint_state(js, now):
    n = check_n("n_dof", js.n_dof, c.MAX_DOF)
    check_time("measurement_time_ns", js.measurement_time_ns, now)
    for f in ("position", "velocity", "effort"):
        check_finite(f, list(getattr(js, f))[:n])
    return n


def validate_command(cmd, now):
    n = check_n("n_dof", cmd.n_dof, c.MAX_DOF)
    if cmd.mode not in (c.COMMAND_MODE_POSITION, c.COMMAND_MODE_HOLD):
        raise Invalid("mode", f"mode {cmd.mode} is unknown")
    check_time("publish_time_ns", cmd.publish_time_ns, now)
    for f in ("position", "velocity", "acceleration"):
        check_finite(f, list(getattr(cmd, f))[:n])
    return n


def validate_status(st, now):
    check_time("publish_time_ns", st.publish_time_ns, now)
    if st.n_dof > c.MAX_DOF:
        raise Invalid("n_dof", f"n_dof {st.n_dof} is not in 0..{c.MAX_DOF}")


def validate_chunk(m, now):
    """The chunk's rows and columns used, its first action's time and its period, or Invalid."""
    h = check_n("horizon", m.horizon, c.MAX_CHUNK_HORIZON)
    n = check_n("n_dof", m.n_dof, c.MAX_DOF)
    if m.chunk_id == 0:
        raise Invalid("other", "chunk id 0")
    if m.reserved != 0:
        raise Invalid("other", f"reserved {m.reserved} is not zero")
    for f in ("publish_time_ns", "observation_time_ns", "ready_time_ns"):
        check_time(f, getattr(m, f), now)
    if m.ready_time_ns < m.observation_time_ns:
        raise Invalid("time", "ready before its observation")
    if not 1 <= m.period_ns <= MAX_PERIOD_NS:
        raise Invalid("time", f"period_ns {m.period_ns} is not in 1..{MAX_PERIOD_NS}")
    if m.start_shift_ns > MAX_START_SHIFT_NS:
        raise Invalid("time", f"start_shift_ns {m.start_shift_ns} is over {MAX_START_SHIFT_NS}")
    a = np.ctypeslib.as_array(m.actions)[:h, :n]
    if not np.all(np.isfinite(a)):
        raise Invalid("non_finite", "actions are not finite")
    return h, n, m.observation_time_ns + m.start_shift_ns, m.period_ns


def validate_frame(header, size, now):
    check_time("capture_time_ns", header.capture_time_ns, now)
    channels = c.BYTES_PER_PIXEL.get(header.encoding)
    if channels is None:
        raise Invalid("frame", f"encoding {header.encoding} is unknown")
    h, w = header.height, header.width
    if not (1 <= h <= MAX_IMAGE_SIDE and 1 <= w <= MAX_IMAGE_SIDE):
        raise Invalid("frame", f"{w} x {h} pixels")
    if header.stride < w * channels or size < header.stride * h:
        raise Invalid("frame", f"stride {header.stride} / {size} bytes for {w} x {h}")
    return h, w, channels


class Stream:
    """One publisher's stream, as the controller's ``StreamGuard``: the first publisher binds,
    another may bind after ``REBIND_NS`` of its silence; seq rises, times do not go back."""

    def __init__(self):
        self.origin = None
        self.last_seen = 0
        self.seq = None
        self.time = 0

    def check(self, origin, seq, t, now):
        if self.origin is not None and origin != self.origin and now - self.last_seen < REBIND_NS:
            raise Invalid("foreign", f"publisher {origin:#x} is not the bound one")
        if origin != self.origin:
            self.origin, self.seq, self.time = origin, None, 0
        if self.seq is not None and seq <= self.seq:
            raise Invalid("out_of_order", f"seq {seq} after {self.seq}")
        if t < self.time:
            raise Invalid("out_of_order", f"time {t} before {self.time}")
        self.last_seen = now
        self.seq = seq
        self.time = t

    def release(self):
        self.origin = None


class Columns:
    """Scalars gathered per entity and sent in batches (``rr.send_columns``): one call per
    entity every flush, not one per sample. ``bytes`` is everything the recorder has written."""

    def __init__(self):
        self.data = {}
        self.bytes = 0
        self.styled = set()  # the paths whose SeriesLines style is written

    def add(self, path, t_ns, value):
        ts, vs = self.data.setdefault(path, ([], []))
        ts.append(t_ns)
        vs.append(value)
        self.bytes += 16

    def flush(self):
        for path, (ts, vs) in self.data.items():
            if ts:
                if path not in self.styled:
                    self.styled.add(path)
                    if log_style(path):
                        self.bytes += STYLE_BYTES
                rr.send_columns(
                    path,
                    indexes=[rr.TimeColumn("robot_time", duration=secs(ts))],
                    columns=rr.Scalars.columns(scalars=np.asarray(vs, dtype=np.float64)),
                )
                self.bytes += CALL_BYTES
        self.data = {}


class Recorder:
    def __init__(self, args):
        self.args = args
        self.cols = Columns()
        self.chunks = {}  # id -> (t0_ns, period_ns, actions[h][n]) of the current controller
        self.session = 0  # a controller's chunk ids start again at 1: a new session
        self.last_chunk_id = 0
        self.counts = dict(joint_states=0, commands=0, statuses=0, chunks=0, frames=0, frames_kept=0,
                           dropped_over_limit=0, joint_states_missed=0, commands_missed=0,
                           chunks_missed=0, rejected=0, foreign=0, errors=0, chunk_series=0,
                           chunks_not_plotted=0, chunks_unbound=0)
        self.rejected = {}
        self.last_seq = {}
        self.last_state = None
        self.last_status = None
        self.full = False
        self.file_bytes = 0
        self.n = None
        # the controller, bound from its status (SessionGate's rules)
        self.status_stream = Stream()
        self.controller_pid = None  # the bound status publisher's process
        # the bound controller's first status was its first (seq 1): the recorder was there before
        # its first chunk, so a chunk seq above 1 at the start is a chunk lost, not one before us
        self.controller_from_start = False
        self.controller_chunk_origin = None
        # the process of the controller that last stopped cleanly: its last chunks may come after
        # its STOPPED status (the inference thread publishes them; statuses are read first)
        self.stopped_pid = None
        self.command_publisher = 0  # announced in its status
        self.chunk_stream = Stream()
        self.state_stream = Stream()
        self.pending = []  # (origin, pid, msg) of chunks that came before any controller bound
        self.said = {}  # what -> when last said on stderr (rate limit)

    def say(self, what, text):
        """A line on stderr, at most one per ``what`` every 10 s."""
        now = time.monotonic()
        if now - self.said.get(what, -1e9) >= 10.0:
            self.said[what] = now
            print(f"chunkrt_record: {text}", file=sys.stderr, flush=True)

    def reject(self, kind, e):
        if e.reason == "foreign":
            self.counts["foreign"] += 1
            self.say("foreign-" + kind, f"{kind} from another publisher ignored ({e}); "
                     f"{self.counts['foreign']} so far")
            return
        self.counts["rejected"] += 1
        key = f"{kind}:{e.reason}"
        self.rejected[key] = self.rejected.get(key, 0) + 1
        self.say("rejected-" + key, f"a {kind} rejected ({e.reason}: {e}); {self.rejected[key]} so far")

    def error(self, kind, e):
        self.counts["errors"] += 1
        self.say("error-" + kind, f"a {kind} could not be recorded ({type(e).__name__}: {e}); "
                 f"{self.counts['errors']} errors so far")

    def take(self, kind, handler, msg, origin=0, pid=0):
        """One message through its handler: rejected, foreign or failed, it is counted and
        dropped; nothing a message holds stops the recorder."""
        try:
            handler(msg, origin, pid)
        except Invalid as e:
            self.reject(kind, e)
        except Exception as e:  # noqa: BLE001 (a fault in one message loses that message only)
            self.error(kind, e)

    def charge(self, nbytes):
        self.cols.bytes += nbytes

    def budget(self, cost=0):
        """Whether ``cost`` more bytes fit under ``--max-mb`` (all written bytes, and the file's
        own size as last seen)."""
        if not self.full and max(self.cols.bytes, self.file_bytes) + cost > self.args.max_mb * 1e6:
            print(f"chunkrt_record: {self.args.max_mb} MB written: no more data is recorded",
                  file=sys.stderr, flush=True)
            self.full = True
        return not self.full

    def flush(self):
        """Sends the gathered columns (if they fit) and reads the file's size."""
        pending = sum(len(ts) for ts, _ in self.cols.data.values())
        cost = sum(CALL_BYTES + (p not in self.cols.styled and series_style(p) is not None) * STYLE_BYTES
                   for p in self.cols.data)
        if pending and not self.budget(cost):
            self.cols.data = {}
        self.cols.flush()
        try:
            self.file_bytes = os.path.getsize(self.args.out)
        except OSError:
            pass

    def add(self, path, t, value):
        """A sample into the columns if it fits (with its share of the next flush's calls)."""
        # a new path this flush: the call flush() makes for it (charged there) must fit too
        first = 0 if path in self.cols.data else CALL_BYTES
        style = 0 if path in self.cols.styled or series_style(path) is None else STYLE_BYTES
        if self.budget(16 + first + style):
            self.cols.add(path, t, value)

    def log(self, path, t_ns, text, level="INFO"):
        cost = len(text) + 64
        if not self.budget(cost):
            self.counts["dropped_over_limit"] += 1
            return
        rr.set_time("robot_time", duration=t_ns * 1e-9)
        rr.log(path, rr.TextLog(text, level=level))
        self.charge(cost)

    def missed(self, key, seq):
        """Counts the messages a full subscriber buffer dropped (a gap in the publisher's seq)."""
        last = self.last_seq.get(key)
        if last is not None and seq > last + 1:
            self.counts[key + "_missed"] += min(seq - last - 1, 1 << 32)
        self.last_seq[key] = seq

    def joint_state(self, js, origin=0, pid=0):
        now = now_ns()
        n = validate_joint_state(js, now)
        self.state_stream.check(origin, js.seq, js.measurement_time_ns, now)
        self.counts["joint_states"] += 1
        self.missed("joint_states", js.seq)
        if not self.budget(32 * n):
            self.counts["dropped_over_limit"] += 1
            return
        self.n = n
        t = js.measurement_time_ns
        for j in range(n):
            self.add(f"joints/{j}/measured", t, js.position[j])
            self.add(f"joints/{j}/velocity", t, js.velocity[j])

    def command(self, cmd, origin=0, pid=0):
        now = now_ns()
        n = validate_command(cmd, now)
        if self.command_publisher == 0 or origin != self.command_publisher:
            raise Invalid("foreign", f"publisher {origin:#x} is not the command publisher the "
                          f"controller announces ({self.command_publisher:#x})")
        self.counts["commands"] += 1
        self.missed("commands", cmd.seq)
        if not self.budget(32 * n):
            self.counts["dropped_over_limit"] += 1
            return
        t = cmd.publish_time_ns
        for j in range(n):
            self.add(f"joints/{j}/command", t, cmd.position[j])
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
                    self.add(f"joints/{j}/target", t, float(row[j]))

    def status(self, st, origin=0, pid=0):
        now = now_ns()
        validate_status(st, now)
        previous = self.status_stream.origin
        self.status_stream.check(origin, st.seq, st.publish_time_ns, now)
        if previous != origin:
            # a controller bound (the first, or another after the last one's silence or stop)
            self.controller_pid = pid
            self.controller_from_start = st.seq == 1
            self.command_publisher = 0
            self.chunk_stream.release()
        if st.state == c.CONTROLLER_STATE_STOPPED:
            self.status_stream.release()  # a clean stop ends the session
            self.stopped_pid = self.controller_pid
            self.controller_pid = None  # the next controller's first chunks wait for its status
        if st.command_publisher():
            self.command_publisher = st.command_publisher()
        self.counts["statuses"] += 1
        if self.pending:
            pending, self.pending = self.pending, []
            for o, p, m in pending:
                self.take("chunk", self.chunk, m, o, p)
        t = st.publish_time_ns
        self.add("controller/state", t, st.state)
        self.add("controller/reason", t, st.state_reason)
        self.add("controller/overruns", t, st.overruns)
        self.add("controller/holds", t, st.hold_entries)
        self.add("controller/lateness_p99_us", t, st.lateness_p99_ns / 1e3)
        self.add("controller/rejected", t, sum(st.rejected))
        key = (st.state, st.state_reason, st.rearm_seq)
        if key != self.last_state:
            name = STATE_NAMES.get(st.state, str(st.state))
            extra = f", re-arm {st.rearm_seq}: result {st.rearm_result}" if st.rearm_seq else ""
            level = "INFO" if st.state == c.CONTROLLER_STATE_RUNNING else "WARN"
            self.log("controller/log", t, f"{name} (reason {st.state_reason}){extra}", level)
            self.last_state = key
        self.last_status = st

    def chunk(self, m, origin=0, pid=0):
        now = now_ns()
        if self.controller_pid is not None and pid == self.controller_pid:
            # every chunk the controller's process published and the recorder received, valid or
            # not, before the checks below: a gap is one a full buffer dropped (a flood on the
            # service from others pushes the controller's chunks out of the 4-slot buffer)
            if origin != self.controller_chunk_origin:
                self.controller_chunk_origin = origin
                self.last_seq["chunks"] = 0 if self.controller_from_start else None
            self.missed("chunks", m.seq)
        h, n, t0, period = validate_chunk(m, now)
        if self.controller_pid is None and pid is not None and pid == self.stopped_pid:
            pass  # the stopped controller's last chunks, from its own process
        elif self.controller_pid is None:
            if len(self.pending) < PENDING_CHUNKS:
                self.pending.append((origin, pid, m))
            else:
                raise Invalid("foreign", "no controller bound yet")
            return
        elif pid != self.controller_pid:
            raise Invalid("foreign", f"publisher {origin:#x} is not in the controller's process")
        self.chunk_stream.check(origin, m.seq, m.publish_time_ns, now)
        self.counts["chunks"] += 1
        if m.chunk_id <= self.last_chunk_id:
            self.session += 1
            self.chunks.clear()
        self.last_chunk_id = m.chunk_id
        a = np.ctypeslib.as_array(m.actions)[:h, :n].copy()
        self.chunks[m.chunk_id] = (t0, period, a)
        if len(self.chunks) > 64:
            self.chunks.pop(next(iter(self.chunks)))
        latency_ms = (m.ready_time_ns - m.observation_time_ns) / 1e6
        cost = n * (STYLE_BYTES + CALL_BYTES + 16 * h)  # the style and the values, per joint
        plotted = self.counts["chunk_series"] + n <= self.args.max_chunk_series
        if plotted and self.budget(cost):
            times = t0 + period * np.arange(h, dtype=np.int64)
            for j in range(n):
                path = f"joints/{j}/chunks/{self.chunk_path(m.chunk_id)}"
                log_style(path)
                rr.send_columns(
                    path,
                    indexes=[rr.TimeColumn("robot_time", duration=secs(times))],
                    columns=rr.Scalars.columns(scalars=a[:, j]),
                )
            self.charge(cost)
            self.counts["chunk_series"] += n
        elif not self.full:
            self.counts["chunks_not_plotted"] += 1
            self.say("series", f"{self.args.max_chunk_series} chunk series written: "
                     "further chunks get their log line only")
        self.log("chunks/log", m.ready_time_ns,
                 f"chunk {self.chunk_path(m.chunk_id)}: {h} x {n}, delay {m.delay_steps}, "
                 f"latency {latency_ms:.1f} ms, observation seq {m.observation_seq}")
        self.add("controller/inference_latency_ms", m.ready_time_ns, latency_ms)

    def chunk_path(self, chunk_id):
        """``<id>``, or ``<session>-<id>`` once a second controller has run."""
        return f"{self.session}-{chunk_id}" if self.session else str(chunk_id)

    def frame(self, name, header, pixels):
        self.counts["frames"] += 1
        h, w, channels = validate_frame(header, len(pixels), now_ns())
        if (self.counts["frames"] - 1) % max(self.args.frame_every, 1) != 0:
            return
        if not self.budget(h * w * channels + CALL_BYTES):
            self.counts["dropped_over_limit"] += 1
            return
        img = np.frombuffer(pixels, dtype=np.uint8, count=header.stride * h).reshape(h, header.stride)
        img = img[:, : w * channels].reshape(h, w, channels)
        if header.encoding == c.ENCODING_BGR8:
            img = img[:, :, ::-1]
        rr.set_time("robot_time", duration=header.capture_time_ns * 1e-9)
        rr.log(f"cameras/{name}", rr.Image(img if channels == 3 else img[:, :, 0]))
        self.counts["frames_kept"] += 1
        self.charge(img.nbytes + CALL_BYTES)


def origin_of(sample):
    """(publisher id, process id) of a sample, from iceoryx2's header (not from its payload)."""
    import iceoryx2 as iox2

    header = sample.header
    return header.publisher_id.value, header.node_id.pid(iox2.ServiceType.Ipc)


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--namespace", required=True, help="the run's service namespace")
    ap.add_argument("--out", required=True, help="the .rrd file to write")
    ap.add_argument("--cameras", default="", help="camera names to record, comma separated")
    ap.add_argument("--frame-every", type=int, default=1, help="keep one frame in N")
    ap.add_argument("--duration", type=float, default=0.0, help="seconds (0: until SIGINT / SIGTERM)")
    ap.add_argument("--max-mb", type=float, default=500.0,
                    help="megabytes to write at most (everything written counts)")
    ap.add_argument("--max-chunk-series", type=int, default=30000,
                    help="predicted-chunk series (one per chunk and joint) to write at most")
    ap.add_argument("--prompt", default="", help="the run's prompt (a property)")
    ap.add_argument("--config", default="", help="the run's configuration file (a property)")
    ap.add_argument("--property", action="append", default=[], metavar="KEY=VALUE",
                    help="another property of the recording (repeatable)")
    args = ap.parse_args()

    stop = []
    signal.signal(signal.SIGINT, lambda *_: stop.append(1))
    signal.signal(signal.SIGTERM, lambda *_: stop.append(1))

    cameras = [n for n in args.cameras.split(",") if n]
    rr.init("chunkrt", recording_id=f"{args.namespace}-{os.getpid()}", spawn=False)
    rr.save(args.out, default_blueprint=layout(cameras))
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

    rec = Recorder(args)
    rec.charge(len(text) + 4 * CALL_BYTES)  # the properties and the blueprint
    node = c.node(f"chunkrt-record-{os.getpid()}")
    subs = {
        "js": c.subscriber(c.typed_service(node, c.joint_state_name(args.namespace), c.JointState)),
        "cmd": c.subscriber(c.typed_service(node, c.joint_command_name(args.namespace), c.JointCommand)),
        "status": c.subscriber(c.typed_service(node, c.status_name(args.namespace), c.ControllerStatus)),
        "chunks": c.subscriber(c.typed_service(node, c.chunks_name(args.namespace), c.ActionChunkMsg)),
    }
    cams = []
    for name in cameras:
        svc = c.camera_service(node, c.camera_name(args.namespace, name))
        cams.append((name, c.subscriber(svc, c.CAMERA_BUFFER_SIZE)))

    # statuses first (they bind the controller), then chunks (a command names the chunk it executes)
    kinds = [("status", c.ControllerStatus, rec.status), ("chunks", c.ActionChunkMsg, rec.chunk),
             ("js", c.JointState, rec.joint_state), ("cmd", c.JointCommand, rec.command)]
    start = time.monotonic()
    last_flush = start
    print(f"chunkrt_record: recording '{args.namespace}' into {args.out}", flush=True)
    while not stop and (args.duration <= 0 or time.monotonic() - start < args.duration):
        for key, ty, handle in kinds:
            for _ in range(4096):  # a flood cannot keep the loop from the other services
                sample = subs[key].receive()
                if sample is None:
                    break
                try:
                    origin, pid = origin_of(sample)
                    msg = ty.from_buffer_copy(sample.payload().contents)
                except Exception as e:  # noqa: BLE001
                    rec.error(key, e)
                    continue
                finally:
                    sample.delete()
                rec.take(key, handle, msg, origin, pid)
        for name, sub in cams:
            for _ in range(64):
                sample = sub.receive()
                if sample is None:
                    break
                try:
                    header = c.CameraFrameHeader.from_buffer_copy(sample.user_header().contents)
                    # one copy of the slice (bytes(slice) would read it a byte at a time through
                    # the Slice's __getitem__: 4.4 M calls, 70 % of the recorder's time, in 12 s)
                    payload = sample.payload()
                    pixels = ctypes.string_at(payload.as_ptr(), payload.len())
                except Exception as e:  # noqa: BLE001
                    rec.error("frame", e)
                    continue
                finally:
                    sample.delete()
                rec.take("frame", lambda m, o, p, name=name: rec.frame(name, *m), (header, pixels))
        now = time.monotonic()
        if now - last_flush > 0.2:
            rec.flush()
            last_flush = now
        time.sleep(0.0005)
    rec.flush()
    rr.disconnect()
    rec.counts["chunks_unbound"] = len(rec.pending)  # no controller's status ever claimed them
    counts = " ".join(f"{k}={v}" for k, v in rec.counts.items())
    print(f"chunkrt_record summary: {counts} out={args.out}", flush=True)
    if rec.rejected:
        print("chunkrt_record rejected: " + " ".join(f"{k}={v}" for k, v in sorted(rec.rejected.items())),
              flush=True)
    return 0 if rec.counts["commands"] > 0 else 1


if __name__ == "__main__":
    sys.exit(main())
