//! Jerk-limited timing (issue 3 item 6) with `rsruckig`, the pure-Rust Ruckig port (no cloud
//! client, unlike the `ruckig` crate's C++ build): every path segment is a rest-to-rest
//! motion of one path parameter `s` from 0 to 1 under the joint limits scaled by each joint's
//! share of the segment (`v_s = min_j v_j / |Δq_j|`, likewise for acceleration and jerk), and
//! `q = q_a + s·Δq`: all joints follow one common profile and the executed motion stays on the
//! straight joint-space segment that was checked by construction. (Six-DoF Ruckig with phase
//! synchronization gives the same profile when it can, but falls back to time
//! synchronization on some segments once durations are discretized: up to 0.015 rad off the
//! checked segment on MBM problems, enough to graze an obstacle.)
//! Durations are discretized to whole controller periods so that every waypoint falls on a
//! sample.
//!
//! Also the limit validation of a sampled trajectory (issue 3 item 7): positions, and
//! velocity, acceleration and jerk differentiated numerically from the samples.

// Per-joint and per-cell index loops mirror the formulas; iterator chains would hide them.
#![allow(clippy::needless_range_loop)]

use crate::error::PlanError;
use cell_types::{Joints, Trajectory, TrajectorySample};
use rsruckig::prelude::*;

/// Kinematic limits per joint and the controller period.
#[derive(Copy, Clone, Debug, PartialEq)]
pub struct PlannerLimits {
    /// Max joint speed (rad/s); UR5: π.
    pub max_velocity: Joints,
    /// Max joint acceleration (rad/s²).
    pub max_acceleration: Joints,
    /// Max joint jerk (rad/s³).
    pub max_jerk: Joints,
    /// Controller period (s): 0.008 on CB3 (125 Hz), 0.002 on e-Series.
    pub period: f64,
}

impl Default for PlannerLimits {
    /// UR5 CB3: π rad/s, 5 rad/s² (the ROS placeholder; UR publishes none), 50 rad/s³, 125 Hz.
    fn default() -> Self {
        Self {
            max_velocity: [std::f64::consts::PI; 6],
            max_acceleration: [5.0; 6],
            max_jerk: [50.0; 6],
            period: 0.008,
        }
    }
}

impl PlannerLimits {
    /// Checks every limit is positive and finite.
    pub fn validate(&self) -> Result<(), PlanError> {
        for (what, vals) in [
            ("max_velocity", &self.max_velocity),
            ("max_acceleration", &self.max_acceleration),
            ("max_jerk", &self.max_jerk),
        ] {
            for v in vals {
                if !(v.is_finite() && *v > 0.0) {
                    return Err(PlanError::BadLimit { what, value: *v });
                }
            }
        }
        if !(self.period.is_finite() && self.period > 0.0) {
            return Err(PlanError::BadLimit {
                what: "period",
                value: self.period,
            });
        }
        Ok(())
    }
}

