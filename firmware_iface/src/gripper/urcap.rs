//! The URCap text socket (fact sheet "URCap text socket", TCP 63352): `SET NAME VALUE ...`
//! answered by `ack`, `GET NAME` answered by `NAME VALUE`, or `?` while in emergency stop.
//! Lines end in `\n`. Pure codec: no I/O.

use std::fmt;

use super::GripperError;

/// Default TCP port of the URCap gripper socket.
pub const URCAP_PORT: u16 = 63352;
/// Longest line either side accepts: longer input is garbage, not a command.
pub const MAX_LINE: usize = 256;

/// A variable of the URCap socket.
#[derive(Copy, Clone, Debug, PartialEq, Eq, Hash)]
pub enum Var {
    /// rACT / gACT.
    Act,
    /// rGTO / gGTO.
    Gto,
    /// rATR.
    Atr,
    /// rARD.
    Ard,
    /// SET: rPR; GET: gPO (actual position).
    Pos,
    /// rSP.
    Spe,
    /// rFR.
    For,
    /// gSTA.
    Sta,
    /// gPR (echo of the position request).
    Pre,
    /// gOBJ.
    Obj,
    /// gFLT.
    Flt,
}

impl Var {
    /// Every variable, in the fact sheet's order.
    pub const ALL: [Var; 11] = [
        Var::Act,
        Var::Gto,
        Var::Atr,
        Var::Ard,
        Var::Pos,
        Var::Spe,
        Var::For,
        Var::Sta,
        Var::Pre,
        Var::Obj,
        Var::Flt,
    ];

    /// The name on the wire.
    pub fn name(self) -> &'static str {
        match self {
            Var::Act => "ACT",
            Var::Gto => "GTO",
            Var::Atr => "ATR",
            Var::Ard => "ARD",
            Var::Pos => "POS",
            Var::Spe => "SPE",
            Var::For => "FOR",
            Var::Sta => "STA",
            Var::Pre => "PRE",
            Var::Obj => "OBJ",
            Var::Flt => "FLT",
        }
    }

    /// Parses a wire name (exact, upper case). `ADR` is accepted for `ARD`: Robotiq's own
    /// examples spell the release-direction variable that way, the fact sheet `ARD`.
    pub fn parse(name: &str) -> Result<Self, GripperError> {
        if name == "ADR" {
            return Ok(Var::Ard);
        }
        Self::ALL
            .into_iter()
            .find(|v| v.name() == name)
            .ok_or_else(|| GripperError::Malformed {
                what: "URCap variable",
                detail: format!("unknown variable {name:?}"),
            })
    }
}

impl fmt::Display for Var {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(self.name())
    }
}

/// A line from the client (host) to the URCap server.
#[derive(Clone, Debug, PartialEq, Eq)]
pub enum UrcapCommand {
    /// `SET NAME VALUE [NAME VALUE ...]`.
    Set(Vec<(Var, u8)>),
    /// `GET NAME`.
    Get(Var),
}

/// A line from the URCap server to the client.
#[derive(Clone, Debug, PartialEq, Eq)]
pub enum UrcapReply {
    /// `ack`: a SET was applied.
    Ack,
    /// `NAME VALUE`: the answer to a GET.
    Value(Var, u8),
    /// `?`: not available (emergency stop).
    Unavailable,
}

fn value(s: &str) -> Result<u8, GripperError> {
    s.parse::<u8>().map_err(|_| GripperError::Malformed {
        what: "URCap value",
        detail: format!("{s:?} is not an integer in 0..=255"),
    })
}

fn check_line(line: &str) -> Result<&str, GripperError> {
    if line.len() > MAX_LINE {
        return Err(GripperError::Malformed {
            what: "URCap line",
            detail: format!("{} bytes, longer than {MAX_LINE}", line.len()),
        });
    }
    Ok(line.trim_end_matches(['\n', '\r']))
}

impl UrcapCommand {
    /// The line, newline included.
    pub fn encode(&self) -> String {
        match self {
            Self::Set(pairs) => {
                let mut s = String::from("SET");
                for (v, x) in pairs {
                    s.push_str(&format!(" {v} {x}"));
                }
                s.push('\n');
                s
            }
            Self::Get(v) => format!("GET {v}\n"),
        }
    }

