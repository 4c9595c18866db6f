//! MotionBenchMaker UR5 problems (issue 3 item 9): the problems file of VAMP's distribution
//! (boxes and cylinders with poses, start and goal configurations), the spherized robot they
//! use, the obstacles as primitives or as clouds sampled from their surfaces, and a runner
//! that plans every problem and summarizes per scene.

use crate::error::PlanError;
use crate::model::RobotModel;
use crate::planner::Planner;
use crate::world::{CloudParams, Obstacle, World};
use cell_types::{FrameId, Joints, PointCloud};
use nalgebra::{Isometry3, Point3, Quaternion, Translation3, UnitQuaternion, Vector3};
use serde::{Deserialize, Serialize};
use std::collections::BTreeMap;
use std::time::Instant;

/// The spherized UR5 + Robotiq 85 of the MBM problems (base raised 0.9144 m, turned 1.57 rad).
pub const MBM_UR5_URDF: &str = include_str!("../data/mbm_ur5/ur5_spherized.urdf");

/// Path of the problems file in this repository.
pub const MBM_PROBLEMS_PATH: &str =
    concat!(env!("CARGO_MANIFEST_DIR"), "/data/mbm_ur5/problems.json");

/// The robot model of the MBM problems.
pub fn mbm_robot() -> Result<RobotModel, PlanError> {
    RobotModel::from_urdf(MBM_UR5_URDF, "ee_link")
}

/// The robot model of the MBM problems with the UR5's analytic IK fitted to its chain (goals
/// given as TCP poses).
pub fn mbm_robot_with_ik() -> Result<RobotModel, PlanError> {
    mbm_robot()?.with_ur_ik(crate::kinematics::UR5)
}

/// A box obstacle.
#[derive(Clone, Debug, Deserialize)]
pub struct MbmBox {
    /// Name.
    pub name: String,
    /// Half edge lengths (m).
    pub half_extents: [f64; 3],
    /// Centre (m).
    pub position: [f64; 3],
    /// Orientation, quaternion x y z w.
    pub orientation_quat_xyzw: [f64; 4],
}

/// A cylinder obstacle (axis along its local z; `length` is the full length).
#[derive(Clone, Debug, Deserialize)]
pub struct MbmCylinder {
    /// Name.
    pub name: String,
    /// Full length (m).
    pub length: f64,
    /// Radius (m).
    pub radius: f64,
    /// Centre (m).
    pub position: [f64; 3],
    /// Orientation, quaternion x y z w.
    pub orientation_quat_xyzw: [f64; 4],
}

/// A sphere obstacle.
#[derive(Clone, Debug, Deserialize)]
pub struct MbmSphere {
    /// Name.
    #[serde(default)]
    pub name: String,
    /// Radius (m).
    pub radius: f64,
    /// Centre (m).
    pub position: [f64; 3],
}

/// One problem.
#[derive(Clone, Debug, Deserialize)]
pub struct MbmProblem {
    /// Sphere obstacles.
    #[serde(default)]
    pub sphere: Vec<MbmSphere>,
    /// Cylinder obstacles.
    #[serde(default)]
    pub cylinder: Vec<MbmCylinder>,
    /// Box obstacles.
    #[serde(rename = "box", default)]
    pub boxes: Vec<MbmBox>,
    /// Index within its scene (1-based).
    pub index: usize,
    /// Start configuration.
    pub start: Vec<f64>,
    /// Goal configurations (the first is used).
    pub goals: Vec<Vec<f64>>,
    /// False for the problems MBM itself marks invalid.
    pub valid: bool,
}

/// The problems file.
#[derive(Clone, Debug, Deserialize)]
pub struct MbmFile {
    /// Problems by scene name.
    pub problems: BTreeMap<String, Vec<MbmProblem>>,
}

fn pose(position: &[f64; 3], q: &[f64; 4]) -> Isometry3<f64> {
    Isometry3::from_parts(
        Translation3::new(position[0], position[1], position[2]),
        UnitQuaternion::from_quaternion(Quaternion::new(q[3], q[0], q[1], q[2])),
    )
}

