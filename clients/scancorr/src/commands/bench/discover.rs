//! `scancorr bench discover`: the demo's loop (`shared::demo`) timed.

use crate::shared::demo::run_in;
use anyhow::Result;

/// `scancorr bench discover`: the demo's loop (default campaign, ≈ 330 k samples per stream,
/// from the nominal model), timed; prints seconds, steps, the final error and peak memory.
pub fn exec(json: bool, max_steps: usize) -> Result<()> {
    let dir = crate::shared::output::private_dir("scancorr-bench-discover")?;
    let r = run_in(&[], &dir, false, true, max_steps);
    std::fs::remove_dir_all(&dir).ok();
    let mut v = r?;
    let rss_kb = std::fs::read_to_string("/proc/self/status")
        .ok()
        .and_then(|s| {
            s.lines().find(|l| l.starts_with("VmHWM:")).and_then(|l| {
                l.split_whitespace()
                    .nth(1)
                    .and_then(|x| x.parse::<u64>().ok())
            })
        });
    v["peak_rss_kb"] = serde_json::json!(rss_kb);
    if json {
        outln!("{v}")?;
    } else {
        outln!(
            "lab discover on the default campaign from the nominal model: {:.1} s, {} steps, held-out {:.3} µm ({:.2}× the noise floor {:.3} µm), peak RSS {} MB",
            v["seconds"].as_f64().unwrap_or(0.0),
            v["steps"].as_array().map(|a| a.len()).unwrap_or(0),
            v["final"]["heldout_rms_um"].as_f64().unwrap_or(0.0),
            v["final"]["heldout_rms_um"].as_f64().unwrap_or(0.0) / v["final"]["noise_floor_um"].as_f64().unwrap_or(1.0).max(1e-9),
            v["final"]["noise_floor_um"].as_f64().unwrap_or(0.0),
            rss_kb.map(|k| (k / 1024).to_string()).unwrap_or_else(|| "?".into())
        )?;
    }
    Ok(())
}
