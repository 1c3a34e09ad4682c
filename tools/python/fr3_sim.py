#!/usr/bin/env python3
"""franka-sim (PyPI 1.1.7) on one loopback address, with its own count of reflexes.

franka-sim's command line binds the single arm to 0.0.0.0:1337 (and the Franka Hand to 1338);
FCI's port is fixed for libfranka, so tests that run side by side each take their own address
(127.0.0.x). This starts franka-sim's own server class on HOST with both of the FCI's checks
enforced by default (motion limits: position, velocity, acceleration, jerk; communication: 20
consecutive lost cycles) and the FCI's rule for a command that misses its cycle (dropped: the
robot's continuation stands; franka-sim itself applies it after the fact, `--late apply`), and
counts what the simulator itself logs:

  reflexes      every motion it aborted ("... -- aborting the motion": a reflex on a real FR3)
  violations    limit violations it only logged (with --no-enforce: what would have been one)
  lost_cycles   its reports of lost command cycles

Two of franka-sim's physics rules a real FR3's controller does not share are replaced (each with
a switch back): a late physics loop steps through the steps it missed with the commands of their
time instead of dropping them (`Steps`, --no-catch-up), and the position servo's velocity
feedforward is the robot's reference velocity per command instead of the target differenced over
physics steps (`ReferenceFeedforward`, --franka-feedforward). Both made the *measured* velocity
run up to twice a smooth command (reflexes against the envelope with the command at 0.6 of it).

Prints "franka-sim: ready HOST:PORT" once its simulation loop runs, and on SIGTERM / SIGINT /
--duration "franka-sim summary: reflexes=N violations=N lost_reports=N enforced=0|1" with how
often its own physics loop ran late (physics_late_*, physics_gap_max_ms: see `Steps`), the rule
for late commands and how many it dropped (late=, late_dropped=), and the first reasons.

  $CHUNKRT_FRANKA_PYTHON tools/python/fr3_sim.py --host 127.0.0.2 [--no-enforce]
  $CHUNKRT_FRANKA_PYTHON tools/python/fr3_sim.py --self-test   (`DropLate` on franka-sim's checker)
Needs FR3_MJCF (scripts/franka-env.sh) so that nothing is fetched from the network.
"""
import argparse
import logging
import os
import signal
import sys
import threading
import time


class Counter(logging.Handler):
    def __init__(self, host, port):
        super().__init__(level=logging.INFO)
        self.reflexes, self.violations, self.lost = 0, 0, 0
        self.reasons = []
        self.ready = threading.Event()
        self.where = f"{host}:{port}"

    def emit(self, record):
        try:
            msg = record.getMessage()
        except Exception:  # a malformed record must not take the server down
            return
        if "aborting the motion" in msg:
            self.reflexes += 1
            if len(self.reasons) < 8:
                self.reasons.append(msg[:240])
            # with the time (CLOCK_MONOTONIC, s): what the machine did then can be looked up
            print(f"franka-sim: REFLEX {msg[:240]} [t={time.monotonic():.4f}]", flush=True)
        elif "not enforced" in msg:
            self.violations += 1
            if len(self.reasons) < 8:
                self.reasons.append(msg[:240])
        elif "lost command cycle" in msg:
            self.lost += 1
        if not self.ready.is_set() and "simulation loop" in msg.lower():
            self.ready.set()
            print(f"franka-sim: ready {self.where}", flush=True)


def strict(f):
    """Scales franka-sim's joint motion limits by f where its checker reads them: the
    acceleration and jerk tables (imported by name into the checker) and the position-based
    velocity envelope (maximum velocity, deceleration) that its limit functions read."""
    from franka_sim.limits import checker, tables

    for mod in (checker, tables):
        for name in ("MAX_JOINT_ACCELERATION", "MAX_JOINT_JERK"):
            if not hasattr(mod, name):
                sys.exit(f"fr3_sim.py: franka-sim has no {mod.__name__}.{name} (its layout changed)")
            setattr(mod, name, tuple(f * x for x in getattr(mod, name)))
    env = getattr(tables, "POSITION_BASED_VELOCITY_LIMITS", None)
    if env is None:
        sys.exit("fr3_sim.py: franka-sim has no POSITION_BASED_VELOCITY_LIMITS (its layout changed)")
    tables.POSITION_BASED_VELOCITY_LIMITS = tuple(
        (f * vmax, offset, f * decel) for vmax, offset, decel in env)
    print(f"franka-sim: limits x {f}: acceleration {checker.MAX_JOINT_ACCELERATION[0]:.2f}, "
          f"jerk {checker.MAX_JOINT_JERK[0]:.0f}", flush=True)


