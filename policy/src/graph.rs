//! The whole sample — prefix pass and denoising loop — replayed as one captured CUDA graph.
//!
//! Candle launches one kernel per op, and on a GPU at batch 1 the host's launches, not the
//! arithmetic, set the pace. In the fixed layout ([`PiModel::set_fixed_step_shapes`]) every
//! shape, offset and buffer of a sample is the same for every observation:
//! [`PiModel::prepare_prefix`] does the host work (checks, masks, RoPE tables) and copies the
//! observation into the prefix cache's buffers, [`PiModel::run_prefix`] and
//! [`PiModel::denoise`] then read nothing but those buffers and the weights, and nothing back
//! to the host. So that device half is captured once on candle's stream and replayed with one
//! launch per observation: the vision tower, the VLM prefix pass filling the KV cache, and every
//! denoising step.
//!
//! RTC's guided loop with the identity Jacobian (`rtc_jacobian = "identity"`, the default) is
//! captured the same way ([`SampleGraph::capture_guided`]): its target Y and weights W are two
//! more buffers the graph reads, written before each replay; β and the steps are part of the
//! graph (another β captures again).
//!
//! Self-checking: the first replay is compared with the eager run on the same inputs (the same
//! kernels in the same order, so they must agree to rounding); on any capture error or mismatch
//! the graph is dropped and the runtime stays eager, with a warning. Without the `cuda` feature
//! (or on a CPU device) [`SampleGraph::capture`] reports that no graph applies.

use candle_core::{DType, Tensor, TensorId};

use crate::error::PolicyError;
use crate::model::{PiModel, PrefixCache, SampleOutput};
use crate::rtc::{GuidanceTarget, Jacobian};

/// What the captures and replays share.
#[cfg(feature = "cuda")]
mod cuda {
    use candle_core::cuda_backend::cudarc::driver::{sys, CudaGraph};
    use candle_core::cuda_backend::CudaDevice;

    use crate::error::PolicyError;
    use crate::model::{PiModel, PrefixCache};

    fn err(what: &str, e: &dyn std::fmt::Display) -> PolicyError {
        PolicyError::Candle(candle_core::Error::Msg(format!("{what}: {e}")))
    }

    /// The model's CUDA device where a graph applies: a GPU model in the fixed layout, a cache
    /// without compaction.
    pub fn device<'m>(model: &'m PiModel, cache: &PrefixCache) -> Option<&'m CudaDevice> {
        match model.device().as_cuda_device() {
            Ok(dev) if model.fixed_step_shapes() && cache.rows.is_empty() => Some(dev),
            _ => None,
        }
    }

    /// Captures what `f` launches on candle's stream. The caller has run `f` eagerly under
    /// `enable_cuda_graph_htod_cache` (the small per-op uploads are then cached by content).
    /// The capture always ends, whatever happened inside, so the stream stays usable.
    pub fn capture<T>(
        dev: &CudaDevice,
        f: impl FnOnce() -> Result<T, PolicyError>,
    ) -> Result<(T, CudaGraph), PolicyError> {
        let stream = dev.cuda_stream();
        stream
            .begin_capture(sys::CUstreamCaptureMode::CU_STREAM_CAPTURE_MODE_THREAD_LOCAL)
            .map_err(|e| err("begin capture", &e))?;
        let captured = f();
        let graph = stream.end_capture(
            sys::CUgraphInstantiate_flags::CUDA_GRAPH_INSTANTIATE_FLAG_AUTO_FREE_ON_LAUNCH,
        );
        let captured = captured?;
        let graph = graph
            .map_err(|e| err("end capture", &e))?
            .ok_or_else(|| err("end capture", &"the driver returned no graph"))?;
        Ok((captured, graph))
    }

    /// One replay.
    pub fn launch(graph: &CudaGraph) -> Result<(), PolicyError> {
        graph.launch().map_err(|e| err("graph launch", &e))
    }

    /// A graph check failure.
    pub fn mismatch(d: f32, rms: f32) -> PolicyError {
        err(
            "graph check",
            &format!("replay differs from the eager run by {d} (RMS {rms})"),
        )
    }
}

#[cfg(not(feature = "cuda"))]
fn no_cuda() -> PolicyError {
    PolicyError::Config("CUDA graphs need a build with --features cuda".into())
}

