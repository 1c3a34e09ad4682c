//! Checkpoints: `model.safetensors` with openpi PyTorch key names or LeRobot's (`model.` prefix),
//! f32 or bf16 (computed in f32), dimensions from the directory's layout ([`crate::layout`]:
//! chunkrt's, openpi's or LeRobot's), every tensor checked by name and shape before the model is
//! built.

use std::collections::HashMap;
use std::path::Path;

use candle_core::{DType, Device, Tensor};
use candle_nn::VarBuilder;

use super::config::{ConfigOverrides, ModelConfig, ModelKind};
use super::model::PiModel;
use crate::error::PolicyError;
use crate::layout::{Layout, LayoutOptions};

const PG: &str = "paligemma_with_expert.paligemma";
/// The token embedding's key, and the LM head's (which holds it when the embedding is absent).
pub const EMBED: &str = "paligemma_with_expert.paligemma.model.language_model.embed_tokens.weight";
pub const LM_HEAD: &str = "paligemma_with_expert.paligemma.lm_head.weight";

/// Every tensor the model reads, with its shape (the token embedding under `lm_head.weight`).
pub fn expected_tensors(cfg: &ModelConfig) -> Vec<(String, Vec<usize>)> {
    let mut v: Vec<(String, Vec<usize>)> = Vec::new();
    let vis = &cfg.vision;
    let dv = vis.hidden_size;
    let vp = format!("{PG}.model.vision_tower.vision_model");
    v.push((
        format!("{vp}.embeddings.patch_embedding.weight"),
        vec![dv, 3, vis.patch_size, vis.patch_size],
    ));
    v.push((format!("{vp}.embeddings.patch_embedding.bias"), vec![dv]));
    v.push((
        format!("{vp}.embeddings.position_embedding.weight"),
        vec![vis.num_tokens(), dv],
    ));
    for i in 0..vis.num_hidden_layers {
        let l = format!("{vp}.encoder.layers.{i}");
        for n in ["layer_norm1", "layer_norm2"] {
            v.push((format!("{l}.{n}.weight"), vec![dv]));
            v.push((format!("{l}.{n}.bias"), vec![dv]));
        }
        for n in ["q_proj", "k_proj", "v_proj", "out_proj"] {
            v.push((format!("{l}.self_attn.{n}.weight"), vec![dv, dv]));
            v.push((format!("{l}.self_attn.{n}.bias"), vec![dv]));
        }
        v.push((
            format!("{l}.mlp.fc1.weight"),
            vec![vis.intermediate_size, dv],
        ));
        v.push((format!("{l}.mlp.fc1.bias"), vec![vis.intermediate_size]));
        v.push((
            format!("{l}.mlp.fc2.weight"),
            vec![dv, vis.intermediate_size],
        ));
        v.push((format!("{l}.mlp.fc2.bias"), vec![dv]));
    }
    v.push((format!("{vp}.post_layernorm.weight"), vec![dv]));
    v.push((format!("{vp}.post_layernorm.bias"), vec![dv]));
    let w = cfg.paligemma.width;
    v.push((
        format!("{PG}.model.multi_modal_projector.linear.weight"),
        vec![w, dv],
    ));
    v.push((
        format!("{PG}.model.multi_modal_projector.linear.bias"),
        vec![w],
    ));
    v.push((LM_HEAD.to_string(), vec![cfg.vocab_size, w]));
    let pi05 = cfg.kind == ModelKind::Pi05;
    for (prefix, d, ada) in [
        (format!("{PG}.model.language_model"), &cfg.paligemma, false),
        (
            "paligemma_with_expert.gemma_expert.model".to_string(),
            &cfg.action_expert,
            pi05,
        ),
    ] {
        let w = d.width;
        let qd = d.num_heads * d.head_dim;
        let kvd = d.num_kv_heads * d.head_dim;
        let norm = |v: &mut Vec<(String, Vec<usize>)>, n: String| {
            if ada {
                v.push((format!("{n}.dense.weight"), vec![3 * w, w]));
                v.push((format!("{n}.dense.bias"), vec![3 * w]));
            } else {
                v.push((format!("{n}.weight"), vec![w]));
            }
        };
        for i in 0..d.depth {
            let l = format!("{prefix}.layers.{i}");
            norm(&mut v, format!("{l}.input_layernorm"));
            norm(&mut v, format!("{l}.post_attention_layernorm"));
            v.push((format!("{l}.self_attn.q_proj.weight"), vec![qd, w]));
            v.push((format!("{l}.self_attn.k_proj.weight"), vec![kvd, w]));
            v.push((format!("{l}.self_attn.v_proj.weight"), vec![kvd, w]));
            v.push((format!("{l}.self_attn.o_proj.weight"), vec![w, qd]));
            v.push((format!("{l}.mlp.gate_proj.weight"), vec![d.mlp_dim, w]));
            v.push((format!("{l}.mlp.up_proj.weight"), vec![d.mlp_dim, w]));
            v.push((format!("{l}.mlp.down_proj.weight"), vec![w, d.mlp_dim]));
        }
        norm(&mut v, format!("{prefix}.norm"));
    }
    let (a, we) = (cfg.action_dim, cfg.action_expert.width);
    let mut lin = |n: &str, i: usize, o: usize| {
        v.push((format!("{n}.weight"), vec![o, i]));
        v.push((format!("{n}.bias"), vec![o]));
    };
    lin("action_in_proj", a, we);
    lin("action_out_proj", we, a);
    match cfg.kind {
        ModelKind::Pi0 => {
            lin("state_proj", a, we);
            lin("action_time_mlp_in", 2 * we, we);
            lin("action_time_mlp_out", we, we);
        }
        ModelKind::Pi05 => {
            lin("time_mlp_in", we, we);
            lin("time_mlp_out", we, we);
        }
    }
    v
}

