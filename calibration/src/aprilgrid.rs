//! Kalibr AprilGrid targets (issue 8 item 1): the printed pattern (for the renderer) and
//! the detection of its tag corners in IR images.
//!
//! Detection uses the `aprilgrid` crate (pure Rust, a port of Kalibr's AprilGrid detector):
//! it finds the saddle points where each tag's black border meets the black squares in the
//! gaps, groups them into quads and decodes each quad's tag36h11 code, so every corner comes
//! with its tag's id and partial views of the board are usable. The pattern drawn by
//! [`level`] uses the same code table (`aprilgrid::tag_families::T36H11`); a peer test checks
//! it bit for bit against OpenCV's drawing of the same tags.
//!
//! Pixel convention: the crate samples pixel `(u, v)` at integer coordinates, i.e. (0, 0)
//! is the centre of the top-left pixel, which is this crate's convention; the test of
//! rendered boards measures no offset beyond the corner noise.

use std::panic::{catch_unwind, AssertUnwindSafe};

use aprilgrid::detector::{DetectorParams, TagDetector};
use aprilgrid::tag_families::T36H11;
use aprilgrid::TagFamily;
use cell_types::Image;
use image::{DynamicImage, GrayImage};

use crate::board::BoardConfig;
use crate::capture::Corner;
use crate::detect::IrLevels;
use crate::error::CalibrationError;

/// Bits across a tag36h11 tag as Kalibr prints it: 6 data bits inside a 2-bit black border.
const TAG_BITS: f64 = 10.0;

/// Fewest tags a view must show: two tags give eight corners, enough for a pose.
pub const MIN_TAGS: usize = 2;

/// Whether data bit (`row`, `col`) of `code` (row 0 at the tag's top, as printed) is white:
/// the code's most significant of 36 bits is the top-left one, row by row.
fn data_bit_white(code: u64, row: u32, col: u32) -> bool {
    (code >> (35 - (row * 6 + col))) & 1 == 1
}

/// The printed cells of tag `tag` (10 x 10: a 2-cell black border round 6 x 6 data bits),
/// row 0 at the top as printed, `true` for white; `None` past the family's last tag.
pub fn tag_cells(tag: usize) -> Option<[[bool; 10]; 10]> {
    let code = *T36H11.get(tag)?;
    Some(std::array::from_fn(|r| {
        std::array::from_fn(|c| {
            let (r, c) = (r as u32, c as u32);
            (2..8).contains(&r) && (2..8).contains(&c) && data_bit_white(code, r - 2, c - 2)
        })
    }))
}

/// Grey level of an AprilGrid at board-frame point `(x, y)`, or `None` off the board (its
/// white margin is one gap wide around the corner squares).
pub fn level(board: &BoardConfig, x: f64, y: f64, levels: &IrLevels) -> Option<f64> {
    let s = board.square_m;
    let g = board.spacing * s;
    let pitch = board.tag_pitch();
    let [lo, hi] = board.pattern_bounds();
    if x < lo[0] - g || y < lo[1] - g || x > hi[0] + g || y > hi[1] + g {
        return None;
    }
    let dark = f64::from(levels.dark);
    let light = f64::from(levels.light);
    // Shift by one gap so that cell i holds the gap before tag i, then tag i.
    let (cx, cy) = ((x + g) / pitch, (y + g) / pitch);
    let (ix, iy) = (cx.floor(), cy.floor());
    let (ox, oy) = ((cx - ix) * pitch, (cy - iy) * pitch);
    let (cols, rows) = (f64::from(board.cols), f64::from(board.rows));
    let in_grid_x = (0.0..=cols).contains(&ix);
    let in_grid_y = (0.0..=rows).contains(&iy);
    let (gap_x, gap_y) = (ox < g, oy < g);
    if !(in_grid_x && in_grid_y) {
        return Some(light);
    }
    if gap_x && gap_y {
        return Some(dark);
    }
    if gap_x || gap_y || ix >= cols || iy >= rows {
        return Some(light);
    }
    // Inside tag (ix, iy): bit cell, counted from the tag's top-left as printed (board y up).
    let bx = (((ox - g) / s) * TAG_BITS)
        .floor()
        .clamp(0.0, TAG_BITS - 1.0) as u32;
    let by_up = (((oy - g) / s) * TAG_BITS)
        .floor()
        .clamp(0.0, TAG_BITS - 1.0) as u32;
    let by = 9 - by_up;
    if !(2..8).contains(&bx) || !(2..8).contains(&by) {
        return Some(dark);
    }
    let tag = iy as usize * board.cols as usize + ix as usize;
    let white = T36H11
        .get(tag)
        .is_some_and(|code| data_bit_white(*code, by - 2, bx - 2));
    Some(if white { light } else { dark })
}

