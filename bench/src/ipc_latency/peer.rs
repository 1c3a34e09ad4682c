//! The peer (receiving) process of the ipc_latency bench: subscribes, waits by event, answers
//! every sample on the ack service.

use super::*;

/// Arguments of the peer (receiving) process.
#[derive(Debug, Clone, clap::Args)]
pub struct PeerArgs {
    /// Service namespace of this case.
    #[arg(long)]
    pub namespace: String,
    /// Number of cameras (0: joint state).
    #[arg(long, default_value_t = 0)]
    pub cameras: u32,
    /// Frame width.
    #[arg(long, default_value_t = 0)]
    pub width: u32,
    /// Frame height.
    #[arg(long, default_value_t = 0)]
    pub height: u32,
    /// Exit after this long without a message (the bench process died).
    #[arg(long, default_value_t = 10_000)]
    pub idle_timeout_ms: u64,
    /// How to wait for samples.
    #[arg(long, value_enum, default_value_t = Wake::Event)]
    pub wake: Wake,
}

#[derive(Debug, clap::Parser)]
#[command(name = "ipc-latency-peer")]
pub(super) struct PeerCli {
    #[command(flatten)]
    args: PeerArgs,
}

/// Parses peer arguments (without the program name) and runs the peer.
pub fn peer_from_args(args: impl IntoIterator<Item = String>) -> Result<(), BenchError> {
    use clap::Parser;
    let cli = PeerCli::try_parse_from(std::iter::once("peer".to_string()).chain(args))
        .map_err(|e| BenchError::Option(e.to_string()))?;
    peer_main(&cli.args)
}

pub(super) fn port_err(what: &'static str) -> impl Fn(String) -> BenchError {
    move |reason| BenchError::Port { what, reason }
}

pub(super) fn ack_service_name(ns: &Namespace) -> String {
    format!("{}/bench_ack", ns.as_str())
}

/// Event services: `<ns>/bench_wake` (bench → peer) and `<ns>/bench_ack_wake` (peer → bench).
pub(super) fn event_ports(
    node: &iceoryx2::node::Node<services::Ipc>,
    ns: &Namespace,
    peer_side: bool,
) -> Result<
    (
        iceoryx2::port::notifier::Notifier<services::Ipc>,
        iceoryx2::port::listener::Listener<services::Ipc>,
    ),
    BenchError,
> {
    use iceoryx2::prelude::ServiceName;
    let open = |name: String| {
        let sn = ServiceName::new(&name).map_err(|e| port_err("event name")(format!("{e:?}")))?;
        node.service_builder(&sn)
            .event()
            .open_or_create()
            .map_err(|e| port_err("event service")(format!("{e:?}")))
    };
    let to_peer = open(format!("{}/bench_wake", ns.as_str()))?;
    let to_bench = open(format!("{}/bench_ack_wake", ns.as_str()))?;
    let (n, l) = if peer_side {
        (&to_bench, &to_peer)
    } else {
        (&to_peer, &to_bench)
    };
    let notifier = n
        .notifier_builder()
        .create()
        .map_err(|e| port_err("notifier")(format!("{e:?}")))?;
    let listener = l
        .listener_builder()
        .create()
        .map_err(|e| port_err("listener")(format!("{e:?}")))?;
    Ok((notifier, listener))
}

/// Waits for the next sample: blocks on the listener (event) or yields (poll).
pub(super) fn wait_for_more(
    wake: Wake,
    listener: &iceoryx2::port::listener::Listener<services::Ipc>,
    timeout: Duration,
) -> Result<(), BenchError> {
    match wake {
        Wake::Event => listener
            .timed_wait(|_| {}, timeout)
            .map(|_| ())
            .map_err(|e| port_err("event wait")(format!("{e:?}"))),
        Wake::Poll => {
            // Drain stale notifications so they do not pile up; then give the core away.
            let _ = listener.try_wait(|_| {});
            std::thread::yield_now();
            Ok(())
        }
    }
}

