//! Install toilet roll: a holder (a spindle on a base, on a pedestal) is posed by a seeded
//! SE(3) transform (x 0.42–0.60 m, 8–20 cm to one side of the base x axis, any yaw, tilt
//! ≤ 10°, lift ≤ 3 cm); the roll stands upright on the table on the other side (SE(2):
//! x 0.40–0.60 m, 8–20 cm to the other side, any yaw). The robot grasps the roll across
//! its outside (the expert up to 6 mm off its centre along the pads), carries it with the
//! roll's centre above the spindle, lowers it over the spindle along the holder's axis and
//! lets go. Variations: a large or a small roll.

use std::f64::consts::{FRAC_PI_2, FRAC_PI_4};
use std::fmt;

use cell_types::Keyframe;
use hil_sim::scene::Primitive;
use nalgebra::{Isometry3, Point3, Translation3, UnitQuaternion, Vector3};
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use serde::{Deserialize, Serialize};

use super::{
    angle_between, grasp_rotation, keyframe, keyframe_through, pedestal, rounded, sample_fixture,
    Body, BodyPart, ExpertPlan, GraspSite, TaskInstance, TaskKind, HALF_TURN,
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
/// Index of the roll among the task's bodies (the holder is 0).
pub const ROLL: usize = 1;
/// The expert's grasp turn is drawn from this stream of the task's seed.
const TURN_STREAM: u64 = 2;
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
            pedestal(PEDESTAL_HALF, PEDESTAL_HALF, 0.0, [120, 100, 80]),
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

/// The expert's turn of an executed grasp (rad) about the jaws' closing axis, within
/// ±`max_turn` ([`super::ExpertSettings::grasp_turn_deg`]); 0 when `max_turn` is 0.
pub fn expert_grasp_turn(task: &TaskInstance, max_turn: f64) -> f64 {
    if max_turn <= 0.0 {
        return 0.0;
    }
    let mut rng = ChaCha8Rng::seed_from_u64(task.seed);
    rng.set_stream(TURN_STREAM);
    rng.random_range(-max_turn..=max_turn)
}

/// Above the roll (open), around its top (close) at [`expert_grasp_offset`] along the pads,
/// lifted, the roll's centre above the spindle along the holder's axis, lowered over it and
/// let go, back up.
pub(crate) fn expert(task: &TaskInstance) -> Vec<Keyframe> {
    expert_turned(task, 0.0, false).executed
}

/// The expert's episode with its grasp executed turned by `turn` (rad) about the jaws'
/// closing axis, through the TCP, where the recorded grasp stays the clean one; the held roll
/// keeps the turn, and the keyframes after the grasp (recorded as executed) lift the TCP as
/// it is and place the roll's axis, not the TCP's, along the spindle. With `centred_labels`
/// the approach above the roll and the grasp are recorded as if the offset along the pads
/// were 0 ([`super::ExpertSettings::centred_grasp_labels`]). With `turn` 0 and no
/// `centred_labels` both lists are the plain expert's.
pub(crate) fn expert_turned(task: &TaskInstance, turn: f64, centred_labels: bool) -> ExpertPlan {
    let roll = task.bodies[ROLL].base_from_body;
    let h = match task.kind {
        TaskKind::InstallToiletRoll(s) => s.half_height(),
        _ => 0.0,
    };
    let axis = roll.rotation * Vector3::z();
    let r = grasp_rotation(-axis, roll.rotation * Vector3::x());
    let along = expert_grasp_offset(task);
    let grasp = roll.translation.vector + axis * (h - GRASP_BELOW_TOP) + r * Vector3::y() * along;
    let clean = Isometry3::from_parts(Translation3::from(grasp), r);
    // Turning about TCP x through the TCP keeps the grasp site centred across the jaws, so
    // the jaws do not slide the roll and it sits in the hand as here.
    let held = clean * Isometry3::rotation(Vector3::x() * turn);
    let tcp_from_roll = held.inverse() * roll;
    let fz = task.base_from_fixture.rotation * Vector3::z();
    let r_place = grasp_rotation(-fz, r * Vector3::x());
    // On the spindle the roll is turned as the clean grasp would place it.
    let roll_placed = r_place * (clean.inverse() * roll).rotation;
    // The TCP when the roll's bottom is `s` above the seat.
    let place = |s: f64| {
        let roll_at = Isometry3::from_parts(
            Translation3::from(seated_centre(task, h) + fz * s),
            roll_placed,
        );
        roll_at * tcp_from_roll.inverse()
    };
    let above = place(SPINDLE_HEIGHT + 0.03);
    let release = place(RELEASE_HEIGHT);
    let back_up = Translation3::from(fz * 0.10) * release;
    let lift = Translation3::new(0.0, 0.0, 0.15) * held;
    let at = |p: &Isometry3<f64>, open: bool| keyframe(p.translation.vector, p.rotation, open);
    let through =
        |p: &Isometry3<f64>, open: bool| keyframe_through(p.translation.vector, p.rotation, open);
    let executed = vec![
        keyframe(grasp + Vector3::z() * 0.10, r, true),
        at(&held, false),
        at(&lift, false),
        at(&above, false),
        // Down over the spindle and back up are planned without the cloud: the carried
        // roll's own points lie where the gripper goes.
        through(&release, true),
        through(&back_up, true),
    ];
    let mut recorded = executed.clone();
    recorded[1] = at(&clean, false);
    if centred_labels {
        let centred = grasp - r * Vector3::y() * along;
        recorded[0] = keyframe(centred + Vector3::z() * 0.10, r, true);
        recorded[1] = keyframe(centred, r, false);
    }
    ExpertPlan { recorded, executed }
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
    index == ROLL
        && (pose.translation.vector.z - (task.table_height + size.half_height())).abs() < 1e-3
}

/// How a roll let go relates to the holder's spindle (all in the fixture frame).
#[derive(Copy, Clone, Debug, PartialEq)]
struct OverSpindle {
    /// Distance of the roll's centre from the spindle's axis (m).
    radial: f64,
    /// Angle between the roll's axis and the spindle's (rad).
    tilt: f64,
    /// Height of the middle of the roll's bottom face above the holder's seat (m).
    bottom: f64,
    /// Where the spindle is relative to the roll's hole.
    fit: SpindleFit,
}

/// Where the spindle is relative to a released roll's hole.
#[derive(Copy, Clone, Debug, PartialEq)]
enum SpindleFit {
    /// The spindle reaches into the hole: the largest distance of the spindle's axis from the
    /// hole's axis over the length inside (m). Within the hole's play the roll slides down
    /// the spindle whatever its tilt (it straightens on the seat); beyond it the roll's wall
    /// cuts through the spindle, a state the carry can reach only because the held roll is
    /// not collision-checked against the holder (a real one would have hit the spindle).
    Around(f64),
    /// The roll is above the spindle's top: the distance of the spindle's tip from the
    /// hole's axis (m). The falling roll goes over the spindle when the tip is within the
    /// play and the roll is nearly upright.
    Above(f64),
    /// Neither: the roll lies on its side, or is below the seat.
    Away,
}

/// The hole's play around the spindle (m): the spindle fits in the hole while its axis
/// stays this close to the hole's.
const HOLE_PLAY: f64 = HOLE_RADIUS - SPINDLE_RADIUS;
/// Largest tilt of a roll falling onto the spindle from above that still goes over it.
const DROP_TILT_DEG: f64 = 15.0;
/// Half the side of the holder's square pedestal (m).
const PEDESTAL_HALF: f64 = 0.06;

impl OverSpindle {
    /// Measures a roll of `size` at `pose` against `task`'s holder.
    fn measure(task: &TaskInstance, size: RollSize, pose: &Isometry3<f64>) -> Self {
        let h = size.half_height();
        let local = task.base_from_fixture.inverse() * pose;
        let c = local.translation.vector;
        // A roll is the same either way up: take its axis pointing up the spindle.
        let mut a = local.rotation * Vector3::z();
        if a.z < 0.0 {
            a = -a;
        }
        let bottom = c - a * h;
        // Distance of the spindle's axis point at height z from the hole's axis.
        let off_axis = |z: f64| {
            let d = Vector3::new(0.0, 0.0, z) - c;
            (d - a * d.dot(&a)).norm()
        };
        // The spindle's axis (0, 0, z), z in [0, SPINDLE_HEIGHT], is inside the roll where
        // its position along the roll's axis is within ±h: z·a_z − c·a within ±h.
        // Leaning more than ~75° (a_z < 0.25), the roll is on its side: no hole to speak of.
        let fit = if a.z < 0.25 {
            SpindleFit::Away
        } else {
            let lo = ((c.dot(&a) - h) / a.z).max(0.0);
            let hi = ((c.dot(&a) + h) / a.z).min(SPINDLE_HEIGHT);
            if lo > SPINDLE_HEIGHT {
                SpindleFit::Above(off_axis(SPINDLE_HEIGHT))
            } else if lo <= hi && bottom.z > -0.005 {
                // Distance to a line is convex along a segment: the ends bound it.
                SpindleFit::Around(off_axis(lo).max(off_axis(hi)))
            } else {
                SpindleFit::Away
            }
        };
        Self {
            radial: c.x.hypot(c.y),
            tilt: angle_between(&a, &Vector3::z()),
            bottom: bottom.z,
            fit,
        }
    }

    /// Whether the roll ends on the spindle: around it within the play, or above it with
    /// the tip within the play and tilted less than [`DROP_TILT_DEG`].
    fn seats(&self) -> bool {
        match self.fit {
            SpindleFit::Around(off) => off < HOLE_PLAY,
            SpindleFit::Above(off) => off < HOLE_PLAY && self.tilt < DROP_TILT_DEG.to_radians(),
            SpindleFit::Away => false,
        }
    }
}

/// A released roll that [`OverSpindle::seats`] slides down onto the seat. One let go over
/// the holder that does not seat was driven into the spindle or against the pedestal (the
/// held roll is not collision-checked against the holder), or dropped onto the spindle's
/// tip: it falls off the holder, and the simulator lays it on its side on the table beside
/// the pedestal, where the task is lost ([`lost`]). Where it really lands (on the pedestal,
/// leaning on the spindle, upright or not) is not modelled; on its side is the conservative
/// choice, as no demonstration shows how to pick a roll up from there. A roll let go
/// elsewhere falls upright to the table below, where it can be grasped again.
///
/// Returns where the roll comes to rest and the measurements the decision was made on;
/// `None` for another body (the holder is never held).
pub(crate) fn released(
    task: &TaskInstance,
    size: RollSize,
    index: usize,
    pose: &Isometry3<f64>,
) -> Option<(Isometry3<f64>, RollRelease)> {
    if index != ROLL {
        return None;
    }
    let h = size.half_height();
    let x = pose.rotation * Vector3::x();
    let heading = UnitQuaternion::from_axis_angle(&Vector3::z_axis(), x.y.atan2(x.x));
    let c = pose.translation.vector;
    let m = OverSpindle::measure(task, size, pose);
    let landing = Landing::of(task, size, pose, &m);
    let rest = match landing {
        Landing::OnSpindle => {
            let local = task.base_from_fixture.inverse() * pose;
            let x = local.rotation * Vector3::x();
            let yaw = x.y.atan2(x.x);
            task.base_from_fixture
                * Isometry3::from_parts(
                    Translation3::new(0.0, 0.0, h),
                    UnitQuaternion::from_axis_angle(&Vector3::z_axis(), yaw),
                )
        }
        Landing::OnTheTable => {
            Isometry3::from_parts(Translation3::new(c.x, c.y, task.table_height + h), heading)
        }
        Landing::OffTheHolder => {
            let beside = off_the_holder(task, size, &c);
            Isometry3::from_parts(
                Translation3::new(beside.x, beside.y, task.table_height + size.radius()),
                heading * UnitQuaternion::from_axis_angle(&Vector3::x_axis(), FRAC_PI_2),
            )
        }
    };
    Some((rest, RollRelease::of(task, pose, &m, landing)))
}

/// Where a released roll ends up: the one decision the release acts on and
/// [`RollRelease`] reports.
#[derive(Copy, Clone, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum Landing {
    /// It slid down onto the spindle.
    OnSpindle,
    /// Over the holder but not onto the spindle: it falls off onto its side.
    OffTheHolder,
    /// Away from the holder: it falls upright to the table.
    OnTheTable,
}

