//! The built-in simulated cell: hil_sim's UR controller, gripper emulator and depth cameras
//! on loopback, with the real drivers connected to them over their wire protocols.
//!
//! The simulator keeps the world's truth (where the object is, whether it is held); the
//! episode loop only sees it through the drivers, the cameras and [`SimWorld`]'s success
//! test, as it would on the real cell.

use std::net::SocketAddr;
use std::sync::{Arc, RwLock};

use anyhow::Context;
use cell_types::config::CellConfig;
use cell_types::{CellTypesError, Clock, Joints, TickClock, Transform};
use firmware_iface::camera::DepthCamera;
use firmware_iface::gripper::transport::UrcapTransport;
use firmware_iface::gripper::RobotiqGripper;
use firmware_iface::ur::{UrArm, UrConfig, UrPorts};
use hil_sim::depth_camera::{default_rig, rig_calibration, SharedScene, SimCameraDevice};
use hil_sim::gripper::{GripperSim, SimServer};
use hil_sim::scene::{Scene, HOME_Q};
use hil_sim::ur_controller::{self, UrSimConfig, UrSimHandle};
use nalgebra::{Isometry3, Translation3, Vector3};

use crate::task::world::{GripperEvent, TaskWorld};
use crate::task::{TaskInstance, TaskKind};

/// Which simulated episodes to run (`equact eval`, `equact demos collect`): task
/// variations, episodes per variation, the first seed, and the simulator's speed.
#[derive(Clone, Debug, PartialEq)]
pub struct EpisodePlan {
    /// Task variations.
    pub kinds: Vec<TaskKind>,
    /// Episodes per variation.
    pub episodes: u64,
    /// Seed of each variation's first episode (the next ones add one).
    pub seed: u64,
    /// How many times faster than real time the simulated cell runs (1: real time, as the
    /// real cell does; see [`TickClock`]).
    pub sim_speed: f64,
}

impl EpisodePlan {
    /// A fresh clock for one episode at the plan's speed, or why that speed cannot run.
    pub fn clock(&self) -> Result<Arc<TickClock>, CellTypesError> {
        TickClock::new(self.sim_speed).map(Arc::new)
    }
}

/// Control cycles without data before the driver stops a motion, in the simulated cell.
const SIM_LOST_CYCLES: u32 = cell_types::config::MAX_LOST_CYCLES;

/// The servo program's watchdog in the simulated cell, in control cycles (200 ms): the
/// driver shares two cores with the simulator, so it tolerates the same silence as
/// [`SIM_LOST_CYCLES`] instead of the real robot's 10. Faster than real time this matters
/// most: at `--sim-speed` S the driver has 1/S of the wall time to answer.
const SIM_WATCHDOG_CYCLES: u32 = SIM_LOST_CYCLES;

/// The simulated world's truth for the task: the bodies, which one is held, and their
/// solids in the rendered scene.
pub struct SimWorld {
    scene: Scene,
    /// Per body, per part: the part's index in the scene.
    part_index: Vec<Vec<usize>>,
    /// The task being run.
    pub task: TaskInstance,
    truth: TaskWorld,
    shared: SharedScene,
    gripper: GripperSim,
    tcp_offset: f64,
}

impl SimWorld {
    /// Where the task's main object is now (pick fruit: the fruit).
    pub fn object_pose(&self) -> Isometry3<f64> {
        let i = self
            .task
            .bodies
            .iter()
            .position(|b| b.grasp.is_some())
            .unwrap_or(0);
        self.truth.poses()[i]
    }

    /// Every body's pose now (the order of the task's bodies).
    pub fn body_poses(&self) -> &[Isometry3<f64>] {
        self.truth.poses()
    }

    /// True while the gripper holds an object.
    pub fn holds_object(&self) -> bool {
        self.truth.held().is_some()
    }

    /// The gripper emulator (fault injection in tests).
    pub fn gripper_sim(&self) -> &GripperSim {
        &self.gripper
    }

