//! `equact eval`: closed-loop episodes in the simulated cell (policy → planner → UR driver →
//! simulated arm and gripper, at most [`crate::episode::MAX_KEYFRAMES`] keyframes each) over
//! seeded SE(3)-perturbed scenes, and the success-rate table per task variation.
//!
//! Evaluation seeds start at [`EVAL_SEED`] by default, away from the demonstrations' seeds
//! (`equact demos collect` starts at 0), so that a policy is not evaluated on the scenes it
//! was trained on.

use std::collections::BTreeMap;
use std::path::Path;
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::Arc;

use anyhow::Context;
use cell_types::config::CellConfig;
use serde::Serialize;

use crate::episode::{run_sim_episode, KeyframeSource, ScriptedExpert};
use crate::learned::LearnedPolicy;
use crate::recording::EpisodeRecorder;
use crate::sim_cell::{EpisodePlan, SimCell};
use crate::task::world::GripperEvent;
use crate::task::{TaskInstance, TaskKind};

/// First evaluation seed by default (demonstrations use 0, 1, ...).
pub const EVAL_SEED: u64 = 1_000_000;

/// The file in the output folder that gets one JSON line per finished episode
/// ([`EpisodeSummary`]), appended across runs into the same folder.
pub const EPISODE_LOG: &str = "episodes.jsonl";

/// The results of one task variation.
#[derive(Clone, Debug, PartialEq, Serialize)]
pub struct VariationResult {
    /// `task/variation`.
    pub task: String,
    /// Episodes run.
    pub episodes: u64,
    /// Episodes whose success test passed.
    pub successes: u64,
    /// Episodes per outcome label.
    pub outcomes: BTreeMap<&'static str, u64>,
    /// Each episode, in the order run.
    pub runs: Vec<EpisodeSummary>,
}

/// One evaluation episode: what a user analysing a run needs without opening its recording.
#[derive(Clone, Debug, PartialEq, Serialize)]
pub struct EpisodeSummary {
    /// `task/variation`.
    pub task: String,
    /// The scene's seed.
    pub seed: u64,
    /// Outcome label ([`crate::episode::Outcome::label`]).
    pub outcome: &'static str,
    /// Keyframes executed.
    pub steps: usize,
    /// What happened, in words.
    pub detail: String,
    /// What the gripper did to objects: (keyframe, words).
    pub gripper_events: Vec<(usize, String)>,
    /// The same events measured (grasp offsets in the hand, a roll's release against the
    /// spindle): what `equact eval report` tabulates. Absent from logs written before
    /// 2026-12-06.
    pub gripper_measures: Vec<(usize, GripperEvent)>,
    /// The episode's MCAP recording.
    pub recording: std::path::PathBuf,
}

impl VariationResult {
    /// Success rate in [0, 1] (0 with no episode).
    pub fn rate(&self) -> f64 {
        crate::stats::Count {
            successes: self.successes,
            episodes: self.episodes,
        }
        .rate()
    }
}

/// The evaluation of a policy over task variations.
#[derive(Clone, Debug, PartialEq, Serialize)]
pub struct EvalTable {
    /// Which policy ran (`expert`, `learned`).
    pub policy: String,
    /// One row per task variation, in the order run.
    pub rows: Vec<VariationResult>,
}

impl EvalTable {
    /// Successes and episodes per task (all its variations together), in the order run.
    pub fn per_task(&self) -> Vec<(String, u64, u64)> {
        let mut out: Vec<(String, u64, u64)> = Vec::new();
        for r in &self.rows {
            let task = task_name(&r.task).to_string();
            match out.iter_mut().find(|(t, _, _)| *t == task) {
                Some(e) => {
                    e.1 += r.successes;
                    e.2 += r.episodes;
                }
                None => out.push((task, r.successes, r.episodes)),
            }
        }
        out
    }

    /// The table as Markdown (per variation, then per task), each rate with its 95 %
    /// interval: at 20 episodes a rate is known to about ±20 points, which a reader
    /// comparing two models needs beside it.
    pub fn markdown(&self) -> String {
        let mut s = format!(
            "| task/variation ({}) | success | rate | 95 % interval |\n|---|---|---|---|\n",
            self.policy
        );
        let rows = self
            .rows
            .iter()
            .map(|r| (r.task.clone(), r.successes, r.episodes))
            .chain(
                self.per_task()
                    .into_iter()
                    .map(|(task, ok, n)| (format!("**{task}**"), ok, n)),
            );
        for (name, ok, n) in rows {
            let count = crate::stats::Count {
                successes: ok,
                episodes: n,
            };
            s.push_str(&format!(
                "| {name} | {ok}/{n} | {:.0} % | {} |\n",
                100.0 * count.rate(),
                crate::stats::interval_words(ok, n)
            ));
        }
        s
    }
}

