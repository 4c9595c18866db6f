//! The calibration board on the flange (issue 8 item 1): a planar set of corners with known
//! ids, either the inner corners of a chessboard or the tag corners of a Kalibr AprilGrid
//! (only their layout matters to the solver).
//!
//! Board frame (`cell_types::Board`): origin at corner 0, x along a row (increasing column),
//! y along a column (increasing row), z out of the printed face (towards a camera that sees
//! it); seen from the front, x points right and y up.
//! - Chessboard: corner `id = row * cols + col` sits at `(col * square, row * square, 0)`.
//! - AprilGrid (Kalibr's layout): `rows x cols` tag36h11 tags of side `square_m` (the tag's
//!   black border included), `spacing * square_m` apart, tag `t = row * cols + col` with its
//!   lower-left corner at `(col, row) * (1 + spacing) * square_m`; a black square of side
//!   `spacing * square_m` fills each gap crossing, so every tag corner is an X-junction.
//!   Corner `id = 4 t + k` is the tag's lower-left, lower-right, upper-right, upper-left
//!   corner for k = 0..3 (Kalibr's order), which lets a detector label partial views.

use nalgebra::Point3;
use serde::{Deserialize, Serialize};

use crate::error::CalibrationError;

/// What kind of target is printed (the configuration's `[calibration.board] kind`).
pub use cell_types::config::BoardKind;

/// Kalibr's default gap between AprilGrid tags, as a fraction of the tag size.
pub const DEFAULT_TAG_SPACING: f64 = 0.3;

pub use cell_types::config::{TAG36H11_CODES, TAG_SPACING_RANGE};

fn default_tag_spacing() -> f64 {
    DEFAULT_TAG_SPACING
}

/// A board's layout: for a chessboard `rows x cols` inner corners `square_m` apart, for an
/// AprilGrid `rows x cols` tags of side `square_m`, `spacing * square_m` apart.
#[derive(Copy, Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct BoardConfig {
    /// The printed target type.
    #[serde(default)]
    pub kind: BoardKind,
    /// Chessboard: inner-corner rows (along y); AprilGrid: tag rows.
    pub rows: u32,
    /// Chessboard: inner-corner columns (along x); AprilGrid: tag columns.
    pub cols: u32,
    /// Chessboard: square side (m); AprilGrid: tag side, black border included (m).
    pub square_m: f64,
    /// AprilGrid only: gap between tags as a fraction of the tag side (Kalibr's
    /// `tagSpacing`).
    #[serde(default = "default_tag_spacing")]
    pub spacing: f64,
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
            spacing: DEFAULT_TAG_SPACING,
        }
    }
}

impl BoardConfig {
    /// A 4 x 3-tag AprilGrid of 80 mm tags, 24 mm apart (43 x 34 cm printed): 8 mm bits,
    /// 3 px or more for a D455's 848 x 480 IR image up to about 1.1 m away.
    pub fn default_april_grid() -> Self {
        Self {
            kind: BoardKind::AprilGrid,
            rows: 3,
            cols: 4,
            square_m: 0.08,
            spacing: DEFAULT_TAG_SPACING,
        }
    }

