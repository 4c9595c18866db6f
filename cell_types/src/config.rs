//! The cell configuration (`cell.toml`): parsed with `deny_unknown_fields`, then validated
//! once into a [`CellConfig`] that the rest of the stack trusts.
//!
//! Every mistake is reported as a [`ConfigError`] naming the key and what is wrong with it.
//! The built-in simulated cell ([`CellConfig::simulated`]) is `config/sim_cell.toml`.

use std::path::{Path, PathBuf};

use serde::{Deserialize, Serialize};
use thiserror::Error;

use crate::joints::{Joints, JOINT_COUNT};

/// The built-in simulated cell's configuration text.
pub const SIMULATED_CELL_TOML: &str = include_str!("../config/sim_cell.toml");

/// UR5 maximum joint speed (rad/s): π on every joint.
pub const UR5_MAX_JOINT_SPEED: f64 = std::f64::consts::PI;

/// Why a configuration could not be read or accepted.
#[derive(Debug, Error)]
#[non_exhaustive]
pub enum ConfigError {
    /// The file could not be read.
    #[error("cannot read cell configuration {path}: {source}; check the path given to --config")]
    Read {
        /// The file.
        path: PathBuf,
        /// The I/O error.
        source: std::io::Error,
    },
    /// The text is not valid TOML or does not match the schema (unknown key, wrong type,
    /// missing key). The message from the parser names the key and the line.
    #[error("cell configuration {origin} is malformed: {message}")]
    Parse {
        /// Where the text came from.
        origin: String,
        /// The parser's message (names the key and the line).
        message: String,
    },
    /// A value is outside what the key accepts.
    #[error("cell configuration key `{key}` = {value}: {problem}")]
    Invalid {
        /// The dotted key, e.g. `limits.max_velocity[2]`.
        key: String,
        /// The value as written.
        value: String,
        /// What is wrong and what would be accepted.
        problem: String,
    },
}

/// Which robot controller the cell talks to.
#[derive(Copy, Clone, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum RobotBackend {
    /// hil_sim's simulated controller on loopback.
    Sim,
    /// A real UR controller at `robot.host`.
    Ur,
}

/// The arm model.
#[derive(Copy, Clone, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum RobotModel {
    /// UR5 on a CB3 controller (RTDE up to 125 Hz).
    Ur5,
    /// UR5e on an e-Series controller (RTDE up to 500 Hz).
    Ur5e,
}

impl RobotModel {
    /// Highest RTDE rate the controller serves (Hz).
    pub fn max_rate_hz(self) -> f64 {
        match self {
            RobotModel::Ur5 => 125.0,
            RobotModel::Ur5e => 500.0,
        }
    }
}

/// `[robot]`: how to reach the arm.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct RobotSection {
    /// Simulated or real controller.
    pub backend: RobotBackend,
    /// Arm model.
    pub model: RobotModel,
    /// Controller address (IPv4/IPv6 literal or host name).
    pub host: String,
    /// RTDE port (30004 on a real controller; 0 lets the simulator choose).
    pub rtde_port: u16,
    /// Dashboard port (29999 on a real controller).
    pub dashboard_port: u16,
    /// Secondary interface port for URScript (30002 on a real controller).
    pub secondary_port: u16,
    /// Servo streaming rate (Hz).
    pub controller_rate_hz: f64,
    /// Flange to TCP distance along the flange z axis (m).
    pub tcp_offset_m: f64,
    /// Control cycles without a state package before the driver stops a motion (backend
    /// "ur"; the simulated cell sets its own). Keep the default on a real controller.
    #[serde(default = "default_lost_cycles")]
    pub lost_cycles: u32,
    /// `SCHED_FIFO` priority (1-99) of the UR driver's thread that answers the controller
    /// every cycle, asked for at connect (a preflight line says whether it was granted);
    /// 0 leaves it at normal priority.
    #[serde(default = "default_realtime_priority")]
    pub realtime_priority: u8,
}

/// The driver's watchdog on a real controller: 3 cycles (24 ms at 125 Hz).
pub const DEFAULT_LOST_CYCLES: u32 = 3;

/// The most cycles `robot.lost_cycles` may allow: 200 ms of blind motion at 125 Hz.
pub const MAX_LOST_CYCLES: u32 = 25;

fn default_lost_cycles() -> u32 {
    DEFAULT_LOST_CYCLES
}

impl RobotSection {
    /// The driver thread's `SCHED_FIFO` priority to ask for; `None` for 0 (normal priority).
    pub fn fifo_priority(&self) -> Option<u8> {
        (self.realtime_priority != 0).then_some(self.realtime_priority)
    }
}

/// The highest `SCHED_FIFO` priority Linux offers (`robot.realtime_priority`'s bound).
pub const MAX_REALTIME_PRIORITY: u8 = 99;

/// The driver thread's `SCHED_FIFO` priority by default: high, under the kernel's own
/// real-time threads (99), as UR's client library runs its RTDE thread.
pub const DEFAULT_REALTIME_PRIORITY: u8 = 80;

