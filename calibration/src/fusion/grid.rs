//! Dense grids for the fusion pipeline's voxelisation and neighbour search, and their
//! reusable buffers.
//!
//! Both replace hash maps: the workspace is small and known, so a flat array indexed by
//! cell finds a voxel with one load, and a counting sort of the points by cell (compressed
//! rows: one start offset per cell) makes every row of neighbouring cells one contiguous run
//! of points, stored as structure-of-arrays so that distances vectorise.

use nalgebra::{Point3, Vector3};

use super::{voxel_centroid, voxel_colour, voxel_downsample_hashed, Points};

/// Marks an unoccupied cell or brick of the voxel grid (entries hold an index + 1, so that
/// a fresh brick table is zeroed memory, which the allocator hands out without writing it).
const EMPTY: u32 = 0;

/// The most cells a voxel grid may have (a brick table of 512 kB; the EquAct workspace at
/// 5 mm needs 3.3 M cells, padded to whole bricks); larger boxes fall back to the hash map.
pub(super) const DENSE_VOXEL_CELLS: usize = 1 << 23;

/// Cells per brick edge of the voxel slots (see `CellBox::brick_index`).
const BRICK: usize = 4;

/// Cell coordinates are clamped to +-2^20 (the range of the packed hash keys).
const COORD_LIMIT: i64 = 1 << 20;

/// The grid cell of one coordinate: `floor(v * inv)`, clamped (NaN lands in cell 0).
/// Truncates and corrects instead of calling `floor`, which without SSE4.1 (the baseline
/// x86-64 target) is a library call that cost more than the rest of a voxel insert.
#[inline]
pub(super) fn cell_coord(v: f32, inv: f32) -> i64 {
    let t = v * inv;
    let i = t as i64;
    let i = if (i as f32) > t {
        i.saturating_sub(1)
    } else {
        i
    };
    i.clamp(-COORD_LIMIT, COORD_LIMIT - 1)
}

/// The voxel of `p` in a grid with corner `o` and inverse edge `inv`.
#[inline]
pub(super) fn voxel_coords(p: &Point3<f32>, o: &Vector3<f32>, inv: f32) -> [i64; 3] {
    [
        cell_coord(p.x - o.x, inv),
        cell_coord(p.y - o.y, inv),
        cell_coord(p.z - o.z, inv),
    ]
}

/// A box of grid cells: `dims[a]` cells from `lo[a]` on each axis, x fastest.
#[derive(Copy, Clone, Debug, PartialEq, Eq)]
pub(super) struct CellBox {
    /// The first cell on each axis.
    pub lo: [i64; 3],
    /// Cells per axis (each at least 1).
    pub dims: [usize; 3],
}

impl CellBox {
    /// The box from cell `lo` to cell `hi` (both included).
    pub fn spanning(lo: [i64; 3], hi: [i64; 3]) -> CellBox {
        CellBox {
            lo,
            dims: [0, 1, 2].map(|a| (hi[a] - lo[a]).max(0) as usize + 1),
        }
    }

    /// The smallest box holding every cell of `cells` (`None` when there is none).
    pub fn around(cells: impl Iterator<Item = [i64; 3]>) -> Option<CellBox> {
        let mut lo = [i64::MAX; 3];
        let mut hi = [i64::MIN; 3];
        for c in cells {
            for a in 0..3 {
                lo[a] = lo[a].min(c[a]);
                hi[a] = hi[a].max(c[a]);
            }
        }
        (lo[0] <= hi[0]).then(|| CellBox::spanning(lo, hi))
    }

    /// Number of cells (saturating).
    pub fn cells(&self) -> usize {
        self.dims.iter().fold(1usize, |n, &d| n.saturating_mul(d))
    }

    /// Number of cells with each axis padded to whole bricks of `BRICK` cells (saturating).
    pub fn brick_cells(&self) -> usize {
        self.dims
            .iter()
            .fold(1usize, |n, &d| n.saturating_mul(d.div_ceil(BRICK)))
            .saturating_mul(BRICK * BRICK * BRICK)
    }

