//! Board corners in IR images (issue 8 item 1), and a renderer of the board's IR image for
//! tests and the simulator. [`detect_board`] picks the detector of the board's kind: the
//! chessboard detector below, or [`crate::aprilgrid`]'s.
//!
//! Detection, for a plain chessboard whose every inner corner is in view:
//! 1. Gaussian blur, then the saddle response `Ixy^2 - Ixx Iyy` of the Hessian (positive at
//!    X-junctions, near zero on edges), non-maximum suppression and a relative threshold.
//! 2. Sub-pixel refinement by gradient orthogonality (the method of OpenCV's
//!    `cornerSubPix`): the corner `q` solves `sum w g g^T (p - q) = 0` over a window.
//! 3. Grid growing from the candidate nearest the centre: predict each neighbour from the
//!    local grid step, take the nearest candidate within 35 % of a step.
//! 4. Labelling: of the 8 symmetries of the grid, keep the one whose extents match the
//!    board, whose axes have the board frame's handedness seen from the front, and where the
//!    square diagonally inside corner 0 is dark. A board with `rows + cols` even looks the
//!    same turned by 180° (as a plain chessboard it is ambiguous, use an AprilGrid or an
//!    odd sum): that is an error rather than a guess.
//!
//! Pixels follow this crate's convention: (0, 0) is the centre of the top-left pixel.
//!
//! Printed layout assumed by [`render_board_ir`]: `(rows + 1) x (cols + 1)` squares of side
//! `square_m`, square `(i, j)` (row, column) dark when `i + j` is even, so the squares at
//! corner 0 on its diagonal are dark; a white margin of half a square around.

use std::collections::{HashMap, VecDeque};

use cell_types::{CameraFrame, Image};
use nalgebra::{Isometry3, Matrix2, Point2, Point3, Vector2};

use crate::board::{BoardConfig, BoardKind};
use crate::camera::raw_depth_to_m;
use crate::camera::Intrinsics;
use crate::capture::{CameraView, Corner, DepthSample};
use crate::error::CalibrationError;

/// Grey levels of a rendered board image.
#[derive(Copy, Clone, Debug, PartialEq)]
pub struct IrLevels {
    /// Where the ray misses the board.
    pub background: u8,
    /// Dark squares.
    pub dark: u8,
    /// Light squares and the margin.
    pub light: u8,
}

impl Default for IrLevels {
    fn default() -> Self {
        Self {
            background: 90,
            dark: 25,
            light: 210,
        }
    }
}

/// Grey level of the board at board-frame point `(x, y)`, or `None` off the board.
fn board_level(board: &BoardConfig, x: f64, y: f64, levels: &IrLevels) -> Option<f64> {
    match board.kind {
        BoardKind::Chessboard => chessboard_level(board, x, y, levels),
        BoardKind::AprilGrid => crate::aprilgrid::level(board, x, y, levels),
    }
}

/// Grey level of a chessboard at board-frame point `(x, y)`, or `None` off the board.
fn chessboard_level(board: &BoardConfig, x: f64, y: f64, levels: &IrLevels) -> Option<f64> {
    let s = board.square_m;
    let (cols, rows) = (f64::from(board.cols), f64::from(board.rows));
    if x < -1.5 * s || y < -1.5 * s || x > (cols + 0.5) * s || y > (rows + 0.5) * s {
        return None;
    }
    let j = (x / s + 1.0).floor();
    let i = (y / s + 1.0).floor();
    let inside = (0.0..=cols).contains(&j) && (0.0..=rows).contains(&i);
    let dark = inside && (i + j).rem_euclid(2.0) < 0.5;
    Some(f64::from(if dark { levels.dark } else { levels.light }))
}