fn joints(v: &[f64], what: &str) -> Result<Joints, PlanError> {
    v.try_into().map_err(|_| PlanError::BadWorld {
        what: format!("{what} has {} values, need 6", v.len()),
    })
}

impl MbmFile {
    /// Parses the problems file.
    pub fn parse(json: &str) -> Result<Self, PlanError> {
        serde_json::from_str(json).map_err(|e| PlanError::BadWorld {
            what: format!("MBM problems file: {e}"),
        })
    }
}

impl MbmProblem {
    /// Start and first goal.
    pub fn start_goal(&self) -> Result<(Joints, Joints), PlanError> {
        let goal = self.goals.first().ok_or_else(|| PlanError::BadWorld {
            what: format!("problem {} has no goal", self.index),
        })?;
        Ok((joints(&self.start, "start")?, joints(goal, "goal")?))
    }

    /// The obstacles as exact primitives.
    pub fn obstacles(&self) -> Vec<Obstacle> {
        let mut out = Vec::new();
        for b in &self.boxes {
            out.push(Obstacle::Cuboid {
                name: b.name.clone(),
                pose: pose(&b.position, &b.orientation_quat_xyzw),
                half: Vector3::from(b.half_extents),
            });
        }
        for c in &self.cylinder {
            out.push(Obstacle::Cylinder {
                name: c.name.clone(),
                pose: pose(&c.position, &c.orientation_quat_xyzw),
                radius: c.radius,
                half_length: c.length / 2.0,
            });
        }
        for s in &self.sphere {
            out.push(Obstacle::Ball {
                name: s.name.clone(),
                center: Point3::from(s.position),
                radius: s.radius,
            });
        }
        out
    }

    /// The problem's world in the given mode: the primitives, or the distance field over the
    /// 1 cm surface cloud.
    pub fn world(&self, mode: WorldMode) -> Result<World, PlanError> {
        match mode {
            WorldMode::Primitives => Ok(self
                .obstacles()
                .into_iter()
                .fold(World::empty(), World::with_obstacle)),
            WorldMode::Cloud => {
                World::from_cloud(&self.surface_cloud(0.01)?, &CloudParams::default())
            }
        }
    }

    /// Points on the obstacle surfaces, about `spacing` apart (the robot base frame of the
    /// problems, which is their world frame).
    pub fn surface_cloud(&self, spacing: f64) -> Result<PointCloud, PlanError> {
        let mut pts = Vec::new();
        let steps = |len: f64| ((len / spacing).ceil() as usize).max(1);
        for b in &self.boxes {
            let p = pose(&b.position, &b.orientation_quat_xyzw);
            let h = b.half_extents;
            for axis in 0..3 {
                let (u, v) = ((axis + 1) % 3, (axis + 2) % 3);
                let (nu, nv) = (steps(2.0 * h[u]), steps(2.0 * h[v]));
                for i in 0..=nu {
                    for k in 0..=nv {
                        for sgn in [-1.0, 1.0] {
                            let mut l = [0.0; 3];
                            l[axis] = sgn * h[axis];
                            l[u] = -h[u] + 2.0 * h[u] * i as f64 / nu as f64;
                            l[v] = -h[v] + 2.0 * h[v] * k as f64 / nv as f64;
                            pts.push((p * Point3::from(l)).cast::<f32>());
                        }
                    }
                }
            }
        }
        for c in &self.cylinder {
            let p = pose(&c.position, &c.orientation_quat_xyzw);
            let nz = steps(c.length);
            let na = steps(std::f64::consts::TAU * c.radius).max(8);
            for i in 0..=nz {
                let z = -c.length / 2.0 + c.length * i as f64 / nz as f64;
                for k in 0..na {
                    let a = std::f64::consts::TAU * k as f64 / na as f64;
                    pts.push(
                        (p * Point3::new(c.radius * a.cos(), c.radius * a.sin(), z)).cast::<f32>(),
                    );
                }
            }
            let nr = steps(c.radius);
            for i in 0..=nr {
                let r = c.radius * i as f64 / nr as f64;
                let na = steps(std::f64::consts::TAU * r).max(1);
                for k in 0..na {
                    let a = std::f64::consts::TAU * k as f64 / na as f64;
                    for z in [-c.length / 2.0, c.length / 2.0] {
                        pts.push((p * Point3::new(r * a.cos(), r * a.sin(), z)).cast::<f32>());
                    }
                }
            }
        }
        for s in &self.sphere {
            let n = steps(std::f64::consts::PI * s.radius).max(4);
            for i in 0..=n {
                let th = std::f64::consts::PI * i as f64 / n as f64;
                let na = steps(std::f64::consts::TAU * s.radius * th.sin()).max(1);
                for k in 0..na {
                    let ph = std::f64::consts::TAU * k as f64 / na as f64;
                    let d = Vector3::new(th.sin() * ph.cos(), th.sin() * ph.sin(), th.cos());
                    pts.push((Point3::from(s.position) + d * s.radius).cast::<f32>());
                }
            }
        }
        PointCloud::new(FrameId::Base, pts, None).map_err(|e| PlanError::BadWorld {
            what: e.to_string(),
        })
    }
}

