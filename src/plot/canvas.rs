//! A small RGB raster with the primitives the plots need: lines, rectangles, dots and
//! 8×8 bitmap text (the public-domain `font8x8` glyphs), written as PNG.

use std::fs::File;
use std::io::BufWriter;
use std::path::Path;

use super::PlotError;

/// An RGB colour.
pub type Colour = [u8; 3];

/// White background.
pub const WHITE: Colour = [255, 255, 255];
/// Axis and text colour.
pub const BLACK: Colour = [0, 0, 0];
/// Limit lines.
pub const RED: Colour = [220, 30, 30];
/// Light grid lines.
pub const GREY: Colour = [200, 200, 200];
/// One colour per joint (1..6).
pub const JOINT_COLOURS: [Colour; 6] = [
    [31, 119, 180],
    [255, 127, 14],
    [44, 160, 44],
    [148, 103, 189],
    [140, 86, 75],
    [23, 190, 207],
];

/// An RGB image being drawn.
#[derive(Clone, Debug)]
pub struct Canvas {
    /// Width (px).
    pub width: u32,
    /// Height (px).
    pub height: u32,
    /// Row-major pixels.
    pub pixels: Vec<Colour>,
}

impl Canvas {
    /// A canvas filled with `background`.
    pub fn new(width: u32, height: u32, background: Colour) -> Self {
        Self {
            width,
            height,
            pixels: vec![background; width as usize * height as usize],
        }
    }

    /// The pixel at (x, y), if inside.
    pub fn get(&self, x: i64, y: i64) -> Option<Colour> {
        self.index(x, y).map(|i| self.pixels[i])
    }

    fn index(&self, x: i64, y: i64) -> Option<usize> {
        (x >= 0 && y >= 0 && x < i64::from(self.width) && y < i64::from(self.height))
            .then(|| y as usize * self.width as usize + x as usize)
    }

    /// Sets one pixel; outside the canvas is clipped.
    pub fn set(&mut self, x: i64, y: i64, c: Colour) {
        if let Some(i) = self.index(x, y) {
            self.pixels[i] = c;
        }
    }

    /// A filled square of side `2r + 1` centred on (x, y).
    pub fn dot(&mut self, x: i64, y: i64, r: i64, c: Colour) {
        for dy in -r..=r {
            for dx in -r..=r {
                self.set(x + dx, y + dy, c);
            }
        }
    }

    /// A line (Bresenham), `thickness` pixels wide.
    pub fn line(&mut self, from: (i64, i64), to: (i64, i64), c: Colour, thickness: i64) {
        let (mut x, mut y) = from;
        let (dx, dy) = ((to.0 - x).abs(), -(to.1 - y).abs());
        let (sx, sy) = (if x < to.0 { 1 } else { -1 }, if y < to.1 { 1 } else { -1 });
        let mut err = dx + dy;
        let r = (thickness - 1) / 2;
        // Lines far outside (a wild value) are clipped by length, not drawn forever.
        for _ in 0..=(dx - dy).min(100_000) {
            self.dot(x, y, r, c);
            if (x, y) == to {
                break;
            }
            let e2 = 2 * err;
            if e2 >= dy {
                err += dy;
                x += sx;
            }
            if e2 <= dx {
                err += dx;
                y += sy;
            }
        }
    }

    /// A horizontal dashed line from x0 to x1 at y.
    pub fn dashed_hline(&mut self, x0: i64, x1: i64, y: i64, c: Colour) {
        for x in x0..=x1 {
            if (x - x0) % 8 < 5 {
                self.set(x, y, c);
                self.set(x, y + 1, c);
            }
        }
    }

    /// The outline of a rectangle.
    pub fn rect(&mut self, x0: i64, y0: i64, x1: i64, y1: i64, c: Colour) {
        self.line((x0, y0), (x1, y0), c, 1);
        self.line((x1, y0), (x1, y1), c, 1);
        self.line((x1, y1), (x0, y1), c, 1);
        self.line((x0, y1), (x0, y0), c, 1);
    }

    /// ASCII text with its top-left corner at (x, y), 8 px per character.
    pub fn text(&mut self, x: i64, y: i64, s: &str, c: Colour) {
        for (k, ch) in s.chars().enumerate() {
            let glyph = font8x8::legacy::BASIC_LEGACY
                .get(ch as usize)
                .copied()
                .unwrap_or([0; 8]);
            for (row, bits) in glyph.iter().enumerate() {
                for col in 0..8 {
                    if bits & (1 << col) != 0 {
                        self.set(x + 8 * k as i64 + col, y + row as i64, c);
                    }
                }
            }
        }
    }

