//! slcan (Lawicel ASCII) lines, as spoken by serial CAN adapters and python-can's `slcan`
//! interface (fact sheet "CAN"): `O`/`C` open/close, `L` listen only, `Sn` bit rate
//! (`S6` = 500 kbit/s), `tIIILDD..` standard and `TIIIIIIIILDD..` extended data frames,
//! `rIIIL`/`RIIIIIIIIL` remote frames, `V`/`N`/`F` queries. Every line ends in `\r`; the
//! adapter answers `\r` (ok), `\x07` (error), `z\r`/`Z\r` (frame queued) and sends received
//! frames as `t...\r`. Pure codec: no I/O.

use super::can::{CanFrame, CanId};
use super::GripperError;

/// Line terminator.
pub const CR: u8 = b'\r';
/// Error answer.
pub const BELL: u8 = 0x07;

/// One slcan line (either direction).
#[derive(Clone, Debug, PartialEq, Eq)]
pub enum SlcanLine {
    /// `O`: open the channel.
    Open,
    /// `L`: open listen-only.
    ListenOnly,
    /// `C`: close the channel.
    Close,
    /// `Sn`: standard bit rate code 0..=8 (6 = 500 kbit/s).
    Bitrate(u8),
    /// `V`: version query (host) or `Vxxxx` answer (adapter).
    Version(String),
    /// `N`: serial number query or `Nxxxx` answer.
    Serial(String),
    /// `F`: status flags query or `Fxx` answer.
    Flags(String),
    /// A data or remote frame.
    Frame(CanFrame),
    /// `z` / `Z`: the adapter queued a transmitted frame.
    TxAck,
    /// An empty line: the adapter's "ok".
    Ok,
    /// `\x07`: the adapter's "error".
    Error,
}

fn hex_digit(n: u8) -> u8 {
    b"0123456789ABCDEF"[usize::from(n & 15)]
}

fn push_hex(out: &mut Vec<u8>, value: u32, digits: usize) {
    for i in (0..digits).rev() {
        out.push(hex_digit((value >> (4 * i)) as u8));
    }
}

fn parse_hex(s: &[u8], what: &'static str) -> Result<u32, GripperError> {
    let text = std::str::from_utf8(s).unwrap_or("");
    if s.is_empty() || text.len() != s.len() || !text.bytes().all(|b| b.is_ascii_hexdigit()) {
        return Err(GripperError::Malformed {
            what,
            detail: format!("{:?} is not hexadecimal", String::from_utf8_lossy(s)),
        });
    }
    u32::from_str_radix(text, 16).map_err(|e| GripperError::Malformed {
        what,
        detail: e.to_string(),
    })
}

impl SlcanLine {
    /// The line's bytes, terminator included.
    pub fn encode(&self) -> Vec<u8> {
        let mut out = Vec::with_capacity(32);
        match self {
            Self::Open => out.push(b'O'),
            Self::ListenOnly => out.push(b'L'),
            Self::Close => out.push(b'C'),
            Self::Bitrate(n) => {
                out.push(b'S');
                out.push(hex_digit(*n));
            }
            Self::Version(s) => {
                out.push(b'V');
                out.extend_from_slice(s.as_bytes());
            }
            Self::Serial(s) => {
                out.push(b'N');
                out.extend_from_slice(s.as_bytes());
            }
            Self::Flags(s) => {
                out.push(b'F');
                out.extend_from_slice(s.as_bytes());
            }
            Self::Frame(f) => {
                let (letter, digits) = match (f.id, f.rtr) {
                    (CanId::Standard(_), false) => (b't', 3),
                    (CanId::Standard(_), true) => (b'r', 3),
                    (CanId::Extended(_), false) => (b'T', 8),
                    (CanId::Extended(_), true) => (b'R', 8),
                };
                out.push(letter);
                push_hex(&mut out, f.id.raw(), digits);
                out.push(hex_digit(f.len.min(8)));
                if !f.rtr {
                    for b in f.payload() {
                        push_hex(&mut out, u32::from(*b), 2);
                    }
                }
            }
            Self::TxAck => out.push(b'z'),
            Self::Ok => {}
            Self::Error => return vec![BELL],
        }
        out.push(CR);
        out
    }

