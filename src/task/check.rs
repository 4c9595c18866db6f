//! The fast kinematic check of a task's expert: the episode without cameras, controller or
//! gripper emulator. Per keyframe, the planner plans against a cloud sampled from the
//! true body surfaces (minus the robot's own points and the table band, as the fusion and
//! the episode loop drop them) and the table, the arm jumps to the plan's goal, and the
//! gripper's attachment rules of [`TaskWorld`] apply; the task's success test judges the end.

use cell_types::{FrameId, Joints, PointCloud};
use hil_sim::scene::{robot_capsules, Primitive, HOME_Q};
use nalgebra::{Isometry3, Point3, Vector3};
use planner::{CloudParams, Obstacle, Planner, World};

use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;

use super::world::TaskWorld;
use super::{ExpertSettings, TaskInstance};
use crate::episode::MAX_KEYFRAMES;

/// Spacing of the sampled surface points (m), about the fusion's voxel.
const SPACING: f64 = 0.006;
/// The fusion's margin around the robot's capsules (m).
const ROBOT_MARGIN: f64 = 0.02;
/// The episode loop's table band (m).
const TABLE_BAND: f64 = 0.012;
/// Amplitude of the uniform jitter on every sampled point (m), standing in for the depth
/// noise of the fused cloud.
const JITTER: f64 = 0.003;
/// The 2F-85's stroke (m).
const OPEN_WIDTH: f64 = 0.085;

/// How a kinematic episode ended.
#[derive(Clone, Debug, PartialEq)]
pub struct KinematicReport {
    /// The task's success test passed.
    pub success: bool,
    /// Keyframes reached.
    pub steps: usize,
    /// What went wrong, when something did.
    pub failure: Option<String>,
}

/// Points on a primitive's surface, in its own frame, about `spacing` apart.
pub fn surface_points(shape: &Primitive, spacing: f64) -> Vec<Point3<f64>> {
    let mut out = Vec::new();
    let steps = |len: f64| ((len / spacing).ceil() as usize).max(1);
    let sphere =
        |out: &mut Vec<Point3<f64>>, c: Vector3<f64>, r: f64, upper_only: Option<Vector3<f64>>| {
            let n = steps(4.0 * std::f64::consts::PI * r * r / (spacing * spacing));
            let golden = std::f64::consts::PI * (3.0 - 5f64.sqrt());
            for i in 0..n {
                let z = 1.0 - 2.0 * (i as f64 + 0.5) / n as f64;
                let rho = (1.0 - z * z).max(0.0).sqrt();
                let th = golden * i as f64;
                let d = Vector3::new(rho * th.cos(), rho * th.sin(), z);
                if upper_only.is_none_or(|a| d.dot(&a) >= 0.0) {
                    out.push(Point3::from(c + d * r));
                }
            }
        };
    match *shape {
        Primitive::Sphere { radius } => sphere(&mut out, Vector3::zeros(), radius, None),
        Primitive::Box { half_extents: h } => {
            for axis in 0..3 {
                let (u, v) = ((axis + 1) % 3, (axis + 2) % 3);
                let (nu, nv) = (steps(2.0 * h[u]), steps(2.0 * h[v]));
                for s in [-1.0, 1.0] {
                    for i in 0..=nu {
                        for j in 0..=nv {
                            let mut p = [0.0; 3];
                            p[axis] = s * h[axis];
                            p[u] = -h[u] + 2.0 * h[u] * i as f64 / nu as f64;
                            p[v] = -h[v] + 2.0 * h[v] * j as f64 / nv as f64;
                            out.push(Point3::new(p[0], p[1], p[2]));
                        }
                    }
                }
            }
        }
        Primitive::Cylinder {
            half_height,
            radius,
        } => {
            let na = steps(2.0 * std::f64::consts::PI * radius);
            let nz = steps(2.0 * half_height);
            for i in 0..na {
                let a = 2.0 * std::f64::consts::PI * i as f64 / na as f64;
                for j in 0..=nz {
                    let z = -half_height + 2.0 * half_height * j as f64 / nz as f64;
                    out.push(Point3::new(radius * a.cos(), radius * a.sin(), z));
                }
            }
            let nr = steps(radius);
            for s in [-1.0, 1.0] {
                for k in 0..=nr {
                    let r = radius * k as f64 / nr as f64;
                    let n = steps(2.0 * std::f64::consts::PI * r);
                    for i in 0..n {
                        let a = 2.0 * std::f64::consts::PI * i as f64 / n as f64;
                        out.push(Point3::new(r * a.cos(), r * a.sin(), s * half_height));
                    }
                }
            }
        }
        Primitive::Capsule { a, b, radius } => {
            let a = Vector3::from(a);
            let b = Vector3::from(b);
            let axis = b - a;
            let len = axis.norm();
            let dir = if len > 1e-9 { axis / len } else { Vector3::z() };
            let u = dir.cross(&Vector3::x());
            let u = if u.norm() > 1e-6 {
                u.normalize()
            } else {
                dir.cross(&Vector3::y()).normalize()
            };
            let v = dir.cross(&u);
            let na = steps(2.0 * std::f64::consts::PI * radius);
            let nl = steps(len);
            for i in 0..na {
                let t = 2.0 * std::f64::consts::PI * i as f64 / na as f64;
                let off = (u * t.cos() + v * t.sin()) * radius;
                for j in 0..=nl {
                    out.push(Point3::from(a + axis * (j as f64 / nl as f64) + off));
                }
            }
            sphere(&mut out, a, radius, Some(-dir));
            sphere(&mut out, b, radius, Some(dir));
        }
    }
    out
}

