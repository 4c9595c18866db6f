//! D455 camera models, board detection, hand-eye and joint bundle adjustment, cloud fusion.
//!
//! Modules: [`camera`] (the D455 camera model, issue 7 item 1), [`fusion`] (the fused point
//! cloud, issue 7 item 3),
//! [`view`] (PLY export and point splats, issue 7 item 5). Board detection and the bundle adjustment (issue 8) build on
//! [`camera::Intrinsics`] and the IR images of `cell_types::CameraFrame`.
//!
//! Libraries: `nalgebra` (the workspace's matrix library) for geometry; no image-processing
//! library is needed because the fusion works on depth images pixel by pixel.

pub mod board;
pub mod camera;
pub mod capture;
pub mod error;
pub mod fusion;
pub mod geometry;
pub mod simulate;
pub mod solve;
pub mod view;

pub use board::{BoardConfig, BoardKind};
pub use camera::{DepthMode, Distortion, Intrinsics};
pub use capture::{
    load_captures, CameraInfo, CameraView, Capture, CaptureFolder, CaptureSet, Corner, DepthSample,
    PixelConvention, Session,
};
pub use error::CalibrationError;
pub use fusion::{CameraCalibration, CellCalibration, FusionParams, FusionPipeline};
