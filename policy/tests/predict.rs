//! The inference API: deterministic per seed, moves with the scene in equivariant mode, names
//! bad input, and round-trips its own weights and instruction files.

#![allow(clippy::unwrap_used, clippy::expect_used)] // tests may unwrap (CONVENTIONS 6)

mod common;

use cell_types::{Base, FrameId, PointCloud, Tcp, Transform};
use nalgebra::{Isometry3, Point3, Translation3, UnitQuaternion, Vector3};
use policy::init::random_weights;
use policy::model::HeadKind;
use policy::predict::{
    GripperPose, InstructionEmbedding, Policy, PolicyConfig, PolicyMode, SamplingConfig,
};
use policy::transblock::FilmKind;
use policy::weights::Weights;
use policy::PolicyError;
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;

/// A table below the focus box, three blobs on it, random colours: 700 points.
fn scene(seed: u64) -> PointCloud {
    let mut rng = ChaCha8Rng::seed_from_u64(seed);
    let mut pts = Vec::new();
    for _ in 0..400 {
        pts.push(Point3::new(
            rng.random_range(0.25..0.9f32),
            rng.random_range(-0.33..0.33f32),
            -0.08,
        ));
    }
    for (cx, cy, r) in [
        (0.45f32, 0.1f32, 0.05f32),
        (0.6, -0.15, 0.07),
        (0.75, 0.05, 0.04),
    ] {
        for _ in 0..100 {
            let d = Vector3::new(
                rng.random_range(-1.0..1.0f32),
                rng.random_range(-1.0..1.0f32),
                rng.random_range(0.0..1.0f32),
            )
            .normalize();
            pts.push(Point3::new(cx + r * d.x, cy + r * d.y, -0.05 + r * d.z));
        }
    }
    let rgb = (0..pts.len())
        .map(|_| [rng.random(), rng.random(), rng.random()])
        .collect();
    PointCloud::new(FrameId::Base, pts, Some(rgb)).unwrap()
}

fn gripper() -> GripperPose {
    GripperPose {
        base_from_tcp: Transform::from_xyz_rpy([0.5, 0.02, 0.3], [3.0, 0.1, 0.4]),
        open: true,
    }
}

fn tiny(mode: PolicyMode) -> Policy {
    Policy::random(PolicyConfig::tiny().with_mode(mode), 7).unwrap()
}

/// The tiny gated configuration with its sampling changed by `edit`.
fn gated_tiny_sampling(edit: impl FnOnce(&mut SamplingConfig)) -> PolicyConfig {
    let mut cfg = PolicyConfig::tiny().with_mode(PolicyMode::Gated);
    edit(&mut cfg.sampling);
    cfg
}

/// A network of `cfg` with random weights (seed 7) sampling with `seed`.
fn seeded(cfg: PolicyConfig, seed: u64) -> Policy {
    let mut p = Policy::random(cfg, 7).unwrap();
    p.seed = seed;
    p
}

#[test]
fn prediction_is_deterministic_per_seed() {
    let mut p = tiny(PolicyMode::Parity);
    let cloud = scene(1);
    let instr = InstructionEmbedding::random(3);
    p.seed = 11;
    let a = p.predict_detailed(&cloud, &gripper(), &instr).unwrap();
    let b = p.predict_detailed(&cloud, &gripper(), &instr).unwrap();
    assert_eq!(a.keyframe, b.keyframe);
    assert_eq!(a.levels, b.levels);
    p.seed = 12;
    let c = p.predict_detailed(&cloud, &gripper(), &instr).unwrap();
    assert_ne!(
        a.levels[0].0, c.levels[0].0,
        "another seed draws other samples"
    );
    // The answer is one of the last level's samples, inside the gripper bounds.
    let t = a.keyframe.base_from_tcp.translation();
    let b = PolicyConfig::tiny().gripper_bounds;
    assert!((0..3).all(|i| t[i] >= b[0][i] && t[i] <= b[1][i]), "{t:?}");
    let last = &a.levels.last().unwrap().0;
    assert!(last
        .iter()
        .any(|q| (0..3).all(|i| (f64::from(q[i]) - t[i]).abs() < 1e-6)));
    // Refinement never lowers the logit of the coarse grid's best rotation.
    assert!(a.rotation_logit >= a.coarse_rotation_logit);
    assert_eq!(a.levels.len(), 3);
    assert_eq!(a.levels[1].0.len(), 30);
}

