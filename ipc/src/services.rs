//! Service names and the one place where each service's quality of service is chosen.
//!
//! Every process opens services through these functions so that all of them agree on the
//! settings (iceoryx2 refuses to open a service whose settings are incompatible with the
//! creator's). The Python mirror (`ipc/python/chunkrt_ipc.py`) repeats the same numbers.
//!
//! Real-time choices: subscribers keep only the newest samples (`history 1`, small buffers),
//! overflow is safe (the oldest unread sample is overwritten, so a stalled reader never blocks a
//! writer), and publishers never block.

use iceoryx2::port::listener::Listener;
use iceoryx2::port::notifier::Notifier;
use iceoryx2::port::publisher::Publisher;
use iceoryx2::port::subscriber::Subscriber;
use iceoryx2::prelude::*;

use crate::messages::*;

/// Subscriber buffer of the joint state / command / status services.
pub const BUFFER_SIZE: usize = 4;
/// Subscriber buffer of a camera service (frames are large; only the newest matters).
pub const CAMERA_BUFFER_SIZE: usize = 2;
/// Late joiners get the last sample.
pub const HISTORY_SIZE: usize = 1;
/// Processes per service (publisher + subscribers + monitors + tests).
pub const MAX_NODES: usize = 16;
/// Subscribers per service.
pub const MAX_SUBSCRIBERS: usize = 8;
/// Samples a subscriber may hold at once (it copies what it needs and lets go).
pub const MAX_BORROWED_SAMPLES: usize = 2;
/// Samples a publisher may have on loan at once (it loans, writes and sends in one go).
pub const MAX_LOANED_SAMPLES: usize = 2;
/// Publishers per service (a restarted process overlaps its dead predecessor briefly).
pub const MAX_PUBLISHERS: usize = 4;

/// Errors opening the IPC edge.
#[derive(Debug, thiserror::Error)]
pub enum IpcError {
    #[error("invalid service name '{name}': {reason}")]
    InvalidName { name: String, reason: String },
    #[error("cannot open service '{name}': {reason}")]
    Service { name: String, reason: String },
    #[error("cannot create {what} port on '{name}': {reason}")]
    Port {
        what: &'static str,
        name: String,
        reason: String,
    },
    #[error("cannot create iceoryx2 node: {0}")]
    Node(String),
}

/// iceoryx2's error when a service cannot be opened, with what it means and what to do: a
/// service that exists with other settings was made by another program (or an older chunkrt)
/// in the same namespace, and chunkrt will not talk on it.
pub fn explain_open(raw: &str) -> String {
    let what = if raw.contains("DoesNotSupportRequestedAmountOf") {
        Some(
            "it already exists with fewer publishers, subscribers or nodes than chunkrt needs: \
             another program (or an older chunkrt) created it with other settings",
        )
    } else if raw.contains("Incompatible") {
        Some(
            "it already exists with another message type or settings: another program, or a \
             chunkrt of another version, uses this namespace",
        )
    } else if raw.contains("InsufficientPermissions") {
        Some("another user's process owns it")
    } else if raw.contains("CorruptedState") || raw.contains("HangsInCreation") {
        Some(
            "its shared memory is left from a process that crashed while creating it; it is \
             cleaned up when no process uses it any more",
        )
    } else {
        None
    };
    match what {
        Some(w) => format!("{w}; stop that program or use another namespace (--namespace) [{raw}]"),
        None => raw.to_string(),
    }
}

/// iceoryx2's error when a port cannot be created, with what it means.
pub fn explain_port(raw: &str) -> String {
    if raw.contains("ExceedsMax") {
        format!(
            "the service already has as many of these ports as it allows: other processes hold \
             them (another robot or controller on this namespace, or a program squatting it); \
             stop them or use another namespace (--namespace) [{raw}]"
        )
    } else {
        raw.to_string()
    }
}

/// Namespace of one robot's services, e.g. `chunkrt/arm0`.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Namespace(String);

