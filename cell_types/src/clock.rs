//! Injected time: control code reads a [`Clock`], never the wall clock directly, so the
//! simulator can run faster than real time and seeded runs repeat exactly.

use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::{Arc, Condvar, Mutex, MutexGuard};
use std::time::{Duration, Instant};

use crate::CellTypesError;

/// A source of monotonic time and of waiting.
pub trait Clock: Send + Sync {
    /// Time since this clock's epoch.
    fn now(&self) -> Duration;
    /// Waits until `deadline` (since the epoch) has passed.
    fn sleep_until(&self, deadline: Duration);
    /// For the one thread that keeps a simulation's time (the simulated controller's control
    /// loop): the next cycle starts at `t`. Most clocks just wait for it; a [`TickClock`]
    /// moves its time there (at most its speed allows) and wakes whoever waits for it.
    fn advance_to(&self, t: Duration) {
        self.sleep_until(t);
    }
    /// For the thread that kept time with [`Clock::advance_to`]: it has stopped. A
    /// [`TickClock`] then runs on by itself, so that nothing waiting on it hangs.
    fn keeper_stopped(&self) {}
    /// How many times faster than real time the clock runs (1 for the wall clock and for a
    /// clock moved by hand), so a simulator can turn its own waits into wall time.
    fn speed(&self) -> f64 {
        1.0
    }
}

/// Checks a simulated clock's speed: finite, positive, at most [`ScaledClock::MAX_SPEED`].
fn checked_speed(speed: f64) -> Result<f64, CellTypesError> {
    if !speed.is_finite() {
        return Err(CellTypesError::NotFinite {
            what: "clock speed",
            value: speed,
        });
    }
    if !(speed > 0.0 && speed <= ScaledClock::MAX_SPEED) {
        return Err(CellTypesError::OutOfRange {
            what: "clock speed (times real time)",
            value: speed,
            min: 0.0,
            max: ScaledClock::MAX_SPEED,
        });
    }
    Ok(speed)
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
        Ok(Self {
            epoch: Instant::now(),
            speed: checked_speed(speed)?,
        })
    }
}

impl Clock for ScaledClock {
    fn now(&self) -> Duration {
        self.epoch.elapsed().mul_f64(self.speed)
    }

    fn sleep_until(&self, deadline: Duration) {
        sleep_until_scaled(|| self.now(), deadline, self.speed);
    }

    fn speed(&self) -> f64 {
        self.speed
    }
}

/// Simulated time that moves only when its keeper, the simulated controller's control loop,
/// moves it ([`Clock::advance_to`], once per control cycle), and at most `speed` times
/// faster than real time. Everything else in the simulated cell reads and waits on it, so
/// time is counted in control cycles: a cycle that waits for its client's answer (lockstep)
/// delays the clock with it instead of leaving the arm behind its time stamps, and a
/// seeded episode replays bit for bit. When the keeper stops ([`Clock::keeper_stopped`]),
/// or is silent for [`TickClock::KEEPER_SILENCE`] of wall time, the clock runs on by
/// itself at its speed, so that no waiting thread hangs.
#[derive(Debug)]
pub struct TickClock {
    speed: f64,
    state: Mutex<TickState>,
    moved: Condvar,
}

#[derive(Debug)]
struct TickState {
    /// Simulated time (while kept).
    now: Duration,
    /// The pace's origin: this wall instant is due at simulated time `pace_sim`.
    pace_wall: Instant,
    pace_sim: Duration,
    /// Wall instant of the keeper's last move.
    last_move: Instant,
    /// Running by itself since this wall instant, from this simulated time.
    free_since: Option<(Instant, Duration)>,
}

impl TickState {
    fn now(&self, speed: f64) -> Duration {
        match self.free_since {
            Some(since) => free_running_now(since, speed),
            None => self.now,
        }
    }
}

/// The time of a tick clock running by itself since `(wall, sim)` at `speed`.
fn free_running_now((wall, sim): (Instant, Duration), speed: f64) -> Duration {
    sim + wall.elapsed().mul_f64(speed)
}

impl TickClock {
    /// The keeper's silence (wall time) after which the clock runs by itself.
    pub const KEEPER_SILENCE: Duration = Duration::from_secs(2);

    /// A clock at t = 0 whose keeper may move it `speed` times faster than real time at
    /// most (checked as [`ScaledClock::new`] checks it).
    pub fn new(speed: f64) -> Result<Self, CellTypesError> {
        let wall = Instant::now();
        Ok(Self {
            speed: checked_speed(speed)?,
            state: Mutex::new(TickState {
                now: Duration::ZERO,
                pace_wall: wall,
                pace_sim: Duration::ZERO,
                last_move: wall,
                free_since: None,
            }),
            moved: Condvar::new(),
        })
    }

    fn state(&self) -> MutexGuard<'_, TickState> {
        self.state.lock().unwrap_or_else(|e| e.into_inner())
    }
}

