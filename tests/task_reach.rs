//! The reach task end to end: `chunkrt train` writes a checkpoint the runtime loads, `chunkrt
//! eval` sweeps every strategy, the committed policy reaches held-out targets in closed loop
//! (simulated time, so the figures do not depend on this machine's load), and `chunkrt demo`
//! runs it as separate processes over iceoryx2.

use std::path::Path;
use std::process::Command;

use chunkrt_controller::config::{Config, Jacobian};
use chunkrt_controller::inference::PolicySource;
use chunkrt_learn::task::sim::{run_episode, SimSettings};
use chunkrt_learn::train::held_out_episodes;

const EXE: &str = env!("CARGO_BIN_EXE_chunkrt");

fn tmp(name: &str) -> std::path::PathBuf {
    let d = std::env::temp_dir().join(format!("chunkrt-task-{name}-{}", std::process::id()));
    std::fs::remove_dir_all(&d).ok();
    std::fs::create_dir_all(&d).unwrap();
    d
}

/// The static task's episode settings: `delay_steps` of inference delay, at most `max_seconds`.
fn settings(delay_steps: u64, max_seconds: f64) -> SimSettings {
    SimSettings {
        delay_steps,
        max_seconds,
        synchronous: false,
        record: false,
        retarget_at: None,
        drift: None,
    }
}

/// Runs `cmd` to completion and returns its stdout, after checking that it succeeded (stdout
/// and stderr in the message otherwise).
fn run_ok(cmd: &mut Command) -> String {
    let res = cmd.output().expect("the chunkrt binary runs");
    let out = String::from_utf8_lossy(&res.stdout).into_owned();
    assert!(
        res.status.success(),
        "{out}\n{}",
        String::from_utf8_lossy(&res.stderr)
    );
    out
}

#[test]
fn train_quick_writes_a_checkpoint_the_runtime_loads() {
    let dir = tmp("train");
    let out = dir.join("ckpt");
    let res = Command::new(EXE)
        .args(["train", "--quick", "--out"])
        .arg(&out)
        .arg("--dataset")
        .arg(dir.join("ds.safetensors"))
        .output()
        .unwrap();
    let err = String::from_utf8_lossy(&res.stderr);
    assert!(res.status.success(), "{err}");
    assert!(err.contains("done: 6 steps"), "{err}");
    for f in [
        "model.safetensors",
        "config.json",
        "norm_stats.json",
        "tokenizer.json",
    ] {
        assert!(out.join(f).exists(), "{f} missing");
    }
    // the dataset round-trips and the training log has the validation row
    let ds = chunkrt_learn::task::dataset::Dataset::load(&dir.join("ds.safetensors")).unwrap();
    assert_eq!(ds.episodes(), 6);
    let log = std::fs::read_to_string(dir.join("train_log.csv")).unwrap();
    assert!(log.lines().count() >= 2, "{log}");
    // the checkpoint is openpi-format: `inspect` finds a complete π0.5
    let ins = Command::new(EXE).arg("inspect").arg(&out).output().unwrap();
    let text = String::from_utf8_lossy(&ins.stdout);
    assert!(ins.status.success(), "{text}");
    assert!(text.contains("pi05"), "{text}");
    // and the controller's policy source loads it and computes a chunk
    let mut cfg = Config::embedded_default();
    cfg.policy.checkpoint = Some(out.clone());
    let mut p = PolicySource::load(&cfg).unwrap();
    let ep = held_out_episodes(&cfg, 5, 1, 0);
    let r = run_episode(
        &cfg,
        &mut p,
        &ep[0],
        &SimSettings {
            record: true,
            ..settings(1, 0.5)
        },
    )
    .unwrap();
    assert!(r.chunks >= 1);
    assert!(!r.recording.unwrap().samples.is_empty());
    std::fs::remove_dir_all(&dir).ok();
}

