//! `chunkrt record` and `--record FILE` on `demo` and `soak`: a run into a Rerun recording.
//!
//! The recorder is a process of its own (`tools/python/chunkrt_record.py`, in the virtual
//! environment of `scripts/rerun-env.sh`: PyPI's rerun-sdk, whose `rerun` is also the viewer). It
//! subscribes to the namespace's services, so the controller does no work for it; the chunks come
//! from the controller's `NS/chunks` service.

use std::path::{Path, PathBuf};
use std::process::{Command, Stdio};

use anyhow::Context;

/// `chunkrt record`: everything a namespace carries into an `.rrd` file, until Ctrl-C.
#[derive(Debug, clap::Args)]
pub struct RecordArgs {
    /// The run's service namespace (`chunkrt monitor` lists them).
    #[arg(long)]
    pub namespace: String,
    /// The Rerun recording to write (open it with `rerun FILE`).
    #[arg(long, value_name = "FILE")]
    pub out: PathBuf,
    /// Camera names to record, comma separated (none: no frames).
    #[arg(long, default_value = "")]
    pub cameras: String,
    /// Keep one camera frame in N.
    #[arg(long, value_name = "N", default_value_t = 1)]
    pub frame_every: u32,
    /// Seconds to record (0: until Ctrl-C / SIGTERM).
    #[arg(long, default_value_t = 0.0)]
    pub duration: f64,
    /// Megabytes to write at most, everything written counted (then the recorder says so and
    /// records no more).
    #[arg(long, value_name = "MB", default_value_t = 500.0)]
    pub max_mb: f64,
}

/// The interpreter of the recorder's virtual environment: `CHUNKRT_RERUN_PYTHON`, else
/// `CHUNKRT_RERUN_PREFIX` (default `~/.cache/chunkrt-rerun`)`/venv/bin/python`.
pub fn rerun_python() -> anyhow::Result<PathBuf> {
    let (_, py) = crate::args::venv_python(
        "CHUNKRT_RERUN_PREFIX",
        "chunkrt-rerun",
        "CHUNKRT_RERUN_PYTHON",
    );
    anyhow::ensure!(
        py.is_file(),
        "recording needs PyPI's rerun-sdk in its own environment: bash scripts/rerun-env.sh \
         (looked for {})",
        py.display()
    );
    Ok(py)
}

/// The recorder script beside the other Python tools.
pub fn recorder_script() -> PathBuf {
    chunkrt_learn::task::so101::sim_script().with_file_name("chunkrt_record.py")
}

/// The recorder's command line for `ns` into `out`.
pub fn recorder_command(
    ns: &str,
    out: &Path,
    cameras: &[String],
    extra: &[String],
) -> anyhow::Result<Command> {
    let py = rerun_python()?;
    let script = recorder_script();
    anyhow::ensure!(
        script.is_file(),
        "the recorder {} is missing",
        script.display()
    );
    if let Some(dir) = out.parent().filter(|d| !d.as_os_str().is_empty()) {
        std::fs::create_dir_all(dir).with_context(|| format!("cannot create {}", dir.display()))?;
    }
    let mut cmd = Command::new(py);
    cmd.arg(script)
        .args(["--namespace", ns, "--out"])
        .arg(out)
        .args(["--cameras", &cameras.join(",")])
        .args(extra)
        .stdin(Stdio::null());
    Ok(cmd)
}