/// Renders the IR image of `board` seen with `camera_from_board` through `k`: each pixel
/// averages 8 x 8 rays (anti-aliased edges, so corners keep sub-pixel information).
pub fn render_board_ir(
    k: &Intrinsics,
    camera_from_board: &Isometry3<f64>,
    board: &BoardConfig,
    levels: &IrLevels,
) -> Image<u8> {
    let (w, h) = (k.width, k.height);
    let mut img = Image::filled(w, h, levels.background);
    let board_from_camera = camera_from_board.inverse();
    let n = camera_from_board.rotation * nalgebra::Vector3::z();
    let t = camera_from_board.translation.vector;
    // Only pixels near the board's projection (pattern and margin) need rays.
    let [lo_b, hi_b] = board.pattern_bounds();
    let m = board.square_m;
    let outline = [
        Point3::new(lo_b[0] - m, lo_b[1] - m, 0.0),
        Point3::new(hi_b[0] + m, lo_b[1] - m, 0.0),
        Point3::new(lo_b[0] - m, hi_b[1] + m, 0.0),
        Point3::new(hi_b[0] + m, hi_b[1] + m, 0.0),
    ];
    let mut lo = Vector2::new(f64::from(w), f64::from(h));
    let mut hi = Vector2::new(0.0, 0.0);
    for p in outline {
        match k.project(&(camera_from_board * p)) {
            Ok(px) => {
                lo = lo.inf(&px.coords);
                hi = hi.sup(&px.coords);
            }
            Err(_) => {
                lo = Vector2::zeros();
                hi = Vector2::new(f64::from(w), f64::from(h));
            }
        }
    }
    let u0 = (lo.x.floor() as i64 - 1).clamp(0, i64::from(w)) as u32;
    let u1 = (hi.x.ceil() as i64 + 2).clamp(0, i64::from(w)) as u32;
    let v0 = (lo.y.floor() as i64 - 1).clamp(0, i64::from(h)) as u32;
    let v1 = (hi.y.ceil() as i64 + 2).clamp(0, i64::from(h)) as u32;
    const N: usize = 8;
    let sub: [f64; N] = std::array::from_fn(|i| (i as f64 + 0.5) / N as f64 - 0.5);
    for v in v0..v1 {
        for u in u0..u1 {
            let mut sum = 0.0;
            for dv in sub {
                for du in sub {
                    let px = Point2::new(f64::from(u) + du, f64::from(v) + dv);
                    let level = k.pixel_ray(px).ok().and_then(|ray| {
                        let denom = n.dot(&ray);
                        let lambda = n.dot(&t) / denom;
                        if !(denom.abs() > 1e-12 && lambda > 0.0) {
                            return None;
                        }
                        let p = board_from_camera * Point3::from(ray * lambda);
                        board_level(board, p.x, p.y, levels)
                    });
                    sum += level.unwrap_or(f64::from(levels.background));
                }
            }
            let k_ = v as usize * w as usize + u as usize;
            if let Some(px) = img.data.get_mut(k_) {
                *px = (sum / (N * N) as f64).round().clamp(0.0, 255.0) as u8;
            }
        }
    }
    img
}

/// Detector settings.
#[derive(Copy, Clone, Debug, PartialEq)]
pub struct DetectParams {
    /// Gaussian blur before the saddle response (px).
    pub blur_sigma: f64,
    /// Candidates must reach this fraction of the strongest saddle response.
    pub min_response: f64,
    /// Half-size of the sub-pixel window (px).
    pub subpix_radius: i64,
}

impl Default for DetectParams {
    fn default() -> Self {
        Self {
            blur_sigma: 1.0,
            min_response: 0.1,
            subpix_radius: 6,
        }
    }
}

/// A float image with bilinear sampling.
struct Gray {
    w: usize,
    h: usize,
    d: Vec<f64>,
}

impl Gray {
    fn at(&self, x: usize, y: usize) -> f64 {
        self.d[y * self.w + x]
    }
    fn bilinear(&self, p: Point2<f64>) -> Option<f64> {
        let (x0, y0) = (p.x.floor(), p.y.floor());
        if x0 < 0.0 || y0 < 0.0 || x0 + 1.0 >= self.w as f64 || y0 + 1.0 >= self.h as f64 {
            return None;
        }
        let (fx, fy) = (p.x - x0, p.y - y0);
        let (x, y) = (x0 as usize, y0 as usize);
        Some(
            self.at(x, y) * (1.0 - fx) * (1.0 - fy)
                + self.at(x + 1, y) * fx * (1.0 - fy)
                + self.at(x, y + 1) * (1.0 - fx) * fy
                + self.at(x + 1, y + 1) * fx * fy,
        )
    }
}

