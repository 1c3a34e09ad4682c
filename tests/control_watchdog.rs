//! Safety state machine: stale joint state, NaN actions, missing chunks and overrun streaks put
//! the executor in HOLD within the configured time, braking to zero velocity within the
//! limits; good inputs bring it back to RUNNING; HOLD for too long is a FAULT that only a
//! re-arm clears. Uses the scripted chunk source (a test double).

use chunkrt_bench::scripted::{ScriptedConfig, ScriptedSim};
use chunkrt_controller::config::Config;
use chunkrt_controller::control::{Event, Rearm, Reason, State};
use chunkrt_ipc::{JointCommand, COMMAND_MODE_HOLD, CONTROLLER_STATE_HOLD};

const START_NS: u64 = 10_000_000_000;

fn sim(hold_to_fault_ms: f64) -> (Config, ScriptedSim) {
    let mut c = Config::embedded_default();
    c.execution.strategy = chunkrt_controller::config::Strategy::Rtc;
    c.execution.hold_to_fault_ms = hold_to_fault_ms;
    c.validate("test").expect("valid test config");
    let s = ScriptedSim::new(&c, ScriptedConfig::demo(80_000_000, 0.02), START_NS)
        .expect("executor builds");
    (c, s)
}

fn events(s: &ScriptedSim) -> Vec<Event> {
    let mut v = Vec::new();
    s.exec.events().drain(|e| v.push(e));
    v
}

/// Braking between ticks `from..to` of the command log stays within the limits and ends at
/// rest in COMMAND_MODE_HOLD.
fn assert_brakes_within_limits(cfg: &Config, cmds: &[JointCommand]) {
    let dt = 1e-3;
    for k in 1..cmds.len() {
        for (j, jc) in cfg.robot.joints.iter().enumerate() {
            assert!(
                cmds[k].velocity[j].abs() <= jc.max_velocity * (1.0 + 1e-9),
                "tick {k} joint {j}: v {} a {} mode {}",
                cmds[k].velocity[j],
                cmds[k].acceleration[j],
                cmds[k].mode
            );
            assert!(cmds[k].acceleration[j].abs() <= jc.max_acceleration * (1.0 + 1e-9));
            let jerk = (cmds[k].acceleration[j] - cmds[k - 1].acceleration[j]) / dt;
            assert!(
                jerk.abs() <= jc.max_jerk * (1.0 + 1e-6) + 1e-6,
                "tick {k} joint {j}: {jerk}"
            );
        }
    }
    let last = cmds.last().expect("commands");
    assert_eq!(last.mode, COMMAND_MODE_HOLD, "at rest in the end");
    assert!(last.velocity.iter().all(|v| *v == 0.0));
}

/// Limits only (the run may end while moving again).
fn assert_brakes_within_limits_partial(cfg: &Config, cmds: &[JointCommand]) {
    let dt = 1e-3;
    for k in 1..cmds.len() {
        for (j, jc) in cfg.robot.joints.iter().enumerate() {
            assert!(cmds[k].velocity[j].abs() <= jc.max_velocity * (1.0 + 1e-9));
            assert!(cmds[k].acceleration[j].abs() <= jc.max_acceleration * (1.0 + 1e-9));
            let jerk = (cmds[k].acceleration[j] - cmds[k - 1].acceleration[j]) / dt;
            assert!(
                jerk.abs() <= jc.max_jerk * (1.0 + 1e-6) + 1e-6,
                "tick {k} joint {j}: {jerk}"
            );
        }
    }
}

#[test]
fn stale_joint_state_holds_then_recovers() {
    let (cfg, mut s) = sim(10_000.0);
    s.run(1500);
    assert_eq!(s.exec.state(), State::Running);
    events(&s);
    // The robot stops reporting: HOLD once the state is older than joint_state_max_age_ms.
    s.robot_reports = false;
    let stop_tick = s.reports.len();
    s.run(600);
    let hold_tick = s.reports[stop_tick..]
        .iter()
        .position(|r| r.state == State::Hold)
        .expect("enters HOLD");
    let max_age = cfg.control.joint_state_max_age_ms as usize;
    // The last report was at stop_tick - 1; stale once older than max_age ms.
    assert!(
        hold_tick <= max_age + 1 && hold_tick >= max_age - 1,
        "HOLD after {hold_tick} ticks, max age {max_age} ms"
    );
    assert_brakes_within_limits(&cfg, &s.commands[stop_tick - 2..]);
    let ev = events(&s);
    assert_eq!(ev.len(), 1, "{ev:?}");
    assert_eq!(ev[0].reason, Reason::StaleJointState);
    assert_eq!((ev[0].from, ev[0].to), (State::Running, State::Hold));
    let mut st = chunkrt_ipc::ControllerStatus::default();
    s.exec.fill_status(&mut st);
    assert_eq!(st.state, CONTROLLER_STATE_HOLD);
    assert_eq!(st.hold_entries, 1);
    assert!(st.joint_state_age_ns > 500_000_000);
    // The robot reports again: back to RUNNING at once (chunks kept coming).
    s.robot_reports = true;
    s.step();
    assert_eq!(s.exec.state(), State::Running);
    let ev = events(&s);
    assert_eq!(ev[0].reason, Reason::InputsGood);
}

