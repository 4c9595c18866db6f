//! Coordinate frames and frame-tagged rigid transforms.
//!
//! A [`Transform<A, B>`] maps coordinates expressed in frame `B` into frame `A`; name values
//! `a_from_b` (e.g. `base_from_tcp`). Composition checks the frames at compile time:
//! `Transform<A, B> * Transform<B, C> = Transform<A, C>`. Cameras are numbered at run time
//! ([`FrameId::Camera`]); their transforms use the [`Camera`] tag and carry the index in the
//! surrounding struct.

use std::fmt;
use std::marker::PhantomData;
use std::ops::Mul;

use nalgebra::{Isometry3, Point3, Translation3, UnitQuaternion, Vector3};
use serde::{Deserialize, Serialize};

/// A frame marker type.
pub trait Frame: Copy + Clone + fmt::Debug + Default + PartialEq + Send + Sync + 'static {
    /// Human-readable name of the frame.
    const NAME: &'static str;
}

macro_rules! frame {
    ($(#[$doc:meta])* $name:ident, $label:literal) => {
        $(#[$doc])*
        #[derive(Copy, Clone, Debug, Default, PartialEq, Eq, Hash, Serialize, Deserialize)]
        pub struct $name;
        impl Frame for $name {
            const NAME: &'static str = $label;
        }
    };
}

frame!(
    /// The robot base frame (UR convention: z up, at the base mounting plate).
    Base, "base");
frame!(
    /// The tool flange (UR `tool0`).
    Flange, "flange");
frame!(
    /// The tool centre point: between the gripper fingertips.
    Tcp, "tcp");
frame!(
    /// A depth camera's optical frame (x right, y down, z forward), librealsense convention.
    Camera, "camera");
frame!(
    /// The calibration board's frame (origin at its first corner, z out of the board).
    Board, "board");
frame!(
    /// A world frame, where a scene or benchmark defines one apart from the robot base.
    World, "world");

/// A frame named at run time, for data that carries its frame with it (clouds, recordings).
#[derive(Copy, Clone, Debug, PartialEq, Eq, Hash, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum FrameId {
    /// The robot base frame.
    Base,
    /// The tool flange.
    Flange,
    /// The tool centre point.
    Tcp,
    /// Camera number `n`'s optical frame.
    Camera(u8),
    /// The calibration board.
    Board,
    /// A world frame.
    World,
}

impl fmt::Display for FrameId {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self {
            FrameId::Base => write!(f, "base"),
            FrameId::Flange => write!(f, "flange"),
            FrameId::Tcp => write!(f, "tcp"),
            FrameId::Camera(i) => write!(f, "camera_{i}"),
            FrameId::Board => write!(f, "board"),
            FrameId::World => write!(f, "world"),
        }
    }
}

/// A rigid transform that maps coordinates in frame `From` into frame `To` (`to_from_from`).
#[derive(Copy, Clone, PartialEq, Serialize, Deserialize)]
#[serde(transparent)]
pub struct Transform<To: Frame, From: Frame> {
    iso: Isometry3<f64>,
    #[serde(skip)]
    _frames: PhantomData<(To, From)>,
}

impl<To: Frame, From: Frame> fmt::Debug for Transform<To, From> {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        let t = self.iso.translation.vector;
        let (r, p, y) = self.iso.rotation.euler_angles();
        write!(
            f,
            "{}_from_{}(t = [{:.6}, {:.6}, {:.6}] m, rpy = [{:.6}, {:.6}, {:.6}] rad)",
            To::NAME,
            From::NAME,
            t.x,
            t.y,
            t.z,
            r,
            p,
            y
        )
    }
}

impl<To: Frame, From: Frame> Default for Transform<To, From> {
    fn default() -> Self {
        Self::identity()
    }
}

impl<To: Frame, From: Frame> Transform<To, From> {
    /// Wraps a plain isometry, asserting by name that it maps `From` into `To`.
    pub fn from_isometry(iso: Isometry3<f64>) -> Self {
        Self {
            iso,
            _frames: PhantomData,
        }
    }

    /// The identity transform.
    pub fn identity() -> Self {
        Self::from_isometry(Isometry3::identity())
    }

    /// Builds from a translation (m) and a unit quaternion.
    pub fn from_parts(translation: Vector3<f64>, rotation: UnitQuaternion<f64>) -> Self {
        Self::from_isometry(Isometry3::from_parts(
            Translation3::from(translation),
            rotation,
        ))
    }

