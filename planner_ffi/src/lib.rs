//! C ABI over the planner's sphere collision checker (`planner::checker::Checker`) on one
//! MotionBenchMaker problem, so that OMPL's RRTConnect (from Python, via ctypes) plans with
//! exactly the checker our RRT-Connect uses: the same robot spheres, the same world (exact
//! primitives or the 1 cm surface cloud's distance field) and the same motion check (lever
//! bound, the planner's search spacing, bisection order). `equact bench planner --ompl`
//! drives it through `planner/benches/ompl_rrtconnect.py`.
//!
//! Protocol: `eqp_suite_open(path)` parses the problems file once; `eqp_problem_open(suite,
//! scene, index, mode)` builds one problem's world (the cloud build is not part of any
//! timing); `eqp_is_valid`, `eqp_motion_valid` answer queries; `eqp_*_close` frees. On
//! failure a function returns null / false and `eqp_last_error()` says why.
//!
//! Only std and the planner: ctypes needs nothing more than `extern "C"` functions.

use planner::checker::Checker;
use planner::mbm::{mbm_robot, MbmFile, WorldMode};
use planner::{PlannerConfig, RobotModel, World};
use std::cell::RefCell;
use std::ffi::{c_char, CStr, CString};

thread_local! {
    static LAST_ERROR: RefCell<CString> = RefCell::new(CString::default());
}

fn set_error(msg: impl Into<String>) {
    let s = CString::new(msg.into().replace('\0', " ")).unwrap_or_default();
    LAST_ERROR.with(|e| *e.borrow_mut() = s);
}

/// The problems file and the MBM robot.
pub struct Suite {
    file: MbmFile,
    model: RobotModel,
}

/// One problem: its world and a checker over it.
pub struct Problem {
    /// Borrows `model` and `world`; `None` only while dropping.
    checker: Option<Checker<'static>>,
    model: *mut RobotModel,
    world: *mut World,
    start: [f64; 6],
    goal: [f64; 6],
}

impl Problem {
    fn checker(&mut self) -> Option<&mut Checker<'static>> {
        self.checker.as_mut()
    }
}

impl Drop for Problem {
    fn drop(&mut self) {
        // The checker goes first: it borrows the model and the world.
        self.checker = None;
        // SAFETY: both came from Box::into_raw in `open_problem`, are freed only here, and
        // nothing borrows them any more.
        unsafe {
            drop(Box::from_raw(self.world));
            drop(Box::from_raw(self.model));
        }
    }
}

/// Parses a problems file and loads the MBM robot, or returns null (see `eqp_last_error`).
///
/// # Safety
/// `path` must be a NUL-terminated string.
#[no_mangle]
pub unsafe extern "C" fn eqp_suite_open(path: *const c_char) -> *mut Suite {
    if path.is_null() {
        set_error("null path");
        return std::ptr::null_mut();
    }
    // SAFETY: the caller passes a NUL-terminated string.
    let path = unsafe { CStr::from_ptr(path) }
        .to_string_lossy()
        .into_owned();
    let text = match std::fs::read_to_string(&path) {
        Ok(t) => t,
        Err(e) => {
            set_error(format!("reading {path}: {e}"));
            return std::ptr::null_mut();
        }
    };
    match (MbmFile::parse(&text), mbm_robot()) {
        (Ok(file), Ok(model)) => Box::into_raw(Box::new(Suite { file, model })),
        (Err(e), _) | (_, Err(e)) => {
            set_error(e.to_string());
            std::ptr::null_mut()
        }
    }
}

/// Frees a suite (null is ignored).
///
/// # Safety
/// `suite` must come from `eqp_suite_open` and not be used afterwards.
#[no_mangle]
pub unsafe extern "C" fn eqp_suite_close(suite: *mut Suite) {
    if !suite.is_null() {
        // SAFETY: from Box::into_raw in eqp_suite_open.
        drop(unsafe { Box::from_raw(suite) });
    }
}

