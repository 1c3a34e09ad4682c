//! Pre/post-processing: camera frames -> model images, openpi `norm_stats.json`, π0.5 state
//! discretisation into the prompt, prompt formats, tokenizer, padding and un-normalisation.

use std::path::Path;

use serde::Deserialize;

use crate::error::PolicyError;

/// Pixel layout of a raw frame (the `ENCODING_*` codes of `CameraFrameHeader`).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Encoding {
    /// 3 bytes R, G, B.
    Rgb8,
    /// 3 bytes B, G, R.
    Bgr8,
    /// 1 byte grey.
    Mono8,
}

impl Encoding {
    /// Bytes per pixel.
    pub fn bytes_per_pixel(self) -> usize {
        match self {
            Encoding::Mono8 => 1,
            _ => 3,
        }
    }
}

/// Copies a strided frame into packed RGB HWC.
pub fn to_rgb(
    data: &[u8],
    width: usize,
    height: usize,
    stride: usize,
    enc: Encoding,
) -> Result<Vec<u8>, PolicyError> {
    let bpp = enc.bytes_per_pixel();
    if width == 0 || height == 0 || stride < width * bpp {
        return Err(PolicyError::Input(format!(
            "frame {width}x{height} with stride {stride} is invalid"
        )));
    }
    let need = stride * (height - 1) + width * bpp;
    if data.len() < need {
        return Err(PolicyError::Input(format!(
            "frame {width}x{height} stride {stride} needs {need} bytes, got {}",
            data.len()
        )));
    }
    let mut out = Vec::with_capacity(width * height * 3);
    for y in 0..height {
        let row = &data[y * stride..y * stride + width * bpp];
        match enc {
            Encoding::Rgb8 => out.extend_from_slice(row),
            Encoding::Bgr8 => {
                for px in row.chunks_exact(3) {
                    out.extend_from_slice(&[px[2], px[1], px[0]]);
                }
            }
            Encoding::Mono8 => {
                for &g in row {
                    out.extend_from_slice(&[g, g, g]);
                }
            }
        }
    }
    Ok(out)
}

/// Antialiased linear resampling weights along one axis (the triangle kernel of
/// `jax.image.resize(..., "linear")`, widened by the downscale factor): per output index, the first
/// input index and the normalised weights.
fn axis_weights(inp: usize, out: usize) -> Vec<(usize, Vec<f32>)> {
    let scale = out as f64 / inp as f64;
    let ks = scale.min(1.0);
    let radius = 1.0 / ks;
    (0..out)
        .map(|i| {
            let c = (i as f64 + 0.5) / scale - 0.5;
            let lo = ((c - radius).floor().max(0.0)) as usize;
            let hi = ((c + radius).ceil() as usize).min(inp - 1);
            let mut w: Vec<f64> = (lo..=hi)
                .map(|j| (1.0 - ((j as f64 - c) * ks).abs()).max(0.0))
                .collect();
            let s: f64 = w.iter().sum();
            if s > 0.0 {
                w.iter_mut().for_each(|x| *x /= s);
            }
            (lo, w.into_iter().map(|x| x as f32).collect())
        })
        .collect()
}

/// openpi `resize_with_pad`: keeps the aspect ratio, resizes (linear, antialiased, rounded) so
/// the image fits `out_h x out_w`, and pads with black, centred. RGB HWC in and out.
pub fn resize_with_pad(
    rgb: &[u8],
    h: usize,
    w: usize,
    out_h: usize,
    out_w: usize,
) -> Result<Vec<u8>, PolicyError> {
    if rgb.len() != h * w * 3 || h == 0 || w == 0 {
        return Err(PolicyError::Input(format!(
            "rgb buffer of {} bytes for {h}x{w}",
            rgb.len()
        )));
    }
    let ratio = (w as f64 / out_w as f64).max(h as f64 / out_h as f64);
    let rh = ((h as f64 / ratio) as usize).clamp(1, out_h);
    let rw = ((w as f64 / ratio) as usize).clamp(1, out_w);
    let wy = axis_weights(h, rh);
    let wx = axis_weights(w, rw);
    // vertical pass: [rh, w, 3] f32
    let mut tmp = vec![0f32; rh * w * 3];
    for (oy, (lo, ws)) in wy.iter().enumerate() {
        let dst = &mut tmp[oy * w * 3..(oy + 1) * w * 3];
        for (k, &wt) in ws.iter().enumerate() {
            let src = &rgb[(lo + k) * w * 3..(lo + k + 1) * w * 3];
            for (d, &s) in dst.iter_mut().zip(src) {
                *d += wt * s as f32;
            }
        }
    }
    let (py, px) = ((out_h - rh) / 2, (out_w - rw) / 2);
    let mut out = vec![0u8; out_h * out_w * 3];
    for oy in 0..rh {
        let row = &tmp[oy * w * 3..(oy + 1) * w * 3];
        for (ox, (lo, ws)) in wx.iter().enumerate() {
            let mut acc = [0f32; 3];
            for (k, &wt) in ws.iter().enumerate() {
                let s = &row[(lo + k) * 3..(lo + k) * 3 + 3];
                acc[0] += wt * s[0];
                acc[1] += wt * s[1];
                acc[2] += wt * s[2];
            }
            let o = ((oy + py) * out_w + ox + px) * 3;
            for c in 0..3 {
                out[o + c] = acc[c].round().clamp(0.0, 255.0) as u8;
            }
        }
    }
    Ok(out)
}

