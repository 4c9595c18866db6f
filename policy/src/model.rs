//! The whole `EquFieldUnet`: instruction condition, point features with the gripper
//! proprioception, the iFiLM EquiformerV2 U-net, and the field heads.
//!
//! Spec: `equact.md` ("Point cloud in", "U-net", "Heads") and the `whole_model_small` sidecar
//! (`conventions.inputs`, `conventions.unet_schedule`). Down block n pools (FPS + 16-NN
//! coefficient max-pool) when its ratio is below 1, the middle block pools the last down
//! output, up blocks interpolate (3-NN inverse-distance) onto the skip coordinates and add the
//! skip features after their TransBlock; the last up block outputs `field_nn_c` channels and
//! `norm_1` closes the U-net. Every discrete choice (FPS, kNN lists, graph edges) can be
//! injected, so a parity run can follow recorded choices among near-coincident points. The
//! heads are the reference's equivariant ones or, with [`HeadKind::Plain`], the paper's
//! plain-transformer ablation ([`crate::plain_heads`]).

use crate::attention::{AttentionConfig, EdgeSet};
use crate::error::{PolicyError, Result};
use crate::grids::GridRotation;
use crate::grids::S2Resolution;
use crate::heads::{FieldHeads, FieldHeadsConfig, RotationQuery};
use crate::language::InstructionEncoder;
use crate::layers::{rows_of, GaussianRbf, Linear, RmsNormSh};
use crate::plain_heads::{PlainHeads, PlainHeadsConfig};
use crate::points::{
    check_finite, coefficient_max_pool_threads, farthest_point_sampling, knn_threads, upsample,
    upsample_weights, UpsampleDistance,
};
use crate::so3::{num_coefficients, WignerCalculator};
use crate::transblock::{FilmKind, TransBlock, TransBlockConfig};
use crate::weights::Scope;

/// Neighbours of each pooled centre in the max-pool.
pub const POOL_NEIGHBOURS: usize = 16;
/// Neighbours of each fine point in the up-sampling.
pub const UPSAMPLE_NEIGHBOURS: usize = 3;

/// Which field heads read the U-net features.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub enum HeadKind {
    /// The reference's equivariant graph-attention heads ([`FieldHeads`]).
    #[default]
    Equivariant,
    /// The paper's ablation: a plain transformer layer per head ([`PlainHeads`]).
    Plain,
}

/// The reference's `EquFieldUnet` constructor arguments this implementation uses.
#[derive(Debug, Clone, PartialEq)]
pub struct ModelConfig {
    /// kNN graph size per scale (self included).
    pub max_neighbors: Vec<usize>,
    /// Graph radius per scale (the radial basis cut-off is 0.99 × this).
    pub max_radius: Vec<f64>,
    /// Pool ratio per scale (1 = no pooling).
    pub pool_ratio: Vec<f64>,
    /// Channels per level (one more entry than scales).
    pub sphere_channels: Vec<usize>,
    /// Attention hidden channels per scale.
    pub attn_hidden_channels: Vec<usize>,
    /// Attention heads.
    pub num_heads: usize,
    /// Attention logit channels per head, per scale.
    pub attn_alpha_channels: Vec<usize>,
    /// Attention value channels per head, per scale.
    pub attn_value_channels: Vec<usize>,
    /// Feed-forward hidden channels per scale.
    pub ffn_hidden_channels: Vec<usize>,
    /// Maximum degree of the U-net.
    pub lmax: usize,
    /// Maximum order in the U-net's edge frames.
    pub mmax: usize,
    /// Channels of the field heads.
    pub field_nn_c: usize,
    /// Number of cloud points replaced by the gripper.
    pub n_gripper_pos: usize,
    /// Heads of the instruction Transformer.
    pub lang_heads: usize,
    /// Width of one instruction-Transformer head.
    pub lang_dim_head: usize,
    /// HEALPix level of the rotation grid.
    pub rotation_grid_level: u32,
    /// S2 activation grids (reference = parity mode).
    pub s2_resolution: S2Resolution,
    /// Distance of the up-sampling weights (L1 = parity mode).
    pub upsample_distance: UpsampleDistance,
    /// The U-net feed-forward networks' iFiLM (the reference's hypernetwork = parity mode).
    pub film_kind: FilmKind,
    /// The field heads (equivariant = the reference; plain = the paper's ablation).
    pub heads: HeadKind,
}

