//! The emulator's Modbus RTU slave (fact sheet "Modbus RTU") on a pseudo-terminal: FC04
//! reads of the status image at 0x07D0, FC16 writes of the request image at 0x03E8, FC23
//! both. Like the gripper it sends no exception responses: requests for other slaves or
//! registers, bad CRCs and truncated frames are dropped, logged and counted.

use std::io::{ErrorKind, Read, Write};
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::Arc;

use firmware_iface::gripper::modbus_rtu::{Direction, FrameReader, Request, Response, Scan};
use firmware_iface::gripper::registers::{
    RequestImage, IMAGE_REGISTERS, REQUEST_REGISTER, STATUS_REGISTER,
};

use super::{pty_pair, spawn_thread, Endpoint, GripperSim, ServerStats, SimError, SimServer};

const NAME: &str = "modbus-rtu";

pub(crate) fn spawn(sim: GripperSim, slave: u8) -> Result<SimServer, SimError> {
    let (master, slave_port, path) = pty_pair()?;
    let stats = Arc::new(ServerStats::default());
    let stop = Arc::new(AtomicBool::new(false));
    let thread = {
        let (stats, stop) = (stats.clone(), stop.clone());
        spawn_thread("gripper-sim-modbus", move || {
            serve(master, sim, slave, &stats, &stop)
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
    sim: GripperSim,
    slave: u8,
    stats: &ServerStats,
    stop: &AtomicBool,
) {
    let mut reader = FrameReader::new(Direction::Requests);
    let mut buf = [0u8; 512];
    while !stop.load(Ordering::SeqCst) {
        let n = match port.read(&mut buf) {
            Ok(n) => n,
            Err(e)
                if matches!(
                    e.kind(),
                    ErrorKind::TimedOut | ErrorKind::WouldBlock | ErrorKind::Interrupted
                ) =>
            {
                0
            }
            Err(e) => {
                stats.reject(NAME, format!("read error {e}"));
                std::thread::sleep(super::POLL);
                0
            }
        };
        if n == 0 {
            // Silence longer than a frame gap ends any frame in progress.
            if let Some(Scan::Dropped { bytes, reason }) = reader.silence() {
                stats.reject(NAME, format!("{bytes} bytes: {reason}"));
            }
            continue;
        }
        reader.push(&buf[..n]);
        while let Some(scan) = reader.next_scan() {
            match scan {
                Scan::Dropped { bytes, reason } => {
                    stats.reject(NAME, format!("{bytes} bytes: {reason}"))
                }
                Scan::Frame(f) => match Request::decode(&f) {
                    Err(e) => stats.reject(NAME, e.to_string()),
                    Ok((id, _)) if id != slave => {
                        stats.reject(NAME, format!("frame for slave {id}, we are {slave}"))
                    }
                    Ok((_, req)) => match answer(&sim, &req) {
                        Err(reason) => stats.reject(NAME, reason),
                        Ok(resp) => match resp.encode(slave) {
                            Ok(bytes) => {
                                stats.accept();
                                if let Err(e) = port.write_all(&bytes) {
                                    stats.reject(NAME, format!("write error {e}"));
                                }
                            }
                            Err(e) => stats.reject(NAME, e.to_string()),
                        },
                    },
                },
            }
        }
    }
}

/// Offset of `[start, start + count)` within a 3-register image at `base`.
fn window(start: u16, count: usize, base: u16) -> Result<usize, String> {
    let off = usize::from(start.wrapping_sub(base));
    if start >= base && count >= 1 && off + count <= usize::from(IMAGE_REGISTERS) {
        Ok(off)
    } else {
        Err(format!(
            "registers {start:#06x}+{count} are outside {base:#06x}..{:#06x}",
            base + IMAGE_REGISTERS
        ))
    }
}

fn write(sim: &GripperSim, start: u16, values: &[u16]) -> Result<(), String> {
    let off = window(start, values.len(), REQUEST_REGISTER)?;
    let mut regs = sim.request().to_registers();
    regs[off..off + values.len()].copy_from_slice(values);
    sim.write_request(RequestImage::from_registers(regs));
    Ok(())
}

fn read(sim: &GripperSim, start: u16, count: u16) -> Result<Vec<u16>, String> {
    let off = window(start, usize::from(count), STATUS_REGISTER)?;
    let regs = sim.read_status().to_registers();
    Ok(regs[off..off + usize::from(count)].to_vec())
}

fn answer(sim: &GripperSim, req: &Request) -> Result<Response, String> {
    match req {
        Request::ReadInput { start, count } => Ok(Response::ReadInput {
            values: read(sim, *start, *count)?,
        }),
        Request::WriteMultiple { start, values } => {
            write(sim, *start, values)?;
            Ok(Response::WriteMultiple {
                start: *start,
                count: values.len() as u16,
            })
        }
        Request::ReadWrite {
            read_start,
            read_count,
            write_start,
            values,
        } => {
            // Check the read window before writing, so a bad request changes nothing.
            window(*read_start, usize::from(*read_count), STATUS_REGISTER)?;
            write(sim, *write_start, values)?;
            Ok(Response::ReadWrite {
                values: read(sim, *read_start, *read_count)?,
            })
        }
    }
}
