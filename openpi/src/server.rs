//! A websocket policy server that speaks openpi's protocol (openpi's `WebsocketPolicyServer`,
//! byte for byte on the wire): the metadata on connect, then one reply per observation, an
//! error as a text frame and a close with 1011, `GET /healthz` → 200 `OK`.
//!
//! Threads: one accepts connections; one per connection reads, decodes and checks its requests
//! (a bad message is answered on its own connection and never reaches the policy); one runs the
//! policy. Requests of every connection queue in arrival order for the policy thread, which
//! serves one at a time (first come, first served; a connection has at most one request in
//! flight, as openpi's client waits for each reply). Beyond `max_connections` a connection is
//! refused with HTTP 503; a wrong or missing api key with 401, before any model work.

use std::io::{Read, Write};
use std::net::{SocketAddr, TcpListener, TcpStream};
use std::sync::atomic::{AtomicBool, AtomicU64, AtomicUsize, Ordering};
use std::sync::{mpsc, Arc, Mutex};
use std::thread::JoinHandle;
use std::time::{Duration, Instant};

use tungstenite::protocol::frame::coding::CloseCode;
use tungstenite::protocol::{CloseFrame, WebSocketConfig};
use tungstenite::{Message, WebSocket};

use crate::message::{Reply, Request, RequestError};
use crate::msgpack::{decode, Limits, Value};

/// How the server listens and what it accepts.
#[derive(Debug, Clone)]
pub struct ServerConfig {
    /// Where to listen (port 0: any free port; [`Server::local_addr`] tells which).
    pub addr: SocketAddr,
    /// The `Authorization: Api-Key …` every connection must send (None: no key needed).
    pub api_key: Option<String>,
    /// The largest request message (bytes); a larger one is an error on its connection.
    pub max_message_bytes: usize,
    /// Connections served at once.
    pub max_connections: usize,
    /// Decoding limits.
    pub limits: Limits,
    /// Connections one address may hold at once (a peer cannot take every slot).
    pub max_per_address: usize,
    /// A connection that has not completed its HTTP request and websocket handshake within
    /// this is closed (a half-sent request holds its slot no longer).
    pub handshake_timeout: Duration,
    /// A websocket that sends no request for this long is closed (openpi-client's keep-alive
    /// pings do not count; a client that pauses longer reconnects).
    pub idle_timeout: Duration,
}

impl ServerConfig {
    /// `addr` with the defaults: no api key, 16 connections of which 4 per address, 2 s for
    /// the handshake, 10 minutes idle, messages up to `max_message_bytes`.
    pub fn new(addr: SocketAddr, max_message_bytes: usize) -> Self {
        Self {
            addr,
            api_key: None,
            max_message_bytes,
            max_connections: 16,
            limits: Limits::default(),
            max_per_address: 4,
            handshake_timeout: Duration::from_secs(2),
            idle_timeout: Duration::from_secs(600),
        }
    }
}

/// Reads a decoded message into a request (runs on the connection threads).
pub type Parse = dyn Fn(&Value<'_>) -> Result<Request, RequestError> + Send + Sync;

/// Answers a request (runs on the policy thread, one request at a time).
pub type Handle = dyn FnMut(&Request) -> Result<Reply, String> + Send;

/// Hears of refused connections and failed requests: `(kind, line)`, kind as
/// [`Failure::name`] or `unauthorized`; the caller rate-limits its log (many threads call it).
pub type Report = dyn Fn(&str, String) + Send + Sync;

/// What went wrong with a request, by kind (the server's counters).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Failure {
    /// Not msgpack-numpy, or beyond the decoding limits.
    Decode,
    /// Missing keys, wrong dtypes or shapes, non-finite numbers.
    Request,
    /// Larger than `max_message_bytes`.
    TooLarge,
    /// A text frame (openpi's protocol is binary).
    Text,
    /// The policy failed.
    Policy,
}

impl Failure {
    /// Every kind.
    pub const ALL: [Failure; 5] = [
        Failure::Decode,
        Failure::Request,
        Failure::TooLarge,
        Failure::Text,
        Failure::Policy,
    ];

    /// Its name in logs and status lines.
    pub fn name(self) -> &'static str {
        match self {
            Failure::Decode => "decode",
            Failure::Request => "request",
            Failure::TooLarge => "too_large",
            Failure::Text => "text_frame",
            Failure::Policy => "policy",
        }
    }
}