impl Namespace {
    /// Validates a namespace: non-empty, `[A-Za-z0-9_./-]` only, no leading or trailing '/'.
    pub fn new(ns: &str) -> Result<Self, IpcError> {
        let bad = |reason: &str| IpcError::InvalidName {
            name: ns.to_string(),
            reason: reason.to_string(),
        };
        if ns.is_empty() {
            return Err(bad("empty"));
        }
        if ns.len() > 200 {
            return Err(bad("longer than 200 characters"));
        }
        if ns.starts_with('/') || ns.ends_with('/') {
            return Err(bad("must not start or end with '/'"));
        }
        if let Some(c) = ns
            .chars()
            .find(|c| !(c.is_ascii_alphanumeric() || "_-./".contains(*c)))
        {
            return Err(bad(&format!("character '{c}' not allowed")));
        }
        Ok(Self(ns.to_string()))
    }

    /// The namespace as given.
    pub fn as_str(&self) -> &str {
        &self.0
    }

    /// `<ns>/joint_state`
    pub fn joint_state(&self) -> String {
        format!("{}/joint_state", self.0)
    }
    /// `<ns>/joint_command`
    pub fn joint_command(&self) -> String {
        format!("{}/joint_command", self.0)
    }
    /// `<ns>/status`
    pub fn status(&self) -> String {
        format!("{}/status", self.0)
    }

    /// `<ns>/chunks`
    pub fn chunks(&self) -> String {
        format!("{}/chunks", self.0)
    }

    /// `<ns>/rearm`
    pub fn rearm(&self) -> String {
        format!("{}/rearm", self.0)
    }
    /// `<ns>/camera/<name>`
    pub fn camera(&self, camera: &str) -> String {
        format!("{}/camera/{}", self.0, camera)
    }
}

/// The iceoryx2 service flavour every chunkrt process uses (inter-process, not thread-safe
/// ports: each port lives in the thread that created it).
pub type Ipc = ipc::Service;

/// Creates a node with signal handling left to the process (chunkrt installs its own handler so
/// that every thread sees one shutdown flag).
pub fn node(name: &str) -> Result<Node<Ipc>, IpcError> {
    let node_name = NodeName::new(name).map_err(|e| IpcError::Node(format!("{e:?}")))?;
    NodeBuilder::new()
        .name(&node_name)
        .signal_handling_mode(SignalHandlingMode::Disabled)
        .create::<Ipc>()
        .map_err(|e| IpcError::Node(format!("{e:?}")))
}

/// Removes the shared-memory resources left by processes that died without cleaning up, so a
/// restart right after a crash works. Returns the number of nodes cleaned.
pub fn cleanup_dead_nodes(node: &Node<Ipc>) -> usize {
    let state = node.try_cleanup_dead_nodes();
    state.cleanups as usize
}

fn service_name(name: &str) -> Result<ServiceName, IpcError> {
    ServiceName::new(name).map_err(|e| IpcError::InvalidName {
        name: name.to_string(),
        reason: format!("{e:?}"),
    })
}

macro_rules! typed_service {
    ($fn_name:ident, $ty:ty, $doc:literal) => {
        #[doc = $doc]
        pub fn $fn_name(
            node: &Node<Ipc>,
            name: &str,
        ) -> Result<
            iceoryx2::service::port_factory::publish_subscribe::PortFactory<Ipc, $ty, ()>,
            IpcError,
        > {
            node.service_builder(&service_name(name)?)
                .publish_subscribe::<$ty>()
                .history_size(HISTORY_SIZE)
                .subscriber_max_buffer_size(BUFFER_SIZE)
                .subscriber_max_borrowed_samples(MAX_BORROWED_SAMPLES)
                .enable_safe_overflow(true)
                .max_publishers(MAX_PUBLISHERS)
                .max_subscribers(MAX_SUBSCRIBERS)
                .max_nodes(MAX_NODES)
                .open_or_create()
                .map_err(|e| IpcError::Service {
                    name: name.to_string(),
                    reason: explain_open(&format!("{e:?}")),
                })
        }
    };
}

typed_service!(
    joint_state_service,
    JointState,
    "Opens (or creates) a joint state service."
);
typed_service!(
    joint_command_service,
    JointCommand,
    "Opens (or creates) a joint command service."
);
typed_service!(
    status_service,
    ControllerStatus,
    "Opens (or creates) a controller status service."
);
typed_service!(
    chunk_service,
    ActionChunkMsg,
    "Opens (or creates) the action chunk service."
);
typed_service!(
    rearm_service,
    RearmRequest,
    "Opens (or creates) the re-arm request service."
);

/// Port factory of a camera service: `[u8]` pixels with a [`CameraFrameHeader`] user header.
pub type CameraService =
    iceoryx2::service::port_factory::publish_subscribe::PortFactory<Ipc, [u8], CameraFrameHeader>;

