//! `equact calibrate capture` in the simulated cell, end to end: planned board poses, the
//! arm driven there through the UR driver, the board detected in rendered IR images, an
//! interrupted run resumed without losing or repeating a pose, and the captures solved to
//! the simulated cameras' true poses.

#![allow(clippy::unwrap_used, clippy::expect_used)] // test helpers may panic

use std::sync::Arc;

use calibration::detect::{render_board_ir, IrLevels};
use calibration::simulate::SimConfig;
use cell_types::config::CellConfig;
use cell_types::{Base, Camera, CameraFrame, DepthImage, Image, SystemClock, TickClock, Transform};
use equact::calibrate_capture::{capture_in_sim, capture_on_cell, CapturePlan};
use firmware_iface::camera::{CameraError, DepthCamera};
use hil_sim::ur_controller::{start, UrSimConfig, UrSimHandle};
use nalgebra::{Isometry3, Translation3, UnitQuaternion, Vector3};

fn plan(limit: Option<usize>) -> CapturePlan {
    CapturePlan {
        seed: 5,
        poses: 14,
        limit,
        ir_sigma: 2.0,
        settle_s: 0.0,
    }
}

#[test]
fn capture_resume_and_solve_in_the_simulated_cell() {
    let _cell = tests::one_cell_at_a_time();
    let cfg = CellConfig::simulated().unwrap();
    let dir = std::env::temp_dir().join(format!("equact-capture-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&dir);
    let clock = Arc::new(TickClock::new(tests::SIM_SPEED).unwrap());
    let mut lines = Vec::new();

    // An interrupted run: only 4 poses.
    let first = capture_in_sim(&cfg, &dir, plan(Some(4)), clock.clone(), &mut |l| {
        lines.push(l.to_string())
    })
    .unwrap();
    assert_eq!(first.captured, 4);
    assert_eq!(first.resumed, 0);
    let kept: Vec<_> = std::fs::read_dir(&dir)
        .unwrap()
        .map(|e| e.unwrap().file_name().to_string_lossy().into_owned())
        .filter(|n| n.starts_with("pose_"))
        .collect();
    assert_eq!(kept.len(), 4, "{kept:?}");
    // Every camera's IR image of every captured pose is kept beside it.
    let images = std::fs::read_dir(&dir)
        .unwrap()
        .filter(|e| {
            let name = e.as_ref().unwrap().file_name();
            let name = name.to_string_lossy();
            name.starts_with("ir_pose_") && name.ends_with(".png")
        })
        .count();
    assert_eq!(images, 4 * 3);
    let before = std::fs::read(dir.join(&kept[0])).unwrap();

    // Resumed: the 4 are kept as they were, the rest captured (or skipped with a reason).
    let second = capture_in_sim(&cfg, &dir, plan(None), clock, &mut |l| {
        lines.push(l.to_string())
    })
    .unwrap();
    assert_eq!(second.resumed, 4);
    assert_eq!(second.captured + second.skipped.len() + 4, second.planned);
    assert!(second.captured + 4 >= 10, "{second:?}");
    assert_eq!(std::fs::read(dir.join(&kept[0])).unwrap(), before);
    assert!(lines.iter().any(|l| l.contains("cameras found the board")));

    let set = calibration::load_captures(&dir).unwrap();
    let solution = calibration::solve(&set, &calibration::SolveOptions::default()).unwrap();
    let truth = calibration::load_truth(&dir).unwrap();
    for (id, m, rad) in solution.errors_to(&truth) {
        assert!(
            m < 1e-3 && rad < 0.05_f64.to_radians(),
            "camera {id}: {m} m, {rad} rad"
        );
    }
    let _ = std::fs::remove_dir_all(&dir);
}

/// A camera of a "real" cell in this test: it sees the board where the simulated
/// controller has put the flange (its true pose is not the configured approximate one).
struct BoardCamera {
    id: u8,
    sim: SimConfig,
    base_from_camera: Transform<Base, Camera>,
    controller: Arc<UrSimHandle>,
    model: planner::RobotModel,
}

impl DepthCamera for BoardCamera {
    fn id(&self) -> u8 {
        self.id
    }

    fn capture(&mut self) -> Result<CameraFrame, CameraError> {
        let q = self.controller.snapshot().actual_q;
        let base_from_flange = self.model.fk_flange(&q).ok_or(CameraError::Device {
            camera: self.id,
            message: "no flange link".into(),
        })?;
        let k = &self.sim.cameras[usize::from(self.id)].intrinsics;
        let camera_from_board = self.base_from_camera.isometry().inverse()
            * base_from_flange.isometry()
            * self.sim.flange_from_board.isometry();
        let ir = render_board_ir(k, &camera_from_board, &self.sim.board, &IrLevels::default());
        let (w, h) = (ir.width, ir.height);
        Ok(CameraFrame {
            camera: self.id,
            timestamp: std::time::Duration::ZERO,
            depth: DepthImage {
                raw: Image::new(w, h, vec![0; (w * h) as usize]).unwrap(),
                depth_scale: 0.001,
            },
            ir: Some(ir),
            colour: None,
        })
    }
}

/// `equact calibrate capture --config` on a real cell: the arm behind a real-cell config
/// (backend "ur") on loopback, the board imaged by the cameras' IR streams, the poses
/// planned from the config's approximate camera placement (a few cm and degrees off the
/// truth), and the captures solved to the cameras' true poses.
#[test]
fn capture_on_a_real_cell_config_with_approximately_placed_cameras() {
    let _cell = tests::one_cell_at_a_time();
    let mut cfg = CellConfig::simulated().unwrap();
    let clock = Arc::new(SystemClock::new());
    let tcp = cfg.robot.tcp_offset_m;
    let controller = Arc::new(
        start(
            UrSimConfig {
                initial_q: hil_sim::scene::HOME_Q,
                flange_from_tcp: Transform::from_parts(
                    Vector3::new(0.0, 0.0, tcp),
                    Default::default(),
                ),
                floor_z: Some(cfg.workspace.table_height),
                ..UrSimConfig::for_tests()
            },
            clock.clone(),
        )
        .unwrap(),
    );
    cfg = tests::loopback_real_cell_config(&controller, None).unwrap();
    let sim = SimConfig::default_cell();
    let mut cameras: Vec<Box<dyn DepthCamera>> = Vec::new();
    let mut truth = Vec::new();
    for (i, c) in sim.cameras.iter().enumerate() {
        // The configured placement: where the truth's optical axis starts and points.
        let iso = c.base_from_camera.isometry();
        let eye = iso.translation.vector;
        let look = iso * nalgebra::Point3::new(0.0, 0.0, 0.8);
        cfg.cameras[i].approx_position = Some([eye.x, eye.y, eye.z]);
        cfg.cameras[i].approx_look_at = Some([look.x, look.y, look.z]);
        // The truth: 3 cm and 2 degrees away from it.
        let off = Isometry3::from_parts(
            Translation3::new(0.03, -0.02, 0.01),
            UnitQuaternion::from_euler_angles(0.02, -0.03, 0.035),
        );
        let base_from_camera = Transform::from_isometry(iso * off);
        truth.push(base_from_camera);
        cameras.push(Box::new(BoardCamera {
            id: c.id,
            sim: sim.clone(),
            base_from_camera,
            controller: controller.clone(),
            model: planner::RobotModel::ur5().unwrap(),
        }));
    }
    let dir = std::env::temp_dir().join(format!("equact-capture-real-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&dir);
    let mut lines = Vec::new();
    let run = capture_on_cell(
        &cfg,
        &dir,
        &dir,
        CapturePlan {
            seed: 3,
            poses: 12,
            limit: None,
            ir_sigma: 0.0,
            settle_s: 0.0,
        },
        &mut cameras,
        clock,
        &mut |l| lines.push(l.to_string()),
    )
    .unwrap();
    // Each pose is reached, if not by its planned configuration then by another IK branch.
    assert!(run.captured >= 11, "{run:?}");
    assert!(lines.iter().any(|l| l.contains("cameras found the board")));
    // Nothing about the truth is in the folder: only captures and images.
    assert!(!dir.join(calibration::simulate::TRUTH_FILE).exists());

    let set = calibration::load_captures(&dir).unwrap();
    let solution = calibration::solve(&set, &calibration::SolveOptions::default()).unwrap();
    for c in &solution.cameras {
        let want = truth[usize::from(c.id)].isometry();
        let got = c.base_from_camera.isometry();
        let m = (got.translation.vector - want.translation.vector).norm();
        let rad = got.rotation.angle_to(&want.rotation);
        assert!(
            m < 1e-3 && rad < 0.05_f64.to_radians(),
            "camera {}: {m} m, {rad} rad",
            c.id
        );
    }
    drop(cameras);
    if let Ok(c) = Arc::try_unwrap(controller) {
        c.shutdown();
    }
    let _ = std::fs::remove_dir_all(&dir);
}