fn default_realtime_priority() -> u8 {
    DEFAULT_REALTIME_PRIORITY
}

/// `[limits]`: joint limits the planner and the driver enforce.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct LimitsSection {
    /// Maximum joint speed (rad/s).
    pub max_velocity: Joints,
    /// Maximum joint acceleration (rad/s²).
    pub max_acceleration: Joints,
    /// Maximum joint jerk (rad/s³).
    pub max_jerk: Joints,
    /// Lower joint position limits (rad).
    pub joint_min: Joints,
    /// Upper joint position limits (rad).
    pub joint_max: Joints,
    /// Largest per-joint tracking error tolerated while executing (rad).
    pub tracking_error_bound: f64,
    /// Deceleration used to stop the arm on a fault or a stop request (rad/s²).
    pub stop_deceleration: f64,
}

/// How the gripper is connected.
#[derive(Copy, Clone, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum GripperTransport {
    /// hil_sim's emulator (over its URCap text socket on loopback).
    Sim,
    /// The URCap text socket of a gripper on the UR tool flange (TCP 63352).
    Urcap,
    /// Modbus RTU over an RS-485 serial adapter.
    ModbusRtu,
    /// CAN through an slcan serial adapter.
    CanSlcan,
    /// CAN through a Linux SocketCAN interface.
    Socketcan,
}

/// `[gripper]`: the Robotiq 2F-85.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct GripperSection {
    /// Transport.
    pub transport: GripperTransport,
    /// URCap socket host.
    pub host: String,
    /// URCap socket port.
    pub port: u16,
    /// Serial device (Modbus RTU, slcan) or SocketCAN interface name.
    pub device: String,
    /// Modbus slave id.
    pub slave_id: u8,
    /// CAN id of the request frames.
    pub can_command_id: u32,
    /// CAN id of the status frames.
    pub can_status_id: u32,
    /// Default finger speed (m/s).
    pub default_speed: f64,
    /// Default grip force (N).
    pub default_force: f64,
}

/// `[workspace]`: the box the TCP and the observed cloud are kept to (base frame, m).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct WorkspaceSection {
    /// Lower corner.
    pub min: [f64; 3],
    /// Upper corner.
    pub max: [f64; 3],
    /// Height of the table top (m).
    pub table_height: f64,
}

/// Default radius (m) of the ball around the gripper that the fusion and the network may
/// sample densely: one value for both, since a network is refused on clouds sampled in a
/// smaller ball than its own.
pub const DEFAULT_GRIPPER_RADIUS_M: f64 = 0.08;

/// `[perception]`: how the fused cloud is sampled for the policy (optional section).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct PerceptionSection {
    /// Points handed to the policy (2048, EquAct's); three quarters of them
    /// ([`Self::points_inside`]) are sampled in the focus box, the rest outside it. A policy
    /// that reads all of them (its weights' cloud size equal to this) sees every point the
    /// fusion chose; one that reads fewer thins them by farthest point sampling.
    pub points: usize,
    /// Of the focus box's points, how many are first sampled within `gripper_radius_m` of
    /// the TCP, at the dense cloud's spacing instead of the whole scene's (0, the default:
    /// EquAct's plain split). A policy trained on clouds sampled this way needs them
    /// sampled the same way at run time.
    pub gripper_points: usize,
    /// Radius (m) of that ball around the TCP.
    pub gripper_radius_m: f64,
    /// Raise the focus box's floor to this height (m) above `workspace.table_height`, so its
    /// share of the points goes to the objects standing on the table instead of the table
    /// top (absent, the default: EquAct's box, whose floor is the table, -0.06 m). The table
    /// then gets the quarter sampled outside the box.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub focus_above_table_m: Option<f64>,
}

impl Default for PerceptionSection {
    fn default() -> Self {
        Self {
            points: DEFAULT_POLICY_POINTS,
            gripper_points: 0,
            gripper_radius_m: DEFAULT_GRIPPER_RADIUS_M,
            focus_above_table_m: None,
        }
    }
}

/// Points the fusion hands to the policy by default (EquAct's 2048).
pub const DEFAULT_POLICY_POINTS: usize = 2048;

/// Fewest points `[perception] points` accepts (the network's neighbour graphs need some).
pub const MIN_POLICY_POINTS: usize = 64;

/// Most points `[perception] points` accepts.
pub const MAX_POLICY_POINTS: usize = 16384;

impl PerceptionSection {
    /// How many of [`Self::points`] are sampled in the focus box: three quarters, EquAct's
    /// split (1536 of 2048).
    pub fn points_inside(&self) -> usize {
        self.points * 3 / 4
    }
}

impl std::fmt::Display for PerceptionSection {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(
            f,
            "points = {}, gripper_points = {} (radius {} m), ",
            self.points, self.gripper_points, self.gripper_radius_m
        )?;
        match self.focus_above_table_m {
            Some(h) => write!(f, "focus_above_table_m = {h}"),
            None => write!(f, "focus box from the table (EquAct's)"),
        }
    }
}