/// Joint limits of the MBM robot: `lo[6]`, `hi[6]` (rad).
///
/// # Safety
/// `suite` must be valid; `lo` and `hi` must point to 6 writable doubles each.
#[no_mangle]
pub unsafe extern "C" fn eqp_suite_limits(suite: *const Suite, lo: *mut f64, hi: *mut f64) {
    // SAFETY: per the contract above.
    let (s, lo, hi) = unsafe {
        (
            &*suite,
            std::slice::from_raw_parts_mut(lo, 6),
            std::slice::from_raw_parts_mut(hi, 6),
        )
    };
    for j in 0..6 {
        (lo[j], hi[j]) = s.model.limits[j];
    }
}

fn open_problem(s: &Suite, scene: &str, index: usize, mode: u32) -> Result<Problem, String> {
    let mode = match mode {
        0 => WorldMode::Primitives,
        1 => WorldMode::Cloud,
        m => return Err(format!("mode {m}: use 0 (primitives) or 1 (cloud)")),
    };
    let p = s
        .file
        .problems
        .get(scene)
        .and_then(|ps| ps.iter().find(|p| p.index == index))
        .ok_or_else(|| format!("no problem {scene} #{index}"))?;
    let (start, goal) = p.start_goal().map_err(|e| e.to_string())?;
    let world = p.world(mode).map_err(|e| e.to_string())?;
    let model = Box::into_raw(Box::new(s.model.clone()));
    let world = Box::into_raw(Box::new(world));
    // SAFETY: both boxes live until Problem's Drop, which replaces the checker first.
    let (m, w): (&'static RobotModel, &'static World) = unsafe { (&*model, &*world) };
    Ok(Problem {
        checker: Some(Checker::new(
            m,
            w,
            PlannerConfig::default().check_resolution,
        )),
        model,
        world,
        start,
        goal,
    })
}

/// Builds one problem's world (`mode` 0: primitives, 1: 1 cm surface cloud), or null.
///
/// # Safety
/// `suite` must be valid and `scene` NUL-terminated.
#[no_mangle]
pub unsafe extern "C" fn eqp_problem_open(
    suite: *const Suite,
    scene: *const c_char,
    index: usize,
    mode: u32,
) -> *mut Problem {
    if suite.is_null() || scene.is_null() {
        set_error("null suite or scene");
        return std::ptr::null_mut();
    }
    // SAFETY: per the contract above.
    let (s, scene) = unsafe { (&*suite, CStr::from_ptr(scene).to_string_lossy()) };
    match open_problem(s, &scene, index, mode) {
        Ok(p) => Box::into_raw(Box::new(p)),
        Err(e) => {
            set_error(e);
            std::ptr::null_mut()
        }
    }
}

/// Frees a problem (null is ignored).
///
/// # Safety
/// `p` must come from `eqp_problem_open` and not be used afterwards.
#[no_mangle]
pub unsafe extern "C" fn eqp_problem_close(p: *mut Problem) {
    if !p.is_null() {
        // SAFETY: from Box::into_raw in eqp_problem_open.
        drop(unsafe { Box::from_raw(p) });
    }
}

/// The problem's start and goal: `out[0..6]` start, `out[6..12]` goal.
///
/// # Safety
/// `p` must be valid and `out` point to 12 writable doubles.
#[no_mangle]
pub unsafe extern "C" fn eqp_problem_start_goal(p: *const Problem, out: *mut f64) {
    // SAFETY: per the contract above.
    let (p, out) = unsafe { (&*p, std::slice::from_raw_parts_mut(out, 12)) };
    out[..6].copy_from_slice(&p.start);
    out[6..].copy_from_slice(&p.goal);
}

