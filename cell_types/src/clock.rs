//! Injected time: control code reads a [`Clock`], never the wall clock directly, so the
//! simulator can run faster than real time and seeded runs repeat exactly.

use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::Arc;
use std::time::{Duration, Instant};

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
        // Sleep most of the way, then spin the last stretch: `thread::sleep` alone overshoots
        // by the scheduler's slack (50–100 µs), which shows up as control-loop jitter.
        const SPIN: Duration = Duration::from_micros(200);
        loop {
            let now = self.now();
            if now >= deadline {
                return;
            }
            let left = deadline - now;
            if left > SPIN {
                std::thread::sleep(left - SPIN);
            } else {
                std::hint::spin_loop();
            }
        }
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
}
