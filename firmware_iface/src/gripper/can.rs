//! CAN frames and the gripper's mapping onto them (fact sheet "CAN"): one frame each way
//! holding the 6 register bytes. The ids follow the CANopen PDO convention so that they do
//! not collide with other nodes on a shared bus: the command (request image) travels on
//! `0x200 + node`, the status image on `0x180 + node`. Every command frame is answered by a
//! status frame; a remote (RTR) frame, or an empty data frame (for carriers without remote
//! frames, like socketcand), on the status id asks for the current status. Every id is
//! configurable. Pure codec.

use super::registers::{RequestImage, StatusImage, IMAGE_LEN};
use super::GripperError;

/// A CAN identifier.
#[derive(Copy, Clone, Debug, PartialEq, Eq, Hash)]
pub enum CanId {
    /// 11-bit identifier.
    Standard(u16),
    /// 29-bit identifier.
    Extended(u32),
}

impl CanId {
    /// A checked 11-bit id.
    pub fn standard(id: u16) -> Result<Self, GripperError> {
        if id <= 0x7FF {
            Ok(Self::Standard(id))
        } else {
            Err(GripperError::OutOfRange {
                what: "standard CAN id",
                value: f64::from(id),
                min: 0.0,
                max: 2047.0,
            })
        }
    }

    /// A checked 29-bit id.
    pub fn extended(id: u32) -> Result<Self, GripperError> {
        if id <= 0x1FFF_FFFF {
            Ok(Self::Extended(id))
        } else {
            Err(GripperError::OutOfRange {
                what: "extended CAN id",
                value: f64::from(id),
                min: 0.0,
                max: f64::from(0x1FFF_FFFFu32),
            })
        }
    }

    /// The numeric id.
    pub fn raw(self) -> u32 {
        match self {
            Self::Standard(i) => u32::from(i),
            Self::Extended(i) => i,
        }
    }
}

/// A classic CAN frame (up to 8 data bytes), data or remote.
#[derive(Copy, Clone, Debug, PartialEq, Eq)]
pub struct CanFrame {
    /// Identifier.
    pub id: CanId,
    /// Remote transmission request (no data, `len` is the requested length).
    pub rtr: bool,
    /// Data length code, 0..=8.
    pub len: u8,
    /// Data; bytes past `len` are zero.
    pub data: [u8; 8],
}

impl CanFrame {
    /// A data frame; at most 8 bytes.
    pub fn data(id: CanId, bytes: &[u8]) -> Result<Self, GripperError> {
        if bytes.len() > 8 {
            return Err(GripperError::Malformed {
                what: "CAN frame",
                detail: format!("{} data bytes, classic CAN carries at most 8", bytes.len()),
            });
        }
        let mut data = [0; 8];
        data[..bytes.len()].copy_from_slice(bytes);
        Ok(Self {
            id,
            rtr: false,
            len: bytes.len() as u8,
            data,
        })
    }

    /// A remote frame asking for `len` bytes.
    pub fn remote(id: CanId, len: u8) -> Result<Self, GripperError> {
        if len > 8 {
            return Err(GripperError::Malformed {
                what: "CAN remote frame",
                detail: format!("length {len} > 8"),
            });
        }
        Ok(Self {
            id,
            rtr: true,
            len,
            data: [0; 8],
        })
    }

    /// The payload.
    pub fn payload(&self) -> &[u8] {
        &self.data[..usize::from(self.len.min(8))]
    }
}

/// Which CAN ids carry the gripper's register images.
#[derive(Copy, Clone, Debug, PartialEq, Eq)]
pub struct CanMapping {
    /// Id of host-to-gripper frames carrying the request image.
    pub command_id: CanId,
    /// Id of gripper-to-host frames carrying the status image.
    pub status_id: CanId,
}

impl Default for CanMapping {
    fn default() -> Self {
        Self::for_node(super::modbus_rtu::SLAVE_ID)
    }
}