    /// Cell `c` in a grid stored brick by brick (`BRICK`^3 cells each, x fastest inside a
    /// brick and among bricks): its brick and its index in it, or `None` outside the box.
    /// Neighbouring cells then mostly share cache lines, which a row-major grid of this size
    /// does not along y and z.
    #[inline]
    pub fn brick_index(&self, c: [i64; 3]) -> Option<(usize, usize)> {
        let mut r = [0usize; 3];
        for a in 0..3 {
            let v = c[a] - self.lo[a];
            if v < 0 || v as usize >= self.dims[a] {
                return None;
            }
            r[a] = v as usize;
        }
        let nb = self.dims.map(|d| d.div_ceil(BRICK));
        let brick = ((r[2] / BRICK) * nb[1] + r[1] / BRICK) * nb[0] + r[0] / BRICK;
        let inner = ((r[2] % BRICK) * BRICK + r[1] % BRICK) * BRICK + r[0] % BRICK;
        Some((brick, inner))
    }

    /// Cell `c` moved into the box (nearest cell on each axis).
    #[inline]
    fn clamp(&self, c: [i64; 3]) -> [usize; 3] {
        [0, 1, 2].map(|a| (c[a] - self.lo[a]).clamp(0, self.dims[a] as i64 - 1) as usize)
    }
}

/// Voxelisation buffers: a grid of voxel slots in bricks, allocated for the bricks that
/// hold points only, and the per-voxel sums.
#[derive(Default)]
pub(super) struct VoxelScratch {
    /// Per brick of the grid, where its slots start in `pool` divided by `BRICK`^3, plus one,
    /// or `EMPTY`; all `EMPTY` between calls.
    bricks: Vec<u32>,
    /// The slots of the bricks in use: per cell, the index of its voxel plus one, or
    /// `EMPTY`. A surface cloud fills few of the workspace's bricks, so this stays small
    /// and cached where a dense grid of the workspace takes 13 MB.
    pool: Vec<u32>,
    /// The bricks in use (to reset `bricks` afterwards).
    used: Vec<u32>,
    /// Per voxel, the sum of its points (f64: 10^4 points of one voxel lose no precision).
    sums: Vec<[f64; 3]>,
    /// Per voxel, the sum of its colours.
    colours: Vec<[u32; 3]>,
    /// Per voxel, its number of points.
    counts: Vec<u32>,
}

impl VoxelScratch {
    /// Voxel centroids of `points` (voxel edge `voxel_m`, grid corner `origin`) into `out`, in
    /// order of first occurrence. Uses the dense grid `grid` when given (it must hold every
    /// point's voxel; the pipeline's is the workspace's), else one around the points, and
    /// falls back to a hash map when that has more than `DENSE_VOXEL_CELLS` cells or a point
    /// lies outside it. All three give the same result.
    pub fn voxelise(
        &mut self,
        points: &Points,
        voxel_m: f64,
        origin: [f64; 3],
        grid: Option<CellBox>,
        out: &mut Points,
    ) {
        let inv = (1.0 / voxel_m) as f32;
        let o = Vector3::new(origin[0] as f32, origin[1] as f32, origin[2] as f32);
        // The box around the points from their extreme coordinates: a point's cell grows with
        // each coordinate, so these bound every cell (NaN ones excepted, which land in cell
        // 0 and, when that is outside, send the call to the hash map).
        let grid = grid.or_else(|| {
            let mut lo = Point3::from([f32::INFINITY; 3]);
            let mut hi = Point3::from([f32::NEG_INFINITY; 3]);
            for p in &points.xyz {
                lo = lo.inf(p);
                hi = hi.sup(p);
            }
            (lo.x <= hi.x && lo.y <= hi.y && lo.z <= hi.z)
                .then(|| CellBox::spanning(voxel_coords(&lo, &o, inv), voxel_coords(&hi, &o, inv)))
        });
        if let Some(g) = grid.filter(|g| g.brick_cells() <= DENSE_VOXEL_CELLS) {
            if self.accumulate(points, &g, &o, inv) {
                self.write(points.rgb.len() == points.len(), out);
                return;
            }
        }
        *out = voxel_downsample_hashed(points, voxel_m, origin);
    }

