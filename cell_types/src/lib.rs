//! The shared vocabulary of the cell stack.
//!
//! Every other crate speaks these types: frame-tagged rigid transforms ([`Transform`]),
//! joint vectors ([`Joints`], [`JointState`]), point clouds ([`PointCloud`]), policy
//! keyframes ([`Keyframe`]), time-stamped joint trajectories ([`Trajectory`]) and gripper
//! commands and states ([`gripper`]); and the one algorithm two crates need bit for bit,
//! farthest point sampling of clouds ([`fps`]). Units are SI inside (metres, radians, seconds,
//! newtons); degrees and millimetres only at the edges (CLI, config files, wire formats).
//!
//! Uses `nalgebra` for the linear algebra (the workspace's one matrix library) and `serde`
//! so that every type can be recorded and configured.

pub mod clock;
pub mod cloud;
pub mod config;
pub mod error;
pub mod fps;
pub mod frames;
pub mod gripper;
pub mod image;
pub mod joints;
pub mod keyframe;
pub mod trajectory;

pub use clock::{Clock, ManualClock, ScaledClock, SystemClock, TickClock};
pub use cloud::{PointCloud, Rgb};
pub use config::{CellConfig, ConfigError};
pub use error::CellTypesError;
pub use frames::{Base, Board, Camera, Flange, Frame, FrameId, Tcp, Transform, World};
pub use gripper::{GripperCommand, GripperFault, GripperState, ObjectStatus};
pub use image::{CameraFrame, DepthImage, Image};
pub use joints::{JointState, Joints, JOINT_COUNT};
pub use keyframe::Keyframe;
pub use trajectory::{Trajectory, TrajectorySample};
