//! Keyframe to validated trajectory (issue 3 items 3–8): goal selection over the IK
//! solutions, keyframe semantics (gripper closing volume, "ignore collisions"), path search,
//! shortcutting, jerk-limited timing and the final dense re-checks of the sampled trajectory:
//! with the sphere model, then with the exact parry shapes ([`crate::exact`]) against the same
//! world (keyframe semantics applied).

use crate::checker::{dense_walk, sweep_with, Checker};
use crate::error::PlanError;
use crate::exact::{validate_exact, ExactChecker, ExactModel};
use crate::model::RobotModel;
use crate::rrt::{path_length, plan_path, shortcut, RrtParams};
use crate::timing::{time_path, validate_limits, PlannerLimits};
use crate::world::World;
use cell_types::{Base, Joints, Keyframe, Tcp, Trajectory, Transform};
use nalgebra::Point3;
use std::time::Instant;

/// The clock [`PlanStats`] stage times are read from.
#[derive(Copy, Clone, Debug, Default, PartialEq, Eq)]
pub enum StageClock {
    /// Monotonic wall clock.
    #[default]
    Wall,
    /// CPU time of the planning thread (`CLOCK_THREAD_CPUTIME_ID`, via `cpu-time`; a system
    /// call per read): benchmarks on a shared machine, where other processes would inflate
    /// wall-clock times.
    ThreadCpu,
}

/// A stopwatch on a [`StageClock`].
struct Stopwatch {
    wall: Instant,
    cpu: Option<cpu_time::ThreadTime>,
}

impl Stopwatch {
    fn start(clock: StageClock) -> Self {
        Self {
            wall: Instant::now(),
            cpu: match clock {
                StageClock::Wall => None,
                StageClock::ThreadCpu => cpu_time::ThreadTime::try_now().ok(),
            },
        }
    }

    /// Seconds since the start.
    fn elapsed(&self) -> f64 {
        match self.cpu.as_ref().and_then(|c| c.try_elapsed().ok()) {
            Some(d) => d.as_secs_f64(),
            None => self.wall.elapsed().as_secs_f64(),
        }
    }
}

/// The region between the open 2F-85 fingers at the goal, plus a margin: cloud points in it
/// belong to the object being grasped or placed and are excluded for the final approach.
#[derive(Copy, Clone, Debug, PartialEq)]
pub struct ClosingVolume {
    /// Half extents in the TCP frame (m): x across the fingers, y along the pads, z along the
    /// approach axis.
    pub half_extents: [f64; 3],
    /// Offset of the box centre from the TCP along the TCP z (m).
    pub z_offset: f64,
}

impl Default for ClosingVolume {
    /// 85 mm stroke plus the fingers and 1 cm margin; pads 22 mm wide plus margin; from 5 cm
    /// behind the TCP to 2.5 cm past the fingertips.
    fn default() -> Self {
        Self {
            half_extents: [0.0425 + 0.016 + 0.01, 0.011 + 0.01, 0.0375],
            z_offset: -0.0125,
        }
    }
}

impl ClosingVolume {
    /// The whole 2F-85 at the start of a motion (body cylinder, fingers, pads) plus 1 cm: the
    /// space the gripper occupies already. Cloud points in it are the object it holds or
    /// touches (or sensor noise on its surface), not obstacles for moving it away.
    pub fn gripper_envelope() -> Self {
        // TCP frame: body radius 45 mm from 150 to 55 mm behind the TCP, fingers out to
        // x = ±58.5 mm, fingertips 15 mm past the TCP.
        let (back, front) = (-0.15 - 0.01, 0.015 + 0.01);
        Self {
            half_extents: [0.0585 + 0.01, 0.045 + 0.01, (front - back) / 2.0],
            z_offset: (front + back) / 2.0,
        }
    }

    /// A ball containing the volume at TCP pose `base_from_tcp` (centre, radius); `None`
    /// when the volume is empty (a negative half extent).
    pub fn bounding_ball(
        &self,
        base_from_tcp: &Transform<Base, Tcp>,
    ) -> Option<(Point3<f64>, f64)> {
        if self.half_extents.iter().any(|h| *h < 0.0) {
            return None;
        }
        let c = base_from_tcp.transform_point(&Point3::new(0.0, 0.0, self.z_offset));
        let h = self.half_extents;
        Some((c, (h[0] * h[0] + h[1] * h[1] + h[2] * h[2]).sqrt()))
    }