#[test]
fn nan_action_holds_within_a_tick_and_good_chunks_recover() {
    let (cfg, mut s) = sim(10_000.0);
    s.run(1500);
    assert_eq!(s.exec.state(), State::Running);
    events(&s);
    s.source.inject_nan = true;
    let before = s.exec.chunk_counts().1;
    let base = s.commands.len();
    let mut hold_at = None;
    for k in 0..1200 {
        let r = s.step();
        if r.state == State::Hold && hold_at.is_none() {
            hold_at = Some(k);
            // The NaN chunk was rejected in this very tick.
            assert_eq!(s.exec.chunk_counts().1, before + 1);
        }
        if hold_at.is_some() && r.state == State::Running {
            break;
        }
    }
    let hold_at = hold_at.expect("a NaN chunk puts the executor in HOLD");
    assert_eq!(
        s.exec.state(),
        State::Running,
        "the next good chunk recovers"
    );
    let ev = events(&s);
    assert_eq!(ev[0].reason, Reason::NonFiniteAction, "{ev:?}");
    assert_eq!(ev[1].reason, Reason::InputsGood, "{ev:?}");
    // While holding, no command carried a NaN and the limits held.
    for c in &s.commands[base + hold_at - 2..] {
        assert!(c.position.iter().all(|p| p.is_finite()));
    }
    assert_brakes_within_limits_partial(&cfg, &s.commands[base + hold_at - 2..]);
}

#[test]
fn missing_chunks_hold_then_fault_and_only_rearm_recovers() {
    let (cfg, mut s) = sim(500.0);
    s.run(1500);
    assert_eq!(s.exec.state(), State::Running);
    events(&s);
    // The policy goes silent: the newest chunk expires, then HOLD lasts past hold_to_fault.
    s.source.enabled = false;
    let from = s.reports.len();
    s.run(2000);
    let rep = &s.reports[from..];
    let hold = rep
        .iter()
        .position(|r| r.state == State::Hold)
        .expect("HOLD");
    let fault = rep
        .iter()
        .position(|r| r.state == State::Fault)
        .expect("FAULT");
    // Chunks last H = 50 actions (1 s); one had just been requested → expiry within ~1 s.
    assert!(hold < 1100, "hold after {hold} ticks");
    assert_eq!(
        fault - hold,
        500,
        "FAULT exactly hold_to_fault_ms after HOLD"
    );
    assert_brakes_within_limits(&cfg, &s.commands[from + hold - 2..]);
    let ev = events(&s);
    assert_eq!(ev[0].reason, Reason::ChunkExpired, "{ev:?}");
    assert_eq!(ev[1].reason, Reason::HoldTimeout, "{ev:?}");
    // No requests in FAULT, and good chunks do not leave FAULT.
    s.source.enabled = true;
    s.run(500);
    assert_eq!(s.exec.state(), State::Fault);
    assert!(s.reports[s.reports.len() - 500..]
        .iter()
        .all(|r| !r.requested));
    // Re-arm: STARTING, then RUNNING once a new chunk arrives.
    assert_eq!(s.exec.rearm(s.now_ns), Rearm::Accepted);
    assert_eq!(s.exec.state_reason(), Some(Reason::Rearm));
    s.run(300);
    assert_eq!(s.exec.state(), State::Running);
    let ev = events(&s);
    assert_eq!(ev[0].reason, Reason::Rearm);
    assert_eq!((ev[1].from, ev[1].to), (State::Starting, State::Running));
    // nothing to re-arm while running
    assert_eq!(s.exec.rearm(s.now_ns), Rearm::NotInFault(State::Running));
}

