//! Time-stamped joint trajectories sampled at a fixed controller rate.

use serde::{Deserialize, Serialize};

use crate::error::CellTypesError;
use crate::joints::{Joints, JOINT_COUNT};

/// One sample of a trajectory.
#[derive(Copy, Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct TrajectorySample {
    /// Time since the trajectory start (s).
    pub t: f64,
    /// Joint positions (rad).
    pub position: Joints,
    /// Joint velocities (rad/s).
    pub velocity: Joints,
    /// Joint accelerations (rad/s²).
    pub acceleration: Joints,
}

/// A joint trajectory sampled every `period` seconds, starting at t = 0.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Trajectory {
    period: f64,
    samples: Vec<TrajectorySample>,
}

impl Trajectory {
    /// Builds a trajectory, checking that the period is positive, samples are evenly spaced
    /// at it from t = 0, and every value is finite.
    pub fn new(period: f64, samples: Vec<TrajectorySample>) -> Result<Self, CellTypesError> {
        if !(period.is_finite() && period > 0.0) {
            return Err(CellTypesError::NotPositive {
                what: "trajectory period",
                value: period,
            });
        }
        for (i, s) in samples.iter().enumerate() {
            let expected = i as f64 * period;
            if s.t.is_nan() || (s.t - expected).abs() > 1e-9 * (1.0 + expected) {
                return Err(CellTypesError::UnevenTrajectory {
                    index: i,
                    t: s.t,
                    expected,
                    period,
                });
            }
            for j in 0..JOINT_COUNT {
                for (what, v) in [
                    ("trajectory position", s.position[j]),
                    ("trajectory velocity", s.velocity[j]),
                    ("trajectory acceleration", s.acceleration[j]),
                ] {
                    if !v.is_finite() {
                        return Err(CellTypesError::NotFinite { what, value: v });
                    }
                }
            }
        }
        Ok(Self { period, samples })
    }

    /// Sample period (s).
    pub fn period(&self) -> f64 {
        self.period
    }

    /// Sample rate (Hz).
    pub fn rate_hz(&self) -> f64 {
        1.0 / self.period
    }

    /// The samples, in time order.
    pub fn samples(&self) -> &[TrajectorySample] {
        &self.samples
    }

    /// Duration from the first to the last sample (s).
    pub fn duration(&self) -> f64 {
        self.samples.len().saturating_sub(1) as f64 * self.period
    }

    /// Number of samples.
    pub fn len(&self) -> usize {
        self.samples.len()
    }

    /// True when there are no samples.
    pub fn is_empty(&self) -> bool {
        self.samples.is_empty()
    }

    /// The first sample's positions, if any.
    pub fn start(&self) -> Option<&Joints> {
        self.samples.first().map(|s| &s.position)
    }

    /// The last sample's positions, if any.
    pub fn goal(&self) -> Option<&Joints> {
        self.samples.last().map(|s| &s.position)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn sample(t: f64) -> TrajectorySample {
        TrajectorySample {
            t,
            ..Default::default()
        }
    }

    #[test]
    fn even_samples_accepted() {
        let tr =
            Trajectory::new(0.008, (0..10).map(|i| sample(i as f64 * 0.008)).collect()).unwrap();
        assert_eq!(tr.len(), 10);
        assert!((tr.duration() - 0.072).abs() < 1e-12);
        assert!((tr.rate_hz() - 125.0).abs() < 1e-9);
    }

    #[test]
    fn uneven_samples_rejected() {
        let err = Trajectory::new(0.008, vec![sample(0.0), sample(0.01)]).unwrap_err();
        assert!(matches!(
            err,
            CellTypesError::UnevenTrajectory { index: 1, .. }
        ));
    }

    #[test]
    fn bad_period_and_nan_rejected() {
        assert!(Trajectory::new(0.0, vec![]).is_err());
        let mut s = sample(0.0);
        s.velocity[3] = f64::NAN;
        assert!(matches!(
            Trajectory::new(0.002, vec![s]),
            Err(CellTypesError::NotFinite {
                what: "trajectory velocity",
                ..
            })
        ));
    }
}