    /// Sums the points per voxel of `grid`; false when a point lies outside it.
    fn accumulate(&mut self, points: &Points, grid: &CellBox, o: &Vector3<f32>, inv: f32) -> bool {
        const CELLS: usize = BRICK * BRICK * BRICK;
        let n_bricks = grid.brick_cells() / CELLS;
        if self.bricks.is_empty() {
            self.bricks = vec![EMPTY; n_bricks];
        } else if self.bricks.len() < n_bricks {
            self.bricks.resize(n_bricks, EMPTY);
        }
        self.pool.clear();
        self.sums.clear();
        self.colours.clear();
        self.counts.clear();
        let has_rgb = points.rgb.len() == points.len();
        let mut inside = true;
        for (i, p) in points.xyz.iter().enumerate() {
            let Some((brick, inner)) = grid.brick_index(voxel_coords(p, o, inv)) else {
                inside = false;
                break;
            };
            let mut base = self.bricks[brick];
            if base == EMPTY {
                base = (self.pool.len() / CELLS) as u32 + 1;
                self.bricks[brick] = base;
                self.used.push(brick as u32);
                self.pool.resize(self.pool.len() + CELLS, EMPTY);
            }
            let cell = (base as usize - 1) * CELLS + inner;
            let mut slot = self.pool[cell];
            if slot == EMPTY {
                slot = self.sums.len() as u32 + 1;
                self.pool[cell] = slot;
                self.sums.push([0.0; 3]);
                self.colours.push([0; 3]);
                self.counts.push(0);
            }
            let s = slot as usize - 1;
            let sum = &mut self.sums[s];
            sum[0] += f64::from(p.x);
            sum[1] += f64::from(p.y);
            sum[2] += f64::from(p.z);
            if has_rgb {
                for (sum, &v) in self.colours[s].iter_mut().zip(&points.rgb[i]) {
                    *sum += u32::from(v);
                }
            }
            self.counts[s] += 1;
        }
        for &b in &self.used {
            self.bricks[b as usize] = EMPTY;
        }
        self.used.clear();
        inside
    }

    /// The centroids (and mean colours) of the accumulated voxels.
    fn write(&self, has_rgb: bool, out: &mut Points) {
        out.xyz.clear();
        out.rgb.clear();
        out.xyz.reserve(self.sums.len());
        out.xyz.extend(
            self.sums
                .iter()
                .zip(&self.counts)
                .map(|(s, &n)| voxel_centroid(s, n)),
        );
        if has_rgb {
            out.rgb.extend(
                self.colours
                    .iter()
                    .zip(&self.counts)
                    .map(|(c, &n)| voxel_colour(c, n)),
            );
        }
    }
}

/// Neighbour-search buffers: the points counting-sorted by grid cell, structure of arrays.
#[derive(Default)]
pub(super) struct KnnScratch {
    /// Per cell, the first of its points in the sorted arrays; one more entry at the end.
    start: Vec<u32>,
    /// Per input point, its cell (`u32::MAX`: not finite, not indexed).
    cell_of: Vec<u32>,
    /// Sorted positions.
    xs: Vec<f32>,
    ys: Vec<f32>,
    zs: Vec<f32>,
    /// Per sorted point, its input index.
    ids: Vec<u32>,
    /// Per axis, each cell's slab (widened a little; the border cells open outwards).
    walls: [Vec<[f32; 2]>; 3],
    /// Candidates' squared distances, as bits (non-negative floats order like their bits).
    cand: Vec<u32>,
    /// Candidates beyond the previous point's k-th distance (see `Block::within`).
    far: Vec<u32>,
    /// The points around the current cell.
    block: Block,
    /// Per input point, the result.
    pub mean: Vec<f32>,
}

/// The most cells a neighbour grid may have beyond two per point (4 MB of offsets); a
/// cloud spread wider is searched in a window of cells, the points outside it clamped into
/// its border cells (still exact, only slower for them).
const KNN_MIN_CELLS: usize = 1 << 20;

