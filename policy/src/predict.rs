//! Inference: one observation (cloud, gripper, instruction) in, one keyframe out.
//!
//! Spec: `equact.md` ("Point cloud in", "Heads") and the reference's `EquAct.forward` in
//! evaluation mode. [`Policy::predict`]:
//! 1. input preparation: the cloud (base frame, metres) is cropped to the workspace box;
//!    optionally [`PolicyConfig::n_near_gripper`] points are first sampled in a ball around
//!    the gripper; up to `n_outside_focus` points are farthest-point sampled outside the
//!    focus box (the gripper bounds with z-min at the table height) and the rest inside it,
//!    then randomly permuted;
//!    colours go to [0, 1] (grey without colour); the model writes the gripper into the last
//!    `n_gripper_pos` points;
//! 2. the U-net encodes the scene once;
//! 3. coarse-to-fine translation: level 0 samples uniformly in the gripper bounds (and, with
//!    [`SamplingConfig::near_gripper`] and [`SamplingConfig::near_cloud`], in balls around
//!    the gripper and around the cloud's objects), level l > 0 uniformly in balls of
//!    diameter 0.25/4^(l−1) m (clipped to the bounds) around the top-k samples of the level
//!    before (level 0's kept apart with [`SamplingConfig::spread_anchors`]); the answer is
//!    the best sample of the last level;
//! 4. at that point: the gripper-open logit and the rotation logits; the rotation is the
//!    argmax over a HEALPix SO(3) grid refined by a local pattern search on SO(3) (the
//!    reference evaluates a 2.36 M-rotation grid instead).
//!
//! Every random choice (permutation, gripper jitter, samples) comes from a ChaCha generator
//! seeded with [`Policy::seed`], so a prediction is a deterministic function of the seed and
//! the inputs. The boxes live in a workspace frame (`base_from_workspace`, identity by
//! default) and the samples are drawn in that frame: moving the scene, the gripper and that
//! frame together moves the keyframe with them (the equivariance test).

use std::path::Path;
use std::time::Instant;

use cell_types::{Base, FrameId, Keyframe, PointCloud, Tcp, Transform};
use nalgebra::{Isometry3, Matrix3, Point3, Rotation3, UnitQuaternion, Vector3};
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;

use crate::error::{PolicyError, Result};
use crate::fixtures::{read_safetensors, StoredTensor, TensorData};
use crate::grids::{so3_healpix_grid, GridRotation, S2Resolution};
use crate::heads::TRANS_KNN;
use crate::init::{random_weights, ExtraSizes};
use crate::model::{BlockIndices, EquFieldUnet, GripperState, ModelConfig};
use crate::points::{
    check_finite, coefficient_max_pool_choices, farthest_point_sampling, knn, UpsampleDistance,
};
use crate::rotation_head::{flat_wigner, RotationHead, SO3_COEFFS};
use crate::so3::WignerCalculator;
use crate::weights::Weights;

/// The calling thread's CPU time in seconds (`CLOCK_THREAD_CPUTIME_ID` through `cpu-time`, as
/// the planner's stage clock), or the wall time since the first call where that is
/// unavailable. On one thread and an idle machine both agree; on a shared one the CPU time is
/// what a free core would take. (Linux's `/proc/thread-self/schedstat` lags a running thread
/// by up to a scheduler tick, which lost short worker parts entirely.)
pub fn thread_seconds() -> f64 {
    static START: std::sync::OnceLock<Instant> = std::sync::OnceLock::new();
    cpu_time::ThreadTime::try_now().map_or_else(
        |_| START.get_or_init(Instant::now).elapsed().as_secs_f64(),
        |t| t.as_duration().as_secs_f64(),
    )
}

/// A stopwatch on [`thread_seconds`] plus the inference workers' CPU time
/// ([`crate::parallel::worker_seconds`]): the CPU cost of a stage however many threads ran
/// it (workers of other concurrent predictions count too).
#[derive(Debug, Clone, Copy)]
pub struct CpuTimer(f64);

impl CpuTimer {
    /// Starts the stopwatch.
    pub fn start() -> Self {
        Self(thread_seconds() + crate::parallel::worker_seconds())
    }

    /// Seconds since the start.
    pub fn elapsed(&self) -> f64 {
        thread_seconds() + crate::parallel::worker_seconds() - self.0
    }
}

/// Tokens of a CLIP-style instruction embedding.
pub const INSTRUCTION_TOKENS: usize = 53;
/// Width of a CLIP-style instruction token.
pub const INSTRUCTION_DIM: usize = 512;
/// Radius of the reference's gripper-point jitter (m).
pub const GRIPPER_JITTER: f64 = 1e-5;
/// Radius of the gripper-point jitter in the equivariant modes (m). The edges among the
/// gripper points take their direction from differences of f32 coordinates, which are
/// rounded to ~3e-8 m near 0.5 m: at 1e-5 m apart that is a few mrad of direction noise,
/// which dominated the equivariance error once the S2 grids were exact (2e-5..1e-4 relative
/// on the tiny network). 5e-4 m cuts it 50-fold and keeps every gripper-gripper distance
/// (≤ 1e-3 m) below the radial bases' inner cut-off (1 % of the smallest radius, 1.98e-3 m):
/// those edges still see an all-zero radial basis, as in the reference.
pub const EQUIVARIANT_GRIPPER_JITTER: f64 = 5e-4;

/// A precomputed instruction embedding `[tokens, dim]` (CLIP text model, last hidden state).
#[derive(Debug, Clone, PartialEq)]
pub struct InstructionEmbedding {
    tokens: usize,
    dim: usize,
    values: Vec<f32>,
}

impl InstructionEmbedding {
    /// Wraps `values` `[tokens, dim]`, checking the size.
    pub fn new(values: Vec<f32>, tokens: usize, dim: usize) -> Result<Self> {
        if values.len() != tokens * dim || tokens == 0 || dim == 0 {
            return Err(PolicyError::ShapeMismatch {
                name: "instruction embedding".into(),
                expected: vec![tokens, dim],
                got: vec![values.len()],
            });
        }
        Ok(Self {
            tokens,
            dim,
            values,
        })
    }

    /// A seeded N(0, 1) embedding of the CLIP size (for tests and benchmarks).
    pub fn random(seed: u64) -> Self {
        let mut rng = ChaCha8Rng::seed_from_u64(seed);
        let values = (0..INSTRUCTION_TOKENS * INSTRUCTION_DIM)
            .map(|_| {
                // Sum of 12 uniforms − 6: unit variance, close enough to normal here.
                (0..12).map(|_| rng.random::<f32>()).sum::<f32>() - 6.0
            })
            .collect();
        Self {
            tokens: INSTRUCTION_TOKENS,
            dim: INSTRUCTION_DIM,
            values,
        }
    }

    /// Reads a safetensors file holding one F32 tensor `[tokens, width]` or
    /// `[1, tokens, width]` (or several, one of them named `instruction` or `embedding`):
    /// CLIP's `[53, 512]` as the reference uses, or MiniLM's per-token states
    /// `[tokens, 384]` (`equact policy embed --out`). The network checks the width against
    /// its own when it predicts.
    pub fn from_file(path: &Path) -> Result<Self> {
        let tensors = read_safetensors(path)?;
        let key = if tensors.len() == 1 {
            tensors.keys().next().cloned()
        } else {
            ["instruction", "embedding"]
                .iter()
                .find(|k| tensors.contains_key(**k))
                .map(|k| (*k).to_string())
        };
        let Some(key) = key else {
            return Err(PolicyError::MissingTensor {
                name: "instruction (or a file with a single tensor)".into(),
                file: path.display().to_string(),
            });
        };
        let t = tensors
            .get(&key)
            .ok_or_else(|| PolicyError::MissingTensor {
                name: key.clone(),
                file: path.display().to_string(),
            })?;
        let name = format!("{} in {}", key, path.display());
        let TensorData::F32(values) = &t.data else {
            return Err(PolicyError::WrongDtype {
                name,
                expected: "F32",
                got: "I64".into(),
            });
        };
        let (tokens, dim) = match t.shape.as_slice() {
            [1, a, b] | [a, b] if *a > 0 && *b > 0 => (*a, *b),
            _ => {
                return Err(PolicyError::ShapeMismatch {
                    name,
                    expected: vec![INSTRUCTION_TOKENS, INSTRUCTION_DIM],
                    got: t.shape.clone(),
                })
            }
        };
        Self::new(values.clone(), tokens, dim)
    }

    /// Writes the embedding as a safetensors file with one tensor `instruction` `[tokens, dim]`.
    pub fn save(&self, path: &Path) -> Result<()> {
        let mut map = std::collections::HashMap::new();
        map.insert(
            "instruction".to_string(),
            StoredTensor {
                shape: vec![self.tokens, self.dim],
                data: TensorData::F32(self.values.clone()),
            },
        );
        Weights::from_tensors("instruction", map).save(path)
    }

    /// Number of tokens.
    pub fn tokens(&self) -> usize {
        self.tokens
    }

