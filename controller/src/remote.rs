//! A policy on another machine as the chunk source (`[policy] source = "remote"`): the
//! observation the inference thread assembled from iceoryx2 goes to an openpi-protocol server
//! (`chunkrt serve`, openpi's `serve_policy.py`, SGLang, vLLM-Omni) and its reply becomes an
//! action chunk. Runs in the inference thread; the control thread never touches the network.
//!
//! - **What is sent**: the newest frame of every camera (and delayed view) as uint8 arrays, the
//!   state — the measured one, or with future-state inference where the current chunk will
//!   have taken the robot ([`Conditioner`]) — and the prompt, laid out as `[openpi]` says;
//!   with a chunkrt server also the real-time-chunking keys it advertises (guidance towards the
//!   previous chunk, a committed prefix) and a new noise seed when one was asked for.
//! - **Timing**: the chunk's `t_obs` stays the joint state's measurement time, so the delay
//!   estimate and the latency accounting include the network.
//! - **Failures**: a slow, dead or restarted server answers no request; the chunk source fails
//!   fast (the control tick asks again at its next tick), chunks expire and the robot holds
//!   exactly as with a slow local policy. The client reconnects with a backoff (0.1 s doubling
//!   to 2 s); when chunks flow again the controller resumes under the safety state machine's
//!   rules. A server whose metadata or actions do not fit the robot is an error at start-up and
//!   at every reconnect, never a motion.

use std::time::{Duration, Instant};

use anyhow::Context;

use chunkrt_ipc::{monotonic_ns, ENCODING_BGR8, ENCODING_MONO8};
use chunkrt_openpi::{
    decode, ChunkrtMetadata, Client, ClientConfig, ImageRef, Layout, Limits, Outgoing, Reply,
    Writer,
};
use chunkrt_policy::Conditioning;

use crate::chunk::ActionChunk;
use crate::conditioning::Conditioner;
use crate::config::{Config, Strategy};
use crate::contract::{ChunkSource, InferenceRequest, Observation};
use crate::inference::next_chunk_id;
use chunkrt_openpi::ActionSpace;

/// The first reconnection delay, doubled after every failed attempt up to [`BACKOFF_MAX`].
const BACKOFF_START: Duration = Duration::from_millis(100);
/// The longest reconnection delay.
const BACKOFF_MAX: Duration = Duration::from_secs(2);

/// A policy behind an openpi-protocol server.
pub struct RemoteSource {
    client_cfg: ClientConfig,
    layout: Layout,
    client: Option<Client>,
    /// What a chunkrt server says of itself (None: another kind of server).
    server: Option<ChunkrtMetadata>,
    conditioner: Conditioner,
    prompt: String,
    period_ns: u64,
    n_dof: usize,
    execute_horizon: usize,
    strategy: Strategy,
    truncate: bool,
    /// The image inputs the robot can send (cameras, then delayed views).
    inputs: Vec<String>,
    /// The server model's delayed views (from its metadata at the first connect).
    views: Vec<chunkrt_policy::DelayedView>,
    /// Chunk length: the server's (metadata or last reply), 0 until known.
    horizon: usize,
    next_attempt: Instant,
    backoff: Duration,
    /// The wait after a failed request of any kind (a transport error, a reply that is not
    /// msgpack, an error text, wrong shapes, non-finite actions), doubled per consecutive
    /// failure up to [`BACKOFF_MAX`]; back to [`BACKOFF_START`] after a good chunk.
    fail_backoff: Duration,
    /// Consecutive failed requests, and all of them.
    failures: u64,
    failures_total: u64,
    /// What the last failure was (a request's error, or the failed connect), for the answer
    /// given while its backoff is waited out.
    last_cause: String,
    reseed: Option<u64>,
    warned_fresh: bool,
    writer: Writer,
    pixels: Vec<Vec<u8>>,
    connects: u64,
    /// DROID's robot environment (`[openpi] action_space = "droid_joint_velocity"`).
    droid: Option<Droid>,
    /// The state sent with the last request (DROID: the gripper as DROID reports it); the
    /// velocity actions are integrated from its joints.
    sent_state: Vec<f64>,
}

