//! The world the robot must not touch (issue 3 item 2): static primitives (table plane, boxes,
//! cylinders, balls) and an observed point cloud turned into a Euclidean distance field.
//!
//! The field is exact on the grid (Felzenszwalb & Huttenlocher, "Distance Transforms of
//! Sampled Functions", 2012: three separable 1-D lower-envelope passes) between cell centres.
//! For any query point in a cell whose centre is `D` from the nearest occupied cell centre,
//! the true distance to the cloud lies in `[D − √3·h, D + √3·h]`: a sphere query is one lookup
//! and two compares, and only spheres whose radius falls in that band (a thin shell around
//! the cloud) go on to an exact k-d tree query. The answer is exact (up to f32 rounding of
//! the points, resolved towards contact), never conservative by a cell.

// Per-joint and per-cell index loops mirror the formulas; iterator chains would hide them.
#![allow(clippy::needless_range_loop)]

use crate::collision::Sphere;
use crate::error::PlanError;
use crate::kdtree::KdTree;
use cell_types::{FrameId, PointCloud};
use nalgebra::{Isometry3, Matrix3, Point3, Unit, Vector3};

/// A static obstacle.
#[derive(Clone, Debug, PartialEq)]
pub enum Obstacle {
    /// A box centred on `pose` with half edge lengths `half`.
    Cuboid {
        /// Name (for error messages).
        name: String,
        /// Pose of the centre in the base frame.
        pose: Isometry3<f64>,
        /// Half edge lengths (m).
        half: Vector3<f64>,
    },
    /// A cylinder along its pose's z, centred on the pose.
    Cylinder {
        /// Name.
        name: String,
        /// Pose of the centre.
        pose: Isometry3<f64>,
        /// Radius (m).
        radius: f64,
        /// Half length (m).
        half_length: f64,
    },
    /// A ball.
    Ball {
        /// Name.
        name: String,
        /// Centre (m).
        center: Point3<f64>,
        /// Radius (m).
        radius: f64,
    },
    /// Everything on the far side of a plane: points with `normal · p < offset` are inside
    /// (a table top at height h: normal +z, offset h).
    HalfSpace {
        /// Name.
        name: String,
        /// Unit normal pointing into free space.
        normal: Unit<Vector3<f64>>,
        /// Plane offset along the normal (m).
        offset: f64,
    },
}

impl Obstacle {
    /// The table top: everything below z = `height` in the base frame, named `table`.
    pub fn table(height: f64) -> Self {
        Obstacle::HalfSpace {
            name: "table".into(),
            normal: Vector3::z_axis(),
            offset: height,
        }
    }

    /// The obstacle's name.
    pub fn name(&self) -> &str {
        match self {
            Obstacle::Cuboid { name, .. }
            | Obstacle::Cylinder { name, .. }
            | Obstacle::Ball { name, .. }
            | Obstacle::HalfSpace { name, .. } => name,
        }
    }

    /// A ball containing the obstacle (`None` for unbounded ones).
    pub fn bounding_ball(&self) -> Option<(Point3<f64>, f64)> {
        match self {
            Obstacle::Cuboid { pose, half, .. } => Some((pose * Point3::origin(), half.norm())),
            Obstacle::Cylinder {
                pose,
                radius,
                half_length,
                ..
            } => Some((pose * Point3::origin(), radius.hypot(*half_length))),
            Obstacle::Ball { center, radius, .. } => Some((*center, *radius)),
            Obstacle::HalfSpace { .. } => None,
        }
    }

    /// Signed distance from `p` to the obstacle's surface (negative inside); exact.
    pub fn distance(&self, p: &Point3<f64>) -> f64 {
        self.distance_local(&self.frame().inverse_transform_point(p))
    }

    /// The frame [`Self::distance_local`] works in: the pose for boxes and cylinders, the
    /// centre for balls, the base frame for half-spaces.
    fn frame(&self) -> Isometry3<f64> {
        match self {
            Obstacle::Cuboid { pose, .. } | Obstacle::Cylinder { pose, .. } => *pose,
            Obstacle::Ball { center, .. } => Isometry3::translation(center.x, center.y, center.z),
            Obstacle::HalfSpace { .. } => Isometry3::identity(),
        }
    }