def trace_events(path):
    """Debugging aid ($FR3_SIM_EVENTS=path): the checker's last 400 events (states published,
    cycles continued, commands absorbed) are written to `path` when it reports a violation."""
    import collections
    from franka_sim.limits import checker

    ring = collections.deque(maxlen=400)
    cls = checker.MotionLimitChecker
    orig_pub, orig_ext, orig_abs, orig_rep = (cls.note_published, cls.extrapolate,
                                              cls.absorb_command, cls.report)

    def hist(self):
        j = self._joint
        return [round(x, 9) for x in j.value], [round(x, 6) for x in j.first], [round(x, 3) for x in j.second]

    def note_published(self, published_id):
        ring.append((time.monotonic(), "published", published_id))
        return orig_pub(self, published_id)

    def extrapolate(self, message_id):
        out = orig_ext(self, message_id)
        ring.append((time.monotonic(), "extrapolated", message_id, self._applied_id, hist(self)))
        return out

    def absorb_command(self, command, joint_positions=None, *, fresh, enforce=False):
        cycles = self.cycles_since_applied(command)
        out = orig_abs(self, command, joint_positions, fresh=fresh, enforce=enforce)
        ring.append((time.monotonic(), "absorbed", command.get("message_id"), fresh, out.rewound,
                     out.recorded, cycles, [round(x, 9) for x in command["q_c"]],
                     out.violation.describe() if out.violation else None, hist(self)))
        return out

    def report(self, violation, *, enforced):
        # a copy first: list() of a deque holds the interpreter lock throughout, while iterating
        # the ring itself raced the other threads' appends (a dump cut short by "deque mutated
        # during iteration", in the thread that was reporting)
        events = list(ring)
        with open(path, "a") as f:
            f.write(f"--- violation {violation.describe()}\n")
            for e in events:
                f.write(repr(e) + "\n")
        return orig_rep(self, violation, enforced=enforced)

    cls.note_published, cls.extrapolate, cls.absorb_command, cls.report = (
        note_published, extrapolate, absorb_command, report)


class DropLate:
    """`--late drop`: a command that missed its cycle is dropped, as the FCI drops it ("If the <1 ms
    constraint is violated for a cycle, the packet is dropped by FCI", libfranka's network
    requirements): the robot's continuation of that cycle stands, the command reaches neither the
    limit checker's history nor the physics. franka-sim itself applies such a command after the
    fact (it rewinds its continuation and differences the command over the cycles since: its
    `MotionLimitChecker.rewind_extrapolation` says it is the one place it parts from the robot);
    `--late apply` keeps that (what a real FR3 never does). The cycle counts as lost either way
    (franka-sim's accounting).

    A motion's *first* command dropped: the robot holds its start (its reference stays `q_d`, at
    `dq_d`, `ddq_d`) and differences the next command against that, one cycle. franka-sim's checker
    extrapolates nothing before a first command is recorded, so it would take the next command as
    the motion's start, rebase it at zero velocity and charge the one after it a jerk of
    a / 1 ms: a conforming ramp from rest (3.3 then 4.6 rad/s^2) aborted with
    `joint_motion_generator_acceleration_discontinuity: 7917 rad/s^3` on the restarted robot of the
    takeover test. So the cycles up to the next command's are recorded as held at the start
    (`first_held`), just before that command is absorbed: not at the drop itself, where the publish
    thread may still be about to close the dropped cycle."""

    def __init__(self):
        from franka_sim.control_modes import ControlMode
        from franka_sim.franka_sim_server import FrankaSimServer
        from franka_sim.limits.checker import MotionLimitChecker

        self.dropped = 0
        self.first_held = 0
        orig = FrankaSimServer._absorb_within_motion_limits
        me = self
        pending = {}  # checker -> the motion whose first command was dropped

        def hold_start(chk, command):
            """The dropped first command's cycles, held at the start (lock held)."""
            if not (chk._active and chk._first_command and chk._mode is ControlMode.POSITION):
                return
            if pending.get(id(chk)) != chk._motion_id:
                return
            answered = int(command.get("message_id", 0))
            if chk._applied_id is not None and answered - 1 <= chk._applied_id:
                return
            pending.pop(id(chk), None)
            chk._first_command = False
            chk._applied_id = answered - 1
            chk._last_command = dict(command, q_c=list(chk._joint.value))
            me.first_held += 1

        orig_start = MotionLimitChecker.start_motion

        def start_motion(chk, *a, **k):
            pending.pop(id(chk), None)  # a new motion: nothing dropped in it yet
            return orig_start(chk, *a, **k)

        MotionLimitChecker.start_motion = start_motion

        def absorb(server, command, *, fresh):
            chk = server.motion_limits
            if not fresh:
                me.dropped += 1
                with chk._lock:
                    if chk._active and chk._first_command:
                        pending[id(chk)] = chk._motion_id
                return False  # the caller then neither records nor dispatches it
            with chk._lock:
                hold_start(chk, command)
            return orig(server, command, fresh=fresh)

        FrankaSimServer._absorb_within_motion_limits = absorb