fn blur(img: &Image<u8>, sigma: f64) -> Gray {
    let (w, h) = (img.width as usize, img.height as usize);
    let r = (3.0 * sigma).ceil().max(1.0) as i64;
    let kernel: Vec<f64> = (-r..=r)
        .map(|i| (-(i * i) as f64 / (2.0 * sigma * sigma)).exp())
        .collect();
    let norm: f64 = kernel.iter().sum();
    let src: Vec<f64> = img.data.iter().map(|v| f64::from(*v)).collect();
    let mut tmp = vec![0.0; w * h];
    let clampi = |v: i64, n: usize| v.clamp(0, n as i64 - 1) as usize;
    for y in 0..h {
        for x in 0..w {
            let mut s = 0.0;
            for (k, kv) in kernel.iter().enumerate() {
                s += kv * src[y * w + clampi(x as i64 + k as i64 - r, w)];
            }
            tmp[y * w + x] = s / norm;
        }
    }
    let mut out = vec![0.0; w * h];
    for y in 0..h {
        for x in 0..w {
            let mut s = 0.0;
            for (k, kv) in kernel.iter().enumerate() {
                s += kv * tmp[clampi(y as i64 + k as i64 - r, h) * w + x];
            }
            out[y * w + x] = s / norm;
        }
    }
    Gray { w, h, d: out }
}

/// Saddle-point candidates (pixel positions), strongest first.
fn saddles(g: &Gray, min_response: f64) -> Vec<Point2<f64>> {
    let (w, h) = (g.w, g.h);
    if w < 8 || h < 8 {
        return Vec::new();
    }
    let mut resp = vec![0.0; w * h];
    let mut max: f64 = 0.0;
    for y in 1..h - 1 {
        for x in 1..w - 1 {
            let ixx = g.at(x + 1, y) - 2.0 * g.at(x, y) + g.at(x - 1, y);
            let iyy = g.at(x, y + 1) - 2.0 * g.at(x, y) + g.at(x, y - 1);
            let ixy = (g.at(x + 1, y + 1) - g.at(x + 1, y - 1) - g.at(x - 1, y + 1)
                + g.at(x - 1, y - 1))
                / 4.0;
            let s = ixy * ixy - ixx * iyy;
            resp[y * w + x] = s;
            max = max.max(s);
        }
    }
    let thr = min_response * max;
    let mut out = Vec::new();
    const R: usize = 1;
    for y in R + 1..h - R - 1 {
        for x in R + 1..w - R - 1 {
            let s = resp[y * w + x];
            if s <= thr || s <= 0.0 {
                continue;
            }
            let mut is_max = true;
            'n: for yy in y - R..=y + R {
                for xx in x - R..=x + R {
                    let o = resp[yy * w + xx];
                    if o > s || (o == s && (yy, xx) < (y, x)) {
                        is_max = false;
                        break 'n;
                    }
                }
            }
            if is_max {
                out.push((s, Point2::new(x as f64, y as f64)));
            }
        }
    }
    out.sort_by(|a, b| b.0.total_cmp(&a.0));
    out.into_iter().map(|(_, p)| p).collect()
}

/// Gradient-orthogonality sub-pixel refinement of a corner near `start`.
fn refine(g: &Gray, start: Point2<f64>, radius: i64) -> Option<Point2<f64>> {
    let mut q = start;
    let sigma = radius as f64 / 1.5;
    for _ in 0..30 {
        let (cx, cy) = (q.x.round() as i64, q.y.round() as i64);
        let mut a = Matrix2::zeros();
        let mut b = Vector2::zeros();
        for dy in -radius..=radius {
            for dx in -radius..=radius {
                let (x, y) = (cx + dx, cy + dy);
                if x < 1 || y < 1 || x >= g.w as i64 - 1 || y >= g.h as i64 - 1 {
                    return None;
                }
                let (xu, yu) = (x as usize, y as usize);
                let gx = (g.at(xu + 1, yu) - g.at(xu - 1, yu)) / 2.0;
                let gy = (g.at(xu, yu + 1) - g.at(xu, yu - 1)) / 2.0;
                let p = Vector2::new(x as f64, y as f64);
                let d2 = (p - q.coords).norm_squared();
                let wgt = (-d2 / (2.0 * sigma * sigma)).exp();
                let gg = Matrix2::new(gx * gx, gx * gy, gx * gy, gy * gy) * wgt;
                a += gg;
                b += gg * p;
            }
        }
        let next = Point2::from(a.try_inverse()? * b);
        let step = (next - q).norm();
        if !step.is_finite() || (next - start).norm() > radius as f64 {
            return None;
        }
        q = next;
        if step < 1e-4 {
            break;
        }
    }
    Some(q)
}

