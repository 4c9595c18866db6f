//! The Robotiq 2F-85 driver (issue 6, item 2): the activation sequence of the fact sheet
//! ("Activation": clear, set rACT, poll until gSTA = 3), go-to motions in metres, state in
//! physical units, all over any [`RegisterTransport`]. Time comes from an injected
//! [`Clock`]: polls are paced at the gripper's 100 Hz register refresh.

use std::net::ToSocketAddrs;
use std::sync::Arc;
use std::time::Duration;

use cell_types::{Clock, GripperCommand, GripperFault, GripperState, ObjectStatus};

use super::can::CanMapping;
use super::registers::{fault_from_code, ActivationStatus, RequestImage, StatusImage};
use super::transport::{
    ModbusRtuTransport, RegisterTransport, SlcanTransport, SocketcandTransport, UrcapTransport,
    DEFAULT_REPLY_TIMEOUT,
};
use super::{Gripper, GripperError};

/// Maps register counts to physical units. Counts are linear in the opening; the defaults
/// are the fact sheet's (3..230 counts over the 85 mm stroke, 20–150 mm/s, 20–235 N, about
/// 10 mA per current count); calibrate `open_count`/`closed_count` per gripper.
#[derive(Copy, Clone, Debug, PartialEq)]
pub struct Calibration {
    /// gPO when fully open.
    pub open_count: u8,
    /// gPO when fully closed (fingertips touching).
    pub closed_count: u8,
    /// Opening when fully open (m).
    pub stroke_m: f64,
    /// Finger speed at rSP = 0 (m/s).
    pub min_speed_mps: f64,
    /// Finger speed at rSP = 255 (m/s).
    pub max_speed_mps: f64,
    /// Grip force at rFR = 0 (N).
    pub min_force_n: f64,
    /// Grip force at rFR = 255 (N).
    pub max_force_n: f64,
    /// Motor current per gCU count (A).
    pub amps_per_count: f64,
}

impl Default for Calibration {
    fn default() -> Self {
        Self {
            open_count: 3,
            closed_count: 230,
            stroke_m: 0.085,
            min_speed_mps: 0.020,
            max_speed_mps: 0.150,
            min_force_n: 20.0,
            max_force_n: 235.0,
            amps_per_count: 0.010,
        }
    }
}

impl Calibration {
    /// Checks that the calibration maps counts to metres one-to-one.
    pub fn validate(&self) -> Result<(), GripperError> {
        let bad = |detail: String| Err(GripperError::BadCalibration { detail });
        if self.closed_count <= self.open_count {
            return bad(format!(
                "closed_count {} must exceed open_count {}",
                self.closed_count, self.open_count
            ));
        }
        for (what, lo, hi) in [
            ("speed", self.min_speed_mps, self.max_speed_mps),
            ("force", self.min_force_n, self.max_force_n),
        ] {
            if !(lo.is_finite() && hi.is_finite() && 0.0 <= lo && lo < hi) {
                return bad(format!(
                    "{what} range [{lo}, {hi}] must be finite and increasing"
                ));
            }
        }
        if !(self.stroke_m.is_finite() && self.stroke_m > 0.0) {
            return bad(format!("stroke {} m must be positive", self.stroke_m));
        }
        if !(self.amps_per_count.is_finite() && self.amps_per_count >= 0.0) {
            return bad(format!(
                "amps_per_count {} must be >= 0",
                self.amps_per_count
            ));
        }
        Ok(())
    }

    fn span(&self) -> f64 {
        f64::from(self.closed_count) - f64::from(self.open_count)
    }

    /// The position count for an opening of `width_m`; an error outside the stroke.
    pub fn width_to_count(&self, width_m: f64) -> Result<u8, GripperError> {
        if !(width_m.is_finite() && (0.0..=self.stroke_m).contains(&width_m)) {
            return Err(GripperError::OutOfRange {
                what: "gripper width (m)",
                value: width_m,
                min: 0.0,
                max: self.stroke_m,
            });
        }
        let c = f64::from(self.closed_count) - width_m / self.stroke_m * self.span();
        Ok(c.round().clamp(0.0, 255.0) as u8)
    }

