//! The UR driver's link thread allocates nothing while it streams a trajectory (issue 5 §2:
//! "no allocation per cycle"). A counting global allocator counts allocations made on the
//! thread named `ur-rtde-link` only.

#![allow(clippy::unwrap_used, clippy::expect_used)] // test helpers may panic
#![allow(unsafe_code)] // a GlobalAlloc implementation is unsafe by definition

use std::alloc::{GlobalAlloc, Layout, System};
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::Arc;

use cell_types::{SystemClock, Trajectory, TrajectorySample};
use firmware_iface::arm::{Arm, ExecutionOutcome};
use firmware_iface::ur::{UrArm, UrConfig};
use hil_sim::ur_controller::{start, UrSimConfig};

struct Counting;

static LINK_ALLOCS: AtomicU64 = AtomicU64::new(0);

fn on_link_thread() -> bool {
    // Spawned threads carry their handle from the start, so this does not allocate.
    std::thread::current().name() == Some("ur-rtde-link")
}

// SAFETY: forwards every call to the system allocator unchanged; only counts.
unsafe impl GlobalAlloc for Counting {
    unsafe fn alloc(&self, layout: Layout) -> *mut u8 {
        if on_link_thread() {
            LINK_ALLOCS.fetch_add(1, Ordering::Relaxed);
        }
        unsafe { System.alloc(layout) }
    }
    unsafe fn dealloc(&self, ptr: *mut u8, layout: Layout) {
        unsafe { System.dealloc(ptr, layout) }
    }
    unsafe fn realloc(&self, ptr: *mut u8, layout: Layout, new_size: usize) -> *mut u8 {
        if on_link_thread() {
            LINK_ALLOCS.fetch_add(1, Ordering::Relaxed);
        }
        unsafe { System.realloc(ptr, layout, new_size) }
    }
}

#[global_allocator]
static GLOBAL: Counting = Counting;

#[test]
fn link_thread_streams_a_trajectory_without_allocating() {
    let h = start(UrSimConfig::for_tests(), Arc::new(SystemClock::new())).unwrap();
    let mut arm = UrArm::connect(
        UrConfig {
            host: h.addr(),
            ports: h.ports(),
            lost_cycles: 12,
            ..UrConfig::default()
        },
        Arc::new(SystemClock::new()),
    )
    .unwrap();
    let q0 = arm.state().unwrap().joints.position;
    let samples = (0..=150)
        .map(|i| {
            let s = i as f64 / 150.0;
            let mut q = q0;
            q[4] += 0.2 * (3.0 * s * s - 2.0 * s * s * s);
            TrajectorySample {
                t: i as f64 * 0.008,
                position: q,
                ..Default::default()
            }
        })
        .collect();
    let traj = Trajectory::new(0.008, samples).unwrap();
    let before = LINK_ALLOCS.load(Ordering::SeqCst);
    let outcome = arm.execute(&traj).unwrap();
    let after = LINK_ALLOCS.load(Ordering::SeqCst);
    let ExecutionOutcome::Completed { jitter, .. } = outcome else {
        panic!("{outcome:?}");
    };
    assert!(jitter.cycles > 150, "{jitter:?}");
    assert_eq!(
        after - before,
        0,
        "link thread allocated during {} cycles",
        jitter.cycles
    );
}
