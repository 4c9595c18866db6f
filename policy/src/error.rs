//! The one error type of the `policy` crate.

use std::path::PathBuf;

/// Everything that can go wrong in the policy crate, with the data needed to fix it.
#[derive(Debug, thiserror::Error)]
#[non_exhaustive]
pub enum PolicyError {
    /// A direction vector was zero or not finite, so it has no spherical-harmonic expansion.
    #[error("vector {value:?} has no direction (zero length or not finite); pass a finite, non-zero vector")]
    NoDirection {
        /// The offending vector.
        value: [f64; 3],
    },
    /// A matrix that must be a rotation is not one (not orthonormal, det != +1, or not finite).
    #[error("matrix is not a rotation (orthonormality/determinant error {error:.3e} > {tolerance:.1e}); re-orthonormalise it first")]
    NotARotation {
        /// Largest deviation from orthonormality or unit determinant.
        error: f64,
        /// The tolerance that was exceeded.
        tolerance: f64,
    },
    /// A spherical-harmonic degree outside what this code supports was asked for.
    #[error("degree l_max = {lmax} (m_max = {mmax}) is not supported; use 0 <= m_max <= l_max <= {max_supported}")]
    UnsupportedDegree {
        /// The requested maximum degree.
        lmax: usize,
        /// The requested maximum order.
        mmax: usize,
        /// The largest supported degree.
        max_supported: usize,
    },
    /// A point set was too small for the requested operation.
    #[error("{what}: need at least {needed} points, got {got}")]
    TooFewPoints {
        /// The operation that needed the points.
        what: &'static str,
        /// The number of points required.
        needed: usize,
        /// The number of points given.
        got: usize,
    },
    /// An instruction or the files of the language model could not be used.
    #[error("instruction: {what}")]
    BadInstruction {
        /// What was wrong, and which file.
        what: String,
    },
    /// Values a computation needs finite were not (NaN, infinite, or none at all).
    #[error("{what}: not finite; check the network's inputs and weights")]
    NonFinite {
        /// What was not finite.
        what: String,
    },
    /// The observed point cloud has no points at all.
    #[error("the point cloud is empty; the policy needs an observed scene (check the cameras and the crop)")]
    EmptyCloud,
    /// The point cloud is not in the frame the policy needs.
    #[error("the point cloud is in the {got} frame; the policy needs it in the robot base frame")]
    WrongFrame {
        /// The cloud's frame.
        got: String,
    },
    /// A point coordinate was NaN or infinite.
    #[error("{what}: point {index} has a non-finite coordinate {value:?}; drop or repair invalid points before calling")]
    NonFinitePoint {
        /// The operation that saw the point.
        what: &'static str,
        /// Index of the point in its input.
        index: usize,
        /// The point.
        value: [f32; 3],
    },
    /// A tensor or buffer had a shape other than the one required.
    #[error("tensor '{name}' has shape {got:?}, expected {expected:?}")]
    ShapeMismatch {
        /// Name of the tensor (a safetensors key or an argument name).
        name: String,
        /// The shape that was expected.
        expected: Vec<usize>,
        /// The shape found.
        got: Vec<usize>,
    },
    /// A tensor key was missing from a safetensors file.
    #[error("tensor '{name}' is missing from {file}; the file does not match the expected layout")]
    MissingTensor {
        /// The missing key.
        name: String,
        /// The file that was read.
        file: String,
    },
    /// A tensor had a dtype other than the one required.
    #[error("tensor '{name}' has dtype {got}, expected {expected}")]
    WrongDtype {
        /// Name of the tensor.
        name: String,
        /// The expected dtype.
        expected: &'static str,
        /// The dtype found.
        got: String,
    },
    /// An index stored in a tensor points outside the range it indexes.
    #[error("index tensor '{name}' holds {value}, outside 0..{len}")]
    IndexOutOfRange {
        /// Name of the index tensor.
        name: String,
        /// The offending value.
        value: i64,
        /// The size of the indexed axis.
        len: usize,
    },
    /// A file could not be read.
    #[error("cannot read {path}: {source}")]
    Io {
        /// The file.
        path: PathBuf,
        /// The underlying error.
        source: std::io::Error,
    },
    /// A safetensors container could not be parsed.
    #[error("{path} is not a valid safetensors file: {message}")]
    Safetensors {
        /// The file.
        path: PathBuf,
        /// What the parser said.
        message: String,
    },
    /// A policy configuration that cannot run (sampling, point counts, boxes).
    #[error("invalid policy configuration: {0}")]
    BadConfig(String),
    /// A JSON sidecar could not be parsed or lacks a required field.
    #[error("sidecar {path}: {message}")]
    Sidecar {
        /// The file.
        path: PathBuf,
        /// What was wrong.
        message: String,
    },
}

/// Result alias of the policy crate.
pub type Result<T> = std::result::Result<T, PolicyError>;
