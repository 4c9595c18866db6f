//! Simulated tasks: a seeded scene, the scripted expert's keyframes from the true object
//! poses, and a success test on the outcome (the objects' state), not on the keyframes.
//!
//! The paper's four physical tasks, each in its own module with its language variations:
//! - [`pick_fruit`]: pick up a strawberry, peach or plum and lift it (posed in SE(2), as the
//!   paper does);
//! - [`pipe`]: disassemble a pipe: pull off the first link, the second link, or both;
//! - [`flower`]: pluck the top, middle or bottom flower out of a foam block;
//! - [`toilet_roll`]: install a large or small toilet roll on its holder's spindle.
//!
//! A posed task is a list of rigid [`Body`]s made of scene primitives; [`world::TaskWorld`]
//! keeps their poses and the grasp attachment (a closed gripper around a body carries it,
//! opening releases it and the task says where it comes to rest). The fixtures of pipe,
//! flower and toilet roll are posed by a seeded random SE(3) transform (position, yaw, a
//! tilt of up to 10° and a lift) and stand on a pedestal down to the table.

pub mod check;
pub mod flower;
pub mod pick_fruit;
pub mod pipe;
pub mod toilet_roll;
pub mod world;

use std::f64::consts::PI;

use cell_types::{Base, Keyframe, Tcp, Transform};
use hil_sim::scene::{Primitive, HOME_Q};
use nalgebra::{Isometry3, Matrix3, Rotation3, Translation3, UnitQuaternion, Vector3};
use rand::Rng;
use rand_chacha::ChaCha8Rng;
use serde::{Deserialize, Serialize};

pub use flower::FlowerLevel;
pub use pick_fruit::{Fruit, GRASP_HEIGHT_ABOVE_CENTRE, LIFT_SUCCESS_HEIGHT};
pub use pipe::PipePart;
pub use toilet_roll::RollSize;

/// Why a task name could not be used.
#[derive(Clone, Debug, PartialEq, Eq, thiserror::Error)]
pub enum TaskError {
    /// The task is not one of the simulated tasks.
    #[error(
        "unknown task `{0}`: the simulated cell has pick_fruit, disassemble_pipe, pluck_flower \
         and install_toilet_roll; name a variation as task/variation, e.g. pluck_flower/top"
    )]
    UnknownTask(String),
    /// The variation is not one of the task's.
    #[error("unknown {task} variation `{variation}`: use one of {choices}")]
    UnknownVariation {
        /// The task.
        task: &'static str,
        /// The variation asked for.
        variation: String,
        /// The task's variations.
        choices: &'static str,
    },
}

/// A task the simulated cell can pose and judge, with its language variation.
#[derive(Copy, Clone, Debug, PartialEq, Eq, Hash)]
pub enum TaskKind {
    /// Pick a fruit from the table and lift it.
    PickFruit(Fruit),
    /// Pull links off a pipe assembly.
    DisassemblePipe(PipePart),
    /// Pluck one flower out of a foam block.
    PluckFlower(FlowerLevel),
    /// Put a toilet roll on its holder's spindle.
    InstallToiletRoll(RollSize),
}

impl TaskKind {
    /// Every task variation the simulated cell has, in a fixed order.
    pub fn all() -> Vec<TaskKind> {
        let mut v = Vec::new();
        v.extend(Fruit::ALL.map(TaskKind::PickFruit));
        v.extend(PipePart::ALL.map(TaskKind::DisassemblePipe));
        v.extend(FlowerLevel::ALL.map(TaskKind::PluckFlower));
        v.extend(RollSize::ALL.map(TaskKind::InstallToiletRoll));
        v
    }

    /// The variations of the task named `task` (all four tasks' names), or `None`.
    pub fn variations_of(task: &str) -> Option<Vec<TaskKind>> {
        let v: Vec<TaskKind> = Self::all()
            .into_iter()
            .filter(|k| k.task_name() == task)
            .collect();
        (!v.is_empty()).then_some(v)
    }

