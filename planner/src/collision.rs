//! Sphere collision model of the robot (issue 3 item 1): spheres generated from each link's
//! collision primitives (cylinders and boxes are covered by a row of spheres whose union
//! provably contains them; URDF spheres are taken as they are), grouped into rigid bodies
//! (links joined by fixed joints), with self-collision checked between bodies that are at
//! least three joints apart in the chain (nearer pairs touch by construction at the joints:
//! the URDF-adjacency allowed-collision rule, widened by one because the UR wrists overlap).

use crate::error::{Contact, PlanError};
use crate::urdf::{AnchorFk, Chain, Shape};
use nalgebra::{Isometry3, Matrix3, Point3, Vector3};

/// One sphere of the model, fixed to a link.
#[derive(Copy, Clone, Debug, PartialEq)]
pub struct LinkSphere {
    /// Link index in the chain.
    pub link: usize,
    /// Rigid body index (links joined by fixed joints share one).
    pub body: usize,
    /// Centre in the link frame.
    pub center: Point3<f64>,
    /// Radius (m).
    pub radius: f64,
}

/// A sphere placed in the base frame.
#[derive(Copy, Clone, Debug, Default, PartialEq)]
pub struct Sphere {
    /// Centre (m).
    pub center: Point3<f64>,
    /// Radius (m).
    pub radius: f64,
}

/// The spheres of a robot and the pairs checked for self-collision.
#[derive(Clone, Debug)]
pub struct SphereModel {
    /// All spheres.
    pub spheres: Vec<LinkSphere>,
    /// Link names (for error messages).
    pub link_names: Vec<&'static str>,
    /// Sphere index pairs checked for self-collision.
    pub self_pairs: Vec<(u16, u16)>,
    /// Spheres checked against the world (not those of the root body, which stands on the
    /// table by design).
    pub world_spheres: Vec<u16>,
    /// Per link: anchor slot and fixed pose in it (see [`Chain::anchors`]).
    pub link_anchors: Vec<(usize, Isometry3<f64>)>,
    /// Per sphere: anchor slot and centre in the anchor frame.
    pub anchored: Vec<(usize, Point3<f64>)>,
    /// The anchor poses' forward kinematics with the constant transforms multiplied out.
    pub fk: AnchorFk,
    /// Self-collision grouped by pairs of rigid bodies: each group's two body balls (anchor
    /// slot, centre in the anchor frame, radius covering the body's spheres) and its range in
    /// `self_pairs`. Two balls apart rule out every sphere pair of the group with one test.
    pub body_pairs: Vec<BodyPair>,
    /// The world spheres grouped by rigid body, distal bodies first, each group with its body
    /// ball: a ball clear of every obstacle and of the cloud clears all its spheres at once.
    pub world_bodies: Vec<(BodyBall, Vec<u16>)>,
}

/// A ball around all spheres of one rigid body, in its anchor frame.
#[derive(Copy, Clone, Debug, PartialEq)]
pub struct BodyBall {
    /// Anchor slot (see [`Chain::anchors`]).
    pub slot: usize,
    /// Centre in the anchor frame.
    pub center: Point3<f64>,
    /// Radius (m), covering every sphere of the body.
    pub radius: f64,
}

/// The sphere pairs between two rigid bodies checked for self-collision: every sphere of the
/// first against every sphere of the second, the second's spheres in clusters of a few
/// neighbours with a ball each, so that a sphere of the first body meets only the clusters
/// near it.
#[derive(Clone, Debug, PartialEq)]
pub struct BodyPair {
    /// Ball of the first body.
    pub a: BodyBall,
    /// Ball of the second body.
    pub b: BodyBall,
    /// Spheres of the first body.
    pub a_spheres: Vec<u16>,
    /// Spheres of the second body in clusters, each with a ball in the second body's anchor
    /// frame covering its spheres.
    pub b_clusters: Vec<(BodyBall, Vec<u16>)>,
}

/// Largest cluster of [`BodyPair::b_clusters`].
const CLUSTER: usize = 4;

