//! The openpi message layer's unit tests (kept apart so that message.rs reads as the layer).
use super::*;
use crate::layout::Preset;
use crate::msgpack::{decode, Limits};

fn names(ns: &[&str]) -> Vec<String> {
    ns.iter().map(|s| s.to_string()).collect()
}

#[test]
fn a_request_round_trips_in_every_preset() {
    let rgb: Vec<u8> = (0..2 * 3 * 3).map(|i| i as u8).collect();
    let imgs = [
        ImageRef {
            name: "base_0_rgb",
            width: 3,
            height: 2,
            channels: 3,
            data: &rgb,
        },
        ImageRef {
            name: "left_wrist_0_rgb",
            width: 3,
            height: 2,
            channels: 3,
            data: &rgb,
        },
    ];
    let actions = [0.5; 6];
    let weights = [1.0f32, 0.5, 0.0];
    for preset in Preset::ALL {
        let layout = Layout::preset(preset);
        let split: &[usize] = if preset == Preset::Droid {
            &[1, 1]
        } else {
            &[]
        };
        let out = Outgoing {
            images: &imgs,
            state: &[0.25, -1.0],
            state_split: split,
            prompt: "pick up the fork",
            guidance: Some((&actions, &weights, 10.0, "vjp")),
            committed: None,
            delay_steps: Some(3),
            reseed: Some(7),
        };
        let mut w = Writer::new();
        out.write(&layout, &mut w).unwrap();
        let v = decode(&w.buf, Limits::default()).unwrap();
        let r = Request::parse(&v, &layout, &names(&["base_0_rgb", "left_wrist_0_rgb"])).unwrap();
        assert_eq!(r.images.len(), 2, "{preset:?}");
        assert_eq!(r.images[0].data, rgb, "{preset:?}: CHW and back");
        assert_eq!((r.images[0].width, r.images[0].height), (3, 2));
        assert_eq!(r.state, vec![0.25, -1.0]);
        assert_eq!(r.prompt.as_deref(), Some("pick up the fork"));
        let g = r.guidance.unwrap();
        assert_eq!((g.rows, g.beta, g.jacobian.as_str()), (3, 10.0, "vjp"));
        assert_eq!(g.weights, vec![1.0, 0.5, 0.0]);
        assert_eq!((r.delay_steps, r.reseed), (Some(3), Some(7)));
    }
}

#[test]
fn bad_requests_say_what_is_wrong() {
    let layout = Layout::preset(Preset::Libero);
    let cams = names(&["base_0_rgb"]);
    let parse = |w: &Writer| {
        let v = decode(&w.buf, Limits::default()).unwrap();
        Request::parse(&v, &layout, &cams)
            .map(|_| ())
            .unwrap_err()
            .0
    };
    let mut w = Writer::new();
    w.map(1).str("prompt").str("x");
    assert!(
        parse(&w).contains("missing key \"observation/image\""),
        "{}",
        parse(&w)
    );
    let mut w = Writer::new();
    w.map(2)
        .str("observation/image")
        .u8_array(&[2, 2, 3], &[0; 12])
        .str("observation/state")
        .f64_array(&[2], &[1.0, f64::NAN]);
    assert!(parse(&w).contains("not finite"), "{}", parse(&w));
    let mut w = Writer::new();
    w.map(2)
        .str("observation/image")
        .ndarray_with(DType::I32, &[2, 2], |b| b.extend_from_slice(&[0; 16]))
        .str("observation/state")
        .f64_array(&[1], &[1.0]);
    assert!(parse(&w).contains("expected uint8"), "{}", parse(&w));
    let mut w = Writer::new();
    w.map(2)
        .str("observation/image")
        .u8_array(&[2, 2, 4], &[0; 16])
        .str("observation/state")
        .f64_array(&[1], &[1.0]);
    assert!(parse(&w).contains("expected [H, W, 3]"), "{}", parse(&w));
    let mut w = Writer::new();
    w.list(0);
    assert!(parse(&w).contains("expected a map"));
}

#[test]
fn replies_from_each_kind_of_server() {
    let r = Reply {
        actions: vec![1.0, 2.0, 3.0, 4.0],
        horizon: 2,
        dims: 2,
        policy_infer_ms: Some(1.5),
        server_infer_ms: Some(2.0),
        prev_total_ms: None,
    };
    let mut w = Writer::new();
    r.write(&mut w);
    assert_eq!(
        Reply::parse(&decode(&w.buf, Limits::default()).unwrap()),
        Ok(r)
    );
    // vLLM-Omni: a bare float32 array
    let mut w = Writer::new();
    w.f32_array(&[1, 2], &[0.5, 0.25]);
    let bare = Reply::parse(&decode(&w.buf, Limits::default()).unwrap()).unwrap();
    assert_eq!((bare.horizon, bare.dims, bare.actions[1]), (1, 2, 0.25));
    // vLLM-Omni's error message
    let mut w = Writer::new();
    w.map(2)
        .str("type")
        .str("error")
        .str("message")
        .str("Invalid request payload");
    let e = Reply::parse(&decode(&w.buf, Limits::default()).unwrap()).unwrap_err();
    assert!(e.0.contains("Invalid request payload"));
    let meta = ChunkrtMetadata {
        version: "0.1.0".into(),
        model: "pi05".into(),
        action_horizon: 10,
        action_dim: 32,
        image_inputs: names(&["base_0_rgb"]),
        conditioning: names(&["guided"]),
        rtc_prefix_max: 0,
        layout: "chunkrt".into(),
        delayed_views: vec![("base_1s".into(), "base_0_rgb".into(), 1000.0)],
        reset_pose: None,
    };
    let mut w = Writer::new();
    meta.write(&mut w);
    let parsed = ChunkrtMetadata::parse(&decode(&w.buf, Limits::default()).unwrap());
    assert_eq!(parsed.as_ref(), Some(&meta));
    assert!(parsed.unwrap().serves("guided"));
    // openpi's empty metadata
    assert_eq!(
        ChunkrtMetadata::parse(&decode(&[0x80], Limits::default()).unwrap()),
        None
    );
}
