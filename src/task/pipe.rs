//! Disassemble pipe: a pipe of two links plugged into a junction on a post stands on a
//! pedestal posed by a seeded SE(3) transform (x 0.45–0.58 m, y −0.08–0.08 m, the links
//! along the base y ±45°, tilt ≤ 10°, lift ≤ 3 cm). The robot pulls a link out of the
//! junction along its axis and lifts it away. Variations: the first link, the second link,
//! or all (the first is put down beside the pipe, then the second is pulled off).

use std::f64::consts::FRAC_PI_2;
use std::f64::consts::FRAC_PI_4;

use cell_types::Keyframe;
use hil_sim::scene::Primitive;
use nalgebra::{Isometry3, UnitQuaternion, Vector3};
use rand::SeedableRng;
use rand_chacha::ChaCha8Rng;

use super::{
    grasp_rotation, keyframe, keyframe_through, lying_on_table, moved, moved_from_place, pedestal,
    sample_fixture, Body, BodyPart, GraspSite, TaskInstance, TaskKind,
};

/// Radius of a pipe link (m).
pub const LINK_RADIUS: f64 = 0.016;
/// Half the length of a pipe link (m).
pub const LINK_HALF_LENGTH: f64 = 0.045;
/// Height of the pipe's axis above the pedestal (m).
const AXIS_HEIGHT: f64 = 0.08;
/// Distance of a link's centre from the junction (m).
const LINK_OFFSET: f64 = 0.07;
/// Where the expert grasps a link: this far out from its centre along its axis (m), so
/// the gripper's palm (4.5 cm radius) clears the junction.
const GRASP_OFFSET: f64 = 0.012;
/// Radius of the junction the links plug into (m).
const JUNCTION_RADIUS: f64 = 0.022;
/// How far the expert pulls a link along its axis (m): its inner end clears the junction.
const PULL: f64 = 0.07;
/// How far the expert lifts a pulled link (m).
const LIFT: f64 = 0.10;
/// A link counts as removed this far from where it was plugged in (m).
pub const REMOVED_DISTANCE: f64 = 0.08;
/// A link counts as in place this close to where it was plugged in (m).
const IN_PLACE_DISTANCE: f64 = 0.01;

/// The variations of `disassemble_pipe`.
#[derive(Copy, Clone, Debug, PartialEq, Eq, Hash)]
pub enum PipePart {
    /// Remove the first link only.
    FirstLink,
    /// Remove the second link only.
    SecondLink,
    /// Remove both links.
    All,
}

impl PipePart {
    /// The variations in order.
    pub const ALL: [PipePart; 3] = [PipePart::FirstLink, PipePart::SecondLink, PipePart::All];

    /// The variation's name.
    pub fn name(self) -> &'static str {
        match self {
            PipePart::FirstLink => "first_link",
            PipePart::SecondLink => "second_link",
            PipePart::All => "all",
        }
    }

    /// The language instruction.
    pub fn instruction(self) -> &'static str {
        match self {
            PipePart::FirstLink => "disassemble the first link of the pipe",
            PipePart::SecondLink => "disassemble the second link of the pipe",
            PipePart::All => "disassemble all links of the pipe",
        }
    }

    /// Which links (body indices 1 = first, 2 = second) are to be removed.
    fn targets(self) -> &'static [usize] {
        match self {
            PipePart::FirstLink => &[1],
            PipePart::SecondLink => &[2],
            PipePart::All => &[1, 2],
        }
    }
}

/// Poses the pipe assembly (body 0: pedestal, post and junction; 1: first link; 2: second).
pub(crate) fn sample(part: PipePart, seed: u64, table_height: f64) -> TaskInstance {
    let mut rng = ChaCha8Rng::seed_from_u64(seed);
    let fixture = sample_fixture(
        &mut rng,
        (0.45, 0.58),
        (-0.08, 0.08),
        (FRAC_PI_2 - FRAC_PI_4, FRAC_PI_2 + FRAC_PI_4),
        10.0,
        table_height,
    );
    let grey = [150, 150, 160];
    let base = Body {
        name: "pipe junction".into(),
        base_from_body: fixture,
        parts: vec![
            pedestal(0.04, 0.04, 0.0, [120, 100, 80]),
            BodyPart {
                shape: Primitive::Box {
                    half_extents: [0.02, 0.02, 0.04],
                },
                body_from_part: Isometry3::translation(0.0, 0.0, 0.04),
                colour: grey,
            },
            BodyPart {
                shape: Primitive::Sphere {
                    radius: JUNCTION_RADIUS,
                },
                body_from_part: Isometry3::translation(0.0, 0.0, AXIS_HEIGHT),
                colour: [200, 160, 40],
            },
        ],
        grasp: None,
    };
    // A link's frame: origin at its centre, x along its axis pointing out of the junction.
    let link = |name: &str, side: f64, colour: [u8; 3]| {
        let yaw = if side < 0.0 {
            std::f64::consts::PI
        } else {
            0.0
        };
        Body {
            name: name.into(),
            base_from_body: fixture
                * Isometry3::from_parts(
                    nalgebra::Translation3::new(side * LINK_OFFSET, 0.0, AXIS_HEIGHT),
                    UnitQuaternion::from_axis_angle(&Vector3::z_axis(), yaw),
                ),
            parts: vec![BodyPart {
                shape: Primitive::Cylinder {
                    half_height: LINK_HALF_LENGTH,
                    radius: LINK_RADIUS,
                },
                body_from_part: Isometry3::rotation(Vector3::y() * FRAC_PI_2),
                colour,
            }],
            grasp: Some(GraspSite {
                point: Vector3::new(GRASP_OFFSET, 0.0, 0.0),
                width: 2.0 * LINK_RADIUS,
            }),
        }
    };
    TaskInstance {
        kind: TaskKind::DisassemblePipe(part),
        seed,
        bodies: vec![
            base,
            link("first link", -1.0, [60, 120, 200]),
            link("second link", 1.0, [60, 170, 90]),
        ],
        base_from_fixture: fixture,
        table_height,
    }
}