/// A re-arm is refused while the input that is still bad says so (here the joint state), and
/// accepted once it is good again; the refusal changes nothing.
#[test]
fn rearm_is_refused_while_the_joint_state_is_stale() {
    let (_cfg, mut s) = sim(300.0);
    s.run(1500);
    assert_eq!(s.exec.state(), State::Running);
    s.robot_reports = false;
    s.run(1500);
    assert_eq!(s.exec.state(), State::Fault);
    assert_eq!(s.exec.state_reason(), Some(Reason::HoldTimeout));
    events(&s);
    assert_eq!(
        s.exec.rearm(s.now_ns),
        Rearm::InputsBad(Reason::StaleJointState)
    );
    s.run(10);
    assert_eq!(
        s.exec.state(),
        State::Fault,
        "a refused re-arm changes nothing"
    );
    assert!(events(&s).is_empty());
    s.robot_reports = true;
    s.run(2);
    assert_eq!(s.exec.rearm(s.now_ns), Rearm::Accepted);
    s.run(500);
    assert_eq!(s.exec.state(), State::Running);
}

#[test]
fn overrun_streak_holds_and_recovers() {
    let mut c = Config::embedded_default();
    c.execution.overrun_streak = 5;
    let mut s = ScriptedSim::new(&c, ScriptedConfig::demo(80_000_000, 0.02), START_NS)
        .expect("executor builds");
    s.run(1500);
    assert_eq!(s.exec.state(), State::Running);
    events(&s);
    s.compute_ns = 1_500_000; // every tick now overruns the 1 ms period
    s.run(4);
    assert_eq!(s.exec.state(), State::Running, "4 overruns are tolerated");
    s.run(2);
    assert_eq!(s.exec.state(), State::Hold);
    s.compute_ns = 50_000;
    s.run(2);
    assert_eq!(s.exec.state(), State::Running);
    let ev = events(&s);
    assert_eq!(ev[0].reason, Reason::Overruns);
    assert_eq!(s.exec.timing().overruns, 6);
}

#[test]
fn starting_waits_for_joint_state_and_bad_robot_faults() {
    let c = Config::embedded_default();
    let mut exec = chunkrt_controller::control::Executor::new(&c).expect("executor builds");
    let mut cmd = JointCommand::default();
    let r = exec.tick(START_NS, None, &mut cmd);
    assert_eq!(r.state, State::Starting);
    assert!(
        !r.publish,
        "nothing to command before the first joint state"
    );
    // A fresh joint state without chunks: hold the measured pose, still STARTING.
    let mut js = chunkrt_ipc::JointState {
        n_dof: 4,
        measurement_time_ns: START_NS,
        ..Default::default()
    };
    js.position[1] = 0.7;
    let r = exec.tick(START_NS + 1_000_000, Some(&js), &mut cmd);
    assert!(r.publish);
    assert_eq!(r.state, State::Starting);
    assert!((cmd.position[1] - 0.7).abs() < 1e-12);
    assert!(r.requested, "the first inference is requested at once");
    // A joint state for another robot: FAULT.
    js.n_dof = 3;
    js.measurement_time_ns = START_NS + 2_000_000;
    let r = exec.tick(START_NS + 2_000_000, Some(&js), &mut cmd);
    assert_eq!(r.state, State::Fault);
    let mut ev = Vec::new();
    exec.events().drain(|e| ev.push(e));
    assert_eq!(ev[0].reason, Reason::BadJointState);
}

/// A robot that restarts elsewhere while the controller holds (issue 16 point 5): leaving HOLD
/// starts from the measured state, not from the controller's last command, and moves to the
/// chunk within the limits. (It resumed 1.58 rad away from the restarted robot.)
/// The robot, silent, comes back at rest at `measured` and stands there while the executor
/// holds, then follows its commands; `ticks` ticks. Returns the index in `s.commands` of the
/// first command after the executor resumed.
fn come_back_at(s: &mut ScriptedSim, measured: [f64; chunkrt_ipc::MAX_DOF], ticks: usize) -> usize {
    let resume_at = s.commands.len();
    for _ in 0..ticks {
        s.joint_state.seq += 1;
        s.joint_state.measurement_time_ns = s.now_ns;
        if s.exec.state() == State::Hold {
            // standing still where it restarted until the controller resumes
            s.joint_state.position = measured;
            s.joint_state.velocity = [0.0; chunkrt_ipc::MAX_DOF];
        } else if let Some(c) = s.commands.last() {
            s.joint_state.position = c.position;
            s.joint_state.velocity = c.velocity;
        }
        s.step();
    }
    let first_running = s.reports[s.reports.len() - ticks..]
        .iter()
        .position(|r| r.state == State::Running)
        .expect("resumes");
    resume_at + first_running
}

