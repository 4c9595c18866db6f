//! Byte transports carrying the register images: Modbus RTU on a serial device, the URCap
//! text socket on TCP, and CAN frames through an slcan serial adapter. Each is a thin
//! facade over its codec; rejected bytes are logged with their reason and returned as
//! typed errors, and the next exchange starts clean.

use std::io::{BufRead, BufReader, ErrorKind, Read, Write};
use std::net::{TcpStream, ToSocketAddrs};
use std::time::Duration;

use log::{debug, warn};
use serialport::{ClearBuffer, SerialPort};

use super::can::{CanFrame, CanMapping};
use super::modbus_rtu::{self, Direction, FrameReader, Request, Response, Scan};
use super::registers::{
    ActivationStatus, RequestImage, StatusImage, IMAGE_REGISTERS, REQUEST_REGISTER, STATUS_REGISTER,
};
use super::slcan::{LineSplitter, SlcanLine};
use super::socketcand::{MessageSplitter, SocketcandMsg};
use super::urcap::{UrcapCommand, UrcapReply, Var, MAX_LINE};
use super::GripperError;

/// Moves register images to and from a gripper.
pub trait RegisterTransport: Send {
    /// Writes the whole request image.
    fn write_request(&mut self, request: &RequestImage) -> Result<(), GripperError>;
    /// Reads the whole status image.
    fn read_status(&mut self) -> Result<StatusImage, GripperError>;
    /// A short name for messages ("modbus-rtu", "urcap", "slcan").
    fn name(&self) -> &'static str;
}

/// Default time to wait for an answer.
pub const DEFAULT_REPLY_TIMEOUT: Duration = Duration::from_millis(200);

pub(super) fn io_err(context: impl Into<String>) -> impl FnOnce(std::io::Error) -> GripperError {
    let context = context.into();
    move |source| GripperError::Io { context, source }
}

/// Opens a serial device at 115200 8N1 (the gripper's and the usual slcan adapter's rate).
pub fn open_serial(path: &str, timeout: Duration) -> Result<Box<dyn SerialPort>, GripperError> {
    serialport::new(path, 115_200)
        .data_bits(serialport::DataBits::Eight)
        .parity(serialport::Parity::None)
        .stop_bits(serialport::StopBits::One)
        .flow_control(serialport::FlowControl::None)
        .timeout(timeout)
        .open()
        .map_err(|source| GripperError::Serial {
            path: path.to_owned(),
            source,
        })
}

/// Reads once with the port's timeout; `Ok(0)` on timeout.
fn read_some(port: &mut dyn Read, buf: &mut [u8], what: &str) -> Result<usize, GripperError> {
    match port.read(buf) {
        Ok(n) => Ok(n),
        Err(e) if matches!(e.kind(), ErrorKind::TimedOut | ErrorKind::WouldBlock) => Ok(0),
        Err(e) if e.kind() == ErrorKind::Interrupted => Ok(0),
        Err(e) => Err(io_err(format!("reading {what}"))(e)),
    }
}

/// Reads and discards what a socket holds right now, without waiting.
fn drain_socket(stream: &mut TcpStream) -> Result<(), GripperError> {
    stream
        .set_nonblocking(true)
        .map_err(io_err("draining a socket"))?;
    let mut buf = [0u8; 512];
    let mut dropped = 0;
    let result = loop {
        match stream.read(&mut buf) {
            Ok(0) => break Ok(()),
            Ok(n) => dropped += n,
            Err(e) if e.kind() == ErrorKind::WouldBlock => break Ok(()),
            Err(e) if e.kind() == ErrorKind::Interrupted => {}
            Err(e) => break Err(io_err("draining a socket")(e)),
        }
    };
    if dropped > 0 {
        warn!("dropped {dropped} stale bytes from the socket");
    }
    stream
        .set_nonblocking(false)
        .map_err(io_err("draining a socket"))?;
    result
}

/// Modbus RTU master on a serial line: FC16 to write the request image, FC04 to read the
/// status image, each answered before the next request (the gripper is a slave).
pub struct ModbusRtuTransport {
    port: Box<dyn SerialPort>,
    slave: u8,
    reader: FrameReader,
    reply_timeout: Duration,
    /// When the last frame ended, for the inter-frame gap.
    line_quiet_since: Option<std::time::Instant>,
}

