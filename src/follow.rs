//! Does a keyframe predicted while the gripper holds an object read the scene, or move with
//! the held object? (`equact policy follow`)
//!
//! Closed loop, the roll's release is let go a median 10-18 mm off the spindle's axis while
//! the same model releases 4-5 mm off from the expert's own state (README, toilet roll). One
//! explanation is compounding: if the release is placed relative to where the gripper and
//! the roll already are rather than relative to the spindle, every earlier step's error is
//! carried into it. This probe measures that directly: for every recorded step whose
//! observation has the gripper closed, the gripper and the cloud points within
//! [`HELD_RADIUS_M`] of its TCP (the held object: the fusion removes the gripper itself) are
//! moved sideways by a few millimetres, the rest of the scene stays, and the keyframe is
//! predicted again with the same seed. The share of the motion the keyframe follows, β =
//! (p′ − p)·δ / |δ|², is 0 for a keyframe placed by the scene (where a release must go, over
//! the spindle) and 1 for one placed relative to the hand.

use anyhow::Context;
use nalgebra::Vector3;
use policy::predict::Policy;
use policy::trainer::TrainSample;
use policy::training::HELD_RADIUS_M;
use serde::Serialize;

use crate::score::quantile;
use crate::train::DemoSample;

/// The default sideways motion (m) of the gripper and the held object.
pub const DEFAULT_SHIFT_M: f64 = 0.01;

/// The four sideways directions of the motion (base frame: ±x, ±y).
const DIRECTIONS: [[f64; 3]; 4] = [
    [1.0, 0.0, 0.0],
    [-1.0, 0.0, 0.0],
    [0.0, 1.0, 0.0],
    [0.0, -1.0, 0.0],
];

/// `sample` with its gripper and the cloud points within [`HELD_RADIUS_M`] of the TCP moved
/// by `shift` (base frame, m; [`policy::training::shift_held`], as the training's
/// held-object shift moves them), and how many points moved.
pub fn shift_held(sample: &TrainSample, shift: Vector3<f64>) -> (TrainSample, usize) {
    let mut out = sample.clone();
    let moved = policy::training::shift_held(&mut out.cloud, &mut out.gripper, shift);
    (out, moved)
}

/// The share of the motion `shift` that a prediction moved from `before` to `after`
/// follows: 1 when it moved with it, 0 when it stayed (NaN for no motion).
pub fn followed_share(before: &Vector3<f64>, after: &Vector3<f64>, shift: &Vector3<f64>) -> f64 {
    (after - before).dot(shift) / shift.norm_squared()
}

/// One recorded step moved in each direction.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct FollowedStep {
    /// `task/variation`.
    pub variation: String,
    /// The demonstration's seed.
    pub seed: u64,
    /// The step's index in its demonstration.
    pub step: usize,
    /// Cloud points moved with the gripper (the held object's).
    pub held_points: usize,
    /// The share of the motion followed, per direction (+x, −x, +y, −y).
    pub followed: [f64; 4],
}

impl FollowedStep {
    /// The mean of the four directions' shares.
    pub fn mean(&self) -> f64 {
        self.followed.iter().sum::<f64>() / 4.0
    }
}

/// The steps of one variation and step index.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct FollowRow {
    /// `task/variation step N`.
    pub name: String,
    /// Steps moved.
    pub steps: usize,
    /// Median over the steps of their mean share followed.
    pub followed_median: f64,
    /// Lower quartile of the same.
    pub followed_p25: f64,
    /// Upper quartile of the same.
    pub followed_p75: f64,
}

/// What `equact policy follow` reports.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct FollowTable {
    /// The sideways motion (m).
    pub shift_m: f64,
    /// One row per variation and step index with the gripper closed, in that order.
    pub rows: Vec<FollowRow>,
    /// Every step moved.
    pub steps: Vec<FollowedStep>,
    /// Closed-gripper steps skipped because no cloud point lay near the TCP.
    pub without_held_points: usize,
}

