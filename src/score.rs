//! Offline scoring of a learned policy against recorded demonstrations (`equact policy
//! score`): every step's observation goes through the network, and its keyframe is compared
//! with the expert's. No cell runs, so a model or an inference setting (the translation
//! sampling) can be judged on held-out demonstrations in minutes instead of an hour of
//! closed-loop episodes; the closed loop (`equact eval`) stays the measure of success.

use std::collections::BTreeMap;

use anyhow::Context;
use cell_types::Keyframe;
use nalgebra::{Point3, Rotation3, Vector3};
use policy::predict::Policy;
use serde::Serialize;

use crate::train::DemoSample;

/// How far a predicted keyframe is from the expert's.
#[derive(Debug, Clone, Copy, PartialEq, Serialize)]
pub struct KeyframeError {
    /// Distance between the TCP positions (m).
    pub position_m: f64,
    /// The predicted TCP position minus the expert's (m, base frame): a bias shared by the
    /// steps of one stage shows in it, noise does not.
    pub offset_m: [f64; 3],
    /// Angle between the TCP orientations (degrees), the smaller of the angle to the
    /// expert's and to the expert's turned half a turn about the approach axis: the
    /// parallel gripper's two fingers are alike.
    pub rotation_deg: f64,
    /// Whether the gripper's open state agrees.
    pub open_agrees: bool,
}

/// One scored step: which demonstration step it is, the error and the prediction's cost.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct ScoredStep {
    /// `task/variation`.
    pub variation: String,
    /// The demonstration's seed.
    pub seed: u64,
    /// The step's index in its demonstration (0: the first keyframe).
    pub step: usize,
    /// The keyframe's error.
    pub error: KeyframeError,
    /// CPU seconds of the prediction, all of its threads (`policy::predict::StageTimings`).
    pub prediction_cpu_s: f64,
    /// The translation field's logit at the predicted position.
    pub predicted_logit: f32,
    /// The field's logit at the expert's position: above `predicted_logit`, the sampling
    /// missed a better peak; below, the field itself prefers the wrong place.
    pub expert_logit: f32,
}

impl ScoredStep {
    /// Whether the prediction is more than [`FAR_M`] from the expert's position.
    pub fn is_off(&self) -> bool {
        self.error.position_m > FAR_M
    }

    /// Whether the step is off ([`ScoredStep::is_off`]) and the field scores the expert's
    /// position higher than the prediction (a miss of the coarse-to-fine sampling, not of
    /// the field).
    pub fn missed_by_sampling(&self) -> bool {
        self.is_off() && self.expert_logit > self.predicted_logit
    }
}

/// Position error (m) above which a step counts as off for [`ScoreRow::missed_by_sampling`].
pub const FAR_M: f64 = 0.01;

/// Compares `got` with `want`.
pub fn keyframe_error(got: &Keyframe, want: &Keyframe) -> KeyframeError {
    let g = got.base_from_tcp.isometry();
    let w = want.base_from_tcp.isometry();
    let offset = g.translation.vector - w.translation.vector;
    let flip = Rotation3::from_axis_angle(&Vector3::z_axis(), std::f64::consts::PI);
    let rg = g.rotation.to_rotation_matrix();
    let rw = w.rotation.to_rotation_matrix();
    let rotation = rg.angle_to(&rw).min(rg.angle_to(&(rw * flip)));
    KeyframeError {
        position_m: offset.norm(),
        offset_m: offset.into(),
        rotation_deg: rotation.to_degrees(),
        open_agrees: got.gripper_open == want.gripper_open,
    }
}