#[test]
fn worker_threads_change_nothing_but_the_time() {
    let cloud = scene(3);
    let instr = InstructionEmbedding::random(3);
    for mut p in [
        tiny(PolicyMode::Parity),
        tiny(PolicyMode::Gated),
        tiny_plain(PolicyMode::Gated),
    ] {
        p.seed = 9;
        let one = p.predict_detailed(&cloud, &gripper(), &instr).unwrap();
        // Three threads split the tiny graphs (1920 edges in the full-resolution U-net
        // blocks, eight query batches per level) unevenly.
        p.set_threads(3);
        assert_eq!(p.threads(), 3);
        let three = p.predict_detailed(&cloud, &gripper(), &instr).unwrap();
        assert_eq!(one.levels, three.levels, "translation logits, bit for bit");
        assert_eq!(one.keyframe, three.keyframe);
        assert_eq!(one.rotation_logit, three.rotation_logit);
        assert_eq!(one.open_probability, three.open_probability);
        p.set_threads(0);
        assert_eq!(p.threads(), 1, "0 threads means the caller's only");
    }
}

#[test]
fn candidates_are_the_finest_level_ranked_and_each_becomes_a_keyframe() {
    let mut p = tiny(PolicyMode::Gated);
    let cloud = scene(2);
    let instr = InstructionEmbedding::random(3);
    p.seed = 5;
    let a = p.predict_detailed(&cloud, &gripper(), &instr).unwrap();
    let (queries, logits) = a.levels.last().unwrap();
    assert_eq!(a.candidates.len(), queries.len());
    assert!(a.candidates.windows(2).all(|w| w[0].logit >= w[1].logit));
    let best = logits.iter().copied().fold(f32::NEG_INFINITY, f32::max);
    assert_eq!(a.candidates[0].logit, best);
    assert_eq!(a.candidates[0].logit, a.translation_logit);
    // Every candidate is one of the level's samples with its logit.
    for c in &a.candidates {
        assert!(queries.iter().zip(logits).any(|(q, &l)| l == c.logit
            && (0..3).all(|i| (f64::from(q[i]) - c.position[i]).abs() < 1e-6)));
    }
    // The best candidate's keyframe is the prediction; another candidate gets its own
    // position with the rotation head's answer there.
    let first = p.keyframe_at(&a.scene, &a.candidates[0].position).unwrap();
    assert_eq!(first.keyframe, a.keyframe);
    assert_eq!(first.rotation_logit, a.rotation_logit);
    let other = p.keyframe_at(&a.scene, &a.candidates[5].position).unwrap();
    let t = other.keyframe.base_from_tcp.translation();
    assert!((t - a.candidates[5].position.coords).norm() < 1e-9);
    assert!(other.rotation_logit >= other.coarse_rotation_logit);
}

#[test]
fn distinct_candidates_start_at_the_keyframe_and_keep_apart() {
    let mut p = tiny(PolicyMode::Gated);
    let cloud = scene(2);
    p.seed = 5;
    let a = p
        .predict_detailed(&cloud, &gripper(), &InstructionEmbedding::random(3))
        .unwrap();
    let samples: Vec<(Point3<f64>, f32)> = a
        .levels
        .iter()
        .flat_map(|(q, l)| {
            q.iter()
                .zip(l)
                .map(|(q, &l)| (Point3::new(q[0].into(), q[1].into(), q[2].into()), l))
        })
        .collect();
    for separation in [0.0, 0.01, 0.05] {
        let d = a.distinct_candidates(8, separation);
        assert_eq!(d.len(), 8, "plenty of samples for 8");
        assert_eq!(d[0], a.candidates[0], "the keyframe's own position first");
        assert!(d[1..].windows(2).all(|w| w[0].logit >= w[1].logit));
        for (i, c) in d.iter().enumerate() {
            assert!(samples
                .iter()
                .any(|(q, l)| *l == c.logit && (q - c.position).norm() < 1e-6));
            for k in &d[..i] {
                assert!((k.position - c.position).norm() >= separation);
            }
        }
        // Nothing better was skipped but for being too close to one taken.
        let worst = d.last().unwrap().logit;
        for (q, l) in &samples {
            if *l > worst {
                assert!(d
                    .iter()
                    .any(|k| (k.position - q).norm() < separation.max(1e-6)));
            }
        }
    }
    assert!(a.distinct_candidates(0, 0.01).is_empty());
}

#[test]
fn a_network_with_the_per_degree_scalar_film_predicts_and_reads_the_instruction() {
    // The paper's cheap iFiLM: random weights with its keys load, the policy predicts, and
    // another instruction changes the logits of the same samples.
    let mut cfg = PolicyConfig::tiny();
    cfg.model.film_kind = FilmKind::PerDegreeScalar;
    let w = random_weights(&cfg.model, &cfg.extra, 7);
    assert!(w.contains("down_blocks.0.block.transblock.ffn.so3_linear_1.film.weight"));
    assert!(!w.contains("down_blocks.0.block.transblock.ffn.so3_linear_1.cond_encoder.1.weight"));
    let mut p = Policy::from_weights(cfg, &w).unwrap();
    p.seed = 11;
    let cloud = scene(1);
    let a = p
        .predict_detailed(&cloud, &gripper(), &InstructionEmbedding::random(3))
        .unwrap();
    let b = p
        .predict_detailed(&cloud, &gripper(), &InstructionEmbedding::random(4))
        .unwrap();
    assert!(a.levels[0].1.iter().all(|v| v.is_finite()));
    assert_eq!(
        a.levels[0].0, b.levels[0].0,
        "same seed, same first samples"
    );
    let change = a.levels[0]
        .1
        .iter()
        .zip(&b.levels[0].1)
        .map(|(x, y)| (x - y).abs())
        .fold(0.0f32, f32::max);
    assert!(change > 1e-4, "the instruction moves the logits ({change})");
    // Hypernetwork weights do not load as the scalar kind.
    let mut hyper = PolicyConfig::tiny();
    let w_hyper = random_weights(&hyper.model, &hyper.extra, 7);
    hyper.model.film_kind = FilmKind::PerDegreeScalar;
    assert!(Policy::from_weights(hyper, &w_hyper).is_err());
}