    /// Width of one token.
    pub fn dim(&self) -> usize {
        self.dim
    }

    /// The values, row-major `[tokens, dim]`.
    pub fn values(&self) -> &[f32] {
        &self.values
    }
}

/// The robot state the policy reads: current TCP pose in the base frame and gripper state.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct GripperPose {
    /// Current TCP pose.
    pub base_from_tcp: Transform<Base, Tcp>,
    /// Whether the gripper is open.
    pub open: bool,
}

impl GripperPose {
    /// The model's view: position, quaternion (x, y, z, w), open as 1/0.
    pub fn state(&self) -> GripperState {
        let t = self.base_from_tcp.translation();
        let q = self.base_from_tcp.rotation();
        let c = q.coords;
        GripperState {
            position: [t.x as f32, t.y as f32, t.z as f32],
            quaternion: [c.x as f32, c.y as f32, c.z as f32, c.w as f32],
            open: if self.open { 1.0 } else { 0.0 },
        }
    }
}

/// Parity (the reference as it is) or equivariant mode.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum PolicyMode {
    /// The reference's coarse S2 grids, L1 up-sampling weights, gripper jitter of radius
    /// [`GRIPPER_JITTER`] in the base frame.
    Parity,
    /// `s2_grid` × `s2_grid` S2 activation grids, Euclidean up-sampling weights, gripper
    /// jitter of radius [`EQUIVARIANT_GRIPPER_JITTER`] in the gripper's own frame (so it
    /// turns with the gripper, and f32 rounding barely turns the gripper-gripper edges).
    Equivariant {
        /// Latitude and longitude samples of every S2 activation grid.
        s2_grid: usize,
    },
    /// Equivariant mode with a gated activation in place of every separable S2 activation
    /// (l = 0: SiLU of the gating scalars; l > 0: times their sigmoid): exactly equivariant
    /// and cheaper than any grid. The weights keep their shapes, but the nonlinearity differs,
    /// so weights trained with S2 activations compute something else here: this mode is for
    /// weights trained in it. Euclidean up-sampling and turning jitter as
    /// [`PolicyMode::Equivariant`].
    Gated,
}

impl PolicyMode {
    /// A short name: `parity`, `equivariant_s2_N` or `gated`.
    pub fn name(&self) -> String {
        match self {
            Self::Parity => "parity".into(),
            Self::Equivariant { s2_grid } => format!("equivariant_s2_{s2_grid}"),
            Self::Gated => "gated".into(),
        }
    }
}

/// The coarse-to-fine translation sampling of the reference (evaluation mode).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct SamplingConfig {
    /// Sampling levels.
    pub levels: usize,
    /// Samples per level (a multiple of `top_k`).
    pub per_level: usize,
    /// Anchors kept per level.
    pub top_k: usize,
    /// Ball diameter of level 1 (m); level l uses this / 4^(l−1).
    pub fine_ball_diameter: f64,
    /// Extra level-0 samples uniform in a ball of [`NEAR_GRIPPER_RADIUS_M`] around the
    /// gripper's current position (clipped to the gripper bounds; none where the ball
    /// misses them). 0 is the reference's level 0, the gripper bounds alone. Why: a target
    /// in free space near the gripper (pulling a held part out) is a narrow peak of the
    /// field that 333 samples spread over the whole box (about 10 cm apart) can miss, and
    /// the levels after only refine around what level 0 found.
    pub near_gripper: usize,
    /// Extra level-0 samples each uniform in a [`NEAR_CLOUD_RADIUS_M`] ball around a random
    /// object point of the cloud (more than 1 cm above the table, inside the gripper bounds;
    /// none when there is no such point). 0 is the reference's level 0. Why: a keyframe sits
    /// near the scene's objects, often in free space above one (the place above the toilet
    /// roll holder's spindle); where the field's peak there is narrow, level 0's box
    /// samples (about 10 cm apart) miss it and the levels after refine a weaker mode.
    pub near_cloud: usize,
    /// Level 0 keeps as anchors the best samples at least level 1's ball radius apart
    /// (greedy non-maximum suppression) instead of the `top_k` best. false is the
    /// reference's. Why: when one broad mode of the field holds level 0's best samples, the
    /// plain top-k spends every anchor on it and a narrower, higher peak elsewhere is never
    /// refined; spread anchors refine each mode before they compete at the finer levels.
    pub spread_anchors: bool,
}

/// Radius of the level-0 ball around the gripper ([`SamplingConfig::near_gripper`], m): the
/// demonstrations' moves of a held object (pulls of 7–8 cm, lifts of 8–10 cm) end inside it.
pub const NEAR_GRIPPER_RADIUS_M: f64 = 0.15;

/// Radius of the level-0 balls around object points ([`SamplingConfig::near_cloud`], m):
/// the demonstrations' approach and place keyframes lie within 7–12 cm of an object's
/// points (pre-grasps 10–12 cm above a fruit or roll, the place above the spindle).
pub const NEAR_CLOUD_RADIUS_M: f64 = 0.15;

/// The local rotation search.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct RotationSearch {
    /// HEALPix level of the coarse SO(3) grid (72·8^level rotations).
    pub grid_level: u32,
    /// Smallest pattern-search step (rad); the search stops below it.
    pub min_step: f64,
}

impl RotationSearch {
    /// Starting step: about half the coarse grid spacing.
    pub fn start_step(&self) -> f64 {
        // 6·2^level gammas per turn: spacing 2π/(6·2^level).
        std::f64::consts::PI / (6.0 * f64::from(1u32 << self.grid_level))
    }
}

/// The most cloud points a configuration may feed the network.
pub const MAX_POINTS: usize = 16_384;

/// Everything the policy needs besides the weights.
#[derive(Debug, Clone, PartialEq)]
pub struct PolicyConfig {
    /// The network (its mode fields are set from `mode`).
    pub model: ModelConfig,
    /// Sizes the weight generator needs.
    pub extra: ExtraSizes,
    /// Parity or equivariant mode.
    pub mode: PolicyMode,
    /// Points fed to the network (gripper points included).
    pub n_points: usize,
    /// Of those, at most this many from outside the focus box.
    pub n_outside_focus: usize,
    /// Of `n_points`, how many are first sampled within `near_gripper_radius` of the
    /// gripper (fewer when the ball holds fewer; 0 in every built-in configuration).
    /// Farthest point sampling spreads the points at the whole scene's spacing (18 mm at
    /// 1024), so a held object is seen through a dozen points; these see it at the
    /// cloud's own spacing near the gripper. The ball moves with the gripper, so the
    /// choice is SE(3)-equivariant.
    pub n_near_gripper: usize,
    /// Radius (m) of the ball around the gripper that `n_near_gripper` are sampled in.
    pub near_gripper_radius: f64,
    /// The frame the boxes are expressed in.
    pub base_from_workspace: Isometry3<f64>,
    /// Crop box [min, max] (m).
    pub workspace_bounds: [[f64; 3]; 2],
    /// Where the gripper may go [min, max] (m): the translation samples.
    pub gripper_bounds: [[f64; 3]; 2],
    /// Table height (m): the focus box is the gripper bounds with this z-min (plus
    /// [`Self::focus_above_table`]).
    pub table_height: f64,
    /// Height (m) of the focus box's floor above `table_height`: 0 in every built-in
    /// configuration (EquAct's: the table top fills most of the focus box's share, a
    /// strawberry gets 4 of 1024 points); raised (e.g. 0.01) the share goes to the objects
    /// first, at their own spacing, and the table gets the `n_outside_focus` points. The
    /// floor is a plane of the workspace frame, as the boxes are, so the sampling still
    /// moves with the scene.
    pub focus_above_table: f64,
    /// Translation sampling.
    pub sampling: SamplingConfig,
    /// Rotation search.
    pub rotation: RotationSearch,
}

impl PolicyConfig {
    /// The physical-robot configuration (2048 points, l_max 3, the reference's default
    /// widths), equivariant mode with 16 × 16 S2 grids.
    pub fn physical() -> Self {
        let per = 1000 / 3;
        Self {
            model: ModelConfig::reference(),
            extra: ExtraSizes::reference(),
            mode: PolicyMode::Equivariant { s2_grid: 16 },
            n_points: 2048,
            n_outside_focus: 512,
            n_near_gripper: 0,
            near_gripper_radius: cell_types::config::DEFAULT_GRIPPER_RADIUS_M,
            base_from_workspace: Isometry3::identity(),
            workspace_bounds: [[0.18, -0.39, -0.10], [0.96, 0.39, 0.53]],
            gripper_bounds: [[0.18, -0.39, -0.07], [0.96, 0.39, 0.53]],
            table_height: -0.06,
            focus_above_table: 0.0,
            sampling: SamplingConfig {
                levels: 3,
                per_level: per - per % 3,
                top_k: 3,
                fine_ball_diameter: 0.25,
                near_gripper: 0,
                near_cloud: 0,
                spread_anchors: false,
            },
            rotation: RotationSearch {
                grid_level: 2,
                min_step: 1e-4,
            },
        }
        .with_mode(PolicyMode::Equivariant { s2_grid: 16 })
    }

