//! The lab's arguments: its subcommands (`LabCmd`) and the data every one of them reads
//! (`DataArgs`).

use super::plan;
use clap::{Args, Subcommand};
use std::path::{Path, PathBuf};

#[derive(Subcommand)]
pub enum LabCmd {
    /// Plan a campaign before measuring it: the scans that make every effect of the model
    /// (and the candidates it is confounded with) identifiable, each parameter's predicted σ;
    /// writes a program record `scancorr sim --program FILE` runs.
    Plan(plan::PlanArgs),
    /// Compare the model with measurements of known artifacts: deviation and where it fails.
    Compare {
        #[command(flatten)]
        data: DataArgs,
        /// Also correct with this calibration and show it as "before" in the report.
        #[arg(long)]
        before: Option<PathBuf>,
        /// Print JSON (`rms_um`, `pv_um`, `noise_floor_um`, `failures`, `traces`, …).
        #[arg(long)]
        json: bool,
        /// Write a self-contained HTML report.
        #[arg(long)]
        report: Option<PathBuf>,
        /// Write every plotted series as CSV into this folder (traces, bins, harmonics).
        #[arg(long, value_name = "DIR")]
        csv: Option<PathBuf>,
    },
    /// Rank the effects missing from the model by the residual they explain on held-out data.
    Diagnose {
        #[command(flatten)]
        data: DataArgs,
        /// Print JSON (`candidates`, `confounded`, `unexplained`).
        #[arg(long)]
        json: bool,
        /// Write a self-contained HTML report.
        #[arg(long)]
        report: Option<PathBuf>,
        /// Write every plotted series as CSV into this folder (the candidates, and the
        /// comparison's traces, bins and harmonics).
        #[arg(long, value_name = "DIR")]
        csv: Option<PathBuf>,
    },
    /// Add an effect (built-in, with variant, or custom), fit it, write a new version.
    Add {
        /// Effect: a library kind (`accel_deflection`), a variant (`accel_deflection:full,order=1`)
        /// or `custom` with --term.
        effect: String,
        #[command(flatten)]
        data: DataArgs,
        /// The new calibration version.
        #[arg(long)]
        out: PathBuf,
        /// Refit every effect of the model with the new one (the default; kept for scripts).
        #[arg(long, conflicts_with = "only_new")]
        refit_all: bool,
        /// Fit only the new effect, keeping the others as they are (the others stay biased by
        /// what they had absorbed; for comparison only).
        #[arg(long)]
        only_new: bool,
        /// Custom effect term AXIS:EXPR, e.g. 'x:sin(2*pi*x/4)' (repeatable).
        #[arg(long = "term")]
        terms: Vec<String>,
        /// Name of a custom effect.
        #[arg(long)]
        name: Option<String>,
        /// Print JSON (`rms_before_um`, `rms_after_um`, `heldout_rms_before_um`, `heldout_rms_after_um`).
        #[arg(long)]
        json: bool,
        /// Write a self-contained HTML report (before/after).
        #[arg(long)]
        report: Option<PathBuf>,
    },
    /// Take an effect out of the model (by id), refit the rest, write a new version.
    Remove {
        /// The effect's id (as `lab diagnose` and `calib check` name it).
        effect: String,
        #[command(flatten)]
        data: DataArgs,
        /// The new calibration version.
        #[arg(long)]
        out: PathBuf,
        /// Print JSON.
        #[arg(long)]
        json: bool,
    },
    /// The whole loop, unattended: refit the nominal model, then diagnose, add (or swap, or
    /// drop) the best candidate and refit everything until no candidate is significant. Each
    /// step is written as a calibration version in --out-dir.
    Discover {
        #[command(flatten)]
        data: DataArgs,
        /// Folder for the versions (v<N>.json, one per step) and the final `calibration.json`.
        #[arg(long)]
        out_dir: PathBuf,
        /// Most steps.
        #[arg(long, default_value_t = 20)]
        max_steps: usize,
        /// Print JSON (`steps`, `confounded`, `final`).
        #[arg(long)]
        json: bool,
        /// Write a self-contained HTML report of the steps and the error fall.
        #[arg(long)]
        report: Option<PathBuf>,
        /// When the loop stops with a confounded pair or parameters not determined, the
        /// artifacts the plan it writes (--out-dir/plan.json) may use: ring:d=50.0012,
        /// sphere:d=25.0004, straightedge:l=400 (repeatable; default: those the bags measured).
        #[arg(long)]
        plan_artifact: Vec<String>,
        /// Machine time for that plan, minutes.
        #[arg(long, default_value_t = 8.0)]
        plan_minutes: f64,
    },
    /// Refit an unchanged model: the nominal model's time constants, then every effect.
    Fit {
        #[command(flatten)]
        data: DataArgs,
        /// The new calibration version.
        #[arg(long)]
        out: PathBuf,
        /// Print JSON.
        #[arg(long)]
        json: bool,
        /// Write the refitted version even when it is worse than the one it starts from.
        /// Worse: a larger RMS on the fit data, or on the --validate data when given, by more
        /// than 3 % + 0.05 × the noise floor (above 1 % + 0.02 × the floor: a warning only).
        /// Without this flag such a refit is refused: nothing is written and the exit code is
        /// 1; with it, it is written with a warning.
        #[arg(long)]
        accept_worse: bool,
    },
    /// The error fall across calibration versions.
    History {
        /// Folder of calibration documents (*.json).
        #[arg(long)]
        calib_dir: Option<PathBuf>,
        /// The machine's versions in the service's store (asks scancorrd at --connect).
        #[arg(long)]
        machine: Option<String>,
        /// Re-evaluate every version on these bags (otherwise the figures recorded by the lab).
        #[arg(long)]
        bag: Vec<PathBuf>,
        /// Artifact for bags without a program record.
        #[arg(long)]
        artifact: Option<String>,
        /// Print JSON.
        #[arg(long)]
        json: bool,
        /// Write a self-contained HTML report.
        #[arg(long)]
        report: Option<PathBuf>,
        #[command(flatten)]
        bus: crate::shared::bus::Bus,
    },
}

#[derive(Args)]
pub struct DataArgs {
    /// Bags to fit (MCAP).
    #[arg(long, required = true)]
    pub(super) bag: Vec<PathBuf>,
    /// The calibration to start from.
    #[arg(long)]
    pub(super) calib: PathBuf,
    /// Held-out bags (otherwise every other scan of each artifact is held out).
    #[arg(long)]
    pub(super) validate: Vec<PathBuf>,
    /// The artifact, for bags that do not say: ring:d=50.0012, sphere:d=25.0004, straightedge.
    #[arg(long)]
    pub(super) artifact: Option<String>,
    /// Keep every N-th point of a scan.
    #[arg(long, default_value_t = 4)]
    pub(super) stride: usize,
}

impl DataArgs {
    /// Every input file, with its flag.
    pub(super) fn inputs(&self) -> Vec<(&'static str, &Path)> {
        let mut v: Vec<(&'static str, &Path)> = vec![("--calib", self.calib.as_path())];
        v.extend(self.bag.iter().map(|b| ("--bag", b.as_path())));
        v.extend(self.validate.iter().map(|b| ("--validate", b.as_path())));
        v
    }
}
