//! openpi's attention masks: the 2-D mask from padding and autoregressive flags, and its additive
//! bias.

use candle_core::{Device, Tensor};

use crate::gemma::MASK_VALUE;

/// Additive bias from a boolean mask: 0 where visible, [`MASK_VALUE`] elsewhere (f32: scores
/// are masked and normalised in f32 whatever the model's dtype).
pub(crate) fn bias_tensor(
    vis: Vec<bool>,
    shape: (usize, usize, usize, usize),
    dev: &Device,
) -> candle_core::Result<Tensor> {
    let v: Vec<f32> = vis
        .into_iter()
        .map(|b| if b { 0.0 } else { MASK_VALUE })
        .collect();
    Tensor::from_vec(v, shape, dev)
}

/// openpi `make_att_2d_masks`: query i sees key j iff `cum[j] <= cum[i]` and both are valid.
pub fn att_2d_mask(pad: &[bool], ar: &[bool]) -> Vec<bool> {
    let n = pad.len();
    let mut cum = Vec::with_capacity(n);
    let mut c = 0u32;
    for &a in ar {
        c += a as u32;
        cum.push(c);
    }
    let mut m = Vec::with_capacity(n * n);
    for i in 0..n {
        for j in 0..n {
            m.push(cum[j] <= cum[i] && pad[i] && pad[j]);
        }
    }
    m
}
