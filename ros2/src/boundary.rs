//! What the bridge takes from the ROS 2 side, checked before anything reaches chunkrt: a
//! `JointState` is matched to the configured joints by name (extra joints ignored) or refused
//! with a typed reason; every refusal is counted by kind and logged at a bounded rate.

use chunkrt_ipc::MAX_DOF;

use crate::msg;

/// More names than this in one `JointState` is not a robot (refused before it is searched).
pub const MAX_NAMES: usize = 256;

/// Why a `JointState` was refused.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum StateError {
    /// `name` is empty: nothing to match by.
    NoNames,
    /// More than [`MAX_NAMES`] names.
    TooManyNames { names: usize },
    /// `position` (or a non-empty `velocity` / `effort`) has another length than `name`.
    Length {
        field: &'static str,
        len: usize,
        names: usize,
    },
    /// A name appears twice (`index` is the second).
    Repeated { index: usize },
    /// A configured joint is not in the message.
    Missing { joint: usize },
    /// A configured joint's value is NaN or infinite.
    NonFinite { joint: usize, field: &'static str },
}

/// Kinds of refusal, for the counters (indices of [`ErrorCounters::counts`]).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum ErrorKind {
    StateNames = 0,
    StateLength = 1,
    StateMissing = 2,
    StateNonFinite = 3,
    StampSkew = 4,
    Decode = 5,
    ForeignCommander = 6,
    PeerSilent = 7,
    CommandRefused = 8,
    PublishFailed = 9,
    ImageRejected = 10,
    StaleArrival = 11,
}

/// Number of [`ErrorKind`]s.
pub const ERROR_KINDS: usize = 12;

impl ErrorKind {
    /// Every kind, in counter order.
    pub const ALL: [ErrorKind; ERROR_KINDS] = [
        ErrorKind::StateNames,
        ErrorKind::StateLength,
        ErrorKind::StateMissing,
        ErrorKind::StateNonFinite,
        ErrorKind::StampSkew,
        ErrorKind::Decode,
        ErrorKind::ForeignCommander,
        ErrorKind::PeerSilent,
        ErrorKind::CommandRefused,
        ErrorKind::PublishFailed,
        ErrorKind::ImageRejected,
        ErrorKind::StaleArrival,
    ];

    /// The key in the summary line.
    pub const fn key(self) -> &'static str {
        match self {
            ErrorKind::StateNames => "state_bad_names",
            ErrorKind::StateLength => "state_bad_length",
            ErrorKind::StateMissing => "state_missing_joint",
            ErrorKind::StateNonFinite => "state_non_finite",
            ErrorKind::StampSkew => "stamp_skew",
            ErrorKind::Decode => "decode_errors",
            ErrorKind::ForeignCommander => "foreign_commanders",
            ErrorKind::PeerSilent => "peer_silences",
            ErrorKind::CommandRefused => "commands_refused",
            ErrorKind::PublishFailed => "publish_errors",
            ErrorKind::ImageRejected => "images_rejected",
            ErrorKind::StaleArrival => "stale_arrivals",
        }
    }
}

impl StateError {
    /// The counter this refusal goes to.
    pub const fn kind(&self) -> ErrorKind {
        match self {
            StateError::NoNames | StateError::TooManyNames { .. } | StateError::Repeated { .. } => {
                ErrorKind::StateNames
            }
            StateError::Length { .. } => ErrorKind::StateLength,
            StateError::Missing { .. } => ErrorKind::StateMissing,
            StateError::NonFinite { .. } => ErrorKind::StateNonFinite,
        }
    }

    /// The refusal in words, naming the joint from `names` (the configured ROS 2 names).
    pub fn describe(&self, names: &[String], msg: &msg::JointState) -> String {
        let cfg = |j: usize| names.get(j).map(String::as_str).unwrap_or("?");
        match *self {
            StateError::NoNames => "JointState without names: joints are matched by name".into(),
            StateError::TooManyNames { names } => {
                format!("JointState with {names} names (at most {MAX_NAMES})")
            }
            StateError::Length { field, len, names } => {
                format!("JointState.{field} has {len} values for {names} names")
            }
            StateError::Repeated { index } => format!(
                "JointState names joint {:?} twice",
                msg.name.get(index).map(String::as_str).unwrap_or("?")
            ),
            StateError::Missing { joint } => format!(
                "JointState lacks joint {:?} (configured in ros2.joints; the message names {})",
                cfg(joint),
                preview(&msg.name)
            ),
            StateError::NonFinite { joint, field } => {
                format!("JointState.{field} of joint {:?} is not finite", cfg(joint))
            }
        }
    }
}

