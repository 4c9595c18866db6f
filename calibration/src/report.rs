//! The calibration report and `calibration.toml` (issue 8 item 4).
//!
//! [`Solution::report`] condenses a solution into a [`Report`] (text via its `Display`, JSON
//! via serde): per camera the held-out reprojection RMS (k-fold over robot poses, recorded
//! robot poses, px per coordinate), the fit RMS, the one-sigma pose uncertainty, and the
//! depth-vs-board-plane residual. [`Solution::write_calibration_toml`] writes what the
//! perception pipeline reads: a [`CellCalibration`] (`[[cameras]]` with id, intrinsics and
//! `base_from_camera`), plus the board pose and the quality numbers for people.

use std::fmt;
use std::path::Path;

use cell_types::{Board, Flange, Transform};
use serde::{Deserialize, Serialize};

use cell_types::{CameraFrame, FrameId, Image, PointCloud, Rgb};
use nalgebra::Point3;

use crate::camera::DepthCorrection;
use crate::capture::write_atomic;
use crate::error::CalibrationError;
use crate::fusion::{overlap_residual, Bounds, CameraCalibration, CellCalibration, FusionPipeline};
use crate::solve::{DepthResidual, RejectedView, Solution};

/// The format tag of `calibration.toml`.
pub const CALIBRATION_FORMAT: &str = "equact-calibration/1";

/// One camera's line of the report.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct CameraReport {
    /// Camera id.
    pub id: u8,
    /// Camera name.
    pub name: String,
    /// Poses in which it saw the board.
    pub views: usize,
    /// Translation of `base_from_camera` (m).
    pub translation_m: [f64; 3],
    /// Rotation of `base_from_camera` as a quaternion `[x, y, z, w]`.
    pub rotation_xyzw: [f64; 4],
    /// Held-out reprojection RMS (px per coordinate), when cross-validated.
    pub heldout_rms_px: Option<f64>,
    /// Fit reprojection RMS (px per coordinate).
    pub fit_rms_px: f64,
    /// One-sigma position uncertainty along base x, y, z (mm).
    pub sigma_pos_mm: [f64; 3],
    /// One-sigma rotation uncertainty about base x, y, z (deg).
    pub sigma_rot_deg: [f64; 3],
    /// Depth measured on the board minus the calibrated board plane.
    pub depth: Option<DepthResidual>,
    /// The depth correction written to `calibration.toml` (identity when none was fitted).
    #[serde(default)]
    pub depth_correction: DepthCorrection,
    /// Refined `[fx, fy, ppx, ppy]` (px) and their one-sigma, when the intrinsics were
    /// refined.
    #[serde(default)]
    pub refined_intrinsics: Option<([f64; 4], [f64; 4])>,
}

/// A calibration's report.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Report {
    /// Per camera.
    pub cameras: Vec<CameraReport>,
    /// The board on the flange.
    pub flange_from_board: Transform<Flange, Board>,
    /// Robot poses used.
    pub poses: usize,
    /// Corner observations used.
    pub observations: usize,
    /// Views left out, and why.
    pub rejected: Vec<RejectedView>,
    /// Residual variance factor (about 1 when the noise model is right).
    pub variance_factor: f64,
    /// Corner noise assumed (px per coordinate): the floor of the held-out RMS.
    pub corner_sigma_px: f64,
    /// RMS flange-pose corrections (mm, deg), when the robot prior is on.
    pub robot_correction_rms: Option<(f64, f64)>,
    /// Cross-camera overlap check, when frames of a scene were given ([`overlap_check`]).
    #[serde(default)]
    pub overlap: Vec<OverlapPair>,
}

/// How well camera `a`'s points lie on camera `b`'s surfaces in a region both see.
#[derive(Copy, Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct OverlapPair {
    /// The camera whose points are checked.
    pub a: u8,
    /// The camera whose surfaces they are checked against.
    pub b: u8,
    /// Points compared.
    pub points: usize,
    /// RMS point-to-plane distance (mm).
    pub rms_mm: f64,
    /// Mean signed point-to-plane distance (mm): a calibration error shows as an offset.
    pub mean_mm: f64,
}

