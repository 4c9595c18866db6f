//! Install toilet roll: a holder (a spindle on a base, on a pedestal) is posed by a seeded
//! SE(3) transform (x 0.42–0.60 m, 8–20 cm to one side of the base x axis, any yaw, tilt
//! ≤ 10°, lift ≤ 3 cm); the roll stands upright on the table on the other side (SE(2):
//! x 0.40–0.60 m, 8–20 cm to the other side, any yaw). The robot grasps the roll across
//! its outside (the expert up to 6 mm off its centre along the pads), carries it with the
//! roll's centre above the spindle, lowers it over the spindle along the holder's axis and
//! lets go. Variations: a large or a small roll.

use cell_types::Keyframe;
use hil_sim::scene::Primitive;
use nalgebra::{Isometry3, Point3, Translation3, UnitQuaternion, Vector3};
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;

use super::{
    angle_between, grasp_rotation, keyframe, keyframe_through, pedestal, rounded_mm,
    sample_fixture, Body, BodyPart, GraspSite, TaskInstance, TaskKind, HALF_TURN,
};

/// Radius of the holder's spindle (m).
pub const SPINDLE_RADIUS: f64 = 0.012;
/// Height of the spindle above the holder's seat (m).
pub const SPINDLE_HEIGHT: f64 = 0.035;
/// Radius of a roll's hole (m).
pub const HOLE_RADIUS: f64 = 0.02;
/// Depth of the grasp TCP below the roll's top (m): the gripper's palm is 1 cm behind the
/// TCP, so the TCP stays 5 mm above the top face (the palm 15 mm above it, clear of the
/// depth noise) and the 15 mm fingertips hold the roll's rim.
const GRASP_BELOW_TOP: f64 = -0.005;
/// Height of the roll's bottom above the seat where the expert lets go (m).
const RELEASE_HEIGHT: f64 = 0.012;
/// A seated roll's centre is this close to its place on the holder (m).
const SEATED_DISTANCE: f64 = 0.01;
/// Largest offset along the pads of the expert's grasp (m). Closing jaws centre a roll
/// across them but not along the pads, so a grasp that misses the centre that way carries
/// the roll off-centre in the hand; the expert grasps anywhere within this offset and
/// places the roll's centre, not the TCP, over the spindle, so its demonstrations show how
/// to place a roll held off-centre (a learned grasp is a few millimetres off).
pub const GRASP_ALONG_PADS: f64 = 0.006;
/// The expert's grasp offset is drawn from this stream of the task's seed (the scene uses
/// stream 0).
const EXPERT_STREAM: u64 = 1;

/// The variations of `install_toilet_roll`.
#[derive(Copy, Clone, Debug, PartialEq, Eq, Hash)]
pub enum RollSize {
    /// A large roll.
    Large,
    /// A small roll.
    Small,
}

impl RollSize {
    /// The variations in order.
    pub const ALL: [RollSize; 2] = [RollSize::Large, RollSize::Small];

    /// The variation's name.
    pub fn name(self) -> &'static str {
        match self {
            RollSize::Large => "large",
            RollSize::Small => "small",
        }
    }

    /// Outer radius (m); the 2F-85's 85 mm stroke closes across it.
    pub fn radius(self) -> f64 {
        match self {
            RollSize::Large => 0.035,
            RollSize::Small => 0.03,
        }
    }

    /// Half the roll's height (m).
    pub fn half_height(self) -> f64 {
        match self {
            RollSize::Large => 0.03,
            RollSize::Small => 0.025,
        }
    }
}