/// The task of a `task/variation` name (the name itself when it has no variation).
pub fn task_name(variation: &str) -> &str {
    variation.split('/').next().unwrap_or(variation)
}

/// Hands out the keyframe source of each evaluation episode.
pub trait EpisodePolicy {
    /// The policy's name in the table and the recordings.
    fn name(&self) -> &str;
    /// The source for one episode of variation `kind` on scene `task` with `seed`.
    fn for_episode(
        &mut self,
        kind: TaskKind,
        task: &TaskInstance,
        seed: u64,
    ) -> anyhow::Result<&mut dyn KeyframeSource>;
}

/// The scripted expert, from each scene's true object poses.
#[derive(Default)]
pub struct ExpertEval {
    current: Option<ScriptedExpert>,
}

impl EpisodePolicy for ExpertEval {
    fn name(&self) -> &str {
        "expert"
    }
    fn for_episode(
        &mut self,
        _kind: TaskKind,
        task: &TaskInstance,
        _seed: u64,
    ) -> anyhow::Result<&mut dyn KeyframeSource> {
        Ok(self
            .current
            .insert(ScriptedExpert::new(task.expert_keyframes())))
    }
}

/// The learned policy (loaded once) with each variation's instruction embedding.
pub struct LearnedEval {
    /// The network.
    pub policy: LearnedPolicy,
    /// One embedding per variation evaluated.
    pub embeddings: Vec<(TaskKind, policy::predict::InstructionEmbedding)>,
}

impl EpisodePolicy for LearnedEval {
    fn name(&self) -> &str {
        "learned"
    }
    fn for_episode(
        &mut self,
        kind: TaskKind,
        _task: &TaskInstance,
        seed: u64,
    ) -> anyhow::Result<&mut dyn KeyframeSource> {
        let embedding = self
            .embeddings
            .iter()
            .find(|(k, _)| *k == kind)
            .map(|(_, e)| e.clone())
            .with_context(|| format!("no instruction embedding for {}", kind.name()))?;
        self.policy.set_instruction(embedding);
        self.policy.set_seed(seed);
        Ok(&mut self.policy)
    }
}

/// Runs the evaluation: for each variation and seed, a fresh simulated cell and the
/// policy's source for that episode; recordings go to `out`, and one JSON line per finished
/// episode to `out`/[`EPISODE_LOG`].
/// Progress lines go to `progress`. Ctrl-C (`interrupt`) stops after the current episode
/// (its arm stopped, its recording finished) and returns the table so far.
pub fn evaluate(
    cfg: &CellConfig,
    plan: &EpisodePlan,
    policy: &mut dyn EpisodePolicy,
    out: &Path,
    interrupt: &Arc<AtomicBool>,
    progress: &mut dyn FnMut(&str),
) -> anyhow::Result<EvalTable> {
    plan.clock().context("the simulator's speed")?;
    std::fs::create_dir_all(out).with_context(|| format!("creating {}", out.display()))?;
    let log_path = out.join(EPISODE_LOG);
    let policy_name = policy.name().to_string();
    let mut table = EvalTable {
        policy: policy_name.clone(),
        rows: Vec::new(),
    };
    let total = plan.episodes * plan.kinds.len() as u64;
    let mut done = 0;
    for &kind in &plan.kinds {
        let mut row = VariationResult {
            task: kind.name(),
            episodes: 0,
            successes: 0,
            outcomes: BTreeMap::new(),
            runs: Vec::new(),
        };
        for e in 0..plan.episodes {
            if interrupt.load(Ordering::SeqCst) {
                break;
            }
            let seed = plan.seed + e;
            let clock = plan.clock()?;
            let task = TaskInstance::sample(kind, seed, cfg.workspace.table_height);
            let source = policy.for_episode(kind, &task, seed)?;
            let mut cell = SimCell::start(cfg, task, seed, clock.clone())?;
            let path = out.join(format!(
                "{}_{policy_name}_seed{seed}.mcap",
                kind.name().replace('/', "-")
            ));
            let mut meta = BTreeMap::new();
            meta.insert("task".into(), kind.name());
            meta.insert("seed".into(), seed.to_string());
            meta.insert("policy".into(), policy_name.clone());
            meta.insert("purpose".into(), "evaluation".into());
            let mut recorder = EpisodeRecorder::create(&path, &meta)?;
            let report = run_sim_episode(
                cfg,
                &mut cell,
                source,
                &mut recorder,
                interrupt,
                clock.as_ref(),
                seed,
            );
            cell.controller.shutdown();
            done += 1;
            row.episodes += 1;
            let success = report.outcome == crate::episode::Outcome::Success;
            row.successes += u64::from(success);
            *row.outcomes.entry(report.outcome.label()).or_default() += 1;
            // Why an episode failed is the first thing a user asks: say it on the line.
            let why = if success {
                String::new()
            } else {
                format!(
                    ": {}{}",
                    report.detail,
                    gripper_summary(&report.gripper_events)
                )
            };
            progress(&format!(
                "[{done}/{total}] {} seed {seed}: {} after {} keyframes ({}/{} so far){why}",
                kind.name(),
                report.outcome.label(),
                report.steps,
                row.successes,
                row.episodes
            ));
            let summary = EpisodeSummary {
                task: kind.name(),
                seed,
                outcome: report.outcome.label(),
                steps: report.steps,
                detail: report.detail,
                gripper_events: report
                    .gripper_events
                    .iter()
                    .map(|(k, e)| (*k, e.to_string()))
                    .collect(),
                gripper_measures: report.gripper_events,
                recording: report.recording,
            };
            // One line per episode as it ends, so that a long run killed midway keeps what
            // it measured. A failed write (disk full) is reported and the evaluation goes on:
            // the table and the recordings still hold the episode.
            if let Err(e) = append_json_line(&log_path, &summary) {
                progress(&format!("warning: {e:#}"));
            }
            row.runs.push(summary);
        }
        table.rows.push(row);
        if interrupt.load(Ordering::SeqCst) {
            break;
        }
    }
    Ok(table)
}

