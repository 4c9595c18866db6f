//! The Robotiq 2F-85 register images (fact sheet "Registers"): the 6-byte request image
//! written at 0x03E8 and the 6-byte status image read at 0x07D0, the same on every
//! transport. Pure codec: no I/O.

use cell_types::{GripperFault, ObjectStatus};

/// First Modbus register of the request (output) image.
pub const REQUEST_REGISTER: u16 = 0x03E8;
/// First Modbus register of the status (input) image.
pub const STATUS_REGISTER: u16 = 0x07D0;
/// Bytes in either image.
pub const IMAGE_LEN: usize = 6;
/// 16-bit registers in either image.
pub const IMAGE_REGISTERS: u16 = 3;

const ACT: u8 = 1 << 0;
const GTO: u8 = 1 << 3;
const ATR: u8 = 1 << 4;
const ARD: u8 = 1 << 5;

/// What the host asks of the gripper (bytes 0..6 at 0x03E8).
#[derive(Copy, Clone, Debug, Default, PartialEq, Eq)]
pub struct RequestImage {
    /// rACT: activate (a rising edge starts activation, low resets).
    pub activate: bool,
    /// rGTO: go to the requested position.
    pub go_to: bool,
    /// rATR: automatic release (emergency release).
    pub auto_release: bool,
    /// rARD: automatic release direction (true = open).
    pub release_direction: bool,
    /// rPR: requested position, 0 open .. 255 closed.
    pub position: u8,
    /// rSP: speed, 0 slowest .. 255 fastest.
    pub speed: u8,
    /// rFR: force, 0 lowest .. 255 highest.
    pub force: u8,
}

impl RequestImage {
    /// The 6 register bytes in wire order.
    pub fn encode(&self) -> [u8; IMAGE_LEN] {
        let mut b0 = 0;
        for (on, bit) in [
            (self.activate, ACT),
            (self.go_to, GTO),
            (self.auto_release, ATR),
            (self.release_direction, ARD),
        ] {
            if on {
                b0 |= bit;
            }
        }
        [b0, 0, 0, self.position, self.speed, self.force]
    }

    /// Reads an image from its 6 bytes; reserved bits and bytes are ignored, as the gripper does.
    pub fn decode(bytes: [u8; IMAGE_LEN]) -> Self {
        Self {
            activate: bytes[0] & ACT != 0,
            go_to: bytes[0] & GTO != 0,
            auto_release: bytes[0] & ATR != 0,
            release_direction: bytes[0] & ARD != 0,
            position: bytes[3],
            speed: bytes[4],
            force: bytes[5],
        }
    }

    /// The image as three big-endian 16-bit registers (high byte = lower-numbered byte).
    pub fn to_registers(&self) -> [u16; 3] {
        bytes_to_registers(self.encode())
    }

    /// Reads an image from three registers.
    pub fn from_registers(regs: [u16; 3]) -> Self {
        Self::decode(registers_to_bytes(regs))
    }
}

/// gSTA: where activation stands.
#[derive(Copy, Clone, Debug, PartialEq, Eq)]
pub enum ActivationStatus {
    /// 0: reset (or automatic release).
    Reset,
    /// 1: activation in progress.
    Activating,
    /// 2: not used by the 2F-85.
    Unused,
    /// 3: activation completed.
    Activated,
}

impl ActivationStatus {
    /// The 2-bit gSTA code.
    pub fn code(self) -> u8 {
        match self {
            Self::Reset => 0,
            Self::Activating => 1,
            Self::Unused => 2,
            Self::Activated => 3,
        }
    }

    /// From the 2-bit gSTA code (higher bits ignored).
    pub fn from_code(code: u8) -> Self {
        match code & 3 {
            0 => Self::Reset,
            1 => Self::Activating,
            2 => Self::Unused,
            _ => Self::Activated,
        }
    }
}

/// The 2-bit gOBJ code of an object status.
pub fn object_code(o: ObjectStatus) -> u8 {
    match o {
        ObjectStatus::Moving => 0,
        ObjectStatus::ContactOpening => 1,
        ObjectStatus::ContactClosing => 2,
        ObjectStatus::AtTarget => 3,
    }
}

