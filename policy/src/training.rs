//! The pieces of EquAct's training objective that do not depend on the network's backward
//! pass (issue 9 item 3; `equact.md` "Heads" and "Physical-robot configuration"): the three
//! losses with their gradients with respect to the network's logits, and the paper's
//! rotation augmentation of a training sample.
//!
//! - Translation: hard cross-entropy over the sampled query points against the sample
//!   nearest the ground truth (training inserts the ground truth among the samples, so that
//!   nearest is the truth itself).
//! - Gripper open: binary cross-entropy on the open logit.
//! - Rotation: soft cross-entropy over the SO(3) grid with labels
//!   `softmax(−geodesic° / 2.5)`.
//! - Augmentation: a rotation about the workspace centre, uniform within ±5°, ±5°, ±45°
//!   about the base x, y, z axes, applied to the cloud, the current gripper pose and the
//!   keyframe together (so the sample stays consistent).
//! - Held-object shift (ours, off by default): where a keyframe is placed by the scene while
//!   the gripper carries a free object (a roll carried to the spindle and let go over it),
//!   the gripper and the points of what it holds are moved sideways and the keyframe is kept,
//!   so the network learns to place it by the scene, not relative to the hand (which every
//!   demonstration shows exactly where the expert put it).
//!
//! Every loss is computed in a numerically stable form (log-sum-exp with the maximum
//! subtracted; BCE through softplus) and returns the gradient the backward pass starts
//! from.

use cell_types::{Base, Keyframe, PointCloud, Tcp, Transform};
use nalgebra::{Isometry3, Matrix3, Point3, Translation3, UnitQuaternion, Vector3};
use rand::Rng;

use crate::error::{PolicyError, Result};
use crate::predict::GripperPose;

/// Temperature of the rotation labels (degrees of geodesic distance).
pub const ROTATION_LABEL_DEG: f64 = 2.5;

/// A loss value and its gradient with respect to the logits it was computed from.
#[derive(Debug, Clone, PartialEq)]
pub struct LossGrad {
    /// The loss.
    pub loss: f64,
    /// d loss / d logit, one per logit.
    pub grad: Vec<f64>,
}

/// Index of the sample nearest `truth` (the translation target).
pub fn nearest_sample(samples: &[[f32; 3]], truth: [f32; 3]) -> Result<usize> {
    let d2 = |p: &[f32; 3]| (0..3).map(|k| (p[k] - truth[k]).powi(2)).sum::<f32>();
    samples
        .iter()
        .enumerate()
        .filter(|(_, p)| p.iter().all(|v| v.is_finite()))
        .min_by(|a, b| d2(a.1).total_cmp(&d2(b.1)))
        .map(|(i, _)| i)
        .ok_or(PolicyError::TooFewPoints {
            what: "translation loss samples",
            needed: 1,
            got: 0,
        })
}

/// Hard cross-entropy of the translation logits against the sample nearest `truth`.
pub fn translation_loss(logits: &[f32], samples: &[[f32; 3]], truth: [f32; 3]) -> Result<LossGrad> {
    if logits.len() != samples.len() {
        return Err(PolicyError::ShapeMismatch {
            name: "translation logits".into(),
            expected: vec![samples.len()],
            got: vec![logits.len()],
        });
    }
    let target = nearest_sample(samples, truth)?;
    let logits: Vec<f64> = logits.iter().map(|&v| f64::from(v)).collect();
    let (lse, p) = log_softmax_parts(&logits, "translation logits")?;
    let mut grad = p;
    grad[target] -= 1.0;
    Ok(LossGrad {
        loss: lse - logits[target],
        grad,
    })
}

/// Binary cross-entropy of the open logit against whether the keyframe's gripper is open.
pub fn open_loss(logit: f32, open: bool) -> Result<LossGrad> {
    let z = f64::from(logit);
    if !z.is_finite() {
        return Err(PolicyError::NonFinite {
            what: "open logit".into(),
        });
    }
    let y = if open { 1.0 } else { 0.0 };
    // BCE(z, y) = softplus(z) − y z, stable for large |z|.
    let softplus = z.max(0.0) + (-z.abs()).exp().ln_1p();
    let sigmoid = 1.0 / (1.0 + (-z).exp());
    Ok(LossGrad {
        loss: softplus - y * z,
        grad: vec![sigmoid - y],
    })
}

