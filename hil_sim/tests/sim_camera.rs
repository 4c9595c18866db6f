//! The simulated D455 against its noise model (issue 7 acceptance: plane recovery, sigma at
//! 0.6 / 1 / 1.5 m within 20 %, holes, band, flying pixels, determinism).

// Test helpers outside #[test] functions may unwrap too: a failure there is a test failure.
#![allow(clippy::unwrap_used)]

use std::sync::{Arc, RwLock};
use std::time::Duration;

use calibration::camera::raw_depth_to_m;
use cell_types::{Clock, ManualClock};
use firmware_iface::camera::DepthCamera;
use hil_sim::depth_camera::{default_rig, look_at, NoiseModel, SimCameraDevice, SimDepthCamera};
use hil_sim::scene::{Material, Part, Primitive, Scene, SceneObject};
use nalgebra::{Isometry3, Point2, Point3, Vector3};

fn camera(noise: NoiseModel, eye: Point3<f64>, target: Point3<f64>) -> SimDepthCamera {
    let mut cam = default_rig(11).remove(0);
    cam.base_from_camera = look_at(eye, target);
    cam.noise = noise;
    cam
}

/// A wall (box) whose front face is the plane x = `x`, facing -x.
fn wall_scene(x: f64) -> Scene {
    Scene {
        objects: vec![SceneObject {
            name: "wall".into(),
            base_from_object: Isometry3::translation(x + 0.05, 0.0, 0.0),
            shape: Primitive::Box {
                half_extents: [0.05, 5.0, 5.0],
            },
            material: Material::default(),
            part: Part::Object,
        }],
        table_height: -1.0,
    }
}

fn valid_depths(frame: &cell_types::CameraFrame) -> Vec<(usize, usize, f64)> {
    let w = frame.depth.raw.width as usize;
    frame
        .depth
        .raw
        .data
        .iter()
        .enumerate()
        .filter_map(|(i, &r)| raw_depth_to_m(r, frame.depth.depth_scale).map(|d| (i % w, i / w, d)))
        .collect()
}

#[test]
fn axial_noise_matches_the_model_at_0_6_1_and_1_5_m() {
    for z0 in [0.6, 1.0, 1.5] {
        let g = wall_scene(z0).build().unwrap();
        let cam = camera(
            NoiseModel::d455(),
            Point3::origin(),
            Point3::new(1.0, 0.0, 0.0),
        );
        let frame = cam.render(&g, 0, Duration::ZERO).unwrap();
        let d = valid_depths(&frame);
        assert!(d.len() > 300_000, "{} valid pixels", d.len());
        let n = d.len() as f64;
        let mean = d.iter().map(|p| p.2 - z0).sum::<f64>() / n;
        let sd = (d.iter().map(|p| (p.2 - z0 - mean).powi(2)).sum::<f64>() / n).sqrt();
        let model = cam.noise.sigma_z(z0, cam.intrinsics.fx);
        println!(
            "z = {z0} m: measured sigma {:.3} mm, model {:.3} mm",
            sd * 1e3,
            model * 1e3
        );
        assert!(
            (sd / model - 1.0).abs() < 0.2,
            "z {z0}: sd {sd} model {model}"
        );
        assert!(mean.abs() < 0.2e-3, "bias {mean}");
    }
}

