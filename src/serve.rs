//! `chunkrt serve`: chunkrt's policy behind openpi's websocket protocol, for any openpi client
//! (`openpi-client`'s `WebsocketClientPolicy`, a controller with `policy.source = "remote"`).
//!
//! The composition: the policy crate's [`Policy`] on its own thread pool, answering the
//! requests that [`chunkrt_openpi::Server`] decodes and checks ([`chunkrt_openpi::Request`]),
//! one at a time in arrival order. What a request may carry beyond openpi's keys (guidance,
//! a committed prefix, a noise seed) becomes a [`Conditioning`]; the reply's actions are the
//! robot's: un-normalised, delta joints made absolute, as many columns as the state had.

use std::path::PathBuf;
use std::sync::atomic::Ordering;
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

use anyhow::Context;

use chunkrt_controller::config::{Config, DeviceSpec, Precision};
use chunkrt_controller::log_limit::LogLimiter;
use chunkrt_openpi::{
    ChunkrtMetadata, Failure, Layout, Limits, Preset, Reply, Request, Server, ServerConfig, Value,
    Writer,
};
use chunkrt_policy::runtime::{Conditioning, Guidance, Policy, RawFrame, RawObservation};
use chunkrt_policy::{Encoding, Jacobian};

/// `chunkrt serve`.
#[derive(Debug, Clone, clap::Args)]
pub struct ServeArgs {
    /// Checkpoint directory (`model.safetensors`, `config.json`, `norm_stats.json`, tokenizer).
    #[arg(long)]
    pub checkpoint: PathBuf,
    /// Robot configuration (TOML): its `[policy]` options (steps, threads, precision, device,
    /// model overrides, the default prompt) and its `[openpi]` request layout. Default: the
    /// embedded demo robot's.
    #[arg(long)]
    pub config: Option<PathBuf>,
    /// Where the policy runs: cpu, cuda or cuda:N (overrides `policy.device`).
    #[arg(long)]
    pub device: Option<DeviceSpec>,
    /// f32 or bf16 (overrides `policy.precision`).
    #[arg(long)]
    pub precision: Option<Precision>,
    /// Address to listen on (127.0.0.1: this machine only; 0.0.0.0: every interface).
    #[arg(long, default_value = "127.0.0.1")]
    pub host: String,
    /// Port (0: any free port, printed at start).
    #[arg(long, default_value_t = 8000)]
    pub port: u16,
    /// Require `Authorization: Api-Key KEY` (what `WebsocketClientPolicy(api_key=KEY)` sends);
    /// a connection without it is refused before any model work.
    #[arg(long, env = "CHUNKRT_API_KEY", hide_env_values = true)]
    pub api_key: Option<String>,
    /// The request layout: chunkrt, libero, aloha or droid (overrides `[openpi] preset`).
    #[arg(long)]
    pub layout: Option<String>,
    /// The largest request (MiB; default: 4 × one 640×480 RGB frame per image input, + 1).
    #[arg(long)]
    pub max_message_mb: Option<f64>,
    #[command(flatten)]
    pub files: crate::args::LayoutArgs,
    /// Connections served at once (more are refused with HTTP 503; default `[serve]
    /// max_connections`, 16).
    #[arg(long)]
    pub max_connections: Option<usize>,
    /// Connections one peer address may hold (default `[serve] max_per_address`, 4).
    #[arg(long)]
    pub max_per_address: Option<usize>,
    /// Seconds a connection has to send its request and complete the websocket handshake
    /// (default `[serve] handshake_timeout_s`, 2).
    #[arg(long, value_name = "SECONDS")]
    pub handshake_timeout: Option<f64>,
    /// Seconds a websocket may go without a request before it is closed (default `[serve]
    /// idle_timeout_s`, 30).
    #[arg(long, value_name = "SECONDS")]
    pub idle_timeout: Option<f64>,
    /// Seconds between status lines (0: none).
    #[arg(long, default_value_t = 10.0)]
    pub log_every: f64,
    /// Stop after this many seconds (default: until SIGINT / SIGTERM).
    #[arg(long)]
    pub duration: Option<f64>,
}

