//! The real-cell path of `equact run --config`: the parts connect from a real-cell
//! configuration (backend "ur", URCap gripper) pointed at the simulated controller and
//! gripper emulator on loopback, and the episode loop runs a cell without a success test
//! (what a real cell is), ending with the operator's judgement and the arm still.

#![allow(clippy::unwrap_used, clippy::expect_used)] // test helpers may panic

use std::collections::BTreeMap;
use std::sync::atomic::AtomicBool;
use std::sync::Arc;
use std::time::Duration;

use cell_types::config::{CellConfig, GripperTransport};
use cell_types::Joints;
use cell_types::{SystemClock, TickClock};
use equact::episode::{run_episode, CellIo, OperatorJudged, Outcome, ScriptedExpert, TaskMonitor};
use equact::real_cell::{connect_gripper, read_calibration, RealCell};
use equact::recording::EpisodeRecorder;
use equact::sim_cell::{SimCell, SimWorld};
use equact::task::world::GripperEvent;
use equact::task::{Fruit, TaskInstance, TaskKind};
use firmware_iface::gripper::Gripper;
use hil_sim::gripper::{GripperSim, SimConfig};
use hil_sim::ur_controller::{start, UrSimConfig};

#[test]
fn a_real_cell_config_connects_arm_gripper_and_calibration_and_names_the_cameras() {
    let clock = Arc::new(SystemClock::new());
    let controller = start(UrSimConfig::for_tests(), clock.clone()).unwrap();
    let (_gripper, server) =
        GripperSim::spawn_urcap_on_loopback(clock.clone(), SimConfig::default()).unwrap();
    let dir = std::env::temp_dir().join(format!("equact-real-cell-{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();

    let mut cfg =
        tests::loopback_real_cell_config(&controller, Some(server.addr().unwrap().port())).unwrap();

    // No calibration file named: a clear error before anything connects.
    let err = RealCell::connect(&cfg, &dir, clock.clone()).err().unwrap();
    assert!(format!("{err:#}").contains("calibration.file"), "{err:#}");

    // A calibration solved from simulated exact captures of the cell.
    cfg.calibration.file = "calibration.toml".into();
    tests::write_exact_calibration(&dir).unwrap();
    let cal = read_calibration(&cfg, &dir).unwrap();
    assert_eq!(cal.cameras.len(), cfg.cameras.len());

    // The gripper on its configured transport answers; the simulated transport is refused.
    let mut g = connect_gripper(&cfg, clock.clone()).unwrap();
    let state = g.activate().unwrap();
    assert!(state.activated && state.fault.is_none(), "{state:?}");
    drop(g);
    let mut sim_gripper = cfg.clone();
    sim_gripper.gripper.transport = GripperTransport::Sim;
    let err = connect_gripper(&sim_gripper, clock.clone()).err().unwrap();
    assert!(format!("{err}").contains("real transport"), "{err}");

    // Arm, gripper and calibration connect; the cameras are the D455s the config names,
    // which this machine does not have: the error says so.
    let err = RealCell::connect(&cfg, &dir, clock.clone()).err().unwrap();
    assert!(format!("{err:#}").contains("D455"), "{err:#}");
    controller.shutdown();
}

/// The simulated world behaving as the real one does (the scene follows the arm and the
/// gripper), but with a real cell's knowledge: the instruction, no success test.
struct RealWorld<'a> {
    sim: &'a mut SimWorld,
    judged: OperatorJudged,
}

impl TaskMonitor for RealWorld<'_> {
    fn instruction(&self) -> String {
        self.judged.instruction()
    }
    fn success(&self) -> Option<bool> {
        self.judged.success()
    }
    fn update_robot(&mut self, q: &Joints, opening: f64) -> anyhow::Result<()> {
        self.sim.update_robot(q, opening)
    }
    fn before_close(&mut self, q: &Joints) {
        self.sim.before_close(q);
    }
    fn after_gripper(&mut self, q: &Joints, holding: bool) -> Option<GripperEvent> {
        // The world moves the object, but a real cell cannot see where it went: no report.
        self.sim.after_gripper(q, holding);
        self.judged.after_gripper(q, holding)
    }
}

/// A cell without a success test (a real one) runs the loop to the policy's end and leaves
/// the outcome to the operator; the arm ends still and the recording is complete.
#[test]
fn an_episode_without_a_success_test_is_left_to_the_operator() {
    let cfg = CellConfig::simulated().unwrap();
    let clock = Arc::new(TickClock::new(1.0).unwrap());
    let seed = 0;
    let task = TaskInstance::sample(
        TaskKind::PickFruit(Fruit::Strawberry),
        seed,
        cfg.workspace.table_height,
    );
    let mut cell = SimCell::start(&cfg, task.clone(), seed, clock.clone()).unwrap();
    let path = std::env::temp_dir()
        .join(format!("equact-real-cell-{}", std::process::id()))
        .join("operator.mcap");
    let mut recorder = EpisodeRecorder::create(&path, &BTreeMap::new()).unwrap();
    let mut policy = ScriptedExpert::new(task.expert_keyframes());
    let mut judged = RealWorld {
        sim: &mut cell.world,
        judged: OperatorJudged {
            instruction: "pick the strawberry".into(),
        },
    };
    let io = CellIo {
        arm: &mut cell.arm,
        gripper: &mut cell.gripper as &mut dyn Gripper,
        cameras: &mut cell.cameras,
        calibration: &cell.calibration,
        task: &mut judged,
    };
    let interrupt = Arc::new(AtomicBool::new(false));
    let report = run_episode(
        &cfg,
        io,
        &mut policy,
        &mut recorder,
        &interrupt,
        clock.as_ref(),
        seed,
    );
    assert_eq!(report.outcome, Outcome::TaskNotDone, "{}", report.detail);
    assert!(report.detail.contains("judge"), "{}", report.detail);
    assert_eq!(report.steps, task.expert_keyframes().len());
    // The expert grasped the fruit, but a real cell has no world truth to report it from.
    assert!(
        report.gripper_events.is_empty(),
        "{:?}",
        report.gripper_events
    );
    std::thread::sleep(Duration::from_millis(600));
    let snap = cell.controller.snapshot();
    assert!(snap.actual_qd.iter().all(|v| v.abs() < 1e-3));
    cell.controller.shutdown();

    let v = tests::check_recording_with_peer(&path).unwrap();
    assert_eq!(v["outcome"]["outcome"], "task_not_done");
}