/// The tensors of a safetensors file under the model's names (LeRobot's `model.` prefix
/// stripped, the tied token embedding under [`LM_HEAD`]), memory-mapped and read one at a time:
/// a `VarBuilder` over it copies each weight from the file straight into the requested dtype on
/// the requested device, so a 7 GB bf16 checkpoint never becomes a host-side f32 copy.
pub struct WeightFile {
    st: candle_core::safetensors::MmapedSafetensors,
    /// model name -> name in the file
    names: HashMap<String, String>,
    shapes: HashMap<String, Vec<usize>>,
    dtypes: Vec<DType>,
}

pub use crate::files::{read_bounded, read_side_file, MAX_SIDE_FILE_BYTES};

impl WeightFile {
    /// Maps `path` and indexes its tensors (no tensor data is read).
    pub fn open(path: &Path) -> Result<Self, PolicyError> {
        let io = |e: candle_core::Error| PolicyError::Io(format!("{}: {e}", path.display()));
        // SAFETY: the file is mapped read-only; like every safetensors reader that maps, we rely
        // on nobody truncating or rewriting the checkpoint while the policy loads it.
        let st = unsafe { candle_core::safetensors::MmapedSafetensors::new(path) }.map_err(io)?;
        let views = st.tensors();
        let lerobot = views
            .iter()
            .any(|(k, _)| k.starts_with("model.paligemma_with_expert."));
        let mut names = HashMap::with_capacity(views.len());
        let mut shapes = HashMap::with_capacity(views.len());
        let mut dtypes = Vec::new();
        let mut embed = None;
        for (k, v) in &views {
            let dt = DType::try_from(v.dtype()).map_err(io)?;
            if !dtypes.contains(&dt) {
                dtypes.push(dt);
            }
            let name = match (lerobot, k.strip_prefix("model.")) {
                (true, Some(s)) => s.to_string(),
                _ => k.clone(),
            };
            if name == EMBED {
                embed = Some((k.clone(), v.shape().to_vec()));
                continue;
            }
            shapes.insert(name.clone(), v.shape().to_vec());
            names.insert(name, k.clone());
        }
        // the token embedding is tied to the LM head: one name, the embedding's where both exist
        if let Some((k, shape)) = embed {
            shapes.insert(LM_HEAD.to_string(), shape);
            names.insert(LM_HEAD.to_string(), k);
        }
        Ok(Self {
            st,
            names,
            shapes,
            dtypes,
        })
    }

    /// Shapes by model name.
    pub fn shapes(&self) -> &HashMap<String, Vec<usize>> {
        &self.shapes
    }

    /// Dtypes stored in the file.
    pub fn dtypes(&self) -> &[DType] {
        &self.dtypes
    }

    fn load(&self, name: &str, dtype: DType, dev: &Device) -> candle_core::Result<Tensor> {
        let stored = self
            .names
            .get(name)
            .ok_or_else(|| candle_core::Error::Msg(format!("checkpoint has no tensor {name}")))?;
        self.st.load(stored, dev)?.to_dtype(dtype)
    }
}

