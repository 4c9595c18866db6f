//! `equact calibrate capture` in the simulated cell: the capture loop a real calibration
//! runs, against the loopback simulator. Plans diverse board poses (the `calibration`
//! crate's pose sampler, each candidate checked for IK reachability and collisions by the
//! planner), drives the arm there through the real UR driver, reads back the joints it
//! reached, renders and detects the flange board in each camera's IR image and writes one
//! capture per pose (`pose_NNNN.json`, and each IR image as `ir_pose_NNNN_cam_K.png`) into a
//! resumable captures folder. Each pose is written atomically: an interrupted run loses
//! nothing, and running it again resumes where it stopped.

use std::path::Path;
use std::sync::Arc;

use anyhow::Context;
use calibration::capture::{CameraView, Capture, CaptureFolder};
use calibration::detect::{detect_chessboard, render_board_ir, DetectParams, IrLevels};
use calibration::simulate::{simulate_set_with, PoseCheck, SimConfig, Truth};
use cell_types::config::CellConfig;
use cell_types::{Clock, Joints, Transform};
use firmware_iface::arm::{Arm, ExecutionOutcome};
use planner::{Obstacle, World};
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use rand_distr::StandardNormal;

use crate::episode::planner_from_config;
use crate::sim_cell::SimCell;
use crate::task::{TaskInstance, TaskKind};

/// What one capture run did.
#[derive(Clone, Debug, PartialEq)]
pub struct CaptureRun {
    /// Poses planned.
    pub planned: usize,
    /// Poses already in the folder (skipped).
    pub resumed: usize,
    /// Poses captured in this run.
    pub captured: usize,
    /// Poses the arm could not reach (plan or execution failed), with why.
    pub skipped: Vec<(usize, String)>,
}

/// What to capture.
#[derive(Copy, Clone, Debug, PartialEq)]
pub struct CapturePlan {
    /// Seed of the pose plan (and the image noise).
    pub seed: u64,
    /// Number of board poses planned.
    pub poses: usize,
    /// At most this many new poses in this run (None: all).
    pub limit: Option<usize>,
    /// Gaussian grey-level noise of the rendered IR images.
    pub ir_sigma: f64,
}

