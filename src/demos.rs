//! Demonstration datasets: the scripted expert's episodes in the simulated cell, recorded per
//! keyframe step as the policy will see them — the fused cloud (the simulated cameras through
//! the real perception pipeline), the joints, the gripper state, the expert's keyframe and
//! the task's language instruction.
//!
//! On disk: one safetensors shard per episode (`<task>-<variation>/seed_<seed>.safetensors`)
//! and `index.json` listing every episode tried, with the cell's `[perception]` sampling
//! the clouds were recorded with (absent in older indexes: EquAct's plain sampling). Shards and the index are written to a
//! temporary file and renamed, so an interrupted collection never leaves a half-written
//! file under its final name; on restart, episodes already in the index are skipped.
//!
//! Tensors of a shard with S steps and P points per cloud: `cloud_xyz` f32 `[S, P, 3]` (base
//! frame, m), `cloud_rgb` u8 `[S, P, 3]`, `joints` f64 `[S, 6]`, `gripper_width` f64 `[S]`,
//! `gripper_open` u8 `[S]` (before the step), `keyframe_pose` f64 `[S, 7]` (x, y, z, qx, qy,
//! qz, qw of the TCP in the base frame), `keyframe_open` u8 `[S]`,
//! `keyframe_ignore_collisions` u8 `[S]`. Its metadata holds the task, variation,
//! instruction, seed and format.

use std::collections::BTreeMap;
use std::fs;
use std::path::{Path, PathBuf};
use std::sync::atomic::AtomicBool;
use std::sync::Arc;
use std::time::Instant;

use cell_types::config::{CellConfig, PerceptionSection};
use cell_types::{CellTypesError, Keyframe, TickClock, Transform};
use nalgebra::{Quaternion, UnitQuaternion, Vector3};
use safetensors::tensor::TensorView;
use safetensors::{Dtype, SafeTensors};
use serde::{Deserialize, Serialize};

use crate::episode::{run_sim_episode, KeyframeSource, Observation, Outcome, ScriptedExpert};
use crate::recording::EpisodeRecorder;
use crate::sim_cell::{EpisodePlan, SimCell};
use crate::task::{ExpertSettings, TaskInstance, TaskKind};

mod merge;
pub use merge::{merge, MergeSummary, Replacement};

/// The format written into every shard and the index.
pub const FORMAT: &str = "equact-demos/1";

/// Why a dataset could not be written or read.
#[derive(Debug, thiserror::Error)]
pub enum DemosError {
    /// A file or directory could not be read or written.
    #[error("{path}: {source}; check the path and its permissions")]
    Io {
        /// The path.
        path: PathBuf,
        /// The I/O error.
        source: std::io::Error,
    },
    /// The index is not a dataset index of this format.
    #[error("{path} is not an equact demos index ({why}); point --out at a new directory or fix the file")]
    BadIndex {
        /// The index path.
        path: PathBuf,
        /// What is wrong.
        why: String,
    },
    /// A shard is unreadable or misshapen.
    #[error("demo shard {path}: {why}; delete it and its index entry to record it again")]
    BadShard {
        /// The shard path.
        path: PathBuf,
        /// What is wrong.
        why: String,
    },
    /// A collection would mix clouds sampled two ways in one dataset.
    #[error(
        "{path} holds demonstrations recorded with [perception] {recorded}; this cell \
         samples {cell}: record into another folder, or use the configuration the dataset \
         was recorded with"
    )]
    PerceptionMismatch {
        /// The dataset directory.
        path: PathBuf,
        /// The dataset's sampling.
        recorded: Box<PerceptionSection>,
        /// The cell's sampling.
        cell: Box<PerceptionSection>,
    },
    /// A collection would mix two experts' demonstrations in one dataset.
    #[error(
        "{path} holds demonstrations recorded by {}, not {}: record into another folder, or \
         pass {}",
        expert_words(recorded),
        expert_words(asked),
        expert_flags(recorded)
    )]
    ExpertMismatch {
        /// The dataset directory.
        path: PathBuf,
        /// The dataset's expert.
        recorded: ExpertSettings,
        /// The one asked for now.
        asked: ExpertSettings,
    },
    /// A folder given as a dataset holds none.
    #[error(
        "{0} holds no index.json, so it is not a demonstration dataset; pass the folder that \
         `equact demos collect --out` wrote"
    )]
    NotADataset(PathBuf),
    /// `demos merge` was pointed at a folder that already holds a dataset.
    #[error(
        "{0} already holds a dataset (index.json); merge writes a new one: pass an --out \
         folder without an index.json, other than the sources"
    )]
    MergeInto(PathBuf),
    /// Two datasets cannot become one.
    #[error("{other} cannot join {first} in one dataset: {why}; leave one of them out")]
    MergeMismatch {
        /// The first source that set the dataset's kind.
        first: PathBuf,
        /// The source that differs.
        other: PathBuf,
        /// How they differ.
        why: String,
    },
    /// The expert's settings are out of range.
    #[error("the expert's grasp turn must be a number from 0 to 30°, got {0}")]
    BadExpertSettings(f64),
    /// The simulator cannot run at the speed asked.
    #[error("{0}: the simulated cell runs above 0 and at most {max} times real time", max = cell_types::ScaledClock::MAX_SPEED)]
    SimSpeed(CellTypesError),
    /// The simulated cell could not run the episode.
    #[error("episode {task} seed {seed}: {why}")]
    Episode {
        /// The task variation.
        task: String,
        /// The seed.
        seed: u64,
        /// What went wrong.
        why: String,
    },
}

