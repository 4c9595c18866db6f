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
    /// A calibration board description is unusable.
    #[error("calibration board invalid: {why}; fix the [board] entry (rows and cols count inner corners, at least 2 each; square size in metres, > 0)")]
    InvalidBoard {
        /// What is wrong.
        why: String,
    },
    /// Reading or writing a captures folder, a report or `calibration.toml` failed.
    #[error(
        "{path}: {why}; check the path and free space; files already captured are left as they are"
    )]
    CaptureIo {
        /// The file or folder.
        path: String,
        /// The operating system's or parser's message.
        why: String,
    },
    /// A captures folder holds files that do not fit together.
    #[error("captures in {path} are inconsistent: {why}; {what_to_do}")]
    InconsistentCaptures {
        /// The file (or folder) at fault.
        path: String,
        /// What does not fit.
        why: String,
        /// What to do about it.
        what_to_do: String,
    },
    /// Too few robot poses for a calibration.
    #[error("only {got} usable robot poses, at least {needed} are needed; capture {more} more poses (25-40 diverse poses recommended), the ones already captured are kept")]
    TooFewPoses {
        /// Usable poses found.
        got: usize,
        /// Poses needed.
        needed: usize,
        /// How many more to capture.
        more: usize,
    },
    /// A camera saw the board in too few poses.
    #[error("camera {camera} saw the board in {views} poses, at least {needed} are needed; capture poses where the board faces camera {camera} fully inside its image (tilted less than 60 degrees to its line of sight)")]
    BoardNotSeen {
        /// The camera id.
        camera: u8,
        /// Poses in which it saw enough corners.
        views: usize,
        /// Poses needed.
        needed: usize,
    },
    /// The robot poses seen by a camera do not rotate the board about two different axes.
    #[error("camera {camera}: the flange rotations of its {views} poses are degenerate ({why}); hand-eye needs rotations of at least {min_angle_deg} degrees about two different axes: capture poses that tilt the board about its x and y axes and turn it about its normal")]
    NoRotationDiversity {
        /// The camera id.
        camera: u8,
        /// Poses the camera saw.
        views: usize,
        /// What is missing.
        why: String,
        /// Minimum relative rotation asked for (degrees).
        min_angle_deg: f64,
    },
    /// The board pose in one view could not be estimated.
    #[error("camera {camera}, pose {pose}: board pose estimation failed ({why}); delete or re-capture that pose")]
    PoseEstimation {
        /// The camera id.
        camera: u8,
        /// The capture index.
        pose: usize,
        /// Why.
        why: String,
    },
    /// The least-squares solver did not converge.
    #[error("calibration solver failed in {stage}: {why}; check the captures for outliers (wrong joint files, misdetected boards) or add poses")]
    SolverFailed {
        /// Which stage.
        stage: &'static str,
        /// Why.
        why: String,
    },
    /// No complete board was found in an image.
    #[error("board not found in the IR image: {why}; keep the whole board inside the image, facing the camera (tilted less than 60 degrees), evenly lit with the IR projector off")]
    BoardNotFound {
        /// What the detector saw.
        why: String,
    },
}
