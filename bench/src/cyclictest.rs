//! `cyclictest` (Debian's rt-tests) as the platform's floor: the wake-up latency of a thread
//! that does nothing but sleep to absolute deadlines, on the same core, at the same rate.

use std::process::Command;

use hdrhistogram::Histogram;

use super::BenchError;
use crate::report::latency_histogram;

/// How to run cyclictest.
#[derive(Debug, Clone)]
pub struct CyclictestConfig {
    /// Wake-up interval (µs).
    pub interval_us: u64,
    /// Number of wake-ups.
    pub loops: u64,
    /// Core to pin to.
    pub core: Option<usize>,
    /// SCHED_FIFO priority (None: SCHED_OTHER).
    pub priority: Option<i32>,
    /// Histogram range (µs); later wake-ups count as overflows.
    pub hist_max_us: u64,
}

/// What cyclictest measured.
#[derive(Debug, Clone)]
pub struct CyclictestResult {
    /// Latencies (ns; cyclictest resolves 1 µs). Overflows are recorded at the reported maximum.
    pub latency: Histogram<u64>,
    /// Wake-ups later than `hist_max_us`.
    pub overflows: u64,
    /// Reported maximum (µs).
    pub max_us: u64,
    /// The command line that ran.
    pub command: String,
}

/// True when `cyclictest` can be started.
pub fn available() -> bool {
    Command::new("cyclictest")
        .arg("--help")
        .output()
        .map(|o| !o.stdout.is_empty() || !o.stderr.is_empty())
        .unwrap_or(false)
}

/// Runs cyclictest (one thread, `-q`, histogram output) and parses its histogram.
pub fn run(cfg: &CyclictestConfig) -> Result<CyclictestResult, BenchError> {
    let mut cmd = Command::new("cyclictest");
    cmd.args(["-q", "-t1"])
        .arg(format!("-i{}", cfg.interval_us))
        .arg(format!("-l{}", cfg.loops))
        .arg(format!("-h{}", cfg.hist_max_us));
    if let Some(c) = cfg.core {
        cmd.arg(format!("-a{c}"));
    }
    if let Some(p) = cfg.priority {
        cmd.arg(format!("-p{p}"));
    }
    let command = format!("{cmd:?}").replace('"', "");
    let out = cmd.output().map_err(|e| BenchError::Process {
        what: "cyclictest".into(),
        reason: e.to_string(),
    })?;
    if !out.status.success() {
        return Err(BenchError::Process {
            what: command,
            reason: format!(
                "exited with {}: {}",
                out.status,
                String::from_utf8_lossy(&out.stderr).trim()
            ),
        });
    }
    let mut r = parse(&String::from_utf8_lossy(&out.stdout))?;
    r.command = command;
    Ok(r)
}

/// Parses cyclictest's `-h` output: `NNNNNN CCCCCC` histogram lines (µs, count), then
/// `# Max Latencies:` and `# Histogram Overflows:` summary lines.
pub fn parse(text: &str) -> Result<CyclictestResult, BenchError> {
    let bad = |reason: String| BenchError::Parse {
        what: "cyclictest output",
        reason,
    };
    let mut latency = latency_histogram();
    let mut overflows = None;
    let mut max_us = None;
    let mut buckets = 0;
    for line in text.lines() {
        let line = line.trim();
        if let Some(rest) = line.strip_prefix("# Max Latencies:") {
            max_us = rest.split_whitespace().next().and_then(|v| v.parse().ok());
        } else if let Some(rest) = line.strip_prefix("# Histogram Overflows:") {
            overflows = rest.split_whitespace().next().and_then(|v| v.parse().ok());
        } else if !line.starts_with('#') && !line.is_empty() {
            let mut it = line.split_whitespace();
            let (Some(us), Some(count)) = (it.next(), it.next()) else {
                continue;
            };
            let (Ok(us), Ok(count)) = (us.parse::<u64>(), count.parse::<u64>()) else {
                continue;
            };
            buckets += 1;
            if count > 0 {
                latency.saturating_record_n(us * 1000, count);
            }
        }
    }
    let max_us: u64 = max_us.ok_or_else(|| bad("no '# Max Latencies' line".into()))?;
    let overflows: u64 = overflows.unwrap_or(0);
    if buckets == 0 {
        return Err(bad("no histogram lines (was -h given?)".into()));
    }
    if overflows > 0 {
        latency.saturating_record_n(max_us * 1000, overflows);
    }
    Ok(CyclictestResult {
        latency,
        overflows,
        max_us,
        command: String::new(),
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn parses_histogram_output() {
        let text = "# /dev/cpu_dma_latency set to 0us\n# Histogram\n000000 000000\n\
                    000003 000090\n000010 000008\n# Total: 000000100\n# Min Latencies: 00003\n\
                    # Avg Latencies: 00004\n# Max Latencies: 00250\n# Histogram Overflows: 00002\n";
        let r = parse(text).expect("valid output");
        assert_eq!(r.latency.len(), 100);
        assert_eq!(r.overflows, 2);
        assert_eq!(r.max_us, 250);
        assert!(
            r.latency.value_at_quantile(0.5) >= 3000 && r.latency.value_at_quantile(0.5) < 3010
        );
        assert!(r.latency.max() >= 250_000);
        assert!(parse("garbage").is_err());
    }
}
