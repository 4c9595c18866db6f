//! Real spherical harmonics, e3nn rotation angles and Wigner-D matrices.
//!
//! Spec: `equact.md`, section "Conventions (e3nn, which the reference uses)", and the
//! fixtures README, "Coefficient axis" and "Rotations and angles". The basis is e3nn's real
//! spherical harmonics with `component` normalisation (sum over m of Y_lm^2 = 2l+1) and the
//! **y axis as the pole**: for l = 1 the components are sqrt(3)·(x, y, z). A coefficient
//! vector up to degree L has (L+1)² entries, entry `l*l + m + l` for m = -l..=l.
//!
//! Everything is computed in `f64`. The Wigner matrices are computed exactly (to f64
//! rounding) as the unique matrices with Y(R v) = D(R) Y(v), obtained by a least-squares fit
//! on fixed sample directions, instead of from e3nn's tabulated J matrices; the tabulated
//! values are only accurate to about 6e-6, so comparisons against the reference's Wigner
//! matrices use a 5e-5 tolerance (fixtures README, "Parity tolerances").

use nalgebra::{DMatrix, Matrix3, Vector3};

use crate::error::{PolicyError, Result};

/// The largest degree the tables here are built for (the rotation head uses l = 4).
pub const MAX_DEGREE: usize = 8;

/// Number of coefficients of all degrees 0..=lmax: (lmax+1)².
pub const fn num_coefficients(lmax: usize) -> usize {
    (lmax + 1) * (lmax + 1)
}

/// Index of coefficient (l, m) in the l-major layout, `l*l + m + l`.
pub const fn coefficient_index(l: usize, m: i64) -> usize {
    // m is in -l..=l, so l + m >= 0.
    (l as i64 * l as i64 + m + l as i64) as usize
}

/// Writes Y_lm(u) for l = 0..=lmax of a **unit** vector `u` into `out[..(lmax+1)²]`.
///
/// The caller guarantees `u` is unit length (use [`spherical_harmonics`] for arbitrary
/// vectors); this variant exists so inner loops allocate nothing.
pub fn spherical_harmonics_unit_into(lmax: usize, u: [f64; 3], out: &mut [f64]) {
    let [x, y, z] = u;
    // With y as the pole, z = sin(b) cos(a) and x = sin(b) sin(a), so
    // (z + i x)^k = sin^k(b) (cos(k a) + i sin(k a)): the azimuthal parts are polynomials,
    // which keeps the poles free of division by sin(b).
    let mut cos_k = [0.0f64; MAX_DEGREE + 1];
    let mut sin_k = [0.0f64; MAX_DEGREE + 1];
    cos_k[0] = 1.0;
    for k in 1..=lmax.min(MAX_DEGREE) {
        cos_k[k] = cos_k[k - 1] * z - sin_k[k - 1] * x;
        sin_k[k] = sin_k[k - 1] * z + cos_k[k - 1] * x;
    }
    let consts = sh_constants();
    // q[l] = P_l^k(y) / sin^k(b) for the current order k (no Condon-Shortley phase, as e3nn).
    for k in 0..=lmax.min(MAX_DEGREE) {
        let mut q_prev = 0.0f64;
        let mut q = consts.start[k];
        for l in k..=lmax {
            if l > k {
                let q_next = if l == k + 1 {
                    (2 * k + 1) as f64 * y * q
                } else {
                    ((2 * l - 1) as f64 * y * q - (l + k - 1) as f64 * q_prev) / (l - k) as f64
                };
                q_prev = q;
                q = q_next;
            }
            let norm = consts.norm[l][k];
            if k == 0 {
                out[coefficient_index(l, 0)] = norm * q;
            } else {
                let s2 = std::f64::consts::SQRT_2;
                out[coefficient_index(l, k as i64)] = norm * q * s2 * cos_k[k];
                out[coefficient_index(l, -(k as i64))] = norm * q * s2 * sin_k[k];
            }
        }
    }
}

/// The harmonics' per-(l, k) constants, computed once: every edge frame evaluates the
/// harmonics at a dozen directions, and the factorials and square roots were a third of it.
struct ShConstants {
    /// (2k − 1)!!, the recurrence's start for order k.
    start: [f64; MAX_DEGREE + 1],
    /// √((2l + 1) (l − k)! / (l + k)!) for k <= l.
    norm: [[f64; MAX_DEGREE + 1]; MAX_DEGREE + 1],
}

