//! The sweep's results: per-cell statistics (success with its 95 % Wilson interval, time to
//! target, switch jumps, jerk, reaction), the per-episode rows, the Markdown table and the plot.
//! Owns no simulation: `super::sweep` fills these from `task::sim` outcomes.

use std::path::Path;

use crate::task::sim::{EpisodeOutcome, EpisodeSpec};

/// One cell of the sweep.
#[derive(Debug, Clone, PartialEq)]
pub struct Cell {
    pub strategy: String,
    pub delay: u64,
    pub episodes: usize,
    pub successes: usize,
    /// 95 % Wilson interval of the success rate.
    pub ci: (f64, f64),
    /// Mean time to target of the successes (s; NaN when none).
    pub time_to_target: f64,
    /// Largest target jump at a chunk switch over the cell's episodes (rad).
    pub max_jump: f64,
    /// 90th percentile over the cell's episodes of each episode's largest switch jump (rad): the
    /// maximum over 30 episodes is one episode's outlier; this is the typical bad case.
    pub p90_jump: f64,
    /// Mean over episodes of the command's RMS jerk (rad/s³).
    pub rms_jerk: f64,
    /// Mean share of ticks in HOLD.
    pub hold_ticks: f64,
    /// Dynamic variant: mean reaction time of the episodes that reacted (s; NaN: static task or
    /// none reacted), and how many reacted.
    pub reaction_time: f64,
    pub reacted: usize,
    /// The cell ran the dynamic variant.
    pub dynamic: bool,
}

impl Cell {
    /// Success rate.
    pub fn rate(&self) -> f64 {
        self.successes as f64 / self.episodes.max(1) as f64
    }
}

/// The mean of `v`; NaN when empty.
fn mean(v: impl Iterator<Item = f64>) -> f64 {
    let (sum, n) = v.fold((0.0, 0usize), |(s, n), x| (s + x, n + 1));
    if n == 0 {
        f64::NAN
    } else {
        sum / n as f64
    }
}

/// The 90th percentile (nearest rank) of `v`; 0 when empty.
pub fn p90(v: impl Iterator<Item = f64>) -> f64 {
    let mut v: Vec<f64> = v.collect();
    if v.is_empty() {
        return 0.0;
    }
    v.sort_by(f64::total_cmp);
    v[((0.9 * v.len() as f64).ceil() as usize).clamp(1, v.len()) - 1]
}

/// 95 % Wilson score interval of `k` successes in `n` trials.
pub fn wilson(k: usize, n: usize) -> (f64, f64) {
    if n == 0 {
        return (0.0, 1.0);
    }
    let (n, p, z) = (n as f64, k as f64 / n as f64, 1.96f64);
    let den = 1.0 + z * z / n;
    let centre = (p + z * z / (2.0 * n)) / den;
    let half = z * (p * (1.0 - p) / n + z * z / (4.0 * n * n)).sqrt() / den;
    ((centre - half).max(0.0), (centre + half).min(1.0))
}

pub(super) fn summarise(
    strategy: &str,
    delay: u64,
    outs: &[EpisodeOutcome],
    dynamic: bool,
) -> Cell {
    let n = outs.len();
    let k = outs.iter().filter(|o| o.success).count();
    let t: Vec<f64> = outs.iter().filter_map(|o| o.time_to_target).collect();
    Cell {
        strategy: strategy.to_string(),
        delay,
        episodes: n,
        successes: k,
        ci: wilson(k, n),
        time_to_target: if t.is_empty() {
            f64::NAN
        } else {
            t.iter().sum::<f64>() / t.len() as f64
        },
        max_jump: outs
            .iter()
            .map(|o| o.smoothness.max_switch_jump_target)
            .fold(0.0, f64::max),
        p90_jump: p90(outs.iter().map(|o| o.smoothness.max_switch_jump_target)),
        rms_jerk: outs.iter().map(|o| o.smoothness.rms_jerk).sum::<f64>() / n.max(1) as f64,
        hold_ticks: outs.iter().map(|o| o.hold_ticks as f64).sum::<f64>() / n.max(1) as f64,
        reaction_time: mean(outs.iter().filter_map(|o| o.reaction_time)),
        reacted: outs.iter().filter(|o| o.reaction_time.is_some()).count(),
        dynamic,
    }
}

/// One episode of a sweep, for `episodes.csv`.
#[derive(Debug, Clone, PartialEq)]
pub struct EpisodeRow {
    pub strategy: String,
    pub delay: u64,
    pub spec: EpisodeSpec,
    pub outcome: EpisodeOutcome,
    /// What the SO-101's physics showed (None: the reach task).
    pub physics: Option<crate::task::so101::Physics>,
}