    /// A tiny configuration for tests: 128 points, 3 scales, narrow layers, 60 samples per
    /// level.
    pub fn tiny() -> Self {
        let model = ModelConfig {
            max_neighbors: vec![16; 3],
            max_radius: vec![0.2, 0.4, 0.8],
            pool_ratio: vec![1.0, 0.25, 0.25],
            sphere_channels: vec![8, 8, 8, 8],
            attn_hidden_channels: vec![4; 3],
            num_heads: 2,
            attn_alpha_channels: vec![4; 3],
            attn_value_channels: vec![2; 3],
            ffn_hidden_channels: vec![8; 3],
            field_nn_c: 8,
            lang_heads: 2,
            lang_dim_head: 8,
            rotation_grid_level: 1,
            ..ModelConfig::reference()
        };
        Self {
            model,
            extra: ExtraSizes {
                edge_channels: vec![8; 3],
                num_distance_basis: 16,
                field_num_basis: 64,
                film_dim: 16,
                token_dim: INSTRUCTION_DIM,
                lang_depth: 1,
                lang_mlp: 32,
            },
            n_points: 128,
            n_outside_focus: 32,
            sampling: SamplingConfig {
                levels: 3,
                per_level: 30,
                top_k: 3,
                fine_ball_diameter: 0.25,
                near_gripper: 0,
                near_cloud: 0,
                spread_anchors: false,
            },
            rotation: RotationSearch {
                grid_level: 1,
                min_step: 1e-4,
            },
            ..Self::physical()
        }
        .with_mode(PolicyMode::Parity)
    }

    /// The configuration trained on a 2-core CPU (`equact train`'s default): 512 points,
    /// 3 scales with 16-32 channels, l_max 3, the paper's per-degree scalar iFiLM, gated
    /// activations (exactly equivariant and the cheapest to train); 4 levels of 333
    /// translation queries at inference, the first with 111 more around the gripper.
    pub fn cpu() -> Self {
        let model = ModelConfig {
            max_neighbors: vec![16; 3],
            max_radius: vec![0.1, 0.2, 0.4],
            pool_ratio: vec![1.0, 0.25, 0.25],
            sphere_channels: vec![16, 16, 32, 32],
            attn_hidden_channels: vec![16; 3],
            num_heads: 2,
            attn_alpha_channels: vec![8; 3],
            attn_value_channels: vec![4; 3],
            ffn_hidden_channels: vec![32; 3],
            field_nn_c: 16,
            lang_heads: 2,
            lang_dim_head: 16,
            rotation_grid_level: 2,
            film_kind: crate::transblock::FilmKind::PerDegreeScalar,
            ..ModelConfig::reference()
        };
        Self {
            model,
            extra: ExtraSizes {
                edge_channels: vec![16; 3],
                num_distance_basis: 32,
                field_num_basis: 64,
                film_dim: 32,
                token_dim: crate::minilm::HIDDEN,
                lang_depth: 1,
                lang_mlp: 64,
            },
            n_points: 512,
            n_outside_focus: 128,
            // Inference only (training samples its own three levels): a fourth level, a
            // 7.8 mm ball, and 333 queries per level. On held-out demonstrations the
            // keyframes' median position error fell from 29 mm (3 levels of 99) to 12 mm
            // (`equact policy score`); the translation head costs about 4.5 times more.
            // Plus 111 first-level queries around the gripper: the held-out p90 fell from
            // 94 to 27 mm (the flower's pulls, far off in 3 of 9 steps, no longer are).
            // Not adopted: `near_cloud` 111 with `spread_anchors` (README, "Queries near the
            // objects"): the toilet roll's place above the spindle was found every time, but
            // held-out precision and closed-loop success did not improve.
            sampling: SamplingConfig {
                levels: 4,
                per_level: 333,
                top_k: 3,
                fine_ball_diameter: 0.25,
                near_gripper: 111,
                near_cloud: 0,
                spread_anchors: false,
            },
            ..Self::physical()
        }
        .with_mode(PolicyMode::Gated)
    }

    /// The same configuration fed `n` cloud points (gripper points included), a quarter of
    /// them at most from outside the focus box, as in every built-in configuration. The
    /// weights do not depend on the count, but a network sees the scene as densely as it
    /// was trained to. In the simulated cell's scenes a point's nearest neighbour is a
    /// median 26 mm away with 512 points, 18 mm with 1024 and 13 mm with 2048, against the
    /// toilet-roll spindle's 8 mm of play.
    pub fn with_points(mut self, n: usize) -> Self {
        self.n_points = n;
        self.n_outside_focus = n / 4;
        self
    }

    /// The same configuration with `n` of its points sampled first near the gripper
    /// ([`Self::n_near_gripper`]).
    pub fn with_near_gripper_points(mut self, n: usize) -> Self {
        self.n_near_gripper = n;
        self
    }

    /// The same configuration with the focus box's floor `h` m above the table
    /// ([`Self::focus_above_table`]).
    pub fn with_focus_above_table(mut self, h: f64) -> Self {
        self.focus_above_table = h;
        self
    }

    /// The same configuration in another mode (sets the network's S2 grids and up-sampling
    /// distance).
    pub fn with_mode(mut self, mode: PolicyMode) -> Self {
        self.mode = mode;
        match mode {
            PolicyMode::Parity => {
                self.model.s2_resolution = S2Resolution::Reference;
                self.model.upsample_distance = UpsampleDistance::L1;
            }
            PolicyMode::Equivariant { s2_grid } => {
                self.model.s2_resolution = S2Resolution::Square(s2_grid);
                self.model.upsample_distance = UpsampleDistance::Euclidean;
            }
            PolicyMode::Gated => {
                self.model.s2_resolution = S2Resolution::Gated;
                self.model.upsample_distance = UpsampleDistance::Euclidean;
            }
        }
        self
    }

    /// Checks the sampling, the point count and the boxes (each error says what to change).
    pub fn check(&self) -> Result<()> {
        let s = &self.sampling;
        if s.levels == 0 {
            return Err(PolicyError::BadConfig(
                "sampling.levels is 0: the translation needs at least one sampling level".into(),
            ));
        }
        if s.top_k == 0 || s.per_level < s.top_k || !s.per_level.is_multiple_of(s.top_k) {
            return Err(PolicyError::BadConfig(format!(
                "sampling.per_level is {}: the translation queries per level must be a \
                 positive multiple of the {} anchors kept per level (e.g. {})",
                s.per_level,
                s.top_k,
                (s.per_level / s.top_k.max(1)).max(1) * s.top_k.max(1)
            )));
        }
        if self.n_points <= self.model.n_gripper_pos || self.n_points > MAX_POINTS {
            return Err(PolicyError::BadConfig(format!(
                "n_points is {}: the network needs more points than the {} gripper points \
                 and at most {MAX_POINTS} (the physical network's 2048 take seconds per \
                 keyframe on a CPU already)",
                self.n_points, self.model.n_gripper_pos
            )));
        }
        if self.n_near_gripper > self.n_points - self.n_outside_focus.min(self.n_points) {
            return Err(PolicyError::BadConfig(format!(
                "n_near_gripper is {}: at most the {} points the focus box may take \
                 (n_points {} less n_outside_focus {})",
                self.n_near_gripper,
                self.n_points - self.n_outside_focus.min(self.n_points),
                self.n_points,
                self.n_outside_focus
            )));
        }
        if !(self.near_gripper_radius.is_finite() && self.near_gripper_radius > 0.0) {
            return Err(PolicyError::BadConfig(format!(
                "near_gripper_radius is {}: use a positive radius in metres, e.g. 0.08",
                self.near_gripper_radius
            )));
        }
        let floor = self.table_height + self.focus_above_table;
        if !(self.focus_above_table >= 0.0 && floor < self.gripper_bounds[1][2]) {
            return Err(PolicyError::BadConfig(format!(
                "focus_above_table is {}: use a height in metres from 0 (EquAct's focus box) \
                 to below the gripper bounds' top, e.g. 0.01",
                self.focus_above_table
            )));
        }
        for b in [self.workspace_bounds, self.gripper_bounds] {
            if (0..3).any(|i| b[0][i].partial_cmp(&b[1][i]) != Some(std::cmp::Ordering::Less)) {
                return Err(PolicyError::BadConfig(format!(
                    "bounds {b:?} are empty (min must be below max)"
                )));
            }
        }
        Ok(())
    }
}

/// The network input made from one observation.
#[derive(Debug, Clone)]
pub struct PreparedInput {
    /// Point positions (base frame), `n_points`.
    pub xyz: Vec<[f32; 3]>,
    /// Colours in [0, 1].
    pub rgb: Vec<[f32; 3]>,
    /// The gripper as the model reads it.
    pub gripper: GripperState,
    /// The gripper points' jitter (base frame).
    pub gripper_eps: Vec<[f32; 3]>,
    /// Cloud points inside the workspace box.
    pub in_workspace: usize,
}