/// Soft labels over `grid` for the rotation `truth`: `softmax(−geodesic° / 2.5)`.
pub fn rotation_labels(grid: &[Matrix3<f64>], truth: &Matrix3<f64>) -> Vec<f64> {
    let scores: Vec<f64> = grid
        .iter()
        .map(|g| -geodesic_deg(g, truth) / ROTATION_LABEL_DEG)
        .collect();
    let max = scores.iter().copied().fold(f64::NEG_INFINITY, f64::max);
    let exp: Vec<f64> = scores.iter().map(|s| (s - max).exp()).collect();
    let sum: f64 = exp.iter().sum();
    exp.into_iter().map(|e| e / sum).collect()
}

/// Soft cross-entropy of the rotation logits over `grid` against the labels of `truth`.
pub fn rotation_loss(
    logits: &[f64],
    grid: &[Matrix3<f64>],
    truth: &Matrix3<f64>,
) -> Result<LossGrad> {
    if logits.len() != grid.len() {
        return Err(PolicyError::ShapeMismatch {
            name: "rotation logits".into(),
            expected: vec![grid.len()],
            got: vec![logits.len()],
        });
    }
    let labels = rotation_labels(grid, truth);
    let (lse, p) = log_softmax_parts(logits, "rotation logits")?;
    let loss = labels.iter().zip(logits).map(|(y, z)| y * (lse - z)).sum();
    let grad = p.iter().zip(&labels).map(|(p, y)| p - y).collect();
    Ok(LossGrad { loss, grad })
}

/// Geodesic distance between two rotations (degrees).
pub fn geodesic_deg(a: &Matrix3<f64>, b: &Matrix3<f64>) -> f64 {
    let c = ((a.transpose() * b).trace() - 1.0) / 2.0;
    c.clamp(-1.0, 1.0).acos().to_degrees()
}

/// `log Σ exp(z)` and `softmax(z)`, with the maximum subtracted.
fn log_softmax_parts(z: &[f64], what: &str) -> Result<(f64, Vec<f64>)> {
    if z.is_empty() || z.iter().any(|v| !v.is_finite()) {
        return Err(PolicyError::NonFinite {
            what: format!("{what} (empty or not finite)"),
        });
    }
    let max = z.iter().copied().fold(f64::NEG_INFINITY, f64::max);
    let exp: Vec<f64> = z.iter().map(|v| (v - max).exp()).collect();
    let sum: f64 = exp.iter().sum();
    Ok((max + sum.ln(), exp.into_iter().map(|e| e / sum).collect()))
}

/// The paper's rotation augmentation.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct RotationAugmentation {
    /// Largest rotation about the base x, y, z axes (degrees).
    pub max_deg: [f64; 3],
    /// The point rotated about (base frame, m): the workspace centre.
    pub centre: [f64; 3],
}

impl RotationAugmentation {
    /// The physical-robot setting: ±5°, ±5°, ±45° about the centre of `bounds`.
    pub fn physical(bounds: [[f64; 3]; 2]) -> Self {
        Self {
            max_deg: [5.0, 5.0, 45.0],
            centre: [0, 1, 2].map(|k| 0.5 * (bounds[0][k] + bounds[1][k])),
        }
    }

    /// Draws one motion: rotation uniform within the ranges, about the centre.
    pub fn sample(&self, rng: &mut impl Rng) -> Isometry3<f64> {
        let a = self.max_deg.map(|m| rng.random_range(-m..=m).to_radians());
        let r = UnitQuaternion::from_axis_angle(&Vector3::z_axis(), a[2])
            * UnitQuaternion::from_axis_angle(&Vector3::y_axis(), a[1])
            * UnitQuaternion::from_axis_angle(&Vector3::x_axis(), a[0]);
        let c = Vector3::from(self.centre);
        Isometry3::from_parts(Translation3::from(c - r * c), r)
    }
}

