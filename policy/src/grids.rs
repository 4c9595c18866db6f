//! Sampling grids: the S2 grids of the separable S2 activation, and HEALPix grids on the
//! sphere and on SO(3).
//!
//! Spec: fixtures README, "S2 grids" and "HEALPix SO(3) grid"; `equact.md`, "EquiformerV2
//! block" (separable S2 activation) and "Heads" (rotation grid). The S2 grid matrices are
//! built from their closed forms (they agree with the reference's tables to 6e-8).

use crate::error::{PolicyError, Result};
use crate::matmul::{gemm_acc, Strided};
use crate::so3::{angles_to_matrix, angles_to_xyz, spherical_harmonics_unit_into, MAX_DEGREE};
use nalgebra::Matrix3;

/// Full-basis indices (l*l + m + l) of the coefficients with |m| <= mmax, in l-major order.
pub fn reduced_coefficients(lmax: usize, mmax: usize) -> Vec<usize> {
    let mut out = Vec::new();
    for l in 0..=lmax {
        let mm = l.min(mmax) as i64;
        for m in -mm..=mm {
            out.push(crate::so3::coefficient_index(l, m));
        }
    }
    out
}

/// The reference's grid resolution for (lmax, mmax) with `grid_resolution=None`:
/// (lat, long) = (2(lmax+1), 2(mmax+1)+1 if lmax == mmax else 2 mmax + 1).
pub fn reference_resolution(lmax: usize, mmax: usize) -> (usize, usize) {
    let lat = 2 * (lmax + 1);
    let long = if lmax == mmax {
        2 * (mmax + 1) + 1
    } else {
        2 * mmax + 1
    };
    (lat, long)
}

/// Kostelec-Rockmore quadrature weights per latitude ring, scaled as the reference's
/// `from_grid` uses them (qw_b = w_b · lat² / long).
pub fn quadrature_weights(lat: usize, long: usize) -> Vec<f64> {
    use std::f64::consts::PI;
    let b = lat as f64 / 2.0;
    (0..lat)
        .map(|j| {
            let jj = (2 * j + 1) as f64;
            let mut s = 0.0;
            for k in 0..(lat / 2) {
                let kk = (2 * k + 1) as f64;
                s += (jj * kk * PI / (4.0 * b)).sin() / kk;
            }
            let w = (2.0 / b) * (PI * jj / (4.0 * b)).sin() * s / (2.0 * (2.0 * b) * (2.0 * b));
            w * (lat * lat) as f64 / long as f64
        })
        .collect()
}

/// An S2 grid with its to-grid and from-grid matrices for the reduced coefficient set.
#[derive(Debug, Clone)]
pub struct S2Grid {
    /// Maximum degree.
    pub lmax: usize,
    /// Maximum order kept.
    pub mmax: usize,
    /// Number of latitude rings (beta samples).
    pub lat: usize,
    /// Number of longitudes (alpha samples).
    pub long: usize,
    /// Full-basis index of each reduced coefficient.
    pub reduced: Vec<usize>,
    /// [lat, long, n_reduced], row-major.
    pub to_grid: Vec<f64>,
    /// [lat, long, n_reduced], row-major.
    pub from_grid: Vec<f64>,
    /// `to_grid` in f32 (the activation's fast path).
    to_grid32: Vec<f32>,
    /// `from_grid` in f32.
    from_grid32: Vec<f32>,
    /// A gated activation instead of the grid (no grid points): exactly equivariant.
    pub gated: bool,
}

impl S2Grid {
    /// The reference's grid for (lmax, mmax) (parity mode).
    pub fn reference(lmax: usize, mmax: usize) -> Result<Self> {
        let (lat, long) = reference_resolution(lmax, mmax);
        Self::with_resolution(lmax, mmax, lat, long)
    }