impl FollowTable {
    /// The rows as a Markdown table.
    pub fn markdown(&self) -> String {
        let mut s = format!(
            "Gripper and held object moved {:.0} mm sideways (±x, ±y), the scene kept: the \
             share of the motion each keyframe follows (0: placed by the scene, 1: moves with \
             the hand).\n\n| step | steps | followed: median | quartiles |\n|---|---|---|---|\n",
            self.shift_m * 1e3
        );
        for r in &self.rows {
            s.push_str(&format!(
                "| {} | {} | {:.2} | {:.2}-{:.2} |\n",
                r.name, r.steps, r.followed_median, r.followed_p25, r.followed_p75
            ));
        }
        if self.without_held_points > 0 {
            s.push_str(&format!(
                "\n{} closed-gripper step(s) had no cloud point within {:.0} mm of the TCP and \
                 were skipped.\n",
                self.without_held_points,
                HELD_RADIUS_M * 1e3
            ));
        }
        s
    }
}

/// Moves every closed-gripper step of `samples` by `shift_m` in four sideways directions
/// and predicts it again (each step's five predictions seeded alike, `seed + i` for the
/// i-th step moved, so a run is reproducible); `progress` hears one line per step.
pub fn follow(
    policy: &mut Policy,
    samples: &[DemoSample],
    shift_m: f64,
    seed: u64,
    progress: &mut dyn FnMut(&str),
) -> anyhow::Result<FollowTable> {
    if !(shift_m.is_finite() && shift_m > 0.0) {
        anyhow::bail!("the motion must be a positive distance, got {shift_m} m");
    }
    let held: Vec<&DemoSample> = samples.iter().filter(|d| !d.sample.gripper.open).collect();
    if held.is_empty() {
        anyhow::bail!(
            "no recorded step has the gripper closed (nothing held to move); record whole \
             episodes with `equact demos collect`"
        );
    }
    let mut steps = Vec::new();
    let mut without_held_points = 0;
    for (i, demo) in held.iter().enumerate() {
        let what = || format!("{} seed {} step {}", demo.kind.name(), demo.seed, demo.step);
        let s = &demo.sample;
        policy.seed = seed.wrapping_add(i as u64);
        let predict = |policy: &mut Policy, sample: &TrainSample| {
            policy
                .predict(&sample.cloud, &sample.gripper, &sample.instruction)
                .map(|k| k.base_from_tcp.translation())
        };
        let before = predict(policy, s).with_context(|| format!("predicting {}", what()))?;
        let mut followed = [0.0; 4];
        let mut held_points = 0;
        for (f, d) in followed.iter_mut().zip(DIRECTIONS) {
            let shift = Vector3::from(d) * shift_m;
            let (moved, n) = shift_held(s, shift);
            held_points = n;
            if n == 0 {
                break;
            }
            let after = predict(policy, &moved)
                .with_context(|| format!("predicting {} moved by {shift:?}", what()))?;
            *f = followed_share(&before, &after, &shift);
        }
        if held_points == 0 {
            without_held_points += 1;
            continue;
        }
        let step = FollowedStep {
            variation: demo.kind.name(),
            seed: demo.seed,
            step: demo.step,
            held_points,
            followed,
        };
        progress(&format!(
            "[{}/{}] {}: {} held points, followed {:.2} (±x {:.2} {:.2}, ±y {:.2} {:.2})",
            i + 1,
            held.len(),
            what(),
            held_points,
            step.mean(),
            followed[0],
            followed[1],
            followed[2],
            followed[3]
        ));
        steps.push(step);
    }
    let mut keys: Vec<(String, usize)> = steps
        .iter()
        .map(|s| (s.variation.clone(), s.step))
        .collect();
    keys.sort();
    keys.dedup();
    let rows = keys
        .into_iter()
        .map(|(variation, step)| {
            let means: Vec<f64> = steps
                .iter()
                .filter(|s| s.variation == variation && s.step == step)
                .map(FollowedStep::mean)
                .collect();
            FollowRow {
                name: format!("{variation} step {step}"),
                steps: means.len(),
                followed_median: quantile(&means, 0.5),
                followed_p25: quantile(&means, 0.25),
                followed_p75: quantile(&means, 0.75),
            }
        })
        .collect();
    Ok(FollowTable {
        shift_m,
        rows,
        steps,
        without_held_points,
    })
}

#[cfg(test)]
mod tests {
    #![allow(clippy::unwrap_used)]

    use super::*;
    use crate::task::TaskKind;
    use cell_types::Transform;
    use nalgebra::{Point3, UnitQuaternion};

    const TABLE: f64 = -0.06;

