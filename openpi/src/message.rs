//! The protocol's three messages, as typed values: the metadata a server sends on connect, an
//! observation request, and the reply with the action chunk.
//!
//! **Request** (client → server, binary): a msgpack-numpy map laid out as a [`Layout`] says
//! (images as uint8 arrays, the state as float arrays, the prompt as a str), plus optional
//! chunkrt keys that openpi servers ignore (every key starts with `chunkrt/`):
//!
//! | key | value | meaning |
//! |---|---|---|
//! | `chunkrt/guidance/actions` | float `[H, n]` | RTC: the previous chunk's actions the new one should continue (robot units; row i is for the new chunk's action i) |
//! | `chunkrt/guidance/weights` | float `[H]` | RTC: the soft mask W (1 on the actions executed while the chunk is computed) |
//! | `chunkrt/guidance/beta` | float | RTC: the guidance clip β |
//! | `chunkrt/guidance/jacobian` | `"identity"` or `"vjp"` | RTC: how the guidance treats the Jacobian |
//! | `chunkrt/committed` | float `[d, n]` | training-time RTC: the chunk's first d actions, given |
//! | `chunkrt/delay_steps` | int | the controller's inference-delay estimate (action steps; informational) |
//! | `chunkrt/reseed` | int | restart the server policy's noise sequence from this seed before this chunk |
//!
//! The state to observe needs no key of its own: with future-state inference the client sends
//! the state the robot will have reached as the state.
//!
//! **Reply** (server → client, binary): `{"actions": float32 [H, n], "policy_timing": {"infer_ms"},
//! "server_timing": {"infer_ms", "prev_total_ms"}}` as openpi's server sends it
//! (`prev_total_ms` from the second reply of a connection on). A client also reads a bare
//! ndarray reply (vLLM-Omni) and float64 actions (openpi's own un-normalisation yields them).
//! An error is a text frame, then a close with code 1011.
//!
//! **Metadata** (server → client, binary, once on connect): a msgpack map; chunkrt's server
//! puts what a client needs to check the fit under `chunkrt` ([`ChunkrtMetadata`]).

use crate::layout::{KeyPath, Layout};
use crate::msgpack::{DType, NdArray, Value, Writer};

/// The chunkrt keys of a request.
pub mod keys {
    /// RTC: the previous chunk's actions.
    pub const GUIDANCE_ACTIONS: &str = "chunkrt/guidance/actions";
    /// RTC: the soft mask.
    pub const GUIDANCE_WEIGHTS: &str = "chunkrt/guidance/weights";
    /// RTC: β.
    pub const GUIDANCE_BETA: &str = "chunkrt/guidance/beta";
    /// RTC: the Jacobian.
    pub const GUIDANCE_JACOBIAN: &str = "chunkrt/guidance/jacobian";
    /// Training-time RTC: the committed actions.
    pub const COMMITTED: &str = "chunkrt/committed";
    /// The delay estimate.
    pub const DELAY_STEPS: &str = "chunkrt/delay_steps";
    /// A new noise seed.
    pub const RESEED: &str = "chunkrt/reseed";
    /// The metadata's chunkrt map.
    pub const METADATA: &str = "chunkrt";
}

/// A request that cannot be served, with what is wrong in words a client can act on.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
#[error("{0}")]
pub struct RequestError(pub String);

fn err(s: impl Into<String>) -> RequestError {
    RequestError(s.into())
}

/// One image of a request, tightly packed HWC (converted from CHW or float if it came so).
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Image {
    /// The image input it feeds.
    pub name: String,
    /// Pixels per row.
    pub width: u32,
    /// Rows.
    pub height: u32,
    /// 3 (RGB) or 1 (grey).
    pub channels: u8,
    /// `height * width * channels` bytes.
    pub data: Vec<u8>,
}

/// RTC guidance as it travels (robot units).
#[derive(Debug, Clone, PartialEq)]
pub struct WireGuidance {
    /// `[rows][n]` row-major.
    pub actions: Vec<f64>,
    /// Rows of `actions`.
    pub rows: usize,
    /// One per row.
    pub weights: Vec<f64>,
    /// β.
    pub beta: f64,
    /// `identity` or `vjp`.
    pub jacobian: String,
}