    /// A grid with the given resolution (finer grids make the S2 activation closer to
    /// equivariant; the scale factors keep the reference's normalisation).
    pub fn with_resolution(lmax: usize, mmax: usize, lat: usize, long: usize) -> Result<Self> {
        if lmax > MAX_DEGREE || mmax > lmax || lat < 2 || long < 1 || !lat.is_multiple_of(2) {
            return Err(PolicyError::UnsupportedDegree {
                lmax,
                mmax,
                max_supported: MAX_DEGREE,
            });
        }
        use std::f64::consts::PI;
        let reduced = reduced_coefficients(lmax, mmax);
        let nr = reduced.len();
        let qw = quadrature_weights(lat, long);
        let mut to_grid = vec![0.0; lat * long * nr];
        let mut from_grid = vec![0.0; lat * long * nr];
        let mut y = vec![0.0; crate::so3::num_coefficients(lmax)];
        let degree_of = |i: usize| (i as f64).sqrt().floor() as usize;
        for (bi, &qb) in qw.iter().enumerate() {
            let beta = (bi as f64 + 0.5) * PI / lat as f64;
            for ai in 0..long {
                let alpha = 2.0 * PI * ai as f64 / long as f64;
                spherical_harmonics_unit_into(lmax, angles_to_xyz(alpha, beta), &mut y);
                for (r, &full) in reduced.iter().enumerate() {
                    let l = degree_of(full);
                    let tl = (2 * l + 1) as f64;
                    let rescale = if l > mmax {
                        (tl / (2 * mmax + 1) as f64).sqrt()
                    } else {
                        1.0
                    };
                    let idx = (bi * long + ai) * nr + r;
                    to_grid[idx] = y[full] / (tl * (lmax + 1) as f64).sqrt() * rescale;
                    from_grid[idx] = qb * y[full] * ((lmax + 1) as f64 * tl).sqrt() * rescale;
                }
            }
        }
        Ok(Self {
            lmax,
            mmax,
            lat,
            long,
            reduced,
            to_grid32: to_grid.iter().map(|v| *v as f32).collect(),
            from_grid32: from_grid.iter().map(|v| *v as f32).collect(),
            to_grid,
            from_grid,
            gated: false,
        })
    }

    /// The gated activation for (lmax, mmax) in place of a grid (equivariant mode's exact
    /// option): no grid points; [`S2Grid::activate`] and
    /// [`crate::layers::separable_s2_activation`] then multiply every l > 0 channel by a
    /// sigmoid gate instead of sampling the sphere.
    pub fn gate(lmax: usize, mmax: usize) -> Result<Self> {
        if lmax > MAX_DEGREE || mmax > lmax {
            return Err(PolicyError::UnsupportedDegree {
                lmax,
                mmax,
                max_supported: MAX_DEGREE,
            });
        }
        Ok(Self {
            lmax,
            mmax,
            lat: 0,
            long: 0,
            reduced: reduced_coefficients(lmax, mmax),
            to_grid: Vec::new(),
            from_grid: Vec::new(),
            to_grid32: Vec::new(),
            from_grid32: Vec::new(),
            gated: true,
        })
    }

    /// Number of grid points.
    pub fn num_points(&self) -> usize {
        self.lat * self.long
    }

    /// `grid[z, p, c] = sum_i to_grid[p, i] x[z, i, c]` for x of shape [n, n_reduced, c].
    pub fn to_grid_values(&self, x: &[f32], n: usize, c: usize) -> Result<Vec<f32>> {
        let nr = self.reduced.len();
        check_len("S2 grid input", x.len(), &[n, nr, c])?;
        let grid = self.to_grid_columns(&swap_outer(x, n, nr, c), n * c)?;
        Ok(swap_outer(&grid, self.num_points(), n, c))
    }

    /// The to-grid product on coefficient-major values `[n_reduced, cols]`: `[points, cols]`.
    fn to_grid_columns(&self, xt: &[f32], cols: usize) -> Result<Vec<f32>> {
        let (np, nr) = (self.num_points(), self.reduced.len());
        let mut grid = vec![0.0f32; np * cols];
        gemm_acc(
            Strided::row_major(&self.to_grid32, 0, np, nr),
            Strided::row_major(xt, 0, nr, cols),
            &mut grid,
            0,
            cols,
        )?;
        Ok(grid)
    }

