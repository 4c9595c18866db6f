//! A simulated UR5 controller that speaks the real protocols on loopback: RTDE server
//! ([`rtde_server`]), dashboard server ([`dashboard_server`]), secondary interface script sink
//! ([`secondary`]), and the controller state stepped on an injected clock ([`core`]).
//! Implements issue 4 against the UR fact sheet (`ur5_and_protocols.md`).
//!
//! Threads: one control thread steps the controller every control period (8 ms on CB3, 2 ms
//! on e-Series) and hands each snapshot to every RTDE session's writer over a bounded channel
//! (`try_send`, so a slow client never slows the controller); one accept thread per port;
//! one reader thread per connection plus one writer thread per RTDE session. A bad packet
//! closes only its connection, with the reason recorded in [`UrSimHandle::log`] and printed
//! to stderr.

pub mod bench;
pub mod core;
pub mod dashboard_server;
pub mod rtde_server;
pub mod secondary;
pub mod variables;

use std::collections::HashMap;
use std::f64::consts::FRAC_PI_2;
use std::io;
use std::net::{IpAddr, Ipv4Addr, SocketAddr, TcpListener, TcpStream};
use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
use std::sync::mpsc::{SyncSender, TrySendError};
use std::sync::{Arc, Condvar, Mutex, MutexGuard};
use std::thread::JoinHandle;
use std::time::Duration;

use cell_types::{Clock, Flange, Joints, Tcp, Transform};
use firmware_iface::dashboard::RobotMode;
use firmware_iface::rtde::{ControllerVersion, TextMessage};
use firmware_iface::ur::UrPorts;
use thiserror::Error;

pub use self::core::{ControllerSnapshot, Core};

/// Why the simulated controller could not start.
#[derive(Debug, Error)]
#[non_exhaustive]
pub enum UrSimError {
    /// A port could not be bound.
    #[error("cannot serve {service} on {addr}: {source}; choose another port (0 picks a free one) or stop whatever listens there")]
    Bind {
        /// Which server.
        service: &'static str,
        /// Address tried.
        addr: SocketAddr,
        /// The OS error.
        source: io::Error,
    },
    /// A thread could not be started.
    #[error("cannot start the {what} thread: {source}")]
    Spawn {
        /// Which thread.
        what: &'static str,
        /// The OS error.
        source: io::Error,
    },
}

/// Configuration of the simulated controller.
#[derive(Clone, Debug)]
pub struct UrSimConfig {
    /// Address to listen on (loopback).
    pub bind: IpAddr,
    /// Ports; 0 picks a free one (tests).
    pub ports: UrPorts,
    /// Controller software version: major < 5 is a CB3 (125 Hz), 5+ an e-Series (500 Hz).
    pub controller: ControllerVersion,
    /// Joint positions at start (rad).
    pub initial_q: Joints,
    /// Robot mode at start (a real controller boots into POWER_OFF).
    pub initial_mode: RobotMode,
    /// Joint acceleration bound of the servo loop (rad/s²).
    pub max_accel: f64,
    /// The tool: flange to TCP.
    pub flange_from_tcp: Transform<Flange, Tcp>,
    /// Table top height in the base frame (m); links below it raise a protective stop.
    pub floor_z: Option<f64>,
    /// Lockstep: after each cycle, wait (one period of the clock's time; up to 100 ms of wall
    /// time while a client streams) for its input package before the next. With a
    /// [`cell_types::TickClock`] (the simulated cell) or a [`cell_types::ManualClock`]
    /// shared by the simulator and the driver, each cycle sees the driver's answer to the
    /// one before whatever the load, and a slow answer delays the clock with the cycle.
    pub lockstep: bool,
}

impl Default for UrSimConfig {
    fn default() -> Self {
        Self {
            bind: IpAddr::V4(Ipv4Addr::LOCALHOST),
            ports: UrPorts::default(),
            controller: ControllerVersion {
                major: 3,
                minor: 15,
                bugfix: 7,
                build: 106331,
            },
            initial_q: [0.0, -FRAC_PI_2, FRAC_PI_2, -FRAC_PI_2, -FRAC_PI_2, 0.0],
            initial_mode: RobotMode::PowerOff,
            max_accel: 15.0,
            flange_from_tcp: Transform::identity(),
            floor_z: Some(0.0),
            lockstep: false,
        }
    }
}