/// Cloud points within this distance (m) of a closed gripper's TCP are the object it holds:
/// the fusion removes the gripper itself, and a held roll's centre hangs 3-3.5 cm below the
/// TCP.
pub const HELD_RADIUS_M: f64 = 0.08;

/// Moves the gripper and the cloud points within [`HELD_RADIUS_M`] of its TCP (what it
/// holds) by `shift` (base frame, m); the rest of the cloud stays. Returns how many points
/// moved.
pub fn shift_held(cloud: &mut PointCloud, gripper: &mut GripperPose, shift: Vector3<f64>) -> usize {
    let tcp = gripper.base_from_tcp.translation();
    let step = shift.cast::<f32>();
    let mut moved = 0;
    for p in &mut cloud.points {
        if (p.coords.cast::<f64>() - tcp).norm() <= HELD_RADIUS_M {
            *p += step;
            moved += 1;
        }
    }
    gripper.base_from_tcp = Transform::from_parts(tcp + shift, gripper.base_from_tcp.rotation());
    moved
}

/// A sideways motion (base x, y) uniform in the disc of radius `radius` (m).
pub fn sideways_in_disc(radius: f64, rng: &mut impl Rng) -> Vector3<f64> {
    loop {
        let (x, y) = (rng.random_range(-1.0..=1.0), rng.random_range(-1.0..=1.0));
        if x * x + y * y <= 1.0 {
            return Vector3::new(x * radius, y * radius, 0.0);
        }
    }
}

/// Moves a training sample rigidly: the cloud's points, the current gripper pose and the
/// keyframe (the colours and the open states are unchanged).
pub fn move_sample(
    motion: &Isometry3<f64>,
    cloud: &mut PointCloud,
    gripper: &mut GripperPose,
    keyframe: &mut Keyframe,
) {
    for p in &mut cloud.points {
        let q = motion * Point3::new(f64::from(p.x), f64::from(p.y), f64::from(p.z));
        *p = Point3::new(q.x as f32, q.y as f32, q.z as f32);
    }
    let m: Transform<Base, Base> = Transform::from_isometry(*motion);
    gripper.base_from_tcp = moved(&m, &gripper.base_from_tcp);
    keyframe.base_from_tcp = moved(&m, &keyframe.base_from_tcp);
}

fn moved(m: &Transform<Base, Base>, t: &Transform<Base, Tcp>) -> Transform<Base, Tcp> {
    Transform::from_isometry(m.isometry() * t.isometry())
}

/// The rotation matrix of a keyframe (what the rotation loss compares against).
pub fn keyframe_rotation(k: &Keyframe) -> Matrix3<f64> {
    k.base_from_tcp.rotation().to_rotation_matrix().into_inner()
}

#[cfg(test)]
mod tests {
    use super::*;
    use nalgebra::Rotation3;
    use rand::SeedableRng;
    use rand_chacha::ChaCha8Rng;

    /// Central finite differences of `f` at `x` with step `h`.
    fn numeric_grad(x: &[f64], h: f64, f: impl Fn(&[f64]) -> f64) -> Vec<f64> {
        (0..x.len())
            .map(|i| {
                let mut a = x.to_vec();
                let mut b = x.to_vec();
                a[i] += h;
                b[i] -= h;
                (f(&a) - f(&b)) / (2.0 * h)
            })
            .collect()
    }

    fn max_diff(a: &[f64], b: &[f64]) -> f64 {
        a.iter()
            .zip(b)
            .map(|(x, y)| (x - y).abs())
            .fold(0.0, f64::max)
    }

    #[test]
    fn translation_loss_targets_the_nearest_sample_and_its_gradient_is_exact() {
        let mut rng = ChaCha8Rng::seed_from_u64(1);
        let samples: Vec<[f32; 3]> = (0..40)
            .map(|_| [rng.random(), rng.random(), rng.random()])
            .collect();
        let truth = samples[17];
        assert_eq!(nearest_sample(&samples, truth).unwrap(), 17);
        let logits: Vec<f32> = (0..40).map(|_| rng.random_range(-3.0..3.0)).collect();
        let lg = translation_loss(&logits, &samples, truth).unwrap();
        let f = |z: &[f64]| {
            let z: Vec<f32> = z.iter().map(|&v| v as f32).collect();
            translation_loss(&z, &samples, truth).unwrap().loss
        };
        let x: Vec<f64> = logits.iter().map(|&v| f64::from(v)).collect();
        // f32 logits: a step of 1e-2 (exact in f32 around these values) keeps rounding out.
        assert!(max_diff(&lg.grad, &numeric_grad(&x, 1e-2, f)) < 1e-4);
        // Raising the target's logit lowers the loss.
        let mut better = logits.clone();
        better[17] += 1.0;
        assert!(translation_loss(&better, &samples, truth).unwrap().loss < lg.loss);
        assert!(translation_loss(&logits[..3], &samples, truth).is_err());
    }

