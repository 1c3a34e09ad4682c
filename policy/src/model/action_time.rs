//! π0's action-time MLP on the inference path: `mlp_out(swish(mlp_in([a, te])))` over the
//! action tokens `a` and the time embedding `te`, split so a denoising step does not redo the
//! time's half. `mlp_in([a, te]) = a · W_aᵀ + (te · W_tᵀ + b_in)`: the bracket depends on the
//! flow time only and is made once per time with the other time features; the action half and
//! `mlp_out` are packed products on the CPU. A trainable model keeps the concatenation.

use candle_core::{Result, Tensor};
use candle_nn::Linear;

use crate::ops;
use crate::packed::{PackedRhs, Precision};

/// The split weights of π0's `action_time_mlp_in` / `action_time_mlp_out` (f32, as openpi
/// keeps them).
#[derive(Debug, Clone)]
pub(super) struct ActionTimeMlp {
    /// The action half of `mlp_in` as [K, N] = W_aᵀ [We, We], and its packing (CPU).
    wa: Tensor,
    pa: Option<PackedRhs>,
    /// The time half of `mlp_in` [O, K] = W_t [We, We], and `mlp_in`'s bias [We].
    wt: Tensor,
    b_in: Tensor,
    /// `mlp_out` [O, K], its bias, and both packed together (CPU).
    w_out: Tensor,
    b_out: Tensor,
    p_out: Option<PackedRhs>,
}

impl ActionTimeMlp {
    /// The split of `mlp_in` [We, 2 We] / `mlp_out` [We, We]; `None` when the weights are
    /// trainable variables (copies would not follow the optimiser) or have no bias.
    pub(super) fn new(mlp_in: &Linear, mlp_out: &Linear) -> Result<Option<Self>> {
        let (w_in, w_out) = (mlp_in.weight(), mlp_out.weight());
        let (Some(b_in), Some(b_out)) = (mlp_in.bias(), mlp_out.bias()) else {
            return Ok(None);
        };
        if w_in.is_variable() || w_out.is_variable() {
            return Ok(None);
        }
        let we = w_out.dim(0)?;
        if w_in.dims() != [we, 2 * we] {
            candle_core::bail!("action_time_mlp_in {:?} for width {we}", w_in.dims());
        }
        let wa = w_in.narrow(1, 0, we)?.t()?.contiguous()?;
        let pa = PackedRhs::pack(&wa, Precision::F32)?;
        let p_out = PackedRhs::pack_weight(w_out, Precision::F32)?
            .map(|p| b_out.to_vec1::<f32>().map(|b| p.with_bias(b)))
            .transpose()?;
        Ok(Some(ActionTimeMlp {
            wa,
            pa,
            wt: w_in.narrow(1, we, we)?.contiguous()?,
            b_in: b_in.clone(),
            w_out: w_out.clone(),
            b_out: b_out.clone(),
            p_out,
        }))
    }

    /// `te · W_tᵀ + b_in` for a time embedding [B, We] or [B, H, We] (same shape out).
    pub(super) fn time_term(&self, te: &Tensor) -> Result<Tensor> {
        ops::linear(te, &self.wt, &self.b_in)
    }

    /// The MLP over action tokens `a` [B, H, We] with the time term `tt` of
    /// [`Self::time_term`] ([B, We] or [B, H, We]). Returns [B, H, We].
    pub(super) fn forward(&self, a: &Tensor, tt: &Tensor) -> Result<Tensor> {
        let tt = if tt.rank() == 2 {
            tt.unsqueeze(1)?
        } else {
            tt.clone()
        };
        let h = ops::matmul(a, &self.wa, self.pa.as_ref())?
            .broadcast_add(&tt)?
            .silu()?;
        ops::dense(
            &h,
            &self.w_out,
            &self.b_out,
            self.p_out.as_ref(),
            false,
            None,
        )
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use candle_core::{Device, Module};

    /// The split MLP equals the concatenated one, for a time per batch row and per token, on
    /// the packed products and on candle's (packing off); a trainable model keeps the original.
    #[test]
    fn split_equals_the_concatenated_mlp() {
        let dev = Device::Cpu;
        let (b, h, we) = (2, 7, 24);
        let r = |s: &[usize]| Tensor::randn(0f32, 1.0, s, &dev).expect("randn");
        let mlp_in = Linear::new(r(&[we, 2 * we]), Some(r(&[we])));
        let mlp_out = Linear::new(r(&[we, we]), Some(r(&[we])));
        let full = |a: &Tensor, te: &Tensor| -> Tensor {
            let at = Tensor::cat(&[a, te], 2).expect("cat");
            let h = mlp_in.forward(&at).expect("in").silu().expect("silu");
            mlp_out.forward(&h).expect("out")
        };
        let a = r(&[b, h, we]);
        let te_row = r(&[b, we]);
        let te_tok = r(&[b, h, we]);
        let split = ActionTimeMlp::new(&mlp_in, &mlp_out)
            .expect("split")
            .expect("not trainable");
        // the packed products (where this CPU has them) and candle's (another device's path)
        let unpacked = ActionTimeMlp {
            pa: None,
            p_out: None,
            ..split.clone()
        };
        for (packed, mlp) in [(true, &split), (false, &unpacked)] {
            for te in [&te_row, &te_tok] {
                let wide = te
                    .unsqueeze(1)
                    .and_then(|t| t.broadcast_as((b, h, we)))
                    .and_then(|t| t.contiguous());
                let te_full = if te.rank() == 2 {
                    wide.expect("broadcast")
                } else {
                    te.clone()
                };
                let want = full(&a, &te_full);
                let tt = mlp.time_term(te).expect("time term");
                let got = mlp.forward(&a, &tt).expect("forward");
                let d = (got - want)
                    .and_then(|d| d.abs())
                    .and_then(|d| d.max_all())
                    .and_then(|d| d.to_scalar::<f32>())
                    .expect("diff");
                assert!(d < 1e-4, "packed {packed}, te {:?}: {d}", te.dims());
            }
        }
        let var = candle_core::Var::from_tensor(mlp_in.weight()).expect("var");
        let trainable = Linear::new(var.as_tensor().clone(), mlp_in.bias().cloned());
        assert!(ActionTimeMlp::new(&trainable, &mlp_out)
            .expect("split")
            .is_none());
    }
}
