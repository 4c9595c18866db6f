//! The RTDE client: negotiation and recipes at connect, then one thread that reads every
//! state package at the controller rate and, while a motion runs, answers each with the next
//! servo target. The package arrival is the loop's clock, as in UR's own control-loop
//! example; the thread allocates nothing per cycle (fixed buffers, preallocated cycle log).

use std::io::{Read, Write};
use std::net::{SocketAddr, TcpStream};
use std::sync::mpsc::{sync_channel, SyncSender};
use std::sync::{Arc, Condvar, Mutex, MutexGuard};
use std::time::{Duration, Instant};

use cell_types::{Clock, JointState, TrajectorySample, JOINT_COUNT};

use crate::arm::{
    ArmError, ArmState, ExecutionOutcome, JitterStats, StopCause, StopHandle, StoppedBy,
};
use crate::dashboard::{RobotMode, SafetyMode};
use crate::realtime::Scheduling;
use crate::rtde::robot_to_host::borrow_data_package;
use crate::rtde::{
    split_package, ControllerVersion, DataType, FieldType, HostMessage, Layout, ProtocolVersion,
    RobotMessage, Value, DATA_PACKAGE,
};
use crate::urscript::{SEQ_HOLD, SEQ_STOP};

/// Output recipe, in this order.
pub const OUTPUTS: [&str; 9] = [
    "timestamp",
    "actual_q",
    "actual_qd",
    "target_q",
    "actual_TCP_pose",
    "robot_mode",
    "safety_mode",
    "runtime_state",
    "output_int_register_24",
];

/// Input recipe, in this order.
pub const INPUTS: [&str; 7] = [
    "input_int_register_24",
    "input_double_register_24",
    "input_double_register_25",
    "input_double_register_26",
    "input_double_register_27",
    "input_double_register_28",
    "input_double_register_29",
];

/// How long input setup keeps asking while inputs are IN_USE: a controller releases a closed
/// client's inputs only once it notices the close, so an immediate reconnect (preflight, then
/// the run) can briefly find its own previous session still holding them.
pub const INPUT_RELEASE_GRACE: Duration = Duration::from_secs(1);

/// Pause between input setup requests within [`INPUT_RELEASE_GRACE`].
const INPUT_RELEASE_POLL: Duration = Duration::from_millis(20);

fn io(source: std::io::Error) -> ArmError {
    ArmError::Io {
        service: "RTDE",
        source,
    }
}

fn lock<T>(m: &Mutex<T>) -> MutexGuard<'_, T> {
    m.lock().unwrap_or_else(|e| e.into_inner())
}

/// What the link knows right now.
#[derive(Clone, Debug, Default)]
pub struct LinkStatus {
    /// Latest state.
    pub state: ArmState,
    /// Latest acknowledgement word.
    pub ack: i32,
    /// Packages received.
    pub packages: u64,
    /// Set when the link died, with the reason.
    pub down: Option<String>,
}

/// Every state package received, with the local clock's receive time, in a buffer
/// allocated once at connect (the link thread never allocates for it): the controller-rate
/// history that recordings need. When nobody drains it and it is full, new states are
/// counted as dropped instead of stored.
#[derive(Debug, Default)]
pub(crate) struct StateLog {
    entries: Vec<(Duration, ArmState)>,
    dropped: u64,
}

impl StateLog {
    /// Seconds of history kept between drains.
    const SECONDS: f64 = 60.0;

    fn with_period(period: f64) -> Self {
        let capacity = (Self::SECONDS / period).ceil() as usize;
        Self {
            entries: Vec::with_capacity(capacity),
            dropped: 0,
        }
    }

    fn push(&mut self, at: Duration, state: ArmState) {
        if self.entries.len() < self.entries.capacity() {
            self.entries.push((at, state));
        } else {
            self.dropped += 1;
        }
    }

    /// Moves the entries into `out` (keeping this buffer's capacity); returns and resets the
    /// dropped count.
    pub(crate) fn drain_into(&mut self, out: &mut Vec<(Duration, ArmState)>) -> u64 {
        out.append(&mut self.entries);
        std::mem::take(&mut self.dropped)
    }
}

