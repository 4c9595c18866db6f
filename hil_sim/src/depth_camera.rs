//! Simulated D455 depth cameras (issue 7 item 2; fact sheet `cameras_and_calibration.md`,
//! "Depth noise model for the simulator").
//!
//! Each pixel centre (librealsense convention: pixel (0, 0) is the centre of the top-left
//! pixel) casts one ray through the scene's BVH (parry3d). The ray direction is
//! `(x, y, 1)` in the optical frame, so the hit parameter *is* the depth z. The noise model:
//! axial noise `sigma_z = z^2 s / (f B)`, 1 mm quantisation, flying pixels at depth jumps
//! over 3 cm (a random mix of fore- and background), holes at grazing incidence
//! (`cos < 0.2`) and 2 % random dropouts, a minimum-range cut, and the invalid band at the
//! left image edge `f B / z` pixels wide. Randomness comes from a ChaCha8 stream per image
//! row, seeded by (seed, camera, frame index), so a frame is the same whatever the thread
//! count.
//!
//! The IR image shares the depth intrinsics (the left imager; rectified); the colour image
//! is rendered already aligned to depth (what librealsense's `align_to(depth)` delivers),
//! which keeps the colour model's distortion out of the simulated fusion path.
//!
//! Libraries: parry3d (BVH ray casting, via [`crate::scene`]), rand_chacha (a seedable,
//! portable stream cipher RNG with independent streams per row), rand_distr (the normal
//! distribution). Rows are split over scoped std threads (no pool, no threads left behind):
//! see the `fusion` benchmark for single- vs multi-thread render times.

use std::sync::{Arc, RwLock};
use std::time::Duration;

use calibration::camera::{m_to_raw_depth, Intrinsics, D455_BASELINE_M, D455_DEPTH_SCALE};
use calibration::DepthMode;
use cell_types::{Base, Camera, CameraFrame, Clock, DepthImage, Image, Rgb, Transform};
use firmware_iface::camera::{CameraError, DepthCamera};
use nalgebra::{Matrix3, Point3, Rotation3, UnitQuaternion, Vector3};
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use rand_distr::StandardNormal;

use crate::scene::{SceneError, SceneGeometry};

/// The D455 noise model's parameters.
#[derive(Copy, Clone, Debug, PartialEq)]
pub struct NoiseModel {
    /// Stereo subpixel matching error `s` (px); 0 disables axial noise.
    pub subpixel: f64,
    /// Stereo baseline `B` (m).
    pub baseline_m: f64,
    /// Depth quantum (m): the raw unit.
    pub quantum_m: f64,
    /// Depth jump (m) above which edge pixels may fly; `f64::INFINITY` disables.
    pub flying_jump_m: f64,
    /// Probability that a pixel at such a jump flies.
    pub flying_probability: f64,
    /// Incidence cosine below which a pixel is a hole.
    pub grazing_cos: f64,
    /// Probability of a random dropout.
    pub dropout: f64,
    /// Minimum range (m); `None` scales the D455's 0.52 m at f = 641.5 px by the focal
    /// length (the minimum disparity is fixed in pixels).
    pub min_range_m: Option<f64>,
    /// Maximum range (m).
    pub max_range_m: f64,
    /// Whether the invalid band at the left edge is cut.
    pub left_band: bool,
}

impl NoiseModel {
    /// The fact sheet's D455 model.
    pub fn d455() -> Self {
        Self {
            subpixel: 0.08,
            baseline_m: D455_BASELINE_M,
            quantum_m: D455_DEPTH_SCALE,
            flying_jump_m: 0.03,
            flying_probability: 0.5,
            grazing_cos: 0.2,
            dropout: 0.02,
            min_range_m: None,
            max_range_m: 6.0,
            left_band: true,
        }
    }

    /// No noise, no holes, no band: only the 1 mm quantisation and the range limits.
    pub fn ideal() -> Self {
        Self {
            subpixel: 0.0,
            flying_jump_m: f64::INFINITY,
            flying_probability: 0.0,
            grazing_cos: 0.0,
            dropout: 0.0,
            left_band: false,
            ..Self::d455()
        }
    }

    /// Axial noise sigma (m) at depth `z` (m) for focal length `f` (px).
    pub fn sigma_z(&self, z: f64, f: f64) -> f64 {
        z * z * self.subpixel / (f * self.baseline_m)
    }

    /// The minimum range (m) for focal length `f` (px).
    pub fn min_range(&self, f: f64) -> f64 {
        self.min_range_m.unwrap_or(0.52 * f / 641.5)
    }
}