impl ModbusRtuTransport {
    /// Opens `path` at 115200 8N1 for slave `slave` (9 on a Robotiq gripper).
    pub fn open(path: &str, slave: u8) -> Result<Self, GripperError> {
        let port = open_serial(path, Duration::from_millis(5))?;
        Ok(Self::new(port, slave))
    }

    /// Wraps an opened port (its read timeout sets the polling granularity).
    pub fn new(port: Box<dyn SerialPort>, slave: u8) -> Self {
        Self {
            port,
            slave,
            reader: FrameReader::new(Direction::Responses),
            reply_timeout: DEFAULT_REPLY_TIMEOUT,
            line_quiet_since: None,
        }
    }

    /// Sets how long to wait for an answer.
    pub fn with_reply_timeout(mut self, t: Duration) -> Self {
        self.reply_timeout = t;
        self
    }

    /// Sends `req` and returns the matching response.
    pub fn transact(&mut self, req: &Request) -> Result<Response, GripperError> {
        let frame = req.encode(self.slave)?;
        // Stale bytes (a late answer, noise) must not be taken for this request's answer.
        let _ = self.port.clear(ClearBuffer::Input);
        self.reader = FrameReader::new(Direction::Responses);
        // RTU frames are delimited by 3.5 character times of silence: wait out what is
        // left of it since the last frame on the line.
        let gap = modbus_rtu::frame_gap(115_200);
        if let Some(left) = self
            .line_quiet_since
            .map(|t| gap.saturating_sub(t.elapsed()))
        {
            if !left.is_zero() {
                std::thread::sleep(left);
            }
        }
        self.port
            .write_all(&frame)
            .and_then(|()| self.port.flush())
            .map_err(io_err("writing a Modbus RTU request"))?;
        let timeout = self.reply_timeout;
        let granularity = self.port.timeout().max(Duration::from_millis(1));
        let mut waited = Duration::ZERO;
        let mut buf = [0u8; 256];
        // The first rejection is the cause; what follows it is usually its debris.
        let mut last_error = None;
        while waited < timeout {
            let n = read_some(&mut self.port, &mut buf, "a Modbus RTU response")?;
            if n == 0 {
                waited += granularity;
                if self.reader.pending() > 0 {
                    if let Some(Scan::Dropped { reason, bytes }) = self.reader.silence() {
                        warn!("modbus-rtu: dropped {bytes} bytes: {reason}");
                        last_error.get_or_insert(GripperError::Truncated {
                            what: "Modbus RTU response",
                            needed: bytes + 1,
                            got: bytes,
                        });
                    }
                }
                continue;
            }
            self.reader.push(&buf[..n]);
            while let Some(scan) = self.reader.next_scan() {
                match scan {
                    Scan::Dropped { bytes, reason } => {
                        warn!("modbus-rtu: dropped {bytes} bytes: {reason}");
                        last_error.get_or_insert(GripperError::Malformed {
                            what: "Modbus RTU response",
                            detail: reason,
                        });
                    }
                    Scan::Frame(f) => {
                        let (slave, resp) = Response::decode(&f)?;
                        if slave != self.slave {
                            warn!("modbus-rtu: ignoring a frame from slave {slave}");
                            last_error.get_or_insert(GripperError::WrongSlave {
                                expected: self.slave,
                                got: slave,
                            });
                            continue;
                        }
                        self.line_quiet_since = Some(std::time::Instant::now());
                        return check_response(req, resp);
                    }
                }
            }
        }
        Err(last_error.unwrap_or(GripperError::Timeout {
            what: "a Modbus RTU response",
            after: timeout,
        }))
    }
}

