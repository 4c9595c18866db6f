//! `equact check`: the dry-run check of a cell before anything moves. It connects to the
//! UR controller and the gripper the configuration names, reads their state without
//! commanding motion, checks the calibration file and the workspace, and says per check
//! what is wrong and what to do. The cameras are opened through librealsense (loaded at run
//! time, `firmware_iface::realsense`): each configured serial must be connected and stream
//! at its mode, with intrinsics that agree with the calibration file's. Every check runs even when an earlier one fails, so one
//! pass lists everything to fix.

use std::net::{IpAddr, SocketAddr, ToSocketAddrs};
use std::path::Path;
use std::sync::Arc;

use calibration::CellCalibration;
use cell_types::config::{CameraSection, CellConfig, GripperTransport, RobotModel};
use cell_types::{Clock, Transform};
use firmware_iface::arm::{Arm, ArmError, JointLimits};
use firmware_iface::dashboard::{RobotMode, SafetyMode};
use firmware_iface::gripper::RobotiqGripper;
use firmware_iface::realsense::{self, RealSenseCamera, RealSenseError, StreamIntrinsics};
use firmware_iface::realtime::Scheduling;
use firmware_iface::ur::{UrArm, UrConfig, UrPorts};
use nalgebra::{Isometry3, Translation3, UnitQuaternion, Vector3};

/// The result of one check.
#[derive(Clone, Debug, PartialEq)]
pub struct Check {
    /// Short name (`controller`, `gripper`, ...).
    pub name: &'static str,
    /// Whether it passed (a warning passes).
    pub passed: bool,
    /// A passed check with something the operator should know.
    pub warning: bool,
    /// What was found.
    pub detail: String,
    /// What to do when it failed (empty when it passed).
    pub fix: String,
}

impl Check {
    fn pass(name: &'static str, detail: impl Into<String>) -> Self {
        Self {
            name,
            passed: true,
            warning: false,
            detail: detail.into(),
            fix: String::new(),
        }
    }

    fn warn(name: &'static str, detail: impl Into<String>, fix: impl Into<String>) -> Self {
        Self {
            name,
            passed: true,
            warning: true,
            detail: detail.into(),
            fix: fix.into(),
        }
    }

    fn fail(name: &'static str, detail: impl Into<String>, fix: impl Into<String>) -> Self {
        Self {
            name,
            passed: false,
            warning: false,
            detail: detail.into(),
            fix: fix.into(),
        }
    }
}

/// The controller address of the configuration (a name is resolved once).
pub fn controller_ip(cfg: &CellConfig) -> Result<IpAddr, String> {
    if let Ok(ip) = cfg.robot.host.parse::<IpAddr>() {
        return Ok(ip);
    }
    (cfg.robot.host.as_str(), cfg.robot.rtde_port)
        .to_socket_addrs()
        .ok()
        .and_then(|mut a| a.next())
        .map(|a| a.ip())
        .ok_or_else(|| format!("robot.host `{}` does not resolve", cfg.robot.host))
}

/// Driver settings from the configuration: address, ports, limits, tracking bound, stop
/// deceleration and lost-cycle watchdog; everything else keeps the driver's real-robot defaults.
pub fn ur_config(cfg: &CellConfig) -> Result<UrConfig, String> {
    Ok(UrConfig {
        host: controller_ip(cfg)?,
        ports: UrPorts {
            rtde: cfg.robot.rtde_port,
            dashboard: cfg.robot.dashboard_port,
            secondary: cfg.robot.secondary_port,
        },
        tracking_bound: cfg.limits.tracking_error_bound,
        stop_decel: cfg.limits.stop_deceleration,
        limits: JointLimits {
            min: cfg.limits.joint_min,
            max: cfg.limits.joint_max,
            max_speed: cfg.limits.max_velocity,
        },
        lost_cycles: cfg.robot.lost_cycles,
        realtime_priority: cfg.robot.fifo_priority(),
        ..UrConfig::default()
    })
}

/// Whether the driver's link thread got the real-time priority the config asked for.
fn scheduling_check(s: &Scheduling) -> Check {
    const NAME: &str = "driver thread";
    match s {
        Scheduling::Fifo(_) | Scheduling::Normal => Check::pass(NAME, s.to_string()),
        Scheduling::Refused { .. } => Check::warn(
            NAME,
            s.to_string(),
            "on a busy machine a driver thread at normal priority can miss the controller's \
             cycles and have its motions stopped: grant this user real-time priorities, or \
             set robot.realtime_priority = 0 to stop asking",
        ),
    }
}

