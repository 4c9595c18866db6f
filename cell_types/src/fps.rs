//! Farthest point sampling with buckets: the same samples as the textbook O(N k) loop, with
//! most of its distance updates skipped. Shared by the perception pipeline (`calibration`'s
//! fusion samples the fused cloud) and the policy (its input and U-net levels), which both
//! need the textbook loop's exact samples.
//!
//! The textbook loop keeps each candidate's squared distance `d` to the nearest sample and,
//! for every new sample `c`, lowers `d[j]` to `|p_j - c|^2` where that is smaller, then takes
//! the first candidate with the largest `d` as the next sample. Here the candidates are
//! counting-sorted into the cells of a grid; each occupied cell ("bucket") keeps the box
//! around its points and the largest `d` among them. A bucket whose box lies at least that
//! far (squared) from `c` cannot have a point that gets closer, so it is skipped. The check
//! is exact in f32: for a point inside the box, each coordinate difference to `c` is at
//! least the box's gap on that axis, and rounded subtraction, squaring and addition are
//! monotonic, so the point's computed squared distance is at least the box's computed one.
//! Moreover the new sample was the farthest candidate, so no candidate's `d` exceeds its
//! own: only the grid cells within that distance of it are visited. As sampling proceeds,
//! that distance shrinks and each sample touches a few buckets near it; a tournament tree
//! over the buckets gives the next farthest candidate.
//!
//! Ties go to the first candidate, as in the textbook loop: within a bucket the points keep
//! their candidate order, and buckets compare their best candidate's index on equal
//! distances.

/// Target number of candidates per grid cell (of the box around all candidates). Clouds
/// of surfaces occupy a small fraction of the cells, so occupied buckets hold more.
/// Benchmark cloud (35 k candidates inside the focus box): 2, 4, 8, 16 take 7.2, 5.9, 5.0,
/// 4.4 ms CPU for the whole `sample`.
const POINTS_PER_CELL: usize = 16;

/// The most grid cells (the counting sort's offsets).
const MAX_CELLS: usize = 1 << 20;

/// Farthest point sampling of `count` of `candidates` (indices into `xyz`, each below
/// `xyz.len()`) from candidate number `first`: the chosen indices into `xyz`, in the order
/// chosen. At most `candidates.len()` of them; none when `first` is not a candidate number.
/// Each next point is the first candidate farthest (squared distance in f32, x² + y² + z²
/// of the differences) from those chosen: the textbook loop's samples
/// ([`farthest_point_sample_textbook`]).
pub fn farthest_point_sample<P: Copy + Into<[f32; 3]>>(
    xyz: &[P],
    candidates: &[usize],
    count: usize,
    first: usize,
) -> Vec<usize> {
    let Some(count) = feasible(candidates, count, first) else {
        return Vec::new();
    };
    let finite = candidates
        .iter()
        .all(|&i| xyz[i].into().iter().all(|v| v.is_finite()));
    if !finite {
        // The box test needs finite coordinates; NaN points keep the textbook behaviour.
        return farthest_point_sample_textbook(xyz, candidates, count, first);
    }
    let b = Buckets::new(xyz, candidates);
    b.sample(xyz, candidates, count, first)
}

/// The number of samples to draw (at most every candidate), or None when there is nothing
/// to sample: no count, or `first` not a candidate number.
fn feasible(candidates: &[usize], count: usize, first: usize) -> Option<usize> {
    let count = count.min(candidates.len());
    (count > 0 && first < candidates.len()).then_some(count)
}

/// The textbook loop of [`farthest_point_sample`] (its reference, and its path for clouds
/// with non-finite points), with the same arguments and results.
pub fn farthest_point_sample_textbook<P: Copy + Into<[f32; 3]>>(
    xyz: &[P],
    candidates: &[usize],
    count: usize,
    first: usize,
) -> Vec<usize> {
    let Some(count) = feasible(candidates, count, first) else {
        return Vec::new();
    };
    let mut dist = vec![f32::INFINITY; candidates.len()];
    let mut out = Vec::with_capacity(count);
    let mut current = first;
    for _ in 0..count {
        out.push(candidates[current]);
        let c: [f32; 3] = xyz[candidates[current]].into();
        let mut far = 0;
        let mut far_d = -1.0f32;
        for (j, d) in dist.iter_mut().enumerate() {
            let dj = dist2(xyz[candidates[j]].into(), c);
            if dj < *d {
                *d = dj;
            }
            if *d > far_d {
                far_d = *d;
                far = j;
            }
        }
        current = far;
    }
    out
}

/// Squared distance in f32, the textbook loop's order.
#[inline]
fn dist2(p: [f32; 3], c: [f32; 3]) -> f32 {
    let (dx, dy, dz) = (p[0] - c[0], p[1] - c[1], p[2] - c[2]);
    dx * dx + dy * dy + dz * dz
}

