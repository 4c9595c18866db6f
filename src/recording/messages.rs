//! Builders of the JSON messages the recorder writes (Foxglove's message layouts).

use base64::Engine;
use cell_types::{JointState, Joints, PointCloud, Trajectory};
use nalgebra::{Isometry3, Point3};
use serde_json::{json, Value};

/// UR joint names, as in the UR ROS description.
pub const JOINT_NAMES: [&str; 6] = [
    "shoulder_pan_joint",
    "shoulder_lift_joint",
    "elbow_joint",
    "wrist_1_joint",
    "wrist_2_joint",
    "wrist_3_joint",
];

fn time(ns: u64) -> Value {
    json!({ "sec": ns / 1_000_000_000, "nsec": ns % 1_000_000_000 })
}

fn pose(iso: &Isometry3<f64>) -> Value {
    let t = iso.translation.vector;
    let q = iso.rotation.coords; // (i, j, k, w)
    json!({
        "position": { "x": t.x, "y": t.y, "z": t.z },
        "orientation": { "x": q[0], "y": q[1], "z": q[2], "w": q[3] },
    })
}

fn colour(r: f64, g: f64, b: f64, a: f64) -> Value {
    json!({ "r": r, "g": g, "b": b, "a": a })
}

/// A `foxglove.JointStates` message.
pub fn joint_states_message(t_ns: u64, state: &JointState) -> Value {
    let joints: Vec<Value> = (0..6)
        .map(|j| {
            json!({
                "name": JOINT_NAMES[j],
                "position": state.position[j],
                "velocity": state.velocity[j],
            })
        })
        .collect();
    json!({ "timestamp": time(t_ns), "joints": joints })
}

/// One `foxglove.FrameTransform` (goes inside a `foxglove.FrameTransforms` message).
pub fn frame_transform(
    t_ns: u64,
    parent: &str,
    child: &str,
    parent_from_child: &Isometry3<f64>,
) -> Value {
    let p = pose(parent_from_child);
    json!({
        "timestamp": time(t_ns),
        "parent_frame_id": parent,
        "child_frame_id": child,
        "translation": p["position"],
        "rotation": p["orientation"],
    })
}

/// A `foxglove.RawImage` holding a depth image in millimetres (`16UC1`, little endian).
pub fn depth_image_message(
    t_ns: u64,
    frame_id: &str,
    width: u32,
    height: u32,
    depth_mm: &[u16],
) -> Value {
    let mut bytes = Vec::with_capacity(depth_mm.len() * 2);
    for d in depth_mm {
        bytes.extend_from_slice(&d.to_le_bytes());
    }
    json!({
        "timestamp": time(t_ns),
        "frame_id": frame_id,
        "width": width,
        "height": height,
        "encoding": "16UC1",
        "step": width * 2,
        "data": base64::engine::general_purpose::STANDARD.encode(&bytes),
    })
}

/// A `foxglove.PointCloud`: x, y, z as float32, plus red, green, blue as uint8 when the
/// cloud has colour.
pub fn cloud_message(t_ns: u64, cloud: &PointCloud) -> Value {
    const FLOAT32: u32 = 7;
    const UINT8: u32 = 1;
    let with_rgb = cloud.rgb.is_some();
    let stride: usize = if with_rgb { 16 } else { 12 };
    let mut data = Vec::with_capacity(cloud.len() * stride);
    for (i, p) in cloud.points.iter().enumerate() {
        for v in [p.x, p.y, p.z] {
            data.extend_from_slice(&v.to_le_bytes());
        }
        if let Some(rgb) = &cloud.rgb {
            let c = rgb.get(i).copied().unwrap_or([0, 0, 0]);
            data.extend_from_slice(&[c[0], c[1], c[2], 255]);
        }
    }
    let mut fields = vec![
        json!({"name": "x", "offset": 0, "type": FLOAT32}),
        json!({"name": "y", "offset": 4, "type": FLOAT32}),
        json!({"name": "z", "offset": 8, "type": FLOAT32}),
    ];
    if with_rgb {
        fields.push(json!({"name": "red", "offset": 12, "type": UINT8}));
        fields.push(json!({"name": "green", "offset": 13, "type": UINT8}));
        fields.push(json!({"name": "blue", "offset": 14, "type": UINT8}));
    }
    json!({
        "timestamp": time(t_ns),
        "frame_id": cloud.frame.to_string(),
        "pose": pose(&Isometry3::identity()),
        "point_stride": stride,
        "fields": fields,
        "data": base64::engine::general_purpose::STANDARD.encode(&data),
    })
}

