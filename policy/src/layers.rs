//! Basic layers: dense linear, LayerNorm, the equivariant per-degree linear (`SO3_LinearV2`),
//! the equivariant RMS norm (`rms_norm_sh`), the Gaussian radial basis, the radial MLP, the
//! FiLM-conditioned equivariant linear (`SO3_FiLM_Linear`) and the scalar activations.
//!
//! Spec: fixtures README ("rms_norm_sh", "RBF", "FiLM") and the `linear_norm_rbf` sidecar.
//! Embeddings are row-major `[nodes, (lmax+1)², channels]` `f32` slices; dot products
//! accumulate in `f64`.

use std::sync::Arc;

use crate::error::{PolicyError, Result};
use crate::matmul::{gemm_acc, Strided};
use crate::so3::num_coefficients;
use crate::weights::Scope;

mod sparse_rbf;

/// Checks that `len` equals the product of `shape`, naming the tensor otherwise.
pub fn check_len(name: &str, len: usize, shape: &[usize]) -> Result<()> {
    if len != shape.iter().product::<usize>() {
        return Err(PolicyError::ShapeMismatch {
            name: name.to_string(),
            expected: shape.to_vec(),
            got: vec![len],
        });
    }
    Ok(())
}

/// An error naming the first of `idx` that is not below `len` (`name` says what indexes
/// what).
pub fn check_indices<'a>(
    name: &str,
    idx: impl IntoIterator<Item = &'a usize>,
    len: usize,
) -> Result<()> {
    match idx.into_iter().find(|&&i| i >= len) {
        Some(&bad) => Err(PolicyError::IndexOutOfRange {
            name: name.into(),
            value: bad as i64,
            len,
        }),
        None => Ok(()),
    }
}

/// The degree l of full-basis coefficient index `i` (i = l² + m + l).
pub fn degree_of(i: usize) -> usize {
    let mut l = 0;
    while (l + 1) * (l + 1) <= i {
        l += 1;
    }
    l
}

/// The degree l with (l+1)² = `k`, or an error naming `what`.
pub fn lmax_of(what: &str, k: usize) -> Result<usize> {
    let l = degree_of(k.saturating_sub(1));
    if num_coefficients(l) != k {
        return Err(PolicyError::ShapeMismatch {
            name: what.to_string(),
            expected: vec![num_coefficients(l)],
            got: vec![k],
        });
    }
    Ok(l)
}

/// SiLU x·σ(x).
pub fn silu(x: f32) -> f32 {
    x / (1.0 + (-x).exp())
}

/// Logistic sigmoid.
pub fn sigmoid(x: f32) -> f32 {
    1.0 / (1.0 + (-x).exp())
}

/// Softplus log(1 + eˣ) (linear above 20, as PyTorch).
pub fn softplus(x: f32) -> f32 {
    if x > 20.0 {
        x
    } else {
        x.exp().ln_1p()
    }
}

/// Mish x·tanh(softplus(x)).
pub fn mish(x: f32) -> f32 {
    x * softplus(x).tanh()
}

/// The reference's smooth leaky ReLU with slope `alpha`: ((1+α)/2)x + ((1−α)/2)x(2σ(x) − 1).
pub fn smooth_leaky_relu(x: f32, alpha: f32) -> f32 {
    smooth_leaky_relu_of(x, sigmoid(x), alpha)
}

/// [`smooth_leaky_relu`] of `x` given its sigmoid `sig` = σ(x) (e.g. from
/// [`crate::vector_exp::sigmoid_in_place`]): the same bits.
pub fn smooth_leaky_relu_of(x: f32, sig: f32, alpha: f32) -> f32 {
    0.5 * (1.0 + alpha) * x + 0.5 * (1.0 - alpha) * x * (2.0 * sig - 1.0)
}

/// Exact (erf) GELU.
pub fn gelu(x: f32) -> f32 {
    let xd = f64::from(x);
    (0.5 * xd * (1.0 + erf(xd / std::f64::consts::SQRT_2))) as f32
}

/// The error function (Abramowitz–Stegun 7.1.26 is too coarse; this uses a series / continued
/// fraction with ~1e-15 accuracy).
pub fn erf(x: f64) -> f64 {
    let ax = x.abs();
    // Zero is its own value; the series below would add zero terms forever (every term 0,
    // so none is ever below 1e-17 of the sum), hanging a forward pass on an exact 0.
    if ax == 0.0 {
        return x;
    }
    let v = if ax < 2.5 {
        // Taylor series: erf x = 2/√π Σ (−1)ⁿ x^(2n+1) / (n! (2n+1)).
        let mut sum = 0.0;
        let mut term = ax;
        let x2 = ax * ax;
        let mut n = 0.0;
        loop {
            let t = term / (2.0 * n + 1.0);
            sum += t;
            if t.abs() < 1e-17 * sum.abs() {
                break;
            }
            n += 1.0;
            term *= -x2 / n;
        }
        sum * 2.0 / std::f64::consts::PI.sqrt()
    } else {
        // Continued fraction for erfc, evaluated bottom-up.
        let mut f = 0.0;
        for k in (1..60).rev() {
            f = (k as f64 / 2.0) / (ax + f);
        }
        1.0 - (-ax * ax).exp() / std::f64::consts::PI.sqrt() / (ax + f)
    };
    if x < 0.0 {
        -v
    } else {
        v
    }
}

/// Σ_i a[i] b[i], accumulated in f64 over 4 interleaved partial sums (vectorisable).
fn dot(a: &[f32], b: &[f32]) -> f32 {
    let mut acc = [0.0f64; 4];
    let ca = a.chunks_exact(4);
    let cb = b.chunks_exact(4);
    let (ra, rb) = (ca.remainder(), cb.remainder());
    for (x, y) in ca.zip(cb) {
        for k in 0..4 {
            acc[k] += f64::from(x[k]) * f64::from(y[k]);
        }
    }
    let mut s = (acc[0] + acc[1]) + (acc[2] + acc[3]);
    for (x, y) in ra.iter().zip(rb) {
        s += f64::from(*x) * f64::from(*y);
    }
    s as f32
}

/// `y[r, :] += Σ_i x[r, i] · wt[i, :]` for every row r of `x` `[rows, inp]`, with `wt`
/// `[inp, out]` and `y` `[rows, out]`, in f32. Dense inputs go through one cache-blocked
/// matrix product ([`crate::matmul::gemm_acc`]); mostly-zero inputs (the narrow field
/// radial basis) through a kernel that skips the zeros.
pub fn axpy_rows(x: &[f32], inp: usize, wt: &[f32], out: usize, y: &mut [f32]) -> Result<()> {
    if inp == 0 || out == 0 {
        return Ok(());
    }
    let rows = rows_of("matrix product input", x.len(), inp)?;
    // Sparse or dense: judged on the first rows.
    let probe = &x[..x.len().min(4 * inp)];
    let zeros = probe.iter().filter(|v| **v == 0.0).count();
    if 2 * zeros > probe.len() {
        axpy_rows_sparse(x, inp, wt, out, y);
        return Ok(());
    }
    gemm_acc(
        Strided::row_major(x, 0, rows, inp),
        Strided::row_major(wt, 0, inp, out),
        y,
        0,
        out,
    )
}

/// Outputs accumulated together by [`Linear::forward_sparse`] (one AVX-512 register).
const SPARSE_BLOCK: usize = 16;

/// Inputs [`axpy_rows_sparse`] tests for zero together.
const ZERO_BLOCK: usize = 16;

/// [`axpy_rows`] skipping zero inputs: each row is scanned in blocks of 16 values, blocks of
/// zeros are passed over, and every non-zero input adds its weight row.
fn axpy_rows_sparse(x: &[f32], inp: usize, wt: &[f32], out: usize, y: &mut [f32]) {
    if out.is_multiple_of(16) {
        // Whole vectors of outputs: see [`SparseAxpy`].
        pulp::Arch::new().dispatch(SparseAxpy { x, inp, wt, out, y });
        return;
    }
    const BLOCK: usize = ZERO_BLOCK;
    for (xr, yr) in x.chunks_exact(inp).zip(y.chunks_exact_mut(out)) {
        for (bi, xb) in xr.chunks(BLOCK).enumerate() {
            if xb.iter().all(|v| *v == 0.0) {
                continue;
            }
            for (j, &xi) in xb.iter().enumerate() {
                if xi == 0.0 {
                    continue;
                }
                let i = bi * BLOCK + j;
                for (a, b) in yr.iter_mut().zip(&wt[i * out..(i + 1) * out]) {
                    *a += xi * b;
                }
            }
        }
    }
}

/// [`axpy_rows_sparse`] for outputs in whole vectors: each output row held in registers (up
/// to eight vectors at a time) while its row of `x` is scanned, each non-zero input's
/// product then sum added in input order, as the plain loop adds them (bit for bit), the
/// output loaded and stored once instead of once per input.
struct SparseAxpy<'a> {
    x: &'a [f32],
    inp: usize,
    wt: &'a [f32],
    out: usize,
    y: &'a mut [f32],
}

impl pulp::WithSimd for SparseAxpy<'_> {
    type Output = ();

    #[inline(always)]
    fn with_simd<S: pulp::Simd>(self, simd: S) {
        let SparseAxpy { x, inp, wt, out, y } = self;
        let ov = out / S::F32_LANES;
        let (wv, _) = S::as_simd_f32s(wt);
        for (xr, yr) in x.chunks_exact(inp).zip(y.chunks_exact_mut(out)) {
            let (yv, _) = S::as_mut_simd_f32s(yr);
            let mut v0 = 0;
            while v0 < ov {
                let at = (xr, wv, ov, v0);
                // No closure: it would not inherit the kernel's target features.
                v0 += match ov - v0 {
                    1 => sparse_axpy_block::<S, 1>(simd, at, yv),
                    2 => sparse_axpy_block::<S, 2>(simd, at, yv),
                    3 => sparse_axpy_block::<S, 3>(simd, at, yv),
                    4 => sparse_axpy_block::<S, 4>(simd, at, yv),
                    5 => sparse_axpy_block::<S, 5>(simd, at, yv),
                    6 => sparse_axpy_block::<S, 6>(simd, at, yv),
                    7 => sparse_axpy_block::<S, 7>(simd, at, yv),
                    _ => sparse_axpy_block::<S, 8>(simd, at, yv),
                };
            }
        }
    }
}

