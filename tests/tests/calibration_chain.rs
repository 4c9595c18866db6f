//! Calibration through to the fused cloud (issue 8 item 4's overlap check): captures of the
//! simulator's own rig (hil_sim's three D455s) are solved, and the calibrated extrinsics
//! deproject hil_sim-rendered depth frames of the default cell; around the red box (top,
//! sides and the table: several planes) the cameras agree with each other as well as with
//! the true extrinsics.
#![allow(clippy::unwrap_used, clippy::expect_used)]

use std::time::Duration;

use calibration::fusion::{Bounds, FusionParams, FusionPipeline};
use calibration::report::CAMERA_COLOURS;
use calibration::simulate::{simulate_set, SimCamera, SimConfig};
use calibration::solve::{solve, SolveOptions};
use calibration::{overlap_check, overlay_image, CellCalibration, DepthMode, Intrinsics};
use hil_sim::depth_camera::{default_rig, render_rig, rig_calibration};
use hil_sim::scene::Scene;
use nalgebra::Point3;

#[test]
fn calibrated_cameras_agree_in_their_overlap_like_the_true_ones() {
    let rig = default_rig(4);
    let cfg = SimConfig {
        cameras: rig
            .iter()
            .map(|c| SimCamera {
                id: c.id,
                name: c.name.clone(),
                intrinsics: c.intrinsics,
                base_from_camera: c.base_from_camera,
            })
            .collect(),
        ..SimConfig::default_cell()
    };
    let (set, truth) = simulate_set(&cfg, 4).unwrap();
    let opts = SolveOptions {
        holdout_folds: 0,
        ..SolveOptions::default()
    };
    let sol = solve(&set, &opts).unwrap();
    for (id, dt, dr) in sol.errors_to(&truth) {
        println!(
            "camera {id}: {:.3} mm {:.4} deg from the truth",
            dt * 1e3,
            dr.to_degrees()
        );
    }
    let geometry = Scene::default_cell().build().unwrap();
    let frames = render_rig(&rig, &geometry, 0, Duration::ZERO).unwrap();
    let region = Bounds {
        min: [0.42, 0.05, -0.12],
        max: [0.68, 0.31, 0.2],
    };
    let check = |cal: CellCalibration| {
        let pipe = FusionPipeline::new(cal, FusionParams::default()).unwrap();
        overlap_check(&pipe, &frames, &region, 0.01).unwrap()
    };
    let ours = check(sol.calibration());
    let truth_pairs = check(rig_calibration(&rig));
    assert_eq!(ours.len(), 6, "every ordered pair overlaps: {ours:?}");
    let mut report = sol.report();
    report.overlap = ours.clone();
    println!("{report}");
    // The picture: the three clouds overlaid, coloured by camera, all three visible.
    let pipe = FusionPipeline::new(sol.calibration(), FusionParams::default()).unwrap();
    let img = overlay_image(
        &pipe,
        &frames,
        &region,
        &Intrinsics::d455_depth(DepthMode::Vga640x480),
        Point3::new(0.9, 0.45, 0.45),
        Point3::new(0.55, 0.18, -0.02),
    )
    .unwrap();
    if let Ok(path) = std::env::var("CALIB_OVERLAY_PPM") {
        // For a look: CALIB_OVERLAY_PPM=/tmp/overlay.ppm cargo test ... calibration_chain
        let mut out = format!("P6 {} {} 255\n", img.width, img.height).into_bytes();
        out.extend(img.data.iter().flatten());
        std::fs::write(path, out).unwrap();
    }
    for colour in &CAMERA_COLOURS[..3] {
        let n = img.data.iter().filter(|p| *p == colour).count();
        assert!(n > 500, "{colour:?}: {n} pixels");
    }
    for (o, t) in ours.iter().zip(&truth_pairs) {
        assert_eq!((o.a, o.b), (t.a, t.b));
        println!(
            "camera {} on {}: calibrated RMS {:.2} mm mean {:+.2} mm; true extrinsics RMS {:.2} mm mean {:+.2} mm",
            o.a, o.b, o.rms_mm, o.mean_mm, t.rms_mm, t.mean_mm
        );
        assert!(o.points > 500, "{o:?}");
        assert!((o.mean_mm - t.mean_mm).abs() < 1.0, "{o:?} vs {t:?}");
        assert!(o.rms_mm < 1.2 * t.rms_mm + 0.2, "{o:?} vs {t:?}");
    }
}
