//! Errors of the Robotiq gripper codecs, transports and driver (module-level, so that the
//! UR arm modules of this crate keep their own enum).

use std::time::Duration;

use cell_types::GripperFault;
use thiserror::Error;

/// Why a gripper frame, line or command was rejected, or a gripper operation failed.
#[derive(Debug, Error)]
#[non_exhaustive]
pub enum GripperError {
    /// A Modbus RTU frame whose CRC does not match its contents.
    #[error("Modbus RTU frame CRC mismatch: frame carries {got:#06x}, contents give {expected:#06x}; line noise or a wrong baud rate (must be 115200 8N1)")]
    Crc {
        /// CRC computed over the frame.
        expected: u16,
        /// CRC carried by the frame.
        got: u16,
    },
    /// A Modbus RTU frame addressed to (or answered by) another slave.
    #[error("Modbus RTU frame for slave {got}, expected slave {expected}; check the gripper's slave id (Robotiq default 9)")]
    WrongSlave {
        /// Slave id expected.
        expected: u8,
        /// Slave id in the frame.
        got: u8,
    },
    /// A Modbus function code this gripper does not speak (it speaks 04, 16 and 23).
    #[error("Modbus function code {code:#04x} is not supported; the Robotiq gripper speaks 0x04, 0x10 and 0x17")]
    UnsupportedFunction {
        /// The function code found.
        code: u8,
    },
    /// The gripper (or a gateway) answered with a Modbus exception.
    #[error("Modbus exception {exception:#04x} to function {function:#04x}; check register addresses (0x03E8 out, 0x07D0 in)")]
    ModbusException {
        /// The function code of the request.
        function: u8,
        /// The exception code.
        exception: u8,
    },
    /// A frame shorter than its header says, or cut off by a silence.
    #[error("truncated {what}: needed {needed} bytes, got {got}; the line went silent mid-frame (check cabling and baud rate)")]
    Truncated {
        /// What was being read.
        what: &'static str,
        /// Bytes needed.
        needed: usize,
        /// Bytes received.
        got: usize,
    },
    /// A frame or line whose contents are not what the protocol allows.
    #[error("malformed {what}: {detail}")]
    Malformed {
        /// What was being decoded.
        what: &'static str,
        /// What was wrong.
        detail: String,
    },
    /// An answer that is well formed but not the answer to the question asked.
    #[error("unexpected reply on the {transport} transport: {detail}; another client may share the line")]
    UnexpectedReply {
        /// Which transport.
        transport: &'static str,
        /// What arrived.
        detail: String,
    },
    /// An I/O error on the transport.
    #[error("{context}: {source}")]
    Io {
        /// What was being done.
        context: String,
        /// The underlying error.
        #[source]
        source: std::io::Error,
    },
    /// The serial device could not be opened or configured.
    #[error("cannot open serial device {path}: {source}; check the path and that no other program holds it")]
    Serial {
        /// Device path.
        path: String,
        /// The underlying error.
        #[source]
        source: serialport::Error,
    },
    /// No (complete) answer within the allowed time.
    #[error("timed out after {after:?} waiting for {what}; check power, cabling and that the gripper is not in emergency stop")]
    Timeout {
        /// What was awaited.
        what: &'static str,
        /// How long we waited.
        after: Duration,
    },
    /// A motion was asked for before `activate` succeeded.
    #[error("the gripper is not activated; call activate() first (and again after a fault)")]
    NotActivated,
    /// The gripper reports a fault.
    #[error("gripper fault {code:#04x} ({fault:?}); re-activate the gripper to clear it (major faults need a new rising edge of rACT)")]
    Fault {
        /// The raw gFLT code.
        code: u8,
        /// Its meaning.
        fault: GripperFault,
    },
    /// A command value outside what the gripper can do.
    #[error("{what} = {value} is outside [{min}, {max}]")]
    OutOfRange {
        /// Which value.
        what: &'static str,
        /// The value given.
        value: f64,
        /// Lowest allowed.
        min: f64,
        /// Highest allowed.
        max: f64,
    },
    /// A calibration that cannot map counts to metres.
    #[error("invalid gripper calibration: {detail}")]
    BadCalibration {
        /// What is wrong.
        detail: String,
    },
    /// A transport this build or platform does not have.
    #[error("the {transport} transport is unavailable: {detail}")]
    TransportUnavailable {
        /// Which transport.
        transport: &'static str,
        /// Why, and what to do.
        detail: String,
    },
    /// The UR controller answered `?`: it is in emergency (or protective) stop.
    #[error("the UR controller reports an emergency stop (URCap answered `?`); release the stop on the teach pendant, then re-activate the gripper")]
    EmergencyStop,
}
