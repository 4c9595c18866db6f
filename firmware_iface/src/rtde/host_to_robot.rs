//! Packages the host (client) sends to the controller: `V`, `v`, `O`, `I`, `S`, `P`, `U`, `M`.

use super::robot_to_host::TextMessage;
use super::*;

/// A host-to-robot RTDE package.
#[derive(Clone, Debug, PartialEq)]
pub enum HostMessage {
    /// `V`: ask for a protocol version.
    RequestProtocolVersion(u16),
    /// `v`: ask for the controller software version.
    GetControllerVersion,
    /// `O`: set up an output recipe. `frequency` is sent in v2 only (None in v1).
    SetupOutputs {
        /// Output rate (Hz); v2 only.
        frequency: Option<f64>,
        /// Variable names in recipe order.
        names: Vec<String>,
    },
    /// `I`: set up an input recipe.
    SetupInputs {
        /// Variable names in recipe order.
        names: Vec<String>,
    },
    /// `S`: start sending output data packages.
    Start,
    /// `P`: pause output data packages.
    Pause,
    /// `U`: input values for recipe `recipe_id` (both versions carry the id).
    DataPackage {
        /// Input recipe id from the `I` reply.
        recipe_id: u8,
        /// Values, laid out by the recipe's [`Layout`].
        values: Vec<u8>,
    },
    /// `M`: a text message to the controller log.
    Text(TextMessage),
}

impl HostMessage {
    /// Encodes into `out` (cleared first; reuse it to avoid allocating).
    pub fn encode_into(
        &self,
        version: ProtocolVersion,
        out: &mut Vec<u8>,
    ) -> Result<(), RtdeError> {
        match self {
            HostMessage::RequestProtocolVersion(v) => {
                begin_package(out, REQUEST_PROTOCOL_VERSION);
                out.extend_from_slice(&v.to_be_bytes());
            }
            HostMessage::GetControllerVersion => begin_package(out, GET_URCONTROL_VERSION),
            HostMessage::SetupOutputs { frequency, names } => {
                begin_package(out, SETUP_OUTPUTS);
                if version == ProtocolVersion::V2 {
                    out.extend_from_slice(&frequency.unwrap_or(125.0).to_be_bytes());
                }
                join_names(names, out)?;
            }
            HostMessage::SetupInputs { names } => {
                begin_package(out, SETUP_INPUTS);
                join_names(names, out)?;
            }
            HostMessage::Start => begin_package(out, START),
            HostMessage::Pause => begin_package(out, PAUSE),
            HostMessage::DataPackage { recipe_id, values } => {
                begin_package(out, DATA_PACKAGE);
                out.push(*recipe_id);
                out.extend_from_slice(values);
            }
            HostMessage::Text(t) => {
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

    /// Decodes one package received by the controller. `V` decodes in any version, since it
    /// is how the version gets chosen.
    pub fn decode(version: ProtocolVersion, raw: RawPackage<'_>) -> Result<Self, RtdeError> {
        let p = raw.payload;
        let mut at = 0;
        let msg = match raw.kind {
            REQUEST_PROTOCOL_VERSION => {
                let b = take(p, &mut at, 2, "request protocol version")?;
                HostMessage::RequestProtocolVersion(u16::from_be_bytes([b[0], b[1]]))
            }
            GET_URCONTROL_VERSION => HostMessage::GetControllerVersion,
            SETUP_OUTPUTS => {
                let frequency = if version == ProtocolVersion::V2 {
                    let b = take(p, &mut at, 8, "setup outputs frequency")?;
                    let mut a = [0u8; 8];
                    a.copy_from_slice(b);
                    Some(f64::from_be_bytes(a))
                } else {
                    None
                };
                let names = split_names(&p[at..])?;
                at = p.len();
                HostMessage::SetupOutputs { frequency, names }
            }
            SETUP_INPUTS => {
                let names = split_names(p)?;
                at = p.len();
                HostMessage::SetupInputs { names }
            }
            START => HostMessage::Start,
            PAUSE => HostMessage::Pause,
            DATA_PACKAGE => {
                let id = take(p, &mut at, 1, "input data package recipe id")?[0];
                let values = p[at..].to_vec();
                at = p.len();
                HostMessage::DataPackage {
                    recipe_id: id,
                    values,
                }
            }
            TEXT_MESSAGE => {
                let t = TextMessage::decode_payload(version, p)?;
                at = p.len();
                HostMessage::Text(t)
            }
            kind => return Err(RtdeError::UnknownPackage { kind }),
        };
        expect_end(p, at, "host package")?;
        Ok(msg)
    }
}
