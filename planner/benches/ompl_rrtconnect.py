#!/usr/bin/env python3
"""OMPL's RRTConnect on the MotionBenchMaker UR5 problems with the planner's own collision
checker, for the ratio printed by `equact bench planner --ompl PYTHON`.

The checker comes from the `planner_ffi` cdylib (libplanner_ffi.so, a C ABI over
planner::checker::Checker) loaded with ctypes, so OMPL and our RRT-Connect query exactly the
same robot spheres, the same world (exact primitives, or the distance field over the 1 cm
surface cloud, built before timing starts) and the same motion check: OMPL's MotionValidator
is replaced by one that calls the planner's `motion_free` (lever-bound spacing of the
planner's search, 4 cm, bisection order), so edge checking has the same resolution on both sides. OMPL's sampled
states are not checked on their own (RRTConnect only checks motions); start and goal are
valid by construction of the problems.

Setup (a benchmark-only virtual environment; the wheel is cp311 manylinux):

    python3 -m venv .venv-bench
    .venv-bench/bin/pip install ompl numpy          # ompl 2.0.1
    cargo build --release -p planner_ffi --bin equact
    target/release/equact bench planner --problems planner/data/mbm_ur5/problems.json \
        --ompl .venv-bench/bin/python

or directly:

    .venv-bench/bin/python planner/benches/ompl_rrtconnect.py --lib target/release/libplanner_ffi.so \
        --problems planner/data/mbm_ur5/problems.json --mode primitives --limit 10

Prints one JSON object on stdout: per problem the solve time (CPU time of this thread around
`SimpleSetup.solve`, like the thread CPU time `equact bench planner` reports for our search,
so that other processes on a shared machine do not skew the ratio; the wall clock as well;
planner setup done before; no simplification), solved or not, motion checks; and the median
/ p95 over solved problems. The time budget is OMPL's own (wall clock). Timing includes the Python callback per
motion check (OMPL calls back into Python, which calls the Rust checker via ctypes), as in
any Python-driven OMPL setup.
"""

import argparse
import ctypes
import importlib.metadata
import json
import os
import sys
import time


def load_lib(path):
    lib = ctypes.CDLL(path)
    p = ctypes.c_void_p
    dbl = ctypes.POINTER(ctypes.c_double)
    lib.eqp_suite_open.argtypes = [ctypes.c_char_p]
    lib.eqp_suite_open.restype = p
    lib.eqp_suite_close.argtypes = [p]
    lib.eqp_suite_limits.argtypes = [p, dbl, dbl]
    lib.eqp_problem_open.argtypes = [p, ctypes.c_char_p, ctypes.c_size_t, ctypes.c_uint32]
    lib.eqp_problem_open.restype = p
    lib.eqp_problem_close.argtypes = [p]
    lib.eqp_problem_start_goal.argtypes = [p, dbl]
    lib.eqp_is_valid.argtypes = [p, dbl]
    lib.eqp_is_valid.restype = ctypes.c_bool
    lib.eqp_motion_valid.argtypes = [p, dbl, dbl]
    lib.eqp_motion_valid.restype = ctypes.c_bool
    lib.eqp_checks.argtypes = [p]
    lib.eqp_checks.restype = ctypes.c_uint64
    lib.eqp_last_error.restype = ctypes.c_char_p
    return lib


