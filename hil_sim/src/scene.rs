//! The simulated cell's geometry (issue 7 item 2): the table, objects as primitives with
//! poses, and the UR5 with its gripper as capsules around the FK link frames.
//!
//! The scene is held in the robot base frame (metres). It is turned into one parry3d
//! [`Compound`] (a BVH over the primitives) for ray casting by the depth cameras and for
//! point-to-surface distances in tests. parry3d 0.31 works in `f32` with glam types; the
//! conversion happens here, once per scene build, and `f32` keeps well under a micrometre
//! at cell distances.

pub use calibration::fusion::Capsule;
use cell_types::{Joints, Rgb};
use nalgebra::{Isometry3, Point3, Translation3, UnitQuaternion, Vector3};
use parry3d::math::{Pose, Rot3, Vector};
use parry3d::query::{PointQuery, Ray};
use parry3d::shape::{CompositeShapeRef, Compound, SharedShape};
use planner::kinematics::UR5;

use thiserror::Error;

/// Why a scene or a simulated camera could not be built or rendered. (The crate's other
/// modules are written in parallel; the lead may fold this into one crate error enum.)
#[derive(Debug, Error, PartialEq)]
#[non_exhaustive]
pub enum SceneError {
    /// A scene with no solid at all cannot be ray cast.
    #[error("the scene has no objects; add at least the table (Scene::table_only)")]
    EmptyScene,
    /// An object has an unusable shape or pose.
    #[error("scene object {name:?}: {why}; fix its entry in the scene description")]
    BadObject {
        /// The object's name.
        name: String,
        /// What is wrong.
        why: &'static str,
    },
    /// A camera's intrinsics or pose are unusable.
    #[error("simulated camera {camera}: {why}")]
    BadCamera {
        /// The camera id.
        camera: u8,
        /// What is wrong.
        why: String,
    },
}

/// A primitive solid, in the object's own frame.
#[derive(Copy, Clone, Debug, PartialEq)]
pub enum Primitive {
    /// A box with these half extents (m) along x, y, z, centred on the origin.
    Box {
        /// Half extents (m).
        half_extents: [f64; 3],
    },
    /// A sphere centred on the origin.
    Sphere {
        /// Radius (m).
        radius: f64,
    },
    /// A cylinder along z, centred on the origin.
    Cylinder {
        /// Half of its height (m).
        half_height: f64,
        /// Radius (m).
        radius: f64,
    },
    /// A capsule around the segment from `a` to `b`.
    Capsule {
        /// Segment start (m).
        a: [f64; 3],
        /// Segment end (m).
        b: [f64; 3],
        /// Radius (m).
        radius: f64,
    },
}

/// What an object looks like to the cameras.
#[derive(Copy, Clone, Debug, PartialEq)]
pub struct Material {
    /// Diffuse colour.
    pub colour: Rgb,
    /// Reflectance in the near infrared, 0..1.
    pub ir_albedo: f64,
}

impl Default for Material {
    fn default() -> Self {
        Self {
            colour: [180, 180, 180],
            ir_albedo: 0.6,
        }
    }
}

/// Which part of the cell an object belongs to (the fusion removes the robot's own points).
#[derive(Copy, Clone, Debug, PartialEq, Eq)]
pub enum Part {
    /// The table top.
    Table,
    /// Something on the table.
    Object,
    /// A link of the arm.
    Arm,
    /// The gripper.
    Gripper,
}

/// One solid of the scene.
#[derive(Clone, Debug, PartialEq)]
pub struct SceneObject {
    /// A name for reports.
    pub name: String,
    /// Its pose in the robot base frame.
    pub base_from_object: Isometry3<f64>,
    /// Its shape.
    pub shape: Primitive,
    /// How it looks.
    pub material: Material,
    /// What it is.
    pub part: Part,
}

/// Radii of the UR5 capsules between consecutive DH frame origins (0-1 base column, 1-2
/// upper arm, 2-3 forearm, 3-4, 4-5, 5-6 wrists). The DH chain drops the shoulder and
/// elbow offsets (they cancel), so the radii are a little generous.
const ARM_RADII: [f64; 6] = [0.075, 0.065, 0.055, 0.048, 0.048, 0.045];

