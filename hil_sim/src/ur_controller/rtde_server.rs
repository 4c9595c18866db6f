//! The RTDE server side (RTDE guide; UR fact sheet "RTDE"): version negotiation, controller
//! version, output/input recipes with NOT_FOUND and IN_USE, start/pause, data packages at the
//! requested frequency, text messages. Uses the shared codec of `firmware_iface::rtde`; the
//! independent Python peers in the test suite keep a bug shared by both sides from hiding.

use std::io::{Read, Write};
use std::net::{Shutdown, TcpStream};
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::mpsc::{sync_channel, RecvTimeoutError};
use std::sync::{Arc, Mutex};
use std::time::Duration;

use firmware_iface::rtde::{
    split_package, DataType, FieldType, HostMessage, Layout, ProtocolVersion, RobotMessage,
    TextMessage,
};

use super::variables::{apply_input, input_type, output_value};
use super::{lock, Outgoing, Shared};

/// Largest package a client may send: a setup package with the longest name list the
/// controller accepts, plus header and frequency.
pub const MAX_CLIENT_PACKAGE: usize = firmware_iface::rtde::MAX_NAMES_LEN + 16;

struct OutputRecipe {
    id: u8,
    names: Vec<String>,
    divisor: u64,
}

struct InputRecipe {
    id: u8,
    names: Vec<String>,
    layout: Layout,
}

struct Session {
    version: ProtocolVersion,
    output: Option<OutputRecipe>,
    inputs: Vec<InputRecipe>,
    next_id: u8,
    started: bool,
}

/// Serves one RTDE connection until it closes or misbehaves.
pub(crate) fn serve(shared: Arc<Shared>, stream: TcpStream, id: u64) {
    let Ok(write_half) = stream.try_clone() else {
        shared.log(format!("RTDE connection {id}: cannot clone socket"));
        return;
    };
    let writer = Arc::new(Mutex::new(write_half));
    let session = Arc::new(Mutex::new(Session {
        version: ProtocolVersion::V1,
        output: None,
        inputs: Vec::new(),
        next_id: 1,
        started: false,
    }));
    let closed = Arc::new(AtomicBool::new(false));
    // Room for half a second at 125 Hz: a writer starved of CPU for a moment catches up
    // instead of dropping packages (a real controller's socket buffer does the same); a
    // client that stops reading for longer loses packages, never slows the controller.
    let (tx, rx) = sync_channel::<Outgoing>(64);
    shared.subscribe(tx);
    let w = {
        let (shared, writer, session, closed) = (
            shared.clone(),
            writer.clone(),
            session.clone(),
            closed.clone(),
        );
        std::thread::Builder::new()
            .name(format!("ur-sim-rtde-writer-{id}"))
            .spawn(move || {
                let mut buf = Vec::with_capacity(1024);
                while !closed.load(Ordering::SeqCst) {
                    let msg = match rx.recv_timeout(Duration::from_millis(50)) {
                        Ok(m) => m,
                        Err(RecvTimeoutError::Timeout) => continue,
                        Err(RecvTimeoutError::Disconnected) => break,
                    };
                    match msg {
                        Outgoing::Data(snap, produced) => {
                            let delay = shared.delay();
                            if !delay.is_zero() {
                                shared.clock.sleep_until(produced + delay);
                            }
                            let s = lock(&session);
                            let Some(out) = s.output.as_ref().filter(|_| s.started) else {
                                continue;
                            };
                            if snap.cycle % out.divisor != 0 {
                                continue;
                            }
                            if encode_data(&mut buf, s.version, out, &snap).is_err() {
                                continue;
                            }
                        }
                        Outgoing::Text(t) => {
                            let v = lock(&session).version;
                            if RobotMessage::Text(t).encode_into(v, &mut buf).is_err() {
                                continue;
                            }
                        }
                    }
                    if lock(&writer).write_all(&buf).is_err() {
                        break;
                    }
                }
            })
    };
    if w.is_err() {
        shared.log(format!("RTDE connection {id}: cannot start writer"));
        return;
    }
    let reason = read_loop(&shared, &stream, id, &writer, &session);
    // Release the inputs before waiting for the writer thread: a client that closes and
    // reconnects at once (preflight, then the run) must find them free.
    shared.release_inputs(id);
    shared.log(format!("RTDE connection {id} closed: {reason}"));
    closed.store(true, Ordering::SeqCst);
    let _ = stream.shutdown(Shutdown::Both);
    if let Ok(w) = w {
        let _ = w.join();
    }
}