    /// Signed distance from a point given in [`Self::frame`].
    #[inline]
    fn distance_local(&self, l: &Point3<f64>) -> f64 {
        match self {
            Obstacle::Cuboid { half, .. } => {
                let q = l.coords.abs() - half;
                let outside = q.map(|v| v.max(0.0)).norm();
                let inside = q.x.max(q.y).max(q.z).min(0.0);
                outside + inside
            }
            Obstacle::Cylinder {
                radius,
                half_length,
                ..
            } => {
                let dr = (l.x * l.x + l.y * l.y).sqrt() - radius;
                let dz = l.z.abs() - half_length;
                let outside = (dr.max(0.0).powi(2) + dz.max(0.0).powi(2)).sqrt();
                outside + dr.max(dz).min(0.0)
            }
            Obstacle::Ball { radius, .. } => l.coords.norm() - radius,
            Obstacle::HalfSpace { normal, offset, .. } => normal.dot(&l.coords) - offset,
        }
    }
}

/// An obstacle's bounding ball and the inverse of its frame as a matrix (one matrix-vector
/// product per distance instead of a quaternion rotation).
#[derive(Clone, Debug)]
struct Bound {
    center: Point3<f64>,
    radius: f64,
    inv_rot: Matrix3<f64>,
    origin: Vector3<f64>,
}

impl Bound {
    fn of(o: &Obstacle) -> Self {
        let (center, radius) = o
            .bounding_ball()
            .unwrap_or((Point3::origin(), f64::INFINITY));
        let f = o.frame();
        Self {
            center,
            radius,
            inv_rot: f.rotation.to_rotation_matrix().into_inner().transpose(),
            origin: f.translation.vector,
        }
    }

    /// `o.distance(p)` for the obstacle this bound was made of.
    #[inline]
    fn distance(&self, o: &Obstacle, p: &Point3<f64>) -> f64 {
        o.distance_local(&Point3::from(self.inv_rot * (p.coords - self.origin)))
    }
}

/// Parameters of the cloud structure.
#[derive(Copy, Clone, Debug, PartialEq)]
pub struct CloudParams {
    /// Cell edge (m).
    pub cell: f64,
    /// Free margin around the cloud's bounds covered by the grid (m); must exceed the largest
    /// robot sphere radius.
    pub pad: f64,
    /// Largest grid allowed (cells), to refuse a cloud that would exhaust memory.
    pub max_cells: usize,
}

impl Default for CloudParams {
    fn default() -> Self {
        Self {
            cell: 0.01,
            pad: 0.1,
            max_cells: 60_000_000,
        }
    }
}

/// A distance field over a cloud: per cell, a lower bound on the distance to the cloud.
#[derive(Clone, Debug)]
pub struct DistanceField {
    origin: Point3<f64>,
    inv_h: f64,
    h: f64,
    dims: [usize; 3],
    dist: Vec<f32>,
    two_hd: f64,
    lo: Point3<f64>,
    hi: Point3<f64>,
    tree: KdTree,
}

const FAR: f64 = 1e18;

/// 1-D squared distance transform of `f` (sites where `f < FAR`) into `d`.
fn edt_1d(f: &[f32], d: &mut [f32], v: &mut [usize], z: &mut [f64]) {
    let n = f.len();
    let far = FAR as f32;
    let Some(first) = f.iter().position(|x| *x < far) else {
        d.iter_mut().for_each(|x| *x = far);
        return;
    };
    let mut k = 0usize;
    v[0] = first;
    z[0] = f64::NEG_INFINITY;
    z[1] = f64::INFINITY;
    let inter = |q: usize, p: usize| {
        let (qf, pf) = (q as f64, p as f64);
        ((f64::from(f[q]) + qf * qf) - (f64::from(f[p]) + pf * pf)) / (2.0 * (qf - pf))
    };
    for q in first + 1..n {
        if f[q] >= far {
            continue;
        }
        let mut s = inter(q, v[k]);
        while s <= z[k] {
            // z[0] is −∞, so k never goes below 0.
            k -= 1;
            s = inter(q, v[k]);
        }
        k += 1;
        v[k] = q;
        z[k] = s;
        z[k + 1] = f64::INFINITY;
    }
    k = 0;
    for (q, dq) in d.iter_mut().enumerate() {
        while z[k + 1] < q as f64 {
            k += 1;
        }
        let dx = q as f64 - v[k] as f64;
        *dq = (dx * dx + f64::from(f[v[k]])) as f32;
    }
}

