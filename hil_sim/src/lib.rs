//! Hardware-in-the-loop simulator: UR controller, Robotiq gripper and D455 cameras on loopback.
//!
//! Perception modules (issue 7): [`scene`] (table, objects, the arm as capsules) and
//! [`depth_camera`] (D455-like depth/IR/colour by ray casting with parry3d, with the
//! sensor's noise model).

pub mod depth_camera;
pub mod scene;
