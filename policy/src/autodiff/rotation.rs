//! Taped twin of the rotation readout: the open logit and the S2 → SO(3) lift
//! ([`crate::rotation_head::RotationHead`]) evaluated on given rotations, from the rotation
//! TransBlock's output at the query point (as [`crate::heads::FieldHeads::rot_query`]).
//!
//! The inference head works in f64 (filter, coefficients, logits); the tape is f32, so the
//! filter's spherical harmonics and the Wigner matrices are rounded to f32 here.

use std::sync::Arc;

use super::{Tape, Var};
use crate::error::{PolicyError, Result};
use crate::grids::s2_healpix_grid;
use crate::rotation_head::{ROT_LMAX, SO3_COEFFS};
use crate::so3::{angles_to_xyz, num_coefficients, spherical_harmonics_unit_into};
use crate::weights::Scope;

/// Level of the HEALPix grid the `s2_conv.w` filter lives on (48 pixels).
const KERNEL_LEVEL: u32 = 1;

/// The channel count of the query features `x` `[1, (ROT_LMAX+1)², c]` (its last axis).
fn query_channels(t: &Tape, x: Var) -> Result<usize> {
    let k = num_coefficients(ROT_LMAX);
    let c = t.shape(x).last().copied().unwrap_or(0);
    if c < 2 || t.value(x).len() != k * c {
        return Err(PolicyError::ShapeMismatch {
            name: "rotation query features (S2 channels plus the open channel)".into(),
            expected: vec![1, k, c.max(2)],
            got: t.shape(x).to_vec(),
        });
    }
    Ok(c)
}

/// The gripper-open logit `[1]`: channel c−1 of the l = 0 row of `x` `[1, (ROT_LMAX+1)², c]`.
pub fn open_logit(t: &mut Tape, x: Var) -> Result<Var> {
    let c = query_channels(t, x)?;
    let last = t.slice_cols(x, c, c - 1..c)?;
    let l0 = t.gather_rows(last, 1, &[0])?;
    t.reshape(l0, &[1])
}

/// The SO(3) coefficients `[SO3_COEFFS]` (concatenated M_l, row-major) of the S2 features in
/// channels 0..c−1 of `x` `[1, (ROT_LMAX+1)², c]`, with the filter `s2_conv.w` of `s`.
pub fn so3_coefficients(t: &mut Tape, s: &Scope<'_>, x: Var) -> Result<Var> {
    let c = query_channels(t, x)?;
    let f_in = c - 1;
    let kernel = s2_healpix_grid(KERNEL_LEVEL);
    let np = kernel.len();
    let nc = num_coefficients(ROT_LMAX);
    let w = t.param(&s.sub("s2_conv"), "w", &[f_in, 1, np])?;
    // ψ = w · Yᵀ / √48 with Y the harmonics at the kernel pixels: `[f_in, nc]`.
    let mut yt = vec![0.0f32; nc * np];
    let mut y = vec![0.0f64; nc];
    let scale = 1.0 / (np as f64).sqrt();
    for (k, &(alpha, beta)) in kernel.iter().enumerate() {
        spherical_harmonics_unit_into(ROT_LMAX, angles_to_xyz(alpha, beta), &mut y);
        for (i, v) in y.iter().enumerate() {
            yt[i * np + k] = (v * scale) as f32;
        }
    }
    let yt = t.constant(yt, &[nc, np])?;
    let w2 = t.reshape(w, &[f_in, np])?;
    let psi = t.linear(w2, yt, None)?;
    t.s2_lift(x, psi, c)
}

