//! The plain (non-equivariant) transformer heads on the tape, twins of
//! [`crate::plain_heads::PlainHeads`] (same keys, same layer order: pre-LayerNorm attention
//! of the query token over its edges, a GELU MLP, a readout).

use super::layers::{layer_norm, linear};
use super::model::TapedEncoding;
use super::{Tape, Var};
use crate::error::{PolicyError, Result};
use crate::heads::FieldHeads;
use crate::model::ModelConfig;
use crate::plain_heads::{PlainHeadsConfig, PLAIN_ROT_OUTPUTS, PLAIN_ROT_SCOPE, PLAIN_TRANS_SCOPE};
use crate::rotation_head::SO3_COEFFS;
use crate::so3::num_coefficients;
use crate::weights::Scope;

/// Node features as the plain heads read them.
#[derive(Debug, Clone, Copy)]
pub struct PlainNodes<'a> {
    /// U-net output features `[N, (node_lmax+1)², c]` (only the l = 0 row is read).
    pub embedding: Var,
    /// Node positions.
    pub coord: &'a [[f32; 3]],
}

impl<'a> From<&'a TapedEncoding> for PlainNodes<'a> {
    fn from(enc: &'a TapedEncoding) -> Self {
        Self {
            embedding: enc.embedding,
            coord: &enc.coord,
        }
    }
}

/// The l = 0 rows of the node features: `[N, c]`.
fn node_scalars(t: &mut Tape, sz: PlainHeadsConfig, nodes: PlainNodes<'_>) -> Result<Var> {
    let (c, n) = (sz.channels, nodes.coord.len());
    let k_node = num_coefficients(sz.node_lmax);
    if n == 0 || t.value(nodes.embedding).len() != n * k_node * c {
        return Err(PolicyError::ShapeMismatch {
            name: "plain head node features".into(),
            expected: vec![n.max(1), k_node, c],
            got: t.shape(nodes.embedding).to_vec(),
        });
    }
    let rows: Vec<usize> = (0..n).map(|node| node * k_node).collect();
    t.gather_rows(nodes.embedding, c, &rows)
}

/// The plain layer of `s` on `queries` over edges (src = node, dst = query): (output tokens
/// `[Q, c]` before `norm_out`, readout `[Q, n_out]`), as the inference layer.
fn plain_layer(
    t: &mut Tape,
    s: &Scope<'_>,
    sz: PlainHeadsConfig,
    (x, node_pos): (Var, &[[f32; 3]]),
    queries: &[[f32; 3]],
    (src, dst): (&[usize], &[usize]),
    n_out: usize,
) -> Result<(Var, Var)> {
    sz.validate()?;
    let (c, h, d) = (sz.channels, sz.num_heads, sz.head_dim);
    let inner = sz.inner();
    let nq = queries.len();
    let mut rel = Vec::with_capacity(src.len() * 3);
    for (&sn, &q) in src.iter().zip(dst) {
        let (Some(p), Some(qp)) = (node_pos.get(sn), queries.get(q)) else {
            return Err(PolicyError::IndexOutOfRange {
                name: "plain head edge".into(),
                value: sn.max(q) as i64,
                len: node_pos.len().min(nq),
            });
        };
        rel.extend([p[0] - qp[0], p[1] - qp[1], p[2] - qp[2]]);
    }
    let ne = src.len();
    let feat = t.gather_rows(x, c, src)?;
    let rel = t.constant(rel, &[ne, 3])?;
    let e = t.concat_cols(feat, c, rel, 3)?;
    let en = layer_norm(t, &s.sub("norm_kv"), e, c + 3)?;
    let qpos = t.constant(queries.iter().flatten().copied().collect(), &[nq, 3])?;
    let qpos = linear(t, &s.sub("query_pos"), qpos, c, 3, false)?;
    let query = t.param(s, "query", &[c])?;
    let tiled = t.gather_rows(query, c, &vec![0; nq])?;
    let q0 = t.add(qpos, tiled)?;
    let qn = layer_norm(t, &s.sub("norm_q"), q0, c)?;
    let qm = linear(t, &s.sub("to_q"), qn, inner, c, false)?;
    let k = linear(t, &s.sub("to_k"), en, inner, c + 3, false)?;
    let v = linear(t, &s.sub("to_v"), en, inner, c + 3, false)?;
    // Scores q·k/√d per head: the per-edge product summed within each head by a constant
    // block matrix (the scale folded in), so the existing ops carry the gradient.
    let qe = t.gather_rows(qm, inner, dst)?;
    let prod = t.mul(qe, k)?;
    let scale = 1.0 / (d as f32).sqrt();
    let mut sum_w = vec![0.0f32; h * inner];
    let mut expand_w = vec![0.0f32; inner * h];
    for hd in 0..h {
        for j in hd * d..(hd + 1) * d {
            sum_w[hd * inner + j] = scale;
            expand_w[j * h + hd] = 1.0;
        }
    }
    let sum_w = t.constant(sum_w, &[h, inner])?;
    let score = t.linear(prod, sum_w, None)?;
    let alpha = super::attention::grouped_softmax(t, score, dst, nq, h)?;
    let expand_w = t.constant(expand_w, &[inner, h])?;
    let alpha_wide = t.linear(alpha, expand_w, None)?;
    let weighted = t.mul(alpha_wide, v)?;
    let att = t.scatter_add_rows(weighted, inner, dst, nq)?;
    let out = linear(t, &s.sub("to_out"), att, c, inner, true)?;
    let y = t.add(out, q0)?;
    let hn = layer_norm(t, &s.sub("norm_ff"), y, c)?;
    let hidden = linear(t, &s.sub("ff1"), hn, sz.ffn_hidden, c, true)?;
    let hidden = t.act(hidden, super::Act::Gelu);
    let ff = linear(t, &s.sub("ff2"), hidden, c, sz.ffn_hidden, true)?;
    let y = t.add(ff, y)?;
    let yn = layer_norm(t, &s.sub("norm_out"), y, c)?;
    let readout = linear(t, &s.sub("readout"), yn, n_out, c, true)?;
    Ok((y, readout))
}

