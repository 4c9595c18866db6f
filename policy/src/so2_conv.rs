//! The edge-frame message path: rotation of features into each edge's frame (keeping
//! |m| <= m_max), the SO(2) convolution, and the rotation back.
//!
//! Spec: fixtures README ("Reduced (m-truncated) order", "Edge frame") and the `so2_conv`
//! sidecar. Inside the frame the coefficients are in reduced l-major order; the SO(2)
//! convolution works on (l, ±m) pairs: out(+m) = R a − I b, out(−m) = R b + I a, with R and I
//! the two halves of one bias-free Linear, and the m = 0 block a Linear with bias whose first
//! outputs are extra invariant scalars. The m > 0 blocks are computed with Gauss's three
//! products instead of the four above ([`MProducts`]): the same values to f32 rounding, a
//! quarter fewer multiply-adds.

use crate::error::{PolicyError, Result};
use crate::grids::reduced_coefficients;
use crate::layers::{
    check_indices, check_len, degree_of, rows_of, EdgeFeaturesRef, Linear, RadialMlp,
};
use crate::so3::{edge_rot_mat, num_coefficients, WignerCalculator};
use crate::weights::Scope;

/// The reduced coefficient set for (lmax, mmax) and its (l, m) bookkeeping.
#[derive(Debug, Clone)]
pub struct CoefficientMapping {
    /// Maximum degree.
    pub lmax: usize,
    /// Maximum order kept.
    pub mmax: usize,
    /// Full-basis index (l² + m + l) of each reduced coefficient, l-major.
    pub reduced: Vec<usize>,
}

impl CoefficientMapping {
    /// The mapping for (lmax, mmax), mmax <= lmax.
    pub fn new(lmax: usize, mmax: usize) -> Result<Self> {
        if mmax > lmax {
            return Err(PolicyError::UnsupportedDegree {
                lmax,
                mmax,
                max_supported: crate::so3::MAX_DEGREE,
            });
        }
        Ok(Self {
            lmax,
            mmax,
            reduced: reduced_coefficients(lmax, mmax),
        })
    }

    /// Number of reduced coefficients.
    pub fn len(&self) -> usize {
        self.reduced.len()
    }

    /// Whether the set is empty (never, for valid degrees).
    pub fn is_empty(&self) -> bool {
        self.reduced.is_empty()
    }

    /// Position in the reduced order of coefficient (l, m), |m| <= min(l, mmax).
    pub fn position(&self, l: usize, m: i64) -> usize {
        // Rows before degree l: Σ_{l' < l} (2 min(l', mmax) + 1).
        let before: usize = (0..l).map(|lp| 2 * lp.min(self.mmax) + 1).sum();
        let half = l.min(self.mmax) as i64;
        before + (m + half) as usize
    }

    /// The m-major order used inside the SO(2) convolution, as reduced positions: m = 0
    /// (l ascending), then +1, −1, +2, −2, ...
    pub fn m_major(&self) -> Vec<usize> {
        let mut out = Vec::with_capacity(self.len());
        for l in 0..=self.lmax {
            out.push(self.position(l, 0));
        }
        for m in 1..=self.mmax as i64 {
            for sign in [1, -1] {
                for l in m as usize..=self.lmax {
                    out.push(self.position(l, sign * m));
                }
            }
        }
        out
    }

    /// The multiplier of full-basis row `i` when rotating back: √((2l+1)/(2 mmax+1)) for
    /// l > mmax, else 1.
    pub fn rotate_inv_rescale(&self, i: usize) -> f32 {
        let l = degree_of(i);
        if l > self.mmax {
            (((2 * l + 1) as f64) / ((2 * self.mmax + 1) as f64)).sqrt() as f32
        } else {
            1.0
        }
    }
}

/// Per-edge Wigner matrices D(edge frame), `[E, (lmax+1)², (lmax+1)²]` row-major.
#[derive(Debug, Clone)]
pub struct EdgeWigners {
    /// Maximum degree.
    pub lmax: usize,
    /// Number of edges.
    pub edges: usize,
    /// The matrices.
    pub d: Vec<f32>,
}

impl EdgeWigners {
    /// D of the reference's edge frame (`init_edge_rot_mat2`) of each edge vector.
    pub fn new(calc: &WignerCalculator, lmax: usize, edge_vec: &[[f32; 3]]) -> Result<Self> {
        Self::new_threads(calc, lmax, edge_vec, 1)
    }

    /// [`EdgeWigners::new`] with the edges split over `threads` threads (the same matrices).
    pub fn new_threads(
        calc: &WignerCalculator,
        lmax: usize,
        edge_vec: &[[f32; 3]],
        threads: usize,
    ) -> Result<Self> {
        let k = num_coefficients(lmax);
        let mut d = vec![0.0f32; edge_vec.len() * k * k];
        // Below a few hundred edges a thread costs more than it saves.
        let parts = crate::parallel::split_even(edge_vec.len(), threads.min(edge_vec.len() / 256));
        let mut items = Vec::with_capacity(parts.len());
        let mut rest = d.as_mut_slice();
        for r in &parts {
            let (head, tail) = rest.split_at_mut(r.len() * k * k);
            items.push((&edge_vec[r.clone()], head));
            rest = tail;
        }
        crate::parallel::run_parts(items, |(vecs, out)| Self::fill(calc, lmax, vecs, out))
            .into_iter()
            .collect::<Result<()>>()?;
        Ok(Self {
            lmax,
            edges: edge_vec.len(),
            d,
        })
    }

    /// Writes the matrices of `edge_vec` into `d` (`[E, k, k]`).
    fn fill(
        calc: &WignerCalculator,
        lmax: usize,
        edge_vec: &[[f32; 3]],
        d: &mut [f32],
    ) -> Result<()> {
        let k = num_coefficients(lmax);
        let mut sh = Vec::new();
        for (v, de) in edge_vec.iter().zip(d.chunks_exact_mut(k * k)) {
            let r = edge_rot_mat([f64::from(v[0]), f64::from(v[1]), f64::from(v[2])])?;
            if lmax == calc.lmax() {
                calc.wigner_all_into(&r, &mut sh, de);
            } else {
                // A calculator built for a higher degree: per-degree blocks.
                let w = calc.wigner(lmax, &r)?;
                for (i, row) in de.chunks_exact_mut(k).enumerate() {
                    for (j, x) in row.iter_mut().enumerate() {
                        *x = w[(i, j)] as f32;
                    }
                }
            }
        }
        Ok(())
    }

    /// An error unless `map` is for these matrices' degree.
    fn check_map(&self, map: &CoefficientMapping) -> Result<()> {
        if map.lmax != self.lmax {
            return Err(PolicyError::ShapeMismatch {
                name: "coefficient mapping's lmax for the edge Wigner matrices".into(),
                expected: vec![self.lmax],
                got: vec![map.lmax],
            });
        }
        Ok(())
    }

    /// Edges in `range`, or an error if it runs past the edges.
    fn range_len(&self, range: &std::ops::Range<usize>) -> Result<usize> {
        if range.start > range.end || range.end > self.edges {
            return Err(PolicyError::IndexOutOfRange {
                name: "edge range".into(),
                value: range.end as i64,
                len: self.edges,
            });
        }
        Ok(range.len())
    }

    /// The matrices of the edges in `range` (a copy).
    pub fn slice(&self, range: std::ops::Range<usize>) -> Self {
        let k = num_coefficients(self.lmax);
        Self {
            lmax: self.lmax,
            edges: range.len(),
            d: self.d[range.start * k * k..range.end * k * k].to_vec(),
        }
    }

    /// Rotates `x` `[E, (lmax+1)², c]` into the edge frames, keeping the reduced rows:
    /// `[E, n_reduced, c]`.
    pub fn rotate(&self, map: &CoefficientMapping, x: &[f32], c: usize) -> Result<Vec<f32>> {
        let k = num_coefficients(self.lmax);
        check_len("features to rotate", x.len(), &[self.edges, k, c])?;
        // Edge e's features are row e of `x`: the messages' rotation with identity indices.
        let own: Vec<usize> = (0..self.edges).collect();
        self.rotate_messages(0..self.edges, map, c, (x, &own), None)
    }