/// Runs every check; `config_dir` resolves a relative calibration file.
pub fn run_checks(cfg: &CellConfig, config_dir: &Path, clock: Arc<dyn Clock>) -> Vec<Check> {
    let mut checks = check_controller(cfg, clock.clone());
    checks.push(check_gripper(cfg, clock));
    let (check, calibration) = check_calibration(cfg, config_dir);
    checks.push(check);
    checks.push(check_workspace(cfg));
    checks.extend(check_cameras(cfg, calibration.as_ref()));
    checks
}

/// How far (px) a device's focal lengths and principal point may be from the calibration
/// file's before `equact check` fails: factory and calibrated values of one camera agree to
/// about a pixel; more means the file was made with another camera, mode or camera order.
pub const INTRINSICS_TOLERANCE_PX: f64 = 2.0;

/// The camera checks on the connected D455s: each configured serial is connected and
/// streams depth + IR (and colour where configured) at its mode and rate ("cameras"), and
/// its depth intrinsics agree with the calibration's camera model ("intrinsics", when the
/// calibration file was read).
pub fn check_cameras(cfg: &CellConfig, calibration: Option<&CellCalibration>) -> Vec<Check> {
    if let Err(e) = realsense::library() {
        return vec![Check::fail(
            "cameras",
            format!("{} D455 camera(s) configured: {e}", cfg.cameras.len()),
            "install librealsense2 on this machine (README, \"Cameras\"), or point \
             EQUACT_LIBREALSENSE at librealsense2.so",
        )];
    }
    check_camera_streams(cfg, calibration, &mut crate::real_cell::open_configured)
}

/// [`check_cameras`] with the cameras opened by `open` (a test plays recordings): camera
/// `i` is the config's `i`-th `[[cameras]]` entry.
pub fn check_camera_streams(
    cfg: &CellConfig,
    calibration: Option<&CellCalibration>,
    open: &mut dyn FnMut(u8, &CameraSection) -> Result<RealSenseCamera, RealSenseError>,
) -> Vec<Check> {
    let mut streams = Vec::new();
    let mut stream_fixes = Vec::new();
    let mut intrinsics = Vec::new();
    let mut intrinsics_fixes = Vec::new();
    let mut found: Option<Vec<String>> = None;
    for (i, c) in cfg.cameras.iter().enumerate() {
        let Ok(id) = u8::try_from(i) else {
            streams.push(format!("{}: more than 256 cameras", c.name));
            continue;
        };
        let (w, h) = c.mode.size();
        let mut cam = match open(id, c) {
            Ok(cam) => cam,
            Err(RealSenseError::NotConnected { serial, connected }) => {
                // Said once for all cameras below.
                found = Some(connected);
                streams.push(format!("{}: no D455 with serial {serial}", c.name));
                stream_fixes.push(format!(
                    "plug camera `{}` into a USB 3 port, or fix cameras[{i}].serial",
                    c.name
                ));
                continue;
            }
            Err(e) => {
                streams.push(format!("{} ({}): {e}", c.name, c.serial));
                stream_fixes.push(match e {
                    RealSenseError::Mode { .. } => format!(
                        "set cameras[{i}].mode/fps to a mode the D455 streams (848x480 at 30 fps)"
                    ),
                    _ => format!("replug camera `{}`", c.name),
                });
                continue;
            }
        };
        let d = *cam.depth_intrinsics();
        if (d.width, d.height) != (w, h) {
            streams.push(format!(
                "{} ({}): streams {}x{}, the config says {w}x{h}",
                c.name,
                cam.source(),
                d.width,
                d.height
            ));
            stream_fixes.push(format!("set cameras[{i}].mode"));
            continue;
        }
        match cam.next_frame() {
            Ok(f) => {
                let valid = f.depth.raw.data.iter().filter(|&&v| v > 0).count();
                streams.push(format!(
                    "{} ({}): {w}x{h} at {} fps, {:.0} % of the first frame has depth",
                    c.name,
                    cam.source(),
                    cam.fps(),
                    100.0 * valid as f64 / f.depth.raw.data.len().max(1) as f64
                ));
            }
            Err(e) => {
                streams.push(format!("{} ({}): {e}", c.name, cam.source()));
                stream_fixes.push(format!(
                    "camera `{}` opened but sent no frame: use a USB 3 port (not a hub shared \
                     with the other cameras) and replug it",
                    c.name
                ));
                continue;
            }
        }
        let Some(cal) = calibration else { continue };
        let Some(model) = cal.cameras.iter().find(|m| m.id == id) else {
            // The calibration check already names cameras without a pose.
            continue;
        };
        match compare_intrinsics(&d, &model.intrinsics, INTRINSICS_TOLERANCE_PX) {
            Ok(()) => intrinsics.push(format!(
                "{}: device and calibration agree within {INTRINSICS_TOLERANCE_PX} px",
                c.name
            )),
            Err(why) => {
                intrinsics.push(format!("{}: {why}", c.name));
                intrinsics_fixes.push(format!(
                    "recalibrate camera `{}` at {w}x{h} (`equact calibrate`), or check that \
                     [[cameras]] lists the cameras in the calibration's order",
                    c.name
                ));
            }
        }
    }
    if let Some(found) = found {
        streams.push(format!(
            "connected: {}",
            if found.is_empty() {
                "none".to_string()
            } else {
                found.join(", ")
            }
        ));
        stream_fixes.push("`rs-enumerate-devices` lists the connected serials".into());
    }
    let mut out = vec![if stream_fixes.is_empty() {
        Check::pass("cameras", streams.join("; "))
    } else {
        Check::fail("cameras", streams.join("; "), stream_fixes.join("; "))
    }];
    if !intrinsics.is_empty() {
        out.push(if intrinsics_fixes.is_empty() {
            Check::pass("intrinsics", intrinsics.join("; "))
        } else {
            Check::fail(
                "intrinsics",
                intrinsics.join("; "),
                intrinsics_fixes.join("; "),
            )
        });
    }
    out
}

