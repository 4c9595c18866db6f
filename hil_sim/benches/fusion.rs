//! Benchmark: three simulated 848x480 D455 frames to the fused, downsampled cloud (issue 7),
//! compared in the same run with Open3D doing crop + voxel + outlier removal on the same
//! points (`open3d_fusion.py`, run with the Python given by `--python`, default
//! `<workspace>/.venv/bin/python3`). Prints one JSON object.
//!
//! `cargo bench -p hil_sim --bench fusion [-- --python /path/to/python3 --reps 5]`

use std::path::PathBuf;
use std::process::Command;
use std::time::{Duration, Instant};

use calibration::fusion::{
    remove_statistical_outliers, voxel_downsample, Bounds, FusionParams, FusionPipeline, Points,
};
use hil_sim::depth_camera::{default_rig, render_rig, rig_calibration};
use hil_sim::scene::{robot_capsules, Scene, HOME_Q};
use serde_json::json;

fn median_ms<T>(reps: usize, mut f: impl FnMut() -> T) -> (f64, T) {
    let mut times = Vec::with_capacity(reps);
    let mut last = None;
    for _ in 0..reps.max(1) {
        let t = Instant::now();
        let out = f();
        times.push(t.elapsed());
        last = Some(out);
    }
    times.sort();
    let med = times[times.len() / 2];
    (ms(med), last.unwrap_or_else(|| unreachable!()))
}

fn ms(d: Duration) -> f64 {
    d.as_secs_f64() * 1e3
}

fn main() -> anyhow::Result<()> {
    let ws_root = PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("..");
    let mut python = ws_root.join(".venv/bin/python3");
    let mut reps = 5usize;
    let mut args = std::env::args().skip(1);
    while let Some(a) = args.next() {
        match a.as_str() {
            "--python" => python = PathBuf::from(args.next().unwrap_or_default()),
            "--reps" => reps = args.next().unwrap_or_default().parse()?,
            _ => {} // cargo passes --bench
        }
    }

    let scene = Scene::default_cell();
    let geometry = scene.build()?;
    let mut rig = default_rig(1);
    let threads = rig[0].threads;
    for c in &mut rig {
        c.threads = 1;
    }
    let (render_1, _) = median_ms(3, || render_rig(&rig, &geometry, 0, Duration::ZERO));
    for c in &mut rig {
        c.threads = threads;
    }
    let (render_n, frames) = median_ms(3, || render_rig(&rig, &geometry, 0, Duration::ZERO));
    let frames = frames?;

    let robot = robot_capsules(&HOME_Q, 0.085);
    let params = FusionParams::default();
    let pipe = FusionPipeline::new(rig_calibration(&rig), params.clone())?;
    let (fuse_dense_ms, dense) = median_ms(reps, || pipe.fuse_dense(&frames, &robot));
    let (dense, stats) = dense?;
    let (sample_ms, sampled) = median_ms(reps, || pipe.sample(&dense));
    let sampled = sampled?;

    // The same work as Open3D on the same points: every valid pixel deprojected to the base
    // frame (no crop, no edge filter), then crop + voxel + statistical outliers.
    let everything = FusionParams {
        workspace: Bounds {
            min: [-100.0; 3],
            max: [100.0; 3],
        },
        edge_jump_m: 0.0,
        ..params.clone()
    };
    let all_pipe = FusionPipeline::new(rig_calibration(&rig), everything)?;
    let mut merged = Points::default();
    for f in &frames {
        let (p, _) = all_pipe.camera_points(f)?;
        merged.xyz.extend(p.xyz);
    }
    let ws = params.workspace;
    let (crop_ms, cropped) = median_ms(reps, || Points {
        xyz: merged
            .xyz
            .iter()
            .copied()
            .filter(|p| ws.contains(p))
            .collect(),
        rgb: Vec::new(),
    });
    let (voxel_ms, voxels) = median_ms(reps, || {
        voxel_downsample(&cropped, params.voxel_m, pipe.voxel_origin())
    });
    let (sor_ms, inliers) = median_ms(reps, || {
        remove_statistical_outliers(
            &voxels,
            params.outlier_k,
            params.outlier_std_ratio,
            params.voxel_m * 3.0,
        )
    });
    let ours_same = crop_ms + voxel_ms + sor_ms;

    // Hand the merged points to Open3D.
    let dir = ws_root.join("target/perception_bench");
    std::fs::create_dir_all(&dir)?;
    let bin = dir.join("merged_xyz_f32.bin");
    let mut bytes = Vec::with_capacity(merged.len() * 12);
    for p in &merged.xyz {
        for v in [p.x, p.y, p.z] {
            bytes.extend_from_slice(&v.to_le_bytes());
        }
    }
    std::fs::write(&bin, bytes)?;
    let script = PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("benches/open3d_fusion.py");
    let open3d = match Command::new(&python)
        .arg(&script)
        .arg(&bin)
        .args([
            "--voxel",
            &params.voxel_m.to_string(),
            "--reps",
            &reps.to_string(),
        ])
        .output()
    {
        Ok(out) if out.status.success() => {
            serde_json::from_slice::<serde_json::Value>(&out.stdout)?
        }
        Ok(out) => {
            json!({ "unavailable": String::from_utf8_lossy(&out.stderr).trim().to_string() })
        }
        Err(e) => json!({ "unavailable": format!("cannot run {}: {e}", python.display()) }),
    };
    let open3d_total = ["crop_ms", "voxel_ms", "outliers_ms"]
        .iter()
        .map(|k| open3d.get(*k).and_then(|v| v.as_f64()))
        .sum::<Option<f64>>();

    let report = json!({
        "benchmark": "three 848x480 D455 frames -> fused downsampled cloud",
        "threads_available": threads,
        "render_three_frames_ms": { "threads_1": render_1, format!("threads_{threads}"): render_n },
        "pipeline": {
            "fuse_dense_ms": fuse_dense_ms,
            "fps_sample_ms": sample_ms,
            "stats": stats,
            "sampled_points": sampled.len(),
        },
        "same_work_as_open3d": {
            "input_points": merged.len(),
            "crop_ms": crop_ms, "voxel_ms": voxel_ms, "outliers_ms": sor_ms, "total_ms": ours_same,
            "after_crop": cropped.len(), "after_voxel": voxels.len(), "after_outliers": inliers.len(),
        },
        "open3d": open3d,
        "speedup_vs_open3d": open3d_total.map(|t| t / ours_same),
        "speedup_full_pipeline_vs_open3d_crop_voxel_outliers": open3d_total.map(|t| t / fuse_dense_ms),
    });
    println!("{}", serde_json::to_string_pretty(&report)?);
    Ok(())
}
