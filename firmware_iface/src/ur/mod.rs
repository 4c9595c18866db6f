//! The UR5 driver: RTDE client thread, dashboard client, servo program upload, and the
//! [`crate::arm::Arm`] implementation [`UrArm`] that streams trajectories through the
//! register contract of `urscript/CONTRACT.md` (UR fact sheet, "RTDE", "Dashboard server",
//! "Commanding motion").

/// The three controller ports the driver and the simulator use.
#[derive(Copy, Clone, Debug, PartialEq, Eq, Hash)]
pub struct UrPorts {
    /// RTDE (30004 on a real controller).
    pub rtde: u16,
    /// Dashboard server (29999).
    pub dashboard: u16,
    /// Secondary interface, where URScript programs are sent (30002).
    pub secondary: u16,
}

impl Default for UrPorts {
    fn default() -> Self {
        Self {
            rtde: 30004,
            dashboard: 29999,
            secondary: 30002,
        }
    }
}

pub mod dashboard_client;
pub mod rtde_link;

use std::io::Write;
use std::net::{IpAddr, Ipv4Addr, SocketAddr, TcpStream};
use std::sync::mpsc::sync_channel;
use std::sync::Arc;
use std::time::Duration;

use cell_types::{joints::max_abs_diff, Clock, Trajectory};

use crate::arm::{
    Arm, ArmError, ArmState, ExecutionOutcome, JitterStats, JointLimits, StopCause, StopHandle,
    StoppedBy,
};
use crate::dashboard::{DashboardCommand, RobotMode, SafetyMode};
use crate::realtime::Scheduling;
use crate::urscript::ServoParams;
pub use dashboard_client::DashboardClient;
use rtde_link::{Job, Link};

/// Driver settings (the lead fills them from `cell.toml`).
#[derive(Clone, Debug)]
pub struct UrConfig {
    /// Controller address.
    pub host: IpAddr,
    /// Controller ports.
    pub ports: UrPorts,
    /// Timeout for connecting and for each setup reply.
    pub connect_timeout: Duration,
    /// Power on and release the brakes at connect when the arm is off (otherwise refuse).
    pub power_up: bool,
    /// Speak RTDE protocol 1 only (old controllers; tests of the fallback).
    pub force_v1: bool,
    /// servoj lookahead time (s).
    pub lookahead: f64,
    /// servoj gain.
    pub gain: f64,
    /// Watchdog of the servo program, in control cycles.
    pub watchdog_cycles: u32,
    /// stopj deceleration used on every stop (rad/s²).
    pub stop_decel: f64,
    /// Largest tracking error (rad): measured joints against the nearest sample streamed
    /// within the servo filter's lag (lookahead + 3 cycles).
    pub tracking_bound: f64,
    /// Control cycles without a state package before the motion is stopped.
    pub lost_cycles: u32,
    /// Largest distance (rad) between the arm and a trajectory's first sample.
    pub start_tolerance: f64,
    /// Goal tolerance (rad) for declaring a motion complete.
    pub goal_tolerance: f64,
    /// Longest settling time after the last sample (s).
    pub settle_time: f64,
    /// Joint limits checked before any sample is sent.
    pub limits: JointLimits,
    /// Run the link thread (the 125 Hz answer to the controller) at this `SCHED_FIFO`
    /// priority (1-99), as UR's client library does; `None` leaves its scheduling alone. A
    /// refusal (no permission) is not an error: see [`UrArm::scheduling`].
    pub realtime_priority: Option<u8>,
}

impl Default for UrConfig {
    fn default() -> Self {
        Self {
            host: IpAddr::V4(Ipv4Addr::LOCALHOST),
            ports: UrPorts::default(),
            connect_timeout: Duration::from_secs(2),
            power_up: false,
            force_v1: false,
            lookahead: 0.1,
            gain: 300.0,
            watchdog_cycles: 10,
            stop_decel: 4.0,
            tracking_bound: 0.1,
            lost_cycles: 3,
            start_tolerance: 0.01,
            goal_tolerance: 1e-4,
            settle_time: 1.0,
            limits: JointLimits::ur5(),
            realtime_priority: None,
        }
    }
}

/// A connected UR arm.
pub struct UrArm {
    config: UrConfig,
    dashboard: DashboardClient,
    link: Arc<Link>,
    stop: StopHandle,
    scheduling: Scheduling,
}