    /// The S2 activation of the reference: from_grid(SiLU(to_grid(x))), x of shape [n, n_reduced, c].
    ///
    /// Runs as two matrix products over all nodes and channels at once: the values are
    /// reordered coefficient-major (`[n_reduced, n·c]`), taken to the grid, activated, and
    /// brought back with the transposed from-grid matrix.
    ///
    /// A gated "grid" ([`S2Grid::gate`]) instead gates each channel by its own l = 0 value:
    /// l = 0 → SiLU(x₀), l > 0 → x · σ(x₀).
    pub fn activate(&self, x: &[f32], n: usize, c: usize) -> Result<Vec<f32>> {
        let nr = self.reduced.len();
        check_len("S2 activation input", x.len(), &[n, nr, c])?;
        if self.gated {
            let gates: Vec<f32> = x
                .chunks_exact(nr * c)
                .flat_map(|node| node[..c].iter().copied())
                .collect();
            return Ok(gate_activation(x, &gates, &gates, nr, c));
        }
        let cols = n * c;
        let mut grid = self.to_grid_columns(&swap_outer(x, n, nr, c), cols)?;
        // SiLU once per grid value (an exp in f32 arithmetic, 16 lanes at a time: the finer
        // equivariant grids make this hundreds of millions of values), then spread over the
        // coefficients.
        silu_f32_in_place(&mut grid);
        let np = self.num_points();
        let mut out = vec![0.0f32; nr * cols];
        gemm_acc(
            Strided::row_major(&self.from_grid32, 0, np, nr).t(),
            Strided::row_major(&grid, 0, np, cols),
            &mut out,
            0,
            cols,
        )?;
        Ok(swap_outer(&out, nr, n, c))
    }
}

/// The gated activation on `x` `[n, nr, c]`: row 0 (l = 0) becomes SiLU(`scalars[node, ch]`)
/// and every other row is multiplied by σ(`gates[node, ch]`). Rotations act on each (l,
/// channel) block alone, so multiplying a block by an invariant scalar commutes with them:
/// exactly equivariant, at O(n·nr·c) instead of two products with the grid matrices.
pub fn gate_activation(x: &[f32], scalars: &[f32], gates: &[f32], nr: usize, c: usize) -> Vec<f32> {
    let mut y = x.to_vec();
    gate_activation_in_place(&mut y, scalars, gates, nr, c);
    y
}

/// [`gate_activation`] on `y` in place.
pub fn gate_activation_in_place(
    y: &mut [f32],
    scalars: &[f32],
    gates: &[f32],
    nr: usize,
    c: usize,
) {
    if nr * c == 0 {
        return;
    }
    // SiLU and σ of every node's scalars and gates at once, eight values at a time.
    let nodes = y.len() / (nr * c);
    let mut act = scalars[..nodes * c].to_vec();
    crate::vector_exp::silu_in_place(&mut act);
    let mut sig = gates[..nodes * c].to_vec();
    crate::vector_exp::sigmoid_in_place(&mut sig);
    for ((yn, act), sig) in y
        .chunks_exact_mut(nr * c)
        .zip(act.chunks_exact(c))
        .zip(sig.chunks_exact(c))
    {
        yn[..c].copy_from_slice(act);
        for row in yn[c..].chunks_exact_mut(c) {
            for (v, sg) in row.iter_mut().zip(sig) {
                *v *= sg;
            }
        }
    }
}