/// uint8 RGB HWC -> f32 CHW in [-1, 1] (`x / 255 * 2 - 1`), appended to `out`.
pub fn to_model_chw(rgb: &[u8], h: usize, w: usize, out: &mut Vec<f32>) {
    for c in 0..3 {
        for y in 0..h {
            for x in 0..w {
                out.push(rgb[(y * w + x) * 3 + c] as f32 / 255.0 * 2.0 - 1.0);
            }
        }
    }
}

/// Statistics of one quantity in openpi's `norm_stats.json`.
#[derive(Debug, Clone, Deserialize, serde::Serialize, PartialEq)]
pub struct Stats {
    /// Mean.
    pub mean: Vec<f32>,
    /// Standard deviation.
    pub std: Vec<f32>,
    /// 1 % quantile.
    #[serde(default)]
    pub q01: Option<Vec<f32>>,
    /// 99 % quantile.
    #[serde(default)]
    pub q99: Option<Vec<f32>>,
}

/// openpi `norm_stats.json`: `{"norm_stats": {"state": Stats, "actions": Stats}}`.
#[derive(Debug, Clone, Deserialize, serde::Serialize, PartialEq)]
pub struct NormStats {
    /// State statistics.
    pub state: Stats,
    /// Action statistics.
    pub actions: Stats,
}

#[derive(Deserialize)]
struct NormFile {
    norm_stats: NormStats,
}

/// z-score (π0) or quantile to [-1, 1] (π0.5).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum NormMode {
    /// `(x - mean) / (std + 1e-6)`.
    ZScore,
    /// `(x - q01) / (q99 - q01 + 1e-6) * 2 - 1`.
    Quantile,
}

impl NormStats {
    /// The `norm_stats.json` text (openpi's layout).
    pub fn to_json(&self) -> String {
        let v = serde_json::json!({ "norm_stats": self });
        serde_json::to_string_pretty(&v).unwrap_or_default()
    }

    /// Reads a `norm_stats.json`.
    pub fn from_file(path: &Path) -> Result<Self, PolicyError> {
        let s = crate::files::read_side_file(path)?;
        let f: NormFile = serde_json::from_str(&s)
            .map_err(|e| PolicyError::Config(format!("{}: {e}", path.display())))?;
        for (n, st) in [
            ("state", &f.norm_stats.state),
            ("actions", &f.norm_stats.actions),
        ] {
            if st.mean.len() != st.std.len() {
                return Err(PolicyError::Config(format!(
                    "norm_stats {n}: mean/std lengths differ"
                )));
            }
        }
        Ok(f.norm_stats)
    }