/// Colours of the overlay picture, by camera order: red, green, blue, then yellow, cyan,
/// magenta.
pub const CAMERA_COLOURS: [Rgb; 6] = [
    [230, 60, 50],
    [60, 200, 80],
    [70, 110, 240],
    [230, 210, 60],
    [60, 210, 220],
    [210, 80, 210],
];

/// The report's picture: every camera's points inside `region`, deprojected with the
/// calibration of `pipe` and coloured by camera ([`CAMERA_COLOURS`]), rendered from `eye`
/// towards `target` through `view` (PNG encoding is the caller's). Misaligned cameras show
/// as doubled, differently coloured surfaces.
pub fn overlay_image(
    pipe: &FusionPipeline,
    frames: &[CameraFrame],
    region: &Bounds,
    view: &crate::camera::Intrinsics,
    eye: Point3<f64>,
    target: Point3<f64>,
) -> Result<Image<Rgb>, CalibrationError> {
    let mut points = Vec::new();
    let mut colours = Vec::new();
    for (i, f) in frames.iter().enumerate() {
        let (pts, _) = pipe.camera_points(f)?;
        let colour = CAMERA_COLOURS[i % CAMERA_COLOURS.len()];
        for p in pts.xyz.into_iter().filter(|p| region.contains(p)) {
            points.push(p);
            colours.push(colour);
        }
    }
    // One colour per point by construction, so the cloud is always consistent.
    let cloud = PointCloud {
        frame: FrameId::Base,
        points,
        rgb: Some(colours),
    };
    Ok(crate::view::splat(&cloud, view, eye, target, 1))
}

/// The cross-camera overlap check: each camera's depth frame deprojected with the
/// calibration of `pipe`, cropped to `region` (a part of the scene all cameras see, best a
/// multi-plane object; a flat table alone cannot reveal a shift along it), then the
/// point-to-plane residual of every ordered pair within `radius` (m).
pub fn overlap_check(
    pipe: &FusionPipeline,
    frames: &[CameraFrame],
    region: &Bounds,
    radius: f64,
) -> Result<Vec<OverlapPair>, CalibrationError> {
    let mut clouds = Vec::with_capacity(frames.len());
    for f in frames {
        let (pts, _) = pipe.camera_points(f)?;
        let inside: Vec<_> = pts.xyz.into_iter().filter(|p| region.contains(p)).collect();
        clouds.push((f.camera, inside));
    }
    let mut out = Vec::new();
    for (a, pa) in &clouds {
        for (b, pb) in &clouds {
            if a == b {
                continue;
            }
            let (rms, mean, n) = overlap_residual(pa, pb, radius);
            if n > 0 {
                out.push(OverlapPair {
                    a: *a,
                    b: *b,
                    points: n,
                    rms_mm: rms * 1e3,
                    mean_mm: mean * 1e3,
                });
            }
        }
    }
    Ok(out)
}

impl Solution {
    /// The report of this solution.
    pub fn report(&self) -> Report {
        Report {
            cameras: self
                .cameras
                .iter()
                .map(|c| {
                    let t = c.base_from_camera.translation();
                    let q = c.base_from_camera.rotation().into_inner().coords;
                    CameraReport {
                        id: c.id,
                        name: c.name.clone(),
                        views: c.views,
                        translation_m: [t.x, t.y, t.z],
                        rotation_xyzw: [q.x, q.y, q.z, q.w],
                        heldout_rms_px: c.heldout_rms_px,
                        fit_rms_px: c.fit_rms_px,
                        sigma_pos_mm: c.sigma_pos_mm,
                        sigma_rot_deg: c.sigma_rot_deg,
                        depth: c.depth,
                        depth_correction: c.depth_correction,
                        refined_intrinsics: c.intrinsics_sigma_px.map(|s| {
                            let k = &c.intrinsics;
                            ([k.fx, k.fy, k.ppx, k.ppy], s)
                        }),
                    }
                })
                .collect(),
            flange_from_board: self.flange_from_board,
            poses: self.poses,
            observations: self.observations,
            rejected: self.rejected.clone(),
            variance_factor: self.variance_factor,
            corner_sigma_px: self.options.corner_sigma_px,
            robot_correction_rms: self.robot_correction_rms,
            overlap: Vec::new(),
        }
    }