/// `chunkrt record`.
pub fn run(args: RecordArgs) -> anyhow::Result<()> {
    anyhow::ensure!(
        args.frame_every >= 1,
        "--frame-every {}: must be at least 1",
        args.frame_every
    );
    anyhow::ensure!(
        args.max_mb.is_finite() && args.max_mb > 0.0,
        "--max-mb {}: must be positive",
        args.max_mb
    );
    anyhow::ensure!(
        args.duration.is_finite() && args.duration >= 0.0,
        "--duration {}: must be 0 or more",
        args.duration
    );
    let cameras: Vec<String> = args
        .cameras
        .split(',')
        .filter(|s| !s.is_empty())
        .map(String::from)
        .collect();
    let extra = vec![
        "--frame-every".to_string(),
        args.frame_every.to_string(),
        "--duration".into(),
        args.duration.to_string(),
        "--max-mb".into(),
        args.max_mb.to_string(),
    ];
    // Ctrl-C reaches the recorder too (same process group): this process waits for it to
    // close the file instead of dying first
    let _stop = chunkrt_tools::shutdown::flag();
    let status = recorder_command(&args.namespace, &args.out, &cameras, &extra)?
        .status()
        .context("cannot start the recorder")?;
    anyhow::ensure!(status.success(), "the recorder ended with {status}");
    Ok(())
}

/// A recording's series as `rrd_export.py` writes them: path → (time ns, value), sorted (the
/// joint series thinned to at most 20 000 rows each), the rows each joint series holds in the
/// file before the thinning, and the chunk log's count.
struct Exported {
    series: std::collections::BTreeMap<String, Vec<(i64, f64)>>,
    recorded: std::collections::BTreeMap<String, usize>,
    chunks: usize,
}

/// Reads `rrd_export.py`'s CSV; a line that does not parse is an error naming it.
fn read_export(text: &str) -> anyhow::Result<Exported> {
    let mut series: std::collections::BTreeMap<String, Vec<(i64, f64)>> = Default::default();
    let mut recorded: std::collections::BTreeMap<String, usize> = Default::default();
    let mut chunks = 0;
    for (i, line) in text.lines().enumerate().skip(1) {
        if let Some(n) = line.strip_prefix("# chunks ") {
            chunks = n.trim().parse()?;
            continue;
        }
        if let Some(rest) = line.strip_prefix("# rows ") {
            let (p, n) = rest
                .rsplit_once(' ')
                .with_context(|| format!("line {}: {line:?} is not # rows PATH N", i + 1))?;
            let n = n.parse().with_context(|| format!("line {}", i + 1))?;
            recorded.insert(p.to_string(), n);
            continue;
        }
        let mut f = line.splitn(3, ',');
        let (Some(p), Some(t), Some(v)) = (f.next(), f.next(), f.next()) else {
            anyhow::bail!("line {}: {line:?} is not path,t_ns,value", i + 1);
        };
        let t: i64 = t.parse().with_context(|| format!("line {}", i + 1))?;
        let v: f64 = v.parse().with_context(|| format!("line {}", i + 1))?;
        series.entry(p.to_string()).or_default().push((t, v));
    }
    Ok(Exported {
        series,
        recorded,
        chunks,
    })
}

/// `chunkrt report run.rrd`: the recording's commanded, measured and chunk-target positions
/// per joint with every predicted chunk overlaid (`--png`, default beside the file), and a
/// table of the tracking per joint (`--md`): the picture and the figures from the recorded
/// data, read with Rerun's own SDK.
pub fn report(rrd: &Path, png: Option<&Path>, md: Option<&Path>) -> anyhow::Result<()> {
    anyhow::ensure!(rrd.is_file(), "no recording at {}", rrd.display());
    let py = rerun_python()?;
    let csv = std::env::temp_dir().join(format!("chunkrt-rrd-{}.csv", std::process::id()));
    let script = recorder_script().with_file_name("rrd_export.py");
    let out = std::process::Command::new(&py)
        .arg(&script)
        .arg(rrd)
        .arg(&csv)
        .output()
        .with_context(|| format!("run {}", py.display()))?;
    anyhow::ensure!(
        out.status.success(),
        "{} {}: {}",
        script.display(),
        rrd.display(),
        String::from_utf8_lossy(&out.stderr).trim()
    );
    let text = std::fs::read_to_string(&csv);
    let _ = std::fs::remove_file(&csv);
    let data = read_export(&text?)?;
    let joints: Vec<usize> = {
        let mut j: Vec<usize> = data
            .series
            .keys()
            .filter_map(|p| p.strip_prefix("joints/")?.split('/').next()?.parse().ok())
            .collect();
        j.dedup();
        j
    };
    anyhow::ensure!(
        !joints.is_empty(),
        "{}: no joint series in the recording",
        rrd.display()
    );
    let t0 = data
        .series
        .values()
        .filter_map(|s| s.first().map(|p| p.0))
        .min()
        .unwrap_or(0);
    let png = png.map_or_else(|| rrd.with_extension("png"), Path::to_path_buf);
    let md = md.map_or_else(|| rrd.with_extension("md"), Path::to_path_buf);
    plot_recording(&png, &data, &joints, t0, rrd)?;
    let table = tracking_table(&rrd.display().to_string(), &data, &joints, t0);
    std::fs::write(&md, &table).with_context(|| format!("write {}", md.display()))?;
    print!("{table}");
    println!("\nplot: {}\ntable: {}", png.display(), md.display());
    Ok(())
}