impl candle_nn::var_builder::SimpleBackend for WeightFile {
    fn get(
        &self,
        s: candle_core::Shape,
        name: &str,
        _: candle_nn::Init,
        dtype: DType,
        dev: &Device,
    ) -> candle_core::Result<Tensor> {
        let t = self.load(name, dtype, dev)?;
        if t.shape() != &s {
            return Err(candle_core::Error::Msg(format!(
                "{name}: shape {:?} in the checkpoint, the model needs {:?}",
                t.dims(),
                s.dims()
            )));
        }
        Ok(t)
    }

    fn get_unchecked(&self, name: &str, dtype: DType, dev: &Device) -> candle_core::Result<Tensor> {
        self.load(name, dtype, dev)
    }

    fn contains_tensor(&self, name: &str) -> bool {
        self.names.contains_key(name)
    }
}

/// The shapes of loaded tensors by name (for [`check_tensors`] / [`resolve_config`]).
pub fn shapes_of(t: &HashMap<String, Tensor>) -> HashMap<String, Vec<usize>> {
    t.iter()
        .map(|(k, v)| (k.clone(), v.dims().to_vec()))
        .collect()
}

/// Loads every tensor of a safetensors file as f32 on the CPU, with LeRobot's `model.` prefix
/// stripped. Returns the tensors and the stored dtypes seen.
pub fn load_tensors(path: &Path) -> Result<(HashMap<String, Tensor>, Vec<DType>), PolicyError> {
    let raw = candle_core::safetensors::load(path, &Device::Cpu)
        .map_err(|e| PolicyError::Io(format!("{}: {e}", path.display())))?;
    let lerobot = raw
        .keys()
        .any(|k| k.starts_with("model.paligemma_with_expert."));
    let mut out = HashMap::with_capacity(raw.len());
    let mut dtypes = Vec::new();
    for (k, t) in raw {
        if !dtypes.contains(&t.dtype()) {
            dtypes.push(t.dtype());
        }
        let k = match (lerobot, k.strip_prefix("model.")) {
            (true, Some(s)) => s.to_string(),
            _ => k,
        };
        let t = if t.dtype() == DType::F32 {
            t
        } else {
            t.to_dtype(DType::F32)?
        };
        out.insert(k, t);
    }
    // the token embedding is tied to the LM head: use whichever exists under one name
    if let Some(e) = out.remove(EMBED) {
        out.insert(LM_HEAD.to_string(), e);
    }
    Ok((out, dtypes))
}

pub use crate::config::detect_kind;

/// Compares the tensors with what `cfg` needs: one error listing every missing or mismatched
/// tensor by name and shape. Unused tensors (e.g. the expert's `lm_head`) are ignored.
pub fn check_tensors(
    cfg: &ModelConfig,
    t: &HashMap<String, Vec<usize>>,
) -> Result<(), PolicyError> {
    let mut problems = Vec::new();
    for (name, shape) in expected_tensors(cfg) {
        match t.get(&name) {
            None => problems.push(format!("missing {name} {shape:?}")),
            Some(x) if x != &shape => problems.push(format!(
                "mismatched {name}: found {x:?}, expected {shape:?}"
            )),
            _ => {}
        }
    }
    if problems.is_empty() {
        Ok(())
    } else {
        Err(PolicyError::Checkpoint(format!(
            "{} problem(s):\n  {}",
            problems.len(),
            problems.join("\n  ")
        )))
    }
}

/// Dimensions of a checkpoint directory with the default [`LayoutOptions`]: see [`resolve`].
pub fn resolve_config(
    dir: &Path,
    tensors: &HashMap<String, Vec<usize>>,
    overrides: &ConfigOverrides,
) -> Result<ModelConfig, PolicyError> {
    resolve(dir, tensors, overrides, &LayoutOptions::default()).map(|(cfg, _)| cfg)
}

/// Reads the directory's layout ([`Layout::read`]: chunkrt's, openpi's or LeRobot's), applies
/// `overrides`, and takes the vocabulary from the embedding's shape.
pub fn resolve(
    dir: &Path,
    tensors: &HashMap<String, Vec<usize>>,
    overrides: &ConfigOverrides,
    opts: &LayoutOptions,
) -> Result<(ModelConfig, Layout), PolicyError> {
    let layout = Layout::read(dir, tensors, opts)?;
    let mut cfg = layout.config.clone();
    overrides.apply(&mut cfg)?;
    if let Some(dims) = tensors.get(LM_HEAD) {
        if dims.len() == 2 {
            if dims[1] != cfg.paligemma.width {
                return Err(PolicyError::Checkpoint(format!(
                    "token embedding {LM_HEAD} is {dims:?} but the PaliGemma width is {}",
                    cfg.paligemma.width
                )));
            }
            cfg.vocab_size = dims[0];
        }
    }
    // before anything is sized from it (the expected tensor list, the model)
    cfg.validate()?;
    Ok((cfg, layout))
}

