//! Modbus RTU framing for the Robotiq gripper (fact sheet "Modbus RTU"): slave 9, function
//! codes 04 (read input registers), 16 (write multiple registers) and 23 (read/write
//! multiple registers), CRC-16/MODBUS sent low byte first, frames separated by 3.5
//! character times. Pure codec: no I/O.
//!
//! The CRC comes from the `crc` crate (its `CRC_16_MODBUS` catalogue entry, table driven).
//! The framing itself is written here rather than taken from `rmodbus`: the gripper needs
//! only three function codes, sends no exception responses, and both the driver and the
//! emulator need a streaming reader that resynchronises after garbage and says why it
//! dropped bytes, which is about as much code as adapting `rmodbus`'s register context.

use std::time::Duration;

use crc::{Crc, CRC_16_MODBUS};

use super::GripperError;

/// The Robotiq gripper's default slave id.
pub const SLAVE_ID: u8 = 9;
/// Read input registers.
pub const FC_READ_INPUT: u8 = 0x04;
/// Write multiple registers.
pub const FC_WRITE_MULTIPLE: u8 = 0x10;
/// Read/write multiple registers.
pub const FC_READ_WRITE: u8 = 0x17;
/// Most registers one frame may carry (a 256-byte RTU frame limits it to well under this).
pub const MAX_REGISTERS: u16 = 120;

const CRC16: Crc<u16> = Crc::<u16>::new(&CRC_16_MODBUS);

/// CRC-16/MODBUS of `data`.
pub fn crc16(data: &[u8]) -> u16 {
    CRC16.checksum(data)
}

/// The silence that separates frames at `baud` (8N1: 10 bits a character): 3.5 character
/// times, or the fixed 1.75 ms the Modbus serial line spec prescribes above 19200 baud.
pub fn frame_gap(baud: u32) -> Duration {
    if baud > 19_200 || baud == 0 {
        Duration::from_micros(1750)
    } else {
        Duration::from_nanos(35_000_000_000 / u64::from(baud))
    }
}

/// A request from the master (host) to the gripper.
#[derive(Clone, Debug, PartialEq, Eq)]
pub enum Request {
    /// FC04: read `count` input registers from `start`.
    ReadInput {
        /// First register.
        start: u16,
        /// Number of registers.
        count: u16,
    },
    /// FC16: write `values` from `start`.
    WriteMultiple {
        /// First register.
        start: u16,
        /// Register values.
        values: Vec<u16>,
    },
    /// FC23: write `values` from `write_start`, then read `read_count` from `read_start`.
    ReadWrite {
        /// First register read.
        read_start: u16,
        /// Number of registers read.
        read_count: u16,
        /// First register written.
        write_start: u16,
        /// Register values written.
        values: Vec<u16>,
    },
}

/// A response from the gripper to the host.
#[derive(Clone, Debug, PartialEq, Eq)]
pub enum Response {
    /// FC04: the registers read.
    ReadInput {
        /// Register values.
        values: Vec<u16>,
    },
    /// FC16: echo of the start and count written.
    WriteMultiple {
        /// First register written.
        start: u16,
        /// Number of registers written.
        count: u16,
    },
    /// FC23: the registers read.
    ReadWrite {
        /// Register values.
        values: Vec<u16>,
    },
    /// An exception (the gripper sends none; gateways may).
    Exception {
        /// The request's function code.
        function: u8,
        /// The exception code.
        code: u8,
    },
}

fn push_u16(out: &mut Vec<u8>, v: u16) {
    out.extend_from_slice(&v.to_be_bytes());
}

fn finish(mut out: Vec<u8>) -> Vec<u8> {
    let crc = crc16(&out);
    out.extend_from_slice(&crc.to_le_bytes());
    out
}

fn check_count(what: &'static str, n: usize) -> Result<u16, GripperError> {
    match u16::try_from(n) {
        Ok(c) if (1..=MAX_REGISTERS).contains(&c) => Ok(c),
        _ => Err(GripperError::Malformed {
            what,
            detail: format!("{n} registers; a frame carries 1..={MAX_REGISTERS}"),
        }),
    }
}