    /// Checks at load what every inference will need: for `mode`, the statistics it uses
    /// (z-score: mean and std; quantile: q01 and q99 too), finite, covering at least `n_dof`
    /// values (the robot's joints; 0: not known yet), quantiles ordered.
    pub fn check(&self, mode: NormMode, n_dof: usize) -> Result<(), PolicyError> {
        for (n, st) in [("state", &self.state), ("actions", &self.actions)] {
            let err = |m: String| PolicyError::Config(format!("norm_stats {n}: {m}"));
            let len = st.mean.len();
            if len == 0 || len < n_dof {
                return Err(err(format!("{len} values, the robot has {n_dof} joints")));
            }
            if st.mean.iter().chain(&st.std).any(|x| !x.is_finite()) {
                return Err(err("non-finite mean or std".into()));
            }
            if mode == NormMode::Quantile {
                let (q01, q99) = quantiles(st).map_err(|_| {
                    err("quantile normalisation (pi0.5) needs q01 and q99 of equal length".into())
                })?;
                if q01.len() != len {
                    return Err(err(format!("{} quantiles for {len} means", q01.len())));
                }
                if q01
                    .iter()
                    .zip(q99)
                    .any(|(a, b)| !(a.is_finite() && b.is_finite() && a <= b))
                {
                    return Err(err("q01 must be finite and at most q99".into()));
                }
            }
            // a robot joint whose statistics have no spread divides by ~1e-6: a state a
            // hundredth off becomes 1e4, and the chunk drove the arm to its limits
            let spread: Vec<f32> = match mode {
                NormMode::Quantile => quantiles(st)
                    .map(|(q01, q99)| q01.iter().zip(q99).map(|(a, b)| b - a).collect())
                    .unwrap_or_default(),
                NormMode::ZScore => st.std.clone(),
            };
            let flat: Vec<usize> = (0..n_dof.min(spread.len()))
                .filter(|&i| spread[i] < MIN_SPREAD)
                .collect();
            // statistics far wider than any joint, gripper or end effector moves (a q99 of
            // 1e38 loaded, and the chunks came out at ~1e37 rad: the arm went to its limits at
            // full speed)
            let quant = quantiles(st).ok();
            let wide: Vec<usize> = (0..len)
                .filter(|&i| {
                    let mut xs = vec![st.mean[i], st.std.get(i).copied().unwrap_or(0.0)];
                    if let Some((q01, q99)) = quant {
                        xs.extend([
                            q01.get(i).copied().unwrap_or(0.0),
                            q99.get(i).copied().unwrap_or(0.0),
                        ]);
                    }
                    xs.iter().any(|x| x.abs() > MAX_MAGNITUDE)
                })
                .collect();
            if !wide.is_empty() {
                return Err(err(format!(
                    "dimension(s) {wide:?} have statistics beyond {MAX_MAGNITUDE:e} (a mean, std \
                     or quantile no joint, gripper or end effector reaches): un-normalising by \
                     them would send the arm to its limits; fix the statistics"
                )));
            }
            if !flat.is_empty() {
                return Err(err(format!(
                    "joint(s) {flat:?} have no spread ({} below {MIN_SPREAD}): normalising by it \
                     would turn a small offset into a full-scale action; fix the statistics \
                     (recompute them on data where those joints move)",
                    match mode {
                        NormMode::Quantile => "q99 - q01",
                        NormMode::ZScore => "std",
                    }
                )));
            }
        }
        Ok(())
    }
}

/// The least spread (q99 − q01, or std) a robot joint's statistics may have (rad or m).
pub const MIN_SPREAD: f32 = 1e-4;

/// The largest magnitude a statistic may have (a mean, std or quantile, in rad, m or a
/// normalised unit): 1000 is wider than any joint's range by two orders of magnitude.
pub const MAX_MAGNITUDE: f32 = 1e3;

fn quantiles(s: &Stats) -> Result<(&[f32], &[f32]), PolicyError> {
    match (&s.q01, &s.q99) {
        (Some(a), Some(b)) if a.len() == b.len() => Ok((a, b)),
        _ => Err(PolicyError::Config(
            "quantile normalisation needs q01 and q99 of equal length".into(),
        )),
    }
}

/// Normalises the leading `len(stats)` values of `x` in place (the rest is left unchanged).
pub fn normalize(x: &mut [f32], s: &Stats, mode: NormMode) -> Result<(), PolicyError> {
    match mode {
        NormMode::ZScore => {
            for (i, v) in x.iter_mut().enumerate().take(s.mean.len()) {
                *v = (*v - s.mean[i]) / (s.std[i] + 1e-6);
            }
        }
        NormMode::Quantile => {
            let (q01, q99) = quantiles(s)?;
            for (i, v) in x.iter_mut().enumerate().take(q01.len()) {
                *v = (*v - q01[i]) / (q99[i] - q01[i] + 1e-6) * 2.0 - 1.0;
            }
        }
    }
    Ok(())
}

/// [`normalize`] in f64, as openpi's numpy does it (the statistics widened from f32, the 1e-6 in
/// f64): what π0.5's prompt state is binned from.
pub fn normalize_f64(x: &mut [f64], s: &Stats, mode: NormMode) -> Result<(), PolicyError> {
    match mode {
        NormMode::ZScore => {
            for (i, v) in x.iter_mut().enumerate().take(s.mean.len()) {
                *v = (*v - s.mean[i] as f64) / (s.std[i] as f64 + 1e-6);
            }
        }
        NormMode::Quantile => {
            let (q01, q99) = quantiles(s)?;
            for (i, v) in x.iter_mut().enumerate().take(q01.len()) {
                let (lo, hi) = (q01[i] as f64, q99[i] as f64);
                *v = (*v - lo) / (hi - lo + 1e-6) * 2.0 - 1.0;
            }
        }
    }
    Ok(())
}