fn read_loop(
    shared: &Shared,
    mut stream: &TcpStream,
    id: u64,
    writer: &Mutex<TcpStream>,
    session: &Mutex<Session>,
) -> String {
    let mut buf: Vec<u8> = Vec::with_capacity(4096);
    let mut chunk = [0u8; 4096];
    let mut out = Vec::with_capacity(256);
    loop {
        let n = match stream.read(&mut chunk) {
            Ok(0) if buf.is_empty() => return "client disconnected".into(),
            Ok(0) => {
                return format!(
                    "client disconnected in the middle of a package ({} bytes pending)",
                    buf.len()
                )
            }
            Ok(n) => n,
            Err(e) => return format!("read failed: {e}"),
        };
        if shared.stopping() {
            return "simulator shutting down".into();
        }
        buf.extend_from_slice(&chunk[..n]);
        loop {
            if buf.len() >= 2 {
                let size = usize::from(u16::from_be_bytes([buf[0], buf[1]]));
                if size > MAX_CLIENT_PACKAGE {
                    return format!(
                        "oversized package: size field {size} exceeds {MAX_CLIENT_PACKAGE} bytes"
                    );
                }
            }
            let (raw, used) = match split_package(&buf) {
                Ok(Some(p)) => p,
                Ok(None) => break,
                Err(e) => return format!("bad package: {e}"),
            };
            let version = lock(session).version;
            let msg = match HostMessage::decode(version, raw) {
                Ok(m) => m,
                Err(e) => return format!("bad package: {e}"),
            };
            buf.drain(..used);
            let reply = match handle(shared, id, session, msg) {
                Ok(r) => r,
                Err(reason) => return reason,
            };
            for r in reply {
                let v = lock(session).version;
                if let Err(e) = r.encode_into(v, &mut out) {
                    return format!("cannot encode reply: {e}");
                }
                if let Err(e) = lock(writer).write_all(&out) {
                    return format!("write failed: {e}");
                }
            }
        }
    }
}

/// Writes an output data package straight into `buf`, without intermediate allocation.
fn encode_data(
    buf: &mut Vec<u8>,
    version: ProtocolVersion,
    out: &OutputRecipe,
    snap: &super::ControllerSnapshot,
) -> Result<(), ()> {
    buf.clear();
    buf.extend_from_slice(&[0, 0, firmware_iface::rtde::DATA_PACKAGE]);
    if version == ProtocolVersion::V2 {
        buf.push(out.id);
    }
    for n in &out.names {
        let v = output_value(n, snap).ok_or(())?;
        let at = buf.len();
        buf.resize(at + v.data_type().size(), 0);
        v.write(&mut buf[at..]).map_err(|_| ())?;
    }
    let size = u16::try_from(buf.len()).map_err(|_| ())?;
    buf[..2].copy_from_slice(&size.to_be_bytes());
    Ok(())
}

fn text(message: String, level: u8) -> RobotMessage {
    RobotMessage::Text(TextMessage {
        message,
        source: "RTDE".into(),
        level,
    })
}

