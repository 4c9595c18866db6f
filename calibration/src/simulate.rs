//! Synthetic captures with known truth (issue 8 item 5): `equact calibrate simulate`.
//!
//! Board poses are drawn at random (seeded, ChaCha8): the board centre uniformly in a box
//! in front of the cameras, its face normal tilted up to `max_tilt_deg` from the mean
//! direction towards the cameras, a uniform turn about the normal. A pose is kept when
//! every camera sees every corner inside its image (with a margin) at an obliquity below
//! `max_obliquity_deg`, when it is not a near-duplicate of a kept pose, and when the
//! optional pose check (the CLI passes the planner's IK and collision check here) accepts
//! the flange pose. Corners are projected through the camera model (librealsense pixel
//! convention) and get Gaussian noise; the recorded flange pose gets Gaussian robot noise
//! (per axis, in the flange frame); depth samples on the board follow the D455 axial noise
//! model `sigma_z = z^2 s / (f B)` with 1 mm quantisation.
//!
//! The calibration crate may not depend on `hil_sim` (which depends on it), so the camera
//! rig is an input: [`SimConfig::default_cell`] repeats `hil_sim::depth_camera::default_rig`'s
//! three camera poses (the tests crate checks that they agree).

use std::path::Path;

use cell_types::{Base, Board, Camera, Flange, Joints, Transform};
use nalgebra::{
    DMatrix, Isometry3, Matrix3, Matrix3x6, Matrix6, Point3, Rotation3, UnitQuaternion, Vector3,
};
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use rand_distr::{Distribution, Normal, StandardNormal};
use serde::{Deserialize, Serialize};

use crate::board::BoardConfig;
use crate::camera::{DepthCorrection, DepthMode, Intrinsics, D455_BASELINE_M, D455_DEPTH_SCALE};
use crate::capture::{
    write_atomic, write_captures, CameraInfo, CameraView, Capture, CaptureSet, Corner, DepthSample,
    Session,
};
use crate::detect::{detect_board, render_board_ir, DetectParams, IrLevels};
use crate::error::CalibrationError;
use crate::geometry::{exp6, point_jacobian, project_with_jacobian, skew};

/// A simulated camera: its intrinsics and true pose.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct SimCamera {
    /// Camera id.
    pub id: u8,
    /// Name.
    pub name: String,
    /// Intrinsics (of the stream the board is detected in).
    pub intrinsics: Intrinsics,
    /// The true pose.
    pub base_from_camera: Transform<Base, Camera>,
}

/// Noise injected into synthetic captures (standard deviations, per axis).
#[derive(Copy, Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct SimNoise {
    /// Corner pixel noise (px, per coordinate).
    pub corner_px: f64,
    /// Robot flange position noise (m, per axis).
    pub robot_m: f64,
    /// Robot flange rotation noise (rad, per axis).
    pub robot_rad: f64,
    /// D455 stereo subpixel error `s` for the board depth samples (0: no depth noise;
    /// the quantum below still applies).
    pub depth_subpixel: f64,
    /// Depth quantum (m; the D455 reports millimetres; 0: exact depth).
    #[serde(default = "d455_depth_quantum")]
    pub depth_quantum_m: f64,
}

fn d455_depth_quantum() -> f64 {
    D455_DEPTH_SCALE
}

impl SimNoise {
    /// No noise at all (exact, unquantised depth).
    pub fn none() -> Self {
        Self {
            corner_px: 0.0,
            robot_m: 0.0,
            robot_rad: 0.0,
            depth_subpixel: 0.0,
            depth_quantum_m: 0.0,
        }
    }

    /// The realistic noise: 0.5 px corners, robot 0.5 mm / 0.05 deg, D455 depth.
    pub fn realistic() -> Self {
        Self {
            corner_px: 0.5,
            robot_m: 0.5e-3,
            robot_rad: 0.05_f64.to_radians(),
            depth_subpixel: 0.08,
            depth_quantum_m: D455_DEPTH_SCALE,
        }
    }
}

/// How far the simulated cameras differ from what the captures record: the true
/// intrinsics differ from the recorded (factory) ones the solver starts from, and the
/// depth has a linear error. The default is none.
#[derive(Copy, Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct CameraErrors {
    /// Relative error of the true `fx` and `fy` (each `+-` this, the sign drawn per camera
    /// and axis from the seed).
    pub focal_rel: f64,
    /// Error of the true `ppx` and `ppy` (px, each `+-` this, signs drawn likewise).
    pub principal_px: f64,
    /// The depth every camera measures: `scale * true + offset`.
    pub depth: DepthCorrection,
}

impl Default for CameraErrors {
    fn default() -> Self {
        Self {
            focal_rel: 0.0,
            principal_px: 0.0,
            depth: DepthCorrection::default(),
        }
    }
}

impl CameraErrors {
    /// The example: `fx`, `fy` 1 % off, `ppx`, `ppy` 3 px off, depth scale 1.002
    /// and offset 2 mm.
    pub fn typical() -> Self {
        Self {
            focal_rel: 0.01,
            principal_px: 3.0,
            depth: DepthCorrection {
                scale: 1.002,
                offset_m: 0.002,
            },
        }
    }