    /// True when some point of the world's cloud lies in the volume (one radius query of the
    /// cloud's tree around the volume's bounding ball, instead of a pass over every point).
    pub fn holds_cloud_points(&self, base_from_tcp: &Transform<Base, Tcp>, world: &World) -> bool {
        let (Some((c, r)), Some(f)) = (self.bounding_ball(base_from_tcp), world.field()) else {
            return false;
        };
        f.tree()
            .find_within(&c, r, &mut |p| self.contains(base_from_tcp, p))
            .is_some()
    }

    /// True when the base-frame point lies in the volume at TCP pose `base_from_tcp`.
    pub fn contains(&self, base_from_tcp: &Transform<Base, Tcp>, p: &Point3<f64>) -> bool {
        let l = base_from_tcp.inverse().transform_point(p);
        l.x.abs() <= self.half_extents[0]
            && l.y.abs() <= self.half_extents[1]
            && (l.z - self.z_offset).abs() <= self.half_extents[2]
    }
}

/// Search and check settings.
#[derive(Copy, Clone, Debug, PartialEq)]
pub struct PlannerConfig {
    /// RRT-Connect and shortcut settings.
    pub rrt: RrtParams,
    /// Largest motion of any robot point between two checks during the search (m).
    pub check_resolution: f64,
    /// Largest motion of any robot point (the TCP included) between two checks in the final
    /// re-checks, sphere and exact (m).
    pub validate_resolution: f64,
    /// Joint weights for choosing the IK solution closest to the start.
    pub goal_weights: Joints,
    /// The gripper's closing volume for grasp/place keyframes.
    pub closing_volume: ClosingVolume,
    /// The space the gripper occupies at the start of a motion: cloud points in it are what
    /// it holds or touches and are excluded for that motion (an empty volume turns this off).
    pub start_volume: ClosingVolume,
    /// Clearance (m) the exact re-check demands between the link shapes and the world; 0: the
    /// shapes must not touch (the sphere cover is conservative only for 0).
    pub exact_margin: f64,
    /// Also re-check the trajectory densely with the spheres before the exact re-check (the
    /// spheres cover the shapes, so this only adds false alarms and time; kept on by default).
    pub sphere_recheck: bool,
    /// The clock of the stage times in [`PlanStats`].
    pub clock: StageClock,
}

impl Default for PlannerConfig {
    fn default() -> Self {
        Self {
            rrt: RrtParams::default(),
            // The search's spacing is a speed setting, not the guarantee: the dense re-checks
            // (1 cm, spheres and exact shapes) are, and a contact they find sends the search
            // back at half the spacing. 4 cm halves the search's checks against 2 cm on the
            // MBM problems (median 0.56 vs 0.91 ms on 140 of them) for a few more replans.
            check_resolution: 0.04,
            validate_resolution: 0.01,
            goal_weights: [3.0, 3.0, 2.0, 1.0, 1.0, 1.0],
            closing_volume: ClosingVolume::default(),
            start_volume: ClosingVolume::gripper_envelope(),
            exact_margin: 0.0,
            sphere_recheck: true,
            clock: StageClock::Wall,
        }
    }
}

/// Where the time went and what was done, for one plan.
#[derive(Copy, Clone, Debug, Default, PartialEq)]
pub struct PlanStats {
    /// IK and goal selection (s).
    pub goal_s: f64,
    /// Path search (s).
    pub search_s: f64,
    /// Shortcutting (s).
    pub shortcut_s: f64,
    /// Ruckig timing (s).
    pub timing_s: f64,
    /// Limit validation and dense re-check with the spheres (s).
    pub validate_s: f64,
    /// Dense re-check with the exact parry shapes (s).
    pub exact_s: f64,
    /// Configurations checked with the exact shapes.
    pub exact_checks: u64,
    /// Everything (s).
    pub total_s: f64,
    /// RRT iterations (0: the direct segment was free).
    pub iterations: usize,
    /// Searches repeated at a finer spacing because a dense re-check found a contact the
    /// search had missed (their time is in `total_s` only).
    pub replans: usize,
    /// Configurations checked.
    pub checks: u64,
    /// Joint-space path length after shortcutting (rad).
    pub path_length: f64,
    /// Waypoints after shortcutting.
    pub waypoints: usize,
}