    /// Builds from a translation (m) and roll, pitch, yaw (rad, extrinsic x-y-z).
    pub fn from_xyz_rpy(xyz: [f64; 3], rpy: [f64; 3]) -> Self {
        Self::from_parts(
            Vector3::new(xyz[0], xyz[1], xyz[2]),
            UnitQuaternion::from_euler_angles(rpy[0], rpy[1], rpy[2]),
        )
    }

    /// The underlying isometry.
    pub fn isometry(&self) -> &Isometry3<f64> {
        &self.iso
    }

    /// The translation part (the origin of `From` expressed in `To`), in metres.
    pub fn translation(&self) -> Vector3<f64> {
        self.iso.translation.vector
    }

    /// The rotation part.
    pub fn rotation(&self) -> UnitQuaternion<f64> {
        self.iso.rotation
    }

    /// The inverse transform, mapping `To` into `From`.
    pub fn inverse(&self) -> Transform<From, To> {
        Transform::from_isometry(self.iso.inverse())
    }

    /// Maps a point expressed in `From` into `To`.
    pub fn transform_point(&self, p: &Point3<f64>) -> Point3<f64> {
        self.iso.transform_point(p)
    }

    /// Maps a free vector (direction) expressed in `From` into `To`.
    pub fn transform_vector(&self, v: &Vector3<f64>) -> Vector3<f64> {
        self.iso.transform_vector(v)
    }

    /// Re-tags the frames. Use only where the frames are known by convention (e.g. the
    /// benchmark's world frame equals the base frame).
    pub fn retag<To2: Frame, From2: Frame>(self) -> Transform<To2, From2> {
        Transform::from_isometry(self.iso)
    }

    /// Distance between the origins (m) and the rotation angle between the two (rad).
    pub fn error_to(&self, other: &Self) -> (f64, f64) {
        let dt = (self.translation() - other.translation()).norm();
        let dr = self.rotation().angle_to(&other.rotation());
        (dt, dr)
    }

    /// True when translation and rotation are finite and the quaternion is unit length.
    pub fn is_finite(&self) -> bool {
        let t = self.translation();
        let q = self.rotation().into_inner();
        t.iter().all(|v| v.is_finite())
            && q.coords.iter().all(|v| v.is_finite())
            && (q.norm() - 1.0).abs() < 1e-6
    }
}

impl<A: Frame, B: Frame, C: Frame> Mul<Transform<B, C>> for Transform<A, B> {
    type Output = Transform<A, C>;
    fn mul(self, rhs: Transform<B, C>) -> Transform<A, C> {
        Transform::from_isometry(self.iso * rhs.iso)
    }
}

impl<A: Frame, B: Frame, C: Frame> Mul<&Transform<B, C>> for &Transform<A, B> {
    type Output = Transform<A, C>;
    fn mul(self, rhs: &Transform<B, C>) -> Transform<A, C> {
        Transform::from_isometry(self.iso * rhs.iso)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn composition_and_inverse_round_trip() {
        let base_from_flange: Transform<Base, Flange> =
            Transform::from_xyz_rpy([0.3, -0.1, 0.5], [0.1, -0.2, 0.3]);
        let flange_from_tcp: Transform<Flange, Tcp> =
            Transform::from_xyz_rpy([0.0, 0.0, 0.15], [0.0, 0.0, 1.0]);
        let base_from_tcp = base_from_flange * flange_from_tcp;
        let back = base_from_tcp * flange_from_tcp.inverse();
        let (dt, dr) = back.error_to(&base_from_flange);
        assert!(dt < 1e-12 && dr < 1e-12, "{dt} {dr}");
        let p = Point3::new(0.0, 0.0, 0.0);
        let tcp_in_base = base_from_tcp.transform_point(&p);
        let expected = base_from_flange.transform_point(&Point3::new(0.0, 0.0, 0.15));
        assert!((tcp_in_base - expected).norm() < 1e-12);
    }

    #[test]
    fn debug_names_the_frames() {
        let t: Transform<Base, Tcp> = Transform::identity();
        assert!(format!("{t:?}").starts_with("base_from_tcp("));
    }

    #[test]
    fn non_unit_rotation_is_not_finite() {
        let mut t: Transform<Base, Tcp> = Transform::identity();
        assert!(t.is_finite());
        t = Transform::from_parts(Vector3::new(f64::NAN, 0.0, 0.0), UnitQuaternion::identity());
        assert!(!t.is_finite());
    }
}