impl CanMapping {
    /// The default ids for a node: command `0x200 + node`, status `0x180 + node`.
    pub fn for_node(node: u8) -> Self {
        Self {
            command_id: CanId::Standard(0x200 + u16::from(node)),
            status_id: CanId::Standard(0x180 + u16::from(node)),
        }
    }

    /// The frame carrying a request image.
    pub fn command_frame(&self, r: &RequestImage) -> CanFrame {
        frame6(self.command_id, r.encode())
    }

    /// The frame carrying a status image.
    pub fn status_frame(&self, s: &StatusImage) -> CanFrame {
        frame6(self.status_id, s.encode())
    }

    /// The remote frame that polls the status.
    pub fn status_poll(&self) -> CanFrame {
        CanFrame {
            id: self.status_id,
            rtr: true,
            len: IMAGE_LEN as u8,
            data: [0; 8],
        }
    }

    /// The empty data frame that polls the status where remote frames are unavailable.
    pub fn status_poll_empty(&self) -> CanFrame {
        CanFrame {
            id: self.status_id,
            rtr: false,
            len: 0,
            data: [0; 8],
        }
    }

    /// True for a status poll: a remote frame or an empty data frame on the status id.
    pub fn is_status_poll(&self, f: &CanFrame) -> bool {
        f.id == self.status_id && (f.rtr || f.len == 0)
    }

    /// The request image in a command frame; `Ok(None)` for a frame with another id.
    pub fn decode_command(&self, f: &CanFrame) -> Result<Option<RequestImage>, GripperError> {
        if f.id != self.command_id || f.rtr {
            return Ok(None);
        }
        Ok(Some(RequestImage::decode(image(f, "command frame")?)))
    }

    /// The status image in a status frame; `Ok(None)` for a frame with another id or a poll.
    pub fn decode_status(&self, f: &CanFrame) -> Result<Option<StatusImage>, GripperError> {
        if f.id != self.status_id || self.is_status_poll(f) {
            return Ok(None);
        }
        Ok(Some(StatusImage::decode(image(f, "status frame")?)))
    }
}

fn frame6(id: CanId, b: [u8; IMAGE_LEN]) -> CanFrame {
    let mut data = [0; 8];
    data[..IMAGE_LEN].copy_from_slice(&b);
    CanFrame {
        id,
        rtr: false,
        len: IMAGE_LEN as u8,
        data,
    }
}

fn image(f: &CanFrame, what: &'static str) -> Result<[u8; IMAGE_LEN], GripperError> {
    let p = f.payload();
    <[u8; IMAGE_LEN]>::try_from(p).map_err(|_| GripperError::Malformed {
        what,
        detail: format!("{} data bytes, the register image has {IMAGE_LEN}", p.len()),
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn mapping_golden_frames() {
        let m = CanMapping::default();
        assert_eq!(m.command_id, CanId::Standard(0x209));
        assert_eq!(m.status_id, CanId::Standard(0x189));
        let r = RequestImage {
            activate: true,
            go_to: true,
            position: 0xFF,
            speed: 0x80,
            force: 0x40,
            ..Default::default()
        };
        let f = m.command_frame(&r);
        assert_eq!(f.payload(), &[0x09, 0, 0, 0xFF, 0x80, 0x40]);
        assert_eq!(m.decode_command(&f).unwrap(), Some(r));
        assert_eq!(m.decode_status(&f).unwrap(), None);
        let short = CanFrame::data(m.command_id, &[1, 2, 3]).unwrap();
        assert!(m.decode_command(&short).is_err());
        assert!(m.is_status_poll(&m.status_poll()));
        assert!(m.is_status_poll(&m.status_poll_empty()));
        assert!(!m.is_status_poll(&m.status_frame(&StatusImage::default())));
        assert_eq!(m.decode_status(&m.status_poll_empty()).unwrap(), None);
        assert!(CanId::standard(0x800).is_err());
        assert!(CanId::extended(0x2000_0000).is_err());
        assert!(CanFrame::data(m.command_id, &[0; 9]).is_err());
    }
}