fn handle(
    shared: &Shared,
    id: u64,
    session: &Mutex<Session>,
    msg: HostMessage,
) -> Result<Vec<RobotMessage>, String> {
    let mut s = lock(session);
    Ok(match msg {
        HostMessage::RequestProtocolVersion(v) => match ProtocolVersion::from_number(v) {
            Some(pv) => {
                s.version = pv;
                vec![RobotMessage::ProtocolVersionAccepted(true)]
            }
            None => vec![RobotMessage::ProtocolVersionAccepted(false)],
        },
        HostMessage::GetControllerVersion => {
            vec![RobotMessage::ControllerVersion(shared.config.controller)]
        }
        HostMessage::SetupOutputs { frequency, names } => {
            let max = shared.config.controller.max_frequency();
            let freq = frequency.unwrap_or(max);
            let snap = shared.core().snapshot();
            let types: Vec<FieldType> = names
                .iter()
                .map(|n| {
                    output_value(n, &snap)
                        .map_or(FieldType::NotFound, |v| FieldType::Type(v.data_type()))
                })
                .collect();
            let mut replies = Vec::new();
            let ok_freq = freq.is_finite() && freq > 0.0 && freq <= max;
            if !ok_freq {
                replies.push(text(
                    format!("requested frequency {freq} Hz is outside (0, {max}] Hz"),
                    1,
                ));
            }
            let ok = ok_freq && !types.contains(&FieldType::NotFound) && !names.is_empty();
            let rid = if ok {
                let rid = s.next_id;
                s.next_id = s.next_id.saturating_add(1);
                s.output = Some(OutputRecipe {
                    id: rid,
                    names,
                    divisor: ((max / freq).round() as u64).max(1),
                });
                rid
            } else {
                0
            };
            let recipe_id = (s.version == ProtocolVersion::V2).then_some(rid);
            replies.push(RobotMessage::SetupOutputs { recipe_id, types });
            replies
        }
        HostMessage::SetupInputs { names } => {
            let mut owners = lock(&shared.input_owners);
            let mut types = Vec::with_capacity(names.len());
            for n in &names {
                types.push(match (input_type(n), owners.get(n)) {
                    (None, _) => FieldType::NotFound,
                    (Some(_), Some(owner)) if *owner != id => FieldType::InUse,
                    (Some(t), _) => FieldType::Type(t),
                });
            }
            let data_types: Vec<DataType> = types
                .iter()
                .filter_map(|t| match t {
                    FieldType::Type(d) => Some(*d),
                    _ => None,
                })
                .collect();
            let rid = if data_types.len() == names.len() && !names.is_empty() {
                for n in &names {
                    owners.insert(n.clone(), id);
                }
                let rid = s.next_id;
                s.next_id = s.next_id.saturating_add(1);
                s.inputs.push(InputRecipe {
                    id: rid,
                    names,
                    layout: Layout::new(&data_types),
                });
                rid
            } else {
                0
            };
            vec![RobotMessage::SetupInputs {
                recipe_id: rid,
                types,
            }]
        }
        HostMessage::Start => {
            let ok = s.output.is_some() || !s.inputs.is_empty();
            s.started = ok;
            vec![RobotMessage::StartAccepted(ok)]
        }
        HostMessage::Pause => {
            s.started = false;
            vec![RobotMessage::PauseAccepted(true)]
        }
        HostMessage::DataPackage { recipe_id, values } => {
            let Some(r) = s.inputs.iter().find(|r| r.id == recipe_id) else {
                return Err(format!("data package for unknown input recipe {recipe_id}"));
            };
            let decoded = r
                .layout
                .decode_all(&values)
                .map_err(|e| format!("bad input data package: {e}"))?;
            {
                let mut core = shared.core();
                for (n, v) in r.names.iter().zip(decoded) {
                    apply_input(n, v, &mut core.registers);
                }
                // Counted under the core's lock, so that a control cycle (lockstep) knows
                // exactly which inputs the registers it stepped on held.
                shared.input_received();
            }
            Vec::new()
        }
        HostMessage::Text(t) => {
            drop(s);
            shared.log(format!("RTDE connection {id} says: {}", t.message));
            Vec::new()
        }
    })
}
