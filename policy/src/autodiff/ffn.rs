//! Taped twins of the feed-forward network: the hypernetwork iFiLM (`SO3_FiLM_Linear`), the
//! paper's per-degree scalar iFiLM, and `FeedForwardNetwork` itself. Each reads its
//! parameters by the inference layer's names and computes the same values, so gradients
//! reach the FiLM weights and the condition (the language encoder is trained through it).

use super::layers::{linear, per_degree_linear, so3_linear};
use super::{Act, Tape, Var};
use crate::error::{PolicyError, Result};
use crate::grids::S2Grid;
use crate::layers::{degree_of, rows_of, scalar_film_modulate};
use crate::so3::num_coefficients;
use crate::transblock::FilmKind;
use crate::weights::Scope;

/// Sizes and conditioning of a taped feed-forward network.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct FeedForwardSizes {
    /// Maximum degree.
    pub lmax: usize,
    /// Input channels.
    pub cin: usize,
    /// Hidden channels.
    pub hidden: usize,
    /// Output channels.
    pub cout: usize,
    /// How the first linear reads the condition (`None`: plain `SO3_LinearV2`).
    pub film: Option<FilmKind>,
}

/// The number of conditions B (rows of `dim` values) and of nodes per condition, checking
/// that the nodes of `x` (rows of `row` values) split evenly over them.
fn batches(t: &Tape, x: Var, row: usize, condition: Var, dim: usize) -> Result<(usize, usize)> {
    let nodes = rows_of("FiLM input", t.value(x).len(), row)?;
    let b = rows_of("FiLM condition", t.value(condition).len(), dim)?;
    if b == 0 || nodes % b != 0 {
        return Err(PolicyError::ShapeMismatch {
            name: "FiLM input (nodes must split evenly over the batch)".into(),
            expected: vec![b, 0],
            got: vec![nodes],
        });
    }
    Ok((b, nodes / b))
}

/// Checks that the `SO3_LinearV2` `weight` of `s` is `[(lmax+1), cout, cin]`.
fn check_so3(s: &Scope<'_>, lmax: usize, cin: usize, cout: usize) -> Result<()> {
    let got = s.shape("weight", 3)?;
    if got != [lmax + 1, cout, cin] {
        return Err(PolicyError::ShapeMismatch {
            name: s.key("weight"),
            expected: vec![lmax + 1, cout, cin],
            got,
        });
    }
    Ok(())
}

/// `SO3_FiLM_Linear` on `x` `[B·N, (lmax+1)², cin]` (nodes grouped by condition) with
/// `condition` `[B, dim]`, as [`crate::layers::FilmLinear::forward`]: p =
/// `cond_encoder.1`(Mish(condition)); W = p[..nw]/√(max(lmax,1)·cin), bias = p[nw..]/10.
pub fn film_linear(
    t: &mut Tape,
    s: &Scope<'_>,
    x: Var,
    condition: Var,
    lmax: usize,
    cin: usize,
    cout: usize,
) -> Result<Var> {
    let es = s.sub("cond_encoder").sub("1");
    let dim = es.shape("weight", 2)?[1];
    let k = num_coefficients(lmax);
    let (b, per) = batches(t, x, k * cin, condition, dim)?;
    let nw = (lmax + 1) * cout * cin;
    let out = nw + cout;
    let m = t.act(condition, Act::Mish);
    let p = linear(t, &es, m, out, dim, true)?;
    let w_scale = 1.0 / ((lmax.max(1) * cin) as f32).sqrt();
    let mut y: Option<Var> = None;
    for batch in 0..b {
        let pb = if b == 1 {
            p
        } else {
            t.gather_rows(p, out, &[batch])?
        };
        let w = t.slice_cols(pb, out, 0..nw)?;
        let w = t.scale(w, w_scale);
        let bias = t.slice_cols(pb, out, nw..out)?;
        let bias = t.scale(bias, 0.1);
        if b == 1 {
            return per_degree_linear(t, x, w, Some(bias), (lmax, cin, cout));
        }
        // Each condition's generated weights act on its own nodes only.
        let rows: Vec<usize> = (batch * per..(batch + 1) * per).collect();
        let xb = t.gather_rows(x, k * cin, &rows)?;
        let yb = per_degree_linear(t, xb, w, Some(bias), (lmax, cin, cout))?;
        let placed = t.scatter_add_rows(yb, k * cout, &rows, b * per)?;
        y = Some(match y {
            None => placed,
            Some(acc) => t.add(acc, placed)?,
        });
    }
    let y = y.ok_or(PolicyError::ShapeMismatch {
        name: "FiLM condition (at least one)".into(),
        expected: vec![1, dim],
        got: vec![0, dim],
    })?;
    t.reshape(y, &[b * per, k, cout])
}