fn transform_cloud(c: &PointCloud, m: &Isometry3<f64>) -> PointCloud {
    let pts = c
        .points
        .iter()
        .map(|p| {
            let q = m * Point3::new(f64::from(p.x), f64::from(p.y), f64::from(p.z));
            Point3::new(q.x as f32, q.y as f32, q.z as f32)
        })
        .collect();
    PointCloud::new(FrameId::Base, pts, c.rgb.clone()).unwrap()
}

/// The rigid motion the equivariance tests move the scene by: a few centimetres and a
/// turn about no particular axis.
fn generic_motion() -> Isometry3<f64> {
    Isometry3::from_parts(
        Translation3::new(0.05, -0.1, 0.2),
        UnitQuaternion::from_euler_angles(0.7, -0.4, 1.9),
    )
}

/// Moves the cloud, the gripper and the workspace frame by one rigid motion; returns the
/// translation error (m) and rotation error (rad) of the moved keyframe against the moved
/// original keyframe.
fn moved_keyframe_error(mode: PolicyMode, motion: Isometry3<f64>) -> (f64, f64) {
    moved_keyframe_error_with(PolicyConfig::tiny().with_mode(mode), motion)
}

/// [`moved_keyframe_error`] of the network `cfg` with random weights (seed 7).
fn moved_keyframe_error_with(cfg: PolicyConfig, motion: Isometry3<f64>) -> (f64, f64) {
    let cloud = scene(2);
    let instr = InstructionEmbedding::random(4);
    let mut p = Policy::random(cfg, 7).unwrap();
    p.seed = 5;
    let a = p.predict(&cloud, &gripper(), &instr).unwrap();
    let mut cfg = p.config().clone();
    cfg.base_from_workspace = motion * cfg.base_from_workspace;
    let w = random_weights(&cfg.model, &cfg.extra, 7);
    let mut q = Policy::from_weights(cfg, &w).unwrap();
    q.seed = 5;
    let g = gripper();
    let moved_gripper = GripperPose {
        base_from_tcp: Transform::<Base, Tcp>::from_isometry(motion * g.base_from_tcp.isometry()),
        open: g.open,
    };
    let b = q
        .predict(&transform_cloud(&cloud, &motion), &moved_gripper, &instr)
        .unwrap();
    let expected = motion * a.base_from_tcp.isometry();
    let got = b.base_from_tcp.isometry();
    let dt = (expected.translation.vector - got.translation.vector).norm();
    let dr = expected.rotation.angle_to(&got.rotation);
    assert_eq!(a.gripper_open, b.gripper_open);
    (dt, dr)
}

#[test]
fn level_zero_also_samples_around_the_gripper_and_moves_with_it() {
    let instr = InstructionEmbedding::random(3);
    let cloud = scene(2);
    let config = |near: usize| gated_tiny_sampling(|s| s.near_gripper = near);
    let with = |near: usize| seeded(config(near), 5);
    let per_level = PolicyConfig::tiny().sampling.per_level;
    let plain = with(0)
        .predict_detailed(&cloud, &gripper(), &instr)
        .unwrap();
    let near = with(30)
        .predict_detailed(&cloud, &gripper(), &instr)
        .unwrap();
    let (q0, _) = &near.levels[0];
    assert_eq!(q0.len(), per_level + 30);
    // The box samples are the reference's; the extra ones lie in the ball around the TCP.
    assert_eq!(q0[..per_level], plain.levels[0].0[..]);
    let tcp = gripper().base_from_tcp.translation();
    for q in &q0[per_level..] {
        let d = Vector3::new(f64::from(q[0]), f64::from(q[1]), f64::from(q[2])) - tcp;
        assert!(
            d.norm() < policy::predict::NEAR_GRIPPER_RADIUS_M + 1e-6,
            "{q:?}"
        );
    }
    // A gripper parked above the gripper bounds adds none, and still predicts.
    let parked = GripperPose {
        base_from_tcp: Transform::from_xyz_rpy([0.5, 0.02, 0.9], [3.0, 0.1, 0.4]),
        open: true,
    };
    let high = with(30).predict_detailed(&cloud, &parked, &instr).unwrap();
    assert_eq!(high.levels[0].0.len(), per_level);
    // The ball is drawn in the workspace frame around the moved gripper: the keyframe still
    // moves with the scene to rounding.
    let (dt, _) = moved_keyframe_error_with(config(30), generic_motion());
    assert!(dt < 1e-5, "translation error {dt} m");
}

