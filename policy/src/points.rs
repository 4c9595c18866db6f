//! Point-set operations of the U-net: farthest point sampling, k nearest neighbours, the
//! spherical-coefficient max-pool and the 3-NN up-sampling.
//!
//! Spec: fixtures README, "Pool and upsample" and "Edges"; `equact.md`, "U-net". FPS uses
//! squared L2 distance, starts at index 0 and returns its picks sorted ascending. kNN returns
//! each query's neighbours by increasing distance, ties broken by index (a stable sort, as the
//! reference). The up-sampling weights use the L1 distance in parity mode (as the reference
//! code) and the Euclidean distance in equivariant mode.

use crate::error::{PolicyError, Result};
use crate::layers::check_indices;

/// Checks that every coordinate is finite.
pub fn check_finite(what: &'static str, pos: &[[f32; 3]]) -> Result<()> {
    for (index, p) in pos.iter().enumerate() {
        if !p.iter().all(|v| v.is_finite()) {
            return Err(PolicyError::NonFinitePoint {
                what,
                index,
                value: *p,
            });
        }
    }
    Ok(())
}

fn dist2(a: &[f32; 3], b: &[f32; 3]) -> f32 {
    let dx = a[0] - b[0];
    let dy = a[1] - b[1];
    let dz = a[2] - b[2];
    dx * dx + dy * dy + dz * dz
}

/// Farthest point sampling of `count` points, starting at index 0; indices sorted ascending.
/// The textbook loop's samples (the first farthest point wins ties, as torch's argmax), from
/// [`cell_types::fps`], whose buckets skip the distance updates that cannot change anything.
pub fn farthest_point_sampling(pos: &[[f32; 3]], count: usize) -> Result<Vec<usize>> {
    check_finite("farthest point sampling", pos)?;
    if count == 0 || count > pos.len() {
        return Err(PolicyError::TooFewPoints {
            what: "farthest point sampling",
            needed: count.max(1),
            got: pos.len(),
        });
    }
    let all: Vec<usize> = (0..pos.len()).collect();
    let mut picks = cell_types::fps::farthest_point_sample(pos, &all, count, 0);
    picks.sort_unstable();
    Ok(picks)
}

/// For each query, the indices of its `k` nearest points (fewer if there are fewer points),
/// sorted by increasing squared distance, ties by index.
pub fn knn(points: &[[f32; 3]], queries: &[[f32; 3]], k: usize) -> Result<Vec<Vec<usize>>> {
    knn_threads(points, queries, k, 1)
}

/// [`knn`] with the queries split over `threads` threads (at least 64 queries each): the
/// same neighbours.
pub fn knn_threads(
    points: &[[f32; 3]],
    queries: &[[f32; 3]],
    k: usize,
    threads: usize,
) -> Result<Vec<Vec<usize>>> {
    crate::parallel::map_ranges(queries.len(), threads.min(queries.len() / 64), |r| {
        knn_serial(points, &queries[r], k)
    })
}

/// [`knn`] on the calling thread.
fn knn_serial(points: &[[f32; 3]], queries: &[[f32; 3]], k: usize) -> Result<Vec<Vec<usize>>> {
    check_finite("knn points", points)?;
    check_finite("knn queries", queries)?;
    if points.is_empty() {
        return Err(PolicyError::TooFewPoints {
            what: "knn",
            needed: 1,
            got: 0,
        });
    }
    let k = k.min(points.len());
    let mut dist: Vec<f32> = Vec::with_capacity(points.len());
    let mut order: Vec<(f32, usize)> = Vec::with_capacity(points.len());
    let mut heap: std::collections::BinaryHeap<(u32, usize)> =
        std::collections::BinaryHeap::with_capacity(k + 1);
    Ok(queries
        .iter()
        .map(|q| {
            if k == 0 {
                return Vec::new();
            }
            if k > HEAP_SELECT_MAX {
                // Partial selection, then a stable order of the kept k.
                order.clear();
                order.extend(points.iter().enumerate().map(|(i, p)| (dist2(p, q), i)));
                if k < order.len() {
                    order.select_nth_unstable_by(k - 1, |a, b| {
                        a.0.total_cmp(&b.0).then(a.1.cmp(&b.1))
                    });
                    order.truncate(k);
                }
                order.sort_unstable_by(|a, b| a.0.total_cmp(&b.0).then(a.1.cmp(&b.1)));
                return order.iter().map(|&(_, i)| i).collect();
            }
            // The k smallest (distance, index) pairs in a max-heap while the distances are
            // scanned in index order: once it is full, a point at or beyond the worst kept
            // distance cannot enter (an equal distance loses on its larger index), one
            // float compare for nearly every point.
            dist.clear();
            dist.extend(points.iter().map(|p| dist2(p, q)));
            heap.clear();
            for (i, &d) in dist.iter().enumerate().take(k) {
                heap.push((distance_key(d), i));
            }
            let mut worst = heap.peek().map_or(f32::INFINITY, |w| dist[w.1]);
            for (i, &d) in dist.iter().enumerate().skip(k) {
                // (A NaN cannot arise from the finite points checked above; were it to, it
                // would sort last, so it must not enter either.)
                if d >= worst || d.is_nan() {
                    continue;
                }
                if let Some(mut top) = heap.peek_mut() {
                    *top = (distance_key(d), i);
                }
                worst = heap.peek().map_or(f32::INFINITY, |w| dist[w.1]);
            }
            let mut kept = std::mem::take(&mut heap).into_sorted_vec();
            let out = kept.iter().map(|&(_, i)| i).collect();
            kept.clear();
            heap = kept.into();
            out
        })
        .collect())
}

