//! `chunkrt demo --config config/ros2_mock.toml`: the robot is a ros2_control robot on ROS 2's
//! wire — `tools/python/ros2_mock.py` (mock_components/GenericSystem behind
//! joint_state_broadcaster and a forward position controller, on Cyclone DDS as rmw_cyclonedds)
//! — reached through `chunkrt ros2`, in place of `fake-robot`. Everything else (camera, reach
//! policy, episodes, report) is the ordinary demo's.

use std::fs::File;
use std::process::{Command, Stdio};

use anyhow::Context;

use super::{spawn, Proc, Stack};

/// Whether the configuration has a `[ros2]` section: its robot is reached over ROS 2.
pub(crate) fn is_ros2(stack: &Stack) -> bool {
    std::fs::read_to_string(&stack.cfg.source)
        .ok()
        .and_then(|t| t.parse::<toml::Table>().ok())
        .is_some_and(|t| t.contains_key("ros2"))
}

/// The peer and the bridge, on a DDS domain of their own (the configuration's, else one derived
/// from this process: two demos on one network do not drive each other's robot).
pub(crate) fn spawn_robot(stack: &Stack) -> anyhow::Result<Vec<Proc>> {
    let domain = match std::env::var("ROS_DOMAIN_ID") {
        Ok(d) if !d.trim().is_empty() => d.trim().to_string(),
        _ => (1 + std::process::id() % 200).to_string(),
    };
    let config = stack.cfg.source.display().to_string();
    let script = concat!(env!("CARGO_MANIFEST_DIR"), "/tools/python/ros2_mock.py");
    let log = stack.log_dir.join("ros2-mock.log");
    let out = File::create(&log).with_context(|| format!("cannot create {}", log.display()))?;
    let child = Command::new("python3")
        .args([
            script,
            "--config",
            &config,
            "--domain-id",
            &domain,
            "--rate-hz",
            &format!("{}", stack.cfg.robot.joint_state_rate_hz),
            "--duration",
            "1000000",
            "--loopback",
        ])
        .stdin(Stdio::null())
        .stdout(out.try_clone()?)
        .stderr(out)
        .spawn()
        .context("cannot start tools/python/ros2_mock.py (python3 with cyclonedds and rosbags)")?;
    println!(
        "ros2: the robot is {script} on DDS domain {domain} (log {}); chunkrt ros2 bridges it",
        log.display()
    );
    let peer = Proc {
        name: "ros2-mock",
        child,
        log,
    };
    let mut args = stack.args("ros2");
    args.extend(["--domain-id".to_string(), domain]);
    let bridge = spawn(&stack.exe, "ros2", &args, &stack.log_dir)?;
    Ok(vec![peer, bridge])
}
