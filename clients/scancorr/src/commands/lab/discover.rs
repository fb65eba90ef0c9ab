//! `scancorr lab discover`: the whole loop, unattended, each step a calibration version.

use super::args::LabCmd;
use super::data::{dataset_for, load_from, um};
use super::print::print_discovery;
use crate::report;
use crate::shared::calib::{self, now_rfc3339};
use crate::shared::output::{commit_all, refuse_same_file};
use crate::shared::output::{outputs, put};
use anyhow::{Context, Result};
use scancorr_core::lab::analysis::{self};
use scancorr_core::lab::dataset::{self};
use std::path::{Path, PathBuf};

/// Runs `scancorr lab discover`.
pub(super) fn exec(cmd: LabCmd) -> Result<()> {
    let LabCmd::Discover {
        data,
        out_dir,
        max_steps,
        json,
        report,
    } = cmd
    else {
        unreachable!("lab discover")
    };
    // Every file the loop will write, against every input and each other, before any
    // work: the step versions after the start's, `calibration.json`, --report.
    let start = calib::load_calibration(&data.calib)?;
    let first = start.version.saturating_add(1);
    let last = first.saturating_add(max_steps as u64);
    let inputs = data.inputs();
    let mut others = inputs.clone();
    if let Some(r) = &report {
        others.push(("--report", r.as_path()));
    }
    let written = discover_outputs(&out_dir, first, last, &others);
    let mut outs: Vec<(&str, &Path)> = written.iter().map(|p| ("--out-dir", p.as_path())).collect();
    if let Some(r) = &report {
        outs.push(("--report", r.as_path()));
    }
    refuse_same_file(&outs, &inputs).with_context(|| {
                format!(
                    "lab discover writes v{first}.json … v{last}.json and calibration.json into --out-dir {}",
                    out_dir.display()
                )
            })?;
    let [report_out] = outputs([("--report", report.as_deref())], &inputs)?;
    std::fs::create_dir_all(&out_dir)
        .with_context(|| format!("creating --out-dir {}", out_dir.display()))?;
    let l = load_from(&data, start)?;
    // The start's points: warnings (drops, bags without samples) once, up front.
    dataset_for(&l, &l.cal)?;
    if data.validate.is_empty() {
        eprintln!("note: no --validate bags: every other scan of each artifact is held out, and the loop is judged on the same placements; a run at another position (e.g. `sim --program ring-speeds --position …`) tests what the model predicts elsewhere");
    }
    let opts = scancorr_core::lab::discover::Options {
        build: l.opts.clone(),
        max_steps,
        created: now_rfc3339(),
    };
    let t0 = std::time::Instant::now();
    let mut on_step = |st: &scancorr_core::lab::discover::Step| -> std::result::Result<(), scancorr_core::lab::LabError> {
                let path = out_dir.join(format!("v{}.json", st.version));
                crate::shared::output::write_file("--out-dir", &path, st.calibration.to_json())
                    .map_err(|e| scancorr_core::lab::LabError::Data(format!("{e:#}")))?;
                if !json {
                    let _ = outln!(
                        "  step {:>2}  {:<5} {:<40} held-out {:>7} → {:>7} µm   v{} → {}",
                        st.index,
                        st.action,
                        match &st.replaces {
                            Some(r) => format!("{} (for {r})", st.effect),
                            None => st.effect.clone(),
                        },
                        um(st.heldout_rms_before_um),
                        um(st.heldout_rms_um),
                        st.version,
                        path.display()
                    );
                    if let Some(f) = &st.found {
                        let _ = outln!("            found: {f}");
                    }
                }
                Ok(())
            };
    let mut on_progress = |m: &str| {
        eprintln!("[{:>5.1} s] {m}", t0.elapsed().as_secs_f64());
    };
    let d = scancorr_core::lab::discover::discover(
        &l.bags,
        &l.cal,
        &opts,
        &mut on_step,
        &mut on_progress,
    )?;
    let last = &d.steps.last().expect("step 0 exists").calibration;
    crate::shared::output::write_file(
        "--out-dir",
        &out_dir.join("calibration.json"),
        last.to_json(),
    )?;
    if let Some(p) = &report {
        let ds0 = dataset::build(&l.bags, &l.cal, &l.opts)?;
        let ds1 = dataset::build(&l.bags, last, &l.opts)?;
        let (c0, c1) = (analysis::compare(&ds0)?, analysis::compare(&ds1)?);
        put(
            &report_out,
            report::discover(&l.cal, &d, Some(((&ds0, &c0), (&ds1, &c1)))),
        )?;
        commit_all([report_out])?;
        eprintln!("report: {}", p.display());
    }
    if json {
        outln!("{}", serde_json::to_string_pretty(&d)?)?;
    } else {
        print_discovery(&d, &out_dir)?;
    }
    Ok(())
}

/// Every file `lab discover` may write into `out_dir` that could be the same file as one of
/// `others` (its inputs and `--report`): `calibration.json`, and of the step versions
/// `v<first>.json` … `v<last>.json` those that already exist there (as files, symlinks or
/// hard links) or that one of `others` is named like. A version file that does not exist yet
/// and that nothing is named like is a new file: it can collide with nothing.
fn discover_outputs(
    out_dir: &Path,
    first: u64,
    last: u64,
    others: &[(&str, &Path)],
) -> Vec<PathBuf> {
    let is_step = |name: &std::ffi::OsStr| {
        name.to_str()
            .and_then(|n| {
                let k: u64 = n.strip_prefix('v')?.strip_suffix(".json")?.parse().ok()?;
                (format!("v{k}.json") == n && (first..=last).contains(&k)).then_some(())
            })
            .is_some()
    };
    let mut names: std::collections::BTreeSet<std::ffi::OsString> =
        [std::ffi::OsString::from("calibration.json")].into();
    if let Ok(entries) = std::fs::read_dir(out_dir) {
        for e in entries.flatten() {
            if is_step(&e.file_name()) {
                names.insert(e.file_name());
            }
        }
    }
    for (_, p) in others {
        if let Some(n) = p.file_name().filter(|n| is_step(n)) {
            names.insert(n.to_os_string());
        }
    }
    names.into_iter().map(|n| out_dir.join(n)).collect()
}
