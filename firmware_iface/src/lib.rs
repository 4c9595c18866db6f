//! Hardware traits (Arm, Gripper, DepthCamera), wire codecs with no I/O, and the real UR5 and Robotiq drivers.

pub mod camera;
