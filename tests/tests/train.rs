//! Demonstrations to a trained checkpoint to a closed-loop episode: one expert episode is
//! recorded, read back as training samples (instructions embedded with MiniLM), a tiny
//! network trains a few steps, its checkpoint loads as the learned policy and runs one
//! evaluation episode in the simulated cell. The same observations check the built-in model
//! (`policy::builtin`) against the expert's keyframes.

#![allow(clippy::unwrap_used, clippy::expect_used)] // test helpers may panic

use std::sync::atomic::AtomicBool;
use std::sync::Arc;

use cell_types::config::CellConfig;
use equact::demos::{collect, read_shard, Index};
use equact::eval::{evaluate, LearnedEval, EVAL_SEED};
use equact::learned::{for_cell, LearnedPolicy};
use equact::sim_cell::EpisodePlan;
use equact::task::{ExpertSettings, Fruit, TaskKind};
use equact::train::{load_samples, Instructions};
use policy::init::random_weights;
use policy::optim::AdamWConfig;
use policy::predict::{PolicyConfig, PolicyMode};
use policy::trainer::{TrainConfig, Trainer, WEIGHTS_FILE};

/// How close the built-in model's keyframe must come to the expert's on a training scene
/// (measured with 4 × 333 translation queries, before the 111 near-gripper ones were added
/// to the first level: 8 mm, 7 mm and 11 mm for reach, grasp and lift; the 1024-point model
/// before it 5, 8 and 10 mm; the first built-in model, at 512 points, 3 mm, 5 mm and 18 mm;
/// the bound is about the peach's radius, 3.4 cm).
const BUILTIN_POSITION_M: f64 = 0.03;
/// How far apart their orientations may be (degrees; the fingers' half-turn symmetry
/// aside; measured 14.6°, 3.2° and 1.6° (before it 13.3°, 4.0° and 1.4°), the first
/// built-in model 9°, 1.5° and 2.7°: the round fruit leaves the turn about the approach
/// axis loosely defined, and the reach above it most of all).
const BUILTIN_ROTATION_DEG: f64 = 20.0;

