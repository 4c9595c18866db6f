//! `equact policy ...`: tools around the EquAct network (fixture parity checks for now).

use clap::{Args, Subcommand};

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
}

/// Runs `equact policy`.
pub fn run(args: PolicyArgs) -> anyhow::Result<()> {
    match args.command {
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
