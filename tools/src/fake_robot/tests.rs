//! Unit tests of `fake_robot` (kept apart so the module reads on its own).
use super::*;

#[test]
fn default_args_match_the_empty_command_line() {
    use clap::Parser;
    #[derive(clap::Parser)]
    struct Cli {
        #[command(flatten)]
        args: Args,
    }
    assert_eq!(Cli::parse_from(["fake-robot"]).args, Args::default());
}

fn limits() -> Vec<JointLimits> {
    vec![
        JointLimits {
            position_min: -1.0,
            position_max: 1.0,
            max_velocity: 2.0,
            max_acceleration: 20.0,
        };
        2
    ]
}

fn cmd(seq: u64, now: u64, pos: [f64; 2]) -> JointCommand {
    let mut c = JointCommand {
        seq,
        publish_time_ns: now,
        deadline_ns: now + 5_000_000,
        n_dof: 2,
        mode: COMMAND_MODE_POSITION,
        ..Default::default()
    };
    c.position[..2].copy_from_slice(&pos);
    c
}

#[test]
fn arm_tracks_a_step_within_limits() {
    let mut arm = Arm::new(&limits(), &[0.0, 0.0], 60.0).unwrap();
    let mut t = Target {
        position: [0.0; MAX_DOF],
        velocity: [0.0; MAX_DOF],
        acceleration: [0.0; MAX_DOF],
    };
    t.position[0] = 0.5;
    t.position[1] = 5.0; // beyond the limit
    assert!(arm.clamp_target(&mut t));
    let mut max_v: f64 = 0.0;
    for _ in 0..2000 {
        arm.step(&t, 1e-3);
        max_v = max_v.max(arm.velocity[0].abs());
        assert!(arm.position[1] <= 1.0);
    }
    assert!((arm.position[0] - 0.5).abs() < 1e-4, "{}", arm.position[0]);
    assert!((arm.position[1] - 1.0).abs() < 1e-4, "{}", arm.position[1]);
    assert!(max_v <= 2.0 + 1e-12);
    // critically damped with a velocity limit: no overshoot
    assert!(arm.position[0] <= 0.5 + 1e-9);
}

#[test]
fn watchdog_holds_on_deadline_timeout_and_rejects_bad_commands() {
    let arm = Arm::new(&limits(), &[0.0, 0.0], 60.0).unwrap();
    let t0 = 1_000_000_000u64;
    let mut r = Robot::new(arm, 50_000_000, 1_000_000, t0);
    assert_ne!(r.step(t0, 1e-3) & JOINT_STATUS_HOLDING, 0);

    r.on_command(&cmd(1, t0, [0.3, 0.0]), 7, t0);
    assert_eq!(r.step(t0 + 1_000_000, 1e-3), 0);
    assert_eq!(r.summary().commands_applied, 1);

    // past its deadline: hold
    let f = r.step(t0 + 6_000_000, 1e-3);
    assert_ne!(f & JOINT_STATUS_HOLDING, 0);
    assert_eq!(r.summary().holds, 1);

    // arrives expired
    let late = cmd(2, t0, [0.3, 0.0]);
    r.on_command(&late, 7, t0 + 10_000_000);
    assert_eq!(r.summary().commands_expired, 1);
    assert_ne!(
        r.step(t0 + 10_000_000, 1e-3) & JOINT_STATUS_COMMAND_EXPIRED,
        0
    );

    // invalid
    let mut bad = cmd(3, t0 + 11_000_000, [0.3, f64::NAN]);
    r.on_command(&bad, 7, t0 + 11_000_000);
    bad.n_dof = 3;
    r.on_command(&bad, 7, t0 + 11_000_000);
    assert_eq!(r.summary().commands_rejected, 2);
    assert_ne!(
        r.step(t0 + 11_000_000, 1e-3) & JOINT_STATUS_COMMAND_REJECTED,
        0
    );

    // a valid one again clears the sticky flags; out of order is rejected
    r.on_command(&cmd(4, t0 + 12_000_000, [0.3, 0.0]), 7, t0 + 12_000_000);
    assert_eq!(r.step(t0 + 12_000_000, 1e-3), 0);
    r.on_command(&cmd(4, t0 + 12_000_000, [0.3, 0.0]), 7, t0 + 12_500_000);
    assert_eq!(r.summary().commands_rejected, 3);

    // a far deadline still ends with the command timeout
    let mut long = cmd(5, t0 + 13_000_000, [0.3, 0.0]);
    long.deadline_ns = u64::MAX;
    r.on_command(&long, 7, t0 + 13_000_000);
    assert_eq!(r.step(t0 + 40_000_000, 1e-3), 0);
    let f = r.step(t0 + 70_000_000, 1e-3);
    assert_ne!(f & JOINT_STATUS_COMMAND_TIMEOUT, 0);
    assert_ne!(f & JOINT_STATUS_HOLDING, 0);
}
