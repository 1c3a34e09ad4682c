//! Jerk-limited online trajectory generation: a safe Rust face of the allocation-free C shim
//! over the official ruckig C++ library (`rt/ffi/chunkrt_ruckig.{h,cpp}`, built by `rt/build.rs`).
//!
//! [`Otg::new`] allocates the generator once; [`Otg::update`], [`Otg::calculate`] and
//! [`Otg::at_time`] never allocate (the generator is a fixed-size `Ruckig<16>`; joints beyond
//! `dofs` are disabled).

/// Joints one generator holds: the shim's fixed capacity (`CHUNKRT_RK_MAX_DOF` in
/// `ffi/chunkrt_ruckig.h`). Equal to `chunkrt_ipc::MAX_DOF`, which the controller checks at
/// compile time; kept here so that this crate needs no IPC.
pub const MAX_DOF: usize = 16;

/// Flat input of one update (SI units). Mirrors `chunkrt_rk_input`.
#[repr(C)]
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct OtgInput {
    /// Joints in use, 1..=MAX_DOF.
    pub dofs: u32,
    /// 0: position interface, 1: velocity interface (targets are velocities).
    pub control_interface: i32,
    /// 0: time, 1: time if necessary, 2: phase, 3: none.
    pub synchronization: i32,
    /// Zero.
    pub reserved: i32,
    pub current_position: [f64; MAX_DOF],
    pub current_velocity: [f64; MAX_DOF],
    pub current_acceleration: [f64; MAX_DOF],
    pub target_position: [f64; MAX_DOF],
    pub target_velocity: [f64; MAX_DOF],
    pub target_acceleration: [f64; MAX_DOF],
    pub max_velocity: [f64; MAX_DOF],
    pub max_acceleration: [f64; MAX_DOF],
    pub max_jerk: [f64; MAX_DOF],
    /// `-inf` disables the limit.
    pub min_position: [f64; MAX_DOF],
    /// `+inf` disables the limit.
    pub max_position: [f64; MAX_DOF],
}

impl Default for OtgInput {
    fn default() -> Self {
        Self {
            dofs: 1,
            control_interface: CONTROL_POSITION,
            synchronization: 0,
            reserved: 0,
            current_position: [0.0; MAX_DOF],
            current_velocity: [0.0; MAX_DOF],
            current_acceleration: [0.0; MAX_DOF],
            target_position: [0.0; MAX_DOF],
            target_velocity: [0.0; MAX_DOF],
            target_acceleration: [0.0; MAX_DOF],
            max_velocity: [1.0; MAX_DOF],
            max_acceleration: [1.0; MAX_DOF],
            max_jerk: [1.0; MAX_DOF],
            min_position: [f64::NEG_INFINITY; MAX_DOF],
            max_position: [f64::INFINITY; MAX_DOF],
        }
    }
}

/// Position control interface (`OtgInput::control_interface`).
pub const CONTROL_POSITION: i32 = 0;
/// Velocity control interface (`OtgInput::control_interface`): used for braking.
pub const CONTROL_VELOCITY: i32 = 1;

/// Kinematic state at one instant. Mirrors `chunkrt_rk_state`.
#[repr(C)]
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct OtgState {
    pub position: [f64; MAX_DOF],
    pub velocity: [f64; MAX_DOF],
    pub acceleration: [f64; MAX_DOF],
    pub jerk: [f64; MAX_DOF],
}

impl Default for OtgState {
    fn default() -> Self {
        Self {
            position: [0.0; MAX_DOF],
            velocity: [0.0; MAX_DOF],
            acceleration: [0.0; MAX_DOF],
            jerk: [0.0; MAX_DOF],
        }
    }
}

/// Output of one update. Mirrors `chunkrt_rk_output`.
#[repr(C)]
#[derive(Debug, Clone, Copy, Default, PartialEq)]
pub struct OtgOutput {
    /// State one cycle later.
    pub state: OtgState,
    /// Time on the current trajectory (s).
    pub time: f64,
    /// Duration of the current trajectory (s).
    pub duration: f64,
    /// 1 when the update computed a new trajectory.
    pub new_calculation: i32,
    /// Zero.
    pub reserved: i32,
}

/// ruckig's result codes (`ruckig::Result`).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum OtgResult {
    /// The trajectory is being followed.
    Working,
    /// The target has been reached.
    Finished,
    /// An error (ruckig's negative code).
    Error(i32),
}

impl OtgResult {
    fn from_code(c: i32) -> Self {
        match c {
            0 => Self::Working,
            1 => Self::Finished,
            e => Self::Error(e),
        }
    }

    /// Working or finished.
    pub fn is_ok(self) -> bool {
        !matches!(self, Self::Error(_))
    }
}

#[repr(C)]
struct RawHandle {
    _private: [u8; 0],
}

