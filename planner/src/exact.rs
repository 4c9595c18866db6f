//! Exact collision check with parry3d shapes (issue 3 items 1 and 7): every URDF collision
//! primitive of every link as a parry shape (cylinder, box, ball, capsule, with its URDF
//! origin), placed with the link poses of forward kinematics, and tested against the same
//! [`World`] the search used: its static obstacles as parry shapes (boxes, cylinders, balls,
//! the table as a half-space), its cloud points (candidates from the point tree's radius query
//! around each part's bounding ball, then parry's point query), and the robot itself between
//! links whose rigid bodies are [`SELF_BODY_GAP`] or more moving joints apart (the sphere
//! model's allowed-collision rule, from the URDF adjacency).
//!
//! A link is a hand-rolled compound: its parts each with a bounding ball in the link frame,
//! so a query only runs parry on the parts whose ball comes within reach: the obstacles' exact
//! signed distance to the ball centre and the distance field (a lower bound on the distance
//! to the cloud) skip parts far from everything.
//!
//! [`validate_exact`] re-checks an executed trajectory: configurations along it such that no
//! point of any link (the TCP included) moves more than the resolution between two checks. The bound is configuration-independent: a
//! point of link `L` is at most `Σ |t_j| + |c| + r` from joint `k`'s origin (the joint origins
//! between them, the part's bounding ball), so it moves at most that much per radian of `k`.
//!
//! parry3d works in `f32`: placed poses and points are rounded to about 0.1 µm at arm scale.

use crate::collision::{link_bodies, SELF_BODY_GAP};
use crate::error::{ExactContact, ExactOther, PlanError};
use crate::model::RobotModel;
use crate::urdf::{Chain, Shape};
use crate::world::{Obstacle, World};
use cell_types::{Joints, Trajectory};
use nalgebra::{Isometry3, Point3, UnitQuaternion, Vector3};
use parry3d::math::{Pose, Rot3, Vector};
use parry3d::query;
use parry3d::shape::SharedShape;
use std::f64::consts::FRAC_PI_2;

/// One collision primitive of a link as a parry shape.
#[derive(Clone)]
pub struct ExactPart {
    /// The shape in parry's own frame (cylinders along y, capsules along z).
    pub shape: SharedShape,
    /// Pose of the parry shape in the link frame (the URDF origin, turned for cylinders).
    pub local: Isometry3<f64>,
    /// Centre of a ball containing the shape, in the link frame.
    pub center: Point3<f64>,
    /// Radius of that ball (m).
    pub radius: f64,
}

impl std::fmt::Debug for ExactPart {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("ExactPart")
            .field("shape", &self.shape.shape_type())
            .field("local", &self.local)
            .field("radius", &self.radius)
            .finish()
    }
}

/// Converts a URDF collision primitive into a parry part.
pub fn part_of(shape: &Shape) -> ExactPart {
    let turn_y_to_z = UnitQuaternion::from_axis_angle(&Vector3::x_axis(), FRAC_PI_2);
    match shape {
        Shape::Sphere { origin, radius } => ExactPart {
            shape: SharedShape::ball(*radius as f32),
            local: *origin,
            center: origin * Point3::origin(),
            radius: *radius,
        },
        Shape::Cylinder {
            origin,
            radius,
            length,
        } => ExactPart {
            shape: SharedShape::cylinder((length / 2.0) as f32, *radius as f32),
            local: origin * turn_y_to_z,
            center: origin * Point3::origin(),
            radius: radius.hypot(length / 2.0),
        },
        Shape::Capsule {
            origin,
            radius,
            length,
        } => ExactPart {
            shape: SharedShape::capsule_z((length / 2.0) as f32, *radius as f32),
            local: *origin,
            center: origin * Point3::origin(),
            radius: radius + length / 2.0,
        },
        Shape::Cuboid { origin, size } => ExactPart {
            shape: SharedShape::cuboid(
                (size[0] / 2.0) as f32,
                (size[1] / 2.0) as f32,
                (size[2] / 2.0) as f32,
            ),
            local: *origin,
            center: origin * Point3::origin(),
            radius: Vector3::new(size[0], size[1], size[2]).norm() / 2.0,
        },
    }
}

