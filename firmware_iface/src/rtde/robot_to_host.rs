//! Packages the controller sends to the host: replies to `V`, `v`, `O`, `I`, `S`, `P`, output
//! data packages `U` and text messages `M`.

use super::*;

/// Controller software version (`v` reply).
#[derive(Copy, Clone, Debug, PartialEq, Eq, Hash)]
pub struct ControllerVersion {
    /// Major: 3 = CB3, 5 = e-Series.
    pub major: u32,
    /// Minor.
    pub minor: u32,
    /// Bugfix.
    pub bugfix: u32,
    /// Build.
    pub build: u32,
}

impl ControllerVersion {
    /// Highest output rate this controller offers (Hz): 125 on CB3 (major < 5), 500 after.
    pub fn max_frequency(&self) -> f64 {
        if self.major < 5 {
            125.0
        } else {
            500.0
        }
    }
}

/// A text message (`M`), either direction.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct TextMessage {
    /// The text.
    pub message: String,
    /// Who sent it (v2 only; empty in v1).
    pub source: String,
    /// 0 exception, 1 error, 2 warning, 3 info.
    pub level: u8,
}

impl TextMessage {
    pub(crate) fn encode_payload(
        &self,
        version: ProtocolVersion,
        out: &mut Vec<u8>,
    ) -> Result<(), RtdeError> {
        match version {
            ProtocolVersion::V1 => {
                out.push(self.level);
                out.extend_from_slice(self.message.as_bytes());
            }
            ProtocolVersion::V2 => {
                for (what, s) in [
                    ("text message", &self.message),
                    ("text source", &self.source),
                ] {
                    let n = u8::try_from(s.len()).map_err(|_| RtdeError::Truncated {
                        what,
                        need: 255,
                        got: s.len(),
                    })?;
                    out.push(n);
                    out.extend_from_slice(s.as_bytes());
                }
                out.push(self.level);
            }
        }
        Ok(())
    }

    pub(crate) fn decode_payload(version: ProtocolVersion, p: &[u8]) -> Result<Self, RtdeError> {
        let text = |b: &[u8], what| {
            std::str::from_utf8(b)
                .map(str::to_string)
                .map_err(|_| RtdeError::NotText { what })
        };
        let mut at = 0;
        match version {
            ProtocolVersion::V1 => {
                let level = take(p, &mut at, 1, "text message level")?[0];
                Ok(TextMessage {
                    message: text(&p[1..], "text message")?,
                    source: String::new(),
                    level,
                })
            }
            ProtocolVersion::V2 => {
                let n = usize::from(take(p, &mut at, 1, "text message length")?[0]);
                let message = text(take(p, &mut at, n, "text message")?, "text message")?;
                let n = usize::from(take(p, &mut at, 1, "text source length")?[0]);
                let source = text(take(p, &mut at, n, "text source")?, "text source")?;
                let level = take(p, &mut at, 1, "text message level")?[0];
                expect_end(p, at, "text message")?;
                Ok(TextMessage {
                    message,
                    source,
                    level,
                })
            }
        }
    }
}

/// A robot-to-host RTDE package.
#[derive(Clone, Debug, PartialEq)]
pub enum RobotMessage {
    /// `V` reply.
    ProtocolVersionAccepted(bool),
    /// `v` reply.
    ControllerVersion(ControllerVersion),
    /// `O` reply: recipe id (v2 only) and one type per requested name.
    SetupOutputs {
        /// Output recipe id (None in v1, which has a single output recipe).
        recipe_id: Option<u8>,
        /// Types in request order.
        types: Vec<FieldType>,
    },
    /// `I` reply: recipe id (0 when refused) and one type per requested name.
    SetupInputs {
        /// Input recipe id.
        recipe_id: u8,
        /// Types in request order.
        types: Vec<FieldType>,
    },
    /// `S` reply.
    StartAccepted(bool),
    /// `P` reply.
    PauseAccepted(bool),
    /// `U`: output values (recipe id in v2 only).
    DataPackage {
        /// Output recipe id (None in v1).
        recipe_id: Option<u8>,
        /// Values laid out by the recipe's [`Layout`].
        values: Vec<u8>,
    },
    /// `M`.
    Text(TextMessage),
}

fn encode_types(types: &[FieldType], out: &mut Vec<u8>) {
    for (i, t) in types.iter().enumerate() {
        if i > 0 {
            out.push(b',');
        }
        out.extend_from_slice(t.as_str().as_bytes());
    }
}

fn decode_types(b: &[u8]) -> Result<Vec<FieldType>, RtdeError> {
    let s = std::str::from_utf8(b).map_err(|_| RtdeError::NotText { what: "type list" })?;
    if s.is_empty() {
        return Ok(Vec::new());
    }
    s.split(',').map(FieldType::parse).collect()
}

