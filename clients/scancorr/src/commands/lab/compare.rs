//! `scancorr lab compare`: the model against the artifacts — the deviation and where it fails.

use super::args::LabCmd;
use super::data::{dataset_for, load};
use super::plotdata;
use super::print::print_compare;
use crate::report;
use crate::shared::calib::{self};
use crate::shared::output::commit_all;
use crate::shared::output::{outputs, put};
use anyhow::Result;
use scancorr_core::lab::analysis::{self};

/// Runs `scancorr lab compare`.
pub(super) fn exec(cmd: LabCmd) -> Result<()> {
    let LabCmd::Compare {
        data,
        before,
        json,
        report,
        csv,
    } = cmd
    else {
        unreachable!("lab compare")
    };
    if let Some(d) = &csv {
        plotdata::prepare(d)?;
    }
    let mut inputs = data.inputs();
    if let Some(b) = &before {
        inputs.push(("--before", b));
    }
    let [report_out] = outputs([("--report", report.as_deref())], &inputs)?;
    let l = load(&data)?;
    let ds = dataset_for(&l, &l.cal)?;
    let cmp = analysis::compare(&ds)?;
    let before = match before {
        Some(p) => {
            let c = calib::load_calibration(&p)?;
            let dsb = dataset_for(&l, &c)?;
            let cb = analysis::compare(&dsb)?;
            Some((dsb, cb))
        }
        None => None,
    };
    if let Some(p) = &report {
        let html = report::compare(&l.cal, &ds, &cmp, before.as_ref().map(|(d, c)| (d, c)));
        put(&report_out, html)?;
        commit_all([report_out])?;
        eprintln!("report: {}", p.display());
    }
    if let Some(d) = &csv {
        let mut files = plotdata::comparison(d, "", &cmp)?;
        if let Some((_, b)) = &before {
            files.extend(plotdata::comparison(d, "before-", b)?);
        }
        eprintln!("csv: {} in {}", files.join(", "), d.display());
    }
    if json {
        outln!("{}", serde_json::to_string_pretty(&cmp)?)?;
    } else {
        print_compare(&cmp, &l.cal)?;
    }
    Ok(())
}