/// Spheres covering a shape, in the link frame. `inflate` is the ratio of sphere radius to
/// the shape's cross-section radius (larger: fewer, fatter spheres).
pub fn cover_shape(shape: &Shape, inflate: f64) -> Vec<(Point3<f64>, f64)> {
    let along = |origin: &Isometry3<f64>, axis: Vector3<f64>, len: f64, r: f64| {
        let big = r * (1.0 + inflate);
        // Neighbouring centres at most 2·sqrt(R² − r²) apart keep the whole side covered.
        let step = 2.0 * (big * big - r * r).sqrt();
        let n = ((len / step).ceil() as usize).max(1);
        (0..=n)
            .map(|k| {
                let t = -len / 2.0 + len * k as f64 / n as f64;
                (origin * Point3::from(axis * t), big)
            })
            .collect::<Vec<_>>()
    };
    match shape {
        Shape::Sphere { origin, radius } => vec![(origin * Point3::origin(), *radius)],
        // The end spheres (radius above the shape's) also cover a capsule's half-ball caps.
        Shape::Cylinder {
            origin,
            radius,
            length,
        }
        | Shape::Capsule {
            origin,
            radius,
            length,
        } => along(origin, Vector3::z(), *length, *radius),
        Shape::Cuboid { origin, size } => {
            // Along the longest edge; the cross-section's half diagonal is the radius to cover.
            let (mut k, mut longest) = (0, size[0]);
            for (i, s) in size.iter().enumerate() {
                if *s > longest {
                    longest = *s;
                    k = i;
                }
            }
            let mut axis = Vector3::zeros();
            axis[k] = 1.0;
            let r = size
                .iter()
                .enumerate()
                .filter(|(i, _)| *i != k)
                .map(|(_, s)| (s / 2.0) * (s / 2.0))
                .sum::<f64>()
                .sqrt();
            along(origin, axis, longest, r)
        }
    }
}

/// Self-collision is checked between rigid bodies at least this many moving joints apart;
/// nearer pairs (URDF neighbours, and the overlapping UR wrists) are allowed to touch.
pub const SELF_BODY_GAP: usize = 3;

/// The rigid body of every link: 0 for the root and the links fixed to it, `k + 1` for the
/// links moved by the `k`-th revolute joint (in chain order) and those fixed to them.
pub fn link_bodies(chain: &Chain) -> Vec<usize> {
    let n = chain.links.len();
    // Follow fixed joints to the nearest link with a moving parent joint.
    let mut body_of = vec![0usize; n];
    let mut bodies = 1usize;
    for j in &chain.joints {
        let pb = body_of.get(j.parent).copied().unwrap_or(0);
        if j.axis.is_some() {
            body_of[j.child] = bodies;
            bodies += 1;
        } else {
            body_of[j.child] = pb;
        }
    }
    body_of
}

/// The spheres of rigid body `body`, by index.
fn body_members(spheres: &[LinkSphere], body: usize) -> Vec<u16> {
    (0..spheres.len())
        .filter(|&i| spheres[i].body == body)
        .map(|i| i as u16)
        .collect()
}

/// A ball around the spheres `idx`, in the anchor frame of the first (infinite when they sit
/// on different anchors, which a serial chain's fixed-joint groups never do).
fn ball_around(spheres: &[LinkSphere], anchored: &[(usize, Point3<f64>)], idx: &[u16]) -> BodyBall {
    let slot = idx.first().map_or(0, |&i| anchored[i as usize].0);
    if idx.iter().any(|&i| anchored[i as usize].0 != slot) {
        return BodyBall {
            slot,
            center: Point3::origin(),
            radius: f64::INFINITY,
        };
    }
    let n = idx.len().max(1) as f64;
    let center = Point3::from(
        idx.iter()
            .map(|&i| anchored[i as usize].1.coords)
            .sum::<Vector3<f64>>()
            / n,
    );
    let radius = idx
        .iter()
        .map(|&i| (anchored[i as usize].1 - center).norm() + spheres[i as usize].radius)
        .fold(0.0, f64::max);
    BodyBall {
        slot,
        center,
        radius,
    }
}