/// A decoded, checked observation request.
#[derive(Debug, Clone, PartialEq)]
pub struct Request {
    /// The images found, in the order they were asked for.
    pub images: Vec<Image>,
    /// The state (its parts concatenated), finite.
    pub state: Vec<f64>,
    /// The prompt, if the request has one.
    pub prompt: Option<String>,
    /// RTC guidance.
    pub guidance: Option<WireGuidance>,
    /// Training-time RTC: `[d][n]` row-major.
    pub committed: Option<Vec<f64>>,
    /// The client's delay estimate.
    pub delay_steps: Option<u64>,
    /// A new noise seed.
    pub reseed: Option<u64>,
}

/// The largest image side a request may carry.
pub const MAX_IMAGE_SIDE: usize = 8192;
/// The most state values a request may carry.
pub const MAX_STATE: usize = 1024;

fn image(
    name: &str,
    key: &KeyPath,
    a: &NdArray<'_>,
    prefer_chw: bool,
) -> Result<Image, RequestError> {
    let what = || format!("image {key} (input {name})");
    let channels = |c: usize| c == 3 || c == 1;
    let (h, w, c, chw) = match a.shape[..] {
        [h, w] => (h, w, 1, false),
        // both readings fit (a 3-pixel-wide image): the layout's own order decides
        [c, h, w] if channels(c) && channels(w) && prefer_chw => (h, w, c, true),
        [h, w, c] if channels(c) => (h, w, c, false),
        [c, h, w] if channels(c) => (h, w, c, true),
        _ => {
            return Err(err(format!(
                "{}: shape {:?}; expected [H, W, 3] or [3, H, W]",
                what(),
                a.shape
            )))
        }
    };
    if h == 0 || w == 0 || h > MAX_IMAGE_SIDE || w > MAX_IMAGE_SIDE {
        return Err(err(format!(
            "{}: {w}x{h} pixels; each side must be 1..={MAX_IMAGE_SIDE}",
            what()
        )));
    }
    let n = h * w * c;
    // uint8 as it is; floats as openpi's _parse_image reads them (255·x), clamped
    let px = |i: usize| -> Result<u8, RequestError> {
        match a.dtype {
            DType::U8 => Ok(a.data[i]),
            DType::F32 | DType::F64 | DType::F16 => {
                let v = a.get_f64(i).unwrap_or(f64::NAN);
                if !v.is_finite() {
                    return Err(err(format!("{}: a pixel is not finite", what())));
                }
                Ok((255.0 * v).clamp(0.0, 255.0) as u8)
            }
            other => Err(err(format!(
                "{}: dtype {other}; expected uint8 (or float in [0, 1])",
                what()
            ))),
        }
    };
    let mut data = Vec::with_capacity(n);
    if chw {
        for y in 0..h {
            for x in 0..w {
                for ch in 0..c {
                    data.push(px(ch * h * w + y * w + x)?);
                }
            }
        }
    } else if a.dtype == DType::U8 {
        data.extend_from_slice(a.data);
    } else {
        for i in 0..n {
            data.push(px(i)?);
        }
    }
    Ok(Image {
        name: name.to_string(),
        width: w as u32,
        height: h as u32,
        channels: c as u8,
        data,
    })
}

fn floats(v: &Value<'_>, what: &str) -> Result<(Vec<f64>, Vec<usize>), RequestError> {
    let (vals, shape) = match v {
        Value::NdArray(a) => match a.dtype {
            DType::Bool => return Err(err(format!("{what}: a bool array; expected numbers"))),
            _ => (a.to_f64(), a.shape.clone()),
        },
        Value::Array(xs) => {
            let vals = xs
                .iter()
                .map(|x| x.as_f64())
                .collect::<Option<Vec<_>>>()
                .ok_or_else(|| err(format!("{what}: a list with a non-number")))?;
            let n = vals.len();
            (vals, vec![n])
        }
        other => match other.as_f64() {
            Some(x) => (vec![x], vec![]),
            None => {
                return Err(err(format!(
                    "{what}: {}; expected a float array",
                    other.kind()
                )))
            }
        },
    };
    if let Some(i) = vals.iter().position(|x| !x.is_finite()) {
        return Err(err(format!("{what}: value {i} is not finite")));
    }
    Ok((vals, shape))
}