/// Training-time RTC end to end: `train --rtc-prefix` fine-tuning the committed policy writes a
/// checkpoint that declares its committed prefix and keeps its norm stats, `eval` runs it with
/// `rtc_trained`, and a checkpoint not trained for it is refused with the reason.
#[test]
fn train_rtc_prefix_gives_a_checkpoint_that_runs_rtc_trained() {
    let dir = tmp("train-rtc");
    let out = dir.join("ckpt");
    let init = Path::new(env!("CARGO_MANIFEST_DIR")).join("models/reach_pi05");
    let mut cmd = Command::new(EXE);
    cmd.args(["train", "--quick", "--rtc-prefix", "3", "--init"])
        .arg(&init)
        .arg("--out")
        .arg(&out)
        .arg("--dataset")
        .arg(dir.join("ds.safetensors"));
    run_ok(&mut cmd);
    let cfg: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(out.join("config.json")).unwrap()).unwrap();
    assert_eq!(cfg["rtc_prefix_max"], 3, "{cfg}");
    let stats = |d: &Path| std::fs::read_to_string(d.join("norm_stats.json")).unwrap();
    assert_eq!(stats(&out), stats(&init));

    let mut cmd = Command::new(EXE);
    cmd.args(["eval", "--quick", "--strategies", "replace,rtc_trained"])
        .arg("--checkpoint")
        .arg(&out)
        .arg("--out")
        .arg(dir.join("eval"));
    run_ok(&mut cmd);
    let csv = std::fs::read_to_string(dir.join("eval/eval.csv")).unwrap();
    for cell in ["\nrtc_trained,0,", "\nrtc_trained,2,"] {
        assert!(csv.contains(cell), "{cell} missing: {csv}");
    }
    // the committed default policy was trained without a committed prefix
    let res = Command::new(EXE)
        .args(["eval", "--quick", "--strategies", "rtc_trained", "--out"])
        .arg(dir.join("refused"))
        .output()
        .unwrap();
    let err = String::from_utf8_lossy(&res.stderr);
    assert!(!res.status.success());
    assert!(
        err.contains("rtc_trained needs a checkpoint trained"),
        "{err}"
    );
    std::fs::remove_dir_all(&dir).ok();
}

#[test]
fn eval_quick_sweeps_every_strategy_with_the_committed_policy() {
    let dir = tmp("eval");
    let mut cmd = Command::new(EXE);
    cmd.args(["eval", "--quick", "--switch-plot", "1", "--out"])
        .arg(&dir);
    let out = run_ok(&mut cmd);
    let csv = std::fs::read_to_string(dir.join("eval.csv")).unwrap();
    // header + 2 delays x 5 ways of executing
    assert_eq!(csv.lines().count(), 11, "{csv}");
    for s in ["sync", "replace", "crossfade", "temporal_ensemble", "rtc"] {
        assert!(csv.contains(&format!("\n{s},0,")), "{s} missing: {csv}");
    }
    assert!(dir.join("eval.md").exists());
    assert!(out.contains("| rtc | 2 |"), "{out}");
    // the switch plot: one line per asynchronous strategy, a small jump and a command that
    // follows the target (measured 0.004-0.01 rad on this episode)
    let lines: Vec<&str> = out.lines().filter(|l| l.contains(" switch at ")).collect();
    assert_eq!(lines.len(), 4, "{out}");
    for l in lines {
        let rad: Vec<f64> = l
            .split_whitespace()
            .filter_map(|w| w.parse::<f64>().ok())
            .collect();
        assert!(rad.len() == 3 && rad[1] < 0.05 && rad[2] < 0.05, "{l}");
    }
    assert!(dir.join("switch.png").exists());
    std::fs::remove_dir_all(&dir).ok();
}

