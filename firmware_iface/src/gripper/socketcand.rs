//! socketcand's ASCII protocol (fact sheet "CAN"; TCP 29536), the network form of a CAN
//! bus that python-can's `socketcand` interface speaks: the server greets with `< hi >`,
//! `< open can0 >` and `< rawmode >` are each answered `< ok >`, frames are sent as
//! `< send 209 6 9 0 0 ff 80 40 >` (hex id, hex length, hex bytes) and arrive as
//! `< frame 189 12.345678 B90000FF7B46 >` (3 hex digits = standard id, 8 = extended).
//! The protocol has no remote frames, so a status poll is an empty data frame on the status
//! id (see `can`). Pure codec: no I/O.

use std::time::Duration;

use super::can::{CanFrame, CanId};
use super::GripperError;

/// socketcand's default TCP port.
pub const SOCKETCAND_PORT: u16 = 29536;
/// Longest message either side accepts (python-can discards incomplete ones past 200).
pub const MAX_MESSAGE: usize = 200;

/// One `< ... >` message.
#[derive(Clone, Debug, PartialEq, Eq)]
pub enum SocketcandMsg {
    /// `< hi >`: the server's greeting.
    Hi,
    /// `< ok >`.
    Ok,
    /// `< open BUS >`.
    Open(String),
    /// `< rawmode >`.
    RawMode,
    /// `< send ID LEN B.. >`: a frame to transmit.
    Send(CanFrame),
    /// `< frame ID SEC.USEC HEX >`: a received frame and its time stamp.
    Frame(CanFrame, Duration),
    /// `< error TEXT >`.
    Error(String),
}

fn id_text(id: CanId) -> String {
    match id {
        CanId::Standard(i) => format!("{i:03X}"),
        CanId::Extended(i) => format!("{i:08X}"),
    }
}

fn bad(detail: String) -> GripperError {
    GripperError::Malformed {
        what: "socketcand message",
        detail,
    }
}

fn parse_id(s: &str) -> Result<CanId, GripperError> {
    let raw = u32::from_str_radix(s, 16).map_err(|_| bad(format!("CAN id {s:?} is not hex")))?;
    // Like python-can: the width of the id says standard (3 digits) or extended.
    if s.len() <= 3 {
        CanId::standard(raw as u16)
    } else {
        CanId::extended(raw)
    }
}

fn hex_byte(s: &str) -> Result<u8, GripperError> {
    if s.is_empty() || s.len() > 2 {
        return Err(bad(format!("data byte {s:?} is not 1-2 hex digits")));
    }
    u8::from_str_radix(s, 16).map_err(|_| bad(format!("data byte {s:?} is not hex")))
}

impl SocketcandMsg {
    /// The message text.
    pub fn encode(&self) -> String {
        match self {
            Self::Hi => "< hi >".into(),
            Self::Ok => "< ok >".into(),
            Self::Open(bus) => format!("< open {bus} >"),
            Self::RawMode => "< rawmode >".into(),
            Self::Send(f) => {
                let mut s = format!("< send {} {:X}", id_text(f.id), f.len);
                for b in f.payload() {
                    s.push_str(&format!(" {b:x}"));
                }
                s.push_str(" >");
                s
            }
            Self::Frame(f, t) => {
                let hex: String = f.payload().iter().map(|b| format!("{b:02X}")).collect();
                format!(
                    "< frame {} {}.{:06} {hex} >",
                    id_text(f.id),
                    t.as_secs(),
                    t.subsec_micros()
                )
            }
            Self::Error(text) => format!("< error {text} >"),
        }
    }

    /// Parses one message, `<` and `>` included.
    pub fn parse(msg: &str) -> Result<Self, GripperError> {
        if msg.len() > MAX_MESSAGE {
            return Err(bad(format!(
                "{} bytes, longer than {MAX_MESSAGE}",
                msg.len()
            )));
        }
        let inner = msg
            .trim()
            .strip_prefix('<')
            .and_then(|m| m.strip_suffix('>'))
            .ok_or_else(|| bad(format!("{msg:?} is not enclosed in < >")))?;
        let words: Vec<&str> = inner.split_ascii_whitespace().collect();
        match words.as_slice() {
            ["hi"] => Ok(Self::Hi),
            ["ok"] => Ok(Self::Ok),
            ["open", bus] => Ok(Self::Open((*bus).to_owned())),
            ["rawmode"] => Ok(Self::RawMode),
            ["error", rest @ ..] => Ok(Self::Error(rest.join(" "))),
            ["send", id, len, data @ ..] => {
                let id = parse_id(id)?;
                let len = u8::from_str_radix(len, 16)
                    .map_err(|_| bad(format!("length {len:?} is not hex")))?;
                if usize::from(len) != data.len() {
                    return Err(bad(format!("length {len} but {} data bytes", data.len())));
                }
                let bytes = data
                    .iter()
                    .map(|b| hex_byte(b))
                    .collect::<Result<Vec<u8>, _>>()?;
                Ok(Self::Send(CanFrame::data(id, &bytes)?))
            }
            ["frame", id, time, data @ ..] if data.len() <= 1 => {
                let id = parse_id(id)?;
                let secs: f64 = time
                    .parse()
                    .ok()
                    .filter(|t: &f64| t.is_finite() && *t >= 0.0)
                    .ok_or_else(|| bad(format!("time stamp {time:?} is not a number")))?;
                let hex = data.first().copied().unwrap_or("");
                if hex.len() % 2 != 0 || !hex.is_ascii() {
                    return Err(bad(format!("frame data {hex:?} is not whole hex bytes")));
                }
                let bytes = (0..hex.len())
                    .step_by(2)
                    .map(|i| hex_byte(&hex[i..i + 2]))
                    .collect::<Result<Vec<u8>, _>>()?;
                Ok(Self::Frame(
                    CanFrame::data(id, &bytes)?,
                    Duration::from_secs_f64(secs),
                ))
            }
            _ => Err(bad(format!("unknown message {msg:?}"))),
        }
    }
}