/// One recorded keyframe step.
#[derive(Clone, Debug, PartialEq)]
pub struct DemoStep {
    /// The fused, sampled cloud (base frame, m).
    pub cloud_xyz: Vec<[f32; 3]>,
    /// Its colours (zeros where the cameras gave none).
    pub cloud_rgb: Vec<[u8; 3]>,
    /// The arm's joints before the step (rad).
    pub joints: [f64; 6],
    /// The gripper's opening before the step (m).
    pub gripper_width: f64,
    /// The gripper was open before the step.
    pub gripper_open: bool,
    /// The expert's keyframe for this step.
    pub keyframe: Keyframe,
}

/// One episode of a dataset, as the index lists it.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct IndexEntry {
    /// `task/variation`.
    pub task: String,
    /// The language instruction.
    pub instruction: String,
    /// The episode's seed.
    pub seed: u64,
    /// How the episode ended (`success`, `plan_failed`, ...).
    pub outcome: String,
    /// Keyframe steps recorded.
    pub steps: usize,
    /// The shard, relative to the dataset directory; `None` when the episode failed (failed
    /// episodes are not demonstrations, but are listed so a restart does not retry them).
    pub file: Option<String>,
}

/// The dataset's index file (`index.json`).
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct Index {
    /// [`FORMAT`].
    pub format: String,
    /// Every episode tried, in the order they finished.
    pub episodes: Vec<IndexEntry>,
    /// How the clouds were sampled near the gripper (the cell's `[perception]`); indexes
    /// from before the field read as the default, EquAct's plain sampling, which is how
    /// they were recorded.
    #[serde(default)]
    pub perception: PerceptionSection,
    /// How the expert recorded the episodes; absent in older indexes, which the plain
    /// expert recorded.
    #[serde(default)]
    pub expert: ExpertSettings,
}

/// The expert that `settings` stand for, in words.
pub(crate) fn expert_words(settings: &ExpertSettings) -> String {
    let mut changes = Vec::new();
    if settings.grasp_turn_deg != 0.0 {
        changes.push(format!("grasp turns up to {}°", settings.grasp_turn_deg));
    }
    if settings.centred_grasp_labels {
        changes.push("centred grasp labels".to_string());
    }
    if changes.is_empty() {
        "the plain expert".into()
    } else {
        format!("the expert with {}", changes.join(" and "))
    }
}

/// The `demos collect` options that record with `settings`.
fn expert_flags(settings: &ExpertSettings) -> String {
    let mut flags = format!("--grasp-turn {}", settings.grasp_turn_deg);
    if settings.centred_grasp_labels {
        flags.push_str(" --centred-grasp-labels");
    }
    flags
}

fn io(path: &Path) -> impl FnOnce(std::io::Error) -> DemosError + '_ {
    move |source| DemosError::Io {
        path: path.to_path_buf(),
        source,
    }
}

/// Writes `bytes` to `path` through a temporary file and a rename.
fn write_atomic(path: &Path, bytes: &[u8]) -> Result<(), DemosError> {
    let tmp = path.with_extension("partial");
    fs::write(&tmp, bytes).map_err(io(&tmp))?;
    fs::rename(&tmp, path).map_err(io(path))
}

