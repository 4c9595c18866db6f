//! The simulated Robotiq 2F-85 (issue 6, item 3): finger motion at the speed set by rSP,
//! registers refreshed at 100 Hz, activation taking about a second, contact with an object
//! of given width (gOBJ 1/2) with the current rising on contact, fault 0x09 after a second
//! without communication, other faults injectable. Time is passed in explicitly and the
//! model steps in whole refresh periods, so a run is deterministic for a given sequence of
//! requests and times.

use std::time::Duration;

use cell_types::ObjectStatus;
use firmware_iface::gripper::registers::{fault, ActivationStatus, RequestImage, StatusImage};

/// Communication (0x08, 0x09) and major (0x0A..0x0F) faults stop the fingers and stay until
/// a new rising edge of rACT.
fn latching(code: u8) -> bool {
    code >= 0x08
}

/// Physical and timing parameters of the simulated gripper.
#[derive(Copy, Clone, Debug, PartialEq)]
pub struct SimConfig {
    /// gPO when fully open.
    pub open_count: u8,
    /// gPO when the fingertips touch.
    pub closed_count: u8,
    /// Full opening (m).
    pub stroke_m: f64,
    /// Finger closing speed at rSP = 0 (m/s; the opening between the fingertips).
    pub min_speed_mps: f64,
    /// Finger closing speed at rSP = 255 (m/s).
    pub max_speed_mps: f64,
    /// Time from the rising edge of rACT to gSTA = 3.
    pub activation_time: Duration,
    /// Silence after which fault 0x09 is raised.
    pub comm_timeout: Duration,
    /// Register refresh period (100 Hz).
    pub refresh_period: Duration,
    /// gCU while the fingers move.
    pub moving_current: u8,
    /// gCU when holding an object at rFR = 0; rises to `max_holding_current` at rFR = 255.
    pub min_holding_current: u8,
    /// gCU when holding an object at rFR = 255.
    pub max_holding_current: u8,
    /// How fast gCU follows its target (counts per refresh period).
    pub current_slew: u8,
}

impl Default for SimConfig {
    fn default() -> Self {
        Self {
            open_count: 3,
            closed_count: 230,
            stroke_m: 0.085,
            min_speed_mps: 0.020,
            max_speed_mps: 0.150,
            activation_time: Duration::from_millis(1000),
            comm_timeout: Duration::from_secs(1),
            refresh_period: Duration::from_millis(10),
            moving_current: 15,
            min_holding_current: 20,
            max_holding_current: 120,
            current_slew: 10,
        }
    }
}

/// The simulated gripper's state.
#[derive(Clone, Debug)]
pub struct GripperModel {
    cfg: SimConfig,
    t: Duration,
    request: RequestImage,
    activation: ActivationStatus,
    activation_done: Duration,
    width_m: f64,
    moving: bool,
    object_status: ObjectStatus,
    fault: u8,
    current: f64,
    target_current: f64,
    last_comm: Duration,
    object_width_m: Option<f64>,
    outer_limit_m: Option<f64>,
    emergency_stop: bool,
    latched: StatusImage,
}

impl GripperModel {
    /// A gripper powered up at time 0: reset, fingers fully open, no object.
    pub fn new(cfg: SimConfig) -> Self {
        let mut m = Self {
            cfg,
            t: Duration::ZERO,
            request: RequestImage::default(),
            activation: ActivationStatus::Reset,
            activation_done: Duration::ZERO,
            width_m: cfg.stroke_m,
            moving: false,
            object_status: ObjectStatus::Moving,
            fault: 0,
            current: 0.0,
            target_current: 0.0,
            last_comm: Duration::ZERO,
            object_width_m: None,
            outer_limit_m: None,
            emergency_stop: false,
            latched: StatusImage::default(),
        };
        m.latch();
        m
    }

    /// The configuration.
    pub fn config(&self) -> &SimConfig {
        &self.cfg
    }

    /// Places an object of `width` metres between the fingers (`None`: nothing).
    pub fn set_object(&mut self, width_m: Option<f64>) {
        self.object_width_m = width_m.filter(|w| w.is_finite() && *w > 0.0);
    }

    /// Places an obstacle outside the fingers that stops them opening past `width_m`
    /// (an inside grasp: fingers opening in a bore); `None`: nothing. Contact while opening
    /// is reported as gOBJ = 1.
    pub fn set_outer_limit(&mut self, width_m: Option<f64>) {
        self.outer_limit_m = width_m.filter(|w| w.is_finite() && *w > 0.0);
    }

