//! The UR arm + Robotiq 2F-85 as URDF: a generator that writes the URDF text from DH
//! parameters (issue 2 item 3), and a loader (via `urdf-rs`) that turns any serial-chain URDF
//! into a [`Chain`] with forward kinematics and per-link collision geometry.
//!
//! The generated URDF puts every joint axis along its frame's z and every joint origin equal
//! to the fixed part `Tz(d) Tx(a) Rx(α)` of the previous DH row, so FK over the URDF equals
//! the DH product of [`crate::kinematics`] exactly (the base frame is the UR controller's base,
//! not the ROS `base_link`, which is turned by π).

use crate::error::PlanError;
use crate::kinematics::{UrParams, UR5, UR5E};
use nalgebra::{Isometry3, Point3, Translation3, Unit, UnitQuaternion, Vector3};
use std::fmt::Write as _;

/// Link names of the arm chain, base to tool.
pub const ARM_LINKS: [&str; 7] = [
    "base_link",
    "shoulder_link",
    "upper_arm_link",
    "forearm_link",
    "wrist_1_link",
    "wrist_2_link",
    "wrist_3_link",
];

/// Everything the URDF generator needs: DH lengths, the physical offsets DH folds away, link
/// radii and the tool.
#[derive(Copy, Clone, Debug, PartialEq)]
pub struct UrdfSpec {
    /// Robot name written in the URDF.
    pub name: &'static str,
    /// DH lengths.
    pub ur: UrParams,
    /// Offset of the upper arm along the shoulder axis (UR5: 0.13585 m).
    pub shoulder_offset: f64,
    /// Offset of the forearm back along the elbow axis (UR5: 0.1197 m).
    pub elbow_offset: f64,
    /// Radius of base, shoulder and upper arm (m).
    pub big_radius: f64,
    /// Radius of the forearm (m).
    pub forearm_radius: f64,
    /// Radius of the wrists (m).
    pub wrist_radius: f64,
    /// Flange to TCP distance along the flange z (m): the point between the 2F-85 fingertips.
    pub flange_to_tcp: f64,
    /// Joint limits (rad), lower and upper, per joint.
    pub limits: [(f64, f64); 6],
}

const TAU: f64 = std::f64::consts::TAU;
const PI: f64 = std::f64::consts::PI;

impl UrdfSpec {
    /// The UR5 (CB3) with the Robotiq 2F-85, TCP 0.15 m out of the flange; joints ±2π except
    /// the elbow at ±π (as the ROS description narrows it for planning).
    pub fn ur5() -> Self {
        Self {
            name: "ur5_robotiq_2f85",
            ur: UR5,
            shoulder_offset: 0.13585,
            elbow_offset: 0.1197,
            big_radius: 0.06,
            forearm_radius: 0.05,
            wrist_radius: 0.045,
            flange_to_tcp: 0.15,
            limits: [
                (-TAU, TAU),
                (-TAU, TAU),
                (-PI, PI),
                (-TAU, TAU),
                (-TAU, TAU),
                (-TAU, TAU),
            ],
        }
    }

    /// The UR5e with the Robotiq 2F-85.
    pub fn ur5e() -> Self {
        Self {
            name: "ur5e_robotiq_2f85",
            ur: UR5E,
            shoulder_offset: 0.138,
            elbow_offset: 0.131,
            ..Self::ur5()
        }
    }

