//! The generic operations of the tape: element-wise maps, dense products, row gathers and
//! scatters, channel slices, and constant (non-trained) linear maps over coefficient rows.

use std::sync::Arc;

use super::{check_shape, Tape, Var};
use crate::error::{PolicyError, Result};
use crate::grids::S2Grid;
use crate::layers::{check_indices, gelu, sigmoid, silu, smooth_leaky_relu, smooth_leaky_relu_of};
use crate::matmul::{gemm_acc, Strided};

/// An element-wise activation with its derivative.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum Act {
    /// x·σ(x).
    Silu,
    /// σ(x).
    Sigmoid,
    /// Exact GELU.
    Gelu,
    /// The reference's smooth leaky ReLU with the given slope.
    SmoothLeakyRelu(f32),
    /// eˣ.
    Exp,
    /// x·tanh(softplus(x)).
    Mish,
    /// log(1 + eˣ).
    Softplus,
}

impl Act {
    /// The activation (the inference layers' own functions, so values agree bit for bit).
    pub fn apply(self, x: f32) -> f32 {
        match self {
            Act::Silu => silu(x),
            Act::Sigmoid => sigmoid(x),
            Act::Gelu => gelu(x),
            Act::SmoothLeakyRelu(a) => smooth_leaky_relu(x, a),
            Act::Exp => x.exp(),
            Act::Mish => crate::layers::mish(x),
            Act::Softplus => crate::layers::softplus(x),
        }
    }

    /// [`Act::apply`] of every value of `x`, the same bits: e^x, SiLU and σ (the smooth
    /// leaky ReLU's too) through [`crate::vector_exp`], eight values at a time.
    pub fn apply_all(self, x: &[f32]) -> Vec<f32> {
        let mut v = x.to_vec();
        match self {
            Act::Silu => crate::vector_exp::silu_in_place(&mut v),
            Act::Sigmoid => crate::vector_exp::sigmoid_in_place(&mut v),
            Act::Exp => crate::vector_exp::exp_in_place(&mut v),
            Act::SmoothLeakyRelu(a) => {
                crate::vector_exp::sigmoid_in_place(&mut v);
                for (s, &x) in v.iter_mut().zip(x) {
                    *s = smooth_leaky_relu_of(x, *s, a);
                }
            }
            Act::Gelu | Act::Mish | Act::Softplus => v.iter_mut().for_each(|x| *x = self.apply(*x)),
        }
        v
    }

    /// Its derivative at `x`.
    pub fn derivative(self, x: f32) -> f32 {
        let xd = f64::from(x);
        let s = 1.0 / (1.0 + (-xd).exp());
        let d = match self {
            Act::Silu => s * (1.0 + xd * (1.0 - s)),
            Act::Sigmoid => s * (1.0 - s),
            Act::Gelu => {
                let cdf = 0.5 * (1.0 + crate::layers::erf(xd / std::f64::consts::SQRT_2));
                let pdf = (-0.5 * xd * xd).exp() / (2.0 * std::f64::consts::PI).sqrt();
                cdf + xd * pdf
            }
            Act::SmoothLeakyRelu(a) => {
                let a = f64::from(a);
                0.5 * (1.0 + a) + 0.5 * (1.0 - a) * ((2.0 * s - 1.0) + 2.0 * xd * s * (1.0 - s))
            }
            Act::Exp => xd.exp(),
            Act::Mish => {
                let sp = if xd > 20.0 { xd } else { xd.exp().ln_1p() };
                let th = sp.tanh();
                th + xd * (1.0 - th * th) * s
            }
            Act::Softplus => s,
        };
        d as f32
    }
}

fn same_len(what: &str, a: usize, b: usize) -> Result<()> {
    if a != b {
        return Err(PolicyError::ShapeMismatch {
            name: what.to_string(),
            expected: vec![a],
            got: vec![b],
        });
    }
    Ok(())
}