    /// Sets or releases the UR controller's emergency stop: while set, the fingers stop
    /// and the URCap socket answers `?`.
    pub fn set_emergency_stop(&mut self, on: bool) {
        self.emergency_stop = on;
        if on {
            self.stop(0.0);
        }
    }

    /// True while the emergency stop is set.
    pub fn emergency_stop(&self) -> bool {
        self.emergency_stop
    }

    /// Raises a fault now (e.g. 0x0B); comm and major faults stop the fingers and stay
    /// until a new rising edge of rACT.
    pub fn inject_fault(&mut self, code: u8) {
        self.fault = code;
        if latching(code) {
            self.stop(0.0);
        }
        self.latch();
    }

    /// Current opening between the fingertips (m).
    pub fn width_m(&self) -> f64 {
        self.width_m
    }

    /// The last request image received.
    pub fn request(&self) -> RequestImage {
        self.request
    }

    /// Steps the model up to `now` without counting as communication, and returns the
    /// status image as last refreshed.
    pub fn observe(&mut self, now: Duration) -> StatusImage {
        self.advance(now);
        self.latched
    }

    /// A host read the status image at `now`.
    pub fn read_status(&mut self, now: Duration) -> StatusImage {
        self.advance(now);
        self.last_comm = now;
        self.latched
    }

    /// A host wrote (part of) the request image at `now`.
    pub fn write_request(&mut self, now: Duration, r: RequestImage) {
        self.advance(now);
        self.last_comm = now;
        if self.emergency_stop {
            return;
        }
        let old = self.request;
        self.request = r;
        if !r.activate {
            self.activation = ActivationStatus::Reset;
            self.stop(0.0);
            self.object_status = ObjectStatus::Moving;
            if r.go_to {
                self.fault = fault::ACTIVATION_BIT_NOT_SET;
            } else if self.fault == fault::ACTIVATION_BIT_NOT_SET
                || self.fault == fault::ACTION_DELAYED
            {
                self.fault = 0;
            }
            return;
        }
        if !old.activate {
            // Rising edge of rACT: clears every fault and starts the activation routine.
            self.fault = 0;
            self.activation = ActivationStatus::Activating;
            self.activation_done = now + self.cfg.activation_time;
            self.stop(0.0);
            self.object_status = ObjectStatus::Moving;
            return;
        }
        if latching(self.fault) {
            return;
        }
        match self.activation {
            ActivationStatus::Activated => {
                if self.fault == fault::ACTION_DELAYED {
                    self.fault = 0;
                }
                if !r.go_to {
                    self.stop(0.0);
                    self.object_status = ObjectStatus::Moving;
                } else if !old.go_to
                    || old.position != r.position
                    || old.speed != r.speed
                    || old.force != r.force
                {
                    self.moving = true;
                    self.object_status = ObjectStatus::Moving;
                    self.target_current = f64::from(self.cfg.moving_current);
                }
            }
            _ => {
                if r.go_to {
                    self.fault = fault::ACTION_DELAYED;
                }
            }
        }
    }

    fn stop(&mut self, target_current: f64) {
        self.moving = false;
        self.target_current = target_current;
    }

    fn count_to_width(&self, count: u8) -> f64 {
        let span = f64::from(self.cfg.closed_count) - f64::from(self.cfg.open_count);
        ((f64::from(self.cfg.closed_count) - f64::from(count)) / span * self.cfg.stroke_m)
            .clamp(0.0, self.cfg.stroke_m)
    }

    fn width_to_count(&self, w: f64) -> u8 {
        let span = f64::from(self.cfg.closed_count) - f64::from(self.cfg.open_count);
        (f64::from(self.cfg.closed_count) - w / self.cfg.stroke_m * span)
            .round()
            .clamp(0.0, 255.0) as u8
    }

    fn speed_mps(&self) -> f64 {
        let c = &self.cfg;
        c.min_speed_mps
            + (c.max_speed_mps - c.min_speed_mps) * f64::from(self.request.speed) / 255.0
    }

    fn holding_current(&self) -> f64 {
        let (lo, hi) = (
            f64::from(self.cfg.min_holding_current),
            f64::from(self.cfg.max_holding_current),
        );
        lo + (hi - lo) * f64::from(self.request.force) / 255.0
    }

    /// Steps whole refresh periods up to `now`.
    fn advance(&mut self, now: Duration) {
        let dt = self.cfg.refresh_period.max(Duration::from_micros(100));
        while self.t + dt <= now {
            self.t += dt;
            self.tick(dt.as_secs_f64());
        }
    }