/// Groups the self pairs by body pair (every pair between two bodies is in the list, since
/// the rule is per body), with a ball around each body and clusters of the second body's
/// spheres (neighbours along the body's longest extent). A body whose spheres sit on
/// different anchors (not the case for a serial chain's fixed-joint groups) gets infinite
/// balls, so its pairs are always checked.
fn body_pairs(
    spheres: &[LinkSphere],
    anchored: &[(usize, Point3<f64>)],
    self_pairs: &[(u16, u16)],
) -> Vec<BodyPair> {
    let mut keys: Vec<(usize, usize)> = self_pairs
        .iter()
        .map(|&(a, b)| (spheres[a as usize].body, spheres[b as usize].body))
        .collect();
    keys.dedup();
    keys.into_iter()
        .map(|(ba, bb)| {
            let a_spheres = body_members(spheres, ba);
            let mut b_spheres = body_members(spheres, bb);
            let b = ball_around(spheres, anchored, &b_spheres);
            // Order along the direction from the centre to the farthest sphere, then chunk.
            let far = b_spheres
                .iter()
                .map(|&i| anchored[i as usize].1 - b.center)
                .max_by(|x, y| x.norm().total_cmp(&y.norm()))
                .unwrap_or_else(Vector3::zeros);
            b_spheres.sort_by(|&x, &y| {
                let px = (anchored[x as usize].1 - b.center).dot(&far);
                let py = (anchored[y as usize].1 - b.center).dot(&far);
                px.total_cmp(&py)
            });
            let b_clusters = b_spheres
                .chunks(CLUSTER)
                .map(|c| (ball_around(spheres, anchored, c), c.to_vec()))
                .collect();
            BodyPair {
                a: ball_around(spheres, anchored, &a_spheres),
                b,
                a_spheres,
                b_clusters,
            }
        })
        .collect()
}

fn leak(s: &str) -> &'static str {
    // Link names live as long as the model; models are built a handful of times per process.
    Box::leak(s.to_owned().into_boxed_str())
}

impl SphereModel {
    /// Builds the sphere model of a chain: covers each primitive, groups links into bodies,
    /// and lists the sphere pairs to check for self-collision.
    pub fn from_chain(chain: &Chain, inflate: f64) -> Result<Self, PlanError> {
        let body_of = link_bodies(chain);
        let mut spheres = Vec::new();
        for (link, shapes) in chain.shapes.iter().enumerate() {
            for s in shapes {
                for (c, r) in cover_shape(s, inflate) {
                    spheres.push(LinkSphere {
                        link,
                        body: body_of[link],
                        center: c,
                        radius: r,
                    });
                }
            }
        }
        if spheres.len() > u16::MAX as usize {
            return Err(PlanError::UrdfStructure {
                what: format!("{} collision spheres; at most 65535", spheres.len()),
            });
        }
        // Body depth along the chain (bodies are created in order of moving joints).
        let body_depth = |b: usize| b;
        let mut self_pairs = Vec::new();
        for (i, a) in spheres.iter().enumerate() {
            for (k, b) in spheres.iter().enumerate().skip(i + 1) {
                if body_depth(a.body).abs_diff(body_depth(b.body)) >= SELF_BODY_GAP {
                    self_pairs.push((i as u16, k as u16));
                }
            }
        }
        // Group the pairs by body pair (stable: pairs keep their order within a group).
        self_pairs.sort_by_key(|&(a, b)| (spheres[a as usize].body, spheres[b as usize].body));
        let link_anchors = chain.anchors();
        let anchored: Vec<(usize, Point3<f64>)> = spheres
            .iter()
            .map(|s| {
                let (slot, off) = link_anchors[s.link];
                (slot, off * s.center)
            })
            .collect();
        let body_pairs = body_pairs(&spheres, &anchored, &self_pairs);
        let world_spheres: Vec<u16> = (0..spheres.len())
            .filter(|&i| spheres[i].body != 0)
            .map(|i| i as u16)
            .collect();
        let bodies = spheres.iter().map(|s| s.body + 1).max().unwrap_or(0);
        let world_bodies = (1..bodies)
            .rev()
            .map(|b| {
                let members: Vec<u16> = world_spheres
                    .iter()
                    .copied()
                    .filter(|&i| spheres[i as usize].body == b)
                    .collect();
                let ball = ball_around(&spheres, &anchored, &body_members(&spheres, b));
                (ball, members)
            })
            .filter(|(_, m)| !m.is_empty())
            .collect();
        Ok(Self {
            fk: chain.anchor_fk(&link_anchors),
            body_pairs,
            world_bodies,
            link_anchors,
            anchored,
            spheres,
            link_names: chain.links.iter().map(|l| leak(l)).collect(),
            self_pairs,
            world_spheres,
        })
    }