impl UrSimConfig {
    /// Free ports on 127.0.0.1, arm powered with brakes released (RUNNING): what most tests want.
    pub fn for_tests() -> Self {
        Self {
            ports: UrPorts {
                rtde: 0,
                dashboard: 0,
                secondary: 0,
            },
            initial_mode: RobotMode::Running,
            ..Self::default()
        }
    }

    /// Switches to an e-Series (5.x, 500 Hz) controller.
    pub fn e_series(mut self) -> Self {
        self.controller = ControllerVersion {
            major: 5,
            minor: 11,
            bugfix: 1,
            build: 108318,
        };
        self
    }

    /// Control period (s).
    pub fn period(&self) -> f64 {
        1.0 / self.controller.max_frequency()
    }
}

/// A fault to inject.
#[derive(Copy, Clone, Debug, PartialEq)]
#[non_exhaustive]
pub enum Fault {
    /// A protective stop, as a collision would raise.
    ProtectiveStop,
    /// A robot emergency stop (e-stop button).
    EmergencyStop,
    /// Releases the emergency stop (robot goes IDLE).
    ReleaseEmergencyStop,
    /// Closes every open connection (RTDE, dashboard, secondary).
    DropConnections,
    /// The next `n` control cycles send no data packages.
    LosePackets(u32),
    /// Every data package leaves this much later than it was produced (0 clears).
    Delay(Duration),
    /// The controller freezes (no stepping, no data) for this long.
    Stall(Duration),
}

/// How far the control thread may fall behind its cadence before it stops catching up.
const CATCH_UP_LIMIT: Duration = Duration::from_millis(250);

/// A fault command line (`equact sim` reads them on stdin) that could not be parsed.
#[derive(Debug, Error, Clone, PartialEq, Eq)]
#[error("cannot parse fault {line:?}: expected one of pstop, estop, release-estop, drop, lose <cycles>, delay <ms>, stall <ms>")]
pub struct FaultParseError {
    /// The line given.
    pub line: String,
}

impl std::str::FromStr for Fault {
    type Err = FaultParseError;

    fn from_str(line: &str) -> Result<Self, Self::Err> {
        let err = || FaultParseError {
            line: line.to_string(),
        };
        let mut words = line.split_whitespace();
        let cmd = words.next().ok_or_else(err)?;
        let mut number = || -> Result<u64, FaultParseError> {
            words.next().and_then(|w| w.parse().ok()).ok_or_else(err)
        };
        let fault = match cmd {
            "pstop" => Fault::ProtectiveStop,
            "estop" => Fault::EmergencyStop,
            "release-estop" => Fault::ReleaseEmergencyStop,
            "drop" => Fault::DropConnections,
            "lose" => Fault::LosePackets(u32::try_from(number()?).map_err(|_| err())?),
            "delay" => Fault::Delay(Duration::from_millis(number()?)),
            "stall" => Fault::Stall(Duration::from_millis(number()?)),
            _ => return Err(err()),
        };
        if words.next().is_some() {
            return Err(err());
        }
        Ok(fault)
    }
}

pub(crate) enum Outgoing {
    Data(Arc<ControllerSnapshot>, Duration),
    Text(TextMessage),
}

struct Subscriber {
    tx: SyncSender<Outgoing>,
}

#[derive(Default)]
struct FaultState {
    lose: u32,
    delay: Duration,
    stall_until: Option<Duration>,
}

/// State shared by the simulator's threads.
pub(crate) struct Shared {
    pub(crate) config: UrSimConfig,
    pub(crate) clock: Arc<dyn Clock>,
    core: Mutex<Core>,
    stop: AtomicBool,
    subscribers: Mutex<Vec<Subscriber>>,
    pub(crate) input_owners: Mutex<HashMap<String, u64>>,
    connections: Mutex<HashMap<u64, TcpStream>>,
    next_conn: AtomicU64,
    log: Mutex<Vec<String>>,
    faults: Mutex<FaultState>,
    inputs_seen: Mutex<u64>,
    input_arrived: Condvar,
}

fn lock<T>(m: &Mutex<T>) -> MutexGuard<'_, T> {
    // A panicking session thread must not take the whole simulator down with it.
    m.lock().unwrap_or_else(|e| e.into_inner())
}