/// The errors of one group of steps (a task variation, or all of them).
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct ScoreRow {
    /// `task/variation`, or `all`.
    pub name: String,
    /// Steps scored.
    pub steps: usize,
    /// Median position error (m).
    pub position_median_m: f64,
    /// 90th percentile of the position error (m).
    pub position_p90_m: f64,
    /// Share of steps within 1 cm of the expert's position.
    pub within_1cm: f64,
    /// Median rotation error (degrees).
    pub rotation_median_deg: f64,
    /// 90th percentile of the rotation error (degrees).
    pub rotation_p90_deg: f64,
    /// Share of steps whose open state agrees.
    pub open_agrees: f64,
    /// Of the steps more than [`FAR_M`] off, the share whose expert position the field
    /// scores higher than the prediction ([`ScoredStep::missed_by_sampling`]; NaN: none
    /// off). The others are the field's own error, which only training mends.
    pub missed_by_sampling: f64,
}

impl ScoreRow {
    /// Summarises `errors` (none: every statistic NaN).
    pub fn new(name: String, errors: &[KeyframeError]) -> Self {
        let pos: Vec<f64> = errors.iter().map(|e| e.position_m).collect();
        let rot: Vec<f64> = errors.iter().map(|e| e.rotation_deg).collect();
        let share = |f: &dyn Fn(&KeyframeError) -> bool| {
            if errors.is_empty() {
                f64::NAN
            } else {
                errors.iter().filter(|e| f(e)).count() as f64 / errors.len() as f64
            }
        };
        Self {
            name,
            steps: errors.len(),
            position_median_m: quantile(&pos, 0.5),
            position_p90_m: quantile(&pos, 0.9),
            within_1cm: share(&|e| e.position_m <= 0.01),
            rotation_median_deg: quantile(&rot, 0.5),
            rotation_p90_deg: quantile(&rot, 0.9),
            open_agrees: share(&|e| e.open_agrees),
            missed_by_sampling: f64::NAN,
        }
    }

    /// The row of `steps`, with [`ScoreRow::missed_by_sampling`].
    pub fn of_steps(name: String, steps: &[&ScoredStep]) -> Self {
        let errors: Vec<KeyframeError> = steps.iter().map(|s| s.error).collect();
        let far = steps.iter().filter(|s| s.is_off()).count();
        let missed = steps.iter().filter(|s| s.missed_by_sampling()).count();
        Self {
            missed_by_sampling: if far == 0 {
                f64::NAN
            } else {
                missed as f64 / far as f64
            },
            ..Self::new(name, &errors)
        }
    }
}

/// The `q` quantile of `v` (nearest rank; NaN for none).
pub fn quantile(v: &[f64], q: f64) -> f64 {
    if v.is_empty() {
        return f64::NAN;
    }
    let mut s = v.to_vec();
    s.sort_by(f64::total_cmp);
    let rank = ((q * s.len() as f64).ceil() as usize).clamp(1, s.len());
    s[rank - 1]
}

/// Every step's error and the summaries per variation and overall.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct ScoreTable {
    /// One row per task variation (sorted by name), then `all`.
    pub rows: Vec<ScoreRow>,
    /// One row per task variation and step index (`pick_fruit/plum step 2`), in that order:
    /// which keyframe of a task is imprecise, and whether sampling or the field is to blame
    /// there (a whole-variation row averages the place above the spindle with the grasps).
    pub by_step: Vec<ScoreRow>,
    /// Every step, in the order scored.
    pub steps: Vec<ScoredStep>,
}

impl ScoreTable {
    /// The table of `steps`: rows per variation and `all`, and rows per variation and step.
    pub fn of_steps(steps: Vec<ScoredStep>) -> Self {
        let mut variations: BTreeMap<&str, Vec<&ScoredStep>> = BTreeMap::new();
        let mut by_index: BTreeMap<(&str, usize), Vec<&ScoredStep>> = BTreeMap::new();
        for s in &steps {
            variations.entry(&s.variation).or_default().push(s);
            by_index.entry((&s.variation, s.step)).or_default().push(s);
        }
        let mut rows: Vec<ScoreRow> = variations
            .iter()
            .map(|(n, v)| ScoreRow::of_steps(n.to_string(), v))
            .collect();
        rows.push(ScoreRow::of_steps(
            "all".into(),
            &steps.iter().collect::<Vec<_>>(),
        ));
        let by_step = by_index
            .iter()
            .map(|((n, i), v)| ScoreRow::of_steps(format!("{n} step {i}"), v))
            .collect();
        Self {
            rows,
            by_step,
            steps,
        }
    }