impl Landing {
    /// Where a roll of `size` let go at `pose`, measured as `m`, ends up.
    fn of(task: &TaskInstance, size: RollSize, pose: &Isometry3<f64>, m: &OverSpindle) -> Self {
        if m.seats() {
            Landing::OnSpindle
        } else if over_pedestal(task, size.radius(), &pose.translation.vector) {
            Landing::OffTheHolder
        } else {
            Landing::OnTheTable
        }
    }

    /// The landing in words.
    fn words(self) -> &'static str {
        match self {
            Landing::OnSpindle => "it slid down onto the spindle",
            Landing::OffTheHolder => "it fell off the holder onto its side",
            Landing::OnTheTable => "it fell onto the table",
        }
    }
}

/// The roll lying on its side on the table (where [`released`] puts one that fell off the
/// holder) loses the task.
pub(crate) fn lost(
    task: &TaskInstance,
    size: RollSize,
    poses: &[Isometry3<f64>],
) -> Option<String> {
    let p = &poses[ROLL];
    let on_side = (p.translation.vector.z - (task.table_height + size.radius())).abs() < 1e-6
        && angle_between(&(p.rotation * Vector3::z()), &Vector3::z()) > FRAC_PI_4;
    on_side.then(|| {
        format!(
            "the {} fell off the holder onto its side; no demonstration shows how to pick it \
             up from there",
            task.bodies[ROLL].name
        )
    })
}

