#!/usr/bin/env python3
"""Open3D peer for the fusion benchmark (hil_sim/benches/fusion.rs).

Reads little-endian float32 xyz triples (base frame, metres), runs Open3D's crop to the
EquAct workspace, 5 mm voxel_down_sample and remove_statistical_outlier(20, 2.0), and
prints the median times (ms) and point counts as JSON. Open3D is for benchmarks only; it is
not needed by the test suite. Install: `pip install open3d numpy` (in any venv; pass its
python with `--python` to the Rust benchmark).
"""
import argparse
import json
import sys
import time

try:
    import numpy as np
    import open3d as o3d
except ImportError as e:  # reported by the Rust side as "unavailable"
    sys.stderr.write(f"open3d/numpy not importable ({e}); pip install open3d numpy\n")
    sys.exit(2)


def median_ms(reps, f):
    times, out = [], None
    for _ in range(reps):
        t = time.perf_counter()
        out = f()
        times.append((time.perf_counter() - t) * 1e3)
    times.sort()
    return times[len(times) // 2], out


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("points")
    ap.add_argument("--voxel", type=float, default=0.005)
    ap.add_argument("--reps", type=int, default=5)
    a = ap.parse_args()
    xyz = np.fromfile(a.points, dtype="<f4").reshape(-1, 3).astype(np.float64)
    pcd = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(xyz))
    box = o3d.geometry.AxisAlignedBoundingBox([0.18, -0.39, -0.10], [0.96, 0.39, 0.53])
    crop_ms, cropped = median_ms(a.reps, lambda: pcd.crop(box))
    voxel_ms, vox = median_ms(a.reps, lambda: cropped.voxel_down_sample(a.voxel))
    sor_ms, (inl, _) = median_ms(a.reps, lambda: vox.remove_statistical_outlier(20, 2.0))
    print(json.dumps({
        "open3d_version": o3d.__version__,
        "input_points": len(pcd.points),
        "crop_ms": crop_ms, "voxel_ms": voxel_ms, "outliers_ms": sor_ms,
        "total_ms": crop_ms + voxel_ms + sor_ms,
        "after_crop": len(cropped.points), "after_voxel": len(vox.points),
        "after_outliers": len(inl.points),
    }))


if __name__ == "__main__":
    main()
