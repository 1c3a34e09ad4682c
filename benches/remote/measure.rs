//! `remote`: what a policy behind `chunkrt serve` adds to a chunk's latency, against the same
//! policy in process, in the same run.
//!
//! For each policy (the committed reach policy, a random `pi05_bench`) and each observation
//! (1 and 3 cameras at 224×224, the robot's state, a prompt) a client sends requests to a
//! server and records the round trip and the server's own time in the policy
//! (`server_timing.infer_ms`, the in-process inference of the same call): the difference is
//! what the wire adds — packing, the websocket on loopback (or a network), decoding and
//! checking, the reply. Three links:
//!
//! - `loopback`: `chunkrt serve`'s server in this process, the client on another thread;
//! - `netem D ms`: `chunkrt serve` as a process inside a network namespace this bench creates,
//!   reached through a veth pair whose two ends each delay by D (netem; a round trip gains 2·D);
//!   needs root, `ip` / `tc` (iproute2) and the kernel's `sch_netem`; where one is missing,
//!   `proxy D ms`: the in-process server behind a user-space TCP proxy that delays each
//!   direction by D ([`DelayProxy`]);
//! - the reference: openpi's own Python server (PyPI `openpi-server`, a policy that answers at
//!   once) and `openpi-client` exchanging the same 3 × 224² observation on loopback: the round
//!   trip is all wire and Python.

use std::path::{Path, PathBuf};
use std::process::{Child, Command, Stdio};
use std::time::{Duration, Instant};

use chunkrt::report::{fmt_us, latency_histogram, LatencyTable, Series};
use chunkrt_controller::config::Config;
use chunkrt_openpi::{
    decode, Client, ClientConfig, ImageRef, Layout, Limits, Outgoing, Reply, Request, Server,
    ServerConfig, Value, Writer,
};
use chunkrt_policy::Policy;
use hdrhistogram::Histogram;
use rand::{Rng, SeedableRng};

use chunkrt_bench::{write_outputs, BenchError, BenchOpts};

/// Options of one run.
pub struct Options {
    /// Output folder and quick mode.
    pub bench: BenchOpts,
    /// The `chunkrt` executable (for the netem server process).
    pub chunkrt_exe: Option<PathBuf>,
    /// One-way netem delays to emulate (ms).
    pub netem_ms: Vec<f64>,
    /// Requests per case (after 3 untimed).
    pub requests: usize,
    /// Run the openpi Python reference.
    pub python: bool,
}

impl Options {
    /// Defaults: 0.5 and 5 ms of netem, 40 requests (quick: 5, no netem, no Python).
    pub fn new(bench: BenchOpts, chunkrt_exe: Option<PathBuf>) -> Self {
        let quick = bench.quick;
        Self {
            bench,
            chunkrt_exe,
            netem_ms: if quick { vec![] } else { vec![0.5, 5.0] },
            requests: if quick { 5 } else { 40 },
            python: !quick,
        }
    }
}

fn err(what: &str, e: impl std::fmt::Display) -> BenchError {
    BenchError::Process {
        what: what.to_string(),
        reason: e.to_string(),
    }
}

/// A policy to serve: its checkpoint directory and robot state size.
struct Model {
    name: &'static str,
    dir: PathBuf,
    n_dof: usize,
}

/// Writes a random-weight `pi05_bench` checkpoint (the byte stand-in tokenizer) into `dir`.
fn pi05_bench_checkpoint(dir: &Path) -> Result<(), BenchError> {
    let (_, json) = chunkrt_bench::inference::CONFIGS
        .iter()
        .find(|(n, _)| *n == "pi05_bench")
        .ok_or_else(|| err("pi05_bench", "no such preset"))?;
    let cfg = chunkrt_policy::config::ModelConfig::from_json_str(json)
        .map_err(|e| err("pi05_bench config", e))?;
    let (_, vars) =
        chunkrt_bench::inference::random_model(&cfg).map_err(|e| err("pi05_bench weights", e))?;
    std::fs::create_dir_all(dir).map_err(|e| err("checkpoint dir", e))?;
    vars.save(dir.join("model.safetensors"))
        .map_err(|e| err("pi05_bench save", e))?;
    let mut v: serde_json::Value =
        serde_json::from_str(json).map_err(|e| err("pi05_bench json", e))?;
    v["tokenizer"] = serde_json::Value::String("byte_stand_in".into());
    std::fs::write(dir.join("config.json"), v.to_string()).map_err(|e| err("config.json", e))?;
    Ok(())
}