/// Largest neighbour count [`knn`] keeps in a heap while it scans; above it, a selection
/// over all the distances is faster (measured: 16 neighbours of 2048 points 1.3-1.5× faster
/// by the heap, 100 neighbours 2× slower).
const HEAP_SELECT_MAX: usize = 32;

/// A squared distance as an integer of the same order as `f32::total_cmp`'s.
fn distance_key(d: f32) -> u32 {
    let bits = d.to_bits();
    // Negative values reversed and below the positive ones (a sum of squares is never
    // negative, not even −0, so the scan's float compare agrees with this order).
    if bits >> 31 == 1 {
        !bits
    } else {
        bits | (1 << 31)
    }
}

/// The spherical-coefficient max-pool (`CoefficientMaxPool`): for every centre, degree l and
/// channel, the neighbour whose degree-l block has the largest sum of squares (first on ties)
/// supplies that whole block.
///
/// `x` is [n, (lmax+1)², c]; returns [neighbours.len(), (lmax+1)², c].
pub fn coefficient_max_pool(
    x: &[f32],
    n: usize,
    lmax: usize,
    c: usize,
    neighbours: &[Vec<usize>],
) -> Result<Vec<f32>> {
    coefficient_max_pool_threads(x, n, lmax, c, neighbours, 1)
}

/// [`coefficient_max_pool`] with the choices made on up to `threads` threads (runs of
/// centres): the same values for any count.
pub fn coefficient_max_pool_threads(
    x: &[f32],
    n: usize,
    lmax: usize,
    c: usize,
    neighbours: &[Vec<usize>],
    threads: usize,
) -> Result<Vec<f32>> {
    let nc = crate::so3::num_coefficients(lmax);
    let choice = coefficient_max_pool_choices_threads(x, n, lmax, c, neighbours, threads)?;
    let mut out = vec![0.0f32; neighbours.len() * nc * c];
    for m in 0..neighbours.len() {
        for l in 0..=lmax {
            for ch in 0..c {
                let j = choice[(m * (lmax + 1) + l) * c + ch];
                if j == usize::MAX {
                    continue;
                }
                for i in l * l..(l + 1) * (l + 1) {
                    out[(m * nc + i) * c + ch] = x[(j * nc + i) * c + ch];
                }
            }
        }
    }
    Ok(out)
}

/// The choices of [`coefficient_max_pool`]: for every centre, degree and channel, the index
/// of the neighbour that supplies the block (`usize::MAX` for a centre without neighbours:
/// its blocks stay zero), `[neighbours.len(), lmax + 1, c]`. A choice
/// between blocks of near-equal norm is a discontinuity of the network.
pub fn coefficient_max_pool_choices(
    x: &[f32],
    n: usize,
    lmax: usize,
    c: usize,
    neighbours: &[Vec<usize>],
) -> Result<Vec<usize>> {
    coefficient_max_pool_choices_threads(x, n, lmax, c, neighbours, 1)
}

/// Centres per thread below which [`coefficient_max_pool_choices_threads`] stays on one.
const POOL_CENTRES_PER_THREAD: usize = 64;

