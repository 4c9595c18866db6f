//! The D455 camera model (issue 7 item 1; fact sheet `cameras_and_calibration.md`, "D455").
//!
//! Conventions are librealsense's (`rs2_project_point_to_pixel`,
//! `rs2_deproject_pixel_to_point`): the optical frame is x right, y down, z forward; pixel
//! (0, 0) is the *centre* of the top-left pixel (no +0.5 shift, unlike Open3D's ray casting
//! or AprilTag corners); depth is the z coordinate, not the ray length; depth images hold u16
//! millimetres with a scale of 0.001 m per unit.
//!
//! Depth and left-IR images are rectified (zero distortion). The colour sensor has lens
//! distortion: librealsense reports "inverse Brown-Conrady" for the D455's colour stream,
//! meaning that the polynomial maps *distorted* normalised coordinates to undistorted ones
//! (deprojection applies it directly, projection inverts it). The label is disputed, so
//! both directions are offered ([`Distortion::BrownConrady`] applies the polynomial when
//! projecting). The inverse direction is solved by Newton's method to 1e-14, so projection
//! and deprojection round-trip far below a micro-pixel.

use nalgebra::{Matrix2, Point2, Point3, Vector2, Vector3};
use serde::{Deserialize, Serialize};

use crate::error::CalibrationError;

/// The D455 stereo baseline (m).
pub const D455_BASELINE_M: f64 = 0.095;
/// The D455 depth unit (m per raw count).
pub const D455_DEPTH_SCALE: f64 = 0.001;

/// The D455 depth stream modes.
#[derive(Copy, Clone, Debug, PartialEq, Eq, Hash, Serialize, Deserialize, Default)]
#[serde(rename_all = "snake_case")]
pub enum DepthMode {
    /// 640x480 (VGA, 75°x62° field of view).
    Vga640x480,
    /// 848x480, the recommended mode (up to 90 fps).
    #[default]
    Wvga848x480,
    /// 1280x720 (30 fps).
    Hd1280x720,
}

/// Lens distortion with the five coefficients `[k1, k2, p1, p2, k3]` of librealsense.
#[derive(Copy, Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case", tag = "model", content = "coeffs")]
pub enum Distortion {
    /// No distortion (rectified depth and IR streams).
    None,
    /// The polynomial maps distorted to undistorted coordinates (applied on deprojection).
    InverseBrownConrady([f64; 5]),
    /// The polynomial maps undistorted to distorted coordinates (applied on projection).
    BrownConrady([f64; 5]),
}

/// Pinhole intrinsics of one stream, with its distortion.
#[derive(Copy, Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Intrinsics {
    /// Image width (px).
    pub width: u32,
    /// Image height (px).
    pub height: u32,
    /// Focal length along x (px).
    pub fx: f64,
    /// Focal length along y (px).
    pub fy: f64,
    /// Principal point x (px, pixel-centre convention).
    pub ppx: f64,
    /// Principal point y (px, pixel-centre convention).
    pub ppy: f64,
    /// Lens distortion.
    pub distortion: Distortion,
}

/// The D455 colour stream's sample distortion coefficients (fact sheet).
pub const D455_COLOUR_COEFFS: [f64; 5] = [-0.0565, 0.0688, -0.0007, -0.00003, -0.0224];

impl Intrinsics {
    /// Factory-like depth (and left IR) intrinsics of a D455 in `mode` (sample unit of the
    /// fact sheet; 848x480 is the 1280x720 calibration scaled by 848/1280).
    pub fn d455_depth(mode: DepthMode) -> Self {
        let (width, height, f, ppx, ppy) = match mode {
            DepthMode::Vga640x480 => (640, 480, 384.9, 320.2, 242.3),
            DepthMode::Hd1280x720 => (1280, 720, 641.5, 640.4, 363.8),
            DepthMode::Wvga848x480 => {
                // librealsense scales about pixel edges: (p + 0.5) * s - 0.5.
                let s = 848.0 / 1280.0;
                (
                    848,
                    480,
                    641.5 * s,
                    (640.4 + 0.5) * s - 0.5,
                    (363.8 + 0.5) * s - 0.5,
                )
            }
        };
        Self {
            width,
            height,
            fx: f,
            fy: f,
            ppx,
            ppy,
            distortion: Distortion::None,
        }
    }

