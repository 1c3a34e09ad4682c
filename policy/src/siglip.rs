//! SigLIP vision tower + PaliGemma multi-modal projector.
//!
//! The math and key names are openpi's (HF `SiglipVisionModel` without pooling head): a
//! non-overlapping conv patch embedding with bias, a learned position embedding, pre-LN encoder
//! layers (attention without mask, gelu-tanh MLP), `post_layernorm`, then the projector
//! `Linear(Dv -> W, bias)`. Image tokens are not scaled (openpi removes PaliGemma's `/ sqrt(W)`).
//!
//! Written out here rather than reused from `candle_transformers::models::siglip` for two
//! reasons: every op has a differentiable path (`diff`: compositions with a backward instead of
//! candle's fused layer-norm / softmax kernels) so the tower can be trained, and the inference
//! path runs the patch embedding as one matmul over flattened patches, the Q/K/V projections as
//! one fused matmul over all tokens of all images, and every op through [`ops`] (the device's
//! kernel, or candle's composition).
//!
//! Shapes: N images, S image size, p patch, g = S/p, T = g² tokens, Dv width, nH heads, hd head
//! dim, W the language model width.

use candle_core::{DType, Tensor, D};
use candle_nn::{Init, VarBuilder};

use super::config::VisionDims;
use super::ops;
use super::packed::{PackedRhs, Precision};

/// `x @ w^T + b` over the last dim, any leading dims (one 2-D matmul).
fn linear(x: &Tensor, w: &Tensor, b: &Tensor) -> candle_core::Result<Tensor> {
    let dims = x.dims().to_vec();
    let k = dims[dims.len() - 1];
    let rows: usize = dims[..dims.len() - 1].iter().product();
    let y = x.reshape((rows, k))?.matmul(&w.t()?)?.broadcast_add(b)?;
    let mut out = dims;
    let last = out.len() - 1;
    out[last] = w.dim(0)?;
    y.reshape(out)
}

/// LayerNorm weights.
#[derive(Debug, Clone)]
struct LayerNorm {
    w: Tensor,
    b: Tensor,
    eps: f64,
}

impl LayerNorm {
    fn new(d: usize, eps: f64, vb: VarBuilder) -> candle_core::Result<Self> {
        Ok(Self {
            w: vb.get_with_hints(d, "weight", Init::Const(1.0))?,
            b: vb.get_with_hints(d, "bias", Init::Const(0.0))?,
            eps,
        })
    }

    fn forward(&self, x: &Tensor, diff: bool) -> candle_core::Result<Tensor> {
        if diff {
            let mu = x.mean_keepdim(D::Minus1)?;
            let xc = x.broadcast_sub(&mu)?;
            let var = xc.sqr()?.mean_keepdim(D::Minus1)?;
            xc.broadcast_div(&(var + self.eps)?.sqrt()?)?
                .broadcast_mul(&self.w)?
                .broadcast_add(&self.b)
        } else {
            candle_nn::ops::layer_norm(&x.contiguous()?, &self.w, &self.b, self.eps as f32)
        }
    }
}

/// A dense layer's weight [out, in] and bias [out].
#[derive(Debug, Clone)]
struct Dense {
    w: Tensor,
    b: Tensor,
    /// `w` packed for [`PackedRhs`] (`Vision::pack`); inference only.
    packed: Option<PackedRhs>,
}

impl Dense {
    fn new(i: usize, o: usize, vb: VarBuilder) -> candle_core::Result<Self> {
        let l = candle_nn::linear(i, o, vb)?;
        let b = l
            .bias()
            .cloned()
            .ok_or_else(|| candle_core::Error::Msg("linear without bias".into()))?;
        Ok(Self {
            w: l.weight().clone(),
            b,
            packed: None,
        })
    }

    fn forward(&self, x: &Tensor) -> candle_core::Result<Tensor> {
        if let Some(p) = &self.packed {
            // the bias is fused into the packed product
            if let Some(y) = p.matmul(x)? {
                return Ok(y);
            }
        }
        linear(x, &self.w, &self.b)
    }

    /// `act(x · wᵀ + b) + residual` on the inference path ([`ops::dense`]).
    fn forward_infer(
        &self,
        x: &Tensor,
        gelu: bool,
        residual: Option<&Tensor>,
    ) -> candle_core::Result<Tensor> {
        ops::dense(x, &self.w, &self.b, self.packed.as_ref(), gelu, residual)
    }

    /// Packs `w` for `precision`; false (keeping the previous packing) where this CPU has no
    /// kernel for it.
    fn pack(&mut self, precision: Precision) -> candle_core::Result<bool> {
        match PackedRhs::pack_weight(&self.w, precision)? {
            Some(p) => {
                self.packed = Some(p.with_bias(self.b.to_dtype(DType::F32)?.to_vec1()?));
                Ok(true)
            }
            None => Ok(false),
        }
    }
}

