//! `equact calibrate ...`: camera-to-robot calibration (`calibration` crate): simulated
//! captures with known truth, and the joint bundle adjustment over a captures folder.

use std::path::PathBuf;

use anyhow::Context;
use calibration::simulate::{load_truth, simulate, SimConfig, SimNoise};
use calibration::solve::{solve, SolveOptions};
use clap::{Args, Subcommand, ValueEnum};

/// Arguments of `equact calibrate`.
#[derive(Args, Debug)]
pub struct CalibrateArgs {
    /// What to do.
    #[command(subcommand)]
    pub command: CalibrateCommand,
}

/// Noise of simulated captures.
#[derive(Copy, Clone, Debug, PartialEq, Eq, ValueEnum)]
pub enum NoiseChoice {
    /// Exact corners and robot poses.
    None,
    /// 0.5 px corners, robot 0.5 mm / 0.05°.
    Realistic,
    /// Corners detected in rendered IR images (grey-level noise), realistic robot noise.
    Ir,
}

/// The simulated cell's calibration target.
#[derive(Copy, Clone, Debug, PartialEq, Eq, ValueEnum)]
pub enum BoardChoice {
    /// 7 x 10 inner corners, 35 mm squares.
    Chessboard,
    /// Kalibr AprilGrid: 4 x 3 tag36h11 tags of 80 mm, 0.3 spacing.
    AprilGrid,
}

/// Subcommands of `equact calibrate`.
#[derive(Subcommand, Debug)]
pub enum CalibrateCommand {
    /// Write simulated captures of the simulated cell (with `truth.json`) into a folder;
    /// an interrupted run resumes.
    Simulate {
        /// The captures folder.
        #[arg(long, default_value = "captures")]
        out: PathBuf,
        /// Seed of the robot poses and the noise.
        #[arg(long, default_value_t = 0)]
        seed: u64,
        /// Number of robot poses.
        #[arg(long, default_value_t = 30)]
        poses: usize,
        /// Noise model.
        #[arg(long, value_enum, default_value_t = NoiseChoice::Realistic)]
        noise: NoiseChoice,
        /// Cameras unlike their recorded factory values: fx, fy 1 % and ppx, ppy 3 px off,
        /// depth 1.002 z + 2 mm (solve with --refine-intrinsics to recover them).
        #[arg(long)]
        camera_errors: bool,
        /// The target on the flange.
        #[arg(long, value_enum, default_value_t = BoardChoice::Chessboard)]
        board: BoardChoice,
    },
    /// Move the arm through planned board poses and capture the board in every camera's IR
    /// image (the built-in simulated cell, or the real cell of --config; resumes an
    /// interrupted run).
    Capture {
        /// The cell configuration; the built-in simulated cell when omitted.
        #[arg(long)]
        config: Option<PathBuf>,
        /// The captures folder.
        #[arg(long, default_value = "captures")]
        out: PathBuf,
        /// Seed of the pose plan.
        #[arg(long, default_value_t = 0)]
        seed: u64,
        /// Number of poses.
        #[arg(long, default_value_t = 30)]
        poses: usize,
        /// Capture at most this many new poses in this run.
        #[arg(long)]
        limit: Option<usize>,
        /// On a real cell, start moving without asking (interactive runs ask for Enter).
        #[arg(long)]
        yes: bool,
        /// The simulated cell's speed.
        #[command(flatten)]
        sim: super::args::SimSpeedArgs,
    },
    /// Solve a captures folder: per-camera base_from_camera and flange_from_board in one
    /// bundle adjustment; prints the report and writes calibration.toml.
    Solve {
        /// The captures folder.
        #[arg(long, default_value = "captures")]
        captures: PathBuf,
        /// Where to write the calibration.
        #[arg(long, default_value = "calibration.toml")]
        out: PathBuf,
        /// Print the report as JSON.
        #[arg(long)]
        json: bool,
        /// Also solve each camera's fx, fy, ppx, ppy instead of trusting the factory values.
        #[arg(long)]
        refine_intrinsics: bool,
    },
}