fn preview(names: &[String]) -> String {
    let mut s = String::from("[");
    for (i, n) in names.iter().take(8).enumerate() {
        if i > 0 {
            s.push_str(", ");
        }
        let short: String = n.chars().take(40).collect();
        s.push_str(&format!("{short:?}"));
    }
    if names.len() > 8 {
        s.push_str(&format!(", … {} more", names.len() - 8));
    }
    s.push(']');
    s
}

/// A joint state matched to the configuration's order.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Matched {
    pub position: [f64; MAX_DOF],
    pub velocity: [f64; MAX_DOF],
    pub effort: [f64; MAX_DOF],
}

/// Matches `JointState`s by name to the configured joints. Remembers where each joint was last
/// time (robots send the same order every time), so a message costs one comparison per joint.
#[derive(Debug, Clone)]
pub struct JointMap {
    names: Vec<String>,
    cached: [usize; MAX_DOF],
}

impl JointMap {
    /// A map for `names` (1..=MAX_DOF, unique: checked by the configuration).
    pub fn new(names: &[String]) -> Self {
        let mut cached = [0; MAX_DOF];
        for (j, c) in cached.iter_mut().enumerate().take(names.len()) {
            *c = j;
        }
        Self {
            names: names.to_vec(),
            cached,
        }
    }

    /// The configured ROS 2 names.
    pub fn names(&self) -> &[String] {
        &self.names
    }

    /// Checks `m` and returns its configured joints in order.
    pub fn map(&mut self, m: &msg::JointState) -> Result<Matched, StateError> {
        let names = m.name.len();
        if names == 0 {
            return Err(StateError::NoNames);
        }
        if names > MAX_NAMES {
            return Err(StateError::TooManyNames { names });
        }
        if m.position.len() != names {
            return Err(StateError::Length {
                field: "position",
                len: m.position.len(),
                names,
            });
        }
        for (field, v) in [("velocity", &m.velocity), ("effort", &m.effort)] {
            if !v.is_empty() && v.len() != names {
                return Err(StateError::Length {
                    field,
                    len: v.len(),
                    names,
                });
            }
        }
        for i in 1..names {
            if m.name[..i].contains(&m.name[i]) {
                return Err(StateError::Repeated { index: i });
            }
        }
        let mut out = Matched {
            position: [0.0; MAX_DOF],
            velocity: [0.0; MAX_DOF],
            effort: [0.0; MAX_DOF],
        };
        for j in 0..self.names.len() {
            let want = &self.names[j];
            let at = match m.name.get(self.cached[j]) {
                Some(n) if n == want => self.cached[j],
                _ => match m.name.iter().position(|n| n == want) {
                    Some(i) => {
                        self.cached[j] = i;
                        i
                    }
                    None => return Err(StateError::Missing { joint: j }),
                },
            };
            out.position[j] = m.position[at];
            if !m.velocity.is_empty() {
                out.velocity[j] = m.velocity[at];
            }
            if !m.effort.is_empty() {
                out.effort[j] = m.effort[at];
            }
            for (field, v) in [
                ("position", out.position[j]),
                ("velocity", out.velocity[j]),
                ("effort", out.effort[j]),
            ] {
                if !v.is_finite() {
                    return Err(StateError::NonFinite { joint: j, field });
                }
            }
        }
        Ok(out)
    }
}

/// Counted, rate-limited errors: the first few of each kind are logged, then at most one line a
/// second per kind with the count since.
#[derive(Debug, Clone, Default)]
pub struct ErrorCounters {
    pub counts: [u64; ERROR_KINDS],
    logged_at: [u64; ERROR_KINDS],
    unlogged: [u64; ERROR_KINDS],
}

/// Errors of each kind logged one by one before the rate limit.
const FIRST_LOGGED: u64 = 5;
/// The rate limit after that (ns).
const LOG_EVERY_NS: u64 = 1_000_000_000;