/// The object status of a 2-bit gOBJ code (higher bits ignored).
pub fn object_from_code(code: u8) -> ObjectStatus {
    match code & 3 {
        0 => ObjectStatus::Moving,
        1 => ObjectStatus::ContactOpening,
        2 => ObjectStatus::ContactClosing,
        _ => ObjectStatus::AtTarget,
    }
}

/// The meaning of a gFLT code; `None` for 0 (no fault).
pub fn fault_from_code(code: u8) -> Option<GripperFault> {
    match code {
        0 => None,
        0x05 => Some(GripperFault::ActivationRequired),
        0x07 => Some(GripperFault::ActivationBitNotSet),
        0x08 | 0x09 => Some(GripperFault::Communication(code)),
        0x0A..=0x0F => Some(GripperFault::Major(code)),
        other => Some(GripperFault::Other(other)),
    }
}

/// Well-known fault codes (fact sheet "Faults").
pub mod fault {
    /// Action delayed: activation must complete first.
    pub const ACTION_DELAYED: u8 = 0x05;
    /// The activation bit must be set before a motion.
    pub const ACTIVATION_BIT_NOT_SET: u8 = 0x07;
    /// No communication for at least one second.
    pub const NO_COMMUNICATION: u8 = 0x09;
    /// Lowest major fault code (needs a new rising edge of rACT).
    pub const MAJOR_FIRST: u8 = 0x0A;
    /// Highest major fault code.
    pub const MAJOR_LAST: u8 = 0x0F;
}

/// What the gripper reports (bytes 0..6 at 0x07D0).
#[derive(Copy, Clone, Debug, PartialEq, Eq)]
pub struct StatusImage {
    /// gACT: echo of rACT.
    pub activate: bool,
    /// gGTO: echo of rGTO (the gripper is executing a go-to).
    pub go_to: bool,
    /// gSTA: activation status.
    pub activation: ActivationStatus,
    /// gOBJ: object detection.
    pub object: ObjectStatus,
    /// gFLT: fault code, 0 = none.
    pub fault: u8,
    /// gPR: echo of the requested position.
    pub position_request: u8,
    /// gPO: actual position, 0 open .. 255 closed.
    pub position: u8,
    /// gCU: motor current, about 10 mA per count.
    pub current: u8,
}

impl Default for StatusImage {
    fn default() -> Self {
        Self::decode([0; IMAGE_LEN])
    }
}

impl StatusImage {
    /// The 6 register bytes in wire order.
    pub fn encode(&self) -> [u8; IMAGE_LEN] {
        let mut b0 = self.activation.code() << 4 | object_code(self.object) << 6;
        if self.activate {
            b0 |= ACT;
        }
        if self.go_to {
            b0 |= GTO;
        }
        [
            b0,
            0,
            self.fault,
            self.position_request,
            self.position,
            self.current,
        ]
    }

    /// Reads an image from its 6 bytes; reserved bits and bytes are ignored.
    pub fn decode(bytes: [u8; IMAGE_LEN]) -> Self {
        Self {
            activate: bytes[0] & ACT != 0,
            go_to: bytes[0] & GTO != 0,
            activation: ActivationStatus::from_code(bytes[0] >> 4),
            object: object_from_code(bytes[0] >> 6),
            fault: bytes[2],
            position_request: bytes[3],
            position: bytes[4],
            current: bytes[5],
        }
    }

    /// The image as three big-endian 16-bit registers.
    pub fn to_registers(&self) -> [u16; 3] {
        bytes_to_registers(self.encode())
    }

    /// Reads an image from three registers.
    pub fn from_registers(regs: [u16; 3]) -> Self {
        Self::decode(registers_to_bytes(regs))
    }

    /// True once activation has completed (gSTA = 3).
    pub fn is_activated(&self) -> bool {
        self.activation == ActivationStatus::Activated
    }

    /// The fault, if any.
    pub fn fault(&self) -> Option<GripperFault> {
        fault_from_code(self.fault)
    }
}