/// The metadata of a loaded policy.
pub fn metadata(policy: &Policy, layout: &Layout) -> ChunkrtMetadata {
    let cfg = &policy.model().cfg;
    let mut conditioning = vec!["guided".to_string()];
    if policy.committed_max() > 0 {
        conditioning.push("committed".to_string());
    }
    ChunkrtMetadata {
        version: env!("CARGO_PKG_VERSION").to_string(),
        model: cfg.kind.name().to_string(),
        action_horizon: policy.horizon(),
        action_dim: cfg.action_dim,
        image_inputs: cfg.cameras.clone(),
        conditioning,
        rtc_prefix_max: policy.committed_max(),
        layout: layout.preset.name().to_string(),
        delayed_views: policy
            .delayed_views()
            .iter()
            .map(|v| (v.name.clone(), v.camera.clone(), v.delay_ms))
            .collect(),
        reset_pose: policy
            .openpi_config()
            .and_then(|c| c.reset_pose)
            .map(<[f64]>::to_vec),
    }
}

/// Whether `policy` can answer a request at all: an openpi config's robot's state and action
/// widths fit the model's, and its statistics cover that state (else every request would fail
/// the same way, found per request instead of at load).
pub fn servable(policy: &Policy) -> anyhow::Result<()> {
    let Some(c) = policy.openpi_config() else {
        return Ok(());
    };
    let dim = policy.model().cfg.action_dim;
    let (state, actions) = (c.robot.state_dim(), c.robot.action_dim());
    anyhow::ensure!(
        state <= dim && actions <= dim,
        "openpi config {}: its robot ({}) sends {state} state values and reads {actions} action \
         columns, and this {} model takes {dim}: serve a checkpoint of that config's model, or \
         pick the --openpi-config of this one's robot",
        c.name,
        c.robot.layout(),
        policy.model().cfg.kind.name()
    );
    policy.check_dof(state).with_context(|| {
        format!(
            "openpi config {}: the statistics do not cover its robot's {state} state values",
            c.name
        )
    })?;
    Ok(())
}

/// Answers one request with `policy` (on `pool`): the one place a wire request becomes a
/// policy call.
pub fn answer(
    policy: &mut Policy,
    pool: &rayon::ThreadPool,
    default_prompt: &str,
    req: &Request,
) -> Result<Reply, String> {
    let n = req.state.len();
    policy.check_dof(n).map_err(|e| e.to_string())?;
    if let Some(seed) = req.reseed {
        policy.reseed(seed);
    }
    let frames: Vec<RawFrame<'_>> = req
        .images
        .iter()
        .map(|i| RawFrame {
            camera: &i.name,
            width: i.width,
            height: i.height,
            stride: i.width * i.channels as u32,
            encoding: if i.channels == 1 {
                Encoding::Mono8
            } else {
                Encoding::Rgb8
            },
            data: &i.data,
        })
        .collect();
    // openpi's order: the request's, the server's, the config's default prompt
    let prompt = match (&req.prompt, policy.default_prompt()) {
        (Some(p), _) => p.as_str(),
        (None, _) if !default_prompt.is_empty() => default_prompt,
        (None, Some(p)) => p,
        (None, None) => {
            return Err(
                "missing key \"prompt\" (and the server has no default: [policy] prompt)".into(),
            )
        }
    };
    let weights: Vec<f32>;
    let conditioning = match (&req.guidance, &req.committed) {
        (Some(g), _) => {
            weights = g.weights.iter().map(|&w| w as f32).collect();
            Conditioning::Guided(Guidance {
                prefix: &g.actions,
                weights: &weights,
                beta: g.beta as f32,
                jacobian: g.jacobian.parse::<Jacobian>().map_err(|e| e.to_string())?,
            })
        }
        (None, Some(c)) => Conditioning::Committed(c),
        (None, None) => Conditioning::Fresh,
    };
    let raw = RawObservation {
        frames: &frames,
        joint_positions: &req.state,
        prompt,
    };
    let t = Instant::now();
    let actions = pool
        .install(|| policy.infer(&raw, &conditioning))
        .map_err(|e| e.to_string())?;
    // the robot's columns (an openpi config's: LIBERO's 7 for its 8 state values)
    let dims = policy.action_width(n).max(1);
    Ok(Reply {
        horizon: actions.len() / dims,
        dims,
        actions,
        policy_infer_ms: Some(t.elapsed().as_secs_f64() * 1e3),
        server_infer_ms: None,
        prev_total_ms: None,
    })
}