    /// Median CPU seconds of one prediction (NaN for none).
    pub fn prediction_cpu_median_s(&self) -> f64 {
        let t: Vec<f64> = self.steps.iter().map(|s| s.prediction_cpu_s).collect();
        quantile(&t, 0.5)
    }

    /// The rows as a Markdown table, then the rows per step as a second one (when any).
    pub fn markdown(&self) -> String {
        let mut s = markdown_rows("variation", &self.rows);
        if !self.by_step.is_empty() {
            s.push('\n');
            s.push_str(&markdown_rows("variation, step", &self.by_step));
        }
        s
    }
}

/// `rows` as a Markdown table whose first column is headed `first`.
fn markdown_rows(first: &str, rows: &[ScoreRow]) -> String {
    let mut s = format!(
        "| {first} | steps | position median / p90 (mm) | within 1 cm | rotation median / p90 (deg) | open agrees | off > 1 cm: missed by sampling |\n|---|---|---|---|---|---|---|\n",
    );
    for r in rows {
        s.push_str(&format!(
            "| {} | {} | {:.1} / {:.1} | {:.0} % | {:.1} / {:.1} | {:.0} % | {} |\n",
            r.name,
            r.steps,
            r.position_median_m * 1e3,
            r.position_p90_m * 1e3,
            r.within_1cm * 100.0,
            r.rotation_median_deg,
            r.rotation_p90_deg,
            r.open_agrees * 100.0,
            if r.missed_by_sampling.is_nan() {
                "none off".to_string()
            } else {
                format!("{:.0} %", r.missed_by_sampling * 100.0)
            }
        ));
    }
    s
}

/// For a step more than [`FAR_M`] off, which of sampling and field is to blame, with the
/// translation logits that say so; empty otherwise.
fn why_off(step: &ScoredStep) -> String {
    if !step.is_off() {
        return String::new();
    }
    let (expert, predicted) = (step.expert_logit, step.predicted_logit);
    if step.missed_by_sampling() {
        format!("; sampling missed the expert's position (logit {expert:.2} > {predicted:.2})")
    } else {
        format!("; the field prefers the prediction (logit {predicted:.2} ≥ {expert:.2} at the expert's)")
    }
}

/// Predicts every sample's keyframe with `policy` (prediction `i` seeded `seed + i`, so a
/// score is reproducible) and compares it with the sample's expert keyframe; `progress`
/// hears one line per step.
pub fn score(
    policy: &mut Policy,
    samples: &[DemoSample],
    seed: u64,
    progress: &mut dyn FnMut(&str),
) -> anyhow::Result<ScoreTable> {
    let mut steps = Vec::with_capacity(samples.len());
    for (i, demo) in samples.iter().enumerate() {
        let (variation, sample) = (demo.kind.name(), &demo.sample);
        policy.seed = seed.wrapping_add(i as u64);
        let got = policy
            .predict_detailed(&sample.cloud, &sample.gripper, &sample.instruction)
            .with_context(|| {
                format!(
                    "predicting {variation} seed {} step {}",
                    demo.seed, demo.step
                )
            })?;
        let e = keyframe_error(&got.keyframe, &sample.target);
        let expert_position = Point3::from(sample.target.base_from_tcp.translation());
        let expert_logit = policy
            .translation_logits(&got.scene, &[expert_position])
            .with_context(|| {
                format!(
                    "scoring the expert's position of {variation} seed {} step {}",
                    demo.seed, demo.step
                )
            })?[0];
        let step = ScoredStep {
            variation,
            seed: demo.seed,
            step: demo.step,
            error: e,
            prediction_cpu_s: got.timings.total,
            predicted_logit: got.translation_logit,
            expert_logit,
        };
        progress(&format!(
            "[{}/{}] {} seed {} step {}: {:.1} mm, {:.1} deg, open {}{}",
            i + 1,
            samples.len(),
            step.variation,
            demo.seed,
            demo.step,
            e.position_m * 1e3,
            e.rotation_deg,
            if e.open_agrees { "agrees" } else { "differs" },
            why_off(&step)
        ));
        steps.push(step);
    }
    Ok(ScoreTable::of_steps(steps))
}

