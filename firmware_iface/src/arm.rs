//! The `Arm` trait (issue 5 §2) with its outcome types, and the safety wrappers of §4 that
//! wrap any `Arm`: joint/velocity limits and a TCP workspace bound checked on the whole
//! trajectory before the first sample is sent.

use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::Arc;

use cell_types::{JointState, Joints, Trajectory, JOINT_COUNT};
use thiserror::Error;

use crate::dashboard::{RobotMode, SafetyMode};
use crate::rtde::RtdeError;

/// What the arm reported in its latest state package.
#[derive(Copy, Clone, Debug, PartialEq)]
pub struct ArmState {
    /// Controller timestamp (s since controller start).
    pub controller_time: f64,
    /// Measured joints.
    pub joints: JointState,
    /// The controller's current joint target.
    pub target_q: Joints,
    /// TCP pose `[x, y, z, rx, ry, rz]` in the base frame (m, rotation vector).
    pub tcp_pose: [f64; 6],
    /// Robot mode.
    pub robot_mode: RobotMode,
    /// Safety mode.
    pub safety_mode: SafetyMode,
    /// True while a program runs (runtime_state PLAYING).
    pub program_running: bool,
}

impl Default for ArmState {
    fn default() -> Self {
        Self {
            controller_time: 0.0,
            joints: JointState::default(),
            target_q: [0.0; JOINT_COUNT],
            tcp_pose: [0.0; 6],
            robot_mode: RobotMode::Disconnected,
            safety_mode: SafetyMode::Normal,
            program_running: false,
        }
    }
}

/// Who stopped a motion.
#[derive(Copy, Clone, Debug, PartialEq, Eq)]
pub enum StoppedBy {
    /// The controller (safety system, program end, connection).
    Controller,
    /// The driver's own checks.
    Driver,
    /// The caller, through a [`StopHandle`].
    Caller,
}

/// Why a motion stopped early.
#[derive(Clone, Debug, PartialEq)]
#[non_exhaustive]
pub enum StopCause {
    /// Tracking error over the bound.
    TrackingError {
        /// Joint index (0-based).
        joint: usize,
        /// Error (rad).
        error: f64,
        /// Bound (rad).
        bound: f64,
    },
    /// The controller reported a protective stop.
    ProtectiveStop,
    /// The controller reported an emergency stop.
    EmergencyStop,
    /// The controller left NORMAL safety mode for another reason.
    SafetyMode(SafetyMode),
    /// The robot left RUNNING mode.
    RobotMode(RobotMode),
    /// No state package arrived for more than the allowed cycles (stalled controller or lost packets).
    NoData {
        /// Control cycles without a package.
        missed_cycles: u32,
    },
    /// The RTDE connection closed or failed.
    ConnectionLost {
        /// What the socket said.
        detail: String,
    },
    /// The servo program is no longer running.
    ProgramStopped {
        /// Its last acknowledgement word.
        ack: i32,
    },
    /// The caller asked to stop.
    Requested,
    /// The motion took much longer than planned.
    Timeout {
        /// Seconds waited.
        waited: f64,
    },
}

/// Cycle-time statistics of a streaming loop (µs).
#[derive(Copy, Clone, Debug, Default, PartialEq)]
pub struct JitterStats {
    /// Cycles measured.
    pub cycles: usize,
    /// Nominal period (µs).
    pub period_us: f64,
    /// Median cycle time (µs).
    pub p50_us: f64,
    /// 99th percentile cycle time (µs).
    pub p99_us: f64,
    /// Longest cycle (µs).
    pub max_us: f64,
    /// 99th percentile of |cycle - period| (µs): the jitter.
    pub jitter_p99_us: f64,
    /// Cycles longer than 1.5 periods.
    pub late_cycles: usize,
}

impl JitterStats {
    /// Statistics of `cycle_s` (seconds), sorted in place (no allocation: usable at the end
    /// of a real-time loop with its preallocated buffer).
    pub fn from_cycles(cycle_s: &mut [f64], period: f64) -> Self {
        let n = cycle_s.len();
        if n == 0 {
            return Self {
                period_us: period * 1e6,
                ..Self::default()
            };
        }
        let late = cycle_s.iter().filter(|c| **c > 1.5 * period).count();
        cycle_s.sort_by(f64::total_cmp);
        let pick = |v: &[f64], q: f64| v[((n as f64 - 1.0) * q).round() as usize] * 1e6;
        let (p50, p99, max) = (
            pick(cycle_s, 0.5),
            pick(cycle_s, 0.99),
            cycle_s[n - 1] * 1e6,
        );
        for c in cycle_s.iter_mut() {
            *c = (*c - period).abs();
        }
        cycle_s.sort_by(f64::total_cmp);
        Self {
            cycles: n,
            period_us: period * 1e6,
            p50_us: p50,
            p99_us: p99,
            max_us: max,
            jitter_p99_us: pick(cycle_s, 0.99),
            late_cycles: late,
        }
    }
}