/// Output vectors `v0..v0 + V` of one row of [`SparseAxpy`] (`xr`: the input row, `wv`: the
/// weights, `ov` vectors per row); returns `V`.
#[inline(always)]
fn sparse_axpy_block<S: pulp::Simd, const V: usize>(
    simd: S,
    (xr, wv, ov, v0): (&[f32], &[S::f32s], usize, usize),
    yv: &mut [S::f32s],
) -> usize {
    let mut acc: [S::f32s; V] = std::array::from_fn(|v| yv[v0 + v]);
    for (bi, xb) in xr.chunks(ZERO_BLOCK).enumerate() {
        if xb.iter().all(|v| *v == 0.0) {
            continue;
        }
        for (j, &xi) in xb.iter().enumerate() {
            if xi == 0.0 {
                continue;
            }
            let xs = simd.splat_f32s(xi);
            let start = (bi * ZERO_BLOCK + j) * ov + v0;
            for (a, &w) in acc.iter_mut().zip(&wv[start..start + V]) {
                *a = simd.add_f32s(*a, simd.mul_f32s(xs, w));
            }
        }
    }
    yv[v0..v0 + V].copy_from_slice(&acc);
    V
}

/// The transpose of a row-major `[rows, cols]` matrix.
pub fn transpose(w: &[f32], rows: usize, cols: usize) -> Vec<f32> {
    let mut t = vec![0.0f32; w.len()];
    for r in 0..rows {
        for c in 0..cols {
            t[c * rows + r] = w[r * cols + c];
        }
    }
    t
}

/// Largest matrix (values) a [`Linear`] keeps a transposed copy of for batched rows (the
/// FiLM hypernetworks, used one row at a time, stay untransposed).
const MAX_TRANSPOSED: usize = 1 << 23;

/// A dense layer `y = W x + b` (PyTorch `nn.Linear`, weight `[out, in]`).
#[derive(Debug, Clone)]
pub struct Linear {
    /// Input features.
    pub inp: usize,
    /// Output features.
    pub out: usize,
    w: Vec<f32>,
    /// `[in, out]`, for batches of rows (None for very large matrices).
    wt: Option<Vec<f32>>,
    b: Option<Vec<f32>>,
}

impl Linear {
    /// Loads `weight` (and `bias` if `bias`) from `s`, taking the sizes from the weight.
    pub fn load(s: &Scope<'_>, bias: bool) -> Result<Self> {
        let shape = s.shape("weight", 2)?;
        Self::load_sized(s, shape[0], shape[1], bias)
    }

    /// Loads `weight` `[out, inp]` (and `bias` `[out]`) from `s`, checking the sizes.
    pub fn load_sized(s: &Scope<'_>, out: usize, inp: usize, bias: bool) -> Result<Self> {
        let w = s.f32("weight", &[out, inp])?;
        let b = if bias {
            Some(s.f32("bias", &[out])?)
        } else {
            None
        };
        Ok(Self::new(inp, out, w, b))
    }

    fn new(inp: usize, out: usize, w: Vec<f32>, b: Option<Vec<f32>>) -> Self {
        let wt = (w.len() <= MAX_TRANSPOSED).then(|| transpose(&w, out, inp));
        Self { inp, out, w, wt, b }
    }

    /// Builds a layer from raw values (weight `[out, inp]`).
    pub fn from_parts(out: usize, inp: usize, w: Vec<f32>, b: Option<Vec<f32>>) -> Result<Self> {
        check_len("linear weight", w.len(), &[out, inp])?;
        if let Some(b) = &b {
            check_len("linear bias", b.len(), &[out])?;
        }
        Ok(Self::new(inp, out, w, b))
    }

    /// The weight `[out, inp]`, row-major.
    pub fn weights(&self) -> &[f32] {
        &self.w
    }

    /// The layer restricted to the inputs `keep` (the others taken as always zero).
    pub fn select_inputs(&self, keep: &[usize]) -> Result<Self> {
        check_indices("linear input to keep", keep, self.inp)?;
        let w = (0..self.out)
            .flat_map(|o| keep.iter().map(move |&i| (o, i)))
            .map(|(o, i)| self.w[o * self.inp + i])
            .collect();
        Ok(Self::new(keep.len(), self.out, w, self.b.clone()))
    }

    /// The layer restricted to the outputs `keep`.
    pub fn select_outputs(&self, keep: &[usize]) -> Result<Self> {
        check_indices("linear output to keep", keep, self.out)?;
        let w = keep
            .iter()
            .flat_map(|&o| self.w[o * self.inp..(o + 1) * self.inp].iter().copied())
            .collect();
        let b = self
            .b
            .as_ref()
            .map(|b| keep.iter().map(|&o| b[o]).collect());
        Ok(Self::new(self.inp, keep.len(), w, b))
    }

    /// `rows` copies of the bias (zeros without one), for the products to accumulate onto:
    /// no zero fill that the bias would overwrite.
    fn bias_rows(&self, rows: usize) -> Vec<f32> {
        match &self.b {
            Some(b) => b.repeat(rows),
            None => vec![0.0; rows * self.out],
        }
    }

    /// Applies the layer to compressed rows of `cols` inputs (row r: entries
    /// `ptr[r]..ptr[r + 1]` of `idx`, `val`).
    pub fn forward_sparse(
        &self,
        cols: usize,
        ptr: &[usize],
        idx: &[u32],
        val: &[f32],
    ) -> Result<Vec<f32>> {
        let bad = |got: usize| PolicyError::ShapeMismatch {
            name: "sparse linear input".into(),
            expected: vec![self.inp],
            got: vec![got],
        };
        if cols != self.inp {
            return Err(bad(cols));
        }
        let rows = ptr.len().saturating_sub(1);
        // Every offset and column checked once, so the accumulation below runs unchecked
        // loops the compiler can keep in registers.
        let nnz = ptr.last().copied().unwrap_or(0);
        if ptr.windows(2).any(|w| w[0] > w[1]) || nnz > idx.len() || nnz > val.len() {
            return Err(bad(nnz));
        }
        if let Some(&i) = idx[..nnz].iter().find(|&&i| i as usize >= self.inp) {
            return Err(bad(i as usize));
        }
        let mut y = self.bias_rows(rows);
        let Some(wt) = &self.wt else {
            for (w, yr) in ptr.windows(2).zip(y.chunks_exact_mut(self.out)) {
                for (&i, &v) in idx[w[0]..w[1]].iter().zip(&val[w[0]..w[1]]) {
                    for (o, a) in yr.iter_mut().enumerate() {
                        *a += v * self.w[o * self.inp + i as usize];
                    }
                }
            }
            return Ok(y);
        };
        for (w, yr) in ptr.windows(2).zip(y.chunks_exact_mut(self.out)) {
            let (ix, vs) = (&idx[w[0]..w[1]], &val[w[0]..w[1]]);
            // Sixteen outputs at a time held in a local array across the row's entries:
            // each output still adds its products in entry order, as the plain loop did.
            let mut o0 = 0;
            for block in yr.chunks_mut(SPARSE_BLOCK) {
                if block.len() == SPARSE_BLOCK {
                    let mut acc = [0.0f32; SPARSE_BLOCK];
                    acc.copy_from_slice(block);
                    for (&i, &v) in ix.iter().zip(vs) {
                        let row = &wt[i as usize * self.out + o0..][..SPARSE_BLOCK];
                        for (a, b) in acc.iter_mut().zip(row) {
                            *a += v * b;
                        }
                    }
                    block.copy_from_slice(&acc);
                } else {
                    for (&i, &v) in ix.iter().zip(vs) {
                        let row = &wt[i as usize * self.out + o0..][..block.len()];
                        for (a, b) in block.iter_mut().zip(row) {
                            *a += v * b;
                        }
                    }
                }
                o0 += block.len();
            }
        }
        Ok(y)
    }

    /// Applies the layer to one row.
    pub fn forward_row(&self, x: &[f32], y: &mut [f32]) {
        for (o, yo) in y.iter_mut().enumerate().take(self.out) {
            let mut v = dot(&self.w[o * self.inp..(o + 1) * self.inp], x);
            if let Some(b) = &self.b {
                v += b[o];
            }
            *yo = v;
        }
    }

    /// [`Linear::forward_row`] of one row `x` with the outputs split over `threads` threads
    /// (at least 4096 each): the same values.
    pub fn forward_one_threads(&self, x: &[f32], threads: usize) -> Result<Vec<f32>> {
        check_len("linear input row", x.len(), &[self.inp])?;
        crate::parallel::map_ranges(self.out, threads.min(self.out / 4096), |r| {
            Ok(r.map(|o| {
                let v = dot(&self.w[o * self.inp..(o + 1) * self.inp], x);
                self.b.as_ref().map_or(v, |b| v + b[o])
            })
            .collect())
        })
    }

    /// Applies the layer to every row of `x` (`[rows, inp]` → `[rows, out]`).
    pub fn forward(&self, x: &[f32]) -> Result<Vec<f32>> {
        if self.inp == 0 || !x.len().is_multiple_of(self.inp) {
            return Err(PolicyError::ShapeMismatch {
                name: "linear input".into(),
                expected: vec![0, self.inp],
                got: vec![x.len()],
            });
        }
        let rows = x.len() / self.inp;
        if let (Some(wt), true) = (&self.wt, rows >= 2) {
            let mut y = self.bias_rows(rows);
            axpy_rows(x, self.inp, wt, self.out, &mut y)?;
            return Ok(y);
        }
        let mut y = vec![0.0; rows * self.out];
        for r in 0..rows {
            self.forward_row(
                &x[r * self.inp..(r + 1) * self.inp],
                &mut y[r * self.out..(r + 1) * self.out],
            );
        }
        Ok(y)
    }
}

/// Rows whose sums [`LayerNorm::apply`] interleaves.
const LAYER_NORM_GROUP: usize = 4;