/// The server's counters.
#[derive(Debug, Default)]
pub struct ServerStats {
    /// Websocket connections accepted.
    pub connections: AtomicU64,
    /// Connections open now.
    pub open: AtomicUsize,
    /// Requests answered with a chunk.
    pub replies: AtomicU64,
    /// Failed requests by [`Failure`] (index in `Failure::ALL`).
    pub failures: [AtomicU64; 5],
    /// Connections refused for a wrong or missing api key.
    pub unauthorized: AtomicU64,
    /// Connections refused because `max_connections` were open, or their address held
    /// `max_per_address`.
    pub busy: AtomicU64,
    /// Connections closed before they completed their handshake in time.
    pub handshake_timeouts: AtomicU64,
    /// Websockets closed after `idle_timeout` without a request.
    pub idle_closed: AtomicU64,
    /// `GET /healthz` answered.
    pub health_checks: AtomicU64,
    /// Receive → reply sent of each answered request (µs), and the policy's part of it.
    pub latency_us: Mutex<Vec<(u64, u64)>>,
}

impl ServerStats {
    /// Failures of `kind` so far.
    pub fn failures(&self, kind: Failure) -> u64 {
        let i = Failure::ALL.iter().position(|k| *k == kind).unwrap_or(0);
        self.failures[i].load(Ordering::Relaxed)
    }

    fn fail(&self, kind: Failure) {
        let i = Failure::ALL.iter().position(|k| *k == kind).unwrap_or(0);
        self.failures[i].fetch_add(1, Ordering::Relaxed);
    }

    /// Takes the latencies recorded since the last call.
    pub fn take_latencies(&self) -> Vec<(u64, u64)> {
        self.latency_us
            .lock()
            .map(|mut v| std::mem::take(&mut *v))
            .unwrap_or_default()
    }
}

/// A job for the policy thread.
struct Job {
    request: Request,
    answer: mpsc::SyncSender<(Result<Reply, String>, Duration)>,
}

/// The most of a failure's text a log line carries (bytes).
pub const LOG_TEXT_MAX: usize = 400;
/// The most of a failure's text the error reply carries (bytes).
pub const REPLY_TEXT_MAX: usize = 4096;

/// A running server.
pub struct Server {
    addr: SocketAddr,
    stop: Arc<AtomicBool>,
    stats: Arc<ServerStats>,
    accept: Option<JoinHandle<()>>,
    policy: Option<JoinHandle<()>>,
}

/// What every connection thread shares.
struct Shared {
    cfg: ServerConfig,
    metadata: Vec<u8>,
    parse: Box<Parse>,
    jobs: Mutex<Option<mpsc::SyncSender<Job>>>,
    stats: Arc<ServerStats>,
    stop: Arc<AtomicBool>,
    report: Box<Report>,
    /// Connections open per peer address.
    per_address: Mutex<std::collections::HashMap<std::net::IpAddr, usize>>,
}

impl Server {
    /// Binds `cfg.addr` and serves: `metadata` (packed msgpack) on every connect, `parse` on
    /// the connection threads, `handle` on the policy thread; failures go to `report`.
    pub fn start(
        cfg: ServerConfig,
        metadata: Vec<u8>,
        parse: Box<Parse>,
        mut handle: Box<Handle>,
        report: Box<Report>,
    ) -> std::io::Result<Server> {
        let listener = TcpListener::bind(cfg.addr)?;
        listener.set_nonblocking(true)?;
        let addr = listener.local_addr()?;
        let stop = Arc::new(AtomicBool::new(false));
        let stats = Arc::new(ServerStats::default());
        let (tx, rx) = mpsc::sync_channel::<Job>(cfg.max_connections.max(1));
        let policy = std::thread::Builder::new()
            .name("chunkrt-serve-policy".into())
            .spawn(move || {
                // requests of every connection, first come first served
                while let Ok(job) = rx.recv() {
                    let t = Instant::now();
                    let r = handle(&job.request);
                    let _ = job.answer.send((r, t.elapsed()));
                }
            })?;
        let shared = Arc::new(Shared {
            cfg,
            metadata,
            parse,
            jobs: Mutex::new(Some(tx)),
            stats: stats.clone(),
            stop: stop.clone(),
            report,
            per_address: Mutex::new(std::collections::HashMap::new()),
        });
        let accept = std::thread::Builder::new()
            .name("chunkrt-serve-accept".into())
            .spawn(move || accept_loop(listener, shared))?;
        Ok(Server {
            addr,
            stop,
            stats,
            accept: Some(accept),
            policy: Some(policy),
        })
    }

    /// The address it listens on.
    pub fn local_addr(&self) -> SocketAddr {
        self.addr
    }

    /// Its counters.
    pub fn stats(&self) -> &Arc<ServerStats> {
        &self.stats
    }