/// The dynamic variant: the prompt switches to the other target mid-episode; the sweep reports
/// how long the robot took to turn away from the first target, and rejects a retarget outside
/// the episode.
#[test]
fn eval_dynamic_variant_reports_reaction_times() {
    let dir = tmp("eval-dynamic");
    let mut cmd = Command::new(EXE);
    cmd.args([
        "eval",
        "--max-delay",
        "0",
        "--episodes",
        "6",
        "--max-seconds",
        "3",
    ])
    .args(["--strategies", "sync,rtc", "--retarget-at", "0.5"])
    .arg("--out")
    .arg(&dir);
    let out = run_ok(&mut cmd);
    assert!(out.contains("reaction (s)"), "{out}");
    let csv = std::fs::read_to_string(dir.join("eval.csv")).unwrap();
    assert!(
        csv.lines()
            .next()
            .unwrap()
            .ends_with("reaction_time_s,reacted"),
        "{csv}"
    );
    // some episode turned away from the first target, within the 3 s of a quick episode
    let reacted: Vec<f64> = csv
        .lines()
        .skip(1)
        .filter_map(|l| l.rsplit(',').nth(1)?.parse::<f64>().ok())
        .filter(|t| t.is_finite())
        .collect();
    assert!(
        !reacted.is_empty() && reacted.iter().all(|&t| t > 0.0 && t < 3.0),
        "{csv}"
    );
    std::fs::remove_dir_all(&dir).ok();

    for bad in [
        &["--drift-hz", "0"][..],
        &["--drift-hz", "0.25", "--follow", "9"],
    ] {
        let res = Command::new(EXE)
            .args(["eval", "--quick"])
            .args(bad)
            .output()
            .unwrap();
        let err = String::from_utf8_lossy(&res.stderr);
        assert!(
            !res.status.success() && err.contains(bad[bad.len() - 2]),
            "{err}"
        );
    }
    let res = Command::new(EXE)
        .args(["eval", "--quick", "--retarget-at", "100"])
        .output()
        .unwrap();
    let err = String::from_utf8_lossy(&res.stderr);
    assert!(
        !res.status.success() && err.contains("--retarget-at 100"),
        "{err}"
    );
}

/// The committed weights, closed loop on held-out scenes with the default execution (rtc),
/// an inference delay of one action step.
#[test]
fn committed_policy_reaches_held_out_targets() {
    let cfg = Config::embedded_default();
    assert!(
        Path::new(&cfg.resolve(cfg.policy.checkpoint.as_ref().unwrap()))
            .join("model.safetensors")
            .exists(),
        "the trained policy is not committed"
    );
    let mut p = PolicySource::load(&cfg).unwrap();
    let eps = held_out_episodes(&cfg, 3_000, 10, 42);
    let settings = settings(1, 8.0);
    let mut ok = 0;
    let mut wrong = 0;
    for e in &eps {
        let r = run_episode(&cfg, &mut p, e, &settings).unwrap();
        ok += r.success as usize;
        wrong += (!r.success && r.wrong_target) as usize;
        eprintln!(
            "scene {} {:?}: success {} t {:?} closest {:.3} m  chunks {}",
            e.scene_seed, e.color, r.success, r.time_to_target, r.min_distance, r.chunks
        );
    }
    eprintln!("{ok}/10 reached, {wrong} went to the other target");
    assert!(ok >= MIN_SUCCESS, "{ok}/10 held-out episodes reached");
}

/// rtc's guidance in closed loop with the committed policy at 2 steps of delay, with the default
/// identity Jacobian (`execution.rtc_jacobian`, no backward pass) and with the exact VJP: both
/// reach held-out targets; the identity pull holds the new chunk on the old one at the switch
/// (issue 15's target: within 0.02 rad), the VJP's pull is weak on this policy.
#[test]
fn identity_jacobian_rtc_reaches_and_switches_smoothly() {
    let mut worst = [0.0f64; 2];
    for (i, jacobian) in [Jacobian::Vjp, Jacobian::Identity].into_iter().enumerate() {
        let mut cfg = Config::embedded_default();
        cfg.execution.rtc_jacobian = jacobian;
        cfg.execution.initial_delay_steps = 2;
        let mut p = PolicySource::load(&cfg).unwrap();
        let mut ok = 0;
        for e in &held_out_episodes(&cfg, 3_000, 10, 42) {
            let r = run_episode(&cfg, &mut p, e, &settings(2, 8.0)).unwrap();
            ok += r.success as usize;
            worst[i] = worst[i].max(r.smoothness.max_switch_jump_target);
        }
        eprintln!(
            "rtc, {jacobian} Jacobian, delay 2: {ok}/10 reached, largest switch jump {:.4} rad",
            worst[i]
        );
        // measured 10/10 (VJP) and 9/10 (identity) (simulated time, seeded noise)
        assert!(ok >= 8, "{jacobian}: {ok}/10 held-out episodes reached");
    }
    // measured 0.0180 (VJP) and 0.0016 rad (identity), β 10; the reach sweep's 100 episodes per
    // cell at delays 0-4: 0.050-0.054 against 0.004-0.005
    assert!(worst[1] <= 0.01 && worst[1] < 0.5 * worst[0], "{worst:?}");
}

