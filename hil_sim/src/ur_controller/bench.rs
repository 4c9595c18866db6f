//! Jitter benchmark of the UR driver's streaming loop (issue 5 §5): the driver streams a
//! trajectory to the simulated controller on loopback at 125 Hz (CB3) or 500 Hz (e-Series)
//! and reports the cycle-time statistics of its link thread, next to a baseline measured in
//! the same process: a bare `SystemClock::sleep_until` loop at the same period.

use std::sync::Arc;

use cell_types::{Clock, SystemClock, Trajectory, TrajectorySample};
use firmware_iface::arm::{Arm, ArmError, ExecutionOutcome, JitterStats};
use firmware_iface::ur::{UrArm, UrConfig};

use super::{start, UrSimConfig, UrSimError};

/// Why the benchmark could not run.
#[derive(Debug, thiserror::Error)]
#[non_exhaustive]
pub enum BenchError {
    /// The simulator did not start.
    #[error(transparent)]
    Sim(#[from] UrSimError),
    /// The driver failed.
    #[error(transparent)]
    Arm(#[from] ArmError),
    /// The trajectory could not be built.
    #[error("benchmark trajectory: {0}")]
    Trajectory(#[from] cell_types::CellTypesError),
    /// The motion did not complete.
    #[error("benchmark motion stopped: {0}")]
    Stopped(String),
}

/// One benchmark result.
#[derive(Clone, Debug, PartialEq)]
pub struct JitterReport {
    /// Controller rate (Hz).
    pub rate_hz: f64,
    /// Seconds streamed.
    pub seconds: f64,
    /// The driver's streaming loop.
    pub stream: JitterStats,
    /// A bare sleep loop at the same period, same process.
    pub baseline: JitterStats,
}

impl JitterReport {
    /// JSON summary (hand-written: no serde dependency for one line).
    pub fn to_json(&self) -> String {
        let s = |j: &JitterStats| {
            format!(
                "{{\"cycles\":{},\"p50_us\":{:.1},\"p99_us\":{:.1},\"max_us\":{:.1},\"jitter_p99_us\":{:.1},\"late_cycles\":{}}}",
                j.cycles, j.p50_us, j.p99_us, j.max_us, j.jitter_p99_us, j.late_cycles
            )
        };
        let ratio = if self.baseline.jitter_p99_us > 0.0 {
            self.stream.jitter_p99_us / self.baseline.jitter_p99_us
        } else {
            f64::NAN
        };
        format!(
            "{{\"bench\":\"ur_stream_jitter\",\"rate_hz\":{},\"seconds\":{},\"stream\":{},\"baseline_sleep_loop\":{},\"jitter_p99_ratio\":{:.2}}}",
            self.rate_hz,
            self.seconds,
            s(&self.stream),
            s(&self.baseline),
            ratio
        )
    }
}

fn baseline(period: f64, cycles: usize) -> JitterStats {
    let clock = SystemClock::new();
    let p = std::time::Duration::from_secs_f64(period);
    let mut times = Vec::with_capacity(cycles);
    let mut next = clock.now();
    let mut last = clock.now();
    for _ in 0..cycles {
        next += p;
        clock.sleep_until(next);
        let now = clock.now();
        times.push((now - last).as_secs_f64());
        last = now;
    }
    JitterStats::from_cycles(&mut times, period)
}

/// Streams a `seconds`-long back-and-forth wrist motion at 125 Hz (`e_series` false) or
/// 500 Hz and returns the loop statistics with the baseline.
pub fn stream_jitter(e_series: bool, seconds: f64) -> Result<JitterReport, BenchError> {
    let config = if e_series {
        UrSimConfig::for_tests().e_series()
    } else {
        UrSimConfig::for_tests()
    };
    let period = config.period();
    let sim = start(config, Arc::new(SystemClock::new()))?;
    let mut arm = UrArm::connect(
        UrConfig {
            host: sim.addr(),
            ports: sim.ports(),
            lost_cycles: 50,
            ..UrConfig::default()
        },
        Arc::new(SystemClock::new()),
    )?;
    let q0 = arm.state()?.joints.position;
    let n = (seconds / period).round() as usize;
    let samples = (0..=n)
        .map(|i| {
            let t = i as f64 * period;
            let mut q = q0;
            // One full cosine period: starts and ends at rest at q0.
            q[5] += 0.25 * (1.0 - (std::f64::consts::TAU * t / seconds).cos());
            TrajectorySample {
                t,
                position: q,
                ..Default::default()
            }
        })
        .collect();
    let outcome = arm.execute(&Trajectory::new(period, samples)?)?;
    let stream = match outcome {
        ExecutionOutcome::Completed { jitter, .. } => jitter,
        other => return Err(BenchError::Stopped(format!("{other:?}"))),
    };
    drop(arm);
    drop(sim);
    Ok(JitterReport {
        rate_hz: 1.0 / period,
        seconds,
        baseline: baseline(period, n),
        stream,
    })
}
