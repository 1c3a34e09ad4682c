//! The openpi fixtures in `tests/data` (model, inputs, reference outputs) and tensor comparison
//! helpers, shared by the policy tests (`#[path = "common/fixture.rs"] mod fixture;`).
#![allow(dead_code)]

use std::collections::HashMap;
use std::path::PathBuf;

use candle_core::{DType, Device, Tensor};
use chunkrt_policy::checkpoint;
use chunkrt_policy::model::{ModelInputs, PiModel};
use chunkrt_policy::ConfigOverrides;

/// `tests/data/<name>` of this checkout; a test binary carried to another machine (the GPU
/// machine: scripts/gpu-package.sh) finds it under the working directory instead.
pub fn data(name: &str) -> PathBuf {
    let built = PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("tests/data");
    let root = if built.exists() {
        built
    } else {
        PathBuf::from("tests/data")
    };
    root.join(name)
}

/// One raw camera frame of a fixture: (camera name, RGB8 pixels, height, width).
pub type Frame = (String, Vec<u8>, usize, usize);

/// The raw camera frames (`image_raw_uint8.<camera>`) and the unpadded state of fixture `name`,
/// as a robot would send them.
pub fn raw_observation(name: &str, cameras: &[&str]) -> (Vec<Frame>, Vec<f64>) {
    let inp: HashMap<String, Tensor> =
        candle_core::safetensors::load(data(name).join("inputs.safetensors"), &Device::Cpu)
            .expect("fixture inputs load");
    let frames = cameras
        .iter()
        .map(|c| {
            let t = &inp[&format!("image_raw_uint8.{c}")];
            let (_, h, w, _) = t.dims4().expect("a [1, H, W, 3] frame");
            let px = t.flatten_all().and_then(|t| t.to_vec1::<u8>());
            (c.to_string(), px.expect("u8 pixels"), h, w)
        })
        .collect();
    let state = inp["state_unpadded.0"]
        .to_vec1::<f32>()
        .expect("f32 state")
        .iter()
        .map(|&x| x as f64)
        .collect();
    (frames, state)
}

/// [`Frame`]s as the policy's raw RGB8 frames.
pub fn raw_frames(frames: &[Frame]) -> Vec<chunkrt_policy::RawFrame<'_>> {
    frames
        .iter()
        .map(|(c, d, h, w)| chunkrt_policy::RawFrame {
            camera: c,
            width: *w as u32,
            height: *h as u32,
            stride: (*w * 3) as u32,
            encoding: chunkrt_policy::Encoding::Rgb8,
            data: d,
        })
        .collect()
}

pub struct Fixture {
    pub model: PiModel,
    pub inputs: ModelInputs,
    pub raw: HashMap<String, Tensor>,
    pub out: HashMap<String, Tensor>,
}

pub fn mask_vec(t: &Tensor) -> Vec<bool> {
    t.flatten_all()
        .unwrap()
        .to_dtype(DType::U8)
        .unwrap()
        .to_vec1::<u8>()
        .unwrap()
        .into_iter()
        .map(|v| v != 0)
        .collect()
}

pub fn load(name: &str) -> Fixture {
    load_on(name, &Device::Cpu, DType::F32)
}

/// The fixture's model on `device` with its tensors in `dtype`, and its inputs on that device.
pub fn load_on(name: &str, device: &Device, dtype: DType) -> Fixture {
    let dir = data(name);
    let loaded = checkpoint::load_on(&dir, &ConfigOverrides::default(), device, dtype)
        .expect("fixture loads");
    let model = loaded.model;
    let raw = candle_core::safetensors::load(dir.join("inputs.safetensors"), &Device::Cpu).unwrap();
    let out =
        candle_core::safetensors::load(dir.join("outputs.safetensors"), &Device::Cpu).unwrap();
    let cams = model.cfg.cameras.clone();
    let images = cams
        .iter()
        .map(|c| raw[&format!("image.{c}")].to_device(device).unwrap())
        .collect();
    let image_masks = cams
        .iter()
        .map(|c| mask_vec(&raw[&format!("image_mask.{c}")]))
        .collect();
    let tm = &raw["tokenized_prompt_mask"];
    let (b, lt) = tm.dims2().unwrap();
    let flat = mask_vec(tm);
    let token_mask = (0..b)
        .map(|i| flat[i * lt..(i + 1) * lt].to_vec())
        .collect();
    let inputs = ModelInputs {
        images,
        image_masks,
        tokens: raw["tokenized_prompt"].to_device(device).unwrap(),
        token_mask,
        state: raw["state"].to_device(device).unwrap(),
    };
    Fixture {
        model,
        inputs,
        raw,
        out,
    }
}

pub fn maxdiff(a: &Tensor, b: &Tensor) -> f32 {
    assert_eq!(a.dims(), b.dims(), "shape");
    (a - b)
        .unwrap()
        .abs()
        .unwrap()
        .flatten_all()
        .unwrap()
        .max(0)
        .unwrap()
        .to_scalar::<f32>()
        .unwrap()
}

/// Rows of `t` along `dim` where `valid` is true.
pub fn valid_rows(t: &Tensor, dim: usize, valid: &[bool]) -> Tensor {
    let idx: Vec<u32> = valid
        .iter()
        .enumerate()
        .filter(|(_, v)| **v)
        .map(|(i, _)| i as u32)
        .collect();
    let idx = Tensor::new(idx.as_slice(), &Device::Cpu).unwrap();
    t.index_select(&idx, dim).unwrap()
}

/// max |t| (f32).
pub fn absmax(t: &Tensor) -> f32 {
    t.to_dtype(DType::F32)
        .unwrap()
        .abs()
        .unwrap()
        .max_all()
        .unwrap()
        .to_scalar::<f32>()
        .unwrap()
}

/// max |a - b| / RMS(b): the relative deviation of `a` from the reference `b`.
pub fn rel_maxdiff(a: &Tensor, b: &Tensor) -> f64 {
    let rms = b
        .to_dtype(DType::F32)
        .unwrap()
        .sqr()
        .unwrap()
        .mean_all()
        .unwrap()
        .to_scalar::<f32>()
        .unwrap()
        .sqrt() as f64;
    maxdiff(
        &a.to_dtype(DType::F32)
            .unwrap()
            .to_device(&Device::Cpu)
            .unwrap(),
        &b.to_dtype(DType::F32)
            .unwrap()
            .to_device(&Device::Cpu)
            .unwrap(),
    ) as f64
        / rms.max(1e-12)
}
