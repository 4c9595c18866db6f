//! `equact eval`: closed-loop evaluation episodes in the simulated cell, counted per task
//! variation, for the scripted expert (which must succeed) and the learned policy (tiny
//! network with random weights: the harness runs it and counts its outcomes).

#![allow(clippy::unwrap_used, clippy::expect_used)] // test helpers may panic

use std::sync::atomic::AtomicBool;
use std::sync::Arc;

use cell_types::config::CellConfig;
use equact::eval::{evaluate, ExpertEval, LearnedEval, EPISODE_LOG, EVAL_SEED};
use equact::learned::{for_cell, LearnedPolicy};
use equact::sim_cell::EpisodePlan;
use equact::task::{Fruit, TaskKind};
use policy::predict::{InstructionEmbedding, Policy, PolicyConfig};

#[test]
fn expert_and_learned_policies_are_evaluated_per_variation() {
    let _cell = tests::one_cell_at_a_time();
    let cfg = CellConfig::simulated().unwrap();
    let dir = std::env::temp_dir().join(format!("equact-eval-{}", std::process::id()));
    let interrupt = Arc::new(AtomicBool::new(false));
    let plum = TaskKind::PickFruit(Fruit::Plum);
    let mut lines = Vec::new();
    let table = evaluate(
        &cfg,
        &EpisodePlan {
            kinds: vec![plum],
            episodes: 2,
            seed: EVAL_SEED,
            sim_speed: tests::SIM_SPEED,
        },
        &mut ExpertEval::default(),
        &dir,
        &interrupt,
        &mut |l| lines.push(l.to_string()),
    )
    .unwrap();
    assert_eq!(table.policy, "expert");
    assert_eq!(table.rows.len(), 1);
    let row = &table.rows[0];
    assert_eq!((row.task.as_str(), row.episodes), ("pick_fruit/plum", 2));
    assert_eq!(row.successes, 2, "{:?} {lines:?}", row.outcomes);
    assert!(table
        .markdown()
        .contains("| pick_fruit/plum | 2/2 | 100 % |"));
    assert_eq!(lines.len(), 2);
    // One recording per episode.
    let recordings = std::fs::read_dir(&dir)
        .unwrap()
        .filter(|e| {
            e.as_ref()
                .unwrap()
                .path()
                .extension()
                .is_some_and(|x| x == "mcap")
        })
        .count();
    assert_eq!(recordings, 2);
    // Each episode summarised: its seed, outcome, the grasp the expert made, its recording.
    let seeds: Vec<u64> = row.runs.iter().map(|r| r.seed).collect();
    assert_eq!(seeds, [EVAL_SEED, EVAL_SEED + 1]);
    for r in &row.runs {
        assert_eq!((r.task.as_str(), r.outcome), ("pick_fruit/plum", "success"));
        assert_eq!(r.gripper_events.len(), 1, "{:?}", r.gripper_events);
        assert!(r.gripper_events[0].1.starts_with("grasped the plum"));
        assert!(r.recording.is_file(), "{}", r.recording.display());
    }
    // The same summaries, one JSON line per episode, in the output folder.
    let log = |n: usize| {
        let text = std::fs::read_to_string(dir.join(EPISODE_LOG)).unwrap();
        let lines: Vec<serde_json::Value> = text
            .lines()
            .map(|l| serde_json::from_str(l).unwrap())
            .collect();
        assert_eq!(lines.len(), n, "{text}");
        lines
    };
    let lines = log(2);
    // The report over the table just run is the report over its log read back; without a
    // toilet-roll episode it has no roll part.
    let report = equact::eval_report::EvalReport::of_table(&table);
    let logged = equact::eval_report::read_logs(std::slice::from_ref(&dir)).unwrap();
    assert_eq!(report, equact::eval_report::EvalReport::of(&logged));
    assert_eq!(report.roll_markdown(), "");
    for (line, r) in lines.iter().zip(&row.runs) {
        assert_eq!(line["seed"], r.seed);
        assert_eq!(line["outcome"], "success");
        assert_eq!(line["gripper_events"][0][1], r.gripper_events[0].1.as_str());
        // Measured too: the grasp site in the hand, within the grasp radius of the TCP.
        let grasp = &line["gripper_measures"][0];
        assert_eq!(
            (&grasp[0], &grasp[1]["event"]),
            (&r.gripper_events[0].0.into(), &"grasped".into())
        );
        assert_eq!(grasp[1]["body"], "plum");
        let site: Vec<f64> = serde_json::from_value(grasp[1]["site_in_tcp_m"].clone()).unwrap();
        assert!(
            site.iter().map(|v| v * v).sum::<f64>().sqrt() < 0.03,
            "{site:?}"
        );
    }

    let net = for_cell(PolicyConfig::tiny(), &cfg);
    let policy = LearnedPolicy::new(
        Policy::random(net, 3).unwrap(),
        InstructionEmbedding::random(0),
        &cfg,
    )
    .unwrap();
    let mut learned = LearnedEval {
        policy,
        embeddings: vec![(plum, InstructionEmbedding::random(5))],
    };
    let table = evaluate(
        &cfg,
        &EpisodePlan {
            kinds: vec![plum],
            episodes: 1,
            seed: EVAL_SEED,
            sim_speed: tests::SIM_SPEED,
        },
        &mut learned,
        &dir,
        &interrupt,
        &mut |_| {},
    )
    .unwrap();
    assert_eq!(table.policy, "learned");
    let row = &table.rows[0];
    assert_eq!(row.episodes, 1);
    assert_eq!(row.outcomes.values().sum::<u64>(), 1);
    assert!(!row.outcomes.contains_key("error"), "{:?}", row.outcomes);
    // Appended to the same folder's log.
    let lines = log(3);
    assert_eq!(lines[2]["outcome"], row.runs[0].outcome);
    // `equact eval report` reads the folder back: all three episodes, by outcome.
    let logged = equact::eval_report::read_logs(std::slice::from_ref(&dir)).unwrap();
    let report = equact::eval_report::EvalReport::of(&logged);
    assert_eq!(report.variations.len(), 1);
    let v = &report.variations[0];
    assert_eq!((v.task.as_str(), v.episodes), ("pick_fruit/plum", 3));
    let learned_ok = u64::from(row.runs[0].outcome == "success");
    assert_eq!(v.successes, 2 + learned_ok);
    assert_eq!(v.outcomes.values().sum::<u64>(), 3);
    assert_eq!(report.roll, None);
    let interval = if v.successes == 3 {
        "44-100 %"
    } else {
        "21-94 %"
    };
    assert!(
        report.markdown().contains(&format!(
            "| pick_fruit/plum | {}/3 | {interval} |",
            v.successes
        )),
        "{}",
        report.markdown()
    );

    // A variation without an embedding is an error, not a silent skip.
    let err = evaluate(
        &cfg,
        &EpisodePlan {
            kinds: vec![TaskKind::PickFruit(Fruit::Peach)],
            episodes: 1,
            seed: EVAL_SEED,
            sim_speed: tests::SIM_SPEED,
        },
        &mut learned,
        &dir,
        &interrupt,
        &mut |_| {},
    )
    .unwrap_err();
    assert!(format!("{err:#}").contains("pick_fruit/peach"), "{err:#}");
    let _ = std::fs::remove_dir_all(&dir);
}