impl Index {
    /// Reads `dir/index.json`, or an empty index when there is none yet.
    pub fn load(dir: &Path) -> Result<Self, DemosError> {
        let path = dir.join("index.json");
        if !path.exists() {
            return Ok(Self {
                format: FORMAT.into(),
                ..Self::default()
            });
        }
        let text = fs::read_to_string(&path).map_err(io(&path))?;
        let index: Index = serde_json::from_str(&text).map_err(|e| DemosError::BadIndex {
            path: path.clone(),
            why: e.to_string(),
        })?;
        if index.format != FORMAT {
            return Err(DemosError::BadIndex {
                path,
                why: format!("format `{}`, expected `{FORMAT}`", index.format),
            });
        }
        // A shard path must stay inside its dataset, so that no reader (train, merge, score)
        // opens, and no merge writes, a file elsewhere because of a hand-edited index.
        for entry in &index.episodes {
            let Some(file) = &entry.file else { continue };
            let inside = Path::new(file)
                .components()
                .all(|c| matches!(c, std::path::Component::Normal(_)));
            if !inside {
                return Err(DemosError::BadIndex {
                    path,
                    why: format!(
                        "episode {} seed {} names its shard {file:?}, a path outside the dataset",
                        entry.task, entry.seed
                    ),
                });
            }
        }
        Ok(index)
    }

    /// Writes `dir/index.json` atomically.
    pub fn save(&self, dir: &Path) -> Result<(), DemosError> {
        let path = dir.join("index.json");
        let text = serde_json::to_string_pretty(self).map_err(|e| DemosError::BadIndex {
            path: path.clone(),
            why: e.to_string(),
        })?;
        write_atomic(&path, text.as_bytes())
    }

    /// The entry of `task` (`task/variation`) and `seed`, if it was tried.
    pub fn find(&self, task: &str, seed: u64) -> Option<&IndexEntry> {
        self.episodes
            .iter()
            .find(|e| e.task == task && e.seed == seed)
    }
}

/// The shard path of an episode, relative to the dataset directory.
pub fn shard_name(kind: TaskKind, seed: u64) -> String {
    format!(
        "{}-{}/seed_{seed:06}.safetensors",
        kind.task_name(),
        kind.variation_name()
    )
}

fn bytes_f64(v: &[f64]) -> Vec<u8> {
    v.iter().flat_map(|x| x.to_le_bytes()).collect()
}

/// Serialises an episode's steps into a safetensors shard.
pub fn shard_bytes(kind: TaskKind, seed: u64, steps: &[DemoStep]) -> Result<Vec<u8>, String> {
    let s = steps.len();
    let p = steps.iter().map(|x| x.cloud_xyz.len()).max().unwrap_or(0);
    let mut xyz = Vec::with_capacity(s * p * 12);
    let mut rgb = Vec::with_capacity(s * p * 3);
    for st in steps {
        for i in 0..p {
            // Clouds are sampled to one size; a shorter one repeats its last point.
            let k = i.min(st.cloud_xyz.len().saturating_sub(1));
            let pt = st.cloud_xyz.get(k).copied().unwrap_or([0.0; 3]);
            xyz.extend(pt.iter().flat_map(|v| v.to_le_bytes()));
            rgb.extend(st.cloud_rgb.get(k).copied().unwrap_or([0; 3]));
        }
    }
    let joints: Vec<f64> = steps.iter().flat_map(|x| x.joints).collect();
    let width: Vec<f64> = steps.iter().map(|x| x.gripper_width).collect();
    let open: Vec<u8> = steps.iter().map(|x| u8::from(x.gripper_open)).collect();
    let pose: Vec<f64> = steps
        .iter()
        .flat_map(|x| {
            let t = x.keyframe.base_from_tcp.translation();
            let q = x.keyframe.base_from_tcp.rotation();
            [t.x, t.y, t.z, q.i, q.j, q.k, q.w]
        })
        .collect();
    let kf_open: Vec<u8> = steps
        .iter()
        .map(|x| u8::from(x.keyframe.gripper_open))
        .collect();
    let kf_ignore: Vec<u8> = steps
        .iter()
        .map(|x| u8::from(x.keyframe.ignore_collisions))
        .collect();
    let (joints, width, pose) = (bytes_f64(&joints), bytes_f64(&width), bytes_f64(&pose));
    fn view(dtype: Dtype, shape: Vec<usize>, data: &[u8]) -> Result<TensorView<'_>, String> {
        TensorView::new(dtype, shape, data).map_err(|e| format!("{e}"))
    }
    let tensors = vec![
        ("cloud_xyz", view(Dtype::F32, vec![s, p, 3], &xyz)?),
        ("cloud_rgb", view(Dtype::U8, vec![s, p, 3], &rgb)?),
        ("joints", view(Dtype::F64, vec![s, 6], &joints)?),
        ("gripper_width", view(Dtype::F64, vec![s], &width)?),
        ("gripper_open", view(Dtype::U8, vec![s], &open)?),
        ("keyframe_pose", view(Dtype::F64, vec![s, 7], &pose)?),
        ("keyframe_open", view(Dtype::U8, vec![s], &kf_open)?),
        (
            "keyframe_ignore_collisions",
            view(Dtype::U8, vec![s], &kf_ignore)?,
        ),
    ];
    let meta: std::collections::HashMap<String, String> = [
        ("format", FORMAT.to_string()),
        ("task", kind.task_name().to_string()),
        ("variation", kind.variation_name().to_string()),
        ("instruction", kind.instruction()),
        ("seed", seed.to_string()),
    ]
    .into_iter()
    .map(|(k, v)| (k.to_string(), v))
    .collect();
    let bytes = safetensors::serialize(tensors, Some(meta)).map_err(|e| format!("{e}"))?;
    // The same episode gives the same bytes in every process.
    policy::weights::sorted_safetensors_header(bytes)
}