/// How a trajectory execution ended.
#[derive(Clone, Debug, PartialEq)]
#[must_use]
pub enum ExecutionOutcome {
    /// Every sample was sent and the arm settled at the goal.
    Completed {
        /// State at the end: for the UR driver, the first after the servo program ended
        /// (the arm at rest), or the last of a short wait for it.
        final_state: ArmState,
        /// Largest tracking error seen (rad).
        max_tracking_error: f64,
        /// Streaming loop statistics.
        jitter: JitterStats,
    },
    /// The motion stopped early; the arm was told to stop (stopj) where a link remained.
    Stopped {
        /// Who stopped it.
        by: StoppedBy,
        /// Why.
        cause: StopCause,
        /// Samples sent before the stop.
        samples_sent: usize,
        /// Last state received.
        last_state: ArmState,
        /// Streaming loop statistics up to the stop.
        jitter: JitterStats,
    },
}

impl ExecutionOutcome {
    /// The jitter statistics of either outcome.
    pub fn jitter(&self) -> &JitterStats {
        match self {
            ExecutionOutcome::Completed { jitter, .. }
            | ExecutionOutcome::Stopped { jitter, .. } => jitter,
        }
    }
}

/// A handle that asks a running `execute` to stop; clones share the request.
#[derive(Clone, Debug, Default)]
pub struct StopHandle(Arc<AtomicBool>);

impl StopHandle {
    /// A fresh handle.
    pub fn new() -> Self {
        Self::default()
    }
    /// Asks the motion to stop.
    pub fn request(&self) {
        self.0.store(true, Ordering::SeqCst);
    }
    /// True once a stop was requested.
    pub fn requested(&self) -> bool {
        self.0.load(Ordering::SeqCst)
    }
    /// Clears the request (done by `execute` when it starts).
    pub fn clear(&self) {
        self.0.store(false, Ordering::SeqCst);
    }
}

