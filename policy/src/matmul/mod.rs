//! Dense `f32` matrix products on flat (row-major or strided) slices.
//!
//! The products go through nalgebra's `gemm` on strided matrix views: for dynamically sized
//! `f32` matrices nalgebra hands them to `matrixmultiply`'s cache-blocked sgemm, which picks
//! its AVX2/FMA/AVX-512 kernel at run time (the crate itself is built for baseline x86-64).
//! This is how the per-edge layers run as a few large products instead of per-row loops.
//! On AVX-512 CPUs the products with at most 256 columns and contiguous left rows take an
//! unpacked kernel instead (the private `direct` module), which reads the left operand in
//! place rather than packing it and rounds every output exactly as `matrixmultiply` does.
//! Everything stays on the calling thread. Once [`count_products`] switched it on (`equact
//! bench policy` and `bench matmul` do), every product is counted (calls, multiply-adds,
//! seconds) in process-wide totals, [`product_counts`]: two clock reads per product, about
//! 0.05 % of a keyframe, but 1-2 % of a training step (its tape multiplies each edge's
//! rotation on its own), so it is off by default.

use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
use std::time::Instant;

use nalgebra::{DMatrixView, DMatrixViewMut};

use crate::error::{PolicyError, Result};

mod direct;

/// A read-only strided matrix inside a flat slice: element (r, c) is
/// `data[offset + r·row_stride + c·col_stride]`.
#[derive(Debug, Clone, Copy)]
pub struct Strided<'a> {
    /// The backing values.
    pub data: &'a [f32],
    /// Index of element (0, 0).
    pub offset: usize,
    /// Rows.
    pub rows: usize,
    /// Columns.
    pub cols: usize,
    /// Step between rows.
    pub row_stride: usize,
    /// Step between columns.
    pub col_stride: usize,
}

impl<'a> Strided<'a> {
    /// A contiguous row-major `[rows, cols]` matrix starting at `offset`.
    pub fn row_major(data: &'a [f32], offset: usize, rows: usize, cols: usize) -> Self {
        Self {
            data,
            offset,
            rows,
            cols,
            row_stride: cols,
            col_stride: 1,
        }
    }

    /// The transpose of this matrix (same values, strides swapped).
    pub fn t(self) -> Self {
        Self {
            rows: self.cols,
            cols: self.rows,
            row_stride: self.col_stride,
            col_stride: self.row_stride,
            ..self
        }
    }
}

/// One past the last index a strided `[rows, cols]` matrix touches (0 when empty).
fn extent(offset: usize, rows: usize, cols: usize, rs: usize, cs: usize) -> usize {
    if rows == 0 || cols == 0 {
        offset
    } else {
        offset + (rows - 1) * rs + (cols - 1) * cs + 1
    }
}

/// The error for a product whose operands do not fit their slices or each other.
fn bad_operand(what: &str, expected: Vec<usize>, got: Vec<usize>) -> PolicyError {
    PolicyError::ShapeMismatch {
        name: format!("matrix product {what}"),
        expected,
        got,
    }
}

/// nalgebra forwards a product to `matrixmultiply` only when every size exceeds this; its
/// generic path for smaller ones wrote outside row-strided views in a test here, so those
/// products use [`small_gemm_acc`] instead.
const SMALL: usize = 5;

/// The widest right operand [`direct`] takes: beyond it `matrixmultiply`'s packed panels
/// keep `b` in cache better (`equact bench matmul`, 2026-12-07: 448 and 4608 columns ran at
/// 0.9× and 0.75× of its speed, 16-224 at 1.1-2.2×).
const DIRECT_MAX_COLUMNS: usize = 256;

/// Whether a product with `n` output columns takes the same path (and so rounds each
/// output the same way) as one with `full` columns and otherwise the same operands: a
/// layer restricted to some of its outputs gives those outputs to the bit only then.
pub fn same_rounding(full: usize, n: usize) -> bool {
    (full <= SMALL) == (n <= SMALL)
}

/// `c += a · b` by the definition (products with a side of at most [`SMALL`]).
fn small_gemm_acc(a: &Strided<'_>, b: &Strided<'_>, c: &mut [f32], c_offset: usize, c_rs: usize) {
    for r in 0..a.rows {
        let row = &mut c[c_offset + r * c_rs..c_offset + r * c_rs + b.cols];
        for i in 0..a.cols {
            let x = a.data[a.offset + r * a.row_stride + i * a.col_stride];
            let bi = b.offset + i * b.row_stride;
            if b.col_stride == 1 {
                // Contiguous rows of b: a vectorisable axpy.
                for (y, bv) in row.iter_mut().zip(&b.data[bi..bi + b.cols]) {
                    *y += x * bv;
                }
            } else {
                for (j, y) in row.iter_mut().enumerate() {
                    *y += x * b.data[bi + j * b.col_stride];
                }
            }
        }
    }
}

