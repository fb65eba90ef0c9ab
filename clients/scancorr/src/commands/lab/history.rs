//! `scancorr lab history`: the error fall across calibration versions.

use super::args::LabCmd;
use crate::report;
use crate::shared::bags::{load_bags, SENSORS};
use crate::shared::calib::{self};
use crate::shared::output::commit_all;
use crate::shared::output::{outputs, put};
use anyhow::{bail, Context, Result};
use scancorr_core::lab::analysis::{self};
use scancorr_core::lab::dataset::{self, BuildOptions};
use scancorr_core::lab::program::parse_artifact;
use scancorr_core::Calibration;
use std::path::{Path, PathBuf};

/// Runs `scancorr lab history`.
pub(super) fn exec(cmd: LabCmd) -> Result<()> {
    let LabCmd::History {
        calib_dir,
        machine,
        bag,
        artifact,
        json,
        report,
        bus,
    } = cmd
    else {
        unreachable!("lab history")
    };
    if let Some(m) = &machine {
        crate::shared::output::check_machine("--machine", m)?;
        bus.check()?;
    }
    let dir_files: Vec<PathBuf> = match &calib_dir {
        Some(d) => std::fs::read_dir(d)
            .with_context(|| format!("reading {}", d.display()))?
            .flatten()
            .map(|e| e.path())
            .collect(),
        None => vec![],
    };
    let inputs: Vec<(&str, &Path)> = bag
        .iter()
        .map(|b| ("--bag", b.as_path()))
        .chain(dir_files.iter().map(|p| ("--calib-dir", p.as_path())))
        .collect();
    let [report_out] = outputs([("--report", report.as_deref())], &inputs)?;
    let mut cals = versions(&machine, &calib_dir, &bus)?;
    cals.sort_by_key(|(_, c)| (c.machine_id.clone(), c.version));
    // The same version in two files (`lab discover` writes its last step also as
    // calibration.json) is listed once.
    cals.dedup_by(|b, a| {
        a.1.machine_id == b.1.machine_id
            && a.1.version == b.1.version
            && a.1.to_json() == b.1.to_json()
    });
    // A version without recorded figures takes them from a child that measured it.
    let from_child = |v: u64, key: &str| {
        cals.iter()
            .find(|(_, c)| c.parent_version == Some(v))
            .and_then(|(_, c)| c.metrics.get(key).copied())
    };
    let mut rows = vec![];
    let bags = if bag.is_empty() {
        vec![]
    } else {
        load_bags(&bag, &[], &cals[0].1.machine_id)?
    };
    let art = artifact
        .as_deref()
        .map(parse_artifact)
        .transpose()
        .map_err(|e| anyhow::anyhow!("--artifact: {e}"))?;
    for (p, c) in &cals {
        let mut floor = c.metrics.get("noise_floor_um").copied();
        let (rms, held) = if bags.is_empty() {
            (
                c.metrics
                    .get("rms_um")
                    .copied()
                    .or_else(|| from_child(c.version, "parent_rms_um")),
                c.metrics
                    .get("heldout_rms_um")
                    .copied()
                    .or_else(|| from_child(c.version, "parent_heldout_rms_um")),
            )
        } else {
            let opts = BuildOptions {
                artifact: art.clone(),
                sensors: SENSORS.iter().map(|s| s.to_string()).collect(),
                ..Default::default()
            };
            let ds = dataset::build(&bags, c, &opts)?;
            let pr = analysis::prepare(&ds)?;
            floor = Some(ds.noise_floor_um);
            (Some(pr.rms_fit_um), Some(pr.rms_held_um))
        };
        let change = change(&cals, c);
        rows.push(report::HistoryRow {
            change,
            noise_floor_um: floor,
            file: p
                .file_name()
                .map(|f| f.to_string_lossy().to_string())
                .unwrap_or_default(),
            version: c.version,
            parent: c.parent_version,
            effects: c.effects.iter().map(|e| e.id()).collect(),
            note: c.note.clone(),
            rms_um: rms,
            heldout_rms_um: held,
        });
    }
    if let Some(p) = &report {
        put(&report_out, report::history(&rows))?;
        commit_all([report_out])?;
        eprintln!("report: {}", p.display());
    }
    if json {
        outln!("{}", serde_json::to_string_pretty(&rows)?)?;
    } else {
        out!("{}", report::history_text(&rows))?;
    }
    Ok(())
}

/// The versions to list: every one scancorrd keeps for `--machine`, or the documents in
/// `--calib-dir`.
fn versions(
    machine: &Option<String>,
    calib_dir: &Option<PathBuf>,
    bus: &crate::shared::bus::Bus,
) -> Result<Vec<(PathBuf, Calibration)>> {
    let mut cals: Vec<(PathBuf, Calibration)> = vec![];
    match (machine, calib_dir) {
                (Some(m), None) => {
                    // Every version the service keeps for the machine.
                    let key = scancorr_proto::calibration_key(&bus.prefix, m);
                    let list: serde_json::Value = serde_json::from_str(&crate::shared::bus::query(bus, format!("{key}?history"))?)
                        .context("the service's history reply")?;
                    for v in list.as_array().into_iter().flatten() {
                        let n = v["version"].as_u64().context("a version number")?;
                        let doc = crate::shared::bus::query(bus, format!("{key}?version={n}"))?;
                        let c = Calibration::from_json(&doc)?;
                        cals.push((PathBuf::from(format!("scancorrd:{m}@v{n}")), c));
                    }
                    if cals.is_empty() {
                        bail!("scancorrd keeps no calibration for machine `{m}`");
                    }
                }
                (None, Some(dir)) => {
                    for e in std::fs::read_dir(dir).with_context(|| format!("reading {}", dir.display()))? {
                        let p = e?.path();
                        if p.extension().is_some_and(|x| x == "json") {
                            if let Ok(c) = calib::load_calibration(&p) {
                                cals.push((p, c));
                            }
                        }
                    }
                    if cals.is_empty() {
                        bail!("{}: no calibration documents (*.json)", dir.display());
                    }
                }
                _ => bail!("give either --calib-dir DIR (a folder of versions) or --machine M (the versions scancorrd keeps)"),
            }
    Ok(cals)
}

/// What version `c` added to (or removed from) its parent's effects.
fn change(cals: &[(PathBuf, Calibration)], c: &Calibration) -> String {
    let parent = cals
        .iter()
        .find(|(_, q)| Some(q.version) == c.parent_version)
        .map(|(_, q)| q.effects.iter().map(|e| e.id()).collect::<Vec<_>>());
    let ids: Vec<String> = c.effects.iter().map(|e| e.id()).collect();
    match &parent {
        None if c.parent_version.is_none() => "start".to_string(),
        None => "parent not in the folder".to_string(),
        Some(pe) => {
            let added: Vec<String> = ids
                .iter()
                .filter(|e| !pe.contains(e))
                .map(|e| format!("+{e}"))
                .collect();
            let removed: Vec<String> = pe
                .iter()
                .filter(|e| !ids.contains(e))
                .map(|e| format!("−{e}"))
                .collect();
            let all: Vec<String> = added.into_iter().chain(removed).collect();
            if all.is_empty() {
                "refit".to_string()
            } else {
                all.join(" ")
            }
        }
    }
}
