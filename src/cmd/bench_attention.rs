//! `equact bench attention`: one equivariant graph attention layer of the physical network
//! (the first U-net block: 2048 nodes, 16 neighbours, l_max 3, m_max 2, 32 channels, parity
//! mode's reference S2 grid) timed against the same layer in PyTorch on CPU in the same run,
//! and against itself with the plain four products in its SO(2) convolutions' m > 0 blocks
//! instead of Gauss's three (alternating passes).
//!
//! The PyTorch side (`policy/benches/torch_attention.py`) is EquiformerV2's layer written with
//! the reference's buffers (read from the `graph_attention` fixture); it gets our inputs, our
//! edge-frame Wigner matrices and our radial features, so both time the layer alone, and its
//! output is checked against ours before any time counts.

use std::collections::HashMap;
use std::path::PathBuf;
use std::time::Instant;

use anyhow::Context;
use clap::Args;
use policy::attention::{EdgeSet, GraphAttention};
use policy::fixtures::{StoredTensor, TensorData};
use policy::layers::GaussianRbf;
use policy::predict::PolicyConfig;
use policy::so2_conv::MProducts;
use policy::so3::WignerCalculator;
use policy::weights::Weights;
use rand::{Rng, SeedableRng};

use super::bench::median;

/// The PyTorch layer (in the source tree; the benchmark runs from a checkout).
const TORCH_SCRIPT: &str = concat!(
    env!("CARGO_MANIFEST_DIR"),
    "/policy/benches/torch_attention.py"
);
/// The fixture whose buffers (coefficient orderings, S2 grids) the PyTorch layer reads.
const BUFFERS: &str = concat!(
    env!("CARGO_MANIFEST_DIR"),
    "/policy/tests/fixtures/graph_attention.safetensors"
);
/// The layer's module path in the physical network.
const PREFIX: &str = "down_blocks.0.block.";

/// Arguments of `equact bench attention`.
#[derive(Args, Debug)]
pub struct AttentionBenchArgs {
    /// Nodes of the graph (farthest points of a synthetic scene).
    #[arg(long, default_value_t = 2048)]
    pub nodes: usize,
    /// Timed forward passes per side and thread count (the median is reported).
    #[arg(long, default_value_t = 5)]
    pub reps: usize,
    /// Thread counts, comma-separated.
    #[arg(long, default_value = "1,2", value_delimiter = ',')]
    pub threads: Vec<usize>,
    /// A Python with `torch` and `safetensors` (e.g. .venv-bench/bin/python3): also time the
    /// PyTorch layer and print the speed-ups.
    #[arg(long)]
    pub torch: Option<PathBuf>,
    /// Seed of the weights, the scene and the features.
    #[arg(long, default_value_t = 1)]
    pub seed: u64,
}