/// The SO-101 sweep's physics per cell, as Markdown: how far the servos trail the command,
/// how the jaw behaves through chunk switches, how often the block was lifted, and the block's
/// closest approach to the goal once lifted.
pub fn so101_physics(cells: &[Cell], rows: &[EpisodeRow]) -> String {
    let mut s = String::from(
        "| strategy | delay (steps) | lifted | tracking p50 / p99 / max (rad) | jaw closes / opens per episode | jaw flips ≤ 100 ms after a switch | closest to goal once lifted, median (m) |\n|---|---|---|---|---|---|---|\n",
    );
    for c in cells {
        let ps: Vec<(&EpisodeOutcome, crate::task::so101::Physics)> = rows
            .iter()
            .filter(|r| r.strategy == c.strategy && r.delay == c.delay)
            .filter_map(|r| r.physics.map(|p| (&r.outcome, p)))
            .collect();
        let n = ps.len().max(1) as f64;
        let avg = |f: &dyn Fn(&crate::task::so101::Physics) -> f64| {
            ps.iter().map(|(_, p)| f(p)).sum::<f64>() / n
        };
        let mut close: Vec<f64> = ps
            .iter()
            .map(|(o, _)| o.min_distance)
            .filter(|d| d.is_finite())
            .collect();
        close.sort_by(f64::total_cmp);
        let median = close.get(close.len() / 2).copied().unwrap_or(f64::NAN);
        s.push_str(&format!(
            "| {} | {} | {}/{} | {:.3} / {:.3} / {:.3} | {:.1} / {:.1} | {} | {:.3} |\n",
            c.strategy,
            c.delay,
            ps.iter().filter(|(_, p)| p.carried).count(),
            ps.len(),
            avg(&|p| p.tracking_p50),
            avg(&|p| p.tracking_p99),
            ps.iter().map(|(_, p)| p.tracking_max).fold(0.0, f64::max),
            avg(&|p| p.jaw_closes as f64),
            avg(&|p| p.jaw_opens as f64),
            ps.iter().map(|(_, p)| p.jaw_flips_at_switch).sum::<usize>(),
            median
        ));
    }
    s
}

/// The Markdown table of a sweep.
pub fn markdown(cells: &[Cell]) -> String {
    // the dynamic variant adds the reaction to the retarget
    let dynamic = cells.iter().any(|c| c.dynamic);
    let mut s = String::from(
        "| strategy | delay (steps) | success | 95 % CI | time to target (s) | max switch jump (rad) | p90 switch jump (rad) | RMS jerk (rad/s³) |",
    );
    s.push_str(if dynamic {
        " reaction (s) |\n|---|---:|---:|---|---:|---:|---:|---:|---:|\n"
    } else {
        "\n|---|---:|---:|---|---:|---:|---:|---:|\n"
    });
    for c in cells {
        s.push_str(&format!(
            "| {} | {} | {}/{} ({:.0} %) | {:.0}–{:.0} % | {:.2} | {:.4} | {:.4} | {:.0} |",
            c.strategy,
            c.delay,
            c.successes,
            c.episodes,
            100.0 * c.rate(),
            100.0 * c.ci.0,
            100.0 * c.ci.1,
            c.time_to_target,
            c.max_jump,
            c.p90_jump,
            c.rms_jerk
        ));
        if dynamic {
            s.push_str(&format!(
                " {:.3} ({}/{}) |",
                c.reaction_time, c.reacted, c.episodes
            ));
        }
        s.push('\n');
    }
    s
}

