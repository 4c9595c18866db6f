//! e^x, SiLU and the logistic sigmoid over whole slices, eight values at a time, each value
//! bit for bit what `f32::exp` gives it on x86-64 Linux.
//!
//! The release build targets plain x86-64, so every `f32::exp` is a call into glibc's `expf`
//! (its FMA variant, chosen at load time): about 5 % of a keyframe's CPU in gated mode, in
//! the radial MLPs' SiLU, the gated activation and the attention logits' smooth leaky ReLU.
//! glibc's `expf` (since 2.28, from Arm's optimized-routines) reduces x·32/ln 2 to an
//! integer k and a remainder r, looks 2^(k mod 32 / 32) up in a 32-entry table and evaluates
//! a cubic in r, all in f64 with four fused multiply-adds. The same operations on four f64
//! lanes (AVX2 + FMA through `pulp`'s `V3`, which AVX-512 machines also have) give the same
//! bits: checked for every one of the 2^32 f32 inputs
//! (`exp_equals_the_library_exp_for_every_f32`, ignored: half a minute in a release build).
//! Arguments the library treats apart (|x| ≥ 88, infinities, NaN) go to `f32::exp` itself,
//! eight at a time. Elsewhere (no AVX2/FMA, or another architecture) every value goes to
//! `f32::exp`.

/// 2^(i/32) as f64 bits, minus i << 47 (so that adding k << 47 puts k / 32 in the exponent):
/// glibc's `__exp2f_data.tab`.
const TABLE: [u64; 32] = [
    0x3ff0000000000000,
    0x3fefd9b0d3158574,
    0x3fefb5586cf9890f,
    0x3fef9301d0125b51,
    0x3fef72b83c7d517b,
    0x3fef54873168b9aa,
    0x3fef387a6e756238,
    0x3fef1e9df51fdee1,
    0x3fef06fe0a31b715,
    0x3feef1a7373aa9cb,
    0x3feedea64c123422,
    0x3feece086061892d,
    0x3feebfdad5362a27,
    0x3feeb42b569d4f82,
    0x3feeab07dd485429,
    0x3feea47eb03a5585,
    0x3feea09e667f3bcd,
    0x3fee9f75e8ec5f74,
    0x3feea11473eb0187,
    0x3feea589994cce13,
    0x3feeace5422aa0db,
    0x3feeb737b0cdc5e5,
    0x3feec49182a3f090,
    0x3feed503b23e255d,
    0x3feee89f995ad3ad,
    0x3feeff76f2fb5e47,
    0x3fef199bdd85529c,
    0x3fef3720dcef9069,
    0x3fef5818dcfba487,
    0x3fef7c97337b9b5f,
    0x3fefa4afa2a490da,
    0x3fefd0765b6e4540,
];
/// 32 / ln 2 (glibc's `invln2_scaled`), as bits.
const INV_LN2_32: u64 = 0x40471547652b82fe;
/// 1.5·2^52: adding it rounds to an integer held in the low mantissa bits.
const SHIFT: u64 = 0x4338000000000000;
/// The cubic's coefficients c0 r³ + c1 r² + c2 r + 1 (glibc's `poly_scaled`), as bits.
const POLY: [u64; 3] = [0x3ebc6af84b912394, 0x3f2ebfce50fac4f3, 0x3f962e42ff0c52d6];
/// The exponent bits at and above which glibc's `expf` leaves its main path (|x| ≥ 88,
/// infinities and NaN), as `f32` bits without the sign.
const SPECIAL_ABS_BITS: u32 = 0x42b0_0000;

/// What the kernel computes of each value.
#[derive(Clone, Copy, PartialEq, Eq)]
enum Op {
    /// e^x.
    Exp,
    /// x / (1 + e^−x), as [`crate::layers::silu`].
    Silu,
    /// 1 / (1 + e^−x), as [`crate::layers::sigmoid`].
    Sigmoid,
}

impl Op {
    /// The scalar form: the same bits as the vector one.
    fn scalar(self, x: f32) -> f32 {
        match self {
            Op::Exp => x.exp(),
            Op::Silu => crate::layers::silu(x),
            Op::Sigmoid => crate::layers::sigmoid(x),
        }
    }
}

/// e^x of every value of `v` in place (`f32::exp`'s bits).
pub fn exp_in_place(v: &mut [f32]) {
    apply(Op::Exp, v);
}

/// SiLU x / (1 + e^−x) of every value of `v` in place ([`crate::layers::silu`]'s bits).
pub fn silu_in_place(v: &mut [f32]) {
    apply(Op::Silu, v);
}

/// The logistic sigmoid 1 / (1 + e^−x) of every value of `v` in place
/// ([`crate::layers::sigmoid`]'s bits).
pub fn sigmoid_in_place(v: &mut [f32]) {
    apply(Op::Sigmoid, v);
}

