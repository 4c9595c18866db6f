//! The whole `EquFieldUnet` on the tape: the TransBlock, the U-net encoder and the field
//! heads, each the twin of its inference version ([`crate::transblock::TransBlock`],
//! [`crate::model::EquFieldUnet::encode`], [`crate::heads::FieldHeads`]), reading the same
//! keys from the same store.

use super::attention::{gaussian_rbf, graph_attention};
use super::ffn::{feed_forward, FeedForwardSizes};
use super::language::instruction_condition;
use super::layers::{linear, rms_norm_sh, so3_linear};
use super::points::{coefficient_max_pool, upsample};
use super::rotation::{open_logit, rotation_logits};
use super::{Tape, Var};
use crate::attention::{edge_vectors, EdgeSet};
use crate::error::{PolicyError, Result};
use crate::grids::S2Grid;
use crate::heads::{FieldHeads, QUERY_RADIUS, ROT_LMAX, ROT_MMAX, TRANS_LMAX};
use crate::model::{
    knn_graph, GripperState, ModelConfig, PointInputs, POOL_NEIGHBOURS, UPSAMPLE_NEIGHBOURS,
};
use crate::points::{farthest_point_sampling, knn, upsample_weights};
use crate::so3::{num_coefficients, WignerCalculator};
use crate::transblock::TransBlockConfig;
use crate::weights::Scope;

/// Edges with their frames, for the tape: the inference [`EdgeSet`] supplies the Wigner
/// matrices; the radial basis of the lengths is taped (its parameters train).
pub fn edges_between(
    calc: &WignerCalculator,
    lmax: usize,
    pos_src: &[[f32; 3]],
    pos_dst: &[[f32; 3]],
    src: Vec<usize>,
    dst: Vec<usize>,
) -> Result<EdgeSet> {
    let vec = edge_vectors(pos_src, pos_dst, &src, &dst)?;
    let e = src.len();
    EdgeSet::from_parts(calc, lmax, src, dst, vec, vec![0.0; e])
}

/// A `TransBlock` on the tape: `h = GA(norm_1_src(x_src), norm_1_dst(x_dst)) + x_dst`,
/// `y = FFN(norm_2(h)) + shortcut(h)`.
#[allow(clippy::too_many_arguments)]
pub fn trans_block(
    t: &mut Tape,
    s: &Scope<'_>,
    cfg: TransBlockConfig,
    (attn_grid, ffn_grid): (&S2Grid, &S2Grid),
    x_src: Var,
    x_dst: Var,
    edges: &EdgeSet,
    edge_attr: Var,
    condition: Option<Var>,
) -> Result<Var> {
    let a = cfg.attn;
    let (lmax, c) = (a.lmax, a.sphere_channels);
    let k = num_coefficients(lmax);
    let nd = crate::layers::rows_of("TransBlock destinations", t.value(x_dst).len(), k * c)?;
    let xs = rms_norm_sh(t, &s.sub("norm_1_src"), x_src, lmax, c)?;
    let xd = rms_norm_sh(t, &s.sub("norm_1_dst"), x_dst, lmax, c)?;
    let msg = graph_attention(
        t,
        &s.sub("ga"),
        a,
        attn_grid,
        xs,
        Some(xd),
        nd,
        edges,
        edge_attr,
    )?;
    let h = t.add(msg, x_dst)?;
    let hn = rms_norm_sh(t, &s.sub("norm_2"), h, lmax, c)?;
    let y = feed_forward(
        t,
        &s.sub("ffn"),
        ffn_grid,
        hn,
        condition,
        FeedForwardSizes {
            lmax,
            cin: c,
            hidden: cfg.ffn_hidden_channels,
            cout: cfg.output_channels,
            film: cfg.film,
        },
    )?;
    let res = if cfg.output_channels != c {
        so3_linear(t, &s.sub("ffn_shortcut"), h)?
    } else {
        h
    };
    t.add(y, res)
}

