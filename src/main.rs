//! `equact`: the command-line front end of the cell stack.
//!
//! Each subcommand lives in its own module under `cmd/`; this file only parses the command
//! line and dispatches.

mod cmd;

use clap::{Parser, Subcommand};

/// EquAct on a UR5 cell: run episodes, simulate the cell, plan, calibrate, train, inspect.
#[derive(Parser, Debug)]
#[command(name = "equact", version, about)]
struct Cli {
    #[command(subcommand)]
    command: Command,
}

#[derive(Subcommand, Debug)]
enum Command {
    /// Run episodes end to end (the built-in simulated cell when no --config is given).
    Run(cmd::run::RunArgs),
    /// Serve the simulated UR controller (RTDE, dashboard, secondary) until interrupted.
    Sim(cmd::sim::SimArgs),
    /// Serve the Robotiq gripper emulator, or benchmark its transports.
    Gripper(cmd::gripper::GripperArgs),
    /// Render (or capture) the three depth cameras and write the fused cloud as PLY and PNG.
    Perceive(cmd::perceive::PerceiveArgs),
    /// Calibrate the cameras to the robot: simulate captures, solve a captures folder.
    Calibrate(cmd::calibrate::CalibrateArgs),
    /// Dry-run check of a real cell: controller, safety, gripper, calibration, workspace.
    Check(cmd::check::CheckArgs),
    /// Check a cell configuration file and print the checked configuration.
    Config(cmd::config::ConfigArgs),
    /// Summarise an episode recording (topics, counts, outcome, timings).
    Inspect(cmd::inspect::InspectArgs),
    /// The EquAct network: check parity fixtures, predict, benchmark.
    Policy(cmd::policy::PolicyArgs),
    /// Run a benchmark and print its summary (e.g. `bench planner --problems FILE`).
    Bench(cmd::bench::BenchArgs),
    /// Plan one keyframe from a joint configuration against a cloud file (PLY or PCD).
    Plan(cmd::plan::PlanArgs),
    /// Draw a recording: joint motions with their limits, tracking error, cloud + robot per step.
    Plot(cmd::plot::PlotArgs),
    /// Record scripted-expert demonstrations in the simulated cell into a dataset.
    Demos(cmd::demos::DemosArgs),
    /// Closed-loop evaluation in the simulated cell: success rate per task variation.
    Eval(cmd::eval::EvalArgs),
    /// Train the network on a demonstration dataset (checkpoints resume).
    Train(cmd::train::TrainArgs),
}

fn main() -> std::process::ExitCode {
    keep_freed_memory();
    let cli = Cli::parse();
    match dispatch(cli) {
        Ok(()) => std::process::ExitCode::SUCCESS,
        Err(e) => {
            // The cause chain on one line, without a backtrace; causes that the message
            // above them already quotes are not repeated.
            let mut line = e.to_string();
            for cause in e.chain().skip(1) {
                let text = cause.to_string();
                if !line.contains(&text) {
                    line.push_str(": ");
                    line.push_str(&text);
                }
            }
            eprintln!("error: {line}");
            std::process::ExitCode::FAILURE
        }
    }
}

/// Tells glibc's allocator to keep freed memory in the process: no `mmap` per large block,
/// no trimming of the heap top, and a top pad that keeps worker threads' heaps. Without
/// this, every large tensor of a network forward or backward pass is a fresh `mmap` whose
/// pages the kernel zeroes on first touch and takes back on `free`; training spent a fifth
/// of each step in those page faults (two threads: 22.8 s -> 17.1 s for 12 steps). It is
/// also the real-time habit (the ROS 2 real-time guide's `mallopt` settings): no page fault
/// in a control loop once the process has reached its peak. The cost is that the process
/// keeps its peak memory until it exits.
#[cfg(all(target_os = "linux", target_env = "gnu"))]
#[allow(unsafe_code)]
fn keep_freed_memory() {
    // SAFETY: mallopt only sets allocator parameters and takes plain integers; it runs
    // before any other thread of the process exists. Its return value (0 when a parameter
    // is refused) only means the defaults stay, which is correct, only slower.
    unsafe {
        libc::mallopt(libc::M_MMAP_MAX, 0);
        libc::mallopt(libc::M_TRIM_THRESHOLD, -1);
        // A thread's arena grows by extra 64 MiB heaps, and glibc unmaps such a heap as
        // soon as it is empty unless the top pad is larger than what that would free
        // (`heap_trim`), whatever the trim threshold. Training's batch threads emptied and
        // refilled theirs every step: the pad keeps them (1024-point fine-tune, two
        // threads: about 4.1 -> 3.2 s per step, and no page fault after the first step).
        libc::mallopt(libc::M_TOP_PAD, TOP_PAD_BYTES);
        // No fast bins: a training step's large frees otherwise first merged every small
        // freed block (`malloc_consolidate`, 1.7 % of a step). 20 steps, the same weights
        // bit for bit, two runs side by side twice, two tries: 26.5 / 26.2 s -> 26.0 /
        // 25.7 s and 27.1 / 27.2 s -> 26.9 / 26.8 s (1-2 %).
        libc::mallopt(libc::M_MXFAST, 0);
    }
}