/// The report's table: per joint, the rows the file holds and the rows plotted (the export thins
/// a long run's series), and the tracking, the command against the measured position at the
/// same time, over the rows plotted.
fn tracking_table(title: &str, data: &Exported, joints: &[usize], t0: i64) -> String {
    let mut table = format!(
        "# {title}\n\n{} chunks; {:.1} s recorded.\n\n| joint | measured rows: in the file / \
         plotted | command rows: in the file / plotted | \\|command − measured\\| RMS (rad) | \
         max (rad) |\n|---|---|---|---|---|\n",
        data.chunks,
        data.series
            .values()
            .filter_map(|s| s.last().map(|p| p.0))
            .max()
            .map_or(0.0, |t| (t - t0) as f64 * 1e-9)
    );
    for &j in joints {
        let path = |k: &str| format!("joints/{j}/{k}");
        let get = |k: &str| data.series.get(&path(k));
        let (m, c) = (get("measured"), get("command"));
        let (rms, max) = match (m, c) {
            (Some(m), Some(c)) if !m.is_empty() => tracking(m, c),
            _ => (f64::NAN, f64::NAN),
        };
        let rows = |k: &str, s: Option<&Vec<(i64, f64)>>| {
            let plotted = s.map_or(0, Vec::len);
            let held = data.recorded.get(&path(k)).copied().unwrap_or(plotted);
            format!("{held} / {plotted}")
        };
        table.push_str(&format!(
            "| {j} | {} | {} | {rms:.4} | {max:.4} |\n",
            rows("measured", m),
            rows("command", c)
        ));
    }
    let thinned: Vec<String> = data
        .recorded
        .iter()
        .filter(|(p, &n)| data.series.get(*p).map_or(0, Vec::len) < n)
        .map(|(p, n)| format!("{p} {n}"))
        .collect();
    if !thinned.is_empty() {
        table.push_str(&format!(
            "\nThe plot and the tracking use at most {EXPORT_ROWS} rows per series, evenly spaced \
             by row; the file holds more ({}).\n",
            thinned.join(", ")
        ));
    }
    table
}

/// The rows per joint series `rrd_export.py` keeps for the report (its `--max-points` default).
const EXPORT_ROWS: usize = 20_000;

/// A series cut where nothing was recorded: a time step longer than 10 × the series' median
/// step and than 50 ms (the gap between two episodes, where no chunk gave a target) ends a line,
/// so the plot draws no line through it. Each part is drawn as its own line.
fn segments(s: &[(i64, f64)]) -> Vec<&[(i64, f64)]> {
    if s.len() < 3 {
        return vec![s];
    }
    let mut steps: Vec<i64> = s.windows(2).map(|w| w[1].0 - w[0].0).collect();
    let mid = steps.len() / 2;
    let median = *steps.select_nth_unstable(mid).1;
    let gap = median.saturating_mul(10).max(50_000_000);
    let mut parts = Vec::new();
    let mut start = 0;
    for i in 1..s.len() {
        if s[i].0 - s[i - 1].0 > gap {
            parts.push(&s[start..i]);
            start = i;
        }
    }
    parts.push(&s[start..]);
    parts
}