fn matrix(v: &Value<'_>, what: &str, n: usize) -> Result<(Vec<f64>, usize), RequestError> {
    let (vals, shape) = floats(v, what)?;
    match shape[..] {
        [rows, cols] if cols == n && rows <= 4096 => Ok((vals, rows)),
        _ => Err(err(format!(
            "{what}: shape {shape:?}; expected [rows, {n}] (the state has {n} values)"
        ))),
    }
}

impl Request {
    /// Reads a request laid out as `layout` asks, for the image inputs `image_names` (those the
    /// layout lists as optional may be absent; an absent image is masked, as openpi does with a
    /// missing wrist camera). `msg` is the decoded message.
    pub fn parse(
        msg: &Value<'_>,
        layout: &Layout,
        image_names: &[String],
    ) -> Result<Request, RequestError> {
        let optional = &layout.optional;
        if !matches!(msg, Value::Map(_)) {
            return Err(err(format!(
                "the observation is {}; expected a map (a dict of arrays)",
                msg.kind()
            )));
        }
        let mut images = Vec::new();
        for name in image_names {
            let Some(key) = layout.image_key(name) else {
                continue;
            };
            match key.find(msg) {
                Some(Value::NdArray(a)) => images.push(image(name, &key, a, layout.chw)?),
                Some(other) => {
                    return Err(err(format!(
                        "image {key} (input {name}) is {}; expected a uint8 array",
                        other.kind()
                    )))
                }
                // chunkrt's own layout names every input; the ones a robot has no camera for
                // are masked, as the policy in process masks them (at least one must come)
                None if optional.contains(name) || layout.images.is_none() => {}
                None => {
                    return Err(err(format!(
                        "missing key {key}: the image for input {name} (layout {})",
                        layout.preset.name()
                    )))
                }
            }
        }
        if images.is_empty() && !image_names.is_empty() {
            let keys: Vec<String> = image_names
                .iter()
                .filter_map(|n| layout.image_key(n).map(|k| k.to_string()))
                .collect();
            return Err(err(format!(
                "no image: expected at least one of the keys {} (layout {})",
                keys.join(", "),
                layout.preset.name()
            )));
        }
        let mut state = Vec::new();
        for k in &layout.state {
            let v = k.find(msg).ok_or_else(|| {
                err(format!(
                    "missing key {k}: the state (layout {})",
                    layout.preset.name()
                ))
            })?;
            let (vals, shape) = floats(v, &format!("state {k}"))?;
            if shape.len() > 1 {
                return Err(err(format!(
                    "state {k}: shape {shape:?}; expected a vector"
                )));
            }
            state.extend(vals);
        }
        if state.is_empty() || state.len() > MAX_STATE {
            return Err(err(format!(
                "the state has {} values; expected 1..={MAX_STATE}",
                state.len()
            )));
        }
        let prompt = match layout.prompt.find(msg) {
            None | Some(Value::Nil) => None,
            Some(v) => Some(
                v.key_str()
                    .ok_or_else(|| {
                        err(format!(
                            "prompt {} is {}; expected a str",
                            layout.prompt,
                            v.kind()
                        ))
                    })?
                    .to_string(),
            ),
        };
        let n = state.len();
        let guidance = match msg.get(keys::GUIDANCE_ACTIONS) {
            None => None,
            Some(v) => {
                let (actions, rows) = matrix(v, keys::GUIDANCE_ACTIONS, n)?;
                let weights = msg
                    .get(keys::GUIDANCE_WEIGHTS)
                    .ok_or_else(|| {
                        err(format!(
                            "{} without {}",
                            keys::GUIDANCE_ACTIONS,
                            keys::GUIDANCE_WEIGHTS
                        ))
                    })
                    .and_then(|w| floats(w, keys::GUIDANCE_WEIGHTS))?
                    .0;
                if weights.len() != rows || weights.iter().any(|w| *w < 0.0) {
                    return Err(err(format!(
                        "{}: {} values; expected {rows}, each >= 0",
                        keys::GUIDANCE_WEIGHTS,
                        weights.len()
                    )));
                }
                let beta = msg
                    .get(keys::GUIDANCE_BETA)
                    .and_then(Value::as_f64)
                    .ok_or_else(|| {
                        err(format!("{}: missing or not a number", keys::GUIDANCE_BETA))
                    })?;
                if !beta.is_finite() || beta < 0.0 {
                    return Err(err(format!(
                        "{}: {beta}; expected >= 0",
                        keys::GUIDANCE_BETA
                    )));
                }
                let jacobian = match msg.get(keys::GUIDANCE_JACOBIAN) {
                    None => "identity".to_string(),
                    Some(v) => match v.key_str() {
                        Some(s @ ("identity" | "vjp")) => s.to_string(),
                        _ => {
                            return Err(err(format!(
                                "{}: expected \"identity\" or \"vjp\"",
                                keys::GUIDANCE_JACOBIAN
                            )))
                        }
                    },
                };
                Some(WireGuidance {
                    actions,
                    rows,
                    weights,
                    beta,
                    jacobian,
                })
            }
        };
        let committed = match msg.get(keys::COMMITTED) {
            None => None,
            Some(v) => Some(matrix(v, keys::COMMITTED, n)?.0),
        };
        if guidance.is_some() && committed.is_some() {
            return Err(err(format!(
                "{} and {} together: a chunk is guided or given a committed prefix, not both",
                keys::GUIDANCE_ACTIONS,
                keys::COMMITTED
            )));
        }
        let int = |k: &str| -> Result<Option<u64>, RequestError> {
            match msg.get(k) {
                None => Ok(None),
                Some(v) => v
                    .as_u64()
                    .map(Some)
                    .ok_or_else(|| err(format!("{k}: {}; expected an integer >= 0", v.kind()))),
            }
        };
        Ok(Request {
            images,
            state,
            prompt,
            guidance,
            committed,
            delay_steps: int(keys::DELAY_STEPS)?,
            reseed: int(keys::RESEED)?,
        })
    }
}

