//! `monitor`: lists chunkrt's iceoryx2 services and shows, per service, the live message rate,
//! the publish → receive latency and the last values (like `ros2 topic hz` + `echo`).
//!
//! Services are found with iceoryx2's service listing, filtered to the namespace (or every
//! `chunkrt/…` service with `--all`), and recognised by their payload / user-header type name.
//! The rate comes from the publisher's own sequence numbers and timestamps, so samples that a
//! slow monitor misses (safe overflow) do not make it look slower. Latency is
//! `monotonic_ns()` at receipt minus the message's publish (or measurement) time.

use std::collections::BTreeMap;
use std::io::{IsTerminal, Write};
use std::sync::atomic::Ordering;
use std::time::Duration;

use anyhow::Context;
use chunkrt_ipc::services::{self, Ipc};
use chunkrt_ipc::*;
use iceoryx2::port::subscriber::Subscriber;
use iceoryx2::prelude::{CallbackProgression, Node, Service};
use iceoryx2::service::static_config::messaging_pattern::MessagingPattern as Pattern;

use crate::common::{end_time_ns, open_node, CommonArgs};
use crate::shutdown;

/// Command-line arguments.
#[derive(Debug, Clone, PartialEq, clap::Args)]
pub struct Args {
    #[command(flatten)]
    pub common: CommonArgs,
    /// Show every `chunkrt/…` service, not only the namespace's.
    #[arg(long)]
    pub all: bool,
    /// Measure for one `--interval`, print one table and exit.
    #[arg(long)]
    pub once: bool,
    /// Stop after this many seconds.
    #[arg(long, value_name = "SECONDS")]
    pub duration: Option<f64>,
    /// Refresh (and measurement window) period in seconds.
    #[arg(long, value_name = "SECONDS", default_value_t = 1.0)]
    pub interval: f64,
    /// Print every joint of the last values (default: the first 6).
    #[arg(long)]
    pub wide: bool,
}

impl Default for Args {
    /// The same values as an empty command line.
    fn default() -> Self {
        Self {
            common: CommonArgs::default(),
            all: false,
            once: false,
            duration: None,
            interval: 1.0,
            wide: false,
        }
    }
}

/// What a service carries, from its type names.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Kind {
    JointState,
    JointCommand,
    Status,
    Camera,
    /// A type this monitor does not know (listed without statistics).
    Unknown,
}

impl Kind {
    /// Recognises a publish-subscribe service by payload and user-header type names.
    pub fn from_type_names(payload: &str, user_header: &str) -> Self {
        use chunkrt_ipc::{type_name_of, CameraFrameHeader, ControllerStatus};
        // the contract's own type names (a new message version is recognised without an edit)
        let plain = user_header == "()";
        if plain && payload == type_name_of::<JointState>() {
            Kind::JointState
        } else if plain && payload == type_name_of::<JointCommand>() {
            Kind::JointCommand
        } else if plain && payload == type_name_of::<ControllerStatus>() {
            Kind::Status
        } else if payload == "u8" && user_header == type_name_of::<CameraFrameHeader>() {
            Kind::Camera
        } else {
            Kind::Unknown
        }
    }

    fn label(self) -> &'static str {
        match self {
            Kind::JointState => "JointState",
            Kind::JointCommand => "JointCommand",
            Kind::Status => "ControllerStatus",
            Kind::Camera => "CameraFrame",
            Kind::Unknown => "unknown",
        }
    }
}

/// A chunkrt-looking publish-subscribe service found by the listing.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Listed {
    pub name: String,
    pub kind: Kind,
    /// `payload / user header` type names as iceoryx2 has them.
    pub types: String,
}