class Steps:
    """The simulated robot's own computer: how often its physics loop (one state published, one
    control applied, one MuJoCo step per millisecond) ran late, and what it does then.

    franka-sim drops the steps a late loop missed and applies the newest command in the next one:
    the command has moved on by the stall's length while the arm has not, and its position servo
    differentiates the target over one step (`PositionFeedforward`), so a 10 ms stall commands
    ten times the velocity for a step and the measured velocity overshoots (seen: joint 5 at
    1.72 rad/s against an envelope of 1.45 while commanded well under it). A real FR3's
    controller does not stall. With `catch_up` (the default) a late loop first steps the
    physics through the steps it missed, each with the joint position command that was in force
    at its time (the commands' arrival times recorded), up to MAX_CATCH_UP steps; the arm is
    then where the robot's own 1 kHz controller would have taken it. The states the robot sent
    meanwhile were stale, as a real robot's lost states are; the lateness is still counted. The
    catch-up costs the physics thread the steps it missed, which makes its next gap longer (beside
    a busy loop, gaps past 1.5 ms in 3 runs of the blocked-joint test: 78-282 with it, 16-100
    without); at most MAX_CATCH_UP steps (20 ms) are caught up at once.

    **One clock** (`pace`, the default; `--no-pace` for franka-sim's own): franka-sim steps its
    physics on the wall clock and sends its states on a thread of its own that never bursts, so a
    starved sender makes the robot's cycles slower than its physics. Each command then stays in
    force for more than a millisecond of physics while the servo feeds the reference velocity
    forward, and the arm runs ahead of every command it is given (seen: joint 7 0.06 rad ahead at
    1.5 rad/s, its position moving 1.7 ms of physics per robot cycle, the robot sending 0.8 of
    real time). A real FR3 has one clock. So the physics waits while it is PACE_AHEAD steps ahead
    of the states sent (at most PACE_WAIT_S, then the clocks are re-aligned and the wall clock leads
    until the robot sends again), and catches up no further than the states sent."""

    MAX_CATCH_UP = 20
    #: How many steps the physics may run ahead of the states the robot has sent.
    PACE_AHEAD = 2
    #: The longest the physics waits for the robot's next state before it runs on (no session
    #: sending states, or one stalled: the robot's time is then the wall clock's again).
    PACE_WAIT_S = 0.004

    def __init__(self, catch_up=True, pace=True):
        import collections

        import mujoco
        from franka_sim import mujoco_franka_sim as m
        from franka_sim.control_modes import ControlMode

        self.last = None
        self.late = [0, 0, 0]  # gaps past 1.5, 2.5 and 5 ms
        self.worst = 0.0
        self.caught_up = 0  # physics steps run to catch up
        self.steps = 0  # physics steps, the loop's and the caught-up ones
        self.server = None  # set once the server exists: its states_sent is the robot's clock
        self.anchor = None  # (states_sent, steps) when the two clocks were last aligned
        self.paced = 0  # physics steps that waited for the robot's next state
        self.pace_released = 0  # waits given up (PACE_WAIT_S): the clocks re-aligned
        self.idle_at = None  # states_sent when a wait was given up, until the robot sends again
        self.commands = collections.deque(maxlen=256)  # (arrival, joint positions)
        cls = m.MujocoFrankaSim
        orig = cls._read_and_publish_state
        orig_update = cls.update_joint_positions
        me = self

        def update(sim, positions):
            orig_update(sim, positions)
            me.commands.append((time.perf_counter(), sim.latest_joint_positions))

        def robot_lead():
            """States sent past the physics' steps since the clocks were aligned (or None)."""
            server = me.server
            if server is None or not pace:
                return None
            sent = server.states_sent
            if me.anchor is None or sent < me.anchor[0]:  # a new session counts from 0
                me.anchor = (sent, me.steps)
            return (sent - me.anchor[0]) - (me.steps - me.anchor[1])

        def wait_for_robot():
            """Hold this step while the physics is PACE_AHEAD steps ahead of the robot's clock."""
            lead = robot_lead()
            if lead is None:
                return
            if me.server.states_sent == me.idle_at:
                # the robot sends no states (between sessions, a recovery): the wall clock leads
                me.anchor = (me.idle_at, me.steps)
                return
            me.idle_at = None
            if lead > -me.PACE_AHEAD:
                return
            give_up = time.perf_counter() + me.PACE_WAIT_S
            while robot_lead() <= -me.PACE_AHEAD:
                if time.perf_counter() > give_up:
                    me.idle_at = me.server.states_sent
                    me.anchor = (me.idle_at, me.steps)
                    me.pace_released += 1
                    return
                time.sleep(0.0001)
            me.paced += 1

        def catch_up_steps(sim, since, gap):
            missed = min(int(gap / sim.dt + 0.5) - 1, me.MAX_CATCH_UP)
            lead = robot_lead()
            if lead is not None:
                # no further than the states the robot has sent meanwhile
                missed = min(missed, lead)
            if missed <= 0 or sim.control_mode != ControlMode.POSITION:
                return
            history = list(me.commands)
            newest = sim.latest_joint_positions
            last_before = history[-1] if history else None
            for i in range(1, missed + 1):
                t = since + i * sim.dt
                target = None
                for arrival, q in history:
                    if arrival > t:
                        break
                    target = q
                if target is not None:
                    sim.latest_joint_positions = target
                sim._apply_control()
                mujoco.mj_step(sim.model, sim.data)
                me.caught_up += 1
                me.steps += 1
            # the newest command stands, or one that came while this ran
            after = me.commands[-1] if me.commands else None
            sim.latest_joint_positions = after[1] if after is not last_before else newest

        def publish(sim, *a, **k):
            waited = time.perf_counter()
            wait_for_robot()
            now = time.perf_counter()
            if me.last is not None and now - me.last < 1.0:  # (not the wait before the loop)
                # a wait for the robot's clock is not lateness of the physics
                gap = now - me.last - (now - waited)
                me.worst = max(me.worst, gap)
                for i, limit in enumerate((1.5e-3, 2.5e-3, 5e-3)):
                    me.late[i] += gap > limit
                if catch_up and gap > 1.5 * sim.dt:
                    catch_up_steps(sim, me.last, gap)
            me.last = now
            me.steps += 1  # the step the loop takes after this read
            return orig(sim, *a, **k)

        cls._read_and_publish_state = publish
        if catch_up:
            cls.update_joint_positions = update

    def summary(self):
        return (f"physics_late_1_5ms={self.late[0]} physics_late_2_5ms={self.late[1]} "
                f"physics_late_5ms={self.late[2]} physics_gap_max_ms={self.worst * 1e3:.1f} "
                f"physics_caught_up={self.caught_up} physics_paced={self.paced} "
                f"physics_pace_released={self.pace_released}")