/// CPU time of each stage of one prediction, all its threads (seconds, see [`CpuTimer`]).
#[derive(Debug, Clone, Default, PartialEq)]
pub struct StageTimings {
    /// Crop, farthest point sampling, permutation.
    pub input_prep: f64,
    /// Instruction encoder.
    pub language: f64,
    /// Each U-net block, in execution order.
    pub blocks: Vec<(String, f64)>,
    /// Whole encoder (language, input features, U-net, final norm).
    pub encoder: f64,
    /// Translation head (all levels, sampling included).
    pub translation_head: f64,
    /// Rotation field (TransBlock at the chosen point, open logit, S2 lift).
    pub rotation_head: f64,
    /// Coarse grid argmax and local refinement.
    pub rotation_search: f64,
    /// Everything.
    pub total: f64,
    /// Everything, wall-clock (the other fields are CPU time, see [`CpuTimer`]).
    pub wall_total: f64,
    /// The encoder, wall-clock.
    pub wall_encoder: f64,
    /// The translation head, wall-clock.
    pub wall_translation_head: f64,
}

impl StageTimings {
    /// The timings as JSON (seconds).
    pub fn to_json(&self) -> serde_json::Value {
        let blocks: serde_json::Map<String, serde_json::Value> = self
            .blocks
            .iter()
            .map(|(n, s)| (n.clone(), serde_json::json!(s)))
            .collect();
        serde_json::json!({
            "input_prep": self.input_prep,
            "language": self.language,
            "unet_blocks": blocks,
            "encoder": self.encoder,
            "translation_head": self.translation_head,
            "rotation_head": self.rotation_head,
            "rotation_search": self.rotation_search,
            "total": self.total,
            "wall_total": self.wall_total,
            "wall_encoder": self.wall_encoder,
            "wall_translation_head": self.wall_translation_head,
        })
    }
}

/// A translation the head scored at the finest sampling level (base frame).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct TranslationCandidate {
    /// Position (m, base frame).
    pub position: Point3<f64>,
    /// Its translation logit.
    pub logit: f32,
}

/// What the heads read of an encoded observation: kept with a prediction so that other
/// translation candidates can be made into keyframes without encoding the scene again.
#[derive(Debug, Clone)]
pub struct SceneEncoding {
    embedding: Vec<f32>,
    coord: Vec<[f32; 3]>,
}

/// The keyframe the rotation and open heads give at one translation.
#[derive(Debug, Clone, Copy)]
pub struct KeyframeAt {
    /// The keyframe (`ignore_collisions` is always false: EquAct does not predict it).
    pub keyframe: Keyframe,
    /// Sigmoid of the open logit.
    pub open_probability: f32,
    /// The rotation logit at the refined rotation.
    pub rotation_logit: f64,
    /// The best rotation logit on the coarse grid.
    pub coarse_rotation_logit: f64,
    /// CPU seconds of the rotation head and of the rotation search.
    seconds: (f64, f64),
}

/// One prediction with what led to it.
#[derive(Debug, Clone)]
pub struct Prediction {
    /// The keyframe (`ignore_collisions` is always false: EquAct does not predict it).
    pub keyframe: Keyframe,
    /// Sigmoid of the open logit.
    pub open_probability: f32,
    /// The translation logit of the chosen point.
    pub translation_logit: f32,
    /// The rotation logit at the refined rotation.
    pub rotation_logit: f64,
    /// The best rotation logit on the coarse grid.
    pub coarse_rotation_logit: f64,
    /// Per sampling level, the samples (base frame) and their logits.
    pub levels: Vec<(Vec<[f32; 3]>, Vec<f32>)>,
    /// The finest level's samples, best logit first (the first is the keyframe's).
    pub candidates: Vec<TranslationCandidate>,
    /// The encoded scene, for [`Policy::keyframe_at`] on other candidates.
    pub scene: SceneEncoding,
    /// Cloud points inside the workspace box.
    pub in_workspace: usize,
    /// Stage timings.
    pub timings: StageTimings,
}

impl Prediction {
    /// Up to `n` translation candidates at least `separation` (m) apart: the keyframe's own
    /// position first, then the samples of every level, best logit first, each skipped when
    /// it lies within `separation` of one already taken. The finest level's next-best
    /// samples crowd within millimetres of the best (its balls are a few millimetres
    /// wide), so a caller looking for another keyframe when the planner refuses this one
    /// gets places that differ by more than the sampling noise.
    pub fn distinct_candidates(&self, n: usize, separation: f64) -> Vec<TranslationCandidate> {
        let mut all: Vec<TranslationCandidate> = self
            .levels
            .iter()
            .flat_map(|(queries, logits)| {
                queries
                    .iter()
                    .zip(logits)
                    .map(|(q, &logit)| TranslationCandidate {
                        position: Point3::new(f64::from(q[0]), f64::from(q[1]), f64::from(q[2])),
                        logit,
                    })
            })
            .collect();
        all.sort_by(|a, b| b.logit.total_cmp(&a.logit));
        let mut out: Vec<TranslationCandidate> = Vec::with_capacity(n);
        for c in self.candidates.first().into_iter().chain(&all) {
            if out.len() >= n {
                break;
            }
            if out
                .iter()
                .all(|k| (k.position - c.position).norm() >= separation)
            {
                out.push(*c);
            }
        }
        out
    }
}

/// The EquAct policy: network, configuration, rotation grid.
#[derive(Debug, Clone)]
pub struct Policy {
    cfg: PolicyConfig,
    model: EquFieldUnet,
    calc: WignerCalculator,
    grid: Vec<GridRotation>,
    /// Flat √(2l+1)·D(g) of the coarse grid, `[grid, 165]`.
    grid_wigners: Vec<f64>,
    /// Seed of every random choice of [`Policy::predict`].
    pub seed: u64,
}

impl Policy {
    /// Builds the policy from a weights store (keys as the reference's `state_dict()`, no
    /// prefix).
    pub fn from_weights(cfg: PolicyConfig, weights: &Weights) -> Result<Self> {
        let cfg = cfg.clone().with_mode(cfg.mode);
        cfg.check()?;
        // Any token width loads (CLIP's 512, MiniLM's 384, ...): each prediction checks the
        // instruction's width against the network's.
        let model = EquFieldUnet::load(&weights.scope(""), cfg.model.clone())?;
        let calc = WignerCalculator::new(crate::rotation_head::ROT_LMAX)?;
        let grid = so3_healpix_grid(cfg.rotation.grid_level);
        let mut grid_wigners = Vec::with_capacity(grid.len() * SO3_COEFFS);
        for g in &grid {
            grid_wigners.extend(flat_wigner(&calc, &g.matrix)?);
        }
        Ok(Self {
            cfg,
            model,
            calc,
            grid,
            grid_wigners,
            seed: 0,
        })
    }

    /// A policy with seeded random weights (runs without a checkpoint).
    pub fn random(cfg: PolicyConfig, weight_seed: u64) -> Result<Self> {
        let w = random_weights(&cfg.model, &cfg.extra, weight_seed);
        Self::from_weights(cfg, &w)
    }

    /// Loads the weights from a safetensors file (ours, or a converted reference checkpoint
    /// with the `module.equ_net.` prefix stripped).
    pub fn load(cfg: PolicyConfig, path: &Path) -> Result<Self> {
        Self::from_weights(cfg, &Weights::from_file(path)?)
    }

    /// The configuration.
    pub fn config(&self) -> &PolicyConfig {
        &self.cfg
    }

    /// Threads of each prediction (1, the default: the caller's thread only). More run the
    /// U-net's graphs and attentions and the translation head's query batches on scoped
    /// threads started per call; the keyframe is the same for any count
    /// (see [`crate::parallel`]).
    pub fn set_threads(&mut self, threads: usize) {
        self.model.set_threads(threads);
    }

    /// Threads of each prediction.
    pub fn threads(&self) -> usize {
        self.model.threads()
    }

    /// The network.
    pub fn model(&self) -> &EquFieldUnet {
        &self.model
    }

    /// The coarse rotation grid of the search.
    pub fn rotation_grid(&self) -> &[GridRotation] {
        &self.grid
    }

    /// Predicts one keyframe.
    pub fn predict(
        &mut self,
        cloud: &PointCloud,
        gripper: &GripperPose,
        instruction: &InstructionEmbedding,
    ) -> Result<Keyframe> {
        Ok(self.predict_detailed(cloud, gripper, instruction)?.keyframe)
    }

    /// Crops, samples and permutes the cloud and draws the gripper jitter (consumes `rng`).
    pub fn prepare(
        &self,
        cloud: &PointCloud,
        gripper: &GripperPose,
        rng: &mut ChaCha8Rng,
    ) -> Result<PreparedInput> {
        prepare_input(&self.cfg, cloud, gripper, rng)
    }

