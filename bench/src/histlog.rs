//! Latency histograms and their logs: [`latency_histogram`] (preallocated, recording never
//! allocates), named [`Series`], percentile tables ([`LatencyTable`]) and HdrHistogram interval
//! logs ([`write_interval_log`] / [`read_interval_log`]: the Java `HistogramLogWriter` format,
//! base64 V2-deflate histograms, one tag per series, readable by HdrHistogram's own tools).
//!
//! Owns: the text and log forms of latency measurements. Must not depend on: plotting (the
//! plots and `chunkrt report` live in the app crate's `report`).

use std::fmt::Write as _;
use std::path::{Path, PathBuf};
use std::time::{Duration, SystemTime};

use hdrhistogram::serialization::interval_log::{
    IntervalLogIterator, IntervalLogWriterBuilder, LogEntry, Tag,
};
use hdrhistogram::serialization::{Deserializer, V2DeflateSerializer};
use hdrhistogram::Histogram;

/// Highest latency a histogram made by [`latency_histogram`] records exactly (60 s, in ns);
/// larger values are clamped to it.
pub const MAX_LATENCY_NS: u64 = 60_000_000_000;

/// Errors of reading, writing and drawing latency reports.
#[derive(Debug, thiserror::Error)]
pub enum ReportError {
    /// A file could not be read or written.
    #[error("{path}: {source}")]
    Io {
        /// The file.
        path: PathBuf,
        /// The cause.
        source: std::io::Error,
    },
    /// An interval log is malformed.
    #[error("{path}: malformed interval log: {reason}")]
    BadLog {
        /// The file.
        path: PathBuf,
        /// What is wrong.
        reason: String,
    },
    /// A series name cannot be used as an interval-log tag.
    #[error("series name '{0}' cannot be a log tag (no spaces, ',' or newlines)")]
    BadTag(String),
    /// Histogram serialization failed.
    #[error("cannot serialize histogram '{name}': {reason}")]
    Serialize {
        /// Series name.
        name: String,
        /// The cause.
        reason: String,
    },
    /// The plot could not be drawn.
    #[error("cannot draw {path}: {reason}")]
    Plot {
        /// The PNG file.
        path: PathBuf,
        /// The cause.
        reason: String,
    },
    /// Nothing to report.
    #[error("{0}: no histograms found")]
    Empty(PathBuf),
}

/// A latency histogram in nanoseconds: 1 ns .. [`MAX_LATENCY_NS`], 3 significant digits.
/// All its memory is allocated here, so recording never allocates (use `saturating_record`).
pub fn latency_histogram() -> Histogram<u64> {
    Histogram::new_with_bounds(1, MAX_LATENCY_NS, 3)
        .expect("constant bounds 1..60e9 with 3 significant digits are valid")
}

/// One named latency histogram (values in ns).
#[derive(Debug, Clone)]
pub struct Series {
    /// Name shown in tables, plot legends and log tags (no spaces or commas).
    pub name: String,
    /// Latencies in nanoseconds.
    pub hist: Histogram<u64>,
}

impl Series {
    /// A named series.
    pub fn new(name: impl Into<String>, hist: Histogram<u64>) -> Self {
        Self {
            name: name.into(),
            hist,
        }
    }
}

/// One row of a [`LatencyTable`]; latencies in nanoseconds.
#[derive(Debug, Clone, PartialEq)]
pub struct LatencyRow {
    /// Series name.
    pub name: String,
    /// Number of samples.
    pub count: u64,
    /// Median.
    pub p50_ns: u64,
    /// 90th percentile.
    pub p90_ns: u64,
    /// 99th percentile.
    pub p99_ns: u64,
    /// 99.9th percentile.
    pub p999_ns: u64,
    /// Largest sample.
    pub max_ns: u64,
}