/// Every publish-subscribe service whose name starts with `prefix`, sorted by name.
pub fn list_services(prefix: &str) -> anyhow::Result<Vec<Listed>> {
    let mut out = Vec::new();
    <Ipc as Service>::list(iceoryx2::config::Config::global_config(), |details| {
        let cfg = &details.static_details;
        let name = cfg.name().as_str().to_string();
        if name.starts_with(prefix) {
            if let Pattern::PublishSubscribe(ps) = cfg.messaging_pattern() {
                let t = ps.message_type_details();
                let payload = t.payload.type_name().to_string();
                let header = t.user_header.type_name().to_string();
                out.push(Listed {
                    kind: Kind::from_type_names(&payload, &header),
                    types: format!("{payload} / {header}"),
                    name,
                });
            }
        }
        CallbackProgression::Continue
    })
    .map_err(|e| anyhow::anyhow!("cannot list iceoryx2 services: {e:?}"))?;
    out.sort_by(|a, b| a.name.cmp(&b.name));
    Ok(out)
}

enum Port {
    JointState(Subscriber<Ipc, JointState, ()>),
    JointCommand(Subscriber<Ipc, JointCommand, ()>),
    Status(Subscriber<Ipc, ControllerStatus, ()>),
    Camera(Subscriber<Ipc, [u8], CameraFrameHeader>),
    None,
}

/// Statistics of one service over the current window.
#[derive(Debug, Clone, Default)]
pub struct Stats {
    /// Samples received in the window.
    pub received: u64,
    /// (publisher, seq, time) of the first and last sample of the window.
    first: Option<(u128, u64, u64)>,
    last: Option<(u128, u64, u64)>,
    latency_sum_ns: f64,
    latency_max_ns: u64,
    /// Samples that failed validation in the window.
    pub invalid: u64,
    /// Last values, formatted.
    pub last_value: String,
    /// The distinct publishers of the window (at most [`MAX_NAMED_PUBLISHERS`] named): more
    /// than one on a status or command service is a second controller or a forger.
    pub publishers: Vec<u128>,
    /// Samples of the window from publishers beyond the named ones.
    pub unnamed_samples: u64,
}

/// Publishers named per service and window.
pub const MAX_NAMED_PUBLISHERS: usize = 4;

impl Stats {
    fn record(&mut self, origin: u128, seq: u64, time_ns: u64, now_ns: u64, since_ns: u64) {
        if time_ns < since_ns {
            // Sent before we subscribed (the service's history): a value, not a measurement.
            return;
        }
        self.received += 1;
        if !self.publishers.contains(&origin) {
            if self.publishers.len() < MAX_NAMED_PUBLISHERS {
                self.publishers.push(origin);
            } else {
                self.unnamed_samples += 1;
            }
        }
        let lat = now_ns.saturating_sub(time_ns);
        self.latency_sum_ns += lat as f64;
        self.latency_max_ns = self.latency_max_ns.max(lat);
        match self.first {
            Some((o, _, _)) if o == origin => {}
            _ => self.first = Some((origin, seq, time_ns)),
        }
        self.last = Some((origin, seq, time_ns));
    }

    /// Messages per second from the publisher's seq / timestamps (`None`: fewer than two).
    pub fn rate_hz(&self) -> Option<f64> {
        let (o0, s0, t0) = self.first?;
        let (o1, s1, t1) = self.last?;
        if o0 != o1 || s1 <= s0 || t1 <= t0 {
            return None;
        }
        Some((s1 - s0) as f64 / ((t1 - t0) as f64 * 1e-9))
    }

    /// "publishers=N (ids)" when more than one publisher spoke in the window, else empty.
    pub fn publishers_note(&self) -> String {
        if self.publishers.len() < 2 {
            return String::new();
        }
        let ids: Vec<String> = self
            .publishers
            .iter()
            .map(|id| format!("{:#x}", *id as u64))
            .collect();
        if self.unnamed_samples > 0 {
            format!(
                " PUBLISHERS>{} ({}; {} samples from others)",
                self.publishers.len(),
                ids.join(", "),
                self.unnamed_samples
            )
        } else {
            format!(" PUBLISHERS={} ({})", self.publishers.len(), ids.join(", "))
        }
    }

    /// Mean latency in µs.
    pub fn latency_avg_us(&self) -> Option<f64> {
        (self.received > 0).then(|| self.latency_sum_ns / self.received as f64 / 1e3)
    }

    fn reset_window(&mut self) {
        let last_value = std::mem::take(&mut self.last_value);
        *self = Stats {
            first: self.last,
            last: self.last,
            last_value,
            ..Default::default()
        };
    }
}