/// Inverse of [`normalize`].
pub fn unnormalize(x: &mut [f32], s: &Stats, mode: NormMode) -> Result<(), PolicyError> {
    match mode {
        NormMode::ZScore => {
            for (i, v) in x.iter_mut().enumerate().take(s.mean.len()) {
                *v = *v * (s.std[i] + 1e-6) + s.mean[i];
            }
        }
        NormMode::Quantile => {
            let (q01, q99) = quantiles(s)?;
            for (i, v) in x.iter_mut().enumerate().take(q01.len()) {
                *v = (*v + 1.0) / 2.0 * (q99[i] - q01[i] + 1e-6) + q01[i];
            }
        }
    }
    Ok(())
}

/// π0.5 state bins: `digitize(state, linspace(-1, 1, 257)[:-1]) - 1` on the unpadded normalised
/// state (below -1 -> -1, >= 0.9921875 -> 255). f32 (LeRobot normalises in torch's f32) or f64
/// (openpi normalises the client's state in numpy's f64: [`normalize_f64`]); a value within an
/// f32 rounding of an edge lands on either side depending on which.
pub fn discretize_state<T: Copy + Into<f64>>(state: &[T]) -> Vec<i64> {
    state
        .iter()
        .map(|&s| {
            let s: f64 = s.into();
            // number of edges e_k = -1 + 2k/256 (k = 0..255) with e_k <= s
            let mut n = 0i64;
            for k in 0..256 {
                let e = -1.0 + 2.0 * k as f64 / 256.0;
                if e <= s {
                    n += 1;
                } else {
                    break;
                }
            }
            n - 1
        })
        .collect()
}

/// openpi's prompt cleaning: `strip()`, `_` -> space, newline -> space.
pub fn clean_prompt(p: &str) -> String {
    p.trim().replace(['_', '\n'], " ")
}

/// The π0.5 prompt: `Task: {cleaned}, State: {bins};\nAction: `.
pub fn pi05_prompt(prompt: &str, bins: &[i64]) -> String {
    let b: Vec<String> = bins.iter().map(|x| x.to_string()).collect();
    format!(
        "Task: {}, State: {};\nAction: ",
        clean_prompt(prompt),
        b.join(" ")
    )
}

/// How a checkpoint's training code built π0 prompts (π0.5 prompts are built alike by both).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub enum PromptStyle {
    /// openpi's `PaligemmaTokenizer`: the prompt cleaned (stripped, `_` and newlines as
    /// spaces), then `"\n"` tokenised separately.
    #[default]
    Openpi,
    /// LeRobot's pi0 processor: the task as given with a newline appended, tokenised whole.
    LeRobot,
}

/// Tokenizer of prompts.
pub enum PromptTokenizer {
    /// A `tokenizer.json` (the `tokenizers` crate); `bos` is prepended.
    Hf {
        /// The tokenizer.
        tok: Box<tokenizers::Tokenizer>,
        /// BOS id.
        bos: u32,
    },
    /// A SentencePiece `.model` (openpi's `paligemma_tokenizer.model`), read by
    /// [`crate::sentencepiece`]; its BOS is prepended.
    SentencePiece(Box<crate::sentencepiece::SentencePiece>),
    /// Test double named as such: the fixtures' stand-in byte tokenizer
    /// (`[2] + [byte + 3 ...]`), used when a checkpoint ships no `tokenizer.json`.
    ByteStandIn,
}

impl PromptTokenizer {
    /// Loads a SentencePiece `.model` (it must have a BOS piece).
    pub fn from_sentencepiece(path: &Path) -> Result<Self, PolicyError> {
        let sp = crate::sentencepiece::SentencePiece::from_file(path)?;
        if sp.bos_id().is_none() {
            return Err(PolicyError::Tokenizer(format!(
                "{}: the model has no BOS piece, which openpi's prompts begin with",
                path.display()
            )));
        }
        Ok(PromptTokenizer::SentencePiece(Box::new(sp)))
    }

