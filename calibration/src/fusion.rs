//! The fused point cloud (issue 7 item 3; `equact.md` "Point cloud in"): deproject each
//! camera's depth, transform to the base frame with the calibration, crop to the workspace,
//! merge, voxel-downsample, remove the robot's own points, remove statistical outliers, and
//! farthest-point sample to the policy's point count with EquAct's split (1536 inside the
//! focus box, 512 outside), then shuffle. Optionally ([`FusionParams::gripper_points`],
//! given the TCP) part of the focus box's share is first sampled in a ball around the TCP,
//! so a held object is seen at the dense cloud's spacing rather than the whole scene's.
//!
//! No library does this on depth images directly, and the hot loops are simple: each stage
//! is one pass over flat arrays with no per-point allocation, and the buffers are reused from
//! one keyframe to the next. Deprojection uses a per-pixel ray table computed once per
//! camera, with the crop fused in and the depth-edge filter's 3x3 window from per-row
//! minima and maxima. Voxels live in a dense grid over the (small, known) workspace instead
//! of a hash map. The outlier filter's k nearest neighbours come from a dense grid of points
//! counting-sorted by cell (module `grid`): exact, and usually served by one contiguous block
//! of ~80 points per cell, which beats a k-d tree on an evenly spread voxel cloud.
//!
//! Bad input never panics: zero depth is "no measurement", non-finite depth scales and
//! transforms are typed errors, as are missing frames, unknown cameras and cameras with no
//! valid pixel.

mod grid;

use std::collections::HashMap;
use std::hash::{BuildHasherDefault, Hasher};
use std::sync::{Mutex, TryLockError};

use cell_types::{Base, Camera, CameraFrame, FrameId, PointCloud, Rgb, Transform};
use nalgebra::{Point2, Point3, Vector3};
use rand::seq::SliceRandom;
use rand::SeedableRng;
use rand_chacha::ChaCha8Rng;
use serde::{Deserialize, Serialize};

use crate::camera::{DepthCorrection, Intrinsics};
use crate::error::CalibrationError;
use grid::{CellBox, KnnScratch, VoxelScratch};

/// One camera's calibration: intrinsics of its depth stream and its pose in the base frame.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct CameraCalibration {
    /// Camera id (`FrameId::Camera` index).
    pub id: u8,
    /// Depth-stream intrinsics (undistorted).
    pub intrinsics: Intrinsics,
    /// The optical frame's pose in the base frame.
    pub base_from_camera: Transform<Base, Camera>,
    /// The depth error undone on deprojection (older files without it: none).
    #[serde(default)]
    pub depth_correction: DepthCorrection,
}

/// The calibration of every camera of the cell (what `calibration.toml` holds).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize, Default)]
pub struct CellCalibration {
    /// One entry per camera.
    pub cameras: Vec<CameraCalibration>,
}

impl CellCalibration {
    /// Checks the entries (finite poses, valid intrinsics, unique ids) and that every camera
    /// it names is one of `known` (the cameras the cell configuration declares).
    pub fn validate_against(&self, known: &[u8]) -> Result<(), CalibrationError> {
        for (i, c) in self.cameras.iter().enumerate() {
            if !known.contains(&c.id) {
                return Err(CalibrationError::UnknownCamera {
                    camera: c.id,
                    known: known.to_vec(),
                });
            }
            if self.cameras[..i].iter().any(|o| o.id == c.id) {
                return Err(CalibrationError::DuplicateCamera { camera: c.id });
            }
            if !c.base_from_camera.is_finite() {
                return Err(CalibrationError::BadExtrinsics { camera: c.id });
            }
            c.intrinsics.validate()?;
            c.depth_correction.validate()?;
        }
        Ok(())
    }

    /// The camera ids, in order.
    pub fn ids(&self) -> Vec<u8> {
        self.cameras.iter().map(|c| c.id).collect()
    }
}

/// An axis-aligned box in the base frame (m).
#[derive(Copy, Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Bounds {
    /// Lower corner.
    pub min: [f64; 3],
    /// Upper corner.
    pub max: [f64; 3],
}

impl Bounds {
    /// EquAct's physical-robot workspace [[0.18, -0.39, -0.10], [0.96, 0.39, 0.53]].
    pub const EQUACT_WORKSPACE: Bounds = Bounds {
        min: [0.18, -0.39, -0.10],
        max: [0.96, 0.39, 0.53],
    };
    /// EquAct's focus box: the gripper bounds with z-min at the table height (-0.06).
    pub const EQUACT_FOCUS: Bounds = Bounds {
        min: [0.18, -0.39, -0.06],
        max: [0.96, 0.39, 0.53],
    };

    /// True when `p` is inside (bounds included).
    pub fn contains(&self, p: &Point3<f32>) -> bool {
        (0..3).all(|i| {
            let v = f64::from(p[i]);
            v >= self.min[i] && v <= self.max[i]
        })
    }

    fn validate(&self, what: &'static str) -> Result<(), CalibrationError> {
        for i in 0..3 {
            if !(self.min[i].is_finite() && self.max[i].is_finite() && self.min[i] < self.max[i]) {
                return Err(CalibrationError::InvalidParameter {
                    what,
                    value: self.max[i] - self.min[i],
                    why: "each axis needs finite min < max",
                });
            }
        }
        Ok(())
    }
}

/// A capsule (segment + radius) of the robot's collision geometry, in the base frame.
#[derive(Copy, Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Capsule {
    /// Segment start (m).
    pub a: Point3<f64>,
    /// Segment end (m).
    pub b: Point3<f64>,
    /// Radius (m).
    pub radius: f64,
}

impl Capsule {
    /// Distance from `p` to the capsule's axis segment (m).
    pub fn axis_distance(&self, p: &Point3<f64>) -> f64 {
        let ab = self.b - self.a;
        let len2 = ab.norm_squared();
        let t = if len2 > 0.0 {
            ((p - self.a).dot(&ab) / len2).clamp(0.0, 1.0)
        } else {
            0.0
        };
        (p - (self.a + ab * t)).norm()
    }
}

/// Parameters of the fusion pipeline (the lead fills them from `cell.toml`).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct FusionParams {
    /// Crop box (base frame).
    pub workspace: Bounds,
    /// EquAct's focus box: `points_inside` are sampled in it, the rest outside.
    pub focus: Bounds,
    /// Voxel edge (m).
    pub voxel_m: f64,
    /// Neighbours for the statistical outlier removal.
    pub outlier_k: usize,
    /// Points whose mean neighbour distance exceeds mean + ratio * std are outliers.
    pub outlier_std_ratio: f64,
    /// Extra radius (m) around the robot's capsules inside which points are the robot.
    pub robot_margin_m: f64,
    /// Depth-edge filter: a pixel is dropped when the depths in its 3x3 window span more
    /// than this (m) times max(1, z / 1 m). Stereo cameras put "flying pixels" between fore-
    /// and background at such edges; they form sheets with enough neighbours to survive the
    /// statistical filter, and farthest point sampling picks them first. 0 disables.
    pub edge_jump_m: f64,
    /// Total points handed to the policy.
    pub points: usize,
    /// How many of them come from inside the focus box.
    pub points_inside: usize,
    /// Of `points_inside`, how many are first sampled within `gripper_radius_m` of the
    /// TCP when [`FusionPipeline::fuse_at`] is given one (fewer when the ball holds fewer;
    /// 0, the default, is EquAct's plain split). Farthest point sampling spreads points
    /// at the whole scene's spacing (about 13 mm at 2048), too coarse to see where a held
    /// object sits in the hand; these are sampled at the ball's own, finer spacing.
    #[serde(default)]
    pub gripper_points: usize,
    /// Radius (m) of the ball around the TCP that `gripper_points` are sampled in.
    #[serde(default = "default_gripper_radius")]
    pub gripper_radius_m: f64,
    /// Seed of the sampling's start points and the final permutation.
    pub seed: u64,
}

impl Default for FusionParams {
    fn default() -> Self {
        Self {
            workspace: Bounds::EQUACT_WORKSPACE,
            focus: Bounds::EQUACT_FOCUS,
            voxel_m: 0.005,
            outlier_k: 20,
            outlier_std_ratio: 2.0,
            robot_margin_m: 0.02,
            edge_jump_m: 0.02,
            points: 2048,
            points_inside: 1536,
            gripper_points: 0,
            gripper_radius_m: default_gripper_radius(),
            seed: 0,
        }
    }
}

