//! Checkpoints: `model.safetensors` with openpi PyTorch key names or LeRobot's (`model.` prefix),
//! f32 or bf16 (computed in f32), dimensions from `config.json` or a named preset, every tensor
//! checked by name and shape before the model is built.

use std::collections::HashMap;
use std::path::Path;

use candle_core::{DType, Device, Tensor};
use candle_nn::VarBuilder;

use super::config::{ConfigOverrides, ModelConfig, ModelKind};
use super::model::PiModel;
use super::PolicyError;

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

/// π0.5 checkpoints have `time_mlp_in`; π0 ones `state_proj`.
pub fn detect_kind(t: &HashMap<String, Tensor>) -> Option<ModelKind> {
    if t.contains_key("time_mlp_in.weight") {
        Some(ModelKind::Pi05)
    } else if t.contains_key("state_proj.weight") {
        Some(ModelKind::Pi0)
    } else {
        None
    }
}

/// Compares the tensors with what `cfg` needs: one error listing every missing or mismatched
/// tensor by name and shape. Unused tensors (e.g. the expert's `lm_head`) are ignored.
pub fn check_tensors(cfg: &ModelConfig, t: &HashMap<String, Tensor>) -> Result<(), PolicyError> {
    let mut problems = Vec::new();
    for (name, shape) in expected_tensors(cfg) {
        match t.get(&name) {
            None => problems.push(format!("missing {name} {shape:?}")),
            Some(x) if x.dims() != shape.as_slice() => problems.push(format!(
                "mismatched {name}: found {:?}, expected {shape:?}",
                x.dims()
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

/// Dimensions of a checkpoint directory: `config.json` when present, else the preset of the
/// detected kind; then `overrides`; the vocabulary comes from the embedding's shape.
pub fn resolve_config(
    dir: &Path,
    tensors: &HashMap<String, Tensor>,
    overrides: &ConfigOverrides,
) -> Result<ModelConfig, PolicyError> {
    let cfg_path = dir.join("config.json");
    let mut cfg = if cfg_path.exists() {
        ModelConfig::from_file(&cfg_path)?
    } else {
        let kind = detect_kind(tensors).ok_or_else(|| {
            PolicyError::Checkpoint(
                "no config.json and neither state_proj (pi0) nor time_mlp_in (pi05) found".into(),
            )
        })?;
        ModelConfig::preset(kind.name())?
    };
    overrides.apply(&mut cfg)?;
    if let Some(e) = tensors.get(LM_HEAD) {
        let dims = e.dims();
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
    Ok(cfg)
}

/// A loaded checkpoint.
pub struct Loaded {
    /// The model.
    pub model: PiModel,
    /// Dtypes stored in the file.
    pub stored_dtypes: Vec<DType>,
}

/// Loads `dir/model.safetensors` (+ `config.json`) and builds the model.
pub fn load(dir: &Path, overrides: &ConfigOverrides) -> Result<Loaded, PolicyError> {
    let (tensors, stored_dtypes) = load_tensors(&dir.join("model.safetensors"))?;
    let cfg = resolve_config(dir, &tensors, overrides)?;
    check_tensors(&cfg, &tensors)?;
    let vb = VarBuilder::from_tensors(tensors, DType::F32, &Device::Cpu);
    let model = PiModel::new(&cfg, vb)?;
    Ok(Loaded {
        model,
        stored_dtypes,
    })
}

/// Human-readable description of a checkpoint directory: architecture, parameter counts, dtypes,
/// and what is missing or mismatched.
pub fn inspect(dir: &Path) -> Result<String, PolicyError> {
    use std::fmt::Write;
    let (tensors, dtypes) = load_tensors(&dir.join("model.safetensors"))?;
    let cfg = resolve_config(dir, &tensors, &ConfigOverrides::default())?;
    let mut s = String::new();
    let src = if dir.join("config.json").exists() {
        "config.json"
    } else {
        "preset"
    };
    let _ = writeln!(s, "checkpoint: {}", dir.display());
    let _ = writeln!(s, "kind: {} (dimensions from {src})", cfg.kind.name());
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
    let count = |pred: &dyn Fn(&str) -> bool| -> usize {
        tensors
            .iter()
            .filter(|(k, _)| pred(k))
            .map(|(_, t)| t.elem_count())
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
    match check_tensors(&cfg, &tensors) {
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