/// One image to send: tightly packed HWC pixels.
#[derive(Debug, Clone, Copy)]
pub struct ImageRef<'a> {
    /// The image input it feeds (the camera's name).
    pub name: &'a str,
    /// Pixels per row.
    pub width: usize,
    /// Rows.
    pub height: usize,
    /// 3 or 1.
    pub channels: usize,
    /// `height * width * channels` bytes.
    pub data: &'a [u8],
}

/// What a client sends (borrowed).
#[derive(Debug, Clone, Copy)]
pub struct Outgoing<'a> {
    /// Images.
    pub images: &'a [ImageRef<'a>],
    /// The state, split over the layout's state keys by `state_split` (sizes; empty: all
    /// under the first key).
    pub state: &'a [f64],
    /// Sizes of the state's parts (one per state key of the layout).
    pub state_split: &'a [usize],
    /// The prompt.
    pub prompt: &'a str,
    /// RTC guidance (`[rows][n]` actions, rows weights, β, Jacobian).
    pub guidance: Option<(&'a [f64], &'a [f32], f64, &'a str)>,
    /// Training-time RTC: `[d][n]`.
    pub committed: Option<&'a [f64]>,
    /// The delay estimate.
    pub delay_steps: Option<u64>,
    /// A new noise seed.
    pub reseed: Option<u64>,
}

/// A map being written whose length is known only at the end: entries go into a scratch
/// buffer and the header is written before them.
struct Entries<'w> {
    out: &'w mut Writer,
    body: Writer,
    n: usize,
}

impl<'w> Entries<'w> {
    fn new(out: &'w mut Writer) -> Self {
        Self {
            out,
            body: Writer::new(),
            n: 0,
        }
    }

    fn entry(&mut self, key: &str) -> &mut Writer {
        self.n += 1;
        self.body.str(key)
    }

    fn finish(self) {
        self.out.map(self.n);
        self.out.buf.extend_from_slice(&self.body.buf);
    }
}

/// A tree of nested keys for the request (ALOHA's `images` map).
enum Node<'a> {
    Leaf(Box<dyn Fn(&mut Writer) + 'a>),
    Map(Vec<(String, Node<'a>)>),
}

fn insert<'a>(tree: &mut Vec<(String, Node<'a>)>, path: &[&str], leaf: Node<'a>) {
    let Some((first, rest)) = path.split_first() else {
        return;
    };
    if rest.is_empty() {
        tree.push((first.to_string(), leaf));
        return;
    }
    if let Some((_, Node::Map(sub))) = tree.iter_mut().find(|(k, _)| k == first) {
        insert(sub, rest, leaf);
        return;
    }
    let mut sub = Vec::new();
    insert(&mut sub, rest, leaf);
    tree.push((first.to_string(), Node::Map(sub)));
}