impl ModelConfig {
    /// The reference's default (physical-robot) configuration, parity mode.
    pub fn reference() -> Self {
        Self {
            max_neighbors: vec![16; 4],
            max_radius: vec![0.2, 0.4, 0.8, 1.6],
            pool_ratio: vec![1.0, 0.25, 0.25, 0.25],
            sphere_channels: vec![32, 32, 64, 128, 256],
            attn_hidden_channels: vec![16, 16, 32, 64],
            num_heads: 4,
            attn_alpha_channels: vec![8, 8, 16, 32],
            attn_value_channels: vec![4, 4, 8, 16],
            ffn_hidden_channels: vec![64, 64, 128, 256],
            lmax: 3,
            mmax: 2,
            field_nn_c: 64,
            n_gripper_pos: 10,
            lang_heads: 6,
            lang_dim_head: 64,
            rotation_grid_level: 1,
            s2_resolution: S2Resolution::Reference,
            upsample_distance: UpsampleDistance::L1,
            film_kind: FilmKind::Hypernetwork,
            heads: HeadKind::Equivariant,
        }
    }

    /// The attention sizes of a U-net block at scale `i` with `cin` channels in and out.
    pub fn block_attention(&self, i: usize, cin: usize) -> AttentionConfig {
        AttentionConfig {
            lmax: self.lmax,
            mmax: self.mmax,
            sphere_channels: cin,
            hidden_channels: self.attn_hidden_channels[i],
            num_heads: self.num_heads,
            alpha_channels: self.attn_alpha_channels[i],
            value_channels: self.attn_value_channels[i],
            output_channels: cin,
        }
    }

    /// The sizes the equivariant field heads read (scale 1's attention and feed-forward).
    pub fn heads_config(&self) -> FieldHeadsConfig {
        FieldHeadsConfig {
            field_channels: self.field_nn_c,
            attn_hidden_channels: self.attn_hidden_channels[1],
            num_heads: self.num_heads,
            alpha_channels: self.attn_alpha_channels[1],
            value_channels: self.attn_value_channels[1],
            ffn_hidden_channels: self.ffn_hidden_channels[1],
            node_lmax: self.lmax,
        }
    }

    /// Reads the `EquFieldUnet` constructor record of a fixture sidecar (parity mode).
    pub fn from_constructor(v: &serde_json::Value) -> Result<Self> {
        let bad = |k: &str| PolicyError::Sidecar {
            path: "constructor.EquFieldUnet".into(),
            message: format!("{k} missing or malformed"),
        };
        let list_u = |k: &str| -> Result<Vec<usize>> {
            v.get(k)
                .and_then(|x| x.as_array())
                .and_then(|a| {
                    a.iter()
                        .map(|x| x.as_u64().map(|u| u as usize))
                        .collect::<Option<Vec<_>>>()
                })
                .ok_or_else(|| bad(k))
        };
        let list_f = |k: &str| -> Result<Vec<f64>> {
            v.get(k)
                .and_then(|x| x.as_array())
                .and_then(|a| a.iter().map(|x| x.as_f64()).collect::<Option<Vec<_>>>())
                .ok_or_else(|| bad(k))
        };
        let one = |k: &str| -> Result<usize> {
            v.get(k)
                .and_then(|x| x.as_u64())
                .map(|u| u as usize)
                .ok_or_else(|| bad(k))
        };
        let first =
            |k: &str| -> Result<usize> { list_u(k)?.first().copied().ok_or_else(|| bad(k)) };
        let cfg = Self {
            max_neighbors: list_u("max_neighbors")?,
            max_radius: list_f("max_radius")?,
            pool_ratio: list_f("pool_ratio")?,
            sphere_channels: list_u("sphere_channels")?,
            attn_hidden_channels: list_u("attn_hidden_channels")?,
            num_heads: one("num_heads")?,
            attn_alpha_channels: list_u("attn_alpha_channels")?,
            attn_value_channels: list_u("attn_value_channels")?,
            ffn_hidden_channels: list_u("ffn_hidden_channels")?,
            lmax: first("lmax_list")?,
            mmax: first("mmax_list")?,
            field_nn_c: one("field_nn_c")?,
            n_gripper_pos: one("n_gripper_pos")?,
            ..Self::reference()
        };
        cfg.validate()?;
        Ok(cfg)
    }

