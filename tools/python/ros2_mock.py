#!/usr/bin/env python3
"""A ros2_control robot on ROS 2's wire, without ROS 2: the test peer of `chunkrt ros2`.

What a robot under ros2_control with `mock_components/GenericSystem` shows on its topics, spoken
as rmw_cyclonedds does (Cyclone DDS, ROS 2's naming on DDS: topic `rt/<name>`, type
`<pkg>::msg::dds_::<Type>_`):

- `joint_state_broadcaster`: `sensor_msgs/JointState` on /joint_states at --rate-hz, stamped
  with the system clock, the joints in an order of its own plus one joint the bridge is not told
  about (it must match by name and ignore extras);
- `forward_position_controller`: `std_msgs/Float64MultiArray` on its commands topic, one value
  per joint, a message of another length refused as the real controller does; or
  `joint_trajectory_controller` (--mode trajectory): a `trajectory_msgs/JointTrajectory` whose
  first point is taken;
- GenericSystem: a command becomes the state at the next read, within the joint's limits.

The message layouts are checked against ROS 2's own definitions first: rosbags' Humble and Jazzy
type stores must serialise the same message to the same bytes as the peer sends.

--inject KIND@SECONDS[:DURATION] puts bad input on the wire for a while (the bridge's boundary
tests): missing, repeated, length, nan, noname (broken JointStates instead of good ones), flood
(10 000 JointStates as fast as they go), vanish (no JointStates), foreign (a second publisher on
the command topic), otherdomain (a robot with other joints on another DDS domain, all along).

Prints `ros2_mock summary: key=value ...` at the end.
"""

import argparse
import math
import os
import sys
import time
import tomllib
from dataclasses import dataclass

LOOPBACK_XML = (
    "<CycloneDDS><Domain id=\"any\"><General><Interfaces>"
    "<NetworkInterface address=\"127.0.0.1\"/></Interfaces>"
    "<AllowMulticast>false</AllowMulticast></General>"
    "<Discovery><ParticipantIndex>auto</ParticipantIndex>"
    "<MaxAutoParticipantIndex>40</MaxAutoParticipantIndex>"
    "<Peers><Peer address=\"127.0.0.1\"/></Peers></Discovery></Domain></CycloneDDS>"
)


def parse_args():
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--config", required=True, help="the robot's chunkrt configuration (TOML)")
    p.add_argument("--domain-id", type=int, required=True)
    p.add_argument("--rate-hz", type=float, default=500.0)
    p.add_argument("--duration", type=float, default=10.0)
    p.add_argument("--mode", choices=["forward", "trajectory"], default=None,
                   help="default: the configuration's ros2.command")
    p.add_argument("--loopback", action="store_true",
                   help="keep Cyclone DDS on 127.0.0.1 with a unicast peer (no multicast)")
    p.add_argument("--inject", action="append", default=[],
                   help="KIND@SECONDS[:DURATION], see the module's documentation")
    p.add_argument("--initial", default=None, help="initial positions, comma separated")
    p.add_argument("--camera-hz", type=float, default=30.0,
                   help="rate of each [[ros2.cameras]] topic: rgb8 Images (rows padded by 16 "
                        "bytes) or JPEG CompressedImages of the [[cameras]] size")
    return p.parse_args()