    /// Writes the canvas as an 8-bit RGB PNG.
    pub fn save_png(&self, path: &Path) -> Result<(), PlotError> {
        let write = |path: &Path| -> Result<(), Box<dyn std::error::Error + Send + Sync>> {
            let file = File::create(path)?;
            let mut enc = png::Encoder::new(BufWriter::new(file), self.width, self.height);
            enc.set_color(png::ColorType::Rgb);
            enc.set_depth(png::BitDepth::Eight);
            let mut w = enc.write_header()?;
            w.write_image_data(self.pixels.as_flattened())?;
            w.finish()?;
            Ok(())
        };
        write(path).map_err(|e| PlotError::Write {
            path: path.to_path_buf(),
            detail: e.to_string(),
        })
    }
}

/// A rectangular plot area mapping data (x, y) to pixels.
#[derive(Copy, Clone, Debug)]
pub struct Panel {
    /// Left edge (px).
    pub left: i64,
    /// Top edge (px).
    pub top: i64,
    /// Width (px).
    pub width: i64,
    /// Height (px).
    pub height: i64,
    /// Data range along x.
    pub x: (f64, f64),
    /// Data range along y.
    pub y: (f64, f64),
}

impl Panel {
    /// The pixel of a data point (y grows upwards in data, downwards in pixels).
    pub fn map(&self, x: f64, y: f64) -> (i64, i64) {
        let fx = (x - self.x.0) / (self.x.1 - self.x.0);
        let fy = (y - self.y.0) / (self.y.1 - self.y.0);
        let px = self.left as f64 + fx * self.width as f64;
        let py = (self.top + self.height) as f64 - fy * self.height as f64;
        (
            px.round().clamp(-1e6, 1e6) as i64,
            py.round().clamp(-1e6, 1e6) as i64,
        )
    }

    /// Draws the frame.
    pub fn frame(&self, canvas: &mut Canvas) {
        canvas.rect(
            self.left,
            self.top,
            self.left + self.width,
            self.top + self.height,
            BLACK,
        );
    }

    /// Draws a polyline through (x, y) pairs, clipped to the panel.
    pub fn series(&self, canvas: &mut Canvas, xs: &[f64], ys: &[f64], c: Colour) {
        let mut prev = None;
        for (x, y) in xs.iter().zip(ys) {
            if !x.is_finite() || !y.is_finite() {
                prev = None;
                continue;
            }
            let p = self.map(*x, *y);
            if let Some(q) = prev {
                self.clipped_line(canvas, q, p, c);
            }
            prev = Some(p);
        }
    }

    fn clipped_line(&self, canvas: &mut Canvas, a: (i64, i64), b: (i64, i64), c: Colour) {
        let (x0, x1) = (self.left, self.left + self.width);
        let (y0, y1) = (self.top, self.top + self.height);
        let inside = |p: (i64, i64)| p.0 >= x0 && p.0 <= x1 && p.1 >= y0 && p.1 <= y1;
        if inside(a) || inside(b) {
            let clamp = |p: (i64, i64)| (p.0.clamp(x0, x1), p.1.clamp(y0, y1));
            canvas.line(clamp(a), clamp(b), c, 1);
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn lines_reach_both_ends_and_clip_at_the_border() {
        let mut c = Canvas::new(20, 10, WHITE);
        c.line((2, 3), (15, 8), RED, 1);
        assert_eq!(c.get(2, 3), Some(RED));
        assert_eq!(c.get(15, 8), Some(RED));
        c.line((-50, -50), (50, 50), BLACK, 1);
        assert_eq!(c.get(5, 5), Some(BLACK));
        assert_eq!(c.get(25, 25), None);
    }

    #[test]
    fn panel_maps_corners_to_its_frame() {
        let p = Panel {
            left: 10,
            top: 20,
            width: 100,
            height: 50,
            x: (0.0, 2.0),
            y: (-1.0, 1.0),
        };
        assert_eq!(p.map(0.0, -1.0), (10, 70));
        assert_eq!(p.map(2.0, 1.0), (110, 20));
        assert_eq!(p.map(1.0, 0.0), (60, 45));
    }

    #[test]
    fn text_draws_glyph_pixels() {
        let mut c = Canvas::new(40, 10, WHITE);
        c.text(0, 0, "H1", BLACK);
        let inked = c.pixels.iter().filter(|p| **p == BLACK).count();
        assert!(inked > 10, "{inked}");
        let mut blank = Canvas::new(40, 10, WHITE);
        blank.text(0, 0, "  ", BLACK);
        assert!(blank.pixels.iter().all(|p| *p == WHITE));
    }
}