    /// Number of U-net scales.
    pub fn n_scales(&self) -> usize {
        self.max_radius.len()
    }

    /// Checks that the per-scale lists agree in length.
    pub fn validate(&self) -> Result<()> {
        let n = self.n_scales();
        let lists = [
            ("max_neighbors", self.max_neighbors.len(), n),
            ("pool_ratio", self.pool_ratio.len(), n),
            ("sphere_channels", self.sphere_channels.len(), n + 1),
            ("attn_hidden_channels", self.attn_hidden_channels.len(), n),
            ("attn_alpha_channels", self.attn_alpha_channels.len(), n),
            ("attn_value_channels", self.attn_value_channels.len(), n),
            ("ffn_hidden_channels", self.ffn_hidden_channels.len(), n),
        ];
        for (name, got, expected) in lists {
            if got != expected || n < 2 {
                return Err(PolicyError::ShapeMismatch {
                    name: format!("model config {name}"),
                    expected: vec![expected],
                    got: vec![got],
                });
            }
        }
        Ok(())
    }
}

/// Discrete choices of one U-net block; `None` means "compute".
#[derive(Debug, Clone, Default, PartialEq, Eq)]
pub struct BlockIndices {
    /// FPS picks (sorted) into the block's input nodes.
    pub fps: Option<Vec<usize>>,
    /// Per pooled centre, its neighbours among the input nodes.
    pub pool_knn: Option<Vec<Vec<usize>>>,
    /// Per fine point, its up-sampling neighbours among the coarse nodes.
    pub up_knn: Option<Vec<Vec<usize>>>,
    /// Graph edges (src, dst), grouped by destination.
    pub graph: Option<(Vec<usize>, Vec<usize>)>,
}

/// What one block did: the choices it used and its output.
#[derive(Debug, Clone)]
pub struct BlockTrace {
    /// Block name (`down0`, ..., `middle`, `up0`, ...).
    pub name: String,
    /// The choices made (all `Some` where the block made them).
    pub indices: BlockIndices,
    /// Output node positions.
    pub coord: Vec<[f32; 3]>,
    /// Output features `[n, (lmax+1)², c]` of the block's TransBlock.
    pub embedding: Vec<f32>,
    /// For up blocks with a skip: the features after the skip was added.
    pub after_skip: Option<Vec<f32>>,
    /// CPU time of the block (pooling or up-sampling, graph, TransBlock), seconds.
    pub seconds: f64,
}

/// The encoded scene: U-net output on the cloud points.
#[derive(Debug, Clone)]
pub struct Encoded {
    /// The FiLM condition `[dim]`.
    pub condition: Vec<f32>,
    /// The effective point positions (gripper points written in).
    pub xyz: Vec<[f32; 3]>,
    /// Output features `[n, (lmax+1)², field_nn_c]` after `norm_1`.
    pub embedding: Vec<f32>,
    /// Output node positions.
    pub coord: Vec<[f32; 3]>,
    /// Per block: choices and outputs.
    pub blocks: Vec<BlockTrace>,
    /// CPU time of the instruction encoder, seconds.
    pub language_seconds: f64,
}

/// The robot state the network reads: position, quaternion (x, y, z, w), open state.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct GripperState {
    /// Position (m).
    pub position: [f32; 3],
    /// Orientation quaternion (x, y, z, w).
    pub quaternion: [f32; 4],
    /// Open state (1 open, 0 closed).
    pub open: f32,
}