fn check_response(req: &Request, resp: Response) -> Result<Response, GripperError> {
    let ok = match (req, &resp) {
        (_, Response::Exception { function, code }) => {
            return Err(GripperError::ModbusException {
                function: *function,
                exception: *code,
            })
        }
        (Request::ReadInput { count, .. }, Response::ReadInput { values }) => {
            values.len() == usize::from(*count)
        }
        (Request::WriteMultiple { start, values }, Response::WriteMultiple { start: s, count }) => {
            s == start && usize::from(*count) == values.len()
        }
        (Request::ReadWrite { read_count, .. }, Response::ReadWrite { values }) => {
            values.len() == usize::from(*read_count)
        }
        _ => false,
    };
    if ok {
        Ok(resp)
    } else {
        Err(GripperError::UnexpectedReply {
            transport: "modbus-rtu",
            detail: format!("{resp:?} does not answer {req:?}"),
        })
    }
}

impl RegisterTransport for ModbusRtuTransport {
    fn write_request(&mut self, request: &RequestImage) -> Result<(), GripperError> {
        self.transact(&Request::WriteMultiple {
            start: REQUEST_REGISTER,
            values: request.to_registers().to_vec(),
        })
        .map(|_| ())
    }

    fn read_status(&mut self) -> Result<StatusImage, GripperError> {
        match self.transact(&Request::ReadInput {
            start: STATUS_REGISTER,
            count: IMAGE_REGISTERS,
        })? {
            Response::ReadInput { values } => {
                let regs: [u16; 3] =
                    values
                        .try_into()
                        .map_err(|v: Vec<u16>| GripperError::UnexpectedReply {
                            transport: "modbus-rtu",
                            detail: format!("{} registers instead of 3", v.len()),
                        })?;
                Ok(StatusImage::from_registers(regs))
            }
            other => Err(GripperError::UnexpectedReply {
                transport: "modbus-rtu",
                detail: format!("{other:?}"),
            }),
        }
    }

    fn name(&self) -> &'static str {
        "modbus-rtu"
    }
}

/// Client of the URCap text socket (TCP 63352 on the UR controller). The socket has no
/// current variable, so the status image it builds reports a current of 0.
pub struct UrcapTransport {
    reader: BufReader<TcpStream>,
    writer: TcpStream,
    /// Whether ATR/ARD were last set non-zero (so that clearing them is sent too).
    release_set: bool,
    /// The last exchange failed: unread bytes may follow.
    desynced: bool,
}

impl UrcapTransport {
    /// Connects to the URCap socket at `addr` (e.g. `"192.168.1.10:63352"`).
    pub fn connect(addr: impl ToSocketAddrs, timeout: Duration) -> Result<Self, GripperError> {
        let stream = TcpStream::connect(addr).map_err(io_err("connecting to the URCap socket"))?;
        stream
            .set_read_timeout(Some(timeout))
            .and_then(|()| stream.set_nodelay(true))
            .map_err(io_err("configuring the URCap socket"))?;
        let writer = stream
            .try_clone()
            .map_err(io_err("cloning the URCap socket"))?;
        Ok(Self {
            reader: BufReader::new(stream),
            writer,
            release_set: false,
            desynced: false,
        })
    }

    /// Sends one command and returns its reply line, parsed.
    pub fn exchange(&mut self, cmd: &UrcapCommand) -> Result<UrcapReply, GripperError> {
        if self.desynced {
            // A reply that came late (or half a line) must not answer this command.
            self.drain()?;
            self.desynced = false;
        }
        self.writer
            .write_all(cmd.encode().as_bytes())
            .map_err(io_err("writing to the URCap socket"))?;
        let reply = self.read_reply();
        if reply.is_err() {
            self.desynced = true;
        }
        reply
    }

    fn read_reply(&mut self) -> Result<UrcapReply, GripperError> {
        let mut line = Vec::with_capacity(32);
        let limit = MAX_LINE as u64 + 1;
        match (&mut self.reader).take(limit).read_until(b'\n', &mut line) {
            Ok(0) => Err(GripperError::Io {
                context: "reading the URCap socket".into(),
                source: std::io::Error::new(ErrorKind::UnexpectedEof, "server closed the socket"),
            }),
            Ok(_) if line.last() != Some(&b'\n') => {
                warn!("urcap: reply line cut off or longer than {MAX_LINE} bytes");
                Err(GripperError::Malformed {
                    what: "URCap reply",
                    detail: format!("{} bytes without a newline", line.len()),
                })
            }
            Ok(_) => {
                let text = std::str::from_utf8(&line).map_err(|_| GripperError::Malformed {
                    what: "URCap reply",
                    detail: "not UTF-8".into(),
                });
                text.and_then(UrcapReply::parse)
                    .inspect_err(|e| warn!("urcap: rejected reply: {e}"))
            }
            Err(e) if matches!(e.kind(), ErrorKind::TimedOut | ErrorKind::WouldBlock) => {
                Err(GripperError::Timeout {
                    what: "a URCap reply",
                    after: self
                        .writer
                        .read_timeout()
                        .ok()
                        .flatten()
                        .unwrap_or_default(),
                })
            }
            Err(e) => Err(io_err("reading the URCap socket")(e)),
        }
    }

