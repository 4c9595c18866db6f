//! The episode loop: capture → fuse → predict keyframe → plan → execute → gripper → repeat,
//! until the task reports done, the policy has nothing more, a fault, or the keyframe limit.
//!
//! Every arrow is recorded ([`crate::recording`]); the file is checkpointed after each step
//! and finished whatever happens, so an interrupted or faulted episode leaves a readable
//! recording whose outcome says what happened.

use std::collections::BTreeMap;
use std::path::PathBuf;
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::Arc;
use std::time::Instant;

use calibration::fusion::{FusionParams, FusionPipeline};
use calibration::CellCalibration;
use cell_types::config::CellConfig;
use cell_types::{Clock, GripperState, JointState, Joints, Keyframe, PointCloud};
use firmware_iface::arm::{Arm, ExecutionOutcome};
use firmware_iface::camera::DepthCamera;
use firmware_iface::gripper::Gripper;
use firmware_iface::ur::UrArm;
use nalgebra::{Point3, Vector3};
use planner::{CloudParams, Obstacle, Planner, PlannerConfig, PlannerLimits, RobotModel, World};
use serde_json::json;

use crate::recording::{self, EpisodeRecorder, LogLevel};
use crate::sim_cell::{SimCell, SimWorld};
use crate::task::world::GripperEvent;

/// Most keyframes one episode may take (the keyframe-policy literature's limit).
pub const MAX_KEYFRAMES: usize = 25;

/// Points this close above the table plane are the table's (m): 3 sigma of the D455's depth
/// noise at the cameras' range, plus a margin.
const TABLE_POINT_BAND: f64 = 0.012;

/// What the policy sees at one step.
pub struct Observation<'a> {
    /// The fused, sampled cloud in the base frame.
    pub cloud: &'a PointCloud,
    /// The arm's joints.
    pub joints: &'a JointState,
    /// The gripper's state.
    pub gripper: &'a GripperState,
    /// The language instruction.
    pub instruction: &'a str,
}

/// Anything that emits keyframes: the learned policy or a scripted expert.
pub trait KeyframeSource {
    /// The next keyframe, or `None` when the source considers the task done.
    fn next_keyframe(&mut self, obs: &Observation<'_>) -> anyhow::Result<Option<Keyframe>>;
    /// Another keyframe for the same observation, next in the source's own ranking, after
    /// the planner refused the last one (unreachable or in collision); `None` when the source
    /// has no more. A scripted source has none.
    fn alternative(&mut self) -> anyhow::Result<Option<Keyframe>> {
        Ok(None)
    }
    /// A name for logs and recordings.
    fn name(&self) -> &str;
}

/// The scripted expert: replays keyframes computed from the true object poses.
pub struct ScriptedExpert {
    keyframes: Vec<Keyframe>,
    next: usize,
}

impl ScriptedExpert {
    /// An expert that emits `keyframes` in order.
    pub fn new(keyframes: Vec<Keyframe>) -> Self {
        Self { keyframes, next: 0 }
    }
}

impl KeyframeSource for ScriptedExpert {
    fn next_keyframe(&mut self, _obs: &Observation<'_>) -> anyhow::Result<Option<Keyframe>> {
        let k = self.keyframes.get(self.next).copied();
        self.next += 1;
        Ok(k)
    }

