//! Analytic inverse kinematics of the UR arms: Hawkins, "Analytic Inverse Kinematics for the
//! Universal Robots UR-5/UR-10 Arms" (2013), in the standard-DH form of
//! [`crate::kinematics`]. Up to 8 solutions (shoulder left/right × wrist flip × elbow up/down).
//!
//! Each acos/asin argument is checked: a target out of reach is a typed
//! [`PlanError::Unreachable`], a wrist-singular one (θ5 = 0, θ4 and θ6 not separable) a typed
//! [`PlanError::Singular`]; no NaN ever leaves this module. Every solution is polished with
//! Newton steps on the FK residual so that FK(q) matches the target to ~1e-12, not just to
//! the conditioning of the closed form.

use crate::error::PlanError;
use crate::kinematics::{dh_transform, UrParams};
use cell_types::joints::wrap_to_pi;
use nalgebra::{Isometry3, Matrix6, Vector3, Vector6};
use std::f64::consts::FRAC_PI_2;

/// Below this |sin θ5| the wrist is treated as singular.
const WRIST_SINGULAR: f64 = 1e-9;
/// Tolerance on acos/asin arguments before a branch is called unreachable.
const ARG_TOL: f64 = 1e-10;

fn dh(ur: &UrParams, i: usize, theta: f64) -> Isometry3<f64> {
    let (d, a, alpha) = ur.dh_rows()[i];
    dh_transform(theta, d, a, alpha)
}

fn safe_acos(x: f64) -> Option<f64> {
    if x.abs() > 1.0 + ARG_TOL || !x.is_finite() {
        None
    } else {
        Some(x.clamp(-1.0, 1.0).acos())
    }
}

/// All analytic solutions (angles in (-π, π]) that put the flange at `base_from_flange`.
pub fn ik_flange(
    ur: &UrParams,
    base_from_flange: &Isometry3<f64>,
) -> Result<Vec<[f64; 6]>, PlanError> {
    let t = base_from_flange;
    let p = t.translation.vector;
    let r = t.rotation.to_rotation_matrix();
    let rm = r.matrix();
    if !(p.iter().all(|v| v.is_finite()) && rm.iter().all(|v| v.is_finite())) {
        return Err(PlanError::NotFinite {
            what: "IK target pose",
        });
    }
    // Wrist centre (origin of frame 5): back off d6 along the tool z.
    let z6 = rm.column(2).into_owned();
    let p5 = p - ur.d6 * z6;
    let rxy = (p5.x * p5.x + p5.y * p5.y).sqrt();
    if rxy < ur.d4.abs() + 1e-12 {
        if rxy < 1e-9 {
            return Err(PlanError::Singular {
                kind: "shoulder: wrist centre on the base axis",
            });
        }
        return Err(PlanError::Unreachable {
            reason:
                "wrist centre inside the shoulder offset cylinder (closer to the base axis than d4)",
        });
    }
    let psi = p5.y.atan2(p5.x);
    let phi = (ur.d4 / rxy).clamp(-1.0, 1.0).acos();
    let inv = t.inverse();
    let x60 = inv.rotation * Vector3::x();
    let y60 = inv.rotation * Vector3::y();
    let mut out = Vec::with_capacity(8);
    let mut singular = false;
    let mut reach_fail: Option<&'static str> = None;
    for t1 in [FRAC_PI_2 + psi + phi, FRAC_PI_2 + psi - phi] {
        let (s1, c1) = t1.sin_cos();
        let Some(t5a) = safe_acos((p.x * s1 - p.y * c1 - ur.d4) / ur.d6) else {
            reach_fail =
                Some("wrist 2 cannot turn the flange to this orientation at this position");
            continue;
        };
        for t5 in [t5a, -t5a] {
            let s5 = t5.sin();
            if s5.abs() < WRIST_SINGULAR {
                singular = true;
                continue;
            }
            let t6 = ((-x60.y * s1 + y60.y * c1) / s5).atan2((x60.x * s1 - y60.x * c1) / s5);
            let t14 = dh(ur, 0, t1).inverse() * t * (dh(ur, 4, t5) * dh(ur, 5, t6)).inverse();
            let p13 = t14 * nalgebra::Point3::new(0.0, -ur.d4, 0.0);
            let p13 = p13.coords;
            let n = p13.norm();
            let Some(t3a) =
                safe_acos((n * n - ur.a2 * ur.a2 - ur.a3 * ur.a3) / (2.0 * ur.a2 * ur.a3))
            else {
                reach_fail = Some("target beyond the reach of upper arm + forearm");
                continue;
            };
            if n < 1e-12 {
                singular = true;
                continue;
            }
            for t3 in [t3a, -t3a] {
                let arg = ur.a3 * t3.sin() / n;
                if arg.abs() > 1.0 + ARG_TOL {
                    reach_fail = Some("elbow geometry inconsistent");
                    continue;
                }
                let t2 = -p13.y.atan2(-p13.x) + arg.clamp(-1.0, 1.0).asin();
                let t34 = (dh(ur, 1, t2) * dh(ur, 2, t3)).inverse() * t14;
                let m = t34.rotation.to_rotation_matrix();
                let t4 = m[(1, 0)].atan2(m[(0, 0)]);
                let mut q = [t1, t2, t3, t4, t5, t6];
                polish(ur, t, &mut q);
                for v in q.iter_mut() {
                    *v = wrap_to_pi(*v);
                }
                if q.iter().all(|v| v.is_finite()) {
                    out.push(q);
                }
            }
        }
    }
    if out.is_empty() {
        if singular {
            return Err(PlanError::Singular {
                kind: "wrist: wrist 2 at 0 or π aligns wrist 1 and wrist 3",
            });
        }
        return Err(PlanError::Unreachable {
            reason: reach_fail.unwrap_or("no branch of the closed form applies"),
        });
    }
    Ok(out)
}