    /// Discards whatever the server sent that was not read.
    fn drain(&mut self) -> Result<(), GripperError> {
        let held = self.reader.buffer().len();
        self.reader.consume(held);
        drain_socket(self.reader.get_mut())
    }

    fn get(&mut self, var: Var) -> Result<u8, GripperError> {
        match self.exchange(&UrcapCommand::Get(var))? {
            UrcapReply::Value(v, x) if v == var => Ok(x),
            UrcapReply::Unavailable => Err(GripperError::EmergencyStop),
            other => Err(GripperError::UnexpectedReply {
                transport: "urcap",
                detail: format!("{other:?} in answer to GET {var}"),
            }),
        }
    }
}

impl RegisterTransport for UrcapTransport {
    fn write_request(&mut self, r: &RequestImage) -> Result<(), GripperError> {
        let mut pairs = vec![
            (Var::Act, u8::from(r.activate)),
            (Var::Gto, u8::from(r.go_to)),
            (Var::Pos, r.position),
            (Var::Spe, r.speed),
            (Var::For, r.force),
        ];
        // The release variables are sent only when used: their spelling differs between
        // URCap versions (ARD/ADR), and an unknown name would fail the whole line.
        let release = r.auto_release || r.release_direction;
        if release || self.release_set {
            pairs.push((Var::Atr, u8::from(r.auto_release)));
            pairs.push((Var::Ard, u8::from(r.release_direction)));
        }
        let cmd = UrcapCommand::Set(pairs);
        match self.exchange(&cmd)? {
            UrcapReply::Ack => {
                self.release_set = release;
                Ok(())
            }
            UrcapReply::Unavailable => Err(GripperError::EmergencyStop),
            other => Err(GripperError::UnexpectedReply {
                transport: "urcap",
                detail: format!("{other:?} in answer to SET"),
            }),
        }
    }

    fn read_status(&mut self) -> Result<StatusImage, GripperError> {
        Ok(StatusImage {
            activate: self.get(Var::Act)? != 0,
            go_to: self.get(Var::Gto)? != 0,
            activation: ActivationStatus::from_code(self.get(Var::Sta)?),
            object: super::registers::object_from_code(self.get(Var::Obj)?),
            fault: self.get(Var::Flt)?,
            position_request: self.get(Var::Pre)?,
            position: self.get(Var::Pos)?,
            current: 0,
        })
    }

    fn name(&self) -> &'static str {
        "urcap"
    }
}

/// The gripper's CAN mapping through an slcan (Lawicel) serial adapter: a command frame
/// carries the request image and is answered by a status frame; a remote frame on the
/// status id polls the status.
pub struct SlcanTransport {
    port: Box<dyn SerialPort>,
    mapping: CanMapping,
    splitter: LineSplitter,
    reply_timeout: Duration,
}

impl SlcanTransport {
    /// Opens the adapter at `path`, sets 500 kbit/s (`S6`) and opens the channel.
    pub fn open(path: &str, mapping: CanMapping) -> Result<Self, GripperError> {
        let port = open_serial(path, Duration::from_millis(5))?;
        Self::new(port, mapping)
    }

    /// Wraps an opened port and opens the CAN channel.
    pub fn new(port: Box<dyn SerialPort>, mapping: CanMapping) -> Result<Self, GripperError> {
        let mut t = Self {
            port,
            mapping,
            splitter: LineSplitter::new(),
            reply_timeout: DEFAULT_REPLY_TIMEOUT,
        };
        // Close first: an adapter left open by a crashed program refuses `S6`.
        for line in [SlcanLine::Close, SlcanLine::Bitrate(6), SlcanLine::Open] {
            t.send(&line)?;
        }
        Ok(t)
    }