/// The committed training-time-RTC checkpoint (`models/reach_pi05_rtc`) runs `rtc_trained` in
/// closed loop: it declares its committed prefix, reaches held-out targets at 2 steps of delay
/// with the robot's own executed actions given to it, and every chunk after the first starts
/// with them (the runtime's guarantee, tested in `policy_rtc_trained`).
#[test]
fn committed_rtc_policy_runs_rtc_trained_in_closed_loop() {
    let mut cfg = Config::embedded_default();
    cfg.policy.checkpoint =
        Some(Path::new(env!("CARGO_MANIFEST_DIR")).join("models/reach_pi05_rtc"));
    cfg.execution.strategy = chunkrt_controller::config::Strategy::RtcTrained;
    cfg.execution.initial_delay_steps = 2;
    let mut p = PolicySource::load(&cfg).unwrap();
    assert_eq!(p.committed_max(), 8);
    let eps = held_out_episodes(&cfg, 3_000, 6, 42);
    let settings = settings(2, 8.0);
    let mut ok = 0;
    for e in &eps {
        let r = run_episode(&cfg, &mut p, e, &settings).unwrap();
        ok += r.success as usize;
        assert!(r.chunks >= 2, "{} chunks", r.chunks);
    }
    eprintln!("rtc_trained at 2 steps of delay: {ok}/6 reached");
    // measured 6/6 (simulated time, seeded noise); one episode of margin
    assert!(ok >= 5, "{ok}/6 held-out episodes reached with rtc_trained");
}

/// The drifting variant: the targets swing about the base while the arm reaches, and success
/// asks the arm to stay on the prompted one. On the same episodes (same noise, same world, so
/// each pair of runs is the same trajectory until the first touch) following for 1 s succeeds
/// no more often than touching once, and never earlier.
#[test]
fn drifting_targets_must_be_reached_and_followed() {
    use chunkrt_learn::task::sim::Drift;
    let d = Drift {
        amplitude_rad: 0.3,
        frequency_hz: 0.25,
        phase_rad: 0.0,
        follow_s: 0.0,
    };
    assert_eq!(d.angle(0.0), 0.0);
    assert!(
        (d.angle(1.0) - 0.3).abs() < 1e-12,
        "a quarter swing at 0.25 Hz"
    );
    // the velocity is the derivative of the position (central difference, 1 ms)
    let start = [[0.6, 0.1], [-0.2, 0.7]];
    for t in [0.0, 0.7, 1.9] {
        let (a, b) = (
            d.targets_at(&start, t - 5e-4),
            d.targets_at(&start, t + 5e-4),
        );
        let v = d.velocities_at(&start, t);
        for c in 0..2 {
            for x in 0..2 {
                assert!((v[c][x] - (b[c][x] - a[c][x]) / 1e-3).abs() < 1e-6, "t {t}");
            }
        }
    }
    let cfg = Config::embedded_default();
    let mut p = PolicySource::load(&cfg).unwrap();
    let eps = held_out_episodes(&cfg, 3_000, 6, 42);
    let mut run = |e, follow_s| {
        let settings = SimSettings {
            drift: Some(Drift { follow_s, ..d }),
            ..settings(1, 6.0)
        };
        run_episode(&cfg, &mut p, e, &settings).unwrap()
    };
    let (mut touched, mut followed) = (0, 0);
    for e in &eps {
        let touch = run(e, 0.0);
        let follow = run(e, 1.0);
        touched += touch.success as usize;
        followed += follow.success as usize;
        if follow.success {
            assert!(touch.success && touch.time_to_target <= follow.time_to_target);
        }
    }
    eprintln!("drifting targets: {touched}/6 touched, {followed}/6 followed for 1 s");
    assert!(
        followed >= 1 && followed <= touched,
        "{followed} / {touched}"
    );
}

