//! A static bounding-volume tree over cloud points answering "is any point within r of p"
//! exactly; the distance field sends it only the queries its bounds cannot decide.
//!
//! Built in linear time (issue 3: the cloud structure is rebuilt per observation): the points
//! are sorted by the Morton code of their position (three 10-bit radix passes), cut into
//! leaves of `LEAF` (8) consecutive points, and a complete binary tree of axis-aligned boxes is
//! built bottom-up over the leaves. Queries descend through the boxes a ball reaches.

use nalgebra::Point3;

/// Points per leaf.
const LEAF: usize = 8;

/// Points in Morton order under an implicit complete binary tree of boxes (node `i` has
/// children `2i + 1` and `2i + 2`; leaf `k` is node `leaves − 1 + k`).
#[derive(Clone, Debug, Default)]
pub struct KdTree {
    pts: Vec<[f32; 3]>,
    /// Per node: min x y z, max x y z (an empty node has min > max).
    boxes: Vec<[f32; 6]>,
    /// Number of leaves (a power of two; 0 for an empty tree).
    leaves: usize,
}

const EMPTY: [f32; 6] = [
    f32::INFINITY,
    f32::INFINITY,
    f32::INFINITY,
    f32::NEG_INFINITY,
    f32::NEG_INFINITY,
    f32::NEG_INFINITY,
];

/// Spreads the low 10 bits of `v` to every third bit.
fn spread(v: u32) -> u32 {
    let mut x = v & 0x3ff;
    x = (x | (x << 16)) & 0x0300_00ff;
    x = (x | (x << 8)) & 0x0300_f00f;
    x = (x | (x << 4)) & 0x030c_30c3;
    (x | (x << 2)) & 0x0924_9249
}

/// Squared distance from `q` to box `b` (0 inside; +∞ for an empty box).
#[inline]
fn box_dist2(b: &[f32; 6], q: &[f32; 3]) -> f32 {
    if b[0] > b[3] {
        return f32::INFINITY;
    }
    let mut d = 0.0;
    for k in 0..3 {
        let e = (b[k] - q[k]).max(0.0).max(q[k] - b[k + 3]);
        d += e * e;
    }
    d
}

impl KdTree {
    /// Builds the tree (linear time).
    pub fn build(points: &[Point3<f32>]) -> Self {
        let n = points.len();
        if n == 0 {
            return Self::default();
        }
        let (mut lo, mut hi) = ([f32::INFINITY; 3], [f32::NEG_INFINITY; 3]);
        for p in points {
            for k in 0..3 {
                lo[k] = lo[k].min(p[k]);
                hi[k] = hi[k].max(p[k]);
            }
        }
        let scale: [f32; 3] = std::array::from_fn(|k| {
            let e = hi[k] - lo[k];
            if e > 0.0 {
                1023.0 / e
            } else {
                0.0
            }
        });
        let quant =
            |p: &Point3<f32>, k: usize| ((p[k] - lo[k]) * scale[k]).clamp(0.0, 1023.0) as u32;
        let mut keys: Vec<(u32, u32)> = points
            .iter()
            .enumerate()
            .map(|(i, p)| {
                let m =
                    spread(quant(p, 0)) | (spread(quant(p, 1)) << 1) | (spread(quant(p, 2)) << 2);
                (m, i as u32)
            })
            .collect();
        // LSD radix sort on the 30-bit codes, 10 bits a pass (stable).
        let mut tmp = vec![(0u32, 0u32); n];
        for pass in 0..3 {
            let shift = 10 * pass;
            let mut count = vec![0usize; 1025];
            for (k, _) in &keys {
                count[((k >> shift) & 0x3ff) as usize + 1] += 1;
            }
            for i in 0..1024 {
                count[i + 1] += count[i];
            }
            for e in &keys {
                let b = ((e.0 >> shift) & 0x3ff) as usize;
                tmp[count[b]] = *e;
                count[b] += 1;
            }
            std::mem::swap(&mut keys, &mut tmp);
        }
        let pts: Vec<[f32; 3]> = keys
            .iter()
            .map(|(_, i)| {
                let p = &points[*i as usize];
                [p.x, p.y, p.z]
            })
            .collect();
        let leaves = n.div_ceil(LEAF).next_power_of_two();
        let mut boxes = vec![EMPTY; 2 * leaves - 1];
        for (k, chunk) in pts.chunks(LEAF).enumerate() {
            let b = &mut boxes[leaves - 1 + k];
            for p in chunk {
                for a in 0..3 {
                    b[a] = b[a].min(p[a]);
                    b[a + 3] = b[a + 3].max(p[a]);
                }
            }
        }
        for i in (0..leaves - 1).rev() {
            let (l, r) = (boxes[2 * i + 1], boxes[2 * i + 2]);
            boxes[i] = std::array::from_fn(|a| {
                if a < 3 {
                    l[a].min(r[a])
                } else {
                    l[a].max(r[a])
                }
            });
        }
        Self { pts, boxes, leaves }
    }