impl LatencyRow {
    /// Percentiles of one histogram.
    pub fn from_hist(name: &str, h: &Histogram<u64>) -> Self {
        Self {
            name: name.to_string(),
            count: h.len(),
            p50_ns: h.value_at_quantile(0.5),
            p90_ns: h.value_at_quantile(0.9),
            p99_ns: h.value_at_quantile(0.99),
            p999_ns: h.value_at_quantile(0.999),
            max_ns: h.max(),
        }
    }
}

/// HdrHistogram-style percentile table: count, p50, p90, p99, p99.9, max (shown in µs).
#[derive(Debug, Clone, Default, PartialEq)]
pub struct LatencyTable {
    /// Title printed above the table.
    pub title: String,
    /// One row per series, in insertion order.
    pub rows: Vec<LatencyRow>,
}

/// Formats nanoseconds as microseconds with a precision that suits the magnitude.
pub fn fmt_us(ns: u64) -> String {
    let us = ns as f64 / 1000.0;
    if us < 10.0 {
        format!("{us:.2}")
    } else if us < 1000.0 {
        format!("{us:.1}")
    } else {
        format!("{us:.0}")
    }
}

impl LatencyTable {
    /// An empty table.
    pub fn new(title: impl Into<String>) -> Self {
        Self {
            title: title.into(),
            rows: Vec::new(),
        }
    }

    /// A table with one row per series.
    pub fn from_series(title: impl Into<String>, series: &[Series]) -> Self {
        let mut t = Self::new(title);
        for s in series {
            t.push(&s.name, &s.hist);
        }
        t
    }

    /// Adds a row.
    pub fn push(&mut self, name: &str, h: &Histogram<u64>) {
        self.rows.push(LatencyRow::from_hist(name, h));
    }

    /// The row of a series, if present.
    pub fn row(&self, name: &str) -> Option<&LatencyRow> {
        self.rows.iter().find(|r| r.name == name)
    }

    /// The table as GitHub Markdown (latencies in µs).
    pub fn to_markdown(&self) -> String {
        let mut s = String::new();
        s.push_str("| series | count | p50 µs | p90 µs | p99 µs | p99.9 µs | max µs |\n");
        s.push_str("|---|---:|---:|---:|---:|---:|---:|\n");
        for r in &self.rows {
            let _ = writeln!(
                s,
                "| {} | {} | {} | {} | {} | {} | {} |",
                r.name,
                r.count,
                fmt_us(r.p50_ns),
                fmt_us(r.p90_ns),
                fmt_us(r.p99_ns),
                fmt_us(r.p999_ns),
                fmt_us(r.max_ns)
            );
        }
        s
    }
}

/// One row of a plain-text table: `first` left-aligned in `w0` columns, then each cell
/// right-aligned in its width, one space apart (the percentile tables of every bench).
pub fn write_row(
    f: &mut dyn std::fmt::Write,
    first: &str,
    w0: usize,
    cells: &[String],
    widths: &[usize],
) -> std::fmt::Result {
    write!(f, "{first:<w0$}")?;
    for (c, w) in cells.iter().zip(widths) {
        write!(f, " {c:>w$}")?;
    }
    writeln!(f)
}

impl std::fmt::Display for LatencyTable {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        let w = self
            .rows
            .iter()
            .map(|r| r.name.len())
            .max()
            .unwrap_or(6)
            .max(6);
        if !self.title.is_empty() {
            writeln!(f, "{}", self.title)?;
        }
        let widths = [9, 10, 10, 10, 10, 10];
        let head = ["count", "p50 µs", "p90 µs", "p99 µs", "p99.9 µs", "max µs"];
        write_row(f, "series", w, &head.map(String::from), &widths)?;
        for r in &self.rows {
            let cells = [
                r.count.to_string(),
                fmt_us(r.p50_ns),
                fmt_us(r.p90_ns),
                fmt_us(r.p99_ns),
                fmt_us(r.p999_ns),
                fmt_us(r.max_ns),
            ];
            write_row(f, &r.name, w, &cells, &widths)?;
        }
        Ok(())
    }
}

