//! Point clouds with the frame they are expressed in.

use nalgebra::Point3;
use serde::{Deserialize, Serialize};

use crate::error::CellTypesError;
use crate::frames::FrameId;

/// An 8-bit RGB colour.
pub type Rgb = [u8; 3];

/// A point cloud: positions in metres in `frame`, with optional per-point colour.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct PointCloud {
    /// The frame the positions are expressed in.
    pub frame: FrameId,
    /// Point positions (m). `f32` keeps large clouds small; millimetre precision is kept to
    /// well beyond 10 m.
    pub points: Vec<Point3<f32>>,
    /// Colours, one per point, when a colour stream exists.
    pub rgb: Option<Vec<Rgb>>,
}

impl PointCloud {
    /// An empty cloud in `frame`.
    pub fn empty(frame: FrameId) -> Self {
        Self {
            frame,
            points: Vec::new(),
            rgb: None,
        }
    }

    /// Builds a cloud, checking that colours (if any) match the points one to one and that
    /// every coordinate is finite.
    pub fn new(
        frame: FrameId,
        points: Vec<Point3<f32>>,
        rgb: Option<Vec<Rgb>>,
    ) -> Result<Self, CellTypesError> {
        if let Some(c) = &rgb {
            if c.len() != points.len() {
                return Err(CellTypesError::LengthMismatch {
                    what: "point cloud colours",
                    expected: points.len(),
                    got: c.len(),
                });
            }
        }
        for p in &points {
            for v in p.coords.iter() {
                if !v.is_finite() {
                    return Err(CellTypesError::NotFinite {
                        what: "point cloud coordinate",
                        value: f64::from(*v),
                    });
                }
            }
        }
        Ok(Self { frame, points, rgb })
    }

    /// Number of points.
    pub fn len(&self) -> usize {
        self.points.len()
    }

    /// True when the cloud has no points.
    pub fn is_empty(&self) -> bool {
        self.points.is_empty()
    }

    /// Axis-aligned bounds (min, max), or `None` for an empty cloud.
    pub fn bounds(&self) -> Option<(Point3<f32>, Point3<f32>)> {
        let first = self.points.first()?;
        let mut lo = *first;
        let mut hi = *first;
        for p in &self.points {
            for i in 0..3 {
                lo[i] = lo[i].min(p[i]);
                hi[i] = hi[i].max(p[i]);
            }
        }
        Some((lo, hi))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn colour_count_must_match() {
        let pts = vec![Point3::new(0.0, 0.0, 0.0); 3];
        let err = PointCloud::new(FrameId::Base, pts, Some(vec![[0, 0, 0]; 2])).unwrap_err();
        assert_eq!(
            err,
            CellTypesError::LengthMismatch {
                what: "point cloud colours",
                expected: 3,
                got: 2
            }
        );
    }

    #[test]
    fn nan_points_are_rejected() {
        let pts = vec![Point3::new(0.0, f32::NAN, 0.0)];
        assert!(matches!(
            PointCloud::new(FrameId::Camera(1), pts, None),
            Err(CellTypesError::NotFinite { .. })
        ));
    }

    #[test]
    fn bounds_cover_points() {
        let pts = vec![Point3::new(1.0, -2.0, 0.5), Point3::new(-1.0, 3.0, 0.0)];
        let c = PointCloud::new(FrameId::Base, pts, None).unwrap();
        let (lo, hi) = c.bounds().unwrap();
        assert_eq!(lo, Point3::new(-1.0, -2.0, 0.0));
        assert_eq!(hi, Point3::new(1.0, 3.0, 0.5));
        assert!(PointCloud::empty(FrameId::Base).bounds().is_none());
    }
}