fn sh_constants() -> &'static ShConstants {
    static CONSTS: std::sync::OnceLock<ShConstants> = std::sync::OnceLock::new();
    CONSTS.get_or_init(|| {
        let mut c = ShConstants {
            start: [0.0; MAX_DEGREE + 1],
            norm: [[0.0; MAX_DEGREE + 1]; MAX_DEGREE + 1],
        };
        for k in 0..=MAX_DEGREE {
            c.start[k] = double_factorial(2 * k as i64 - 1);
            for l in k..=MAX_DEGREE {
                c.norm[l][k] = ((2 * l + 1) as f64 * factorial_ratio(l - k, l + k)).sqrt();
            }
        }
        c
    })
}

/// Real spherical harmonics Y_lm(v/|v|) for l = 0..=lmax (component normalisation).
pub fn spherical_harmonics(lmax: usize, v: [f64; 3]) -> Result<Vec<f64>> {
    if lmax > MAX_DEGREE {
        return Err(PolicyError::UnsupportedDegree {
            lmax,
            mmax: lmax,
            max_supported: MAX_DEGREE,
        });
    }
    let u = unit(v)?;
    let mut out = vec![0.0; num_coefficients(lmax)];
    spherical_harmonics_unit_into(lmax, u, &mut out);
    Ok(out)
}

/// `v / |v|`, or an error for zero or non-finite vectors.
pub fn unit(v: [f64; 3]) -> Result<[f64; 3]> {
    let n = (v[0] * v[0] + v[1] * v[1] + v[2] * v[2]).sqrt();
    if !n.is_finite() || n <= 0.0 {
        return Err(PolicyError::NoDirection { value: v });
    }
    Ok([v[0] / n, v[1] / n, v[2] / n])
}

fn double_factorial(n: i64) -> f64 {
    let mut r = 1.0;
    let mut i = n;
    while i > 1 {
        r *= i as f64;
        i -= 2;
    }
    r
}

/// a! / b! for a <= b.
fn factorial_ratio(a: usize, b: usize) -> f64 {
    let mut r = 1.0;
    for i in (a + 1)..=b {
        r /= i as f64;
    }
    r
}

/// e3nn `xyz_to_angles`: (alpha, beta) = (atan2(x, z), acos(y)) of the direction of `v`.
pub fn xyz_to_angles(v: [f64; 3]) -> Result<(f64, f64)> {
    let [x, y, z] = unit(v)?;
    Ok((x.atan2(z), y.clamp(-1.0, 1.0).acos()))
}

/// e3nn `angles_to_xyz`: the unit vector with angles (alpha, beta), (sin b sin a, cos b, sin b cos a).
pub fn angles_to_xyz(alpha: f64, beta: f64) -> [f64; 3] {
    [
        beta.sin() * alpha.sin(),
        beta.cos(),
        beta.sin() * alpha.cos(),
    ]
}

/// Rotation by `angle` about the y axis (e3nn `matrix_y`).
pub fn matrix_y(angle: f64) -> Matrix3<f64> {
    let (s, c) = angle.sin_cos();
    Matrix3::new(c, 0.0, s, 0.0, 1.0, 0.0, -s, 0.0, c)
}

/// Rotation by `angle` about the x axis (e3nn `matrix_x`).
pub fn matrix_x(angle: f64) -> Matrix3<f64> {
    let (s, c) = angle.sin_cos();
    Matrix3::new(1.0, 0.0, 0.0, 0.0, c, -s, 0.0, s, c)
}

/// e3nn `angles_to_matrix`: R = Ry(alpha) Rx(beta) Ry(gamma).
pub fn angles_to_matrix(alpha: f64, beta: f64, gamma: f64) -> Matrix3<f64> {
    matrix_y(alpha) * matrix_x(beta) * matrix_y(gamma)
}

/// The reference's angles of a rotation matrix: alpha, beta from its second column, then
/// gamma = atan2(M02, M00) with M = (Ry(alpha) Rx(beta))ᵀ R.
pub fn matrix_to_angles(r: &Matrix3<f64>) -> Result<(f64, f64, f64)> {
    check_rotation(r)?;
    let col = r.column(1);
    let (alpha, beta) = xyz_to_angles([col[0], col[1], col[2]])?;
    let m = angles_to_matrix(alpha, beta, 0.0).transpose() * r;
    Ok((alpha, beta, m[(0, 2)].atan2(m[(0, 0)])))
}

/// Checks that `r` is a finite proper rotation to 1e-4 (float32 inputs pass).
pub fn check_rotation(r: &Matrix3<f64>) -> Result<()> {
    const TOL: f64 = 1e-4;
    let ortho = (r.transpose() * r - Matrix3::identity()).abs().max();
    let det = (r.determinant() - 1.0).abs();
    let error = ortho.max(det);
    if !error.is_finite() || error > TOL {
        return Err(PolicyError::NotARotation {
            error: if error.is_finite() {
                error
            } else {
                f64::INFINITY
            },
            tolerance: TOL,
        });
    }
    Ok(())
}