impl ErrorCounters {
    /// Counts one error of `kind` at `now_ns`; logs it (the text from `what`, called only when
    /// logged) while within the rate. Returns whether it was logged.
    pub fn count(&mut self, kind: ErrorKind, now_ns: u64, what: impl FnOnce() -> String) -> bool {
        let k = kind as usize;
        self.counts[k] += 1;
        if self.counts[k] <= FIRST_LOGGED
            || now_ns.saturating_sub(self.logged_at[k]) >= LOG_EVERY_NS
        {
            let more = if self.unlogged[k] > 0 {
                format!(" ({} more not logged since the last)", self.unlogged[k])
            } else {
                String::new()
            };
            tracing::warn!(
                "ros2: {}: {}{more} [{} in all]",
                kind.key(),
                what(),
                self.counts[k]
            );
            self.logged_at[k] = now_ns;
            self.unlogged[k] = 0;
            true
        } else {
            self.unlogged[k] += 1;
            false
        }
    }

    /// Errors of `kind` so far.
    pub fn get(&self, kind: ErrorKind) -> u64 {
        self.counts[kind as usize]
    }

    /// `key=count` for every kind.
    pub fn summary(&self) -> String {
        ErrorKind::ALL
            .iter()
            .map(|k| format!("{}={}", k.key(), self.get(*k)))
            .collect::<Vec<_>>()
            .join(" ")
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn js(names: &[&str], pos: &[f64]) -> msg::JointState {
        msg::JointState {
            name: names.iter().map(|s| s.to_string()).collect(),
            position: pos.to_vec(),
            ..Default::default()
        }
    }

    fn map() -> JointMap {
        JointMap::new(&["a".to_string(), "b".to_string()])
    }

    #[test]
    fn joints_are_matched_by_name_in_any_order_and_extras_ignored() {
        let mut m = map();
        let r = m.map(&js(&["x", "b", "a"], &[9.0, 2.0, 1.0])).unwrap();
        assert_eq!(&r.position[..2], &[1.0, 2.0]);
        let r = m.map(&js(&["a", "b"], &[3.0, 4.0])).unwrap();
        assert_eq!(&r.position[..2], &[3.0, 4.0]);
    }

    #[test]
    fn every_lie_is_refused_with_its_reason() {
        let mut m = map();
        assert_eq!(m.map(&js(&[], &[])), Err(StateError::NoNames));
        assert_eq!(
            m.map(&js(&["a", "b"], &[1.0])),
            Err(StateError::Length {
                field: "position",
                len: 1,
                names: 2
            })
        );
        assert_eq!(
            m.map(&js(&["a", "a", "b"], &[1.0, 1.0, 2.0])),
            Err(StateError::Repeated { index: 1 })
        );
        let e = m.map(&js(&["a", "c"], &[1.0, 2.0])).unwrap_err();
        assert_eq!(e, StateError::Missing { joint: 1 });
        assert!(e
            .describe(m.names(), &js(&["a", "c"], &[1.0, 2.0]))
            .contains("lacks joint \"b\""));
        assert_eq!(
            m.map(&js(&["a", "b"], &[f64::NAN, 2.0])),
            Err(StateError::NonFinite {
                joint: 0,
                field: "position"
            })
        );
        let mut v = js(&["a", "b"], &[1.0, 2.0]);
        v.velocity = vec![0.0, f64::INFINITY];
        assert_eq!(
            m.map(&v),
            Err(StateError::NonFinite {
                joint: 1,
                field: "velocity"
            })
        );
        // a NaN on a joint that is not configured is not ours to judge
        assert!(m.map(&js(&["a", "b", "z"], &[1.0, 2.0, f64::NAN])).is_ok());
        let many: Vec<String> = (0..MAX_NAMES + 1).map(|i| format!("j{i}")).collect();
        let big = msg::JointState {
            position: vec![0.0; many.len()],
            name: many,
            ..Default::default()
        };
        assert!(matches!(m.map(&big), Err(StateError::TooManyNames { .. })));
    }

    #[test]
    fn counters_count_every_error_but_log_few() {
        let mut c = ErrorCounters::default();
        let mut logged = 0;
        for i in 0..1000u64 {
            if c.count(ErrorKind::StateMissing, i * 1000, String::new) {
                logged += 1;
            }
        }
        assert_eq!(c.get(ErrorKind::StateMissing), 1000);
        assert_eq!(logged, FIRST_LOGGED);
        // then one a second
        assert!(c.count(ErrorKind::StateMissing, 2_000_000_000, String::new));
        assert!(!c.count(ErrorKind::StateMissing, 2_000_000_001, String::new));
    }
}
