//! Unit tests of `validate` (kept apart so the module reads on its own).
use super::*;

fn state(n: u32) -> JointState {
    JointState {
        n_dof: n,
        ..Default::default()
    }
}

#[test]
fn rearm_checks() {
    let now = 10_000_000_000;
    let ok = RearmRequest {
        seq: 7,
        publish_time_ns: now - 1_000,
        reserved: 0,
    };
    assert_eq!(validate_rearm(&ok, now, 1_000_000), Ok(()));
    let bad = |r: RearmRequest| validate_rearm(&r, now, 1_000_000).map_err(|e| e.reason());
    assert_eq!(bad(RearmRequest { seq: 0, ..ok }), Err(RejectReason::Other));
    assert_eq!(
        bad(RearmRequest { reserved: 1, ..ok }),
        Err(RejectReason::Other)
    );
    assert_eq!(
        bad(RearmRequest {
            publish_time_ns: now + 2_000_000,
            ..ok
        }),
        Err(RejectReason::FromFuture)
    );
    assert_eq!(
        bad(RearmRequest {
            publish_time_ns: now - REARM_MAX_AGE_NS - 1,
            ..ok
        }),
        Err(RejectReason::Stale)
    );
}

#[test]
fn joint_state_checks() {
    assert!(validate_joint_state(&state(6), Some(6)).is_ok());
    assert_eq!(
        validate_joint_state(&state(17), None).unwrap_err().reason(),
        RejectReason::NDof
    );
    assert_eq!(
        validate_joint_state(&state(0), None).unwrap_err().reason(),
        RejectReason::NDof
    );
    assert!(matches!(
        validate_joint_state(&state(5), Some(6)),
        Err(ValidationError::NDofMismatch { .. })
    ));
    let mut s = state(6);
    s.velocity[3] = f64::NAN;
    assert!(matches!(
        validate_joint_state(&s, Some(6)),
        Err(ValidationError::NonFinite {
            field: "velocity",
            index: 3,
            ..
        })
    ));
    // garbage beyond n_dof is ignored
    s.velocity[3] = 0.0;
    s.position[10] = f64::INFINITY;
    assert!(validate_joint_state(&s, Some(6)).is_ok());
}

#[test]
fn command_checks() {
    let mut c = JointCommand {
        n_dof: 2,
        mode: 9,
        ..Default::default()
    };
    assert_eq!(
        validate_joint_command(&c, None).unwrap_err().reason(),
        RejectReason::UnknownCode
    );
    c.mode = COMMAND_MODE_POSITION;
    c.acceleration[1] = f64::NEG_INFINITY;
    assert_eq!(
        validate_joint_command(&c, None).unwrap_err().reason(),
        RejectReason::NonFinite
    );
}

#[test]
fn frame_checks() {
    let h = CameraFrameHeader {
        encoding: ENCODING_RGB8,
        width: 4,
        height: 2,
        stride: 12,
        ..Default::default()
    };
    assert!(validate_frame(&h, 24, 64, 64).is_ok());
    assert!(matches!(
        validate_frame(&h, 23, 64, 64),
        Err(ValidationError::PayloadLength { .. })
    ));
    assert!(matches!(
        validate_frame(&CameraFrameHeader { stride: 11, ..h }, 22, 64, 64),
        Err(ValidationError::StrideTooSmall { .. })
    ));
    assert!(matches!(
        validate_frame(&CameraFrameHeader { encoding: 77, ..h }, 24, 64, 64),
        Err(ValidationError::UnknownEncoding(77))
    ));
    assert!(matches!(
        validate_frame(&h, 24, 3, 64),
        Err(ValidationError::FrameTooLarge { .. })
    ));
    // padded rows are fine, up to twice the row plus alignment; not without bound
    assert!(validate_frame(&CameraFrameHeader { stride: 16, ..h }, 32, 64, 64).is_ok());
    assert!(validate_frame(&CameraFrameHeader { stride: 280, ..h }, 560, 64, 64).is_ok());
    assert!(matches!(
        validate_frame(&CameraFrameHeader { stride: 281, ..h }, 562, 64, 64),
        Err(ValidationError::StrideTooLarge { max: 280, .. })
    ));
    let wide = CameraFrameHeader {
        width: 64,
        height: 64,
        stride: 16 << 20,
        ..h
    };
    assert!(matches!(
        validate_frame(&wide, (16 << 20) * 64, 64, 64),
        Err(ValidationError::StrideTooLarge { .. })
    ));
    // a huge stride x height must not overflow
    let big = CameraFrameHeader {
        stride: u32::MAX,
        height: 2,
        ..h
    };
    assert!(validate_frame(&big, 24, 64, 64).is_err());
}

#[test]
fn stream_guard_orders_and_ages() {
    let lim = Freshness {
        max_age_ns: 1_000,
        max_future_ns: 10,
    };
    let mut g = StreamGuard::new();
    assert!(g.check(1, 5, 100, 200, lim).is_ok());
    assert_eq!(
        g.check(1, 5, 150, 200, lim).unwrap_err().reason(),
        RejectReason::OutOfOrder
    );
    assert!(matches!(
        g.check(1, 6, 90, 200, lim),
        Err(ValidationError::TimeWentBackwards { .. })
    ));
    assert_eq!(
        g.check(1, 7, 300, 200, lim).unwrap_err().reason(),
        RejectReason::FromFuture
    );
    assert_eq!(
        g.check(1, 7, 100, 5_000, lim).unwrap_err().reason(),
        RejectReason::Stale
    );
    // a restarted publisher may start its sequence again (the first one has been silent
    // for longer than the maximum age)
    assert!(g.check(2, 0, 4_500, 5_000, lim).is_ok());
    assert!(g.check(2, 1, 4_600, 5_000, lim).is_ok());
}

/// Two publishers interleaving on one channel: the one bound first is obeyed, every message
/// of the other is rejected while the first is alive, whatever its seq and time; when the
/// first falls silent for longer than the maximum age, the other binds.
#[test]
fn stream_guard_binds_one_publisher() {
    let lim = Freshness {
        max_age_ns: 1_000,
        max_future_ns: 10,
    };
    let mut g = StreamGuard::new();
    let mut forged = 0;
    for k in 0..100u64 {
        let t = 10_000 + 10 * k;
        assert!(g.check(7, k + 1, t, t, lim).is_ok(), "genuine message {k}");
        // the forger: decreasing seq, plausible times, same instant
        let r = g.check(9, 1_000 - k, t + 5, t + 5, lim);
        assert_eq!(
            r.unwrap_err().reason(),
            RejectReason::ForeignPublisher,
            "forged message {k}"
        );
        forged += 1;
    }
    assert_eq!(forged, 100);
    // the genuine publisher's stream is intact
    assert!(g.check(7, 101, 11_000, 11_000, lim).is_ok());
    // it falls silent: within the maximum age the forger is still refused, after it binds
    assert_eq!(
        g.check(9, 1, 11_900, 11_900, lim).unwrap_err().reason(),
        RejectReason::ForeignPublisher
    );
    assert!(g.check(9, 1, 12_100, 12_100, lim).is_ok());
    // and now the first one is the foreign one
    assert_eq!(
        g.check(7, 102, 12_150, 12_150, lim).unwrap_err().reason(),
        RejectReason::ForeignPublisher
    );
}