/// Per link: above it (open), around it (close), pulled out along its axis (planned without
/// the cloud: the held link's own points would block it), lifted. For `all`, the first link
/// is carried outward and dropped onto the table before the second.
pub(crate) fn expert(task: &TaskInstance, part: PipePart) -> Vec<Keyframe> {
    let fz = task.base_from_fixture.rotation * Vector3::z();
    let mut out = Vec::new();
    let targets = part.targets();
    for (n, &i) in targets.iter().enumerate() {
        let link = &task.bodies[i].base_from_body;
        let site = (link * nalgebra::Point3::new(GRASP_OFFSET, 0.0, 0.0)).coords;
        let outward = link.rotation * Vector3::x();
        let r = grasp_rotation(-fz, fz.cross(&outward));
        // The TCP a link radius above the axis: the palm (1 cm behind the TCP) stays 1 cm
        // above the link's top, where the closing volume no longer hides the link's points.
        let grasp = site + fz * LINK_RADIUS;
        let pulled = grasp + outward * PULL;
        let lifted = pulled + Vector3::z() * LIFT;
        out.push(keyframe(site + fz * 0.12, r, true));
        out.push(keyframe(grasp, r, false));
        out.push(keyframe_through(pulled, r, false));
        out.push(keyframe(lifted, r, false));
        if n + 1 < targets.len() {
            // Carry it outward, clear of the pipe, at the lifted height (the held link's
            // own points stay below the gripper) and let go: it falls onto the table.
            let mut h = Vector3::new(outward.x, outward.y, 0.0);
            if h.norm() > 1e-6 {
                h = h.normalize();
            }
            let drop = lifted + h * 0.10;
            let flat = grasp_rotation(-Vector3::z(), r * Vector3::x());
            out.push(keyframe(drop, flat, true));
        }
    }
    out
}

/// The named links are off the junction (at least [`REMOVED_DISTANCE`] from where they were
/// plugged in) and the other link is still in place.
pub(crate) fn success(task: &TaskInstance, part: PipePart, poses: &[Isometry3<f64>]) -> bool {
    (1..=2).all(|i| {
        let moved = moved(task, poses, i);
        if part.targets().contains(&i) {
            moved >= REMOVED_DISTANCE
        } else {
            moved < IN_PLACE_DISTANCE
        }
    })
}

/// Why the task can no longer succeed: a link it must leave in place has moved (a
/// released link falls to the table, so it cannot be put back).
pub(crate) fn lost(
    task: &TaskInstance,
    part: PipePart,
    poses: &[Isometry3<f64>],
) -> Option<String> {
    (1..=2)
        .filter(|i| !part.targets().contains(i))
        .find_map(|i| moved_from_place(task, poses, i, IN_PLACE_DISTANCE))
}

/// A released link falls and lies on the table.
pub(crate) fn released(task: &TaskInstance, pose: &Isometry3<f64>) -> Isometry3<f64> {
    lying_on_table(pose, LINK_RADIUS, task.table_height)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn moving_the_link_to_leave_loses_the_task_and_the_named_one_does_not() {
        let t = TaskInstance::sample(TaskKind::DisassemblePipe(PipePart::FirstLink), 3, -0.06);
        let mut poses: Vec<_> = t.bodies.iter().map(|b| b.base_from_body).collect();
        assert_eq!(t.lost(&poses), None);
        poses[1].translation.vector.z += 0.2;
        assert_eq!(t.lost(&poses), None, "the first link is the one to take");
        poses[2].translation.vector.x += 0.005;
        assert_eq!(t.lost(&poses), None, "5 mm is still in place");
        poses[2].translation.vector.x += 0.01;
        let why = t.lost(&poses).unwrap();
        assert!(
            why.contains(&t.bodies[2].name) && why.contains("1.5 cm"),
            "{why}"
        );
        let all = TaskInstance::sample(TaskKind::DisassemblePipe(PipePart::All), 3, -0.06);
        assert_eq!(all.lost(&poses), None, "both links are to be taken");
    }

    #[test]
    fn success_needs_the_named_link_off_and_the_other_in_place() {
        let t = TaskInstance::sample(TaskKind::DisassemblePipe(PipePart::FirstLink), 3, -0.06);
        let mut poses: Vec<_> = t.bodies.iter().map(|b| b.base_from_body).collect();
        assert!(!t.success(&poses, None));
        poses[1].translation.vector.z += 0.1;
        assert!(t.success(&poses, Some(1)));
        poses[2].translation.vector.x += 0.05;
        assert!(!t.success(&poses, Some(1)));
        let all = TaskInstance::sample(TaskKind::DisassemblePipe(PipePart::All), 3, -0.06);
        assert!(!all.success(&poses, None));
        poses[2].translation.vector.z += 0.1;
        assert!(all.success(&poses, None));
        assert_eq!(all.expert_keyframes().len(), 9);
    }
}
