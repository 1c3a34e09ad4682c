//! The prefix KV cache and its two halves: [`PiModel::prepare_prefix`] (host: checks, layout,
//! masks, RoPE tables, copies of the observation into the cache's buffers) and
//! [`PiModel::run_prefix`] (device: vision, the VLM's prefix pass filling K/V in place).

use std::sync::{Arc, Mutex};

use candle_core::{DType, Module, Tensor};

use crate::ops::PackedKv;

use super::*;

/// Host-side prefix layout: validity and RoPE positions of each prefix token.
#[derive(Debug, Clone, PartialEq)]
pub struct PrefixLayout {
    /// [B][P] valid tokens (camera mask expanded + token mask).
    pub pad: Vec<Vec<bool>>,
    /// [B][P] `cumsum(pad) - 1`.
    pub pos: Vec<Vec<i64>>,
    /// [B] number of valid prefix tokens (= first suffix position).
    pub n_valid: Vec<usize>,
}

/// Post-RoPE K/V of the prefix (and, for π0, of the state token) for every layer, in buffers of
/// length `P + S` that are reused across denoising steps and observations, and the device copies
/// of everything else a prefix pass and a denoising step read ([`PrefixStatics`]).
#[derive(Debug)]
pub struct PrefixCache {
    /// Per layer [B, nKV, P + S, hd].
    pub k: Vec<Tensor>,
    /// Per layer [B, nKV, P + S, hd].
    pub v: Vec<Tensor>,
    /// The observation's tensors on the device (refilled in place in the fixed layout).
    pub statics: PrefixStatics,
    /// Cameras run through the vision tower (compact layout: those valid in some batch row).
    pub cams: Vec<usize>,
    /// Compaction: per batch row, the prefix slots computed, in order (empty: all P slots).
    pub rows: Vec<Tensor>,
    /// Sequence index of the first action token (`Pc + state_tokens`, fixed layout
    /// `P + state_tokens`).
    pub action_offset: usize,
    /// Prefix layout the cache was built from.
    pub layout: PrefixLayout,
    /// Batch size.
    pub batch: usize,
    /// Each layer's K/V before `action_offset` (everything a denoising step reads but does not
    /// write) packed for the CPU attention kernel, once per observation by
    /// [`PiModel::run_prefix`] (None: not packed — a GPU, the kernels off, a refill since).
    packed: Mutex<Option<Arc<Vec<PackedKv>>>>,
}

impl PrefixCache {
    /// Additive mask for action queries over the keys they see [B, 1, 1, Pc + S].
    pub fn step_bias(&self) -> &Tensor {
        &self.statics.step_bias
    }

    /// RoPE tables of the action tokens.
    pub fn action_rope(&self) -> &Rope {
        &self.statics.action_rope
    }

    /// The layers' prefix K/V packed for the CPU attention kernel, where
    /// [`PiModel::run_prefix`] packed them for the observation now in the cache.
    pub fn packed_prefix(&self) -> Option<Arc<Vec<PackedKv>>> {
        self.packed.lock().ok().and_then(|p| p.clone())
    }

    fn set_packed(&self, packed: Option<Vec<PackedKv>>) {
        if let Ok(mut p) = self.packed.lock() {
            *p = packed.map(Arc::new);
        }
    }
}

/// One observation's tensors as the prefix pass and the denoising steps read them. In the fixed
/// layout their shapes do not depend on the observation, and [`PiModel::prepare_prefix`]
/// copies each new observation into the same buffers.
#[derive(Debug)]
pub struct PrefixStatics {
    /// The cameras that run the vision tower, batched [C·B, 3, S, S] f32.
    pub images: Tensor,
    /// Token ids [B · Lt] u32.
    pub ids: Tensor,
    /// State [B, A] f32.
    pub state: Tensor,
    /// Validity of the prefix slots computed [B, Pc] f32 (1 valid, 0 padding): the prefix
    /// self-attention mask is made from it on the device ([`PiModel::run_prefix`]), not uploaded
    /// as a [B, 1, Pc, Pc] table.
    pub prefix_valid: Tensor,
    /// RoPE positions of the prefix slots computed [B, Pc] f32 (the tables are made on the
    /// device).
    pub prefix_pos: Tensor,
    /// Additive mask for action queries [B, 1, 1, Pc + S] f32: the prefix slots computed
    /// (padding masked), then the suffix (fixed layout: rounded up to a multiple of 8 slots,
    /// the extra ones masked).
    pub step_bias: Tensor,
    /// RoPE tables of the action tokens.
    pub action_rope: Rope,
    /// π0's state token: its mask [B, 1, 1, Pc + 1] and RoPE tables.
    pub state_bias: Option<Tensor>,
    /// See `state_bias`.
    pub state_rope: Option<Rope>,
}