/// The UR5 and a Robotiq 2F-85 as capsules in the base frame at joint angles `q`, with the
/// gripper opened to `opening` m (0..0.085).
pub fn robot_capsules(q: &Joints, opening: f64) -> Vec<Capsule> {
    let frames = UR5.link_frames(q);
    let mut out = Vec::with_capacity(10);
    // The base column reaches down to the mounting plate.
    out.push(Capsule {
        a: Point3::new(0.0, 0.0, -0.02),
        b: Point3::from(frames[1].translation.vector),
        radius: ARM_RADII[0],
    });
    for i in 1..6 {
        out.push(Capsule {
            a: Point3::from(frames[i].translation.vector),
            b: Point3::from(frames[i + 1].translation.vector),
            radius: ARM_RADII[i],
        });
    }
    // Robotiq 2F-85 in the flange frame (z out of the flange): body, then two fingers, closing
    // along the flange x as in the planner's URDF and closing volume.
    let flange = frames[6];
    let at = |x: f64, y: f64, z: f64| flange.transform_point(&Point3::new(x, y, z));
    out.push(Capsule {
        a: at(0.0, 0.0, 0.035),
        b: at(0.0, 0.0, 0.095),
        radius: 0.045,
    });
    let half = opening.clamp(0.0, 0.085) / 2.0 + 0.01;
    for s in [-1.0, 1.0] {
        out.push(Capsule {
            a: at(s * half, 0.0, 0.13),
            b: at(s * half, 0.0, 0.16),
            radius: 0.012,
        });
    }
    out
}

/// The simulated cell: solids in the base frame.
#[derive(Clone, Debug, PartialEq)]
pub struct Scene {
    /// All solids (table, objects, robot).
    pub objects: Vec<SceneObject>,
    /// Height of the table top in the base frame (m).
    pub table_height: f64,
}

/// The scene built for queries: a BVH over its solids.
pub struct SceneGeometry {
    compound: Compound,
    materials: Vec<(Material, Part)>,
}

/// A ray's first hit in a scene.
#[derive(Copy, Clone, Debug, PartialEq)]
pub struct Hit {
    /// Ray parameter of the hit (m when the direction has unit length; the depth when the
    /// direction's z in the camera frame is 1).
    pub t: f64,
    /// Unit surface normal at the hit (base frame).
    pub normal: Vector3<f64>,
    /// The index of the solid that was hit in [`Scene::objects`].
    pub object: usize,
}

/// The table top of the default cell (base frame, m), the fact sheet's "table height".
pub const TABLE_HEIGHT: f64 = -0.06;

/// The home configuration of the default cell: the gripper above the table centre,
/// pointing down.
pub const HOME_Q: Joints = [
    std::f64::consts::PI,
    -1.2,
    1.6,
    -1.971,
    -std::f64::consts::FRAC_PI_2,
    0.0,
];

impl Scene {
    /// A scene with only the table (a 1.6 m x 1.6 m top at [`TABLE_HEIGHT`]).
    pub fn table_only() -> Self {
        let thickness = 0.04;
        Self {
            objects: vec![SceneObject {
                name: "table".into(),
                base_from_object: Isometry3::translation(0.5, 0.0, TABLE_HEIGHT - thickness / 2.0),
                shape: Primitive::Box {
                    half_extents: [0.8, 0.8, thickness / 2.0],
                },
                material: Material {
                    colour: [150, 120, 90],
                    ir_albedo: 0.5,
                },
                part: Part::Table,
            }],
            table_height: TABLE_HEIGHT,
        }
    }

    /// The default cell: table, four objects on it (a box, a tilted box, a cylinder, a
    /// ball) and the robot at [`HOME_Q`] with the gripper open.
    pub fn default_cell() -> Self {
        let mut s = Self::table_only();
        let on_table = |x: f64, y: f64, half_z: f64, yaw: f64| {
            Isometry3::from_parts(
                Translation3::new(x, y, TABLE_HEIGHT + half_z),
                UnitQuaternion::from_euler_angles(0.0, 0.0, yaw),
            )
        };
        s.add_object(
            "red box",
            on_table(0.55, 0.18, 0.06, 0.3),
            Primitive::Box {
                half_extents: [0.05, 0.04, 0.06],
            },
            [200, 40, 40],
        );
        s.add_object(
            "blue block",
            on_table(0.78, -0.05, 0.04, -0.6),
            Primitive::Box {
                half_extents: [0.06, 0.06, 0.04],
            },
            [40, 60, 200],
        );
        s.add_object(
            "green can",
            on_table(0.45, -0.2, 0.075, 0.0),
            Primitive::Cylinder {
                half_height: 0.075,
                radius: 0.04,
            },
            [40, 180, 60],
        );
        s.add_object(
            "yellow ball",
            on_table(0.7, 0.25, 0.05, 0.0),
            Primitive::Sphere { radius: 0.05 },
            [220, 200, 40],
        );
        s.set_robot(&HOME_Q, 0.085);
        s
    }

