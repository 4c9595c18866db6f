//! Taped twins of the basic layers: dense linear, `SO3_LinearV2`, `rms_norm_sh` and
//! LayerNorm. Each reads its parameters by the inference layer's names from a scope and
//! computes the same values in the same order.

use super::{Tape, Var};
use crate::error::{PolicyError, Result};
use crate::layers::{balance_weight, degree_of, rms_centre_and_scale, rows_of};
use crate::matmul::{gemm_acc, Strided};
use crate::so3::num_coefficients;
use crate::weights::Scope;

/// `nn.Linear` (`weight` `[out, inp]`, `bias` `[out]` when `bias`) on rows of `inp` values.
pub fn linear(
    t: &mut Tape,
    s: &Scope<'_>,
    x: Var,
    out: usize,
    inp: usize,
    bias: bool,
) -> Result<Var> {
    let w = t.param(s, "weight", &[out, inp])?;
    let b = if bias {
        Some(t.param(s, "bias", &[out])?)
    } else {
        None
    };
    t.linear(x, w, b)
}

/// `SO3_LinearV2` on `x` `[n, (lmax+1)², cin]`, sizes from `weight` `[(lmax+1), cout, cin]`;
/// bias on the l = 0 row.
pub fn so3_linear(t: &mut Tape, s: &Scope<'_>, x: Var) -> Result<Var> {
    let shape = s.shape("weight", 3)?;
    let (lmax, cout, cin) = (shape[0].saturating_sub(1), shape[1], shape[2]);
    let w = t.param(s, "weight", &shape)?;
    let b = t.param(s, "bias", &[cout])?;
    per_degree_linear(t, x, w, Some(b), (lmax, cin, cout))
}

/// Per-degree channel mixing `y[n, i] = W[degree(i)] · x[n, i]` (+ `b` on the l = 0 row),
/// with `w` `[(lmax+1), cout, cin]` a taped value (a parameter or a generated FiLM weight).
pub fn per_degree_linear(
    t: &mut Tape,
    x: Var,
    w: Var,
    b: Option<Var>,
    (lmax, cin, cout): (usize, usize, usize),
) -> Result<Var> {
    let k = num_coefficients(lmax);
    let n = rows_of("SO3 linear input", t.value(x).len(), k * cin)?;
    if t.value(w).len() != (lmax + 1) * cout * cin {
        return Err(PolicyError::ShapeMismatch {
            name: "SO3 linear weight".into(),
            expected: vec![lmax + 1, cout, cin],
            got: t.shape(w).to_vec(),
        });
    }
    let mut y = vec![0.0f32; n * k * cout];
    if let Some(b) = b {
        if t.value(b).len() != cout {
            return Err(PolicyError::ShapeMismatch {
                name: "SO3 linear bias".into(),
                expected: vec![cout],
                got: t.shape(b).to_vec(),
            });
        }
        let bv = t.value(b);
        for yn in y.chunks_exact_mut(k * cout) {
            yn[..cout].copy_from_slice(bv);
        }
    }
    for i in 0..k {
        let l = degree_of(i);
        gemm_acc(
            column_block(t.value(x), i, n, cin, k),
            Strided::row_major(t.value(w), l * cout * cin, cout, cin).t(),
            &mut y,
            i * cout,
            k * cout,
        )?;
    }
    let mut parents = vec![x, w];
    parents.extend(b);
    Ok(t.push(
        y,
        vec![n, k, cout],
        &parents,
        Some(Box::new(move |vals, g, gr| {
            if let Some(acc) = gr.acc(x) {
                for i in 0..k {
                    let l = degree_of(i);
                    let _ = gemm_acc(
                        column_block(g, i, n, cout, k),
                        Strided::row_major(vals.get(w), l * cout * cin, cout, cin),
                        acc,
                        i * cin,
                        k * cin,
                    );
                }
            }
            if let Some(acc) = gr.acc(w) {
                for i in 0..k {
                    let l = degree_of(i);
                    let _ = gemm_acc(
                        column_block(g, i, n, cout, k).t(),
                        column_block(vals.get(x), i, n, cin, k),
                        acc,
                        l * cout * cin,
                        cin,
                    );
                }
            }
            if let Some(b) = b {
                if let Some(acc) = gr.acc(b) {
                    for gn in g.chunks_exact(k * cout) {
                        for (a, v) in acc.iter_mut().zip(&gn[..cout]) {
                            *a += v;
                        }
                    }
                }
            }
        })),
    ))
}