#[test]
fn resume_after_a_robot_restart_starts_from_the_measured_position() {
    let (cfg, mut s) = sim(10_000.0);
    s.run(1500);
    assert_eq!(s.exec.state(), State::Running);
    s.robot_reports = false;
    s.run(300);
    assert_eq!(s.exec.state(), State::Hold);
    // the robot comes back, at rest somewhere else
    let mut measured = s.joint_state.position;
    measured[0] += 1.2;
    measured[1] -= 0.8;
    let first_running = come_back_at(&mut s, measured, 400);
    let first = &s.commands[first_running];
    for (j, m) in measured.iter().enumerate().take(cfg.n_dof()) {
        let d = (first.position[j] - m).abs();
        assert!(
            d < 0.01,
            "joint {j}: first command {d} rad from the measured position"
        );
    }
    assert_brakes_within_limits_partial(&cfg, &s.commands[first_running..]);
}

/// A robot whose driver says it followed this controller through a gap in its states (the
/// session bound to this controller's commands, no hold of its own: the FR3's driver continuing
/// the stream while franka-sim went silent for 20 ms) comes back with the arm where its
/// tracking lag left it, 0.02 rad behind, moving at half the commanded speed. The generator
/// goes on from its own state: no step to the measured state (re-seeded from it, the generator
/// took franka-sim's measured 0.47 rad/s for the commanded 0.96 and the driver carried the
/// difference as an offset, 0.10-0.15 rad from the controller's command). After a long hold (the
/// controller braked on while the silent robot did not: a stopped process), or without the
/// session reported (a restarted robot), the return still starts from the measured state.
#[test]
fn a_robot_that_followed_through_a_gap_resumes_the_generators_own_stream() {
    const ME: u128 = 0x5eed;
    // (reported, ticks silent, resumes its own stream): the joint state goes stale after the
    // default config's 50 ms, so 53 silent ticks make a hold of 2-3 ms, 300 one of 250 ms
    for (reported, silent, continues) in [(true, 53, true), (true, 300, false), (false, 53, false)]
    {
        let (cfg, mut s) = sim(10_000.0);
        s.exec.set_command_publisher(ME);
        if reported {
            s.joint_state.set_obeyed_publisher(ME);
        }
        s.run(1500);
        assert_eq!(s.exec.state(), State::Running);
        s.robot_reports = false;
        s.run(silent);
        assert_eq!(s.exec.state(), State::Hold, "{silent} ticks silent");
        let last = *s.commands.last().expect("commands");
        let mut measured = last.position;
        measured[0] -= 0.02;
        let resume_at = s.commands.len();
        s.robot_reports = true;
        // the first state back: the lagging arm at half the commanded velocity
        s.joint_state.seq += 1;
        s.joint_state.measurement_time_ns = s.now_ns;
        s.joint_state.position = measured;
        for (v, c) in s.joint_state.velocity.iter_mut().zip(&last.velocity) {
            *v = 0.5 * c;
        }
        let mut cmd = JointCommand::default();
        let now = s.now_ns;
        s.exec.tick(now, Some(&s.joint_state), &mut cmd);
        s.commands.push(cmd);
        s.now_ns += s.period_ns;
        s.run(200);
        let first_running = s.reports[s.reports.len() - 200..]
            .iter()
            .position(|r| r.state == State::Running)
            .map(|k| resume_at + 1 + k)
            .unwrap_or(resume_at);
        let step = (s.commands[resume_at].position[0] - last.position[0]).abs();
        if continues {
            let vmax = cfg.robot.joints[0].max_velocity;
            assert!(
                step <= vmax * 1e-3 + 1e-9,
                "a robot that followed: the first command after the gap stepped {step} rad"
            );
            assert_brakes_within_limits_partial(&cfg, &s.commands[resume_at - 1..]);
        } else {
            let d = (s.commands[resume_at].position[0] - measured[0]).abs();
            assert!(
                d < 0.005,
                "reported {reported}, {silent} ticks silent: the first command {d} rad from the \
                 measured state (first running at {first_running})"
            );
        }
    }
}

