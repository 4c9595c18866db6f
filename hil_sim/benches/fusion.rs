//! Benchmark: three simulated 848x480 D455 frames to the fused, downsampled cloud (issue 7),
//! compared in the same run with Open3D doing crop + voxel + outlier removal on the same
//! points, in alternating rounds (`open3d_fusion.py`, run with the Python given by
//! `--python`, default `<workspace>/.venv/bin/python3`). Prints one JSON object.
//!
//! What each side measures:
//! - `ours_full_pipeline_ms`: `FusionPipeline::fuse_dense` from the three raw depth frames:
//!   deprojection, depth-edge filter, crop, merge, voxels, robot removal, outlier removal
//!   (more work than Open3D's three stages, which start from deprojected points).
//! - Per stage on the same input as Open3D (every valid pixel of the three cameras
//!   deprojected to the base frame, no edge filter): crop to the workspace, voxel downsample
//!   with the grid anchored as Open3D anchors it (half a voxel below the cloud's minimum,
//!   so both produce the same voxels), statistical outlier removal with 20 neighbours and
//!   ratio 2. Open3D counts the point itself among its k, so it runs with k = 21: the same
//!   20 neighbours and, the mean being only rescaled, the same inliers.
//! - Ours is single-threaded. Open3D's outlier removal is OpenMP-parallel: it runs once with
//!   its default thread count and once with `OMP_NUM_THREADS=1`, and both ratios are given.
//!   Each side's stage time is the median of `--inner` calls; the speed-ups are medians of
//!   the per-round ratios. Open3D works on f64 points (converted outside the timing).
//! - Wall times on a loaded machine swing with the load; the `cpu_*` ratios compare thread
//!   CPU time of the two single-threaded runs, which the load does not inflate.
//! - `pipeline.fps_sample_ms` / `fps_sample_cpu_ms`: `FusionPipeline::sample` (farthest point
//!   sampling to the policy's points) on the fused cloud, which Open3D's side does not do.
//! - The `*_hash` fields fingerprint the clouds (voxels, inliers, dense, sampled):
//!   equal hashes before and after a change show that it kept the output bit for bit.
//!
//! `cargo bench -p hil_sim --bench fusion [-- --python /path/to/python3 --reps 5 --inner 3]`
//! `--profile N` runs only our pipeline N times (for callgrind) and prints nothing else;
//! `--profile-sample N` runs `FusionPipeline::sample` (farthest point sampling) N times on
//! its output; `--profile-stages N` runs our voxel and outlier stages on Open3D's input.

use std::path::PathBuf;
use std::process::Command;
use std::time::{Duration, Instant};

use calibration::fusion::{
    remove_statistical_outliers, voxel_downsample, Bounds, FusionParams, FusionPipeline, Points,
};
use cpu_time::ThreadTime;
use hil_sim::depth_camera::{default_rig, render_rig, rig_calibration};
use hil_sim::scene::{robot_capsules, Scene, HOME_Q};
use serde_json::{json, Value};

fn median_ms<T>(reps: usize, f: impl FnMut() -> T) -> (f64, T) {
    let (wall, _, out) = median_wall_cpu_ms(reps, f);
    (wall, out)
}

/// Median wall and CPU times (ms) of `reps` calls, and the last result.
fn median_wall_cpu_ms<T>(reps: usize, mut f: impl FnMut() -> T) -> (f64, f64, T) {
    let mut walls = Vec::with_capacity(reps);
    let mut cpus = Vec::with_capacity(reps);
    let mut last = None;
    for _ in 0..reps.max(1) {
        let c = ThreadTime::now();
        let t = Instant::now();
        let out = f();
        walls.push(ms(t.elapsed()));
        cpus.push(ms(c.elapsed()));
        last = Some(out);
    }
    walls.sort_by(f64::total_cmp);
    cpus.sort_by(f64::total_cmp);
    (
        walls[walls.len() / 2],
        cpus[cpus.len() / 2],
        last.unwrap_or_else(|| unreachable!()),
    )
}

/// FNV-1a of the points' bits: equal clouds (same points, same order) hash equal, so that
/// runs before and after a change show that its output did not change.
fn cloud_hash(points: &Points) -> String {
    let mut h = 0xcbf2_9ce4_8422_2325u64;
    for p in &points.xyz {
        for v in [p.x, p.y, p.z] {
            for b in v.to_bits().to_le_bytes() {
                h = (h ^ u64::from(b)).wrapping_mul(0x0000_0100_0000_01b3);
            }
        }
    }
    format!("{h:016x}")
}

fn ms(d: Duration) -> f64 {
    d.as_secs_f64() * 1e3
}

/// Median over rounds of one field of the rounds' records.
fn median_of(rounds: &[Value], key: &str) -> Option<f64> {
    let mut v: Vec<f64> = rounds.iter().filter_map(|r| r[key].as_f64()).collect();
    v.sort_by(f64::total_cmp);
    v.get(v.len() / 2).copied()
}