/// `out[i] += x[i] · s[a·C + c]` for `i = ((a·B + b)·C + c)·D + d`: the product of
/// [`Tape::mul_broadcast`] added into `out`, in blocks of C runs of D values, each run
/// scaled by its factor.
fn scale_blocks(out: &mut [f32], x: &[f32], s: &[f32], [nb, nc, nd]: [usize; 3]) {
    let block = nc * nd;
    if block == 0 {
        return;
    }
    for (ab, (ob, xb)) in out
        .chunks_exact_mut(block)
        .zip(x.chunks_exact(block))
        .enumerate()
    {
        let f = &s[(ab / nb) * nc..(ab / nb + 1) * nc];
        if nd == 1 {
            for ((o, xi), fi) in ob.iter_mut().zip(xb).zip(f) {
                *o += xi * fi;
            }
            continue;
        }
        for ((oc, xc), fi) in ob.chunks_exact_mut(nd).zip(xb.chunks_exact(nd)).zip(f) {
            for (o, xi) in oc.iter_mut().zip(xc) {
                *o += xi * fi;
            }
        }
    }
}

/// The same product appended to `out` (a first gradient contribution or the forward
/// value, written once instead of into zeros).
fn scale_blocks_into(out: &mut Vec<f32>, x: &[f32], s: &[f32], [nb, nc, nd]: [usize; 3]) {
    let block = nc * nd;
    if block == 0 {
        return;
    }
    for (ab, xb) in x.chunks_exact(block).enumerate() {
        let f = &s[(ab / nb) * nc..(ab / nb + 1) * nc];
        if nd == 1 {
            out.extend(xb.iter().zip(f).map(|(xi, fi)| xi * fi));
            continue;
        }
        for (xc, fi) in xb.chunks_exact(nd).zip(f) {
            out.extend(xc.iter().map(|xi| xi * fi));
        }
    }
}

fn rows(what: &str, len: usize, row: usize) -> Result<usize> {
    crate::layers::rows_of(what, len, row)
}

impl Tape {
    /// `a + b` (same length; the result has `a`'s shape).
    pub fn add(&mut self, a: Var, b: Var) -> Result<Var> {
        same_len("add operands", self.value(a).len(), self.value(b).len())?;
        let v = self
            .value(a)
            .iter()
            .zip(self.value(b))
            .map(|(x, y)| x + y)
            .collect();
        let shape = self.shape(a).to_vec();
        Ok(self.push(
            v,
            shape,
            &[a, b],
            Some(Box::new(move |_, g, gr| {
                gr.add(a, g);
                gr.add(b, g);
            })),
        ))
    }

    /// `a ⊙ b` (same length; the result has `a`'s shape).
    pub fn mul(&mut self, a: Var, b: Var) -> Result<Var> {
        same_len("mul operands", self.value(a).len(), self.value(b).len())?;
        let v = self
            .value(a)
            .iter()
            .zip(self.value(b))
            .map(|(x, y)| x * y)
            .collect();
        let shape = self.shape(a).to_vec();
        Ok(self.push(
            v,
            shape,
            &[a, b],
            Some(Box::new(move |vals, g, gr| {
                gr.add_iter(a, g.iter().zip(vals.get(b)).map(|(g, y)| g * y));
                gr.add_iter(b, g.iter().zip(vals.get(a)).map(|(g, x)| g * x));
            })),
        ))
    }

    /// `s · a`.
    pub fn scale(&mut self, a: Var, s: f32) -> Var {
        let v = self.value(a).iter().map(|x| x * s).collect();
        let shape = self.shape(a).to_vec();
        self.push(
            v,
            shape,
            &[a],
            Some(Box::new(move |_, g, gr| {
                gr.add_iter(a, g.iter().map(|y| s * y));
            })),
        )
    }

    /// The activation `f` applied element-wise.
    pub fn act(&mut self, a: Var, f: Act) -> Var {
        let v = f.apply_all(self.value(a));
        let shape = self.shape(a).to_vec();
        self.push(
            v,
            shape,
            &[a],
            Some(Box::new(move |vals, g, gr| {
                let x = vals.get(a);
                gr.add_iter(a, g.iter().zip(x).map(|(gi, xi)| gi * f.derivative(*xi)));
            })),
        )
    }

