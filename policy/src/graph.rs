//! The denoising loop replayed as a captured CUDA graph.
//!
//! Candle launches one kernel per op; a denoising step of a full-size action expert is hundreds
//! of them, which at batch 1 costs more than the arithmetic. The loop's shapes, offsets and
//! buffers are the same for every observation in the fixed step layout
//! ([`PiModel::set_fixed_step_shapes`]), the time features are made once per model
//! ([`PiModel::sample`] warms them up), and the loop reads nothing back to the host, so the whole
//! loop is captured once on candle's stream and replayed: a new observation refills the prefix
//! cache in place (eagerly), its noise is copied into the graph's input buffer, one launch runs
//! all steps.
//!
//! Self-checking: the first replay is compared with the eager loop on the same inputs (the same
//! kernels in the same order, so they must agree to rounding); on any capture error or mismatch
//! the graph is dropped and the runtime stays eager, with a warning. Without the `cuda` feature
//! (or on a CPU device) [`StepGraph::capture`] reports that no graph applies.

use candle_core::{DType, Tensor};

use crate::model::{PiModel, PrefixCache, SampleOutput};
use crate::PolicyError;

/// A captured denoising loop, its input (noise) and output (x_0) buffers, and what it was
/// captured against.
pub struct StepGraph {
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
    /// Identity of the cache buffers the graph reads (K/V of layer 0, the step mask).
    cache_ids: (candle_core::TensorId, candle_core::TensorId),
}

// SAFETY: cudarc's CudaGraph holds raw driver handles and is not Sync; the driver requires that
// calls on one graph are serialised. A StepGraph is owned by one `Policy`, which is used by one
// thread at a time (`&mut self` on every call); moving it to the inference thread is a move, not
// shared access.
unsafe impl Send for StepGraph {}

impl StepGraph {
    /// Whether `self` was captured against `cache` for `steps` steps.
    pub fn fits(&self, cache: &PrefixCache, steps: usize) -> bool {
        self.steps == steps
            && cache.k.first().map(|k| k.id()) == Some(self.cache_ids.0)
            && cache.step_bias.id() == self.cache_ids.1
    }

    /// Replays the loop for `noise` [B, H, A] against the cache the graph was captured with
    /// (refilled in place for the current observation).
    pub fn run(&self, noise: &Tensor) -> Result<SampleOutput, PolicyError> {
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
        self.graph
            .launch()
            .map_err(|e| PolicyError::Candle(candle_core::Error::Msg(format!("graph launch: {e}"))))
    }

    #[cfg(not(feature = "cuda"))]
    fn launch(&self) -> Result<(), PolicyError> {
        Err(PolicyError::Config(
            "CUDA graphs need a build with --features cuda".into(),
        ))
    }

    /// Captures the cached denoising loop of `model` against `cache` (filled for the current
    /// observation) and checks its first replay against `eager`, the eager loop's result for
    /// `noise`. `Ok(None)`: no graph applies here (CPU, no `cuda` feature, compact layout).
    #[allow(unused_variables)]
    pub fn capture(
        model: &PiModel,
        cache: &PrefixCache,
        noise: &Tensor,
        steps: usize,
        eager: &SampleOutput,
    ) -> Result<Option<Self>, PolicyError> {
        #[cfg(feature = "cuda")]
        {
            use candle_core::cuda_backend::cudarc::driver::sys;
            let Ok(dev) = model.device().as_cuda_device() else {
                return Ok(None);
            };
            if !model.fixed_step_shapes() {
                return Ok(None);
            }
            let err = |what: &str, e: &dyn std::fmt::Display| {
                PolicyError::Candle(candle_core::Error::Msg(format!("{what}: {e}")))
            };
            // small host uploads (kernel dims/strides) are cached by content from here on, and
            // one eager run with the graph's own buffers fills that cache
            let _cache_uploads = dev.enable_cuda_graph_htod_cache();
            let buf = noise.to_dtype(DType::F32)?.contiguous()?.copy()?;
            let loop_once = |x: &Tensor| model.denoise(cache, x, steps);
            loop_once(&buf)?;
            model.device().synchronize()?;
            let stream = dev.cuda_stream();
            stream
                .begin_capture(sys::CUstreamCaptureMode::CU_STREAM_CAPTURE_MODE_THREAD_LOCAL)
                .map_err(|e| err("begin capture", &e))?;
            let captured = loop_once(&buf);
            // always end the capture, whatever happened inside, so the stream is usable again
            let graph = stream.end_capture(
                sys::CUgraphInstantiate_flags::CUDA_GRAPH_INSTANTIATE_FLAG_AUTO_FREE_ON_LAUNCH,
            );
            let captured = captured?;
            let graph = graph
                .map_err(|e| err("end capture", &e))?
                .ok_or_else(|| err("end capture", &"the driver returned no graph"))?;
            let g = StepGraph {
                graph,
                noise: buf,
                out: captured.actions,
                v0: captured.v_t_step0,
                times: captured.times,
                steps,
                cache_ids: (
                    cache
                        .k
                        .first()
                        .map(|k| k.id())
                        .ok_or_else(|| err("capture", &"empty cache"))?,
                    cache.step_bias.id(),
                ),
            };
            let replay = g.run(noise)?;
            let d = (&replay.actions - &eager.actions)?
                .abs()?
                .max_all()?
                .to_scalar::<f32>()?;
            let rms = eager.actions.sqr()?.mean_all()?.to_scalar::<f32>()?.sqrt();
            if !(d <= 1e-3 * rms.max(1e-6)) {
                return Err(err(
                    "graph check",
                    &format!("replay differs from the eager loop by {d} (RMS {rms})"),
                ));
            }
            Ok(Some(g))
        }
        #[cfg(not(feature = "cuda"))]
        {
            Ok(None)
        }
    }
}