/// Behind its pace by more than this (wall time), a tick clock restarts its pace from now
/// instead of catching up in a burst.
const TICK_PACE_SLACK: Duration = Duration::from_millis(20);

impl Clock for TickClock {
    fn now(&self) -> Duration {
        self.state().now(self.speed)
    }

    fn sleep_until(&self, deadline: Duration) {
        let mut s = self.state();
        loop {
            if let Some(since) = s.free_since {
                drop(s);
                let speed = self.speed;
                sleep_until_scaled(|| free_running_now(since, speed), deadline, speed);
                return;
            }
            if s.now >= deadline {
                return;
            }
            if s.last_move.elapsed() >= Self::KEEPER_SILENCE {
                let now = s.now;
                s.free_since = Some((Instant::now(), now));
                continue;
            }
            let left = Self::KEEPER_SILENCE.saturating_sub(s.last_move.elapsed());
            s = self
                .moved
                .wait_timeout(s, left)
                .map(|(g, _)| g)
                .unwrap_or_else(|e| e.into_inner().0);
        }
    }

    fn advance_to(&self, t: Duration) {
        let due = {
            let s = self.state();
            s.pace_wall + t.saturating_sub(s.pace_sim).div_f64(self.speed)
        };
        let wall = Instant::now();
        if due > wall {
            std::thread::sleep(due - wall);
        }
        let mut s = self.state();
        let now = s.now(self.speed).max(t);
        if wall > due + TICK_PACE_SLACK {
            s.pace_wall = Instant::now();
            s.pace_sim = now;
        }
        s.now = now;
        s.free_since = None;
        s.last_move = Instant::now();
        drop(s);
        self.moved.notify_all();
    }

    fn keeper_stopped(&self) {
        let mut s = self.state();
        if s.free_since.is_none() {
            let now = s.now;
            s.free_since = Some((Instant::now(), now));
        }
        drop(s);
        self.moved.notify_all();
    }

    fn speed(&self) -> f64 {
        self.speed
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
        for bad in [0.0, f64::NAN, ScaledClock::MAX_SPEED * 2.0] {
            assert!(TickClock::new(bad).is_err(), "{bad}");
        }
    }

    /// A tick clock's time is its keeper's: it stands still between moves, and a thread
    /// waiting for a time wakes at the first move that reaches it.
    #[test]
    fn tick_clock_moves_only_with_its_keeper_and_wakes_sleepers_at_its_moves() {
        let c = Arc::new(TickClock::new(16.0).unwrap());
        assert_eq!(c.speed(), 16.0);
        let sleeper = {
            let c = c.clone();
            std::thread::spawn(move || {
                c.sleep_until(Duration::from_millis(50));
                c.now()
            })
        };
        std::thread::sleep(Duration::from_millis(20));
        assert_eq!(c.now(), Duration::ZERO);
        assert!(!sleeper.is_finished());
        for k in 1..=8u64 {
            c.advance_to(Duration::from_millis(8 * k));
        }
        assert_eq!(c.now(), Duration::from_millis(64));
        let woke = sleeper.join().unwrap();
        assert!(
            woke >= Duration::from_millis(50) && woke <= Duration::from_millis(64),
            "{woke:?}"
        );
        // Moving back is not possible.
        c.advance_to(Duration::from_millis(10));
        assert_eq!(c.now(), Duration::from_millis(64));
    }

    /// The keeper cannot move a tick clock faster than its speed: 400 ms of its time at 4
    /// take at least 100 ms of wall time.
    #[test]
    fn tick_clock_keeps_its_pace() {
        let c = TickClock::new(4.0).unwrap();
        let wall = Instant::now();
        for k in 1..=50u64 {
            c.advance_to(Duration::from_millis(8 * k));
        }
        let waited = wall.elapsed();
        assert_eq!(c.now(), Duration::from_millis(400));
        assert!(waited >= Duration::from_millis(95), "{waited:?}");
    }

    /// Once its keeper has stopped, or has been silent for `KEEPER_SILENCE`, a tick clock
    /// runs on by itself, so that nothing waiting on it hangs.
    #[test]
    fn tick_clock_runs_by_itself_without_its_keeper() {
        let c = TickClock::new(4.0).unwrap();
        c.advance_to(Duration::from_millis(8));
        c.keeper_stopped();
        let wall = Instant::now();
        c.sleep_until(Duration::from_millis(48));
        assert!(c.now() >= Duration::from_millis(48));
        assert!(
            wall.elapsed() >= Duration::from_millis(9),
            "{:?}",
            wall.elapsed()
        );

        let silent = TickClock::new(1.0).unwrap();
        let wall = Instant::now();
        silent.sleep_until(Duration::from_millis(5));
        assert!(wall.elapsed() >= TickClock::KEEPER_SILENCE);
        assert!(silent.now() >= Duration::from_millis(5));
    }
}
