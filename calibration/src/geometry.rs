//! Geometry for the solver: pose perturbations, projection with its Jacobian, planar PnP
//! (homography DLT, then Levenberg-Marquardt), and the closed-form robot-world hand-eye
//! initialisation `A_i X = Z B_i` (linear Kronecker form of Shah 2013 / Li 2010).
//!
//! Pose perturbations are 6-vectors `(omega, v)`: rotation vector then translation, applied
//! as `pose * exp(d)` with `exp(d) = (R(omega), v)` ("right" perturbation, in the pose's own
//! frame).

use levenberg_marquardt::{LeastSquaresProblem, LevenbergMarquardt};
use nalgebra::{
    storage::Owned, DMatrix, DVector, Dyn, Isometry3, Matrix2x3, Matrix3, Matrix3x6, Point2,
    Point3, Rotation3, SymmetricEigen, Translation3, UnitQuaternion, Vector3,
};

use crate::camera::{Distortion, Intrinsics};

/// `exp(d)` of a 6-vector `(omega, v)`: rotation `R(omega)`, translation `v`.
pub fn exp6(d: &[f64]) -> Isometry3<f64> {
    let (w, v) = match d {
        [a, b, c, x, y, z, ..] => (Vector3::new(*a, *b, *c), Vector3::new(*x, *y, *z)),
        _ => (Vector3::zeros(), Vector3::zeros()),
    };
    Isometry3::from_parts(Translation3::from(v), UnitQuaternion::from_scaled_axis(w))
}

/// The skew-symmetric matrix of `v` (`skew(v) * p = v x p`).
pub fn skew(v: &Vector3<f64>) -> Matrix3<f64> {
    Matrix3::new(0.0, -v.z, v.y, v.z, 0.0, -v.x, -v.y, v.x, 0.0)
}

/// `d(exp(d) p) / d d` at `d = 0`: `[-skew(p) | I]`.
pub fn point_jacobian(p: &Vector3<f64>) -> Matrix3x6<f64> {
    let mut j = Matrix3x6::zeros();
    j.fixed_view_mut::<3, 3>(0, 0).copy_from(&(-skew(p)));
    j.fixed_view_mut::<3, 3>(0, 3)
        .copy_from(&Matrix3::identity());
    j
}

/// Projects `c` (camera optical frame) and returns the pixel and `d pixel / d c`. Points
/// at or behind the camera are clamped to 1 mm depth so that a solver step that pushes
/// them there sees a huge, smooth residual instead of failing.
pub fn project_with_jacobian(k: &Intrinsics, c: &Vector3<f64>) -> (Point2<f64>, Matrix2x3<f64>) {
    let c = Vector3::new(c.x, c.y, c.z.max(1e-3));
    let pinhole = |c: &Vector3<f64>| {
        let (x, y) = (c.x / c.z, c.y / c.z);
        match k.project(&Point3::from(*c)) {
            Ok(p) => p,
            Err(_) => Point2::new(x * k.fx + k.ppx, y * k.fy + k.ppy),
        }
    };
    match k.distortion {
        Distortion::None => {
            let iz = 1.0 / c.z;
            let (x, y) = (c.x * iz, c.y * iz);
            let px = Point2::new(k.fx * x + k.ppx, k.fy * y + k.ppy);
            let j = Matrix2x3::new(
                k.fx * iz,
                0.0,
                -k.fx * x * iz,
                0.0,
                k.fy * iz,
                -k.fy * y * iz,
            );
            (px, j)
        }
        _ => {
            // Central differences through the distortion model (relative step 1e-6).
            let px = pinhole(&c);
            let mut j = Matrix2x3::zeros();
            let h = 1e-6 * c.z;
            for a in 0..3 {
                let mut cp = c;
                let mut cm = c;
                cp[a] += h;
                cm[a] -= h;
                let d = (pinhole(&cp) - pinhole(&cm)) / (2.0 * h);
                j[(0, a)] = d.x;
                j[(1, a)] = d.y;
            }
            (px, j)
        }
    }
}

/// Projects a 3x3 matrix onto SO(3) (nearest rotation in Frobenius norm).
pub fn nearest_rotation(m: &Matrix3<f64>) -> Option<Rotation3<f64>> {
    let svd = m.svd(true, true);
    let (u, vt) = (svd.u?, svd.v_t?);
    let mut d = Matrix3::identity();
    if (u * vt).determinant() < 0.0 {
        d[(2, 2)] = -1.0;
    }
    Some(Rotation3::from_matrix_unchecked(u * d * vt))
}