    /// Places every sphere in the base frame given the link poses (no allocation).
    pub fn place_into(&self, link_poses: &[Isometry3<f64>], out: &mut [Sphere]) {
        for (s, o) in self.spheres.iter().zip(out.iter_mut()) {
            let pose = link_poses
                .get(s.link)
                .copied()
                .unwrap_or_else(Isometry3::identity);
            *o = Sphere {
                center: pose * s.center,
                radius: s.radius,
            };
        }
    }

    /// Places every sphere given the 7 anchor poses of [`Chain::anchor_poses_into`]; same
    /// result as [`Self::place_into`] with far fewer transform products.
    #[inline]
    pub fn place_from_anchors(&self, anchors: &[Isometry3<f64>; 7], out: &mut [Sphere]) {
        // Seven quaternion-to-matrix conversions, then a matrix-vector product per sphere:
        // about half the arithmetic of rotating every centre by its quaternion.
        let frames: [(Matrix3<f64>, Vector3<f64>); 7] = std::array::from_fn(|i| {
            (
                anchors[i].rotation.to_rotation_matrix().into_inner(),
                anchors[i].translation.vector,
            )
        });
        for ((slot, c), (s, o)) in self
            .anchored
            .iter()
            .zip(self.spheres.iter().zip(out.iter_mut()))
        {
            let (r, t) = &frames[(*slot).min(6)];
            *o = Sphere {
                center: Point3::from(r * c.coords + t),
                radius: s.radius,
            };
        }
    }

    /// The first self-collision among placed spheres, if any. `anchors` are the poses the
    /// spheres were placed with: a group of pairs runs only when its two body balls overlap.
    pub fn self_collision(
        &self,
        anchors: &[Isometry3<f64>; 7],
        placed: &[Sphere],
    ) -> Option<Contact> {
        for g in &self.body_pairs {
            let ca = anchors[g.a.slot.min(6)] * g.a.center;
            let cb = anchors[g.b.slot.min(6)] * g.b.center;
            let rr = g.a.radius + g.b.radius;
            if (ca - cb).norm_squared() >= rr * rr {
                continue;
            }
            // Each sphere of the first body against the clusters of the second near it.
            let mut clusters = [(Point3::origin(), 0.0); 16];
            let nc = g.b_clusters.len().min(clusters.len());
            for (slot, (ball, _)) in clusters.iter_mut().zip(&g.b_clusters) {
                *slot = (anchors[ball.slot.min(6)] * ball.center, ball.radius);
            }
            for &a in &g.a_spheres {
                let sa = placed[a as usize];
                let reach = sa.radius + g.b.radius;
                if (sa.center - cb).norm_squared() >= reach * reach {
                    continue;
                }
                for (k, (_, members)) in g.b_clusters.iter().enumerate() {
                    if k < nc {
                        let (cc, cr) = clusters[k];
                        let reach = sa.radius + cr;
                        if (sa.center - cc).norm_squared() >= reach * reach {
                            continue;
                        }
                    }
                    for &b in members {
                        let sb = placed[b as usize];
                        let rr = sa.radius + sb.radius;
                        if (sa.center - sb.center).norm_squared() < rr * rr {
                            return Some(Contact {
                                link: self.link_names[self.spheres[a as usize].link],
                                other: self.link_names[self.spheres[b as usize].link].to_string(),
                            });
                        }
                    }
                }
            }
        }
        None
    }

    /// Name of the link a sphere belongs to.
    pub fn link_of(&self, sphere: usize) -> &'static str {
        self.spheres
            .get(sphere)
            .map(|s| self.link_names[s.link])
            .unwrap_or("unknown")
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::model::RobotModel;
    use crate::urdf::surface_samples;

    #[test]
    fn spheres_cover_every_collision_primitive() {
        let model = RobotModel::ur5().unwrap();
        let sm = &model.spheres;
        assert!(
            (30..=60).contains(&sm.spheres.len()),
            "{} spheres",
            sm.spheres.len()
        );
        for (link, shapes) in model.chain.shapes.iter().enumerate() {
            for shape in shapes {
                for p in surface_samples(shape, 24) {
                    let covered = sm
                        .spheres
                        .iter()
                        .filter(|s| s.link == link)
                        .any(|s| (s.center - p).norm() <= s.radius + 1e-12);
                    assert!(
                        covered,
                        "link {} point {p:?} not covered",
                        model.chain.links[link]
                    );
                }
            }
        }
    }