/// Opens (or creates) a camera service.
pub fn camera_service(node: &Node<Ipc>, name: &str) -> Result<CameraService, IpcError> {
    node.service_builder(&service_name(name)?)
        .publish_subscribe::<[u8]>()
        .user_header::<CameraFrameHeader>()
        .history_size(HISTORY_SIZE)
        .subscriber_max_buffer_size(CAMERA_BUFFER_SIZE)
        .subscriber_max_borrowed_samples(MAX_BORROWED_SAMPLES)
        .enable_safe_overflow(true)
        .max_publishers(MAX_PUBLISHERS)
        .max_subscribers(MAX_SUBSCRIBERS)
        .max_nodes(MAX_NODES)
        .open_or_create()
        .map_err(|e| IpcError::Service {
            name: name.to_string(),
            reason: explain_open(&format!("{e:?}")),
        })
}

/// Event services of the robot-clocked tick (`[control] clock = "robot"`), named as the
/// publish-subscribe service whose samples they announce (iceoryx2 keeps the two kinds apart):
/// the robot notifies `NS/joint_state` after each state it publishes, the controller notifies
/// `NS/joint_command` after each command. At most [`MAX_EVENT_PORTS`] notifiers and listeners.
pub type EventService = iceoryx2::service::port_factory::event::PortFactory<Ipc>;

/// Notifiers and listeners an event service takes (each).
pub const MAX_EVENT_PORTS: usize = 8;

/// Opens (or creates) the event service `name`.
pub fn event_service(node: &Node<Ipc>, name: &str) -> Result<EventService, IpcError> {
    node.service_builder(&service_name(name)?)
        .event()
        .max_notifiers(MAX_EVENT_PORTS)
        .max_listeners(MAX_EVENT_PORTS)
        .max_nodes(MAX_NODES)
        .open_or_create()
        .map_err(|e| IpcError::Service {
            name: name.to_string(),
            reason: explain_open(&format!("{e:?}")),
        })
}

/// The service a port factory opens, by name (its errors say which; typed once, where the
/// service was opened).
fn port_name<F: iceoryx2::service::port_factory::PortFactory>(factory: &F) -> String {
    factory.name().as_str().to_string()
}

/// A notifier on `factory`.
pub fn notifier(factory: &EventService) -> Result<Notifier<Ipc>, IpcError> {
    factory
        .notifier_builder()
        .create()
        .map_err(|e| IpcError::Port {
            what: "notifier",
            name: port_name(factory),
            reason: explain_port(&format!("{e:?}")),
        })
}

/// A listener on `factory`.
pub fn listener(factory: &EventService) -> Result<Listener<Ipc>, IpcError> {
    factory
        .listener_builder()
        .create()
        .map_err(|e| IpcError::Port {
            what: "listener",
            name: port_name(factory),
            reason: explain_port(&format!("{e:?}")),
        })
}

/// Waits until `listener` is notified or `timeout` has passed, then takes every pending
/// notification. Returns true when one came. iceoryx2 0.10's own `timed_wait` sleeps in steps of
/// about 8 ms whatever the timeout (measured: 8.0 ms for 50 µs), too coarse for a 1 kHz robot
/// cycle: this waits with `ppoll` on the listener's file descriptor instead (its timeout is the
/// kernel's, within its timer slack: 50 µs for an ordinary thread, none for SCHED_FIFO).
/// No allocation.
pub fn wait_event(
    listener: &Listener<Ipc>,
    timeout: std::time::Duration,
) -> Result<bool, IpcError> {
    // SAFETY: the descriptor stays owned by the listener, which outlives this call; it is only
    // polled, never closed or read here
    let fd = unsafe { listener.file_descriptor().native_handle() };
    let mut pfd = libc::pollfd {
        fd,
        events: libc::POLLIN,
        revents: 0,
    };
    let ts = libc::timespec {
        tv_sec: timeout.as_secs().min(i32::MAX as u64) as libc::time_t,
        tv_nsec: timeout.subsec_nanos() as libc::c_long,
    };
    // SAFETY: one valid pollfd, a valid timespec, no signal mask change
    let r = unsafe { libc::ppoll(&mut pfd, 1, &ts, std::ptr::null()) };
    if r < 0 {
        let e = std::io::Error::last_os_error();
        if e.kind() != std::io::ErrorKind::Interrupted {
            return Err(IpcError::Port {
                what: "listener",
                name: String::new(),
                reason: format!("ppoll: {e}"),
            });
        }
    }
    let mut woke = false;
    listener
        .try_wait(|_| woke = true)
        .map_err(|e| IpcError::Port {
            what: "listener",
            name: String::new(),
            reason: explain_port(&format!("{e:?}")),
        })?;
    Ok(woke)
}