/// D455 depth stream modes.
#[derive(Copy, Clone, Debug, PartialEq, Eq, Serialize, Deserialize)]
pub enum DepthMode {
    /// 848×480, the recommended depth mode.
    #[serde(rename = "848x480")]
    W848H480,
    /// 1280×720.
    #[serde(rename = "1280x720")]
    W1280H720,
    /// 640×480 (VGA).
    #[serde(rename = "640x480")]
    W640H480,
}

impl DepthMode {
    /// Width and height in pixels.
    pub fn size(self) -> (u32, u32) {
        match self {
            DepthMode::W848H480 => (848, 480),
            DepthMode::W1280H720 => (1280, 720),
            DepthMode::W640H480 => (640, 480),
        }
    }
}

/// Pinhole intrinsics (pixels) overriding the factory values.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct IntrinsicsOverride {
    /// Focal length x.
    pub fx: f64,
    /// Focal length y.
    pub fy: f64,
    /// Principal point x.
    pub ppx: f64,
    /// Principal point y.
    pub ppy: f64,
}

/// `[[cameras]]`: one D455.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct CameraSection {
    /// Name used in recordings and the calibration file (e.g. `front`).
    pub name: String,
    /// Device serial number (the simulator accepts any non-empty text).
    pub serial: String,
    /// Depth mode.
    pub mode: DepthMode,
    /// Frame rate (Hz).
    pub fps: u32,
    /// Intrinsics to use instead of the device's factory calibration.
    #[serde(default)]
    pub intrinsics: Option<IntrinsicsOverride>,
    /// Roughly where the camera is (base frame, m; a tape measure is enough): the first
    /// calibration plans board poses the camera can see from it.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub approx_position: Option<[f64; 3]>,
    /// Roughly the point the camera looks at (base frame, m), with `approx_position`.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub approx_look_at: Option<[f64; 3]>,
    /// Also stream colour (RGB8 at the depth mode's size, aligned to depth by librealsense):
    /// the fused cloud then carries colour. Off by default (depth and IR only).
    #[serde(default, skip_serializing_if = "std::ops::Not::not")]
    pub colour: bool,
}

/// `[calibration]`: where the camera extrinsics come from.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct CalibrationSection {
    /// Path of `calibration.toml` (relative to the config file); empty in simulation means
    /// the simulator's true camera poses.
    pub file: String,
    /// The target on the flange (default: a chessboard of 7 x 10 inner corners, 35 mm
    /// squares).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub board: Option<BoardSection>,
}

/// What kind of calibration target is printed: it sets the corner layout and the detector.
#[derive(Copy, Clone, Debug, PartialEq, Eq, Serialize, Deserialize, Default)]
#[serde(rename_all = "snake_case")]
pub enum BoardKind {
    /// A plain chessboard: corners are its inner corners; the whole board must be in view.
    #[default]
    Chessboard,
    /// A Kalibr AprilGrid of tag36h11 tags: corners are the tag corners, each tag names its
    /// own four, so partial views count.
    AprilGrid,
}

/// Tags in the tag36h11 family (the most an AprilGrid can hold).
pub const TAG36H11_CODES: u32 = 587;

/// AprilGrid tag spacings (gap / tag size) the detector finds boards with: the `aprilgrid`
/// crate's grid search assumes Kalibr's 0.3 and tolerates 0.25 to 0.4 in the calibration
/// crate's rendered-board tests (0.2 fails).
pub const TAG_SPACING_RANGE: std::ops::RangeInclusive<f64> = 0.25..=0.4;

/// `[calibration.board]`: the printed target mounted on the tool flange.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct BoardSection {
    /// `"chessboard"` (default) or `"april_grid"` (Kalibr's layout, tag36h11).
    #[serde(default)]
    pub kind: BoardKind,
    /// Chessboard: inner-corner rows; AprilGrid: tag rows.
    pub rows: u32,
    /// Chessboard: inner-corner columns; AprilGrid: tag columns.
    pub cols: u32,
    /// Chessboard: square size; AprilGrid: tag size, black border included; as printed and
    /// measured (mm).
    pub square_mm: f64,
    /// AprilGrid only: gap between tags as a fraction of the tag size (Kalibr's
    /// `tagSpacing`; default 0.3).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub spacing: Option<f64>,
}

/// `[recording]`: where episode recordings go.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct RecordingSection {
    /// Folder for MCAP files (relative to the working directory).
    pub dir: String,
}

/// A validated cell configuration.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct CellConfig {
    /// The arm.
    pub robot: RobotSection,
    /// Joint limits.
    pub limits: LimitsSection,
    /// The gripper.
    pub gripper: GripperSection,
    /// Workspace bounds.
    pub workspace: WorkspaceSection,
    /// The depth cameras.
    pub cameras: Vec<CameraSection>,
    /// Camera calibration.
    pub calibration: CalibrationSection,
    /// Recording.
    pub recording: RecordingSection,
    /// Sampling of the fused cloud (optional; defaults to EquAct's).
    #[serde(default)]
    pub perception: PerceptionSection,
}

