//! `equact eval report`: what evaluation logs (`episodes.jsonl`, [`crate::eval::EPISODE_LOG`])
//! say together, without re-running an episode: outcomes per task variation, and for the
//! toilet roll each episode's first release against how far along the pads the roll was
//! held. That table is why the roll fails: a roll held off-centre is let go off the
//! spindle's axis, beyond the hole's play, and falls off the holder.
//!
//! Logs are read as written, one JSON line per episode; lines from before the gripper
//! events were measured (2026-12-06) count in the outcomes but not in the roll table. Every
//! line counts, also the same seed evaluated twice into one folder.

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};

use anyhow::Context;
use serde::{Deserialize, Serialize};

use crate::eval::{EpisodeSummary, EvalTable, EPISODE_LOG};
use crate::task::toilet_roll::{RollRelease, HOLE_PLAY_MM};
use crate::task::world::GripperEvent;
use crate::task::ReleaseOutcome;

/// One episode's line of an evaluation log, as far as the report reads it.
#[derive(Clone, Debug, Deserialize)]
pub struct LoggedEpisode {
    /// `task/variation`.
    pub task: String,
    /// The scene's seed.
    pub seed: u64,
    /// Outcome label (`success`, `task_lost`, ...).
    pub outcome: String,
    /// The gripper events, measured; `None` in a log written before they were.
    #[serde(default)]
    pub gripper_measures: Option<Vec<(usize, GripperEvent)>>,
}

impl LoggedEpisode {
    /// Whether the episode's success test passed.
    pub fn succeeded(&self) -> bool {
        self.outcome == "success"
    }

    /// The first release of a toilet roll and the grasp that carried it (the last grasp of
    /// the same body before it): `None` without measurements or without such a release.
    pub fn first_roll_release(&self) -> Option<(f64, RollRelease)> {
        let events = self.gripper_measures.as_ref()?;
        let mut held: BTreeMap<&str, f64> = BTreeMap::new();
        for (_, e) in events {
            match e {
                GripperEvent::Grasped {
                    body, site_in_tcp, ..
                } => {
                    held.insert(body, site_in_tcp.y * 1e3);
                }
                GripperEvent::Released {
                    body,
                    outcome: ReleaseOutcome::Roll(r),
                } => return held.get(body.as_str()).map(|along| (*along, *r)),
                GripperEvent::Released { .. } => {}
            }
        }
        None
    }
}

impl From<&EpisodeSummary> for LoggedEpisode {
    /// An episode just run, as its log line reads back.
    fn from(e: &EpisodeSummary) -> Self {
        Self {
            task: e.task.clone(),
            seed: e.seed,
            outcome: e.outcome.to_string(),
            gripper_measures: Some(e.gripper_measures.clone()),
        }
    }
}

/// Reads every `episodes.jsonl` under `dirs` (each a folder `equact eval --out` wrote, or
/// the log file itself), in order.
pub fn read_logs(dirs: &[PathBuf]) -> anyhow::Result<Vec<LoggedEpisode>> {
    if dirs.is_empty() {
        anyhow::bail!("no evaluation folder given: name one or more `equact eval --out` folders");
    }
    let mut out = Vec::new();
    for d in dirs {
        let path = if d.is_dir() {
            d.join(EPISODE_LOG)
        } else {
            d.clone()
        };
        out.extend(read_log(&path)?);
    }
    Ok(out)
}

/// The episodes of one log file; a line that is not an episode's summary is an error
/// naming the file and line (no silent skip: the counts would be wrong).
fn read_log(path: &Path) -> anyhow::Result<Vec<LoggedEpisode>> {
    let text = std::fs::read_to_string(path).with_context(|| {
        format!(
            "reading the evaluation log {} (is it a folder `equact eval --out` wrote?)",
            path.display()
        )
    })?;
    text.lines()
        .enumerate()
        .filter(|(_, l)| !l.trim().is_empty())
        .map(|(i, l)| {
            serde_json::from_str(l).with_context(|| {
                format!(
                    "{} line {}: not an episode summary of `equact eval`",
                    path.display(),
                    i + 1
                )
            })
        })
        .collect()
}

