//! The controller's state and one control cycle: robot/safety state machine, the servo
//! program's register semantics (`firmware_iface/src/urscript/CONTRACT.md`) and the arm
//! dynamics (UR fact sheet: π rad/s joint speed, ±2π range, servoj/stopj behaviour).

use cell_types::{Flange, Joints, Tcp, Transform, JOINT_COUNT};
use firmware_iface::dashboard::{ProgramState, RobotMode, SafetyMode};
use firmware_iface::urscript::{
    ServoParams, ACK_REGISTER, ACK_STOPPED, ACK_WATCHDOG, SEQ_REGISTER, SEQ_STOP, TARGET_REGISTER,
};

/// Number of general purpose registers of each kind.
pub const REGISTER_COUNT: usize = 48;
/// Joint speed limit (rad/s).
pub const MAX_JOINT_SPEED: f64 = std::f64::consts::PI;
/// Joint position limit (rad).
pub const JOINT_LIMIT: f64 = std::f64::consts::TAU;
/// Deceleration of a protective or emergency stop (rad/s²): a category 1/2 stop is fast.
pub const SAFETY_STOP_DECEL: f64 = 20.0;
/// How long `power on` and `brake release` take before the mode changes (s).
pub const MODE_CHANGE_DELAY: f64 = 0.3;
/// How long after a protective stop it may be unlocked (s).
pub const UNLOCK_DELAY: f64 = 5.0;

/// The general purpose RTDE registers.
#[derive(Copy, Clone, Debug, PartialEq)]
pub struct Registers {
    /// input_int_register_0..47.
    pub input_int: [i32; REGISTER_COUNT],
    /// input_double_register_0..47.
    pub input_double: [f64; REGISTER_COUNT],
    /// input_bit_register_0..127 (64..127 are the named BOOL ones).
    pub input_bits: u128,
    /// output_int_register_0..47.
    pub output_int: [i32; REGISTER_COUNT],
    /// output_double_register_0..47.
    pub output_double: [f64; REGISTER_COUNT],
    /// output_bit_register_0..127.
    pub output_bits: u128,
    /// speed_slider_fraction input.
    pub speed_slider: f64,
}

impl Default for Registers {
    fn default() -> Self {
        Self {
            input_int: [0; REGISTER_COUNT],
            input_double: [0.0; REGISTER_COUNT],
            input_bits: 0,
            output_int: [0; REGISTER_COUNT],
            output_double: [0.0; REGISTER_COUNT],
            output_bits: 0,
            speed_slider: 1.0,
        }
    }
}

/// What the controller publishes each cycle: everything an RTDE output recipe can ask for.
#[derive(Copy, Clone, Debug, PartialEq)]
pub struct ControllerSnapshot {
    /// Controller time since start (s).
    pub time: f64,
    /// Cycle counter.
    pub cycle: u64,
    /// Measured joint positions (rad).
    pub actual_q: Joints,
    /// Measured joint velocities (rad/s).
    pub actual_qd: Joints,
    /// Servo target positions (rad).
    pub target_q: Joints,
    /// Commanded velocities (rad/s).
    pub target_qd: Joints,
    /// Commanded accelerations (rad/s²).
    pub target_qdd: Joints,
    /// TCP pose `[x, y, z, rx, ry, rz]` (m, rotation vector) from FK of actual_q.
    pub actual_tcp_pose: [f64; 6],
    /// TCP pose from FK of target_q.
    pub target_tcp_pose: [f64; 6],
    /// TCP linear and angular speed.
    pub actual_tcp_speed: [f64; 6],
    /// Robot mode.
    pub robot_mode: RobotMode,
    /// Safety mode.
    pub safety_mode: SafetyMode,
    /// Program state.
    pub program_state: ProgramState,
    /// Registers.
    pub registers: Registers,
}

impl ControllerSnapshot {
    /// RTDE `runtime_state`: 1 stopped, 2 playing, 3 paused... (UR numbering: 0 stopping,
    /// 1 stopped, 2 playing, 3 pausing, 4 paused, 5 resuming).
    pub fn runtime_state(&self) -> u32 {
        match self.program_state {
            ProgramState::Stopped => 1,
            ProgramState::Playing => 2,
            ProgramState::Paused => 4,
        }
    }

    /// RTDE `robot_status_bits`: power on, program running.
    pub fn robot_status_bits(&self) -> u32 {
        let powered = !matches!(
            self.robot_mode,
            RobotMode::PowerOff | RobotMode::Disconnected
        );
        u32::from(powered) | (u32::from(self.program_state == ProgramState::Playing) << 1)
    }

