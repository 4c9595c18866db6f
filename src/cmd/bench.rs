//! `equact bench ...`: benchmarks that print a JSON summary (timings are compared as ratios
//! within one run, never asserted in tests).

use anyhow::Context;
use clap::{Args, Subcommand};
use planner::mbm::{
    mbm_robot, mbm_robot_with_ik, run_problem_with, summarize, time_collision_checks, GoalKind,
    MbmFile, WorldMode,
};
use planner::{CloudParams, Planner, PlannerConfig, PlannerLimits, World};
use std::time::Instant;

/// Arguments of `equact bench`.
#[derive(Args, Debug)]
pub struct BenchArgs {
    /// Which benchmark.
    #[command(subcommand)]
    pub what: BenchWhat,
}

/// The benchmarks.
#[derive(Subcommand, Debug)]
pub enum BenchWhat {
    /// MotionBenchMaker UR5 problems: as primitives and as 1 cm surface clouds.
    Planner(PlannerBenchArgs),
    /// The UR driver's streaming-loop jitter at 125 and 500 Hz.
    Ur(super::bench_ur::BenchUrArgs),
    /// The EquAct policy, physical configuration: per-stage timing of a keyframe and the
    /// equivariance error of parity and equivariant mode over random SE(3) motions.
    Policy(PolicyBenchArgs),
    /// One graph attention layer of the physical network, ours against PyTorch's on CPU.
    Attention(super::bench_attention::AttentionBenchArgs),
    /// The physical network's largest matrix products alone (their rate without the rest).
    Matmul(super::bench_matmul::MatmulBenchArgs),
}

/// Arguments of `equact bench policy`.
#[derive(Args, Debug)]
pub struct PolicyBenchArgs {
    /// Points fed to the network.
    #[arg(long, default_value_t = 2048)]
    pub points: usize,
    /// Random SE(3) motions of the equivariance measurement.
    #[arg(long, default_value_t = 10)]
    pub repeats: usize,
    /// Timed predictions per mode (the median is reported).
    #[arg(long, default_value_t = 3)]
    pub predictions: usize,
    /// Points of the synthetic input cloud.
    #[arg(long, default_value_t = 20_000)]
    pub cloud_points: usize,
    /// S2 grid size of `equivariant` in --mode.
    #[arg(long, default_value_t = 16)]
    pub s2_grid: usize,
    /// Modes, comma-separated: parity, equivariant (with --s2-grid), equivariant:N (N × N
    /// grids), gated. Default: parity, equivariant, gated.
    #[arg(long)]
    pub mode: Option<String>,
    /// Largest angle (rad) between the moved input's best rotation and the motion times the
    /// unmoved input's best rotation that counts as "the argmax moves with the input".
    #[arg(long, default_value_t = 1e-2)]
    pub argmax_tolerance: f64,
    /// Seed of the motions, the scene and the predictions.
    #[arg(long, default_value_t = 1)]
    pub seed: u64,
    /// Thread counts to time each mode with, comma-separated (the first is the baseline of
    /// the wall-clock speed-ups; the equivariance runs on the last).
    #[arg(long, default_value = "1", value_delimiter = ',')]
    pub threads: Vec<usize>,
    /// Also time each prediction with every matrix product through `matrixmultiply`
    /// (alternated with the normal ones): the baseline of the unpacked AVX-512 kernel.
    #[arg(long)]
    pub compare_packed: bool,
}

