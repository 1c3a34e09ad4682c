//! A websocket policy server that speaks openpi's protocol (openpi's `WebsocketPolicyServer`,
//! byte for byte on the wire): the metadata on connect, then one reply per observation, an
//! error as a text frame and a close with 1011, `GET /healthz` → 200 `OK`.
//!
//! Threads: one accepts connections; one per connection reads, decodes and checks its requests
//! (a bad message is answered on its own connection and never reaches the policy); one runs the
//! policy. Requests of every connection queue in arrival order for the policy thread, which
//! serves one at a time (first come, first served; a connection has at most one request in
//! flight, as openpi's client waits for each reply). A wrong or missing api key is refused with
//! 401, before any model work.
//!
//! Slots: `max_connections` websockets, of which an address holds `max_per_address` and a
//! network (IPv4 /24, IPv6 /64) `max_per_network`. A connection in its handshake holds none of
//! them (`max_handshakes` may be pending, half per network; the oldest whose request head is
//! still incomplete makes way for a new one). When a handshake is done and a share is full,
//! the websocket of that share idle the longest (none with a request in flight or within the
//! last second) is closed for it; only when there is none is it refused with 503. A message
//! that has begun must be complete within `message_timeout`.

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
    /// Connections one network may hold at once: an IPv4 /24, an IPv6 /64 (a peer with many
    /// addresses in one network, as a host's IPv6 privacy addresses, is one peer here too).
    pub max_per_network: usize,
    /// Connections still in their HTTP request and websocket handshake at once (they hold none
    /// of the `max_connections` slots; when this many are pending, the oldest is dropped for a
    /// new one, so a flood of unfinished requests cannot keep a client's handshake out).
    pub max_handshakes: usize,
    /// A message that has begun to arrive must be complete within this (a frame announced
    /// large and sent a byte at a time holds its slot no longer).
    pub message_timeout: Duration,
}

impl ServerConfig {
    /// `addr` with the defaults: no api key, 16 connections of which 4 per address and 8 per
    /// network (/24, /64), 64 handshakes pending, 2 s for the handshake, 30 s idle (openpi's
    /// clients ask every few hundred milliseconds), 10 s for a message once it has begun,
    /// messages up to `max_message_bytes`.
    pub fn new(addr: SocketAddr, max_message_bytes: usize) -> Self {
        Self {
            addr,
            api_key: None,
            max_message_bytes,
            max_connections: 16,
            limits: Limits::default(),
            max_per_address: 4,
            handshake_timeout: Duration::from_secs(2),
            idle_timeout: Duration::from_secs(DEFAULT_IDLE_TIMEOUT_S),
            max_per_network: 8,
            max_handshakes: 64,
            message_timeout: Duration::from_secs(10),
        }
    }
}

/// The default idle timeout (s): openpi's clients send a request every few hundred ms while
/// they run; one that pauses longer reconnects.
pub const DEFAULT_IDLE_TIMEOUT_S: u64 = 30;

/// A websocket that has had a request within this is never dropped for a new connection.
const RECENT: Duration = Duration::from_secs(1);

/// The network an address is accounted in: an IPv4 address's /24, an IPv6 address's /64 (an
/// IPv4-mapped IPv6 address as its IPv4 address).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub enum Network {
    /// The first three octets.
    V4([u8; 3]),
    /// The first four 16-bit groups.
    V6([u16; 4]),
}

impl Network {
    /// The network of `ip`.
    pub fn of(ip: std::net::IpAddr) -> Self {
        match ip {
            std::net::IpAddr::V4(a) => {
                let o = a.octets();
                Network::V4([o[0], o[1], o[2]])
            }
            std::net::IpAddr::V6(a) => match a.to_ipv4_mapped() {
                Some(v4) => Network::of(std::net::IpAddr::V4(v4)),
                None => {
                    let g = a.segments();
                    Network::V6([g[0], g[1], g[2], g[3]])
                }
            },
        }
    }
}

/// Selects connections of the table (an address's, a network's, all).
type SlotFilter<'a> = dyn Fn(&Slot) -> bool + 'a;

