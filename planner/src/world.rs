//! The world the robot must not touch (issue 3 item 2): static primitives (table plane, boxes,
//! cylinders, balls) and an observed point cloud turned into a Euclidean distance field.
//!
//! The field holds, per cell, the squared grid distance (cells) to the nearest cell holding a
//! point, exact up to [`FIELD_CAP_CELLS`] cells (one byte per cell; three separable
//! windowed-minimum passes along contiguous rows) and a coarser lower bound beyond it. For
//! any query point in a cell whose grid distance is `D`, the true distance to the cloud lies
//! in `[D − √3·h, D + √3·h]`: a sphere query is one lookup and two compares, and only spheres
//! whose radius falls in that band (a thin shell around the cloud) go on to an exact query of
//! the bounding-volume tree over the points. The answer is exact (up to f32 rounding of the
//! points, resolved towards contact), never conservative by a cell.

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

/// Grid distances up to this many cells are stored exactly; larger ones only as "beyond".
/// It should exceed the largest robot sphere radius plus the cell slack (8 cm + 1.7 cm at
/// the default 1 cm cell) so that no sphere far from the cloud needs an exact query; each
/// cell more costs two more vector operations per cell in the Y and Z passes.
pub const FIELD_CAP_CELLS: usize = 10;
const CAP2: u8 = (FIELD_CAP_CELLS * FIELD_CAP_CELLS) as u8;
/// Stored squared distance meaning "more than the cap".
const BEYOND: u8 = u8::MAX;
/// Brick edge (cells, a power of two) of the coarse lower bound used beyond the cap.
const BRICK_SHIFT: usize = 3;
const BRICK: usize = 1 << BRICK_SHIFT;

