//! Latency reports: percentile plots (PNG) and `chunkrt report DIR`, on top of the
//! latency histograms and interval logs ([`crate::histlog`], re-exported here).
//!
//! - [`plot_percentiles`]: latency by percentile on HdrHistogram's log-scaled percentile axis
//!   (0 %, 90 %, 99 %, 99.9 %, …), one line per series, PNG.
//! - [`run`]: `chunkrt report DIR` renders every `*.hlog` of a folder into `report.png` and
//!   `report.md`.

use std::path::{Path, PathBuf};

use hdrhistogram::Histogram;

pub use crate::histlog::*;

/// Percentile axis position of a quantile: `log10(1 / (1 - q))` (0 → 0 %, 1 → 90 %, 2 → 99 %…).
pub fn percentile_x(q: f64) -> f64 {
    (1.0 / (1.0 - q).max(1e-12)).log10()
}

fn percentile_label(x: f64) -> String {
    let q = 1.0 - 10f64.powf(-x);
    let pct = q * 100.0;
    let digits = (x.round() as i64 - 2).max(0) as usize;
    format!("{pct:.digits$}%")
}

/// Points `(percentile axis x, latency µs)` of a histogram, up to the percentile its sample
/// count resolves, ending at its maximum.
pub fn percentile_curve(h: &Histogram<u64>) -> Vec<(f64, f64)> {
    if h.is_empty() {
        return Vec::new();
    }
    let x_max = (h.len() as f64).log10().clamp(1.0, 7.0);
    let steps = 200;
    let mut pts: Vec<(f64, f64)> = (0..=steps)
        .map(|i| {
            let x = x_max * i as f64 / steps as f64;
            let q = 1.0 - 10f64.powf(-x);
            (x, h.value_at_quantile(q) as f64 / 1000.0)
        })
        .collect();
    pts.push((x_max, h.max() as f64 / 1000.0));
    pts
}

/// Draws latency by percentile (HdrHistogram's log-scaled percentile x axis, log-scaled µs y
/// axis), one line per series, into a PNG of `size` pixels.
pub fn plot_percentiles(
    path: &Path,
    title: &str,
    series: &[Series],
    size: (u32, u32),
) -> Result<(), ReportError> {
    use plotters::prelude::*;
    if let Some(parent) = path.parent() {
        std::fs::create_dir_all(parent).map_err(io_err(parent))?;
    }
    let perr = |e: String| ReportError::Plot {
        path: path.to_path_buf(),
        reason: e,
    };
    let curves: Vec<(&str, Vec<(f64, f64)>)> = series
        .iter()
        .filter(|s| !s.hist.is_empty())
        .map(|s| (s.name.as_str(), percentile_curve(&s.hist)))
        .collect();
    if curves.is_empty() {
        return Err(perr("no non-empty series".into()));
    }
    let x_max = curves
        .iter()
        .flat_map(|(_, c)| c.iter().map(|p| p.0))
        .fold(1.0f64, f64::max)
        .ceil();
    let (y_min, y_max) = curves
        .iter()
        .flat_map(|(_, c)| c.iter().map(|p| p.1))
        .fold((f64::MAX, 0.0f64), |(lo, hi), y| (lo.min(y), hi.max(y)));
    let y_lo = (y_min.max(0.01) / 1.5).max(0.01);
    let y_hi = (y_max * 1.5).max(y_lo * 10.0);

    let root = BitMapBackend::new(path, size).into_drawing_area();
    root.fill(&WHITE).map_err(|e| perr(e.to_string()))?;
    let mut chart = ChartBuilder::on(&root)
        .caption(title, ("sans-serif", 20))
        .margin(12)
        .x_label_area_size(40)
        .y_label_area_size(60)
        .build_cartesian_2d(0f64..x_max, (y_lo..y_hi).log_scale())
        .map_err(|e| perr(e.to_string()))?;
    chart
        .configure_mesh()
        .x_labels(x_max as usize + 1)
        .x_label_formatter(&|x| percentile_label(*x))
        .y_label_formatter(&|y| {
            if *y >= 1.0 {
                format!("{y:.0}")
            } else {
                format!("{y:.2}")
            }
        })
        .x_desc("percentile")
        .y_desc("latency (µs)")
        .draw()
        .map_err(|e| perr(e.to_string()))?;
    for (i, (name, pts)) in curves.iter().enumerate() {
        let color = Palette99::pick(i).to_rgba().stroke_width(2);
        chart
            .draw_series(LineSeries::new(pts.iter().copied(), color))
            .map_err(|e| perr(e.to_string()))?
            // leading space: plotters clips glyphs with a negative left bearing (the j of
            // "joint_state") at the start of a label
            .label(format!(" {name}"))
            .legend(move |(x, y)| {
                PathElement::new(
                    vec![(x, y), (x + 20, y)],
                    Palette99::pick(i).stroke_width(2),
                )
            });
    }
    chart
        .configure_series_labels()
        .position(SeriesLabelPosition::UpperLeft)
        .background_style(WHITE.mix(0.85))
        .border_style(BLACK)
        .draw()
        .map_err(|e| perr(e.to_string()))?;
    root.present().map_err(|e| perr(e.to_string()))?;
    Ok(())
}

