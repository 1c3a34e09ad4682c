//! Flow times of the action tokens: one per batch row, or per token with a committed prefix
//! (training-time RTC), the sinusoidal time embedding, and the mask of the tokens left to
//! generate.

use candle_core::{Device, Tensor};

/// The flow times of the action tokens: `t[b]` for every token of batch row b, except (with
/// `committed`, training-time real-time chunking) the first `committed[b]` tokens of the row,
/// which are clean actions at flow time 0.
#[derive(Debug, Clone, Copy)]
pub struct FlowTimes<'a> {
    /// Time per batch row [B].
    pub t: &'a [f32],
    /// Committed (clean) action tokens per batch row [B], or none.
    pub committed: Option<&'a [usize]>,
}

impl<'a> FlowTimes<'a> {
    /// One time per batch row, no committed prefix.
    pub fn new(t: &'a [f32]) -> Self {
        Self { t, committed: None }
    }
}

impl<'a> From<&'a [f32]> for FlowTimes<'a> {
    fn from(t: &'a [f32]) -> Self {
        Self::new(t)
    }
}

impl<'a> From<&'a Vec<f32>> for FlowTimes<'a> {
    fn from(t: &'a Vec<f32>) -> Self {
        Self::new(t)
    }
}

impl<'a, const N: usize> From<&'a [f32; N]> for FlowTimes<'a> {
    fn from(t: &'a [f32; N]) -> Self {
        Self::new(t)
    }
}

/// The tokens a committed prefix leaves to generate: [B, H, 1] f32, 0 on the first
/// `committed[b]` action tokens of row b (given, at flow time 0), 1 on the others.
pub(crate) fn free_mask(
    committed: &[usize],
    h: usize,
    dev: &Device,
) -> candle_core::Result<Tensor> {
    let b = committed.len();
    let f: Vec<f32> = (0..b * h)
        .map(|i| if i % h < committed[i / h] { 0.0 } else { 1.0 })
        .collect();
    Tensor::from_vec(f, (b, h, 1), dev)
}

/// Sinusoidal time embedding [B, W] (sin half then cos half), computed in f64 like openpi's
/// PyTorch reference, then cast to f32.
pub fn time_embedding(
    t: &[f32],
    width: usize,
    min_period: f64,
    max_period: f64,
    dev: &Device,
) -> candle_core::Result<Tensor> {
    let half = width / 2;
    let mut out = Vec::with_capacity(t.len() * width);
    for &ti in t {
        let mut sin = Vec::with_capacity(half);
        let mut cos = Vec::with_capacity(half);
        for i in 0..half {
            let frac = if half > 1 {
                i as f64 / (half - 1) as f64
            } else {
                0.0
            };
            let period = min_period * (max_period / min_period).powf(frac);
            let x = (1.0 / period * 2.0 * std::f64::consts::PI) * ti as f64;
            sin.push(x.sin() as f32);
            cos.push(x.cos() as f32);
        }
        out.extend(sin);
        out.extend(cos);
    }
    Tensor::from_vec(out, (t.len(), width), dev)
}