fn default_gripper_radius() -> f64 {
    cell_types::config::DEFAULT_GRIPPER_RADIUS_M
}

/// Points with optional colours, the working set between stages.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct Points {
    /// Positions (m, base frame).
    pub xyz: Vec<Point3<f32>>,
    /// Colours (empty when no frame had colour, else one per point).
    pub rgb: Vec<Rgb>,
}

impl Points {
    fn push(&mut self, p: Point3<f32>, c: Option<Rgb>) {
        self.xyz.push(p);
        if let Some(c) = c {
            self.rgb.push(c);
        }
    }

    fn select(&self, keep: impl Fn(usize) -> bool) -> Points {
        let has_rgb = self.rgb.len() == self.xyz.len();
        let mut out = Points::default();
        for i in 0..self.xyz.len() {
            if keep(i) {
                out.xyz.push(self.xyz[i]);
                if has_rgb {
                    out.rgb.push(self.rgb[i]);
                }
            }
        }
        out
    }

    /// Number of points.
    pub fn len(&self) -> usize {
        self.xyz.len()
    }

    /// True when empty.
    pub fn is_empty(&self) -> bool {
        self.xyz.is_empty()
    }

    /// As a base-frame cloud.
    pub fn into_cloud(self) -> PointCloud {
        let rgb = (self.rgb.len() == self.xyz.len() && !self.xyz.is_empty()).then_some(self.rgb);
        PointCloud {
            frame: FrameId::Base,
            points: self.xyz,
            rgb,
        }
    }
}

/// Point counts after each stage, for logs and reports.
#[derive(Clone, Debug, Default, PartialEq, Serialize)]
pub struct FusionStats {
    /// Valid depth pixels per camera, in calibration order.
    pub valid_pixels: Vec<usize>,
    /// Points inside the workspace, all cameras.
    pub cropped: usize,
    /// Occupied voxels.
    pub voxels: usize,
    /// After removing the robot.
    pub without_robot: usize,
    /// After outlier removal.
    pub inliers: usize,
}

/// The pipeline's result.
#[derive(Clone, Debug, PartialEq)]
pub struct Fused {
    /// The dense cloud after outlier removal (for the planner's collision checks).
    pub dense: PointCloud,
    /// The sampled cloud for the policy (`points` points, shuffled).
    pub sampled: PointCloud,
    /// Counts per stage.
    pub stats: FusionStats,
}

/// The fusion pipeline for one calibrated set of cameras.
#[derive(Clone, Debug)]
pub struct FusionPipeline {
    calibration: CellCalibration,
    params: FusionParams,
    /// Per camera, the normalised ray (x, y) of every pixel.
    rays: Vec<Vec<[f32; 2]>>,
    /// The workspace's voxels (the dense grid every cropped point falls in).
    voxel_box: CellBox,
    /// Buffers reused from one call to the next.
    scratch: ScratchCell,
}

/// Buffers the pipeline reuses from one keyframe to the next.
#[derive(Default)]
struct Scratch {
    /// The deprojected, cropped points of all cameras.
    merged: Points,
    edges: EdgeWindows,
    voxels: VoxelScratch,
    knn: KnnScratch,
}

/// Each depth pixel's row neighbourhood (itself and its left and right neighbours): the
/// largest raw depth and the smallest valid one, so that the depth-edge filter's 3x3 window
/// is three look-ups instead of nine.
#[derive(Default)]
struct EdgeWindows {
    /// Largest raw depth of the three (0 is never the largest of a valid pixel's window).
    max: Vec<u16>,
    /// Smallest raw depth of the three minus one, wrapping: 0 (no measurement) becomes
    /// `u16::MAX` and never wins.
    min: Vec<u16>,
}

impl EdgeWindows {
    /// Fills both for an image of width `w` stored in `data`.
    fn rows(&mut self, data: &[u16], w: usize) {
        self.max.clear();
        self.min.clear();
        if w == 0 {
            return;
        }
        self.max.resize(data.len(), 0);
        self.min.resize(data.len(), 0);
        // The first and last pixels' windows are clamped at the border; the loop between
        // them has no branches and vectorises.
        let lo = |v: u16| v.wrapping_sub(1);
        for ((row, max), min) in data
            .chunks_exact(w)
            .zip(self.max.chunks_exact_mut(w))
            .zip(self.min.chunks_exact_mut(w))
        {
            let (first, last) = (row[..2.min(w)].iter(), row[w.saturating_sub(2)..].iter());
            max[0] = first.clone().copied().fold(0, u16::max);
            min[0] = first.map(|&v| lo(v)).fold(u16::MAX, u16::min);
            max[w - 1] = last.clone().copied().fold(0, u16::max);
            min[w - 1] = last.map(|&v| lo(v)).fold(u16::MAX, u16::min);
            if w >= 3 {
                let mid = row
                    .windows(3)
                    .zip(&mut max[1..w - 1])
                    .zip(&mut min[1..w - 1]);
                for ((abc, max), min) in mid {
                    *max = abc[0].max(abc[1]).max(abc[2]);
                    *min = lo(abc[0]).min(lo(abc[1])).min(lo(abc[2]));
                }
            }
        }
    }

    /// The smallest valid and the largest raw depth of a 3x3 window, from the flat indices
    /// of its rows' centres (a valid pixel's window always has a valid depth).
    #[inline]
    fn window(&self, up: usize, at: usize, down: usize) -> (u16, u16) {
        let hi = self.max[up].max(self.max[at]).max(self.max[down]);
        let lo = self.min[up].min(self.min[at]).min(self.min[down]);
        (lo.wrapping_add(1), hi)
    }
}

/// The pipeline's buffers behind a lock (`fuse` takes `&self`). A second thread fusing with
/// the same pipeline at the same time gets fresh buffers instead of waiting; a clone starts
/// with empty ones.
#[derive(Default)]
struct ScratchCell(Mutex<Scratch>);

impl Clone for ScratchCell {
    fn clone(&self) -> Self {
        Self::default()
    }
}

impl std::fmt::Debug for ScratchCell {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str("ScratchCell")
    }
}

impl FusionPipeline {
    /// Checks the calibration and the parameters and precomputes every pixel's ray.
    pub fn new(
        calibration: CellCalibration,
        params: FusionParams,
    ) -> Result<Self, CalibrationError> {
        let ids = calibration.ids();
        calibration.validate_against(&ids)?;
        params.workspace.validate("workspace")?;
        params.focus.validate("focus")?;
        let bad =
            |what, value: f64, why| Err(CalibrationError::InvalidParameter { what, value, why });
        if !(params.voxel_m.is_finite() && params.voxel_m >= 1e-4) {
            return bad(
                "voxel_m",
                params.voxel_m,
                "use a voxel edge of at least 0.1 mm",
            );
        }
        if params.outlier_k == 0 || params.outlier_k > 64 {
            return bad(
                "outlier_k",
                params.outlier_k as f64,
                "use 1..=64 neighbours",
            );
        }
        if !(params.outlier_std_ratio.is_finite() && params.outlier_std_ratio > 0.0) {
            return bad(
                "outlier_std_ratio",
                params.outlier_std_ratio,
                "use a positive ratio",
            );
        }
        if !(params.robot_margin_m.is_finite() && params.robot_margin_m >= 0.0) {
            return bad("robot_margin_m", params.robot_margin_m, "use a margin >= 0");
        }
        if !(params.edge_jump_m.is_finite() && params.edge_jump_m >= 0.0) {
            return bad(
                "edge_jump_m",
                params.edge_jump_m,
                "use a jump >= 0 (0 disables)",
            );
        }
        if params.points_inside > params.points {
            return bad(
                "points_inside",
                params.points_inside as f64,
                "must not exceed points",
            );
        }
        if params.gripper_points > params.points_inside {
            return bad(
                "gripper_points",
                params.gripper_points as f64,
                "must not exceed points_inside (they are part of the focus box's share)",
            );
        }
        if !(params.gripper_radius_m.is_finite() && params.gripper_radius_m > 0.0) {
            return bad(
                "gripper_radius_m",
                params.gripper_radius_m,
                "use a positive radius (m), e.g. 0.08",
            );
        }
        let mut rays = Vec::with_capacity(calibration.cameras.len());
        for c in &calibration.cameras {
            let k = &c.intrinsics;
            let mut r = Vec::with_capacity(k.width as usize * k.height as usize);
            for v in 0..k.height {
                for u in 0..k.width {
                    let ray = k.pixel_ray(Point2::new(f64::from(u), f64::from(v)))?;
                    r.push([ray.x as f32, ray.y as f32]);
                }
            }
            rays.push(r);
        }
        let inv = (1.0 / params.voxel_m) as f32;
        let h = params.voxel_m / 2.0;
        let o = params.workspace.min.map(|v| (v - h) as f32);
        let o = Vector3::new(o[0], o[1], o[2]);
        let corner = |c: [f64; 3]| Point3::new(c[0] as f32, c[1] as f32, c[2] as f32);
        // The crop keeps points in [min, max] (as f32) and the voxel of a coordinate grows
        // with it, so the voxels of these two corners bound every cropped point's voxel.
        let voxel_box = CellBox::spanning(
            grid::voxel_coords(&corner(params.workspace.min), &o, inv),
            grid::voxel_coords(&corner(params.workspace.max), &o, inv),
        );
        Ok(Self {
            calibration,
            params,
            rays,
            voxel_box,
            scratch: ScratchCell::default(),
        })
    }

