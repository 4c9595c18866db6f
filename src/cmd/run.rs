//! `equact run`: episodes end to end — in the built-in simulated cell when no config is
//! given (hil_sim on loopback, ephemeral ports), printing progress, the outcome and where
//! the recording is.

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::Arc;

use anyhow::Context;
use cell_types::config::RobotBackend;
use cell_types::{SystemClock, TickClock};
use clap::{Args, ValueEnum};
use equact::episode::{
    run_episode, run_sim_episode, KeyframeSource, OperatorJudged, Outcome, ScriptedExpert,
};
use equact::learned::LearnedPolicy;
use equact::real_cell::RealCell;
use equact::recording::EpisodeRecorder;
use equact::sim_cell::SimCell;
use equact::task::{TaskInstance, TaskKind};
use firmware_iface::arm::Arm;
use policy::predict::PolicyConfig;

use super::policy::HeadsArg;

/// Which policy drives the episode.
#[derive(Copy, Clone, Debug, PartialEq, Eq, ValueEnum)]
pub enum PolicyChoice {
    /// The EquAct network: the built-in model, or trained weights (`--weights`, also
    /// spelled `--model`; `equact train` makes them).
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
    /// install_toilet_roll/{large,small}; without a variation, the first. The default is
    /// the variation the built-in model does best (README, Training).
    #[arg(long, default_value = "pick_fruit/plum")]
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
    /// The simulator's speed.
    #[command(flatten)]
    pub sim: super::args::SimSpeedArgs,
    /// Which policy to run.
    #[arg(long, value_enum, default_value_t = PolicyChoice::Learned)]
    pub policy: PolicyChoice,
    /// Network weights for `--policy learned` (safetensors, as `equact policy predict` reads);
    /// the built-in model (`policy/weights/cpu_gated.safetensors`, compiled in) when omitted.
    /// `--model` is the same flag, as `eval` and `policy score` spell it.
    #[arg(long, alias = "model")]
    pub weights: Option<PathBuf>,
    /// Instruction embedding for `--policy learned` (safetensors, one F32 tensor: tokens x
    /// width, e.g. CLIP's 53 x 512).
    #[arg(long, conflicts_with = "minilm")]
    pub instruction_embedding: Option<PathBuf>,
    /// For `--policy learned`: embed the instruction (`--instruction`, or the variation's)
    /// with the MiniLM sentence model in this folder, as `equact train --minilm` does.
    /// Without this or `--instruction-embedding`, the built-in MiniLM embedding of the
    /// instruction (the simulated tasks' own wording only).
    #[arg(long)]
    pub minilm: Option<PathBuf>,
    /// Network size the weights were trained with (default: cpu for the built-in model,
    /// physical for `--weights`).
    #[arg(long, value_enum)]
    pub network: Option<NetworkSize>,
    /// Field heads the weights were trained with (`equact train --heads`).
    #[arg(long, value_enum, default_value_t = HeadsArg::Equivariant)]
    pub heads: HeadsArg,
    /// Next-ranked keyframes of the learned policy to try when the planner refuses its
    /// best one, each also moved back 1 and 2 cm along its approach axis (0: the network's
    /// argmax or nothing, as the paper evaluates).
    #[arg(long, default_value_t = equact::learned::DEFAULT_ALTERNATIVES)]
    pub alternatives: usize,
    /// Threads of each network prediction (1: the caller's only; the keyframes are the
    /// same for any count). Leave a core free for the UR driver on a real cell.
    #[arg(long, default_value_t = 1)]
    pub threads: usize,
    /// The network's translation sampling (learned policy).
    #[command(flatten)]
    pub sampling: super::policy::SamplingArgs,
    /// On a real cell, start moving without asking (for scripted runs; interactive runs
    /// ask for Enter first).
    #[arg(long)]
    pub yes: bool,
}