    /// The message parts (`x_a` with its node of each edge, then `x_b`'s if given), checked:
    /// the mapping matches, `ne` indices each, `c` channels per node, every index a node.
    fn message_parts<'a>(
        &self,
        map: &CoefficientMapping,
        ne: usize,
        c: usize,
        a: (&'a [f32], &'a [usize]),
        b: Option<(&'a [f32], &'a [usize])>,
    ) -> Result<Vec<(&'a [f32], &'a [usize])>> {
        self.check_map(map)?;
        let k = num_coefficients(self.lmax);
        let parts: Vec<(&[f32], &[usize])> = std::iter::once(a).chain(b).collect();
        for (x, idx) in &parts {
            check_len("message node indices", idx.len(), &[ne])?;
            let n = rows_of("message node features", x.len(), k * c)?;
            check_indices("message node index", idx.iter(), n)?;
        }
        Ok(parts)
    }

    /// [`EdgeWigners::rotate`] of the edges in `range` (no copy of their matrices) on the
    /// messages `concat(x_a[a[e]], x_b[b[e]])` along channels (`x_a` `[Na, (lmax+1)², c]`; the second part is optional), read straight from
    /// the node features instead of from a gathered copy: `[E, n_reduced, c or 2c]`, the
    /// same values.
    pub fn rotate_messages(
        &self,
        range: std::ops::Range<usize>,
        map: &CoefficientMapping,
        c: usize,
        (x_a, a): (&[f32], &[usize]),
        b: Option<(&[f32], &[usize])>,
    ) -> Result<Vec<f32>> {
        let ne = self.range_len(&range)?;
        let parts = self.message_parts(map, ne, c, (x_a, a), b)?;
        let mc = parts.len() * c;
        let nr = map.len();
        // Appended in output order (edge, reduced row, part): every value is written once,
        // with no zero fill before.
        let mut y = Vec::with_capacity(ne * nr * mc);
        for e in 0..ne {
            for &i in &map.reduced {
                self.append_rotated_row(range.start + e, e, i, c, &parts, &mut y);
            }
        }
        Ok(y)
    }

    /// Appends row `i` (a coefficient index) of edge `edge`'s rotated messages to `out`: for
    /// each part, `Σ_j D[i, j] · x[idx[local], j]` over the coefficients j of i's degree (c
    /// values). `local` indexes the parts' node indices, `edge` the Wigner matrices.
    #[inline]
    fn append_rotated_row(
        &self,
        edge: usize,
        local: usize,
        i: usize,
        c: usize,
        parts: &[(&[f32], &[usize])],
        out: &mut Vec<f32>,
    ) {
        let k = num_coefficients(self.lmax);
        let d = &self.d[edge * k * k..(edge + 1) * k * k];
        let l = degree_of(i);
        let block = l * l..(l + 1) * (l + 1);
        for (x, idx) in parts {
            let xe = &x[idx[local] * k * c..(idx[local] + 1) * k * c];
            combine_rows(
                &d[i * k + block.start..i * k + block.end],
                &xe[block.start * c..block.end * c],
                c,
                out,
            );
        }
    }

    /// [`EdgeWigners::rotate_messages`] written as the SO(2) convolution's |m| blocks, each
    /// row scaled by the radial weights `rad` `[E, rad_w]` where given (the convolution's
    /// layout: m = 0 rows for l = 0..=lmax, then for each m > 0 the rows l = m..=lmax, the
    /// +m and −m halves sharing their weights): the m = 0 block `[E, (lmax+1)·mc]` and the
    /// (+m, −m) halves `[E, (lmax+1−m)·mc]` each, mc = c or 2c channels per row.
    pub fn rotate_messages_blocks(
        &self,
        range: std::ops::Range<usize>,
        map: &CoefficientMapping,
        c: usize,
        (x_a, a): (&[f32], &[usize]),
        b: Option<(&[f32], &[usize])>,
        rad: Option<&[f32]>,
    ) -> Result<MBlocks> {
        let ne = self.range_len(&range)?;
        let parts = self.message_parts(map, ne, c, (x_a, a), b)?;
        let mc = parts.len() * c;
        let (lmax, mmax) = (map.lmax, map.mmax);
        let l1 = lmax + 1;
        // Per edge: the m = 0 rows, then each m's rows, l ascending (the weights' layout).
        let rad_w = l1 * mc + (1..=mmax).map(|m| (l1 - m) * mc).sum::<usize>();
        if let Some(r) = rad {
            check_len("radial weights", r.len(), &[ne, rad_w])?;
        }
        let mut v0 = Vec::with_capacity(ne * l1 * mc);
        let mut halves: Vec<[Vec<f32>; 2]> = (1..=mmax)
            .map(|m| {
                let n = ne * (l1 - m) * mc;
                [Vec::with_capacity(n), Vec::with_capacity(n)]
            })
            .collect();
        let kernel = RotateMessages {
            wigners: self,
            edges: range,
            map,
            c,
            parts: &parts,
            rad: rad.map(|r| (r, rad_w)),
            out: (&mut v0, &mut halves),
        };
        run_on_channels(c, kernel);
        Ok(MBlocks { m0: v0, halves })
    }

    /// Rotates `y` `[E, n_reduced, c]` back to the global frame with Dᵀ and the reference's
    /// rescaling of degrees above mmax: `[E, (lmax+1)², c]`.
    pub fn rotate_back(&self, map: &CoefficientMapping, y: &[f32], c: usize) -> Result<Vec<f32>> {
        self.rotate_back_range(0..self.edges, map, y, c)
    }

    /// [`EdgeWigners::rotate_back`] for the edges in `range` only.
    pub fn rotate_back_range(
        &self,
        range: std::ops::Range<usize>,
        map: &CoefficientMapping,
        y: &[f32],
        c: usize,
    ) -> Result<Vec<f32>> {
        self.check_map(map)?;
        let k = num_coefficients(self.lmax);
        let nr = map.len();
        let ne = self.range_len(&range)?;
        check_len("features to rotate back", y.len(), &[ne, nr, c])?;
        // Each degree's reduced rows are a run of the l-major reduced order, m = −half..half.
        let runs: Vec<std::ops::Range<usize>> = (0..=self.lmax)
            .map(|l| {
                let half = l.min(map.mmax);
                let start = map.position(l, -(half as i64));
                start..start + 2 * half + 1
            })
            .collect();
        let rescale: Vec<f32> = (0..k).map(|j| map.rotate_inv_rescale(j)).collect();
        let d = &self.d[range.start * k * k..(range.start + ne) * k * k];
        let mut x = Vec::with_capacity(ne * k * c);
        let kernel = RotateBack {
            d,
            y,
            rows: (&map.reduced, &runs, &rescale),
            shape: (k, nr, c),
            x: &mut x,
        };
        run_on_channels(c, kernel);
        Ok(x)
    }
}

/// Runs a rotation kernel over `c` channels: on whole vectors (AVX-512 or AVX2, `pulp`'s
/// run-time dispatch) where `c` is a multiple of 16, as in every layer of the physical
/// configuration, else one channel at a time at `pulp`'s scalar level; the same sums in
/// the same order either way.
fn run_on_channels<K: pulp::WithSimd<Output = ()>>(c: usize, kernel: K) {
    if c.is_multiple_of(16) {
        pulp::Arch::new().dispatch(kernel);
    } else {
        kernel.with_simd(pulp::Scalar::new());
    }
}

/// One part of the messages: node features `[N, K, c]` and each edge's node.
type MessagePart<'a> = (&'a [f32], &'a [usize]);