/// Success rate (with the 95 % intervals), time to target and max switch jump against the delay,
/// one line per strategy.
pub fn plot(path: &Path, cells: &[Cell]) -> anyhow::Result<()> {
    use plotters::prelude::*;
    let strategies: Vec<&str> = {
        let mut v: Vec<&str> = Vec::new();
        for c in cells {
            if !v.contains(&c.strategy.as_str()) {
                v.push(&c.strategy);
            }
        }
        v
    };
    let dmax = cells.iter().map(|c| c.delay).max().unwrap_or(1).max(1) as f64;
    let jmax = cells.iter().map(|c| c.max_jump).fold(1e-3, f64::max) * 1.1;
    let tmax = cells
        .iter()
        .map(|c| c.time_to_target)
        .filter(|t| t.is_finite())
        .fold(0.1, f64::max)
        * 1.1;
    let root = BitMapBackend::new(path, (1500, 460)).into_drawing_area();
    root.fill(&WHITE)?;
    let panels = root.split_evenly((1, 3));
    let (left, middle, right) = (&panels[0], &panels[1], &panels[2]);
    let err = |e: &dyn std::fmt::Display| anyhow::anyhow!("plot {}: {e}", path.display());
    let mut a = ChartBuilder::on(left)
        .caption("success rate vs inference delay", ("sans-serif", 18))
        .margin(10)
        .x_label_area_size(40)
        .y_label_area_size(50)
        .build_cartesian_2d(-0.3f64..dmax + 0.3, 0f64..1.05)
        .map_err(|e| err(&e))?;
    let int_ticks = |x: &f64| {
        if (x - x.round()).abs() < 1e-6 {
            format!("{:.0}", x)
        } else {
            String::new()
        }
    };
    a.configure_mesh()
        .x_label_formatter(&int_ticks)
        .x_desc("inference delay (action steps)")
        .y_desc("success rate (95 % CI)")
        .draw()
        .map_err(|e| err(&e))?;
    let mut m = ChartBuilder::on(middle)
        .caption("time to target (successes)", ("sans-serif", 18))
        .margin(10)
        .x_label_area_size(40)
        .y_label_area_size(50)
        .build_cartesian_2d(-0.3f64..dmax + 0.3, 0f64..tmax)
        .map_err(|e| err(&e))?;
    m.configure_mesh()
        .x_label_formatter(&int_ticks)
        .x_desc("inference delay (action steps)")
        .y_desc("s")
        .draw()
        .map_err(|e| err(&e))?;
    let mut b = ChartBuilder::on(right)
        .caption("largest target jump at a chunk switch", ("sans-serif", 18))
        .margin(10)
        .x_label_area_size(40)
        .y_label_area_size(60)
        .build_cartesian_2d(-0.3f64..dmax + 0.3, 0f64..jmax)
        .map_err(|e| err(&e))?;
    b.configure_mesh()
        .x_label_formatter(&int_ticks)
        .x_desc("inference delay (action steps)")
        .y_desc("rad")
        .draw()
        .map_err(|e| err(&e))?;
    let n = strategies.len().max(1) as f64;
    for (i, s) in strategies.iter().enumerate() {
        let color = Palette99::pick(i).to_rgba();
        // small horizontal offsets keep the error bars apart
        let dx = (i as f64 - (n - 1.0) / 2.0) * 0.06;
        let mine: Vec<&Cell> = cells.iter().filter(|c| c.strategy == *s).collect();
        a.draw_series(LineSeries::new(
            mine.iter().map(|c| (c.delay as f64 + dx, c.rate())),
            color.stroke_width(2),
        ))
        .map_err(|e| err(&e))?
        .label(*s)
        .legend(move |(x, y)| PathElement::new(vec![(x, y), (x + 20, y)], color.stroke_width(2)));
        a.draw_series(mine.iter().map(|c| {
            ErrorBar::new_vertical(
                c.delay as f64 + dx,
                c.ci.0,
                c.rate(),
                c.ci.1,
                color.stroke_width(1),
                6,
            )
        }))
        .map_err(|e| err(&e))?;
        let timed: Vec<&&Cell> = mine
            .iter()
            .filter(|c| c.time_to_target.is_finite())
            .collect();
        m.draw_series(LineSeries::new(
            timed.iter().map(|c| (c.delay as f64, c.time_to_target)),
            color.stroke_width(2),
        ))
        .map_err(|e| err(&e))?;
        m.draw_series(
            timed
                .iter()
                .map(|c| Circle::new((c.delay as f64, c.time_to_target), 3, color.filled())),
        )
        .map_err(|e| err(&e))?;
        b.draw_series(LineSeries::new(
            mine.iter().map(|c| (c.delay as f64, c.max_jump)),
            color.stroke_width(2),
        ))
        .map_err(|e| err(&e))?;
        b.draw_series(
            mine.iter()
                .map(|c| Circle::new((c.delay as f64, c.max_jump), 3, color.filled())),
        )
        .map_err(|e| err(&e))?;
    }
    a.configure_series_labels()
        .position(SeriesLabelPosition::LowerLeft)
        .background_style(WHITE.mix(0.85))
        .border_style(BLACK)
        .label_font(("sans-serif", 14))
        .margin(8)
        .draw()
        .map_err(|e| err(&e))?;
    root.present().map_err(|e| err(&e))?;
    Ok(())
}