/// The network sizes `equact run --policy learned` can load.
#[derive(Copy, Clone, Debug, PartialEq, Eq, ValueEnum)]
pub enum NetworkSize {
    /// The physical-robot configuration: 2048 points, l_max 3, the reference's widths.
    Physical,
    /// The tiny test configuration (128 points, narrow layers).
    Tiny,
    /// The configuration trained on a 2-core CPU (512 points, 16-32 channels, gated).
    Cpu,
}

impl NetworkSize {
    /// The network configuration of this size.
    pub fn config(self) -> PolicyConfig {
        match self {
            Self::Physical => PolicyConfig::physical(),
            Self::Tiny => PolicyConfig::tiny(),
            Self::Cpu => PolicyConfig::cpu(),
        }
    }
}

/// The network configuration for the chosen weights (`None`: the built-in model, which is
/// the cpu network with equivariant heads; a weights file defaults to the physical size).
pub fn network_config(
    weights: Option<&Path>,
    network: Option<NetworkSize>,
    heads: HeadsArg,
) -> anyhow::Result<PolicyConfig> {
    if weights.is_none() {
        if network.is_some_and(|n| n != NetworkSize::Cpu) || heads != HeadsArg::Equivariant {
            anyhow::bail!(
                "the built-in model ({}) is the cpu network with equivariant heads; another \
                 --network or --heads needs its weights file (--weights / --model FILE)",
                policy::builtin::WEIGHTS_PATH
            );
        }
        return Ok(policy::builtin::config());
    }
    let mut cfg = network.unwrap_or(NetworkSize::Physical).config();
    cfg.model.heads = heads.kind();
    if let Some(path) = weights {
        // A network trained on another point count than its size's default says so in its
        // file; feeding it the default would blur what it learned.
        let header = policy::weights::Weights::header_only(path)
            .with_context(|| format!("reading the weights file {}", path.display()))?;
        if let Some(n) = header.trained_points()? {
            cfg = cfg.with_points(n);
        }
        cfg = cfg.with_near_gripper_points(header.trained_near_gripper_points()?.unwrap_or(0));
        let floor = header.trained_focus_above_table()?;
        cfg = cfg.with_focus_above_table(floor.unwrap_or(0.0));
    }
    Ok(cfg)
}

/// Says on stderr when the clouds of `source` (sampled as `now`) are not sampled as the
/// demonstrations of `weights` were (`equact::learned::perception_note`).
pub(crate) fn note_perception(
    weights: Option<&Path>,
    now: &cell_types::config::PerceptionSection,
    source: &str,
) -> anyhow::Result<()> {
    let trained = equact::learned::weights_perception(weights)?;
    if let Some(note) = equact::learned::perception_note(&trained, now, source) {
        eprintln!("{note}");
    }
    Ok(())
}

/// Names the weights a learned policy runs, for the terminal and the recordings.
pub fn describe_weights(weights: Option<&Path>) -> String {
    match weights {
        Some(w) => w.display().to_string(),
        None => format!(
            "the built-in model ({}, cpu network)",
            policy::builtin::WEIGHTS_PATH
        ),
    }
}

impl PolicyChoice {
    fn label(self) -> &'static str {
        match self {
            Self::Learned => "learned",
            Self::Expert => "expert",
        }
    }
}