    /// Predicts one keyframe with its logits, samples and stage timings.
    pub fn predict_detailed(
        &mut self,
        cloud: &PointCloud,
        gripper: &GripperPose,
        instruction: &InstructionEmbedding,
    ) -> Result<Prediction> {
        let t_total = CpuTimer::start();
        let wall = Instant::now();
        if instruction.dim() != self.model.language().token_dim() {
            return Err(PolicyError::ShapeMismatch {
                name: "instruction embedding (token width)".into(),
                expected: vec![instruction.tokens(), self.model.language().token_dim()],
                got: vec![instruction.tokens(), instruction.dim()],
            });
        }
        let mut rng = ChaCha8Rng::seed_from_u64(self.seed);
        let t = CpuTimer::start();
        let prep = self.prepare(cloud, gripper, &mut rng)?;
        let input_prep = t.elapsed();

        let (t, w) = (CpuTimer::start(), Instant::now());
        let enc = self.model.encode(
            &prep.xyz,
            &prep.rgb,
            &prep.gripper,
            &prep.gripper_eps,
            instruction.values(),
            &[],
        )?;
        let (encoder, wall_encoder) = (t.elapsed(), w.elapsed().as_secs_f64());

        // Coarse-to-fine translation, sampled in the workspace frame.
        let (t, w) = (CpuTimer::start(), Instant::now());
        let cfg = &self.cfg;
        let s = cfg.sampling;
        let ws = cfg.base_from_workspace;
        let to_base = |q: &Point3<f64>| {
            let p = ws * q;
            [p.x as f32, p.y as f32, p.z as f32]
        };
        let mut anchors: Vec<Point3<f64>> = Vec::new();
        let mut best = (Point3::origin(), f32::NEG_INFINITY);
        let mut levels = Vec::with_capacity(s.levels);
        let mut candidates = Vec::new();
        for level in 0..s.levels {
            let samples: Vec<Point3<f64>> = if level == 0 {
                let mut out: Vec<Point3<f64>> = (0..s.per_level)
                    .map(|_| uniform_in_box(&mut rng, &cfg.gripper_bounds))
                    .collect();
                if s.near_gripper > 0 {
                    let at = ws.inverse() * Point3::from(gripper.base_from_tcp.translation());
                    // A gripper whose ball misses the bounds (parked outside them) adds none.
                    out.extend(
                        uniform_in_ball(
                            &mut rng,
                            &at,
                            NEAR_GRIPPER_RADIUS_M,
                            &cfg.gripper_bounds,
                            s.near_gripper,
                        )
                        .unwrap_or_default(),
                    );
                }
                if s.near_cloud > 0 {
                    let objects = object_points(cloud, cfg);
                    out.extend(queries_near_points(
                        &mut rng,
                        &cfg.gripper_bounds,
                        &objects,
                        NEAR_CLOUD_RADIUS_M,
                        s.near_cloud,
                    )?);
                }
                out
            } else {
                let r = s.fine_ball_diameter / 4f64.powi(level as i32 - 1) / 2.0;
                let per = s.per_level / anchors.len().max(1);
                let mut out = Vec::with_capacity(s.per_level);
                for a in &anchors {
                    out.extend(uniform_in_ball(&mut rng, a, r, &cfg.gripper_bounds, per)?);
                }
                out
            };
            let queries: Vec<[f32; 3]> = samples.iter().map(to_base).collect();
            let logits = self
                .model
                .heads()
                .trans_logits(&enc.embedding, &enc.coord, &queries)?;
            let order = if s.spread_anchors && level == 0 && s.levels > 1 {
                // Apart by level 1's ball radius: each anchor's ball covers its own region.
                top_k_apart(&samples, &logits, s.top_k, s.fine_ball_diameter / 2.0)
            } else {
                top_k(&logits, s.top_k)
            };
            anchors = order.iter().map(|&i| samples[i]).collect();
            if let Some(&i) = order.first() {
                best = (samples[i], logits[i]);
            }
            candidates = samples
                .iter()
                .zip(&logits)
                .map(|(q, &logit)| TranslationCandidate {
                    position: ws * q,
                    logit,
                })
                .collect();
            levels.push((queries, logits));
        }
        candidates.sort_by(|a, b| b.logit.total_cmp(&a.logit));
        let (translation_head, wall_translation_head) = (t.elapsed(), w.elapsed().as_secs_f64());

        let scene = SceneEncoding {
            embedding: enc.embedding,
            coord: enc.coord,
        };

        let at = self.keyframe_at(&scene, &(ws * best.0))?;
        let timings = StageTimings {
            input_prep,
            language: enc.language_seconds,
            blocks: enc
                .blocks
                .iter()
                .map(|b| (b.name.clone(), b.seconds))
                .collect(),
            encoder,
            translation_head,
            rotation_head: at.seconds.0,
            rotation_search: at.seconds.1,
            total: t_total.elapsed(),
            wall_total: wall.elapsed().as_secs_f64(),
            wall_encoder,
            wall_translation_head,
        };
        Ok(Prediction {
            keyframe: at.keyframe,
            open_probability: at.open_probability,
            translation_logit: best.1,
            rotation_logit: at.rotation_logit,
            coarse_rotation_logit: at.coarse_rotation_logit,
            levels,
            candidates,
            scene,
            in_workspace: prep.in_workspace,
            timings,
        })
    }

    /// The translation field's logits at `positions` (base frame) of an encoded scene, for
    /// diagnostics: how the field ranks the expert's position against the prediction.
    pub fn translation_logits(
        &self,
        scene: &SceneEncoding,
        positions: &[Point3<f64>],
    ) -> Result<Vec<f32>> {
        let queries: Vec<[f32; 3]> = positions
            .iter()
            .map(|p| [p.x as f32, p.y as f32, p.z as f32])
            .collect();
        self.model
            .heads()
            .trans_logits(&scene.embedding, &scene.coord, &queries)
    }

    /// The keyframe at `position` (base frame) of an encoded scene: the rotation head's
    /// argmax on the grid refined by the pattern search, and the open head. A caller whose
    /// planner refuses the best prediction turns the next [`Prediction::candidates`] into
    /// keyframes with this.
    pub fn keyframe_at(&self, scene: &SceneEncoding, position: &Point3<f64>) -> Result<KeyframeAt> {
        let t = CpuTimer::start();
        let rot = self.model.heads().rot_query(
            &scene.embedding,
            &scene.coord,
            [position.x as f32, position.y as f32, position.z as f32],
        )?;
        let rotation_head = t.elapsed();

        let t = CpuTimer::start();
        let (coarse_i, coarse_logit) = self.coarse_argmax(&rot.so3_coeffs);
        let start = self
            .grid
            .get(coarse_i)
            .map_or(Matrix3::identity(), |g| g.matrix);
        let (rotation, rotation_logit) = self.refine(&rot.so3_coeffs, start, coarse_logit)?;
        let rotation_search = t.elapsed();

        let open_probability = 1.0 / (1.0 + (-rot.open_logit).exp());
        let base_from_tcp =
            Transform::from_parts(position.coords, UnitQuaternion::from_matrix(&rotation));
        let keyframe =
            Keyframe::new(base_from_tcp, open_probability > 0.5, false).map_err(|e| {
                PolicyError::Sidecar {
                    path: "keyframe".into(),
                    message: e.to_string(),
                }
            })?;
        Ok(KeyframeAt {
            keyframe,
            open_probability,
            rotation_logit,
            coarse_rotation_logit: coarse_logit,
            seconds: (rotation_head, rotation_search),
        })
    }

    /// Index and value of the best coarse-grid rotation.
    fn coarse_argmax(&self, coeffs: &[f64]) -> (usize, f64) {
        let mut best = (0, f64::NEG_INFINITY);
        for (i, fw) in self.grid_wigners.chunks_exact(SO3_COEFFS).enumerate() {
            let v: f64 = fw.iter().zip(coeffs).map(|(a, b)| a * b).sum();
            if v > best.1 {
                best = (i, v);
            }
        }
        best
    }

    /// The rotation logit at `r`.
    pub fn rotation_logit(&self, coeffs: &[f64], r: &Matrix3<f64>) -> Result<f64> {
        let fw = flat_wigner(&self.calc, r)?;
        Ok(RotationHead::logits(coeffs, &[fw])
            .first()
            .copied()
            .unwrap_or(f64::NAN))
    }

    /// Pattern search on SO(3): try r·exp(±δ eᵢ), move to the best improvement, halve δ when
    /// none improves, stop below `min_step`.
    fn refine(
        &self,
        coeffs: &[f64],
        start: Matrix3<f64>,
        start_logit: f64,
    ) -> Result<(Matrix3<f64>, f64)> {
        let mut r = start;
        let mut v = start_logit;
        let mut step = self.cfg.rotation.start_step();
        let mut evals = 0;
        while step >= self.cfg.rotation.min_step && evals < 2000 {
            let mut moved = None;
            for axis in 0..6 {
                let mut w = Vector3::zeros();
                w[axis / 2] = if axis % 2 == 0 { step } else { -step };
                let cand = r * Rotation3::new(w).into_inner();
                let c = self.rotation_logit(coeffs, &cand)?;
                evals += 1;
                if c > v && moved.as_ref().is_none_or(|(_, b)| c > *b) {
                    moved = Some((cand, c));
                }
            }
            match moved {
                Some((cand, c)) => {
                    // Re-orthonormalise against drift.
                    r = Rotation3::from_matrix(&cand).into_inner();
                    v = c;
                }
                None => step /= 2.0,
            }
        }
        Ok((r, v))
    }