impl Request {
    /// The complete RTU frame (address, PDU, CRC) for `slave`.
    pub fn encode(&self, slave: u8) -> Result<Vec<u8>, GripperError> {
        let mut out = vec![slave];
        match self {
            Self::ReadInput { start, count } => {
                check_count("FC04 request", usize::from(*count))?;
                out.push(FC_READ_INPUT);
                push_u16(&mut out, *start);
                push_u16(&mut out, *count);
            }
            Self::WriteMultiple { start, values } => {
                let n = check_count("FC16 request", values.len())?;
                out.push(FC_WRITE_MULTIPLE);
                push_u16(&mut out, *start);
                push_u16(&mut out, n);
                out.push((n * 2) as u8);
                values.iter().for_each(|v| push_u16(&mut out, *v));
            }
            Self::ReadWrite {
                read_start,
                read_count,
                write_start,
                values,
            } => {
                check_count("FC23 request", usize::from(*read_count))?;
                let n = check_count("FC23 request", values.len())?;
                out.push(FC_READ_WRITE);
                push_u16(&mut out, *read_start);
                push_u16(&mut out, *read_count);
                push_u16(&mut out, *write_start);
                push_u16(&mut out, n);
                out.push((n * 2) as u8);
                values.iter().for_each(|v| push_u16(&mut out, *v));
            }
        }
        Ok(finish(out))
    }

    /// Decodes one complete request frame, checking CRC; returns the slave id and request.
    pub fn decode(frame: &[u8]) -> Result<(u8, Self), GripperError> {
        let body = check_frame("request frame", frame, request_frame_len)?;
        let slave = body[0];
        let u = |i: usize| u16::from_be_bytes([body[i], body[i + 1]]);
        let req = match body[1] {
            FC_READ_INPUT => Self::ReadInput {
                start: u(2),
                count: u(4),
            },
            FC_WRITE_MULTIPLE => {
                let count = u(4);
                let values = registers(&body[7..], count, body[6], "FC16 request")?;
                Self::WriteMultiple {
                    start: u(2),
                    values,
                }
            }
            FC_READ_WRITE => {
                let count = u(8);
                let values = registers(&body[11..], count, body[10], "FC23 request")?;
                Self::ReadWrite {
                    read_start: u(2),
                    read_count: u(4),
                    write_start: u(6),
                    values,
                }
            }
            code => return Err(GripperError::UnsupportedFunction { code }),
        };
        if let Self::ReadInput { count, .. }
        | Self::ReadWrite {
            read_count: count, ..
        } = &req
        {
            check_count("read request", usize::from(*count))?;
        }
        Ok((slave, req))
    }
}

impl Response {
    /// The complete RTU frame (address, PDU, CRC) from `slave`.
    pub fn encode(&self, slave: u8) -> Result<Vec<u8>, GripperError> {
        let mut out = vec![slave];
        match self {
            Self::ReadInput { values } | Self::ReadWrite { values } => {
                let n = check_count("read response", values.len())?;
                out.push(if matches!(self, Self::ReadInput { .. }) {
                    FC_READ_INPUT
                } else {
                    FC_READ_WRITE
                });
                out.push((n * 2) as u8);
                values.iter().for_each(|v| push_u16(&mut out, *v));
            }
            Self::WriteMultiple { start, count } => {
                out.push(FC_WRITE_MULTIPLE);
                push_u16(&mut out, *start);
                push_u16(&mut out, *count);
            }
            Self::Exception { function, code } => {
                out.push(function | 0x80);
                out.push(*code);
            }
        }
        Ok(finish(out))
    }

    /// Decodes one complete response frame, checking CRC; returns the slave id and response.
    pub fn decode(frame: &[u8]) -> Result<(u8, Self), GripperError> {
        let body = check_frame("response frame", frame, response_frame_len)?;
        let slave = body[0];
        let fc = body[1];
        let resp = match fc {
            FC_READ_INPUT | FC_READ_WRITE => {
                let bytes = body[2];
                if bytes % 2 != 0 || bytes == 0 {
                    return Err(GripperError::Malformed {
                        what: "read response",
                        detail: format!("odd or zero byte count {bytes}"),
                    });
                }
                let values = registers(&body[3..], u16::from(bytes / 2), bytes, "read response")?;
                if fc == FC_READ_INPUT {
                    Self::ReadInput { values }
                } else {
                    Self::ReadWrite { values }
                }
            }
            FC_WRITE_MULTIPLE => Self::WriteMultiple {
                start: u16::from_be_bytes([body[2], body[3]]),
                count: u16::from_be_bytes([body[4], body[5]]),
            },
            f if f & 0x80 != 0 => Self::Exception {
                function: f & 0x7F,
                code: body[2],
            },
            code => return Err(GripperError::UnsupportedFunction { code }),
        };
        Ok((slave, resp))
    }
}