#[test]
fn demonstrations_train_a_checkpoint_that_runs_an_episode() {
    let cfg = CellConfig::simulated().unwrap();
    let root = std::env::temp_dir().join(format!("equact-train-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&root);
    let demos = root.join("demos");
    let kind = TaskKind::PickFruit(Fruit::Peach);
    let stop = Arc::new(AtomicBool::new(false));
    let s = collect(
        &cfg,
        &EpisodePlan {
            kinds: vec![kind],
            episodes: 1,
            seed: 3,
            sim_speed: tests::SIM_SPEED,
        },
        &demos,
        &ExpertSettings::default(),
        &stop,
    )
    .unwrap();
    assert_eq!(s.recorded, 1);

    let minilm = tests::minilm_model_dir().unwrap();
    let (index, samples) = load_samples(&demos, &cfg, &Instructions::MiniLm(&minilm)).unwrap();
    assert_eq!(index, Index::load(&demos).unwrap());
    let shard = read_shard(&demos.join(index.episodes[0].file.as_ref().unwrap())).unwrap();
    assert_eq!(samples.len(), shard.steps.len());
    for (i, (demo, step)) in samples.iter().zip(&shard.steps).enumerate() {
        let sample = &demo.sample;
        assert_eq!((demo.kind, demo.seed, demo.step), (kind, 3, i));
        assert_eq!(sample.target, step.keyframe);
        assert_eq!(sample.cloud.points.len(), step.cloud_xyz.len());
        assert_eq!(sample.gripper.open, step.gripper_open);
        assert_eq!(sample.instruction.dim(), policy::minilm::HIDDEN);
    }
    // The first step starts at the home pose: the TCP is where the arm's kinematics put it.
    let home = equact::episode::robot_model(&cfg)
        .unwrap()
        .fk_tcp(&shard.steps[0].joints);
    assert!(
        (samples[0].sample.gripper.base_from_tcp.translation() - home.translation()).norm() < 1e-12
    );

    // The built-in model was trained on this variation's seeds 0-14: on this demonstration's
    // observations (seed 3) it gives the expert's keyframes back (`equact policy score`).
    let mut builtin = policy::builtin::policy(for_cell(policy::builtin::config(), &cfg)).unwrap();
    let mut lines = 0;
    let table = equact::score::score(&mut builtin, &samples, 0, &mut |_| lines += 1).unwrap();
    assert_eq!((lines, table.steps.len()), (samples.len(), samples.len()));
    assert_eq!(table.rows.len(), 2, "{:?}", table.rows);
    assert_eq!(table.rows[0].name, kind.name());
    assert_eq!(table.rows[1].name, "all");
    for (step, s) in table.steps.iter().enumerate() {
        let e = &s.error;
        assert_eq!(
            (s.variation.clone(), s.seed, s.step),
            (kind.name(), 3, step)
        );
        assert!(s.prediction_cpu_s > 0.0);
        assert!(s.predicted_logit.is_finite() && s.expert_logit.is_finite());
        assert!(
            e.position_m < BUILTIN_POSITION_M
                && e.rotation_deg < BUILTIN_ROTATION_DEG
                && e.open_agrees,
            "step {step}: the built-in model's keyframe is {e:?} from the expert's"
        );
    }
    assert!(table.rows[0].open_agrees == 1.0 && table.rows[0].steps == samples.len());
    // One row per keyframe of the one demonstration, in step order.
    assert_eq!(table.by_step.len(), samples.len());
    for (i, r) in table.by_step.iter().enumerate() {
        assert_eq!(
            (r.name.clone(), r.steps),
            (format!("{} step {i}", kind.name()), 1)
        );
    }

    let mut net = for_cell(PolicyConfig::tiny(), &cfg).with_mode(PolicyMode::Gated);
    net.extra.token_dim = policy::minilm::HIDDEN;
    let train = TrainConfig {
        policy: net.clone(),
        optim: AdamWConfig {
            lr: 1e-3,
            ..AdamWConfig::reference()
        },
        levels: policy::trainer::TRAIN_LEVELS,
        queries_per_level: 12,
        top_k: 3,
        // Half the first level's queries near the recorded cloud's objects.
        cloud_query_share: 0.5,
        rotation_grid_level: 0,
        augment: true,
        held_shift_m: 0.0,
        batch: 2,
        seed: 1,
        threads: 2,
    };
    let weights = random_weights(&net.model, &net.extra, 4);
    let mut trainer = Trainer::new(train, weights).unwrap();
    let batch: Vec<_> = samples.iter().take(2).map(|d| &d.sample).collect();
    for _ in 0..3 {
        let r = trainer.step(&batch).unwrap();
        assert!(r.losses.total().is_finite() && r.grad_norm > 0.0, "{r:?}");
    }
    let out = root.join("run");
    trainer.save(&out).unwrap();

    let embedding = Instructions::MiniLm(&minilm).embedding(kind).unwrap();
    let policy = LearnedPolicy::load_with(
        net,
        Some(&out.join(WEIGHTS_FILE)),
        embedding.clone(),
        &cfg,
        0,
    )
    .unwrap();
    let mut learned = LearnedEval {
        policy,
        embeddings: vec![(kind, embedding)],
    };
    let table = evaluate(
        &cfg,
        &EpisodePlan {
            kinds: vec![kind],
            episodes: 1,
            seed: EVAL_SEED,
            sim_speed: tests::SIM_SPEED,
        },
        &mut learned,
        &root.join("eval"),
        &Arc::new(AtomicBool::new(false)),
        &mut |_| {},
    )
    .unwrap();
    let row = &table.rows[0];
    assert_eq!(row.episodes, 1);
    assert!(!row.outcomes.contains_key("error"), "{:?}", row.outcomes);
    let _ = std::fs::remove_dir_all(&root);
}