    /// Collision cylinders `(link, from, to, radius)` in each link's frame. The link frame of
    /// joint `i`'s child is the DH frame `i-1` turned by `q_i`; the gripper's is the flange.
    pub fn cylinders(&self) -> Vec<(&'static str, [f64; 3], [f64; 3], f64)> {
        let u = &self.ur;
        let s = self.shoulder_offset;
        let f = self.shoulder_offset - self.elbow_offset;
        let (rb, rf, rw) = (self.big_radius, self.forearm_radius, self.wrist_radius);
        let body = self.flange_to_tcp - 0.055;
        vec![
            ("base_link", [0.0, 0.0, 0.0], [0.0, 0.0, 0.075], 0.075),
            // Starts above the base plate so the shoulder spheres clear the mounting table.
            ("shoulder_link", [0.0, 0.0, 0.075], [0.0, 0.0, u.d1], rb),
            ("shoulder_link", [0.0, rb, u.d1], [0.0, -s, u.d1], rb),
            ("upper_arm_link", [0.0, 0.0, s], [u.a2, 0.0, s], rb),
            ("forearm_link", [0.0, 0.0, f], [0.0, 0.0, s], rb * 0.95),
            ("forearm_link", [0.0, 0.0, f], [u.a3, 0.0, f], rf),
            ("wrist_1_link", [0.0, 0.0, f], [0.0, 0.0, u.d4 + 0.04], rw),
            (
                "wrist_2_link",
                [0.0, 0.0, 0.02],
                [0.0, 0.0, u.d5 + 0.04],
                rw,
            ),
            ("wrist_3_link", [0.0, 0.0, 0.03], [0.0, 0.0, u.d6], rw),
            ("gripper_link", [0.0, 0.0, 0.0], [0.0, 0.0, body], 0.045),
        ]
    }

    /// Collision boxes `(link, centre, size)` in the link frame: the 2F-85 fingers, open
    /// (85 mm stroke), reaching 15 mm past the TCP.
    pub fn boxes(&self) -> Vec<(&'static str, [f64; 3], [f64; 3])> {
        let zc = self.flange_to_tcp - 0.02;
        let x = 0.0425 + 0.008;
        vec![
            ("gripper_link", [x, 0.0, zc], [0.016, 0.022, 0.07]),
            ("gripper_link", [-x, 0.0, zc], [0.016, 0.022, 0.07]),
        ]
    }