/// Poses the holder (body 0) and the roll (body 1).
pub(crate) fn sample(size: RollSize, seed: u64, table_height: f64) -> TaskInstance {
    let mut rng = ChaCha8Rng::seed_from_u64(seed);
    let side = if rng.random_bool(0.5) { 1.0 } else { -1.0 };
    let fixture = sample_fixture(
        &mut rng,
        (0.42, 0.60),
        if side > 0.0 {
            (0.08, 0.20)
        } else {
            (-0.20, -0.08)
        },
        (-HALF_TURN, HALF_TURN),
        10.0,
        table_height,
    );
    let holder = Body {
        name: "roll holder".into(),
        base_from_body: fixture,
        parts: vec![
            pedestal(0.06, 0.06, 0.0, [120, 100, 80]),
            BodyPart {
                shape: Primitive::Cylinder {
                    half_height: SPINDLE_HEIGHT / 2.0,
                    radius: SPINDLE_RADIUS,
                },
                body_from_part: Isometry3::translation(0.0, 0.0, SPINDLE_HEIGHT / 2.0),
                colour: [200, 200, 210],
            },
        ],
        grasp: None,
    };
    let x = rng.random_range(0.40..0.60);
    let y = -side * rng.random_range(0.08..0.20);
    let yaw = rng.random_range(-HALF_TURN..HALF_TURN);
    let h = size.half_height();
    let roll = Body {
        name: format!("{} toilet roll", size.name()),
        base_from_body: Isometry3::from_parts(
            Translation3::new(x, y, table_height + h),
            UnitQuaternion::from_axis_angle(&Vector3::z_axis(), yaw),
        ),
        parts: vec![
            BodyPart {
                shape: Primitive::Cylinder {
                    half_height: h,
                    radius: size.radius(),
                },
                body_from_part: Isometry3::identity(),
                colour: [235, 235, 230],
            },
            // The hole, seen from above: a dark disc on the top face.
            BodyPart {
                shape: Primitive::Cylinder {
                    half_height: 0.001,
                    radius: HOLE_RADIUS,
                },
                body_from_part: Isometry3::translation(0.0, 0.0, h),
                colour: [120, 90, 60],
            },
        ],
        grasp: Some(GraspSite {
            point: Vector3::new(0.0, 0.0, h - GRASP_BELOW_TOP),
            width: 2.0 * size.radius(),
        }),
    };
    TaskInstance {
        kind: TaskKind::InstallToiletRoll(size),
        seed,
        bodies: vec![holder, roll],
        base_from_fixture: fixture,
        table_height,
    }
}

/// Where the roll's centre sits when it is on the holder.
fn seated_centre(task: &TaskInstance, h: f64) -> Vector3<f64> {
    (task.base_from_fixture * Point3::new(0.0, 0.0, h)).coords
}

/// The expert's grasp offset along the pads (TCP y) for `task`, within
/// ±[`GRASP_ALONG_PADS`].
pub fn expert_grasp_offset(task: &TaskInstance) -> f64 {
    let mut rng = ChaCha8Rng::seed_from_u64(task.seed);
    rng.set_stream(EXPERT_STREAM);
    rng.random_range(-GRASP_ALONG_PADS..=GRASP_ALONG_PADS)
}

/// Above the roll (open), around its top (close) at [`expert_grasp_offset`] along the pads,
/// lifted, the roll's centre above the spindle along the holder's axis, lowered over it and
/// let go, back up.
pub(crate) fn expert(task: &TaskInstance) -> Vec<Keyframe> {
    let roll = &task.bodies[1].base_from_body;
    let h = match task.kind {
        TaskKind::InstallToiletRoll(s) => s.half_height(),
        _ => 0.0,
    };
    let axis = roll.rotation * Vector3::z();
    let r = grasp_rotation(-axis, roll.rotation * Vector3::x());
    let along = expert_grasp_offset(task);
    let grasp = roll.translation.vector + axis * (h - GRASP_BELOW_TOP) + r * Vector3::y() * along;
    let fz = task.base_from_fixture.rotation * Vector3::z();
    let r_place = grasp_rotation(-fz, r * Vector3::x());
    // The TCP when the roll's bottom is `s` above the seat: the held roll's centre is
    // h − GRASP_BELOW_TOP below the TCP along the TCP z and `along` behind it along the
    // TCP y (the jaws keep the grasp's offset along the pads).
    let place = |s: f64| {
        seated_centre(task, h) + fz * (s + h - GRASP_BELOW_TOP) + r_place * Vector3::y() * along
    };
    let release = place(RELEASE_HEIGHT);
    vec![
        keyframe(grasp + Vector3::z() * 0.10, r, true),
        keyframe(grasp, r, false),
        keyframe(grasp + Vector3::z() * 0.15, r, false),
        keyframe(place(SPINDLE_HEIGHT + 0.03), r_place, false),
        // Down over the spindle and back up are planned without the cloud: the carried
        // roll's own points lie where the gripper goes.
        keyframe_through(release, r_place, true),
        keyframe_through(release + fz * 0.10, r_place, true),
    ]
}