def percentile(v, q):
    if not v:
        return None
    s = sorted(v)
    return s[round((len(s) - 1) * q)]


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--lib", required=True, help="path of libplanner_ffi.so")
    ap.add_argument("--problems", required=True, help="MBM problems.json")
    ap.add_argument("--mode", choices=["primitives", "cloud"], default="primitives")
    ap.add_argument("--limit", type=int, default=None, help="first N valid problems per scene")
    ap.add_argument("--budget", type=float, default=5.0, help="time budget per problem (s)")
    ap.add_argument("--range", type=float, default=0.0,
                    help="RRTConnect range (rad, L2); 0 keeps OMPL's default")
    a = ap.parse_args()

    try:
        from ompl import base as ob
        from ompl import geometric as og
        from ompl import util as ou
    except ImportError as e:
        print(json.dumps({"error": f"cannot import ompl ({e}); install it in a venv: "
                          "python3 -m venv .venv-bench && .venv-bench/bin/pip install ompl numpy"}))
        return 2
    ou.setLogLevel(ou.LogLevel.LOG_ERROR)

    lib = load_lib(a.lib)
    suite = lib.eqp_suite_open(a.problems.encode())
    if not suite:
        print(json.dumps({"error": lib.eqp_last_error().decode()}))
        return 2
    D6 = ctypes.c_double * 6
    lo, hi = D6(), D6()
    lib.eqp_suite_limits(suite, lo, hi)
    with open(a.problems) as f:
        problems = json.load(f)["problems"]
    mode = 0 if a.mode == "primitives" else 1

    space = ob.RealVectorStateSpace(6)
    bounds = ob.RealVectorBounds(6)
    for j in range(6):
        bounds.setLow(j, lo[j])
        bounds.setHigh(j, hi[j])
    space.setBounds(bounds)

    results = []
    for scene in sorted(problems):
        valid = [p for p in problems[scene] if p["valid"]]
        for prob in valid[: a.limit] if a.limit is not None else valid:
            h = lib.eqp_problem_open(suite, scene.encode(), prob["index"], mode)
            if not h:
                print(json.dumps({"error": lib.eqp_last_error().decode()}))
                return 2
            sg = (ctypes.c_double * 12)()
            lib.eqp_problem_start_goal(h, sg)
            qa, qb = D6(), D6()

            def valid_state(s, h=h, qa=qa):
                for j in range(6):
                    qa[j] = s[j]
                return lib.eqp_is_valid(h, qa)

            class Motion(ob.MotionValidator):
                def checkMotion(self, s1, s2, h=h, qa=qa, qb=qb):
                    for j in range(6):
                        qa[j] = s1[j]
                        qb[j] = s2[j]
                    return lib.eqp_motion_valid(h, qa, qb)

            ss = og.SimpleSetup(space)
            ss.setStateValidityChecker(valid_state)
            si = ss.getSpaceInformation()
            mv = Motion(si)
            si.setMotionValidator(mv)
            start, goal = space.allocState(), space.allocState()
            for j in range(6):
                start[j] = sg[j]
                goal[j] = sg[6 + j]
            ss.setStartAndGoalStates(start, goal)
            planner = og.RRTConnect(si)
            if a.range > 0:
                planner.setRange(a.range)
            ss.setPlanner(planner)
            ss.setup()
            t, w = time.thread_time(), time.perf_counter()
            status = ss.solve(a.budget)
            dt, wall = time.thread_time() - t, time.perf_counter() - w
            solved = bool(ss.haveExactSolutionPath())
            results.append({"scene": scene, "index": prob["index"], "solved": solved,
                            "status": str(status), "solve_s": dt, "wall_s": wall,
                            "checks": int(lib.eqp_checks(h))})
            del ss, planner, mv
            lib.eqp_problem_close(h)
    lib.eqp_suite_close(suite)
    ok = [r["solve_s"] * 1e3 for r in results if r["solved"]]
    out = {
        "ompl_version": importlib.metadata.version("ompl"),
        "mode": a.mode,
        "budget_s": a.budget,
        "range": a.range if a.range > 0 else "OMPL default",
        "solved": len(ok),
        "total": len(results),
        "solve_ms_median": percentile(ok, 0.5),
        "solve_ms_p95": percentile(ok, 0.95),
        "problems": results,
    }
    sys.stdout.write(json.dumps(out) + "\n")
    sys.stdout.flush()
    # Skip interpreter teardown: nanobind prints reference-leak noise for OMPL's bindings.
    os._exit(0)


if __name__ == "__main__":
    sys.exit(main())