    /// Parses a task name as the CLI takes it (`pick_fruit`, `pick_fruit/peach`,
    /// `disassemble_pipe/all`, ...). Without a variation, the task's first one.
    pub fn parse(name: &str) -> Result<Self, TaskError> {
        let (task, variant) = match name.split_once('/') {
            Some((t, v)) => (t, Some(v)),
            None => (name, None),
        };
        let variations =
            Self::variations_of(task).ok_or_else(|| TaskError::UnknownTask(task.to_string()))?;
        let Some(variant) = variant else {
            return variations
                .first()
                .copied()
                .ok_or_else(|| TaskError::UnknownTask(task.to_string()));
        };
        variations
            .iter()
            .copied()
            .find(|k| k.variation_name() == variant)
            .ok_or_else(|| {
                let (task, choices) = match variations[0] {
                    TaskKind::PickFruit(_) => ("pick_fruit", "strawberry, peach, plum"),
                    TaskKind::DisassemblePipe(_) => {
                        ("disassemble_pipe", "first_link, second_link, all")
                    }
                    TaskKind::PluckFlower(_) => ("pluck_flower", "top, middle, bottom"),
                    TaskKind::InstallToiletRoll(_) => ("install_toilet_roll", "large, small"),
                };
                TaskError::UnknownVariation {
                    task,
                    variation: variant.to_string(),
                    choices,
                }
            })
    }

    /// The task's name without the variation.
    pub fn task_name(&self) -> &'static str {
        match self {
            TaskKind::PickFruit(_) => "pick_fruit",
            TaskKind::DisassemblePipe(_) => "disassemble_pipe",
            TaskKind::PluckFlower(_) => "pluck_flower",
            TaskKind::InstallToiletRoll(_) => "install_toilet_roll",
        }
    }

    /// The variation's name.
    pub fn variation_name(&self) -> &'static str {
        match self {
            TaskKind::PickFruit(f) => f.name(),
            TaskKind::DisassemblePipe(p) => p.name(),
            TaskKind::PluckFlower(l) => l.name(),
            TaskKind::InstallToiletRoll(s) => s.name(),
        }
    }

    /// Whether the expert's keyframe `step` (0: the first) is placed by the scene while the
    /// gripper carries a free object, so that the hand and what it holds could be elsewhere
    /// and the keyframe would stay: the toilet roll carried above the spindle (step 3) and
    /// lowered over it and let go (step 4). A lift is placed relative to the hand, and a
    /// pipe link or a flower is held while still attached to the scene (moving the hand would
    /// move it off its place, which no observation shows), so no other step is.
    pub fn placed_by_scene(&self, step: usize) -> bool {
        matches!(self, TaskKind::InstallToiletRoll(_)) && matches!(step, 3 | 4)
    }

    /// The task's name with its variation (`task/variation`).
    pub fn name(&self) -> String {
        format!("{}/{}", self.task_name(), self.variation_name())
    }

    /// The language instruction of this variation.
    pub fn instruction(&self) -> String {
        match self {
            TaskKind::PickFruit(f) => format!("pick up the {}", f.name()),
            TaskKind::DisassemblePipe(p) => p.instruction().to_string(),
            TaskKind::PluckFlower(l) => format!("pluck the {} flower", l.name()),
            TaskKind::InstallToiletRoll(s) => {
                format!("install the {} toilet roll on the holder", s.name())
            }
        }
    }
}

/// One solid of a body, in the body's frame.
#[derive(Copy, Clone, Debug, PartialEq)]
pub struct BodyPart {
    /// Its shape.
    pub shape: Primitive,
    /// Where it sits in the body frame.
    pub body_from_part: Isometry3<f64>,
    /// Its colour for the cameras.
    pub colour: [u8; 3],
}

/// Where a body can be grasped.
#[derive(Copy, Clone, Debug, PartialEq)]
pub struct GraspSite {
    /// The point (body frame) the TCP must be within [`world::GRASP_RADIUS`] of.
    pub point: Vector3<f64>,
    /// The width the fingers stop at when they close on it (m).
    pub width: f64,
}

/// A rigid body of a task's scene: a fixture or an object.
#[derive(Clone, Debug, PartialEq)]
pub struct Body {
    /// A name for the scene and reports.
    pub name: String,
    /// Its pose in the base frame as posed.
    pub base_from_body: Isometry3<f64>,
    /// Its solids.
    pub parts: Vec<BodyPart>,
    /// Where it can be grasped; `None` for fixtures.
    pub grasp: Option<GraspSite>,
}

