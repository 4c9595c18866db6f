//! The simulated controller's thread, woken late, catches up with a burst of cycles no
//! client can answer inside; the servo program's watchdog must not blame the driver for
//! them (`Core::step_late`). A binary of its own: the driver keeps the real robot's
//! 10-cycle watchdog (80 ms), which other tests running beside it could starve it past.

#![allow(clippy::unwrap_used, clippy::expect_used)] // test helpers may panic

use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::Arc;
use std::time::Duration;

use cell_types::{Clock, SystemClock, Trajectory, TrajectorySample};
use firmware_iface::arm::{Arm, ExecutionOutcome};
use firmware_iface::ur::{UrArm, UrConfig};
use hil_sim::ur_controller::{start, UrSimConfig};

/// The wall clock plus an offset the test can jump forward: to the simulator's control
/// thread, a jump looks like a wake-up that came that much late (its thread starved of CPU).
struct JumpClock {
    wall: SystemClock,
    offset_ns: AtomicU64,
}

impl JumpClock {
    fn offset(&self) -> Duration {
        Duration::from_nanos(self.offset_ns.load(Ordering::SeqCst))
    }
}

impl Clock for JumpClock {
    fn now(&self) -> Duration {
        self.wall.now() + self.offset()
    }

    fn sleep_until(&self, deadline: Duration) {
        self.wall
            .sleep_until(deadline.saturating_sub(self.offset()));
    }
}

#[test]
fn a_starved_controller_thread_catching_up_does_not_trip_the_watchdog() {
    let clock = Arc::new(JumpClock {
        wall: SystemClock::new(),
        offset_ns: AtomicU64::new(0),
    });
    let h = start(UrSimConfig::for_tests(), clock.clone()).unwrap();
    // The driver's own clock runs on: only the controller's thread was late.
    let mut arm = UrArm::connect(
        UrConfig {
            host: h.addr(),
            ports: h.ports(),
            lost_cycles: 12,
            watchdog_cycles: 10,
            ..UrConfig::default()
        },
        Arc::new(SystemClock::new()),
    )
    .unwrap();
    let start_q = arm.state().unwrap().joints.position;
    let mut goal = start_q;
    goal[0] += 0.3;
    goal[5] -= 0.3;
    // A 3 s cosine ramp: slow enough that the arm holding its target through the burst
    // stays well inside the tracking bound.
    let (duration, period) = (3.0, arm.period());
    let n = (duration / period).round() as usize;
    let samples = (0..=n)
        .map(|i| {
            let t = i as f64 * period;
            let phase = std::f64::consts::PI * t / duration;
            let s = 0.5 * (1.0 - phase.cos());
            let ds = 0.5 * std::f64::consts::PI / duration * phase.sin();
            TrajectorySample {
                t,
                position: std::array::from_fn(|j| start_q[j] + (goal[j] - start_q[j]) * s),
                velocity: std::array::from_fn(|j| (goal[j] - start_q[j]) * ds),
                acceleration: [0.0; 6],
            }
        })
        .collect();
    let traj = Trajectory::new(period, samples).unwrap();
    let outcome = std::thread::scope(|s| {
        s.spawn(|| {
            // Three times 15 cycles late: each time the controller runs them back to back,
            // faster than any client could answer; more than the program's 10-cycle
            // watchdog. The driver's answer sometimes lands inside a burst (longer bursts
            // make that likelier and would hide the fault), so three of them.
            for _ in 0..3 {
                std::thread::sleep(Duration::from_millis(600));
                clock.offset_ns.fetch_add(
                    Duration::from_millis(120).as_nanos() as u64,
                    Ordering::SeqCst,
                );
            }
        });
        arm.execute(&traj).unwrap()
    });
    assert!(
        matches!(outcome, ExecutionOutcome::Completed { .. }),
        "{outcome:?}"
    );
    assert!(cell_types::joints::max_abs_diff(&h.snapshot().actual_q, &goal) < 0.01);
}