/// Coefficient row `i` of `[n, k, c]` values: a `[n, c]` matrix with row step `k·c`.
fn column_block(data: &[f32], i: usize, n: usize, c: usize, k: usize) -> Strided<'_> {
    Strided {
        row_stride: k * c,
        ..Strided::row_major(data, i * c, n, c)
    }
}

/// `rms_norm_sh` on `x` `[n, (lmax+1)², c]` (`affine_weight` `[(lmax+1), c]`, `affine_bias`
/// `[c]`), as [`crate::layers::RmsNormSh::forward`].
pub fn rms_norm_sh(t: &mut Tape, s: &Scope<'_>, x: Var, lmax: usize, c: usize) -> Result<Var> {
    let w = t.param(s, "affine_weight", &[lmax + 1, c])?;
    let b = t.param(s, "affine_bias", &[c])?;
    let k = num_coefficients(lmax);
    let n = rows_of("RMS norm input", t.value(x).len(), k * c)?;
    let bw: Vec<f64> = (0..k).map(|i| balance_weight(i, lmax)).collect();
    // Per node: the centred input (f32, as the inference layer keeps it) and the scale.
    let mut centred = t.value(x).to_vec();
    let mut scales = Vec::with_capacity(n);
    let mut y = vec![0.0f32; n * k * c];
    let (wv, bv) = (t.value(w), t.value(b));
    for (node, yn) in centred
        .chunks_exact_mut(k * c)
        .zip(y.chunks_exact_mut(k * c))
    {
        let scale = rms_centre_and_scale(node, lmax, c);
        scales.push(scale);
        for i in 0..k {
            let l = degree_of(i);
            for ch in 0..c {
                let mut v = (f64::from(node[i * c + ch]) * scale) as f32 * wv[l * c + ch];
                if i == 0 {
                    v += bv[ch];
                }
                yn[i * c + ch] = v;
            }
        }
    }
    Ok(t.push(
        y,
        vec![n, k, c],
        &[x, w, b],
        Some(Box::new(move |vals, g, gr| {
            let wv = vals.get(w);
            if let Some(acc) = gr.acc(b) {
                for gn in g.chunks_exact(k * c) {
                    for (a, v) in acc.iter_mut().zip(&gn[..c]) {
                        *a += v;
                    }
                }
            }
            if let Some(acc) = gr.acc(w) {
                for ((gn, xn), s) in g
                    .chunks_exact(k * c)
                    .zip(centred.chunks_exact(k * c))
                    .zip(&scales)
                {
                    for i in 0..k {
                        let l = degree_of(i);
                        for ch in 0..c {
                            acc[l * c + ch] +=
                                (f64::from(gn[i * c + ch]) * f64::from(xn[i * c + ch]) * s) as f32;
                        }
                    }
                }
            }
            if let Some(acc) = gr.acc(x) {
                for ((gn, xn), (s, an)) in g
                    .chunks_exact(k * c)
                    .zip(centred.chunks_exact(k * c))
                    .zip(scales.iter().zip(acc.chunks_exact_mut(k * c)))
                {
                    // ds = Σ g·w·x̃; dx̃ = g·w·s − ds·s³·bw_i·x̃ / c.
                    let mut ds = 0.0f64;
                    for i in 0..k {
                        let l = degree_of(i);
                        for ch in 0..c {
                            ds += f64::from(gn[i * c + ch])
                                * f64::from(wv[l * c + ch])
                                * f64::from(xn[i * c + ch]);
                        }
                    }
                    let s3 = s * s * s;
                    let mut dx = vec![0.0f64; k * c];
                    for i in 0..k {
                        let l = degree_of(i);
                        for ch in 0..c {
                            dx[i * c + ch] =
                                f64::from(gn[i * c + ch]) * f64::from(wv[l * c + ch]) * s
                                    - ds * s3 * bw[i] * f64::from(xn[i * c + ch]) / c as f64;
                        }
                    }
                    // The l = 0 row was centred over channels.
                    let m = dx[..c].iter().sum::<f64>() / c as f64;
                    for v in &mut dx[..c] {
                        *v -= m;
                    }
                    for (a, v) in an.iter_mut().zip(&dx) {
                        *a += *v as f32;
                    }
                }
            }
        })),
    ))
}

