//! The Robotiq 2F-85 emulator (issue 6, item 3): one [`model::GripperModel`] behind three
//! transports, each speaking the real wire protocol through the codecs of
//! `firmware_iface::gripper`: a Modbus RTU slave on a pseudo-terminal ([`modbus`]), the
//! URCap text server on loopback TCP ([`urcap`]) and the CAN mapping through an slcan
//! adapter on a pseudo-terminal ([`slcan`]) or a socketcand server on loopback TCP
//! ([`socketcand`]). Time comes from an injected [`Clock`]; with a
//! `ManualClock` shared with the driver, the driver's poll sleeps drive simulated time and
//! tests run faster than real time.
//!
//! Uses `serialport`'s `TTYPort::pair` for the pseudo-terminals (no unsafe code here) and
//! `log` for the reasons bytes are rejected. Servers run on their own threads and stop when
//! their [`SimServer`] handle is dropped.

pub mod modbus;
pub mod model;
pub mod slcan;
pub mod socketcand;
pub mod urcap;

use std::net::SocketAddr;
use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
use std::sync::{Arc, Mutex, MutexGuard, PoisonError};
use std::thread::JoinHandle;

use cell_types::Clock;
use firmware_iface::gripper::can::CanMapping;
use firmware_iface::gripper::registers::{RequestImage, StatusImage};
use thiserror::Error;

pub use model::{GripperModel, SimConfig};

/// Why an emulator transport could not start.
#[derive(Debug, Error)]
#[non_exhaustive]
pub enum SimError {
    /// The pseudo-terminal could not be created.
    #[error("cannot create a pseudo-terminal: {source}; check that /dev/ptmx is available")]
    Pty {
        /// The underlying error.
        #[source]
        source: serialport::Error,
    },
    /// A socket or thread could not be set up.
    #[error("{context}: {source}")]
    Io {
        /// What was being done.
        context: String,
        /// The underlying error.
        #[source]
        source: std::io::Error,
    },
}

/// The simulated gripper, shared by every transport serving it.
#[derive(Clone)]
pub struct GripperSim {
    model: Arc<Mutex<GripperModel>>,
    clock: Arc<dyn Clock>,
}

impl GripperSim {
    /// A gripper powered up now.
    pub fn new(clock: Arc<dyn Clock>, cfg: SimConfig) -> Self {
        Self {
            model: Arc::new(Mutex::new(GripperModel::new(cfg))),
            clock,
        }
    }

    fn lock(&self) -> MutexGuard<'_, GripperModel> {
        // A panic while holding the lock cannot leave the model half-updated in a way that
        // matters more than stopping the simulation would, so keep serving.
        self.model.lock().unwrap_or_else(PoisonError::into_inner)
    }

    /// Places an object of `width_m` between the fingers (`None`: nothing).
    pub fn set_object(&self, width_m: Option<f64>) {
        self.lock().set_object(width_m);
    }

    /// Places an obstacle that stops the fingers opening past `width_m` (gOBJ = 1).
    pub fn set_outer_limit(&self, width_m: Option<f64>) {
        self.lock().set_outer_limit(width_m);
    }

    /// Sets or releases the UR controller's emergency stop (URCap answers `?`).
    pub fn set_emergency_stop(&self, on: bool) {
        self.lock().set_emergency_stop(on);
    }

    /// True while the emergency stop is set.
    pub fn emergency_stop(&self) -> bool {
        self.lock().emergency_stop()
    }

    /// Raises a gripper fault (e.g. 0x0B).
    pub fn inject_fault(&self, code: u8) {
        self.lock().inject_fault(code);
    }

    /// The status image now, without counting as communication.
    pub fn observe(&self) -> StatusImage {
        let now = self.clock.now();
        self.lock().observe(now)
    }

    /// The fingers' true opening (m).
    pub fn width_m(&self) -> f64 {
        self.lock().width_m()
    }

    /// A host read the status (used by the transports).
    pub fn read_status(&self) -> StatusImage {
        let now = self.clock.now();
        self.lock().read_status(now)
    }

    /// A host wrote the request (used by the transports).
    pub fn write_request(&self, r: RequestImage) {
        let now = self.clock.now();
        self.lock().write_request(now, r);
    }

    /// The last request written.
    pub fn request(&self) -> RequestImage {
        self.lock().request()
    }

    /// Serves Modbus RTU (slave 9) on a new pseudo-terminal; connect to `handle.pty_path()`.
    pub fn spawn_modbus_rtu(&self) -> Result<SimServer, SimError> {
        modbus::spawn(self.clone(), firmware_iface::gripper::modbus_rtu::SLAVE_ID)
    }

    /// Serves the URCap text socket on `addr` (`127.0.0.1:0` picks a free port).
    pub fn spawn_urcap(&self, addr: SocketAddr) -> Result<SimServer, SimError> {
        urcap::spawn(self.clone(), addr)
    }

    /// Serves the CAN mapping through an emulated slcan adapter on a new pseudo-terminal.
    pub fn spawn_slcan(&self, mapping: CanMapping) -> Result<SimServer, SimError> {
        slcan::spawn(self.clone(), mapping)
    }

    /// Serves the CAN mapping on bus `bus` through a socketcand server on `addr`.
    pub fn spawn_socketcand(
        &self,
        addr: SocketAddr,
        bus: &str,
        mapping: CanMapping,
    ) -> Result<SimServer, SimError> {
        socketcand::spawn(self.clone(), addr, bus.to_owned(), mapping)
    }

    /// Convenience for the main job: a gripper and its URCap server on a free loopback port.
    pub fn spawn_urcap_on_loopback(
        clock: Arc<dyn Clock>,
        cfg: SimConfig,
    ) -> Result<(Self, SimServer), SimError> {
        let sim = Self::new(clock, cfg);
        let server = sim.spawn_urcap(SocketAddr::from(([127, 0, 0, 1], 0)))?;
        Ok((sim, server))
    }
}

