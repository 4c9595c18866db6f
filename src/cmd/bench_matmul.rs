//! `equact bench matmul`: the physical network's largest matrix products alone, for the
//! ceiling that `bench policy`'s `matrix_products` rate compares with.

use clap::Args;
use policy::matmul::{
    count_products, direct_products_available, gemm_acc, product_counts, use_direct_products,
    ProductCounts, Strided,
};

/// The sixteen product shapes (m, k, n) with the most multiply-adds in one keyframe of the
/// physical configuration (gated mode, 2048 points; traced from `matmul::gemm_acc` on
/// 2026-12-06, m the mean rows of the shape's calls). Together 70 % of its multiply-adds.
const PHYSICAL_SHAPES: [(usize, usize, usize); 16] = [
    (598, 128, 80),
    (395, 2048, 448),
    (512, 1024, 224),
    (521, 512, 112),
    (395, 1536, 192),
    (512, 768, 96),
    (521, 384, 48),
    (519, 256, 112),
    (519, 192, 48),
    (598, 16, 192),
    (598, 64, 16),
    (520, 16, 576),
    (395, 64, 4608),
    (538, 64, 64),
    (567, 32, 32),
    (592, 16, 16),
];

/// Arguments of `equact bench matmul`.
#[derive(Args, Debug)]
pub struct MatmulBenchArgs {
    /// Seconds to spend on each shape each way (as `gemm_acc` chooses, and all through
    /// `matrixmultiply`; at least three products each).
    #[arg(long, default_value_t = 0.5)]
    pub seconds: f64,
}

/// Runs `equact bench matmul`: JSON with each shape's rate on the calling thread.
pub fn run(a: MatmulBenchArgs) -> anyhow::Result<()> {
    let out = measure(a.seconds)?;
    println!("{}", serde_json::to_string_pretty(&out)?);
    Ok(())
}

/// Times every shape of [`PHYSICAL_SHAPES`] for about `seconds` each, as `gemm_acc` runs it
/// and all through `matrixmultiply`.
fn measure(seconds: f64) -> anyhow::Result<serde_json::Value> {
    count_products(true);
    if !(seconds.is_finite() && seconds > 0.0) {
        anyhow::bail!("--seconds must be a positive number of seconds, got {seconds}");
    }
    let mut shapes = Vec::new();
    for (m, k, n) in PHYSICAL_SHAPES {
        // Deterministic operands in [-1, 1]; the same ones every product (hot caches).
        let lhs: Vec<f32> = (0..m * k)
            .map(|i| (i * 37 % 101) as f32 / 50.0 - 1.0)
            .collect();
        let rhs: Vec<f32> = (0..k * n)
            .map(|i| (i * 53 % 97) as f32 / 48.0 - 1.0)
            .collect();
        let mut out = vec![0.0f32; m * n];
        let reps = ((seconds * 1e11 / (2 * m * k * n) as f64) as usize).max(3);
        // The product as `gemm_acc` runs it, then every product through `matrixmultiply`
        // (the baseline), alternated in two halves each so that a drifting machine shares
        // out evenly; the results are the same bits.
        let (mut chosen, mut packed) = (ProductCounts::default(), ProductCounts::default());
        for half in 0..4 {
            use_direct_products(half % 2 == 0);
            let before = product_counts();
            for _ in 0..reps.div_ceil(2) {
                gemm_acc(
                    Strided::row_major(&lhs, 0, m, k),
                    Strided::row_major(&rhs, 0, k, n),
                    &mut out,
                    0,
                    n,
                )?;
            }
            let counted = product_counts().since(before);
            let total = if half % 2 == 0 {
                &mut chosen
            } else {
                &mut packed
            };
            total.products += counted.products;
            total.multiply_adds += counted.multiply_adds;
            total.seconds += counted.seconds;
        }
        use_direct_products(true);
        let rate = chosen.flops_per_second() * 1e-9;
        let packed_rate = packed.flops_per_second() * 1e-9;
        shapes.push(serde_json::json!({
            "m": m, "k": k, "n": n,
            "products": chosen.products,
            "gflops_per_second": rate,
            "packed_gflops_per_second": packed_rate,
            "speedup_over_packed": rate / packed_rate,
        }));
    }
    Ok(serde_json::json!({
        "what": "the physical network's 16 largest product shapes alone, one thread, the same operands each time; compare bench policy's matrix_products.gflops_per_second. packed: every product through matrixmultiply, the baseline of the direct kernel",
        "direct_kernel": direct_products_available(),
        "shapes": shapes,
    }))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn every_shape_is_timed() {
        let out = measure(1e-4).unwrap_or_else(|e| panic!("{e}"));
        let shapes = out["shapes"].as_array().cloned().unwrap_or_default();
        assert_eq!(shapes.len(), PHYSICAL_SHAPES.len());
        for (s, (m, k, n)) in shapes.iter().zip(PHYSICAL_SHAPES) {
            assert_eq!(
                [&s["m"], &s["k"], &s["n"]],
                [m, k, n].map(serde_json::Value::from).each_ref()
            );
            assert!(s["products"].as_u64().unwrap_or(0) >= 3, "{s}");
            for rate in ["gflops_per_second", "packed_gflops_per_second"] {
                assert!(s[rate].as_f64().unwrap_or(0.0) > 0.0, "{s}");
            }
        }
    }

    #[test]
    fn a_time_that_is_not_positive_is_refused() {
        for bad in [0.0, -1.0, f64::NAN, f64::INFINITY] {
            let err = measure(bad).map(|_| ()).unwrap_err().to_string();
            assert!(err.contains("--seconds must be a positive"), "{err}");
        }
    }
}