    /// The voxel grid's corner: half a voxel below the workspace's lower corner, which puts
    /// the EquAct table height (-0.06 m) mid-voxel instead of on a voxel boundary (where
    /// noise splits the table into two layers of voxels).
    pub fn voxel_origin(&self) -> [f64; 3] {
        let h = self.params.voxel_m / 2.0;
        self.params.workspace.min.map(|v| v - h)
    }

    /// The parameters.
    pub fn params(&self) -> &FusionParams {
        &self.params
    }

    /// The calibration.
    pub fn calibration(&self) -> &CellCalibration {
        &self.calibration
    }

    /// Finds each calibrated camera's frame, checking ids and sizes.
    fn match_frames<'a>(
        &self,
        frames: &'a [CameraFrame],
    ) -> Result<Vec<&'a CameraFrame>, CalibrationError> {
        let ids = self.calibration.ids();
        for (i, f) in frames.iter().enumerate() {
            if !ids.contains(&f.camera) {
                return Err(CalibrationError::UnknownCamera {
                    camera: f.camera,
                    known: ids,
                });
            }
            if frames[..i].iter().any(|o| o.camera == f.camera) {
                return Err(CalibrationError::DuplicateCamera { camera: f.camera });
            }
        }
        self.calibration
            .cameras
            .iter()
            .map(|c| {
                let f = frames.iter().find(|f| f.camera == c.id).ok_or_else(|| {
                    CalibrationError::MissingFrame {
                        camera: c.id,
                        expected: ids.clone(),
                    }
                })?;
                check_frame(c, f)?;
                Ok(f)
            })
            .collect()
    }

    /// Deprojects one camera's frame to the base frame, keeping only points inside the
    /// workspace; also returns the number of valid depth pixels.
    pub fn camera_points(&self, frame: &CameraFrame) -> Result<(Points, usize), CalibrationError> {
        let idx = self
            .calibration
            .cameras
            .iter()
            .position(|c| c.id == frame.camera)
            .ok_or_else(|| CalibrationError::UnknownCamera {
                camera: frame.camera,
                known: self.calibration.ids(),
            })?;
        check_frame(&self.calibration.cameras[idx], frame)?;
        let mut out = Points::default();
        let valid = self.deproject_into(idx, frame, &mut out, &mut EdgeWindows::default());
        Ok((out, valid))
    }

    /// Deprojects one frame (already checked against its camera) into `out`: valid pixels
    /// that pass the depth-edge filter and land in the workspace. Returns the number of
    /// valid depth pixels.
    fn deproject_into(
        &self,
        idx: usize,
        frame: &CameraFrame,
        out: &mut Points,
        edges: &mut EdgeWindows,
    ) -> usize {
        let cam = &self.calibration.cameras[idx];
        let rays = &self.rays[idx];
        let iso = cam.base_from_camera.isometry();
        let r = iso.rotation.to_rotation_matrix().into_inner().cast::<f32>();
        let t = iso.translation.vector.cast::<f32>();
        let scale = frame.depth.depth_scale;
        // The calibrated depth error: true = (measured - offset) / scale.
        let dc = cam.depth_correction;
        let (gain, bias) = ((1.0 / dc.scale) as f32, (-dc.offset_m / dc.scale) as f32);
        let ws = &self.params.workspace;
        let (lo, hi) = (
            Vector3::new(ws.min[0] as f32, ws.min[1] as f32, ws.min[2] as f32),
            Vector3::new(ws.max[0] as f32, ws.max[1] as f32, ws.max[2] as f32),
        );
        let colour = frame.colour.as_ref();
        let data = &frame.depth.raw.data;
        let (w, h) = (
            frame.depth.raw.width as usize,
            frame.depth.raw.height as usize,
        );
        let jump = self.params.edge_jump_m as f32;
        if jump > 0.0 {
            edges.rows(data, w);
        }
        let mut valid = 0;
        for v in 0..h {
            // The window's rows, clamped at the image border (a repeated row changes no
            // minimum or maximum).
            let up = v.saturating_sub(1) * w;
            let down = (v + 1).min(h - 1) * w;
            let row = v * w;
            for u in 0..w {
                let i = row + u;
                let raw = data[i];
                if raw == 0 {
                    continue;
                }
                let z = f32::from(raw) * scale * gain + bias;
                if !(z.is_finite() && z > 0.0) {
                    continue;
                }
                valid += 1;
                if jump > 0.0 {
                    let (lo_raw, hi_raw) = edges.window(up + u, i, down + u);
                    if f32::from(hi_raw - lo_raw) * scale > jump * z.max(1.0) {
                        continue;
                    }
                }
                let ray = rays[i];
                let p = r * Vector3::new(ray[0] * z, ray[1] * z, z) + t;
                if p.x < lo.x || p.y < lo.y || p.z < lo.z || p.x > hi.x || p.y > hi.y || p.z > hi.z
                {
                    continue;
                }
                out.push(
                    Point3::from(p),
                    colour.map(|c| c.data.get(i).copied().unwrap_or([128; 3])),
                );
            }
        }
        valid
    }

    /// Runs the whole pipeline on one frame per calibrated camera. `robot` is the robot's
    /// collision geometry at the time of the frames (from FK).
    pub fn fuse(
        &self,
        frames: &[CameraFrame],
        robot: &[Capsule],
    ) -> Result<Fused, CalibrationError> {
        self.fuse_at(frames, robot, None)
    }

    /// [`fuse`](Self::fuse) with the TCP's position (base frame) at the time of the
    /// frames, around which `gripper_points` are sampled first (see [`Self::sample_at`]).
    pub fn fuse_at(
        &self,
        frames: &[CameraFrame],
        robot: &[Capsule],
        tcp: Option<Point3<f32>>,
    ) -> Result<Fused, CalibrationError> {
        let (dense, stats) = self.fuse_dense(frames, robot)?;
        let sampled = self.sample_at(&dense, tcp)?;
        Ok(Fused {
            dense: dense.into_cloud(),
            sampled: sampled.into_cloud(),
            stats,
        })
    }

    /// Everything up to and including outlier removal: the dense fused cloud.
    pub fn fuse_dense(
        &self,
        frames: &[CameraFrame],
        robot: &[Capsule],
    ) -> Result<(Points, FusionStats), CalibrationError> {
        let mut fresh = None;
        let mut guard = match self.scratch.0.try_lock() {
            Ok(g) => Some(g),
            Err(TryLockError::Poisoned(e)) => {
                // A panic mid-call may have left the voxel slots dirty: start afresh.
                let mut g = e.into_inner();
                *g = Scratch::default();
                Some(g)
            }
            Err(TryLockError::WouldBlock) => None,
        };
        let scratch = match guard.as_deref_mut() {
            Some(s) => s,
            None => fresh.insert(Scratch::default()),
        };
        self.fuse_dense_with(frames, robot, scratch)
    }

    fn fuse_dense_with(
        &self,
        frames: &[CameraFrame],
        robot: &[Capsule],
        scratch: &mut Scratch,
    ) -> Result<(Points, FusionStats), CalibrationError> {
        let matched = self.match_frames(frames)?;
        let mut stats = FusionStats::default();
        let any_colour = matched.iter().any(|f| f.colour.is_some());
        let merged = &mut scratch.merged;
        merged.xyz.clear();
        merged.rgb.clear();
        for (idx, f) in matched.iter().enumerate() {
            let before = merged.len();
            let valid = self.deproject_into(idx, f, merged, &mut scratch.edges);
            if valid == 0 {
                return Err(CalibrationError::NoValidDepth {
                    camera: f.camera,
                    width: f.depth.raw.width,
                    height: f.depth.raw.height,
                });
            }
            if any_colour && f.colour.is_none() {
                // Keep colours one per point: grey where a camera has no colour stream.
                merged
                    .rgb
                    .resize(merged.rgb.len() + merged.len() - before, [128; 3]);
            }
            stats.valid_pixels.push(valid);
        }
        stats.cropped = merged.len();
        let mut voxels = Points::default();
        scratch.voxels.voxelise(
            merged,
            self.params.voxel_m,
            self.voxel_origin(),
            Some(self.voxel_box),
            &mut voxels,
        );
        stats.voxels = voxels.len();
        let without_robot = remove_robot(&voxels, robot, self.params.robot_margin_m);
        stats.without_robot = without_robot.len();
        let inliers = remove_outliers_with(
            &without_robot,
            self.params.outlier_k,
            self.params.outlier_std_ratio,
            self.params.voxel_m * 3.0,
            &mut scratch.knn,
        );
        stats.inliers = inliers.len();
        Ok((inliers, stats))
    }

    /// Farthest point sampling to `points` with `points_inside` from the focus box (fewer
    /// when the box holds fewer; the rest from outside, and vice versa), then shuffled.
    pub fn sample(&self, dense: &Points) -> Result<Points, CalibrationError> {
        self.sample_at(dense, None)
    }

    /// [`sample`](Self::sample) that, given the TCP, first takes up to `gripper_points`
    /// of the focus box's share by farthest point sampling of the points within
    /// `gripper_radius_m` of it; the split's two samplings then choose the rest from the
    /// other points. With no TCP or `gripper_points` 0 it is exactly [`Self::sample`].
    pub fn sample_at(
        &self,
        dense: &Points,
        tcp: Option<Point3<f32>>,
    ) -> Result<Points, CalibrationError> {
        let p = &self.params;
        if dense.len() < p.points {
            return Err(CalibrationError::TooFewPoints {
                got: dense.len(),
                needed: p.points,
            });
        }
        let mut rng = ChaCha8Rng::seed_from_u64(p.seed);
        let mut chosen = Vec::with_capacity(p.points);
        let mut taken = Vec::new();
        if let (Some(tcp), true) = (tcp, p.gripper_points > 0) {
            let r2 = (p.gripper_radius_m * p.gripper_radius_m) as f32;
            let near: Vec<usize> = (0..dense.len())
                .filter(|&i| (dense.xyz[i] - tcp).norm_squared() <= r2)
                .collect();
            chosen = farthest_point_sample(&dense.xyz, &near, p.gripper_points, &mut rng);
            taken = vec![false; dense.len()];
            for &i in &chosen {
                taken[i] = true;
            }
        }
        let free = |i: &usize| taken.get(*i) != Some(&true);
        let (inside, outside): (Vec<usize>, Vec<usize>) = (0..dense.len())
            .filter(free)
            .partition(|&i| p.focus.contains(&dense.xyz[i]));
        let rest = p.points - chosen.len();
        let n_in = (p.points_inside - chosen.len())
            .min(inside.len())
            .max(rest.saturating_sub(outside.len()));
        let n_out = rest - n_in;
        chosen.extend(farthest_point_sample(&dense.xyz, &inside, n_in, &mut rng));
        chosen.extend(farthest_point_sample(&dense.xyz, &outside, n_out, &mut rng));
        chosen.shuffle(&mut rng);
        let has_rgb = dense.rgb.len() == dense.len();
        Ok(Points {
            xyz: chosen.iter().map(|&i| dense.xyz[i]).collect(),
            rgb: if has_rgb {
                chosen.iter().map(|&i| dense.rgb[i]).collect()
            } else {
                Vec::new()
            },
        })
    }
}

