//! `equact bench-ur`: jitter of the UR driver's streaming loop at 125 Hz and 500 Hz against
//! the simulated controller, as JSON lines (one per rate), with a same-process baseline.

use clap::Args;

/// Arguments of `equact bench-ur`.
#[derive(Args, Debug)]
pub struct BenchUrArgs {
    /// Seconds streamed per rate.
    #[arg(long, default_value_t = 5.0)]
    pub seconds: f64,
}

/// Runs `equact bench-ur`.
pub fn run(args: BenchUrArgs) -> anyhow::Result<()> {
    anyhow::ensure!(
        args.seconds.is_finite() && args.seconds >= 0.5,
        "--seconds must be at least 0.5, got {}",
        args.seconds
    );
    for e_series in [false, true] {
        let r = hil_sim::ur_controller::bench::stream_jitter(e_series, args.seconds)?;
        println!("{}", r.to_json());
    }
    Ok(())
}