#[cfg(test)]
mod tests {
    #![allow(clippy::unwrap_used)]

    use super::*;
    use cell_types::{Base, Tcp, Transform};
    use nalgebra::{Isometry3, Translation3, UnitQuaternion};

    fn kf(x: f64, yaw: f64, roll: f64, open: bool) -> Keyframe {
        let iso = Isometry3::from_parts(
            Translation3::new(x, 0.1, 0.2),
            UnitQuaternion::from_euler_angles(roll, 0.0, 0.0)
                * UnitQuaternion::from_axis_angle(&Vector3::z_axis(), yaw),
        );
        Keyframe::new(Transform::<Base, Tcp>::from_isometry(iso), open, false).unwrap()
    }

    #[test]
    fn errors_measure_distance_angle_and_the_finger_symmetry() {
        let want = kf(0.5, 0.0, 0.0, true);
        let e = keyframe_error(&kf(0.53, 0.0, 0.0, true), &want);
        assert!((e.position_m - 0.03).abs() < 1e-12 && e.rotation_deg < 1e-9 && e.open_agrees);
        // The offset is predicted minus expert, in the base frame.
        assert!((e.offset_m[0] - 0.03).abs() < 1e-12 && e.offset_m[1..] == [0.0, 0.0]);
        // 20 degrees about the approach axis is 20 degrees; 180 is none (the fingers swap).
        let e = keyframe_error(&kf(0.5, 20f64.to_radians(), 0.0, false), &want);
        assert!((e.rotation_deg - 20.0).abs() < 1e-9 && !e.open_agrees);
        let e = keyframe_error(&kf(0.5, std::f64::consts::PI, 0.0, true), &want);
        assert!(e.rotation_deg < 1e-6, "{e:?}");
        // A tilt of the approach axis has no such symmetry.
        let e = keyframe_error(&kf(0.5, 0.0, 30f64.to_radians(), true), &want);
        assert!((e.rotation_deg - 30.0).abs() < 1e-9, "{e:?}");
    }

    #[test]
    fn a_far_step_is_a_sampling_miss_only_when_the_field_prefers_the_expert() {
        let step = |position_m: f64, predicted_logit: f32, expert_logit: f32| ScoredStep {
            variation: "pick_fruit/plum".into(),
            seed: 1,
            step: 0,
            error: KeyframeError {
                position_m,
                offset_m: [position_m, 0.0, 0.0],
                rotation_deg: 0.0,
                open_agrees: true,
            },
            prediction_cpu_s: 0.5,
            predicted_logit,
            expert_logit,
        };
        let missed = step(0.12, 50.0, 55.0);
        let field_wrong = step(0.12, 55.0, 50.0);
        let close = step(0.005, 50.0, 55.0);
        assert!(missed.missed_by_sampling());
        assert!(!field_wrong.missed_by_sampling());
        assert!(!close.missed_by_sampling(), "within 1 cm is not off");
        // Each off step's progress line says which one to blame.
        assert!(
            why_off(&missed).contains("sampling missed"),
            "{}",
            why_off(&missed)
        );
        assert!(why_off(&field_wrong).contains("field prefers the prediction"));
        assert_eq!(why_off(&close), "");
        let r = ScoreRow::of_steps("x".into(), &[&missed, &field_wrong, &close]);
        assert_eq!(r.steps, 3);
        assert!((r.missed_by_sampling - 0.5).abs() < 1e-12, "{r:?}");
        let none_off = ScoreRow::of_steps("y".into(), &[&close]);
        assert!(none_off.missed_by_sampling.is_nan());
        let table = ScoreTable {
            rows: vec![r, none_off],
            by_step: vec![],
            steps: vec![],
        };
        let md = table.markdown();
        assert!(
            md.contains("| 50 % |") && md.contains("| none off |"),
            "{md}"
        );
    }