/// How DROID's robot environment turns its actions into robot motion, as chunkrt executes it
/// (`ActionSpace::DroidJointVelocity`): the last joint is the gripper, its range the hand's
/// opening (width at `open`, closed at `closed`).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Droid {
    /// Rad per full-scale velocity action.
    pub max_joint_delta: f64,
    /// The gripper channel's value when open (the hand's full width) and closed.
    pub open: f64,
    /// The gripper channel's value when closed.
    pub closed: f64,
}

impl Droid {
    /// The gripper's state as DROID reports it: 0 open, 1 closed.
    pub fn gripper_state(&self, width: f64) -> f64 {
        ((self.open - width) / (self.open - self.closed)).clamp(0.0, 1.0)
    }

    /// The server's chunk (`rows` of `n` values: the joints' velocities in [-1, 1], then the
    /// gripper's position in [0, 1]) as positions from `state` (the joints as the observation
    /// saw them): DROID's robot environment sets each step's target to where the arm is plus
    /// `max_joint_delta` × the clipped velocity (droid/franka/robot.py); chunkrt makes the whole
    /// chunk at once, each step from the one before (what DROID computes when the arm reaches
    /// each target within its step), and binarises the gripper at 0.5 as openpi's DROID client
    /// does (examples/droid/main.py): closed above, open otherwise.
    pub fn positions(&self, state: &[f64], rows: &mut [f64], n: usize) {
        let joints = n.saturating_sub(1);
        let mut q: [f64; chunkrt_ipc::MAX_DOF] = [0.0; chunkrt_ipc::MAX_DOF];
        q[..joints].copy_from_slice(&state[..joints]);
        for row in rows.chunks_exact_mut(n) {
            for (a, q) in row[..joints].iter_mut().zip(q.iter_mut()) {
                let v = if a.is_finite() {
                    a.clamp(-1.0, 1.0)
                } else {
                    0.0
                };
                *q += self.max_joint_delta * v;
                *a = *q;
            }
            row[joints] = if row[joints] > 0.5 {
                self.closed
            } else {
                self.open
            };
        }
    }
}

/// `text` cut to 300 bytes (at a character boundary): a cause quoted in every answer given while
/// a backoff is waited out stays short whatever a server said.
fn cut(text: &str) -> String {
    let mut end = text.len().min(300);
    while !text.is_char_boundary(end) {
        end -= 1;
    }
    if end < text.len() {
        format!("{}…", &text[..end])
    } else {
        text.to_string()
    }
}

/// How the state is split over a layout's state keys: the last keys carry one value each (a
/// gripper), the first the rest (DROID: 7 joints, then the gripper).
fn state_split(parts: usize, n: usize) -> Vec<usize> {
    if parts <= 1 || n < parts {
        return Vec::new();
    }
    let mut v = vec![1; parts];
    v[0] = n - (parts - 1);
    v
}