/// Appends `value` as one JSON line to `path` (created if missing).
fn append_json_line(path: &Path, value: &impl Serialize) -> anyhow::Result<()> {
    use std::io::Write;
    let mut line = serde_json::to_string(value)?;
    line.push('\n');
    std::fs::OpenOptions::new()
        .create(true)
        .append(true)
        .open(path)
        .and_then(|mut f| f.write_all(line.as_bytes()))
        .with_context(|| format!("appending an episode's summary to {}", path.display()))
}

/// Gripper events shown on a failed episode's line: the first grasp, the first release and
/// the first re-grasp usually say why it failed.
const EVENTS_SHOWN: usize = 3;

/// A failed episode's gripper events for its progress line: ` | keyframe K: event` for the
/// first three, then how many more; empty without events.
pub fn gripper_summary(events: &[(usize, impl std::fmt::Display)]) -> String {
    let mut s: String = events
        .iter()
        .take(EVENTS_SHOWN)
        .map(|(k, e)| format!(" | keyframe {k}: {e}"))
        .collect();
    if events.len() > EVENTS_SHOWN {
        s.push_str(&format!(
            " | {} more gripper events",
            events.len() - EVENTS_SHOWN
        ));
    }
    s
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_table_gives_each_rate_its_interval() {
        let row = |task: &str, successes, episodes| VariationResult {
            task: task.into(),
            episodes,
            successes,
            outcomes: BTreeMap::new(),
            runs: Vec::new(),
        };
        let table = EvalTable {
            policy: "learned".into(),
            rows: vec![
                row("install_toilet_roll/large", 5, 20),
                row("install_toilet_roll/small", 3, 20),
            ],
        };
        let md = table.markdown();
        assert!(
            md.contains("| install_toilet_roll/large | 5/20 | 25 % | 11-47 % |"),
            "{md}"
        );
        assert!(
            md.contains("| **install_toilet_roll** | 8/40 | 20 % | 10-35 % |"),
            "{md}"
        );
    }

    #[test]
    fn a_failed_episodes_line_shows_its_first_gripper_events() {
        assert_eq!(gripper_summary(&[] as &[(usize, String)]), "");
        let events: Vec<(usize, String)> = (0..5).map(|k| (2 * k, format!("event {k}"))).collect();
        assert_eq!(gripper_summary(&events[..1]), " | keyframe 0: event 0");
        assert_eq!(
            gripper_summary(&events),
            " | keyframe 0: event 0 | keyframe 2: event 1 | keyframe 4: event 2 | 2 more gripper events"
        );
    }
}
