//! A blocking client of an openpi-protocol policy server (openpi's `WebsocketClientPolicy` on
//! the wire): connect, read the metadata, then one request → one reply.
//!
//! Every wait is bounded: the TCP connect, the handshake and the metadata by
//! [`ClientConfig::connect_timeout`], each reply by [`ClientConfig::reply_timeout`]. A failure
//! leaves the client unusable (its connection may hold a late reply); the caller connects anew.

use std::net::{TcpStream, ToSocketAddrs};
use std::time::{Duration, Instant};

use tungstenite::client::IntoClientRequest;
use tungstenite::http::HeaderValue;
use tungstenite::protocol::WebSocketConfig;
use tungstenite::{Message, WebSocket};

use crate::msgpack::{decode, Limits, Value};

/// Where and how to connect.
#[derive(Debug, Clone)]
pub struct ClientConfig {
    /// `ws://host:port[/path]` (a path for servers that route by it: SGLang's `/openpi/policy`,
    /// vLLM-Omni's `/v1/realtime/robot/openpi`). `wss://` is not supported.
    pub url: String,
    /// Sent as `Authorization: Api-Key …`.
    pub api_key: Option<String>,
    /// TCP connect + handshake + metadata.
    pub connect_timeout: Duration,
    /// Request sent → reply read.
    pub reply_timeout: Duration,
    /// The largest reply or metadata message.
    pub max_message_bytes: usize,
    /// Decoding limits.
    pub limits: Limits,
}

impl ClientConfig {
    /// Defaults for `url`: 2 s to connect, 5 s per reply, 64 MiB messages.
    pub fn new(url: &str) -> Self {
        Self {
            url: url.to_string(),
            api_key: None,
            connect_timeout: Duration::from_secs(2),
            reply_timeout: Duration::from_secs(5),
            max_message_bytes: 64 << 20,
            limits: Limits::default(),
        }
    }
}

/// Why a call failed.
#[derive(Debug, thiserror::Error)]
pub enum ClientError {
    #[error("{0}: not a ws:// URL ({1})")]
    Url(String, String),
    #[error("cannot connect to {0}: {1}")]
    Connect(String, String),
    #[error("{0}: the websocket handshake failed: {1}")]
    Handshake(String, String),
    #[error("no reply within {0:?}")]
    Timeout(Duration),
    #[error("the server answered with an error: {0}")]
    Server(String),
    #[error("the connection failed: {0}")]
    Connection(String),
    #[error("the server's message is not msgpack-numpy: {0}")]
    Decode(String),
}

/// A connected client.
pub struct Client {
    ws: WebSocket<TcpStream>,
    metadata: Vec<u8>,
    cfg: ClientConfig,
}

fn would_block(e: &tungstenite::Error) -> bool {
    matches!(e, tungstenite::Error::Io(io) if matches!(
        io.kind(),
        std::io::ErrorKind::WouldBlock | std::io::ErrorKind::TimedOut
    ))
}