/// One observation of `cameras` 224×224 frames.
fn request(cameras: usize, n_dof: usize, rng: &mut impl Rng) -> Vec<u8> {
    let names = ["base_0_rgb", "left_wrist_0_rgb", "right_wrist_0_rgb"];
    let px: Vec<Vec<u8>> = (0..cameras)
        .map(|_| (0..224 * 224 * 3).map(|_| rng.gen()).collect())
        .collect();
    let imgs: Vec<ImageRef<'_>> = px
        .iter()
        .zip(names)
        .map(|(d, name)| ImageRef {
            name,
            width: 224,
            height: 224,
            channels: 3,
            data: d,
        })
        .collect();
    let state: Vec<f64> = (0..n_dof).map(|i| 0.1 * i as f64).collect();
    let mut w = Writer::new();
    let _ = Outgoing {
        images: &imgs,
        state: &state,
        state_split: &[],
        prompt: "reach the red target",
        guidance: None,
        committed: None,
        delay_steps: None,
        reseed: None,
    }
    .write(&Layout::default(), &mut w);
    w.buf
}

/// Round trips, the server's policy time, and their difference (what the wire adds).
type Exchange = (Histogram<u64>, Histogram<u64>, Histogram<u64>);

/// [`Exchange`] of `n` requests (after 3 untimed).
fn exchange(client: &mut Client, msg: &[u8], n: usize) -> Result<Exchange, BenchError> {
    let (mut rtt, mut infer, mut wire) = (
        latency_histogram(),
        latency_histogram(),
        latency_histogram(),
    );
    for i in 0..n + 3 {
        let t = Instant::now();
        let bytes = client.infer(msg).map_err(|e| err("request", e))?;
        let reply = decode(&bytes, Limits::default())
            .map_err(|e| err("reply", e))
            .and_then(|v| Reply::parse(&v).map_err(|e| err("reply", e)))?;
        let total = t.elapsed().as_nanos() as u64;
        let server = (reply.server_infer_ms.unwrap_or(0.0) * 1e6) as u64;
        if i >= 3 {
            rtt.saturating_record(total);
            infer.saturating_record(server.max(1));
            wire.saturating_record(total.saturating_sub(server).max(1));
        }
    }
    Ok((rtt, infer, wire))
}

/// The 1- and 3-camera cases of `model` through `client` over `link`: prints each and keeps its
/// remote round trip and what the link adds (and the in-process time, `in_process`).
fn measure_cases(
    client: &mut Client,
    model: &Model,
    link: &str,
    in_process: bool,
    requests: usize,
    rng: &mut impl Rng,
    series: &mut Vec<Series>,
) -> Result<(), BenchError> {
    for cams in [1usize, 3] {
        let msg = request(cams, model.n_dof, rng);
        let (rtt, infer, wire) = exchange(client, &msg, requests)?;
        let tag = format!("{}_cam{cams}_{link}", model.name);
        println!(
            "{tag}: in process {} µs, remote {} µs (p50), the link adds p50 {} / p99 {} µs ({} kB a request)",
            fmt_us(infer.value_at_quantile(0.5)),
            fmt_us(rtt.value_at_quantile(0.5)),
            fmt_us(wire.value_at_quantile(0.5)),
            fmt_us(wire.value_at_quantile(0.99)),
            msg.len() / 1000
        );
        if in_process {
            series.push(Series::new(format!("{tag}_in_process"), infer));
        }
        series.push(Series::new(format!("{tag}_remote"), rtt));
        series.push(Series::new(format!("{tag}_added"), wire));
    }
    Ok(())
}

