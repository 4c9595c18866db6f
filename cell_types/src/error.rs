//! Errors raised when a value of the shared vocabulary is built from bad data.

use thiserror::Error;

/// Why a cell type could not be built from the data given.
#[derive(Debug, Error, PartialEq)]
#[non_exhaustive]
pub enum CellTypesError {
    /// A value that must be finite was NaN or infinite.
    #[error(
        "{what} is not finite ({value}); check the source of this value (sensor, file, solver)"
    )]
    NotFinite {
        /// Which value.
        what: &'static str,
        /// The offending number.
        value: f64,
    },
    /// Two arrays that must have the same length do not.
    #[error("{what}: expected {expected} entries, got {got}")]
    LengthMismatch {
        /// Which array.
        what: &'static str,
        /// Length required.
        expected: usize,
        /// Length found.
        got: usize,
    },
    /// A trajectory's samples are not evenly spaced at its period, or its period is not positive.
    #[error("trajectory sample {index} is at t = {t} s but the period {period} s puts it at {expected} s; resample the trajectory at the controller rate")]
    UnevenTrajectory {
        /// Sample index.
        index: usize,
        /// Its time stamp.
        t: f64,
        /// Where it should be.
        expected: f64,
        /// The trajectory period.
        period: f64,
    },
    /// A period, rate or width that must be positive was not.
    #[error("{what} must be positive, got {value}")]
    NotPositive {
        /// Which value.
        what: &'static str,
        /// The offending number.
        value: f64,
    },
    /// A value outside its allowed range.
    #[error("{what} = {value} is outside [{min}, {max}]")]
    OutOfRange {
        /// Which value.
        what: &'static str,
        /// The offending number.
        value: f64,
        /// Lower bound.
        min: f64,
        /// Upper bound.
        max: f64,
    },
}

/// Checks that `value` is finite, naming it in the error.
pub fn ensure_finite(what: &'static str, value: f64) -> Result<f64, CellTypesError> {
    if value.is_finite() {
        Ok(value)
    } else {
        Err(CellTypesError::NotFinite { what, value })
    }
}