/// A few Gauss–Newton steps on the 6-D pose residual (numerical Jacobian of the DH FK): the
/// closed form loses digits near acos(±1); this brings every solution to ~1e-13.
fn polish(ur: &UrParams, target: &Isometry3<f64>, q: &mut [f64; 6]) {
    let residual = |q: &[f64; 6]| -> Vector6<f64> {
        let f = ur.link_frames(q)[6];
        let dp = target.translation.vector - f.translation.vector;
        let dr = (target.rotation * f.rotation.inverse()).scaled_axis();
        Vector6::new(dp.x, dp.y, dp.z, dr.x, dr.y, dr.z)
    };
    for _ in 0..3 {
        let r0 = residual(q);
        if r0.norm() < 1e-12 {
            return;
        }
        let mut jac = Matrix6::zeros();
        let h = 1e-7;
        for k in 0..6 {
            let mut qp = *q;
            qp[k] += h;
            let mut qm = *q;
            qm[k] -= h;
            // residual = target - f, so d(f)/dq = -(d residual / dq)
            let col = (residual(&qm) - residual(&qp)) / (2.0 * h);
            jac.set_column(k, &col);
        }
        let Some(dq) = jac.lu().solve(&r0) else {
            return;
        };
        if !dq.iter().all(|v| v.is_finite()) || dq.norm() > 1e-3 {
            return;
        }
        for k in 0..6 {
            q[k] += dq[k];
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::kinematics::{UR5, UR5E};
    use rand::{Rng, SeedableRng};
    use std::f64::consts::{PI, TAU};

    fn ang_eq(a: f64, b: f64) -> bool {
        let d = (a - b).rem_euclid(TAU);
        d.min(TAU - d) < 1e-7
    }

    fn check_many(ur: &UrParams, n: usize, seed: u64) {
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(seed);
        let mut worst = (0.0f64, 0.0f64);
        for _ in 0..n {
            let q: [f64; 6] = std::array::from_fn(|_| rng.random_range(-PI..PI));
            let target = ur.link_frames(&q)[6];
            let sols = ik_flange(ur, &target).unwrap_or_else(|e| panic!("q = {q:?}: {e}"));
            assert!(sols.len() <= 8);
            for s in &sols {
                let f = ur.link_frames(s)[6];
                let dt = (f.translation.vector - target.translation.vector).norm();
                let dr = f.rotation.angle_to(&target.rotation);
                worst = (worst.0.max(dt), worst.1.max(dr));
                assert!(
                    dt < 1e-9 && dr < 1e-9,
                    "q = {q:?} sol {s:?}: {dt} m {dr} rad"
                );
            }
            assert!(
                sols.iter()
                    .any(|s| s.iter().zip(&q).all(|(a, b)| ang_eq(*a, *b))),
                "q = {q:?} not among {sols:?}"
            );
        }
        eprintln!("worst IK residual: {} m, {} rad", worst.0, worst.1);
    }

    #[test]
    fn ten_thousand_random_configurations_round_trip_ur5() {
        check_many(&UR5, 10_000, 7);
    }

    #[test]
    fn random_configurations_round_trip_ur5e() {
        check_many(&UR5E, 2_000, 11);
    }

    #[test]
    fn unreachable_target_is_typed_error() {
        let far = Isometry3::translation(3.0, 0.0, 0.5);
        assert!(matches!(
            ik_flange(&UR5, &far),
            Err(PlanError::Unreachable { .. })
        ));
        let nan = Isometry3::translation(f64::NAN, 0.0, 0.5);
        assert!(matches!(
            ik_flange(&UR5, &nan),
            Err(PlanError::NotFinite { .. })
        ));
    }

    #[test]
    fn wrist_singular_target_is_typed_error_not_nan() {
        // θ5 = 0 for both shoulder branches: the flange z points along the shoulder axis
        // direction; take FK at θ5 = 0 and check every solution is finite or an error is typed.
        let q = [0.3, -1.0, 1.2, -0.5, 0.0, 0.7];
        let target = UR5.link_frames(&q)[6];
        match ik_flange(&UR5, &target) {
            Ok(sols) => {
                for s in sols {
                    assert!(s.iter().all(|v| v.is_finite()));
                    let f = UR5.link_frames(&s)[6];
                    assert!((f.translation.vector - target.translation.vector).norm() < 1e-9);
                }
            }
            Err(e) => assert!(matches!(e, PlanError::Singular { .. }), "{e}"),
        }
    }

    #[test]
    fn base_axis_target_is_typed_error() {
        // Wrist centre on the base z axis: shoulder singularity.
        let target = Isometry3::from_parts(
            nalgebra::Translation3::new(0.0, 0.0, 0.6 + UR5.d6),
            nalgebra::UnitQuaternion::identity(),
        );
        let e = ik_flange(&UR5, &target).unwrap_err();
        assert!(
            matches!(
                e,
                PlanError::Singular { .. } | PlanError::Unreachable { .. }
            ),
            "{e}"
        );
    }
}