class ReferenceFeedforward:
    """The position servo's velocity feedforward from the robot's own reference velocity.

    franka-sim's servo damps against `PositionFeedforward`: the target's difference over the
    physics steps since it last changed. Its network thread and its physics thread run on two
    ~1 kHz clocks of their own, and when two commands land between two physics steps the
    difference covers two commands in one step: the feedforward doubles for that step and is
    held through the next (seen: joint 4 measured at 1.94 rad/s for a command of 0.98 held
    within 0.1 % for 45 ms, the arm overtaking its command, a reflex at the envelope's 1.67
    with franka-sim's own loop never late past 4 ms). A real FR3's controller runs in the
    motion generator's cycle: its reference velocity is the command's, per cycle (`dq_d`).
    Here each command the limit checker takes as the motion's next sample registers its
    reference velocity (the checker's own, over the cycles the command covers) with the target
    it belongs to, before the target reaches the physics; a physics step that finds that
    target new takes that velocity. Anything else (a hold, a replayed echo, the catch-up's
    older targets) keeps franka-sim's rule."""

    def __init__(self):
        import numpy as np
        from franka_sim import mujoco_franka_sim as m
        from franka_sim.limits import checker
        from franka_sim.sim_common import PositionFeedforward

        self.used = 0
        me = self
        pending = {}
        orig_absorb = checker.MotionLimitChecker.absorb_command
        orig_update = m.MujocoFrankaSim.update_joint_positions
        orig_step = PositionFeedforward.step

        def absorb_command(chk, command, joint_positions=None, *, fresh, enforce=False):
            out = orig_absorb(chk, command, joint_positions, fresh=fresh, enforce=enforce)
            pending.clear()
            if out.recorded and out.violation is None:
                pending["ref"] = (np.array(command["q_c"], dtype=float),
                                  np.array(chk._joint.first, dtype=float))
            return out

        def update(sim, positions):
            ref = pending.pop("ref", None)
            ff = sim._position_feedforward
            with ff._lock:
                ff._reference = ref if ref is not None and np.array_equal(
                    ref[0], np.asarray(positions, dtype=float)) else None
            return orig_update(sim, positions)

        def step(ff, target, dt):
            target = np.asarray(target, dtype=float)
            with ff._lock:
                ref = getattr(ff, "_reference", None)
                if (ref is not None and ref[1].shape == target.shape
                        and not np.array_equal(target, ff.previous)
                        and np.array_equal(target, ref[0])):
                    ff.dq_c = ref[1].copy()
                    ff.previous = np.array(target, dtype=float)
                    ff._unchanged_steps = 0
                    me.used += 1
                    return ff.dq_c
            return orig_step(ff, target, dt)

        checker.MotionLimitChecker.absorb_command = absorb_command
        m.MujocoFrankaSim.update_joint_positions = update
        PositionFeedforward.step = step