    /// Stops accepting, closes every connection within a second, and ends the policy thread.
    pub fn stop(mut self) {
        self.shutdown();
    }

    fn shutdown(&mut self) {
        self.stop.store(true, Ordering::SeqCst);
        if let Some(h) = self.accept.take() {
            let _ = h.join();
        }
        if let Some(h) = self.policy.take() {
            let _ = h.join();
        }
    }
}

impl Drop for Server {
    fn drop(&mut self) {
        self.shutdown();
    }
}

fn accept_loop(listener: TcpListener, shared: Arc<Shared>) {
    let mut conns: Vec<JoinHandle<()>> = Vec::new();
    while !shared.stop.load(Ordering::Relaxed) {
        conns.retain(|h| !h.is_finished());
        match listener.accept() {
            Ok((stream, peer)) => {
                let _ = stream.set_nonblocking(false);
                let _ = stream.set_nodelay(true);
                if shared.stats.open.load(Ordering::Relaxed) >= shared.cfg.max_connections {
                    shared.stats.busy.fetch_add(1, Ordering::Relaxed);
                    refuse(stream, "503 Service Unavailable", "too many connections\n");
                    continue;
                }
                // one address holds at most max_per_address of the slots
                let ip = peer.ip();
                let admitted = shared.per_address.lock().is_ok_and(|mut m| {
                    let n = m.entry(ip).or_insert(0);
                    if *n >= shared.cfg.max_per_address.max(1) {
                        false
                    } else {
                        *n += 1;
                        true
                    }
                });
                if !admitted {
                    shared.stats.busy.fetch_add(1, Ordering::Relaxed);
                    shared.warn("busy", || {
                        format!(
                            "serve: {peer}: refused: {ip} already holds {} connections",
                            shared.cfg.max_per_address
                        )
                    });
                    refuse(
                        stream,
                        "503 Service Unavailable",
                        "too many connections from this address\n",
                    );
                    continue;
                }
                let release = move |s: &Shared| {
                    s.stats.open.fetch_sub(1, Ordering::Relaxed);
                    if let Ok(mut m) = s.per_address.lock() {
                        if let Some(n) = m.get_mut(&ip) {
                            *n = n.saturating_sub(1);
                            if *n == 0 {
                                m.remove(&ip);
                            }
                        }
                    }
                };
                shared.stats.open.fetch_add(1, Ordering::Relaxed);
                let s = shared.clone();
                let spawned = std::thread::Builder::new()
                    .name("chunkrt-serve-conn".into())
                    .spawn(move || {
                        serve_connection(stream, peer, &s);
                        release(&s);
                    });
                match spawned {
                    Ok(h) => conns.push(h),
                    Err(e) => {
                        release(&shared);
                        tracing::warn!("serve: cannot start a connection thread: {e}");
                    }
                }
            }
            Err(e) if e.kind() == std::io::ErrorKind::WouldBlock => {
                std::thread::sleep(Duration::from_millis(10));
            }
            Err(e) => {
                tracing::warn!("serve: accept failed: {e}");
                std::thread::sleep(Duration::from_millis(50));
            }
        }
    }
    // closing the job queue ends the policy thread once the connections are gone
    for h in conns {
        let _ = h.join();
    }
    if let Ok(mut j) = shared.jobs.lock() {
        j.take();
    }
}

fn refuse(mut stream: TcpStream, status: &str, body: &str) {
    let _ = stream.set_write_timeout(Some(Duration::from_secs(1)));
    let _ = write!(
        stream,
        "HTTP/1.1 {status}\r\nContent-Type: text/plain; charset=utf-8\r\nContent-Length: {}\r\nConnection: close\r\n\r\n{body}",
        body.len()
    );
    let _ = stream.flush();
}

/// The request head, peeked (not consumed) so the websocket handshake can read it again.
struct Head {
    len: usize,
    path: String,
    authorization: Option<String>,
}

