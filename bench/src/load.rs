//! Load generator standing in for inference: a thread pinned to one core doing candle f32
//! matmuls back to back until stopped.
//!
//! candle's CPU matmul parallelises over `RAYON_NUM_THREADS` (default: all cores). To keep the
//! load on its one core, the bench mains set `RAYON_NUM_THREADS=1` before any thread starts;
//! [`MatmulLoad::threads`] reports what candle will use so the output can say so.

use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
use std::sync::Arc;
use std::thread::JoinHandle;
use std::time::Instant;

use candle_core::{Device, Tensor};

use super::BenchError;

/// A running matmul load.
#[derive(Debug)]
pub struct MatmulLoad {
    stop: Arc<AtomicBool>,
    matmuls: Arc<AtomicU64>,
    handle: Option<JoinHandle<Result<(), String>>>,
    started: Instant,
    size: usize,
}

/// What the load did.
#[derive(Debug, Clone, Copy)]
pub struct LoadStats {
    /// Matmuls completed.
    pub matmuls: u64,
    /// Achieved GFLOP/s.
    pub gflops: f64,
}

impl MatmulLoad {
    /// Threads candle's matmul will use (1 keeps the load on its pinned core).
    pub fn threads() -> usize {
        candle_core::utils::get_num_threads()
    }

    /// Starts `size`×`size` f32 matmuls in a thread pinned to `core` (if given).
    pub fn start(core: Option<usize>, size: usize) -> Result<Self, BenchError> {
        let stop = Arc::new(AtomicBool::new(false));
        let matmuls = Arc::new(AtomicU64::new(0));
        let (s, m) = (stop.clone(), matmuls.clone());
        let handle = std::thread::Builder::new()
            .name("chunkrt-load".into())
            .spawn(move || -> Result<(), String> {
                if let Some(c) = core {
                    let _ = chunkrt_controller::rt::pin_current_thread(c);
                }
                let dev = Device::Cpu;
                let a = Tensor::randn(0f32, 1.0, (size, size), &dev).map_err(|e| e.to_string())?;
                let b = Tensor::randn(0f32, 1.0, (size, size), &dev).map_err(|e| e.to_string())?;
                while !s.load(Ordering::Relaxed) {
                    let c = a.matmul(&b).map_err(|e| e.to_string())?;
                    std::hint::black_box(c);
                    m.fetch_add(1, Ordering::Relaxed);
                }
                Ok(())
            })
            .map_err(|e| BenchError::Thread(e.to_string()))?;
        Ok(Self {
            stop,
            matmuls,
            handle: Some(handle),
            started: Instant::now(),
            size,
        })
    }

    /// Stops the load and reports what it did.
    pub fn stop(mut self) -> Result<LoadStats, BenchError> {
        self.stop.store(true, Ordering::Relaxed);
        let secs = self.started.elapsed().as_secs_f64();
        if let Some(h) = self.handle.take() {
            h.join()
                .map_err(|_| BenchError::Thread("load thread panicked".into()))?
                .map_err(BenchError::Candle)?;
        }
        let n = self.matmuls.load(Ordering::Relaxed);
        let flops = 2.0 * (self.size as f64).powi(3) * n as f64;
        Ok(LoadStats {
            matmuls: n,
            gflops: flops / secs.max(1e-9) / 1e9,
        })
    }
}

impl Drop for MatmulLoad {
    fn drop(&mut self) {
        self.stop.store(true, Ordering::Relaxed);
        if let Some(h) = self.handle.take() {
            let _ = h.join();
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn load_runs_and_stops() {
        let load = MatmulLoad::start(None, 64).expect("load starts");
        std::thread::sleep(std::time::Duration::from_millis(100));
        let st = load.stop().expect("load stops");
        assert!(st.matmuls > 10, "{st:?}");
        assert!(st.gflops > 0.1, "{st:?}");
    }
}
