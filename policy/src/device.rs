//! Where the policy runs and in which arithmetic: `device = "cpu" | "cuda" | "cuda:N"` and
//! `precision = "f32" | "bf16"`, turned into a candle [`Device`] and the model's [`DType`].
//!
//! - CPU: weights and activations stay f32; `bf16` runs the experts' and SigLIP's matrix
//!   products on the packed bf16 kernels (f32 accumulation) where the CPU has them.
//! - CUDA: the model's tensors are stored in the precision's dtype (bf16: half the memory and
//!   the tensor cores); what openpi keeps in f32 stays f32 (norm statistics, softmax, the time
//!   embedding and the adaRMS conditioning, the sampler state).

use std::fmt;
use std::str::FromStr;

use candle_core::{DType, Device};

use crate::error::PolicyError;
pub use crate::packed::Precision;

/// The device a policy runs on.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub enum DeviceSpec {
    /// The host CPU (candle's CPU backend and chunkrt's packed kernels).
    #[default]
    Cpu,
    /// NVIDIA GPU number N (candle's CUDA backend; needs the `cuda` feature).
    Cuda(usize),
}

impl DeviceSpec {
    /// Opens the device. Errors say what is missing: a binary built without the `cuda`
    /// feature, or no usable GPU (driver, ordinal).
    pub fn open(&self) -> Result<Device, PolicyError> {
        match *self {
            DeviceSpec::Cpu => Ok(Device::Cpu),
            DeviceSpec::Cuda(n) => {
                if !cfg!(feature = "cuda") {
                    return Err(PolicyError::Config(format!(
                        "device {self}: this binary was built without CUDA support; rebuild with \
                         `cargo build --release --features cuda` (docs/gpu.md)"
                    )));
                }
                #[cfg(feature = "cuda")]
                missing_cuda_libraries().map_err(|missing| {
                    PolicyError::Config(format!(
                        "device {self}: cannot load {missing}: install the NVIDIA driver (580 \
                         series, CUDA 13.0; it brings libcuda.so.1) and put the CUDA 13 \
                         libraries on the library path (a CUDA 13.0 toolkit, or the \
                         nvidia-*-cu13 wheels; docs/gpu.md)"
                    ))
                })?;
                let dev = Device::new_cuda(n).map_err(|e| {
                    // the driver's error on its first line (candle appends a backtrace)
                    let e = e.to_string();
                    let e = e.lines().next().unwrap_or("").trim_end_matches(':');
                    PolicyError::Config(format!(
                        "device {self}: no usable NVIDIA GPU ({e}); check the driver \
                         (nvidia-smi), libcuda.so.1 on the library path, and the GPU number"
                    ))
                })?;
                #[cfg(feature = "cuda")]
                if let Ok(c) = dev.as_cuda_device() {
                    // SAFETY: the policy runs every op on candle's one stream of this device
                    // (the inference thread's), so the per-access CUDA events that order tensor
                    // uses across streams order nothing here and only cost two driver calls per
                    // kernel; frees stay stream-ordered.
                    unsafe { c.disable_event_tracking() };
                }
                Ok(dev)
            }
        }
    }

    /// True for a GPU.
    pub fn is_cuda(&self) -> bool {
        matches!(self, DeviceSpec::Cuda(_))
    }

    /// The spec of an open device.
    pub fn of(device: &Device) -> Self {
        match device.location() {
            candle_core::DeviceLocation::Cuda { gpu_id } => DeviceSpec::Cuda(gpu_id),
            _ => DeviceSpec::Cpu,
        }
    }
}

impl fmt::Display for DeviceSpec {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self {
            DeviceSpec::Cpu => write!(f, "cpu"),
            DeviceSpec::Cuda(n) => write!(f, "cuda:{n}"),
        }
    }
}

impl FromStr for DeviceSpec {
    type Err = PolicyError;

    fn from_str(s: &str) -> Result<Self, Self::Err> {
        let bad = || {
            PolicyError::Config(format!(
                "device {s:?}: expected one of \"cpu\", \"cuda\", \"cuda:N\" (N a GPU number)"
            ))
        };
        match s.trim() {
            "cpu" => Ok(DeviceSpec::Cpu),
            "cuda" => Ok(DeviceSpec::Cuda(0)),
            t => {
                let n = t.strip_prefix("cuda:").ok_or_else(bad)?;
                let n: usize = n.parse().map_err(|_| bad())?;
                // a machine with more than 64 GPUs in one process is not a robot controller
                if n >= 64 {
                    return Err(bad());
                }
                Ok(DeviceSpec::Cuda(n))
            }
        }
    }
}

