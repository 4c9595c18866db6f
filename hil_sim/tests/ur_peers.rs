//! Independent peers against the simulated controller: the `ur-rtde` Python package's
//! receive interface, and a raw Python RTDE client written from the protocol description.
//! Both need the workspace's Python environment (`make venv`).

#![allow(clippy::unwrap_used, clippy::expect_used)] // test helpers may panic

use std::io::{BufRead, BufReader};
use std::net::{IpAddr, Ipv4Addr};
use std::path::PathBuf;
use std::process::{Command, Stdio};
use std::sync::{Arc, Mutex};

/// The peers are CPU-heavy Python processes: run one test at a time on a small CI machine.
static ONE_AT_A_TIME: Mutex<()> = Mutex::new(());

use cell_types::{SystemClock, Trajectory, TrajectorySample};
use firmware_iface::arm::{Arm, ExecutionOutcome};
use firmware_iface::ur::{UrArm, UrConfig, UrPorts};
use hil_sim::ur_controller::{start, UrSimConfig};

fn python() -> PathBuf {
    let p = PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../.venv/bin/python3");
    assert!(
        p.exists(),
        "{} is missing: run `make venv` at the workspace root to install the Python test peers",
        p.display()
    );
    p
}

fn peer(name: &str) -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR"))
        .join("tests/peers")
        .join(name)
}

/// RTDEReceiveInterface always dials port 30004, so each run gets its own loopback address.
fn private_loopback() -> IpAddr {
    let pid = std::process::id();
    IpAddr::V4(Ipv4Addr::new(127, 77, (pid >> 8) as u8, (pid as u8).max(2)))
}

#[test]
fn ur_rtde_receive_interface_reads_the_emulator_and_sees_the_arm_move() {
    let _one = ONE_AT_A_TIME.lock().unwrap_or_else(|e| e.into_inner());
    let host = private_loopback();
    let h = start(
        UrSimConfig {
            bind: host,
            ports: UrPorts {
                rtde: 30004,
                dashboard: 0,
                secondary: 0,
            },
            ..UrSimConfig::for_tests()
        },
        Arc::new(SystemClock::new()),
    )
    .unwrap();
    let mut child = Command::new(python())
        .arg(peer("ur_rtde_receive.py"))
        .arg(host.to_string())
        .arg("2.5")
        .stdout(Stdio::piped())
        .spawn()
        .unwrap();
    let mut out = BufReader::new(child.stdout.take().unwrap());
    let mut line = String::new();
    out.read_line(&mut line).unwrap();
    let first: serde_json::Value = serde_json::from_str(&line)
        .unwrap_or_else(|e| panic!("peer said {line:?} ({e}); sim log:\n{}", h.log().join("\n")));
    let first = &first["ready"];
    let snap = h.snapshot();
    for j in 0..6 {
        let q = first["actual_q"][j].as_f64().unwrap();
        assert!(
            (q - snap.actual_q[j]).abs() < 1e-9,
            "joint {j}: {q} vs {}",
            snap.actual_q[j]
        );
        let p = first["actual_tcp_pose"][j].as_f64().unwrap();
        assert!((p - snap.actual_tcp_pose[j]).abs() < 1e-9);
    }
    assert_eq!(first["robot_mode"], 7);
    assert_eq!(first["safety_mode"], 1);

    // Move the arm with our driver while the peer watches.
    let mut arm = UrArm::connect(
        UrConfig {
            host,
            ports: h.ports(),
            lost_cycles: 12,
            ..UrConfig::default()
        },
        Arc::new(SystemClock::new()),
    )
    .unwrap();
    let q0 = arm.state().unwrap().joints.position;
    let samples = (0..=125)
        .map(|i| {
            let s = i as f64 / 125.0;
            let mut q = q0;
            q[0] += 0.3 * (3.0 * s * s - 2.0 * s * s * s);
            TrajectorySample {
                t: i as f64 * 0.008,
                position: q,
                ..Default::default()
            }
        })
        .collect();
    let outcome = arm
        .execute(&Trajectory::new(0.008, samples).unwrap())
        .unwrap();
    assert!(
        matches!(outcome, ExecutionOutcome::Completed { .. }),
        "{outcome:?}"
    );

    line.clear();
    out.read_line(&mut line).unwrap();
    let last: serde_json::Value = serde_json::from_str(&line).unwrap();
    assert!(child.wait().unwrap().success());
    assert!(last["moved"].as_f64().unwrap() > 0.25, "{last}");
    let q_end = last["last"]["actual_q"][0].as_f64().unwrap();
    assert!((q_end - (q0[0] + 0.3)).abs() < 0.01, "{q_end}");
}

#[test]
fn raw_python_client_negotiates_v1_and_v2_and_reads_at_125_hz() {
    // The issue asks for 10 s; both versions run side by side so the suite pays 10 s once.
    const SECONDS: &str = "10";
    let _one = ONE_AT_A_TIME.lock().unwrap_or_else(|e| e.into_inner());
    let h = start(UrSimConfig::for_tests(), Arc::new(SystemClock::new())).unwrap();
    let port = h.ports().rtde.to_string();
    let children: Vec<_> = ["1", "2"]
        .iter()
        .map(|v| {
            Command::new(python())
                .arg(peer("rtde_raw_client.py"))
                .args(["127.0.0.1", &port, v, SECONDS])
                .stdout(Stdio::piped())
                .stderr(Stdio::piped())
                .spawn()
                .unwrap()
        })
        .collect();
    for (v, child) in ["1", "2"].iter().zip(children) {
        let out = child.wait_with_output().unwrap();
        assert!(
            out.status.success(),
            "v{v}: {}",
            String::from_utf8_lossy(&out.stderr)
        );
        let r: serde_json::Value = serde_json::from_slice(&out.stdout).unwrap();
        assert_eq!(r["accepted"], true, "v{v}: {r}");
        assert_eq!(r["controller"][0], 3);
        let rate = r["wall_rate_hz"].as_f64().unwrap();
        assert!((rate - 125.0).abs() <= 1.0, "v{v}: {r}");
        assert!(
            (r["controller_rate_hz"].as_f64().unwrap() - 125.0).abs() < 1e-6,
            "v{v}: {r}"
        );
        assert_eq!(r["gaps"], 0, "v{v}: {r}");
        eprintln!("v{v}: {r}");
    }
}