/// A simulated D455: intrinsics, pose in the base frame, noise, and which streams it renders.
#[derive(Clone, Debug, PartialEq)]
pub struct SimDepthCamera {
    /// Camera id (`FrameId::Camera` index).
    pub id: u8,
    /// A name ("front", "left_shoulder", "right_shoulder").
    pub name: String,
    /// Depth (and IR) intrinsics; must be undistorted.
    pub intrinsics: Intrinsics,
    /// The true pose of the optical frame in the base frame.
    pub base_from_camera: Transform<Base, Camera>,
    /// The noise model.
    pub noise: NoiseModel,
    /// Seed of the noise.
    pub seed: u64,
    /// Whether to render the IR image.
    pub ir: bool,
    /// Whether to render the colour image (aligned to depth).
    pub colour: bool,
    /// Rendering threads (rows are split between them); 1 renders on the caller's thread.
    pub threads: usize,
}

/// The optical frame at `eye` looking at `target` with the image's "up" along +z of the
/// base (x right, y down, z forward).
pub fn look_at(eye: Point3<f64>, target: Point3<f64>) -> Transform<Base, Camera> {
    let z = (target - eye).normalize();
    let x = z.cross(&Vector3::z()).normalize();
    let y = z.cross(&x);
    let r = Rotation3::from_matrix_unchecked(Matrix3::from_columns(&[x, y, z]));
    Transform::from_parts(eye.coords, UnitQuaternion::from_rotation_matrix(&r))
}

/// The camera ids of the default rig, as EquAct names them.
pub const CAMERA_NAMES: [&str; 3] = ["front", "left_shoulder", "right_shoulder"];

/// The three cameras of the paper's cell around the workspace
/// [[0.18, -0.39, -0.10], [0.96, 0.39, 0.53]]: front (id 0, facing the robot, ~1.0 m from the
/// table centre), left and right shoulder (ids 1, 2, behind and above the robot's
/// shoulders, ~1.1 m), all 848x480 with the D455 noise.
pub fn default_rig(seed: u64) -> Vec<SimDepthCamera> {
    let poses = [
        look_at(Point3::new(1.35, 0.0, 0.55), Point3::new(0.55, 0.0, -0.02)),
        look_at(Point3::new(0.05, 0.6, 0.75), Point3::new(0.6, -0.05, -0.05)),
        look_at(Point3::new(0.05, -0.6, 0.75), Point3::new(0.6, 0.05, -0.05)),
    ];
    poses
        .into_iter()
        .zip(CAMERA_NAMES)
        .enumerate()
        .map(|(i, (pose, name))| SimDepthCamera {
            id: i as u8,
            name: name.to_string(),
            intrinsics: Intrinsics::d455_depth(DepthMode::Wvga848x480),
            base_from_camera: pose,
            noise: NoiseModel::d455(),
            seed,
            ir: true,
            colour: true,
            threads: std::thread::available_parallelism().map_or(1, |n| n.get().min(4)),
        })
        .collect()
}

/// The true calibration of a rig (what a perfect `equact calibrate` would write).
pub fn rig_calibration(rig: &[SimDepthCamera]) -> calibration::CellCalibration {
    calibration::CellCalibration {
        cameras: rig
            .iter()
            .map(|c| calibration::CameraCalibration {
                id: c.id,
                intrinsics: c.intrinsics,
                base_from_camera: c.base_from_camera,
                depth_correction: calibration::DepthCorrection::default(),
            })
            .collect(),
    }
}

/// Renders every camera of `rig` (frame `frame_index`, stamped `timestamp`).
pub fn render_rig(
    rig: &[SimDepthCamera],
    scene: &SceneGeometry,
    frame_index: u64,
    timestamp: Duration,
) -> Result<Vec<CameraFrame>, SceneError> {
    rig.iter()
        .map(|c| c.render(scene, frame_index, timestamp))
        .collect()
}

/// Per-pixel result of the ray-casting pass.
#[derive(Copy, Clone, Debug, Default)]
struct Sample {
    /// True depth (m); 0 for no hit.
    z: f32,
    /// |cos| of the incidence angle.
    cos: f32,
    /// Index of the solid hit.
    object: u32,
}

