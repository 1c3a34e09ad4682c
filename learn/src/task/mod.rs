//! The reach task on the controller side: scripted expert demonstrations, the dataset they are
//! recorded into, and closed-loop episodes in simulated time (training validation, `chunkrt
//! eval`). The scene itself (geometry, targets, rendering) lives in `chunkrt_tools::scene`, so
//! the fake camera renders exactly the pixels the policy was trained on.

pub mod dataset;
pub mod expert;
pub mod probe;
pub mod sim;
pub mod so101;
pub mod vocab;

pub use chunkrt_tools::scene::{
    end_effector, inverse_kinematics, ReachScene, TargetColor, REACH_TOLERANCE, TARGET_RADIUS,
};

use chunkrt_controller::config::{CameraConfig, Config};

/// The tasks chunkrt trains and evaluates on.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, clap::ValueEnum)]
pub enum TaskKind {
    /// The embedded demo's planar arm reaching a prompted target (in process).
    #[default]
    Reach,
    /// The SO-101 pick-and-place of `lerobot-env-so101` in MuJoCo ([`so101`]).
    So101,
}

/// Arm joints of the task robot (then the gripper).
pub const ARM_JOINTS: usize = 3;
/// Joints of the task robot: 3 arm joints and the gripper.
pub const TASK_DOF: usize = 4;

/// The camera the task is seen through: the configuration's first camera, which must be rgb8.
pub fn task_camera(cfg: &Config) -> anyhow::Result<&CameraConfig> {
    let cam = cfg.cameras.first().ok_or_else(|| {
        anyhow::anyhow!("the reach task needs a camera; the configuration has none")
    })?;
    anyhow::ensure!(
        cam.encoding == "rgb8",
        "camera {}: the reach task renders rgb8, the configuration says {}",
        cam.name,
        cam.encoding
    );
    anyhow::ensure!(
        cfg.n_dof() == TASK_DOF,
        "the reach task drives {TASK_DOF} joints (3 arm joints + gripper), the configuration has {}",
        cfg.n_dof()
    );
    Ok(cam)
}

/// A rendered task frame (RGB rows, `width` × `height`, no padding) as the policy takes it,
/// under the image input `camera`.
pub fn rgb_frame<'a>(
    camera: &'a str,
    width: usize,
    height: usize,
    data: &'a [u8],
) -> chunkrt_policy::runtime::RawFrame<'a> {
    chunkrt_policy::runtime::RawFrame {
        camera,
        width: width as u32,
        height: height as u32,
        stride: 3 * width as u32,
        encoding: chunkrt_policy::Encoding::Rgb8,
        data,
    }
}

/// The robot's home pose (the configured initial positions of the task's joints).
pub fn home_pose(cfg: &Config) -> [f64; TASK_DOF] {
    let mut home = [0.0; TASK_DOF];
    for (h, j) in home.iter_mut().zip(cfg.robot.joints.iter()) {
        *h = j.initial_position;
    }
    home
}