    /// RTDE `safety_status_bits`.
    pub fn safety_status_bits(&self) -> u32 {
        let bit = match self.safety_mode {
            SafetyMode::Normal => 0,
            SafetyMode::Reduced => 1,
            SafetyMode::ProtectiveStop => 2,
            SafetyMode::Recovery => 3,
            SafetyMode::SafeguardStop => 4,
            SafetyMode::SystemEmergencyStop => 5,
            SafetyMode::RobotEmergencyStop => 6,
            SafetyMode::Violation => 8,
            SafetyMode::Fault => 9,
        };
        let mut bits = 1u32 << bit;
        if self.safety_mode.is_emergency_stop() {
            bits |= 1 << 7;
        }
        if self.safety_mode != SafetyMode::Normal && self.safety_mode != SafetyMode::Reduced {
            bits |= 1 << 10;
        }
        bits
    }
}

/// How the arm is being driven.
#[derive(Copy, Clone, Debug, PartialEq)]
enum Motion {
    /// Brakes on or holding still.
    Hold,
    /// servoj towards `target` with feed-forward velocity `ff`.
    Servo { target: Joints, ff: Joints },
    /// Decelerating every joint at `decel` (stopj or a safety stop).
    Stopping { decel: f64 },
}

/// The running servo program's state.
#[derive(Copy, Clone, Debug, PartialEq)]
struct ServoProgram {
    params: ServoParams,
    last: i32,
    stale: u32,
    target: Joints,
}

/// Arm and controller parameters of the model.
#[derive(Copy, Clone, Debug, PartialEq)]
pub struct ArmModel {
    /// Control period (s): 0.008 CB3, 0.002 e-Series.
    pub period: f64,
    /// Largest joint acceleration the servo loop commands (rad/s²).
    pub max_accel: f64,
    /// Flange to TCP.
    pub flange_from_tcp: Transform<Flange, Tcp>,
    /// Height of the table top in the base frame (m): a link frame (elbow, wrists, flange)
    /// or the TCP below it is a collision with the scene. None disables the check.
    pub floor_z: Option<f64>,
}

/// The whole controller state, stepped once per control cycle.
#[derive(Clone, Debug)]
pub struct Core {
    model: ArmModel,
    time: f64,
    cycle: u64,
    q: Joints,
    qd: Joints,
    qdd: Joints,
    motion: Motion,
    robot_mode: RobotMode,
    safety_mode: SafetyMode,
    program_state: ProgramState,
    program_name: String,
    program: Option<ServoProgram>,
    pending_mode: Option<(RobotMode, f64)>,
    protective_stop_at: Option<f64>,
    /// Registers, written by RTDE input recipes.
    pub registers: Registers,
    prev_tcp: [f64; 6],
    events: Vec<String>,
}

/// Pose of the TCP as UR reports it: position and rotation vector.
pub fn tcp_pose(q: &Joints, flange_from_tcp: &Transform<Flange, Tcp>) -> [f64; 6] {
    let t = planner::kinematics::UR5.forward(q) * *flange_from_tcp;
    let p = t.translation();
    let r = t.rotation().scaled_axis();
    [p.x, p.y, p.z, r.x, r.y, r.z]
}

impl Core {
    /// A controller at `q`, in `robot_mode` with safety NORMAL and no program.
    pub fn new(model: ArmModel, q: Joints, robot_mode: RobotMode) -> Self {
        Self {
            model,
            time: 0.0,
            cycle: 0,
            q,
            qd: [0.0; JOINT_COUNT],
            qdd: [0.0; JOINT_COUNT],
            motion: Motion::Hold,
            robot_mode,
            safety_mode: SafetyMode::Normal,
            program_state: ProgramState::Stopped,
            program_name: "<unnamed>".into(),
            program: None,
            pending_mode: None,
            protective_stop_at: None,
            registers: Registers::default(),
            prev_tcp: tcp_pose(&q, &model.flange_from_tcp),
            events: Vec::new(),
        }
    }

    /// The model parameters.
    pub fn model(&self) -> &ArmModel {
        &self.model
    }

    /// Controller time (s).
    pub fn time(&self) -> f64 {
        self.time
    }

    /// Robot mode.
    pub fn robot_mode(&self) -> RobotMode {
        self.robot_mode
    }

    /// Safety mode.
    pub fn safety_mode(&self) -> SafetyMode {
        self.safety_mode
    }