/// Detects the tag corners of the AprilGrid `board` in an IR image; returns them with their
/// ids (`4 * tag + k`, see [`crate::board`]). Tags whose id is past the board's are ignored
/// (another target in view).
pub fn detect_april_grid(
    img: &Image<u8>,
    board: &BoardConfig,
) -> Result<Vec<Corner>, CalibrationError> {
    board.validate()?;
    let not_found = |why: String| CalibrationError::BoardNotFound { why };
    if !img.is_consistent() {
        return Err(not_found("the image buffer does not match its size".into()));
    }
    if img.width < 16 || img.height < 16 {
        return Err(not_found(format!(
            "a {} x {} image is too small to hold an AprilGrid",
            img.width, img.height
        )));
    }
    let gray = GrayImage::from_raw(img.width, img.height, img.data.clone())
        .ok_or_else(|| not_found("the image buffer does not match its size".into()))?;
    // aprilgrid 0.8 does not read the spacing yet (its grid search assumes 0.3, hence
    // `TAG_SPACING_RANGE`); it is passed for the versions that will.
    let params = DetectorParams {
        tag_spacing_ratio: board.spacing as f32,
        ..DetectorParams::default_params()
    };
    let detector = TagDetector::new(&TagFamily::T36H11, Some(params));
    let image = DynamicImage::ImageLuma8(gray);
    // The detector is a third-party library with internal unwraps: a panic on a strange
    // image must become an error, never bring down a capture session.
    let tags = catch_unwind(AssertUnwindSafe(|| detector.detect(&image))).map_err(|_| {
        not_found("the AprilGrid detector failed on this image (it panicked)".into())
    })?;
    let n_tags = board.rows * board.cols;
    let mut ids: Vec<u32> = tags.keys().copied().filter(|id| *id < n_tags).collect();
    ids.sort_unstable();
    if ids.len() < MIN_TAGS {
        return Err(not_found(format!(
            "{} of the board's {n_tags} tags found (at least {MIN_TAGS} needed); bring the board closer or face it to the camera",
            ids.len()
        )));
    }
    let mut corners = Vec::with_capacity(4 * ids.len());
    for id in ids {
        let Some(quad) = tags.get(&id) else {
            continue;
        };
        // The crate gives each tag's corners in the board's order: the printed tag's
        // lower-left, lower-right, upper-right, upper-left (checked against the rendered
        // truth in the tests below).
        for (k, (u, v)) in quad.iter().enumerate() {
            corners.push(Corner {
                id: 4 * id + k as u32,
                u: f64::from(*u),
                v: f64::from(*v),
            });
        }
    }
    Ok(corners)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::board::BoardKind;
    use crate::camera::{DepthMode, Intrinsics};
    use crate::detect::render_board_ir;
    use nalgebra::{Isometry3, Point2, Translation3, UnitQuaternion, Vector2, Vector3};
    use rand::{Rng, SeedableRng};
    use rand_distr::StandardNormal;

    /// 4 x 3 tags of 80 mm: 8 mm bits, 3-5 px each for a D455 at 0.7-1.1 m in 848 x 480.
    fn grid() -> BoardConfig {
        BoardConfig {
            kind: BoardKind::AprilGrid,
            rows: 3,
            cols: 4,
            square_m: 0.08,
            spacing: 0.3,
        }
    }

    fn pose(rpy: [f64; 3], at: Vector3<f64>, b: &BoardConfig) -> Isometry3<f64> {
        // Board centre at `at`, face towards the camera, tilted.
        let rot = UnitQuaternion::from_euler_angles(std::f64::consts::PI + rpy[0], rpy[1], rpy[2]);
        Isometry3::from_parts(Translation3::from(at - rot * b.centre().coords), rot)
    }

    fn noisy(img: &mut Image<u8>, sigma: f64, rng: &mut impl Rng) {
        for p in &mut img.data {
            let g: f64 = rng.sample(StandardNormal);
            *p = (f64::from(*p) + sigma * g).round().clamp(0.0, 255.0) as u8;
        }
    }

    /// Per-corner errors against the true projections: (rms, worst, mean offset).
    fn errors(
        corners: &[Corner],
        k: &Intrinsics,
        truth: &Isometry3<f64>,
        b: &BoardConfig,
    ) -> (f64, f64, Vector2<f64>) {
        let mut ss = 0.0;
        let mut worst: f64 = 0.0;
        let mut bias = Vector2::zeros();
        for c in corners {
            let want = k.project(&(truth * b.corner(c.id).unwrap())).unwrap();
            let d = Point2::new(c.u, c.v) - want;
            bias += d / corners.len() as f64;
            ss += d.norm_squared();
            worst = worst.max(d.norm());
        }
        ((ss / corners.len() as f64).sqrt(), worst, bias)
    }

    #[test]
    fn every_tag_is_found_with_its_corners_to_a_tenth_of_a_pixel() {
        let k = Intrinsics::d455_depth(DepthMode::Wvga848x480);
        let b = grid();
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(5);
        let mut total_bias = Vector2::zeros();
        let poses = [
            [0.0, 0.0, 0.0],
            [0.4, 0.2, 0.3],
            [-0.3, 0.4, 2.0],
            [0.3, -0.4, -2.5],
            [0.0, 0.3, 1.57],
            [0.2, 0.1, 3.1],
        ];
        for (n, rpy) in poses.into_iter().enumerate() {
            let truth = pose(rpy, Vector3::new(0.02, -0.01, 0.7 + 0.08 * n as f64), &b);
            let mut img = render_board_ir(&k, &truth, &b, &IrLevels::default());
            noisy(&mut img, 2.0, &mut rng);
            let corners = detect_april_grid(&img, &b).unwrap();
            assert_eq!(corners.len(), b.corner_count(), "pose {n}");
            let (rms, worst, bias) = errors(&corners, &k, &truth, &b);
            eprintln!("pose {n}: rms {rms:.4} worst {worst:.4} bias {bias:?}");
            total_bias += bias / poses.len() as f64;
            assert!(
                rms < 0.1 && worst < 0.3,
                "pose {n}: rms {rms} worst {worst}"
            );
        }
        // No half-pixel convention error: the mean offset over all poses is noise.
        assert!(total_bias.norm() < 0.03, "mean offset {total_bias:?}");
    }

    #[test]
    fn a_partly_visible_board_gives_the_tags_in_view_with_the_right_ids() {
        let k = Intrinsics::d455_depth(DepthMode::Wvga848x480);
        let b = grid();
        // The board's centre near the right image edge: its right-hand tags are cut off.
        let truth = pose([0.1, 0.2, 0.2], Vector3::new(0.74, 0.0, 0.8), &b);
        let img = render_board_ir(&k, &truth, &b, &IrLevels::default());
        let corners = detect_april_grid(&img, &b).unwrap();
        let n = corners.len();
        assert!(n >= 4 * MIN_TAGS && n < b.corner_count(), "{n} corners");
        let (rms, worst, _) = errors(&corners, &k, &truth, &b);
        assert!(rms < 0.1 && worst < 0.3, "rms {rms} worst {worst}");
        for c in &corners {
            assert!((0.0..f64::from(k.width)).contains(&c.u), "{c:?}");
        }
    }

    #[test]
    fn no_board_or_a_useless_image_is_a_clear_error() {
        let k = Intrinsics::d455_depth(DepthMode::Wvga848x480);
        let b = grid();
        let blank = Image::filled(k.width, k.height, 128u8);
        let err = detect_april_grid(&blank, &b).unwrap_err();
        assert!(
            matches!(&err, CalibrationError::BoardNotFound { why } if why.contains("0 of the board's 12 tags")),
            "{err}"
        );
        let tiny = Image::filled(8, 8, 0u8);
        let err = detect_april_grid(&tiny, &b).unwrap_err();
        assert!(err.to_string().contains("too small"), "{err}");
        let mut broken = Image::filled(k.width, k.height, 0u8);
        broken.data.truncate(10);
        assert!(detect_april_grid(&broken, &b).is_err());
        // A chessboard is not an AprilGrid.
        let chess = BoardConfig::default();
        let img = render_board_ir(
            &k,
            &pose([0.1, 0.1, 0.1], Vector3::new(0.0, 0.0, 0.8), &chess),
            &chess,
            &IrLevels::default(),
        );
        assert!(detect_april_grid(&img, &b).is_err());
    }

    #[test]
    fn tags_past_the_configured_grid_are_not_reported() {
        let k = Intrinsics::d455_depth(DepthMode::Wvga848x480);
        let printed = grid();
        let truth = pose([0.2, 0.1, 0.3], Vector3::new(0.0, 0.0, 0.8), &printed);
        let img = render_board_ir(&k, &truth, &printed, &IrLevels::default());
        // Configured as its first two rows only: the third row's tags (8..12) are others'.
        let smaller = BoardConfig { rows: 2, ..printed };
        let corners = detect_april_grid(&img, &smaller).unwrap();
        assert_eq!(corners.len(), 4 * 8);
        assert!(corners.iter().all(|c| c.id < 32));
    }
}