// The constants of `exp_f32` (and of its vector form in `SiluInPlace`).
const EXP_LOG2E: f32 = std::f32::consts::LOG2_E;
// ln 2 split so that n·LN2_HI is exact for |n| < 2^9.
const EXP_LN2_HI: f32 = 0.693_359_4;
const EXP_LN2_LO: f32 = -2.121_944_4e-4;
// 1.5·2^23: adding it rounds to an integer held in the low mantissa bits.
const EXP_SHIFTER: f32 = 12_582_912.0;
// e^r on |r| <= ln2/2: Taylor series to degree 7 (truncation below 1e-8), highest first.
const EXP_TAYLOR: [f32; 8] = [
    1.0 / 5040.0,
    1.0 / 720.0,
    1.0 / 120.0,
    1.0 / 24.0,
    1.0 / 6.0,
    0.5,
    1.0,
    1.0,
];

/// e^x in f32 arithmetic only (no libm call), so loops over it vectorise. Relative error
/// below 3e-7 (within a few f32 ulps of `f32::exp`); arguments are clamped to [−87, 88],
/// which keeps the result finite and normal.
pub fn exp_f32(x: f32) -> f32 {
    let x = x.clamp(-87.0, 88.0);
    let t = x * EXP_LOG2E + EXP_SHIFTER;
    let n = t - EXP_SHIFTER;
    let r = x - n * EXP_LN2_HI - n * EXP_LN2_LO;
    let mut p = EXP_TAYLOR[0];
    for &c in &EXP_TAYLOR[1..] {
        p = c + r * p;
    }
    // 2^n from the integer in t's low bits, placed in the exponent field.
    let ni = (t.to_bits() as i32).wrapping_sub(EXP_SHIFTER.to_bits() as i32);
    p * f32::from_bits(((ni + 127) as u32) << 23)
}

/// SiLU x / (1 + e^−x) of every value of `v` in place, with [`exp_f32`]: whole vectors
/// through `pulp`'s run-time dispatch (AVX-512 or AVX2; the build targets plain x86-64,
/// whose 4-lane loop spent most of its time waiting on divisions), the same operations in
/// the same order as the scalar form, so every value is the same bit for bit.
pub fn silu_f32_in_place(v: &mut [f32]) {
    pulp::Arch::new().dispatch(SiluInPlace(v));
}

/// The SiLU of [`silu_f32_in_place`].
fn silu_f32(x: f32) -> f32 {
    x / (1.0 + exp_f32(-x))
}

/// [`silu_f32_in_place`]'s kernel: [`exp_f32`] lane by lane.
struct SiluInPlace<'a>(&'a mut [f32]);

impl pulp::WithSimd for SiluInPlace<'_> {
    type Output = ();

    #[inline(always)]
    fn with_simd<S: pulp::Simd>(self, simd: S) {
        let (head, tail) = S::as_mut_simd_f32s(self.0);
        // No closures in here: they would not inherit the kernel's target features.
        let (lo, hi) = (simd.splat_f32s(-87.0), simd.splat_f32s(88.0));
        let (log2e, shifter) = (simd.splat_f32s(EXP_LOG2E), simd.splat_f32s(EXP_SHIFTER));
        let (ln2_hi, ln2_lo) = (simd.splat_f32s(EXP_LN2_HI), simd.splat_f32s(EXP_LN2_LO));
        let one = simd.splat_f32s(1.0);
        let mut taylor = [one; EXP_TAYLOR.len()];
        for (t, &c) in taylor.iter_mut().zip(&EXP_TAYLOR) {
            *t = simd.splat_f32s(c);
        }
        let bias = simd.splat_u32s(127u32.wrapping_sub(EXP_SHIFTER.to_bits()));
        let exponent_shift = simd.splat_u32s(23);
        for g in head {
            let x = simd.neg_f32s(*g);
            // The scalar clamp (a NaN argument's SiLU is NaN either way: it is divided).
            let x = simd.min_f32s(simd.max_f32s(x, lo), hi);
            let t = simd.add_f32s(simd.mul_f32s(x, log2e), shifter);
            let n = simd.sub_f32s(t, shifter);
            let r = simd.sub_f32s(
                simd.sub_f32s(x, simd.mul_f32s(n, ln2_hi)),
                simd.mul_f32s(n, ln2_lo),
            );
            let mut p = taylor[0];
            for &c in &taylor[1..] {
                p = simd.add_f32s(c, simd.mul_f32s(r, p));
            }
            // (t's bits − the shifter's + 127) << 23, in wrapping u32 as the scalar i32 form.
            let e = simd.add_u32s(simd.transmute_u32s_f32s(t), bias);
            let scale = simd.transmute_f32s_u32s(simd.wrapping_dyn_shl_u32s(e, exponent_shift));
            *g = simd.div_f32s(*g, simd.add_f32s(one, simd.mul_f32s(p, scale)));
        }
        for g in tail {
            *g = silu_f32(*g);
        }
    }
}