/// The roll is not held and sits on the holder: its centre within 1 cm of its seated place
/// and its axis within 10° of the spindle's.
pub(crate) fn success(
    task: &TaskInstance,
    size: RollSize,
    poses: &[Isometry3<f64>],
    held: Option<usize>,
) -> bool {
    let fz = task.base_from_fixture.rotation * Vector3::z();
    let p = &poses[1];
    held != Some(1)
        && (p.translation.vector - seated_centre(task, size.half_height())).norm() < SEATED_DISTANCE
        && angle_between(&(p.rotation * Vector3::z()), &fz) < 10f64.to_radians()
}

/// Whether body `index` is the roll standing on the table (not on the spindle, not held up).
pub(crate) fn on_table(
    task: &TaskInstance,
    size: RollSize,
    index: usize,
    pose: &Isometry3<f64>,
) -> bool {
    index == 1
        && (pose.translation.vector.z - (task.table_height + size.half_height())).abs() < 1e-3
}

/// Where a roll let go sits relative to the holder's spindle.
#[derive(Copy, Clone, Debug, PartialEq)]
struct OverSpindle {
    /// Distance of the roll's centre from the spindle's axis (m).
    radial: f64,
    /// Angle between the roll's axis and the spindle's (rad).
    tilt: f64,
    /// Height of the roll's bottom above the holder's seat (m).
    bottom: f64,
}

/// The hole's play around the spindle: a roll whose centre is further off the axis does not
/// go over it (m).
const HOLE_PLAY: f64 = HOLE_RADIUS - SPINDLE_RADIUS;
/// Largest tilt of a roll that still slides down the spindle.
const SEAT_TILT_DEG: f64 = 15.0;
/// Lowest and highest roll bottom (above the seat) that still slides down the spindle (m):
/// from just below the seat's face to the spindle's top.
const SEAT_BOTTOM: std::ops::Range<f64> = -0.005..SPINDLE_HEIGHT;

impl OverSpindle {
    /// Measures a roll of `size` at `pose` against `task`'s holder.
    fn measure(task: &TaskInstance, size: RollSize, pose: &Isometry3<f64>) -> Self {
        let local = task.base_from_fixture.inverse() * pose;
        let c = local.translation.vector;
        Self {
            radial: c.x.hypot(c.y),
            tilt: angle_between(&(local.rotation * Vector3::z()), &Vector3::z()),
            bottom: c.z - size.half_height(),
        }
    }

    /// Whether the roll's hole is around the spindle: axis within [`SEAT_TILT_DEG`], centre
    /// within the hole's play, bottom between the seat and the spindle's top.
    fn seats(&self) -> bool {
        self.tilt < SEAT_TILT_DEG.to_radians()
            && self.radial < HOLE_PLAY
            && SEAT_BOTTOM.contains(&self.bottom)
    }
}