/// Computes Wigner-D matrices D^l(R) in the real SH basis, with Y(R v) = D(R) Y(v).
///
/// For each degree it keeps a fixed set of well-spread sample directions v_k and the
/// pseudo-inverse of their SH matrix A; then D^l(R) = [Y^l(R v_k)] A⁺. This is exact (to f64
/// rounding) because Y^l(R v) is linear in Y^l(v), and costs O(l³) per degree.
#[derive(Debug, Clone)]
pub struct WignerCalculator {
    lmax: usize,
    /// Per degree: sample directions and the pseudo-inverse [n_samples, 2l+1].
    per_degree: Vec<(Vec<[f64; 3]>, DMatrix<f64>)>,
    /// One sample set for all degrees (that of degree lmax) and, per degree, the
    /// pseudo-inverse of its SH matrix on those samples, row-major [n_samples, 2l+1]: the
    /// whole block-diagonal D from one SH evaluation per sample (`wigner_all_into`; empty
    /// for degrees 0 and 1, which it writes directly).
    shared: (Vec<[f64; 3]>, Vec<Vec<f64>>),
}

impl WignerCalculator {
    /// Builds the tables for degrees 0..=lmax.
    pub fn new(lmax: usize) -> Result<Self> {
        if lmax > MAX_DEGREE {
            return Err(PolicyError::UnsupportedDegree {
                lmax,
                mmax: lmax,
                max_supported: MAX_DEGREE,
            });
        }
        let mut per_degree = Vec::with_capacity(lmax + 1);
        let mut buf = vec![0.0; num_coefficients(lmax)];
        for l in 0..=lmax {
            let d = 2 * l + 1;
            // Twice as many Fibonacci-sphere directions as unknowns: well conditioned.
            let n = 2 * d + 1;
            let pts = fibonacci_sphere(n);
            let mut a = DMatrix::<f64>::zeros(d, n);
            for (k, p) in pts.iter().enumerate() {
                spherical_harmonics_unit_into(l, *p, &mut buf);
                for i in 0..d {
                    a[(i, k)] = buf[l * l + i];
                }
            }
            let gram = &a * a.transpose();
            let inv = gram.try_inverse().ok_or(PolicyError::UnsupportedDegree {
                lmax,
                mmax: lmax,
                max_supported: l.saturating_sub(1),
            })?;
            per_degree.push((pts, a.transpose() * inv));
        }
        let shared_pts = per_degree
            .last()
            .map(|(p, _)| p.clone())
            .unwrap_or_default();
        let mut shared_pinv = Vec::with_capacity(lmax + 1);
        for l in 0..=lmax {
            if l < 2 {
                // `wigner_all_into` writes degrees 0 and 1 directly.
                shared_pinv.push(Vec::new());
                continue;
            }
            let d = 2 * l + 1;
            let mut a = DMatrix::<f64>::zeros(d, shared_pts.len());
            for (k, p) in shared_pts.iter().enumerate() {
                spherical_harmonics_unit_into(l, *p, &mut buf);
                for i in 0..d {
                    a[(i, k)] = buf[l * l + i];
                }
            }
            let inv = (&a * a.transpose())
                .try_inverse()
                .ok_or(PolicyError::UnsupportedDegree {
                    lmax,
                    mmax: lmax,
                    max_supported: l.saturating_sub(1),
                })?;
            let pinv = a.transpose() * inv;
            let mut rows = Vec::with_capacity(shared_pts.len() * d);
            for k in 0..shared_pts.len() {
                rows.extend((0..d).map(|j| pinv[(k, j)]));
            }
            shared_pinv.push(rows);
        }
        Ok(Self {
            lmax,
            per_degree,
            shared: (shared_pts, shared_pinv),
        })
    }