/// Outcomes of one task variation over the logs.
#[derive(Clone, Debug, PartialEq, Serialize)]
pub struct VariationCount {
    /// `task/variation`.
    pub task: String,
    /// Episodes logged.
    pub episodes: u64,
    /// Of them, successes.
    pub successes: u64,
    /// Episodes per outcome label.
    pub outcomes: BTreeMap<String, u64>,
}

/// Bounds of the roll table's rows: how far along the pads the roll was held (mm).
pub const ALONG_PADS_BINS_MM: [f64; 4] = [2.0, 4.0, 7.0, 10.0];

/// Toilet-roll episodes whose grasps held the roll this far along the pads from its centre.
#[derive(Clone, Debug, PartialEq, Serialize)]
pub struct GraspRow {
    /// Lower bound of |offset along the pads| (mm), inclusive.
    pub from_mm: f64,
    /// Upper bound (mm), exclusive; `None`: no bound.
    pub to_mm: Option<f64>,
    /// Episodes in the row.
    pub episodes: u64,
    /// Median distance of the first release from the spindle's axis (mm).
    pub median_off_axis_mm: Option<f64>,
    /// First releases within the hole's play of the axis.
    pub within_play: u64,
    /// Episodes whose roll was installed.
    pub installed: u64,
}

/// Installed rolls among first releases on one side of the hole's play.
#[derive(Clone, Copy, Debug, Default, PartialEq, Serialize)]
pub struct Installed {
    /// First releases.
    pub releases: u64,
    /// Of them, episodes that installed the roll.
    pub installed: u64,
}

/// The toilet roll's first releases against the grasp that carried them.
#[derive(Clone, Debug, PartialEq, Serialize)]
pub struct RollTable {
    /// Toilet-roll episodes logged.
    pub episodes: u64,
    /// Of them, logged before the gripper events were measured.
    pub unmeasured: u64,
    /// Of them, measured but without a grasp and a release of the roll.
    pub without_release: u64,
    /// Quartiles of |offset along the pads| of the grasps that carried the first releases
    /// (mm); `None` without one.
    pub along_pads_quartiles_mm: Option<[f64; 3]>,
    /// One row per [`ALONG_PADS_BINS_MM`] band.
    pub by_grasp: Vec<GraspRow>,
    /// First releases within the hole's play of the spindle's axis.
    pub within_play: Installed,
    /// First releases further off.
    pub beyond_play: Installed,
}

/// What the logs say.
#[derive(Clone, Debug, PartialEq, Serialize)]
pub struct EvalReport {
    /// Outcomes per task variation, in the order first logged.
    pub variations: Vec<VariationCount>,
    /// The toilet-roll table; `None` without a toilet-roll episode.
    pub roll: Option<RollTable>,
}

impl EvalReport {
    /// The report over `episodes`.
    pub fn of(episodes: &[LoggedEpisode]) -> Self {
        let mut variations: Vec<VariationCount> = Vec::new();
        for e in episodes {
            let i = match variations.iter().position(|v| v.task == e.task) {
                Some(i) => i,
                None => {
                    variations.push(VariationCount {
                        task: e.task.clone(),
                        episodes: 0,
                        successes: 0,
                        outcomes: BTreeMap::new(),
                    });
                    variations.len() - 1
                }
            };
            let v = &mut variations[i];
            v.episodes += 1;
            v.successes += u64::from(e.succeeded());
            *v.outcomes.entry(e.outcome.clone()).or_default() += 1;
        }
        let rolls: Vec<&LoggedEpisode> = episodes
            .iter()
            .filter(|e| e.task.starts_with("install_toilet_roll"))
            .collect();
        let roll = (!rolls.is_empty()).then(|| roll_table(&rolls));
        Self { variations, roll }
    }

    /// The report over the episodes of an evaluation just run.
    pub fn of_table(table: &EvalTable) -> Self {
        let episodes: Vec<LoggedEpisode> = table
            .rows
            .iter()
            .flat_map(|r| r.runs.iter().map(LoggedEpisode::from))
            .collect();
        Self::of(&episodes)
    }

