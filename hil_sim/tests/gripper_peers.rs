//! Independent peers against the emulator (issue 6 acceptance): `pymodbus` reads and writes
//! the registers over the pseudo-terminal and sees the fingers move; `python-can` (slcan
//! interface on the pseudo-terminal) exchanges frames and decodes them with the documented
//! mapping. These run in real time (SystemClock): the peers pace themselves by the wall clock.

use std::net::SocketAddr;
use std::path::PathBuf;
use std::process::Command;
use std::sync::Arc;

use cell_types::{Clock, SystemClock};
use firmware_iface::gripper::can::CanMapping;
use hil_sim::gripper::{GripperSim, SimConfig};
use serde_json::Value;

fn python() -> anyhow::Result<PathBuf> {
    let root = PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("..");
    let py = root.join(".venv/bin/python3");
    anyhow::ensure!(
        py.exists(),
        "{} is missing: run `make venv` at the workspace root to install the Python test peers",
        py.display()
    );
    Ok(py)
}

fn run_peer(script: &str, args: &[&str]) -> anyhow::Result<Value> {
    let script = PathBuf::from(env!("CARGO_MANIFEST_DIR"))
        .join("tests/peers")
        .join(script);
    let out = Command::new(python()?).arg(&script).args(args).output()?;
    anyhow::ensure!(
        out.status.success(),
        "{} failed: {}\n{}",
        script.display(),
        out.status,
        String::from_utf8_lossy(&out.stderr)
    );
    Ok(serde_json::from_slice(&out.stdout)?)
}

fn u(v: &Value, key: &str) -> u64 {
    v[key].as_u64().unwrap_or(u64::MAX)
}

#[test]
fn pymodbus_sees_the_fingers_move() -> anyhow::Result<()> {
    let clock: Arc<dyn Clock> = Arc::new(SystemClock::new());
    let sim = GripperSim::new(clock, SimConfig::default());
    sim.set_object(Some(0.040));
    let server = sim.spawn_modbus_rtu()?;
    let path = server.pty_path().ok_or_else(|| anyhow::anyhow!("no pty"))?;
    let out = run_peer("pymodbus_gripper.py", &[path])?;

    let act = out["activation_s"].as_f64().unwrap_or(0.0);
    assert!(act > 0.8, "activation seen after {act} s");
    assert!(
        out["activation_statuses"].to_string().contains('1'),
        "{out}"
    );
    let positions: Vec<u64> = out["close_positions"]
        .as_array()
        .map(|a| a.iter().filter_map(Value::as_u64).collect())
        .unwrap_or_default();
    assert!(positions.len() >= 3, "{positions:?}");
    assert!(positions.windows(2).all(|w| w[1] >= w[0]), "{positions:?}");
    assert!(positions.first() < positions.last(), "{positions:?}");
    let closed = &out["closed"];
    assert_eq!(u(closed, "gOBJ"), 2, "{closed}");
    assert_eq!(u(closed, "gSTA"), 3);
    // 40 mm with the default calibration: 230 - 40/85 * 227 = 123.2.
    assert!((122..=124).contains(&u(closed, "gPO")), "{closed}");
    assert!(
        u(closed, "gCU") > 15,
        "no current rise on contact: {closed}"
    );
    let opened = &out["opened"];
    assert_eq!(u(opened, "gOBJ"), 3);
    assert!(u(opened, "gPO") <= 4, "{opened}");
    assert_eq!(sim.request().position, 0);
    assert_eq!(
        server.stats().rejected(),
        0,
        "{}",
        server.stats().last_reject()
    );
    Ok(())
}

fn check_python_can(out: &Value, sim: &GripperSim) {
    assert_eq!(u(&out["after_clear"], "gSTA"), 0, "{out}");
    assert_eq!(u(&out["activated"], "gACT"), 1);
    let closed = &out["closed"];
    assert_eq!(u(closed, "gOBJ"), 2, "{closed}");
    assert!((122..=124).contains(&u(closed, "gPO")), "{closed}");
    assert_eq!(out["frame_ids"], serde_json::json!([0x189]));
    assert!(sim.request().go_to && sim.request().force == 200);
}

#[test]
fn python_can_exchanges_frames_over_slcan() -> anyhow::Result<()> {
    let clock: Arc<dyn Clock> = Arc::new(SystemClock::new());
    let sim = GripperSim::new(clock, SimConfig::default());
    sim.set_object(Some(0.040));
    let server = sim.spawn_slcan(CanMapping::for_node(9))?;
    let path = server.pty_path().ok_or_else(|| anyhow::anyhow!("no pty"))?;
    let out = run_peer("python_can_gripper.py", &["slcan", path])?;
    check_python_can(&out, &sim);
    assert_eq!(
        server.stats().rejected(),
        0,
        "{}",
        server.stats().last_reject()
    );
    Ok(())
}

#[test]
fn python_can_exchanges_frames_over_socketcand() -> anyhow::Result<()> {
    let clock: Arc<dyn Clock> = Arc::new(SystemClock::new());
    let sim = GripperSim::new(clock, SimConfig::default());
    sim.set_object(Some(0.040));
    let addr = SocketAddr::from(([127, 0, 0, 1], 0));
    let server = sim.spawn_socketcand(addr, "can0", CanMapping::for_node(9))?;
    let addr = server.addr().ok_or_else(|| anyhow::anyhow!("no address"))?;
    let port = addr.port().to_string();
    let out = run_peer("python_can_gripper.py", &["socketcand", "127.0.0.1", &port])?;
    check_python_can(&out, &sim);
    assert_eq!(
        server.stats().rejected(),
        0,
        "{}",
        server.stats().last_reject()
    );
    Ok(())
}