fn apply(op: Op, v: &mut [f32]) {
    #[cfg(target_arch = "x86_64")]
    if let Some(v3) = pulp::x86::V3::try_new() {
        v3.vectorize(Kernel { v3, op, v });
        return;
    }
    for x in v {
        *x = op.scalar(*x);
    }
}

/// [`apply`] with AVX2 + FMA.
#[cfg(target_arch = "x86_64")]
struct Kernel<'a> {
    v3: pulp::x86::V3,
    op: Op,
    v: &'a mut [f32],
}

#[cfg(target_arch = "x86_64")]
impl pulp::NullaryFnOnce for Kernel<'_> {
    type Output = ();

    #[inline(always)]
    fn call(self) {
        use pulp::Simd;
        let Kernel { v3, op, v } = self;
        let (head, tail) = pulp::x86::V3::as_mut_simd_f32s(v);
        let (abs_bits, special) = (v3.splat_u32s(0x7fff_ffff), v3.splat_u32s(SPECIAL_ABS_BITS));
        let one = v3.splat_f32s(1.0);
        // No closures in here: they would not inherit the kernel's target features.
        for x in head {
            let arg = match op {
                Op::Exp => *x,
                Op::Silu | Op::Sigmoid => v3.neg_f32s(*x),
            };
            let bits: pulp::u32x8 = pulp::cast(arg);
            let mask: [u32; 8] = pulp::cast(v3.cmp_ge_u32x8(v3.and_u32s(bits, abs_bits), special));
            let any_special =
                mask[0] | mask[1] | mask[2] | mask[3] | mask[4] | mask[5] | mask[6] | mask[7];
            if any_special != 0 {
                let mut lanes: [f32; 8] = pulp::cast(*x);
                for lane in &mut lanes {
                    *lane = op.scalar(*lane);
                }
                *x = pulp::cast(lanes);
                continue;
            }
            let [lo, hi]: [pulp::f32x4; 2] = pulp::cast(arg);
            let e: pulp::f32x8 = pulp::cast([exp4(v3, lo), exp4(v3, hi)]);
            *x = match op {
                Op::Exp => e,
                Op::Silu => v3.div_f32s(*x, v3.add_f32s(one, e)),
                Op::Sigmoid => v3.div_f32s(one, v3.add_f32s(one, e)),
            };
        }
        for x in tail {
            *x = op.scalar(*x);
        }
    }
}

/// glibc's `expf` main path on four values (none of them special), in its order of
/// operations: k = round(x·32/ln 2) by the shift, r = x·32/ln 2 − k (both fused),
/// s = 2^(k/32) from the table, e^x = s·((c0 r + c1) r² + (c2 r + 1)).
#[cfg(target_arch = "x86_64")]
#[inline(always)]
fn exp4(v3: pulp::x86::V3, x: pulp::f32x4) -> pulp::f32x4 {
    use pulp::Simd;
    let inv_ln2 = v3.splat_f64s(f64::from_bits(INV_LN2_32));
    let shift = v3.splat_f64s(f64::from_bits(SHIFT));
    let xd = v3.convert_f32x4_to_f64x4(x);
    let shifted = v3.mul_add_f64s(inv_ln2, xd, shift);
    let ki: pulp::u64x4 = pulp::cast(shifted);
    let kd = v3.sub_f64s(shifted, shift);
    let r = v3.mul_sub_f64x4(inv_ln2, xd, kd);
    let k: [u64; 4] = pulp::cast(ki);
    let table: pulp::u64x4 = pulp::cast([
        TABLE[(k[0] % 32) as usize],
        TABLE[(k[1] % 32) as usize],
        TABLE[(k[2] % 32) as usize],
        TABLE[(k[3] % 32) as usize],
    ]);
    let s: pulp::f64x4 = pulp::cast(v3.add_u64s(table, v3.shl_const_u64x4::<47>(ki)));
    let [c0, c1, c2] = [
        v3.splat_f64s(f64::from_bits(POLY[0])),
        v3.splat_f64s(f64::from_bits(POLY[1])),
        v3.splat_f64s(f64::from_bits(POLY[2])),
    ];
    let z = v3.mul_add_f64s(r, c0, c1);
    let r2 = v3.mul_f64s(r, r);
    let y = v3.mul_add_f64s(r, c2, v3.splat_f64s(1.0));
    let y = v3.mul_add_f64s(z, r2, y);
    v3.convert_f64x4_to_f32x4(v3.mul_f64s(y, s))
}

#[cfg(test)]
pub(crate) mod tests {
    use super::{exp_in_place, sigmoid_in_place, silu_in_place};
    use crate::layers::{sigmoid, silu};

