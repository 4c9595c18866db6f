//! Simulated tasks: a seeded scene, the scripted expert's keyframes from the true object
//! poses, and a success test on the outcome (not on the keyframes).
//!
//! One task so far, `pick_fruit` (the paper's physical "pick fruit", posed in SE(2) as the
//! paper does): a fruit lies on the table; the robot must pick it up and lift it.

use std::f64::consts::PI;

use cell_types::{Base, Keyframe, Tcp, Transform};
use nalgebra::{Isometry3, Translation3, UnitQuaternion, Vector3};
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;

/// How far above the table a lifted object must be for the task to count as done (m).
pub const LIFT_SUCCESS_HEIGHT: f64 = 0.08;

/// Height of the grasp TCP above the fruit's centre (m).
pub const GRASP_HEIGHT_ABOVE_CENTRE: f64 = 0.02;

/// A task the simulated cell can pose and judge.
#[derive(Copy, Clone, Debug, PartialEq, Eq)]
pub enum TaskKind {
    /// Pick a fruit from the table and lift it.
    PickFruit(Fruit),
}

/// The fruit variations of `pick_fruit`.
#[derive(Copy, Clone, Debug, PartialEq, Eq)]
pub enum Fruit {
    /// A small fruit.
    Strawberry,
    /// A large fruit.
    Peach,
    /// A medium fruit.
    Plum,
}

impl Fruit {
    /// Radius of the fruit's sphere (m).
    pub fn radius(self) -> f64 {
        match self {
            Fruit::Strawberry => 0.02,
            Fruit::Plum => 0.025,
            Fruit::Peach => 0.034,
        }
    }

    /// Colour for the cameras.
    pub fn colour(self) -> [u8; 3] {
        match self {
            Fruit::Strawberry => [210, 30, 40],
            Fruit::Plum => [110, 30, 120],
            Fruit::Peach => [250, 170, 90],
        }
    }

    fn name(self) -> &'static str {
        match self {
            Fruit::Strawberry => "strawberry",
            Fruit::Plum => "plum",
            Fruit::Peach => "peach",
        }
    }
}

impl TaskKind {
    /// Parses a task name as the CLI takes it (`pick_fruit`, `pick_fruit/peach`, ...).
    pub fn parse(name: &str) -> Result<Self, String> {
        let (task, variant) = name.split_once('/').unwrap_or((name, "strawberry"));
        match task {
            "pick_fruit" => {
                let fruit = match variant {
                    "strawberry" => Fruit::Strawberry,
                    "peach" => Fruit::Peach,
                    "plum" => Fruit::Plum,
                    other => {
                        return Err(format!(
                            "unknown pick_fruit variation `{other}`: use strawberry, peach or plum"
                        ))
                    }
                };
                Ok(TaskKind::PickFruit(fruit))
            }
            other => Err(format!(
                "unknown task `{other}`: the simulated cell has pick_fruit[/strawberry|/peach|/plum] \
                 (disassemble_pipe, pluck_flower and install_toilet_roll are not built yet)"
            )),
        }
    }

    /// The task's name with its variation.
    pub fn name(&self) -> String {
        match self {
            TaskKind::PickFruit(f) => format!("pick_fruit/{}", f.name()),
        }
    }

    /// The language instruction of this variation.
    pub fn instruction(&self) -> String {
        match self {
            TaskKind::PickFruit(f) => format!("pick up the {}", f.name()),
        }
    }
}

/// A posed instance of a task: where its objects are.
#[derive(Clone, Debug, PartialEq)]
pub struct TaskInstance {
    /// Which task.
    pub kind: TaskKind,
    /// The object's pose in the base frame.
    pub base_from_object: Isometry3<f64>,
    /// Table top height (m).
    pub table_height: f64,
}