    /// A toilet-roll step with the stand-in table points and, unless `bare`, a small held
    /// object under the TCP at (0.45, 0, 0.2); the gripper closed unless `open`.
    fn demo(step: usize, open: bool, bare: bool) -> DemoSample {
        let kind = TaskKind::parse("install_toilet_roll/large").unwrap();
        let mut d = crate::train::stand_in_demo(kind, 3, step, TABLE);
        if !bare {
            let held = (0..30).map(|i| Point3::new(0.45 + 0.002 * i as f32, 0.0, 0.17));
            d.sample.cloud.points.extend(held);
            d.sample.cloud.rgb = Some(vec![[120, 120, 120]; d.sample.cloud.points.len()]);
        }
        d.sample.gripper = policy::predict::GripperPose {
            base_from_tcp: Transform::from_parts(
                Vector3::new(0.45, 0.0, 0.2),
                UnitQuaternion::identity(),
            ),
            open,
        };
        d
    }

    #[test]
    fn only_the_gripper_and_the_points_near_it_move() {
        let d = demo(4, false, false);
        let shift = Vector3::new(0.0, 0.01, 0.0);
        let (moved, n) = shift_held(&d.sample, shift);
        assert_eq!(n, 30, "the held object's points, not the table's");
        for (a, b) in d.sample.cloud.points.iter().zip(&moved.cloud.points) {
            let near =
                (a.coords.cast::<f64>() - Vector3::new(0.45, 0.0, 0.2)).norm() <= HELD_RADIUS_M;
            let want = if near { a + shift.cast::<f32>() } else { *a };
            assert_eq!(*b, want);
        }
        let tcp = moved.gripper.base_from_tcp;
        assert!((tcp.translation() - Vector3::new(0.45, 0.01, 0.2)).norm() < 1e-12);
        assert_eq!(tcp.rotation(), d.sample.gripper.base_from_tcp.rotation());
        assert_eq!(moved.target, d.sample.target, "the label is not moved");
    }

    #[test]
    fn the_share_followed_is_the_motion_projected() {
        let (p, shift) = (Vector3::new(0.3, 0.1, 0.2), Vector3::new(0.01, 0.0, 0.0));
        assert!((followed_share(&p, &(p + shift), &shift) - 1.0).abs() < 1e-12);
        assert!(followed_share(&p, &p, &shift).abs() < 1e-12);
        let half_and_aside = p + shift * 0.5 + Vector3::new(0.0, 0.02, 0.0);
        assert!((followed_share(&p, &half_and_aside, &shift) - 0.5).abs() < 1e-12);
        assert!((followed_share(&p, &(p - shift), &shift) + 1.0).abs() < 1e-12);
    }

    #[test]
    fn closed_gripper_steps_are_moved_and_tabulated() {
        let cfg = cell_types::config::CellConfig::simulated().unwrap();
        let mut net = crate::learned::for_cell(policy::predict::PolicyConfig::tiny(), &cfg);
        net.extra.token_dim = policy::minilm::HIDDEN;
        let mut policy = Policy::random(net, 1).unwrap();
        let samples = vec![
            demo(0, true, false),
            demo(3, false, false),
            demo(4, false, false),
            demo(4, false, true),
        ];
        let mut lines = Vec::new();
        let t = follow(&mut policy, &samples, 0.01, 0, &mut |l| {
            lines.push(l.to_string())
        })
        .unwrap();
        // The open step is not asked; the bare one has nothing held.
        assert_eq!(t.steps.len(), 2, "{:?}", t.steps);
        assert_eq!(lines.len(), 2);
        assert_eq!(t.without_held_points, 1);
        assert!(t.steps.iter().all(|s| s.held_points == 30));
        assert!(t
            .steps
            .iter()
            .all(|s| s.followed.iter().all(|f| f.is_finite())));
        let names: Vec<&str> = t.rows.iter().map(|r| r.name.as_str()).collect();
        assert_eq!(
            names,
            [
                "install_toilet_roll/large step 3",
                "install_toilet_roll/large step 4"
            ]
        );
        assert!((t.rows[1].followed_median - t.steps[1].mean()).abs() < 1e-12);
        assert!(t
            .markdown()
            .contains("| install_toilet_roll/large step 4 | 1 |"));
        assert!(t.markdown().contains("skipped"));

        let err = follow(&mut policy, &samples[..1], 0.01, 0, &mut |_| {})
            .unwrap_err()
            .to_string();
        assert!(err.contains("gripper closed"), "{err}");
        let err = follow(&mut policy, &samples, 0.0, 0, &mut |_| {})
            .unwrap_err()
            .to_string();
        assert!(err.contains("positive distance"), "{err}");
    }
}
