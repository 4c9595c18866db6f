#!/usr/bin/env python3
"""OpenCV's hand-eye calibrations on our captures folders (issue 8's side-by-side check).

Usage: calib_opencv.py ROOT
ROOT holds one captures folder per trial (session.json + pose_NNNN.json, see
calibration/src/capture.rs). For every trial, camera and method this prints one JSON line
{"trial", "camera", "method", "R" (3x3, row-major), "t" (m)} with OpenCV's base_from_camera.

Eye-to-hand (cameras fixed, board on the flange), per the OpenCV docs:
- calibrateHandEye: pass base2gripper (= inverse of FK, flange_from_base) as "gripper2base"
  and the PnP target2cam (camera_from_board); the result "cam2gripper" is base_from_camera.
- calibrateRobotWorldHandEye solves cam_T_world = cam_T_gripper gripper_T_base base_T_world;
  with the board in the role of "cam" and the camera in the role of "world":
  world2cam = board_from_camera (inverse PnP), base2gripper = flange_from_base; the result
  base2world is camera_from_base, inverted here.
Board poses come from cv2.solvePnP (SOLVEPNP_ITERATIVE) on the same corners; pixels are in
the OpenCV convention (pixel centre at integers), as the folder's session states.
"""
import json
import os
import sys

import cv2
import numpy as np

HAND_EYE = {
    "tsai": cv2.CALIB_HAND_EYE_TSAI,
    "park": cv2.CALIB_HAND_EYE_PARK,
    "horaud": cv2.CALIB_HAND_EYE_HORAUD,
    "andreff": cv2.CALIB_HAND_EYE_ANDREFF,
    "daniilidis": cv2.CALIB_HAND_EYE_DANIILIDIS,
}
ROBOT_WORLD = {
    "shah": cv2.CALIB_ROBOT_WORLD_HAND_EYE_SHAH,
    "li": cv2.CALIB_ROBOT_WORLD_HAND_EYE_LI,
}


def quat_to_r(q):
    x, y, z, w = q
    n = np.sqrt(x * x + y * y + z * z + w * w)
    x, y, z, w = x / n, y / n, z / n, w / n
    return np.array(
        [
            [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
            [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
            [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)],
        ]
    )


def invert(r, t):
    return r.T, -r.T @ t


def load(folder):
    with open(os.path.join(folder, "session.json")) as f:
        session = json.load(f)
    if session["pixel_convention"] != "centre_at_integer":
        raise SystemExit(f"{folder}: pixel convention {session['pixel_convention']} not handled")
    poses = []
    for name in sorted(os.listdir(folder)):
        if name.startswith("pose_") and name.endswith(".json"):
            with open(os.path.join(folder, name)) as f:
                poses.append(json.load(f))
    return session, poses


def calibrate(folder, trial):
    session, poses = load(folder)
    board = session["board"]
    rows, cols, sq = board["rows"], board["cols"], board["square_m"]
    out = []
    for cam in session["cameras"]:
        k = cam["intrinsics"]
        if k["distortion"]["model"] != "none":
            raise SystemExit("only undistorted (IR/depth) streams are handled")
        kmat = np.array([[k["fx"], 0, k["ppx"]], [0, k["fy"], k["ppy"]], [0, 0, 1.0]])
        r_g2b, t_g2b, r_t2c, t_t2c = [], [], [], []
        for p in poses:
            view = next((v for v in p["views"] if v["camera"] == cam["id"]), None)
            if view is None or len(view["corners"]) < 8:
                continue
            obj = np.array(
                [[(c["id"] % cols) * sq, (c["id"] // cols) * sq, 0.0] for c in view["corners"]]
            )
            img = np.array([[c["u"], c["v"]] for c in view["corners"]])
            ok, rvec, tvec = cv2.solvePnP(obj, img, kmat, None, flags=cv2.SOLVEPNP_ITERATIVE)
            if not ok:
                continue
            r_bf = quat_to_r(p["base_from_flange"]["rotation"])
            t_bf = np.array(p["base_from_flange"]["translation"])
            r_fb, t_fb = invert(r_bf, t_bf)
            r_cb, _ = cv2.Rodrigues(rvec)
            r_g2b.append(r_fb)
            t_g2b.append(t_fb)
            r_t2c.append(r_cb)
            t_t2c.append(tvec.reshape(3))
        for name, method in HAND_EYE.items():
            r, t = cv2.calibrateHandEye(r_g2b, t_g2b, r_t2c, t_t2c, method=method)
            out.append(dict(trial=trial, camera=cam["id"], method=name,
                            R=r.tolist(), t=t.reshape(3).tolist()))
        # Robot-world: world2cam = board_from_camera, base2gripper = flange_from_base.
        r_w2c, t_w2c = [], []
        for r_cb, t_cb in zip(r_t2c, t_t2c):
            r_bc, t_bc = invert(r_cb, t_cb)
            r_w2c.append(r_bc)
            t_w2c.append(t_bc)
        for name, method in ROBOT_WORLD.items():
            r_b2w, t_b2w, _, _ = cv2.calibrateRobotWorldHandEye(
                r_w2c, t_w2c, r_g2b, t_g2b, method=method
            )
            r, t = invert(r_b2w, t_b2w.reshape(3))
            out.append(dict(trial=trial, camera=cam["id"], method=name,
                            R=r.tolist(), t=t.reshape(3).tolist()))
    return out


def main():
    root = sys.argv[1]
    for trial in sorted(os.listdir(root)):
        folder = os.path.join(root, trial)
        if os.path.isfile(os.path.join(folder, "session.json")):
            for line in calibrate(folder, trial):
                print(json.dumps(line))
    print(json.dumps({"opencv": cv2.__version__}))


if __name__ == "__main__":
    main()