/// The encoded scene on the tape.
#[derive(Debug, Clone)]
pub struct TapedEncoding {
    /// The FiLM condition `[1, dim]`.
    pub condition: Var,
    /// Output features `[n, (lmax+1)², field_nn_c]` after `norm_1`.
    pub embedding: Var,
    /// Output node positions (the input points, gripper points written in).
    pub coord: Vec<[f32; 3]>,
}

/// One observation as the network reads it (see [`crate::predict::PreparedInput`]).
#[derive(Debug, Clone, Copy)]
pub struct NetworkInput<'a> {
    /// Point positions.
    pub xyz: &'a [[f32; 3]],
    /// Colours in [0, 1].
    pub rgb: &'a [[f32; 3]],
    /// The gripper state.
    pub gripper: &'a GripperState,
    /// Jitter of the gripper points.
    pub gripper_eps: &'a [[f32; 3]],
    /// Instruction tokens `[T, token_dim]`.
    pub instruction: &'a [f32],
}

/// The U-net on the tape, as [`crate::model::EquFieldUnet::encode`] (every discrete choice
/// computed: FPS, kNN, graphs).
pub fn encode(
    t: &mut Tape,
    s: &Scope<'_>,
    cfg: &ModelConfig,
    input: NetworkInput<'_>,
) -> Result<TapedEncoding> {
    cfg.validate()?;
    let inputs = PointInputs::new(cfg, input.xyz, input.rgb, input.gripper, input.gripper_eps)?;
    let condition =
        instruction_condition(t, s, input.instruction, cfg.lang_heads, cfg.lang_dim_head)?;
    let (n, k, c0) = (inputs.pts.len(), inputs.k, inputs.c0);
    let feat = t.constant(inputs.feat.clone(), &[n, 3])?;
    let t0 = linear(t, &s.sub("type0_linear"), feat, c0, 3, true)?;
    // Rows l >= 1: zero, except the gripper axes.
    let mut higher = vec![0.0f32; n * (k - 1) * c0];
    for (node, row, ch, v) in inputs.gripper_axes(input.gripper) {
        higher[(node * (k - 1) + row - 1) * c0 + ch] = v;
    }
    let higher = t.constant(higher, &[n, (k - 1) * c0])?;
    let x = t.concat_cols(t0, c0, higher, (k - 1) * c0)?;
    let mut x = t.reshape(x, &[n, k, c0])?;
    let pts = inputs.pts;

    let calc = WignerCalculator::new(cfg.lmax)?;
    let attn_grid = cfg.s2_resolution.grid(cfg.lmax, cfg.mmax)?;
    let ffn_grid = cfg.s2_resolution.grid(cfg.lmax, cfg.lmax)?;
    let ns = cfg.n_scales();
    let sc = &cfg.sphere_channels;
    // As in inference: a block on an earlier block's nodes with its neighbour count (an up
    // block and its down block) reuses that block's graph and edge frames.
    let mut shared: Vec<(Vec<[f32; 3]>, usize, EdgeSet)> = Vec::new();
    let block = |t: &mut Tape,
                 shared: &mut Vec<(Vec<[f32; 3]>, usize, EdgeSet)>,
                 scope: Scope<'_>,
                 i: usize,
                 (cin, cout): (usize, usize),
                 coord: &[[f32; 3]],
                 x: Var|
     -> Result<Var> {
        let attn = cfg.block_attention(i, cin);
        let k = cfg.max_neighbors[i];
        let pos = shared.iter().position(|(c, kk, _)| *kk == k && c == coord);
        let pos = match pos {
            Some(p) => p,
            None => {
                let (src, dst) = knn_graph(coord, k)?;
                let edges = edges_between(&calc, cfg.lmax, coord, coord, src, dst)?;
                shared.push((coord.to_vec(), k, edges));
                shared.len() - 1
            }
        };
        let edges = &shared[pos].2;
        let attr = gaussian_rbf(
            t,
            &scope.sub("distance_expansion"),
            &edges.dist,
            cfg.max_radius[i] * 0.99,
        )?;
        trans_block(
            t,
            &scope.sub("transblock"),
            TransBlockConfig {
                attn,
                ffn_hidden_channels: cfg.ffn_hidden_channels[i],
                output_channels: cout,
                film: Some(cfg.film_kind),
            },
            (&attn_grid, &ffn_grid),
            x,
            x,
            edges,
            attr,
            Some(condition),
        )
    };
    let pool = |t: &mut Tape,
                coord: &[[f32; 3]],
                x: Var,
                ratio: f64,
                c: usize|
     -> Result<(Vec<[f32; 3]>, Var)> {
        if ratio >= 1.0 {
            return Ok((coord.to_vec(), x));
        }
        let m = ((ratio * coord.len() as f64).ceil() as usize).max(1);
        let fps = farthest_point_sampling(coord, m)?;
        let centres: Vec<[f32; 3]> = fps.iter().map(|&i| coord[i]).collect();
        let nb = knn(coord, &centres, POOL_NEIGHBOURS)?;
        let y = coefficient_max_pool(t, x, coord.len(), cfg.lmax, c, &nb)?;
        Ok((centres, y))
    };

    let mut coord = pts.clone();
    let mut skips: Vec<(Vec<[f32; 3]>, Var)> = Vec::new();
    for i in 0..ns {
        let (c2, x2) = pool(t, &coord, x, cfg.pool_ratio[i], sc[i])?;
        let scope = s.sub("down_blocks").sub(&i.to_string()).sub("block");
        x = block(t, &mut shared, scope, i, (sc[i], sc[i + 1]), &c2, x2)?;
        coord = c2;
        skips.push((coord.clone(), x));
    }
    skips.pop();
    let (c2, x2) = pool(t, &coord, x, cfg.pool_ratio[ns - 1], sc[ns])?;
    x = block(
        t,
        &mut shared,
        s.sub("middle_block").sub("block"),
        ns - 1,
        (sc[ns], sc[ns]),
        &c2,
        x2,
    )?;
    coord = c2;
    for (j, i) in (0..ns).rev().enumerate() {
        let cout = if i == 0 { cfg.field_nn_c } else { sc[i] };
        let scope = s.sub("up_blocks").sub(&j.to_string()).sub("block");
        let skip = if cfg.pool_ratio[i] < 1.0 {
            skips.pop()
        } else {
            None
        };
        let (c2, x2) = match &skip {
            Some((up, _)) => {
                let nb = knn(&coord, up, UPSAMPLE_NEIGHBOURS)?;
                let w = upsample_weights(up, &coord, &nb, cfg.upsample_distance)?;
                let y = upsample(t, x, coord.len(), k * sc[i + 1], &nb, &w)?;
                (up.clone(), y)
            }
            None => (coord.clone(), x),
        };
        let mut y = block(t, &mut shared, scope, i, (sc[i + 1], cout), &c2, x2)?;
        if let Some((_, sx)) = skip {
            y = t.add(y, sx)?;
        }
        coord = c2;
        x = y;
    }
    let embedding = rms_norm_sh(t, &s.sub("norm_1"), x, cfg.lmax, cfg.field_nn_c)?;
    Ok(TapedEncoding {
        condition,
        embedding,
        coord,
    })
}