impl CellConfig {
    /// The built-in simulated cell.
    pub fn simulated() -> Result<Self, ConfigError> {
        Self::from_toml_str(SIMULATED_CELL_TOML, "the built-in simulated cell")
    }

    /// Reads and validates a `cell.toml` file.
    pub fn load(path: &Path) -> Result<Self, ConfigError> {
        let text = std::fs::read_to_string(path).map_err(|source| ConfigError::Read {
            path: path.to_path_buf(),
            source,
        })?;
        Self::from_toml_str(&text, &path.display().to_string())
    }

    /// Parses and validates configuration text; `origin` names it in errors.
    pub fn from_toml_str(text: &str, origin: &str) -> Result<Self, ConfigError> {
        let cfg: CellConfig = toml::from_str(text).map_err(|e| ConfigError::Parse {
            origin: origin.to_string(),
            message: e.to_string(),
        })?;
        cfg.validate()?;
        Ok(cfg)
    }

    /// Renders the configuration back to TOML.
    pub fn to_toml_string(&self) -> Result<String, ConfigError> {
        toml::to_string_pretty(self).map_err(|e| ConfigError::Parse {
            origin: "the configuration being written".into(),
            message: e.to_string(),
        })
    }

    /// Checks every value; the first problem found is returned.
    pub fn validate(&self) -> Result<(), ConfigError> {
        let r = &self.robot;
        if r.host.trim().is_empty() {
            return invalid(
                "robot.host",
                "\"\"",
                "give the controller's address, e.g. 192.168.1.10",
            );
        }
        if r.backend == RobotBackend::Ur {
            for (key, port) in [
                ("robot.rtde_port", r.rtde_port),
                ("robot.dashboard_port", r.dashboard_port),
                ("robot.secondary_port", r.secondary_port),
            ] {
                if port == 0 {
                    return invalid(key, "0", "a real controller needs its real port (RTDE 30004, dashboard 29999, secondary 30002)");
                }
            }
        }
        let max_rate = r.model.max_rate_hz();
        if !(r.controller_rate_hz.is_finite()
            && r.controller_rate_hz > 0.0
            && r.controller_rate_hz <= max_rate)
        {
            return invalid(
                "robot.controller_rate_hz",
                &r.controller_rate_hz.to_string(),
                &format!("must be in (0, {max_rate}] Hz for this robot model"),
            );
        }
        positive_finite("robot.tcp_offset_m", r.tcp_offset_m, true)?;
        if !(1..=MAX_LOST_CYCLES).contains(&r.lost_cycles) {
            return invalid(
                "robot.lost_cycles",
                &r.lost_cycles.to_string(),
                &format!(
                    "must be 1 to {MAX_LOST_CYCLES} control cycles; leave it at \
                     {DEFAULT_LOST_CYCLES} on a real controller and raise it only for a \
                     simulated controller on a loaded machine"
                ),
            );
        }
        if r.realtime_priority > MAX_REALTIME_PRIORITY {
            return invalid(
                "robot.realtime_priority",
                &r.realtime_priority.to_string(),
                &format!(
                    "must be a SCHED_FIFO priority, 1 to {MAX_REALTIME_PRIORITY}, or 0 for \
                     normal priority"
                ),
            );
        }

        let l = &self.limits;
        for (name, arr) in [
            ("limits.max_velocity", &l.max_velocity),
            ("limits.max_acceleration", &l.max_acceleration),
            ("limits.max_jerk", &l.max_jerk),
        ] {
            for (j, v) in arr.iter().enumerate() {
                positive_finite(&format!("{name}[{j}]"), *v, false)?;
            }
        }
        for (j, v) in l.max_velocity.iter().enumerate() {
            if *v > UR5_MAX_JOINT_SPEED + 1e-3 {
                return invalid(
                    &format!("limits.max_velocity[{j}]"),
                    &v.to_string(),
                    "exceeds the UR5's joint speed limit of pi rad/s",
                );
            }
        }
        for j in 0..JOINT_COUNT {
            let (lo, hi) = (l.joint_min[j], l.joint_max[j]);
            if !(lo.is_finite() && hi.is_finite() && lo < hi) {
                return invalid(
                    &format!("limits.joint_min[{j}]"),
                    &lo.to_string(),
                    &format!("must be finite and below limits.joint_max[{j}] = {hi}"),
                );
            }
            if lo < -2.0 * std::f64::consts::TAU || hi > 2.0 * std::f64::consts::TAU {
                return invalid(
                    &format!("limits.joint_min[{j}]"),
                    &format!("[{lo}, {hi}]"),
                    "joint limits beyond ±4π are not physical for a UR arm",
                );
            }
        }
        positive_finite("limits.tracking_error_bound", l.tracking_error_bound, false)?;
        positive_finite("limits.stop_deceleration", l.stop_deceleration, false)?;

        let g = &self.gripper;
        positive_finite("gripper.default_speed", g.default_speed, false)?;
        positive_finite("gripper.default_force", g.default_force, false)?;
        match g.transport {
            GripperTransport::ModbusRtu
            | GripperTransport::CanSlcan
            | GripperTransport::Socketcan
                if g.device.trim().is_empty() =>
            {
                return invalid(
                    "gripper.device",
                    "\"\"",
                    "this transport needs a device, e.g. /dev/ttyUSB0 (serial) or can0 (SocketCAN)",
                );
            }
            GripperTransport::Urcap if g.port == 0 => {
                return invalid("gripper.port", "0", "the URCap socket listens on 63352");
            }
            _ => {}
        }
        if g.can_command_id > 0x1FFF_FFFF || g.can_status_id > 0x1FFF_FFFF {
            return invalid(
                "gripper.can_command_id",
                &format!("{:#x}/{:#x}", g.can_command_id, g.can_status_id),
                "CAN ids must fit in 29 bits",
            );
        }

        let w = &self.workspace;
        for i in 0..3 {
            let axis = ["x", "y", "z"][i];
            if !(w.min[i].is_finite() && w.max[i].is_finite()) {
                return invalid(
                    &format!("workspace.min[{i}]"),
                    &w.min[i].to_string(),
                    "must be finite",
                );
            }
            if w.min[i] >= w.max[i] {
                return invalid(
                    &format!("workspace.min[{i}]"),
                    &w.min[i].to_string(),
                    &format!(
                        "workspace min {axis} must be below max {axis} = {}",
                        w.max[i]
                    ),
                );
            }
        }
        if !w.table_height.is_finite() {
            return invalid(
                "workspace.table_height",
                &w.table_height.to_string(),
                "must be finite",
            );
        }
        let pc = &self.perception;
        if !(MIN_POLICY_POINTS..=MAX_POLICY_POINTS).contains(&pc.points) {
            return invalid(
                "perception.points",
                &pc.points.to_string(),
                &format!(
                    "use {MIN_POLICY_POINTS}..={MAX_POLICY_POINTS} points (2048, EquAct's, \
                     when in doubt)"
                ),
            );
        }
        if pc.gripper_points > pc.points_inside() {
            return invalid(
                "perception.gripper_points",
                &pc.gripper_points.to_string(),
                &format!(
                    "at most the {} points of the focus box (three quarters of \
                     perception.points; 0 turns it off)",
                    pc.points_inside()
                ),
            );
        }
        if !(pc.gripper_radius_m.is_finite() && pc.gripper_radius_m > 0.0) {
            return invalid(
                "perception.gripper_radius_m",
                &pc.gripper_radius_m.to_string(),
                "use a positive radius in metres, e.g. 0.08",
            );
        }
        if let Some(h) = pc.focus_above_table_m {
            let room = w.max[2] - w.table_height;
            if !(h.is_finite() && h >= 0.0 && h < room) {
                return invalid(
                    "perception.focus_above_table_m",
                    &h.to_string(),
                    &format!(
                        "use a height in metres from 0 to below the workspace's top ({room:.2} m \
                         above the table), e.g. 0.01"
                    ),
                );
            }
        }

        if self.cameras.is_empty() {
            return invalid("cameras", "[]", "list at least one [[cameras]] entry");
        }
        for (i, c) in self.cameras.iter().enumerate() {
            if c.name.trim().is_empty() {
                return invalid(
                    &format!("cameras[{i}].name"),
                    "\"\"",
                    "give each camera a name, e.g. front",
                );
            }
            if c.serial.trim().is_empty() {
                return invalid(
                    &format!("cameras[{i}].serial"),
                    "\"\"",
                    &format!("camera `{}` needs its serial number (printed on the device; `rs-enumerate-devices` lists it)", c.name),
                );
            }
            if self.cameras[..i].iter().any(|o| o.name == c.name) {
                return invalid(
                    &format!("cameras[{i}].name"),
                    &c.name,
                    "camera names must be unique",
                );
            }
            if self.cameras[..i].iter().any(|o| o.serial == c.serial) {
                return invalid(
                    &format!("cameras[{i}].serial"),
                    &c.serial,
                    "two cameras share this serial",
                );
            }
            if !(1..=90).contains(&c.fps) {
                return invalid(
                    &format!("cameras[{i}].fps"),
                    &c.fps.to_string(),
                    "the D455 streams depth at 5 to 90 fps",
                );
            }
            if let Some(k) = &c.intrinsics {
                for (key, v) in [("fx", k.fx), ("fy", k.fy), ("ppx", k.ppx), ("ppy", k.ppy)] {
                    positive_finite(&format!("cameras[{i}].intrinsics.{key}"), v, false)?;
                }
            }
            match (c.approx_position, c.approx_look_at) {
                (None, None) => {}
                (Some(p), Some(t)) => {
                    if !p.iter().chain(t.iter()).all(|v| v.is_finite()) {
                        return invalid(
                            &format!("cameras[{i}].approx_position"),
                            &format!("{p:?} -> {t:?}"),
                            "approximate camera placement must be finite (m)",
                        );
                    }
                    let d = (0..3).map(|k| (t[k] - p[k]).powi(2)).sum::<f64>().sqrt();
                    if d < 0.1 {
                        return invalid(
                            &format!("cameras[{i}].approx_look_at"),
                            &format!("{t:?}"),
                            "the look-at point must be at least 0.1 m from the camera's position",
                        );
                    }
                }
                _ => {
                    return invalid(
                        &format!("cameras[{i}].approx_position"),
                        "only one of approx_position / approx_look_at",
                        "give both (base frame, m) or neither",
                    )
                }
            }
        }
        if let Some(b) = &self.calibration.board {
            match b.kind {
                BoardKind::Chessboard => {
                    if b.rows < 3 || b.cols < 3 || b.rows > 64 || b.cols > 64 {
                        return invalid(
                            "calibration.board",
                            &format!("{} x {}", b.rows, b.cols),
                            "a chessboard has 3 to 64 inner corners per side",
                        );
                    }
                    if (b.rows + b.cols) % 2 == 0 {
                        return invalid(
                            "calibration.board",
                            &format!("{} x {}", b.rows, b.cols),
                            "rows + cols must be odd, so that the board's half-turn can be told apart",
                        );
                    }
                    if b.spacing.is_some() {
                        return invalid(
                            "calibration.board.spacing",
                            "set",
                            "spacing is for kind = \"april_grid\"; remove it for a chessboard",
                        );
                    }
                }
                BoardKind::AprilGrid => {
                    if b.rows < 1
                        || b.cols < 2
                        || u64::from(b.rows) * u64::from(b.cols) > u64::from(TAG36H11_CODES)
                    {
                        return invalid(
                            "calibration.board",
                            &format!("{} x {} tags", b.rows, b.cols),
                            &format!(
                                "an AprilGrid has at least 1 x 2 and at most {TAG36H11_CODES} tag36h11 tags"
                            ),
                        );
                    }
                    if let Some(g) = b.spacing {
                        if !(g.is_finite() && TAG_SPACING_RANGE.contains(&g)) {
                            return invalid(
                                "calibration.board.spacing",
                                &g.to_string(),
                                &format!(
                                    "the gap between tags, as a fraction of the tag size, must be in {TAG_SPACING_RANGE:?} (Kalibr's default 0.3)"
                                ),
                            );
                        }
                    }
                }
            }
            positive_finite("calibration.board.square_mm", b.square_mm, false)?;
        }
        if self.robot.backend == RobotBackend::Ur && self.calibration.file.trim().is_empty() {
            return invalid(
                "calibration.file",
                "\"\"",
                "a real cell needs a calibration file: run `equact calibrate` and name its calibration.toml here",
            );
        }
        if self.recording.dir.trim().is_empty() {
            return invalid(
                "recording.dir",
                "\"\"",
                "name a folder for recordings, e.g. recordings",
            );
        }
        Ok(())
    }

