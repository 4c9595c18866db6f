//! `equact config`: check a cell configuration file and print it as the stack will use it.

use std::path::PathBuf;

use anyhow::Context;
use cell_types::CellConfig;
use clap::Args;

/// Arguments of `equact config`.
#[derive(Args, Debug)]
pub struct ConfigArgs {
    /// The cell configuration file; the built-in simulated cell when omitted.
    #[arg(long)]
    pub config: Option<PathBuf>,
}

/// Loads the configuration named on the command line, or the built-in simulated cell.
pub fn load(path: Option<&PathBuf>) -> anyhow::Result<CellConfig> {
    match path {
        Some(p) => CellConfig::load(p).with_context(|| "the cell configuration was refused"),
        None => CellConfig::simulated().with_context(|| "the built-in simulated cell is invalid"),
    }
}

/// The folder relative paths inside the configuration (the calibration file) resolve
/// against: the config file's folder, or the working directory for the built-in cell.
pub fn config_dir(path: Option<&PathBuf>) -> PathBuf {
    path.and_then(|p| p.parent())
        .map(PathBuf::from)
        .unwrap_or_default()
}

/// Runs `equact config`: validates and prints the checked configuration.
pub fn run(args: ConfigArgs) -> anyhow::Result<()> {
    let cfg = load(args.config.as_ref())?;
    let origin = args.config.as_ref().map_or_else(
        || "built-in simulated cell".to_string(),
        |p| p.display().to_string(),
    );
    println!("# {origin}: valid");
    print!("{}", cfg.to_toml_string()?);
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn shipped_example_of_a_real_cell_is_valid() {
        let path = PathBuf::from(concat!(env!("CARGO_MANIFEST_DIR"), "/cell.example.toml"));
        let cfg = load(Some(&path)).unwrap();
        assert_eq!(cfg.robot.backend, cell_types::config::RobotBackend::Ur);
        assert_eq!(cfg.robot.rtde_port, 30004);
    }

    #[test]
    fn missing_file_is_an_error_not_a_panic() {
        let err = load(Some(&PathBuf::from("/no/such/cell.toml"))).unwrap_err();
        assert!(format!("{err:#}").contains("/no/such/cell.toml"));
    }
}