impl PrefixStatics {
    /// `new` copied into `self`'s buffers where every shape and dtype matches (fixed layout:
    /// the buffers keep their addresses), else `new` itself.
    fn refill(self, new: PrefixStatics) -> candle_core::Result<PrefixStatics> {
        fn same(a: &Tensor, b: &Tensor) -> bool {
            a.dims() == b.dims() && a.dtype() == b.dtype()
        }
        let ropes = |a: &Rope, b: &Rope| same(&a.cos, &b.cos) && same(&a.sin, &b.sin);
        let fits = same(&self.images, &new.images)
            && same(&self.ids, &new.ids)
            && same(&self.state, &new.state)
            && same(&self.prefix_valid, &new.prefix_valid)
            && same(&self.prefix_pos, &new.prefix_pos)
            && same(&self.step_bias, &new.step_bias)
            && ropes(&self.action_rope, &new.action_rope)
            && match (&self.state_bias, &new.state_bias) {
                (Some(a), Some(b)) => same(a, b),
                (None, None) => true,
                _ => false,
            }
            && match (&self.state_rope, &new.state_rope) {
                (Some(a), Some(b)) => ropes(a, b),
                (None, None) => true,
                _ => false,
            };
        if !fits {
            return Ok(new);
        }
        let pairs = [
            (&self.images, &new.images),
            (&self.ids, &new.ids),
            (&self.state, &new.state),
            (&self.prefix_valid, &new.prefix_valid),
            (&self.prefix_pos, &new.prefix_pos),
            (&self.step_bias, &new.step_bias),
            (&self.action_rope.cos, &new.action_rope.cos),
            (&self.action_rope.sin, &new.action_rope.sin),
        ];
        for (dst, src) in pairs {
            dst.slice_set(&src.contiguous()?, 0, 0)?;
        }
        if let (Some(a), Some(b)) = (&self.state_bias, &new.state_bias) {
            a.slice_set(&b.contiguous()?, 0, 0)?;
        }
        if let (Some(a), Some(b)) = (&self.state_rope, &new.state_rope) {
            a.cos.slice_set(&b.cos.contiguous()?, 0, 0)?;
            a.sin.slice_set(&b.sin.contiguous()?, 0, 0)?;
        }
        Ok(self)
    }

    /// Identities of every buffer (a captured graph checks it still reads the same ones).
    pub fn ids(&self) -> Vec<candle_core::TensorId> {
        let mut v = vec![
            self.images.id(),
            self.ids.id(),
            self.state.id(),
            self.prefix_valid.id(),
            self.prefix_pos.id(),
            self.step_bias.id(),
            self.action_rope.cos.id(),
            self.action_rope.sin.id(),
        ];
        v.extend(self.state_bias.iter().map(|t| t.id()));
        v.extend(
            self.state_rope
                .iter()
                .flat_map(|r| [r.cos.id(), r.sin.id()]),
        );
        v
    }
}

