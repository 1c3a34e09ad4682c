//! Matrix products through cuBLASLt with the algorithm picked per shape by timing (a switch of
//! [`super::CudaPaths`]: `lt`).
//!
//! candle runs every product through `cublasGemmStridedBatchedEx` with cuBLAS's default choice.
//! At batch 1 the action expert's products are skinny (M = 50 rows against 1024–8192 columns):
//! they read the weights once and are bound by memory bandwidth, where a split-K algorithm or
//! another tile shape can matter more than the default gives. So on the first product of each
//! shape (m, n, k, layout, dtype) this asks cuBLASLt for up to [`CANDIDATES`] algorithms that fit
//! a 32 MiB workspace, times each on the real operands with CUDA events (after warm-ups), and
//! keeps the fastest with its descriptors; every later product of that shape launches it
//! directly. The tuning synchronises the stream, so it only runs outside a CUDA-graph capture:
//! the eager run that precedes every capture ([`crate::graph`]) meets every shape first, and a
//! shape first seen inside a capture falls back to candle's product.
//!
//! The same numbers as candle's product up to the order of the f32 accumulation (each algorithm
//! computes the exact product of the bf16 operands in f32); the bench compares the actions.

use std::collections::HashMap;
use std::ffi::c_void;
use std::sync::{Mutex, OnceLock};

use candle_core::cuda_backend::cudarc::cublaslt::{result, sys};
use candle_core::cuda_backend::cudarc::driver::sys::{CUevent_flags, CUstreamCaptureStatus};
use candle_core::cuda_backend::cudarc::driver::CudaSlice;
use candle_core::cuda_backend::{CudaDevice, DeviceId};
use candle_core::{DType, Result};

/// Algorithms asked of cuBLASLt's heuristic per shape.
pub const CANDIDATES: usize = 16;
/// Timed launches per candidate (after two warm-ups).
const REPS: usize = 8;
/// The workspace every algorithm may use (NVIDIA's recommendation for Hopper).
const WORKSPACE: usize = 32 << 20;

fn err(what: &str, e: impl std::fmt::Debug) -> candle_core::Error {
    candle_core::Error::Msg(format!("cuBLASLt {what}: {e:?}"))
}

/// A product's shape in cuBLAS's column-major terms: D [m, n] = op(A) [m, k] · B [k, n].
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub struct Shape {
    pub m: u64,
    pub n: u64,
    pub k: u64,
    /// A transposed (a row-major `[N, K]` weight seen through `.t()`).
    pub transa: bool,
    pub lda: i64,
    pub bf16: bool,
}

/// One shape's descriptors and chosen algorithm (created once, reused by every launch).
struct Plan {
    desc: sys::cublasLtMatmulDesc_t,
    a: sys::cublasLtMatrixLayout_t,
    b: sys::cublasLtMatrixLayout_t,
    d: sys::cublasLtMatrixLayout_t,
    algo: sys::cublasLtMatmulAlgo_t,
    workspace: usize,
}

/// A device's handle, workspace and plans.
struct Lt {
    handle: sys::cublasLtHandle_t,
    workspace: CudaSlice<u8>,
    plans: HashMap<Shape, Option<Plan>>,
}

// SAFETY: the raw handles are only used under the global mutex below, one call at a time, on the
// device's one stream.
unsafe impl Send for Lt {}

fn registry() -> &'static Mutex<HashMap<DeviceId, Lt>> {
    static R: OnceLock<Mutex<HashMap<DeviceId, Lt>>> = OnceLock::new();
    R.get_or_init(|| Mutex::new(HashMap::new()))
}

/// What the tuning found, one line per shape (the bench prints it).
fn report() -> &'static Mutex<Vec<String>> {
    static R: OnceLock<Mutex<Vec<String>>> = OnceLock::new();
    R.get_or_init(|| Mutex::new(Vec::new()))
}

/// The tuning lines so far (shape, candidates, cuBLASLt's first choice against the fastest).
pub fn tuning_report() -> Vec<String> {
    report().lock().map(|r| r.clone()).unwrap_or_default()
}

fn data_type(bf16: bool) -> sys::cudaDataType {
    if bf16 {
        sys::cudaDataType_t::CUDA_R_16BF
    } else {
        sys::cudaDataType_t::CUDA_R_32F
    }
}

