//! `equact eval compare`: two evaluations side by side (a model and its ablation, two
//! training runs), per task variation, per task and over all variations both ran, each
//! difference with Fisher's exact test and, over the episodes both ran on the same scene
//! seed, McNemar's, so that a claim such as "the equivariant heads beat the plain ones" is
//! measured in the repository rather than by a script beside it.

use serde::Serialize;

use crate::eval_report::{EvalReport, LoggedEpisode};
use crate::stats::{fisher_exact, mcnemar_exact, Count};

/// One row of a comparison: the same variation (or task, or all of them) in both.
#[derive(Clone, Debug, PartialEq, Serialize)]
pub struct CompareRow {
    /// `task/variation`, a task name, or `all`.
    pub name: String,
    /// The first evaluation's count.
    pub a: Count,
    /// The second evaluation's count.
    pub b: Count,
    /// Fisher's exact test, two-sided.
    pub p: Option<f64>,
    /// The episodes both ran on the same seed, as pairs: how many, and the exact McNemar
    /// test of their disagreements (more telling than Fisher's when the scenes are shared).
    pub paired: Paired,
}

/// Episodes both evaluations ran on the same scene seed.
#[derive(Clone, Copy, Debug, Default, PartialEq, Serialize)]
pub struct Paired {
    /// Seed-matched pairs.
    pub pairs: u64,
    /// Pairs only the first evaluation succeeded in.
    pub only_a: u64,
    /// Pairs only the second succeeded in.
    pub only_b: u64,
    /// McNemar's exact test, two-sided; `None` without a pair.
    pub p: Option<f64>,
}

impl Paired {
    fn add(&mut self, other: Paired) {
        self.pairs += other.pairs;
        self.only_a += other.only_a;
        self.only_b += other.only_b;
        self.p = (self.pairs > 0).then(|| mcnemar_exact(self.only_a, self.only_b));
    }
}

/// Two evaluations compared over the task variations both ran.
#[derive(Clone, Debug, PartialEq, Serialize)]
pub struct Comparison {
    /// What the first evaluation is called (its folder, as given).
    pub a_name: String,
    /// What the second is called.
    pub b_name: String,
    /// The variations both ran (in the first's order), then per task, then `all`.
    pub rows: Vec<CompareRow>,
    /// Variations only the first ran (not compared).
    pub only_in_a: Vec<String>,
    /// Variations only the second ran (not compared).
    pub only_in_b: Vec<String>,
    /// Compared variations whose two evaluations ran different scene seeds.
    pub different_seeds: Vec<String>,
}

impl Comparison {
    /// Compares the episodes of two evaluations; an error when they share no variation.
    pub fn of(
        a_name: &str,
        a: &[LoggedEpisode],
        b_name: &str,
        b: &[LoggedEpisode],
    ) -> anyhow::Result<Self> {
        let (ra, rb) = (EvalReport::of(a), EvalReport::of(b));
        let count = |v: &crate::eval_report::VariationCount| Count {
            successes: v.successes,
            episodes: v.episodes,
        };
        let mut rows: Vec<CompareRow> = Vec::new();
        let mut only_in_a = Vec::new();
        let mut different_seeds = Vec::new();
        for va in &ra.variations {
            let Some(vb) = rb.variations.iter().find(|v| v.task == va.task) else {
                only_in_a.push(va.task.clone());
                continue;
            };
            let mut r = row(va.task.clone(), count(va), count(vb));
            let (paired, same_seeds) = pairs(a, b, &va.task);
            r.paired.add(paired);
            rows.push(r);
            if !same_seeds {
                different_seeds.push(va.task.clone());
            }
        }
        let only_in_b: Vec<String> = rb
            .variations
            .iter()
            .filter(|v| !ra.variations.iter().any(|va| va.task == v.task))
            .map(|v| v.task.clone())
            .collect();
        if rows.is_empty() {
            anyhow::bail!(
                "{a_name} and {b_name} share no task variation ({a_name}: {}; {b_name}: {}): \
                 compare evaluations of the same tasks",
                names(&only_in_a),
                names(&only_in_b)
            );
        }
        let mut tasks: Vec<CompareRow> = Vec::new();
        let mut all = row("all".into(), Count::default(), Count::default());
        for r in &rows {
            let task = crate::eval::task_name(&r.name);
            let i = tasks
                .iter()
                .position(|t| t.name == task)
                .unwrap_or_else(|| {
                    tasks.push(row(task.into(), Count::default(), Count::default()));
                    tasks.len() - 1
                });
            let t = &mut tasks[i];
            for acc in [&mut t.a, &mut all.a] {
                acc.successes += r.a.successes;
                acc.episodes += r.a.episodes;
            }
            for acc in [&mut t.b, &mut all.b] {
                acc.successes += r.b.successes;
                acc.episodes += r.b.episodes;
            }
            t.paired.add(r.paired);
            all.paired.add(r.paired);
        }
        for t in tasks.iter_mut().chain(std::iter::once(&mut all)) {
            t.p = fisher_exact(t.a, t.b);
        }
        rows.extend(tasks);
        rows.push(all);
        Ok(Self {
            a_name: a_name.into(),
            b_name: b_name.into(),
            rows,
            only_in_a,
            only_in_b,
            different_seeds,
        })
    }

