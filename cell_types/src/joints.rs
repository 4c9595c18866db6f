//! Joint vectors of the six-axis arm, in radians.

use serde::{Deserialize, Serialize};

/// Number of arm joints (UR5: base, shoulder, elbow, wrist 1, wrist 2, wrist 3).
pub const JOINT_COUNT: usize = 6;

/// Joint positions (rad), or velocities (rad/s), accelerations, jerks: one value per joint.
pub type Joints = [f64; JOINT_COUNT];

/// What the arm reports about its joints at one instant.
#[derive(Copy, Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct JointState {
    /// Joint positions (rad).
    pub position: Joints,
    /// Joint velocities (rad/s).
    pub velocity: Joints,
}

impl JointState {
    /// A state at rest at `position`.
    pub fn at_rest(position: Joints) -> Self {
        Self {
            position,
            velocity: [0.0; JOINT_COUNT],
        }
    }
}

/// Largest absolute per-joint difference between two joint vectors.
pub fn max_abs_diff(a: &Joints, b: &Joints) -> f64 {
    a.iter()
        .zip(b)
        .map(|(x, y)| (x - y).abs())
        .fold(0.0, f64::max)
}

/// Wraps an angle into (-π, π].
pub fn wrap_to_pi(angle: f64) -> f64 {
    let two_pi = std::f64::consts::TAU;
    let mut a = angle.rem_euclid(two_pi);
    if a > std::f64::consts::PI {
        a -= two_pi;
    }
    a
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::f64::consts::PI;

    #[test]
    fn wrap_to_pi_range() {
        for k in -20..=20 {
            let a = 0.3 + k as f64 * 0.77;
            let w = wrap_to_pi(a);
            assert!(w > -PI - 1e-12 && w <= PI + 1e-12);
            assert!(
                ((a - w) / std::f64::consts::TAU).fract().abs() < 1e-9
                    || ((a - w) / std::f64::consts::TAU).fract().abs() > 1.0 - 1e-9
            );
        }
        assert!((wrap_to_pi(PI) - PI).abs() < 1e-12);
        assert!((wrap_to_pi(-PI) - PI).abs() < 1e-12);
    }

    #[test]
    fn max_abs_diff_picks_largest() {
        let a = [0.0, 1.0, 2.0, 3.0, 4.0, 5.0];
        let b = [0.0, 1.5, 2.0, 2.0, 4.0, 5.1];
        assert!((max_abs_diff(&a, &b) - 1.0).abs() < 1e-12);
    }
}
