//! `equact demos merge`: one dataset from several, e.g. the simulated demonstrations of
//! three tasks with another expert's demonstrations of the fourth, or simulated ones with
//! those recorded on the real cell. The sources are read, never changed; every shard is
//! checked and copied, so the new dataset stands on its own.

use std::collections::HashMap;
use std::fs;
use std::path::{Path, PathBuf};

use super::{expert_words, io, parse_shard, write_atomic, DemosError, Index, IndexEntry};
use crate::task::{ExpertSettings, TaskKind};

/// Episodes of one task variation that a later source replaced.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct Replacement {
    /// `task/variation`.
    pub task: String,
    /// How many of its episodes (seeds).
    pub episodes: usize,
    /// The source they came from.
    pub earlier: PathBuf,
    /// The source whose episodes of the same seeds took their place.
    pub later: PathBuf,
}

/// What [`merge`] wrote.
#[derive(Clone, Debug, Default, PartialEq, Eq)]
pub struct MergeSummary {
    /// Episodes in the new index (failed tries included).
    pub episodes: usize,
    /// Shards copied (the demonstrations).
    pub shards: usize,
    /// Episodes listed by more than one source, per task variation and pair of sources.
    pub replaced: Vec<Replacement>,
}

/// An episode kept so far, with the source it comes from.
struct Kept {
    entry: IndexEntry,
    source: usize,
}

/// Writes into `out` one dataset holding the episodes of every source, in order.
///
/// An episode (task variation and seed) listed by two sources is taken from the later one,
/// unless the later one only failed where the earlier recorded a demonstration. The sources
/// must have sampled their clouds alike, and the experts of the episodes kept must agree
/// where their settings matter (the toilet roll's grasp turn and grasp labels). `out` must
/// not hold a dataset yet; its index is written last, after every shard, so an interrupted
/// merge leaves no index and can be run again.
pub fn merge(sources: &[PathBuf], out: &Path) -> Result<MergeSummary, DemosError> {
    if out.join("index.json").exists() || sources.iter().any(|s| same_dir(s, out)) {
        return Err(DemosError::MergeInto(out.to_path_buf()));
    }
    let mut indexes = Vec::with_capacity(sources.len());
    for src in sources {
        if !src.join("index.json").is_file() {
            return Err(DemosError::NotADataset(src.clone()));
        }
        indexes.push(Index::load(src)?);
    }
    let (Some(first), Some(first_index)) = (sources.first(), indexes.first()) else {
        return Ok(MergeSummary::default());
    };
    for (src, index) in sources.iter().zip(&indexes).skip(1) {
        if index.perception != first_index.perception {
            return Err(DemosError::MergeMismatch {
                first: first.clone(),
                other: src.clone(),
                why: format!(
                    "its clouds were sampled with [perception] {}, the first's with {}",
                    index.perception, first_index.perception
                ),
            });
        }
    }

    let mut kept: Vec<Kept> = Vec::new();
    let mut at: HashMap<(String, u64), usize> = HashMap::new();
    let mut replaced: Vec<Replacement> = Vec::new();
    for (source, index) in indexes.iter().enumerate() {
        for entry in &index.episodes {
            let key = (entry.task.clone(), entry.seed);
            let Some(&i) = at.get(&key) else {
                at.insert(key, kept.len());
                kept.push(Kept {
                    entry: entry.clone(),
                    source,
                });
                continue;
            };
            // A failed try does not push out a demonstration.
            if entry.file.is_none() && kept[i].entry.file.is_some() {
                continue;
            }
            let earlier = kept[i].source;
            match replaced.iter_mut().find(|r| {
                r.task == entry.task && r.earlier == sources[earlier] && r.later == sources[source]
            }) {
                Some(r) => r.episodes += 1,
                None => replaced.push(Replacement {
                    task: entry.task.clone(),
                    episodes: 1,
                    earlier: sources[earlier].clone(),
                    later: sources[source].clone(),
                }),
            }
            kept[i] = Kept {
                entry: entry.clone(),
                source,
            };
        }
    }

    let expert = kept_expert(sources, &indexes, &kept)?;
    check_shard_paths(sources, &kept)?;
    fs::create_dir_all(out).map_err(io(out))?;
    let mut shards = 0;
    for k in &kept {
        let Some(file) = &k.entry.file else { continue };
        let from = sources[k.source].join(file);
        let bytes = fs::read(&from).map_err(io(&from))?;
        let demo = parse_shard(&from, &bytes)?;
        let meta = |key: &str| demo.metadata.get(key).map(String::as_str).unwrap_or("?");
        let shard_task = format!("{}/{}", meta("task"), meta("variation"));
        if shard_task != k.entry.task || meta("seed") != k.entry.seed.to_string() {
            return Err(DemosError::BadShard {
                path: from,
                why: format!(
                    "it holds {shard_task} seed {}, but the index lists it for {} seed {}",
                    meta("seed"),
                    k.entry.task,
                    k.entry.seed
                ),
            });
        }
        let to = out.join(file);
        if let Some(dir) = to.parent() {
            fs::create_dir_all(dir).map_err(io(dir))?;
        }
        write_atomic(&to, &bytes)?;
        shards += 1;
    }
    let index = Index {
        format: first_index.format.clone(),
        episodes: kept.into_iter().map(|k| k.entry).collect(),
        perception: first_index.perception.clone(),
        expert,
    };
    index.save(out)?;
    Ok(MergeSummary {
        episodes: index.episodes.len(),
        shards,
        replaced,
    })
}

