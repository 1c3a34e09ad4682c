//! Rust fallback of the websocket baseline ([`super::ws_baseline`]) for machines without Python /
//! openpi-client: a websocket server and client over loopback (`tungstenite`) that exchange the
//! same messages as `tools/python/openpi_baseline/`, packed the way openpi-client's
//! `msgpack_numpy` packs them (`rmp` to pack, `rmpv` to unpack).
//!
//! Wire format (byte for byte what `msgpack_numpy.Packer().pack(obs)` produces, see the tests):
//!
//! ```text
//! observation  {"observation/state" | "observation/image_<i>": ndarray, ..., "seq": int}
//! ndarray      {b"__ndarray__": True, b"data": <raw bytes>, b"dtype": "<f8" | "|u1", b"shape": [..]}
//! reply        {"seq": int, "t_recv_ns": int, "bytes": int}
//! metadata     {"server": "chunkrt-openpi-baseline"}   (server → client right after connecting)
//! ```
//!
//! Like `server.py`, the server decodes every message into msgpack values (copying the array
//! bytes out of the frame, as Python's `unpackb` does), rebuilds the arrays (dtype, shape, size
//! checked), takes CLOCK_MONOTONIC, and replies; the client measures one way (send start → server
//! finished unpacking) and round trip exactly like `client.py`, with its warm-up and gap. The
//! server runs on a thread of the bench process rather than in a second process.

use std::net::{SocketAddr, TcpListener, TcpStream};
use std::thread::JoinHandle;
use std::time::{Duration, Instant};

use chunkrt_ipc::monotonic_ns;
use rand::{Rng, SeedableRng};
use rmpv::Value;
use tungstenite::{Message, WebSocket};

use super::ws::{Baseline, Case, CaseResult};
use super::BenchError;
use crate::report::latency_histogram;

/// What `server.py` sends on connect.
pub const SERVER_NAME: &str = "chunkrt-openpi-baseline";

/// Joint-state observation length (`client.py`: 48 float64).
pub const STATE_DIM: usize = 48;

/// One numpy array as openpi's `msgpack_numpy` carries it.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct NdArray {
    /// Raw bytes (`ndarray.tobytes()`).
    pub data: Vec<u8>,
    /// numpy dtype string (`dtype.str`), e.g. `<f8`, `|u1`.
    pub dtype: String,
    /// Shape.
    pub shape: Vec<usize>,
}

impl NdArray {
    /// `ndarray.nbytes`.
    pub fn nbytes(&self) -> usize {
        self.data.len()
    }
}

/// An unpacked observation: its arrays by key, and `seq`.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Observation {
    /// `(key, array)` in message order.
    pub arrays: Vec<(String, NdArray)>,
    /// The client's sequence number.
    pub seq: u64,
}

/// Item size of a numpy dtype string (`<f8` → 8, `|u1` → 1); None for kinds openpi does not
/// pack (object, void, complex) or malformed strings.
pub fn itemsize(dtype: &str) -> Option<usize> {
    let rest = dtype.strip_prefix(['<', '>', '|', '=']).unwrap_or(dtype);
    let mut chars = rest.chars();
    let kind = chars.next()?;
    if !"biuf".contains(kind) {
        return None;
    }
    chars.as_str().parse().ok().filter(|n| *n > 0)
}

fn pack_ndarray(buf: &mut Vec<u8>, a: &NdArray) -> std::io::Result<()> {
    use rmp::encode;
    encode::write_map_len(buf, 4)?;
    encode::write_bin(buf, b"__ndarray__")?;
    encode::write_bool(buf, true)?;
    encode::write_bin(buf, b"data")?;
    encode::write_bin(buf, &a.data)?;
    encode::write_bin(buf, b"dtype")?;
    encode::write_str(buf, &a.dtype)?;
    encode::write_bin(buf, b"shape")?;
    encode::write_array_len(buf, a.shape.len() as u32)?;
    for d in &a.shape {
        encode::write_uint(buf, *d as u64)?;
    }
    Ok(())
}