    /// The true intrinsics behind `factory`, drawn for the camera at `index` (seeded
    /// apart from the poses and noise, so adding camera errors keeps the same poses).
    pub fn true_intrinsics(&self, factory: &Intrinsics, seed: u64, index: usize) -> Intrinsics {
        let mut rng = ChaCha8Rng::seed_from_u64(seed ^ 0x1a7e_c0de_0000_0000 ^ index as u64);
        let mut sign = || if rng.random::<bool>() { 1.0 } else { -1.0 };
        let mut k = *factory;
        k.fx *= 1.0 + sign() * self.focal_rel;
        k.fy *= 1.0 + sign() * self.focal_rel;
        k.ppx += sign() * self.principal_px;
        k.ppy += sign() * self.principal_px;
        k
    }
}

/// How the robot poses are chosen from the feasible candidates.
#[derive(Copy, Clone, Debug, PartialEq, Eq, Serialize, Deserialize, Default)]
#[serde(rename_all = "snake_case")]
pub enum PoseSelection {
    /// Greedy farthest-point in pose space (10 cm or 20 deg count as 1): spread out, but
    /// blind to what each pose tells about the cameras.
    #[default]
    FarthestPoint,
    /// Greedy optimal design: each next pose is the candidate that most reduces the worst
    /// camera's predicted error (rotation variance over (0.05 deg)^2 plus position variance
    /// over (1 mm)^2, from the bundle adjustment's information at the nominal camera poses
    /// with the robot noise and corner noise of the configuration).
    Information,
}

/// What to simulate.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct SimConfig {
    /// The board.
    pub board: BoardConfig,
    /// The cameras and their true poses.
    pub cameras: Vec<SimCamera>,
    /// The board's true pose on the flange.
    pub flange_from_board: Transform<Flange, Board>,
    /// Number of robot poses.
    pub poses: usize,
    /// Noise.
    pub noise: SimNoise,
    /// Lower corner of the box the board centre is drawn in (base frame, m).
    pub region_min: [f64; 3],
    /// Upper corner of that box.
    pub region_max: [f64; 3],
    /// Largest tilt of the board normal from the mean direction to the cameras (deg).
    pub max_tilt_deg: f64,
    /// Largest angle between the board normal and a camera's line of sight (deg).
    pub max_obliquity_deg: f64,
    /// Corners must project at least this far inside the image (px).
    pub margin_px: f64,
    /// Whether to record depth samples on the board.
    pub depth_samples: bool,
    /// Fewest cameras that must see the whole board in a pose (clamped to 1..=cameras).
    pub min_cameras_per_pose: usize,
    /// Feasible candidates drawn per pose kept; the kept poses are the most spread out of
    /// them (greedy farthest-point). 1 keeps the random draw as it is.
    pub candidates_per_pose: usize,
    /// `Some(sigma)`: render each view's IR image (grey-level noise `sigma`) and detect the
    /// corners in it ([`crate::detect`]) instead of projecting them with `noise.corner_px`.
    #[serde(default)]
    pub ir_noise: Option<f64>,
    /// True intrinsics and depth unlike the recorded ones (none by default).
    #[serde(default)]
    pub camera_errors: CameraErrors,
    /// How the kept poses are chosen from the candidates (configurations written before
    /// this existed used farthest-point).
    #[serde(default)]
    pub selection: PoseSelection,
}

/// The optical frame at `eye` looking at `target`, image "up" along +z of the base (the
/// same construction as `hil_sim::depth_camera::look_at`).
pub fn look_at(eye: Point3<f64>, target: Point3<f64>) -> Transform<Base, Camera> {
    let z = (target - eye).normalize();
    let x = z.cross(&Vector3::z()).normalize();
    let y = z.cross(&x);
    let r = Rotation3::from_matrix_unchecked(Matrix3::from_columns(&[x, y, z]));
    Transform::from_parts(eye.coords, UnitQuaternion::from_rotation_matrix(&r))
}

/// Where the simulated cell's board sits on the flange: face along the flange's z, centred on
/// the flange axis 60 mm out, turned a little so that no axis is special.
fn flange_mount(board: &BoardConfig) -> Transform<Flange, Board> {
    let rot = UnitQuaternion::from_euler_angles(0.03, -0.02, 0.5);
    let t = Vector3::new(0.004, -0.003, 0.06) - rot * board.centre().coords;
    Transform::from_parts(t, rot)
}

