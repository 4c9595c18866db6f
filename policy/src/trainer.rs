//! Training the network on demonstrations: one sample's loss and parameter gradients
//! through the taped network ([`crate::autodiff::model`]), AdamW steps over mini-batches,
//! and checkpoints that resume exactly.
//!
//! A training sample is an observation (the fused cloud in the base frame, the gripper
//! pose), an instruction embedding and the expert's next keyframe. Each use of a sample
//! draws, from the step's seed: the paper's rotation augmentation (cloud, gripper and
//! keyframe moved together), the input preparation (crop, farthest-point sampling,
//! permutation, gripper jitter) and the coarse-to-fine translation queries with the ground
//! truth inserted at every level. The rotation head is read at the true position (teacher
//! forcing), as the reference trains it.

use std::path::{Path, PathBuf};

use cell_types::{Keyframe, PointCloud};
use nalgebra::{Matrix3, Point3};
use rand::SeedableRng;
use rand_chacha::ChaCha8Rng;

use crate::autodiff::model::{encode, rot_query, trans_logits, NetworkInput};
use crate::autodiff::Tape;
use crate::error::{PolicyError, Result};
use crate::grids::{so3_healpix_grid, GridRotation};
use crate::heads::ROT_LMAX;
use crate::optim::{AdamW, AdamWConfig};
use crate::predict::{
    check_cloud_query_share, first_level_queries, in_box, object_points, prepare_input, top_k,
    uniform_in_ball, GripperPose, InstructionEmbedding, PolicyConfig,
};
use crate::rotation_head::RotationHead;
use crate::so3::WignerCalculator;
use crate::training::{
    keyframe_rotation, move_sample, open_loss, rotation_loss, shift_held, sideways_in_disc,
    translation_loss, RotationAugmentation,
};
use crate::weights::Weights;

/// The paper's translation sampling levels in training: the whole gripper box, then balls
/// of 12.5 cm and 3.1 cm radius around the best anchors.
pub const TRAIN_LEVELS: usize = 3;

/// Everything training needs besides the data and the weights.
#[derive(Debug, Clone, PartialEq)]
pub struct TrainConfig {
    /// The network and its input preparation (mode, point count, boxes).
    pub policy: PolicyConfig,
    /// The optimiser.
    pub optim: AdamWConfig,
    /// Sampling levels of the translation loss ([`TRAIN_LEVELS`], the paper's); the
    /// policy's own `sampling` is for inference and may refine further.
    pub levels: usize,
    /// Translation queries per sampling level (the ground truth is added to each level).
    pub queries_per_level: usize,
    /// Share of the first level's queries drawn near the observed cloud instead of uniform
    /// in the gripper box ([`first_level_queries`]; 0, the paper's, draws them all uniform).
    pub cloud_query_share: f64,
    /// Anchors kept per level (10 in the reference's training).
    pub top_k: usize,
    /// HEALPix level of the SO(3) grid the rotation loss runs on (72·8^level rotations).
    pub rotation_grid_level: u32,
    /// Apply the paper's rotation augmentation.
    pub augment: bool,
    /// Largest sideways motion (m) of the gripper and the object it holds in the samples
    /// whose keyframe the scene places ([`TrainSample::placed_by_scene`]), drawn uniform in
    /// a horizontal disc per sample and step, the keyframe kept (0: none, the paper's).
    /// Demonstrations show the hand exactly where the expert put it, so without it the
    /// network may place such a keyframe relative to the hand and carry every earlier
    /// step's error into it (`equact policy follow` measures this).
    pub held_shift_m: f64,
    /// Samples per optimiser step.
    pub batch: usize,
    /// Seed of every random draw (step k uses `seed + k`).
    pub seed: u64,
    /// Worker threads over the samples of a batch (the result does not depend on it).
    pub threads: usize,
}

/// One demonstration step: what the network saw, what it should answer.
#[derive(Debug, Clone)]
pub struct TrainSample {
    /// The fused cloud (base frame).
    pub cloud: PointCloud,
    /// The gripper before the step.
    pub gripper: GripperPose,
    /// The task's instruction.
    pub instruction: InstructionEmbedding,
    /// The expert's keyframe.
    pub target: Keyframe,
    /// Positions (base frame) the instruction must tell from the target: where the same
    /// scene's other instructions go at this step. Each one inside the gripper box is added
    /// to the first sampling level's queries, so the loss always pushes the field down
    /// there (empty: the paper's loss).
    pub negatives: Vec<Point3<f64>>,
    /// The keyframe is placed by the scene while the gripper carries a free object (a roll
    /// carried to the spindle and let go over it): moving the hand and what it holds leaves
    /// the keyframe where it is, so [`TrainConfig::held_shift_m`] may move them.
    pub placed_by_scene: bool,
}

impl TrainSample {
    /// Whether [`TrainConfig::held_shift_m`] may move this sample: its keyframe is placed
    /// by the scene and the gripper holds something (closed) before the step.
    pub fn held_shift_applies(&self) -> bool {
        self.placed_by_scene && !self.gripper.open
    }
}