impl GripperState {
    /// The rotation matrix of the quaternion (PyTorch3D's formula, in f32).
    pub fn matrix(&self) -> [[f32; 3]; 3] {
        let [i, j, k, r] = self.quaternion;
        let two_s = 2.0 / (r * r + i * i + j * j + k * k);
        [
            [
                1.0 - two_s * (j * j + k * k),
                two_s * (i * j - k * r),
                two_s * (i * k + j * r),
            ],
            [
                two_s * (i * j + k * r),
                1.0 - two_s * (i * i + k * k),
                two_s * (j * k - i * r),
            ],
            [
                two_s * (i * k - j * r),
                two_s * (j * k + i * r),
                1.0 - two_s * (i * i + j * j),
            ],
        ]
    }
}

/// The point inputs of the network, shared by inference and training: positions with the
/// gripper points written in, and the type-0 input features.
#[derive(Debug, Clone)]
pub(crate) struct PointInputs {
    /// Positions; the last `n_gripper_pos` are the gripper position plus its jitter.
    pub pts: Vec<[f32; 3]>,
    /// Type-0 input features `[n, 3]`: colour − 0.5, and (open − 0.5)·10 − 0.5 on the
    /// gripper points.
    pub feat: Vec<f32>,
    /// Coefficients per node, (lmax+1)².
    pub k: usize,
    /// Channels of the first level.
    pub c0: usize,
    /// Index of the first gripper point.
    pub first_gripper: usize,
}

impl PointInputs {
    /// Checks the observation against `cfg` and builds the inputs.
    pub(crate) fn new(
        cfg: &ModelConfig,
        xyz: &[[f32; 3]],
        rgb: &[[f32; 3]],
        gripper: &GripperState,
        gripper_eps: &[[f32; 3]],
    ) -> Result<Self> {
        let n = xyz.len();
        let ng = cfg.n_gripper_pos;
        if n <= ng {
            return Err(PolicyError::TooFewPoints {
                what: "encode (cloud points plus the gripper points)",
                needed: ng + 1,
                got: n,
            });
        }
        check_finite("point cloud", xyz)?;
        if rgb.len() != n || gripper_eps.len() != ng {
            return Err(PolicyError::ShapeMismatch {
                name: "rgb / gripper_eps".into(),
                expected: vec![n, ng],
                got: vec![rgb.len(), gripper_eps.len()],
            });
        }
        let mut pts = xyz.to_vec();
        let mut feat: Vec<f32> = Vec::with_capacity(n * 3);
        for (i, c) in rgb.iter().enumerate() {
            let c = if i >= n - ng {
                [(gripper.open - 0.5) * 10.0; 3]
            } else {
                *c
            };
            feat.extend(c.iter().map(|v| v - 0.5));
        }
        for (p, e) in pts[n - ng..].iter_mut().zip(gripper_eps) {
            *p = [
                gripper.position[0] + e[0],
                gripper.position[1] + e[1],
                gripper.position[2] + e[2],
            ];
        }
        check_finite("point cloud with gripper points", &pts)?;
        let k = num_coefficients(cfg.lmax);
        let c0 = cfg.sphere_channels[0];
        if c0 < 3 || k < 4 {
            return Err(PolicyError::ShapeMismatch {
                name: "sphere_channels[0] (the gripper axes need 3 type-1 channels)".into(),
                expected: vec![3],
                got: vec![c0],
            });
        }
        Ok(Self {
            pts,
            feat,
            k,
            c0,
            first_gripper: n - ng,
        })
    }

    /// The gripper's axes on the gripper points: (node, coefficient row, channel, value) with
    /// 10·R on the l = 1 rows of channels 0..2; every other l ≥ 1 input is zero.
    pub(crate) fn gripper_axes(
        &self,
        gripper: &GripperState,
    ) -> impl Iterator<Item = (usize, usize, usize, f32)> {
        let g = gripper.matrix();
        (self.first_gripper..self.pts.len()).flat_map(move |node| {
            (0..3).flat_map(move |a| (0..3).map(move |ch| (node, 1 + a, ch, 10.0 * g[a][ch])))
        })
    }
}

#[derive(Debug, Clone)]
struct UnetBlock {
    name: String,
    scale: f64,
    k: usize,
    rbf: GaussianRbf,
    block: TransBlock,
}