/// A demonstration episode read back from its shard.
#[derive(Clone, Debug, PartialEq)]
pub struct DemoEpisode {
    /// The shard's metadata (task, variation, instruction, seed, format).
    pub metadata: BTreeMap<String, String>,
    /// Points per cloud.
    pub points: usize,
    /// The steps.
    pub steps: Vec<DemoStep>,
}

/// Reads a shard written by [`shard_bytes`], checking every tensor's type and shape.
pub fn read_shard(path: &Path) -> Result<DemoEpisode, DemosError> {
    let bytes = fs::read(path).map_err(io(path))?;
    parse_shard(path, &bytes)
}

/// Parses the bytes of the shard at `path` (named in errors) as [`read_shard`] does.
fn parse_shard(path: &Path, bytes: &[u8]) -> Result<DemoEpisode, DemosError> {
    let bad = |why: String| DemosError::BadShard {
        path: path.to_path_buf(),
        why,
    };
    let (_, header) = SafeTensors::read_metadata(bytes).map_err(|e| bad(e.to_string()))?;
    let metadata: BTreeMap<String, String> = header
        .metadata()
        .clone()
        .unwrap_or_default()
        .into_iter()
        .collect();
    if metadata.get("format").map(String::as_str) != Some(FORMAT) {
        return Err(bad(format!(
            "format {:?}, expected {FORMAT}",
            metadata.get("format")
        )));
    }
    let st = SafeTensors::deserialize(bytes).map_err(|e| bad(e.to_string()))?;
    let get =
        |name: &str, dtype: Dtype, tail: &[usize]| -> Result<(Vec<usize>, Vec<u8>), DemosError> {
            let t = st
                .tensor(name)
                .map_err(|e| bad(format!("tensor {name}: {e}")))?;
            let shape = t.shape();
            // A 0 in `tail` stands for any size (the point count).
            let fits = shape.len() == tail.len() + 1
                && shape[1..].iter().zip(tail).all(|(a, b)| *b == 0 || a == b);
            if t.dtype() != dtype || !fits {
                return Err(bad(format!(
                    "tensor {name} is {:?} {shape:?}, expected {dtype:?} [S, {tail:?}]",
                    t.dtype()
                )));
            }
            Ok((t.shape().to_vec(), t.data().to_vec()))
        };
    let f64s = |b: &[u8]| -> Vec<f64> {
        b.chunks_exact(8)
            .map(|c| f64::from_le_bytes([c[0], c[1], c[2], c[3], c[4], c[5], c[6], c[7]]))
            .collect()
    };
    let (xshape, xyz) = get("cloud_xyz", Dtype::F32, &[0, 3])?;
    let (s, p) = (xshape[0], xshape[1]);
    let (_, rgb) = get("cloud_rgb", Dtype::U8, &[0, 3])?;
    let (_, joints) = get("joints", Dtype::F64, &[6])?;
    let (_, width) = get("gripper_width", Dtype::F64, &[])?;
    let (_, open) = get("gripper_open", Dtype::U8, &[])?;
    let (_, pose) = get("keyframe_pose", Dtype::F64, &[7])?;
    let (_, kf_open) = get("keyframe_open", Dtype::U8, &[])?;
    let (_, kf_ignore) = get("keyframe_ignore_collisions", Dtype::U8, &[])?;
    let (joints, width, pose) = (f64s(&joints), f64s(&width), f64s(&pose));
    let sizes = [
        (rgb.len(), s * p * 3),
        (joints.len(), s * 6),
        (width.len(), s),
        (open.len(), s),
        (pose.len(), s * 7),
        (kf_open.len(), s),
        (kf_ignore.len(), s),
    ];
    if sizes.iter().any(|(a, b)| a != b) {
        return Err(bad(format!(
            "tensor sizes {sizes:?} disagree with {s} steps of {p} points"
        )));
    }
    let mut steps = Vec::with_capacity(s);
    for i in 0..s {
        let cloud_xyz = (0..p)
            .map(|k| {
                let o = (i * p + k) * 12;
                let f = |j: usize| {
                    f32::from_le_bytes([xyz[o + j], xyz[o + j + 1], xyz[o + j + 2], xyz[o + j + 3]])
                };
                [f(0), f(4), f(8)]
            })
            .collect();
        let cloud_rgb = (0..p)
            .map(|k| {
                let o = (i * p + k) * 3;
                [rgb[o], rgb[o + 1], rgb[o + 2]]
            })
            .collect();
        let q = &pose[i * 7..i * 7 + 7];
        let rotation = UnitQuaternion::from_quaternion(Quaternion::new(q[6], q[3], q[4], q[5]));
        let mut j = [0.0; 6];
        j.copy_from_slice(&joints[i * 6..i * 6 + 6]);
        steps.push(DemoStep {
            cloud_xyz,
            cloud_rgb,
            joints: j,
            gripper_width: width[i],
            gripper_open: open[i] != 0,
            keyframe: Keyframe {
                base_from_tcp: Transform::from_parts(Vector3::new(q[0], q[1], q[2]), rotation),
                gripper_open: kf_open[i] != 0,
                ignore_collisions: kf_ignore[i] != 0,
            },
        });
    }
    Ok(DemoEpisode {
        metadata,
        points: p,
        steps,
    })
}