impl DistanceField {
    /// Builds the field over `points` (base frame, metres).
    pub fn build(points: &[Point3<f32>], params: &CloudParams) -> Result<Option<Self>, PlanError> {
        if !(params.cell.is_finite() && params.cell > 0.0 && params.pad >= 0.0) {
            return Err(PlanError::BadWorld {
                what: format!(
                    "cell {} m and pad {} m must be positive",
                    params.cell, params.pad
                ),
            });
        }
        let Some(first) = points.first() else {
            return Ok(None);
        };
        let mut lo = first.cast::<f64>();
        let mut hi = lo;
        for p in points {
            let p = p.cast::<f64>();
            if !p.coords.iter().all(|v| v.is_finite()) {
                return Err(PlanError::NotFinite {
                    what: "cloud point",
                });
            }
            lo = lo.inf(&p);
            hi = hi.sup(&p);
        }
        let h = params.cell;
        let origin = lo - Vector3::repeat(params.pad);
        let ext = (hi - lo) + Vector3::repeat(2.0 * params.pad);
        let dims = [
            (ext.x / h).ceil() as usize + 1,
            (ext.y / h).ceil() as usize + 1,
            (ext.z / h).ceil() as usize + 1,
        ];
        let cells = dims[0].saturating_mul(dims[1]).saturating_mul(dims[2]);
        if cells > params.max_cells {
            return Err(PlanError::BadWorld {
                what: format!(
                    "cloud spans {:.2} x {:.2} x {:.2} m: {cells} cells of {h} m exceed {}; crop the cloud to the workspace",
                    ext.x, ext.y, ext.z, params.max_cells
                ),
            });
        }
        let (nx, ny, nz) = (dims[0], dims[1], dims[2]);
        let mut f = vec![FAR as f32; cells];
        let mut row_has = vec![false; ny * nz];
        for p in points {
            let c = (p.cast::<f64>() - origin) / h;
            let (x, y, z) = (c.x as usize, c.y as usize, c.z as usize);
            if x < nx && y < ny && z < nz {
                f[x + nx * (y + ny * z)] = 0.0;
                row_has[y + ny * z] = true;
            }
        }
        // X pass: rows are contiguous and sites are binary, so two sweeps give the 1-D
        // distance to the nearest site; rows without sites stay far.
        let mut dist = vec![f32::INFINITY; nx];
        for (r, row) in f.chunks_exact_mut(nx).enumerate() {
            if !row_has[r] {
                continue;
            }
            let mut last: Option<usize> = None;
            dist.iter_mut().for_each(|d| *d = f32::INFINITY);
            for x in 0..nx {
                if row[x] == 0.0 {
                    last = Some(x);
                }
                if let Some(l) = last {
                    dist[x] = (x - l) as f32;
                }
            }
            last = None;
            for x in (0..nx).rev() {
                if row[x] == 0.0 {
                    last = Some(x);
                }
                if let Some(l) = last {
                    dist[x] = dist[x].min((l - x) as f32);
                }
                row[x] = dist[x] * dist[x];
            }
        }
        // Y and Z passes: copy a block whose lines run along the pass axis into a transposed
        // buffer (contiguous reads of x rows, cache-resident writes), transform each line,
        // and copy back: strided per-line gathers over a grid of millions of cells thrash.
        let nmax = nx.max(ny).max(nz);
        let mut buf = vec![0f32; nx * nmax];
        let mut out = vec![0f32; nmax];
        let mut v = vec![0usize; nmax];
        let mut zb = vec![0.0f64; nmax + 1];
        let far = FAR as f32;
        for pass in 0..2 {
            let (outer, n) = if pass == 0 { (nz, ny) } else { (ny, nz) };
            for o in 0..outer {
                // Row (x-run) index of line position t in this block.
                let row = |t: usize| if pass == 0 { t + ny * o } else { o + ny * t };
                for t in 0..n {
                    let src = &f[row(t) * nx..row(t) * nx + nx];
                    for (x, val) in src.iter().enumerate() {
                        buf[x * n + t] = *val;
                    }
                }
                for x in 0..nx {
                    let line = &mut buf[x * n..x * n + n];
                    if line.iter().all(|d| *d >= far) {
                        continue;
                    }
                    edt_1d(line, &mut out[..n], &mut v, &mut zb);
                    line.copy_from_slice(&out[..n]);
                }
                for t in 0..n {
                    let dst = &mut f[row(t) * nx..row(t) * nx + nx];
                    for (x, val) in dst.iter_mut().enumerate() {
                        *val = buf[x * n + t];
                    }
                }
            }
        }
        let two_hd = 3f64.sqrt() * h;
        let dist = f
            .iter()
            .map(|d2| (f64::from(*d2).sqrt() * h) as f32)
            .collect();
        Ok(Some(Self {
            origin,
            inv_h: 1.0 / h,
            h,
            dims,
            dist,
            // Slack for the f32 storage of distances.
            two_hd: two_hd + 1e-5,
            lo,
            hi,
            tree: KdTree::build(points),
        }))
    }