fn write_tree(w: &mut Writer, tree: &[(String, Node<'_>)]) {
    w.map(tree.len());
    for (k, node) in tree {
        w.str(k);
        match node {
            Node::Leaf(f) => f(w),
            Node::Map(sub) => write_tree(w, sub),
        }
    }
}

impl Outgoing<'_> {
    /// Packs the request into `w` as `layout` lays it out (images HWC, or CHW when the layout
    /// says so; the state as float64 arrays; the chunkrt keys at the top level).
    pub fn write(&self, layout: &Layout, w: &mut Writer) -> Result<(), RequestError> {
        let mut tree: Vec<(String, Node<'_>)> = Vec::new();
        for img in self.images {
            let Some(key) = layout.image_key(img.name) else {
                continue;
            };
            let (wd, ht, c, data) = (img.width, img.height, img.channels, img.data);
            if data.len() != wd * ht * c {
                return Err(err(format!(
                    "image {}: {} bytes for {wd}x{ht}x{c}",
                    img.name,
                    data.len()
                )));
            }
            let chw = layout.chw;
            insert(
                &mut tree,
                &key.segments(),
                Node::Leaf(Box::new(move |w: &mut Writer| {
                    if chw {
                        w.ndarray_with(DType::U8, &[c, ht, wd], |b| {
                            for ch in 0..c {
                                b.extend((0..ht * wd).map(|p| data[p * c + ch]));
                            }
                        });
                    } else {
                        w.u8_array(&[ht, wd, c], data);
                    }
                })),
            );
        }
        let parts: Vec<usize> = if self.state_split.is_empty() {
            vec![self.state.len()]
        } else {
            self.state_split.to_vec()
        };
        if parts.len() > layout.state.len() || parts.iter().sum::<usize>() != self.state.len() {
            return Err(err(format!(
                "the state's {} values do not split as {parts:?} over {} keys",
                self.state.len(),
                layout.state.len()
            )));
        }
        let mut at = 0;
        for (k, &len) in layout.state.iter().zip(&parts) {
            let part = &self.state[at..at + len];
            at += len;
            insert(
                &mut tree,
                &k.segments(),
                Node::Leaf(Box::new(move |w: &mut Writer| {
                    w.f64_array(&[part.len()], part);
                })),
            );
        }
        let prompt = self.prompt;
        insert(
            &mut tree,
            &layout.prompt.segments(),
            Node::Leaf(Box::new(move |w: &mut Writer| {
                w.str(prompt);
            })),
        );
        let n = self.state.len().max(1);
        if let Some((actions, weights, beta, jacobian)) = self.guidance {
            let rows = actions.len() / n;
            insert(
                &mut tree,
                &[keys::GUIDANCE_ACTIONS],
                Node::Leaf(Box::new(move |w: &mut Writer| {
                    w.f64_array(&[rows, n], actions);
                })),
            );
            insert(
                &mut tree,
                &[keys::GUIDANCE_WEIGHTS],
                Node::Leaf(Box::new(move |w: &mut Writer| {
                    w.ndarray_with(DType::F32, &[weights.len()], |b| {
                        for x in weights {
                            b.extend_from_slice(&x.to_le_bytes());
                        }
                    });
                })),
            );
            insert(
                &mut tree,
                &[keys::GUIDANCE_BETA],
                Node::Leaf(Box::new(move |w: &mut Writer| {
                    w.f64(beta);
                })),
            );
            insert(
                &mut tree,
                &[keys::GUIDANCE_JACOBIAN],
                Node::Leaf(Box::new(move |w: &mut Writer| {
                    w.str(jacobian);
                })),
            );
        }
        if let Some(c) = self.committed {
            let rows = c.len() / n;
            insert(
                &mut tree,
                &[keys::COMMITTED],
                Node::Leaf(Box::new(move |w: &mut Writer| {
                    w.f64_array(&[rows, n], c);
                })),
            );
        }
        for (k, v) in [
            (keys::DELAY_STEPS, self.delay_steps),
            (keys::RESEED, self.reseed),
        ] {
            if let Some(v) = v {
                insert(
                    &mut tree,
                    &[k],
                    Node::Leaf(Box::new(move |w: &mut Writer| {
                        w.uint(v);
                    })),
                );
            }
        }
        write_tree(w, &tree);
        Ok(())
    }
}

/// A reply: the chunk and the timings.
#[derive(Debug, Clone, PartialEq)]
pub struct Reply {
    /// `[horizon][dims]` row-major.
    pub actions: Vec<f64>,
    /// Rows.
    pub horizon: usize,
    /// Columns.
    pub dims: usize,
    /// `policy_timing.infer_ms` (the model's time), when sent.
    pub policy_infer_ms: Option<f64>,
    /// `server_timing.infer_ms`, when sent.
    pub server_infer_ms: Option<f64>,
    /// `server_timing.prev_total_ms`, when sent.
    pub prev_total_ms: Option<f64>,
}

impl Reply {
    /// Packs a chunkrt server's reply (actions as float32, as openpi's clients expect).
    pub fn write(&self, w: &mut Writer) {
        let mut m = Entries::new(w);
        m.entry("actions")
            .f32_array(&[self.horizon, self.dims], &self.actions);
        if let Some(ms) = self.policy_infer_ms {
            m.entry("policy_timing").map(1).str("infer_ms").f64(ms);
        }
        if self.server_infer_ms.is_some() || self.prev_total_ms.is_some() {
            let n = self.server_infer_ms.is_some() as usize + self.prev_total_ms.is_some() as usize;
            let t = m.entry("server_timing").map(n);
            if let Some(ms) = self.server_infer_ms {
                t.str("infer_ms").f64(ms);
            }
            if let Some(ms) = self.prev_total_ms {
                t.str("prev_total_ms").f64(ms);
            }
        }
        m.finish();
    }

    /// Reads a reply: a map with `actions` (openpi, SGLang) or a bare ndarray (vLLM-Omni);
    /// float32 or float64, `[H, D]`, finite.
    pub fn parse(msg: &Value<'_>) -> Result<Reply, RequestError> {
        let (actions, rest) = match msg {
            Value::NdArray(a) => (a, None),
            Value::Map(_) => match msg.get("actions") {
                Some(Value::NdArray(a)) => (a, Some(msg)),
                Some(other) => {
                    return Err(err(format!(
                        "the reply's 'actions' is {}; expected an array",
                        other.kind()
                    )))
                }
                None => {
                    if let Some(m) = msg.get("message").or_else(|| msg.get("error")) {
                        return Err(err(format!(
                            "the server answered with an error: {}",
                            m.key_str().unwrap_or("(not a str)")
                        )));
                    }
                    return Err(err("the reply has no 'actions'"));
                }
            },
            other => {
                return Err(err(format!(
                    "the reply is {}; expected a map with 'actions'",
                    other.kind()
                )))
            }
        };
        let (horizon, dims) = match actions.shape[..] {
            [h, d] => (h, d),
            [1, h, d] => (h, d),
            _ => {
                return Err(err(format!(
                    "the reply's actions have shape {:?}; expected [H, D]",
                    actions.shape
                )))
            }
        };
        if !matches!(actions.dtype, DType::F32 | DType::F64 | DType::F16) {
            return Err(err(format!(
                "the reply's actions are {}; expected float32 or float64",
                actions.dtype
            )));
        }
        let vals = actions.to_f64();
        if let Some(i) = vals.iter().position(|x| !x.is_finite()) {
            return Err(err(format!(
                "the reply's action {}, dim {} is not finite",
                i / dims.max(1),
                i % dims.max(1)
            )));
        }
        let timing = |outer: &str, inner: &str| {
            rest.and_then(|m| m.get(outer))
                .and_then(|t| t.get(inner))
                .and_then(Value::as_f64)
        };
        Ok(Reply {
            actions: vals,
            horizon,
            dims,
            policy_infer_ms: timing("policy_timing", "infer_ms"),
            server_infer_ms: timing("server_timing", "infer_ms"),
            prev_total_ms: timing("server_timing", "prev_total_ms"),
        })
    }
}

/// `text` as a log line or an error reply may carry it: at most `max` bytes (cut at a character
/// boundary), the original length said when cut. Outside data (a prompt, a key, a value) never
/// makes a line longer than its caller allows.
pub fn clip_text(text: &str, max: usize) -> std::borrow::Cow<'_, str> {
    if text.len() <= max {
        return std::borrow::Cow::Borrowed(text);
    }
    let mut end = max;
    while !text.is_char_boundary(end) {
        end -= 1;
    }
    std::borrow::Cow::Owned(format!("{}… ({} bytes in all)", &text[..end], text.len()))
}

/// What a chunkrt server says about its policy (the metadata's `chunkrt` map).
#[derive(Debug, Clone, PartialEq, Default)]
pub struct ChunkrtMetadata {
    /// chunkrt's version.
    pub version: String,
    /// `pi0` or `pi05`.
    pub model: String,
    /// Actions per chunk.
    pub action_horizon: usize,
    /// The model's (padded) action dimension: the most state / action values it takes.
    pub action_dim: usize,
    /// The image inputs, in the model's order.
    pub image_inputs: Vec<String>,
    /// The conditionings it serves beside a fresh chunk: `guided`, `committed`.
    pub conditioning: Vec<String>,
    /// The longest committed prefix (0: none).
    pub rtc_prefix_max: usize,
    /// The request layout's preset.
    pub layout: String,
    /// Image inputs that are an earlier frame of a camera: `(input, camera, delay_ms)`; the
    /// client sends them under the input's name.
    pub delayed_views: Vec<(String, String, f64)>,
    /// openpi's `policy_metadata` `reset_pose` of the served config (a top-level key, as
    /// openpi's server sends it; openpi's ALOHA client resets the arms to it).
    pub reset_pose: Option<Vec<f64>>,
}

impl ChunkrtMetadata {
    /// Packs the whole metadata map: `{"chunkrt": {...}}` plus `extra` entries written by the
    /// caller (none: pass 0 and a no-op).
    pub fn write(&self, w: &mut Writer) {
        w.map(1 + self.reset_pose.is_some() as usize);
        if let Some(pose) = &self.reset_pose {
            w.str("reset_pose").list(pose.len());
            for v in pose {
                w.f64(*v);
            }
        }
        w.str(keys::METADATA).map(9);
        w.str("version").str(&self.version);
        w.str("model").str(&self.model);
        w.str("action_horizon").uint(self.action_horizon as u64);
        w.str("action_dim").uint(self.action_dim as u64);
        w.str("image_inputs").list(self.image_inputs.len());
        for n in &self.image_inputs {
            w.str(n);
        }
        w.str("conditioning").list(self.conditioning.len());
        for n in &self.conditioning {
            w.str(n);
        }
        w.str("rtc_prefix_max").uint(self.rtc_prefix_max as u64);
        w.str("layout").str(&self.layout);
        w.str("delayed_views").list(self.delayed_views.len());
        for (name, camera, ms) in &self.delayed_views {
            w.list(3).str(name).str(camera).f64(*ms);
        }
    }

    /// The chunkrt map of a server's metadata; `None` for a server that is not chunkrt (openpi's,
    /// SGLang's, vLLM-Omni's).
    pub fn parse(meta: &Value<'_>) -> Option<ChunkrtMetadata> {
        let m = meta.get(keys::METADATA)?;
        let s = |k: &str| m.get(k).and_then(Value::key_str).unwrap_or("").to_string();
        let u = |k: &str| m.get(k).and_then(Value::as_u64).unwrap_or(0) as usize;
        let list = |k: &str| match m.get(k) {
            Some(Value::Array(xs)) => xs
                .iter()
                .filter_map(|x| x.key_str().map(str::to_string))
                .collect(),
            _ => Vec::new(),
        };
        Some(ChunkrtMetadata {
            version: s("version"),
            model: s("model"),
            action_horizon: u("action_horizon"),
            action_dim: u("action_dim"),
            image_inputs: list("image_inputs"),
            conditioning: list("conditioning"),
            rtc_prefix_max: u("rtc_prefix_max"),
            layout: s("layout"),
            delayed_views: match m.get("delayed_views") {
                Some(Value::Array(xs)) => xs
                    .iter()
                    .filter_map(|x| match x {
                        Value::Array(t) if t.len() == 3 => Some((
                            t[0].key_str()?.to_string(),
                            t[1].key_str()?.to_string(),
                            t[2].as_f64().filter(|d| d.is_finite() && *d >= 0.0)?,
                        )),
                        _ => None,
                    })
                    .collect(),
                _ => Vec::new(),
            },
            reset_pose: match meta.get("reset_pose") {
                Some(Value::Array(xs)) => xs.iter().map(Value::as_f64).collect(),
                _ => None,
            },
        })
    }

    /// Whether the server serves this conditioning.
    pub fn serves(&self, conditioning: &str) -> bool {
        self.conditioning.iter().any(|c| c == conditioning)
    }
}

#[cfg(test)]
mod tests;