/// Parameters of one motion, handed to the link thread.
pub(crate) struct Job {
    pub samples: Vec<TrajectorySample>,
    pub tracking_bound: f64,
    /// How many samples the arm may trail the stream (the servo filter's lag).
    pub lag_samples: usize,
    pub lost_cycles: u32,
    pub goal_tolerance: f64,
    pub settle_cycles: u32,
    pub stop: StopHandle,
    pub done: SyncSender<ExecutionOutcome>,
    pub cycles: Vec<f64>,
    /// Installed before the servo program started: the link answers from the first package
    /// that shows it running (and its acknowledgement word cleared), not from whichever
    /// package follows the caller's wake-up.
    pub awaiting_program: bool,
}

/// Shared between the driver and its link thread.
pub(crate) struct Link {
    pub status: Mutex<LinkStatus>,
    pub state_log: Mutex<StateLog>,
    pub changed: Condvar,
    pub job: Mutex<Option<Job>>,
    writer: Mutex<TcpStream>,
    in_layout: Layout,
    in_recipe: u8,
    pub version: ProtocolVersion,
    pub controller: ControllerVersion,
    pub period: f64,
}

struct Conn {
    s: TcpStream,
    buf: Vec<u8>,
    v: ProtocolVersion,
}

impl Conn {
    fn send(&mut self, m: &HostMessage) -> Result<(), ArmError> {
        let b = m.encode(self.v)?;
        self.s.write_all(&b).map_err(io)
    }
    fn recv(&mut self) -> Result<RobotMessage, ArmError> {
        loop {
            if let Some((raw, n)) = split_package(&self.buf)? {
                let m = RobotMessage::decode(self.v, raw)?;
                self.buf.drain(..n);
                // Text messages may arrive before any reply: skip them here.
                if let RobotMessage::Text(_) = m {
                    continue;
                }
                return Ok(m);
            }
            let mut c = [0u8; 4096];
            let n = self.s.read(&mut c).map_err(io)?;
            if n == 0 {
                return Err(ArmError::Protocol {
                    service: "RTDE",
                    detail: "connection closed by the controller during setup".into(),
                });
            }
            self.buf.extend_from_slice(&c[..n]);
        }
    }
    fn ask(&mut self, m: &HostMessage) -> Result<RobotMessage, ArmError> {
        self.send(m)?;
        self.recv()
    }
}

fn unexpected(what: &str, m: &RobotMessage) -> ArmError {
    ArmError::Protocol {
        service: "RTDE",
        detail: format!("expected {what}, got {m:?}"),
    }
}

fn check_types(names: &[&str], types: &[FieldType]) -> Result<Vec<DataType>, ArmError> {
    let pick = |want: FieldType| -> Vec<String> {
        names
            .iter()
            .zip(types)
            .filter(|(_, t)| **t == want)
            .map(|(n, _)| n.to_string())
            .collect()
    };
    let in_use = pick(FieldType::InUse);
    if !in_use.is_empty() {
        return Err(ArmError::InputsInUse { names: in_use });
    }
    let nf = pick(FieldType::NotFound);
    if !nf.is_empty() {
        return Err(ArmError::NotFound { names: nf });
    }
    if types.len() != names.len() {
        return Err(ArmError::Protocol {
            service: "RTDE",
            detail: format!("{} types for {} names", types.len(), names.len()),
        });
    }
    Ok(types
        .iter()
        .filter_map(|t| match t {
            FieldType::Type(d) => Some(*d),
            _ => None,
        })
        .collect())
}