/// Where `chunkrt report` writes (by default inside the folder it reads).
#[derive(Debug, clap::Args)]
pub struct ReportArgs {
    /// Folder of HdrHistogram interval logs (`*.hlog`), or a Rerun recording (`*.rrd`, from
    /// `chunkrt record` or `--record`): then the plot is each joint's command, measured position
    /// and predicted chunks, and the table the tracking per joint (default FILE.png / FILE.md).
    pub dir: PathBuf,
    /// Output PNG (default DIR/report.png).
    #[arg(long)]
    pub png: Option<PathBuf>,
    /// Output Markdown table (default DIR/report.md).
    #[arg(long)]
    pub md: Option<PathBuf>,
    /// Plot title.
    #[arg(long, default_value = "chunkrt latency by percentile")]
    pub title: String,
}

/// Reads every `*.hlog` in `dir` (sorted by name). A series is named `file/tag` when the folder
/// holds more than one log.
pub fn read_log_dir(dir: &Path) -> Result<Vec<Series>, ReportError> {
    let mut files: Vec<PathBuf> = std::fs::read_dir(dir)
        .map_err(io_err(dir))?
        .filter_map(|e| e.ok().map(|e| e.path()))
        .filter(|p| p.extension().is_some_and(|e| e == "hlog"))
        .collect();
    files.sort();
    let many = files.len() > 1;
    let mut all = Vec::new();
    for f in &files {
        let stem = f
            .file_stem()
            .map(|s| s.to_string_lossy().into_owned())
            .unwrap_or_default();
        for mut s in read_interval_log(f)? {
            if many && s.name != stem {
                s.name = format!("{stem}/{}", s.name);
            }
            all.push(s);
        }
    }
    if all.is_empty() {
        return Err(ReportError::Empty(dir.to_path_buf()));
    }
    Ok(all)
}

/// `chunkrt report DIR`: one PNG (latency by percentile, every series) and one Markdown table.
pub fn run(args: ReportArgs) -> anyhow::Result<()> {
    let series = read_log_dir(&args.dir)?;
    let png = args.png.unwrap_or_else(|| args.dir.join("report.png"));
    let md = args.md.unwrap_or_else(|| args.dir.join("report.md"));
    plot_percentiles(&png, &args.title, &series, (1000, 640))?;
    let table = LatencyTable::from_series(args.title.clone(), &series);
    let text = format!(
        "# {}\n\n{}\n![latency by percentile]({})\n",
        args.title,
        table.to_markdown(),
        png.file_name()
            .map(|n| n.to_string_lossy().into_owned())
            .unwrap_or_default()
    );
    std::fs::write(&md, text).map_err(io_err(&md))?;
    print!("{table}");
    println!("wrote {} and {}", png.display(), md.display());
    Ok(())
}

/// A plot's error as a user reads it: a missing font (plotters finds fonts through fontconfig)
/// gets what to install.
pub fn plot_error_text(e: &dyn std::fmt::Display) -> String {
    let text = e.to_string();
    if text.contains("Font") || text.contains("font") {
        format!(
            "{text} (the plots need a sans-serif font found by fontconfig: install \
             fonts-dejavu-core, or point FONTCONFIG_FILE at a fonts.conf naming a folder of .ttf files)"
        )
    } else {
        text
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::time::Duration;

    fn hist(values: impl IntoIterator<Item = u64>) -> Histogram<u64> {
        let mut h = latency_histogram();
        for v in values {
            h.saturating_record(v);
        }
        h
    }

    #[test]
    fn interval_log_roundtrip_and_report() {
        let dir = std::env::temp_dir().join(format!("chunkrt-report-test-{}", std::process::id()));
        let _ = std::fs::remove_dir_all(&dir);
        let a = Series::new("fast", hist((0..5000u64).map(|i| 10_000 + i)));
        let b = Series::new("slow", hist((0..5000u64).map(|i| 100_000 + 20 * i)));
        let path = dir.join("x.hlog");
        write_interval_log(
            &path,
            &[a.clone(), b.clone()],
            Duration::from_secs(2),
            "test",
        )
        .expect("write log");
        let back = read_interval_log(&path).expect("read log");
        assert_eq!(back.len(), 2);
        assert_eq!(back[0].name, "fast");
        assert_eq!(back[0].hist.len(), 5000);
        assert_eq!(
            back[1].hist.value_at_quantile(0.99),
            b.hist.value_at_quantile(0.99)
        );
        assert!(write_interval_log(
            &path,
            &[Series::new("bad name", hist([1]))],
            Duration::ZERO,
            ""
        )
        .is_err());
        write_interval_log(&path, &[a, b], Duration::from_secs(2), "test").expect("rewrite");
        run(ReportArgs {
            dir: dir.clone(),
            png: None,
            md: None,
            title: "t".into(),
        })
        .expect("report");
        let png = std::fs::read(dir.join("report.png")).expect("png written");
        assert_eq!(&png[1..4], b"PNG");
        let md = std::fs::read_to_string(dir.join("report.md")).expect("md written");
        assert!(md.contains("| slow | 5000 |"), "{md}");
        // A garbage log is an error, not a crash.
        std::fs::write(dir.join("y.hlog"), "0.0,1.0,2.0,HISTFAKE!!\n").expect("write garbage");
        assert!(read_log_dir(&dir).is_err());
        let _ = std::fs::remove_dir_all(&dir);
    }

    #[test]
    fn percentile_axis() {
        assert_eq!(percentile_label(0.0), "0%");
        assert_eq!(percentile_label(1.0), "90%");
        assert_eq!(percentile_label(3.0), "99.9%");
        assert!((percentile_x(0.99) - 2.0).abs() < 1e-9);
    }
}
