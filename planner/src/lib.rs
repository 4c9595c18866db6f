//! UR5 model from URDF, FK/IK, collision model, cloud structure, path planning and
//! jerk-limited timing (issues 2 item 3 and 3).
//!
//! Libraries: `urdf-rs` parses the URDF; `nalgebra` is the workspace's linear algebra;
//! `rsruckig` (pure-Rust Ruckig) does jerk-limited timing without the C++ library's cloud
//! client; `rand_chacha` gives seeded, platform-independent sampling for RRT-Connect;
//! `parry3d` gives the exact link, obstacle and point queries of the final re-check of every
//! trajectory ([`exact`]), independent of the sphere model the search uses; `cpu-time` reads
//! the thread's CPU clock for benchmark stage times (a safe wrapper of `clock_gettime`).
//!
//! Keyframe semantics against the observed cloud ([`Planner::plan_to_keyframe`]): cloud
//! points in the gripper's closing volume at the goal are the object to grasp or place, and
//! points inside the gripper where it stands at the start are what it holds or touches; both
//! are excluded for that one motion. "Ignore collisions" drops the cloud; static obstacles
//! (the table) always count.

pub mod checker;
pub mod cloud_io;
pub mod collision;
pub mod error;
pub mod exact;
pub mod ik;
pub mod kdtree;
pub mod kinematics;
pub mod mbm;
pub mod model;
pub mod planner;
pub mod rrt;
pub mod timing;
pub mod urdf;
pub mod world;

pub use error::{Contact, ExactContact, ExactOther, PlanError};
pub use model::RobotModel;
pub use planner::{ClosingVolume, PlanStats, PlannedMotion, Planner, PlannerConfig, StageClock};
pub use rrt::RrtParams;
pub use timing::PlannerLimits;
pub use world::{CloudParams, Obstacle, World};
