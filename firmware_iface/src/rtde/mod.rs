//! RTDE (Real-Time Data Exchange, TCP 30004) codec with no I/O: framing, every package type in
//! both directions, protocol versions 1 and 2.
//!
//! Implements the UR "Real-Time Data Exchange (RTDE) Guide" package layout as summarised in
//! the cell's UR fact sheet: `u16 size (big-endian, header included) | u8 type | payload`.
//! Host-to-robot packages are [`HostMessage`] ([`host_to_robot`]), robot-to-host packages are
//! [`RobotMessage`] ([`robot_to_host`]); data package values are laid out by [`Layout`]
//! ([`types`]). Version differences (v1: no output frequency, no recipe id in output setup
//! replies or robot data packages, text message = level + text) are handled by passing the
//! negotiated [`ProtocolVersion`] to `encode`/`decode`.
//!
//! Written by hand: no maintained Rust crate implements the RTDE server side, and the codec is
//! small; correctness is pinned by golden vectors and checked against independent Python peers.

pub mod host_to_robot;
pub mod robot_to_host;
pub mod types;

pub use host_to_robot::HostMessage;
pub use robot_to_host::{ControllerVersion, RobotMessage, TextMessage};
pub use types::{DataType, FieldType, Layout, Value};

use thiserror::Error;

/// Package type byte: request protocol version (`V`).
pub const REQUEST_PROTOCOL_VERSION: u8 = b'V';
/// Package type byte: get controller version (`v`).
pub const GET_URCONTROL_VERSION: u8 = b'v';
/// Package type byte: text message (`M`).
pub const TEXT_MESSAGE: u8 = b'M';
/// Package type byte: data package (`U`).
pub const DATA_PACKAGE: u8 = b'U';
/// Package type byte: setup outputs (`O`).
pub const SETUP_OUTPUTS: u8 = b'O';
/// Package type byte: setup inputs (`I`).
pub const SETUP_INPUTS: u8 = b'I';
/// Package type byte: start (`S`).
pub const START: u8 = b'S';
/// Package type byte: pause (`P`).
pub const PAUSE: u8 = b'P';

/// Header length: u16 size + u8 type.
pub const HEADER_LEN: usize = 3;
/// Longest variable-name list the controller accepts in a setup package (bytes).
pub const MAX_NAMES_LEN: usize = 2048;

/// RTDE protocol version negotiated with `V`.
#[derive(Copy, Clone, Debug, PartialEq, Eq, Hash)]
pub enum ProtocolVersion {
    /// Version 1 (CB3 before 3.5 and the fallback).
    V1,
    /// Version 2 (output frequency, recipe ids everywhere).
    V2,
}

impl ProtocolVersion {
    /// The number sent in `V`.
    pub fn number(self) -> u16 {
        match self {
            ProtocolVersion::V1 => 1,
            ProtocolVersion::V2 => 2,
        }
    }

    /// The version for a number, if supported.
    pub fn from_number(n: u16) -> Option<Self> {
        match n {
            1 => Some(ProtocolVersion::V1),
            2 => Some(ProtocolVersion::V2),
            _ => None,
        }
    }
}

/// Why RTDE bytes could not be encoded or decoded.
#[derive(Debug, Error, Clone, PartialEq)]
#[non_exhaustive]
pub enum RtdeError {
    /// The header's size field is below the header length.
    #[error("RTDE package size field {size} is below the 3-byte header; the stream is corrupt or not RTDE, reconnect")]
    BadSize {
        /// The size field.
        size: u16,
    },
    /// A package type byte that RTDE does not define in this direction.
    #[error("unknown RTDE package type {kind:#04x}; the peer speaks another protocol or the stream is corrupt")]
    UnknownPackage {
        /// The type byte.
        kind: u8,
    },
    /// A payload shorter than its package type requires.
    #[error("{what}: needs {need} bytes, got {got}; the package is truncated")]
    Truncated {
        /// What was being read.
        what: &'static str,
        /// Bytes needed.
        need: usize,
        /// Bytes available.
        got: usize,
    },
    /// A payload longer than its package type allows.
    #[error("{what}: {extra} unexpected trailing bytes; the peer and we disagree on the protocol version")]
    TrailingBytes {
        /// What was being read.
        what: &'static str,
        /// Bytes left over.
        extra: usize,
    },
    /// A text field that is not UTF-8 (names, types, messages are ASCII on the wire).
    #[error("{what} is not valid UTF-8 text")]
    NotText {
        /// Which field.
        what: &'static str,
    },
    /// A type name that is neither a data type nor `NOT_FOUND`/`IN_USE`.
    #[error("unknown RTDE type string {name:?}; expected one of BOOL, UINT8, UINT32, UINT64, INT32, DOUBLE, VECTOR3D, VECTOR6D, VECTOR6INT32, VECTOR6UINT32, NOT_FOUND, IN_USE")]
    UnknownType {
        /// The string found.
        name: String,
    },
    /// A BOOL byte other than 0 or 1.
    #[error("BOOL field holds {value}, expected 0 or 1")]
    BadBool {
        /// The byte found.
        value: u8,
    },
    /// The variable-name list exceeds the controller's limit.
    #[error(
        "variable list is {len} bytes, the controller accepts at most {max}; split the recipe"
    )]
    NamesTooLong {
        /// Bytes in the list.
        len: usize,
        /// The limit.
        max: usize,
    },
    /// A variable name containing a comma would corrupt the list.
    #[error("variable name {name:?} contains a comma")]
    BadName {
        /// The name.
        name: String,
    },
    /// A package larger than the 16-bit size field can express.
    #[error("RTDE package of {len} bytes exceeds 65535; send fewer fields")]
    TooLarge {
        /// Total length.
        len: usize,
    },
    /// A data package whose value bytes do not match the recipe.
    #[error(
        "data package carries {got} value bytes but the recipe needs {expected}; recipe mismatch"
    )]
    PackageSize {
        /// Bytes the recipe needs.
        expected: usize,
        /// Bytes present.
        got: usize,
    },
    /// A recipe field index out of range.
    #[error("recipe field {index} does not exist (recipe has {count} fields)")]
    FieldIndex {
        /// Index asked for.
        index: usize,
        /// Number of fields.
        count: usize,
    },
    /// A recipe field of another type than asked for.
    #[error("recipe field {index} is {found}, not {expected}")]
    FieldType {
        /// Index.
        index: usize,
        /// Type asked for.
        expected: &'static str,
        /// Type in the recipe.
        found: &'static str,
    },
    /// Values given for a recipe do not match its field count.
    #[error("recipe has {expected} fields, {got} values given")]
    FieldCount {
        /// Fields in the recipe.
        expected: usize,
        /// Values given.
        got: usize,
    },
}