/// Times a waypoint path rest-to-rest per segment and samples it at the controller period.
pub fn time_path(path: &[Joints], limits: &PlannerLimits) -> Result<Trajectory, PlanError> {
    limits.validate()?;
    let dt = limits.period;
    let mut samples: Vec<TrajectorySample> = Vec::new();
    let Some(first) = path.first() else {
        return Err(PlanError::Timing {
            segment: 0,
            message: "empty path".into(),
        });
    };
    samples.push(TrajectorySample {
        t: 0.0,
        position: *first,
        ..Default::default()
    });
    let mut otg = Ruckig::<1, ThrowErrorHandler>::new(None, dt);
    let mut input = InputParameter::<1>::new(None);
    input.duration_discretization = DurationDiscretization::Discrete;
    let mut traj = rsruckig::prelude::Trajectory::<1>::new(None);
    for (seg, w) in path.windows(2).enumerate() {
        if w[0] == w[1] {
            continue;
        }
        let delta: Joints = std::array::from_fn(|j| w[1][j] - w[0][j]);
        // Limits of the path parameter: the tightest joint, scaled by its share.
        let scaled = |lim: &[f64; 6]| {
            (0..6)
                .filter(|&j| delta[j] != 0.0)
                .map(|j| lim[j] / delta[j].abs())
                .fold(f64::INFINITY, f64::min)
        };
        input.max_velocity[0] = scaled(&limits.max_velocity);
        input.max_acceleration[0] = scaled(&limits.max_acceleration);
        input.max_jerk[0] = scaled(&limits.max_jerk);
        input.current_position[0] = 0.0;
        input.current_velocity[0] = 0.0;
        input.current_acceleration[0] = 0.0;
        input.target_position[0] = 1.0;
        input.target_velocity[0] = 0.0;
        input.target_acceleration[0] = 0.0;
        otg.calculate(&input, &mut traj)
            .map_err(|e| PlanError::Timing {
                segment: seg,
                message: e.to_string(),
            })?;
        let duration = traj.get_duration();
        let steps = (duration / dt - 1e-9).ceil().max(1.0) as usize;
        let t0 = samples.last().map(|s| s.t).unwrap_or(0.0);
        let base = samples.len() - 1;
        let mut pos = DataArrayOrVec::<f64, 1>::new(None, 0.0);
        let mut vel = DataArrayOrVec::<f64, 1>::new(None, 0.0);
        let mut acc = DataArrayOrVec::<f64, 1>::new(None, 0.0);
        for k in 1..=steps {
            let t = (k as f64 * dt).min(duration);
            let mut section = None;
            traj.at_time(
                t,
                &mut Some(&mut pos),
                &mut Some(&mut vel),
                &mut Some(&mut acc),
                &mut None,
                &mut section,
            );
            let mut s = TrajectorySample {
                t: t0 + k as f64 * dt,
                ..Default::default()
            };
            // Re-derive the time from the index so sample times stay exact multiples.
            s.t = (base + k) as f64 * dt;
            for j in 0..6 {
                s.position[j] = w[0][j] + pos[0] * delta[j];
                s.velocity[j] = vel[0] * delta[j];
                s.acceleration[j] = acc[0] * delta[j];
            }
            if k == steps {
                // Land exactly on the waypoint, at rest.
                s.position = w[1];
                s.velocity = [0.0; 6];
                s.acceleration = [0.0; 6];
            }
            samples.push(s);
        }
    }
    Trajectory::new(dt, samples).map_err(|e| PlanError::Trajectory {
        message: e.to_string(),
    })
}

/// Relative tolerance on the numerically differentiated limits (on top of an absolute 1e-9):
/// finite differences over one period of a jerk-limited profile are averages of the true
/// derivative, so they stay within the limits up to rounding.
pub const LIMIT_TOLERANCE: f64 = 1e-6;