/// Swaps the two outer axes of `[a, b, c]` values: `[b, a, c]`.
fn swap_outer(x: &[f32], a: usize, b: usize, c: usize) -> Vec<f32> {
    let mut y = vec![0.0f32; x.len()];
    for i in 0..a {
        for j in 0..b {
            y[(j * a + i) * c..(j * a + i + 1) * c]
                .copy_from_slice(&x[(i * b + j) * c..(i * b + j + 1) * c]);
        }
    }
    y
}

/// SiLU x·σ(x).
pub fn silu(x: f64) -> f64 {
    x / (1.0 + (-x).exp())
}

fn check_len(name: &str, len: usize, shape: &[usize]) -> Result<()> {
    if len != shape.iter().product::<usize>() {
        return Err(PolicyError::ShapeMismatch {
            name: name.to_string(),
            expected: shape.to_vec(),
            got: vec![len],
        });
    }
    Ok(())
}

/// HEALPix `pix2ang` in RING order: (colatitude theta, longitude phi) of pixel `p`.
pub fn healpix_pix2ang_ring(nside: usize, p: usize) -> (f64, f64) {
    use std::f64::consts::PI;
    let ns = nside as f64;
    let npix = 12 * nside * nside;
    let ncap = 2 * nside * (nside - 1);
    if p < ncap {
        let iring = isqrt(1 + 2 * p).div_ceil(2);
        let iphi = p + 1 - 2 * iring * (iring - 1);
        let z = 1.0 - (iring * iring) as f64 / (3.0 * ns * ns);
        (z.acos(), (iphi as f64 - 0.5) * PI / (2.0 * iring as f64))
    } else if p < npix - ncap {
        let ip = p - ncap;
        let iring = ip / (4 * nside) + nside;
        let iphi = ip % (4 * nside) + 1;
        let fodd = if (iring + nside) % 2 == 1 { 1.0 } else { 0.5 };
        let z = (2.0 * ns - iring as f64) * 2.0 / (3.0 * ns);
        (z.acos(), (iphi as f64 - fodd) * PI / (2.0 * ns))
    } else {
        let ip = npix - p;
        let iring = isqrt(2 * ip - 1).div_ceil(2);
        let iphi = 4 * iring + 1 - (ip - 2 * iring * (iring - 1));
        let z = -1.0 + (iring * iring) as f64 / (3.0 * ns * ns);
        (z.acos(), (iphi as f64 - 0.5) * PI / (2.0 * iring as f64))
    }
}

fn isqrt(n: usize) -> usize {
    let mut r = (n as f64).sqrt() as usize;
    while r * r > n {
        r -= 1;
    }
    while (r + 1) * (r + 1) <= n {
        r += 1;
    }
    r
}

/// HEALPix sphere grid of `level` (n_side = 2^level): (alpha = longitude, beta = colatitude) per pixel.
pub fn s2_healpix_grid(level: u32) -> Vec<(f64, f64)> {
    let nside = 1usize << level;
    (0..12 * nside * nside)
        .map(|p| {
            let (theta, phi) = healpix_pix2ang_ring(nside, p);
            (phi, theta)
        })
        .collect()
}