/// One complete package found at the start of a byte buffer.
#[derive(Copy, Clone, Debug, PartialEq, Eq)]
pub struct RawPackage<'a> {
    /// Package type byte.
    pub kind: u8,
    /// Payload after the header.
    pub payload: &'a [u8],
}

/// Splits the first complete package off `buf`: `Ok(None)` when more bytes are needed,
/// otherwise the package and the number of bytes it used.
pub fn split_package(buf: &[u8]) -> Result<Option<(RawPackage<'_>, usize)>, RtdeError> {
    if buf.len() < HEADER_LEN {
        return Ok(None);
    }
    let size = u16::from_be_bytes([buf[0], buf[1]]);
    if usize::from(size) < HEADER_LEN {
        return Err(RtdeError::BadSize { size });
    }
    let size = usize::from(size);
    if buf.len() < size {
        return Ok(None);
    }
    Ok(Some((
        RawPackage {
            kind: buf[2],
            payload: &buf[HEADER_LEN..size],
        },
        size,
    )))
}

/// Starts a package in `out` (cleared first); finish it with [`finish_package`].
pub(crate) fn begin_package(out: &mut Vec<u8>, kind: u8) {
    out.clear();
    out.extend_from_slice(&[0, 0, kind]);
}

/// Writes the size field of a package begun with [`begin_package`].
pub(crate) fn finish_package(out: &mut [u8]) -> Result<(), RtdeError> {
    let len = out.len();
    let size = u16::try_from(len).map_err(|_| RtdeError::TooLarge { len })?;
    out[..2].copy_from_slice(&size.to_be_bytes());
    Ok(())
}

/// Joins variable names with commas, checking the controller's limits.
pub(crate) fn join_names(names: &[String], out: &mut Vec<u8>) -> Result<(), RtdeError> {
    let start = out.len();
    for (i, n) in names.iter().enumerate() {
        if n.contains(',') {
            return Err(RtdeError::BadName { name: n.clone() });
        }
        if i > 0 {
            out.push(b',');
        }
        out.extend_from_slice(n.as_bytes());
    }
    let len = out.len() - start;
    if len > MAX_NAMES_LEN {
        return Err(RtdeError::NamesTooLong {
            len,
            max: MAX_NAMES_LEN,
        });
    }
    Ok(())
}

/// Splits a comma-separated name list. One trailing empty name is dropped: the `ur-rtde`
/// client ends its list with a comma, and answering that empty name `NOT_FOUND` crashes it.
pub(crate) fn split_names(bytes: &[u8]) -> Result<Vec<String>, RtdeError> {
    if bytes.len() > MAX_NAMES_LEN {
        return Err(RtdeError::NamesTooLong {
            len: bytes.len(),
            max: MAX_NAMES_LEN,
        });
    }
    let text = std::str::from_utf8(bytes).map_err(|_| RtdeError::NotText {
        what: "variable names",
    })?;
    if text.is_empty() {
        return Ok(Vec::new());
    }
    let mut names: Vec<String> = text.split(',').map(str::to_string).collect();
    if names.last().is_some_and(String::is_empty) {
        names.pop();
    }
    Ok(names)
}

pub(crate) fn take<'a>(
    payload: &'a [u8],
    at: &mut usize,
    n: usize,
    what: &'static str,
) -> Result<&'a [u8], RtdeError> {
    let end = *at + n;
    let s = payload.get(*at..end).ok_or(RtdeError::Truncated {
        what,
        need: end,
        got: payload.len(),
    })?;
    *at = end;
    Ok(s)
}

pub(crate) fn expect_end(payload: &[u8], at: usize, what: &'static str) -> Result<(), RtdeError> {
    if at != payload.len() {
        return Err(RtdeError::TrailingBytes {
            what,
            extra: payload.len() - at,
        });
    }
    Ok(())
}

#[cfg(test)]
mod tests;
