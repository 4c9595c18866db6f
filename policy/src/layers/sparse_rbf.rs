//! [`GaussianRbf::features`]' compressed rows, built a block of distances at a time.
//!
//! Each distance reaches a run of ~40 bases in mean order (a table of windows, or two
//! binary searches, finds it), of which ~25 are non-zero. The scan keeps the non-zero ones' exponents, the block's
//! exponentials are taken at once ([`crate::vector_exp`]), then each row's values are
//! written with the zeros left out. On AVX-512 machines the scan and the rows run 16 bases
//! at a time through `pulp`'s `V4`, kept entries packed by the compress instructions
//! (`vcompressps`), with the same f32 operations in the same order as the scalar form, so
//! the rows are the same bits on any machine; a one-basis-at-a-time loop spent most of its
//! time on branches and on growing vectors entry by entry.

use super::{rbf_scaled, EdgeFeatures, GaussianRbf, RBF_MIN_VALUE, RBF_Z2_MAX};

/// Distances per block: the block's exponents stay in cache.
const ROW_BLOCK: usize = 256;

/// Lanes of the vector scan; every buffer it writes keeps this much room past its end.
const LANES: usize = 16;

/// The bases in mean order, one column per parameter, each padded by `LANES` entries so
/// that a vector load from any basis stays inside (the padding is masked off).
#[derive(Debug, Clone, Default)]
pub(super) struct BasisColumns {
    mean: Vec<f32>,
    std: Vec<f32>,
    /// Largest |u − mean| with a non-zero value ([`super::SortedBasis::reach`]).
    reach: Vec<f32>,
    index: Vec<u32>,
    weight: Vec<f32>,
    /// The candidate windows by stretches of u (None: the binary searches).
    windows: Option<WindowTable>,
}

impl BasisColumns {
    /// The columns of `by_mean`, whose bases are non-zero within `reach` of their mean.
    pub(super) fn new(by_mean: &[super::SortedBasis], reach: f32) -> Self {
        let pad = |mut v: Vec<f32>| {
            v.resize(v.len() + LANES, 0.0);
            v
        };
        let mut index: Vec<u32> = by_mean.iter().map(|b| b.index).collect();
        index.resize(index.len() + LANES, 0);
        Self {
            mean: pad(by_mean.iter().map(|b| b.mean).collect()),
            std: pad(by_mean.iter().map(|b| b.std).collect()),
            reach: pad(by_mean.iter().map(|b| b.reach).collect()),
            index,
            weight: pad(by_mean.iter().map(|b| b.weight).collect()),
            windows: WindowTable::new(by_mean, reach),
        }
    }
}

/// Every u's candidate bases from a table instead of two binary searches (which took
/// about a third of the scan): u's range split into equal stretches, each with the first
/// basis within `reach` of its start and the last within `reach` of its end. The window of
/// u's stretch and its two neighbours (a margin for the rounding of the stretch's number)
/// holds every basis within `reach` of u and a few more; the scan's own tests drop the
/// extra ones, which lie farther than their reach (z² > [`RBF_Z2_MAX`]).
#[derive(Debug, Clone)]
struct WindowTable {
    start: f32,
    per_unit: f32,
    /// Per stretch boundary: the bases with mean < boundary − reach.
    lo: Vec<usize>,
    /// Per stretch boundary: the bases with mean <= boundary + reach.
    hi: Vec<usize>,
}

impl WindowTable {
    /// The table of `by_mean`, or None where its windows would hold many more bases than
    /// the exact ones (means far apart: a few stretches span much of the range).
    fn new(by_mean: &[super::SortedBasis], reach: f32) -> Option<Self> {
        let (first, last) = (by_mean.first()?.mean, by_mean.last()?.mean);
        let (start, end) = (f64::from(first - reach), f64::from(last + reach));
        let stretches = (4 * by_mean.len()).clamp(1024, 1 << 16);
        let width = (end - start) / stretches as f64;
        if !(reach.is_finite() && width.is_finite() && width > 0.0) {
            return None;
        }
        let reach = f64::from(reach);
        let boundary = |j: usize| start + j as f64 * width;
        let lo: Vec<usize> = (0..=stretches)
            .map(|j| by_mean.partition_point(|b| f64::from(b.mean) < boundary(j) - reach))
            .collect();
        let hi: Vec<usize> = (0..=stretches)
            .map(|j| by_mean.partition_point(|b| f64::from(b.mean) <= boundary(j) + reach))
            .collect();
        let exact = lo.iter().zip(&hi).map(|(l, h)| h - l).max().unwrap_or(0);
        let table = Self {
            start: start as f32,
            per_unit: (1.0 / width) as f32,
            lo,
            hi,
        };
        let widest = (0..=stretches)
            .map(|j| table.window_of(j).len())
            .max()
            .unwrap_or(0);
        (widest <= 2 * exact + LANES).then_some(table)
    }