/// Lower bound on the committed policy's held-out success (of 10): measured 10/10 for the weights
/// of 3efe181 (the run is deterministic: simulated time, seeded noise; one episode of margin for
/// floating-point differences between thread counts and build profiles).
const MIN_SUCCESS: usize = 9;

#[test]
fn demo_runs_an_episode_over_ipc_and_writes_its_report() {
    let dir = tmp("demo");
    let (out, md) = run_demo(None, "reach the blue target", &dir);
    assert!(out.contains("success: "), "{out}");
    assert!(out.contains("fake-robot: exited cleanly"), "{out}");
    assert!(md.contains("reach the blue target"), "{md}");
    let png = std::fs::metadata(dir.join("demo.png")).unwrap();
    assert!(png.len() > 10_000);
    std::fs::remove_dir_all(&dir).ok();
}

/// Runs `chunkrt demo` (with `config`, else the embedded default) for one 6 s episode of
/// `prompt`, writing into `dir`; checks that it ran the episode and that the controller
/// computed chunks. Returns stdout and `demo.md`.
fn run_demo(config: Option<&Path>, prompt: &str, dir: &Path) -> (String, String) {
    let mut cmd = Command::new(EXE);
    cmd.arg("demo");
    if let Some(c) = config {
        cmd.arg("--config").arg(c);
    }
    cmd.args(["--prompts", prompt, "--episode-seconds", "6", "--out"])
        .arg(dir);
    let out = run_ok(&mut cmd);
    assert!(out.contains("episode 1/1"), "{out}");
    let md = std::fs::read_to_string(dir.join("demo.md")).unwrap();
    // the controller computed chunks and moved the robot
    let row = md.lines().nth(2).unwrap();
    let chunks: u64 = row.split('|').nth(5).unwrap().trim().parse().unwrap();
    assert!(chunks >= 2, "{row}");
    (out, md)
}

/// Open loop: on held-out scenes, the committed policy's chunk for an observation on the
/// expert's path (the distance-paced expert it was trained on) must be close to the expert's own
/// chunk (first action: the current position; last action: where the expert is 0.9 s later).
#[test]
fn committed_policy_reproduces_expert_chunks_open_loop() {
    use chunkrt_learn::task::expert::{Profile, Reach};
    use chunkrt_learn::task::ReachScene;
    use chunkrt_policy::runtime::{RawFrame, RawObservation};
    let cfg = Config::embedded_default();
    let dir = cfg.resolve(cfg.policy.checkpoint.as_ref().unwrap());
    let mut policy = chunkrt_controller::inference::load_policy(&dir, &cfg.policy).unwrap();
    let eps = held_out_episodes(&cfg, 4_000, 12, 9);
    let (w, h) = (64usize, 64usize);
    let mut img = vec![0u8; w * h * 3];
    let (mut e0, mut elast, mut n) = (0.0f64, 0.0f64, 0usize);
    for e in &eps {
        let scene = ReachScene::from_seed(e.scene_seed);
        let reach =
            Reach::plan_with(&e.start, &scene, e.color, 0.0, Profile::DistancePaced).unwrap();
        for k in [0usize, 5, 10] {
            let t = k as f64 * 0.1;
            let q = reach.at(t);
            scene.render_rgb(&q, w, h, 3 * w, &mut img);
            let frames = [RawFrame {
                camera: "base_0_rgb",
                width: w as u32,
                height: h as u32,
                stride: 3 * w as u32,
                encoding: chunkrt_policy::Encoding::Rgb8,
                data: &img,
            }];
            let acts = policy
                .infer(
                    &RawObservation {
                        frames: &frames,
                        joint_positions: &q,
                        prompt: e.color.prompt(),
                    },
                    &chunkrt_policy::Conditioning::Fresh,
                )
                .unwrap();
            let hz = acts.len() / 4;
            let want_last = reach.at(t + (hz - 1) as f64 * 0.1);
            for j in 0..3 {
                e0 += (acts[j] - q[j]).abs();
                elast += (acts[(hz - 1) * 4 + j] - want_last[j]).abs();
            }
            n += 3;
        }
    }
    let (e0, elast) = (e0 / n as f64, elast / n as f64);
    eprintln!("open loop, mean |error| per arm joint: first action {e0:.3} rad, last action {elast:.3} rad");
    // measured for the committed weights: 0.004 / 0.054 rad (the first action is the current
    // position: with actions relative to the state it is predicted as a delta of ~0); the earlier
    // weights of 9ca3c32, which ignored image and prompt, gave 0.011 / 0.314
    assert!(e0 < 0.02 && elast < 0.12, "first {e0:.3} last {elast:.3}");
}