/// How the obstacles are given to the planner.
#[derive(Copy, Clone, Debug, PartialEq, Eq, Serialize)]
pub enum WorldMode {
    /// Exact primitives.
    Primitives,
    /// A cloud sampled from the obstacle surfaces at 1 cm.
    Cloud,
}

/// The outcome of one problem.
#[derive(Clone, Debug, Serialize)]
pub struct ProblemResult {
    /// Scene.
    pub scene: String,
    /// Index in the scene.
    pub index: usize,
    /// Solved and validated.
    pub solved: bool,
    /// The error, when not solved.
    pub error: Option<String>,
    /// Cloud points (cloud mode).
    pub cloud_points: usize,
    /// Cloud structure build time (s, wall clock).
    pub build_s: f64,
    /// Cloud structure build time (s, thread CPU: what other processes on the machine do not
    /// inflate).
    pub build_cpu_s: f64,
    /// Path search (s).
    pub search_s: f64,
    /// Shortcutting (s).
    pub shortcut_s: f64,
    /// Timing (s).
    pub timing_s: f64,
    /// Validation (s).
    pub validate_s: f64,
    /// Exact (parry) re-check of the trajectory (s).
    pub exact_s: f64,
    /// Configurations the exact re-check tested.
    pub exact_checks: u64,
    /// Whole plan excluding the cloud build (s), on the planner's stage clock.
    pub total_s: f64,
    /// Joint-space path length (rad).
    pub path_length: f64,
    /// Trajectory duration (s).
    pub duration_s: f64,
    /// Searches repeated at a finer spacing after a dense re-check found a contact.
    pub replans: usize,
    /// Wall-clock time of the whole plan excluding the cloud build (s).
    pub wall_s: f64,
    /// IK and goal selection (s; 0 for joint-space goals), included in `total_s`.
    pub goal_s: f64,
}

/// How a problem's goal is given to the planner.
#[derive(Copy, Clone, Debug, PartialEq, Eq, Serialize)]
pub enum GoalKind {
    /// The MBM goal configuration (`plan_to_joints`).
    Joints,
    /// The TCP pose of the goal configuration as a keyframe (`plan_to_keyframe`: IK, goal
    /// selection among the free solutions, then the same pipeline); needs a model with IK
    /// ([`mbm_robot_with_ik`]).
    Pose,
}

/// Plans one problem in the given mode to its goal configuration.
pub fn run_problem(
    planner: &Planner,
    scene: &str,
    p: &MbmProblem,
    mode: WorldMode,
) -> ProblemResult {
    run_problem_with(planner, scene, p, mode, GoalKind::Joints)
}

