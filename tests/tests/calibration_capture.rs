//! `equact calibrate capture` in the simulated cell, end to end: planned board poses, the
//! arm driven there through the UR driver, the board detected in rendered IR images, an
//! interrupted run resumed without losing or repeating a pose, and the captures solved to
//! the simulated cameras' true poses.

#![allow(clippy::unwrap_used, clippy::expect_used)] // test helpers may panic

use std::sync::Arc;

use cell_types::config::CellConfig;
use cell_types::SystemClock;
use equact::calibrate_capture::{capture_in_sim, CapturePlan};

fn plan(limit: Option<usize>) -> CapturePlan {
    CapturePlan {
        seed: 5,
        poses: 14,
        limit,
        ir_sigma: 2.0,
    }
}

#[test]
fn capture_resume_and_solve_in_the_simulated_cell() {
    let cfg = CellConfig::simulated().unwrap();
    let dir = std::env::temp_dir().join(format!("equact-capture-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&dir);
    let clock = Arc::new(SystemClock::new());
    let mut lines = Vec::new();

    // An interrupted run: only 4 poses.
    let first = capture_in_sim(&cfg, &dir, plan(Some(4)), clock.clone(), &mut |l| {
        lines.push(l.to_string())
    })
    .unwrap();
    assert_eq!(first.captured, 4);
    assert_eq!(first.resumed, 0);
    let kept: Vec<_> = std::fs::read_dir(&dir)
        .unwrap()
        .map(|e| e.unwrap().file_name().to_string_lossy().into_owned())
        .filter(|n| n.starts_with("pose_"))
        .collect();
    assert_eq!(kept.len(), 4, "{kept:?}");
    // Every camera's IR image of every captured pose is kept beside it.
    let images = std::fs::read_dir(&dir)
        .unwrap()
        .filter(|e| {
            let name = e.as_ref().unwrap().file_name();
            let name = name.to_string_lossy();
            name.starts_with("ir_pose_") && name.ends_with(".png")
        })
        .count();
    assert_eq!(images, 4 * 3);
    let before = std::fs::read(dir.join(&kept[0])).unwrap();

    // Resumed: the 4 are kept as they were, the rest captured (or skipped with a reason).
    let second = capture_in_sim(&cfg, &dir, plan(None), clock, &mut |l| {
        lines.push(l.to_string())
    })
    .unwrap();
    assert_eq!(second.resumed, 4);
    assert_eq!(second.captured + second.skipped.len() + 4, second.planned);
    assert!(second.captured + 4 >= 10, "{second:?}");
    assert_eq!(std::fs::read(dir.join(&kept[0])).unwrap(), before);
    assert!(lines.iter().any(|l| l.contains("cameras found the board")));

    let set = calibration::load_captures(&dir).unwrap();
    let solution = calibration::solve(&set, &calibration::SolveOptions::default()).unwrap();
    let truth = calibration::load_truth(&dir).unwrap();
    for (id, m, rad) in solution.errors_to(&truth) {
        assert!(
            m < 1e-3 && rad < 0.05_f64.to_radians(),
            "camera {id}: {m} m, {rad} rad"
        );
    }
    let _ = std::fs::remove_dir_all(&dir);
}