/// The committed policy acts on what it sees and what it is told (`task::probe`): swapping the
/// image for another scene's, or the prompt for the other target's, changes its chunks well
/// beyond the spread of two samples of the same observation, and its moves point at the prompted
/// target rather than the other one. The policy of 9ca3c32 failed this: its image and prompt
/// effects were at the noise floor.
#[test]
fn committed_policy_acts_on_its_image_and_prompt() {
    use chunkrt_learn::task::expert::Profile;
    use chunkrt_learn::task::probe::probe;
    let cfg = Config::embedded_default();
    let dir = cfg.resolve(cfg.policy.checkpoint.as_ref().unwrap());
    let mut policy = chunkrt_controller::inference::load_policy(&dir, &cfg.policy).unwrap();
    let eps = held_out_episodes(&cfg, 4_000, 16, 9);
    let r = probe(&mut policy, &cfg, &eps, Profile::DistancePaced).unwrap();
    eprintln!("{r}");
    assert!(r.observations >= 16, "{r}");
    assert!(
        r.image_effect > PROBE_EFFECT_OVER_NOISE * r.noise_floor,
        "image effect {:.3} vs noise floor {:.3}",
        r.image_effect,
        r.noise_floor
    );
    assert!(
        r.prompt_effect > PROBE_EFFECT_OVER_NOISE * r.noise_floor,
        "prompt effect {:.3} vs noise floor {:.3}",
        r.prompt_effect,
        r.noise_floor
    );
    assert!(
        r.cos_prompted > r.cos_other + PROBE_COS_MARGIN,
        "cos prompted {:.3} vs other {:.3}",
        r.cos_prompted,
        r.cos_other
    );
}

/// Lower bounds of the probe test. Measured for the committed weights: image effect 0.354 and
/// prompt effect 0.600 rad over a noise floor of 0.052 (6.8x and 11.5x); cos 0.900 to the prompted
/// target vs 0.086 to the other (margin 0.81). The weights of 9ca3c32: 1.02x, 1.04x, margin 0.02.
const PROBE_EFFECT_OVER_NOISE: f64 = 4.0;
const PROBE_COS_MARGIN: f64 = 0.6;

/// The moving-target policy and its configuration (`config/reach_drift.toml`).
fn drift_config() -> Config {
    Config::load(&Path::new(env!("CARGO_MANIFEST_DIR")).join("config/reach_drift.toml")).unwrap()
}

