//! The paper's ablation of the field heads: a plain (non-equivariant) transformer layer in
//! place of the equivariant graph attention, on the same U-net features and the same query
//! graphs ([`FieldHeads::trans_edges`], [`FieldHeads::rot_edges`]).
//!
//! One plain layer per head (separate weights, keys under `plain_trans_head.` and
//! `plain_rot_head.`), with c = `field_nn_c`, H = `num_heads`, d = `attn_alpha_channels[1]`
//! per head and F = `ffn_hidden_channels[1]`, pre-LayerNorm:
//! - edge tokens `e = concat(node l = 0 features [c], p_node − q [3])` (the raw relative
//!   position: it turns with the scene, which is what makes the layer non-equivariant),
//!   normalised by `norm_kv` (width c + 3);
//! - the query token `q0 = query + query_pos(q)` (a learned `[c]` vector plus a bias-free
//!   Linear 3 → c of the raw query position), normalised by `norm_q`;
//! - multi-head scaled dot-product attention of the query over its own edges (`to_q`,
//!   `to_k`, `to_v`: c or c + 3 → H·d, no bias; scores `q·k/√d`, softmax over the edges of
//!   that query), `to_out` (H·d → c) added to `q0`;
//! - a residual MLP `h + ff2(GELU(ff1(norm_ff(h))))` (c → F → c);
//! - `readout(norm_out(y))`: 1 translation logit, or for the rotation head the open logit
//!   (output 0) and the 165 SO(3) coefficients (outputs 1..166) read out on the rotation grid
//!   as the equivariant head's ([`RotationHead::logits`]).
//!
//! The ablation drops the paper's success rate from 52.8 % to 12.3 %; it exists to reproduce
//! that, not to be deployed.

use crate::attention::grouped_softmax;
use crate::error::{PolicyError, Result};
use crate::grids::{so3_healpix_grid, GridRotation};
use crate::heads::{FieldHeads, RotationQuery};
use crate::layers::{gelu, rows_of, LayerNorm, Linear};
use crate::model::ModelConfig;
use crate::rotation_head::{RotationHead, ROT_LMAX, SO3_COEFFS};
use crate::so3::{num_coefficients, WignerCalculator};
use crate::weights::Scope;

/// Key prefix of the plain translation head.
pub const PLAIN_TRANS_SCOPE: &str = "plain_trans_head";
/// Key prefix of the plain rotation head.
pub const PLAIN_ROT_SCOPE: &str = "plain_rot_head";
/// Translation queries evaluated together (bounds the edge tokens held at once).
pub const PLAIN_QUERY_BATCH: usize = 64;
/// Outputs of the rotation head's readout: the open logit, then the SO(3) coefficients.
pub const PLAIN_ROT_OUTPUTS: usize = 1 + SO3_COEFFS;

/// Widths of the plain heads.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct PlainHeadsConfig {
    /// Token width c (`field_nn_c`, the U-net's output channels).
    pub channels: usize,
    /// Attention heads H (`num_heads`).
    pub num_heads: usize,
    /// Query/key/value width per head d (`attn_alpha_channels[1]`).
    pub head_dim: usize,
    /// Hidden width F of the MLP (`ffn_hidden_channels[1]`).
    pub ffn_hidden: usize,
    /// Degree of the U-net features the heads read (only their l = 0 row is used).
    pub node_lmax: usize,
}

impl PlainHeadsConfig {
    /// The widths of a model configuration (as the equivariant heads take theirs).
    pub fn of(cfg: &ModelConfig) -> Result<Self> {
        let at1 = |name: &str, v: &[usize]| {
            v.get(1).copied().ok_or_else(|| PolicyError::ShapeMismatch {
                name: format!("model config {name} (the heads use scale 1)"),
                expected: vec![2],
                got: vec![v.len()],
            })
        };
        let c = Self {
            channels: cfg.field_nn_c,
            num_heads: cfg.num_heads,
            head_dim: at1("attn_alpha_channels", &cfg.attn_alpha_channels)?,
            ffn_hidden: at1("ffn_hidden_channels", &cfg.ffn_hidden_channels)?,
            node_lmax: cfg.lmax,
        };
        c.validate()?;
        Ok(c)
    }

    /// Attention width H·d.
    pub fn inner(&self) -> usize {
        self.num_heads * self.head_dim
    }

    /// Checks that every width is positive.
    pub fn validate(&self) -> Result<()> {
        let w = [
            self.channels,
            self.num_heads,
            self.head_dim,
            self.ffn_hidden,
        ];
        if w.contains(&0) {
            return Err(PolicyError::ShapeMismatch {
                name: "plain heads widths (channels, heads, head_dim, ffn_hidden)".into(),
                expected: vec![1, 1, 1, 1],
                got: w.to_vec(),
            });
        }
        Ok(())
    }
}

