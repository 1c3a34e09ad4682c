//! `chunkrt eval --switch-plot D`: the executor's target and the command around a chunk switch,
//! one panel per strategy, on the same held-out episode at delay D (`switch.png`), with each
//! strategy's jump at the switch and the command's largest lag behind the target after it.

use std::path::Path;

use anyhow::Context;

use super::{held_out_episodes, EVAL_SCENE_BASE};
use crate::task::sim::{run_episode, Recording, SimSettings};
use crate::task::TASK_DOF;
use chunkrt_controller::config::Config;
use chunkrt_controller::inference::PolicySource;

/// Window drawn around the switch (s): before, after.
const WINDOW: (f64, f64) = (0.15, 0.35);

/// The command is settled on the target before a switch when within this (rad).
const SETTLED: f64 = 0.02;

/// One strategy's episode around a chunk switch.
struct Panel {
    strategy: String,
    /// When the switch took effect (s).
    at: f64,
    /// (time relative to the switch in ms, target, command) inside the window.
    ticks: Vec<(f64, [f64; TASK_DOF], [f64; TASK_DOF])>,
}

impl Panel {
    fn from(strategy: &str, rec: &Recording) -> anyhow::Result<Self> {
        // the first switch the command meets settled on the target (the first chunk starts
        // from wherever the robot stood, and the command is still closing that gap at first)
        let settled = |at: f64| {
            rec.ticks
                .iter()
                .filter(|(t, _, _)| *t >= at - 0.05 && *t < at)
                .all(|(_, a, c)| (0..TASK_DOF).all(|j| (a[j] - c[j]).abs() < SETTLED))
        };
        let at = rec
            .switches
            .iter()
            .copied()
            .find(|&at| settled(at))
            .or(rec.switches.last().copied())
            .with_context(|| format!("{strategy}: no chunk switch in the episode"))?;
        let ticks = rec
            .ticks
            .iter()
            .filter(|(t, _, _)| *t >= at - WINDOW.0 && *t <= at + WINDOW.1)
            .map(|&(t, a, c)| ((t - at) * 1e3, a, c))
            .collect();
        Ok(Self {
            strategy: strategy.to_string(),
            at,
            ticks,
        })
    }

    /// Largest change of the target from the tick before the switch to the tick of it (rad).
    fn jump(&self) -> f64 {
        let before = self.ticks.iter().rev().find(|(t, _, _)| *t < 0.0);
        let at = self.ticks.iter().find(|(t, _, _)| *t >= 0.0);
        match (before, at) {
            (Some((_, a, _)), Some((_, b, _))) => (0..TASK_DOF)
                .map(|j| (a[j] - b[j]).abs())
                .fold(0.0, f64::max),
            _ => f64::NAN,
        }
    }

    /// Largest |command − target| after the switch, over the window (rad).
    fn lag(&self) -> f64 {
        self.ticks
            .iter()
            .filter(|(t, _, _)| *t >= 0.0)
            .flat_map(|(_, a, c)| (0..TASK_DOF).map(move |j| (a[j] - c[j]).abs()))
            .fold(0.0, f64::max)
    }
}