    /// Parses one line without its terminator (`\x07` alone is [`SlcanLine::Error`]).
    pub fn parse(line: &[u8]) -> Result<Self, GripperError> {
        let bad = |detail: String| GripperError::Malformed {
            what: "slcan line",
            detail,
        };
        let Some((&first, rest)) = line.split_first() else {
            return Ok(Self::Ok);
        };
        let text = || String::from_utf8_lossy(rest).into_owned();
        match first {
            BELL if rest.is_empty() => Ok(Self::Error),
            b'O' | b'L' | b'C' | b'z' | b'Z' if !rest.is_empty() => {
                Err(bad(format!("{:?} takes no argument", char::from(first))))
            }
            b'O' => Ok(Self::Open),
            b'L' => Ok(Self::ListenOnly),
            b'C' => Ok(Self::Close),
            b'z' | b'Z' => Ok(Self::TxAck),
            b'S' => match rest {
                [d @ b'0'..=b'8'] => Ok(Self::Bitrate(d - b'0')),
                _ => Err(bad(format!("bit rate code {:?} not in 0..=8", text()))),
            },
            b'V' => Ok(Self::Version(text())),
            b'N' => Ok(Self::Serial(text())),
            b'F' => Ok(Self::Flags(text())),
            b't' | b'T' | b'r' | b'R' => {
                let extended = first.is_ascii_uppercase();
                let rtr = first == b'r' || first == b'R';
                let digits = if extended { 8 } else { 3 };
                if rest.len() < digits + 1 {
                    return Err(GripperError::Truncated {
                        what: "slcan frame",
                        needed: digits + 1,
                        got: rest.len(),
                    });
                }
                let raw = parse_hex(&rest[..digits], "slcan CAN id")?;
                let id = if extended {
                    CanId::extended(raw)?
                } else {
                    CanId::standard(raw as u16)?
                };
                let len = parse_hex(&rest[digits..=digits], "slcan length")? as u8;
                if len > 8 {
                    return Err(bad(format!("length {len} > 8")));
                }
                let data = &rest[digits + 1..];
                if rtr {
                    if !data.is_empty() {
                        return Err(bad("remote frame carries data".to_owned()));
                    }
                    return Ok(Self::Frame(CanFrame::remote(id, len)?));
                }
                if data.len() != 2 * usize::from(len) {
                    return Err(GripperError::Truncated {
                        what: "slcan frame data",
                        needed: 2 * usize::from(len),
                        got: data.len(),
                    });
                }
                let bytes = data
                    .chunks_exact(2)
                    .map(|c| parse_hex(c, "slcan data").map(|v| v as u8))
                    .collect::<Result<Vec<u8>, _>>()?;
                Ok(Self::Frame(CanFrame::data(id, &bytes)?))
            }
            other => Err(bad(format!("unknown command {:?}", char::from(other)))),
        }
    }
}

/// Cuts a byte stream into slcan lines at `\r` (and at `\x07`, which stands alone).
/// Lines longer than any slcan line are dropped whole, so a stream of garbage cannot grow
/// the buffer without bound.
#[derive(Debug, Default)]
pub struct LineSplitter {
    buf: Vec<u8>,
    overflow: bool,
}

/// Longest valid slcan line (an extended frame with 8 bytes: 1 + 8 + 1 + 16).
pub const MAX_LINE: usize = 26;

impl LineSplitter {
    /// An empty splitter.
    pub fn new() -> Self {
        Self::default()
    }