/// Whether a disc of `radius` centred at `centre` (base frame, any height) overlaps the
/// holder's pedestal seen from above (in the fixture's plane).
fn over_pedestal(task: &TaskInstance, radius: f64, centre: &Vector3<f64>) -> bool {
    let c = task.base_from_fixture.inverse() * Point3::from(*centre);
    // Distance from the disc's centre to the square.
    let dx = (c.x.abs() - PEDESTAL_HALF).max(0.0);
    let dy = (c.y.abs() - PEDESTAL_HALF).max(0.0);
    dx.hypot(dy) < radius
}

/// Where a roll falling off the holder at `centre` (base frame) comes down on its side:
/// moved away from the spindle's axis (in the fixture's plane) until a disc covering the
/// lying roll (its half-length and radius) clears the pedestal.
fn off_the_holder(task: &TaskInstance, size: RollSize, centre: &Vector3<f64>) -> Vector3<f64> {
    let lying = size.radius().hypot(size.half_height());
    let f = &task.base_from_fixture;
    let local = f.inverse() * Point3::from(*centre);
    let mut away = Vector3::new(local.x, local.y, 0.0);
    if away.norm() < 1e-6 {
        away = Vector3::x();
    }
    let away = away.normalize();
    // Outward in millimetre steps. A disc centred beyond the pedestal's half-diagonal plus
    // its radius is clear, which bounds the walk (~140 steps), also for a non-finite pose.
    let limit = PEDESTAL_HALF * std::f64::consts::SQRT_2 + lying;
    let mut r = local.x.hypot(local.y);
    while r < limit {
        r += 0.001;
        let p = f * Point3::from(away * r);
        if !over_pedestal(task, lying, &p.coords) {
            return p.coords;
        }
    }
    (f * Point3::from(away * limit)).coords
}