    /// The task's success test on the world's state.
    pub fn success(&self) -> bool {
        self.truth.success()
    }

    /// Why the task can no longer succeed in the world's state, if it cannot.
    pub fn lost(&self) -> Option<String> {
        self.truth.lost()
    }

    fn tcp(&self, q: &Joints) -> Isometry3<f64> {
        let flange = *planner::kinematics::UR5.forward(q).isometry();
        flange * Isometry3::translation(0.0, 0.0, self.tcp_offset)
    }

    /// Before the fingers close at joint angles `q`: an object between them makes the
    /// emulator's fingers stop on it (gOBJ = 2).
    pub fn before_close(&mut self, q: &Joints) {
        let tcp = self.tcp(q);
        let width = self.truth.before_close(&tcp);
        self.gripper.set_object(width);
    }

    /// After a gripper motion: a closed gripper with its fingers on an object carries it;
    /// opening releases it, and it comes to rest where the task says (the table, or the
    /// target of a place task). Returns what happened to a body, if anything.
    pub fn after_gripper(&mut self, q: &Joints, holding: bool) -> Option<GripperEvent> {
        let tcp = self.tcp(q);
        let was_held = self.truth.held().is_some();
        let event = self.truth.after_gripper(&tcp, holding);
        if was_held && self.truth.held().is_none() {
            self.gripper.set_object(None);
        }
        self.place_bodies();
        event
    }

    fn place_bodies(&mut self) {
        for (b, parts) in self.part_index.iter().enumerate() {
            let pose = self.truth.poses()[b];
            for (k, &i) in parts.iter().enumerate() {
                self.scene.objects[i].base_from_object =
                    pose * self.task.bodies[b].parts[k].body_from_part;
            }
        }
    }

    /// Moves the arm (and a held object) in the rendered scene to `q`.
    pub fn update_robot(&mut self, q: &Joints, opening: f64) -> anyhow::Result<()> {
        let tcp = self.tcp(q);
        self.truth.carry(&tcp);
        self.place_bodies();
        self.scene.set_robot(q, opening);
        let geometry = self
            .scene
            .build()
            .context("rebuilding the simulated scene")?;
        let mut guard = self
            .shared
            .write()
            .map_err(|_| anyhow::anyhow!("the simulated scene's lock is poisoned"))?;
        *guard = geometry;
        Ok(())
    }
}

/// Everything the built-in simulated cell runs, with the drivers connected to it.
pub struct SimCell {
    /// The simulated UR controller.
    pub controller: UrSimHandle,
    /// The UR driver, connected over RTDE/dashboard/secondary on loopback.
    pub arm: UrArm,
    /// The gripper emulator's URCap server (kept alive while the cell runs).
    pub gripper_server: SimServer,
    /// The Robotiq driver, connected over the URCap text socket on loopback.
    pub gripper: RobotiqGripper<UrcapTransport>,
    /// The simulated depth cameras.
    pub cameras: Vec<Box<dyn DepthCamera>>,
    /// The cameras' true calibration.
    pub calibration: calibration::CellCalibration,
    /// The world's truth for the task.
    pub world: SimWorld,
}