/// The eigenvector of the smallest eigenvalue of a symmetric matrix.
fn smallest_eigenvector(m: DMatrix<f64>) -> DVector<f64> {
    let eig = SymmetricEigen::new(m);
    let mut best = 0;
    for i in 1..eig.eigenvalues.len() {
        if eig.eigenvalues[i] < eig.eigenvalues[best] {
            best = i;
        }
    }
    eig.eigenvectors.column(best).into_owned()
}

/// Why a planar PnP failed.
pub type PnpError = String;

/// The pose `camera_from_board` of a planar board (points with z = 0) from its corner
/// pixels: DLT homography on undistorted normalised coordinates (Hartley-normalised),
/// decomposition (Zhang), then Levenberg-Marquardt on the pixel reprojection error.
/// Returns the pose and the RMS reprojection error (px, per coordinate).
pub fn planar_pnp(
    k: &Intrinsics,
    board: &[Point3<f64>],
    pixels: &[Point2<f64>],
) -> Result<(Isometry3<f64>, f64), PnpError> {
    if board.len() != pixels.len() || board.len() < 4 {
        return Err(format!("{} corners, at least 4 are needed", board.len()));
    }
    let mut norm = Vec::with_capacity(pixels.len());
    for p in pixels {
        let r = k.pixel_ray(*p).map_err(|e| e.to_string())?;
        norm.push(Point2::new(r.x, r.y));
    }
    let h = homography(board, &norm).ok_or("corners are collinear or degenerate")?;
    let (h1, h2, h3) = (h.column(0), h.column(1), h.column(2));
    let scale = 2.0 / (h1.norm() + h2.norm());
    let mut lambda = scale;
    if (h3 * lambda).z < 0.0 {
        lambda = -lambda;
    }
    let r1 = h1 * lambda;
    let r2 = h2 * lambda;
    let r3 = r1.cross(&r2);
    let r = nearest_rotation(&Matrix3::from_columns(&[r1, r2, r3]))
        .ok_or("homography decomposition failed")?;
    let t = h3 * lambda;
    let init = Isometry3::from_parts(
        Translation3::from(t),
        UnitQuaternion::from_rotation_matrix(&r),
    );
    let problem = PnpProblem {
        k,
        board,
        pixels,
        pose0: init,
        delta: DVector::zeros(6),
    };
    let mut pose = init;
    // Re-linearise twice so the final Jacobian is taken at the optimum.
    let mut problem = problem;
    for _ in 0..3 {
        let (p, report) = LevenbergMarquardt::new()
            .with_patience(200)
            .minimize(problem);
        if !report.termination.was_successful() && report.objective_function.is_nan() {
            return Err(format!("refinement failed: {:?}", report.termination));
        }
        pose = p.pose();
        problem = PnpProblem {
            pose0: pose,
            delta: DVector::zeros(6),
            ..p
        };
    }
    let mut ss = 0.0;
    for (b, px) in board.iter().zip(pixels) {
        let (pred, _) = project_with_jacobian(k, &(pose * b).coords);
        ss += (pred - px).norm_squared();
    }
    let rms = (ss / (2.0 * board.len() as f64)).sqrt();
    if !rms.is_finite() || (pose * Point3::origin()).z <= 0.0 {
        return Err("the board came out behind the camera".into());
    }
    Ok((pose, rms))
}