def block(spec, t0):
    """`--block J,START,SECONDS`: an obstacle holds joint J (1..7) where it is from START to
    START + SECONDS (seconds after the simulator started): the arm does not follow its command
    (a contact, a person, a part in the way), and when the obstacle goes its position servo
    pulls the joint to wherever the command went meanwhile, the snap a driver must bound."""
    from franka_sim import mujoco_franka_sim as m

    try:
        j, start, secs = spec.split(",")
        j, start, secs = int(j), float(start), float(secs)
        if not (1 <= j <= 7 and start >= 0 and secs > 0):
            raise ValueError
    except ValueError:
        sys.exit(f"fr3_sim.py: --block {spec!r}: want JOINT,START_S,SECONDS (joint 1..7)")
    cls = m.MujocoFrankaSim
    orig = cls._apply_control
    held = {}

    def apply(sim):
        # the obstacle as a viscous brake on the joint (MuJoCo integrates joint damping
        # implicitly: stable at any value), 1e5 N·m·s/rad: under the FR3's 87 N·m the joint
        # creeps at 1 mrad/s; the rest of the arm keeps its own dynamics
        t = time.monotonic() - t0
        da = sim.arm_dofs_idx[j - 1]
        if start <= t < start + secs and "q" not in held:
            held["q"] = float(sim.data.qpos[sim.arm_qpos_adr[j - 1]])
            held["damping"] = float(sim.model.dof_damping[da])
            sim.model.dof_damping[da] = 1e5
            print(f"franka-sim: joint {j} blocked at {held['q']:.4f} rad", flush=True)
        elif t >= start + secs and "q" in held and "released" not in held:
            held["released"] = True
            sim.model.dof_damping[da] = held["damping"]
            print(f"franka-sim: joint {j} released", flush=True)
        orig(sim)

    cls._apply_control = apply


