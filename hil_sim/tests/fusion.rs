//! The fused cloud of the simulated cell against the scene's true surfaces (issue 7
//! acceptance: within 3 sigma for >= 99 % of points, robot removed, overlap agreement within
//! 1.3 sigma, bad input never panics).

// Test helpers outside #[test] functions may unwrap too: a failure there is a test failure.
#![allow(clippy::unwrap_used)]

use std::time::Duration;

use calibration::fusion::{overlap_residual, FusionParams, FusionPipeline};
use cell_types::CameraFrame;
use hil_sim::depth_camera::{default_rig, render_rig, rig_calibration, SimDepthCamera};
use hil_sim::scene::{robot_capsules, Scene, SceneGeometry, HOME_Q};
use nalgebra::Point3;
use rand::{Rng, SeedableRng};

struct Cell {
    rig: Vec<SimDepthCamera>,
    geometry: SceneGeometry,
    frames: Vec<CameraFrame>,
    pipe: FusionPipeline,
}

fn cell(seed: u64) -> Cell {
    let rig = default_rig(seed);
    let geometry = Scene::default_cell().build().unwrap();
    let frames = render_rig(&rig, &geometry, 0, Duration::ZERO).unwrap();
    let pipe = FusionPipeline::new(rig_calibration(&rig), FusionParams::default()).unwrap();
    Cell {
        rig,
        geometry,
        frames,
        pipe,
    }
}

/// The largest axial sigma any camera would have at `p`: a conservative bound on the noise
/// of whichever camera saw it.
fn sigma_at(rig: &[SimDepthCamera], p: &Point3<f64>) -> f64 {
    rig.iter()
        .map(|c| {
            let z = c.base_from_camera.inverse().transform_point(p).z;
            c.noise.sigma_z(z, c.intrinsics.fx)
        })
        .fold(0.0, f64::max)
}

#[test]
fn fused_cloud_lies_within_3_sigma_of_the_true_surfaces() {
    let c = cell(1);
    let robot = robot_capsules(&HOME_Q, 0.085);
    let out = c.pipe.fuse(&c.frames, &robot).unwrap();
    println!("{:?}", out.stats);
    assert_eq!(out.stats.valid_pixels.len(), 3);
    assert!(out.dense.len() > 20_000, "{}", out.dense.len());
    for (what, cloud) in [("dense", &out.dense), ("sampled", &out.sampled)] {
        let within = cloud
            .points
            .iter()
            .filter(|p| {
                let p = p.cast::<f64>();
                c.geometry.distance_to_surface(&p) <= 3.0 * sigma_at(&c.rig, &p)
            })
            .count();
        let frac = within as f64 / cloud.len() as f64;
        println!(
            "{what}: {within} of {} within 3 sigma ({frac:.4})",
            cloud.len()
        );
        assert!(frac >= 0.99, "{what}: only {frac} within 3 sigma");
    }
    assert_eq!(out.sampled.len(), 2048);
    let focus = &c.pipe.params().focus;
    let inside = out
        .sampled
        .points
        .iter()
        .filter(|p| focus.contains(p))
        .count();
    assert_eq!(inside, 1536);
    let rgb = out.sampled.rgb.as_ref().unwrap();
    assert!(
        rgb.iter().any(|c| c[0] > 100 && c[1] < 50 && c[2] < 50),
        "the red box is red"
    );
}

#[test]
fn the_robots_own_points_are_removed() {
    let c = cell(2);
    let robot = robot_capsules(&HOME_Q, 0.085);
    let near_robot = |cloud: &cell_types::PointCloud| {
        cloud
            .points
            .iter()
            .filter(|p| {
                let p = p.cast::<f64>();
                robot.iter().any(|k| k.axis_distance(&p) < k.radius + 0.01)
            })
            .count()
    };
    // Without the robot's geometry the gripper and forearm are in the cloud...
    let with = c.pipe.fuse(&c.frames, &[]).unwrap();
    assert!(near_robot(&with.dense) > 200, "{}", near_robot(&with.dense));
    // ... and with it they are gone.
    let without = c.pipe.fuse(&c.frames, &robot).unwrap();
    assert_eq!(near_robot(&without.dense), 0);
    assert_eq!(near_robot(&without.sampled), 0);
}