/// The expert settings of the merged dataset: those of the sources whose kept episodes they
/// change, which must agree; the plain expert's where they change none.
fn kept_expert(
    sources: &[PathBuf],
    indexes: &[Index],
    kept: &[Kept],
) -> Result<ExpertSettings, DemosError> {
    let mut setter: Option<usize> = None;
    for k in kept {
        let kind = TaskKind::parse(&k.entry.task).map_err(|e| DemosError::BadIndex {
            path: sources[k.source].join("index.json"),
            why: format!("episode {} seed {}: {e}", k.entry.task, k.entry.seed),
        })?;
        if !ExpertSettings::apply_to(kind) {
            continue;
        }
        let this = &indexes[k.source].expert;
        match setter {
            None => setter = Some(k.source),
            Some(s) if indexes[s].expert == *this => {}
            Some(s) => {
                return Err(DemosError::MergeMismatch {
                    first: sources[s].clone(),
                    other: sources[k.source].clone(),
                    why: format!(
                        "its {} episodes were recorded by {}, the other's by {}",
                        k.entry.task,
                        expert_words(this),
                        expert_words(&indexes[s].expert)
                    ),
                })
            }
        }
    }
    Ok(setter.map(|s| indexes[s].expert).unwrap_or_default())
}

/// Whether two paths name the same folder (both resolved where they exist).
fn same_dir(a: &Path, b: &Path) -> bool {
    match (a.canonicalize(), b.canonicalize()) {
        (Ok(a), Ok(b)) => a == b,
        _ => a == b,
    }
}

