//! Training data for `equact train`: demonstration datasets ([`crate::demos`]) turned into
//! the policy's training samples, with each task variation's instruction embedding.
//!
//! A dataset step holds the fused cloud, the arm's joints and the gripper state before the
//! step, and the expert's keyframe; the network reads the TCP pose, so the joints go through
//! the cell's forward kinematics here.

use std::collections::BTreeMap;
use std::path::Path;

use anyhow::Context;
use cell_types::config::CellConfig;
use cell_types::{FrameId, PointCloud};
use nalgebra::Point3;
use policy::predict::{GripperPose, InstructionEmbedding};
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

/// The training samples of a dataset: every step of every successful episode, with the
/// episode's task variation, seed and step index.
pub fn load_samples(
    dir: &Path,
    cfg: &CellConfig,
    instructions: &Instructions<'_>,
) -> anyhow::Result<Vec<DemoSample>> {
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
    Ok(out)
}