/// [`EdgeWigners::rotate_messages_blocks`] in vectors of channels (one channel each at
/// `pulp`'s scalar level, for any channel count): each vector of a
/// rotated row summed in a register from +0 over its degree's coefficients in order, a
/// product then a sum per term, then times its radial weights ([`combine_rows`] and the
/// scaling after it, bit for bit).
struct RotateMessages<'a> {
    wigners: &'a EdgeWigners,
    /// The edges, indexing the Wigner matrices.
    edges: std::ops::Range<usize>,
    map: &'a CoefficientMapping,
    /// Channels per part.
    c: usize,
    /// The message parts.
    parts: &'a [MessagePart<'a>],
    /// The radial weights `[E, rad_w]` and rad_w.
    rad: Option<(&'a [f32], usize)>,
    /// The m = 0 block and the (+m, −m) halves, appended to.
    out: (&'a mut Vec<f32>, &'a mut Vec<[Vec<f32>; 2]>),
}

impl pulp::WithSimd for RotateMessages<'_> {
    type Output = ();

    #[inline(always)]
    fn with_simd<S: pulp::Simd>(self, simd: S) {
        let RotateMessages {
            wigners,
            edges,
            map,
            c,
            parts,
            rad,
            out: (v0, halves),
        } = self;
        let k = num_coefficients(wigners.lmax);
        let lmax = map.lmax;
        let l1 = lmax + 1;
        let mc = parts.len() * c;
        let d = &wigners.d[edges.start * k * k..edges.end * k * k];
        // No closure for the row: a closure would not inherit the kernel's target features
        // (every vector operation would become a call).
        for e in 0..edges.len() {
            let re = rad.map(|(r, rad_w)| &r[e * rad_w..(e + 1) * rad_w]);
            for l in 0..=lmax {
                let w = re.map(|r| &r[l * mc..(l + 1) * mc]);
                let de = &d[e * k * k..(e + 1) * k * k];
                rotated_row(simd, (de, k), l * l + l, (parts, e, c), w, v0);
            }
            let mut off = l1 * mc;
            for (mi, pair) in halves.iter_mut().enumerate() {
                let m = mi + 1;
                for (half, sign) in pair.iter_mut().zip([1i64, -1]) {
                    for (li, l) in (m..=lmax).enumerate() {
                        let w = re.map(|r| &r[off + li * mc..off + (li + 1) * mc]);
                        let i = (l * l + l) as i64 + sign * m as i64;
                        let de = &d[e * k * k..(e + 1) * k * k];
                        rotated_row(simd, (de, k), i as usize, (parts, e, c), w, half);
                    }
                }
                off += (l1 - m) * mc;
            }
        }
    }
}