/// No bucket: an empty grid cell.
const EMPTY: u32 = u32::MAX;

/// The candidates sorted into occupied grid cells ("buckets"), structure of arrays.
struct Buckets {
    /// Sorted positions.
    xs: Vec<f32>,
    ys: Vec<f32>,
    zs: Vec<f32>,
    /// Per sorted point, its candidate number.
    ids: Vec<u32>,
    /// Per bucket, its first sorted point; one more entry at the end.
    start: Vec<u32>,
    /// Per bucket, the box around its points: min x, max x, min y, max y, min z, max z.
    boxes: Vec<[f32; 6]>,
    /// Per grid cell (x fastest), its bucket or `EMPTY`.
    bucket_of: Vec<u32>,
    /// The grid: its lower corner, cells per axis, and inverse cell edge.
    lo: [f64; 3],
    dims: [usize; 3],
    inv: f64,
}

impl Buckets {
    fn new<P: Copy + Into<[f32; 3]>>(xyz: &[P], candidates: &[usize]) -> Buckets {
        let n = candidates.len();
        let mut lo = [f32::INFINITY; 3];
        let mut hi = [f32::NEG_INFINITY; 3];
        for &i in candidates {
            let p: [f32; 3] = xyz[i].into();
            for a in 0..3 {
                lo[a] = lo[a].min(p[a]);
                hi[a] = hi[a].max(p[a]);
            }
        }
        let lo = lo.map(f64::from);
        let ext = [0, 1, 2].map(|a| f64::from(hi[a]) - lo[a]);
        let widest = ext.iter().copied().fold(0.0f64, f64::max);
        let floor = (widest / 256.0).max(f64::MIN_POSITIVE);
        let cells = (n / POINTS_PER_CELL).clamp(1, MAX_CELLS) as f64;
        let volume: f64 = ext.iter().map(|e| e.max(floor)).product();
        let h = (volume / cells).cbrt().max(floor);
        let dims = ext.map(|e| ((e / h) as usize + 1).clamp(1, 1 << 10));
        let total = dims[0] * dims[1] * dims[2];
        let inv = 1.0 / h;
        let grid = Grid { lo, dims, inv };
        // Stable counting sort: within a cell, candidates stay in order.
        let mut offsets = vec![0u32; total + 1];
        let cell: Vec<u32> = candidates
            .iter()
            .map(|&i| {
                let p: [f32; 3] = xyz[i].into();
                let [x, y, z] = [0, 1, 2].map(|a| grid.cell(a, f64::from(p[a])));
                let c = (z * dims[1] + y) * dims[0] + x;
                offsets[c + 1] += 1;
                c as u32
            })
            .collect();
        for c in 0..total {
            offsets[c + 1] += offsets[c];
        }
        let mut xs = vec![0.0f32; n];
        let mut ys = vec![0.0f32; n];
        let mut zs = vec![0.0f32; n];
        let mut ids = vec![0u32; n];
        let mut cursor = offsets.clone();
        for (j, (&i, &c)) in candidates.iter().zip(&cell).enumerate() {
            let at = cursor[c as usize] as usize;
            cursor[c as usize] += 1;
            let p: [f32; 3] = xyz[i].into();
            xs[at] = p[0];
            ys[at] = p[1];
            zs[at] = p[2];
            ids[at] = j as u32;
        }
        let mut start = Vec::new();
        let mut boxes = Vec::new();
        let mut bucket_of = vec![EMPTY; total];
        for c in 0..total {
            let (s, e) = (offsets[c] as usize, offsets[c + 1] as usize);
            if s == e {
                continue;
            }
            bucket_of[c] = start.len() as u32;
            start.push(s as u32);
            let mut b = [
                f32::INFINITY,
                f32::NEG_INFINITY,
                f32::INFINITY,
                f32::NEG_INFINITY,
                f32::INFINITY,
                f32::NEG_INFINITY,
            ];
            for (a, v) in [&xs, &ys, &zs].into_iter().enumerate() {
                for &x in &v[s..e] {
                    b[2 * a] = b[2 * a].min(x);
                    b[2 * a + 1] = b[2 * a + 1].max(x);
                }
            }
            boxes.push(b);
        }
        start.push(n as u32);
        Buckets {
            xs,
            ys,
            zs,
            ids,
            start,
            boxes,
            bucket_of,
            lo,
            dims,
            inv,
        }
    }