#[test]
fn points_near_the_gripper_are_sampled_first_and_move_with_it() {
    // A gripper just above the first blob (centre 0.45, 0.1, -0.05; radius 5 cm).
    let g = GripperPose {
        base_from_tcp: Transform::from_xyz_rpy([0.45, 0.1, 0.03], [3.0, 0.1, 0.4]),
        open: false,
    };
    let cloud = scene(2);
    let radius = PolicyConfig::tiny().near_gripper_radius;
    let near_of = |n: usize| {
        let p = seeded(PolicyConfig::tiny().with_near_gripper_points(n), 5);
        let mut rng = ChaCha8Rng::seed_from_u64(1);
        let prep = p.prepare(&cloud, &g, &mut rng).unwrap();
        assert_eq!(prep.xyz.len(), p.config().n_points);
        let mut keys: Vec<[u32; 3]> = prep.xyz.iter().map(|q| q.map(f32::to_bits)).collect();
        keys.sort_unstable();
        keys.dedup();
        assert_eq!(keys.len(), prep.xyz.len(), "a point sampled twice");
        let tcp = g.base_from_tcp.translation();
        prep.xyz
            .iter()
            .filter(|q| {
                (Vector3::new(f64::from(q[0]), f64::from(q[1]), f64::from(q[2])) - tcp).norm()
                    <= radius
            })
            .count()
    };
    let (plain, near) = (near_of(0), near_of(40));
    assert!(
        plain < 30,
        "plain sampling put {plain} points near the gripper"
    );
    assert!(near >= 40, "only {near} points near the gripper");
    // The ball moves with the gripper: the keyframe still moves with the scene (a ball
    // wide enough to reach the blobs from the test's gripper pose).
    let mut cfg = PolicyConfig::tiny()
        .with_mode(PolicyMode::Gated)
        .with_near_gripper_points(40);
    cfg.near_gripper_radius = 0.4;
    let (dt, _) = moved_keyframe_error_with(cfg, generic_motion());
    assert!(dt < 1e-5, "translation error {dt} m");
    // More than the focus box's share is refused with the reason.
    let too_many = PolicyConfig::tiny().with_near_gripper_points(120);
    let err = Policy::random(too_many, 7).unwrap_err().to_string();
    assert!(err.contains("n_near_gripper"), "{err}");
}

#[test]
fn level_zero_also_samples_near_the_objects_and_moves_with_them() {
    let instr = InstructionEmbedding::random(3);
    let cloud = scene(2);
    let config = |near: usize| gated_tiny_sampling(|s| s.near_cloud = near);
    let predict = |near: usize, cloud: &PointCloud| {
        seeded(config(near), 5)
            .predict_detailed(cloud, &gripper(), &instr)
            .unwrap()
    };
    let per_level = PolicyConfig::tiny().sampling.per_level;
    let plain = predict(0, &cloud);
    let near = predict(40, &cloud);
    let (q0, _) = &near.levels[0];
    assert_eq!(q0.len(), per_level + 40);
    assert_eq!(q0[..per_level], plain.levels[0].0[..]);
    // Each extra query lies in the ball around a point of an object (more than 1 cm above
    // the table), none around the table's own points alone.
    let table = PolicyConfig::tiny().table_height;
    let objects: Vec<Point3<f32>> = cloud
        .points
        .iter()
        .filter(|p| f64::from(p.z) > table + 0.01)
        .copied()
        .collect();
    assert!(!objects.is_empty() && objects.len() < cloud.points.len());
    let r = policy::predict::NEAR_CLOUD_RADIUS_M as f32;
    for q in &q0[per_level..] {
        let q = Point3::new(q[0], q[1], q[2]);
        assert!(objects.iter().any(|o| (q - o).norm() < r + 1e-5), "{q:?}");
    }
    // A bare table has no objects: no extra queries, and still a prediction.
    let mut bare = cloud.clone();
    let keep: Vec<bool> = bare
        .points
        .iter()
        .map(|p| f64::from(p.z) <= table)
        .collect();
    let mut it = keep.iter();
    bare.points.retain(|_| *it.next().unwrap());
    if let Some(rgb) = bare.rgb.as_mut() {
        let mut it = keep.iter();
        rgb.retain(|_| *it.next().unwrap());
    }
    assert_eq!(predict(40, &bare).levels[0].0.len(), per_level);
    // The objects are found in the workspace frame: the keyframe moves with the scene.
    let (dt, _) = moved_keyframe_error_with(config(40), generic_motion());
    assert!(dt < 1e-5, "translation error {dt} m");
}