/// Markdown percentile table of some series (see [`LatencyTable::to_markdown`]).
pub fn markdown_table(series: &[Series]) -> String {
    LatencyTable::from_series("", series).to_markdown()
}

/// Maps an I/O error on `path` to [`ReportError::Io`].
pub fn io_err(path: &Path) -> impl FnOnce(std::io::Error) -> ReportError + '_ {
    move |source| ReportError::Io {
        path: path.to_path_buf(),
        source,
    }
}

/// Writes the series as one HdrHistogram interval log (one interval per series, tagged with the
/// series name; `duration` is how long the measurement ran). `comment` lines go in the header.
pub fn write_interval_log(
    path: &Path,
    series: &[Series],
    duration: Duration,
    comment: &str,
) -> Result<(), ReportError> {
    if let Some(parent) = path.parent() {
        std::fs::create_dir_all(parent).map_err(io_err(parent))?;
    }
    let mut buf: Vec<u8> = Vec::new();
    let mut serializer = V2DeflateSerializer::new();
    let now = SystemTime::now();
    let start = now.checked_sub(duration).unwrap_or(now);
    {
        let mut builder = IntervalLogWriterBuilder::new();
        for line in comment.lines() {
            builder.add_comment(line);
        }
        builder.add_comment("values in nanoseconds; one interval per series, tag = series");
        builder.with_start_time(start).with_base_time(start);
        // Max column in ms, for humans reading the log.
        builder.with_max_value_divisor(1e6);
        let mut writer = builder
            .begin_log_with(&mut buf, &mut serializer)
            .map_err(io_err(path))?;
        for s in series {
            let tag = Tag::new(&s.name).ok_or_else(|| ReportError::BadTag(s.name.clone()))?;
            if s.name.contains(' ') {
                return Err(ReportError::BadTag(s.name.clone()));
            }
            writer
                .write_histogram(&s.hist, Duration::ZERO, duration, Some(tag))
                .map_err(|e| ReportError::Serialize {
                    name: s.name.clone(),
                    reason: format!("{e:?}"),
                })?;
        }
    }
    std::fs::write(path, buf).map_err(io_err(path))
}

/// Decodes standard base64 (with or without padding).
fn base64_decode(s: &str) -> Option<Vec<u8>> {
    fn val(c: u8) -> Option<u32> {
        Some(match c {
            b'A'..=b'Z' => c - b'A',
            b'a'..=b'z' => c - b'a' + 26,
            b'0'..=b'9' => c - b'0' + 52,
            b'+' => 62,
            b'/' => 63,
            _ => return None,
        } as u32)
    }
    let bytes: Vec<u8> = s.bytes().filter(|c| *c != b'=').collect();
    let mut out = Vec::with_capacity(bytes.len() * 3 / 4);
    for chunk in bytes.chunks(4) {
        let mut acc = 0u32;
        for (i, c) in chunk.iter().enumerate() {
            acc |= val(*c)? << (18 - 6 * i);
        }
        match chunk.len() {
            4 => out.extend_from_slice(&[(acc >> 16) as u8, (acc >> 8) as u8, acc as u8]),
            3 => out.extend_from_slice(&[(acc >> 16) as u8, (acc >> 8) as u8]),
            2 => out.push((acc >> 16) as u8),
            _ => return None,
        }
    }
    Some(out)
}

/// Interval logs larger than this are refused (a 10-minute soak writes well under 1 MB).
pub const MAX_LOG_BYTES: u64 = 256 << 20;

/// What one encoded histogram may unpack to.
const MAX_HISTOGRAM_BYTES: u64 = 16 << 20;