/// The three loss terms (per sample, or averaged over a batch).
#[derive(Debug, Clone, Copy, Default, PartialEq)]
pub struct Losses {
    /// Translation cross-entropy, summed over the sampling levels.
    pub translation: f64,
    /// Gripper-open binary cross-entropy.
    pub open: f64,
    /// Rotation soft cross-entropy.
    pub rotation: f64,
}

impl Losses {
    /// The training objective: the sum of the three terms.
    pub fn total(&self) -> f64 {
        self.translation + self.open + self.rotation
    }

    fn add(&mut self, o: &Losses, w: f64) {
        self.translation += w * o.translation;
        self.open += w * o.open;
        self.rotation += w * o.rotation;
    }
}

/// Gradients by full parameter key, in the order the network first read the parameters.
pub type ParamGradients = Vec<(String, Vec<f32>)>;

/// The rotation grid of the loss with its Wigner matrices (computed once).
#[derive(Debug, Clone)]
pub struct LossGrid {
    rotations: Vec<Matrix3<f64>>,
    wigners: Vec<Vec<f64>>,
}

impl LossGrid {
    /// The HEALPix SO(3) grid of `level`.
    pub fn new(level: u32) -> Result<Self> {
        let grid: Vec<GridRotation> = so3_healpix_grid(level);
        let calc = WignerCalculator::new(ROT_LMAX)?;
        Ok(Self {
            wigners: RotationHead::grid_wigners(&calc, &grid)?,
            rotations: grid.iter().map(|g| g.matrix).collect(),
        })
    }

    /// Number of rotations.
    pub fn len(&self) -> usize {
        self.rotations.len()
    }

    /// Whether the grid is empty.
    pub fn is_empty(&self) -> bool {
        self.rotations.is_empty()
    }
}

fn as_f32(p: &Point3<f64>) -> [f32; 3] {
    [p.x as f32, p.y as f32, p.z as f32]
}

/// The loss of one sample and the gradient of every parameter (full key → gradient).
pub fn sample_gradients(
    weights: &Weights,
    cfg: &TrainConfig,
    grid: &LossGrid,
    sample: &TrainSample,
    rng: &mut ChaCha8Rng,
) -> Result<(Losses, ParamGradients)> {
    let pc = &cfg.policy;
    let (mut cloud, mut gripper, mut target) =
        (sample.cloud.clone(), sample.gripper, sample.target);
    let mut negatives = sample.negatives.clone();
    if cfg.held_shift_m > 0.0 && sample.held_shift_applies() {
        // Before the rotation, which then turns the moved sample as a whole.
        shift_held(
            &mut cloud,
            &mut gripper,
            sideways_in_disc(cfg.held_shift_m, rng),
        );
    }
    if cfg.augment {
        let motion = RotationAugmentation::physical(pc.workspace_bounds).sample(rng);
        move_sample(&motion, &mut cloud, &mut gripper, &mut target);
        for n in &mut negatives {
            *n = motion * *n;
        }
    }
    let prep = prepare_input(pc, &cloud, &gripper, rng)?;
    if sample.instruction.dim() != weights.shape_of("instruction_embedding.weight")?[1] {
        return Err(PolicyError::ShapeMismatch {
            name: "instruction embedding (token width)".into(),
            expected: weights.shape_of("instruction_embedding.weight")?,
            got: vec![sample.instruction.tokens(), sample.instruction.dim()],
        });
    }
    let mut t = Tape::new();
    let s = weights.scope("");
    let model = &pc.model;
    let enc = encode(
        &mut t,
        &s,
        model,
        NetworkInput {
            xyz: &prep.xyz,
            rgb: &prep.rgb,
            gripper: &prep.gripper,
            gripper_eps: &prep.gripper_eps,
            instruction: sample.instruction.values(),
        },
    )?;
    let truth_base = target.base_from_tcp.translation();
    let truth = [
        truth_base.x as f32,
        truth_base.y as f32,
        truth_base.z as f32,
    ];
    let ws = pc.base_from_workspace;
    let truth_ws = ws.inverse() * Point3::from(truth_base);
    let objects_ws = if cfg.cloud_query_share > 0.0 {
        object_points(&cloud, pc)
    } else {
        Vec::new()
    };
    let mut losses = Losses::default();
    let mut seeds: Vec<(crate::autodiff::Var, Vec<f32>)> = Vec::new();
    let mut anchors: Vec<Point3<f64>> = Vec::new();
    let levels = cfg.levels;
    for level in 0..levels {
        let mut samples: Vec<Point3<f64>> = if level == 0 {
            first_level_queries(
                rng,
                &pc.gripper_bounds,
                &objects_ws,
                cfg.queries_per_level,
                cfg.cloud_query_share,
            )?
        } else {
            let r = pc.sampling.fine_ball_diameter / 4f64.powi(level as i32 - 1) / 2.0;
            let per = (cfg.queries_per_level / anchors.len().max(1)).max(1);
            let mut out = Vec::with_capacity(cfg.queries_per_level);
            for a in &anchors {
                out.extend(uniform_in_ball(rng, a, r, &pc.gripper_bounds, per)?);
            }
            out
        };
        if level == 0 {
            // After the draws, so a sample without negatives draws what it always did.
            samples.extend(
                negatives
                    .iter()
                    .map(|n| ws.inverse() * n)
                    .filter(|n| in_box(n, &pc.gripper_bounds)),
            );
        }
        samples.push(truth_ws);
        let queries: Vec<[f32; 3]> = samples.iter().map(|q| as_f32(&(ws * q))).collect();
        let logits = trans_logits(&mut t, &s, model, &enc, &queries)?;
        let lg = translation_loss(t.value(logits), &queries, truth)?;
        losses.translation += lg.loss;
        seeds.push((logits, lg.grad.iter().map(|&g| g as f32).collect()));
        let order = top_k(t.value(logits), cfg.top_k);
        anchors = order.iter().map(|&i| samples[i]).collect();
    }
    let (open, rot) = rot_query(&mut t, &s, model, &enc, truth, &grid.wigners)?;
    let lo = open_loss(t.value(open)[0], target.gripper_open)?;
    losses.open = lo.loss;
    seeds.push((open, lo.grad.iter().map(|&g| g as f32).collect()));
    let rot_values: Vec<f64> = t.value(rot).iter().map(|&v| f64::from(v)).collect();
    let lr = rotation_loss(&rot_values, &grid.rotations, &keyframe_rotation(&target))?;
    losses.rotation = lr.loss;
    seeds.push((rot, lr.grad.iter().map(|&g| g as f32).collect()));
    let refs: Vec<(crate::autodiff::Var, &[f32])> =
        seeds.iter().map(|(v, g)| (*v, g.as_slice())).collect();
    let grads = t.backward_many(&refs)?;
    Ok((losses, t.param_gradients(&grads)))
}