/// Packs `{key: ndarray, ..., "seq": seq}` like `msgpack_numpy.Packer().pack(obs)`.
pub fn pack_observation(
    buf: &mut Vec<u8>,
    arrays: &[(String, NdArray)],
    seq: u64,
) -> std::io::Result<()> {
    use rmp::encode;
    encode::write_map_len(buf, arrays.len() as u32 + 1)?;
    for (key, a) in arrays {
        encode::write_str(buf, key)?;
        pack_ndarray(buf, a)?;
    }
    encode::write_str(buf, "seq")?;
    encode::write_uint(buf, seq)?;
    Ok(())
}

/// Packs the server's reply `{"seq", "t_recv_ns", "bytes"}` (as `server.py` does).
pub fn pack_reply(buf: &mut Vec<u8>, seq: u64, t_recv_ns: u64, bytes: u64) -> std::io::Result<()> {
    use rmp::encode;
    encode::write_map_len(buf, 3)?;
    encode::write_str(buf, "seq")?;
    encode::write_uint(buf, seq)?;
    encode::write_str(buf, "t_recv_ns")?;
    encode::write_uint(buf, t_recv_ns)?;
    encode::write_str(buf, "bytes")?;
    encode::write_uint(buf, bytes)?;
    Ok(())
}

/// Packs the metadata the server sends on connect.
pub fn pack_metadata(buf: &mut Vec<u8>) -> std::io::Result<()> {
    use rmp::encode;
    encode::write_map_len(buf, 1)?;
    encode::write_str(buf, "server")?;
    encode::write_str(buf, SERVER_NAME)?;
    Ok(())
}

fn decode(msg: &[u8]) -> Result<Vec<(Value, Value)>, String> {
    let mut rd = msg;
    match rmpv::decode::read_value(&mut rd).map_err(|e| format!("msgpack: {e}"))? {
        Value::Map(m) if rd.is_empty() => Ok(m),
        Value::Map(_) => Err(format!("{} trailing bytes after the message", rd.len())),
        other => Err(format!("expected a map, got {other}")),
    }
}

fn is_ndarray(m: &[(Value, Value)]) -> bool {
    m.iter()
        .any(|(k, _)| k.as_slice() == Some(b"__ndarray__".as_slice()))
}

/// `msgpack_numpy.unpack_array` for a map tagged `__ndarray__`: takes the bytes over (numpy
/// wraps the unpacked `bytes` object the same way) and checks them against dtype and shape.
fn ndarray_from_map(m: Vec<(Value, Value)>) -> Result<NdArray, String> {
    let (mut data, mut dtype, mut shape) = (None, None, None);
    for (k, v) in m {
        match (k.as_slice(), v) {
            (Some(b"data"), Value::Binary(b)) => data = Some(b),
            (Some(b"dtype"), Value::String(s)) => dtype = s.into_str(),
            (Some(b"shape"), Value::Array(dims)) => {
                shape = dims
                    .iter()
                    .map(|d| d.as_u64().map(|d| d as usize))
                    .collect::<Option<Vec<_>>>()
            }
            _ => {}
        }
    }
    let data = data.ok_or("ndarray without binary 'data'")?;
    let dtype = dtype.ok_or("ndarray without string 'dtype'")?;
    let shape = shape.ok_or("ndarray without integer 'shape'")?;
    let size = itemsize(&dtype).ok_or_else(|| format!("unsupported dtype '{dtype}'"))?;
    let want = shape.iter().product::<usize>() * size;
    if data.len() != want {
        return Err(format!(
            "ndarray of shape {shape:?} and dtype {dtype} needs {want} bytes, got {}",
            data.len()
        ));
    }
    Ok(NdArray { data, dtype, shape })
}

