//! The task's world truth, independent of the cameras and the controller: where each body
//! is, which one the gripper holds, and the grasp attachment rules. The simulated cell
//! ([`crate::sim_cell::SimWorld`]) renders it; the kinematic check ([`super::check`]) uses
//! it without rendering.

use std::fmt;

use nalgebra::{Isometry3, Point3, Translation3, Vector3};
use serde::{Deserialize, Serialize};

use super::{angle_between, rounded_mm, GraspSite, ReleaseOutcome, TaskInstance};

/// Grasp distance: a body is caught when its grasp site is this close to the TCP as the
/// fingers close (m).
pub const GRASP_RADIUS: f64 = 0.03;

/// What a gripper motion did to a body: what an episode's log says after the step, so that a
/// failed episode shows how it failed (a roll grasped far off-centre, let go beside the
/// spindle) without a debugger. Its [`Display`](fmt::Display) is the words; serialised, the
/// measurements (`episodes.jsonl`'s `gripper_measures`).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(tag = "event", rename_all = "snake_case")]
pub enum GripperEvent {
    /// Closing fingers caught a body.
    Grasped {
        /// The body's name.
        body: String,
        /// Its grasp site in the TCP frame once the jaws closed (m): x across the jaws,
        /// y along the pads, z along the approach.
        #[serde(rename = "site_in_tcp_m")]
        site_in_tcp: Vector3<f64>,
        /// For a body the expert holds with an axis against the approach (a roll), how far
        /// that axis is turned from it in the hand ([`AxisTilt`]): a tilted grasp stays in
        /// the hand and tilts the body wherever it is carried.
        axis_tilt: Option<AxisTilt>,
    },
    /// Opening fingers let a body go.
    Released {
        /// The body's name.
        body: String,
        /// Where it was let go and where it came to rest ([`TaskInstance::release`]).
        outcome: ReleaseOutcome,
    },
}

/// How far a held body's axis is turned from the way the expert holds it (against the TCP's
/// approach, z), in degrees: in all, and its parts about the jaws' closing axis (TCP x: a
/// turn in the pads' plane, which the jaws keep) and about the pads' axis (TCP y).
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct AxisTilt {
    /// Angle between the body's axis and the reversed approach (°).
    pub total_deg: f64,
    /// Its part about the jaws' closing axis (°, unsigned).
    pub about_closing_deg: f64,
    /// Its part about the pads' axis (°, unsigned).
    pub about_pads_deg: f64,
}

impl AxisTilt {
    /// The tilt of `axis_in_tcp` (a body axis, in the TCP frame) from −z.
    pub fn of(axis_in_tcp: &Vector3<f64>) -> Option<Self> {
        let u = -axis_in_tcp.try_normalize(1e-12)?;
        Some(Self {
            total_deg: angle_between(&u, &Vector3::z()).to_degrees(),
            about_closing_deg: u.y.atan2(u.z).abs().to_degrees(),
            about_pads_deg: u.x.atan2(u.z).abs().to_degrees(),
        })
    }
}

impl fmt::Display for GripperEvent {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self {
            GripperEvent::Grasped {
                body,
                site_in_tcp,
                axis_tilt,
            } => {
                let mm = site_in_tcp.map(|v| rounded_mm(v, 0));
                write!(
                    f,
                    "grasped the {body}, its grasp site {:+.0} mm along the pads, {:+.0} mm across \
                     the jaws, {:+.0} mm along the approach from the TCP",
                    mm.y, mm.x, mm.z
                )?;
                if let Some(t) = axis_tilt {
                    write!(
                        f,
                        ", its axis {:.0}° off the approach ({:.0}° about the jaws' closing \
                         axis, {:.0}° about the pads' axis)",
                        t.total_deg, t.about_closing_deg, t.about_pads_deg
                    )?;
                }
                Ok(())
            }
            GripperEvent::Released { body, outcome } => write!(f, "released the {body}: {outcome}"),
        }
    }
}

/// The bodies' poses and the grasp attachment of one posed task.
#[derive(Clone, Debug)]
pub struct TaskWorld {
    /// The task.
    pub task: TaskInstance,
    poses: Vec<Isometry3<f64>>,
    held: Option<(usize, Isometry3<f64>)>,
    between_fingers: Option<usize>,
}

impl TaskWorld {
    /// The task's bodies where the task posed them, nothing held.
    pub fn new(task: TaskInstance) -> Self {
        let poses = task.bodies.iter().map(|b| b.base_from_body).collect();
        Self {
            task,
            poses,
            held: None,
            between_fingers: None,
        }
    }