fn check_frame(c: &CameraCalibration, f: &CameraFrame) -> Result<(), CalibrationError> {
    let d = &f.depth.raw;
    check_size(c, "depth image", d.width, d.height, d.is_consistent())?;
    if let Some(col) = &f.colour {
        check_size(
            c,
            "aligned colour image",
            col.width,
            col.height,
            col.is_consistent(),
        )?;
    }
    let s = f64::from(f.depth.depth_scale);
    if !(s.is_finite() && s > 0.0) {
        return Err(CalibrationError::InvalidParameter {
            what: "depth_scale",
            value: s,
            why: "a frame's depth scale must be positive and finite (D455: 0.001)",
        });
    }
    Ok(())
}

fn check_size(
    c: &CameraCalibration,
    what: &'static str,
    w: u32,
    h: u32,
    consistent: bool,
) -> Result<(), CalibrationError> {
    if w != c.intrinsics.width || h != c.intrinsics.height || !consistent {
        return Err(CalibrationError::ImageSize {
            camera: c.id,
            what,
            expected_width: c.intrinsics.width,
            expected_height: c.intrinsics.height,
            got_width: w,
            got_height: h,
        });
    }
    Ok(())
}

/// A multiplicative hasher for packed integer keys (the std SipHash costs more than the rest
/// of a voxel insert; the keys are not attacker-controlled).
#[derive(Default)]
struct KeyHasher(u64);

impl Hasher for KeyHasher {
    fn finish(&self) -> u64 {
        self.0
    }
    fn write(&mut self, bytes: &[u8]) {
        for b in bytes {
            self.0 = (self.0.rotate_left(5) ^ u64::from(*b)).wrapping_mul(0x517c_c1b7_2722_0a95);
        }
    }
    fn write_u64(&mut self, v: u64) {
        // splitmix64's finaliser: every key bit reaches the low bits hashbrown indexes by
        // (a bare multiply left the bucket chosen by x alone: 10x slower neighbour search).
        let mut z = v ^ self.0;
        z = (z ^ (z >> 30)).wrapping_mul(0xbf58_476d_1ce4_e5b9);
        z = (z ^ (z >> 27)).wrapping_mul(0x94d0_49bb_1331_11eb);
        self.0 = z ^ (z >> 31);
    }
}

type KeyMap<V> = HashMap<u64, V, BuildHasherDefault<KeyHasher>>;

/// Packs a grid cell (21 bits per axis, offset so that negative cells fit).
fn cell_key(p: &Point3<f32>, inv: f32) -> u64 {
    let f = |v: f32| (grid::cell_coord(v, inv) + (1 << 20)) as u64;
    f(p.x) | (f(p.y) << 21) | (f(p.z) << 42)
}

fn key_offset(key: u64, dx: i64, dy: i64, dz: i64) -> u64 {
    let m = (1u64 << 21) - 1;
    let a =
        |shift: u32, d: i64| ((((key >> shift) & m) as i64 + d).clamp(0, m as i64) as u64) << shift;
    a(0, dx) | a(21, dy) | a(42, dz)
}

/// Replaces the points of each occupied voxel (edge `voxel_m`, grid corner at `origin`) by
/// their centroid (and mean colour), like Open3D's `voxel_down_sample`. Output order: first
/// occurrence. Anchor the grid in the base frame (not at the cloud's minimum, as Open3D
/// does) so that voxels stay put from frame to frame. Voxels are found in a dense grid
/// around the cloud (a hash map when that would be too large).
pub fn voxel_downsample(points: &Points, voxel_m: f64, origin: [f64; 3]) -> Points {
    let mut out = Points::default();
    VoxelScratch::default().voxelise(points, voxel_m, origin, None, &mut out);
    out
}

