//! `equact run`: episodes end to end — in the built-in simulated cell when no config is
//! given (hil_sim on loopback, ephemeral ports), printing progress, the outcome and where
//! the recording is.

use std::collections::BTreeMap;
use std::path::PathBuf;
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::Arc;

use anyhow::Context;
use cell_types::config::RobotBackend;
use cell_types::SystemClock;
use clap::{Args, ValueEnum};
use equact::episode::{run_sim_episode, Outcome, ScriptedExpert};
use equact::recording::EpisodeRecorder;
use equact::sim_cell::SimCell;
use equact::task::{TaskInstance, TaskKind};
use firmware_iface::arm::Arm;

/// Which policy drives the episode.
#[derive(Copy, Clone, Debug, PartialEq, Eq, ValueEnum)]
pub enum PolicyChoice {
    /// The trained EquAct network (needs committed weights; not trained yet).
    Learned,
    /// The scripted expert, from the simulator's true object poses.
    Expert,
}

/// Arguments of `equact run`.
#[derive(Args, Debug)]
pub struct RunArgs {
    /// The cell configuration; the built-in simulated cell when omitted.
    #[arg(long)]
    pub config: Option<PathBuf>,
    /// Task and variation: pick_fruit/{strawberry,peach,plum},
    /// disassemble_pipe/{first_link,second_link,all}, pluck_flower/{top,middle,bottom},
    /// install_toilet_roll/{large,small}; without a variation, the first.
    #[arg(long, default_value = "pick_fruit/strawberry")]
    pub task: String,
    /// Language instruction (defaults to the task variation's own).
    #[arg(long)]
    pub instruction: Option<String>,
    /// Number of episodes.
    #[arg(long, default_value_t = 1)]
    pub episodes: u32,
    /// Seed of the first episode (each next episode adds one).
    #[arg(long, default_value_t = 0)]
    pub seed: u64,
    /// Which policy to run.
    #[arg(long, value_enum, default_value_t = PolicyChoice::Expert)]
    pub policy: PolicyChoice,
}

