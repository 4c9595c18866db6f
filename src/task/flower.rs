//! Pluck flower: three flowers stick out of a foam block on a pedestal posed by a seeded
//! SE(3) transform (x 0.55–0.65 m, y −0.12–0.12 m, facing the robot ±30°, tilt ≤ 10°, lift
//! ≤ 3 cm), at three heights and staggered sideways. The robot grasps the named flower's
//! head, pulls it out of the block along the stem and lifts it. Variations: the top,
//! middle or bottom flower.

use std::f64::consts::{FRAC_PI_6, PI};

use cell_types::Keyframe;
use hil_sim::scene::Primitive;
use nalgebra::{Isometry3, Translation3, UnitQuaternion, Vector3};
use rand::SeedableRng;
use rand_chacha::ChaCha8Rng;

use super::{
    grasp_rotation, keyframe, keyframe_through, lying_on_table, moved, moved_from_place, pedestal,
    sample_fixture, Body, BodyPart, GraspSite, TaskInstance, TaskKind,
};

/// Radius of a flower's head (m).
pub const HEAD_RADIUS: f64 = 0.02;
/// Radius of a stem (m).
pub const STEM_RADIUS: f64 = 0.005;
/// Stem length from the root in the block to the head's centre (m).
const STEM_LENGTH: f64 = 0.18;
/// Where the expert grasps the flower, from the root (m): at its head, so the pulled
/// flower trails behind the gripper and the gripper body stays clear of the block.
const GRASP_FROM_ROOT: f64 = STEM_LENGTH;
/// The block's front face (fixture x, m).
const FACE_X: f64 = 0.02;
/// How far the expert pulls the flower along its stem (m).
const PULL: f64 = 0.08;
/// How far the expert lifts a pulled flower (m).
const LIFT: f64 = 0.08;
/// A flower counts as plucked this far from where it was planted (m).
pub const PLUCKED_DISTANCE: f64 = 0.10;
/// A flower counts as in place this close to where it was planted (m).
const IN_PLACE_DISTANCE: f64 = 0.01;

/// The variations of `pluck_flower`.
#[derive(Copy, Clone, Debug, PartialEq, Eq, Hash)]
pub enum FlowerLevel {
    /// The highest flower.
    Top,
    /// The middle flower.
    Middle,
    /// The lowest flower.
    Bottom,
}

impl FlowerLevel {
    /// The variations in order.
    pub const ALL: [FlowerLevel; 3] = [FlowerLevel::Top, FlowerLevel::Middle, FlowerLevel::Bottom];

    /// The variation's name.
    pub fn name(self) -> &'static str {
        match self {
            FlowerLevel::Top => "top",
            FlowerLevel::Middle => "middle",
            FlowerLevel::Bottom => "bottom",
        }
    }

    /// The flower's body index (1 bottom, 2 middle, 3 top).
    fn body(self) -> usize {
        match self {
            FlowerLevel::Bottom => 1,
            FlowerLevel::Middle => 2,
            FlowerLevel::Top => 3,
        }
    }
}

/// Poses the block (body 0) and the flowers (1 bottom, 2 middle, 3 top).
pub(crate) fn sample(level: FlowerLevel, seed: u64, table_height: f64) -> TaskInstance {
    let mut rng = ChaCha8Rng::seed_from_u64(seed);
    let fixture = sample_fixture(
        &mut rng,
        (0.55, 0.65),
        (-0.12, 0.12),
        (-FRAC_PI_6, FRAC_PI_6),
        10.0,
        table_height,
    );
    let block = Body {
        name: "foam block".into(),
        base_from_body: fixture,
        parts: vec![
            pedestal(0.04, 0.17, 0.045, [120, 100, 80]),
            BodyPart {
                shape: Primitive::Box {
                    half_extents: [0.025, 0.16, 0.085],
                },
                body_from_part: Isometry3::translation(FACE_X + 0.025, 0.0, 0.085),
                colour: [70, 140, 70],
            },
        ],
        grasp: None,
    };
    // A flower's frame: origin at the stem's root (1 cm inside the block), x along the stem
    // out of the block (the fixture's −x).
    let flower = |name: &str, y: f64, z: f64, colour: [u8; 3]| Body {
        name: name.into(),
        base_from_body: fixture
            * Isometry3::from_parts(
                Translation3::new(FACE_X + 0.01, y, z),
                UnitQuaternion::from_axis_angle(&Vector3::z_axis(), PI),
            ),
        parts: vec![
            BodyPart {
                shape: Primitive::Capsule {
                    a: [0.0, 0.0, 0.0],
                    b: [STEM_LENGTH - HEAD_RADIUS, 0.0, 0.0],
                    radius: STEM_RADIUS,
                },
                body_from_part: Isometry3::identity(),
                colour: [50, 160, 50],
            },
            BodyPart {
                shape: Primitive::Sphere {
                    radius: HEAD_RADIUS,
                },
                body_from_part: Isometry3::translation(STEM_LENGTH, 0.0, 0.0),
                colour,
            },
        ],
        grasp: Some(GraspSite {
            point: Vector3::new(GRASP_FROM_ROOT, 0.0, 0.0),
            width: 2.0 * HEAD_RADIUS,
        }),
    };
    TaskInstance {
        kind: TaskKind::PluckFlower(level),
        seed,
        bodies: vec![
            block,
            flower("bottom flower", -0.10, 0.06, [240, 220, 40]),
            flower("middle flower", 0.0, 0.10, [240, 120, 180]),
            flower("top flower", 0.10, 0.14, [220, 40, 40]),
        ],
        base_from_fixture: fixture,
        table_height,
    }
}