impl SimCell {
    /// Starts the simulated cell for `task` and connects the drivers. The simulated
    /// controller keeps `clock`'s time, one control cycle at a time, each waiting for the
    /// driver's answer to the one before (lockstep), so that an episode replays bit for bit.
    pub fn start(
        cfg: &CellConfig,
        task: TaskInstance,
        seed: u64,
        clock: Arc<TickClock>,
    ) -> anyhow::Result<Self> {
        let clock: Arc<dyn Clock> = clock;
        let tcp_offset = cfg.robot.tcp_offset_m;
        let sim_cfg = UrSimConfig {
            initial_q: HOME_Q,
            flange_from_tcp: Transform::from_parts(
                Vector3::new(0.0, 0.0, tcp_offset),
                Default::default(),
            ),
            // The controller's table check must see the same table as the planner and the
            // scene: the simulated table top is below the base plate.
            floor_z: Some(cfg.workspace.table_height),
            // Each control cycle waits for the driver's answer to the one before, as a real
            // controller never has to (its client always answers in time): the arm then
            // follows the same targets cycle for cycle whatever the load, and an episode
            // replays bit for bit (with the driver reporting a motion once the arm is at
            // rest, not from its last creep).
            lockstep: true,
            ..UrSimConfig::for_tests()
        };
        let sim_cfg = match cfg.robot.model {
            cell_types::config::RobotModel::Ur5 => sim_cfg,
            cell_types::config::RobotModel::Ur5e => sim_cfg.e_series(),
        };
        let controller = ur_controller::start(sim_cfg, clock.clone())
            .context("starting the simulated UR controller")?;
        let ports: UrPorts = controller.ports();
        let arm = UrArm::connect(
            UrConfig {
                host: controller.addr(),
                ports,
                tracking_bound: cfg.limits.tracking_error_bound,
                stop_decel: cfg.limits.stop_deceleration,
                // The simulated controller shares two cores with the cameras, the fusion and
                // whatever else runs; a real controller has its own. Tolerate 200 ms of
                // silence here instead of the driver's 3 cycles (kept for real robots).
                lost_cycles: SIM_LOST_CYCLES,
                watchdog_cycles: SIM_WATCHDOG_CYCLES,
                // As on the real cell: the thread that answers the controller first.
                realtime_priority: cfg.robot.fifo_priority(),
                ..UrConfig::default()
            },
            clock.clone(),
        )
        .context("connecting the UR driver to the simulated controller")?;

        let (gripper_sim, gripper_server) = GripperSim::spawn_urcap_on_loopback(
            clock.clone(),
            // Behind the URCap socket, the UR controller's URCap polls the gripper over
            // Modbus all the time, so a quiet socket client never starves the gripper
            // into fault 0x09 (that fault belongs to the Modbus and CAN paths).
            hil_sim::gripper::SimConfig {
                comm_timeout: std::time::Duration::from_secs(24 * 3600),
                ..Default::default()
            },
        )
        .context("starting the gripper emulator")?;
        let addr: SocketAddr = gripper_server
            .addr()
            .ok_or_else(|| anyhow::anyhow!("the gripper emulator did not report its port"))?;
        let gripper = RobotiqGripper::urcap(addr, clock.clone())
            .context("connecting the gripper driver to the emulator")?;

        let mut scene = Scene::table_only();
        let mut part_index = Vec::with_capacity(task.bodies.len());
        for body in &task.bodies {
            let mut parts = Vec::with_capacity(body.parts.len());
            for (k, part) in body.parts.iter().enumerate() {
                scene.add_object(
                    &format!("{} part {k}", body.name),
                    body.base_from_body * part.body_from_part,
                    part.shape,
                    part.colour,
                );
                parts.push(scene.objects.len() - 1);
            }
            part_index.push(parts);
        }
        scene.set_robot(&HOME_Q, 0.085);
        let shared: SharedScene = Arc::new(RwLock::new(
            scene.build().context("building the simulated scene")?,
        ));
        let rig = default_rig(seed);
        let calibration = rig_calibration(&rig);
        let cameras: Vec<Box<dyn DepthCamera>> = rig
            .into_iter()
            .map(|c| {
                Box::new(SimCameraDevice::new(c, shared.clone(), clock.clone()))
                    as Box<dyn DepthCamera>
            })
            .collect();
        let world = SimWorld {
            scene,
            part_index,
            truth: TaskWorld::new(task.clone()),
            task,
            shared,
            gripper: gripper_sim,
            tcp_offset,
        };
        Ok(Self {
            controller,
            arm,
            gripper_server,
            gripper,
            cameras,
            calibration,
            world,
        })
    }
}

/// A translation-only isometry (m).
pub fn translation(x: f64, y: f64, z: f64) -> Isometry3<f64> {
    Isometry3::from_parts(Translation3::new(x, y, z), Default::default())
}