/// Checks positions against joint limits and the numerically differentiated velocity,
/// acceleration and jerk against the kinematic limits (tolerance [`LIMIT_TOLERANCE`]).
pub fn validate_limits(
    traj: &Trajectory,
    joint_limits: &[(f64, f64); 6],
    limits: &PlannerLimits,
) -> Result<(), PlanError> {
    let s = traj.samples();
    let dt = traj.period();
    let tol = |lim: f64| lim * (1.0 + LIMIT_TOLERANCE) + 1e-9;
    for (i, x) in s.iter().enumerate() {
        for j in 0..6 {
            let (lo, hi) = joint_limits[j];
            let p = x.position[j];
            if p < lo - 1e-12 || p > hi + 1e-12 {
                return Err(PlanError::LimitViolated {
                    sample: i,
                    joint: j,
                    quantity: "position",
                    value: p,
                    limit: if p < lo { lo } else { hi },
                });
            }
        }
    }
    // v_k = (p_k − p_{k−1}) / dt, a_k = (v_k − v_{k−1}) / dt, j_k = (a_k − a_{k−1}) / dt.
    let n = s.len();
    let mut v = vec![[0.0; 6]; n];
    let mut a = vec![[0.0; 6]; n];
    for i in 1..n {
        for j in 0..6 {
            v[i][j] = (s[i].position[j] - s[i - 1].position[j]) / dt;
        }
    }
    for i in 1..n {
        for j in 0..6 {
            let vel = v[i][j];
            if vel.abs() > tol(limits.max_velocity[j]) {
                return Err(PlanError::LimitViolated {
                    sample: i,
                    joint: j,
                    quantity: "velocity",
                    value: vel,
                    limit: limits.max_velocity[j],
                });
            }
            // The profile's own acceleration is exact; the second difference of positions
            // averages it over two periods.
            let acc = s[i].acceleration[j];
            if acc.abs() > tol(limits.max_acceleration[j]) {
                return Err(PlanError::LimitViolated {
                    sample: i,
                    joint: j,
                    quantity: "acceleration",
                    value: acc,
                    limit: limits.max_acceleration[j],
                });
            }
            if i >= 2 {
                a[i][j] = (v[i][j] - v[i - 1][j]) / dt;
                if a[i][j].abs() > tol(limits.max_acceleration[j]) {
                    return Err(PlanError::LimitViolated {
                        sample: i,
                        joint: j,
                        quantity: "acceleration (differentiated)",
                        value: a[i][j],
                        limit: limits.max_acceleration[j],
                    });
                }
            }
            let jerk = (s[i].acceleration[j] - s[i - 1].acceleration[j]) / dt;
            if jerk.abs() > tol(limits.max_jerk[j]) {
                return Err(PlanError::LimitViolated {
                    sample: i,
                    joint: j,
                    quantity: "jerk (differentiated)",
                    value: jerk,
                    limit: limits.max_jerk[j],
                });
            }
        }
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn segments_stay_on_the_straight_line_and_within_limits() {
        let limits = PlannerLimits::default();
        let path = [
            [0.0; 6],
            [1.0, -0.5, 0.3, 0.0, 0.2, -1.0],
            [0.5, 0.5, 0.3, 1.0, 0.2, -1.0],
        ];
        let traj = time_path(&path, &limits).unwrap();
        assert_eq!(traj.start(), Some(&path[0]));
        assert_eq!(traj.goal(), Some(&path[2]));
        validate_limits(&traj, &[(-7.0, 7.0); 6], &limits).unwrap();
        // Every sample lies on one of the two straight segments (phase synchronization).
        let mut worst = 0.0f64;
        for s in traj.samples() {
            let dev = path
                .windows(2)
                .map(|w| {
                    let d: Vec<f64> = (0..6).map(|j| w[1][j] - w[0][j]).collect();
                    let n2: f64 = d.iter().map(|x| x * x).sum();
                    let t = ((0..6)
                        .map(|j| (s.position[j] - w[0][j]) * d[j])
                        .sum::<f64>()
                        / n2)
                        .clamp(0.0, 1.0);
                    (0..6)
                        .map(|j| (s.position[j] - (w[0][j] + t * d[j])).powi(2))
                        .sum::<f64>()
                        .sqrt()
                })
                .fold(f64::INFINITY, f64::min);
            worst = worst.max(dev);
        }
        assert!(worst < 1e-12, "deviation from the checked path {worst}");
    }

    #[test]
    fn random_segments_stay_on_their_line_to_rounding() {
        use rand::{Rng, SeedableRng};
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(31);
        let limits = PlannerLimits::default();
        for _ in 0..100 {
            let a: Joints = std::array::from_fn(|_| rng.random_range(-3.0..3.0));
            let b: Joints = std::array::from_fn(|j| a[j] + rng.random_range(-1.5..1.5));
            let traj = time_path(&[a, b], &limits).unwrap();
            validate_limits(&traj, &[(-7.0, 7.0); 6], &limits).unwrap();
            let d: Vec<f64> = (0..6).map(|j| b[j] - a[j]).collect();
            let n2: f64 = d.iter().map(|x| x * x).sum();
            for s in traj.samples() {
                let t = (0..6).map(|j| (s.position[j] - a[j]) * d[j]).sum::<f64>() / n2;
                let dev = (0..6)
                    .map(|j| (s.position[j] - (a[j] + t * d[j])).abs())
                    .fold(0.0, f64::max);
                assert!(dev < 1e-12, "{dev} rad off the segment {a:?} -> {b:?}");
            }
        }
    }

    #[test]
    fn tighter_limits_take_longer_and_violations_are_caught() {
        let fast = PlannerLimits::default();
        let slow = PlannerLimits {
            max_velocity: [0.5; 6],
            ..fast
        };
        let path = [[0.0; 6], [2.0, 0.0, 0.0, 0.0, 0.0, 0.0]];
        let a = time_path(&path, &fast).unwrap();
        let b = time_path(&path, &slow).unwrap();
        assert!(b.duration() > a.duration() + 1.0);
        // The fast trajectory breaks the slow limits: the validator says which and where.
        let err = validate_limits(&a, &[(-7.0, 7.0); 6], &slow).unwrap_err();
        assert!(
            matches!(
                err,
                PlanError::LimitViolated {
                    joint: 0,
                    quantity: "velocity",
                    ..
                }
            ),
            "{err}"
        );
        let err = validate_limits(&a, &[(-1.0, 1.0); 6], &fast).unwrap_err();
        assert!(matches!(
            err,
            PlanError::LimitViolated {
                quantity: "position",
                ..
            }
        ));
        assert!(PlannerLimits {
            period: 0.0,
            ..fast
        }
        .validate()
        .is_err());
    }
}