/// RMS and max of |command − measured| with the measured series held at each command's time.
fn tracking(measured: &[(i64, f64)], command: &[(i64, f64)]) -> (f64, f64) {
    let (mut i, mut sum, mut max, mut n) = (0usize, 0.0, 0.0f64, 0usize);
    for &(t, c) in command {
        while i + 1 < measured.len() && measured[i + 1].0 <= t {
            i += 1;
        }
        if measured[i].0 > t {
            continue;
        }
        let e = (c - measured[i].1).abs();
        sum += e * e;
        max = max.max(e);
        n += 1;
    }
    if n == 0 {
        (f64::NAN, f64::NAN)
    } else {
        ((sum / n as f64).sqrt(), max)
    }
}

/// One panel per joint: every predicted chunk (thin, grey), the chunk target, the command and
/// the measured position over the recording's time.
fn plot_recording(
    path: &Path,
    data: &Exported,
    joints: &[usize],
    t0: i64,
    rrd: &Path,
) -> anyhow::Result<()> {
    use plotters::prelude::*;
    let err = |e: &dyn std::fmt::Display| anyhow::anyhow!("plot {}: {e}", path.display());
    let secs = |t: i64| (t - t0) as f64 * 1e-9;
    let root = BitMapBackend::new(path, (1200, 260 * joints.len() as u32 + 40)).into_drawing_area();
    root.fill(&WHITE).map_err(|e| err(&e))?;
    let (top, body) = root.split_vertically(40);
    top.draw_text(
        &format!(
            "{}: {} chunks (lines break where nothing was recorded)",
            rrd.display(),
            data.chunks
        ),
        &("sans-serif", 20).into_font().color(&BLACK),
        (10, 10),
    )
    .map_err(|e| err(&e))?;
    let t_end = data
        .series
        .values()
        .filter_map(|s| s.last().map(|p| secs(p.0)))
        .fold(0.5f64, f64::max);
    for (&j, area) in joints
        .iter()
        .zip(body.split_evenly((joints.len(), 1)).iter())
    {
        let prefix = format!("joints/{j}/");
        let mine: Vec<(&String, &Vec<(i64, f64)>)> = data
            .series
            .iter()
            .filter(|(p, _)| p.starts_with(&prefix))
            .collect();
        let (lo, hi) = mine
            .iter()
            .filter(|(p, _)| !p.contains("/chunks/"))
            .flat_map(|(_, s)| s.iter().map(|p| p.1))
            .fold((f64::MAX, f64::MIN), |(a, b), v| (a.min(v), b.max(v)));
        let (lo, hi) = if lo <= hi {
            let pad = 0.1 * (hi - lo).max(0.05);
            (lo - pad, hi + pad)
        } else {
            (-1.0, 1.0)
        };
        let mut chart = ChartBuilder::on(area)
            .caption(format!("joint {j}"), ("sans-serif", 16))
            .margin(8)
            .x_label_area_size(30)
            .y_label_area_size(55)
            .build_cartesian_2d(0f64..t_end, lo..hi)
            .map_err(|e| err(&e))?;
        chart
            .configure_mesh()
            .x_desc("robot time since the recording began (s)")
            .y_desc("position")
            .draw()
            .map_err(|e| err(&e))?;
        let mut first_chunk = true;
        for (_, s) in mine.iter().filter(|(p, _)| p.contains("/chunks/")) {
            let drawn = chart
                .draw_series(LineSeries::new(
                    s.iter().map(|&(t, v)| (secs(t), v.clamp(lo, hi))),
                    BLACK.mix(0.25).stroke_width(1),
                ))
                .map_err(|e| err(&e))?;
            if first_chunk {
                drawn
                    .label("predicted chunks")
                    .legend(|(x, y)| PathElement::new(vec![(x, y), (x + 20, y)], BLACK.mix(0.25)));
                first_chunk = false;
            }
        }
        for (kind, color, width) in [
            ("target", GREEN.mix(0.9), 1),
            ("measured", BLUE.mix(0.9), 3),
            ("command", RED.mix(0.9), 1),
        ] {
            let Some(s) = data.series.get(&format!("{prefix}{kind}")) else {
                continue;
            };
            for (k, part) in segments(s).into_iter().enumerate() {
                let drawn = chart
                    .draw_series(LineSeries::new(
                        part.iter().map(|&(t, v)| (secs(t), v)),
                        color.stroke_width(width),
                    ))
                    .map_err(|e| err(&e))?;
                if k == 0 {
                    drawn.label(kind).legend(move |(x, y)| {
                        PathElement::new(vec![(x, y), (x + 20, y)], color.stroke_width(width))
                    });
                }
            }
        }
        chart
            .configure_series_labels()
            .position(SeriesLabelPosition::UpperRight)
            .background_style(WHITE.mix(0.8))
            .border_style(BLACK.mix(0.3))
            .draw()
            .map_err(|e| err(&e))?;
    }
    root.present().map_err(|e| err(&e))?;
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    /// 1 kHz rows from `from` to `to` seconds (a line of value `v`).
    fn rows(from: f64, to: f64, v: f64) -> Vec<(i64, f64)> {
        let (a, b) = ((from * 1e3) as i64, (to * 1e3) as i64);
        (a..b).map(|ms| (ms * 1_000_000, v)).collect()
    }

    #[test]
    fn a_line_breaks_where_nothing_was_recorded() {
        // two episodes' targets, 1.5 s apart: two lines, none across the gap
        let mut s = rows(0.0, 2.0, 0.1);
        s.extend(rows(3.5, 5.0, 0.2));
        let parts = segments(&s);
        assert_eq!(
            parts.len(),
            2,
            "{:?}",
            parts.iter().map(|p| p.len()).collect::<Vec<_>>()
        );
        assert_eq!(parts[0].last().unwrap().0, 1_999_000_000);
        assert_eq!(parts[1][0].0, 3_500_000_000);
        // thinned as the export thins it (every 3rd row), the gap still breaks the line
        let thinned: Vec<(i64, f64)> = s.iter().copied().step_by(3).collect();
        assert_eq!(segments(&thinned).len(), 2);
        // the recorder missing a few commands in a row (a 6 ms hole) is not a gap
        let mut holes = rows(0.0, 1.0, 0.1);
        holes.retain(|&(t, _)| !(400_000_000..406_000_000).contains(&t));
        assert_eq!(segments(&holes).len(), 1);
        assert_eq!(segments(&[]).len(), 1);
    }

    #[test]
    fn the_report_says_the_rows_in_the_file_and_the_rows_plotted() {
        // what rrd_export.py writes for a run whose file holds 57 506 measured rows, thinned
        let mut text = String::from("path,t_ns,value\n");
        for (t, v) in [(0, 0.1), (1_000_000, 0.1), (2_000_000, 0.1)] {
            text.push_str(&format!(
                "joints/0/measured,{t},{v}\njoints/0/command,{t},{v}\n"
            ));
        }
        text.push_str(
            "# rows joints/0/command 57510\n# rows joints/0/measured 57506\n# chunks 4\n",
        );
        let data = read_export(&text).unwrap();
        assert_eq!(data.recorded["joints/0/measured"], 57_506);
        let table = tracking_table("run.rrd", &data, &[0], 0);
        let row = table.lines().find(|l| l.starts_with("| 0 | ")).unwrap();
        assert!(row.contains("| 57506 / 3 | 57510 / 3 |"), "{table}");
        assert!(table.contains("4 chunks;"), "{table}");
        assert!(table.contains("joints/0/measured 57506"), "{table}");
        // an export without the counts (nothing thinned) says the rows it has, once each way
        let plain = read_export("path,t_ns,value\njoints/0/measured,0,0.1\n").unwrap();
        let table = tracking_table("run.rrd", &plain, &[0], 0);
        assert!(table.contains("| 0 | 1 / 1 | 0 / 0 |"), "{table}");
        assert!(!table.contains("the file holds more"), "{table}");
    }
}