/// The Q/K/V projections of an encoder layer.
#[derive(Debug, Clone)]
enum Qkv {
    /// Inference models: stacked once, [3 Dv, Dv] and [3 Dv], one product.
    Fused(Dense),
    /// Training models: the three trainable projections, stacked at every forward (a copy
    /// stacked once would not follow the optimiser's updates).
    Separate(Box<[Dense; 3]>),
}

impl Qkv {
    /// [N, T, Dv] -> [N, T, 3 Dv].
    fn forward(&self, h: &Tensor) -> candle_core::Result<Tensor> {
        match self {
            Qkv::Fused(d) => d.forward(h),
            Qkv::Separate(p) => {
                let [q, k, v] = &**p;
                linear(
                    h,
                    &Tensor::cat(&[&q.w, &k.w, &v.w], 0)?,
                    &Tensor::cat(&[&q.b, &k.b, &v.b], 0)?,
                )
            }
        }
    }
}

#[derive(Debug, Clone)]
struct EncoderLayer {
    ln1: LayerNorm,
    qkv: Qkv,
    out: Dense,
    ln2: LayerNorm,
    fc1: Dense,
    fc2: Dense,
}

impl EncoderLayer {
    /// The layer on the inference path, on any device ([`ops`]; on a GPU: bias, activation
    /// and residual folded into one kernel after each product, the Q/K/V head split in one
    /// pass, the scaled softmax in f32 in place; on a CPU: packed products with the bias fused,
    /// one fused attention kernel).
    fn forward_infer(
        &self,
        x: &Tensor,
        nh: usize,
        hd: usize,
        scale: f64,
    ) -> candle_core::Result<Tensor> {
        let h = self.ln1.forward(x, false)?;
        // [N, T, 3 Dv]
        let y = match &self.qkv {
            Qkv::Fused(d) => d.forward_infer(&h, false, None)?,
            Qkv::Separate(_) => self.qkv.forward(&h)?,
        };
        let (q, k, v) = ops::split_qkv(&y, nh, hd)?;
        // [N, T, Dv]
        let arith = self
            .out
            .packed
            .as_ref()
            .map_or(Precision::F32, |p| p.precision());
        let o = ops::attention(&q, &k, &v, None, scale, arith)?;
        let x = self.out.forward_infer(&o, false, Some(x))?;
        let h = self.ln2.forward(&x, false)?;
        let f = self.fc1.forward_infer(&h, true, None)?;
        self.fc2.forward_infer(&f, false, Some(&x))
    }

    /// The layer in candle's ops, with a backward.
    fn forward_diff(
        &self,
        x: &Tensor,
        nh: usize,
        hd: usize,
        scale: f64,
    ) -> candle_core::Result<Tensor> {
        let h = self.ln1.forward(x, true)?;
        let (q, k, v) = ops::split_qkv_composed(&self.qkv.forward(&h)?, nh, hd)?;
        let o = ops::attention_composed(&q, &k, &v, None, scale, true)?;
        let x = x.broadcast_add(&self.out.forward(&o)?)?;
        let h = self.ln2.forward(&x, true)?;
        let f = self.fc1.forward(&h)?.gelu()?;
        x.broadcast_add(&self.fc2.forward(&f)?)
    }
}

/// Vision tower and projector.
#[derive(Debug, Clone)]
pub struct Vision {
    dims: VisionDims,
    /// The tower's dtype (the model's).
    dtype: DType,
    /// Patch embedding as a matrix over flattened (c, y, x) patches: [Dv, 3 p²], bias [Dv].
    patch: Dense,
    /// [T, Dv].
    pos: Tensor,
    layers: Vec<EncoderLayer>,
    post_ln: LayerNorm,
    projector: Dense,
}