    #[test]
    fn open_loss_is_stable_and_its_gradient_is_sigmoid_minus_label() {
        for (z, open) in [(0.3f32, true), (-2.0, false), (60.0, true), (-80.0, true)] {
            let lg = open_loss(z, open).unwrap();
            assert!(lg.loss.is_finite() && lg.loss >= 0.0, "{z} {lg:?}");
            let y = if open { 1.0 } else { 0.0 };
            let num = numeric_grad(&[f64::from(z)], 1e-2, |v| {
                open_loss(v[0] as f32, open).unwrap().loss
            });
            if z.abs() < 10.0 {
                assert!((lg.grad[0] - num[0]).abs() < 1e-4, "{z}: {lg:?} {num:?}");
            }
            assert!((lg.grad[0] - (1.0 / (1.0 + (-f64::from(z)).exp()) - y)).abs() < 1e-12);
        }
        // A confident wrong answer costs about |z|.
        assert!((open_loss(-80.0, true).unwrap().loss - 80.0).abs() < 1e-9);
        assert!(open_loss(f32::NAN, true).is_err());
    }

    #[test]
    fn rotation_loss_is_smallest_at_the_labels_and_its_gradient_is_exact() {
        let grid: Vec<Matrix3<f64>> = crate::grids::so3_healpix_grid(0)
            .into_iter()
            .map(|g| g.matrix)
            .collect();
        let truth = grid[5] * *Rotation3::from_euler_angles(0.02, -0.01, 0.03).matrix();
        let labels = rotation_labels(&grid, &truth);
        assert!((labels.iter().sum::<f64>() - 1.0).abs() < 1e-12);
        let best = labels
            .iter()
            .enumerate()
            .max_by(|a, b| a.1.total_cmp(b.1))
            .unwrap()
            .0;
        assert_eq!(best, 5);
        let mut rng = ChaCha8Rng::seed_from_u64(2);
        let logits: Vec<f64> = (0..grid.len())
            .map(|_| rng.random_range(-2.0..2.0))
            .collect();
        let lg = rotation_loss(&logits, &grid, &truth).unwrap();
        let num = numeric_grad(&logits, 1e-6, |z| {
            rotation_loss(z, &grid, &truth).unwrap().loss
        });
        assert!(max_diff(&lg.grad, &num) < 1e-6);
        // The minimum is at logits = log(labels) (up to a constant): gradient zero there.
        let at_labels: Vec<f64> = labels.iter().map(|p| p.max(1e-300).ln()).collect();
        let g = rotation_loss(&at_labels, &grid, &truth).unwrap();
        assert!(g.grad.iter().all(|v| v.abs() < 1e-9));
        assert!(g.loss <= lg.loss);
    }