/// What one optimiser step did.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct StepReport {
    /// The step's number (1-based, counted over resumes).
    pub step: u64,
    /// Mean losses over the batch.
    pub losses: Losses,
    /// Norm of the mean gradient over all parameters.
    pub grad_norm: f64,
}

/// Weights, optimiser and configuration of a training run.
#[derive(Debug, Clone)]
pub struct Trainer {
    /// Configuration.
    pub cfg: TrainConfig,
    /// The parameters being trained.
    pub weights: Weights,
    /// The optimiser (its step counts the updates so far).
    pub optim: AdamW,
    grid: LossGrid,
}

/// File names inside a checkpoint directory.
pub const WEIGHTS_FILE: &str = "model.safetensors";
/// The optimiser state's file.
pub const OPTIMIZER_FILE: &str = "optimizer.safetensors";

impl Trainer {
    /// Starts from `weights` (random or pre-trained).
    pub fn new(cfg: TrainConfig, mut weights: Weights) -> Result<Self> {
        if cfg.batch == 0 || cfg.queries_per_level == 0 || cfg.top_k == 0 || cfg.levels == 0 {
            return Err(PolicyError::BadConfig(format!(
                "training config: batch ({}), queries per level ({}), anchors per level ({}) and \
                 sampling levels ({}) must all be at least 1",
                cfg.batch, cfg.queries_per_level, cfg.top_k, cfg.levels
            )));
        }
        check_cloud_query_share(cfg.cloud_query_share)?;
        if !(cfg.held_shift_m.is_finite() && cfg.held_shift_m >= 0.0) {
            return Err(PolicyError::BadConfig(format!(
                "training config: the held-object shift must be a distance of at least 0 m, \
                 got {}",
                cfg.held_shift_m
            )));
        }
        cfg.policy.check()?;
        // The inference commands read the point count from the file (see `N_POINTS_KEY`).
        weights.set_metadata(
            crate::weights::N_POINTS_KEY,
            cfg.policy.n_points.to_string(),
        );
        weights.set_metadata(
            crate::weights::NEAR_GRIPPER_POINTS_KEY,
            cfg.policy.n_near_gripper.to_string(),
        );
        weights.set_metadata(
            crate::weights::FOCUS_ABOVE_TABLE_KEY,
            cfg.policy.focus_above_table.to_string(),
        );
        Ok(Self {
            grid: LossGrid::new(cfg.rotation_grid_level)?,
            optim: AdamW::new(cfg.optim),
            cfg,
            weights,
        })
    }

    /// The loss and gradients of `batch` at the current weights without updating them,
    /// with the draws the next step will use.
    pub fn evaluate(&self, batch: &[&TrainSample]) -> Result<(Losses, ParamGradients)> {
        self.gradients(batch, self.cfg.seed.wrapping_add(self.optim.step))
    }