fn entity(t_ns: u64, frame_id: &str, id: &str, metadata: Vec<(String, String)>) -> Value {
    let metadata: Vec<Value> = metadata
        .into_iter()
        .map(|(k, v)| json!({"key": k, "value": v}))
        .collect();
    json!({
        "timestamp": time(t_ns),
        "frame_id": frame_id,
        "id": id,
        "lifetime": {"sec": 0, "nsec": 0},
        "frame_locked": false,
        "metadata": metadata,
        "arrows": [], "cubes": [], "spheres": [], "cylinders": [],
        "lines": [], "triangles": [], "texts": [], "models": [],
    })
}

/// A `foxglove.SceneUpdate` showing a keyframe as an arrow along the TCP approach axis (z),
/// green when the gripper is to be open, red when closed.
pub fn keyframe_scene(
    t_ns: u64,
    step: usize,
    base_from_tcp: &Isometry3<f64>,
    gripper_open: bool,
    ignore_collisions: bool,
) -> Value {
    // Foxglove arrows point along +x of their pose: turn +x onto the TCP's +z.
    let x_to_z = nalgebra::UnitQuaternion::from_axis_angle(
        &nalgebra::Vector3::y_axis(),
        -std::f64::consts::FRAC_PI_2,
    );
    let arrow_pose =
        Isometry3::from_parts(base_from_tcp.translation, base_from_tcp.rotation * x_to_z);
    let mut e = entity(
        t_ns,
        "base",
        &format!("keyframe_{step}"),
        vec![
            ("step".into(), step.to_string()),
            ("gripper_open".into(), gripper_open.to_string()),
            ("ignore_collisions".into(), ignore_collisions.to_string()),
        ],
    );
    let c = if gripper_open {
        colour(0.1, 0.8, 0.2, 1.0)
    } else {
        colour(0.9, 0.1, 0.1, 1.0)
    };
    e["arrows"] = json!([{
        "pose": pose(&arrow_pose),
        "shaft_length": 0.06, "shaft_diameter": 0.008,
        "head_length": 0.02, "head_diameter": 0.016,
        "color": c,
    }]);
    json!({ "deletions": [], "entities": [e] })
}

/// A `foxglove.SceneUpdate` showing a planned trajectory as the line strip its TCP follows.
pub fn trajectory_scene(
    t_ns: u64,
    step: usize,
    trajectory: &Trajectory,
    tcp_of: impl Fn(&Joints) -> Point3<f64>,
) -> Value {
    let points: Vec<Value> = trajectory
        .samples()
        .iter()
        .map(|s| {
            let p = tcp_of(&s.position);
            json!({"x": p.x, "y": p.y, "z": p.z})
        })
        .collect();
    let mut e = entity(
        t_ns,
        "base",
        &format!("trajectory_{step}"),
        vec![
            ("step".into(), step.to_string()),
            ("samples".into(), trajectory.len().to_string()),
            ("duration_s".into(), format!("{:.4}", trajectory.duration())),
        ],
    );
    e["lines"] = json!([{
        "type": 0,
        "pose": pose(&Isometry3::identity()),
        "thickness": 0.004,
        "scale_invariant": false,
        "points": points,
        "color": colour(0.2, 0.4, 1.0, 1.0),
        "colors": [],
        "indices": [],
    }]);
    json!({ "deletions": [], "entities": [e] })
}

/// Foxglove log levels.
#[derive(Copy, Clone, Debug, PartialEq, Eq)]
pub enum LogLevel {
    /// Informational.
    Info = 2,
    /// Something unexpected that the episode survived.
    Warning = 3,
    /// A fault.
    Error = 4,
}

/// A `foxglove.Log` message.
pub fn log_message(t_ns: u64, level: LogLevel, message: &str) -> Value {
    json!({
        "timestamp": time(t_ns),
        "level": level as u8,
        "message": message,
        "name": "equact",
        "file": "",
        "line": 0,
    })
}

/// An `equact.JointTrajectory`: the planned joint samples of one motion with the limits it
/// was planned under, logged when its execution starts (what `equact plot` draws).
pub fn joint_trajectory_message(
    step: usize,
    trajectory: &cell_types::Trajectory,
    limits: &cell_types::config::LimitsSection,
) -> Value {
    let samples = trajectory.samples();
    json!({
        "step": step,
        "period_s": trajectory.period(),
        "positions": samples.iter().map(|s| s.position).collect::<Vec<_>>(),
        "velocities": samples.iter().map(|s| s.velocity).collect::<Vec<_>>(),
        "accelerations": samples.iter().map(|s| s.acceleration).collect::<Vec<_>>(),
        "max_velocity": limits.max_velocity,
        "max_acceleration": limits.max_acceleration,
        "max_jerk": limits.max_jerk,
        "tracking_bound": limits.tracking_error_bound,
    })
}