/// The edges of one U-net block, kept for the later blocks on the same nodes.
struct SharedEdges {
    coord: Vec<[f32; 3]>,
    k: usize,
    /// Whether the graph is the kNN graph (not a forced one).
    knn: bool,
    edges: EdgeSet,
}

/// The `EquFieldUnet` network.
#[derive(Debug, Clone)]
pub struct EquFieldUnet {
    /// Configuration.
    pub cfg: ModelConfig,
    lang: InstructionEncoder,
    type0: Linear,
    down: Vec<UnetBlock>,
    middle: UnetBlock,
    up: Vec<UnetBlock>,
    norm_1: RmsNormSh,
    heads: Heads,
    calc: WignerCalculator,
    /// Threads of a forward pass ([`EquFieldUnet::set_threads`]).
    threads: usize,
}

/// The field heads of a model: the equivariant ones or the plain ablation, with one API
/// (the rotation grid, translation logits, the rotation query, logits on other rotations).
#[derive(Debug, Clone)]
pub enum Heads {
    /// The equivariant heads (boxed, as the plain ones: both are kilobytes of layer structs).
    Equivariant(Box<FieldHeads>),
    /// The plain (non-equivariant) transformer heads.
    Plain(Box<PlainHeads>),
}

impl Heads {
    /// The rotation grid the logits refer to.
    pub fn grid(&self) -> &[GridRotation] {
        match self {
            Heads::Equivariant(h) => h.grid(),
            Heads::Plain(h) => h.grid(),
        }
    }

    /// Translation logits at `queries` from node features `node_emb` at `node_pos`.
    pub fn trans_logits(
        &self,
        node_emb: &[f32],
        node_pos: &[[f32; 3]],
        queries: &[[f32; 3]],
    ) -> Result<Vec<f32>> {
        match self {
            Heads::Equivariant(h) => h.trans_logits(node_emb, node_pos, queries),
            Heads::Plain(h) => h.trans_logits(node_emb, node_pos, queries),
        }
    }

    /// The rotation query at one point: open logit and rotation logits.
    pub fn rot_query(
        &self,
        node_emb: &[f32],
        node_pos: &[[f32; 3]],
        query: [f32; 3],
    ) -> Result<RotationQuery> {
        match self {
            Heads::Equivariant(h) => h.rot_query(node_emb, node_pos, query),
            Heads::Plain(h) => h.rot_query(node_emb, node_pos, query),
        }
    }

    /// Rotation logits of given SO(3) coefficients on an arbitrary set of rotations.
    pub fn logits_on(&self, so3_coeffs: &[f64], rotations: &[GridRotation]) -> Result<Vec<f64>> {
        match self {
            Heads::Equivariant(h) => h.logits_on(so3_coeffs, rotations),
            Heads::Plain(h) => h.logits_on(so3_coeffs, rotations),
        }
    }
}

/// Translation, open and rotation outputs of the heads.
#[derive(Debug, Clone)]
pub struct FieldOutputs {
    /// Translation logits at the queries.
    pub trans_logits: Vec<f32>,
    /// Rotation query (open logit, rotation logits).
    pub rot: RotationQuery,
}