/// `voxel_downsample` with a hash map of voxels: for clouds spread too wide for a dense
/// grid, and the reference the dense grid is tested against.
fn voxel_downsample_hashed(points: &Points, voxel_m: f64, origin: [f64; 3]) -> Points {
    let inv = (1.0 / voxel_m) as f32;
    let o = Vector3::new(origin[0] as f32, origin[1] as f32, origin[2] as f32);
    let has_rgb = points.rgb.len() == points.len();
    let mut slots: KeyMap<u32> = KeyMap::default();
    slots.reserve(points.len() / 4);
    let mut acc: Vec<([f64; 3], [u32; 3], u32)> = Vec::new();
    for (i, p) in points.xyz.iter().enumerate() {
        let key = cell_key(&(p - o), inv);
        let slot = *slots.entry(key).or_insert_with(|| {
            acc.push(([0.0; 3], [0; 3], 0));
            (acc.len() - 1) as u32
        });
        let a = &mut acc[slot as usize];
        for k in 0..3 {
            a.0[k] += f64::from(p[k]);
        }
        if has_rgb {
            for k in 0..3 {
                a.1[k] += u32::from(points.rgb[i][k]);
            }
        }
        a.2 += 1;
    }
    let mut out = Points {
        xyz: Vec::with_capacity(acc.len()),
        rgb: Vec::with_capacity(if has_rgb { acc.len() } else { 0 }),
    };
    for (s, c, n) in acc {
        out.xyz.push(voxel_centroid(&s, n));
        if has_rgb {
            out.rgb.push(voxel_colour(&c, n));
        }
    }
    out
}

/// The centroid of a voxel's `n` points from their coordinate sums (both voxelisers, so
/// the dense grid and the hash map give the same points to the bit).
fn voxel_centroid(sum: &[f64; 3], n: u32) -> Point3<f32> {
    let nf = f64::from(n);
    Point3::new(
        (sum[0] / nf) as f32,
        (sum[1] / nf) as f32,
        (sum[2] / nf) as f32,
    )
}

/// The mean colour of a voxel's `n` points from their channel sums.
fn voxel_colour(sum: &[u32; 3], n: u32) -> Rgb {
    sum.map(|v| (v / n) as u8)
}

/// Drops every point within `margin` of the robot's capsules.
pub fn remove_robot(points: &Points, robot: &[Capsule], margin: f64) -> Points {
    if robot.is_empty() {
        return points.clone();
    }
    // Each capsule's box, grown by its reach and a margin far above rounding: a point
    // outside it is farther than the reach, so only points inside are measured.
    let boxes: Vec<([f64; 3], [f64; 3])> = robot
        .iter()
        .map(|c| {
            let reach = (c.radius + margin) * (1.0 + 1e-9) + 1e-9;
            (
                [0, 1, 2].map(|a| c.a[a].min(c.b[a]) - reach),
                [0, 1, 2].map(|a| c.a[a].max(c.b[a]) + reach),
            )
        })
        .collect();
    points.select(|i| {
        let p = points.xyz[i].cast::<f64>();
        robot.iter().zip(&boxes).all(|(c, (lo, hi))| {
            (0..3).any(|a| p[a] < lo[a] || p[a] > hi[a]) || c.axis_distance(&p) > c.radius + margin
        })
    })
}

/// Open3D's statistical outlier removal: a point is an outlier when its mean distance to
/// its `k` nearest neighbours exceeds the mean of that over all points by `std_ratio`
/// standard deviations. Neighbour distances are capped at `3 cell_m` (a point with fewer
/// neighbours within the cap is isolated; see [`mean_neighbour_distances`]). Non-finite
/// points are removed.
pub fn remove_statistical_outliers(
    points: &Points,
    k: usize,
    std_ratio: f64,
    cell_m: f64,
) -> Points {
    remove_outliers_with(points, k, std_ratio, cell_m, &mut KnnScratch::default())
}

/// [`remove_statistical_outliers`] with the pipeline's reused buffers.
fn remove_outliers_with(
    points: &Points,
    k: usize,
    std_ratio: f64,
    cell_m: f64,
    scratch: &mut KnnScratch,
) -> Points {
    if points.is_empty() || k == 0 {
        return points.clone();
    }
    scratch.mean_neighbour_distances(&points.xyz, k, cell_m);
    let mean_dist = &scratch.mean;
    let finite = || {
        mean_dist
            .iter()
            .filter(|d| d.is_finite())
            .map(|&d| f64::from(d))
    };
    let count = finite().count();
    if count == 0 {
        return Points::default();
    }
    let m = finite().sum::<f64>() / count as f64;
    let var = finite().map(|d| (d - m).powi(2)).sum::<f64>() / (count.max(2) - 1) as f64;
    let threshold = m + std_ratio * var.sqrt();
    points.select(|i| f64::from(mean_dist[i]) <= threshold)
}

/// Each point's mean distance to its `k` nearest neighbours (itself excluded), with each
/// distance capped at 3 grid cells (`cell_m`) and missing neighbours counted at that cap:
/// exact whenever the k-th neighbour lies within 3 cells. Non-finite points are nobody's
/// neighbour and get `+inf`.
pub fn mean_neighbour_distances(points: &[Point3<f32>], k: usize, cell_m: f64) -> Vec<f32> {
    let mut scratch = KnnScratch::default();
    scratch.mean_neighbour_distances(points, k, cell_m);
    scratch.mean
}

/// Farthest point sampling of `count` of the points `candidates` (indices into `xyz`),
/// starting from a random one. Returns the chosen indices (all candidates if fewer).
/// Each next point is the first candidate farthest from those chosen (squared distances in
/// f32); buckets of nearby candidates skip the distance updates that cannot change
/// anything ([`cell_types::fps`]), which gives the same samples as the textbook loop.
pub fn farthest_point_sample(
    xyz: &[Point3<f32>],
    candidates: &[usize],
    count: usize,
    rng: &mut ChaCha8Rng,
) -> Vec<usize> {
    use rand::Rng;
    if count == 0 || candidates.is_empty() {
        return Vec::new();
    }
    if candidates.len() <= count {
        return candidates.to_vec();
    }
    let first = rng.random_range(0..candidates.len());
    cell_types::fps::farthest_point_sample(xyz, candidates, count, first)
}