/// Cuts a text stream into `< ... >` messages; text outside brackets and over-long
/// messages are passed on as errors (with the discarded text) so they can be logged.
#[derive(Debug, Default)]
pub struct MessageSplitter {
    buf: String,
}

impl MessageSplitter {
    /// An empty splitter.
    pub fn new() -> Self {
        Self::default()
    }

    /// Feeds text; calls `on_msg` with each complete message or discarded run.
    pub fn push(&mut self, text: &str, mut on_msg: impl FnMut(Result<&str, &str>)) {
        self.buf.push_str(text);
        loop {
            let Some(start) = self.buf.find('<') else {
                if !self.buf.trim().is_empty() {
                    on_msg(Err(&self.buf));
                }
                self.buf.clear();
                return;
            };
            if !self.buf[..start].trim().is_empty() {
                on_msg(Err(&self.buf[..start]));
            }
            self.buf.drain(..start);
            match self.buf.find('>') {
                Some(end) => {
                    // A `<` inside means the earlier message was cut off: drop it.
                    if let Some(inner) = self.buf[1..end].rfind('<') {
                        on_msg(Err(&self.buf[..=inner]));
                        self.buf.drain(..=inner);
                        continue;
                    }
                    on_msg(Ok(&self.buf[..=end]));
                    self.buf.drain(..=end);
                }
                None => {
                    if self.buf.len() > MAX_MESSAGE {
                        on_msg(Err(&self.buf));
                        self.buf.clear();
                    }
                    return;
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
    fn golden_messages_from_fact_sheet() {
        let f = CanFrame::data(CanId::Standard(0x200), &[1, 2, 3, 4]).unwrap();
        assert_eq!(
            SocketcandMsg::parse("< send 200 4 1 2 3 4 >").unwrap(),
            SocketcandMsg::Send(f)
        );
        assert_eq!(SocketcandMsg::Send(f).encode(), "< send 200 4 1 2 3 4 >");
        let s = CanFrame::data(CanId::Standard(0x189), &[0xB9, 0, 0, 0xFF, 0x7B, 0x46]).unwrap();
        let m = SocketcandMsg::Frame(s, Duration::from_micros(12_345_678));
        assert_eq!(m.encode(), "< frame 189 12.345678 B90000FF7B46 >");
        assert_eq!(SocketcandMsg::parse(&m.encode()).unwrap(), m);
        for (text, msg) in [
            ("< hi >", SocketcandMsg::Hi),
            ("< ok >", SocketcandMsg::Ok),
            ("< open can0 >", SocketcandMsg::Open("can0".into())),
            ("< rawmode >", SocketcandMsg::RawMode),
        ] {
            assert_eq!(SocketcandMsg::parse(text).unwrap(), msg);
            assert_eq!(msg.encode(), text);
        }
        let empty = CanFrame::data(CanId::Standard(0x189), &[]).unwrap();
        assert_eq!(SocketcandMsg::Send(empty).encode(), "< send 189 0 >");
        let ext = CanFrame::data(CanId::Extended(0x189), &[1]).unwrap();
        assert_eq!(SocketcandMsg::Send(ext).encode(), "< send 00000189 1 1 >");
    }

    #[test]
    fn bad_messages_are_typed_errors() {
        for bad in [
            "hi",
            "< send 200 4 1 2 3 >",
            "< send xyz 1 1 >",
            "< send 200 1 100 >",
            "< send 800 0 >",
            "< frame 189 abc 00 >",
            "< frame 189 1.0 ABC >",
            "< bogus >",
            "< send 200 9 0 0 0 0 0 0 0 0 0 >",
        ] {
            assert!(SocketcandMsg::parse(bad).is_err(), "{bad:?} accepted");
        }
    }

    #[test]
    fn splitter_separates_messages_and_garbage() {
        let mut s = MessageSplitter::new();
        let mut got = vec![];
        s.push("< hi >< ok >junk< send 2", |m| {
            got.push(m.map(str::to_owned).map_err(str::to_owned))
        });
        s.push("00 0 >< cut < ok >", |m| {
            got.push(m.map(str::to_owned).map_err(str::to_owned))
        });
        assert_eq!(
            got,
            vec![
                Ok("< hi >".to_owned()),
                Ok("< ok >".to_owned()),
                Err("junk".to_owned()),
                Ok("< send 200 0 >".to_owned()),
                Err("< cut ".to_owned()),
                Ok("< ok >".to_owned()),
            ]
        );
    }

    proptest! {
        #[test]
        fn send_round_trips(ext in any::<bool>(), id in 0u32..0x2000_0000, data in proptest::collection::vec(any::<u8>(), 0..=8), us in 0u64..10_000_000_000) {
            let id = if ext { CanId::Extended(id) } else { CanId::Standard((id & 0x7FF) as u16) };
            let f = CanFrame::data(id, &data).unwrap();
            prop_assert_eq!(SocketcandMsg::parse(&SocketcandMsg::Send(f).encode()).unwrap(), SocketcandMsg::Send(f));
            let m = SocketcandMsg::Frame(f, Duration::from_micros(us));
            prop_assert_eq!(SocketcandMsg::parse(&m.encode()).unwrap(), m);
        }

        #[test]
        fn any_text_never_panics(s in "\\PC{0,120}") {
            let _ = SocketcandMsg::parse(&s);
            MessageSplitter::new().push(&s, |_| {});
        }
    }
}