    #[test]
    fn anchored_placement_equals_link_chain_placement() {
        use rand::{Rng, SeedableRng};
        for model in [RobotModel::ur5().unwrap(), crate::mbm::mbm_robot().unwrap()] {
            let n = model.spheres.spheres.len();
            let (mut a, mut b) = (vec![Sphere::default(); n], vec![Sphere::default(); n]);
            let mut anchors = [Isometry3::identity(); 7];
            let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(4);
            for _ in 0..200 {
                let q: [f64; 6] = std::array::from_fn(|_| rng.random_range(-3.0..3.0));
                model
                    .spheres
                    .place_into(&model.chain.link_poses(&q), &mut a);
                model
                    .chain
                    .anchor_poses_into(&q, &model.spheres.link_anchors, &mut anchors);
                let mut fast = [Isometry3::identity(); 7];
                model.spheres.fk.poses_into(&q, &mut fast);
                for (x, y) in anchors.iter().zip(&fast) {
                    assert!((x.translation.vector - y.translation.vector).norm() < 1e-12);
                    assert!(x.rotation.angle_to(&y.rotation) < 1e-9);
                }
                model.spheres.place_from_anchors(&anchors, &mut b);
                for (x, y) in a.iter().zip(&b) {
                    assert!((x.center - y.center).norm() < 1e-12);
                }
            }
        }
    }

    #[test]
    fn home_and_zero_are_free_of_self_collision_but_folded_wrist_is_not() {
        let model = RobotModel::ur5().unwrap();
        let mut placed = vec![Sphere::default(); model.spheres.spheres.len()];
        let mut anchors = [Isometry3::identity(); 7];
        let mut self_contact = |q: &[f64; 6]| {
            model
                .chain
                .anchor_poses_into(q, &model.spheres.link_anchors, &mut anchors);
            model.spheres.place_from_anchors(&anchors, &mut placed);
            model.spheres.self_collision(&anchors, &placed)
        };
        for q in [[0.0; 6], [0.0, -1.57, 1.57, -1.57, -1.57, 0.0]] {
            assert_eq!(self_contact(&q), None, "{q:?}");
        }
        // Elbow folded back fully: the wrist and gripper come down onto the shoulder/upper arm.
        assert!(self_contact(&[0.0, -1.57, 3.1, -1.57, -1.57, 0.0]).is_some());
    }

    #[test]
    fn body_ball_culling_finds_exactly_the_self_collisions_of_all_pairs() {
        use rand::{Rng, SeedableRng};
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(11);
        for model in [RobotModel::ur5().unwrap(), crate::mbm::mbm_robot().unwrap()] {
            let sm = &model.spheres;
            assert!(sm.body_pairs.len() > 1);
            // The groups hold exactly the self pairs.
            let mut grouped: Vec<(u16, u16)> = sm
                .body_pairs
                .iter()
                .flat_map(|g| {
                    g.a_spheres.iter().flat_map(move |&a| {
                        g.b_clusters
                            .iter()
                            .flat_map(move |(_, m)| m.iter().map(move |&b| (a, b)))
                    })
                })
                .collect();
            grouped.sort_unstable();
            let mut all = sm.self_pairs.clone();
            all.sort_unstable();
            assert_eq!(grouped, all);
            let mut placed = vec![Sphere::default(); sm.spheres.len()];
            let mut anchors = [Isometry3::identity(); 7];
            let mut hits = 0;
            for _ in 0..3000 {
                let q: [f64; 6] = std::array::from_fn(|_| rng.random_range(-3.1..3.1));
                model
                    .chain
                    .anchor_poses_into(&q, &sm.link_anchors, &mut anchors);
                sm.place_from_anchors(&anchors, &mut placed);
                let brute = sm.self_pairs.iter().any(|&(a, b)| {
                    let (sa, sb) = (placed[a as usize], placed[b as usize]);
                    (sa.center - sb.center).norm() < sa.radius + sb.radius
                });
                assert_eq!(
                    sm.self_collision(&anchors, &placed).is_some(),
                    brute,
                    "{q:?}"
                );
                hits += usize::from(brute);
            }
            // Both outcomes occur, so the comparison means something.
            assert!(hits > 50 && hits < 2950, "{hits} self-collisions of 3000");
        }
    }
}
