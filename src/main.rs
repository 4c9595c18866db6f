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
    /// Render (or capture) the three depth cameras and write the fused cloud as PLY and PNG.
    Perceive(cmd::perceive::PerceiveArgs),
}

fn main() -> anyhow::Result<()> {
    let cli = Cli::parse();
    match cli.command {
        Command::Config(args) => cmd::config::run(args),
        Command::Perceive(args) => cmd::perceive::run(args),
    }
}