impl PiModel {
    /// The host half of [`Self::fill_cache`]: checks the inputs, plans the prefix layout and
    /// copies everything the device half reads into the cache (allocating it, or reusing its
    /// buffers when the shapes match). In the fixed layout every buffer keeps its address across
    /// observations, so a graph captured over [`Self::run_prefix`] reads the new observation.
    /// `skip_masked`: cameras masked in every batch row skip the vision pass (compact layout only).
    pub fn prepare_prefix<'c>(
        &self,
        inp: &ModelInputs,
        cache: &'c mut Option<PrefixCache>,
        skip_masked: bool,
    ) -> Result<&'c mut PrefixCache, PolicyError> {
        let b = self.check_inputs(inp)?;
        let d = &self.cfg.paligemma;
        let p = self.cfg.prefix_len();
        let ns = self.cfg.state_tokens();
        let fixed = self.fixed_step_shapes;
        // cache length: P + S, in the fixed layout rounded up to a multiple of 8 slots (masked)
        // so that the step's score and probability rows start 16-byte aligned in bf16 (cuBLAS
        // falls back to slow kernels for misaligned leading dimensions)
        let total = if fixed {
            (p + self.cfg.suffix_len()).next_multiple_of(8)
        } else {
            p + self.cfg.suffix_len()
        };
        let tail = total - p - self.cfg.suffix_len();
        // token ids in range (one host read; the embedding lookup would fault otherwise)
        let ids = inp.tokens.flatten_all()?.to_dtype(DType::U32)?;
        let vocab = self.embed_tokens.dim(0)?;
        let id_range = inp.tokens.flatten_all()?.to_dtype(DType::F64)?;
        let (min_id, max_id) = (
            id_range.min(0)?.to_scalar::<f64>()?,
            id_range.max(0)?.to_scalar::<f64>()?,
        );
        if min_id < 0.0 || max_id >= vocab as f64 {
            return Err(PolicyError::Input(format!(
                "token ids must be in [0, {vocab}), got [{min_id}, {max_id}]"
            )));
        }
        let layout = self.prefix_layout(inp);
        // cameras through the vision tower: all in the fixed layout (same work every time)
        let cams: Vec<usize> = (0..inp.images.len())
            .filter(|&c| fixed || !skip_masked || inp.image_masks[c].iter().any(|&m| m))
            .collect();
        // Compaction (compact layout): padding tokens and masked cameras never influence valid
        // tokens (they are masked as keys everywhere), so the prefix pass runs over the valid
        // tokens only, in order, padded per row to the largest valid count `pc` with (masked)
        // filler tokens. The fixed layout runs all P slots, masked the same way.
        let pc = if fixed {
            p
        } else {
            layout.n_valid.iter().copied().max().unwrap_or(0).max(1)
        };
        let mut rows = Vec::with_capacity(b);
        let mut cpad = Vec::with_capacity(b);
        let mut cpos = Vec::with_capacity(b);
        for bi in 0..b {
            let pad = &layout.pad[bi];
            let mut idx: Vec<u32> = (0..p)
                .filter(|&j| fixed || pad[j])
                .map(|j| j as u32)
                .collect();
            idx.extend(
                (0..p)
                    .filter(|&j| !fixed && !pad[j])
                    .take(pc - idx.len().min(pc))
                    .map(|j| j as u32),
            );
            cpad.push(idx.iter().map(|&j| pad[j as usize]).collect::<Vec<_>>());
            cpos.push(
                idx.iter()
                    .map(|&j| layout.pos[bi][j as usize])
                    .collect::<Vec<_>>(),
            );
            rows.push(idx);
        }
        let rows = if pc == p
            && rows
                .iter()
                .all(|r| r.iter().enumerate().all(|(i, &j)| i == j as usize))
        {
            Vec::new()
        } else {
            rows.iter()
                .map(|r| Tensor::new(r.as_slice(), &self.device))
                .collect::<candle_core::Result<Vec<_>>>()?
        };
        let compact = PrefixLayout {
            pad: cpad,
            pos: cpos,
            n_valid: layout.n_valid.clone(),
        };
        // Where the suffix goes in the cache. Compact layout (the CPU's): right after the
        // compacted prefix, at pc, so a denoising step attends over pc + S keys instead of
        // P + S: the padding slots are skipped, not masked. Fixed layout (GPUs'): at P, so a
        // step's shapes, offsets and buffers are the same for every observation.
        // Key visibility for suffix queries: the computed prefix slots (padding masked), then
        // every suffix slot.
        let so = pc;
        let t_step = so + total - p;
        let mut vis = Vec::with_capacity(b * t_step);
        for row in &compact.pad {
            vis.extend_from_slice(row);
            vis.extend(std::iter::repeat_n(true, total - p - tail));
            vis.extend(std::iter::repeat_n(false, tail));
        }
        // positions of the action tokens: n_valid + state_tokens + [0, H)
        let h = self.cfg.action_horizon;
        let apos: Vec<Vec<i64>> = layout
            .n_valid
            .iter()
            .map(|&n| (0..h).map(|i| (n + ns + i) as i64).collect())
            .collect();
        // π0: the state token sees the computed prefix and itself
        let state_part = if ns == 1 {
            let spos: Vec<Vec<i64>> = layout.n_valid.iter().map(|&n| vec![n as i64]).collect();
            let mut svis = Vec::with_capacity(b * (so + 1));
            for row in &compact.pad {
                svis.extend_from_slice(row);
                svis.push(true);
            }
            Some((
                bias_tensor(svis, (b, 1, 1, so + 1), &self.device)?,
                self.rope(&spos)?,
            ))
        } else {
            None
        };
        let images = if cams.is_empty() {
            // every camera masked: no vision pass (their tokens are padding)
            let s = self.cfg.vision.image_size;
            Tensor::zeros((0, 3, s, s), DType::F32, &self.device)?
        } else {
            let imgs: Vec<Tensor> = cams
                .iter()
                .map(|&c| inp.images[c].to_dtype(DType::F32))
                .collect::<candle_core::Result<_>>()?;
            Tensor::cat(&imgs, 0)?
        };
        // own copies: the caller's tensors may be reused or freed (a conversion to the same
        // dtype, or a cat of one camera, would alias them)
        let fresh = PrefixStatics {
            images: images.copy()?,
            ids: ids.copy()?,
            state: inp.state.to_dtype(DType::F32)?.copy()?,
            prefix_valid: {
                let v: Vec<f32> = compact
                    .pad
                    .iter()
                    .flatten()
                    .map(|&m| m as u8 as f32)
                    .collect();
                Tensor::from_vec(v, (b, pc), &self.device)?
            },
            prefix_pos: {
                let v: Vec<f32> = compact.pos.iter().flatten().map(|&p| p as f32).collect();
                Tensor::from_vec(v, (b, pc), &self.device)?
            },
            step_bias: bias_tensor(vis, (b, 1, 1, t_step), &self.device)?,
            action_rope: self.rope(&apos)?,
            state_bias: state_part.as_ref().map(|s| s.0.clone()),
            state_rope: state_part.map(|s| s.1),
        };
        let reuse = matches!(cache, Some(c) if c.batch == b && c.k.first().map(|k| k.dims() == [b, d.num_kv_heads, total, d.head_dim]).unwrap_or(false));
        let c = match cache.take() {
            Some(mut c) if reuse => {
                // fixed layout: the same device buffers as for the previous observation, refilled
                c.statics = if fixed {
                    c.statics.refill(fresh)?
                } else {
                    fresh
                };
                c.cams = cams;
                c.rows = rows;
                c.action_offset = so + ns;
                c.layout = layout;
                c.set_packed(None);
                c
            }
            _ => {
                let mut ks = Vec::with_capacity(d.depth);
                let mut vs = Vec::with_capacity(d.depth);
                for _ in 0..d.depth {
                    for kv in [&mut ks, &mut vs] {
                        kv.push(Tensor::zeros(
                            (b, d.num_kv_heads, total, d.head_dim),
                            self.dtype,
                            &self.device,
                        )?);
                    }
                }
                PrefixCache {
                    k: ks,
                    v: vs,
                    statics: fresh,
                    cams,
                    rows,
                    action_offset: so + ns,
                    layout,
                    batch: b,
                    packed: Mutex::new(None),
                }
            }
        };
        Ok(cache.insert(c))
    }

    /// The device half of [`Self::fill_cache`]: the vision tower, the embeddings and the VLM
    /// expert over the prefix (and π0's state token through the action expert), K/V into the
    /// cache, reading only the cache's buffers ([`Self::prepare_prefix`] filled them): no host
    /// read or upload of anything observation-dependent. `embs`: precomputed prefix embeddings
    /// [B, P, W] instead of the vision pass.
    pub fn run_prefix(
        &self,
        c: &PrefixCache,
        embs: Option<&Tensor>,
        want_out: bool,
    ) -> Result<Option<Tensor>, PolicyError> {
        let d = &self.cfg.paligemma;
        let b = c.batch;
        let s = &c.statics;
        // the panels of the previous observation go before its K/V are overwritten
        c.set_packed(None);
        let embs = match embs {
            Some(e) => e.clone(),
            None => self.embed_from(c)?,
        };
        let x = match c.rows.as_slice() {
            [] => embs,
            [r] if b == 1 => embs.index_select(r, 1)?,
            rs => {
                let mut parts = Vec::with_capacity(b);
                for (bi, r) in rs.iter().enumerate() {
                    parts.push(embs.narrow(0, bi, 1)?.index_select(r, 1)?);
                }
                Tensor::cat(&parts, 0)?
            }
        };
        // the mask [B, 1, Pc, Pc] (0 where both tokens are valid, the mask value elsewhere) and
        // the RoPE tables, made on the device from the observation's validity and positions
        let prefix_bias = {
            let v = &s.prefix_valid;
            let both = v.unsqueeze(2)?.broadcast_mul(&v.unsqueeze(1)?)?;
            ((both - 1.0)? * (-(MASK_VALUE as f64)))?.unsqueeze(1)?
        };
        let prefix_rope = Rope::from_positions(
            &s.prefix_pos,
            self.cfg.paligemma.head_dim,
            self.cfg.rope_theta,
            self.dtype,
        )?;
        let mut streams = [Stream {
            x,
            expert: &self.vlm,
            cond: None,
            rope: &prefix_rope,
            pending: None,
        }];
        for li in 0..d.depth {
            if li + 1 == d.depth && !want_out {
                // the last layer only has to provide K/V
                kv_only_layer(li, &streams[0], &c.k[li], &c.v[li])?;
                continue;
            }
            joint_layer(
                li,
                &mut streams,
                &prefix_bias,
                KvMode::Own {
                    store: Some((&c.k[li], &c.v[li])),
                },
                false,
            )?;
        }
        let out = if want_out {
            Some(self.vlm.norm.forward(&streams[0].x, None, false)?.0)
        } else {
            None
        };
        if let (Some(sbias), Some(srope)) = (&s.state_bias, &s.state_rope) {
            // π0: the state token sees the prefix and itself only, so its K/V do not depend on
            // x_t or t: run it once through the action expert and keep it in the cache at P.
            let SuffixHeads::Pi0 { state_proj, .. } = &self.heads else {
                return Err(PolicyError::Config("pi0 without state_proj".into()));
            };
            let st = state_proj
                .forward(&s.state)?
                .unsqueeze(1)?
                .to_dtype(self.dtype)?;
            let mut st = [Stream {
                x: st,
                expert: &self.expert,
                cond: None,
                rope: srope,
                pending: None,
            }];
            for li in 0..d.depth {
                joint_layer(
                    li,
                    &mut st,
                    sbias,
                    KvMode::Cached {
                        k: &c.k[li],
                        v: &c.v[li],
                        offset: c.action_offset - 1,
                        packed: None,
                    },
                    false,
                )?;
            }
        }
        c.set_packed(self.pack_prefix(c)?);
        Ok(out)
    }

    /// Every layer's cached K/V before the action tokens, packed for the CPU attention kernel in
    /// the arithmetic of the action expert's layer that reads them; `None` where any layer
    /// cannot be (not the CPU, the kernels off, a layout the kernel does not take, a trainable
    /// model).
    fn pack_prefix(&self, c: &PrefixCache) -> Result<Option<Vec<PackedKv>>, PolicyError> {
        if !self.device.is_cpu() {
            return Ok(None);
        }
        let _span = crate::ops::profile::span(crate::ops::profile::Kind::Attention);
        let mut out = Vec::with_capacity(c.k.len());
        for (li, (k, v)) in c.k.iter().zip(&c.v).enumerate() {
            // only the fused layer reads the panels
            let Some(layer) = self.expert.layers.get(li).filter(|l| l.is_fused()) else {
                return Ok(None);
            };
            match PackedKv::pack(k, v, c.action_offset, layer.attention_arith())? {
                Some(p) => out.push(p),
                None => return Ok(None),
            }
        }
        Ok(Some(out))
    }

    /// Prefix embeddings [B, P, W] from the cache's images and token ids: image embeddings per
    /// camera (zeros for a camera that skipped the vision pass), then `embed(ids) * sqrt(W)`.
    fn embed_from(&self, c: &PrefixCache) -> Result<Tensor, PolicyError> {
        let b = c.batch;
        let t = self.cfg.vision.num_tokens();
        let w = self.cfg.paligemma.width;
        let emb = if c.cams.is_empty() {
            None
        } else {
            Some(
                self.vision
                    .forward_with(&c.statics.images, false)?
                    .to_dtype(self.dtype)?,
            )
        };
        let mut parts = Vec::with_capacity(self.cfg.cameras.len() + 1);
        for cam in 0..self.cfg.cameras.len() {
            match (c.cams.iter().position(|&r| r == cam), &emb) {
                (Some(i), Some(e)) => parts.push(e.narrow(0, i * b, b)?),
                _ => parts.push(Tensor::zeros((b, t, w), self.dtype, &self.device)?),
            }
        }
        let text = self
            .embed_tokens
            .index_select(&c.statics.ids, 0)?
            .reshape((b, self.cfg.max_token_len, w))?;
        parts.push((text * (w as f64).sqrt())?);
        Ok(Tensor::cat(&parts, 1)?)
    }
}