/// Runs the capture loop of `plan` in the simulated cell into the captures folder `dir`.
pub fn capture_in_sim(
    cfg: &CellConfig,
    dir: &Path,
    plan: CapturePlan,
    clock: Arc<dyn Clock>,
    progress: &mut dyn FnMut(&str),
) -> anyhow::Result<CaptureRun> {
    let CapturePlan {
        seed,
        poses,
        limit,
        ir_sigma,
    } = plan;
    let planner = planner_from_config(cfg)?;
    let world = World::empty().with_obstacle(Obstacle::table(cfg.workspace.table_height));
    let home: Joints = hil_sim::scene::HOME_Q;
    let flange_from_tcp = planner
        .model
        .fk_flange(&home)
        .map(|f| f.inverse() * planner.model.fk_tcp(&home))
        .context("the robot model has no flange link")?;

    // Plan the poses: reachable, collision-free, joints nearest home.
    let mut sim = SimConfig::default_cell();
    sim.poses = poses;
    let mut checker = planner::checker::Checker::new(&planner.model, &world, 0.01);
    let (planned, _) = simulate_set_with(&sim, seed, &mut |base_from_flange| {
        let base_from_tcp =
            Transform::from_isometry(base_from_flange.isometry() * flange_from_tcp.isometry());
        let Ok(solutions) = planner.model.ik_near(&base_from_tcp, &home) else {
            return PoseCheck::Reject;
        };
        solutions
            .into_iter()
            .filter(|q| checker.is_free(q))
            .min_by(|a, b| {
                cell_types::joints::max_abs_diff(a, &home)
                    .total_cmp(&cell_types::joints::max_abs_diff(b, &home))
            })
            .map_or(PoseCheck::Reject, |q| PoseCheck::Accept(Some(q)))
    })
    .context("planning the calibration poses")?;

    let mut folder = CaptureFolder::create_or_resume(dir, &sim.session())?;
    // The simulated cameras' true poses, so that `equact calibrate solve` can report its
    // error (the flange poses come from the captures themselves).
    let truth = Truth {
        seed,
        config: sim.clone(),
        base_from_flange: Vec::new(),
        intrinsics: Vec::new(),
    };
    let truth_path = dir.join(calibration::simulate::TRUTH_FILE);
    calibration::capture::write_atomic(
        &truth_path,
        &serde_json::to_vec_pretty(&truth).context("encoding truth.json")?,
    )?;
    let todo = folder.missing(planned.captures.len());
    let mut run = CaptureRun {
        planned: planned.captures.len(),
        resumed: planned.captures.len() - todo.len(),
        captured: 0,
        skipped: Vec::new(),
    };
    progress(&format!(
        "{} poses planned, {} already captured in {}",
        run.planned,
        run.resumed,
        dir.display()
    ));
    if todo.is_empty() {
        return Ok(run);
    }

    let task = TaskInstance::sample(
        TaskKind::parse("pick_fruit/strawberry").map_err(anyhow::Error::msg)?,
        seed,
        cfg.workspace.table_height,
    );
    let mut cell = SimCell::start(cfg, task, seed, clock)?;
    let mut rng = ChaCha8Rng::seed_from_u64(seed ^ 0x1a_b0a2d);
    let result = (|| -> anyhow::Result<()> {
        for (n, index) in todo.iter().enumerate() {
            if limit.is_some_and(|l| run.captured >= l) {
                break;
            }
            let Some(goal) = planned.captures.get(*index).and_then(|c| c.joints) else {
                run.skipped.push((*index, "no joints planned".into()));
                continue;
            };
            let start = cell.arm.state()?.joints.position;
            let motion = match planner.plan_to_joints(&start, &goal, &world) {
                Ok(m) => m,
                Err(e) => {
                    run.skipped.push((*index, format!("no plan: {e}")));
                    continue;
                }
            };
            match cell.arm.execute(&motion.trajectory)? {
                ExecutionOutcome::Completed { .. } => {}
                ExecutionOutcome::Stopped { by, cause, .. } => {
                    anyhow::bail!("pose {index}: the arm stopped ({by:?}: {cause:?}); the poses captured so far are kept, rerun to resume");
                }
            }
            // What the robot reports, not what was planned, goes into the capture.
            let q = cell.arm.state()?.joints.position;
            let base_from_flange = planner
                .model
                .fk_flange(&q)
                .context("the robot model has no flange link")?;
            let mut views = Vec::new();
            for cam in &sim.cameras {
                let camera_from_board = cam.base_from_camera.isometry().inverse()
                    * base_from_flange.isometry()
                    * sim.flange_from_board.isometry();
                let mut img = render_board_ir(
                    &cam.intrinsics,
                    &camera_from_board,
                    &sim.board,
                    &IrLevels::default(),
                );
                for p in &mut img.data {
                    let g: f64 = rng.sample(StandardNormal);
                    *p = (f64::from(*p) + ir_sigma * g).round().clamp(0.0, 255.0) as u8;
                }
                // The image is kept beside the capture (to re-detect or inspect later).
                let png = grey_png(&img).context("encoding an IR image")?;
                calibration::capture::write_atomic(
                    &dir.join(format!("ir_pose_{index:04}_cam_{}.png", cam.id)),
                    &png,
                )?;
                // A camera that does not find the board records no view, as on the real cell.
                if let Ok(corners) = detect_chessboard(&img, &sim.board, &DetectParams::default()) {
                    views.push(CameraView {
                        camera: cam.id,
                        corners,
                        board_depth: Vec::new(),
                    });
                }
            }
            let seen = views.len();
            folder.write(&Capture {
                index: *index,
                joints: Some(q),
                base_from_flange,
                views,
            })?;
            run.captured += 1;
            progress(&format!(
                "pose {:>2} ({}/{}): {seen} of {} cameras found the board",
                index,
                n + 1,
                todo.len(),
                sim.cameras.len()
            ));
        }
        Ok(())
    })();
    let _ = cell.arm.stop();
    cell.controller.shutdown();
    result.map(|()| run)
}

/// An 8-bit grey image as PNG bytes.
fn grey_png(img: &cell_types::Image<u8>) -> Result<Vec<u8>, png::EncodingError> {
    let mut out = Vec::new();
    {
        let mut enc = png::Encoder::new(&mut out, img.width, img.height);
        enc.set_color(png::ColorType::Grayscale);
        enc.set_depth(png::BitDepth::Eight);
        let mut w = enc.write_header()?;
        w.write_image_data(&img.data)?;
        w.finish()?;
    }
    Ok(out)
}