/// A nalgebra isometry as parry's `f32` glam pose.
pub fn to_pose(iso: &Isometry3<f64>) -> Pose {
    let t = iso.translation.vector;
    let q = iso.rotation.coords; // (i, j, k, w)
    Pose::from_parts(
        Vector::new(t.x as f32, t.y as f32, t.z as f32),
        Rot3::from_xyzw(q.x as f32, q.y as f32, q.z as f32, q.w as f32).normalize(),
    )
}

fn to_vec(p: &Point3<f64>) -> Vector {
    Vector::new(p.x as f32, p.y as f32, p.z as f32)
}

/// The robot's exact collision geometry: parry parts per link, the links checked against the
/// world, the link pairs checked against each other, and the motion bound per joint.
#[derive(Clone, Debug)]
pub struct ExactModel {
    /// Link names (for contacts).
    pub link_names: Vec<&'static str>,
    /// All parts, grouped by link: link `l` owns `parts[part_start[l]..part_start[l + 1]]`.
    pub parts: Vec<ExactPart>,
    /// Index of each link's first part (one entry more than there are links).
    pub part_start: Vec<usize>,
    /// Per link: a ball containing all its parts (centre in the link frame, radius), for
    /// rejecting whole links before their parts.
    pub link_balls: Vec<(Point3<f64>, f64)>,
    /// Links checked against the world: those with parts, except the root body's (the base
    /// stands on the table by design, as in the sphere model).
    pub world_links: Vec<usize>,
    /// Link pairs checked for self-collision (bodies at least [`SELF_BODY_GAP`] apart).
    pub self_pairs: Vec<(usize, usize)>,
    /// Per joint: an upper bound on how far any point of any link moves per radian (m).
    pub levers: Joints,
    /// Per link: anchor slot and fixed pose in it (see [`Chain::anchors`]).
    pub link_anchors: Vec<(usize, Isometry3<f64>)>,
    /// Clearance (m) below which a link counts as touching.
    pub margin: f64,
}

impl ExactModel {
    /// Builds the exact model of a robot; `margin` (m, ≥ 0) is the clearance that counts as
    /// contact. The sphere cover is only guaranteed conservative for a margin of 0 (its
    /// spheres touch the shapes at the seams between neighbours).
    pub fn new(model: &RobotModel, margin: f64) -> Result<Self, PlanError> {
        if !(margin.is_finite() && margin >= 0.0) {
            return Err(PlanError::BadLimit {
                what: "exact-check margin",
                value: margin,
            });
        }
        let chain = &model.chain;
        let mut parts = Vec::new();
        let mut part_start = Vec::with_capacity(chain.links.len() + 1);
        for shapes in &chain.shapes {
            part_start.push(parts.len());
            parts.extend(shapes.iter().map(part_of));
        }
        part_start.push(parts.len());
        let has_parts = |l: usize| part_start[l + 1] > part_start[l];
        let bodies = link_bodies(chain);
        let n = chain.links.len();
        let world_links = (0..n).filter(|&l| has_parts(l) && bodies[l] != 0).collect();
        let mut self_pairs = Vec::new();
        for a in (0..n).filter(|&l| has_parts(l)) {
            for b in (a + 1..n).filter(|&l| has_parts(l)) {
                if bodies[a].abs_diff(bodies[b]) >= SELF_BODY_GAP {
                    self_pairs.push((a, b));
                }
            }
        }
        let link_names = (0..n)
            .map(|l| {
                model
                    .spheres
                    .link_names
                    .get(l)
                    .copied()
                    .unwrap_or("unknown")
            })
            .collect();
        let levers = levers(chain, &parts, &part_start);
        let link_balls = (0..n)
            .map(|l| {
                let own = &parts[part_start[l]..part_start[l + 1]];
                let Some(first) = own.first() else {
                    return (Point3::origin(), 0.0);
                };
                let (mut lo, mut hi) = (first.center, first.center);
                for p in own {
                    lo = lo.inf(&p.center);
                    hi = hi.sup(&p.center);
                }
                let c = nalgebra::center(&lo, &hi);
                let r = own
                    .iter()
                    .map(|p| (p.center - c).norm() + p.radius)
                    .fold(0.0, f64::max);
                (c, r)
            })
            .collect();
        Ok(Self {
            link_names,
            parts,
            part_start,
            link_balls,
            link_anchors: chain.anchors(),
            world_links,
            self_pairs,
            levers,
            margin,
        })
    }