/// Translation logits at `queries` on the tape (`[Q]`), as
/// [`crate::heads::FieldHeads::trans_logits`] (or the plain heads' when `cfg.heads` says so).
pub fn trans_logits(
    t: &mut Tape,
    s: &Scope<'_>,
    cfg: &ModelConfig,
    enc: &TapedEncoding,
    queries: &[[f32; 3]],
) -> Result<Var> {
    if cfg.heads == crate::model::HeadKind::Plain {
        return super::plain_heads::trans_logits(t, s, cfg, enc, queries);
    }
    let c = cfg.field_nn_c;
    let n = enc.coord.len();
    let k_node = num_coefficients(cfg.lmax);
    let k = num_coefficients(TRANS_LMAX);
    // Rows l <= 1 of every node.
    let rows: Vec<usize> = (0..n)
        .flat_map(|node| (0..k).map(move |i| node * k_node + i))
        .collect();
    let x = t.gather_rows(enc.embedding, c, &rows)?;
    let x = t.reshape(x, &[n, k, c])?;
    let (src, dst) = FieldHeads::trans_edges(&enc.coord, queries)?;
    let calc = WignerCalculator::new(TRANS_LMAX)?;
    let edges = edges_between(&calc, TRANS_LMAX, &enc.coord, queries, src, dst)?;
    let attr = gaussian_rbf(
        t,
        &s.sub("field_distance_expansion"),
        &edges.dist,
        f64::from(QUERY_RADIUS) * 0.99,
    )?;
    let grid = cfg.s2_resolution.grid(TRANS_LMAX, TRANS_LMAX)?;
    let y = graph_attention(
        t,
        &s.sub("trans_field_layer").sub("0"),
        cfg.heads_config().attention(TRANS_LMAX, TRANS_LMAX),
        &grid,
        x,
        None,
        queries.len(),
        &edges,
        attr,
    )?;
    // Row 0, channel 0 of each query.
    let first: Vec<usize> = (0..queries.len()).map(|q| q * k * c).collect();
    t.gather_rows(y, 1, &first)
}