/// Checks an encoded histogram's header before the deserializer sizes anything from it, and
/// returns it in the uncompressed V2 encoding. A crafted 1.6 KB log used to make `report`
/// allocate 4.2 GB (a payload length or range taken on trust).
fn checked_histogram(raw: &[u8]) -> Result<Vec<u8>, String> {
    const V2: u32 = 0x1c84_9303;
    const V2_DEFLATE: u32 = 0x1c84_9304;
    const HEADER: usize = 40;
    let be32 = |b: &[u8], at: usize| -> Result<u32, String> {
        b.get(at..at + 4)
            .map(|x| u32::from_be_bytes([x[0], x[1], x[2], x[3]]))
            .ok_or_else(|| "truncated histogram".to_string())
    };
    let be64 = |b: &[u8], at: usize| -> Result<u64, String> {
        b.get(at..at + 8)
            .map(|x| u64::from_be_bytes([x[0], x[1], x[2], x[3], x[4], x[5], x[6], x[7]]))
            .ok_or_else(|| "truncated histogram".to_string())
    };
    // the cookie's bits 4-7 carry the word size; the base identifies the encoding
    let plain = match be32(raw, 0)? & !0xf0 {
        V2 => raw.to_vec(),
        V2_DEFLATE => {
            use std::io::Read;
            let n = be32(raw, 4)? as usize;
            let z = raw
                .get(8..8 + n)
                .ok_or_else(|| format!("compressed length {n} beyond the data"))?;
            let mut out = Vec::new();
            flate2::read::ZlibDecoder::new(z)
                .take(MAX_HISTOGRAM_BYTES + 1)
                .read_to_end(&mut out)
                .map_err(|e| format!("inflate: {e}"))?;
            if out.len() as u64 > MAX_HISTOGRAM_BYTES {
                return Err(format!("unpacks to more than {MAX_HISTOGRAM_BYTES} bytes"));
            }
            out
        }
        c => return Err(format!("unknown histogram encoding {c:#x}")),
    };
    if be32(&plain, 0)? & !0xf0 != V2 {
        return Err("compressed histogram does not hold a V2 histogram".into());
    }
    let payload = be32(&plain, 4)? as usize;
    if payload > plain.len().saturating_sub(HEADER) {
        return Err(format!(
            "payload length {payload} beyond the {} bytes present",
            plain.len()
        ));
    }
    let digits = be32(&plain, 12)?;
    let (lowest, highest) = (be64(&plain, 16)?, be64(&plain, 24)?);
    // chunkrt's logs: 1 ns .. 60 s at 3 digits; anything far beyond is not a latency log
    if !(1..=3).contains(&digits) || lowest == 0 || highest > 1 << 42 || highest < 2 * lowest {
        return Err(format!(
            "range {lowest}..{highest} at {digits} significant digits is not a latency histogram"
        ));
    }
    Ok(plain)
}