/// [`coefficient_max_pool_choices`] on up to `threads` threads (runs of centres): the same
/// choices for any count.
pub fn coefficient_max_pool_choices_threads(
    x: &[f32],
    n: usize,
    lmax: usize,
    c: usize,
    neighbours: &[Vec<usize>],
    threads: usize,
) -> Result<Vec<usize>> {
    let nc = crate::so3::num_coefficients(lmax);
    if x.len() != n * nc * c {
        return Err(PolicyError::ShapeMismatch {
            name: "max-pool features".into(),
            expected: vec![n, nc, c],
            got: vec![x.len()],
        });
    }
    check_indices("max-pool neighbours", neighbours.iter().flatten(), n)?;
    let slots = (lmax + 1) * c;
    let parts = threads.min(neighbours.len() / POOL_CENTRES_PER_THREAD);
    crate::parallel::map_ranges(neighbours.len(), parts, |centres| {
        let mut out = Vec::with_capacity(centres.len() * slots);
        let mut best = vec![0.0f32; slots];
        let mut norm = vec![0.0f32; c];
        for nb in &neighbours[centres] {
            let first = out.len();
            out.resize(first + slots, usize::MAX);
            let choice = &mut out[first..];
            // Neighbours in order, each block's sum of squares over its coefficients in
            // order, all channels at once (contiguous); the first neighbour is taken, a later
            // one only when strictly larger (first on ties, a NaN never replaces).
            for (t, &j) in nb.iter().enumerate() {
                for l in 0..=lmax {
                    norm.fill(0.0);
                    for i in l * l..(l + 1) * (l + 1) {
                        let row = &x[(j * nc + i) * c..(j * nc + i + 1) * c];
                        for (s, v) in norm.iter_mut().zip(row) {
                            *s += v * v;
                        }
                    }
                    let (bs, bj) = (
                        &mut best[l * c..(l + 1) * c],
                        &mut choice[l * c..(l + 1) * c],
                    );
                    for ((b, j_best), &s) in bs.iter_mut().zip(bj.iter_mut()).zip(&norm) {
                        if t == 0 || s > *b {
                            *b = s;
                            *j_best = j;
                        }
                    }
                }
            }
        }
        Ok(out)
    })
}

/// Which distance the up-sampling weights use.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum UpsampleDistance {
    /// L1 (Manhattan), as the reference code: not rotation invariant.
    L1,
    /// Euclidean: rotation invariant (equivariant mode).
    Euclidean,
}

/// Up-sampling weights w_k = 1/(d_k + 1e-8), normalised, for each point's neighbours among
/// `centres` (indices into `centre_pos`).
pub fn upsample_weights(
    pos: &[[f32; 3]],
    centre_pos: &[[f32; 3]],
    neighbours: &[Vec<usize>],
    distance: UpsampleDistance,
) -> Result<Vec<Vec<f32>>> {
    let mut out = Vec::with_capacity(pos.len());
    for (p, nb) in pos.iter().zip(neighbours) {
        let mut w = Vec::with_capacity(nb.len());
        for &j in nb {
            let q = centre_pos.get(j).ok_or(PolicyError::IndexOutOfRange {
                name: "up-sampling neighbours".into(),
                value: j as i64,
                len: centre_pos.len(),
            })?;
            let d = match distance {
                UpsampleDistance::L1 => {
                    (p[0] - q[0]).abs() + (p[1] - q[1]).abs() + (p[2] - q[2]).abs()
                }
                UpsampleDistance::Euclidean => dist2(p, q).sqrt(),
            };
            w.push(1.0 / (d + 1e-8));
        }
        let s: f32 = w.iter().sum();
        w.iter_mut().for_each(|v| *v /= s);
        out.push(w);
    }
    Ok(out)
}

/// `out[i] = sum_k w[i][k] · coarse[neighbours[i][k]]` for features [m, nc, c] -> [n, nc, c].
pub fn upsample(
    coarse: &[f32],
    m: usize,
    row: usize,
    neighbours: &[Vec<usize>],
    weights: &[Vec<f32>],
) -> Result<Vec<f32>> {
    if coarse.len() != m * row {
        return Err(PolicyError::ShapeMismatch {
            name: "up-sampling features".into(),
            expected: vec![m, row],
            got: vec![coarse.len()],
        });
    }
    let mut out = vec![0.0f32; neighbours.len() * row];
    for (i, (nb, w)) in neighbours.iter().zip(weights).enumerate() {
        let o = &mut out[i * row..(i + 1) * row];
        for (&j, &wk) in nb.iter().zip(w) {
            if j >= m {
                return Err(PolicyError::IndexOutOfRange {
                    name: "up-sampling neighbours".into(),
                    value: j as i64,
                    len: m,
                });
            }
            for (ov, cv) in o.iter_mut().zip(&coarse[j * row..(j + 1) * row]) {
                *ov += wk * cv;
            }
        }
    }
    Ok(out)
}