/// LayerNorm over rows of `dim` values (`weight`, `bias` `[dim]`, eps 1e-5), as
/// [`crate::layers::LayerNorm::apply`].
pub fn layer_norm(t: &mut Tape, s: &Scope<'_>, x: Var, dim: usize) -> Result<Var> {
    let w = t.param(s, "weight", &[dim])?;
    let b = t.param(s, "bias", &[dim])?;
    rows_of("layer norm input", t.value(x).len(), dim)?;
    let (wv, bv) = (t.value(w), t.value(b));
    let mut xhat = Vec::with_capacity(t.value(x).len());
    let mut invs = Vec::new();
    let mut y = Vec::with_capacity(t.value(x).len());
    for row in t.value(x).chunks_exact(dim) {
        let n = dim as f64;
        let mean = row.iter().map(|v| f64::from(*v)).sum::<f64>() / n;
        let var = row
            .iter()
            .map(|v| (f64::from(*v) - mean).powi(2))
            .sum::<f64>()
            / n;
        let inv = 1.0 / (var + 1e-5).sqrt();
        invs.push(inv);
        for (i, v) in row.iter().enumerate() {
            let h = ((f64::from(*v) - mean) * inv) as f32;
            xhat.push(h);
            y.push(h * wv[i] + bv[i]);
        }
    }
    let shape = t.shape(x).to_vec();
    Ok(t.push(
        y,
        shape,
        &[x, w, b],
        Some(Box::new(move |vals, g, gr| {
            let wv = vals.get(w);
            if let Some(acc) = gr.acc(w) {
                for (gr_row, h) in g.chunks_exact(dim).zip(xhat.chunks_exact(dim)) {
                    for i in 0..dim {
                        acc[i] += gr_row[i] * h[i];
                    }
                }
            }
            if let Some(acc) = gr.acc(b) {
                for gr_row in g.chunks_exact(dim) {
                    for i in 0..dim {
                        acc[i] += gr_row[i];
                    }
                }
            }
            if let Some(acc) = gr.acc(x) {
                for ((gr_row, h), (inv, a)) in g
                    .chunks_exact(dim)
                    .zip(xhat.chunks_exact(dim))
                    .zip(invs.iter().zip(acc.chunks_exact_mut(dim)))
                {
                    let dh: Vec<f64> = (0..dim).map(|i| f64::from(gr_row[i] * wv[i])).collect();
                    let m1 = dh.iter().sum::<f64>() / dim as f64;
                    let m2 = dh
                        .iter()
                        .zip(h)
                        .map(|(d, h)| d * f64::from(*h))
                        .sum::<f64>()
                        / dim as f64;
                    for i in 0..dim {
                        a[i] += (inv * (dh[i] - m1 - f64::from(h[i]) * m2)) as f32;
                    }
                }
            }
        })),
    ))
}

#[cfg(test)]
pub(crate) mod tests {
    use super::*;
    use crate::autodiff::check::{finite_difference_check, FdOptions};
    use crate::init::{random_weights, ExtraSizes};
    use crate::layers::{LayerNorm, Linear, RmsNormSh, So3Linear};
    use crate::model::ModelConfig;
    use crate::weights::Weights;
    use rand::{Rng, SeedableRng};
    use rand_chacha::ChaCha8Rng;

    /// Random weights of a small whole model: every layer's parameters under its real key.
    pub(crate) fn small_weights() -> Weights {
        small_weights_of(crate::transblock::FilmKind::Hypernetwork)
    }

    /// As [`small_weights`] with the U-net's feed-forward networks conditioned by `film`.
    pub(crate) fn small_weights_of(film: crate::transblock::FilmKind) -> Weights {
        let mut cfg = ModelConfig::reference();
        cfg.film_kind = film;
        cfg.sphere_channels = vec![8, 8, 12, 16, 16];
        cfg.attn_hidden_channels = vec![8; 4];
        cfg.attn_alpha_channels = vec![4; 4];
        cfg.attn_value_channels = vec![2; 4];
        cfg.ffn_hidden_channels = vec![8; 4];
        cfg.field_nn_c = 8;
        let mut extra = ExtraSizes::reference();
        extra.edge_channels = vec![8; 4];
        extra.num_distance_basis = 16;
        extra.field_num_basis = 32;
        extra.film_dim = 16;
        extra.token_dim = 12;
        extra.lang_depth = 1;
        extra.lang_mlp = 16;
        cfg.lang_heads = 2;
        cfg.lang_dim_head = 4;
        random_weights(&cfg, &extra, 5)
    }