/// Arguments of `equact bench planner`.
#[derive(Args, Debug)]
pub struct PlannerBenchArgs {
    /// The MBM problems file (planner/data/mbm_ur5/problems.json).
    #[arg(long)]
    pub problems: std::path::PathBuf,
    /// Print the JSON summary only.
    #[arg(long)]
    pub json: bool,
    /// Only the first N valid problems of each scene.
    #[arg(long)]
    pub limit: Option<usize>,
    /// Only one mode: primitives or cloud.
    #[arg(long)]
    pub mode: Option<String>,
    /// RRT seed.
    #[arg(long, default_value_t = 1)]
    pub seed: u64,
    /// RRT-Connect extension step (rad, max-norm); the planner's default when absent.
    #[arg(long)]
    pub range: Option<f64>,
    /// Largest motion of any robot point between two checks during the search (m); the
    /// planner's default when absent (the dense re-checks keep their own spacing).
    #[arg(long)]
    pub check_resolution: Option<f64>,
    /// Only the scenes whose name contains this.
    #[arg(long)]
    pub scene: Option<String>,
    /// Give each goal as the TCP pose of the MBM goal configuration: the planner runs IK and
    /// picks the solution (its time is the "IK+goal" column, and is in the plan time). The
    /// gripper's closing volume is off (the MBM goals are not grasps: with it, the cloud
    /// points it covers would be dropped and the cloud mode would plan in another world).
    #[arg(long)]
    pub goal_pose: bool,
    /// Also run OMPL's RRTConnect on the same problems with the same collision checker, using
    /// this Python (a venv with `ompl`, see planner/benches/ompl_rrtconnect.py), and print the
    /// ratio of the search medians.
    #[arg(long)]
    pub ompl: Option<std::path::PathBuf>,
    /// OMPL's time budget per problem (s).
    #[arg(long, default_value_t = 5.0)]
    pub ompl_budget: f64,
    /// The checker library for OMPL (default: libplanner_ffi.so next to this binary; build it
    /// with `cargo build --release -p planner_ffi`).
    #[arg(long)]
    pub ompl_lib: Option<std::path::PathBuf>,
}

/// The OMPL driver script (in the source tree; the benchmark runs from a checkout).
const OMPL_SCRIPT: &str = concat!(
    env!("CARGO_MANIFEST_DIR"),
    "/planner/benches/ompl_rrtconnect.py"
);

/// Runs OMPL's RRTConnect through the Python driver; the parsed JSON, or why it could not run.
fn run_ompl(
    a: &PlannerBenchArgs,
    python: &std::path::Path,
    mode: WorldMode,
) -> Result<serde_json::Value, String> {
    let lib = match &a.ompl_lib {
        Some(l) => l.clone(),
        None => std::env::current_exe()
            .map_err(|e| format!("locating this binary: {e}"))?
            .with_file_name(format!(
                "{}planner_ffi{}",
                std::env::consts::DLL_PREFIX,
                std::env::consts::DLL_SUFFIX
            )),
    };
    if !lib.exists() {
        return Err(format!(
            "{} not found: build it with `cargo build --release -p planner_ffi` (or pass --ompl-lib)",
            lib.display()
        ));
    }
    let mut cmd = std::process::Command::new(python);
    cmd.arg(OMPL_SCRIPT)
        .arg("--lib")
        .arg(&lib)
        .arg("--problems")
        .arg(&a.problems)
        .arg("--mode")
        .arg(match mode {
            WorldMode::Primitives => "primitives",
            WorldMode::Cloud => "cloud",
        })
        .arg("--budget")
        .arg(a.ompl_budget.to_string());
    if let Some(n) = a.limit {
        cmd.arg("--limit").arg(n.to_string());
    }
    let out = cmd
        .output()
        .map_err(|e| format!("running {} {OMPL_SCRIPT}: {e}", python.display()))?;
    let stdout = String::from_utf8_lossy(&out.stdout);
    let parsed: Option<serde_json::Value> = stdout
        .lines()
        .rev()
        .find_map(|l| serde_json::from_str(l).ok());
    match parsed {
        Some(v) if out.status.success() && v.get("error").is_none() => Ok(v),
        Some(v) if v.get("error").is_some() => Err(format!("OMPL driver: {}", v["error"])),
        _ => Err(format!(
            "OMPL driver exited with {} and no result; stderr: {}",
            out.status,
            String::from_utf8_lossy(&out.stderr)
                .lines()
                .rev()
                .take(5)
                .collect::<Vec<_>>()
                .join(" | ")
        )),
    }
}