    /// The opening for a position count (clamped to the stroke: counts past the calibrated
    /// ends are fingers pressed together or fully open).
    pub fn count_to_width(&self, count: u8) -> f64 {
        let w = (f64::from(self.closed_count) - f64::from(count)) / self.span() * self.stroke_m;
        w.clamp(0.0, self.stroke_m)
    }

    /// rSP for a finger speed; saturates at the gripper's range.
    pub fn speed_to_count(&self, speed_mps: f64) -> u8 {
        scale(speed_mps, self.min_speed_mps, self.max_speed_mps)
    }

    /// rFR for a grip force; saturates at the gripper's range.
    pub fn force_to_count(&self, force_n: f64) -> u8 {
        scale(force_n, self.min_force_n, self.max_force_n)
    }

    /// Motor current for a gCU count.
    pub fn current_amps(&self, count: u8) -> f64 {
        f64::from(count) * self.amps_per_count
    }
}

fn scale(v: f64, lo: f64, hi: f64) -> u8 {
    let x = ((v - lo) / (hi - lo) * 255.0).round();
    if x.is_nan() {
        0
    } else {
        x.clamp(0.0, 255.0) as u8
    }
}

/// How long the driver waits, and how often it polls.
#[derive(Copy, Clone, Debug, PartialEq)]
pub struct DriverTiming {
    /// Longest activation (the fact sheet's is about 1 s).
    pub activation_timeout: Duration,
    /// Longest motion (full stroke at the slowest speed takes about 4.3 s).
    pub motion_timeout: Duration,
    /// Poll period; the gripper refreshes its registers at 100 Hz, so no faster than 10 ms.
    pub poll_period: Duration,
    /// Faults seen this soon after rACT rises are stale (they clear with activation).
    pub activation_grace: Duration,
}

impl Default for DriverTiming {
    fn default() -> Self {
        Self {
            activation_timeout: Duration::from_secs(5),
            motion_timeout: Duration::from_secs(6),
            poll_period: Duration::from_millis(10),
            activation_grace: Duration::from_millis(50),
        }
    }
}

/// The Robotiq 2F-85 driver over a register transport.
pub struct RobotiqGripper<T: RegisterTransport> {
    transport: T,
    clock: Arc<dyn Clock>,
    calibration: Calibration,
    timing: DriverTiming,
    request: RequestImage,
    activated: bool,
    /// Speed used by `open`/`close` (m/s).
    pub default_speed_mps: f64,
    /// Force used by `open`/`close` (N).
    pub default_force_n: f64,
}

impl RobotiqGripper<ModbusRtuTransport> {
    /// A driver on Modbus RTU at `path` (115200 8N1, slave 9).
    pub fn modbus_rtu(path: &str, clock: Arc<dyn Clock>) -> Result<Self, GripperError> {
        let t = ModbusRtuTransport::open(path, super::modbus_rtu::SLAVE_ID)?;
        Ok(Self::new(t, clock))
    }
}

impl RobotiqGripper<UrcapTransport> {
    /// A driver on the URCap text socket at `addr` (the UR controller's port 63352).
    pub fn urcap(addr: impl ToSocketAddrs, clock: Arc<dyn Clock>) -> Result<Self, GripperError> {
        let t = UrcapTransport::connect(addr, DEFAULT_REPLY_TIMEOUT)?;
        Ok(Self::new(t, clock))
    }
}

impl RobotiqGripper<SlcanTransport> {
    /// A driver on CAN through the slcan adapter at `path`.
    pub fn slcan(
        path: &str,
        mapping: CanMapping,
        clock: Arc<dyn Clock>,
    ) -> Result<Self, GripperError> {
        let t = SlcanTransport::open(path, mapping)?;
        Ok(Self::new(t, clock))
    }
}

impl RobotiqGripper<SocketcandTransport> {
    /// A driver on CAN through a socketcand server at `addr`, bus `bus` (e.g. `"can0"`).
    pub fn socketcand(
        addr: impl ToSocketAddrs,
        bus: &str,
        mapping: CanMapping,
        clock: Arc<dyn Clock>,
    ) -> Result<Self, GripperError> {
        let t = SocketcandTransport::connect(addr, bus, mapping)?;
        Ok(Self::new(t, clock))
    }
}