    /// Every body's pose now (the order of [`TaskInstance::bodies`]).
    pub fn poses(&self) -> &[Isometry3<f64>] {
        &self.poses
    }

    /// The body the gripper holds.
    pub fn held(&self) -> Option<usize> {
        self.held.map(|h| h.0)
    }

    /// The task's success test on the current state.
    pub fn success(&self) -> bool {
        self.task.success(&self.poses, self.held())
    }

    /// Why the task can no longer succeed ([`TaskInstance::lost`]).
    pub fn lost(&self) -> Option<String> {
        self.task.lost(&self.poses)
    }

    /// Before the fingers close with the TCP at `base_from_tcp`: the width of the graspable
    /// body between them (the nearest grasp site within [`GRASP_RADIUS`]), or `None`.
    pub fn before_close(&mut self, base_from_tcp: &Isometry3<f64>) -> Option<f64> {
        let tcp = base_from_tcp.translation.vector;
        let mut best: Option<(usize, f64, f64)> = None;
        for (i, body) in self.task.bodies.iter().enumerate() {
            let Some(site) = body.grasp else { continue };
            if self.held() == Some(i) {
                continue;
            }
            let p = self.poses[i] * Point3::from(site.point);
            let d = (p.coords - tcp).norm();
            if d <= GRASP_RADIUS && best.is_none_or(|b| d < b.1) {
                best = Some((i, d, site.width));
            }
        }
        self.between_fingers = best.map(|b| b.0);
        best.map(|b| b.2)
    }

    /// After a gripper motion with the TCP at `base_from_tcp`: closed fingers on the body
    /// found by [`TaskWorld::before_close`] carry it; opening releases the held body, which
    /// comes to rest where the task says. Returns what happened to a body, if anything.
    pub fn after_gripper(
        &mut self,
        base_from_tcp: &Isometry3<f64>,
        holding: bool,
    ) -> Option<GripperEvent> {
        if holding && self.held.is_none() {
            let i = self.between_fingers.take()?;
            let site = self.task.bodies[i].grasp?;
            if self.task.stands_free(i, &self.poses[i]) {
                self.poses[i] = slid_between_jaws(base_from_tcp, &self.poses[i], &site);
            }
            let tcp_from_body = base_from_tcp.inverse() * self.poses[i];
            self.held = Some((i, tcp_from_body));
            Some(GripperEvent::Grasped {
                body: self.task.bodies[i].name.clone(),
                site_in_tcp: (tcp_from_body * Point3::from(site.point)).coords,
                axis_tilt: self
                    .task
                    .held_axis(i)
                    .and_then(|a| AxisTilt::of(&(tcp_from_body.rotation * a))),
            })
        } else if !holding {
            self.between_fingers = None;
            let (i, _) = self.held.take()?;
            let (rest, outcome) = self.task.release(i, &self.poses[i]);
            self.poses[i] = rest;
            Some(GripperEvent::Released {
                body: self.task.bodies[i].name.clone(),
                outcome,
            })
        } else {
            None
        }
    }

    /// Moves the held body with the TCP.
    pub fn carry(&mut self, base_from_tcp: &Isometry3<f64>) {
        if let Some((i, tcp_from_body)) = self.held {
            self.poses[i] = base_from_tcp * tcp_from_body;
        }
    }
}