/// `msgpack_numpy.unpackb(msg)` of an observation: every `__ndarray__` map becomes an array.
pub fn unpack_observation(msg: &[u8]) -> Result<Observation, String> {
    let mut arrays = Vec::new();
    let mut seq = None;
    for (k, v) in decode(msg)? {
        let key = match k {
            Value::String(s) => s.into_str().ok_or("non-UTF-8 key")?,
            other => return Err(format!("non-string key {other}")),
        };
        match v {
            Value::Map(m) if is_ndarray(&m) => arrays.push((key, ndarray_from_map(m)?)),
            v if key == "seq" => seq = Some(v.as_u64().ok_or("'seq' is not an integer")?),
            _ => {}
        }
    }
    Ok(Observation {
        arrays,
        seq: seq.ok_or("observation without 'seq'")?,
    })
}

fn field(m: &[(Value, Value)], key: &str) -> Option<u64> {
    m.iter()
        .find(|(k, _)| k.as_str() == Some(key))
        .and_then(|(_, v)| v.as_u64())
}

/// Unpacks the server's reply into `(seq, t_recv_ns)`.
pub fn unpack_reply(msg: &[u8]) -> Result<(u64, u64), String> {
    let m = decode(msg)?;
    match (field(&m, "seq"), field(&m, "t_recv_ns")) {
        (Some(seq), Some(t)) => Ok((seq, t)),
        _ => Err("reply without integer 'seq' and 't_recv_ns'".into()),
    }
}

/// The observation `client.py` sends for `case`: 48 float64 for joint state, else one
/// `height × width × 3` uint8 image per camera (random content, fixed seed).
pub fn observation(case: &Case, rng: &mut impl Rng) -> Vec<(String, NdArray)> {
    if case.cameras == 0 {
        let data = (0..STATE_DIM)
            .flat_map(|_| (rng.gen::<f64>() * 2.0 - 1.0).to_le_bytes())
            .collect();
        return vec![(
            "observation/state".into(),
            NdArray {
                data,
                dtype: "<f8".into(),
                shape: vec![STATE_DIM],
            },
        )];
    }
    (0..case.cameras)
        .map(|i| {
            let (h, w) = (case.height as usize, case.width as usize);
            let mut data = vec![0u8; h * w * 3];
            rng.fill(&mut data[..]);
            (
                format!("observation/image_{i}"),
                NdArray {
                    data,
                    dtype: "|u1".into(),
                    shape: vec![h, w, 3],
                },
            )
        })
        .collect()
}

fn ws_err(what: &str) -> impl Fn(tungstenite::Error) -> String + '_ {
    move |e| format!("{what}: {e}")
}

/// Next binary message, None once the peer closed (control frames are answered by tungstenite
/// and skipped). The payload is `msg.into_data()`, without another copy.
fn read_binary(ws: &mut WebSocket<TcpStream>, what: &str) -> Result<Option<Message>, String> {
    loop {
        match ws.read() {
            Ok(m @ Message::Binary(_)) => return Ok(Some(m)),
            Ok(Message::Text(t)) => return Err(format!("{what}: text message '{t}'")),
            // Ping / pong / close: tungstenite answers them; the next read reports the close.
            Ok(_) => {}
            Err(tungstenite::Error::ConnectionClosed) => return Ok(None),
            Err(e) => return Err(ws_err(what)(e)),
        }
    }
}

fn send_binary(ws: &mut WebSocket<TcpStream>, buf: Vec<u8>, what: &str) -> Result<(), String> {
    ws.send(Message::binary(buf)).map_err(ws_err(what))
}