/// Plans one problem in the given mode, its goal given as `goal`.
pub fn run_problem_with(
    planner: &Planner,
    scene: &str,
    p: &MbmProblem,
    mode: WorldMode,
    goal_kind: GoalKind,
) -> ProblemResult {
    let mut r = ProblemResult {
        scene: scene.to_string(),
        index: p.index,
        solved: false,
        error: None,
        cloud_points: 0,
        build_s: 0.0,
        build_cpu_s: 0.0,
        search_s: 0.0,
        shortcut_s: 0.0,
        timing_s: 0.0,
        validate_s: 0.0,
        exact_s: 0.0,
        exact_checks: 0,
        total_s: 0.0,
        path_length: 0.0,
        duration_s: 0.0,
        replans: 0,
        wall_s: 0.0,
        goal_s: 0.0,
    };
    let outcome = (|| -> Result<_, PlanError> {
        let (start, goal) = p.start_goal()?;
        let t = Instant::now();
        let cpu = cpu_time::ThreadTime::try_now().ok();
        let world = p.world(mode)?;
        if mode == WorldMode::Cloud {
            r.cloud_points = world.cloud_len();
            // Includes sampling the surfaces (about a millisecond), as the FFI build does.
            r.build_s = t.elapsed().as_secs_f64();
            r.build_cpu_s = cpu
                .and_then(|c| c.try_elapsed().ok())
                .map_or(r.build_s, |d| d.as_secs_f64());
        }
        let t = Instant::now();
        let m = match goal_kind {
            GoalKind::Joints => planner.plan_to_joints(&start, &goal, &world),
            GoalKind::Pose => {
                let pose = planner.model.fk_tcp(&goal);
                let kf = cell_types::Keyframe::new(pose, true, false).map_err(|e| {
                    PlanError::BadWorld {
                        what: e.to_string(),
                    }
                })?;
                planner.plan_to_keyframe(&start, &kf, &world)
            }
        };
        r.wall_s = t.elapsed().as_secs_f64();
        m
    })();
    match outcome {
        Ok(m) => {
            r.solved = true;
            r.search_s = m.stats.search_s;
            r.shortcut_s = m.stats.shortcut_s;
            r.timing_s = m.stats.timing_s;
            r.validate_s = m.stats.validate_s;
            r.exact_s = m.stats.exact_s;
            r.exact_checks = m.stats.exact_checks;
            r.total_s = m.stats.total_s;
            r.path_length = m.stats.path_length;
            r.duration_s = m.trajectory.duration();
            r.replans = m.stats.replans;
            r.goal_s = m.stats.goal_s;
        }
        Err(e) => r.error = Some(e.to_string()),
    }
    r
}

/// Median and 95th percentile of a sample (0 for an empty one).
pub fn median_p95(v: &mut [f64]) -> (f64, f64) {
    if v.is_empty() {
        return (0.0, 0.0);
    }
    v.sort_by(f64::total_cmp);
    let at = |q: f64| v[((v.len() - 1) as f64 * q).round() as usize];
    (at(0.5), at(0.95))
}

/// Per-scene summary of results.
#[derive(Clone, Debug, Serialize)]
pub struct SceneSummary {
    /// Scene name (or "all").
    pub scene: String,
    /// Solved problems.
    pub solved: usize,
    /// Problems run.
    pub total: usize,
    /// Median / p95 whole plan time excluding cloud build (ms), on the planner's stage clock.
    pub plan_ms: (f64, f64),
    /// Median / p95 wall-clock time of the whole plan excluding cloud build (ms).
    pub plan_wall_ms: (f64, f64),
    /// Median / p95 IK and goal selection time (ms; 0 for joint-space goals).
    pub goal_ms: (f64, f64),
    /// Median / p95 search time (ms).
    pub search_ms: (f64, f64),
    /// Median / p95 shortcut time (ms).
    pub shortcut_ms: (f64, f64),
    /// Median / p95 timing + validation time (ms).
    pub timing_validate_ms: (f64, f64),
    /// Median / p95 exact (parry) dense re-check time (ms), included in `plan_ms`.
    pub exact_ms: (f64, f64),
    /// Median / p95 cloud build time (ms, wall clock).
    pub build_ms: (f64, f64),
    /// Median / p95 cloud build time (ms, thread CPU).
    pub build_cpu_ms: (f64, f64),
    /// Median path length (rad).
    pub path_length_median: f64,
    /// Solved problems that needed at least one finer search after a dense re-check.
    pub replanned: usize,
}