/// The receiving process: takes every observation, validates it, reads it, and acknowledges
/// each complete observation (all cameras of one seq) with its receive time.
pub fn peer_main(args: &PeerArgs) -> Result<(), BenchError> {
    let ns = Namespace::new(&args.namespace)?;
    let node = services::node("chunkrt-bench-peer")?;
    let (notifier, listener) = event_ports(&node, &ns, true)?;
    let wait = || wait_for_more(args.wake, &listener, Duration::from_millis(100));
    let ack_name = ack_service_name(&ns);
    let ack_service = services::joint_state_service(&node, &ack_name)?;
    let ack_pub = services::publisher(&ack_service)?;
    let ack = |seq: u64, t: u64| -> Result<(), BenchError> {
        let mut msg = JointState {
            seq,
            measurement_time_ns: t,
            n_dof: 1,
            ..JointState::default()
        };
        msg.position[0] = 0.0;
        ack_pub
            .send_copy(msg)
            .map_err(|e| port_err("ack send")(format!("{e:?}")))?;
        if args.wake == Wake::Event {
            notifier
                .notify()
                .map_err(|e| port_err("notify")(format!("{e:?}")))?;
        }
        Ok(())
    };
    let idle = args.idle_timeout_ms * 1_000_000;
    let mut last_msg = monotonic_ns();
    let mut acked = 0u64;
    if args.cameras == 0 {
        let name = ns.joint_state();
        let svc = services::joint_state_service(&node, &name)?;
        let sub = services::subscriber(&svc)?;
        loop {
            let mut newest = None;
            while let Some(s) = sub
                .receive()
                .map_err(|e| port_err("receive")(format!("{e:?}")))?
            {
                let t = monotonic_ns();
                let msg: &JointState = s.payload();
                if msg.seq == STOP_SEQ {
                    return Ok(());
                }
                if validate_joint_state(msg, None).is_ok() {
                    newest = Some((msg.seq, t));
                }
            }
            match newest {
                Some((seq, t)) if seq > acked => {
                    ack(seq, t)?;
                    acked = seq;
                    last_msg = t;
                }
                _ => {
                    if monotonic_ns() - last_msg > idle {
                        return Err(BenchError::Timeout("peer: no joint state".into()));
                    }
                    wait()?;
                }
            }
        }
    }
    let n = args.cameras as usize;
    let mut subs = Vec::with_capacity(n);
    for i in 0..n {
        let name = ns.camera(&format!("cam{i}"));
        let svc = services::camera_service(&node, &name)?;
        subs.push(services::camera_subscriber(&svc)?);
    }
    let mut last = vec![0u64; n];
    let mut checksum = 0u64;
    loop {
        let mut got = false;
        for (i, sub) in subs.iter().enumerate() {
            while let Some(s) = sub
                .receive()
                .map_err(|e| port_err("receive")(format!("{e:?}")))?
            {
                let h: &CameraFrameHeader = s.user_header();
                if h.seq == STOP_SEQ {
                    return Ok(());
                }
                let px = s.payload();
                if validate_frame(h, px.len(), args.width, args.height).is_ok() {
                    // Read the frame in place, as a preprocessor would (first, middle, last row).
                    let row = h.stride as usize;
                    checksum = checksum
                        .wrapping_add(px[0] as u64)
                        .wrapping_add(px[px.len() / 2] as u64)
                        .wrapping_add(px[px.len() - row..].iter().map(|b| *b as u64).sum::<u64>());
                    last[i] = h.seq;
                    got = true;
                }
            }
        }
        let t = monotonic_ns();
        let seq = last[0];
        if got && seq > acked && last.iter().all(|s| *s == seq) {
            ack(seq, t)?;
            acked = seq;
            last_msg = t;
        } else if !got {
            if t - last_msg > idle {
                return Err(BenchError::Timeout(format!(
                    "peer: no frame (checksum {checksum})"
                )));
            }
            wait()?;
        }
    }
}
