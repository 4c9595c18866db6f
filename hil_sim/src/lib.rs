//! Hardware-in-the-loop simulator: UR controller, Robotiq gripper and D455 cameras on loopback.

pub mod depth_camera;
pub mod scene;