/// Neighbour-grid cells per distance cap: a cell's 3x3x3 block (about 80 points of a 5 mm
/// voxel cloud) then serves radii up to 13.6 mm, around the typical k-th distance (about
/// 13 mm at k = 20). Outlier-stage CPU time on the benchmark's cloud with 2.6, 3.0, 3.3 and
/// 3.6: 31, 27.6, 26.6 and 28.7 ms (the per-candidate cost of the block now outweighs the
/// searches past it that a smaller block leaves).
const KNN_CELLS_PER_CAP: f64 = 3.3;

/// The first search radius as a multiple of the previous point's k-th distance (callgrind
/// on the benchmark's cloud: 1.0, 1.05 and 1.3 cost 21 %, 4 % and 11 % more instructions).
const GUESS: f32 = 1.15;

/// Relative slack on search radii and cell walls: f32 rounding must never leave a point
/// that is within the radius outside the cells searched.
const SLACK: f32 = 1e-4;

impl KnnScratch {
    /// Each point's mean distance to its `k` nearest other points (`k` in 1..=64), each
    /// distance capped at `3 cell_m` and missing neighbours counted at that cap; into
    /// `self.mean`. Non-finite points are nobody's neighbour and get `+inf`.
    ///
    /// Exact: each point gathers the points within a radius r and, when more than k lie
    /// within it, its k nearest are among them. r is first a guess (the previous point's
    /// k-th distance `d_k(p)`, a little more, but no more than the block below serves when
    /// `d_k(p)` fits it: the points come in cell order, so neighbouring points with similar
    /// densities follow each other), then a bound that provably holds k
    /// neighbours (`d_k(p) + |p - q|`: p's k neighbours, or p itself in place of q, are all
    /// that close to q), then the cap; after a failed guess, first the largest radius the
    /// block below serves. Radii up to one cell edge are served from the points of the
    /// cell's 3x3x3 block, copied once per cell so that distances vectorise (computed once
    /// per point, whatever the radius); larger ones from the grid rows whose cells come
    /// within r. The block's candidates come split at the previous point's k-th distance,
    /// so that choosing the k + 1 nearest (the point itself among them) orders only the few
    /// on one side of it; their distances are summed in f64.
    /// Points clamped into a border cell are only extra candidates with their true
    /// distances, and border cells count as open towards the outside, so clamping keeps
    /// the search exact.
    pub fn mean_neighbour_distances(&mut self, points: &[Point3<f32>], k: usize, cell_m: f64) {
        let n = points.len();
        let k = k.clamp(1, 64);
        let cap = (3.0 * cell_m) as f32;
        let g = 3.0 * cell_m / KNN_CELLS_PER_CAP;
        let inv = (1.0 / g) as f32;
        let coords = |p: &Point3<f32>| [p.x, p.y, p.z].map(|v| cell_coord(v, inv));
        let finite = |p: &Point3<f32>| p.x.is_finite() && p.y.is_finite() && p.z.is_finite();
        self.mean.clear();
        self.mean.resize(n, f32::INFINITY);
        let Some(bbox) = CellBox::around(points.iter().filter(|p| finite(p)).map(coords)) else {
            return;
        };
        let grid = window(bbox, KNN_MIN_CELLS.max(2 * n), points, &coords, &finite);
        let [nx, ny, nz] = grid.dims;
        let slack = SLACK * g as f32;
        for (a, walls) in self.walls.iter_mut().enumerate() {
            let wall = |i: usize| {
                let w = (grid.lo[a] + i as i64) as f32 * g as f32;
                (w, slack + w.abs() * 1e-6)
            };
            walls.clear();
            walls.extend((0..grid.dims[a]).map(|i| {
                let ((lo, lo_eps), (hi, hi_eps)) = (wall(i), wall(i + 1));
                [
                    if i == 0 {
                        f32::NEG_INFINITY
                    } else {
                        lo - lo_eps
                    },
                    if i + 1 == grid.dims[a] {
                        f32::INFINITY
                    } else {
                        hi + hi_eps
                    },
                ]
            }));
        }

        // Counting sort by cell.
        if self.start.is_empty() {
            // Fresh buffers: zeroed memory comes from the allocator unwritten.
            self.start = vec![0; grid.cells() + 1];
        } else {
            self.start.clear();
            self.start.resize(grid.cells() + 1, 0);
        }
        self.cell_of.clear();
        for p in points {
            let c = if finite(p) {
                let [x, y, z] = grid.clamp(coords(p));
                let c = (z * ny + y) * nx + x;
                self.start[c + 1] += 1;
                c as u32
            } else {
                u32::MAX
            };
            self.cell_of.push(c);
        }
        for c in 0..grid.cells() {
            self.start[c + 1] += self.start[c];
        }
        let m = self.start[grid.cells()] as usize;
        self.xs.resize(m, 0.0);
        self.ys.resize(m, 0.0);
        self.zs.resize(m, 0.0);
        self.ids.resize(m, 0);
        // Scatter with `start` as the running cursor, then shift it back by one cell.
        for (i, (p, &c)) in points.iter().zip(&self.cell_of).enumerate() {
            if c != u32::MAX {
                let at = self.start[c as usize] as usize;
                self.start[c as usize] += 1;
                self.xs[at] = p.x;
                self.ys[at] = p.y;
                self.zs[at] = p.z;
                self.ids[at] = i as u32;
            }
        }
        self.start.copy_within(0..grid.cells(), 1);
        self.start[0] = 0;

        let search = Search {
            xs: &self.xs[..m],
            ys: &self.ys[..m],
            zs: &self.zs[..m],
            start: &self.start,
            walls: &self.walls,
            grid: &grid,
            inv,
            slack,
        };
        let cand = &mut self.cand;
        let far = &mut self.far;
        let block = &mut self.block;
        let mut prev: Option<([f32; 3], f32)> = None;
        let gf = g as f32;
        let mut c = 0usize;
        for cz in 0..nz {
            for cy in 0..ny {
                for cx in 0..nx {
                    let (first, end) = (self.start[c] as usize, self.start[c + 1] as usize);
                    c += 1;
                    if first == end {
                        continue;
                    }
                    // The 3x3x3 cells around this one: everything within one cell edge of
                    // any of its points, shared by all of them.
                    block.gather(&search, [cx, cy, cz]);
                    for qi in first..end {
                        let p = [self.xs[qi], self.ys[qi], self.zs[qi]];
                        let covered = gf * (1.0 - SLACK)
                            - p.iter().fold(0.0f32, |m, v| m.max(v.abs())) * 1e-6;
                        // First a guess (the previous point's k-th distance: neighbouring
                        // points see similar densities), then the bound, then the cap.
                        let (guess, bound, split) = match prev {
                            Some((q, kth)) => {
                                let d = ((p[0] - q[0]).powi(2)
                                    + (p[1] - q[1]).powi(2)
                                    + (p[2] - q[2]).powi(2))
                                .sqrt();
                                (kth * GUESS, ((kth + d) * (1.0 + SLACK)).min(cap), kth)
                            }
                            None => (cap, cap, cap),
                        };
                        // When the previous k-th distance fits the block, try the block first
                        // (the search past it costs several times more).
                        let mut r = guess.min(bound);
                        if split < covered {
                            r = r.min(covered);
                        }
                        let mut distances = false;
                        let mean = loop {
                            // Every point within r, the point itself included (at distance
                            // 0). With more than k of them, the k nearest are among them
                            // whatever r was.
                            // The candidates come split at the previous point's k-th
                            // distance: the near ones in cand[..near], the others in
                            // far[..beyond]. Usually about k are near, so the selection
                            // works on a few values.
                            let (near, beyond) = if r <= covered {
                                if !distances {
                                    block.distances(p);
                                    distances = true;
                                }
                                block.within(split.min(r), r, cand, far)
                            } else {
                                (search.gather(p, r, cand), 0)
                            };
                            if near > k {
                                // The k + 1 smallest (the point itself among them) into
                                // cand[..=k], the largest of them at k.
                                let kth = *cand[..near].select_nth_unstable(k).1;
                                prev = Some((p, f32::from_bits(kth).sqrt()));
                                break capped_mean(&cand[..=k], &[], k, cap);
                            }
                            if near + beyond > k {
                                // All the near ones and the nearest of the others.
                                let m = k - near;
                                let kth = *far[..beyond].select_nth_unstable(m).1;
                                prev = Some((p, f32::from_bits(kth).sqrt()));
                                break capped_mean(&cand[..near], &far[..=m], k, cap);
                            }
                            if r >= cap {
                                prev = None;
                                break capped_mean(&cand[..near], &far[..beyond], k, cap);
                            }
                            // Then all the block holds, the bound (which holds k neighbours
                            // unless f32 rounding bit), the cap.
                            r = if r < covered.min(bound) {
                                covered.min(bound)
                            } else if r < bound {
                                bound
                            } else {
                                cap
                            };
                        };
                        self.mean[self.ids[qi] as usize] = mean;
                    }
                }
            }
        }
    }
}