    /// The same values under another shape (same number of values).
    pub fn reshape(&mut self, a: Var, shape: &[usize]) -> Result<Var> {
        check_shape("reshape", self.value(a).len(), shape)?;
        Ok(self.push_reshaped(a, shape.to_vec()))
    }

    /// The sum of all values, shape `[1]`.
    pub fn sum(&mut self, a: Var) -> Var {
        let s = self.value(a).iter().map(|&x| f64::from(x)).sum::<f64>() as f32;
        self.push(
            vec![s],
            vec![1],
            &[a],
            Some(Box::new(move |_, g, gr| {
                if let Some(acc) = gr.acc(a) {
                    for x in acc.iter_mut() {
                        *x += g[0];
                    }
                }
            })),
        )
    }

    /// A dense layer on every row: `x` `[rows, inp]`, `w` `[out, inp]` (PyTorch layout),
    /// optional `b` `[out]`; returns `[rows, out]`.
    pub fn linear(&mut self, x: Var, w: Var, b: Option<Var>) -> Result<Var> {
        let ws = self.shape(w).to_vec();
        if ws.len() != 2 {
            return Err(PolicyError::ShapeMismatch {
                name: "linear weight".into(),
                expected: vec![0, 0],
                got: ws,
            });
        }
        let (out, inp) = (ws[0], ws[1]);
        let n = rows("linear input", self.value(x).len(), inp)?;
        let mut y = vec![0.0f32; n * out];
        if let Some(b) = b {
            same_len("linear bias", out, self.value(b).len())?;
            let bv = self.value(b);
            for r in y.chunks_exact_mut(out.max(1)) {
                r.copy_from_slice(bv);
            }
        }
        gemm_acc(
            Strided::row_major(self.value(x), 0, n, inp),
            Strided::row_major(self.value(w), 0, out, inp).t(),
            &mut y,
            0,
            out,
        )?;
        let mut parents = vec![x, w];
        parents.extend(b);
        Ok(self.push(
            y,
            vec![n, out],
            &parents,
            Some(Box::new(move |vals, g, gr| {
                if let Some(acc) = gr.acc(x) {
                    // dx = g · W
                    let _ = gemm_acc(
                        Strided::row_major(g, 0, n, out),
                        Strided::row_major(vals.get(w), 0, out, inp),
                        acc,
                        0,
                        inp,
                    );
                }
                if let Some(acc) = gr.acc(w) {
                    // dW = gᵀ · x
                    let _ = gemm_acc(
                        Strided::row_major(g, 0, n, out).t(),
                        Strided::row_major(vals.get(x), 0, n, inp),
                        acc,
                        0,
                        inp,
                    );
                }
                if let Some(b) = b {
                    if let Some(acc) = gr.acc(b) {
                        for r in g.chunks_exact(out.max(1)) {
                            for (a, v) in acc.iter_mut().zip(r) {
                                *a += v;
                            }
                        }
                    }
                }
            })),
        ))
    }

    /// Rows `idx` of `x` seen as rows of `row` values: `[idx.len(), row]`.
    pub fn gather_rows(&mut self, x: Var, row: usize, idx: &[usize]) -> Result<Var> {
        let n = rows("gather input", self.value(x).len(), row)?;
        check_indices("gathered row", idx, n)?;
        let xv = self.value(x);
        let mut y = Vec::with_capacity(idx.len() * row);
        for &i in idx {
            y.extend_from_slice(&xv[i * row..(i + 1) * row]);
        }
        let idx: Arc<[usize]> = idx.into();
        Ok(self.push(
            y,
            vec![idx.len(), row],
            &[x],
            Some(Box::new(move |_, g, gr| {
                if let Some(acc) = gr.acc(x) {
                    for (e, &i) in idx.iter().enumerate() {
                        for (a, v) in acc[i * row..(i + 1) * row]
                            .iter_mut()
                            .zip(&g[e * row..(e + 1) * row])
                        {
                            *a += v;
                        }
                    }
                }
            })),
        ))
    }

