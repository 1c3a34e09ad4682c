//! The Franka FR3's joint limits, as the robot checks the motion generator's commands.
//!
//! Sources (numbers restated, nothing copied):
//! - Franka's datasheet table of the FR3's joint limits (frankaemika/docs,
//!   `source/control-parameters-joint-fr3.csv`, 2025-08): position range, maximum velocity,
//!   acceleration 10 rad/s², jerk 5000 rad/s³ for every joint.
//! - libfranka's FR3 velocity envelope (`include/franka/rate_limiting.h`, 0.15.0; from 0.18 read
//!   from the URDF the robot serves, with the same values in `test/fr3.urdf` of 0.21.2): near a
//!   position limit the allowed speed towards it is `-offset + sqrt(2 · decel · distance)`,
//!   capped at the maximum velocity, minus 1e-3.
//! - The robot differentiates the commanded positions at 1 kHz: an acceleration past the limit
//!   is `joint_motion_generator_velocity_discontinuity`, a jerk past it
//!   `joint_motion_generator_acceleration_discontinuity` (libfranka's documentation of the
//!   motion generators' errors).

/// Joints of the arm.
pub const JOINTS: usize = 7;

/// The FCI's cycle: one command per millisecond of robot time.
pub const CYCLE_S: f64 = 1e-3;

/// Position range of the datasheet (rad).
pub const Q_MIN: [f64; JOINTS] = [-2.7437, -1.7837, -2.9007, -3.0421, -2.8065, 0.5445, -3.0159];
/// Position range of the datasheet (rad).
pub const Q_MAX: [f64; JOINTS] = [2.7437, 1.7837, 2.9007, -0.1518, 2.8065, 4.5169, 3.0159];
/// Maximum joint velocity of the datasheet (rad/s).
pub const DQ_MAX: [f64; JOINTS] = [2.62, 2.62, 2.62, 2.62, 5.26, 4.18, 5.26];
/// Maximum joint acceleration (rad/s²).
pub const DDQ_MAX: f64 = 10.0;
/// Maximum joint jerk (rad/s³).
pub const DDDQ_MAX: f64 = 5000.0;

/// libfranka's FR3 envelope: the position limits it is computed against (rad).
pub const ENVELOPE_Q_MIN: [f64; JOINTS] = [
    -2.7501, -1.7918, -2.9065, -3.0481, -2.8101, 0.54092, -3.0196,
];
/// libfranka's FR3 envelope: the position limits it is computed against (rad).
pub const ENVELOPE_Q_MAX: [f64; JOINTS] = [2.7501, 1.7918, 2.9065, -0.1458, 2.8101, 4.5205, 3.0196];
/// libfranka's FR3 envelope: the velocity offset per joint (rad/s).
pub const ENVELOPE_OFFSET: [f64; JOINTS] = [0.30, 0.20, 0.20, 0.30, 0.35, 0.35, 0.35];
/// libfranka's FR3 envelope: the deceleration per joint (rad/s²).
pub const ENVELOPE_DECEL: [f64; JOINTS] = [6.0, 2.585, 3.5, 4.0, 17.0, 5.5, 17.0];
/// libfranka's tolerance below the envelope (rad/s).
pub const ENVELOPE_EPS: f64 = 1e-3;

/// The highest velocity the robot accepts at position `q` (towards `ENVELOPE_Q_MAX`), joint `j`.
pub fn upper_velocity(j: usize, q: f64) -> f64 {
    let room = (2.0 * ENVELOPE_DECEL[j] * (ENVELOPE_Q_MAX[j] - q))
        .max(0.0)
        .sqrt();
    DQ_MAX[j].min((room - ENVELOPE_OFFSET[j]).max(0.0)) - ENVELOPE_EPS
}