    /// The candidates of stretch `j` (with its neighbours).
    #[inline(always)]
    fn window_of(&self, j: usize) -> std::ops::Range<usize> {
        let last = self.lo.len() - 1;
        let lo = self.lo[j.saturating_sub(1).min(last)];
        let hi = self.hi[(j + 2).min(last)];
        lo..hi.max(lo)
    }

    /// The candidates of a finite u.
    #[inline(always)]
    fn window(&self, u: f32) -> std::ops::Range<usize> {
        // Clamped first: beyond either end the end's window (which holds no basis within
        // reach, or only those of the end's stretch).
        let at = ((u - self.start) * self.per_unit).clamp(0.0, (self.lo.len() - 1) as f32);
        self.window_of(at as usize)
    }
}

/// The compressed rows of every distance of `d` (the caller has checked that the bases are
/// narrow and their reach finite).
pub(super) fn sparse_features(rbf: &GaussianRbf, d: &[f32]) -> EdgeFeatures {
    sparse_features_on(rbf, d, true)
}

/// [`sparse_features`], with the vector kernels where the CPU has them if `vector`, else
/// one basis at a time (the same bits; the tests compare the two).
fn sparse_features_on(rbf: &GaussianRbf, d: &[f32], vector: bool) -> EdgeFeatures {
    let mut rows = SparseRows {
        ptr: Vec::with_capacity(d.len() + 1),
        ..SparseRows::default()
    };
    rows.ptr.push(0);
    let mut block = RbfBlock::default();
    for part in d.chunks(ROW_BLOCK) {
        block.clear();
        scan(rbf, part, &mut block, vector);
        crate::vector_exp::exp_in_place(&mut block.exp[..block.n]);
        emit(rbf, &block, &mut rows, vector);
    }
    let SparseRows {
        ptr,
        mut idx,
        mut val,
        n,
        ..
    } = rows;
    idx.truncate(n);
    val.truncate(n);
    EdgeFeatures::Sparse {
        cols: rbf.num_basis,
        ptr,
        idx,
        val,
    }
}

/// A block's kept bases, reused from block to block; `n` entries are valid, the vectors
/// are longer (room for a vector store past the last one).
#[derive(Default)]
struct RbfBlock {
    /// Each kept basis's −z²/2, then its exponential.
    exp: Vec<f32>,
    /// Each kept basis's column.
    index: Vec<u32>,
    /// Each kept basis's weight.
    weight: Vec<f32>,
    n: usize,
    /// Per distance: u, its envelope, and where its kept bases end.
    row_end: Vec<(f32, f32, usize)>,
}

impl RbfBlock {
    fn clear(&mut self) {
        self.n = 0;
        self.row_end.clear();
    }

    /// Room for `more` entries and a vector store after them.
    fn room(&mut self, more: usize) {
        let need = self.n + more + LANES;
        if self.exp.len() < need {
            let len = need.max(2 * self.exp.len());
            self.exp.resize(len, 0.0);
            self.index.resize(len, 0);
            self.weight.resize(len, 0.0);
        }
    }
}

/// Compressed rows being built: `n` entries of `idx` and `val` are valid (the vectors are
/// longer, as [`RbfBlock`]'s).
#[derive(Default)]
struct SparseRows {
    ptr: Vec<usize>,
    idx: Vec<u32>,
    val: Vec<f32>,
    n: usize,
    /// A row being sorted into column order.
    scratch: Vec<(u32, f32)>,
}

impl SparseRows {
    /// Room for `more` entries and a vector store after them.
    fn room(&mut self, more: usize) {
        let need = self.n + more + LANES;
        if self.idx.len() < need {
            let len = need.max(2 * self.idx.len());
            self.idx.resize(len, 0);
            self.val.resize(len, 0.0);
        }
    }

    /// Appends a row's non-zero entries (in the order given) and closes it.
    fn push_row(&mut self, entries: impl ExactSizeIterator<Item = (u32, f32)>) {
        self.room(entries.len());
        for (i, v) in entries {
            if v != 0.0 {
                self.idx[self.n] = i;
                self.val[self.n] = v;
                self.n += 1;
            }
        }
        self.ptr.push(self.n);
    }
}