/// Whether [`gemm_acc`] may take [`direct`]'s kernel (on unless a benchmark's baseline
/// switched it off).
static DIRECT: AtomicBool = AtomicBool::new(true);

/// Lets [`gemm_acc`] take the unpacked AVX-512 kernel for the products it suits (`true`,
/// the default) or sends every product to `matrixmultiply` (`false`: the baseline that
/// `equact bench matmul` and `bench policy --compare-packed` time it against). The results
/// are the same bits either way.
pub fn use_direct_products(on: bool) {
    DIRECT.store(on, Ordering::Relaxed);
}

/// Whether this CPU has the unpacked kernel (AVX-512); without it every product goes to
/// `matrixmultiply`.
pub fn direct_products_available() -> bool {
    direct::available()
}

static COUNTING: AtomicBool = AtomicBool::new(false);
static PRODUCTS: AtomicU64 = AtomicU64::new(0);
static MULTIPLY_ADDS: AtomicU64 = AtomicU64::new(0);
static PRODUCT_NANOS: AtomicU64 = AtomicU64::new(0);

/// Totals of [`gemm_acc`]'s products since the process started, over all threads.
#[derive(Debug, Clone, Copy, Default, PartialEq)]
pub struct ProductCounts {
    /// Products computed (empty ones not counted).
    pub products: u64,
    /// Their multiply-adds, m·k·n each.
    pub multiply_adds: u64,
    /// Wall-clock seconds inside them, summed over the threads that ran them.
    pub seconds: f64,
}

impl ProductCounts {
    /// What was counted between `earlier` and `self`.
    pub fn since(self, earlier: Self) -> Self {
        Self {
            products: self.products.saturating_sub(earlier.products),
            multiply_adds: self.multiply_adds.saturating_sub(earlier.multiply_adds),
            seconds: (self.seconds - earlier.seconds).max(0.0),
        }
    }

    /// Floating-point operations per second (two per multiply-add); 0 when nothing ran.
    pub fn flops_per_second(&self) -> f64 {
        if self.seconds > 0.0 {
            2.0 * self.multiply_adds as f64 / self.seconds
        } else {
            0.0
        }
    }
}

/// Switches the counting of [`gemm_acc`]'s products on or off for the whole process (off
/// when it starts).
pub fn count_products(on: bool) {
    COUNTING.store(on, Ordering::Relaxed);
}

/// The products counted so far in this process (while counting was on).
pub fn product_counts() -> ProductCounts {
    ProductCounts {
        products: PRODUCTS.load(Ordering::Relaxed),
        multiply_adds: MULTIPLY_ADDS.load(Ordering::Relaxed),
        seconds: PRODUCT_NANOS.load(Ordering::Relaxed) as f64 * 1e-9,
    }
}

/// `c += a · b` with `c` a strided `[a.rows, b.cols]` matrix inside `c_data`
/// (element (r, j) at `c_offset + r·c_rs + j`).
///
/// Errors if the inner sizes differ or an operand reaches past its slice.
pub fn gemm_acc(
    a: Strided<'_>,
    b: Strided<'_>,
    c_data: &mut [f32],
    c_offset: usize,
    c_rs: usize,
) -> Result<()> {
    let (m, k, n) = (a.rows, a.cols, b.cols);
    if b.rows != k {
        return Err(bad_operand(
            "inner sizes",
            vec![m, k, n],
            vec![b.rows, b.cols],
        ));
    }
    for (what, s) in [("left operand", &a), ("right operand", &b)] {
        let end = extent(s.offset, s.rows, s.cols, s.row_stride, s.col_stride);
        if end > s.data.len() {
            return Err(bad_operand(what, vec![end], vec![s.data.len()]));
        }
    }
    let end = extent(c_offset, m, n, c_rs, 1);
    if end > c_data.len() || (m > 1 && c_rs < n) {
        return Err(bad_operand("output", vec![end], vec![c_data.len()]));
    }
    if m == 0 || n == 0 || k == 0 {
        return Ok(());
    }
    let start = COUNTING.load(Ordering::Relaxed).then(Instant::now);
    if m <= SMALL || n <= SMALL || k <= SMALL {
        small_gemm_acc(&a, &b, c_data, c_offset, c_rs);
    } else if a.col_stride == 1 && n <= DIRECT_MAX_COLUMNS && DIRECT.load(Ordering::Relaxed) {
        let ops = direct::Operands {
            a,
            b,
            c: c_data,
            c_offset,
            c_rs,
        };
        if let Some(ops) = direct::try_gemm_acc(ops) {
            large_gemm_acc(&a, &b, ops.c, c_offset, c_rs);
        }
    } else {
        large_gemm_acc(&a, &b, c_data, c_offset, c_rs);
    }
    let Some(start) = start else {
        return Ok(());
    };
    let nanos = u64::try_from(start.elapsed().as_nanos()).unwrap_or(u64::MAX);
    PRODUCTS.fetch_add(1, Ordering::Relaxed);
    MULTIPLY_ADDS.fetch_add((m * k * n) as u64, Ordering::Relaxed);
    PRODUCT_NANOS.fetch_add(nanos, Ordering::Relaxed);
    Ok(())
}

