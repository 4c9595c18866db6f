//! `c += a · b` without packing `a`: the product for the network's many thin ones.
//!
//! `matrixmultiply` copies every left operand into its kernel's panel layout first (a
//! transpose of the row-major edge features), which costs about as much as the product
//! itself when the right operand is narrow (16-64 columns: the per-edge radial and SO(2)
//! maps). Here each row of `a` is read where it lies: a tile of `R` rows × `V` vectors of
//! output columns stays in registers while the depth runs, each step broadcasting one value
//! of each row against one row of `b`. `pulp` compiles it for AVX-512 behind a run-time
//! check, without `unsafe` here (its x86-64-v4 level needs Rust 1.89).
//!
//! The rounding is `matrixmultiply`'s exactly, so a product gives the same bits whichever
//! runs it: each output sums its terms in depth blocks of [`DEPTH_BLOCK`] (the crate's
//! `S_KC`), each block a chain of fused multiply-adds in depth order from +0, and each block
//! sum is added to `c` once, in order. `matrixmultiply`'s AVX-512 and FMA kernels do just
//! that; this one runs only where the first does.

// Only x86-64 runs the kernel; elsewhere the module is compiled but never called.
#![cfg_attr(not(target_arch = "x86_64"), allow(dead_code))]

use std::cell::RefCell;

use pulp::{Simd, WithSimd};

use super::Strided;

/// `matrixmultiply`'s depth block for `f32` (`archparam_defaults::S_KC`): its products add
/// each block's sum to the output separately, so this one must too to round the same.
const DEPTH_BLOCK: usize = 256;

/// Rows of a wide product's output done together, every column block down them, before the
/// next rows: their part of `a` stays cached across the column blocks.
const ROW_CHUNK: usize = 64;

thread_local! {
    /// The right operand copied into whole vectors per row (reused: no allocation per call).
    static PACKED_B: RefCell<Vec<f32>> = const { RefCell::new(Vec::new()) };
}

/// The operands of one product, checked by the caller: `a` with contiguous rows
/// (`col_stride` 1), `c`'s element (r, j) at `c_offset + r·c_rs + j`.
pub(super) struct Operands<'a, 'c> {
    pub a: Strided<'a>,
    pub b: Strided<'a>,
    pub c: &'c mut [f32],
    pub c_offset: usize,
    pub c_rs: usize,
}

/// Whether this CPU runs [`try_gemm_acc`]'s kernel (AVX-512F, with the AVX2 and FMA that
/// `pulp`'s x86-64-v4 level also asks for).
pub(super) fn available() -> bool {
    #[cfg(target_arch = "x86_64")]
    return pulp::x86::V4::try_new().is_some();
    #[cfg(not(target_arch = "x86_64"))]
    false
}

/// Computes `c += a · b` on an AVX-512 CPU; elsewhere returns the operands untouched, for
/// `matrixmultiply` to take (measured only against its AVX-512 kernel, so its AVX2 one is
/// left alone).
pub(super) fn try_gemm_acc<'a, 'c>(ops: Operands<'a, 'c>) -> Option<Operands<'a, 'c>> {
    #[cfg(target_arch = "x86_64")]
    if let Some(simd) = pulp::x86::V4::try_new() {
        PACKED_B.with_borrow_mut(|packed| Simd::vectorize(simd, Product { ops, packed }));
        return None;
    }
    Some(ops)
}

/// One product with its buffer for the right operand.
struct Product<'a, 'c, 'p> {
    ops: Operands<'a, 'c>,
    packed: &'p mut Vec<f32>,
}

impl WithSimd for Product<'_, '_, '_> {
    type Output = ();

    #[inline(always)]
    fn with_simd<S: Simd>(self, simd: S) {
        let Product { ops, packed } = self;
        let (k, n) = (ops.a.cols, ops.b.cols);
        let lanes = S::F32_LANES;
        let nv = n.div_ceil(lanes);
        // b's rows as whole vectors, the last one padded with zeros (the padded lanes'
        // outputs are never stored).
        packed.clear();
        packed.resize(k * nv * lanes, 0.0);
        for (kk, row) in packed.chunks_exact_mut(nv * lanes).enumerate() {
            let start = ops.b.offset + kk * ops.b.row_stride;
            for (j, x) in row[..n].iter_mut().enumerate() {
                *x = ops.b.data[start + j * ops.b.col_stride];
            }
        }
        let (bv, _) = S::as_simd_f32s(packed);
        let mut out = Output {
            c: ops.c,
            offset: ops.c_offset,
            rs: ops.c_rs,
            n,
        };
        let a = ops.a;
        let cols = Columns { bv, nv };
        for k0 in (0..k).step_by(DEPTH_BLOCK) {
            let depth = k0..(k0 + DEPTH_BLOCK).min(k);
            // Tiles whose accumulators, one broadcast and a row of b fit the 32 vector
            // registers (six rows by four vectors spilled). Up to four vectors of columns:
            // all rows down them. Wider: the rows in chunks, each down blocks of four
            // vectors across.
            match nv {
                1 => column_block::<S, 16, 1>(simd, &a, &cols, depth, &mut out),
                2 => column_block::<S, 8, 2>(simd, &a, &cols, depth, &mut out),
                3 => column_block::<S, 5, 3>(simd, &a, &cols, depth, &mut out),
                _ => row_blocks::<S, 4>(simd, &a, &cols, depth, &mut out),
            }
        }
    }
}

