//! Farthest point sampling with buckets: the same samples as the textbook O(N k) loop, with
//! most of its distance updates skipped.
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
//! As sampling proceeds, a new sample only changes the buckets near it, so most of the work
//! is one box test per bucket.
//!
//! Ties go to the first candidate, as in the textbook loop: within a bucket the points keep
//! their candidate order, and buckets compare their best candidate's index on equal
//! distances.

use nalgebra::Point3;

/// Target number of candidates per grid cell (of the box around all candidates). Clouds
/// of surfaces occupy a small fraction of the cells, so occupied buckets hold more.
const POINTS_PER_CELL: usize = 2;

/// The most grid cells (the counting sort's offsets).
const MAX_CELLS: usize = 1 << 20;

/// Farthest point sampling of `count` (`1..candidates.len()`) of `candidates` (indices into
/// `xyz`) from candidate number `first`: the chosen indices into `xyz`.
pub(super) fn sample(
    xyz: &[Point3<f32>],
    candidates: &[usize],
    count: usize,
    first: usize,
) -> Vec<usize> {
    let finite = candidates
        .iter()
        .all(|&i| xyz[i].iter().all(|v| v.is_finite()));
    if !finite {
        // The box test needs finite coordinates; NaN points keep the textbook behaviour.
        return textbook(xyz, candidates, count, first);
    }
    let b = Buckets::new(xyz, candidates);
    b.sample(xyz, candidates, count, first)
}

/// The textbook loop (the reference, and the path for clouds with non-finite points).
pub(super) fn textbook(
    xyz: &[Point3<f32>],
    candidates: &[usize],
    count: usize,
    first: usize,
) -> Vec<usize> {
    let mut dist = vec![f32::INFINITY; candidates.len()];
    let mut out = Vec::with_capacity(count);
    let mut current = first;
    for _ in 0..count {
        out.push(candidates[current]);
        let c = xyz[candidates[current]];
        let mut far = 0;
        let mut far_d = -1.0f32;
        for (j, d) in dist.iter_mut().enumerate() {
            let dj = (xyz[candidates[j]] - c).norm_squared();
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

/// The candidates sorted into occupied grid cells, structure of arrays.
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
}

impl Buckets {
    fn new(xyz: &[Point3<f32>], candidates: &[usize]) -> Buckets {
        let n = candidates.len();
        let mut lo = [f32::INFINITY; 3];
        let mut hi = [f32::NEG_INFINITY; 3];
        for &i in candidates {
            for a in 0..3 {
                lo[a] = lo[a].min(xyz[i][a]);
                hi[a] = hi[a].max(xyz[i][a]);
            }
        }
        let ext = [0, 1, 2].map(|a| f64::from(hi[a]) - f64::from(lo[a]));
        let widest = ext.iter().copied().fold(0.0f64, f64::max);
        let floor = (widest / 256.0).max(f64::MIN_POSITIVE);
        let cells = (n / POINTS_PER_CELL).clamp(1, MAX_CELLS) as f64;
        let volume: f64 = ext.iter().map(|e| e.max(floor)).product();
        let h = (volume / cells).cbrt().max(floor);
        let dims = ext.map(|e| ((e / h) as usize + 1).clamp(1, 1 << 10));
        let total = dims[0] * dims[1] * dims[2];
        let inv = 1.0 / h;
        let cell_of = |p: &Point3<f32>| {
            let c = |a: usize| {
                let v = ((f64::from(p[a]) - f64::from(lo[a])) * inv) as usize;
                v.min(dims[a] - 1)
            };
            (c(2) * dims[1] + c(1)) * dims[0] + c(0)
        };
        // Stable counting sort: within a cell, candidates stay in order.
        let mut offsets = vec![0u32; total + 1];
        let cell: Vec<u32> = candidates
            .iter()
            .map(|&i| {
                let c = cell_of(&xyz[i]);
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
            let p = xyz[i];
            xs[at] = p.x;
            ys[at] = p.y;
            zs[at] = p.z;
            ids[at] = j as u32;
        }
        let mut start = Vec::new();
        let mut boxes = Vec::new();
        for c in 0..total {
            let (s, e) = (offsets[c] as usize, offsets[c + 1] as usize);
            if s == e {
                continue;
            }
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
        }
    }

    fn sample(
        &self,
        xyz: &[Point3<f32>],
        candidates: &[usize],
        count: usize,
        first: usize,
    ) -> Vec<usize> {
        let n = self.xs.len();
        let nb = self.boxes.len();
        let mut d = vec![f32::INFINITY; n];
        // Per bucket, its largest `d` and the first candidate with it.
        let mut best = vec![f32::INFINITY; nb];
        let mut best_id: Vec<u32> = (0..nb).map(|b| self.ids[self.start[b] as usize]).collect();
        let mut out = Vec::with_capacity(count);
        let mut current = first;
        loop {
            out.push(candidates[current]);
            if out.len() == count {
                return out;
            }
            let c = xyz[candidates[current]];
            let (cx, cy, cz) = (c.x, c.y, c.z);
            let mut far_d = -1.0f32;
            let mut far = 0u32;
            for b in 0..nb {
                let bx = &self.boxes[b];
                let gx = (bx[0] - cx).max(cx - bx[1]).max(0.0);
                let gy = (bx[2] - cy).max(cy - bx[3]).max(0.0);
                let gz = (bx[4] - cz).max(cz - bx[5]).max(0.0);
                let gap = gx * gx + gy * gy + gz * gz;
                if gap < best[b] {
                    let (s, e) = (self.start[b] as usize, self.start[b + 1] as usize);
                    let mut m = -1.0f32;
                    let mut at = s;
                    for j in s..e {
                        let (dx, dy, dz) = (self.xs[j] - cx, self.ys[j] - cy, self.zs[j] - cz);
                        let dj = dx * dx + dy * dy + dz * dz;
                        let dj = if dj < d[j] { dj } else { d[j] };
                        d[j] = dj;
                        if dj > m {
                            m = dj;
                            at = j;
                        }
                    }
                    best[b] = m;
                    best_id[b] = self.ids[at];
                }
                let (m, id) = (best[b], best_id[b]);
                if m > far_d || (m == far_d && id < far) {
                    far_d = m;
                    far = id;
                }
            }
            current = far as usize;
        }
    }
}
