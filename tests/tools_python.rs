//! Cross-language round trip over real iceoryx2 services: the Python robot client
//! (`tools/python/robot_client.py`, PyPI `iceoryx2` + the ctypes mirror) publishes joint states
//! that this Rust process receives and validates, and follows the commands this process
//! publishes. Skipped loudly when `import iceoryx2` fails, a failure when `CI` is set.

use std::time::{Duration, Instant};

use chunkrt_ipc::services;
use chunkrt_ipc::*;
use chunkrt_tools::testing::{summary_value, unique_namespace, ChildGuard};

#[path = "common/python.rs"]
mod python;

/// True if `python3 -c "import iceoryx2"` works; otherwise shouts (and fails in CI).
fn python_iceoryx2_available() -> bool {
    python::python_can_import(
        "import iceoryx2",
        "tools_python",
        "pip install iceoryx2==0.10.0",
    )
}

#[test]
fn tools_python_client_round_trip() {
    if !python_iceoryx2_available() {
        return;
    }
    const N: u32 = 4;
    let initial = [0.1, 0.2, 0.3, 0.4];
    // Exactly representable, so the Python side can print them back verbatim.
    let target = [0.125, -0.5, 0.75, 0.0625];

    let ns_str = unique_namespace("python");
    let ns = Namespace::new(&ns_str).unwrap();
    let node = services::node("tools-test-python").unwrap();
    services::cleanup_dead_nodes(&node);
    let st = services::joint_state_service(&node, &ns.joint_state()).unwrap();
    let st_sub = services::subscriber(&st).unwrap();
    let cmd = services::joint_command_service(&node, &ns.joint_command()).unwrap();
    let cmd_pub = services::publisher(&cmd).unwrap();

    let script = concat!(env!("CARGO_MANIFEST_DIR"), "/tools/python/robot_client.py");
    let client = ChildGuard::spawn(
        "python3",
        &[
            script,
            "--namespace",
            &ns_str,
            "--duration",
            "3",
            "--n-dof",
            "4",
            "--rate-hz",
            "500",
            "--initial",
            "0.1",
            "0.2",
            "0.3",
            "0.4",
        ],
    )
    .expect("spawn python3 robot_client.py");
    let mut client = client;

    let mut guard = StreamGuard::new();
    let limits = Freshness {
        max_age_ns: 1_000_000_000,
        max_future_ns: 1_000_000,
    };
    let mut states = 0u64;
    let mut invalid = Vec::new();
    let mut first: Option<JointState> = None;
    let mut reached = false;
    let mut seq = 0u64;
    let end = Instant::now() + Duration::from_secs(30);
    while client.running() && Instant::now() < end {
        while let Ok(Some(s)) = st_sub.receive() {
            let m = *s.payload();
            let now = monotonic_ns();
            let checked = validate_joint_state(&m, Some(N)).and_then(|_| {
                guard.check(
                    s.origin().value(),
                    m.seq,
                    m.measurement_time_ns,
                    now,
                    limits,
                )
            });
            if let Err(e) = checked {
                invalid.push(format!("seq {}: {e}", m.seq));
                continue;
            }
            states += 1;
            first.get_or_insert(m);
            if (0..N as usize).all(|i| (m.position[i] - target[i]).abs() < 1e-9) {
                reached = true;
            }
        }
        // Commands only once the client is publishing (it subscribes before it publishes).
        if first.is_some() {
            seq += 1;
            let now = monotonic_ns();
            let mut c = JointCommand {
                seq,
                publish_time_ns: now,
                deadline_ns: now + 50_000_000,
                chunk_id: 42,
                n_dof: N,
                mode: COMMAND_MODE_POSITION,
                ..Default::default()
            };
            c.position[..4].copy_from_slice(&target);
            let sample = cmd_pub.loan_uninit().expect("loan");
            sample.write_payload(c).send().expect("send");
        }
        std::thread::sleep(Duration::from_millis(5));
    }
    let out = client.finish(Duration::from_secs(10));
    eprintln!("python client stdout: {}", out.stdout.trim());
    assert_eq!(out.code, Some(0), "client exit: {out:?}");
    assert!(invalid.is_empty(), "invalid joint states: {invalid:?}");
    let first = first.expect("no joint state from the Python client");
    for (p, p0) in first.position.iter().zip(initial) {
        assert!((p - p0).abs() < 0.05, "{first:?}");
    }
    assert!(states >= 100, "only {states} joint states received");
    assert!(reached, "the Python arm never reached the commanded target");

    let v = |k: &str| summary_value(&out.stdout, k).unwrap_or_else(|| panic!("no {k}: {out:?}"));
    assert!(v("commands_received") >= 10.0, "{}", out.stdout);
    assert!(v("commands_valid") >= 10.0, "{}", out.stdout);
    assert_eq!(v("commands_rejected"), 0.0, "{}", out.stdout);
    assert!(
        out.stdout.contains("last_command=seq:")
            && out
                .stdout
                .contains(",chunk:42,mode:1,pos:0.125/-0.5/0.75/0.0625"),
        "{}",
        out.stdout
    );
    eprintln!(
        "round trip: {states} joint states received from Python, {} commands received by it",
        v("commands_received")
    );
}