    /// The mean loss and gradients of `batch` with the draws of `draw_seed` (augmentation,
    /// input sampling, translation queries).
    pub fn gradients(
        &self,
        batch: &[&TrainSample],
        draw_seed: u64,
    ) -> Result<(Losses, ParamGradients)> {
        // Each sample draws from its own stream, so the result does not depend on how the
        // batch is split over threads.
        let one = |i: usize, sample: &TrainSample| {
            let mut rng = ChaCha8Rng::seed_from_u64(draw_seed);
            rng.set_stream(i as u64);
            sample_gradients(&self.weights, &self.cfg, &self.grid, sample, &mut rng)
        };
        let threads = self.cfg.threads.clamp(1, batch.len().max(1));
        let results: Vec<Result<(Losses, ParamGradients)>> = if threads == 1 {
            batch.iter().enumerate().map(|(i, s)| one(i, s)).collect()
        } else {
            // Explicit worker threads for the samples of one batch (training only; nothing
            // outlives the call).
            let per = batch.len().div_ceil(threads);
            std::thread::scope(|scope| {
                let handles: Vec<_> = batch
                    .chunks(per)
                    .enumerate()
                    .map(|(c, chunk)| {
                        let one = &one;
                        scope.spawn(move || {
                            chunk
                                .iter()
                                .enumerate()
                                .map(|(j, s)| one(c * per + j, s))
                                .collect::<Vec<_>>()
                        })
                    })
                    .collect();
                handles
                    .into_iter()
                    .flat_map(|h| {
                        h.join().unwrap_or_else(|_| {
                            vec![Err(PolicyError::NonFinite {
                                what: "a training worker thread panicked".into(),
                            })]
                        })
                    })
                    .collect()
            })
        };
        let mut mean = Losses::default();
        let mut total: ParamGradients = Vec::new();
        let w = 1.0 / batch.len().max(1) as f64;
        for r in results {
            let (l, g) = r?;
            mean.add(&l, w);
            if total.is_empty() {
                total = g;
                for (_, v) in &mut total {
                    v.iter_mut().for_each(|x| *x *= w as f32);
                }
            } else {
                for ((k, acc), (k2, v)) in total.iter_mut().zip(g) {
                    if *k != k2 {
                        return Err(PolicyError::Sidecar {
                            path: "training".into(),
                            message: format!(
                                "parameter order changed between samples ({k} vs {k2})"
                            ),
                        });
                    }
                    for (a, x) in acc.iter_mut().zip(v) {
                        *a += w as f32 * x;
                    }
                }
            }
        }
        Ok((mean, total))
    }

    /// One AdamW step on the mean loss of `batch`. A non-finite loss or gradient leaves the
    /// weights and the optimiser unchanged and is an error.
    pub fn step(&mut self, batch: &[&TrainSample]) -> Result<StepReport> {
        if batch.is_empty() {
            return Err(PolicyError::TooFewPoints {
                what: "training batch (samples)",
                needed: 1,
                got: 0,
            });
        }
        let (losses, grads) = self.evaluate(batch)?;
        if !losses.total().is_finite() {
            return Err(PolicyError::NonFinite {
                what: format!(
                    "training loss at step {} (weights unchanged)",
                    self.optim.step + 1
                ),
            });
        }
        let grad_norm = grads
            .iter()
            .flat_map(|(_, g)| g.iter())
            .map(|&x| f64::from(x).powi(2))
            .sum::<f64>()
            .sqrt();
        self.optim.update(&mut self.weights, &grads)?;
        Ok(StepReport {
            step: self.optim.step,
            losses,
            grad_norm,
        })
    }

    /// Writes the weights and the optimiser state into `dir` (each through a temporary file
    /// and a rename, so a crash leaves the previous checkpoint whole).
    pub fn save(&self, dir: &Path) -> Result<()> {
        std::fs::create_dir_all(dir).map_err(|e| io_error(dir, e))?;
        let tmp_w = dir.join(format!("{WEIGHTS_FILE}.partial"));
        let tmp_o = dir.join(format!("{OPTIMIZER_FILE}.partial"));
        self.weights.save(&tmp_w)?;
        self.optim.save(&tmp_o)?;
        // The optimiser first: a crash between the renames leaves new moments with old
        // weights, which resumes (one step's moments ahead) instead of failing.
        rename(&tmp_o, &dir.join(OPTIMIZER_FILE))?;
        rename(&tmp_w, &dir.join(WEIGHTS_FILE))
    }

    /// Resumes from a checkpoint directory written by [`Trainer::save`].
    pub fn resume(cfg: TrainConfig, dir: &Path) -> Result<Self> {
        let weights = Weights::from_file(&dir.join(WEIGHTS_FILE))?;
        let optim = AdamW::load(cfg.optim, &dir.join(OPTIMIZER_FILE), &weights)?;
        let mut t = Self::new(cfg, weights)?;
        t.optim = optim;
        Ok(t)
    }
}

fn io_error(path: &Path, e: std::io::Error) -> PolicyError {
    PolicyError::Io {
        path: PathBuf::from(path),
        source: e,
    }
}