    /// The parts of link `l`.
    pub fn link_parts(&self, l: usize) -> &[ExactPart] {
        let (a, b) = (
            self.part_start.get(l).copied().unwrap_or(0),
            self.part_start.get(l + 1).copied().unwrap_or(0),
        );
        self.parts.get(a..b).unwrap_or(&[])
    }

    /// Upper bound on how far any point of any link moves between `a` and `b` along the
    /// straight joint-space segment (m).
    pub fn sweep_bound(&self, a: &Joints, b: &Joints) -> f64 {
        (0..6).map(|j| self.levers[j] * (a[j] - b[j]).abs()).sum()
    }
}

/// Per joint, the largest bound on `dist(p, axis)` over the parts (and link origins) it moves.
///
/// For a point `p` of link `L` downstream of joint `k`, walk up from `L`: fixed joints compose
/// exactly; at each revolute joint `j` between, `|p − o_k| ≤ |p − o_j| + |o_j − o_k|` with
/// `|p − o_j|` the (fixed) position of the current point in `j`'s child frame, and the walk
/// continues with `o_j` as the point. The last vector is fixed in joint `k`'s child frame, so
/// only its part perpendicular to `k`'s axis counts.
fn levers(chain: &Chain, parts: &[ExactPart], part_start: &[usize]) -> Joints {
    let mut out = [0.0; 6];
    for (k, &ji) in chain.actuated.iter().enumerate() {
        let axis = chain.joints[ji].axis.unwrap_or_else(Vector3::z_axis);
        for l in 0..chain.links.len() {
            let mut points: Vec<(Point3<f64>, f64)> = parts
                .get(part_start[l]..part_start[l + 1])
                .unwrap_or(&[])
                .iter()
                .map(|p| (p.center, p.radius))
                .collect();
            points.push((Point3::origin(), 0.0));
            for (p0, r) in points {
                let Some(d) = reach_from_joint(chain, ji, &axis, l, p0) else {
                    break;
                };
                out[k] = f64::max(out[k], d + r);
            }
        }
    }
    out
}

/// Bound on the distance of point `p0` of link `l` from joint `ji`'s axis, or `None` when the
/// joint does not move the link.
fn reach_from_joint(
    chain: &Chain,
    ji: usize,
    axis: &nalgebra::Unit<Vector3<f64>>,
    l: usize,
    p0: Point3<f64>,
) -> Option<f64> {
    let mut sum = 0.0;
    let mut link = l;
    let mut p = p0;
    while let Some(j) = chain.joints.iter().position(|j| j.child == link) {
        let joint = &chain.joints[j];
        if j == ji {
            let v = p.coords;
            return Some(sum + (v - axis.into_inner() * axis.dot(&v)).norm());
        }
        if joint.axis.is_some() {
            sum += p.coords.norm();
            p = Point3::origin();
        }
        p = joint.origin * p;
        link = joint.parent;
    }
    None
}

/// A static obstacle as a parry shape.
#[derive(Clone)]
struct ExactObstacle {
    source: Obstacle,
    name: String,
    shape: SharedShape,
    pose: Pose,
    center: Point3<f64>,
    radius: f64,
}

fn obstacle_shape(o: &Obstacle) -> ExactObstacle {
    let turn_y_to_z = UnitQuaternion::from_axis_angle(&Vector3::x_axis(), FRAC_PI_2);
    let (center, radius) = o
        .bounding_ball()
        .unwrap_or((Point3::origin(), f64::INFINITY));
    let (shape, iso) = match o {
        Obstacle::Cuboid { pose, half, .. } => (
            SharedShape::cuboid(half.x as f32, half.y as f32, half.z as f32),
            *pose,
        ),
        Obstacle::Cylinder {
            pose,
            radius,
            half_length,
            ..
        } => (
            SharedShape::cylinder(*half_length as f32, *radius as f32),
            pose * turn_y_to_z,
        ),
        Obstacle::Ball { center, radius, .. } => (
            SharedShape::ball(*radius as f32),
            Isometry3::translation(center.x, center.y, center.z),
        ),
        Obstacle::HalfSpace { normal, offset, .. } => {
            let n = normal.into_inner();
            (
                SharedShape::halfspace(Vector::new(n.x as f32, n.y as f32, n.z as f32)),
                Isometry3::translation(n.x * offset, n.y * offset, n.z * offset),
            )
        }
    };
    ExactObstacle {
        source: o.clone(),
        name: o.name().to_string(),
        shape,
        pose: to_pose(&iso),
        center,
        radius,
    }
}