/// A captured sample (prefix pass + denoising loop), its noise input and outputs, and the
/// buffers it was captured against.
pub struct SampleGraph {
    #[cfg(feature = "cuda")]
    graph: candle_core::cuda_backend::cudarc::driver::CudaGraph,
    /// The noise buffer [B, H, A] f32 the graph reads.
    noise: Tensor,
    /// x_0 [B, H, A] f32 as the graph writes it.
    out: Tensor,
    /// The first velocity, as the graph writes it.
    v0: Tensor,
    times: Vec<f32>,
    steps: usize,
    /// Identity of every buffer the graph reads (KV cache, the observation's buffers).
    buffers: Vec<TensorId>,
    /// The guidance target's buffers (a guided loop), `None` for the plain sampler.
    guide: Option<GuidanceTarget>,
}

// SAFETY: cudarc's CudaGraph holds raw driver handles and is not Sync; the driver requires that
// calls on one graph are serialised. A SampleGraph is owned by one `Policy`, which is used by one
// thread at a time (`&mut self` on every call); moving it to the inference thread is a move, not
// shared access.
unsafe impl Send for SampleGraph {}

/// The prefix pass alone as a captured graph (a diagnostic: the bench splits a captured
/// sample's time into prefix pass and denoising loop with it).
pub struct PrefixGraph {
    #[cfg(feature = "cuda")]
    graph: candle_core::cuda_backend::cudarc::driver::CudaGraph,
}

// SAFETY: as for SampleGraph: one owner, calls serialised.
unsafe impl Send for PrefixGraph {}

impl PrefixGraph {
    /// Captures [`PiModel::run_prefix`] against `cache` (prepared); `None` where graphs do not
    /// apply.
    #[allow(unused_variables)]
    pub fn capture(model: &PiModel, cache: &PrefixCache) -> Result<Option<Self>, PolicyError> {
        #[cfg(feature = "cuda")]
        {
            let Some(dev) = cuda::device(model, cache) else {
                return Ok(None);
            };
            let _cache_uploads = dev.enable_cuda_graph_htod_cache();
            model.run_prefix(cache, None, false)?;
            model.device().synchronize()?;
            let (_, graph) = cuda::capture(dev, || model.run_prefix(cache, None, false))?;
            Ok(Some(PrefixGraph { graph }))
        }
        #[cfg(not(feature = "cuda"))]
        Ok(None)
    }

    /// Replays the prefix pass.
    pub fn run(&self) -> Result<(), PolicyError> {
        #[cfg(feature = "cuda")]
        return cuda::launch(&self.graph);
        #[cfg(not(feature = "cuda"))]
        Err(no_cuda())
    }
}

/// The buffers a sample reads besides the weights.
fn buffer_ids(cache: &PrefixCache) -> Vec<TensorId> {
    let mut v: Vec<TensorId> = cache.k.iter().chain(&cache.v).map(|t| t.id()).collect();
    v.extend(cache.statics.ids());
    v
}

impl SampleGraph {
    /// Whether `self` was captured against `cache`'s buffers for `steps` steps (plain sampler).
    pub fn fits(&self, cache: &PrefixCache, steps: usize) -> bool {
        self.guide.is_none() && self.fits_cache(cache, steps)
    }

    /// [`Self::fits`] for a guided loop towards targets shaped as `target`, with its β.
    pub fn fits_guided(&self, cache: &PrefixCache, steps: usize, target: &GuidanceTarget) -> bool {
        let same = |g: &GuidanceTarget| {
            g.beta == target.beta
                && g.jacobian == target.jacobian
                && g.y.dims() == target.y.dims()
                && g.w.dims() == target.w.dims()
        };
        self.guide.as_ref().is_some_and(same) && self.fits_cache(cache, steps)
    }

    fn fits_cache(&self, cache: &PrefixCache, steps: usize) -> bool {
        self.steps == steps && cache.rows.is_empty() && self.buffers == buffer_ids(cache)
    }

    /// Replays prefix pass and loop for the observation [`PiModel::prepare_prefix`] copied
    /// into the cache the graph was captured with, from `noise` [B, H, A].
    pub fn run(&self, noise: &Tensor) -> Result<SampleOutput, PolicyError> {
        if self.guide.is_some() {
            return Err(PolicyError::Input(
                "a guided graph replays with its target (run_guided)".into(),
            ));
        }
        self.replay(noise)
    }

    /// [`Self::run`] for a guided graph, towards `target` (shaped as the captured one,
    /// [`Self::fits_guided`]): its Y and W are copied into the graph's buffers first.
    pub fn run_guided(
        &self,
        noise: &Tensor,
        target: &GuidanceTarget,
    ) -> Result<SampleOutput, PolicyError> {
        let Some(g) = &self.guide else {
            return Err(PolicyError::Input(
                "a plain graph has no guidance target".into(),
            ));
        };
        g.y.slice_set(&target.y.to_dtype(DType::F32)?.contiguous()?, 0, 0)?;
        g.w.slice_set(&target.w.to_dtype(DType::F32)?.contiguous()?, 0, 0)?;
        self.replay(noise)
    }

