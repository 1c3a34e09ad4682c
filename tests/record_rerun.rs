//! A run recorded into Rerun and read back with Rerun's own Python SDK: the demo robot, the
//! fake camera and the controller with the reach policy run for a few seconds while
//! `tools/python/chunkrt_record.py` (PyPI rerun-sdk 0.41.0, in the virtual environment of
//! `scripts/rerun-env.sh`; `.ci/run` makes it) records the namespace; then
//! `tools/python/rrd_check.py` loads the file and says what it holds. Without the environment
//! the test says so loudly and, in CI, fails.

use std::path::PathBuf;
use std::time::Duration;

use chunkrt_tools::testing::{summary_value, unique_namespace, ChildGuard};

#[path = "common/stack.rs"]
mod stack;
use stack::*;

#[path = "common/python.rs"]
#[allow(dead_code)]
mod python;

const ROOT: &str = env!("CARGO_MANIFEST_DIR");

/// The recorder's interpreter (`CHUNKRT_RERUN_PYTHON`, else scripts/rerun-env.sh's default
/// prefix), or None, said loudly (a failure in CI).
fn rerun_python(test: &str) -> Option<String> {
    let prefix = std::env::var("CHUNKRT_RERUN_PREFIX")
        .map(PathBuf::from)
        .unwrap_or_else(|_| {
            PathBuf::from(std::env::var("HOME").unwrap_or_default()).join(".cache/chunkrt-rerun")
        });
    let py = std::env::var("CHUNKRT_RERUN_PYTHON")
        .unwrap_or_else(|_| prefix.join("venv/bin/python").display().to_string());
    let probe = std::process::Command::new(&py)
        .args(["-c", "import rerun, iceoryx2"])
        .output();
    let why = match probe {
        Ok(o) if o.status.success() => return Some(py),
        Ok(o) => String::from_utf8_lossy(&o.stderr).trim().to_string(),
        Err(e) => format!("cannot run {py}: {e}"),
    };
    let msg = format!(
        "\n!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!\n\
         !!! {test}: the recorder's rerun-sdk is not usable: {why}\n\
         !!! This test did NOT run (bash scripts/rerun-env.sh; .ci/run does).\n\
         !!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!\n"
    );
    if python::in_ci() {
        panic!("{msg}(CI is set: this is a failure)");
    }
    eprintln!("{msg}");
    None
}