def self_test():
    """`--self-test`: `DropLate` against franka-sim's own checker and absorb path, no simulator.

    A joint-position motion from rest whose first command misses its cycle, then a conforming
    ramp (3.3, then 4.6 rad/s^2; jerk 3 333, then 1 250 rad/s^3): franka-sim's absorb with the
    late command only dropped must abort it (the check can fail), `DropLate` must not, and neither
    must a motion whose first command was on time. Prints one line per case; exit 1 on a wrong one.
    """
    import types

    from franka_sim.control_modes import ControlMode
    from franka_sim.franka_sim_server import FrankaSimServer
    from franka_sim.limits.checker import MotionLimitChecker

    start = [0.0, 0.0, 0.0, -1.57, 0.0, 1.57, 0.785]
    ramp = {5: 0.0, 6: 3.333e-6, 7: 1.125e-5, 8: 2.2e-5}  # the restarted robot's trace, joint 1
    plain = FrankaSimServer._absorb_within_motion_limits

    def only_dropped(server, command, *, fresh):
        return False if not fresh else plain(server, command, fresh=fresh)

    def run(first_late, absorb):
        aborted = []
        server = types.SimpleNamespace(
            motion_limits=MotionLimitChecker(enforce=True), enforce_motion_limits=True,
            robot_state=types.SimpleNamespace(state={"q": list(start)}),
            _extrapolated_reference=None, control_mode=ControlMode.POSITION,
            _latch_and_abort=lambda violation, _motion: aborted.append(violation))
        chk = server.motion_limits
        chk.report = lambda *_a, **_k: None
        chk.start_motion(ControlMode.POSITION, {"q": start, "q_d": start, "dq_d": [0.0] * 7,
                                                "ddq_d": [0.0] * 7}, motion_id=7)
        for m, d in ramp.items():
            chk.note_published(m + 1 if first_late and m == 5 else m)
            if m == 6 and first_late:
                chk.extrapolate(5)  # the publish thread closes the dropped cycle: nothing to do
            q = [x - d for x in start]
            command = {"message_id": m, "q_c": q, "motion_generation_finished": False}
            absorb(server, command, fresh=not (first_late and m == 5))
        return aborted

    drop = DropLate()
    cases = [("first command late, only dropped", run(True, only_dropped), True),
             ("first command late, DropLate", run(True, FrankaSimServer._absorb_within_motion_limits),
              False),
             ("first command on time, DropLate",
              run(False, FrankaSimServer._absorb_within_motion_limits), False)]
    wrong = 0
    for name, aborted, expected in cases:
        ok = bool(aborted) == expected
        wrong += not ok
        what = f"aborted: {aborted[0]}" if aborted else "no reflex"
        print(f"fr3_sim self-test: {name}: {what} ({'as expected' if ok else 'WRONG'})")
    print(f"fr3_sim self-test: first_held={drop.first_held}")
    return 1 if wrong else 0


