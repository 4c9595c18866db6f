//! Looking at clouds (issue 7 item 5, and issue 8's report picture): PLY export and a
//! top-down / perspective splat into an RGB image, with no image library (PNG encoding is
//! the caller's).

use std::io::Write;

use cell_types::{Image, PointCloud, Rgb};
use nalgebra::{Matrix3, Point3, Vector3};

use crate::camera::Intrinsics;

/// Writes `cloud` as a binary little-endian PLY (x, y, z as float; red, green, blue as
/// uchar when the cloud has colour).
pub fn write_ply<W: Write>(cloud: &PointCloud, mut out: W) -> std::io::Result<()> {
    let rgb = cloud.rgb.as_ref().filter(|c| c.len() == cloud.len());
    write!(
        out,
        "ply\nformat binary_little_endian 1.0\ncomment frame {}\nelement vertex {}\nproperty float x\nproperty float y\nproperty float z\n",
        cloud.frame,
        cloud.len()
    )?;
    if rgb.is_some() {
        write!(
            out,
            "property uchar red\nproperty uchar green\nproperty uchar blue\n"
        )?;
    }
    writeln!(out, "end_header")?;
    let mut buf = Vec::with_capacity(cloud.len() * 15);
    for (i, p) in cloud.points.iter().enumerate() {
        for v in [p.x, p.y, p.z] {
            buf.extend_from_slice(&v.to_le_bytes());
        }
        if let Some(c) = rgb.and_then(|c| c.get(i)) {
            buf.extend_from_slice(c);
        }
    }
    out.write_all(&buf)
}

/// Colour for a point without colour: a height ramp from blue (low) to yellow (high).
fn height_colour(z: f32, lo: f32, hi: f32) -> Rgb {
    let t = ((z - lo) / (hi - lo).max(1e-6)).clamp(0.0, 1.0);
    [
        (40.0 + 215.0 * t) as u8,
        (60.0 + 160.0 * t) as u8,
        (200.0 * (1.0 - t)) as u8,
    ]
}

/// Renders `cloud` through a virtual pinhole camera at `eye` looking at `target` (z up),
/// nearest point wins, each point a `radius`-pixel square; background dark grey.
pub fn splat(
    cloud: &PointCloud,
    intrinsics: &Intrinsics,
    eye: Point3<f64>,
    target: Point3<f64>,
    radius: u32,
) -> Image<Rgb> {
    let (w, h) = (intrinsics.width, intrinsics.height);
    let mut img = Image::filled(w, h, [30u8, 30, 30]);
    let mut zbuf = vec![f32::INFINITY; w as usize * h as usize];
    let fwd = (target - eye).normalize();
    // Looking straight down: take +x of the base as "up" in the image.
    let up = if fwd.cross(&Vector3::z()).norm() < 1e-6 {
        Vector3::x()
    } else {
        Vector3::z()
    };
    let right = fwd.cross(&up).normalize();
    let down = fwd.cross(&right);
    let camera_from_base =
        Matrix3::from_rows(&[right.transpose(), down.transpose(), fwd.transpose()]);
    let (lo, hi) = cloud.bounds().map_or((0.0, 1.0), |(lo, hi)| (lo.z, hi.z));
    let r = radius as i64;
    for (i, p) in cloud.points.iter().enumerate() {
        let pc = camera_from_base * (p.cast::<f64>() - eye);
        let Ok(px) = intrinsics.project(&Point3::from(pc)) else {
            continue;
        };
        let colour = cloud
            .rgb
            .as_ref()
            .and_then(|c| c.get(i).copied())
            .unwrap_or_else(|| height_colour(p.z, lo, hi));
        let (cu, cv) = (px.x.round() as i64, px.y.round() as i64);
        for dv in -r..=r {
            for du in -r..=r {
                let (u, v) = (cu + du, cv + dv);
                if u < 0 || v < 0 || u >= i64::from(w) || v >= i64::from(h) {
                    continue;
                }
                let k = v as usize * w as usize + u as usize;
                if (pc.z as f32) < zbuf[k] {
                    zbuf[k] = pc.z as f32;
                    img.data[k] = colour;
                }
            }
        }
    }
    img
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::camera::DepthMode;
    use cell_types::FrameId;

    #[test]
    fn ply_header_and_body_sizes_match() {
        let cloud = PointCloud::new(
            FrameId::Base,
            vec![Point3::new(1.0, 2.0, 3.0), Point3::new(-1.0, 0.5, 0.25)],
            Some(vec![[1, 2, 3], [4, 5, 6]]),
        )
        .unwrap();
        let mut out = Vec::new();
        write_ply(&cloud, &mut out).unwrap();
        let text = String::from_utf8_lossy(&out);
        let end = text.find("end_header\n").unwrap() + "end_header\n".len();
        assert!(text.contains("element vertex 2"));
        assert!(text.contains("property uchar red"));
        assert_eq!(out.len() - end, 2 * 15);
        assert_eq!(&out[end..end + 4], &1.0f32.to_le_bytes());
        assert_eq!(&out[end + 12..end + 15], &[1, 2, 3]);
    }

    #[test]
    fn splat_draws_the_nearest_point_where_it_projects() {
        let k = Intrinsics::d455_depth(DepthMode::Vga640x480);
        let cloud = PointCloud::new(
            FrameId::Base,
            vec![Point3::new(0.5, 0.0, 0.0), Point3::new(0.5, 0.0, 0.1)],
            Some(vec![[255, 0, 0], [0, 255, 0]]),
        )
        .unwrap();
        // From above: the higher (green) point hides the red one.
        let img = splat(
            &cloud,
            &k,
            Point3::new(0.5, 0.0, 1.0),
            Point3::new(0.5, 0.0, 0.0),
            1,
        );
        let centre = img.get(k.ppx.round() as u32, k.ppy.round() as u32).unwrap();
        assert_eq!(*centre, [0, 255, 0]);
        assert_eq!(*img.get(5, 5).unwrap(), [30, 30, 30]);
    }
}