#[cfg(all(feature = "socketcan", target_os = "linux"))]
impl RobotiqGripper<super::socketcan_transport::SocketcanTransport> {
    /// A driver on CAN through the SocketCAN interface `ifname` (e.g. `"can0"`).
    pub fn socketcan(
        ifname: &str,
        mapping: CanMapping,
        clock: Arc<dyn Clock>,
    ) -> Result<Self, GripperError> {
        let t = super::socketcan_transport::SocketcanTransport::open(ifname, mapping)?;
        Ok(Self::new(t, clock))
    }
}

impl<T: RegisterTransport> RobotiqGripper<T> {
    /// A driver with the default calibration and timing; call [`Gripper::activate`] next.
    pub fn new(transport: T, clock: Arc<dyn Clock>) -> Self {
        Self {
            transport,
            clock,
            calibration: Calibration::default(),
            timing: DriverTiming::default(),
            request: RequestImage::default(),
            activated: false,
            default_speed_mps: 0.1,
            default_force_n: 60.0,
        }
    }

    /// Replaces the calibration (validated).
    pub fn with_calibration(mut self, c: Calibration) -> Result<Self, GripperError> {
        c.validate()?;
        self.calibration = c;
        Ok(self)
    }

    /// Replaces the timing.
    pub fn with_timing(mut self, t: DriverTiming) -> Self {
        self.timing = t;
        self
    }

    /// The calibration in use.
    pub fn calibration(&self) -> &Calibration {
        &self.calibration
    }

    /// The transport (e.g. for its name or raw exchanges).
    pub fn transport_mut(&mut self) -> &mut T {
        &mut self.transport
    }

    /// Reads the raw status image, faults included (no fault check).
    pub fn status_image(&mut self) -> Result<StatusImage, GripperError> {
        self.transport.read_status()
    }

    /// Converts a status image to physical units.
    pub fn to_state(&self, s: &StatusImage) -> GripperState {
        GripperState {
            activated: s.is_activated(),
            width_m: self.calibration.count_to_width(s.position),
            object: s.object,
            current_a: self.calibration.current_amps(s.current),
            fault: s.fault(),
        }
    }

    fn pause(&self) {
        let deadline = self.clock.now() + self.timing.poll_period;
        self.clock.sleep_until(deadline);
    }

    fn write(&mut self, r: RequestImage) -> Result<(), GripperError> {
        self.transport.write_request(&r)?;
        self.request = r;
        Ok(())
    }

    /// Reads status; a fault becomes an error (and a fault that stops the gripper means it
    /// must be re-activated).
    fn checked_status(&mut self) -> Result<StatusImage, GripperError> {
        let s = self.transport.read_status()?;
        match fault_from_code(s.fault) {
            None => Ok(s),
            Some(fault) => {
                if matches!(
                    fault,
                    GripperFault::Communication(_) | GripperFault::Major(_)
                ) {
                    self.activated = false;
                }
                Err(GripperError::Fault {
                    code: s.fault,
                    fault,
                })
            }
        }
    }

    /// Writes a go-to for raw counts and returns without waiting.
    pub fn go_to_counts(&mut self, position: u8, speed: u8, force: u8) -> Result<(), GripperError> {
        if !self.activated {
            return Err(GripperError::NotActivated);
        }
        let r = RequestImage {
            activate: true,
            go_to: true,
            position,
            speed,
            force,
            ..Default::default()
        };
        // The gripper starts a motion on a rising edge of rGTO or a changed request; the same
        // request again (e.g. close after a stop on contact) needs rGTO toggled.
        if self.request == r {
            self.write(RequestImage { go_to: false, ..r })?;
            self.pause();
        }
        self.write(r)
    }

    /// Waits until the motion to the last requested position ends.
    pub fn wait_motion(&mut self) -> Result<GripperState, GripperError> {
        let start = self.clock.now();
        loop {
            // One refresh period first: the status image then reflects the new request.
            self.pause();
            let s = self.checked_status()?;
            if s.position_request == self.request.position && s.object != ObjectStatus::Moving {
                return Ok(self.to_state(&s));
            }
            if self.clock.now().saturating_sub(start) > self.timing.motion_timeout {
                return Err(GripperError::Timeout {
                    what: "the fingers to stop",
                    after: self.timing.motion_timeout,
                });
            }
        }
    }

