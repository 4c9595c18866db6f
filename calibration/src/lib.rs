//! D455 camera models, board detection, hand-eye and joint bundle adjustment, cloud fusion.
//!
//! Modules: [`camera`] (the D455 camera model, issue 7 item 1), [`fusion`] (the fused point
//! cloud, issue 7 item 3), [`view`] (PLY export and point splats, issue 7 item 5), and the
//! camera-to-robot calibration of issue 8: [`board`] (the target on the flange),
//! [`capture`] (captures and the resumable captures folder), [`detect`] (board corners in IR
//! images: chessboards, and Kalibr AprilGrids through [`aprilgrid`]), [`simulate`](mod@simulate) (synthetic captures with known truth), [`geometry`] (PnP,
//! closed-form hand-eye), [`solve`](mod@solve) (the joint bundle adjustment) and [`report`] (report,
//! overlap check, `calibration.toml`).
//!
//! The calibration API, as the CLI uses it:
//! ```no_run
//! # fn main() -> Result<(), calibration::CalibrationError> {
//! use calibration::{load_captures, simulate, solve, SimConfig, SolveOptions};
//! let dir = std::path::Path::new("captures");
//! simulate(&SimConfig::default_cell(), 7, dir)?;          // equact calibrate simulate
//! let captures = load_captures(dir)?;                      // equact calibrate solve
//! let solution = solve(&captures, &SolveOptions::default())?;
//! println!("{}", solution.report());                       // text; .to_json() for JSON
//! solution.write_calibration_toml(&dir.join("calibration.toml"))?;
//! # Ok(()) }
//! ```
//! A real capture (`equact calibrate capture`) opens a [`CaptureFolder`] with a
//! [`Session`] (resuming where it stopped: [`CaptureFolder::missing`]), and per robot pose
//! writes a [`Capture`] of the joint state, the flange pose and
//! [`detect::view_from_frame`] of each camera's frame. Before solving, the CLI checks the
//! joint files against the planner's FK with [`CaptureSet::check_joints`] (this crate may
//! not depend on the planner).
//!
//! Libraries: `nalgebra` (the workspace's matrix library) for geometry; the fusion works on
//! depth images pixel by pixel without an image library. AprilGrid targets are detected
//! with the `aprilgrid` crate (pure Rust, Kalibr's detector: saddle points, quads, tag36h11
//! decoding), fed through `image`'s `GrayImage`; the chessboard detector is our own. The bundle
//! adjustment uses `levenberg-marquardt` (rust-cv; a port of MINPACK's `lmder` on nalgebra):
//! a well-tested trust-region LM with pivoted QR and column scaling, which is what a dense
//! problem of a few dozen unknowns needs; we supply the residuals and the analytic
//! Jacobian. (argmin would also do, but carries a much larger framework for one solver;
//! sparse solvers such as a Ceres port are not needed at this size because the per-pose
//! robot corrections are eliminated by variable projection.) `serde_json` and `toml` write
//! the captures, report and calibration files; `rand_distr` draws the simulated noise.

pub mod aprilgrid;
pub mod board;
pub mod camera;
pub mod capture;
pub mod detect;
pub mod error;
pub mod fusion;
pub mod geometry;
pub mod report;
pub mod simulate;
pub mod solve;
pub mod view;

pub use board::{BoardConfig, BoardKind};
pub use camera::{DepthCorrection, DepthMode, Distortion, Intrinsics};
pub use capture::{
    load_captures, CameraInfo, CameraView, Capture, CaptureFolder, CaptureSet, Corner, DepthSample,
    PixelConvention, Session,
};
pub use error::CalibrationError;
pub use fusion::{CameraCalibration, CellCalibration, FusionParams, FusionPipeline};
pub use report::{overlap_check, overlay_image, read_calibration_toml, OverlapPair, Report};
pub use simulate::{load_truth, simulate, SimConfig, SimNoise, Truth};
pub use solve::{solve, Solution, SolveOptions};