/// One connection in the server's table: in its handshake, or a websocket holding a slot.
struct Slot {
    id: u64,
    ip: std::net::IpAddr,
    net: Network,
    /// A websocket (holds one of `max_connections`); else still in its handshake.
    open: bool,
    /// Handshake: when it began; websocket: its last request's end (or its connect).
    since: Instant,
    /// A request of it is being answered.
    busy: bool,
    /// It has sent a request since it connected.
    asked: bool,
    /// Its HTTP request head is complete (a handshake about to finish: not dropped for a newer
    /// one).
    head: bool,
    /// Set to make its thread close it.
    drop_it: Arc<AtomicBool>,
}

/// The connections, and who makes way for whom.
#[derive(Default)]
struct Table {
    slots: Vec<Slot>,
    next: u64,
}

impl Table {
    /// The longest-idle websocket among those `pick` selects that has no request in flight and
    /// none within [`RECENT`] (never-asking ones first, by age).
    fn idlest(&self, pick: impl Fn(&Slot) -> bool) -> Option<usize> {
        self.slots
            .iter()
            .enumerate()
            .filter(|(_, c)| {
                c.open && pick(c) && !c.busy && !(c.asked && c.since.elapsed() < RECENT)
            })
            .min_by_key(|(_, c)| (c.asked, c.since))
            .map(|(i, _)| i)
    }

    fn evict(&mut self, i: usize) {
        let c = self.slots.swap_remove(i);
        c.drop_it.store(true, Ordering::Relaxed);
    }