/// Every kept basis's exponent −z²/2, column and weight for the distances `d`, and each
/// distance's row end: a basis is kept when it lies within its own reach of u and has
/// z² <= [`RBF_Z2_MAX`] (every other basis is exactly 0 there).
fn scan(rbf: &GaussianRbf, d: &[f32], block: &mut RbfBlock, vector: bool) {
    #[cfg(target_arch = "x86_64")]
    if let (true, Some(v4)) = (vector, pulp::x86::V4::try_new()) {
        v4.vectorize(ScanV4 { v4, rbf, d, block });
        return;
    }
    #[cfg(not(target_arch = "x86_64"))]
    let _ = vector;
    for &di in d {
        let (u, env) = rbf.normalised(di);
        if u.is_finite() {
            let candidates = rbf.within_reach(u);
            block.room(candidates.len());
            for b in candidates {
                if (u - b.mean).abs() > b.reach {
                    continue;
                }
                let z = (u - b.mean) / b.std;
                let z2 = z * z;
                if z2 > RBF_Z2_MAX {
                    continue;
                }
                let n = block.n;
                block.exp[n] = -0.5 * z2;
                block.index[n] = b.index;
                block.weight[n] = b.weight;
                block.n += 1;
            }
        }
        block.row_end.push((u, env, block.n));
    }
}

/// Each distance's row from the block's exponentials: weight · e · envelope · normaliser
/// ([`super::rbf_basis_value`]'s order), values below [`RBF_MIN_VALUE`] left out, columns
/// in order.
fn emit(rbf: &GaussianRbf, block: &RbfBlock, rows: &mut SparseRows, vector: bool) {
    #[cfg(target_arch = "x86_64")]
    if vector && rbf.index_ordered {
        if let Some(v4) = pulp::x86::V4::try_new() {
            v4.vectorize(EmitV4 {
                v4,
                rbf,
                block,
                rows,
            });
            return;
        }
    }
    #[cfg(not(target_arch = "x86_64"))]
    let _ = vector;
    let mut start = 0;
    for &(u, env, end) in &block.row_end {
        if !u.is_finite() {
            rows.push_row((0..rbf.num_basis).map(|i| (i as u32, rbf.value(i, u, env))));
            continue;
        }
        let values = block.index[start..end]
            .iter()
            .zip(&block.weight[start..end])
            .zip(&block.exp[start..end])
            .map(|((&i, &weight), &e)| (i, rbf_scaled(weight, e, env, rbf.normalizer)));
        if rbf.index_ordered {
            // Mean order is column order: straight into the compressed row.
            rows.push_row(values);
        } else {
            rows.scratch.clear();
            rows.scratch.extend(values);
            rows.scratch.sort_unstable_by_key(|e| e.0);
            let row = std::mem::take(&mut rows.scratch);
            rows.push_row(row.iter().copied());
            rows.scratch = row;
        }
        start = end;
    }
}

/// The lanes below `left` (all 16 when `left` >= 16).
#[cfg(target_arch = "x86_64")]
#[inline(always)]
fn lanes_below(left: usize) -> u16 {
    if left >= LANES {
        u16::MAX
    } else {
        (1u16 << left) - 1
    }
}

/// The 16 values of `s` from `at` (zeros where `s` ends first: never, given the padding
/// and the buffers' room).
#[cfg(target_arch = "x86_64")]
#[inline(always)]
fn load<T: Copy + Default>(s: &[T], at: usize) -> [T; LANES] {
    match s.get(at..).and_then(|s| s.first_chunk::<LANES>()) {
        Some(c) => *c,
        None => [T::default(); LANES],
    }
}

/// Stores 16 values into `s` from `at` (the buffers keep room for it).
#[cfg(target_arch = "x86_64")]
#[inline(always)]
fn store<T: Copy>(s: &mut [T], at: usize, v: [T; LANES]) {
    if let Some(dst) = s.get_mut(at..).and_then(|s| s.first_chunk_mut::<LANES>()) {
        *dst = v;
    }
}

/// The lanes of `v` selected by `keep`, packed to the front (the rest 0).
#[cfg(target_arch = "x86_64")]
#[inline(always)]
fn packed_f32(v4: pulp::x86::V4, keep: u16, v: pulp::f32x16) -> [f32; LANES] {
    pulp::cast(v4.avx512f._mm512_maskz_compress_ps(keep, pulp::cast(v)))
}