/// Point-to-plane agreement of cloud `a` with cloud `b`: for each point of `a` with at least
/// 10 points of `b` within `radius`, the signed distance to the plane fitted to those points.
/// Returns (RMS, mean, number of points compared); the overlap check of issues 7 and 8.
pub fn overlap_residual(a: &[Point3<f32>], b: &[Point3<f32>], radius: f64) -> (f64, f64, usize) {
    let inv = (1.0 / radius) as f32;
    let mut cells: KeyMap<Vec<u32>> = KeyMap::default();
    for (j, p) in b.iter().enumerate() {
        cells.entry(cell_key(p, inv)).or_default().push(j as u32);
    }
    let r2 = (radius * radius) as f32;
    let (mut sum2, mut sum, mut n) = (0.0f64, 0.0f64, 0usize);
    let mut nb: Vec<Vector3<f64>> = Vec::new();
    for p in a {
        nb.clear();
        let key = cell_key(p, inv);
        for dz in -1..=1 {
            for dy in -1..=1 {
                for dx in -1..=1 {
                    if let Some(js) = cells.get(&key_offset(key, dx, dy, dz)) {
                        for &j in js {
                            if (b[j as usize] - p).norm_squared() <= r2 {
                                nb.push(b[j as usize].coords.cast::<f64>());
                            }
                        }
                    }
                }
            }
        }
        if nb.len() < 10 {
            continue;
        }
        let c = nb.iter().sum::<Vector3<f64>>() / nb.len() as f64;
        let mut m = nalgebra::Matrix3::zeros();
        for q in &nb {
            let d = q - c;
            m += d * d.transpose();
        }
        let eig = m.symmetric_eigen();
        let normal = eig.eigenvectors.column(eig.eigenvalues.imin()).into_owned();
        // Orient normals the same way (+z first, then +x) so that the mean is meaningful.
        let normal = if normal.z < 0.0 || (normal.z == 0.0 && normal.x < 0.0) {
            -normal
        } else {
            normal
        };
        let d = (p.coords.cast::<f64>() - c).dot(&normal);
        sum2 += d * d;
        sum += d;
        n += 1;
    }
    if n == 0 {
        return (f64::NAN, f64::NAN, 0);
    }
    ((sum2 / n as f64).sqrt(), sum / n as f64, n)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::camera::DepthMode;
    use cell_types::{DepthImage, Image};
    use std::time::Duration;

    fn calib(ids: &[u8]) -> CellCalibration {
        CellCalibration {
            cameras: ids
                .iter()
                .map(|&id| CameraCalibration {
                    id,
                    intrinsics: Intrinsics::d455_depth(DepthMode::Vga640x480),
                    // Looking straight down from 1 m above the workspace centre.
                    base_from_camera: Transform::from_xyz_rpy(
                        [0.57, 0.0, 0.9],
                        [std::f64::consts::PI, 0.0, -std::f64::consts::FRAC_PI_2],
                    ),
                    depth_correction: DepthCorrection::default(),
                })
                .collect(),
        }
    }

    fn frame(id: u8, raw: u16) -> CameraFrame {
        CameraFrame {
            camera: id,
            timestamp: Duration::ZERO,
            depth: DepthImage {
                raw: Image::filled(640, 480, raw),
                depth_scale: 0.001,
            },
            ir: None,
            colour: None,
        }
    }

    fn grid_plane(n: usize, step: f32) -> Points {
        let mut p = Points::default();
        for i in 0..n {
            for j in 0..n {
                p.xyz
                    .push(Point3::new(i as f32 * step, j as f32 * step, 0.0));
            }
        }
        p
    }

    #[test]
    fn flat_table_frames_fuse_to_the_table_plane() {
        let pipe = FusionPipeline::new(calib(&[0, 1]), FusionParams::default()).unwrap();
        // 0.9 m - 0.95 m = table at z = -0.05.
        let out = pipe.fuse(&[frame(1, 950), frame(0, 950)], &[]).unwrap();
        assert_eq!(out.sampled.len(), 2048);
        assert_eq!(out.stats.valid_pixels, vec![640 * 480; 2]);
        for p in out.dense.points.iter().chain(&out.sampled.points) {
            assert!((p.z + 0.05).abs() < 1e-4, "{p:?}");
            assert!(Bounds::EQUACT_WORKSPACE.contains(p));
        }
        // All inside the focus box (z >= -0.06): no point outside to sample from.
        assert!(out.sampled.rgb.is_none());
    }

    #[test]
    fn the_calibrated_depth_error_is_undone_on_deprojection() {
        let mut cal = calib(&[0]);
        let dc = DepthCorrection {
            scale: 1.01,
            offset_m: 0.0094,
        };
        cal.cameras[0].depth_correction = dc;
        let pipe = FusionPipeline::new(cal, FusionParams::default()).unwrap();
        let (pts, _) = pipe.camera_points(&frame(0, 950)).unwrap();
        // The camera is 0.9 m above z = 0, looking down.
        let z = 0.9 - dc.true_depth(0.95);
        assert!(!pts.xyz.is_empty());
        for p in &pts.xyz {
            assert!((f64::from(p.z) - z).abs() < 1e-5, "{p:?} vs {z}");
        }
        let mut bad = calib(&[0]);
        bad.cameras[0].depth_correction.scale = 0.0;
        assert!(FusionPipeline::new(bad.clone(), FusionParams::default()).is_err());
        assert!(bad.validate_against(&[0]).is_err());
    }

    #[test]
    fn bad_frame_sets_are_typed_errors() {
        let pipe = FusionPipeline::new(calib(&[0, 1]), FusionParams::default()).unwrap();
        assert_eq!(
            pipe.fuse(&[frame(0, 950)], &[]).unwrap_err(),
            CalibrationError::MissingFrame {
                camera: 1,
                expected: vec![0, 1]
            }
        );
        assert!(matches!(
            pipe.fuse(&[frame(0, 950), frame(1, 950), frame(7, 950)], &[]),
            Err(CalibrationError::UnknownCamera { camera: 7, .. })
        ));
        assert!(matches!(
            pipe.fuse(&[frame(0, 950), frame(0, 950)], &[]),
            Err(CalibrationError::DuplicateCamera { camera: 0 })
        ));
        assert!(matches!(
            pipe.fuse(&[frame(0, 950), frame(1, 0)], &[]),
            Err(CalibrationError::NoValidDepth { camera: 1, .. })
        ));
        let mut nan = frame(1, 950);
        nan.depth.depth_scale = f32::NAN;
        assert!(matches!(
            pipe.fuse(&[frame(0, 950), nan], &[]),
            Err(CalibrationError::InvalidParameter {
                what: "depth_scale",
                ..
            })
        ));
        let mut short = frame(1, 950);
        short.depth.raw.data.pop();
        assert!(matches!(
            pipe.fuse(&[frame(0, 950), short], &[]),
            Err(CalibrationError::ImageSize { camera: 1, .. })
        ));
        // A camera that only sees beyond the workspace gives too few points, not a panic.
        assert!(matches!(
            pipe.fuse(&[frame(0, 5000), frame(1, 5000)], &[]),
            Err(CalibrationError::TooFewPoints { got: 0, .. })
        ));
    }

    #[test]
    fn calibration_naming_an_unknown_camera_or_bad_pose_is_rejected() {
        let c = calib(&[0, 1, 5]);
        assert!(matches!(
            c.validate_against(&[0, 1, 2]),
            Err(CalibrationError::UnknownCamera { camera: 5, .. })
        ));
        let mut c = calib(&[0, 1]);
        c.cameras[1].base_from_camera = Transform::from_parts(
            Vector3::new(f64::NAN, 0.0, 0.0),
            nalgebra::UnitQuaternion::identity(),
        );
        assert!(matches!(
            FusionPipeline::new(c, FusionParams::default()),
            Err(CalibrationError::BadExtrinsics { camera: 1 })
        ));
        let params = FusionParams {
            voxel_m: f64::NAN,
            ..FusionParams::default()
        };
        assert!(matches!(
            FusionPipeline::new(calib(&[0]), params),
            Err(CalibrationError::InvalidParameter {
                what: "voxel_m",
                ..
            })
        ));
    }

    #[test]
    fn voxels_average_their_points_and_colours() {
        let pts = Points {
            xyz: vec![
                Point3::new(0.001, 0.001, 0.001),
                Point3::new(0.003, 0.003, 0.003),
                Point3::new(0.011, 0.001, 0.001),
            ],
            rgb: vec![[0, 0, 0], [100, 200, 50], [9, 9, 9]],
        };
        let v = voxel_downsample(&pts, 0.005, [0.0; 3]);
        assert_eq!(v.len(), 2);
        assert!((v.xyz[0] - Point3::new(0.002, 0.002, 0.002)).norm() < 1e-7);
        assert_eq!(v.rgb, vec![[50, 100, 25], [9, 9, 9]]);
    }

    #[test]
    fn statistical_outliers_are_removed_and_the_surface_kept() {
        use rand::Rng;
        // A noisy, unevenly sampled surface, like a voxelised depth cloud.
        let mut rng = ChaCha8Rng::seed_from_u64(3);
        let mut pts = grid_plane(60, 0.005);
        for p in &mut pts.xyz {
            p.x += rng.random_range(-0.0015..0.0015);
            p.y += rng.random_range(-0.0015..0.0015);
            p.z += rng.random_range(-0.001..0.001);
        }
        let n_plane = pts.len();
        pts.xyz.push(Point3::new(0.15, 0.15, 0.05)); // 5 cm above the plane
        pts.xyz.push(Point3::new(0.1, 0.1, 0.012)); // a flying pixel 12 mm off
        let kept = remove_statistical_outliers(&pts, 20, 2.0, 0.015);
        assert!(!kept.xyz.contains(&Point3::new(0.15, 0.15, 0.05)));
        assert!(!kept.xyz.contains(&Point3::new(0.1, 0.1, 0.012)));
        // The surface survives; only some border points may go.
        assert!(
            kept.len() > n_plane * 95 / 100,
            "{} of {n_plane}",
            kept.len()
        );
    }

    #[test]
    fn grid_knn_matches_brute_force_on_random_clouds() {
        use rand::Rng;
        let mut rng = ChaCha8Rng::seed_from_u64(11);
        let cell = 0.015;
        let reach = 3.0 * cell as f32;
        for trial in 0..20 {
            // Clusters of different densities and sizes, some sparse enough to need the
            // second and third rings, some points isolated.
            let mut pts = Vec::new();
            for _ in 0..rng.random_range(1..6) {
                let c = Point3::new(
                    rng.random_range(-0.3f32..0.3),
                    rng.random_range(-0.3f32..0.3),
                    rng.random_range(-0.3f32..0.3),
                );
                let spread = rng.random_range(0.002f32..0.05);
                for _ in 0..rng.random_range(5..300) {
                    pts.push(
                        c + Vector3::new(
                            rng.random_range(-spread..spread),
                            rng.random_range(-spread..spread),
                            rng.random_range(-spread..spread),
                        ),
                    );
                }
            }
            let k = rng.random_range(1..25);
            let fast = mean_neighbour_distances(&pts, k, cell);
            for (i, p) in pts.iter().enumerate() {
                let mut d: Vec<f32> = pts
                    .iter()
                    .enumerate()
                    .filter(|(j, _)| *j != i)
                    .map(|(_, q)| (q - p).norm())
                    .collect();
                d.sort_by(f32::total_cmp);
                // Exact when the k-th neighbour is within reach; otherwise the neighbours
                // within reach plus "reach" for each missing one.
                let within: Vec<f32> = d.iter().copied().filter(|&x| x <= reach).take(k).collect();
                let expected =
                    (within.iter().sum::<f32>() + (k - within.len()) as f32 * reach) / k as f32;
                let ok = (fast[i] - expected).abs() < 1e-5;
                assert!(
                    ok,
                    "trial {trial} point {i} k {k}: {} vs {expected}",
                    fast[i]
                );
            }
        }
    }

    /// Brute-force reference of `mean_neighbour_distances`: finite points only.
    fn brute_mean_distances(pts: &[Point3<f32>], k: usize, reach: f32) -> Vec<f32> {
        let finite = |p: &Point3<f32>| p.iter().all(|v| v.is_finite());
        pts.iter()
            .enumerate()
            .map(|(i, p)| {
                if !finite(p) {
                    return f32::INFINITY;
                }
                let mut d: Vec<f32> = pts
                    .iter()
                    .enumerate()
                    .filter(|(j, q)| *j != i && finite(q))
                    .map(|(_, q)| (q - p).norm())
                    .collect();
                d.sort_by(f32::total_cmp);
                let within: Vec<f32> = d.iter().copied().filter(|&x| x <= reach).take(k).collect();
                (within.iter().sum::<f32>() + (k - within.len()) as f32 * reach) / k as f32
            })
            .collect()
    }

    #[test]
    fn grid_knn_is_exact_on_widely_spread_clouds_and_skips_non_finite_points() {
        use rand::Rng;
        let mut rng = ChaCha8Rng::seed_from_u64(5);
        let cell = 0.01;
        let reach = 3.0 * cell as f32;
        // Clusters kilometres apart: the grid cannot cover them all and clamps the far ones
        // into its border cells, and duplicates (distance 0) must still count.
        for trial in 0..10 {
            let mut pts = Vec::new();
            for _ in 0..rng.random_range(2..5) {
                let c = Point3::new(
                    rng.random_range(-2000.0f32..2000.0),
                    rng.random_range(-1.0f32..1.0),
                    rng.random_range(-300.0f32..300.0),
                );
                for _ in 0..rng.random_range(20..200) {
                    pts.push(
                        c + Vector3::new(
                            rng.random_range(-0.03f32..0.03),
                            rng.random_range(-0.03f32..0.03),
                            rng.random_range(-0.03f32..0.03),
                        ),
                    );
                }
            }
            pts.push(pts[3]);
            pts.push(Point3::new(f32::NAN, 0.0, 0.0));
            pts.push(Point3::new(f32::INFINITY, 0.0, 0.0));
            let k = rng.random_range(1..25);
            let fast = mean_neighbour_distances(&pts, k, cell);
            let slow = brute_mean_distances(&pts, k, reach);
            for (i, (f, s)) in fast.iter().zip(&slow).enumerate() {
                // Centred kilometres out, f32 differences are exact only to ~1e-4 m.
                let ok = f == s || (f - s).abs() < 2e-4;
                assert!(ok, "trial {trial} point {i} k {k}: {f} vs {s}");
            }
        }
        let kept = remove_statistical_outliers(
            &Points {
                xyz: vec![Point3::new(f32::NAN, 0.0, 0.0), Point3::origin()],
                rgb: Vec::new(),
            },
            3,
            2.0,
            cell,
        );
        assert_eq!(kept.xyz, vec![Point3::origin()]);
    }

    #[test]
    fn dense_voxel_grid_equals_the_hash_map_on_random_clouds() {
        use rand::Rng;
        let mut rng = ChaCha8Rng::seed_from_u64(9);
        let mut scratch = VoxelScratch::default();
        for trial in 0..30 {
            let voxel = rng.random_range(0.002..0.02);
            let origin = [0, 1, 2].map(|_| rng.random_range(-0.1..0.1));
            let spread = if trial % 5 == 4 { 50.0 } else { 0.3 };
            let n = rng.random_range(0..3000);
            let mut pts = Points::default();
            for i in 0..n {
                // Repeats make many points per voxel.
                let p = if i > 0 && rng.random_bool(0.5) {
                    pts.xyz[rng.random_range(0..i)]
                        + Vector3::repeat(rng.random_range(0.0..voxel as f32))
                } else {
                    Point3::new(
                        rng.random_range(-spread..spread),
                        rng.random_range(-spread..spread),
                        rng.random_range(-spread..spread),
                    )
                };
                pts.xyz.push(p);
                if trial % 2 == 0 {
                    pts.rgb.push([rng.random(), rng.random(), rng.random()]);
                }
            }
            let reference = voxel_downsample_hashed(&pts, voxel, origin);
            assert_eq!(
                voxel_downsample(&pts, voxel, origin),
                reference,
                "trial {trial}"
            );
            // A given grid too small for some points falls back; the reused scratch stays clean.
            let mut out = Points::default();
            let small = CellBox::spanning([-3; 3], [3; 3]);
            scratch.voxelise(&pts, voxel, origin, Some(small), &mut out);
            assert_eq!(out, reference, "trial {trial} (small grid)");
            let inv = (1.0 / voxel) as f32;
            let o = Vector3::new(origin[0] as f32, origin[1] as f32, origin[2] as f32);
            let all = CellBox::around(pts.xyz.iter().map(|p| grid::voxel_coords(p, &o, inv)));
            if let Some(all) = all.filter(|b| b.brick_cells() <= grid::DENSE_VOXEL_CELLS) {
                scratch.voxelise(&pts, voxel, origin, Some(all), &mut out);
                assert_eq!(out, reference, "trial {trial} (given grid)");
            }
        }
    }

    #[test]
    fn reused_buffers_give_the_same_cloud_as_a_fresh_pipeline() {
        let pipe = FusionPipeline::new(calib(&[0, 1]), FusionParams::default()).unwrap();
        let near = [frame(0, 950), frame(1, 900)];
        let far = [frame(0, 1000), frame(1, 980)];
        let first = pipe.fuse(&near, &[]).unwrap();
        let _ = pipe.fuse(&far, &[]).unwrap();
        assert_eq!(pipe.fuse(&near, &[]).unwrap(), first);
        assert_eq!(pipe.clone().fuse(&near, &[]).unwrap(), first);
    }

    #[test]
    fn edge_windows_match_the_3x3_window_of_valid_depths() {
        use rand::Rng;
        let mut rng = ChaCha8Rng::seed_from_u64(2);
        let mut edges = EdgeWindows::default();
        for (w, h) in [(1, 1), (1, 5), (5, 1), (2, 2), (17, 9), (64, 3)] {
            let data: Vec<u16> = (0..w * h)
                .map(|_| match rng.random_range(0..4) {
                    0 => 0,
                    1 => u16::MAX,
                    _ => rng.random_range(1..3000),
                })
                .collect();
            edges.rows(&data, w);
            for v in 0..h {
                for u in 0..w {
                    if data[v * w + u] == 0 {
                        continue;
                    }
                    let window: Vec<u16> = (v.saturating_sub(1)..(v + 2).min(h))
                        .flat_map(|nv| {
                            (u.saturating_sub(1)..(u + 2).min(w)).map(move |nu| (nv, nu))
                        })
                        .map(|(nv, nu)| data[nv * w + nu])
                        .filter(|&r| r != 0)
                        .collect();
                    let expected = (
                        window.iter().copied().min().unwrap(),
                        window.iter().copied().max().unwrap(),
                    );
                    let up = v.saturating_sub(1) * w + u;
                    let down = (v + 1).min(h - 1) * w + u;
                    assert_eq!(
                        edges.window(up, v * w + u, down),
                        expected,
                        "{w}x{h} ({u}, {v})"
                    );
                }
            }
        }
    }

    #[test]
    fn robot_capsules_remove_their_points() {
        let pts = grid_plane(40, 0.01);
        let arm = Capsule {
            a: Point3::new(0.2, 0.2, -0.1),
            b: Point3::new(0.2, 0.2, 0.1),
            radius: 0.03,
        };
        let kept = remove_robot(&pts, &[arm], 0.01);
        assert!(kept
            .xyz
            .iter()
            .all(|p| arm.axis_distance(&p.cast::<f64>()) > 0.04));
        // A disc of radius 4 cm on a 1 cm grid: about 49 points.
        let removed = pts.len() - kept.len();
        assert!((40..=60).contains(&removed), "{removed}");
    }

    #[test]
    fn farthest_point_sampling_spreads_points_out() {
        let pts = grid_plane(50, 0.01);
        let all: Vec<usize> = (0..pts.len()).collect();
        let mut rng = ChaCha8Rng::seed_from_u64(1);
        let chosen = farthest_point_sample(&pts.xyz, &all, 25, &mut rng);
        assert_eq!(chosen.len(), 25);
        let mut min_d = f32::INFINITY;
        for (i, &a) in chosen.iter().enumerate() {
            for &b in &chosen[..i] {
                min_d = min_d.min((pts.xyz[a] - pts.xyz[b]).norm());
            }
        }
        // 25 points on a 0.49 m square: a 5x5 lattice has spacing ~0.12 m.
        assert!(min_d > 0.09, "{min_d}");
    }

    #[test]
    fn bucketed_farthest_point_sampling_equals_the_textbook_loop() {
        use cell_types::fps::{farthest_point_sample, farthest_point_sample_textbook};
        use rand::Rng;
        let mut rng = ChaCha8Rng::seed_from_u64(17);
        for trial in 0..40 {
            let mut xyz = Vec::new();
            match trial % 4 {
                // A lattice: many equal distances, so ties must go to the first candidate.
                0 => xyz.extend(grid_plane(rng.random_range(5..40), 0.01).xyz),
                // Clusters of different spreads, with duplicates.
                1 | 2 => {
                    for _ in 0..rng.random_range(1..6) {
                        let c = Vector3::new(
                            rng.random_range(-1.0f32..1.0),
                            rng.random_range(-1.0f32..1.0),
                            rng.random_range(-1.0f32..1.0),
                        );
                        let spread = rng.random_range(0.0f32..0.3);
                        for _ in 0..rng.random_range(1..800) {
                            let p = if !xyz.is_empty() && rng.random_bool(0.05) {
                                xyz[rng.random_range(0..xyz.len())]
                            } else {
                                Point3::from(
                                    c + Vector3::from_fn(|_, _| rng.random_range(-spread..=spread)),
                                )
                            };
                            xyz.push(p);
                        }
                    }
                }
                // All on one line, and all in one point.
                _ => {
                    let n = rng.random_range(2..500);
                    let same = rng.random_bool(0.3);
                    xyz.extend((0..n).map(|i| {
                        let t = if same { 0.25 } else { i as f32 * 0.003 };
                        Point3::new(t, 0.5, -t)
                    }));
                }
            }
            // A subset of the points as candidates, in shuffled order.
            let mut candidates: Vec<usize> =
                (0..xyz.len()).filter(|_| rng.random_bool(0.8)).collect();
            candidates.shuffle(&mut rng);
            if candidates.len() < 2 {
                continue;
            }
            let count = rng.random_range(1..candidates.len());
            let first = rng.random_range(0..candidates.len());
            assert_eq!(
                farthest_point_sample(&xyz, &candidates, count, first),
                farthest_point_sample_textbook(&xyz, &candidates, count, first),
                "trial {trial}: {} candidates, {count} samples",
                candidates.len()
            );
        }
        // Non-finite candidates keep the textbook behaviour.
        let mut xyz = grid_plane(10, 0.01).xyz;
        xyz[7] = Point3::new(f32::NAN, 0.0, 0.0);
        xyz[8] = Point3::new(f32::INFINITY, 0.0, 0.0);
        let all: Vec<usize> = (0..xyz.len()).collect();
        assert_eq!(
            farthest_point_sample(&xyz, &all, 30, 3),
            farthest_point_sample_textbook(&xyz, &all, 30, 3)
        );
    }

    #[test]
    fn sampling_a_fused_cloud_equals_the_textbook_loop() {
        use cell_types::fps::farthest_point_sample_textbook;
        // The pipeline's split and shuffle around the textbook sampler, on a fused cloud.
        let params = FusionParams {
            focus: Bounds {
                min: [0.3, -0.39, -0.06],
                max: [0.96, 0.1, 0.53],
            },
            ..FusionParams::default()
        };
        let pipe = FusionPipeline::new(calib(&[0, 1]), params.clone()).unwrap();
        let (dense, _) = pipe
            .fuse_dense(&[frame(0, 950), frame(1, 900)], &[])
            .unwrap();
        let (inside, outside): (Vec<usize>, Vec<usize>) =
            (0..dense.len()).partition(|&i| params.focus.contains(&dense.xyz[i]));
        assert!(inside.len() > params.points_inside && outside.len() > 512);
        let mut rng = ChaCha8Rng::seed_from_u64(params.seed);
        use rand::Rng;
        let mut chosen = {
            let first = rng.random_range(0..inside.len());
            farthest_point_sample_textbook(&dense.xyz, &inside, params.points_inside, first)
        };
        chosen.extend({
            let first = rng.random_range(0..outside.len());
            farthest_point_sample_textbook(&dense.xyz, &outside, 512, first)
        });
        chosen.shuffle(&mut rng);
        let expected: Vec<Point3<f32>> = chosen.iter().map(|&i| dense.xyz[i]).collect();
        assert_eq!(pipe.sample(&dense).unwrap().xyz, expected);
    }

    #[test]
    fn inside_outside_split_follows_equact() {
        let mut params = FusionParams {
            points: 40,
            points_inside: 30,
            ..FusionParams::default()
        };
        params.focus = Bounds {
            min: [0.0, 0.0, 0.0],
            max: [1.0, 1.0, 1.0],
        };
        let pipe = FusionPipeline::new(calib(&[0]), params).unwrap();
        let mut pts = grid_plane(20, 0.01); // z = 0: inside
        for i in 0..100 {
            pts.xyz.push(Point3::new(i as f32 * 0.01, 0.0, -0.5)); // outside
        }
        let s = pipe.sample(&pts).unwrap();
        let inside = s
            .xyz
            .iter()
            .filter(|p| pipe.params().focus.contains(p))
            .count();
        assert_eq!((s.len(), inside), (40, 30));
    }

    #[test]
    fn gripper_points_sample_the_ball_around_the_tcp_densely() {
        let params = FusionParams {
            points: 100,
            points_inside: 100,
            gripper_points: 40,
            gripper_radius_m: 0.05,
            focus: Bounds {
                min: [-1.0, -1.0, -1.0],
                max: [2.0, 2.0, 2.0],
            },
            ..FusionParams::default()
        };
        let pipe = FusionPipeline::new(calib(&[0]), params).unwrap();
        let pts = grid_plane(100, 0.005); // 0.5 m square, 5 mm spacing
        let tcp = Point3::new(0.25f32, 0.25, 0.02);
        let near = |s: &Points| s.xyz.iter().filter(|p| (*p - tcp).norm() <= 0.05).count();
        let plain = pipe.sample(&pts).unwrap();
        assert_eq!(pipe.sample_at(&pts, None).unwrap(), plain);
        let dense = pipe.sample_at(&pts, Some(tcp)).unwrap();
        assert_eq!(dense.len(), 100);
        // Plain sampling spreads 100 points about 5 cm apart: a handful in the ball.
        assert!(near(&plain) < 10, "{}", near(&plain));
        assert!(near(&dense) >= 40, "{}", near(&dense));
        let mut seen: Vec<_> = dense
            .xyz
            .iter()
            .map(|p| (p.x.to_bits(), p.y.to_bits()))
            .collect();
        seen.sort_unstable();
        seen.dedup();
        assert_eq!(seen.len(), 100, "a point sampled twice");
        // A TCP away from every point leaves the plain split.
        let far = Point3::new(5.0f32, 5.0, 5.0);
        assert_eq!(pipe.sample_at(&pts, Some(far)).unwrap().len(), 100);
        let bad = FusionParams {
            gripper_points: 2000,
            ..FusionParams::default()
        };
        assert!(matches!(
            FusionPipeline::new(calib(&[0]), bad),
            Err(CalibrationError::InvalidParameter {
                what: "gripper_points",
                ..
            })
        ));
    }
}