/// The rotation query on the tape: (open logit `[1]`, rotation logits `[R]` on the
/// rotations whose flattened Wigner matrices are `flat_wigners`), as
/// [`crate::heads::FieldHeads::rot_query`] (or the plain heads' when `cfg.heads` says so).
pub fn rot_query(
    t: &mut Tape,
    s: &Scope<'_>,
    cfg: &ModelConfig,
    enc: &TapedEncoding,
    query: [f32; 3],
    flat_wigners: &[Vec<f64>],
) -> Result<(Var, Var)> {
    if cfg.heads == crate::model::HeadKind::Plain {
        return super::plain_heads::rot_query(t, s, cfg, enc, query, flat_wigners);
    }
    let c = cfg.field_nn_c;
    let n = enc.coord.len();
    let k_node = num_coefficients(cfg.lmax);
    let k = num_coefficients(ROT_LMAX);
    let k_copy = k_node.min(k);
    if k_node > k {
        return Err(PolicyError::UnsupportedDegree {
            lmax: cfg.lmax,
            mmax: cfg.mmax,
            max_supported: ROT_LMAX,
        });
    }
    // Lift to l <= 4 (the last c channels are all of them: c_node = field_nn_c).
    let copied = t.reshape(enc.embedding, &[n, k_copy * c])?;
    let zeros = t.constant(vec![0.0; n * (k - k_copy) * c], &[n, (k - k_copy) * c])?;
    let x = t.concat_cols(copied, k_copy * c, zeros, (k - k_copy) * c)?;
    let x = t.reshape(x, &[n, k, c])?;
    let queries = [query];
    let (src, dst) = FieldHeads::rot_edges(&enc.coord, &queries)?;
    let calc = WignerCalculator::new(ROT_LMAX)?;
    let edges = edges_between(&calc, ROT_LMAX, &enc.coord, &queries, src, dst)?;
    let attr = gaussian_rbf(
        t,
        &s.sub("field_distance_expansion"),
        &edges.dist,
        f64::from(QUERY_RADIUS) * 0.99,
    )?;
    let x_dst = t.constant(vec![0.0; k * c], &[1, k, c])?;
    let emb = trans_block(
        t,
        &s.sub("rot_field_layer").sub("0"),
        TransBlockConfig {
            attn: cfg.heads_config().attention(ROT_LMAX, ROT_MMAX),
            ffn_hidden_channels: cfg.ffn_hidden_channels[1],
            output_channels: c,
            film: None,
        },
        (
            &cfg.s2_resolution.grid(ROT_LMAX, ROT_MMAX)?,
            &cfg.s2_resolution.grid(ROT_LMAX, ROT_LMAX)?,
        ),
        x,
        x_dst,
        &edges,
        attr,
        None,
    )?;
    let open = open_logit(t, emb)?;
    let rot = rotation_logits(t, s, emb, flat_wigners)?;
    Ok((open, rot))
}
