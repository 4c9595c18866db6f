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
    /// Write one dataset holding the episodes of several (shards checked and copied; an
    /// episode listed by two sources is taken from the later one).
    Merge(MergeArgs),
}

/// Arguments of `equact demos merge`.
#[derive(Args, Debug)]
pub struct MergeArgs {
    /// The new dataset's folder (it must not hold an index.json yet).
    #[arg(long)]
    pub out: PathBuf,
    /// The datasets to merge, in order: where two list the same task variation and seed,
    /// the later one's episode is kept (unless it failed where the earlier succeeded).
    #[arg(required = true, num_args = 1..)]
    pub sources: Vec<PathBuf>,
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
    /// The simulator's speed.
    #[command(flatten)]
    pub sim: super::args::SimSpeedArgs,
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
    /// Toilet roll: record the approach and the grasp centred along the pads while the arm
    /// executes them at the episode's random offset along the pads (up to 6 mm); the release
    /// still places the off-centre roll over the spindle. Keeps the offset, which no
    /// observation shows before the grasp, out of the grasp labels. Off by default (a
    /// fine-tune on such demonstrations grasped further off-centre; README, "Centred grasp
    /// labels"); the dataset's index records it.
    #[arg(long)]
    pub centred_grasp_labels: bool,
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
    match args.command {
        DemosCommand::Collect(args) => collect(args),
        DemosCommand::Merge(args) => merge(args),
    }
}

/// Runs `equact demos merge`.
fn merge(args: MergeArgs) -> anyhow::Result<()> {
    let s = equact::demos::merge(&args.sources, &args.out)?;
    for r in &s.replaced {
        println!(
            "{}: {} episode(s) of {} replaced by those of {}",
            r.task,
            r.episodes,
            r.earlier.display(),
            r.later.display()
        );
    }
    println!(
        "{} episodes ({} demonstrations) from {} dataset(s) in {}",
        s.episodes,
        s.shards,
        args.sources.len(),
        args.out.display()
    );
    Ok(())
}

/// Runs `equact demos collect`.
fn collect(args: CollectArgs) -> anyhow::Result<()> {
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
    let plan = equact::sim_cell::EpisodePlan {
        kinds,
        episodes: args.episodes,
        seed: args.seed,
        sim_speed: args.sim.speed,
    };
    let s = equact::demos::collect(
        &cfg,
        &plan,
        &args.out,
        &equact::task::ExpertSettings {
            grasp_turn_deg: args.grasp_turn,
            centred_grasp_labels: args.centred_grasp_labels,
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