    /// The comparison as a Markdown table and the notes under it.
    pub fn markdown(&self) -> String {
        let mut s = format!(
            "| task/variation | {} | {} | p (Fisher, two-sided) | same-seed pairs: only first / only second, p (McNemar) |\n|---|---|---|---|---|\n",
            self.a_name, self.b_name
        );
        let cell = |c: Count| format!("{}/{} ({:.0} %)", c.successes, c.episodes, 100.0 * c.rate());
        for r in &self.rows {
            let name = if r.name.contains('/') {
                r.name.clone()
            } else {
                format!("**{}**", r.name)
            };
            let paired = match r.paired.p {
                Some(p) => format!(
                    "{} pairs: {} / {}, {}",
                    r.paired.pairs,
                    r.paired.only_a,
                    r.paired.only_b,
                    p_words(p)
                ),
                None => "-".into(),
            };
            s.push_str(&format!(
                "| {name} | {} | {} | {} | {paired} |\n",
                cell(r.a),
                cell(r.b),
                r.p.map_or_else(|| "-".into(), p_words)
            ));
        }
        s.push_str(
            "\np: how likely a difference this large or larger is were both at one rate \
             (Fisher's exact test; no correction for the several rows). Where both ran the \
             same scene seeds, McNemar's exact test weighs only the pairs they disagree on.\n",
        );
        for (what, list) in [
            (
                format!("Only in {}, not compared", self.a_name),
                &self.only_in_a,
            ),
            (
                format!("Only in {}, not compared", self.b_name),
                &self.only_in_b,
            ),
            (
                "Run on different scene seeds in the two".to_string(),
                &self.different_seeds,
            ),
        ] {
            if !list.is_empty() {
                s.push_str(&format!("{what}: {}.\n", list.join(", ")));
            }
        }
        s
    }
}

fn row(name: String, a: Count, b: Count) -> CompareRow {
    CompareRow {
        name,
        a,
        b,
        p: fisher_exact(a, b),
        paired: Paired::default(),
    }
}

/// The seed-matched episodes of `task` in both evaluations (a seed run twice in one of them
/// pairs its first run), and whether the two ran the same seeds.
fn pairs(a: &[LoggedEpisode], b: &[LoggedEpisode], task: &str) -> (Paired, bool) {
    let outcomes = |eps: &[LoggedEpisode]| {
        let mut m = std::collections::BTreeMap::new();
        for e in eps.iter().filter(|e| e.task == task) {
            m.entry(e.seed).or_insert(e.succeeded());
        }
        m
    };
    let (oa, ob) = (outcomes(a), outcomes(b));
    let mut p = Paired::default();
    for (seed, &sa) in &oa {
        if let Some(&sb) = ob.get(seed) {
            p.pairs += 1;
            p.only_a += u64::from(sa && !sb);
            p.only_b += u64::from(sb && !sa);
        }
    }
    (p, oa.keys().eq(ob.keys()))
}

fn names(list: &[String]) -> String {
    if list.is_empty() {
        "none".into()
    } else {
        list.join(", ")
    }
}

/// A p-value in a table: two significant digits (0.49, 0.047, 0.0028), below 0.0001 as
/// `< 0.0001`.
fn p_words(p: f64) -> String {
    if p < 1e-4 {
        return "< 0.0001".into();
    }
    let digits = (1 - p.log10().floor() as i32).max(1) as usize;
    format!("{p:.digits$}")
}

#[cfg(test)]
mod tests {
    use super::*;

    fn episodes(task: &str, successes: u64, n: u64, first_seed: u64) -> Vec<LoggedEpisode> {
        (0..n)
            .map(|i| LoggedEpisode {
                task: task.into(),
                seed: first_seed + i,
                outcome: if i < successes {
                    "success"
                } else {
                    "task_lost"
                }
                .into(),
                gripper_measures: None,
            })
            .collect()
    }

