//! `equact bench ...`: benchmarks that print a JSON summary (timings are compared as ratios
//! within one run, never asserted in tests).

use anyhow::Context;
use clap::{Args, Subcommand};
use planner::mbm::{mbm_robot, run_problem, summarize, time_collision_checks, MbmFile, WorldMode};
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
}

/// Runs `equact bench`.
pub fn run(args: BenchArgs) -> anyhow::Result<()> {
    match args.what {
        BenchWhat::Planner(a) => run_planner(a),
        BenchWhat::Ur(a) => super::bench_ur::run(a),
    }
}

fn run_planner(a: PlannerBenchArgs) -> anyhow::Result<()> {
    let text = std::fs::read_to_string(&a.problems)
        .with_context(|| format!("reading {}", a.problems.display()))?;
    let file = MbmFile::parse(&text)?;
    let mut config = PlannerConfig::default();
    config.rrt.seed = a.seed;
    let planner = Planner::new(mbm_robot()?, PlannerLimits::default(), config)?;
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
            for p in ps
                .iter()
                .filter(|p| p.valid)
                .take(a.limit.unwrap_or(usize::MAX))
            {
                let r = run_problem(&planner, scene, p, mode);
                if !a.json && !r.solved {
                    eprintln!("{scene} #{}: {:?}", p.index, r.error);
                }
                results.push(r);
            }
        }
        let summary = summarize(&results);
        if !a.json {
            println!("mode {mode:?} ({:.1} s wall)", t.elapsed().as_secs_f64());
            println!(
                "{:<18} {:>9} {:>17} {:>17} {:>17} {:>17} {:>17} {:>17} {:>8}",
                "scene",
                "solved",
                "plan ms med/p95",
                "search",
                "shortcut",
                "timing+valid.",
                "exact re-check",
                "cloud build",
                "len rad"
            );
            for s in &summary {
                println!(
                    "{:<18} {:>4}/{:<4} {:>8.3}/{:<8.3} {:>8.3}/{:<8.3} {:>8.3}/{:<8.3} {:>8.3}/{:<8.3} {:>8.3}/{:<8.3} {:>8.2}/{:<8.2} {:>8.2}",
                    s.scene, s.solved, s.total, s.plan_ms.0, s.plan_ms.1, s.search_ms.0, s.search_ms.1,
                    s.shortcut_ms.0, s.shortcut_ms.1, s.timing_validate_ms.0, s.timing_validate_ms.1,
                    s.exact_ms.0, s.exact_ms.1, s.build_ms.0, s.build_ms.1, s.path_length_median
                );
            }
        }
        out.insert(
            format!("{mode:?}").to_lowercase(),
            serde_json::to_value(&summary)?,
        );
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