/// A planned, timed and validated motion.
#[derive(Clone, Debug)]
pub struct PlannedMotion {
    /// The trajectory at the controller rate.
    pub trajectory: Trajectory,
    /// The geometric path (waypoints) the trajectory follows exactly.
    pub path: Vec<Joints>,
    /// The chosen goal configuration.
    pub goal: Joints,
    /// Timing and work statistics.
    pub stats: PlanStats,
}

/// The planner: a robot model, its limits and search settings.
#[derive(Clone, Debug)]
pub struct Planner {
    /// The robot.
    pub model: RobotModel,
    /// Kinematic limits and controller period.
    pub limits: PlannerLimits,
    /// Search settings.
    pub config: PlannerConfig,
    /// The robot's exact (parry) shapes for the final re-check, built by [`Planner::new`] with
    /// `config.exact_margin` (rebuild it after changing that margin).
    pub exact: ExactModel,
}

impl Planner {
    /// A planner, checking the limits.
    pub fn new(
        model: RobotModel,
        limits: PlannerLimits,
        config: PlannerConfig,
    ) -> Result<Self, PlanError> {
        limits.validate()?;
        let exact = ExactModel::new(&model, config.exact_margin)?;
        Ok(Self {
            model,
            limits,
            config,
            exact,
        })
    }

    /// Plans from `start` to the keyframe's TCP pose against `world`.
    pub fn plan_to_keyframe(
        &self,
        start: &Joints,
        keyframe: &Keyframe,
        world: &World,
    ) -> Result<PlannedMotion, PlanError> {
        let t0 = Stopwatch::start(self.config.clock);
        self.model.check_limits(start)?;
        // Keyframe semantics: "ignore collisions" drops the cloud; otherwise points in the
        // closing volume at the goal belong to the object and are excluded for this motion,
        // and so are points inside the gripper where it stands now (what it holds or
        // touches: a grasp a few millimetres off leaves the object's surface in the palm).
        let cv = self.config.closing_volume;
        let sv = self.config.start_volume;
        let pose = keyframe.base_from_tcp;
        let start_pose = self.model.fk_tcp(start);
        let at_goal = cv.holds_cloud_points(&pose, world);
        let at_start = sv.holds_cloud_points(&start_pose, world);
        let owned;
        let world = if keyframe.ignore_collisions {
            owned = world.without_cloud();
            &owned
        } else if !at_goal && !at_start {
            world
        } else {
            match world.without_points(|p| {
                (at_goal && cv.contains(&pose, p)) || (at_start && sv.contains(&start_pose, p))
            })? {
                Some(w) => {
                    owned = w;
                    &owned
                }
                None => world,
            }
        };
        let sols = self.model.ik_near(&pose, start)?;
        let mut checker = Checker::new(&self.model, world, self.config.check_resolution);
        if let Some(contact) = checker.contact(start) {
            return Err(PlanError::StartInCollision { contact });
        }
        let mut free = Vec::new();
        let mut first_contact = None;
        for s in &sols {
            match checker.contact(s) {
                None => free.push(*s),
                Some(c) => {
                    first_contact.get_or_insert(c);
                }
            }
        }
        let w = self.config.goal_weights;
        let cost = |q: &Joints| -> f64 { (0..6).map(|j| w[j] * (q[j] - start[j]).abs()).sum() };
        free.sort_by(|a, b| cost(a).total_cmp(&cost(b)));
        if free.is_empty() {
            if let Some(first) = first_contact {
                return Err(PlanError::AllSolutionsInCollision {
                    solutions: sols.len(),
                    first,
                });
            }
        }
        let goal_s = t0.elapsed();
        let mut last_err = PlanError::NoPath { iterations: 0 };
        for goal in free {
            match self.plan_joints_inner(start, &goal, &mut checker, world) {
                Ok(mut m) => {
                    m.stats.goal_s = goal_s;
                    m.stats.total_s = t0.elapsed();
                    return Ok(m);
                }
                Err(e) => last_err = e,
            }
        }
        Err(last_err)
    }

