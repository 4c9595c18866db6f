//! Calibration side by side with OpenCV (issue 8): the same simulated captures folders go
//! to our joint bundle adjustment and to OpenCV 4.14's `calibrateHandEye` (Tsai, Park,
//! Horaud, Andreff, Daniilidis) and `calibrateRobotWorldHandEye` (Shah, Li), through the
//! peer `tests/peers/calib_opencv.py`. Over 10 seeded trials (30 poses, 0.5 px corners,
//! robot 0.5 mm / 0.05 deg per axis, three 848x480 cameras) our median error, in translation
//! and in rotation, must be below every OpenCV method's.
#![allow(clippy::unwrap_used, clippy::expect_used)]

use std::collections::BTreeMap;

use calibration::simulate::{simulate, SimConfig, Truth};
use calibration::solve::{solve, SolveOptions};
use nalgebra::{Matrix3, Rotation3, UnitQuaternion, Vector3};

const TRIALS: u64 = 10;

fn median(v: &mut [f64]) -> f64 {
    v.sort_by(f64::total_cmp);
    let n = v.len();
    if n % 2 == 1 {
        v[n / 2]
    } else {
        (v[n / 2 - 1] + v[n / 2]) / 2.0
    }
}

#[test]
fn joint_bundle_adjustment_beats_every_opencv_method_on_the_median() {
    let root = std::env::temp_dir().join(format!("calib-opencv-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&root);
    let cfg = SimConfig::default_cell();
    let opts = SolveOptions {
        holdout_folds: 0,
        ..SolveOptions::default()
    };
    let mut truths: BTreeMap<String, Truth> = BTreeMap::new();
    // method -> (translation errors m, rotation errors rad)
    let mut errors: BTreeMap<String, (Vec<f64>, Vec<f64>)> = BTreeMap::new();
    for seed in 0..TRIALS {
        let name = format!("trial_{seed:02}");
        let dir = root.join(&name);
        let (set, truth) = simulate(&cfg, 1000 + seed, &dir).unwrap();
        let sol = solve(&set, &opts).unwrap();
        for c in &sol.cameras {
            let t = truth.base_from_camera(c.id).unwrap();
            let (dt, dr) = c.base_from_camera.error_to(&t);
            let e = errors.entry("ours (joint BA)".into()).or_default();
            e.0.push(dt);
            e.1.push(dr);
            let (dt, dr) = c.closed_form.error_to(&t);
            let e = errors.entry("ours (closed form)".into()).or_default();
            e.0.push(dt);
            e.1.push(dr);
        }
        truths.insert(name, truth);
    }
    let out = tests::run_peer("calib_opencv.py", &[root.to_str().unwrap()]).unwrap();
    let mut version = String::new();
    let mut lines = 0;
    for line in out.lines() {
        let v: serde_json::Value = serde_json::from_str(line).unwrap();
        if let Some(ver) = v.get("opencv") {
            version = ver.as_str().unwrap().to_string();
            continue;
        }
        lines += 1;
        let trial = v["trial"].as_str().unwrap();
        let camera = v["camera"].as_u64().unwrap() as u8;
        let method = v["method"].as_str().unwrap();
        let r: Vec<Vec<f64>> = serde_json::from_value(v["R"].clone()).unwrap();
        let t: Vec<f64> = serde_json::from_value(v["t"].clone()).unwrap();
        let m = Matrix3::from_fn(|i, j| r[i][j]);
        let rot = UnitQuaternion::from_rotation_matrix(&Rotation3::from_matrix(&m));
        let truth = truths[trial].base_from_camera(camera).unwrap();
        let dt = (Vector3::new(t[0], t[1], t[2]) - truth.translation()).norm();
        let dr = rot.angle_to(&truth.rotation());
        let e = errors.entry(format!("opencv {method}")).or_default();
        e.0.push(dt);
        e.1.push(dr);
    }
    assert!(version.starts_with("4."), "OpenCV {version}");
    assert_eq!(
        lines as u64,
        TRIALS * 3 * 7,
        "7 methods x 3 cameras x trials"
    );
    let mut medians = BTreeMap::new();
    eprintln!(
        "OpenCV {version}; base_from_camera error vs truth over {TRIALS} trials x 3 cameras:"
    );
    eprintln!("{:<22} {:>12} {:>12}", "method", "median mm", "median deg");
    for (method, (t, r)) in &mut errors {
        let (mt, mr) = (median(t), median(r));
        eprintln!("{method:<22} {:>12.3} {:>12.4}", mt * 1e3, mr.to_degrees());
        medians.insert(method.clone(), (mt, mr));
    }
    let ours = medians["ours (joint BA)"];
    for (method, (mt, mr)) in &medians {
        if method.starts_with("opencv") {
            assert!(
                ours.0 < *mt && ours.1 < *mr,
                "{method}: {mt} m {mr} rad vs ours {:?}",
                ours
            );
        }
    }
    std::fs::remove_dir_all(&root).unwrap();
}

#[test]
fn simulated_calibration_rig_is_the_simulators_rig() {
    let sim = SimConfig::default_cell();
    let rig = hil_sim::depth_camera::default_rig(0);
    assert_eq!(sim.cameras.len(), rig.len());
    for (c, r) in sim.cameras.iter().zip(&rig) {
        assert_eq!((c.id, c.name.as_str()), (r.id, r.name.as_str()));
        assert_eq!(c.intrinsics, r.intrinsics);
        let (dt, dr) = c.base_from_camera.error_to(&r.base_from_camera);
        assert!(dt < 1e-12 && dr < 1e-9, "camera {}: {dt} {dr}", c.id);
    }
}