    /// Writes the URDF text.
    pub fn to_urdf(&self) -> String {
        let mut s = String::new();
        let _ = writeln!(s, "<?xml version=\"1.0\"?>");
        let _ = writeln!(
            s,
            "<!-- Generated by planner::urdf::UrdfSpec::to_urdf; do not edit by hand. -->"
        );
        let _ = writeln!(s, "<robot name=\"{}\">", self.name);
        let cyl = self.cylinders();
        let boxes = self.boxes();
        let links: Vec<&str> = ARM_LINKS
            .iter()
            .copied()
            .chain(["flange", "gripper_link", "tcp"])
            .collect();
        for link in &links {
            let _ = writeln!(s, "  <link name=\"{link}\">");
            for (l, a, b, r) in cyl.iter().filter(|c| c.0 == *link) {
                let _ = l;
                let (xyz, rpy, len) = cylinder_pose(*a, *b);
                let _ = writeln!(s, "    <collision>");
                let _ = writeln!(s, "      <origin xyz=\"{}\" rpy=\"{}\"/>", v3(xyz), v3(rpy));
                let _ = writeln!(
                    s,
                    "      <geometry><cylinder radius=\"{}\" length=\"{}\"/></geometry>",
                    num(*r),
                    num(len)
                );
                let _ = writeln!(s, "    </collision>");
            }
            for (_, c, size) in boxes.iter().filter(|b| b.0 == *link) {
                let _ = writeln!(s, "    <collision>");
                let _ = writeln!(s, "      <origin xyz=\"{}\" rpy=\"0 0 0\"/>", v3(*c));
                let _ = writeln!(
                    s,
                    "      <geometry><box size=\"{}\"/></geometry>",
                    v3(*size)
                );
                let _ = writeln!(s, "    </collision>");
            }
            let _ = writeln!(s, "  </link>");
        }
        let joints = [
            "shoulder_pan_joint",
            "shoulder_lift_joint",
            "elbow_joint",
            "wrist_1_joint",
            "wrist_2_joint",
            "wrist_3_joint",
        ];
        let rows = self.ur.dh_rows();
        for i in 0..6 {
            // Joint i's origin is the fixed part of DH row i-1 (identity for the first joint).
            let (xyz, rpy) = if i == 0 {
                ([0.0; 3], [0.0; 3])
            } else {
                let (d, a, alpha) = rows[i - 1];
                ([a, 0.0, d], [alpha, 0.0, 0.0])
            };
            let (lo, hi) = self.limits[i];
            let effort = if i < 3 { 150.0 } else { 28.0 };
            let _ = writeln!(s, "  <joint name=\"{}\" type=\"revolute\">", joints[i]);
            let _ = writeln!(s, "    <parent link=\"{}\"/>", ARM_LINKS[i]);
            let _ = writeln!(s, "    <child link=\"{}\"/>", ARM_LINKS[i + 1]);
            let _ = writeln!(s, "    <origin xyz=\"{}\" rpy=\"{}\"/>", v3(xyz), v3(rpy));
            let _ = writeln!(s, "    <axis xyz=\"0 0 1\"/>");
            let _ = writeln!(
                s,
                "    <limit lower=\"{}\" upper=\"{}\" effort=\"{}\" velocity=\"{}\"/>",
                num(lo),
                num(hi),
                num(effort),
                num(PI)
            );
            let _ = writeln!(s, "  </joint>");
        }
        let fixed = [
            (
                "flange_joint",
                "wrist_3_link",
                "flange",
                [0.0, 0.0, self.ur.d6],
            ),
            ("gripper_joint", "flange", "gripper_link", [0.0; 3]),
            (
                "tcp_joint",
                "gripper_link",
                "tcp",
                [0.0, 0.0, self.flange_to_tcp],
            ),
        ];
        for (name, parent, child, xyz) in fixed {
            let _ = writeln!(s, "  <joint name=\"{name}\" type=\"fixed\">");
            let _ = writeln!(s, "    <parent link=\"{parent}\"/>");
            let _ = writeln!(s, "    <child link=\"{child}\"/>");
            let _ = writeln!(s, "    <origin xyz=\"{}\" rpy=\"0 0 0\"/>", v3(xyz));
            let _ = writeln!(s, "  </joint>");
        }
        let _ = writeln!(s, "</robot>");
        s
    }
}

fn num(v: f64) -> String {
    // Shortest round-trip formatting, so parsing the text gives back the same f64.
    let v = if v == 0.0 { 0.0 } else { v };
    format!("{v:?}")
}

fn v3(v: [f64; 3]) -> String {
    format!("{} {} {}", num(v[0]), num(v[1]), num(v[2]))
}

/// Origin (centre), rpy and length of a URDF cylinder (axis along its z) from `a` to `b`.
fn cylinder_pose(a: [f64; 3], b: [f64; 3]) -> ([f64; 3], [f64; 3], f64) {
    let va = Vector3::from(a);
    let vb = Vector3::from(b);
    let d = vb - va;
    let len = d.norm();
    let c = (va + vb) / 2.0;
    let rot = UnitQuaternion::rotation_between(&Vector3::z(), &d)
        .unwrap_or_else(|| UnitQuaternion::from_axis_angle(&Vector3::x_axis(), PI));
    let (r, p, y) = rot.euler_angles();
    ([c.x, c.y, c.z], [r, p, y], len)
}

/// A collision primitive of a link, in the link's frame.
#[derive(Clone, Debug, PartialEq)]
pub enum Shape {
    /// A sphere.
    Sphere {
        /// Pose of the centre in the link frame.
        origin: Isometry3<f64>,
        /// Radius (m).
        radius: f64,
    },
    /// A cylinder along its origin's z, centred on the origin.
    Cylinder {
        /// Pose in the link frame.
        origin: Isometry3<f64>,
        /// Radius (m).
        radius: f64,
        /// Length (m).
        length: f64,
    },
    /// A capsule: a cylinder of `length` along its origin's z, centred on the origin, capped
    /// by half balls of the same radius (URDF `capsule`).
    Capsule {
        /// Pose in the link frame.
        origin: Isometry3<f64>,
        /// Radius (m).
        radius: f64,
        /// Length of the cylindrical part (m).
        length: f64,
    },
    /// A box centred on its origin.
    Cuboid {
        /// Pose in the link frame.
        origin: Isometry3<f64>,
        /// Full edge lengths (m).
        size: [f64; 3],
    },
}