impl TaskInstance {
    /// Poses the task with a seeded random transform within the task's ranges: for
    /// `pick_fruit`, SE(2) on the table (x 0.40–0.62 m, y −0.22–0.22 m, any yaw).
    pub fn sample(kind: TaskKind, seed: u64, table_height: f64) -> Self {
        let mut rng = ChaCha8Rng::seed_from_u64(seed);
        match kind {
            TaskKind::PickFruit(fruit) => {
                let x = rng.random_range(0.40..0.62);
                let y = rng.random_range(-0.22..0.22);
                let yaw = rng.random_range(-PI..PI);
                Self {
                    kind,
                    base_from_object: Isometry3::from_parts(
                        Translation3::new(x, y, table_height + fruit.radius()),
                        UnitQuaternion::from_axis_angle(&Vector3::z_axis(), yaw),
                    ),
                    table_height,
                }
            }
        }
    }

    /// The scripted expert: keyframes from the true object pose. Pre-grasp above the object
    /// (open), grasp at its centre (then close), lift.
    pub fn expert_keyframes(&self) -> Vec<Keyframe> {
        match self.kind {
            TaskKind::PickFruit(_) => {
                let c = self.base_from_object.translation.vector;
                let yaw = self.base_from_object.rotation.euler_angles().2;
                // Top-down grasp: TCP z along −z of the base, fingers closing across the
                // fruit's yaw (a sphere has no preferred yaw; keep it for the other tasks).
                let down = UnitQuaternion::from_axis_angle(&Vector3::z_axis(), yaw)
                    * UnitQuaternion::from_axis_angle(&Vector3::x_axis(), PI);
                let at = |dz: f64| -> Transform<Base, Tcp> {
                    Transform::from_parts(Vector3::new(c.x, c.y, c.z + dz), down)
                };
                vec![
                    Keyframe {
                        base_from_tcp: at(0.12),
                        gripper_open: true,
                        ignore_collisions: false,
                    },
                    // The TCP 2 cm above the centre: the finger pads reach 15 mm past the TCP
                    // (so they close just above the equator), and the planner's spheres
                    // around the fingertips must clear the table under small fruit.
                    Keyframe {
                        base_from_tcp: at(GRASP_HEIGHT_ABOVE_CENTRE),
                        gripper_open: false,
                        ignore_collisions: false,
                    },
                    Keyframe {
                        base_from_tcp: at(0.18),
                        gripper_open: false,
                        ignore_collisions: false,
                    },
                ]
            }
        }
    }

    /// The success test on the world's state: the object is held and lifted.
    pub fn success(&self, base_from_object_now: &Isometry3<f64>, held: bool) -> bool {
        match self.kind {
            TaskKind::PickFruit(f) => {
                let lifted =
                    base_from_object_now.translation.vector.z - (self.table_height + f.radius());
                held && lifted >= LIFT_SUCCESS_HEIGHT
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn task_names_parse_and_bad_names_are_refused() {
        assert_eq!(
            TaskKind::parse("pick_fruit/peach"),
            Ok(TaskKind::PickFruit(Fruit::Peach))
        );
        assert_eq!(
            TaskKind::parse("pick_fruit"),
            Ok(TaskKind::PickFruit(Fruit::Strawberry))
        );
        assert!(TaskKind::parse("pick_fruit/apple")
            .unwrap_err()
            .contains("strawberry"));
        assert!(TaskKind::parse("juggle")
            .unwrap_err()
            .contains("unknown task"));
    }

    #[test]
    fn sampling_is_seeded_and_on_the_table() {
        let k = TaskKind::PickFruit(Fruit::Plum);
        let a = TaskInstance::sample(k, 4, -0.06);
        let b = TaskInstance::sample(k, 4, -0.06);
        let c = TaskInstance::sample(k, 5, -0.06);
        assert_eq!(a, b);
        assert_ne!(a, c);
        let z = a.base_from_object.translation.vector.z;
        assert!((z - (-0.06 + 0.025)).abs() < 1e-12);
    }

    #[test]
    fn success_needs_hold_and_lift() {
        let inst = TaskInstance::sample(TaskKind::PickFruit(Fruit::Peach), 1, -0.06);
        let mut lifted = inst.base_from_object;
        lifted.translation.vector.z += 0.1;
        assert!(inst.success(&lifted, true));
        assert!(!inst.success(&lifted, false));
        assert!(!inst.success(&inst.base_from_object, true));
    }
}