    #[test]
    fn rows_per_variation_task_and_all_with_fishers_p() {
        let a: Vec<LoggedEpisode> = [
            episodes("pick_fruit/plum", 3, 4, 0),
            episodes("pick_fruit/peach", 10, 10, 0),
            episodes("pluck_flower/top", 1, 10, 0),
        ]
        .concat();
        let b: Vec<LoggedEpisode> = [
            episodes("pick_fruit/plum", 1, 4, 0),
            episodes("pick_fruit/peach", 10, 10, 5),
            episodes("pluck_flower/top", 11, 14, 0),
            episodes("install_toilet_roll/large", 1, 2, 0),
        ]
        .concat();
        let c = Comparison::of("first", &a, "ablation", &b).unwrap();
        let names: Vec<&str> = c.rows.iter().map(|r| r.name.as_str()).collect();
        assert_eq!(
            names,
            [
                "pick_fruit/plum",
                "pick_fruit/peach",
                "pluck_flower/top",
                "pick_fruit",
                "pluck_flower",
                "all"
            ]
        );
        // The textbook tables (see `stats`): tea tasting and Wikipedia's example.
        assert!((c.rows[0].p.unwrap() - 0.485_714).abs() < 1e-6);
        assert!((c.rows[2].p.unwrap() - 0.002_759).abs() < 1e-6);
        let fruit = &c.rows[3];
        assert_eq!((fruit.a.successes, fruit.a.episodes), (13, 14));
        assert_eq!((fruit.b.successes, fruit.b.episodes), (11, 14));
        let all = &c.rows[5];
        assert_eq!((all.a.successes, all.a.episodes), (14, 24));
        assert_eq!((all.b.successes, all.b.episodes), (22, 28));
        assert_eq!(all.p, fisher_exact(all.a, all.b));
        // Pairs by seed: plum 0-3 in both (first alone wins seeds 1 and 2), peach 5-9 (both
        // win), flower 0-9 (the second alone wins seeds 1-9).
        assert_eq!(
            c.rows[0].paired,
            Paired {
                pairs: 4,
                only_a: 2,
                only_b: 0,
                p: Some(0.5)
            }
        );
        assert_eq!((c.rows[1].paired.pairs, c.rows[1].paired.p), (5, Some(1.0)));
        assert_eq!(
            c.rows[2].paired,
            Paired {
                pairs: 10,
                only_a: 0,
                only_b: 9,
                p: Some(2.0 / 512.0)
            }
        );
        assert_eq!(
            (all.paired.pairs, all.paired.only_a, all.paired.only_b),
            (19, 2, 9)
        );
        assert_eq!(all.paired.p, Some(mcnemar_exact(2, 9)));
        assert_eq!(c.only_in_b, ["install_toilet_roll/large"]);
        assert!(c.only_in_a.is_empty());
        // Peach: seeds 0-9 against 5-14; the flower: 10 episodes against 14.
        assert_eq!(c.different_seeds, ["pick_fruit/peach", "pluck_flower/top"]);
        let md = c.markdown();
        assert!(
            md.contains(
                "| pluck_flower/top | 1/10 (10 %) | 11/14 (79 %) | 0.0028 | 10 pairs: 0 / 9, 0.0039 |"
            ),
            "{md}"
        );
        assert!(
            md.contains("| **all** | 14/24 (58 %) | 22/28 (79 %) |"),
            "{md}"
        );
        assert!(
            md.contains("Only in ablation, not compared: install_toilet_roll/large."),
            "{md}"
        );
        assert!(
            md.contains(
                "Run on different scene seeds in the two: pick_fruit/peach, pluck_flower/top."
            ),
            "{md}"
        );
    }

    #[test]
    fn evaluations_without_a_common_variation_are_refused_by_name() {
        let a = episodes("pick_fruit/plum", 1, 2, 0);
        let b = episodes("pluck_flower/top", 1, 2, 0);
        let err = Comparison::of("x", &a, "y", &b).unwrap_err().to_string();
        assert!(
            err.contains("share no task variation (x: pick_fruit/plum; y: pluck_flower/top)"),
            "{err}"
        );
    }

    #[test]
    fn p_values_read_at_two_significant_digits() {
        assert_eq!(p_words(1.0), "1.0");
        assert_eq!(p_words(0.485_714), "0.49");
        assert_eq!(p_words(0.047_31), "0.047");
        assert_eq!(p_words(0.002_759), "0.0028");
        assert_eq!(p_words(0.000_265_46), "0.00027");
        assert_eq!(p_words(0.000_01), "< 0.0001");
    }
}
