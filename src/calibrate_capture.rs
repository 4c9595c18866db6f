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
use calibration::capture::{CameraView, Capture, CaptureFolder, CaptureSet};
use calibration::detect::{detect_board, render_board_ir, DetectParams, IrLevels};
use calibration::simulate::{simulate_set_with, PoseCheck, SimCamera, SimConfig, Truth};
use calibration::{BoardConfig, Intrinsics};
use cell_types::config::{CameraSection, CellConfig};
use cell_types::{Base, Clock, Flange, Image, Joints, Transform};
use firmware_iface::arm::{Arm, ExecutionOutcome};
use firmware_iface::camera::DepthCamera;
use firmware_iface::ur::UrArm;
use hil_sim::depth_camera::look_at;
use nalgebra::Point3;
use planner::{Obstacle, Planner, World};
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
    /// Gaussian grey-level noise of the rendered IR images (simulated cell only).
    pub ir_sigma: f64,
    /// Wait after each motion before imaging (s): a real arm and board swing briefly.
    pub settle_s: f64,
}

/// Where the board images of one pose come from.
pub trait BoardImager {
    /// One IR image per camera that delivered one, with the flange at `base_from_flange`
    /// (real cameras ignore it: they see the board where it is).
    fn images(
        &mut self,
        base_from_flange: &Transform<Base, Flange>,
    ) -> anyhow::Result<Vec<(u8, Image<u8>)>>;
}

/// The simulated cell's cameras seeing the board: rendered IR with grey-level noise.
struct RenderedBoard<'a> {
    sim: &'a SimConfig,
    rng: ChaCha8Rng,
    ir_sigma: f64,
}

impl BoardImager for RenderedBoard<'_> {
    fn images(
        &mut self,
        base_from_flange: &Transform<Base, Flange>,
    ) -> anyhow::Result<Vec<(u8, Image<u8>)>> {
        let mut out = Vec::with_capacity(self.sim.cameras.len());
        for cam in &self.sim.cameras {
            let camera_from_board = cam.base_from_camera.isometry().inverse()
                * base_from_flange.isometry()
                * self.sim.flange_from_board.isometry();
            let mut img = render_board_ir(
                &cam.intrinsics,
                &camera_from_board,
                &self.sim.board,
                &IrLevels::default(),
            );
            for p in &mut img.data {
                let g: f64 = self.rng.sample(StandardNormal);
                *p = (f64::from(*p) + self.ir_sigma * g)
                    .round()
                    .clamp(0.0, 255.0) as u8;
            }
            out.push((cam.id, img));
        }
        Ok(out)
    }
}

/// Depth cameras' IR streams (the D455's left imager, which shares the depth intrinsics).
pub struct CameraIr<'a> {
    /// The cameras, numbered as the configuration lists them.
    pub cameras: &'a mut [Box<dyn DepthCamera>],
}

impl BoardImager for CameraIr<'_> {
    fn images(
        &mut self,
        _base_from_flange: &Transform<Base, Flange>,
    ) -> anyhow::Result<Vec<(u8, Image<u8>)>> {
        let mut out = Vec::with_capacity(self.cameras.len());
        for cam in self.cameras.iter_mut() {
            // The first frame may have been exposed while the arm was still moving (the
            // stream queues frames): keep the second.
            cam.capture()
                .with_context(|| format!("camera {}: first frame", cam.id()))?;
            let frame = cam
                .capture()
                .with_context(|| format!("camera {}: settled frame", cam.id()))?;
            let Some(ir) = frame.ir else {
                anyhow::bail!(
                    "camera {} delivered no IR image: the calibration detects the board in the \
                     left IR stream; enable it (and switch the IR projector off)",
                    cam.id()
                );
            };
            out.push((cam.id(), ir));
        }
        Ok(out)
    }
}