/// Runs `equact bench`.
pub fn run(args: BenchArgs) -> anyhow::Result<()> {
    match args.what {
        BenchWhat::Planner(a) => run_planner(a),
        BenchWhat::Ur(a) => super::bench_ur::run(a),
        BenchWhat::Policy(a) => {
            // The report's `matrix_products` per keyframe.
            policy::matmul::count_products(true);
            run_policy(a)
        }
        BenchWhat::Attention(a) => super::bench_attention::run(a),
        BenchWhat::Matmul(a) => super::bench_matmul::run(a),
    }
}

fn run_planner(a: PlannerBenchArgs) -> anyhow::Result<()> {
    let text = std::fs::read_to_string(&a.problems)
        .with_context(|| format!("reading {}", a.problems.display()))?;
    let file = MbmFile::parse(&text)?;
    let mut config = PlannerConfig::default();
    config.rrt.seed = a.seed;
    if let Some(r) = a.range {
        config.rrt.range = r;
    }
    if let Some(r) = a.check_resolution {
        config.check_resolution = r;
    }
    // Thread CPU time: other processes on the machine do not inflate the stage times.
    config.clock = planner::StageClock::ThreadCpu;
    let goal_kind = if a.goal_pose {
        // The benchmark's problems are plain obstacle worlds: no grasped object to exclude.
        config.closing_volume.half_extents = [-1.0; 3];
        config.start_volume.half_extents = [-1.0; 3];
        GoalKind::Pose
    } else {
        GoalKind::Joints
    };
    let model = match goal_kind {
        GoalKind::Joints => mbm_robot()?,
        GoalKind::Pose => mbm_robot_with_ik()?,
    };
    let planner = Planner::new(model, PlannerLimits::default(), config)?;
    let modes: Vec<WorldMode> = match a.mode.as_deref() {
        None => vec![WorldMode::Primitives, WorldMode::Cloud],
        Some("primitives") => vec![WorldMode::Primitives],
        Some("cloud") => vec![WorldMode::Cloud],
        Some(m) => anyhow::bail!("unknown --mode {m}; use primitives or cloud"),
    };
    let mut out = serde_json::Map::new();
    for mode in modes {
        let t = Instant::now();
        let mut results = Vec::new();
        for (scene, ps) in &file.problems {
            if a.scene
                .as_ref()
                .is_some_and(|s| !scene.contains(s.as_str()))
            {
                continue;
            }
            for p in ps
                .iter()
                .filter(|p| p.valid)
                .take(a.limit.unwrap_or(usize::MAX))
            {
                let r = run_problem_with(&planner, scene, p, mode, goal_kind);
                if !a.json && !r.solved {
                    eprintln!("{scene} #{}: {:?}", p.index, r.error);
                }
                results.push(r);
            }
        }
        let summary = summarize(&results);
        if !a.json {
            println!(
                "mode {mode:?} ({:.1} s wall; times in ms of thread CPU unless marked wall)",
                t.elapsed().as_secs_f64()
            );
            println!(
                "{:<18} {:>9} {:>17} {:>17} {:>17} {:>17} {:>17} {:>17} {:>17} {:>17} {:>17} {:>8} {:>8}",
                "scene",
                "solved",
                "plan ms med/p95",
                "plan wall ms",
                "IK+goal",
                "search",
                "shortcut",
                "timing+valid.",
                "exact re-check",
                "cloud build wall",
                "cloud build",
                "len rad",
                "replans"
            );
            for s in &summary {
                println!(
                    "{:<18} {:>4}/{:<4} {:>8.3}/{:<8.3} {:>8.3}/{:<8.3} {:>8.3}/{:<8.3} {:>8.3}/{:<8.3} {:>8.3}/{:<8.3} {:>8.3}/{:<8.3} {:>8.3}/{:<8.3} {:>8.2}/{:<8.2} {:>8.2}/{:<8.2} {:>8.2} {:>8}",
                    s.scene, s.solved, s.total, s.plan_ms.0, s.plan_ms.1, s.plan_wall_ms.0, s.plan_wall_ms.1, s.goal_ms.0, s.goal_ms.1, s.search_ms.0, s.search_ms.1,
                    s.shortcut_ms.0, s.shortcut_ms.1, s.timing_validate_ms.0, s.timing_validate_ms.1,
                    s.exact_ms.0, s.exact_ms.1, s.build_ms.0, s.build_ms.1, s.build_cpu_ms.0, s.build_cpu_ms.1, s.path_length_median, s.replanned
                );
            }
        }
        out.insert(
            format!("{mode:?}").to_lowercase(),
            serde_json::to_value(&summary)?,
        );
        if let Some(python) = &a.ompl {
            let ours = summary.last().map_or((f64::NAN, f64::NAN), |s| s.search_ms);
            let entry = match run_ompl(&a, python, mode) {
                Ok(mut v) => {
                    let med = v["solve_ms_median"].as_f64().unwrap_or(f64::NAN);
                    let p95 = v["solve_ms_p95"].as_f64().unwrap_or(f64::NAN);
                    if !a.json {
                        println!(
                            "OMPL RRTConnect ({mode:?}, same checker via planner_ffi, Python callbacks): solved {}/{}, median {med:.3} ms, p95 {p95:.3} ms; ours (search) median {:.3} ms, p95 {:.3} ms; OMPL/ours median ratio {:.1}",
                            v["solved"], v["total"], ours.0, ours.1, med / ours.0
                        );
                    }
                    if let Some(o) = v.as_object_mut() {
                        // Per-problem times stay in the driver's own output; the summary keeps
                        // the statistics.
                        o.remove("problems");
                        o.insert("ours_search_ms_median".into(), serde_json::json!(ours.0));
                        o.insert("ours_search_ms_p95".into(), serde_json::json!(ours.1));
                        o.insert(
                            "median_ratio_ompl_over_ours".into(),
                            serde_json::json!(med / ours.0),
                        );
                        o.insert(
                            "p95_ratio_ompl_over_ours".into(),
                            serde_json::json!(p95 / ours.1),
                        );
                    }
                    v
                }
                Err(e) => {
                    if !a.json {
                        println!("OMPL RRTConnect ({mode:?}) did not run: {e}");
                    }
                    serde_json::json!({"error": e})
                }
            };
            out.insert(
                format!("ompl_{}", format!("{mode:?}").to_lowercase()),
                entry,
            );
        }
    }
    // Collision check of one configuration against a cloud of the densest scene.
    if let Some(p) = file.problems.get("bookshelf_tall").and_then(|v| v.first()) {
        let cloud = p.surface_cloud(0.01)?;
        let world = World::from_cloud(&cloud, &CloudParams::default())?;
        let (med, p95, frac) = time_collision_checks(&planner.model, &world, 100_000, 3);
        let prim = p
            .obstacles()
            .into_iter()
            .fold(World::empty(), World::with_obstacle);
        let (pmed, pp95, pfrac) = time_collision_checks(&planner.model, &prim, 100_000, 3);
        let spheres = planner.model.spheres.spheres.len();
        if !a.json {
            println!(
                "collision check, {spheres} spheres, random configurations: cloud ({} pts) median {med:.0} ns p95 {p95:.0} ns ({:.0}% in collision); primitives median {pmed:.0} ns p95 {pp95:.0} ns ({:.0}%)",
                cloud.len(), frac * 100.0, pfrac * 100.0
            );
        }
        out.insert(
            "collision_check_ns".into(),
            serde_json::json!({"spheres": spheres, "cloud_points": cloud.len(),
                "cloud": {"median": med, "p95": p95, "in_collision": frac},
                "primitives": {"median": pmed, "p95": pp95, "in_collision": pfrac}}),
        );
    }
    if a.json {
        println!("{}", serde_json::to_string_pretty(&out)?);
    }
    Ok(())
}