impl Vision {
    /// `vb` at `paligemma_with_expert.paligemma.model`.
    pub fn new(dims: &VisionDims, width: usize, vb: VarBuilder) -> candle_core::Result<Self> {
        let d = dims.hidden_size;
        let p = dims.patch_size;
        let t = dims.num_tokens();
        let eps = dims.layer_norm_eps;
        let vm = vb.pp("vision_tower.vision_model");
        // the patch and position embeddings stay f32 whatever the model's dtype (openpi keeps
        // them f32); the tower runs in the model's dtype from their sum on
        let emb = vm.pp("embeddings").set_dtype(DType::F32);
        // conv weight [Dv, 3, p, p] -> [Dv, 3 p²] (row-major: c, then y, then x)
        let pw = emb.pp("patch_embedding").get_with_hints(
            (d, 3, p, p),
            "weight",
            candle_nn::init::DEFAULT_KAIMING_NORMAL,
        )?;
        let pb = emb
            .pp("patch_embedding")
            .get_with_hints(d, "bias", Init::Const(0.0))?;
        let pos = emb.pp("position_embedding").get_with_hints(
            (t, d),
            "weight",
            Init::Randn {
                mean: 0.0,
                stdev: 0.02,
            },
        )?;
        let mut layers = Vec::with_capacity(dims.num_hidden_layers);
        for i in 0..dims.num_hidden_layers {
            let l = vm.pp(format!("encoder.layers.{i}"));
            let a = l.pp("self_attn");
            let q = Dense::new(d, d, a.pp("q_proj"))?;
            let k = Dense::new(d, d, a.pp("k_proj"))?;
            let v = Dense::new(d, d, a.pp("v_proj"))?;
            let qkv = if q.w.is_variable() {
                Qkv::Separate(Box::new([q, k, v]))
            } else {
                Qkv::Fused(Dense {
                    w: Tensor::cat(&[&q.w, &k.w, &v.w], 0)?,
                    b: Tensor::cat(&[&q.b, &k.b, &v.b], 0)?,
                    packed: None,
                })
            };
            layers.push(EncoderLayer {
                ln1: LayerNorm::new(d, eps, l.pp("layer_norm1"))?,
                qkv,
                out: Dense::new(d, d, a.pp("out_proj"))?,
                ln2: LayerNorm::new(d, eps, l.pp("layer_norm2"))?,
                fc1: Dense::new(d, dims.intermediate_size, l.pp("mlp.fc1"))?,
                fc2: Dense::new(dims.intermediate_size, d, l.pp("mlp.fc2"))?,
            });
        }
        let mut vision = Vision {
            dims: dims.clone(),
            dtype: vb.dtype(),
            patch: Dense {
                w: pw.reshape((d, 3 * p * p))?,
                b: pb,
                packed: None,
            },
            pos,
            layers,
            post_ln: LayerNorm::new(d, eps, vm.pp("post_layernorm"))?,
            projector: Dense::new(d, width, vb.pp("multi_modal_projector.linear"))?,
        };
        // inference models (plain tensors, not trainable variables) run on packed f32 weights
        if !pw.is_variable() {
            vision.pack(Precision::F32)?;
        }
        Ok(vision)
    }

    /// SigLIP last hidden state: images [N, 3, S, S] in [-1, 1] -> [N, T, Dv].
    pub fn tower(&self, images: &Tensor) -> candle_core::Result<Tensor> {
        self.tower_with(images, false)
    }

    /// Runs the dense layers (patch embedding, Q/K/V, out, MLP, projector) with weights packed
    /// for `precision`. Returns false where this CPU has no kernel for it (layers keep their
    /// previous packing). For loaded (inference) models: the packed copies do not follow
    /// optimiser updates and have no backward.
    pub fn pack(&mut self, precision: Precision) -> candle_core::Result<bool> {
        let mut ok = self.patch.pack(precision)? & self.projector.pack(precision)?;
        for l in &mut self.layers {
            if let Qkv::Fused(d) = &mut l.qkv {
                ok &= d.pack(precision)?;
            }
            for d in [&mut l.out, &mut l.fc1, &mut l.fc2] {
                ok &= d.pack(precision)?;
            }
        }
        Ok(ok)
    }

    /// [`Self::tower`]; `diff` selects ops with a backward.
    pub fn tower_with(&self, images: &Tensor, diff: bool) -> candle_core::Result<Tensor> {
        let (n, c, s, _) = images.dims4()?;
        let p = self.dims.patch_size;
        let g = s / p;
        let d = self.dims.hidden_size;
        let nh = self.dims.num_attention_heads;
        let hd = d / nh;
        // [N, 3, g, p, g, p] -> [N, g, g, 3, p, p] -> [N, T, 3 p²]
        let patches = images
            .to_dtype(DType::F32)?
            .reshape((n, c, g, p, g, p))?
            .permute((0, 2, 4, 1, 3, 5))?
            .contiguous()?
            .reshape((n, g * g, c * p * p))?;
        // [N, T, Dv]
        let emb = self.patch.forward(&patches)?;
        let mut x = if diff {
            emb.broadcast_add(&self.pos)?
        } else {
            ops::add(&emb, &self.pos)?
        }
        .to_dtype(self.dtype)?;
        let scale = (hd as f64).powf(-0.5);
        for l in &self.layers {
            x = if diff {
                l.forward_diff(&x, nh, hd, scale)?
            } else {
                l.forward_infer(&x, nh, hd, scale)?
            };
        }
        self.post_ln.forward(&x, diff)
    }

    /// Projector: [N, T, Dv] -> [N, T, W].
    pub fn forward_projector(&self, hidden: &Tensor) -> candle_core::Result<Tensor> {
        self.projector.forward(hidden)
    }

    /// Image token embeddings: [N, 3, S, S] -> [N, T, W].
    pub fn forward(&self, images: &Tensor) -> candle_core::Result<Tensor> {
        self.forward_with(images, false)
    }

    /// [`Self::forward`]; `diff` selects ops with a backward.
    pub fn forward_with(&self, images: &Tensor, diff: bool) -> candle_core::Result<Tensor> {
        self.projector.forward(&self.tower_with(images, diff)?)
    }
}