/// The in-process server for `model`.
fn local_server(model: &Model) -> Result<Server, BenchError> {
    let cfg = Config::embedded_default();
    let pool =
        chunkrt_controller::inference::policy_pool(&cfg.policy).map_err(|e| err("pool", e))?;
    let mut opts = cfg.policy.load_options();
    opts.kind = None;
    let mut policy = pool
        .install(|| Policy::load(&model.dir, &opts))
        .map_err(|e| err(model.name, e))?;
    let layout = Layout::default();
    let inputs = policy.model().cfg.cameras.clone();
    let mut w = Writer::new();
    chunkrt::serve::metadata(&policy, &layout).write(&mut w);
    Server::start(
        ServerConfig {
            addr: "127.0.0.1:0".parse().expect("a socket address"),
            api_key: None,
            max_message_bytes: 64 << 20,
            max_connections: 4,
            limits: Limits::default(),
            ..ServerConfig::new("127.0.0.1:0".parse().unwrap(), 1 << 20)
        },
        w.buf,
        Box::new(move |v: &Value<'_>| Request::parse(v, &layout, &inputs)),
        Box::new(move |r: &Request| chunkrt::serve::answer(&mut policy, &pool, "", r)),
        Box::new(|_, line| eprintln!("remote bench server: {line}")),
    )
    .map_err(|e| err("server", e))
}

/// A network namespace with a veth pair whose two ends each delay by `delay_ms` (netem).
struct Netns {
    name: String,
}

fn sh(args: &[&str]) -> Result<(), String> {
    let o = Command::new(args[0])
        .args(&args[1..])
        .output()
        .map_err(|e| format!("{}: {e}", args.join(" ")))?;
    if o.status.success() {
        Ok(())
    } else {
        Err(format!(
            "{}: {}",
            args.join(" "),
            String::from_utf8_lossy(&o.stderr).trim()
        ))
    }
}

impl Netns {
    const HOST: &'static str = "10.213.7.1";
    const PEER: &'static str = "10.213.7.2";

    fn create(delay_ms: f64) -> Result<Self, String> {
        let name = format!("chunkrt-bench-{}", std::process::id());
        let d = format!("{delay_ms}ms");
        let (h, p) = ("crb0", "crb1");
        let _ = sh(&["ip", "netns", "del", &name]);
        let _ = sh(&["ip", "link", "del", h]);
        let me = Self { name };
        let n = me.name.as_str();
        sh(&["ip", "netns", "add", n])?;
        sh(&["ip", "link", "add", h, "type", "veth", "peer", "name", p])?;
        sh(&["ip", "link", "set", p, "netns", n])?;
        sh(&["ip", "addr", "add", &format!("{}/24", Self::HOST), "dev", h])?;
        sh(&["ip", "link", "set", h, "up"])?;
        sh(&[
            "ip",
            "netns",
            "exec",
            n,
            "ip",
            "addr",
            "add",
            &format!("{}/24", Self::PEER),
            "dev",
            p,
        ])?;
        sh(&["ip", "netns", "exec", n, "ip", "link", "set", p, "up"])?;
        sh(&["ip", "netns", "exec", n, "ip", "link", "set", "lo", "up"])?;
        sh(&["tc", "qdisc", "add", "dev", h, "root", "netem", "delay", &d])?;
        sh(&[
            "ip", "netns", "exec", n, "tc", "qdisc", "add", "dev", p, "root", "netem", "delay", &d,
        ])?;
        Ok(me)
    }
}

impl Drop for Netns {
    fn drop(&mut self) {
        let _ = sh(&["ip", "link", "del", "crb0"]);
        let _ = sh(&["ip", "netns", "del", &self.name]);
    }
}

/// A TCP forwarder that delays every byte by `delay` in each direction: the emulated network
/// where the kernel has no netem (a round trip gains 2·delay; bandwidth is loopback's).
pub struct DelayProxy {
    addr: std::net::SocketAddr,
    stop: std::sync::Arc<std::sync::atomic::AtomicBool>,
}

impl DelayProxy {
    /// Listens on 127.0.0.1 and forwards each connection to `target`.
    pub fn start(target: std::net::SocketAddr, delay: Duration) -> std::io::Result<Self> {
        use std::sync::atomic::{AtomicBool, Ordering};
        let listener = std::net::TcpListener::bind("127.0.0.1:0")?;
        let addr = listener.local_addr()?;
        let stop = std::sync::Arc::new(AtomicBool::new(false));
        let stop2 = stop.clone();
        listener.set_nonblocking(true)?;
        std::thread::spawn(move || {
            while !stop2.load(Ordering::Relaxed) {
                let Ok((down, _)) = listener.accept() else {
                    std::thread::sleep(Duration::from_millis(5));
                    continue;
                };
                let _ = down.set_nonblocking(false);
                let Ok(up) = std::net::TcpStream::connect(target) else {
                    continue;
                };
                let _ = (down.set_nodelay(true), up.set_nodelay(true));
                for (from, to) in [
                    (down.try_clone(), up.try_clone()),
                    (up.try_clone(), down.try_clone()),
                ] {
                    if let (Ok(from), Ok(to)) = (from, to) {
                        pipe(from, to, delay);
                    }
                }
            }
        });
        Ok(Self { addr, stop })
    }

    /// Where clients connect.
    pub fn addr(&self) -> std::net::SocketAddr {
        self.addr
    }
}

impl Drop for DelayProxy {
    fn drop(&mut self) {
        self.stop.store(true, std::sync::atomic::Ordering::Relaxed);
    }
}

/// Copies `from` → `to`, each read released `delay` after it arrived, in order.
fn pipe(mut from: std::net::TcpStream, mut to: std::net::TcpStream, delay: Duration) {
    use std::io::{Read, Write};
    let (tx, rx) = std::sync::mpsc::channel::<(Instant, Vec<u8>)>();
    std::thread::spawn(move || {
        let mut buf = vec![0u8; 1 << 16];
        while let Ok(n) = from.read(&mut buf) {
            if n == 0
                || tx
                    .send((Instant::now() + delay, buf[..n].to_vec()))
                    .is_err()
            {
                break;
            }
        }
    });
    std::thread::spawn(move || {
        while let Ok((due, bytes)) = rx.recv() {
            let now = Instant::now();
            if due > now {
                std::thread::sleep(due - now);
            }
            if to.write_all(&bytes).is_err() {
                break;
            }
        }
        let _ = to.shutdown(std::net::Shutdown::Both);
    });
}

struct Guard(Child);

impl Drop for Guard {
    fn drop(&mut self) {
        let _ = self.0.kill();
        let _ = self.0.wait();
    }
}

fn connect_retry(url: &str, timeout: Duration) -> Result<Client, BenchError> {
    let t0 = Instant::now();
    loop {
        match Client::connect(&ClientConfig::new(url)) {
            Ok(c) => return Ok(c),
            Err(e) if t0.elapsed() > timeout => return Err(err(url, e)),
            Err(_) => std::thread::sleep(Duration::from_millis(100)),
        }
    }
}

/// The openpi reference: openpi-server (instant policy) and openpi-client on loopback.
fn python_reference(requests: usize) -> Result<Histogram<u64>, String> {
    let peer = concat!(
        env!("CARGO_MANIFEST_DIR"),
        "/../tools/python/openpi_peer.py"
    );
    let port = std::net::TcpListener::bind("127.0.0.1:0")
        .and_then(|l| l.local_addr())
        .map_err(|e| e.to_string())?
        .port();
    let server = Command::new("python3")
        .args([peer, "serve-instant", "--port", &port.to_string()])
        .stdout(Stdio::null())
        .stderr(Stdio::null())
        .spawn()
        .map_err(|e| format!("python3: {e}"))?;
    let _g = Guard(server);
    let o = Command::new("python3")
        .args([
            peer,
            "bench-client",
            "--url",
            &format!("ws://127.0.0.1:{port}"),
            "--cameras",
            "3",
            "--requests",
            &requests.to_string(),
        ])
        .output()
        .map_err(|e| format!("python3: {e}"))?;
    if !o.status.success() {
        return Err(String::from_utf8_lossy(&o.stderr).trim().to_string());
    }
    let mut h = latency_histogram();
    for l in String::from_utf8_lossy(&o.stdout).lines() {
        if let Ok(ns) = l.trim().parse::<u64>() {
            h.saturating_record(ns.max(1));
        }
    }
    if h.is_empty() {
        return Err("the Python client printed no round trips".into());
    }
    Ok(h)
}

/// Runs the bench; prints and writes the table.
pub fn run(opts: &Options) -> Result<LatencyTable, BenchError> {
    let t0 = Instant::now();
    let tmp = std::env::temp_dir().join(format!("chunkrt-remote-bench-{}", std::process::id()));
    pi05_bench_checkpoint(&tmp.join("pi05_bench"))?;
    let models = [
        Model {
            name: "reach",
            dir: PathBuf::from(concat!(env!("CARGO_MANIFEST_DIR"), "/models/reach_pi05")),
            n_dof: 4,
        },
        Model {
            name: "pi05_bench",
            dir: tmp.join("pi05_bench"),
            n_dof: 7,
        },
    ];
    let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(7);
    let mut series: Vec<Series> = Vec::new();
    let mut notes: Vec<String> = Vec::new();
    for m in &models {
        let server = local_server(m)?;
        let url = format!("ws://{}", server.local_addr());
        let mut client = connect_retry(&url, Duration::from_secs(10))?;
        measure_cases(
            &mut client,
            m,
            "loopback",
            true,
            opts.requests,
            &mut rng,
            &mut series,
        )?;
        server.stop();
        for &d in &opts.netem_ms {
            // the kernel's netem in a network namespace when there is one; else a user-space
            // delay proxy in front of an in-process server
            let netns = match Netns::create(d) {
                Ok(ns) => Some(ns),
                Err(e) => {
                    notes.push(format!(
                        "{d} ms: netem unavailable ({e}); emulated by a user-space TCP proxy \
                         that delays each direction by {d} ms"
                    ));
                    None
                }
            };
            let (link, _child, _proxy, _server, url) = match (&netns, &opts.chunkrt_exe) {
                (Some(ns), Some(exe)) => {
                    let child = Command::new("ip")
                        .args(["netns", "exec", &ns.name])
                        .arg(exe)
                        .args(["serve", "--checkpoint"])
                        .arg(&m.dir)
                        .args(["--host", Netns::PEER, "--port", "8000", "--log-every", "0"])
                        .stdout(Stdio::null())
                        .stderr(Stdio::null())
                        .spawn()
                        .map_err(|e| err("chunkrt serve in the namespace", e))?;
                    (
                        "netem",
                        Some(Guard(child)),
                        None,
                        None,
                        format!("ws://{}:8000", Netns::PEER),
                    )
                }
                _ => {
                    let server = local_server(m)?;
                    let proxy =
                        DelayProxy::start(server.local_addr(), Duration::from_secs_f64(d / 1e3))
                            .map_err(|e| err("delay proxy", e))?;
                    let url = format!("ws://{}", proxy.addr());
                    ("proxy", None, Some(proxy), Some(server), url)
                }
            };
            let mut client = connect_retry(&url, Duration::from_secs(60))?;
            let link = format!("{link}{d}ms");
            measure_cases(
                &mut client,
                m,
                &link,
                false,
                opts.requests,
                &mut rng,
                &mut series,
            )?;
        }
    }
    if opts.python {
        match python_reference(opts.requests) {
            Ok(h) => {
                println!(
                    "openpi reference (openpi-server + openpi-client, instant policy, 3 × 224², \
                     loopback): round trip p50 {} / p99 {} µs",
                    fmt_us(h.value_at_quantile(0.5)),
                    fmt_us(h.value_at_quantile(0.99))
                );
                series.push(Series::new("openpi_python_cam3_loopback_roundtrip", h));
            }
            Err(e) => notes.push(format!("openpi reference: not measured: {e}")),
        }
    }
    let _ = std::fs::remove_dir_all(&tmp);
    let table = LatencyTable::from_series(
        "remote policy: in process vs behind chunkrt serve (µs)",
        &series,
    );
    println!("{table}");
    for n in &notes {
        println!("note: {n}");
    }
    let names: Vec<String> = series
        .iter()
        .filter(|s| s.name.ends_with("_added"))
        .map(|s| s.name.clone())
        .collect();
    let out = write_outputs(
        &opts.bench.out_dir,
        "remote",
        &table,
        &series,
        &[("remote_added", "what the wire adds to a chunk", names)],
        t0.elapsed(),
        &notes.join("; "),
    )?;
    println!("{out}");
    Ok(table)
}
