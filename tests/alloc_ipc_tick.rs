//! The whole control tick as the control thread runs it — joint-state receive and validation
//! over a real iceoryx2 service, the executor (ruckig included), the command publish and the
//! periodic status publish — allocates nothing in steady state except the one allocation
//! iceoryx2 0.10 makes per publish loan, which is counted and must equal the number of
//! publishes. Chunks come from the scripted source (a test double) outside the measured window.

use std::sync::atomic::Ordering;

use chunkrt_bench::scripted::{ScriptedChunkSource, ScriptedConfig};
use chunkrt_controller::config::Config;
use chunkrt_controller::contract::Observation;
use chunkrt_controller::control::{cxx_allocations, Executor, State};
use chunkrt_controller::controller::{ControlLoop, Shared};
use chunkrt_controller::worker::{Delivery, InferenceWorker};
use chunkrt_ipc::services;
use chunkrt_ipc::{monotonic_ns, JointState};

#[path = "common/counting_alloc.rs"]
mod counting_alloc;
use counting_alloc::thread_allocations;

#[test]
fn control_tick_with_ipc_allocates_only_the_iceoryx2_loan() {
    let mut cfg = Config::embedded_default();
    cfg.robot.namespace = format!("chunkrt/test-{}-alloc", std::process::id());
    let node = services::node("test-alloc-tick").unwrap();
    let shared = Shared::new();
    let mut lp = ControlLoop::new(&node, &cfg).unwrap();
    let mut exec = Executor::new(&cfg).unwrap();
    let mut worker = InferenceWorker::new(exec.connect(), Delivery::AtReady);
    let obs = Observation::new(&cfg);
    let mut src = ScriptedChunkSource::new(ScriptedConfig::demo(60_000_000, 0.05));

    // the robot side, in this process: a joint-state publisher
    let ns = cfg.namespace();
    let js_pub =
        services::publisher(&services::joint_state_service(&node, &ns.joint_state()).unwrap())
            .unwrap();
    let mut js = JointState {
        n_dof: cfg.n_dof() as u32,
        ..Default::default()
    };
    js.position[1] = 1.2;
    js.position[2] = 0.6;

    let (ticks, warmup) = (3000u64, 500u64);
    let (mut allocs, mut cxx) = (0u64, 0u64);
    let mut publishes_before = 0;
    let mut running = false;
    for k in 0..ticks {
        let now = monotonic_ns();
        // robot and inference sides: not measured (they allocate freely)
        js.seq += 1;
        js.measurement_time_ns = now;
        js_pub.send_copy(js).unwrap();
        worker.step(now, &mut src, &obs);
        if k == warmup {
            publishes_before = shared.commands.load(Ordering::Relaxed);
        }
        // measured: one tick exactly as the control thread runs it
        // this thread's allocations: the tick's, not the test harness's own threads'
        let (a0, c0) = (thread_allocations(), cxx_allocations());
        lp.step(now, monotonic_ns(), &shared, &mut exec);
        let (a1, c1) = (thread_allocations(), cxx_allocations());
        if k >= warmup {
            allocs += a1 - a0;
            cxx += c1 - c0;
            running |= exec.state() == State::Running;
        }
        std::thread::sleep(std::time::Duration::from_micros(200));
    }
    let publishes = shared.commands.load(Ordering::Relaxed) - publishes_before;
    let status_publishes = (ticks - warmup) / 100;
    eprintln!(
        "{} ticks: {allocs} Rust allocations, {cxx} C++ allocations, {publishes} command and \
         ~{status_publishes} status publishes",
        ticks - warmup
    );
    assert!(running, "the executor ran chunks during the window");
    assert_eq!(publishes, ticks - warmup, "a command every tick");
    assert_eq!(cxx, 0, "C++ allocations in the tick");
    assert_eq!(shared.counters.rejected_total(), 0);
    // exactly one allocation per loan (commands + status), nothing else: receive, validation,
    // executor, ruckig and histograms allocate nothing (if iceoryx2 stops allocating in loans,
    // this fails and should be tightened to zero)
    assert_eq!(
        allocs,
        publishes + status_publishes,
        "allocations vs iceoryx2 loans (commands + status)"
    );
}