impl RemoteSource {
    /// Connects to `policy.url` and checks that the server fits the robot (an error says why
    /// not); the delayed views, if the server's model has any, come from its metadata.
    pub fn connect(cfg: &Config) -> anyhow::Result<Self> {
        let p = &cfg.policy;
        let url = p.url.clone().context("policy.url is not set")?;
        let mut client_cfg = ClientConfig::new(&url);
        client_cfg.api_key = p
            .api_key
            .clone()
            .or_else(|| std::env::var("CHUNKRT_API_KEY").ok());
        client_cfg.connect_timeout = Duration::from_secs_f64(p.connect_timeout_ms / 1e3);
        client_cfg.reply_timeout =
            Duration::from_secs_f64(cfg.execution.inference_timeout_ms / 1e3);
        let layout = Layout::from_config(&cfg.openpi).map_err(anyhow::Error::msg)?;
        let droid = match layout.action_space {
            ActionSpace::JointPosition => None,
            ActionSpace::DroidJointVelocity => {
                let g = cfg
                    .robot
                    .joints
                    .last()
                    .filter(|g| g.step && cfg.robot.joints.len() >= 2)
                    .context(
                        "openpi.action_space = \"droid_joint_velocity\" needs the gripper as the \
                         robot's last joint, a step channel (its range the hand's opening)",
                    )?;
                Some(Droid {
                    max_joint_delta: layout.max_joint_delta,
                    open: g.position_max,
                    closed: g.position_min,
                })
            }
        };
        let mut me = Self {
            client_cfg,
            layout,
            client: None,
            server: None,
            conditioner: Conditioner::new(cfg),
            prompt: p.prompt.clone(),
            period_ns: (1e9 / p.action_rate_hz).round() as u64,
            n_dof: cfg.n_dof(),
            execute_horizon: cfg.execution.execute_horizon,
            strategy: cfg.execution.strategy,
            truncate: p.truncate_actions,
            inputs: cfg.cameras.iter().map(|c| c.name.clone()).collect(),
            views: Vec::new(),
            horizon: 0,
            next_attempt: Instant::now(),
            backoff: BACKOFF_START,
            fail_backoff: BACKOFF_START,
            failures: 0,
            failures_total: 0,
            last_cause: String::new(),
            reseed: None,
            warned_fresh: false,
            writer: Writer::new(),
            pixels: Vec::new(),
            connects: 0,
            droid,
            sent_state: Vec::with_capacity(chunkrt_ipc::MAX_DOF),
        };
        me.reconnect()
            .with_context(|| format!("policy.url = {url:?}"))?;
        Ok(me)
    }

    /// The server's URL.
    pub fn url(&self) -> &str {
        &self.client_cfg.url
    }

    /// What a chunkrt server said of itself at the last connect (None: another kind).
    pub fn server(&self) -> Option<&ChunkrtMetadata> {
        self.server.as_ref()
    }

    /// Successful connections so far (the first and every reconnect).
    pub fn connects(&self) -> u64 {
        self.connects
    }

    /// Failed requests so far (every kind), and how many of the last ones in a row.
    pub fn failures(&self) -> (u64, u64) {
        (self.failures_total, self.failures)
    }

    /// Connects and checks the fit; on failure the next attempt waits out the backoff.
    fn reconnect(&mut self) -> anyhow::Result<()> {
        self.client = None;
        let result = Client::connect(&self.client_cfg)
            .map_err(anyhow::Error::from)
            .and_then(|c| {
                let meta = ChunkrtMetadata::parse(&c.metadata());
                self.check_fit(meta.as_ref())?;
                Ok((c, meta))
            });
        match result {
            Ok((c, meta)) => {
                if let Some(m) = &meta {
                    self.horizon = m.action_horizon;
                }
                if self.connects == 0 {
                    // the controller keeps a frame history for these from the start; a later
                    // server must ask for the same (check_fit)
                    self.views = meta
                        .iter()
                        .flat_map(|m| &m.delayed_views)
                        .map(|(name, camera, delay_ms)| chunkrt_policy::DelayedView {
                            name: name.clone(),
                            camera: camera.clone(),
                            delay_ms: *delay_ms,
                        })
                        .collect();
                }
                self.server = meta;
                self.client = Some(c);
                self.backoff = BACKOFF_START;
                self.connects += 1;
                // one line per power of two: a server that fails every reply cannot flood the log
                let reconnects = self.connects - 1;
                if reconnects > 0 && reconnects.is_power_of_two() {
                    tracing::info!(
                        "remote policy: reconnected to {} ({reconnects} reconnects so far)",
                        self.client_cfg.url
                    );
                }
                Ok(())
            }
            Err(e) => {
                self.next_attempt = Instant::now() + self.backoff;
                self.backoff = (self.backoff * 2).min(BACKOFF_MAX);
                Err(e)
            }
        }
    }

