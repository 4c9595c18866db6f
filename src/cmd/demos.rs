//! `equact demos collect`: records scripted-expert demonstrations in the simulated cell into
//! a dataset directory (one safetensors shard per episode plus `index.json`; see
//! [`equact::demos`]). Restarting with the same arguments skips the episodes already done.

use std::path::PathBuf;
use std::sync::atomic::Ordering;

use clap::{Args, Subcommand};
use equact::task::TaskKind;

/// Arguments of `equact demos`.
#[derive(Args, Debug)]
pub struct DemosArgs {
    /// What to do.
    #[command(subcommand)]
    pub command: DemosCommand,
}

/// `equact demos` subcommands.
#[derive(Subcommand, Debug)]
pub enum DemosCommand {
    /// Record expert demonstrations in the simulated cell.
    Collect(CollectArgs),
}

/// Arguments of `equact demos collect`.
#[derive(Args, Debug)]
pub struct CollectArgs {
    /// `task/variation`, a task name (all its variations) or `all` (every task variation).
    #[arg(long)]
    pub task: String,
    /// Episodes per task variation.
    #[arg(long, default_value_t = 10)]
    pub episodes: u64,
    /// Seed of the first episode of each variation (the next ones add one).
    #[arg(long, default_value_t = 0)]
    pub seed: u64,
    /// The dataset directory (created when missing; an existing one is resumed).
    #[arg(long)]
    pub out: PathBuf,
    /// The cell configuration; the built-in simulated cell when omitted.
    #[arg(long)]
    pub config: Option<PathBuf>,
    /// Toilet roll: execute each grasp turned about the jaws' closing axis by a random angle
    /// up to this many degrees (0-30), record the clean grasp as the label, and place the
    /// turned roll's axis along the spindle; shows a policy how to place a roll its own grasp
    /// left turned in the hand. 0, the plain expert, by default; the dataset's index records it.
    #[arg(long, default_value_t = 0.0)]
    pub grasp_turn: f64,
}

/// The task variations `--task` names.
pub fn kinds_for(task: &str) -> anyhow::Result<Vec<TaskKind>> {
    if task == "all" {
        return Ok(TaskKind::all());
    }
    if let Some(v) = TaskKind::variations_of(task) {
        return Ok(v);
    }
    Ok(vec![TaskKind::parse(task)?])
}

/// Runs `equact demos`.
pub fn run(args: DemosArgs) -> anyhow::Result<()> {
    let DemosCommand::Collect(args) = args.command;
    let cfg = super::config::load(args.config.as_ref())?;
    if cfg.robot.backend != cell_types::config::RobotBackend::Sim {
        anyhow::bail!(
            "demonstrations are recorded in the simulated cell only for now; omit --config or \
             use a cell configuration with backend = \"sim\""
        );
    }
    let kinds = kinds_for(&args.task)?;
    let interrupt =
        super::args::interrupt_flag("finishing the current episode's stop; rerun to resume")?;
    println!(
        "recording {} episodes of {} task variation(s) into {}",
        args.episodes * kinds.len() as u64,
        kinds.len(),
        args.out.display()
    );
    let s = equact::demos::collect(
        &cfg,
        &kinds,
        args.episodes,
        args.seed,
        &args.out,
        &equact::task::ExpertSettings {
            grasp_turn_deg: args.grasp_turn,
        },
        &interrupt,
    )?;
    println!(
        "{} recorded, {} already there, {} failed (listed in index.json without a shard)",
        s.recorded, s.skipped, s.failed
    );
    if interrupt.load(Ordering::SeqCst) {
        anyhow::bail!("interrupted by Ctrl-C; rerun the same command to resume");
    }
    Ok(())
}
