//! Search statistics on one MBM scene for a few RRT settings
//! (`cargo run --release -p planner --example cage_stats -- cage [range...]`).
#![allow(clippy::unwrap_used, missing_docs)]
use planner::mbm::{mbm_robot, median_p95, MbmFile, WorldMode, MBM_PROBLEMS_PATH};
use planner::planner::{Planner, PlannerConfig};
use planner::timing::PlannerLimits;

fn main() {
    let args: Vec<String> = std::env::args().collect();
    let scene = args.get(1).cloned().unwrap_or_else(|| "cage".into());
    let ranges: Vec<f64> = if args.len() > 2 {
        args[2..].iter().map(|s| s.parse().unwrap()).collect()
    } else {
        vec![0.5]
    };
    let file = MbmFile::parse(&std::fs::read_to_string(MBM_PROBLEMS_PATH).unwrap()).unwrap();
    let ps: Vec<_> = file.problems[&scene].iter().filter(|p| p.valid).collect();
    for range in ranges {
        let mut cfg = PlannerConfig::default();
        cfg.rrt.range = range;
        let planner = Planner::new(mbm_robot().unwrap(), PlannerLimits::default(), cfg).unwrap();
        let (mut its, mut ms, mut checks) = (vec![], vec![], vec![]);
        let mut fails = 0;
        for p in &ps {
            let (s, g) = p.start_goal().unwrap();
            let w = p.world(WorldMode::Primitives).unwrap();
            match planner.plan_to_joints(&s, &g, &w) {
                Ok(m) => {
                    its.push(m.stats.iterations as f64);
                    ms.push(m.stats.search_s * 1e3);
                    checks.push(m.stats.checks as f64);
                }
                Err(_) => fails += 1,
            }
        }
        println!(
            "{scene} range {range}: fails {fails}, iterations {:?}, search ms {:?}, checks {:?}",
            median_p95(&mut its),
            median_p95(&mut ms),
            median_p95(&mut checks)
        );
    }
}