/// The server: one connection (the client keeps one for all cases, like `client.py`); metadata,
/// then unpack every observation and reply with the time right after unpacking. Returns the
/// number of observations answered.
fn serve(listener: TcpListener, io_timeout: Duration) -> Result<u64, String> {
    let (stream, _) = listener.accept().map_err(|e| format!("accept: {e}"))?;
    stream
        .set_nodelay(true)
        .and_then(|_| stream.set_read_timeout(Some(io_timeout)))
        .map_err(|e| format!("socket options: {e}"))?;
    let mut ws = tungstenite::accept(stream).map_err(|e| format!("handshake: {e}"))?;
    let mut meta = Vec::new();
    pack_metadata(&mut meta).map_err(|e| e.to_string())?;
    send_binary(&mut ws, meta, "send metadata")?;
    let mut answered = 0u64;
    while let Some(msg) = read_binary(&mut ws, "server receive")? {
        let obs = unpack_observation(&msg.into_data())?;
        let t_recv = monotonic_ns();
        let bytes: usize = obs.arrays.iter().map(|(_, a)| a.nbytes()).sum();
        let mut reply = Vec::with_capacity(32);
        pack_reply(&mut reply, obs.seq, t_recv, bytes as u64).map_err(|e| e.to_string())?;
        send_binary(&mut ws, reply, "server send")?;
        answered += 1;
    }
    Ok(answered)
}

/// Joins the server thread; unblocks its `accept` first when the client never connected.
struct Server {
    addr: SocketAddr,
    handle: Option<JoinHandle<Result<u64, String>>>,
    connected: bool,
}

impl Server {
    fn join(&mut self) -> Result<u64, String> {
        let Some(handle) = self.handle.take() else {
            return Ok(0);
        };
        if !self.connected {
            let _ = TcpStream::connect(self.addr);
        }
        handle
            .join()
            .unwrap_or_else(|_| Err("server thread panicked".into()))
    }
}

impl Drop for Server {
    fn drop(&mut self) {
        let _ = self.join();
    }
}

fn client(
    server: &mut Server,
    cases: &[Case],
    iters: usize,
    warmup: usize,
    gap: Duration,
    timeout: Duration,
    io_timeout: Duration,
) -> Result<Vec<CaseResult>, BenchError> {
    let err = |reason: String| BenchError::Process {
        what: "websocket baseline (Rust client)".into(),
        reason,
    };
    let stream = TcpStream::connect(server.addr).map_err(|e| err(format!("connect: {e}")))?;
    server.connected = true;
    stream
        .set_nodelay(true)
        .and_then(|_| stream.set_read_timeout(Some(io_timeout)))
        .map_err(|e| err(format!("socket options: {e}")))?;
    let (mut ws, _) = tungstenite::client(format!("ws://{}", server.addr), stream)
        .map_err(|e| err(format!("handshake: {e}")))?;
    let meta = read_binary(&mut ws, "metadata")
        .map_err(err)?
        .ok_or_else(|| err("server closed before its metadata".into()))?;
    decode(&meta.into_data()).map_err(|e| err(format!("metadata: {e}")))?;

    let started = Instant::now();
    let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(0);
    let mut out = Vec::with_capacity(cases.len());
    for case in cases {
        let arrays = observation(case, &mut rng);
        let payload: usize = arrays.iter().map(|(_, a)| a.nbytes()).sum();
        let mut one_way = latency_histogram();
        let mut rtt = latency_histogram();
        for i in 0..(warmup + iters) as u64 {
            if started.elapsed() > timeout {
                return Err(BenchError::Timeout(format!(
                    "Rust websocket baseline still running after {timeout:?}"
                )));
            }
            let t0 = monotonic_ns();
            let mut buf = Vec::with_capacity(payload + 256);
            pack_observation(&mut buf, &arrays, i).map_err(|e| err(e.to_string()))?;
            send_binary(&mut ws, buf, "client send").map_err(err)?;
            let reply = read_binary(&mut ws, "client receive")
                .map_err(err)?
                .ok_or_else(|| err("server closed the connection".into()))?;
            let (seq, t_recv) = unpack_reply(&reply.into_data()).map_err(err)?;
            let t1 = monotonic_ns();
            if seq != i {
                return Err(err(format!("reply for seq {seq}, expected {i}")));
            }
            if i >= warmup as u64 {
                one_way.saturating_record(t_recv.saturating_sub(t0));
                rtt.saturating_record(t1.saturating_sub(t0));
            }
            std::thread::sleep(gap);
        }
        out.push(CaseResult {
            name: case.name.clone(),
            one_way,
            rtt,
        });
    }
    // Close handshake, so the server sees a clean end.
    let _ = ws.close(None);
    while ws.read().is_ok() {}
    Ok(out)
}

