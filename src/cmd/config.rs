//! `equact config`: check a cell configuration file.

use clap::Args;

/// Arguments of `equact config`.
#[derive(Args, Debug)]
pub struct ConfigArgs {
    /// The cell configuration file; the built-in simulated cell when omitted.
    #[arg(long)]
    pub config: Option<std::path::PathBuf>,
}

/// Runs `equact config`.
pub fn run(args: ConfigArgs) -> anyhow::Result<()> {
    let _ = args;
    Ok(())
}