    /// Sample D455 colour intrinsics at 640x480 with inverse Brown-Conrady distortion.
    pub fn d455_colour_640x480() -> Self {
        Self {
            width: 640,
            height: 480,
            fx: 379.5,
            fy: 379.2,
            ppx: 319.9,
            ppy: 242.0,
            distortion: Distortion::InverseBrownConrady(D455_COLOUR_COEFFS),
        }
    }

    /// Checks that the parameters describe a usable camera.
    pub fn validate(&self) -> Result<(), CalibrationError> {
        let bad = |what, value: f64| Err(CalibrationError::InvalidIntrinsics { what, value });
        if self.width == 0 {
            return bad("width", 0.0);
        }
        if self.height == 0 {
            return bad("height", 0.0);
        }
        for (what, v) in [("fx", self.fx), ("fy", self.fy)] {
            if !(v.is_finite() && v > 0.0) {
                return bad(what, v);
            }
        }
        for (what, v) in [("ppx", self.ppx), ("ppy", self.ppy)] {
            if !v.is_finite() {
                return bad(what, v);
            }
        }
        let coeffs = match self.distortion {
            Distortion::None => [0.0; 5],
            Distortion::InverseBrownConrady(c) | Distortion::BrownConrady(c) => c,
        };
        if let Some(c) = coeffs.iter().find(|c| !c.is_finite()) {
            return bad("distortion coefficient", *c);
        }
        Ok(())
    }

    /// The normalised, undistorted ray `(x, y, 1)` through pixel `(u, v)` (pixel-centre
    /// convention): a point on it at depth `z` is `z * ray`.
    pub fn pixel_ray(&self, pixel: Point2<f64>) -> Result<Vector3<f64>, CalibrationError> {
        let xd = (pixel.x - self.ppx) / self.fx;
        let yd = (pixel.y - self.ppy) / self.fy;
        let (x, y) = match self.distortion {
            Distortion::None => (xd, yd),
            Distortion::InverseBrownConrady(c) => {
                let p = brown_conrady(&c, Vector2::new(xd, yd));
                (p.x, p.y)
            }
            Distortion::BrownConrady(c) => {
                let p = invert_brown_conrady(&c, Vector2::new(xd, yd))?;
                (p.x, p.y)
            }
        };
        Ok(Vector3::new(x, y, 1.0))
    }

    /// Deprojects pixel `(u, v)` with depth `depth` (m, the z coordinate) to a 3-D point in
    /// the camera's optical frame (`rs2_deproject_pixel_to_point`).
    pub fn deproject(
        &self,
        pixel: Point2<f64>,
        depth: f64,
    ) -> Result<Point3<f64>, CalibrationError> {
        if !(depth.is_finite() && depth > 0.0) {
            return Err(CalibrationError::InvalidDepth { depth });
        }
        Ok(Point3::from(self.pixel_ray(pixel)? * depth))
    }

    /// Projects a point of the optical frame to its pixel (`rs2_project_point_to_pixel`).
    /// The pixel may lie outside the image; check with [`Intrinsics::contains`].
    pub fn project(&self, p: &Point3<f64>) -> Result<Point2<f64>, CalibrationError> {
        if !(p.z.is_finite() && p.z > 0.0 && p.x.is_finite() && p.y.is_finite()) {
            return Err(CalibrationError::BehindCamera { z: p.z });
        }
        let n = Vector2::new(p.x / p.z, p.y / p.z);
        let d = match self.distortion {
            Distortion::None => n,
            Distortion::BrownConrady(c) => brown_conrady(&c, n),
            Distortion::InverseBrownConrady(c) => invert_brown_conrady(&c, n)?,
        };
        Ok(Point2::new(
            d.x * self.fx + self.ppx,
            d.y * self.fy + self.ppy,
        ))
    }