struct Watched {
    listed: Listed,
    port: Port,
    stats: Stats,
    /// When the subscriber was created (monotonic ns).
    since_ns: u64,
}

fn fmt_joints(v: &[f64], n: usize, wide: bool) -> String {
    let shown = if wide { n } else { n.min(6) };
    let mut s = String::from("[");
    for (i, x) in v.iter().take(shown).enumerate() {
        if i > 0 {
            s.push_str(", ");
        }
        s.push_str(&format!("{x:.3}"));
    }
    if shown < n {
        s.push_str(", …");
    }
    s.push(']');
    s
}

fn joint_flags(flags: u32) -> String {
    let names = [
        (JOINT_STATUS_HOLDING, "HOLDING"),
        (JOINT_STATUS_AT_REST, "AT_REST"),
        (JOINT_STATUS_COMMAND_EXPIRED, "EXPIRED"),
        (JOINT_STATUS_COMMAND_TIMEOUT, "TIMEOUT"),
        (JOINT_STATUS_COMMAND_REJECTED, "REJECTED"),
        (JOINT_STATUS_LIMIT_CLAMPED, "CLAMPED"),
        (JOINT_STATUS_COMMAND_FAR, "FAR"),
    ];
    let set: Vec<&str> = names
        .iter()
        .filter(|(b, _)| flags & b != 0)
        .map(|(_, n)| *n)
        .collect();
    if set.is_empty() {
        "ok".to_string()
    } else {
        set.join("|")
    }
}

impl Watched {
    fn open(node: &Node<Ipc>, listed: Listed) -> Self {
        let name = listed.name.as_str();
        let port = match listed.kind {
            Kind::JointState => services::joint_state_service(node, name)
                .and_then(|f| services::subscriber(&f))
                .map(Port::JointState),
            Kind::JointCommand => services::joint_command_service(node, name)
                .and_then(|f| services::subscriber(&f))
                .map(Port::JointCommand),
            Kind::Status => services::status_service(node, name)
                .and_then(|f| services::subscriber(&f))
                .map(Port::Status),
            Kind::Camera => services::camera_service(node, name)
                .and_then(|f| services::camera_subscriber(&f))
                .map(Port::Camera),
            Kind::Unknown => Ok(Port::None),
        };
        let port = port.unwrap_or_else(|e| {
            tracing::warn!("monitor: cannot subscribe to '{name}': {e}");
            Port::None
        });
        Self {
            listed,
            port,
            stats: Stats::default(),
            since_ns: monotonic_ns(),
        }
    }