    /// Which kind of tokenizer this is, for logs and `inspect`.
    pub fn describe(&self) -> String {
        match self {
            PromptTokenizer::Hf { tok, .. } => {
                format!("tokenizer.json, {} ids", tok.get_vocab_size(true))
            }
            PromptTokenizer::SentencePiece(sp) => {
                format!("SentencePiece BPE, {} pieces", sp.vocab_size())
            }
            PromptTokenizer::ByteStandIn => "the byte stand-in (a test double)".into(),
        }
    }

    /// Loads `tokenizer.json`; BOS = the id of `<bos>` (2 when absent).
    pub fn from_file(path: &Path) -> Result<Self, PolicyError> {
        let bytes = crate::files::read_bounded(path, crate::files::MAX_SIDE_FILE_BYTES)?;
        let tok = tokenizers::Tokenizer::from_bytes(&bytes)
            .map_err(|e| PolicyError::Tokenizer(format!("{}: {e}", path.display())))?;
        let bos = tok.token_to_id("<bos>").unwrap_or(2);
        Ok(PromptTokenizer::Hf {
            tok: Box::new(tok),
            bos,
        })
    }

    fn encode(&self, text: &str) -> Result<Vec<u32>, PolicyError> {
        match self {
            PromptTokenizer::Hf { tok, .. } => Ok(tok
                .encode(text, false)
                .map_err(|e| PolicyError::Tokenizer(e.to_string()))?
                .get_ids()
                .to_vec()),
            PromptTokenizer::SentencePiece(sp) => Ok(sp.encode(text)),
            PromptTokenizer::ByteStandIn => Ok(text.bytes().map(|b| b as u32 + 3).collect()),
        }
    }

    /// The largest id this tokenizer can produce, plus one.
    pub fn id_bound(&self) -> usize {
        match self {
            PromptTokenizer::Hf { tok, .. } => tok.get_vocab_size(true),
            PromptTokenizer::SentencePiece(sp) => sp.vocab_size(),
            PromptTokenizer::ByteStandIn => 256 + 3,
        }
    }

    fn bos(&self) -> u32 {
        match self {
            PromptTokenizer::Hf { bos, .. } => *bos,
            // checked at load (from_sentencepiece)
            PromptTokenizer::SentencePiece(sp) => sp.bos_id().unwrap_or(2),
            PromptTokenizer::ByteStandIn => 2,
        }
    }

    /// π0: BOS + cleaned prompt, then `"\n"` tokenized separately; π0.5 (`state_bins` given):
    /// BOS + the π0.5 prompt. Padded with 0 / truncated to `max_len`; returns ids and mask
    /// (openpi's `PaligemmaTokenizer.tokenize`). [`Self::tokenize_counted`] also says how long
    /// the prompt was before truncation.
    pub fn tokenize(
        &self,
        prompt: &str,
        state_bins: Option<&[i64]>,
        max_len: usize,
    ) -> Result<(Vec<u32>, Vec<bool>), PolicyError> {
        let (ids, mask, _) = self.tokenize_counted(prompt, state_bins, max_len)?;
        Ok((ids, mask))
    }

    /// [`Self::tokenize`], with the untruncated length as the third value.
    pub fn tokenize_counted(
        &self,
        prompt: &str,
        state_bins: Option<&[i64]>,
        max_len: usize,
    ) -> Result<(Vec<u32>, Vec<bool>, usize), PolicyError> {
        self.tokenize_styled(prompt, state_bins, max_len, PromptStyle::Openpi)
    }

    /// [`Self::tokenize_counted`] in a checkpoint's own prompt style.
    pub fn tokenize_styled(
        &self,
        prompt: &str,
        state_bins: Option<&[i64]>,
        max_len: usize,
        style: PromptStyle,
    ) -> Result<(Vec<u32>, Vec<bool>, usize), PolicyError> {
        let mut ids = vec![self.bos()];
        match (state_bins, style) {
            (Some(b), _) => ids.extend(self.encode(&pi05_prompt(prompt, b))?),
            (None, PromptStyle::Openpi) => {
                ids.extend(self.encode(&clean_prompt(prompt))?);
                ids.extend(self.encode("\n")?);
            }
            (None, PromptStyle::LeRobot) => {
                // LeRobot's pi0 pre-processor: the task as given, a newline appended unless it
                // ends with one, tokenised in one piece
                if prompt.ends_with('\n') {
                    ids.extend(self.encode(prompt)?);
                } else {
                    ids.extend(self.encode(&format!("{prompt}\n"))?);
                }
            }
        }
        let full = ids.len();
        ids.truncate(max_len);
        let n = ids.len();
        ids.resize(max_len, 0);
        let mask = (0..max_len).map(|i| i < n).collect();
        Ok((ids, mask, full))
    }
}