/// Why the arm refused or failed an operation.
#[derive(Debug, Error)]
#[non_exhaustive]
pub enum ArmError {
    /// Nothing listens at the address.
    #[error("cannot connect to the UR {service} at {addr}: {source}; check that the controller (or `equact sim`) runs there and the port is right")]
    Connect {
        /// Which service.
        service: &'static str,
        /// Address tried.
        addr: std::net::SocketAddr,
        /// The OS error.
        source: std::io::Error,
    },
    /// A socket failed after connecting.
    #[error("UR {service} connection failed: {source}; check the network and the controller, then reconnect")]
    Io {
        /// Which service.
        service: &'static str,
        /// The OS error.
        source: std::io::Error,
    },
    /// The controller answered something the protocol does not allow.
    #[error("UR {service} protocol error: {detail}")]
    Protocol {
        /// Which service.
        service: &'static str,
        /// What was wrong.
        detail: String,
    },
    /// RTDE bytes could not be decoded.
    #[error("RTDE: {0}")]
    Rtde(#[from] RtdeError),
    /// The controller is powered off.
    #[error("the UR controller is in POWER_OFF; power the arm on and release the brakes (dashboard `power on`, then `brake release`, or connect with power_up = true)")]
    PoweredOff,
    /// The controller is not RUNNING/NORMAL, so it will not move.
    #[error("the arm is not ready to move: robot mode {robot_mode:?}, safety mode {safety_mode:?}; release the brakes and clear any protective or emergency stop first")]
    NotReady {
        /// Robot mode found.
        robot_mode: RobotMode,
        /// Safety mode found.
        safety_mode: SafetyMode,
    },
    /// RTDE inputs owned by another client.
    #[error("RTDE inputs {names:?} are still IN_USE by another RTDE client or fieldbus after waiting 1 s for it to let go; stop that client (e.g. ur_rtde RTDEControlInterface, a PLC/EtherNet-IP adapter) and reconnect")]
    InputsInUse {
        /// The inputs.
        names: Vec<String>,
    },
    /// RTDE names the controller does not know.
    #[error("RTDE variables {names:?} are NOT_FOUND on this controller; its software is too old for this driver, update it")]
    NotFound {
        /// The names.
        names: Vec<String>,
    },
    /// A sample outside a joint's position limits.
    #[error("trajectory sample {sample}: joint {joint} at {value:.4} rad is outside ±{limit:.4} rad; replan within the joint limits")]
    JointLimit {
        /// Sample index.
        sample: usize,
        /// Joint (0-based).
        joint: usize,
        /// Position.
        value: f64,
        /// Limit.
        limit: f64,
    },
    /// A sample over a joint's speed limit.
    #[error("trajectory sample {sample}: joint {joint} moves at {value:.4} rad/s, over the {limit:.4} rad/s limit; retime the trajectory slower")]
    VelocityLimit {
        /// Sample index.
        sample: usize,
        /// Joint.
        joint: usize,
        /// Speed (rad/s).
        value: f64,
        /// Limit (rad/s).
        limit: f64,
    },
    /// A TCP position outside the workspace box.
    #[error("trajectory sample {sample}: TCP at {position:?} m leaves the workspace box {min:?}..{max:?}; replan inside the workspace")]
    Workspace {
        /// Sample index.
        sample: usize,
        /// TCP position.
        position: [f64; 3],
        /// Box minimum.
        min: [f64; 3],
        /// Box maximum.
        max: [f64; 3],
    },
    /// The trajectory does not start where the arm is.
    #[error("trajectory starts {distance:.4} rad away from the arm (tolerance {tolerance}); plan from the current joint state")]
    StartMismatch {
        /// Largest joint difference (rad).
        distance: f64,
        /// Tolerance (rad).
        tolerance: f64,
    },
    /// The trajectory's rate is not the controller's.
    #[error("trajectory period {period} s differs from the controller period {controller} s; resample at the controller rate")]
    RateMismatch {
        /// Trajectory period.
        period: f64,
        /// Controller period.
        controller: f64,
    },
    /// An empty trajectory.
    #[error("trajectory has no samples; nothing to execute")]
    EmptyTrajectory,
    /// The servo program did not start.
    #[error("the servo program did not start within {waited:.1} s ({detail}); check the controller log and that nothing else runs a program")]
    ProgramNotStarted {
        /// Seconds waited.
        waited: f64,
        /// What was seen.
        detail: String,
    },
    /// The RTDE link is gone.
    #[error("the RTDE link is down ({detail}); reconnect the arm")]
    LinkDown {
        /// Why.
        detail: String,
    },
    /// Waited too long for the controller.
    #[error("timed out after {waited:.1} s waiting for {what}; check the controller")]
    Timeout {
        /// What.
        what: &'static str,
        /// Seconds.
        waited: f64,
    },
}

/// A robot arm that executes joint trajectories.
pub trait Arm {
    /// The latest state the arm reported.
    fn state(&self) -> Result<ArmState, ArmError>;
    /// Executes `trajectory` from the arm's current position; returns how it ended. Never
    /// blocks for much longer than the trajectory's duration.
    fn execute(&mut self, trajectory: &Trajectory) -> Result<ExecutionOutcome, ArmError>;
    /// A handle to stop the running (or next) `execute` from another thread.
    fn stop_handle(&self) -> StopHandle;
    /// Stops any motion now (decelerating).
    fn stop(&mut self) -> Result<(), ArmError>;
}

/// Joint position and speed limits.
#[derive(Copy, Clone, Debug, PartialEq)]
pub struct JointLimits {
    /// Lower position limits (rad).
    pub min: Joints,
    /// Upper position limits (rad).
    pub max: Joints,
    /// Speed limits (rad/s).
    pub max_speed: Joints,
}

impl JointLimits {
    /// The UR5's hardware limits: ±2π, π rad/s.
    pub fn ur5() -> Self {
        Self {
            min: [-std::f64::consts::TAU; JOINT_COUNT],
            max: [std::f64::consts::TAU; JOINT_COUNT],
            max_speed: [std::f64::consts::PI; JOINT_COUNT],
        }
    }

