//! Taped twins of the edge and attention path: the Gaussian radial basis, the radial MLP,
//! the edge-frame rotations, the SO(2) convolution, the grouped softmax and the whole
//! `SO2EquivariantGraphAttention`. Each reads its parameters by the inference layer's names
//! and computes the same values (up to the summation order of the dense products).

use std::sync::Arc;

use super::{layers, Act, Tape, Var};
use crate::attention::{AttentionConfig, EdgeSet};
use crate::error::{PolicyError, Result};
use crate::grids::S2Grid;
use crate::layers::{check_indices, degree_of, rbf_basis_value, rows_of, sigmoid, softplus};
use crate::matmul::{gemm_acc, Strided};
use crate::so2_conv::{CoefficientMapping, EdgeWigners};
use crate::so3::num_coefficients;
use crate::weights::Scope;

fn mismatch(name: &str, expected: Vec<usize>, got: Vec<usize>) -> PolicyError {
    PolicyError::ShapeMismatch {
        name: name.to_string(),
        expected,
        got,
    }
}

/// `GaussianRadialBasisLayerFiniteCutoff` of the edge `lengths` (`mean`, `std_logit`,
/// `weight_logit` `[1, K]`; offset 0.01 · cutoff): `[E, K]`, dense.
pub fn gaussian_rbf(t: &mut Tape, s: &Scope<'_>, lengths: &[f32], cutoff: f64) -> Result<Var> {
    let k = s.shape("mean", 2)?[1];
    let mean = t.param(s, "mean", &[1, k])?;
    let std_logit = t.param(s, "std_logit", &[1, k])?;
    let weight_logit = t.param(s, "weight_logit", &[1, k])?;
    // The inference layer's constants, rounded the same way.
    let offset = 0.01 * cutoff;
    let (off32, span) = (offset as f32, (cutoff - offset) as f32);
    let normalizer = (k as f64).sqrt() as f32;
    let std: Vec<f32> = t
        .value(std_logit)
        .iter()
        .map(|v| softplus(*v) + 1e-5)
        .collect();
    let weight: Vec<f32> = t
        .value(weight_logit)
        .iter()
        .map(|v| sigmoid(*v) * 4.0)
        .collect();
    let mv = t.value(mean);
    let ne = lengths.len();
    let mut y = vec![0.0f32; ne * k];
    let mut ue = Vec::with_capacity(ne);
    for (&d, row) in lengths.iter().zip(y.chunks_exact_mut(k.max(1))) {
        let u = (d - off32) / span;
        let env = crate::layers::rbf_envelope(u);
        ue.push((u, env));
        for (i, o) in row.iter_mut().enumerate() {
            *o = rbf_basis_value(u, mv[i], std[i], weight[i], env, normalizer);
        }
    }
    Ok(t.push(
        y,
        vec![ne, k],
        &[mean, std_logit, weight_logit],
        Some(Box::new(move |vals, g, gr| {
            let (mv, sl, wl) = (vals.get(mean), vals.get(std_logit), vals.get(weight_logit));
            let mut dm = vec![0.0f64; k];
            let mut ds = vec![0.0f64; k];
            let mut dw = vec![0.0f64; k];
            let norm = f64::from(normalizer);
            // Per basis: std, its derivative σ(std_logit), σ(weight_logit).
            let sd: Vec<f64> = sl.iter().map(|v| f64::from(softplus(*v) + 1e-5)).collect();
            let dsd: Vec<f64> = sl.iter().map(|v| f64::from(sigmoid(*v))).collect();
            let sg: Vec<f64> = wl.iter().map(|v| f64::from(sigmoid(*v))).collect();
            // The forward pass's f32 weights, once per basis (not an `expf` per value).
            let w32: Vec<f32> = wl.iter().map(|v| sigmoid(*v) * 4.0).collect();
            for (&(u, env), gr_row) in ue.iter().zip(g.chunks_exact(k.max(1))) {
                for i in 0..k {
                    // Where the forward value was cut to 0, so is its gradient.
                    if rbf_basis_value(u, mv[i], sd[i] as f32, w32[i], env, normalizer) == 0.0 {
                        continue;
                    }
                    let z = (f64::from(u) - f64::from(mv[i])) / sd[i];
                    let gauss = (-0.5 * z * z).exp();
                    let c = f64::from(gr_row[i]) * f64::from(env) * norm;
                    dw[i] += c * gauss * 4.0 * sg[i] * (1.0 - sg[i]);
                    // dv/dz = −z·v; dz/dmean = −1/std; dz/dstd = −z/std.
                    let dz = -c * 4.0 * sg[i] * gauss * z;
                    dm[i] -= dz / sd[i];
                    ds[i] -= dz * z / sd[i] * dsd[i];
                }
            }
            let f = |v: Vec<f64>| v.into_iter().map(|x| x as f32).collect::<Vec<f32>>();
            gr.add(mean, &f(dm));
            gr.add(std_logit, &f(ds));
            gr.add(weight_logit, &f(dw));
        })),
    ))
}

/// `RadialFunction` (as [`crate::layers::RadialMlp`]): `net.{3i}` Linear, `net.{3i+1}`
/// LayerNorm and SiLU per hidden layer, then the last Linear, on rows of `x`.
pub fn radial_mlp(t: &mut Tape, s: &Scope<'_>, x: Var) -> Result<Var> {
    let net = s.sub("net");
    let mut h = x;
    let mut i = 0;
    loop {
        let ls = net.sub(&i.to_string());
        let shape = ls.shape("weight", 2)?;
        h = layers::linear(t, &ls, h, shape[0], shape[1], true)?;
        if !net.contains(&format!("{}.weight", i + 1)) {
            return Ok(h);
        }
        h = layers::layer_norm(t, &net.sub(&(i + 1).to_string()), h, shape[0])?;
        h = t.act(h, Act::Silu);
        i += 3;
    }
}

/// Checks that `w` and `map` agree on the degree and returns (k, n_reduced).
fn rotation_sizes(w: &EdgeWigners, map: &CoefficientMapping) -> Result<(usize, usize)> {
    if w.lmax != map.lmax {
        return Err(PolicyError::UnsupportedDegree {
            lmax: w.lmax,
            mmax: map.mmax,
            max_supported: map.lmax,
        });
    }
    let k = num_coefficients(w.lmax);
    if w.d.len() != w.edges * k * k {
        return Err(mismatch(
            "edge Wigner matrices",
            vec![w.edges, k, k],
            vec![w.d.len()],
        ));
    }
    Ok((k, map.len()))
}

/// Per-edge matrices `[E, n_reduced, (lmax+1)²]` of [`EdgeWigners::rotate`]: the reduced rows
/// of D, zero outside each row's degree block.
pub fn rotation_matrices(w: &EdgeWigners, map: &CoefficientMapping) -> Result<Arc<[f32]>> {
    let (k, nr) = rotation_sizes(w, map)?;
    let mut m = vec![0.0f32; w.edges * nr * k];
    for (d, me) in w.d.chunks_exact(k * k).zip(m.chunks_exact_mut(nr * k)) {
        for (r, &i) in map.reduced.iter().enumerate() {
            let l = degree_of(i);
            for j in l * l..(l + 1) * (l + 1) {
                me[r * k + j] = d[i * k + j];
            }
        }
    }
    Ok(m.into())
}

/// Per-edge matrices `[E, (lmax+1)², n_reduced]` of [`EdgeWigners::rotate_back`]: Dᵀ on the
/// reduced rows with the rescale of degrees above m_max.
pub fn rotation_back_matrices(w: &EdgeWigners, map: &CoefficientMapping) -> Result<Arc<[f32]>> {
    let (k, nr) = rotation_sizes(w, map)?;
    let mut m = vec![0.0f32; w.edges * k * nr];
    for (d, me) in w.d.chunks_exact(k * k).zip(m.chunks_exact_mut(k * nr)) {
        for (r, &i) in map.reduced.iter().enumerate() {
            let l = degree_of(i);
            for j in l * l..(l + 1) * (l + 1) {
                me[j * nr + r] = d[i * k + j] * map.rotate_inv_rescale(j);
            }
        }
    }
    Ok(m.into())
}