    /// Bounds `[lower, upper]` on the distance from `p` to the nearest cloud point.
    #[inline]
    pub fn distance_bounds(&self, p: &Point3<f64>) -> (f64, f64) {
        let c = (p - self.origin) * self.inv_h;
        if c.x >= 0.0 && c.y >= 0.0 && c.z >= 0.0 {
            let (x, y, z) = (c.x as usize, c.y as usize, c.z as usize);
            if x < self.dims[0] && y < self.dims[1] && z < self.dims[2] {
                let d = f64::from(self.dist[x + self.dims[0] * (y + self.dims[1] * z)]);
                return (d - self.two_hd, d + self.two_hd);
            }
        }
        // Outside the grid: every point lies in the cloud's bounding box.
        let q = p.coords.sup(&self.lo.coords).inf(&self.hi.coords);
        ((p.coords - q).norm(), f64::INFINITY)
    }

    /// A lower bound on the distance from `p` to the nearest cloud point.
    pub fn clearance(&self, p: &Point3<f64>) -> f64 {
        self.distance_bounds(p).0
    }

    /// True when some cloud point lies within `r` of `p` (exact).
    #[inline]
    pub fn touches(&self, p: &Point3<f64>, r: f64) -> bool {
        let (lo, hi) = self.distance_bounds(p);
        if lo > r {
            false
        } else if hi <= r {
            true
        } else {
            self.tree.any_within(p, r)
        }
    }

    /// The k-d tree over the cloud points (exact radius queries).
    pub fn tree(&self) -> &KdTree {
        &self.tree
    }

    /// Cell edge (m).
    pub fn cell(&self) -> f64 {
        self.h
    }
}

/// What a robot sphere touched.
#[derive(Copy, Clone, Debug, PartialEq, Eq)]
pub enum Hit {
    /// The observed cloud.
    Cloud,
    /// Static obstacle number `i`.
    Obstacle(usize),
}

/// What a ball may touch ([`World::near_ball`]): a bit per obstacle (all of them when there are
/// more than 64) and the cloud.
#[derive(Copy, Clone, Debug, PartialEq, Eq)]
pub struct Near {
    mask: u64,
    all: bool,
    cloud: bool,
}

impl Near {
    /// True when the ball touches nothing.
    #[inline]
    pub fn is_empty(&self) -> bool {
        self.mask == 0 && !self.all && !self.cloud
    }
}

/// Static geometry plus (optionally) an observed cloud.
#[derive(Clone, Debug, Default)]
pub struct World {
    /// Static obstacles.
    pub obstacles: Vec<Obstacle>,
    /// Bounding ball of each obstacle (centre, radius; infinite radius when unbounded): one
    /// distance rejects most sphere/obstacle pairs before the exact test.
    bounds: Vec<Bound>,
    field: Option<DistanceField>,
    points: Vec<Point3<f32>>,
    params: Option<CloudParams>,
}

impl World {
    /// A world with nothing in it.
    pub fn empty() -> Self {
        Self::default()
    }

    /// A world from a cloud in the base frame (and no static geometry yet).
    pub fn from_cloud(cloud: &PointCloud, params: &CloudParams) -> Result<Self, PlanError> {
        if cloud.frame != FrameId::Base {
            return Err(PlanError::BadWorld {
                what: format!(
                    "cloud is in frame {}, the planner needs the base frame; transform it first",
                    cloud.frame
                ),
            });
        }
        Ok(Self {
            obstacles: Vec::new(),
            bounds: Vec::new(),
            field: DistanceField::build(&cloud.points, params)?,
            points: cloud.points.clone(),
            params: Some(*params),
        })
    }

