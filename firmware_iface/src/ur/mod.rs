//! The UR5 driver: RTDE client thread, dashboard client, servo program upload, and the
//! [`crate::arm::Arm`] implementation [`UrArm`] that streams trajectories through the
//! register contract of `urscript/CONTRACT.md` (UR fact sheet, "RTDE", "Dashboard server",
//! "Commanding motion").

/// The three controller ports the driver and the simulator use.
#[derive(Copy, Clone, Debug, PartialEq, Eq, Hash)]
pub struct UrPorts {
    /// RTDE (30004 on a real controller).
    pub rtde: u16,
    /// Dashboard server (29999).
    pub dashboard: u16,
    /// Secondary interface, where URScript programs are sent (30002).
    pub secondary: u16,
}

impl Default for UrPorts {
    fn default() -> Self {
        Self {
            rtde: 30004,
            dashboard: 29999,
            secondary: 30002,
        }
    }
}
