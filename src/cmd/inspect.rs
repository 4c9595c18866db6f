//! `equact inspect FILE.mcap`: what a recording holds (topics, counts, outcome, timings).

use std::path::PathBuf;

use clap::Args;
use equact::recording::inspect_file;

/// Arguments of `equact inspect`.
#[derive(Args, Debug)]
pub struct InspectArgs {
    /// The recording.
    pub file: PathBuf,
    /// Print the summary as JSON instead of text.
    #[arg(long)]
    pub json: bool,
}

/// Runs `equact inspect`.
pub fn run(args: InspectArgs) -> anyhow::Result<()> {
    let s = inspect_file(&args.file)?;
    if args.json {
        println!("{}", serde_json::to_string_pretty(&s)?);
        return Ok(());
    }
    println!("{}", args.file.display());
    println!(
        "  file: {}",
        if s.complete {
            "complete".to_string()
        } else {
            format!(
                "truncated or unfinished ({}); showing its complete chunks",
                s.read_error.as_deref().unwrap_or("no footer")
            )
        }
    );
    if let Some((a, b)) = s.time_range_ns {
        println!("  span: {:.3} s", (b.saturating_sub(a)) as f64 * 1e-9);
    }
    println!("  topics ({} messages):", s.message_count());
    for (topic, (schema, n)) in &s.topics {
        println!("    {topic:<24} {n:>8}  {schema}");
    }
    if !s.phases.is_empty() {
        println!("  step timings:");
        for (phase, t) in &s.phases {
            println!(
                "    {phase:<10} n={:<4} mean={:.4} s max={:.4} s",
                t.count,
                t.total_s / t.count.max(1) as f64,
                t.max_s
            );
        }
    }
    match &s.outcome {
        Some(o) => println!("  outcome: {o}"),
        None => println!("  outcome: none recorded (the episode did not finish)"),
    }
    Ok(())
}