/// The upper median of `v` (sorted in place; NaN for none).
pub(super) fn median(v: &mut [f64]) -> f64 {
    v.sort_by(f64::total_cmp);
    if v.is_empty() {
        f64::NAN
    } else {
        v[v.len() / 2]
    }
}

/// Median, 95th percentile and maximum of each of the three relative errors (translation
/// logits, open logit, rotation logits).
fn error_summary(errs: &[[f64; 3]]) -> serde_json::Value {
    let one = |k: usize| {
        let mut v: Vec<f64> = errs.iter().map(|e| e[k]).collect();
        v.sort_by(f64::total_cmp);
        let q = |p: f64| {
            v.get(((v.len() as f64 - 1.0) * p).round() as usize)
                .copied()
                .unwrap_or(f64::NAN)
        };
        serde_json::json!({"median": q(0.5), "p95": q(0.95), "max": q(1.0)})
    };
    serde_json::json!({
        "motions": errs.len(),
        "translation_logits_rel": one(0),
        "open_logit_rel": one(1),
        "rotation_logits_rel": one(2),
    })
}

/// What a prediction answered, exactly (shortest round-trip decimals): a change meant to
/// make the network faster can be checked to leave every keyframe as it was.
fn prediction_json(p: &policy::predict::Prediction) -> serde_json::Value {
    let iso = p.keyframe.base_from_tcp.isometry();
    let q = iso.rotation.quaternion();
    serde_json::json!({
        "position_m": [iso.translation.x, iso.translation.y, iso.translation.z],
        "rotation_xyzw": [q.i, q.j, q.k, q.w],
        "open_probability": p.open_probability,
        "translation_logit": p.translation_logit,
        "rotation_logit": p.rotation_logit,
    })
}

