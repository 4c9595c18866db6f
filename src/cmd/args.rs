//! Helpers shared by subcommands: comma-separated numbers, the simulator's speed, cloud
//! files, the Ctrl-C flag.

use std::path::Path;
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::Arc;

use anyhow::Context;
use cell_types::PointCloud;

/// Parses `--what` as exactly `N` comma-separated numbers.
pub fn numbers<const N: usize>(s: &str, what: &str) -> anyhow::Result<[f64; N]> {
    let v: Vec<f64> = s
        .split(',')
        .map(|x| x.trim().parse::<f64>())
        .collect::<Result<_, _>>()
        .with_context(|| format!("--{what} must be {N} comma-separated numbers"))?;
    v.try_into()
        .map_err(|v: Vec<f64>| anyhow::anyhow!("--{what} has {} numbers, need {N}", v.len()))
}

/// `--sim-speed`, of every command that runs episodes in the simulated cell.
#[derive(clap::Args, Debug, Clone, Copy)]
pub struct SimSpeedArgs {
    /// Run the simulated cell this many times faster than real time (above 0, at most 16;
    /// 1, the real cell's pace, by default). The controller, gripper, cameras and episode
    /// all keep the simulator's time, so episodes play out as in real time while the
    /// driver still answers the controller: the servo watchdog's 200 ms of simulated time
    /// is 200/S ms of wall time (README, "Faster than real time").
    #[arg(long = "sim-speed", default_value_t = 1.0, value_parser = sim_speed)]
    pub speed: f64,
}

impl SimSpeedArgs {
    /// Refuses a speed other than real time for a real cell, whose arm moves in real time.
    pub fn refuse_on_real_cell(self, real: bool) -> anyhow::Result<()> {
        if real && self.speed != 1.0 {
            anyhow::bail!(
                "--sim-speed {} applies to the simulated cell only: a real arm moves in real \
                 time; omit --sim-speed with a real cell's --config",
                self.speed
            );
        }
        Ok(())
    }
}

/// Parses `--sim-speed`: how many times faster than real time the simulated cell runs
/// (above 0, at most [`cell_types::ScaledClock::MAX_SPEED`]).
fn sim_speed(s: &str) -> Result<f64, String> {
    let v: f64 = s
        .trim()
        .parse()
        .map_err(|e| format!("{s:?} is not a number ({e})"))?;
    cell_types::TickClock::new(v)
        .map(|c| cell_types::Clock::speed(&c))
        .map_err(|e| e.to_string())
}

/// Reads a point cloud file (PLY or PCD, see `planner::cloud_io`).
pub fn read_cloud_file(path: &Path) -> anyhow::Result<PointCloud> {
    let bytes = std::fs::read(path).with_context(|| format!("reading {}", path.display()))?;
    planner::cloud_io::read_cloud(&bytes).with_context(|| format!("parsing {}", path.display()))
}

/// A flag Ctrl-C sets (printing `message`), for loops that stop at their next safe point.
pub fn interrupt_flag(message: &'static str) -> anyhow::Result<Arc<AtomicBool>> {
    let interrupt = Arc::new(AtomicBool::new(false));
    let flag = interrupt.clone();
    ctrlc::set_handler(move || {
        flag.store(true, Ordering::SeqCst);
        eprintln!("\nCtrl-C: {message}");
    })
    .context("installing the Ctrl-C handler")?;
    Ok(interrupt)
}

/// Prints `value` as pretty JSON with `--json`, else its Markdown table.
pub fn print_json_or_markdown(
    json: bool,
    value: &impl serde::Serialize,
    markdown: impl FnOnce() -> String,
) -> anyhow::Result<()> {
    if json {
        println!("{}", serde_json::to_string_pretty(value)?);
    } else {
        print!("{}", markdown());
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A real arm moves in real time: another speed is refused there, named, and allowed
    /// for the simulated cell.
    #[test]
    fn a_real_cell_refuses_another_speed() {
        let fast = SimSpeedArgs { speed: 4.0 };
        let err = fast.refuse_on_real_cell(true).unwrap_err().to_string();
        assert!(
            err.contains("--sim-speed 4") && err.contains("real"),
            "{err}"
        );
        assert!(fast.refuse_on_real_cell(false).is_ok());
        assert!(SimSpeedArgs { speed: 1.0 }
            .refuse_on_real_cell(true)
            .is_ok());
    }
}