/// One plain transformer layer from edge tokens onto query tokens (see the module doc).
#[derive(Debug, Clone)]
struct PlainLayer {
    cfg: PlainHeadsConfig,
    query: Vec<f32>,
    query_pos: Linear,
    norm_q: LayerNorm,
    norm_kv: LayerNorm,
    to_q: Linear,
    to_k: Linear,
    to_v: Linear,
    to_out: Linear,
    norm_ff: LayerNorm,
    ff1: Linear,
    ff2: Linear,
    norm_out: LayerNorm,
    readout: Linear,
}

impl PlainLayer {
    fn load(s: &Scope<'_>, cfg: PlainHeadsConfig, n_out: usize) -> Result<Self> {
        cfg.validate()?;
        let (c, inner, f) = (cfg.channels, cfg.inner(), cfg.ffn_hidden);
        Ok(Self {
            cfg,
            query: s.f32("query", &[c])?,
            query_pos: Linear::load_sized(&s.sub("query_pos"), c, 3, false)?,
            norm_q: LayerNorm::load(&s.sub("norm_q"), c)?,
            norm_kv: LayerNorm::load(&s.sub("norm_kv"), c + 3)?,
            to_q: Linear::load_sized(&s.sub("to_q"), inner, c, false)?,
            to_k: Linear::load_sized(&s.sub("to_k"), inner, c + 3, false)?,
            to_v: Linear::load_sized(&s.sub("to_v"), inner, c + 3, false)?,
            to_out: Linear::load_sized(&s.sub("to_out"), c, inner, true)?,
            norm_ff: LayerNorm::load(&s.sub("norm_ff"), c)?,
            ff1: Linear::load_sized(&s.sub("ff1"), f, c, true)?,
            ff2: Linear::load_sized(&s.sub("ff2"), c, f, true)?,
            norm_out: LayerNorm::load(&s.sub("norm_out"), c)?,
            readout: Linear::load_sized(&s.sub("readout"), n_out, c, true)?,
        })
    }

    /// The layer on `queries` over edges (src = node, dst = query): (output tokens `[Q, c]`
    /// before `norm_out`, readout `[Q, n_out]`). `node_l0` is `[N, c]`.
    fn forward(
        &self,
        node_l0: &[f32],
        node_pos: &[[f32; 3]],
        queries: &[[f32; 3]],
        src: &[usize],
        dst: &[usize],
    ) -> Result<(Vec<f32>, Vec<f32>)> {
        let (c, h, d) = (self.cfg.channels, self.cfg.num_heads, self.cfg.head_dim);
        let inner = h * d;
        let nq = queries.len();
        // Edge tokens: node features and the raw offset of the node from its query.
        let mut e = Vec::with_capacity(src.len() * (c + 3));
        for (&s, &q) in src.iter().zip(dst) {
            let (Some(p), Some(qp)) = (node_pos.get(s), queries.get(q)) else {
                return Err(PolicyError::IndexOutOfRange {
                    name: "plain head edge".into(),
                    value: s.max(q) as i64,
                    len: node_pos.len().min(nq),
                });
            };
            let feat = node_l0
                .get(s * c..(s + 1) * c)
                .ok_or(PolicyError::IndexOutOfRange {
                    name: "plain head edge source".into(),
                    value: s as i64,
                    len: node_l0.len() / c,
                })?;
            e.extend_from_slice(feat);
            e.extend([p[0] - qp[0], p[1] - qp[1], p[2] - qp[2]]);
        }
        self.norm_kv.apply(&mut e);
        let flat_q: Vec<f32> = queries.iter().flatten().copied().collect();
        let mut q0 = self.query_pos.forward(&flat_q)?;
        for row in q0.chunks_exact_mut(c) {
            for (v, b) in row.iter_mut().zip(&self.query) {
                *v += b;
            }
        }
        let mut qn = q0.clone();
        self.norm_q.apply(&mut qn);
        let qm = self.to_q.forward(&qn)?;
        let (k, v) = if e.is_empty() {
            (Vec::new(), Vec::new())
        } else {
            (self.to_k.forward(&e)?, self.to_v.forward(&e)?)
        };
        let scale = 1.0 / (d as f32).sqrt();
        let mut score = vec![0.0f32; src.len() * h];
        for (i, &q) in dst.iter().enumerate() {
            for hd in 0..h {
                let a = &qm[q * inner + hd * d..q * inner + (hd + 1) * d];
                let b = &k[i * inner + hd * d..i * inner + (hd + 1) * d];
                score[i * h + hd] = a.iter().zip(b).map(|(x, y)| x * y).sum::<f32>() * scale;
            }
        }
        let alpha = grouped_softmax(&score, dst, nq, h);
        let mut att = vec![0.0f32; nq * inner];
        for (i, &q) in dst.iter().enumerate() {
            for hd in 0..h {
                let a = alpha[i * h + hd];
                let o = &mut att[q * inner + hd * d..q * inner + (hd + 1) * d];
                for (x, y) in o
                    .iter_mut()
                    .zip(&v[i * inner + hd * d..i * inner + (hd + 1) * d])
                {
                    *x += a * y;
                }
            }
        }
        let mut y = self.to_out.forward(&att)?;
        for (a, b) in y.iter_mut().zip(&q0) {
            *a += b;
        }
        let mut hn = y.clone();
        self.norm_ff.apply(&mut hn);
        let mut hidden = self.ff1.forward(&hn)?;
        hidden.iter_mut().for_each(|x| *x = gelu(*x));
        let ff = self.ff2.forward(&hidden)?;
        for (a, b) in y.iter_mut().zip(&ff) {
            *a += b;
        }
        let mut yn = y.clone();
        self.norm_out.apply(&mut yn);
        let out = self.readout.forward(&yn)?;
        Ok((y, out))
    }
}

