//! What the calibrate procedures share on their command line: the bags measured, the
//! calibration started from and the new version written ([`VersionArgs`]), and what is printed
//! ([`PrintArgs`]: JSON, an HTML report). Each procedure flattens them into its own arguments
//! (`#[command(flatten)]`); its own words for them (what its bags hold, what of the starting
//! calibration it replaces, what its JSON and report show) stand in [`HELP`], side by side.

use clap::Args;
use std::path::PathBuf;

// No doc comment on the two structs: a flattened struct's doc would be its command's about.

#[derive(Args, Debug)]
pub struct VersionArgs {
    /// Bags of the measurement.
    #[arg(long, required = true)]
    pub bag: Vec<PathBuf>,
    /// The calibration to start from.
    #[arg(long)]
    pub calib: PathBuf,
    /// The new calibration version.
    #[arg(long)]
    pub out: PathBuf,
}

#[derive(Args, Debug)]
pub struct PrintArgs {
    /// Print JSON.
    #[arg(long)]
    pub json: bool,
    /// Write an HTML report.
    #[arg(long)]
    pub report: Option<PathBuf>,
}

/// Each procedure's help for the shared arguments, by subcommand and argument (one paragraph,
/// no closing full stop, as clap makes of a doc comment).
const HELP: &[(&str, &str, &str)] = &[
    ("tips", "bag", "Bags of the qualification (the master sphere measured by every tip)"),
    ("tips", "calib", "The calibration to start from (catalogue styli or an earlier qualification)"),
    ("tips", "json", "Print JSON (`params` and `uncertainty` by the simulator's truth names, `settings`, …)"),
    ("tips", "report", "Write an HTML report: each setting against the reference before and after, the reference's drift in time, every parameter"),
    ("scales", "bag", "Bags of the measurement (`scancorr sim --program scales`)"),
    ("scales", "calib", "The calibration to start from (its scale_thermal is replaced)"),
    ("probe-force", "bag", "Bags of the measurement (each tip on the sphere at ≥ 2 deflections)"),
    ("probe-force", "calib", "The calibration to start from (its probe_force effect is replaced)"),
    ("probe-force", "json", "Print JSON (`params` and `uncertainty` by the simulator's truth names, `settings`, …)"),
    ("probe-force", "report", "Write an HTML report: each setting's radius against deflection before and after, every parameter"),
    ("straightness", "json", "Print JSON: per station `stations_mm`, `guide_straightness_mm`, `part_straightness_mm`, `pitch_rad`, each with `…_u`, and `cannot_see`"),
    ("straightness", "report", "Write an HTML report: guide and part profiles with uncertainty bands, the pitch"),
    ("dynamics", "bag", "Bags of the ring measurement"),
    ("dynamics", "calib", "The calibration to start from (its dynamic effects are replaced)"),
    ("dynamics", "json", "Print JSON (`params` and `uncertainty` by the simulator's truth names, `positions`, …)"),
    ("dynamics", "report", "Write an HTML report: ΔR against acceleration per position before and after, the fitted compliance along each line of positions, every parameter"),
    ("dynamic-map", "bag", "Bags of the measurement (S1, F1 and F2 of one circle)"),
    ("dynamic-map", "calib", "The calibration to start from (its maps of these scans are replaced)"),
    ("dynamic-map", "json", "Print JSON (`params` and `uncertainty`, `maps` with every bin's S1, F1, F2, HSZD, LSZD, e1, e2 and their σ in µm)"),
    ("dynamic-map", "report", "Write an HTML report: the scans, the extrapolations to zero deflection and e2 per map"),
    ("thermal-drift", "report", "Write an HTML report: per channel the drift against time (measured, nominal, model), the residual, and the drift against the sensor it follows most"),
];

/// The words of [`HELP`] for `command`'s shared arguments:
/// `#[command(mut_args(helps("tips")))]` on its arguments' struct.
pub fn helps(command: &'static str) -> impl FnMut(clap::Arg) -> clap::Arg {
    move |a| match HELP
        .iter()
        .find(|(c, id, _)| *c == command && a.get_id() == *id)
    {
        Some((_, _, text)) => a.help(*text),
        None => a,
    }
}
