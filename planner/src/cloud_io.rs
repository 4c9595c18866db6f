//! Reading point clouds for `equact plan` (issue 3 item 9): PLY (ascii, or
//! binary_little_endian with float/double coordinates) and PCD (ascii). Only x, y, z are
//! read; the cloud is taken to be in the robot base frame, in metres.

use crate::error::PlanError;
use cell_types::{FrameId, PointCloud};
use nalgebra::Point3;

fn bad(what: impl Into<String>) -> PlanError {
    PlanError::BadWorld { what: what.into() }
}

/// Parses a PLY or PCD file's bytes (the format is told by its first line).
pub fn read_cloud(bytes: &[u8]) -> Result<PointCloud, PlanError> {
    if bytes.starts_with(b"ply") {
        read_ply(bytes)
    } else {
        read_pcd(bytes)
    }
}

fn read_ply(bytes: &[u8]) -> Result<PointCloud, PlanError> {
    let end = bytes
        .windows(10)
        .position(|w| w == b"end_header")
        .ok_or_else(|| bad("PLY without end_header"))?;
    let header = std::str::from_utf8(&bytes[..end]).map_err(|_| bad("PLY header is not text"))?;
    let mut body = &bytes[end + 10..];
    while let Some((b'\r' | b'\n', rest)) = body.split_first() {
        body = rest;
    }
    let mut format = "";
    let mut count = 0usize;
    let mut in_vertex = false;
    let mut props: Vec<(String, String)> = Vec::new();
    for line in header.lines() {
        let t: Vec<&str> = line.split_whitespace().collect();
        match t.as_slice() {
            ["format", f, ..] => format = f,
            ["element", "vertex", n] => {
                in_vertex = true;
                count = n
                    .parse()
                    .map_err(|_| bad(format!("PLY vertex count {n}")))?;
            }
            ["element", ..] => in_vertex = false,
            ["property", ty, name] if in_vertex => props.push(((*ty).into(), (*name).into())),
            _ => {}
        }
    }
    let idx = |n: &str| {
        props
            .iter()
            .position(|p| p.1 == n)
            .ok_or_else(|| bad(format!("PLY vertex has no {n} property")))
    };
    let (ix, iy, iz) = (idx("x")?, idx("y")?, idx("z")?);
    let mut pts = Vec::with_capacity(count);
    match format {
        "ascii" => {
            let text = std::str::from_utf8(body).map_err(|_| bad("PLY ascii body is not text"))?;
            for line in text.lines().take(count) {
                let v: Vec<f32> = line
                    .split_whitespace()
                    .map(|s| s.parse::<f32>().map_err(|_| bad(format!("PLY value {s}"))))
                    .collect::<Result<_, _>>()?;
                let get = |i: usize| v.get(i).copied().ok_or_else(|| bad("PLY line too short"));
                pts.push(Point3::new(get(ix)?, get(iy)?, get(iz)?));
            }
        }
        "binary_little_endian" => {
            let sizes: Vec<usize> = props
                .iter()
                .map(|(t, _)| match t.as_str() {
                    "float" | "float32" | "int" | "uint" | "int32" | "uint32" => Ok(4),
                    "double" | "float64" => Ok(8),
                    "uchar" | "char" | "uint8" | "int8" => Ok(1),
                    "short" | "ushort" | "int16" | "uint16" => Ok(2),
                    t => Err(bad(format!("PLY property type {t} not supported"))),
                })
                .collect::<Result<_, _>>()?;
            let stride: usize = sizes.iter().sum();
            let offset = |i: usize| sizes[..i].iter().sum::<usize>();
            let read = |rec: &[u8], i: usize| -> Result<f32, PlanError> {
                let o = offset(i);
                match props[i].0.as_str() {
                    "float" | "float32" => Ok(f32::from_le_bytes(
                        rec[o..o + 4].try_into().map_err(|_| bad("PLY record"))?,
                    )),
                    "double" | "float64" => Ok(f64::from_le_bytes(
                        rec[o..o + 8].try_into().map_err(|_| bad("PLY record"))?,
                    ) as f32),
                    t => Err(bad(format!(
                        "PLY coordinate type {t}; need float or double"
                    ))),
                }
            };
            if body.len() < stride * count {
                return Err(bad(format!(
                    "PLY body has {} bytes, {count} vertices need {}",
                    body.len(),
                    stride * count
                )));
            }
            for rec in body.chunks_exact(stride).take(count) {
                pts.push(Point3::new(read(rec, ix)?, read(rec, iy)?, read(rec, iz)?));
            }
        }
        f => {
            return Err(bad(format!(
                "PLY format {f} not supported; use ascii or binary_little_endian"
            )))
        }
    }
    PointCloud::new(FrameId::Base, pts, None).map_err(|e| bad(e.to_string()))
}