/// A publisher that never blocks: when a subscriber's buffer is full its oldest sample goes.
pub fn publisher<T: core::fmt::Debug + ZeroCopySend>(
    factory: &iceoryx2::service::port_factory::publish_subscribe::PortFactory<Ipc, T, ()>,
) -> Result<Publisher<Ipc, T, ()>, IpcError> {
    factory
        .publisher_builder()
        .max_loaned_samples(MAX_LOANED_SAMPLES)
        .create()
        .map_err(|e| {
            let raw = format!("{e:?}");
            let reason = if raw.contains("ExceedsMaxSupportedPublishers") {
                format!(
                    "the service already has its maximum of {MAX_PUBLISHERS} publishers ({raw}): \
                     other processes hold them — another controller or driver on this \
                     namespace, or a process of this user squatting it; find them with \
                     `chunkrt monitor --namespace ...`, stop them, or use another namespace"
                )
            } else {
                raw
            };
            IpcError::Port {
                what: "publisher",
                name: port_name(factory),
                reason,
            }
        })
}

/// A subscriber keeping the last few samples.
pub fn subscriber<T: core::fmt::Debug + ZeroCopySend>(
    factory: &iceoryx2::service::port_factory::publish_subscribe::PortFactory<Ipc, T, ()>,
) -> Result<Subscriber<Ipc, T, ()>, IpcError> {
    factory
        .subscriber_builder()
        .buffer_size(BUFFER_SIZE)
        .create()
        .map_err(|e| IpcError::Port {
            what: "subscriber",
            name: port_name(factory),
            reason: explain_port(&format!("{e:?}")),
        })
}

/// A camera publisher sized for frames up to `max_bytes` (allocated once, up front).
pub fn camera_publisher(
    factory: &CameraService,
    max_bytes: usize,
) -> Result<Publisher<Ipc, [u8], CameraFrameHeader>, IpcError> {
    factory
        .publisher_builder()
        .initial_max_slice_len(max_bytes.max(1))
        .allocation_strategy(AllocationStrategy::Static)
        .max_loaned_samples(MAX_LOANED_SAMPLES)
        .create()
        .map_err(|e| IpcError::Port {
            what: "camera publisher",
            name: port_name(factory),
            reason: explain_port(&format!("{e:?}")),
        })
}

/// A camera subscriber.
pub fn camera_subscriber(
    factory: &CameraService,
) -> Result<Subscriber<Ipc, [u8], CameraFrameHeader>, IpcError> {
    factory
        .subscriber_builder()
        .buffer_size(CAMERA_BUFFER_SIZE)
        .create()
        .map_err(|e| IpcError::Port {
            what: "camera subscriber",
            name: port_name(factory),
            reason: explain_port(&format!("{e:?}")),
        })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_squatted_service_is_named_with_what_to_do() {
        // another program made the joint state service first, with one publisher allowed
        let node = node("test-squat").unwrap();
        let name = format!("chunkrt/test-squat-{}/joint_state", std::process::id());
        let _squat = node
            .service_builder(&service_name(&name).unwrap())
            .publish_subscribe::<crate::JointState>()
            .max_publishers(1)
            .create()
            .unwrap();
        let e = match joint_state_service(&node, &name) {
            Ok(_) => panic!("a squatted service was opened"),
            Err(e) => e.to_string(),
        };
        assert!(
            e.contains(&name) && e.contains("another program") && e.contains("--namespace"),
            "{e}"
        );
    }

    #[test]
    fn namespace_rules() {
        assert!(Namespace::new("chunkrt/arm0").is_ok());
        assert!(Namespace::new("").is_err());
        assert!(Namespace::new("/x").is_err());
        assert!(Namespace::new("a b").is_err());
        let ns = Namespace::new("chunkrt/t1").unwrap();
        assert_eq!(ns.camera("base"), "chunkrt/t1/camera/base");
        assert_eq!(ns.joint_state(), "chunkrt/t1/joint_state");
    }
}