    /// Adds an object with a colour and the default IR albedo.
    pub fn add_object(
        &mut self,
        name: &str,
        base_from_object: Isometry3<f64>,
        shape: Primitive,
        colour: Rgb,
    ) {
        self.objects.push(SceneObject {
            name: name.into(),
            base_from_object,
            shape,
            material: Material {
                colour,
                ir_albedo: 0.6,
            },
            part: Part::Object,
        });
    }

    /// Replaces the robot's solids with the arm at `q` and the gripper opened to `opening`.
    pub fn set_robot(&mut self, q: &Joints, opening: f64) {
        self.objects
            .retain(|o| !matches!(o.part, Part::Arm | Part::Gripper));
        for (i, c) in robot_capsules(q, opening).into_iter().enumerate() {
            let part = if i < 6 { Part::Arm } else { Part::Gripper };
            self.objects.push(SceneObject {
                name: format!("{part:?} capsule {i}"),
                base_from_object: Isometry3::identity(),
                shape: Primitive::Capsule {
                    a: c.a.coords.into(),
                    b: c.b.coords.into(),
                    radius: c.radius,
                },
                material: Material {
                    colour: if part == Part::Arm {
                        [90, 160, 200]
                    } else {
                        [40, 40, 40]
                    },
                    ir_albedo: 0.4,
                },
                part,
            });
        }
    }

    /// Builds the BVH for ray casting and distance queries.
    pub fn build(&self) -> Result<SceneGeometry, SceneError> {
        if self.objects.is_empty() {
            return Err(SceneError::EmptyScene);
        }
        let mut shapes = Vec::with_capacity(self.objects.len());
        let mut materials = Vec::with_capacity(self.objects.len());
        for o in &self.objects {
            let (shape, local) = primitive_shape(&o.name, &o.shape)?;
            if !o
                .base_from_object
                .translation
                .vector
                .iter()
                .all(|v| v.is_finite())
                || !o
                    .base_from_object
                    .rotation
                    .coords
                    .iter()
                    .all(|v| v.is_finite())
            {
                return Err(SceneError::BadObject {
                    name: o.name.clone(),
                    why: "its pose is not finite",
                });
            }
            shapes.push((to_pose(&(o.base_from_object * local)), shape));
            materials.push((o.material, o.part));
        }
        Ok(SceneGeometry {
            compound: Compound::new(shapes),
            materials,
        })
    }
}

fn primitive_shape(name: &str, p: &Primitive) -> Result<(SharedShape, Isometry3<f64>), SceneError> {
    let bad = |why| SceneError::BadObject {
        name: name.to_string(),
        why,
    };
    let positive = |v: f64| v.is_finite() && v > 0.0;
    Ok(match *p {
        Primitive::Box { half_extents: h } => {
            if !h.iter().all(|v| positive(*v)) {
                return Err(bad("box half extents must be positive"));
            }
            (
                SharedShape::cuboid(h[0] as f32, h[1] as f32, h[2] as f32),
                Isometry3::identity(),
            )
        }
        Primitive::Sphere { radius } => {
            if !positive(radius) {
                return Err(bad("sphere radius must be positive"));
            }
            (SharedShape::ball(radius as f32), Isometry3::identity())
        }
        Primitive::Cylinder {
            half_height,
            radius,
        } => {
            if !(positive(half_height) && positive(radius)) {
                return Err(bad("cylinder size must be positive"));
            }
            // parry's cylinders run along y; ours along z.
            (
                SharedShape::cylinder(half_height as f32, radius as f32),
                Isometry3::rotation(Vector3::x() * std::f64::consts::FRAC_PI_2),
            )
        }
        Primitive::Capsule { a, b, radius } => {
            if !positive(radius) || !a.iter().chain(b.iter()).all(|v| v.is_finite()) {
                return Err(bad("capsule radius must be positive and its ends finite"));
            }
            let v = |p: [f64; 3]| Vector::new(p[0] as f32, p[1] as f32, p[2] as f32);
            (
                SharedShape::capsule(v(a), v(b), radius as f32),
                Isometry3::identity(),
            )
        }
    })
}