/// The expert, recording what it saw and its label at every step while the cell executes
/// the plan's executed keyframe.
struct RecordingExpert {
    inner: ScriptedExpert,
    labels: Vec<Keyframe>,
    steps: Vec<DemoStep>,
}

impl KeyframeSource for RecordingExpert {
    fn next_keyframe(&mut self, obs: &Observation<'_>) -> anyhow::Result<Option<Keyframe>> {
        let k = self.inner.next_keyframe(obs)?;
        if let Some(executed) = k {
            let keyframe = self
                .labels
                .get(self.steps.len())
                .copied()
                .unwrap_or(executed);
            let rgb = obs.cloud.rgb.as_ref();
            self.steps.push(DemoStep {
                cloud_xyz: obs.cloud.points.iter().map(|p| [p.x, p.y, p.z]).collect(),
                cloud_rgb: (0..obs.cloud.points.len())
                    .map(|i| rgb.and_then(|c| c.get(i).copied()).unwrap_or([0; 3]))
                    .collect(),
                joints: obs.joints.position,
                // The episode loop's own test of an open gripper.
                gripper_open: obs.gripper.width_m > 0.08,
                gripper_width: obs.gripper.width_m,
                keyframe,
            });
        }
        Ok(k)
    }

    fn name(&self) -> &str {
        "expert"
    }
}

/// What [`collect`] did.
#[derive(Clone, Debug, Default, PartialEq, Eq)]
pub struct CollectSummary {
    /// Episodes recorded now.
    pub recorded: usize,
    /// Episodes skipped because the index already had them.
    pub skipped: usize,
    /// Episodes that ended without success now (listed in the index without a shard).
    pub failed: usize,
}

