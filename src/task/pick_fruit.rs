//! Pick fruit (the paper's physical "pick fruit", posed in SE(2) as the paper does): a fruit
//! lies on the table; the robot must pick it up and lift it. Variations: strawberry, peach,
//! plum.

use nalgebra::{Isometry3, Translation3, UnitQuaternion, Vector3};
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;

use cell_types::Keyframe;
use hil_sim::scene::Primitive;

use super::{grasp_rotation, keyframe, Body, BodyPart, GraspSite, TaskInstance, TaskKind};

/// How far above the table a lifted object must be for the task to count as done (m).
pub const LIFT_SUCCESS_HEIGHT: f64 = 0.08;

/// Height of the grasp TCP above the fruit's centre (m).
pub const GRASP_HEIGHT_ABOVE_CENTRE: f64 = 0.02;

/// The fruit variations of `pick_fruit`.
#[derive(Copy, Clone, Debug, PartialEq, Eq, Hash)]
pub enum Fruit {
    /// A small fruit.
    Strawberry,
    /// A large fruit.
    Peach,
    /// A medium fruit.
    Plum,
}

impl Fruit {
    /// The variations in order.
    pub const ALL: [Fruit; 3] = [Fruit::Strawberry, Fruit::Peach, Fruit::Plum];

    /// Radius of the fruit's sphere (m).
    pub fn radius(self) -> f64 {
        match self {
            Fruit::Strawberry => 0.02,
            Fruit::Plum => 0.025,
            Fruit::Peach => 0.034,
        }
    }

    /// Height of the grasp TCP above the fruit's centre (m): [`GRASP_HEIGHT_ABOVE_CENTRE`],
    /// or higher for a large fruit, whose top must stay 4 mm clear of the palm (1 cm behind
    /// the TCP) with the depth noise on it.
    pub fn grasp_height(self) -> f64 {
        (self.radius() - 0.004).max(GRASP_HEIGHT_ABOVE_CENTRE)
    }

    /// Colour for the cameras.
    pub fn colour(self) -> [u8; 3] {
        match self {
            Fruit::Strawberry => [210, 30, 40],
            Fruit::Plum => [110, 30, 120],
            Fruit::Peach => [250, 170, 90],
        }
    }

    /// The variation's name.
    pub fn name(self) -> &'static str {
        match self {
            Fruit::Strawberry => "strawberry",
            Fruit::Plum => "plum",
            Fruit::Peach => "peach",
        }
    }
}

/// Poses the fruit: SE(2) on the table (x 0.40–0.62 m, y −0.22–0.22 m, any yaw).
pub(crate) fn sample(fruit: Fruit, seed: u64, table_height: f64) -> TaskInstance {
    let mut rng = ChaCha8Rng::seed_from_u64(seed);
    let x = rng.random_range(0.40..0.62);
    let y = rng.random_range(-0.22..0.22);
    let yaw = rng.random_range(-super::HALF_TURN..super::HALF_TURN);
    let pose = Isometry3::from_parts(
        Translation3::new(x, y, table_height + fruit.radius()),
        UnitQuaternion::from_axis_angle(&Vector3::z_axis(), yaw),
    );
    TaskInstance {
        kind: TaskKind::PickFruit(fruit),
        seed,
        bodies: vec![Body {
            name: fruit.name().to_string(),
            base_from_body: pose,
            parts: vec![BodyPart {
                shape: Primitive::Sphere {
                    radius: fruit.radius(),
                },
                body_from_part: Isometry3::identity(),
                colour: fruit.colour(),
            }],
            grasp: Some(GraspSite {
                point: Vector3::new(0.0, 0.0, fruit.grasp_height()),
                width: 2.0 * fruit.radius(),
            }),
        }],
        base_from_fixture: pose,
        table_height,
    }
}

/// Pre-grasp above the fruit (open), grasp near its centre (then close), lift.
pub(crate) fn expert(task: &TaskInstance, fruit: Fruit) -> Vec<Keyframe> {
    let pose = task.base_from_object();
    let c = pose.translation.vector;
    // Top-down grasp, fingers closing across the fruit's yaw (a sphere has no preferred
    // yaw; the nearer of the two finger orientations to the home pose's is taken).
    let down = grasp_rotation(-Vector3::z(), pose.rotation * Vector3::x());
    let at = |dz: f64| c + Vector3::new(0.0, 0.0, dz);
    vec![
        keyframe(at(0.12), down, true),
        // The TCP 2 cm above the centre (more for a peach): the finger pads reach 15 mm past the TCP (so they
        // close just above the equator), and the planner's spheres around the fingertips
        // must clear the table under small fruit.
        keyframe(at(fruit.grasp_height()), down, false),
        keyframe(at(0.18), down, false),
    ]
}

/// Held and lifted at least [`LIFT_SUCCESS_HEIGHT`] above where it lay.
pub(crate) fn success(
    task: &TaskInstance,
    fruit: Fruit,
    poses: &[Isometry3<f64>],
    held: Option<usize>,
) -> bool {
    let lifted = poses[0].translation.vector.z - (task.table_height + fruit.radius());
    held == Some(0) && lifted >= LIFT_SUCCESS_HEIGHT
}

/// A released fruit drops onto the table below.
pub(crate) fn released(task: &TaskInstance, fruit: Fruit, pose: &Isometry3<f64>) -> Isometry3<f64> {
    let mut p = *pose;
    p.translation.vector.z = task.table_height + fruit.radius();
    p
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn sampling_is_on_the_table() {
        let a = TaskInstance::sample(TaskKind::PickFruit(Fruit::Plum), 4, -0.06);
        let z = a.base_from_object().translation.vector.z;
        assert!((z - (-0.06 + 0.025)).abs() < 1e-12);
    }

    #[test]
    fn success_needs_hold_and_lift() {
        let inst = TaskInstance::sample(TaskKind::PickFruit(Fruit::Peach), 1, -0.06);
        let mut lifted = inst.base_from_object();
        lifted.translation.vector.z += 0.1;
        assert!(inst.success(&[lifted], Some(0)));
        assert!(!inst.success(&[lifted], None));
        assert!(!inst.success(&[inst.base_from_object()], Some(0)));
    }
}