/// Counts of what a server accepted and rejected.
#[derive(Debug, Default)]
pub struct ServerStats {
    accepted: AtomicU64,
    rejected: AtomicU64,
    last_reject: Mutex<String>,
}

impl ServerStats {
    fn accept(&self) {
        self.accepted.fetch_add(1, Ordering::Relaxed);
    }

    fn reject(&self, transport: &str, reason: impl Into<String>) {
        let reason = reason.into();
        log::warn!("gripper sim ({transport}): rejected input: {reason}");
        self.rejected.fetch_add(1, Ordering::Relaxed);
        *self
            .last_reject
            .lock()
            .unwrap_or_else(PoisonError::into_inner) = reason;
    }

    /// Well-formed requests served.
    pub fn accepted(&self) -> u64 {
        self.accepted.load(Ordering::Relaxed)
    }

    /// Inputs rejected (bad CRC, wrong slave, truncated, garbage).
    pub fn rejected(&self) -> u64 {
        self.rejected.load(Ordering::Relaxed)
    }

    /// The reason of the last rejection.
    pub fn last_reject(&self) -> String {
        self.last_reject
            .lock()
            .unwrap_or_else(PoisonError::into_inner)
            .clone()
    }
}

/// Where a server listens.
#[derive(Clone, Debug, PartialEq, Eq)]
pub enum Endpoint {
    /// The slave side of a pseudo-terminal.
    Pty(String),
    /// A TCP address.
    Tcp(SocketAddr),
}

/// A running emulator transport; dropping it stops the server threads.
pub struct SimServer {
    endpoint: Endpoint,
    stats: Arc<ServerStats>,
    stop: Arc<AtomicBool>,
    thread: Option<JoinHandle<()>>,
    // The emulator keeps the slave side open so that the master never reads EIO between
    // clients (a pty master sees a hang-up whenever no slave is open).
    _slave: Option<serialport::TTYPort>,
}

impl SimServer {
    /// The endpoint clients connect to.
    pub fn endpoint(&self) -> &Endpoint {
        &self.endpoint
    }

    /// The pseudo-terminal path, for serial transports.
    pub fn pty_path(&self) -> Option<&str> {
        match &self.endpoint {
            Endpoint::Pty(p) => Some(p),
            Endpoint::Tcp(_) => None,
        }
    }

    /// The TCP address, for socket transports.
    pub fn addr(&self) -> Option<SocketAddr> {
        match &self.endpoint {
            Endpoint::Tcp(a) => Some(*a),
            Endpoint::Pty(_) => None,
        }
    }

    /// What the server accepted and rejected so far.
    pub fn stats(&self) -> &ServerStats {
        &self.stats
    }

    /// True while the server thread runs (it ends only when stopped).
    pub fn is_running(&self) -> bool {
        self.thread.as_ref().is_some_and(|t| !t.is_finished())
    }
}

impl Drop for SimServer {
    fn drop(&mut self) {
        self.stop.store(true, Ordering::SeqCst);
        if let Some(t) = self.thread.take() {
            let _ = t.join();
        }
    }
}

/// Read timeout of the server loops: how quickly they notice a stop request, and the
/// silence after which a partial frame counts as truncated.
pub(crate) const POLL: std::time::Duration = std::time::Duration::from_millis(10);

fn pty_pair() -> Result<(serialport::TTYPort, serialport::TTYPort, String), SimError> {
    use serialport::SerialPort;
    let (mut master, slave) =
        serialport::TTYPort::pair().map_err(|source| SimError::Pty { source })?;
    master
        .set_timeout(POLL)
        .map_err(|source| SimError::Pty { source })?;
    let path = slave.name().ok_or_else(|| SimError::Io {
        context: "naming the pseudo-terminal".into(),
        source: std::io::Error::other("the slave side has no path"),
    })?;
    Ok((master, slave, path))
}

fn spawn_thread(name: &str, f: impl FnOnce() + Send + 'static) -> Result<JoinHandle<()>, SimError> {
    std::thread::Builder::new()
        .name(name.to_owned())
        .spawn(f)
        .map_err(|source| SimError::Io {
            context: format!("starting the {name} thread"),
            source,
        })
}