/// Summarizes results per scene and overall.
pub fn summarize(results: &[ProblemResult]) -> Vec<SceneSummary> {
    let mut scenes: Vec<String> = results.iter().map(|r| r.scene.clone()).collect();
    scenes.dedup();
    scenes.push("all".into());
    scenes
        .into_iter()
        .map(|s| {
            let rs: Vec<&ProblemResult> = results
                .iter()
                .filter(|r| s == "all" || r.scene == s)
                .collect();
            let ok: Vec<&&ProblemResult> = rs.iter().filter(|r| r.solved).collect();
            let col = |f: &dyn Fn(&ProblemResult) -> f64| -> (f64, f64) {
                let mut v: Vec<f64> = ok.iter().map(|r| f(r) * 1e3).collect();
                median_p95(&mut v)
            };
            SceneSummary {
                scene: s,
                solved: ok.len(),
                total: rs.len(),
                plan_ms: col(&|r| r.total_s),
                plan_wall_ms: col(&|r| r.wall_s),
                goal_ms: col(&|r| r.goal_s),
                search_ms: col(&|r| r.search_s),
                shortcut_ms: col(&|r| r.shortcut_s),
                timing_validate_ms: col(&|r| r.timing_s + r.validate_s),
                exact_ms: col(&|r| r.exact_s),
                build_ms: col(&|r| r.build_s),
                build_cpu_ms: col(&|r| r.build_cpu_s),
                replanned: ok.iter().filter(|r| r.replans > 0).count(),
                path_length_median: {
                    let mut v: Vec<f64> = ok.iter().map(|r| r.path_length).collect();
                    median_p95(&mut v).0
                },
            }
        })
        .collect()
}

