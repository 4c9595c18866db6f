//! The D455 backend (`firmware_iface::realsense`) against the real librealsense 2.59, with
//! no camera: the pyrealsense2 wheel in the venv statically contains librealsense and
//! exports its `rs2_*` C API, so the backend's dlopen path talks to the real library.
//!
//! - With no device connected, opening a serial fails with the typed "not connected" error
//!   (a real context and device query).
//! - librealsense's own recorder (driven from Python: a software device streaming depth Z16
//!   and IR Y8, `tests/peers/realsense_bag.py`) writes a recording with frames whose every
//!   pixel is known; the backend plays it through the same pipeline code as a live device
//!   and must return every frame, size, intrinsic, timestamp and depth value exactly, in
//!   millimetres whatever the recorded depth units, then time out at the end (no repeat).

#![allow(clippy::unwrap_used, clippy::expect_used)] // test helpers may panic

use std::path::Path;
use std::time::Duration;

use cell_types::config::DepthMode;
use firmware_iface::camera::{CameraError, DepthCamera};
use firmware_iface::realsense::{DistortionModel, RealSenseCamera, RealSenseError};

const W: u32 = 64;
const H: u32 = 48;
const FPS: u32 = 30;
const FRAMES: u32 = 5;

#[test]
fn open_without_a_camera_says_none_is_connected() {
    tests::load_venv_librealsense().unwrap();
    let e = RealSenseCamera::open(0, "123456789012", DepthMode::W848H480, 30).unwrap_err();
    match &e {
        RealSenseError::NotConnected { serial, connected } => {
            assert_eq!(serial, "123456789012");
            assert!(connected.is_empty(), "{connected:?}");
        }
        other => panic!("expected NotConnected, got {other:?}"),
    }
    assert!(
        e.to_string()
            .starts_with("no D455 with serial 123456789012; connected: none"),
        "{e}"
    );
    assert!(firmware_iface::realsense::connected_devices()
        .unwrap()
        .is_empty());
}

/// Writes a recording with the peer and returns its path.
fn record(dir: &Path, name: &str, units: f64) -> std::path::PathBuf {
    std::fs::create_dir_all(dir).unwrap();
    let path = dir.join(name);
    let _ = std::fs::remove_file(&path);
    let out = tests::run_peer(
        "realsense_bag.py",
        &[
            path.to_str().unwrap(),
            &W.to_string(),
            &H.to_string(),
            &FPS.to_string(),
            &FRAMES.to_string(),
            &units.to_string(),
        ],
    )
    .unwrap();
    let v: serde_json::Value = serde_json::from_str(out.trim()).unwrap();
    assert_eq!(v["frames"], FRAMES);
    assert!(path.exists(), "the peer wrote no {}", path.display());
    path
}

/// Plays `path` and checks every frame against the peer's formula.
fn check_playback(path: &Path) {
    let mut cam = RealSenseCamera::open_recording(3, path).unwrap();
    cam.set_timeout(Duration::from_millis(500));
    let d = *cam.depth_intrinsics();
    assert_eq!((d.width, d.height), (W, H));
    // The peer's intrinsics (exact in f32).
    assert_eq!((d.fx, d.fy), (421.25, 420.75));
    assert_eq!(
        (d.ppx, d.ppy),
        (
            f64::from(W) / 2.0 - 0.5 + 1.25,
            f64::from(H) / 2.0 - 0.5 - 0.75
        )
    );
    assert_eq!(d.model, DistortionModel::None);
    assert_eq!(d.coeffs, [0.0; 5]);
    assert_eq!(cam.ir_intrinsics(), Some(&d));
    assert_eq!(cam.fps(), FPS);
    assert_eq!(cam.id(), 3);

    for i in 0..FRAMES {
        let f = cam.capture().unwrap();
        assert_eq!(f.camera, 3);
        // The recording keeps timestamps to the microsecond.
        let ms = f.timestamp.as_secs_f64() * 1e3;
        let want = f64::from(i) * 1000.0 / f64::from(FPS);
        assert!(
            (ms - want).abs() < 1e-3,
            "frame {i} at {ms} ms, want {want}"
        );
        assert_eq!(f.depth.depth_scale, 0.001);
        assert_eq!((f.depth.raw.width, f.depth.raw.height), (W, H));
        assert!(f.colour.is_none());
        let ir = f.ir.as_ref().expect("an IR image");
        assert_eq!((ir.width, ir.height), (W, H));
        for v in 0..H {
            for u in 0..W {
                let mm = 500 + 3 * u + 7 * v + 11 * i;
                assert_eq!(
                    u32::from(*f.depth.raw.get(u, v).unwrap()),
                    mm,
                    "frame {i} depth at ({u}, {v})"
                );
                let grey = (u + 2 * v + 5 * i) % 256;
                assert_eq!(
                    u32::from(*ir.get(u, v).unwrap()),
                    grey,
                    "frame {i} IR at ({u}, {v})"
                );
            }
        }
    }
    // Played once: past the last frame nothing more comes.
    assert_eq!(
        cam.capture().unwrap_err(),
        CameraError::Timeout {
            camera: 3,
            timeout_ms: 500
        }
    );
}

#[test]
fn a_recording_plays_back_exactly() {
    tests::load_venv_librealsense().unwrap();
    let dir = std::env::temp_dir().join(format!("equact-realsense-{}", std::process::id()));
    // The D455's own unit: raw values are millimetres already.
    check_playback(&record(&dir, "mm.db3", 0.001));
    // 100 um units (a D455 set to finer depth units): converted to millimetres.
    check_playback(&record(&dir, "tenth_mm.db3", 0.0001));
    let _ = std::fs::remove_dir_all(&dir);
}

#[test]
fn a_missing_recording_is_a_typed_error() {
    tests::load_venv_librealsense().unwrap();
    let e = RealSenseCamera::open_recording(0, Path::new("/nonexistent/cell.db3")).unwrap_err();
    assert!(
        matches!(&e, RealSenseError::Call { message, .. } if !message.is_empty()),
        "{e:?}"
    );
    assert!(e.to_string().contains("/nonexistent/cell.db3"), "{e}");
}