/// The robot comes back with the arm outside the controller's position range (a reflex in an
/// extreme pose, a person who moved it): the first command starts where the arm is (a command
/// clamped into the range would be a step, refused as far by the robot every tick: the FR3
/// refused 5 000 in a row after a reflex), and the stream returns inside the range within the
/// limits, never further out.
#[test]
fn resume_outside_the_position_range_starts_from_the_arm_and_returns_inside() {
    let (cfg, mut s) = sim(10_000.0);
    s.run(1500);
    s.robot_reports = false;
    s.run(300);
    assert_eq!(s.exec.state(), State::Hold);
    let mut measured = s.joint_state.position;
    let (lo, hi) = (
        cfg.robot.joints[0].position_min,
        cfg.robot.joints[0].position_max,
    );
    measured[0] = hi + 0.1;
    let first_running = come_back_at(&mut s, measured, 3000);
    let cmds = &s.commands[first_running..];
    let d = (cmds[0].position[0] - measured[0]).abs();
    assert!(d < 0.01, "the first command {d} rad from the arm");
    assert_brakes_within_limits_partial(&cfg, cmds);
    for c in cmds {
        assert!(
            c.position[0] <= measured[0] + 1e-9,
            "further out: {}",
            c.position[0]
        );
    }
    let last = cmds.last().expect("commands").position[0];
    assert!(
        (lo..=hi).contains(&last),
        "joint 0 at {last}, outside {lo}..{hi} after {} ticks",
        cmds.len()
    );
}

/// A camera the policy uses stops sending (the inference thread sets its bit in the link's
/// `stale_cameras`): the next tick holds, brakes within the limits, and the status names the
/// camera; when frames are back the executor runs again.
#[test]
fn stale_camera_holds_at_once_and_recovers() {
    let (cfg, mut s) = sim(10_000.0);
    s.run(1500);
    assert_eq!(s.exec.state(), State::Running);
    events(&s);
    let link = s.exec.connect();
    link.stale_cameras
        .store(0b1, std::sync::atomic::Ordering::Relaxed);
    let stop_tick = s.commands.len();
    s.run(600);
    let ev = events(&s);
    assert_eq!(ev.len(), 1, "{ev:?}");
    assert_eq!(ev[0].reason, Reason::StaleCamera);
    assert_eq!((ev[0].from, ev[0].to), (State::Running, State::Hold));
    assert_eq!(
        s.reports[stop_tick].state,
        State::Hold,
        "held on the first tick that saw the stale camera"
    );
    assert_brakes_within_limits(&cfg, &s.commands[stop_tick - 2..]);
    let mut st = chunkrt_ipc::ControllerStatus::default();
    s.exec.fill_status(&mut st);
    assert_eq!(st.state, CONTROLLER_STATE_HOLD);
    assert_eq!(st.stale_cameras, 0b1, "the status says which camera");
    assert_eq!(
        chunkrt_controller::controller::camera_names(&cfg, st.stale_cameras),
        cfg.cameras[0].name
    );
    // frames again: RUNNING (the scripted source kept producing chunks)
    link.stale_cameras
        .store(0, std::sync::atomic::Ordering::Relaxed);
    s.run(300);
    assert_eq!(s.exec.state(), State::Running);
    s.exec.fill_status(&mut st);
    assert_eq!(st.stale_cameras, 0);
}

/// The inference thread's verdict: a camera is stale when it never sent a frame or its newest
/// frame is older than the maximum age at the time of use.
#[test]
fn stale_cameras_mask_from_frame_ages() {
    use chunkrt_controller::edge::Observation;
    let mut c = Config::embedded_default();
    let mut second = c.cameras[0].clone();
    second.name = "wrist".into();
    c.cameras.push(second);
    let mut obs = Observation::new(&c);
    let now = 5_000_000_000u64;
    let max_age = 200_000_000u64;
    assert_eq!(
        chunkrt_controller::controller::stale_cameras(&obs.frames, now, max_age),
        0b11,
        "no frame yet: stale"
    );
    obs.frames[0].valid = true;
    obs.frames[0].header.capture_time_ns = now - max_age;
    obs.frames[1].valid = true;
    obs.frames[1].header.capture_time_ns = now - max_age - 1;
    assert_eq!(
        chunkrt_controller::controller::stale_cameras(&obs.frames, now, max_age),
        0b10
    );
    assert_eq!(
        chunkrt_controller::controller::camera_names(&c, 0b10),
        "wrist"
    );
    // a frame stamped slightly in the future (within the validated bound) is fresh
    obs.frames[1].header.capture_time_ns = now + 1_000;
    assert_eq!(
        chunkrt_controller::controller::stale_cameras(&obs.frames, now, max_age),
        0
    );
}