/// b's rows as vectors, `nv` per row.
struct Columns<'b, T> {
    bv: &'b [T],
    nv: usize,
}

/// The output: `n` columns per row, rows `rs` apart from `offset`.
struct Output<'c> {
    c: &'c mut [f32],
    offset: usize,
    rs: usize,
    n: usize,
}

/// All of the output's `V` column vectors (`V` = `nv`): tiles of `R` rows, then single rows.
#[inline(always)]
fn column_block<S: Simd, const R: usize, const V: usize>(
    simd: S,
    a: &Strided<'_>,
    cols: &Columns<'_, S::f32s>,
    depth: std::ops::Range<usize>,
    out: &mut Output<'_>,
) {
    let mut r0 = 0;
    while r0 + R <= a.rows {
        tile::<S, R, V>(simd, a, r0, cols, 0, depth.clone(), out);
        r0 += R;
    }
    while r0 < a.rows {
        tile::<S, 1, V>(simd, a, r0, cols, 0, depth.clone(), out);
        r0 += 1;
    }
}

/// Any number of column vectors: the rows in chunks of [`ROW_CHUNK`], each chunk down
/// blocks of four vectors across (then the last one to three) in tiles of `R` rows.
#[inline(always)]
fn row_blocks<S: Simd, const R: usize>(
    simd: S,
    a: &Strided<'_>,
    cols: &Columns<'_, S::f32s>,
    depth: std::ops::Range<usize>,
    out: &mut Output<'_>,
) {
    for chunk in (0..a.rows).step_by(ROW_CHUNK) {
        let rows = chunk..(chunk + ROW_CHUNK).min(a.rows);
        let mut v0 = 0;
        while v0 < cols.nv {
            match cols.nv - v0 {
                1 => down::<S, R, 1>(simd, a, rows.clone(), cols, v0, depth.clone(), out),
                2 => down::<S, R, 2>(simd, a, rows.clone(), cols, v0, depth.clone(), out),
                3 => down::<S, R, 3>(simd, a, rows.clone(), cols, v0, depth.clone(), out),
                _ => down::<S, R, 4>(simd, a, rows.clone(), cols, v0, depth.clone(), out),
            }
            v0 += 4;
        }
    }
}

/// Rows `rows` × column vectors `v0..v0 + V`: tiles of `R` rows, then single rows.
#[inline(always)]
fn down<S: Simd, const R: usize, const V: usize>(
    simd: S,
    a: &Strided<'_>,
    rows: std::ops::Range<usize>,
    cols: &Columns<'_, S::f32s>,
    v0: usize,
    depth: std::ops::Range<usize>,
    out: &mut Output<'_>,
) {
    let mut r0 = rows.start;
    while r0 + R <= rows.end {
        tile::<S, R, V>(simd, a, r0, cols, v0, depth.clone(), out);
        r0 += R;
    }
    while r0 < rows.end {
        tile::<S, 1, V>(simd, a, r0, cols, v0, depth.clone(), out);
        r0 += 1;
    }
}

/// Rows `r0..r0 + R` × column vectors `v0..v0 + V`: one depth block's fused multiply-add
/// chains from +0, then added to `c`.
#[inline(always)]
fn tile<S: Simd, const R: usize, const V: usize>(
    simd: S,
    a: &Strided<'_>,
    r0: usize,
    cols: &Columns<'_, S::f32s>,
    v0: usize,
    depth: std::ops::Range<usize>,
    out: &mut Output<'_>,
) {
    let len = depth.len();
    let rows: [&[f32]; R] = std::array::from_fn(|r| {
        let start = a.offset + (r0 + r) * a.row_stride + depth.start;
        &a.data[start..start + len]
    });
    let mut acc = [[simd.splat_f32s(0.0); V]; R];
    for (i, kk) in depth.enumerate() {
        let start = kk * cols.nv + v0;
        let b: [S::f32s; V] = std::array::from_fn(|v| cols.bv[start + v]);
        for (acc_r, row) in acc.iter_mut().zip(&rows) {
            let x = simd.splat_f32s(row[i]);
            for (acc_rv, bv) in acc_r.iter_mut().zip(&b) {
                *acc_rv = simd.mul_add_f32s(x, *bv, *acc_rv);
            }
        }
    }
    let lanes = S::F32_LANES;
    for (r, acc_r) in acc.iter().enumerate() {
        let start = out.offset + (r0 + r) * out.rs;
        for (v, sum) in acc_r.iter().enumerate() {
            let j = (v0 + v) * lanes;
            let width = (out.n - j).min(lanes);
            let dst = &mut out.c[start + j..start + j + width];
            let before = simd.partial_load_f32s(dst);
            simd.partial_store_f32s(dst, simd.add_f32s(before, *sum));
        }
    }
}