/// Translation logits `[Q]` of the plain head from node features `nodes`, as
/// [`crate::plain_heads::PlainHeads::trans_logits`]; `s` is the model's root scope.
pub fn trans_logits_from(
    t: &mut Tape,
    s: &Scope<'_>,
    sz: PlainHeadsConfig,
    nodes: PlainNodes<'_>,
    queries: &[[f32; 3]],
) -> Result<Var> {
    let x = node_scalars(t, sz, nodes)?;
    let (src, dst) = FieldHeads::trans_edges(nodes.coord, queries)?;
    let (_, out) = plain_layer(
        t,
        &s.sub(PLAIN_TRANS_SCOPE),
        sz,
        (x, nodes.coord),
        queries,
        (&src, &dst),
        1,
    )?;
    t.reshape(out, &[queries.len()])
}

/// The plain rotation query from node features `nodes`: (open logit `[1]`, rotation logits
/// `[R]` on the rotations whose flattened Wigner matrices are `flat_wigners`), as
/// [`crate::plain_heads::PlainHeads::rot_query`].
pub fn rot_query_from(
    t: &mut Tape,
    s: &Scope<'_>,
    sz: PlainHeadsConfig,
    nodes: PlainNodes<'_>,
    query: [f32; 3],
    flat_wigners: &[Vec<f64>],
) -> Result<(Var, Var)> {
    if let Some(bad) = flat_wigners.iter().find(|fw| fw.len() != SO3_COEFFS) {
        return Err(PolicyError::ShapeMismatch {
            name: "flat Wigner matrices".into(),
            expected: vec![flat_wigners.len(), SO3_COEFFS],
            got: vec![bad.len()],
        });
    }
    let x = node_scalars(t, sz, nodes)?;
    let queries = [query];
    let (src, dst) = FieldHeads::rot_edges(nodes.coord, &queries)?;
    let (_, out) = plain_layer(
        t,
        &s.sub(PLAIN_ROT_SCOPE),
        sz,
        (x, nodes.coord),
        &queries,
        (&src, &dst),
        PLAIN_ROT_OUTPUTS,
    )?;
    let open = t.slice_cols(out, PLAIN_ROT_OUTPUTS, 0..1)?;
    let open = t.reshape(open, &[1])?;
    let coeffs = t.slice_cols(out, PLAIN_ROT_OUTPUTS, 1..PLAIN_ROT_OUTPUTS)?;
    // Logits = Σ coefficient · flattened Wigner-D of each rotation: a constant product, as
    // `RotationHead::logits` (the Wigner entries rounded to f32).
    let g = flat_wigners.len();
    let fw: Vec<f32> = flat_wigners.iter().flatten().map(|v| *v as f32).collect();
    let fw = t.constant(fw, &[g, SO3_COEFFS])?;
    let logits = t.linear(coeffs, fw, None)?;
    let logits = t.reshape(logits, &[g])?;
    Ok((open, logits))
}

/// Translation logits `[Q]` of the plain head on an encoded scene (`cfg.heads == Plain`).
pub fn trans_logits(
    t: &mut Tape,
    s: &Scope<'_>,
    cfg: &ModelConfig,
    enc: &TapedEncoding,
    queries: &[[f32; 3]],
) -> Result<Var> {
    trans_logits_from(t, s, PlainHeadsConfig::of(cfg)?, enc.into(), queries)
}