    /// Feeds bytes; calls `on_line` with each complete line (terminator removed; a lone
    /// BELL is passed as `[0x07]`). An over-long line is passed as `Err(len)`.
    pub fn push(&mut self, bytes: &[u8], mut on_line: impl FnMut(Result<&[u8], usize>)) {
        for &b in bytes {
            match b {
                CR => {
                    if self.overflow {
                        on_line(Err(self.buf.len()));
                    } else {
                        on_line(Ok(&self.buf));
                    }
                    self.buf.clear();
                    self.overflow = false;
                }
                BELL if self.buf.is_empty() => on_line(Ok(&[BELL])),
                _ => {
                    if self.buf.len() < MAX_LINE {
                        self.buf.push(b);
                    } else {
                        self.overflow = true;
                    }
                }
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use proptest::prelude::*;

    #[test]
    fn golden_lines() {
        let f = CanFrame::data(CanId::Standard(0x209), &[0x09, 0, 0, 0xFF, 0x80, 0x40]).unwrap();
        assert_eq!(SlcanLine::Frame(f).encode(), b"t2096090000FF8040\r");
        let e = CanFrame::data(CanId::Extended(0x1234_5678), &[0xAB]).unwrap();
        assert_eq!(SlcanLine::Frame(e).encode(), b"T123456781AB\r");
        let r = CanFrame::remote(CanId::Standard(0x189), 6).unwrap();
        assert_eq!(SlcanLine::Frame(r).encode(), b"r1896\r");
        assert_eq!(SlcanLine::Bitrate(6).encode(), b"S6\r");
        assert_eq!(SlcanLine::Open.encode(), b"O\r");
        assert_eq!(SlcanLine::Error.encode(), b"\x07");
        assert_eq!(
            SlcanLine::parse(b"t1896B90000FFB430").unwrap(),
            SlcanLine::Frame(
                CanFrame::data(CanId::Standard(0x189), &[0xB9, 0, 0, 0xFF, 0xB4, 0x30]).unwrap()
            )
        );
        assert_eq!(
            SlcanLine::parse(b"V").unwrap(),
            SlcanLine::Version(String::new())
        );
        assert_eq!(SlcanLine::parse(b"").unwrap(), SlcanLine::Ok);
    }

    #[test]
    fn bad_lines_are_typed_errors() {
        for bad in [
            &b"t20"[..],
            b"t2096090000FF80",
            b"t8001",
            b"t2099",
            b"tXYZ0",
            b"S9",
            b"Q",
            b"r1896AA",
            b"T2000000000",
            b"O1",
        ] {
            assert!(
                SlcanLine::parse(bad).is_err(),
                "{:?} accepted",
                String::from_utf8_lossy(bad)
            );
        }
    }

    #[test]
    fn splitter_cuts_lines_and_drops_overlong_ones() {
        let mut s = LineSplitter::new();
        let mut lines = vec![];
        s.push(b"O\rt2090\r\x07", |l| lines.push(l.map(<[u8]>::to_vec)));
        s.push(&[b'x'; 40], |l| lines.push(l.map(<[u8]>::to_vec)));
        s.push(b"\rC\r", |l| lines.push(l.map(<[u8]>::to_vec)));
        assert_eq!(
            lines,
            vec![
                Ok(b"O".to_vec()),
                Ok(b"t2090".to_vec()),
                Ok(vec![BELL]),
                Err(MAX_LINE),
                Ok(b"C".to_vec())
            ]
        );
    }

    fn any_frame() -> impl Strategy<Value = CanFrame> {
        (
            any::<bool>(),
            0u32..0x2000_0000,
            any::<bool>(),
            proptest::collection::vec(any::<u8>(), 0..=8),
        )
            .prop_map(|(ext, id, rtr, data)| {
                let id = if ext {
                    CanId::Extended(id)
                } else {
                    CanId::Standard((id & 0x7FF) as u16)
                };
                if rtr {
                    CanFrame::remote(id, data.len() as u8).unwrap()
                } else {
                    CanFrame::data(id, &data).unwrap()
                }
            })
    }

    proptest! {
        #[test]
        fn frames_round_trip(f in any_frame()) {
            let bytes = SlcanLine::Frame(f).encode();
            prop_assert_eq!(bytes.last(), Some(&CR));
            prop_assert_eq!(SlcanLine::parse(&bytes[..bytes.len() - 1]).unwrap(), SlcanLine::Frame(f));
        }

        #[test]
        fn random_lines_never_panic(bytes in proptest::collection::vec(any::<u8>(), 0..40)) {
            let _ = SlcanLine::parse(&bytes);
            let mut s = LineSplitter::new();
            s.push(&bytes, |_| {});
        }
    }
}