    /// True when `pixel` falls on the image (within half a pixel of the outer pixel centres).
    pub fn contains(&self, pixel: Point2<f64>) -> bool {
        pixel.x >= -0.5
            && pixel.y >= -0.5
            && pixel.x < f64::from(self.width) - 0.5
            && pixel.y < f64::from(self.height) - 0.5
    }

    /// Horizontal and vertical field of view (rad) of an undistorted stream.
    pub fn field_of_view(&self) -> (f64, f64) {
        let w = f64::from(self.width);
        let h = f64::from(self.height);
        let hfov = ((self.ppx + 0.5) / self.fx).atan() + ((w - 0.5 - self.ppx) / self.fx).atan();
        let vfov = ((self.ppy + 0.5) / self.fy).atan() + ((h - 0.5 - self.ppy) / self.fy).atan();
        (hfov, vfov)
    }
}

/// A camera's linear depth error, `measured = scale * true + offset`, as the calibration
/// estimates it on the board; the fusion undoes it when deprojecting. The identity (scale
/// 1, offset 0) is the default, so calibration files written before it existed still read.
#[derive(Copy, Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct DepthCorrection {
    /// Depth scale (1: none).
    pub scale: f64,
    /// Depth offset (m).
    pub offset_m: f64,
}

impl Default for DepthCorrection {
    fn default() -> Self {
        Self {
            scale: 1.0,
            offset_m: 0.0,
        }
    }
}

impl DepthCorrection {
    /// The depth a camera with this error reports for a true depth `z` (m).
    pub fn measured(&self, z: f64) -> f64 {
        self.scale * z + self.offset_m
    }

    /// The true depth (m) behind a measured depth `d` (m).
    pub fn true_depth(&self, d: f64) -> f64 {
        (d - self.offset_m) / self.scale
    }

    /// Checks that the correction is plausible: a scale within 10 % of 1 and an offset
    /// under 10 cm (larger ones mean a broken camera or a broken fit, not a bias).
    pub fn validate(&self) -> Result<(), CalibrationError> {
        if !(self.scale.is_finite() && (0.9..=1.1).contains(&self.scale)) {
            return Err(CalibrationError::InvalidParameter {
                what: "depth correction scale",
                value: self.scale,
                why: "must be within 0.9..1.1; re-run the calibration or delete the entry to use 1",
            });
        }
        if !(self.offset_m.is_finite() && self.offset_m.abs() <= 0.1) {
            return Err(CalibrationError::InvalidParameter {
                what: "depth correction offset_m",
                value: self.offset_m,
                why: "must be within +-0.1 m; re-run the calibration or delete the entry to use 0",
            });
        }
        Ok(())
    }
}

/// The Brown-Conrady polynomial of librealsense (coefficients `[k1, k2, p1, p2, k3]`).
fn brown_conrady(c: &[f64; 5], p: Vector2<f64>) -> Vector2<f64> {
    let (x, y) = (p.x, p.y);
    let r2 = x * x + y * y;
    let f = 1.0 + c[0] * r2 + c[1] * r2 * r2 + c[4] * r2 * r2 * r2;
    Vector2::new(
        x * f + 2.0 * c[2] * x * y + c[3] * (r2 + 2.0 * x * x),
        y * f + 2.0 * c[3] * x * y + c[2] * (r2 + 2.0 * y * y),
    )
}

/// The Jacobian of [`brown_conrady`].
fn brown_conrady_jacobian(c: &[f64; 5], p: Vector2<f64>) -> Matrix2<f64> {
    let (x, y) = (p.x, p.y);
    let r2 = x * x + y * y;
    let f = 1.0 + c[0] * r2 + c[1] * r2 * r2 + c[4] * r2 * r2 * r2;
    // d f / d r2
    let fp = c[0] + 2.0 * c[1] * r2 + 3.0 * c[4] * r2 * r2;
    let (p1, p2) = (c[2], c[3]);
    Matrix2::new(
        f + 2.0 * x * x * fp + 2.0 * p1 * y + 6.0 * p2 * x,
        2.0 * x * y * fp + 2.0 * p1 * x + 2.0 * p2 * y,
        2.0 * x * y * fp + 2.0 * p2 * y + 2.0 * p1 * x,
        f + 2.0 * y * y * fp + 2.0 * p2 * x + 6.0 * p1 * y,
    )
}