/// Whether a device's depth intrinsics match a calibration camera model: same size, and
/// focal lengths and principal point within `tolerance_px`; the error names what differs.
pub fn compare_intrinsics(
    device: &StreamIntrinsics,
    model: &calibration::Intrinsics,
    tolerance_px: f64,
) -> Result<(), String> {
    if (device.width, device.height) != (model.width, model.height) {
        return Err(format!(
            "the device streams {}x{}, the calibration's model is {}x{}",
            device.width, device.height, model.width, model.height
        ));
    }
    let off: Vec<String> = [
        ("fx", device.fx, model.fx),
        ("fy", device.fy, model.fy),
        ("ppx", device.ppx, model.ppx),
        ("ppy", device.ppy, model.ppy),
    ]
    .iter()
    .filter(|(_, d, m)| (d - m).abs() > tolerance_px || !d.is_finite())
    .map(|(k, d, m)| format!("{k} {d:.2} (device) vs {m:.2} (calibration)"))
    .collect();
    if off.is_empty() {
        Ok(())
    } else {
        Err(format!(
            "{} differ by more than {tolerance_px} px",
            off.join(", ")
        ))
    }
}

fn check_controller(cfg: &CellConfig, clock: Arc<dyn Clock>) -> Vec<Check> {
    let ur = match ur_config(cfg) {
        Ok(c) => c,
        Err(e) => return vec![Check::fail("controller", e, "fix robot.host in the config")],
    };
    let addr = SocketAddr::new(ur.host, ur.ports.rtde);
    let arm = match UrArm::connect(ur, clock) {
        Ok(a) => a,
        Err(e) => {
            let fix = match &e {
                ArmError::PoweredOff => {
                    "power the arm on and release the brakes on the teach pendant".to_string()
                }
                _ => format!(
                    "check the cable and address ({addr}), that the controller is in remote \
                     control, and that no other program holds the RTDE inputs"
                ),
            };
            return vec![Check::fail("controller", e.to_string(), fix)];
        }
    };
    let mut out = Vec::new();
    let rate = 1.0 / arm.period();
    let v = arm.controller();
    let series = match cfg.robot.model {
        RobotModel::Ur5 => 3,
        RobotModel::Ur5e => 5,
    };
    let detail = format!(
        "controller {}.{}.{}, RTDE {:?} at {rate:.0} Hz",
        v.major,
        v.minor,
        v.bugfix,
        arm.protocol()
    );
    if v.major != series || (rate - cfg.robot.controller_rate_hz).abs() > 1.0 {
        out.push(Check::fail(
            "controller",
            format!(
                "{detail}; the config says {:?} at {} Hz",
                cfg.robot.model, cfg.robot.controller_rate_hz
            ),
            "set robot.model and robot.controller_rate_hz to the controller you have",
        ));
    } else {
        out.push(Check::pass("controller", detail));
    }
    out.push(scheduling_check(arm.scheduling()));
    match arm.state() {
        Ok(s) => {
            if s.robot_mode == RobotMode::Running && s.safety_mode == SafetyMode::Normal {
                out.push(Check::pass("safety", "RUNNING, NORMAL"));
            } else {
                out.push(Check::fail(
                    "safety",
                    format!("robot {:?}, safety {:?}", s.robot_mode, s.safety_mode),
                    "clear the stop on the teach pendant (a protective stop unlocks after 5 s), \
                     power on and release the brakes",
                ));
            }
            let q = s.joints.position;
            let outside: Vec<String> = (0..6)
                .filter(|&j| q[j] < cfg.limits.joint_min[j] || q[j] > cfg.limits.joint_max[j])
                .map(|j| format!("joint {} at {:.3} rad", j + 1, q[j]))
                .collect();
            if outside.is_empty() {
                out.push(Check::pass(
                    "joints",
                    format!("within the configured limits: {q:.3?}"),
                ));
            } else {
                out.push(Check::fail(
                    "joints",
                    format!("outside the configured limits: {}", outside.join(", ")),
                    "jog the arm back inside limits.joint_min/max with the teach pendant",
                ));
            }
        }
        Err(e) => out.push(Check::fail(
            "safety",
            e.to_string(),
            "the RTDE link dropped; check the network",
        )),
    }
    out
}

