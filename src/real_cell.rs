//! A real cell, connected from its configuration: the UR driver to the controller, the
//! Robotiq driver on the configured transport, the configured D455 cameras, and the
//! calibration file. `equact run --config` drives it through the same episode loop as the
//! simulated cell ([`crate::episode::CellIo`]).

use std::path::Path;
use std::sync::Arc;

use anyhow::Context;
use calibration::CellCalibration;
use cell_types::config::{CameraSection, CellConfig, GripperTransport};
use cell_types::{CameraFrame, Clock};
use firmware_iface::camera::DepthCamera;
use firmware_iface::gripper::can::{CanId, CanMapping};
use firmware_iface::gripper::{Gripper, RobotiqGripper};
use firmware_iface::realsense::{RealSenseCamera, RealSenseError};
use firmware_iface::ur::UrArm;

use crate::episode::{CellIo, TaskMonitor};

/// The connected parts of a real cell.
pub struct RealCell {
    /// The UR driver, connected to the controller.
    pub arm: UrArm,
    /// The gripper driver on the configured transport.
    pub gripper: Box<dyn Gripper + Send>,
    /// The depth cameras, numbered by their order in the configuration.
    pub cameras: Vec<Box<dyn DepthCamera>>,
    /// The cameras' calibration (from `calibration.file`).
    pub calibration: CellCalibration,
}

impl RealCell {
    /// Connects everything the configuration names; `config_dir` resolves a relative
    /// calibration file. Nothing moves.
    pub fn connect(
        cfg: &CellConfig,
        config_dir: &Path,
        clock: Arc<dyn Clock>,
    ) -> anyhow::Result<Self> {
        let calibration = read_calibration(cfg, config_dir)?;
        let ur = crate::preflight::ur_config(cfg).map_err(anyhow::Error::msg)?;
        let arm = UrArm::connect(ur, clock.clone())
            .with_context(|| format!("connecting to the UR controller at {}", cfg.robot.host))?;
        let gripper = connect_gripper(cfg, clock)?;
        let cameras = open_cameras(cfg)?;
        Ok(Self {
            arm,
            gripper,
            cameras,
            calibration,
        })
    }

    /// Borrows the parts for one episode, with `task` as what is known about the task.
    pub fn io<'a>(&'a mut self, task: &'a mut dyn TaskMonitor) -> CellIo<'a> {
        CellIo {
            arm: &mut self.arm,
            gripper: self.gripper.as_mut(),
            cameras: &mut self.cameras,
            calibration: &self.calibration,
            task,
        }
    }
}

/// Reads `calibration.file` (relative to `config_dir`) and checks it names exactly the
/// configured cameras (numbered by their order in `[[cameras]]`).
pub fn read_calibration(cfg: &CellConfig, config_dir: &Path) -> anyhow::Result<CellCalibration> {
    if cfg.calibration.file.trim().is_empty() {
        anyhow::bail!(
            "the config names no calibration.file: calibrate the cameras (`equact calibrate`) \
             and name the file in [calibration]"
        );
    }
    let path = config_dir.join(&cfg.calibration.file);
    let calibration = calibration::read_calibration_toml(&path)
        .with_context(|| format!("reading the calibration {}", path.display()))?;
    let known: Vec<u8> = (0..cfg.cameras.len())
        .filter_map(|i| u8::try_from(i).ok())
        .collect();
    calibration
        .validate_against(&known)
        .with_context(|| format!("{} does not fit the configured cameras", path.display()))?;
    let missing = cameras_without_pose(cfg, &calibration);
    if !missing.is_empty() {
        anyhow::bail!(
            "{} has no pose for camera(s) {}: recalibrate with every configured camera",
            path.display(),
            missing.join(", ")
        );
    }
    Ok(calibration)
}

/// The configured cameras (`index (name)`, numbered by their order in `[[cameras]]`) that
/// `calibration` has no pose for.
pub fn cameras_without_pose(cfg: &CellConfig, calibration: &CellCalibration) -> Vec<String> {
    cfg.cameras
        .iter()
        .enumerate()
        .filter(|(i, _)| !calibration.cameras.iter().any(|c| usize::from(c.id) == *i))
        .map(|(i, c)| format!("{i} ({})", c.name))
        .collect()
}

/// The CAN identifiers of the configuration (11-bit when they fit, else 29-bit).
pub fn can_mapping(cfg: &CellConfig) -> Result<CanMapping, String> {
    let id = |raw: u32| {
        if raw <= 0x7FF {
            CanId::standard(raw as u16)
        } else {
            CanId::extended(raw)
        }
        .map_err(|e| e.to_string())
    };
    Ok(CanMapping {
        command_id: id(cfg.gripper.can_command_id)?,
        status_id: id(cfg.gripper.can_status_id)?,
    })
}