/// The lowest velocity the robot accepts at position `q` (towards `ENVELOPE_Q_MIN`), joint `j`.
pub fn lower_velocity(j: usize, q: f64) -> f64 {
    let room = (2.0 * ENVELOPE_DECEL[j] * (q - ENVELOPE_Q_MIN[j]))
        .max(0.0)
        .sqrt();
    (-DQ_MAX[j]).max((ENVELOPE_OFFSET[j] - room).min(0.0)) + ENVELOPE_EPS
}

/// How a command would fare at the robot: the first limit it breaks, with its value and the
/// limit (what a reflex would name), or `None`.
pub fn violation(
    prev: &[f64; JOINTS],
    dq_prev: &[f64; JOINTS],
    ddq_prev: &[f64; JOINTS],
    q: &[f64; JOINTS],
) -> Option<(usize, &'static str, f64, f64)> {
    for j in 0..JOINTS {
        let v = (q[j] - prev[j]) / CYCLE_S;
        let a = (v - dq_prev[j]) / CYCLE_S;
        let jerk = (a - ddq_prev[j]) / CYCLE_S;
        if !(Q_MIN[j]..=Q_MAX[j]).contains(&q[j]) {
            return Some((
                j,
                "position",
                q[j],
                if q[j] < Q_MIN[j] { Q_MIN[j] } else { Q_MAX[j] },
            ));
        }
        if v > upper_velocity(j, prev[j]) + ENVELOPE_EPS
            || v < lower_velocity(j, prev[j]) - ENVELOPE_EPS
        {
            return Some((j, "velocity", v, DQ_MAX[j]));
        }
        if a.abs() > DDQ_MAX {
            return Some((j, "acceleration", a, DDQ_MAX));
        }
        if jerk.abs() > DDDQ_MAX {
            return Some((j, "jerk", jerk, DDDQ_MAX));
        }
    }
    None
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_envelope_closes_at_the_limits_and_opens_to_the_maximum_between() {
        for j in 0..JOINTS {
            let mid = 0.5 * (ENVELOPE_Q_MIN[j] + ENVELOPE_Q_MAX[j]);
            assert!(
                (upper_velocity(j, mid) - (DQ_MAX[j] - ENVELOPE_EPS)).abs() < 1e-12,
                "{j}"
            );
            assert!(
                (lower_velocity(j, mid) + (DQ_MAX[j] - ENVELOPE_EPS)).abs() < 1e-12,
                "{j}"
            );
            // at the limit nothing more towards it is allowed
            assert!(upper_velocity(j, ENVELOPE_Q_MAX[j]) <= 0.0, "{j}");
            assert!(lower_velocity(j, ENVELOPE_Q_MIN[j]) >= 0.0, "{j}");
            // joint 2 (a = 2.585, offset 0.2): 0.1 rad from the limit, sqrt(0.517) - 0.2
            if j == 1 {
                let v = upper_velocity(j, ENVELOPE_Q_MAX[j] - 0.1);
                assert!((v - (0.517f64.sqrt() - 0.2 - 1e-3)).abs() < 1e-9, "{v}");
            }
        }
    }

    #[test]
    fn a_step_of_ten_milliradians_is_an_acceleration_past_the_limit() {
        let q0 = [0.0, 0.0, 0.0, -1.57, 0.0, 1.57, 0.785];
        let mut q = q0;
        q[3] += 0.01;
        let v = violation(&q0, &[0.0; JOINTS], &[0.0; JOINTS], &q).expect("a violation");
        // 10 rad/s in one cycle: past the velocity limit before anything else
        assert_eq!((v.0, v.1), (3, "velocity"));
        let mut q = q0;
        q[3] += 1e-6; // 1 mrad/s: 1 rad/s² in one cycle, 1000 rad/s³
        assert!(violation(&q0, &[0.0; JOINTS], &[0.0; JOINTS], &q).is_none());
        q[3] = q0[3] + 0.8e-5; // 8 rad/s² (within), 8000 rad/s³ (not)
        assert_eq!(
            violation(&q0, &[0.0; JOINTS], &[0.0; JOINTS], &q).map(|v| v.1),
            Some("jerk")
        );
    }
}