    /// Adds a static obstacle.
    pub fn with_obstacle(mut self, o: Obstacle) -> Self {
        self.bounds.push(Bound::of(&o));
        self.obstacles.push(o);
        self
    }

    /// The same static geometry without the cloud ("ignore collisions" keyframes).
    pub fn without_cloud(&self) -> Self {
        Self {
            obstacles: self.obstacles.clone(),
            bounds: self.bounds.clone(),
            field: None,
            points: Vec::new(),
            params: None,
        }
    }

    /// The same world with cloud points inside `inside` removed (rebuilds the field); `None`
    /// when no point was inside, so the caller can keep using `self`.
    pub fn without_points<F: Fn(&Point3<f64>) -> bool>(
        &self,
        inside: F,
    ) -> Result<Option<Self>, PlanError> {
        let Some(params) = self.params else {
            return Ok(None);
        };
        let kept: Vec<Point3<f32>> = self
            .points
            .iter()
            .filter(|p| !inside(&p.cast::<f64>()))
            .copied()
            .collect();
        if kept.len() == self.points.len() {
            return Ok(None);
        }
        Ok(Some(Self {
            obstacles: self.obstacles.clone(),
            bounds: self.bounds.clone(),
            field: DistanceField::build(&kept, &params)?,
            points: kept,
            params: Some(params),
        }))
    }

    /// Number of cloud points.
    pub fn cloud_len(&self) -> usize {
        self.points.len()
    }

    /// The distance field, if there is a cloud.
    pub fn field(&self) -> Option<&DistanceField> {
        self.field.as_ref()
    }

    /// The obstacles and cloud a ball of radius `r` at `c` may touch (a superset of those
    /// it touches): one test per obstacle for a whole group of spheres inside the ball.
    #[inline]
    pub fn near_ball(&self, c: &Point3<f64>, r: f64) -> Near {
        let cloud = self
            .field
            .as_ref()
            .is_some_and(|f| f.distance_bounds(c).0 <= r);
        if self.obstacles.len() > 64 {
            return Near {
                mask: 0,
                all: true,
                cloud,
            };
        }
        let mut mask = 0u64;
        for (i, (o, b)) in self.obstacles.iter().zip(&self.bounds).enumerate() {
            let reach = b.radius + r;
            if (c - b.center).norm_squared() <= reach * reach && b.distance(o, c) <= r {
                mask |= 1 << i;
            }
        }
        Near {
            mask,
            all: false,
            cloud,
        }
    }

    /// What the sphere touches among `near` (from [`Self::near_ball`] of a ball containing
    /// the sphere), if anything; the same answer as [`Self::sphere_hit`].
    #[inline]
    pub fn sphere_hit_near(&self, s: &Sphere, near: &Near) -> Option<Hit> {
        if near.all {
            return self.sphere_hit(s);
        }
        if near.cloud {
            if let Some(f) = &self.field {
                if f.touches(&s.center, s.radius) {
                    return Some(Hit::Cloud);
                }
            }
        }
        let mut m = near.mask;
        while m != 0 {
            let i = m.trailing_zeros() as usize;
            m &= m - 1;
            let (o, b) = (&self.obstacles[i], &self.bounds[i]);
            let reach = b.radius + s.radius;
            if (s.center - b.center).norm_squared() <= reach * reach
                && b.distance(o, &s.center) <= s.radius
            {
                return Some(Hit::Obstacle(i));
            }
        }
        None
    }

    /// What the sphere touches, if anything.
    #[inline]
    pub fn sphere_hit(&self, s: &Sphere) -> Option<Hit> {
        if let Some(f) = &self.field {
            if f.touches(&s.center, s.radius) {
                return Some(Hit::Cloud);
            }
        }
        for (i, (o, b)) in self.obstacles.iter().zip(&self.bounds).enumerate() {
            let reach = b.radius + s.radius;
            if (s.center - b.center).norm_squared() > reach * reach {
                continue;
            }
            if o.distance(&s.center) <= s.radius {
                return Some(Hit::Obstacle(i));
            }
        }
        None
    }

