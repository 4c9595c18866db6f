//! Does the instruction reach the keyframe? (`equact policy ground`)
//!
//! A pipe or flower scene drawn with one seed is the same under each of its task's
//! variations; only the instruction says which link or flower to take. So every recorded
//! scene is an exact counterfactual: the network sees the same observation once per
//! instruction, and its first keyframe (the approach above the part to grasp) should land
//! nearest the scripted expert's first keyframe for *that* instruction. `policy score`
//! cannot show this, as it only asks each demonstration's own instruction: a model that
//! always takes the first link scores well on a third of the pipe's scenes.
//!
//! Scenes whose task draws a different scene per variation (the fruit and the roll differ
//! in size or colour), or whose variations share one first keyframe, hold no counterfactual
//! and are skipped.

use std::collections::BTreeSet;

use anyhow::Context;
use nalgebra::Vector3;
use policy::predict::Policy;
use serde::Serialize;

use crate::task::{TaskInstance, TaskKind};
use crate::train::{DemoSample, Instructions};

/// Two variations' first keyframes closer than this (m) are one target: the instruction
/// need not tell them apart (the pipe's "all" starts where "first link" does).
pub const SAME_TARGET_M: f64 = 0.03;

/// Predictions under two instructions closer than this (m) count as the same keyframe.
pub const SAME_PREDICTION_M: f64 = 0.01;

/// A scene's variations with their expert first keyframes' positions (base frame, m).
pub type Targets = Vec<(TaskKind, Vector3<f64>)>;

/// One scene's predictions: (predicted position, its instruction's target), per instruction.
type Made = Vec<(Vector3<f64>, Vector3<f64>)>;

/// One prediction: a scene under one of its task's instructions.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct GroundedPrediction {
    /// The instruction's `task/variation`.
    pub variation: String,
    /// The scene's seed.
    pub seed: u64,
    /// Distance from the prediction to this instruction's expert first keyframe (m).
    pub own_target_m: f64,
    /// Distance to the nearest expert first keyframe of the scene's other instructions
    /// with a different target (m).
    pub other_target_m: f64,
    /// The predicted TCP position (base frame, m).
    pub position: [f64; 3],
}

impl GroundedPrediction {
    /// Whether the prediction lies nearer its own instruction's target than any other.
    pub fn grounded(&self) -> bool {
        self.own_target_m < self.other_target_m
    }
}

/// The summary of one task's counterfactual scenes.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct GroundingRow {
    /// The task, or `all`.
    pub task: String,
    /// Scenes probed.
    pub scenes: usize,
    /// Predictions made (scenes × instructions with a target of their own).
    pub predictions: usize,
    /// Share of predictions nearest their own instruction's target.
    pub grounded: f64,
    /// Median distance to the own target (m).
    pub own_target_median_m: f64,
    /// Share of instruction pairs with different targets whose predictions are the same
    /// keyframe ([`SAME_PREDICTION_M`]): the instruction was not heard.
    pub ignored_pairs: f64,
}

/// Every prediction and the rows per task (sorted by name), then `all`.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct GroundingTable {
    /// One row per task with counterfactual scenes, then `all`.
    pub rows: Vec<GroundingRow>,
    /// Every prediction, in the order made.
    pub predictions: Vec<GroundedPrediction>,
    /// Tasks whose scenes hold no counterfactual (skipped).
    pub skipped_tasks: Vec<String>,
}

impl GroundingTable {
    /// The rows as a Markdown table.
    pub fn markdown(&self) -> String {
        let mut s = String::from(
            "| task | scenes | predictions | nearest own target | own target median (mm) | instruction pairs ignored |\n|---|---|---|---|---|---|\n",
        );
        for r in &self.rows {
            s.push_str(&format!(
                "| {} | {} | {} | {:.0} % | {:.1} | {:.0} % |\n",
                r.task,
                r.scenes,
                r.predictions,
                r.grounded * 100.0,
                r.own_target_median_m * 1e3,
                r.ignored_pairs * 100.0
            ));
        }
        if !self.skipped_tasks.is_empty() {
            s.push_str(&format!(
                "\nno counterfactual scenes (the scene differs by variation, or one target): {}\n",
                self.skipped_tasks.join(", ")
            ));
        }
        s
    }
}

