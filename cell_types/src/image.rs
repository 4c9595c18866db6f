//! Camera images and frames as the depth cameras deliver them (issue 7: D455 depth in u16
//! millimetres, left IR, colour aligned to depth).

use std::time::Duration;

use serde::{Deserialize, Serialize};

use crate::cloud::Rgb;
use crate::error::CellTypesError;

/// A row-major image of `width` x `height` pixels; pixel (u, v) is `data[v * width + u]`.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Image<T> {
    /// Width in pixels.
    pub width: u32,
    /// Height in pixels.
    pub height: u32,
    /// Pixels, row by row from the top-left.
    pub data: Vec<T>,
}

impl<T: Clone> Image<T> {
    /// An image filled with `value`.
    pub fn filled(width: u32, height: u32, value: T) -> Self {
        Self {
            width,
            height,
            data: vec![value; width as usize * height as usize],
        }
    }

    /// Wraps a pixel buffer, checking that it holds exactly `width * height` pixels.
    pub fn new(width: u32, height: u32, data: Vec<T>) -> Result<Self, CellTypesError> {
        let expected = width as usize * height as usize;
        if data.len() != expected {
            return Err(CellTypesError::LengthMismatch {
                what: "image pixels",
                expected,
                got: data.len(),
            });
        }
        Ok(Self {
            width,
            height,
            data,
        })
    }

    /// The pixel at column `u`, row `v`, or `None` outside the image.
    pub fn get(&self, u: u32, v: u32) -> Option<&T> {
        if u < self.width && v < self.height {
            self.data.get(v as usize * self.width as usize + u as usize)
        } else {
            None
        }
    }

    /// True when the buffer length matches the declared size.
    pub fn is_consistent(&self) -> bool {
        self.data.len() == self.width as usize * self.height as usize
    }
}

/// A depth image: raw sensor units; metres = `raw * depth_scale`; 0 means "no depth".
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct DepthImage {
    /// The raw values (D455: millimetres).
    pub raw: Image<u16>,
    /// Metres per raw unit (D455: 0.001).
    pub depth_scale: f32,
}

/// One capture of a depth camera: depth, and the other streams when enabled.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct CameraFrame {
    /// The camera's id (its `FrameId::Camera` index).
    pub camera: u8,
    /// Capture time on the clock of whoever captured it.
    pub timestamp: Duration,
    /// The depth image (rectified: zero distortion).
    pub depth: DepthImage,
    /// The left infrared image; it shares the depth intrinsics pixel for pixel.
    pub ir: Option<Image<u8>>,
    /// The colour image aligned to the depth image pixel for pixel (librealsense
    /// `align_to(depth)`), when a colour stream exists.
    pub colour: Option<Image<Rgb>>,
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn image_size_is_checked() {
        assert!(matches!(
            Image::new(3, 2, vec![0u8; 5]),
            Err(CellTypesError::LengthMismatch {
                expected: 6,
                got: 5,
                ..
            })
        ));
        let img = Image::new(3, 2, vec![0u8, 1, 2, 3, 4, 5]).unwrap();
        assert_eq!(img.get(1, 1), Some(&4));
        assert_eq!(img.get(3, 0), None);
    }
}