impl Link {
    /// Connects, negotiates (v2, falling back to v1 unless `force_v1`), sets up both recipes
    /// at the controller's full rate, starts, and spawns the link thread.
    pub(crate) fn connect(
        addr: SocketAddr,
        timeout: Duration,
        force_v1: bool,
        clock: Arc<dyn Clock>,
        realtime_priority: Option<u8>,
    ) -> Result<(Arc<Link>, Scheduling), ArmError> {
        let s = TcpStream::connect_timeout(&addr, timeout).map_err(|source| ArmError::Connect {
            service: "RTDE interface",
            addr,
            source,
        })?;
        s.set_nodelay(true).map_err(io)?;
        s.set_read_timeout(Some(timeout)).map_err(io)?;
        let mut c = Conn {
            s,
            buf: Vec::with_capacity(8192),
            v: ProtocolVersion::V1,
        };
        let mut version = ProtocolVersion::V1;
        let tries: &[ProtocolVersion] = if force_v1 {
            &[ProtocolVersion::V1]
        } else {
            &[ProtocolVersion::V2, ProtocolVersion::V1]
        };
        let mut accepted = false;
        for v in tries {
            match c.ask(&HostMessage::RequestProtocolVersion(v.number()))? {
                RobotMessage::ProtocolVersionAccepted(true) => {
                    version = *v;
                    accepted = true;
                    break;
                }
                RobotMessage::ProtocolVersionAccepted(false) => {}
                m => return Err(unexpected("protocol version reply", &m)),
            }
        }
        if !accepted {
            return Err(ArmError::Protocol {
                service: "RTDE",
                detail: "controller accepts neither RTDE protocol 2 nor 1".into(),
            });
        }
        c.v = version;
        let controller = match c.ask(&HostMessage::GetControllerVersion)? {
            RobotMessage::ControllerVersion(v) => v,
            m => return Err(unexpected("controller version", &m)),
        };
        let freq = controller.max_frequency();
        let out_types = match c.ask(&HostMessage::SetupOutputs {
            frequency: Some(freq),
            names: OUTPUTS.iter().map(|s| s.to_string()).collect(),
        })? {
            RobotMessage::SetupOutputs { recipe_id, types } => {
                let t = check_types(&OUTPUTS, &types)?;
                if recipe_id == Some(0) {
                    return Err(ArmError::Protocol {
                        service: "RTDE",
                        detail: format!(
                            "controller refused the output recipe at {freq} Hz (recipe id 0)"
                        ),
                    });
                }
                t
            }
            m => return Err(unexpected("output setup reply", &m)),
        };
        let out_layout = Layout::new(&out_types);
        let asked = Instant::now();
        let setup_reply = loop {
            let reply = c.ask(&HostMessage::SetupInputs {
                names: INPUTS.iter().map(|s| s.to_string()).collect(),
            })?;
            // A client that has just closed its connection (ours, a moment ago) still owns
            // its inputs until the controller notices the close: ask again for a moment
            // before calling them taken.
            if let RobotMessage::SetupInputs { types, .. } = &reply {
                if types.contains(&FieldType::InUse) && asked.elapsed() < INPUT_RELEASE_GRACE {
                    std::thread::sleep(INPUT_RELEASE_POLL);
                    continue;
                }
            }
            break reply;
        };
        let (in_recipe, in_types) = match setup_reply {
            RobotMessage::SetupInputs { recipe_id, types } => {
                let t = check_types(&INPUTS, &types)?;
                if recipe_id == 0 {
                    return Err(ArmError::Protocol {
                        service: "RTDE",
                        detail: "controller refused the input recipe (recipe id 0)".into(),
                    });
                }
                (recipe_id, t)
            }
            m => return Err(unexpected("input setup reply", &m)),
        };
        let in_layout = Layout::new(&in_types);
        match c.ask(&HostMessage::Start)? {
            RobotMessage::StartAccepted(true) => {}
            m => return Err(unexpected("start accepted", &m)),
        }
        let period = 1.0 / freq;
        let writer = c.s.try_clone().map_err(io)?;
        let link = Arc::new(Link {
            status: Mutex::new(LinkStatus::default()),
            state_log: Mutex::new(StateLog::with_period(period)),
            changed: Condvar::new(),
            job: Mutex::new(None),
            writer: Mutex::new(writer),
            in_layout,
            in_recipe,
            version,
            controller,
            period,
        });
        // Reads time out after one period so that missing packages are noticed per cycle.
        c.s.set_read_timeout(Some(Duration::from_secs_f64(period)))
            .map_err(io)?;
        let l = link.clone();
        // The thread waits at this gate until its priority is set, so that it answers no
        // package at normal priority (the request needs the thread's handle first).
        let (go, gate) = sync_channel::<()>(1);
        let thread = std::thread::Builder::new()
            .name("ur-rtde-link".into())
            .spawn(move || {
                let _ = gate.recv();
                l.run(c, out_layout, clock)
            })
            .map_err(io)?;
        let scheduling = match realtime_priority {
            Some(p) => crate::realtime::request_fifo(&thread, p),
            None => Scheduling::Normal,
        };
        let _ = go.send(());
        if let Scheduling::Refused { .. } = &scheduling {
            log::warn!("UR driver link thread: {scheduling}");
        }
        // Detached, as before: the thread ends when the connection closes.
        drop(thread);
        Ok((link, scheduling))
    }