    fn tick(&mut self, dt: f64) {
        if self.activation == ActivationStatus::Activating && self.t >= self.activation_done {
            self.activation = ActivationStatus::Activated;
            // The activation routine ends with the fingers fully open.
            self.width_m = self.cfg.stroke_m;
            if self.fault == fault::ACTION_DELAYED {
                self.fault = 0;
            }
        }
        if self.request.activate
            && self.fault == 0
            && self.t.saturating_sub(self.last_comm) >= self.cfg.comm_timeout
        {
            log::warn!(
                "gripper sim: no communication for {:?}: fault 0x09",
                self.t.saturating_sub(self.last_comm)
            );
            self.fault = fault::NO_COMMUNICATION;
            self.stop(0.0);
        }
        if self.moving {
            self.step_fingers(dt);
        }
        let slew = f64::from(self.cfg.current_slew);
        self.current += (self.target_current - self.current).clamp(-slew, slew);
        self.latch();
    }

    fn step_fingers(&mut self, dt: f64) {
        let target = self.count_to_width(self.request.position);
        let step = self.speed_mps() * dt;
        if target < self.width_m {
            let next = (self.width_m - step).max(target);
            match self.object_width_m {
                Some(obj) if obj <= self.width_m && obj > target && next <= obj => {
                    self.width_m = obj;
                    self.object_status = ObjectStatus::ContactClosing;
                    let hold = self.holding_current();
                    self.stop(hold);
                }
                _ => self.width_m = next,
            }
        } else {
            let next = (self.width_m + step).min(target);
            match self.outer_limit_m {
                Some(lim) if lim >= self.width_m && lim < target && next >= lim => {
                    self.width_m = lim;
                    self.object_status = ObjectStatus::ContactOpening;
                    let hold = self.holding_current();
                    self.stop(hold);
                }
                _ => self.width_m = next,
            }
        }
        if self.moving && (self.width_m - target).abs() < 1e-12 {
            self.object_status = ObjectStatus::AtTarget;
            self.stop(0.0);
        }
    }