/// Rotation logits `[flat_wigners.len()]`: `Q(g) = ⟨coefficients, flat_wigner(g)⟩` for the
/// precomputed `√(2l+1)·D^l(g)` of each rotation (from
/// [`crate::rotation_head::RotationHead::grid_wigners`]), `x` as in [`so3_coefficients`].
pub fn rotation_logits(
    t: &mut Tape,
    s: &Scope<'_>,
    x: Var,
    flat_wigners: &[Vec<f64>],
) -> Result<Var> {
    if let Some(bad) = flat_wigners.iter().find(|fw| fw.len() != SO3_COEFFS) {
        return Err(PolicyError::ShapeMismatch {
            name: "flat Wigner matrices".into(),
            expected: vec![flat_wigners.len(), SO3_COEFFS],
            got: vec![bad.len()],
        });
    }
    let coeffs = so3_coefficients(t, s, x)?;
    let g = flat_wigners.len();
    let fw: Vec<f32> = flat_wigners.iter().flatten().map(|v| *v as f32).collect();
    let fw = t.constant(fw, &[g, SO3_COEFFS])?;
    let row = t.reshape(coeffs, &[1, SO3_COEFFS])?;
    let logits = t.linear(row, fw, None)?;
    t.reshape(logits, &[g])
}

impl Tape {
    /// The S2 → SO(3) lift `M_l[u,v] = (1/√f_in) Σ_f x[l²+u, f] ψ[f, l²+v]` for l ≤ ROT_LMAX
    /// with `x` `[(ROT_LMAX+1)², c]` (channels f < f_in = `psi` rows used) and `psi`
    /// `[f_in, (ROT_LMAX+1)²]`; returns the blocks concatenated row-major, `[SO3_COEFFS]`.
    fn s2_lift(&mut self, x: Var, psi: Var, c: usize) -> Result<Var> {
        let nc = num_coefficients(ROT_LMAX);
        let f_in = crate::layers::rows_of("S2 filter", self.value(psi).len(), nc)?;
        if f_in > c || self.value(x).len() != nc * c {
            return Err(PolicyError::ShapeMismatch {
                name: "S2 lift features".into(),
                expected: vec![nc, c.max(f_in)],
                got: self.shape(x).to_vec(),
            });
        }
        // (output index, degree block start, u, v) of every coefficient.
        let index: Arc<[(usize, usize, usize)]> = (0..=ROT_LMAX)
            .flat_map(|l| {
                let d = 2 * l + 1;
                (0..d * d).map(move |uv| (l * l, uv / d, uv % d))
            })
            .collect();
        let norm = 1.0 / (f_in as f64).sqrt();
        let (xv, pv) = (self.value(x), self.value(psi));
        let out: Vec<f32> = index
            .iter()
            .map(|&(b, u, v)| {
                let s: f64 = (0..f_in)
                    .map(|f| f64::from(xv[(b + u) * c + f]) * f64::from(pv[f * nc + b + v]))
                    .sum();
                (s * norm) as f32
            })
            .collect();
        Ok(self.push(
            out,
            vec![SO3_COEFFS],
            &[x, psi],
            Some(Box::new(move |vals, g, gr| {
                let (xv, pv) = (vals.get(x), vals.get(psi));
                let norm = norm as f32;
                if let Some(acc) = gr.acc(x) {
                    for (&(b, u, v), gi) in index.iter().zip(g) {
                        for f in 0..f_in {
                            acc[(b + u) * c + f] += norm * gi * pv[f * nc + b + v];
                        }
                    }
                }
                if let Some(acc) = gr.acc(psi) {
                    for (&(b, u, v), gi) in index.iter().zip(g) {
                        for f in 0..f_in {
                            acc[f * nc + b + v] += norm * gi * xv[(b + u) * c + f];
                        }
                    }
                }
            })),
        ))
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::autodiff::check::{finite_difference_check, FdOptions};
    use crate::autodiff::layers::tests::random;
    use crate::autodiff::layers::tests::small_weights;
    use crate::grids::so3_healpix_grid;
    use crate::rotation_head::RotationHead;
    use crate::so3::WignerCalculator;

    /// field_nn_c of `small_weights`.
    const C: usize = 8;

    #[test]
    fn rotation_logits_match_inference_and_finite_differences() {
        let w = small_weights();
        let s = w.scope("");
        let nc = num_coefficients(ROT_LMAX);
        let x = random(nc * C, 31);
        // The inference path, as FieldHeads::rot_query: S2 features [f, i] = x[i, f].
        let filter = s.sub("s2_conv").f32("w", &[C - 1, 1, 48]).unwrap();
        let head = RotationHead::new(&filter, C - 1).unwrap();
        let mut s2 = vec![0.0f32; (C - 1) * nc];
        for i in 0..nc {
            for f in 0..C - 1 {
                s2[f * nc + i] = x[i * C + f];
            }
        }
        let want_coeffs = head.so3_coefficients(&s2).unwrap();
        let calc = WignerCalculator::new(ROT_LMAX).unwrap();
        let fw = RotationHead::grid_wigners(&calc, &so3_healpix_grid(0)).unwrap();
        let want = RotationHead::logits(&want_coeffs, &fw);

        let mut t = Tape::new();
        let xv = t.variable(x.clone(), &[1, nc, C]).unwrap();
        let coeffs = so3_coefficients(&mut t, &s, xv).unwrap();
        let logits = rotation_logits(&mut t, &s, xv, &fw).unwrap();
        assert_eq!(t.shape(logits), &[fw.len()]);
        // The inference is f64 throughout; here the harmonics, ψ, the Wigner entries and the
        // 48- and 165-term sums are f32 (relative rounding ~1e-7 per step), so agreement is to
        // ~1e-5 of the largest magnitude rather than of each value.
        let close = |got: &[f32], want: &[f64], what: &str| {
            let scale = 1.0 + want.iter().fold(0.0f64, |m, v| m.max(v.abs()));
            for (i, (a, b)) in got.iter().zip(want).enumerate() {
                assert!(
                    (f64::from(*a) - b).abs() <= 2e-5 * scale,
                    "{what}[{i}]: {a} vs {b}"
                );
            }
        };
        close(t.value(coeffs), &want_coeffs, "coefficients");
        close(t.value(logits), &want, "logits");

        let r = finite_difference_check(
            &w,
            "",
            &[(x, vec![1, nc, C])],
            FdOptions {
                per_tensor: 16,
                ..FdOptions::default()
            },
            |t, s, v| rotation_logits(t, s, v[0], &fw),
        )
        .unwrap();
        assert!(
            r.passed(),
            "worst {:.3} at {} ({:?})",
            r.worst_ratio,
            r.worst,
            r.tensors
        );
        assert_eq!(r.tensors, ["input 0", "s2_conv.w"]);
    }

    #[test]
    fn open_logit_matches_inference_and_finite_differences() {
        let w = small_weights();
        let nc = num_coefficients(ROT_LMAX);
        let x = random(nc * C, 32);
        let mut t = Tape::new();
        let xv = t.variable(x.clone(), &[1, nc, C]).unwrap();
        let y = open_logit(&mut t, xv).unwrap();
        // FieldHeads::rot_query: `embedding[c - 1]`.
        assert_eq!(t.value(y), &[x[C - 1]]);
        let r = finite_difference_check(
            &w,
            "",
            &[(x, vec![1, nc, C])],
            FdOptions {
                per_tensor: 200,
                ..FdOptions::default()
            },
            |t, _, v| open_logit(t, v[0]),
        )
        .unwrap();
        assert!(r.passed(), "worst {:.3} at {}", r.worst_ratio, r.worst);
    }

    #[test]
    fn bad_rotation_inputs_are_errors() {
        let w = small_weights();
        let s = w.scope("");
        let nc = num_coefficients(ROT_LMAX);
        let mut t = Tape::new();
        let flat = t.variable(vec![0.0; nc * C], &[nc * C]).unwrap();
        assert!(open_logit(&mut t, flat).is_err(), "no channel axis");
        let one = t.variable(vec![0.0; nc], &[1, nc, 1]).unwrap();
        assert!(open_logit(&mut t, one).is_err(), "no open channel");
        let wide = t.variable(vec![0.0; nc * 6], &[1, nc, 6]).unwrap();
        assert!(
            rotation_logits(&mut t, &s, wide, &[]).is_err(),
            "filter is for 7 channels"
        );
        let x = t.variable(vec![0.0; nc * C], &[1, nc, C]).unwrap();
        assert!(rotation_logits(&mut t, &s, x, &[vec![0.0; 3]]).is_err());
        assert!(rotation_logits(&mut t, &s, x, &[vec![0.0; SO3_COEFFS]]).is_ok());
    }
}