/// The captures' layout and the cameras' placement a pose plan needs: the board, the
/// cameras (intrinsics and approximate poses) and the board's mount on the flange.
fn plan_poses(
    planner: &Planner,
    world: &World,
    sim: &SimConfig,
    seed: u64,
) -> anyhow::Result<CaptureSet> {
    let home: Joints = hil_sim::scene::HOME_Q;
    let flange_from_tcp = planner
        .model
        .fk_flange(&home)
        .map(|f| f.inverse() * planner.model.fk_tcp(&home))
        .context("the robot model has no flange link")?;
    let mut checker = planner::checker::Checker::new(&planner.model, world, 0.01);
    let (planned, _) = simulate_set_with(sim, seed, &mut |base_from_flange| {
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
    Ok(planned)
}

/// A capture run ready to move the arm: the planner and its world, the layout the poses
/// were planned for, the planned poses, the open captures folder and what is left to do.
struct PreparedCapture {
    planner: Planner,
    world: World,
    layout: SimConfig,
    planned: CaptureSet,
    folder: CaptureFolder,
    todo: Vec<usize>,
    run: CaptureRun,
}

impl PreparedCapture {
    /// Plans `plan.poses` board poses for `layout` (reachable and collision-free) and opens
    /// or resumes the captures folder `dir`; nothing moves.
    fn new(
        cfg: &CellConfig,
        mut layout: SimConfig,
        dir: &Path,
        plan: &CapturePlan,
        progress: &mut dyn FnMut(&str),
    ) -> anyhow::Result<Self> {
        let planner = planner_from_config(cfg)?;
        let world = World::empty().with_obstacle(Obstacle::table(cfg.workspace.table_height));
        layout.poses = plan.poses;
        let planned = plan_poses(&planner, &world, &layout, plan.seed)?;
        let folder = CaptureFolder::create_or_resume(dir, &layout.session())?;
        let todo = folder.missing(planned.captures.len());
        let run = CaptureRun {
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
        Ok(Self {
            planner,
            world,
            layout,
            planned,
            folder,
            todo,
            run,
        })
    }

    /// Drives `arm` through the poses left to do, images the board at each and writes one
    /// capture per pose into the folder (atomically, so an interruption loses nothing).
    fn capture(
        &mut self,
        arm: &mut UrArm,
        imager: &mut dyn BoardImager,
        dir: &Path,
        plan: &CapturePlan,
        progress: &mut dyn FnMut(&str),
    ) -> anyhow::Result<()> {
        let Self {
            planner,
            world,
            layout,
            planned,
            folder,
            todo,
            run,
        } = self;
        let board = &layout.board;
        let cameras = folder.session().cameras.len();
        for (n, index) in todo.iter().enumerate() {
            if plan.limit.is_some_and(|l| run.captured >= l) {
                break;
            }
            let Some(goal) = planned.captures.get(*index).and_then(|c| c.joints) else {
                run.skipped.push((*index, "no joints planned".into()));
                continue;
            };
            let start = arm.state()?.joints.position;
            let mut why = String::from("no IK solution");
            let mut motion = None;
            for candidate in goal_candidates(&planner.model, &goal, &start) {
                match planner.plan_to_joints(&start, &candidate, world) {
                    Ok(m) => {
                        motion = Some(m);
                        break;
                    }
                    Err(e) => why = e.to_string(),
                }
            }
            let Some(motion) = motion else {
                run.skipped.push((*index, format!("no plan: {why}")));
                continue;
            };
            match arm.execute(&motion.trajectory)? {
                ExecutionOutcome::Completed { .. } => {}
                ExecutionOutcome::Stopped { by, cause, .. } => {
                    anyhow::bail!(
                        "pose {index}: the arm stopped ({by:?}: {cause:?}); the poses captured so \
                         far are kept, rerun to resume"
                    );
                }
            }
            if plan.settle_s > 0.0 {
                // Let the arm and the board stop swinging before the exposure.
                std::thread::sleep(std::time::Duration::from_secs_f64(plan.settle_s));
            }
            // What the robot reports, not what was planned, goes into the capture.
            let q = arm.state()?.joints.position;
            let base_from_flange = planner
                .model
                .fk_flange(&q)
                .context("the robot model has no flange link")?;
            let mut views = Vec::new();
            for (camera, img) in imager.images(&base_from_flange)? {
                // The image is kept beside the capture (to re-detect or inspect later).
                let png = grey_png(&img).context("encoding an IR image")?;
                calibration::capture::write_atomic(
                    &dir.join(format!("ir_pose_{index:04}_cam_{camera}.png")),
                    &png,
                )?;
                // A camera that does not find the board records no view.
                if let Ok(corners) = detect_board(&img, board, &DetectParams::default()) {
                    views.push(CameraView {
                        camera,
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
                "pose {:>2} ({}/{}): {seen} of {cameras} cameras found the board",
                index,
                n + 1,
                todo.len(),
            ));
        }
        Ok(())
    }
}

/// The arm configurations that put the flange where `goal` does, nearest to `start`
/// first: the poses are planned near home, but the arm arrives from the previous pose, and
/// the planned configuration can lie beyond a self-collision band of the wrist (a
/// different IK branch reaches the same board pose).
fn goal_candidates(model: &planner::RobotModel, goal: &Joints, start: &Joints) -> Vec<Joints> {
    let mut out = model
        .ik_near(&model.fk_tcp(goal), start)
        .unwrap_or_default();
    out.sort_by(|a, b| {
        cell_types::joints::max_abs_diff(a, start)
            .total_cmp(&cell_types::joints::max_abs_diff(b, start))
    });
    if out.is_empty() {
        out.push(*goal);
    }
    out
}

/// Runs the capture loop of `plan` in the simulated cell into the captures folder `dir`.
pub fn capture_in_sim(
    cfg: &CellConfig,
    dir: &Path,
    plan: CapturePlan,
    clock: Arc<cell_types::TickClock>,
    progress: &mut dyn FnMut(&str),
) -> anyhow::Result<CaptureRun> {
    let mut prepared = PreparedCapture::new(cfg, SimConfig::default_cell(), dir, &plan, progress)?;
    // The simulated cameras' true poses, so that `equact calibrate solve` can report its
    // error (the flange poses come from the captures themselves).
    let truth = Truth {
        seed: plan.seed,
        config: prepared.layout.clone(),
        base_from_flange: Vec::new(),
        intrinsics: Vec::new(),
    };
    calibration::capture::write_atomic(
        &dir.join(calibration::simulate::TRUTH_FILE),
        &serde_json::to_vec_pretty(&truth).context("encoding truth.json")?,
    )?;
    if prepared.todo.is_empty() {
        return Ok(prepared.run);
    }
    let task = TaskInstance::sample(
        TaskKind::parse("pick_fruit/strawberry").map_err(anyhow::Error::msg)?,
        plan.seed,
        cfg.workspace.table_height,
    );
    let mut cell = SimCell::start(cfg, task, plan.seed, clock)?;
    let layout = prepared.layout.clone();
    let mut imager = RenderedBoard {
        sim: &layout,
        rng: ChaCha8Rng::seed_from_u64(plan.seed ^ 0x1a_b0a2d),
        ir_sigma: plan.ir_sigma,
    };
    let result = prepared.capture(&mut cell.arm, &mut imager, dir, &plan, progress);
    let _ = cell.arm.stop();
    cell.controller.shutdown();
    result.map(|()| prepared.run)
}

/// The depth-stream intrinsics of a configured camera: the D455 factory values for its
/// mode, or the configuration's override.
pub fn configured_intrinsics(c: &CameraSection) -> Intrinsics {
    use cell_types::config::DepthMode as Configured;
    let mode = match c.mode {
        Configured::W848H480 => calibration::DepthMode::Wvga848x480,
        Configured::W1280H720 => calibration::DepthMode::Hd1280x720,
        Configured::W640H480 => calibration::DepthMode::Vga640x480,
    };
    let mut k = Intrinsics::d455_depth(mode);
    if let Some(o) = &c.intrinsics {
        k.fx = o.fx;
        k.fy = o.fy;
        k.ppx = o.ppx;
        k.ppy = o.ppy;
    }
    k
}

/// What a capture on a real cell plans with: the configured board and cameras, placed where
/// the existing calibration file says (a recalibration) or, for a first calibration, where
/// the configuration's `approx_position` / `approx_look_at` say.
pub fn real_cell_layout(cfg: &CellConfig, config_dir: &Path) -> anyhow::Result<SimConfig> {
    let mut sim = SimConfig::default_cell();
    if let Some(b) = &cfg.calibration.board {
        sim.board = BoardConfig {
            kind: b.kind,
            rows: b.rows,
            cols: b.cols,
            square_m: b.square_mm * 1e-3,
            spacing: b.spacing.unwrap_or(calibration::board::DEFAULT_TAG_SPACING),
        };
    }
    let previous = crate::real_cell::read_calibration(cfg, config_dir).ok();
    let mut cameras = Vec::with_capacity(cfg.cameras.len());
    let mut unplaced = Vec::new();
    for (i, c) in cfg.cameras.iter().enumerate() {
        let id = u8::try_from(i).context("more than 255 cameras")?;
        let pose = match (c.approx_position, c.approx_look_at) {
            (Some(p), Some(t)) => Some(look_at(Point3::from(p), Point3::from(t))),
            _ => previous
                .as_ref()
                .and_then(|cal| cal.cameras.iter().find(|k| k.id == id))
                .map(|k| k.base_from_camera),
        };
        match pose {
            Some(base_from_camera) => cameras.push(SimCamera {
                id,
                name: c.name.clone(),
                intrinsics: configured_intrinsics(c),
                base_from_camera,
            }),
            None => unplaced.push(c.name.clone()),
        }
    }
    if !unplaced.is_empty() {
        anyhow::bail!(
            "camera(s) {} have no placement to plan board poses with: give approx_position and \
             approx_look_at (base frame, m; measured roughly) in their [[cameras]] entries, or \
             name an existing calibration.toml",
            unplaced.join(", ")
        );
    }
    sim.cameras = cameras;
    sim.noise = calibration::SimNoise::none();
    Ok(sim)
}

/// Runs the capture loop of `plan` on a cell whose arm is reached by the configuration's
/// controller address, imaging the board with `cameras` (the configured D455s on a real
/// cell), into the captures folder `dir`. Nothing moves before the poses are planned and
/// the folder is open; an interrupted run resumes.
pub fn capture_on_cell(
    cfg: &CellConfig,
    config_dir: &Path,
    dir: &Path,
    plan: CapturePlan,
    cameras: &mut [Box<dyn DepthCamera>],
    clock: Arc<dyn Clock>,
    progress: &mut dyn FnMut(&str),
) -> anyhow::Result<CaptureRun> {
    let mut prepared = PreparedCapture::new(
        cfg,
        real_cell_layout(cfg, config_dir)?,
        dir,
        &plan,
        progress,
    )?;
    if prepared.todo.is_empty() {
        return Ok(prepared.run);
    }
    let ur = crate::preflight::ur_config(cfg).map_err(anyhow::Error::msg)?;
    let mut arm = UrArm::connect(ur, clock)
        .with_context(|| format!("connecting to the UR controller at {}", cfg.robot.host))?;
    let result = prepared.capture(&mut arm, &mut CameraIr { cameras }, dir, &plan, progress);
    let _ = arm.stop();
    result.map(|()| prepared.run)
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