    /// Farthest point sampling from candidate `first`.
    ///
    /// The new sample `c` was the farthest candidate, at squared distance `far_d` from the
    /// samples before it, and no candidate is farther: only candidates nearer to `c` than
    /// that can get closer, so only the cells within `sqrt(far_d)` (and a margin far above
    /// f32 rounding) are visited, and of those only the buckets whose box passes the test.
    /// A tournament tree over the buckets' best candidates gives the next sample.
    fn sample<P: Copy + Into<[f32; 3]>>(
        &self,
        xyz: &[P],
        candidates: &[usize],
        count: usize,
        first: usize,
    ) -> Vec<usize> {
        let n = self.xs.len();
        let nb = self.boxes.len();
        let grid = Grid {
            lo: self.lo,
            dims: self.dims,
            inv: self.inv,
        };
        let [nx, ny, _] = self.dims;
        let mut d = vec![f32::INFINITY; n];
        let mut tree = Tree::new(nb, |b| (f32::INFINITY, self.ids[self.start[b] as usize]));
        let mut out = Vec::with_capacity(count);
        let mut current = first;
        let mut far_d = f32::INFINITY;
        let mut touched: Vec<u32> = Vec::new();
        loop {
            out.push(candidates[current]);
            if out.len() == count {
                return out;
            }
            let [cx, cy, cz]: [f32; 3] = xyz[candidates[current]].into();
            let reach = f64::from(far_d).sqrt() * (1.0 + 1e-3)
                + 1e-6 * (1.0 + f64::from(cx.abs().max(cy.abs()).max(cz.abs())));
            let span = |a: usize, v: f32| {
                let v = f64::from(v);
                (grid.cell(a, v - reach), grid.cell(a, v + reach))
            };
            let (x0, x1) = span(0, cx);
            let (y0, y1) = span(1, cy);
            let (z0, z1) = span(2, cz);
            for z in z0..=z1 {
                for y in y0..=y1 {
                    let row = (z * ny + y) * nx;
                    for &b in &self.bucket_of[row + x0..=row + x1] {
                        if b == EMPTY {
                            continue;
                        }
                        let b = b as usize;
                        let bx = &self.boxes[b];
                        let gx = (bx[0] - cx).max(cx - bx[1]).max(0.0);
                        let gy = (bx[2] - cy).max(cy - bx[3]).max(0.0);
                        let gz = (bx[4] - cz).max(cz - bx[5]).max(0.0);
                        let gap = gx * gx + gy * gy + gz * gz;
                        if gap >= tree.leaf(b).0 {
                            continue;
                        }
                        let (s, e) = (self.start[b] as usize, self.start[b + 1] as usize);
                        let mut m = -1.0f32;
                        let mut at = 0;
                        let points = self.xs[s..e]
                            .iter()
                            .zip(&self.ys[s..e])
                            .zip(&self.zs[s..e])
                            .zip(&mut d[s..e]);
                        for (j, (((&x, &y), &z), dj_old)) in points.enumerate() {
                            let (dx, dy, dz) = (x - cx, y - cy, z - cz);
                            let dj = dx * dx + dy * dy + dz * dz;
                            let dj = if dj < *dj_old { dj } else { *dj_old };
                            *dj_old = dj;
                            if dj > m {
                                m = dj;
                                at = j;
                            }
                        }
                        tree.set_leaf(b, (m, self.ids[s + at]));
                        touched.push(b as u32);
                    }
                }
            }
            // Many changed leaves (the first samples): one pass over the tree is cheaper.
            if touched.len() * 8 > nb {
                tree.rebuild();
            } else {
                for &b in &touched {
                    tree.update(b as usize);
                }
            }
            touched.clear();
            let (dmax, id) = tree.top();
            far_d = dmax;
            current = id as usize;
        }
    }
}

/// The bucket grid's cell arithmetic.
struct Grid {
    lo: [f64; 3],
    dims: [usize; 3],
    inv: f64,
}

impl Grid {
    /// The cell of coordinate `v` on axis `a`, clamped into the grid (monotonic in `v`).
    #[inline]
    fn cell(&self, a: usize, v: f64) -> usize {
        // `as usize` saturates: below the grid (and NaN) is cell 0.
        (((v - self.lo[a]) * self.inv) as usize).min(self.dims[a] - 1)
    }
}

/// A tournament tree over the buckets' best (squared distance, candidate number): the
/// largest distance wins, the smaller candidate number on ties.
struct Tree {
    /// Leaves from `size`; node `i`'s children are `2i` and `2i + 1`; the root is 1.
    nodes: Vec<(f32, u32)>,
    size: usize,
}

impl Tree {
    fn new(n: usize, leaf: impl Fn(usize) -> (f32, u32)) -> Tree {
        let size = n.next_power_of_two();
        let mut nodes = vec![(-1.0f32, u32::MAX); 2 * size];
        for i in 0..n {
            nodes[size + i] = leaf(i);
        }
        let mut tree = Tree { nodes, size };
        tree.rebuild();
        tree
    }