/// Runs `equact run`.
pub fn run(args: RunArgs) -> anyhow::Result<()> {
    let cfg = super::config::load(args.config.as_ref())?;
    let real = cfg.robot.backend == RobotBackend::Ur;
    if real && args.policy == PolicyChoice::Expert {
        anyhow::bail!(
            "the scripted expert reads the simulator's true object poses, which a real cell \
             does not have: run a real cell with --policy learned (the default), or use the \
             simulated cell (no --config)"
        );
    }
    args.sim.refuse_on_real_cell(real)?;
    let learned_chosen = args.policy == PolicyChoice::Learned;
    // Checked before anything starts: a wrong size or heads for the built-in model fails now.
    let network = if learned_chosen {
        Some(args.sampling.apply(network_config(
            args.weights.as_deref(),
            args.network,
            args.heads,
        )?))
    } else {
        None
    };
    if learned_chosen {
        note_perception(
            args.weights.as_deref(),
            &cfg.perception,
            "this cell's fusion",
        )?;
    }
    let kind = TaskKind::parse(&args.task).map_err(anyhow::Error::msg)?;
    if let (Some(text), false) = (&args.instruction, learned_chosen) {
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

    // Load the network once, before any cell starts: a bad file fails fast.
    let mut learned = match network {
        None => None,
        Some(network) => {
            println!(
                "loading the EquAct network: {} (--policy expert runs the scripted expert)",
                describe_weights(args.weights.as_deref())
            );
            let text = args
                .instruction
                .clone()
                .unwrap_or_else(|| kind.instruction());
            let instruction = match (&args.instruction_embedding, &args.minilm) {
                (Some(file), _) => policy::predict::InstructionEmbedding::from_file(file)
                    .with_context(|| {
                        format!("reading the instruction embedding {}", file.display())
                    })?,
                (None, Some(dir)) => equact::train::Instructions::MiniLm(dir).embed_text(&text)?,
                (None, None) => equact::train::Instructions::Builtin.embed_text(&text)?,
            };
            let mut policy = LearnedPolicy::load_with(
                network,
                args.weights.as_deref(),
                instruction,
                &cfg,
                args.seed,
            )?;
            policy.set_alternatives(args.alternatives);
            policy.set_threads(args.threads);
            Some(policy)
        }
    };

    if real {
        let Some(policy) = learned.as_mut() else {
            anyhow::bail!("a real cell needs --policy learned");
        };
        return run_real(&args, &cfg, kind, policy, &interrupt, &stop_handles);
    }

    // Fuse with a calibration from `equact calibrate` instead of the simulator's true camera
    // poses when the config names one (relative to the config file); read once for all
    // episodes.
    let calibrated = if cfg.calibration.file.trim().is_empty() {
        None
    } else {
        let path = super::config::config_dir(args.config.as_ref()).join(&cfg.calibration.file);
        let calibration = calibration::read_calibration_toml(&path)
            .with_context(|| format!("reading the calibration {}", path.display()))?;
        Some((path, calibration))
    };

    let mut successes = 0;
    let mut failures = Vec::new();
    for e in 0..args.episodes {
        if interrupt.load(Ordering::SeqCst) {
            break;
        }
        let seed = args.seed + u64::from(e);
        let clock = Arc::new(TickClock::new(args.sim.speed)?);
        let task = TaskInstance::sample(kind, seed, cfg.workspace.table_height);
        println!(
            "episode {}/{} · task {} (\"{}\") · seed {seed} · policy {}",
            e + 1,
            args.episodes,
            kind.name(),
            kind.instruction(),
            args.policy.label()
        );
        let mut cell = SimCell::start(&cfg, task.clone(), seed, clock.clone())?;
        if let Some((path, calibration)) = &calibrated {
            let known: Vec<u8> = cell.calibration.cameras.iter().map(|c| c.id).collect();
            calibration
                .validate_against(&known)
                .with_context(|| format!("{} does not fit this cell", path.display()))?;
            cell.calibration = calibration.clone();
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
            args.policy.label()
        ));
        let mut meta = BTreeMap::new();
        meta.insert("task".into(), kind.name());
        meta.insert("instruction".into(), kind.instruction());
        meta.insert("seed".into(), seed.to_string());
        meta.insert("policy".into(), args.policy.label().into());
        if learned_chosen {
            meta.insert("weights".into(), describe_weights(args.weights.as_deref()));
            let instruction = match (&args.instruction_embedding, &args.minilm) {
                (Some(file), _) => ("instruction_embedding", file.display().to_string()),
                (None, Some(dir)) => ("minilm", dir.display().to_string()),
                (None, None) => (
                    "instruction_embedding",
                    format!("built-in ({})", policy::builtin::INSTRUCTIONS_PATH),
                ),
            };
            meta.insert(instruction.0.into(), instruction.1);
        }
        meta.insert("equact_version".into(), env!("CARGO_PKG_VERSION").into());
        meta.insert("config".into(), cfg.to_toml_string()?);
        let mut recorder = EpisodeRecorder::create(&path, &meta)?;
        let mut expert = ScriptedExpert::new(task.expert_keyframes());
        let source: &mut dyn KeyframeSource = match learned.as_mut() {
            Some(l) => {
                l.set_seed(seed);
                l
            }
            None => &mut expert,
        };
        let report = run_sim_episode(
            &cfg,
            &mut cell,
            source,
            &mut recorder,
            &interrupt,
            clock.as_ref(),
            seed,
        );
        print_report(&report);
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

/// Episodes on a real cell: the dry-run checks first (nothing moves unless every check
/// passes), then the same loop as the simulated cell with the learned policy. There is no
/// success test on a real cell: each episode ends when the keyframe limit is reached, on a
/// fault or on Ctrl-C, and the operator judges the outcome.
fn run_real(
    args: &RunArgs,
    cfg: &cell_types::config::CellConfig,
    kind: TaskKind,
    policy: &mut LearnedPolicy,
    interrupt: &Arc<AtomicBool>,
    stop_handles: &Arc<std::sync::Mutex<Vec<firmware_iface::arm::StopHandle>>>,
) -> anyhow::Result<()> {
    let config_dir = super::config::config_dir(args.config.as_ref());
    let clock: Arc<dyn cell_types::Clock> = Arc::new(SystemClock::new());
    println!("checking the cell before anything moves (as `equact check`)...");
    let checks = equact::preflight::run_checks(cfg, &config_dir, clock.clone());
    let failed: Vec<_> = checks.iter().filter(|c| !c.passed).collect();
    for c in &checks {
        println!(
            "  {} {:<12} {}",
            if c.passed { "ok  " } else { "FAIL" },
            c.name,
            c.detail
        );
    }
    if !failed.is_empty() {
        let fixes: Vec<String> = failed
            .iter()
            .map(|c| format!("{}: {}", c.name, c.fix))
            .collect();
        anyhow::bail!(
            "{} check(s) failed, nothing was moved; fix: {}",
            failed.len(),
            fixes.join("; ")
        );
    }
    let mut cell = RealCell::connect(cfg, &config_dir, clock.clone())?;
    equact::real_cell::confirm_motion(args.yes)?;
    if let Ok(mut handles) = stop_handles.lock() {
        handles.clear();
        handles.push(cell.arm.stop_handle());
    }
    let instruction = args
        .instruction
        .clone()
        .unwrap_or_else(|| kind.instruction());
    for e in 0..args.episodes {
        if interrupt.load(Ordering::SeqCst) {
            break;
        }
        if e > 0 {
            println!("reset the scene for episode {}, then press Enter", e + 1);
            let mut line = String::new();
            std::io::stdin()
                .read_line(&mut line)
                .context("waiting for Enter")?;
        }
        let seed = args.seed + u64::from(e);
        policy.set_seed(seed);
        println!(
            "episode {}/{} · real cell {} · \"{instruction}\" · seed {seed}",
            e + 1,
            args.episodes,
            cfg.robot.host
        );
        let stamp = std::time::SystemTime::now()
            .duration_since(std::time::UNIX_EPOCH)
            .map_or(0, |d| d.as_secs());
        let path = cfg.recording_dir().join(format!(
            "real_{}_seed{seed}_{stamp}.mcap",
            kind.name().replace('/', "-")
        ));
        let mut meta = BTreeMap::new();
        meta.insert("task".into(), kind.name());
        meta.insert("instruction".into(), instruction.clone());
        meta.insert("seed".into(), seed.to_string());
        meta.insert("policy".into(), "learned".into());
        meta.insert("cell".into(), "real".into());
        meta.insert("equact_version".into(), env!("CARGO_PKG_VERSION").into());
        meta.insert("config".into(), cfg.to_toml_string()?);
        let mut recorder = EpisodeRecorder::create(&path, &meta)?;
        let mut task = OperatorJudged {
            instruction: instruction.clone(),
        };
        let report = run_episode(
            cfg,
            cell.io(&mut task),
            policy,
            &mut recorder,
            interrupt,
            clock.as_ref(),
            seed,
        );
        print_report(&report);
    }
    if interrupt.load(Ordering::SeqCst) {
        anyhow::bail!("interrupted by Ctrl-C; the arm was stopped and the recording finished");
    }
    Ok(())
}

/// The end of one episode on the terminal: outcome and where the recording is.
fn print_report(report: &equact::episode::EpisodeReport) {
    println!(
        "  outcome: {} after {} keyframes ({})",
        report.outcome.label(),
        report.steps,
        report.detail
    );
    println!("  recording: {}", report.recording.display());
}

#[cfg(test)]
mod tests {
    #![allow(clippy::unwrap_used)]

    use super::*;

    #[test]
    fn the_builtin_model_is_the_cpu_network_with_equivariant_heads() {
        let builtin = network_config(None, None, HeadsArg::Equivariant).unwrap();
        assert_eq!(builtin.n_points, policy::builtin::config().n_points);
        assert!(network_config(None, Some(NetworkSize::Cpu), HeadsArg::Equivariant).is_ok());
        for (network, heads) in [
            (Some(NetworkSize::Physical), HeadsArg::Equivariant),
            (None, HeadsArg::Plain),
        ] {
            let err = network_config(None, network, heads)
                .unwrap_err()
                .to_string();
            assert!(err.contains("needs its weights file"), "{err}");
        }
        // A weights file keeps the documented default size, and takes the heads asked for.
        let dir =
            std::env::temp_dir().join(format!("equact_network_config_{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let file = dir.join("model.safetensors");
        let mut weights = policy::init::random_weights(
            &PolicyConfig::tiny().model,
            &PolicyConfig::tiny().extra,
            1,
        );
        weights.save(&file).unwrap();
        let physical = network_config(Some(&file), None, HeadsArg::Plain).unwrap();
        assert_eq!(physical.n_points, PolicyConfig::physical().n_points);
        assert_eq!(physical.model.heads, policy::model::HeadKind::Plain);
        assert!(describe_weights(None).contains(policy::builtin::WEIGHTS_PATH));
        assert_eq!(describe_weights(Some(&file)), file.display().to_string());
        // ... unless the file says how many points the network was trained with.
        weights.set_metadata(policy::weights::N_POINTS_KEY, "1024".into());
        weights.save(&file).unwrap();
        let cpu =
            network_config(Some(&file), Some(NetworkSize::Cpu), HeadsArg::Equivariant).unwrap();
        assert_eq!((cpu.n_points, cpu.n_outside_focus), (1024, 256));
        assert_eq!(cpu.focus_above_table, 0.0);
        // ... and where its focus box's floor was.
        weights.set_metadata(policy::weights::FOCUS_ABOVE_TABLE_KEY, "0.01".into());
        weights.save(&file).unwrap();
        let raised =
            network_config(Some(&file), Some(NetworkSize::Cpu), HeadsArg::Equivariant).unwrap();
        assert_eq!(raised.focus_above_table, 0.01);
        weights.set_metadata(policy::weights::FOCUS_ABOVE_TABLE_KEY, "-1".into());
        weights.save(&file).unwrap();
        let err = format!(
            "{:#}",
            network_config(Some(&file), Some(NetworkSize::Cpu), HeadsArg::Equivariant).unwrap_err()
        );
        assert!(err.contains("focus_above_table_m"), "{err}");
        // A file that cannot be read is named.
        let missing = dir.join("missing.safetensors");
        let err = format!(
            "{:#}",
            network_config(Some(&missing), None, HeadsArg::Equivariant).unwrap_err()
        );
        assert!(err.contains("missing.safetensors"), "{err}");
        std::fs::remove_dir_all(&dir).unwrap();
    }
}