/// A chunk source that never delivers a usable chunk (test doubles): it fails, it hands out
/// non-finite chunks, or it has nothing.
#[derive(Clone, Copy, PartialEq, Eq, Debug)]
enum Broken {
    Fails,
    NonFinite,
    Nothing,
}

impl chunkrt_controller::contract::ChunkSource for Broken {
    fn name(&self) -> &str {
        "broken (test double)"
    }

    fn compute(
        &mut self,
        _obs: &chunkrt_controller::contract::Observation,
        req: &chunkrt_controller::contract::InferenceRequest,
    ) -> anyhow::Result<Option<chunkrt_controller::chunk::ActionChunk>> {
        match self {
            Broken::Fails => anyhow::bail!("inference failed (test double)"),
            Broken::Nothing => Ok(None),
            Broken::NonFinite => Ok(Some(chunkrt_controller::chunk::ActionChunk {
                id: req.id,
                observation_seq: req.id,
                t_obs_ns: req.t_ref_ns,
                period_ns: 20_000_000,
                n_dof: 4,
                actions: vec![f64::NAN; 4 * 50],
                ready_ns: req.t_ref_ns,
                start_shift_ns: 0,
            })),
        }
    }
}

/// Runs `source` for `ms` ticks of 1 ms with a fresh joint state; returns the state and the
/// state reason at every tick.
fn run_broken(
    mut source: Broken,
    hold_to_fault_ms: f64,
    ms: u64,
    without_source: bool,
) -> Vec<(State, Option<Reason>)> {
    use chunkrt_controller::worker::{Delivery, InferenceWorker};
    let mut cfg = Config::embedded_default();
    cfg.execution.hold_to_fault_ms = hold_to_fault_ms;
    let mut exec = chunkrt_controller::control::Executor::new(&cfg).unwrap();
    if without_source {
        exec.without_chunk_source();
    }
    let mut worker = InferenceWorker::new(exec.connect(), Delivery::Immediate);
    let obs = chunkrt_controller::contract::Observation::new(&cfg);
    let mut js = chunkrt_ipc::JointState {
        n_dof: 4,
        ..Default::default()
    };
    js.position[1] = 1.2;
    js.position[2] = 0.6;
    let mut cmd = JointCommand::default();
    (0..ms)
        .map(|k| {
            let now = START_NS + k * 1_000_000;
            worker.step(now, &mut source, &obs);
            js.seq += 1;
            js.measurement_time_ns = now;
            exec.tick(now, Some(&js), &mut cmd);
            (exec.state(), exec.state_reason())
        })
        .collect()
}

/// A policy that never produces a usable chunk does not leave the controller in STARTING: the
/// status names the cause while it waits, and after `hold_to_fault_ms` it is a FAULT with that
/// cause (issue: 14 s in STARTING with state reason 0 was observed).
#[test]
fn a_source_that_never_delivers_escalates_to_fault_with_its_cause() {
    for (source, cause) in [
        (Broken::Fails, Reason::InferenceError),
        (Broken::NonFinite, Reason::NonFiniteAction),
        (Broken::Nothing, Reason::NoChunk),
    ] {
        let trace = run_broken(source, 300.0, 600, false);
        // waiting: STARTING, naming the cause
        assert_eq!(trace[150], (State::Starting, Some(cause)), "{source:?}");
        // escalated within hold_to_fault (plus the first request's tick)
        let fault = trace
            .iter()
            .position(|(s, _)| *s == State::Fault)
            .unwrap_or_else(|| panic!("{source:?}: never FAULT"));
        assert!(
            (299..=305).contains(&fault),
            "{source:?}: FAULT at tick {fault}"
        );
        assert_eq!(trace[fault].1, Some(cause), "{source:?}");
        assert!(trace[fault..].iter().all(|(s, _)| *s == State::Fault));
    }
    // without a chunk source (`policy.kind = "hold"`) STARTING is the plan: no escalation
    let trace = run_broken(Broken::Nothing, 300.0, 900, true);
    assert!(trace.iter().all(|(s, _)| *s == State::Starting));
}