    /// Writes the sequence word and targets (one input package; no allocation).
    pub(crate) fn write_inputs(&self, seq: i32, q: &[f64; JOINT_COUNT]) -> Result<(), ArmError> {
        let mut pkg = [0u8; 4 + 4 + 6 * 8];
        let n = 4 + self.in_layout.size();
        pkg[2] = DATA_PACKAGE;
        pkg[3] = self.in_recipe;
        let values = &mut pkg[4..n];
        self.in_layout.set(values, 0, Value::Int32(seq))?;
        for (j, x) in q.iter().enumerate() {
            self.in_layout.set(values, 1 + j, Value::Double(*x))?;
        }
        let size = n as u16;
        pkg[..2].copy_from_slice(&size.to_be_bytes());
        lock(&self.writer).write_all(&pkg[..n]).map_err(io)
    }

    /// Hands `job` to the link thread (it streams once the program has started).
    pub(crate) fn set_job(&self, job: Job) {
        *lock(&self.job) = Some(job);
    }

    /// Takes the job back from the link thread (`None`: it has finished it already).
    pub(crate) fn take_job(&self) -> Option<Job> {
        lock(&self.job).take()
    }

    /// Takes the job back if the link thread has not seen its program start yet; whether
    /// it did.
    pub(crate) fn take_unstarted_job(&self) -> bool {
        let mut slot = lock(&self.job);
        let unstarted = slot.as_ref().is_some_and(|j| j.awaiting_program);
        if unstarted {
            slot.take();
        }
        unstarted
    }

    /// Closes the RTDE socket; the link thread sees the end of the stream and exits.
    pub(crate) fn close(&self) {
        let _ = lock(&self.writer).shutdown(std::net::Shutdown::Both);
    }

    /// Blocks until the status satisfies `pred` or `timeout` passes; returns the status.
    pub(crate) fn wait_for(
        &self,
        timeout: Duration,
        pred: impl Fn(&LinkStatus) -> bool,
    ) -> Result<LinkStatus, Box<LinkStatus>> {
        let g = lock(&self.status);
        let (g, _) = self
            .changed
            .wait_timeout_while(g, timeout, |s| !pred(s) && s.down.is_none())
            .unwrap_or_else(|e| e.into_inner());
        if pred(&g) {
            Ok(g.clone())
        } else {
            Err(Box::new(g.clone()))
        }
    }

    fn decode(layout: &Layout, v: &[u8], st: &mut LinkStatus) -> Result<(), ArmError> {
        let s = &mut st.state;
        s.controller_time = layout.get_f64(v, 0)?;
        s.joints = JointState {
            position: layout.get_vec6(v, 1)?,
            velocity: layout.get_vec6(v, 2)?,
        };
        s.target_q = layout.get_vec6(v, 3)?;
        s.tcp_pose = layout.get_vec6(v, 4)?;
        s.robot_mode =
            RobotMode::from_code(layout.get_i32(v, 5)?).unwrap_or(RobotMode::NoController);
        s.safety_mode = SafetyMode::from_code(layout.get_i32(v, 6)?).unwrap_or(SafetyMode::Fault);
        s.program_running = layout.get_u32(v, 7)? == 2;
        st.ack = layout.get_i32(v, 8)?;
        st.packages += 1;
        Ok(())
    }

    fn run(self: Arc<Self>, mut c: Conn, layout: Layout, clock: Arc<dyn Clock>) {
        let mut buf = [0u8; 8192];
        let mut filled = 0usize;
        let mut last_rx = clock.now();
        let mut streamer = Streamer::default();
        loop {
            // Consume every complete package in the buffer.
            let mut at = 0;
            let mut got_data = false;
            loop {
                let (raw, used) = match split_package(&buf[at..filled]) {
                    Ok(Some(p)) => p,
                    Ok(None) => break,
                    Err(e) => return self.die(format!("bad RTDE stream: {e}")),
                };
                if raw.kind == DATA_PACKAGE {
                    let values = match borrow_data_package(self.version, raw) {
                        Ok((_, v)) => v,
                        Err(e) => return self.die(format!("bad data package: {e}")),
                    };
                    let mut st = lock(&self.status);
                    if let Err(e) = Self::decode(&layout, values, &mut st) {
                        drop(st);
                        return self.die(format!("data package does not match the recipe: {e}"));
                    }
                    lock(&self.state_log).push(clock.now(), st.state);
                    got_data = true;
                }
                at += used;
            }
            if at > 0 {
                buf.copy_within(at..filled, 0);
                filled -= at;
            }
            let now = clock.now();
            if got_data {
                let cycle = (now - last_rx).as_secs_f64();
                last_rx = now;
                self.changed.notify_all();
                let status = lock(&self.status).clone_state();
                streamer.on_package(&self, cycle, &status);
            } else {
                let missed = ((now - last_rx).as_secs_f64() / self.period) as u32;
                streamer.on_silence(&self, missed);
            }
            if filled == buf.len() {
                return self.die("RTDE package larger than the receive buffer".into());
            }
            match c.s.read(&mut buf[filled..]) {
                Ok(0) => {
                    // Mark the link down before reporting, so a caller that sees the outcome
                    // also sees the link as down.
                    self.die("connection closed by the controller".into());
                    return streamer.on_link_lost(&self, "connection closed by the controller");
                }
                Ok(n) => filled += n,
                Err(e)
                    if matches!(
                        e.kind(),
                        std::io::ErrorKind::WouldBlock | std::io::ErrorKind::TimedOut
                    ) => {}
                Err(e) => {
                    let why = format!("read failed: {e}");
                    self.die(why.clone());
                    return streamer.on_link_lost(&self, &why);
                }
            }
        }
    }