/// LayerNorm over the last axis (eps 1e-5, affine).
#[derive(Debug, Clone)]
pub struct LayerNorm {
    /// Normalised width.
    pub dim: usize,
    w: Vec<f32>,
    b: Vec<f32>,
}

impl LayerNorm {
    /// Loads `weight` and `bias` `[dim]`.
    pub fn load(s: &Scope<'_>, dim: usize) -> Result<Self> {
        Ok(Self {
            dim,
            w: s.f32("weight", &[dim])?,
            b: s.f32("bias", &[dim])?,
        })
    }

    /// Normalises each row of `x` in place.
    pub fn apply(&self, x: &mut [f32]) {
        if self.dim == 0 {
            return;
        }
        // Rows a group at a time: each row's sums still add its values in order (the same
        // rounding), but the groups' independent sums overlap instead of each waiting on
        // its own chain of f64 additions (the per-edge norms are short rows, 8-64 wide).
        let mut groups = x.chunks_exact_mut(LAYER_NORM_GROUP * self.dim);
        for group in &mut groups {
            self.apply_group::<LAYER_NORM_GROUP>(group);
        }
        for row in groups.into_remainder().chunks_exact_mut(self.dim) {
            self.apply_group::<1>(row);
        }
    }

    /// [`LayerNorm::apply`] on `G` consecutive rows, their sums interleaved.
    fn apply_group<const G: usize>(&self, rows: &mut [f32]) {
        let (dim, n) = (self.dim, self.dim as f64);
        // -0.0: where `Iterator::sum` starts, so that even a row of negative zeros keeps its sign.
        let mut mean = [-0.0f64; G];
        for i in 0..dim {
            for (g, m) in mean.iter_mut().enumerate() {
                *m += f64::from(rows[g * dim + i]);
            }
        }
        mean.iter_mut().for_each(|m| *m /= n);
        let mut var = [-0.0f64; G];
        for i in 0..dim {
            for (g, v) in var.iter_mut().enumerate() {
                *v += (f64::from(rows[g * dim + i]) - mean[g]).powi(2);
            }
        }
        for (g, row) in rows.chunks_exact_mut(dim).enumerate() {
            let inv = 1.0 / (var[g] / n + 1e-5).sqrt();
            for (i, v) in row.iter_mut().enumerate() {
                *v = ((f64::from(*v) - mean[g]) * inv) as f32 * self.w[i] + self.b[i];
            }
        }
    }
}

/// `SO3_LinearV2`: a channel-mixing matrix per degree, bias on the l = 0 row only.
#[derive(Debug, Clone)]
pub struct So3Linear {
    /// Maximum degree.
    pub lmax: usize,
    /// Input channels.
    pub cin: usize,
    /// Output channels.
    pub cout: usize,
    /// `[(lmax+1), cout, cin]`.
    w: Vec<f32>,
    /// `[(lmax+1), cin, cout]`.
    wt: Vec<f32>,
    b: Vec<f32>,
}

/// Applies per-degree weights `wt` `[(lmax+1), cin, cout]` to `x` `[n, (lmax+1)², cin]`, with
/// `bias` on the l = 0 row: `[n, (lmax+1)², cout]`.
fn per_degree_apply(
    x: &[f32],
    lmax: usize,
    cin: usize,
    cout: usize,
    wt: &[f32],
    bias: &[f32],
) -> Result<Vec<f32>> {
    let k = num_coefficients(lmax);
    let n = rows_of("SO3 linear input", x.len(), k * cin)?;
    let mut y = vec![0.0; n * k * cout];
    for yn in y.chunks_exact_mut(k * cout) {
        yn[..cout].copy_from_slice(bias);
    }
    // One product per coefficient row i over all nodes: x[:, i, :] · wt[degree(i)].
    for i in 0..k {
        let l = degree_of(i);
        gemm_acc(
            Strided {
                row_stride: k * cin,
                ..Strided::row_major(x, i * cin, n, cin)
            },
            Strided::row_major(wt, l * cin * cout, cin, cout),
            &mut y,
            i * cout,
            k * cout,
        )?;
    }
    Ok(y)
}

/// Transposes each degree's `[cout, cin]` block of `[(lmax+1), cout, cin]`.
fn transpose_per_degree(w: &[f32], lmax: usize, cout: usize, cin: usize) -> Vec<f32> {
    let mut t = Vec::with_capacity(w.len());
    for l in 0..=lmax {
        t.extend(transpose(
            &w[l * cout * cin..(l + 1) * cout * cin],
            cout,
            cin,
        ));
    }
    t
}

impl So3Linear {
    /// Loads `weight` `[(lmax+1), cout, cin]` and `bias` `[cout]`, sizes from the weight.
    pub fn load(s: &Scope<'_>) -> Result<Self> {
        let shape = s.shape("weight", 3)?;
        let (lmax, cout, cin) = (shape[0].saturating_sub(1), shape[1], shape[2]);
        let w = s.f32("weight", &shape)?;
        Ok(Self {
            lmax,
            cin,
            cout,
            wt: transpose_per_degree(&w, lmax, cout, cin),
            w,
            b: s.f32("bias", &[cout])?,
        })
    }

    /// Applies the layer to `x` `[n, (lmax+1)², cin]`.
    pub fn forward(&self, x: &[f32]) -> Result<Vec<f32>> {
        per_degree_apply(x, self.lmax, self.cin, self.cout, &self.wt, &self.b)
    }

    /// The weights `[(lmax+1), cout, cin]`.
    pub fn weight(&self) -> &[f32] {
        &self.w
    }
}

/// The number of rows of a flat buffer of `len` values with `row` values per row.
pub fn rows_of(what: &str, len: usize, row: usize) -> Result<usize> {
    if row == 0 || !len.is_multiple_of(row) {
        return Err(PolicyError::ShapeMismatch {
            name: what.to_string(),
            expected: vec![0, row],
            got: vec![len],
        });
    }
    Ok(len / row)
}

/// The degree-balance weight of coefficient `i` of `rms_norm_sh`: 1/((2l+1)(lmax+1)).
pub fn balance_weight(i: usize, lmax: usize) -> f64 {
    1.0 / (((2 * degree_of(i) + 1) * (lmax + 1)) as f64)
}

/// The first half of `rms_norm_sh` on one node's `[(lmax+1)², c]` values: centres the l = 0
/// row over channels in place (kept in f32, as the reference) and returns the scale
/// (degree-balanced mean square + 1e-5)^(−1/2).
pub fn rms_centre_and_scale(node: &mut [f32], lmax: usize, c: usize) -> f64 {
    let mean = node[..c].iter().map(|v| f64::from(*v)).sum::<f64>() / c as f64;
    for v in &mut node[..c] {
        *v = (f64::from(*v) - mean) as f32;
    }
    let mut norm = 0.0f64;
    for (i, row) in node.chunks_exact(c).enumerate() {
        norm += balance_weight(i, lmax) * row.iter().map(|v| f64::from(*v).powi(2)).sum::<f64>();
    }
    norm /= c as f64;
    (norm + 1e-5).powf(-0.5)
}

/// Nodes whose sums [`RmsNormSh::forward`] interleaves.
const RMS_GROUP: usize = 4;

/// [`rms_centre_and_scale`] of the [`RMS_GROUP`] nodes of `group` at once: the same f64
/// sums in the same order per node (from −0, as `Iterator::sum`), interleaved so that the
/// nodes' chains of dependent additions overlap instead of each waiting on the last.
fn rms_centre_and_scale_group(group: &mut [f32], lmax: usize, c: usize) -> [f64; RMS_GROUP] {
    let len = group.len() / RMS_GROUP;
    let mut mean = [-0.0f64; RMS_GROUP];
    for ch in 0..c {
        for (g, m) in mean.iter_mut().enumerate() {
            *m += f64::from(group[g * len + ch]);
        }
    }
    for (g, m) in mean.iter_mut().enumerate() {
        *m /= c as f64;
        for v in &mut group[g * len..g * len + c] {
            *v = (f64::from(*v) - *m) as f32;
        }
    }
    let mut norm = [0.0f64; RMS_GROUP];
    for i in 0..len / c {
        let mut rows = [-0.0f64; RMS_GROUP];
        for ch in 0..c {
            for (g, r) in rows.iter_mut().enumerate() {
                *r += f64::from(group[g * len + i * c + ch]).powi(2);
            }
        }
        let w = balance_weight(i, lmax);
        for (n, r) in norm.iter_mut().zip(rows) {
            *n += w * r;
        }
    }
    norm.map(|n| (n / c as f64 + 1e-5).powf(-0.5))
}

/// `rms_norm_sh`: centre l = 0 over channels, divide by the degree-balanced RMS, scale per
/// (degree, channel), add a bias on l = 0.
#[derive(Debug, Clone)]
pub struct RmsNormSh {
    /// Maximum degree.
    pub lmax: usize,
    /// Channels.
    pub c: usize,
    w: Vec<f32>,
    b: Vec<f32>,
}

impl RmsNormSh {
    /// Loads `affine_weight` `[(lmax+1), c]` and `affine_bias` `[c]`.
    pub fn load(s: &Scope<'_>, lmax: usize, c: usize) -> Result<Self> {
        Ok(Self {
            lmax,
            c,
            w: s.f32("affine_weight", &[lmax + 1, c])?,
            b: s.f32("affine_bias", &[c])?,
        })
    }

    /// Loads with the sizes taken from `affine_weight`.
    pub fn load_any(s: &Scope<'_>) -> Result<Self> {
        let shape = s.shape("affine_weight", 2)?;
        Self::load(s, shape[0].saturating_sub(1), shape[1])
    }

    /// The degree-balance weight of coefficient `i`: 1/((2l+1)(lmax+1)).
    pub fn balance_weight(&self, i: usize) -> f64 {
        balance_weight(i, self.lmax)
    }

