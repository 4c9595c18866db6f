//! Injected time: control code reads a [`Clock`], never the wall clock directly, so the
//! simulator can run faster than real time and seeded runs repeat exactly.

use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::Arc;
use std::time::{Duration, Instant};

use crate::CellTypesError;

/// A source of monotonic time and of waiting.
pub trait Clock: Send + Sync {
    /// Time since this clock's epoch.
    fn now(&self) -> Duration;
    /// Waits until `deadline` (since the epoch) has passed.
    fn sleep_until(&self, deadline: Duration);
}

/// The machine's monotonic clock; sleeps really sleep.
#[derive(Clone, Debug)]
pub struct SystemClock {
    epoch: Instant,
}

impl SystemClock {
    /// A clock whose epoch is now.
    pub fn new() -> Self {
        Self {
            epoch: Instant::now(),
        }
    }
}

impl Default for SystemClock {
    fn default() -> Self {
        Self::new()
    }
}

impl Clock for SystemClock {
    fn now(&self) -> Duration {
        self.epoch.elapsed()
    }

    fn sleep_until(&self, deadline: Duration) {
        sleep_until_scaled(|| self.now(), deadline, 1.0);
    }
}

/// Waits until `now()` reaches `deadline`, on a clock that runs `speed` times faster than
/// the wall clock: sleeps most of the way, then spins the last stretch, because
/// `thread::sleep` alone overshoots by the scheduler's slack (50–100 µs), which shows up as
/// control-loop jitter.
fn sleep_until_scaled(now: impl Fn() -> Duration, deadline: Duration, speed: f64) {
    const SPIN: Duration = Duration::from_micros(200);
    loop {
        let now = now();
        if now >= deadline {
            return;
        }
        let left = (deadline - now).div_f64(speed);
        if left > SPIN {
            std::thread::sleep(left - SPIN);
        } else {
            std::hint::spin_loop();
        }
    }
}

/// The machine's monotonic clock run `speed` times faster than real time: a simulated cell
/// whose controller, gripper, cameras and episode all read one such clock plays out
/// faster than real time and behaves the same (every cadence, motion and time stamp is in
/// its time). Wall-clock timeouts in the drivers only become looser. What limits the speed
/// is the driver, which must still answer every controller package within the (now
/// shorter) wall time of a control cycle.
#[derive(Clone, Debug)]
pub struct ScaledClock {
    epoch: Instant,
    speed: f64,
}

impl ScaledClock {
    /// The fastest speed accepted: at 16 a 500 Hz (e-Series) controller's cycle is 125 µs of
    /// wall time, not much more than a sleeping thread's wake-up slack.
    pub const MAX_SPEED: f64 = 16.0;

    /// A clock whose epoch is now, running `speed` times real time (1 is the wall clock).
    /// Refuses a speed that is not finite, not positive, or above [`Self::MAX_SPEED`].
    pub fn new(speed: f64) -> Result<Self, CellTypesError> {
        if !speed.is_finite() {
            return Err(CellTypesError::NotFinite {
                what: "clock speed",
                value: speed,
            });
        }
        if !(speed > 0.0 && speed <= Self::MAX_SPEED) {
            return Err(CellTypesError::OutOfRange {
                what: "clock speed (times real time)",
                value: speed,
                min: 0.0,
                max: Self::MAX_SPEED,
            });
        }
        Ok(Self {
            epoch: Instant::now(),
            speed,
        })
    }

    /// How many times faster than real time this clock runs.
    pub fn speed(&self) -> f64 {
        self.speed
    }
}

impl Clock for ScaledClock {
    fn now(&self) -> Duration {
        self.epoch.elapsed().mul_f64(self.speed)
    }

    fn sleep_until(&self, deadline: Duration) {
        sleep_until_scaled(|| self.now(), deadline, self.speed);
    }
}

/// A clock advanced by hand (tests, faster-than-real-time simulation). Sleeping advances it
/// to the deadline at once. Clones share the same time.
#[derive(Clone, Debug, Default)]
pub struct ManualClock {
    nanos: Arc<AtomicU64>,
}

impl ManualClock {
    /// A clock at t = 0.
    pub fn new() -> Self {
        Self::default()
    }

    /// Moves time forward by `dt`.
    pub fn advance(&self, dt: Duration) {
        self.nanos.fetch_add(
            u64::try_from(dt.as_nanos()).unwrap_or(u64::MAX),
            Ordering::SeqCst,
        );
    }
}

impl Clock for ManualClock {
    fn now(&self) -> Duration {
        Duration::from_nanos(self.nanos.load(Ordering::SeqCst))
    }

    fn sleep_until(&self, deadline: Duration) {
        let target = u64::try_from(deadline.as_nanos()).unwrap_or(u64::MAX);
        self.nanos.fetch_max(target, Ordering::SeqCst);
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn manual_clock_advances_and_sleeps_forward_only() {
        let c = ManualClock::new();
        let shared = c.clone();
        c.advance(Duration::from_millis(5));
        assert_eq!(shared.now(), Duration::from_millis(5));
        c.sleep_until(Duration::from_millis(3));
        assert_eq!(c.now(), Duration::from_millis(5));
        c.sleep_until(Duration::from_millis(8));
        assert_eq!(shared.now(), Duration::from_millis(8));
    }

    #[test]
    fn system_clock_sleeps_at_least_until_deadline() {
        let c = SystemClock::new();
        let d = c.now() + Duration::from_millis(2);
        c.sleep_until(d);
        assert!(c.now() >= d);
    }

    #[test]
    fn scaled_clock_runs_faster_than_the_wall_clock() {
        let c = ScaledClock::new(4.0).unwrap();
        assert_eq!(c.speed(), 4.0);
        let wall = Instant::now();
        let d = c.now() + Duration::from_millis(400);
        c.sleep_until(d);
        let waited = wall.elapsed();
        assert!(c.now() >= d);
        // 400 ms of clock time is 100 ms of wall time: never less, and far below the 400 ms
        // an unscaled sleep would take even on a loaded machine.
        assert!(waited >= Duration::from_millis(100), "{waited:?}");
        assert!(waited < Duration::from_millis(300), "{waited:?}");
        // Between two readings four clock seconds pass per wall second: never more than four
        // times the wall time around the readings, never less than four times the sleep
        // between them.
        let w0 = Instant::now();
        let t0 = c.now();
        std::thread::sleep(Duration::from_millis(20));
        let t1 = c.now();
        let around = w0.elapsed();
        assert!(t1 - t0 >= Duration::from_millis(80), "{:?}", t1 - t0);
        assert!(t1 - t0 <= around * 4, "{:?} in {around:?}", t1 - t0);
    }

    #[test]
    fn scaled_clock_refuses_speeds_it_cannot_run() {
        for bad in [
            0.0,
            -1.0,
            f64::NAN,
            f64::INFINITY,
            ScaledClock::MAX_SPEED * 2.0,
        ] {
            let e = ScaledClock::new(bad).unwrap_err();
            assert!(e.to_string().contains("clock speed"), "{bad}: {e}");
        }
        assert!(ScaledClock::new(0.5).is_ok());
        assert!(ScaledClock::new(ScaledClock::MAX_SPEED).is_ok());
    }
}