#[test]
fn deprojected_tilted_plane_recovers_the_plane_within_sigma() {
    // A plane through (1, 0, 0) tilted 30° about z, seen from the origin.
    let tilt = 30f64.to_radians();
    let normal = Vector3::new(-tilt.cos(), -tilt.sin(), 0.0); // facing the camera
    let mut s = wall_scene(0.0);
    s.objects[0].base_from_object =
        Isometry3::new(Vector3::new(1.0, 0.0, 0.0), Vector3::z() * tilt)
            * Isometry3::translation(0.05, 0.0, 0.0);
    let g = s.build().unwrap();
    let cam = camera(
        NoiseModel::d455(),
        Point3::origin(),
        Point3::new(1.0, 0.0, 0.0),
    );
    let frame = cam.render(&g, 3, Duration::ZERO).unwrap();
    let iso = cam.base_from_camera.isometry();
    let pts: Vec<Point3<f64>> = valid_depths(&frame)
        .into_iter()
        .map(|(u, v, d)| {
            let p = cam
                .intrinsics
                .deproject(Point2::new(u as f64, v as f64), d)
                .unwrap();
            iso.transform_point(&p)
        })
        .collect();
    assert!(pts.len() > 100_000);
    // Least-squares plane: centroid + smallest eigenvector of the scatter.
    let c = pts.iter().fold(Vector3::zeros(), |a, p| a + p.coords) / pts.len() as f64;
    let mut m = nalgebra::Matrix3::zeros();
    for p in &pts {
        let d = p.coords - c;
        m += d * d.transpose();
    }
    let eig = m.symmetric_eigen();
    let i = eig.eigenvalues.imin();
    let n_fit = eig.eigenvectors.column(i).into_owned();
    let angle = n_fit.dot(&normal).abs().min(1.0).acos();
    let offset = (c - Vector3::new(1.0, 0.0, 0.0)).dot(&normal);
    // sigma at the plane's mean depth along the optical axis.
    let z_mean = pts
        .iter()
        .map(|p| iso.inverse_transform_point(p).z)
        .sum::<f64>()
        / pts.len() as f64;
    let sigma = cam.noise.sigma_z(z_mean, cam.intrinsics.fx);
    let rms = (pts
        .iter()
        .map(|p| (p.coords - c).dot(&n_fit).powi(2))
        .sum::<f64>()
        / pts.len() as f64)
        .sqrt();
    println!(
        "plane: angle {:.2e} rad, offset {:.3} mm, rms {:.3} mm, sigma {:.3} mm",
        angle,
        offset * 1e3,
        rms * 1e3,
        sigma * 1e3
    );
    assert!(offset.abs() < sigma, "offset {offset} sigma {sigma}");
    assert!(angle < 1e-3, "normal off by {angle} rad");
    assert!(rms < 2.0 * sigma, "rms {rms} sigma {sigma}");
}

#[test]
fn ideal_camera_reports_true_depth_to_the_millimetre() {
    let g = wall_scene(0.8).build().unwrap();
    let cam = camera(
        NoiseModel::ideal(),
        Point3::origin(),
        Point3::new(1.0, 0.0, 0.0),
    );
    let frame = cam.render(&g, 0, Duration::ZERO).unwrap();
    assert!(frame.depth.raw.data.iter().all(|&r| r == 800));
}

#[test]
fn left_band_is_f_b_over_z_wide_and_dropouts_are_two_percent() {
    let z0 = 1.0;
    let g = wall_scene(z0).build().unwrap();
    let cam = camera(
        NoiseModel::d455(),
        Point3::origin(),
        Point3::new(1.0, 0.0, 0.0),
    );
    let frame = cam.render(&g, 0, Duration::ZERO).unwrap();
    let w = frame.depth.raw.width as usize;
    let band = cam.intrinsics.fx * cam.noise.baseline_m / z0; // ~40 px
    let col_valid = |u: usize| {
        (0..frame.depth.raw.height as usize)
            .filter(|v| frame.depth.raw.data[v * w + u] != 0)
            .count()
    };
    assert_eq!(col_valid(0), 0);
    assert_eq!(col_valid(band as usize - 1), 0);
    assert!(col_valid(band as usize + 2) > 400);
    let outside = (band as usize + 2) * frame.depth.raw.height as usize;
    let total = frame.depth.raw.data.len() - outside;
    let holes = frame
        .depth
        .raw
        .data
        .iter()
        .enumerate()
        .filter(|(i, &r)| i % w > band as usize + 1 && r == 0)
        .count();
    let rate = holes as f64 / total as f64;
    assert!((rate - 0.02).abs() < 0.003, "dropout rate {rate}");
}

