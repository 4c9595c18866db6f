//! The field heads of `EquFieldUnet`: translation logits at query points, the gripper-open
//! logit and rotation logits at one query location.
//!
//! Spec: fixtures README ("Field heads", "Rotation head") and the `query_heads` sidecar.
//! Translation: node features cut to l <= 1 (first `field_nn_c` channels); per query the
//! edges are the first 200 nodes within radius 2 (ascending index) followed by the 100
//! nearest (duplicates kept); one graph attention (lmax 1, mmax 1) onto zero destination
//! features; the logit is output row 0, channel 0. Rotation: node features lifted to l <= 4
//! (last `field_nn_c` channels, l = 4 zero), every node within radius 2 connects to the query,
//! one TransBlock (lmax 4, mmax 3, no FiLM); channel C−1 at l = 0 is the open logit, channels
//! 0..C−2 go through the S2 → SO(3) lift and are evaluated on the rotation grid.

use crate::attention::{AttentionConfig, EdgeSet, GraphAttention};
use crate::error::{PolicyError, Result};
use crate::grids::{so3_healpix_grid, GridRotation, S2Resolution};
use crate::layers::{rows_of, GaussianRbf};
use crate::points::{check_finite, knn};
use crate::rotation_head::RotationHead;
use crate::so3::{num_coefficients, WignerCalculator};
use crate::transblock::{TransBlock, TransBlockConfig};
use crate::weights::Scope;

/// Radius of the query graphs (the reference's `trans_query_r` and `rot_query_r`).
pub const QUERY_RADIUS: f32 = 2.0;
/// Radius neighbours kept per translation query (300 − 100).
pub const TRANS_RADIUS_NEIGHBOURS: usize = 200;
/// Nearest neighbours appended per translation query.
pub const TRANS_KNN: usize = 100;
/// Radius neighbours kept per rotation query.
pub const ROT_MAX_NEIGHBOURS: usize = 10000;
/// Translation queries evaluated together (their edges never interact: the softmax is per
/// query).
pub const TRANS_QUERY_BATCH: usize = 4;
/// Degree of the translation field.
pub const TRANS_LMAX: usize = 1;
/// Degree of the rotation field.
pub const ROT_LMAX: usize = 4;
/// Order kept in the rotation field's edge frames.
pub const ROT_MMAX: usize = 3;

/// Sizes of the field heads (the reference's `EquFieldUnet` arguments that reach them).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct FieldHeadsConfig {
    /// Channels of the field features (`field_nn_c`).
    pub field_channels: usize,
    /// Attention hidden channels (`attn_hidden_channels[1]`).
    pub attn_hidden_channels: usize,
    /// Attention heads.
    pub num_heads: usize,
    /// Logit channels per head (`attn_alpha_channels[1]`).
    pub alpha_channels: usize,
    /// Value channels per head (`attn_value_channels[1]`).
    pub value_channels: usize,
    /// Hidden channels of the rotation TransBlock's feed-forward (`ffn_hidden_channels[1]`).
    pub ffn_hidden_channels: usize,
    /// Degree of the U-net features the heads read.
    pub node_lmax: usize,
}

impl FieldHeadsConfig {
    /// The sizes of a head's graph attention at (lmax, mmax), field channels in and out.
    pub fn attention(&self, lmax: usize, mmax: usize) -> AttentionConfig {
        AttentionConfig {
            lmax,
            mmax,
            sphere_channels: self.field_channels,
            hidden_channels: self.attn_hidden_channels,
            num_heads: self.num_heads,
            alpha_channels: self.alpha_channels,
            value_channels: self.value_channels,
            output_channels: self.field_channels,
        }
    }
}

/// Everything the rotation query produces for one query point.
#[derive(Debug, Clone)]
pub struct RotationQuery {
    /// The TransBlock output at the query, `[(ROT_LMAX+1)², field_channels]`.
    pub embedding: Vec<f32>,
    /// The gripper-open logit (pre-sigmoid).
    pub open_logit: f32,
    /// The SO(3) coefficients of the lifted signal (165 values).
    pub so3_coeffs: Vec<f64>,
    /// Logits on the head's rotation grid.
    pub rot_logits: Vec<f64>,
}

/// The translation and rotation field heads.
#[derive(Debug, Clone)]
pub struct FieldHeads {
    /// Sizes.
    pub cfg: FieldHeadsConfig,
    rbf: GaussianRbf,
    trans: GraphAttention,
    rot: TransBlock,
    rot_head: RotationHead,
    calc: WignerCalculator,
    /// Wigner matrices of the translation field's degree (its edge frames).
    trans_calc: WignerCalculator,
    grid: Vec<GridRotation>,
    grid_wigners: Vec<Vec<f64>>,
    /// Threads of the translation logits ([`FieldHeads::set_threads`]).
    threads: usize,
}

