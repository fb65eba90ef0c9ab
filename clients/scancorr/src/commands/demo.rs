//! `scancorr demo`: the main job on embedded defaults — the model lab's loop on a simulated
//! machine (`shared::demo`), its files kept where the user can open them.

use crate::shared::demo::run_in;
use anyhow::{Context, Result};
use std::path::PathBuf;

/// Runs the demo. `with` switches on physics the default machine does not have
/// (e.g. `probe_lobing`, `cyclic_error`).
pub fn exec(with: &[String], dir: Option<PathBuf>, json: bool) -> Result<()> {
    // Its files (bags, versions, reports) stay where the user can open them: `--dir`, or
    // `scancorr-demo/` in the current folder.
    let keep = true;
    let dir = dir.unwrap_or_else(|| PathBuf::from("scancorr-demo"));
    // The folder is the demo's own: a second run replaces the first's bags, versions and
    // reports (no user file is an output of the demo).
    crate::shared::output::set_force(true);
    std::fs::create_dir_all(&dir).with_context(|| format!("creating {}", dir.display()))?;
    let result = run_in(with, &dir, keep, json, 20);
    if json {
        outln!("{}", result?)?;
        return Ok(());
    }
    result.map(|_| ())
}