impl SimConfig {
    /// The simulated cell: `hil_sim`'s three 848x480 D455s (front, left and right
    /// shoulder), a 7x10-corner chessboard of 35 mm squares 60 mm in front of the flange, 30
    /// poses, realistic noise.
    pub fn default_cell() -> Self {
        let eyes = [
            (Point3::new(1.35, 0.0, 0.55), Point3::new(0.55, 0.0, -0.02)),
            (Point3::new(0.05, 0.6, 0.75), Point3::new(0.6, -0.05, -0.05)),
            (Point3::new(0.05, -0.6, 0.75), Point3::new(0.6, 0.05, -0.05)),
        ];
        let names = ["front", "left_shoulder", "right_shoulder"];
        let cameras = eyes
            .iter()
            .zip(names)
            .enumerate()
            .map(|(i, ((eye, target), name))| SimCamera {
                id: i as u8,
                name: name.to_string(),
                intrinsics: Intrinsics::d455_depth(DepthMode::Wvga848x480),
                base_from_camera: look_at(*eye, *target),
            })
            .collect();
        let board = BoardConfig::default();
        Self {
            board,
            cameras,
            flange_from_board: flange_mount(&board),
            poses: 30,
            noise: SimNoise::realistic(),
            region_min: [0.2, -0.4, 0.1],
            region_max: [0.8, 0.4, 0.7],
            max_tilt_deg: 45.0,
            max_obliquity_deg: 75.0,
            margin_px: 8.0,
            depth_samples: true,
            min_cameras_per_pose: 3,
            candidates_per_pose: 3,
            ir_noise: None,
            camera_errors: CameraErrors::default(),
            selection: PoseSelection::Information,
        }
    }

    /// The same cell with another board, mounted like the default one (centred on the
    /// flange axis).
    pub fn with_board(self, board: BoardConfig) -> Self {
        Self {
            board,
            flange_from_board: flange_mount(&board),
            ..self
        }
    }

    /// The session a simulated capture writes.
    pub fn session(&self) -> Session {
        Session::new(
            self.board,
            self.cameras
                .iter()
                .map(|c| CameraInfo {
                    id: c.id,
                    name: c.name.clone(),
                    intrinsics: c.intrinsics,
                })
                .collect(),
        )
    }
}

/// The ground truth of a simulated capture set (`truth.json`).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Truth {
    /// The seed.
    pub seed: u64,
    /// The configuration simulated.
    pub config: SimConfig,
    /// The true flange pose of every capture (the captures hold the noisy ones).
    pub base_from_flange: Vec<Transform<Base, Flange>>,
    /// The true intrinsics of every camera, in the configuration's order (empty: the
    /// recorded ones are true).
    #[serde(default)]
    pub intrinsics: Vec<Intrinsics>,
}

impl Truth {
    /// The true pose of camera `id`.
    pub fn base_from_camera(&self, id: u8) -> Option<Transform<Base, Camera>> {
        self.config
            .cameras
            .iter()
            .find(|c| c.id == id)
            .map(|c| c.base_from_camera)
    }

    /// The true intrinsics of camera `id`.
    pub fn intrinsics(&self, id: u8) -> Option<Intrinsics> {
        let i = self.config.cameras.iter().position(|c| c.id == id)?;
        Some(
            self.intrinsics
                .get(i)
                .copied()
                .unwrap_or(self.config.cameras[i].intrinsics),
        )
    }

    /// The true depth error of every camera.
    pub fn depth(&self) -> DepthCorrection {
        self.config.camera_errors.depth
    }
}

/// The verdict of a caller's pose check (reachability, collisions).
#[derive(Copy, Clone, Debug, PartialEq)]
pub enum PoseCheck {
    /// The pose cannot be used.
    Reject,
    /// The pose is fine; the joint state reaching it, when known.
    Accept(Option<Joints>),
}

/// Simulates captures of `cfg` with `seed` in memory; every flange pose is accepted.
pub fn simulate_set(cfg: &SimConfig, seed: u64) -> Result<(CaptureSet, Truth), CalibrationError> {
    simulate_set_with(cfg, seed, &mut |_| PoseCheck::Accept(None))
}