/// The points of a block of cells, copied contiguous so that distances to all of them
/// vectorise.
#[derive(Default)]
pub(super) struct Block {
    xs: Vec<f32>,
    ys: Vec<f32>,
    zs: Vec<f32>,
    /// Squared distances to the current point.
    d2: Vec<f32>,
}

impl Block {
    /// Copies the points of the 3x3x3 cells around `cell` (clamped to the grid).
    fn gather(&mut self, search: &Search<'_>, cell: [usize; 3]) {
        self.xs.clear();
        self.ys.clear();
        self.zs.clear();
        let [nx, ny, nz] = search.grid.dims;
        let [cx, cy, cz] = cell;
        let (x0, x1) = (cx.saturating_sub(1), (cx + 1).min(nx - 1));
        for z in cz.saturating_sub(1)..=(cz + 1).min(nz - 1) {
            for y in cy.saturating_sub(1)..=(cy + 1).min(ny - 1) {
                let row = (z * ny + y) * nx;
                let s = search.start[row + x0] as usize;
                let e = search.start[row + x1 + 1] as usize;
                self.xs.extend_from_slice(&search.xs[s..e]);
                self.ys.extend_from_slice(&search.ys[s..e]);
                self.zs.extend_from_slice(&search.zs[s..e]);
            }
        }
    }