/// The paper's per-degree scalar iFiLM on `x` `[B·N, (lmax+1)², cin]` with `condition`
/// `[B, dim]`, as [`crate::layers::ScalarFilmLinear::forward`]: `SO3_LinearV2` (`weight`,
/// `bias`), then y_l ← (1 + m_l) ⊙ y_l and y_0 ← y_0 + γ with (m_0..m_lmax, γ) =
/// `film`(Mish(condition)).
pub fn scalar_film_linear(
    t: &mut Tape,
    s: &Scope<'_>,
    x: Var,
    condition: Var,
    lmax: usize,
    cin: usize,
    cout: usize,
) -> Result<Var> {
    check_so3(s, lmax, cin, cout)?;
    let fs = s.sub("film");
    let dim = fs.shape("weight", 2)?[1];
    let k = num_coefficients(lmax);
    batches(t, x, k * cin, condition, dim)?;
    let y = so3_linear(t, s, x)?;
    let mc = t.act(condition, Act::Mish);
    let m = linear(t, &fs, mc, (lmax + 2) * cout, dim, true)?;
    modulate(t, y, m, lmax, cout)
}

/// y `[B·N, (lmax+1)², cout]` modulated by m `[B, (lmax+2)·cout]` (one row per condition,
/// nodes grouped by condition), as [`crate::layers::ScalarFilmLinear`].
fn modulate(t: &mut Tape, y: Var, m: Var, lmax: usize, cout: usize) -> Result<Var> {
    let k = num_coefficients(lmax);
    let mw = (lmax + 2) * cout;
    let (b, per) = batches(t, y, k * cout, m, mw)?;
    let block = (per * k * cout).max(1);
    let mut out = t.value(y).to_vec();
    for (yb, mb) in out.chunks_mut(block).zip(t.value(m).chunks_exact(mw)) {
        scalar_film_modulate(yb, mb, lmax, cout);
    }
    let shape = vec![b * per, k, cout];
    Ok(t.push(
        out,
        shape,
        &[y, m],
        Some(Box::new(move |vals, g, gr| {
            let (yv, mv) = (vals.get(y), vals.get(m));
            if let Some(acc) = gr.acc(y) {
                for ((a, gb), mb) in acc
                    .chunks_mut(block)
                    .zip(g.chunks(block))
                    .zip(mv.chunks_exact(mw))
                {
                    for (idx, (ai, gi)) in a.iter_mut().zip(gb).enumerate() {
                        let (i, ch) = ((idx / cout) % k, idx % cout);
                        *ai += gi * (1.0 + mb[degree_of(i) * cout + ch]);
                    }
                }
            }
            if let Some(acc) = gr.acc(m) {
                for ((ab, gb), yb) in acc
                    .chunks_exact_mut(mw)
                    .zip(g.chunks(block))
                    .zip(yv.chunks(block))
                {
                    for (idx, (gi, yi)) in gb.iter().zip(yb).enumerate() {
                        let (i, ch) = ((idx / cout) % k, idx % cout);
                        ab[degree_of(i) * cout + ch] += gi * yi;
                        if i == 0 {
                            ab[(lmax + 1) * cout + ch] += gi;
                        }
                    }
                }
            }
        })),
    ))
}