/// An episode summary that cannot be written (here the log's path is a folder; on a cell,
/// a full disk) is reported, and the evaluation goes on: the table still counts it.
#[test]
fn an_unwritable_episode_log_is_reported_and_the_evaluation_goes_on() {
    let _cell = tests::one_cell_at_a_time();
    let cfg = CellConfig::simulated().unwrap();
    let dir = std::env::temp_dir().join(format!("equact-eval-log-{}", std::process::id()));
    std::fs::create_dir_all(dir.join(EPISODE_LOG)).unwrap();
    let mut lines = Vec::new();
    let table = evaluate(
        &cfg,
        &EpisodePlan {
            kinds: vec![TaskKind::PickFruit(Fruit::Strawberry)],
            episodes: 1,
            seed: EVAL_SEED,
            sim_speed: tests::SIM_SPEED,
        },
        &mut ExpertEval::default(),
        &dir,
        &Arc::new(AtomicBool::new(false)),
        &mut |l| lines.push(l.to_string()),
    )
    .unwrap();
    assert_eq!(table.rows[0].successes, 1, "{lines:?}");
    assert_eq!(table.rows[0].runs.len(), 1);
    assert!(
        lines.iter().any(
            |l| l.starts_with("warning: appending an episode's summary to ")
                && l.contains(EPISODE_LOG)
        ),
        "{lines:?}"
    );
    let _ = std::fs::remove_dir_all(&dir);
}
