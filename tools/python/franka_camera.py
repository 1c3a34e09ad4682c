#!/usr/bin/env python3
"""The DROID setup's two views of the FR3, rendered from its joint states (headless MuJoCo).

Subscribes to the namespace's joint states (the Franka driver's: 7 joints, then the hand's
width), poses the same FR3 model that franka-sim simulates (FR3_MJCF, with the Franka Hand) on a
table with a few blocks, and publishes two camera services at --fps:

  exterior  a fixed camera beside the table looking at the arm (DROID's exterior_image_1_left)
  wrist     a camera on the hand looking along the fingers (DROID's wrist_image_left)

as the robot configuration's first two [[cameras]] (config/franka_fr3.toml: base_0_rgb and
left_wrist_0_rgb, which the droid layout maps to observation/exterior_image_1_left and
observation/wrist_image_left). Frames are RGB8 at the configured size, stamped with the
measurement time of the joint state they show.

  $CHUNKRT_FRANKA_PYTHON tools/python/franka_camera.py --config config/franka_fr3.toml \\
      --namespace NS [--fps 15] [--duration S]
Prints "franka-camera summary: frames=N render_ms_p50=... render_ms_p99=..." at the end.
"""
import argparse
import ctypes
import os
import re
import signal
import sys
import time
import tomllib

sys.path.insert(0, os.path.join(os.path.dirname(os.path.abspath(__file__)), "..", "..", "ipc", "python"))
import chunkrt_ipc as c  # noqa: E402

SCENE = """
    <light pos="0.6 -0.8 2.2" dir="-0.2 0.3 -1" diffuse="0.8 0.8 0.8"/>
    <light pos="-0.5 0.6 2.0" dir="0.3 -0.2 -1" diffuse="0.4 0.4 0.4"/>
    <geom name="chunkrt_floor" type="plane" pos="0 0 -0.75" size="3 3 0.01" rgba="0.55 0.55 0.58 1" contype="0" conaffinity="0"/>
    <geom name="chunkrt_table" type="box" pos="0.35 0 -0.2" size="0.6 0.7 0.2" rgba="0.62 0.48 0.33 1" contype="0" conaffinity="0"/>
    <geom name="chunkrt_red" type="box" pos="0.55 -0.15 0.025" size="0.025 0.025 0.025" rgba="0.85 0.1 0.1 1" contype="0" conaffinity="0"/>
    <geom name="chunkrt_blue" type="box" pos="0.45 0.2 0.025" size="0.025 0.025 0.025" rgba="0.1 0.2 0.85 1" contype="0" conaffinity="0"/>
    <geom name="chunkrt_bowl" type="cylinder" pos="0.65 0.05 0.01" size="0.06 0.01" rgba="0.9 0.9 0.85 1" contype="0" conaffinity="0"/>
    <camera name="exterior" pos="1.2 -0.8 0.75" xyaxes="0.55 0.83 0 -0.38 0.25 0.89" fovy="55"/>
"""
# on the hand, beside the fingers, looking along them (the hand's z) at what they grasp
WRIST = '<camera name="wrist" pos="-0.075 0 0.03" xyaxes="0 1 0 0.96 0 -0.28" fovy="80"/>'


def write_png(path, rgb):
    """An RGB8 array (H x W x 3) as a PNG file (zlib, no filter; no imaging package needed)."""
    import struct
    import zlib

    h, w, _ = rgb.shape
    rows = b"".join(b"\x00" + rgb[y].tobytes() for y in range(h))

    def chunk(kind, data):
        body = kind + data
        return struct.pack(">I", len(data)) + body + struct.pack(">I", zlib.crc32(body) & 0xFFFFFFFF)

    with open(path, "wb") as f:
        f.write(b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", struct.pack(">IIBBBBB", w, h, 8, 2, 0, 0, 0))
                + chunk(b"IDAT", zlib.compress(rows, 6)) + chunk(b"IEND", b""))