    /// Plans from `start` to the joint configuration `goal` against `world` (the MBM
    /// benchmark's problems are given this way).
    pub fn plan_to_joints(
        &self,
        start: &Joints,
        goal: &Joints,
        world: &World,
    ) -> Result<PlannedMotion, PlanError> {
        let t0 = Stopwatch::start(self.config.clock);
        self.model.check_limits(start)?;
        self.model.check_limits(goal)?;
        let mut checker = Checker::new(&self.model, world, self.config.check_resolution);
        if let Some(contact) = checker.contact(start) {
            return Err(PlanError::StartInCollision { contact });
        }
        if let Some(first) = checker.contact(goal) {
            return Err(PlanError::AllSolutionsInCollision {
                solutions: 1,
                first,
            });
        }
        let mut m = self.plan_joints_inner(start, goal, &mut checker, world)?;
        m.stats.total_s = t0.elapsed();
        Ok(m)
    }

    /// Search, shortcut, time and validate; when the dense re-check finds a contact the
    /// coarser search missed (a sphere clipping an edge between two search checks), search
    /// again at half the spacing, down to the validation spacing / 2.
    fn plan_joints_inner(
        &self,
        start: &Joints,
        goal: &Joints,
        checker: &mut Checker<'_>,
        world: &World,
    ) -> Result<PlannedMotion, PlanError> {
        let first = self.plan_joints_once(start, goal, checker, world);
        let mut spent = checker.checks;
        let mut res = self.config.check_resolution;
        let mut result = first;
        let mut replans = 0;
        while matches!(
            result,
            Err(PlanError::TrajectoryCollides { .. } | PlanError::ExactCollision { .. })
        ) && res > self.config.validate_resolution / 2.0
        {
            res /= 2.0;
            replans += 1;
            let mut finer = Checker::new(&self.model, world, res);
            result = self.plan_joints_once(start, goal, &mut finer, world);
            spent += finer.checks;
        }
        result.map(|mut m| {
            m.stats.checks = m.stats.checks.max(spent);
            m.stats.replans = replans;
            m
        })
    }

    fn plan_joints_once(
        &self,
        start: &Joints,
        goal: &Joints,
        checker: &mut Checker<'_>,
        world: &World,
    ) -> Result<PlannedMotion, PlanError> {
        let mut stats = PlanStats::default();
        let t = Stopwatch::start(self.config.clock);
        let search = plan_path(start, goal, &self.model.limits, checker, &self.config.rrt)?;
        stats.search_s = t.elapsed();
        stats.iterations = search.iterations;
        let mut path = search.path;
        let t = Stopwatch::start(self.config.clock);
        shortcut(
            &mut path,
            checker,
            self.config.rrt.shortcut_attempts,
            self.config.rrt.seed,
        );
        stats.shortcut_s = t.elapsed();
        stats.path_length = path_length(&path);
        stats.waypoints = path.len();
        let t = Stopwatch::start(self.config.clock);
        let trajectory = time_path(&path, &self.limits)?;
        stats.timing_s = t.elapsed();
        let t = Stopwatch::start(self.config.clock);
        validate_limits(&trajectory, &self.model.limits, &self.limits)?;
        let mut dense = Checker::new(&self.model, world, self.config.validate_resolution);
        if self.config.sphere_recheck {
            validate_dense(&trajectory, &mut dense)?;
        }
        stats.validate_s = t.elapsed();
        // The same world the search used (keyframe semantics applied), with the exact shapes.
        let t = Stopwatch::start(self.config.clock);
        let mut exact = ExactChecker::new(
            &self.exact,
            &self.model.chain,
            world,
            self.config.validate_resolution,
        );
        validate_exact(&trajectory, &mut exact)?;
        stats.exact_s = t.elapsed();
        stats.exact_checks = exact.checks;
        stats.checks = checker.checks + dense.checks;
        Ok(PlannedMotion {
            trajectory,
            path,
            goal: *goal,
            stats,
        })
    }
}

