//! The calibration board on the flange (issue 8 item 1): a planar grid of corners (the inner
//! corners of a chessboard, or the corners of a ChArUco/AprilGrid board; only their layout
//! matters to the solver).
//!
//! Board frame (`cell_types::Board`): origin at corner 0, x along a row (increasing column),
//! y along a column (increasing row), z out of the printed face (towards a camera that sees
//! it). Corner `id = row * cols + col` sits at `(col * square, row * square, 0)`.

use nalgebra::Point3;
use serde::{Deserialize, Serialize};

use crate::error::CalibrationError;

/// What kind of target is printed (informational; the solver only uses the corner layout).
#[derive(Copy, Clone, Debug, PartialEq, Eq, Serialize, Deserialize, Default)]
#[serde(rename_all = "snake_case")]
pub enum BoardKind {
    /// A plain chessboard: corners are its inner corners.
    Chessboard,
    /// A ChArUco board: corners are the chessboard corners, identified by the markers.
    #[default]
    Charuco,
    /// A Kalibr AprilGrid: corners are tag corners on a regular grid.
    AprilGrid,
}

/// A board's corner layout: `rows x cols` corners at `square_m` spacing.
#[derive(Copy, Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct BoardConfig {
    /// The printed target type.
    #[serde(default)]
    pub kind: BoardKind,
    /// Corner rows (inner corners along y).
    pub rows: u32,
    /// Corner columns (inner corners along x).
    pub cols: u32,
    /// Corner spacing (m).
    pub square_m: f64,
}

impl Default for BoardConfig {
    /// A 7 x 10-corner chessboard of 35 mm squares (8 x 11 squares, 38.5 x 28 cm printed):
    /// `rows + cols` odd, so a plain chessboard's half-turn is told apart by
    /// [`crate::detect::detect_chessboard`].
    fn default() -> Self {
        Self {
            kind: BoardKind::Chessboard,
            rows: 7,
            cols: 10,
            square_m: 0.035,
        }
    }
}

impl BoardConfig {
    /// Checks the layout: at least 2x2 corners, at most 10 000, positive finite spacing.
    pub fn validate(&self) -> Result<(), CalibrationError> {
        if self.rows < 2 || self.cols < 2 {
            return Err(CalibrationError::InvalidBoard {
                why: format!("{} x {} corners is less than 2 x 2", self.rows, self.cols),
            });
        }
        if u64::from(self.rows) * u64::from(self.cols) > 10_000 {
            return Err(CalibrationError::InvalidBoard {
                why: format!("{} x {} corners is more than 10 000", self.rows, self.cols),
            });
        }
        if !(self.square_m.is_finite() && self.square_m > 0.0) {
            return Err(CalibrationError::InvalidBoard {
                why: format!("square size {} m", self.square_m),
            });
        }
        Ok(())
    }

    /// Number of corners.
    pub fn corner_count(&self) -> usize {
        self.rows as usize * self.cols as usize
    }

    /// Corner `id` in the board frame, or `None` for an id past the last corner.
    pub fn corner(&self, id: u32) -> Option<Point3<f64>> {
        if id as usize >= self.corner_count() {
            return None;
        }
        let (row, col) = (id / self.cols, id % self.cols);
        Some(Point3::new(
            f64::from(col) * self.square_m,
            f64::from(row) * self.square_m,
            0.0,
        ))
    }

    /// All corners in id order, in the board frame.
    pub fn corners(&self) -> Vec<Point3<f64>> {
        (0..self.corner_count() as u32)
            .filter_map(|id| self.corner(id))
            .collect()
    }

    /// The board's centre (centre of the corner grid) in the board frame.
    pub fn centre(&self) -> Point3<f64> {
        Point3::new(
            f64::from(self.cols - 1) * self.square_m / 2.0,
            f64::from(self.rows - 1) * self.square_m / 2.0,
            0.0,
        )
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn corners_are_row_major_on_the_grid() {
        let b = BoardConfig {
            kind: BoardKind::Chessboard,
            rows: 3,
            cols: 4,
            square_m: 0.02,
        };
        b.validate().unwrap();
        assert_eq!(b.corner_count(), 12);
        assert_eq!(b.corner(0).unwrap(), Point3::new(0.0, 0.0, 0.0));
        let c5 = b.corner(5).unwrap();
        assert!((c5.x - 0.02).abs() < 1e-15 && (c5.y - 0.02).abs() < 1e-15);
        let last = b.corner(11).unwrap();
        assert!((last.x - 0.06).abs() < 1e-15 && (last.y - 0.04).abs() < 1e-15);
        assert!(b.corner(12).is_none());
        assert_eq!(b.corners().len(), 12);
        assert!((b.centre().x - 0.03).abs() < 1e-15);
    }

    #[test]
    fn bad_boards_are_rejected() {
        for (rows, cols, sq) in [
            (1, 5, 0.03),
            (5, 5, 0.0),
            (5, 5, f64::NAN),
            (200, 200, 0.01),
        ] {
            let b = BoardConfig {
                kind: BoardKind::Charuco,
                rows,
                cols,
                square_m: sq,
            };
            assert!(matches!(
                b.validate(),
                Err(CalibrationError::InvalidBoard { .. })
            ));
        }
    }
}