    fn die(&self, why: String) {
        lock(&self.status).down = Some(why);
        self.changed.notify_all();
    }
}

impl LinkStatus {
    fn clone_state(&self) -> (ArmState, i32) {
        (self.state, self.ack)
    }
}

/// The per-motion state of the link thread.
#[derive(Default)]
struct Streamer {
    index: usize,
    seq: i32,
    settled_for: u32,
    settle_cycles: u32,
    max_err: f64,
    started: bool,
    /// Packages since the stop word ended a motion that reached its goal, while waiting for
    /// the program to end (`None`: still streaming).
    ending: Option<u32>,
}

/// Whether our servo program runs with its acknowledgement word cleared: the state a job
/// waits for before it streams (a program still ending, or not yet started, fails it).
pub(crate) fn servo_program_started(state: &ArmState, ack: i32) -> bool {
    state.program_running && ack == 0
}

/// After a motion reached its goal and the stop word went out, how long (s) the driver waits
/// for the servo program to end (its `stopj` brings the last sub-millimetre creep to rest)
/// before it reports the motion completed anyway.
pub(crate) const PROGRAM_END_WAIT_S: f64 = 0.25;

impl Streamer {
    fn finish(
        &mut self,
        link: &Link,
        job: &mut Job,
        outcome: impl FnOnce(JitterStats) -> ExecutionOutcome,
    ) {
        let jitter = JitterStats::from_cycles(&mut job.cycles, link.period);
        let _ = job.done.try_send(outcome(jitter));
        *self = Streamer::default();
    }

    fn stop(
        &mut self,
        link: &Link,
        by: StoppedBy,
        cause: StopCause,
        state: ArmState,
        hold: [f64; 6],
    ) {
        let _ = link.write_inputs(SEQ_STOP, &hold);
        let mut slot = lock(&link.job);
        if let Some(mut job) = slot.take() {
            let sent = self.index;
            self.finish(link, &mut job, |jitter| ExecutionOutcome::Stopped {
                by,
                cause,
                samples_sent: sent,
                last_state: state,
                jitter,
            });
        }
    }