    /// Program state and name.
    pub fn program_state(&self) -> (ProgramState, &str) {
        (self.program_state, &self.program_name)
    }

    /// Takes the events logged since the last call (mode changes, program start/stop).
    pub fn take_events(&mut self) -> Vec<String> {
        std::mem::take(&mut self.events)
    }

    fn log(&mut self, what: String) {
        self.events.push(format!("t={:.3}s {what}", self.time));
    }

    /// The published state.
    pub fn snapshot(&self) -> ControllerSnapshot {
        let target_q = match (self.motion, self.program) {
            (Motion::Servo { target, .. }, _) => target,
            _ => self.q,
        };
        let tcp = tcp_pose(&self.q, &self.model.flange_from_tcp);
        let dt = self.model.period;
        let mut speed = [0.0; 6];
        for i in 0..3 {
            speed[i] = (tcp[i] - self.prev_tcp[i]) / dt;
        }
        ControllerSnapshot {
            time: self.time,
            cycle: self.cycle,
            actual_q: self.q,
            actual_qd: self.qd,
            target_q,
            target_qd: self.qd,
            target_qdd: self.qdd,
            actual_tcp_pose: tcp,
            target_tcp_pose: tcp_pose(&target_q, &self.model.flange_from_tcp),
            actual_tcp_speed: speed,
            robot_mode: self.robot_mode,
            safety_mode: self.safety_mode,
            program_state: self.program_state,
            registers: self.registers,
        }
    }

    /// Dashboard `power on`.
    pub fn power_on(&mut self) {
        if self.robot_mode == RobotMode::PowerOff {
            self.robot_mode = RobotMode::PowerOn;
            self.pending_mode = Some((RobotMode::Idle, self.time + MODE_CHANGE_DELAY));
            self.log("power on".into());
        }
    }

    /// Dashboard `power off`.
    pub fn power_off(&mut self) {
        self.stop_program("power off");
        self.robot_mode = RobotMode::PowerOff;
        self.pending_mode = None;
        self.qd = [0.0; JOINT_COUNT];
        self.motion = Motion::Hold;
    }

    /// Dashboard `brake release`.
    pub fn brake_release(&mut self) {
        if self.robot_mode == RobotMode::Idle && !self.safety_mode.is_emergency_stop() {
            self.pending_mode = Some((RobotMode::Running, self.time + MODE_CHANGE_DELAY));
            self.log("brake release".into());
        }
    }

    /// Dashboard `unlock protective stop`: false when refused (less than 5 s after the stop).
    pub fn unlock_protective_stop(&mut self) -> bool {
        match (self.safety_mode, self.protective_stop_at) {
            (SafetyMode::ProtectiveStop, Some(at)) if self.time - at < UNLOCK_DELAY => false,
            (SafetyMode::ProtectiveStop, _) => {
                self.safety_mode = SafetyMode::Normal;
                self.protective_stop_at = None;
                self.log("protective stop unlocked".into());
                true
            }
            _ => true,
        }
    }

    /// True when a program may start (RUNNING and NORMAL).
    pub fn can_run(&self) -> bool {
        self.robot_mode == RobotMode::Running && self.safety_mode == SafetyMode::Normal
    }

    /// Starts our servo program (replacing any running one, as the real controller does).
    pub fn start_servo_program(&mut self, params: ServoParams) -> Result<(), String> {
        if !self.can_run() {
            return Err(format!(
                "program not started: robot mode {} and safety mode {}; power on, release the brakes and clear stops first",
                self.robot_mode.name(),
                self.safety_mode.name()
            ));
        }
        self.program = Some(ServoProgram {
            params,
            last: 0,
            stale: 0,
            target: self.q,
        });
        self.program_state = ProgramState::Playing;
        self.program_name = "equact_servo".into();
        self.registers.output_int[ACK_REGISTER] = 0;
        self.log("servo program started".into());
        Ok(())
    }

    /// Dashboard `play`: resumes a paused program; false when nothing can run.
    pub fn play(&mut self) -> bool {
        if self.program_state == ProgramState::Paused && self.can_run() {
            self.program_state = ProgramState::Playing;
            return true;
        }
        false
    }

    /// Dashboard `pause`.
    pub fn pause(&mut self) {
        if self.program_state == ProgramState::Playing {
            self.program_state = ProgramState::Paused;
            self.motion = Motion::Stopping {
                decel: self
                    .program
                    .map_or(SAFETY_STOP_DECEL, |p| p.params.stop_decel),
            };
        }
    }