#[test]
fn a_run_is_recorded_and_rerun_reads_it_back() {
    let Some(py) = rerun_python("record_rerun") else {
        return;
    };
    let _one = serial();
    let ns = unique_namespace("record");
    let dir = std::env::temp_dir().join(format!("chunkrt-record-test-{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    let rrd = dir.join("run.rrd");
    let _robot = start("fake-robot", &ns, &[]);
    let _camera = start("fake-camera", &ns, &["--scene", "reach"]);
    let recorder = ChildGuard::spawn(
        &py,
        &[
            &format!("{ROOT}/tools/python/chunkrt_record.py"),
            "--namespace",
            &ns,
            "--out",
            rrd.to_str().unwrap(),
            "--cameras",
            "base_0_rgb",
            "--prompt",
            "reach the red target",
        ],
    )
    .expect("start the recorder");
    std::thread::sleep(Duration::from_secs(2));
    let ctl = start(
        "run",
        &ns,
        &[
            "--log-every",
            "0",
            "--duration",
            "8",
            "--prompt",
            "reach the red target",
        ],
    );
    // a forger on the chunk service, from a process of its own, during the run: a chunk at
    // 2^63 ns and past, then 3 s of tiny chunks whose ids go down (500 a second); the recorder
    // records none of them and keeps recording the controller's (issue 54 §4)
    std::thread::sleep(Duration::from_secs(1));
    let forger = ChildGuard::spawn(
        &py,
        &[
            &format!("{ROOT}/tests/python/record_forger.py"),
            &ns,
            "3",
            "500",
        ],
    )
    .expect("start the forger");
    let c_out = ctl.finish(Duration::from_secs(60));
    assert_eq!(c_out.code, Some(0), "{}", c_out.stderr);
    let f_out = forger.finish(Duration::from_secs(30));
    println!("forger: {}", f_out.stdout.trim());
    assert_eq!(f_out.code, Some(0), "{}\n{}", f_out.stdout, f_out.stderr);
    std::thread::sleep(Duration::from_millis(500));
    let r_out = recorder.terminate(Duration::from_secs(30));
    println!("recorder: {}", r_out.stdout.trim());
    assert_eq!(r_out.code, Some(0), "{}\n{}", r_out.stdout, r_out.stderr);
    let forged = summary_value(&f_out.stdout, "sent").expect(&f_out.stdout);
    let foreign = summary_value(&r_out.stdout, "foreign").unwrap_or(0.0);
    assert!(
        forged >= 100.0 && foreign >= 100.0,
        "the forger sent {forged} chunks, the recorder counted {foreign} foreign messages\n{}",
        r_out.stderr
    );
    assert_eq!(
        summary_value(&r_out.stdout, "errors"),
        Some(0.0),
        "{}",
        r_out.stderr
    );
    let chunks = summary_value(&c_out.stdout, "chunks")
        .or_else(|| summary_value(&c_out.stderr, "chunks"))
        .unwrap_or_else(|| panic!("no chunks= in the controller's summary:\n{}", c_out.stdout));
    let recorded_chunks = summary_value(&r_out.stdout, "chunks").expect(&r_out.stdout);
    // read back with Rerun's own SDK
    let check = std::process::Command::new(&py)
        .arg(format!("{ROOT}/tools/python/rrd_check.py"))
        .arg(&rrd)
        .output()
        .expect("run rrd_check.py");
    let text = String::from_utf8_lossy(&check.stdout).to_string();
    println!("{text}");
    assert!(
        check.status.success(),
        "{text}\n{}",
        String::from_utf8_lossy(&check.stderr)
    );
    let v: serde_json::Value = serde_json::from_str(text.lines().last().unwrap_or("{}"))
        .unwrap_or_else(|e| panic!("rrd_check.py printed no JSON ({e}): {text}"));
    let n = chunkrt_controller::config::Config::embedded_default().n_dof();
    for j in 0..n {
        for series in ["measured", "command", "velocity", "target"] {
            let rows = v["series"][format!("joints/{j}/{series}")]["rows"]
                .as_u64()
                .unwrap_or(0);
            assert!(rows > 100, "joints/{j}/{series}: {rows} rows\n{text}");
            assert_eq!(
                v["series"][format!("joints/{j}/{series}")]["rising"].as_bool(),
                Some(true),
                "joints/{j}/{series}: its times go back\n{text}"
            );
            assert_eq!(
                v["series"][format!("joints/{j}/{series}")]["style"]["name"].as_str(),
                Some(series),
                "joints/{j}/{series}: no style of its own in the file\n{text}"
            );
        }
    }
    assert_eq!(
        v["chunk_styles"][0]["series"].as_u64(),
        Some(recorded_chunks as u64 * n as u64),
        "every chunk series in one style\n{text}"
    );
    // every chunk the controller counted is in the file, as one series per joint, or counted as
    // missed: the forger's 500 chunks a second can push the controller's out of the service's
    // 4-slot subscriber buffer when the recorder is slow (a loaded machine), and the recorder
    // must say so (a gap in the controller's chunk seq); none of the controller's is refused
    let missed = summary_value(&r_out.stdout, "chunks_missed").expect(&r_out.stdout);
    println!("chunks: the controller made {chunks}, recorded {recorded_chunks}, missed {missed}");
    assert!(chunks >= 5.0, "only {chunks} chunks in 8 s");
    assert!(
        recorded_chunks >= 5.0,
        "only {recorded_chunks} of the controller's chunks recorded"
    );
    assert_eq!(
        recorded_chunks + missed,
        chunks,
        "the recorder saw {recorded_chunks} chunks and missed {missed}, the controller made {chunks}"
    );
    // refused: at most the forger's first chunk (its times at 2^63, refused before the question
    // of whose it is); any other refusal may be one of the controller's, hidden from the account
    let refused = summary_value(&r_out.stdout, "rejected").expect(&r_out.stdout);
    let refused_times = summary_value(&r_out.stdout, "chunks:time").unwrap_or(0.0);
    assert!(
        refused <= 1.0 && refused == refused_times,
        "the recorder refused more than the forger's chunk at 2^63\n{}",
        r_out.stdout
    );
    assert_eq!(
        v["chunk_series"].as_u64(),
        Some(recorded_chunks as u64 * n as u64),
        "chunk series in the file\n{text}"
    );
    let frames = v["frames"].as_u64().unwrap_or(0);
    assert!(frames >= 10, "{frames} camera frames in the file\n{text}");
    assert!(
        v["text_logs"].as_u64().unwrap_or(0) >= chunks as u64,
        "a log line per chunk\n{text}"
    );
    // the report's plot and table come from the same file: `chunkrt report run.rrd`
    let rep = std::process::Command::new(EXE)
        .arg("report")
        .arg(&rrd)
        .env("CHUNKRT_RERUN_PYTHON", &py)
        .output()
        .expect("run chunkrt report");
    let table = String::from_utf8_lossy(&rep.stdout).to_string();
    println!("{table}");
    assert!(
        rep.status.success(),
        "{table}\n{}",
        String::from_utf8_lossy(&rep.stderr)
    );
    let png = std::fs::metadata(dir.join("run.png")).map_or(0, |m| m.len());
    assert!(png > 20_000, "run.png: {png} bytes");
    let md = std::fs::read_to_string(dir.join("run.md")).expect("run.md");
    assert!(
        md.contains(&format!("\n{} chunks;", chunks as u64)),
        "the report's chunk count is not the controller's ({chunks}):\n{md}"
    );
    for j in 0..n {
        let row = md
            .lines()
            .find(|l| l.starts_with(&format!("| {j} | ")))
            .unwrap_or_else(|| panic!("no row for joint {j}:\n{md}"));
        let rms: f64 = row.split('|').nth(4).unwrap().trim().parse().unwrap();
        // the demo robot follows its command within a few milliradians
        assert!(rms < 0.05, "joint {j}: command − measured RMS {rms}\n{md}");
    }
    // Rerun's own viewer (the pinned rerun-sdk's, headless) opens the file and draws it
    // (tools/python/rrd_screenshot.py; docs/rerun-demo.png was made with it)
    let shot = dir.join("viewer.png");
    let view = std::process::Command::new(&py)
        .arg(format!("{ROOT}/tools/python/rrd_screenshot.py"))
        .arg(&rrd)
        .arg(&shot)
        .output()
        .expect("run rrd_screenshot.py");
    let said = format!(
        "{}{}",
        String::from_utf8_lossy(&view.stdout),
        String::from_utf8_lossy(&view.stderr)
    );
    if view.status.code() == Some(3) {
        // no graphics adapter on this machine (.ci/run installs no system packages)
        eprintln!(
            "\n!!! record_rerun: the viewer's screenshot did NOT run: no graphics adapter here \
             (a GPU, or Mesa's lavapipe: apt install mesa-vulkan-drivers)\n{}\n",
            said.lines()
                .filter(|l| l.starts_with("rrd_screenshot"))
                .collect::<Vec<_>>()
                .join("\n")
        );
    } else {
        assert!(view.status.success(), "rrd_screenshot.py failed:\n{said}");
        let bytes = std::fs::metadata(&shot).map_or(0, |m| m.len());
        assert!(bytes > 50_000, "viewer.png: {bytes} bytes\n{said}");
        // what the viewer itself loaded: every chunk of every joint, and the measured series
        let held = said
            .lines()
            .find(|l| l.contains("the viewer holds"))
            .unwrap_or_else(|| panic!("the viewer said nothing of what it holds:\n{said}"));
        println!("{held}; {bytes} bytes of PNG");
        let series = held
            .split(", ")
            .find_map(|p| p.strip_suffix(" chunk series"))
            .and_then(|n| n.trim().parse::<u64>().ok());
        assert_eq!(series, Some(chunks as u64 * n as u64), "{held}");
        assert!(held.ends_with("joints/0/measured yes"), "{held}");
    }
    let _ = std::fs::remove_dir_all(&dir);
}

/// The recorder fed hostile messages in-process (tests/python/record_validates.py): chunks
/// that break the contract (times at 2^63 and past, a period of 2^63, no rows, 4e9 joints,
/// NaN, from the future) are counted and dropped, not a crash; a chunk from another process
/// is not recorded; a flood of tiny chunks with ids going down and 40 000 statuses stays under
/// `--max-mb` (everything written counts) and under the bound on chunk series, and the file
/// reads back. On the recorder of acdf275 (before): four crashes (`OverflowError`), 13.2 MB
/// under `--max-mb 1`, 6 010 entity paths.
#[test]
fn the_recorder_validates_what_it_reads() {
    let Some(py) = rerun_python("record_rerun (validation)") else {
        return;
    };
    let dir = std::env::temp_dir().join(format!("chunkrt-record-valid-{}", std::process::id()));
    let out = std::process::Command::new(&py)
        .arg(format!("{ROOT}/tests/python/record_validates.py"))
        .arg(&dir)
        .output()
        .expect("run record_validates.py");
    let text = String::from_utf8_lossy(&out.stdout).to_string();
    println!("{text}");
    let _ = std::fs::remove_dir_all(&dir);
    assert!(
        out.status.success() && text.trim_end().ends_with("ok"),
        "{text}\n{}",
        String::from_utf8_lossy(&out.stderr)
    );
}

/// The series are styled in the recording itself (tests/python/record_styles.py: the recorder
/// fed a short run in-process, the file read back by `rrd_check.py`): command, measured and
/// target each a colour and width of their own, every predicted chunk one thin grey style named
/// `predicted chunk`. On the recorder of 2402189 (before): no series carried a style, and the
/// viewer gave measured and the chunks the same automatic colour.
#[test]
fn the_series_are_styled_in_the_recording() {
    let Some(py) = rerun_python("record_rerun (styles)") else {
        return;
    };
    let dir = std::env::temp_dir().join(format!("chunkrt-record-styles-{}", std::process::id()));
    let out = std::process::Command::new(&py)
        .arg(format!("{ROOT}/tests/python/record_styles.py"))
        .arg(&dir)
        .output()
        .expect("run record_styles.py");
    let text = String::from_utf8_lossy(&out.stdout).to_string();
    println!("{text}");
    let _ = std::fs::remove_dir_all(&dir);
    assert!(
        out.status.success() && text.trim_end().ends_with("ok"),
        "{text}\n{}",
        String::from_utf8_lossy(&out.stderr)
    );
}

/// On a machine with no Vulkan driver (made so here: `VK_DRIVER_FILES` names no file) the
/// screenshot tool says so and exits with its own status 3, with no backtrace (before: the
/// viewer's panic and its stack on stderr).
#[test]
fn the_screenshot_without_vulkan_exits_3_without_a_backtrace() {
    let Some(py) = rerun_python("record_rerun (screenshot without Vulkan)") else {
        return;
    };
    let dir = std::env::temp_dir().join(format!("chunkrt-shot-novk-{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    let rrd = dir.join("two.rrd");
    // two chunks of joint 0: something to screenshot
    let make = std::process::Command::new(&py)
        .args([
            "-c",
            "import sys, numpy as np, rerun as rr\n\
             rr.init('chunkrt', spawn=False); rr.save(sys.argv[1])\n\
             for k in range(2):\n\
             \x20   t = (np.arange(5) * 20_000_000 + k * 50_000_000) * 1e-9\n\
             \x20   rr.send_columns(f'joints/0/chunks/{k + 1}', indexes=[rr.TimeColumn('robot_time', duration=t)], columns=rr.Scalars.columns(scalars=np.arange(5.0)))\n\
             rr.disconnect()",
        ])
        .arg(&rrd)
        .output()
        .expect("make a recording");
    assert!(
        make.status.success(),
        "{}",
        String::from_utf8_lossy(&make.stderr)
    );
    let none = dir.join("no-such-icd.json");
    let view = std::process::Command::new(&py)
        .arg(format!("{ROOT}/tools/python/rrd_screenshot.py"))
        .arg(&rrd)
        .arg(dir.join("shot.png"))
        .args(["--settle", "1"])
        .env("VK_DRIVER_FILES", &none)
        .env("VK_ICD_FILENAMES", &none)
        .output()
        .expect("run rrd_screenshot.py");
    let said = format!(
        "{}{}",
        String::from_utf8_lossy(&view.stdout),
        String::from_utf8_lossy(&view.stderr)
    );
    println!("{said}");
    let _ = std::fs::remove_dir_all(&dir);
    assert_eq!(view.status.code(), Some(3), "{said}");
    for bad in ["Traceback", "panicked", "stack backtrace"] {
        assert!(!said.contains(bad), "'{bad}' in what it said:\n{said}");
    }
    assert!(said.contains("rrd_screenshot: no Vulkan driver"), "{said}");
}