#[test]
fn top_k_apart_keeps_the_best_that_are_far_enough_and_fills_up() {
    use policy::predict::top_k_apart;
    let x = |v: f64| Point3::new(v, 0.0, 0.0);
    let samples = [x(0.0), x(0.05), x(0.3), x(0.32), x(0.7)];
    let logits = [9.0, 8.0, 7.0, 6.0, 1.0];
    // 0.05 and 0.32 sit within 0.1 of a better sample.
    assert_eq!(top_k_apart(&samples, &logits, 3, 0.1), vec![0, 2, 4]);
    assert_eq!(top_k_apart(&samples, &logits, 2, 0.1), vec![0, 2]);
    // Spacing 0 is the plain top-k.
    assert_eq!(top_k_apart(&samples, &logits, 3, 0.0), vec![0, 1, 2]);
    // Too few far enough apart: the rest are the next best, in logit order.
    assert_eq!(top_k_apart(&samples, &logits, 4, 0.5), vec![0, 4, 1, 2]);
    assert_eq!(top_k_apart(&samples, &logits, 9, 0.1).len(), 5);
    assert!(top_k_apart(&[], &[], 3, 0.1).is_empty());
}

#[test]
fn spread_anchors_refine_regions_apart_and_move_with_the_scene() {
    let instr = InstructionEmbedding::random(3);
    let cloud = scene(2);
    let config = |spread: bool| gated_tiny_sampling(|s| s.spread_anchors = spread);
    // Sampling seed 0: its best level-0 samples crowd together (most seeds' do not).
    let predict = |spread: bool| {
        seeded(config(spread), 0)
            .predict_detailed(&cloud, &gripper(), &instr)
            .unwrap()
    };
    let s = PolicyConfig::tiny().sampling;
    let r1 = s.fine_ball_diameter / 2.0;
    let as_points = |q: &[[f32; 3]]| -> Vec<Point3<f64>> {
        q.iter()
            .map(|q| Point3::new(f64::from(q[0]), f64::from(q[1]), f64::from(q[2])))
            .collect()
    };
    let (plain, spread) = (predict(false), predict(true));
    // Level 0 is drawn the same way; only the anchors kept from it differ.
    assert_eq!(plain.levels[0], spread.levels[0]);
    let (q0, logits0) = &spread.levels[0];
    let samples = as_points(q0);
    let apart = policy::predict::top_k_apart(&samples, logits0, s.top_k, r1);
    let best = policy::predict::top_k(logits0, s.top_k);
    assert_eq!(apart[0], best[0]);
    for (i, &a) in apart.iter().enumerate() {
        for &b in &apart[..i] {
            assert!((samples[a] - samples[b]).norm() >= r1);
        }
    }
    // Here two of the best three crowd together, so the two rules pick different anchors.
    assert_ne!(apart, best);
    // Level 1 samples around the kept anchors, each anchor's share in turn.
    let per = s.per_level / s.top_k;
    for (anchors, levels) in [(&apart, &spread.levels), (&best, &plain.levels)] {
        let q1 = as_points(&levels[1].0);
        assert_eq!(q1.len(), per * s.top_k);
        for (j, chunk) in q1.chunks(per).enumerate() {
            let a = samples[anchors[j]];
            assert!(
                chunk.iter().all(|q| (q - a).norm() < r1 + 1e-5),
                "anchor {j}"
            );
        }
    }
    let (dt, _) = moved_keyframe_error_with(config(true), generic_motion());
    assert!(dt < 1e-5, "translation error {dt} m");
}

#[test]
fn moving_the_scene_moves_the_keyframe_in_equivariant_mode() {
    let motion = generic_motion();
    let mode = PolicyMode::Equivariant { s2_grid: 16 };
    let (dt, dr) = moved_keyframe_error(mode, motion);
    // The network's own equivariance error on this scene (logits), which bounds the rest.
    let p = tiny(mode);
    let mut rng = ChaCha8Rng::seed_from_u64(5);
    let (prep, queries) = prepared_with_queries(&p, &mut rng);
    let errs = p
        .equivariance_errors(
            &prep,
            &InstructionEmbedding::random(4),
            &queries,
            [0.5, 0.0, 0.2],
            &[motion],
        )
        .unwrap()[0];
    println!(
        "equivariant mode: translation error {dt:.2e} m, rotation error {dr:.2e} rad; logits \
         (trans, open, rot) relative error {errs:?}"
    );
    assert!(errs.iter().all(|e| *e < 1e-3), "{errs:?}");
    // The samples are drawn in the workspace frame and moved with it, so with the same
    // discrete choices the answer is the moved sample: only f32/f64 rounding remains. A
    // flipped top-k choice would move it by a sample spacing of the last level (~5 mm), so
    // 1e-5 m separates the two cases.
    assert!(dt < 1e-5, "translation error {dt} m");
    // The refined rotation is the local maximum of a logit function that moves with the scene
    // up to the logit error above (~1e-4 relative with 16 x 16 S2 grids). Near a maximum a
    // logit error e moves the argmax by about sqrt(2e / curvature): a few mrad for a flat
    // maximum of these random weights (1.8e-3 rad measured here; 2.7e-4 rad with 32 x 32
    // grids, which are too slow for this test). 5e-3 rad (0.3 degrees) is that bound; the
    // coarse grid the search starts on is spaced 30 degrees, so a grid-level answer would
    // fail it.
    assert!(dr < 5e-3, "rotation error {dr} rad");
}