/// Exact configuration checks of one robot against one world (allocates once).
pub struct ExactChecker<'a> {
    model: &'a ExactModel,
    chain: &'a Chain,
    world: &'a World,
    obstacles: Vec<ExactObstacle>,
    poses: Vec<Isometry3<f64>>,
    anchors: [Isometry3<f64>; 7],
    /// Per link: its ball's centre in the base frame.
    link_centers: Vec<Point3<f64>>,
    resolution: f64,
    /// Number of configurations checked so far.
    pub checks: u64,
}

impl<'a> ExactChecker<'a> {
    /// A checker whose trajectory re-check moves no link point more than `resolution` (m)
    /// between two checks.
    pub fn new(model: &'a ExactModel, chain: &'a Chain, world: &'a World, resolution: f64) -> Self {
        Self {
            model,
            chain,
            world,
            obstacles: world.obstacles.iter().map(obstacle_shape).collect(),
            poses: vec![Isometry3::identity(); chain.links.len()],
            anchors: [Isometry3::identity(); 7],
            link_centers: vec![Point3::origin(); chain.links.len()],
            resolution: resolution.max(1e-4),
            checks: 0,
        }
    }

    /// Places every link that has parts at configuration `q` (parts are placed on demand).
    pub fn place(&mut self, q: &Joints) {
        let link_anchors = &self.model.link_anchors;
        self.chain
            .anchor_poses_into(q, link_anchors, &mut self.anchors);
        for (l, (slot, off)) in link_anchors.iter().enumerate() {
            if self.model.part_start[l] == self.model.part_start[l + 1] {
                continue;
            }
            let pose = self.anchors[(*slot).min(6)] * off;
            self.poses[l] = pose;
            self.link_centers[l] = pose * self.model.link_balls[l].0;
        }
    }

    /// Part `i` of link `l`: its bounding-ball centre in the base frame.
    #[inline]
    fn part_center(&self, l: usize, i: usize) -> Point3<f64> {
        self.poses[l] * self.model.parts[i].center
    }

    /// Part `i` of link `l`: its parry pose.
    #[inline]
    fn part_pose(&self, l: usize, i: usize) -> Pose {
        to_pose(&(self.poses[l] * self.model.parts[i].local))
    }

    fn touch(
        &self,
        p1: &Pose,
        s1: &SharedShape,
        p2: &Pose,
        s2: &SharedShape,
    ) -> Result<bool, PlanError> {
        let unsupported = |_| PlanError::ExactUnsupported {
            what: format!("{:?} against {:?}", s1.shape_type(), s2.shape_type()),
        };
        if self.model.margin > 0.0 {
            let d = query::distance(p1, &**s1, p2, &**s2).map_err(unsupported)?;
            Ok(f64::from(d.distance) <= self.model.margin)
        } else {
            let t = query::intersection_test(p1, &**s1, p2, &**s2).map_err(unsupported)?;
            Ok(t.intersecting)
        }
    }