/// Simulates captures like [`simulate_set`], asking `check` about every candidate flange
/// pose (the CLI passes the planner's IK and collision check; accepted joints are recorded).
pub fn simulate_set_with(
    cfg: &SimConfig,
    seed: u64,
    check: &mut dyn FnMut(&Transform<Base, Flange>) -> PoseCheck,
) -> Result<(CaptureSet, Truth), CalibrationError> {
    cfg.board.validate()?;
    let bad = |what: &'static str, value: f64, why: &'static str| {
        Err(CalibrationError::InvalidParameter { what, value, why })
    };
    for (what, v) in [
        ("noise.corner_px", cfg.noise.corner_px),
        ("noise.robot_m", cfg.noise.robot_m),
        ("noise.robot_rad", cfg.noise.robot_rad),
        ("noise.depth_subpixel", cfg.noise.depth_subpixel),
        ("noise.depth_quantum_m", cfg.noise.depth_quantum_m),
    ] {
        if !(v.is_finite() && v >= 0.0) {
            return bad(what, v, "a standard deviation must be finite and >= 0");
        }
    }
    if cfg.cameras.is_empty() {
        return bad("cameras", 0.0, "simulate at least one camera");
    }
    for c in &cfg.cameras {
        c.intrinsics.validate()?;
    }
    let errs = &cfg.camera_errors;
    if !(errs.focal_rel.is_finite() && errs.focal_rel.abs() < 0.2) {
        return bad(
            "camera_errors.focal_rel",
            errs.focal_rel,
            "use |error| < 0.2",
        );
    }
    if !(errs.principal_px.is_finite() && errs.principal_px.abs() < 50.0) {
        return bad(
            "camera_errors.principal_px",
            errs.principal_px,
            "use |error| < 50 px",
        );
    }
    errs.depth.validate()?;
    // The cameras as they truly are; the session records the factory intrinsics.
    let true_cams: Vec<SimCamera> = cfg
        .cameras
        .iter()
        .enumerate()
        .map(|(i, c)| SimCamera {
            intrinsics: errs.true_intrinsics(&c.intrinsics, seed, i),
            ..c.clone()
        })
        .collect();
    let session = cfg.session();
    let mut rng = ChaCha8Rng::seed_from_u64(seed);
    let lo = Vector3::from(cfg.region_min);
    let hi = Vector3::from(cfg.region_max);
    let centre = Point3::from((lo + hi) / 2.0);
    let mean_dir = true_cams
        .iter()
        .map(|c| (Point3::from(c.base_from_camera.translation()) - centre).normalize())
        .sum::<Vector3<f64>>()
        .normalize();
    let corners = cfg.board.corners();
    let board_centre = cfg.board.centre();
    let x = *cfg.flange_from_board.isometry();
    let cos_obl = cfg.max_obliquity_deg.to_radians().cos();
    let mut kept_boards: Vec<Isometry3<f64>> = Vec::new();
    let mut candidates = Vec::new();
    let wanted = cfg.poses * cfg.candidates_per_pose.max(1);
    const ATTEMPTS: usize = 400_000;
    let mut attempts = 0;
    while candidates.len() < wanted && attempts < ATTEMPTS {
        attempts += 1;
        // Board pose: normal tilted from the mean direction, turned about it.
        let pos = Vector3::new(
            rng.random_range(lo.x..=hi.x),
            rng.random_range(lo.y..=hi.y),
            rng.random_range(lo.z..=hi.z),
        );
        let tilt = cfg.max_tilt_deg.to_radians() * rng.random::<f64>().sqrt();
        let az = rng.random_range(-std::f64::consts::PI..std::f64::consts::PI);
        let other = if mean_dir.x.abs() < 0.9 {
            Vector3::x()
        } else {
            Vector3::y()
        };
        let perp = mean_dir.cross(&other).normalize();
        let tilt_axis = UnitQuaternion::from_scaled_axis(mean_dir * az) * perp;
        let normal = UnitQuaternion::from_scaled_axis(tilt_axis * tilt) * mean_dir;
        let spin = rng.random_range(-std::f64::consts::PI..std::f64::consts::PI);
        let face = UnitQuaternion::rotation_between(&Vector3::z(), &normal).unwrap_or_else(|| {
            UnitQuaternion::from_scaled_axis(Vector3::x() * std::f64::consts::PI)
        });
        let rot = face * UnitQuaternion::from_scaled_axis(Vector3::z() * spin);
        let base_from_board = Isometry3::from_parts(
            nalgebra::Translation3::from(pos - rot * board_centre.coords),
            rot,
        );
        if kept_boards.iter().any(|k| {
            (k.translation.vector - base_from_board.translation.vector).norm() < 0.03
                && k.rotation.angle_to(&base_from_board.rotation) < 5f64.to_radians()
        }) {
            continue;
        }
        // Every camera must see every corner, not too obliquely.
        // Which cameras see every corner, not too obliquely.
        let mut pixels = Vec::with_capacity(true_cams.len());
        for cam in &true_cams {
            let camera_from_board = cam.base_from_camera.isometry().inverse() * base_from_board;
            let to_cam = cam.base_from_camera.translation() - pos;
            if normal.dot(&to_cam.normalize()) < cos_obl {
                pixels.push(None);
                continue;
            }
            let k = &cam.intrinsics;
            let px: Option<Vec<_>> = corners
                .iter()
                .map(|b| {
                    k.project(&(camera_from_board * b)).ok().filter(|p| {
                        p.x >= cfg.margin_px
                            && p.y >= cfg.margin_px
                            && p.x <= f64::from(k.width) - 1.0 - cfg.margin_px
                            && p.y <= f64::from(k.height) - 1.0 - cfg.margin_px
                    })
                })
                .collect();
            pixels.push(px.map(|px| (camera_from_board, px)));
        }
        let seen = pixels.iter().filter(|p| p.is_some()).count();
        if seen < cfg.min_cameras_per_pose.clamp(1, true_cams.len()) {
            continue;
        }
        let base_from_flange_true: Transform<Base, Flange> =
            Transform::from_isometry(base_from_board * x.inverse());
        let joints = match check(&base_from_flange_true) {
            PoseCheck::Reject => continue,
            PoseCheck::Accept(j) => j,
        };
        kept_boards.push(base_from_board);
        candidates.push((base_from_board, base_from_flange_true, joints, pixels));
    }
    if candidates.len() < cfg.poses {
        return Err(CalibrationError::TooFewPoses {
            got: candidates.len(),
            needed: cfg.poses,
            more: cfg.poses - candidates.len(),
        });
    }
    let chosen = match cfg.selection {
        PoseSelection::FarthestPoint => farthest_poses(
            &candidates.iter().map(|c| c.0).collect::<Vec<_>>(),
            cfg.poses,
        ),
        PoseSelection::Information => {
            let sigma_px = cfg.noise.corner_px.max(0.05);
            let robot = (cfg.noise.robot_rad, cfg.noise.robot_m);
            let infos: Vec<DMatrix<f64>> = candidates
                .iter()
                .map(|(_, flange, _, pixels)| {
                    let seen: Vec<bool> = pixels.iter().map(Option::is_some).collect();
                    pose_information(
                        &true_cams,
                        &x,
                        flange.isometry(),
                        &seen,
                        &corners,
                        sigma_px,
                        robot,
                    )
                })
                .collect();
            informative_poses(&infos, true_cams.len(), cfg.poses)
        }
    };
    let mut captures = Vec::new();
    let mut truths: Vec<Transform<Base, Flange>> = Vec::new();
    for ci in chosen {
        let (_, base_from_flange_true, joints, pixels) = candidates[ci].clone();
        // Noise: robot, corners, depth.
        let mut n = [0.0; 6];
        for (i, v) in n.iter_mut().enumerate() {
            let s: f64 = rng.sample(StandardNormal);
            *v = s * if i < 3 {
                cfg.noise.robot_rad
            } else {
                cfg.noise.robot_m
            };
        }
        let recorded = Transform::from_isometry(base_from_flange_true.isometry() * exp6(&n));
        let mut views = Vec::with_capacity(true_cams.len());
        for (cam, seen) in true_cams.iter().zip(pixels) {
            let Some((camera_from_board, px)) = seen else {
                continue;
            };
            let corners_px: Vec<Corner> = match cfg.ir_noise {
                // The whole chain: render the IR image, detect the corners in it.
                Some(sigma) => {
                    let mut img = render_board_ir(
                        &cam.intrinsics,
                        &camera_from_board,
                        &cfg.board,
                        &IrLevels::default(),
                    );
                    for p in &mut img.data {
                        let g: f64 = rng.sample(StandardNormal);
                        *p = (f64::from(*p) + sigma * g).round().clamp(0.0, 255.0) as u8;
                    }
                    match detect_board(&img, &cfg.board, &DetectParams::default()) {
                        Ok(c) => c,
                        // Like a real capture: a view without a detection is not recorded.
                        Err(_) => continue,
                    }
                }
                None => px
                    .iter()
                    .enumerate()
                    .map(|(id, p)| {
                        let du: f64 = rng.sample(StandardNormal);
                        let dv: f64 = rng.sample(StandardNormal);
                        Corner {
                            id: id as u32,
                            u: p.x + du * cfg.noise.corner_px,
                            v: p.y + dv * cfg.noise.corner_px,
                        }
                    })
                    .collect(),
            };
            let board_depth = if cfg.depth_samples {
                depth_samples(
                    &cam.intrinsics,
                    &camera_from_board,
                    &px,
                    cfg.noise.depth_subpixel,
                    cfg.noise.depth_quantum_m,
                    &errs.depth,
                    &mut rng,
                )
            } else {
                Vec::new()
            };
            views.push(CameraView {
                camera: cam.id,
                corners: corners_px,
                board_depth,
            });
        }
        captures.push(Capture {
            index: captures.len(),
            joints,
            base_from_flange: recorded,
            views,
        });
        truths.push(base_from_flange_true);
    }
    let set = CaptureSet { session, captures };
    Ok((
        set,
        Truth {
            seed,
            config: cfg.clone(),
            base_from_flange: truths,
            intrinsics: true_cams.iter().map(|c| c.intrinsics).collect(),
        },
    ))
}