/// A posed instance of a task: where its bodies are.
#[derive(Clone, Debug, PartialEq)]
pub struct TaskInstance {
    /// Which task.
    pub kind: TaskKind,
    /// The seed it was posed with; an expert draws its own variations (where it grasps)
    /// from a stream of it apart from the scene's, so the scenes stay as they were.
    pub seed: u64,
    /// The bodies as posed (fixtures and objects).
    pub bodies: Vec<Body>,
    /// The pose of the task's fixture (pick fruit: the fruit's own pose).
    pub base_from_fixture: Isometry3<f64>,
    /// Table top height (m).
    pub table_height: f64,
}

impl TaskInstance {
    /// Poses the task with a seeded random transform within the task's ranges (see each
    /// task's module).
    pub fn sample(kind: TaskKind, seed: u64, table_height: f64) -> Self {
        match kind {
            TaskKind::PickFruit(f) => pick_fruit::sample(f, seed, table_height),
            TaskKind::DisassemblePipe(p) => pipe::sample(p, seed, table_height),
            TaskKind::PluckFlower(l) => flower::sample(l, seed, table_height),
            TaskKind::InstallToiletRoll(s) => toilet_roll::sample(s, seed, table_height),
        }
    }

    /// The pose of the task's main object as posed (pick fruit: the fruit).
    pub fn base_from_object(&self) -> Isometry3<f64> {
        self.bodies
            .iter()
            .find(|b| b.grasp.is_some())
            .map_or(self.base_from_fixture, |b| b.base_from_body)
    }

    /// The scripted expert's episode under `settings`: what it records as demonstration
    /// labels and what it executes, which differ only where the settings inject a
    /// perturbation into the execution (a turned toilet-roll grasp).
    pub fn expert_plan(&self, settings: &ExpertSettings) -> ExpertPlan {
        match self.kind {
            TaskKind::InstallToiletRoll(_) => toilet_roll::expert_turned(
                self,
                toilet_roll::expert_grasp_turn(self, settings.grasp_turn_deg.to_radians()),
                settings.centred_grasp_labels,
            ),
            _ => {
                let executed = self.expert_keyframes();
                ExpertPlan {
                    recorded: executed.clone(),
                    executed,
                }
            }
        }
    }

    /// The scripted expert: keyframes from the true body poses.
    pub fn expert_keyframes(&self) -> Vec<Keyframe> {
        match self.kind {
            TaskKind::PickFruit(f) => pick_fruit::expert(self, f),
            TaskKind::DisassemblePipe(p) => pipe::expert(self, p),
            TaskKind::PluckFlower(l) => flower::expert(self, l),
            TaskKind::InstallToiletRoll(_) => toilet_roll::expert(self),
        }
    }

    /// The success test on the world's state: the bodies' poses now (same order as
    /// [`TaskInstance::bodies`]) and which body the gripper holds.
    pub fn success(&self, poses: &[Isometry3<f64>], held: Option<usize>) -> bool {
        if poses.len() != self.bodies.len() {
            return false;
        }
        match self.kind {
            TaskKind::PickFruit(f) => pick_fruit::success(self, f, poses, held),
            TaskKind::DisassemblePipe(p) => pipe::success(self, p, poses),
            TaskKind::PluckFlower(l) => flower::success(self, l, poses),
            TaskKind::InstallToiletRoll(s) => toilet_roll::success(self, s, poses, held),
        }
    }

    /// Why the task can no longer succeed in this state (a part it must leave in place has
    /// moved, a roll fell off the holder onto its side); `None` while it still can. A fruit
    /// can always be picked again, a roll dropped upright on the table re-grasped.
    pub fn lost(&self, poses: &[Isometry3<f64>]) -> Option<String> {
        if poses.len() != self.bodies.len() {
            return None;
        }
        match self.kind {
            TaskKind::DisassemblePipe(p) => pipe::lost(self, p, poses),
            TaskKind::PluckFlower(l) => flower::lost(self, l, poses),
            TaskKind::InstallToiletRoll(s) => toilet_roll::lost(self, s, poses),
            TaskKind::PickFruit(_) => None,
        }
    }