/// The cloud the episode loop would plan against: the bodies' surfaces in the base frame,
/// without the points within the fusion's margin of the robot at `q` (gripper opened to
/// `opening`) and without the table band.
/// `seed` draws the jitter.
pub fn planning_cloud(world: &TaskWorld, q: &Joints, opening: f64, seed: u64) -> PointCloud {
    let mut rng = ChaCha8Rng::seed_from_u64(seed);
    let robot = robot_capsules(q, opening);
    let floor = world.task.table_height + TABLE_BAND;
    let mut points = Vec::new();
    for (body, pose) in world.task.bodies.iter().zip(world.poses()) {
        for part in &body.parts {
            let iso: Isometry3<f64> = pose * part.body_from_part;
            for p in surface_points(&part.shape, SPACING) {
                let mut w = iso * p;
                for k in 0..3 {
                    w[k] += rng.random_range(-JITTER..JITTER);
                }
                if w.z <= floor {
                    continue;
                }
                if robot
                    .iter()
                    .all(|c| c.axis_distance(&w) > c.radius + ROBOT_MARGIN)
                {
                    points.push(w.cast::<f32>());
                }
            }
        }
    }
    PointCloud {
        frame: FrameId::Base,
        points,
        rgb: None,
    }
}

/// Runs `task`'s expert (recording under `settings`: what it executes) kinematically from
/// the home pose with `planner`.
pub fn kinematic_episode(
    task: &TaskInstance,
    settings: &ExpertSettings,
    planner: &Planner,
) -> KinematicReport {
    let keyframes = task.expert_plan(settings).executed;
    let mut world = TaskWorld::new(task.clone());
    let table = Obstacle::table(task.table_height);
    let mut q = HOME_Q;
    let mut open = true;
    let mut opening = OPEN_WIDTH;
    let fail = |steps, why: String| KinematicReport {
        success: false,
        steps,
        failure: Some(why),
    };
    for (step, kf) in keyframes.iter().enumerate().take(MAX_KEYFRAMES) {
        let cloud = planning_cloud(&world, &q, opening, step as u64);
        let scene = match World::from_cloud(&cloud, &CloudParams::default()) {
            Ok(w) => w.with_obstacle(table.clone()),
            Err(e) => return fail(step, format!("keyframe {step}: world: {e}")),
        };
        let motion = match planner.plan_to_keyframe(&q, kf, &scene) {
            Ok(m) => m,
            Err(e) => return fail(step, format!("keyframe {step}: plan: {e}")),
        };
        q = motion.goal;
        let tcp = *planner.model.fk_tcp(&q).isometry();
        world.carry(&tcp);
        if kf.gripper_open != open {
            if kf.gripper_open {
                world.after_gripper(&tcp, false);
                opening = OPEN_WIDTH;
            } else {
                let width = world.before_close(&tcp);
                world.after_gripper(&tcp, width.is_some());
                opening = width.unwrap_or(0.0);
            }
            open = kf.gripper_open;
        }
        if world.success() {
            return KinematicReport {
                success: true,
                steps: step + 1,
                failure: None,
            };
        }
    }
    let n = keyframes.len();
    fail(
        n,
        format!(
            "task not done after the expert's {n} keyframes (held: {:?})",
            world.held()
        ),
    )
}