/// A roll let go, measured: what an episode's log keeps of each release (`episodes.jsonl`),
/// so that a run's releases can be counted against how the roll was held (`equact eval
/// report`) without parsing its words. Its [`Display`](fmt::Display) is the words.
/// Lengths in millimetres, angles in degrees, unrounded.
#[derive(Copy, Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct RollRelease {
    /// Distance of the roll's centre from the spindle's axis (mm).
    pub off_axis_mm: f64,
    /// Angle between the roll's axis and the spindle's (°).
    pub tilt_deg: f64,
    /// The roll's lean from the vertical (°).
    pub roll_lean_deg: f64,
    /// The spindle's lean from the vertical (°): a roll let go upright over a leaning
    /// holder is tilted from the spindle by the holder's lean.
    pub spindle_lean_deg: f64,
    /// Height of the middle of the roll's bottom face above the holder's seat (mm).
    pub bottom_mm: f64,
    /// Where the spindle was relative to the roll's hole.
    pub fit: HoleFit,
    /// Where the roll came to rest.
    pub landing: Landing,
}

/// Where the spindle was relative to a released roll's hole, against the hole's play
/// ([`HOLE_PLAY_MM`]).
#[derive(Copy, Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(tag = "kind", rename_all = "snake_case")]
pub enum HoleFit {
    /// The spindle reaches into the hole, its axis at most `off_mm` from the hole's: within
    /// the play the roll slides down it; beyond, the roll's wall cuts through the spindle
    /// (the held roll was carried into it).
    Inside {
        /// Largest distance of the spindle's axis from the hole's over the length inside (mm).
        off_mm: f64,
    },
    /// The roll is above the spindle's tip.
    Above {
        /// Distance of the spindle's tip from the hole's axis (mm).
        off_mm: f64,
    },
    /// The hole is not around the spindle (the roll on its side, or below the seat).
    Away,
}

/// The hole's play around the spindle in millimetres, as reports give it.
pub const HOLE_PLAY_MM: f64 = HOLE_PLAY * 1e3;

impl RollRelease {
    /// The report of a roll let go at `pose`, measured as `m`, that ended up at `landing`.
    fn of(task: &TaskInstance, pose: &Isometry3<f64>, m: &OverSpindle, landing: Landing) -> Self {
        let up = Vector3::z();
        let lean = |axis: Vector3<f64>| angle_between(&axis, &up).min(angle_between(&-axis, &up));
        let fit = match m.fit {
            SpindleFit::Around(off) => HoleFit::Inside { off_mm: off * 1e3 },
            SpindleFit::Above(off) => HoleFit::Above { off_mm: off * 1e3 },
            SpindleFit::Away => HoleFit::Away,
        };
        Self {
            off_axis_mm: m.radial * 1e3,
            tilt_deg: m.tilt.to_degrees(),
            roll_lean_deg: lean(pose.rotation * up).to_degrees(),
            spindle_lean_deg: lean(task.base_from_fixture.rotation * up).to_degrees(),
            bottom_mm: m.bottom * 1e3,
            fit,
            landing,
        }
    }
}