    /// Whether body `index` at `pose` stands free on the table, so that closing fingers
    /// slide it to the middle of the jaws (a fruit, a roll standing on the table) rather than
    /// closing on it where it is (pipe links held by the junction, stems in the foam, a roll
    /// on the spindle).
    pub fn stands_free(&self, index: usize, pose: &Isometry3<f64>) -> bool {
        match self.kind {
            TaskKind::PickFruit(_) => true,
            TaskKind::InstallToiletRoll(s) => toilet_roll::on_table(self, s, index, pose),
            TaskKind::DisassemblePipe(_) | TaskKind::PluckFlower(_) => false,
        }
    }

    /// The axis (body frame) of body `index` that the expert holds against the approach, where
    /// its direction matters: a roll's, which must go down the spindle. The grasp report says
    /// how far a grasp turned it ([`world::AxisTilt`]).
    pub fn held_axis(&self, index: usize) -> Option<Vector3<f64>> {
        match self.kind {
            TaskKind::InstallToiletRoll(_) if index == toilet_roll::ROLL => Some(Vector3::z()),
            _ => None,
        }
    }

    /// Body `index` let go by the gripper at `let_go`: where it comes to rest, and what
    /// happened, measured ([`ReleaseOutcome`]).
    pub fn release(
        &self,
        index: usize,
        let_go: &Isometry3<f64>,
    ) -> (Isometry3<f64>, ReleaseOutcome) {
        let rest = match self.kind {
            TaskKind::PickFruit(f) => pick_fruit::released(self, f, let_go),
            TaskKind::DisassemblePipe(_) => pipe::released(self, let_go),
            TaskKind::PluckFlower(_) => flower::released(self, let_go),
            TaskKind::InstallToiletRoll(s) => match toilet_roll::released(self, s, index, let_go) {
                Some((rest, roll)) => return (rest, ReleaseOutcome::Roll(roll)),
                None => *let_go,
            },
        };
        let p = rest.translation.vector;
        let outcome = ReleaseOutcome::Fell {
            drop_mm: (let_go.translation.vector.z - p.z) * 1e3,
            rest_m: [p.x, p.y, p.z],
        };
        (rest, outcome)
    }
}

/// What letting go of a body did: for a toilet roll, how it met the holder's spindle; for
/// any other body, how far it fell and where it came to rest. Its
/// [`Display`](std::fmt::Display) is the words an episode's log shows.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
#[serde(tag = "kind", rename_all = "snake_case")]
pub enum ReleaseOutcome {
    /// A toilet roll, measured against the holder.
    Roll(toilet_roll::RollRelease),
    /// Any other body.
    Fell {
        /// Height it fell (mm).
        drop_mm: f64,
        /// Where it came to rest: its origin in the base frame (m).
        rest_m: [f64; 3],
    },
}

impl std::fmt::Display for ReleaseOutcome {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            ReleaseOutcome::Roll(roll) => roll.fmt(f),
            ReleaseOutcome::Fell { drop_mm, rest_m } => write!(
                f,
                "it fell {:.0} mm and came to rest at [{:.3}, {:.3}, {:.3}] m",
                rounded(*drop_mm, 0),
                rest_m[0],
                rest_m[1],
                rest_m[2]
            ),
        }
    }
}

/// How far body `i` is from where the task placed it (m).
pub(crate) fn moved(task: &TaskInstance, poses: &[Isometry3<f64>], i: usize) -> f64 {
    (poses[i].translation.vector - task.bodies[i].base_from_body.translation.vector).norm()
}

/// Why body `i` is no longer in place ("the X moved N cm from its place; ..."), when it
/// moved `limit` or more.
pub(crate) fn moved_from_place(
    task: &TaskInstance,
    poses: &[Isometry3<f64>],
    i: usize,
    limit: f64,
) -> Option<String> {
    let d = moved(task, poses, i);
    (d >= limit).then(|| {
        format!(
            "the {} moved {:.1} cm from its place; the task needs it left in place",
            task.bodies[i].name,
            d * 100.0
        )
    })
}