    /// Squared distances of the block's points to `p`.
    fn distances(&mut self, p: [f32; 3]) {
        self.d2.resize(self.xs.len(), 0.0);
        for (((d2, &x), &y), &z) in self.d2.iter_mut().zip(&self.xs).zip(&self.ys).zip(&self.zs) {
            let (dx, dy, dz) = (x - p[0], y - p[1], z - p[2]);
            *d2 = dx * dx + dy * dy + dz * dz;
        }
    }

    /// The squared distances (as bits, from the last `distances`) up to `split` into
    /// `near`, those above it and up to `r` into `far`; returns how many of each.
    fn within(
        &self,
        split: f32,
        r: f32,
        near: &mut Vec<u32>,
        far: &mut Vec<u32>,
    ) -> (usize, usize) {
        let n = self.d2.len();
        for buf in [&mut *near, &mut *far] {
            if buf.len() < n {
                buf.resize(n, 0);
            }
        }
        let (s2, r2) = (split * split, r * r);
        let (mut n_near, mut n_far) = (0, 0);
        for &d2 in &self.d2 {
            let bits = d2.to_bits();
            near[n_near] = bits;
            far[n_far] = bits;
            let is_near = d2 <= s2;
            n_near += usize::from(is_near);
            n_far += usize::from(!is_near & (d2 <= r2));
        }
        (n_near, n_far)
    }
}

/// The sorted points and their grid, for gathering the points within a radius.
struct Search<'a> {
    xs: &'a [f32],
    ys: &'a [f32],
    zs: &'a [f32],
    start: &'a [u32],
    walls: &'a [Vec<[f32; 2]>; 3],
    grid: &'a CellBox,
    inv: f32,
    /// Absolute slack on radii (m).
    slack: f32,
}

