//! UR5 model from URDF, FK/IK, collision model, cloud structure, path planning and
//! jerk-limited timing.

pub mod kinematics;