/// Rotates `x` `[E, (lmax+1)², c]` into the edge frames, as [`EdgeWigners::rotate`]:
/// `[E, n_reduced, c]`.
pub fn rotate(
    t: &mut Tape,
    w: &EdgeWigners,
    map: &CoefficientMapping,
    x: Var,
    c: usize,
) -> Result<Var> {
    let (k, _) = rotation_sizes(w, map)?;
    let ne = rows_of("features to rotate", t.value(x).len(), k * c)?;
    // One row per edge.
    if ne != w.edges {
        return Err(mismatch(
            "features to rotate",
            vec![w.edges, k, c],
            vec![ne, k, c],
        ));
    }
    // The attention's rotation with edge e reading row e: one implementation for both.
    let rows: Vec<usize> = (0..ne).collect();
    rotate_messages(t, w, map, (x, &rows), None, c)
}

/// Rotates `y` `[E, n_reduced, c]` back to the global frame, as
/// [`EdgeWigners::rotate_back`]: `[E, (lmax+1)², c]`.
pub fn rotate_back(
    t: &mut Tape,
    w: &EdgeWigners,
    map: &CoefficientMapping,
    y: Var,
    c: usize,
) -> Result<Var> {
    let (k, nr) = rotation_sizes(w, map)?;
    let ne = rows_of("features to rotate back", t.value(y).len(), nr * c)?;
    if ne != w.edges {
        return Err(mismatch(
            "features to rotate back",
            vec![w.edges, nr, c],
            vec![ne, nr, c],
        ));
    }
    let mats = rotation_back_matrices(w, map)?;
    t.const_matmul(y, mats, (k, nr, c))
}

/// The attention's messages rotated into the edge frames: row e is `[x_src[src[e]] |
/// x_dst[dst[e]]]` (`[(lmax+1)², c]` each side; the source side alone without `dst_side`)
/// rotated as [`EdgeWigners::rotate`], `[E, n_reduced, present]`. The values and gradients of
/// `gather_rows`, `concat_cols` and [`rotate`] (each product's sums in their order, the
/// gathered rows' gradients added destination side first, as that composition's backward
/// pass did), with no gathered or concatenated copy forward and none of their gradients
/// backward: each edge's product reads the nodes' rows in place. Bit for bit the same as
/// long as `c` exceeds [`crate::matmul`]'s small-product sizes (5; every network here has
/// 16 channels or more): a side's product then takes the same kernel as both sides' did.
fn rotate_messages(
    t: &mut Tape,
    w: &EdgeWigners,
    map: &CoefficientMapping,
    (x_src, src): (Var, &[usize]),
    dst_side: Option<(Var, &[usize])>,
    c: usize,
) -> Result<Var> {
    let (k, nr) = rotation_sizes(w, map)?;
    let ne = w.edges;
    let mut sides = vec![(x_src, Arc::<[usize]>::from(src))];
    sides.extend(dst_side.map(|(x, idx)| (x, Arc::<[usize]>::from(idx))));
    for &(x, ref idx) in &sides {
        let n = rows_of("features to rotate", t.value(x).len(), k * c)?;
        if idx.len() != ne {
            return Err(mismatch("message edges", vec![ne], vec![idx.len()]));
        }
        check_indices("message node", idx.iter(), n)?;
    }
    let present = sides.len() * c;
    let mats = rotation_matrices(w, map)?;
    let mut y = vec![0.0f32; ne * nr * present];
    for (side, (x, idx)) in sides.iter().enumerate() {
        let xv = t.value(*x);
        for (e, &i) in idx.iter().enumerate() {
            gemm_acc(
                Strided::row_major(&mats, e * nr * k, nr, k),
                Strided::row_major(xv, i * k * c, k, c),
                &mut y,
                e * nr * present + side * c,
                present,
            )?;
        }
    }
    let parents: Vec<Var> = sides.iter().map(|(x, _)| *x).collect();
    Ok(t.push(
        y,
        vec![ne, nr, present],
        &parents,
        Some(Box::new(move |_, g, gr| {
            for (side, (x, idx)) in sides.iter().enumerate().rev() {
                let Some(acc) = gr.acc(*x) else {
                    continue;
                };
                for (e, &i) in idx.iter().enumerate() {
                    let _ = gemm_acc(
                        Strided::row_major(&mats, e * nr * k, nr, k).t(),
                        Strided {
                            data: g,
                            offset: e * nr * present + side * c,
                            rows: nr,
                            cols: c,
                            row_stride: present,
                            col_stride: 1,
                        },
                        acc,
                        i * k * c,
                        c,
                    );
                }
            }
        })),
    ))
}

/// Sizes of a taped SO(2) convolution (the inference layer's constructor arguments).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct So2ConvSizes {
    /// Input channels of the weights.
    pub cin: usize,
    /// Channels present in the input (≤ `cin`): the first ones; the others are zero and
    /// skipped, as [`crate::so2_conv::So2Conv::first_channels`].
    pub present: usize,
    /// Output channels.
    pub cout: usize,
    /// Extra m = 0 outputs (0 for none).
    pub extra: usize,
}

/// The first `keep` of every `cin` channels of `nl` degree blocks in rows of `nl·cin`
/// values: `[rows, nl·keep]` (identity when all are kept).
fn keep_channels(
    t: &mut Tape,
    v: Var,
    rows: usize,
    (nl, cin, keep): (usize, usize, usize),
) -> Result<Var> {
    if keep == cin {
        return Ok(v);
    }
    let r = t.reshape(v, &[rows * nl, cin])?;
    let r = t.slice_cols(r, cin, 0..keep)?;
    t.reshape(r, &[rows, nl * keep])
}