    /// The calibration the perception pipeline uses.
    pub fn calibration(&self) -> CellCalibration {
        CellCalibration {
            cameras: self
                .cameras
                .iter()
                .map(|c| CameraCalibration {
                    id: c.id,
                    intrinsics: c.intrinsics,
                    base_from_camera: c.base_from_camera,
                    depth_correction: c.depth_correction,
                })
                .collect(),
        }
    }

    /// Writes `calibration.toml` atomically (see the module docs).
    pub fn write_calibration_toml(&self, path: &Path) -> Result<(), CalibrationError> {
        let file = CalibrationFile {
            format: CALIBRATION_FORMAT.to_string(),
            cameras: self.calibration().cameras,
            flange_from_board: self.flange_from_board,
            quality: self.report().cameras,
        };
        let body = toml::to_string(&file).map_err(|e| CalibrationError::CaptureIo {
            path: path.display().to_string(),
            why: e.to_string(),
        })?;
        let text = format!(
            "# Camera extrinsics from `equact calibrate solve` (joint bundle adjustment).\n\
             # base_from_camera maps the optical frame (x right, y down, z forward) into the\n\
             # robot base; rotation is a quaternion [x, y, z, w], translation in metres.\n{body}"
        );
        write_atomic(path, text.as_bytes())
    }
}

/// What `calibration.toml` holds.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
struct CalibrationFile {
    format: String,
    cameras: Vec<CameraCalibration>,
    flange_from_board: Transform<Flange, Board>,
    quality: Vec<CameraReport>,
}

/// Reads the camera calibration from a `calibration.toml` written by
/// [`Solution::write_calibration_toml`] (other keys are ignored).
pub fn read_calibration_toml(path: &Path) -> Result<CellCalibration, CalibrationError> {
    let io = |why: String| CalibrationError::CaptureIo {
        path: path.display().to_string(),
        why,
    };
    let text = std::fs::read_to_string(path).map_err(|e| io(e.to_string()))?;
    let cal: CellCalibration = toml::from_str(&text).map_err(|e| io(e.to_string()))?;
    for c in &cal.cameras {
        if !c.base_from_camera.is_finite() {
            return Err(CalibrationError::BadExtrinsics { camera: c.id });
        }
        c.intrinsics.validate()?;
        c.depth_correction.validate()?;
    }
    Ok(cal)
}

impl Report {
    /// The report as pretty JSON.
    pub fn to_json(&self) -> String {
        serde_json::to_string_pretty(self).unwrap_or_else(|e| format!("{{\"error\": \"{e}\"}}"))
    }
}

impl fmt::Display for Report {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        writeln!(
            f,
            "calibration: {} poses, {} corner observations, variance factor {:.3}",
            self.poses, self.observations, self.variance_factor
        )?;
        for c in &self.cameras {
            let held = c
                .heldout_rms_px
                .map_or("not cross-validated".to_string(), |h| {
                    format!(
                        "{h:.3} px ({:+.3} px over the {:.2} px noise floor)",
                        h - self.corner_sigma_px,
                        self.corner_sigma_px
                    )
                });
            writeln!(f, "camera {} ({}), {} views:", c.id, c.name, c.views)?;
            writeln!(
                f,
                "  base_from_camera t = [{:.5}, {:.5}, {:.5}] m, q = [{:.6}, {:.6}, {:.6}, {:.6}]",
                c.translation_m[0],
                c.translation_m[1],
                c.translation_m[2],
                c.rotation_xyzw[0],
                c.rotation_xyzw[1],
                c.rotation_xyzw[2],
                c.rotation_xyzw[3]
            )?;
            writeln!(
                f,
                "  reprojection RMS: held-out {held}, fit {:.3} px",
                c.fit_rms_px
            )?;
            writeln!(
                f,
                "  1-sigma: position [{:.3}, {:.3}, {:.3}] mm, rotation [{:.4}, {:.4}, {:.4}] deg (base x, y, z)",
                c.sigma_pos_mm[0],
                c.sigma_pos_mm[1],
                c.sigma_pos_mm[2],
                c.sigma_rot_deg[0],
                c.sigma_rot_deg[1],
                c.sigma_rot_deg[2]
            )?;
            match &c.depth {
                Some(d) => writeln!(
                    f,
                    "  depth vs board plane: bias {:+.2} mm, RMS {:.2} mm over {} samples (fit: scale {:.5}, offset {:+.2} mm)",
                    d.mean_mm, d.rms_mm, d.samples, d.scale, d.offset_mm
                )?,
                None => writeln!(f, "  depth vs board plane: no depth samples captured")?,
            }
            let dc = c.depth_correction;
            writeln!(
                f,
                "  depth correction applied by the fusion: true = (measured {:+.2} mm) / {:.5}",
                -dc.offset_m * 1e3,
                dc.scale
            )?;
            if let Some((k, s)) = c.refined_intrinsics {
                writeln!(
                    f,
                    "  refined intrinsics: fx {:.2}+-{:.2}, fy {:.2}+-{:.2}, ppx {:.2}+-{:.2}, ppy {:.2}+-{:.2} px",
                    k[0], s[0], k[1], s[1], k[2], s[2], k[3], s[3]
                )?;
            }
        }
        if let Some((t, r)) = self.robot_correction_rms {
            writeln!(
                f,
                "robot pose corrections: RMS {t:.3} mm, {r:.4} deg (compare with the robot's accuracy)"
            )?;
        }
        for r in &self.rejected {
            writeln!(
                f,
                "left out: pose {}, camera {}: {}",
                r.pose, r.camera, r.why
            )?;
        }
        if !self.overlap.is_empty() {
            writeln!(
                f,
                "overlap (point-to-plane, camera a's points on camera b's surface):"
            )?;
        }
        for o in &self.overlap {
            writeln!(
                f,
                "  camera {} on {}: RMS {:.2} mm, mean {:+.2} mm over {} points",
                o.a, o.b, o.rms_mm, o.mean_mm, o.points
            )?;
        }
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::simulate::{simulate_set, SimConfig};
    use crate::solve::{solve, SolveOptions};

