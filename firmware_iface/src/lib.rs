//! Hardware traits (Arm, Gripper, DepthCamera), wire codecs with no I/O, and the real UR5 and Robotiq drivers.
//!
//! # Cameras
//!
//! [`realsense::RealSenseCamera`] is the Intel RealSense D455 driver. It loads librealsense2
//! at run time (dlopen), so the crate builds and tests without it and has no `realsense`
//! feature: there is nothing to gate, the build costs one small pure-Rust dependency
//! (`libloading`), and CI exercises the backend on every run. On the cell's machine install
//! librealsense2 (Debian/Ubuntu: `librealsense2-dev` from Intel's apt repository) or set
//! `EQUACT_LIBREALSENSE=/path/to/librealsense2.so`; without it, opening a camera returns
//! [`realsense::RealSenseError::LibraryNotFound`], which says so. The tests
//! (`tests/tests/realsense.rs`) run the driver against the real librealsense contained in
//! the `pyrealsense2` wheel of the test venv: no camera connected, and recordings written
//! by librealsense's recorder played back pixel for pixel.

pub mod arm;
pub mod camera;
pub mod dashboard;
pub mod gripper;
pub mod realsense;
pub mod realtime;
pub mod rtde;
pub mod ur;
pub mod urscript;