/// `SO2_Convolution` on `x_rot` `[E, n_reduced, present]` (reduced l-major order), as
/// [`crate::so2_conv::So2Conv::forward_features`]: the inputs are scaled by `rad_func` of
/// `edge_attr` when given (required when the scope has a radial MLP); returns
/// `[E, n_reduced, cout]` and the extra m = 0 outputs `[E, extra]` (None when 0).
pub fn so2_conv(
    t: &mut Tape,
    s: &Scope<'_>,
    map: &CoefficientMapping,
    sizes: So2ConvSizes,
    x_rot: Var,
    edge_attr: Option<Var>,
) -> Result<(Var, Option<Var>)> {
    let So2ConvSizes {
        cin,
        present: keep,
        cout,
        extra,
    } = sizes;
    if keep == 0 || keep > cin {
        return Err(mismatch(
            "SO(2) convolution channels present",
            vec![cin],
            vec![keep],
        ));
    }
    let (lmax, nr) = (map.lmax, map.len());
    let l1 = lmax + 1;
    let ne = rows_of("SO(2) convolution input", t.value(x_rot).len(), nr * keep)?;
    let xr = t.reshape(x_rot, &[ne * nr, keep])?;
    let rad_w: usize = l1 * cin + (1..=map.mmax).map(|m| (l1 - m) * cin).sum::<usize>();
    let rad = match edge_attr {
        Some(a) => {
            let r = radial_mlp(t, &s.sub("rad_func"), a)?;
            if t.value(r).len() != ne * rad_w {
                return Err(mismatch(
                    &s.key("rad_func (output width)"),
                    vec![ne, rad_w],
                    t.shape(r).to_vec(),
                ));
            }
            Some(r)
        }
        None if s.contains("rad_func.net.0.weight") => {
            return Err(mismatch(
                "SO(2) convolution edge features (required by its radial MLP)",
                vec![ne, 0],
                vec![0],
            ));
        }
        None => None,
    };
    // Rows `positions` of every edge's input, scaled by the radial weights at `roff`.
    let block = |t: &mut Tape, positions: &[usize], roff: usize| -> Result<Var> {
        let nl = positions.len();
        match rad {
            Some(r) => gather_scaled(t, (xr, nr), positions, (r, rad_w, roff), (cin, keep)),
            None => {
                let idx: Vec<usize> = (0..ne)
                    .flat_map(|e| positions.iter().map(move |p| e * nr + p))
                    .collect();
                let v = t.gather_rows(xr, keep, &idx)?;
                t.reshape(v, &[ne, nl * keep])
            }
        }
    };
    // m = 0: one Linear with bias; its first outputs are the extra scalars.
    let p0: Vec<usize> = (0..=lmax).map(|l| map.position(l, 0)).collect();
    let v0 = block(t, &p0, 0)?;
    let s0 = s.sub("fc_m0");
    let w0_out = extra + l1 * cout;
    let w0 = t.param(&s0, "weight", &[w0_out, l1 * cin])?;
    let w0 = keep_channels(t, w0, w0_out, (l1, cin, keep))?;
    let b0 = t.param(&s0, "bias", &[w0_out])?;
    let o0 = t.linear(v0, w0, Some(b0))?;
    let extra_out = if extra > 0 {
        Some(t.slice_cols(o0, w0_out, 0..extra)?)
    } else {
        None
    };
    let mut pairs = Vec::with_capacity(map.mmax);
    let mut roff = l1 * cin;
    for m in 1..=map.mmax {
        let nl = l1 - m;
        let pa: Vec<usize> = (m..=lmax).map(|l| map.position(l, m as i64)).collect();
        let pb: Vec<usize> = (m..=lmax).map(|l| map.position(l, -(m as i64))).collect();
        let va = block(t, &pa, roff)?;
        let vb = block(t, &pb, roff)?;
        roff += nl * cin;
        let fs = s.sub("so2_m_conv").sub(&(m - 1).to_string()).sub("fc");
        let half = nl * cout;
        let w = t.param(&fs, "weight", &[2 * half, nl * cin])?;
        let w = keep_channels(t, w, 2 * half, (nl, cin, keep))?;
        pairs.push((t.linear(va, w, None)?, t.linear(vb, w, None)?));
    }
    let y = so2_outputs(t, map, (o0, w0_out, extra), &pairs, cout, ne);
    Ok((y, extra_out))
}

/// Rows `e·nr + positions[l]` of `x` (`[ne·nr, keep]`) for every edge e and l, as `[ne,
/// nl·keep]` (nl = `positions.len()`), each value multiplied by its edge's radial weight:
/// value (e, l·keep + c) by `r[e, roff + l·cin + c]` (`r` `[ne, rad_w]`). The SO(2)
/// convolution's scaled input blocks in one pass: the values and gradients of
/// `gather_rows`, `slice_cols`, `keep_channels` and `mul` (each product as they formed
/// it, each accumulator's sums in the same order), without their three intermediate
/// copies forward and two backward, nor a list of the gathered rows.
fn gather_scaled(
    t: &mut Tape,
    (x, nr): (Var, usize),
    positions: &[usize],
    (r, rad_w, roff): (Var, usize, usize),
    (cin, keep): (usize, usize),
) -> Result<Var> {
    let nl = positions.len();
    let ne = rows_of("scaled gather input", t.value(x).len(), nr * keep)?;
    check_indices("gathered coefficient row", positions, nr)?;
    if x == r || keep > cin || roff + nl * cin > rad_w || t.value(r).len() != ne * rad_w {
        return Err(mismatch(
            "radial weights of a scaled gather",
            vec![ne, roff + nl * cin],
            t.shape(r).to_vec(),
        ));
    }
    let positions: Arc<[usize]> = positions.into();
    let (xv, rv) = (t.value(x), t.value(r));
    let mut y = Vec::with_capacity(ne * nl * keep);
    for e in 0..ne {
        for (l, &p) in positions.iter().enumerate() {
            let i = e * nr + p;
            let rc = e * rad_w + roff + l * cin;
            let (xr, rr) = (&xv[i * keep..(i + 1) * keep], &rv[rc..rc + keep]);
            y.extend(xr.iter().zip(rr).map(|(a, b)| a * b));
        }
    }
    Ok(t.push(
        y,
        vec![ne, nl * keep],
        &[x, r],
        Some(Box::new(move |vals, g, gr| {
            let (xv, rv) = (vals.get(x), vals.get(r));
            // Row (e, l) of the output and of its gradient `g`.
            let rows = || {
                (0..ne).flat_map(|e| {
                    positions.iter().enumerate().map(move |(l, &p)| {
                        let (i, rc, o) = (e * nr + p, e * rad_w + roff + l * cin, e * nl + l);
                        (l, i, rc, &g[o * keep..(o + 1) * keep])
                    })
                })
            };
            // The product's gradient to the radial weights first (the slice was recorded
            // after the gather, so the backward pass reached it first): a first
            // contribution written in their own order, zeros in the columns this block
            // does not read ...
            if gr.starts(r) {
                let mut fresh = Vec::with_capacity(ne * rad_w);
                for (l, i, _, gk) in rows() {
                    if l == 0 {
                        fresh.resize(fresh.len() + roff, 0.0);
                    }
                    let xr = &xv[i * keep..(i + 1) * keep];
                    fresh.extend(gk.iter().zip(xr).map(|(gi, xi)| gi * xi));
                    fresh.resize(fresh.len() + cin - keep, 0.0);
                    if l + 1 == nl {
                        fresh.resize(fresh.len() + rad_w - roff - nl * cin, 0.0);
                    }
                }
                fresh.resize(ne * rad_w, 0.0);
                gr.add_owned(r, fresh);
            } else if let Some(acc) = gr.acc(r) {
                for (_, i, rc, gk) in rows() {
                    let xr = &xv[i * keep..(i + 1) * keep];
                    for ((a, gi), xi) in acc[rc..rc + keep].iter_mut().zip(gk).zip(xr) {
                        *a += gi * xi;
                    }
                }
            }
            // ... then to the gathered rows, added in the gather's order.
            if let Some(acc) = gr.acc(x) {
                for (_, i, rc, gk) in rows() {
                    let rr = &rv[rc..rc + keep];
                    for ((a, gi), ri) in acc[i * keep..(i + 1) * keep].iter_mut().zip(gk).zip(rr) {
                        *a += gi * ri;
                    }
                }
            }
        })),
    ))
}

/// One term of an SO(2) convolution output row: `sign ·` columns `col..col + cout` of
/// input `input` (0: the m = 0 product; 2m − 1, 2m: pair m's a and b).
#[derive(Debug, Clone, Copy)]
struct So2Term {
    input: usize,
    col: usize,
    sign: f32,
}

