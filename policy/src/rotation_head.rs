//! The rotation head: the S2 -> SO(3) lifting convolution (`S2Conv`) and the evaluation of
//! the resulting SO(3) signal on a HEALPix rotation grid.
//!
//! Spec: `equact.md`, "Heads" (rotation); fixtures README, "Rotation head". With per-query S2
//! features x[f, i] (f < f_in, i < 25) and the filter ψ = (w on the 48 level-1 HEALPix
//! pixels, projected on Y) / √48:
//! `M_l[u,v] = (1/√f_in) Σ_f x[f, l²+u] ψ[f, l²+v]` and
//! `Q(g) = Σ_l √(2l+1) Σ_{u,v} M_l[u,v] D^l(g)[u,v]`.
//! If the scene rotates by R, then Q'(R g) = Q(g).

use nalgebra::Matrix3;

use crate::error::{PolicyError, Result};
use crate::grids::{s2_healpix_grid, GridRotation};
use crate::so3::{
    angles_to_xyz, num_coefficients, spherical_harmonics_unit_into, WignerCalculator,
};

/// Degree of the rotation head's S2 features.
pub const ROT_LMAX: usize = 4;
/// Number of SO(3) coefficients Σ_l (2l+1)² for l <= 4.
pub const SO3_COEFFS: usize = 165;

/// The S2Conv lift plus grid evaluation, with its filter precomputed.
#[derive(Debug, Clone)]
pub struct RotationHead {
    f_in: usize,
    /// ψ [f_in, 25].
    psi: Vec<f64>,
}

/// Flattened √(2l+1)·D^l(R) for l = 0..=4, row-major per block, 165 values.
pub fn flat_wigner(calc: &WignerCalculator, r: &Matrix3<f64>) -> Result<Vec<f64>> {
    let mut out = Vec::with_capacity(SO3_COEFFS);
    for l in 0..=ROT_LMAX {
        let d = calc.wigner_block(l, r)?;
        let s = ((2 * l + 1) as f64).sqrt();
        for u in 0..2 * l + 1 {
            for v in 0..2 * l + 1 {
                out.push(s * d[(u, v)]);
            }
        }
    }
    Ok(out)
}

impl RotationHead {
    /// Builds the head from the reference parameter `s2_conv.w` of shape [f_in, 1, 48].
    pub fn new(w: &[f32], f_in: usize) -> Result<Self> {
        let kernel = s2_healpix_grid(1);
        let n = kernel.len();
        if w.len() != f_in * n || f_in == 0 {
            return Err(PolicyError::ShapeMismatch {
                name: "s2_conv.w".into(),
                expected: vec![f_in, 1, n],
                got: vec![w.len()],
            });
        }
        let nc = num_coefficients(ROT_LMAX);
        let mut y = vec![0.0; nc];
        let mut psi = vec![0.0; f_in * nc];
        let scale = 1.0 / (n as f64).sqrt();
        for (k, &(alpha, beta)) in kernel.iter().enumerate() {
            spherical_harmonics_unit_into(ROT_LMAX, angles_to_xyz(alpha, beta), &mut y);
            for f in 0..f_in {
                let wf = f64::from(w[f * n + k]) * scale;
                for i in 0..nc {
                    psi[f * nc + i] += wf * y[i];
                }
            }
        }
        Ok(Self { f_in, psi })
    }

    /// Number of input S2 feature channels.
    pub fn f_in(&self) -> usize {
        self.f_in
    }

    /// The SO(3) coefficients (concatenated M_l, row-major) of one query's features x [f_in, 25].
    pub fn so3_coefficients(&self, x: &[f32]) -> Result<Vec<f64>> {
        let nc = num_coefficients(ROT_LMAX);
        if x.len() != self.f_in * nc {
            return Err(PolicyError::ShapeMismatch {
                name: "rotation head input".into(),
                expected: vec![self.f_in, nc],
                got: vec![x.len()],
            });
        }
        let norm = 1.0 / (self.f_in as f64).sqrt();
        let mut out = Vec::with_capacity(SO3_COEFFS);
        for l in 0..=ROT_LMAX {
            let d = 2 * l + 1;
            for u in 0..d {
                for v in 0..d {
                    let mut s = 0.0;
                    for f in 0..self.f_in {
                        s += f64::from(x[f * nc + l * l + u]) * self.psi[f * nc + l * l + v];
                    }
                    out.push(s * norm);
                }
            }
        }
        Ok(out)
    }

    /// Logits Q(g) = <coefficients, flat_wigner(g)> for each precomputed grid rotation.
    pub fn logits(coeffs: &[f64], flat_wigners: &[Vec<f64>]) -> Vec<f64> {
        flat_wigners
            .iter()
            .map(|fw| fw.iter().zip(coeffs).map(|(a, b)| a * b).sum())
            .collect()
    }

    /// Precomputes the flat Wigner matrices of a rotation grid.
    pub fn grid_wigners(calc: &WignerCalculator, grid: &[GridRotation]) -> Result<Vec<Vec<f64>>> {
        grid.iter().map(|g| flat_wigner(calc, &g.matrix)).collect()
    }
}
