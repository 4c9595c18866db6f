//! Argument helpers shared by subcommands: comma-separated numbers and cloud files.

use std::path::Path;

use anyhow::Context;
use cell_types::PointCloud;

/// Parses `--what` as exactly `N` comma-separated numbers.
pub fn numbers<const N: usize>(s: &str, what: &str) -> anyhow::Result<[f64; N]> {
    let v: Vec<f64> = s
        .split(',')
        .map(|x| x.trim().parse::<f64>())
        .collect::<Result<_, _>>()
        .with_context(|| format!("--{what} must be {N} comma-separated numbers"))?;
    v.try_into()
        .map_err(|v: Vec<f64>| anyhow::anyhow!("--{what} has {} numbers, need {N}", v.len()))
}

/// Reads a point cloud file (PLY or PCD, see `planner::cloud_io`).
pub fn read_cloud_file(path: &Path) -> anyhow::Result<PointCloud> {
    let bytes = std::fs::read(path).with_context(|| format!("reading {}", path.display()))?;
    planner::cloud_io::read_cloud(&bytes).with_context(|| format!("parsing {}", path.display()))
}