/// Samples the SE(3) fixture transform of the non-planar tasks: position in the given x and
/// y ranges, yaw about the base z in `yaw`, roll and pitch each within ±`tilt_deg`, lifted
/// 0–3 cm above the table (the pedestal under the fixture reaches the table).
pub(crate) fn sample_fixture(
    rng: &mut ChaCha8Rng,
    x: (f64, f64),
    y: (f64, f64),
    yaw: (f64, f64),
    tilt_deg: f64,
    table_height: f64,
) -> Isometry3<f64> {
    let px = rng.random_range(x.0..x.1);
    let py = rng.random_range(y.0..y.1);
    let lift = rng.random_range(0.0..0.03);
    let yaw = rng.random_range(yaw.0..yaw.1);
    let t = tilt_deg.to_radians();
    let roll = rng.random_range(-t..t);
    let pitch = rng.random_range(-t..t);
    let rotation = UnitQuaternion::from_axis_angle(&Vector3::z_axis(), yaw)
        * UnitQuaternion::from_euler_angles(roll, pitch, 0.0);
    Isometry3::from_parts(Translation3::new(px, py, table_height + lift), rotation)
}

/// A pedestal under a fixture: a box of `half_x` × `half_y` reaching 0.25 m below the
/// fixture origin (through the table, which hides the rest).
pub(crate) fn pedestal(half_x: f64, half_y: f64, centre_x: f64, colour: [u8; 3]) -> BodyPart {
    BodyPart {
        shape: Primitive::Box {
            half_extents: [half_x, half_y, 0.125],
        },
        body_from_part: Isometry3::translation(centre_x, 0.0, -0.125),
        colour,
    }
}

/// The home TCP's x axis (the fingers' closing direction) in the base frame.
fn home_closing_axis() -> Vector3<f64> {
    let flange = planner::kinematics::UR5.forward(&HOME_Q);
    flange.isometry().rotation * Vector3::x()
}

/// A TCP orientation approaching along `approach` (the TCP z) with the fingers closing
/// along `closing` (made perpendicular to the approach); of the two equivalent finger
/// orientations, the one nearer the home pose's, so the wrist does not wind half a turn.
pub(crate) fn grasp_rotation(approach: Vector3<f64>, closing: Vector3<f64>) -> UnitQuaternion<f64> {
    let z = approach.normalize();
    let mut x = closing - z * closing.dot(&z);
    if x.norm() < 1e-9 {
        x = z.cross(&Vector3::x());
        if x.norm() < 1e-9 {
            x = z.cross(&Vector3::y());
        }
    }
    let mut x = x.normalize();
    if x.dot(&home_closing_axis()) < 0.0 {
        x = -x;
    }
    let y = z.cross(&x);
    UnitQuaternion::from_rotation_matrix(&Rotation3::from_matrix_unchecked(Matrix3::from_columns(
        &[x, y, z],
    )))
}

/// A keyframe at TCP position `p` with orientation `r`.
pub(crate) fn keyframe(p: Vector3<f64>, r: UnitQuaternion<f64>, open: bool) -> Keyframe {
    let base_from_tcp: Transform<Base, Tcp> = Transform::from_parts(p, r);
    Keyframe {
        base_from_tcp,
        gripper_open: open,
        ignore_collisions: false,
    }
}

/// The pose lying flat on the table that a released elongated body (its long axis along
/// body x, `radius` its half thickness) falls into: same x, y and heading.
pub(crate) fn lying_on_table(
    pose: &Isometry3<f64>,
    radius: f64,
    table_height: f64,
) -> Isometry3<f64> {
    let axis = pose.rotation * Vector3::x();
    let heading = axis.y.atan2(axis.x);
    let heading = if heading.is_finite() { heading } else { 0.0 };
    Isometry3::from_parts(
        Translation3::new(
            pose.translation.vector.x,
            pose.translation.vector.y,
            table_height + radius,
        ),
        UnitQuaternion::from_axis_angle(&Vector3::z_axis(), heading),
    )
}

/// A length (m) in millimetres rounded to `decimals` places, for reports: a value that
/// rounds to zero prints as 0, never "-0".
pub(crate) fn rounded_mm(m: f64, decimals: i32) -> f64 {
    rounded(m * 1e3, decimals)
}

/// `v` rounded to `decimals` places, for reports: a value that rounds to zero prints as 0,
/// never "-0".
pub(crate) fn rounded(v: f64, decimals: i32) -> f64 {
    let scale = 10f64.powi(decimals);
    // Adding 0.0 turns the −0.0 that rounding a small negative value gives into 0.0.
    (v * scale).round() / scale + 0.0
}

/// Angle between two unit vectors (rad).
pub(crate) fn angle_between(a: &Vector3<f64>, b: &Vector3<f64>) -> f64 {
    a.dot(b).clamp(-1.0, 1.0).acos()
}