extern "C" {
    fn chunkrt_rk_new(delta_time: f64) -> *mut RawHandle;
    fn chunkrt_rk_free(h: *mut RawHandle);
    fn chunkrt_rk_reset(h: *mut RawHandle);
    fn chunkrt_rk_update(h: *mut RawHandle, input: *const OtgInput, out: *mut OtgOutput) -> i32;
    fn chunkrt_rk_calculate(h: *mut RawHandle, input: *const OtgInput, duration: *mut f64) -> i32;
    fn chunkrt_rk_at_time(h: *const RawHandle, time: f64, out: *mut OtgState);
    fn chunkrt_rk_cxx_allocations() -> u64;
}

/// The generator could not be created.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum OtgError {
    #[error("ruckig cycle time {0} s must be finite and positive")]
    DeltaTime(f64),
    #[error("out of memory creating the ruckig generator")]
    OutOfMemory,
}

/// One ruckig generator (fixed capacity of [`MAX_DOF`] joints).
pub struct Otg {
    raw: *mut RawHandle,
    delta_time: f64,
}

// SAFETY: the handle is exclusively owned; the C++ object has no thread affinity.
unsafe impl Send for Otg {}

impl Otg {
    /// Creates a generator for cycle time `delta_time` (s). Allocates (once).
    pub fn new(delta_time: f64) -> Result<Self, OtgError> {
        if !(delta_time.is_finite() && delta_time > 0.0) {
            return Err(OtgError::DeltaTime(delta_time));
        }
        // SAFETY: plain C call; returns null on failure.
        let raw = unsafe { chunkrt_rk_new(delta_time) };
        if raw.is_null() {
            return Err(OtgError::OutOfMemory);
        }
        Ok(Self { raw, delta_time })
    }

    /// Cycle time (s).
    pub fn delta_time(&self) -> f64 {
        self.delta_time
    }

    /// Forces a new calculation at the next update.
    pub fn reset(&mut self) {
        // SAFETY: `raw` is a live handle owned by `self`.
        unsafe { chunkrt_rk_reset(self.raw) }
    }

    /// One online step (ruckig's `update`): the state one cycle along the time-optimal
    /// trajectory from the input's current state to its target. Allocation-free.
    pub fn update(&mut self, input: &OtgInput, out: &mut OtgOutput) -> OtgResult {
        // SAFETY: `raw` is live; `input` and `out` are valid for the call; the shim checks `dofs`.
        OtgResult::from_code(unsafe { chunkrt_rk_update(self.raw, input, out) })
    }

    /// Offline calculation (ruckig's `calculate`); returns the result and the duration (s).
    pub fn calculate(&mut self, input: &OtgInput) -> (OtgResult, f64) {
        let mut d = 0.0;
        // SAFETY: as in `update`.
        let r = unsafe { chunkrt_rk_calculate(self.raw, input, &mut d) };
        (OtgResult::from_code(r), d)
    }

    /// Samples the trajectory of the last [`Otg::calculate`] at `time` (s).
    pub fn at_time(&self, time: f64, out: &mut OtgState) {
        // SAFETY: `raw` is live; `out` is valid.
        unsafe { chunkrt_rk_at_time(self.raw, time, out) }
    }
}

impl Drop for Otg {
    fn drop(&mut self) {
        // SAFETY: `raw` came from `chunkrt_rk_new` and is freed exactly once.
        unsafe { chunkrt_rk_free(self.raw) }
    }
}

/// Number of C++ `operator new` calls in this process so far (the shim replaces the global
/// allocation functions with counting ones). Tests use it to prove the tick allocates nothing.
pub fn cxx_allocations() -> u64 {
    // SAFETY: reads an atomic counter.
    unsafe { chunkrt_rk_cxx_allocations() }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn reaches_target_within_limits() {
        let mut otg = Otg::new(0.001).expect("valid dt");
        let mut inp = OtgInput {
            dofs: 2,
            ..Default::default()
        };
        inp.target_position[0] = 1.0;
        inp.target_position[1] = -0.5;
        inp.max_velocity[..2].copy_from_slice(&[2.0, 2.0]);
        inp.max_acceleration[..2].copy_from_slice(&[10.0, 10.0]);
        inp.max_jerk[..2].copy_from_slice(&[100.0, 100.0]);
        let mut out = OtgOutput::default();
        let mut finished = false;
        for _ in 0..5000 {
            let r = otg.update(&inp, &mut out);
            assert!(r.is_ok(), "{r:?}");
            for j in 0..2 {
                assert!(out.state.velocity[j].abs() <= 2.0 + 1e-9);
                assert!(out.state.acceleration[j].abs() <= 10.0 + 1e-9);
            }
            inp.current_position = out.state.position;
            inp.current_velocity = out.state.velocity;
            inp.current_acceleration = out.state.acceleration;
            if r == OtgResult::Finished {
                finished = true;
                break;
            }
        }
        assert!(finished);
        assert!((out.state.position[0] - 1.0).abs() < 1e-9);
        assert!((out.state.position[1] + 0.5).abs() < 1e-9);
        assert!(Otg::new(0.0).is_err());
    }
}
