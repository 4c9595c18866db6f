//! A static 3-D k-d tree over cloud points answering "is any point within r of p" exactly;
//! the distance field sends it only the queries its bounds cannot decide.

use nalgebra::Point3;

const LEAF: usize = 8;

/// Points reordered into an implicit balanced k-d tree (median splits on the widest axis).
#[derive(Clone, Debug, Default)]
pub struct KdTree {
    pts: Vec<[f32; 3]>,
    nodes: Vec<Node>,
}

#[derive(Copy, Clone, Debug)]
struct Node {
    lo: usize,
    hi: usize,
    axis: u8,
    split: f32,
    left: u32,
    right: u32,
}

const NONE: u32 = u32::MAX;

impl KdTree {
    /// Builds the tree (O(n log n)).
    pub fn build(points: &[Point3<f32>]) -> Self {
        let mut t = Self {
            pts: points.iter().map(|p| [p.x, p.y, p.z]).collect(),
            nodes: Vec::new(),
        };
        if !t.pts.is_empty() {
            let n = t.pts.len();
            t.build_rec(0, n);
        }
        t
    }

    fn build_rec(&mut self, lo: usize, hi: usize) -> u32 {
        let id = self.nodes.len();
        self.nodes.push(Node {
            lo,
            hi,
            axis: 0,
            split: 0.0,
            left: NONE,
            right: NONE,
        });
        if hi - lo > LEAF {
            let mut mn = [f32::INFINITY; 3];
            let mut mx = [f32::NEG_INFINITY; 3];
            for p in &self.pts[lo..hi] {
                for k in 0..3 {
                    mn[k] = mn[k].min(p[k]);
                    mx[k] = mx[k].max(p[k]);
                }
            }
            let axis = (0..3)
                .max_by(|a, b| (mx[*a] - mn[*a]).total_cmp(&(mx[*b] - mn[*b])))
                .unwrap_or(0);
            let mid = (lo + hi) / 2;
            self.pts[lo..hi].select_nth_unstable_by(mid - lo, |a, b| a[axis].total_cmp(&b[axis]));
            let split = self.pts[mid][axis];
            let left = self.build_rec(lo, mid);
            let right = self.build_rec(mid, hi);
            let n = &mut self.nodes[id];
            n.axis = axis as u8;
            n.split = split;
            n.left = left;
            n.right = right;
        }
        id as u32
    }

    /// True when some point lies within `r` of `p`.
    pub fn any_within(&self, p: &Point3<f64>, r: f64) -> bool {
        if self.nodes.is_empty() {
            return false;
        }
        let q = [p.x as f32, p.y as f32, p.z as f32];
        // A hair of slack for the f32 round trip keeps the answer conservative.
        let r = r as f32 + 1e-6;
        self.within_rec(0, &q, r * r)
    }

    /// The first point within `r` of `p` (nearer subtrees first, not the nearest point) for
    /// which `hit` returns true; `hit` sees every point within `r` until one is accepted.
    pub fn find_within<F: FnMut(&Point3<f64>) -> bool>(
        &self,
        p: &Point3<f64>,
        r: f64,
        hit: &mut F,
    ) -> Option<Point3<f64>> {
        if self.nodes.is_empty() {
            return None;
        }
        let q = [p.x as f32, p.y as f32, p.z as f32];
        let r = r as f32 + 1e-6;
        self.find_rec(0, &q, r * r, hit)
    }

    fn find_rec<F: FnMut(&Point3<f64>) -> bool>(
        &self,
        id: u32,
        q: &[f32; 3],
        r2: f32,
        hit: &mut F,
    ) -> Option<Point3<f64>> {
        let n = self.nodes[id as usize];
        if n.left == NONE {
            for p in &self.pts[n.lo..n.hi] {
                let d = [p[0] - q[0], p[1] - q[1], p[2] - q[2]];
                if d[0] * d[0] + d[1] * d[1] + d[2] * d[2] <= r2 {
                    let pt = Point3::new(f64::from(p[0]), f64::from(p[1]), f64::from(p[2]));
                    if hit(&pt) {
                        return Some(pt);
                    }
                }
            }
            return None;
        }
        let diff = q[n.axis as usize] - n.split;
        let (near, far) = if diff < 0.0 {
            (n.left, n.right)
        } else {
            (n.right, n.left)
        };
        if let Some(p) = self.find_rec(near, q, r2, hit) {
            return Some(p);
        }
        if diff * diff <= r2 {
            return self.find_rec(far, q, r2, hit);
        }
        None
    }

    fn within_rec(&self, id: u32, q: &[f32; 3], r2: f32) -> bool {
        let n = self.nodes[id as usize];
        if n.left == NONE {
            return self.pts[n.lo..n.hi].iter().any(|p| {
                let d = [p[0] - q[0], p[1] - q[1], p[2] - q[2]];
                d[0] * d[0] + d[1] * d[1] + d[2] * d[2] <= r2
            });
        }
        let diff = q[n.axis as usize] - n.split;
        let (near, far) = if diff < 0.0 {
            (n.left, n.right)
        } else {
            (n.right, n.left)
        };
        self.within_rec(near, q, r2) || (diff * diff <= r2 && self.within_rec(far, q, r2))
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
