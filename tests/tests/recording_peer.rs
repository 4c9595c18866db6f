//! Recordings checked from outside: the Python `mcap` reader and Foxglove's published JSON
//! schemas accept every topic we write, with the counts we report, also when the file is
//! cut short.
#![allow(clippy::unwrap_used, clippy::expect_used)]

use std::collections::BTreeMap;

use cell_types::{FrameId, JointState, PointCloud, Trajectory, TrajectorySample};
use equact::recording::{self, EpisodeRecorder, LogLevel};
use nalgebra::{Isometry3, Point3, Translation3, UnitQuaternion};

fn sample_recording(path: &std::path::Path) -> BTreeMap<&'static str, u64> {
    let cfg = cell_types::config::CellConfig::simulated().unwrap();
    let mut meta = BTreeMap::new();
    meta.insert("seed".into(), "3".into());
    let mut rec = EpisodeRecorder::create(path, &meta).unwrap();
    rec.write(
        "/robot_description",
        0,
        &serde_json::json!({"data": "<robot name=\"ur5\"/>"}),
    )
    .unwrap();
    let pose = Isometry3::from_parts(
        Translation3::new(0.5, 0.1, 0.2),
        UnitQuaternion::from_euler_angles(3.1, 0.0, 0.4),
    );
    for step in 0..3usize {
        let t = step as u64 * 2_000_000_000;
        for k in 0..20u64 {
            let s = JointState::at_rest([0.01 * k as f64; 6]);
            rec.write(
                "/joint_states",
                t + k,
                &recording::joint_states_message(t + k, &s),
            )
            .unwrap();
            rec.write(
                "/tf",
                t + k,
                &serde_json::json!({"transforms": [recording::frame_transform(t + k, "base", "tcp", &pose)]}),
            )
            .unwrap();
        }
        let depth: Vec<u16> = (0..64 * 48).map(|i| (i % 2000) as u16).collect();
        rec.write(
            "/camera/depth",
            t,
            &recording::depth_image_message(t, "camera_0", 64, 48, &depth),
        )
        .unwrap();
        let cloud = PointCloud::new(
            FrameId::Base,
            (0..300)
                .map(|i| Point3::new(i as f32 * 1e-3, 0.2, 0.1))
                .collect(),
            Some(vec![[200, 100, 50]; 300]),
        )
        .unwrap();
        rec.write("/cloud/fused", t, &recording::cloud_message(t, &cloud))
            .unwrap();
        rec.write(
            "/keyframes",
            t,
            &recording::keyframe_scene(t, step, &pose, step % 2 == 0, false),
        )
        .unwrap();
        let samples = (0..10)
            .map(|i| TrajectorySample {
                t: i as f64 * 0.008,
                position: [0.01 * i as f64; 6],
                ..Default::default()
            })
            .collect();
        let traj = Trajectory::new(0.008, samples).unwrap();
        rec.write(
            "/trajectory/joints",
            t,
            &recording::joint_trajectory_message(step, &traj, &cfg.limits),
        )
        .unwrap();
        rec.write(
            "/trajectory/planned",
            t,
            &recording::trajectory_scene(t, step, &traj, |q| Point3::new(q[0], q[1], 0.3)),
        )
        .unwrap();
        rec.write(
            "/gripper",
            t,
            &serde_json::json!({"activated": true, "width_m": 0.04, "object": "ContactClosing", "current_a": 0.3, "fault": null}),
        )
        .unwrap();
        rec.write(
            "/episode/step",
            t,
            &serde_json::json!({"step": step, "phase": "plan", "duration_s": 0.003, "detail": "direct"}),
        )
        .unwrap();
        rec.write(
            "/log",
            t,
            &recording::log_message(t, LogLevel::Info, "step done"),
        )
        .unwrap();
        rec.checkpoint().unwrap();
    }
    rec.write(
        "/episode/outcome",
        7_000_000_000,
        &serde_json::json!({"outcome": "success", "success": true, "steps": 3, "detail": ""}),
    )
    .unwrap();
    let counts = rec.counts().clone();
    rec.finish().unwrap();
    counts
}

#[test]
fn python_mcap_reader_and_foxglove_schemas_accept_every_topic() {
    let dir = std::env::temp_dir().join(format!("equact-peer-rec-{}", std::process::id()));
    let path = dir.join("episode.mcap");
    let counts = sample_recording(&path);
    assert_eq!(
        counts.len(),
        recording::TOPICS.len(),
        "the sample must cover every topic"
    );
    let v = tests::check_recording_with_peer(&path).unwrap();
    assert_eq!(v["outcome"]["outcome"], "success");
    for (topic, n) in &counts {
        assert_eq!(
            v["counts"][topic].as_u64(),
            Some(*n),
            "count of {topic}: {v}"
        );
    }
    std::fs::remove_dir_all(dir).ok();
}

#[test]
fn truncated_recording_is_readable_by_python_up_to_its_last_chunk() {
    let dir = std::env::temp_dir().join(format!("equact-peer-trunc-{}", std::process::id()));
    let path = dir.join("episode.mcap");
    sample_recording(&path);
    let bytes = std::fs::read(&path).unwrap();
    let schemas = tests::foxglove_schemas().unwrap();
    // Seeded cut points across the file (a fixed LCG: the test is repeatable).
    let mut state: u64 = 0x5eed;
    for _ in 0..6 {
        state = state
            .wrapping_mul(6364136223846793005)
            .wrapping_add(1442695040888963407);
        let cut = 16 + (state >> 33) as usize % (bytes.len() - 16);
        let cut_path = dir.join(format!("cut_{cut}.mcap"));
        std::fs::write(&cut_path, &bytes[..cut]).unwrap();
        let ours = recording::inspect_bytes(&bytes[..cut]);
        let out = tests::run_peer(
            "check_mcap.py",
            &[
                cut_path.to_str().unwrap(),
                "--schemas",
                schemas.to_str().unwrap(),
                "--truncated",
            ],
        )
        .unwrap();
        let v: serde_json::Value = serde_json::from_str(out.trim()).unwrap();
        // Both readers agree on what survives the cut, and nothing that survived is invalid.
        let theirs: u64 = v["counts"]
            .as_object()
            .unwrap()
            .values()
            .map(|n| n.as_u64().unwrap())
            .sum();
        assert_eq!(
            theirs,
            ours.message_count(),
            "cut at {cut}: python {v} vs ours {ours:?}"
        );
        let schema_errors: Vec<_> = v["errors"]
            .as_array()
            .unwrap()
            .iter()
            .filter(|e| !e.as_str().unwrap_or("").starts_with("stream ended"))
            .collect();
        assert!(schema_errors.is_empty(), "{schema_errors:?}");
    }
    std::fs::remove_dir_all(dir).ok();
}