/// Times `a.predictions` predictions of `policy` on one scene: the median of each stage (CPU
/// seconds of all threads) and of the wall-clock total, and each prediction's answer
/// ([`prediction_json`]).
fn time_predictions(
    policy: &mut policy::predict::Policy,
    a: &PolicyBenchArgs,
    name: &str,
    (cloud, gripper, instruction): (
        &cell_types::PointCloud,
        &policy::predict::GripperPose,
        &policy::predict::InstructionEmbedding,
    ),
) -> anyhow::Result<(serde_json::Value, f64, Vec<serde_json::Value>)> {
    let (mut runs, mut products) = (Vec::new(), Vec::new());
    let (mut packed_runs, mut packed_products) = (Vec::new(), Vec::new());
    for i in 0..a.predictions.max(1) {
        policy.seed = a.seed + i as u64;
        let before = policy::matmul::product_counts();
        runs.push(policy.predict_detailed(cloud, gripper, instruction)?);
        products.push(policy::matmul::product_counts().since(before));
        // After the normal one, so that the first prediction is still the one that makes
        // the FiLM maps.
        if a.compare_packed {
            policy::matmul::use_direct_products(false);
            let before = policy::matmul::product_counts();
            let run = policy.predict_detailed(cloud, gripper, instruction);
            policy::matmul::use_direct_products(true);
            packed_runs.push(run?);
            packed_products.push(policy::matmul::product_counts().since(before));
        }
        eprintln!(
            "{name}: {} threads: prediction {} of {}: {:.3} s CPU, {:.3} s wall",
            policy.threads(),
            i + 1,
            a.predictions.max(1),
            runs.last().map_or(0.0, |r| r.timings.total),
            runs.last().map_or(0.0, |r| r.timings.wall_total)
        );
    }
    let stage_of = |runs: &[policy::predict::Prediction],
                    f: &dyn Fn(&policy::predict::StageTimings) -> f64| {
        let mut v: Vec<f64> = runs.iter().map(|r| f(&r.timings)).collect();
        median(&mut v)
    };
    let stage = |f: &dyn Fn(&policy::predict::StageTimings) -> f64| stage_of(&runs, f);
    let mut blocks = serde_json::Map::new();
    if let Some(first) = runs.first() {
        for (j, (bn, _)) in first.timings.blocks.iter().enumerate() {
            let mut v: Vec<f64> = runs
                .iter()
                .filter_map(|r| r.timings.blocks.get(j).map(|b| b.1))
                .collect();
            blocks.insert(bn.clone(), serde_json::json!(median(&mut v)));
        }
    }
    let product_of = |products: &[policy::matmul::ProductCounts],
                      f: &dyn Fn(&policy::matmul::ProductCounts) -> f64| {
        let mut v: Vec<f64> = products.iter().map(f).collect();
        median(&mut v)
    };
    let product = |f: &dyn Fn(&policy::matmul::ProductCounts) -> f64| product_of(&products, f);
    let wall = stage(&|t| t.wall_total);
    // The baseline: the same predictions with every product through `matrixmultiply`.
    let packed = a.compare_packed.then(|| {
        let packed_wall = stage_of(&packed_runs, &|t| t.wall_total);
        let answers = |runs: &[policy::predict::Prediction]| {
            runs.iter().map(prediction_json).collect::<Vec<_>>()
        };
        serde_json::json!({
            "total": stage_of(&packed_runs, &|t| t.total),
            "wall_total": packed_wall,
            "encoder": stage_of(&packed_runs, &|t| t.encoder),
            "matrix_products_seconds": product_of(&packed_products, &|p| p.seconds),
            "wall_speedup_of_direct": packed_wall / wall,
            "cpu_speedup_of_direct": stage_of(&packed_runs, &|t| t.total) / stage(&|t| t.total),
            "same_predictions": answers(&packed_runs) == answers(&runs),
        })
    });
    let timings = serde_json::json!({
        "input_prep": stage(&|t| t.input_prep),
        "language": stage(&|t| t.language),
        "unet_blocks": blocks,
        "unet_total": stage(&|t| t.blocks.iter().map(|b| b.1).sum()),
        "encoder": stage(&|t| t.encoder),
        "translation_head": stage(&|t| t.translation_head),
        "rotation_head": stage(&|t| t.rotation_head),
        "rotation_search": stage(&|t| t.rotation_search),
        "total": stage(&|t| t.total),
        "wall_total": wall,
        "wall_encoder": stage(&|t| t.wall_encoder),
        "wall_translation_head": stage(&|t| t.wall_translation_head),
        // The dense matrix products of a keyframe (`policy::matmul`): their count and
        // multiply-adds, their seconds summed over threads, and the rate they ran at.
        "matrix_products": {
            "products": product(&|p| p.products as f64),
            "multiply_adds": product(&|p| p.multiply_adds as f64),
            "seconds": product(&|p| p.seconds),
            "gflops_per_second": product(&|p| p.flops_per_second() * 1e-9),
        },
        // With --compare-packed (else null).
        "packed_products_baseline": packed,
        // The first prediction also runs the hypernetwork FiLM for the instruction; the
        // later ones (an episode's next keyframes) reuse its maps.
        "first_prediction": {
            "total": runs.first().map(|r| r.timings.total),
            "wall_total": runs.first().map(|r| r.timings.wall_total),
            "encoder": runs.first().map(|r| r.timings.encoder),
        },
    });
    Ok((timings, wall, runs.iter().map(prediction_json).collect()))
}