    /// Normalises `x` `[n, (lmax+1)², c]`.
    pub fn forward(&self, x: &[f32]) -> Result<Vec<f32>> {
        let k = num_coefficients(self.lmax);
        let c = self.c;
        let n = rows_of("RMS norm input", x.len(), k * c)?;
        let mut y = x.to_vec();
        let mut groups = y.chunks_exact_mut(RMS_GROUP * k * c);
        for group in &mut groups {
            let scales = rms_centre_and_scale_group(group, self.lmax, c);
            for (node, scale) in group.chunks_exact_mut(k * c).zip(scales) {
                self.scale_node(node, scale);
            }
        }
        for node in groups.into_remainder().chunks_exact_mut(k * c) {
            let scale = rms_centre_and_scale(node, self.lmax, c);
            self.scale_node(node, scale);
        }
        debug_assert_eq!(y.len(), n * k * c);
        Ok(y)
    }

    /// One centred node times its scale, then the affine map.
    fn scale_node(&self, node: &mut [f32], scale: f64) {
        let c = self.c;
        for (i, row) in node.chunks_exact_mut(c).enumerate() {
            let l = degree_of(i);
            for (ch, v) in row.iter_mut().enumerate() {
                *v = (f64::from(*v) * scale) as f32 * self.w[l * c + ch];
                if i == 0 {
                    *v += self.b[ch];
                }
            }
        }
    }
}

/// Largest z² of a Gaussian basis evaluated: beyond it a basis is below e^−23 ≈ 1e-10 of
/// its own peak and is taken as 0. A radial MLP's first layer sums a row's values times its
/// weights in f32, rounding at 6e-8 of the sum's terms; the bases overlap (the narrow field
/// heads' means lie about a width apart), so a row that holds any value holds one near its
/// peak, and the dropped tails move the sum by ~1e-10 of that term: far below its rounding
/// (a test bounds it against the uncut bases). The field heads' 1024 narrow bases then
/// evaluate about 27 values per distance instead of 52 (at z² ≤ 170, the cut once chosen
/// to drop only values below f32's normal range).
pub(crate) const RBF_Z2_MAX: f32 = 46.0;

/// Basis values below this are 0: near the inner cut-off the envelope makes values
/// subnormal, and a subnormal operand makes an x86 multiply about a hundred times slower;
/// a product below 1e-30 · |weight| cannot change an f32 sum that starts from its bias
/// (half an ulp of even 1e-20 is 5e-28).
pub(crate) const RBF_MIN_VALUE: f32 = 1e-30;

/// One Gaussian basis `weight · exp(−z²/2) · env · normalizer`, z = (u − mean)/std, in the
/// reference's f32 operation order; 0 beyond [`RBF_Z2_MAX`] and below [`RBF_MIN_VALUE`].
/// Inference and training both evaluate the basis with it.
pub(crate) fn rbf_basis_value(
    u: f32,
    mean: f32,
    std: f32,
    weight: f32,
    env: f32,
    normalizer: f32,
) -> f32 {
    let z = (u - mean) / std;
    let z2 = z * z;
    if z2 > RBF_Z2_MAX {
        return 0.0;
    }
    rbf_scaled(weight, (-0.5 * z2).exp(), env, normalizer)
}

/// A basis value from its exponential `e`: weight · e · envelope · normaliser, in this
/// order; a product below [`RBF_MIN_VALUE`] is 0, a NaN stays NaN (the comparison is false).
#[inline(always)]
pub(crate) fn rbf_scaled(weight: f32, e: f32, env: f32, normalizer: f32) -> f32 {
    let v = weight * e * env * normalizer;
    if v < RBF_MIN_VALUE {
        0.0
    } else {
        v
    }
}

/// The radial basis's soft inner cut-off: 0 for u <= 0, 1 for u >= 0.2 (1 − step(s),
/// s = (1 − u − 0.8)/0.2), in the reference's f32 operation order.
pub(crate) fn rbf_envelope(u: f32) -> f32 {
    if u > 0.5 {
        return 1.0;
    }
    let s = ((1.0 - u) - 0.8) / 0.2;
    let step = if s <= 0.0 {
        0.0
    } else if s >= 1.0 {
        1.0
    } else {
        4.0 * s.powi(3) - 3.0 * s.powi(4)
    };
    1.0 - step
}

/// The reference's Gaussian radial basis with a soft inner cut-off
/// (`GaussianRadialBasisLayerFiniteCutoff`). Evaluated in f32 in the reference's operation
/// order: the narrow field-head Gaussians (1024 of them) amplify rounding differences.
#[derive(Debug, Clone)]
pub struct GaussianRbf {
    /// Number of basis functions.
    pub num_basis: usize,
    offset: f32,
    span: f32,
    mean: Vec<f32>,
    std: Vec<f32>,
    weight: Vec<f32>,
    normalizer: f32,
    /// The bases sorted by mean, each with its parameters: the bases a distance can reach
    /// are a run of them, read without gathering from the per-index vectors.
    by_mean: Vec<SortedBasis>,
    /// Whether sorting by mean kept the index order (then a row's values need no sort).
    index_ordered: bool,
    /// Largest |u − mean| with a non-zero value, √[`RBF_Z2_MAX`] · max std (infinite:
    /// evaluate all).
    reach: f32,
    /// `by_mean` one column per parameter, for the vector scan of [`GaussianRbf::features`].
    columns: sparse_rbf::BasisColumns,
}

impl GaussianRbf {
    /// Loads `mean`, `std_logit` and `weight_logit` `[1, num_basis]`; offset = 0.01 · cutoff.
    pub fn load(s: &Scope<'_>, cutoff: f64) -> Result<Self> {
        let shape = s.shape("mean", 2)?;
        let k = shape[1];
        let mean = s.f32("mean", &[1, k])?;
        let std: Vec<f32> = s
            .f32("std_logit", &[1, k])?
            .into_iter()
            .map(|v| softplus(v) + 1e-5)
            .collect();
        let weight: Vec<f32> = s
            .f32("weight_logit", &[1, k])?
            .into_iter()
            .map(|v| sigmoid(v) * 4.0)
            .collect();
        let offset = 0.01 * cutoff;
        let max_std = std.iter().copied().fold(0.0f32, f32::max);
        let mut by_mean: Vec<SortedBasis> = (0..k)
            .map(|i| SortedBasis {
                mean: mean[i],
                std: std[i],
                weight: weight[i],
                index: i as u32,
                reach: Z2_REACH * std[i],
            })
            .collect();
        by_mean.sort_by(|a, b| a.mean.total_cmp(&b.mean));
        let index_ordered = by_mean.windows(2).all(|w| w[0].index < w[1].index);
        let finite = mean.iter().chain(&std).all(|v| v.is_finite());
        // Z2_REACH keeps a margin so rounding in z never hides a non-zero basis.
        let reach = if finite {
            Z2_REACH * max_std
        } else {
            f32::INFINITY
        };
        let columns = sparse_rbf::BasisColumns::new(&by_mean, reach);
        Ok(Self {
            num_basis: k,
            offset: offset as f32,
            span: (cutoff - offset) as f32,
            mean,
            std,
            weight,
            normalizer: (k as f64).sqrt() as f32,
            by_mean,
            index_ordered,
            reach,
            columns,
        })
    }

    /// The basis values of one distance, written to `out[..num_basis]`.
    pub fn eval_into(&self, d: f32, out: &mut [f32]) {
        let (u, env) = self.normalised(d);
        // Only the bases whose mean lies within `reach` of u have z² <= RBF_Z2_MAX; all
        // others are exactly 0 (the narrow field-head bases are sparse, so this skips most
        // of them).
        let out = &mut out[..self.num_basis];
        if !(self.reach.is_finite() && u.is_finite()) {
            for (i, o) in out.iter_mut().enumerate() {
                *o = self.value(i, u, env);
            }
            return;
        }
        out.iter_mut().for_each(|o| *o = 0.0);
        for b in self.within_reach(u) {
            out[b.index as usize] = b.value(u, env, self.normalizer);
        }
    }

    /// The bases, by mean, whose mean lies within `reach` of the normalised distance `u`:
    /// every other basis is exactly 0 there.
    fn within_reach(&self, u: f32) -> &[SortedBasis] {
        self.by_mean.get(self.reach_range(u)).unwrap_or_default()
    }

    /// [`GaussianRbf::within_reach`] as positions in mean order.
    fn reach_range(&self, u: f32) -> std::ops::Range<usize> {
        let lo = self.by_mean.partition_point(|b| b.mean < u - self.reach);
        let hi = self.by_mean.partition_point(|b| b.mean <= u + self.reach);
        lo..hi.max(lo)
    }

    /// A distance normalised to the basis's span, and its envelope.
    fn normalised(&self, d: f32) -> (f32, f32) {
        let u = (d - self.offset) / self.span;
        (u, rbf_envelope(u))
    }

    /// Basis `i` at normalised distance `u` with envelope `env`.
    fn value(&self, i: usize, u: f32, env: f32) -> f32 {
        rbf_basis_value(
            u,
            self.mean[i],
            self.std[i],
            self.weight[i],
            env,
            self.normalizer,
        )
    }

    /// The basis values of every distance as [`EdgeFeatures`]: compressed rows when the
    /// bases are narrow (at most a quarter of them reach any one distance), else dense.
    pub fn features(&self, d: &[f32]) -> EdgeFeatures {
        let window = self.by_mean.first().map_or(0, |first| {
            self.by_mean
                .partition_point(|b| b.mean <= first.mean + 2.0 * self.reach)
        });
        if !self.reach.is_finite() || 4 * window > self.num_basis || self.num_basis == 0 {
            return EdgeFeatures::Dense {
                cols: self.num_basis,
                values: self.forward(d),
            };
        }
        sparse_rbf::sparse_features(self, d)
    }