/// The request layout of `cfg`, with `--layout` over its preset.
pub fn layout_of(cfg: &Config, preset: Option<&str>) -> anyhow::Result<Layout> {
    let mut c = cfg.openpi.clone();
    if let Some(p) = preset {
        c.preset = Preset::ALL
            .into_iter()
            .find(|x| x.name() == p)
            .with_context(|| {
                format!("--layout {p:?}: must be one of chunkrt, libero, aloha, droid")
            })?;
    }
    Layout::from_config(&c).map_err(anyhow::Error::msg)
}

/// A running `chunkrt serve` (also started in-process by tests and benches).
pub struct Serving {
    /// The server.
    pub server: Server,
    /// Its log limiter (flushed by the status loop).
    pub log: Arc<Mutex<LogLimiter>>,
}

/// Loads the policy and starts serving it.
pub fn start(args: &ServeArgs) -> anyhow::Result<Serving> {
    let mut cfg = crate::args::load_config(args.config.as_ref(), None)?;
    if let Some(d) = args.device {
        cfg.policy.device = d;
    }
    if let Some(p) = args.precision {
        cfg.policy.precision = p;
    }
    args.files.apply(&mut cfg.policy)?;
    let pool = chunkrt_controller::inference::policy_pool(&cfg.policy)?;
    let mut opts = cfg.policy.load_options();
    opts.kind = None; // whatever the checkpoint is
    let mut policy = pool
        .install(|| Policy::load(&args.checkpoint, &opts))
        .with_context(|| format!("cannot load the policy from {}", args.checkpoint.display()))?;
    servable(&policy).with_context(|| {
        format!(
            "{} cannot answer any request: refused at load",
            args.checkpoint.display()
        )
    })?;
    // an openpi config's robot sends the keys of openpi's example client for it
    let preset = args.layout.as_deref().or(match policy.openpi_config() {
        Some(c) if cfg.openpi.preset == chunkrt_openpi::layout::Preset::default() => {
            Some(c.robot.layout())
        }
        _ => None,
    });
    let layout = layout_of(&cfg, preset)?;
    let meta = metadata(&policy, &layout);
    let inputs = policy.model().cfg.cameras.clone();
    let max_message_bytes = match args.max_message_mb {
        Some(mb) if mb.is_finite() && mb > 0.0 => (mb * (1 << 20) as f64) as usize,
        Some(mb) => anyhow::bail!("--max-message-mb {mb}: must be > 0"),
        None => 4 * inputs.len().max(1) * 640 * 480 * 3 + (1 << 20),
    };
    let addr = format!("{}:{}", args.host, args.port);
    let addr: std::net::SocketAddr = std::net::ToSocketAddrs::to_socket_addrs(&addr)
        .with_context(|| format!("--host {} --port {}", args.host, args.port))?
        .next()
        .with_context(|| format!("{addr} resolves to no address"))?;
    let mut w = Writer::new();
    meta.write(&mut w);
    let default_prompt = cfg.policy.prompt.clone();
    let log = Arc::new(Mutex::new(LogLimiter::new(Duration::from_secs(1))));
    let report_log = log.clone();
    let limits = &cfg.serve;
    let secs = |flag: &str, v: f64| -> anyhow::Result<Duration> {
        anyhow::ensure!(
            v.is_finite() && v > 0.0 && v < 1e7,
            "{flag} {v}: must be a positive number of seconds"
        );
        Ok(Duration::from_secs_f64(v))
    };
    let per_address = args
        .max_per_address
        .unwrap_or(limits.max_per_address)
        .max(1);
    let server = Server::start(
        ServerConfig {
            addr,
            api_key: args.api_key.clone().filter(|k| !k.is_empty()),
            max_message_bytes,
            max_connections: args
                .max_connections
                .unwrap_or(limits.max_connections)
                .max(1),
            limits: Limits::default(),
            max_per_address: per_address,
            // a network (/24, /64) holds twice an address's share
            max_per_network: 2 * per_address,
            handshake_timeout: secs(
                "handshake timeout",
                args.handshake_timeout.unwrap_or(limits.handshake_timeout_s),
            )?,
            idle_timeout: secs(
                "idle timeout",
                args.idle_timeout.unwrap_or(limits.idle_timeout_s),
            )?,
            ..ServerConfig::new(addr, max_message_bytes)
        },
        w.buf,
        Box::new(move |v: &Value<'_>| Request::parse(v, &layout, &inputs)),
        Box::new(move |r: &Request| answer(&mut policy, &pool, &default_prompt, r)),
        Box::new(move |kind: &str, line: String| {
            if let Ok(mut l) = report_log.lock() {
                let full = line.clone();
                if l.admit(kind, move || line, Instant::now()) {
                    tracing::warn!("{full}");
                }
            }
        }),
    )
    .with_context(|| format!("cannot listen on {addr}"))?;
    tracing::info!(
        "chunkrt serve: {} ({} actions × {} dims max, images {:?}, conditioning {:?}) on ws://{} \
         (layout {}, {}, requests up to {:.1} MiB)",
        meta.model,
        meta.action_horizon,
        meta.action_dim,
        meta.image_inputs,
        meta.conditioning,
        server.local_addr(),
        meta.layout,
        if args.api_key.as_deref().is_some_and(|k| !k.is_empty()) {
            "api key required"
        } else {
            "no api key"
        },
        max_message_bytes as f64 / (1 << 20) as f64
    );
    Ok(Serving { server, log })
}

/// One status line: connections, replies, latency percentiles since the last line, failures.
pub fn status_line(s: &Serving, latencies: &[(u64, u64)]) -> String {
    let st = s.server.stats();
    let q = |sel: fn(&(u64, u64)) -> u64, p: f64| {
        let mut h = hdrhistogram::Histogram::<u64>::new_with_bounds(1, 600_000_000, 3)
            .expect("valid histogram bounds");
        for l in latencies {
            let _ = h.record(sel(l).max(1));
        }
        h.value_at_quantile(p) as f64 / 1e3
    };
    let failures: Vec<String> = Failure::ALL
        .iter()
        .filter_map(|k| {
            let n = st.failures(*k);
            (n > 0).then(|| format!("{}={n}", k.name()))
        })
        .collect();
    format!(
        "serve: {} open, {} replies ({} in this interval: round trip p50/p99 {:.1}/{:.1} ms, \
         policy p50 {:.1} ms), failures [{}], unauthorized {}, busy {}",
        st.open.load(Ordering::Relaxed),
        st.replies.load(Ordering::Relaxed),
        latencies.len(),
        q(|l| l.0, 0.5),
        q(|l| l.0, 0.99),
        q(|l| l.1, 0.5),
        failures.join(" "),
        st.unauthorized.load(Ordering::Relaxed),
        st.busy.load(Ordering::Relaxed),
    )
}

/// `chunkrt serve` until SIGINT / SIGTERM or `--duration`.
pub fn run(args: ServeArgs) -> anyhow::Result<()> {
    let stop = chunkrt_tools::shutdown::flag();
    let serving = start(&args)?;
    // the address on stdout (a port 0 server tells where it is)
    println!(
        "chunkrt serve: listening on ws://{}",
        serving.server.local_addr()
    );
    let started = Instant::now();
    let mut last = Instant::now();
    while !stop.load(Ordering::Relaxed) {
        std::thread::sleep(Duration::from_millis(50));
        if let Ok(mut l) = serving.log.lock() {
            l.flush(Instant::now(), |kind, n, last| {
                tracing::warn!("serve: {kind}: {n} more in the last second (last: {last})")
            });
        }
        if args.log_every > 0.0 && last.elapsed().as_secs_f64() >= args.log_every {
            let lat = serving.server.stats().take_latencies();
            tracing::info!("{}", status_line(&serving, &lat));
            last = Instant::now();
        }
        if args
            .duration
            .is_some_and(|d| started.elapsed().as_secs_f64() >= d)
        {
            break;
        }
    }
    let lat = serving.server.stats().take_latencies();
    println!("{}", status_line(&serving, &lat));
    serving.server.stop();
    Ok(())
}
