//! Real-time scheduling of a driver thread: Linux `SCHED_FIFO`, as UR's own client library
//! asks for its RTDE thread. The UR driver's link thread answers the controller every
//! 8 ms; at normal priority, a busy machine (the policy's inference, point-cloud fusion)
//! can delay it past the servo program's watchdog. Two libc calls (libc is already in the
//! tree for the allocator setting), so no crate for it.
#![allow(unsafe_code)] // pthread_setschedparam / pthread_getschedparam; see each SAFETY

use std::os::unix::thread::JoinHandleExt;
use std::thread::JoinHandle;

/// The highest `SCHED_FIFO` priority Linux offers.
pub const MAX_PRIORITY: u8 = cell_types::config::MAX_REALTIME_PRIORITY;

/// How a driver thread is scheduled.
#[derive(Clone, Debug, PartialEq, Eq)]
pub enum Scheduling {
    /// Normal time-sharing: no real-time priority was asked for.
    Normal,
    /// First-in-first-out real-time scheduling at this priority (1-99).
    Fifo(u8),
    /// Real-time scheduling was asked for and refused: the thread runs time-shared.
    Refused {
        /// The priority asked for.
        priority: u8,
        /// Why, from the operating system, with what to do.
        why: String,
    },
}

impl std::fmt::Display for Scheduling {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            Scheduling::Normal => write!(f, "normal priority (no real-time priority asked)"),
            Scheduling::Fifo(p) => write!(f, "real-time, SCHED_FIFO priority {p}"),
            Scheduling::Refused { priority, why } => write!(
                f,
                "normal priority: SCHED_FIFO priority {priority} refused ({why})"
            ),
        }
    }
}

/// Asks for `SCHED_FIFO` at `priority` (1-99) for `thread`; what it got, never an error:
/// a refused request leaves the thread as it was.
pub fn request_fifo<T>(thread: &JoinHandle<T>, priority: u8) -> Scheduling {
    if !(1..=MAX_PRIORITY).contains(&priority) {
        return Scheduling::Refused {
            priority,
            why: format!("a SCHED_FIFO priority is 1 to {MAX_PRIORITY}"),
        };
    }
    let param = libc::sched_param {
        sched_priority: i32::from(priority),
    };
    // SAFETY: the pthread_t comes from a JoinHandle we hold, so the thread has not been
    // joined or detached and the id is valid; `param` is a valid sched_param for the call.
    let rc =
        unsafe { libc::pthread_setschedparam(thread.as_pthread_t(), libc::SCHED_FIFO, &param) };
    if rc == 0 {
        return Scheduling::Fifo(priority);
    }
    let err = std::io::Error::from_raw_os_error(rc);
    let why = if rc == libc::EPERM {
        format!(
            "{err}: let this user use real-time priorities, e.g. `@realtime - rtprio \
             {MAX_PRIORITY}` in /etc/security/limits.conf and the user in group realtime, \
             or run with CAP_SYS_NICE"
        )
    } else {
        err.to_string()
    };
    Scheduling::Refused { priority, why }
}

/// The scheduling policy and priority `thread` runs at (`libc::SCHED_*`, priority), as the
/// operating system reports it.
pub fn policy_of<T>(thread: &JoinHandle<T>) -> std::io::Result<(i32, i32)> {
    let mut policy = 0;
    let mut param = libc::sched_param { sched_priority: 0 };
    // SAFETY: as in `request_fifo`; both out-pointers point to live locals.
    let rc = unsafe { libc::pthread_getschedparam(thread.as_pthread_t(), &mut policy, &mut param) };
    if rc == 0 {
        Ok((policy, param.sched_priority))
    } else {
        Err(std::io::Error::from_raw_os_error(rc))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// What the thread got is what the operating system reports: FIFO at the priority where
    /// it was granted (as root or with rtprio), unchanged where refused.
    #[test]
    fn a_request_is_granted_as_reported_or_refused_with_a_reason() {
        let (tx, rx) = std::sync::mpsc::channel::<()>();
        let t = std::thread::spawn(move || {
            let _ = rx.recv();
        });
        let before = policy_of(&t).unwrap();
        assert_eq!(before.0, libc::SCHED_OTHER);
        match request_fifo(&t, 10) {
            Scheduling::Fifo(p) => {
                assert_eq!(p, 10);
                assert_eq!(policy_of(&t).unwrap(), (libc::SCHED_FIFO, 10));
            }
            Scheduling::Refused { priority, why } => {
                assert_eq!(priority, 10);
                assert!(!why.is_empty());
                assert_eq!(policy_of(&t).unwrap(), before);
            }
            Scheduling::Normal => panic!("a request never leaves Normal"),
        }
        let bad = request_fifo(&t, 0);
        assert!(
            matches!(&bad, Scheduling::Refused { priority: 0, why } if why.contains("1 to 99")),
            "{bad:?}"
        );
        tx.send(()).unwrap();
        t.join().unwrap();
    }
}
