//! Shared helpers for the HIL regression tests in `tests/tests/`: where the Python peers
//! live and how to run them.

use std::path::{Path, PathBuf};
use std::process::Command;

/// The workspace root.
pub fn workspace_root() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR"))
        .parent()
        .map_or_else(|| PathBuf::from("."), Path::to_path_buf)
}

/// The venv's Python with the independent peers, or an error that says how to make it.
pub fn peer_python() -> anyhow::Result<PathBuf> {
    let p = workspace_root().join(".venv/bin/python3");
    if p.exists() {
        Ok(p)
    } else {
        anyhow::bail!(
            "{} is missing: run `make venv` (the README's test command does) to install the Python peers",
            p.display()
        )
    }
}

/// Foxglove's published JSON schemas, fetched by `scripts/fetch_foxglove_schemas.sh`.
pub fn foxglove_schemas() -> anyhow::Result<PathBuf> {
    let p = workspace_root().join(".venv/foxglove-schemas");
    if p.join(".version").exists() {
        Ok(p)
    } else {
        anyhow::bail!(
            "{} is missing: run `make venv` to fetch Foxglove's schemas",
            p.display()
        )
    }
}

/// Runs a peer script from `tests/peers/` with arguments; returns its stdout, or an error
/// carrying its stderr.
pub fn run_peer(script: &str, args: &[&str]) -> anyhow::Result<String> {
    let python = peer_python()?;
    let out = Command::new(python)
        .arg(workspace_root().join("tests/peers").join(script))
        .args(args)
        .output()?;
    if !out.status.success() {
        anyhow::bail!(
            "peer {script} failed ({}): {}",
            out.status,
            String::from_utf8_lossy(&out.stderr)
        );
    }
    Ok(String::from_utf8_lossy(&out.stdout).into_owned())
}
