//! `equact plot FILE.mcap --out DIR`: pictures of a recorded episode.

use std::path::PathBuf;

use clap::Args;

/// Arguments of `equact plot`.
#[derive(Args, Debug)]
pub struct PlotArgs {
    /// The recording.
    pub file: PathBuf,
    /// Folder for the pictures (created if missing).
    #[arg(long, default_value = "plots")]
    pub out: PathBuf,
}

/// Runs `equact plot`.
pub fn run(args: PlotArgs) -> anyhow::Result<()> {
    let written = equact::plot::plot_file(&args.file, &args.out)?;
    for path in &written {
        println!("{}", path.display());
    }
    println!("{} pictures in {}", written.len(), args.out.display());
    Ok(())
}