    fn name(&self) -> &str {
        "expert"
    }
}

/// What the loop knows about the task besides the cameras: in the simulated cell the
/// simulator's truth (success test, grasp attachment); on a real cell only the instruction.
pub trait TaskMonitor {
    /// The language instruction of the episode.
    fn instruction(&self) -> String;
    /// Whether the task is done: `Some` where a success test exists (simulation), `None` on
    /// a real cell (the operator judges the outcome).
    fn success(&self) -> Option<bool>;
    /// Why the task can no longer succeed (simulation: a part it must leave in place has
    /// moved), which ends the episode; `None` while it still can, and always on a real cell.
    fn lost(&self) -> Option<String> {
        None
    }
    /// The arm moved to `q` with the fingers `opening` apart.
    fn update_robot(&mut self, _q: &Joints, _opening: f64) -> anyhow::Result<()> {
        Ok(())
    }
    /// The gripper is about to close at `q`.
    fn before_close(&mut self, _q: &Joints) {}
    /// The gripper finished moving at `q`; `holding` as the gripper reports. Returns what
    /// happened to an object where the cell knows (simulation: the roll released 14.2 mm
    /// from the spindle's axis, measured; its words in the log); `None` on a real cell.
    fn after_gripper(&mut self, _q: &Joints, _holding: bool) -> Option<GripperEvent> {
        None
    }
}

impl TaskMonitor for SimWorld {
    fn instruction(&self) -> String {
        self.task.kind.instruction()
    }
    fn success(&self) -> Option<bool> {
        Some(SimWorld::success(self))
    }
    fn lost(&self) -> Option<String> {
        SimWorld::lost(self)
    }
    fn update_robot(&mut self, q: &Joints, opening: f64) -> anyhow::Result<()> {
        SimWorld::update_robot(self, q, opening)
    }
    fn before_close(&mut self, q: &Joints) {
        SimWorld::before_close(self, q);
    }
    fn after_gripper(&mut self, q: &Joints, holding: bool) -> Option<GripperEvent> {
        SimWorld::after_gripper(self, q, holding)
    }
}

/// A real cell's task: only the instruction is known; success is the operator's call.
pub struct OperatorJudged {
    /// The language instruction.
    pub instruction: String,
}

impl TaskMonitor for OperatorJudged {
    fn instruction(&self) -> String {
        self.instruction.clone()
    }
    fn success(&self) -> Option<bool> {
        None
    }
}

/// The parts of a cell one episode drives, simulated or real: the UR driver, a gripper on
/// any transport, the depth cameras, their calibration and the task monitor.
pub struct CellIo<'a> {
    /// The UR driver (connected to a real controller or the simulated one).
    pub arm: &'a mut UrArm,
    /// The gripper driver.
    pub gripper: &'a mut dyn Gripper,
    /// The depth cameras.
    pub cameras: &'a mut [Box<dyn DepthCamera>],
    /// The cameras' calibration.
    pub calibration: &'a CellCalibration,
    /// What is known about the task.
    pub task: &'a mut dyn TaskMonitor,
}

impl<'a> CellIo<'a> {
    /// Borrows the simulated cell's parts.
    pub fn sim(cell: &'a mut SimCell) -> Self {
        Self {
            arm: &mut cell.arm,
            gripper: &mut cell.gripper,
            cameras: &mut cell.cameras,
            calibration: &cell.calibration,
            task: &mut cell.world,
        }
    }
}

/// How an episode ended.
#[derive(Clone, Debug, PartialEq, Eq)]
pub enum Outcome {
    /// The task's success test passed.
    Success,
    /// The policy finished (or the keyframe limit was hit) without the task being done.
    TaskNotDone,
    /// The task can no longer succeed (simulation: a part it must leave in place moved).
    TaskLost,
    /// A keyframe could not be planned; the arm stayed where it was.
    PlanFailed,
    /// The arm stopped during a motion (protective stop, tracking error, lost link, ...).
    ArmStopped,
    /// The gripper reported a fault or did not answer.
    GripperFault,
    /// A camera delivered no usable frame, or the fusion failed.
    PerceptionFault,
    /// Ctrl-C: the arm was stopped with a controlled deceleration.
    Interrupted,
    /// Anything else that ended the episode (policy error, recording error).
    Error,
}

impl Outcome {
    /// The outcome's name in recordings and on the terminal.
    pub fn label(&self) -> &'static str {
        match self {
            Outcome::Success => "success",
            Outcome::TaskNotDone => "task_not_done",
            Outcome::TaskLost => "task_lost",
            Outcome::PlanFailed => "plan_failed",
            Outcome::ArmStopped => "arm_stopped",
            Outcome::GripperFault => "gripper_fault",
            Outcome::PerceptionFault => "perception_fault",
            Outcome::Interrupted => "interrupted",
            Outcome::Error => "error",
        }
    }
}