    /// Drains the subscriber.
    fn poll(&mut self, wide: bool) {
        let st = &mut self.stats;
        let since = self.since_ns;
        match &self.port {
            Port::JointState(sub) => {
                while let Ok(Some(s)) = sub.receive() {
                    let now = monotonic_ns();
                    let m = s.payload();
                    st.record(s.origin().value(), m.seq, m.measurement_time_ns, now, since);
                    if validate_joint_state(m, None).is_err() {
                        st.invalid += 1;
                        continue;
                    }
                    let n = m.n_dof as usize;
                    let obeys = match m.obeyed_publisher() {
                        None => String::new(),
                        Some(0) => " obeys=nobody".to_string(),
                        Some(id) => format!(" obeys={:#x}", id as u64),
                    };
                    st.last_value = format!(
                        "seq={} n_dof={n} flags={}{obeys} pos={}",
                        m.seq,
                        joint_flags(m.status_flags),
                        fmt_joints(&m.position, n, wide)
                    );
                }
            }
            Port::JointCommand(sub) => {
                while let Ok(Some(s)) = sub.receive() {
                    let now = monotonic_ns();
                    let m = s.payload();
                    st.record(s.origin().value(), m.seq, m.publish_time_ns, now, since);
                    if validate_joint_command(m, None).is_err() {
                        st.invalid += 1;
                        continue;
                    }
                    let n = m.n_dof as usize;
                    let mode = if m.mode == COMMAND_MODE_HOLD {
                        "hold"
                    } else {
                        "position"
                    };
                    st.last_value = format!(
                        "seq={} mode={mode} chunk={} deadline_in_us={:.0} pos={}",
                        m.seq,
                        m.chunk_id,
                        (m.deadline_ns as f64 - m.publish_time_ns as f64) / 1e3,
                        fmt_joints(&m.position, n, wide)
                    );
                }
            }
            Port::Status(sub) => {
                while let Ok(Some(s)) = sub.receive() {
                    let now = monotonic_ns();
                    let m = s.payload();
                    st.record(s.origin().value(), m.seq, m.publish_time_ns, now, since);
                    let rejected: u64 = m.rejected.iter().sum();
                    st.last_value = format!(
                        "state={} ({}) ticks={} overruns={} chunks={} rejected={rejected} \
                         foreign_statuses={} late_p99_us={:.1} compute_p99_us={:.1} \
                         inference_ms={:.1}",
                        controller_state_name(m.state),
                        chunkrt_ipc::state_reason_name(m.state_reason),
                        m.ticks,
                        m.overruns,
                        m.chunks,
                        m.foreign_statuses,
                        m.lateness_p99_ns as f64 / 1e3,
                        m.compute_p99_ns as f64 / 1e3,
                        m.last_inference_latency_ns as f64 / 1e6
                    );
                }
            }
            Port::Camera(sub) => {
                while let Ok(Some(s)) = sub.receive() {
                    let now = monotonic_ns();
                    let h = *s.user_header();
                    st.record(s.origin().value(), h.seq, h.publish_time_ns, now, since);
                    if validate_frame(&h, s.payload().len(), u32::MAX, u32::MAX).is_err() {
                        st.invalid += 1;
                        continue;
                    }
                    st.last_value = format!(
                        "seq={} id={} {}x{} {} capture_to_publish_us={:.0}",
                        h.seq,
                        h.camera_id,
                        h.width,
                        h.height,
                        encoding_name(h.encoding),
                        h.publish_time_ns.saturating_sub(h.capture_time_ns) as f64 / 1e3
                    );
                }
            }
            Port::None => {}
        }
    }

    fn line(&self) -> String {
        let s = &self.stats;
        let rate = s
            .rate_hz()
            .map(|r| format!("{r:.1}"))
            .unwrap_or_else(|| "-".into());
        let lat = s
            .latency_avg_us()
            .map(|l| format!("{l:.1}"))
            .unwrap_or_else(|| "-".into());
        let lat_max = if s.received > 0 {
            format!("{:.1}", s.latency_max_ns as f64 / 1e3)
        } else {
            "-".into()
        };
        if matches!(self.port, Port::None) {
            return format!(
                "{}  {}  ({})",
                self.listed.name,
                self.listed.kind.label(),
                self.listed.types
            );
        }
        format!(
            "{}  {}  rate_hz={rate} received={} latency_avg_us={lat} latency_max_us={lat_max} \
             invalid={}{}  {}",
            self.listed.name,
            self.listed.kind.label(),
            s.received,
            s.invalid,
            s.publishers_note(),
            if s.last_value.is_empty() {
                "(no data)"
            } else {
                &s.last_value
            }
        )
    }
}