fn rename(from: &Path, to: &Path) -> Result<()> {
    std::fs::rename(from, to).map_err(|e| io_error(to, e))
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::init::random_weights;
    use crate::model::{EquFieldUnet, HeadKind};
    use crate::predict::{synthetic_scene, uniform_in_box, PolicyMode, CLOUD_QUERY_RADIUS_M};
    use cell_types::{Base, Tcp, Transform};
    use nalgebra::{Translation3, UnitQuaternion, Vector3};

    fn pose(x: f64, y: f64, z: f64, yaw: f64) -> Transform<Base, Tcp> {
        let r = UnitQuaternion::from_axis_angle(&Vector3::z_axis(), yaw)
            * UnitQuaternion::from_axis_angle(&Vector3::x_axis(), std::f64::consts::PI);
        Transform::from_isometry(nalgebra::Isometry3::from_parts(
            Translation3::new(x, y, z),
            r,
        ))
    }

    fn config(mode: PolicyMode) -> TrainConfig {
        let mut policy = PolicyConfig::tiny().with_mode(mode);
        policy.n_points = 96;
        policy.n_outside_focus = 24;
        TrainConfig {
            policy,
            optim: AdamWConfig {
                lr: 3e-3,
                ..AdamWConfig::reference()
            },
            levels: TRAIN_LEVELS,
            queries_per_level: 12,
            top_k: 3,
            cloud_query_share: 0.0,
            rotation_grid_level: 0,
            augment: false,
            held_shift_m: 0.0,
            batch: 1,
            seed: 3,
            threads: 1,
        }
    }

    fn sample(seed: u64, target: Transform<Base, Tcp>, open: bool) -> TrainSample {
        TrainSample {
            cloud: synthetic_scene(400, seed).unwrap(),
            gripper: GripperPose {
                base_from_tcp: pose(0.5, 0.0, 0.3, 0.0),
                open: true,
            },
            instruction: InstructionEmbedding::random(seed),
            target: Keyframe::new(target, open, false).unwrap(),
            negatives: Vec::new(),
            placed_by_scene: false,
        }
    }

    #[test]
    fn a_negative_inside_the_gripper_box_is_a_first_level_query() {
        let mut cfg = config(PolicyMode::Gated);
        cfg.levels = 1;
        let weights = random_weights(&cfg.policy.model, &cfg.policy.extra, 5);
        let grid = LossGrid::new(0).unwrap();
        let plain = sample(2, pose(0.6, 0.1, 0.1, 0.3), false);
        let loss = |s: &TrainSample| {
            let mut rng = ChaCha8Rng::seed_from_u64(4);
            sample_gradients(&weights, &cfg, &grid, s, &mut rng)
                .unwrap()
                .0
        };
        let base = loss(&plain);
        let mut with = plain.clone();
        with.negatives = vec![Point3::new(0.45, -0.1, 0.15)];
        let more = loss(&with);
        // One more query in the softmax: the cross-entropy grows; the other terms do not move.
        assert!(more.translation > base.translation, "{more:?} vs {base:?}");
        assert_eq!(more.open, base.open);
        assert_eq!(more.rotation, base.rotation);
        // Outside the gripper box, a negative is not a query.
        with.negatives = vec![Point3::new(5.0, 0.0, 0.0)];
        assert_eq!(loss(&with), base);
    }

    #[test]
    fn held_shift_draws_only_for_closed_hands_whose_keyframe_the_scene_places() {
        let mut cfg = config(PolicyMode::Gated);
        cfg.levels = 1;
        let weights = random_weights(&cfg.policy.model, &cfg.policy.extra, 5);
        let grid = LossGrid::new(0).unwrap();
        let loss = |cfg: &TrainConfig, s: &TrainSample| {
            let mut rng = ChaCha8Rng::seed_from_u64(4);
            sample_gradients(&weights, cfg, &grid, s, &mut rng)
                .unwrap()
                .0
        };
        let mut closed = sample(2, pose(0.6, 0.1, 0.1, 0.3), true);
        closed.gripper.open = false;
        let base = loss(&cfg, &closed);
        let shifting = TrainConfig {
            held_shift_m: 0.02,
            ..cfg.clone()
        };
        // A keyframe placed relative to the hand: the paper's draws and loss.
        assert_eq!(loss(&shifting, &closed), base);
        let placed = TrainSample {
            placed_by_scene: true,
            ..closed.clone()
        };
        assert_eq!(
            loss(&cfg, &placed),
            base,
            "without the shift, nothing moves"
        );
        let moved = loss(&shifting, &placed);
        assert!(moved.total().is_finite());
        assert_ne!(moved, base, "the hand moved");
        // An open hand holds nothing to move.
        let mut open = placed.clone();
        open.gripper.open = true;
        assert_eq!(loss(&shifting, &open), loss(&cfg, &open));
        // The predicate the trainer and `equact train`'s count share.
        assert!(placed.held_shift_applies());
        assert!(!closed.held_shift_applies() && !open.held_shift_applies());
        for bad in [-0.01, f64::NAN, f64::INFINITY] {
            let c = TrainConfig {
                held_shift_m: bad,
                ..cfg.clone()
            };
            let w = random_weights(&c.policy.model, &c.policy.extra, 1);
            assert!(
                matches!(Trainer::new(c, w), Err(PolicyError::BadConfig(_))),
                "{bad}"
            );
        }
    }

    #[test]
    fn first_level_queries_near_the_cloud_land_on_every_object_and_share_0_is_the_papers() {
        let bounds = [[0.0, -0.5, 0.0], [1.0, 0.5, 0.5]];
        let objects = [Point3::new(0.3, -0.2, 0.1), Point3::new(0.7, 0.25, 0.2)];
        // A point outside the box is never a centre.
        let cloud = [objects[0], objects[1], Point3::new(2.0, 0.0, 0.1)];
        let draw = |cloud: &[Point3<f64>], share: f64| {
            first_level_queries(&mut ChaCha8Rng::seed_from_u64(9), &bounds, cloud, 30, share)
                .unwrap()
        };
        // Share 0: the paper's uniform draws, the same ones as before the option existed.
        let mut rng = ChaCha8Rng::seed_from_u64(9);
        let uniform: Vec<Point3<f64>> =
            (0..30).map(|_| uniform_in_box(&mut rng, &bounds)).collect();
        assert_eq!(draw(&cloud, 0.0), uniform);
        // No object point in the box: all uniform too.
        assert_eq!(draw(&cloud[2..], 0.5), uniform);
        let q = draw(&cloud, 0.5);
        assert_eq!(q.len(), 30);
        assert!(q.iter().all(|p| in_box(p, &bounds)));
        let near = |p: &Point3<f64>, o: &Point3<f64>| (p - o).norm() < CLOUD_QUERY_RADIUS_M;
        // The first 15 are the uniform ones, the last 15 each near an object, and both
        // objects get some.
        assert_eq!(&q[..15], &uniform[..15]);
        assert!(q[15..].iter().all(|p| objects.iter().any(|o| near(p, o))));
        for o in &objects {
            assert!(q[15..].iter().any(|p| near(p, o)), "no query near {o:?}");
        }
        let all_near = draw(&cloud, 1.0);
        assert!(all_near.iter().all(|p| objects.iter().any(|o| near(p, o))));
        for bad in [-0.1, 1.5, f64::NAN] {
            let e =
                first_level_queries(&mut ChaCha8Rng::seed_from_u64(9), &bounds, &cloud, 30, bad);
            assert!(matches!(e, Err(PolicyError::BadConfig(_))), "{bad}: {e:?}");
        }
        let mut cfg = config(PolicyMode::Gated);
        cfg.cloud_query_share = 2.0;
        let w = random_weights(&cfg.policy.model, &cfg.policy.extra, 1);
        assert!(matches!(
            Trainer::new(cfg, w),
            Err(PolicyError::BadConfig(_))
        ));
    }

    #[test]
    fn only_points_above_the_table_are_query_centres() {
        let mut pc = PolicyConfig::tiny();
        pc.table_height = 0.05;
        let mut cloud = synthetic_scene(10, 1).unwrap();
        cloud.points = vec![
            nalgebra::Point3::new(0.5f32, 0.0, 0.05),
            nalgebra::Point3::new(0.5f32, 0.0, 0.055),
            nalgebra::Point3::new(0.5f32, 0.1, 0.07),
        ];
        cloud.rgb = None;
        let got = object_points(&cloud, &pc);
        assert_eq!(got.len(), 1);
        assert!((got[0] - Point3::new(0.5, 0.1, 0.07)).norm() < 1e-6);
    }

    /// The taped network computes what the inference network computes, on the same weights
    /// and the same prepared input (equivariant heads in both modes, and the plain heads).
    #[test]
    fn taped_network_matches_inference() {
        for (mode, heads) in [
            (PolicyMode::Parity, HeadKind::Equivariant),
            (PolicyMode::Gated, HeadKind::Equivariant),
            (PolicyMode::Gated, HeadKind::Plain),
        ] {
            let mut cfg = config(mode);
            cfg.policy.model.heads = heads;
            let pc = &cfg.policy;
            let weights = random_weights(&pc.model, &pc.extra, 11);
            let net = EquFieldUnet::load(&weights.scope(""), pc.model.clone()).unwrap();
            let s = sample(1, pose(0.6, 0.1, 0.1, 0.3), false);
            let mut rng = ChaCha8Rng::seed_from_u64(5);
            let prep = prepare_input(pc, &s.cloud, &s.gripper, &mut rng).unwrap();
            let enc = net
                .encode(
                    &prep.xyz,
                    &prep.rgb,
                    &prep.gripper,
                    &prep.gripper_eps,
                    s.instruction.values(),
                    &[],
                )
                .unwrap();
            let queries = [[0.5f32, 0.0, 0.1], [0.7, -0.2, 0.2], [0.45, 0.12, 0.0]];
            let out = net.query(&enc, &queries, queries[1]).unwrap();

            let mut t = Tape::new();
            let root = weights.scope("");
            let tenc = encode(
                &mut t,
                &root,
                &pc.model,
                NetworkInput {
                    xyz: &prep.xyz,
                    rgb: &prep.rgb,
                    gripper: &prep.gripper,
                    gripper_eps: &prep.gripper_eps,
                    instruction: s.instruction.values(),
                },
            )
            .unwrap();
            let close = |a: &[f32], b: &[f32], tol: f32, what: &str| {
                assert_eq!(a.len(), b.len(), "{what}");
                let scale = b.iter().fold(0.0f32, |m, v| m.max(v.abs())).max(1.0);
                for (i, (x, y)) in a.iter().zip(b).enumerate() {
                    assert!(
                        (x - y).abs() <= tol * scale,
                        "{mode:?} {heads:?} {what}[{i}]: {x} vs {y}"
                    );
                }
            };
            close(t.value(tenc.embedding), &enc.embedding, 1e-4, "embedding");
            let tl = trans_logits(&mut t, &root, &pc.model, &tenc, &queries).unwrap();
            close(t.value(tl), &out.trans_logits, 1e-4, "translation logits");
            let grid = LossGrid::new(0).unwrap();
            let (open, rot) =
                rot_query(&mut t, &root, &pc.model, &tenc, queries[1], &grid.wigners).unwrap();
            close(t.value(open), &[out.rot.open_logit], 1e-4, "open logit");
            let want: Vec<f32> = net
                .heads()
                .logits_on(&out.rot.so3_coeffs, &so3_healpix_grid(0))
                .unwrap()
                .iter()
                .map(|&v| v as f32)
                .collect();
            close(t.value(rot), &want, 1e-3, "rotation logits");
        }
    }

    /// Finite differences of the whole training loss agree with the backward pass at
    /// parameters spread over the network (language, U-net, both heads).
    #[test]
    fn whole_model_gradients_match_finite_differences() {
        let mut cfg = config(PolicyMode::Gated);
        // One sampling level: the finer levels' anchors are the top logits, a discrete
        // choice that a perturbation can flip (the loss then jumps).
        cfg.levels = 1;
        let pc = &cfg.policy;
        let weights = random_weights(&pc.model, &pc.extra, 12);
        let grid = LossGrid::new(0).unwrap();
        let s = sample(2, pose(0.55, -0.05, 0.05, -0.4), true);
        let loss_at = |w: &Weights| {
            let mut rng = ChaCha8Rng::seed_from_u64(9);
            sample_gradients(w, &cfg, &grid, &s, &mut rng).unwrap()
        };
        let (_, grads) = loss_at(&weights);
        let keys = [
            "instruction_embedding.weight",
            "type0_linear.weight",
            "down_blocks.1.block.transblock.ga.so2_conv_1.fc_m0.weight",
            "middle_block.block.transblock.ffn.so3_linear_2.weight",
            "up_blocks.2.block.transblock.norm_2.affine_weight",
            "norm_1.affine_bias",
            "trans_field_layer.0.proj.weight",
            "rot_field_layer.0.ffn.so3_linear_2.weight",
            "s2_conv.w",
        ];
        let mut checked = 0;
        for key in keys {
            let Some((_, g)) = grads.iter().find(|(k, _)| k == key) else {
                panic!("no gradient for {key}");
            };
            // The entry with the largest gradient: well above the f32 noise floor.
            let (j, &a) = g
                .iter()
                .enumerate()
                .max_by(|x, y| x.1.abs().total_cmp(&y.1.abs()))
                .unwrap();
            // Max-pool choices are discrete: a step that flips one makes the loss jump, and
            // its difference quotient means nothing. A correct gradient agrees at (at least)
            // two of three step sizes; a wrong one at none.
            let a = f64::from(a);
            let mut agree = 0;
            let mut seen = Vec::new();
            for eps in [1e-3f32, 3e-4, 1e-4] {
                let side = |sign: f32| {
                    let mut w = weights.clone();
                    w.f32_mut(key).unwrap()[j] += sign * eps;
                    loss_at(&w).0.total()
                };
                let numeric = (side(1.0) - side(-1.0)) / (2.0 * f64::from(eps));
                seen.push(numeric);
                if (a - numeric).abs() <= 2e-3 + 5e-2 * a.abs().max(numeric.abs()) {
                    agree += 1;
                }
            }
            assert!(
                agree >= 2,
                "{key}[{j}]: analytic {a:.5e}, numeric at steps 1e-3, 3e-4, 1e-4: {seen:?}"
            );
            checked += 1;
        }
        assert_eq!(checked, keys.len());
    }

    /// Training runs through the plain heads (the ablation): their parameters, and not the
    /// equivariant heads', receive gradients, and a few steps on a fixed sample lower its loss.
    #[test]
    fn plain_heads_train_through_the_dispatch() {
        let mut cfg = config(PolicyMode::Gated);
        cfg.policy.model.heads = HeadKind::Plain;
        let pc = &cfg.policy;
        let weights = random_weights(&pc.model, &pc.extra, 14);
        assert!(!weights.contains("trans_field_layer.0.proj.weight"));
        let mut trainer = Trainer::new(cfg.clone(), weights).unwrap();
        let s = sample(3, pose(0.62, 0.08, 0.08, 0.7), false);
        let batch = [&s];
        let (before, grads) = trainer.gradients(&batch, 0).unwrap();
        let norm = |prefix: &str| -> f64 {
            grads
                .iter()
                .filter(|(k, _)| k.starts_with(prefix))
                .flat_map(|(_, g)| g.iter())
                .map(|&x| f64::from(x).powi(2))
                .sum()
        };
        assert!(norm("plain_trans_head.") > 0.0, "translation head trains");
        assert!(norm("plain_rot_head.") > 0.0, "rotation head trains");
        assert!(norm("down_blocks.") > 0.0, "the U-net trains through them");
        assert!(!grads.iter().any(|(k, _)| k.starts_with("rot_field_layer")
            || k.starts_with("trans_field_layer")
            || k.starts_with("s2_conv")
            || k.starts_with("field_distance_expansion")));
        for _ in 0..12 {
            let (_, grads) = trainer.gradients(&batch, 0).unwrap();
            trainer.optim.update(&mut trainer.weights, &grads).unwrap();
        }
        let after = trainer.gradients(&batch, 0).unwrap().0.total();
        assert!(
            after < 0.8 * before.total(),
            "loss {:.4} -> {after:.4}",
            before.total()
        );
    }

    #[test]
    fn a_further_sampling_level_adds_a_finer_translation_term_and_none_is_refused() {
        let cfg = config(PolicyMode::Gated);
        let pc = &cfg.policy;
        let weights = random_weights(&pc.model, &pc.extra, 13);
        let s = sample(3, pose(0.62, 0.08, 0.08, 0.7), false);
        let losses = |levels: usize| {
            let mut c = cfg.clone();
            c.levels = levels;
            let t = Trainer::new(c, weights.clone()).unwrap();
            t.gradients(&[&s], 0).unwrap().0
        };
        let (three, four) = (losses(TRAIN_LEVELS), losses(TRAIN_LEVELS + 1));
        // The first three levels draw the same samples; the fourth adds its own
        // cross-entropy, and the heads read at the truth are untouched.
        assert!(
            four.translation > three.translation,
            "{three:?} -> {four:?}"
        );
        assert_eq!((four.open, four.rotation), (three.open, three.rotation));
        let mut none = cfg.clone();
        none.levels = 0;
        match Trainer::new(none, weights) {
            Err(PolicyError::BadConfig(m)) => assert!(m.contains("sampling levels (0)"), "{m}"),
            other => panic!("zero levels accepted: {:?}", other.map(|t| t.cfg.levels)),
        }
    }

    /// The CI smoke test of training: a few AdamW steps on one fixed sample lower its loss,
    /// and a checkpoint resumes to the same weights and step.
    #[test]
    fn training_lowers_the_loss_on_a_fixed_batch_and_resumes() {
        let cfg = config(PolicyMode::Gated);
        let pc = &cfg.policy;
        let weights = random_weights(&pc.model, &pc.extra, 13);
        let mut trainer = Trainer::new(cfg.clone(), weights).unwrap();
        let s = sample(3, pose(0.62, 0.08, 0.08, 0.7), false);
        let batch = [&s];
        // The same draws every step: a fixed batch in the strict sense.
        let before = trainer.gradients(&batch, 0).unwrap().0.total();
        for _ in 0..12 {
            let (_, grads) = trainer.gradients(&batch, 0).unwrap();
            trainer.optim.update(&mut trainer.weights, &grads).unwrap();
        }
        let after = trainer.gradients(&batch, 0).unwrap().0.total();
        assert!(after < 0.8 * before, "loss {before:.4} -> {after:.4}");

        // Two threads over a batch of two give the same mean as one thread.
        let s2 = sample(4, pose(0.5, -0.1, 0.12, -0.2), true);
        let pair = [&s, &s2];
        let one = trainer.gradients(&pair, 7).unwrap();
        let mut two_threads = trainer.clone();
        two_threads.cfg.threads = 2;
        assert_eq!(two_threads.gradients(&pair, 7).unwrap(), one);

        let dir = std::env::temp_dir().join(format!("equact_trainer_{}", std::process::id()));
        trainer.step(&batch).unwrap();
        trainer.save(&dir).unwrap();
        let n_points = cfg.policy.n_points;
        let back = Trainer::resume(cfg, &dir).unwrap();
        assert_eq!(back.optim.step, trainer.optim.step);
        // The checkpoint says how many cloud points the network was trained with.
        assert_eq!(
            crate::weights::trained_points(&dir.join(WEIGHTS_FILE)).unwrap(),
            Some(n_points)
        );
        assert_eq!(
            back.weights.metadata(crate::weights::N_POINTS_KEY),
            Some(n_points.to_string().as_str())
        );
        assert_eq!(
            crate::weights::Weights::header_only(&dir.join(WEIGHTS_FILE))
                .unwrap()
                .trained_focus_above_table()
                .unwrap(),
            Some(trainer.cfg.policy.focus_above_table)
        );
        for key in trainer.weights.keys() {
            assert_eq!(
                back.weights.f32_any(key).unwrap().1,
                trainer.weights.f32_any(key).unwrap().1,
                "{key}"
            );
        }
        let mut a = trainer.clone();
        let mut b = back;
        assert_eq!(
            a.step(&batch).unwrap(),
            b.step(&batch).unwrap(),
            "resumed step is identical"
        );
        std::fs::remove_dir_all(&dir).unwrap();
    }
}
