//! The server and the client of this crate against each other on loopback: metadata, a reply
//! per request, the api key, `/healthz`, and a bad message answered on its own connection while
//! another client goes on.

use std::io::{Read, Write};
use std::net::{SocketAddr, TcpStream};
use std::sync::Arc;
use std::time::Duration;

use chunkrt_openpi::*;

fn layout() -> Layout {
    Layout::preset(Preset::Libero)
}

fn start(api_key: Option<&str>) -> Server {
    let names = vec!["base_0_rgb".to_string()];
    let meta = ChunkrtMetadata {
        version: "test".into(),
        model: "pi05".into(),
        action_horizon: 4,
        action_dim: 32,
        image_inputs: names.clone(),
        conditioning: vec!["guided".into()],
        rtc_prefix_max: 0,
        layout: "libero".into(),
        delayed_views: vec![],
        reset_pose: Some(vec![0.0, -1.5, 1.5, 0.0, 0.0, 0.0]),
    };
    let mut w = Writer::new();
    meta.write(&mut w);
    let l = layout();
    Server::start(
        ServerConfig {
            addr: "127.0.0.1:0".parse().unwrap(),
            api_key: api_key.map(str::to_string),
            max_message_bytes: 1 << 20,
            max_connections: 8,
            limits: Limits::default(),
            ..ServerConfig::new("127.0.0.1:0".parse().unwrap(), 1 << 20)
        },
        w.buf,
        Box::new(move |v: &Value<'_>| Request::parse(v, &l, &names)),
        // the "policy": every action row is the state plus the row index
        Box::new(|r: &Request| {
            let n = r.state.len();
            let actions = (0..4)
                .flat_map(|k| r.state.iter().map(move |s| s + k as f64))
                .collect();
            Ok(Reply {
                actions,
                horizon: 4,
                dims: n,
                policy_infer_ms: Some(0.5),
                server_infer_ms: None,
                prev_total_ms: None,
            })
        }),
        Box::new(|_, _| {}),
    )
    .unwrap()
}

fn request(state: &[f64]) -> Vec<u8> {
    let px = vec![9u8; 4 * 4 * 3];
    let imgs = [ImageRef {
        name: "base_0_rgb",
        width: 4,
        height: 4,
        channels: 3,
        data: &px,
    }];
    let mut w = Writer::new();
    Outgoing {
        images: &imgs,
        state,
        state_split: &[],
        prompt: "go",
        guidance: None,
        committed: None,
        delay_steps: None,
        reseed: None,
    }
    .write(&layout(), &mut w)
    .unwrap();
    w.buf
}

fn url(addr: SocketAddr) -> String {
    format!("ws://{addr}")
}

fn http_get(addr: SocketAddr, path: &str) -> String {
    let mut s = TcpStream::connect(addr).unwrap();
    s.set_read_timeout(Some(Duration::from_secs(5))).unwrap();
    write!(s, "GET {path} HTTP/1.1\r\nHost: x\r\n\r\n").unwrap();
    let mut out = String::new();
    let _ = s.read_to_string(&mut out);
    out
}

#[test]
fn metadata_replies_and_timings() {
    let server = start(None);
    let mut c = Client::connect(&ClientConfig::new(&url(server.local_addr()))).unwrap();
    let meta = ChunkrtMetadata::parse(&c.metadata()).unwrap();
    assert_eq!((meta.action_horizon, meta.layout.as_str()), (4, "libero"));
    // openpi's policy_metadata key, top level as openpi's server sends it
    assert_eq!(meta.reset_pose, Some(vec![0.0, -1.5, 1.5, 0.0, 0.0, 0.0]));
    for i in 0..3 {
        let bytes = c.infer(&request(&[1.0, 2.0])).unwrap();
        let r = Reply::parse(&decode(&bytes, Limits::default()).unwrap()).unwrap();
        assert_eq!((r.horizon, r.dims), (4, 2));
        assert_eq!(r.actions[6..], [4.0, 5.0]);
        assert_eq!(r.policy_infer_ms, Some(0.5));
        assert!(r.server_infer_ms.is_some());
        // openpi sends prev_total_ms from the second reply of a connection on
        assert_eq!(r.prev_total_ms.is_some(), i > 0);
    }
    assert_eq!(
        server
            .stats()
            .replies
            .load(std::sync::atomic::Ordering::Relaxed),
        3
    );
    assert!(http_get(server.local_addr(), "/healthz").ends_with("\r\n\r\nOK\n"));
}

#[test]
fn api_key_is_required_before_any_work() {
    let server = start(Some("s3cret"));
    let mut cfg = ClientConfig::new(&url(server.local_addr()));
    assert!(matches!(
        Client::connect(&cfg),
        Err(ClientError::Handshake(..))
    ));
    cfg.api_key = Some("wrong".into());
    assert!(Client::connect(&cfg).is_err());
    cfg.api_key = Some("s3cret".into());
    let mut c = Client::connect(&cfg).unwrap();
    assert!(c.infer(&request(&[0.0])).is_ok());
    assert_eq!(
        server
            .stats()
            .unauthorized
            .load(std::sync::atomic::Ordering::Relaxed),
        2
    );
}

#[test]
fn a_bad_message_closes_only_its_own_connection() {
    let server = Arc::new(start(None));
    let u = url(server.local_addr());
    let mut good = Client::connect(&ClientConfig::new(&u)).unwrap();
    let bad_inputs: Vec<(Vec<u8>, &str)> = vec![
        (vec![0xc1, 0x00], "malformed msgpack-numpy"),
        (vec![0x80], "missing key"),
        (request(&[f64::NAN]), "not finite"),
        (vec![0u8; 2 << 20], "larger than"),
    ];
    for (msg, want) in bad_inputs {
        let mut bad = Client::connect(&ClientConfig::new(&u)).unwrap();
        match bad.infer(&msg) {
            Err(ClientError::Server(text)) => assert!(text.contains(want), "{text}"),
            other => panic!("expected an error text containing {want:?}, got {other:?}"),
        }
        // the connection is closed after the error (openpi's 1011)
        assert!(bad.infer(&request(&[0.0])).is_err());
        assert!(good.infer(&request(&[3.0])).is_ok());
    }
    assert_eq!(server.stats().failures(Failure::Decode), 1);
    assert_eq!(server.stats().failures(Failure::Request), 2);
    assert_eq!(server.stats().failures(Failure::TooLarge), 1);
}
