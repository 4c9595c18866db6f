//! Hardware traits (Arm, Gripper, DepthCamera), wire codecs with no I/O, and the real UR5 and Robotiq drivers.

pub mod arm;
pub mod camera;
pub mod dashboard;
pub mod gripper;
pub mod realsense;
pub mod rtde;
pub mod ur;
pub mod urscript;
