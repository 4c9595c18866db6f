//! The depth-camera hardware trait (ARCHITECTURE.md "Cameras"; issue 7 item 4).
//!
//! Implemented by `hil_sim::depth_camera::SimDepthCamera` and by the librealsense D455
//! driver [`crate::realsense::RealSenseCamera`] (librealsense loaded at run time). Intrinsics and
//! extrinsics are not part of a frame: they come from `calibration` (factory intrinsics or
//! `calibration.toml`), so the fusion never trusts a driver's idea of where it is.

use cell_types::CameraFrame;
use thiserror::Error;

/// Why a camera could not deliver a frame.
#[derive(Debug, Error, PartialEq)]
#[non_exhaustive]
pub enum CameraError {
    /// No frame arrived within the timeout.
    #[error("camera {camera}: no frame within {timeout_ms} ms; check the USB 3 link and that the stream is started")]
    Timeout {
        /// The camera id.
        camera: u8,
        /// The timeout (ms).
        timeout_ms: u64,
    },
    /// The device is gone or failed.
    #[error("camera {camera}: device error: {message}; replug the camera or restart the stream")]
    Device {
        /// The camera id.
        camera: u8,
        /// What the device or library reported.
        message: String,
    },
}

/// A depth camera that delivers depth frames (and optionally IR and aligned colour).
pub trait DepthCamera: Send {
    /// The camera's id (its `FrameId::Camera` index, as `calibration.toml` names it).
    fn id(&self) -> u8;
    /// Captures the next frame, blocking until it arrives.
    fn capture(&mut self) -> Result<CameraFrame, CameraError>;
}