unsafe fn set_desc(desc: sys::cublasLtMatmulDesc_t, attr: sys::cublasLtMatmulDescAttributes_t, v: i32) -> Result<()> {
    result::set_matmul_desc_attribute(desc, attr, (&v) as *const i32 as *const c_void, 4)
        .map_err(|e| err("descriptor", e))
}

impl Plan {
    /// The descriptors of `s` (no algorithm yet).
    fn descriptors(s: &Shape) -> Result<(sys::cublasLtMatmulDesc_t, [sys::cublasLtMatrixLayout_t; 3])> {
        let dt = data_type(s.bf16);
        let desc = result::create_matmul_desc(
            sys::cublasComputeType_t::CUBLAS_COMPUTE_32F,
            sys::cudaDataType_t::CUDA_R_32F,
        )
        .map_err(|e| err("descriptor", e))?;
        // SAFETY: a descriptor just created
        unsafe {
            set_desc(desc, sys::cublasLtMatmulDescAttributes_t::CUBLASLT_MATMUL_DESC_TRANSA, s.transa as i32)?;
            set_desc(desc, sys::cublasLtMatmulDescAttributes_t::CUBLASLT_MATMUL_DESC_TRANSB, 0)?;
        }
        let (ar, ac) = if s.transa { (s.k, s.m) } else { (s.m, s.k) };
        let a = result::create_matrix_layout(dt, ar, ac, s.lda).map_err(|e| err("layout", e))?;
        let b = result::create_matrix_layout(dt, s.k, s.n, s.k as i64).map_err(|e| err("layout", e))?;
        let d = result::create_matrix_layout(dt, s.m, s.n, s.m as i64).map_err(|e| err("layout", e))?;
        Ok((desc, [a, b, d]))
    }
}

/// Launches `plan` on `stream`: D = A · B (alpha 1, beta 0, D also as C).
unsafe fn launch(
    lt: &Lt,
    plan: &Plan,
    algo: &sys::cublasLtMatmulAlgo_t,
    ptrs: (u64, u64, u64),
    dev: &CudaDevice,
) -> Result<()> {
    let (one, zero) = (1f32, 0f32);
    let stream = dev.cuda_stream();
    let (ws, _guard) =
        candle_core::cuda_backend::cudarc::driver::DevicePtr::device_ptr(&lt.workspace, &stream);
    result::matmul(
        lt.handle,
        plan.desc,
        (&one) as *const f32 as *const c_void,
        (&zero) as *const f32 as *const c_void,
        ptrs.0 as *const c_void,
        plan.a,
        ptrs.1 as *const c_void,
        plan.b,
        ptrs.2 as *const c_void,
        plan.d,
        ptrs.2 as *mut c_void,
        plan.d,
        algo as *const _,
        ws as *mut c_void,
        plan.workspace.max(1),
        stream.cu_stream() as *mut _,
    )
    .map_err(|e| err("matmul", e))
}