    /// The report as Markdown tables.
    pub fn markdown(&self) -> String {
        let mut s = String::from(
            "| task/variation | success | 95 % interval | outcomes |\n|---|---|---|---|\n",
        );
        for v in &self.variations {
            let outcomes: Vec<String> =
                v.outcomes.iter().map(|(k, n)| format!("{k} {n}")).collect();
            s.push_str(&format!(
                "| {} | {}/{} | {} | {} |\n",
                v.task,
                v.successes,
                v.episodes,
                crate::stats::interval_words(v.successes, v.episodes),
                outcomes.join(", ")
            ));
        }
        s.push_str(&self.roll_markdown());
        s
    }

    /// The toilet-roll part of [`EvalReport::markdown`], starting with a blank line; empty
    /// without a toilet-roll episode.
    pub fn roll_markdown(&self) -> String {
        let mut s = String::new();
        let Some(r) = &self.roll else { return s };
        let measured = r.episodes - r.unmeasured - r.without_release;
        if measured == 0 {
            s.push_str(&format!(
                "\nToilet roll: no release to tabulate (of its episodes, {} logged before gripper \
                 measurements, {} without a grasp and release of the roll); evaluations since \
                 2026-12-06 log them.\n",
                r.unmeasured, r.without_release
            ));
            return s;
        }
        s.push_str(&format!(
            "\nToilet roll: the first release against the grasp that carried it ({measured} of {} \
             episodes; {} logged before gripper measurements, {} without a grasp and release of \
             the roll).\n\n",
            r.episodes, r.unmeasured, r.without_release
        ));
        if let Some([q1, q2, q3]) = r.along_pads_quartiles_mm {
            s.push_str(&format!(
                "Held along the pads (quartiles): {q1:.1}, {q2:.1}, {q3:.1} mm.\n\n"
            ));
        }
        s.push_str(&format!(
            "| held along the pads | episodes | let go off the spindle's axis (median) | within \
             the {HOLE_PLAY_MM:.0} mm play | installed |\n|---|---|---|---|---|\n"
        ));
        for row in &r.by_grasp {
            let band = match row.to_mm {
                Some(to) if row.from_mm == 0.0 => format!("< {to:.0} mm"),
                Some(to) => format!("{:.0}-{to:.0} mm", row.from_mm),
                None => format!("≥ {:.0} mm", row.from_mm),
            };
            let median = row
                .median_off_axis_mm
                .map_or("-".to_string(), |m| format!("{m:.1} mm"));
            s.push_str(&format!(
                "| {band} | {} | {median} | {} | {} |\n",
                row.episodes, row.within_play, row.installed
            ));
        }
        s.push_str(&format!(
            "\nFirst releases within {HOLE_PLAY_MM:.0} mm of the axis: {} of {} installed; further \
             off: {} of {}.\n",
            r.within_play.installed,
            r.within_play.releases,
            r.beyond_play.installed,
            r.beyond_play.releases
        ));
        s
    }
}

/// The roll table over toilet-roll episodes.
fn roll_table(rolls: &[&LoggedEpisode]) -> RollTable {
    let mut table = RollTable {
        episodes: rolls.len() as u64,
        unmeasured: 0,
        without_release: 0,
        along_pads_quartiles_mm: None,
        by_grasp: Vec::new(),
        within_play: Installed::default(),
        beyond_play: Installed::default(),
    };
    let mut measured: Vec<(f64, RollRelease, bool)> = Vec::new();
    for e in rolls {
        if e.gripper_measures.is_none() {
            table.unmeasured += 1;
            continue;
        }
        match e.first_roll_release() {
            Some((along, r)) => measured.push((along.abs(), r, e.succeeded())),
            None => table.without_release += 1,
        }
    }
    let mut along: Vec<f64> = measured.iter().map(|(a, _, _)| *a).collect();
    table.along_pads_quartiles_mm = quartiles(&mut along);
    for (_, r, ok) in &measured {
        let side = if r.off_axis_mm < HOLE_PLAY_MM {
            &mut table.within_play
        } else {
            &mut table.beyond_play
        };
        side.releases += 1;
        side.installed += u64::from(*ok);
    }
    let mut from = 0.0;
    for to in ALONG_PADS_BINS_MM
        .iter()
        .map(|&b| Some(b))
        .chain(std::iter::once(None))
    {
        let in_band: Vec<&(f64, RollRelease, bool)> = measured
            .iter()
            .filter(|(a, _, _)| *a >= from && to.is_none_or(|t| *a < t))
            .collect();
        let mut off: Vec<f64> = in_band.iter().map(|(_, r, _)| r.off_axis_mm).collect();
        table.by_grasp.push(GraspRow {
            from_mm: from,
            to_mm: to,
            episodes: in_band.len() as u64,
            median_off_axis_mm: median(&mut off),
            within_play: off.iter().filter(|&&o| o < HOLE_PLAY_MM).count() as u64,
            installed: in_band.iter().filter(|(_, _, ok)| *ok).count() as u64,
        });
        if let Some(t) = to {
            from = t;
        }
    }
    table
}