    /// The link (if any) whose placed parts lie within the margin of `p` (after [`Self::place`]),
    /// among the links checked against the world.
    pub fn link_touching_point(&self, p: &Point3<f64>) -> Option<&'static str> {
        let v = to_vec(p);
        let m = self.model.margin;
        for &l in &self.model.world_links {
            for i in self.model.part_start[l]..self.model.part_start[l + 1] {
                let part = &self.model.parts[i];
                let c = self.part_center(l, i);
                if (p - c).norm() > part.radius + m {
                    continue;
                }
                let pose = self.part_pose(l, i);
                if f64::from(part.shape.distance_to_point(&pose, v, true)) <= m {
                    return Some(self.model.link_names[l]);
                }
            }
        }
        None
    }

    /// What touches what among the placed parts (after [`Self::place`]).
    pub fn placed_contact(&self) -> Result<Option<ExactContact>, PlanError> {
        let m = self.model.margin;
        let field = self.world.field();
        for &l in &self.model.world_links {
            let link = self.model.link_names[l];
            // The link lies in its ball, each part in its own: a ball whose centre is farther
            // than its radius (+ margin) from an obstacle (exact signed distance) or from the
            // cloud (distance-field lower bound) cannot touch it; parry runs on the rest.
            let (lc, lr) = (self.link_centers[l], self.model.link_balls[l].1 + m);
            let near = |o: &ExactObstacle| {
                (lc - o.center).norm() <= lr + o.radius && o.source.distance(&lc) <= lr
            };
            let cloud_near = field.filter(|f| f.distance_bounds(&lc).0 <= lr);
            if cloud_near.is_none() && !self.obstacles.iter().any(near) {
                continue;
            }
            for i in self.model.part_start[l]..self.model.part_start[l + 1] {
                let part = &self.model.parts[i];
                let c = &self.part_center(l, i);
                let pose = &self.part_pose(l, i);
                for o in self.obstacles.iter().filter(|o| near(o)) {
                    if (c - o.center).norm() > part.radius + o.radius + m
                        || o.source.distance(c) > part.radius + m
                    {
                        continue;
                    }
                    if self.touch(pose, &part.shape, &o.pose, &o.shape)? {
                        return Ok(Some(ExactContact {
                            link,
                            other: ExactOther::Obstacle(o.name.clone()),
                        }));
                    }
                }
                if let Some(f) = cloud_near {
                    let reach = part.radius + m;
                    if f.distance_bounds(c).0 > reach {
                        continue;
                    }
                    let shape = &*part.shape;
                    let hit = f.tree().find_within(c, reach, &mut |p| {
                        f64::from(shape.distance_to_point(pose, to_vec(p), true)) <= m
                    });
                    if let Some(p) = hit {
                        return Ok(Some(ExactContact {
                            link,
                            other: ExactOther::CloudPoint([p.x, p.y, p.z]),
                        }));
                    }
                }
            }
        }
        for &(a, b) in &self.model.self_pairs {
            let reach = self.model.link_balls[a].1 + self.model.link_balls[b].1 + m;
            if (self.link_centers[a] - self.link_centers[b]).norm() > reach {
                continue;
            }
            for i in self.model.part_start[a]..self.model.part_start[a + 1] {
                for k in self.model.part_start[b]..self.model.part_start[b + 1] {
                    let (pa, pb) = (&self.model.parts[i], &self.model.parts[k]);
                    let (ca, cb) = (self.part_center(a, i), self.part_center(b, k));
                    if (ca - cb).norm() > pa.radius + pb.radius + m {
                        continue;
                    }
                    let (posa, posb) = (self.part_pose(a, i), self.part_pose(b, k));
                    if self.touch(&posa, &pa.shape, &posb, &pb.shape)? {
                        return Ok(Some(ExactContact {
                            link: self.model.link_names[a],
                            other: ExactOther::Link(self.model.link_names[b]),
                        }));
                    }
                }
            }
        }
        Ok(None)
    }

    /// What touches what at `q` with the exact shapes, or `None` when it is free.
    pub fn contact(&mut self, q: &Joints) -> Result<Option<ExactContact>, PlanError> {
        self.checks += 1;
        self.place(q);
        self.placed_contact()
    }

    /// Number of steps for the straight segment a → b so that no link point moves more than
    /// the resolution per step.
    pub fn steps(&self, a: &Joints, b: &Joints) -> usize {
        ((self.model.sweep_bound(a, b) / self.resolution).ceil() as usize).max(1)
    }
}