/// The moving-target policy sees its earlier frame (a delayed view of the camera, 1 s back):
/// for the same newest frame, joint state and noise, an earlier frame with the targets elsewhere
/// changes the chunk, as much as the probe measured for the committed weights within a margin; a
/// policy whose view never arrived (a masked image input) would give the same chunk. Whether the
/// change leads the motion is what the probe's lead columns say: see BENCHMARKS.md section 6
/// (it does not, for these weights).
#[test]
fn drift_policy_sees_its_earlier_frame() {
    use chunkrt_learn::eval::{MOTION_PROBE_RATE_RAD_S, PROBE_SCENE_BASE};
    let cfg = drift_config();
    let dir = cfg.resolve(cfg.policy.checkpoint.as_ref().unwrap());
    let mut policy = chunkrt_controller::inference::load_policy(&dir, &cfg.policy).unwrap();
    assert_eq!(policy.delayed_views().len(), 1);
    let eps = held_out_episodes(&cfg, PROBE_SCENE_BASE, 16, 9);
    let m =
        chunkrt_learn::task::probe::motion_probe(&mut policy, &cfg, &eps, MOTION_PROBE_RATE_RAD_S)
            .unwrap();
    eprintln!("{m}");
    assert!(m.observations >= 12, "{m}");
    // the tracking expert leads the way the targets move (the probe's own check)
    assert!(m.reaching.expert > 0.2 && m.following.expert > 0.2, "{m}");
    assert!(m.reaching.still_vs_cw > MIN_EARLIER_FRAME_EFFECT_RAD, "{m}");
}

/// Lower bound of the earlier frame's effect on the chunk's end at the start pose (rad): measured
/// 0.092 for the committed weights (16 episodes, 15 in reach); a masked view gives 0.
const MIN_EARLIER_FRAME_EFFECT_RAD: f64 = 0.03;

/// The moving-target policy in closed loop on the drifting variant, its earlier frames rendered
/// by the simulator from the joint positions and targets of 400 ms before: it reaches and
/// follows the swinging target at 8 steps of delay (where the committed rtc policy follows 59 of
/// 100 and this one 88: BENCHMARKS.md section 6).
#[test]
fn drift_policy_follows_swinging_targets_in_closed_loop() {
    use chunkrt_learn::task::sim::Drift;
    let settings = SimSettings {
        drift: Some(Drift {
            amplitude_rad: 0.3,
            frequency_hz: 0.25,
            phase_rad: 0.0,
            follow_s: 1.0,
        }),
        ..settings(8, 8.0)
    };
    let followed = |cfg: &Config| {
        let mut p = PolicySource::load(cfg).unwrap();
        held_out_episodes(cfg, 3_000, 12, 42)
            .iter()
            .filter(|e| run_episode(cfg, &mut p, e, &settings).unwrap().success)
            .count()
    };
    let cfg = drift_config();
    assert_eq!(PolicySource::load(&cfg).unwrap().delayed_views().len(), 1);
    let drift = followed(&cfg);
    let mut base = cfg.clone();
    base.policy.checkpoint =
        Some(Path::new(env!("CARGO_MANIFEST_DIR")).join("models/reach_pi05_rtc"));
    let base = followed(&base);
    eprintln!(
        "drifting targets, 8 steps of delay: drift policy {drift}/12, reach_pi05_rtc {base}/12"
    );
    assert!(drift >= MIN_DRIFT_FOLLOWED, "{drift}/12");
}

/// Measured 12/12 for the committed weights (reach_pi05_rtc: 10/12 on these episodes; over 100
/// episodes 88 against 59, BENCHMARKS.md section 6); simulated time and seeded noise make the run
/// deterministic, two episodes of margin.
const MIN_DRIFT_FOLLOWED: usize = 10;

/// `chunkrt demo` with the moving-target policy: the controller keeps the camera's earlier
/// frames (the policy's delayed view) from the real camera stream over iceoryx2 and reaches.
#[test]
fn demo_runs_the_history_policy_over_ipc() {
    let dir = tmp("demo-drift");
    let cfg = Path::new(env!("CARGO_MANIFEST_DIR")).join("config/reach_drift.toml");
    run_demo(Some(&cfg), "reach the red target", &dir);
    std::fs::remove_dir_all(&dir).ok();
}