/// One joint of a serial chain: a fixed origin, then a rotation about `axis` (revolute) or
/// nothing (fixed), producing the child link's frame.
#[derive(Clone, Debug)]
pub struct ChainJoint {
    /// Joint name.
    pub name: String,
    /// Child link index.
    pub child: usize,
    /// Parent link index.
    pub parent: usize,
    /// Fixed transform parent link -> joint frame.
    pub origin: Isometry3<f64>,
    /// `Some(axis)` for a revolute joint, `None` for a fixed one.
    pub axis: Option<Unit<Vector3<f64>>>,
    /// Limits (rad) for revolute joints.
    pub limits: (f64, f64),
}

/// A serial (tree-shaped, with one actuated path) kinematic chain loaded from URDF.
#[derive(Clone, Debug)]
pub struct Chain {
    /// Link names; index 0 is the root.
    pub links: Vec<String>,
    /// Collision shapes per link.
    pub shapes: Vec<Vec<Shape>>,
    /// Joints in topological order (parents before children).
    pub joints: Vec<ChainJoint>,
    /// Which joints are the six actuated ones, in order.
    pub actuated: [usize; 6],
}

fn iso(o: &urdf_rs::Pose) -> Isometry3<f64> {
    let rot = UnitQuaternion::from_euler_angles(o.rpy[0], o.rpy[1], o.rpy[2]);
    Isometry3::from_parts(Translation3::new(o.xyz[0], o.xyz[1], o.xyz[2]), rot)
}

impl Chain {
    /// Parses URDF text into a chain. The six revolute joints in topological order become the
    /// actuated joints; continuous joints are rejected (the arm has limits).
    pub fn from_urdf_str(text: &str) -> Result<Self, PlanError> {
        let robot = urdf_rs::read_from_string(text).map_err(|e| PlanError::UrdfParse {
            message: e.to_string(),
        })?;
        let links: Vec<String> = robot.links.iter().map(|l| l.name.clone()).collect();
        let index = |name: &str| -> Result<usize, PlanError> {
            links
                .iter()
                .position(|l| l == name)
                .ok_or_else(|| PlanError::UrdfStructure {
                    what: format!("joint refers to unknown link {name}"),
                })
        };
        let mut shapes = Vec::with_capacity(links.len());
        for l in &robot.links {
            let mut v = Vec::new();
            for c in &l.collision {
                let origin = iso(&c.origin);
                match &c.geometry {
                    urdf_rs::Geometry::Sphere { radius } => v.push(Shape::Sphere {
                        origin,
                        radius: *radius,
                    }),
                    urdf_rs::Geometry::Cylinder { radius, length } => v.push(Shape::Cylinder {
                        origin,
                        radius: *radius,
                        length: *length,
                    }),
                    urdf_rs::Geometry::Capsule { radius, length } => v.push(Shape::Capsule {
                        origin,
                        radius: *radius,
                        length: *length,
                    }),
                    urdf_rs::Geometry::Box { size } => v.push(Shape::Cuboid {
                        origin,
                        size: [size[0], size[1], size[2]],
                    }),
                    // Meshes are for display here; collision uses the primitives above.
                    urdf_rs::Geometry::Mesh { .. } => {}
                }
            }
            shapes.push(v);
        }
        // Order joints so that every joint's parent link is already placed.
        let mut placed = vec![false; links.len()];
        let children: Vec<usize> = robot
            .joints
            .iter()
            .map(|j| index(&j.child.link))
            .collect::<Result<_, _>>()?;
        let root = (0..links.len())
            .find(|i| !children.contains(i))
            .ok_or_else(|| PlanError::UrdfStructure {
                what: "no root link (every link is a joint's child)".into(),
            })?;
        placed[root] = true;
        let mut joints = Vec::new();
        let mut remaining: Vec<&urdf_rs::Joint> = robot.joints.iter().collect();
        while !remaining.is_empty() {
            let before = remaining.len();
            let mut rest = Vec::new();
            for j in remaining {
                let p = index(&j.parent.link)?;
                if placed[p] {
                    let c = index(&j.child.link)?;
                    placed[c] = true;
                    let axis = match j.joint_type {
                        urdf_rs::JointType::Revolute => {
                            let a = Vector3::new(j.axis.xyz[0], j.axis.xyz[1], j.axis.xyz[2]);
                            Some(Unit::try_new(a, 1e-12).ok_or_else(|| {
                                PlanError::UrdfStructure {
                                    what: format!("joint {} has a zero axis", j.name),
                                }
                            })?)
                        }
                        urdf_rs::JointType::Fixed => None,
                        _ => {
                            return Err(PlanError::UrdfStructure {
                                what: format!(
                                    "joint {} is {:?}; only revolute and fixed are supported",
                                    j.name, j.joint_type
                                ),
                            })
                        }
                    };
                    joints.push(ChainJoint {
                        name: j.name.clone(),
                        child: c,
                        parent: p,
                        origin: iso(&j.origin),
                        axis,
                        limits: (j.limit.lower, j.limit.upper),
                    });
                } else {
                    rest.push(j);
                }
            }
            if rest.len() == before {
                return Err(PlanError::UrdfStructure {
                    what: "joints do not form a tree from one root".into(),
                });
            }
            remaining = rest;
        }
        let rev: Vec<usize> = (0..joints.len())
            .filter(|&i| joints[i].axis.is_some())
            .collect();
        let actuated: [usize; 6] =
            rev.try_into()
                .map_err(|v: Vec<usize>| PlanError::UrdfStructure {
                    what: format!("found {} revolute joints, need 6", v.len()),
                })?;
        Ok(Self {
            links,
            shapes,
            joints,
            actuated,
        })
    }