    fn latch(&mut self) {
        self.latched = StatusImage {
            activate: self.request.activate,
            go_to: self.request.go_to && self.activation == ActivationStatus::Activated,
            activation: self.activation,
            object: self.object_status,
            fault: self.fault,
            position_request: self.request.position,
            position: self.width_to_count(self.width_m),
            current: self.current.round().clamp(0.0, 255.0) as u8,
        };
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use proptest::prelude::*;

    fn ms(n: u64) -> Duration {
        Duration::from_millis(n)
    }

    fn activated() -> (GripperModel, Duration) {
        let mut m = GripperModel::new(SimConfig::default());
        m.write_request(ms(0), RequestImage::default());
        m.write_request(
            ms(10),
            RequestImage {
                activate: true,
                ..Default::default()
            },
        );
        let mut t = ms(10);
        while !m.read_status(t).is_activated() {
            t += ms(10);
            assert!(t < ms(2000), "activation never completed");
        }
        (m, t)
    }

    #[test]
    fn activation_takes_about_a_second() {
        let (m, t) = activated();
        assert!(t >= ms(1000) && t <= ms(1030), "activated at {t:?}");
        assert_eq!(m.latched.encode()[0], 0x31);
    }

    #[test]
    fn closes_on_object_with_rising_current() {
        let (mut m, mut t) = activated();
        m.set_object(Some(0.040));
        let close = RequestImage {
            activate: true,
            go_to: true,
            position: 255,
            speed: 255,
            force: 128,
            ..Default::default()
        };
        m.write_request(t, close);
        let mut currents = vec![];
        let mut widths = vec![];
        loop {
            t += ms(10);
            let s = m.read_status(t);
            widths.push(m.width_m());
            currents.push(s.current);
            if s.object != ObjectStatus::Moving {
                assert_eq!(s.object, ObjectStatus::ContactClosing);
                break;
            }
            assert!(t < ms(5000));
        }
        assert!(widths.windows(2).all(|w| w[1] <= w[0]), "fingers went back");
        assert!((m.width_m() - 0.040).abs() < 1e-9);
        // 45 mm at 150 mm/s: about 0.3 s.
        assert!(
            widths.len() >= 29 && widths.len() <= 32,
            "{} ticks",
            widths.len()
        );
        for _ in 0..10 {
            t += ms(10);
            currents.push(m.read_status(t).current);
        }
        let last = *currents.last().unwrap_or(&0);
        assert!(last > 15, "holding current {last} not above moving current");
        assert_eq!(m.read_status(t).encode()[0], 0xB9);
    }

    #[test]
    fn opening_against_an_outer_limit_is_contact_while_opening() {
        let (mut m, mut t) = activated();
        let go = |pos| RequestImage {
            activate: true,
            go_to: true,
            position: pos,
            speed: 255,
            force: 50,
            ..Default::default()
        };
        m.write_request(t, go(230));
        while m.read_status(t).object == ObjectStatus::Moving {
            t += ms(10);
        }
        m.set_outer_limit(Some(0.030));
        m.write_request(t, go(0));
        loop {
            t += ms(10);
            let s = m.read_status(t);
            if s.object != ObjectStatus::Moving {
                assert_eq!(s.object, ObjectStatus::ContactOpening);
                assert_eq!(s.encode()[0] >> 6, 1);
                break;
            }
            assert!(t < ms(10_000));
        }
        assert!((m.width_m() - 0.030).abs() < 1e-12);
    }

    #[test]
    fn silence_raises_0x09_until_reactivation() {
        let (mut m, t) = activated();
        assert_eq!(m.observe(t + ms(900)).fault, 0);
        assert_eq!(m.observe(t + ms(1100)).fault, fault::NO_COMMUNICATION);
        // Communication alone does not clear it; a new rising edge of rACT does.
        let go = RequestImage {
            activate: true,
            go_to: true,
            position: 100,
            ..Default::default()
        };
        m.write_request(t + ms(1200), go);
        assert_eq!(m.read_status(t + ms(1300)).fault, fault::NO_COMMUNICATION);
        m.write_request(t + ms(1300), RequestImage::default());
        m.write_request(
            t + ms(1310),
            RequestImage {
                activate: true,
                ..Default::default()
            },
        );
        assert_eq!(m.read_status(t + ms(1320)).fault, 0);
    }

    #[test]
    fn go_to_before_activation_is_fault_05_and_without_act_0x07() {
        let mut m = GripperModel::new(SimConfig::default());
        m.write_request(
            ms(0),
            RequestImage {
                activate: true,
                ..Default::default()
            },
        );
        m.write_request(
            ms(10),
            RequestImage {
                activate: true,
                go_to: true,
                position: 200,
                ..Default::default()
            },
        );
        assert_eq!(m.read_status(ms(20)).fault, fault::ACTION_DELAYED);
        let mut m = GripperModel::new(SimConfig::default());
        m.write_request(
            ms(0),
            RequestImage {
                go_to: true,
                ..Default::default()
            },
        );
        assert_eq!(m.read_status(ms(10)).fault, fault::ACTIVATION_BIT_NOT_SET);
    }

    #[test]
    fn injected_major_fault_stops_motion() {
        let (mut m, t) = activated();
        m.write_request(
            t,
            RequestImage {
                activate: true,
                go_to: true,
                position: 255,
                speed: 0,
                ..Default::default()
            },
        );
        let w0 = {
            m.read_status(t + ms(100));
            m.width_m()
        };
        m.inject_fault(0x0B);
        m.read_status(t + ms(500));
        assert_eq!(m.width_m(), w0);
        assert_eq!(m.latched.fault, 0x0B);
    }

    /// One step of a random session: wait `dt_ms`, maybe move the object, write a request.
    type Step = (u64, [u8; 6], Option<f64>);

    fn run(steps: &[Step]) -> Vec<(StatusImage, f64)> {
        let mut m = GripperModel::new(SimConfig::default());
        let mut t = Duration::ZERO;
        let mut trace = vec![];
        for (dt_ms, bytes, obj) in steps {
            t += ms(*dt_ms);
            m.set_object(*obj);
            m.write_request(t, RequestImage::decode(*bytes));
            for _ in 0..5 {
                t += ms(37);
                trace.push((m.read_status(t), m.width_m()));
            }
        }
        trace
    }

    proptest! {
        #![proptest_config(ProptestConfig::with_cases(300))]
        #[test]
        fn random_sessions_keep_invariants_and_replay_exactly(
            steps in proptest::collection::vec(
                (0u64..1500, any::<[u8; 6]>(), proptest::option::of(0.001f64..0.09)),
                1..40,
            )
        ) {
            let cfg = SimConfig::default();
            let trace = run(&steps);
            for (s, w) in &trace {
                prop_assert!((0.0..=cfg.stroke_m).contains(w), "width {w}");
                prop_assert!((cfg.open_count..=cfg.closed_count).contains(&s.position), "{s:?}");
                prop_assert!([0, 5, 7, 9].contains(&s.fault), "unexpected fault {s:?}");
                prop_assert!(s.current <= cfg.max_holding_current, "{s:?}");
                if s.activation != ActivationStatus::Activated {
                    prop_assert!(!s.go_to, "{s:?}");
                }
            }
            // Same inputs, same outputs: a recorded session replays exactly.
            prop_assert_eq!(run(&steps), trace);
        }
    }
}