    /// Stops the running program (dashboard `stop`, a safety stop, power off).
    pub fn stop_program(&mut self, why: &str) {
        if self.program_state != ProgramState::Stopped {
            let decel = self
                .program
                .map_or(SAFETY_STOP_DECEL, |p| p.params.stop_decel);
            self.program_state = ProgramState::Stopped;
            self.program = None;
            self.motion = Motion::Stopping { decel };
            self.log(format!("program stopped: {why}"));
        }
    }

    /// Raises a protective stop (fault injection, joint limit, collision).
    pub fn protective_stop(&mut self, why: &str) {
        if self.safety_mode == SafetyMode::Normal {
            self.safety_mode = SafetyMode::ProtectiveStop;
            self.protective_stop_at = Some(self.time);
            self.stop_program(why);
            self.motion = Motion::Stopping {
                decel: SAFETY_STOP_DECEL,
            };
            self.log(format!("protective stop: {why}"));
        }
    }

    /// Raises a robot emergency stop: program stopped, arm stopped, brakes engaged (IDLE).
    pub fn emergency_stop(&mut self) {
        self.safety_mode = SafetyMode::RobotEmergencyStop;
        self.stop_program("emergency stop");
        self.motion = Motion::Stopping {
            decel: SAFETY_STOP_DECEL,
        };
        self.log("emergency stop".into());
    }

    /// Releases an emergency stop: safety NORMAL, robot IDLE (brakes to be released again).
    pub fn release_emergency_stop(&mut self) {
        if self.safety_mode.is_emergency_stop() {
            self.safety_mode = SafetyMode::Normal;
            if self.robot_mode == RobotMode::Running {
                self.robot_mode = RobotMode::Idle;
            }
            self.log("emergency stop released".into());
        }
    }

    /// Runs one control cycle.
    pub fn step(&mut self) {
        self.cycle_once(true);
    }

    /// Runs one control cycle that started late, back to back with others after the
    /// control thread was starved of CPU: the client had no time to answer it, so the servo
    /// program's watchdog does not count it. (A real controller never runs late; without
    /// this, a stall of the simulator's own thread would be blamed on the client.)
    pub fn step_late(&mut self) {
        self.cycle_once(false);
    }

    fn cycle_once(&mut self, on_time: bool) {
        let dt = self.model.period;
        self.prev_tcp = tcp_pose(&self.q, &self.model.flange_from_tcp);
        self.time += dt;
        self.cycle += 1;
        if let Some((mode, at)) = self.pending_mode {
            if self.time >= at {
                self.robot_mode = mode;
                self.pending_mode = None;
                self.log(format!("robot mode {}", mode.name()));
            }
        }
        if self.program_state == ProgramState::Playing {
            self.run_program(on_time);
        }
        self.move_arm(dt);
    }

    /// One cycle of the servo program; `on_time` says whether a stale sequence word counts
    /// toward the watchdog (see [`Core::step_late`]).
    fn run_program(&mut self, on_time: bool) {
        let Some(mut p) = self.program else {
            return;
        };
        let seq = self.registers.input_int[SEQ_REGISTER];
        if seq == SEQ_STOP {
            self.registers.output_int[ACK_REGISTER] = ACK_STOPPED;
            self.stop_program("stop requested by the client (sequence word -1)");
            return;
        }
        if seq > 0 && seq != p.last {
            // Targets stream one per cycle; when the client's packages bunch up (a loaded
            // host), several arrive within one cycle and only the newest is read. The target
            // then moved `steps` samples: its velocity is the jump over that many cycles, not
            // over one (which would double the feed-forward and run the arm ahead).
            let steps = if p.last > 0 {
                f64::from(seq.wrapping_sub(p.last).clamp(1, 10))
            } else {
                1.0
            };
            p.last = seq;
            p.stale = 0;
            let mut target = [0.0; JOINT_COUNT];
            target.copy_from_slice(
                &self.registers.input_double[TARGET_REGISTER..TARGET_REGISTER + JOINT_COUNT],
            );
            let prev = match self.motion {
                Motion::Servo { target, .. } => target,
                _ => self.q,
            };
            let ff = std::array::from_fn(|i| (target[i] - prev[i]) / (steps * p.params.cycle));
            p.target = target;
            self.motion = Motion::Servo { target, ff };
            self.registers.output_int[ACK_REGISTER] = seq;
        } else if seq > 0 {
            if on_time {
                p.stale += 1;
            }
            if p.stale > p.params.watchdog_cycles {
                self.registers.output_int[ACK_REGISTER] = ACK_WATCHDOG;
                self.stop_program("watchdog: sequence word did not advance");
                return;
            }
            // The program keeps servoing to its last target: no feed-forward any more.
            self.motion = Motion::Servo {
                target: p.target,
                ff: [0.0; JOINT_COUNT],
            };
        }
        self.program = Some(p);
    }