/// Packs 6 bytes into 3 registers, high byte first (fact sheet).
pub fn bytes_to_registers(b: [u8; IMAGE_LEN]) -> [u16; 3] {
    [
        u16::from_be_bytes([b[0], b[1]]),
        u16::from_be_bytes([b[2], b[3]]),
        u16::from_be_bytes([b[4], b[5]]),
    ]
}

/// Unpacks 3 registers into 6 bytes, high byte first.
pub fn registers_to_bytes(r: [u16; 3]) -> [u8; IMAGE_LEN] {
    let [a, b] = r[0].to_be_bytes();
    let [c, d] = r[1].to_be_bytes();
    let [e, f] = r[2].to_be_bytes();
    [a, b, c, d, e, f]
}

#[cfg(test)]
mod tests {
    use super::*;
    use proptest::prelude::*;

    #[test]
    fn status_examples_from_fact_sheet() {
        let s = StatusImage::decode([0x31, 0, 0, 0, 3, 0]);
        assert!(s.activate && !s.go_to && s.is_activated());
        assert_eq!(s.object, ObjectStatus::Moving);
        let s = StatusImage::decode([0x39, 0, 0, 0, 3, 0]);
        assert!(s.go_to && s.is_activated());
        assert_eq!(s.object, ObjectStatus::Moving);
        let s = StatusImage::decode([0xB9, 0, 0, 0xFF, 0x80, 0x30]);
        assert_eq!(s.object, ObjectStatus::ContactClosing);
        assert_eq!(
            (s.position_request, s.position, s.current),
            (255, 0x80, 0x30)
        );
        let s = StatusImage::decode([0xF9, 0, 0, 0, 3, 0]);
        assert_eq!(s.object, ObjectStatus::AtTarget);
        assert_eq!(s.encode()[0], 0xF9);
    }

    #[test]
    fn request_golden_bytes() {
        let r = RequestImage {
            activate: true,
            go_to: true,
            position: 0xFF,
            speed: 0x80,
            force: 0x40,
            ..Default::default()
        };
        assert_eq!(r.encode(), [0x09, 0, 0, 0xFF, 0x80, 0x40]);
        assert_eq!(r.to_registers(), [0x0900, 0x00FF, 0x8040]);
        let rel = RequestImage {
            auto_release: true,
            release_direction: true,
            ..Default::default()
        };
        assert_eq!(rel.encode()[0], 0x30);
    }

    #[test]
    fn fault_codes_map_to_meanings() {
        assert_eq!(fault_from_code(0), None);
        assert_eq!(fault_from_code(5), Some(GripperFault::ActivationRequired));
        assert_eq!(fault_from_code(7), Some(GripperFault::ActivationBitNotSet));
        assert_eq!(fault_from_code(9), Some(GripperFault::Communication(9)));
        assert_eq!(fault_from_code(0x0B), Some(GripperFault::Major(0x0B)));
        assert_eq!(fault_from_code(0x03), Some(GripperFault::Other(3)));
    }

    fn any_request() -> impl Strategy<Value = RequestImage> {
        (any::<[bool; 4]>(), any::<[u8; 3]>()).prop_map(|(b, v)| RequestImage {
            activate: b[0],
            go_to: b[1],
            auto_release: b[2],
            release_direction: b[3],
            position: v[0],
            speed: v[1],
            force: v[2],
        })
    }

    proptest! {
        #[test]
        fn request_round_trips(r in any_request()) {
            prop_assert_eq!(RequestImage::decode(r.encode()), r);
            prop_assert_eq!(RequestImage::from_registers(r.to_registers()), r);
        }

        #[test]
        fn status_round_trips(bytes in any::<[u8; 6]>()) {
            // Every status image the wire can carry decodes; re-encoding keeps every
            // meaningful bit (reserved bits 1, 2 of byte 0 and byte 1 are dropped).
            let s = StatusImage::decode(bytes);
            let again = s.encode();
            prop_assert_eq!(again[0], bytes[0] & 0xF9);
            prop_assert_eq!(&again[2..], &bytes[2..]);
            prop_assert_eq!(StatusImage::decode(again), s);
        }
    }
}