/// The kind (π0 or π0.5) of the checkpoint in `dir`, from its layout (only the weights' index
/// is read).
pub fn kind_of(dir: &Path, opts: &LayoutOptions) -> Result<ModelKind, PolicyError> {
    let file = WeightFile::open(&dir.join("model.safetensors"))?;
    let (cfg, _) = resolve(dir, file.shapes(), &ConfigOverrides::default(), opts)?;
    Ok(cfg.kind)
}

/// A loaded checkpoint.
pub struct Loaded {
    /// The model.
    pub model: PiModel,
    /// Dtypes stored in the file.
    pub stored_dtypes: Vec<DType>,
    /// Where its configuration, tokenizer and statistics came from.
    pub layout: Layout,
}

/// Loads `dir/model.safetensors` (+ `config.json`) and builds the model in f32 on the CPU.
pub fn load(dir: &Path, overrides: &ConfigOverrides) -> Result<Loaded, PolicyError> {
    load_on(dir, overrides, &Device::Cpu, DType::F32)
}

/// Loads `dir/model.safetensors` (+ `config.json`) and builds the model on `device` with its
/// tensors in `dtype` ([`crate::model_dtype`] picks it for a precision), each weight read from
/// the file straight into that dtype on that device.
pub fn load_on(
    dir: &Path,
    overrides: &ConfigOverrides,
    device: &Device,
    dtype: DType,
) -> Result<Loaded, PolicyError> {
    load_with(dir, overrides, &LayoutOptions::default(), device, dtype)
}

/// [`load_on`] with the user's choices for the layout (tokenizer path, openpi asset id).
pub fn load_with(
    dir: &Path,
    overrides: &ConfigOverrides,
    opts: &LayoutOptions,
    device: &Device,
    dtype: DType,
) -> Result<Loaded, PolicyError> {
    let file = WeightFile::open(&dir.join("model.safetensors"))?;
    let (cfg, layout) = resolve(dir, file.shapes(), overrides, opts)?;
    check_tensors(&cfg, file.shapes())?;
    let stored_dtypes = file.dtypes().to_vec();
    let vb = VarBuilder::from_backend(Box::new(file), dtype, device.clone());
    let model = PiModel::new(&cfg, vb)?;
    Ok(Loaded {
        model,
        stored_dtypes,
        layout,
    })
}

/// Bytes the model's weights take in `dtype` (the f32-kept norms and heads counted as `dtype`:
/// they are a few MB): what a device must hold before activations and the KV cache.
pub fn model_bytes(dir: &Path, dtype: DType) -> Result<u64, PolicyError> {
    let file = WeightFile::open(&dir.join("model.safetensors"))?;
    let cfg = resolve_config(dir, file.shapes(), &ConfigOverrides::default())?;
    let n: usize = expected_tensors(&cfg)
        .iter()
        .map(|(_, s)| s.iter().product::<usize>())
        .sum();
    Ok((n * dtype.size_in_bytes()) as u64)
}

/// What loading `dir` would refuse in its statistics, without loading the weights: the same
/// checks as [`crate::Policy::load`] (several asset ids to choose from, statistics that are
/// not finite, ordered, spread or of sane magnitude, an openpi config they do not fit), so that
/// `chunkrt inspect` and `run` give one verdict.
pub fn verdict(dir: &Path, opts: &LayoutOptions) -> Result<(), PolicyError> {
    let file = WeightFile::open(&dir.join("model.safetensors"))?;
    let (cfg, layout) = resolve(dir, file.shapes(), &ConfigOverrides::default(), opts)?;
    if let Some(problem) = &layout.norm_problem {
        return Err(PolicyError::Config(problem.clone()));
    }
    if let Some(ns) = &layout.norm {
        let mode = match cfg.kind {
            ModelKind::Pi0 => crate::preprocess::NormMode::ZScore,
            ModelKind::Pi05 => crate::preprocess::NormMode::Quantile,
        };
        ns.check(mode, 0)
            .map_err(|e| PolicyError::Config(format!("{}: {e}", dir.display())))?;
    }
    Ok(())
}