/// True when a ring around `q` alternates dark, light, dark, light and is symmetric under a
/// half turn (an X-junction), which rejects the T-junctions where the squares meet the
/// board's margin and points of the margin between two squares.
fn is_x_junction(g: &Gray, q: Point2<f64>) -> bool {
    const N: usize = 24;
    let mut ring = [0.0; N];
    for (k, v) in ring.iter_mut().enumerate() {
        let a = k as f64 * std::f64::consts::TAU / N as f64;
        match g.bilinear(q + Vector2::new(a.cos(), a.sin()) * 3.0) {
            Some(x) => *v = x,
            None => return false,
        }
    }
    let (lo, hi) = ring
        .iter()
        .fold((f64::INFINITY, f64::NEG_INFINITY), |(l, h), v| {
            (l.min(*v), h.max(*v))
        });
    if hi - lo < 10.0 {
        return false;
    }
    let mid = (lo + hi) / 2.0;
    let changes = (0..N)
        .filter(|&k| (ring[k] > mid) != (ring[(k + 1) % N] > mid))
        .count();
    // An X-junction looks the same turned by half a turn (locally affine).
    let asym = (0..N / 2)
        .map(|k| (ring[k] - ring[k + N / 2]).abs())
        .sum::<f64>()
        / (N / 2) as f64;
    changes == 4 && asym < 0.25 * (hi - lo)
}

/// Refined, de-duplicated X-junction candidates, strongest first.
fn candidates(g: &Gray, params: &DetectParams) -> Vec<Point2<f64>> {
    let starts = saddles(g, params.min_response);
    // Where corners crowd (foreshortened boards), a window reaching the next corner would
    // pull the refinement onto it: shrink it to under half the distance to the nearest
    // other saddle, and reject refinements that wander further than that.
    let refined: Vec<Point2<f64>> = starts
        .iter()
        .filter_map(|p| {
            let d = starts
                .iter()
                .map(|o| (o - p).norm())
                .filter(|d| *d > 1.0)
                .fold(f64::INFINITY, f64::min);
            let r = ((0.45 * d).floor() as i64).clamp(2, params.subpix_radius.max(2));
            refine(g, *p, r).filter(|q| (q - p).norm() < (0.4 * d).max(1.0))
        })
        .filter(|q| is_x_junction(g, *q))
        .collect();
    // Several saddle maxima may refine onto one corner: keep the strongest.
    let merge = 1.5;
    let mut cands: Vec<Point2<f64>> = Vec::new();
    for q in refined {
        if cands.iter().all(|c| (c - q).norm() > merge) {
            cands.push(q);
        }
    }
    cands
}

/// Grid position -> (candidate, local step along i, local step along j).
type Node = (usize, Vector2<f64>, Vector2<f64>);