/// What an episode did.
#[derive(Clone, Debug)]
pub struct EpisodeReport {
    /// How it ended.
    pub outcome: Outcome,
    /// Keyframes executed.
    pub steps: usize,
    /// What happened, in words.
    pub detail: String,
    /// What the gripper did to objects, measured, with the keyframe (index from 0) at which
    /// it happened; empty on a real cell, which cannot tell.
    pub gripper_events: Vec<(usize, GripperEvent)>,
    /// The recording.
    pub recording: PathBuf,
    /// Messages recorded per topic.
    pub counts: BTreeMap<&'static str, u64>,
}

/// The kinematic and collision model of the configured arm.
pub fn robot_model(cfg: &CellConfig) -> anyhow::Result<RobotModel> {
    Ok(match cfg.robot.model {
        cell_types::config::RobotModel::Ur5 => RobotModel::ur5()?,
        cell_types::config::RobotModel::Ur5e => RobotModel::ur5e()?,
    })
}

/// Builds the planner the cell's configuration asks for.
pub fn planner_from_config(cfg: &CellConfig) -> anyhow::Result<Planner> {
    let model = robot_model(cfg)?;
    let limits = PlannerLimits {
        max_velocity: cfg.limits.max_velocity,
        max_acceleration: cfg.limits.max_acceleration,
        max_jerk: cfg.limits.max_jerk,
        period: cfg.controller_period(),
    };
    Ok(Planner::new(model, limits, PlannerConfig::default())?)
}

/// Builds the fusion pipeline for the cell's workspace and `[perception]` section.
pub fn fusion_params(cfg: &CellConfig, seed: u64) -> FusionParams {
    let perception = &cfg.perception;
    let mut p = FusionParams {
        seed,
        points: perception.points,
        points_inside: perception.points_inside(),
        gripper_points: perception.gripper_points,
        gripper_radius_m: perception.gripper_radius_m,
        ..FusionParams::default()
    };
    p.workspace.min = cfg.workspace.min;
    p.workspace.max = cfg.workspace.max;
    if let Some(h) = perception.focus_above_table_m {
        p.focus.min[2] = cfg.workspace.table_height + h;
    }
    p
}

fn gripper_message(s: &GripperState) -> serde_json::Value {
    json!({
        "activated": s.activated,
        "width_m": s.width_m,
        "object": format!("{:?}", s.object),
        "current_a": s.current_a,
        "fault": s.fault.map(|f| format!("{f:?}")),
    })
}

fn ns(clock: &dyn Clock) -> u64 {
    u64::try_from(clock.now().as_nanos()).unwrap_or(u64::MAX)
}

/// Records every arm state the driver received since the last call, at the controller
/// rate: `/joint_states` and the TCP in `/tf` (from the controller's own `actual_TCP_pose`),
/// each at its receive time. A full driver log is reported on `/log`, not hidden.
fn record_arm_states(
    rec: &mut EpisodeRecorder,
    arm: &firmware_iface::ur::UrArm,
    buf: &mut Vec<(std::time::Duration, firmware_iface::arm::ArmState)>,
) -> anyhow::Result<()> {
    buf.clear();
    let dropped = arm.drain_states(buf);
    for (at, state) in buf.iter() {
        let t = u64::try_from(at.as_nanos()).unwrap_or(u64::MAX);
        rec.write(
            "/joint_states",
            t,
            &recording::joint_states_message(t, &state.joints),
        )?;
        let [x, y, z, rx, ry, rz] = state.tcp_pose;
        let pose = nalgebra::Isometry3::from_parts(
            nalgebra::Translation3::new(x, y, z),
            nalgebra::UnitQuaternion::from_scaled_axis(Vector3::new(rx, ry, rz)),
        );
        rec.write(
            "/tf",
            t,
            &json!({ "transforms": [recording::frame_transform(t, "base", "tcp", &pose)] }),
        )?;
    }
    if dropped > 0 {
        let t = buf.last().map_or(0, |(at, _)| {
            u64::try_from(at.as_nanos()).unwrap_or(u64::MAX)
        });
        rec.write(
            "/log",
            t,
            &recording::log_message(
                t,
                LogLevel::Warning,
                &format!("{dropped} arm states were not recorded: the driver's log was full"),
            ),
        )?;
    }
    Ok(())
}