/// The SO(2) convolution's outputs in the reduced l-major order, `[ne, nr, cout]`: the
/// m = 0 rows from `o0` (`[ne, w0]`, after its first `extra` scalars), and for each m > 0
/// out(+m) = R a − I b and out(−m) = R b + I a from `pairs[m − 1]` = (a, b), each
/// `[ne, 2·(lmax + 1 − m)·cout]` with the real part R before the imaginary part I. One
/// table of terms drives both passes, where the plain composition's slices, negation,
/// sums, growing concatenations and reordering gather each copied everything; the values
/// and gradients are the same (each input value feeds one output value).
fn so2_outputs(
    t: &mut Tape,
    map: &CoefficientMapping,
    (o0, w0, extra): (Var, usize, usize),
    pairs: &[(Var, Var)],
    cout: usize,
    ne: usize,
) -> Var {
    let l1 = map.lmax + 1;
    let term = |input, col, sign| So2Term { input, col, sign };
    // The inputs with their row widths.
    let mut inputs = vec![(o0, w0)];
    for (k, &(a, b)) in pairs.iter().enumerate() {
        let width = 2 * (l1 - k - 1) * cout;
        inputs.extend([(a, width), (b, width)]);
    }
    // Rows in m-major order (m = 0, +1, −1, +2, −2, ...; l ascending in each).
    let mut by_m: Vec<Vec<So2Term>> = (0..l1)
        .map(|l| vec![term(0, extra + l * cout, 1.0)])
        .collect();
    for m in 1..=map.mmax {
        let (a, b, half) = (2 * m - 1, 2 * m, (l1 - m) * cout);
        by_m.extend(
            (0..l1 - m).map(|i| vec![term(a, i * cout, 1.0), term(b, half + i * cout, -1.0)]),
        );
        by_m.extend(
            (0..l1 - m).map(|i| vec![term(b, i * cout, 1.0), term(a, half + i * cout, 1.0)]),
        );
    }
    // ... placed at their l-major positions.
    let mut rows = vec![Vec::new(); map.len()];
    for (j, &p) in map.m_major().iter().enumerate() {
        rows[p] = std::mem::take(&mut by_m[j]);
    }
    let nr = rows.len();
    // Written row by row (the first term of a row written, the others added), not into a
    // zero-filled buffer.
    let mut y = Vec::with_capacity(ne * nr * cout);
    let values: Vec<&[f32]> = inputs.iter().map(|&(v, _)| t.value(v)).collect();
    for e in 0..ne {
        for terms in rows.iter() {
            let start = y.len();
            let Some((first, rest)) = terms.split_first() else {
                y.resize(start + cout, 0.0);
                continue;
            };
            let at = e * inputs[first.input].1 + first.col;
            y.extend(
                values[first.input][at..at + cout]
                    .iter()
                    .map(|x| first.sign * x),
            );
            for tm in rest {
                let at = e * inputs[tm.input].1 + tm.col;
                let src = &values[tm.input][at..at + cout];
                for (o, x) in y[start..].iter_mut().zip(src) {
                    *o += tm.sign * x;
                }
            }
        }
    }
    // Where each input's columns go: (column, output row, sign) in column order (a stable
    // sort: equal columns keep the rows' order), which drives both backward paths: a first
    // gradient contribution written in the input's own order, or added.
    let mut by_input: Vec<Vec<(usize, usize, f32)>> = vec![Vec::new(); inputs.len()];
    for (r, terms) in rows.iter().enumerate() {
        for tm in terms {
            by_input[tm.input].push((tm.col, r, tm.sign));
        }
    }
    for cols in &mut by_input {
        cols.sort_by_key(|&(col, _, _)| col);
    }
    // Written in order only where the columns do not overlap (they do not: each input value
    // feeds one output value); otherwise added as they come.
    let in_order = by_input.iter().zip(&inputs).all(|(cols, &(_, width))| {
        cols.windows(2).all(|w| w[0].0 + cout <= w[1].0)
            && cols.last().is_none_or(|&(col, _, _)| col + cout <= width)
    });
    let parents: Vec<Var> = inputs.iter().map(|&(v, _)| v).collect();
    t.push(
        y,
        vec![ne, nr, cout],
        &parents,
        Some(Box::new(move |_, g, gr| {
            if cout == 0 {
                return;
            }
            // Each input value feeds exactly one output value: writing a first contribution
            // (zeros where no output reads the input, as the m = 0 product's extra scalars)
            // or adding into an accumulator gives what the plain composition's chain of
            // copies gave.
            for (input, &(v, width)) in inputs.iter().enumerate() {
                if in_order && gr.starts(v) {
                    let mut fresh = Vec::with_capacity(ne * width);
                    for ge in g.chunks_exact(nr * cout) {
                        let row_start = fresh.len();
                        for &(col, r, sign) in &by_input[input] {
                            fresh.resize(row_start + col, 0.0);
                            fresh.extend(ge[r * cout..(r + 1) * cout].iter().map(|x| sign * x));
                        }
                        fresh.resize(row_start + width, 0.0);
                    }
                    gr.add_owned(v, fresh);
                    continue;
                }
                let Some(acc) = gr.acc(v) else {
                    continue;
                };
                for (e, ge) in g.chunks_exact(nr * cout).enumerate() {
                    for &(col, r, sign) in &by_input[input] {
                        let at = e * width + col;
                        let grow = &ge[r * cout..(r + 1) * cout];
                        for (a, x) in acc[at..at + cout].iter_mut().zip(grow) {
                            *a += sign * x;
                        }
                    }
                }
            }
        })),
    )
}

/// Softmax of `logit` `[E, heads]` over the edges sharing a destination, as
/// [`crate::attention::grouped_softmax`] (PyG: max subtracted, 1e-16 in the denominator).
pub fn grouped_softmax(
    t: &mut Tape,
    logit: Var,
    dst: &[usize],
    nd: usize,
    heads: usize,
) -> Result<Var> {
    let ne = rows_of("softmax logits", t.value(logit).len(), heads)?;
    if dst.len() != ne {
        return Err(mismatch("softmax destinations", vec![ne], vec![dst.len()]));
    }
    check_indices("softmax destination", dst, nd)?;
    let y = crate::attention::grouped_softmax(t.value(logit), dst, nd, heads);
    let yk = y.clone();
    let dst: Arc<[usize]> = dst.into();
    Ok(t.push(
        y,
        vec![ne, heads],
        &[logit],
        Some(Box::new(move |_, g, gr| {
            // dz_e = y_e (g_e − Σ_f g_f y_f) over e's group (the max is a constant shift).
            let mut dots = vec![0.0f64; nd * heads];
            for (e, &d) in dst.iter().enumerate() {
                for h in 0..heads {
                    let i = e * heads + h;
                    dots[d * heads + h] += f64::from(g[i]) * f64::from(yk[i]);
                }
            }
            if let Some(acc) = gr.acc(logit) {
                for (e, &d) in dst.iter().enumerate() {
                    for h in 0..heads {
                        let i = e * heads + h;
                        let y = f64::from(yk[i]);
                        acc[i] += (y * (f64::from(g[i]) - dots[d * heads + h])) as f32;
                    }
                }
            }
        })),
    ))
}

