//! The calibration crate's one error type.

use thiserror::Error;

/// What went wrong in a camera model, a calibration or the fusion pipeline.
#[derive(Debug, Error, PartialEq)]
#[non_exhaustive]
pub enum CalibrationError {
    /// A point at or behind the camera's image plane cannot be projected.
    #[error("point z = {z} m is not in front of the camera (z must be > 0); only project points the camera can see")]
    BehindCamera {
        /// The point's depth along the optical axis (m).
        z: f64,
    },
    /// A depth that must be positive and finite was not.
    #[error("depth {depth} m is not a positive finite number; zero and NaN depths mean \"no measurement\" and must be skipped before deprojection")]
    InvalidDepth {
        /// The offending depth (m).
        depth: f64,
    },
    /// A camera model parameter is unusable.
    #[error("camera intrinsics invalid: {what} = {value}; focal lengths and image size must be positive and finite, the principal point finite")]
    InvalidIntrinsics {
        /// Which parameter.
        what: &'static str,
        /// The offending value.
        value: f64,
    },
    /// Newton iteration failed to invert the lens distortion at this point.
    #[error("lens distortion could not be inverted at normalised ({x}, {y}) after {iterations} iterations; the point is far outside the lens's calibrated field of view")]
    DistortionNotInvertible {
        /// Normalised x.
        x: f64,
        /// Normalised y.
        y: f64,
        /// Iterations spent.
        iterations: usize,
    },
    /// An image's pixel buffer does not match its declared size, or the size does not match
    /// the camera model.
    #[error("camera {camera}: {what} is {got_width}x{got_height} but {expected_width}x{expected_height} was expected; check the stream mode against the calibration")]
    ImageSize {
        /// The camera id.
        camera: u8,
        /// Which image.
        what: &'static str,
        /// Expected width (px).
        expected_width: u32,
        /// Expected height (px).
        expected_height: u32,
        /// Width found.
        got_width: u32,
        /// Height found.
        got_height: u32,
    },
    /// A frame was expected from a camera the calibration lists, and none was given.
    #[error("no frame from camera {camera}; the calibration lists cameras {expected:?}: check that every camera is streaming (or drop it from calibration.toml)")]
    MissingFrame {
        /// The camera id with no frame.
        camera: u8,
        /// All camera ids the calibration lists.
        expected: Vec<u8>,
    },
    /// A frame or calibration entry names a camera the pipeline does not know.
    #[error("camera {camera} is unknown; known cameras are {known:?}: fix the camera id in calibration.toml or in the camera configuration")]
    UnknownCamera {
        /// The unknown id.
        camera: u8,
        /// The ids that are known.
        known: Vec<u8>,
    },
    /// The same camera appears twice.
    #[error("camera {camera} appears more than once; each camera id may appear once per calibration and once per set of frames")]
    DuplicateCamera {
        /// The repeated id.
        camera: u8,
    },
    /// A camera delivered a frame in which no pixel holds a usable depth.
    #[error("camera {camera} delivered a frame with no valid depth pixel ({width}x{height}); check that its lens is uncovered, the emitter is on and the scene is within range")]
    NoValidDepth {
        /// The camera id.
        camera: u8,
        /// Frame width (px).
        width: u32,
        /// Frame height (px).
        height: u32,
    },
    /// A fusion parameter is unusable.
    #[error("fusion parameter {what} = {value} is invalid: {why}")]
    InvalidParameter {
        /// Which parameter.
        what: &'static str,
        /// The offending value.
        value: f64,
        /// What a valid value looks like.
        why: &'static str,
    },
    /// The extrinsic transform of a camera is not a finite rigid transform.
    #[error("base_from_camera of camera {camera} is not a finite rigid transform; re-run `equact calibrate`")]
    BadExtrinsics {
        /// The camera id.
        camera: u8,
    },
    /// The fused cloud has fewer points than the policy needs.
    #[error("the fused cloud has {got} points but {needed} are needed; check that the cameras see the workspace and that the crop box and voxel size are right")]
    TooFewPoints {
        /// Points available.
        got: usize,
        /// Points needed.
        needed: usize,
    },
}