fn peek_head(stream: &TcpStream, deadline: Instant, stop: &AtomicBool) -> Option<Head> {
    let mut buf = vec![0u8; 16 * 1024];
    // short waits, so a stop or the deadline is seen while the peer sends nothing
    let _ = stream.set_read_timeout(Some(Duration::from_millis(100)));
    loop {
        if stop.load(Ordering::Relaxed) || Instant::now() >= deadline {
            return None;
        }
        let n = match stream.peek(&mut buf) {
            Ok(n) => n,
            Err(e)
                if matches!(
                    e.kind(),
                    std::io::ErrorKind::WouldBlock | std::io::ErrorKind::TimedOut
                ) =>
            {
                continue
            }
            Err(_) => return None,
        };
        if n == 0 {
            return None;
        }
        let mut headers = [httparse::EMPTY_HEADER; 64];
        let mut req = httparse::Request::new(&mut headers);
        match req.parse(&buf[..n]) {
            Ok(httparse::Status::Complete(len)) => {
                let authorization = req
                    .headers
                    .iter()
                    .find(|h| h.name.eq_ignore_ascii_case("authorization"))
                    .and_then(|h| std::str::from_utf8(h.value).ok())
                    .map(str::to_string);
                return Some(Head {
                    len,
                    path: req.path.unwrap_or("").to_string(),
                    authorization,
                });
            }
            Ok(httparse::Status::Partial) if n < buf.len() && Instant::now() < deadline => {
                std::thread::sleep(Duration::from_millis(2));
            }
            _ => return None,
        }
    }
}

/// Compares without stopping at the first difference.
fn same_key(given: &str, key: &str) -> bool {
    let (a, b) = (given.as_bytes(), key.as_bytes());
    let diff = a
        .iter()
        .zip(b.iter())
        .fold(0u8, |acc, (x, y)| acc | (x ^ y));
    diff == 0 && a.len() == b.len()
}

fn serve_connection(mut stream: TcpStream, peer: SocketAddr, s: &Shared) {
    let deadline = Instant::now() + s.cfg.handshake_timeout;
    let _ = stream.set_write_timeout(Some(Duration::from_secs(2)));
    let Some(head) = peek_head(&stream, deadline, &s.stop) else {
        s.stats.handshake_timeouts.fetch_add(1, Ordering::Relaxed);
        return;
    };
    // the rest of the handshake within what is left of the deadline
    let left = deadline
        .saturating_duration_since(Instant::now())
        .max(Duration::from_millis(10));
    let _ = stream.set_read_timeout(Some(left));
    let consume = |stream: &mut TcpStream, n: usize| {
        let mut sink = vec![0u8; n];
        let _ = stream.read_exact(&mut sink);
    };
    if head.path == "/healthz" {
        s.stats.health_checks.fetch_add(1, Ordering::Relaxed);
        consume(&mut stream, head.len);
        refuse(stream, "200 OK", "OK\n");
        return;
    }
    if let Some(key) = &s.cfg.api_key {
        let ok = head
            .authorization
            .as_deref()
            .and_then(|a| a.strip_prefix("Api-Key "))
            .is_some_and(|given| same_key(given.trim(), key));
        if !ok {
            s.stats.unauthorized.fetch_add(1, Ordering::Relaxed);
            s.warn("unauthorized", || {
                format!("serve: {peer}: refused: wrong or missing api key")
            });
            consume(&mut stream, head.len);
            refuse(stream, "401 Unauthorized", "wrong or missing api key\n");
            return;
        }
    }
    let ws_cfg = WebSocketConfig::default()
        .max_message_size(Some(s.cfg.max_message_bytes))
        .max_frame_size(Some(s.cfg.max_message_bytes));
    let mut ws = match tungstenite::accept_with_config(stream, Some(ws_cfg)) {
        Ok(ws) => ws,
        Err(e) => {
            tracing::debug!("serve: {peer}: handshake failed: {e}");
            return;
        }
    };
    s.stats.connections.fetch_add(1, Ordering::Relaxed);
    tracing::info!("serve: {peer} connected");
    // short reads, so the thread sees a stop; tungstenite keeps a partial frame across them
    let _ = ws
        .get_ref()
        .set_read_timeout(Some(Duration::from_millis(200)));
    if ws.send(Message::Binary(s.metadata.clone().into())).is_err() {
        return;
    }
    let mut prev_total: Option<Duration> = None;
    let mut waiting_since = Instant::now();
    loop {
        if waiting_since.elapsed() >= s.cfg.idle_timeout {
            s.stats.idle_closed.fetch_add(1, Ordering::Relaxed);
            tracing::info!(
                "serve: {peer}: no request for {:.0} s: closed",
                s.cfg.idle_timeout.as_secs_f64()
            );
            let _ = ws.close(Some(CloseFrame {
                code: CloseCode::Away,
                reason: "idle".into(),
            }));
            let _ = ws.flush();
            return;
        }
        if s.stop.load(Ordering::Relaxed) {
            let _ = ws.close(Some(CloseFrame {
                code: CloseCode::Away,
                reason: "server stopping".into(),
            }));
            let _ = ws.flush();
            return;
        }
        let msg = match ws.read() {
            Ok(m) => m,
            Err(tungstenite::Error::Io(e))
                if matches!(
                    e.kind(),
                    std::io::ErrorKind::WouldBlock | std::io::ErrorKind::TimedOut
                ) =>
            {
                continue
            }
            Err(tungstenite::Error::Capacity(e)) => {
                fail(
                    &mut ws,
                    peer,
                    s,
                    Failure::TooLarge,
                    &format!(
                        "the message is larger than the server's limit of {} bytes ({e})",
                        s.cfg.max_message_bytes
                    ),
                );
                return;
            }
            Err(_) => {
                tracing::info!("serve: {peer} disconnected");
                return;
            }
        };
        let bytes = match msg {
            Message::Binary(b) => b,
            Message::Text(_) => {
                fail(
                    &mut ws,
                    peer,
                    s,
                    Failure::Text,
                    "expected a binary msgpack frame, got text",
                );
                return;
            }
            Message::Close(_) => {
                tracing::info!("serve: {peer} closed the connection");
                return;
            }
            _ => continue,
        };
        let start = waiting_since;
        let value = match decode(&bytes, s.cfg.limits) {
            Ok(v) => v,
            Err(e) => {
                fail(
                    &mut ws,
                    peer,
                    s,
                    Failure::Decode,
                    &format!("malformed msgpack-numpy: {e}"),
                );
                return;
            }
        };
        let request = match (s.parse)(&value) {
            Ok(r) => r,
            Err(e) => {
                fail(
                    &mut ws,
                    peer,
                    s,
                    Failure::Request,
                    &format!("bad observation: {e}"),
                );
                return;
            }
        };
        drop(value);
        let (answer_tx, answer_rx) = mpsc::sync_channel(1);
        let queued = s
            .jobs
            .lock()
            .ok()
            .and_then(|j| j.as_ref().cloned())
            .is_some_and(|tx| {
                tx.send(Job {
                    request,
                    answer: answer_tx,
                })
                .is_ok()
            });
        let answer = if queued { answer_rx.recv().ok() } else { None };
        let (mut reply, infer) = match answer {
            Some((Ok(r), t)) => (r, t),
            Some((Err(e), _)) => {
                fail(
                    &mut ws,
                    peer,
                    s,
                    Failure::Policy,
                    &format!("policy error: {e}"),
                );
                return;
            }
            None => {
                fail(
                    &mut ws,
                    peer,
                    s,
                    Failure::Policy,
                    "the policy thread has stopped",
                );
                return;
            }
        };
        reply.server_infer_ms = Some(infer.as_secs_f64() * 1e3);
        reply.prev_total_ms = prev_total.map(|t| t.as_secs_f64() * 1e3);
        let mut w = crate::msgpack::Writer::new();
        reply.write(&mut w);
        // counted before it is sent: a client that has its reply finds it counted
        s.stats.replies.fetch_add(1, Ordering::Relaxed);
        if ws.send(Message::Binary(w.buf.into())).is_err() {
            return;
        }
        let total = start.elapsed();
        prev_total = Some(total);
        waiting_since = Instant::now();
        if let Ok(mut l) = s.stats.latency_us.lock() {
            if l.len() < 1 << 20 {
                l.push((total.as_micros() as u64, infer.as_micros() as u64));
            }
        }
    }
}

