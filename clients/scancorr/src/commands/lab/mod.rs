//! `scancorr lab …`: the model lab's I/O — reading bags and calibrations, printing, writing
//! new calibration versions and reports. The logic is `scancorr_core::lab`.

mod args;
mod data;
pub mod plan;
mod plotdata;
mod print;

mod add;
mod compare;
mod diagnose;
mod discover;
mod fit;
mod history;
mod remove;

use anyhow::Result;
pub use args::LabCmd;

/// Runs a lab command.
pub fn exec(cmd: LabCmd) -> Result<()> {
    crate::shared::output::started();
    match cmd {
        LabCmd::Plan(a) => plan::exec(a),
        c @ LabCmd::Compare { .. } => compare::exec(c),
        c @ LabCmd::Diagnose { .. } => diagnose::exec(c),
        c @ LabCmd::Add { .. } => add::exec(c),
        c @ LabCmd::Remove { .. } => remove::exec(c),
        c @ LabCmd::Discover { .. } => discover::exec(c),
        c @ LabCmd::Fit { .. } => fit::exec(c),
        c @ LabCmd::History { .. } => history::exec(c),
    }
}