#[test]
fn the_three_cameras_agree_in_their_overlap_within_1_3_sigma() {
    let c = cell(3);
    // A patch of bare table that all three cameras see.
    let patch =
        |p: &Point3<f32>| p.x > 0.25 && p.x < 0.4 && p.y > -0.1 && p.y < 0.05 && p.z < -0.04;
    let clouds: Vec<Vec<Point3<f32>>> = c
        .frames
        .iter()
        .map(|f| {
            let (pts, _) = c.pipe.camera_points(f).unwrap();
            pts.xyz.into_iter().filter(|p| patch(p)).collect()
        })
        .collect();
    for a in 0..3 {
        assert!(clouds[a].len() > 1000, "camera {a}: {}", clouds[a].len());
        for b in 0..3 {
            if a == b {
                continue;
            }
            let (rms, mean, n) = overlap_residual(&clouds[a], &clouds[b], 0.01);
            let cam = &c.rig[a];
            let sigma = (clouds[a]
                .iter()
                .map(|p| sigma_at(std::slice::from_ref(cam), &p.cast::<f64>()).powi(2))
                .sum::<f64>()
                / clouds[a].len() as f64)
                .sqrt();
            // Axial noise moves a point along its ray; across the table (normal +z) that is
            // sigma_z * |ray . z| / z: the residual the model predicts for this geometry.
            let eye = cam.base_from_camera.translation();
            let across = (clouds[a]
                .iter()
                .map(|p| {
                    let p = p.cast::<f64>();
                    let z = cam.base_from_camera.inverse().transform_point(&p).z;
                    let s = cam.noise.sigma_z(z, cam.intrinsics.fx) * (p.coords - eye).z.abs() / z;
                    s * s
                })
                .sum::<f64>()
                / clouds[a].len() as f64)
                .sqrt();
            println!("camera {a} vs {b}: rms {:.3} mm, mean {:.3} mm, sigma_z {:.3} mm, predicted across the table {:.3} mm, n {n}", rms * 1e3, mean * 1e3, sigma * 1e3, across * 1e3);
            assert!(n > 1000);
            assert!(rms <= 1.3 * sigma, "{a} vs {b}: rms {rms} sigma {sigma}");
            assert!(
                rms <= 1.3 * across && rms >= 0.7 * across,
                "{a} vs {b}: rms {rms} predicted {across}"
            );
            assert!(mean.abs() < 1e-3, "{a} vs {b}: mean offset {mean}");
        }
    }
}

#[test]
fn fusion_is_deterministic() {
    let c = cell(4);
    let robot = robot_capsules(&HOME_Q, 0.085);
    assert_eq!(
        c.pipe.fuse(&c.frames, &robot).unwrap(),
        c.pipe.fuse(&c.frames, &robot).unwrap()
    );
}

#[test]
fn garbage_depth_never_panics() {
    let c = cell(5);
    let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(9);
    for trial in 0..4 {
        let mut frames = c.frames.clone();
        for f in &mut frames {
            for d in &mut f.depth.raw.data {
                *d = match trial {
                    0 => rng.random(),
                    1 => u16::MAX,
                    2 => 0,
                    _ => rng.random_range(0..3),
                };
            }
        }
        // Any typed outcome is fine; a panic fails the test.
        let _ = c.pipe.fuse(&frames, &[]);
    }
    let mut frames = c.frames.clone();
    for f in &mut frames {
        f.depth.raw.data.fill(0);
    }
    assert!(matches!(
        c.pipe.fuse(&frames, &[]),
        Err(calibration::CalibrationError::NoValidDepth { camera: 0, .. })
    ));
}