impl FieldHeads {
    /// Threads of [`FieldHeads::trans_logits`] (the query batches are split among them) and
    /// of [`FieldHeads::rot_query`] (its edge frames and its one destination's edges).
    pub fn set_threads(&mut self, threads: usize) {
        self.threads = threads.max(1);
        self.rot.set_threads(self.threads);
    }

    /// Loads `field_distance_expansion`, `trans_field_layer.0`, `rot_field_layer.0` and
    /// `s2_conv.w` from `s`; the rotation grid is HEALPix level `grid_level`.
    pub fn load(s: &Scope<'_>, cfg: FieldHeadsConfig, grid_level: u32) -> Result<Self> {
        Self::load_with(s, cfg, grid_level, S2Resolution::Reference)
    }

    /// As [`FieldHeads::load`] with the S2 activation grids at `res`.
    pub fn load_with(
        s: &Scope<'_>,
        cfg: FieldHeadsConfig,
        grid_level: u32,
        res: S2Resolution,
    ) -> Result<Self> {
        let c = cfg.field_channels;
        let rbf = GaussianRbf::load(
            &s.sub("field_distance_expansion"),
            f64::from(QUERY_RADIUS) * 0.99,
        )?;
        let attn = |lmax, mmax| cfg.attention(lmax, mmax);
        let mut trans = GraphAttention::load_with_grid(
            &s.sub("trans_field_layer").sub("0"),
            attn(TRANS_LMAX, TRANS_LMAX),
            res.grid(TRANS_LMAX, TRANS_LMAX)?,
        )?;
        trans.prepare_zero_destinations()?;
        let rot = TransBlock::load_with_grids(
            &s.sub("rot_field_layer").sub("0"),
            TransBlockConfig {
                attn: attn(ROT_LMAX, ROT_MMAX),
                ffn_hidden_channels: cfg.ffn_hidden_channels,
                output_channels: c,
                film: None,
            },
            res.grid(ROT_LMAX, ROT_MMAX)?,
            res.grid(ROT_LMAX, ROT_LMAX)?,
        )?;
        if c < 2 {
            return Err(PolicyError::ShapeMismatch {
                name: "field_nn_c (needs S2 channels plus the open channel)".into(),
                expected: vec![2],
                got: vec![c],
            });
        }
        let w = s.sub("s2_conv").f32("w", &[c - 1, 1, 48])?;
        let rot_head = RotationHead::new(&w, c - 1)?;
        let calc = WignerCalculator::new(ROT_LMAX)?;
        let grid = so3_healpix_grid(grid_level);
        let grid_wigners = RotationHead::grid_wigners(&calc, &grid)?;
        Ok(Self {
            cfg,
            rbf,
            trans,
            rot,
            rot_head,
            calc,
            trans_calc: WignerCalculator::new(TRANS_LMAX)?,
            grid,
            grid_wigners,
            threads: 1,
        })
    }

    /// The rotation grid the logits refer to.
    pub fn grid(&self) -> &[GridRotation] {
        &self.grid
    }

    /// The translation query graph: per query the first 200 nodes within the radius
    /// (ascending index), then its 100 nearest nodes; returns (src = node, dst = query).
    pub fn trans_edges(
        node_pos: &[[f32; 3]],
        queries: &[[f32; 3]],
    ) -> Result<(Vec<usize>, Vec<usize>)> {
        check_finite("translation queries", queries)?;
        let near = knn(node_pos, queries, TRANS_KNN)?;
        let (mut src, mut dst) = (Vec::new(), Vec::new());
        for (q, qp) in queries.iter().enumerate() {
            for i in radius_neighbours(node_pos, qp, TRANS_RADIUS_NEIGHBOURS) {
                src.push(i);
                dst.push(q);
            }
            for &i in &near[q] {
                src.push(i);
                dst.push(q);
            }
        }
        Ok((src, dst))
    }

    /// The rotation query graph: every node within the radius (ascending index, at most
    /// 10000) to each query.
    pub fn rot_edges(
        node_pos: &[[f32; 3]],
        queries: &[[f32; 3]],
    ) -> Result<(Vec<usize>, Vec<usize>)> {
        check_finite("rotation queries", queries)?;
        check_finite("node positions", node_pos)?;
        let (mut src, mut dst) = (Vec::new(), Vec::new());
        for (q, qp) in queries.iter().enumerate() {
            for i in radius_neighbours(node_pos, qp, ROT_MAX_NEIGHBOURS) {
                src.push(i);
                dst.push(q);
            }
        }
        Ok((src, dst))
    }