/// Runs `equact run`.
pub fn run(args: RunArgs) -> anyhow::Result<()> {
    let cfg = super::config::load(args.config.as_ref())?;
    if cfg.robot.backend == RobotBackend::Ur {
        anyhow::bail!(
            "running on a real UR controller is not wired into `equact run` yet: the drivers \
             (firmware_iface::ur::UrArm, RobotiqGripper, realsense::RealSenseCamera) work, \
             `equact check --config FILE` checks the cell without moving it and `equact \
             perceive --config FILE` captures and fuses the cameras; use the simulated cell \
             (no --config) for episodes for now"
        );
    }
    if args.policy == PolicyChoice::Learned {
        anyhow::bail!(
            "no trained EquAct weights are committed yet (issue 9); run with --policy expert"
        );
    }
    let kind = TaskKind::parse(&args.task).map_err(anyhow::Error::msg)?;
    if let Some(text) = &args.instruction {
        if *text != kind.instruction() {
            anyhow::bail!(
                "the scripted expert follows the task variation, not free text: `{text}` is not \
                 `{}`; choose the variation with --task",
                kind.instruction()
            );
        }
    }
    let interrupt = Arc::new(AtomicBool::new(false));
    let stop_handles: Arc<std::sync::Mutex<Vec<firmware_iface::arm::StopHandle>>> = Arc::default();
    {
        let interrupt = interrupt.clone();
        let stop_handles = stop_handles.clone();
        ctrlc::set_handler(move || {
            // Ctrl-C stops the arm with its controlled deceleration; the loop then finishes
            // the recording and reports the outcome.
            interrupt.store(true, Ordering::SeqCst);
            if let Ok(handles) = stop_handles.lock() {
                for h in handles.iter() {
                    h.request();
                }
            }
            eprintln!("\nCtrl-C: stopping the arm...");
        })
        .context("installing the Ctrl-C handler")?;
    }

    let mut successes = 0;
    let mut failures = Vec::new();
    for e in 0..args.episodes {
        if interrupt.load(Ordering::SeqCst) {
            break;
        }
        let seed = args.seed + u64::from(e);
        let clock = Arc::new(SystemClock::new());
        let task = TaskInstance::sample(kind, seed, cfg.workspace.table_height);
        println!(
            "episode {}/{} · task {} (\"{}\") · seed {seed} · policy {:?}",
            e + 1,
            args.episodes,
            kind.name(),
            kind.instruction(),
            args.policy
        );
        let mut cell = SimCell::start(&cfg, task.clone(), seed, clock.clone())?;
        if !cfg.calibration.file.trim().is_empty() {
            // Fuse with a calibration from `equact calibrate` instead of the simulator's true
            // camera poses (the file is relative to the config file).
            let dir = args
                .config
                .as_ref()
                .and_then(|p| p.parent())
                .map(PathBuf::from)
                .unwrap_or_default();
            let path = dir.join(&cfg.calibration.file);
            let calibration = calibration::read_calibration_toml(&path)
                .with_context(|| format!("reading the calibration {}", path.display()))?;
            let known: Vec<u8> = cell.calibration.cameras.iter().map(|c| c.id).collect();
            calibration
                .validate_against(&known)
                .with_context(|| format!("{} does not fit this cell", path.display()))?;
            cell.calibration = calibration;
            println!("  cameras calibrated from {}", path.display());
        }
        if let Ok(mut handles) = stop_handles.lock() {
            handles.clear();
            handles.push(cell.arm.stop_handle());
        }
        println!(
            "  simulated cell: RTDE {}, dashboard {}, secondary {}, gripper {} ({} cameras)",
            cell.controller.ports().rtde,
            cell.controller.ports().dashboard,
            cell.controller.ports().secondary,
            cell.gripper_server
                .addr()
                .map_or_else(|| "?".to_string(), |a| a.to_string()),
            cell.cameras.len()
        );
        let stamp = std::time::SystemTime::now()
            .duration_since(std::time::UNIX_EPOCH)
            .map_or(0, |d| d.as_secs());
        let path = cfg.recording_dir().join(format!(
            "{}_{}_seed{seed}_{stamp}.mcap",
            kind.name().replace('/', "-"),
            "expert"
        ));
        let mut meta = BTreeMap::new();
        meta.insert("task".into(), kind.name());
        meta.insert("instruction".into(), kind.instruction());
        meta.insert("seed".into(), seed.to_string());
        meta.insert("policy".into(), format!("{:?}", args.policy));
        meta.insert("equact_version".into(), env!("CARGO_PKG_VERSION").into());
        meta.insert("config".into(), cfg.to_toml_string()?);
        let mut recorder = EpisodeRecorder::create(&path, &meta)?;
        let mut expert = ScriptedExpert::new(task.expert_keyframes());
        let report = run_sim_episode(
            &cfg,
            &mut cell,
            &mut expert,
            &mut recorder,
            &interrupt,
            clock.as_ref(),
            seed,
        );
        println!(
            "  outcome: {} after {} keyframes ({})",
            report.outcome.label(),
            report.steps,
            report.detail
        );
        println!("  recording: {}", report.recording.display());
        if report.outcome == Outcome::Success {
            successes += 1;
        } else {
            failures.push(format!("seed {seed}: {}", report.outcome.label()));
        }
        cell.controller.shutdown();
    }
    println!(
        "{successes}/{} episodes succeeded{}",
        args.episodes,
        if failures.is_empty() {
            String::new()
        } else {
            format!(" ({})", failures.join(", "))
        }
    );
    if interrupt.load(Ordering::SeqCst) {
        anyhow::bail!("interrupted by Ctrl-C; the arm was stopped and the recording finished");
    }
    Ok(())
}