    /// Sums row e of `x` (rows of `row` values) into output row `idx[e]`: `[n_out, row]`.
    pub fn scatter_add_rows(
        &mut self,
        x: Var,
        row: usize,
        idx: &[usize],
        n_out: usize,
    ) -> Result<Var> {
        let n = rows("scatter input", self.value(x).len(), row)?;
        same_len("scatter indices", n, idx.len())?;
        check_indices("scatter destination", idx, n_out)?;
        let xv = self.value(x);
        let mut y = vec![0.0f32; n_out * row];
        for (e, &i) in idx.iter().enumerate() {
            for (a, v) in y[i * row..(i + 1) * row]
                .iter_mut()
                .zip(&xv[e * row..(e + 1) * row])
            {
                *a += v;
            }
        }
        let idx: Arc<[usize]> = idx.into();
        Ok(self.push(
            y,
            vec![n_out, row],
            &[x],
            Some(Box::new(move |_, g, gr| {
                if let Some(acc) = gr.acc(x) {
                    for (e, &i) in idx.iter().enumerate() {
                        for (a, v) in acc[e * row..(e + 1) * row]
                            .iter_mut()
                            .zip(&g[i * row..(i + 1) * row])
                        {
                            *a += v;
                        }
                    }
                }
            })),
        ))
    }

    /// Columns `range` of `x` seen as rows of `cols` values: `[rows, range.len()]`.
    pub fn slice_cols(
        &mut self,
        x: Var,
        cols: usize,
        range: std::ops::Range<usize>,
    ) -> Result<Var> {
        let n = rows("column slice input", self.value(x).len(), cols)?;
        if range.start > range.end || range.end > cols {
            return Err(PolicyError::IndexOutOfRange {
                name: "column slice end".into(),
                value: range.end as i64,
                len: cols,
            });
        }
        let w = range.len();
        let xv = self.value(x);
        let mut y = Vec::with_capacity(n * w);
        for r in xv.chunks_exact(cols) {
            y.extend_from_slice(&r[range.clone()]);
        }
        let start = range.start;
        Ok(self.push(
            y,
            vec![n, w],
            &[x],
            Some(Box::new(move |_, g, gr| {
                gr.add_cols(x, cols, start, g.chunks_exact(w.max(1)));
            })),
        ))
    }

    /// Row-wise concatenation: row r of `a` (`ca` values) then row r of `b` (`cb` values).
    pub fn concat_cols(&mut self, a: Var, ca: usize, b: Var, cb: usize) -> Result<Var> {
        let n = rows("concat left", self.value(a).len(), ca)?;
        same_len(
            "concat right rows",
            n,
            rows("concat right", self.value(b).len(), cb)?,
        )?;
        let (av, bv) = (self.value(a), self.value(b));
        let mut y = Vec::with_capacity(n * (ca + cb));
        for r in 0..n {
            y.extend_from_slice(&av[r * ca..(r + 1) * ca]);
            y.extend_from_slice(&bv[r * cb..(r + 1) * cb]);
        }
        let c = ca + cb;
        Ok(self.push(
            y,
            vec![n, c],
            &[a, b],
            Some(Box::new(move |_, g, gr| {
                gr.add_cols(a, ca, 0, (0..n).map(|r| &g[r * c..r * c + ca]));
                gr.add_cols(b, cb, 0, (0..n).map(|r| &g[r * c + ca..(r + 1) * c]));
            })),
        ))
    }