/// Times single-configuration collision checks (FK + all spheres vs the world + self pairs)
/// on `n` seeded random configurations within limits; returns (median, p95) in nanoseconds
/// and the fraction of configurations in collision. Each call is timed on its own (the
/// clock read costs some tens of ns, included).
pub fn time_collision_checks(
    model: &RobotModel,
    world: &World,
    n: usize,
    seed: u64,
) -> (f64, f64, f64) {
    use rand::{Rng, SeedableRng};
    let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(seed);
    let mut checker = crate::checker::Checker::new(model, world, 0.01);
    let mut times = Vec::with_capacity(n);
    let mut hits = 0usize;
    for _ in 0..n {
        let q: Joints =
            std::array::from_fn(|j| rng.random_range(model.limits[j].0..=model.limits[j].1));
        let t = Instant::now();
        let hit = checker.contact(&q).is_some();
        times.push(t.elapsed().as_secs_f64() * 1e9);
        hits += usize::from(hit);
    }
    let (m, p) = median_p95(&mut times);
    (m, p, hits as f64 / n.max(1) as f64)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::planner::PlannerConfig;
    use crate::timing::PlannerLimits;

    /// The fitted IK of the MBM robot: every problem's goal pose (its FK) has an IK solution
    /// with the same pose, and one of them is the goal configuration itself (up to 2π wraps).
    #[test]
    fn mbm_robot_ik_recovers_the_goal_configurations() {
        let model = mbm_robot_with_ik().unwrap();
        let file = MbmFile::parse(&std::fs::read_to_string(MBM_PROBLEMS_PATH).unwrap()).unwrap();
        for ps in file.problems.values() {
            for p in ps.iter().filter(|p| p.valid) {
                let (start, goal) = p.start_goal().unwrap();
                let pose = model.fk_tcp(&goal);
                let sols = model.ik_near(&pose, &start).unwrap();
                for s in &sols {
                    let e = model.fk_tcp(s);
                    assert!((e.translation() - pose.translation()).norm() < 1e-6);
                    assert!(e.rotation().angle_to(&pose.rotation()) < 1e-6);
                    assert!(model.within_limits(s));
                }
                let wrapped = |a: f64, b: f64| {
                    let d = (a - b).rem_euclid(std::f64::consts::TAU);
                    d.min(std::f64::consts::TAU - d)
                };
                assert!(
                    sols.iter()
                        .any(|s| (0..6).all(|j| wrapped(s[j], goal[j]) < 1e-6)),
                    "goal {goal:?} not among {sols:?}"
                );
            }
        }
    }

    #[test]
    fn surface_clouds_are_dense_and_start_goal_parse() {
        let file = MbmFile::parse(&std::fs::read_to_string(MBM_PROBLEMS_PATH).unwrap()).unwrap();
        assert_eq!(file.problems.len(), 7);
        let valid: usize = file
            .problems
            .values()
            .map(|v| v.iter().filter(|p| p.valid).count())
            .sum();
        assert_eq!(valid, 689);
        for (scene, ps) in &file.problems {
            let c = ps[0].surface_cloud(0.01).unwrap();
            eprintln!("{scene}: {} points", c.len());
            assert!(c.len() > 5_000, "{scene}: {}", c.len());
        }
    }

    /// A seeded subset of ≥ 70 valid problems (10 per scene) in both modes: all solved, and
    /// every trajectory passed the limit, sphere and exact (parry) dense re-checks inside
    /// `plan_to_joints`.
    #[test]
    fn seeded_subset_of_mbm_problems_is_solved_in_both_modes() {
        let file = MbmFile::parse(&std::fs::read_to_string(MBM_PROBLEMS_PATH).unwrap()).unwrap();
        let planner = Planner::new(
            mbm_robot().unwrap(),
            PlannerLimits::default(),
            PlannerConfig::default(),
        )
        .unwrap();
        let mut results = Vec::new();
        for (scene, ps) in &file.problems {
            let valid: Vec<&MbmProblem> = ps.iter().filter(|p| p.valid).collect();
            // Seeded pick: every 9th valid problem from an offset derived from the scene name.
            let off = scene.bytes().map(usize::from).sum::<usize>() % 9;
            for p in valid.iter().skip(off).step_by(9).take(10) {
                for mode in [WorldMode::Primitives, WorldMode::Cloud] {
                    results.push(run_problem(&planner, scene, p, mode));
                }
            }
        }
        let failed: Vec<String> = results
            .iter()
            .filter(|r| !r.solved)
            .map(|r| {
                format!(
                    "{} #{}: {}",
                    r.scene,
                    r.index,
                    r.error.clone().unwrap_or_default()
                )
            })
            .collect();
        for mode in [WorldMode::Primitives, WorldMode::Cloud] {
            let ok: Vec<&ProblemResult> = results
                .iter()
                .filter(|r| r.solved && (r.cloud_points > 0) == matches!(mode, WorldMode::Cloud))
                .collect();
            let mut exact: Vec<f64> = ok.iter().map(|r| r.exact_s * 1e3).collect();
            let mut checks: Vec<f64> = ok.iter().map(|r| r.exact_checks as f64).collect();
            let mut valid: Vec<f64> = ok.iter().map(|r| r.validate_s * 1e3).collect();
            eprintln!(
                "{mode:?}: exact re-check median/p95 {:?} ms, checks {:?}; sphere validation {:?} ms",
                median_p95(&mut exact),
                median_p95(&mut checks),
                median_p95(&mut valid)
            );
        }
        assert!(results.len() >= 140);
        assert!(
            failed.is_empty(),
            "{} of {} failed:\n{}",
            failed.len(),
            results.len(),
            failed.join("\n")
        );
    }
}