#[test]
fn grazing_surfaces_are_holes() {
    // A floor seen at 80° incidence (cos 0.17 < 0.2) has no depth; at 45° it has.
    let mut s = wall_scene(0.0);
    s.objects[0].base_from_object = Isometry3::translation(0.0, 0.0, -0.05 - 0.6);
    s.objects[0].shape = Primitive::Box {
        half_extents: [5.0, 5.0, 0.05],
    }; // floor top at z = -0.6
    let g = s.build().unwrap();
    let steep = camera(
        NoiseModel::d455(),
        Point3::origin(),
        Point3::new(1.0, 0.0, -1.0),
    );
    let frame = steep.render(&g, 0, Duration::ZERO).unwrap();
    let (w, h) = (
        frame.depth.raw.width as usize,
        frame.depth.raw.height as usize,
    );
    assert_ne!(
        frame.depth.raw.data[(h / 2) * w + w / 2],
        0,
        "45° must be seen"
    );
    let shallow = camera(
        NoiseModel::d455(),
        Point3::origin(),
        Point3::new(
            1.0,
            0.0,
            -(80f64.to_radians().cos() / 80f64.to_radians().sin()),
        ),
    );
    let frame = shallow.render(&g, 0, Duration::ZERO).unwrap();
    let centre_row: Vec<u16> = (w / 2 - 5..w / 2 + 5)
        .map(|u| frame.depth.raw.data[(h / 2) * w + u])
        .collect();
    assert!(centre_row.iter().all(|&r| r == 0), "{centre_row:?}");
}

#[test]
fn flying_pixels_appear_at_depth_edges_only_with_the_noise_model() {
    // A 0.2 m cube 0.8 m away in front of a wall at 1.5 m.
    let mut s = wall_scene(1.5);
    s.add_object(
        "cube",
        Isometry3::translation(0.9, 0.0, 0.0),
        Primitive::Box {
            half_extents: [0.1; 3],
        },
        [1, 2, 3],
    );
    let g = s.build().unwrap();
    let count_between = |noise: NoiseModel| {
        let cam = camera(noise, Point3::origin(), Point3::new(1.0, 0.0, 0.0));
        let f = cam.render(&g, 0, Duration::ZERO).unwrap();
        f.depth
            .raw
            .data
            .iter()
            .filter(|&&r| r > 830 && r < 1460)
            .count()
    };
    assert_eq!(count_between(NoiseModel::ideal()), 0);
    assert!(count_between(NoiseModel::d455()) > 100);
}

#[test]
fn frames_are_deterministic_per_seed_and_frame_index_and_thread_count() {
    let g = Scene::default_cell().build().unwrap();
    let mut cam = default_rig(5).remove(1);
    cam.threads = 1;
    let a = cam.render(&g, 7, Duration::ZERO).unwrap();
    cam.threads = 3;
    let b = cam.render(&g, 7, Duration::ZERO).unwrap();
    assert_eq!(a, b);
    let c = cam.render(&g, 8, Duration::ZERO).unwrap();
    assert_ne!(a.depth, c.depth);
    assert!(a.ir.as_ref().unwrap().data.iter().any(|&v| v > 20));
    assert!(a
        .colour
        .as_ref()
        .unwrap()
        .data
        .iter()
        .any(|c| c[0] > 100 && c[1] < 60));
}

#[test]
fn sim_camera_device_is_a_depth_camera_with_clock_timestamps() {
    let clock = ManualClock::new();
    let scene = Arc::new(RwLock::new(Scene::default_cell().build().unwrap()));
    let mut cam = default_rig(1).remove(0);
    cam.intrinsics = calibration::Intrinsics::d455_depth(calibration::DepthMode::Vga640x480);
    let mut dev = SimCameraDevice::new(cam, scene, Arc::new(clock.clone()));
    clock.advance(Duration::from_millis(33));
    let f1 = dev.capture().unwrap();
    clock.advance(Duration::from_millis(33));
    let f2 = dev.capture().unwrap();
    assert_eq!(dev.id(), 0);
    assert_eq!((f1.depth.raw.width, f1.depth.raw.height), (640, 480));
    assert_eq!(f1.timestamp, Duration::from_millis(33));
    assert_eq!(f2.timestamp, clock.now());
    assert_ne!(f1.depth, f2.depth, "each capture draws new noise");
}