    /// Index of a link by name.
    pub fn link_index(&self, name: &str) -> Option<usize> {
        self.links.iter().position(|l| l == name)
    }

    /// Frames of every link in the root frame at configuration `q`, written into `out`
    /// (length = number of links; no allocation).
    pub fn link_poses_into(&self, q: &[f64; 6], out: &mut [Isometry3<f64>]) {
        let mut k = 0;
        for j in &self.joints {
            let parent = out
                .get(j.parent)
                .copied()
                .unwrap_or_else(Isometry3::identity);
            let mut t = parent * j.origin;
            if let Some(axis) = &j.axis {
                let angle = q.get(k).copied().unwrap_or(0.0);
                k += 1;
                t *= UnitQuaternion::from_axis_angle(axis, angle);
            }
            if let Some(slot) = out.get_mut(j.child) {
                *slot = t;
            }
        }
    }

    /// Frames of every link in the root frame at `q`.
    pub fn link_poses(&self, q: &[f64; 6]) -> Vec<Isometry3<f64>> {
        let mut out = vec![Isometry3::identity(); self.links.len()];
        self.link_poses_into(q, &mut out);
        out
    }

    /// For every link, the rigid body it belongs to as an anchor slot (0: the root body,
    /// `k + 1`: the body moved by actuated joint `k`) and its fixed pose in that anchor.
    pub fn anchors(&self) -> Vec<(usize, Isometry3<f64>)> {
        let poses = self.link_poses(&[0.0; 6]);
        let mut slot_of = vec![0usize; self.links.len()];
        for j in &self.joints {
            slot_of[j.child] = match self
                .actuated
                .iter()
                .position(|&a| self.joints[a].child == j.child)
            {
                Some(k) => k + 1,
                None => slot_of[j.parent],
            };
        }
        let anchor_link = |slot: usize| -> Option<usize> {
            if slot == 0 {
                (0..self.links.len()).find(|i| self.joints.iter().all(|j| j.child != *i))
            } else {
                self.actuated.get(slot - 1).map(|&a| self.joints[a].child)
            }
        };
        (0..self.links.len())
            .map(|l| {
                let s = slot_of[l];
                let a = anchor_link(s).unwrap_or(0);
                (s, poses[a].inverse() * poses[l])
            })
            .collect()
    }

