//! The configuration's enums: each names its values as the TOML spells them, and an unknown
//! value is a load error that lists the allowed set.

use serde::{Deserialize, Serialize};

/// An enum of the configuration: serde by its TOML names (an unknown value is a load error that
/// lists the allowed set), `name()`, `Display`, and `FromStr` with the allowed set in the error.
macro_rules! config_enum {
    (
        $(#[$m:meta])*
        pub enum $name:ident ($what:literal) {
            $( $(#[$vm:meta])* $var:ident = $s:literal, )+
        }
    ) => {
        $(#[$m])*
        #[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, Default, Serialize, Deserialize)]
        pub enum $name {
            $( $(#[$vm])* #[serde(rename = $s)] $var, )+
        }

        impl $name {
            /// Every value, in the order the documentation lists them.
            pub const ALL: &'static [$name] = &[$($name::$var),+];

            /// The name in the configuration.
            pub fn name(&self) -> &'static str {
                match self {
                    $( $name::$var => $s, )+
                }
            }

            /// The allowed names, comma-separated (for errors and help).
            pub fn allowed() -> String {
                [$($s),+].join(", ")
            }
        }

        impl std::fmt::Display for $name {
            fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
                f.write_str(self.name())
            }
        }

        impl std::str::FromStr for $name {
            type Err = String;
            fn from_str(s: &str) -> Result<Self, String> {
                match s {
                    $( $s => Ok($name::$var), )+
                    _ => Err(format!("{} {s:?}: must be one of {}", $what, Self::allowed())),
                }
            }
        }
    };
}

config_enum! {
    /// `policy.kind`: which chunk source feeds the control loop.
    pub enum PolicyKind ("policy kind") {
        /// No policy: the controller holds the robot where it is.
        #[default]
        Hold = "hold",
        /// π0.
        Pi0 = "pi0",
        /// π0.5.
        Pi05 = "pi05",
    }
}

config_enum! {
    /// `policy.precision`: the arithmetic of the model's matrix products.
    pub enum PolicyPrecision ("precision") {
        /// f32 (the reference the parity tests hold to openpi).
        #[default]
        F32 = "f32",
        /// bf16 inputs with f32 accumulation (CPU: AMX / AVX512-BF16 kernels; GPU: bf16 tensors).
        Bf16 = "bf16",
    }
}

config_enum! {
    /// `execution.strategy`: how consecutive chunks take over from each other.
    pub enum Strategy ("strategy") {
        /// Switch at the first action of the new chunk that is not yet due.
        Replace = "replace",
        /// Blend old → new over `crossfade_ms`, starting where `Replace` would switch.
        Crossfade = "crossfade",
        /// ACT's temporal ensemble: exponentially weighted average of every chunk covering now.
        TemporalEnsemble = "temporal_ensemble",
        /// Real-time chunking: switch at once, at the index real time has reached; the sampler
        /// is guided towards the actions still to be executed.
        #[default]
        Rtc = "rtc",
        /// Training-time real-time chunking: switch at once like `Rtc`; a policy trained with a
        /// committed prefix (`chunkrt train --rtc-prefix`) is given the actions still to be
        /// executed and continues them (no guidance pass).
        RtcTrained = "rtc_trained",
    }
}

config_enum! {
    /// `execution.rtc_jacobian`: how `rtc`'s guidance treats the Jacobian of the clean estimate.
    pub enum RtcJacobian ("rtc jacobian") {
        /// ∂Â/∂x_t ≈ I: the guidance pulls the clean estimate straight towards the previous
        /// chunk; a guided step costs what an unguided one does. The default: on the reach
        /// sweep it also switches 10x more smoothly than the VJP, whose pull is weak where the
        /// policy's chunk hardly depends on the noise (BENCHMARKS.md §5).
        #[default]
        Identity = "identity",
        /// The exact vector-Jacobian product (the paper's): a backward pass through the action
        /// expert per denoising step.
        Vjp = "vjp",
    }
}

config_enum! {
    /// `execution.interpolation` between a chunk's actions.
    pub enum Interpolation ("interpolation") {
        /// Velocity-continuous cubic Hermite.
        #[default]
        Cubic = "cubic",
        /// Piecewise linear.
        Linear = "linear",
    }
}

config_enum! {
    /// `execution.trigger`: when the next inference is requested.
    pub enum Trigger ("trigger") {
        /// Once `execute_horizon` actions of the newest chunk are due.
        #[default]
        AfterS = "after_s",
        /// As soon as the previous inference landed.
        Continuous = "continuous",
    }
}

config_enum! {
    /// `execution.rtc_schedule`: RTC's soft-mask schedule between d and H − s.
    pub enum Schedule ("rtc schedule") {
        /// The paper's exponential decay `c (e^c − 1)/(e − 1)`.
        #[default]
        Exp = "exp",
        /// Linear decay `c`.
        Linear = "linear",
        /// 1 everywhere before H − s (hard prefix over the whole overlap).
        Ones = "ones",
        /// 0 from d on (hard prefix of d actions only).
        Zeros = "zeros",
    }
}

/// `policy.device`: `"cpu"`, `"cuda"` (GPU 0) or `"cuda:N"`.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub enum PolicyDevice {
    /// The host CPU.
    #[default]
    Cpu,
    /// NVIDIA GPU number N (a binary built with `--features cuda`).
    Cuda(u32),
}

impl std::fmt::Display for PolicyDevice {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            PolicyDevice::Cpu => f.write_str("cpu"),
            PolicyDevice::Cuda(n) => write!(f, "cuda:{n}"),
        }
    }
}

impl std::str::FromStr for PolicyDevice {
    type Err = String;
    fn from_str(s: &str) -> Result<Self, String> {
        let n = match s {
            "cpu" => return Ok(PolicyDevice::Cpu),
            "cuda" => Some(0),
            _ => s
                .strip_prefix("cuda:")
                .and_then(|n| n.parse::<u32>().ok())
                .filter(|&n| n < 64),
        };
        n.map(PolicyDevice::Cuda).ok_or_else(|| {
            format!(
                "device {s:?}: must be one of \"cpu\", \"cuda\", \"cuda:N\" (N a GPU number < 64)"
            )
        })
    }
}

impl Serialize for PolicyDevice {
    fn serialize<S: serde::Serializer>(&self, s: S) -> Result<S::Ok, S::Error> {
        s.collect_str(self)
    }
}

impl<'de> Deserialize<'de> for PolicyDevice {
    fn deserialize<D: serde::Deserializer<'de>>(d: D) -> Result<Self, D::Error> {
        let s = String::deserialize(d)?;
        s.parse().map_err(serde::de::Error::custom)
    }
}
