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
        plan_artifact,
        plan_minutes,
    } = cmd
    else {
        unreachable!("lab discover")
    };
    // Every file the loop will write, against every input and each other, before any
    // work: the step versions after the start's, `calibration.json`, `plan.json`, --report.
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
    let plan = write_plan(&d, &l, last, &out_dir, &plan_artifact, plan_minutes, &data)?;
    if json {
        let mut j = super::print::json_with_profile_units(&d)?;
        if let Some(p) = &plan {
            j["plan"] = serde_json::to_value(p)?;
        }
        outln!("{}", serde_json::to_string_pretty(&j)?)?;
    } else {
        print_discovery(&d, &out_dir)?;
        print_after(&d, plan.as_ref())?;
    }
    Ok(())
}

/// The plan `lab discover` wrote for what it left confounded or not determined.
#[derive(serde::Serialize)]
struct PlanWritten {
    /// The program record (`scancorr sim --program FILE`, or the part program to write).
    file: Option<PathBuf>,
    /// What it is for.
    left: Vec<String>,
    /// The candidates it makes identifiable beside the final model.
    candidates: Vec<String>,
    /// Machine time, minutes.
    minutes: f64,
    /// Parameters the bags given could not determine.
    undetermined_before: usize,
    /// Parameters (of the final model and the candidates) the plan's design alone would leave
    /// undetermined, predicted (the plan is measured beside the campaign, not instead of it).
    undetermined_plan_alone: usize,
    /// Why no plan was written, when none was.
    #[serde(skip_serializing_if = "Option::is_none")]
    not_written: Option<String>,
}

/// When the loop stopped with a confounded pair or parameters not determined: the plan that
/// separates them (`scancorr_core::lab::plan::plan`, as `lab plan` makes it) from the final
/// model, written to `out_dir/plan.json`.
fn write_plan(
    d: &scancorr_core::lab::discover::Discovery,
    l: &super::data::Loaded,
    last: &scancorr_core::Calibration,
    out_dir: &Path,
    artifacts: &[String],
    minutes: f64,
    data: &super::args::DataArgs,
) -> Result<Option<PlanWritten>> {
    use scancorr_core::lab::discover::{left_to_plan, owned_in, plan_candidates};
    use scancorr_core::lab::plan::{self, Assumptions, Owned, PlanRequest};
    let left = left_to_plan(d);
    if left.is_empty() {
        return Ok(None);
    }
    let candidates = plan_candidates(d);
    let mut w = PlanWritten {
        file: None,
        left,
        candidates: candidates.clone(),
        minutes: 0.0,
        undetermined_before: d.unidentifiable.len(),
        undetermined_plan_alone: 0,
        not_written: None,
    };
    let owned: Vec<Owned> = if artifacts.is_empty() {
        owned_in(&l.bags)
    } else {
        artifacts
            .iter()
            .map(|s| Owned::parse(s).map_err(|e| anyhow::anyhow!("--plan-artifact {e}")))
            .collect::<Result<_>>()?
    };
    let travel = last.limits.travel_mm;
    if travel.iter().any(|[lo, hi]| hi - lo >= 9000.0) {
        w.not_written = Some("the calibration's limits.travel_mm is the default ±5000 mm, not the machine's: make the start with `calib nominal --datasheet`, or run `lab plan --datasheet`".into());
        return Ok(Some(w));
    }
    let req = PlanRequest {
        travel_mm: travel,
        owned,
        minutes,
        candidates,
        assumptions: Assumptions {
            noise_um: d.r#final.noise_floor_um,
            stride: l.opts.stride,
            heldout_alternate: data.validate.is_empty(),
            ..Assumptions::default()
        },
    };
    let planned = match plan::plan(last, &req) {
        Ok(p) => p,
        Err(e) => {
            w.not_written = Some(format!("{e}"));
            return Ok(Some(w));
        }
    };
    let path = out_dir.join("plan.json");
    crate::shared::output::write_file("--out-dir", &path, planned.program.to_json())?;
    w.file = Some(path);
    w.minutes = planned.minutes;
    w.undetermined_plan_alone = planned.prediction.undetermined.len();
    Ok(Some(w))
}

/// What the text output adds to [`print_discovery`]: pairs told apart by their scores, and
/// the plan written.
fn print_after(d: &scancorr_core::lab::discover::Discovery, p: Option<&PlanWritten>) -> Result<()> {
    for s in &d.separated {
        outln!(
            "  not confounded: {} and {} correct alike, but their scores separate them (cross-validated {} vs {} µm)",
            s.effects[0],
            s.effects[1],
            um(s.cv_rms_um[0]),
            um(s.cv_rms_um[1])
        )?;
    }
    let Some(p) = p else { return Ok(()) };
    outln!("  left for a plan: {}", p.left.join("; "))?;
    match (&p.file, &p.not_written) {
        (Some(f), _) => {
            outln!(
                "  plan: {} ({:.1} min of machine time; with {}): measure it (`scancorr sim --program {}` on the simulator) and run `lab discover` again with its bag beside the campaign (--bag CAMPAIGN --bag PLAN); the bags given left {} parameter(s) undetermined, the plan alone would leave {} (predicted from its design)",
                f.display(),
                p.minutes,
                if p.candidates.is_empty() {
                    "the final model's effects".to_string()
                } else {
                    p.candidates.join(", ")
                },
                f.display(),
                p.undetermined_before,
                p.undetermined_plan_alone
            )?;
        }
        (None, Some(why)) => outln!("  no plan written: {why}")?,
        (None, None) => {}
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
    let mut names: std::collections::BTreeSet<std::ffi::OsString> = [
        std::ffi::OsString::from("calibration.json"),
        std::ffi::OsString::from("plan.json"),
    ]
    .into();
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