    /// The basis values of every distance, `[n, num_basis]`: each value as
    /// [`GaussianRbf::eval_into`] gives it, the exponentials of a block of rows at once
    /// ([`crate::vector_exp`]) instead of one library call per value.
    pub fn forward(&self, d: &[f32]) -> Vec<f32> {
        let k = self.num_basis;
        let mut y = vec![0.0; d.len() * k];
        if k == 0 {
            return y;
        }
        // Blocks of rows that stay in cache through the three passes.
        let rows = (8192 / k).max(1);
        for (block, d) in y.chunks_mut(rows * k).zip(d.chunks(rows)) {
            for (row, &di) in block.chunks_exact_mut(k).zip(d) {
                let (u, _) = self.normalised(di);
                for ((o, &mean), &std) in row.iter_mut().zip(&self.mean).zip(&self.std) {
                    let z = (u - mean) / std;
                    let z2 = z * z;
                    // A basis beyond RBF_Z2_MAX is 0 (`rbf_basis_value`): e^−∞ makes it so.
                    *o = if z2 > RBF_Z2_MAX {
                        f32::NEG_INFINITY
                    } else {
                        -0.5 * z2
                    };
                }
            }
            crate::vector_exp::exp_in_place(block);
            for (row, &di) in block.chunks_exact_mut(k).zip(d) {
                let (_, env) = self.normalised(di);
                for (o, &weight) in row.iter_mut().zip(&self.weight) {
                    *o = rbf_scaled(weight, *o, env, self.normalizer);
                }
            }
        }
        y
    }
}

/// One basis of [`GaussianRbf`] in its mean order, with its parameters.
#[derive(Debug, Clone, Copy)]
struct SortedBasis {
    mean: f32,
    std: f32,
    weight: f32,
    index: u32,
    /// Largest |u − mean| with z² <= [`RBF_Z2_MAX`], with [`Z2_REACH`]'s margin.
    reach: f32,
}

/// √[`RBF_Z2_MAX`] with 1 % to spare: beyond `Z2_REACH · std` the exact z² exceeds
/// 1.02 · RBF_Z2_MAX, which the f32 rounding of (u − mean)/std cannot bring below it, so
/// skipping such a basis never hides a non-zero value.
const Z2_REACH: f32 = 6.85;

impl SortedBasis {
    /// The basis at normalised distance `u` with envelope `env`.
    fn value(&self, u: f32, env: f32, normalizer: f32) -> f32 {
        rbf_basis_value(u, self.mean, self.std, self.weight, env, normalizer)
    }
}

/// Rows of invariant edge features (radial basis values), dense or in compressed rows.
#[derive(Debug, Clone, PartialEq)]
pub enum EdgeFeatures {
    /// Row-major `[rows, cols]`.
    Dense {
        /// Values per row.
        cols: usize,
        /// The values.
        values: Vec<f32>,
    },
    /// Only the non-zero values of each row (the narrow field-head bases).
    Sparse {
        /// Values per row (zeros included).
        cols: usize,
        /// Row r's entries are `ptr[r]..ptr[r + 1]` of `idx` and `val` (rows + 1 offsets).
        ptr: Vec<usize>,
        /// Column of each entry.
        idx: Vec<u32>,
        /// Value of each entry.
        val: Vec<f32>,
    },
}

/// A borrowed range of rows of [`EdgeFeatures`].
#[derive(Debug, Clone, Copy)]
pub enum EdgeFeaturesRef<'a> {
    /// Row-major `[rows, cols]`.
    Dense {
        /// Values per row.
        cols: usize,
        /// The values of the rows.
        values: &'a [f32],
    },
    /// Compressed rows: `ptr` holds rows + 1 offsets into `idx` and `val`.
    Sparse {
        /// Values per row (zeros included).
        cols: usize,
        /// Offsets of the rows' entries.
        ptr: &'a [usize],
        /// Columns of all entries.
        idx: &'a [u32],
        /// Values of all entries.
        val: &'a [f32],
    },
}

impl EdgeFeatures {
    /// Dense features of `rows` rows (an error if the length does not split evenly).
    pub fn dense(values: Vec<f32>, rows: usize) -> Result<Self> {
        let cols = if rows == 0 {
            0
        } else {
            rows_of("edge features", values.len(), rows)?
        };
        Ok(Self::Dense { cols, values })
    }

    /// All rows, borrowed.
    pub fn view(&self) -> EdgeFeaturesRef<'_> {
        match self {
            Self::Dense { cols, values } => EdgeFeaturesRef::Dense {
                cols: *cols,
                values,
            },
            Self::Sparse {
                cols,
                ptr,
                idx,
                val,
            } => EdgeFeaturesRef::Sparse {
                cols: *cols,
                ptr,
                idx,
                val,
            },
        }
    }

    /// Number of rows.
    pub fn rows(&self) -> usize {
        self.view().rows()
    }

    /// The rows of `parts` one after the other (parts of one radial basis: all dense or all
    /// sparse, with the same columns; anything else is an error).
    pub fn concat(parts: Vec<EdgeFeatures>) -> Result<Self> {
        let mut parts = parts.into_iter();
        let Some(mut out) = parts.next() else {
            return Ok(Self::Dense {
                cols: 0,
                values: Vec::new(),
            });
        };
        for p in parts {
            match (&mut out, p) {
                (Self::Dense { cols, values }, Self::Dense { cols: c, values: v })
                    if *cols == c =>
                {
                    values.extend_from_slice(&v);
                }
                (
                    Self::Sparse {
                        cols,
                        ptr,
                        idx,
                        val,
                    },
                    Self::Sparse {
                        cols: c,
                        ptr: p2,
                        idx: i2,
                        val: v2,
                    },
                ) if *cols == c => {
                    let base = idx.len();
                    ptr.extend(p2.iter().skip(1).map(|o| o + base));
                    idx.extend_from_slice(&i2);
                    val.extend_from_slice(&v2);
                }
                (o, p) => {
                    return Err(PolicyError::ShapeMismatch {
                        name: "edge feature parts".into(),
                        expected: vec![o.cols()],
                        got: vec![p.cols()],
                    })
                }
            }
        }
        Ok(out)
    }

    /// Values per row.
    pub fn cols(&self) -> usize {
        self.view().cols()
    }

    /// The rows in `range`.
    pub fn slice(&self, range: std::ops::Range<usize>) -> EdgeFeaturesRef<'_> {
        match self {
            Self::Dense { cols, values } => EdgeFeaturesRef::Dense {
                cols: *cols,
                values: &values[range.start * cols..range.end * cols],
            },
            Self::Sparse {
                cols,
                ptr,
                idx,
                val,
            } => EdgeFeaturesRef::Sparse {
                cols: *cols,
                ptr: &ptr[range.start..=range.end],
                idx,
                val,
            },
        }
    }

    /// All rows as dense row-major values.
    pub fn to_dense(&self) -> Vec<f32> {
        match self {
            Self::Dense { values, .. } => values.clone(),
            Self::Sparse {
                cols,
                ptr,
                idx,
                val,
            } => {
                let mut out = vec![0.0f32; self.rows() * cols];
                for (r, w) in ptr.windows(2).enumerate() {
                    for e in w[0]..w[1] {
                        out[r * cols + idx[e] as usize] = val[e];
                    }
                }
                out
            }
        }
    }
}

impl EdgeFeaturesRef<'_> {
    /// Number of rows.
    pub fn rows(&self) -> usize {
        match self {
            Self::Dense { cols, values } => values.len().checked_div(*cols).unwrap_or(0),
            Self::Sparse { ptr, .. } => ptr.len().saturating_sub(1),
        }
    }

    /// Values per row.
    pub fn cols(&self) -> usize {
        match self {
            Self::Dense { cols, .. } | Self::Sparse { cols, .. } => *cols,
        }
    }
}

/// `RadialFunction`: Linear → LayerNorm → SiLU repeated, then a final Linear.
#[derive(Debug, Clone)]
pub struct RadialMlp {
    hidden: Vec<(Linear, LayerNorm)>,
    last: Linear,
}

impl RadialMlp {
    /// Loads `net.{3i}` (Linear) and `net.{3i+1}` (LayerNorm) for each hidden layer and the
    /// final Linear; the depth is read from the keys present.
    pub fn load(s: &Scope<'_>) -> Result<Self> {
        let net = s.sub("net");
        let mut hidden = Vec::new();
        let mut i = 0;
        loop {
            let lin = Linear::load(&net.sub(&i.to_string()), true)?;
            if net.contains(&format!("{}.weight", i + 1)) {
                let ln = LayerNorm::load(&net.sub(&(i + 1).to_string()), lin.out)?;
                if let Some((prev, _)) = hidden.last() {
                    let prev: &Linear = prev;
                    if prev.out != lin.inp {
                        return Err(PolicyError::ShapeMismatch {
                            name: net.key(&format!("{i}.weight")),
                            expected: vec![lin.out, prev.out],
                            got: vec![lin.out, lin.inp],
                        });
                    }
                }
                hidden.push((lin, ln));
                i += 3;
            } else {
                return Ok(Self { hidden, last: lin });
            }
        }
    }

    /// Input width.
    pub fn inp(&self) -> usize {
        self.hidden.first().map_or(self.last.inp, |(l, _)| l.inp)
    }

    /// Output width.
    pub fn out(&self) -> usize {
        self.last.out
    }

    /// The MLP with only the outputs `keep`.
    pub fn select_outputs(&self, keep: &[usize]) -> Result<Self> {
        Ok(Self {
            hidden: self.hidden.clone(),
            last: self.last.select_outputs(keep)?,
        })
    }

    /// Applies the MLP to every row of `x`, dense or compressed (the first layer then adds
    /// one weight column per non-zero input).
    pub fn forward_features(&self, x: EdgeFeaturesRef<'_>) -> Result<Vec<f32>> {
        let (ptr, idx, val) = match x {
            EdgeFeaturesRef::Dense { values, .. } => return self.forward(values),
            EdgeFeaturesRef::Sparse { ptr, idx, val, .. } => (ptr, idx, val),
        };
        let (first, ln) = match self.hidden.first() {
            Some((lin, ln)) => (lin, Some(ln)),
            None => (&self.last, None),
        };
        let h = first.forward_sparse(x.cols(), ptr, idx, val)?;
        let Some(ln) = ln else {
            return Ok(h);
        };
        self.after_first(h, ln, &self.hidden[1..])
    }

    /// Applies the MLP to every row of `x`.
    pub fn forward(&self, x: &[f32]) -> Result<Vec<f32>> {
        let Some(((first, ln), rest)) = self.hidden.split_first() else {
            return self.last.forward(x);
        };
        // The first layer reads `x` itself: no copy of the (wide) edge features.
        self.after_first(first.forward(x)?, ln, rest)
    }