    pub(crate) fn random(n: usize, seed: u64) -> Vec<f32> {
        let mut rng = ChaCha8Rng::seed_from_u64(seed);
        (0..n).map(|_| rng.random_range(-1.5f32..1.5)).collect()
    }

    pub(crate) fn assert_close(a: &[f32], b: &[f32], tol: f32, what: &str) {
        assert_eq!(a.len(), b.len(), "{what}: lengths");
        for (i, (x, y)) in a.iter().zip(b).enumerate() {
            assert!(
                (x - y).abs() <= tol * (1.0 + y.abs()),
                "{what}[{i}]: {x} vs {y}"
            );
        }
    }

    pub(crate) fn assert_passes(r: &crate::autodiff::check::FdReport, what: &str) {
        assert!(
            r.passed(),
            "{what}: worst {:.3} at {} ({:?})",
            r.worst_ratio,
            r.worst,
            r.tensors
        );
    }

    const BLOCK: &str = "down_blocks.1.block.transblock.";

    #[test]
    fn linear_matches_inference_and_finite_differences() {
        let w = small_weights();
        let s = w.scope("type0_linear.");
        let x = random(7 * 3, 1);
        let want = Linear::load_sized(&s, 8, 3, true)
            .unwrap()
            .forward(&x)
            .unwrap();
        let mut t = Tape::new();
        let xv = t.variable(x.clone(), &[7, 3]).unwrap();
        let y = linear(&mut t, &s, xv, 8, 3, true).unwrap();
        assert_close(t.value(y), &want, 1e-6, "linear");
        let r = finite_difference_check(
            &w,
            "type0_linear.",
            &[(x, vec![7, 3])],
            FdOptions::default(),
            |t, s, v| linear(t, s, v[0], 8, 3, true),
        )
        .unwrap();
        assert_passes(&r, "linear");
        assert_eq!(r.tensors.len(), 3, "input, weight and bias checked");
    }

    #[test]
    fn so3_linear_matches_inference_and_finite_differences() {
        let w = small_weights();
        let p = format!("{BLOCK}ffn.so3_linear_2.");
        let s = w.scope(&p);
        let l = So3Linear::load(&s).unwrap();
        let x = random(5 * 16 * l.cin, 2);
        let want = l.forward(&x).unwrap();
        let mut t = Tape::new();
        let xv = t.variable(x.clone(), &[5, 16, l.cin]).unwrap();
        let y = so3_linear(&mut t, &s, xv).unwrap();
        assert_close(t.value(y), &want, 1e-5, "so3_linear");
        let r = finite_difference_check(
            &w,
            &p,
            &[(x, vec![5, 16, l.cin])],
            FdOptions::default(),
            |t, s, v| so3_linear(t, s, v[0]),
        )
        .unwrap();
        assert_passes(&r, "so3_linear");
    }

    #[test]
    fn rms_norm_sh_matches_inference_and_finite_differences() {
        let w = small_weights();
        let p = format!("{BLOCK}norm_2.");
        let s = w.scope(&p);
        let c = 8;
        let x = random(4 * 16 * c, 3);
        let want = RmsNormSh::load(&s, 3, c).unwrap().forward(&x).unwrap();
        let mut t = Tape::new();
        let xv = t.variable(x.clone(), &[4, 16, c]).unwrap();
        let y = rms_norm_sh(&mut t, &s, xv, 3, c).unwrap();
        assert_close(t.value(y), &want, 0.0, "rms_norm_sh");
        let opts = FdOptions {
            per_tensor: 12,
            ..FdOptions::default()
        };
        let r = finite_difference_check(&w, &p, &[(x, vec![4, 16, c])], opts, |t, s, v| {
            rms_norm_sh(t, s, v[0], 3, c)
        })
        .unwrap();
        assert_passes(&r, "rms_norm_sh");
    }

    #[test]
    fn layer_norm_matches_inference_and_finite_differences() {
        let w = small_weights();
        let p = format!("{BLOCK}ga.alpha_norm.");
        let s = w.scope(&p);
        let dim = 4;
        let x = random(6 * dim, 4);
        let mut want = x.clone();
        LayerNorm::load(&s, dim).unwrap().apply(&mut want);
        let mut t = Tape::new();
        let xv = t.variable(x.clone(), &[6, dim]).unwrap();
        let y = layer_norm(&mut t, &s, xv, dim).unwrap();
        assert_close(t.value(y), &want, 0.0, "layer_norm");
        let r = finite_difference_check(
            &w,
            &p,
            &[(x, vec![6, dim])],
            FdOptions::default(),
            |t, s, v| layer_norm(t, s, v[0], dim),
        )
        .unwrap();
        assert_passes(&r, "layer_norm");
    }