/// A distance field over a cloud: per cell, the squared grid distance (cells) to the nearest
/// cell holding a point, exact up to [`FIELD_CAP_CELLS`] cells and "beyond" past it (one byte
/// per cell); beyond the cap, a lower bound per brick of `BRICK³` cells from a distance
/// transform of the bricks holding points.
///
/// The build is three separable passes of a windowed minimum (`min over |d| ≤ cap of
/// g(i + d) + d²`, saturating bytes) that run along whole contiguous x rows, so they
/// vectorize and need no transposes: a few milliseconds for millions of cells.
#[derive(Clone, Debug)]
pub struct DistanceField {
    origin: Point3<f64>,
    inv_h: f64,
    h: f64,
    dims: [usize; 3],
    /// Squared grid distance per cell (x fastest, rows `row` long), `BEYOND` past the cap.
    sq: Vec<u8>,
    /// Stored row length (≥ `dims[0]`).
    row: usize,
    /// Metres of each stored squared distance (`√v · h`; the cap for `BEYOND`).
    metres: [f32; 256],
    /// Bricks along x, y, z.
    bdims: [usize; 3],
    /// Per brick: a lower bound (m) on the grid distance from its cells to any point's cell.
    coarse: Vec<f32>,
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

/// Squared Euclidean distance transform of a small dense grid in place (x fastest).
fn edt_3d_dense(f: &mut [f32], dims: [usize; 3]) {
    let n = dims[0].max(dims[1]).max(dims[2]);
    let (mut line, mut out) = (vec![0f32; n], vec![0f32; n]);
    let (mut v, mut z) = (vec![0usize; n], vec![0f64; n + 1]);
    let stride = [1, dims[0], dims[0] * dims[1]];
    for axis in 0..3 {
        let (a, b) = ((axis + 1) % 3, (axis + 2) % 3);
        let len = dims[axis];
        for i in 0..dims[a] {
            for k in 0..dims[b] {
                let base = i * stride[a] + k * stride[b];
                for t in 0..len {
                    line[t] = f[base + t * stride[axis]];
                }
                edt_1d(&line[..len], &mut out[..len], &mut v, &mut z);
                for t in 0..len {
                    f[base + t * stride[axis]] = out[t];
                }
            }
        }
    }
}

/// Row length granule (bytes): rows are padded to a multiple of it so that the byte loops
/// below run whole vectors with no scalar tail.
const LANES: usize = 32;

/// `out[i] = min(out[i], inp[i] + add)`, saturating (byte adds and mins, `LANES` at a time;
/// both lengths are multiples of `LANES`).
#[inline]
fn min_add_row(out: &mut [u8], inp: &[u8], add: u8) {
    for (o, i) in out.chunks_exact_mut(LANES).zip(inp.chunks_exact(LANES)) {
        for k in 0..LANES {
            o[k] = o[k].min(i[k].saturating_add(add));
        }
    }
}

/// `out[i] = inp[i] + add`, saturating, like [`min_add_row`].
#[inline]
fn add_row(out: &mut [u8], inp: &[u8], add: u8) {
    for (o, i) in out.chunks_exact_mut(LANES).zip(inp.chunks_exact(LANES)) {
        for k in 0..LANES {
            o[k] = i[k].saturating_add(add);
        }
    }
}

/// One windowed pass: output block `o` (of `len` bytes at `o · step` in `dst`) is the
/// minimum over sources `t` with `|t − o| ≤ cap` of source block `t` plus `(t − o)²`; blocks
/// `base + i · stride` for `i < n`. `any_in` flags source blocks holding anything under
/// `BEYOND` (others are skipped); `any_out` gets the same for the output.
#[allow(clippy::too_many_arguments)]
fn window_pass(
    src: &[u8],
    dst: &mut [u8],
    len: usize,
    base: usize,
    stride: usize,
    n: usize,
    any_in: &[bool],
    any_out: &mut [bool],
) {
    let cap = FIELD_CAP_CELLS;
    for o in 0..n {
        let ob = base + o * stride;
        let out = &mut dst[ob * len..ob * len + len];
        let mut touched = false;
        for t in o.saturating_sub(cap)..(o + cap + 1).min(n) {
            let ib = base + t * stride;
            if !any_in[ib] {
                continue;
            }
            let add = (t.abs_diff(o) * t.abs_diff(o)) as u8;
            let inp = &src[ib * len..ib * len + len];
            if touched {
                min_add_row(out, inp, add);
            } else {
                add_row(out, inp, add);
                touched = true;
            }
        }
        if !touched {
            out.fill(BEYOND);
        }
        any_out[ob] = touched;
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
        // Stored row length: x runs padded to whole vectors (the padding holds no site and
        // is never read back).
        let nxs = nx.next_multiple_of(LANES);
        let bdims = dims.map(|d| d.div_ceil(BRICK));
        let mut occupied = vec![FAR as f32; bdims[0] * bdims[1] * bdims[2]];
        // Sites: the cells holding a point (all inside the grid: it spans their bounds plus
        // the pad). X pass on the fly: rows are contiguous and sites binary, so two sweeps
        // over the rows holding a site give the capped 1-D squared distance.
        let mut a = vec![BEYOND; nxs * ny * nz];
        let mut row_any = vec![false; ny * nz];
        for p in points {
            let c = (p.cast::<f64>() - origin) * (1.0 / h);
            let (x, y, z) = (
                (c.x as usize).min(nx - 1),
                (c.y as usize).min(ny - 1),
                (c.z as usize).min(nz - 1),
            );
            a[x + nxs * (y + ny * z)] = 0;
            row_any[y + ny * z] = true;
            occupied[(x >> BRICK_SHIFT)
                + bdims[0] * ((y >> BRICK_SHIFT) + bdims[1] * (z >> BRICK_SHIFT))] = 0.0;
        }
        let cap = FIELD_CAP_CELLS;
        // X pass: the same windowed minimum along each row holding a site, over a copy of
        // the row with `cap` cells of nothing on either side.
        let mut buf = vec![BEYOND; nxs + 2 * cap];
        for (r, row) in a.chunks_exact_mut(nxs).enumerate() {
            if !row_any[r] {
                continue;
            }
            buf[cap..cap + nxs].copy_from_slice(row);
            for d in 1..=cap {
                let add = (d * d) as u8;
                min_add_row(row, &buf[cap + d..cap + d + nxs], add);
                min_add_row(row, &buf[cap - d..cap - d + nxs], add);
            }
        }
        // Y pass along the rows of each z slab, then Z pass with whole slabs as blocks, back
        // and forth between two grids.
        let mut b = vec![BEYOND; nxs * ny * nz];
        let mut row_any_b = vec![false; ny * nz];
        for z in 0..nz {
            window_pass(&a, &mut b, nxs, ny * z, 1, ny, &row_any, &mut row_any_b);
        }
        let slab_any: Vec<bool> = row_any_b
            .chunks_exact(ny)
            .map(|r| r.contains(&true))
            .collect();
        let mut slab_out = vec![false; nz];
        window_pass(&b, &mut a, nxs * ny, 0, 1, nz, &slab_any, &mut slab_out);
        // Anything over the cap is not exact (the window saw only sites within the cap).
        for v in &mut a {
            if *v > CAP2 {
                *v = BEYOND;
            }
        }
        let mut metres = [0f32; 256];
        for (v, m) in metres.iter_mut().enumerate() {
            *m = ((v as f64).sqrt().min(cap as f64) * h) as f32;
        }
        metres[usize::from(BEYOND)] = (cap as f64 * h) as f32;
        // Beyond the cap: at least the cap, and at least the brick-level distance less the
        // two bricks' half diagonals.
        edt_3d_dense(&mut occupied, bdims);
        let diag = 3f64.sqrt() * (BRICK as f64 - 1.0);
        let coarse = occupied
            .iter()
            .map(|d2| {
                let lb = (f64::from(*d2).sqrt() * BRICK as f64 - diag).max(cap as f64);
                (lb * h) as f32
            })
            .collect();
        let two_hd = 3f64.sqrt() * h;
        Ok(Some(Self {
            origin,
            inv_h: 1.0 / h,
            h,
            dims,
            sq: a,
            row: nxs,
            metres,
            bdims,
            coarse,
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
                let v = self.sq[x + self.row * (y + self.dims[1] * z)];
                if v != BEYOND {
                    let d = f64::from(self.metres[usize::from(v)]);
                    return (d - self.two_hd, d + self.two_hd);
                }
                let bd = self.bdims;
                let b =
                    (x >> BRICK_SHIFT) + bd[0] * ((y >> BRICK_SHIFT) + bd[1] * (z >> BRICK_SHIFT));
                return (f64::from(self.coarse[b]) - self.two_hd, f64::INFINITY);
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

    /// The bounding-volume tree over the cloud points (exact radius queries).
    pub fn tree(&self) -> &KdTree {
        &self.tree
    }

    /// Cell edge (m).
    pub fn cell(&self) -> f64 {
        self.h
    }

    /// Grid size in cells along x, y, z.
    pub fn dims(&self) -> [usize; 3] {
        self.dims
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

    /// The capped byte field against brute force on surface-like clouds (planes sampled at
    /// the cell size, as the MBM clouds are, plus scattered points): the bounds always hold
    /// the true distance, are the cell slack wide within the cap, and the sphere query is
    /// exact at every radius.
    #[test]
    fn capped_field_bounds_hold_the_brute_force_distance_on_surface_clouds() {
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(11);
        for trial in 0..3 {
            let mut pts: Vec<Point3<f32>> = Vec::new();
            for _ in 0..3 {
                let o = Vector3::new(
                    rng.random_range(-0.3..0.3),
                    rng.random_range(-0.3..0.3),
                    rng.random_range(-0.2..0.2),
                );
                let (u, v) = if trial % 2 == 0 {
                    (Vector3::x(), Vector3::y())
                } else {
                    (Vector3::y(), Vector3::z())
                };
                for i in 0..30 {
                    for k in 0..30 {
                        let p = o + u * (i as f64 * 0.01) + v * (k as f64 * 0.01);
                        pts.push(Point3::from(p).cast::<f32>());
                    }
                }
            }
            for _ in 0..50 {
                pts.push(Point3::new(
                    rng.random_range(-0.4..0.4),
                    rng.random_range(-0.4..0.4),
                    rng.random_range(-0.3..0.3),
                ));
            }
            let params = CloudParams {
                cell: [0.01, 0.02, 0.013][trial],
                ..CloudParams::default()
            };
            let f = DistanceField::build(&pts, &params).unwrap().unwrap();
            let slack = 3f64.sqrt() * params.cell + 1e-5;
            // Beyond the pad the query is outside the grid (bounding-box bound only).
            let cap = (FIELD_CAP_CELLS as f64 * params.cell).min(params.pad);
            for _ in 0..4000 {
                let p = Point3::new(
                    rng.random_range(-0.7..0.7),
                    rng.random_range(-0.7..0.7),
                    rng.random_range(-0.6..0.6),
                );
                let truth = brute(&pts, &p);
                let (lo, hi) = f.distance_bounds(&p);
                assert!(
                    lo <= truth + 1e-6 && truth <= hi + 1e-6,
                    "{lo} {truth} {hi}"
                );
                if truth + slack < cap {
                    assert!(hi - lo <= 2.0 * slack + 1e-6, "{lo} {hi} at {truth}");
                }
                for r in [truth - 0.003, truth + 0.003, rng.random_range(0.0..0.15)] {
                    if r > 0.0 {
                        assert_eq!(f.touches(&p, r), truth <= r, "p {p:?} r {r} truth {truth}");
                    }
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