impl fmt::Display for RollRelease {
    /// How far from the spindle's axis, its tilt and height, how the spindle sits in its hole
    /// against the hole's play, and where the roll went.
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        let play = HOLE_PLAY_MM.round();
        write!(
            f,
            "let go {:.1} mm from the spindle's axis, tilted {:.0}° from it (the roll {:.0}° from \
             the vertical, the spindle {:.0}°), its bottom {:.0} mm above the seat, ",
            rounded(self.off_axis_mm, 1),
            self.tilt_deg,
            self.roll_lean_deg,
            self.spindle_lean_deg,
            rounded(self.bottom_mm, 0),
        )?;
        match self.fit {
            HoleFit::Inside { off_mm } if off_mm < HOLE_PLAY_MM => write!(
                f,
                "the spindle in its hole, at most {:.1} mm off the hole's axis (fits within \
                 {play:.0} mm)",
                rounded(off_mm, 1)
            )?,
            HoleFit::Inside { off_mm } => write!(
                f,
                "the spindle cutting through its wall, {:.1} mm off the hole's axis (fits within \
                 {play:.0} mm; the held roll was carried into the spindle)",
                rounded(off_mm, 1)
            )?,
            HoleFit::Above { off_mm } => write!(
                f,
                "above the spindle, its tip {:.1} mm off the hole's axis (a falling roll goes over \
                 it within {play:.0} mm, tilted less than {DROP_TILT_DEG:.0}°)",
                rounded(off_mm, 1)
            )?,
            HoleFit::Away => write!(f, "its hole not around the spindle")?,
        }
        write!(f, "; {}", self.landing.words())
    }
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
    fn centred_grasp_labels_record_the_grasp_on_the_axis_and_execute_the_offset_one() {
        use crate::task::world::{GripperEvent, TaskWorld};
        use crate::task::ExpertSettings;
        let settings = ExpertSettings {
            centred_grasp_labels: true,
            ..ExpertSettings::default()
        };
        for seed in 0..20 {
            let size = RollSize::ALL[seed as usize % 2];
            let t = TaskInstance::sample(TaskKind::InstallToiletRoll(size), seed, -0.06);
            let plain = t.expert_plan(&ExpertSettings::default());
            let plan = t.expert_plan(&settings);
            // The arm does what the plain expert does; only the approach's and the grasp's
            // labels change, and the later labels place the roll the offset grasp carries.
            assert_eq!(plan.executed, plain.executed);
            for i in 0..plan.executed.len() {
                assert_eq!(
                    plan.recorded[i] == plan.executed[i],
                    i > 1,
                    "seed {seed} step {i}"
                );
            }
            let pose = |k: &[Keyframe], i: usize| *k[i].base_from_tcp.isometry();
            let along = expert_grasp_offset(&t);
            let axis_point = Point3::from(t.bodies[ROLL].base_from_body.translation.vector);
            for i in [0, 1] {
                // The label sits on the roll's axis, the executed keyframe `along` off it,
                // in the same orientation and open state.
                let (label, done) = (pose(&plan.recorded, i), pose(&plan.executed, i));
                assert_eq!(plan.recorded[i].gripper_open, plan.executed[i].gripper_open);
                assert!(label.rotation.angle_to(&done.rotation) < 1e-12);
                let local = label.inverse() * axis_point;
                assert!(
                    local.x.hypot(local.y) < 1e-9,
                    "seed {seed} step {i}: {local:?}"
                );
                let shift = done.inverse() * Point3::from(label.translation.vector);
                assert!(
                    (shift.y + along).abs() < 1e-9 && shift.x.abs() < 1e-9,
                    "{shift:?}"
                );
            }
            // Executing the label would grasp the roll centred along the pads.
            let label = pose(&plan.recorded, 1);
            let mut w = TaskWorld::new(t.clone());
            assert!(w.before_close(&label).is_some());
            let Some(GripperEvent::Grasped { site_in_tcp, .. }) = w.after_gripper(&label, true)
            else {
                panic!("seed {seed}: no grasp")
            };
            assert!(site_in_tcp.y.abs() < 1e-9, "seed {seed}: {site_in_tcp:?}");
        }
    }

    #[test]
    fn a_turned_grasp_is_executed_the_clean_one_recorded_and_the_roll_still_seats() {
        use crate::task::world::{GripperEvent, TaskWorld};
        use crate::task::ExpertSettings;
        let settings = ExpertSettings {
            grasp_turn_deg: 12.0,
            ..ExpertSettings::default()
        };
        let mut turns = Vec::new();
        for seed in 0..40 {
            let size = RollSize::ALL[seed as usize % 2];
            let t = TaskInstance::sample(TaskKind::InstallToiletRoll(size), seed, -0.06);
            // The plain expert is the plan with no turn, recorded as executed.
            let plain = t.expert_plan(&ExpertSettings::default());
            assert_eq!(plain.recorded, plain.executed);
            assert_eq!(plain.executed, t.expert_keyframes());
            let turn = expert_grasp_turn(&t, 12f64.to_radians());
            assert_eq!(
                turn,
                expert_grasp_turn(&t, 12f64.to_radians()),
                "drawn from the seed"
            );
            assert!(turn.abs() <= 12f64.to_radians());
            turns.push(turn);
            let plan = t.expert_plan(&settings);
            let pose = |k: &[Keyframe], i: usize| *k[i].base_from_tcp.isometry();
            // Only the grasp's label differs from what is executed: the clean grasp, turned
            // about its own x through the TCP.
            for i in 0..plan.executed.len() {
                assert_eq!(plan.recorded[i] == plan.executed[i], i != 1 || turn == 0.0);
            }
            assert_eq!(plan.recorded[1], plain.executed[1]);
            let (clean, held) = (pose(&plan.recorded, 1), pose(&plan.executed, 1));
            let d = clean.inverse() * held;
            assert!(d.translation.vector.norm() < 1e-9);
            assert!((d.rotation.scaled_axis() - Vector3::x() * turn).norm() < 1e-9);
            // Executed: the grasp leaves the turn in the hand ...
            let mut w = TaskWorld::new(t.clone());
            assert!(w.before_close(&held).is_some());
            let Some(GripperEvent::Grasped {
                axis_tilt: Some(tilt),
                ..
            }) = w.after_gripper(&held, true)
            else {
                panic!("seed {seed}: no grasp")
            };
            assert!((tilt.about_closing_deg - turn.abs().to_degrees()).abs() < 1e-6);
            assert!(tilt.about_pads_deg < 1e-6);
            // ... and the release holds the roll's axis along the spindle's, its centre on it.
            let release = pose(&plan.executed, 4);
            w.carry(&release);
            let on_holder = t.base_from_fixture.inverse() * w.poses()[ROLL];
            let c = on_holder.translation.vector;
            assert!(c.x.hypot(c.y) < 1e-6, "seed {seed}: {c:?} off the axis");
            assert!((c.z - size.half_height() - RELEASE_HEIGHT).abs() < 1e-6);
            assert!((on_holder.rotation * Vector3::z()).angle(&Vector3::z()) < 1e-9);
            w.after_gripper(&release, false);
            assert!(w.success(), "seed {seed}");
        }
        let (lo, hi) = turns
            .iter()
            .fold((f64::MAX, f64::MIN), |(lo, hi), &v| (lo.min(v), hi.max(v)));
        assert!(lo < -0.1 && hi > 0.1, "{turns:?}");
    }

    #[test]
    fn a_roll_let_go_over_the_spindle_seats_and_elsewhere_falls() {
        let t = TaskInstance::sample(TaskKind::InstallToiletRoll(RollSize::Small), 7, -0.06);
        let h = RollSize::Small.half_height();
        let over = t.base_from_fixture * Isometry3::translation(0.002, 0.0, h + 0.01);
        let seated = t.release(1, &over).0;
        let mut poses: Vec<_> = t.bodies.iter().map(|b| b.base_from_body).collect();
        assert!(!t.success(&poses, None));
        poses[1] = seated;
        assert!(t.success(&poses, None));
        assert!(!t.success(&poses, Some(1)));
        let beside = t.base_from_fixture * Isometry3::translation(0.03, 0.0, h + 0.01);
        poses[1] = t.release(1, &beside).0;
        assert!(!t.success(&poses, None));
        // Off the holder, on its side.
        let r = RollSize::Small.radius();
        assert!((poses[1].translation.vector.z - (-0.06 + r)).abs() < 1e-9);
    }

    /// A roll of `size` whose hole's axis passes through the spindle's axis point at height
    /// `z` (fixture frame) `off` to the side (fixture y), tilted `tilt_deg` about the fixture
    /// x, its bottom face `above` along its axis beyond that point (negative: the point is
    /// inside the roll); in the base frame.
    fn roll_at(
        t: &TaskInstance,
        size: RollSize,
        z: f64,
        off: f64,
        tilt_deg: f64,
        above: f64,
    ) -> Isometry3<f64> {
        let r = UnitQuaternion::from_axis_angle(&Vector3::x_axis(), tilt_deg.to_radians());
        let a = r * Vector3::z();
        let c = Vector3::new(0.0, off, z) + a * (size.half_height() + above);
        t.base_from_fixture * Isometry3::from_parts(Translation3::from(c), r)
    }

    /// Released, then: its words, and whether it sits on the spindle.
    fn release(t: &TaskInstance, size: RollSize, pose: &Isometry3<f64>) -> (String, bool) {
        let (rest, outcome) = t.release(1, pose);
        let seated = (rest.translation.vector - seated_centre(t, size.half_height())).norm() < 1e-9;
        let words = outcome.to_string();
        assert_eq!(
            seated,
            words.ends_with("it slid down onto the spindle"),
            "{words}"
        );
        (words, seated)
    }

    /// The rule is the hole's fit around the spindle: upright, the spindle inside the hole
    /// within the play seats and just beyond it does not, and the report says which and by
    /// how much.
    #[test]
    fn an_upright_roll_seats_within_the_holes_play_and_the_report_says_how_far_off_it_was() {
        let size = RollSize::Large;
        let t = TaskInstance::sample(TaskKind::InstallToiletRoll(size), 4, -0.06);
        let lean = angle_between(
            &(t.base_from_fixture.rotation * Vector3::z()),
            &Vector3::z(),
        )
        .to_degrees();
        assert!(lean > 2.0, "seed 4's holder leans {lean}°");
        // 12 mm above the seat, off the axis along the fixture's y.
        let (inside, seated) = release(&t, size, &roll_at(&t, size, 0.0, 0.0079, 0.0, 0.012));
        assert!(seated);
        assert_eq!(
            inside,
            format!(
                "let go 7.9 mm from the spindle's axis, tilted 0° from it (the roll {lean:.0}° \
                 from the vertical, the spindle {lean:.0}°), its bottom 12 mm above the seat, \
                 the spindle in its hole, at most 7.9 mm off the hole's axis (fits within 8 mm); \
                 it slid down onto the spindle"
            )
        );
        let (outside, seated) = release(&t, size, &roll_at(&t, size, 0.0, 0.0081, 0.0, 0.012));
        assert!(!seated);
        assert!(
            outside.starts_with("let go 8.1 mm")
                && outside.contains("the spindle cutting through its wall, 8.1 mm off")
                && outside.ends_with("it fell off the holder onto its side"),
            "{outside}"
        );
        // Upright over the leaning holder: tilted from the spindle by the holder's lean.
        let centre = t.base_from_fixture * Point3::new(0.0, 0.0, size.half_height() + 0.012);
        let upright = Isometry3::from_parts(
            Translation3::from(centre.coords),
            UnitQuaternion::identity(),
        );
        let (words, _) = release(&t, size, &upright);
        assert!(
            words.contains(&format!(
                "tilted {lean:.0}° from it (the roll 0° from the vertical, the spindle {lean:.0}°)"
            )),
            "{words}"
        );
        // A bottom a hair below the seat prints as 0 mm, not "-0 mm".
        let (words, seated) = release(&t, size, &roll_at(&t, size, 0.0, 0.0, 0.0, -1e-6));
        assert!(
            seated && words.contains("its bottom 0 mm above the seat"),
            "{words}"
        );
        // Lying on its side: its hole is nowhere near the spindle.
        let (words, seated) = release(&t, size, &roll_at(&t, size, 0.02, 0.0, 90.0, 0.0));
        assert!(
            !seated && words.contains("its hole not around the spindle"),
            "{words}"
        );
    }

    /// Tilt matters through the fit, not by itself: tilted 20°, a roll around the spindle's
    /// top few millimetres is within the play and slides down; the same tilt with the
    /// spindle deep in the hole puts the spindle's foot through the roll's wall.
    #[test]
    fn a_tilted_roll_seats_when_the_spindle_fits_in_its_hole() {
        let size = RollSize::Small;
        let t = TaskInstance::sample(TaskKind::InstallToiletRoll(size), 9, -0.06);
        // The hole's axis through the spindle's axis 2 mm below its tip, the roll's bottom 3
        // mm below that: about 5 mm of spindle inside.
        let shallow = roll_at(&t, size, SPINDLE_HEIGHT - 0.002, 0.0, 20.0, -0.003);
        let (words, seated) = release(&t, size, &shallow);
        assert!(seated, "{words}");
        assert!(
            words.contains("tilted 20° from it")
                && words.contains("its bottom 30 mm above the seat")
                && words.contains("at most 1.1 mm off the hole's axis"),
            "{words}"
        );
        // The same tilt, the roll's bottom 5 mm above the seat and its centre on the axis:
        // the spindle's foot is ~10 mm off the hole's axis.
        let deep = t.base_from_fixture
            * Isometry3::from_parts(
                Translation3::new(
                    0.0,
                    0.0,
                    0.005 + size.half_height() * 20f64.to_radians().cos(),
                ),
                UnitQuaternion::from_axis_angle(&Vector3::x_axis(), 20f64.to_radians()),
            );
        let (words, seated) = release(&t, size, &deep);
        assert!(!seated, "{words}");
        assert!(
            words.contains("the spindle cutting through its wall"),
            "{words}"
        );
    }

    /// Let go above the spindle: upright with the tip under the hole it falls over the
    /// spindle; tilted past 15°, or with the tip under its wall, it falls off the holder onto
    /// its side.
    #[test]
    fn a_roll_let_go_above_the_spindle_falls_over_it_only_upright_and_centred() {
        let size = RollSize::Large;
        let t = TaskInstance::sample(TaskKind::InstallToiletRoll(size), 2, -0.06);
        let (words, seated) = release(
            &t,
            size,
            &roll_at(&t, size, SPINDLE_HEIGHT, 0.003, 5.0, 0.02),
        );
        assert!(seated, "{words}");
        assert!(
            words.contains("above the spindle, its tip 3.0 mm off the hole's axis"),
            "{words}"
        );
        let (words, seated) = release(
            &t,
            size,
            &roll_at(&t, size, SPINDLE_HEIGHT, 0.003, 20.0, 0.02),
        );
        assert!(!seated, "{words}");
        let (words, seated) = release(
            &t,
            size,
            &roll_at(&t, size, SPINDLE_HEIGHT, 0.009, 0.0, 0.02),
        );
        assert!(!seated, "{words}");
        assert!(
            words.ends_with("it fell off the holder onto its side"),
            "{words}"
        );
    }

    /// A roll that does not seat over the holder never ends inside it: it lies on its side
    /// beside the pedestal, which loses the task, and the success test cannot take it for
    /// seated even on a holder whose seat is at the table's height.
    #[test]
    fn a_roll_falling_off_the_holder_lies_beside_it_and_loses_the_task() {
        let size = RollSize::Small;
        let lying = size.radius().hypot(size.half_height());
        for seed in 0..20 {
            let mut t = TaskInstance::sample(TaskKind::InstallToiletRoll(size), seed, -0.06);
            // The seat at the table's height, level: the worst case for a false success.
            let f = &mut t.base_from_fixture;
            f.translation.vector.z = t.table_height;
            f.rotation = UnitQuaternion::from_axis_angle(&Vector3::z_axis(), 0.3 * seed as f64);
            let tilted = roll_at(&t, size, 0.0, 0.001, 24.0, 0.005);
            let (words, seated) = release(&t, size, &tilted);
            assert!(!seated && words.ends_with("it fell off the holder onto its side"));
            let rest = t.release(1, &tilted).0;
            let mut poses: Vec<_> = t.bodies.iter().map(|b| b.base_from_body).collect();
            assert_eq!(t.lost(&poses), None, "seed {seed}: the roll as posed");
            poses[1] = rest;
            assert!(!t.success(&poses, None), "seed {seed}");
            let why = t.lost(&poses).unwrap();
            assert!(
                why.contains("small toilet roll fell off the holder"),
                "{why}"
            );
            // On its side, on the table, just clear of the pedestal (within a millimetre
            // step of touching it).
            let axis = rest.rotation * Vector3::z();
            assert!(axis.z.abs() < 1e-9, "seed {seed}: {axis}");
            assert!((rest.translation.z - (t.table_height + size.radius())).abs() < 1e-12);
            assert!(!over_pedestal(&t, lying, &rest.translation.vector));
            let local = t.base_from_fixture.inverse() * Point3::from(rest.translation.vector);
            let gap = (local.x.abs() - PEDESTAL_HALF)
                .max(0.0)
                .hypot((local.y.abs() - PEDESTAL_HALF).max(0.0));
            assert!(gap - lying < 0.0011, "seed {seed}: {gap}");
            assert!(!t.stands_free(1, &rest), "seed {seed}");
        }
        // A non-finite pose (a broken TCP) ends the walk off the holder rather than hanging.
        let t = TaskInstance::sample(TaskKind::InstallToiletRoll(size), 0, -0.06);
        let broken = Isometry3::translation(f64::NAN, 0.0, 0.0);
        assert!(t.release(1, &broken).0.translation.x.is_nan());
        // Let go well away from the holder, it lands upright where it was, to be grasped
        // again: not lost.
        let t = TaskInstance::sample(TaskKind::InstallToiletRoll(size), 1, -0.06);
        let far = t.bodies[1].base_from_body * Isometry3::translation(0.0, 0.0, 0.05);
        let (rest, outcome) = t.release(1, &far);
        assert!(
            (rest.translation.vector - t.bodies[1].base_from_body.translation.vector).norm()
                < 1e-12
        );
        assert!(t.stands_free(1, &rest));
        assert_eq!(t.lost(&[t.bodies[0].base_from_body, rest]), None);
        assert!(outcome.to_string().ends_with("; it fell onto the table"));
        assert!(
            matches!(outcome, crate::task::ReleaseOutcome::Roll(r) if r.landing == Landing::OnTheTable),
            "{outcome:?}"
        );
    }
}
