//! The whole control tick as the control thread runs it — joint-state receive and validation
//! over a real iceoryx2 service, the executor (ruckig included), the command publish and the
//! periodic status publish — allocates nothing in steady state except the one allocation
//! iceoryx2 0.10 makes per publish loan, which is counted and must equal the number of
//! publishes. Chunks come from the scripted source (a test double) outside the measured window.

use std::sync::atomic::Ordering;

use chunkrt::config::Config;
use chunkrt::contract::Observation;
use chunkrt::control::{cxx_allocations, Executor, State};
use chunkrt::controller::{ControlLoop, Shared};
use chunkrt::ipc::services;
use chunkrt::ipc::{monotonic_ns, JointState};
use chunkrt::worker::{Delivery, InferenceWorker};
use chunkrt_bench::scripted::{ScriptedChunkSource, ScriptedConfig};

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
    let js_pub = services::publisher(
        &services::joint_state_service(&node, &ns.joint_state()).unwrap(),
        "js",
    )
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