/// The median of `v` (sorted in place); `None` when empty or not all finite.
fn median(v: &mut [f64]) -> Option<f64> {
    quantile(v, 0.5)
}

/// The lower quartile, median and upper quartile of `v` (sorted in place); `None` when empty
/// or not all finite.
fn quartiles(v: &mut [f64]) -> Option<[f64; 3]> {
    Some([quantile(v, 0.25)?, quantile(v, 0.5)?, quantile(v, 0.75)?])
}

/// The `q` quantile of `v` (sorted in place), interpolated between the two nearest ranks
/// (numpy's default); `None` when empty or not all finite.
fn quantile(v: &mut [f64], q: f64) -> Option<f64> {
    if v.is_empty() || v.iter().any(|x| !x.is_finite()) {
        return None;
    }
    v.sort_by(f64::total_cmp);
    let at = q * (v.len() - 1) as f64;
    let (lo, hi) = (at.floor() as usize, at.ceil() as usize);
    Some(v[lo] + (v[hi] - v[lo]) * (at - lo as f64))
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::task::toilet_roll::{expert_grasp_offset, HoleFit, Landing, RollSize};
    use crate::task::world::TaskWorld;
    use crate::task::{TaskInstance, TaskKind};
    use nalgebra::{Isometry3, Vector3};

    /// The expert's grasp and release of the roll in seed `seed`'s scene, the release moved
    /// `aside` (m) along the base's y: the gripper events the simulated cell measures.
    fn roll_events(seed: u64, aside: f64) -> (TaskInstance, Vec<(usize, GripperEvent)>) {
        let t = TaskInstance::sample(
            TaskKind::InstallToiletRoll(RollSize::ALL[seed as usize % 2]),
            seed,
            -0.06,
        );
        let keys = t.expert_keyframes();
        let pose = |i: usize| *keys[i].base_from_tcp.isometry();
        let mut w = TaskWorld::new(t.clone());
        assert!(w.before_close(&pose(1)).is_some());
        let grasp = w.after_gripper(&pose(1), true).unwrap();
        let release = Isometry3::translation(0.0, aside, 0.0) * pose(4);
        w.carry(&release);
        let released = w.after_gripper(&release, false).unwrap();
        (t, vec![(1, grasp), (4, released)])
    }

    /// An episode's log line as `equact eval` writes it.
    fn line(task: &str, seed: u64, outcome: &str, events: &[(usize, GripperEvent)]) -> String {
        serde_json::json!({
            "task": task, "seed": seed, "outcome": outcome, "steps": 5, "detail": "",
            "gripper_events": events.iter().map(|(k, e)| (k, e.to_string())).collect::<Vec<_>>(),
            "gripper_measures": events,
            "recording": "x.mcap",
        })
        .to_string()
    }

    #[test]
    fn roll_releases_measured_in_the_cell_survive_the_log_and_fill_the_table() {
        let dir = std::env::temp_dir().join(format!("equact-eval-report-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let mut text = String::new();
        let mut along = Vec::new();
        for seed in 0..6 {
            let (t, events) = roll_events(seed, 0.0);
            along.push(expert_grasp_offset(&t).abs() * 1e3);
            let GripperEvent::Released {
                outcome: ReleaseOutcome::Roll(r),
                ..
            } = &events[1].1
            else {
                panic!("{:?}", events[1])
            };
            assert_eq!(r.landing, Landing::OnSpindle, "seed {seed}");
            text += &line(&t.kind.name(), seed, "success", &events);
            text.push('\n');
        }
        // Let go 15 mm beside the axis: the spindle cuts through the wall, the roll falls.
        let (t, events) = roll_events(6, 0.015);
        let GripperEvent::Released {
            outcome: ReleaseOutcome::Roll(r),
            ..
        } = &events[1].1
        else {
            panic!("{:?}", events[1])
        };
        assert_eq!(r.landing, Landing::OffTheHolder);
        assert!(matches!(r.fit, HoleFit::Inside { off_mm } if off_mm > HOLE_PLAY_MM));
        assert!((r.off_axis_mm - 15.0).abs() < 2.0, "{r:?}");
        let far_along = expert_grasp_offset(&t).abs() * 1e3;
        text += &line(&t.kind.name(), 6, "task_lost", &events);
        // A line from before the measurements, and a fruit.
        text += "\n{\"task\":\"install_toilet_roll/large\",\"seed\":9,\"outcome\":\"task_lost\",\
                 \"steps\":5,\"detail\":\"\",\"gripper_events\":[],\"recording\":\"y.mcap\"}\n";
        text += &line("pick_fruit/plum", 1, "success", &[]);
        text.push('\n');
        std::fs::write(dir.join(EPISODE_LOG), &text).unwrap();

        let episodes = read_logs(std::slice::from_ref(&dir)).unwrap();
        assert_eq!(episodes.len(), 9);
        let report = EvalReport::of(&episodes);
        let count = |task: &str| report.variations.iter().find(|v| v.task == task).unwrap();
        assert_eq!(
            (
                count("pick_fruit/plum").successes,
                count("pick_fruit/plum").episodes
            ),
            (1, 1)
        );
        let large = count("install_toilet_roll/large");
        let small = count("install_toilet_roll/small");
        assert_eq!(large.episodes + small.episodes, 8);
        assert_eq!(large.successes + small.successes, 6);
        let roll = report.roll.as_ref().unwrap();
        assert_eq!(
            (roll.episodes, roll.unmeasured, roll.without_release),
            (8, 1, 0)
        );
        assert_eq!(
            roll.within_play,
            Installed {
                releases: 6,
                installed: 6
            }
        );
        assert_eq!(
            roll.beyond_play,
            Installed {
                releases: 1,
                installed: 0
            }
        );
        // Each episode sits in the band of the expert's drawn offset along the pads.
        for row in &roll.by_grasp {
            let inside = |a: f64| a >= row.from_mm && row.to_mm.is_none_or(|t| a < t);
            let want = along.iter().filter(|&&a| inside(a)).count() as u64;
            let lost = u64::from(inside(far_along));
            assert_eq!(row.episodes, want + lost, "{row:?}");
            assert_eq!(row.installed, want, "{row:?}");
            assert_eq!(row.within_play, want, "{row:?}");
        }
        assert_eq!(roll.by_grasp.len(), ALONG_PADS_BINS_MM.len() + 1);
        let mut all = along.clone();
        all.push(far_along);
        let [q1, q2, q3] = roll.along_pads_quartiles_mm.unwrap();
        let [w1, w2, w3] = quartiles(&mut all).unwrap();
        // The measured grasps are the drawn offsets to well under a micrometre.
        for (got, want) in [(q1, w1), (q2, w2), (q3, w3)] {
            assert!((got - want).abs() < 1e-3, "{got} {want}");
        }
        assert!(q1 <= q2 && q2 <= q3 && q3 <= 6.0, "{q1} {q2} {q3}");
        let md = report.markdown();
        assert!(
            md.contains("(7 of 8 episodes; 1 logged before gripper measurements"),
            "{md}"
        );
        assert!(
            md.contains("within 8 mm of the axis: 6 of 6 installed; further off: 0 of 1"),
            "{md}"
        );
        assert!(md.contains("| ≥ 10 mm | 0 | - | 0 | 0 |"), "{md}");
        // Only unmeasured roll lines: no empty table, a sentence saying why.
        let old: Vec<LoggedEpisode> = episodes.iter().filter(|e| e.seed == 9).cloned().collect();
        let md = EvalReport::of(&old).markdown();
        assert!(
            md.contains("Toilet roll: no release to tabulate (of its episodes, 1 logged before"),
            "{md}"
        );
        assert!(!md.contains("held along the pads"), "{md}");
        // The log file named directly reads the same.
        assert_eq!(read_logs(&[dir.join(EPISODE_LOG)]).unwrap().len(), 9);
        std::fs::remove_dir_all(&dir).unwrap();
    }

    #[test]
    fn the_release_counted_is_the_first_with_the_grasp_that_carried_it() {
        let (_, first) = roll_events(1, 0.2);
        let (_, second) = roll_events(3, 0.0);
        let grasp_along = |e: &GripperEvent| match e {
            GripperEvent::Grasped { site_in_tcp, .. } => site_in_tcp.y * 1e3,
            other => panic!("{other:?}"),
        };
        // A regrasp of another body between does not count; the roll's own last grasp does.
        let other = GripperEvent::Grasped {
            body: "holder".into(),
            site_in_tcp: Vector3::new(0.0, 0.05, 0.0),
            axis_tilt: None,
        };
        let mut events = vec![
            second[0].clone(),
            first[0].clone(),
            (3, other),
            first[1].clone(),
        ];
        events.extend(second.iter().cloned());
        let e = LoggedEpisode {
            task: "install_toilet_roll/small".into(),
            seed: 1,
            outcome: "success".into(),
            gripper_measures: Some(events),
        };
        let (along, r) = e.first_roll_release().unwrap();
        assert_eq!(along, grasp_along(&first[0].1));
        assert_eq!(r.landing, Landing::OnTheTable, "{r:?}");
        // Without a grasp before it, or without measurements: nothing to count.
        let alone = LoggedEpisode {
            gripper_measures: Some(vec![first[1].clone()]),
            ..e.clone()
        };
        assert_eq!(alone.first_roll_release(), None);
        assert_eq!(
            LoggedEpisode {
                gripper_measures: None,
                ..e
            }
            .first_roll_release(),
            None
        );
    }

    #[test]
    fn a_bad_log_is_an_error_naming_the_file_and_line() {
        let dir =
            std::env::temp_dir().join(format!("equact-eval-report-bad-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let path = dir.join(EPISODE_LOG);
        std::fs::write(
            &path,
            format!(
                "{}\n{{\"task\": 3}}\n",
                line("pick_fruit/plum", 1, "success", &[])
            ),
        )
        .unwrap();
        let err = format!("{:#}", read_logs(std::slice::from_ref(&dir)).unwrap_err());
        assert!(
            err.contains(&format!(
                "{} line 2: not an episode summary",
                path.display()
            )),
            "{err}"
        );
        let missing = dir.join("nothing-here");
        let err = format!(
            "{:#}",
            read_logs(std::slice::from_ref(&missing)).unwrap_err()
        );
        assert!(
            err.contains(&missing.display().to_string()) && err.contains("equact eval --out"),
            "{err}"
        );
        let err = read_logs(&[]).unwrap_err().to_string();
        assert!(err.contains("no evaluation folder given"), "{err}");
        std::fs::remove_dir_all(&dir).unwrap();
    }

    #[test]
    fn quantiles_interpolate_between_the_nearest_ranks() {
        assert_eq!(median(&mut []), None);
        assert_eq!(median(&mut [3.0, 1.0, 2.0]), Some(2.0));
        assert_eq!(median(&mut [4.0, 1.0, 3.0, 2.0]), Some(2.5));
        assert_eq!(median(&mut [1.0, f64::NAN]), None);
        assert_eq!(
            quartiles(&mut [4.0, 0.0, 2.0, 1.0, 3.0]),
            Some([1.0, 2.0, 3.0])
        );
        assert_eq!(quartiles(&mut [0.0, 1.0]), Some([0.25, 0.5, 0.75]));
        assert_eq!(quartiles(&mut []), None);
    }
}
