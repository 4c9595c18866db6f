//! Helpers shared by the policy crate's integration tests.

use nalgebra::{Matrix3, Rotation3, Vector3};
use rand::Rng;
use rand_chacha::ChaCha8Rng;

/// A random rotation: a uniformly drawn axis direction and an angle in (−3.1, 3.1) rad.
pub fn random_rotation(rng: &mut ChaCha8Rng) -> Matrix3<f64> {
    let axis = Vector3::new(
        rng.random_range(-1.0..1.0),
        rng.random_range(-1.0..1.0),
        rng.random_range(-1.0..1.0),
    );
    let angle = rng.random_range(-3.1..3.1);
    Rotation3::from_scaled_axis(axis.normalize() * angle).into_inner()
}