    /// Parses one line (trailing `\n` or `\r\n` allowed).
    pub fn parse(line: &str) -> Result<Self, GripperError> {
        let line = check_line(line)?;
        let mut words = line.split_ascii_whitespace();
        let bad = |detail: String| GripperError::Malformed {
            what: "URCap command",
            detail,
        };
        match words.next() {
            Some("SET") => {
                let rest: Vec<&str> = words.collect();
                if rest.is_empty() || !rest.len().is_multiple_of(2) {
                    return Err(bad(format!("SET needs NAME VALUE pairs, got {line:?}")));
                }
                let pairs = rest
                    .chunks_exact(2)
                    .map(|p| Ok((Var::parse(p[0])?, value(p[1])?)))
                    .collect::<Result<Vec<_>, GripperError>>()?;
                Ok(Self::Set(pairs))
            }
            Some("GET") => match (words.next(), words.next()) {
                (Some(name), None) => Ok(Self::Get(Var::parse(name)?)),
                _ => Err(bad(format!("GET takes exactly one variable, got {line:?}"))),
            },
            _ => Err(bad(format!("expected SET or GET, got {line:?}"))),
        }
    }
}

impl UrcapReply {
    /// The line, newline included.
    pub fn encode(&self) -> String {
        match self {
            Self::Ack => "ack\n".to_owned(),
            Self::Value(v, x) => format!("{v} {x}\n"),
            Self::Unavailable => "?\n".to_owned(),
        }
    }

    /// Parses one line (trailing `\n` or `\r\n` allowed).
    pub fn parse(line: &str) -> Result<Self, GripperError> {
        let line = check_line(line)?;
        match line {
            "ack" => Ok(Self::Ack),
            "?" => Ok(Self::Unavailable),
            _ => {
                let mut words = line.split_ascii_whitespace();
                match (words.next(), words.next(), words.next()) {
                    (Some(n), Some(x), None) => Ok(Self::Value(Var::parse(n)?, value(x)?)),
                    _ => Err(GripperError::Malformed {
                        what: "URCap reply",
                        detail: format!("expected `ack`, `?` or `NAME VALUE`, got {line:?}"),
                    }),
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
    fn golden_lines_from_fact_sheet() {
        assert_eq!(
            UrcapCommand::Set(vec![(Var::Act, 1)]).encode(),
            "SET ACT 1\n"
        );
        assert_eq!(
            UrcapCommand::parse("SET GTO 1 POS 255 SPE 128 FOR 64\n").unwrap(),
            UrcapCommand::Set(vec![
                (Var::Gto, 1),
                (Var::Pos, 255),
                (Var::Spe, 128),
                (Var::For, 64)
            ])
        );
        assert_eq!(UrcapCommand::Get(Var::Pos).encode(), "GET POS\n");
        assert_eq!(UrcapReply::parse("ack\n").unwrap(), UrcapReply::Ack);
        assert_eq!(
            UrcapReply::parse("POS 123\n").unwrap(),
            UrcapReply::Value(Var::Pos, 123)
        );
        assert_eq!(UrcapReply::parse("?\n").unwrap(), UrcapReply::Unavailable);
        assert_eq!(
            UrcapCommand::parse("SET ADR 1").unwrap(),
            UrcapCommand::Set(vec![(Var::Ard, 1)])
        );
    }

    #[test]
    fn garbage_lines_are_typed_errors() {
        for bad in [
            "",
            "HELLO",
            "SET ACT",
            "SET ACT 256",
            "SET XYZ 1",
            "GET",
            "GET POS STA",
            "SET ACT -1",
            "\u{0}\u{1}\u{2}",
        ] {
            assert!(UrcapCommand::parse(bad).is_err(), "{bad:?} accepted");
        }
        assert!(UrcapCommand::parse(&"SET ACT 1 ".repeat(40)).is_err());
        for bad in ["", "ACK", "POS", "POS 1 2", "POS x"] {
            assert!(UrcapReply::parse(bad).is_err(), "{bad:?} accepted");
        }
    }

    fn any_var() -> impl Strategy<Value = Var> {
        proptest::sample::select(Var::ALL.to_vec())
    }

    proptest! {
        #[test]
        fn commands_round_trip(pairs in proptest::collection::vec((any_var(), any::<u8>()), 1..8), g in any_var()) {
            let set = UrcapCommand::Set(pairs);
            prop_assert_eq!(UrcapCommand::parse(&set.encode()).unwrap(), set);
            let get = UrcapCommand::Get(g);
            prop_assert_eq!(UrcapCommand::parse(&get.encode()).unwrap(), get);
        }

        #[test]
        fn replies_round_trip(v in any_var(), x in any::<u8>()) {
            for r in [UrcapReply::Ack, UrcapReply::Unavailable, UrcapReply::Value(v, x)] {
                prop_assert_eq!(UrcapReply::parse(&r.encode()).unwrap(), r);
            }
        }

        #[test]
        fn any_text_never_panics(s in "\\PC{0,80}") {
            let _ = UrcapCommand::parse(&s);
            let _ = UrcapReply::parse(&s);
        }
    }
}