/// Scene 2 prepared for `p`, and queries a few millimetres off every fourth input point:
/// the input of the equivariance measurements.
fn prepared_with_queries(
    p: &Policy,
    rng: &mut ChaCha8Rng,
) -> (policy::predict::PreparedInput, Vec<[f32; 3]>) {
    let prep = p.prepare(&scene(2), &gripper(), rng).unwrap();
    let queries = prep
        .xyz
        .iter()
        .step_by(4)
        .map(|p| [p[0] + 0.003, p[1] - 0.002, p[2] + 0.001])
        .collect();
    (prep, queries)
}

#[test]
fn gated_mode_is_equivariant_to_rounding_and_its_argmax_moves_with_the_input() {
    // Gated activations, Euclidean up-sampling and turning gripper jitter leave no
    // approximation in the network: what remains is f32 rounding (coordinates of ~0.5 m are
    // rounded to ~3e-8 m, features carry ~1e-7 relative rounding through the blocks) and the
    // discrete choices (FPS, kNN, max-pool), which only change at near-ties.
    let p = tiny(PolicyMode::Gated);
    let mut rng = ChaCha8Rng::seed_from_u64(5);
    let (prep, queries) = prepared_with_queries(&p, &mut rng);
    let motions: Vec<Isometry3<f64>> = (0..3)
        .map(|_| {
            let r = nalgebra::Rotation3::from_matrix(&common::random_rotation(&mut rng));
            Isometry3::from_parts(
                Translation3::new(
                    rng.random_range(-0.2..0.2),
                    rng.random_range(-0.2..0.2),
                    rng.random_range(-0.2..0.2),
                ),
                UnitQuaternion::from_rotation_matrix(&r),
            )
        })
        .collect();
    let report = p
        .equivariance_report(
            &prep,
            &InstructionEmbedding::random(4),
            &queries,
            [0.5, 0.0, 0.2],
            &motions,
        )
        .unwrap();
    for m in &report {
        println!("{m:?}");
        // With a discrete choice flipped the network is a different function near the tie;
        // forced onto the same choices it must agree.
        let e = m.errors_same_choices.unwrap_or(m.errors);
        assert!(e.iter().all(|e| *e < 1e-5), "{m:?}");
        // The refined argmax stops at 1e-4 rad steps; logit errors of 1e-6 relative move a
        // maximum by ~sqrt(1e-6) at most.
        assert!(m.argmax_angle < 2e-3, "{m:?}");
    }
}

#[test]
fn bad_input_is_refused_with_the_reason() {
    let mut p = tiny(PolicyMode::Parity);
    let instr = InstructionEmbedding::random(3);
    let g = gripper();
    let e = p
        .predict(&PointCloud::empty(FrameId::Base), &g, &instr)
        .unwrap_err();
    assert!(matches!(e, PolicyError::EmptyCloud), "{e}");
    let mut c = scene(1);
    c.points[7].y = f32::NAN;
    let e = p.predict(&c, &g, &instr).unwrap_err();
    assert!(
        matches!(e, PolicyError::NonFinitePoint { index: 7, .. }),
        "{e}"
    );
    let mut c = scene(1);
    c.points.truncate(100);
    c.rgb = None;
    let e = p.predict(&c, &g, &instr).unwrap_err();
    assert!(
        matches!(
            e,
            PolicyError::TooFewPoints {
                needed: 128,
                got: 100,
                ..
            }
        ),
        "{e}"
    );
    let mut c = scene(1);
    c.frame = FrameId::Camera(0);
    let e = p.predict(&c, &g, &instr).unwrap_err();
    assert!(matches!(e, PolicyError::WrongFrame { .. }), "{e}");
    let short = InstructionEmbedding::new(vec![0.0; 53 * 100], 53, 100).unwrap();
    let e = p.predict(&scene(1), &g, &short).unwrap_err();
    assert!(matches!(e, PolicyError::ShapeMismatch { .. }), "{e}");
}

fn temp(name: &str) -> std::path::PathBuf {
    std::env::temp_dir().join(format!("policy_test_{}_{name}", std::process::id()))
}