/// Runs the Open3D peer once (`single_thread`: with `OMP_NUM_THREADS=1`).
fn open3d(python: &PathBuf, args: &[String], single_thread: bool) -> Value {
    let script = PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("benches/open3d_fusion.py");
    let mut cmd = Command::new(python);
    cmd.arg(&script).args(args);
    if single_thread {
        cmd.env("OMP_NUM_THREADS", "1");
    }
    match cmd.output() {
        Ok(out) if out.status.success() => serde_json::from_slice::<Value>(&out.stdout)
            .unwrap_or_else(
                |e| json!({ "unavailable": format!("bad JSON from Open3D peer: {e}") }),
            ),
        Ok(out) => {
            json!({ "unavailable": String::from_utf8_lossy(&out.stderr).trim().to_string() })
        }
        Err(e) => json!({ "unavailable": format!("cannot run {}: {e}", python.display()) }),
    }
}

fn main() -> anyhow::Result<()> {
    let ws_root = PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("..");
    let mut python = ws_root.join(".venv/bin/python3");
    let mut reps = 5usize;
    let mut inner = 3usize;
    let mut profile = None;
    let mut profile_sample = None;
    let mut profile_stages = None;
    let mut args = std::env::args().skip(1);
    while let Some(a) = args.next() {
        match a.as_str() {
            "--python" => python = PathBuf::from(args.next().unwrap_or_default()),
            "--reps" => reps = args.next().unwrap_or_default().parse()?,
            "--inner" => inner = args.next().unwrap_or_default().parse()?,
            "--profile" => profile = Some(args.next().unwrap_or_default().parse::<usize>()?),
            "--profile-stages" => {
                profile_stages = Some(args.next().unwrap_or_default().parse::<usize>()?)
            }
            "--profile-sample" => {
                profile_sample = Some(args.next().unwrap_or_default().parse::<usize>()?)
            }
            _ => {} // cargo passes --bench
        }
    }

    let scene = Scene::default_cell();
    let geometry = scene.build()?;
    let mut rig = default_rig(1);
    let robot = robot_capsules(&HOME_Q, 0.085);
    let params = FusionParams::default();
    let pipe = FusionPipeline::new(rig_calibration(&rig), params.clone())?;
    if let Some(n) = profile {
        let frames = render_rig(&rig, &geometry, 0, Duration::ZERO)?;
        for _ in 0..n {
            std::hint::black_box(pipe.fuse_dense(&frames, &robot)?);
        }
        return Ok(());
    }
    if let Some(n) = profile_sample {
        let frames = render_rig(&rig, &geometry, 0, Duration::ZERO)?;
        let (dense, _) = pipe.fuse_dense(&frames, &robot)?;
        for _ in 0..n {
            std::hint::black_box(pipe.sample(&dense)?);
        }
        return Ok(());
    }
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

    let (fuse_dense_ms, dense) = median_ms(reps, || pipe.fuse_dense(&frames, &robot));
    let (dense, stats) = dense?;
    let (sample_ms, sample_cpu_ms, sampled) = median_wall_cpu_ms(reps, || pipe.sample(&dense));
    let sampled = sampled?;

    // The same input as Open3D's: every valid pixel deprojected to the base frame (no crop,
    // no edge filter).
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
    let [lo, hi] = [ws.min, ws.max].map(|c| c.map(|v| v as f32));
    let crop = || Points {
        xyz: merged
            .xyz
            .iter()
            .copied()
            .filter(|p| (0..3).all(|a| p[a] >= lo[a] && p[a] <= hi[a]))
            .collect(),
        rgb: Vec::new(),
    };
    let cropped = crop();
    // Open3D's voxel grid corner: half a voxel below the cropped cloud's minimum.
    let mut min = [f64::INFINITY; 3];
    for p in &cropped.xyz {
        for a in 0..3 {
            min[a] = min[a].min(f64::from(p[a]));
        }
    }
    let o3d_origin = min.map(|v| v - params.voxel_m / 2.0);
    let f = |v: f64| v.to_string();
    let o3d_args: Vec<String> = [
        bin.display().to_string(),
        "--voxel".into(),
        f(params.voxel_m),
    ]
    .into_iter()
    .chain(["--k".into(), (params.outlier_k + 1).to_string()])
    .chain(["--ratio".into(), f(params.outlier_std_ratio)])
    .chain(std::iter::once("--min".to_string()).chain(ws.min.map(f)))
    .chain(std::iter::once("--max".to_string()).chain(ws.max.map(f)))
    .chain(["--reps".into(), inner.to_string()])
    .collect();

    if let Some(n) = profile_stages {
        for _ in 0..n {
            let voxels = voxel_downsample(&cropped, params.voxel_m, o3d_origin);
            std::hint::black_box(remove_statistical_outliers(
                &voxels,
                params.outlier_k,
                params.outlier_std_ratio,
                params.voxel_m * 3.0,
            ));
        }
        return Ok(());
    }
    // Rounds alternate ours and Open3D so that both see the same machine load (the build
    // machine is shared); the speed-ups are the medians of the per-round ratios.
    let mut rounds = Vec::new();
    let mut counts = json!(null);
    let mut last = [json!(null), json!(null)];
    for _ in 0..reps.max(1) {
        let (full_ms, full_cpu, _) = median_wall_cpu_ms(inner, || pipe.fuse_dense(&frames, &robot));
        let (crop_ms, crop_cpu, cropped) = median_wall_cpu_ms(inner, crop);
        let (voxel_ms, voxel_cpu, voxels) = median_wall_cpu_ms(inner, || {
            voxel_downsample(&cropped, params.voxel_m, o3d_origin)
        });
        let (sor_ms, sor_cpu, inliers) = median_wall_cpu_ms(inner, || {
            remove_statistical_outliers(
                &voxels,
                params.outlier_k,
                params.outlier_std_ratio,
                params.voxel_m * 3.0,
            )
        });
        counts = json!({
            "input_points": merged.len(), "after_crop": cropped.len(),
            "after_voxel": voxels.len(), "after_outliers": inliers.len(),
            "voxels_hash": cloud_hash(&voxels), "inliers_hash": cloud_hash(&inliers),
        });
        let ours = crop_ms + voxel_ms + sor_ms;
        let mut round = json!({
            "ours_crop_ms": crop_ms, "ours_voxel_ms": voxel_ms, "ours_outliers_ms": sor_ms,
            "ours_total_ms": ours, "ours_full_pipeline_ms": full_ms,
            "ours_crop_cpu_ms": crop_cpu, "ours_voxel_cpu_ms": voxel_cpu,
            "ours_outliers_cpu_ms": sor_cpu, "ours_total_cpu_ms": crop_cpu + voxel_cpu + sor_cpu,
            "ours_full_pipeline_cpu_ms": full_cpu,
        });
        for (i, (single, tag)) in [(false, "open3d"), (true, "open3d_1thread")]
            .into_iter()
            .enumerate()
        {
            let o = open3d(&python, &o3d_args, single);
            for stage in ["crop", "voxel", "outliers", "total"] {
                let t = o[format!("{stage}_ms")].as_f64();
                let ours_stage = round[format!("ours_{stage}_ms")].as_f64();
                round[format!("{tag}_{stage}_ms")] = json!(t);
                round[format!("speedup_vs_{tag}_{stage}")] =
                    json!(t.zip(ours_stage).map(|(t, o)| t / o));
            }
            round[format!("speedup_full_pipeline_vs_{tag}")] =
                json!(o["total_ms"].as_f64().map(|t| t / full_ms));
            if single {
                // Both single-threaded: CPU time is the like-for-like cost under load.
                for stage in ["crop", "voxel", "outliers"] {
                    let t = o[format!("{stage}_cpu_ms")].as_f64();
                    round[format!("{tag}_{stage}_cpu_ms")] = json!(t);
                    round[format!("cpu_speedup_vs_{tag}_{stage}")] = json!(t
                        .zip(round[format!("ours_{stage}_cpu_ms")].as_f64())
                        .map(|(t, o)| t / o));
                }
                let t: Option<f64> = ["crop", "voxel", "outliers"]
                    .iter()
                    .map(|s| o[format!("{s}_cpu_ms")].as_f64())
                    .sum();
                round[format!("{tag}_total_cpu_ms")] = json!(t);
                round[format!("cpu_speedup_vs_{tag}_total")] =
                    json!(t.map(|t| t / (crop_cpu + voxel_cpu + sor_cpu)));
                round[format!("cpu_speedup_full_pipeline_vs_{tag}")] =
                    json!(t.map(|t| t / full_cpu));
            }
            last[i] = o;
        }
        rounds.push(round);
    }

    let mut summary = serde_json::Map::new();
    let keys: Vec<String> = rounds[0]
        .as_object()
        .map(|o| o.keys().cloned().collect())
        .unwrap_or_default();
    for key in keys {
        summary.insert(key.clone(), json!(median_of(&rounds, &key)));
    }
    let [o3d_last, o3d_1_last] = last;
    let report = json!({
        "benchmark": "three 848x480 D455 frames -> fused downsampled cloud",
        "threads": { "ours": 1, "open3d": o3d_last["cpu_count"], "open3d_1thread": 1,
                     "machine_cpus": std::thread::available_parallelism().map(|n| n.get()).ok() },
        "render_three_frames_ms": { "threads_1": render_1, format!("threads_{threads}"): render_n },
        "pipeline": {
            "fuse_dense_ms": fuse_dense_ms,
            "fps_sample_ms": sample_ms,
            "fps_sample_cpu_ms": sample_cpu_ms,
            "stats": stats,
            "dense_hash": cloud_hash(&dense),
            "sampled_points": sampled.len(),
            "sampled_hash": cloud_hash(&sampled),
        },
        "same_work_as_open3d": {
            "ours_counts": counts,
            "open3d_last_round": o3d_last,
            "open3d_1thread_last_round": o3d_1_last,
        },
        "median_over_rounds": summary,
        "rounds": rounds,
    });
    println!("{}", serde_json::to_string_pretty(&report)?);
    Ok(())
}
