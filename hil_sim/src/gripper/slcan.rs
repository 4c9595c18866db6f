//! The emulator's CAN side (fact sheet "CAN"): an slcan (Lawicel) adapter on a
//! pseudo-terminal with the gripper's gateway behind it. A command frame carrying the
//! request image is answered by a status frame; a remote frame on the status id polls the
//! status. Adapter commands get `\r`, transmitted frames `z\r`/`Z\r`, bad lines `\x07`
//! (the Lawicel error answer), logged and counted.

use std::io::{ErrorKind, Read, Write};
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::Arc;

use firmware_iface::gripper::can::{CanFrame, CanId, CanMapping};
use firmware_iface::gripper::slcan::{LineSplitter, SlcanLine};

use super::{pty_pair, spawn_thread, Endpoint, GripperSim, ServerStats, SimError, SimServer};

const NAME: &str = "slcan";

pub(crate) fn spawn(sim: GripperSim, mapping: CanMapping) -> Result<SimServer, SimError> {
    let (master, slave_port, path) = pty_pair()?;
    let stats = Arc::new(ServerStats::default());
    let stop = Arc::new(AtomicBool::new(false));
    let thread = {
        let (stats, stop) = (stats.clone(), stop.clone());
        spawn_thread("gripper-sim-slcan", move || {
            serve(master, &sim, mapping, &stats, &stop)
        })?
    };
    Ok(SimServer {
        endpoint: Endpoint::Pty(path),
        stats,
        stop,
        thread: Some(thread),
        _slave: Some(slave_port),
    })
}

fn serve(
    mut port: serialport::TTYPort,
    sim: &GripperSim,
    mapping: CanMapping,
    stats: &ServerStats,
    stop: &AtomicBool,
) {
    let mut splitter = LineSplitter::new();
    let mut open = false;
    let mut buf = [0u8; 256];
    let mut out = Vec::with_capacity(256);
    while !stop.load(Ordering::SeqCst) {
        let n = match port.read(&mut buf) {
            Ok(n) => n,
            Err(e)
                if matches!(
                    e.kind(),
                    ErrorKind::TimedOut | ErrorKind::WouldBlock | ErrorKind::Interrupted
                ) =>
            {
                continue
            }
            Err(e) => {
                stats.reject(NAME, format!("read error {e}"));
                std::thread::sleep(super::POLL);
                continue;
            }
        };
        out.clear();
        splitter.push(&buf[..n], |line| {
            let reply = match line {
                Err(len) => {
                    stats.reject(NAME, format!("over-long line ({len} bytes)"));
                    SlcanLine::Error.encode()
                }
                Ok(l) => handle(l, sim, mapping, &mut open, stats),
            };
            out.extend_from_slice(&reply);
        });
        if !out.is_empty() && port.write_all(&out).is_err() {
            stats.reject(NAME, "write error");
        }
    }
}

fn handle(
    line: &[u8],
    sim: &GripperSim,
    mapping: CanMapping,
    open: &mut bool,
    stats: &ServerStats,
) -> Vec<u8> {
    let ok = SlcanLine::Ok.encode();
    let parsed = match SlcanLine::parse(line) {
        Ok(p) => p,
        Err(e) => {
            stats.reject(NAME, e.to_string());
            return SlcanLine::Error.encode();
        }
    };
    match parsed {
        SlcanLine::Open | SlcanLine::ListenOnly => {
            *open = true;
            ok
        }
        SlcanLine::Close => {
            *open = false;
            ok
        }
        SlcanLine::Bitrate(_) if *open => {
            stats.reject(NAME, "bit rate change while the channel is open");
            SlcanLine::Error.encode()
        }
        SlcanLine::Bitrate(_) => ok,
        SlcanLine::Version(_) => SlcanLine::Version("1013".into()).encode(),
        SlcanLine::Serial(_) => SlcanLine::Serial("SIM9".into()).encode(),
        SlcanLine::Flags(_) => SlcanLine::Flags("00".into()).encode(),
        SlcanLine::Ok => ok,
        SlcanLine::Frame(f) if !*open => {
            stats.reject(
                NAME,
                format!("frame {:#x} while the channel is closed", f.id.raw()),
            );
            SlcanLine::Error.encode()
        }
        SlcanLine::Frame(f) => {
            let mut reply = match f.id {
                CanId::Standard(_) => b"z\r".to_vec(),
                CanId::Extended(_) => b"Z\r".to_vec(),
            };
            if let Some(status) = gateway(sim, mapping, &f, stats) {
                reply.extend(SlcanLine::Frame(status).encode());
            }
            reply
        }
        SlcanLine::TxAck | SlcanLine::Error => {
            stats.reject(NAME, "adapter answer sent by the host");
            SlcanLine::Error.encode()
        }
    }
}

/// The gateway behind any CAN carrier: a command frame updates the request image and is
/// answered with the status frame; a status poll is answered with the status frame; frames
/// for other ids are not ours.
pub(crate) fn gateway(
    sim: &GripperSim,
    mapping: CanMapping,
    f: &CanFrame,
    stats: &ServerStats,
) -> Option<CanFrame> {
    if mapping.is_status_poll(f) {
        stats.accept();
        return Some(mapping.status_frame(&sim.read_status()));
    }
    match mapping.decode_command(f) {
        Ok(Some(r)) => {
            stats.accept();
            sim.write_request(r);
            Some(mapping.status_frame(&sim.read_status()))
        }
        Ok(None) => {
            log::debug!("gripper sim (CAN): frame {f:?} is not for us");
            None
        }
        Err(e) => {
            stats.reject("can", e.to_string());
            None
        }
    }
}