/// [`packed_f32`] for columns.
#[cfg(target_arch = "x86_64")]
#[inline(always)]
fn packed_u32(v4: pulp::x86::V4, keep: u16, v: [u32; LANES]) -> [u32; LANES] {
    pulp::cast(v4.avx512f._mm512_maskz_compress_epi32(keep, pulp::cast(v)))
}

/// [`scan`] with AVX-512.
#[cfg(target_arch = "x86_64")]
struct ScanV4<'a> {
    v4: pulp::x86::V4,
    rbf: &'a GaussianRbf,
    d: &'a [f32],
    block: &'a mut RbfBlock,
}

#[cfg(target_arch = "x86_64")]
impl pulp::NullaryFnOnce for ScanV4<'_> {
    type Output = ();

    #[inline(always)]
    fn call(self) {
        use pulp::Simd;
        let ScanV4 { v4, rbf, d, block } = self;
        let cols = &rbf.columns;
        let (z2_max, minus_half) = (v4.splat_f32s(RBF_Z2_MAX), v4.splat_f32s(-0.5));
        for &di in d {
            let (u, env) = rbf.normalised(di);
            if u.is_finite() {
                let candidates = match &cols.windows {
                    Some(table) => table.window(u),
                    None => rbf.reach_range(u),
                };
                block.room(candidates.len());
                let at_u = v4.splat_f32s(u);
                for j in candidates.clone().step_by(LANES) {
                    let mean: pulp::f32x16 = pulp::cast(load(&cols.mean, j));
                    let diff = v4.sub_f32s(at_u, mean);
                    let z = v4.div_f32s(diff, pulp::cast(load(&cols.std, j)));
                    let z2 = v4.mul_f32s(z, z);
                    let far =
                        v4.cmp_gt_f32x16(v4.abs_f32x16(diff), pulp::cast(load(&cols.reach, j)));
                    let wide = v4.cmp_gt_f32x16(z2, z2_max);
                    let keep = lanes_below(candidates.end - j) & !far.0 & !wide.0;
                    let n = block.n;
                    let e = v4.mul_f32s(minus_half, z2);
                    store(&mut block.exp, n, packed_f32(v4, keep, e));
                    let index = packed_u32(v4, keep, load(&cols.index, j));
                    store(&mut block.index, n, index);
                    let weight = packed_f32(v4, keep, pulp::cast(load(&cols.weight, j)));
                    store(&mut block.weight, n, weight);
                    block.n += keep.count_ones() as usize;
                }
            }
            block.row_end.push((u, env, block.n));
        }
    }
}

/// [`emit`] with AVX-512, for bases whose mean order is their column order.
#[cfg(target_arch = "x86_64")]
struct EmitV4<'a> {
    v4: pulp::x86::V4,
    rbf: &'a GaussianRbf,
    block: &'a RbfBlock,
    rows: &'a mut SparseRows,
}