    /// Translation logits at `queries` from node features `node_emb`
    /// `[N, (node_lmax+1)², C_node]` at `node_pos`.
    pub fn trans_logits(
        &self,
        node_emb: &[f32],
        node_pos: &[[f32; 3]],
        queries: &[[f32; 3]],
    ) -> Result<Vec<f32>> {
        let (k_node, c_node) = self.node_layout(node_emb, node_pos.len())?;
        let c = self.cfg.field_channels;
        let k = num_coefficients(TRANS_LMAX);
        // l <= 1 rows, first c channels.
        let mut x = Vec::with_capacity(node_pos.len() * k * c);
        for node in 0..node_pos.len() {
            for i in 0..k {
                let base = (node * k_node + i) * c_node;
                x.extend_from_slice(&node_emb[base..base + c]);
            }
        }
        // Queries in small batches: each batch's edge set (300 edges per query, 1024 radial
        // basis values per edge) stays in cache instead of hundreds of MB per level. With
        // threads, each takes a run of whole batches: the same batches, the same logits.
        crate::parallel::map_chunks(queries, TRANS_QUERY_BATCH, self.threads, |batch| {
            let (src, dst) = Self::trans_edges(node_pos, batch)?;
            let edges = EdgeSet::new(
                &self.trans_calc,
                TRANS_LMAX,
                node_pos,
                batch,
                src,
                dst,
                &self.rbf,
            )?;
            // The field is the l = 0 row's first channel: only the invariant readout.
            let y = self
                .trans
                .invariant_zero_destinations(&x, batch.len(), &edges)?;
            Ok((0..batch.len()).map(|q| y[q * c]).collect())
        })
    }

    /// The rotation query at one point: open logit and rotation logits.
    pub fn rot_query(
        &self,
        node_emb: &[f32],
        node_pos: &[[f32; 3]],
        query: [f32; 3],
    ) -> Result<RotationQuery> {
        let (k_node, c_node) = self.node_layout(node_emb, node_pos.len())?;
        let c = self.cfg.field_channels;
        let k = num_coefficients(ROT_LMAX);
        let k_copy = num_coefficients(self.cfg.node_lmax.min(ROT_LMAX)).min(k_node);
        // Lift to l <= 4, last c channels (the rows above the nodes' degree zero), written
        // once in order.
        let mut x = Vec::with_capacity(node_pos.len() * k * c);
        for node in 0..node_pos.len() {
            for i in 0..k_copy {
                let base = (node * k_node + i) * c_node + (c_node - c);
                x.extend_from_slice(&node_emb[base..base + c]);
            }
            x.resize(x.len() + (k - k_copy) * c, 0.0);
        }
        let queries = [query];
        let (src, dst) = Self::rot_edges(node_pos, &queries)?;
        let edges = EdgeSet::new_threads(
            &self.calc,
            ROT_LMAX,
            (node_pos, &queries),
            src,
            dst,
            &self.rbf,
            self.threads,
        )?;
        let zeros = vec![0.0f32; k * c];
        let embedding = self.rot.forward(&x, &zeros, &edges, None)?;
        let open_logit = embedding[c - 1];
        // S2 features [f, i] = embedding[i, f] for f < c - 1.
        let f_in = c - 1;
        let mut s2 = vec![0.0f32; f_in * k];
        for i in 0..k {
            for f in 0..f_in {
                s2[f * k + i] = embedding[i * c + f];
            }
        }
        let so3_coeffs = self.rot_head.so3_coefficients(&s2)?;
        let rot_logits = RotationHead::logits(&so3_coeffs, &self.grid_wigners);
        Ok(RotationQuery {
            embedding,
            open_logit,
            so3_coeffs,
            rot_logits,
        })
    }

    /// Rotation logits of given SO(3) coefficients on an arbitrary set of rotations.
    pub fn logits_on(&self, so3_coeffs: &[f64], rotations: &[GridRotation]) -> Result<Vec<f64>> {
        let fw = RotationHead::grid_wigners(&self.calc, rotations)?;
        Ok(RotationHead::logits(so3_coeffs, &fw))
    }

    fn node_layout(&self, node_emb: &[f32], n: usize) -> Result<(usize, usize)> {
        let k_node = num_coefficients(self.cfg.node_lmax);
        let c_node = rows_of("node features", node_emb.len(), n.max(1) * k_node)?;
        if c_node < self.cfg.field_channels || n == 0 {
            return Err(PolicyError::ShapeMismatch {
                name: "node features".into(),
                expected: vec![n.max(1), k_node, self.cfg.field_channels],
                got: vec![n, k_node, c_node],
            });
        }
        Ok((k_node, c_node))
    }
}

/// Indices of the points with squared distance < r² to `q`, ascending, at most `max`.
fn radius_neighbours(points: &[[f32; 3]], q: &[f32; 3], max: usize) -> Vec<usize> {
    let r2 = QUERY_RADIUS * QUERY_RADIUS;
    points
        .iter()
        .enumerate()
        .filter(|(_, p)| {
            let d = [p[0] - q[0], p[1] - q[1], p[2] - q[2]];
            d[0] * d[0] + d[1] * d[1] + d[2] * d[2] < r2
        })
        .map(|(i, _)| i)
        .take(max)
        .collect()
}