    /// The controller period (s).
    pub fn controller_period(&self) -> f64 {
        1.0 / self.robot.controller_rate_hz
    }

    /// The recording folder.
    pub fn recording_dir(&self) -> PathBuf {
        PathBuf::from(&self.recording.dir)
    }
}

fn invalid(key: &str, value: &str, problem: &str) -> Result<(), ConfigError> {
    Err(ConfigError::Invalid {
        key: key.to_string(),
        value: value.to_string(),
        problem: problem.to_string(),
    })
}

fn positive_finite(key: &str, v: f64, allow_zero: bool) -> Result<(), ConfigError> {
    let ok = v.is_finite() && (v > 0.0 || (allow_zero && v == 0.0));
    if ok {
        Ok(())
    } else {
        invalid(
            key,
            &v.to_string(),
            if allow_zero {
                "must be a finite number, zero or more"
            } else {
                "must be a finite number above zero"
            },
        )
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn sim_text() -> String {
        SIMULATED_CELL_TOML.to_string()
    }

    fn expect_invalid(text: &str, key: &str) -> String {
        match CellConfig::from_toml_str(text, "test") {
            Err(ConfigError::Invalid {
                key: k, problem, ..
            }) => {
                assert_eq!(k, key, "wrong key blamed: {problem}");
                problem
            }
            other => panic!("expected Invalid for {key}, got {other:?}"),
        }
    }

    #[test]
    fn builtin_simulated_cell_is_valid_and_round_trips() {
        let cfg = CellConfig::simulated().unwrap();
        assert_eq!(cfg.cameras.len(), 3);
        assert_eq!(cfg.robot.backend, RobotBackend::Sim);
        let text = cfg.to_toml_string().unwrap();
        let again = CellConfig::from_toml_str(&text, "round trip").unwrap();
        assert_eq!(cfg, again);
        assert!((cfg.controller_period() - 0.008).abs() < 1e-12);
    }

    #[test]
    fn unknown_key_is_named() {
        let text = sim_text().replace("[robot]\n", "[robot]\nspeed_scale = 0.5\n");
        match CellConfig::from_toml_str(&text, "cell.toml") {
            Err(ConfigError::Parse { message, origin }) => {
                assert!(message.contains("speed_scale"), "{message}");
                assert_eq!(origin, "cell.toml");
            }
            other => panic!("expected Parse error, got {other:?}"),
        }
    }

    #[test]
    fn missing_key_is_named() {
        let text = sim_text().replace("tcp_offset_m = 0.15", "");
        match CellConfig::from_toml_str(&text, "cell.toml") {
            Err(ConfigError::Parse { message, .. }) => {
                assert!(message.contains("tcp_offset_m"), "{message}")
            }
            other => panic!("expected Parse error, got {other:?}"),
        }
    }

    #[test]
    fn lost_cycles_defaults_to_three_and_is_bounded() {
        let cfg = CellConfig::from_toml_str(&sim_text(), "test").unwrap();
        assert_eq!(cfg.robot.lost_cycles, DEFAULT_LOST_CYCLES);
        let raised = sim_text().replace("[robot]\n", "[robot]\nlost_cycles = 25\n");
        let cfg = CellConfig::from_toml_str(&raised, "test").unwrap();
        assert_eq!(cfg.robot.lost_cycles, 25);
        for bad in ["0", "26"] {
            let text = sim_text().replace("[robot]\n", &format!("[robot]\nlost_cycles = {bad}\n"));
            let p = expect_invalid(&text, "robot.lost_cycles");
            assert!(p.contains("real controller"), "{p}");
        }
    }

    #[test]
    fn realtime_priority_defaults_to_80_and_is_a_fifo_priority_or_off() {
        let cfg = CellConfig::from_toml_str(&sim_text(), "test").unwrap();
        assert_eq!(cfg.robot.realtime_priority, DEFAULT_REALTIME_PRIORITY);
        assert_eq!(cfg.robot.fifo_priority(), Some(DEFAULT_REALTIME_PRIORITY));
        let off = sim_text().replace("[robot]\n", "[robot]\nrealtime_priority = 0\n");
        let cfg = CellConfig::from_toml_str(&off, "test").unwrap();
        assert_eq!(cfg.robot.realtime_priority, 0);
        assert_eq!(cfg.robot.fifo_priority(), None);
        let bad = sim_text().replace("[robot]\n", "[robot]\nrealtime_priority = 100\n");
        let p = expect_invalid(&bad, "robot.realtime_priority");
        assert!(p.contains("1 to 99"), "{p}");
    }

    #[test]
    fn perception_section_is_optional_and_checked() {
        let cfg = CellConfig::from_toml_str(&sim_text(), "test").unwrap();
        assert_eq!(cfg.perception, PerceptionSection::default());
        assert_eq!(cfg.perception.gripper_points, 0);
        let set = format!("{}\n[perception]\ngripper_points = 256\n", sim_text());
        let cfg = CellConfig::from_toml_str(&set, "test").unwrap();
        assert_eq!(cfg.perception.gripper_points, 256);
        assert_eq!(cfg.perception.gripper_radius_m, 0.08);
        let text = format!("{}\n[perception]\ngripper_points = 2000\n", sim_text());
        expect_invalid(&text, "perception.gripper_points");
        let text = format!("{}\n[perception]\ngripper_radius_m = -0.1\n", sim_text());
        expect_invalid(&text, "perception.gripper_radius_m");
        assert_eq!(cfg.perception.points, 2048);
        assert_eq!(cfg.perception.points_inside(), 1536);
        assert_eq!(cfg.perception.focus_above_table_m, None);
    }

    #[test]
    fn perception_points_and_focus_floor_are_checked() {
        let set = format!(
            "{}\n[perception]\npoints = 1024\nfocus_above_table_m = 0.01\n",
            sim_text()
        );
        let cfg = CellConfig::from_toml_str(&set, "test").unwrap();
        assert_eq!(cfg.perception.points, 1024);
        assert_eq!(cfg.perception.points_inside(), 768);
        assert_eq!(cfg.perception.focus_above_table_m, Some(0.01));
        assert!(cfg
            .perception
            .to_string()
            .contains("focus_above_table_m = 0.01"));
        // The focus box's share shrinks with the total: 1000 near the gripper no longer fit.
        let text = format!(
            "{}\n[perception]\npoints = 1024\ngripper_points = 1000\n",
            sim_text()
        );
        let p = expect_invalid(&text, "perception.gripper_points");
        assert!(p.contains("768"), "{p}");
        for bad in ["0", "63", "20000"] {
            let text = format!("{}\n[perception]\npoints = {bad}\n", sim_text());
            expect_invalid(&text, "perception.points");
        }
        for bad in ["-0.01", "0.7", "nan"] {
            let text = format!(
                "{}\n[perception]\nfocus_above_table_m = {bad}\n",
                sim_text()
            );
            expect_invalid(&text, "perception.focus_above_table_m");
        }
    }

    #[test]
    fn negative_limit_is_named() {
        let text = sim_text().replace(
            "max_acceleration = [5.0, 5.0, 5.0, 5.0, 5.0, 5.0]",
            "max_acceleration = [5.0, 5.0, -5.0, 5.0, 5.0, 5.0]",
        );
        let p = expect_invalid(&text, "limits.max_acceleration[2]");
        assert!(p.contains("above zero"));
    }

    #[test]
    fn velocity_above_ur5_limit_is_refused() {
        let text = sim_text().replace("max_velocity = [3.14159,", "max_velocity = [4.0,");
        expect_invalid(&text, "limits.max_velocity[0]");
    }

    #[test]
    fn approximate_camera_placement_and_board_are_checked() {
        let placed = sim_text().replace(
            "serial = \"sim-left\"",
            "serial = \"sim-left\"\napprox_position = [0.05, 0.6, 0.75]\napprox_look_at = [0.6, -0.05, -0.05]",
        );
        let cfg = CellConfig::from_toml_str(&placed, "test").unwrap();
        assert_eq!(cfg.cameras[1].approx_look_at, Some([0.6, -0.05, -0.05]));
        let half = sim_text().replace(
            "serial = \"sim-left\"",
            "serial = \"sim-left\"\napprox_position = [0.05, 0.6, 0.75]",
        );
        expect_invalid(&half, "cameras[1].approx_position");
        let same = placed.replace("[0.6, -0.05, -0.05]", "[0.05, 0.6, 0.7]");
        expect_invalid(&same, "cameras[1].approx_look_at");
        let board = format!(
            "{}\n[calibration.board]\nrows = 7\ncols = 9\nsquare_mm = 35.0\n",
            sim_text()
        );
        let p = expect_invalid(&board, "calibration.board");
        assert!(p.contains("odd"), "{p}");
        let ok = board.replace("cols = 9", "cols = 10");
        let cfg = CellConfig::from_toml_str(&ok, "test").unwrap();
        assert_eq!(cfg.calibration.board.map(|b| b.cols), Some(10));
        // An AprilGrid has no parity rule, but its gap must be a fraction of the tag.
        let grid = board.replace("rows = 7", "kind = \"april_grid\"\nrows = 3\nspacing = 0.3");
        let cfg = CellConfig::from_toml_str(&grid, "test").unwrap();
        let b = cfg.calibration.board.unwrap();
        assert_eq!(
            (b.kind, b.rows, b.cols, b.spacing),
            (BoardKind::AprilGrid, 3, 9, Some(0.3))
        );
        let wide = grid.replace("spacing = 0.3", "spacing = 3.0");
        expect_invalid(&wide, "calibration.board.spacing");
        let huge = grid.replace("rows = 3", "rows = 70");
        expect_invalid(&huge, "calibration.board");
        let chess_gap = ok.replace("rows = 7", "rows = 7\nspacing = 0.3");
        expect_invalid(&chess_gap, "calibration.board.spacing");
        let unknown = board.replace("rows = 7", "kind = \"charuco\"\nrows = 7");
        assert!(CellConfig::from_toml_str(&unknown, "test").is_err());
    }

    #[test]
    fn missing_camera_serial_is_named() {
        let text = sim_text().replace("serial = \"sim-left\"", "serial = \"\"");
        let p = expect_invalid(&text, "cameras[1].serial");
        assert!(p.contains("left_shoulder"), "{p}");
    }

    #[test]
    fn workspace_min_above_max_is_named() {
        let text = sim_text().replace("min = [0.18, -0.39, -0.10]", "min = [0.18, 0.5, -0.10]");
        let p = expect_invalid(&text, "workspace.min[1]");
        assert!(p.contains("below max y"), "{p}");
    }

    #[test]
    fn rate_above_controller_maximum_is_refused() {
        let text = sim_text().replace("controller_rate_hz = 125.0", "controller_rate_hz = 500.0");
        expect_invalid(&text, "robot.controller_rate_hz");
        let e_series = text.replace("model = \"ur5\"", "model = \"ur5e\"");
        assert!(CellConfig::from_toml_str(&e_series, "test").is_ok());
    }

    #[test]
    fn real_robot_needs_ports_and_calibration() {
        let text = sim_text().replace("backend = \"sim\"", "backend = \"ur\"");
        expect_invalid(&text, "robot.rtde_port");
        let with_ports = text
            .replace("rtde_port = 0", "rtde_port = 30004")
            .replace("dashboard_port = 0", "dashboard_port = 29999")
            .replace("secondary_port = 0", "secondary_port = 30002");
        let p = expect_invalid(&with_ports, "calibration.file");
        assert!(p.contains("equact calibrate"));
    }

    #[test]
    fn serial_gripper_needs_device() {
        let text = sim_text().replace("transport = \"sim\"", "transport = \"modbus_rtu\"");
        expect_invalid(&text, "gripper.device");
    }

    #[test]
    fn duplicate_camera_names_refused() {
        let text = sim_text().replace("name = \"left_shoulder\"", "name = \"front\"");
        expect_invalid(&text, "cameras[1].name");
    }

    #[test]
    fn unreadable_file_names_the_path() {
        let err = CellConfig::load(Path::new("/nonexistent/cell.toml")).unwrap_err();
        assert!(err.to_string().contains("/nonexistent/cell.toml"));
    }
}