/// Solves `brown_conrady(c, p) = target` for `p` by Newton's method. librealsense itself
/// uses a fixed 10 fixed-point iterations, which leaves errors of ~1e-6 at the image corners;
/// Newton converges quadratically, which the 1e-9 round trip needs.
fn invert_brown_conrady(
    c: &[f64; 5],
    target: Vector2<f64>,
) -> Result<Vector2<f64>, CalibrationError> {
    const MAX_ITER: usize = 30;
    let mut p = target;
    for _ in 0..MAX_ITER {
        let r = brown_conrady(c, p) - target;
        if r.norm() < 1e-14 {
            return Ok(p);
        }
        let Some(inv) = brown_conrady_jacobian(c, p).try_inverse() else {
            break;
        };
        p -= inv * r;
        if !(p.x.is_finite() && p.y.is_finite()) {
            break;
        }
    }
    if (brown_conrady(c, p) - target).norm() < 1e-12 {
        return Ok(p);
    }
    Err(CalibrationError::DistortionNotInvertible {
        x: target.x,
        y: target.y,
        iterations: MAX_ITER,
    })
}

/// Converts a raw depth count to metres, or `None` for "no depth" (0) and non-finite scales.
pub fn raw_depth_to_m(raw: u16, depth_scale: f32) -> Option<f64> {
    let d = f64::from(raw) * f64::from(depth_scale);
    (raw != 0 && d.is_finite() && d > 0.0).then_some(d)
}

