//! SigLIP vision tower + PaliGemma multi-modal projector.
//!
//! The tower is `candle_transformers::models::siglip::VisionModel` without its pooling head (its
//! math and key names are openpi's: conv patch embedding with bias, learned position embedding,
//! pre-LN encoder with gelu-tanh MLP, `post_layernorm`). The projector is `Linear(Dv -> W, bias)`.
//! Image tokens are not scaled (openpi removes PaliGemma's `/ sqrt(W)`).

use candle_core::{Module, Tensor};
use candle_nn::{Linear, VarBuilder};
use candle_transformers::models::siglip;

use super::config::VisionDims;

/// Vision tower and projector.
#[derive(Debug, Clone)]
pub struct Vision {
    tower: siglip::VisionModel,
    projector: Linear,
}

impl Vision {
    /// `vb` at `paligemma_with_expert.paligemma.model`.
    pub fn new(dims: &VisionDims, width: usize, vb: VarBuilder) -> candle_core::Result<Self> {
        let cfg = siglip::VisionConfig {
            hidden_size: dims.hidden_size,
            intermediate_size: dims.intermediate_size,
            num_hidden_layers: dims.num_hidden_layers,
            num_attention_heads: dims.num_attention_heads,
            num_channels: 3,
            image_size: dims.image_size,
            patch_size: dims.patch_size,
            hidden_act: candle_nn::Activation::GeluPytorchTanh,
            layer_norm_eps: dims.layer_norm_eps,
        };
        let tower = siglip::VisionModel::new(&cfg, false, vb.pp("vision_tower.vision_model"))?;
        let projector = candle_nn::linear(
            dims.hidden_size,
            width,
            vb.pp("multi_modal_projector.linear"),
        )?;
        Ok(Vision { tower, projector })
    }

    /// SigLIP last hidden state: images [N, 3, S, S] in [-1, 1] -> [N, T, Dv].
    pub fn tower(&self, images: &Tensor) -> candle_core::Result<Tensor> {
        self.tower.forward(images)
    }

    /// Projector: [N, T, Dv] -> [N, T, W].
    pub fn forward_projector(&self, hidden: &Tensor) -> candle_core::Result<Tensor> {
        self.projector.forward(hidden)
    }

    /// Image token embeddings: [N, 3, S, S] -> [N, T, W].
    pub fn forward(&self, images: &Tensor) -> candle_core::Result<Tensor> {
        self.projector.forward(&self.tower(images)?)
    }
}
