//! Taped twins of the U-net's point-set operations: the spherical-coefficient max-pool
//! ([`crate::points::coefficient_max_pool`]) and the 3-NN up-sampling
//! ([`crate::points::upsample`]).

use std::sync::Arc;

use super::{Tape, Var};
use crate::error::{PolicyError, Result};
use crate::points::coefficient_max_pool_choices;
use crate::so3::num_coefficients;

/// The max-pool of `x` `[n, (lmax+1)², c]` onto `neighbours.len()` centres: per centre,
/// degree and channel the neighbour whose degree-l block has the largest norm supplies it.
/// The choices are made in the forward pass (as the inference) and the gradient flows to
/// the chosen blocks only; a centre without neighbours gets zeros.
pub fn coefficient_max_pool(
    t: &mut Tape,
    x: Var,
    n: usize,
    lmax: usize,
    c: usize,
    neighbours: &[Vec<usize>],
) -> Result<Var> {
    let nc = num_coefficients(lmax);
    // The inference's own choice function, so ties and shape errors are decided alike.
    let choice: Arc<[usize]> =
        coefficient_max_pool_choices(t.value(x), n, lmax, c, neighbours)?.into();
    let m = neighbours.len();
    // (output offset, input offset) of every copied value.
    let mut pairs = Vec::with_capacity(m * nc * c);
    for centre in 0..m {
        for l in 0..=lmax {
            for ch in 0..c {
                let j = choice[(centre * (lmax + 1) + l) * c + ch];
                if j == usize::MAX {
                    continue;
                }
                for i in l * l..(l + 1) * (l + 1) {
                    pairs.push(((centre * nc + i) * c + ch, (j * nc + i) * c + ch));
                }
            }
        }
    }
    let xv = t.value(x);
    let mut y = vec![0.0f32; m * nc * c];
    for &(o, i) in &pairs {
        y[o] = xv[i];
    }
    Ok(t.push(
        y,
        vec![m, nc, c],
        &[x],
        Some(Box::new(move |_, g, gr| {
            if let Some(acc) = gr.acc(x) {
                for &(o, i) in &pairs {
                    acc[i] += g[o];
                }
            }
        })),
    ))
}