fn registers(
    data: &[u8],
    count: u16,
    byte_count: u8,
    what: &'static str,
) -> Result<Vec<u16>, GripperError> {
    if usize::from(byte_count) != usize::from(count) * 2 || data.len() != usize::from(byte_count) {
        return Err(GripperError::Malformed {
            what,
            detail: format!(
                "register count {count}, byte count {byte_count} and {} data bytes disagree",
                data.len()
            ),
        });
    }
    check_count(what, usize::from(count))?;
    Ok(data
        .chunks_exact(2)
        .map(|c| u16::from_be_bytes([c[0], c[1]]))
        .collect())
}

/// Checks length and CRC; returns the frame without its CRC.
fn check_frame<'a>(
    what: &'static str,
    frame: &'a [u8],
    len: fn(&[u8]) -> Result<Option<usize>, GripperError>,
) -> Result<&'a [u8], GripperError> {
    let needed = match len(frame)? {
        Some(n) => n,
        None => {
            return Err(GripperError::Truncated {
                what,
                needed: frame.len() + 1,
                got: frame.len(),
            })
        }
    };
    if frame.len() < needed {
        return Err(GripperError::Truncated {
            what,
            needed,
            got: frame.len(),
        });
    }
    if frame.len() > needed {
        return Err(GripperError::Malformed {
            what,
            detail: format!("{} bytes after a {needed}-byte frame", frame.len() - needed),
        });
    }
    let (body, crc) = frame.split_at(needed - 2);
    let got = u16::from_le_bytes([crc[0], crc[1]]);
    let expected = crc16(body);
    if got != expected {
        return Err(GripperError::Crc { expected, got });
    }
    Ok(body)
}

/// Length of the request frame that starts with `prefix`, once the prefix says it
/// (`Ok(None)`: need more bytes); an error for a function code the gripper does not speak.
pub fn request_frame_len(prefix: &[u8]) -> Result<Option<usize>, GripperError> {
    let Some(&fc) = prefix.get(1) else {
        return Ok(None);
    };
    match fc {
        FC_READ_INPUT => Ok(Some(8)),
        FC_WRITE_MULTIPLE => Ok(prefix.get(6).map(|n| 9 + usize::from(*n))),
        FC_READ_WRITE => Ok(prefix.get(10).map(|n| 13 + usize::from(*n))),
        code => Err(GripperError::UnsupportedFunction { code }),
    }
}

/// Length of the response frame that starts with `prefix` (see [`request_frame_len`]).
pub fn response_frame_len(prefix: &[u8]) -> Result<Option<usize>, GripperError> {
    let Some(&fc) = prefix.get(1) else {
        return Ok(None);
    };
    match fc {
        FC_READ_INPUT | FC_READ_WRITE => Ok(prefix.get(2).map(|n| 5 + usize::from(*n))),
        FC_WRITE_MULTIPLE => Ok(Some(8)),
        f if f & 0x80 != 0 => Ok(Some(5)),
        code => Err(GripperError::UnsupportedFunction { code }),
    }
}

/// Which side of the line a [`FrameReader`] listens to.
#[derive(Copy, Clone, Debug, PartialEq, Eq)]
pub enum Direction {
    /// Frames from the master (the emulator's side).
    Requests,
    /// Frames from the gripper (the driver's side).
    Responses,
}

/// What a [`FrameReader`] found in the bytes it was given.
#[derive(Clone, Debug, PartialEq, Eq)]
pub enum Scan {
    /// A complete frame with a good CRC (its bytes, CRC included).
    Frame(Vec<u8>),
    /// Bytes dropped, with the reason (for the log).
    Dropped {
        /// How many bytes.
        bytes: usize,
        /// Why.
        reason: String,
    },
}