/// Answers a failed request as openpi's server does (the error as a text frame, then a close
/// with 1011), counts it and logs it (rate-limited). Other connections go on.
fn fail(ws: &mut WebSocket<TcpStream>, peer: SocketAddr, s: &Shared, kind: Failure, text: &str) {
    s.stats.fail(kind);
    // the text may quote what the peer sent: bounded in the log and in the reply
    s.warn(kind.name(), || {
        format!(
            "serve: {peer}: {}",
            crate::message::clip_text(text, LOG_TEXT_MAX)
        )
    });
    let _ = ws.send(Message::Text(
        crate::message::clip_text(text, REPLY_TEXT_MAX)
            .into_owned()
            .into(),
    ));
    let _ = ws.close(Some(CloseFrame {
        code: CloseCode::Error,
        reason: "Internal server error".into(),
    }));
    // let the close handshake finish (bounded by the read timeouts)
    let deadline = Instant::now() + Duration::from_secs(1);
    while Instant::now() < deadline {
        match ws.read() {
            Ok(_) => {}
            Err(tungstenite::Error::Io(e))
                if matches!(
                    e.kind(),
                    std::io::ErrorKind::WouldBlock | std::io::ErrorKind::TimedOut
                ) => {}
            Err(_) => break,
        }
    }
}

impl Shared {
    fn warn(&self, kind: &str, line: impl FnOnce() -> String) {
        (self.report)(kind, line());
    }
}