/// The Fisher information of one robot pose about the cameras and the board on the flange
/// (`6 k + 6` unknowns: per camera and for the board a rotation and a translation
/// perturbation, as in the bundle adjustment), with the pose's own flange error
/// (`robot`: rad, m per axis) marginalised out; `seen` says which cameras see the board.
fn pose_information(
    cams: &[SimCamera],
    x: &Isometry3<f64>,
    flange: &Isometry3<f64>,
    seen: &[bool],
    corners: &[Point3<f64>],
    sigma_px: f64,
    robot: (f64, f64),
) -> DMatrix<f64> {
    let n = 6 * cams.len() + 6;
    let mut htt = DMatrix::<f64>::zeros(n, n);
    let mut hte = DMatrix::<f64>::zeros(n, 6);
    let mut hee = Matrix6::<f64>::zeros();
    let r_x = x.rotation.to_rotation_matrix().into_inner();
    for (k, cam) in cams.iter().enumerate() {
        if !seen.get(k).copied().unwrap_or(false) {
            continue;
        }
        let cf = cam.base_from_camera.isometry().inverse() * flange;
        let r_cf = cf.rotation.to_rotation_matrix().into_inner();
        for b in corners {
            let q = x * b;
            let c = cf * q;
            let (_, jp) = project_with_jacobian(&cam.intrinsics, &c.coords);
            let jp = jp / sigma_px;
            let mut jc = Matrix3x6::zeros();
            jc.fixed_view_mut::<3, 3>(0, 0).copy_from(&skew(&c.coords));
            jc.fixed_view_mut::<3, 3>(0, 3)
                .copy_from(&(-Matrix3::identity()));
            let mut jt = DMatrix::<f64>::zeros(2, n);
            jt.fixed_view_mut::<2, 6>(0, 6 * k).copy_from(&(jp * jc));
            jt.fixed_view_mut::<2, 6>(0, n - 6)
                .copy_from(&(jp * r_cf * r_x * point_jacobian(&b.coords)));
            let je = jp * r_cf * point_jacobian(&q.coords);
            htt += jt.transpose() * &jt;
            hte += jt.transpose() * je;
            hee += je.transpose() * je;
        }
    }
    if robot.0 <= 0.0 || robot.1 <= 0.0 {
        // An exact robot: nothing to marginalise.
        return htt;
    }
    for a in 0..6 {
        let s = if a < 3 { robot.0 } else { robot.1 };
        hee[(a, a)] += 1.0 / (s * s);
    }
    match hee.cholesky() {
        Some(ch) => {
            let mut solved = DMatrix::<f64>::zeros(6, n);
            for col in 0..n {
                let v = nalgebra::Vector6::from_iterator(hte.row(col).iter().copied());
                solved.column_mut(col).copy_from(&ch.solve(&v));
            }
            htt - hte * solved
        }
        None => htt,
    }
}