def idl_types():
    from cyclonedds.idl import IdlStruct
    from cyclonedds.idl.types import float64, int32, sequence, uint8, uint32

    @dataclass
    class Time(IdlStruct, typename="builtin_interfaces::msg::dds_::Time_"):
        sec: int32
        nanosec: uint32

    @dataclass
    class Duration(IdlStruct, typename="builtin_interfaces::msg::dds_::Duration_"):
        sec: int32
        nanosec: uint32

    @dataclass
    class Header(IdlStruct, typename="std_msgs::msg::dds_::Header_"):
        stamp: Time
        frame_id: str

    @dataclass
    class JointState(IdlStruct, typename="sensor_msgs::msg::dds_::JointState_"):
        header: Header
        name: sequence[str]
        position: sequence[float64]
        velocity: sequence[float64]
        effort: sequence[float64]

    @dataclass
    class MultiArrayDimension(IdlStruct, typename="std_msgs::msg::dds_::MultiArrayDimension_"):
        label: str
        size: uint32
        stride: uint32

    @dataclass
    class MultiArrayLayout(IdlStruct, typename="std_msgs::msg::dds_::MultiArrayLayout_"):
        dim: sequence[MultiArrayDimension]
        data_offset: uint32

    @dataclass
    class Float64MultiArray(IdlStruct, typename="std_msgs::msg::dds_::Float64MultiArray_"):
        layout: MultiArrayLayout
        data: sequence[float64]

    @dataclass
    class JointTrajectoryPoint(IdlStruct, typename="trajectory_msgs::msg::dds_::JointTrajectoryPoint_"):
        positions: sequence[float64]
        velocities: sequence[float64]
        accelerations: sequence[float64]
        effort: sequence[float64]
        time_from_start: Duration

    @dataclass
    class JointTrajectory(IdlStruct, typename="trajectory_msgs::msg::dds_::JointTrajectory_"):
        header: Header
        joint_names: sequence[str]
        points: sequence[JointTrajectoryPoint]

    @dataclass
    class String(IdlStruct, typename="std_msgs::msg::dds_::String_"):
        data: str

    # Images: `bytes` serialises a sequence<uint8> in one copy (the element-wise sequence[uint8]
    # takes 26 ms for 640x480x3), but Cyclone cannot build the topic's type object from it; the
    # topic is made with sequence[uint8] and the sample serialised by the `bytes` twin (the same
    # bytes: checked against rosbags below).
    @dataclass
    class ImageWire(IdlStruct, typename="sensor_msgs::msg::dds_::Image_"):
        header: Header
        height: uint32
        width: uint32
        encoding: str
        is_bigendian: uint8
        step: uint32
        data: bytes

    @dataclass
    class Image(IdlStruct, typename="sensor_msgs::msg::dds_::Image_"):
        header: Header
        height: uint32
        width: uint32
        encoding: str
        is_bigendian: uint8
        step: uint32
        data: sequence[uint8]

        def serialize(self, *args, **kw):
            return ImageWire(self.header, self.height, self.width, self.encoding,
                             self.is_bigendian, self.step, bytes(self.data)).serialize(*args, **kw)

    @dataclass
    class CompressedImageWire(IdlStruct, typename="sensor_msgs::msg::dds_::CompressedImage_"):
        header: Header
        format: str
        data: bytes

    @dataclass
    class CompressedImage(IdlStruct, typename="sensor_msgs::msg::dds_::CompressedImage_"):
        header: Header
        format: str
        data: sequence[uint8]

        def serialize(self, *args, **kw):
            return CompressedImageWire(self.header, self.format, bytes(self.data)).serialize(*args, **kw)

    return dict(Time=Time, Duration=Duration, Header=Header, JointState=JointState,
                MultiArrayDimension=MultiArrayDimension, MultiArrayLayout=MultiArrayLayout,
                Float64MultiArray=Float64MultiArray, JointTrajectoryPoint=JointTrajectoryPoint,
                JointTrajectory=JointTrajectory, String=String, Image=Image,
                CompressedImage=CompressedImage)