    fn on_package(&mut self, link: &Link, cycle: f64, (state, ack): &(ArmState, i32)) {
        let mut slot = lock(&link.job);
        let Some(job) = slot.as_mut() else {
            return;
        };
        let Some(last_sample) = job.samples.len().checked_sub(1) else {
            // execute() never hands over an empty trajectory; finish rather than index.
            drop(slot);
            return self.stop(
                link,
                StoppedBy::Driver,
                StopCause::Requested,
                *state,
                state.joints.position,
            );
        };
        if job.awaiting_program {
            if !servo_program_started(state, *ack) {
                // Still the upload's few cycles: nothing to answer yet.
                return;
            }
            job.awaiting_program = false;
        }
        if !self.started {
            self.started = true;
            self.settle_cycles = job.settle_cycles;
        } else if job.cycles.len() < job.cycles.capacity() {
            job.cycles.push(cycle);
        }
        if let Some(packages) = self.ending {
            // The goal was reached and the stop word sent: the motion is complete once the
            // program has ended and the arm is at rest, so that the state it reports (and
            // the next motion starts from) is where the arm stays, not one from the last
            // cycles of its creep (which package that is would depend on timing).
            let waited = f64::from(packages) * link.period;
            let safety_stop =
                state.safety_mode != SafetyMode::Normal || state.robot_mode != RobotMode::Running;
            if !state.program_running || safety_stop || waited >= PROGRAM_END_WAIT_S {
                let max_err = self.max_err;
                let final_state = *state;
                if let Some(mut job) = slot.take() {
                    drop(slot);
                    self.finish(link, &mut job, |jitter| ExecutionOutcome::Completed {
                        final_state,
                        max_tracking_error: max_err,
                        jitter,
                    });
                }
            } else {
                self.ending = Some(packages + 1);
            }
            return;
        }
        let q = state.joints.position;
        let last = self.index.saturating_sub(1).min(job.samples.len() - 1);
        let cause = if state.safety_mode == SafetyMode::ProtectiveStop {
            Some((StoppedBy::Controller, StopCause::ProtectiveStop))
        } else if state.safety_mode.is_emergency_stop() {
            Some((StoppedBy::Controller, StopCause::EmergencyStop))
        } else if state.safety_mode != SafetyMode::Normal {
            Some((
                StoppedBy::Controller,
                StopCause::SafetyMode(state.safety_mode),
            ))
        } else if state.robot_mode != RobotMode::Running {
            Some((
                StoppedBy::Controller,
                StopCause::RobotMode(state.robot_mode),
            ))
        } else if !state.program_running {
            Some((
                StoppedBy::Controller,
                StopCause::ProgramStopped { ack: *ack },
            ))
        } else if job.stop.requested() {
            Some((StoppedBy::Caller, StopCause::Requested))
        } else {
            // Tracking error: the distance to the nearest of the samples sent within the
            // servo filter's lag (the arm trails the stream by design). A stalled or blocked
            // arm falls behind that window and the error grows past the bound.
            let (joint, error) = (last.saturating_sub(job.lag_samples)..=last)
                .map(|i| {
                    let cmd = &job.samples[i].position;
                    (0..JOINT_COUNT)
                        .map(|j| (j, (q[j] - cmd[j]).abs()))
                        .fold((0, 0.0), |a, b| if b.1 > a.1 { b } else { a })
                })
                .fold((0, f64::INFINITY), |a, b| if b.1 < a.1 { b } else { a });
            self.max_err = self.max_err.max(error);
            (error > job.tracking_bound).then_some((
                StoppedBy::Driver,
                StopCause::TrackingError {
                    joint,
                    error,
                    bound: job.tracking_bound,
                },
            ))
        };
        if let Some((by, cause)) = cause {
            drop(slot);
            return self.stop(link, by, cause, *state, q);
        }
        let n = job.samples.len();
        let target = job.samples[self.index.min(last_sample)].position;
        if self.index >= n {
            let err = (0..JOINT_COUNT)
                .map(|j| (q[j] - target[j]).abs())
                .fold(0.0, f64::max);
            let still = state.joints.velocity.iter().all(|v| v.abs() < 1e-3);
            if (err <= job.goal_tolerance && still) || self.settled_for >= self.settle_cycles {
                let _ = link.write_inputs(SEQ_STOP, &target);
                self.ending = Some(0);
                return;
            }
            self.settled_for += 1;
        }
        self.seq = self.seq.wrapping_add(1).max(1);
        self.index += 1;
        if let Err(e) = link.write_inputs(self.seq, &target) {
            drop(slot);
            self.stop(
                link,
                StoppedBy::Controller,
                StopCause::ConnectionLost {
                    detail: e.to_string(),
                },
                *state,
                q,
            );
        }
    }

    fn on_silence(&mut self, link: &Link, missed: u32) {
        let (lost, state) = {
            let slot = lock(&link.job);
            let Some(job) = slot.as_ref() else {
                return;
            };
            (missed > job.lost_cycles, lock(&link.status).state)
        };
        if lost {
            let q = state.joints.position;
            self.stop(
                link,
                StoppedBy::Driver,
                StopCause::NoData {
                    missed_cycles: missed,
                },
                state,
                q,
            );
        }
    }

    fn on_link_lost(&mut self, link: &Link, why: &str) {
        let state = lock(&link.status).state;
        let mut slot = lock(&link.job);
        if let Some(mut job) = slot.take() {
            drop(slot);
            let sent = self.index;
            let detail = why.to_string();
            self.finish(link, &mut job, |jitter| ExecutionOutcome::Stopped {
                by: StoppedBy::Controller,
                cause: StopCause::ConnectionLost { detail },
                samples_sent: sent,
                last_state: state,
                jitter,
            });
        }
    }
}

/// The hold command: sequence word 0 and the given joints.
pub(crate) fn hold(link: &Link, q: &[f64; JOINT_COUNT]) -> Result<(), ArmError> {
    link.write_inputs(SEQ_HOLD, q)
}