/// `SO2EquivariantGraphAttention` from `x_src` `[Ns, (lmax+1)², C]` to `nd` destinations
/// with features `x_dst` (None: all zero, as the field heads' queries) over `edges`, with
/// the taped radial basis `edge_attr` `[E, basis]` and the S2 activation on `grid`, as
/// [`crate::attention::GraphAttention::forward`]: `[nd, (lmax+1)², output_channels]`.
#[allow(clippy::too_many_arguments)]
pub fn graph_attention(
    t: &mut Tape,
    s: &Scope<'_>,
    cfg: AttentionConfig,
    grid: &S2Grid,
    x_src: Var,
    x_dst: Option<Var>,
    nd: usize,
    edges: &EdgeSet,
    edge_attr: Var,
) -> Result<Var> {
    let map = CoefficientMapping::new(cfg.lmax, cfg.mmax)?;
    if edges.wigners.lmax != cfg.lmax {
        return Err(PolicyError::UnsupportedDegree {
            lmax: edges.wigners.lmax,
            mmax: cfg.mmax,
            max_supported: cfg.lmax,
        });
    }
    if grid.lmax != cfg.lmax || grid.reduced != map.reduced {
        return Err(PolicyError::UnsupportedDegree {
            lmax: grid.lmax,
            mmax: grid.mmax,
            max_supported: cfg.lmax,
        });
    }
    let k = num_coefficients(cfg.lmax);
    let c = cfg.sphere_channels;
    let heads = cfg.num_heads;
    let (ach, vc, hidden) = (cfg.alpha_channels, cfg.value_channels, cfg.hidden_channels);
    let proj_shape = s.sub("proj").shape("weight", 3)?;
    if proj_shape != [cfg.lmax + 1, cfg.output_channels, heads * vc] {
        return Err(mismatch(
            &s.key("proj.weight"),
            vec![cfg.lmax + 1, cfg.output_channels, heads * vc],
            proj_shape,
        ));
    }
    rows_of("attention source features", t.value(x_src).len(), k * c)?;
    let ne = edges.len();
    if edges.dst.len() != ne || edges.wigners.edges != ne {
        return Err(mismatch(
            "attention edges (destinations, Wigner matrices)",
            vec![ne, ne],
            vec![edges.dst.len(), edges.wigners.edges],
        ));
    }
    let dst = &edges.dst;

    // Messages concat(x_src[src], x_dst[dst]) per coefficient row (only the source half
    // when the destinations are zero: the zero half contributes nothing).
    let dst_side = match x_dst {
        Some(xd) => {
            let n = rows_of("attention destination features", t.value(xd).len(), k * c)?;
            if n != nd {
                return Err(mismatch(
                    "attention destination features",
                    vec![nd, k, c],
                    vec![n, k, c],
                ));
            }
            Some((xd, &dst[..]))
        }
        None => None,
    };
    let present = if dst_side.is_some() { 2 * c } else { c };
    let x_rot = rotate_messages(t, &edges.wigners, &map, (x_src, &edges.src), dst_side, c)?;
    let n_alpha = heads * ach;
    let n_extra = n_alpha + hidden;
    let (h, extra) = so2_conv(
        t,
        &s.sub("so2_conv_1"),
        &map,
        So2ConvSizes {
            cin: 2 * c,
            present,
            cout: hidden,
            extra: n_extra,
        },
        x_rot,
        Some(edge_attr),
    )?;
    let extra = extra.ok_or_else(|| mismatch("attention extra scalars", vec![n_extra], vec![0]))?;
    let alpha_in = t.slice_cols(extra, n_extra, 0..n_alpha)?;
    let gating = t.slice_cols(extra, n_extra, n_alpha..n_extra)?;
    let h = t.separable_s2_activation(grid, gating, h, hidden)?;
    let (v, _) = so2_conv(
        t,
        &s.sub("so2_conv_2"),
        &map,
        So2ConvSizes {
            cin: hidden,
            present: hidden,
            cout: heads * vc,
            extra: 0,
        },
        h,
        None,
    )?;

    // Logits: LayerNorm, smooth leaky ReLU, dot with each head's alpha_dot.
    let a = t.reshape(alpha_in, &[ne * heads, ach])?;
    let a = layers::layer_norm(t, &s.sub("alpha_norm"), a, ach)?;
    let a = t.act(a, Act::SmoothLeakyRelu(0.2));
    let dot = t.param(s, "alpha_dot", &[heads, ach])?;
    let prod = t.mul_broadcast(a, dot, [1, ne, heads * ach, 1])?;
    let ones = t.constant(vec![1.0; ach], &[1, ach])?;
    let logit = t.linear(prod, ones, None)?;
    let alpha = grouped_softmax(t, logit, dst, nd, heads)?;

    // Weight each head's values, rotate back, sum at the destinations, project.
    let v = t.mul_broadcast(v, alpha, [ne, map.len(), heads, vc])?;
    let back = rotate_back(t, &edges.wigners, &map, v, heads * vc)?;
    let agg = t.scatter_add_rows(back, k * heads * vc, dst, nd)?;
    let agg = t.reshape(agg, &[nd, k, heads * vc])?;
    layers::so3_linear(t, &s.sub("proj"), agg)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::attention::GraphAttention;
    use crate::autodiff::check::{finite_difference_check, FdOptions};
    use crate::autodiff::layers::tests::small_weights;
    use crate::autodiff::layers::tests::{assert_passes, random};
    use crate::layers::{GaussianRbf, RadialMlp};
    use crate::model::knn_graph;
    use crate::so2_conv::So2Conv;
    use crate::so3::WignerCalculator;
    use crate::weights::Weights;
    use rand::{Rng, SeedableRng};
    use rand_chacha::ChaCha8Rng;

    const BLOCK: &str = "down_blocks.1.block.";
    /// `max_radius[1]` of the reference model, times 0.99 as `EquFieldUnet` loads it.
    const CUTOFF: f64 = 0.4 * 0.99;

    fn assert_close(a: &[f32], b: &[f32], tol: f32, what: &str) {
        assert_eq!(a.len(), b.len(), "{what}: lengths");
        let scale = b.iter().fold(0.0f32, |m, v| m.max(v.abs()));
        for (i, (x, y)) in a.iter().zip(b).enumerate() {
            assert!(
                (x - y).abs() <= tol * (1.0 + y.abs().max(scale)),
                "{what}[{i}]: {x} vs {y}"
            );
        }
    }

    fn attention_config() -> AttentionConfig {
        // down_blocks.1 of `small_weights`: 8 channels, 4 heads of 4 logits and 2 values.
        AttentionConfig {
            lmax: 3,
            mmax: 2,
            sphere_channels: 8,
            hidden_channels: 8,
            num_heads: 4,
            alpha_channels: 4,
            value_channels: 2,
            output_channels: 8,
        }
    }

    /// `n` random points in a 0.5 box and their k = 4 nearest-neighbour graph.
    fn graph(n: usize, seed: u64) -> (Vec<[f32; 3]>, Vec<usize>, Vec<usize>) {
        let mut rng = ChaCha8Rng::seed_from_u64(seed);
        let pos: Vec<[f32; 3]> = (0..n)
            .map(|_| std::array::from_fn(|_| rng.random_range(-0.25f32..0.25)))
            .collect();
        let (src, dst) = knn_graph(&pos, 4).unwrap();
        (pos, src, dst)
    }

    /// Edges of the 6-node graph with the block's radial basis, and the weights.
    fn edges(w: &Weights, lmax: usize) -> EdgeSet {
        let (pos, src, dst) = graph(6, 11);
        let rbf = GaussianRbf::load(&w.scope(BLOCK).sub("distance_expansion"), CUTOFF).unwrap();
        let calc = WignerCalculator::new(lmax).unwrap();
        EdgeSet::new(&calc, lmax, &pos, &pos, src, dst, &rbf).unwrap()
    }

    #[test]
    fn gaussian_rbf_matches_inference_and_finite_differences() {
        let mut w = small_weights();
        let e = edges(&w, 3);
        // Field-head bases narrow enough (std ≈ 0.004 of the span) that inference keeps them
        // in compressed rows and skips the bases out of reach.
        for v in w.f32_mut("field_distance_expansion.std_logit").unwrap() {
            *v = -5.5;
        }
        let field_cutoff = f64::from(crate::heads::QUERY_RADIUS) * 0.99;
        for (prefix, cutoff, sparse) in [
            (format!("{BLOCK}distance_expansion."), CUTOFF, false),
            ("field_distance_expansion.".to_string(), field_cutoff, true),
        ] {
            let s = w.scope(&prefix);
            let rbf = GaussianRbf::load(&s, cutoff).unwrap();
            let mut lengths = e.dist.clone();
            lengths.extend([0.0, 0.001, 0.3 * cutoff as f32, 0.9 * cutoff as f32, 2.5]);
            let mut t = Tape::new();
            let y = gaussian_rbf(&mut t, &s, &lengths, cutoff).unwrap();
            assert_close(t.value(y), &rbf.forward(&lengths), 0.0, "rbf (dense)");
            let features = rbf.features(&lengths);
            assert_eq!(
                matches!(features, crate::layers::EdgeFeatures::Sparse { .. }),
                sparse
            );
            assert_close(t.value(y), &features.to_dense(), 0.0, "rbf (features)");
            assert!(t.value(y).iter().any(|v| *v > 0.0));
        }
        let r = finite_difference_check(
            &w,
            &format!("{BLOCK}distance_expansion."),
            &[],
            FdOptions {
                eps: 1e-3,
                per_tensor: 10,
                ..FdOptions::default()
            },
            |t, s, _| gaussian_rbf(t, s, &e.dist, CUTOFF),
        )
        .unwrap();
        assert_passes(&r, "gaussian_rbf");
        assert_eq!(r.tensors.len(), 3, "mean, std_logit and weight_logit");
    }

    #[test]
    fn radial_mlp_matches_inference_and_finite_differences() {
        let w = small_weights();
        let p = format!("{BLOCK}transblock.ga.so2_conv_1.rad_func.");
        let s = w.scope(&p);
        let mlp = RadialMlp::load(&s).unwrap();
        let x = random(5 * mlp.inp(), 1);
        let want = mlp.forward(&x).unwrap();
        let mut t = Tape::new();
        let xv = t.variable(x.clone(), &[5, mlp.inp()]).unwrap();
        let y = radial_mlp(&mut t, &s, xv).unwrap();
        assert_close(t.value(y), &want, 1e-5, "radial_mlp");
        let r = finite_difference_check(
            &w,
            &p,
            &[(x, vec![5, mlp.inp()])],
            FdOptions::default(),
            |t, s, v| radial_mlp(t, s, v[0]),
        )
        .unwrap();
        assert_passes(&r, "radial_mlp");
        assert_eq!(
            r.tensors.len(),
            1 + 10,
            "input, 3 linears and 2 layer norms"
        );
    }

    #[test]
    fn edge_rotations_match_inference_and_finite_differences() {
        let w = small_weights();
        for (lmax, mmax) in [(3, 2), (3, 3), (4, 3), (1, 1)] {
            let e = edges(&w, lmax);
            let map = CoefficientMapping::new(lmax, mmax).unwrap();
            let (k, nr, c, ne) = (num_coefficients(lmax), map.len(), 3, e.len());
            let x = random(ne * k * c, 2);
            let y = random(ne * nr * c, 3);
            let mut t = Tape::new();
            let xv = t.variable(x.clone(), &[ne, k, c]).unwrap();
            let yv = t.variable(y.clone(), &[ne, nr, c]).unwrap();
            let rx = rotate(&mut t, &e.wigners, &map, xv, c).unwrap();
            let by = rotate_back(&mut t, &e.wigners, &map, yv, c).unwrap();
            let want_r = e.wigners.rotate(&map, &x, c).unwrap();
            let want_b = e.wigners.rotate_back(&map, &y, c).unwrap();
            assert_close(t.value(rx), &want_r, 1e-6, "rotate");
            assert_close(t.value(by), &want_b, 1e-6, "rotate_back");
            let inputs = [(x, vec![ne, k, c]), (y, vec![ne, nr, c])];
            let r = finite_difference_check(&w, "", &inputs, FdOptions::default(), |t, _, v| {
                let a = rotate(t, &e.wigners, &map, v[0], c)?;
                let b = rotate_back(t, &e.wigners, &map, v[1], c)?;
                let a = t.reshape(a, &[ne, nr * c])?;
                let b = t.reshape(b, &[ne, k * c])?;
                t.concat_cols(a, nr * c, b, k * c)
            })
            .unwrap();
            assert_passes(&r, "edge rotations");
        }
        // Features of a different edge count are an error, not a shared matrix.
        let e = edges(&w, 3);
        let map = CoefficientMapping::new(3, 2).unwrap();
        let one = e.wigners.slice(0..1);
        let mut t = Tape::new();
        let x = t.constant(vec![0.0; 2 * 16 * 3], &[2, 16, 3]).unwrap();
        assert!(rotate(&mut t, &one, &map, x, 3).is_err());
        let map4 = CoefficientMapping::new(4, 2).unwrap();
        assert!(rotate(&mut t, &e.wigners, &map4, x, 3).is_err());
    }

    #[test]
    fn rotated_messages_match_the_composition_they_replace_bit_for_bit() {
        let w = small_weights();
        // More channels than `matmul`'s small-product path takes, on each side alone too.
        let (lmax, c) = (3, 8);
        let map = CoefficientMapping::new(lmax, 2).unwrap();
        let e = edges(&w, lmax);
        let (ne, k, nr) = (e.len(), num_coefficients(lmax), map.len());
        let n = 6;
        let x = random(n * k * c, 31);
        // Destinations: the same features (self-attention, where both sides' gradients meet
        // in one accumulator) or none.
        for with_dst in [true, false] {
            let present = if with_dst { 2 * c } else { c };
            let seed = random(ne * nr * present, 32);
            let run = |fused: bool| {
                let mut t = Tape::new();
                let xv = t.variable(x.clone(), &[n, k, c]).unwrap();
                let y = if fused {
                    let dst_side = with_dst.then_some((xv, &e.dst[..]));
                    rotate_messages(&mut t, &e.wigners, &map, (xv, &e.src), dst_side, c).unwrap()
                } else {
                    let xs = t.gather_rows(xv, k * c, &e.src).unwrap();
                    let msg = if with_dst {
                        let xd = t.gather_rows(xv, k * c, &e.dst).unwrap();
                        let a = t.reshape(xs, &[ne * k, c]).unwrap();
                        let b = t.reshape(xd, &[ne * k, c]).unwrap();
                        t.concat_cols(a, c, b, c).unwrap()
                    } else {
                        xs
                    };
                    rotate(&mut t, &e.wigners, &map, msg, present).unwrap()
                };
                let g = t.backward(y, &seed).unwrap();
                let bits = |v: &[f32]| v.iter().map(|x| x.to_bits()).collect::<Vec<_>>();
                (bits(t.value(y)), bits(g.of(xv).unwrap()))
            };
            let (fused, plain) = (run(true), run(false));
            let differ = |a: &[u32], b: &[u32]| a.iter().zip(b).filter(|(x, y)| x != y).count();
            assert_eq!(fused.0.len(), plain.0.len());
            assert_eq!(
                differ(&fused.0, &plain.0),
                0,
                "values (destinations: {with_dst})"
            );
            assert_eq!(
                differ(&fused.1, &plain.1),
                0,
                "gradients (destinations: {with_dst})"
            );
        }
        // A node index past the features is an error, not a panic.
        let mut t = Tape::new();
        let xv = t.variable(x.clone(), &[n, k, c]).unwrap();
        let mut bad = e.src.clone();
        bad[0] = n;
        let err = rotate_messages(&mut t, &e.wigners, &map, (xv, &bad), None, c);
        assert!(
            matches!(err, Err(PolicyError::IndexOutOfRange { .. })),
            "{err:?}"
        );
    }

    #[test]
    fn scaled_gathers_match_the_composition_they_replace_bit_for_bit() {
        // Two blocks read the same radial columns (as an m > 0 pair does), so the radial
        // weights' accumulator is written once and added to once; fewer channels kept than
        // the radial MLP gives (a convolution on the first channels).
        let (ne, nr, keep, cin) = (5, 16, 3, 4);
        let (rad_w, roff) = (11 * cin, 2 * cin);
        let positions: [&[usize]; 2] = [&[4, 9, 12], &[5, 10, 13]];
        let idx = |ps: &[usize]| -> Vec<usize> {
            (0..ne)
                .flat_map(|e| ps.iter().map(move |p| e * nr + p))
                .collect()
        };
        let x = random(ne * nr * keep, 21);
        let r = random(ne * rad_w, 22);
        let seed = random(2 * ne * 3 * keep, 23);
        let run = |fused: bool| {
            let mut t = Tape::new();
            let xv = t.variable(x.clone(), &[ne * nr, keep]).unwrap();
            let rv = t.variable(r.clone(), &[ne, rad_w]).unwrap();
            let mut outs = Vec::new();
            for ps in positions {
                let nl = ps.len();
                let y = if fused {
                    gather_scaled(&mut t, (xv, nr), ps, (rv, rad_w, roff), (cin, keep)).unwrap()
                } else {
                    let v = t.gather_rows(xv, keep, &idx(ps)).unwrap();
                    let v = t.reshape(v, &[ne, nl * keep]).unwrap();
                    let rs = t.slice_cols(rv, rad_w, roff..roff + nl * cin).unwrap();
                    let rs = keep_channels(&mut t, rs, ne, (nl, cin, keep)).unwrap();
                    t.mul(v, rs).unwrap()
                };
                outs.push(y);
            }
            let y = t.concat_cols(outs[0], 3 * keep, outs[1], 3 * keep).unwrap();
            let g = t.backward(y, &seed).unwrap();
            let bits = |v: &[f32]| v.iter().map(|x| x.to_bits()).collect::<Vec<_>>();
            (
                bits(t.value(y)),
                bits(g.of(xv).unwrap()),
                bits(g.of(rv).unwrap()),
            )
        };
        let (fused, plain) = (run(true), run(false));
        assert_eq!(fused.0, plain.0, "values");
        assert_eq!(fused.1, plain.1, "gradient of the gathered rows");
        assert_eq!(fused.2, plain.2, "gradient of the radial weights");
        // Out-of-range rows are an error, not a panic.
        let mut t = Tape::new();
        let xv = t.variable(x.clone(), &[ne * nr, keep]).unwrap();
        let rv = t.variable(r.clone(), &[ne, rad_w]).unwrap();
        let err = gather_scaled(&mut t, (xv, nr), &[4, nr], (rv, rad_w, roff), (cin, keep));
        assert!(
            matches!(err, Err(PolicyError::IndexOutOfRange { .. })),
            "{err:?}"
        );
        // Radial weights too narrow for the block.
        let err = gather_scaled(
            &mut t,
            (xv, nr),
            &[4, 9, 12],
            (rv, rad_w, 9 * cin),
            (cin, keep),
        );
        assert!(
            matches!(err, Err(PolicyError::ShapeMismatch { .. })),
            "{err:?}"
        );
    }

    #[test]
    fn so2_conv_matches_inference_and_finite_differences() {
        let w = small_weights();
        let cfg = attention_config();
        let map = CoefficientMapping::new(cfg.lmax, cfg.mmax).unwrap();
        let nr = map.len();
        let e = edges(&w, cfg.lmax);
        let ne = e.len();
        let attr = e.attr.to_dense();
        let nb = e.attr.cols();
        let c = cfg.sphere_channels;
        let n_extra = cfg.num_heads * cfg.alpha_channels + cfg.hidden_channels;
        let p = format!("{BLOCK}transblock.ga.so2_conv_1.");
        let full = So2Conv::load(
            &w.scope(&p),
            &map,
            2 * c,
            cfg.hidden_channels,
            n_extra,
            true,
        )
        .unwrap();
        for present in [2 * c, c] {
            let conv = if present == 2 * c {
                full.clone()
            } else {
                full.first_channels(present).unwrap()
            };
            let x = random(ne * nr * present, 4);
            let (want_y, want_extra) = conv.forward(&x, Some(&attr)).unwrap();
            let sizes = So2ConvSizes {
                cin: 2 * c,
                present,
                cout: cfg.hidden_channels,
                extra: n_extra,
            };
            let build = |t: &mut Tape, s: &Scope<'_>, v: &[Var]| -> Result<Var> {
                let (y, ex) = so2_conv(t, s, &map, sizes, v[0], Some(v[1]))?;
                let y = t.reshape(y, &[ne, nr * cfg.hidden_channels])?;
                let ex = ex.ok_or_else(|| mismatch("extra", vec![n_extra], vec![0]))?;
                t.concat_cols(y, nr * cfg.hidden_channels, ex, n_extra)
            };
            let mut t = Tape::new();
            let xv = t.variable(x.clone(), &[ne, nr, present]).unwrap();
            let av = t.variable(attr.clone(), &[ne, nb]).unwrap();
            let (y, ex) = so2_conv(&mut t, &w.scope(&p), &map, sizes, xv, Some(av)).unwrap();
            assert_close(t.value(y), &want_y, 1e-5, "so2_conv features");
            assert_close(t.value(ex.unwrap()), &want_extra, 1e-5, "so2_conv extra");
            let inputs = [(x, vec![ne, nr, present]), (attr.clone(), vec![ne, nb])];
            let r = finite_difference_check(&w, &p, &inputs, FdOptions::default(), build).unwrap();
            assert_passes(&r, "so2_conv");
        }
        // Without a radial MLP and extra outputs (the second convolution).
        let p2 = format!("{BLOCK}transblock.ga.so2_conv_2.");
        let hv = cfg.num_heads * cfg.value_channels;
        let conv2 = So2Conv::load(&w.scope(&p2), &map, cfg.hidden_channels, hv, 0, false).unwrap();
        let x = random(ne * nr * cfg.hidden_channels, 5);
        let (want, _) = conv2.forward(&x, None).unwrap();
        let sizes = So2ConvSizes {
            cin: cfg.hidden_channels,
            present: cfg.hidden_channels,
            cout: hv,
            extra: 0,
        };
        let mut t = Tape::new();
        let xv = t
            .variable(x.clone(), &[ne, nr, cfg.hidden_channels])
            .unwrap();
        let (y, ex) = so2_conv(&mut t, &w.scope(&p2), &map, sizes, xv, None).unwrap();
        assert!(ex.is_none());
        assert_close(t.value(y), &want, 1e-5, "so2_conv_2");
        let inputs = [(x, vec![ne, nr, cfg.hidden_channels])];
        let r = finite_difference_check(&w, &p2, &inputs, FdOptions::default(), |t, s, v| {
            Ok(so2_conv(t, s, &map, sizes, v[0], None)?.0)
        })
        .unwrap();
        assert_passes(&r, "so2_conv_2");
        // The first convolution needs its edge features.
        let mut t = Tape::new();
        let x = t
            .constant(vec![0.0; ne * nr * 2 * c], &[ne, nr, 2 * c])
            .unwrap();
        let sizes = So2ConvSizes {
            cin: 2 * c,
            present: 2 * c,
            cout: cfg.hidden_channels,
            extra: n_extra,
        };
        assert!(so2_conv(&mut t, &w.scope(&p), &map, sizes, x, None).is_err());
    }

    #[test]
    fn grouped_softmax_matches_inference_and_finite_differences() {
        let w = small_weights();
        let dst = vec![0, 0, 1, 2, 2, 2, 0, 1];
        let (nd, heads) = (4, 3);
        let logit = random(dst.len() * heads, 6);
        let want = crate::attention::grouped_softmax(&logit, &dst, nd, heads);
        let mut t = Tape::new();
        let lv = t.variable(logit.clone(), &[dst.len(), heads]).unwrap();
        let y = grouped_softmax(&mut t, lv, &dst, nd, heads).unwrap();
        assert_close(t.value(y), &want, 0.0, "grouped_softmax");
        let inputs = [(logit, vec![dst.len(), heads])];
        let opts = FdOptions {
            per_tensor: 24,
            ..FdOptions::default()
        };
        let r = finite_difference_check(&w, "", &inputs, opts, |t, _, v| {
            grouped_softmax(t, v[0], &dst, nd, heads)
        })
        .unwrap();
        assert_passes(&r, "grouped_softmax");
        assert!(grouped_softmax(&mut t, lv, &dst, 2, heads).is_err());
        assert!(grouped_softmax(&mut t, lv, &dst[1..], nd, heads).is_err());
    }

    /// The taped attention (radial basis from the block's `distance_expansion`) against
    /// inference and finite differences, with real or zero destinations, on `grid`.
    fn check_attention(grid: S2Grid, zero_destinations: bool) {
        let w = small_weights();
        let cfg = attention_config();
        let e = edges(&w, cfg.lmax);
        let (n, k, c) = (6, num_coefficients(cfg.lmax), cfg.sphere_channels);
        let x_src = random(n * k * c, 7);
        let x_dst = if zero_destinations {
            vec![0.0; n * k * c]
        } else {
            random(n * k * c, 8)
        };
        let ga = format!("{BLOCK}transblock.ga.");
        let mut inf = GraphAttention::load_with_grid(&w.scope(&ga), cfg, grid.clone()).unwrap();
        let want = if zero_destinations {
            inf.prepare_zero_destinations().unwrap();
            let direct = inf.forward_zero_destinations(&x_src, n, &e).unwrap();
            let via_zeros = inf.forward(&x_src, &x_dst, &e).unwrap();
            assert_close(&direct, &via_zeros, 1e-5, "inference zero destinations");
            direct
        } else {
            inf.forward(&x_src, &x_dst, &e).unwrap()
        };
        let build = |t: &mut Tape, s: &Scope<'_>, v: &[Var]| -> Result<Var> {
            let attr = gaussian_rbf(t, &s.sub("distance_expansion"), &e.dist, CUTOFF)?;
            let xd = (!zero_destinations).then(|| v[1]);
            let s = s.sub("transblock").sub("ga");
            graph_attention(t, &s, cfg, &grid, v[0], xd, n, &e, attr)
        };
        let mut inputs = vec![(x_src, vec![n, k, c])];
        if !zero_destinations {
            inputs.push((x_dst, vec![n, k, c]));
        }
        let mut t = Tape::new();
        let vars: Vec<Var> = inputs
            .iter()
            .map(|(x, s)| t.variable(x.clone(), s).unwrap())
            .collect();
        let y = build(&mut t, &w.scope(BLOCK), &vars).unwrap();
        assert_eq!(t.shape(y), [n, k, cfg.output_channels]);
        assert_close(t.value(y), &want, 1e-5, "graph_attention");
        // The composed layer is curved enough (narrow bases, a LayerNorm over 4 logits) that
        // the default step's truncation error reaches a few percent; 3e-3 shrinks it ~10×.
        let opts = FdOptions {
            eps: 3e-3,
            ..FdOptions::default()
        };
        let r = finite_difference_check(&w, BLOCK, &inputs, opts, build).unwrap();
        assert_passes(&r, "graph_attention");
        // Inputs, 3 radial basis, 10 radial MLP, 4 + 4 convolution, 2 LayerNorm, alpha_dot
        // and 2 projection tensors: every parameter of the layer receives a gradient.
        assert_eq!(r.tensors.len(), inputs.len() + 26, "{:?}", r.tensors);
    }

    #[test]
    fn graph_attention_matches_inference_and_finite_differences() {
        check_attention(S2Grid::reference(3, 2).unwrap(), false);
    }

    #[test]
    fn graph_attention_zero_destinations_matches_inference_and_finite_differences() {
        check_attention(S2Grid::reference(3, 2).unwrap(), true);
    }

    #[test]
    fn graph_attention_gated_grid_matches_inference_and_finite_differences() {
        check_attention(S2Grid::gate(3, 2).unwrap(), false);
    }

    #[test]
    fn graph_attention_rejects_mismatched_inputs() {
        let w = small_weights();
        let cfg = attention_config();
        let e = edges(&w, cfg.lmax);
        let s = w.scope(BLOCK).sub("transblock").sub("ga");
        let mut t = Tape::new();
        let x = t.constant(vec![0.0; 6 * 16 * 8], &[6, 16, 8]).unwrap();
        let attr = t.constant(e.attr.to_dense(), &[e.len(), 16]).unwrap();
        let grid = S2Grid::reference(3, 2).unwrap();
        let run =
            |t: &mut Tape, cfg: AttentionConfig, grid: &S2Grid, nd: usize, xd: Option<Var>| {
                graph_attention(t, &s, cfg, grid, x, xd, nd, &e, attr)
            };
        assert!(run(&mut t, cfg, &grid, 6, Some(x)).is_ok());
        assert!(run(&mut t, cfg, &grid, 5, Some(x)).is_err(), "nd vs x_dst");
        assert!(
            run(&mut t, cfg, &grid, 3, None).is_err(),
            "destination out of range"
        );
        let other = S2Grid::reference(3, 3).unwrap();
        assert!(run(&mut t, cfg, &other, 6, None).is_err(), "grid degrees");
        let wide = AttentionConfig {
            value_channels: 3,
            ..cfg
        };
        assert!(run(&mut t, wide, &grid, 6, None).is_err(), "proj width");
    }

    #[test]
    fn field_head_attention_matches_inference_and_finite_differences() {
        // `trans_field_layer.0`: degree 1, zero query features, the field radial basis, every
        // query attending to every node.
        use crate::heads::{QUERY_RADIUS, TRANS_LMAX};
        let w = small_weights();
        let cfg = AttentionConfig {
            lmax: TRANS_LMAX,
            mmax: TRANS_LMAX,
            ..attention_config()
        };
        let cutoff = f64::from(QUERY_RADIUS) * 0.99;
        let (pos, _, _) = graph(6, 12);
        let queries = [[0.05f32, -0.1, 0.02], [-0.2, 0.1, 0.15], [0.1, 0.2, -0.1]];
        let src: Vec<usize> = (0..queries.len()).flat_map(|_| 0..pos.len()).collect();
        let dst: Vec<usize> = (0..queries.len())
            .flat_map(|q| std::iter::repeat_n(q, pos.len()))
            .collect();
        let rbf = GaussianRbf::load(&w.scope("field_distance_expansion."), cutoff).unwrap();
        let calc = WignerCalculator::new(TRANS_LMAX).unwrap();
        let e = EdgeSet::new(&calc, TRANS_LMAX, &pos, &queries, src, dst, &rbf).unwrap();
        let (n, nq, k, c) = (pos.len(), queries.len(), num_coefficients(TRANS_LMAX), 8);
        let grid = S2Grid::reference(TRANS_LMAX, TRANS_LMAX).unwrap();
        let mut inf =
            GraphAttention::load_with_grid(&w.scope("trans_field_layer.0."), cfg, grid.clone())
                .unwrap();
        inf.prepare_zero_destinations().unwrap();
        let x_src = random(n * k * c, 13);
        let want = inf.forward_zero_destinations(&x_src, nq, &e).unwrap();
        let build = |t: &mut Tape, s: &Scope<'_>, v: &[Var]| -> Result<Var> {
            let attr = gaussian_rbf(t, &s.sub("field_distance_expansion"), &e.dist, cutoff)?;
            let s = s.sub("trans_field_layer").sub("0");
            graph_attention(t, &s, cfg, &grid, v[0], None, nq, &e, attr)
        };
        let inputs = [(x_src, vec![n, k, c])];
        let mut t = Tape::new();
        let xv = t.variable(inputs[0].0.clone(), &[n, k, c]).unwrap();
        let y = build(&mut t, &w.scope(""), &[xv]).unwrap();
        assert_close(t.value(y), &want, 1e-5, "field head attention");
        let opts = FdOptions {
            eps: 3e-3,
            ..FdOptions::default()
        };
        let r = finite_difference_check(&w, "", &inputs, opts, build).unwrap();
        assert_passes(&r, "field head attention");
    }
}