fn check_gripper(cfg: &CellConfig, clock: Arc<dyn Clock>) -> Check {
    let g = &cfg.gripper;
    let status = match g.transport {
        GripperTransport::Sim => {
            return Check::pass("gripper", "simulated (hil_sim emulator)");
        }
        GripperTransport::Urcap => RobotiqGripper::urcap((g.host.as_str(), g.port), clock)
            .and_then(|mut d| d.status_image().map(|s| d.to_state(&s))),
        GripperTransport::ModbusRtu => RobotiqGripper::modbus_rtu(&g.device, clock)
            .and_then(|mut d| d.status_image().map(|s| d.to_state(&s))),
        GripperTransport::CanSlcan => match crate::real_cell::can_mapping(cfg) {
            Ok(m) => RobotiqGripper::slcan(&g.device, m, clock)
                .and_then(|mut d| d.status_image().map(|s| d.to_state(&s))),
            Err(e) => return Check::fail("gripper", e, "fix gripper.can_*_id"),
        },
        GripperTransport::Socketcan => {
            return Check::fail(
                "gripper",
                "SocketCAN is only built with the `socketcan` feature of firmware_iface",
                "use can_slcan with a serial adapter, or build with --features socketcan",
            );
        }
    };
    match status {
        Ok(s) if s.fault.is_some() => Check::fail(
            "gripper",
            format!("reachable, but it reports fault {:?}", s.fault),
            "clear the fault (reset and activate the gripper) before running",
        ),
        Ok(s) => Check::pass(
            "gripper",
            format!(
                "{:?}: activated {}, opening {:.1} mm",
                g.transport,
                s.activated,
                s.width_m * 1e3
            ),
        ),
        Err(e) => Check::fail(
            "gripper",
            e.to_string(),
            format!(
                "check gripper.transport ({:?}) and its address or device",
                g.transport
            ),
        ),
    }
}