impl UrArm {
    /// Connects to the dashboard and RTDE, refusing a powered-off arm unless
    /// `config.power_up`, and refusing RTDE inputs owned by another client.
    pub fn connect(config: UrConfig, clock: Arc<dyn Clock>) -> Result<Self, ArmError> {
        let t = config.connect_timeout;
        let mut dashboard =
            DashboardClient::connect(SocketAddr::new(config.host, config.ports.dashboard), t)?;
        if dashboard.robot_mode()? == RobotMode::PowerOff {
            if !config.power_up {
                return Err(ArmError::PoweredOff);
            }
            dashboard.power_up(Duration::from_secs(30))?;
        }
        let (link, scheduling) = Link::connect(
            SocketAddr::new(config.host, config.ports.rtde),
            t,
            config.force_v1,
            clock,
            config.realtime_priority,
        )?;
        let arm = Self {
            config,
            dashboard,
            link,
            stop: StopHandle::new(),
            scheduling,
        };
        arm.link
            .wait_for(t, |s| s.packages > 0)
            .map_err(|s| ArmError::LinkDown {
                detail: s
                    .down
                    .unwrap_or_else(|| "no state package after start".into()),
            })?;
        Ok(arm)
    }

    /// Moves every state received since the last call (one per RTDE package, at the
    /// controller rate, with the local clock's receive time) into `out`; returns how many
    /// were dropped because nobody drained them for a minute.
    pub fn drain_states(&self, out: &mut Vec<(Duration, ArmState)>) -> u64 {
        self.link
            .state_log
            .lock()
            .unwrap_or_else(|e| e.into_inner())
            .drain_into(out)
    }

    /// The negotiated RTDE protocol version.
    pub fn protocol(&self) -> crate::rtde::ProtocolVersion {
        self.link.version
    }

    /// The controller's software version.
    pub fn controller(&self) -> crate::rtde::ControllerVersion {
        self.link.controller
    }

    /// How the link thread is scheduled: what [`UrConfig::realtime_priority`] asked for and
    /// got (a preflight line on a real cell).
    pub fn scheduling(&self) -> &Scheduling {
        &self.scheduling
    }

    /// Control period (s).
    pub fn period(&self) -> f64 {
        self.link.period
    }

    /// The dashboard client (power, brakes, unlock).
    pub fn dashboard(&mut self) -> &mut DashboardClient {
        &mut self.dashboard
    }

    fn upload(&self, params: &ServoParams) -> Result<(), ArmError> {
        let text = params.render().map_err(|e| ArmError::Protocol {
            service: "secondary interface",
            detail: e.to_string(),
        })?;
        let addr = SocketAddr::new(self.config.host, self.config.ports.secondary);
        let mut s =
            TcpStream::connect_timeout(&addr, self.config.connect_timeout).map_err(|source| {
                ArmError::Connect {
                    service: "secondary interface",
                    addr,
                    source,
                }
            })?;
        s.write_all(text.as_bytes()).map_err(|source| ArmError::Io {
            service: "secondary interface",
            source,
        })
    }
}

impl Drop for UrArm {
    fn drop(&mut self) {
        // Ends the link thread; a program still running is stopped by its own watchdog.
        self.link.close();
    }
}

impl Arm for UrArm {
    fn state(&self) -> Result<ArmState, ArmError> {
        let s = self.link.status.lock().unwrap_or_else(|e| e.into_inner());
        if let Some(d) = &s.down {
            return Err(ArmError::LinkDown { detail: d.clone() });
        }
        Ok(s.state)
    }