/// The allocator's top pad: more than a thread heap's 64 MiB, so none is ever unmapped.
#[cfg(all(target_os = "linux", target_env = "gnu"))]
const TOP_PAD_BYTES: libc::c_int = 256 << 20;

/// Other allocators keep their own defaults.
#[cfg(not(all(target_os = "linux", target_env = "gnu")))]
fn keep_freed_memory() {}

fn dispatch(cli: Cli) -> anyhow::Result<()> {
    match cli.command {
        Command::Run(args) => cmd::run::run(args),
        Command::Sim(args) => cmd::sim::run(args),
        Command::Gripper(args) => cmd::gripper::run(args),
        Command::Perceive(args) => cmd::perceive::run(args),
        Command::Calibrate(args) => cmd::calibrate::run(args),
        Command::Check(args) => cmd::check::run(args),
        Command::Config(args) => cmd::config::run(args),
        Command::Inspect(args) => cmd::inspect::run(args),
        Command::Policy(args) => cmd::policy::run(args),
        Command::Bench(args) => cmd::bench::run(args),
        Command::Plan(args) => cmd::plan::run(args),
        Command::Plot(args) => cmd::plot::run(args),
        Command::Demos(args) => cmd::demos::run(args),
        Command::Eval(args) => cmd::eval::run(args),
        Command::Train(args) => cmd::train::run(args),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// `run` and `policy predict` name the weights `--weights`, `eval`, `policy score` and
    /// `policy ground` name them `--model`: each takes the other spelling too.
    #[test]
    fn weights_and_model_are_one_flag_everywhere() {
        let weights = |args: &[&str]| -> Option<std::path::PathBuf> {
            let cli = Cli::try_parse_from(args).unwrap_or_else(|e| panic!("{args:?}: {e}"));
            match cli.command {
                Command::Run(a) => a.weights,
                Command::Eval(a) => a.model,
                Command::Policy(p) => match p.command {
                    cmd::policy::PolicyCommand::Predict(a) => a.weights,
                    cmd::policy::PolicyCommand::Score(a)
                    | cmd::policy::PolicyCommand::Ground(a) => a.model,
                    other => panic!("{other:?}"),
                },
                other => panic!("{other:?}"),
            }
        };
        let want = Some(std::path::PathBuf::from("w.safetensors"));
        for flag in ["--weights", "--model"] {
            assert_eq!(weights(&["equact", "run", flag, "w.safetensors"]), want);
            assert_eq!(weights(&["equact", "eval", flag, "w.safetensors"]), want);
            for sub in ["score", "ground"] {
                assert_eq!(
                    weights(&[
                        "equact",
                        "policy",
                        sub,
                        "--demos",
                        "d",
                        flag,
                        "w.safetensors"
                    ]),
                    want
                );
            }
            assert_eq!(
                weights(&[
                    "equact",
                    "policy",
                    "predict",
                    "--cloud",
                    "c.ply",
                    flag,
                    "w.safetensors"
                ]),
                want
            );
        }
    }

    /// `demos merge` takes its sources in order after `--out`, at least one.
    #[test]
    fn demos_merge_takes_its_sources_in_order() {
        let cli =
            Cli::try_parse_from(["equact", "demos", "merge", "--out", "o", "a", "b"]).unwrap();
        let Command::Demos(d) = cli.command else {
            panic!("not demos")
        };
        let cmd::demos::DemosCommand::Merge(m) = d.command else {
            panic!("not merge")
        };
        assert_eq!(m.out, std::path::PathBuf::from("o"));
        assert_eq!(m.sources, ["a", "b"].map(std::path::PathBuf::from));
        let err = Cli::try_parse_from(["equact", "demos", "merge", "--out", "o"]).unwrap_err();
        assert_eq!(err.kind(), clap::error::ErrorKind::MissingRequiredArgument);
    }

    /// `eval report` takes its logs in order, at least one, `eval compare` exactly two;
    /// without a subcommand `eval` runs episodes as before, and episode options do not mix
    /// with a subcommand.
    #[test]
    fn eval_report_is_a_subcommand_beside_the_episode_options() {
        let report = |args: &[&str]| {
            let cli = Cli::try_parse_from(args).unwrap_or_else(|e| panic!("{args:?}: {e}"));
            let Command::Eval(e) = cli.command else {
                panic!("not eval")
            };
            e
        };
        let e = report(&[
            "equact",
            "eval",
            "report",
            "a",
            "b/episodes.jsonl",
            "--json",
        ]);
        let Some(cmd::eval::EvalAction::Report(r)) = e.action else {
            panic!("not report: {e:?}")
        };
        assert_eq!(
            r.logs,
            ["a", "b/episodes.jsonl"].map(std::path::PathBuf::from)
        );
        assert!(r.json);
        let e = report(&["equact", "eval", "--task", "pick_fruit", "--episodes", "3"]);
        assert!(e.action.is_none());
        assert_eq!((e.task.as_str(), e.episodes), ("pick_fruit", 3));
        let e = report(&[
            "equact",
            "eval",
            "compare",
            "first",
            "ablation/episodes.jsonl",
        ]);
        let Some(cmd::eval::EvalAction::Compare(c)) = e.action else {
            panic!("not compare: {e:?}")
        };
        assert_eq!(
            [c.a, c.b],
            ["first", "ablation/episodes.jsonl"].map(std::path::PathBuf::from)
        );
        assert!(!c.json);
        for bad in [
            &["equact", "eval", "report"][..],
            &["equact", "eval", "--episodes", "3", "report", "a"][..],
            &["equact", "eval", "compare", "a"][..],
            &["equact", "eval", "compare", "a", "b", "c"][..],
        ] {
            assert!(Cli::try_parse_from(bad).is_err(), "{bad:?}");
        }
    }

    /// `run`, `eval` and `demos collect` take `--sim-speed` (real time by default) and refuse
    /// a speed the simulator cannot run, naming it.
    #[test]
    fn sim_speed_is_one_checked_flag_of_every_simulated_command() {
        let speed = |args: &[&str]| -> Result<f64, String> {
            let cli = Cli::try_parse_from(args).map_err(|e| e.to_string())?;
            Ok(match cli.command {
                Command::Run(a) => a.sim.speed,
                Command::Eval(a) => a.sim.speed,
                Command::Demos(d) => match d.command {
                    cmd::demos::DemosCommand::Collect(c) => c.sim.speed,
                    other => panic!("{other:?}"),
                },
                other => panic!("{other:?}"),
            })
        };
        let commands: [&[&str]; 3] = [
            &["equact", "run"],
            &["equact", "eval"],
            &["equact", "demos", "collect", "--task", "all", "--out", "d"],
        ];
        for base in commands {
            assert_eq!(speed(base), Ok(1.0), "{base:?}");
            let with = |v: &str| {
                let flag = format!("--sim-speed={v}");
                speed(&[base, &[flag.as_str()]].concat())
            };
            assert_eq!(with("4"), Ok(4.0), "{base:?}");
            assert_eq!(with("0.5"), Ok(0.5), "{base:?}");
            for bad in ["0", "-2", "nan", "17", "fast"] {
                let err = with(bad).unwrap_err();
                assert!(
                    err.contains("--sim-speed") && err.contains(bad),
                    "{base:?} {bad}: {err}"
                );
            }
        }
    }
}
