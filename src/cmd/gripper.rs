//! `equact gripper`: serve the Robotiq 2F-85 emulator on one of its transports (for demos
//! and manual tests with real clients), or measure the status-read latency of each
//! transport against the in-process model (issue 6).

use std::net::SocketAddr;
use std::sync::Arc;
use std::time::{Duration, Instant};

use anyhow::Context;
use cell_types::{Clock, SystemClock};
use clap::{Args, Subcommand, ValueEnum};
use firmware_iface::gripper::can::CanMapping;
use firmware_iface::gripper::modbus_rtu::SLAVE_ID;
use firmware_iface::gripper::transport::{
    ModbusRtuTransport, RegisterTransport, SlcanTransport, SocketcandTransport, UrcapTransport,
};
use hil_sim::gripper::{GripperSim, SimConfig, SimServer};

/// Arguments of `equact gripper`.
#[derive(Args, Debug)]
pub struct GripperArgs {
    /// What to do.
    #[command(subcommand)]
    pub action: GripperAction,
}

/// The `equact gripper` actions.
#[derive(Subcommand, Debug)]
pub enum GripperAction {
    /// Serve the emulator and print where to connect.
    Sim {
        /// Which wire protocol to serve.
        #[arg(long, value_enum, default_value = "urcap")]
        transport: Transport,
        /// TCP address for urcap/socketcand (port 0 picks a free one).
        #[arg(long, default_value = "127.0.0.1:0")]
        addr: SocketAddr,
        /// Width of an object between the fingers, in millimetres.
        #[arg(long)]
        object_mm: Option<f64>,
        /// Stop after this many seconds (default: run until killed).
        #[arg(long)]
        seconds: Option<f64>,
    },
    /// Measure status reads per transport; prints JSON.
    Bench {
        /// Timed reads per transport.
        #[arg(long, default_value_t = 300)]
        reads: usize,
    },
}

/// A gripper transport.
#[derive(Copy, Clone, Debug, PartialEq, Eq, ValueEnum)]
pub enum Transport {
    /// Modbus RTU slave on a pseudo-terminal.
    Modbus,
    /// URCap text socket on TCP.
    Urcap,
    /// CAN through an slcan adapter on a pseudo-terminal.
    Slcan,
    /// CAN through a socketcand server on TCP.
    Socketcand,
}

/// Runs `equact gripper`.
pub fn run(args: GripperArgs) -> anyhow::Result<()> {
    match args.action {
        GripperAction::Sim {
            transport,
            addr,
            object_mm,
            seconds,
        } => serve(transport, addr, object_mm, seconds),
        GripperAction::Bench { reads } => bench(reads),
    }
}

fn spawn(sim: &GripperSim, transport: Transport, addr: SocketAddr) -> anyhow::Result<SimServer> {
    let mapping = CanMapping::default();
    Ok(match transport {
        Transport::Modbus => sim.spawn_modbus_rtu()?,
        Transport::Urcap => sim.spawn_urcap(addr)?,
        Transport::Slcan => sim.spawn_slcan(mapping)?,
        Transport::Socketcand => sim.spawn_socketcand(addr, "can0", mapping)?,
    })
}

fn serve(
    transport: Transport,
    addr: SocketAddr,
    object_mm: Option<f64>,
    seconds: Option<f64>,
) -> anyhow::Result<()> {
    let clock: Arc<dyn Clock> = Arc::new(SystemClock::new());
    let sim = GripperSim::new(clock, SimConfig::default());
    sim.set_object(object_mm.map(|mm| mm / 1000.0));
    let server = spawn(&sim, transport, addr)?;
    println!(
        "{}",
        serde_json::json!({
            "transport": format!("{transport:?}").to_lowercase(),
            "endpoint": format!("{:?}", server.endpoint()),
        })
    );
    let limit = seconds.map(Duration::from_secs_f64);
    let start = Instant::now();
    while limit.is_none_or(|l| start.elapsed() < l) {
        std::thread::sleep(Duration::from_millis(100));
    }
    println!(
        "{}",
        serde_json::json!({ "accepted": server.stats().accepted(), "rejected": server.stats().rejected() })
    );
    Ok(())
}

fn timed(reads: usize, mut f: impl FnMut() -> anyhow::Result<()>) -> anyhow::Result<Vec<f64>> {
    for _ in 0..reads.min(20) {
        f()?;
    }
    let mut us = Vec::with_capacity(reads);
    for _ in 0..reads {
        let t = Instant::now();
        f()?;
        us.push(t.elapsed().as_secs_f64() * 1e6);
    }
    us.sort_by(f64::total_cmp);
    Ok(us)
}

fn summary(name: &str, us: &[f64], baseline_mean: f64) -> serde_json::Value {
    let mean = us.iter().sum::<f64>() / us.len().max(1) as f64;
    let pct = |p: f64| {
        us.get(((us.len() as f64 - 1.0) * p).round() as usize)
            .copied()
            .unwrap_or(f64::NAN)
    };
    serde_json::json!({
        "transport": name,
        "reads": us.len(),
        "mean_us": mean,
        "p50_us": pct(0.5),
        "p99_us": pct(0.99),
        "ratio_to_in_process": mean / baseline_mean,
    })
}

fn bench(reads: usize) -> anyhow::Result<()> {
    anyhow::ensure!(reads > 0, "--reads must be at least 1");
    let clock: Arc<dyn Clock> = Arc::new(SystemClock::new());
    let sim = GripperSim::new(clock, SimConfig::default());
    let baseline = timed(reads, || {
        std::hint::black_box(sim.read_status());
        Ok(())
    })?;
    let base_mean = baseline.iter().sum::<f64>() / baseline.len() as f64;
    let mut rows = vec![summary("in-process", &baseline, base_mean)];
    let local = SocketAddr::from(([127, 0, 0, 1], 0));
    for transport in [
        Transport::Modbus,
        Transport::Urcap,
        Transport::Slcan,
        Transport::Socketcand,
    ] {
        let server = spawn(&sim, transport, local)?;
        let pty = || server.pty_path().context("no pty");
        let tcp = || server.addr().context("no address");
        let mut t: Box<dyn RegisterTransport> = match transport {
            Transport::Modbus => Box::new(ModbusRtuTransport::open(pty()?, SLAVE_ID)?),
            Transport::Urcap => {
                Box::new(UrcapTransport::connect(tcp()?, Duration::from_millis(500))?)
            }
            Transport::Slcan => Box::new(SlcanTransport::open(pty()?, CanMapping::default())?),
            Transport::Socketcand => Box::new(SocketcandTransport::connect(
                tcp()?,
                "can0",
                CanMapping::default(),
            )?),
        };
        let us = timed(reads, || {
            t.read_status()?;
            Ok(())
        })?;
        rows.push(summary(t.name(), &us, base_mean));
    }
    println!(
        "{}",
        serde_json::to_string_pretty(
            &serde_json::json!({ "bench": "gripper status read", "results": rows })
        )?
    );
    Ok(())
}