/// Records the plan's expert episodes (`plan.episodes` per kind, seeds `plan.seed..`) into
/// the dataset at `out`, skipping those its index already lists. Progress goes to stdout.
pub fn collect(
    cfg: &CellConfig,
    plan: &EpisodePlan,
    out: &Path,
    expert: &ExpertSettings,
    interrupt: &Arc<AtomicBool>,
) -> Result<CollectSummary, DemosError> {
    let turn = expert.grasp_turn_deg;
    if !(0.0..=30.0).contains(&turn) {
        return Err(DemosError::BadExpertSettings(turn));
    }
    plan.clock().map_err(DemosError::SimSpeed)?;
    let (kinds, episodes, first_seed) = (&plan.kinds, plan.episodes, plan.seed);
    fs::create_dir_all(out).map_err(io(out))?;
    let mut index = Index::load(out)?;
    if index.episodes.is_empty() {
        index.perception = cfg.perception.clone();
        index.expert = *expert;
    } else if index.perception != cfg.perception {
        return Err(DemosError::PerceptionMismatch {
            path: out.to_path_buf(),
            recorded: Box::new(index.perception.clone()),
            cell: Box::new(cfg.perception.clone()),
        });
    } else if index.expert != *expert {
        return Err(DemosError::ExpertMismatch {
            path: out.to_path_buf(),
            recorded: index.expert,
            asked: *expert,
        });
    }
    let total = kinds.len() as u64 * episodes;
    let mut summary = CollectSummary::default();
    let started = Instant::now();
    let mut done_now = 0u64;
    let mut n = 0u64;
    for &kind in kinds {
        let dir = out.join(format!("{}-{}", kind.task_name(), kind.variation_name()));
        fs::create_dir_all(&dir).map_err(io(&dir))?;
        for seed in first_seed..first_seed + episodes {
            n += 1;
            if interrupt.load(std::sync::atomic::Ordering::SeqCst) {
                return Ok(summary);
            }
            let name = kind.name();
            if let Some(e) = index.find(&name, seed) {
                let shard_ok = e.file.as_ref().is_none_or(|f| out.join(f).exists());
                if shard_ok {
                    summary.skipped += 1;
                    println!(
                        "[{n}/{total}] {name} seed {seed}: already recorded ({})",
                        e.outcome
                    );
                    continue;
                }
                // Listed but its shard is gone: record it again.
                index
                    .episodes
                    .retain(|x| !(x.task == name && x.seed == seed));
            }
            let t0 = Instant::now();
            let clock = plan.clock().map_err(DemosError::SimSpeed)?;
            let (outcome, steps) = record_episode(cfg, kind, seed, clock, out, expert, interrupt)?;
            let file = if outcome == Outcome::Success {
                let rel = shard_name(kind, seed);
                let bytes =
                    shard_bytes(kind, seed, &steps).map_err(|why| DemosError::BadShard {
                        path: out.join(&rel),
                        why,
                    })?;
                write_atomic(&out.join(&rel), &bytes)?;
                summary.recorded += 1;
                Some(rel)
            } else {
                summary.failed += 1;
                None
            };
            if outcome == Outcome::Interrupted {
                // Not a result: leave it out of the index so a restart records it.
                return Ok(summary);
            }
            index.episodes.push(IndexEntry {
                task: name.clone(),
                instruction: kind.instruction(),
                seed,
                outcome: outcome.label().into(),
                steps: steps.len(),
                file,
            });
            index.save(out)?;
            done_now += 1;
            let per = started.elapsed().as_secs_f64() / done_now as f64;
            println!(
                "[{n}/{total}] {name} seed {seed}: {} in {} steps, {:.1} s (about {:.0} s left)",
                outcome.label(),
                steps.len(),
                t0.elapsed().as_secs_f64(),
                per * (total - n) as f64
            );
        }
    }
    Ok(summary)
}

/// Runs one expert episode in a fresh simulated cell and returns its outcome and steps.
fn record_episode(
    cfg: &CellConfig,
    kind: TaskKind,
    seed: u64,
    clock: Arc<TickClock>,
    out: &Path,
    expert: &ExpertSettings,
    interrupt: &Arc<AtomicBool>,
) -> Result<(Outcome, Vec<DemoStep>), DemosError> {
    let err = |why: String| DemosError::Episode {
        task: kind.name(),
        seed,
        why,
    };
    let task = TaskInstance::sample(kind, seed, cfg.workspace.table_height);
    let mut cell = SimCell::start(cfg, task.clone(), seed, clock.clone())
        .map_err(|e| err(format!("{e:#}")))?;
    // The episode's full MCAP recording (depth images and all) is scratch here.
    let scratch = out.join(format!(
        ".scratch-{}-{}-{seed}.mcap",
        kind.task_name(),
        kind.variation_name()
    ));
    let mut recorder =
        EpisodeRecorder::create(&scratch, &BTreeMap::new()).map_err(|e| err(format!("{e}")))?;
    let plan = task.expert_plan(expert);
    let mut expert = RecordingExpert {
        inner: ScriptedExpert::new(plan.executed),
        labels: plan.recorded,
        steps: Vec::new(),
    };
    let report = run_sim_episode(
        cfg,
        &mut cell,
        &mut expert,
        &mut recorder,
        interrupt,
        clock.as_ref(),
        seed,
    );
    cell.controller.shutdown();
    let _ = fs::remove_file(&scratch);
    Ok((report.outcome, expert.steps))
}