impl Search<'_> {
    /// The cells (clamped into the grid) that hold coordinates within `r` of `v` on axis `a`.
    #[inline]
    fn span(&self, a: usize, v: f32, r: f32) -> (usize, usize) {
        let r = r * (1.0 + SLACK) + self.slack + v.abs() * 1e-6;
        let cell = |v: f32| {
            (cell_coord(v, self.inv) - self.grid.lo[a]).clamp(0, self.grid.dims[a] as i64 - 1)
                as usize
        };
        (cell(v - r), cell(v + r))
    }

    /// Distance from `v` to cell `i`'s slab on axis `a` (0 inside).
    #[inline]
    fn gap(&self, a: usize, i: usize, v: f32) -> f32 {
        let [lo, hi] = self.walls[a][i];
        (lo - v).max(v - hi).max(0.0)
    }

    /// Squared distances (as bits) of every point within `r` of `p` into `cand[..n]`;
    /// returns n.
    fn gather(&self, p: [f32; 3], r: f32, cand: &mut Vec<u32>) -> usize {
        let r2 = r * r;
        let (nx, ny) = (self.grid.dims[0], self.grid.dims[1]);
        let (x0, x1) = self.span(0, p[0], r);
        let (y0, y1) = self.span(1, p[1], r);
        let (z0, z1) = self.span(2, p[2], r);
        let mut used = 0;
        for z in z0..=z1 {
            let gz = self.gap(2, z, p[2]);
            for y in y0..=y1 {
                let gy = self.gap(1, y, p[1]);
                if gz * gz + gy * gy > r2 {
                    continue;
                }
                let row = (z * ny + y) * nx;
                let (s, e) = (
                    self.start[row + x0] as usize,
                    self.start[row + x1 + 1] as usize,
                );
                if cand.len() < used + (e - s) {
                    cand.resize(used + (e - s), 0);
                }
                for ((&x, &y), &z) in self.xs[s..e].iter().zip(&self.ys[s..e]).zip(&self.zs[s..e]) {
                    let (dx, dy, dz) = (x - p[0], y - p[1], z - p[2]);
                    let d2 = dx * dx + dy * dy + dz * dz;
                    cand[used] = d2.to_bits();
                    used += usize::from(d2 <= r2);
                }
            }
        }
        used
    }
}

/// Mean of the capped distances of `best` and `more` (squared, as bits; the point itself among them at
/// distance 0), the missing ones of `k` counted at the cap. Summed in f64, which for these
/// few f32 values is exact in practice whatever their order (the selection leaves them in
/// none in particular).
fn capped_mean(best: &[u32], more: &[u32], k: usize, cap: f32) -> f32 {
    let sum: f64 = best
        .iter()
        .chain(more)
        .map(|&d2| f64::from(f32::from_bits(d2).sqrt().min(cap)))
        .sum();
    ((sum + (k + 1 - best.len() - more.len()) as f64 * f64::from(cap)) / k as f64) as f32
}

/// `bbox` shrunk to at most `budget` cells: the widest axis first, to a window centred on the
/// points' median cell on that axis.
fn window(
    bbox: CellBox,
    budget: usize,
    points: &[Point3<f32>],
    coords: &impl Fn(&Point3<f32>) -> [i64; 3],
    finite: &impl Fn(&Point3<f32>) -> bool,
) -> CellBox {
    let mut b = bbox;
    while b.cells() > budget {
        let a = (0..3).max_by_key(|&a| b.dims[a]).unwrap_or(0);
        if b.dims[a] == 1 {
            break;
        }
        let others = b.dims[(a + 1) % 3].saturating_mul(b.dims[(a + 2) % 3]);
        let d = (budget / others.max(1)).clamp(1, b.dims[a] - 1);
        let mut on_axis: Vec<i64> = points
            .iter()
            .filter(|p| finite(p))
            .map(|p| coords(p)[a])
            .collect();
        let mid = on_axis.len() / 2;
        let median = *on_axis.select_nth_unstable(mid).1;
        b.lo[a] = median - (d / 2) as i64;
        b.dims[a] = d;
    }
    b
}