impl EquFieldUnet {
    /// Loads every module from `s` (keys as the reference's `state_dict()`).
    pub fn load(s: &Scope<'_>, cfg: ModelConfig) -> Result<Self> {
        cfg.validate()?;
        let n = cfg.n_scales();
        let lang = InstructionEncoder::load(s, cfg.lang_heads, cfg.lang_dim_head)?;
        let type0 = Linear::load_sized(&s.sub("type0_linear"), cfg.sphere_channels[0], 3, true)?;
        let block = |scope: Scope<'_>, name: String, i: usize, cin: usize, cout: usize, scale| {
            let attn = cfg.block_attention(i, cin);
            let tb = TransBlock::load_with_grids(
                &scope.sub("transblock"),
                TransBlockConfig {
                    attn,
                    ffn_hidden_channels: cfg.ffn_hidden_channels[i],
                    output_channels: cout,
                    film: Some(cfg.film_kind),
                },
                cfg.s2_resolution.grid(cfg.lmax, cfg.mmax)?,
                cfg.s2_resolution.grid(cfg.lmax, cfg.lmax)?,
            )?;
            Ok::<_, PolicyError>(UnetBlock {
                name,
                scale,
                k: cfg.max_neighbors[i],
                rbf: GaussianRbf::load(&scope.sub("distance_expansion"), cfg.max_radius[i] * 0.99)?,
                block: tb,
            })
        };
        let sc = &cfg.sphere_channels;
        let mut down = Vec::with_capacity(n);
        for i in 0..n {
            down.push(block(
                s.sub("down_blocks").sub(&i.to_string()).sub("block"),
                format!("down{i}"),
                i,
                sc[i],
                sc[i + 1],
                cfg.pool_ratio[i],
            )?);
        }
        let middle = block(
            s.sub("middle_block").sub("block"),
            "middle".into(),
            n - 1,
            sc[n],
            sc[n],
            cfg.pool_ratio[n - 1],
        )?;
        let mut up = Vec::with_capacity(n);
        for (j, i) in (0..n).rev().enumerate() {
            let cout = if i == 0 { cfg.field_nn_c } else { sc[i] };
            up.push(block(
                s.sub("up_blocks").sub(&j.to_string()).sub("block"),
                format!("up{j}"),
                i,
                sc[i + 1],
                cout,
                1.0 / cfg.pool_ratio[i],
            )?);
        }
        let norm_1 = RmsNormSh::load(&s.sub("norm_1"), cfg.lmax, cfg.field_nn_c)?;
        let heads = match cfg.heads {
            HeadKind::Equivariant => Heads::Equivariant(Box::new(FieldHeads::load_with(
                s,
                cfg.heads_config(),
                cfg.rotation_grid_level,
                cfg.s2_resolution,
            )?)),
            HeadKind::Plain => Heads::Plain(Box::new(PlainHeads::load(
                s,
                PlainHeadsConfig::of(&cfg)?,
                cfg.rotation_grid_level,
            )?)),
        };
        Ok(Self {
            calc: WignerCalculator::new(cfg.lmax)?,
            cfg,
            lang,
            type0,
            down,
            middle,
            up,
            norm_1,
            heads,
            threads: 1,
        })
    }

    /// Threads of [`EquFieldUnet::encode`] and [`EquFieldUnet::query`] (1: the caller's
    /// only). The U-net's graphs and attentions and the translation head's query batches
    /// are split among them; the results are the same for any count (see [`crate::parallel`]).
    pub fn set_threads(&mut self, threads: usize) {
        let threads = threads.max(1);
        self.threads = threads;
        for b in self
            .down
            .iter_mut()
            .chain([&mut self.middle])
            .chain(&mut self.up)
        {
            b.block.set_threads(threads);
        }
        match &mut self.heads {
            Heads::Equivariant(h) => h.set_threads(threads),
            Heads::Plain(h) => h.set_threads(threads),
        }
    }

    /// Threads of a forward pass.
    pub fn threads(&self) -> usize {
        self.threads
    }

    /// The field heads (rotation grid, logits on other rotations).
    pub fn heads(&self) -> &Heads {
        &self.heads
    }

    /// The instruction encoder.
    pub fn language(&self) -> &InstructionEncoder {
        &self.lang
    }

    /// Names of the U-net blocks in execution order.
    pub fn block_names(&self) -> Vec<String> {
        self.down
            .iter()
            .chain(std::iter::once(&self.middle))
            .chain(&self.up)
            .map(|b| b.name.clone())
            .collect()
    }

    /// Encodes one observation: `xyz`, `rgb` (in [0, 1]) of equal length, the gripper state,
    /// the jitter of the gripper points (`n_gripper_pos` offsets, ~1e-5), and the instruction
    /// tokens `[T, token_dim]`. `overrides` (by block name) replaces computed choices.
    pub fn encode(
        &self,
        xyz: &[[f32; 3]],
        rgb: &[[f32; 3]],
        gripper: &GripperState,
        gripper_eps: &[[f32; 3]],
        instruction: &[f32],
        overrides: &[(String, BlockIndices)],
    ) -> Result<Encoded> {
        let cfg = &self.cfg;
        let inputs = PointInputs::new(cfg, xyz, rgb, gripper, gripper_eps)?;
        let t_lang = crate::predict::CpuTimer::start();
        let condition = self.lang.condition(instruction, 1)?;
        let language_seconds = t_lang.elapsed();
        let (n, k, c0) = (inputs.pts.len(), inputs.k, inputs.c0);
        let t0 = self.type0.forward(&inputs.feat)?;
        let mut x = vec![0.0f32; n * k * c0];
        for node in 0..n {
            x[node * k * c0..node * k * c0 + c0].copy_from_slice(&t0[node * c0..(node + 1) * c0]);
        }
        for (node, row, ch, v) in inputs.gripper_axes(gripper) {
            x[(node * k + row) * c0 + ch] = v;
        }
        let find = |name: &str| {
            overrides
                .iter()
                .find(|(b, _)| b == name)
                .map(|(_, i)| i.clone())
                .unwrap_or_default()
        };
        let mut blocks = Vec::new();
        let mut shared = Vec::new();
        let mut coord = inputs.pts.clone();
        let pts = inputs.pts;
        let mut skips: Vec<(Vec<[f32; 3]>, Vec<f32>)> = Vec::new();
        for b in &self.down {
            let (c2, x2) = self.block_forward(
                b,
                &coord,
                &x,
                None,
                &condition,
                find(&b.name),
                (&mut blocks, &mut shared),
            )?;
            coord = c2;
            x = x2;
            skips.push((coord.clone(), x.clone()));
        }
        skips.pop();
        let (c2, x2) = self.block_forward(
            &self.middle,
            &coord,
            &x,
            None,
            &condition,
            find(&self.middle.name),
            (&mut blocks, &mut shared),
        )?;
        coord = c2;
        x = x2;
        for b in &self.up {
            let skip = if b.scale > 1.0 { skips.pop() } else { None };
            let (c2, mut x2) = self.block_forward(
                b,
                &coord,
                &x,
                skip.as_ref().map(|s| s.0.as_slice()),
                &condition,
                find(&b.name),
                (&mut blocks, &mut shared),
            )?;
            if let Some((_, sx)) = &skip {
                if sx.len() != x2.len() {
                    return Err(PolicyError::ShapeMismatch {
                        name: format!("{} skip features", b.name),
                        expected: vec![x2.len()],
                        got: vec![sx.len()],
                    });
                }
                for (a, s) in x2.iter_mut().zip(sx) {
                    *a += s;
                }
                if let Some(t) = blocks.last_mut() {
                    t.after_skip = Some(x2.clone());
                }
            }
            coord = c2;
            x = x2;
        }
        let embedding = self.norm_1.forward(&x)?;
        Ok(Encoded {
            condition,
            xyz: pts,
            embedding,
            coord,
            blocks,
            language_seconds,
        })
    }

    #[allow(clippy::too_many_arguments)]
    fn block_forward(
        &self,
        b: &UnetBlock,
        coord: &[[f32; 3]],
        x: &[f32],
        up_coord: Option<&[[f32; 3]]>,
        condition: &[f32],
        mut idx: BlockIndices,
        (trace, shared): (&mut Vec<BlockTrace>, &mut Vec<SharedEdges>),
    ) -> Result<(Vec<[f32; 3]>, Vec<f32>)> {
        let t0 = crate::predict::CpuTimer::start();
        let lmax = self.cfg.lmax;
        let k = num_coefficients(lmax);
        let n = coord.len();
        let c = rows_of(&format!("{} input features", b.name), x.len(), n.max(1) * k)?;
        let (coord, x) = if b.scale < 1.0 {
            let m = ((b.scale * n as f64).ceil() as usize).max(1);
            let fps = match idx.fps.take() {
                Some(f) => f,
                None => farthest_point_sampling(coord, m)?,
            };
            let centres: Vec<[f32; 3]> = fps
                .iter()
                .map(|&i| {
                    coord.get(i).copied().ok_or(PolicyError::IndexOutOfRange {
                        name: format!("{} fps", b.name),
                        value: i as i64,
                        len: n,
                    })
                })
                .collect::<Result<_>>()?;
            let nb = match idx.pool_knn.take() {
                Some(v) => v,
                None => knn_threads(coord, &centres, POOL_NEIGHBOURS, self.threads)?,
            };
            let pooled = coefficient_max_pool_threads(x, n, lmax, c, &nb, self.threads)?;
            idx.fps = Some(fps);
            idx.pool_knn = Some(nb);
            (centres, pooled)
        } else if b.scale > 1.0 {
            let Some(up) = up_coord else {
                return Err(PolicyError::TooFewPoints {
                    what: "up-sampling block without skip coordinates",
                    needed: 1,
                    got: 0,
                });
            };
            let nb = match idx.up_knn.take() {
                Some(v) => v,
                None => knn_threads(coord, up, UPSAMPLE_NEIGHBOURS, self.threads)?,
            };
            let w = upsample_weights(up, coord, &nb, self.cfg.upsample_distance)?;
            let y = upsample(x, n, k * c, &nb, &w)?;
            idx.up_knn = Some(nb);
            (up.to_vec(), y)
        } else {
            (coord.to_vec(), x.to_vec())
        };
        // An earlier block on the same nodes with the same neighbour count (an up block and
        // its down block, the middle block and the last down block) has built these edges and
        // their frames already: only the radial basis is this block's own. A forced graph
        // (the equivariance report's) must be that block's graph too, and a block without one
        // takes only a kNN graph.
        let same = shared.iter().find(|g| {
            g.k == b.k
                && g.coord == coord
                && match &idx.graph {
                    Some((s, d)) => *s == g.edges.src && *d == g.edges.dst,
                    None => g.knn,
                }
        });
        let knn = idx.graph.is_none();
        let edges = match same {
            Some(g) => g.edges.with_rbf(&b.rbf, self.threads)?,
            None => {
                let (src, dst) = match idx.graph.take() {
                    Some(g) => g,
                    None => knn_graph_threads(&coord, b.k, self.threads)?,
                };
                EdgeSet::new_threads(
                    &self.calc,
                    lmax,
                    (&coord, &coord),
                    src,
                    dst,
                    &b.rbf,
                    self.threads,
                )?
            }
        };
        let y = b.block.forward(&x, &x, &edges, Some(condition))?;
        idx.graph = Some((edges.src.clone(), edges.dst.clone()));
        if same.is_none() {
            shared.push(SharedEdges {
                coord: coord.clone(),
                k: b.k,
                knn,
                edges,
            });
        }
        trace.push(BlockTrace {
            name: b.name.clone(),
            indices: idx,
            coord: coord.clone(),
            embedding: y.clone(),
            after_skip: None,
            seconds: t0.elapsed(),
        });
        Ok((coord, y))
    }

    /// Runs the heads on an encoded scene: translation logits at `trans_queries`, open and
    /// rotation logits at `rot_query`.
    pub fn query(
        &self,
        enc: &Encoded,
        trans_queries: &[[f32; 3]],
        rot_query: [f32; 3],
    ) -> Result<FieldOutputs> {
        Ok(FieldOutputs {
            trans_logits: self
                .heads
                .trans_logits(&enc.embedding, &enc.coord, trans_queries)?,
            rot: self
                .heads
                .rot_query(&enc.embedding, &enc.coord, rot_query)?,
        })
    }
}

/// The U-net's kNN graph: for each node its `k` nearest nodes (itself included) by
/// increasing distance, the self edge dropped; (src, dst) grouped by destination.
pub fn knn_graph(coord: &[[f32; 3]], k: usize) -> Result<(Vec<usize>, Vec<usize>)> {
    knn_graph_threads(coord, k, 1)
}

/// [`knn_graph`] with the neighbour search on `threads` threads (the same graph).
pub fn knn_graph_threads(
    coord: &[[f32; 3]],
    k: usize,
    threads: usize,
) -> Result<(Vec<usize>, Vec<usize>)> {
    let nb = knn_threads(coord, coord, k, threads)?;
    let (mut src, mut dst) = (Vec::new(), Vec::new());
    for (d, row) in nb.iter().enumerate() {
        for &s in row.iter().filter(|&&s| s != d) {
            src.push(s);
            dst.push(d);
        }
    }
    Ok((src, dst))
}