/// One rotation of the HEALPix SO(3) grid.
#[derive(Debug, Clone, Copy)]
pub struct GridRotation {
    /// e3nn angles (alpha, beta, gamma).
    pub angles: [f64; 3],
    /// Ry(alpha) Rx(beta) Ry(gamma).
    pub matrix: Matrix3<f64>,
}

/// HEALPix SO(3) grid of `level`: 72·8^level rotations, index q·npix + p (gamma-major).
pub fn so3_healpix_grid(level: u32) -> Vec<GridRotation> {
    use std::f64::consts::PI;
    let pix = s2_healpix_grid(level);
    let n_gamma = 6 * (1usize << level);
    let mut out = Vec::with_capacity(pix.len() * n_gamma);
    for q in 0..n_gamma {
        let gamma = 2.0 * PI * q as f64 / n_gamma as f64;
        for &(alpha, beta) in &pix {
            out.push(GridRotation {
                angles: [alpha, beta, gamma],
                matrix: angles_to_matrix(alpha, beta, gamma),
            });
        }
    }
    out
}

/// Which S2 grids the separable S2 activations use.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub enum S2Resolution {
    /// The reference's coarse grids (parity mode).
    #[default]
    Reference,
    /// `n` × `n` grids for every (lmax, mmax) (equivariant mode; 48 gives ~1e-7).
    Square(usize),
    /// No grids: a gated activation (l > 0 channels times a sigmoid of the layer's gating
    /// scalars), exactly equivariant; same weights.
    Gated,
}

impl S2Resolution {
    /// The grid for (lmax, mmax) at this resolution.
    pub fn grid(self, lmax: usize, mmax: usize) -> Result<S2Grid> {
        match self {
            Self::Reference => S2Grid::reference(lmax, mmax),
            Self::Square(n) => S2Grid::with_resolution(lmax, mmax, n, n),
            Self::Gated => S2Grid::gate(lmax, mmax),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::{exp_f32, silu_f32, silu_f32_in_place};

    #[test]
    fn silu_of_whole_vectors_equals_the_scalar_form_bit_for_bit() {
        // 400 000 values from −100 to 100, plus the edges: ±0, the clamp's bounds and
        // beyond, infinities, subnormals, the extremes; 37 values at a time so that each call
        // has a remainder after its whole vectors.
        let mut values: Vec<f32> = (-200_000..200_000)
            .map(|i| i as f32 * 5e-4 + 1e-5)
            .collect();
        values.extend([
            0.0,
            -0.0,
            87.0,
            -87.0,
            88.0,
            -88.0,
            1e3,
            -1e3,
            f32::INFINITY,
            f32::NEG_INFINITY,
            f32::MIN_POSITIVE / 4.0,
            f32::MAX,
            f32::MIN,
        ]);
        for chunk in values.chunks(37) {
            let mut got = chunk.to_vec();
            silu_f32_in_place(&mut got);
            for (&x, y) in chunk.iter().zip(&got) {
                assert_eq!(y.to_bits(), silu_f32(x).to_bits(), "SiLU({x}): {y}");
            }
        }
        let mut nan = vec![f32::NAN; 20];
        silu_f32_in_place(&mut nan);
        assert!(nan.iter().all(|v| v.is_nan()));
        // And the values are SiLU's.
        for x in [-3.0f32, -0.5, 0.0, 0.5, 3.0] {
            let want = f64::from(x) / (1.0 + (-f64::from(x)).exp());
            assert!((f64::from(silu_f32(x)) - want).abs() < 1e-6, "SiLU({x})");
        }
    }

    #[test]
    fn exp_f32_matches_the_library_exp() {
        let mut worst = 0.0f64;
        for i in -8700..8800 {
            let x = i as f32 * 0.01 + 0.003;
            let want = f64::from(x).exp();
            let got = f64::from(exp_f32(x));
            worst = worst.max(((got - want) / want).abs());
        }
        assert!(worst < 3e-7, "worst relative error {worst}");
        // Clamped: finite at the extremes.
        assert!(exp_f32(1000.0).is_finite() && exp_f32(-1000.0) > 0.0);
    }
}