    #[inline]
    fn winner(a: (f32, u32), b: (f32, u32)) -> (f32, u32) {
        if b.0 > a.0 || (b.0 == a.0 && b.1 < a.1) {
            b
        } else {
            a
        }
    }

    #[inline]
    fn leaf(&self, i: usize) -> (f32, u32) {
        self.nodes[self.size + i]
    }

    /// Sets leaf `i` without updating its ancestors (see `update`, `rebuild`).
    #[inline]
    fn set_leaf(&mut self, i: usize, v: (f32, u32)) {
        self.nodes[self.size + i] = v;
    }

    /// Updates the ancestors of leaf `i`, up to the first that keeps its value.
    fn update(&mut self, i: usize) {
        let mut at = self.size + i;
        while at > 1 {
            at /= 2;
            let w = Self::winner(self.nodes[2 * at], self.nodes[2 * at + 1]);
            if w == self.nodes[at] {
                return;
            }
            self.nodes[at] = w;
        }
    }

    /// Recomputes every inner node.
    fn rebuild(&mut self) {
        for i in (1..self.size).rev() {
            self.nodes[i] = Self::winner(self.nodes[2 * i], self.nodes[2 * i + 1]);
        }
    }

    fn top(&self) -> (f32, u32) {
        self.nodes[1]
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use proptest::prelude::*;

    /// Points from small integers times `step`: many equal distances, and duplicates.
    fn lattice(cells: &[(i8, i8, i8)], step: f32) -> Vec<[f32; 3]> {
        cells
            .iter()
            .map(|&(x, y, z)| {
                [
                    f32::from(x) * step,
                    f32::from(y) * step,
                    f32::from(z) * step,
                ]
            })
            .collect()
    }

    proptest! {
        #[test]
        fn buckets_give_the_textbook_samples(
            cells in prop::collection::vec((-6i8..6, -6i8..6, -2i8..2), 2..300),
            step in prop_oneof![Just(0.01f32), Just(0.37f32), Just(1e-4f32)],
            jitter in prop::collection::vec(-1.0f32..1.0, 0..300),
            every in 1usize..4,
            count_frac in 0.0f64..1.0,
            first_frac in 0.0f64..1.0,
        ) {
            // A lattice, part of it moved off the lattice by up to a quarter step.
            let mut xyz = lattice(&cells, step);
            for (p, j) in xyz.iter_mut().zip(&jitter) {
                p[0] += 0.25 * step * j;
            }
            // Candidates: every `every`-th point, in reverse order.
            let candidates: Vec<usize> = (0..xyz.len()).rev().step_by(every).collect();
            let n = candidates.len();
            let count = 1 + ((n - 1) as f64 * count_frac) as usize;
            let first = ((n - 1) as f64 * first_frac) as usize;
            let got = farthest_point_sample(&xyz, &candidates, count, first);
            prop_assert_eq!(got.len(), count);
            prop_assert_eq!(got, farthest_point_sample_textbook(&xyz, &candidates, count, first));
        }
    }

    #[test]
    fn the_textbook_loop_takes_the_farthest_and_the_first_on_ties() {
        let xyz = [
            [0.0f32, 0.0, 0.0],
            [1.0, 0.0, 0.0],
            [-1.0, 0.0, 0.0],
            [0.0, 3.0, 0.0],
        ];
        let all = [0, 1, 2, 3];
        // From 0: 3 is farthest; then 1 and 2 tie (distance 1 to 0), the first wins.
        assert_eq!(
            farthest_point_sample_textbook(&xyz, &all, 3, 0),
            vec![0, 3, 1]
        );
        assert_eq!(farthest_point_sample(&xyz, &all, 3, 0), vec![0, 3, 1]);
    }

    #[test]
    fn counts_and_starts_out_of_range_sample_what_they_can() {
        let xyz = [[0.0f32, 0.0, 0.0], [1.0, 0.0, 0.0], [2.0, 0.0, 0.0]];
        let all = [0, 1, 2];
        assert_eq!(farthest_point_sample(&xyz, &all, 9, 0), vec![0, 2, 1]);
        assert!(farthest_point_sample(&xyz, &all, 2, 3).is_empty());
        assert!(farthest_point_sample(&xyz, &all, 0, 0).is_empty());
        assert!(farthest_point_sample(&xyz, &[], 2, 0).is_empty());
        // Non-finite points take the textbook path.
        let odd = [[0.0f32, 0.0, 0.0], [f32::NAN, 0.0, 0.0], [2.0, 0.0, 0.0]];
        assert_eq!(
            farthest_point_sample(&odd, &all, 3, 0),
            farthest_point_sample_textbook(&odd, &all, 3, 0)
        );
    }
}