/// Re-checks the executed trajectory with the exact shapes: configurations along it such that
/// no point of any link (the TCP included) moves more than the checker's resolution between
/// two checks (`checker::dense_walk`). Consecutive samples lie on one straight checked segment
/// (phase-synchronized rest-to-rest timing), so linear interpolation between them is the
/// executed motion.
pub fn validate_exact(traj: &Trajectory, checker: &mut ExactChecker<'_>) -> Result<(), PlanError> {
    let model = checker.model;
    crate::checker::dense_walk(
        traj.samples(),
        traj.period(),
        checker.resolution,
        |a, b| model.sweep_bound(a, b),
        |q, t| match checker.contact(q)? {
            Some(contact) => Err(PlanError::ExactCollision { t, contact }),
            None => Ok(()),
        },
    )
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::checker::Checker;
    use crate::collision::Sphere;
    use crate::urdf::surface_samples;
    use crate::world::CloudParams;
    use cell_types::{FrameId, PointCloud};
    use proptest::prelude::*;
    use rand::{Rng, SeedableRng};

    const HOME: Joints = [0.0, -1.57, 1.57, -1.57, -1.57, 0.0];

    fn cloud_world(pts: &[Point3<f64>]) -> World {
        let pts = pts.iter().map(|p| p.cast::<f32>()).collect();
        let cloud = PointCloud::new(FrameId::Base, pts, None).unwrap();
        World::from_cloud(&cloud, &CloudParams::default()).unwrap()
    }

    /// The forearm's long cylinder (along its link x): pose in the base frame at `q`, radius.
    fn forearm_cylinder(
        model: &RobotModel,
        q: &Joints,
    ) -> (Isometry3<f64>, f64, f64, &'static str) {
        let l = model.chain.link_index("forearm_link").unwrap();
        let poses = model.chain.link_poses(q);
        let (origin, radius, length) = model.chain.shapes[l]
            .iter()
            .find_map(|s| match s {
                Shape::Cylinder {
                    origin,
                    radius,
                    length,
                } if *length > 0.3 => Some((*origin, *radius, *length)),
                _ => None,
            })
            .unwrap();
        (poses[l] * origin, radius, length, "forearm_link")
    }

    #[test]
    fn point_one_millimetre_inside_or_outside_the_forearm() {
        let model = RobotModel::ur5().unwrap();
        let exact = ExactModel::new(&model, 0.0).unwrap();
        let (cyl, r, _, name) = forearm_cylinder(&model, &HOME);
        // Mid-length, radially along the cylinder frame's x.
        let inside = cyl * Point3::new(r - 0.001, 0.0, 0.0);
        let outside = cyl * Point3::new(r + 0.001, 0.0, 0.0);
        let w_in = cloud_world(&[inside]);
        let mut c = ExactChecker::new(&exact, &model.chain, &w_in, 0.01);
        let hit = c.contact(&HOME).unwrap().unwrap();
        assert_eq!(hit.link, name);
        assert!(
            matches!(hit.other, ExactOther::CloudPoint(p) if (Point3::from(p) - inside).norm() < 1e-6),
            "{hit}"
        );
        // The sphere model agrees on the inside point (it is conservative).
        assert!(Checker::new(&model, &w_in, 0.01).contact(&HOME).is_some());
        let w_out = cloud_world(&[outside]);
        let mut c = ExactChecker::new(&exact, &model.chain, &w_out, 0.01);
        assert_eq!(c.contact(&HOME).unwrap(), None);
        // A 2 mm margin turns the outside point into a contact.
        let exact2 = ExactModel::new(&model, 0.002).unwrap();
        let mut c = ExactChecker::new(&exact2, &model.chain, &w_out, 0.01);
        assert_eq!(c.contact(&HOME).unwrap().map(|h| h.link), Some(name));
        assert!(ExactModel::new(&model, -1.0).is_err());
    }

    #[test]
    fn box_touching_the_forearm_by_a_millimetre() {
        let model = RobotModel::ur5().unwrap();
        let exact = ExactModel::new(&model, 0.0).unwrap();
        let (cyl, r, _, name) = forearm_cylinder(&model, &HOME);
        let half = 0.04;
        for (gap, touches) in [(-0.001, true), (0.001, false)] {
            // A cube aligned with the cylinder frame, its face `gap` off the surface.
            let pose = cyl * Isometry3::translation(r + half + gap, 0.0, 0.0);
            let world = World::empty().with_obstacle(Obstacle::Cuboid {
                name: "crate".into(),
                pose,
                half: Vector3::repeat(half),
            });
            let mut c = ExactChecker::new(&exact, &model.chain, &world, 0.01);
            let hit = c.contact(&HOME).unwrap();
            if touches {
                let hit = hit.unwrap();
                assert_eq!(hit.link, name);
                assert_eq!(hit.other, ExactOther::Obstacle("crate".into()));
                assert!(hit.to_string().contains("obstacle crate"), "{hit}");
            } else {
                assert_eq!(hit, None);
            }
        }
    }

    #[test]
    fn table_half_space_at_the_lowest_link_point() {
        let model = RobotModel::ur5().unwrap();
        let exact = ExactModel::new(&model, 0.0).unwrap();
        let poses = model.chain.link_poses(&HOME);
        let (mut zmin, mut low) = (f64::INFINITY, "");
        for &l in &exact.world_links {
            for s in &model.chain.shapes[l] {
                for p in surface_samples(s, 64) {
                    let z = (poses[l] * p).z;
                    if z < zmin {
                        zmin = z;
                        low = exact.link_names[l];
                    }
                }
            }
        }
        for (dz, touches) in [(0.001, true), (-0.001, false)] {
            let world = World::empty().with_obstacle(Obstacle::HalfSpace {
                name: "table".into(),
                normal: Vector3::z_axis(),
                offset: zmin + dz,
            });
            let mut c = ExactChecker::new(&exact, &model.chain, &world, 0.01);
            let hit = c.contact(&HOME).unwrap();
            assert_eq!(
                hit.clone().map(|h| (h.link, h.other)),
                touches.then(|| (low, ExactOther::Obstacle("table".into()))),
                "table at {} m",
                zmin + dz
            );
        }
    }

    #[test]
    fn folded_elbow_collides_with_itself_and_home_does_not() {
        let model = RobotModel::ur5().unwrap();
        let exact = ExactModel::new(&model, 0.0).unwrap();
        let world = World::empty();
        let mut c = ExactChecker::new(&exact, &model.chain, &world, 0.01);
        assert_eq!(c.contact(&HOME).unwrap(), None);
        assert_eq!(c.contact(&[0.0; 6]).unwrap(), None);
        let folded = [0.0, -1.57, 3.1, -1.57, -1.57, 0.0];
        let hit = c.contact(&folded).unwrap().unwrap();
        assert!(matches!(hit.other, ExactOther::Link(_)), "{hit}");
        assert!(hit.to_string().contains("self-collision"), "{hit}");
    }

    #[test]
    fn lever_bound_covers_real_motion_of_every_part_and_the_tcp() {
        for model in [RobotModel::ur5().unwrap(), crate::mbm::mbm_robot().unwrap()] {
            let exact = ExactModel::new(&model, 0.0).unwrap();
            let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(21);
            for _ in 0..200 {
                let a: Joints = std::array::from_fn(|_| rng.random_range(-3.0..3.0));
                let b: Joints = std::array::from_fn(|j| a[j] + rng.random_range(-0.05..0.05));
                let (pa, pb) = (model.chain.link_poses(&a), model.chain.link_poses(&b));
                let bound = exact.sweep_bound(&a, &b);
                for (l, shapes) in model.chain.shapes.iter().enumerate() {
                    let mut pts = vec![Point3::origin()];
                    for s in shapes {
                        pts.extend(surface_samples(s, 6));
                    }
                    for p in pts {
                        assert!((pa[l] * p - pb[l] * p).norm() <= bound + 1e-12);
                    }
                }
            }
        }
    }

    fn wall() -> Obstacle {
        Obstacle::Cuboid {
            name: "wall".into(),
            pose: Isometry3::translation(0.0, 0.6, 0.4),
            half: Vector3::new(0.02, 0.3, 0.4),
        }
    }

    #[test]
    fn trajectory_through_a_wall_fails_with_the_link_and_time_and_a_free_one_passes() {
        use crate::timing::{time_path, PlannerLimits};
        let model = RobotModel::ur5().unwrap();
        let exact = ExactModel::new(&model, 0.0).unwrap();
        let world = World::empty().with_obstacle(wall());
        let a = [-2.4, -1.57, 1.57, -1.57, -1.57, 0.0];
        let b = [-0.9, -1.57, 1.57, -1.57, -1.57, 0.0];
        let traj = time_path(&[a, b], &PlannerLimits::default()).unwrap();
        let mut c = ExactChecker::new(&exact, &model.chain, &world, 0.01);
        match validate_exact(&traj, &mut c).unwrap_err() {
            PlanError::ExactCollision { t, contact } => {
                assert!(t > 0.0 && t < traj.duration(), "t = {t}");
                assert_eq!(contact.other, ExactOther::Obstacle("wall".into()));
                assert!(model.chain.link_index(contact.link).is_some());
            }
            e => panic!("unexpected {e}"),
        }
        // Without the wall the same motion passes, checked at ≤ 1 cm of link motion.
        let empty = World::empty();
        let mut c = ExactChecker::new(&exact, &model.chain, &empty, 0.01);
        let t0 = std::time::Instant::now();
        validate_exact(&traj, &mut c).unwrap();
        let spent = t0.elapsed().as_secs_f64();
        let sweep = exact.sweep_bound(&a, &b);
        assert!(c.checks as f64 >= sweep / 0.01, "{} checks", c.checks);
        eprintln!(
            "exact re-check: {} samples, {} checks, sweep bound {sweep:.2} m, {:.2} ms",
            traj.samples().len(),
            c.checks,
            spent * 1e3
        );
    }

    /// Points near the robot at `q`: surface samples of its world links pushed up to 3 cm out
    /// or in, so that many fall between the shapes and their sphere cover.
    fn points_near(
        model: &RobotModel,
        exact: &ExactModel,
        q: &Joints,
        seed: u64,
    ) -> Vec<Point3<f64>> {
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(seed);
        let poses = model.chain.link_poses(q);
        let mut out = Vec::new();
        for &l in &exact.world_links {
            for s in &model.chain.shapes[l] {
                let samples = surface_samples(s, 6);
                for _ in 0..8 {
                    let p = samples[rng.random_range(0..samples.len())];
                    let d = Vector3::from_fn(|_, _| rng.random_range(-0.03..0.03));
                    out.push(poses[l] * p + d);
                }
            }
        }
        out
    }

    proptest! {
        #![proptest_config(ProptestConfig {
            cases: 48,
            rng_seed: proptest::test_runner::RngSeed::Fixed(0x5eed),
            failure_persistence: None,
            ..ProptestConfig::default()
        })]

        /// Sphere-free implies exact-free, for points near the links, small boxes and balls
        /// near them, and self-collision, at random configurations.
        #[test]
        fn sphere_model_is_conservative_wrt_exact_shapes(
            q in proptest::array::uniform6(-3.1f64..3.1),
            seed in any::<u64>(),
        ) {
            let model = RobotModel::ur5().unwrap();
            let exact = ExactModel::new(&model, 0.0).unwrap();
            let sm = &model.spheres;
            let mut placed = vec![Sphere::default(); sm.spheres.len()];
            let mut anchors = [Isometry3::identity(); 7];
            model.chain.anchor_poses_into(&q, &sm.link_anchors, &mut anchors);
            sm.place_from_anchors(&anchors, &mut placed);
            let empty = World::empty();
            let mut ec = ExactChecker::new(&exact, &model.chain, &empty, 0.01);
            ec.place(&q);
            let mut exact_hits = 0;
            for p in points_near(&model, &exact, &q, seed) {
                let sphere_hit = sm.world_spheres.iter().any(|&i| {
                    let s = placed[i as usize];
                    (s.center - p).norm() <= s.radius
                });
                let exact_hit = ec.link_touching_point(&p);
                exact_hits += usize::from(exact_hit.is_some());
                prop_assert!(sphere_hit || exact_hit.is_none(), "{p:?} touches {exact_hit:?} but no sphere");
            }
            prop_assert!(exact_hits > 0);
            // Small obstacles near the robot.
            let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(seed ^ 1);
            let near = points_near(&model, &exact, &q, seed ^ 2);
            for (k, c) in near.iter().take(12).enumerate() {
                let rot = UnitQuaternion::from_euler_angles(
                    rng.random_range(-3.0..3.0), rng.random_range(-3.0..3.0), rng.random_range(-3.0..3.0));
                let o = if k % 2 == 0 {
                    Obstacle::Cuboid {
                        name: "b".into(),
                        pose: Isometry3::from_parts(c.coords.into(), rot),
                        half: Vector3::from_fn(|_, _| rng.random_range(0.005..0.03)),
                    }
                } else {
                    Obstacle::Cylinder {
                        name: "c".into(),
                        pose: Isometry3::from_parts(c.coords.into(), rot),
                        radius: rng.random_range(0.005..0.03),
                        half_length: rng.random_range(0.005..0.05),
                    }
                };
                let world = World::empty().with_obstacle(o);
                let sphere_free = Checker::new(&model, &world, 0.01).contact(&q).is_none();
                let exact_hit = ExactChecker::new(&exact, &model.chain, &world, 0.01).contact(&q).unwrap();
                prop_assert!(!sphere_free || exact_hit.is_none(), "{exact_hit:?}");
            }
            // Self-collision.
            let self_free = sm.self_collision(&anchors, &placed).is_none();
            let exact_self = ec.placed_contact().unwrap();
            prop_assert!(!self_free || exact_self.is_none(), "{exact_self:?}");
        }
    }
}