fn check_calibration(cfg: &CellConfig, config_dir: &Path) -> (Check, Option<CellCalibration>) {
    if cfg.calibration.file.is_empty() {
        return (
            Check::fail(
                "calibration",
                "no calibration.file in the config",
                "calibrate the cameras (`equact calibrate`) and name the file in [calibration]",
            ),
            None,
        );
    }
    let path = config_dir.join(&cfg.calibration.file);
    let calibration = match calibration::read_calibration_toml(&path) {
        Ok(c) => c,
        Err(e) => {
            return (
                Check::fail(
                    "calibration",
                    e.to_string(),
                    "calibrate the cameras (`equact calibrate solve`) or fix calibration.file",
                ),
                None,
            )
        }
    };
    // Cameras are numbered by their order in the config's [[cameras]] list.
    let missing = crate::real_cell::cameras_without_pose(cfg, &calibration);
    let known: Vec<u8> = (0..cfg.cameras.len())
        .filter_map(|i| u8::try_from(i).ok())
        .collect();
    if let Err(e) = calibration.validate_against(&known) {
        return (
            Check::fail(
                "calibration",
                format!("{}: {e}", path.display()),
                "recalibrate with the cameras the config lists, in its order",
            ),
            None,
        );
    }
    let check = if missing.is_empty() {
        Check::pass(
            "calibration",
            format!(
                "{}: a pose for each of the {} cameras",
                path.display(),
                cfg.cameras.len()
            ),
        )
    } else {
        Check::fail(
            "calibration",
            format!(
                "{} has no pose for camera(s) {}",
                path.display(),
                missing.join(", ")
            ),
            "recalibrate with every camera connected",
        )
    };
    (check, Some(calibration))
}

/// The corners of the workspace box with the gripper pointing down should be reachable; a
/// box larger than the arm's reach is only a warning (the box also crops the cloud, and
/// keyframes out of reach are refused by the planner with their own error).
fn check_workspace(cfg: &CellConfig) -> Check {
    let model = match crate::episode::planner_from_config(cfg) {
        Ok(p) => p.model,
        Err(e) => return Check::fail("workspace", format!("{e:#}"), "fix [robot] and [limits]"),
    };
    let (lo, hi) = (cfg.workspace.min, cfg.workspace.max);
    let down = UnitQuaternion::from_axis_angle(&Vector3::x_axis(), std::f64::consts::PI);
    let mut unreachable = Vec::new();
    for corner in 0..8 {
        let pick = |k: usize| if corner & (1 << k) != 0 { hi[k] } else { lo[k] };
        // Just above the table: the gripper cannot go below it anyway.
        let z = pick(2).max(cfg.workspace.table_height + 0.05);
        let pose = Isometry3::from_parts(Translation3::new(pick(0), pick(1), z), down);
        let ok = model
            .ik(&Transform::from_isometry(pose))
            .is_ok_and(|s| !s.is_empty());
        if !ok {
            unreachable.push(format!("[{:.2}, {:.2}, {:.2}]", pick(0), pick(1), z));
        }
    }
    if unreachable.is_empty() {
        Check::pass(
            "workspace",
            "every corner is reachable with the gripper pointing down",
        )
    } else {
        Check::warn(
            "workspace",
            format!(
                "corners not reachable gripper-down: {}",
                unreachable.join(" ")
            ),
            "keyframes there will be refused as unreachable; shrink [workspace] min/max to \
             what the arm reaches if the policy should not aim there",
        )
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn driver_config_takes_the_cells_limits_and_watchdog() {
        let mut cfg = CellConfig::simulated().unwrap();
        cfg.robot.lost_cycles = 7;
        cfg.limits.tracking_error_bound = 0.05;
        let ur = ur_config(&cfg).unwrap();
        assert_eq!(ur.lost_cycles, 7);
        assert_eq!(ur.tracking_bound, 0.05);
        assert_eq!(ur.limits.max_speed, cfg.limits.max_velocity);
        assert_eq!(ur.realtime_priority, Some(80));
        cfg.robot.realtime_priority = 0;
        assert_eq!(ur_config(&cfg).unwrap().realtime_priority, None);
    }

    #[test]
    fn a_refused_real_time_priority_is_a_warning_with_the_way_out() {
        let refused = Scheduling::Refused {
            priority: 80,
            why: "Operation not permitted (os error 1)".into(),
        };
        let c = scheduling_check(&refused);
        assert!(c.passed && c.warning, "{c:?}");
        assert!(
            c.detail
                .contains("priority 80 refused (Operation not permitted"),
            "{c:?}"
        );
        assert!(
            c.fix
                .contains("miss the controller's cycles and have its motions stopped: grant"),
            "{c:?}"
        );
        assert!(c.fix.contains("robot.realtime_priority = 0"), "{c:?}");
        let c = scheduling_check(&Scheduling::Fifo(80));
        assert!(c.passed && !c.warning && c.detail.contains("SCHED_FIFO priority 80"));
    }
}
