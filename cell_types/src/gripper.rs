//! Gripper commands and states in physical units (the register counts live in the driver).

use serde::{Deserialize, Serialize};

use crate::error::{ensure_finite, CellTypesError};

/// A gripper motion request: opening width (m), finger speed (m/s) and grip force (N).
#[derive(Copy, Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct GripperCommand {
    /// Target opening between the fingertips (m), 0 = closed.
    pub width_m: f64,
    /// Finger speed (m/s).
    pub speed_mps: f64,
    /// Grip force (N).
    pub force_n: f64,
}

impl GripperCommand {
    /// Builds a command, rejecting negative or non-finite values.
    pub fn new(width_m: f64, speed_mps: f64, force_n: f64) -> Result<Self, CellTypesError> {
        for (what, v) in [
            ("gripper width", width_m),
            ("gripper speed", speed_mps),
            ("gripper force", force_n),
        ] {
            ensure_finite(what, v)?;
            if v < 0.0 {
                return Err(CellTypesError::OutOfRange {
                    what,
                    value: v,
                    min: 0.0,
                    max: f64::INFINITY,
                });
            }
        }
        Ok(Self {
            width_m,
            speed_mps,
            force_n,
        })
    }
}

/// What the fingers report about an object (Robotiq gOBJ semantics).
#[derive(Copy, Clone, Debug, PartialEq, Eq, Serialize, Deserialize)]
pub enum ObjectStatus {
    /// Fingers are moving towards the requested position.
    Moving,
    /// Fingers stopped by contact while opening.
    ContactOpening,
    /// Fingers stopped by contact while closing: an object is held.
    ContactClosing,
    /// Fingers at the requested position, no object.
    AtTarget,
}

/// A gripper fault, as reported by the device.
#[derive(Copy, Clone, Debug, PartialEq, Eq, Serialize, Deserialize)]
pub enum GripperFault {
    /// Action delayed: the gripper must be activated first (Robotiq 0x05).
    ActivationRequired,
    /// The activation bit is not set (Robotiq 0x07).
    ActivationBitNotSet,
    /// Communication fault (Robotiq 0x08, 0x09: no communication for a second).
    Communication(u8),
    /// A major fault that needs re-activation (Robotiq 0x0A–0x0F), with its code.
    Major(u8),
    /// Any other fault code.
    Other(u8),
}

/// The gripper's state in physical units.
#[derive(Copy, Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct GripperState {
    /// True once activation has completed.
    pub activated: bool,
    /// Opening between the fingertips (m).
    pub width_m: f64,
    /// Object detection status.
    pub object: ObjectStatus,
    /// Motor current (A).
    pub current_a: f64,
    /// Active fault, if any.
    pub fault: Option<GripperFault>,
}

impl GripperState {
    /// True when the fingers stopped on an object while closing.
    pub fn holds_object(&self) -> bool {
        self.object == ObjectStatus::ContactClosing
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn negative_or_nan_commands_rejected() {
        assert!(GripperCommand::new(0.04, 0.1, 50.0).is_ok());
        assert!(matches!(
            GripperCommand::new(-0.01, 0.1, 50.0),
            Err(CellTypesError::OutOfRange {
                what: "gripper width",
                ..
            })
        ));
        assert!(matches!(
            GripperCommand::new(0.01, f64::NAN, 50.0),
            Err(CellTypesError::NotFinite {
                what: "gripper speed",
                ..
            })
        ));
    }
}