def check_layouts(T):
    """The peer's messages serialise as ROS 2's own definitions do (rosbags, Humble and Jazzy)."""
    import numpy as np
    from rosbags.typesys import Stores, get_typestore

    js = T["JointState"](T["Header"](T["Time"](12, 345), "base"), ["a", "bb"], [1.5, -2.0],
                         [0.25, 0.0], [])
    fa = T["Float64MultiArray"](T["MultiArrayLayout"]([T["MultiArrayDimension"]("x", 2, 2)], 0),
                                [0.5, -0.5])
    jt = T["JointTrajectory"](T["Header"](T["Time"](1, 2), ""), ["a", "bb"], [
        T["JointTrajectoryPoint"]([1.0, 2.0], [0.1, 0.2], [], [], T["Duration"](0, 20_000_000))])
    f64 = lambda v: np.array(v, dtype=np.float64)  # noqa: E731
    for store in (Stores.ROS2_HUMBLE, Stores.ROS2_JAZZY):
        ts = get_typestore(store)
        t = ts.types
        r_js = t["sensor_msgs/msg/JointState"](
            header=t["std_msgs/msg/Header"](stamp=t["builtin_interfaces/msg/Time"](sec=12, nanosec=345),
                                            frame_id="base"),
            name=["a", "bb"], position=f64([1.5, -2.0]), velocity=f64([0.25, 0.0]), effort=f64([]))
        r_fa = t["std_msgs/msg/Float64MultiArray"](
            layout=t["std_msgs/msg/MultiArrayLayout"](
                dim=[t["std_msgs/msg/MultiArrayDimension"](label="x", size=2, stride=2)], data_offset=0),
            data=f64([0.5, -0.5]))
        r_jt = t["trajectory_msgs/msg/JointTrajectory"](
            header=t["std_msgs/msg/Header"](stamp=t["builtin_interfaces/msg/Time"](sec=1, nanosec=2),
                                            frame_id=""),
            joint_names=["a", "bb"],
            points=[t["trajectory_msgs/msg/JointTrajectoryPoint"](
                positions=f64([1.0, 2.0]), velocities=f64([0.1, 0.2]), accelerations=f64([]),
                effort=f64([]),
                time_from_start=t["builtin_interfaces/msg/Duration"](sec=0, nanosec=20_000_000))])
        im = T["Image"](T["Header"](T["Time"](3, 4), "cam"), 2, 3, "rgb8", 0, 10, bytes(range(20)))
        r_im = t["sensor_msgs/msg/Image"](
            header=t["std_msgs/msg/Header"](stamp=t["builtin_interfaces/msg/Time"](sec=3, nanosec=4),
                                            frame_id="cam"),
            height=2, width=3, encoding="rgb8", is_bigendian=0, step=10,
            data=np.frombuffer(bytes(range(20)), dtype=np.uint8))
        ci = T["CompressedImage"](T["Header"](T["Time"](3, 4), ""), "jpeg", b"\xff\xd8\xff")
        r_ci = t["sensor_msgs/msg/CompressedImage"](
            header=t["std_msgs/msg/Header"](stamp=t["builtin_interfaces/msg/Time"](sec=3, nanosec=4),
                                            frame_id=""),
            format="jpeg", data=np.frombuffer(b"\xff\xd8\xff", dtype=np.uint8))
        for ours, theirs, name in ((im, r_im, "sensor_msgs/msg/Image"),
                                   (ci, r_ci, "sensor_msgs/msg/CompressedImage"),
                                   (js, r_js, "sensor_msgs/msg/JointState"),
                                   (fa, r_fa, "std_msgs/msg/Float64MultiArray"),
                                   (jt, r_jt, "trajectory_msgs/msg/JointTrajectory")):
            a = bytes(ours.serialize())
            b = bytes(ts.serialize_cdr(theirs, name))
            if a != b:
                sys.exit(f"ros2_mock: {name} does not serialise as {store.name} defines it:\n"
                         f"  cyclonedds {a.hex()}\n  rosbags    {b.hex()}")
    return "humble,jazzy"


def pct(xs, q):
    if not xs:
        return 0.0
    s = sorted(xs)
    return s[min(len(s) - 1, int(q * len(s)))]


STOP = []