/// Re-checks the executed trajectory densely with the spheres: configurations along it such
/// that no robot point moves more than the checker's resolution between two checks
/// ([`dense_walk`]). Consecutive samples lie on one straight checked segment
/// (phase-synchronized rest-to-rest timing), so linear interpolation between them is the
/// executed motion.
pub fn validate_dense(traj: &Trajectory, checker: &mut Checker<'_>) -> Result<(), PlanError> {
    let res = checker.resolution();
    let levers = checker.levers();
    dense_walk(
        traj.samples(),
        traj.period(),
        res,
        |a, b| sweep_with(&levers, a, b),
        |q, t| match checker.contact(q) {
            Some(contact) => Err(PlanError::TrajectoryCollides { t, contact }),
            None => Ok(()),
        },
    )
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::world::{CloudParams, Obstacle};
    use cell_types::{FrameId, PointCloud};
    use nalgebra::{Isometry3, Vector3};

    fn planner() -> Planner {
        Planner::new(
            RobotModel::ur5().unwrap(),
            PlannerLimits::default(),
            PlannerConfig::default(),
        )
        .unwrap()
    }

    const HOME: Joints = [0.0, -1.57, 1.57, -1.57, -1.57, 0.0];

    fn table() -> Obstacle {
        Obstacle::HalfSpace {
            name: "table".into(),
            normal: Vector3::z_axis(),
            offset: -0.01,
        }
    }

    fn wall() -> Obstacle {
        Obstacle::Cuboid {
            name: "wall".into(),
            pose: Isometry3::translation(0.0, 0.6, 0.4),
            half: Vector3::new(0.02, 0.3, 0.4),
        }
    }

    /// Points on the surface of the wall box, 1 cm apart.
    fn wall_cloud() -> PointCloud {
        let mut pts = Vec::new();
        for i in 0..=60 {
            for k in 0..=80 {
                let y = 0.3 + i as f32 * 0.01;
                let z = k as f32 * 0.01;
                pts.push(Point3::new(-0.02, y, z));
                pts.push(Point3::new(0.02, y, z));
            }
        }
        PointCloud::new(FrameId::Base, pts, None).unwrap()
    }

    fn assert_valid(p: &Planner, m: &PlannedMotion, start: &Joints, world: &World) {
        assert_eq!(m.trajectory.start(), Some(start));
        assert_eq!(m.trajectory.goal(), Some(&m.goal));
        validate_limits(&m.trajectory, &p.model.limits, &p.limits).unwrap();
        let mut c = Checker::new(&p.model, world, 0.005);
        validate_dense(&m.trajectory, &mut c).unwrap();
    }

    #[test]
    fn keyframe_behind_a_wall_needs_rrt_and_gives_a_valid_trajectory() {
        let p = planner();
        let world = World::empty().with_obstacle(table()).with_obstacle(wall());
        let start = [-2.4, -1.57, 1.57, -1.57, -1.57, 0.0];
        let goal = [-0.9, -1.57, 1.57, -1.57, -1.57, 0.0];
        let kf = Keyframe::new(p.model.fk_tcp(&goal), true, false).unwrap();
        let m = p.plan_to_keyframe(&start, &kf, &world).unwrap();
        assert!(
            m.stats.iterations > 0,
            "the direct segment crosses the wall"
        );
        let (dt, dr) = p.model.fk_tcp(&m.goal).error_to(&kf.base_from_tcp);
        assert!(dt < 1e-9 && dr < 1e-9);
        assert_valid(&p, &m, &start, &world);
        // Deterministic for a seed.
        let again = p.plan_to_keyframe(&start, &kf, &world).unwrap();
        assert_eq!(again.path, m.path);
    }

    #[test]
    fn same_wall_as_a_cloud_is_also_avoided() {
        let p = planner();
        let world = World::from_cloud(&wall_cloud(), &CloudParams::default())
            .unwrap()
            .with_obstacle(table());
        let start = [-2.4, -1.57, 1.57, -1.57, -1.57, 0.0];
        let goal = [-0.9, -1.57, 1.57, -1.57, -1.57, 0.0];
        let m = p.plan_to_joints(&start, &goal, &world).unwrap();
        assert!(m.stats.iterations > 0);
        assert_valid(&p, &m, &start, &world);
    }

    #[test]
    fn keyframe_inside_an_obstacle_names_the_touching_link() {
        let p = planner();
        let q = [-1.5, -1.2, 1.4, -1.6, -1.57, 0.0];
        let tcp = p.model.fk_tcp(&q);
        let block = Obstacle::Ball {
            name: "block".into(),
            center: Point3::from(tcp.translation()) + Vector3::new(0.0, 0.0, 0.0),
            radius: 0.08,
        };
        let world = World::empty().with_obstacle(block);
        let kf = Keyframe::new(tcp, true, false).unwrap();
        let err = p.plan_to_keyframe(&HOME, &kf, &world).unwrap_err();
        match err {
            PlanError::AllSolutionsInCollision { first, .. } => {
                assert_eq!(first.other, "obstacle block");
                assert!(
                    first.link == "gripper_link" || first.link == "wrist_3_link",
                    "{first}"
                );
            }
            e => panic!("unexpected {e}"),
        }
    }

    /// The tree query for cloud points in the closing volume agrees with a pass over every
    /// point, and an empty volume (negative extent) holds none.
    #[test]
    fn closing_volume_tree_query_matches_a_scan_of_the_points() {
        use rand::{Rng, SeedableRng};
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(4);
        let pts: Vec<Point3<f32>> = (0..3000)
            .map(|_| {
                Point3::new(
                    rng.random_range(0.2..0.6),
                    rng.random_range(-0.2..0.2),
                    rng.random_range(0.0..0.4),
                )
            })
            .collect();
        let cloud = PointCloud::new(FrameId::Base, pts.clone(), None).unwrap();
        let world = World::from_cloud(&cloud, &CloudParams::default()).unwrap();
        let cv = ClosingVolume::default();
        let (mut inside, mut outside) = (0, 0);
        for _ in 0..300 {
            let pose = Transform::<Base, Tcp>::from_isometry(nalgebra::Isometry3::new(
                nalgebra::Vector3::new(
                    rng.random_range(0.1..0.7),
                    rng.random_range(-0.3..0.3),
                    rng.random_range(-0.1..0.5),
                ),
                nalgebra::Vector3::new(
                    rng.random_range(-3.0..3.0),
                    rng.random_range(-3.0..3.0),
                    rng.random_range(-3.0..3.0),
                ),
            ));
            let scan = pts.iter().any(|p| cv.contains(&pose, &p.cast::<f64>()));
            assert_eq!(cv.holds_cloud_points(&pose, &world), scan);
            if scan {
                inside += 1;
            } else {
                outside += 1;
            }
            let empty = ClosingVolume {
                half_extents: [-1.0; 3],
                ..cv
            };
            assert!(!empty.holds_cloud_points(&pose, &world));
        }
        assert!(inside > 10 && outside > 10, "{inside} {outside}");
    }

    #[test]
    fn grasp_target_in_the_cloud_is_excluded_but_ignore_collisions_still_sees_the_table() {
        let p = planner();
        let q = [-1.5, -1.2, 1.4, -1.6, -1.57, 0.0];
        let tcp = p.model.fk_tcp(&q);
        // A small object between the fingers at the goal: a 3 cm cube of points.
        let c = tcp.translation();
        let mut pts = Vec::new();
        for i in 0..4 {
            for j in 0..4 {
                for k in 0..4 {
                    let d =
                        Vector3::new(i as f64, j as f64, k as f64) * 0.01 - Vector3::repeat(0.015);
                    pts.push(Point3::from(c + d).cast::<f32>());
                }
            }
        }
        let cloud = PointCloud::new(FrameId::Base, pts, None).unwrap();
        let world = World::from_cloud(&cloud, &CloudParams::default()).unwrap();
        let kf = Keyframe::new(tcp, false, false).unwrap();
        let m = p.plan_to_keyframe(&HOME, &kf, &world).unwrap();
        assert_eq!(m.trajectory.goal(), Some(&m.goal));
        // Without the exclusion the same goal is in collision with the object.
        let mut checker = Checker::new(&p.model, &world, 0.01);
        assert!(checker.contact(&m.goal).is_some());
        // "Ignore collisions" plans through the cloud but not through static geometry.
        let static_world = world.clone().with_obstacle(Obstacle::Ball {
            name: "fixture".into(),
            center: Point3::from(c),
            radius: 0.02,
        });
        let kf_ignore = Keyframe::new(tcp, false, true).unwrap();
        let err = p
            .plan_to_keyframe(&HOME, &kf_ignore, &static_world)
            .unwrap_err();
        assert!(
            matches!(err, PlanError::AllSolutionsInCollision { ref first, .. } if first.other == "obstacle fixture"),
            "{err}"
        );
        // With the cloud only, "ignore collisions" plans straight to the goal.
        let m = p.plan_to_keyframe(&HOME, &kf_ignore, &world).unwrap();
        assert_eq!(m.trajectory.goal(), Some(&m.goal));
    }

    #[test]
    fn exact_margin_larger_than_the_clearance_gives_a_typed_exact_collision() {
        let config = PlannerConfig {
            exact_margin: 0.3,
            ..PlannerConfig::default()
        };
        let p = Planner::new(RobotModel::ur5().unwrap(), PlannerLimits::default(), config).unwrap();
        let world = World::empty().with_obstacle(wall());
        let start = [-2.4, -1.57, 1.57, -1.57, -1.57, 0.0];
        let goal = [-0.9, -1.57, 1.57, -1.57, -1.57, 0.0];
        let err = p.plan_to_joints(&start, &goal, &world).unwrap_err();
        match err {
            PlanError::ExactCollision { contact, .. } => {
                assert_eq!(contact.other, crate::ExactOther::Obstacle("wall".into()));
                assert!(p.model.chain.link_index(contact.link).is_some());
            }
            e => panic!("unexpected {e}"),
        }
        let bad = PlannerConfig {
            exact_margin: f64::NAN,
            ..PlannerConfig::default()
        };
        assert!(Planner::new(RobotModel::ur5().unwrap(), PlannerLimits::default(), bad).is_err());
    }

    #[test]
    fn points_inside_the_gripper_at_the_start_do_not_block_moving_away() {
        let p = planner();
        let q = [-1.5, -1.2, 1.4, -1.6, -1.57, 0.0];
        let tcp = p.model.fk_tcp(&q);
        // A held object whose top reaches into the palm: a column of points along the
        // approach axis from the fingertips to 8 cm behind the TCP.
        let pts: Vec<_> = (0..20)
            .map(|i| {
                let local = Point3::new(0.0, 0.0, 0.01 - 0.0045 * i as f64);
                tcp.transform_point(&local).cast::<f32>()
            })
            .collect();
        let cloud = PointCloud::new(FrameId::Base, pts, None).unwrap();
        let world = World::from_cloud(&cloud, &CloudParams::default()).unwrap();
        let mut checker = Checker::new(&p.model, &world, 0.01);
        assert!(
            checker.contact(&q).is_some(),
            "the start touches the object"
        );
        let kf = Keyframe::new(p.model.fk_tcp(&HOME), true, false).unwrap();
        let m = p.plan_to_keyframe(&q, &kf, &world).unwrap();
        assert_eq!(m.trajectory.goal(), Some(&m.goal));
        // With the envelope turned off the same start is refused, naming the contact.
        let off = Planner::new(
            RobotModel::ur5().unwrap(),
            PlannerLimits::default(),
            PlannerConfig {
                start_volume: ClosingVolume {
                    half_extents: [-1.0; 3],
                    z_offset: 0.0,
                },
                ..PlannerConfig::default()
            },
        )
        .unwrap();
        let err = off.plan_to_keyframe(&q, &kf, &world).unwrap_err();
        assert!(
            matches!(err, PlanError::StartInCollision { ref contact } if contact.other.contains("cloud")),
            "{err}"
        );
        // The envelope covers the gripper's links but not the wrist: a point at the wrist
        // still blocks.
        let wrist = tcp
            .transform_point(&Point3::new(0.0, 0.0, -0.25))
            .cast::<f32>();
        let cloud = PointCloud::new(FrameId::Base, vec![wrist], None).unwrap();
        let world = World::from_cloud(&cloud, &CloudParams::default()).unwrap();
        assert!(Checker::new(&p.model, &world, 0.01).contact(&q).is_some());
        let err = p.plan_to_keyframe(&q, &kf, &world).unwrap_err();
        assert!(matches!(err, PlanError::StartInCollision { .. }), "{err}");
    }

    #[test]
    fn start_in_collision_and_out_of_limits_are_typed() {
        let p = planner();
        let world = World::empty().with_obstacle(Obstacle::HalfSpace {
            name: "table".into(),
            normal: Vector3::z_axis(),
            offset: 0.5,
        });
        let kf = Keyframe::new(p.model.fk_tcp(&HOME), true, false).unwrap();
        let err = p.plan_to_keyframe(&HOME, &kf, &world).unwrap_err();
        assert!(matches!(err, PlanError::StartInCollision { .. }), "{err}");
        let mut bad = HOME;
        bad[2] = 4.0;
        let err = p.plan_to_keyframe(&bad, &kf, &World::empty()).unwrap_err();
        assert!(
            matches!(err, PlanError::JointLimit { joint: 2, .. }),
            "{err}"
        );
    }
}