/// Where a body standing free on the table ends when parallel jaws close on it off-centre:
/// the first finger to touch slides it horizontally over the table until its grasp site
/// lies midway between the jaws along the closing axis (TCP x), as a real 2F-85 does with a
/// fruit or a roll; with level jaws its offset along the pads and in height stays as it was.
/// Jaws closing more steeply than 45° push into the table instead, and leave the body where
/// it is.
fn slid_between_jaws(
    base_from_tcp: &Isometry3<f64>,
    pose: &Isometry3<f64>,
    site: &GraspSite,
) -> Isometry3<f64> {
    let across = base_from_tcp.rotation * Vector3::x();
    let flat = Vector3::new(across.x, across.y, 0.0);
    // flat · across = |flat|²: moving by −off/|flat|² along `flat` cancels the offset along
    // `across`.
    let level = flat.norm_squared();
    if level < 0.5 {
        return *pose;
    }
    let site_in_base = pose * Point3::from(site.point);
    let off = (site_in_base.coords - base_from_tcp.translation.vector).dot(&across);
    Isometry3::from_parts(
        Translation3::from(pose.translation.vector - flat * (off / level)),
        pose.rotation,
    )
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::task::{Fruit, PipePart, RollSize, TaskKind};

    /// The grasp site of body `i` in the TCP frame at `base_from_tcp`.
    fn site_in_tcp(w: &TaskWorld, i: usize, base_from_tcp: &Isometry3<f64>) -> Vector3<f64> {
        let site = w.task.bodies[i].grasp.unwrap().point;
        (base_from_tcp.inverse() * w.poses()[i] * Point3::from(site)).coords
    }

    /// The expert's first closing keyframe of `task`, moved by `offset` in its TCP frame.
    fn off_centre_grasp(task: &TaskInstance, offset: Vector3<f64>) -> Isometry3<f64> {
        let grasp = task
            .expert_keyframes()
            .into_iter()
            .find(|k| !k.gripper_open)
            .unwrap();
        grasp.base_from_tcp.isometry() * Isometry3::translation(offset.x, offset.y, offset.z)
    }

    #[test]
    fn closing_jaws_centre_a_standing_roll_along_their_axis_only() {
        let task = TaskInstance::sample(TaskKind::InstallToiletRoll(RollSize::Small), 7, -0.06);
        let at = off_centre_grasp(&task, Vector3::new(0.008, 0.005, 0.002));
        let mut w = TaskWorld::new(task.clone());
        let before = site_in_tcp(&w, 1, &at);
        // The expert's own grasp is off-centre along the pads by its drawn offset.
        let along = crate::task::toilet_roll::expert_grasp_offset(&task);
        assert!((before - Vector3::new(-0.008, -0.005 - along, -0.002)).norm() < 1e-9);
        assert!(w.before_close(&at).is_some());
        let event = w.after_gripper(&at, true);
        assert_eq!(w.held(), Some(1));
        // Centred across the jaws; the offset along the pads and in height stays.
        let after = site_in_tcp(&w, 1, &at);
        assert!(after.x.abs() < 1e-9, "{after}");
        // The event reports where in the hand the roll is held.
        let Some(GripperEvent::Grasped {
            body,
            site_in_tcp: held_at,
            axis_tilt,
        }) = &event
        else {
            panic!("{event:?}")
        };
        assert_eq!(body, "small toilet roll");
        assert!((held_at - after).norm() < 1e-12);
        // The expert's rotation holds the roll's axis against the approach.
        assert!(
            axis_tilt.is_some_and(|t| t.total_deg < 1e-6),
            "{axis_tilt:?}"
        );
        let words = event.unwrap().to_string();
        let mm = after * 1e3;
        assert_eq!(
            words,
            format!(
                "grasped the small toilet roll, its grasp site {:+.0} mm along the pads, +0 mm \
                 across the jaws, -2 mm along the approach from the TCP, its axis 0° off the \
                 approach (0° about the jaws' closing axis, 0° about the pads' axis)",
                mm.y
            )
        );
        assert!(mm.y < -4.0, "{mm}: the 5 mm offset along the pads shows");
        assert!(
            (after.yz() - before.yz()).norm() < 1e-9,
            "{after} vs {before}"
        );
        // Slid over the table, not lifted or turned.
        let (was, now) = (task.bodies[1].base_from_body, w.poses()[1]);
        assert!((now.translation.z - was.translation.z).abs() < 1e-12);
        assert!(now.rotation.angle_to(&was.rotation) < 1e-12);
        assert!(((now.translation.vector - was.translation.vector).norm() - 0.008).abs() < 1e-9);
        // Carried with the centred offset.
        let up = Isometry3::translation(0.0, 0.0, 0.1) * at;
        w.carry(&up);
        assert!((site_in_tcp(&w, 1, &up) - after).norm() < 1e-9);
    }

    #[test]
    fn a_tilted_grasp_reports_the_rolls_axis_turned_in_the_hand_and_keeps_it() {
        let task = TaskInstance::sample(TaskKind::InstallToiletRoll(RollSize::Large), 11, -0.06);
        let expert = off_centre_grasp(&task, Vector3::zeros());
        // 12° about the jaws' closing axis (TCP x), then 5° about the pads' axis (TCP y).
        let turn =
            |axis: Vector3<f64>, deg: f64| Isometry3::rotation(axis.normalize() * deg.to_radians());
        let at = expert * turn(Vector3::x(), 12.0) * turn(Vector3::y(), 5.0);
        let mut w = TaskWorld::new(task.clone());
        assert!(w.before_close(&at).is_some());
        let Some(GripperEvent::Grasped {
            axis_tilt: Some(t), ..
        }) = w.after_gripper(&at, true)
        else {
            panic!("no tilt reported")
        };
        // The roll stands upright, so in the TCP frame its axis is turned back by both.
        assert!((t.about_closing_deg - 12.0).abs() < 0.1, "{t:?}");
        assert!((t.about_pads_deg - 5.0).abs() < 0.6, "{t:?}");
        let expected = (12f64.to_radians().cos() * 5f64.to_radians().cos()).acos();
        assert!((t.total_deg - expected.to_degrees()).abs() < 1e-9, "{t:?}");
        // Carried upright by the TCP, the roll leans by the grasp's tilt.
        let up = Isometry3::translation(0.0, 0.0, 0.1) * expert;
        w.carry(&up);
        let lean = (w.poses()[1].rotation * Vector3::z()).angle(&Vector3::z());
        assert!((lean.to_degrees() - t.total_deg).abs() < 1e-6, "{lean}");
        // Bodies without an axis that matters report none.
        let fruit = TaskInstance::sample(TaskKind::PickFruit(Fruit::Plum), 1, -0.06);
        let mut w = TaskWorld::new(fruit.clone());
        let at = fruit.base_from_object() * Isometry3::translation(0.0, 0.0, 0.021);
        assert!(w.before_close(&at).is_some());
        assert!(matches!(
            w.after_gripper(&at, true),
            Some(GripperEvent::Grasped {
                axis_tilt: None,
                ..
            })
        ));
        assert_eq!(AxisTilt::of(&Vector3::zeros()), None);
    }

    #[test]
    fn closing_jaws_leave_held_in_parts_and_seated_rolls_where_they_are() {
        let task = TaskInstance::sample(TaskKind::DisassemblePipe(PipePart::FirstLink), 3, -0.06);
        let at = off_centre_grasp(&task, Vector3::new(0.008, 0.0, 0.0));
        let mut w = TaskWorld::new(task.clone());
        let i = task.bodies.iter().position(|b| b.grasp.is_some()).unwrap();
        assert!(w.before_close(&at).is_some());
        w.after_gripper(&at, true);
        assert_eq!(w.held(), Some(i));
        assert_eq!(w.poses()[i], task.bodies[i].base_from_body);

        let task = TaskInstance::sample(TaskKind::InstallToiletRoll(RollSize::Large), 5, -0.06);
        let h = RollSize::Large.half_height();
        let seated = task.base_from_fixture * Isometry3::translation(0.0, 0.0, h);
        assert!(!task.stands_free(1, &seated));
        assert!(task.stands_free(1, &task.bodies[1].base_from_body));
        assert!(!task.stands_free(0, &task.bodies[0].base_from_body));
    }

    #[test]
    fn a_closed_gripper_carries_and_opening_drops_the_fruit() {
        let task = TaskInstance::sample(TaskKind::PickFruit(Fruit::Plum), 1, -0.06);
        let mut w = TaskWorld::new(task.clone());
        let at = task.base_from_object() * Isometry3::translation(0.0, 0.0, 0.021);
        let far = Isometry3::translation(0.0, 0.0, 0.3) * at;
        assert_eq!(w.before_close(&far), None);
        assert_eq!(w.before_close(&at), Some(0.05));
        assert!(matches!(
            w.after_gripper(&at, true),
            Some(GripperEvent::Grasped { .. })
        ));
        assert_eq!(w.held(), Some(0));
        // Closing again on the held fruit, or opening empty, does nothing to report.
        assert_eq!(w.after_gripper(&at, true), None);
        let up = Isometry3::translation(0.0, 0.0, 0.1) * at;
        w.carry(&up);
        assert!(w.success());
        let event = w.after_gripper(&up, false).unwrap().to_string();
        let rest = w.poses()[0].translation.vector;
        assert_eq!(
            event,
            format!(
                "released the plum: it fell 100 mm and came to rest at [{:.3}, {:.3}, -0.035] m",
                rest.x, rest.y
            )
        );
        assert_eq!(w.after_gripper(&up, false), None);
        assert_eq!(w.held(), None);
        assert!((w.poses()[0].translation.vector.z - (-0.06 + 0.025)).abs() < 1e-12);
        assert!(!w.success());
    }
}