impl Shared {
    pub(crate) fn core(&self) -> MutexGuard<'_, Core> {
        lock(&self.core)
    }

    pub(crate) fn stopping(&self) -> bool {
        self.stop.load(Ordering::SeqCst)
    }

    pub(crate) fn log(&self, line: String) {
        eprintln!("[hil_sim ur] {line}");
        lock(&self.log).push(line);
    }

    pub(crate) fn subscribe(&self, tx: SyncSender<Outgoing>) {
        lock(&self.subscribers).push(Subscriber { tx });
    }

    /// Called by RTDE sessions for every input data package (lockstep pacing).
    pub(crate) fn input_received(&self) {
        *lock(&self.inputs_seen) += 1;
        self.input_arrived.notify_all();
    }

    pub(crate) fn delay(&self) -> Duration {
        lock(&self.faults).delay
    }

    /// Sends a text message to every RTDE session.
    pub(crate) fn broadcast_text(&self, message: String, level: u8) {
        self.log(format!("text message: {message}"));
        let t = TextMessage {
            message,
            source: "hil_sim".into(),
            level,
        };
        for s in lock(&self.subscribers).iter() {
            let _ = s.tx.try_send(Outgoing::Text(t.clone()));
        }
    }

    /// Registers a connection so that a `DropConnections` fault can close it.
    pub(crate) fn register(&self, stream: &TcpStream) -> u64 {
        let id = self.next_conn.fetch_add(1, Ordering::SeqCst);
        if let Ok(s) = stream.try_clone() {
            lock(&self.connections).insert(id, s);
        }
        id
    }

    /// Forgets a closed connection and releases the inputs it owned.
    pub(crate) fn unregister(&self, id: u64) {
        lock(&self.connections).remove(&id);
        self.release_inputs(id);
    }

    /// Releases the RTDE inputs a connection owned, so that a client reconnecting at once
    /// can claim them again.
    pub(crate) fn release_inputs(&self, id: u64) {
        lock(&self.input_owners).retain(|_, owner| *owner != id);
    }

    fn drop_connections(&self) {
        for (_, s) in lock(&self.connections).drain() {
            let _ = s.shutdown(std::net::Shutdown::Both);
        }
    }

    fn control_loop(&self) {
        let period = Duration::from_secs_f64(self.config.period());
        let mut next = self.clock.now();
        // The client let a streaming wait run out: wait only a period for it until it
        // answers again, so that a client that stopped answering meets the watchdog soon.
        let mut client_silent = false;
        while !self.stopping() {
            next += period;
            // The controller keeps the simulated cell's time: on a `TickClock` this cycle's
            // start is what moves it.
            self.clock.advance_to(next);
            let now = self.clock.now();
            // Started after the next cycle was due: part of a catch-up burst.
            let late = now > next + period;
            if now > next + CATCH_UP_LIMIT {
                // Starved of CPU for long: resume the cadence from now. Shorter delays are
                // caught up (a short burst of packages), so that the average rate a client
                // measures stays the controller's rate on a loaded machine.
                next = now;
            }
            {
                let mut f = lock(&self.faults);
                if let Some(until) = f.stall_until {
                    if now < until {
                        continue;
                    }
                    f.stall_until = None;
                }
            }
            let (snap, events, seen_before) = {
                let mut core = self.core();
                if late {
                    core.step_late();
                } else {
                    core.step();
                }
                // Inputs are counted under the core's lock: those after this count came
                // after the cycle (the answer a lockstep cycle waits for).
                let seen = *lock(&self.inputs_seen);
                (Arc::new(core.snapshot()), core.take_events(), seen)
            };
            for e in events {
                self.log(e);
            }
            {
                let mut f = lock(&self.faults);
                if f.lose > 0 {
                    f.lose -= 1;
                    continue;
                }
            }
            lock(&self.subscribers).retain(|s| {
                !matches!(
                    s.tx.try_send(Outgoing::Data(snap.clone(), now)),
                    Err(TrySendError::Disconnected(_))
                )
            });
            if self.config.lockstep {
                // Real-time wait on purpose: without a streaming client the simulator keeps
                // its clock's pace (one period of its time) instead of spinning its
                // simulated clock away. While a servo program plays, every cycle waits for
                // the client's answer (the driver answers from the program's first cycle
                // on) with more patience, so that a client starved of CPU for a few periods
                // on a loaded machine still answers every cycle and the arm moves the same
                // whatever the threads' timing. Outside a program nothing waits on inputs:
                // one then (the driver's hold word before a motion) must not stall the clock
                // for the patience.
                let streaming =
                    snap.program_state == firmware_iface::dashboard::ProgramState::Playing;
                let patience = if streaming && !client_silent {
                    LOCKSTEP_STREAMING_PATIENCE.max(period)
                } else {
                    period.div_f64(self.clock.speed())
                };
                let g = lock(&self.inputs_seen);
                let (g, _) = self
                    .input_arrived
                    .wait_timeout_while(g, patience, |n| *n == seen_before)
                    .unwrap_or_else(|e| e.into_inner());
                client_silent = streaming && *g == seen_before;
            }
        }
    }
}

