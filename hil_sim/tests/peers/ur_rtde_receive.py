"""Independent peer: the SDU `ur-rtde` package's RTDEReceiveInterface reads the simulated
controller. RTDEReceiveInterface has no port argument (it always uses 30004), so the test
serves the simulator on a private loopback address instead.

Usage: ur_rtde_receive.py HOST SECONDS
Prints one JSON line "ready" with the first reading, then after SECONDS one JSON line with
the last reading and the largest joint change seen.
"""
import json
import sys
import time

import rtde_receive

host, seconds = sys.argv[1], float(sys.argv[2])
r = rtde_receive.RTDEReceiveInterface(host)


def reading():
    return {
        "actual_q": list(r.getActualQ()),
        "actual_tcp_pose": list(r.getActualTCPPose()),
        "robot_mode": r.getRobotMode(),
        "safety_mode": r.getSafetyMode(),
        "timestamp": r.getTimestamp(),
    }


first = reading()
print(json.dumps({"ready": first}), flush=True)
moved = 0.0
t_end = time.time() + seconds
while time.time() < t_end:
    q = r.getActualQ()
    moved = max(moved, max(abs(a - b) for a, b in zip(q, first["actual_q"])))
    time.sleep(0.01)
last = reading()
r.disconnect()
print(json.dumps({"last": last, "moved": moved}), flush=True)