    /// Equivariance of the network on a prepared input under each `motion` (x → R x + t):
    /// relative errors of the translation logits at the moved queries, of the open logit, and
    /// of the rotation logits on the moved rotation grid (max abs difference / max abs value).
    /// The unmoved input is encoded once. [`Policy::equivariance_report`] says more.
    pub fn equivariance_errors(
        &self,
        prep: &PreparedInput,
        instruction: &InstructionEmbedding,
        queries: &[[f32; 3]],
        rot_query: [f32; 3],
        motions: &[Isometry3<f64>],
    ) -> Result<Vec<[f64; 3]>> {
        Ok(self
            .equivariance_report(prep, instruction, queries, rot_query, motions)?
            .into_iter()
            .map(|m| m.errors)
            .collect())
    }

    /// [`Policy::equivariance_errors`] with what lies behind each motion's error: which
    /// discrete choices (FPS picks, pooling, up-sampling and graph neighbour sets, the
    /// translation queries' nearest-node sets) differ between the input and the moved input,
    /// the errors again with the moved input forced onto the input's U-net choices (only
    /// when some differ: what remains is the continuous part), and whether the best rotation
    /// (coarse-grid argmax refined by the pattern search) moves with the input.
    pub fn equivariance_report(
        &self,
        prep: &PreparedInput,
        instruction: &InstructionEmbedding,
        queries: &[[f32; 3]],
        rot_query: [f32; 3],
        motions: &[Isometry3<f64>],
    ) -> Result<Vec<MotionEquivariance>> {
        let encode = |p: &PreparedInput, ov: &[(String, BlockIndices)]| {
            self.model.encode(
                &p.xyz,
                &p.rgb,
                &p.gripper,
                &p.gripper_eps,
                instruction.values(),
                ov,
            )
        };
        let enc_a = encode(prep, &[])?;
        let a = self.model.query(&enc_a, queries, rot_query)?;
        let best_a = self.best_rotation(&a.rot.so3_coeffs)?;
        let knn_a = set_lists(knn(&enc_a.coord, queries, TRANS_KNN)?);
        let choices_a: Vec<(String, BlockIndices)> = enc_a
            .blocks
            .iter()
            .map(|b| (b.name.clone(), b.indices.clone()))
            .collect();
        let f = |v: &[f32]| v.iter().map(|x| f64::from(*x)).collect::<Vec<_>>();
        let mut out = Vec::with_capacity(motions.len());
        for motion in motions {
            let (moved, mq, mrq) = move_input(prep, queries, rot_query, motion);
            let rm = motion.rotation.to_rotation_matrix().into_inner();
            let errors_of = |enc: &crate::model::Encoded| -> Result<([f64; 3], Matrix3<f64>)> {
                let b = self.model.query(enc, &mq, mrq)?;
                let grid: Vec<GridRotation> = self
                    .model
                    .heads()
                    .grid()
                    .iter()
                    .map(|g| GridRotation {
                        angles: g.angles,
                        matrix: rm * g.matrix,
                    })
                    .collect();
                let b_rot = self.model.heads().logits_on(&b.rot.so3_coeffs, &grid)?;
                let errors = [
                    relative_error(&f(&b.trans_logits), &f(&a.trans_logits)),
                    relative_error(
                        &[f64::from(b.rot.open_logit)],
                        &[f64::from(a.rot.open_logit)],
                    ),
                    relative_error(&b_rot, &a.rot.rot_logits),
                ];
                Ok((errors, self.best_rotation(&b.rot.so3_coeffs)?))
            };
            let enc_b = encode(&moved, &[])?;
            let (errors, best_b) = errors_of(&enc_b)?;
            let mut changed_blocks: Vec<String> = enc_a
                .blocks
                .iter()
                .zip(&enc_b.blocks)
                .filter_map(|(x, y)| {
                    changed_choices(&x.indices, &y.indices).map(|what| format!("{}.{what}", x.name))
                })
                .collect();
            // The index choices can be forced onto the moved input; the max-pool's cannot.
            let errors_same_choices = if changed_blocks.is_empty() {
                changed_blocks.extend(self.changed_max_pool(&enc_a, &enc_b)?);
                None
            } else {
                Some(errors_of(&encode(&moved, &choices_a)?)?.0)
            };
            let knn_b = set_lists(knn(&enc_b.coord, &mq, TRANS_KNN)?);
            let changed_query_lists = knn_a.iter().zip(&knn_b).filter(|(x, y)| x != y).count();
            let d = best_b.transpose() * rm * best_a;
            let argmax_angle = ((d.trace() - 1.0) / 2.0).clamp(-1.0, 1.0).acos();
            out.push(MotionEquivariance {
                errors,
                changed_blocks,
                changed_query_lists,
                errors_same_choices,
                argmax_angle,
            });
        }
        Ok(out)
    }

    /// `block.max_pool` for every pooling block whose max-pool choices differ between two
    /// encodings with the same pooling neighbours (a block of the moved input wins where a
    /// block of near-equal norm won before); the first such block also says how many
    /// choices flipped, how many of them were between gripper points, and the largest
    /// relative norm gap of a flip in the unmoved input (`down1.max_pool(flips 2, gripper 2,
    /// gap 3e-7)`).
    fn changed_max_pool(
        &self,
        a: &crate::model::Encoded,
        b: &crate::model::Encoded,
    ) -> Result<Vec<String>> {
        let lmax = self.cfg.model.lmax;
        let k = crate::so3::num_coefficients(lmax);
        let ng = self.cfg.model.n_gripper_pos;
        let mut out = Vec::new();
        for j in 1..a.blocks.len().min(b.blocks.len()) {
            let (Some(nb), prev_a, prev_b) = (
                &a.blocks[j].indices.pool_knn,
                &a.blocks[j - 1],
                &b.blocks[j - 1],
            ) else {
                continue;
            };
            let n = prev_a.coord.len();
            let c = prev_a.embedding.len() / (n * k).max(1);
            let ca = coefficient_max_pool_choices(&prev_a.embedding, n, lmax, c, nb)?;
            let cb = coefficient_max_pool_choices(&prev_b.embedding, n, lmax, c, nb)?;
            if ca == cb {
                continue;
            }
            if !out.is_empty() {
                out.push(format!("{}.max_pool", a.blocks[j].name));
                continue;
            }
            // Gripper points are the last ng nodes while the nodes are still the input's
            // (the first pooling block reads the full-resolution nodes).
            let full = n == a.xyz.len();
            let x = &prev_a.embedding;
            let norm = |node: usize, idx: usize| {
                let (l, ch) = (idx / c % (lmax + 1), idx % c);
                (l * l..(l + 1) * (l + 1))
                    .map(|i| f64::from(x[(node * k + i) * c + ch]).powi(2))
                    .sum::<f64>()
            };
            let (mut flips, mut gripper, mut gap) = (0, 0, 0.0f64);
            for (idx, (&p, &q)) in ca.iter().zip(&cb).enumerate() {
                if p != q && p != usize::MAX && q != usize::MAX {
                    flips += 1;
                    if full && p >= n - ng && q >= n - ng {
                        gripper += 1;
                    }
                    let (np, nq) = (norm(p, idx), norm(q, idx));
                    gap = gap.max((np - nq).abs() / np.max(nq).max(f64::MIN_POSITIVE));
                }
            }
            out.push(format!(
                "{}.max_pool(flips {flips}, gripper {gripper}, gap {gap:.1e})",
                a.blocks[j].name
            ));
        }
        Ok(out)
    }

    /// The best rotation of `coeffs`: the coarse-grid argmax refined by the pattern search.
    pub fn best_rotation(&self, coeffs: &[f64]) -> Result<Matrix3<f64>> {
        let (i, v) = self.coarse_argmax(coeffs);
        let start = self.grid.get(i).map_or(Matrix3::identity(), |g| g.matrix);
        Ok(self.refine(coeffs, start, v)?.0)
    }
}