/// [`verdict`], and the action statistics held against a robot's joint ranges
/// ([`crate::openpi_config::check_action_ranges`]) as `run` holds them at load.
pub fn verdict_for_robot(
    dir: &Path,
    opts: &LayoutOptions,
    joints: &[crate::openpi_config::JointRange],
) -> Result<(), PolicyError> {
    verdict(dir, opts)?;
    let file = WeightFile::open(&dir.join("model.safetensors"))?;
    let (cfg, layout) = resolve(dir, file.shapes(), &ConfigOverrides::default(), opts)?;
    if let Some(ns) = &layout.norm {
        let mode = match cfg.kind {
            ModelKind::Pi0 => crate::preprocess::NormMode::ZScore,
            ModelKind::Pi05 => crate::preprocess::NormMode::Quantile,
        };
        crate::openpi_config::check_action_ranges(
            layout.openpi.as_ref().map(|(c, _)| *c),
            &cfg.delta_action_mask,
            ns,
            mode,
            cfg.action_dim,
            joints,
        )?;
    }
    Ok(())
}

/// Human-readable description of a checkpoint directory: architecture, parameter counts, dtypes,
/// and what is missing or mismatched.
pub fn inspect(dir: &Path, opts: &LayoutOptions) -> Result<String, PolicyError> {
    use std::fmt::Write;
    // shapes and dtypes from the file's index: no tensor data is read
    let file = WeightFile::open(&dir.join("model.safetensors"))?;
    let (tensors, dtypes) = (file.shapes(), file.dtypes());
    let (cfg, layout) = resolve(dir, tensors, &ConfigOverrides::default(), opts)?;
    let mut s = String::new();
    let _ = writeln!(s, "checkpoint: {}", dir.display());
    s.push_str(&layout.report());
    let _ = writeln!(s, "kind: {}", cfg.kind.name());
    let v = &cfg.vision;
    let _ = writeln!(
        s,
        "vision: SigLIP width {} depth {} heads {} mlp {} patch {} image {} -> {} tokens/camera",
        v.hidden_size,
        v.num_hidden_layers,
        v.num_attention_heads,
        v.intermediate_size,
        v.patch_size,
        v.image_size,
        v.num_tokens()
    );
    for (n, g) in [
        ("paligemma", &cfg.paligemma),
        ("action expert", &cfg.action_expert),
    ] {
        let _ = writeln!(
            s,
            "{n}: width {} depth {} mlp {} heads {} kv heads {} head_dim {}",
            g.width, g.depth, g.mlp_dim, g.num_heads, g.num_kv_heads, g.head_dim
        );
    }
    let _ = writeln!(
        s,
        "vocab {} action_dim {} horizon {} max_token_len {} cameras {:?}",
        cfg.vocab_size, cfg.action_dim, cfg.action_horizon, cfg.max_token_len, cfg.cameras
    );
    for v in &cfg.delayed_views {
        let _ = writeln!(
            s,
            "image input {} is camera {} {} ms earlier (a delayed view)",
            v.name, v.camera, v.delay_ms
        );
    }
    let count = |pred: &dyn Fn(&str) -> bool| -> usize {
        tensors
            .iter()
            .filter(|(k, _)| pred(k))
            .map(|(_, t)| t.iter().product::<usize>())
            .sum()
    };
    let total = count(&|_| true);
    let vision = count(&|k| k.contains("vision_tower") || k.contains("multi_modal_projector"));
    let vlm = count(&|k| k.contains("paligemma.model.language_model"));
    let embed = count(&|k| k == LM_HEAD);
    let expert = count(&|k| k.contains("gemma_expert.model"));
    let _ = writeln!(
        s,
        "parameters: total {total} (vision+projector {vision}, language model {vlm}, token embedding {embed}, action expert {expert}, other {})",
        total - vision - vlm - embed - expert
    );
    let _ = writeln!(s, "stored dtypes: {dtypes:?} ({} tensors)", tensors.len());
    let expected = expected_tensors(&cfg);
    let names: std::collections::HashSet<&str> = expected.iter().map(|(n, _)| n.as_str()).collect();
    let unused: Vec<&String> = tensors
        .keys()
        .filter(|k| !names.contains(k.as_str()))
        .collect();
    if !unused.is_empty() {
        let _ = writeln!(s, "unused tensors (ignored): {}", unused.len());
        for u in unused.iter().take(10) {
            let _ = writeln!(s, "  {u}");
        }
    }
    match check_tensors(&cfg, tensors) {
        Ok(()) => {
            let _ = writeln!(
                s,
                "missing: none (all {} tensors present with the right shapes)",
                expected.len()
            );
        }
        Err(e) => {
            let _ = writeln!(s, "{e}");
        }
    }
    Ok(s)
}