    /// The server's metadata against the robot: image inputs it needs, the action dimension,
    /// the chunk length, the conditioning the strategy needs.
    fn check_fit(&mut self, meta: Option<&ChunkrtMetadata>) -> anyhow::Result<()> {
        let url = &self.client_cfg.url;
        let Some(m) = meta else {
            // openpi's, SGLang's or vLLM-Omni's server: plain chunks only
            anyhow::ensure!(
                self.strategy != Strategy::RtcTrained,
                "execution.strategy = \"rtc_trained\" needs a server that takes a committed \
                 action prefix; {url} is not a chunkrt server (its metadata has no 'chunkrt' \
                 entry): use strategy \"rtc\" or \"replace\", or chunkrt serve"
            );
            return Ok(());
        };
        let views: Vec<&String> = m.delayed_views.iter().map(|v| &v.0).collect();
        let missing: Vec<&String> = m
            .image_inputs
            .iter()
            .filter(|n| {
                !self.inputs.contains(n) && !views.contains(n) && !self.layout.optional.contains(n)
            })
            .collect();
        if self.connects > 0 {
            let same = m.delayed_views.len() == self.views.len()
                && m.delayed_views
                    .iter()
                    .zip(&self.views)
                    .all(|(a, b)| a.0 == b.name && a.1 == b.camera && a.2 == b.delay_ms);
            anyhow::ensure!(
                same,
                "the server's model now takes other delayed views than at start-up; restart \
                 the controller to serve it"
            );
        }
        if !missing.is_empty() && self.layout.images.is_none() {
            // chunkrt's layout: the server masks what is not sent, as the policy in process does
            tracing::warn!(
                "remote policy: the server's model takes the image input(s) {missing:?}, which \
                 this robot has no camera for: they are masked (cameras: {:?})",
                self.inputs
            );
        } else {
            anyhow::ensure!(
                missing.is_empty(),
                "the server's model takes the image input(s) {missing:?}, which this robot has \
                 no camera for (cameras: {:?}) and layout {} requires",
                self.inputs,
                self.layout.preset.name()
            );
        }
        anyhow::ensure!(
            self.n_dof <= m.action_dim,
            "the server's model takes at most {} state / action values; this robot has {} joints",
            m.action_dim,
            self.n_dof
        );
        anyhow::ensure!(
            m.action_horizon >= self.execute_horizon,
            "the server's chunks have {} actions; execution.execute_horizon = {} needs at least \
             that many (a chunk would run out before the next one is asked for)",
            m.action_horizon,
            self.execute_horizon
        );
        anyhow::ensure!(
            self.strategy != Strategy::RtcTrained || m.serves("committed"),
            "execution.strategy = \"rtc_trained\" needs a policy trained with a committed \
             prefix; the server's is not (its metadata: rtc_prefix_max = 0)"
        );
        Ok(())
    }