    /// The rest of the MLP from the first hidden layer's products `h`: its norm and SiLU,
    /// then each of the `rest` hidden layers (product, norm, SiLU), then the last layer.
    fn after_first(
        &self,
        mut h: Vec<f32>,
        ln: &LayerNorm,
        rest: &[(Linear, LayerNorm)],
    ) -> Result<Vec<f32>> {
        ln.apply(&mut h);
        crate::vector_exp::silu_in_place(&mut h);
        for (lin, ln) in rest {
            h = lin.forward(&h)?;
            ln.apply(&mut h);
            crate::vector_exp::silu_in_place(&mut h);
        }
        self.last.forward(&h)
    }
}

/// `SO3_FiLM_Linear`: an [`So3Linear`] whose weights and bias are generated per batch from a
/// condition vector (p = Linear(Mish(condition))).
#[derive(Debug, Clone)]
pub struct FilmLinear {
    /// Maximum degree.
    pub lmax: usize,
    /// Input channels.
    pub cin: usize,
    /// Output channels.
    pub cout: usize,
    encoder: Linear,
    last: FilmCache,
}

/// The last condition a [`FilmLinear`] prepared its map for, and that map. An episode keeps
/// one instruction, so every keyframe after the first reuses the map instead of running the
/// hypernetwork again (for the reference's widths a matrix-vector product over up to 33 M
/// weights per layer, memory bound). Keyed by the condition's exact bits: a different
/// instruction computes a new map. A clone starts empty.
#[derive(Debug, Default)]
struct FilmCache(std::sync::Mutex<Option<(Vec<u32>, Arc<PreparedFilm>)>>);

impl Clone for FilmCache {
    fn clone(&self) -> Self {
        Self::default()
    }
}

/// The per-batch weights generated by [`FilmLinear::weights`].
#[derive(Debug, Clone)]
pub struct FilmWeights {
    /// `[(lmax+1), cout, cin]`, already divided by √(lmax·cin).
    pub w: Vec<f32>,
    /// `[cout]`, already divided by 10.
    pub b: Vec<f32>,
}

impl FilmLinear {
    /// Loads `cond_encoder.1` (the Linear after Mish) for the given sizes.
    pub fn load(s: &Scope<'_>, lmax: usize, cin: usize, cout: usize) -> Result<Self> {
        let shape = s.sub("cond_encoder").sub("1").shape("weight", 2)?;
        let out = (lmax + 1) * cout * cin + cout;
        let encoder = Linear::load_sized(&s.sub("cond_encoder").sub("1"), out, shape[1], true)?;
        Ok(Self {
            lmax,
            cin,
            cout,
            encoder,
            last: FilmCache::default(),
        })
    }

    /// Width of the condition vector.
    pub fn condition_dim(&self) -> usize {
        self.encoder.inp
    }

    /// The weights for one condition vector, the hypernetwork's outputs split over
    /// `threads` threads (the same weights for any count).
    pub fn weights(&self, condition: &[f32], threads: usize) -> Result<FilmWeights> {
        check_len("FiLM condition", condition.len(), &[self.encoder.inp])?;
        let m: Vec<f32> = condition.iter().map(|v| mish(*v)).collect();
        let p = self.encoder.forward_one_threads(&m, threads)?;
        let nw = (self.lmax + 1) * self.cout * self.cin;
        let scale = 1.0 / ((self.lmax.max(1) * self.cin) as f32).sqrt();
        Ok(FilmWeights {
            w: p[..nw].iter().map(|v| v * scale).collect(),
            b: p[nw..].iter().map(|v| v / 10.0).collect(),
        })
    }

    /// Applies the layer to `x` `[B·N, (lmax+1)², cin]` (nodes grouped by batch, equal
    /// counts) with `condition` `[B, condition_dim]`.
    pub fn forward(&self, x: &[f32], condition: &[f32]) -> Result<Vec<f32>> {
        let k = num_coefficients(self.lmax);
        let nodes = rows_of("FiLM input", x.len(), k * self.cin)?;
        let b = rows_of("FiLM condition", condition.len(), self.encoder.inp)?;
        if b == 0 || nodes % b != 0 {
            return Err(PolicyError::ShapeMismatch {
                name: "FiLM input (nodes must split evenly over the batch)".into(),
                expected: vec![b, 0],
                got: vec![nodes],
            });
        }
        let per = nodes / b;
        let mut y = Vec::with_capacity(nodes * k * self.cout);
        for batch in 0..b {
            let prepared = self.prepare(
                &condition[batch * self.encoder.inp..(batch + 1) * self.encoder.inp],
                1,
            )?;
            let xb = &x[batch * per * k * self.cin..(batch + 1) * per * k * self.cin];
            y.extend(self.apply(xb, &prepared)?);
        }
        Ok(y)
    }

    /// The per-degree map of one condition vector, ready for [`FilmLinear::apply`] (the
    /// hypernetwork on `threads` threads): computed once per forward pass, not once per run
    /// of nodes, and kept for the next pass with the same condition (an episode keeps one
    /// instruction; a different condition computes a new map).
    pub fn prepare(&self, condition: &[f32], threads: usize) -> Result<Arc<PreparedFilm>> {
        let key: Vec<u32> = condition.iter().map(|v| v.to_bits()).collect();
        // A poisoned lock only means another thread panicked mid-update: recompute.
        if let Ok(last) = self.last.0.lock() {
            if let Some((k, map)) = last.as_ref() {
                if *k == key {
                    return Ok(Arc::clone(map));
                }
            }
        }
        let fw = self.weights(condition, threads)?;
        let map = Arc::new(PreparedFilm {
            wt: transpose_per_degree(&fw.w, self.lmax, self.cout, self.cin),
            b: fw.b,
        });
        if let Ok(mut last) = self.last.0.lock() {
            *last = Some((key, Arc::clone(&map)));
        }
        Ok(map)
    }

    /// Applies a prepared map to `x` `[N, (lmax+1)², cin]` (every node, one condition).
    pub fn apply(&self, x: &[f32], prepared: &PreparedFilm) -> Result<Vec<f32>> {
        per_degree_apply(x, self.lmax, self.cin, self.cout, &prepared.wt, &prepared.b)
    }
}

/// A [`FilmLinear`]'s map for one condition: per-degree transposed weights and the bias.
#[derive(Debug, Clone)]
pub struct PreparedFilm {
    wt: Vec<f32>,
    b: Vec<f32>,
}

/// The paper's per-degree scalar iFiLM: an [`So3Linear`] (`weight`, `bias`) whose output is
/// modulated per (degree, channel) by the condition: with m = `film`(Mish(condition)),
/// `[(lmax+2)·cout]` read as rows `m_0 .. m_lmax, γ` of `cout` values,
/// y_l ← (1 + m_l) ⊙ y_l for every degree l (the l = 0 scale is β, the l > 0 scales are α_l)
/// and y_0 ← y_0 + γ. A scalar per (degree, channel) commutes with every rotation, so the
/// layer is exactly equivariant in the features and invariant in the condition; zero `film`
/// weights make it the plain linear map.
#[derive(Debug, Clone)]
pub struct ScalarFilmLinear {
    linear: So3Linear,
    film: Linear,
}

/// Applies m `[(lmax+2)·cout]` (see [`ScalarFilmLinear`]) to `y` `[n, (lmax+1)², cout]`.
pub(crate) fn scalar_film_modulate(y: &mut [f32], m: &[f32], lmax: usize, cout: usize) {
    let k = num_coefficients(lmax);
    let shift = &m[(lmax + 1) * cout..];
    for yn in y.chunks_exact_mut(k * cout) {
        for (i, row) in yn.chunks_exact_mut(cout).enumerate() {
            let scale = &m[degree_of(i) * cout..(degree_of(i) + 1) * cout];
            for (ch, v) in row.iter_mut().enumerate() {
                *v *= 1.0 + scale[ch];
                if i == 0 {
                    *v += shift[ch];
                }
            }
        }
    }
}

impl ScalarFilmLinear {
    /// Loads `weight`, `bias` (sizes from the weight) and `film.weight`
    /// `[(lmax+2)·cout, condition_dim]`, `film.bias`.
    pub fn load(s: &Scope<'_>) -> Result<Self> {
        let linear = So3Linear::load(s)?;
        let shape = s.sub("film").shape("weight", 2)?;
        let out = (linear.lmax + 2) * linear.cout;
        let film = Linear::load_sized(&s.sub("film"), out, shape[1], true)?;
        Ok(Self { linear, film })
    }

    /// The unmodulated linear map.
    pub fn linear(&self) -> &So3Linear {
        &self.linear
    }

    /// Width of the condition vector.
    pub fn condition_dim(&self) -> usize {
        self.film.inp
    }

    /// The modulation m `[(lmax+2)·cout]` for one condition vector.
    pub fn modulation(&self, condition: &[f32]) -> Result<Vec<f32>> {
        check_len("FiLM condition", condition.len(), &[self.film.inp])?;
        let m: Vec<f32> = condition.iter().map(|v| mish(*v)).collect();
        self.film.forward(&m)
    }

    /// Applies the layer to `x` `[B·N, (lmax+1)², cin]` (nodes grouped by batch, equal
    /// counts) with `condition` `[B, condition_dim]`.
    pub fn forward(&self, x: &[f32], condition: &[f32]) -> Result<Vec<f32>> {
        let (lmax, cout) = (self.linear.lmax, self.linear.cout);
        let k = num_coefficients(lmax);
        let nodes = rows_of("FiLM input", x.len(), k * self.linear.cin)?;
        let b = rows_of("FiLM condition", condition.len(), self.film.inp)?;
        if b == 0 || nodes % b != 0 {
            return Err(PolicyError::ShapeMismatch {
                name: "FiLM input (nodes must split evenly over the batch)".into(),
                expected: vec![b, 0],
                got: vec![nodes],
            });
        }
        let mut y = self.linear.forward(x)?;
        let per = nodes / b;
        for (batch, yb) in y.chunks_mut((per * k * cout).max(1)).enumerate() {
            let d = self.film.inp;
            let m = self.modulation(&condition[batch * d..(batch + 1) * d])?;
            scalar_film_modulate(yb, &m, lmax, cout);
        }
        Ok(y)
    }
}