/// Grows the grid from `seed` with the first steps `d1`, `d2`: predicts each neighbour from
/// the local step and takes the nearest free candidate within 35 % of a step.
fn grow_grid(
    cands: &[Point2<f64>],
    seed: usize,
    d1: Vector2<f64>,
    d2: Vector2<f64>,
) -> HashMap<(i64, i64), Node> {
    let mut grid: HashMap<(i64, i64), Node> = HashMap::new();
    let mut owner: Vec<Option<(i64, i64)>> = vec![None; cands.len()];
    grid.insert((0, 0), (seed, d1, d2));
    owner[seed] = Some((0, 0));
    let mut queue = VecDeque::from([(0i64, 0i64)]);
    while let Some((i, j)) = queue.pop_front() {
        let Some(&(idx, si, sj)) = grid.get(&(i, j)) else {
            continue;
        };
        let p = cands[idx];
        for (di, dj) in [(1i64, 0i64), (-1, 0), (0, 1), (0, -1)] {
            let key = (i + di, j + dj);
            if grid.contains_key(&key) {
                continue;
            }
            let step = si * di as f64 + sj * dj as f64;
            let pred = p + step;
            let best = (0..cands.len())
                .filter(|&c| owner[c].is_none())
                .min_by(|&a, &b| {
                    (cands[a] - pred)
                        .norm()
                        .total_cmp(&(cands[b] - pred).norm())
                });
            let Some(c) = best else { continue };
            if (cands[c] - pred).norm() > 0.35 * step.norm() {
                continue;
            }
            let measured = cands[c] - p;
            let (nsi, nsj) = if di != 0 {
                (measured * di as f64, sj)
            } else {
                (si, measured * dj as f64)
            };
            grid.insert(key, (c, nsi, nsj));
            owner[c] = Some(key);
            queue.push_back(key);
        }
    }
    grid
}

/// The one fully populated `rows x cols` (or `cols x rows`) window of a grown grid
/// `(i0, j0, extent i, extent j)`: stray candidates next to the board may extend the grid
/// by a partial row or column.
fn board_window(
    grid: &HashMap<(i64, i64), Node>,
    rows: i64,
    cols: i64,
) -> Result<(i64, i64, i64, i64), String> {
    let gimin = grid.keys().map(|k| k.0).min().unwrap_or(0);
    let gimax = grid.keys().map(|k| k.0).max().unwrap_or(0);
    let gjmin = grid.keys().map(|k| k.1).min().unwrap_or(0);
    let gjmax = grid.keys().map(|k| k.1).max().unwrap_or(0);
    let mut windows = Vec::new();
    for (wi, wj) in [(cols, rows), (rows, cols)] {
        for i0 in gimin..=gimax - wi + 1 {
            for j0 in gjmin..=gjmax - wj + 1 {
                let full = (i0..i0 + wi).all(|i| (j0..j0 + wj).all(|j| grid.contains_key(&(i, j))));
                if full && !windows.contains(&(i0, j0, wi, wj)) {
                    windows.push((i0, j0, wi, wj));
                }
            }
        }
    }
    match windows.as_slice() {
        [w] => Ok(*w),
        [] => Err(format!(
            "found a grid of {} corners spanning {} x {}, the board has {rows} x {cols}",
            grid.len(),
            gimax - gimin + 1,
            gjmax - gjmin + 1,
        )),
        _ => Err(format!(
            "the grid of {} corners holds the {rows} x {cols} board in {} places; crop the image to the board",
            grid.len(),
            windows.len()
        )),
    }
}

/// Detects `board`'s corners in an IR image with the detector of its kind; returns them
/// with their ids.
pub fn detect_board(
    img: &Image<u8>,
    board: &BoardConfig,
    params: &DetectParams,
) -> Result<Vec<Corner>, CalibrationError> {
    match board.kind {
        BoardKind::Chessboard => detect_chessboard(img, board, params),
        BoardKind::AprilGrid => crate::aprilgrid::detect_april_grid(img, board),
    }
}

