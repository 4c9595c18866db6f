//! `equact plan`: plan one keyframe from a joint configuration against a cloud file and
//! print the result and its timing.

use cell_types::{Base, Keyframe, Tcp, Transform};
use clap::Args;
use planner::{CloudParams, Planner, PlannerConfig, PlannerLimits, RobotModel, World};
use std::time::Instant;

/// Arguments of `equact plan`.
#[derive(Args, Debug)]
pub struct PlanArgs {
    /// Start configuration: six joint angles in radians, comma-separated.
    #[arg(long, allow_hyphen_values = true)]
    pub start: String,
    /// Keyframe TCP pose in the base frame: x,y,z (m), roll,pitch,yaw (rad).
    #[arg(long, allow_hyphen_values = true)]
    pub pose: String,
    /// Point cloud in the base frame (PLY or PCD); none for an empty world.
    #[arg(long)]
    pub cloud: Option<std::path::PathBuf>,
    /// Plan without the cloud (the keyframe's "ignore collisions" flag).
    #[arg(long)]
    pub ignore_collisions: bool,
    /// The keyframe closes the gripper (a grasp); default open.
    #[arg(long)]
    pub close: bool,
    /// UR5e instead of UR5 (CB3); also sets the 500 Hz controller period.
    #[arg(long)]
    pub ur5e: bool,
    /// Print the trajectory samples as JSON.
    #[arg(long)]
    pub json: bool,
}

/// Runs `equact plan`.
pub fn run(args: PlanArgs) -> anyhow::Result<()> {
    let start = super::args::numbers::<6>(&args.start, "start")?;
    let pose = super::args::numbers::<6>(&args.pose, "pose")?;
    let (model, period) = if args.ur5e {
        (RobotModel::ur5e()?, 0.002)
    } else {
        (RobotModel::ur5()?, 0.008)
    };
    let limits = PlannerLimits {
        period,
        ..PlannerLimits::default()
    };
    let planner = Planner::new(model, limits, PlannerConfig::default())?;
    let t = Instant::now();
    let world = match &args.cloud {
        Some(path) => {
            let cloud = super::args::read_cloud_file(path)?;
            World::from_cloud(&cloud, &CloudParams::default())?
        }
        None => World::empty(),
    };
    let build_ms = t.elapsed().as_secs_f64() * 1e3;
    let base_from_tcp: Transform<Base, Tcp> =
        Transform::from_xyz_rpy([pose[0], pose[1], pose[2]], [pose[3], pose[4], pose[5]]);
    let keyframe = Keyframe::new(base_from_tcp, !args.close, args.ignore_collisions)?;
    let m = planner.plan_to_keyframe(&start, &keyframe, &world)?;
    let s = m.stats;
    if args.json {
        println!("{}", serde_json::to_string_pretty(&m.trajectory)?);
    } else {
        println!(
            "cloud: {} points, structure built in {build_ms:.2} ms",
            world.cloud_len()
        );
        println!("goal: {:?}", m.goal);
        println!(
            "path: {} waypoints, {:.3} rad; trajectory {} samples, {:.3} s at {:.0} Hz",
            s.waypoints,
            s.path_length,
            m.trajectory.len(),
            m.trajectory.duration(),
            m.trajectory.rate_hz()
        );
        println!(
            "time: total {:.3} ms (goal {:.3}, search {:.3} [{} RRT iterations], shortcut {:.3}, timing {:.3}, validation {:.3}); {} configurations checked",
            s.total_s * 1e3,
            s.goal_s * 1e3,
            s.search_s * 1e3,
            s.iterations,
            s.shortcut_s * 1e3,
            s.timing_s * 1e3,
            s.validate_s * 1e3,
            s.checks
        );
    }
    Ok(())
}