    fn open_count(&self) -> usize {
        self.slots.iter().filter(|c| c.open).count()
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
    /// Connections refused with 503: every websocket of their share (address, network, all)
    /// was answering or had just asked, or too many connection threads were alive.
    pub busy: AtomicU64,
    /// Connections closed before they completed their handshake in time.
    pub handshake_timeouts: AtomicU64,
    /// Websockets closed after `idle_timeout` without a request.
    pub idle_closed: AtomicU64,
    /// Connections dropped to make way for a new one: websockets idle the longest (the server
    /// was full, or their address or network held its share), and the oldest pending
    /// handshakes (`max_handshakes` were pending).
    pub made_way: AtomicU64,
    /// Websockets closed because a message that had begun did not complete in
    /// `message_timeout`.
    pub message_timeouts: AtomicU64,
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
    /// Every connection, in its handshake or open.
    table: Mutex<Table>,
    /// Connection threads alive (including those told to go and not yet gone).
    threads: AtomicUsize,
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
            table: Mutex::new(Table::default()),
            threads: AtomicUsize::new(0),
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
                // threads alive, those told to go included: a flood of new connections is
                // refused rather than met with ever more threads
                let cap = shared.cfg.max_connections.max(1) + shared.cfg.max_handshakes.max(1);
                if shared.threads.load(Ordering::Relaxed) >= 2 * cap {
                    shared.stats.busy.fetch_add(1, Ordering::Relaxed);
                    refuse(stream, "503 Service Unavailable", "too many connections\n");
                    continue;
                }
                // a handshake holds no websocket slot; the oldest pending one makes way
                let Some((id, drop_it)) = shared.begin_handshake(peer.ip()) else {
                    refuse(stream, "503 Service Unavailable", "too many connections\n");
                    continue;
                };
                shared.threads.fetch_add(1, Ordering::Relaxed);
                let s = shared.clone();
                let spawned = std::thread::Builder::new()
                    .name("chunkrt-serve-conn".into())
                    .spawn(move || {
                        serve_connection(stream, peer, &s, id, &drop_it);
                        s.release(id);
                        s.threads.fetch_sub(1, Ordering::Relaxed);
                    });
                match spawned {
                    Ok(h) => conns.push(h),
                    Err(e) => {
                        shared.release(id);
                        shared.threads.fetch_sub(1, Ordering::Relaxed);
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

fn peek_head(
    stream: &TcpStream,
    deadline: Instant,
    stop: &AtomicBool,
    drop_it: &AtomicBool,
) -> Option<Head> {
    let mut buf = vec![0u8; 16 * 1024];
    // short waits, so a stop or the deadline is seen while the peer sends nothing
    let _ = stream.set_read_timeout(Some(Duration::from_millis(100)));
    loop {
        // a head already here is taken even when this connection was told to make way (a
        // client whose request arrived with its connect is not dropped for a flood after it)
        let n = match stream.peek(&mut buf) {
            Ok(0) => return None,
            Ok(n) => n,
            Err(e)
                if matches!(
                    e.kind(),
                    std::io::ErrorKind::WouldBlock | std::io::ErrorKind::TimedOut
                ) =>
            {
                0
            }
            Err(_) => return None,
        };
        if n > 0 {
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
                Ok(httparse::Status::Partial) if n < buf.len() => {}
                _ => return None,
            }
        }
        if stop.load(Ordering::Relaxed)
            || drop_it.load(Ordering::Relaxed)
            || Instant::now() >= deadline
        {
            return None;
        }
        if n > 0 {
            std::thread::sleep(Duration::from_millis(2));
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

fn serve_connection(
    stream: TcpStream,
    peer: SocketAddr,
    s: &Shared,
    id: u64,
    drop_it: &AtomicBool,
) {
    let Some(ws) = handshake(stream, peer, s, id, drop_it) else {
        return;
    };
    Session {
        peer,
        s,
        id,
        drop_it,
        prev_total: None,
        waiting_since: Instant::now(),
        mark: ws.get_ref().bytes,
        begun: None,
        ws,
    }
    .run();
}

/// The connection's way to a websocket within `handshake_timeout`: its request head, then
/// [`admit`] and [`upgrade`]. None: it has been answered (health check, refusal), or it failed
/// or went.
fn handshake(
    stream: TcpStream,
    peer: SocketAddr,
    s: &Shared,
    id: u64,
    drop_it: &AtomicBool,
) -> Option<WebSocket<Counted>> {
    let deadline = Instant::now() + s.cfg.handshake_timeout;
    let _ = stream.set_write_timeout(Some(Duration::from_secs(2)));
    let Some(head) = peek_head(&stream, deadline, &s.stop, drop_it) else {
        if !drop_it.load(Ordering::Relaxed) {
            s.stats.handshake_timeouts.fetch_add(1, Ordering::Relaxed);
        }
        return None;
    };
    s.head_done(id);
    // the rest of the handshake within what is left of the deadline
    let left = deadline
        .saturating_duration_since(Instant::now())
        .max(Duration::from_millis(10));
    let _ = stream.set_read_timeout(Some(left));
    let stream = admit(stream, &head, peer, s, id)?;
    upgrade(stream, peer, s)
}

/// Answers a request that gets no websocket: `GET /healthz` (200), a wrong or missing api key
/// (401), no slot to be had (503). Some: the connection now holds a websocket slot.
fn admit(
    mut stream: TcpStream,
    head: &Head,
    peer: SocketAddr,
    s: &Shared,
    id: u64,
) -> Option<TcpStream> {
    if head.path == "/healthz" {
        s.stats.health_checks.fetch_add(1, Ordering::Relaxed);
        consume(&mut stream, head.len);
        refuse(stream, "200 OK", "OK\n");
        return None;
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
            return None;
        }
    }
    // a websocket slot: the longest-idle websocket of this address, network or all makes way
    if let Err(why) = s.open(id) {
        s.stats.busy.fetch_add(1, Ordering::Relaxed);
        s.warn("busy", || format!("serve: {peer}: refused: {why}"));
        consume(&mut stream, head.len);
        refuse(
            stream,
            "503 Service Unavailable",
            &format!("too many connections: {why}\n"),
        );
        return None;
    }
    Some(stream)
}

/// Reads the `n` bytes of the peeked request head and drops them.
fn consume(stream: &mut TcpStream, n: usize) {
    let mut sink = vec![0u8; n];
    let _ = stream.read_exact(&mut sink);
}

/// The websocket handshake of an admitted connection, then the metadata sent. None: either
/// failed.
fn upgrade(stream: TcpStream, peer: SocketAddr, s: &Shared) -> Option<WebSocket<Counted>> {
    let ws_cfg = WebSocketConfig::default()
        .max_message_size(Some(s.cfg.max_message_bytes))
        .max_frame_size(Some(s.cfg.max_message_bytes));
    let stream = Counted { stream, bytes: 0 };
    let mut ws = match tungstenite::accept_with_config(stream, Some(ws_cfg)) {
        Ok(ws) => ws,
        Err(e) => {
            tracing::debug!("serve: {peer}: handshake failed: {e}");
            return None;
        }
    };
    s.stats.connections.fetch_add(1, Ordering::Relaxed);
    tracing::info!("serve: {peer} connected");
    // short reads, so the thread sees a stop; tungstenite keeps a partial frame across them
    let _ = ws
        .get_ref()
        .stream
        .set_read_timeout(Some(Duration::from_millis(200)));
    if ws.send(Message::Binary(s.metadata.clone().into())).is_err() {
        return None;
    }
    Some(ws)
}

/// An open websocket: its requests answered one at a time until it closes or is closed.
struct Session<'a> {
    ws: WebSocket<Counted>,
    peer: SocketAddr,
    s: &'a Shared,
    id: u64,
    drop_it: &'a AtomicBool,
    /// Receive → reply sent of the last request answered (sent with the next reply).
    prev_total: Option<Duration>,
    /// Since when the connection has been waiting for a request.
    waiting_since: Instant,
    /// Bytes read when the last message completed, and since when a message has been arriving.
    mark: u64,
    begun: Option<Instant>,
}

/// What the next read of a [`Session`] gave.
enum Next {
    /// A request's bytes.
    Request(tungstenite::Bytes),
    /// Nothing yet (a read timeout), or a frame that is no request (ping, pong).
    Again,
    /// The connection is done: closed by the peer, gone, or failed and answered so.
    End,
}

impl Session<'_> {
    fn run(mut self) {
        loop {
            if self.close_if_due() {
                return;
            }
            let bytes = match self.read_request() {
                Next::Request(b) => b,
                Next::Again => continue,
                Next::End => return,
            };
            if !self.answer(&bytes) {
                return;
            }
        }
    }

    /// Closes the websocket where it must go: it made way for a new connection, a message
    /// begun `message_timeout` ago is still incomplete, no request came for `idle_timeout`,
    /// or the server is stopping. True: closed.
    fn close_if_due(&mut self) -> bool {
        let (s, peer) = (self.s, self.peer);
        if self.drop_it.load(Ordering::Relaxed) {
            tracing::info!("serve: {peer}: idle the longest: closed for a new connection");
            self.close(CloseCode::Again, "made way for a new connection");
            return true;
        }
        if self.ws.get_ref().bytes > self.mark && self.begun.is_none() {
            self.begun = Some(Instant::now());
        }
        if self
            .begun
            .is_some_and(|t| t.elapsed() >= s.cfg.message_timeout)
        {
            s.stats.message_timeouts.fetch_add(1, Ordering::Relaxed);
            s.warn("message_timeout", || {
                format!(
                    "serve: {peer}: a message begun {:.0} s ago is still incomplete: closed",
                    s.cfg.message_timeout.as_secs_f64()
                )
            });
            self.close(CloseCode::Policy, "message too slow");
            return true;
        }
        if self.waiting_since.elapsed() >= s.cfg.idle_timeout {
            s.stats.idle_closed.fetch_add(1, Ordering::Relaxed);
            tracing::info!(
                "serve: {peer}: no request for {:.0} s: closed",
                s.cfg.idle_timeout.as_secs_f64()
            );
            self.close(CloseCode::Away, "idle");
            return true;
        }
        if s.stop.load(Ordering::Relaxed) {
            self.close(CloseCode::Away, "server stopping");
            return true;
        }
        false
    }

    fn close(&mut self, code: CloseCode, reason: &'static str) {
        let _ = self.ws.close(Some(CloseFrame {
            code,
            reason: reason.into(),
        }));
        let _ = self.ws.flush();
    }

    /// The next message: a request's bytes, or why there is none now. A message larger than
    /// the limit, or a text frame, is answered as a failure.
    fn read_request(&mut self) -> Next {
        let peer = self.peer;
        let msg = match self.ws.read() {
            Ok(m) => {
                self.mark = self.ws.get_ref().bytes;
                self.begun = None;
                m
            }
            Err(tungstenite::Error::Io(e))
                if matches!(
                    e.kind(),
                    std::io::ErrorKind::WouldBlock | std::io::ErrorKind::TimedOut
                ) =>
            {
                return Next::Again
            }
            Err(tungstenite::Error::Capacity(e)) => {
                let text = format!(
                    "the message is larger than the server's limit of {} bytes ({e})",
                    self.s.cfg.max_message_bytes
                );
                self.fail(Failure::TooLarge, &text);
                return Next::End;
            }
            Err(_) => {
                tracing::info!("serve: {peer} disconnected");
                return Next::End;
            }
        };
        match msg {
            Message::Binary(b) => Next::Request(b),
            Message::Text(_) => {
                self.fail(Failure::Text, "expected a binary msgpack frame, got text");
                Next::End
            }
            Message::Close(_) => {
                tracing::info!("serve: {peer} closed the connection");
                Next::End
            }
            _ => Next::Again,
        }
    }

    /// Answers one request: decoded and parsed here, its chunk asked of the policy thread,
    /// the reply sent, the latency noted. False: the connection is done (the request failed
    /// and was answered so, or the reply could not be sent).
    fn answer(&mut self, bytes: &[u8]) -> bool {
        let start = self.waiting_since;
        self.s.asking(self.id, true);
        let Some(request) = self.parse(bytes) else {
            return false;
        };
        let Some((mut reply, infer)) = self.ask_policy(request) else {
            return false;
        };
        reply.server_infer_ms = Some(infer.as_secs_f64() * 1e3);
        reply.prev_total_ms = self.prev_total.map(|t| t.as_secs_f64() * 1e3);
        let mut w = crate::msgpack::Writer::new();
        reply.write(&mut w);
        // counted before it is sent: a client that has its reply finds it counted
        self.s.stats.replies.fetch_add(1, Ordering::Relaxed);
        if self.ws.send(Message::Binary(w.buf.into())).is_err() {
            return false;
        }
        self.answered(start, infer);
        true
    }

    /// The request in `bytes`; None: it is malformed or no observation (answered as a
    /// failure).
    fn parse(&mut self, bytes: &[u8]) -> Option<Request> {
        let value = match decode(bytes, self.s.cfg.limits) {
            Ok(v) => v,
            Err(e) => {
                self.fail(Failure::Decode, &format!("malformed msgpack-numpy: {e}"));
                return None;
            }
        };
        match (self.s.parse)(&value) {
            Ok(r) => Some(r),
            Err(e) => {
                self.fail(Failure::Request, &format!("bad observation: {e}"));
                None
            }
        }
    }

    /// The policy thread's reply to `request` and its inference time; None: the policy failed
    /// or has stopped (answered as a failure).
    fn ask_policy(&mut self, request: Request) -> Option<(Reply, Duration)> {
        let (answer_tx, answer_rx) = mpsc::sync_channel(1);
        let queued = self
            .s
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
        match answer {
            Some((Ok(r), t)) => Some((r, t)),
            Some((Err(e), _)) => {
                self.fail(Failure::Policy, &format!("policy error: {e}"));
                None
            }
            None => {
                self.fail(Failure::Policy, "the policy thread has stopped");
                None
            }
        }
    }

    /// A reply sent: its latency noted (for the next reply and the stats), the connection
    /// waiting again.
    fn answered(&mut self, start: Instant, infer: Duration) {
        let total = start.elapsed();
        self.prev_total = Some(total);
        self.waiting_since = Instant::now();
        self.s.asking(self.id, false);
        if let Ok(mut l) = self.s.stats.latency_us.lock() {
            if l.len() < 1 << 20 {
                l.push((total.as_micros() as u64, infer.as_micros() as u64));
            }
        }
    }

    fn fail(&mut self, kind: Failure, text: &str) {
        fail(&mut self.ws, self.peer, self.s, kind, text);
    }
}

/// Answers a failed request as openpi's server does (the error as a text frame, then a close
/// with 1011), counts it and logs it (rate-limited). Other connections go on.
fn fail(ws: &mut WebSocket<Counted>, peer: SocketAddr, s: &Shared, kind: Failure, text: &str) {
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

    /// A new connection from `ip` in its handshake: its id and its drop flag. When
    /// `max_handshakes` are pending (or its network holds half of them) the oldest such makes
    /// way; None when the table cannot be had.
    fn begin_handshake(&self, ip: std::net::IpAddr) -> Option<(u64, Arc<AtomicBool>)> {
        let mut t = self.table.lock().ok()?;
        let net = Network::of(ip);
        let most = self.cfg.max_handshakes.max(1);
        let pending = |t: &Table, f: &dyn Fn(&Slot) -> bool| {
            t.slots
                .iter()
                .filter(|c| !c.open && !c.head && f(c))
                .count()
        };
        let oldest = |t: &Table, f: &dyn Fn(&Slot) -> bool| {
            t.slots
                .iter()
                .enumerate()
                .filter(|(_, c)| !c.open && !c.head && f(c))
                .min_by_key(|(_, c)| c.since)
                .map(|(i, _)| i)
        };
        let mine = |c: &Slot| c.net == net;
        let any = |_: &Slot| true;
        let victim = if pending(&t, &mine) >= (most / 2).max(1) {
            oldest(&t, &mine)
        } else if pending(&t, &any) >= most {
            oldest(&t, &any)
        } else {
            None
        };
        if let Some(i) = victim {
            t.evict(i);
            self.stats.made_way.fetch_add(1, Ordering::Relaxed);
        }
        t.next += 1;
        let id = t.next;
        let drop_it = Arc::new(AtomicBool::new(false));
        t.slots.push(Slot {
            id,
            ip,
            net,
            open: false,
            since: Instant::now(),
            busy: false,
            asked: false,
            head: false,
            drop_it: drop_it.clone(),
        });
        Some((id, drop_it))
    }

    /// Connection `id`'s handshake is done: it takes a websocket slot, the longest-idle
    /// websocket of its address, of its network or of all making way where that share is full.
    /// Err: the line to refuse it with (every holder of that share is answering or asked
    /// within the last second).
    fn open(&self, id: u64) -> Result<(), String> {
        let mut t = self
            .table
            .lock()
            .map_err(|_| "the server is stopping".to_string())?;
        let Some(me) = t.slots.iter().position(|c| c.id == id) else {
            return Err("made way for a newer connection".into());
        };
        let (ip, net) = (t.slots[me].ip, t.slots[me].net);
        let count = |t: &Table, f: &dyn Fn(&Slot) -> bool| {
            t.slots.iter().filter(|c| c.open && f(c)).count()
        };
        let shares: [(&str, usize, &SlotFilter); 3] = [
            (
                "this address",
                self.cfg.max_per_address.max(1),
                &|c: &Slot| c.ip == ip,
            ),
            (
                "this network",
                self.cfg.max_per_network.max(1),
                &|c: &Slot| c.net == net,
            ),
            ("all", self.cfg.max_connections.max(1), &|_: &Slot| true),
        ];
        for (what, most, f) in shares {
            while count(&t, f) >= most {
                match t.idlest(f) {
                    Some(i) => {
                        t.evict(i);
                        self.stats.made_way.fetch_add(1, Ordering::Relaxed);
                    }
                    None => {
                        return Err(format!("the connections of {what} ({most}) are all in use"))
                    }
                }
            }
        }
        if let Some(c) = t.slots.iter_mut().find(|c| c.id == id) {
            c.open = true;
            c.since = Instant::now();
        }
        self.stats.open.store(t.open_count(), Ordering::Relaxed);
        Ok(())
    }

    /// Connection `id` has sent its whole request head.
    fn head_done(&self, id: u64) {
        if let Ok(mut t) = self.table.lock() {
            if let Some(c) = t.slots.iter_mut().find(|c| c.id == id) {
                c.head = true;
            }
        }
    }

    /// Connection `id` is answering a request (`busy`), or has answered one.
    fn asking(&self, id: u64, busy: bool) {
        if let Ok(mut t) = self.table.lock() {
            if let Some(c) = t.slots.iter_mut().find(|c| c.id == id) {
                c.busy = busy;
                c.asked = true;
                c.since = Instant::now();
            }
        }
    }

    /// Connection `id` has gone.
    fn release(&self, id: u64) {
        if let Ok(mut t) = self.table.lock() {
            if let Some(i) = t.slots.iter().position(|c| c.id == id) {
                t.slots.swap_remove(i);
            }
            self.stats.open.store(t.open_count(), Ordering::Relaxed);
        }
    }
}

/// A TCP stream that notes when bytes last arrived and how many (a message in progress).
struct Counted {
    stream: TcpStream,
    bytes: u64,
}

impl Read for Counted {
    fn read(&mut self, buf: &mut [u8]) -> std::io::Result<usize> {
        let n = self.stream.read(buf)?;
        self.bytes += n as u64;
        Ok(n)
    }
}

impl Write for Counted {
    fn write(&mut self, buf: &[u8]) -> std::io::Result<usize> {
        self.stream.write(buf)
    }
    fn flush(&mut self) -> std::io::Result<()> {
        self.stream.flush()
    }
}