/// The same on the robot's clock (`[control] clock = "robot"`, the Franka's): the control
/// thread's wait for the robot's state event (`services::wait_event`, ppoll on the listener),
/// the tick, and the command event it notifies for the robot: still only the loans allocate.
/// The robot side (state publish, state event, its wait for the command event) is not measured.
#[test]
fn robot_clocked_tick_with_its_events_allocates_only_the_iceoryx2_loan() {
    let mut cfg = Config::embedded_default();
    cfg.robot.namespace = format!("chunkrt/test-{}-alloc-robot", std::process::id());
    cfg.control.clock = chunkrt_ipc::config::ControlClock::Robot;
    let node = services::node("test-alloc-robot-tick").unwrap();
    let shared = Shared::new();
    let mut lp = ControlLoop::new(&node, &cfg).unwrap();
    let mut exec = Executor::new(&cfg).unwrap();
    let mut worker = InferenceWorker::new(exec.connect(), Delivery::AtReady);
    let obs = Observation::new(&cfg);
    let mut src = ScriptedChunkSource::new(ScriptedConfig::demo(60_000_000, 0.05));

    let ns = cfg.namespace();
    let (js_name, cmd_name) = (ns.joint_state(), ns.joint_command());
    // the robot side: states out with their event, the controller's command event in
    let js_pub =
        services::publisher(&services::joint_state_service(&node, &js_name).unwrap()).unwrap();
    let state_events = services::event_service(&node, &js_name).unwrap();
    let state_notifier = services::notifier(&state_events).unwrap();
    let cmd_events = services::event_service(&node, &cmd_name).unwrap();
    let robot_listener = services::listener(&cmd_events).unwrap();
    // the control thread's listener, as control_thread makes it
    let control_listener = services::listener(&state_events).unwrap();
    let mut js = JointState {
        n_dof: cfg.n_dof() as u32,
        ..Default::default()
    };
    js.position[1] = 1.2;
    js.position[2] = 0.6;

    let (ticks, warmup) = (3000u64, 500u64);
    let (mut allocs, mut cxx, mut woken, mut answered) = (0u64, 0u64, 0u64, 0u64);
    let mut publishes_before = 0;
    let mut running = false;
    let timeout = std::time::Duration::from_millis(50);
    for k in 0..ticks {
        let now = monotonic_ns();
        js.seq += 1;
        js.measurement_time_ns = now;
        js_pub.send_copy(js).unwrap();
        state_notifier.notify().unwrap();
        worker.step(now, &mut src, &obs);
        if k == warmup {
            publishes_before = shared.commands.load(Ordering::Relaxed);
        }
        // measured: the wait for the robot's event, then the tick (which notifies the robot)
        let (a0, c0) = (thread_allocations(), cxx_allocations());
        let woke = services::wait_event(&control_listener, timeout).unwrap_or(false);
        let wake = monotonic_ns();
        lp.step(wake, wake, &shared, &mut exec);
        let (a1, c1) = (thread_allocations(), cxx_allocations());
        if k >= warmup {
            allocs += a1 - a0;
            cxx += c1 - c0;
            woken += woke as u64;
            running |= exec.state() == State::Running;
        }
        // the robot's wait for its answer (not measured)
        if services::wait_event(&robot_listener, timeout).unwrap_or(false) && k >= warmup {
            answered += 1;
        }
        std::thread::sleep(std::time::Duration::from_micros(200));
    }
    let publishes = shared.commands.load(Ordering::Relaxed) - publishes_before;
    let status_publishes = (ticks - warmup) / 100;
    eprintln!(
        "{} robot-clocked ticks: woken by the state event {woken}, command events seen by the \
         robot {answered}; {allocs} Rust allocations, {cxx} C++ allocations, {publishes} command \
         and ~{status_publishes} status publishes",
        ticks - warmup
    );
    assert!(running, "the executor ran chunks during the window");
    assert_eq!(
        woken,
        ticks - warmup,
        "every tick woken by the robot's state event"
    );
    assert_eq!(
        answered,
        ticks - warmup,
        "every state answered with a command event"
    );
    assert_eq!(publishes, ticks - warmup, "a command every tick");
    assert_eq!(cxx, 0, "C++ allocations in the tick");
    assert_eq!(shared.counters.rejected_total(), 0);
    assert_eq!(
        allocs,
        publishes + status_publishes,
        "allocations vs iceoryx2 loans (commands + status)"
    );
}