    fn execute(&mut self, trajectory: &Trajectory) -> Result<ExecutionOutcome, ArmError> {
        let (Some(start), Some(goal)) = (trajectory.start(), trajectory.goal()) else {
            return Err(ArmError::EmptyTrajectory);
        };
        let period = self.link.period;
        if (trajectory.period() - period).abs() > 1e-9 {
            return Err(ArmError::RateMismatch {
                period: trajectory.period(),
                controller: period,
            });
        }
        self.config.limits.check(trajectory)?;
        let state = self.state()?;
        if state.robot_mode != RobotMode::Running || state.safety_mode != SafetyMode::Normal {
            return Err(ArmError::NotReady {
                robot_mode: state.robot_mode,
                safety_mode: state.safety_mode,
            });
        }
        let distance = max_abs_diff(start, &state.joints.position);
        if distance > self.config.start_tolerance {
            return Err(ArmError::StartMismatch {
                distance,
                tolerance: self.config.start_tolerance,
            });
        }
        // Hold first, so that neither a stale stop word nor an old sequence number from the
        // previous run reaches the new program.
        let seen = self
            .link
            .status
            .lock()
            .unwrap_or_else(|e| e.into_inner())
            .packages;
        rtde_link::hold(&self.link, &state.joints.position)?;
        let params = ServoParams {
            cycle: period,
            lookahead: self.config.lookahead,
            gain: self.config.gain,
            watchdog_cycles: self.config.watchdog_cycles,
            stop_decel: self.config.stop_decel,
        };
        // Two packages later the controller has applied the hold word; only then may the
        // new program start reading it.
        self.link
            .wait_for(Duration::from_secs_f64(0.5), |s| s.packages >= seen + 2)
            .map_err(|s| ArmError::LinkDown {
                detail: s
                    .down
                    .unwrap_or_else(|| "no state package for 0.5 s".into()),
            })?;
        self.stop.clear();
        let (tx, rx) = sync_channel(1);
        let settle_cycles = (self.config.settle_time / period).ceil() as u32;
        let job = Job {
            samples: trajectory.samples().to_vec(),
            tracking_bound: self.config.tracking_bound,
            // servoj follows its target through a lookahead filter: the arm trails the
            // stream by up to the lookahead time plus a few cycles of transport.
            lag_samples: (self.config.lookahead / period).ceil() as usize + 3,
            lost_cycles: self.config.lost_cycles,
            goal_tolerance: self.config.goal_tolerance,
            settle_cycles,
            stop: self.stop.clone(),
            done: tx,
            cycles: Vec::with_capacity(
                trajectory.len()
                    + settle_cycles as usize
                    + (rtde_link::PROGRAM_END_WAIT_S / period).ceil() as usize
                    + 8,
            ),
            awaiting_program: true,
        };
        // Installed before the program starts, so that the link thread answers the very
        // first package that shows it running: the first target then always reaches the
        // controller one cycle after the program's first cycle (a simulated controller in
        // lockstep replays the same motion whatever the threads' timing).
        self.link.set_job(job);
        if let Err(e) = self.upload(&params) {
            self.link.take_job();
            return Err(e);
        }
        let wait = Duration::from_secs(2);
        if let Err(s) = self
            .link
            .wait_for(wait, |s| rtde_link::servo_program_started(&s.state, s.ack))
        {
            // A short motion may have started and ended while this thread waited: only a job
            // still waiting for its program means the program never ran.
            if self.link.take_unstarted_job() {
                return Err(ArmError::ProgramNotStarted {
                    waited: wait.as_secs_f64(),
                    detail: match s.down {
                        Some(d) => d,
                        None => format!(
                            "runtime running = {}, ack = {}, robot {:?}, safety {:?}",
                            s.state.program_running, s.ack, s.state.robot_mode, s.state.safety_mode
                        ),
                    },
                });
            }
        }
        let limit = trajectory.duration() + self.config.settle_time + 2.0;
        match rx.recv_timeout(Duration::from_secs_f64(limit)) {
            Ok(outcome) => Ok(outcome),
            Err(_) => {
                // The link thread never answered (it died without a job outcome): stop the
                // motion by every means left and report it.
                let job = self.link.take_job();
                let _ = self.link.write_inputs(crate::urscript::SEQ_STOP, goal);
                let _ = self.dashboard.command(&DashboardCommand::Stop);
                let status = self
                    .link
                    .status
                    .lock()
                    .unwrap_or_else(|e| e.into_inner())
                    .clone();
                let mut cycles = job.map(|j| j.cycles).unwrap_or_default();
                Ok(ExecutionOutcome::Stopped {
                    by: StoppedBy::Driver,
                    cause: match status.down {
                        Some(detail) => StopCause::ConnectionLost { detail },
                        None => StopCause::Timeout { waited: limit },
                    },
                    samples_sent: 0,
                    last_state: status.state,
                    jitter: JitterStats::from_cycles(&mut cycles, period),
                })
            }
        }
    }

    fn stop_handle(&self) -> StopHandle {
        self.stop.clone()
    }

    fn stop(&mut self) -> Result<(), ArmError> {
        self.stop.request();
        let q = self.state().map(|s| s.joints.position).unwrap_or_default();
        let r = self.link.write_inputs(crate::urscript::SEQ_STOP, &q);
        self.dashboard.command(&DashboardCommand::Stop)?;
        r
    }
}
