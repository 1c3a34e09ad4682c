//! π0 / π0.5 policies in candle: the model (exact to openpi), the prefix KV cache, checkpoints,
//! pre/post-processing and the runtime API for the controller (the inference benchmark is the
//! `chunkrt-bench` crate's).
//!
//! One file per part: [`config`] (dimensions, presets), [`siglip`] (vision tower + projector),
//! [`gemma`] (the dual-expert transformer), [`model`] (embeddings, masks, cache, sampler, loss),
//! [`checkpoint`] (safetensors loading and checks), [`preprocess`] (images, normalisation,
//! prompts, tokenizer), [`runtime`] (`Policy::load` / `Policy::infer`).
//!
//! Owns: the model, its sampler (written once, [`model::euler`]) and RTC guidance ([`rtc`]), the
//! CPU kernels ([`packed`], [`amx`], [`fastops`]) and the CUDA ones ([`kernels`], [`graph`]).
//! The layers reach the kernels through one seam, [`ops`]: a function per op kind that picks
//! the kernel for the tensors' device and falls back to candle's composition in one place.
//! Must not depend on: the controller, `chunkrt-ipc`, iceoryx2 (`cargo tree -p chunkrt-policy`
//! shows neither); thread pools are the caller's (`runtime::LoadOptions`).

pub mod amx;
pub mod checkpoint;
pub mod config;
pub mod device;
pub mod error;
pub mod fastops;
pub mod files;
pub mod gemma;
pub mod gpu;
pub mod graph;
pub mod kernels;
pub mod layout;
pub mod model;
pub mod openpi_config;
pub mod ops;
pub mod packed;
pub mod preprocess;
pub mod rtc;
pub mod runtime;
pub mod sentencepiece;
pub mod siglip;

pub use config::{ConfigOverrides, DelayedView, ModelConfig, ModelKind};
pub use device::{model_dtype, DeviceSpec, Precision};
pub use error::PolicyError;
pub use model::{ModelInputs, PiModel, PrefixCache, SampleOutput};
pub use preprocess::Encoding;
pub use rtc::{Guidance, Jacobian};
pub use runtime::{Conditioning, LoadOptions, Policy, RawFrame, RawObservation};

/// Turns chunkrt's CPU kernels (the packed matrix products, [`packed`], and the fused ops,
/// [`fastops`]) off or back on for the whole process. Off, a CPU model runs the same candle
/// compositions a GPU model runs: the tests use it to hold that device-generic path to openpi's
/// fixtures on machines without a GPU, the benches to measure candle as an in-run baseline.
pub fn set_cpu_fast_paths(on: bool) {
    packed::set_enabled(on);
    fastops::set_enabled(on);
}

/// Tells the C allocator (glibc) to keep freed memory for reuse instead of handing it back to
/// the kernel, for the process's whole life. Every CPU inference op allocates its output (candle
/// tensors), up to megabytes each; by default glibc serves the largest from fresh `mmap`s and
/// trims the heap's freed top, so the next call faults the same pages in again and the kernel
/// zeroes them: 7 % of a profiled pi0_bench run on 2 threads was `clear_page`. With the mmap
/// threshold at its maximum (32 MiB) and the heap trimmed only above 1 GiB of free top, those
/// pages stay mapped and are reused. The process keeps its peak heap. Call it once, early, from
/// a binary (the control tick allocates nothing, so it is not affected); no effect where
/// `MALLOC_MMAP_THRESHOLD_` or `MALLOC_TRIM_THRESHOLD_` is set (the user's choice stands) or
/// where the C library is not glibc.
pub fn keep_freed_memory() {
    #[cfg(all(target_os = "linux", target_env = "gnu"))]
    {
        let set = |var| std::env::var_os(var).is_some();
        if set("MALLOC_MMAP_THRESHOLD_") || set("MALLOC_TRIM_THRESHOLD_") {
            return;
        }
        // SAFETY: mallopt only changes the allocator's tunables; both values are in range (the
        // mmap threshold's maximum is 32 MiB on 64-bit glibc).
        unsafe {
            libc::mallopt(libc::M_MMAP_THRESHOLD, 32 << 20);
            libc::mallopt(libc::M_TRIM_THRESHOLD, 1 << 30);
        }
    }
}
