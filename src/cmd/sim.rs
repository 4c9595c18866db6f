//! `equact sim`: serve the simulated UR controller (RTDE, dashboard, secondary interface)
//! on loopback until interrupted.

use std::net::IpAddr;
use std::sync::Arc;

use clap::Args;
use firmware_iface::dashboard::RobotMode;
use firmware_iface::ur::UrPorts;
use hil_sim::ur_controller::{start, Fault, UrSimConfig};

/// Arguments of `equact sim`.
#[derive(Args, Debug)]
pub struct SimArgs {
    /// Address to serve on.
    #[arg(long, default_value = "127.0.0.1")]
    pub host: IpAddr,
    /// RTDE port (0 picks a free one).
    #[arg(long, default_value_t = 30004)]
    pub rtde_port: u16,
    /// Dashboard server port.
    #[arg(long, default_value_t = 29999)]
    pub dashboard_port: u16,
    /// Secondary interface port (URScript programs).
    #[arg(long, default_value_t = 30002)]
    pub secondary_port: u16,
    /// Simulate an e-Series (5.x, 500 Hz) controller instead of a CB3 (3.x, 125 Hz).
    #[arg(long)]
    pub e_series: bool,
    /// Start powered on with brakes released (RUNNING) instead of POWER_OFF.
    #[arg(long)]
    pub powered: bool,
}

/// Runs `equact sim`.
pub fn run(args: SimArgs) -> anyhow::Result<()> {
    let mut config = UrSimConfig {
        bind: args.host,
        ports: UrPorts {
            rtde: args.rtde_port,
            dashboard: args.dashboard_port,
            secondary: args.secondary_port,
        },
        initial_mode: if args.powered {
            RobotMode::Running
        } else {
            RobotMode::PowerOff
        },
        ..UrSimConfig::default()
    };
    if args.e_series {
        config = config.e_series();
    }
    let rate = config.controller.max_frequency();
    let sim = start(config, Arc::new(cell_types::SystemClock::new()))?;
    let p = sim.ports();
    println!(
        "simulated UR5 ({} Hz) on {}: rtde {} dashboard {} secondary {}; Ctrl-C to stop",
        rate,
        sim.addr(),
        p.rtde,
        p.dashboard,
        p.secondary
    );
    println!(
        "fault injection: type pstop, estop, release-estop, drop, lose <cycles>, delay <ms> or stall <ms>"
    );
    for line in std::io::stdin().lines() {
        let line = line?;
        if line.trim().is_empty() {
            continue;
        }
        match line.parse::<Fault>() {
            Ok(f) => {
                sim.inject(f);
                println!("injected {f:?}");
            }
            Err(e) => println!("{e}"),
        }
    }
    // stdin closed (run in the background): keep serving until interrupted.
    loop {
        std::thread::park();
    }
}
