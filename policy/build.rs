//! With the `cuda` feature: compiles the policy's fused CUDA kernels (kernels/ops.cu) to PTX
//! with nvcc, for `src/kernels.rs` to embed and load at run time (no nvcc needed there). The
//! virtual architecture is `compute_$CUDA_COMPUTE_CAP` (default 80: the driver JIT-compiles the
//! PTX for the GPU at hand, Ampere and newer).

use std::path::PathBuf;
use std::process::Command;

fn main() {
    println!("cargo:rerun-if-changed=kernels/ops.cu");
    println!("cargo:rerun-if-env-changed=CUDA_COMPUTE_CAP");
    println!("cargo:rerun-if-env-changed=NVCC");
    if std::env::var_os("CARGO_FEATURE_CUDA").is_none() {
        return;
    }
    let out = PathBuf::from(std::env::var("OUT_DIR").expect("cargo sets OUT_DIR")).join("ops.ptx");
    let cap = std::env::var("CUDA_COMPUTE_CAP").unwrap_or_else(|_| "80".into());
    let nvcc = std::env::var("NVCC").unwrap_or_else(|_| "nvcc".into());
    let status = Command::new(&nvcc)
        .args(["--ptx", "-O3", "-std=c++17"])
        .arg(format!("-arch=compute_{cap}"))
        .arg("kernels/ops.cu")
        .arg("-o")
        .arg(&out)
        .status();
    match status {
        Ok(s) if s.success() => {}
        Ok(s) => panic!("{nvcc} failed on kernels/ops.cu ({s})"),
        Err(e) => panic!(
            "the `cuda` feature needs nvcc ({nvcc}: {e}); scripts/cuda-toolkit.sh installs one \
             and prints the environment to export"
        ),
    }
}
