//! Choosing the gripper's transport at run time (issue 6, item 2): one value saying where
//! the gripper is, one call that connects the driver over it. The main job fills
//! [`GripperLink`] from `cell.toml` and gets a `Box<dyn Gripper + Send>`.

use std::sync::Arc;

use cell_types::Clock;

use super::can::CanMapping;
use super::driver::{Calibration, DriverTiming, RobotiqGripper};
use super::transport::{ModbusRtuTransport, SlcanTransport, SocketcandTransport, UrcapTransport};
use super::{Gripper, GripperError};

/// Where the gripper is and which wire reaches it.
#[derive(Clone, Debug, PartialEq)]
pub enum GripperLink {
    /// Modbus RTU on a serial device (115200 8N1).
    ModbusRtu {
        /// Serial device, e.g. `/dev/ttyUSB0`.
        path: String,
        /// Slave id (Robotiq default 9).
        slave: u8,
    },
    /// The URCap text socket on the UR controller.
    Urcap {
        /// `host:port`, port 63352 on a UR controller.
        addr: String,
    },
    /// CAN through an slcan serial adapter.
    Slcan {
        /// Serial device of the adapter.
        path: String,
        /// CAN ids of the register images.
        mapping: CanMapping,
    },
    /// CAN through a socketcand server.
    Socketcand {
        /// `host:port`, port 29536 by default.
        addr: String,
        /// Bus name on the server, e.g. `can0`.
        bus: String,
        /// CAN ids of the register images.
        mapping: CanMapping,
    },
    /// CAN on a SocketCAN interface (needs the `socketcan` feature and a Linux kernel with CAN).
    Socketcan {
        /// Interface name, e.g. `can0`.
        ifname: String,
        /// CAN ids of the register images.
        mapping: CanMapping,
    },
}

fn boxed<T: super::RegisterTransport + 'static>(
    t: T,
    clock: Arc<dyn Clock>,
    calibration: Calibration,
    timing: DriverTiming,
) -> Result<Box<dyn Gripper + Send>, GripperError> {
    Ok(Box::new(
        RobotiqGripper::new(t, clock)
            .with_calibration(calibration)?
            .with_timing(timing),
    ))
}

/// Connects the Robotiq driver over `link` (not yet activated: call `activate`).
pub fn connect(
    link: &GripperLink,
    calibration: Calibration,
    timing: DriverTiming,
    clock: Arc<dyn Clock>,
) -> Result<Box<dyn Gripper + Send>, GripperError> {
    calibration.validate()?;
    match link {
        GripperLink::ModbusRtu { path, slave } => boxed(
            ModbusRtuTransport::open(path, *slave)?,
            clock,
            calibration,
            timing,
        ),
        GripperLink::Urcap { addr } => boxed(
            UrcapTransport::connect(addr.as_str(), super::transport::DEFAULT_REPLY_TIMEOUT)?,
            clock,
            calibration,
            timing,
        ),
        GripperLink::Slcan { path, mapping } => boxed(
            SlcanTransport::open(path, *mapping)?,
            clock,
            calibration,
            timing,
        ),
        GripperLink::Socketcand { addr, bus, mapping } => boxed(
            SocketcandTransport::connect(addr.as_str(), bus, *mapping)?,
            clock,
            calibration,
            timing,
        ),
        GripperLink::Socketcan { ifname, mapping } => {
            socketcan(ifname, *mapping, clock, calibration, timing)
        }
    }
}

#[cfg(all(feature = "socketcan", target_os = "linux"))]
fn socketcan(
    ifname: &str,
    mapping: CanMapping,
    clock: Arc<dyn Clock>,
    calibration: Calibration,
    timing: DriverTiming,
) -> Result<Box<dyn Gripper + Send>, GripperError> {
    let t = super::socketcan_transport::SocketcanTransport::open(ifname, mapping)?;
    boxed(t, clock, calibration, timing)
}

#[cfg(not(all(feature = "socketcan", target_os = "linux")))]
fn socketcan(
    ifname: &str,
    _mapping: CanMapping,
    _clock: Arc<dyn Clock>,
    _calibration: Calibration,
    _timing: DriverTiming,
) -> Result<Box<dyn Gripper + Send>, GripperError> {
    Err(GripperError::TransportUnavailable {
        transport: "socketcan",
        detail: format!(
            "cannot open {ifname}: this build has no SocketCAN support; rebuild with \
             `--features firmware_iface/socketcan` on Linux, or use an slcan adapter"
        ),
    })
}