/// A uniformly random rotation (normalised Gaussian quaternion) and a shift within ±0.2 m.
fn random_motion(rng: &mut rand_chacha::ChaCha8Rng) -> nalgebra::Isometry3<f64> {
    use rand::Rng;
    let mut g = || {
        // Box-Muller.
        let (u1, u2): (f64, f64) = (1.0 - rng.random::<f64>(), rng.random::<f64>());
        (-2.0 * u1.ln()).sqrt() * (std::f64::consts::TAU * u2).cos()
    };
    let q = nalgebra::Quaternion::new(g(), g(), g(), g());
    let r = nalgebra::UnitQuaternion::from_quaternion(q);
    let t = nalgebra::Translation3::new(
        rng.random_range(-0.2..0.2),
        rng.random_range(-0.2..0.2),
        rng.random_range(-0.2..0.2),
    );
    nalgebra::Isometry3::from_parts(t, r)
}

fn run_policy(a: PolicyBenchArgs) -> anyhow::Result<()> {
    use policy::predict::{
        synthetic_scene, GripperPose, InstructionEmbedding, Policy, PolicyConfig, PolicyMode,
    };
    use rand::{Rng, SeedableRng};
    let modes: Vec<PolicyMode> = a
        .mode
        .as_deref()
        .unwrap_or("parity,equivariant,gated")
        .split(',')
        .map(|m| match m.trim() {
            "parity" => Ok(PolicyMode::Parity),
            "equivariant" => Ok(PolicyMode::Equivariant { s2_grid: a.s2_grid }),
            "gated" => Ok(PolicyMode::Gated),
            m => match m.strip_prefix("equivariant:").map(str::parse::<usize>) {
                Some(Ok(s2_grid)) => Ok(PolicyMode::Equivariant { s2_grid }),
                _ => anyhow::bail!(
                    "unknown --mode {m}; use parity, equivariant, equivariant:N or gated"
                ),
            },
        })
        .collect::<anyhow::Result<_>>()?;
    let a_tol = a.argmax_tolerance;
    let cloud = synthetic_scene(a.cloud_points, a.seed)?;
    let gripper = GripperPose {
        base_from_tcp: cell_types::Transform::from_xyz_rpy([0.5, 0.02, 0.3], [3.0, 0.1, 0.4]),
        open: true,
    };
    let instruction = InstructionEmbedding::random(a.seed);
    let mut out = serde_json::Map::new();
    let physical = PolicyConfig::physical();
    out.insert(
        "config".into(),
        serde_json::json!({
            "points": a.points,
            "cloud_points": cloud.len(),
            "lmax": physical.model.lmax,
            "mmax": physical.model.mmax,
            "sphere_channels": physical.model.sphere_channels,
            "field_nn_c": physical.model.field_nn_c,
            "translation_samples": physical.sampling.levels * physical.sampling.per_level,
            "rotation_grid_level": physical.rotation.grid_level,
            "threads": a.threads,
            "timings": "CPU seconds of all the prediction's threads (the machine may be \
                        shared); wall_total is wall-clock",
        }),
    );
    for mode in modes {
        let name = mode.name();
        let mut cfg = PolicyConfig::physical().with_mode(mode);
        cfg.n_points = a.points;
        cfg.n_outside_focus = a.points / 4;
        let t = policy::predict::CpuTimer::start();
        let mut policy = Policy::random(cfg.clone(), 1)?;
        let build_s = t.elapsed();
        if a.threads.is_empty() || a.threads.contains(&0) {
            anyhow::bail!("--threads takes counts of at least 1, e.g. --threads 1,2");
        }
        let mut by_threads = serde_json::Map::new();
        let (mut timings, mut total, mut base_wall) = (serde_json::Value::Null, 0.0, None);
        for &threads in &a.threads {
            // A fresh copy per count: its first prediction computes the instruction's FiLM
            // maps again, as an episode's first keyframe does.
            let mut timed = policy.clone();
            timed.set_threads(threads);
            let (t, wall, keyframes) =
                time_predictions(&mut timed, &a, &name, (&cloud, &gripper, &instruction))?;
            let base = *base_wall.get_or_insert(wall);
            total = t["total"].as_f64().unwrap_or(f64::NAN);
            by_threads.insert(
                threads.to_string(),
                serde_json::json!({
                    "stage_timings_s": t,
                    "wall_speedup": base / wall,
                    "predictions": keyframes,
                }),
            );
            timings = t;
        }
        policy.set_threads(a.threads.last().copied().unwrap_or(1));
        // Equivariance of the network on one prepared input.
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(a.seed);
        let prep = policy.prepare(&cloud, &gripper, &mut rng)?;
        let b = cfg.gripper_bounds;
        let queries: Vec<[f32; 3]> = (0..cfg.sampling.per_level)
            .map(|_| [0, 1, 2].map(|i| rng.random_range(b[0][i]..b[1][i]) as f32))
            .collect();
        let motions: Vec<_> = (0..a.repeats).map(|_| random_motion(&mut rng)).collect();
        let t = policy::predict::CpuTimer::start();
        let report = if motions.is_empty() {
            Vec::new()
        } else {
            policy.equivariance_report(
                &prep,
                &instruction,
                &queries,
                [0.55, 0.0, 0.15],
                &motions,
            )?
        };
        // Thread CPU time of one encode + heads (the machine may be shared; motions whose
        // discrete choices changed are encoded twice).
        let encodes = 1
            + report.len()
            + report
                .iter()
                .filter(|m| m.errors_same_choices.is_some())
                .count();
        let forward_s = t.elapsed() / encodes as f64;
        let errs: Vec<[f64; 3]> = report.iter().map(|m| m.errors).collect();
        // Discontinuities: motions where a discrete choice changed, and the errors of the
        // others; for the changed ones, the errors with the unmoved input's choices forced.
        let unchanged: Vec<[f64; 3]> = report
            .iter()
            .filter(|m| m.changed_blocks.is_empty() && m.changed_query_lists == 0)
            .map(|m| m.errors)
            .collect();
        let forced: Vec<[f64; 3]> = report
            .iter()
            .filter_map(|m| m.errors_same_choices)
            .collect();
        let mut changed = serde_json::Map::new();
        for m in &report {
            for b in &m.changed_blocks {
                // `down1.max_pool(flips 2, ...)`: counted under `down1.max_pool`.
                let key = b.split('(').next().unwrap_or(b.as_str()).to_string();
                let e = changed.entry(key).or_insert(serde_json::json!(0));
                *e = serde_json::json!(e.as_u64().unwrap_or(0) + 1);
            }
        }
        let angles: Vec<f64> = report.iter().map(|m| m.argmax_angle).collect();
        let argmax_ok = angles.iter().filter(|a| **a <= a_tol).count();
        let max_angle = angles.iter().copied().fold(f64::NAN, f64::max);
        for (i, m) in report.iter().enumerate() {
            eprintln!(
                "{name}: motion {i}: errors {:.2e} {:.2e} {:.2e}; argmax angle {:.2e} rad; \
                 changed {:?}, query lists {}; same choices {:?}",
                m.errors[0],
                m.errors[1],
                m.errors[2],
                m.argmax_angle,
                m.changed_blocks,
                m.changed_query_lists,
                m.errors_same_choices
            );
        }
        eprintln!(
            "{name}: median total {total:.3} s (CPU, {} threads); equivariance {}; argmax moves \
             with the input in {argmax_ok} of {} (max angle {max_angle:.2e} rad)",
            policy.threads(),
            error_summary(&errs),
            angles.len(),
        );
        out.insert(
            name,
            serde_json::json!({
                "build_random_weights_s": build_s,
                "time_per_keyframe_s": total,
                "stage_timings_s": timings,
                "by_threads": by_threads,
                "equivariance": {
                    "all": error_summary(&errs),
                    "forward_s": forward_s,
                    "queries": queries.len(),
                    "argmax": {
                        "tolerance_rad": a_tol,
                        "moves_with_input": argmax_ok,
                        "of": angles.len(),
                        "max_angle_rad": max_angle,
                    },
                    "discontinuities": {
                        "motions_with_changed_unet_choices":
                            report.iter().filter(|m| !m.changed_blocks.is_empty()).count(),
                        "changed_choices": changed,
                        "motions_with_changed_query_neighbours":
                            report.iter().filter(|m| m.changed_query_lists > 0).count(),
                        "unchanged_motions": error_summary(&unchanged),
                        "changed_motions_with_forced_choices": error_summary(&forced),
                    },
                },
            }),
        );
    }
    println!("{}", serde_json::to_string_pretty(&out)?);
    Ok(())
}