def main():
    import signal
    # SIGINT / SIGTERM end the loop and still print the summary
    for sig in (signal.SIGINT, signal.SIGTERM):
        signal.signal(sig, lambda *_: STOP.append(1))
    a = parse_args()
    if a.loopback:
        os.environ["CYCLONEDDS_URI"] = LOOPBACK_XML
    with open(a.config, "rb") as f:
        cfg = tomllib.load(f)
    joints = cfg["robot"]["joints"]
    r2 = cfg.get("ros2", {})
    names = r2.get("joints") or [j["name"] for j in joints]
    lo = [j["position_min"] for j in joints]
    hi = [j["position_max"] for j in joints]
    pos = [j.get("initial_position", 0.0) for j in joints]
    if a.initial:
        pos = [float(v) for v in a.initial.split(",")]
    n = len(names)
    arm = [i for i, j in enumerate(joints) if not j.get("step", False)]
    mode = a.mode or r2.get("command", "forward")
    cmd_topic = r2.get("command_topic") or (
        "/forward_position_controller/commands" if mode == "forward"
        else "/joint_trajectory_controller/joint_trajectory")
    state_topic = r2.get("joint_states_topic", "/joint_states")
    # a gripper on a topic of its own: the step joints there, the others on the command topic
    gripper_topic = r2.get("gripper_topic", "")
    grip_idx = [i for i, j in enumerate(joints) if j.get("step", False)] if gripper_topic else []
    cmd_idx = [i for i in range(n) if i not in grip_idx]
    injects = []
    for spec in a.inject:
        kind, _, when = spec.partition("@")
        start, _, dur = when.partition(":")
        injects.append((kind, float(start or 0), float(dur or 0.5)))

    T = idl_types()
    stores = check_layouts(T)

    from cyclonedds.core import Policy, Qos
    from cyclonedds.domain import DomainParticipant
    from cyclonedds.pub import DataWriter
    from cyclonedds.sub import DataReader
    from cyclonedds.topic import Topic
    from cyclonedds.util import duration

    sensor = Qos(Policy.Reliability.BestEffort, Policy.History.KeepLast(5),
                 Policy.Durability.Volatile)
    reliable = Qos(Policy.Reliability.Reliable(duration(milliseconds=100)),
                   Policy.History.KeepLast(10), Policy.Durability.Volatile)
    dp = DomainParticipant(a.domain_id)
    dds = lambda t: "rt" + t  # noqa: E731  ROS 2's topic prefix on DDS
    js_topic = Topic(dp, dds(state_topic), T["JointState"])
    js_writer = DataWriter(dp, js_topic, qos=sensor)
    ctype = T["Float64MultiArray"] if mode == "forward" else T["JointTrajectory"]
    c_topic = Topic(dp, dds(cmd_topic), ctype)
    c_reader = DataReader(dp, c_topic, qos=reliable)
    g_reader = None
    if gripper_topic:
        g_reader = DataReader(dp, Topic(dp, dds(gripper_topic), T["Float64MultiArray"]), qos=reliable)
    gripper_commands = 0
    foreign_writer = None
    if any(k == "foreign" for k, _, _ in injects):
        dp2 = DomainParticipant(a.domain_id)
        foreign_writer = DataWriter(dp2, Topic(dp2, dds(cmd_topic), ctype), qos=reliable)
    other_writer = None
    if any(k == "otherdomain" for k, _, _ in injects):
        dpo = DomainParticipant((a.domain_id + 1) % 233)
        other_writer = DataWriter(dpo, Topic(dpo, dds(state_topic), T["JointState"]), qos=sensor)
    # the chunk and status topics the bridge publishes (counted, and their layouts read back)
    chunk_reader = status_reader = None
    if r2.get("chunk_topic", "/chunkrt/predicted_chunk"):
        chunk_reader = DataReader(dp, Topic(dp, dds(r2.get("chunk_topic", "/chunkrt/predicted_chunk")),
                                            T["JointTrajectory"]), qos=reliable)
    if r2.get("status_topic", "/chunkrt/status"):
        status_reader = DataReader(dp, Topic(dp, dds(r2.get("status_topic", "/chunkrt/status")),
                                             T["String"]), qos=reliable)

    # cameras: a few frames made up front (a moving gradient), sent in turn
    cams = []
    for rc in r2.get("cameras", []):
        import io
        import numpy as np
        sc = next(c for c in cfg.get("cameras", []) if c["name"] == rc["name"])
        w, h = sc["width"], sc["height"]
        frames = []
        for k in range(8):
            img = np.zeros((h, w, 3), dtype=np.uint8)
            img[:, :, 0] = (np.arange(w)[None, :] * 255 // max(1, w - 1) + 32 * k) % 256
            img[:, :, 1] = (np.arange(h)[:, None] * 255 // max(1, h - 1))
            img[:, :, 2] = 40 * k
            if rc.get("compressed", False):
                from PIL import Image as PILImage
                buf = io.BytesIO()
                PILImage.fromarray(img).save(buf, format="JPEG", quality=85)
                frames.append(buf.getvalue())
            else:
                step = w * 3 + 16
                padded = np.zeros((h, step), dtype=np.uint8)
                padded[:, : w * 3] = img.reshape(h, w * 3)
                frames.append((step, padded.tobytes()))
        ty = T["CompressedImage"] if rc.get("compressed", False) else T["Image"]
        writer = DataWriter(dp, Topic(dp, dds(rc["topic"]), ty), qos=sensor)
        cams.append(dict(name=rc["name"], w=w, h=h, compressed=rc.get("compressed", False),
                         frames=frames, writer=writer, sent=0, bad=0))
    next_frame = time.monotonic()

    def send_frames(bad):
        for c in cams:
            ns_ = time.time_ns()
            hdr = T["Header"](T["Time"](ns_ // 1_000_000_000, ns_ % 1_000_000_000), c["name"])
            f = c["frames"][c["sent"] % len(c["frames"])]
            if c["compressed"]:
                data = f if not bad else f[: len(f) // 3]  # a cut JPEG
                c["writer"].write(T["CompressedImage"](hdr, "jpeg", data))
            else:
                step, data = f
                w, h, enc = c["w"], c["h"], "rgb8"
                if bad:
                    kind = c["bad"] % 4
                    if kind == 0:
                        enc = "rgba8"                      # an encoding it is not
                    elif kind == 1:
                        step = c["w"] * 3 - 1              # rows shorter than the pixels
                    elif kind == 2:
                        data = data[:-1]                   # a byte missing
                    else:
                        w, h = 100_000, 1_000              # claims 300 MB
                c["writer"].write(T["Image"](hdr, h, w, enc, 0, step, data))
            if bad:
                c["bad"] += 1
            else:
                c["sent"] += 1

    # the broadcaster's order: reversed, with a joint the bridge is not told about in the middle
    order = list(range(n))[::-1]
    extra = "mock_extra_joint"

    def joint_state(p, v, names_override=None, pos_override=None):
        ns = time.time_ns()
        nm = [names[i] for i in order]
        ps = [p[i] for i in order]
        vs = [v[i] for i in order]
        nm.insert(1, extra)
        ps.insert(1, 0.0)
        vs.insert(1, 0.0)
        if names_override is not None:
            nm = names_override(nm)
        if pos_override is not None:
            ps = pos_override(ps)
        return T["JointState"](T["Header"](T["Time"](ns // 1_000_000_000, ns % 1_000_000_000), "mock"),
                               nm, ps, vs, [])

    period = 1.0 / a.rate_hz
    vel = [0.0] * n
    states = commands = bad_commands = clamped = limit_violations = 0
    answered = unanswered = 0
    latencies = []
    first_cmd_t = None
    mins = list(pos)
    maxs = list(pos)
    max_step = 0.0
    last_state_t = None
    got_answer = True
    foreign_sent = other_sent = flooded = injected = 0
    injected_by = {}
    vanished = 0
    chunks_seen = statuses_seen = 0
    chunk_points = 0
    t0 = time.monotonic()
    next_t = t0
    end = t0 + a.duration
    target = None
    while True:
        now = time.monotonic()
        if now >= end or STOP:
            break
        # wait for commands until the next tick, timing each on arrival
        while True:
            samples = c_reader.take(N=64)
            tnow = time.monotonic()
            for s in samples:
                if isinstance(s, ctype):
                    pass
                else:
                    continue
                if mode == "forward":
                    data = list(s.data)
                else:
                    data = list(s.points[0].positions) if s.points else []
                    want = [names[i] for i in cmd_idx]
                    if list(s.joint_names) != want:
                        # JTC matches by name
                        idx = {nm: i for i, nm in enumerate(s.joint_names)}
                        if all(nm in idx for nm in want):
                            data = [data[idx[nm]] for nm in want]
                        else:
                            data = []
                if len(data) != len(cmd_idx) or not all(math.isfinite(x) for x in data):
                    bad_commands += 1
                    continue
                commands += 1
                if first_cmd_t is None:
                    first_cmd_t = tnow
                full = list(target if target is not None else pos)
                for k, i in enumerate(cmd_idx):
                    full[i] = data[k]
                for i in cmd_idx:
                    if full[i] < lo[i] - 1e-12 or full[i] > hi[i] + 1e-12:
                        limit_violations += 1
                if target is not None:
                    max_step = max(max_step, max(abs(full[i] - target[i]) for i in arm))
                data = full
                target = data
                if last_state_t is not None and not got_answer:
                    latencies.append(tnow - last_state_t)
                    got_answer = True
            if g_reader is not None:
                for g in g_reader.take(N=16):
                    if not isinstance(g, T["Float64MultiArray"]):
                        continue
                    gd = list(g.data)
                    if len(gd) != len(grip_idx) or not all(math.isfinite(x) for x in gd):
                        bad_commands += 1
                        continue
                    gripper_commands += 1
                    full = list(target if target is not None else pos)
                    for k, i in enumerate(grip_idx):
                        if gd[k] < lo[i] - 1e-12 or gd[k] > hi[i] + 1e-12:
                            limit_violations += 1
                        full[i] = gd[k]
                    target = full
            if time.monotonic() >= next_t:
                break
            time.sleep(min(0.0005, max(0.0, next_t - time.monotonic())))
        next_t += period
        if time.monotonic() - next_t > 0.2:
            next_t = time.monotonic() + period  # far behind (a stalled machine): no burst
        for r, what in ((chunk_reader, "chunk"), (status_reader, "status")):
            if r is None:
                continue
            for s in r.take(N=16):
                if what == "chunk" and isinstance(s, T["JointTrajectory"]):
                    chunks_seen += 1
                    chunk_points += len(s.points)
                elif what == "status" and isinstance(s, T["String"]):
                    statuses_seen += 1
        # GenericSystem: the command becomes the state, within limits
        if target is not None:
            new = []
            for i in range(n):
                c = min(max(target[i], lo[i]), hi[i])
                if c != target[i]:
                    clamped += 1
                new.append(c)
            vel = [(new[i] - pos[i]) / period for i in range(n)]
            pos = new
        else:
            vel = [0.0] * n
        for i in range(n):
            mins[i] = min(mins[i], pos[i])
            maxs[i] = max(maxs[i], pos[i])
        el = time.monotonic() - t0
        active = [k for k, s0, d in injects if s0 <= el < s0 + d]
        if last_state_t is not None and first_cmd_t is not None and not got_answer:
            unanswered += 1
        msg = None
        if "vanish" in active:
            vanished += 1
        elif "missing" in active:
            msg = joint_state(pos, vel, names_override=lambda nm: [x if x != names[0] else "not_" + x for x in nm])
        elif "repeated" in active:
            msg = joint_state(pos, vel, names_override=lambda nm: nm[:-1] + [nm[0]])
        elif "length" in active:
            msg = joint_state(pos, vel, pos_override=lambda ps: ps[:-1])
        elif "nan" in active:
            msg = joint_state(pos, vel, pos_override=lambda ps: [float("nan")] + ps[1:])
        elif "noname" in active:
            msg = joint_state(pos, vel, names_override=lambda nm: [])
        else:
            msg = joint_state(pos, vel)
        if msg is not None:
            js_writer.write(msg)
            bad = [k for k in ("missing", "repeated", "length", "nan", "noname") if k in active]
            if bad:
                injected += 1
                injected_by[bad[0]] = injected_by.get(bad[0], 0) + 1
            else:
                states += 1
            last_state_t = time.monotonic()
            got_answer = first_cmd_t is None
        if cams and time.monotonic() >= next_frame:
            send_frames("badimage" in active)
            next_frame += 1.0 / a.camera_hz
            if time.monotonic() - next_frame > 0.2:
                next_frame = time.monotonic() + 1.0 / a.camera_hz
        if "flood" in active and not flooded:
            for _ in range(10_000):
                js_writer.write(joint_state(pos, vel))
            flooded = 10_000
        if foreign_writer is not None and "foreign" in active:
            if mode == "forward":
                foreign_writer.write(T["Float64MultiArray"](T["MultiArrayLayout"]([], 0), list(pos)))
            else:
                foreign_writer.write(T["JointTrajectory"](T["Header"](T["Time"](0, 0), ""), list(names), []))
            foreign_sent += 1
        if other_writer is not None:
            other_writer.write(T["JointState"](T["Header"](T["Time"](0, 0), ""), ["x", "y"], [math.nan, 1e9], [], []))
            other_sent += 1

    rng = [maxs[i] - mins[i] for i in range(n)]
    print(
        "ros2_mock summary: "
        f"layouts={stores} mode={mode} rate_hz={a.rate_hz:g} states={states} injected={injected} "
        f"flooded={flooded} foreign_sent={foreign_sent} other_domain_sent={other_sent} "
        f"commands={commands} bad_commands={bad_commands} answered={len(latencies)} "
        f"unanswered={unanswered} "
        f"latency_p50_us={pct(latencies, 0.5) * 1e6:.1f} latency_p99_us={pct(latencies, 0.99) * 1e6:.1f} "
        f"latency_max_us={(max(latencies) if latencies else 0) * 1e6:.1f} "
        f"first_command_s={(first_cmd_t - t0) if first_cmd_t else -1:.3f} "
        f"clamped={clamped} limit_violations={limit_violations} max_arm_step={max_step:.6f} "
        f"range_max={max(rng):.4f} range=" + ",".join(f"{x:.4f}" for x in rng) + " "
        f"final=" + ",".join(f"{x:.4f}" for x in pos) + " "
        f"chunks_seen={chunks_seen} chunk_points={chunk_points} statuses_seen={statuses_seen} "
        f"vanished_ticks={vanished} gripper_commands={gripper_commands} "
        f"frames_sent={sum(c['sent'] for c in cams)} bad_images_sent={sum(c['bad'] for c in cams)} "
        + " ".join(f"injected_{k}={injected_by.get(k, 0)}"
                   for k in ("missing", "repeated", "length", "nan", "noname")),
        flush=True,
    )


if __name__ == "__main__":
    main()