    /// Sets how long to wait for a status frame.
    pub fn with_reply_timeout(mut self, t: Duration) -> Self {
        self.reply_timeout = t;
        self
    }

    fn send(&mut self, line: &SlcanLine) -> Result<(), GripperError> {
        self.port
            .write_all(&line.encode())
            .and_then(|()| self.port.flush())
            .map_err(io_err("writing to the slcan adapter"))
    }

    /// Sends `frame` and waits for the next status frame.
    pub fn exchange(&mut self, frame: CanFrame) -> Result<StatusImage, GripperError> {
        let _ = self.port.clear(ClearBuffer::Input);
        self.splitter = LineSplitter::new();
        self.send(&SlcanLine::Frame(frame))?;
        let granularity = self.port.timeout().max(Duration::from_millis(1));
        let mut waited = Duration::ZERO;
        let mut buf = [0u8; 128];
        let mut found = None;
        let mut last_error = None;
        while waited < self.reply_timeout {
            let n = read_some(&mut self.port, &mut buf, "the slcan adapter")?;
            if n == 0 {
                waited += granularity;
                continue;
            }
            let mapping = self.mapping;
            self.splitter.push(&buf[..n], |line| {
                if found.is_some() {
                    return;
                }
                let parsed = match line {
                    Err(len) => {
                        warn!("slcan: dropped a {len}-byte over-long line");
                        return;
                    }
                    Ok(l) => SlcanLine::parse(l),
                };
                match parsed {
                    Ok(SlcanLine::Frame(f)) => match mapping.decode_status(&f) {
                        Ok(Some(s)) => found = Some(s),
                        Ok(None) => debug!("slcan: ignoring frame {f:?}"),
                        Err(e) => {
                            warn!("slcan: rejected status frame: {e}");
                            last_error = Some(e);
                        }
                    },
                    Ok(SlcanLine::Error) => {
                        warn!("slcan: adapter answered with an error (BELL)");
                        last_error = Some(GripperError::UnexpectedReply {
                            transport: "slcan",
                            detail: "adapter error (BELL)".into(),
                        });
                    }
                    Ok(_) => {}
                    Err(e) => {
                        warn!("slcan: rejected line: {e}");
                        last_error = Some(e);
                    }
                }
            });
            if let Some(s) = found {
                return Ok(s);
            }
        }
        Err(last_error.unwrap_or(GripperError::Timeout {
            what: "a CAN status frame",
            after: self.reply_timeout,
        }))
    }
}

impl RegisterTransport for SlcanTransport {
    fn write_request(&mut self, request: &RequestImage) -> Result<(), GripperError> {
        let frame = self.mapping.command_frame(request);
        self.exchange(frame).map(|_| ())
    }

    fn read_status(&mut self) -> Result<StatusImage, GripperError> {
        let frame = self.mapping.status_poll();
        self.exchange(frame)
    }

    fn name(&self) -> &'static str {
        "slcan"
    }
}

impl Drop for SlcanTransport {
    fn drop(&mut self) {
        let _ = self.send(&SlcanLine::Close);
    }
}

/// The gripper's CAN mapping through a socketcand server (TCP 29536): the `< hi >`,
/// `< open BUS >`, `< rawmode >` handshake, then command frames answered by status frames;
/// status polls are empty frames on the status id (socketcand carries no remote frames).
pub struct SocketcandTransport {
    stream: TcpStream,
    mapping: CanMapping,
    splitter: MessageSplitter,
    reply_timeout: Duration,
}