impl SimDepthCamera {
    /// Renders one frame of `scene`. `frame_index` selects the noise draw; `timestamp` is
    /// stamped on the frame.
    pub fn render(
        &self,
        scene: &SceneGeometry,
        frame_index: u64,
        timestamp: Duration,
    ) -> Result<CameraFrame, SceneError> {
        let k = &self.intrinsics;
        k.validate().map_err(|e| SceneError::BadCamera {
            camera: self.id,
            why: e.to_string(),
        })?;
        if !matches!(k.distortion, calibration::Distortion::None) {
            return Err(SceneError::BadCamera {
                camera: self.id,
                why: "depth intrinsics must be undistorted (rectified)".into(),
            });
        }
        if !self.base_from_camera.is_finite() {
            return Err(SceneError::BadCamera {
                camera: self.id,
                why: "base_from_camera is not a finite rigid transform".into(),
            });
        }
        let (w, h) = (k.width as usize, k.height as usize);
        let threads = self.threads.clamp(1, 64);
        let rows_per = h.div_ceil(threads);

        // Pass 1: ray cast.
        let mut samples = vec![Sample::default(); w * h];
        let cast_rows = |first_row: usize, out: &mut [Sample]| {
            let iso = self.base_from_camera.isometry();
            let origin = Point3::from(iso.translation.vector);
            for (r, row) in out.chunks_mut(w).enumerate() {
                let v = (first_row + r) as f64;
                let y = (v - k.ppy) / k.fy;
                for (u, s) in row.iter_mut().enumerate() {
                    let x = (u as f64 - k.ppx) / k.fx;
                    let dir = iso.rotation * Vector3::new(x, y, 1.0);
                    if let Some(hit) = scene.cast(&origin, &dir, self.noise.max_range_m) {
                        let cos = hit.normal.dot(&dir).abs() / dir.norm();
                        *s = Sample {
                            z: hit.t as f32,
                            cos: cos as f32,
                            object: hit.object as u32,
                        };
                    }
                }
            }
        };
        std::thread::scope(|sc| {
            let mut chunks = samples.chunks_mut(rows_per * w).enumerate();
            // The first chunk runs here; the rest on scoped threads.
            let first = chunks.next();
            for (i, chunk) in chunks {
                let cast_rows = &cast_rows;
                sc.spawn(move || cast_rows(i * rows_per, chunk));
            }
            if let Some((_, chunk)) = first {
                cast_rows(0, chunk);
            }
        });

        // Pass 2: the sensor's noise, per row with its own random stream.
        let mut depth = vec![0u16; w * h];
        let mut ir = if self.ir {
            vec![0u8; w * h]
        } else {
            Vec::new()
        };
        let mut colour: Vec<Rgb> = if self.colour {
            vec![[0, 0, 0]; w * h]
        } else {
            Vec::new()
        };
        let stream_seed = self.seed
            ^ u64::from(self.id).wrapping_mul(0x9E37_79B9_7F4A_7C15)
            ^ frame_index.wrapping_mul(0xC2B2_AE3D_27D4_EB4F);
        let samples = &samples;
        let noise_rows = |first_row: usize, d: &mut [u16], ir: &mut [u8], col: &mut [Rgb]| {
            for r in 0..d.len() / w {
                let v = first_row + r;
                let mut rng = ChaCha8Rng::seed_from_u64(stream_seed);
                rng.set_stream(v as u64);
                for u in 0..w {
                    let i = r * w + u;
                    let s = samples[v * w + u];
                    let (z, valid) = self.noisy_depth(samples, u, v, &mut rng);
                    if valid {
                        d[i] = m_to_raw_depth(z);
                    }
                    if s.z <= 0.0 {
                        continue;
                    }
                    let Some((mat, _)) = scene.material(s.object as usize) else {
                        continue;
                    };
                    if !ir.is_empty() {
                        let zt = f64::from(s.z);
                        let shade = mat.ir_albedo * (0.35 + 0.65 * f64::from(s.cos));
                        let level = 255.0 * shade * (0.9 / zt).powi(2)
                            + 2.0 * rng.sample::<f64, _>(StandardNormal);
                        ir[i] = level.clamp(0.0, 255.0) as u8;
                    }
                    if !col.is_empty() && d[i] != 0 {
                        let shade = 0.3 + 0.7 * f64::from(s.cos);
                        col[i] = mat.colour.map(|c| (f64::from(c) * shade).round() as u8);
                    }
                }
            }
        };
        std::thread::scope(|sc| {
            let mut parts = Vec::new();
            let mut d_rest = depth.as_mut_slice();
            let mut ir_rest = ir.as_mut_slice();
            let mut c_rest = colour.as_mut_slice();
            let mut row = 0;
            while row < h {
                let n = rows_per.min(h - row) * w;
                let (d, dr) = d_rest.split_at_mut(n);
                d_rest = dr;
                let (i, ir_r) = ir_rest.split_at_mut(if self.ir { n } else { 0 });
                ir_rest = ir_r;
                let (c, cr) = c_rest.split_at_mut(if self.colour { n } else { 0 });
                c_rest = cr;
                parts.push((row, d, i, c));
                row += rows_per;
            }
            let mut it = parts.into_iter();
            let first = it.next();
            for (row, d, i, c) in it {
                let noise_rows = &noise_rows;
                sc.spawn(move || noise_rows(row, d, i, c));
            }
            if let Some((row, d, i, c)) = first {
                noise_rows(row, d, i, c);
            }
        });

        let (wu, hu) = (k.width, k.height);
        let image_err = |e: cell_types::CellTypesError| SceneError::BadCamera {
            camera: self.id,
            why: e.to_string(),
        };
        Ok(CameraFrame {
            camera: self.id,
            timestamp,
            depth: DepthImage {
                raw: Image::new(wu, hu, depth).map_err(image_err)?,
                depth_scale: D455_DEPTH_SCALE as f32,
            },
            ir: if self.ir {
                Some(Image::new(wu, hu, ir).map_err(image_err)?)
            } else {
                None
            },
            colour: if self.colour {
                Some(Image::new(wu, hu, colour).map_err(image_err)?)
            } else {
                None
            },
        })
    }