/// Runs until SIGINT / SIGTERM, `--duration`, or after one window with `--once`.
pub fn run(args: Args) -> anyhow::Result<()> {
    let stop = shutdown::flag();
    let (_cfg, ns) = args.common.load()?;
    anyhow::ensure!(
        args.interval.is_finite() && (0.05..=3600.0).contains(&args.interval),
        "--interval {}: must be in 0.05..=3600 seconds",
        args.interval
    );
    let prefix = if args.all {
        "chunkrt/".to_string()
    } else {
        format!("{}/", ns.as_str())
    };
    let node = open_node("chunkrt-monitor")?;
    let start = monotonic_ns();
    let end = end_time_ns(start, args.duration)?;
    let interval_ns = (args.interval * 1e9) as u64;
    let tty = std::io::stdout().is_terminal() && !args.once;
    let mut watched: BTreeMap<String, Watched> = BTreeMap::new();
    let mut next_refresh = start + interval_ns;
    let mut printed_lines = 0usize;
    let mut stdout = std::io::stdout();

    let discover = |watched: &mut BTreeMap<String, Watched>| -> anyhow::Result<()> {
        for l in list_services(&prefix)? {
            if !watched.contains_key(&l.name) {
                watched.insert(l.name.clone(), Watched::open(&node, l));
            }
        }
        Ok(())
    };
    discover(&mut watched)?;
    loop {
        for w in watched.values_mut() {
            w.poll(args.wide);
        }
        let now = monotonic_ns();
        let finished = stop.load(Ordering::Relaxed) || now >= end;
        if now >= next_refresh || finished {
            let mut text = String::new();
            if watched.is_empty() {
                text.push_str(&format!("no services under '{prefix}'\n"));
            }
            for w in watched.values() {
                text.push_str(&w.line());
                text.push('\n');
            }
            if tty && printed_lines > 0 {
                // Move up and clear the previous table: one refreshing line per service.
                write!(stdout, "\x1b[{printed_lines}A\x1b[J").ok();
            } else if !tty && printed_lines > 0 {
                text.insert(0, '\n');
            }
            stdout.write_all(text.as_bytes()).context("stdout")?;
            stdout.flush().ok();
            printed_lines = text.lines().filter(|l| !l.is_empty()).count();
            if args.once || finished {
                break;
            }
            for w in watched.values_mut() {
                w.stats.reset_window();
            }
            discover(&mut watched)?;
            next_refresh += interval_ns;
        }
        std::thread::sleep(Duration::from_micros(500));
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn default_args_match_the_empty_command_line() {
        use clap::Parser;
        #[derive(clap::Parser)]
        struct Cli {
            #[command(flatten)]
            args: Args,
        }
        assert_eq!(Cli::parse_from(["monitor"]).args, Args::default());
    }

    #[test]
    fn kinds_and_rates() {
        assert_eq!(
            Kind::from_type_names("chunkrt.JointState.v2", "()"),
            Kind::JointState
        );
        assert_eq!(
            Kind::from_type_names("chunkrt.ControllerStatus.v4", "()"),
            Kind::Status
        );
        assert_eq!(
            Kind::from_type_names("chunkrt.ControllerStatus.v3", "()"),
            Kind::Unknown,
            "an old status version is not read as the current one"
        );
        assert_eq!(
            Kind::from_type_names("u8", "chunkrt.CameraFrameHeader.v1"),
            Kind::Camera
        );
        assert_eq!(Kind::from_type_names("u8", "()"), Kind::Unknown);
        let mut s = Stats::default();
        assert_eq!(s.rate_hz(), None);
        s.record(1, 10, 1_000_000_000, 1_000_050_000, 0);
        s.record(1, 20, 1_010_000_000, 1_010_150_000, 0);
        assert!((s.rate_hz().unwrap() - 1000.0).abs() < 1e-6);
        assert!((s.latency_avg_us().unwrap() - 100.0).abs() < 1e-6);
        s.reset_window();
        assert_eq!(s.received, 0);
        s.record(1, 30, 1_020_000_000, 1_020_000_000, 0);
        assert!((s.rate_hz().unwrap() - 1000.0).abs() < 1e-6);
        // a new publisher restarts the measurement
        s.record(2, 1, 1_030_000_000, 1_030_000_000, 0);
        // samples from before the subscription do not count
        s.record(2, 2, 5, 1_031_000_000, 1_000_000_000);
        assert_eq!(s.received, 2);
        assert_eq!(s.rate_hz(), None);
        // two publishers in one window are named
        assert_eq!(s.publishers_note(), " PUBLISHERS=2 (0x1, 0x2)");
        for id in [3, 4, 5, 6, 7, 7] {
            s.record(id, 1, 1_040_000_000, 1_040_000_000, 0);
        }
        assert_eq!(
            s.publishers_note(),
            " PUBLISHERS>4 (0x1, 0x2, 0x3, 0x4; 4 samples from others)"
        );
        s.reset_window();
        assert_eq!(s.publishers_note(), "");
    }
}