/// Greedy optimal design over the candidates' information matrices (see
/// [`PoseSelection::Information`]): `n` candidate indices.
fn informative_poses(infos: &[DMatrix<f64>], ncam: usize, n: usize) -> Vec<usize> {
    let Some(dim) = infos.first().map(|m| m.nrows()) else {
        return Vec::new();
    };
    let rot = 0.05_f64.to_radians().powi(2);
    let pos = 1e-3_f64.powi(2);
    // A weak prior (1 rad, 1 m) keeps the first few sums invertible.
    let mut total = DMatrix::<f64>::identity(dim, dim);
    let score = |m: &DMatrix<f64>| -> f64 {
        let Some(cov) = m.clone().cholesky().map(|c| c.inverse()) else {
            return f64::INFINITY;
        };
        (0..ncam)
            .map(|k| {
                let o = 6 * k;
                let r: f64 = (0..3).map(|a| cov[(o + a, o + a)]).sum();
                let t: f64 = (3..6).map(|a| cov[(o + a, o + a)]).sum();
                r / rot + t / pos
            })
            .fold(0.0, f64::max)
    };
    let mut chosen = Vec::with_capacity(n);
    let mut used = vec![false; infos.len()];
    while chosen.len() < n.min(infos.len()) {
        let best = (0..infos.len())
            .filter(|&i| !used[i])
            .map(|i| (i, score(&(&total + &infos[i]))))
            .min_by(|a, b| a.1.total_cmp(&b.1));
        let Some((i, _)) = best else {
            break;
        };
        used[i] = true;
        total += &infos[i];
        chosen.push(i);
    }
    chosen
}

/// Greedy farthest-point selection of `n` board poses (distance: 10 cm of position or 20°
/// of rotation count as 1), starting from the pose nearest the centre: spreads the poses
/// over the reachable set, which conditions the hand-eye problem far better than a random
/// draw of the same size.
fn farthest_poses(boards: &[Isometry3<f64>], n: usize) -> Vec<usize> {
    let dist = |a: &Isometry3<f64>, b: &Isometry3<f64>| {
        let dp = (a.translation.vector - b.translation.vector).norm() / 0.1;
        let dr = a.rotation.angle_to(&b.rotation) / 20f64.to_radians();
        (dp * dp + dr * dr).sqrt()
    };
    if boards.is_empty() {
        return Vec::new();
    }
    let centre = boards
        .iter()
        .fold(Vector3::zeros(), |a, b| a + b.translation.vector)
        / boards.len() as f64;
    let first = (0..boards.len())
        .min_by(|&a, &b| {
            (boards[a].translation.vector - centre)
                .norm()
                .total_cmp(&(boards[b].translation.vector - centre).norm())
        })
        .unwrap_or(0);
    let mut chosen = vec![first];
    let mut nearest: Vec<f64> = boards.iter().map(|b| dist(b, &boards[first])).collect();
    while chosen.len() < n.min(boards.len()) {
        let Some(next) = (0..boards.len())
            .filter(|i| !chosen.contains(i))
            .max_by(|&a, &b| nearest[a].total_cmp(&nearest[b]))
        else {
            break;
        };
        chosen.push(next);
        for (i, d) in nearest.iter_mut().enumerate() {
            *d = d.min(dist(&boards[i], &boards[next]));
        }
    }
    chosen
}