/// The up-sampling `out[i] = Σ_k weights[i][k] · x[neighbours[i][k]]` of `x` `[m, row]`
/// (rows of `row` values) to `[neighbours.len(), row]`; the weights (from
/// [`crate::points::upsample_weights`]) are constants.
pub fn upsample(
    t: &mut Tape,
    x: Var,
    m: usize,
    row: usize,
    neighbours: &[Vec<usize>],
    weights: &[Vec<f32>],
) -> Result<Var> {
    // The inference zips these silently; on the tape a mismatch is a caller's error.
    if neighbours.len() != weights.len()
        || neighbours
            .iter()
            .zip(weights)
            .any(|(a, b)| a.len() != b.len())
    {
        return Err(PolicyError::ShapeMismatch {
            name: "up-sampling weights (one per neighbour)".into(),
            expected: neighbours.iter().map(Vec::len).collect(),
            got: weights.iter().map(Vec::len).collect(),
        });
    }
    // The inference function checks the shape and the indices and gives the same values.
    let y = crate::points::upsample(t.value(x), m, row, neighbours, weights)?;
    let nb: Arc<[Vec<usize>]> = neighbours.into();
    let w: Arc<[Vec<f32>]> = weights.into();
    Ok(t.push(
        y,
        vec![neighbours.len(), row],
        &[x],
        Some(Box::new(move |_, g, gr| {
            if let Some(acc) = gr.acc(x) {
                for (i, (nbi, wi)) in nb.iter().zip(w.iter()).enumerate() {
                    let gi = &g[i * row..(i + 1) * row];
                    for (&j, &wk) in nbi.iter().zip(wi) {
                        for (a, v) in acc[j * row..(j + 1) * row].iter_mut().zip(gi) {
                            *a += wk * v;
                        }
                    }
                }
            }
        })),
    ))
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::autodiff::check::{finite_difference_check, FdOptions};
    use crate::autodiff::layers::tests::random;
    use crate::autodiff::layers::tests::small_weights;
    use crate::points::{knn, upsample_weights, UpsampleDistance};

    fn points(n: usize, seed: u64) -> Vec<[f32; 3]> {
        random(3 * n, seed)
            .chunks_exact(3)
            .map(|p| [p[0], p[1], p[2]])
            .collect()
    }

    /// The smallest gap between the largest and any other block sum of squares over all
    /// centres, degrees and channels (a centre with one distinct neighbour has no gap).
    fn min_gap(x: &[f32], lmax: usize, c: usize, neighbours: &[Vec<usize>]) -> f32 {
        let nc = num_coefficients(lmax);
        let mut gap = f32::INFINITY;
        for nb in neighbours {
            for l in 0..=lmax {
                for ch in 0..c {
                    let mut s: Vec<(f32, usize)> = nb
                        .iter()
                        .map(|&j| {
                            let v = (l * l..(l + 1) * (l + 1))
                                .map(|i| x[(j * nc + i) * c + ch].powi(2))
                                .sum();
                            (v, j)
                        })
                        .collect();
                    s.sort_by(|a, b| b.0.total_cmp(&a.0));
                    if let Some(other) = s.iter().find(|o| o.1 != s[0].1) {
                        gap = gap.min(s[0].0 - other.0);
                    }
                }
            }
        }
        gap
    }

    #[test]
    fn coefficient_max_pool_matches_inference_and_finite_differences() {
        let w = small_weights();
        let (n, lmax, c) = (7, 2, 3);
        let nc = num_coefficients(lmax);
        let pos = points(n, 21);
        let centres: Vec<[f32; 3]> = [0, 3, 5].iter().map(|&i| pos[i]).collect();
        let mut neighbours = knn(&pos, &centres, 3).unwrap();
        neighbours.push(Vec::new());
        // A perturbation of ε = 1e-2 changes a block's sum of squares by at most
        // 2·1.5·ε + ε² < 0.04: a seed whose choices are further apart than twice that keeps
        // every choice fixed under the check, where the pool is linear.
        let x = (30..)
            .map(|seed| random(n * nc * c, seed))
            .find(|x| min_gap(x, lmax, c, &neighbours) > 0.1)
            .unwrap();
        let want = crate::points::coefficient_max_pool(&x, n, lmax, c, &neighbours).unwrap();
        let mut t = Tape::new();
        let xv = t.variable(x.clone(), &[n, nc, c]).unwrap();
        let y = coefficient_max_pool(&mut t, xv, n, lmax, c, &neighbours).unwrap();
        assert_eq!(t.value(y), want.as_slice(), "a copy: bit for bit");
        assert_eq!(t.shape(y), &[4, nc, c]);
        let r = finite_difference_check(
            &w,
            "",
            &[(x, vec![n, nc, c])],
            FdOptions {
                per_tensor: 40,
                ..FdOptions::default()
            },
            |t, _, v| coefficient_max_pool(t, v[0], n, lmax, c, &neighbours),
        )
        .unwrap();
        assert!(r.passed(), "worst {:.3} at {}", r.worst_ratio, r.worst);
        // Every chosen block gets exactly its output gradient; the others get none.
        let g = t.backward(y, &vec![1.0; 4 * nc * c]).unwrap();
        let total: f32 = g.of(xv).unwrap().iter().sum();
        assert_eq!(total, (3 * nc * c) as f32);
    }

    #[test]
    fn upsample_matches_inference_and_finite_differences() {
        let w = small_weights();
        let (m, n, row) = (4, 6, 5);
        let coarse = points(m, 22);
        let fine = points(n, 23);
        let neighbours = knn(&coarse, &fine, 3).unwrap();
        let weights =
            upsample_weights(&fine, &coarse, &neighbours, UpsampleDistance::Euclidean).unwrap();
        let x = random(m * row, 24);
        let want = crate::points::upsample(&x, m, row, &neighbours, &weights).unwrap();
        let mut t = Tape::new();
        let xv = t.variable(x.clone(), &[m, row]).unwrap();
        let y = upsample(&mut t, xv, m, row, &neighbours, &weights).unwrap();
        assert_eq!(t.value(y), want.as_slice(), "same sums in the same order");
        let r = finite_difference_check(
            &w,
            "",
            &[(x, vec![m, row])],
            FdOptions {
                per_tensor: 20,
                ..FdOptions::default()
            },
            |t, _, v| upsample(t, v[0], m, row, &neighbours, &weights),
        )
        .unwrap();
        assert!(r.passed(), "worst {:.3} at {}", r.worst_ratio, r.worst);
    }

    #[test]
    fn bad_pool_and_upsample_inputs_are_errors() {
        let mut t = Tape::new();
        let x = t.variable(vec![0.5; 2 * 4 * 2], &[2, 4, 2]).unwrap();
        assert!(coefficient_max_pool(&mut t, x, 2, 1, 2, &[vec![0, 2]]).is_err());
        assert!(coefficient_max_pool(&mut t, x, 3, 1, 2, &[vec![0]]).is_err());
        assert!(upsample(&mut t, x, 2, 8, &[vec![0, 1]], &[vec![1.0]]).is_err());
        assert!(upsample(&mut t, x, 2, 8, &[vec![2]], &[vec![1.0]]).is_err());
        assert!(upsample(&mut t, x, 3, 8, &[vec![0]], &[vec![1.0]]).is_err());
        assert!(upsample(&mut t, x, 2, 8, &[vec![1]], &[vec![1.0]]).is_ok());
    }
}
