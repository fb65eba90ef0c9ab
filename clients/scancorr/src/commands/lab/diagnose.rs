//! `scancorr lab diagnose`: the effects missing from the model, ranked by the residual they explain.

use super::args::LabCmd;
use super::data::{dataset_for, load};
use super::plotdata;
use super::print::{json_with_profile_units, print_diagnosis};
use crate::report;
use crate::shared::output::commit_all;
use crate::shared::output::{outputs, put};
use anyhow::Result;
use scancorr_core::lab::analysis::{self};

/// Runs `scancorr lab diagnose`.
pub(super) fn exec(cmd: LabCmd) -> Result<()> {
    let LabCmd::Diagnose {
        data,
        json,
        report,
        csv,
    } = cmd
    else {
        unreachable!("lab diagnose")
    };
    let [report_out] = outputs([("--report", report.as_deref())], &data.inputs())?;
    if let Some(d) = &csv {
        plotdata::prepare(d)?;
    }
    let l = load(&data)?;
    let ds = dataset_for(&l, &l.cal)?;
    let mut dg = analysis::diagnose(&ds)?;
    // One row per move, in one order, in the text, the JSON and the report alike.
    let model = report::model_variants(&l.cal, &ds);
    report::tidy_diagnosis(&mut dg, &model);
    let cmp = if report.is_some() || csv.is_some() {
        Some(analysis::compare(&ds)?)
    } else {
        None
    };
    if let (Some(p), Some(cmp)) = (&report, &cmp) {
        put(&report_out, report::diagnose(&l.cal, &ds, cmp, &dg, &model))?;
        commit_all([report_out])?;
        eprintln!("report: {}", p.display());
    }
    if let (Some(d), Some(cmp)) = (&csv, &cmp) {
        let mut files = plotdata::diagnosis(d, &dg)?;
        files.extend(plotdata::comparison(d, "", cmp)?);
        eprintln!("csv: {} in {}", files.join(", "), d.display());
    }
    if json {
        // The rows' order and each candidate's share of the held-out data, stated as the
        // text and the report state them.
        let mut j = json_with_profile_units(&dg)?;
        j["ranked_by"] = report::DIAGNOSIS_ORDER.into();
        if let Some(cs) = j["candidates"].as_array_mut() {
            for (v, c) in cs.iter_mut().zip(&dg.candidates) {
                if let Some(h) = report::heldout_explained(c) {
                    v["heldout_explained_fraction"] = h.into();
                }
            }
        }
        outln!("{}", serde_json::to_string_pretty(&j)?)?;
    } else {
        print_diagnosis(&dg, &data, &model)?;
    }
    Ok(())
}