    fn replay(&self, noise: &Tensor) -> Result<SampleOutput, PolicyError> {
        self.noise
            .slice_set(&noise.to_dtype(DType::F32)?.contiguous()?, 0, 0)?;
        self.launch()?;
        Ok(SampleOutput {
            // copies: the next replay overwrites the graph's buffers
            actions: self.out.copy()?,
            v_t_step0: self.v0.copy()?,
            times: self.times.clone(),
        })
    }

    #[cfg(feature = "cuda")]
    fn launch(&self) -> Result<(), PolicyError> {
        cuda::launch(&self.graph)
    }

    #[cfg(not(feature = "cuda"))]
    fn launch(&self) -> Result<(), PolicyError> {
        Err(no_cuda())
    }

    /// Runs the device half of a sample eagerly against `cache` (prepared for the current
    /// observation), captures it, and checks the first replay against the eager result, which
    /// is returned with the graph. `Ok((eager, None))`: no graph applies here (CPU, no `cuda`
    /// feature, compact layout).
    pub fn capture(
        model: &PiModel,
        cache: &PrefixCache,
        noise: &Tensor,
        steps: usize,
    ) -> Result<(SampleOutput, Option<Self>), PolicyError> {
        Self::capture_with(model, cache, noise, steps, None)
    }

    /// [`Self::capture`] of RTC's guided loop towards `target` ([`crate::rtc::denoise_guided`];
    /// checked with `rtc::check_target`, identity Jacobian only: the VJP runs autograd's
    /// backward, which is not captured). Replays with [`Self::run_guided`].
    pub fn capture_guided(
        model: &PiModel,
        cache: &PrefixCache,
        noise: &Tensor,
        steps: usize,
        target: &GuidanceTarget,
    ) -> Result<(SampleOutput, Option<Self>), PolicyError> {
        if target.jacobian != Jacobian::Identity {
            return Err(PolicyError::Config(
                "only the identity Jacobian's guided loop is captured".into(),
            ));
        }
        // the graph's own copies of Y and W, rewritten before every replay
        let guide = GuidanceTarget {
            y: target.y.to_dtype(DType::F32)?.contiguous()?.copy()?,
            w: target.w.to_dtype(DType::F32)?.contiguous()?.copy()?,
            beta: target.beta,
            jacobian: target.jacobian,
        };
        Self::capture_with(model, cache, noise, steps, Some(guide))
    }

    #[allow(unused_variables)]
    fn capture_with(
        model: &PiModel,
        cache: &PrefixCache,
        noise: &Tensor,
        steps: usize,
        guide: Option<GuidanceTarget>,
    ) -> Result<(SampleOutput, Option<Self>), PolicyError> {
        let once = |x: &Tensor| -> Result<SampleOutput, PolicyError> {
            model.run_prefix(cache, None, false)?;
            match &guide {
                Some(g) => crate::rtc::denoise_guided(model, cache, x, steps, g),
                None => model.denoise(cache, x, steps),
            }
        };
        #[cfg(feature = "cuda")]
        {
            let Some(dev) = cuda::device(model, cache) else {
                return Ok((once(noise)?, None));
            };
            // small host uploads (kernel dims/strides) are cached by content from here on, and
            // one eager run with the graph's own buffers fills that cache
            let _cache_uploads = dev.enable_cuda_graph_htod_cache();
            let buf = noise.to_dtype(DType::F32)?.contiguous()?.copy()?;
            let eager = once(&buf)?;
            // the eager result must outlive the replays that overwrite nothing of it
            let eager = SampleOutput {
                actions: eager.actions.copy()?,
                v_t_step0: eager.v_t_step0.copy()?,
                times: eager.times,
            };
            model.device().synchronize()?;
            let (captured, graph) = cuda::capture(dev, || once(&buf))?;
            let g = SampleGraph {
                graph,
                noise: buf,
                out: captured.actions,
                v0: captured.v_t_step0,
                times: captured.times,
                steps,
                buffers: buffer_ids(cache),
                guide,
            };
            let replay = g.replay(noise)?;
            let d = (&replay.actions - &eager.actions)?
                .abs()?
                .max_all()?
                .to_scalar::<f32>()?;
            let rms = eager.actions.sqr()?.mean_all()?.to_scalar::<f32>()?.sqrt();
            // NaN fails too
            if d.is_nan() || d > 1e-3 * rms.max(1e-6) {
                return Err(cuda::mismatch(d, rms));
            }
            Ok((eager, Some(g)))
        }
        #[cfg(not(feature = "cuda"))]
        {
            Ok((once(noise)?, None))
        }
    }
}