/// The plain translation and rotation heads (the ablation of [`FieldHeads`]).
#[derive(Debug, Clone)]
pub struct PlainHeads {
    /// Widths.
    pub cfg: PlainHeadsConfig,
    trans: PlainLayer,
    rot: PlainLayer,
    calc: WignerCalculator,
    grid: Vec<GridRotation>,
    grid_wigners: Vec<Vec<f64>>,
    /// Threads of the translation logits ([`PlainHeads::set_threads`]).
    threads: usize,
}

impl PlainHeads {
    /// Threads of [`PlainHeads::trans_logits`] (whole query batches each).
    pub fn set_threads(&mut self, threads: usize) {
        self.threads = threads.max(1);
    }

    /// Loads `plain_trans_head.*` and `plain_rot_head.*` from `s`; the rotation grid is
    /// HEALPix level `grid_level`.
    pub fn load(s: &Scope<'_>, cfg: PlainHeadsConfig, grid_level: u32) -> Result<Self> {
        let trans = PlainLayer::load(&s.sub(PLAIN_TRANS_SCOPE), cfg, 1)?;
        let rot = PlainLayer::load(&s.sub(PLAIN_ROT_SCOPE), cfg, PLAIN_ROT_OUTPUTS)?;
        let calc = WignerCalculator::new(ROT_LMAX)?;
        let grid = so3_healpix_grid(grid_level);
        let grid_wigners = RotationHead::grid_wigners(&calc, &grid)?;
        Ok(Self {
            cfg,
            trans,
            rot,
            calc,
            grid,
            grid_wigners,
            threads: 1,
        })
    }

    /// The rotation grid the logits refer to.
    pub fn grid(&self) -> &[GridRotation] {
        &self.grid
    }

    /// Translation logits at `queries` from node features `node_emb`
    /// `[N, (node_lmax+1)², C_node]` at `node_pos` (their l = 0 row, first c channels).
    pub fn trans_logits(
        &self,
        node_emb: &[f32],
        node_pos: &[[f32; 3]],
        queries: &[[f32; 3]],
    ) -> Result<Vec<f32>> {
        let x = self.node_scalars(node_emb, node_pos.len())?;
        crate::parallel::map_chunks(queries, PLAIN_QUERY_BATCH, self.threads, |batch| {
            let (src, dst) = FieldHeads::trans_edges(node_pos, batch)?;
            let (_, out) = self.trans.forward(&x, node_pos, batch, &src, &dst)?;
            Ok(out)
        })
    }

    /// The rotation query at one point. `embedding` is the plain layer's output token at the
    /// query (`[c]`, before `norm_out`; there are no per-degree rows here).
    pub fn rot_query(
        &self,
        node_emb: &[f32],
        node_pos: &[[f32; 3]],
        query: [f32; 3],
    ) -> Result<RotationQuery> {
        let x = self.node_scalars(node_emb, node_pos.len())?;
        let queries = [query];
        let (src, dst) = FieldHeads::rot_edges(node_pos, &queries)?;
        let (embedding, out) = self.rot.forward(&x, node_pos, &queries, &src, &dst)?;
        let so3_coeffs: Vec<f64> = out[1..].iter().map(|v| f64::from(*v)).collect();
        let rot_logits = RotationHead::logits(&so3_coeffs, &self.grid_wigners);
        Ok(RotationQuery {
            embedding,
            open_logit: out[0],
            so3_coeffs,
            rot_logits,
        })
    }

    /// Rotation logits of given SO(3) coefficients on an arbitrary set of rotations.
    pub fn logits_on(&self, so3_coeffs: &[f64], rotations: &[GridRotation]) -> Result<Vec<f64>> {
        let fw = RotationHead::grid_wigners(&self.calc, rotations)?;
        Ok(RotationHead::logits(so3_coeffs, &fw))
    }

    /// The l = 0 row (first c channels) of every node: `[N, c]`.
    fn node_scalars(&self, node_emb: &[f32], n: usize) -> Result<Vec<f32>> {
        let c = self.cfg.channels;
        let k_node = num_coefficients(self.cfg.node_lmax);
        let c_node = rows_of("node features", node_emb.len(), n.max(1) * k_node)?;
        if c_node < c || n == 0 {
            return Err(PolicyError::ShapeMismatch {
                name: "node features".into(),
                expected: vec![n.max(1), k_node, c],
                got: vec![n, k_node, c_node],
            });
        }
        Ok((0..n)
            .flat_map(|node| {
                let base = node * k_node * c_node;
                node_emb[base..base + c].iter().copied()
            })
            .collect())
    }
}