/// Depth samples at the integer pixels nearest the corners: the board plane's depth along
/// each pixel's ray, the camera's depth error, D455 axial noise, 1 mm quantisation.
fn depth_samples(
    k: &Intrinsics,
    camera_from_board: &Isometry3<f64>,
    pixels: &[nalgebra::Point2<f64>],
    subpixel: f64,
    quantum: f64,
    error: &DepthCorrection,
    rng: &mut ChaCha8Rng,
) -> Vec<DepthSample> {
    let n = camera_from_board.rotation * Vector3::z();
    let p0 = camera_from_board.translation.vector;
    let f = (k.fx + k.fy) / 2.0;
    let mut out = Vec::with_capacity(pixels.len());
    for p in pixels {
        let (u, v) = (p.x.round(), p.y.round());
        let Ok(ray) = k.pixel_ray(nalgebra::Point2::new(u, v)) else {
            continue;
        };
        let denom = n.dot(&ray);
        if denom.abs() < 1e-9 {
            continue;
        }
        let z = error.measured(n.dot(&p0) / denom);
        let sigma = z * z * subpixel / (f * D455_BASELINE_M);
        let noisy = if sigma > 0.0 {
            Normal::new(z, sigma).map_or(z, |d| d.sample(rng))
        } else {
            z
        };
        let q = if quantum > 0.0 {
            (noisy / quantum).round() * quantum
        } else {
            noisy
        };
        if q > 0.0 {
            out.push(DepthSample { u, v, depth_m: q });
        }
    }
    out
}

/// The truth file's name in a simulated captures folder.
pub const TRUTH_FILE: &str = "truth.json";

/// Simulates captures of `cfg` with `seed` into the captures folder `dir` (plus
/// `truth.json`), resuming an interrupted run (poses already written are kept; the same
/// seed regenerates the same poses).
pub fn simulate(
    cfg: &SimConfig,
    seed: u64,
    dir: &Path,
) -> Result<(CaptureSet, Truth), CalibrationError> {
    let (set, truth) = simulate_set(cfg, seed)?;
    write_captures(dir, &set)?;
    let path = dir.join(TRUTH_FILE);
    let text = serde_json::to_vec_pretty(&truth).map_err(|e| CalibrationError::CaptureIo {
        path: path.display().to_string(),
        why: e.to_string(),
    })?;
    write_atomic(&path, &text)?;
    Ok((set, truth))
}