/// DLT homography mapping `src` (x, y of points with z = 0) to `dst`, Hartley-normalised.
fn homography(src: &[Point3<f64>], dst: &[Point2<f64>]) -> Option<Matrix3<f64>> {
    let normaliser = |pts: &[Point2<f64>]| {
        let n = pts.len() as f64;
        let c = pts
            .iter()
            .fold(nalgebra::Vector2::zeros(), |a, p| a + p.coords)
            / n;
        let d = pts.iter().map(|p| (p.coords - c).norm()).sum::<f64>() / n;
        let s = if d > 0.0 {
            std::f64::consts::SQRT_2 / d
        } else {
            1.0
        };
        Matrix3::new(s, 0.0, -s * c.x, 0.0, s, -s * c.y, 0.0, 0.0, 1.0)
    };
    let src2: Vec<Point2<f64>> = src.iter().map(|p| Point2::new(p.x, p.y)).collect();
    let ts = normaliser(&src2);
    let td = normaliser(dst);
    let mut ata = DMatrix::<f64>::zeros(9, 9);
    for (s, d) in src2.iter().zip(dst) {
        let s = ts * Vector3::new(s.x, s.y, 1.0);
        let d = td * Vector3::new(d.x, d.y, 1.0);
        let rows = [
            [-s.x, -s.y, -1.0, 0.0, 0.0, 0.0, d.x * s.x, d.x * s.y, d.x],
            [0.0, 0.0, 0.0, -s.x, -s.y, -1.0, d.y * s.x, d.y * s.y, d.y],
        ];
        for r in rows {
            for i in 0..9 {
                for j in 0..9 {
                    ata[(i, j)] += r[i] * r[j];
                }
            }
        }
    }
    let h = smallest_eigenvector(ata);
    let hn = Matrix3::new(h[0], h[1], h[2], h[3], h[4], h[5], h[6], h[7], h[8]);
    let h = td.try_inverse()? * hn * ts;
    // Collinear points leave a rank-deficient homography.
    let svd = h.svd(false, false);
    let sv = svd.singular_values;
    let (max, min) = (sv.max(), sv.min());
    if min.is_nan() || min <= 1e-9 * max {
        return None;
    }
    Some(h)
}

/// Levenberg-Marquardt problem of one planar PnP (6 parameters, left perturbation).
struct PnpProblem<'a> {
    k: &'a Intrinsics,
    board: &'a [Point3<f64>],
    pixels: &'a [Point2<f64>],
    pose0: Isometry3<f64>,
    delta: DVector<f64>,
}

impl PnpProblem<'_> {
    fn pose(&self) -> Isometry3<f64> {
        exp6(self.delta.as_slice()) * self.pose0
    }
}

impl LeastSquaresProblem<f64, Dyn, Dyn> for PnpProblem<'_> {
    type ResidualStorage = Owned<f64, Dyn>;
    type JacobianStorage = Owned<f64, Dyn, Dyn>;
    type ParameterStorage = Owned<f64, Dyn>;

    fn set_params(&mut self, x: &DVector<f64>) {
        self.delta.copy_from(x);
    }

    fn params(&self) -> DVector<f64> {
        self.delta.clone()
    }

    fn residuals(&self) -> Option<DVector<f64>> {
        let pose = self.pose();
        let mut r = DVector::zeros(2 * self.board.len());
        for (i, (b, px)) in self.board.iter().zip(self.pixels).enumerate() {
            let (pred, _) = project_with_jacobian(self.k, &(pose * b).coords);
            r[2 * i] = pred.x - px.x;
            r[2 * i + 1] = pred.y - px.y;
        }
        Some(r)
    }

    fn jacobian(&self) -> Option<DMatrix<f64>> {
        let pose = self.pose();
        let mut j = DMatrix::zeros(2 * self.board.len(), 6);
        for (i, b) in self.board.iter().enumerate() {
            let c = (pose * b).coords;
            let (_, jp) = project_with_jacobian(self.k, &c);
            let jc = jp * point_jacobian(&c);
            j.fixed_view_mut::<2, 6>(2 * i, 0).copy_from(&jc);
        }
        Some(j)
    }
}