/// Connects the gripper driver on the configured transport (not the simulated one).
pub fn connect_gripper(
    cfg: &CellConfig,
    clock: Arc<dyn Clock>,
) -> anyhow::Result<Box<dyn Gripper + Send>> {
    let g = &cfg.gripper;
    let what = format!("connecting the gripper ({:?})", g.transport);
    Ok(match g.transport {
        GripperTransport::Sim => anyhow::bail!(
            "gripper.transport = \"sim\" names the simulated gripper, which only the built-in \
             simulated cell has: set the real transport (urcap, modbus_rtu, can_slcan)"
        ),
        GripperTransport::Urcap => {
            Box::new(RobotiqGripper::urcap((g.host.as_str(), g.port), clock).context(what)?)
        }
        GripperTransport::ModbusRtu => {
            Box::new(RobotiqGripper::modbus_rtu(&g.device, clock).context(what)?)
        }
        GripperTransport::CanSlcan => {
            let mapping = can_mapping(cfg).map_err(anyhow::Error::msg)?;
            Box::new(RobotiqGripper::slcan(&g.device, mapping, clock).context(what)?)
        }
        GripperTransport::Socketcan => anyhow::bail!(
            "SocketCAN is only built with the `socketcan` feature of firmware_iface: use \
             can_slcan with a serial adapter, or build with --features socketcan"
        ),
    })
}

/// Frames dropped after each camera starts, while its auto-exposure settles.
const WARMUP_FRAMES: u32 = 30;

/// Opens the configured D455 cameras (librealsense2, loaded at run time), numbered by
/// their order in `[[cameras]]`, and lets each settle its exposure.
pub fn open_cameras(cfg: &CellConfig) -> anyhow::Result<Vec<Box<dyn DepthCamera>>> {
    let mut cameras: Vec<Box<dyn DepthCamera>> = Vec::with_capacity(cfg.cameras.len());
    for (i, c) in cfg.cameras.iter().enumerate() {
        let id = u8::try_from(i).context("more than 255 cameras")?;
        let cam = open_settled(id, c, WARMUP_FRAMES, &mut open_configured)?;
        cameras.push(Box::new(cam));
    }
    Ok(cameras)
}

/// Opens camera `id` (entry `c`) with `open` and drops `warmup` framesets while its
/// auto-exposure settles.
fn open_settled(
    id: u8,
    c: &CameraSection,
    warmup: u32,
    open: &mut dyn FnMut(u8, &CameraSection) -> Result<RealSenseCamera, RealSenseError>,
) -> anyhow::Result<RealSenseCamera> {
    let mut cam = open(id, c)
        .with_context(|| format!("opening the D455 `{}` (serial {})", c.name, c.serial))?;
    for _ in 0..warmup {
        cam.next_frame()
            .with_context(|| format!("camera `{}` warming up", c.name))?;
    }
    Ok(cam)
}

/// Opens the D455 of one `[[cameras]]` entry as configured: depth and IR at its mode and
/// rate, plus colour aligned to depth when `colour = true`.
pub fn open_configured(id: u8, c: &CameraSection) -> Result<RealSenseCamera, RealSenseError> {
    if c.colour {
        RealSenseCamera::open_with_colour(id, &c.serial, c.mode, c.fps)
    } else {
        RealSenseCamera::open(id, &c.serial, c.mode, c.fps)
    }
}

/// One frameset from each configured camera (`equact perceive --config`): camera `i` (the
/// config's `i`-th entry) is opened by `open`, drops `warmup` framesets while its
/// auto-exposure settles, gives one and is closed before the next opens.
pub fn capture_frames(
    cfg: &CellConfig,
    warmup: u32,
    open: &mut dyn FnMut(u8, &CameraSection) -> Result<RealSenseCamera, RealSenseError>,
) -> anyhow::Result<Vec<CameraFrame>> {
    let mut frames = Vec::with_capacity(cfg.cameras.len());
    for (i, c) in cfg.cameras.iter().enumerate() {
        let id = u8::try_from(i).context("more than 255 cameras")?;
        let mut cam = open_settled(id, c, warmup, open)?;
        frames.push(
            cam.next_frame()
                .with_context(|| format!("capturing from camera `{}`", c.name))?,
        );
    }
    Ok(frames)
}

/// A real arm moves only after the operator said so: Enter at a terminal, or `--yes`.
pub fn confirm_motion(yes: bool) -> anyhow::Result<()> {
    use std::io::IsTerminal;
    if yes {
        return Ok(());
    }
    if !std::io::stdin().is_terminal() {
        anyhow::bail!(
            "the arm is about to move and nobody can confirm it (stdin is not a terminal): \
             pass --yes to run unattended"
        );
    }
    println!(
        "the arm will move now: keep clear of the cell; press Enter to start, Ctrl-C to abort"
    );
    let mut line = String::new();
    std::io::stdin()
        .read_line(&mut line)
        .context("waiting for Enter")?;
    Ok(())
}