impl SocketcandTransport {
    /// Connects to `addr`, opens `bus` (e.g. `"can0"`) in raw mode.
    pub fn connect(
        addr: impl ToSocketAddrs,
        bus: &str,
        mapping: CanMapping,
    ) -> Result<Self, GripperError> {
        let stream = TcpStream::connect(addr).map_err(io_err("connecting to socketcand"))?;
        stream
            .set_read_timeout(Some(Duration::from_millis(5)))
            .and_then(|()| stream.set_nodelay(true))
            .map_err(io_err("configuring the socketcand socket"))?;
        let mut t = Self {
            stream,
            mapping,
            splitter: MessageSplitter::new(),
            reply_timeout: DEFAULT_REPLY_TIMEOUT,
        };
        t.expect(&SocketcandMsg::Hi)?;
        t.send(&SocketcandMsg::Open(bus.to_owned()))?;
        t.expect(&SocketcandMsg::Ok)?;
        t.send(&SocketcandMsg::RawMode)?;
        t.expect(&SocketcandMsg::Ok)?;
        Ok(t)
    }

    /// Sets how long to wait for an answer.
    pub fn with_reply_timeout(mut self, t: Duration) -> Self {
        self.reply_timeout = t;
        self
    }

    fn send(&mut self, m: &SocketcandMsg) -> Result<(), GripperError> {
        self.stream
            .write_all(m.encode().as_bytes())
            .map_err(io_err("writing to socketcand"))
    }

    /// Waits for the first message that `pick` accepts; other messages are logged.
    fn wait_for<R>(
        &mut self,
        what: &'static str,
        mut pick: impl FnMut(SocketcandMsg) -> Option<Result<R, GripperError>>,
    ) -> Result<R, GripperError> {
        let granularity = Duration::from_millis(5);
        let mut waited = Duration::ZERO;
        let mut buf = [0u8; 512];
        let mut pending: Vec<SocketcandMsg> = Vec::new();
        loop {
            for m in pending.drain(..) {
                if let Some(r) = pick(m) {
                    return r;
                }
            }
            if waited >= self.reply_timeout {
                return Err(GripperError::Timeout {
                    what,
                    after: self.reply_timeout,
                });
            }
            let n = read_some(&mut self.stream, &mut buf, "socketcand")?;
            if n == 0 {
                waited += granularity;
                continue;
            }
            let text = String::from_utf8_lossy(&buf[..n]).into_owned();
            self.splitter.push(&text, |m| match m {
                Err(junk) => warn!("socketcand: discarded {junk:?}"),
                Ok(m) => match SocketcandMsg::parse(m) {
                    Ok(msg) => pending.push(msg),
                    Err(e) => warn!("socketcand: rejected message: {e}"),
                },
            });
        }
    }

    fn expect(&mut self, want: &SocketcandMsg) -> Result<(), GripperError> {
        let want = want.clone();
        self.wait_for("a socketcand handshake answer", |m| {
            Some(if m == want {
                Ok(())
            } else {
                Err(GripperError::UnexpectedReply {
                    transport: "socketcand",
                    detail: format!("{m:?} instead of {want:?}"),
                })
            })
        })
    }

    /// Sends `frame` and waits for the next status frame.
    pub fn exchange(&mut self, frame: CanFrame) -> Result<StatusImage, GripperError> {
        // Frames left from an exchange that timed out must not answer this one.
        drain_socket(&mut self.stream)?;
        self.splitter = MessageSplitter::new();
        self.send(&SocketcandMsg::Send(frame))?;
        let mapping = self.mapping;
        self.wait_for("a CAN status frame", |m| match m {
            SocketcandMsg::Frame(f, _) => match mapping.decode_status(&f) {
                Ok(Some(s)) => Some(Ok(s)),
                Ok(None) => None,
                Err(e) => {
                    warn!("socketcand: rejected status frame: {e}");
                    Some(Err(e))
                }
            },
            SocketcandMsg::Error(text) => Some(Err(GripperError::UnexpectedReply {
                transport: "socketcand",
                detail: format!("server error: {text}"),
            })),
            _ => None,
        })
    }
}

impl RegisterTransport for SocketcandTransport {
    fn write_request(&mut self, request: &RequestImage) -> Result<(), GripperError> {
        let frame = self.mapping.command_frame(request);
        self.exchange(frame).map(|_| ())
    }

    fn read_status(&mut self) -> Result<StatusImage, GripperError> {
        let frame = self.mapping.status_poll_empty();
        self.exchange(frame)
    }

    fn name(&self) -> &'static str {
        "socketcand"
    }
}
