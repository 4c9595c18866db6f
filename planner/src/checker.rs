//! Configuration and motion checks against a [`World`] with the sphere model (issue 3 items
//! 1, 2 and 7): the inner loop of the path search and the dense re-check of the result.
//!
//! Motions are checked at a spacing chosen from a per-joint lever bound: no sphere moves more
//! than `Σ_j L_j |Δq_j|` (L_j: the farthest any sphere surface can be from joint j's axis), so
//! sampling that sum at `resolution` metres means no part of the robot (the TCP included)
//! moves more than `resolution` between two checks.

use crate::collision::Sphere;
use crate::error::Contact;
use crate::model::RobotModel;
use crate::world::World;
use cell_types::{Joints, TrajectorySample};
use nalgebra::Isometry3;

/// Per-joint lever arms (m): an upper bound on how far a sphere surface moves per radian.
pub fn lever_arms(model: &RobotModel) -> Joints {
    let chain = &model.chain;
    let poses = chain.link_poses(&[0.0; 6]);
    let mut levers = [0.0; 6];
    for (k, &ji) in chain.actuated.iter().enumerate() {
        let j = &chain.joints[ji];
        let origin = (poses[j.parent] * j.origin).translation.vector;
        for s in &model.spheres.spheres {
            // Only spheres that move with joint k: those on links downstream of it.
            if downstream(model, ji, s.link) {
                let c = poses[s.link] * s.center;
                let d = (c.coords - origin).norm() + s.radius;
                levers[k] = f64::max(levers[k], d);
            }
        }
    }
    levers
}

fn downstream(model: &RobotModel, joint: usize, link: usize) -> bool {
    let chain = &model.chain;
    let mut l = link;
    loop {
        let Some((ji, j)) = chain.joints.iter().enumerate().find(|(_, j)| j.child == l) else {
            return false;
        };
        if ji == joint {
            return true;
        }
        l = j.parent;
    }
}

/// Reusable collision checker for one robot and one world.
pub struct Checker<'a> {
    model: &'a RobotModel,
    world: &'a World,
    poses: [Isometry3<f64>; 7],
    placed: Vec<Sphere>,
    levers: Joints,
    resolution: f64,
    /// Number of configurations checked so far.
    pub checks: u64,
}

impl<'a> Checker<'a> {
    /// A checker whose motion checks move no sphere more than `resolution` metres per step.
    pub fn new(model: &'a RobotModel, world: &'a World, resolution: f64) -> Self {
        Self {
            model,
            world,
            poses: [Isometry3::identity(); 7],
            placed: vec![Sphere::default(); model.spheres.spheres.len()],
            levers: lever_arms(model),
            resolution: resolution.max(1e-4),
            checks: 0,
        }
    }

    /// The lever bound on sphere motion between two configurations (m).
    pub fn sweep_bound(&self, a: &Joints, b: &Joints) -> f64 {
        sweep_with(&self.levers, a, b)
    }

    /// The per-joint lever arms of [`Self::sweep_bound`] (m/rad).
    pub fn levers(&self) -> Joints {
        self.levers
    }

    /// Largest motion of any sphere between two checks of a motion (m).
    pub fn resolution(&self) -> f64 {
        self.resolution
    }

    /// What touches what at `q`, or `None` when it is free.
    pub fn contact(&mut self, q: &Joints) -> Option<Contact> {
        self.checks += 1;
        let sm = &self.model.spheres;
        sm.fk.poses_into(q, &mut self.poses);
        sm.place_from_anchors(&self.poses, &mut self.placed);
        // Per rigid body (distal first): one test of its ball against each obstacle and the
        // distance field, then its spheres only against what the ball may touch.
        for (ball, members) in &sm.world_bodies {
            let c = self.poses[ball.slot.min(6)] * ball.center;
            let near = self.world.near_ball(&c, ball.radius);
            if near.is_empty() {
                continue;
            }
            for &i in members {
                if let Some(h) = self.world.sphere_hit_near(&self.placed[i as usize], &near) {
                    return Some(Contact {
                        link: sm.link_of(i as usize),
                        other: self.world.hit_name(h),
                    });
                }
            }
        }
        sm.self_collision(&self.poses, &self.placed)
    }