/// Runs one episode in the simulated cell with `policy`, recording into `recorder`.
/// `interrupt` is set by Ctrl-C. Never returns with the arm moving.
pub fn run_sim_episode(
    cfg: &CellConfig,
    cell: &mut SimCell,
    policy: &mut dyn KeyframeSource,
    recorder: &mut EpisodeRecorder,
    interrupt: &Arc<AtomicBool>,
    clock: &dyn Clock,
    seed: u64,
) -> EpisodeReport {
    run_episode(
        cfg,
        CellIo::sim(cell),
        policy,
        recorder,
        interrupt,
        clock,
        seed,
    )
}

/// Runs one episode on any cell (see [`CellIo`]) with `policy`, recording into `recorder`.
/// `interrupt` is set by Ctrl-C. Never returns with the arm moving.
pub fn run_episode(
    cfg: &CellConfig,
    mut cell: CellIo<'_>,
    policy: &mut dyn KeyframeSource,
    recorder: &mut EpisodeRecorder,
    interrupt: &Arc<AtomicBool>,
    clock: &dyn Clock,
    seed: u64,
) -> EpisodeReport {
    let mut steps = 0;
    let mut gripper_events = Vec::new();
    let (outcome, detail) = match episode_steps(
        cfg,
        &mut cell,
        policy,
        recorder,
        interrupt,
        clock,
        seed,
        &mut steps,
        &mut gripper_events,
    ) {
        Ok((o, d)) => (o, d),
        Err(e) => (Outcome::Error, format!("{e:#}")),
    };
    // Whatever happened, leave the arm still: a no-op when it already is.
    if !matches!(
        outcome,
        Outcome::Success | Outcome::TaskNotDone | Outcome::TaskLost
    ) {
        if let Err(e) = cell.arm.stop() {
            let _ = recorder.write(
                "/log",
                ns(clock),
                &recording::log_message(
                    ns(clock),
                    LogLevel::Error,
                    &format!("stop after the episode failed: {e}"),
                ),
            );
        }
    }
    // The stop's deceleration and the final rest belong to the recording too.
    if let Err(e) = record_arm_states(recorder, cell.arm, &mut Vec::new()) {
        eprintln!("warning: recording the last arm states failed: {e:#}");
    }
    let t = ns(clock);
    let _ = recorder.write(
        "/episode/outcome",
        t,
        &json!({"outcome": outcome.label(), "success": outcome == Outcome::Success, "steps": steps, "detail": detail}),
    );
    let counts = recorder.counts().clone();
    let _ = recorder.finish();
    EpisodeReport {
        outcome,
        steps,
        detail,
        gripper_events,
        recording: recorder.path().to_path_buf(),
        counts,
    }
}