/// Detects the inner corners of a chessboard in an IR image; returns them with their ids.
pub fn detect_chessboard(
    img: &Image<u8>,
    board: &BoardConfig,
    params: &DetectParams,
) -> Result<Vec<Corner>, CalibrationError> {
    board.validate()?;
    let not_found = |why: String| CalibrationError::BoardNotFound { why };
    if !img.is_consistent() {
        return Err(not_found("the image buffer does not match its size".into()));
    }
    let g = blur(img, params.blur_sigma);
    let cands = candidates(&g, params);
    let needed = board.corner_count();
    if cands.len() < needed {
        return Err(not_found(format!(
            "{} corner candidates, the board has {needed}",
            cands.len()
        )));
    }
    // Seed: the candidate nearest the centroid of the strongest `needed` candidates.
    let centroid = cands[..needed]
        .iter()
        .fold(Vector2::zeros(), |a, p| a + p.coords)
        / needed as f64;
    let seed = (0..cands.len())
        .min_by(|&a, &b| {
            (cands[a].coords - centroid)
                .norm()
                .total_cmp(&(cands[b].coords - centroid).norm())
        })
        .ok_or_else(|| not_found("no candidates".into()))?;
    // Grid axes run along square edges: the midpoint of an axis step lies on an edge (grey
    // between dark and light); the midpoint of a diagonal step lies inside a square.
    let (lo, hi) = (0..24).fold((f64::INFINITY, f64::NEG_INFINITY), |(l, h), k| {
        let a = k as f64 * std::f64::consts::TAU / 24.0;
        match g.bilinear(cands[seed] + Vector2::new(a.cos(), a.sin()) * 3.0) {
            Some(v) => (l.min(v), h.max(v)),
            None => (l, h),
        }
    });
    let mid_level = (lo + hi) / 2.0;
    let axis_like = |d: &Vector2<f64>| {
        g.bilinear(cands[seed] + d * 0.5)
            .is_some_and(|v| (v - mid_level).abs() < 0.25 * (hi - lo))
    };
    let mut near: Vec<Vector2<f64>> = cands
        .iter()
        .map(|c| c - cands[seed])
        .filter(|d| d.norm() > 1e-9)
        .filter(|d| axis_like(d))
        .collect();
    near.sort_by(|a, b| a.norm().total_cmp(&b.norm()));
    let d1 = *near
        .first()
        .ok_or_else(|| not_found("a single candidate".into()))?;
    // The second axis: the shortest axis-like step not parallel to d1, also among the
    // steps minus multiples of d1 (a sheared basis would index the grid wrongly).
    let cos = |a: &Vector2<f64>, b: &Vector2<f64>| (a.dot(b) / (a.norm() * b.norm())).abs();
    // Second-axis choices: axis-like steps not parallel to d1, shortest first; the first
    // that grows a grid holding the board wins (a sheared basis indexes the grid wrongly
    // and holds no full board window).
    let mut d2s: Vec<Vector2<f64>> = near
        .iter()
        .take(16)
        .flat_map(|v| (-2..=2).map(move |k| v - d1 * f64::from(k)))
        .filter(|w| w.norm() > 1e-9 && cos(w, &d1) < 0.9 && axis_like(w))
        .collect();
    d2s.sort_by(|a, b| a.norm().total_cmp(&b.norm()));
    d2s.dedup_by(|a, b| (*a - *b).norm() < 0.5);
    let (rows, cols) = (i64::from(board.rows), i64::from(board.cols));
    let mut last_why = "the candidates do not form a grid".to_string();
    let mut chosen = None;
    for d2 in d2s.into_iter().take(6) {
        let grid = grow_grid(&cands, seed, d1, d2);
        match board_window(&grid, rows, cols) {
            Ok(w) => {
                chosen = Some((grid, w));
                break;
            }
            Err(why) => last_why = format!("{why} (of {} candidates)", cands.len()),
        }
    }
    let (grid, (imin, jmin, ni, nj)) = chosen.ok_or_else(|| not_found(last_why))?;
    let at = |i: i64, j: i64| grid.get(&(i, j)).map(|e| cands[e.0]);
    // The 8 symmetries: (swap, flip col, flip row) map (i, j) to (col, row).
    let mut found: Vec<Vec<Corner>> = Vec::new();
    for swap in [false, true] {
        let (ncol, nrow) = if swap { (nj, ni) } else { (ni, nj) };
        if ncol != cols || nrow != rows {
            continue;
        }
        for flip_c in [false, true] {
            for flip_r in [false, true] {
                let to_grid = |col: i64, row: i64| {
                    let c = if flip_c { cols - 1 - col } else { col };
                    let r = if flip_r { rows - 1 - row } else { row };
                    if swap {
                        (imin + r, jmin + c)
                    } else {
                        (imin + c, jmin + r)
                    }
                };
                let pix = |col: i64, row: i64| {
                    let (i, j) = to_grid(col, row);
                    at(i, j)
                };
                let (Some(p0), Some(pa), Some(pb)) = (pix(0, 0), pix(1, 0), pix(0, 1)) else {
                    continue;
                };
                let (a, b) = (pa - p0, pb - p0);
                // Seen from the front, +x then +y turn clockwise on screen (y down).
                if a.x * b.y - a.y * b.x >= 0.0 {
                    continue;
                }
                let inside = g.bilinear(p0 + 0.5 * a + 0.5 * b);
                let beside = g.bilinear(p0 + 0.5 * a - 0.5 * b);
                match (inside, beside) {
                    (Some(d), Some(l)) if d < l => {}
                    _ => continue,
                }
                let mut corners = Vec::with_capacity(needed);
                for row in 0..rows {
                    for col in 0..cols {
                        if let Some(p) = pix(col, row) {
                            corners.push(Corner {
                                id: (row * cols + col) as u32,
                                u: p.x,
                                v: p.y,
                            });
                        }
                    }
                }
                found.push(corners);
            }
        }
    }
    match found.len() {
        1 => Ok(found.swap_remove(0)),
        0 => Err(not_found(
            "no labelling of the grid fits the board (wrong rows/cols, or seen from behind)".into(),
        )),
        n => Err(not_found(format!(
            "{n} labellings fit: a {} x {} chessboard looks the same turned by 180 degrees; use rows + cols odd or an AprilGrid",
            board.rows, board.cols
        ))),
    }
}

