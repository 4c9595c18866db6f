//! Helpers shared by subcommands: comma-separated numbers, cloud files, the Ctrl-C flag.

use std::path::Path;
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::Arc;

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

/// A flag Ctrl-C sets (printing `message`), for loops that stop at their next safe point.
pub fn interrupt_flag(message: &'static str) -> anyhow::Result<Arc<AtomicBool>> {
    let interrupt = Arc::new(AtomicBool::new(false));
    let flag = interrupt.clone();
    ctrlc::set_handler(move || {
        flag.store(true, Ordering::SeqCst);
        eprintln!("\nCtrl-C: {message}");
    })
    .context("installing the Ctrl-C handler")?;
    Ok(interrupt)
}