#[cfg(target_arch = "x86_64")]
impl pulp::NullaryFnOnce for EmitV4<'_> {
    type Output = ();

    #[inline(always)]
    fn call(self) {
        use pulp::Simd;
        let EmitV4 {
            v4,
            rbf,
            block,
            rows,
        } = self;
        let (normalizer, min) = (v4.splat_f32s(rbf.normalizer), v4.splat_f32s(RBF_MIN_VALUE));
        let mut start = 0;
        for &(u, env, end) in &block.row_end {
            if !u.is_finite() {
                rows.push_row((0..rbf.num_basis).map(|i| (i as u32, rbf.value(i, u, env))));
                continue;
            }
            rows.room(end - start);
            let env = v4.splat_f32s(env);
            for j in (start..end).step_by(LANES) {
                let weight: pulp::f32x16 = pulp::cast(load(&block.weight, j));
                let e: pulp::f32x16 = pulp::cast(load(&block.exp, j));
                let v = v4.mul_f32s(v4.mul_f32s(v4.mul_f32s(weight, e), env), normalizer);
                // A value below RBF_MIN_VALUE is 0 and left out; a NaN stays.
                let small = v4.cmp_lt_f32x16(v, min);
                let keep = lanes_below(end - j) & !small.0;
                let n = rows.n;
                store(&mut rows.val, n, packed_f32(v4, keep, v));
                store(
                    &mut rows.idx,
                    n,
                    packed_u32(v4, keep, load(&block.index, j)),
                );
                rows.n += keep.count_ones() as usize;
            }
            rows.ptr.push(rows.n);
            start = end;
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::fixtures::{StoredTensor, TensorData};
    use crate::weights::Weights;

    /// A radial basis with these means and the logits of its widths and weights.
    fn basis(mean: Vec<f32>, std_logit: Vec<f32>, weight_logit: Vec<f32>) -> GaussianRbf {
        let k = mean.len();
        let tensor = |v: Vec<f32>| StoredTensor {
            shape: vec![1, k],
            data: TensorData::F32(v),
        };
        let tensors = [
            ("mean", mean),
            ("std_logit", std_logit),
            ("weight_logit", weight_logit),
        ]
        .into_iter()
        .map(|(name, v)| (format!("rbf.{name}"), tensor(v)))
        .collect();
        let w = Weights::from_tensors("test", tensors);
        GaussianRbf::load(&w.scope("rbf."), 1.98).unwrap()
    }

    /// A value's bits, so that NaN rows compare too.
    fn bits(f: &EdgeFeatures) -> Vec<u32> {
        f.to_dense().iter().map(|v| v.to_bits()).collect()
    }

    #[test]
    fn vector_and_scalar_rows_equal_the_dense_values_in_any_mean_order() {
        // 1024 narrow bases over u in [0, 1] (the field heads' shape, widths varied), in
        // column order, shuffled, and with one mean far off (no window table then).
        let k = 1024;
        let ordered: Vec<f32> = (0..k).map(|i| i as f32 / k as f32).collect();
        let std_logit: Vec<f32> = (0..k).map(|i| -7.5 + (i * 37 % 11) as f32 * 0.1).collect();
        let weight_logit: Vec<f32> = (0..k).map(|i| ((i * 53 % 17) as f32 - 8.0) * 0.3).collect();
        let mut shuffled = ordered.clone();
        for i in 0..k {
            shuffled.swap(i, i * 389 % k);
        }
        let mut outlier = ordered.clone();
        outlier[k - 1] = 1e4;
        // Distances across the span and past both ends, the block size crossed, and the
        // ones every row treats apart.
        let d: Vec<f32> = (0..700)
            .map(|i| i as f32 * 3.1e-3 - 0.1)
            .chain([
                0.0,
                -0.0,
                1.98,
                1e30,
                -1e30,
                f32::INFINITY,
                f32::NEG_INFINITY,
                f32::NAN,
            ])
            .collect();
        for (name, mean, table) in [
            ("ordered", ordered, true),
            ("shuffled", shuffled, true),
            ("outlier", outlier, false),
        ] {
            let rbf = basis(mean, std_logit.clone(), weight_logit.clone());
            assert_eq!(rbf.index_ordered, name != "shuffled", "{name}");
            assert_eq!(rbf.columns.windows.is_some(), table, "{name}");
            let dense: Vec<u32> = rbf.forward(&d).iter().map(|v| v.to_bits()).collect();
            assert!(
                dense.iter().filter(|&&v| v != 0).count() > 10 * d.len(),
                "{name}: rows with values"
            );
            for vector in [true, false] {
                let rows = sparse_features_on(&rbf, &d, vector);
                assert!(matches!(rows, EdgeFeatures::Sparse { .. }), "{name}");
                assert_eq!(bits(&rows), dense, "{name}, vector {vector}: bit for bit");
                let EdgeFeatures::Sparse { ptr, idx, .. } = &rows else {
                    unreachable!()
                };
                for r in ptr.windows(2) {
                    assert!(
                        idx[r[0]..r[1]].windows(2).all(|w| w[0] < w[1]),
                        "{name}: columns in order"
                    );
                }
            }
        }
    }

    #[test]
    fn the_window_table_holds_every_basis_within_reach() {
        let k = 1024;
        let mean: Vec<f32> = (0..k)
            .map(|i| (i as f32 / k as f32).powi(2) * 0.7 + 0.05)
            .collect();
        let rbf = basis(mean, vec![-6.0; k], vec![0.0; k]);
        let table = rbf
            .columns
            .windows
            .as_ref()
            .expect("close means get a table");
        let (mut extra, mut within) = (0, 0);
        for i in 0..200_000 {
            let u = i as f32 * 7e-6 - 0.2;
            let (exact, window) = (rbf.reach_range(u), table.window(u));
            assert!(
                window.start <= exact.start && exact.end <= window.end,
                "u = {u}: {window:?} holds {exact:?}"
            );
            extra += window.len() - exact.len();
            within += exact.len();
        }
        assert!(within > 200_000 * 10, "windows of many bases ({within})");
        assert!(
            4 * extra < within,
            "few extra candidates ({extra} to {within})"
        );
    }
}