/// Runs `equact bench attention`.
pub fn run(a: AttentionBenchArgs) -> anyhow::Result<()> {
    if a.threads.is_empty() || a.threads.contains(&0) || a.reps == 0 {
        anyhow::bail!("--threads takes counts of at least 1 (e.g. 1,2) and --reps at least 1");
    }
    let cfg = PolicyConfig::physical().with_mode(policy::predict::PolicyMode::Parity);
    let m = &cfg.model;
    let weights = policy::init::random_weights(m, &cfg.extra, a.seed);
    let attn_cfg = m.block_attention(0, m.sphere_channels[0]);
    let scope = weights.scope(PREFIX);
    let mut layer = GraphAttention::load(&scope.sub("transblock").sub("ga"), attn_cfg)?;
    let rbf = GaussianRbf::load(&scope.sub("distance_expansion"), m.max_radius[0] * 0.99)?;

    // The graph: farthest points of a synthetic scene, their 16-nearest-neighbour graph.
    let cloud = policy::predict::synthetic_scene(20_000, a.seed)?;
    let pts: Vec<[f32; 3]> = cloud.points.iter().map(|p| [p.x, p.y, p.z]).collect();
    let fps = policy::points::farthest_point_sampling(&pts, a.nodes)?;
    let coord: Vec<[f32; 3]> = fps.iter().map(|&i| pts[i]).collect();
    let (src, dst) = policy::model::knn_graph(&coord, m.max_neighbors[0])?;
    let calc = WignerCalculator::new(m.lmax)?;
    let edges = EdgeSet::new(&calc, m.lmax, &coord, &coord, src, dst, &rbf)?;
    let k = policy::so3::num_coefficients(m.lmax);
    let c = attn_cfg.sphere_channels;
    let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(a.seed);
    let x: Vec<f32> = (0..coord.len() * k * c)
        .map(|_| rng.random_range(-1.0..1.0f32))
        .collect();

    let mut ours = serde_json::Map::new();
    let mut plain = serde_json::Map::new();
    let mut gauss_speedups = serde_json::Map::new();
    let mut y = Vec::new();
    for &t in &a.threads {
        layer.set_threads(t);
        // Gauss's three products in the SO(2) convolutions (ours) against the plain four
        // (the reference's form), alternating so that both see the same machine.
        let mut times = [Vec::with_capacity(a.reps), Vec::with_capacity(a.reps)];
        for rep in 0..=a.reps {
            for (products, times) in [MProducts::Plain, MProducts::Gauss].iter().zip(&mut times) {
                layer.set_m_products(*products);
                let t0 = Instant::now();
                y = layer.forward(&x, &x, &edges)?;
                // The first pass of each warms the caches and is not counted.
                if rep > 0 {
                    times.push(t0.elapsed().as_secs_f64());
                }
            }
        }
        let [mut plain_times, mut gauss_times] = times;
        eprintln!("ours, {t} threads: {gauss_times:.4?} s (plain m products {plain_times:.4?} s)");
        let (p, g) = (median(&mut plain_times), median(&mut gauss_times));
        ours.insert(t.to_string(), serde_json::json!({"median_s": g}));
        plain.insert(t.to_string(), serde_json::json!({"median_s": p}));
        gauss_speedups.insert(t.to_string(), serde_json::json!(p / g));
    }
    let mut out = serde_json::json!({
        "layer": format!("{PREFIX}transblock.ga (SO2EquivariantGraphAttention, parity grid)"),
        "nodes": coord.len(),
        "edges": edges.len(),
        "lmax": m.lmax,
        "mmax": m.mmax,
        "channels": c,
        "timing": "wall-clock seconds of one forward pass (edges, frames and radial features given)",
        "ours": ours,
        "ours_plain_m_products": plain,
        "speedup_gauss_vs_plain_m_products": gauss_speedups,
    });
    if let Some(py) = &a.torch {
        let dir =
            std::env::temp_dir().join(format!("equact-bench-attention-{}", std::process::id()));
        std::fs::create_dir_all(&dir).with_context(|| format!("creating {}", dir.display()))?;
        let problem = dir.join("problem.safetensors");
        let config = serde_json::json!({
            "heads": attn_cfg.num_heads,
            "alpha": attn_cfg.alpha_channels,
            "value": attn_cfg.value_channels,
            "hidden": attn_cfg.hidden_channels,
            "lmax": attn_cfg.lmax,
            "mmax": attn_cfg.mmax,
        });
        // The problem file is tens of MB: gone again whether the comparison works or not.
        let compared = write_problem(&weights, &x, &edges, &y, [coord.len(), k, c], &problem)
            .and_then(|()| compare_with_torch(py, &problem, &config, &a, &out));
        std::fs::remove_dir_all(&dir).ok();
        let (torch, speedups) = compared?;
        out["torch"] = serde_json::Value::Object(torch);
        out["speedup_vs_torch"] = serde_json::Value::Object(speedups);
    }
    println!("{}", serde_json::to_string_pretty(&out)?);
    Ok(())
}

