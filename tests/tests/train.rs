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
use equact::eval::{evaluate, EvalPlan, LearnedEval, EVAL_SEED};
use equact::learned::{for_cell, LearnedPolicy};
use equact::task::{Fruit, TaskKind};
use equact::train::{load_samples, Instructions};
use policy::init::random_weights;
use policy::optim::AdamWConfig;
use policy::predict::{PolicyConfig, PolicyMode};
use policy::trainer::{TrainConfig, Trainer, WEIGHTS_FILE};

/// How close the built-in model's keyframe must come to the expert's on a training scene
/// (measured: 9 mm, 8 mm and 23 mm for reach, grasp and lift, approach axes 3-4 degrees apart;
/// the bound is about the peach's radius, 3.4 cm).
const BUILTIN_POSITION_M: f64 = 0.03;
/// How far apart their approach axes may be.
const BUILTIN_APPROACH_DEG: f64 = 10.0;

#[test]
fn demonstrations_train_a_checkpoint_that_runs_an_episode() {
    let cfg = CellConfig::simulated().unwrap();
    let root = std::env::temp_dir().join(format!("equact-train-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&root);
    let demos = root.join("demos");
    let kind = TaskKind::PickFruit(Fruit::Peach);
    let stop = Arc::new(AtomicBool::new(false));
    let s = collect(&cfg, &[kind], 1, 3, &demos, &stop).unwrap();
    assert_eq!(s.recorded, 1);

    let minilm = tests::minilm_model_dir().unwrap();
    let samples = load_samples(&demos, &cfg, &Instructions::MiniLm(&minilm)).unwrap();
    let index = Index::load(&demos).unwrap();
    let shard = read_shard(&demos.join(index.episodes[0].file.as_ref().unwrap())).unwrap();
    assert_eq!(samples.len(), shard.steps.len());
    for ((k, sample), step) in samples.iter().zip(&shard.steps) {
        assert_eq!(*k, kind);
        assert_eq!(sample.target, step.keyframe);
        assert_eq!(sample.cloud.points.len(), step.cloud_xyz.len());
        assert_eq!(sample.gripper.open, step.gripper_open);
        assert_eq!(sample.instruction.dim(), policy::minilm::HIDDEN);
    }
    // The first step starts at the home pose: the TCP is where the arm's kinematics put it.
    let home = equact::episode::robot_model(&cfg)
        .unwrap()
        .fk_tcp(&shard.steps[0].joints);
    assert!((samples[0].1.gripper.base_from_tcp.translation() - home.translation()).norm() < 1e-12);

    // The built-in model was trained on this variation's seeds 0-14: on this demonstration's
    // observations (seed 3) it gives the expert's keyframes back.
    let mut builtin = policy::builtin::policy(for_cell(policy::builtin::config(), &cfg)).unwrap();
    for (step, (_, sample)) in samples.iter().enumerate() {
        let text = kind.instruction();
        let instruction = policy::builtin::instruction(&text).unwrap();
        let got = builtin
            .predict(&sample.cloud, &sample.gripper, &instruction)
            .unwrap();
        let want = &sample.target;
        let off = (got.base_from_tcp.translation() - want.base_from_tcp.translation()).norm();
        let z =
            |k: &cell_types::Keyframe| k.base_from_tcp.isometry().rotation * nalgebra::Vector3::z();
        let tilt = z(&got).angle(&z(want)).to_degrees();
        assert!(
            off < BUILTIN_POSITION_M
                && tilt < BUILTIN_APPROACH_DEG
                && got.gripper_open == want.gripper_open,
            "step {step}: the built-in model says {:?} (open {}), the expert {:?} (open {}): \
             {off:.3} m, approach {tilt:.1} deg apart",
            got.base_from_tcp.translation(),
            got.gripper_open,
            want.base_from_tcp.translation(),
            want.gripper_open
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
        queries_per_level: 12,
        top_k: 3,
        rotation_grid_level: 0,
        augment: true,
        batch: 2,
        seed: 1,
        threads: 2,
    };
    let weights = random_weights(&net.model, &net.extra, 4);
    let mut trainer = Trainer::new(train, weights).unwrap();
    let batch: Vec<_> = samples.iter().take(2).map(|(_, s)| s).collect();
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
        &EvalPlan {
            kinds: vec![kind],
            episodes: 1,
            seed: EVAL_SEED,
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