impl Client {
    /// Connects and reads the server's metadata.
    pub fn connect(cfg: &ClientConfig) -> Result<Client, ClientError> {
        let url = cfg.url.clone();
        let mut req = url
            .as_str()
            .into_client_request()
            .map_err(|e| ClientError::Url(url.clone(), e.to_string()))?;
        let uri = req.uri().clone();
        if uri.scheme_str() != Some("ws") {
            return Err(ClientError::Url(
                url,
                "only ws:// (no TLS: put the server behind an SSH tunnel or a VPN)".into(),
            ));
        }
        let host = uri
            .host()
            .ok_or_else(|| ClientError::Url(url.clone(), "no host".into()))?;
        let port = uri.port_u16().unwrap_or(80);
        if let Some(key) = &cfg.api_key {
            let v = HeaderValue::from_str(&format!("Api-Key {key}"))
                .map_err(|e| ClientError::Url(url.clone(), format!("api key: {e}")))?;
            req.headers_mut().insert("Authorization", v);
        }
        let deadline = Instant::now() + cfg.connect_timeout;
        let addrs: Vec<_> = (host.trim_start_matches('[').trim_end_matches(']'), port)
            .to_socket_addrs()
            .map_err(|e| ClientError::Connect(url.clone(), e.to_string()))?
            .collect();
        let mut last = String::from("the host resolves to no address");
        let mut stream = None;
        for a in addrs {
            let left = deadline.saturating_duration_since(Instant::now());
            if left.is_zero() {
                break;
            }
            match TcpStream::connect_timeout(&a, left) {
                Ok(s) => {
                    stream = Some(s);
                    break;
                }
                Err(e) => last = format!("{a}: {e}"),
            }
        }
        let stream = stream.ok_or_else(|| ClientError::Connect(url.clone(), last))?;
        let _ = stream.set_nodelay(true);
        let left = deadline
            .saturating_duration_since(Instant::now())
            .max(Duration::from_millis(1));
        let _ = stream.set_read_timeout(Some(left));
        let _ = stream.set_write_timeout(Some(left));
        let ws_cfg = WebSocketConfig::default()
            .max_message_size(Some(cfg.max_message_bytes))
            .max_frame_size(Some(cfg.max_message_bytes));
        let (ws, _) = tungstenite::client::client_with_config(req, stream, Some(ws_cfg))
            .map_err(|e| ClientError::Handshake(url.clone(), e.to_string()))?;
        let mut c = Client {
            ws,
            metadata: Vec::new(),
            cfg: cfg.clone(),
        };
        c.metadata = c.read_binary(deadline)?;
        // the metadata must be msgpack (an empty map for openpi's LIBERO / DROID servers)
        decode(&c.metadata, cfg.limits).map_err(|e| ClientError::Decode(e.to_string()))?;
        Ok(c)
    }

    /// The metadata's bytes (decode with [`Self::metadata`]).
    pub fn metadata_bytes(&self) -> &[u8] {
        &self.metadata
    }

    /// The metadata the server sent on connect.
    pub fn metadata(&self) -> Value<'_> {
        decode(&self.metadata, self.cfg.limits).unwrap_or(Value::Nil)
    }

    fn read_binary(&mut self, deadline: Instant) -> Result<Vec<u8>, ClientError> {
        loop {
            let left = deadline.saturating_duration_since(Instant::now());
            if left.is_zero() {
                return Err(ClientError::Timeout(self.cfg.reply_timeout));
            }
            let _ = self.ws.get_ref().set_read_timeout(Some(left));
            match self.ws.read() {
                Ok(Message::Binary(b)) => return Ok(b.to_vec()),
                Ok(Message::Text(t)) => return Err(ClientError::Server(t.to_string())),
                Ok(Message::Close(f)) => {
                    return Err(ClientError::Connection(format!(
                        "the server closed the connection{}",
                        f.map(|f| format!(" ({}: {})", f.code, f.reason))
                            .unwrap_or_default()
                    )))
                }
                Ok(_) => {}
                Err(e) if would_block(&e) => {}
                Err(e) => return Err(ClientError::Connection(e.to_string())),
            }
        }
    }

    /// Sends one request (a packed observation) and returns the reply's bytes. An error text
    /// from the server is [`ClientError::Server`].
    pub fn infer(&mut self, request: &[u8]) -> Result<Vec<u8>, ClientError> {
        let deadline = Instant::now() + self.cfg.reply_timeout;
        let _ = self
            .ws
            .get_ref()
            .set_write_timeout(Some(self.cfg.reply_timeout));
        self.ws
            .send(Message::Binary(request.to_vec().into()))
            .map_err(|e| ClientError::Connection(e.to_string()))?;
        self.read_binary(deadline)
    }

    /// Closes the connection politely (bounded by a short timeout).
    pub fn close(mut self) {
        let _ = self
            .ws
            .get_ref()
            .set_read_timeout(Some(Duration::from_millis(200)));
        let _ = self.ws.close(None);
        let _ = self.ws.flush();
    }
}