#[test]
fn instruction_files_are_read_and_checked() {
    let path = temp("instr.safetensors");
    let instr = InstructionEmbedding::random(9);
    instr.save(&path).unwrap();
    assert_eq!(InstructionEmbedding::from_file(&path).unwrap(), instr);
    let e = InstructionEmbedding::from_file(&temp("missing.safetensors")).unwrap_err();
    assert!(matches!(e, PolicyError::Io { .. }), "{e}");
    std::fs::write(&path, b"not a safetensors file").unwrap();
    let e = InstructionEmbedding::from_file(&path).unwrap_err();
    assert!(matches!(e, PolicyError::Safetensors { .. }), "{e}");
    // Any [tokens, width] reads (MiniLM's states are [tokens, 384]); a flat tensor does not.
    let minilm = InstructionEmbedding::new(vec![0.5; 9 * 384], 9, 384).unwrap();
    minilm.save(&path).unwrap();
    assert_eq!(InstructionEmbedding::from_file(&path).unwrap(), minilm);
    let mut flat = std::collections::HashMap::new();
    flat.insert(
        "instruction".to_string(),
        policy::fixtures::StoredTensor {
            shape: vec![53 * 512],
            data: policy::fixtures::TensorData::F32(vec![0.0; 53 * 512]),
        },
    );
    Weights::from_tensors("flat", flat).save(&path).unwrap();
    let e = InstructionEmbedding::from_file(&path).unwrap_err();
    assert!(
        matches!(&e, PolicyError::ShapeMismatch { got, .. } if got == &vec![53 * 512]),
        "{e}"
    );
    std::fs::remove_file(&path).unwrap();
}

#[test]
fn a_network_with_minilm_wide_tokens_runs_on_minilm_embeddings_only() {
    // A network whose instruction encoder reads 384-wide tokens (all-MiniLM-L6-v2's), fed
    // 11 tokens of that width; CLIP's 512-wide tokens are refused with both widths named.
    let mut cfg = PolicyConfig::tiny();
    cfg.extra.token_dim = 384;
    let mut p = Policy::random(cfg, 7).unwrap();
    let mut rng = ChaCha8Rng::seed_from_u64(3);
    let values = (0..11 * 384)
        .map(|_| rng.random_range(-1.0..1.0f32))
        .collect();
    let minilm = InstructionEmbedding::new(values, 11, 384).unwrap();
    let k = p.predict(&scene(1), &gripper(), &minilm).unwrap();
    assert!(k.base_from_tcp.translation().iter().all(|v| v.is_finite()));
    let e = p
        .predict(&scene(1), &gripper(), &InstructionEmbedding::random(1))
        .unwrap_err();
    assert!(
        matches!(&e, PolicyError::ShapeMismatch { expected, got, .. } if expected == &vec![53, 384] && got == &vec![53, 512]),
        "{e}"
    );
}

#[test]
fn own_weights_round_trip_and_bad_checkpoints_are_named() {
    let cfg = PolicyConfig::tiny();
    let w = random_weights(&cfg.model, &cfg.extra, 21);
    let path = temp("weights.safetensors");
    w.save(&path).unwrap();
    let mut a = Policy::from_weights(cfg.clone(), &w).unwrap();
    let mut b = Policy::load(cfg.clone(), &path).unwrap();
    std::fs::remove_file(&path).unwrap();
    let (cloud, instr) = (scene(3), InstructionEmbedding::random(1));
    let pa = a.predict_detailed(&cloud, &gripper(), &instr).unwrap();
    let pb = b.predict_detailed(&cloud, &gripper(), &instr).unwrap();
    assert_eq!(pa.keyframe, pb.keyframe);
    assert_eq!(pa.levels, pb.levels);

    // A checkpoint without a key, or with a misshapen one, is refused naming the key.
    let reread = Weights::from_file(&{
        w.save(&path).unwrap();
        path.clone()
    })
    .unwrap();
    std::fs::remove_file(&path).unwrap();
    assert_eq!(reread.len(), w.len());
    let key = "up_blocks.1.block.transblock.ga.so2_conv_1.fc_m0.weight";
    assert!(w.contains(key));
    let mut tensors = std::collections::HashMap::new();
    for k in w.keys() {
        if k != key {
            let (shape, v) = w.f32_any(k).unwrap();
            tensors.insert(
                k.to_string(),
                policy::fixtures::StoredTensor {
                    shape,
                    data: policy::fixtures::TensorData::F32(v),
                },
            );
        }
    }
    let e = Policy::from_weights(
        cfg.clone(),
        &Weights::from_tensors("edited", tensors.clone()),
    )
    .unwrap_err();
    assert!(
        matches!(&e, PolicyError::MissingTensor { name, .. } if name == key),
        "{e}"
    );
    tensors.insert(
        key.to_string(),
        policy::fixtures::StoredTensor {
            shape: vec![2, 3],
            data: policy::fixtures::TensorData::F32(vec![0.0; 6]),
        },
    );
    let e = Policy::from_weights(cfg, &Weights::from_tensors("edited", tensors)).unwrap_err();
    assert!(
        matches!(&e, PolicyError::ShapeMismatch { name, got, .. } if name == key && got == &vec![2, 3]),
        "{e}"
    );
}