#[cfg(test)]
mod tests {
    #![allow(clippy::unwrap_used)] // tests may unwrap (CONVENTIONS 6)
    use super::*;

    /// An episode's shard is the same bytes whichever process writes it (the metadata's
    /// hash order is sorted away), and reads back to the same episode.
    #[test]
    fn a_shard_is_the_same_bytes_every_time() {
        let kind = TaskKind::parse("pick_fruit/plum").unwrap();
        let step = DemoStep {
            cloud_xyz: vec![[0.5, 0.1, 0.02], [0.45, -0.1, 0.03]],
            cloud_rgb: vec![[200, 10, 10], [0, 0, 0]],
            joints: [0.0, -1.2, 1.4, -1.8, -1.57, 0.3],
            gripper_width: 0.085,
            gripper_open: true,
            keyframe: Keyframe {
                base_from_tcp: cell_types::Transform::from_xyz_rpy(
                    [0.5, 0.1, 0.1],
                    [std::f64::consts::PI, 0.0, 0.2],
                ),
                gripper_open: false,
                ignore_collisions: false,
            },
        };
        let first = shard_bytes(kind, 7, std::slice::from_ref(&step)).unwrap();
        for _ in 0..8 {
            assert!(shard_bytes(kind, 7, std::slice::from_ref(&step)).unwrap() == first);
        }
        let dir = std::env::temp_dir().join(format!("equact_shard_{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let file = dir.join("seed_000007.safetensors");
        std::fs::write(&file, &first).unwrap();
        let back = read_shard(&file).unwrap();
        assert_eq!(back.steps.len(), 1);
        assert_eq!(back.steps[0].keyframe, step.keyframe);
        assert_eq!(back.steps[0].cloud_xyz, step.cloud_xyz);
        std::fs::remove_dir_all(&dir).unwrap();
    }

    /// A speed the simulator cannot run is refused, named, before anything is written.
    #[test]
    fn a_speed_the_simulator_cannot_run_is_refused_before_anything_is_written() {
        let dir = std::env::temp_dir().join(format!("equact-demos-speed-{}", std::process::id()));
        let _ = fs::remove_dir_all(&dir);
        let cfg = CellConfig::simulated().unwrap();
        let stop = Arc::new(AtomicBool::new(false));
        for speed in [0.0, -1.0, f64::NAN, 100.0] {
            let plan = EpisodePlan {
                kinds: vec![TaskKind::parse("pick_fruit/plum").unwrap()],
                episodes: 1,
                seed: 0,
                sim_speed: speed,
            };
            let err = collect(&cfg, &plan, &dir, &ExpertSettings::default(), &stop).unwrap_err();
            assert!(matches!(err, DemosError::SimSpeed(_)), "{speed}: {err}");
            assert!(err.to_string().contains("clock speed"), "{err}");
            assert!(err.to_string().contains("at most 16 times"), "{err}");
            assert!(!dir.exists());
        }
    }

    #[test]
    fn a_dataset_keeps_one_perception_setting_and_old_indexes_read_as_plain() {
        let dir = std::env::temp_dir().join(format!("equact-demos-perc-{}", std::process::id()));
        fs::create_dir_all(&dir).unwrap();
        // An index from before the field: plain sampling.
        let old = r#"{"format": "equact-demos/1", "episodes": [{"task":
            "install_toilet_roll/large", "instruction": "install the large toilet roll",
            "seed": 0, "outcome": "plan_failed", "steps": 1, "file": null}]}"#;
        fs::write(dir.join("index.json"), old).unwrap();
        let index = Index::load(&dir).unwrap();
        assert_eq!(index.perception, PerceptionSection::default());
        // Resuming it with denser sampling near the gripper would mix two kinds of cloud.
        let mut cfg = CellConfig::simulated().unwrap();
        cfg.perception.gripper_points = 256;
        let plan = EpisodePlan {
            kinds: vec![TaskKind::parse("install_toilet_roll/large").unwrap()],
            episodes: 1,
            seed: 0,
            sim_speed: 1.0,
        };
        let stop = Arc::new(AtomicBool::new(false));
        let err = collect(&cfg, &plan, &dir, &ExpertSettings::default(), &stop).unwrap_err();
        match &err {
            DemosError::PerceptionMismatch { recorded, cell, .. } => {
                assert_eq!(recorded.gripper_points, 0);
                assert_eq!(cell.gripper_points, 256);
            }
            other => panic!("expected a perception mismatch, got {other}"),
        }
        assert!(err.to_string().contains("gripper_points = 256"), "{err}");
        // So would fewer points, or a focus box raised off the table.
        for change in [
            |c: &mut CellConfig| c.perception.points = 1024,
            |c: &mut CellConfig| c.perception.focus_above_table_m = Some(0.01),
        ] {
            let mut cfg = CellConfig::simulated().unwrap();
            change(&mut cfg);
            let err = collect(&cfg, &plan, &dir, &ExpertSettings::default(), &stop).unwrap_err();
            assert!(
                matches!(err, DemosError::PerceptionMismatch { .. }),
                "{err}"
            );
        }
        // Training or scoring a network that samples near the gripper on these clouds is
        // refused; on clouds recorded densely enough it is not.
        let network = policy::builtin::config().with_near_gripper_points(48);
        let err = crate::train::check_dataset_perception(
            &Index::load(&dir).unwrap().perception,
            &dir,
            &network,
        )
        .unwrap_err();
        assert!(err.to_string().contains("gripper_points"), "{err}");
        let mut index = Index::load(&dir).unwrap();
        index.perception.gripper_points = 256;
        index.save(&dir).unwrap();
        assert_eq!(Index::load(&dir).unwrap().perception, index.perception);
        assert!(crate::train::check_dataset_perception(&index.perception, &dir, &network).is_ok());
        assert!(crate::train::check_dataset_perception(
            &index.perception,
            &dir,
            &policy::builtin::config()
        )
        .is_ok());
        // A network reading more points than the clouds hold is refused too.
        index.perception.points = 512;
        index.save(&dir).unwrap();
        assert_eq!(Index::load(&dir).unwrap().perception, index.perception);
        let err = crate::train::check_dataset_perception(
            &index.perception,
            &dir,
            &policy::builtin::config(),
        )
        .unwrap_err()
        .to_string();
        assert!(err.contains("[perception] points"), "{err}");
        let _ = fs::remove_dir_all(&dir);
    }

    #[test]
    fn an_expert_mismatch_names_both_experts_and_the_options_that_resume() {
        let centred = ExpertSettings {
            centred_grasp_labels: true,
            ..ExpertSettings::default()
        };
        let err = DemosError::ExpertMismatch {
            path: PathBuf::from("d"),
            recorded: centred,
            asked: ExpertSettings::default(),
        }
        .to_string();
        assert_eq!(
            err,
            "d holds demonstrations recorded by the expert with centred grasp labels, not the \
             plain expert: record into another folder, or pass --grasp-turn 0 \
             --centred-grasp-labels"
        );
    }

    #[test]
    fn an_index_whose_shard_paths_leave_the_dataset_is_refused() {
        let dir = std::env::temp_dir().join(format!("equact-demos-paths-{}", std::process::id()));
        fs::create_dir_all(&dir).unwrap();
        let entry = |file: &str| IndexEntry {
            task: "pick_fruit/peach".into(),
            instruction: "pick the peach".into(),
            seed: 7,
            outcome: "success".into(),
            steps: 2,
            file: Some(file.into()),
        };
        let mut index = Index {
            format: FORMAT.into(),
            episodes: vec![entry("pick_fruit-peach/seed_000007.safetensors")],
            ..Index::default()
        };
        index.save(&dir).unwrap();
        assert_eq!(
            Index::load(&dir).unwrap(),
            index,
            "a relative path inside is kept"
        );
        for bad in [
            "../other/seed_000007.safetensors",
            "/etc/passwd",
            "a/./../../b",
        ] {
            index.episodes[0] = entry(bad);
            index.save(&dir).unwrap();
            let err = Index::load(&dir).unwrap_err();
            assert!(
                matches!(err, DemosError::BadIndex { .. })
                    && err.to_string().contains("pick_fruit/peach seed 7")
                    && err.to_string().contains("a path outside the dataset"),
                "{bad}: {err}"
            );
        }
        let _ = fs::remove_dir_all(&dir);
    }
}