    #[test]
    fn held_shift_moves_the_hand_and_what_it_holds_sideways_only() {
        use cell_types::FrameId;
        let tcp = Vector3::new(0.5, 0.0, 0.3);
        let rotation = UnitQuaternion::from_euler_angles(3.1, 0.2, 0.7);
        let mut gripper = GripperPose {
            base_from_tcp: Transform::from_parts(tcp, rotation),
            open: false,
        };
        // A held object just under the TCP, its edge, and table points far below.
        let points = vec![
            Point3::new(0.5f32, 0.0, 0.27),
            Point3::new(0.5f32, 0.079, 0.3),
            Point3::new(0.5f32, 0.081, 0.3),
            Point3::new(0.5f32, 0.0, 0.0),
        ];
        let mut cloud = PointCloud {
            frame: FrameId::Base,
            points: points.clone(),
            rgb: None,
        };
        let shift = Vector3::new(0.01, -0.02, 0.0);
        assert_eq!(shift_held(&mut cloud, &mut gripper, shift), 2);
        let s = shift.cast::<f32>();
        assert_eq!(
            cloud.points,
            [points[0] + s, points[1] + s, points[2], points[3]]
        );
        assert!((gripper.base_from_tcp.translation() - (tcp + shift)).norm() < 1e-12);
        assert_eq!(gripper.base_from_tcp.rotation(), rotation);
        assert!(!gripper.open);

        let mut rng = ChaCha8Rng::seed_from_u64(5);
        let draws: Vec<Vector3<f64>> = (0..2000)
            .map(|_| sideways_in_disc(0.02, &mut rng))
            .collect();
        assert!(draws.iter().all(|d| d.z == 0.0 && d.norm() <= 0.02));
        // Uniform in the disc: a quarter within half the radius, the mean near 0.
        let inner = draws.iter().filter(|d| d.norm() <= 0.01).count() as f64 / 2000.0;
        assert!((inner - 0.25).abs() < 0.04, "{inner}");
        let mean = draws.iter().sum::<Vector3<f64>>() / 2000.0;
        assert!(mean.norm() < 1e-3, "{mean:?}");
    }

    #[test]
    fn augmentation_stays_in_range_and_moves_the_sample_rigidly() {
        let aug = RotationAugmentation::physical([[0.18, -0.39, -0.10], [0.96, 0.39, 0.53]]);
        let mut rng = ChaCha8Rng::seed_from_u64(3);
        let centre = Point3::from(aug.centre);
        for _ in 0..200 {
            let m = aug.sample(&mut rng);
            // The centre stays put; the rotation is within the ranges.
            assert!(((m * centre) - centre).norm() < 1e-12);
            let (roll, pitch, yaw) = m.rotation.euler_angles();
            assert!(roll.abs().to_degrees() <= 5.0 + 1e-9);
            assert!(pitch.abs().to_degrees() <= 5.0 + 1e-9);
            assert!(yaw.abs().to_degrees() <= 45.0 + 1e-9);
        }
        let m = aug.sample(&mut rng);
        let mut cloud = PointCloud {
            frame: cell_types::FrameId::Base,
            points: vec![Point3::new(0.5, 0.1, 0.0), Point3::new(0.6, -0.2, 0.1)],
            rgb: None,
        };
        let mut gripper = GripperPose {
            base_from_tcp: Transform::from_xyz_rpy([0.5, 0.0, 0.3], [3.1, 0.0, 0.2]),
            open: true,
        };
        let mut keyframe = Keyframe {
            base_from_tcp: Transform::from_xyz_rpy([0.6, -0.2, 0.12], [3.0, 0.1, -0.4]),
            gripper_open: false,
            ignore_collisions: false,
        };
        let before = (cloud.clone(), gripper, keyframe);
        move_sample(&m, &mut cloud, &mut gripper, &mut keyframe);
        // What the policy must learn is unchanged: the keyframe relative to the points and
        // to the gripper.
        let rel = |k: &Keyframe, p: &Point3<f32>| {
            k.base_from_tcp.isometry().inverse()
                * Point3::new(f64::from(p.x), f64::from(p.y), f64::from(p.z))
        };
        for i in 0..2 {
            let a = rel(&before.2, &before.0.points[i]);
            let b = rel(&keyframe, &cloud.points[i]);
            assert!((a - b).norm() < 1e-6);
        }
        let a = before.1.base_from_tcp.isometry().inverse() * before.2.base_from_tcp.isometry();
        let b = gripper.base_from_tcp.isometry().inverse() * keyframe.base_from_tcp.isometry();
        assert!((a.translation.vector - b.translation.vector).norm() < 1e-9);
        assert!(a.rotation.angle_to(&b.rotation) < 1e-9);
        assert!(!keyframe.gripper_open && gripper.open);
        let r = keyframe_rotation(&keyframe);
        assert!(geodesic_deg(&r, &keyframe_rotation(&before.2)) > 0.0);
    }
}