/// The plain rotation query on an encoded scene (`cfg.heads == Plain`).
pub fn rot_query(
    t: &mut Tape,
    s: &Scope<'_>,
    cfg: &ModelConfig,
    enc: &TapedEncoding,
    query: [f32; 3],
    flat_wigners: &[Vec<f64>],
) -> Result<(Var, Var)> {
    rot_query_from(
        t,
        s,
        PlainHeadsConfig::of(cfg)?,
        enc.into(),
        query,
        flat_wigners,
    )
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::autodiff::check::{finite_difference_check, FdOptions};
    use crate::autodiff::layers::tests::{assert_passes, random};
    use crate::grids::so3_healpix_grid;
    use crate::init::{random_weights, ExtraSizes};
    use crate::model::HeadKind;
    use crate::plain_heads::PlainHeads;
    use crate::rotation_head::RotationHead;
    use crate::so3::WignerCalculator;
    use crate::weights::Weights;

    /// A small model with plain heads: c = 8, 2 heads of 4, MLP 12, l_max 3.
    fn plain_weights() -> (ModelConfig, Weights) {
        let mut cfg = ModelConfig::reference();
        cfg.heads = HeadKind::Plain;
        cfg.sphere_channels = vec![8, 8, 12, 16, 16];
        cfg.attn_hidden_channels = vec![8; 4];
        cfg.num_heads = 2;
        cfg.attn_alpha_channels = vec![4; 4];
        cfg.attn_value_channels = vec![2; 4];
        cfg.ffn_hidden_channels = vec![12; 4];
        cfg.field_nn_c = 8;
        cfg.lang_heads = 2;
        cfg.lang_dim_head = 4;
        let mut extra = ExtraSizes::reference();
        extra.edge_channels = vec![8; 4];
        extra.num_distance_basis = 16;
        extra.film_dim = 16;
        extra.token_dim = 12;
        extra.lang_depth = 1;
        extra.lang_mlp = 16;
        let w = random_weights(&cfg, &extra, 21);
        (cfg, w)
    }

    /// `n` node positions spread over a 3 m cube (some nodes outside each query's radius).
    fn positions(n: usize, seed: u64) -> Vec<[f32; 3]> {
        random(3 * n, seed)
            .chunks_exact(3)
            .map(|p| [p[0], p[1], 0.5 * p[2]])
            .collect()
    }

    #[test]
    fn random_weights_hold_the_plain_heads_and_not_the_equivariant_ones() {
        let (_, w) = plain_weights();
        for key in [
            "plain_trans_head.query",
            "plain_trans_head.to_q.weight",
            "plain_trans_head.readout.weight",
            "plain_rot_head.norm_kv.weight",
            "plain_rot_head.readout.bias",
        ] {
            assert!(w.contains(key), "{key}");
        }
        assert_eq!(
            w.shape_of("plain_rot_head.readout.weight").unwrap(),
            [PLAIN_ROT_OUTPUTS, 8]
        );
        for k in w.keys() {
            assert!(
                !(k.starts_with("trans_field_layer")
                    || k.starts_with("rot_field_layer")
                    || k.starts_with("s2_conv")
                    || k.starts_with("field_distance_expansion")),
                "{k}"
            );
        }
    }

    #[test]
    fn taped_plain_heads_match_inference() {
        let (cfg, w) = plain_weights();
        let sz = PlainHeadsConfig::of(&cfg).unwrap();
        let s = w.scope("");
        let heads = PlainHeads::load(&s, sz, 0).unwrap();
        let k_node = num_coefficients(cfg.lmax);
        let n = 40;
        let pos = positions(n, 3);
        let emb = random(n * k_node * 8, 4);
        let queries = [[0.1f32, 0.2, 0.0], [-0.5, 0.3, 0.2], [0.9, -0.8, -0.1]];
        let want_t = heads.trans_logits(&emb, &pos, &queries).unwrap();
        let want_r = heads.rot_query(&emb, &pos, queries[1]).unwrap();
        assert_eq!(want_r.so3_coeffs.len(), SO3_COEFFS);
        assert_eq!(want_r.embedding.len(), 8);
        assert_eq!(want_r.rot_logits.len(), heads.grid().len());

        let mut t = Tape::new();
        let ev = t.constant(emb, &[n, k_node, 8]).unwrap();
        let nodes = PlainNodes {
            embedding: ev,
            coord: &pos,
        };
        let tl = trans_logits_from(&mut t, &s, sz, nodes, &queries).unwrap();
        let calc = WignerCalculator::new(crate::rotation_head::ROT_LMAX).unwrap();
        let fw = RotationHead::grid_wigners(&calc, &so3_healpix_grid(0)).unwrap();
        let (open, rot) = rot_query_from(&mut t, &s, sz, nodes, queries[1], &fw).unwrap();
        let close = |a: &[f32], b: &[f32], what: &str| {
            assert_eq!(a.len(), b.len(), "{what}");
            let scale = b.iter().fold(1.0f32, |m, v| m.max(v.abs()));
            for (i, (x, y)) in a.iter().zip(b).enumerate() {
                assert!((x - y).abs() <= 1e-5 * scale, "{what}[{i}]: {x} vs {y}");
            }
        };
        close(t.value(tl), &want_t, "translation logits");
        close(t.value(open), &[want_r.open_logit], "open logit");
        let want: Vec<f32> = RotationHead::logits(&want_r.so3_coeffs, &fw)
            .iter()
            .map(|&v| v as f32)
            .collect();
        close(t.value(rot), &want, "rotation logits");
    }

    #[test]
    fn plain_heads_pass_finite_differences() {
        let (cfg, w) = plain_weights();
        let sz = PlainHeadsConfig::of(&cfg).unwrap();
        let k_node = num_coefficients(cfg.lmax);
        let n = 24;
        let pos = positions(n, 5);
        let emb = random(n * k_node * 8, 6);
        let queries = [[0.2f32, -0.1, 0.1], [-0.4, 0.5, 0.0]];
        let opts = FdOptions {
            per_tensor: 8,
            ..FdOptions::default()
        };
        let input = [(emb, vec![n, k_node, 8])];
        let r = finite_difference_check(&w, "", &input, opts, |t, s, v| {
            let nodes = PlainNodes {
                embedding: v[0],
                coord: &pos,
            };
            trans_logits_from(t, s, sz, nodes, &queries)
        })
        .unwrap();
        assert_passes(&r, "plain translation head");
        // The input and the layer's 21 tensors (query, query_pos, 4 norms × 2, to_q/k/v,
        // to_out × 2, ff1 × 2, ff2 × 2, readout × 2).
        assert_eq!(r.tensors.len(), 22, "{:?}", r.tensors);
        assert!(r
            .tensors
            .iter()
            .skip(1)
            .all(|k| k.starts_with("plain_trans_head.")));

        let calc = WignerCalculator::new(crate::rotation_head::ROT_LMAX).unwrap();
        let fw = RotationHead::grid_wigners(&calc, &so3_healpix_grid(0)).unwrap();
        let r = finite_difference_check(&w, "", &input, opts, |t, s, v| {
            let nodes = PlainNodes {
                embedding: v[0],
                coord: &pos,
            };
            let (open, rot) = rot_query_from(t, s, sz, nodes, queries[0], &fw)?;
            let rot = t.reshape(rot, &[1, fw.len()])?;
            t.concat_cols(open, 1, rot, fw.len())
        })
        .unwrap();
        assert_passes(&r, "plain rotation head");
        assert_eq!(r.tensors.len(), 22, "{:?}", r.tensors);
    }

    #[test]
    fn plain_heads_without_neighbours_and_bad_shapes() {
        let (cfg, w) = plain_weights();
        let sz = PlainHeadsConfig::of(&cfg).unwrap();
        let s = w.scope("");
        let heads = PlainHeads::load(&s, sz, 0).unwrap();
        let k_node = num_coefficients(cfg.lmax);
        let pos = positions(10, 7);
        let emb = random(10 * k_node * 8, 8);
        // Far from every node: no rotation edges, the query token alone decides.
        let far = [40.0f32, 0.0, 0.0];
        let q = heads.rot_query(&emb, &pos, far).unwrap();
        assert!(q.open_logit.is_finite());
        let mut t = Tape::new();
        let ev = t.constant(emb.clone(), &[10, k_node, 8]).unwrap();
        let nodes = PlainNodes {
            embedding: ev,
            coord: &pos,
        };
        let (open, _) = rot_query_from(&mut t, &s, sz, nodes, far, &[]).unwrap();
        assert!((t.value(open)[0] - q.open_logit).abs() < 1e-5);
        // Wrong widths, missing keys, non-finite queries: errors, not panics.
        assert!(heads.trans_logits(&emb[1..], &pos, &[far]).is_err());
        assert!(heads.trans_logits(&emb, &pos, &[[f32::NAN; 3]]).is_err());
        assert!(rot_query_from(&mut t, &s, sz, nodes, far, &[vec![0.0; 3]]).is_err());
        let short = t.constant(vec![0.0; 10], &[10]).unwrap();
        let bad = PlainNodes {
            embedding: short,
            coord: &pos,
        };
        assert!(trans_logits_from(&mut t, &s, sz, bad, &[far]).is_err());
        let none = w.scope("nothing.");
        assert!(PlainHeads::load(&none, sz, 0).is_err());
        assert!(trans_logits_from(&mut t, &none, sz, nodes, &[far]).is_err());
        let mut zero = sz;
        zero.num_heads = 0;
        assert!(PlainHeads::load(&s, zero, 0).is_err());
    }
}