/// Above the head (open), around it (close), pulled out along the stem, lifted.
pub(crate) fn expert(task: &TaskInstance, level: FlowerLevel) -> Vec<Keyframe> {
    let fz = task.base_from_fixture.rotation * Vector3::z();
    let body = &task.bodies[level.body()];
    let site = body.base_from_body * nalgebra::Point3::new(GRASP_FROM_ROOT, 0.0, 0.0);
    let site = site.coords;
    let outward = body.base_from_body.rotation * Vector3::x();
    let r = grasp_rotation(-fz, fz.cross(&outward));
    let grasp = site + fz * 0.01;
    // Out along the stem and 2 cm up: a holder tilted towards the robot must not take the
    // fingers of the bottom flower down to the table.
    let pulled = grasp + outward * PULL + Vector3::z() * 0.02;
    vec![
        keyframe(site + fz * 0.10, r, true),
        keyframe(grasp, r, false),
        keyframe_through(pulled, r, false),
        keyframe(pulled + Vector3::z() * LIFT, r, false),
    ]
}

/// The named flower is out of the block (at least [`PLUCKED_DISTANCE`] from where it was
/// planted) and the others are still in place.
pub(crate) fn success(task: &TaskInstance, level: FlowerLevel, poses: &[Isometry3<f64>]) -> bool {
    (1..=3).all(|i| {
        let moved = moved(task, poses, i);
        if i == level.body() {
            moved >= PLUCKED_DISTANCE
        } else {
            moved < IN_PLACE_DISTANCE
        }
    })
}

/// Why the task can no longer succeed: another flower has come out of its place (a
/// released flower falls to the table, so it cannot be put back).
pub(crate) fn lost(
    task: &TaskInstance,
    level: FlowerLevel,
    poses: &[Isometry3<f64>],
) -> Option<String> {
    (1..=3)
        .filter(|&i| i != level.body())
        .find_map(|i| moved_from_place(task, poses, i, IN_PLACE_DISTANCE))
}

/// A released flower falls and lies on the table.
pub(crate) fn released(task: &TaskInstance, pose: &Isometry3<f64>) -> Isometry3<f64> {
    lying_on_table(pose, HEAD_RADIUS, task.table_height)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn plucking_another_flower_loses_the_task() {
        let t = TaskInstance::sample(TaskKind::PluckFlower(FlowerLevel::Middle), 2, -0.06);
        let mut poses: Vec<_> = t.bodies.iter().map(|b| b.base_from_body).collect();
        assert_eq!(t.lost(&poses), None);
        poses[FlowerLevel::Middle.body()].translation.vector.x -= 0.1;
        assert_eq!(t.lost(&poses), None);
        poses[FlowerLevel::Top.body()].translation.vector.x -= 0.03;
        let why = t.lost(&poses).unwrap();
        assert!(why.contains("top flower"), "{why}");
    }

    #[test]
    fn success_needs_the_named_flower_out_and_the_others_in() {
        let t = TaskInstance::sample(TaskKind::PluckFlower(FlowerLevel::Middle), 2, -0.06);
        let mut poses: Vec<_> = t.bodies.iter().map(|b| b.base_from_body).collect();
        assert!(!t.success(&poses, None));
        poses[2].translation.vector.z += 0.12;
        assert!(t.success(&poses, Some(2)));
        poses[3].translation.vector.z += 0.12;
        assert!(!t.success(&poses, Some(2)));
    }
}