    #[test]
    fn steps_are_summarised_per_variation_and_per_step() {
        let step = |variation: &str, index: usize, position_m: f64| ScoredStep {
            variation: variation.into(),
            seed: 7,
            step: index,
            error: KeyframeError {
                position_m,
                offset_m: [position_m, 0.0, 0.0],
                rotation_deg: 1.0,
                open_agrees: true,
            },
            prediction_cpu_s: 0.5,
            predicted_logit: 50.0,
            // Far steps here are sampling misses: the field prefers the expert's position.
            expert_logit: 55.0,
        };
        let steps = vec![
            step("pick_fruit/plum", 1, 0.002),
            step("install_toilet_roll/small", 3, 0.020),
            step("pick_fruit/plum", 0, 0.004),
            step("install_toilet_roll/small", 3, 0.030),
            step("install_toilet_roll/small", 0, 0.006),
        ];
        let t = ScoreTable::of_steps(steps.clone());
        assert_eq!(t.steps, steps, "every step is kept in the order scored");
        let names: Vec<&str> = t.rows.iter().map(|r| r.name.as_str()).collect();
        assert_eq!(
            names,
            ["install_toilet_roll/small", "pick_fruit/plum", "all"]
        );
        assert_eq!(
            t.rows.iter().map(|r| r.steps).collect::<Vec<_>>(),
            [3, 2, 5]
        );
        let names: Vec<&str> = t.by_step.iter().map(|r| r.name.as_str()).collect();
        assert_eq!(
            names,
            [
                "install_toilet_roll/small step 0",
                "install_toilet_roll/small step 3",
                "pick_fruit/plum step 0",
                "pick_fruit/plum step 1"
            ]
        );
        let third = &t.by_step[1];
        assert_eq!(third.steps, 2);
        assert!((third.position_median_m - 0.020).abs() < 1e-12, "{third:?}");
        assert!((third.missed_by_sampling - 1.0).abs() < 1e-12, "{third:?}");
        assert!(t.by_step[0].missed_by_sampling.is_nan(), "none off");
        let md = t.markdown();
        assert!(md.contains("| variation, step |"), "{md}");
        assert!(
            md.contains("| install_toilet_roll/small step 3 | 2 | 20.0 / 30.0 | 0 % |"),
            "{md}"
        );
    }

    #[test]
    fn rows_summarise_by_nearest_rank() {
        let errors: Vec<KeyframeError> = (1..=10)
            .map(|i| KeyframeError {
                position_m: f64::from(i) * 0.002,
                offset_m: [0.0, 0.0, f64::from(i) * 0.002],
                rotation_deg: f64::from(i),
                open_agrees: i != 3,
            })
            .collect();
        let r = ScoreRow::new("x".into(), &errors);
        assert_eq!(r.steps, 10);
        assert!((r.position_median_m - 0.010).abs() < 1e-12);
        assert!((r.position_p90_m - 0.018).abs() < 1e-12);
        assert!((r.within_1cm - 0.5).abs() < 1e-12);
        assert_eq!((r.rotation_median_deg, r.rotation_p90_deg), (5.0, 9.0));
        assert!((r.open_agrees - 0.9).abs() < 1e-12);
        let empty = ScoreRow::new("none".into(), &[]);
        assert!(empty.position_median_m.is_nan() && empty.open_agrees.is_nan());
    }
}