/// A keyframe planned without the observed cloud (the keyframe-policy literature's "ignore
/// collisions"): short extraction and insertion moves, where the held object's own points
/// would block the gripper that carries it.
pub(crate) fn keyframe_through(p: Vector3<f64>, r: UnitQuaternion<f64>, open: bool) -> Keyframe {
    Keyframe {
        ignore_collisions: true,
        ..keyframe(p, r, open)
    }
}

/// How the scripted expert records demonstrations (`equact demos collect`); the default is
/// the plain expert.
#[derive(Clone, Copy, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct ExpertSettings {
    /// Largest turn (°) of the executed toilet-roll grasp about the jaws' closing axis; each
    /// episode draws its own from the seed. The recorded grasp stays the clean one and the
    /// later keyframes place the turned roll's axis along the spindle, so the demonstrations
    /// show how to place a roll held turned, as a learned grasp leaves it (the idea of
    /// DART: perturb the execution, keep the expert's labels). 0 by default; other tasks
    /// ignore it.
    #[serde(default)]
    pub grasp_turn_deg: f64,
    /// Toilet roll: record the approach above the roll and the grasp centred along the pads,
    /// while the arm still executes them at the episode's offset along the pads (within
    /// [`toilet_roll::GRASP_ALONG_PADS`]) and the release still places the off-centre roll
    /// over the spindle. The offset is drawn from the seed and cannot be seen before the
    /// grasp, so the plain expert's grasp labels carry it as noise; these labels do not (DART
    /// again). A 600-step fine-tune on 15 such demonstrations per roll grasped further off
    /// the middle than one on the plain labels (README, "Centred grasp labels"), so it is off
    /// by default, and in older indexes.
    #[serde(default, skip_serializing_if = "std::ops::Not::not")]
    pub centred_grasp_labels: bool,
}

impl ExpertSettings {
    /// Whether the settings change the expert's demonstrations of `kind` (the grasp turn and
    /// the centred grasp labels: the toilet roll's only).
    pub fn apply_to(kind: TaskKind) -> bool {
        matches!(kind, TaskKind::InstallToiletRoll(_))
    }
}

/// An expert episode: the keyframes recorded as labels and those executed.
#[derive(Clone, Debug, PartialEq)]
pub struct ExpertPlan {
    /// The labels, one per step.
    pub recorded: Vec<Keyframe>,
    /// What the arm is sent, one per step.
    pub executed: Vec<Keyframe>,
}

/// Half a turn, for the yaw ranges.
pub(crate) const HALF_TURN: f64 = PI;

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn every_task_name_parses_back_and_bad_names_are_refused() {
        let all = TaskKind::all();
        assert_eq!(all.len(), 11);
        for k in &all {
            assert_eq!(TaskKind::parse(&k.name()), Ok(*k));
            assert!(!k.instruction().is_empty());
        }
        assert_eq!(
            TaskKind::parse("pick_fruit"),
            Ok(TaskKind::PickFruit(Fruit::Strawberry))
        );
        assert_eq!(
            TaskKind::parse("pluck_flower/top"),
            Ok(TaskKind::PluckFlower(FlowerLevel::Top))
        );
        let e = TaskKind::parse("pick_fruit/apple").unwrap_err().to_string();
        assert!(e.contains("strawberry"), "{e}");
        let e = TaskKind::parse("juggle").unwrap_err().to_string();
        assert!(e.contains("unknown task"), "{e}");
    }

    #[test]
    fn sampling_is_seeded() {
        for k in TaskKind::all() {
            let a = TaskInstance::sample(k, 4, -0.06);
            let b = TaskInstance::sample(k, 4, -0.06);
            let c = TaskInstance::sample(k, 5, -0.06);
            assert_eq!(a, b);
            assert_ne!(a, c);
            assert!(!a.expert_keyframes().is_empty());
        }
    }

    #[test]
    fn grasp_rotation_is_a_right_handed_frame_along_the_approach() {
        let r = grasp_rotation(-Vector3::z(), Vector3::new(1.0, 1.0, 0.3));
        let z = r * Vector3::z();
        assert!((z + Vector3::z()).norm() < 1e-9);
        let x = r * Vector3::x();
        assert!(x.z.abs() < 1e-9);
    }
}