    /// True when `q` is within limits and free.
    pub fn is_free(&mut self, q: &Joints) -> bool {
        self.model.within_limits(q) && self.contact(q).is_none()
    }

    /// Number of steps for the straight segment a → b at this checker's resolution.
    pub fn steps(&self, a: &Joints, b: &Joints) -> usize {
        ((self.sweep_bound(a, b) / self.resolution).ceil() as usize).max(1)
    }

    /// True when the straight joint-space segment a → b is free (end points included).
    /// Interior samples go in bisection order so that a blocked segment fails early.
    pub fn motion_free(&mut self, a: &Joints, b: &Joints) -> bool {
        let n = self.steps(a, b);
        if !self.is_free(b) {
            return false;
        }
        // Bisection order over 1..n (van der Corput-like): halves, then quarters, ...
        let mut stride = n.next_power_of_two();
        while stride >= 1 {
            let mut i = stride / 2;
            if stride == 1 {
                break;
            }
            while i < n {
                if !i.is_multiple_of(stride) {
                    let t = i as f64 / n as f64;
                    let q = lerp(a, b, t);
                    if !self.is_free(&q) {
                        return false;
                    }
                }
                i += stride;
            }
            stride /= 2;
        }
        true
    }

    /// First contact along the segment a → b (start included), in order, with its parameter.
    pub fn first_contact_on(&mut self, a: &Joints, b: &Joints) -> Option<(f64, Contact)> {
        let n = self.steps(a, b);
        for i in 0..=n {
            let t = i as f64 / n as f64;
            if let Some(c) = self.contact(&lerp(a, b, t)) {
                return Some((t, c));
            }
        }
        None
    }
}

/// `Σ_j levers_j |a_j − b_j|`: a bound on how far any point moves from `a` to `b` (m).
#[inline]
pub fn sweep_with(levers: &Joints, a: &Joints, b: &Joints) -> f64 {
    (0..6).map(|j| levers[j] * (a[j] - b[j]).abs()).sum()
}

/// Walks the executed trajectory (straight joint-space motion between consecutive samples)
/// and calls `visit(q, t)` on configurations spaced so that the motion bound `sweep` between
/// two consecutive visits, summed over the samples passed in between, is at most
/// `resolution`: the first sample, evenly spaced points along the path, and the last sample.
/// Where the samples crowd (near rest) one visit covers many of them; where they are far
/// apart, several visits fall between two. Stops at the first error `visit` returns.
pub fn dense_walk<E>(
    samples: &[TrajectorySample],
    period: f64,
    resolution: f64,
    sweep: impl Fn(&Joints, &Joints) -> f64,
    mut visit: impl FnMut(&Joints, f64) -> Result<(), E>,
) -> Result<(), E> {
    let (Some(first), Some(last)) = (samples.first(), samples.last()) else {
        return Ok(());
    };
    visit(&first.position, first.t)?;
    // Motion bound since the last visit.
    let mut travel = 0.0;
    for w in samples.windows(2) {
        let (a, b) = (&w[0].position, &w[1].position);
        let len = sweep(a, b);
        if travel + len <= resolution {
            travel += len;
            continue;
        }
        // Distance along this segment of the next visit, then every `resolution`.
        let mut pos = resolution - travel;
        while pos < len {
            let f = pos / len;
            visit(&lerp(a, b, f), w[0].t + f * period)?;
            pos += resolution;
        }
        travel = len - (pos - resolution);
    }
    if samples.len() > 1 {
        visit(&last.position, last.t)?;
    }
    Ok(())
}