/// The variations of a scene's task that draw the same scene with `seed` and their expert
/// first keyframes' positions; `None` when fewer than two distinct targets remain.
pub fn counterfactuals(kind: TaskKind, seed: u64, table_height: f64) -> Option<Targets> {
    let variations = TaskKind::variations_of(kind.task_name())?;
    let targets: Targets = variations
        .into_iter()
        .filter(|&k| draws_same_scene(kind, k, seed, table_height))
        .filter_map(|k| {
            let scene = TaskInstance::sample(k, seed, table_height);
            let first = scene.expert_keyframes().into_iter().next()?;
            Some((k, first.base_from_tcp.translation()))
        })
        .collect();
    let distinct = targets
        .iter()
        .any(|(_, a)| targets.iter().any(|(_, b)| (a - b).norm() > SAME_TARGET_M));
    distinct.then_some(targets)
}

/// Whether variations `a` and `b` draw the same bodies in the same places from `seed`.
pub fn draws_same_scene(a: TaskKind, b: TaskKind, seed: u64, table_height: f64) -> bool {
    let (a, b) = (
        TaskInstance::sample(a, seed, table_height),
        TaskInstance::sample(b, seed, table_height),
    );
    a.bodies.len() == b.bodies.len()
        && a.bodies.iter().zip(&b.bodies).all(|(x, y)| {
            x.base_from_body == y.base_from_body && x.parts == y.parts && x.grasp == y.grasp
        })
}

/// For each sample, its [`scene_siblings`](crate::train::scene_siblings) whose keyframe goes
/// elsewhere (more than [`SAME_TARGET_M`] from its own), or all of them where none does:
/// the partners of `equact train --paired`. A pair whose two instructions go to one place
/// teaches nothing about the instruction, and on the pipe's first step ("first link" and
/// "all" both start at the first link) narrowing also evens the two targets out: every
/// pair holds both, where uniform partners put the first link in two samples of three.
pub fn contrasting_siblings(samples: &[DemoSample]) -> Vec<Vec<usize>> {
    crate::train::scene_siblings(samples)
        .into_iter()
        .enumerate()
        .map(|(i, sib)| {
            let elsewhere: Vec<usize> = going_elsewhere(samples, i, &sib).collect();
            if elsewhere.is_empty() {
                sib
            } else {
                elsewhere
            }
        })
        .collect()
}

/// The siblings `sib` of sample `i` whose keyframe is more than [`SAME_TARGET_M`] from its
/// own.
fn going_elsewhere<'a>(
    samples: &'a [DemoSample],
    i: usize,
    sib: &'a [usize],
) -> impl Iterator<Item = usize> + 'a {
    let target = |j: usize| samples[j].sample.target.base_from_tcp.translation();
    let own = target(i);
    sib.iter()
        .copied()
        .filter(move |&j| (target(j) - own).norm() > SAME_TARGET_M)
}

/// Gives each sample, as [`policy::trainer::TrainSample::negatives`], the targets of the same
/// step of the same scene under its task's other instructions (only tasks whose variations
/// draw one scene from a seed; targets more than [`SAME_TARGET_M`] from its own), so that
/// training always shows the field where the instruction must not send it. Returns how
/// many samples got at least one.
pub fn add_sibling_negatives(samples: &mut [DemoSample], table_height: f64) -> usize {
    let siblings = crate::train::scene_siblings(samples);
    let negatives: Vec<Vec<nalgebra::Point3<f64>>> = siblings
        .iter()
        .enumerate()
        .map(|(i, sib)| {
            let own = &samples[i];
            let mut out: Vec<nalgebra::Point3<f64>> = Vec::new();
            for o in going_elsewhere(samples, i, sib).map(|j| &samples[j]) {
                let t = o.sample.target.base_from_tcp.translation();
                // Two instructions going to one place give one negative, not a doubled one.
                if out
                    .iter()
                    .all(|n| (n.coords - t).norm() > SAME_PREDICTION_M)
                    && draws_same_scene(own.kind, o.kind, own.seed, table_height)
                {
                    out.push(t.into());
                }
            }
            out
        })
        .collect();
    let mut with = 0;
    for (s, n) in samples.iter_mut().zip(negatives) {
        with += usize::from(!n.is_empty());
        s.sample.negatives = n;
    }
    with
}

/// The targets of a scene's other variations that are a distinct part from `target`.
fn others(targets: &[(TaskKind, Vector3<f64>)], target: &Vector3<f64>) -> Vec<Vector3<f64>> {
    targets
        .iter()
        .map(|(_, t)| *t)
        .filter(|t| (t - target).norm() > SAME_TARGET_M)
        .collect()
}