    /// Human-readable name of a hit.
    pub fn hit_name(&self, h: Hit) -> String {
        match h {
            Hit::Cloud => "the point cloud".into(),
            Hit::Obstacle(i) => self
                .obstacles
                .get(i)
                .map(|o| format!("obstacle {}", o.name()))
                .unwrap_or_else(|| "an obstacle".into()),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use rand::{Rng, SeedableRng};

    fn brute(points: &[Point3<f32>], p: &Point3<f64>) -> f64 {
        points
            .iter()
            .map(|q| (q.cast::<f64>() - p).norm())
            .fold(f64::INFINITY, f64::min)
    }

    #[test]
    fn field_clearance_is_a_tight_lower_bound_of_the_true_distance() {
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(5);
        let pts: Vec<Point3<f32>> = (0..400)
            .map(|_| {
                Point3::new(
                    rng.random_range(-0.3..0.3),
                    rng.random_range(-0.3..0.3),
                    rng.random_range(0.0..0.2),
                )
            })
            .collect();
        let cloud = PointCloud::new(FrameId::Base, pts.clone(), None).unwrap();
        let w = World::from_cloud(&cloud, &CloudParams::default()).unwrap();
        let f = w.field().unwrap();
        let slack = 2.0 * 3f64.sqrt() * 0.01 + 1e-6;
        for _ in 0..3000 {
            let p = Point3::new(
                rng.random_range(-0.8..0.8),
                rng.random_range(-0.8..0.8),
                rng.random_range(-0.5..0.7),
            );
            let truth = brute(&pts, &p);
            let c = f.clearance(&p);
            assert!(
                c <= truth + 1e-6,
                "clearance {c} > true distance {truth} at {p:?}"
            );
            if truth < 0.08 {
                assert!(
                    c >= truth - slack - 1e-4,
                    "clearance {c} too loose vs {truth}"
                );
            }
            // The sphere query is exact: compare with brute force at radii around the truth.
            for r in [truth - 0.004, truth + 0.004, rng.random_range(0.0..0.1)] {
                if r > 0.0 {
                    assert_eq!(f.touches(&p, r), truth <= r, "p {p:?} r {r} truth {truth}");
                }
            }
        }
    }

    #[test]
    fn obstacles_report_signed_distance_and_names() {
        let w = World::empty()
            .with_obstacle(Obstacle::HalfSpace {
                name: "table".into(),
                normal: Vector3::z_axis(),
                offset: 0.0,
            })
            .with_obstacle(Obstacle::Cuboid {
                name: "box".into(),
                pose: Isometry3::translation(1.0, 0.0, 0.5),
                half: Vector3::new(0.1, 0.1, 0.1),
            });
        let s = Sphere {
            center: Point3::new(1.0, 0.0, 0.65),
            radius: 0.06,
        };
        assert_eq!(w.sphere_hit(&s), Some(Hit::Obstacle(1)));
        assert_eq!(w.hit_name(Hit::Obstacle(1)), "obstacle box");
        let low = Sphere {
            center: Point3::new(0.0, 0.0, 0.03),
            radius: 0.05,
        };
        assert_eq!(w.sphere_hit(&low), Some(Hit::Obstacle(0)));
        let free = Sphere {
            center: Point3::new(0.0, 0.0, 0.3),
            radius: 0.05,
        };
        assert_eq!(w.sphere_hit(&free), None);
        let cyl = Obstacle::Cylinder {
            name: "c".into(),
            pose: Isometry3::identity(),
            radius: 0.1,
            half_length: 0.2,
        };
        assert!((cyl.distance(&Point3::new(0.3, 0.0, 0.0)) - 0.2).abs() < 1e-12);
        assert!((cyl.distance(&Point3::new(0.0, 0.0, 0.5)) - 0.3).abs() < 1e-12);
        assert!((cyl.distance(&Point3::new(0.0, 0.0, 0.0)) + 0.1).abs() < 1e-12);
    }

    #[test]
    fn cloud_in_camera_frame_and_huge_cloud_are_refused() {
        let c = PointCloud::new(FrameId::Camera(0), vec![Point3::origin()], None).unwrap();
        assert!(matches!(
            World::from_cloud(&c, &CloudParams::default()),
            Err(PlanError::BadWorld { .. })
        ));
        let c = PointCloud::new(
            FrameId::Base,
            vec![Point3::origin(), Point3::new(100.0, 100.0, 100.0)],
            None,
        )
        .unwrap();
        assert!(matches!(
            World::from_cloud(&c, &CloudParams::default()),
            Err(PlanError::BadWorld { .. })
        ));
    }
}