    /// Poses of the 7 anchor bodies (root, then each actuated joint's child) at `q`, computing
    /// only the six joint rotations (fixed joints are folded into constant offsets).
    pub fn anchor_poses_into(
        &self,
        q: &[f64; 6],
        anchors: &[(usize, Isometry3<f64>)],
        out: &mut [Isometry3<f64>; 7],
    ) {
        out[0] = Isometry3::identity();
        for (k, &ji) in self.actuated.iter().enumerate() {
            let j = &self.joints[ji];
            let (slot, off) = anchors
                .get(j.parent)
                .copied()
                .unwrap_or((0, Isometry3::identity()));
            let axis = j.axis.unwrap_or_else(Vector3::z_axis);
            out[k + 1] =
                out[slot.min(6)] * off * j.origin * UnitQuaternion::from_axis_angle(&axis, q[k]);
        }
    }

    /// [`Self::anchor_poses_into`] with the constant part of each joint's transform (parent
    /// anchor offset times joint origin) multiplied out once.
    pub fn anchor_fk(&self, anchors: &[(usize, Isometry3<f64>)]) -> AnchorFk {
        let joints = std::array::from_fn(|k| {
            let Some(j) = self.actuated.get(k).map(|&ji| &self.joints[ji]) else {
                return (0, Isometry3::identity(), Vector3::z_axis());
            };
            let (slot, off) = anchors
                .get(j.parent)
                .copied()
                .unwrap_or((0, Isometry3::identity()));
            (
                slot.min(6),
                off * j.origin,
                j.axis.unwrap_or_else(Vector3::z_axis),
            )
        });
        AnchorFk { joints }
    }

    /// Joint limits of the six actuated joints.
    pub fn limits(&self) -> [(f64, f64); 6] {
        let mut l = [(0.0, 0.0); 6];
        for (i, &j) in self.actuated.iter().enumerate() {
            l[i] = self.joints[j].limits;
        }
        l
    }
}

/// The seven anchor poses of a chain as one fixed transform and one rotation per joint (see
/// [`Chain::anchor_fk`]).
#[derive(Clone, Debug, PartialEq)]
pub struct AnchorFk {
    /// Per actuated joint: parent anchor slot, fixed transform from it, rotation axis.
    joints: [(usize, Isometry3<f64>, Unit<Vector3<f64>>); 6],
}

impl AnchorFk {
    /// The same poses as [`Chain::anchor_poses_into`] with the anchors this was built from.
    #[inline]
    pub fn poses_into(&self, q: &[f64; 6], out: &mut [Isometry3<f64>; 7]) {
        out[0] = Isometry3::identity();
        for (k, (slot, fixed, axis)) in self.joints.iter().enumerate() {
            out[k + 1] = out[*slot] * fixed * UnitQuaternion::from_axis_angle(axis, q[k]);
        }
    }
}

/// Rings of `m` points on the side of a cylinder (or a capsule's cylindrical part) along z.
fn side_rings(
    pts: &mut Vec<Point3<f64>>,
    origin: &Isometry3<f64>,
    radius: f64,
    length: f64,
    m: usize,
) {
    for i in 0..=m {
        let z = -length / 2.0 + length * i as f64 / m as f64;
        for k in 0..m {
            let ph = TAU * k as f64 / m as f64;
            pts.push(origin * Point3::new(radius * ph.cos(), radius * ph.sin(), z));
        }
    }
}

