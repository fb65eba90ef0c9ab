//! `scancorr correct`: a bag corrected offline through the core (`shared::bags`), points and
//! alarms to a bag (with Foxglove's channels unless `--no-foxglove`), the summary printed.

use crate::shared::{bags, output};
use anyhow::Result;
use std::path::PathBuf;

/// Runs `scancorr correct`.
pub fn exec(
    bag: PathBuf,
    calib: PathBuf,
    out: Option<PathBuf>,
    json: bool,
    no_foxglove: bool,
) -> Result<()> {
    if let Some(o) = &out {
        output::refuse_same_file(&[("--out", o)], &[("--bag", &bag), ("--calib", &calib)])?;
    }
    let cal = crate::shared::calib::load_calibration(&calib)?;
    let (s, warnings) = bags::correct_with(&bag, &cal, out.as_deref(), !no_foxglove)?;
    for w in warnings {
        eprintln!("warning: {w}");
    }
    // A feature map applies only to its own part program's scans: said as such.
    let maps = cal.feature_map_ids();
    for e in &s.inactive_effects {
        if maps.contains(e) {
            eprintln!(
                "warning: feature map `{e}` of the calibration applies to none of the {} points: a map applies only to its own part program's scans (segment ids, tip and head angles, place, speed)",
                s.points
            );
            continue;
        }
        eprintln!(
                    "warning: effect `{e}` of the calibration contributed to none of the {} points: inactive for lack of its signal (e.g. no rotation for servo effects, no deflection for probe effects)",
                    s.points
                );
    }
    if json {
        outln!("{}", serde_json::to_string_pretty(&s)?)?;
    } else {
        outln!(
                    "{}: machine {}, calibration v{}: {} samples → {} points ({} flagged), {} alarm(s), dropped {:?}{} in {:.2} s ({:.2e} samples/s)",
                    bag.display(),
                    s.machine,
                    s.calibration_version,
                    s.samples,
                    s.points,
                    s.points_flagged,
                    s.alarms,
                    s.dropped,
                    if s.bad_messages > 0 { format!(", {} malformed message(s)", s.bad_messages) } else { String::new() }
                        + &if s.clock_resets > 0 { format!(", {} controller clock reset(s)", s.clock_resets) } else { String::new() },
                    s.seconds,
                    s.samples_per_s
                )?;
    }
    Ok(())
}
