//! `equact check` against the simulated controller and gripper emulator on loopback, set up
//! as a real cell would be (backend "ur", URCap gripper): a ready cell passes every hardware
//! check; a protective stop, a missing calibration file, a dead gripper address and an
//! out-of-reach workspace each fail with their own message and fix.

#![allow(clippy::unwrap_used, clippy::expect_used)] // test helpers may panic

use std::sync::Arc;

use cell_types::SystemClock;
use equact::preflight::{run_checks, Check};
use hil_sim::gripper::{GripperSim, SimConfig};
use hil_sim::ur_controller::{start, Fault, UrSimConfig};

fn find<'a>(checks: &'a [Check], name: &str) -> &'a Check {
    checks
        .iter()
        .find(|c| c.name == name)
        .unwrap_or_else(|| panic!("no {name} check in {checks:?}"))
}

#[test]
fn preflight_of_a_loopback_cell() {
    let clock = Arc::new(SystemClock::new());
    let controller = start(UrSimConfig::for_tests(), clock.clone()).unwrap();
    let (_gripper, server) =
        GripperSim::spawn_urcap_on_loopback(clock.clone(), SimConfig::default()).unwrap();
    let dir = std::env::temp_dir().join(format!("equact-preflight-{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();

    let mut cfg =
        tests::loopback_real_cell_config(&controller, Some(server.addr().unwrap().port())).unwrap();
    cfg.calibration.file = "calibration.toml".into();
    // A real calibration file: simulated exact captures of the cell, solved.
    tests::write_exact_calibration(&dir).unwrap();

    // A ready cell: every hardware check passes; the cameras fail (no D455 is connected
    // here, or librealsense is not installed; tests/tests/realsense.rs checks them).
    cfg.workspace.min = [0.25, -0.3, -0.05];
    cfg.workspace.max = [0.6, 0.25, 0.3];
    let checks = run_checks(&cfg, &dir, clock.clone());
    for name in [
        "controller",
        "safety",
        "joints",
        "gripper",
        "calibration",
        "workspace",
    ] {
        let c = find(&checks, name);
        assert!(c.passed && !c.warning, "{c:?}");
    }
    assert!(!find(&checks, "cameras").passed);
    // The driver thread asked for real-time priority (the default 80): granted here when the
    // tests run with the right (root, CAP_SYS_NICE, rtprio), else a warning saying why.
    let c = find(&checks, "driver thread");
    assert!(c.passed, "{c:?}");
    assert!(
        c.detail.contains("SCHED_FIFO priority 80") && (c.warning == c.detail.contains("refused")),
        "{c:?}"
    );

    // The config names the wrong controller generation.
    let mut wrong = cfg.clone();
    wrong.robot.model = cell_types::config::RobotModel::Ur5e;
    wrong.robot.controller_rate_hz = 500.0;
    let c = run_checks(&wrong, &dir, clock.clone());
    let c = find(&c, "controller");
    assert!(!c.passed && c.fix.contains("robot.model"), "{c:?}");

    // A protective stop: safety fails and says how to clear it.
    controller.inject(Fault::ProtectiveStop);
    std::thread::sleep(std::time::Duration::from_millis(100));
    let checks = run_checks(&cfg, &dir, clock.clone());
    let c = find(&checks, "safety");
    assert!(!c.passed && c.detail.contains("Protective"), "{c:?}");

    // Missing calibration file, a camera without a pose, a dead gripper port, a workspace
    // the arm cannot reach.
    let mut broken = cfg.clone();
    broken.calibration.file = "nowhere.toml".into();
    broken.gripper.port = 1;
    broken.workspace.max[0] = 1.6;
    let checks = run_checks(&broken, &dir, clock.clone());
    let c = find(&checks, "calibration");
    assert!(!c.passed && c.detail.contains("nowhere.toml"), "{c:?}");
    assert!(!find(&checks, "gripper").passed);
    // A box beyond the UR5's 0.85 m reach is a warning naming the corners, not a failure.
    let c = find(&checks, "workspace");
    assert!(c.passed && c.warning && c.detail.contains("1.60"), "{c:?}");
    // A camera the calibration does not know.
    let mut extra = cfg.clone();
    let mut fourth = extra.cameras[0].clone();
    fourth.name = "top".into();
    fourth.serial = "sim-top".into();
    extra.cameras.push(fourth);
    let checks = run_checks(&extra, &dir, clock);
    let c = find(&checks, "calibration");
    assert!(!c.passed && c.detail.contains("3 (top)"), "{c:?}");

    // Nothing moved: the controller never ran a program.
    assert_eq!(controller.snapshot().runtime_state(), 1);
    controller.shutdown();
    let _ = std::fs::remove_dir_all(&dir);
}