    /// The points of leaf node `id`.
    #[inline]
    fn leaf_points(&self, id: usize) -> &[[f32; 3]] {
        let k = id - (self.leaves - 1);
        let lo = (k * LEAF).min(self.pts.len());
        let hi = (lo + LEAF).min(self.pts.len());
        &self.pts[lo..hi]
    }

    /// True when some point lies within `r` of `p`.
    pub fn any_within(&self, p: &Point3<f64>, r: f64) -> bool {
        self.find_within(p, r, &mut |_| true).is_some()
    }

    /// The first point within `r` of `p` (nearer subtrees first, not the nearest point) for
    /// which `hit` returns true; `hit` sees every point within `r` until one is accepted.
    pub fn find_within<F: FnMut(&Point3<f64>) -> bool>(
        &self,
        p: &Point3<f64>,
        r: f64,
        hit: &mut F,
    ) -> Option<Point3<f64>> {
        if self.leaves == 0 {
            return None;
        }
        let q = [p.x as f32, p.y as f32, p.z as f32];
        // A hair of slack for the f32 round trip keeps the answer conservative.
        let r = r as f32 + 1e-6;
        let r2 = r * r;
        if box_dist2(&self.boxes[0], &q) > r2 {
            return None;
        }
        let mut stack = [0usize; 64];
        let mut top = 1;
        while top > 0 {
            top -= 1;
            let id = stack[top];
            if id >= self.leaves - 1 {
                for pt in self.leaf_points(id) {
                    let d = [pt[0] - q[0], pt[1] - q[1], pt[2] - q[2]];
                    if d[0] * d[0] + d[1] * d[1] + d[2] * d[2] <= r2 {
                        let pt = Point3::new(f64::from(pt[0]), f64::from(pt[1]), f64::from(pt[2]));
                        if hit(&pt) {
                            return Some(pt);
                        }
                    }
                }
                continue;
            }
            let (l, rr) = (2 * id + 1, 2 * id + 2);
            let (dl, dr) = (
                box_dist2(&self.boxes[l], &q),
                box_dist2(&self.boxes[rr], &q),
            );
            // Push the farther child first so the nearer one is visited first.
            let (near, dn, far, df) = if dl <= dr {
                (l, dl, rr, dr)
            } else {
                (rr, dr, l, dl)
            };
            if df <= r2 {
                stack[top] = far;
                top += 1;
            }
            if dn <= r2 {
                stack[top] = near;
                top += 1;
            }
        }
        None
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use rand::{Rng, SeedableRng};

    #[test]
    fn matches_brute_force() {
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(2);
        let pts: Vec<Point3<f32>> = (0..2000)
            .map(|_| Point3::new(rng.random(), rng.random(), rng.random()))
            .collect();
        let t = KdTree::build(&pts);
        for _ in 0..2000 {
            let p = Point3::new(
                rng.random_range(-0.2..1.2),
                rng.random_range(-0.2..1.2),
                rng.random_range(-0.2..1.2),
            );
            let r = rng.random_range(0.0..0.1);
            let brute = pts.iter().any(|q| (q.cast::<f64>() - p).norm() <= r);
            let fast = t.any_within(&p, r);
            // The tree may only err on the side of contact, within its 1e-6 m slack.
            if fast != brute {
                let d = pts
                    .iter()
                    .map(|q| (q.cast::<f64>() - p).norm())
                    .fold(f64::INFINITY, f64::min);
                assert!(
                    fast && d <= r + 2e-6,
                    "{p:?} r {r}: tree {fast} brute {brute}"
                );
            }
        }
        assert!(!KdTree::build(&[]).any_within(&Point3::origin(), 1.0));
        // The visitor sees exactly the points within r (up to the same slack).
        for _ in 0..200 {
            let p = Point3::new(rng.random(), rng.random(), rng.random());
            let r = rng.random_range(0.0..0.15);
            let mut seen = 0usize;
            let none = t.find_within(&p, r, &mut |_| {
                seen += 1;
                false
            });
            assert!(none.is_none());
            let brute = pts
                .iter()
                .filter(|q| (q.cast::<f64>() - p).norm() <= r + 2e-6)
                .count();
            let inner = pts
                .iter()
                .filter(|q| (q.cast::<f64>() - p).norm() <= r - 2e-6)
                .count();
            assert!(inner <= seen && seen <= brute, "{inner} {seen} {brute}");
        }
    }
}