    /// Constant linear maps over coefficient rows: `x` `[B, k_in, c]` and `mats` either
    /// `[B, k_out, k_in]` (one matrix per batch item: edge-frame rotations) or `[k_out, k_in]`
    /// (one shared matrix: S2 grid projections); returns `[B, k_out, c]` with
    /// `y[b] = M[b] · x[b]`. The matrices are not trained.
    pub fn const_matmul(
        &mut self,
        x: Var,
        mats: Arc<[f32]>,
        (k_out, k_in, c): (usize, usize, usize),
    ) -> Result<Var> {
        let per = k_out * k_in;
        let nb = rows("const matmul input", self.value(x).len(), k_in * c)?;
        let shared = mats.len() == per && nb != 1;
        if !shared && mats.len() != nb * per {
            return Err(PolicyError::ShapeMismatch {
                name: "const matmul matrices".into(),
                expected: vec![nb, k_out, k_in],
                got: vec![mats.len()],
            });
        }
        let m_off = move |b: usize| if shared { 0 } else { b * per };
        let xv = self.value(x);
        let mut y = vec![0.0f32; nb * k_out * c];
        for b in 0..nb {
            gemm_acc(
                Strided::row_major(&mats, m_off(b), k_out, k_in),
                Strided::row_major(xv, b * k_in * c, k_in, c),
                &mut y,
                b * k_out * c,
                c,
            )?;
        }
        Ok(self.push(
            y,
            vec![nb, k_out, c],
            &[x],
            Some(Box::new(move |_, g, gr| {
                if let Some(acc) = gr.acc(x) {
                    for b in 0..nb {
                        let _ = gemm_acc(
                            Strided::row_major(&mats, m_off(b), k_out, k_in).t(),
                            Strided::row_major(g, b * k_out * c, k_out, c),
                            acc,
                            b * k_in * c,
                            c,
                        );
                    }
                }
            })),
        ))
    }

    /// Each row of `x` `[n·r, c]` (r rows per node) multiplied element-wise by its node's
    /// row of `s` `[n, c]`.
    pub fn mul_per_node(&mut self, x: Var, s: Var, c: usize) -> Result<Var> {
        let n = rows("per-node factors", self.value(s).len(), c)?;
        let rows_x = rows("per-node product input", self.value(x).len(), c)?;
        if n == 0 || rows_x % n != 0 {
            return Err(PolicyError::ShapeMismatch {
                name: "per-node product input (rows must split evenly over the nodes)".into(),
                expected: vec![n, 0, c],
                got: vec![rows_x, c],
            });
        }
        self.mul_broadcast(x, s, [n, rows_x / n, c, 1])
    }

    /// `x` `[A, B, C, D]` times `s` `[A, C]` broadcast over B and D:
    /// `y[a, b, c, d] = x[a, b, c, d] · s[a, c]` (a gate per node and channel over the node's
    /// coefficient rows, an attention weight per edge and head over the edge's rows and
    /// value channels). The values and gradients are those of `mul` with `s` gathered to
    /// `x`'s shape, summed in the same order, without the gathered copy and its indices.
    pub fn mul_broadcast(&mut self, x: Var, s: Var, dims: [usize; 4]) -> Result<Var> {
        let [na, nb, nc, nd] = dims;
        same_len(
            "broadcast product input",
            na * nb * nc * nd,
            self.value(x).len(),
        )?;
        same_len("broadcast product factors", na * nc, self.value(s).len())?;
        let block = nc * nd;
        let (xv, sv) = (self.value(x), self.value(s));
        let mut y = Vec::with_capacity(xv.len());
        scale_blocks_into(&mut y, xv, sv, [nb, nc, nd]);
        let shape = self.shape(x).to_vec();
        Ok(self.push(
            y,
            shape,
            &[x, s],
            Some(Box::new(move |vals, g, gr| {
                if block == 0 {
                    return;
                }
                if gr.starts(x) {
                    let mut fresh = Vec::with_capacity(g.len());
                    scale_blocks_into(&mut fresh, g, vals.get(s), [nb, nc, nd]);
                    gr.add_owned(x, fresh);
                } else if let Some(acc) = gr.acc(x) {
                    scale_blocks(acc, g, vals.get(s), [nb, nc, nd]);
                }
                if let Some(acc) = gr.acc(s) {
                    let xv = vals.get(x);
                    for (ab, (xb, gb)) in xv
                        .chunks_exact(block)
                        .zip(g.chunks_exact(block))
                        .enumerate()
                    {
                        let ar = &mut acc[(ab / nb) * nc..(ab / nb + 1) * nc];
                        if nd == 1 {
                            for ((a, xi), gi) in ar.iter_mut().zip(xb).zip(gb) {
                                *a += gi * xi;
                            }
                        } else {
                            for ((a, xc), gc) in ar
                                .iter_mut()
                                .zip(xb.chunks_exact(nd))
                                .zip(gb.chunks_exact(nd))
                            {
                                // Added one product at a time, in order: the sums of the
                                // gathered product's backward, bit for bit.
                                let mut sum = *a;
                                for (gi, xi) in gc.iter().zip(xc) {
                                    sum += gi * xi;
                                }
                                *a = sum;
                            }
                        }
                    }
                }
            })),
        ))
    }

