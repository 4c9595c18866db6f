//! Forward kinematics of the UR arms from their Denavit–Hartenberg parameters.
//!
//! Standard DH (Hawkins, "Analytic Inverse Kinematics for the Universal Robots UR-5/UR-10
//! Arms"): `T_i = Rz(θ_i) · Tz(d_i) · Tx(a_i) · Rx(α_i)`, with the base frame of the UR
//! controller (the frame `actual_TCP_pose` is reported in; the ROS `base_link` is this one
//! turned by π about z).

use cell_types::{Base, Flange, Joints, Transform};
use nalgebra::{Isometry3, Translation3, UnitQuaternion, Vector3};
use serde::{Deserialize, Serialize};
use std::f64::consts::FRAC_PI_2;

/// DH lengths of a UR arm (m).
#[derive(Copy, Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct UrParams {
    /// Base to shoulder height.
    pub d1: f64,
    /// Upper-arm length (negative in UR's convention).
    pub a2: f64,
    /// Forearm length (negative in UR's convention).
    pub a3: f64,
    /// Wrist 1 offset.
    pub d4: f64,
    /// Wrist 2 offset.
    pub d5: f64,
    /// Wrist 3 to flange.
    pub d6: f64,
}

/// The UR5 (CB3).
pub const UR5: UrParams = UrParams {
    d1: 0.089159,
    a2: -0.425,
    a3: -0.39225,
    d4: 0.10915,
    d5: 0.09465,
    d6: 0.0823,
};

/// The UR5e.
pub const UR5E: UrParams = UrParams {
    d1: 0.1625,
    a2: -0.425,
    a3: -0.3922,
    d4: 0.1333,
    d5: 0.0997,
    d6: 0.0996,
};

impl UrParams {
    /// The DH table rows `(d, a, alpha)` for joints 1..6.
    pub fn dh_rows(&self) -> [(f64, f64, f64); 6] {
        [
            (self.d1, 0.0, FRAC_PI_2),
            (0.0, self.a2, 0.0),
            (0.0, self.a3, 0.0),
            (self.d4, 0.0, FRAC_PI_2),
            (self.d5, 0.0, -FRAC_PI_2),
            (self.d6, 0.0, 0.0),
        ]
    }

    /// The frames of every joint's output link in the base frame: entry 0 is the base itself,
    /// entry `i` the frame after joint `i` (entry 6 is the flange).
    pub fn link_frames(&self, q: &Joints) -> [Isometry3<f64>; 7] {
        let mut out = [Isometry3::identity(); 7];
        let mut t = Isometry3::identity();
        for (i, (d, a, alpha)) in self.dh_rows().iter().enumerate() {
            t *= dh_transform(q[i], *d, *a, *alpha);
            out[i + 1] = t;
        }
        out
    }

    /// Pose of the flange (UR `tool0`) in the base frame.
    pub fn forward(&self, q: &Joints) -> Transform<Base, Flange> {
        Transform::from_isometry(self.link_frames(q)[6])
    }
}

/// One standard DH step `Rz(θ) Tz(d) Tx(a) Rx(α)`.
pub fn dh_transform(theta: f64, d: f64, a: f64, alpha: f64) -> Isometry3<f64> {
    let rz = UnitQuaternion::from_axis_angle(&Vector3::z_axis(), theta);
    let rx = UnitQuaternion::from_axis_angle(&Vector3::x_axis(), alpha);
    let trans = rz * Vector3::new(a, 0.0, d);
    Isometry3::from_parts(Translation3::from(trans), rz * rx)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn zero_configuration_matches_ur_convention() {
        // At q = 0 the UR5 is stretched out along -x of the base frame, flange pointing -y
        // after wrist 2... the classic values: x = a2 + a3, y = -(d4 + d6), z = d1 - d5.
        let p = UR5.forward(&[0.0; 6]).translation();
        assert!((p.x - (UR5.a2 + UR5.a3)).abs() < 1e-12);
        assert!((p.y - (-(UR5.d4 + UR5.d6))).abs() < 1e-12);
        assert!((p.z - (UR5.d1 - UR5.d5)).abs() < 1e-12);
    }
}