/// Runs the first held-out episode of the sweep at `delay` once per strategy (`sync` left out:
/// it never switches mid-motion), draws `path`, and returns one summary line per strategy.
pub fn switch_plot(
    cfg: &Config,
    delay: u64,
    strategies: &[String],
    path: &Path,
) -> anyhow::Result<Vec<String>> {
    let spec = held_out_episodes(cfg, EVAL_SCENE_BASE, 1, 0xe7a1)
        .into_iter()
        .next()
        .context("no held-out episode")?;
    let mut policy = PolicySource::load(cfg)?;
    let mut panels = Vec::new();
    for s in strategies.iter().filter(|s| s.as_str() != "sync") {
        let (c, _) = super::cell_config(cfg, s, delay)?;
        let settings = SimSettings {
            delay_steps: delay,
            max_seconds: 8.0,
            synchronous: false,
            record: true,
            retarget_at: None,
            drift: None,
        };
        let out = run_episode(&c, &mut policy, &spec, &settings)?;
        let rec = out.recording.context("the episode was recorded")?;
        panels.push(Panel::from(s, &rec)?);
    }
    anyhow::ensure!(
        !panels.is_empty(),
        "--switch-plot needs an asynchronous strategy"
    );
    // the joint that moves most around the switches
    let range = |j: usize| {
        panels
            .iter()
            .map(|p| {
                let v = p.ticks.iter().map(|(_, a, _)| a[j]);
                v.clone().fold(f64::MIN, f64::max) - v.fold(f64::MAX, f64::min)
            })
            .sum::<f64>()
    };
    let joint = (0..TASK_DOF)
        .max_by(|&a, &b| range(a).total_cmp(&range(b)))
        .unwrap_or(0);
    draw(path, &panels, joint, delay)?;
    Ok(panels
        .iter()
        .map(|p| {
            format!(
                "{:<18} switch at {:.3} s: target jump {:.4} rad, command's largest lag after it {:.4} rad",
                p.strategy,
                p.at,
                p.jump(),
                p.lag()
            )
        })
        .collect())
}

fn draw(path: &Path, panels: &[Panel], joint: usize, delay: u64) -> anyhow::Result<()> {
    use plotters::prelude::*;
    let err = |e: &dyn std::fmt::Display| anyhow::anyhow!("plot {}: {e}", path.display());
    let root = BitMapBackend::new(path, (380 * panels.len() as u32, 420)).into_drawing_area();
    root.fill(&WHITE).map_err(|e| err(&e))?;
    let areas = root.split_evenly((1, panels.len()));
    for (p, area) in panels.iter().zip(areas.iter()) {
        let ys = p.ticks.iter().flat_map(|(_, a, c)| [a[joint], c[joint]]);
        let (lo, hi) = ys.fold((f64::MAX, f64::MIN), |(l, h), v| (l.min(v), h.max(v)));
        let pad = ((hi - lo) * 0.1).max(1e-3);
        let mut chart = ChartBuilder::on(area)
            .caption(
                format!("{} (delay {delay}, joint {joint})", p.strategy),
                ("sans-serif", 16),
            )
            .margin(8)
            .x_label_area_size(36)
            .y_label_area_size(56)
            .build_cartesian_2d(-WINDOW.0 * 1e3..WINDOW.1 * 1e3, (lo - pad)..(hi + pad))
            .map_err(|e| err(&e))?;
        chart
            .configure_mesh()
            .x_labels(6)
            .x_desc("ms from the switch")
            .y_desc("rad")
            .draw()
            .map_err(|e| err(&e))?;
        chart
            .draw_series(LineSeries::new(
                p.ticks.iter().map(|(t, a, _)| (*t, a[joint])),
                BLUE.stroke_width(2),
            ))
            .map_err(|e| err(&e))?
            .label("target")
            .legend(|(x, y)| PathElement::new([(x, y), (x + 16, y)], BLUE));
        chart
            .draw_series(LineSeries::new(
                p.ticks.iter().map(|(t, _, c)| (*t, c[joint])),
                RED,
            ))
            .map_err(|e| err(&e))?
            .label("command")
            .legend(|(x, y)| PathElement::new([(x, y), (x + 16, y)], RED));
        chart
            .draw_series(LineSeries::new(
                [(0.0, lo - pad), (0.0, hi + pad)],
                BLACK.mix(0.3),
            ))
            .map_err(|e| err(&e))?;
        chart
            .configure_series_labels()
            .border_style(BLACK.mix(0.3))
            .background_style(WHITE.mix(0.8))
            .draw()
            .map_err(|e| err(&e))?;
    }
    root.present().map_err(|e| err(&e))?;
    Ok(())
}