def main():
    if sys.argv[1:] == ["--self-test"]:
        sys.exit(self_test())
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--host", default="127.0.0.1")
    ap.add_argument("--port", type=int, default=1337)
    ap.add_argument("--no-enforce", action="store_true",
                    help="log limit violations instead of aborting the motion")
    ap.add_argument("--no-gripper", action="store_true")
    ap.add_argument("--duration", type=float, default=None, help="stop after this many seconds")
    ap.add_argument("--log", default=None, help="franka-sim's own log (default: stderr, warnings only)")
    ap.add_argument("--model", default=None, help="the FR3 MJCF (default: $FR3_MJCF)")
    ap.add_argument("--realtime", type=int, default=0, metavar="PRIO",
                    help="run the simulator's threads at SCHED_FIFO priority PRIO (1..99; 0: no), as a "
                         "real FR3's controller runs on a real-time computer of its own; a machine "
                         "that refuses it is said on stdout and the simulator runs without")
    ap.add_argument("--strict", type=float, default=1.0, metavar="F",
                    help="a stricter robot: franka-sim's joint acceleration and jerk limits and its "
                         "velocity envelope (maximum velocity and deceleration) times F (0.5..1)")
    ap.add_argument("--late", choices=("apply", "drop"), default=os.environ.get("FR3_SIM_LATE", "drop"),
                    help="a command that missed its cycle: 'apply' it after the fact (franka-sim's own "
                         "choice) or 'drop' it, as the FCI does (default: $FR3_SIM_LATE, else drop)")
    ap.add_argument("--no-catch-up", action="store_true",
                    default=os.environ.get("FR3_SIM_NO_CATCH_UP", "") not in ("", "0"),
                    help="franka-sim's own rule for a late physics loop (the missed steps dropped, "
                         "the newest command applied at once) instead of stepping through them "
                         "with the commands of their time (see `Steps`)")
    ap.add_argument("--no-pace", action="store_true",
                    help="franka-sim's own physics clock (the wall clock) instead of the robot's "
                         "(the states it has sent; see `Steps`)")
    ap.add_argument("--franka-feedforward", action="store_true",
                    help="franka-sim's own velocity feedforward for its position servo (the target "
                         "differenced over physics steps) instead of the robot's reference velocity "
                         "per command (see `ReferenceFeedforward`)")
    ap.add_argument("--block", default=None, metavar="J,START,SECONDS",
                    help="an obstacle holds joint J (1..7) from START for SECONDS (seconds after "
                         "the simulator started): a joint that does not follow its command")
    args = ap.parse_args()
    t0 = time.monotonic()
    if not 0.5 <= args.strict <= 1.0:
        sys.exit(f"fr3_sim.py: --strict {args.strict}: must be within 0.5..1")
    if args.model:
        os.environ["FR3_MJCF"] = args.model
    if not os.environ.get("FR3_MJCF"):
        sys.exit("fr3_sim.py: set FR3_MJCF to the offline FR3 model (bash scripts/franka-env.sh)")

    if args.realtime:
        # before any thread starts: franka-sim's physics, state and command threads inherit it
        # (a starved physics thread steps late and its measured velocity jumps when it catches
        # up, a fault of the simulated robot's computer, not of the stream it is judging)
        try:
            os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(args.realtime))
            print(f"franka-sim: SCHED_FIFO priority {args.realtime}", flush=True)
            # the simulator's threads share one interpreter lock: a thread that wants it waits
            # for the holder's switch interval (5 ms by default), five of the robot's cycles
            sys.setswitchinterval(float(os.environ.get("FR3_SIM_SWITCH", "0.0002")))
        except (OSError, AttributeError, ValueError) as e:
            print(f"franka-sim: NOT real-time ({e}): a loaded machine can starve its physics",
                  flush=True)

    counter = Counter(args.host, args.port)
    root = logging.getLogger()
    root.setLevel(logging.INFO)
    root.addHandler(counter)
    sink = logging.FileHandler(args.log) if args.log else logging.StreamHandler(sys.stderr)
    sink.setLevel(logging.INFO if args.log else logging.WARNING)
    sink.setFormatter(logging.Formatter("%(asctime)s %(levelname)s %(name)s: %(message)s"))
    root.addHandler(sink)

    from franka_sim.franka_sim_server import FrankaSimServer

    if args.strict != 1.0:
        strict(args.strict)
    if os.environ.get("FR3_SIM_EVENTS"):
        trace_events(os.environ["FR3_SIM_EVENTS"])

    feedforward = None if args.franka_feedforward else ReferenceFeedforward()
    steps = Steps(catch_up=not args.no_catch_up, pace=not args.no_pace)
    drop = DropLate() if args.late == "drop" else None
    if drop:
        print("franka-sim: commands that miss their cycle are dropped, as the FCI drops them",
              flush=True)
    if args.block:
        block(args.block, t0)
    enforce = not args.no_enforce
    server = FrankaSimServer(host=args.host, port=args.port, enable_gripper=not args.no_gripper,
                             enforce_comm_constraints=enforce, enforce_motion_limits=enforce)
    steps.server = server
    done = threading.Event()

    def stop(*_):
        done.set()

    signal.signal(signal.SIGTERM, stop)
    signal.signal(signal.SIGINT, stop)
    runner = threading.Thread(target=server.start, daemon=True)
    runner.start()
    while not done.wait(0.1):
        if args.duration is not None and time.monotonic() - t0 > args.duration:
            break
        if not runner.is_alive():
            print("fr3_sim.py: the simulator's server stopped", file=sys.stderr, flush=True)
            break
    try:
        server.stop()
    except Exception as e:  # report, still print the summary
        print(f"fr3_sim.py: stop: {e}", file=sys.stderr)
    print(f"franka-sim summary: reflexes={counter.reflexes} violations={counter.violations} "
          f"lost_reports={counter.lost} enforced={int(enforce)} {steps.summary()} "
          f"late={args.late} late_dropped={drop.dropped if drop else 0} "
          f"first_held={drop.first_held if drop else 0} "
          f"reference_feedforward={feedforward.used if feedforward else -1}", flush=True)
    for r in counter.reasons:
        print(f"franka-sim reason: {r}", flush=True)
    sys.exit(0 if runner.is_alive() or done.is_set() or args.duration else 1)


if __name__ == "__main__":
    main()