/// One motion of [`Policy::equivariance_report`].
#[derive(Debug, Clone, PartialEq)]
pub struct MotionEquivariance {
    /// Relative errors (translation logits, open logit, rotation logits).
    pub errors: [f64; 3],
    /// `block.choice` for every U-net choice whose set differs (`fps`, `pool_knn`,
    /// `up_knn`, `graph`; `max_pool` when none of those did but a max-pool choice did): a
    /// discontinuity of the network (ties up to f32 rounding).
    pub changed_blocks: Vec<String>,
    /// Translation queries whose nearest-node set (the head's 100-NN edges) differs.
    pub changed_query_lists: usize,
    /// The errors with the moved input run on the unmoved input's U-net index choices, when
    /// any differ (what remains is the continuous part of the error, and max-pool flips).
    pub errors_same_choices: Option<[f64; 3]>,
    /// Angle (rad) between the moved input's best rotation and the motion times the
    /// unmoved input's best rotation.
    pub argmax_angle: f64,
}

/// Each list as a sorted set (neighbour order among near-equal distances does not matter).
fn set_lists(mut v: Vec<Vec<usize>>) -> Vec<Vec<usize>> {
    v.iter_mut().for_each(|l| l.sort_unstable());
    v
}

/// The first of a block's choices whose sets differ, by name.
fn changed_choices(a: &BlockIndices, b: &BlockIndices) -> Option<&'static str> {
    if a.fps != b.fps {
        return Some("fps");
    }
    let sets = |v: &Option<Vec<Vec<usize>>>| v.clone().map(set_lists);
    if sets(&a.pool_knn) != sets(&b.pool_knn) {
        return Some("pool_knn");
    }
    if sets(&a.up_knn) != sets(&b.up_knn) {
        return Some("up_knn");
    }
    let edges = |g: &Option<(Vec<usize>, Vec<usize>)>| {
        g.as_ref().map(|(s, d)| {
            let mut e: Vec<(usize, usize)> = d.iter().copied().zip(s.iter().copied()).collect();
            e.sort_unstable();
            e
        })
    };
    if edges(&a.graph) != edges(&b.graph) {
        return Some("graph");
    }
    None
}

/// Crops, samples and permutes the cloud and draws the gripper jitter (consumes `rng`): the
/// network input of one observation under `cfg` (inference and training share it).
pub fn prepare_input(
    cfg: &PolicyConfig,
    cloud: &PointCloud,
    gripper: &GripperPose,
    rng: &mut ChaCha8Rng,
) -> Result<PreparedInput> {
    if cloud.frame != FrameId::Base {
        return Err(PolicyError::WrongFrame {
            got: cloud.frame.to_string(),
        });
    }
    if cloud.is_empty() {
        return Err(PolicyError::EmptyCloud);
    }
    let raw: Vec<[f32; 3]> = cloud.points.iter().map(|p| [p.x, p.y, p.z]).collect();
    check_finite("input point cloud", &raw)?;
    if let Some(c) = &cloud.rgb {
        if c.len() != raw.len() {
            return Err(PolicyError::ShapeMismatch {
                name: "point cloud colours".into(),
                expected: vec![raw.len()],
                got: vec![c.len()],
            });
        }
    }
    let inv = cfg.base_from_workspace.inverse();
    let mut focus_box = cfg.gripper_bounds;
    focus_box[0][2] = cfg.table_height + cfg.focus_above_table;
    let (mut focused, mut other) = (Vec::new(), Vec::new());
    for (i, p) in raw.iter().enumerate() {
        let w = inv * Point3::new(f64::from(p[0]), f64::from(p[1]), f64::from(p[2]));
        if in_box(&w, &cfg.workspace_bounds) {
            if in_box(&w, &focus_box) {
                focused.push(i);
            } else {
                other.push(i);
            }
        }
    }
    let in_workspace = focused.len() + other.len();
    if in_workspace < cfg.n_points {
        return Err(PolicyError::TooFewPoints {
            what: "point cloud inside the workspace box (the network's point count)",
            needed: cfg.n_points,
            got: in_workspace,
        });
    }
    let mut picked = Vec::with_capacity(cfg.n_points);
    if cfg.n_near_gripper > 0 {
        // The points near the gripper first, at their own spacing; the split below then
        // samples the others.
        let g = gripper.base_from_tcp.translation();
        let r2 = cfg.near_gripper_radius * cfg.near_gripper_radius;
        let dist2 = |i: usize| {
            (0..3)
                .map(|k| (f64::from(raw[i][k]) - g[k]).powi(2))
                .sum::<f64>()
        };
        let near: Vec<usize> = focused
            .iter()
            .copied()
            .filter(|&i| dist2(i) <= r2)
            .collect();
        if !near.is_empty() {
            let pos: Vec<[f32; 3]> = near.iter().map(|&i| raw[i]).collect();
            let n = cfg.n_near_gripper.min(near.len());
            for j in farthest_point_sampling(&pos, n)? {
                picked.push(near[j]);
            }
            let mut taken = vec![false; raw.len()];
            for &i in &picked {
                taken[i] = true;
            }
            focused.retain(|&i| !taken[i]);
        }
    }
    // Outside the focus box at most n_outside_focus; the focus box fills the rest (and
    // the outside tops up when the focus box has too few).
    let rest = cfg.n_points - picked.len();
    let n_in = rest
        .saturating_sub(cfg.n_outside_focus.min(other.len()))
        .min(focused.len());
    let n_out = rest - n_in;
    for (set, n) in [(&other, n_out), (&focused, n_in)] {
        if n == 0 {
            continue;
        }
        let pos: Vec<[f32; 3]> = set.iter().map(|&i| raw[i]).collect();
        for j in farthest_point_sampling(&pos, n)? {
            picked.push(set[j]);
        }
    }
    // Fisher-Yates permutation.
    for i in (1..picked.len()).rev() {
        let j = rng.random_range(0..=i);
        picked.swap(i, j);
    }
    let xyz = picked.iter().map(|&i| raw[i]).collect();
    let rgb = picked
        .iter()
        .map(|&i| match &cloud.rgb {
            Some(c) => c[i].map(|v| f32::from(v) / 255.0),
            None => [0.5; 3],
        })
        .collect();
    let state = gripper.state();
    let turn = match cfg.mode {
        PolicyMode::Parity => Matrix3::identity(),
        PolicyMode::Equivariant { .. } | PolicyMode::Gated => *gripper
            .base_from_tcp
            .rotation()
            .to_rotation_matrix()
            .matrix(),
    };
    let jitter = match cfg.mode {
        PolicyMode::Parity => GRIPPER_JITTER,
        PolicyMode::Equivariant { .. } | PolicyMode::Gated => EQUIVARIANT_GRIPPER_JITTER,
    };
    let mut gripper_eps = Vec::with_capacity(cfg.model.n_gripper_pos);
    while gripper_eps.len() < cfg.model.n_gripper_pos {
        let e = Vector3::new(
            rng.random_range(-jitter..jitter),
            rng.random_range(-jitter..jitter),
            rng.random_range(-jitter..jitter),
        );
        if e.norm() < jitter {
            let e = turn * e;
            gripper_eps.push([e.x as f32, e.y as f32, e.z as f32]);
        }
    }
    Ok(PreparedInput {
        xyz,
        rgb,
        gripper: state,
        gripper_eps,
        in_workspace,
    })
}

/// The prepared input, queries and rotation query moved by `motion` (the gripper jitter
/// turns with it).
pub fn move_input(
    prep: &PreparedInput,
    queries: &[[f32; 3]],
    rot_query: [f32; 3],
    motion: &Isometry3<f64>,
) -> (PreparedInput, Vec<[f32; 3]>, [f32; 3]) {
    let mv = |p: &[f32; 3]| {
        let q = motion * Point3::new(f64::from(p[0]), f64::from(p[1]), f64::from(p[2]));
        [q.x as f32, q.y as f32, q.z as f32]
    };
    let rm = motion.rotation.to_rotation_matrix().into_inner();
    let turn = |v: &[f32; 3]| {
        let w = rm * Vector3::new(f64::from(v[0]), f64::from(v[1]), f64::from(v[2]));
        [w.x as f32, w.y as f32, w.z as f32]
    };
    let g = prep.gripper;
    let gq = UnitQuaternion::from_quaternion(nalgebra::Quaternion::new(
        f64::from(g.quaternion[3]),
        f64::from(g.quaternion[0]),
        f64::from(g.quaternion[1]),
        f64::from(g.quaternion[2]),
    ));
    let gq2 = motion.rotation * gq;
    let moved = PreparedInput {
        xyz: prep.xyz.iter().map(mv).collect(),
        rgb: prep.rgb.clone(),
        gripper: GripperState {
            position: mv(&g.position),
            quaternion: [
                gq2.coords.x as f32,
                gq2.coords.y as f32,
                gq2.coords.z as f32,
                gq2.coords.w as f32,
            ],
            open: g.open,
        },
        gripper_eps: prep.gripper_eps.iter().map(turn).collect(),
        in_workspace: prep.in_workspace,
    };
    (moved, queries.iter().map(mv).collect(), mv(&rot_query))
}

