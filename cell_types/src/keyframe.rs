//! Keyframes: what the policy emits and the planner consumes.

use serde::{Deserialize, Serialize};

use crate::error::CellTypesError;
use crate::frames::{Base, Tcp, Transform};

/// One keyframe of a keyframe policy (PerAct / 3D Diffuser Actor / EquAct convention).
#[derive(Copy, Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Keyframe {
    /// Target TCP pose in the robot base frame.
    pub base_from_tcp: Transform<Base, Tcp>,
    /// Gripper state to reach at the keyframe: `true` open, `false` closed.
    pub gripper_open: bool,
    /// Plan the motion without the observed cloud (still with self-collision and the cell's
    /// static geometry), as the keyframe-policy literature's "ignore collisions" flag.
    pub ignore_collisions: bool,
}

impl Keyframe {
    /// Builds a keyframe, rejecting a non-finite or non-unit pose.
    pub fn new(
        base_from_tcp: Transform<Base, Tcp>,
        gripper_open: bool,
        ignore_collisions: bool,
    ) -> Result<Self, CellTypesError> {
        if !base_from_tcp.is_finite() {
            return Err(CellTypesError::NotFinite {
                what: "keyframe pose",
                value: f64::NAN,
            });
        }
        Ok(Self {
            base_from_tcp,
            gripper_open,
            ignore_collisions,
        })
    }
}