/// True when `q[6]` is within limits and free.
///
/// # Safety
/// `p` must be valid (and used from one thread at a time) and `q` point to 6 doubles.
#[no_mangle]
pub unsafe extern "C" fn eqp_is_valid(p: *mut Problem, q: *const f64) -> bool {
    // SAFETY: per the contract above.
    let (p, q) = unsafe { (&mut *p, &*(q as *const [f64; 6])) };
    p.checker().is_some_and(|c| c.is_free(q))
}

/// True when the straight segment `a[6]` → `b[6]` is free, `b` included and `a` assumed
/// valid (OMPL's `checkMotion` contract): the planner's own motion check.
///
/// # Safety
/// `p` must be valid (one thread at a time); `a` and `b` point to 6 doubles each.
#[no_mangle]
pub unsafe extern "C" fn eqp_motion_valid(p: *mut Problem, a: *const f64, b: *const f64) -> bool {
    // SAFETY: per the contract above.
    let (p, a, b) = unsafe { (&mut *p, &*(a as *const [f64; 6]), &*(b as *const [f64; 6])) };
    p.checker().is_some_and(|c| c.motion_free(a, b))
}

/// Configurations checked on this problem so far.
///
/// # Safety
/// `p` must be valid.
#[no_mangle]
pub unsafe extern "C" fn eqp_checks(p: *const Problem) -> u64 {
    // SAFETY: per the contract above.
    unsafe { (*p).checker.as_ref().map_or(0, |c| c.checks) }
}

/// The last error of this thread, NUL-terminated (valid until the next failing call).
#[no_mangle]
pub extern "C" fn eqp_last_error() -> *const c_char {
    LAST_ERROR.with(|e| e.borrow().as_ptr())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn checks_an_mbm_problem_through_the_c_abi_and_reports_errors() {
        let path =
            CString::new(planner::mbm::MBM_PROBLEMS_PATH).unwrap_or_else(|_| CString::default());
        // SAFETY: valid NUL-terminated strings and buffers of the documented sizes.
        unsafe {
            let suite = eqp_suite_open(path.as_ptr());
            assert!(!suite.is_null());
            let (mut lo, mut hi) = ([0.0; 6], [0.0; 6]);
            eqp_suite_limits(suite, lo.as_mut_ptr(), hi.as_mut_ptr());
            assert!(lo.iter().zip(&hi).all(|(l, h)| l < h));
            let scene = CString::new("cage").unwrap_or_default();
            for mode in [0, 1] {
                let p = eqp_problem_open(suite, scene.as_ptr(), 1, mode);
                assert!(!p.is_null());
                let mut sg = [0.0; 12];
                eqp_problem_start_goal(p, sg.as_mut_ptr());
                assert!(eqp_is_valid(p, sg.as_ptr()));
                assert!(eqp_is_valid(p, sg[6..].as_ptr()));
                // Outside the joint limits is invalid; a short move from the start is free.
                let mut out = [0.0; 6];
                out.copy_from_slice(&sg[..6]);
                out[0] = hi[0] + 0.1;
                assert!(!eqp_is_valid(p, out.as_ptr()));
                let mut near = [0.0; 6];
                near.copy_from_slice(&sg[..6]);
                near[5] -= 0.05;
                assert!(eqp_motion_valid(p, sg.as_ptr(), near.as_ptr()));
                // Folded onto itself: the motion there is blocked.
                let folded = [sg[0], sg[1], 3.1, sg[3], sg[4], sg[5]];
                assert!(!eqp_motion_valid(p, sg.as_ptr(), folded.as_ptr()));
                assert!(eqp_checks(p) > 3);
                eqp_problem_close(p);
            }
            let missing = CString::new("no_such_scene").unwrap_or_default();
            assert!(eqp_problem_open(suite, missing.as_ptr(), 1, 0).is_null());
            let err = CStr::from_ptr(eqp_last_error()).to_string_lossy();
            assert!(err.contains("no_such_scene"), "{err}");
            assert!(eqp_problem_open(suite, scene.as_ptr(), 1, 7).is_null());
            eqp_suite_close(suite);
        }
    }
}