def scene_model(path):
    import mujoco

    xml = open(path).read()
    mesh_dir = os.path.join(os.path.dirname(os.path.abspath(path)), "meshes")
    xml, n = re.subn(r'meshdir="[^"]*"', f'meshdir="{mesh_dir}"', xml, count=1)
    if n != 1:
        raise SystemExit(f"franka_camera.py: {path} has no meshdir")
    xml = xml.replace("<worldbody>", "<worldbody>" + SCENE, 1)
    xml, n = re.subn(r'(<body name="hand"[^>]*>)', r"\1" + WRIST, xml, count=1)
    if n != 1:
        raise SystemExit(f"franka_camera.py: {path} has no body 'hand' for the wrist camera")
    return mujoco.MjModel.from_xml_string(xml)


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--config", required=True)
    ap.add_argument("--namespace", default=None)
    ap.add_argument("--model", default=os.environ.get("FR3_MJCF"))
    ap.add_argument("--fps", type=float, default=15.0)
    ap.add_argument("--duration", type=float, default=None)
    ap.add_argument("--snapshot", default=None, metavar="DIR",
                    help="render both views at the FR3's start pose into DIR/*.png and exit")
    args = ap.parse_args()
    if not args.model:
        sys.exit("franka_camera.py: set FR3_MJCF or --model (bash scripts/franka-env.sh)")
    if not 0.5 <= args.fps <= 60:
        sys.exit("franka_camera.py: --fps must be within 0.5..60")
    os.environ.setdefault("MUJOCO_GL", "egl")
    import mujoco
    import numpy as np

    with open(args.config, "rb") as f:
        cfg = tomllib.load(f)
    ns = args.namespace or cfg["robot"]["namespace"]
    cams = cfg.get("cameras", [])[:2]
    if len(cams) != 2:
        sys.exit("franka_camera.py: the configuration needs two [[cameras]] (exterior, wrist)")

    model = scene_model(args.model)
    data = mujoco.MjData(model)
    arm = [model.joint(f"fr3_joint{i}").qposadr[0] for i in range(1, 8)]
    fingers = [model.joint(n).qposadr[0] for n in ("finger_joint1", "finger_joint2")]
    views = []
    for cam_cfg, cam in zip(cams, ("exterior", "wrist")):
        w, h = int(cam_cfg["width"]), int(cam_cfg["height"])
        views.append((cam_cfg["name"], model.camera(cam).id, mujoco.Renderer(model, height=h, width=w), w, h))
    # the collision meshes drawn as their convex hulls, without shadows, reflections or skybox:
    # ~11 ms a view in software EGL on this 2-core box, against ~190 ms for the visual meshes
    # with shadows (~43 ms without): two views at 15 fps fit beside the control loop
    opt = mujoco.MjvOption()
    opt.geomgroup[2] = 0
    opt.geomgroup[3] = 1
    opt.flags[mujoco.mjtVisFlag.mjVIS_CONVEXHULL] = 1
    quiet = (mujoco.mjtRndFlag.mjRND_SHADOW, mujoco.mjtRndFlag.mjRND_REFLECTION,
             mujoco.mjtRndFlag.mjRND_SKYBOX)

    if args.snapshot:
        start = [0.0, 0.0, 0.0, -1.57, 0.0, 1.57, 0.785]
        for a, q in zip(arm, start):
            data.qpos[a] = q
        for a in fingers:
            data.qpos[a] = 0.04
        mujoco.mj_forward(model, data)
        os.makedirs(args.snapshot, exist_ok=True)
        for name, cam_id, renderer, w, h in views:
            renderer.update_scene(data, camera=cam_id, scene_option=opt)
            for f in quiet:
                renderer.scene.flags[f] = 0
            write_png(os.path.join(args.snapshot, f"{name}.png"), renderer.render())
            renderer.close()
        print(f"franka_camera.py: wrote {len(views)} views to {args.snapshot}")
        return

    node = c.node("chunkrt-franka-camera")
    js_sub = c.subscriber(c.typed_service(node, c.joint_state_name(ns), c.JointState))
    pubs = [
        c.camera_service(node, c.camera_name(ns, name))
        .publisher_builder()
        .initial_max_slice_len(w * h * 3)
        .max_loaned_samples(c.PUBLISHER_MAX_LOANED_SAMPLES)
        .create()
        for name, _, _, w, h in views
    ]

    stop = []
    signal.signal(signal.SIGTERM, lambda *_: stop.append(1))
    signal.signal(signal.SIGINT, lambda *_: stop.append(1))
    period = 1.0 / args.fps
    t0 = time.monotonic()
    next_t = t0
    latest = None
    frames, seq, render_ms = 0, 0, []
    while not stop:
        if args.duration is not None and time.monotonic() - t0 > args.duration:
            break
        while True:
            s = js_sub.receive()
            if s is None:
                break
            latest = c.JointState.from_buffer_copy(s.payload().contents)
            s.delete()
        now = time.monotonic()
        if now < next_t or latest is None:
            time.sleep(min(0.005, max(0.0, next_t - now)))
            continue
        next_t += period
        if next_t < now:
            next_t = now + period
        n = min(latest.n_dof, 8)
        for i in range(min(n, 7)):
            data.qpos[arm[i]] = latest.position[i]
        if n == 8:  # the hand's width, shared by the two fingers
            for a in fingers:
                data.qpos[a] = min(max(latest.position[7] / 2.0, 0.0), 0.04)
        mujoco.mj_forward(model, data)
        seq += 1
        for index, ((name, cam_id, renderer, w, h), pub) in enumerate(zip(views, pubs)):
            r0 = time.perf_counter()
            renderer.update_scene(data, camera=cam_id, scene_option=opt)
            for f in quiet:
                renderer.scene.flags[f] = 0
            rgb = np.ascontiguousarray(renderer.render())
            render_ms.append((time.perf_counter() - r0) * 1e3)
            frame = pub.loan_slice_uninit(w * h * 3)
            ctypes.memmove(frame.payload_ptr, rgb.ctypes.data, w * h * 3)
            hdr = c.CameraFrameHeader(
                seq=seq, capture_time_ns=latest.measurement_time_ns, publish_time_ns=c.monotonic_ns(),
                camera_id=index, encoding=c.ENCODING_RGB8, width=w, height=h, stride=w * 3)
            ctypes.memmove(frame.user_header_ptr, ctypes.byref(hdr), ctypes.sizeof(hdr))
            frame.assume_init().send()
            frames += 1
    for _, _, renderer, _, _ in views:
        renderer.close()
    views.clear()
    p = (lambda q: float(np.percentile(render_ms, q)) if render_ms else 0.0)
    print(f"franka-camera summary: frames={frames} render_ms_p50={p(50):.2f} render_ms_p99={p(99):.2f}",
          flush=True)


if __name__ == "__main__":
    main()
