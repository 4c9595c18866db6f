//! `equact demos collect` as a library call: one expert episode recorded through the
//! simulated cameras and the real fusion, read back from its safetensors shard (shapes, the
//! language, keyframes equal to the expert's), and a second run that resumes (skips it).
#![allow(clippy::unwrap_used, clippy::expect_used)]

use std::sync::atomic::AtomicBool;
use std::sync::Arc;

use cell_types::config::CellConfig;
use equact::demos::{collect, read_shard, Index};
use equact::sim_cell::EpisodePlan;
use equact::task::{ExpertSettings, PipePart, TaskInstance, TaskKind};

/// `episodes` of `kind` from `seed`, the simulated cell at the tests' speed.
fn plan(kind: TaskKind, episodes: u64, seed: u64) -> EpisodePlan {
    EpisodePlan {
        kinds: vec![kind],
        episodes,
        seed,
        sim_speed: tests::SIM_SPEED,
    }
}

#[test]
fn a_collected_demo_reads_back_with_the_experts_keyframes_and_a_rerun_skips_it() {
    let _cell = tests::one_cell_at_a_time();
    let cfg = CellConfig::simulated().unwrap();
    let out = std::env::temp_dir().join(format!("equact-demos-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&out);
    let kind = TaskKind::DisassemblePipe(PipePart::FirstLink);
    let stop = Arc::new(AtomicBool::new(false));
    // The same command twice: a run, then its rerun.
    let collect_seed_7 = || {
        collect(
            &cfg,
            &plan(kind, 1, 7),
            &out,
            &ExpertSettings::default(),
            &stop,
        )
        .unwrap()
    };
    let s = collect_seed_7();
    assert_eq!((s.recorded, s.skipped, s.failed), (1, 0, 0));

    let index = Index::load(&out).unwrap();
    assert_eq!(index.episodes.len(), 1);
    let entry = &index.episodes[0];
    assert_eq!(entry.task, "disassemble_pipe/first_link");
    assert_eq!(entry.outcome, "success");
    let demo = read_shard(&out.join(entry.file.as_ref().unwrap())).unwrap();
    assert_eq!(demo.metadata["instruction"], kind.instruction());
    assert_eq!(demo.metadata["seed"], "7");

    let expert = TaskInstance::sample(kind, 7, cfg.workspace.table_height).expert_keyframes();
    assert_eq!(demo.steps.len(), entry.steps);
    assert_eq!(demo.steps.len(), expert.len());
    assert!(demo.points >= 1000, "{} points", demo.points);
    for (i, (step, k)) in demo.steps.iter().zip(&expert).enumerate() {
        assert_eq!(step.cloud_xyz.len(), demo.points);
        assert_eq!(step.cloud_rgb.len(), demo.points);
        let d = (step.keyframe.base_from_tcp.translation() - k.base_from_tcp.translation()).norm();
        let a = step
            .keyframe
            .base_from_tcp
            .rotation()
            .angle_to(&k.base_from_tcp.rotation());
        assert!(d < 1e-12 && a < 1e-9, "step {i}: {d} m, {a} rad");
        assert_eq!(step.keyframe.gripper_open, k.gripper_open);
        assert_eq!(step.keyframe.ignore_collisions, k.ignore_collisions);
        // Every cloud lies in the workspace the fusion crops to.
        for p in &step.cloud_xyz {
            assert!(p[0] >= 0.17 && p[0] <= 0.97 && p[2] >= -0.11, "{p:?}");
        }
    }
    // The gripper state before each step: open until the grasp, closed after it.
    assert!(demo.steps[0].gripper_open && demo.steps[1].gripper_open);
    assert!(!demo.steps[2].gripper_open);
    assert!(demo.steps[2].gripper_width < 0.05);

    // A rerun skips the finished episode and leaves its shard untouched.
    let shard = out.join(entry.file.as_ref().unwrap());
    let before = std::fs::metadata(&shard).unwrap().modified().unwrap();
    let s = collect_seed_7();
    assert_eq!((s.recorded, s.skipped), (0, 1));
    assert_eq!(
        std::fs::metadata(&shard).unwrap().modified().unwrap(),
        before
    );
    let leftovers: Vec<_> = std::fs::read_dir(&out)
        .unwrap()
        .map(|e| e.unwrap().file_name().to_string_lossy().into_owned())
        .filter(|n| n.ends_with(".partial") || n.starts_with(".scratch"))
        .collect();
    assert!(leftovers.is_empty(), "{leftovers:?}");
    let _ = std::fs::remove_dir_all(&out);
}

/// Points of a recorded cloud more than `clearance` above the table: the objects.
fn above_table(cloud: &[[f32; 3]], table: f64, clearance: f64) -> usize {
    cloud
        .iter()
        .filter(|p| f64::from(p[2]) > table + clearance)
        .count()
}

#[test]
fn a_focus_box_raised_off_the_table_samples_the_objects_instead_of_the_table_top() {
    let _cell = tests::one_cell_at_a_time();
    let kind = TaskKind::DisassemblePipe(PipePart::FirstLink);
    let stop = Arc::new(AtomicBool::new(false));
    let mut counts = Vec::new();
    for raised in [false, true] {
        let mut cfg = CellConfig::simulated().unwrap();
        if raised {
            cfg.perception.points = 1024;
            cfg.perception.focus_above_table_m = Some(0.01);
        }
        let out = std::env::temp_dir().join(format!(
            "equact-demos-focus-{raised}-{}",
            std::process::id()
        ));
        let _ = std::fs::remove_dir_all(&out);
        let s = collect(
            &cfg,
            &plan(kind, 1, 3),
            &out,
            &ExpertSettings::default(),
            &stop,
        )
        .unwrap();
        assert_eq!(s.recorded, 1);
        let index = Index::load(&out).unwrap();
        assert_eq!(index.perception, cfg.perception);
        let demo = read_shard(&out.join(index.episodes[0].file.as_ref().unwrap())).unwrap();
        assert_eq!(demo.points, cfg.perception.points);
        let first = &demo.steps[0].cloud_xyz;
        let table = cfg.workspace.table_height;
        counts.push((above_table(first, table, 0.01), first.len()));
        let _ = std::fs::remove_dir_all(&out);
    }
    let ((plain, of_plain), (raised, of_raised)) = (counts[0], counts[1]);
    // EquAct's box starts at the table: the pipe is a few dozen of 2048 points.
    assert!(plain < 150, "{plain} of {of_plain} above the table");
    // Raised, the box's three quarters go to the pipe, and the table keeps a quarter.
    assert!(
        raised > 4 * plain,
        "{raised} of {of_raised} against {plain}"
    );
    assert!(of_raised - raised >= 200, "{raised} of {of_raised}");
}

/// `--grasp-turn`: the arm executes the toilet-roll grasp turned in the pads' plane while the
/// shard records the clean grasp as the label; the index keeps the setting, and a dataset
/// is not resumed with another (or with a turn out of range).
#[test]
fn a_turned_grasp_is_executed_while_the_clean_grasp_is_recorded() {
    let _cell = tests::one_cell_at_a_time();
    use equact::demos::DemosError;
    use equact::task::{toilet_roll, RollSize};
    let cfg = CellConfig::simulated().unwrap();
    let planner = equact::episode::planner_from_config(&cfg).unwrap();
    let kind = TaskKind::InstallToiletRoll(RollSize::Small);
    let table = cfg.workspace.table_height;
    let turned = ExpertSettings {
        grasp_turn_deg: 12.0,
        ..ExpertSettings::default()
    };
    // A seed whose drawn turn is large enough to tell from tracking error.
    let (seed, turn) = (0..50)
        .map(|s| {
            let t = TaskInstance::sample(kind, s, table);
            (s, toilet_roll::expert_grasp_turn(&t, 12f64.to_radians()))
        })
        .find(|(_, t)| t.abs().to_degrees() > 6.0)
        .unwrap();
    let out = std::env::temp_dir().join(format!("equact-demos-turn-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&out);
    let stop = Arc::new(AtomicBool::new(false));
    let s = collect(&cfg, &plan(kind, 1, seed), &out, &turned, &stop).unwrap();
    assert_eq!((s.recorded, s.failed), (1, 0));
    let index = Index::load(&out).unwrap();
    assert_eq!(index.expert, turned);
    let demo = read_shard(&out.join(index.episodes[0].file.as_ref().unwrap())).unwrap();
    let plain = TaskInstance::sample(kind, seed, table).expert_keyframes();
    // The label is the clean grasp ...
    let label = demo.steps[1].keyframe.base_from_tcp;
    assert!(
        label
            .rotation()
            .angle_to(&plain[1].base_from_tcp.rotation())
            < 1e-9
    );
    // ... and the arm stood turned by the drawn angle after executing it.
    let reached = planner.model.fk_tcp(&demo.steps[2].joints);
    let off = reached.rotation().angle_to(&label.rotation()).to_degrees();
    assert!(
        (off - turn.abs().to_degrees()).abs() < 0.5,
        "{off}° against {}°",
        turn.to_degrees()
    );
    // A resume with the plain expert, or a turn out of range, is refused.
    let plain_settings = ExpertSettings::default();
    let err = collect(&cfg, &plan(kind, 2, seed), &out, &plain_settings, &stop).unwrap_err();
    assert!(matches!(err, DemosError::ExpertMismatch { .. }), "{err}");
    assert!(
        err.to_string()
            .contains("by the expert with grasp turns up to 12°, not the plain expert")
            && err.to_string().contains("--grasp-turn 12"),
        "{err}"
    );
    // So is one that would also record centred grasp labels.
    let centred = ExpertSettings {
        centred_grasp_labels: true,
        ..turned
    };
    let err = collect(&cfg, &plan(kind, 2, seed), &out, &centred, &stop).unwrap_err();
    assert!(
        err.to_string().contains(
            "not the expert with grasp turns up to 12° and centred grasp labels: record into \
             another folder, or pass --grasp-turn 12"
        ),
        "{err}"
    );
    for bad in [f64::NAN, -1.0, 45.0] {
        let settings = ExpertSettings {
            grasp_turn_deg: bad,
            ..ExpertSettings::default()
        };
        let err = collect(&cfg, &plan(kind, 1, seed), &out, &settings, &stop).unwrap_err();
        assert!(matches!(err, DemosError::BadExpertSettings(_)), "{err}");
    }
    let _ = std::fs::remove_dir_all(&out);
}

/// The simulated cell replays an episode bit for bit: the same seed recorded twice gives the
/// same joints, gripper widths, clouds and keyframes at every step. (The controller waits
/// for the driver's answer each cycle, and the driver reports a motion once the arm is at
/// rest; without either, the joints after a motion differed by micro-radians from run to
/// run, and through the held roll's pose so did the later clouds.)
#[test]
fn the_same_seed_replays_bit_for_bit() {
    let _cell = tests::one_cell_at_a_time();
    use equact::task::RollSize;
    let cfg = CellConfig::simulated().unwrap();
    let kind = TaskKind::InstallToiletRoll(RollSize::Large);
    let stop = Arc::new(AtomicBool::new(false));
    let record = |run: &str| {
        let out =
            std::env::temp_dir().join(format!("equact-demos-replay-{run}-{}", std::process::id()));
        let _ = std::fs::remove_dir_all(&out);
        let s = collect(
            &cfg,
            &plan(kind, 1, 5),
            &out,
            &ExpertSettings::default(),
            &stop,
        )
        .unwrap();
        assert_eq!((s.recorded, s.failed), (1, 0));
        let index = Index::load(&out).unwrap();
        let demo = read_shard(&out.join(index.episodes[0].file.as_ref().unwrap())).unwrap();
        let _ = std::fs::remove_dir_all(&out);
        demo.steps
    };
    let first = record("a");
    let second = record("b");
    assert_eq!(first.len(), 5);
    for (i, (a, b)) in first.iter().zip(&second).enumerate() {
        assert_eq!(a.joints, b.joints, "step {i}");
        assert_eq!(a.gripper_width, b.gripper_width, "step {i}");
        assert!(a == b, "step {i}: the clouds or keyframes differ");
    }
}