/// Points on the surface of a shape (for checking that spheres cover it), in its link frame.
pub fn surface_samples(shape: &Shape, n: usize) -> Vec<Point3<f64>> {
    let mut pts = Vec::new();
    let m = n.max(4);
    match shape {
        Shape::Sphere { origin, radius } => {
            for i in 0..m {
                for k in 0..m {
                    let th = PI * (i as f64 + 0.5) / m as f64;
                    let ph = TAU * k as f64 / m as f64;
                    let p =
                        Point3::new(th.sin() * ph.cos(), th.sin() * ph.sin(), th.cos()) * *radius;
                    pts.push(origin * p);
                }
            }
        }
        Shape::Cylinder {
            origin,
            radius,
            length,
        } => {
            side_rings(&mut pts, origin, *radius, *length, m);
            for i in 0..=m {
                let r = radius * i as f64 / m as f64;
                for k in 0..m {
                    let ph = TAU * k as f64 / m as f64;
                    for z in [-length / 2.0, length / 2.0] {
                        pts.push(origin * Point3::new(r * ph.cos(), r * ph.sin(), z));
                    }
                }
            }
        }
        Shape::Capsule {
            origin,
            radius,
            length,
        } => {
            side_rings(&mut pts, origin, *radius, *length, m);
            // The caps: half spheres around the axis ends.
            for i in 0..m {
                let th = PI / 2.0 * (i as f64 + 0.5) / m as f64;
                for k in 0..m {
                    let ph = TAU * k as f64 / m as f64;
                    let (r, h) = (radius * th.sin(), radius * th.cos());
                    for s in [-1.0, 1.0] {
                        let z = s * (length / 2.0 + h);
                        pts.push(origin * Point3::new(r * ph.cos(), r * ph.sin(), z));
                    }
                }
            }
        }
        Shape::Cuboid { origin, size } => {
            for i in 0..=m {
                for k in 0..=m {
                    let u = i as f64 / m as f64 - 0.5;
                    let v = k as f64 / m as f64 - 0.5;
                    for s in [-0.5, 0.5] {
                        pts.push(origin * Point3::new(s * size[0], u * size[1], v * size[2]));
                        pts.push(origin * Point3::new(u * size[0], s * size[1], v * size[2]));
                        pts.push(origin * Point3::new(u * size[0], v * size[1], s * size[2]));
                    }
                }
            }
        }
    }
    pts
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn committed_urdf_equals_generator_output() {
        let committed = include_str!("../robot/ur5.urdf");
        assert_eq!(
            committed,
            UrdfSpec::ur5().to_urdf(),
            "planner/robot/ur5.urdf is stale: regenerate it with `cargo test -p planner -- --ignored regenerate_urdf`"
        );
        let committed_e = include_str!("../robot/ur5e.urdf");
        assert_eq!(committed_e, UrdfSpec::ur5e().to_urdf());
    }

    #[test]
    #[ignore = "writes planner/robot/*.urdf; run by hand after changing the generator"]
    fn regenerate_urdf() {
        let dir = concat!(env!("CARGO_MANIFEST_DIR"), "/robot");
        std::fs::write(format!("{dir}/ur5.urdf"), UrdfSpec::ur5().to_urdf()).unwrap();
        std::fs::write(format!("{dir}/ur5e.urdf"), UrdfSpec::ur5e().to_urdf()).unwrap();
    }

    #[test]
    fn broken_urdf_gives_typed_errors() {
        assert!(matches!(
            Chain::from_urdf_str("<robot"),
            Err(PlanError::UrdfParse { .. })
        ));
        let two = r#"<robot name="r"><link name="a"/><link name="b"/>
            <joint name="j" type="revolute"><parent link="a"/><child link="b"/>
            <axis xyz="0 0 1"/><limit lower="-1" upper="1" effort="1" velocity="1"/></joint></robot>"#;
        let err = Chain::from_urdf_str(two).unwrap_err();
        assert!(
            matches!(err, PlanError::UrdfStructure { ref what } if what.contains("1 revolute")),
            "{err}"
        );
    }
}