    /// The separable S2 activation on `x` `[n, grid.reduced.len(), c]` with `gating` `[n,
    /// c]`, as [`crate::layers::separable_s2_activation`]: l = 0 becomes SiLU(gating); l > 0
    /// goes through the grid (to grid, SiLU, back), or with a gated grid is multiplied by
    /// σ(gating).
    pub fn separable_s2_activation(
        &mut self,
        grid: &S2Grid,
        gating: Var,
        x: Var,
        c: usize,
    ) -> Result<Var> {
        let nr = grid.reduced.len();
        let n = rows("S2 activation input", self.value(x).len(), nr * c)?;
        same_len("S2 activation gating", n * c, self.value(gating).len())?;
        let scalars = self.act(gating, Act::Silu);
        let higher = if grid.gated {
            let rest = self.slice_cols(x, nr * c, c..nr * c)?;
            let sig = self.act(gating, Act::Sigmoid);
            self.mul_per_node(rest, sig, c)?
        } else {
            let np = grid.num_points();
            let to: Arc<[f32]> = grid.to_grid.iter().map(|v| *v as f32).collect();
            let mut from_t = vec![0.0f32; nr * np];
            for p in 0..np {
                for i in 0..nr {
                    from_t[i * np + p] = grid.from_grid[p * nr + i] as f32;
                }
            }
            let on_grid = self.const_matmul(x, to, (np, nr, c))?;
            let act = self.act(on_grid, Act::Silu);
            let back = self.const_matmul(act, from_t.into(), (nr, np, c))?;
            self.slice_cols(back, nr * c, c..nr * c)?
        };
        let y = self.concat_cols(scalars, c, higher, (nr - 1) * c)?;
        self.reshape(y, &[n, nr, c])
    }
}

#[cfg(test)]
mod tests {
    use super::Act;

    #[test]
    fn activations_of_whole_slices_equal_one_value_at_a_time_bit_for_bit() {
        // Every 4099th f32 and the exp's edges (the vector kernels' own samples), in a
        // length with a remainder after the eight-value vectors.
        let mut x = crate::vector_exp::tests::samples();
        x.extend(std::iter::repeat_n(0.75f32, 8 - x.len() % 8 + 3));
        assert_eq!(x.len() % 8, 3);
        for act in [
            Act::Silu,
            Act::Sigmoid,
            Act::Gelu,
            Act::SmoothLeakyRelu(0.2),
            Act::Exp,
            Act::Mish,
            Act::Softplus,
        ] {
            let all = act.apply_all(&x);
            assert_eq!(all.len(), x.len());
            for (&xi, y) in x.iter().zip(&all) {
                let want = act.apply(xi);
                assert!(
                    y.to_bits() == want.to_bits() || (y.is_nan() && want.is_nan()),
                    "{act:?}({xi}) = {y}, one at a time {want}"
                );
            }
        }
    }
}