    /// Packs the observation (and the ask) into the writer.
    fn pack(&mut self, obs: &Observation, request: &InferenceRequest) -> anyhow::Result<u64> {
        let horizon = if self.horizon > 0 {
            self.horizon
        } else {
            request.horizon.max(1)
        };
        let ask = self
            .conditioner
            .ask(request, &obs.joint_state, obs.t_obs_ns(), horizon);
        // frames as tightly packed HWC (rgb8, or one channel for mono8)
        let frames: Vec<_> = obs.frames.iter().filter(|f| f.valid).collect();
        self.pixels.resize_with(frames.len(), Vec::new);
        let mut channels = Vec::with_capacity(frames.len());
        for (f, buf) in frames.iter().zip(self.pixels.iter_mut()) {
            let (w, h, stride) = (
                f.header.width as usize,
                f.header.height as usize,
                f.header.stride as usize,
            );
            let c = if f.header.encoding == ENCODING_MONO8 {
                1
            } else {
                3
            };
            let px = f.pixels();
            buf.clear();
            for y in 0..h {
                let row = px
                    .get(y * stride..y * stride + w * c)
                    .context("a frame is shorter than its header says")?;
                if f.header.encoding == ENCODING_BGR8 {
                    for p in row.chunks_exact(3) {
                        buf.extend_from_slice(&[p[2], p[1], p[0]]);
                    }
                } else {
                    buf.extend_from_slice(row);
                }
            }
            channels.push((w, h, c));
        }
        let images: Vec<ImageRef<'_>> = frames
            .iter()
            .zip(&self.pixels)
            .zip(&channels)
            .map(|((f, data), &(width, height, channels))| ImageRef {
                name: &f.name,
                width,
                height,
                channels,
                data,
            })
            .collect();
        let serves = |c: &str| self.server.as_ref().is_some_and(|m| m.serves(c));
        let jacobian;
        let guidance = match &ask.conditioning {
            Conditioning::Guided(g) if serves("guided") => {
                jacobian = g.jacobian.name();
                Some((g.prefix, g.weights, g.beta as f64, jacobian))
            }
            _ => None,
        };
        let committed = match &ask.conditioning {
            Conditioning::Committed(rows) if serves("committed") => Some(*rows),
            _ => None,
        };
        let dropped = !matches!(ask.conditioning, Conditioning::Fresh)
            && guidance.is_none()
            && committed.is_none();
        if dropped && !self.warned_fresh {
            self.warned_fresh = true;
            tracing::warn!(
                "remote policy: {} takes no real-time-chunking keys; its chunks are fresh \
                 (future-state inference still applies: the state sent is where the robot will \
                 be)",
                self.client_cfg.url
            );
        }
        let split = state_split(self.layout.state.len(), ask.state.len());
        self.sent_state.clear();
        self.sent_state.extend_from_slice(ask.state);
        if let (Some(d), Some(g)) = (&self.droid, self.sent_state.last_mut()) {
            *g = d.gripper_state(*g);
        }
        let chunkrt = self.server.is_some();
        self.writer.clear();
        Outgoing {
            images: &images,
            state: &self.sent_state,
            state_split: &split,
            prompt: &self.prompt,
            guidance,
            committed,
            delay_steps: chunkrt.then_some(request.delay_steps as u64),
            reseed: if chunkrt { self.reseed.take() } else { None },
        }
        .write(&self.layout, &mut self.writer)
        .map_err(anyhow::Error::msg)?;
        Ok(ask.start_shift_ns)
    }

    /// One exchange; the connection is dropped on any failure.
    fn exchange(&mut self) -> anyhow::Result<Reply> {
        let client = self.client.as_mut().context("not connected")?;
        let bytes = match client.infer(&self.writer.buf) {
            Ok(b) => b,
            Err(e) => {
                self.client = None;
                self.next_attempt = Instant::now() + BACKOFF_START;
                return Err(e.into());
            }
        };
        let parsed = decode(&bytes, Limits::default())
            .map_err(|e| anyhow::anyhow!("the reply is not msgpack-numpy: {e}"))
            .and_then(|v| Reply::parse(&v).map_err(anyhow::Error::from));
        if parsed.is_err() {
            self.client = None;
        }
        parsed
    }
}

impl ChunkSource for RemoteSource {
    fn name(&self) -> &str {
        "remote policy"
    }

    fn uses_cameras(&self) -> bool {
        true
    }

    fn delayed_views(&self) -> &[chunkrt_policy::DelayedView] {
        &self.views
    }

    fn set_prompt(&mut self, prompt: &str) {
        self.prompt = prompt.to_string();
    }

    fn reseed(&mut self, seed: u64) {
        // sent with the next request (a chunkrt server restarts its noise from it)
        self.reseed = Some(seed);
    }

    fn compute(
        &mut self,
        obs: &Observation,
        request: &InferenceRequest,
    ) -> anyhow::Result<Option<ActionChunk>> {
        // every failure waits out a backoff, whatever its kind: a server that answers every
        // request with NaN or the wrong shapes is asked at most a few times a second, not
        // hundreds (its connection dropped and made again each time)
        // (a poll while waiting is no request: answered NotAsked, which the worker does not
        // count as a failure, naming what is waited out)
        let now = Instant::now();
        if now < self.next_attempt {
            return Err(crate::contract::NotAsked(format!(
                "{}: {}; next attempt in {} ms",
                self.client_cfg.url,
                self.last_cause,
                (self.next_attempt - now).as_millis()
            ))
            .into());
        }
        if self.client.is_none() {
            if let Err(e) = self.reconnect() {
                self.last_cause = cut(&format!("cannot connect: {e:#}"));
                return Err(e.context(format!("cannot reconnect to {}", self.client_cfg.url)));
            }
        }
        let result = self.request(obs, request);
        match &result {
            Ok(_) => {
                self.failures = 0;
                self.fail_backoff = BACKOFF_START;
            }
            Err(e) => {
                self.failures += 1;
                self.failures_total += 1;
                self.last_cause = cut(&format!(
                    "{} requests failed in a row, the last: {e:#}",
                    self.failures
                ));
                self.next_attempt = Instant::now() + self.fail_backoff;
                self.fail_backoff = (self.fail_backoff * 2).min(BACKOFF_MAX);
            }
        }
        result
    }
}

