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
    /// Check a cell configuration file and print the checked configuration.
    Config(cmd::config::ConfigArgs),
    /// Run a benchmark and print its summary (e.g. `bench planner --problems FILE`).
    Bench(cmd::bench::BenchArgs),
    /// Plan one keyframe from a joint configuration against a cloud file (PLY or PCD).
    Plan(cmd::plan::PlanArgs),
}

fn main() -> anyhow::Result<()> {
    let cli = Cli::parse();
    match cli.command {
        Command::Config(args) => cmd::config::run(args),
        Command::Bench(args) => cmd::bench::run(args),
        Command::Plan(args) => cmd::plan::run(args),
    }
}