    // Index loops: each joint reads and writes several parallel arrays.
    #[allow(clippy::needless_range_loop)]
    fn move_arm(&mut self, dt: f64) {
        if matches!(
            self.robot_mode,
            RobotMode::PowerOff | RobotMode::PowerOn | RobotMode::Idle
        ) {
            self.qd = [0.0; JOINT_COUNT];
            self.qdd = [0.0; JOINT_COUNT];
            return;
        }
        let old = self.qd;
        match self.motion {
            Motion::Hold => self.qd = [0.0; JOINT_COUNT],
            Motion::Servo { target, ff } => {
                // servoj model: the controller tracks the target with a first-order filter
                // whose time constant grows with lookahead and shrinks with gain (gain 300,
                // lookahead 0.1 s -> 0.1 s), plus the target's own velocity as feed-forward,
                // limited by joint speed and acceleration like the real trajectory generator.
                let params = self.program.map(|p| p.params).unwrap_or_default();
                let tau = (params.lookahead * 300.0 / params.gain).max(2.0 * dt);
                let max_dv = self.model.max_accel * dt;
                for i in 0..JOINT_COUNT {
                    let want = (ff[i] + (target[i] - self.q[i]) / tau)
                        .clamp(-MAX_JOINT_SPEED, MAX_JOINT_SPEED);
                    self.qd[i] = old[i] + (want - old[i]).clamp(-max_dv, max_dv);
                }
            }
            Motion::Stopping { decel } => {
                let dv = decel * dt;
                let mut moving = false;
                for v in self.qd.iter_mut() {
                    *v -= v.signum() * v.abs().min(dv);
                    moving |= *v != 0.0;
                }
                if !moving {
                    self.motion = Motion::Hold;
                }
            }
        }
        for i in 0..JOINT_COUNT {
            self.qdd[i] = (self.qd[i] - old[i]) / dt;
            self.q[i] += 0.5 * (old[i] + self.qd[i]) * dt;
        }
        if let Some(floor) = self.model.floor_z {
            let frames = planner::kinematics::UR5.link_frames(&self.q);
            let tcp = tcp_pose(&self.q, &self.model.flange_from_tcp);
            // Frames 0..=1 sit on the base column and never move vertically.
            let low = frames[2..]
                .iter()
                .map(|f| f.translation.vector.z)
                .chain(std::iter::once(tcp[2]))
                .fold(f64::INFINITY, f64::min);
            if low < floor {
                self.qd = [0.0; JOINT_COUNT];
                self.protective_stop(&format!(
                    "collision with the table: a link reached z = {low:.3} m below {floor:.3} m"
                ));
            }
        }
        if let Some(j) = (0..JOINT_COUNT).find(|&j| self.q[j].abs() > JOINT_LIMIT) {
            self.q[j] = self.q[j].clamp(-JOINT_LIMIT, JOINT_LIMIT);
            self.qd[j] = 0.0;
            self.protective_stop(&format!("joint {} position limit", j + 1));
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn model() -> ArmModel {
        ArmModel {
            period: 0.008,
            max_accel: 15.0,
            flange_from_tcp: Transform::identity(),
            floor_z: Some(0.0),
        }
    }

    fn running_core() -> Core {
        Core::new(
            model(),
            [0.0, -1.57, 1.57, -1.57, -1.57, 0.0],
            RobotMode::Running,
        )
    }

    #[test]
    fn power_on_and_brake_release_take_time() {
        let mut c = Core::new(model(), [0.0; 6], RobotMode::PowerOff);
        c.brake_release();
        c.power_on();
        assert_eq!(c.robot_mode(), RobotMode::PowerOn);
        for _ in 0..50 {
            c.step();
        }
        assert_eq!(c.robot_mode(), RobotMode::Idle);
        c.brake_release();
        assert_eq!(c.robot_mode(), RobotMode::Idle);
        for _ in 0..50 {
            c.step();
        }
        assert_eq!(c.robot_mode(), RobotMode::Running);
    }

    #[test]
    fn servo_program_tracks_targets_and_stops_on_watchdog() {
        let mut c = running_core();
        let start = c.snapshot().actual_q;
        c.start_servo_program(ServoParams::default()).unwrap();
        let mut target = start;
        for k in 1..=200 {
            target[0] = start[0] + 0.5 * (k as f64 / 200.0);
            c.registers.input_int[SEQ_REGISTER] = k;
            c.registers.input_double[24..30].copy_from_slice(&target);
            c.step();
            assert_eq!(c.snapshot().registers.output_int[ACK_REGISTER], k);
            assert!(c.snapshot().actual_qd[0].abs() <= MAX_JOINT_SPEED);
        }
        // No new sequence: after more than 10 stale cycles the watchdog stops the program.
        stale_cycles_trip_the_watchdog(&mut c);
        for _ in 0..200 {
            c.step();
        }
        let s = c.snapshot();
        assert!(s.actual_qd.iter().all(|v| *v == 0.0));
        assert!((s.actual_q[0] - target[0]).abs() < 0.01, "{:?}", s.actual_q);
    }

    #[test]
    fn late_cycles_do_not_count_toward_the_watchdog() {
        let mut c = running_core();
        c.start_servo_program(ServoParams::default()).unwrap();
        c.registers.input_int[SEQ_REGISTER] = 1;
        let q = c.snapshot().actual_q;
        c.registers.input_double[24..30].copy_from_slice(&q);
        c.step();
        assert_eq!(c.snapshot().registers.output_int[ACK_REGISTER], 1);
        // A burst of catch-up cycles longer than the watchdog: the program keeps running.
        for _ in 0..30 {
            c.step_late();
        }
        assert_eq!(c.program_state().0, ProgramState::Playing);
        // On-time stale cycles still count, from where the last on-time cycle left off.
        stale_cycles_trip_the_watchdog(&mut c);
    }

    /// Ten more on-time cycles without a new sequence word leave the program playing; the
    /// eleventh stops it with the watchdog's acknowledgement.
    fn stale_cycles_trip_the_watchdog(c: &mut Core) {
        for _ in 0..10 {
            c.step();
        }
        assert_eq!(c.program_state().0, ProgramState::Playing);
        c.step();
        assert_eq!(c.program_state().0, ProgramState::Stopped);
        assert_eq!(
            c.snapshot().registers.output_int[ACK_REGISTER],
            ACK_WATCHDOG
        );
    }

    #[test]
    fn protective_stop_stops_program_and_unlock_needs_five_seconds() {
        let mut c = running_core();
        c.start_servo_program(ServoParams::default()).unwrap();
        c.protective_stop("test");
        assert_eq!(c.safety_mode(), SafetyMode::ProtectiveStop);
        assert_eq!(c.program_state().0, ProgramState::Stopped);
        assert!(c.start_servo_program(ServoParams::default()).is_err());
        for _ in 0..(4.9 / 0.008) as usize {
            c.step();
        }
        assert!(!c.unlock_protective_stop());
        for _ in 0..20 {
            c.step();
        }
        assert!(c.unlock_protective_stop());
        assert_eq!(c.safety_mode(), SafetyMode::Normal);
    }

    #[test]
    fn driving_the_tool_into_the_table_raises_protective_stop() {
        let mut c = running_core();
        c.start_servo_program(ServoParams::default()).unwrap();
        let start = c.snapshot().actual_q;
        // Shoulder down: the forearm and wrist swing into the table.
        for k in 1..400 {
            let mut q = start;
            q[1] = start[1] + 2.0 * (k as f64 / 400.0);
            c.registers.input_int[SEQ_REGISTER] = k;
            c.registers.input_double[24..30].copy_from_slice(&q);
            c.step();
            if c.safety_mode() != SafetyMode::Normal {
                break;
            }
        }
        assert_eq!(c.safety_mode(), SafetyMode::ProtectiveStop);
        assert!(c
            .take_events()
            .iter()
            .any(|e| e.contains("collision with the table")));
        assert!(c.snapshot().actual_tcp_pose[2] > -0.05);
    }

    #[test]
    fn joint_limit_raises_protective_stop() {
        let mut c = Core::new(model(), [6.25, 0.0, 0.0, 0.0, 0.0, 0.0], RobotMode::Running);
        c.start_servo_program(ServoParams::default()).unwrap();
        for k in 1..100 {
            c.registers.input_int[SEQ_REGISTER] = k;
            c.registers.input_double[24] = 7.0;
            c.step();
        }
        assert_eq!(c.safety_mode(), SafetyMode::ProtectiveStop);
        assert!(c.snapshot().actual_q[0] <= JOINT_LIMIT);
    }
}