/// Runs the PyTorch layer on the problem for each thread count, refuses outputs that differ
/// from ours, and returns its results and the speed-ups over `out["ours"]`.
fn compare_with_torch(
    py: &std::path::Path,
    problem: &std::path::Path,
    config: &serde_json::Value,
    a: &AttentionBenchArgs,
    out: &serde_json::Value,
) -> anyhow::Result<(
    serde_json::Map<String, serde_json::Value>,
    serde_json::Map<String, serde_json::Value>,
)> {
    let mut torch = serde_json::Map::new();
    let mut speedups = serde_json::Map::new();
    for &t in &a.threads {
        let r = run_torch(py, problem, config, a.reps, t)?;
        let err = r["max_abs_err"].as_f64().unwrap_or(f64::INFINITY);
        let scale = r["max_abs_value"].as_f64().unwrap_or(1.0).max(1.0);
        if err.is_nan() || err > 1e-3 * scale {
            anyhow::bail!(
                "the PyTorch layer disagrees with ours (max abs error {err:.3e} on values up \
                     to {scale:.3}): the comparison would not time the same computation"
            );
        }
        let theirs = r["median_s"].as_f64().unwrap_or(f64::NAN);
        let mine = out["ours"][t.to_string()]["median_s"]
            .as_f64()
            .unwrap_or(f64::NAN);
        eprintln!(
            "torch, {t} threads: median {theirs:.4} s (ours {mine:.4} s: {:.2}x), max abs \
                 error {err:.2e}",
            theirs / mine
        );
        speedups.insert(t.to_string(), serde_json::json!(theirs / mine));
        torch.insert(t.to_string(), r);
    }
    Ok((torch, speedups))
}

/// Writes the PyTorch side's problem: the layer's parameters (`param.*`, reference names),
/// the inputs, our edge-frame matrices and our output.
fn write_problem(
    weights: &Weights,
    x: &[f32],
    edges: &EdgeSet,
    y: &[f32],
    [n, k, c]: [usize; 3],
    path: &std::path::Path,
) -> anyhow::Result<()> {
    let mut t: HashMap<String, StoredTensor> = HashMap::new();
    let f32t = |shape: Vec<usize>, v: Vec<f32>| StoredTensor {
        shape,
        data: TensorData::F32(v),
    };
    let ga = format!("{PREFIX}transblock.ga.");
    for key in weights.keys() {
        if let Some(name) = key.strip_prefix(&ga) {
            let (shape, v) = weights.f32_any(key)?;
            t.insert(format!("param.{name}"), f32t(shape, v));
        }
    }
    let e = edges.len();
    let idx = |v: &[usize]| StoredTensor {
        shape: vec![v.len()],
        data: TensorData::I64(v.iter().map(|&i| i as i64).collect()),
    };
    t.insert("in.x".into(), f32t(vec![n, k, c], x.to_vec()));
    t.insert("in.edge_src".into(), idx(&edges.src));
    t.insert("in.edge_dst".into(), idx(&edges.dst));
    let attr = edges.attr.to_dense();
    t.insert(
        "in.edge_attr".into(),
        f32t(vec![e, attr.len() / e.max(1)], attr),
    );
    t.insert(
        "buf.wigner".into(),
        f32t(vec![e, k, k], edges.wigners.d.clone()),
    );
    t.insert(
        "out.y".into(),
        f32t(vec![n, k, y.len() / (n * k).max(1)], y.to_vec()),
    );
    Weights::from_tensors("attention benchmark", t).save(path)?;
    Ok(())
}

/// Runs the PyTorch layer on the problem and returns its JSON line.
fn run_torch(
    py: &std::path::Path,
    problem: &std::path::Path,
    config: &serde_json::Value,
    reps: usize,
    threads: usize,
) -> anyhow::Result<serde_json::Value> {
    let out = std::process::Command::new(py)
        .arg(TORCH_SCRIPT)
        .arg("--problem")
        .arg(problem)
        .args(["--buffers", BUFFERS, "--config", &config.to_string()])
        .args([
            "--reps",
            &reps.to_string(),
            "--threads",
            &threads.to_string(),
        ])
        .output()
        .with_context(|| format!("running {} {TORCH_SCRIPT}", py.display()))?;
    if !out.status.success() {
        anyhow::bail!(
            "the PyTorch layer failed ({}); does {} have torch and safetensors? stderr:\n{}",
            out.status,
            py.display(),
            String::from_utf8_lossy(&out.stderr)
        );
    }
    let text = String::from_utf8_lossy(&out.stdout);
    let line = text.lines().last().unwrap_or_default();
    serde_json::from_str(line)
        .with_context(|| format!("reading the PyTorch layer's output {line:?}"))
}
