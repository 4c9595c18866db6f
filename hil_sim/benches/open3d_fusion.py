#!/usr/bin/env python3
"""Open3D peer for the fusion benchmark (hil_sim/benches/fusion.rs).

Reads little-endian float32 xyz triples (base frame, metres), runs Open3D's crop to the
EquAct workspace, voxel_down_sample and remove_statistical_outlier(k, ratio), and prints the
median wall and CPU times (ms) and point counts as JSON. CPU time above wall time shows that
Open3D ran a stage on several threads (its statistical outlier removal is OpenMP-parallel;
OMP_NUM_THREADS=1 pins it to one). Open3D is for benchmarks only; it is not needed by the
test suite. Install: `pip install open3d numpy` (in any venv; pass its python with
`--python` to the Rust benchmark).
"""
import argparse
import json
import os
import sys
import time

try:
    import numpy as np
    import open3d as o3d
except ImportError as e:  # reported by the Rust side as "unavailable"
    sys.stderr.write(f"open3d/numpy not importable ({e}); pip install open3d numpy\n")
    sys.exit(2)


def median_ms(reps, f):
    """Median wall and CPU (all threads) time of `reps` calls, and the last result."""
    walls, cpus, out = [], [], None
    for _ in range(reps):
        c, t = time.process_time(), time.perf_counter()
        out = f()
        walls.append((time.perf_counter() - t) * 1e3)
        cpus.append((time.process_time() - c) * 1e3)
    walls.sort()
    cpus.sort()
    return walls[len(walls) // 2], cpus[len(cpus) // 2], out


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("points")
    ap.add_argument("--voxel", type=float, default=0.005)
    ap.add_argument("--k", type=int, default=20)
    ap.add_argument("--ratio", type=float, default=2.0)
    ap.add_argument("--min", type=float, nargs=3, default=[0.18, -0.39, -0.10])
    ap.add_argument("--max", type=float, nargs=3, default=[0.96, 0.39, 0.53])
    ap.add_argument("--reps", type=int, default=3)
    a = ap.parse_args()
    # float64 is Open3D's point type: convert outside the timed stages.
    xyz = np.fromfile(a.points, dtype="<f4").reshape(-1, 3).astype(np.float64)
    pcd = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(xyz))
    box = o3d.geometry.AxisAlignedBoundingBox(a.min, a.max)
    crop_ms, crop_cpu, cropped = median_ms(a.reps, lambda: pcd.crop(box))
    voxel_ms, voxel_cpu, vox = median_ms(a.reps, lambda: cropped.voxel_down_sample(a.voxel))
    sor_ms, sor_cpu, (inl, _) = median_ms(
        a.reps, lambda: vox.remove_statistical_outlier(a.k, a.ratio)
    )
    print(json.dumps({
        "open3d_version": o3d.__version__,
        "omp_num_threads": os.environ.get("OMP_NUM_THREADS"),
        "cpu_count": os.cpu_count(),
        "input_points": len(pcd.points),
        "crop_ms": crop_ms, "voxel_ms": voxel_ms, "outliers_ms": sor_ms,
        "total_ms": crop_ms + voxel_ms + sor_ms,
        "crop_cpu_ms": crop_cpu, "voxel_cpu_ms": voxel_cpu, "outliers_cpu_ms": sor_cpu,
        "after_crop": len(cropped.points), "after_voxel": len(vox.points),
        "after_outliers": len(inl.points),
    }))


if __name__ == "__main__":
    main()