    /// Checks every sample's positions and velocities, and the speed implied by
    /// consecutive positions (a trajectory with wrong velocity fields must not slip through).
    pub fn check(&self, trajectory: &Trajectory) -> Result<(), ArmError> {
        let dt = trajectory.period();
        let samples = trajectory.samples();
        for (i, s) in samples.iter().enumerate() {
            for j in 0..JOINT_COUNT {
                let q = s.position[j];
                if q < self.min[j] || q > self.max[j] {
                    return Err(ArmError::JointLimit {
                        sample: i,
                        joint: j,
                        value: q,
                        limit: if q < self.min[j] {
                            self.min[j]
                        } else {
                            self.max[j]
                        },
                    });
                }
                let implied = if i > 0 {
                    (q - samples[i - 1].position[j]) / dt
                } else {
                    0.0
                };
                for v in [s.velocity[j], implied] {
                    if v.abs() > self.max_speed[j] * (1.0 + 1e-9) {
                        return Err(ArmError::VelocityLimit {
                            sample: i,
                            joint: j,
                            value: v.abs(),
                            limit: self.max_speed[j],
                        });
                    }
                }
            }
        }
        Ok(())
    }
}

/// Wraps an arm: refuses trajectories outside joint/speed limits before anything is sent.
pub struct LimitedArm<A: Arm> {
    inner: A,
    limits: JointLimits,
}

impl<A: Arm> LimitedArm<A> {
    /// Wraps `inner` with `limits`.
    pub fn new(inner: A, limits: JointLimits) -> Self {
        Self { inner, limits }
    }
    /// The wrapped arm.
    pub fn inner(&mut self) -> &mut A {
        &mut self.inner
    }
}

impl<A: Arm> Arm for LimitedArm<A> {
    fn state(&self) -> Result<ArmState, ArmError> {
        self.inner.state()
    }
    fn execute(&mut self, trajectory: &Trajectory) -> Result<ExecutionOutcome, ArmError> {
        self.limits.check(trajectory)?;
        self.inner.execute(trajectory)
    }
    fn stop_handle(&self) -> StopHandle {
        self.inner.stop_handle()
    }
    fn stop(&mut self) -> Result<(), ArmError> {
        self.inner.stop()
    }
}

/// Wraps an arm: refuses to move unless the controller reports RUNNING and NORMAL.
pub struct ModeGuard<A: Arm> {
    inner: A,
}

impl<A: Arm> ModeGuard<A> {
    /// Wraps `inner`.
    pub fn new(inner: A) -> Self {
        Self { inner }
    }
}

impl<A: Arm> Arm for ModeGuard<A> {
    fn state(&self) -> Result<ArmState, ArmError> {
        self.inner.state()
    }
    fn execute(&mut self, trajectory: &Trajectory) -> Result<ExecutionOutcome, ArmError> {
        let s = self.inner.state()?;
        if s.robot_mode != RobotMode::Running || s.safety_mode != SafetyMode::Normal {
            return Err(ArmError::NotReady {
                robot_mode: s.robot_mode,
                safety_mode: s.safety_mode,
            });
        }
        self.inner.execute(trajectory)
    }
    fn stop_handle(&self) -> StopHandle {
        self.inner.stop_handle()
    }
    fn stop(&mut self) -> Result<(), ArmError> {
        self.inner.stop()
    }
}

/// Forward kinematics to the TCP position (m); firmware_iface does not depend on the
/// planner, so the caller passes its model in (e.g. `planner::kinematics::UR5`).
pub type TcpPosition = Box<dyn Fn(&Joints) -> [f64; 3] + Send>;

/// Wraps an arm: refuses trajectories whose TCP leaves an axis-aligned box in the base frame.
pub struct WorkspaceGuard<A: Arm> {
    inner: A,
    fk: TcpPosition,
    min: [f64; 3],
    max: [f64; 3],
}

impl<A: Arm> WorkspaceGuard<A> {
    /// Wraps `inner` with the box `min..max` (m) and the forward kinematics `fk`.
    pub fn new(inner: A, fk: TcpPosition, min: [f64; 3], max: [f64; 3]) -> Self {
        Self {
            inner,
            fk,
            min,
            max,
        }
    }
}

impl<A: Arm> Arm for WorkspaceGuard<A> {
    fn state(&self) -> Result<ArmState, ArmError> {
        self.inner.state()
    }
    fn execute(&mut self, trajectory: &Trajectory) -> Result<ExecutionOutcome, ArmError> {
        for (i, s) in trajectory.samples().iter().enumerate() {
            let p = (self.fk)(&s.position);
            if (0..3).any(|k| !(p[k] >= self.min[k] && p[k] <= self.max[k])) {
                return Err(ArmError::Workspace {
                    sample: i,
                    position: p,
                    min: self.min,
                    max: self.max,
                });
            }
        }
        self.inner.execute(trajectory)
    }
    fn stop_handle(&self) -> StopHandle {
        self.inner.stop_handle()
    }
    fn stop(&mut self) -> Result<(), ArmError> {
        self.inner.stop()
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use cell_types::TrajectorySample;

    /// An arm that records whether anything reached it.
    struct Recorder {
        executed: usize,
        state: ArmState,
    }

    impl Recorder {
        fn new(safety_mode: SafetyMode) -> Self {
            Self {
                executed: 0,
                state: ArmState {
                    robot_mode: RobotMode::Running,
                    safety_mode,
                    ..ArmState::default()
                },
            }
        }
    }

    impl Arm for Recorder {
        fn state(&self) -> Result<ArmState, ArmError> {
            Ok(self.state)
        }
        fn execute(&mut self, _: &Trajectory) -> Result<ExecutionOutcome, ArmError> {
            self.executed += 1;
            Ok(ExecutionOutcome::Completed {
                final_state: ArmState::default(),
                max_tracking_error: 0.0,
                jitter: JitterStats::default(),
            })
        }
        fn stop_handle(&self) -> StopHandle {
            StopHandle::new()
        }
        fn stop(&mut self) -> Result<(), ArmError> {
            Ok(())
        }
    }

    fn traj(positions: &[[f64; 6]]) -> Trajectory {
        Trajectory::new(
            0.008,
            positions
                .iter()
                .enumerate()
                .map(|(i, p)| TrajectorySample {
                    t: i as f64 * 0.008,
                    position: *p,
                    ..Default::default()
                })
                .collect(),
        )
        .unwrap()
    }

    #[test]
    fn limits_refuse_before_the_inner_arm_sees_anything() {
        let mut arm = LimitedArm::new(Recorder::new(SafetyMode::Normal), JointLimits::ur5());
        let bad_pos = traj(&[[0.0; 6], [0.0, 0.0, 7.0, 0.0, 0.0, 0.0]]);
        assert!(matches!(
            arm.execute(&bad_pos),
            Err(ArmError::JointLimit {
                sample: 1,
                joint: 2,
                ..
            })
        ));
        // 0.03 rad in 8 ms = 3.75 rad/s > π.
        let too_fast = traj(&[[0.0; 6], [0.0, 0.0, 0.0, 0.03, 0.0, 0.0]]);
        assert!(matches!(
            arm.execute(&too_fast),
            Err(ArmError::VelocityLimit {
                sample: 1,
                joint: 3,
                ..
            })
        ));
        assert_eq!(arm.inner().executed, 0);
        let ok = traj(&[[0.0; 6], [0.0, 0.0, 0.0, 0.02, 0.0, 0.0]]);
        assert!(arm.execute(&ok).is_ok());
        assert_eq!(arm.inner().executed, 1);
    }

    #[test]
    fn workspace_guard_refuses_tcp_outside_the_box() {
        let fk: TcpPosition = Box::new(|q: &Joints| [q[0], q[1], q[2]]);
        let mut arm =
            WorkspaceGuard::new(Recorder::new(SafetyMode::Normal), fk, [-1.0; 3], [1.0; 3]);
        let out = traj(&[[0.0; 6], [0.0, 1.5, 0.0, 0.0, 0.0, 0.0]]);
        assert!(matches!(
            arm.execute(&out),
            Err(ArmError::Workspace { sample: 1, .. })
        ));
        assert!(arm.execute(&traj(&[[0.5; 6]])).is_ok());
    }

    #[test]
    fn mode_guard_refuses_unless_running_and_normal() {
        let t = traj(&[[0.0; 6]]);
        let mut stopped = ModeGuard::new(Recorder::new(SafetyMode::ProtectiveStop));
        assert!(matches!(
            stopped.execute(&t),
            Err(ArmError::NotReady {
                safety_mode: SafetyMode::ProtectiveStop,
                ..
            })
        ));
        assert_eq!(stopped.inner.executed, 0);
        let mut ok = ModeGuard::new(Recorder::new(SafetyMode::Normal));
        assert!(ok.execute(&t).is_ok());
        assert_eq!(ok.inner.executed, 1);
    }

    #[test]
    fn jitter_stats_percentiles_and_late_cycles() {
        let mut c: Vec<f64> = (0..100).map(|_| 0.008).collect();
        c[10] = 0.013;
        c[20] = 0.020;
        let s = JitterStats::from_cycles(&mut c, 0.008);
        assert_eq!(s.cycles, 100);
        assert_eq!(s.late_cycles, 2);
        assert!((s.p50_us - 8000.0).abs() < 1e-6);
        assert!((s.max_us - 20000.0).abs() < 1e-6);
        assert!((s.p99_us - 13000.0).abs() < 1e-6);
    }
}