/// Cuts a byte stream into frames. Frames are delimited by their own length (derived from
/// the function code) because pseudo-terminals and USB adapters do not keep the 3.5
/// character gaps; a bad CRC or unknown function code drops one byte and rescans, so a
/// good frame after garbage is still found. Call [`FrameReader::silence`] when the line has
/// been quiet longer than a frame gap: a partial frame then is a truncated frame.
#[derive(Debug)]
pub struct FrameReader {
    dir: Direction,
    buf: Vec<u8>,
}

impl FrameReader {
    /// A reader for frames travelling in `dir`.
    pub fn new(dir: Direction) -> Self {
        Self {
            dir,
            buf: Vec::with_capacity(256),
        }
    }

    /// Appends received bytes.
    pub fn push(&mut self, bytes: &[u8]) {
        self.buf.extend_from_slice(bytes);
    }

    /// Bytes held that do not yet form a frame.
    pub fn pending(&self) -> usize {
        self.buf.len()
    }

    /// The line went silent: drops any partial frame, saying so.
    pub fn silence(&mut self) -> Option<Scan> {
        if self.buf.is_empty() {
            return None;
        }
        let bytes = self.buf.len();
        self.buf.clear();
        Some(Scan::Dropped {
            bytes,
            reason: format!("truncated frame: {bytes} bytes followed by silence"),
        })
    }