/// Reads an interval log; intervals with the same tag are added into one series (untagged
/// intervals form the series named after the file). Series keep the order of first appearance.
pub fn read_interval_log(path: &Path) -> Result<Vec<Series>, ReportError> {
    let bad = |reason: String| ReportError::BadLog {
        path: path.to_path_buf(),
        reason,
    };
    let len = std::fs::metadata(path).map_err(io_err(path))?.len();
    if len > MAX_LOG_BYTES {
        return Err(bad(format!(
            "{len} bytes; logs of more than {MAX_LOG_BYTES} bytes are not read"
        )));
    }
    let bytes = std::fs::read(path).map_err(io_err(path))?;
    let default_name = path
        .file_stem()
        .map(|s| s.to_string_lossy().into_owned())
        .unwrap_or_else(|| "series".to_string());
    let mut out: Vec<Series> = Vec::new();
    let mut de = Deserializer::new();
    for entry in IntervalLogIterator::new(&bytes) {
        let entry = entry.map_err(|e| bad(format!("{e:?}")))?;
        let LogEntry::Interval(iv) = entry else {
            continue;
        };
        let name = iv
            .tag()
            .map(|t| t.as_str().to_string())
            .unwrap_or_else(|| default_name.clone());
        let raw = base64_decode(iv.encoded_histogram())
            .ok_or_else(|| bad(format!("series '{name}': invalid base64")))?;
        let raw = checked_histogram(&raw).map_err(|e| bad(format!("series '{name}': {e}")))?;
        let h: Histogram<u64> = de
            .deserialize(&mut std::io::Cursor::new(raw))
            .map_err(|e| bad(format!("series '{name}': {e:?}")))?;
        match out.iter_mut().find(|s| s.name == name) {
            Some(s) => s
                .hist
                .add(&h)
                .map_err(|e| bad(format!("series '{name}': {e:?}")))?,
            None => {
                let mut acc = latency_histogram();
                acc.add(&h)
                    .map_err(|e| bad(format!("series '{name}': {e:?}")))?;
                out.push(Series::new(name, acc));
            }
        }
    }
    Ok(out)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn crafted_histograms_are_refused_before_anything_is_sized() {
        use hdrhistogram::serialization::{Serializer, V2Serializer};
        use std::io::Write;
        let h = hist([1_000, 2_000, 50_000]);
        let mut plain = Vec::new();
        V2Serializer::new().serialize(&h, &mut plain).unwrap();
        let mut packed = Vec::new();
        V2DeflateSerializer::new()
            .serialize(&h, &mut packed)
            .unwrap();
        assert_eq!(checked_histogram(&plain).unwrap(), plain);
        assert_eq!(checked_histogram(&packed).unwrap(), plain);
        // a payload length of 4 GB in 1.6 KB (it made `report` allocate 4.2 GB)
        let mut huge = plain.clone();
        huge[4..8].copy_from_slice(&u32::MAX.to_be_bytes());
        let e = checked_histogram(&huge).unwrap_err();
        assert!(e.contains("payload length"), "{e}");
        // the same inside the compressed encoding
        let mut z = flate2::write::ZlibEncoder::new(Vec::new(), flate2::Compression::default());
        z.write_all(&huge).unwrap();
        let z = z.finish().unwrap();
        let mut crafted = packed[0..4].to_vec();
        crafted.extend((z.len() as u32).to_be_bytes());
        crafted.extend(z);
        assert!(checked_histogram(&crafted)
            .unwrap_err()
            .contains("payload length"));
        // a range no latency log has
        let mut wide = plain.clone();
        wide[24..32].copy_from_slice(&u64::MAX.to_be_bytes());
        assert!(checked_histogram(&wide).is_err());
        // a compressed length beyond the data, garbage, truncation
        let mut short = packed.clone();
        short[4..8].copy_from_slice(&u32::MAX.to_be_bytes());
        assert!(checked_histogram(&short).is_err());
        assert!(checked_histogram(&[1, 2, 3]).is_err());
        assert!(checked_histogram(&plain[..20]).is_err());
    }

    fn hist(values: impl IntoIterator<Item = u64>) -> Histogram<u64> {
        let mut h = latency_histogram();
        for v in values {
            h.saturating_record(v);
        }
        h
    }

    #[test]
    fn base64_roundtrip_known() {
        assert_eq!(base64_decode("aGVsbG8=").as_deref(), Some(&b"hello"[..]));
        assert_eq!(base64_decode("aGk").as_deref(), Some(&b"hi"[..]));
        assert_eq!(base64_decode("a!b="), None);
    }

    #[test]
    fn table_percentiles() {
        let h = hist(1..=1000u64);
        let t = LatencyTable::from_series("t", &[Series::new("a", h)]);
        let r = t.row("a").expect("row a was pushed");
        assert_eq!(r.count, 1000);
        assert!((r.p50_ns as i64 - 500).abs() <= 1, "{r:?}");
        assert!((r.p99_ns as i64 - 990).abs() <= 1, "{r:?}");
        assert_eq!(r.max_ns, 1000);
        let md = t.to_markdown();
        assert!(md.contains("| a | 1000 |"), "{md}");
        assert!(t.to_string().contains("p99.9 µs"));
    }
}
