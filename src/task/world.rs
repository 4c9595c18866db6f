//! The task's world truth, independent of the cameras and the controller: where each body
//! is, which one the gripper holds, and the grasp attachment rules. The simulated cell
//! ([`crate::sim_cell::SimWorld`]) renders it; the kinematic check ([`super::check`]) uses
//! it without rendering.

use nalgebra::Isometry3;

use super::TaskInstance;

/// Grasp distance: a body is caught when its grasp site is this close to the TCP as the
/// fingers close (m).
pub const GRASP_RADIUS: f64 = 0.03;

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
            let p = self.poses[i] * nalgebra::Point3::from(site.point);
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
    /// comes to rest where the task says.
    pub fn after_gripper(&mut self, base_from_tcp: &Isometry3<f64>, holding: bool) {
        if holding && self.held.is_none() {
            if let Some(i) = self.between_fingers.take() {
                self.held = Some((i, base_from_tcp.inverse() * self.poses[i]));
            }
        } else if !holding {
            self.between_fingers = None;
            if let Some((i, _)) = self.held.take() {
                self.poses[i] = self.task.released_pose(i, &self.poses[i]);
            }
        }
    }

    /// Moves the held body with the TCP.
    pub fn carry(&mut self, base_from_tcp: &Isometry3<f64>) {
        if let Some((i, tcp_from_body)) = self.held {
            self.poses[i] = base_from_tcp * tcp_from_body;
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::task::{Fruit, TaskKind};

    #[test]
    fn a_closed_gripper_carries_and_opening_drops_the_fruit() {
        let task = TaskInstance::sample(TaskKind::PickFruit(Fruit::Plum), 1, -0.06);
        let mut w = TaskWorld::new(task.clone());
        let at = task.base_from_object() * Isometry3::translation(0.0, 0.0, 0.021);
        let far = Isometry3::translation(0.0, 0.0, 0.3) * at;
        assert_eq!(w.before_close(&far), None);
        assert_eq!(w.before_close(&at), Some(0.05));
        w.after_gripper(&at, true);
        assert_eq!(w.held(), Some(0));
        let up = Isometry3::translation(0.0, 0.0, 0.1) * at;
        w.carry(&up);
        assert!(w.success());
        w.after_gripper(&up, false);
        assert_eq!(w.held(), None);
        assert!((w.poses()[0].translation.vector.z - (-0.06 + 0.025)).abs() < 1e-12);
        assert!(!w.success());
    }
}
