//! `equact check --config cell.toml`: the dry-run check of a real cell (see
//! `equact::preflight`); nothing moves.

use std::path::PathBuf;
use std::sync::Arc;

use cell_types::SystemClock;
use clap::Args;

/// Arguments of `equact check`.
#[derive(Args, Debug)]
pub struct CheckArgs {
    /// The cell configuration to check.
    #[arg(long)]
    pub config: PathBuf,
}

/// Runs `equact check`; fails when any check fails.
pub fn run(args: CheckArgs) -> anyhow::Result<()> {
    let cfg = super::config::load(Some(&args.config))?;
    let dir = super::config::config_dir(Some(&args.config));
    let checks = equact::preflight::run_checks(&cfg, &dir, Arc::new(SystemClock::new()));
    for c in &checks {
        let mark = match (c.passed, c.warning) {
            (true, false) => "ok  ",
            (true, true) => "warn",
            (false, _) => "FAIL",
        };
        println!("{mark} {:<12} {}", c.name, c.detail);
        if !c.fix.is_empty() {
            println!("     {:<12} -> {}", "", c.fix);
        }
    }
    let failed = checks.iter().filter(|c| !c.passed).count();
    if failed > 0 {
        anyhow::bail!(
            "{failed} of {} checks failed; nothing was moved",
            checks.len()
        );
    }
    println!("all {} checks passed", checks.len());
    Ok(())
}