/// `transport` of a run of the Rust pair, naming the fallback and why it was used.
pub fn transport(reason: &str) -> String {
    format!("websocket + msgpack-numpy (Rust tungstenite + rmp fallback: {reason})")
}

/// What the Rust pair stands in for (`Baseline::substitution`).
pub const SUBSTITUTION: &str = "openpi-client (Python) not used: its msgpack_numpy wire format \
     over a websocket reproduced by a Rust tungstenite + rmp client/server pair (server on a \
     thread of the bench process), so Python's own overhead is not in these figures";

/// Runs the baseline with the Rust pair: same cases, counts and gap as the Python client, one
/// connection for all cases. `reason` says why Python was not used (it goes into `transport`).
pub fn run(
    cases: &[Case],
    iters: usize,
    warmup: usize,
    gap: Duration,
    timeout: Duration,
    reason: &str,
) -> Result<Baseline, BenchError> {
    let proc_err = |reason: String| BenchError::Process {
        what: "websocket baseline (Rust server)".into(),
        reason,
    };
    let listener = TcpListener::bind("127.0.0.1:0").map_err(|e| proc_err(e.to_string()))?;
    let addr = listener.local_addr().map_err(|e| proc_err(e.to_string()))?;
    let io_timeout = timeout.clamp(Duration::from_secs(1), Duration::from_secs(10));
    let handle = std::thread::Builder::new()
        .name("ws-baseline-server".into())
        .spawn(move || serve(listener, io_timeout))
        .map_err(|e| BenchError::Thread(e.to_string()))?;
    let mut server = Server {
        addr,
        handle: Some(handle),
        connected: false,
    };
    let measured = client(&mut server, cases, iters, warmup, gap, timeout, io_timeout);
    let served = server.join();
    let cases = match (measured, served) {
        (Ok(c), _) => c,
        (Err(e), Err(s)) => return Err(proc_err(format!("{e} (server: {s})"))),
        (Err(e), Ok(_)) => return Err(e),
    };
    Ok(Baseline {
        transport: transport(reason),
        substitution: Some(SUBSTITUTION.to_string()),
        cases,
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    fn hex(b: &[u8]) -> String {
        b.iter().map(|x| format!("{x:02x}")).collect()
    }

    fn image(first: u8) -> NdArray {
        NdArray {
            data: (0..12u8).map(|i| (i + first) % 12).collect(),
            dtype: "|u1".into(),
            shape: vec![2, 2, 3],
        }
    }

    // Expected bytes from openpi-client 's `msgpack_numpy.Packer().pack(...)` (Python 3.11,
    // msgpack 1.x) of the same values.
    const PY_IMAGES: &str = "83b36f62736572766174696f6e2f696d6167655f3084c40b5f5f6e6461727261795f5fc3c40464617461c40c000102030405060708090a0bc4056474797065a37c7531c405736861706593020203b36f62736572766174696f6e2f696d6167655f3184c40b5f5f6e6461727261795f5fc3c40464617461c40c060708090a0b000102030405c4056474797065a37c7531c405736861706593020203a3736571cd012c";
    const PY_STATE: &str = "82b16f62736572766174696f6e2f737461746584c40b5f5f6e6461727261795f5fc3c40464617461c4180000000000000000000000000000e03f000000000000f03fc4056474797065a33c6638c40573686170659103a373657107";
    const PY_REPLY: &str = "83a373657107a9745f726563765f6e73cf0000001cbe991a14a5627974657318";
    const PY_META: &str = "81a6736572766572b76368756e6b72742d6f70656e70692d626173656c696e65";

    #[test]
    fn packs_like_openpi_msgpack_numpy() {
        let images = vec![
            ("observation/image_0".to_string(), image(0)),
            ("observation/image_1".to_string(), image(6)),
        ];
        let mut buf = Vec::new();
        pack_observation(&mut buf, &images, 300).expect("pack");
        assert_eq!(hex(&buf), PY_IMAGES);

        let state = vec![(
            "observation/state".to_string(),
            NdArray {
                data: [0.0f64, 0.5, 1.0]
                    .iter()
                    .flat_map(|x| x.to_le_bytes())
                    .collect(),
                dtype: "<f8".into(),
                shape: vec![3],
            },
        )];
        buf.clear();
        pack_observation(&mut buf, &state, 7).expect("pack");
        assert_eq!(hex(&buf), PY_STATE);

        buf.clear();
        pack_reply(&mut buf, 7, 123_456_789_012, 24).expect("pack");
        assert_eq!(hex(&buf), PY_REPLY);
        buf.clear();
        pack_metadata(&mut buf).expect("pack");
        assert_eq!(hex(&buf), PY_META);
    }

    #[test]
    fn unpacks_observations_and_replies() {
        let images = vec![
            ("observation/image_0".to_string(), image(0)),
            ("observation/image_1".to_string(), image(6)),
        ];
        let mut buf = Vec::new();
        pack_observation(&mut buf, &images, 300).expect("pack");
        let obs = unpack_observation(&buf).expect("valid observation");
        assert_eq!(obs.seq, 300);
        assert_eq!(obs.arrays, images);

        let mut reply = Vec::new();
        pack_reply(&mut reply, 7, 123_456_789_012, 24).expect("pack");
        assert_eq!(unpack_reply(&reply), Ok((7, 123_456_789_012)));

        // Size must match dtype × shape; truncated messages and non-maps are errors.
        let mut bad = image(0);
        bad.shape = vec![2, 2, 4];
        buf.clear();
        pack_observation(&mut buf, &[("x".into(), bad)], 1).expect("pack");
        assert!(unpack_observation(&buf).is_err());
        buf.clear();
        pack_observation(&mut buf, &images, 1).expect("pack");
        assert!(unpack_observation(&buf[..buf.len() - 3]).is_err());
        assert!(unpack_observation(&[0x07]).is_err());
        assert_eq!(itemsize("<f8"), Some(8));
        assert_eq!(itemsize("|u1"), Some(1));
        assert_eq!(itemsize("|O"), None);
    }

    #[test]
    fn observation_matches_client_py() {
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(0);
        let js = Case {
            name: "joint_state".into(),
            cameras: 0,
            width: 0,
            height: 0,
        };
        let o = observation(&js, &mut rng);
        assert_eq!(o.len(), 1);
        assert_eq!(o[0].1.shape, vec![48]);
        assert_eq!(o[0].1.nbytes(), 48 * 8);
        let cams = Case {
            name: "cam3_64x32".into(),
            cameras: 3,
            width: 64,
            height: 32,
        };
        let o = observation(&cams, &mut rng);
        assert_eq!(o.len(), 3);
        assert_eq!(o[2].0, "observation/image_2");
        assert_eq!(o[2].1.shape, vec![32, 64, 3]);
    }

    #[test]
    fn pair_measures_tiny_cases() {
        let cases = [
            Case {
                name: "joint_state".into(),
                cameras: 0,
                width: 0,
                height: 0,
            },
            Case {
                name: "cam2_16x8".into(),
                cameras: 2,
                width: 16,
                height: 8,
            },
        ];
        let b = run(
            &cases,
            25,
            3,
            Duration::from_micros(100),
            Duration::from_secs(30),
            "test",
        )
        .expect("Rust pair runs");
        assert!(b
            .transport
            .contains("Rust tungstenite + rmp fallback: test"));
        assert!(b.substitution.is_some());
        assert_eq!(b.cases.len(), 2);
        for c in &b.cases {
            assert_eq!(c.one_way.len(), 25, "{}", c.name);
            assert_eq!(c.rtt.len(), 25, "{}", c.name);
            assert!(c.one_way.value_at_quantile(0.5) <= c.rtt.value_at_quantile(0.5));
        }
    }
}
