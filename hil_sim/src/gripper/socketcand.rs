//! The emulator's CAN side over socketcand (fact sheet "CAN", TCP 29536): a small server
//! speaking the socketcand ASCII protocol for one bus, with the gripper's gateway on it.
//! It greets with `< hi >`, answers `< open BUS >` and `< rawmode >` with `< ok >`, and
//! answers each `< send ... >` for the gripper with a `< frame ... >` carrying the status.
//! Garbage and bad messages are logged and counted (answered `< error ... >` where the
//! protocol has one); the connection stays up.

use std::io::{ErrorKind, Read, Write};
use std::net::{SocketAddr, TcpListener, TcpStream};
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::Arc;

use firmware_iface::gripper::can::CanMapping;
use firmware_iface::gripper::socketcand::{MessageSplitter, SocketcandMsg};

use super::slcan::gateway;
use super::{spawn_thread, Endpoint, GripperSim, ServerStats, SimError, SimServer, POLL};

const NAME: &str = "socketcand";

pub(crate) fn spawn(
    sim: GripperSim,
    addr: SocketAddr,
    bus: String,
    mapping: CanMapping,
) -> Result<SimServer, SimError> {
    let io = |context: &str| {
        let context = context.to_owned();
        move |source| SimError::Io { context, source }
    };
    let listener = TcpListener::bind(addr).map_err(io("binding the socketcand server"))?;
    let local = listener
        .local_addr()
        .map_err(io("reading the socketcand address"))?;
    listener
        .set_nonblocking(true)
        .map_err(io("configuring the socketcand listener"))?;
    let stats = Arc::new(ServerStats::default());
    let stop = Arc::new(AtomicBool::new(false));
    let thread = {
        let (stats, stop) = (stats.clone(), stop.clone());
        spawn_thread("gripper-sim-socketcand", move || {
            let mut clients = Vec::new();
            while !stop.load(Ordering::SeqCst) {
                match listener.accept() {
                    Ok((stream, _)) => {
                        let (sim, client_stats, stop, bus) =
                            (sim.clone(), stats.clone(), stop.clone(), bus.clone());
                        match spawn_thread("gripper-sim-socketcand-client", move || {
                            serve(stream, &sim, &bus, mapping, &client_stats, &stop)
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

#[derive(PartialEq)]
enum Mode {
    Greeted,
    Opened,
    Raw,
}

fn serve(
    mut stream: TcpStream,
    sim: &GripperSim,
    bus: &str,
    mapping: CanMapping,
    stats: &ServerStats,
    stop: &AtomicBool,
) {
    if stream.set_nonblocking(false).is_err()
        || stream.set_read_timeout(Some(POLL)).is_err()
        || stream.set_nodelay(true).is_err()
        || stream
            .write_all(SocketcandMsg::Hi.encode().as_bytes())
            .is_err()
    {
        stats.reject(NAME, "cannot set up a client socket");
        return;
    }
    let mut mode = Mode::Greeted;
    let mut splitter = MessageSplitter::new();
    let mut buf = [0u8; 512];
    let mut out = String::new();
    while !stop.load(Ordering::SeqCst) {
        let n = match stream.read(&mut buf) {
            Ok(0) => return,
            Ok(n) => n,
            Err(e)
                if matches!(
                    e.kind(),
                    ErrorKind::WouldBlock | ErrorKind::TimedOut | ErrorKind::Interrupted
                ) =>
            {
                continue
            }
            Err(_) => return,
        };
        let text = String::from_utf8_lossy(&buf[..n]).into_owned();
        out.clear();
        splitter.push(&text, |m| {
            let msg = match m {
                Err(junk) => {
                    stats.reject(NAME, format!("text outside < >: {junk:?}"));
                    return;
                }
                Ok(m) => match SocketcandMsg::parse(m) {
                    Ok(msg) => msg,
                    Err(e) => {
                        stats.reject(NAME, e.to_string());
                        out.push_str(&SocketcandMsg::Error("could not parse".into()).encode());
                        return;
                    }
                },
            };
            match (msg, &mode) {
                (SocketcandMsg::Open(b), Mode::Greeted) if b == bus => {
                    mode = Mode::Opened;
                    out.push_str(&SocketcandMsg::Ok.encode());
                }
                (SocketcandMsg::RawMode, Mode::Opened) => {
                    mode = Mode::Raw;
                    out.push_str(&SocketcandMsg::Ok.encode());
                }
                (SocketcandMsg::Send(f), Mode::Raw) => {
                    if let Some(status) = gateway(sim, mapping, &f, stats) {
                        let t = sim.clock.now();
                        out.push_str(&SocketcandMsg::Frame(status, t).encode());
                    }
                }
                (other, _) => {
                    stats.reject(NAME, format!("{other:?} not valid now"));
                    out.push_str(&SocketcandMsg::Error("unexpected".into()).encode());
                }
            }
        });
        if !out.is_empty() && stream.write_all(out.as_bytes()).is_err() {
            return;
        }
    }
}