/// A released roll whose hole is around the spindle ([`OverSpindle::seats`]) slides down
/// onto the seat; anywhere else it falls onto the table, upright.
pub(crate) fn released(
    task: &TaskInstance,
    size: RollSize,
    index: usize,
    pose: &Isometry3<f64>,
) -> Isometry3<f64> {
    let h = size.half_height();
    if index != 1 {
        return *pose;
    }
    if OverSpindle::measure(task, size, pose).seats() {
        let local = task.base_from_fixture.inverse() * pose;
        let x = local.rotation * Vector3::x();
        let yaw = x.y.atan2(x.x);
        return task.base_from_fixture
            * Isometry3::from_parts(
                Translation3::new(0.0, 0.0, h),
                UnitQuaternion::from_axis_angle(&Vector3::z_axis(), yaw),
            );
    }
    let x = pose.rotation * Vector3::x();
    Isometry3::from_parts(
        Translation3::new(
            pose.translation.vector.x,
            pose.translation.vector.y,
            task.table_height + h,
        ),
        UnitQuaternion::from_axis_angle(&Vector3::z_axis(), x.y.atan2(x.x)),
    )
}

/// The roll (body 1) let go at `pose`, in words: how far from the spindle's axis against the
/// hole's play, its tilt and height, and whether it went onto the spindle; `None` for
/// another body.
pub(crate) fn describe_release(
    task: &TaskInstance,
    size: RollSize,
    index: usize,
    pose: &Isometry3<f64>,
) -> Option<String> {
    if index != 1 {
        return None;
    }
    let m = OverSpindle::measure(task, size, pose);
    Some(format!(
        "let go {:.1} mm from the spindle's axis (a roll goes over it within {:.0} mm), tilted \
         {:.0}° (within {SEAT_TILT_DEG:.0}°), its bottom {:.0} mm above the seat ({:.0} to {:.0}); {}",
        rounded_mm(m.radial, 1),
        rounded_mm(HOLE_PLAY, 0),
        m.tilt.to_degrees(),
        rounded_mm(m.bottom, 0),
        rounded_mm(SEAT_BOTTOM.start, 0),
        rounded_mm(SEAT_BOTTOM.end, 0),
        if m.seats() {
            "it slid down onto the spindle"
        } else {
            "it fell onto the table"
        }
    ))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_expert_grasps_off_centre_along_the_pads_and_centres_the_roll_on_the_spindle() {
        use crate::task::world::TaskWorld;
        let mut offsets = Vec::new();
        for seed in 0..40 {
            let size = RollSize::ALL[seed as usize % 2];
            let t = TaskInstance::sample(TaskKind::InstallToiletRoll(size), seed, -0.06);
            let along = expert_grasp_offset(&t);
            assert_eq!(along, expert_grasp_offset(&t), "drawn from the seed");
            assert!(along.abs() <= GRASP_ALONG_PADS);
            offsets.push(along);
            let keys = t.expert_keyframes();
            let pose = |i: usize| *keys[i].base_from_tcp.isometry();
            let mut w = TaskWorld::new(t.clone());
            // The grasp is `along` from the roll's axis, along the pads (TCP y).
            let grasp = pose(1);
            let axis_point = t.bodies[1].base_from_body.translation.vector;
            let local = grasp.inverse() * Point3::from(axis_point);
            assert!(local.x.abs() < 1e-9, "{local:?}");
            assert!((local.y + along).abs() < 1e-9, "{local:?}");
            assert!(w.before_close(&grasp).is_some());
            w.after_gripper(&grasp, true);
            assert_eq!(w.held(), Some(1));
            // Carried to the release: the roll's centre (not the TCP) on the spindle's axis.
            let release = pose(4);
            w.carry(&release);
            let on_holder = t.base_from_fixture.inverse() * w.poses()[1];
            let c = on_holder.translation.vector;
            assert!(c.x.hypot(c.y) < 1e-6, "seed {seed}: {c:?} off the axis");
            let centre_height = size.half_height() + RELEASE_HEIGHT;
            assert!((c.z - centre_height).abs() < 1e-6, "seed {seed}: {c:?}");
            w.after_gripper(&release, false);
            assert!(w.success(), "seed {seed}");
        }
        // Spread over the range, both ways.
        let (lo, hi) = offsets
            .iter()
            .fold((f64::MAX, f64::MIN), |(lo, hi), &v| (lo.min(v), hi.max(v)));
        assert!(
            lo < -GRASP_ALONG_PADS / 2.0 && hi > GRASP_ALONG_PADS / 2.0,
            "{offsets:?}"
        );
    }

    #[test]
    fn a_roll_let_go_over_the_spindle_seats_and_elsewhere_falls() {
        let t = TaskInstance::sample(TaskKind::InstallToiletRoll(RollSize::Small), 7, -0.06);
        let h = RollSize::Small.half_height();
        let over = t.base_from_fixture * Isometry3::translation(0.002, 0.0, h + 0.01);
        let seated = t.released_pose(1, &over);
        let mut poses: Vec<_> = t.bodies.iter().map(|b| b.base_from_body).collect();
        assert!(!t.success(&poses, None));
        poses[1] = seated;
        assert!(t.success(&poses, None));
        assert!(!t.success(&poses, Some(1)));
        let beside = t.base_from_fixture * Isometry3::translation(0.03, 0.0, h + 0.01);
        poses[1] = t.released_pose(1, &beside);
        assert!(!t.success(&poses, None));
        assert!((poses[1].translation.vector.z - (-0.06 + h)).abs() < 1e-9);
    }

    /// The release report measures what the seating rule measures: just inside the hole's
    /// play seats and says so, just outside falls and says so, with the distance.
    #[test]
    fn the_release_report_says_how_far_off_the_spindle_the_roll_was_let_go() {
        let t = TaskInstance::sample(TaskKind::InstallToiletRoll(RollSize::Large), 4, -0.06);
        let h = RollSize::Large.half_height();
        // Off the axis along a diagonal of the fixture frame, 12 mm above the seat.
        let at = |r: f64| {
            t.base_from_fixture
                * Isometry3::translation(r * 0.6, r * 0.8, h + 0.012)
                * Isometry3::rotation(Vector3::x() * 3f64.to_radians())
        };
        let words = |r: f64| {
            let p = at(r);
            let rest = t.released_pose(1, &p);
            let seated = (rest.translation.vector - seated_centre(&t, h)).norm() < 1e-9;
            (t.describe_release(1, &p, &rest), seated)
        };
        let (inside, seated) = words(0.0079);
        assert!(seated);
        assert!(
            inside.starts_with("let go 7.9 mm from the spindle's axis (a roll goes over it within 8 mm), tilted 3°")
                && inside.contains("its bottom 12 mm above the seat")
                && inside.ends_with("it slid down onto the spindle"),
            "{inside}"
        );
        let (outside, seated) = words(0.0081);
        assert!(!seated);
        assert!(
            outside.starts_with("let go 8.1 mm") && outside.ends_with("it fell onto the table"),
            "{outside}"
        );
        // Too high above the spindle: centred, yet it falls, and the report says how high.
        let high = t.base_from_fixture * Isometry3::translation(0.0, 0.0, h + 0.04);
        let rest = t.released_pose(1, &high);
        let words = t.describe_release(1, &high, &rest);
        assert!(
            words.contains("0.0 mm") && words.contains("bottom 40 mm above the seat (-5 to 35)"),
            "{words}"
        );
        assert!(words.ends_with("it fell onto the table"), "{words}");
        // A bottom a hair below the seat prints as 0 mm, not "-0 mm".
        let low = t.base_from_fixture * Isometry3::translation(0.0, 0.0, h - 1e-6);
        let words = t.describe_release(1, &low, &t.released_pose(1, &low));
        assert!(words.contains("its bottom 0 mm above the seat"), "{words}");
        assert!(words.ends_with("it slid down onto the spindle"), "{words}");
        // The holder is not the roll: the generic report.
        let holder = t.bodies[0].base_from_body;
        assert!(t
            .describe_release(0, &holder, &holder)
            .starts_with("it fell 0 mm"));
    }
}
