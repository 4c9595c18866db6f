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
use cell_types::{Clock, Joints, Transform};
use firmware_iface::camera::DepthCamera;
use firmware_iface::gripper::transport::UrcapTransport;
use firmware_iface::gripper::RobotiqGripper;
use firmware_iface::ur::{UrArm, UrConfig, UrPorts};
use hil_sim::depth_camera::{default_rig, rig_calibration, SharedScene, SimCameraDevice};
use hil_sim::gripper::{GripperSim, SimServer};
use hil_sim::scene::{Primitive, Scene, HOME_Q};
use hil_sim::ur_controller::{self, UrSimConfig, UrSimHandle};
use nalgebra::{Isometry3, Translation3, Vector3};

use crate::task::TaskInstance;

/// Grasp distance: the object is caught when its centre is this close to the TCP as the
/// fingers close (m).
const GRASP_RADIUS: f64 = 0.03;

/// Control cycles without data before the driver stops a motion, in the simulated cell.
const SIM_LOST_CYCLES: u32 = 25;

/// The simulated world's truth for the task: the object and whether it is held.
pub struct SimWorld {
    scene: Scene,
    object_index: usize,
    /// The task being run.
    pub task: TaskInstance,
    held: Option<Isometry3<f64>>,
    shared: SharedScene,
    gripper: GripperSim,
    tcp_offset: f64,
}

impl SimWorld {
    /// Where the object is now.
    pub fn object_pose(&self) -> Isometry3<f64> {
        self.scene.objects[self.object_index].base_from_object
    }

    /// True while the gripper holds the object.
    pub fn holds_object(&self) -> bool {
        self.held.is_some()
    }

    /// The gripper emulator (fault injection in tests).
    pub fn gripper_sim(&self) -> &GripperSim {
        &self.gripper
    }

    /// The task's success test on the world's state.
    pub fn success(&self) -> bool {
        self.task.success(&self.object_pose(), self.holds_object())
    }

    fn tcp(&self, q: &Joints) -> Isometry3<f64> {
        let flange = *planner::kinematics::UR5.forward(q).isometry();
        flange * Isometry3::translation(0.0, 0.0, self.tcp_offset)
    }

    /// Before the fingers close at joint angles `q`: an object between them makes the
    /// emulator's fingers stop on it (gOBJ = 2).
    pub fn before_close(&mut self, q: &Joints) {
        let tcp = self.tcp(q);
        let d = (tcp.translation.vector - self.object_pose().translation.vector).norm();
        if d <= GRASP_RADIUS {
            let crate::task::TaskKind::PickFruit(f) = self.task.kind;
            self.gripper.set_object(Some(2.0 * f.radius()));
        } else {
            self.gripper.set_object(None);
        }
    }

    /// After a gripper motion: a closed gripper with its fingers on the object carries it;
    /// opening releases it onto the table.
    pub fn after_gripper(&mut self, q: &Joints, holding: bool) {
        let tcp = self.tcp(q);
        if holding && self.held.is_none() {
            self.held = Some(tcp.inverse() * self.object_pose());
        } else if !holding && self.held.is_some() {
            self.held = None;
            self.gripper.set_object(None);
            let mut p = self.object_pose();
            let crate::task::TaskKind::PickFruit(f) = self.task.kind;
            p.translation.vector.z = self.task.table_height + f.radius();
            self.scene.objects[self.object_index].base_from_object = p;
        }
    }

    /// Moves the arm (and a held object) in the rendered scene to `q`.
    pub fn update_robot(&mut self, q: &Joints, opening: f64) -> anyhow::Result<()> {
        if let Some(tcp_from_object) = self.held {
            self.scene.objects[self.object_index].base_from_object = self.tcp(q) * tcp_from_object;
        }
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
    /// Starts the simulated cell for `task` and connects the drivers.
    pub fn start(
        cfg: &CellConfig,
        task: TaskInstance,
        seed: u64,
        clock: Arc<dyn Clock>,
    ) -> anyhow::Result<Self> {
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
        let crate::task::TaskKind::PickFruit(fruit) = task.kind;
        scene.add_object(
            &task.kind.name(),
            task.base_from_object,
            Primitive::Sphere {
                radius: fruit.radius(),
            },
            fruit.colour(),
        );
        let object_index = scene.objects.len() - 1;
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
            object_index,
            task,
            held: None,
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