/// Times the candidates of `s` on the real operands and keeps the fastest (`None`: cuBLASLt has
/// no algorithm for it).
fn tune(lt: &Lt, s: &Shape, ptrs: (u64, u64, u64), dev: &CudaDevice) -> Result<Option<Plan>> {
    let (desc, [a, b, d]) = Plan::descriptors(s)?;
    let pref = result::create_matmul_pref().map_err(|e| err("preference", e))?;
    let ws = WORKSPACE;
    // SAFETY: live descriptors; the results array holds CANDIDATES entries
    let mut found = unsafe {
        result::set_matmul_pref_attribute(
            pref,
            sys::cublasLtMatmulPreferenceAttributes_t::CUBLASLT_MATMUL_PREF_MAX_WORKSPACE_BYTES,
            (&ws) as *const usize as *const c_void,
            std::mem::size_of::<usize>(),
        )
        .map_err(|e| err("preference", e))?;
        let mut out: Vec<sys::cublasLtMatmulHeuristicResult_t> = Vec::with_capacity(CANDIDATES);
        let mut n = 0i32;
        let st = sys::cublasLtMatmulAlgoGetHeuristic(
            lt.handle,
            desc,
            a,
            b,
            d,
            d,
            pref,
            CANDIDATES as i32,
            out.as_mut_ptr(),
            &mut n,
        );
        let _ = result::destroy_matmul_pref(pref);
        if st != sys::cublasStatus_t::CUBLAS_STATUS_SUCCESS || n <= 0 {
            Vec::new()
        } else {
            out.set_len(n as usize);
            out
        }
    };
    found.retain(|h| h.state == sys::cublasStatus_t::CUBLAS_STATUS_SUCCESS && h.workspaceSize <= ws);
    if found.is_empty() {
        return Ok(None);
    }
    let stream = dev.cuda_stream();
    let mut plan = Plan { desc, a, b, d, algo: found[0].algo, workspace: ws };
    let mut times = Vec::with_capacity(found.len());
    for h in &found {
        let run = || -> Result<f32> {
            for _ in 0..2 {
                // SAFETY: the caller checked the operands against the shape
                unsafe { launch(lt, &plan, &h.algo, ptrs, dev)? };
            }
            let t0 = stream
                .record_event(Some(CUevent_flags::CU_EVENT_DEFAULT))
                .map_err(|e| err("event", e))?;
            for _ in 0..REPS {
                unsafe { launch(lt, &plan, &h.algo, ptrs, dev)? };
            }
            let t1 = stream
                .record_event(Some(CUevent_flags::CU_EVENT_DEFAULT))
                .map_err(|e| err("event", e))?;
            t0.elapsed_ms(&t1).map_err(|e| err("event", e))
        };
        // a candidate that fails to launch is skipped
        times.push(run().map(|ms| ms / REPS as f32).unwrap_or(f32::INFINITY));
    }
    let best = (0..times.len())
        .min_by(|&i, &j| times[i].total_cmp(&times[j]))
        .unwrap_or(0);
    if !times[best].is_finite() {
        return Ok(None);
    }
    plan.algo = found[best].algo;
    let line = format!(
        "m {} n {} k {} {}{}: {} candidates, cuBLASLt's first {:.1} us, fastest (#{best}) {:.1} us",
        s.m,
        s.n,
        s.k,
        if s.bf16 { "bf16" } else { "f32" },
        if s.transa { " A^T" } else { "" },
        found.len(),
        times[0] * 1e3,
        times[best] * 1e3
    );
    tracing::debug!("{line}");
    if let Ok(mut r) = report().lock() {
        r.push(line);
    }
    Ok(Some(plan))
}

/// D = op(A) · B on `dev`'s stream with the shape's tuned algorithm; `ptrs` = (A, B, D) device
/// addresses of live allocations of the sizes `s` implies. Returns false where no algorithm
/// applies (a shape first seen inside a graph capture, or none that cuBLASLt offers): the caller
/// then runs candle's product.
pub fn matmul(dev: &CudaDevice, s: Shape, dt: DType, ptrs: (u64, u64, u64)) -> Result<bool> {
    debug_assert_eq!(dt == DType::BF16, s.bf16);
    let mut reg = registry().lock().map_err(|_| err("registry", "poisoned"))?;
    let lt = match reg.entry(dev.id()) {
        std::collections::hash_map::Entry::Occupied(e) => e.into_mut(),
        std::collections::hash_map::Entry::Vacant(e) => {
            let handle = result::create_handle().map_err(|e| err("handle", e))?;
            // SAFETY: written by the algorithms that use it before they read it
            let workspace = unsafe { dev.cuda_stream().alloc::<u8>(WORKSPACE) }
                .map_err(|e| err("workspace", e))?;
            e.insert(Lt {
                handle,
                workspace,
                plans: HashMap::new(),
            })
        }
    };
    if !lt.plans.contains_key(&s) {
        let capturing = dev
            .cuda_stream()
            .capture_status()
            .map_err(|e| err("capture status", e))?
            != CUstreamCaptureStatus::CU_STREAM_CAPTURE_STATUS_NONE;
        if capturing {
            return Ok(false);
        }
        let plan = tune(lt, &s, ptrs, dev)?;
        lt.plans.insert(s, plan);
    }
    let lt = &*lt;
    match lt.plans.get(&s).and_then(|p| p.as_ref()) {
        Some(plan) => {
            // SAFETY: as for `tune`
            unsafe { launch(lt, plan, &plan.algo, ptrs, dev)? };
            Ok(true)
        }
        None => Ok(false),
    }
}