/// Runs `equact calibrate`.
pub fn run(args: CalibrateArgs) -> anyhow::Result<()> {
    match args.command {
        CalibrateCommand::Simulate {
            out,
            seed,
            poses,
            noise,
            camera_errors,
            board,
        } => {
            let mut cfg = match board {
                BoardChoice::Chessboard => SimConfig::default_cell(),
                BoardChoice::AprilGrid => SimConfig::default_cell()
                    .with_board(calibration::BoardConfig::default_april_grid()),
            };
            cfg.poses = poses;
            if camera_errors {
                cfg.camera_errors = calibration::simulate::CameraErrors::typical();
            }
            match noise {
                NoiseChoice::None => cfg.noise = SimNoise::none(),
                NoiseChoice::Realistic => cfg.noise = SimNoise::realistic(),
                NoiseChoice::Ir => {
                    cfg.noise = SimNoise::realistic();
                    cfg.ir_noise = Some(2.0);
                }
            }
            let (set, _) = simulate(&cfg, seed, &out)
                .with_context(|| format!("simulating captures into {}", out.display()))?;
            println!(
                "{} poses with {} camera views in {} (truth in truth.json)",
                set.captures.len(),
                set.captures.iter().map(|c| c.views.len()).sum::<usize>(),
                out.display()
            );
            Ok(())
        }
        CalibrateCommand::Capture {
            config,
            out,
            seed,
            poses,
            limit,
            yes,
            sim,
        } => {
            let cfg = super::config::load(config.as_ref())?;
            let mut progress = |line: &str| eprintln!("{line}");
            let real = cfg.robot.backend == cell_types::config::RobotBackend::Ur;
            sim.refuse_on_real_cell(real)?;
            let run = if real {
                let clock = std::sync::Arc::new(cell_types::SystemClock::new());
                let config_dir = super::config::config_dir(config.as_ref());
                let mut cameras = equact::real_cell::open_cameras(&cfg)?;
                equact::real_cell::confirm_motion(yes)?;
                equact::calibrate_capture::capture_on_cell(
                    &cfg,
                    &config_dir,
                    &out,
                    equact::calibrate_capture::CapturePlan {
                        seed,
                        poses,
                        limit,
                        ir_sigma: 0.0,
                        settle_s: 0.5,
                    },
                    &mut cameras,
                    clock,
                    &mut progress,
                )?
            } else {
                let clock = std::sync::Arc::new(cell_types::TickClock::new(sim.speed)?);
                equact::calibrate_capture::capture_in_sim(
                    &cfg,
                    &out,
                    equact::calibrate_capture::CapturePlan {
                        seed,
                        poses,
                        limit,
                        ir_sigma: 2.0,
                        settle_s: 0.0,
                    },
                    clock,
                    &mut progress,
                )?
            };
            for (i, why) in &run.skipped {
                eprintln!("pose {i} skipped: {why}");
            }
            println!(
                "{} new poses captured, {} kept from before, {} of {} planned; next: equact calibrate solve --captures {}",
                run.captured,
                run.resumed,
                run.captured + run.resumed,
                run.planned,
                out.display()
            );
            Ok(())
        }
        CalibrateCommand::Solve {
            captures,
            out,
            json,
            refine_intrinsics,
        } => {
            let set = calibration::capture::load_captures(&captures)?;
            eprintln!(
                "solving {} poses from {} ...",
                set.captures.len(),
                captures.display()
            );
            let opts = SolveOptions {
                refine_intrinsics,
                ..SolveOptions::default()
            };
            let solution = solve(&set, &opts)?;
            let mut report = solution.report();
            let truth = load_truth(&captures).ok();
            let camera_errors = truth.as_ref().is_some_and(|t| {
                t.config.camera_errors != calibration::simulate::CameraErrors::default()
            });
            if camera_errors {
                eprintln!(
                    "no overlap check or picture: the captures were simulated with camera \
                     errors, which the simulated cell's rendered depth frames do not have"
                );
            } else if let Some(truth) = &truth {
                // Simulated captures: render the simulated cell's cameras at their true poses
                // and check and draw the calibrated clouds' overlap.
                let picture = out.with_extension("overlay.png");
                report.overlap = overlap_picture(&solution, truth, &picture)?;
                eprintln!(
                    "wrote {} (the three clouds, coloured by camera)",
                    picture.display()
                );
            } else {
                eprintln!(
                    "no overlap check or picture: they need depth frames of the calibrated \
                     cameras, which this build captures only in the simulated cell"
                );
            }
            if json {
                println!("{}", report.to_json());
            } else {
                println!("{report}");
            }
            if let Some(truth) = &truth {
                for (id, m, rad) in solution.errors_to(truth) {
                    eprintln!(
                        "camera {id}: {:.3} mm, {:.4} deg from the simulated truth",
                        m * 1e3,
                        rad.to_degrees()
                    );
                }
                let depth = truth.depth();
                for c in &solution.cameras {
                    let (Some(t), k) = (truth.intrinsics(c.id), c.intrinsics) else {
                        continue;
                    };
                    eprintln!(
                        "camera {}: intrinsics off the truth by fx {:+.2}, fy {:+.2}, ppx {:+.2}, ppy {:+.2} px; depth scale {:+.5}, offset {:+.2} mm",
                        c.id,
                        k.fx - t.fx,
                        k.fy - t.fy,
                        k.ppx - t.ppx,
                        k.ppy - t.ppy,
                        c.depth_correction.scale - depth.scale,
                        (c.depth_correction.offset_m - depth.offset_m) * 1e3
                    );
                }
            }
            solution.write_calibration_toml(&out)?;
            eprintln!("wrote {}", out.display());
            Ok(())
        }
    }
}

/// Renders the simulated cell's cameras at their true poses, deprojects with the solved
/// calibration, returns the overlap check and writes the overlay picture to `path`.
fn overlap_picture(
    solution: &calibration::Solution,
    truth: &calibration::Truth,
    path: &std::path::Path,
) -> anyhow::Result<Vec<calibration::OverlapPair>> {
    use calibration::fusion::{Bounds, FusionParams, FusionPipeline};
    let mut rig = hil_sim::depth_camera::default_rig(0);
    for c in &mut rig {
        if let Some(t) = truth.config.cameras.iter().find(|t| t.id == c.id) {
            c.base_from_camera = t.base_from_camera;
            c.intrinsics = t.intrinsics;
        }
    }
    let geometry = hil_sim::scene::Scene::default_cell().build()?;
    let frames = hil_sim::depth_camera::render_rig(&rig, &geometry, 0, std::time::Duration::ZERO)?;
    // A part of the scene every camera sees, with more than one plane in it.
    let region = Bounds {
        min: [0.42, 0.05, -0.12],
        max: [0.68, 0.31, 0.2],
    };
    let pipe = FusionPipeline::new(solution.calibration(), FusionParams::default())?;
    let overlap = calibration::overlap_check(&pipe, &frames, &region, 0.01)?;
    let img = calibration::overlay_image(
        &pipe,
        &frames,
        &region,
        &calibration::Intrinsics::d455_depth(calibration::DepthMode::Vga640x480),
        nalgebra::Point3::new(0.9, 0.45, 0.45),
        nalgebra::Point3::new(0.55, 0.18, -0.02),
    )?;
    super::perceive::write_png_rgb(path, &img)?;
    Ok(overlap)
}
