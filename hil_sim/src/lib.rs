//! Hardware-in-the-loop simulator: UR controller, Robotiq gripper and D455 cameras on loopback.

pub mod ur_controller;
pub mod gripper;
