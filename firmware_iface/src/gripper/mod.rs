//! The Robotiq 2F-85 gripper (fact sheet `robotiq_2f85.md`, issue 6): the register model
//! ([`registers`]), the wire codecs of its three transports ([`modbus_rtu`], [`urcap`],
//! [`can`] carried by [`slcan`] adapters or a [`socketcand`] server), the byte transports that carry them ([`transport`]) and the driver
//! ([`driver::RobotiqGripper`]) implementing the [`Gripper`] trait.
//!
//! Libraries: `serialport` opens and configures serial devices (115200 8N1, termios done
//! right on Linux and elsewhere, read timeouts without a hidden thread); `crc` supplies
//! CRC-16/MODBUS; `log` carries the reasons for rejected bytes; with the `socketcan`
//! feature (Linux), the `socketcan` crate opens raw CAN sockets. Codecs do no I/O.

pub mod can;
pub mod driver;
mod error;
pub mod link;
pub mod modbus_rtu;
pub mod registers;
pub mod slcan;
#[cfg(all(feature = "socketcan", target_os = "linux"))]
pub mod socketcan_transport;
pub mod socketcand;
pub mod transport;
pub mod urcap;

use cell_types::{GripperCommand, GripperState};

pub use driver::{Calibration, DriverTiming, RobotiqGripper};
pub use error::GripperError;
pub use link::{connect, GripperLink};
pub use registers::{RequestImage, StatusImage};
pub use transport::RegisterTransport;

/// A parallel gripper, in physical units. Implemented by the Robotiq driver on every
/// transport; the simulator is reached through the same driver over its emulated wire.
pub trait Gripper {
    /// Runs the activation sequence (reset, then rACT) and waits until it completes.
    /// Also clears faults: call it again after a fault.
    fn activate(&mut self) -> Result<GripperState, GripperError>;
    /// Starts a motion to `cmd.width_m` at `cmd.speed_mps` with `cmd.force_n`; returns at once.
    fn command(&mut self, cmd: &GripperCommand) -> Result<(), GripperError>;
    /// Moves like [`Gripper::command`], then waits until the fingers stop (at the target or
    /// on an object) and returns the final state.
    fn move_to(&mut self, cmd: &GripperCommand) -> Result<GripperState, GripperError>;
    /// Opens fully at default speed and force; returns the final state.
    fn open(&mut self) -> Result<GripperState, GripperError>;
    /// Closes fully at default speed and force (stopping on an object); returns the final state.
    fn close(&mut self) -> Result<GripperState, GripperError>;
    /// Reads the current state; a reported fault is returned as [`GripperError::Fault`].
    fn state(&mut self) -> Result<GripperState, GripperError>;
}