    /// Writes the block-diagonal D(R) over degrees 0..=lmax (the calculator's own lmax) as
    /// f32, row-major `[(lmax+1)², (lmax+1)²]`, into `out`; `sh` is scratch of
    /// `n_samples · (lmax+1)²` values. No allocation: the per-edge frames use this.
    pub fn wigner_all_into(&self, r: &Matrix3<f64>, sh: &mut Vec<f64>, out: &mut [f32]) {
        let k = num_coefficients(self.lmax);
        out[..k * k].iter_mut().for_each(|v| *v = 0.0);
        // Degrees 0 and 1 exactly: D⁰ = 1, and D¹ = R because the degree-1 harmonics are
        // √3 (x, y, z) (e3nn's order). The samples' least squares gives them to f64
        // rounding, so the same f32 values but for a rounding tie; the translation field's
        // frames (degree 1) need no samples at all.
        out[0] = 1.0;
        if self.lmax >= 1 {
            for i in 0..3 {
                for j in 0..3 {
                    out[(1 + i) * k + 1 + j] = r[(i, j)] as f32;
                }
            }
        }
        if self.lmax < 2 {
            return;
        }
        let (pts, pinv) = &self.shared;
        sh.resize(pts.len() * k, 0.0);
        for (p, y) in pts.iter().zip(sh.chunks_exact_mut(k)) {
            let rv = r * Vector3::new(p[0], p[1], p[2]);
            spherical_harmonics_unit_into(self.lmax, [rv[0], rv[1], rv[2]], y);
        }
        for (l, pl) in pinv.iter().enumerate().skip(2) {
            let d = 2 * l + 1;
            for i in 0..d {
                let mut row = [0.0f64; 2 * MAX_DEGREE + 1];
                for (y, pk) in sh.chunks_exact(k).zip(pl.chunks_exact(d)) {
                    let yi = y[l * l + i];
                    for (acc, pv) in row.iter_mut().zip(pk) {
                        *acc += yi * pv;
                    }
                }
                let o = (l * l + i) * k + l * l;
                for (dst, v) in out[o..o + d].iter_mut().zip(&row) {
                    *dst = *v as f32;
                }
            }
        }
    }

    /// The largest degree this calculator serves.
    pub fn lmax(&self) -> usize {
        self.lmax
    }

    /// D^l(R) as a (2l+1)×(2l+1) matrix.
    pub fn wigner_block(&self, l: usize, r: &Matrix3<f64>) -> Result<DMatrix<f64>> {
        let Some((pts, pinv)) = self.per_degree.get(l) else {
            return Err(PolicyError::UnsupportedDegree {
                lmax: l,
                mmax: l,
                max_supported: self.lmax,
            });
        };
        let d = 2 * l + 1;
        let mut b = DMatrix::<f64>::zeros(d, pts.len());
        let mut buf = vec![0.0; num_coefficients(l)];
        for (k, p) in pts.iter().enumerate() {
            let rv = r * Vector3::new(p[0], p[1], p[2]);
            spherical_harmonics_unit_into(l, [rv[0], rv[1], rv[2]], &mut buf);
            for i in 0..d {
                b[(i, k)] = buf[l * l + i];
            }
        }
        Ok(b * pinv)
    }

    /// Block-diagonal D(R) over degrees 0..=lmax, [(lmax+1)², (lmax+1)²].
    pub fn wigner(&self, lmax: usize, r: &Matrix3<f64>) -> Result<DMatrix<f64>> {
        check_rotation(r)?;
        if lmax > self.lmax {
            return Err(PolicyError::UnsupportedDegree {
                lmax,
                mmax: lmax,
                max_supported: self.lmax,
            });
        }
        let n = num_coefficients(lmax);
        let mut out = DMatrix::<f64>::zeros(n, n);
        for l in 0..=lmax {
            let blk = self.wigner_block(l, r)?;
            out.view_mut((l * l, l * l), (2 * l + 1, 2 * l + 1))
                .copy_from(&blk);
        }
        Ok(out)
    }
}

/// `n` nearly uniform unit vectors (Fibonacci lattice), deterministic.
pub fn fibonacci_sphere(n: usize) -> Vec<[f64; 3]> {
    let golden = std::f64::consts::PI * (3.0 - 5.0f64.sqrt());
    (0..n)
        .map(|i| {
            let y = 1.0 - 2.0 * (i as f64 + 0.5) / n as f64;
            let r = (1.0 - y * y).max(0.0).sqrt();
            let t = golden * i as f64;
            [r * t.cos(), y, r * t.sin()]
        })
        .collect()
}

/// The reference's edge frame (`init_edge_rot_mat2`): rows (z, x, -y) with x the unit edge
/// vector, so the matrix maps the edge direction to +y.
///
/// f is the coordinate axis with the smallest |x_k| (first on ties), z = unit(x × f),
/// y = unit(x × z). The roll about the edge is arbitrary; the SO(2) convolutions make the
/// layers independent of it.
pub fn edge_rot_mat(edge_vec: [f64; 3]) -> Result<Matrix3<f64>> {
    let x = Vector3::from(unit(edge_vec)?);
    let mut k = 0;
    for i in 1..3 {
        if x[i].abs() < x[k].abs() {
            k = i;
        }
    }
    let mut f = Vector3::zeros();
    f[k] = 1.0;
    let z = x.cross(&f).normalize();
    let y = x.cross(&z).normalize();
    Ok(Matrix3::from_rows(&[
        z.transpose(),
        x.transpose(),
        (-y).transpose(),
    ]))
}
