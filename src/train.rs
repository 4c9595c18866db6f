//! Training data for `equact train`: demonstration datasets ([`crate::demos`]) turned into
//! the policy's training samples, with each task variation's instruction embedding.
//!
//! A dataset step holds the fused cloud, the arm's joints and the gripper state before the
//! step, and the expert's keyframe; the network reads the TCP pose, so the joints go through
//! the cell's forward kinematics here.

use std::collections::BTreeMap;
use std::path::Path;

use anyhow::Context;
use cell_types::config::{CellConfig, PerceptionSection};
use cell_types::{FrameId, PointCloud};
use nalgebra::Point3;
use policy::predict::{GripperPose, InstructionEmbedding, PolicyConfig};
use policy::trainer::TrainSample;

use crate::demos::{read_shard, Index};
use crate::episode::robot_model;
use crate::task::TaskKind;

/// Where each variation's instruction embedding comes from.
pub enum Instructions<'a> {
    /// `<dir>/<task>/<variation>.safetensors`, as `equact eval --instruction-embeddings`.
    Folder(&'a Path),
    /// Embedded now with the MiniLM sentence model in this folder (per-token states).
    MiniLm(&'a Path),
    /// The MiniLM states compiled into the binary (`policy::builtin`), for the simulated
    /// tasks' own instructions.
    Builtin,
}

impl<'a> Instructions<'a> {
    /// The source the command-line flags name: a folder of embedding files, else the MiniLM
    /// model folder, else the built-in embeddings (the simulated tasks' instructions; other
    /// texts are refused by name when embedded).
    pub fn from_flags(folder: Option<&'a Path>, minilm: Option<&'a Path>) -> Self {
        match (folder, minilm) {
            (Some(d), _) => Self::Folder(d),
            (None, Some(m)) => Self::MiniLm(m),
            (None, None) => Self::Builtin,
        }
    }

    /// The embedding of `kind`'s instruction.
    pub fn embedding(&self, kind: TaskKind) -> anyhow::Result<InstructionEmbedding> {
        match self {
            Self::Folder(dir) => {
                let path = dir
                    .join(kind.task_name())
                    .join(format!("{}.safetensors", kind.variation_name()));
                InstructionEmbedding::from_file(&path).with_context(|| {
                    format!(
                        "reading the embedding of `{}` from {}",
                        kind.instruction(),
                        path.display()
                    )
                })
            }
            Self::MiniLm(_) | Self::Builtin => self.embed_text(&kind.instruction()),
        }
    }

    /// The embedding of free text (MiniLM; the built-in store has the tasks' own texts only,
    /// and a folder of files has no entry for free text).
    pub fn embed_text(&self, text: &str) -> anyhow::Result<InstructionEmbedding> {
        let dir = match self {
            Self::MiniLm(dir) => dir,
            Self::Builtin => return Ok(policy::builtin::instruction(text)?),
            Self::Folder(_) => {
                anyhow::bail!("free-text instructions need the MiniLM model (--minilm DIR)")
            }
        };
        let model = policy::minilm::MiniLm::load(dir)
            .with_context(|| format!("loading the MiniLM sentence model from {}", dir.display()))?;
        let (tokens, states) = model.token_states(text)?;
        Ok(InstructionEmbedding::new(
            states,
            tokens,
            policy::minilm::HIDDEN,
        )?)
    }
}

/// One step of a recorded demonstration as a training sample, with where it came from.
#[derive(Debug, Clone)]
pub struct DemoSample {
    /// The episode's task variation.
    pub kind: TaskKind,
    /// The episode's seed.
    pub seed: u64,
    /// The step's index in its episode (0: the first keyframe).
    pub step: usize,
    /// The observation and the expert's keyframe.
    pub sample: TrainSample,
}

/// Refuses to train or score `network` on the demonstrations in `dir` when it reads more
/// points than their clouds hold, or samples more near the gripper than they hold there
/// (`recorded`: how their index says they were recorded).
pub fn check_dataset_perception(
    recorded: &PerceptionSection,
    dir: &Path,
    network: &PolicyConfig,
) -> anyhow::Result<()> {
    crate::learned::check_perception(
        network,
        recorded,
        &format!("the demonstrations in {}", dir.display()),
        "record them with [perception] gripper_points of at least that (`equact demos collect \
         --config` a cell file with it), or use a network with fewer (--near-gripper-points)",
    )
}

/// A dataset's index and its training samples: every step of every successful episode, with
/// the episode's task variation, seed and step index. The index is read once, so the samples
/// and the recording settings it lists (perception, expert) come from the same file.
pub fn load_samples(
    dir: &Path,
    cfg: &CellConfig,
    instructions: &Instructions<'_>,
) -> anyhow::Result<(Index, Vec<DemoSample>)> {
    // `Index::load` reads a folder without an index as a new, empty dataset (what `demos
    // collect` starts from); here that is a wrong path, and saying so beats "no demonstration".
    if !dir.join("index.json").is_file() {
        anyhow::bail!(
            "{} is not a demonstrations folder (it has no index.json); record one with \
             `equact demos collect --out {}`",
            dir.display(),
            dir.display()
        );
    }
    let index = Index::load(dir)?;
    let model = robot_model(cfg)?;
    let mut embeddings: BTreeMap<String, InstructionEmbedding> = BTreeMap::new();
    let mut out = Vec::new();
    for entry in &index.episodes {
        let Some(file) = &entry.file else {
            continue;
        };
        let kind = TaskKind::parse(&entry.task).with_context(|| {
            format!(
                "episode {} seed {} in {}",
                entry.task,
                entry.seed,
                dir.display()
            )
        })?;
        let embedding = match embeddings.get(&entry.task) {
            Some(e) => e.clone(),
            None => {
                let e = instructions.embedding(kind)?;
                embeddings.insert(entry.task.clone(), e.clone());
                e
            }
        };
        let episode = read_shard(&dir.join(file))?;
        for (index, step) in episode.steps.into_iter().enumerate() {
            let cloud = PointCloud {
                frame: FrameId::Base,
                points: step
                    .cloud_xyz
                    .iter()
                    .map(|p| Point3::new(p[0], p[1], p[2]))
                    .collect(),
                rgb: Some(step.cloud_rgb.clone()),
            };
            out.push(DemoSample {
                kind,
                seed: entry.seed,
                step: index,
                sample: TrainSample {
                    cloud,
                    gripper: GripperPose {
                        base_from_tcp: model.fk_tcp(&step.joints),
                        open: step.gripper_open,
                    },
                    instruction: embedding.clone(),
                    target: step.keyframe,
                    negatives: Vec::new(),
                    placed_by_scene: kind.placed_by_scene(index),
                },
            });
        }
    }
    if out.is_empty() {
        anyhow::bail!(
            "{} holds no successful demonstration; record some with `equact demos collect`",
            dir.display()
        );
    }
    Ok((index, out))
}

/// For each sample, the other samples of the same scene: the same task, seed and step under
/// the task's other variations (a pipe or flower scene with one seed is the same in every
/// variation, so these are exact counterfactuals that differ only in the instruction).
pub fn scene_siblings(samples: &[DemoSample]) -> Vec<Vec<usize>> {
    let keys: Vec<_> = samples
        .iter()
        .map(|s| (s.kind.task_name(), s.seed, s.step))
        .collect();
    siblings_by_key(&keys)
}

/// For each key, the indices of the other entries with the same key.
fn siblings_by_key<K: Eq + std::hash::Hash>(keys: &[K]) -> Vec<Vec<usize>> {
    let mut groups: std::collections::HashMap<&K, Vec<usize>> = std::collections::HashMap::new();
    for (i, k) in keys.iter().enumerate() {
        groups.entry(k).or_default().push(i);
    }
    keys.iter()
        .enumerate()
        .map(|(i, k)| groups[k].iter().copied().filter(|&j| j != i).collect())
        .collect()
}

/// The sample indices of training step `step`: each epoch walks a fresh permutation of the
/// `n` samples drawn from `seed` (so a resumed run draws the same batches as an
/// uninterrupted one), `anchors` per step. With `siblings` ([`scene_siblings`]), each anchor
/// is followed by one of its siblings drawn from `seed` and the step, so that the step's
/// gradient holds the same scene under two instructions: what the scene alone explains
/// cancels, and what is left is how the instruction must change the field.
pub fn batch_indices(
    n: usize,
    anchors: usize,
    siblings: Option<&[Vec<usize>]>,
    seed: u64,
    step: u64,
) -> Vec<usize> {
    use rand::seq::{IndexedRandom, SliceRandom};
    use rand::SeedableRng;
    let anchors = anchors.max(1);
    let per_epoch = n.div_ceil(anchors).max(1) as u64;
    let epoch = step / per_epoch;
    let mut order: Vec<usize> = (0..n).collect();
    order.shuffle(&mut rand_chacha::ChaCha8Rng::seed_from_u64(
        seed ^ (epoch << 20),
    ));
    let at = ((step % per_epoch) as usize) * anchors;
    let picked = &order[at.min(n)..(at + anchors).min(n)];
    let Some(siblings) = siblings else {
        return picked.to_vec();
    };
    let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(seed ^ step.rotate_left(32) ^ 0x5eed);
    let mut out = Vec::with_capacity(2 * picked.len());
    for &i in picked {
        out.push(i);
        if let Some(&j) = siblings.get(i).and_then(|s| s.choose(&mut rng)) {
            out.push(j);
        }
    }
    out
}

/// A demonstration step of `kind`'s scene drawn with `seed`, labelled with the scripted
/// expert's keyframe `step`, with a stand-in cloud (a grid of points on the table at
/// `table`) and an open gripper at (0.4, 0, 0.3): for tests of what reads demonstrations.
#[cfg(test)]
pub(crate) fn stand_in_demo(kind: TaskKind, seed: u64, step: usize, table: f64) -> DemoSample {
    use cell_types::Transform;
    let scene = crate::task::TaskInstance::sample(kind, seed, table);
    let points: Vec<Point3<f32>> = (0..400)
        .map(|i| {
            let (a, b) = ((i % 20) as f32, (i / 20) as f32);
            Point3::new(0.35 + 0.015 * a, -0.15 + 0.015 * b, table as f32 + 0.02)
        })
        .collect();
    DemoSample {
        kind,
        seed,
        step,
        sample: TrainSample {
            cloud: PointCloud {
                frame: FrameId::Base,
                rgb: Some(vec![[120, 120, 120]; points.len()]),
                points,
            },
            gripper: GripperPose {
                base_from_tcp: Transform::from_parts(
                    nalgebra::Vector3::new(0.4, 0.0, 0.3),
                    nalgebra::UnitQuaternion::identity(),
                ),
                open: true,
            },
            instruction: Instructions::Builtin
                .embedding(kind)
                .unwrap_or_else(|e| panic!("{e}")),
            target: scene.expert_keyframes()[step],
            negatives: Vec::new(),
            placed_by_scene: kind.placed_by_scene(step),
        },
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_folder_without_an_index_is_named_not_read_as_empty() {
        let cfg = CellConfig::simulated().unwrap_or_else(|e| panic!("{e}"));
        let dir = std::env::temp_dir().join(format!("equact-no-demos-{}", std::process::id()));
        for d in [dir.join("missing"), dir.clone()] {
            if d == dir {
                std::fs::create_dir_all(&d).unwrap_or_else(|e| panic!("{e}"));
            }
            let err = load_samples(&d, &cfg, &Instructions::Builtin)
                .err()
                .map(|e| e.to_string())
                .unwrap_or_default();
            assert!(
                err.contains("not a demonstrations folder") && err.contains("demos collect"),
                "{err}"
            );
        }
        let _ = std::fs::remove_dir_all(&dir);
    }

    #[test]
    fn siblings_are_the_other_entries_of_the_same_scene() {
        let keys = [
            ("pipe", 0u64, 0usize),
            ("pipe", 0, 0),
            ("pipe", 1, 0),
            ("fruit", 0, 0),
            ("pipe", 0, 0),
            ("pipe", 0, 1),
        ];
        let s = siblings_by_key(&keys);
        let want: Vec<Vec<usize>> =
            vec![vec![1, 4], vec![0, 4], vec![], vec![], vec![0, 1], vec![]];
        assert_eq!(s, want);
    }

    #[test]
    fn each_epoch_visits_every_sample_once_and_the_same_step_draws_the_same_batch() {
        let (n, anchors) = (7, 2);
        for epoch in 0..3u64 {
            let mut seen: Vec<usize> = (0..4)
                .flat_map(|k| batch_indices(n, anchors, None, 9, 4 * epoch + k))
                .collect();
            assert_eq!(batch_indices(n, anchors, None, 9, 4 * epoch + 3).len(), 1);
            seen.sort_unstable();
            assert_eq!(seen, (0..n).collect::<Vec<_>>(), "epoch {epoch}");
        }
        assert_eq!(
            batch_indices(n, anchors, None, 9, 5),
            batch_indices(n, anchors, None, 9, 5)
        );
        // Epochs differ in order.
        let first: Vec<_> = (0..4)
            .flat_map(|k| batch_indices(n, anchors, None, 9, k))
            .collect();
        let second: Vec<_> = (4..8)
            .flat_map(|k| batch_indices(n, anchors, None, 9, k))
            .collect();
        assert_ne!(first, second);
    }

    #[test]
    fn paired_batches_follow_each_anchor_with_one_of_its_siblings() {
        // Samples 0, 1, 2 are one scene under three variations; 3 has no counterpart.
        let siblings = siblings_by_key(&[0, 0, 0, 1]);
        let mut partners_of_0 = std::collections::BTreeSet::new();
        for step in 0..40u64 {
            let b = batch_indices(4, 1, Some(&siblings), 3, step);
            match b[..] {
                [3] => {}
                [a, p] => {
                    assert!(a < 3 && p < 3 && a != p, "step {step}: {b:?}");
                    if a == 0 {
                        partners_of_0.insert(p);
                    }
                }
                _ => panic!("step {step}: {b:?}"),
            }
            assert_eq!(b, batch_indices(4, 1, Some(&siblings), 3, step));
        }
        // The counterpart is drawn, not fixed.
        assert_eq!(partners_of_0, [1, 2].into());
        // The anchors still walk every sample once per epoch.
        let mut anchors: Vec<usize> = (0..4)
            .map(|k| batch_indices(4, 1, Some(&siblings), 3, k)[0])
            .collect();
        anchors.sort_unstable();
        assert_eq!(anchors, vec![0, 1, 2, 3]);
    }
}