    /// Every 4099th f32 bit pattern (both signs, all exponents, NaN included), then the
    /// edges of the library's main path and its hardest inputs mixed into vectors of
    /// ordinary values.
    pub(crate) fn samples() -> Vec<f32> {
        let mut v: Vec<f32> = (0..=u32::MAX / 4099)
            .map(|i| f32::from_bits(i * 4099))
            .collect();
        for edge in [
            88.0f32,
            -88.0,
            87.99999,
            -87.99999,
            88.72284,
            88.72285,
            -103.27893,
            -103.97208,
            -104.0,
            f32::INFINITY,
            f32::NEG_INFINITY,
            f32::NAN,
            0.0,
            -0.0,
            f32::MIN_POSITIVE,
            // The only two f32s whose e^x changes when the remainder's multiply-add is not
            // fused (none changes with any of the other three unfused).
            f32::from_bits(0x4202_422f),
            f32::from_bits(0xc27c_65d9),
        ] {
            v.extend([0.5, -1.25, edge, 3.0, -7.5, 11.0, 0.001]);
        }
        v
    }

    fn assert_same(name: &str, xs: &[f32], want: impl Fn(f32) -> f32, run: fn(&mut [f32])) {
        // Odd lengths, so that every call also ends in a remainder.
        for chunk in xs.chunks(1003) {
            let mut got = chunk.to_vec();
            run(&mut got);
            for (&x, y) in chunk.iter().zip(&got) {
                let w = want(x);
                assert!(
                    y.to_bits() == w.to_bits() || (y.is_nan() && w.is_nan()),
                    "{name}({x:e}) = {y:e}, the scalar form gives {w:e}"
                );
            }
        }
    }

    #[test]
    fn the_table_holds_the_powers_of_two_and_the_constants_their_values() {
        // Entry i plus i << 47 is 2^(i/32) (to the last bit of an f64, within one ulp of
        // the library's exp2).
        for (i, &t) in super::TABLE.iter().enumerate() {
            let got = f64::from_bits(t + ((i as u64) << 47));
            let want = (i as f64 / 32.0).exp2();
            assert!(
                got.to_bits().abs_diff(want.to_bits()) <= 1,
                "2^({i}/32): {got} vs {want}"
            );
        }
        let inv = f64::from_bits(super::INV_LN2_32);
        assert!((inv - 32.0 / std::f64::consts::LN_2).abs() < 1e-13);
        assert_eq!(f64::from_bits(super::SHIFT), 1.5 * 2f64.powi(52));
        // The cubic approximates 2^(r/32) − 1 ≈ (ln2/32) r + (ln2/32)²/2 r² + (ln2/32)³/6 r³.
        let a = std::f64::consts::LN_2 / 32.0;
        for (c, want) in super::POLY.iter().zip([a * a * a / 6.0, a * a / 2.0, a]) {
            let c = f64::from_bits(*c);
            assert!(((c - want) / want).abs() < 1e-3, "{c} vs {want}");
        }
    }

    #[test]
    fn silu_and_sigmoid_of_slices_equal_the_scalar_forms_bit_for_bit() {
        let xs = samples();
        assert_same("silu", &xs, silu, silu_in_place);
        assert_same("sigmoid", &xs, sigmoid, sigmoid_in_place);
        // And they are what they say.
        let mut v = vec![-2.0f32, 0.0, 2.0, 30.0, -30.0, -100.0, 100.0, 1.0, 0.5];
        sigmoid_in_place(&mut v);
        for (x, s) in [-2.0f64, 0.0, 2.0, 30.0, -30.0, -100.0, 100.0, 1.0, 0.5]
            .iter()
            .zip(&v)
        {
            assert!(
                (f64::from(*s) - 1.0 / (1.0 + (-x).exp())).abs() < 1e-7,
                "σ({x})"
            );
        }
    }

    /// glibc's `expf` is the algorithm this module follows; other C libraries differ.
    #[cfg(all(target_os = "linux", target_env = "gnu"))]
    #[test]
    fn exp_of_slices_equals_the_library_exp_bit_for_bit() {
        assert_same("exp", &samples(), f32::exp, exp_in_place);
    }

    /// The whole of the claim: every f32 (2^32 of them; half a minute in a release build:
    /// `cargo test --release -p policy exp_equals -- --ignored`).
    #[cfg(all(target_os = "linux", target_env = "gnu"))]
    #[test]
    #[ignore = "2^32 values: run by hand with --release"]
    fn exp_equals_the_library_exp_for_every_f32() {
        let mut buf = vec![0.0f32; 1 << 16];
        let mut mismatches = 0u64;
        for high in 0..1u32 << 16 {
            for (low, b) in buf.iter_mut().enumerate() {
                *b = f32::from_bits(high << 16 | low as u32);
            }
            let mut got = buf.clone();
            exp_in_place(&mut got);
            mismatches += buf
                .iter()
                .zip(&got)
                .filter(|(x, y)| {
                    let w = x.exp();
                    y.to_bits() != w.to_bits() && !(y.is_nan() && w.is_nan())
                })
                .count() as u64;
        }
        assert_eq!(mismatches, 0);
    }
}
