//! The gripper's CAN mapping on a SocketCAN interface (Linux with CAN in the kernel;
//! feature `socketcan`). Same exchange as over slcan: a command frame is answered by a
//! status frame, a remote frame on the status id polls the status. Uses the `socketcan`
//! crate for the raw socket (no unsafe code here, blocking reads with a timeout, no thread).

use std::io::ErrorKind;
use std::time::{Duration, Instant};

use log::{debug, warn};
use socketcan::{CanSocket, EmbeddedFrame, ExtendedId, Id, Socket, StandardId};

use super::can::{CanFrame, CanId, CanMapping};
use super::registers::{RequestImage, StatusImage};
use super::transport::{io_err, RegisterTransport, DEFAULT_REPLY_TIMEOUT};
use super::GripperError;

/// Converts one of our frames to a SocketCAN frame.
pub fn to_socketcan(f: &CanFrame) -> Result<socketcan::CanFrame, GripperError> {
    let id: Id = match f.id {
        CanId::Standard(i) => StandardId::new(i).map(Id::Standard),
        CanId::Extended(i) => ExtendedId::new(i).map(Id::Extended),
    }
    .ok_or(GripperError::OutOfRange {
        what: "CAN id",
        value: f64::from(f.id.raw()),
        min: 0.0,
        max: f64::from(0x1FFF_FFFFu32),
    })?;
    let frame = if f.rtr {
        socketcan::CanFrame::new_remote(id, usize::from(f.len))
    } else {
        socketcan::CanFrame::new(id, f.payload())
    };
    frame.ok_or_else(|| GripperError::Malformed {
        what: "CAN frame",
        detail: format!("SocketCAN cannot carry {f:?}"),
    })
}

/// Converts a SocketCAN frame to ours; `None` for error frames.
pub fn from_socketcan(f: &socketcan::CanFrame) -> Option<CanFrame> {
    let id = match f.id() {
        Id::Standard(i) => CanId::Standard(i.as_raw()),
        Id::Extended(i) => CanId::Extended(i.as_raw()),
    };
    match f {
        socketcan::CanFrame::Data(_) => CanFrame::data(id, f.data()).ok(),
        socketcan::CanFrame::Remote(_) => CanFrame::remote(id, f.dlc().min(8) as u8).ok(),
        socketcan::CanFrame::Error(_) => None,
    }
}

/// The gripper on a SocketCAN interface (e.g. `can0`).
pub struct SocketcanTransport {
    sock: CanSocket,
    mapping: CanMapping,
    reply_timeout: Duration,
}

impl SocketcanTransport {
    /// Opens interface `ifname`.
    pub fn open(ifname: &str, mapping: CanMapping) -> Result<Self, GripperError> {
        let sock = CanSocket::open(ifname).map_err(io_err(format!(
            "opening SocketCAN interface {ifname} (is CAN in the kernel and the link up? \
             `ip link set {ifname} up type can bitrate 500000`)"
        )))?;
        sock.set_read_timeout(Duration::from_millis(5))
            .map_err(io_err("configuring the SocketCAN socket"))?;
        Ok(Self {
            sock,
            mapping,
            reply_timeout: DEFAULT_REPLY_TIMEOUT,
        })
    }

    /// Sends `frame` and waits for the next status frame.
    pub fn exchange(&mut self, frame: CanFrame) -> Result<StatusImage, GripperError> {
        self.sock
            .write_frame(&to_socketcan(&frame)?)
            .map_err(io_err("writing a CAN frame"))?;
        // Reply timeouts are I/O deadlines, not control time: the wall clock is right here.
        let start = Instant::now();
        while start.elapsed() < self.reply_timeout {
            let f = match self.sock.read_frame() {
                Ok(f) => f,
                Err(e) if matches!(e.kind(), ErrorKind::WouldBlock | ErrorKind::TimedOut) => {
                    continue
                }
                Err(e) => return Err(io_err("reading a CAN frame")(e)),
            };
            let Some(ours) = from_socketcan(&f) else {
                warn!("socketcan: error frame on the bus");
                continue;
            };
            match self.mapping.decode_status(&ours) {
                Ok(Some(s)) => return Ok(s),
                Ok(None) => debug!("socketcan: ignoring frame {ours:?}"),
                Err(e) => {
                    warn!("socketcan: rejected status frame: {e}");
                    return Err(e);
                }
            }
        }
        Err(GripperError::Timeout {
            what: "a CAN status frame",
            after: self.reply_timeout,
        })
    }
}

impl RegisterTransport for SocketcanTransport {
    fn write_request(&mut self, request: &RequestImage) -> Result<(), GripperError> {
        let frame = self.mapping.command_frame(request);
        self.exchange(frame).map(|_| ())
    }

    fn read_status(&mut self) -> Result<StatusImage, GripperError> {
        let frame = self.mapping.status_poll();
        self.exchange(frame)
    }

    fn name(&self) -> &'static str {
        "socketcan"
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn frames_convert_both_ways() {
        let m = CanMapping::default();
        for f in [
            m.command_frame(&RequestImage::default()),
            m.status_poll(),
            CanFrame::data(CanId::Extended(0x1234_5678), &[1, 2]).unwrap(),
        ] {
            assert_eq!(from_socketcan(&to_socketcan(&f).unwrap()), Some(f));
        }
    }

    #[test]
    fn missing_interface_is_a_typed_error() {
        // This machine's kernel has no CAN: either way, opening must fail cleanly.
        match SocketcanTransport::open("nosuchcan7", CanMapping::default()) {
            Err(GripperError::Io { context, .. }) => assert!(context.contains("nosuchcan7")),
            Err(e) => panic!("unexpected error {e}"),
            Ok(_) => panic!("opened a CAN interface that does not exist"),
        }
    }
}