    #[test]
    fn generic_operations_pass_finite_differences() {
        let w = small_weights();
        let (a, b) = (random(6 * 4, 5), random(6 * 4, 6));
        let inputs = [(a, vec![6, 4]), (b, vec![6, 4])];
        let r = finite_difference_check(&w, "", &inputs, FdOptions::default(), |t, _, v| {
            let m = t.mul(v[0], v[1])?;
            let s = t.act(m, crate::autodiff::Act::Silu);
            let g = t.gather_rows(s, 4, &[5, 0, 0, 3])?;
            let sc = t.scatter_add_rows(g, 4, &[1, 1, 0, 2], 3)?;
            let left = t.slice_cols(sc, 4, 1..3)?;
            let e = t.act(left, crate::autodiff::Act::Gelu);
            let cat = t.concat_cols(e, 2, left, 2)?;
            let rot: std::sync::Arc<[f32]> = random(3 * 2 * 2, 7).into();
            let r = t.reshape(cat, &[3, 2, 2])?;
            let y = t.const_matmul(r, rot, (2, 2, 2))?;
            let z = t.act(y, crate::autodiff::Act::SmoothLeakyRelu(0.2));
            let q = t.act(z, crate::autodiff::Act::Sigmoid);
            let added = t.add(q, z)?;
            Ok(t.scale(added, 0.5))
        })
        .unwrap();
        assert_passes(&r, "generic operations");
    }

    #[test]
    fn s2_activations_match_inference_and_finite_differences() {
        use crate::grids::S2Grid;
        let w = small_weights();
        let c = 3;
        for grid in [
            S2Grid::reference(3, 2).unwrap(),
            S2Grid::gate(3, 2).unwrap(),
            S2Grid::reference(3, 3).unwrap(),
        ] {
            let nr = grid.reduced.len();
            let (x, gating) = (random(4 * nr * c, 8), random(4 * c, 9));
            let want = crate::layers::separable_s2_activation(&grid, &gating, &x, c).unwrap();
            let mut t = Tape::new();
            let xv = t.variable(x.clone(), &[4, nr, c]).unwrap();
            let gv = t.variable(gating.clone(), &[4, c]).unwrap();
            let y = t.separable_s2_activation(&grid, gv, xv, c).unwrap();
            assert_close(t.value(y), &want, 1e-5, "S2 activation");
            let inputs = [(x, vec![4, nr, c]), (gating, vec![4, c])];
            let r = finite_difference_check(&w, "", &inputs, FdOptions::default(), |t, _, v| {
                t.separable_s2_activation(&grid, v[1], v[0], c)
            })
            .unwrap();
            assert_passes(&r, "S2 activation");
        }
        let mut t = Tape::new();
        let x = t.variable(vec![0.0; 7], &[7]).unwrap();
        let m = t.act(x, crate::autodiff::Act::Mish);
        let g = t.backward(m, &[1.0; 7]).unwrap();
        assert!(
            (g.of(x).unwrap()[0] - 0.6).abs() < 1e-6,
            "mish'(0) = tanh(ln 2)"
        );
    }

    #[test]
    fn shared_parameters_accumulate_and_bad_shapes_are_errors() {
        let w = small_weights();
        let s = w.scope("type0_linear.");
        let mut t = Tape::new();
        let a = t.param(&s, "weight", &[8, 3]).unwrap();
        let b = t.param(&s, "weight", &[8, 3]).unwrap();
        assert_eq!(a, b, "one leaf per key");
        assert!(t.param(&s, "weight", &[3, 8]).is_err());
        let y = t.add(a, b).unwrap();
        let g = t.backward(y, &[1.0; 24]).unwrap();
        assert!(g.of(a).unwrap().iter().all(|v| *v == 2.0));
        assert!(t.backward(y, &[1.0; 3]).is_err());
        assert!(t.backward(y, &[f32::NAN; 24]).is_err());
        let x = t.constant(vec![0.0; 5], &[5]).unwrap();
        assert!(t.linear(x, a, None).is_err(), "5 values are not rows of 3");
        assert!(t.gather_rows(a, 3, &[8]).is_err());
    }
}