impl RemoteSource {
    /// One request and its chunk (any failure is [`ChunkSource::compute`]'s to pace).
    fn request(
        &mut self,
        obs: &Observation,
        request: &InferenceRequest,
    ) -> anyhow::Result<Option<ActionChunk>> {
        let start_shift_ns = self.pack(obs, request)?;
        let reply = self.exchange()?;
        let n = self.n_dof.min(obs.joint_state.n_dof as usize);
        anyhow::ensure!(
            reply.dims == n || (reply.dims > n && self.truncate),
            "the server's actions have {} values per step and the robot has {n} joints{}",
            reply.dims,
            if reply.dims > n {
                " (set policy.truncate_actions = true to use the first ones, if they are the \
                 robot's joints in its order)"
            } else {
                ""
            }
        );
        anyhow::ensure!(reply.horizon > 0, "the server's chunk is empty");
        if self.horizon != reply.horizon {
            if self.horizon != 0 && self.server.is_some() {
                tracing::warn!(
                    "remote policy: chunks of {} actions, the server's metadata said {}",
                    reply.horizon,
                    self.horizon
                );
            }
            self.horizon = reply.horizon;
        }
        let mut actions = Vec::with_capacity(reply.horizon * n);
        for row in reply.actions.chunks_exact(reply.dims) {
            actions.extend_from_slice(&row[..n]);
        }
        if let Some(d) = &self.droid {
            anyhow::ensure!(
                self.sent_state.len() >= n,
                "no state was sent for the chunk's joints"
            );
            d.positions(&self.sent_state, &mut actions, n);
        }
        let chunk = ActionChunk {
            id: next_chunk_id(),
            observation_seq: obs.joint_state.seq,
            t_obs_ns: obs.t_obs_ns(),
            period_ns: self.period_ns,
            n_dof: n,
            actions,
            ready_ns: monotonic_ns(),
            start_shift_ns,
        };
        chunk.validate()?;
        Ok(Some(chunk))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn droid_velocities_become_positions_and_the_gripper_is_binarised() {
        let d = Droid {
            max_joint_delta: 0.2,
            open: 0.08,
            closed: 0.0,
        };
        // the hand half open reports 0.5 closed; fully open 0, closed 1
        assert_eq!(d.gripper_state(0.04), 0.5);
        assert_eq!(d.gripper_state(0.08), 0.0);
        assert_eq!(d.gripper_state(0.0), 1.0);
        // 2 joints + gripper, 3 steps: full, half, clipped past 1; gripper 0.49 / 0.51 / NaN
        let state = [1.0, -1.0, 0.0];
        let mut rows = vec![1.0, -0.5, 0.49, 0.5, 0.0, 0.51, 2.0, f64::NAN, f64::NAN];
        d.positions(&state, &mut rows, 3);
        let want = [1.2, -1.1, 0.08, 1.3, -1.1, 0.0, 1.5, -1.1, 0.08];
        for (g, w) in rows.iter().zip(want) {
            assert!((g - w).abs() < 1e-12, "{rows:?}");
        }
    }

    #[test]
    fn the_state_splits_with_the_grippers_last() {
        assert_eq!(state_split(1, 8), Vec::<usize>::new());
        assert_eq!(state_split(2, 8), vec![7, 1]);
        assert_eq!(state_split(3, 14), vec![12, 1, 1]);
    }
}