/// Linear interpolation in joint space.
pub fn lerp(a: &Joints, b: &Joints, t: f64) -> Joints {
    std::array::from_fn(|j| a[j] + (b[j] - a[j]) * t)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::world::Obstacle;
    use nalgebra::Vector3;
    use rand::{Rng, SeedableRng};

    #[test]
    fn lever_bound_covers_real_sphere_motion() {
        let model = RobotModel::ur5().unwrap();
        let world = World::empty();
        let c = Checker::new(&model, &world, 0.01);
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(9);
        for _ in 0..300 {
            let a: Joints = std::array::from_fn(|_| rng.random_range(-3.0..3.0));
            let b: Joints = std::array::from_fn(|j| a[j] + rng.random_range(-0.05..0.05));
            let pa = model.chain.link_poses(&a);
            let pb = model.chain.link_poses(&b);
            let mut worst = 0.0f64;
            for s in &model.spheres.spheres {
                let d = (pa[s.link] * s.center - pb[s.link] * s.center).norm();
                worst = worst.max(d);
            }
            assert!(worst <= c.sweep_bound(&a, &b) + 1e-12);
        }
    }

    /// The grouped check (body balls against obstacles, the field and each other) answers
    /// exactly as every world sphere against the whole world plus every self pair, on MBM
    /// scenes as primitives and as clouds.
    #[test]
    fn grouped_check_equals_brute_force_over_all_spheres() {
        use crate::mbm::{mbm_robot, MbmFile, WorldMode, MBM_PROBLEMS_PATH};
        let file = MbmFile::parse(&std::fs::read_to_string(MBM_PROBLEMS_PATH).unwrap()).unwrap();
        let model = mbm_robot().unwrap();
        let sm = &model.spheres;
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(21);
        for scene in ["bookshelf_small", "cage", "table_pick"] {
            let p = file.problems[scene].iter().find(|p| p.valid).unwrap();
            for mode in [WorldMode::Primitives, WorldMode::Cloud] {
                let world = p.world(mode).unwrap();
                let mut c = Checker::new(&model, &world, 0.02);
                let (mut placed, mut anchors) = (c.placed.clone(), [Isometry3::identity(); 7]);
                let mut hits = 0;
                for _ in 0..1500 {
                    // Around the start configuration: both outcomes occur often.
                    let (start, _) = p.start_goal().unwrap();
                    let q: Joints = std::array::from_fn(|j| start[j] + rng.random_range(-2.0..2.0));
                    model
                        .chain
                        .anchor_poses_into(&q, &sm.link_anchors, &mut anchors);
                    sm.place_from_anchors(&anchors, &mut placed);
                    let world_hit = sm
                        .world_spheres
                        .iter()
                        .any(|&i| world.sphere_hit(&placed[i as usize]).is_some());
                    let self_hit = sm.self_pairs.iter().any(|&(a, b)| {
                        let (sa, sb) = (placed[a as usize], placed[b as usize]);
                        (sa.center - sb.center).norm() < sa.radius + sb.radius
                    });
                    let brute = world_hit || self_hit;
                    assert_eq!(c.contact(&q).is_some(), brute, "{scene} {mode:?} {q:?}");
                    hits += usize::from(brute);
                }
                assert!(
                    hits > 100 && hits < 1400,
                    "{scene} {mode:?}: {hits} of 1500"
                );
            }
        }
    }

    #[test]
    fn segment_through_a_wall_is_blocked_and_names_the_link() {
        let model = RobotModel::ur5().unwrap();
        let world = World::empty().with_obstacle(Obstacle::Cuboid {
            name: "wall".into(),
            pose: Isometry3::translation(0.0, 0.6, 0.4),
            half: Vector3::new(0.02, 0.3, 0.4),
        });
        let mut c = Checker::new(&model, &world, 0.01);
        let a = [-2.4, -1.57, 1.57, -1.57, -1.57, 0.0];
        let b = [-0.9, -1.57, 1.57, -1.57, -1.57, 0.0];
        assert!(c.contact(&a).is_none(), "{:?}", c.contact(&a));
        assert!(c.contact(&b).is_none(), "{:?}", c.contact(&b));
        assert!(!c.motion_free(&a, &b));
        let (_, contact) = c.first_contact_on(&a, &b).unwrap();
        assert_eq!(contact.other, "obstacle wall");
        assert!(model.chain.links.iter().any(|l| l == contact.link));
    }
}