    /// Checks the layout: at least 2x2 corners (chessboard) or tags (AprilGrid), at most
    /// 10 000 corners or 587 tags, positive finite sizes, an AprilGrid gap in
    /// [`TAG_SPACING_RANGE`].
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
        if self.kind == BoardKind::AprilGrid {
            if u64::from(self.rows) * u64::from(self.cols) > u64::from(TAG36H11_CODES) {
                return Err(CalibrationError::InvalidBoard {
                    why: format!(
                        "{} x {} tags is more than the {TAG36H11_CODES} tags of tag36h11",
                        self.rows, self.cols
                    ),
                });
            }
            if !(self.spacing.is_finite() && TAG_SPACING_RANGE.contains(&self.spacing)) {
                return Err(CalibrationError::InvalidBoard {
                    why: format!(
                        "tag spacing {} is outside {:?} of the tag size, where the AprilGrid detector works (Kalibr's default is {DEFAULT_TAG_SPACING})",
                        self.spacing, TAG_SPACING_RANGE
                    ),
                });
            }
        }
        Ok(())
    }

    /// Distance between neighbouring AprilGrid tags' lower-left corners (m).
    pub fn tag_pitch(&self) -> f64 {
        self.square_m * (1.0 + self.spacing)
    }

    /// Number of corners.
    pub fn corner_count(&self) -> usize {
        let grid = self.rows as usize * self.cols as usize;
        match self.kind {
            BoardKind::Chessboard => grid,
            BoardKind::AprilGrid => 4 * grid,
        }
    }

    /// Corner `id` in the board frame, or `None` for an id past the last corner.
    pub fn corner(&self, id: u32) -> Option<Point3<f64>> {
        if id as usize >= self.corner_count() {
            return None;
        }
        match self.kind {
            BoardKind::Chessboard => {
                let (row, col) = (id / self.cols, id % self.cols);
                Some(Point3::new(
                    f64::from(col) * self.square_m,
                    f64::from(row) * self.square_m,
                    0.0,
                ))
            }
            BoardKind::AprilGrid => {
                let (tag, k) = (id / 4, id % 4);
                let (row, col) = (tag / self.cols, tag % self.cols);
                let (dx, dy) = [(0.0, 0.0), (1.0, 0.0), (1.0, 1.0), (0.0, 1.0)][k as usize];
                let p = self.tag_pitch();
                Some(Point3::new(
                    f64::from(col) * p + dx * self.square_m,
                    f64::from(row) * p + dy * self.square_m,
                    0.0,
                ))
            }
        }
    }

    /// The printed pattern's extent in the board frame, `[min, max]` of x and y: the outer
    /// squares of a chessboard or the corner squares of an AprilGrid (white margin excluded).
    pub fn pattern_bounds(&self) -> [[f64; 2]; 2] {
        let (rows, cols) = (f64::from(self.rows), f64::from(self.cols));
        let s = self.square_m;
        match self.kind {
            BoardKind::Chessboard => [[-s, -s], [cols * s, rows * s]],
            BoardKind::AprilGrid => {
                let g = self.spacing * s;
                let p = self.tag_pitch();
                [[-g, -g], [cols * p, rows * p]]
            }
        }
    }

    /// All corners in id order, in the board frame.
    pub fn corners(&self) -> Vec<Point3<f64>> {
        (0..self.corner_count() as u32)
            .filter_map(|id| self.corner(id))
            .collect()
    }

    /// The board's centre (centre of the corner grid) in the board frame.
    pub fn centre(&self) -> Point3<f64> {
        let [lo, hi] = self.pattern_bounds();
        Point3::new((lo[0] + hi[0]) / 2.0, (lo[1] + hi[1]) / 2.0, 0.0)
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
            spacing: DEFAULT_TAG_SPACING,
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
                kind: BoardKind::Chessboard,
                rows,
                cols,
                square_m: sq,
                spacing: DEFAULT_TAG_SPACING,
            };
            assert!(matches!(
                b.validate(),
                Err(CalibrationError::InvalidBoard { .. })
            ));
        }
    }

    fn april_grid(rows: u32, cols: u32) -> BoardConfig {
        BoardConfig {
            kind: BoardKind::AprilGrid,
            rows,
            cols,
            square_m: 0.05,
            spacing: 0.3,
        }
    }

    #[test]
    fn april_grid_corners_go_round_each_tag_in_kalibr_order() {
        let b = april_grid(2, 3);
        b.validate().unwrap();
        assert_eq!(b.corner_count(), 24);
        let at = |id: u32| b.corner(id).unwrap();
        let near =
            |p: Point3<f64>, x: f64, y: f64| (p.x - x).abs() < 1e-12 && (p.y - y).abs() < 1e-12;
        // Tag 0: lower-left, lower-right, upper-right, upper-left.
        assert!(near(at(0), 0.0, 0.0));
        assert!(near(at(1), 0.05, 0.0));
        assert!(near(at(2), 0.05, 0.05));
        assert!(near(at(3), 0.0, 0.05));
        // Tag 4 is row 1, column 1: one pitch (65 mm) right and up.
        assert!(near(at(16), 0.065, 0.065));
        assert!(near(at(18), 0.115, 0.115));
        assert!(b.corner(24).is_none());
        // The pattern runs from the first corner square to the last one.
        let [lo, hi] = b.pattern_bounds();
        assert!((lo[0] + 0.015).abs() < 1e-12 && (hi[0] - 0.195).abs() < 1e-12);
        assert!((hi[1] - 0.13).abs() < 1e-12);
        let c = b.centre();
        assert!((c.x - 0.09).abs() < 1e-12 && (c.y - 0.0575).abs() < 1e-12);
    }

    #[test]
    fn april_grid_layouts_beyond_the_tag_family_or_with_bad_gaps_are_rejected() {
        for b in [
            april_grid(30, 20),
            BoardConfig {
                spacing: 0.0,
                ..april_grid(3, 4)
            },
            BoardConfig {
                spacing: f64::NAN,
                ..april_grid(3, 4)
            },
            BoardConfig {
                spacing: 1.5,
                ..april_grid(3, 4)
            },
        ] {
            let err = b.validate().unwrap_err();
            assert!(
                matches!(err, CalibrationError::InvalidBoard { .. }),
                "{b:?}"
            );
        }
    }
}