/// A synthetic tabletop scene in the base frame for benchmarks and tests: a table just below
/// the focus box (z = −0.08 m) over x 0.25..0.9, y −0.33..0.33, and three hemispherical
/// blobs on it, random colours; `n` points (at least 8).
pub fn synthetic_scene(n: usize, seed: u64) -> Result<PointCloud> {
    let mut rng = ChaCha8Rng::seed_from_u64(seed);
    let n = n.max(8);
    let n_table = n * 4 / 7;
    let mut pts = Vec::with_capacity(n);
    for _ in 0..n_table {
        pts.push(Point3::new(
            rng.random_range(0.25..0.9f32),
            rng.random_range(-0.33..0.33f32),
            -0.08,
        ));
    }
    let blobs = [
        (0.45f32, 0.1f32, 0.05f32),
        (0.6, -0.15, 0.07),
        (0.75, 0.05, 0.04),
    ];
    let mut b = 0;
    while pts.len() < n {
        let (cx, cy, r) = blobs[b % 3];
        b += 1;
        let d = Vector3::new(
            rng.random_range(-1.0..1.0f32),
            rng.random_range(-1.0..1.0f32),
            rng.random_range(0.0..1.0f32),
        );
        let len = d.norm();
        if !(1e-3..=1.0).contains(&len) {
            continue;
        }
        let d = d / len;
        pts.push(Point3::new(cx + r * d.x, cy + r * d.y, -0.05 + r * d.z));
    }
    let rgb = (0..pts.len())
        .map(|_| [rng.random(), rng.random(), rng.random()])
        .collect();
    PointCloud::new(FrameId::Base, pts, Some(rgb)).map_err(|e| PolicyError::Sidecar {
        path: "synthetic scene".into(),
        message: e.to_string(),
    })
}

/// max |x − y| / max |y|.
pub fn relative_error(x: &[f64], y: &[f64]) -> f64 {
    let m = y.iter().fold(0.0f64, |m, v| m.max(v.abs()));
    let e = x
        .iter()
        .zip(y)
        .fold(0.0f64, |e, (p, q)| e.max((p - q).abs()));
    if m > 0.0 {
        e / m
    } else {
        e
    }
}

/// Indices of the `k` largest values, largest first (ties: lower index first).
pub fn top_k(v: &[f32], k: usize) -> Vec<usize> {
    let mut idx: Vec<usize> = (0..v.len()).collect();
    idx.sort_by(|&a, &b| v[b].total_cmp(&v[a]).then(a.cmp(&b)));
    idx.truncate(k);
    idx
}

/// Radius (m) of the ball around a cloud point that a cloud-drawn query is uniform in.
pub const CLOUD_QUERY_RADIUS_M: f64 = 0.02;

/// Height above the table (m) below which a cloud point counts as the table's, not an
/// object's, when queries are drawn near the cloud.
const TABLE_BAND_M: f64 = 0.01;

/// The cloud's points more than [`TABLE_BAND_M`] above the table, in the workspace frame:
/// the scene's objects, where the informative negatives are.
pub(crate) fn object_points(cloud: &PointCloud, pc: &PolicyConfig) -> Vec<Point3<f64>> {
    let inv = pc.base_from_workspace.inverse();
    cloud
        .points
        .iter()
        .map(|p| inv * Point3::new(f64::from(p.x), f64::from(p.y), f64::from(p.z)))
        .filter(|p| p.z > pc.table_height + TABLE_BAND_M)
        .collect()
}

/// Checks a [`crate::trainer::TrainConfig::cloud_query_share`]: a share, so in [0, 1].
pub(crate) fn check_cloud_query_share(share: f64) -> Result<()> {
    if (0.0..=1.0).contains(&share) {
        Ok(())
    } else {
        Err(PolicyError::BadConfig(format!(
            "training config: the share of first-level queries drawn near the cloud must be \
             in [0, 1] (e.g. 0.5), got {share}"
        )))
    }
}

/// The first sampling level's `n` translation queries (workspace frame): `share` of them
/// (rounded) each uniform in a [`CLOUD_QUERY_RADIUS_M`] ball around a random point of
/// `cloud` (the scene's object points) inside `bounds`, the rest uniform in `bounds`.
///
/// Why: the loss only pushes the field down where a query lands. The reference draws a
/// third of 1000 queries per level; with the CPU configuration's 30, uniform queries in the
/// gripper box almost never land on the other objects of the scene (the second pipe link
/// when the first is asked for, the other flowers), so nothing teaches the field, or the
/// instruction encoder, to tell them from the one the instruction names. Queries drawn
/// near the cloud put negatives on every object. With `share` 0 no draw differs from the
/// paper's sampling; with no cloud point in `bounds` every query is uniform.
pub fn first_level_queries(
    rng: &mut ChaCha8Rng,
    bounds: &[[f64; 3]; 2],
    cloud: &[Point3<f64>],
    n: usize,
    share: f64,
) -> Result<Vec<Point3<f64>>> {
    check_cloud_query_share(share)?;
    let any_inside = share > 0.0 && cloud.iter().any(|p| in_box(p, bounds));
    let near = if any_inside {
        ((share * n as f64).round() as usize).min(n)
    } else {
        0
    };
    let mut out: Vec<Point3<f64>> = (0..n - near).map(|_| uniform_in_box(rng, bounds)).collect();
    out.extend(queries_near_points(
        rng,
        bounds,
        cloud,
        CLOUD_QUERY_RADIUS_M,
        near,
    )?);
    Ok(out)
}

/// `n` queries, each uniform in the ball of `radius` around a random one of `points` that
/// lies inside `bounds` (clipped to them); none when no point does.
pub(crate) fn queries_near_points(
    rng: &mut ChaCha8Rng,
    bounds: &[[f64; 3]; 2],
    points: &[Point3<f64>],
    radius: f64,
    n: usize,
) -> Result<Vec<Point3<f64>>> {
    let inside: Vec<&Point3<f64>> = points.iter().filter(|p| in_box(p, bounds)).collect();
    if inside.is_empty() {
        return Ok(Vec::new());
    }
    let mut out = Vec::with_capacity(n);
    for _ in 0..n {
        let centre = inside[rng.random_range(0..inside.len())];
        // A centre inside the bounds leaves at least an eighth of its ball's cube in them,
        // so a single draw never fails.
        out.extend(uniform_in_ball(rng, centre, radius, bounds, 1)?);
    }
    Ok(out)
}

/// Indices of up to `k` samples, best logit first, each at least `min_dist` from the ones
/// before; filled up with the next best when fewer are that far apart.
pub fn top_k_apart(samples: &[Point3<f64>], logits: &[f32], k: usize, min_dist: f64) -> Vec<usize> {
    // One pass in logit order: a sample far enough from every kept one is kept, the others
    // wait, in the same order, to fill up.
    let (mut kept, mut rest) = (Vec::with_capacity(k), Vec::new());
    for i in top_k(logits, logits.len()) {
        if kept.len() < k
            && kept
                .iter()
                .all(|&j: &usize| (samples[i] - samples[j]).norm() >= min_dist)
        {
            kept.push(i);
        } else {
            rest.push(i);
        }
    }
    kept.extend(rest);
    kept.truncate(k);
    kept
}

/// Whether `p` lies in the box `b` = [min, max] (bounds included).
pub(crate) fn in_box(p: &Point3<f64>, b: &[[f64; 3]; 2]) -> bool {
    (0..3).all(|i| p[i] >= b[0][i] && p[i] <= b[1][i])
}

pub(crate) fn uniform_in_box(rng: &mut ChaCha8Rng, b: &[[f64; 3]; 2]) -> Point3<f64> {
    Point3::new(
        rng.random_range(b[0][0]..b[1][0]),
        rng.random_range(b[0][1]..b[1][1]),
        rng.random_range(b[0][2]..b[1][2]),
    )
}

/// `n` points uniform in the ball (`centre`, `r`) clipped to the box `b` (rejection sampling
/// in the clipped cube, as the reference).
pub(crate) fn uniform_in_ball(
    rng: &mut ChaCha8Rng,
    centre: &Point3<f64>,
    r: f64,
    b: &[[f64; 3]; 2],
    n: usize,
) -> Result<Vec<Point3<f64>>> {
    let mut cube = [[0.0; 3]; 2];
    for i in 0..3 {
        cube[0][i] = (centre[i] - r).clamp(b[0][i], b[1][i]);
        cube[1][i] = (centre[i] + r).clamp(b[0][i], b[1][i]);
        if cube[0][i].partial_cmp(&cube[1][i]) != Some(std::cmp::Ordering::Less) {
            return Err(PolicyError::TooFewPoints {
                what: "translation sampling (anchor ball outside the gripper bounds)",
                needed: n,
                got: 0,
            });
        }
    }
    let mut out = Vec::with_capacity(n);
    let mut tries = 0usize;
    while out.len() < n {
        let p = uniform_in_box(rng, &cube);
        if (p - centre).norm() < r {
            out.push(p);
        }
        tries += 1;
        if tries > 1000 * n.max(1) {
            return Err(PolicyError::TooFewPoints {
                what: "translation sampling (ball and gripper bounds barely overlap)",
                needed: n,
                got: out.len(),
            });
        }
    }
    Ok(out)
}