/// `c += a · b` through nalgebra's `gemm` (every side larger than [`SMALL`]; operands checked).
fn large_gemm_acc(
    a: &Strided<'_>,
    b: &Strided<'_>,
    c_data: &mut [f32],
    c_offset: usize,
    c_rs: usize,
) {
    let (m, k, n) = (a.rows, a.cols, b.cols);
    let av =
        DMatrixView::from_slice_with_strides(&a.data[a.offset..], m, k, a.row_stride, a.col_stride);
    let bv =
        DMatrixView::from_slice_with_strides(&b.data[b.offset..], k, n, b.row_stride, b.col_stride);
    // A single output row has no row step to speak of; any value >= n keeps the view valid.
    let c_rs = if m == 1 { n.max(1) } else { c_rs };
    let mut cv =
        DMatrixViewMut::from_slice_with_strides_mut(&mut c_data[c_offset..], m, n, c_rs, 1);
    cv.gemm(1.0, &av, &bv, 1.0);
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The product by the definition, for comparison.
    fn naive(a: &Strided<'_>, b: &Strided<'_>) -> Vec<f32> {
        let at = |s: &Strided<'_>, r: usize, c: usize| {
            s.data[s.offset + r * s.row_stride + c * s.col_stride]
        };
        let mut out = vec![0.0; a.rows * b.cols];
        for r in 0..a.rows {
            for j in 0..b.cols {
                out[r * b.cols + j] = (0..a.cols).map(|i| at(a, r, i) * at(b, i, j)).sum();
            }
        }
        out
    }

    #[test]
    fn strided_products_match_the_definition() {
        let vals: Vec<f32> = (0..4000)
            .map(|i| ((i * 37 % 101) as f32 - 50.0) / 25.0)
            .collect();
        // Row-major a [9, 13] at offset 5; b the transpose of a row-major [11, 13] block.
        let a = Strided::row_major(&vals, 5, 9, 13);
        let b = Strided::row_major(&vals, 300, 11, 13).t();
        let want = naive(&a, &b);
        // Output rows of 11 inside rows of 20, starting at 3; the rest must stay untouched.
        let mut c = vec![1.0f32; 3 + 9 * 20];
        gemm_acc(a, b, &mut c, 3, 20).unwrap_or_else(|e| panic!("{e}"));
        for r in 0..9 {
            for j in 0..20 {
                let got = c[3 + r * 20 + j];
                let expect = if j < 11 { 1.0 + want[r * 11 + j] } else { 1.0 };
                assert!((got - expect).abs() < 1e-4, "({r}, {j}): {got} vs {expect}");
            }
        }
    }

    #[test]
    fn small_and_large_shapes_match_the_definition() {
        for (m, k, n) in [(100, 3, 32), (1, 128, 70), (2, 9, 1), (40, 64, 48)] {
            let a_vals: Vec<f32> = (0..m * k).map(|i| (i % 7) as f32 - 3.0).collect();
            let b_vals: Vec<f32> = (0..k * n).map(|i| (i % 5) as f32 - 2.0).collect();
            let a = Strided::row_major(&a_vals, 0, m, k);
            let b = Strided::row_major(&b_vals, 0, k, n);
            let want = naive(&a, &b);
            // A guard region after the output must stay untouched.
            let mut c = vec![0.0f32; m * n + 16];
            gemm_acc(a, b, &mut c[..m * n], 0, n).unwrap_or_else(|e| panic!("{e}"));
            assert_eq!(&c[..m * n], &want[..], "{m}×{k}×{n}");
            assert!(c[m * n..].iter().all(|v| *v == 0.0));
        }
    }

    /// Values spread over six decades with both signs, so that sums round differently
    /// when their order or fusing changes.
    fn spread_values(len: usize, seed: u64) -> Vec<f32> {
        let mut x = seed.wrapping_mul(0x9E37_79B9_7F4A_7C15) | 1;
        (0..len)
            .map(|_| {
                x ^= x << 13;
                x ^= x >> 7;
                x ^= x << 17;
                let unit = (x >> 40) as f32 / (1u64 << 24) as f32;
                let scale = 10f32.powi((x % 7) as i32 - 3);
                (2.0 * unit - 1.0) * scale
            })
            .collect()
    }

    #[test]
    fn the_direct_kernel_rounds_every_output_as_matrixmultiply() {
        if !direct_products_available() {
            eprintln!("no AVX-512 on this CPU: every product goes to matrixmultiply");
            return;
        }
        let mut differs_from_plain_sums = false;
        // One to five vectors of columns with a partial last one, whole and partial row
        // tiles and row chunks, depths across `direct`'s 256-deep blocks, b row-major and
        // transposed, output rows wider than the product.
        for (i, &(m, k, n, b_transposed, c_rs)) in [
            (6, 6, 6, false, 6),
            (37, 300, 33, false, 40),
            (40, 513, 64, true, 64),
            (23, 40, 70, false, 75),
            (130, 64, 250, true, 256),
            (67, 257, 16, false, 16),
            (9, 7, 17, true, 17),
        ]
        .iter()
        .enumerate()
        {
            let a_vals = spread_values(m * k + 3, 2 * i as u64);
            let b_vals = spread_values(k * n, 2 * i as u64 + 1);
            let a = Strided::row_major(&a_vals, 3, m, k);
            let b = if b_transposed {
                Strided::row_major(&b_vals, 0, n, k).t()
            } else {
                Strided::row_major(&b_vals, 0, k, n)
            };
            let start = spread_values(m * c_rs, 99);
            let mut packed = start.clone();
            large_gemm_acc(&a, &b, &mut packed, 0, c_rs);
            let mut direct = start.clone();
            let ops = direct::Operands {
                a,
                b,
                c: &mut direct,
                c_offset: 0,
                c_rs,
            };
            assert!(direct::try_gemm_acc(ops).is_none(), "the kernel declined");
            for r in 0..m {
                for j in 0..c_rs {
                    let (got, want) = (direct[r * c_rs + j], packed[r * c_rs + j]);
                    assert_eq!(got.to_bits(), want.to_bits(), "{m}×{k}×{n} ({r}, {j})");
                    if j >= n {
                        assert_eq!(got.to_bits(), start[r * c_rs + j].to_bits());
                    }
                }
            }
            // The comparison sees rounding: plain (unfused, one-block) sums differ.
            let plain = naive(&a, &b);
            differs_from_plain_sums |= (0..m * n).any(|e| {
                let (r, j) = (e / n, e % n);
                (start[r * c_rs + j] + plain[e]).to_bits() != direct[r * c_rs + j].to_bits()
            });
        }
        assert!(differs_from_plain_sums);
    }

    #[test]
    fn products_are_counted() {
        let (m, k, n) = (12, 7, 9);
        let vals = vec![0.5f32; m * k + k * n];
        let a = Strided::row_major(&vals, 0, m, k);
        let b = Strided::row_major(&vals, m * k, k, n);
        let mut c = vec![0.0f32; m * n];
        count_products(true);
        let before = product_counts();
        gemm_acc(a, b, &mut c, 0, n).unwrap_or_else(|e| panic!("{e}"));
        // An empty product is not counted.
        gemm_acc(Strided::row_major(&vals, 0, 0, k), b, &mut c, 0, n)
            .unwrap_or_else(|e| panic!("{e}"));
        let counted = product_counts().since(before);
        // Other tests may run products at the same time: at least this one is counted.
        assert!(counted.products >= 1, "{counted:?}");
        assert!(counted.multiply_adds >= (m * k * n) as u64, "{counted:?}");
        assert!(
            counted.seconds > 0.0 && counted.flops_per_second() > 0.0,
            "{counted:?}"
        );
        assert!(c.iter().all(|v| (*v - 0.25 * k as f32).abs() < 1e-6));
        let zero = ProductCounts::default();
        assert_eq!(zero.since(counted), zero);
        assert_eq!(zero.flops_per_second(), 0.0);
    }

    #[test]
    fn operands_past_their_slices_are_errors() {
        let vals = vec![0.0f32; 20];
        let a = Strided::row_major(&vals, 0, 4, 5);
        let too_long = Strided::row_major(&vals, 10, 5, 3);
        let mut c = vec![0.0f32; 12];
        assert!(gemm_acc(a, too_long, &mut c, 0, 3).is_err());
        let b = Strided::row_major(&vals, 0, 5, 3);
        assert!(gemm_acc(a, b, &mut c[..11], 0, 3).is_err());
        assert!(gemm_acc(a, b, &mut c, 0, 3).is_ok());
        let wrong_inner = Strided::row_major(&vals, 0, 4, 3);
        assert!(gemm_acc(a, wrong_inner, &mut c, 0, 3).is_err());
    }
}