/// Multiplies every node's coefficients by a block-diagonal Wigner matrix `d`
/// `[(lmax+1)², (lmax+1)²]`: `y[n, i, c] = Σ_j d[i, j] x[n, j, c]` (rotates the features).
pub fn rotate_embedding(x: &[f32], c: usize, d: &nalgebra::DMatrix<f64>) -> Result<Vec<f32>> {
    let k = d.nrows();
    let n = rows_of("embedding to rotate", x.len(), k * c)?;
    let mut y = vec![0.0f32; x.len()];
    for node in 0..n {
        let xn = &x[node * k * c..(node + 1) * k * c];
        let yn = &mut y[node * k * c..(node + 1) * k * c];
        for i in 0..k {
            let l = degree_of(i);
            for j in l * l..(l + 1) * (l + 1) {
                let dij = d[(i, j)];
                for ch in 0..c {
                    yn[i * c + ch] += (dij * f64::from(xn[j * c + ch])) as f32;
                }
            }
        }
    }
    Ok(y)
}

/// The separable S2 activation: l > 0 rows through `grid` (to grid, SiLU, back); the l = 0
/// row replaced by SiLU(`gating`). `x` is `[n, grid.reduced.len(), c]`, `gating` `[n, c]`.
/// With a gated grid ([`crate::grids::S2Grid::gate`]) the l > 0 rows are instead multiplied
/// by σ(`gating`) (the same scalars: the weights keep their shapes), which is exactly
/// equivariant.
pub fn separable_s2_activation(
    grid: &crate::grids::S2Grid,
    gating: &[f32],
    x: &[f32],
    c: usize,
) -> Result<Vec<f32>> {
    let nr = grid.reduced.len();
    let n = rows_of("S2 activation input", x.len(), nr * c)?;
    check_len("S2 activation gating", gating.len(), &[n, c])?;
    if grid.gated {
        return Ok(crate::grids::gate_activation(x, gating, gating, nr, c));
    }
    let mut y = grid.activate(x, n, c)?;
    if nr * c == 0 {
        return Ok(y);
    }
    let mut scalars = gating.to_vec();
    crate::vector_exp::silu_in_place(&mut scalars);
    for (yn, s) in y.chunks_exact_mut(nr * c).zip(scalars.chunks_exact(c)) {
        yn[..c].copy_from_slice(s);
    }
    Ok(y)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::predict::PolicyConfig;

    /// erf at zero, at both signs of zero and at NaN returns at once (an exact 0 once hung a
    /// training run in the instruction encoder's GELU); elsewhere it matches tabulated values.
    #[test]
    fn erf_is_defined_everywhere_and_exact_at_zero() {
        assert_eq!(erf(0.0), 0.0);
        assert!(erf(-0.0) == 0.0 && erf(-0.0).is_sign_negative());
        assert!(erf(f64::NAN).is_nan());
        assert_eq!(erf(f64::INFINITY), 1.0);
        assert_eq!(erf(f64::NEG_INFINITY), -1.0);
        assert_eq!(gelu(0.0), 0.0);
        // Abramowitz & Stegun table 7.1, and erf(3).
        for (x, want) in [
            (1e-300, 2.0 / std::f64::consts::PI.sqrt() * 1e-300),
            (0.5, 0.520_499_877_8),
            (1.0, 0.842_700_792_9),
            (2.0, 0.995_322_265_0),
            (3.0, 0.999_977_909_5),
        ] {
            assert!((erf(x) - want).abs() < 1e-9, "erf({x}) = {}", erf(x));
            assert_eq!(erf(-x), -erf(x));
        }
    }

    /// The interleaved rows give each row's LayerNorm as it alone would get it, to the bit,
    /// for any row count (groups and the rest), a row of negative zeros among them.
    #[test]
    fn layer_norm_rows_in_groups_equal_each_row_alone() {
        let dim = 11;
        let ln = LayerNorm {
            dim,
            w: (0..dim).map(|i| 0.5 + i as f32 * 0.1).collect(),
            b: (0..dim).map(|i| i as f32 * 0.01 - 0.05).collect(),
        };
        for rows in 0..10 {
            let mut x: Vec<f32> = (0..rows * dim)
                .map(|i| ((i * 7919 % 1013) as f32 / 97.0).sin() * 10f32.powi((i % 5) as i32 - 2))
                .collect();
            if rows > 2 {
                x[dim * 2..dim * 3].iter_mut().for_each(|v| *v = -0.0);
            }
            // One row at a time (the ungrouped path; the training tape's `layer_norm`, which
            // is the definition written out, is compared with it to the bit in
            // autodiff::layers).
            let mut want = x.clone();
            for row in want.chunks_exact_mut(dim) {
                ln.apply(row);
            }
            ln.apply(&mut x);
            let bits = |v: &[f32]| v.iter().map(|x| x.to_bits()).collect::<Vec<_>>();
            assert_eq!(bits(&x), bits(&want), "{rows} rows");
        }
    }

    #[test]
    fn a_row_split_over_threads_equals_the_one_thread_row() {
        // A hypernetwork-sized layer: 9000 outputs of 16 inputs, split in three parts.
        let (inp, out) = (16, 9000);
        let w: Vec<f32> = (0..inp * out)
            .map(|i| ((i * 37 % 101) as f32 - 50.0) / 50.0)
            .collect();
        let b: Vec<f32> = (0..out).map(|i| (i % 7) as f32 * 0.1).collect();
        let lin = Linear::new(inp, out, w, Some(b));
        let x: Vec<f32> = (0..inp).map(|i| i as f32 * 0.25 - 2.0).collect();
        let mut one = vec![0.0; out];
        lin.forward_row(&x, &mut one);
        assert_eq!(lin.forward_one_threads(&x, 3).unwrap(), one, "bit for bit");
        assert!(lin.forward_one_threads(&x[..15], 2).is_err(), "a short row");
    }

    #[test]
    fn dense_radial_rows_equal_the_values_one_at_a_time() {
        // The field heads' narrow bases and every U-net block's wide ones, over distances
        // that cross the row blocks, with the ones every row treats apart.
        let cfg = PolicyConfig::physical();
        let w = crate::init::random_weights(&cfg.model, &cfg.extra, 4);
        let d: Vec<f32> = (0..3000)
            .map(|i| i as f32 * 7e-4 - 0.05)
            .chain([0.0, -0.0, 1e30, f32::INFINITY, f32::NEG_INFINITY, f32::NAN])
            .collect();
        let scopes: Vec<String> = w
            .keys()
            .into_iter()
            .filter(|k| k.ends_with("distance_expansion.mean"))
            .map(|k| k.trim_end_matches("mean").to_string())
            .collect();
        assert!(scopes.len() > 2, "the field heads' and the U-net's bases");
        for scope in scopes {
            let rbf = GaussianRbf::load(&w.scope(&scope), 1.98).unwrap();
            let k = rbf.num_basis;
            let mut want = vec![0.0f32; d.len() * k];
            for (row, &di) in want.chunks_exact_mut(k).zip(&d) {
                rbf.eval_into(di, row);
            }
            let bits = |v: &[f32]| v.iter().map(|x| x.to_bits()).collect::<Vec<_>>();
            let got = rbf.forward(&d);
            assert_eq!(bits(&got), bits(&want), "{scope}: bit for bit");
            assert!(
                got.iter().filter(|v| **v > 0.0).count() > d.len(),
                "{scope}: values"
            );
        }
    }

    #[test]
    fn compressed_radial_features_equal_the_dense_values() {
        // The field heads' 1024 narrow bases (physical sizes) and the U-net's wide ones.
        let cfg = PolicyConfig::physical();
        let w = crate::init::random_weights(&cfg.model, &cfg.extra, 3);
        let narrow = GaussianRbf::load(&w.scope("field_distance_expansion."), 1.98).unwrap();
        let d: Vec<f32> = (0..2000)
            .map(|i| i as f32 * 1e-3 + 0.013)
            .chain([0.0, 1.98, 2.5, f32::INFINITY])
            .collect();
        let sparse = narrow.features(&d);
        assert!(matches!(sparse, EdgeFeatures::Sparse { .. }));
        assert_eq!(sparse.rows(), d.len());
        assert_eq!(sparse.to_dense(), narrow.forward(&d), "bit for bit");
        // Split in parts and joined again: the same rows.
        let parts = vec![narrow.features(&d[..700]), narrow.features(&d[700..])];
        assert_eq!(EdgeFeatures::concat(parts).unwrap(), sparse);
        // A U-net block's bases (wide: dense rows).
        let key = w
            .keys()
            .into_iter()
            .find(|k| k.ends_with("distance_expansion.mean") && !k.starts_with("field_"))
            .expect("a U-net block's radial basis")
            .trim_end_matches("mean")
            .to_string();
        let wide = GaussianRbf::load(&w.scope(&key), 0.2).unwrap();
        let dense = wide.features(&d[..300]);
        assert!(matches!(dense, EdgeFeatures::Dense { .. }));
        let joined =
            EdgeFeatures::concat(vec![wide.features(&d[..100]), wide.features(&d[100..300])]);
        assert_eq!(joined.unwrap(), dense);
        // Dense and compressed parts do not mix.
        assert!(EdgeFeatures::concat(vec![dense, sparse]).is_err());
    }

    #[test]
    fn the_cut_basis_moves_the_radial_layer_less_than_its_f32_rounding() {
        // The field heads' 1024 narrow bases: the values the reference would compute (every
        // basis, z² up to 210, subnormals included) against ours, cut at RBF_Z2_MAX and
        // RBF_MIN_VALUE. Both through the radial MLP's first layer.
        let cfg = PolicyConfig::physical();
        let w = crate::init::random_weights(&cfg.model, &cfg.extra, 5);
        let rbf = GaussianRbf::load(&w.scope("field_distance_expansion."), 1.98).unwrap();
        let first = w
            .keys()
            .into_iter()
            .find(|k| k.starts_with("trans_field_layer") && k.ends_with("rad_func.net.0.weight"))
            .expect("the translation head's radial MLP")
            .trim_end_matches("weight")
            .to_string();
        let lin = Linear::load(&w.scope(&first), true).unwrap();
        // The same layer with |weight| and |bias|: each output's sum of absolute terms, the
        // scale of its f32 rounding.
        let abs = |v: &[f32]| v.iter().map(|x| x.abs()).collect::<Vec<f32>>();
        let lin_abs = Linear::from_parts(
            lin.out,
            lin.inp,
            abs(lin.weights()),
            lin.b.as_deref().map(abs),
        )
        .unwrap();
        let d: Vec<f32> = (0..3000).map(|i| i as f32 * 6.7e-4 + 0.015).collect();
        let (mut ptr, mut idx, mut val) = (vec![0], Vec::new(), Vec::new());
        let mut subnormal = 0;
        for &di in &d {
            let u = (di - rbf.offset) / rbf.span;
            let env = rbf_envelope(u);
            for i in 0..rbf.num_basis {
                let z = (u - rbf.mean[i]) / rbf.std[i];
                let v = if z * z > 210.0 {
                    0.0
                } else {
                    rbf.weight[i] * (-0.5 * z * z).exp() * env * rbf.normalizer
                };
                if v != 0.0 {
                    subnormal += usize::from(!v.is_normal());
                    idx.push(i as u32);
                    val.push(v);
                }
            }
            ptr.push(idx.len());
        }
        assert!(
            subnormal > 1000,
            "the uncut values hold subnormals ({subnormal})"
        );
        let EdgeFeatures::Sparse {
            ptr: p2,
            idx: i2,
            val: v2,
            ..
        } = rbf.features(&d)
        else {
            panic!("narrow bases give compressed rows");
        };
        assert!(v2.iter().all(|v| *v >= RBF_MIN_VALUE), "no tiny value kept");
        assert!(
            2 * i2.len() < idx.len(),
            "the cut drops more than half the entries ({} of {})",
            idx.len() - i2.len(),
            idx.len()
        );
        let cut = lin.forward_sparse(rbf.num_basis, &p2, &i2, &v2).unwrap();
        let uncut = lin.forward_sparse(rbf.num_basis, &ptr, &idx, &val).unwrap();
        let scale = lin_abs
            .forward_sparse(rbf.num_basis, &ptr, &idx, &abs(&val))
            .unwrap();
        for ((c, u), s) in cut.iter().zip(&uncut).zip(&scale) {
            // Within one rounding of the sum (6e-8 of its terms), with room for the order.
            assert!((c - u).abs() <= 1e-7 * s, "{c} against {u}, terms {s}");
        }
    }

    #[test]
    fn a_film_map_is_reused_only_for_the_same_condition() {
        let cfg = PolicyConfig::tiny();
        let w = crate::init::random_weights(&cfg.model, &cfg.extra, 2);
        let key = w
            .keys()
            .into_iter()
            .find(|k| k.ends_with("cond_encoder.1.weight"))
            .expect("a hypernetwork FiLM in the tiny reference model")
            .trim_end_matches("cond_encoder.1.weight")
            .to_string();
        let scope = w.scope(&key);
        let shape = scope
            .sub("cond_encoder")
            .sub("1")
            .shape("weight", 2)
            .unwrap();
        let lmax = cfg.model.lmax;
        let k = lmax + 1;
        // out = (lmax+1)·cout·cin + cout with cin = cout = the ffn's sizes: find them.
        let (cin, cout) = (1..=64)
            .flat_map(|ci| (1..=64).map(move |co| (ci, co)))
            .find(|&(ci, co)| k * co * ci + co == shape[0])
            .expect("FiLM sizes");
        let film = FilmLinear::load(&scope, lmax, cin, cout).unwrap();
        let dim = film.condition_dim();
        let a: Vec<f32> = (0..dim).map(|i| (i as f32 * 0.37).sin()).collect();
        let mut b = a.clone();
        b[dim / 2] += 0.5;
        let first = film.prepare(&a, 1).unwrap();
        assert!(Arc::ptr_eq(&first, &film.prepare(&a, 1).unwrap()), "reused");
        let other = film.prepare(&b, 1).unwrap();
        assert!(!Arc::ptr_eq(&first, &other));
        assert_ne!(other.wt, first.wt, "another condition, another map");
        // Back to the first condition: recomputed, the same values; a clone starts empty.
        let again = film.prepare(&a, 1).unwrap();
        assert!(!Arc::ptr_eq(&first, &again));
        assert_eq!((&again.wt, &again.b), (&first.wt, &first.b));
        let copy = film.clone();
        let fresh = copy.prepare(&a, 2).unwrap();
        assert!(!Arc::ptr_eq(&again, &fresh));
        assert_eq!((&fresh.wt, &fresh.b), (&first.wt, &first.b));
    }

    #[test]
    fn rms_norm_of_interleaved_nodes_equals_one_node_at_a_time_bit_for_bit() {
        let (lmax, c) = (2, 6);
        let k = num_coefficients(lmax);
        let norm = RmsNormSh {
            lmax,
            c,
            w: (0..(lmax + 1) * c).map(|i| 0.5 + i as f32 * 0.07).collect(),
            // A −0 bias keeps the sign of a zero.
            b: (0..c)
                .map(|i| if i == 0 { -0.0 } else { i as f32 * 0.1 - 0.2 })
                .collect(),
        };
        // Nine nodes: two groups and one left over; one node all −0 (the sums' starting
        // sign shows), one with a huge and a tiny value.
        let n = 9;
        let mut x: Vec<f32> = (0..n * k * c)
            .map(|i| ((i * 37 % 101) as f32 - 50.0) / 13.0)
            .collect();
        x[2 * k * c..3 * k * c].iter_mut().for_each(|v| *v = -0.0);
        x[5 * k * c + 3] = 3.0e30;
        x[5 * k * c + 4] = 1.0e-30;
        let mut want = x.clone();
        for node in want.chunks_exact_mut(k * c) {
            let scale = rms_centre_and_scale(node, lmax, c);
            for i in 0..k {
                for ch in 0..c {
                    let v = &mut node[i * c + ch];
                    *v = (f64::from(*v) * scale) as f32 * norm.w[degree_of(i) * c + ch];
                    if i == 0 {
                        *v += norm.b[ch];
                    }
                }
            }
        }
        let bits = |v: &[f32]| v.iter().map(|f| f.to_bits()).collect::<Vec<_>>();
        assert_eq!(bits(&norm.forward(&x).unwrap()), bits(&want));
    }

    #[test]
    fn mostly_zero_inputs_add_their_nonzero_terms_in_order_bit_for_bit() {
        let inp = 40;
        // A remainder (the plain loop); one, three and nine vectors of outputs (the vector
        // kernel, nine as eight and one).
        for out in [20, 16, 48, 144] {
            let w: Vec<f32> = (0..inp * out)
                .map(|i| ((i * 53 % 97) as f32 - 48.0) / 31.0)
                .collect();
            let rows = 5;
            // Mostly zeros: whole zero blocks, scattered values, a -0 (skipped as zero) and,
            // in the last row, a NaN (added: the output turns NaN).
            let mut x = vec![0.0f32; rows * inp];
            for (i, v) in x.iter_mut().enumerate() {
                if i % 7 == 3 && (i % inp) >= 16 {
                    *v = (i as f32 * 0.37).sin() * 3.0;
                }
            }
            x[inp + 20] = -0.0;
            x[(rows - 1) * inp + 30] = f32::NAN;
            let y0: Vec<f32> = (0..rows * out).map(|i| (i as f32 * 0.11).cos()).collect();
            let mut want = y0.clone();
            for r in 0..rows {
                for i in 0..inp {
                    let xi = x[r * inp + i];
                    if xi != 0.0 {
                        for o in 0..out {
                            want[r * out + o] += xi * w[i * out + o];
                        }
                    }
                }
            }
            let mut y = y0.clone();
            axpy_rows(&x, inp, &w, out, &mut y).unwrap();
            let bits = |v: &[f32]| v.iter().map(|f| f.to_bits()).collect::<Vec<_>>();
            assert_eq!(bits(&y), bits(&want), "{out} outputs");
            assert!(y[(rows - 1) * out].is_nan() && !y[0].is_nan());
        }
    }

    #[test]
    fn sparse_rows_add_their_entries_in_order_and_bad_rows_are_refused() {
        // 20 outputs: one block of 16 held in registers and a remainder of 4.
        let (inp, out) = (40, 20);
        let w: Vec<f32> = (0..inp * out)
            .map(|i| ((i * 53 % 97) as f32 - 48.0) / 31.0)
            .collect();
        let b: Vec<f32> = (0..out).map(|o| o as f32 * 0.3 - 2.0).collect();
        let lin = Linear::new(inp, out, w.clone(), Some(b.clone()));
        let ptr = vec![0, 3, 3, 7];
        let idx = vec![5, 1, 39, 0, 2, 4, 8];
        let val = vec![0.5, -1.25, 3.0, 0.1, 7.0, -0.3, 2.5];
        let y = lin.forward_sparse(inp, &ptr, &idx, &val).unwrap();
        for r in 0..3 {
            for o in 0..out {
                let mut want = b[o];
                for e in ptr[r]..ptr[r + 1] {
                    want += val[e] * w[o * inp + idx[e] as usize];
                }
                assert_eq!(y[r * out + o], want, "row {r} output {o}");
            }
        }
        // A column past the inputs, offsets going back, offsets past the entries.
        assert!(lin.forward_sparse(inp, &[0, 1], &[40], &[1.0]).is_err());
        assert!(lin
            .forward_sparse(inp, &[0, 2, 1], &[0, 1], &[1.0, 1.0])
            .is_err());
        assert!(lin
            .forward_sparse(inp, &[0, 3], &[0, 1], &[1.0, 1.0])
            .is_err());
        assert!(lin.forward_sparse(inp + 1, &[0, 1], &[0], &[1.0]).is_err());
    }
}