fn read_pcd(bytes: &[u8]) -> Result<PointCloud, PlanError> {
    let text = std::str::from_utf8(bytes)
        .map_err(|_| bad("PCD is not ascii text (binary PCD is not supported)"))?;
    let mut fields: Vec<&str> = Vec::new();
    let mut lines = text.lines();
    for line in lines.by_ref() {
        let t: Vec<&str> = line.split_whitespace().collect();
        match t.first() {
            Some(&"FIELDS") => fields = t[1..].to_vec(),
            Some(&"DATA") => {
                if t.get(1) != Some(&"ascii") {
                    return Err(bad(
                        "PCD DATA is not ascii; convert it (binary PCD is not supported)",
                    ));
                }
                break;
            }
            _ => {}
        }
    }
    let idx = |n: &str| {
        fields
            .iter()
            .position(|f| *f == n)
            .ok_or_else(|| bad(format!("PCD has no field {n}")))
    };
    let (ix, iy, iz) = (idx("x")?, idx("y")?, idx("z")?);
    let mut pts = Vec::new();
    for line in lines {
        let v: Vec<&str> = line.split_whitespace().collect();
        if v.is_empty() {
            continue;
        }
        let get = |i: usize| -> Result<f32, PlanError> {
            v.get(i)
                .ok_or_else(|| bad("PCD line too short"))?
                .parse::<f32>()
                .map_err(|_| bad(format!("PCD value in line {line}")))
        };
        let p = Point3::new(get(ix)?, get(iy)?, get(iz)?);
        // PCD marks missing points with NaN; drop them rather than refuse the cloud.
        if p.coords.iter().all(|c| c.is_finite()) {
            pts.push(p);
        }
    }
    PointCloud::new(FrameId::Base, pts, None).map_err(|e| bad(e.to_string()))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn ascii_ply_binary_ply_and_pcd_read_the_same_points() {
        let ply = "ply\nformat ascii 1.0\nelement vertex 2\nproperty float x\nproperty float y\nproperty float z\nproperty uchar red\nend_header\n1 2 3 255\n4 5 6 0\n";
        let a = read_cloud(ply.as_bytes()).unwrap();
        let mut bin = b"ply\nformat binary_little_endian 1.0\nelement vertex 2\nproperty double x\nproperty float y\nproperty float z\nend_header\n".to_vec();
        for p in [[1.0f64, 2.0, 3.0], [4.0, 5.0, 6.0]] {
            bin.extend_from_slice(&p[0].to_le_bytes());
            bin.extend_from_slice(&(p[1] as f32).to_le_bytes());
            bin.extend_from_slice(&(p[2] as f32).to_le_bytes());
        }
        let b = read_cloud(&bin).unwrap();
        let pcd = "# .PCD v0.7\nVERSION 0.7\nFIELDS x y z\nSIZE 4 4 4\nTYPE F F F\nCOUNT 1 1 1\nWIDTH 3\nHEIGHT 1\nPOINTS 3\nDATA ascii\n1 2 3\nnan nan nan\n4 5 6\n";
        let c = read_cloud(pcd.as_bytes()).unwrap();
        assert_eq!(a.points, b.points);
        assert_eq!(a.points, c.points);
        assert_eq!(a.points[1], Point3::new(4.0, 5.0, 6.0));
    }

    #[test]
    fn malformed_files_give_typed_errors() {
        assert!(matches!(
            read_cloud(b"ply\nformat ascii 1.0\n"),
            Err(PlanError::BadWorld { .. })
        ));
        let short = b"ply\nformat binary_little_endian 1.0\nelement vertex 5\nproperty float x\nproperty float y\nproperty float z\nend_header\n\x00\x00";
        assert!(matches!(read_cloud(short), Err(PlanError::BadWorld { .. })));
        assert!(matches!(
            read_cloud(b"FIELDS a b\nDATA ascii\n1 2\n"),
            Err(PlanError::BadWorld { .. })
        ));
    }
}