/// Lockstep: the longest real-time wait for a streaming client's input before the next cycle.
const LOCKSTEP_STREAMING_PATIENCE: Duration = Duration::from_millis(100);

/// A running simulated controller; dropping it stops every thread and closes every socket.
pub struct UrSimHandle {
    shared: Arc<Shared>,
    ports: UrPorts,
    threads: Vec<JoinHandle<()>>,
}

/// Injects faults into a running simulated controller; clones share the controller.
#[derive(Clone)]
pub struct FaultInjector {
    shared: Arc<Shared>,
}

impl FaultInjector {
    /// Injects a fault.
    pub fn inject(&self, fault: Fault) {
        self.shared.log(format!("fault injected: {fault:?}"));
        match fault {
            Fault::ProtectiveStop => self.shared.core().protective_stop("injected fault"),
            Fault::EmergencyStop => self.shared.core().emergency_stop(),
            Fault::ReleaseEmergencyStop => self.shared.core().release_emergency_stop(),
            Fault::DropConnections => self.shared.drop_connections(),
            Fault::LosePackets(n) => lock(&self.shared.faults).lose += n,
            Fault::Delay(d) => lock(&self.shared.faults).delay = d,
            Fault::Stall(d) => {
                lock(&self.shared.faults).stall_until = Some(self.shared.clock.now() + d)
            }
        }
    }
}

/// Starts the simulated controller on `clock` (use [`cell_types::SystemClock`] whenever a
/// client runs in real time).
pub fn start(config: UrSimConfig, clock: Arc<dyn Clock>) -> Result<UrSimHandle, UrSimError> {
    let bind = |service, port| {
        let addr = SocketAddr::new(config.bind, port);
        let l = TcpListener::bind(addr).map_err(|source| UrSimError::Bind {
            service,
            addr,
            source,
        })?;
        let port = l.local_addr().map_err(|source| UrSimError::Bind {
            service,
            addr,
            source,
        })?;
        l.set_nonblocking(true).map_err(|source| UrSimError::Bind {
            service,
            addr,
            source,
        })?;
        Ok::<_, UrSimError>((l, port.port()))
    };
    let (rtde, rtde_port) = bind("RTDE", config.ports.rtde)?;
    let (dash, dash_port) = bind("dashboard", config.ports.dashboard)?;
    let (sec, sec_port) = bind("secondary interface", config.ports.secondary)?;
    let model = core::ArmModel {
        period: config.period(),
        max_accel: config.max_accel,
        flange_from_tcp: config.flange_from_tcp,
        floor_z: config.floor_z,
    };
    let core = Core::new(model, config.initial_q, config.initial_mode);
    let shared = Arc::new(Shared {
        config,
        clock,
        core: Mutex::new(core),
        stop: AtomicBool::new(false),
        subscribers: Mutex::new(Vec::new()),
        input_owners: Mutex::new(HashMap::new()),
        connections: Mutex::new(HashMap::new()),
        next_conn: AtomicU64::new(1),
        log: Mutex::new(Vec::new()),
        faults: Mutex::new(FaultState::default()),
        inputs_seen: Mutex::new(0),
        input_arrived: Condvar::new(),
    });
    let mut handle = UrSimHandle {
        shared: shared.clone(),
        ports: UrPorts {
            rtde: rtde_port,
            dashboard: dash_port,
            secondary: sec_port,
        },
        threads: Vec::new(),
    };
    let spawn = |what: &'static str, f: Box<dyn FnOnce() + Send>| {
        std::thread::Builder::new()
            .name(format!("ur-sim-{what}"))
            .spawn(f)
            .map_err(|source| UrSimError::Spawn { what, source })
    };
    let s = shared.clone();
    handle.threads.push(spawn(
        "control",
        Box::new(move || {
            s.control_loop();
            // Whatever still waits on a clock this loop kept must not wait for it.
            s.clock.keeper_stopped();
        }),
    )?);
    let s = shared.clone();
    handle.threads.push(spawn(
        "rtde-accept",
        Box::new(move || accept_loop(&s, rtde, "RTDE", rtde_server::serve)),
    )?);
    let s = shared.clone();
    handle.threads.push(spawn(
        "dashboard-accept",
        Box::new(move || accept_loop(&s, dash, "dashboard", dashboard_server::serve)),
    )?);
    let s = shared;
    handle.threads.push(spawn(
        "secondary-accept",
        Box::new(move || accept_loop(&s, sec, "secondary", secondary::serve)),
    )?);
    Ok(handle)
}