    /// The depth the sensor reports at pixel (u, v), and whether it reports one.
    fn noisy_depth(
        &self,
        samples: &[Sample],
        u: usize,
        v: usize,
        rng: &mut ChaCha8Rng,
    ) -> (f64, bool) {
        let k = &self.intrinsics;
        let n = &self.noise;
        let (w, h) = (k.width as usize, k.height as usize);
        let s = samples[v * w + u];
        // Draw every random number up front so that a pixel's fate does not shift the
        // stream of its neighbours.
        let p_fly: f64 = rng.random();
        let alpha: f64 = rng.random();
        let p_drop: f64 = rng.random();
        let gauss: f64 = rng.sample(StandardNormal);
        if s.z <= 0.0 {
            return (0.0, false);
        }
        let mut z = f64::from(s.z);
        if z < n.min_range(k.fx) || z > n.max_range_m || f64::from(s.cos) < n.grazing_cos {
            return (0.0, false);
        }
        if n.left_band && (u as f64) < k.fx * n.baseline_m / z {
            return (0.0, false);
        }
        if p_drop < n.dropout {
            return (0.0, false);
        }
        // Flying pixel: the stereo window straddles a depth edge and lands in between.
        let mut jump = 0.0f64;
        let mut other = z;
        let neighbours = [
            (u.wrapping_sub(1), v),
            (u + 1, v),
            (u, v.wrapping_sub(1)),
            (u, v + 1),
        ];
        for (nu, nv) in neighbours {
            if nu < w && nv < h {
                let zn = f64::from(samples[nv * w + nu].z);
                if zn > 0.0 && (zn - z).abs() > jump {
                    jump = (zn - z).abs();
                    other = zn;
                }
            }
        }
        if jump > n.flying_jump_m && p_fly < n.flying_probability {
            z += alpha * (other - z);
        }
        z += n.sigma_z(z, k.fx) * gauss;
        (z, true)
    }
}

/// A scene shared between the simulated cameras and whoever moves things in it.
pub type SharedScene = Arc<RwLock<SceneGeometry>>;

/// A simulated camera bound to a shared scene and a clock: the [`DepthCamera`] the rest of
/// the stack sees.
pub struct SimCameraDevice {
    camera: SimDepthCamera,
    scene: SharedScene,
    clock: Arc<dyn Clock>,
    frame_index: u64,
}

impl SimCameraDevice {
    /// Binds `camera` to `scene`, stamping frames with `clock`.
    pub fn new(camera: SimDepthCamera, scene: SharedScene, clock: Arc<dyn Clock>) -> Self {
        Self {
            camera,
            scene,
            clock,
            frame_index: 0,
        }
    }
}

impl DepthCamera for SimCameraDevice {
    fn id(&self) -> u8 {
        self.camera.id
    }

    fn capture(&mut self) -> Result<CameraFrame, CameraError> {
        let scene = self.scene.read().map_err(|_| CameraError::Device {
            camera: self.camera.id,
            message: "the simulated scene's lock is poisoned (a writer panicked)".into(),
        })?;
        let frame = self
            .camera
            .render(&scene, self.frame_index, self.clock.now())
            .map_err(|e| CameraError::Device {
                camera: self.camera.id,
                message: e.to_string(),
            })?;
        self.frame_index += 1;
        Ok(frame)
    }
}