impl RobotMessage {
    /// Encodes into `out` (cleared first).
    pub fn encode_into(
        &self,
        version: ProtocolVersion,
        out: &mut Vec<u8>,
    ) -> Result<(), RtdeError> {
        let v2 = version == ProtocolVersion::V2;
        match self {
            RobotMessage::ProtocolVersionAccepted(a) => {
                begin_package(out, REQUEST_PROTOCOL_VERSION);
                out.push(u8::from(*a));
            }
            RobotMessage::ControllerVersion(v) => {
                begin_package(out, GET_URCONTROL_VERSION);
                for x in [v.major, v.minor, v.bugfix, v.build] {
                    out.extend_from_slice(&x.to_be_bytes());
                }
            }
            RobotMessage::SetupOutputs { recipe_id, types } => {
                begin_package(out, SETUP_OUTPUTS);
                if v2 {
                    out.push(recipe_id.unwrap_or(0));
                }
                encode_types(types, out);
            }
            RobotMessage::SetupInputs { recipe_id, types } => {
                begin_package(out, SETUP_INPUTS);
                out.push(*recipe_id);
                encode_types(types, out);
            }
            RobotMessage::StartAccepted(a) => {
                begin_package(out, START);
                out.push(u8::from(*a));
            }
            RobotMessage::PauseAccepted(a) => {
                begin_package(out, PAUSE);
                out.push(u8::from(*a));
            }
            RobotMessage::DataPackage { recipe_id, values } => {
                begin_package(out, DATA_PACKAGE);
                if v2 {
                    out.push(recipe_id.unwrap_or(1));
                }
                out.extend_from_slice(values);
            }
            RobotMessage::Text(t) => {
                begin_package(out, TEXT_MESSAGE);
                t.encode_payload(version, out)?;
            }
        }
        finish_package(out)
    }

    /// Encodes into a fresh buffer.
    pub fn encode(&self, version: ProtocolVersion) -> Result<Vec<u8>, RtdeError> {
        let mut out = Vec::new();
        self.encode_into(version, &mut out)?;
        Ok(out)
    }

    /// Decodes one package received by the host.
    pub fn decode(version: ProtocolVersion, raw: RawPackage<'_>) -> Result<Self, RtdeError> {
        let p = raw.payload;
        let v2 = version == ProtocolVersion::V2;
        let mut at = 0;
        let one = |what| -> Result<bool, RtdeError> {
            let b = p.first().ok_or(RtdeError::Truncated {
                what,
                need: 1,
                got: 0,
            })?;
            expect_end(p, 1, what)?;
            Ok(*b != 0)
        };
        Ok(match raw.kind {
            REQUEST_PROTOCOL_VERSION => {
                RobotMessage::ProtocolVersionAccepted(one("protocol version reply")?)
            }
            GET_URCONTROL_VERSION => {
                let b = take(p, &mut at, 16, "controller version")?;
                expect_end(p, at, "controller version")?;
                let w = |i: usize| u32::from_be_bytes([b[i], b[i + 1], b[i + 2], b[i + 3]]);
                RobotMessage::ControllerVersion(ControllerVersion {
                    major: w(0),
                    minor: w(4),
                    bugfix: w(8),
                    build: w(12),
                })
            }
            SETUP_OUTPUTS => {
                let recipe_id = if v2 {
                    Some(take(p, &mut at, 1, "output recipe id")?[0])
                } else {
                    None
                };
                RobotMessage::SetupOutputs {
                    recipe_id,
                    types: decode_types(&p[at..])?,
                }
            }
            SETUP_INPUTS => {
                let recipe_id = take(p, &mut at, 1, "input recipe id")?[0];
                RobotMessage::SetupInputs {
                    recipe_id,
                    types: decode_types(&p[at..])?,
                }
            }
            START => RobotMessage::StartAccepted(one("start reply")?),
            PAUSE => RobotMessage::PauseAccepted(one("pause reply")?),
            DATA_PACKAGE => {
                let recipe_id = if v2 {
                    Some(take(p, &mut at, 1, "output recipe id")?[0])
                } else {
                    None
                };
                RobotMessage::DataPackage {
                    recipe_id,
                    values: p[at..].to_vec(),
                }
            }
            TEXT_MESSAGE => RobotMessage::Text(TextMessage::decode_payload(version, p)?),
            kind => return Err(RtdeError::UnknownPackage { kind }),
        })
    }
}

/// Decodes an output data package in place: the recipe id (v2) and the value bytes, borrowed
/// from `raw` so a real-time loop reads fields without allocating.
pub fn borrow_data_package<'a>(
    version: ProtocolVersion,
    raw: RawPackage<'a>,
) -> Result<(Option<u8>, &'a [u8]), RtdeError> {
    if raw.kind != DATA_PACKAGE {
        return Err(RtdeError::UnknownPackage { kind: raw.kind });
    }
    match version {
        ProtocolVersion::V1 => Ok((None, raw.payload)),
        ProtocolVersion::V2 => {
            let (id, rest) = raw.payload.split_first().ok_or(RtdeError::Truncated {
                what: "output recipe id",
                need: 1,
                got: 0,
            })?;
            Ok((Some(*id), rest))
        }
    }
}