/// Reads `truth.json` of a simulated captures folder.
pub fn load_truth(dir: &Path) -> Result<Truth, CalibrationError> {
    let path = dir.join(TRUTH_FILE);
    let io = |e: &dyn std::fmt::Display| CalibrationError::CaptureIo {
        path: path.display().to_string(),
        why: e.to_string(),
    };
    let text = std::fs::read_to_string(&path).map_err(|e| io(&e))?;
    serde_json::from_str(&text).map_err(|e| io(&e))
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::capture::load_captures;

    #[test]
    fn noise_free_captures_project_exactly_and_see_every_corner() {
        let mut cfg = SimConfig::default_cell();
        cfg.noise = SimNoise::none();
        let (set, truth) = simulate_set(&cfg, 1).unwrap();
        assert_eq!(set.captures.len(), 30);
        set.validate("sim").unwrap();
        let x = cfg.flange_from_board.isometry();
        for (c, f) in set.captures.iter().zip(&truth.base_from_flange) {
            assert_eq!(c.views.len(), 3);
            assert_eq!(c.base_from_flange, *f);
            for v in &c.views {
                assert_eq!(v.corners.len(), cfg.board.corner_count());
                let cam = truth.base_from_camera(v.camera).unwrap();
                let k = set.session.camera(v.camera).unwrap().intrinsics;
                for k_ in &v.corners {
                    let b = cfg.board.corner(k_.id).unwrap();
                    let p = cam.isometry().inverse() * f.isometry() * x * b;
                    let px = k.project(&p).unwrap();
                    assert!((px.x - k_.u).abs() < 1e-9 && (px.y - k_.v).abs() < 1e-9);
                }
                // Depth samples lie on the board (1 mm quantisation).
                assert!(!v.board_depth.is_empty());
                for d in &v.board_depth {
                    let p = k
                        .deproject(nalgebra::Point2::new(d.u, d.v), d.depth_m)
                        .unwrap();
                    let on_board = (f.isometry() * x).inverse() * cam.isometry() * p;
                    assert!(on_board.z.abs() < 2e-3, "{}", on_board.z);
                }
            }
        }
    }

    /// Simulates `cfg` (IR images on) and the same poses with projected corners: the image
    /// captures, their truth, and how many views the projection saw.
    fn image_and_projected(cfg: &SimConfig, seed: u64) -> (CaptureSet, Truth, usize) {
        let (set, truth) = simulate_set(cfg, seed).unwrap();
        let (projected, _) = simulate_set(
            &SimConfig {
                ir_noise: None,
                ..cfg.clone()
            },
            seed,
        )
        .unwrap();
        let seen = projected.captures.iter().map(|c| c.views.len()).sum();
        (set, truth, seen)
    }

    /// Solves captures detected in images without robot noise: every camera within
    /// 0.3 mm / 0.02° of the truth, every fit within 0.1 px (the detector's error).
    fn assert_image_chain_recovers(set: &CaptureSet, truth: &Truth) {
        let opts = crate::solve::SolveOptions {
            robot_prior: None,
            corner_sigma_px: 0.05,
            min_poses: 10,
            min_views_per_camera: 5,
            holdout_folds: 0,
            ..Default::default()
        };
        let sol = crate::solve::solve(set, &opts).unwrap();
        for (id, dt, dr) in sol.errors_to(truth) {
            eprintln!("camera {id}: {:.4} mm {:.5} deg", dt * 1e3, dr.to_degrees());
            assert!(
                dt < 0.3e-3 && dr.to_degrees() < 0.02,
                "camera {id}: {dt} m {dr} rad"
            );
        }
        for c in &sol.cameras {
            eprintln!("camera {}: fit RMS {:.4} px", c.id, c.fit_rms_px);
            assert!(c.fit_rms_px < 0.1, "{}", c.fit_rms_px);
        }
    }

    #[test]
    fn the_whole_chain_from_april_grid_images_recovers_the_cameras() {
        // As below with an AprilGrid: render, detect the tags, solve, no robot noise.
        let mut cfg = SimConfig::default_cell().with_board(BoardConfig::default_april_grid());
        cfg.poses = 15;
        cfg.noise = SimNoise::none();
        cfg.ir_noise = Some(2.0);
        cfg.max_obliquity_deg = 60.0;
        let (set, truth, seen) = image_and_projected(&cfg, 9);
        let mut views = 0;
        let mut corners = 0;
        for c in &set.captures {
            views += c.views.len();
            corners += c.views.iter().map(|v| v.corners.len()).sum::<usize>();
        }
        eprintln!("AprilGrid chain: {views} of {seen} views, {corners} corners");
        // Far or oblique tags have bits too small to decode: their views are partial (which
        // an AprilGrid allows) or missing, but most of the board is read.
        assert!(views * 5 >= seen * 4, "{views} of {seen} views detected");
        let complete = views * cfg.board.corner_count();
        assert!(
            corners * 3 >= complete * 2,
            "{corners} of {complete} corners"
        );
        assert_image_chain_recovers(&set, &truth);
    }

    #[test]
    fn the_whole_chain_from_ir_images_recovers_the_cameras() {
        // Render IR images, detect the chessboard, solve: no robot noise, so what is left is
        // the detector's sub-pixel error.
        // Views at most 65 degrees oblique (a chessboard detector needs squares of a few
        // pixels in an 848x480 image).
        let mut cfg = SimConfig::default_cell();
        cfg.poses = 15;
        cfg.noise = SimNoise::none();
        cfg.ir_noise = Some(2.0);
        cfg.max_obliquity_deg = 65.0;
        let (set, truth, seen) = image_and_projected(&cfg, 8);
        let mut views = 0;
        for c in &set.captures {
            views += c.views.len();
            for v in &c.views {
                assert_eq!(v.corners.len(), cfg.board.corner_count());
            }
        }
        assert!(views * 10 >= seen * 9, "{views} of {seen} views detected");
        eprintln!("IR chain: {views} of {seen} views detected");
        assert_image_chain_recovers(&set, &truth);
    }

    #[test]
    fn same_seed_same_captures_and_noise_is_seeded() {
        let cfg = SimConfig::default_cell();
        let (a, _) = simulate_set(&cfg, 5).unwrap();
        let (b, _) = simulate_set(&cfg, 5).unwrap();
        let (c, _) = simulate_set(&cfg, 6).unwrap();
        assert_eq!(a, b);
        assert_ne!(a, c);
    }

    #[test]
    fn the_check_can_reject_poses_and_record_joints() {
        let cfg = SimConfig {
            poses: 5,
            ..SimConfig::default_cell()
        };
        let mut asked = 0;
        let (set, _) = simulate_set_with(&cfg, 2, &mut |f| {
            asked += 1;
            if f.translation().z > 0.2 {
                PoseCheck::Accept(Some([f.translation().z; 6]))
            } else {
                PoseCheck::Reject
            }
        })
        .unwrap();
        assert!(asked >= 5);
        for c in &set.captures {
            let q = c.joints.unwrap();
            assert!(q[0] > 0.2);
        }
    }

    #[test]
    fn simulate_writes_a_loadable_folder_and_resumes() {
        let dir = std::env::temp_dir().join(format!("calib-sim-{}", std::process::id()));
        let _ = std::fs::remove_dir_all(&dir);
        let cfg = SimConfig {
            poses: 6,
            ..SimConfig::default_cell()
        };
        let (set, truth) = simulate(&cfg, 3, &dir).unwrap();
        // Interrupt: lose two poses, then run again: they come back, identical.
        std::fs::remove_file(dir.join("pose_0002.json")).unwrap();
        std::fs::remove_file(dir.join("pose_0005.json")).unwrap();
        simulate(&cfg, 3, &dir).unwrap();
        let loaded = load_captures(&dir).unwrap();
        assert_eq!(loaded, set);
        assert_eq!(load_truth(&dir).unwrap(), truth);
        std::fs::remove_dir_all(&dir).unwrap();
    }
}