    /// The next frame or drop event, or `None` when more bytes are needed.
    pub fn next_scan(&mut self) -> Option<Scan> {
        let mut dropped = 0;
        let mut reason = String::new();
        loop {
            let len = match self.dir {
                Direction::Requests => request_frame_len(&self.buf),
                Direction::Responses => response_frame_len(&self.buf),
            };
            let verdict = match len {
                Ok(None) => None,
                Ok(Some(n)) if self.buf.len() < n => None,
                Ok(Some(n)) => {
                    let frame = &self.buf[..n];
                    let (body, crc) = frame.split_at(n - 2);
                    let got = u16::from_le_bytes([crc[0], crc[1]]);
                    let expected = crc16(body);
                    if got == expected {
                        if dropped > 0 {
                            // Report the drop first; the good frame stays for the next call.
                            return Some(Scan::Dropped {
                                bytes: dropped,
                                reason,
                            });
                        }
                        return Some(Scan::Frame(self.buf.drain(..n).collect()));
                    }
                    Some(format!(
                        "CRC mismatch (frame {got:#06x}, computed {expected:#06x})"
                    ))
                }
                Err(e) => Some(e.to_string()),
            };
            match verdict {
                Some(why) => {
                    if reason.is_empty() {
                        reason = why;
                    }
                    self.buf.remove(0);
                    dropped += 1;
                }
                None => {
                    return (dropped > 0).then_some(Scan::Dropped {
                        bytes: dropped,
                        reason,
                    });
                }
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use proptest::prelude::*;

    fn hex(s: &str) -> Vec<u8> {
        s.split_whitespace()
            .map(|b| u8::from_str_radix(b, 16).unwrap())
            .collect()
    }

    #[test]
    fn golden_clear_request_from_fact_sheet() {
        // Fact sheet: `09 10 03E8 0003 06 000000000000` + CRC; Robotiq's manual gives the CRC
        // as 73 30.
        let req = Request::WriteMultiple {
            start: 0x03E8,
            values: vec![0, 0, 0],
        };
        let frame = req.encode(SLAVE_ID).unwrap();
        assert_eq!(frame, hex("09 10 03 E8 00 03 06 00 00 00 00 00 00 73 30"));
        assert_eq!(Request::decode(&frame).unwrap(), (9, req));
    }

    #[test]
    fn golden_activate_and_read_frames() {
        // Robotiq manual: activation request and the gripper's FC16 answer.
        let act = Request::WriteMultiple {
            start: 0x03E8,
            values: vec![0x0100, 0, 0],
        };
        assert_eq!(
            act.encode(9).unwrap(),
            hex("09 10 03 E8 00 03 06 01 00 00 00 00 00 72 E1")
        );
        let ack = Response::WriteMultiple {
            start: 0x03E8,
            count: 3,
        };
        assert_eq!(ack.encode(9).unwrap(), hex("09 10 03 E8 00 03 01 30"));
        // Reference CRC-16/MODBUS check value ("123456789" -> 0x4B37).
        assert_eq!(crc16(b"123456789"), 0x4B37);
    }

    #[test]
    fn bad_frames_are_typed_errors() {
        let mut f = Request::ReadInput {
            start: 0x07D0,
            count: 3,
        }
        .encode(9)
        .unwrap();
        assert_eq!(f.len(), 8);
        assert!(Request::decode(&f[..5]).is_err());
        let last = f.len() - 1;
        f[last] ^= 0xFF;
        assert!(matches!(Request::decode(&f), Err(GripperError::Crc { .. })));
        assert!(matches!(
            Request::decode(&[9, 0x03, 0x07, 0xD0, 0, 1, 0x85, 0xCF]),
            Err(GripperError::UnsupportedFunction { code: 3 })
        ));
        assert!(Request::decode(&[]).is_err());
        let ex = Response::Exception {
            function: 4,
            code: 2,
        }
        .encode(9)
        .unwrap();
        assert_eq!(
            Response::decode(&ex).unwrap().1,
            Response::Exception {
                function: 4,
                code: 2
            }
        );
        assert!(Request::WriteMultiple {
            start: 0,
            values: vec![]
        }
        .encode(9)
        .is_err());
    }

    #[test]
    fn reader_finds_frame_after_garbage_and_reports_truncation() {
        let good = Request::ReadInput {
            start: 0x07D0,
            count: 3,
        }
        .encode(9)
        .unwrap();
        let mut r = FrameReader::new(Direction::Requests);
        r.push(&[0xFF, 0x00, 0x13, 0x37]);
        r.push(&good);
        let mut frames = vec![];
        let mut dropped = 0;
        while let Some(s) = r.next_scan() {
            match s {
                Scan::Frame(f) => frames.push(f),
                Scan::Dropped { bytes, .. } => dropped += bytes,
            }
        }
        assert_eq!(frames, vec![good.clone()]);
        assert_eq!(dropped, 4);
        r.push(&good[..5]);
        assert_eq!(r.next_scan(), None);
        assert!(matches!(r.silence(), Some(Scan::Dropped { bytes: 5, .. })));
        assert_eq!(r.pending(), 0);
    }

    #[test]
    fn frame_gap_follows_the_spec() {
        assert_eq!(frame_gap(115_200), Duration::from_micros(1750));
        assert_eq!(frame_gap(9600), Duration::from_nanos(3_645_833));
    }

    fn regs() -> impl Strategy<Value = Vec<u16>> {
        proptest::collection::vec(any::<u16>(), 1..=20)
    }

    proptest! {
        #[test]
        fn requests_round_trip(slave in any::<u8>(), start in any::<u16>(), count in 1u16..=120,
                               values in regs(), w in any::<u16>()) {
            for req in [
                Request::ReadInput { start, count },
                Request::WriteMultiple { start, values: values.clone() },
                Request::ReadWrite { read_start: start, read_count: count, write_start: w, values: values.clone() },
            ] {
                let f = req.encode(slave).unwrap();
                prop_assert_eq!(Request::decode(&f).unwrap(), (slave, req));
                let mut r = FrameReader::new(Direction::Requests);
                r.push(&f);
                prop_assert_eq!(r.next_scan(), Some(Scan::Frame(f)));
            }
        }

        #[test]
        fn responses_round_trip(slave in any::<u8>(), values in regs(), start in any::<u16>(), count in any::<u16>()) {
            for resp in [
                Response::ReadInput { values: values.clone() },
                Response::ReadWrite { values: values.clone() },
                Response::WriteMultiple { start, count },
            ] {
                let f = resp.encode(slave).unwrap();
                prop_assert_eq!(Response::decode(&f).unwrap(), (slave, resp));
            }
        }

        #[test]
        fn random_bytes_never_panic(bytes in proptest::collection::vec(any::<u8>(), 0..64)) {
            let _ = Request::decode(&bytes);
            let _ = Response::decode(&bytes);
            let mut r = FrameReader::new(Direction::Responses);
            r.push(&bytes);
            let mut n = 0;
            while r.next_scan().is_some() { n += 1; prop_assert!(n <= 64); }
        }
    }
}