    #[test]
    fn report_and_calibration_toml_round_trip() {
        let (set, truth) = simulate_set(&SimConfig::default_cell(), 21).unwrap();
        let sol = solve(
            &set,
            &SolveOptions {
                holdout_folds: 3,
                ..SolveOptions::default()
            },
        )
        .unwrap();
        let report = sol.report();
        let text = report.to_string();
        assert!(
            text.contains("camera 2 (right_shoulder), 30 views"),
            "{text}"
        );
        assert!(text.contains("held-out") && text.contains("depth vs board plane: bias"));
        let json: serde_json::Value = serde_json::from_str(&report.to_json()).unwrap();
        assert_eq!(json["cameras"].as_array().unwrap().len(), 3);
        assert!(json["cameras"][0]["heldout_rms_px"].as_f64().unwrap() > 0.4);
        let back: Report = serde_json::from_str(&report.to_json()).unwrap();
        assert_eq!(back, report);

        let dir = std::env::temp_dir().join(format!("calib-report-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let path = dir.join("calibration.toml");
        sol.write_calibration_toml(&path).unwrap();
        let cal = read_calibration_toml(&path).unwrap();
        assert_eq!(cal, sol.calibration());
        cal.validate_against(&[0, 1, 2]).unwrap();
        for c in &cal.cameras {
            let (dt, dr) = c
                .base_from_camera
                .error_to(&truth.base_from_camera(c.id).unwrap());
            assert!(dt < 1e-3 && dr < 0.05f64.to_radians());
        }
        let text = std::fs::read_to_string(&path).unwrap();
        assert!(
            text.contains("[[cameras]]") && text.contains("[[quality]]"),
            "{text}"
        );
        // A file written before the depth correction existed reads as no correction.
        let old: String = text
            .lines()
            .filter(|l| {
                !(l.contains("depth_correction]")
                    || l.starts_with("scale =")
                    || l.starts_with("offset_m ="))
            })
            .map(|l| format!("{l}\n"))
            .collect();
        assert!(!old.contains("depth_correction]"));
        std::fs::write(&path, &old).unwrap();
        let back = read_calibration_toml(&path).unwrap();
        for (b, c) in back.cameras.iter().zip(&cal.cameras) {
            assert_eq!(b.depth_correction, DepthCorrection::default());
            assert_eq!(b.base_from_camera, c.base_from_camera);
        }
        // A broken file is a typed error naming it.
        std::fs::write(&path, "cameras = 3").unwrap();
        let err = read_calibration_toml(&path).unwrap_err();
        assert!(err.to_string().contains("calibration.toml"));
        std::fs::remove_dir_all(&dir).unwrap();
    }
}