#[allow(clippy::too_many_arguments)]
fn episode_steps(
    cfg: &CellConfig,
    cell: &mut CellIo<'_>,
    policy: &mut dyn KeyframeSource,
    rec: &mut EpisodeRecorder,
    interrupt: &Arc<AtomicBool>,
    clock: &dyn Clock,
    seed: u64,
    steps: &mut usize,
    gripper_events: &mut Vec<(usize, GripperEvent)>,
) -> anyhow::Result<(Outcome, String)> {
    let planner = planner_from_config(cfg)?;
    let fusion = FusionPipeline::new(cell.calibration.clone(), fusion_params(cfg, seed))?;
    let instruction = cell.task.instruction();
    rec.write(
        "/robot_description",
        ns(clock),
        &json!({"data": planner::model::UR5_URDF}),
    )?;
    rec.attach(
        "ur5.urdf",
        "application/xml",
        ns(clock),
        planner::model::UR5_URDF.as_bytes(),
    )?;

    let mut gstate = match cell.gripper.activate().and_then(|_| cell.gripper.open()) {
        Ok(s) => s,
        Err(e) => {
            return Ok((
                Outcome::GripperFault,
                format!("gripper activation failed: {e}"),
            ))
        }
    };
    let table = Obstacle::table(cfg.workspace.table_height);

    let mut states = Vec::new();
    for step in 0..MAX_KEYFRAMES {
        if interrupt.load(Ordering::SeqCst) {
            return Ok((
                Outcome::Interrupted,
                format!("Ctrl-C before keyframe {step}"),
            ));
        }
        let arm_state = match cell.arm.state() {
            Ok(s) => s,
            Err(e) => return Ok((Outcome::ArmStopped, format!("before keyframe {step}: {e}"))),
        };
        let q = arm_state.joints.position;
        record_arm_states(rec, cell.arm, &mut states)?;
        let t = ns(clock);
        rec.write("/gripper", t, &gripper_message(&gstate))?;
        // The TCP is already in /tf at the controller rate (record_arm_states): here only
        // the cameras.
        let mut transforms = Vec::with_capacity(cell.calibration.cameras.len());
        for c in &cell.calibration.cameras {
            transforms.push(recording::frame_transform(
                t,
                "base",
                &format!("camera_{}", c.id),
                c.base_from_camera.isometry(),
            ));
        }
        rec.write("/tf", t, &json!({ "transforms": transforms }))?;

        // Capture and fuse.
        let t0 = Instant::now();
        let mut frames = Vec::with_capacity(cell.cameras.len());
        for cam in cell.cameras.iter_mut() {
            match cam.capture() {
                Ok(f) => frames.push(f),
                Err(e) => {
                    return Ok((
                        Outcome::PerceptionFault,
                        format!("camera {} gave no frame: {e}", cam.id()),
                    ))
                }
            }
        }
        let capture_s = t0.elapsed().as_secs_f64();
        for f in &frames {
            let d = &f.depth.raw;
            rec.write(
                "/camera/depth",
                t,
                &recording::depth_image_message(
                    t,
                    &format!("camera_{}", f.camera),
                    d.width,
                    d.height,
                    &d.data,
                ),
            )?;
        }
        let t1 = Instant::now();
        let opening = gstate.width_m;
        let robot = hil_sim::scene::robot_capsules(&q, opening);
        let tcp = planner.model.fk_tcp(&q).translation();
        let tcp = Point3::new(tcp.x as f32, tcp.y as f32, tcp.z as f32);
        let fused = match fusion.fuse_at(&frames, &robot, Some(tcp)) {
            Ok(f) => f,
            Err(e) => return Ok((Outcome::PerceptionFault, format!("fusion failed: {e}"))),
        };
        let fuse_s = t1.elapsed().as_secs_f64();
        rec.write(
            "/cloud/fused",
            t,
            &recording::cloud_message(t, &fused.sampled),
        )?;

        // Predict.
        let t2 = Instant::now();
        let obs = Observation {
            cloud: &fused.sampled,
            joints: &arm_state.joints,
            gripper: &gstate,
            instruction: &instruction,
        };
        let Some(keyframe) = policy.next_keyframe(&obs)? else {
            let finished = format!(
                "the {} policy finished after {step} keyframes",
                policy.name()
            );
            return Ok(match cell.task.success() {
                Some(true) => (Outcome::Success, finished),
                Some(false) => (Outcome::TaskNotDone, finished),
                None => (
                    Outcome::TaskNotDone,
                    format!("{finished}; no success test on a real cell: judge the outcome"),
                ),
            });
        };
        let predict_s = t2.elapsed().as_secs_f64();
        rec.write(
            "/keyframes",
            t,
            &recording::keyframe_scene(
                t,
                step,
                keyframe.base_from_tcp.isometry(),
                keyframe.gripper_open,
                keyframe.ignore_collisions,
            ),
        )?;

        // Plan against the dense fused cloud and the table.
        let t3 = Instant::now();
        // The table is known static geometry (a half-space obstacle): its points are dropped
        // from the planning cloud so sensor noise on the table top cannot block grasps of
        // objects lying on it.
        let above_table = cfg.workspace.table_height + TABLE_POINT_BAND;
        let keep: Vec<usize> = (0..fused.dense.len())
            .filter(|&i| f64::from(fused.dense.points[i].z) > above_table)
            .collect();
        let planning_cloud = PointCloud {
            frame: fused.dense.frame,
            points: keep.iter().map(|&i| fused.dense.points[i]).collect(),
            rgb: None,
        };
        let world = World::from_cloud(&planning_cloud, &CloudParams::default())?
            .with_obstacle(table.clone());
        // A keyframe the planner refuses is replaced by the source's next-ranked one, if it
        // has any: the arm runs the best prediction it can reach.
        let mut keyframe = keyframe;
        let mut planned = planner.plan_to_keyframe(&q, &keyframe, &world);
        let mut alternatives = 0;
        while planned.is_err() {
            let Some(next) = policy.alternative()? else {
                break;
            };
            alternatives += 1;
            rec.write(
                "/keyframes",
                t,
                &recording::keyframe_scene(
                    t,
                    step,
                    next.base_from_tcp.isometry(),
                    next.gripper_open,
                    next.ignore_collisions,
                ),
            )?;
            if let Ok(m) = planner.plan_to_keyframe(&q, &next, &world) {
                keyframe = next;
                planned = Ok(m);
            }
        }
        let motion = match planned {
            Ok(m) => m,
            Err(e) => {
                let also = match alternatives {
                    0 => String::new(),
                    n => format!(" (nor could the policy's {n} next-ranked keyframes)"),
                };
                return Ok((
                    Outcome::PlanFailed,
                    format!(
                        "keyframe {step} ({}) could not be planned: {e}{also}",
                        describe_pose(&keyframe)
                    ),
                ));
            }
        };
        let plan_s = t3.elapsed().as_secs_f64();
        rec.write(
            "/trajectory/planned",
            t,
            &recording::trajectory_scene(t, step, &motion.trajectory, |qq| {
                Point3::from(planner.model.fk_tcp(qq).translation())
            }),
        )?;

        // Execute.
        let t4 = Instant::now();
        let t = ns(clock);
        rec.write(
            "/trajectory/joints",
            t,
            &recording::joint_trajectory_message(step, &motion.trajectory, &cfg.limits),
        )?;
        let outcome = match cell.arm.execute(&motion.trajectory) {
            Ok(o) => o,
            // Refused before the first sample (a stop already active) or the link went down:
            // the arm is not following the plan either way.
            Err(e) => return Ok((Outcome::ArmStopped, format!("keyframe {step}: {e}"))),
        };
        let exec_s = t4.elapsed().as_secs_f64();
        record_arm_states(rec, cell.arm, &mut states)?;
        let (final_q, jitter) = match &outcome {
            ExecutionOutcome::Completed {
                final_state,
                jitter,
                ..
            } => (final_state.joints.position, *jitter),
            ExecutionOutcome::Stopped {
                by,
                cause,
                last_state,
                ..
            } => {
                cell.task
                    .update_robot(&last_state.joints.position, opening)?;
                let detail = format!("keyframe {step}: arm stopped by {by:?}: {cause:?}");
                return Ok((
                    if interrupt.load(Ordering::SeqCst) {
                        Outcome::Interrupted
                    } else {
                        Outcome::ArmStopped
                    },
                    detail,
                ));
            }
        };
        cell.task.update_robot(&final_q, opening)?;

        // Gripper.
        let t5 = Instant::now();
        let was_open = gstate.width_m > 0.08;
        let mut event = None;
        if keyframe.gripper_open != was_open {
            let result = if keyframe.gripper_open {
                cell.gripper.open()
            } else {
                cell.task.before_close(&final_q);
                cell.gripper.close()
            };
            gstate = match result {
                Ok(s) => s,
                Err(e) => {
                    return Ok((
                        Outcome::GripperFault,
                        format!("keyframe {step}: gripper: {e}"),
                    ))
                }
            };
            event = cell.task.after_gripper(&final_q, gstate.holds_object());
            cell.task.update_robot(&final_q, gstate.width_m)?;
        }
        let gripper_s = t5.elapsed().as_secs_f64();
        *steps = step + 1;

        for (phase, d, detail) in [
            ("capture", capture_s, format!("{} cameras", frames.len())),
            (
                "fuse",
                fuse_s,
                format!(
                    "{} dense, {} sampled points",
                    fused.dense.len(),
                    fused.sampled.len()
                ),
            ),
            (
                "predict",
                predict_s,
                match alternatives {
                    0 => policy.name().to_string(),
                    n => format!("{}, its keyframe ranked {} planned", policy.name(), n + 1),
                },
            ),
            (
                "plan",
                plan_s,
                format!(
                    "{} samples, {} RRT iterations",
                    motion.trajectory.len(),
                    motion.stats.iterations
                ),
            ),
            (
                "execute",
                exec_s,
                format!("jitter p99 {:.0} us", jitter.jitter_p99_us),
            ),
            (
                "gripper",
                gripper_s,
                format!(
                    "width {:.4} m, holds object: {}{}",
                    gstate.width_m,
                    gstate.holds_object(),
                    event.as_ref().map(|e| format!("; {e}")).unwrap_or_default()
                ),
            ),
        ] {
            rec.write(
                "/episode/step",
                t,
                &json!({"step": step, "phase": phase, "duration_s": d, "detail": detail}),
            )?;
        }
        rec.checkpoint()?;
        println!(
            "  step {step:>2}: keyframe at [{:.3}, {:.3}, {:.3}] {}{} | capture {:.2} s, fuse {:.3} s, plan {:.1} ms, execute {:.2} s, gripper {:.2} s",
            keyframe.base_from_tcp.translation().x,
            keyframe.base_from_tcp.translation().y,
            keyframe.base_from_tcp.translation().z,
            if keyframe.gripper_open { "open  " } else { "closed" },
            match alternatives {
                0 => String::new(),
                n => format!(" (ranked {})", n + 1),
            },
            capture_s,
            fuse_s,
            plan_s * 1e3,
            exec_s,
            gripper_s,
        );
        if let Some(e) = event {
            println!("           {e}");
            gripper_events.push((step, e));
        }
        if cell.task.success() == Some(true) {
            return Ok((
                Outcome::Success,
                format!("task done after {} keyframes", step + 1),
            ));
        }
        // Keyframes after this could not change the outcome; on a real cell `lost` is None.
        if let Some(why) = cell.task.lost() {
            return Ok((
                Outcome::TaskLost,
                format!("task lost after {} keyframes: {why}", step + 1),
            ));
        }
    }
    Ok((
        Outcome::TaskNotDone,
        match cell.task.success() {
            None => format!("{MAX_KEYFRAMES} keyframes; no success test on a real cell"),
            Some(_) => format!("{MAX_KEYFRAMES} keyframes without finishing the task"),
        },
    ))
}

/// A keyframe's TCP position and approach axis (the TCP z) in the base frame, for messages.
fn describe_pose(keyframe: &Keyframe) -> String {
    let p = keyframe.base_from_tcp.translation();
    let z = keyframe.base_from_tcp.isometry().rotation * Vector3::z();
    format!(
        "TCP at [{:.3}, {:.3}, {:.3}] m, approach [{:.2}, {:.2}, {:.2}], {}",
        p.x,
        p.y,
        p.z,
        z.x,
        z.y,
        z.z,
        if keyframe.gripper_open {
            "open"
        } else {
            "closed"
        }
    )
}