/// `FeedForwardNetwork` on `x` `[n, (lmax+1)², cin]`, as
/// [`crate::transblock::FeedForward::forward`]: gating = `gating_linear`(l = 0 row);
/// u = `so3_linear_1` (plain or FiLM with `condition` `[B, dim]`); the separable S2
/// activation on `grid` (reference, finer or gated); `so3_linear_2`.
pub fn feed_forward(
    t: &mut Tape,
    s: &Scope<'_>,
    grid: &S2Grid,
    x: Var,
    condition: Option<Var>,
    sizes: FeedForwardSizes,
) -> Result<Var> {
    let FeedForwardSizes {
        lmax,
        cin,
        hidden,
        cout,
        film,
    } = sizes;
    if grid.lmax != lmax || grid.mmax != lmax {
        return Err(PolicyError::UnsupportedDegree {
            lmax: grid.lmax,
            mmax: grid.mmax,
            max_supported: lmax,
        });
    }
    let k = num_coefficients(lmax);
    rows_of("feed-forward input", t.value(x).len(), k * cin)?;
    let l0 = t.slice_cols(x, k * cin, 0..cin)?;
    let gating = linear(t, &s.sub("gating_linear"), l0, hidden, cin, true)?;
    let first = s.sub("so3_linear_1");
    let u = match (film, condition) {
        (None, _) => {
            check_so3(&first, lmax, cin, hidden)?;
            so3_linear(t, &first, x)?
        }
        (Some(FilmKind::Hypernetwork), Some(c)) => film_linear(t, &first, x, c, lmax, cin, hidden)?,
        (Some(FilmKind::PerDegreeScalar), Some(c)) => {
            scalar_film_linear(t, &first, x, c, lmax, cin, hidden)?
        }
        (Some(_), None) => {
            return Err(PolicyError::ShapeMismatch {
                name: "FiLM condition (required by this feed-forward network)".into(),
                expected: vec![1, 0],
                got: vec![0],
            })
        }
    };
    let u = t.separable_s2_activation(grid, gating, u, hidden)?;
    let second = s.sub("so3_linear_2");
    check_so3(&second, lmax, hidden, cout)?;
    so3_linear(t, &second, u)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::autodiff::check::{finite_difference_check, FdOptions};
    use crate::autodiff::layers::tests::{assert_close, assert_passes, random, small_weights_of};
    use crate::layers::{FilmLinear, ScalarFilmLinear, So3Linear};
    use crate::transblock::FeedForward;

    const FFN: &str = "down_blocks.1.block.transblock.ffn.";
    /// Sizes of `FFN` in the small model: lmax 3, 8 → hidden 8 → 12 channels, condition 16.
    const LMAX: usize = 3;
    const CIN: usize = 8;
    const HIDDEN: usize = 8;
    const COUT: usize = 12;
    const DIM: usize = 16;
    const K: usize = 16;

    fn sizes(film: Option<FilmKind>) -> FeedForwardSizes {
        FeedForwardSizes {
            lmax: LMAX,
            cin: CIN,
            hidden: HIDDEN,
            cout: COUT,
            film,
        }
    }

    #[test]
    fn film_linears_match_inference_and_finite_differences() {
        for kind in [FilmKind::Hypernetwork, FilmKind::PerDegreeScalar] {
            let w = small_weights_of(kind);
            let p = format!("{FFN}so3_linear_1.");
            let s = w.scope(&p);
            let build = |t: &mut Tape, s: &Scope<'_>, v: &[Var]| match kind {
                FilmKind::Hypernetwork => film_linear(t, s, v[0], v[1], LMAX, CIN, HIDDEN),
                FilmKind::PerDegreeScalar => {
                    scalar_film_linear(t, s, v[0], v[1], LMAX, CIN, HIDDEN)
                }
            };
            for b in [1, 2] {
                let (x, c) = (random(4 * K * CIN, 11), random(b * DIM, 12));
                let want = match kind {
                    FilmKind::Hypernetwork => FilmLinear::load(&s, LMAX, CIN, HIDDEN)
                        .unwrap()
                        .forward(&x, &c),
                    FilmKind::PerDegreeScalar => {
                        ScalarFilmLinear::load(&s).unwrap().forward(&x, &c)
                    }
                }
                .unwrap();
                let mut t = Tape::new();
                let xv = t.variable(x.clone(), &[4, K, CIN]).unwrap();
                let cv = t.variable(c.clone(), &[b, DIM]).unwrap();
                let y = build(&mut t, &s, &[xv, cv]).unwrap();
                assert_eq!(t.shape(y), &[4, K, HIDDEN]);
                assert_close(t.value(y), &want, 1e-5, &format!("{kind:?} B = {b}"));
                let inputs = [(x, vec![4, K, CIN]), (c, vec![b, DIM])];
                let r =
                    finite_difference_check(&w, &p, &inputs, FdOptions::default(), build).unwrap();
                assert_passes(&r, &format!("{kind:?} B = {b}"));
                let params = if kind == FilmKind::Hypernetwork { 2 } else { 4 };
                assert_eq!(r.tensors.len(), 2 + params, "{:?}", r.tensors);
            }
        }
    }

    #[test]
    fn feed_forwards_match_inference_and_finite_differences() {
        // The plain network is the rotation head's (lmax 4, 8 → 8 → 8, no FiLM).
        let plain = FeedForwardSizes {
            lmax: crate::heads::ROT_LMAX,
            cout: CIN,
            ..sizes(None)
        };
        let cases = [
            (None, "rot_field_layer.0.ffn.", plain),
            (
                Some(FilmKind::Hypernetwork),
                FFN,
                sizes(Some(FilmKind::Hypernetwork)),
            ),
            (
                Some(FilmKind::PerDegreeScalar),
                FFN,
                sizes(Some(FilmKind::PerDegreeScalar)),
            ),
        ];
        for (film, prefix, sz) in cases {
            let w = small_weights_of(film.unwrap_or_default());
            let s = w.scope(prefix);
            let k = num_coefficients(sz.lmax);
            for grid in [
                S2Grid::reference(sz.lmax, sz.lmax).unwrap(),
                S2Grid::gate(sz.lmax, sz.lmax).unwrap(),
            ] {
                let what = format!("{film:?}, gated {}", grid.gated);
                let (x, c) = (random(3 * k * sz.cin, 13), random(DIM, 14));
                let inference = FeedForward::load_with_grid(
                    &s,
                    sz.lmax,
                    sz.cin,
                    sz.hidden,
                    sz.cout,
                    film,
                    grid.clone(),
                )
                .unwrap();
                let want = inference.forward(&x, Some(&c)).unwrap();
                let mut t = Tape::new();
                let xv = t.variable(x.clone(), &[3, k, sz.cin]).unwrap();
                let cv = t.variable(c.clone(), &[1, DIM]).unwrap();
                let y = feed_forward(&mut t, &s, &grid, xv, Some(cv), sz).unwrap();
                assert_close(t.value(y), &want, 1e-5, &what);
                let inputs = [(x, vec![3, k, sz.cin]), (c, vec![1, DIM])];
                let r = finite_difference_check(
                    &w,
                    prefix,
                    &inputs,
                    FdOptions::default(),
                    |t, s, v| feed_forward(t, s, &grid, v[0], Some(v[1]), sz),
                )
                .unwrap();
                assert_passes(&r, &what);
            }
        }
    }

    #[test]
    fn zero_modulation_is_the_plain_linear_and_bad_conditions_are_errors() {
        let mut w = small_weights_of(FilmKind::PerDegreeScalar);
        let p = format!("{FFN}so3_linear_1.");
        for name in ["film.weight", "film.bias"] {
            w.f32_mut(&format!("{p}{name}"))
                .unwrap()
                .iter_mut()
                .for_each(|v| *v = 0.0);
        }
        let s = w.scope(&p);
        let x = random(2 * K * CIN, 15);
        let plain = So3Linear::load(&s).unwrap().forward(&x).unwrap();
        let film = ScalarFilmLinear::load(&s).unwrap();
        assert_eq!(film.forward(&x, &random(DIM, 16)).unwrap(), plain);
        assert!(film.forward(&x, &random(DIM - 1, 16)).is_err());
        assert!(
            film.forward(&x, &random(3 * DIM, 16)).is_err(),
            "2 nodes, 3 conditions"
        );
        let ffn = FeedForward::load(
            &w.scope(FFN),
            LMAX,
            CIN,
            HIDDEN,
            COUT,
            Some(FilmKind::PerDegreeScalar),
        )
        .unwrap();
        assert_eq!(ffn.condition_dim(), Some(DIM));
        assert!(ffn.forward(&x, None).is_err(), "the condition is required");
        let mut t = Tape::new();
        let xv = t.variable(x, &[2, K, CIN]).unwrap();
        let grid = S2Grid::gate(LMAX, LMAX).unwrap();
        let sz = sizes(Some(FilmKind::PerDegreeScalar));
        assert!(feed_forward(&mut t, &w.scope(FFN), &grid, xv, None, sz).is_err());
        let bad = t.variable(random(3 * DIM, 17), &[3, DIM]).unwrap();
        assert!(feed_forward(&mut t, &w.scope(FFN), &grid, xv, Some(bad), sz).is_err());
        let wrong = FeedForwardSizes { cout: 5, ..sz };
        let c = t.variable(random(DIM, 18), &[1, DIM]).unwrap();
        assert!(feed_forward(&mut t, &w.scope(FFN), &grid, xv, Some(c), wrong).is_err());
        let coarse = S2Grid::gate(LMAX, 2).unwrap();
        assert!(feed_forward(&mut t, &w.scope(FFN), &coarse, xv, Some(c), sz).is_err());
    }
}