/// Closed-form solution of `A_i X = Z B_i` for rigid `X`, `Z` (robot-world hand-eye; here
/// `A_i = base_from_flange`, `X = flange_from_board`, `Z = base_from_camera`,
/// `B_i = camera_from_board`): rotations from the null vector of the stacked Kronecker
/// system `(I (x) R_A) vec(R_X) - (R_B^T (x) I) vec(R_Z) = 0`, projected onto SO(3); then
/// translations by linear least squares `R_A t_X - t_Z = R_Z t_B - t_A`.
/// Returns `(X, Z)`, or `None` for fewer than 3 pairs or a degenerate set.
pub fn robot_world_hand_eye(
    pairs: &[(Isometry3<f64>, Isometry3<f64>)],
) -> Option<(Isometry3<f64>, Isometry3<f64>)> {
    if pairs.len() < 3 {
        return None;
    }
    let mut mtm = DMatrix::<f64>::zeros(18, 18);
    for (a, b) in pairs {
        let ra = a.rotation.to_rotation_matrix().into_inner();
        let rb = b.rotation.to_rotation_matrix().into_inner();
        let mut m = DMatrix::<f64>::zeros(9, 18);
        // (I (x) R_A): block diagonal with R_A.
        for blk in 0..3 {
            for i in 0..3 {
                for j in 0..3 {
                    m[(3 * blk + i, 3 * blk + j)] = ra[(i, j)];
                }
            }
        }
        // -(R_B^T (x) I): block (p, q) = R_B^T[p, q] * I = R_B[q, p] * I.
        for p in 0..3 {
            for q in 0..3 {
                for i in 0..3 {
                    m[(3 * p + i, 9 + 3 * q + i)] -= rb[(q, p)];
                }
            }
        }
        mtm += m.transpose() * &m;
    }
    let x = smallest_eigenvector(mtm);
    let rx = Matrix3::from_column_slice(&x.as_slice()[0..9]);
    let rz = Matrix3::from_column_slice(&x.as_slice()[9..18]);
    let sign = if rx.determinant() < 0.0 { -1.0 } else { 1.0 };
    let rx = nearest_rotation(&(rx * sign))?;
    let rz = nearest_rotation(&(rz * sign))?;
    // Translations: [R_A, -I] [t_X; t_Z] = R_Z t_B - t_A.
    let mut ata = nalgebra::Matrix6::<f64>::zeros();
    let mut atb = nalgebra::Vector6::<f64>::zeros();
    for (a, b) in pairs {
        let ra = a.rotation.to_rotation_matrix().into_inner();
        let mut m = nalgebra::Matrix3x6::<f64>::zeros();
        m.fixed_view_mut::<3, 3>(0, 0).copy_from(&ra);
        m.fixed_view_mut::<3, 3>(0, 3)
            .copy_from(&(-Matrix3::identity()));
        let rhs = rz * b.translation.vector - a.translation.vector;
        ata += m.transpose() * m;
        atb += m.transpose() * rhs;
    }
    let t = ata.try_inverse()? * atb;
    let x = Isometry3::from_parts(
        Translation3::new(t[0], t[1], t[2]),
        UnitQuaternion::from_rotation_matrix(&rx),
    );
    let z = Isometry3::from_parts(
        Translation3::new(t[3], t[4], t[5]),
        UnitQuaternion::from_rotation_matrix(&rz),
    );
    Some((x, z))
}

/// The largest relative rotation (rad) among `rotations`, and the largest angle (rad,
/// up to 90°) between the axes of two relative rotations of at least `min_angle` each:
/// hand-eye needs both to be well above zero.
pub fn rotation_diversity(rotations: &[UnitQuaternion<f64>], min_angle: f64) -> (f64, f64) {
    let mut axes: Vec<Vector3<f64>> = Vec::new();
    let mut max_angle: f64 = 0.0;
    for i in 0..rotations.len() {
        for j in i + 1..rotations.len() {
            let rel = rotations[i].inverse() * rotations[j];
            let angle = rel.angle();
            max_angle = max_angle.max(angle);
            if angle >= min_angle && axes.len() < 300 {
                if let Some(axis) = rel.axis() {
                    axes.push(axis.into_inner());
                }
            }
        }
    }
    let mut max_axis_angle: f64 = 0.0;
    for i in 0..axes.len() {
        for j in i + 1..axes.len() {
            let s = axes[i].cross(&axes[j]).norm().clamp(0.0, 1.0);
            max_axis_angle = max_axis_angle.max(s.asin());
        }
    }
    (max_angle, max_axis_angle)
}