impl Precision {
    /// `f32` / `bf16`.
    pub fn name(&self) -> &'static str {
        match self {
            Precision::F32 => "f32",
            Precision::Bf16 => "bf16",
        }
    }
}

impl fmt::Display for Precision {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(self.name())
    }
}

impl FromStr for Precision {
    type Err = PolicyError;

    fn from_str(s: &str) -> Result<Self, Self::Err> {
        match s.trim() {
            "f32" => Ok(Precision::F32),
            "bf16" => Ok(Precision::Bf16),
            _ => Err(PolicyError::Config(format!(
                "precision {s:?}: must be one of f32, bf16"
            ))),
        }
    }
}

/// The CUDA libraries this build opens at run time (cudarc loads them dynamically: the binary
/// starts without them) that cannot be loaded here, as one list; Ok when all can.
#[cfg(feature = "cuda")]
fn missing_cuda_libraries() -> Result<(), String> {
    use candle_core::cuda_backend::cudarc;
    // SAFETY: each call only tries to dlopen the library (and closes nothing it did not open)
    let present = unsafe {
        [
            (
                "libcuda.so.1 (the NVIDIA driver)",
                cudarc::driver::sys::is_culib_present(),
            ),
            ("libcublas.so.13", cudarc::cublas::sys::is_culib_present()),
            (
                "libcublasLt.so.13",
                cudarc::cublaslt::sys::is_culib_present(),
            ),
            ("libcurand.so.10", cudarc::curand::sys::is_culib_present()),
            ("libnvrtc.so.13", cudarc::nvrtc::sys::is_culib_present()),
        ]
    };
    let missing: Vec<&str> = present
        .iter()
        .filter(|(_, ok)| !ok)
        .map(|(name, _)| *name)
        .collect();
    if missing.is_empty() {
        Ok(())
    } else {
        Err(missing.join(", "))
    }
}

/// serde through the names users write (`"cpu"`, `"cuda:1"`, `"bf16"`, ...): the `[policy]`
/// section of a robot configuration deserializes into these types directly.
macro_rules! serde_by_name {
    ($($t:ty),*) => {$(
        impl serde::Serialize for $t {
            fn serialize<S: serde::Serializer>(&self, s: S) -> Result<S::Ok, S::Error> {
                s.collect_str(self)
            }
        }

        impl<'de> serde::Deserialize<'de> for $t {
            fn deserialize<D: serde::Deserializer<'de>>(d: D) -> Result<Self, D::Error> {
                let s = <String as serde::Deserialize>::deserialize(d)?;
                s.parse()
                    .map_err(|e: PolicyError| serde::de::Error::custom(e.to_string()))
            }
        }
    )*};
}
pub(crate) use serde_by_name;

serde_by_name!(DeviceSpec, Precision);

/// The dtype the model's tensors are stored in on `device` for `precision`: f32 on the CPU
/// (bf16 there is a property of the packed products, not of storage), the precision's dtype on
/// a GPU.
pub fn model_dtype(device: &Device, precision: Precision) -> DType {
    match (device.is_cpu(), precision) {
        (true, _) | (false, Precision::F32) => DType::F32,
        (false, Precision::Bf16) => DType::BF16,
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn device_specs_parse_and_print() {
        assert_eq!("cpu".parse::<DeviceSpec>().unwrap(), DeviceSpec::Cpu);
        assert_eq!("cuda".parse::<DeviceSpec>().unwrap(), DeviceSpec::Cuda(0));
        assert_eq!("cuda:3".parse::<DeviceSpec>().unwrap(), DeviceSpec::Cuda(3));
        assert_eq!(DeviceSpec::Cuda(3).to_string(), "cuda:3");
        for bad in ["gpu", "cuda:", "cuda:x", "cuda:-1", "cuda:1000", "CPU", ""] {
            let e = bad.parse::<DeviceSpec>().unwrap_err().to_string();
            assert!(e.contains("\"cpu\", \"cuda\", \"cuda:N\""), "{bad}: {e}");
        }
        assert_eq!("bf16".parse::<Precision>().unwrap(), Precision::Bf16);
        assert!("fp16".parse::<Precision>().is_err());
    }

    #[test]
    fn cpu_keeps_f32_storage() {
        assert_eq!(model_dtype(&Device::Cpu, Precision::Bf16), DType::F32);
        assert_eq!(model_dtype(&Device::Cpu, Precision::F32), DType::F32);
    }

    #[cfg(not(feature = "cuda"))]
    #[test]
    fn cuda_without_the_feature_says_how_to_get_it() {
        let e = DeviceSpec::Cuda(0).open().unwrap_err().to_string();
        assert!(e.contains("--features cuda"), "{e}");
    }
}
