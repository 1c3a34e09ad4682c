//! What the policy needs from the GPU beyond candle's tensor ops: timing with CUDA events on
//! candle's stream, and the device's memory in use. Compiled to no-ops without the `cuda`
//! feature and on CPU devices, so callers need no `cfg`.

use candle_core::Device;

/// Times a span of device work with two CUDA events on the device's stream (`None` on the CPU).
pub struct EventTimer {
    #[cfg(feature = "cuda")]
    inner: Option<(
        std::sync::Arc<candle_core::cuda_backend::cudarc::driver::CudaStream>,
        candle_core::cuda_backend::cudarc::driver::CudaEvent,
    )>,
}

impl EventTimer {
    /// Records the start event on `device`'s stream (nothing on the CPU).
    pub fn start(device: &Device) -> Self {
        #[cfg(feature = "cuda")]
        {
            use candle_core::cuda_backend::cudarc::driver::sys::CUevent_flags;
            let inner = device.as_cuda_device().ok().and_then(|d| {
                let stream = d.cuda_stream();
                let ev = stream
                    .record_event(Some(CUevent_flags::CU_EVENT_DEFAULT))
                    .ok()?;
                Some((stream, ev))
            });
            Self { inner }
        }
        #[cfg(not(feature = "cuda"))]
        {
            let _ = device;
            Self {}
        }
    }

    /// Records the end event and returns the device time between the two in ms (waits for the
    /// end event); `None` on the CPU or when the driver refused an event.
    pub fn stop_ms(self) -> Option<f64> {
        #[cfg(feature = "cuda")]
        {
            use candle_core::cuda_backend::cudarc::driver::sys::CUevent_flags;
            let (stream, start) = self.inner?;
            let end = stream
                .record_event(Some(CUevent_flags::CU_EVENT_DEFAULT))
                .ok()?;
            start.elapsed_ms(&end).ok().map(|ms| ms as f64)
        }
        #[cfg(not(feature = "cuda"))]
        {
            None
        }
    }
}

/// Device memory in use and in total (bytes) on a GPU, as the driver reports it (the whole
/// device: this process's context, candle's pool and anything else running); `None` on the CPU.
pub fn memory(device: &Device) -> Option<(u64, u64)> {
    #[cfg(feature = "cuda")]
    {
        let d = device.as_cuda_device().ok()?;
        let (free, total) = d.cuda_stream().context().mem_get_info().ok()?;
        Some(((total - free) as u64, total as u64))
    }
    #[cfg(not(feature = "cuda"))]
    {
        let _ = device;
        None
    }
}

/// The GPU's name (e.g. "NVIDIA H100 80GB HBM3"); `None` on the CPU.
pub fn name(device: &Device) -> Option<String> {
    #[cfg(feature = "cuda")]
    {
        let d = device.as_cuda_device().ok()?;
        d.cuda_stream().context().name().ok()
    }
    #[cfg(not(feature = "cuda"))]
    {
        let _ = device;
        None
    }
}

/// Starts (`true`) or stops the CUDA profilers' collection (`ncu --profile-from-start off`
/// profiles only what runs in between). No-op without the `cuda` feature.
pub fn profiler(on: bool) {
    #[cfg(feature = "cuda")]
    {
        use candle_core::cuda_backend::cudarc::driver::sys;
        // SAFETY: plain driver calls without arguments; an error (no profiler attached) is
        // harmless and ignored.
        unsafe {
            if on {
                sys::cuProfilerStart();
            } else {
                sys::cuProfilerStop();
            }
        }
    }
    #[cfg(not(feature = "cuda"))]
    let _ = on;
}