/// Covariance helper: the 6x6 block `(omega, v)` of a parameter covariance at `offset`.
pub fn block6(cov: &DMatrix<f64>, offset: usize) -> nalgebra::Matrix6<f64> {
    cov.fixed_view::<6, 6>(offset, offset).into_owned()
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::camera::DepthMode;
    use crate::BoardConfig;

    fn iso(xyz: [f64; 3], rpy: [f64; 3]) -> Isometry3<f64> {
        Isometry3::from_parts(
            Translation3::new(xyz[0], xyz[1], xyz[2]),
            UnitQuaternion::from_euler_angles(rpy[0], rpy[1], rpy[2]),
        )
    }

    #[test]
    fn pnp_recovers_an_exact_pose() {
        let k = Intrinsics::d455_depth(DepthMode::Wvga848x480);
        let board = BoardConfig::default().corners();
        let truth = iso([-0.1, -0.05, 0.9], [2.8, 0.3, 0.4]);
        let pixels: Vec<_> = board
            .iter()
            .map(|b| k.project(&(truth * b)).unwrap())
            .collect();
        let (pose, rms) = planar_pnp(&k, &board, &pixels).unwrap();
        let dt = (pose.translation.vector - truth.translation.vector).norm();
        let dr = pose.rotation.angle_to(&truth.rotation);
        assert!(dt < 1e-9 && dr < 1e-9 && rms < 1e-9, "{dt} {dr} {rms}");
        // Distorted colour model too.
        let kc = Intrinsics::d455_colour_640x480();
        let truth = iso([-0.1, -0.05, 0.7], [2.9, -0.2, 0.1]);
        let pixels: Vec<_> = board
            .iter()
            .map(|b| kc.project(&(truth * b)).unwrap())
            .collect();
        let (pose, _) = planar_pnp(&kc, &board, &pixels).unwrap();
        assert!((pose.translation.vector - truth.translation.vector).norm() < 1e-7);
    }

    #[test]
    fn pnp_rejects_collinear_corners() {
        let k = Intrinsics::d455_depth(DepthMode::Wvga848x480);
        let board: Vec<_> = (0..6)
            .map(|i| Point3::new(f64::from(i) * 0.03, 0.0, 0.0))
            .collect();
        let truth = iso([0.0, 0.0, 1.0], [3.0, 0.1, 0.0]);
        let pixels: Vec<_> = board
            .iter()
            .map(|b| k.project(&(truth * b)).unwrap())
            .collect();
        assert!(planar_pnp(&k, &board, &pixels).is_err());
    }

    #[test]
    fn closed_form_hand_eye_is_exact_on_exact_data() {
        let x = iso([0.01, -0.02, 0.08], [0.05, -0.03, 0.4]);
        let z = iso([1.3, 0.1, 0.6], [-2.0, 0.1, 1.5]);
        let pairs: Vec<_> = (0..8)
            .map(|i| {
                let f = f64::from(i);
                let a = iso(
                    [0.5 + 0.02 * f, -0.1 + 0.03 * f, 0.3],
                    [0.3 * f.sin(), 0.4 * (1.3 * f).cos(), 0.7 * f],
                );
                // Z B = A X  =>  B = Z^-1 A X
                let b = z.inverse() * a * x;
                (a, b)
            })
            .collect();
        let (xe, ze) = robot_world_hand_eye(&pairs).unwrap();
        assert!((xe.translation.vector - x.translation.vector).norm() < 1e-9);
        assert!(xe.rotation.angle_to(&x.rotation) < 1e-9);
        assert!((ze.translation.vector - z.translation.vector).norm() < 1e-9);
        assert!(ze.rotation.angle_to(&z.rotation) < 1e-9);
    }

    #[test]
    fn diversity_sees_a_single_axis() {
        let one_axis: Vec<_> = (0..10)
            .map(|i| UnitQuaternion::from_euler_angles(0.0, 0.0, 0.2 * f64::from(i)))
            .collect();
        let (max, axes) = rotation_diversity(&one_axis, 0.1);
        assert!(max > 1.5 && axes < 1e-6, "{max} {axes}");
        let two: Vec<_> = (0..10)
            .map(|i| {
                UnitQuaternion::from_euler_angles(0.3 * f64::from(i % 2), 0.0, 0.2 * f64::from(i))
            })
            .collect();
        assert!(rotation_diversity(&two, 0.1).1 > 0.3);
    }

    #[test]
    fn projection_jacobian_matches_finite_differences() {
        for k in [
            Intrinsics::d455_depth(DepthMode::Wvga848x480),
            Intrinsics::d455_colour_640x480(),
        ] {
            let c = Vector3::new(0.2, -0.1, 0.9);
            let (_, j) = project_with_jacobian(&k, &c);
            for a in 0..3 {
                let mut cp = c;
                cp[a] += 1e-7;
                let d = (k.project(&Point3::from(cp)).unwrap()
                    - k.project(&Point3::from(c)).unwrap())
                    / 1e-7;
                assert!((d.x - j[(0, a)]).abs() < 1e-3 * (1.0 + d.x.abs()));
                assert!((d.y - j[(1, a)]).abs() < 1e-3 * (1.0 + d.y.abs()));
            }
        }
    }
}
