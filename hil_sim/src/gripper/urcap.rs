//! The emulator's URCap text server (fact sheet "URCap text socket") on loopback TCP: one
//! thread per client, `SET` answered by `ack`, `GET` by `NAME VALUE`. Lines that do not
//! parse (garbage, unknown variables, over-long lines, bad UTF-8) get no answer: they are
//! logged and counted and the connection stays up.

use std::io::{BufRead, BufReader, ErrorKind, Read, Write};
use std::net::{SocketAddr, TcpListener, TcpStream};
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::Arc;

use firmware_iface::gripper::registers::object_code;
use firmware_iface::gripper::urcap::{UrcapCommand, UrcapReply, Var, MAX_LINE};

use super::{spawn_thread, Endpoint, GripperSim, ServerStats, SimError, SimServer, POLL};

const NAME: &str = "urcap";

pub(crate) fn spawn(sim: GripperSim, addr: SocketAddr) -> Result<SimServer, SimError> {
    let io = |context: &str| {
        let context = context.to_owned();
        move |source| SimError::Io { context, source }
    };
    let listener = TcpListener::bind(addr).map_err(io("binding the URCap server"))?;
    let local = listener
        .local_addr()
        .map_err(io("reading the URCap address"))?;
    listener
        .set_nonblocking(true)
        .map_err(io("configuring the URCap listener"))?;
    let stats = Arc::new(ServerStats::default());
    let stop = Arc::new(AtomicBool::new(false));
    let thread = {
        let (stats, stop) = (stats.clone(), stop.clone());
        spawn_thread("gripper-sim-urcap", move || {
            let mut clients = Vec::new();
            while !stop.load(Ordering::SeqCst) {
                match listener.accept() {
                    Ok((stream, _)) => {
                        let (sim, client_stats, stop) = (sim.clone(), stats.clone(), stop.clone());
                        match spawn_thread("gripper-sim-urcap-client", move || {
                            serve(stream, &sim, &client_stats, &stop)
                        }) {
                            Ok(h) => clients.push(h),
                            Err(e) => stats.reject(NAME, e.to_string()),
                        }
                    }
                    Err(e) if e.kind() == ErrorKind::WouldBlock => std::thread::sleep(POLL),
                    Err(e) => {
                        stats.reject(NAME, format!("accept failed: {e}"));
                        std::thread::sleep(POLL);
                    }
                }
                clients.retain(|h: &std::thread::JoinHandle<()>| !h.is_finished());
            }
            for h in clients {
                let _ = h.join();
            }
        })?
    };
    Ok(SimServer {
        endpoint: Endpoint::Tcp(local),
        stats,
        stop,
        thread: Some(thread),
        _slave: None,
    })
}

fn serve(stream: TcpStream, sim: &GripperSim, stats: &ServerStats, stop: &AtomicBool) {
    if stream.set_nonblocking(false).is_err() || stream.set_read_timeout(Some(POLL)).is_err() {
        stats.reject(NAME, "cannot configure a client socket");
        return;
    }
    let Ok(mut writer) = stream.try_clone() else {
        stats.reject(NAME, "cannot clone a client socket");
        return;
    };
    let mut reader = BufReader::new(stream);
    let mut line = Vec::with_capacity(MAX_LINE + 1);
    while !stop.load(Ordering::SeqCst) {
        let room = (MAX_LINE + 1).saturating_sub(line.len()) as u64;
        match (&mut reader).take(room).read_until(b'\n', &mut line) {
            Ok(0) if line.is_empty() => return,
            Ok(_) => {}
            Err(e) if matches!(e.kind(), ErrorKind::WouldBlock | ErrorKind::TimedOut) => continue,
            Err(e) if e.kind() == ErrorKind::Interrupted => continue,
            Err(e) => {
                stats.reject(NAME, format!("client read error: {e}"));
                return;
            }
        }
        if line.last() != Some(&b'\n') {
            if line.len() > MAX_LINE {
                stats.reject(NAME, format!("line longer than {MAX_LINE} bytes"));
                line.clear();
            }
            continue;
        }
        let reply = match std::str::from_utf8(&line) {
            Err(_) => {
                stats.reject(NAME, "line is not UTF-8");
                None
            }
            Ok(text) => match UrcapCommand::parse(text) {
                Err(e) => {
                    stats.reject(NAME, e.to_string());
                    None
                }
                Ok(cmd) => {
                    stats.accept();
                    Some(answer(sim, &cmd))
                }
            },
        };
        line.clear();
        if let Some(r) = reply {
            if writer.write_all(r.encode().as_bytes()).is_err() {
                return;
            }
        }
    }
}

fn answer(sim: &GripperSim, cmd: &UrcapCommand) -> UrcapReply {
    // In emergency stop the controller cannot reach the gripper: every request gets `?`.
    if sim.emergency_stop() {
        return UrcapReply::Unavailable;
    }
    match cmd {
        UrcapCommand::Set(pairs) => {
            let mut r = sim.request();
            for (var, x) in pairs {
                let on = *x != 0;
                match var {
                    Var::Act => r.activate = on,
                    Var::Gto => r.go_to = on,
                    Var::Atr => r.auto_release = on,
                    Var::Ard => r.release_direction = on,
                    Var::Pos => r.position = *x,
                    Var::Spe => r.speed = *x,
                    Var::For => r.force = *x,
                    // Status variables are read-only; the URCap ignores writes to them.
                    Var::Sta | Var::Pre | Var::Obj | Var::Flt => {}
                }
            }
            sim.write_request(r);
            UrcapReply::Ack
        }
        UrcapCommand::Get(var) => {
            let s = sim.read_status();
            let r = sim.request();
            let x = match var {
                Var::Act => u8::from(s.activate),
                Var::Gto => u8::from(s.go_to),
                Var::Atr => u8::from(r.auto_release),
                Var::Ard => u8::from(r.release_direction),
                Var::Pos => s.position,
                Var::Spe => r.speed,
                Var::For => r.force,
                Var::Sta => s.activation.code(),
                Var::Pre => s.position_request,
                Var::Obj => object_code(s.object),
                Var::Flt => s.fault,
            };
            UrcapReply::Value(*var, x)
        }
    }
}