/// Converts metres to the D455's raw millimetre count (1 mm quantisation); out-of-range or
/// non-finite depths become 0, "no depth".
pub fn m_to_raw_depth(depth_m: f64) -> u16 {
    let mm = (depth_m / D455_DEPTH_SCALE).round();
    if mm.is_finite() && mm >= 1.0 && mm <= f64::from(u16::MAX) {
        mm as u16
    } else {
        0
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use rand::{Rng, SeedableRng};

    fn all_models() -> Vec<Intrinsics> {
        let mut bc = Intrinsics::d455_colour_640x480();
        bc.distortion = Distortion::BrownConrady(D455_COLOUR_COEFFS);
        vec![
            Intrinsics::d455_depth(DepthMode::Vga640x480),
            Intrinsics::d455_depth(DepthMode::Wvga848x480),
            Intrinsics::d455_depth(DepthMode::Hd1280x720),
            Intrinsics::d455_colour_640x480(),
            bc,
        ]
    }

    #[test]
    fn pixel_deproject_project_round_trips_to_1e9() {
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(7);
        for k in all_models() {
            k.validate().unwrap();
            for _ in 0..5000 {
                let u = rng.random_range(-0.5..f64::from(k.width) - 0.5);
                let v = rng.random_range(-0.5..f64::from(k.height) - 0.5);
                let z = rng.random_range(0.3..6.0);
                let p = k.deproject(Point2::new(u, v), z).unwrap();
                assert!((p.z - z).abs() < 1e-12, "depth is z, not range");
                let back = k.project(&p).unwrap();
                assert!(
                    (back.x - u).abs() < 1e-9 && (back.y - v).abs() < 1e-9,
                    "{k:?}: ({u}, {v}) -> {back:?}"
                );
            }
        }
    }

    #[test]
    fn point_project_deproject_round_trips_to_1e9() {
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(8);
        for k in all_models() {
            for _ in 0..2000 {
                let z: f64 = rng.random_range(0.3..4.0);
                let p = Point3::new(
                    rng.random_range(-0.6..0.6) * z,
                    rng.random_range(-0.45..0.45) * z,
                    z,
                );
                let px = k.project(&p).unwrap();
                let back = k.deproject(px, p.z).unwrap();
                assert!((back - p).norm() < 1e-9, "{k:?}: {p:?} -> {back:?}");
            }
        }
    }

    #[test]
    fn principal_point_is_on_the_axis_and_pixel_centres_are_integers() {
        let k = Intrinsics::d455_depth(DepthMode::Vga640x480);
        let p = k.deproject(Point2::new(k.ppx, k.ppy), 2.0).unwrap();
        assert!(p.x.abs() < 1e-15 && p.y.abs() < 1e-15 && (p.z - 2.0).abs() < 1e-15);
        // Pixel (0, 0) is the centre of the top-left pixel: x = (0 - ppx) / fx, no 0.5 shift.
        let corner = k.deproject(Point2::new(0.0, 0.0), 1.0).unwrap();
        assert!((corner.x - (-320.2 / 384.9)).abs() < 1e-15);
        assert!((corner.y - (-242.3 / 384.9)).abs() < 1e-15);
    }

    #[test]
    fn depth_modes_have_the_datasheet_fields_of_view() {
        let (h, v) = Intrinsics::d455_depth(DepthMode::Wvga848x480).field_of_view();
        // Datasheet: 87° x 58° (the sample unit's focal length gives ~90° x 59°).
        assert!(
            (h.to_degrees() - 87.0).abs() < 3.5,
            "hfov {}",
            h.to_degrees()
        );
        assert!(
            (v.to_degrees() - 58.0).abs() < 1.5,
            "vfov {}",
            v.to_degrees()
        );
        let k = Intrinsics::d455_depth(DepthMode::Wvga848x480);
        assert!((k.fx - 425.0).abs() < 0.1 && (k.ppx - 424.0).abs() < 0.5);
        assert!((k.ppy - 241.0).abs() < 0.5);
    }

    #[test]
    fn colour_distortion_moves_corner_pixels_and_not_the_centre() {
        let k = Intrinsics::d455_colour_640x480();
        let centre = k.pixel_ray(Point2::new(k.ppx, k.ppy)).unwrap();
        assert!(centre.x.abs() < 1e-15 && centre.y.abs() < 1e-15);
        let undist = (0.0 - k.ppx) / k.fx;
        let corner = k.pixel_ray(Point2::new(0.0, 0.0)).unwrap();
        // k1 < 0 in the inverse model: the undistorted ray is pulled inwards at the corner.
        assert!(corner.x > undist + 1e-3, "{} vs {}", corner.x, undist);
    }

    #[test]
    fn bad_inputs_are_typed_errors() {
        let k = Intrinsics::d455_depth(DepthMode::Wvga848x480);
        for d in [0.0, -1.0, f64::NAN, f64::INFINITY] {
            assert!(matches!(
                k.deproject(Point2::new(1.0, 1.0), d),
                Err(CalibrationError::InvalidDepth { .. })
            ));
        }
        assert!(matches!(
            k.project(&Point3::new(0.1, 0.1, 0.0)),
            Err(CalibrationError::BehindCamera { .. })
        ));
        assert!(matches!(
            k.project(&Point3::new(f64::NAN, 0.1, 1.0)),
            Err(CalibrationError::BehindCamera { .. })
        ));
        let mut bad = k;
        bad.fx = 0.0;
        assert!(matches!(
            bad.validate(),
            Err(CalibrationError::InvalidIntrinsics { what: "fx", .. })
        ));
    }

    #[test]
    fn depth_units_are_millimetres() {
        assert_eq!(m_to_raw_depth(1.2344), 1234);
        assert_eq!(m_to_raw_depth(1.2346), 1235);
        assert_eq!(m_to_raw_depth(f64::NAN), 0);
        assert_eq!(m_to_raw_depth(100.0), 0);
        assert_eq!(raw_depth_to_m(0, 0.001), None);
        assert!((raw_depth_to_m(1500, 0.001).unwrap() - 1.5).abs() < 1e-6);
    }
}