/// One rotated row (every part, `c` channels each) of an edge with Wigner matrix `d` (K × K)
/// appended to `out`, times its weights `w`: [`RotateMessages`]'s row.
#[inline(always)]
fn rotated_row<S: pulp::Simd>(
    simd: S,
    (d, k): (&[f32], usize),
    i: usize,
    (parts, e, c): (&[MessagePart<'_>], usize, usize),
    w: Option<&[f32]>,
    out: &mut Vec<f32>,
) {
    let cv = c / S::F32_LANES;
    let l = degree_of(i);
    let block = l * l..(l + 1) * (l + 1);
    let di = &d[i * k + block.start..i * k + block.end];
    let at = out.len();
    out.resize(at + parts.len() * c, 0.0);
    let (ov, _) = S::as_mut_simd_f32s(&mut out[at..]);
    for (p, ((x, idx), op)) in parts.iter().zip(ov.chunks_exact_mut(cv)).enumerate() {
        let node = idx[e] * k * c;
        let (xv, _) = S::as_simd_f32s(&x[node + block.start * c..node + block.end * c]);
        let wv = w.map(|w| S::as_simd_f32s(&w[p * c..(p + 1) * c]).0);
        for (b, o) in op.iter_mut().enumerate() {
            let mut acc = simd.splat_f32s(0.0);
            for (&dt, &xt) in di.iter().zip(xv[b..].iter().step_by(cv)) {
                acc = simd.add_f32s(acc, simd.mul_f32s(simd.splat_f32s(dt), xt));
            }
            *o = match wv {
                Some(wv) => simd.mul_f32s(acc, wv[b]),
                None => acc,
            };
        }
    }
}

/// [`EdgeWigners::rotate_back_range`] in vectors of channels (one channel each at `pulp`'s
/// scalar level, for any channel count): per edge and output row, each vector of channels
/// summed in a register from +0 over its degree's reduced rows in order, a product then a
/// sum per term ([`combine_rows`]'s rounding, bit for bit).
struct RotateBack<'a> {
    /// The edges' matrices `[E, K, K]`.
    d: &'a [f32],
    /// The edge-frame features `[E, n_reduced, c]`.
    y: &'a [f32],
    /// Each reduced row's full index, each degree's run of reduced rows, each output row's
    /// rescaling.
    rows: (&'a [usize], &'a [std::ops::Range<usize>], &'a [f32]),
    /// (K, n_reduced, c).
    shape: (usize, usize, usize),
    /// The output `[E, K, c]`, appended to.
    x: &'a mut Vec<f32>,
}

/// Most reduced rows, and most output rows, of one degree.
const MAX_ROWS: usize = 2 * crate::so3::MAX_DEGREE + 1;

impl pulp::WithSimd for RotateBack<'_> {
    type Output = ();

    #[inline(always)]
    fn with_simd<S: pulp::Simd>(self, simd: S) {
        let RotateBack {
            d,
            y,
            rows,
            shape,
            x,
        } = self;
        let (reduced, runs, rescale) = rows;
        let (k, nr, c) = shape;
        let cv = c / S::F32_LANES;
        // One degree's weights, [reduced row][output row of the degree].
        let mut w = [[0.0f32; MAX_ROWS]; MAX_ROWS];
        for (de, ye) in d.chunks_exact(k * k).zip(y.chunks_exact(nr * c)) {
            let (yv, _) = S::as_simd_f32s(ye);
            let start = x.len();
            x.resize(start + k * c, 0.0);
            let (xv, _) = S::as_mut_simd_f32s(&mut x[start..]);
            for (l, run) in runs.iter().enumerate() {
                let outs = l * l..(l + 1) * (l + 1);
                // Row i of Dᵀ's block is row i of D read along the degree's columns.
                for (wt, &i) in w.iter_mut().zip(&reduced[run.clone()]) {
                    let di = &de[i * k + outs.start..i * k + outs.end];
                    for ((wtj, &dij), &sj) in wt.iter_mut().zip(di).zip(&rescale[outs.clone()]) {
                        *wtj = dij * sj;
                    }
                }
                let w = &w[..run.len()];
                let rows = &yv[run.start * cv..run.end * cv];
                for (jj, xj) in xv[outs.start * cv..outs.end * cv]
                    .chunks_exact_mut(cv)
                    .enumerate()
                {
                    for (b, out) in xj.iter_mut().enumerate() {
                        let mut acc = simd.splat_f32s(0.0);
                        for (wt, yt) in w.iter().zip(rows[b..].iter().step_by(cv)) {
                            acc = simd.add_f32s(acc, simd.mul_f32s(simd.splat_f32s(wt[jj]), *yt));
                        }
                        *out = acc;
                    }
                }
            }
        }
    }
}

/// Appends `Σ_j w[j] · x[j]` over the rows `x[j] = x[j·c..(j+1)·c]` (c values) to `y`, the
/// terms added in j order to 0 as a row-by-row loop of `y += w[j] · x[j]` adds them (the same
/// rounding, bit for bit), a block of channels at a time held in registers: each output is
/// stored once, not loaded and stored once per term, and needs no zero fill before.
#[inline]
fn combine_rows(w: &[f32], x: &[f32], c: usize, y: &mut Vec<f32>) {
    const LANES: usize = 16;
    debug_assert!(x.len() == w.len() * c);
    let mut start = 0;
    while start + LANES <= c {
        let mut acc = [0.0f32; LANES];
        for (j, &wj) in w.iter().enumerate() {
            let xs = &x[j * c + start..j * c + start + LANES];
            for (a, &xv) in acc.iter_mut().zip(xs) {
                *a += wj * xv;
            }
        }
        y.extend_from_slice(&acc);
        start += LANES;
    }
    for t in start..c {
        let mut acc = 0.0f32;
        for (j, &wj) in w.iter().enumerate() {
            acc += wj * x[j * c + t];
        }
        y.push(acc);
    }
}

/// The inputs of an SO(2) convolution's per-|m| maps, every edge's rows in order.
#[derive(Debug, Clone, PartialEq)]
pub struct MBlocks {
    /// m = 0: `[E, (lmax+1)·cin]`, rows l = 0..=lmax.
    pub m0: Vec<f32>,
    /// For each m = 1..=mmax, the +m and −m halves `[E, (lmax+1−m)·cin]`, rows l = m..=lmax.
    pub halves: Vec<[Vec<f32>; 2]>,
}

/// `SO2_Convolution`: per-|m| linear maps in the edge frame, optionally scaled by a radial MLP
/// of invariant edge features, with extra invariant m = 0 outputs.
#[derive(Debug, Clone)]
pub struct So2Conv {
    map: CoefficientMapping,
    /// Input channels.
    pub cin: usize,
    /// Output channels.
    pub cout: usize,
    /// Extra m = 0 outputs (0 for none).
    pub extra: usize,
    fc_m0: Linear,
    /// The degrees whose m = 0 outputs `fc_m0` computes, ascending (all but those a reader
    /// never uses; the others' rows come out as zeros).
    m0_degrees: Vec<usize>,
    fc_m: Vec<Linear>,
    /// `fc_m` as Gauss's three products, one per |m|.
    gauss: Vec<GaussProducts>,
    rad: Option<RadialMlp>,
}

/// One |m| block's map as three products instead of four: with k1 = R(a + b),
/// k2 = (I − R)a and k3 = (R + I)b, out(+m) = Ra − Ib = k1 − k3 and
/// out(−m) = Rb + Ia = k1 + k2 (Gauss's complex multiplication). A quarter fewer
/// multiply-adds for the m > 0 blocks, the bulk of the convolution.
#[derive(Debug, Clone)]
struct GaussProducts {
    r: Linear,
    i_minus_r: Linear,
    r_plus_i: Linear,
}

impl GaussProducts {
    /// The three maps of `fc`, whose first half of outputs is R and second half I.
    fn of(fc: &Linear) -> Result<Self> {
        let (half, inp) = (fc.out / 2, fc.inp);
        let (r, i) = fc.weights().split_at(half * inp);
        let combine = |f: fn(f32, f32) -> f32| -> Vec<f32> {
            r.iter().zip(i).map(|(&r, &i)| f(r, i)).collect()
        };
        Ok(Self {
            r: Linear::from_parts(half, inp, r.to_vec(), None)?,
            i_minus_r: Linear::from_parts(half, inp, combine(|r, i| i - r), None)?,
            r_plus_i: Linear::from_parts(half, inp, combine(|r, i| r + i), None)?,
        })
    }
}

/// An SO(2) convolution's m = 0 block with some of its output degrees
/// ([`So2Conv::m0_block`]): reads the m = 0 rows (l = 0..=lmax) of the edge frame only.
#[derive(Debug, Clone)]
pub struct M0Block {
    /// (lmax, 0): the m = 0 rows.
    map: CoefficientMapping,
    /// Input channels.
    cin: usize,
    /// The kept outputs of `fc_m0` (the extras, then the kept degrees' channels), or the
    /// whole map and the outputs to pick from it.
    fc: (Linear, Option<Vec<usize>>),
    /// The radial MLP's m = 0 outputs, or the whole MLP and the outputs to pick.
    rad: Option<(RadialMlp, Option<Vec<usize>>)>,
}

/// The radial MLP `r` of the edge features `xe`, which must hold one row per edge.
fn radial_weights(r: &RadialMlp, xe: EdgeFeaturesRef<'_>, edges: usize) -> Result<Vec<f32>> {
    if xe.rows() != edges || xe.cols() != r.inp() {
        return Err(PolicyError::ShapeMismatch {
            name: "SO(2) convolution edge features".into(),
            expected: vec![edges, r.inp()],
            got: vec![xe.rows(), xe.cols()],
        });
    }
    r.forward_features(xe)
}

/// The columns `pick` of each `width`-wide row of `y` (all of `y` when None).
fn pick_columns(y: Vec<f32>, width: usize, pick: &Option<Vec<usize>>) -> Vec<f32> {
    match pick {
        None => y,
        Some(cols) => y
            .chunks_exact(width)
            .flat_map(|row| cols.iter().map(|&c| row[c]))
            .collect(),
    }
}

impl M0Block {
    /// Outputs per edge (the extras, then `cout` per kept degree).
    pub fn outputs(&self) -> usize {
        match &self.fc {
            (_, Some(pick)) => pick.len(),
            (fc, None) => fc.out,
        }
    }

    /// The kept outputs of the map on the m = 0 block `x`.
    fn map(&self, x: &[f32]) -> Result<Vec<f32>> {
        let (fc, pick) = &self.fc;
        Ok(pick_columns(fc.forward(x)?, fc.out, pick))
    }

    /// The block on given m = 0 rows `x` `[E, lmax+1, cin]` (no radial MLP: an error if the
    /// convolution has one).
    pub fn forward(&self, x: &[f32]) -> Result<Vec<f32>> {
        if let Some((r, _)) = &self.rad {
            return Err(PolicyError::ShapeMismatch {
                name: "SO(2) convolution edge features (required by its radial MLP)".into(),
                expected: vec![r.inp()],
                got: vec![0],
            });
        }
        rows_of(
            "m = 0 rows of an SO(2) convolution",
            x.len(),
            (self.map.lmax + 1) * self.cin,
        )?;
        self.map(x)
    }

    /// The block on the m = 0 rows of the messages `x_a[a[e]]` rotated into the frames of
    /// the edges `range` of `wigners` (c channels; see
    /// [`So2Conv::forward_rotated`]), scaled by the radial MLP of `x_edge`: `[E, outputs]`.
    pub fn forward_rotated(
        &self,
        (wigners, range): (&EdgeWigners, std::ops::Range<usize>),
        parts: (&[f32], &[usize]),
        x_edge: EdgeFeaturesRef<'_>,
    ) -> Result<Vec<f32>> {
        let edges = wigners.range_len(&range)?;
        let rad = match &self.rad {
            Some((r, pick)) => Some(pick_columns(
                radial_weights(r, x_edge, edges)?,
                r.out(),
                pick,
            )),
            None => None,
        };
        let blocks = wigners.rotate_messages_blocks(
            range,
            &self.map,
            self.cin,
            parts,
            None,
            rad.as_deref(),
        )?;
        self.map(&blocks.m0)
    }
}

/// Which products compute the m > 0 blocks.
#[derive(Copy, Clone, Debug, PartialEq, Eq)]
pub enum MProducts {
    /// Gauss's three (the default).
    Gauss,
    /// The plain four (R and I times each half), the reference's form: kept as the test
    /// oracle and the benchmark's baseline.
    Plain,
}

impl So2Conv {
    /// Loads `fc_m0`, `so2_m_conv.{m-1}.fc` and, if `radial`, `rad_func`.
    pub fn load(
        s: &Scope<'_>,
        map: &CoefficientMapping,
        cin: usize,
        cout: usize,
        extra: usize,
        radial: bool,
    ) -> Result<Self> {
        let l1 = map.lmax + 1;
        let fc_m0 = Linear::load_sized(&s.sub("fc_m0"), extra + l1 * cout, l1 * cin, true)?;
        let mut fc_m = Vec::new();
        let mut rad_width = l1 * cin;
        for m in 1..=map.mmax {
            let nl = map.lmax + 1 - m;
            fc_m.push(Linear::load_sized(
                &s.sub("so2_m_conv").sub(&(m - 1).to_string()).sub("fc"),
                2 * nl * cout,
                nl * cin,
                false,
            )?);
            rad_width += nl * cin;
        }
        let rad = if radial {
            let r = RadialMlp::load(&s.sub("rad_func"))?;
            if r.out() != rad_width {
                return Err(PolicyError::ShapeMismatch {
                    name: s.key("rad_func (output width)"),
                    expected: vec![rad_width],
                    got: vec![r.out()],
                });
            }
            Some(r)
        } else {
            None
        };
        Self::assemble(map.clone(), cin, cout, extra, fc_m0, fc_m, rad)
    }

    /// The convolution from its maps, with their Gauss products.
    fn assemble(
        map: CoefficientMapping,
        cin: usize,
        cout: usize,
        extra: usize,
        fc_m0: Linear,
        fc_m: Vec<Linear>,
        rad: Option<RadialMlp>,
    ) -> Result<Self> {
        let gauss = fc_m.iter().map(GaussProducts::of).collect::<Result<_>>()?;
        Ok(Self {
            m0_degrees: (0..=map.lmax).collect(),
            map,
            cin,
            cout,
            extra,
            fc_m0,
            fc_m,
            gauss,
            rad,
        })
    }

    /// The convolution for inputs whose channels from `keep` on are always zero (the
    /// attention's messages onto all-zero destination features): those input channels and
    /// their radial weights are dropped, so the products are half as wide. Same outputs.
    pub fn first_channels(&self, keep: usize) -> Result<Self> {
        if keep == 0 || keep > self.cin {
            return Err(PolicyError::ShapeMismatch {
                name: "SO(2) convolution channels to keep".into(),
                expected: vec![self.cin],
                got: vec![keep],
            });
        }
        // Inputs of an m block are [degrees, cin]; keep channel < `keep` of every degree.
        let cols = |degrees: usize| -> Vec<usize> {
            (0..degrees)
                .flat_map(|l| (0..keep).map(move |ch| l * self.cin + ch))
                .collect()
        };
        let l1 = self.map.lmax + 1;
        let fc_m0 = self.fc_m0.select_inputs(&cols(l1))?;
        let mut rad_keep = cols(l1);
        let mut offset = l1 * self.cin;
        let mut fc_m = Vec::with_capacity(self.fc_m.len());
        for (mi, fc) in self.fc_m.iter().enumerate() {
            let nl = l1 - (mi + 1);
            fc_m.push(fc.select_inputs(&cols(nl))?);
            rad_keep.extend(cols(nl).into_iter().map(|i| i + offset));
            offset += nl * self.cin;
        }
        let rad = match &self.rad {
            Some(r) => Some(r.select_outputs(&rad_keep)?),
            None => None,
        };
        Ok(Self {
            m0_degrees: self.m0_degrees.clone(),
            ..Self::assemble(
                self.map.clone(),
                keep,
                self.cout,
                self.extra,
                fc_m0,
                fc_m,
                rad,
            )?
        })
    }

    /// The convolution without the l = 0 outputs (m = 0 row of degree 0), which come out
    /// as zeros: for a reader that replaces that row (the gated activation writes
    /// SiLU(gating) there). The other outputs to the bit, one block of `cout` fewer
    /// columns in the m = 0 product.
    pub fn without_l0_outputs(&self) -> Result<Self> {
        let Some(at) = self.m0_degrees.iter().position(|&l| l == 0) else {
            return Ok(self.clone());
        };
        let start = self.extra + at * self.cout;
        let keep: Vec<usize> = (0..self.fc_m0.out)
            .filter(|&o| o < start || o >= start + self.cout)
            .collect();
        if !crate::matmul::same_rounding(self.fc_m0.out, keep.len()) {
            // Narrower than matmul's small size: the other outputs would round differently.
            return Ok(self.clone());
        }
        let mut out = self.clone();
        out.fc_m0 = self.fc_m0.select_outputs(&keep)?;
        out.m0_degrees.remove(at);
        Ok(out)
    }

    /// The column of `fc_m0` where degree `l`'s m = 0 outputs start (None: not computed).
    fn m0_column(&self, l: usize) -> Option<usize> {
        let at = self.m0_degrees.iter().position(|&d| d == l)?;
        Some(self.extra + at * self.cout)
    }

    /// The m = 0 block alone, with the extra outputs and the outputs of the degrees
    /// `degrees` only (ascending): for a reader of the invariant (m = 0) rows of the edge
    /// frame that never needs the m > 0 rows or the other degrees (the field heads'
    /// translation readout). Its outputs are those of the whole convolution to the bit.
    pub fn m0_block(&self, degrees: &[usize]) -> Result<M0Block> {
        let l1 = self.map.lmax + 1;
        if let Some(&bad) = degrees.iter().find(|&&l| l >= l1) {
            return Err(PolicyError::UnsupportedDegree {
                lmax: bad,
                mmax: 0,
                max_supported: self.map.lmax,
            });
        }
        if degrees.windows(2).any(|w| w[1] <= w[0]) {
            return Err(PolicyError::ShapeMismatch {
                name: "output degrees of an m = 0 block (ascending, each once)".into(),
                expected: vec![],
                got: degrees.to_vec(),
            });
        }
        // fc_m0's outputs: the extras, then cout per computed degree.
        let mut keep: Vec<usize> = (0..self.extra).collect();
        for &l in degrees {
            let start = self.m0_column(l).ok_or(PolicyError::UnsupportedDegree {
                lmax: l,
                mmax: 0,
                max_supported: self.map.lmax,
            })?;
            keep.extend(start..start + self.cout);
        }
        // The radial weights' first l1·cin outputs scale the m = 0 rows.
        let rad_keep: Vec<usize> = (0..l1 * self.cin).collect();
        let rad = match &self.rad {
            Some(r) if crate::matmul::same_rounding(r.out(), rad_keep.len()) => {
                Some((r.select_outputs(&rad_keep)?, None))
            }
            Some(r) => Some((r.clone(), Some(rad_keep))),
            None => None,
        };
        // A product narrowed below matmul's small size would round differently: such a map
        // stays whole and its kept outputs are picked after.
        let fc = if crate::matmul::same_rounding(self.fc_m0.out, keep.len()) {
            (self.fc_m0.select_outputs(&keep)?, None)
        } else {
            (self.fc_m0.clone(), Some(keep))
        };
        Ok(M0Block {
            map: CoefficientMapping::new(self.map.lmax, 0)?,
            cin: self.cin,
            fc,
            rad,
        })
    }

    /// Input width of the radial MLP (0 without one).
    pub fn edge_features(&self) -> usize {
        self.rad.as_ref().map_or(0, RadialMlp::inp)
    }

    /// Applies the convolution to `x` `[E, n_reduced, cin]` (reduced l-major order) with the
    /// invariant edge features `x_edge` `[E, edge_features]` (ignored without a radial MLP).
    /// Returns `[E, n_reduced, cout]` and the extra outputs `[E, extra]`.
    pub fn forward(&self, x: &[f32], x_edge: Option<&[f32]>) -> Result<(Vec<f32>, Vec<f32>)> {
        let cols = self.edge_features();
        self.forward_features(
            x,
            x_edge.map(|values| EdgeFeaturesRef::Dense { cols, values }),
        )
    }

    /// [`So2Conv::forward`] with edge features dense or in compressed rows.
    pub fn forward_features(
        &self,
        x: &[f32],
        x_edge: Option<EdgeFeaturesRef<'_>>,
    ) -> Result<(Vec<f32>, Vec<f32>)> {
        self.forward_with(x, x_edge, MProducts::Gauss)
    }

    /// [`So2Conv::forward_features`] with the m > 0 blocks computed by `products`.
    pub fn forward_with(
        &self,
        x: &[f32],
        x_edge: Option<EdgeFeaturesRef<'_>>,
        products: MProducts,
    ) -> Result<(Vec<f32>, Vec<f32>)> {
        let nr = self.map.len();
        let cin = self.cin;
        let edges = rows_of("SO(2) convolution input", x.len(), nr * cin)?;
        let rad = self.radial(x_edge, edges)?;
        let rad_w = self.rad.as_ref().map_or(0, RadialMlp::out);
        let lmax = self.map.lmax;
        let l1 = lmax + 1;
        // The inputs of each |m|'s linear map are gathered (and scaled by the radial MLP) in
        // one pass each, and the outputs assembled in one pass at the end: no zero-filled
        // buffers that are overwritten right after.
        // m = 0: all edges' inputs as one matrix [E, l1·cin], one batched linear map.
        let mut v = Vec::with_capacity(edges * l1 * cin);
        for e in 0..edges {
            let xe = &x[e * nr * cin..(e + 1) * nr * cin];
            for l in 0..=lmax {
                let p = self.map.position(l, 0);
                let xl = &xe[p * cin..(p + 1) * cin];
                match &rad {
                    Some(r) => {
                        let rl = &r[e * rad_w + l * cin..e * rad_w + (l + 1) * cin];
                        v.extend(xl.iter().zip(rl).map(|(xi, ri)| xi * ri));
                    }
                    None => v.extend_from_slice(xl),
                }
            }
        }
        // m > 0: the +m halves a and the −m halves b of every edge as two matrices
        // [E, (l1 − m)·cin] per m.
        let mut halves = Vec::with_capacity(self.fc_m.len());
        let mut roff = l1 * cin;
        for m in 1..=self.fc_m.len() {
            let width = (l1 - m) * cin;
            let mut pair = [
                Vec::with_capacity(edges * width),
                Vec::with_capacity(edges * width),
            ];
            for e in 0..edges {
                let xe = &x[e * nr * cin..(e + 1) * nr * cin];
                let rw = rad
                    .as_ref()
                    .map(|r| &r[e * rad_w + roff..e * rad_w + roff + width]);
                for (half, sign) in pair.iter_mut().zip([1, -1]) {
                    for (li, l) in (m..=lmax).enumerate() {
                        let p = self.map.position(l, sign * m as i64);
                        let xl = &xe[p * cin..(p + 1) * cin];
                        match rw {
                            Some(rw) => half.extend(
                                xl.iter()
                                    .zip(&rw[li * cin..(li + 1) * cin])
                                    .map(|(xi, ri)| xi * ri),
                            ),
                            None => half.extend_from_slice(xl),
                        }
                    }
                }
            }
            roff += width;
            halves.push(pair);
        }
        self.finish(edges, MBlocks { m0: v, halves }, products)
    }

    /// [`So2Conv::forward_features`] of the messages `concat(x_a[a[e]], x_b[b[e]])` rotated
    /// into the frames of the edges `range` of `wigners` (what
    /// [`EdgeWigners::rotate_messages`] gives, with `c` channels per part): each rotated
    /// row is scaled by the radial MLP and written straight into its |m| block, with no
    /// rotated copy gathered again. The same values.
    pub fn forward_rotated(
        &self,
        (wigners, range): (&EdgeWigners, std::ops::Range<usize>),
        c: usize,
        parts: (&[f32], &[usize]),
        second: Option<(&[f32], &[usize])>,
        x_edge: Option<EdgeFeaturesRef<'_>>,
        products: MProducts,
    ) -> Result<(Vec<f32>, Vec<f32>)> {
        let mc = if second.is_some() { 2 * c } else { c };
        if mc != self.cin {
            return Err(PolicyError::ShapeMismatch {
                name: "SO(2) convolution message channels".into(),
                expected: vec![self.cin],
                got: vec![mc],
            });
        }
        let edges = wigners.range_len(&range)?;
        let rad = self.radial(x_edge, edges)?;
        let blocks =
            wigners.rotate_messages_blocks(range, &self.map, c, parts, second, rad.as_deref())?;
        self.finish(edges, blocks, products)
    }

    /// The radial MLP of the edge features (None without one), checked against `edges`.
    fn radial(
        &self,
        x_edge: Option<EdgeFeaturesRef<'_>>,
        edges: usize,
    ) -> Result<Option<Vec<f32>>> {
        match (&self.rad, x_edge) {
            (Some(r), Some(xe)) => Ok(Some(radial_weights(r, xe, edges)?)),
            (Some(r), None) => Err(PolicyError::ShapeMismatch {
                name: "SO(2) convolution edge features (required by its radial MLP)".into(),
                expected: vec![edges, r.inp()],
                got: vec![0],
            }),
            (None, _) => Ok(None),
        }
    }

    /// The per-|m| products of the gathered inputs and the outputs in reduced order, edge
    /// by edge: `[E, n_reduced, cout]` and the extra outputs `[E, extra]`.
    fn finish(
        &self,
        edges: usize,
        MBlocks { m0: v, halves }: MBlocks,
        products: MProducts,
    ) -> Result<(Vec<f32>, Vec<f32>)> {
        let nr = self.map.len();
        let cout = self.cout;
        let l1 = self.map.lmax + 1;
        let o0 = self.fc_m0.forward(&v)?;
        drop(v);
        // out(+m) and out(−m) as two matrices [E, (l1 − m)·cout] per m.
        let mut om = Vec::with_capacity(self.fc_m.len());
        for ((fc, gauss), [mut a, b]) in self.fc_m.iter().zip(&self.gauss).zip(halves) {
            om.push(match products {
                MProducts::Gauss => {
                    // In place where the buffers allow: a becomes a + b once k2 is taken,
                    // k3 becomes out(+m) = k1 − k3 and k2 out(−m) = k1 + k2.
                    let mut k2 = gauss.i_minus_r.forward(&a)?;
                    let mut k3 = gauss.r_plus_i.forward(&b)?;
                    a.iter_mut().zip(&b).for_each(|(a, b)| *a += b);
                    let k1 = gauss.r.forward(&a)?;
                    k3.iter_mut().zip(&k1).for_each(|(k3, k1)| *k3 = k1 - *k3);
                    k2.iter_mut().zip(&k1).for_each(|(k2, k1)| *k2 += k1);
                    (k3, k2)
                }
                MProducts::Plain => {
                    let (oa, ob) = (fc.forward(&a)?, fc.forward(&b)?);
                    let half = fc.out / 2;
                    let (mut plus, mut minus) = (
                        Vec::with_capacity(edges * half),
                        Vec::with_capacity(edges * half),
                    );
                    // out(+m) = R a − I b, out(−m) = R b + I a.
                    for (oa, ob) in oa.chunks_exact(fc.out).zip(ob.chunks_exact(fc.out)) {
                        plus.extend(oa[..half].iter().zip(&ob[half..]).map(|(r, i)| r - i));
                        minus.extend(ob[..half].iter().zip(&oa[half..]).map(|(r, i)| r + i));
                    }
                    (plus, minus)
                }
            });
        }
        // The outputs in reduced order, edge by edge.
        let w0 = self.fc_m0.out;
        let m0_columns: Vec<Option<usize>> = (0..l1).map(|l| self.m0_column(l)).collect();
        let mut y = Vec::with_capacity(edges * nr * cout);
        let mut extra = Vec::with_capacity(edges * self.extra);
        for e in 0..edges {
            let oe = &o0[e * w0..(e + 1) * w0];
            extra.extend_from_slice(&oe[..self.extra]);
            for &i in &self.map.reduced {
                let l = degree_of(i);
                let m = i as i64 - (l * l + l) as i64;
                if m == 0 {
                    match m0_columns[l] {
                        Some(at) => y.extend_from_slice(&oe[at..at + cout]),
                        None => y.resize(y.len() + cout, 0.0),
                    }
                    continue;
                }
                let am = m.unsigned_abs() as usize;
                let (plus, minus) = &om[am - 1];
                let half = (l1 - am) * cout;
                let o = if m > 0 { plus } else { minus };
                let q = e * half + (l - am) * cout;
                y.extend_from_slice(&o[q..q + cout]);
            }
        }
        Ok((y, extra))
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use rand::{Rng, SeedableRng};

    #[test]
    fn rotations_equal_the_plain_loops_bit_for_bit() {
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(11);
        let (lmax, mmax, ne) = (3, 2, 7);
        let k = num_coefficients(lmax);
        let calc = WignerCalculator::new(lmax).unwrap();
        let map = CoefficientMapping::new(lmax, mmax).unwrap();
        let nr = map.len();
        let vecs: Vec<[f32; 3]> = (0..ne)
            .map(|_| [0; 3].map(|_| rng.random_range(-1.0..1.0f32)))
            .collect();
        let w = EdgeWigners::new(&calc, lmax, &vecs).unwrap();
        // Below, at and past one register block of channels, with a tail; whole vectors of
        // channels (the vector kernel's rotation back).
        for c in [5, 16, 37, 48] {
            let x: Vec<f32> = (0..ne * k * c)
                .map(|_| rng.random_range(-1.0..1.0f32))
                .collect();
            // `y += d·x` row by row and term by term, as the rotations were first written.
            let mut want = vec![0.0f32; ne * nr * c];
            for e in 0..ne {
                for (r, &i) in map.reduced.iter().enumerate() {
                    let l = degree_of(i);
                    for j in l * l..(l + 1) * (l + 1) {
                        for t in 0..c {
                            want[(e * nr + r) * c + t] +=
                                w.d[e * k * k + i * k + j] * x[(e * k + j) * c + t];
                        }
                    }
                }
            }
            let y = w.rotate(&map, &x, c).unwrap();
            assert_eq!(y, want, "rotate, c = {c}");
            let mut back_want = vec![0.0f32; ne * k * c];
            for e in 0..ne {
                for (r, &i) in map.reduced.iter().enumerate() {
                    let l = degree_of(i);
                    for j in l * l..(l + 1) * (l + 1) {
                        let wij = w.d[e * k * k + i * k + j] * map.rotate_inv_rescale(j);
                        for t in 0..c {
                            back_want[(e * k + j) * c + t] += wij * y[(e * nr + r) * c + t];
                        }
                    }
                }
            }
            assert_eq!(
                w.rotate_back(&map, &y, c).unwrap(),
                back_want,
                "rotate back, c = {c}"
            );
            // A range of the edges: their rows of the whole.
            assert_eq!(
                w.rotate_back_range(2..5, &map, &y[2 * nr * c..5 * nr * c], c)
                    .unwrap(),
                back_want[2 * k * c..5 * k * c],
                "rotate back edges 2..5, c = {c}"
            );
        }
        // A mapping for another degree is an error, not a panic.
        let other = CoefficientMapping::new(2, 2).unwrap();
        let x = vec![0.0f32; ne * k];
        assert!(w.rotate(&other, &x, 1).is_err());
        assert!(w.rotate_back(&other, &x[..ne * other.len()], 1).is_err());
    }

    #[test]
    fn message_blocks_are_the_rotated_rows_times_their_weights_bit_for_bit() {
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(5);
        let (lmax, mmax, nodes, ne) = (3, 2, 9, 30);
        let k = num_coefficients(lmax);
        let calc = WignerCalculator::new(lmax).unwrap();
        let map = CoefficientMapping::new(lmax, mmax).unwrap();
        let nr = map.len();
        let vecs: Vec<[f32; 3]> = (0..ne)
            .map(|_| [0; 3].map(|_| rng.random_range(-1.0..1.0f32)))
            .collect();
        let w = EdgeWigners::new(&calc, lmax, &vecs).unwrap();
        let a: Vec<usize> = (0..ne).map(|e| (e * 7) % nodes).collect();
        let b: Vec<usize> = (0..ne).map(|e| (e * 3 + 1) % nodes).collect();
        let range = 4..21;
        let (ra, rb) = (&a[range.clone()], &b[range.clone()]);
        // A tail of channels (the plain loops) and whole vectors (the vector kernel).
        for c in [5, 16, 32] {
            let mut feats =
                |n: usize| -> Vec<f32> { (0..n).map(|_| rng.random_range(-1.0..1.0f32)).collect() };
            let (xa, xb) = (feats(nodes * k * c), feats(nodes * k * c));
            for two in [false, true] {
                let mc = if two { 2 * c } else { c };
                let second = two.then_some((xb.as_slice(), rb));
                let rad_w =
                    (lmax + 1) * mc + (1..=mmax).map(|m| (lmax + 1 - m) * mc).sum::<usize>();
                let rad = feats(range.len() * rad_w);
                let rows = w
                    .rotate_messages(range.clone(), &map, c, (&xa, ra), second)
                    .unwrap();
                for weights in [None, Some(rad.as_slice())] {
                    let blocks = w
                        .rotate_messages_blocks(range.clone(), &map, c, (&xa, ra), second, weights)
                        .unwrap();
                    // Row (l, m) of edge e times the weights at `off` of the edge's.
                    let want = |e: usize, l: usize, m: i64, off: usize| -> Vec<f32> {
                        let r = map.position(l, m);
                        let row = &rows[(e * nr + r) * mc..(e * nr + r + 1) * mc];
                        match weights {
                            Some(wt) => row
                                .iter()
                                .zip(&wt[e * rad_w + off..e * rad_w + off + mc])
                                .map(|(v, w)| v * w)
                                .collect(),
                            None => row.to_vec(),
                        }
                    };
                    let mut m0 = Vec::new();
                    let mut halves = vec![[Vec::new(), Vec::new()]; mmax];
                    for e in 0..range.len() {
                        for l in 0..=lmax {
                            m0.extend(want(e, l, 0, l * mc));
                        }
                        let mut off = (lmax + 1) * mc;
                        for m in 1..=mmax {
                            for (half, sign) in halves[m - 1].iter_mut().zip([1i64, -1]) {
                                for (li, l) in (m..=lmax).enumerate() {
                                    half.extend(want(e, l, sign * m as i64, off + li * mc));
                                }
                            }
                            off += (lmax + 1 - m) * mc;
                        }
                    }
                    let what = format!("c = {c}, two parts {two}, weights {}", weights.is_some());
                    assert_eq!(blocks.m0, m0, "m = 0 block, {what}");
                    assert_eq!(blocks.halves, halves, "halves, {what}");
                }
            }
        }
    }

    #[test]
    fn messages_rotated_from_the_nodes_equal_rotated_gathered_copies() {
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(4);
        let (lmax, mmax, c, nodes, ne) = (3, 2, 5, 9, 40);
        let k = num_coefficients(lmax);
        let calc = WignerCalculator::new(lmax).unwrap();
        let map = CoefficientMapping::new(lmax, mmax).unwrap();
        let vecs: Vec<[f32; 3]> = (0..ne)
            .map(|_| [0; 3].map(|_| rng.random_range(-1.0..1.0f32)))
            .collect();
        let w = EdgeWigners::new(&calc, lmax, &vecs).unwrap();
        let mut feats = || -> Vec<f32> {
            (0..nodes * k * c)
                .map(|_| rng.random_range(-1.0..1.0f32))
                .collect()
        };
        let (xa, xb) = (feats(), feats());
        let a: Vec<usize> = (0..ne).map(|e| (e * 7) % nodes).collect();
        let b: Vec<usize> = (0..ne).map(|e| (e * 3 + 1) % nodes).collect();
        let range = 10..30;
        let gather = |parts: &[(&[f32], &[usize])]| -> Vec<f32> {
            let mc = parts.len() * c;
            let mut m = vec![0.0f32; range.len() * k * mc];
            for (e, edge) in range.clone().enumerate() {
                for i in 0..k {
                    for (p, (x, idx)) in parts.iter().enumerate() {
                        let s = idx[edge];
                        m[(e * k + i) * mc + p * c..(e * k + i) * mc + (p + 1) * c]
                            .copy_from_slice(&x[(s * k + i) * c..(s * k + i + 1) * c]);
                    }
                }
            }
            m
        };
        let r = range.clone();
        let part = w.slice(r.clone());
        let both = w
            .rotate_messages(
                r.clone(),
                &map,
                c,
                (&xa, &a[r.clone()]),
                Some((&xb, &b[r.clone()])),
            )
            .unwrap();
        let copied = gather(&[(&xa, &a), (&xb, &b)]);
        assert_eq!(both, part.rotate(&map, &copied, 2 * c).unwrap());
        let one = w
            .rotate_messages(r.clone(), &map, c, (&xa, &a[r.clone()]), None)
            .unwrap();
        let copied = gather(&[(&xa, &a)]);
        assert_eq!(one, part.rotate(&map, &copied, c).unwrap());
        // A node index past the features is an error, not a panic.
        let mut bad = a[r.clone()].to_vec();
        bad[3] = nodes;
        assert!(w.rotate_messages(r, &map, c, (&xa, &bad), None).is_err());
        assert!(w
            .rotate_messages(30..41, &map, c, (&xa, &a[..11]), None)
            .is_err());
    }

    /// The tiny model's first attention (random weights, seed 9): its sizes, mapping, and
    /// its two convolutions (the first with a radial MLP).
    fn tiny_first_attention() -> (
        crate::attention::AttentionConfig,
        CoefficientMapping,
        So2Conv,
        So2Conv,
    ) {
        let cfg = crate::predict::PolicyConfig::tiny();
        let m = &cfg.model;
        let w = crate::init::random_weights(m, &cfg.extra, 9);
        let attn = m.block_attention(0, m.sphere_channels[0]);
        let s = w.scope("down_blocks.0.block.transblock.ga.");
        let map = CoefficientMapping::new(attn.lmax, attn.mmax).unwrap();
        let n_extra = attn.num_heads * attn.alpha_channels + attn.hidden_channels;
        let conv1 = So2Conv::load(
            &s.sub("so2_conv_1"),
            &map,
            2 * attn.sphere_channels,
            attn.hidden_channels,
            n_extra,
            true,
        )
        .unwrap();
        let conv2 = So2Conv::load(
            &s.sub("so2_conv_2"),
            &map,
            attn.hidden_channels,
            attn.num_heads * attn.value_channels,
            0,
            false,
        )
        .unwrap();
        (attn, map, conv1, conv2)
    }

    #[test]
    fn the_convolution_of_rotated_messages_equals_rotating_then_convolving() {
        // The tiny model's first attention: conv1 (radial MLP, source and destination
        // channels) and its source-only form, on messages of random node features.
        let (attn, map, conv1, _) = tiny_first_attention();
        let c = attn.sphere_channels;
        let sources = conv1.first_channels(c).unwrap();
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(6);
        let (lmax, nodes, ne) = (attn.lmax, 11, 37);
        let k = num_coefficients(lmax);
        let calc = WignerCalculator::new(lmax).unwrap();
        let vecs: Vec<[f32; 3]> = (0..ne)
            .map(|_| [0; 3].map(|_| rng.random_range(-1.0..1.0f32)))
            .collect();
        let wig = EdgeWigners::new(&calc, lmax, &vecs).unwrap();
        let mut random =
            |n: usize| -> Vec<f32> { (0..n).map(|_| rng.random_range(-1.0..1.0f32)).collect() };
        let (xa, xb) = (random(nodes * k * c), random(nodes * k * c));
        let xe = random(ne * conv1.edge_features());
        let a: Vec<usize> = (0..ne).map(|e| (e * 5) % nodes).collect();
        let b: Vec<usize> = (0..ne).map(|e| (e * 2 + 3) % nodes).collect();
        let r = 4..29;
        let feats = EdgeFeaturesRef::Dense {
            cols: conv1.edge_features(),
            values: &xe[r.start * conv1.edge_features()..r.end * conv1.edge_features()],
        };
        for (conv, second) in [(&conv1, Some((&xb[..], &b[r.clone()]))), (&sources, None)] {
            let first = (&xa[..], &a[r.clone()]);
            let rotated = wig
                .rotate_messages(r.clone(), &map, c, first, second)
                .unwrap();
            for products in [MProducts::Gauss, MProducts::Plain] {
                let want = conv.forward_with(&rotated, Some(feats), products).unwrap();
                let got = conv
                    .forward_rotated((&wig, r.clone()), c, first, second, Some(feats), products)
                    .unwrap();
                assert_eq!(got, want, "bit for bit");
            }
        }
        // Message channels that do not match the convolution's are an error.
        assert!(sources
            .forward_rotated(
                (&wig, r.clone()),
                c,
                (&xa, &a[r.clone()]),
                Some((&xb, &b[r.clone()])),
                Some(feats),
                MProducts::Gauss
            )
            .is_err());
        // So is a radial MLP without its edge features.
        assert!(conv1
            .forward_rotated(
                (&wig, r.clone()),
                c,
                (&xa, &a[r.clone()]),
                Some((&xb, &b[r.clone()])),
                None,
                MProducts::Gauss
            )
            .is_err());
    }

    /// Dropping the l = 0 outputs (read by nobody under the gated activation) leaves every
    /// other output and the extras as they were, to the bit, and zeros in the l = 0 rows;
    /// the m = 0 block of the narrowed convolution no longer offers degree 0.
    #[test]
    fn without_l0_outputs_the_other_outputs_stay_bit_for_bit() {
        let (attn, map, conv1, _) = tiny_first_attention();
        let narrow = conv1.without_l0_outputs().unwrap();
        assert_eq!(narrow.fc_m0.out, conv1.fc_m0.out - conv1.cout);
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(6);
        let edges = 19;
        let x: Vec<f32> = (0..edges * map.len() * conv1.cin)
            .map(|_| rng.random_range(-1.0..1.0f32))
            .collect();
        let xe: Vec<f32> = (0..edges * conv1.edge_features())
            .map(|_| rng.random_range(0.0..1.0f32))
            .collect();
        let feats = Some(EdgeFeaturesRef::Dense {
            cols: conv1.edge_features(),
            values: &xe,
        });
        let (y, extra) = conv1.forward_features(&x, feats).unwrap();
        let (yn, extra_n) = narrow.forward_features(&x, feats).unwrap();
        assert_eq!(extra_n, extra);
        let row = map.len() * conv1.cout;
        for (e, (a, b)) in y.chunks_exact(row).zip(yn.chunks_exact(row)).enumerate() {
            let l0 = map.position(0, 0) * conv1.cout..(map.position(0, 0) + 1) * conv1.cout;
            assert!(b[l0.clone()].iter().all(|v| *v == 0.0), "edge {e}");
            assert!(a[l0.clone()].iter().any(|v| *v != 0.0));
            assert_eq!(&a[l0.end..], &b[l0.end..], "edge {e}");
        }
        // The zero-destination form keeps the narrowing.
        let sources = narrow.first_channels(attn.sphere_channels).unwrap();
        assert_eq!(sources.m0_degrees, narrow.m0_degrees);
        assert!(narrow.m0_block(&[0]).is_err());
        assert!(narrow.m0_block(&[1]).is_ok());
        assert!(conv1.m0_block(&[1, 1]).is_err());
    }

    /// Gauss's three products give the plain four's outputs to f32 rounding, with and
    /// without the radial MLP, and for the source-only convolution.
    #[test]
    fn gauss_products_equal_the_plain_four() {
        let (attn, map, conv1, conv2) = tiny_first_attention();
        let sources = conv1.first_channels(attn.sphere_channels).unwrap();
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(5);
        let edges = 23;
        let mut random =
            |n: usize| -> Vec<f32> { (0..n).map(|_| rng.random_range(-1.0..1.0f32)).collect() };
        for conv in [&conv1, &conv2, &sources] {
            let x = random(edges * map.len() * conv.cin);
            let xe = random(edges * conv.edge_features());
            let feats = (conv.edge_features() > 0).then_some(EdgeFeaturesRef::Dense {
                cols: conv.edge_features(),
                values: &xe,
            });
            let (y3, e3) = conv.forward_with(&x, feats, MProducts::Gauss).unwrap();
            let (y4, e4) = conv.forward_with(&x, feats, MProducts::Plain).unwrap();
            assert_eq!(e3, e4, "the m = 0 extras do not change");
            assert_eq!(y3.len(), y4.len());
            let scale = y4.iter().fold(0f32, |a, v| a.max(v.abs()));
            let err = y3
                .iter()
                .zip(&y4)
                .fold(0f32, |a, (p, q)| a.max((p - q).abs()));
            assert!(
                scale > 0.1 && err <= 1e-5 * scale,
                "{err} on values up to {scale}"
            );
            // Not the same computation: the products round differently somewhere.
            assert_ne!(y3, y4);
        }
    }
}