/// Converts a nalgebra isometry to parry's glam pose.
fn to_pose(iso: &Isometry3<f64>) -> Pose {
    let t = iso.translation.vector;
    let q = iso.rotation.coords; // (i, j, k, w)
    Pose::from_parts(
        Vector::new(t.x as f32, t.y as f32, t.z as f32),
        Rot3::from_xyzw(q.x as f32, q.y as f32, q.z as f32, q.w as f32).normalize(),
    )
}

impl SceneGeometry {
    /// The first hit of the ray `origin + t * dir` with `t` in `(0, max_t]`.
    pub fn cast(&self, origin: &Point3<f64>, dir: &Vector3<f64>, max_t: f64) -> Option<Hit> {
        let ray = Ray::new(
            Vector::new(origin.x as f32, origin.y as f32, origin.z as f32),
            Vector::new(dir.x as f32, dir.y as f32, dir.z as f32),
        );
        let (id, hit) = CompositeShapeRef(&self.compound).cast_local_ray_and_get_normal(
            &ray,
            max_t as f32,
            true,
        )?;
        let n = hit.normal;
        Some(Hit {
            t: f64::from(hit.time_of_impact),
            normal: Vector3::new(f64::from(n.x), f64::from(n.y), f64::from(n.z)),
            object: id as usize,
        })
    }

    /// Distance from `p` to the nearest surface of the scene (m), inside or out.
    pub fn distance_to_surface(&self, p: &Point3<f64>) -> f64 {
        let v = Vector::new(p.x as f32, p.y as f32, p.z as f32);
        f64::from(self.compound.distance_to_local_point(v, false))
    }

    /// The material and part of solid `object`.
    pub fn material(&self, object: usize) -> Option<(Material, Part)> {
        self.materials.get(object).copied()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn home_pose_puts_the_gripper_above_the_table_pointing_down() {
        let flange = UR5.forward(&HOME_Q);
        let p = flange.translation();
        assert!(p.x > 0.3 && p.x < 0.7, "{p:?}");
        assert!(p.y.abs() < 0.2, "{p:?}");
        assert!(p.z > 0.2 && p.z < 0.5, "{p:?}");
        let z = flange.rotation() * Vector3::z();
        assert!(z.z < -0.95, "flange z {z:?}");
    }

    #[test]
    fn ray_down_hits_table_top_and_objects() {
        let g = Scene::default_cell().build().unwrap();
        let down = -Vector3::z();
        let hit = g.cast(&Point3::new(0.3, 0.3, 1.0), &down, 5.0).unwrap();
        assert!((hit.t - (1.0 - TABLE_HEIGHT)).abs() < 1e-5, "{hit:?}");
        assert!((hit.normal - Vector3::z()).norm() < 1e-5);
        // The green can, 0.15 m tall.
        let hit = g.cast(&Point3::new(0.45, -0.2, 1.0), &down, 5.0).unwrap();
        assert!(
            (hit.t - (1.0 - TABLE_HEIGHT - 0.15)).abs() < 1e-5,
            "{hit:?}"
        );
        let (m, part) = g.material(hit.object).unwrap();
        assert_eq!((m.colour, part), ([40, 180, 60], Part::Object));
        assert!(g
            .cast(&Point3::new(0.3, 0.3, 1.0), &Vector3::z(), 5.0)
            .is_none());
    }

    #[test]
    fn distance_to_surface_is_zero_on_surfaces() {
        let g = Scene::table_only().build().unwrap();
        assert!(g.distance_to_surface(&Point3::new(0.5, 0.0, TABLE_HEIGHT)) < 1e-6);
        assert!(
            (g.distance_to_surface(&Point3::new(0.5, 0.0, TABLE_HEIGHT + 0.1)) - 0.1).abs() < 1e-6
        );
    }

    #[test]
    fn bad_objects_are_rejected() {
        let mut s = Scene::table_only();
        s.add_object(
            "flat",
            Isometry3::identity(),
            Primitive::Sphere { radius: 0.0 },
            [0, 0, 0],
        );
        assert!(matches!(s.build(), Err(SceneError::BadObject { .. })));
        assert!(matches!(
            Scene {
                objects: vec![],
                table_height: 0.0
            }
            .build(),
            Err(SceneError::EmptyScene)
        ));
    }
}