/// Refuses, before anything is copied, kept episodes whose shard paths would collide in the
/// merged dataset (`Index::load` already refused paths that leave their dataset).
fn check_shard_paths(sources: &[PathBuf], kept: &[Kept]) -> Result<(), DemosError> {
    let mut named: HashMap<&str, &IndexEntry> = HashMap::new();
    for k in kept {
        let Some(file) = &k.entry.file else { continue };
        // Two sources may name different episodes' shards alike: one would overwrite the other.
        if let Some(other) = named.insert(file, &k.entry) {
            return Err(DemosError::BadIndex {
                path: sources[k.source].join("index.json"),
                why: format!(
                    "episode {} seed {} names its shard {file:?}, as another source's {} seed {} \
                     does; rename one of them and its index entry",
                    k.entry.task, k.entry.seed, other.task, other.seed
                ),
            });
        }
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    #![allow(clippy::unwrap_used)] // tests may unwrap (CONVENTIONS 6)
    use super::*;
    use crate::demos::{read_shard, shard_bytes, shard_name, DemoStep};
    use cell_types::config::PerceptionSection;
    use cell_types::{Keyframe, Transform};
    use nalgebra::{UnitQuaternion, Vector3};

    /// A dataset in `dir` with one-step episodes: (task, seed, succeeded); the step's
    /// gripper width is `width`, so shards from different sources differ.
    fn dataset(
        dir: &Path,
        perception: PerceptionSection,
        expert: ExpertSettings,
        width: f64,
        episodes: &[(&str, u64, bool)],
    ) {
        let _ = fs::remove_dir_all(dir);
        let mut index = Index {
            format: crate::demos::FORMAT.into(),
            perception,
            expert,
            ..Index::default()
        };
        for &(task, seed, ok) in episodes {
            let kind = TaskKind::parse(task).unwrap();
            let file = ok.then(|| shard_name(kind, seed));
            if let Some(f) = &file {
                let step = DemoStep {
                    cloud_xyz: vec![[0.1, 0.2, 0.3]; 4],
                    cloud_rgb: vec![[1, 2, 3]; 4],
                    joints: [0.0, -1.5, 1.5, 0.0, 1.5, 0.0],
                    gripper_width: width,
                    gripper_open: true,
                    keyframe: Keyframe {
                        base_from_tcp: Transform::from_parts(
                            Vector3::new(0.4, 0.1, seed as f64 * 0.01),
                            UnitQuaternion::identity(),
                        ),
                        gripper_open: false,
                        ignore_collisions: false,
                    },
                };
                let path = dir.join(f);
                fs::create_dir_all(path.parent().unwrap()).unwrap();
                fs::write(&path, shard_bytes(kind, seed, &[step]).unwrap()).unwrap();
            }
            index.episodes.push(IndexEntry {
                task: kind.name(),
                instruction: kind.instruction(),
                seed,
                outcome: if ok { "success" } else { "plan_failed" }.into(),
                steps: 1,
                file,
            });
        }
        fs::create_dir_all(dir).unwrap();
        index.save(dir).unwrap();
    }

    #[test]
    fn merged_datasets_keep_every_demonstration_and_refuse_to_mix_experts_or_clouds() {
        let root = std::env::temp_dir().join(format!("equact-demos-merge-{}", std::process::id()));
        let _ = fs::remove_dir_all(&root);
        let (a, b, out) = (root.join("a"), root.join("b"), root.join("out"));
        let turned = ExpertSettings {
            grasp_turn_deg: 10.0,
            ..ExpertSettings::default()
        };
        let (fruit, roll) = ("pick_fruit/peach", "install_toilet_roll/large");
        let plain = ExpertSettings::default();
        let sampling = PerceptionSection::default();
        dataset(
            &a,
            sampling.clone(),
            plain,
            0.085,
            &[
                (fruit, 0, true),
                (fruit, 1, true),
                (roll, 0, true),
                (roll, 1, false),
            ],
        );
        dataset(
            &b,
            sampling.clone(),
            turned,
            0.05,
            &[(roll, 0, true), (roll, 1, true), (fruit, 1, false)],
        );

        let s = merge(&[a.clone(), b.clone()], &out).unwrap();
        assert_eq!((s.episodes, s.shards), (4, 4));
        // B's roll episodes replace A's (a demonstration replaces a failed try too); B's
        // failed fruit try does not push out A's demonstration.
        assert_eq!(
            s.replaced,
            vec![Replacement {
                task: roll.into(),
                episodes: 2,
                earlier: a.clone(),
                later: b.clone(),
            }]
        );
        let index = Index::load(&out).unwrap();
        assert_eq!(index.expert, turned, "the kept roll episodes are B's");
        assert_eq!(index.perception, sampling);
        let widths: Vec<(String, u64, f64)> = index
            .episodes
            .iter()
            .map(|e| {
                let demo = read_shard(&out.join(e.file.as_ref().unwrap())).unwrap();
                (e.task.clone(), e.seed, demo.steps[0].gripper_width)
            })
            .collect();
        assert_eq!(
            widths,
            vec![
                (fruit.into(), 0, 0.085),
                (fruit.into(), 1, 0.085),
                (roll.into(), 0, 0.05),
                (roll.into(), 1, 0.05),
            ]
        );
        // The copy is the source's file, byte for byte.
        let f = shard_name(TaskKind::parse(roll).unwrap(), 1);
        assert_eq!(
            fs::read(out.join(&f)).unwrap(),
            fs::read(b.join(&f)).unwrap()
        );

        // The other order keeps A's plain roll demonstration of seed 0 beside B's turned one
        // of seed 1 (A only failed it): two experts' roll episodes, refused before anything
        // is written.
        let out2 = root.join("out2");
        let err = merge(&[b.clone(), a.clone()], &out2).unwrap_err();
        assert!(matches!(err, DemosError::MergeMismatch { .. }), "{err}");
        let text = err.to_string();
        assert!(
            text.contains("recorded by the expert with grasp turns up to 10°")
                && text.contains("the other's by the plain expert")
                && text.contains(roll),
            "{text}"
        );
        assert!(!out2.exists());
        // Fruit-only datasets do not care about the roll expert.
        let c = root.join("c");
        dataset(&c, sampling.clone(), turned, 0.07, &[(fruit, 7, true)]);
        let out3 = root.join("out3");
        let s = merge(&[a.clone(), c.clone()], &out3).unwrap();
        assert_eq!((s.episodes, s.shards), (5, 4));
        assert_eq!(Index::load(&out3).unwrap().expert, plain);

        // Clouds sampled another way cannot join.
        let d = root.join("d");
        let denser = PerceptionSection {
            gripper_points: 256,
            ..PerceptionSection::default()
        };
        dataset(&d, denser, plain, 0.07, &[(fruit, 8, true)]);
        let err = merge(&[a.clone(), d.clone()], &root.join("out4")).unwrap_err();
        assert!(
            matches!(err, DemosError::MergeMismatch { .. })
                && err.to_string().contains("gripper_points = 256"),
            "{err}"
        );

        // A shard that is not the episode its index entry names is refused.
        let e = root.join("e");
        dataset(&e, sampling.clone(), plain, 0.07, &[(fruit, 3, true)]);
        let mut index = Index::load(&e).unwrap();
        index.episodes[0].seed = 4;
        index.save(&e).unwrap();
        let err = merge(std::slice::from_ref(&e), &root.join("out5")).unwrap_err();
        assert!(
            matches!(err, DemosError::BadShard { .. })
                && err.to_string().contains("holds pick_fruit/peach seed 3")
                && err
                    .to_string()
                    .contains("lists it for pick_fruit/peach seed 4"),
            "{err}"
        );

        // Nor one whose index points outside its dataset.
        let mut index = Index::load(&e).unwrap();
        index.episodes[0].seed = 3;
        index.episodes[0].file = Some("../a/index.json".into());
        index.save(&e).unwrap();
        let err = merge(std::slice::from_ref(&e), &root.join("out_outside")).unwrap_err();
        assert!(
            matches!(err, DemosError::BadIndex { .. })
                && err.to_string().contains("a path outside the dataset"),
            "{err}"
        );
        assert!(
            !root.join("out_outside").exists(),
            "refused before anything is written"
        );

        // Nor two sources whose different episodes name the same shard.
        let f = root.join("f");
        dataset(&f, sampling.clone(), plain, 0.07, &[(fruit, 9, true)]);
        let mut index = Index::load(&f).unwrap();
        index.episodes[0].file = Some(shard_name(TaskKind::parse(fruit).unwrap(), 0));
        index.save(&f).unwrap();
        let err = merge(&[a.clone(), f.clone()], &root.join("out7")).unwrap_err();
        assert!(
            matches!(err, DemosError::BadIndex { .. })
                && err.to_string().contains("pick_fruit/peach seed 0 does"),
            "{err}"
        );
        assert!(
            !root.join("out7").exists(),
            "refused before anything is written"
        );

        // Nothing is written over a dataset or into a source; a folder without an index is
        // not a dataset.
        let err = merge(std::slice::from_ref(&a), &out).unwrap_err();
        assert!(matches!(err, DemosError::MergeInto(_)), "{err}");
        let err = merge(&[a.clone(), root.join(".").join("b")], &b).unwrap_err();
        assert!(matches!(err, DemosError::MergeInto(_)), "{err}");
        let err = merge(&[a.clone(), root.join("none")], &root.join("out6")).unwrap_err();
        assert!(matches!(err, DemosError::NotADataset(_)), "{err}");
        let _ = fs::remove_dir_all(&root);
    }
}