/// The tiny policy with the plain (ablation) heads in `mode`.
fn tiny_plain(mode: PolicyMode) -> Policy {
    let mut cfg = PolicyConfig::tiny().with_mode(mode);
    cfg.model.heads = HeadKind::Plain;
    let w = random_weights(&cfg.model, &cfg.extra, 7);
    Policy::from_weights(cfg, &w).unwrap()
}

#[test]
fn plain_heads_predict_a_keyframe_end_to_end() {
    let mut p = tiny_plain(PolicyMode::Gated);
    let instr = InstructionEmbedding::random(3);
    let k = p.predict(&scene(1), &gripper(), &instr).unwrap();
    let t = k.base_from_tcp.isometry();
    assert!(t.translation.vector.iter().all(|v| v.is_finite()));
    assert!(t.rotation.coords.iter().all(|v| v.is_finite()));
    // Deterministic per seed, as the equivariant policy.
    let again = p.predict(&scene(1), &gripper(), &instr).unwrap();
    assert_eq!(k, again);
}

#[test]
fn plain_heads_are_not_equivariant() {
    // Same U-net, same scene and motion: the gated equivariant heads move with the scene to
    // rounding, the plain heads (raw offsets and query positions) do not.
    let motion = generic_motion();
    let errors = |p: &Policy| {
        let mut rng = ChaCha8Rng::seed_from_u64(5);
        let (prep, queries) = prepared_with_queries(p, &mut rng);
        let m = p
            .equivariance_report(
                &prep,
                &InstructionEmbedding::random(4),
                &queries,
                [0.5, 0.0, 0.2],
                &[motion],
            )
            .unwrap()
            .remove(0);
        m.errors_same_choices.unwrap_or(m.errors)
    };
    let equivariant = errors(&tiny(PolicyMode::Gated));
    let plain = errors(&tiny_plain(PolicyMode::Gated));
    println!("relative errors (trans, open, rot): equivariant {equivariant:?}, plain {plain:?}");
    assert!(equivariant[0] < 1e-4, "{equivariant:?}");
    assert!(plain[0] > 1e-2, "{plain:?}");
    assert!(plain[2] > 1e-2, "{plain:?}");
}

#[test]
fn a_raised_focus_floor_keeps_the_objects_points_and_moves_with_the_scene() {
    // A table top just above the table height (inside EquAct's focus box) and one small
    // object 3 cm above it: farthest point sampling at the table's spacing sees the object
    // through a handful of points.
    let cfg = PolicyConfig::tiny();
    let table = cfg.table_height as f32;
    let mut rng = ChaCha8Rng::seed_from_u64(3);
    let mut pts = Vec::new();
    for _ in 0..600 {
        pts.push(Point3::new(
            rng.random_range(0.25..0.9f32),
            rng.random_range(-0.33..0.33f32),
            table + 0.002,
        ));
    }
    for _ in 0..60 {
        pts.push(Point3::new(
            0.5 + rng.random_range(-0.02..0.02f32),
            rng.random_range(-0.02..0.02f32),
            table + 0.03 + rng.random_range(0.0..0.02f32),
        ));
    }
    let cloud = PointCloud::new(FrameId::Base, pts, None).unwrap();
    let on_object = |floor: f64| {
        let p = seeded(PolicyConfig::tiny().with_focus_above_table(floor), 5);
        let mut rng = ChaCha8Rng::seed_from_u64(1);
        let prep = p.prepare(&cloud, &gripper(), &mut rng).unwrap();
        assert_eq!(prep.xyz.len(), p.config().n_points);
        prep.xyz.iter().filter(|q| q[2] > table + 0.01).count()
    };
    let (plain, raised) = (on_object(0.0), on_object(0.01));
    assert!(
        plain < 20,
        "EquAct's box kept {plain} of the object's 60 points"
    );
    assert_eq!(
        raised, 60,
        "the raised box kept {raised} of the object's 60 points"
    );
    // The floor is a plane of the workspace frame: the keyframe moves with the scene.
    let cfg = PolicyConfig::tiny()
        .with_mode(PolicyMode::Gated)
        .with_focus_above_table(0.01);
    let (dt, _) = moved_keyframe_error_with(cfg, generic_motion());
    assert!(dt < 1e-5, "translation error {dt} m");
    // A floor below the table or above the gripper's reach is refused with the reason.
    for bad in [-0.01, 1.0, f64::NAN] {
        let err = Policy::random(PolicyConfig::tiny().with_focus_above_table(bad), 7)
            .unwrap_err()
            .to_string();
        assert!(err.contains("focus_above_table"), "{err}");
    }
}