/// One camera's view of the board from a captured frame (what `equact calibrate capture`
/// records per camera): the corners detected in the left IR image, and the depth image's
/// value at each corner's pixel (skipping holes) for the depth residual.
pub fn view_from_frame(
    frame: &CameraFrame,
    board: &BoardConfig,
    params: &DetectParams,
) -> Result<CameraView, CalibrationError> {
    let ir = frame
        .ir
        .as_ref()
        .ok_or_else(|| CalibrationError::BoardNotFound {
            why: format!(
                "camera {} delivered no IR image (enable the left IR stream)",
                frame.camera
            ),
        })?;
    let corners = detect_board(ir, board, params)?;
    let depth = &frame.depth;
    let board_depth = corners
        .iter()
        .filter_map(|c| {
            let (u, v) = (c.u.round(), c.v.round());
            if u < 0.0 || v < 0.0 {
                return None;
            }
            let raw = *depth.raw.get(u as u32, v as u32)?;
            let depth_m = raw_depth_to_m(raw, depth.depth_scale)?;
            Some(DepthSample { u, v, depth_m })
        })
        .collect();
    Ok(CameraView {
        camera: frame.camera,
        corners,
        board_depth,
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::board::DEFAULT_TAG_SPACING;
    use crate::camera::DepthMode;
    use nalgebra::{Translation3, UnitQuaternion};
    use rand::{Rng, SeedableRng};
    use rand_distr::StandardNormal;

    fn board() -> BoardConfig {
        BoardConfig {
            kind: BoardKind::Chessboard,
            rows: 7,
            cols: 10,
            square_m: 0.035,
            spacing: DEFAULT_TAG_SPACING,
        }
    }

    fn pose(rpy: [f64; 3], z: f64, b: &BoardConfig) -> Isometry3<f64> {
        // Board centre on the optical axis at depth z, face towards the camera, tilted.
        let rot = UnitQuaternion::from_euler_angles(std::f64::consts::PI + rpy[0], rpy[1], rpy[2]);
        let t = nalgebra::Vector3::new(0.02, -0.01, z) - rot * b.centre().coords;
        Isometry3::from_parts(Translation3::from(t), rot)
    }

    #[test]
    fn detects_every_corner_to_a_tenth_of_a_pixel_with_ids() {
        let k = Intrinsics::d455_depth(DepthMode::Wvga848x480);
        let b = board();
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(3);
        for (n, rpy) in [
            [0.0, 0.0, 0.0],
            [0.5, 0.2, 0.3],
            [-0.4, 0.5, 2.0],
            [0.3, -0.6, -2.5],
            [0.0, 0.3, 1.57],
        ]
        .into_iter()
        .enumerate()
        {
            let truth = pose(rpy, 0.8 + 0.1 * n as f64, &b);
            let mut img = render_board_ir(&k, &truth, &b, &IrLevels::default());
            for p in &mut img.data {
                let noise: f64 = rng.sample(StandardNormal);
                *p = (f64::from(*p) + 2.0 * noise).round().clamp(0.0, 255.0) as u8;
            }
            let corners = detect_chessboard(&img, &b, &DetectParams::default()).unwrap();
            assert_eq!(corners.len(), b.corner_count());
            let mut ss = 0.0;
            let mut worst: f64 = 0.0;
            let mut bias = Vector2::zeros();
            for c in &corners {
                let want = k.project(&(truth * b.corner(c.id).unwrap())).unwrap();
                bias += (Point2::new(c.u, c.v) - want) / corners.len() as f64;
                let e = (Point2::new(c.u, c.v) - want).norm();
                ss += e * e;
                worst = worst.max(e);
            }
            let rms = (ss / corners.len() as f64).sqrt();
            eprintln!("pose {n}: rms {rms:.4} worst {worst:.4} bias {bias:?}");
            assert!(
                rms < 0.1 && worst < 0.3,
                "pose {n}: rms {rms} worst {worst}"
            );
        }
    }

    #[test]
    fn a_view_from_a_frame_has_corners_and_depth_at_them() {
        let k = Intrinsics::d455_depth(DepthMode::Wvga848x480);
        let b = board();
        let truth = pose([0.3, -0.2, 0.5], 0.9, &b);
        let ir = render_board_ir(&k, &truth, &b, &IrLevels::default());
        // Depth of the board plane at every pixel (0 off the board), in millimetres.
        let n = truth.rotation * nalgebra::Vector3::z();
        let t = truth.translation.vector;
        let mut raw = Image::filled(k.width, k.height, 0u16);
        for v in 0..k.height {
            for u in 0..k.width {
                let ray = k
                    .pixel_ray(Point2::new(f64::from(u), f64::from(v)))
                    .unwrap();
                let z = n.dot(&t) / n.dot(&ray);
                raw.data[(v * k.width + u) as usize] = crate::camera::m_to_raw_depth(z);
            }
        }
        raw.data[0] = 0;
        let frame = CameraFrame {
            camera: 2,
            timestamp: std::time::Duration::ZERO,
            depth: cell_types::DepthImage {
                raw,
                depth_scale: 0.001,
            },
            ir: Some(ir),
            colour: None,
        };
        let view = view_from_frame(&frame, &b, &DetectParams::default()).unwrap();
        assert_eq!(view.camera, 2);
        assert_eq!(view.corners.len(), 70);
        assert_eq!(view.board_depth.len(), 70);
        for d in &view.board_depth {
            let ray = k.pixel_ray(Point2::new(d.u, d.v)).unwrap();
            assert!((d.depth_m - n.dot(&t) / n.dot(&ray)).abs() <= 0.0005 + 1e-9);
        }
        let no_ir = CameraFrame { ir: None, ..frame };
        let err = view_from_frame(&no_ir, &b, &DetectParams::default()).unwrap_err();
        assert!(err.to_string().contains("no IR image"), "{err}");
    }

    #[test]
    fn no_board_or_the_wrong_board_is_a_typed_error() {
        let k = Intrinsics::d455_depth(DepthMode::Wvga848x480);
        let blank = Image::filled(k.width, k.height, 90u8);
        let err = detect_chessboard(&blank, &board(), &DetectParams::default()).unwrap_err();
        assert!(
            matches!(err, CalibrationError::BoardNotFound { .. }),
            "{err}"
        );
        let b = board();
        let img = render_board_ir(
            &k,
            &pose([0.2, 0.1, 0.4], 0.9, &b),
            &b,
            &IrLevels::default(),
        );
        let other = BoardConfig { rows: 6, ..b };
        assert!(detect_chessboard(&img, &other, &DetectParams::default()).is_err());
        // A board with rows + cols even is ambiguous under a half turn: refused, not guessed.
        let even = BoardConfig {
            rows: 7,
            cols: 9,
            ..b
        };
        let img = render_board_ir(
            &k,
            &pose([0.2, 0.1, 0.4], 0.9, &even),
            &even,
            &IrLevels::default(),
        );
        let err = detect_chessboard(&img, &even, &DetectParams::default()).unwrap_err();
        assert!(err.to_string().contains("180 degrees"), "{err}");
    }
}
