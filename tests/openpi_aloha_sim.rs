//! openpi's own ALOHA sim example client against `chunkrt serve --openpi-config pi0_aloha_sim`:
//! `examples/aloha_sim` of openpi (main.py, env.py, saver.py, run unchanged from an openpi
//! checkout) with PyPI's gym-aloha 0.1.1 (MuJoCo 2.3.7, the versions openpi pins for it), and a
//! π0 of ALOHA's dimensions (action_dim 32, horizon 50: the pi0_bench model) with random
//! weights and statistics around the arms' start pose. One episode (300 steps at 50 Hz, a
//! chunk every 10 actions): every reply must have the 14 columns gym-aloha steps with.
//!
//! Ignored by default, with its reasons: it needs an openpi checkout (its examples are not on
//! PyPI, and chunkrt does not copy them) and the example's own pinned environment (~0.2 GB).
//!
//!     bash scripts/aloha-sim-env.sh
//!     CHUNKRT_OPENPI_DIR=/path/to/openpi cargo test --release --test openpi_aloha_sim -- --ignored --nocapture

use std::net::TcpStream;
use std::path::PathBuf;
use std::process::Command;
use std::time::{Duration, Instant};

use chunkrt_tools::testing::ChildGuard;

const EXE: &str = env!("CARGO_BIN_EXE_chunkrt");

fn free_port() -> u16 {
    std::net::TcpListener::bind("127.0.0.1:0")
        .and_then(|l| l.local_addr())
        .map(|a| a.port())
        .expect("a free port")
}

fn wait_healthy(port: u16, server: &mut ChildGuard) {
    use std::io::{Read, Write};
    let t0 = Instant::now();
    loop {
        assert!(server.running(), "the server exited before it was healthy");
        if let Ok(mut s) = TcpStream::connect(("127.0.0.1", port)) {
            let _ = s.set_read_timeout(Some(Duration::from_secs(2)));
            let _ = s.write_all(b"GET /healthz HTTP/1.1\r\nHost: x\r\n\r\n");
            let mut out = String::new();
            let _ = s.read_to_string(&mut out);
            if out.starts_with("HTTP/1.1 200") {
                return;
            }
        }
        assert!(t0.elapsed() < Duration::from_secs(120), "never healthy");
        std::thread::sleep(Duration::from_millis(100));
    }
}

#[test]
#[ignore = "needs an openpi checkout (CHUNKRT_OPENPI_DIR) and bash scripts/aloha-sim-env.sh"]
fn openpi_aloha_sim_example_runs_an_episode_against_chunkrt_serve() {
    let openpi = std::env::var("CHUNKRT_OPENPI_DIR")
        .expect("CHUNKRT_OPENPI_DIR: an openpi checkout (examples/aloha_sim)");
    let example = PathBuf::from(&openpi).join("examples/aloha_sim");
    assert!(example.join("main.py").is_file(), "{}", example.display());
    let py = std::env::var("CHUNKRT_ALOHA_PYTHON").unwrap_or_else(|_| {
        format!(
            "{}/.cache/chunkrt-aloha-sim/venv/bin/python",
            std::env::var("HOME").unwrap_or_default()
        )
    });
    let dir = std::env::temp_dir().join(format!("chunkrt-aloha-sim-{}", std::process::id()));
    let ckpt = dir.join("pi0_aloha_sim");
    let _ = std::fs::remove_dir_all(&dir);
    std::fs::create_dir_all(&dir).unwrap();

    // a π0 of ALOHA's dimensions, random weights
    let out = Command::new(EXE)
        .args([
            "bench-inference",
            "--preset",
            "pi0_bench",
            "--precision",
            "f32",
        ])
        .arg("--write-checkpoint")
        .arg(&ckpt)
        .output()
        .unwrap();
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    // statistics in the model's space (after openpi's ALOHA input transform): the actions
    // around gym-aloha's start pose (its joints flipped as pi0 has them; the grippers at the
    // middle of ALOHA's range once converted back), narrow, so random weights move little
    let flip = [1.0, -1.0, -1.0, 1.0, 1.0, 1.0, 1.0];
    let home = [0.0, -0.96, 1.16, 0.0, -0.3, 0.0];
    let grip = 0.5 * (1.4910 + 0.6213) - 0.6213 - 0.5476; // gripper_from_angular(grip) = 0.5
    let mut mean = Vec::new();
    for _arm in 0..2 {
        for j in 0..6 {
            mean.push(flip[j] * home[j]);
        }
        mean.push(grip);
    }
    let stats = serde_json::json!({"norm_stats": {
        "state": {"mean": vec![0.0; 14], "std": vec![1.0; 14]},
        "actions": {"mean": mean, "std": vec![0.02; 14]},
    }});
    std::fs::write(ckpt.join("norm_stats.json"), stats.to_string()).unwrap();

    let port = free_port();
    let port_s = port.to_string();
    let mut server = ChildGuard::spawn(
        EXE,
        &[
            "serve",
            "--checkpoint",
            ckpt.to_str().unwrap(),
            "--openpi-config",
            "pi0_aloha_sim",
            "--port",
            &port_s,
            "--log-every",
            "5",
        ],
    )
    .expect("chunkrt serve");
    wait_healthy(port, &mut server);

    let videos = dir.join("videos");
    let t0 = Instant::now();
    let run = Command::new(&py)
        .current_dir(&example)
        .env("MUJOCO_GL", "egl")
        .args([
            "main.py",
            "--args.host",
            "127.0.0.1",
            "--args.port",
            &port_s,
        ])
        .arg("--args.out-dir")
        .arg(&videos)
        .output()
        .expect("run openpi's examples/aloha_sim/main.py");
    let secs = t0.elapsed().as_secs_f64();
    let served = server.terminate(Duration::from_secs(5));
    let log = String::from_utf8_lossy(&run.stderr);
    println!(
        "openpi's aloha_sim example: exit {:?} after {secs:.1} s\n{}",
        run.status.code(),
        log.lines().rev().take(8).collect::<Vec<_>>().join("\n")
    );
    println!(
        "chunkrt serve:\n{}",
        served
            .stderr
            .lines()
            .rev()
            .take(6)
            .collect::<Vec<_>>()
            .join("\n")
    );
    assert!(run.status.success(), "the example failed:\n{log}");
    let video = videos.join("out_0.mp4");
    let size = std::fs::metadata(&video).map(|m| m.len()).unwrap_or(0);
    assert!(size > 0, "no episode video at {}", video.display());
    println!("episode video: {} ({size} bytes)", video.display());
}