/// Predicts the first keyframe of each demonstrated scene (one per task and seed) under each
/// of its task's instructions that has a target of its own, and measures where it lands
/// (prediction `i` seeded `seed + i`); `progress` hears one line per prediction.
pub fn ground(
    policy: &mut Policy,
    samples: &[DemoSample],
    instructions: &Instructions<'_>,
    table_height: f64,
    seed: u64,
    progress: &mut dyn FnMut(&str),
) -> anyhow::Result<GroundingTable> {
    let mut seen = BTreeSet::new();
    let mut scenes: Vec<(&DemoSample, Targets)> = Vec::new();
    let mut probed_tasks = BTreeSet::new();
    let mut all_tasks = BTreeSet::new();
    for s in samples.iter().filter(|s| s.step == 0) {
        all_tasks.insert(s.kind.task_name());
        if !seen.insert((s.kind.task_name(), s.seed)) {
            continue;
        }
        if let Some(targets) = counterfactuals(s.kind, s.seed, table_height) {
            probed_tasks.insert(s.kind.task_name());
            scenes.push((s, targets));
        }
    }
    if scenes.is_empty() {
        anyhow::bail!(
            "the demonstrations hold no counterfactual scene (a pipe or flower episode's first \
             step); record some with `equact demos collect --task disassemble_pipe` or \
             `--task pluck_flower`"
        );
    }
    let total: usize = scenes
        .iter()
        .map(|(_, t)| t.iter().filter(|(_, x)| !others(t, x).is_empty()).count())
        .sum();
    let mut predictions = Vec::with_capacity(total);
    let mut embeddings = std::collections::HashMap::new();
    // Per scene, the predictions' positions and targets, for the ignored pairs.
    let mut per_scene: Vec<(&'static str, Made)> = Vec::new();
    for (demo, targets) in &scenes {
        let mut made = Vec::new();
        for (kind, target) in targets {
            let others = others(targets, target);
            if others.is_empty() {
                continue;
            }
            // Embedded once per variation: a MiniLM source loads its model per call.
            if !embeddings.contains_key(kind) {
                embeddings.insert(*kind, instructions.embedding(*kind)?);
            }
            let instruction = &embeddings[kind];
            policy.seed = seed.wrapping_add(predictions.len() as u64);
            let got = policy
                .predict_detailed(&demo.sample.cloud, &demo.sample.gripper, instruction)
                .with_context(|| {
                    format!(
                        "predicting the {} scene of seed {} under `{}`",
                        demo.kind.task_name(),
                        demo.seed,
                        kind.instruction()
                    )
                })?;
            let p = got.keyframe.base_from_tcp.translation();
            let prediction = GroundedPrediction {
                variation: kind.name(),
                seed: demo.seed,
                own_target_m: (p - target).norm(),
                other_target_m: others
                    .iter()
                    .map(|t| (p - t).norm())
                    .fold(f64::INFINITY, f64::min),
                position: [p.x, p.y, p.z],
            };
            progress(&format!(
                "[{}/{total}] seed {} `{}`: {:.1} mm from its target, {:.1} mm from the nearest other ({})",
                predictions.len() + 1,
                demo.seed,
                kind.instruction(),
                prediction.own_target_m * 1e3,
                prediction.other_target_m * 1e3,
                if prediction.grounded() { "grounded" } else { "wrong part" }
            ));
            predictions.push(prediction);
            made.push((p, *target));
        }
        per_scene.push((demo.kind.task_name(), made));
    }
    let row = |task: Option<&str>| {
        let mine: Vec<&GroundedPrediction> = predictions
            .iter()
            .filter(|p| task.is_none_or(|t| crate::eval::task_name(&p.variation) == t))
            .collect();
        let pairs: Vec<bool> = per_scene
            .iter()
            .filter(|(t, _)| task.is_none_or(|x| *t == x))
            .flat_map(|(_, made)| {
                made.iter().enumerate().flat_map(move |(i, a)| {
                    made[i + 1..]
                        .iter()
                        .filter(move |b| (a.1 - b.1).norm() > SAME_TARGET_M)
                        .map(move |b| (a.0 - b.0).norm() <= SAME_PREDICTION_M)
                })
            })
            .collect();
        let share = |n: usize, of: usize| {
            if of == 0 {
                f64::NAN
            } else {
                n as f64 / of as f64
            }
        };
        let own: Vec<f64> = mine.iter().map(|p| p.own_target_m).collect();
        GroundingRow {
            task: task.unwrap_or("all").to_string(),
            scenes: per_scene
                .iter()
                .filter(|(t, _)| task.is_none_or(|x| *t == x))
                .count(),
            predictions: mine.len(),
            grounded: share(mine.iter().filter(|p| p.grounded()).count(), mine.len()),
            own_target_median_m: crate::score::quantile(&own, 0.5),
            ignored_pairs: share(pairs.iter().filter(|&&b| b).count(), pairs.len()),
        }
    };
    let mut rows: Vec<GroundingRow> = probed_tasks.iter().map(|t| row(Some(t))).collect();
    rows.push(row(None));
    Ok(GroundingTable {
        rows,
        predictions,
        skipped_tasks: all_tasks
            .difference(&probed_tasks)
            .map(|t| t.to_string())
            .collect(),
    })
}

#[cfg(test)]
mod tests {
    #![allow(clippy::unwrap_used)]

    use super::*;

    const TABLE: f64 = -0.06;

    #[test]
    fn pipe_and_flower_scenes_are_counterfactuals_and_the_others_are_not() {
        for seed in [0, 7, 1_000_000] {
            for kind in TaskKind::all() {
                let c = counterfactuals(kind, seed, TABLE);
                match kind.task_name() {
                    "disassemble_pipe" | "pluck_flower" => {
                        let c = c.unwrap_or_else(|| panic!("{} seed {seed}", kind.name()));
                        assert_eq!(c.len(), 3, "every variation draws the same scene");
                        assert!(c.iter().any(|(k, _)| *k == kind));
                    }
                    _ => assert!(c.is_none(), "{} seed {seed}", kind.name()),
                }
            }
        }
    }

    #[test]
    fn the_pipes_all_starts_at_the_first_link_and_the_flowers_differ() {
        let c =
            counterfactuals(TaskKind::parse("disassemble_pipe/all").unwrap(), 3, TABLE).unwrap();
        let at = |name: &str| c.iter().find(|(k, _)| k.name() == name).unwrap().1;
        let first = at("disassemble_pipe/first_link");
        assert!((at("disassemble_pipe/all") - first).norm() <= SAME_TARGET_M);
        assert!((at("disassemble_pipe/second_link") - first).norm() > SAME_TARGET_M);
        let f = counterfactuals(TaskKind::parse("pluck_flower/top").unwrap(), 3, TABLE).unwrap();
        for (i, (_, a)) in f.iter().enumerate() {
            for (_, b) in &f[i + 1..] {
                assert!((a - b).norm() > SAME_TARGET_M, "{a} {b}");
            }
        }
    }

    #[test]
    fn sibling_negatives_are_the_same_scenes_other_targets() {
        let kind = |n: &str| TaskKind::parse(n).unwrap();
        let mut samples = vec![
            demo(kind("disassemble_pipe/first_link"), 5, 0),
            demo(kind("disassemble_pipe/second_link"), 5, 0),
            demo(kind("disassemble_pipe/all"), 5, 0),
            demo(kind("disassemble_pipe/first_link"), 5, 1),
            demo(kind("pick_fruit/plum"), 5, 0),
            demo(kind("pick_fruit/peach"), 5, 0),
        ];
        let target = |s: &DemoSample| s.sample.target.base_from_tcp.translation();
        let (first, second) = (target(&samples[0]), target(&samples[1]));
        assert_eq!(add_sibling_negatives(&mut samples, TABLE), 3);
        let negatives = |i: usize| -> Vec<Vector3<f64>> {
            samples[i]
                .sample
                .negatives
                .iter()
                .map(|p| p.coords)
                .collect()
        };
        // "all" starts where "first link" does: only the second link is a negative for
        // them, and the second link's one negative is the first link, given once.
        assert_eq!(negatives(0), [second]);
        assert_eq!(negatives(1), [first]);
        assert_eq!(negatives(2), [second]);
        // No sibling at step 1; the fruit's variations are different scenes.
        assert!(negatives(3).is_empty());
        assert!(negatives(4).is_empty() && negatives(5).is_empty());
    }

    #[test]
    fn paired_partners_go_elsewhere_where_any_does() {
        let kind = |n: &str| TaskKind::parse(n).unwrap();
        let samples = vec![
            demo(kind("disassemble_pipe/first_link"), 5, 0),
            demo(kind("disassemble_pipe/second_link"), 5, 0),
            demo(kind("disassemble_pipe/all"), 5, 0),
            demo(kind("pluck_flower/top"), 2, 0),
            demo(kind("pluck_flower/middle"), 2, 0),
            demo(kind("disassemble_pipe/first_link"), 5, 1),
            demo(kind("disassemble_pipe/all"), 5, 1),
        ];
        let partners = contrasting_siblings(&samples);
        // "first link" and "all" start at one place: each is paired with the second link
        // only, and the second link with both.
        assert_eq!(partners[0], [1]);
        assert_eq!(partners[2], [1]);
        assert_eq!(partners[1], [0, 2]);
        assert_eq!(partners[3], [4]);
        assert_eq!(partners[4], [3]);
        // The second step of "first link" and "all" (pulling the first link) goes to one
        // place too: with no sibling elsewhere, the one there is stays the partner.
        let t = |i: usize| samples[i].sample.target.base_from_tcp.translation();
        assert!((t(5) - t(6)).norm() <= SAME_TARGET_M);
        assert_eq!(partners[5], [6]);
        assert_eq!(partners[6], [5]);
    }

    /// A demonstration step of `kind`'s scene with `seed`, with a stand-in cloud.
    fn demo(kind: TaskKind, seed: u64, step: usize) -> DemoSample {
        crate::train::stand_in_demo(kind, seed, step, TABLE)
    }

    #[test]
    fn each_counterfactual_scene_is_asked_once_under_each_instruction() {
        let cfg = cell_types::config::CellConfig::simulated().unwrap();
        let mut net = crate::learned::for_cell(policy::predict::PolicyConfig::tiny(), &cfg);
        net.extra.token_dim = policy::minilm::HIDDEN;
        let mut policy = Policy::random(net, 1).unwrap();
        let kind = |n: &str| TaskKind::parse(n).unwrap();
        let samples = vec![
            demo(kind("disassemble_pipe/first_link"), 5, 0),
            demo(kind("disassemble_pipe/first_link"), 5, 1),
            // The same scene again under another variation: asked once.
            demo(kind("disassemble_pipe/all"), 5, 0),
            demo(kind("pick_fruit/plum"), 5, 0),
        ];
        let mut lines = Vec::new();
        let t = ground(
            &mut policy,
            &samples,
            &Instructions::Builtin,
            cfg.workspace.table_height,
            0,
            &mut |l| lines.push(l.to_string()),
        )
        .unwrap();
        assert_eq!(t.predictions.len(), 3, "{:?}", t.predictions);
        assert_eq!(lines.len(), 3);
        let names: Vec<&str> = t.predictions.iter().map(|p| p.variation.as_str()).collect();
        assert_eq!(
            names,
            [
                "disassemble_pipe/first_link",
                "disassemble_pipe/second_link",
                "disassemble_pipe/all"
            ]
        );
        let targets =
            counterfactuals(kind("disassemble_pipe/all"), 5, cfg.workspace.table_height).unwrap();
        for p in &t.predictions {
            let target = targets
                .iter()
                .find(|(k, _)| k.name() == p.variation)
                .unwrap()
                .1;
            let at = Vector3::from(p.position);
            assert!(
                ((at - target).norm() - p.own_target_m).abs() < 1e-9,
                "{p:?}"
            );
            assert!(p.other_target_m.is_finite() && p.other_target_m > 0.0);
        }
        assert_eq!(t.skipped_tasks, ["pick_fruit"]);
        assert_eq!(t.rows.len(), 2);
        assert_eq!(
            (t.rows[0].task.as_str(), t.rows[0].scenes),
            ("disassemble_pipe", 1)
        );
        let grounded = t.predictions.iter().filter(|p| p.grounded()).count();
        assert!((t.rows[1].grounded - grounded as f64 / 3.0).abs() < 1e-12);
        // Two pairs have different targets (first/second, second/all).
        let r = t.rows[1].ignored_pairs * 2.0;
        assert!(
            (r - r.round()).abs() < 1e-12 && (0.0..=2.0).contains(&r),
            "{r}"
        );

        let err = ground(
            &mut policy,
            &samples[3..],
            &Instructions::Builtin,
            cfg.workspace.table_height,
            0,
            &mut |_| {},
        )
        .unwrap_err()
        .to_string();
        assert!(err.contains("no counterfactual scene"), "{err}");
    }

    #[test]
    fn a_prediction_is_grounded_only_nearer_its_own_target() {
        let p = |own: f64, other: f64| GroundedPrediction {
            variation: "pluck_flower/top".into(),
            seed: 1,
            own_target_m: own,
            other_target_m: other,
            position: [0.0; 3],
        };
        assert!(p(0.01, 0.1).grounded());
        assert!(!p(0.1, 0.01).grounded());
        assert!(!p(0.05, 0.05).grounded(), "a tie is not grounded");
        let table = GroundingTable {
            rows: vec![GroundingRow {
                task: "pluck_flower".into(),
                scenes: 3,
                predictions: 9,
                grounded: 5.0 / 9.0,
                own_target_median_m: 0.0123,
                ignored_pairs: 0.25,
            }],
            predictions: vec![],
            skipped_tasks: vec!["pick_fruit".into()],
        };
        let md = table.markdown();
        assert!(
            md.contains("| pluck_flower | 3 | 9 | 56 % | 12.3 | 25 % |")
                && md.contains("pick_fruit"),
            "{md}"
        );
    }
}