fn accept_loop(
    shared: &Arc<Shared>,
    listener: TcpListener,
    service: &'static str,
    serve: fn(Arc<Shared>, TcpStream, u64),
) {
    while !shared.stopping() {
        match listener.accept() {
            Ok((stream, peer)) => {
                let _ = stream.set_nonblocking(false);
                let _ = stream.set_nodelay(true);
                let id = shared.register(&stream);
                shared.log(format!("{service} connection {id} from {peer}"));
                let s = shared.clone();
                let spawned = std::thread::Builder::new()
                    .name(format!("ur-sim-{service}-{id}"))
                    .spawn(move || {
                        serve(s.clone(), stream, id);
                        s.unregister(id);
                    });
                if let Err(e) = spawned {
                    shared.log(format!(
                        "{service} connection {id} refused: cannot spawn: {e}"
                    ));
                    shared.unregister(id);
                }
            }
            Err(e) if e.kind() == io::ErrorKind::WouldBlock => {
                std::thread::sleep(Duration::from_millis(5));
            }
            Err(e) => {
                shared.log(format!("{service} accept failed: {e}"));
                std::thread::sleep(Duration::from_millis(50));
            }
        }
    }
}

impl UrSimHandle {
    /// The ports actually served.
    pub fn ports(&self) -> UrPorts {
        self.ports
    }

    /// The address served.
    pub fn addr(&self) -> IpAddr {
        self.shared.config.bind
    }

    /// The controller's current state.
    pub fn snapshot(&self) -> ControllerSnapshot {
        self.shared.core().snapshot()
    }

    /// Runs `f` on the controller state (tests: set modes, read the program state).
    pub fn with_core<R>(&self, f: impl FnOnce(&mut Core) -> R) -> R {
        f(&mut self.shared.core())
    }

    /// Injects a fault.
    pub fn inject(&self, fault: Fault) {
        self.injector().inject(fault);
    }

    /// A handle that injects faults from another thread (e.g. in the middle of a motion
    /// that the owner of this handle is waiting on).
    pub fn injector(&self) -> FaultInjector {
        FaultInjector {
            shared: self.shared.clone(),
        }
    }

    /// Everything the simulator logged: connections, closed connections with their reason,
    /// mode changes, programs, faults.
    pub fn log(&self) -> Vec<String> {
        lock(&self.shared.log).clone()
    }

    /// Stops the simulator and waits for its threads.
    pub fn shutdown(mut self) {
        self.stop_all();
    }

    fn stop_all(&mut self) {
        self.shared.stop.store(true, Ordering::SeqCst);
        self.shared.drop_connections();
        for t in self.threads.drain(..) {
            let _ = t.join();
        }
    }
}

impl Drop for UrSimHandle {
    fn drop(&mut self) {
        self.stop_all();
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn fault_lines_parse() {
        assert_eq!("pstop".parse(), Ok(Fault::ProtectiveStop));
        assert_eq!(" lose 12 ".parse(), Ok(Fault::LosePackets(12)));
        assert_eq!(
            "stall 250".parse(),
            Ok(Fault::Stall(Duration::from_millis(250)))
        );
        assert!("stall".parse::<Fault>().is_err());
        assert!("stall -1".parse::<Fault>().is_err());
        assert!("pstop now".parse::<Fault>().is_err());
        assert!("explode".parse::<Fault>().is_err());
    }
}