    fn move_counts(&mut self, position: u8) -> Result<GripperState, GripperError> {
        let speed = self.calibration.speed_to_count(self.default_speed_mps);
        let force = self.calibration.force_to_count(self.default_force_n);
        self.go_to_counts(position, speed, force)?;
        self.wait_motion()
    }
}

impl<T: RegisterTransport> Gripper for RobotiqGripper<T> {
    fn activate(&mut self) -> Result<GripperState, GripperError> {
        self.activated = false;
        self.write(RequestImage::default())?;
        self.pause();
        self.write(RequestImage {
            activate: true,
            ..Default::default()
        })?;
        let start = self.clock.now();
        loop {
            self.pause();
            let elapsed = self.clock.now().saturating_sub(start);
            let s = self.transport.read_status()?;
            if s.fault != 0 && elapsed > self.timing.activation_grace {
                if let Some(fault) = s.fault() {
                    return Err(GripperError::Fault {
                        code: s.fault,
                        fault,
                    });
                }
            }
            if s.activation == ActivationStatus::Activated && s.fault == 0 {
                self.activated = true;
                return Ok(self.to_state(&s));
            }
            if elapsed > self.timing.activation_timeout {
                return Err(GripperError::Timeout {
                    what: "activation (gSTA = 3)",
                    after: self.timing.activation_timeout,
                });
            }
        }
    }

    fn command(&mut self, cmd: &GripperCommand) -> Result<(), GripperError> {
        if !self.activated {
            return Err(GripperError::NotActivated);
        }
        let position = self.calibration.width_to_count(cmd.width_m)?;
        let speed = self.calibration.speed_to_count(cmd.speed_mps);
        let force = self.calibration.force_to_count(cmd.force_n);
        self.go_to_counts(position, speed, force)
    }

    fn move_to(&mut self, cmd: &GripperCommand) -> Result<GripperState, GripperError> {
        self.command(cmd)?;
        self.wait_motion()
    }

    fn open(&mut self) -> Result<GripperState, GripperError> {
        self.move_counts(0)
    }

    fn close(&mut self) -> Result<GripperState, GripperError> {
        self.move_counts(255)
    }

    fn state(&mut self) -> Result<GripperState, GripperError> {
        let s = self.checked_status()?;
        Ok(self.to_state(&s))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn calibration_maps_counts_and_metres_both_ways() {
        let c = Calibration::default();
        assert_eq!(c.width_to_count(0.085).unwrap(), 3);
        assert_eq!(c.width_to_count(0.0).unwrap(), 230);
        for count in 3..=230u8 {
            assert_eq!(c.width_to_count(c.count_to_width(count)).unwrap(), count);
        }
        let w = c.count_to_width(c.width_to_count(0.040).unwrap());
        assert!((w - 0.040).abs() < 0.5 * 0.085 / 227.0 + 1e-12);
        assert!(c.width_to_count(0.09).is_err());
        assert!(c.width_to_count(-0.001).is_err());
        assert!(c.width_to_count(f64::NAN).is_err());
        assert_eq!(c.count_to_width(255), 0.0);
        assert_eq!(c.count_to_width(0), 0.085);
        assert_eq!(c.speed_to_count(0.150), 255);
        assert_eq!(c.speed_to_count(1.0), 255);
        assert_eq!(c.speed_to_count(0.0), 0);
        assert_eq!(c.force_to_count(20.0), 0);
        assert!((c.current_amps(30) - 0.3).abs() < 1e-12);
    }

    #[test]
    fn bad_calibrations_rejected() {
        let c = Calibration {
            open_count: 200,
            closed_count: 100,
            ..Default::default()
        };
        assert!(matches!(
            c.validate(),
            Err(GripperError::BadCalibration { .. })
        ));
        let c = Calibration {
            stroke_m: f64::NAN,
            ..Default::default()
        };
        assert!(c.validate().is_err());
        assert!(Calibration::default().validate().is_ok());
    }
}
