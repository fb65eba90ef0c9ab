//! `scancorr lab …`: the model lab's I/O — reading bags and calibrations, printing, writing
//! new calibration versions and reports. The logic is `scancorr_core::lab`.

use crate::offline;
use crate::output::{commit_all, refuse_same_file, AtomicOutput};
use crate::report;
use anyhow::{bail, Context, Result};
use clap::{Args, Subcommand};
use scancorr_core::effects::{custom, EffectConfig};
use scancorr_core::lab::analysis::{self, Comparison, Diagnosis};
use scancorr_core::lab::dataset::{self, BagData, BuildOptions, Dataset};
use scancorr_core::lab::program::{parse_artifact, ProgramSpec};
use scancorr_core::lab::version;
use scancorr_core::sample::Axis;
use scancorr_core::Calibration;
use std::path::{Path, PathBuf};

use crate::plancmd;

#[derive(Subcommand)]
pub enum LabCmd {
    /// Plan a campaign before measuring it: the scans that make every effect of the model
    /// (and the candidates it is confounded with) identifiable, each parameter's predicted σ;
    /// writes a program record `scancorr sim --program FILE` runs.
    Plan(plancmd::PlanArgs),
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
        bus: crate::bus::Bus,
    },
}

#[derive(Args)]
pub struct DataArgs {
    /// Bags to fit (MCAP).
    #[arg(long, required = true)]
    bag: Vec<PathBuf>,
    /// The calibration to start from.
    #[arg(long)]
    calib: PathBuf,
    /// Held-out bags (otherwise every other scan of each artifact is held out).
    #[arg(long)]
    validate: Vec<PathBuf>,
    /// The artifact, for bags that do not say: ring:d=50.0012, sphere:d=25.0004, straightedge.
    #[arg(long)]
    artifact: Option<String>,
    /// Keep every N-th point of a scan.
    #[arg(long, default_value_t = 4)]
    stride: usize,
}

pub(crate) const SENSORS: [&str; 5] = ["stylus", "scale_x", "scale_y", "scale_z", "air"];

/// Loads bags for the lab.
pub fn load_bags(paths: &[PathBuf], validation: &[PathBuf], machine: &str) -> Result<Vec<BagData>> {
    let mut out = vec![];
    for (p, v) in paths
        .iter()
        .map(|p| (p, false))
        .chain(validation.iter().map(|p| (p, true)))
    {
        let input = offline::read_lazy(p, Some(machine))?;
        for w in &input.warnings {
            eprintln!("warning: {w}");
        }
        let program = input
            .metadata
            .iter()
            .find(|(n, _)| n == "scancorr.program")
            .and_then(|(_, m)| m.get("json"))
            .map(|j| serde_json::from_str::<ProgramSpec>(j))
            .transpose()
            .with_context(|| {
                format!("{}: the scancorr.program record is not valid", p.display())
            })?;
        out.push(BagData {
            name: p.display().to_string(),
            samples: std::sync::Arc::new(input.samples),
            program,
            validation: v,
        });
    }
    Ok(out)
}

struct Loaded {
    bags: Vec<BagData>,
    cal: Calibration,
    opts: BuildOptions,
}

fn load(d: &DataArgs) -> Result<Loaded> {
    load_from(d, offline::load_calibration(&d.calib)?)
}

/// [`load`] with the calibration already read.
fn load_from(d: &DataArgs, cal: Calibration) -> Result<Loaded> {
    crate::output::stage(&format!(
        "reading {} bag(s) …",
        d.bag.len() + d.validate.len()
    ));
    let bags = load_bags(&d.bag, &d.validate, &cal.machine_id)?;
    let artifact = d
        .artifact
        .as_deref()
        .map(parse_artifact)
        .transpose()
        .map_err(|e| anyhow::anyhow!("--artifact: {e}"))?;
    let opts = BuildOptions {
        stride: d.stride.max(1),
        holdout_by_segment: true,
        artifact,
        sensors: SENSORS.iter().map(|s| s.to_string()).collect(),
    };
    Ok(Loaded { bags, cal, opts })
}

fn dataset_for(l: &Loaded, cal: &Calibration) -> Result<Dataset> {
    crate::output::stage(&format!("correcting the scans with v{} …", cal.version));
    let ds = dataset::build(&l.bags, cal, &l.opts)?;
    crate::output::stage(&format!("{} points; analysing …", ds.points.len()));
    for w in &ds.warnings {
        eprintln!("warning: {w}");
    }
    Ok(ds)
}

pub(crate) fn now_rfc3339() -> String {
    let secs = std::time::SystemTime::now()
        .duration_since(std::time::UNIX_EPOCH)
        .map(|d| d.as_secs())
        .unwrap_or(0) as i64;
    scancorr_core::calib::rfc3339_utc(secs)
}

fn um(x: f64) -> String {
    format!("{x:.3}")
}

impl DataArgs {
    /// Every input file, with its flag.
    fn inputs(&self) -> Vec<(&'static str, &Path)> {
        let mut v: Vec<(&'static str, &Path)> = vec![("--calib", self.calib.as_path())];
        v.extend(self.bag.iter().map(|b| ("--bag", b.as_path())));
        v.extend(self.validate.iter().map(|b| ("--validate", b.as_path())));
        v
    }
}

/// Refuses outputs that are inputs (or each other), then prepares every output (a temporary
/// file next to each, so an unwritable folder fails before the work).
pub(crate) fn outputs<const N: usize>(
    outs: [(&str, Option<&Path>); N],
    inputs: &[(&str, &Path)],
) -> Result<[Option<AtomicOutput>; N]> {
    let named: Vec<(&str, &Path)> = outs
        .iter()
        .filter_map(|(f, p)| p.map(|p| (*f, p)))
        .collect();
    refuse_same_file(&named, inputs)?;
    crate::provenance::register(inputs);
    let mut v = Vec::with_capacity(N);
    for (f, p) in outs {
        v.push(p.map(|p| AtomicOutput::new(f, p)).transpose()?);
    }
    Ok(v.try_into().unwrap_or_else(|_| unreachable!("N outputs")))
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

/// Writes `text` to a prepared output; an HTML report gets the provenance block.
pub(crate) fn put(o: &Option<AtomicOutput>, text: impl AsRef<[u8]>) -> Result<()> {
    if let Some(o) = o {
        let t = text.as_ref();
        if t.starts_with(b"<!doctype html>") {
            let doc = String::from_utf8_lossy(t);
            o.write_all(crate::provenance::insert(&doc, &now_rfc3339()))?;
        } else {
            o.write_all(t)?;
        }
    }
    Ok(())
}

/// Runs a lab command.
pub fn run(cmd: LabCmd) -> Result<()> {
    crate::output::started();
    match cmd {
        LabCmd::Plan(a) => plancmd::exec(a),
        LabCmd::Compare {
            data,
            before,
            json,
            report,
            csv,
        } => {
            if let Some(d) = &csv {
                crate::plotdata::prepare(d)?;
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
                    let c = offline::load_calibration(&p)?;
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
                let mut files = crate::plotdata::comparison(d, "", &cmp)?;
                if let Some((_, b)) = &before {
                    files.extend(crate::plotdata::comparison(d, "before-", b)?);
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
        LabCmd::Diagnose {
            data,
            json,
            report,
            csv,
        } => {
            let [report_out] = outputs([("--report", report.as_deref())], &data.inputs())?;
            if let Some(d) = &csv {
                crate::plotdata::prepare(d)?;
            }
            let l = load(&data)?;
            let ds = dataset_for(&l, &l.cal)?;
            let dg = analysis::diagnose(&ds)?;
            let cmp = if report.is_some() || csv.is_some() {
                Some(analysis::compare(&ds)?)
            } else {
                None
            };
            if let (Some(p), Some(cmp)) = (&report, &cmp) {
                put(&report_out, report::diagnose(&l.cal, &ds, cmp, &dg))?;
                commit_all([report_out])?;
                eprintln!("report: {}", p.display());
            }
            if let (Some(d), Some(cmp)) = (&csv, &cmp) {
                let mut files = crate::plotdata::diagnosis(d, &dg)?;
                files.extend(crate::plotdata::comparison(d, "", cmp)?);
                eprintln!("csv: {} in {}", files.join(", "), d.display());
            }
            if json {
                outln!("{}", serde_json::to_string_pretty(&dg)?)?;
            } else {
                print_diagnosis(&dg, &data)?;
            }
            Ok(())
        }
        LabCmd::Add {
            effect,
            data,
            out,
            refit_all,
            only_new,
            terms,
            name,
            json,
            report,
        } => {
            let [out_file, report_out] = outputs(
                [
                    ("--out", Some(out.as_path())),
                    ("--report", report.as_deref()),
                ],
                &data.inputs(),
            )?;
            let l = load(&data)?;
            let ds = dataset_for(&l, &l.cal)?;
            let prep = analysis::prepare(&ds)?;
            // Candidate moves: the custom effect, one variant, or every variant of a kind.
            let cands: Vec<analysis::Candidate> = if effect == "custom" {
                if terms.is_empty() {
                    bail!("a custom effect needs terms: --term 'x:sin(2*pi*x/4)' --term 'x:cos(2*pi*x/4)'");
                }
                let mut ts = vec![];
                for t in &terms {
                    let (a, e) = t
                        .split_once(':')
                        .with_context(|| format!("--term {t}: expected AXIS:EXPR"))?;
                    let axis = match a.trim() {
                        "x" => Axis::X,
                        "y" => Axis::Y,
                        "z" => Axis::Z,
                        o => bail!("--term {t}: axis `{o}` (x, y or z)"),
                    };
                    ts.push(custom::Term {
                        axis,
                        expr: e.trim().to_string(),
                    });
                }
                let id = name.clone().unwrap_or_else(|| "custom".into());
                if l.cal.effects.iter().any(|e| e.id() == id) {
                    bail!("an effect with id `{id}` is already in the model; give the new one another --name");
                }
                let n = ts.len();
                vec![analysis::Candidate {
                    action: analysis::Move::Add,
                    effect: id.clone(),
                    replaces: None,
                    config: Some(EffectConfig::Custom(custom::Config {
                        id,
                        dynamic: false,
                        terms: ts,
                        coefficients: vec![0.0; n],
                    })),
                }]
            } else {
                let mut c = analysis::moves_named(&ds, &effect)?;
                if let Some(n) = &name {
                    scancorr_proto::names::check("--name", n)
                        .map_err(|e| anyhow::anyhow!("{e}"))?;
                    for m in &mut c {
                        if m.action == analysis::Move::Add {
                            if let Some(cfg) = &mut m.config {
                                cfg.set_id(Some(n.clone()));
                            }
                        }
                    }
                }
                c
            };
            let _ = refit_all;
            let applied = analysis::apply(&ds, cands, only_new)?;
            let advice = applied.advice.clone();
            let o = applied.outcome;
            let vname = match &applied.candidate.replaces {
                Some(r) => format!("{} (replacing {r})", applied.candidate.effect),
                None => applied.candidate.effect.clone(),
            };
            let mut new = version::next(&l.cal, applied.effects, &now_rfc3339());
            // Measure, don't extrapolate: correct again with the new version.
            let ds_after = dataset_for(&l, &new)?;
            let after = analysis::prepare(&ds_after)?;
            let what = format!(
                "lab add {vname}{}",
                if only_new {
                    " (only the new effect fitted)"
                } else {
                    ""
                }
            );
            version::describe(&mut new, &what, ds.noise_floor_um, &prep, &after);
            new.build().context("the fitted calibration")?;
            put(&out_file, new.to_json())?;
            if report.is_some() {
                let cmp_b = analysis::compare(&ds)?;
                let cmp_a = analysis::compare(&ds_after)?;
                put(
                    &report_out,
                    report::add(&l.cal, &new, &o, &ds, &cmp_b, &ds_after, &cmp_a),
                )?;
            }
            // Every output complete: only now do they replace anything.
            commit_all([out_file, report_out])?;
            if let Some(p) = &report {
                eprintln!("report: {}", p.display());
            }
            let summary = serde_json::json!({
                "effect": vname,
                "version": new.version,
                "parent_version": l.cal.version,
                "rms_before_um": prep.rms_fit_um,
                "rms_after_um": after.rms_fit_um,
                "heldout_rms_before_um": prep.rms_held_um,
                "heldout_rms_after_um": after.rms_held_um,
                "noise_floor_um": ds.noise_floor_um,
                "params": o.params.last(),
                "unidentifiable": o.unidentifiable,
                "heldout_improved": after.rms_held_um < prep.rms_held_um,
                "cv_rms_before_um": o.cv_rms_before_um,
                "cv_rms_after_um": o.cv_rms_after_um,
                "advice": advice,
                "out": out,
            });
            for a in &advice {
                eprintln!("note: {a}");
            }
            if after.rms_held_um >= prep.rms_held_um && prep.rms_held_um > 0.0 {
                eprintln!(
                    "warning: {vname} does not improve the held-out data ({} → {} µm): `lab diagnose` would not propose it; keep the parent version",
                    um(prep.rms_held_um),
                    um(after.rms_held_um)
                );
            }
            if json {
                outln!("{}", serde_json::to_string_pretty(&summary)?)?;
            } else {
                outln!(
                    "added {vname} → {} (version {}, parent {})",
                    out.display(),
                    new.version,
                    l.cal.version
                )?;
                outln!(
                    "  RMS on fit data   {:>8} → {:>8} µm",
                    um(prep.rms_fit_um),
                    um(after.rms_fit_um)
                )?;
                outln!(
                    "  RMS held out      {:>8} → {:>8} µm   (noise floor {} µm)",
                    um(prep.rms_held_um),
                    um(after.rms_held_um),
                    um(ds.noise_floor_um)
                )?;
                if data.validate.is_empty() {
                    outln!(
                        "  (no --validate: the alternate scans held out above are fitted too; each half predicted by the other: {} → {} µm)",
                        um(o.cv_rms_before_um),
                        um(o.cv_rms_after_um)
                    )?;
                }
                let ps = o.params.last().map(Vec::as_slice).unwrap_or_default();
                for p in ps.iter().take(12) {
                    match p.sigma {
                        Some(_) => outln!(
                            "    {:<44} {}{}",
                            p.name,
                            report::value_sigma(p.value, p.sigma),
                            p.note
                                .as_deref()
                                .map(|n| format!("  ({n})"))
                                .unwrap_or_default()
                        )?,
                        None => outln!(
                            "    {:<44} {} (not determined by this data)",
                            p.name,
                            report::value_sigma(p.value, None)
                        )?,
                    }
                }
                if ps.len() > 12 {
                    outln!(
                        "    … {} more (every one in --json and --report)",
                        ps.len() - 12
                    )?;
                }
                if !o.unidentifiable.is_empty() {
                    outln!(
                        "  {} parameter(s) not determined by this data (minimum-norm values)",
                        o.unidentifiable.len()
                    )?;
                }
            }
            Ok(())
        }
        LabCmd::Remove {
            effect,
            data,
            out,
            json,
        } => {
            let [out_file] = outputs([("--out", Some(out.as_path()))], &data.inputs())?;
            let l = load(&data)?;
            if !l.cal.effects.iter().any(|e| e.id() == effect) {
                bail!(
                    "the model has no effect `{effect}` (it has: {})",
                    l.cal
                        .effects
                        .iter()
                        .map(|e| e.id())
                        .collect::<Vec<_>>()
                        .join(", ")
                );
            }
            let ds = dataset_for(&l, &l.cal)?;
            let prep = analysis::prepare(&ds)?;
            let applied = analysis::apply(
                &ds,
                vec![analysis::Candidate {
                    action: analysis::Move::Drop,
                    effect: effect.clone(),
                    replaces: Some(effect.clone()),
                    config: None,
                }],
                false,
            )?;
            let mut new = version::next(&l.cal, applied.effects, &now_rfc3339());
            let ds_after = dataset_for(&l, &new)?;
            let after = analysis::prepare(&ds_after)?;
            version::describe(
                &mut new,
                &format!("lab remove {effect}"),
                ds.noise_floor_um,
                &prep,
                &after,
            );
            new.build().context("the refitted calibration")?;
            put(&out_file, new.to_json())?;
            commit_all([out_file])?;
            let summary = serde_json::json!({
                "removed": effect,
                "version": new.version,
                "parent_version": l.cal.version,
                "rms_before_um": prep.rms_fit_um,
                "rms_after_um": after.rms_fit_um,
                "heldout_rms_before_um": prep.rms_held_um,
                "heldout_rms_after_um": after.rms_held_um,
                "noise_floor_um": ds.noise_floor_um,
                "out": out,
            });
            if json {
                outln!("{}", serde_json::to_string_pretty(&summary)?)?;
            } else {
                outln!(
                    "removed {effect} → {} (version {}, parent {})",
                    out.display(),
                    new.version,
                    l.cal.version
                )?;
                outln!(
                    "  RMS on fit data   {:>8} → {:>8} µm",
                    um(prep.rms_fit_um),
                    um(after.rms_fit_um)
                )?;
                outln!(
                    "  RMS held out      {:>8} → {:>8} µm   (noise floor {} µm)",
                    um(prep.rms_held_um),
                    um(after.rms_held_um),
                    um(ds.noise_floor_um)
                )?;
            }
            Ok(())
        }
        LabCmd::Discover {
            data,
            out_dir,
            max_steps,
            json,
            report,
        } => {
            // Every file the loop will write, against every input and each other, before any
            // work: the step versions after the start's, `calibration.json`, --report.
            let start = offline::load_calibration(&data.calib)?;
            let first = start.version.saturating_add(1);
            let last = first.saturating_add(max_steps as u64);
            let inputs = data.inputs();
            let mut others = inputs.clone();
            if let Some(r) = &report {
                others.push(("--report", r.as_path()));
            }
            let written = discover_outputs(&out_dir, first, last, &others);
            let mut outs: Vec<(&str, &Path)> =
                written.iter().map(|p| ("--out-dir", p.as_path())).collect();
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
                crate::output::write_file("--out-dir", &path, st.calibration.to_json())
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
            crate::output::write_file(
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
        LabCmd::Fit { data, out, json } => {
            let [out_file] = outputs([("--out", Some(out.as_path()))], &data.inputs())?;
            let l = load(&data)?;
            let raw: Vec<&dyn dataset::Samples> = l
                .bags
                .iter()
                .filter(|b| !b.validation)
                .map(|b| &*b.samples)
                .collect();
            let (mut new, axes) = scancorr_core::lab::nominal::fit_nominal(&raw, &l.cal)?;
            let ds0 = dataset_for(&l, &l.cal)?;
            let p0 = analysis::prepare(&ds0)?;
            let ds = dataset_for(&l, &new)?;
            let prep = analysis::prepare(&ds)?;
            let mut unident = vec![];
            if !new.effects.is_empty() {
                let o = analysis::fit_effects(&ds, &prep, &new.effects)?;
                new.effects = o.configs;
                unident = o.unidentifiable;
            }
            // `new` is the start with its nominal model and effects refitted: its child.
            let mut new = version::next(&new, new.effects.clone(), &now_rfc3339());
            let ds_after = dataset_for(&l, &new)?;
            let after = analysis::prepare(&ds_after)?;
            version::describe(&mut new, "lab fit", ds.noise_floor_um, &p0, &after);
            put(&out_file, new.to_json())?;
            commit_all([out_file])?;
            let s = serde_json::json!({
                "version": new.version,
                "nominal": axes,
                "rms_before_um": p0.rms_fit_um,
                "rms_after_um": after.rms_fit_um,
                "heldout_rms_before_um": p0.rms_held_um,
                "heldout_rms_after_um": after.rms_held_um,
                "unidentifiable": unident,
            });
            if json {
                outln!("{}", serde_json::to_string_pretty(&s)?)?;
            } else {
                outln!("refit → {} (version {})", out.display(), new.version)?;
                for a in &axes {
                    outln!(
                        "  axis {}: τ {:.5} → {:.5} s, tracking RMS {:.2} → {:.2} µm",
                        a.axis,
                        a.tau_before_s,
                        a.tau_after_s,
                        a.rms_before_um,
                        a.rms_after_um
                    )?;
                }
                outln!(
                    "  RMS fit {} → {} µm, held out {} → {} µm",
                    um(p0.rms_fit_um),
                    um(after.rms_fit_um),
                    um(p0.rms_held_um),
                    um(after.rms_held_um)
                )?;
            }
            Ok(())
        }
        LabCmd::History {
            calib_dir,
            machine,
            bag,
            artifact,
            json,
            report,
            bus,
        } => {
            if let Some(m) = &machine {
                crate::output::check_machine("--machine", m)?;
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
            let mut cals: Vec<(PathBuf, Calibration)> = vec![];
            match (&machine, &calib_dir) {
                (Some(m), None) => {
                    // Every version the service keeps for the machine.
                    let key = scancorr_proto::calibration_key(&bus.prefix, m);
                    let list: serde_json::Value = serde_json::from_str(&crate::bus::query(&bus, format!("{key}?history"))?)
                        .context("the service's history reply")?;
                    for v in list.as_array().into_iter().flatten() {
                        let n = v["version"].as_u64().context("a version number")?;
                        let doc = crate::bus::query(&bus, format!("{key}?version={n}"))?;
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
                            if let Ok(c) = offline::load_calibration(&p) {
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
                // What this version added to (or removed from) its parent's effects.
                let parent = cals
                    .iter()
                    .find(|(_, q)| Some(q.version) == c.parent_version)
                    .map(|(_, q)| q.effects.iter().map(|e| e.id()).collect::<Vec<_>>());
                let ids: Vec<String> = c.effects.iter().map(|e| e.id()).collect();
                let change = match &parent {
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
                };
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
    }
}

fn print_compare(c: &Comparison, cal: &Calibration) -> Result<()> {
    outln!(
        "calibration v{} ({} effects): {} points",
        cal.version,
        cal.effects.len(),
        c.points
    )?;
    outln!(
        "  deviation RMS {} µm, peak-to-valley {} µm, noise floor {} µm",
        um(c.rms_um),
        um(c.pv_um),
        um(c.noise_floor_um)
    )?;
    if c.failures.is_empty() {
        outln!("  no bin stands out (every bin within 1.3 × the RMS or 2 × the noise floor)")?;
    } else {
        outln!("  where it fails (bins standing out; bins of the same points seen through a correlated feature under the worst):")?;
        for b in c
            .failures
            .iter()
            .filter(|b| b.same_points_as.is_none())
            .take(10)
        {
            outln!(
                "    {:<22} {:<28} RMS {:>7} µm  mean {:>7} µm  ({} points)",
                b.feature,
                b.bin,
                um(b.rms_um),
                um(b.mean_um),
                b.n
            )?;
            let same = c.same_points(b);
            if !same.is_empty() {
                outln!("      the same points as {}", same.join(", "))?;
            }
        }
    }
    let mut features: Vec<usize> = c.traces.iter().map(|t| t.feature).collect();
    features.dedup();
    if !features.is_empty() {
        outln!(
            "  circularity per direction and speed (each trace about its own centre, 1° means):"
        )?;
    }
    for fi in features {
        let ts: Vec<String> = c
            .traces
            .iter()
            .filter(|t| t.feature == fi)
            .map(|t| {
                format!(
                    "{} {} mm/s {} µm",
                    if t.direction > 0 { "CCW" } else { "CW" },
                    t.speed_mm_s,
                    um(t.circularity_um)
                )
            })
            .collect();
        let t0 = c.traces.iter().find(|t| t.feature == fi).expect("listed");
        outln!(
            "    {} {} (Ø{} mm): {}",
            t0.artifact,
            fi + 1,
            t0.diameter_mm,
            ts.join(", ")
        )?;
    }
    for h in &c.harmonics {
        let a: Vec<String> = h
            .amplitude_um
            .iter()
            .enumerate()
            .map(|(k, a)| format!("{}θ {:.3}", k + 1, a))
            .collect();
        outln!(
            "  {} {} harmonics (µm; 1θ is the centre, taken out by the fit): {}",
            h.artifact,
            h.feature + 1,
            a.join("  ")
        )?;
    }
    Ok(())
}

/// What a structure is, in words.
fn structure_text(s: &scancorr_core::lab::analysis::Structure) -> String {
    match (s.kind.as_str(), s.period_mm, s.harmonic) {
        ("probe_direction", _, Some(k)) => {
            format!("the {k}θ harmonic of the probing direction (probe lobing)")
        }
        (_, Some(p), _) => format!("a period of {p:.4} mm along {}", s.axis),
        ("reversal", _, _) => format!("the sign of the {} velocity (reversal)", s.axis),
        (k, _, _) => format!("{k} along {}", s.axis),
    }
}

/// A complete `lab add custom` command for a structure: it runs as it is.
fn custom_command(s: &scancorr_core::lab::analysis::Structure, d: &DataArgs) -> String {
    let q = |p: &Path| {
        let t = p.display().to_string();
        if t.chars()
            .all(|c| c.is_ascii_alphanumeric() || "._-/+=,".contains(c))
        {
            t
        } else {
            format!("'{}'", t.replace('\'', "'\\''"))
        }
    };
    let name = match (s.kind.as_str(), s.harmonic) {
        ("probe_direction", Some(k)) => format!("probe_direction_{k}"),
        (k, _) => format!("{k}_{}", s.axis),
    };
    let mut c = format!("scancorr lab add custom --name {name}");
    for t in &s.custom_terms {
        c += &format!(" --term '{t}'");
    }
    for b in &d.bag {
        c += &format!(" --bag {}", q(b));
    }
    for b in &d.validate {
        c += &format!(" --validate {}", q(b));
    }
    if let Some(a) = &d.artifact {
        c += &format!(" --artifact {a}");
    }
    if d.stride != 4 {
        c += &format!(" --stride {}", d.stride);
    }
    c += &format!(" --calib {} --out next.json", q(&d.calib));
    c
}

fn print_diagnosis(d: &Diagnosis, data: &DataArgs) -> Result<()> {
    outln!(
        "residual RMS {} µm (cross-validated {} µm, held out {} µm), noise floor {} µm, {} fit / {} held-out points",
        um(d.rms_um),
        um(d.cv_rms_um),
        um(d.heldout_rms_um),
        um(d.noise_floor_um),
        d.points[0],
        d.points[1]
    )?;
    outln!(
        "  {:<34} {:>9} {:>4} {:>11} {:>11} {:>9}",
        "candidate",
        "explained",
        "sig",
        "held-out µm",
        "fit µm",
        "ΔBIC"
    )?;
    for c in d.candidates.iter().take(12) {
        outln!(
            "  {:<34} {:>8.1}% {:>4} {:>5}→{:<5} {:>5}→{:<5} {:>9.0}",
            match (&c.action, &c.replaces) {
                (analysis::Move::Swap, Some(r)) => format!("{} for {r}", c.effect),
                (analysis::Move::Drop, _) => format!("drop {}", c.effect),
                _ => c.effect.clone(),
            },
            c.explained * 100.0,
            if c.significant { "yes" } else { "no" },
            format!("{:.3}", c.heldout_rms_before_um),
            format!("{:.3}", c.heldout_rms_after_um),
            format!("{:.3}", c.rms_before_um),
            format!("{:.3}", c.rms_after_um),
            c.delta_bic
        )?;
    }
    if !d.candidates.iter().any(|c| c.significant) {
        outln!("  no candidate is significant (none removes half the noise floor from scans it was not fitted on)")?;
    }
    for s in &d.skipped {
        outln!("  not tested: {s}")?;
    }
    for c in &d.confounded {
        outln!("  confounded: {} and {} (each reproduces {:.0} % / {:.0} % of the other) — to separate them:", c.effects[0], c.effects[1], c.r2[0] * 100.0, c.r2[1] * 100.0)?;
        for s in &c.separate_by {
            outln!("    · {s}")?;
        }
    }
    for s in &d.unexplained {
        outln!(
            "  unexplained: {}, amplitude {:.3} µm, {:.0} % of the residual →\n    {}",
            structure_text(s),
            s.amplitude_um,
            s.explained * 100.0,
            custom_command(s, data)
        )?;
    }
    Ok(())
}

fn print_discovery(d: &scancorr_core::lab::discover::Discovery, dir: &Path) -> Result<()> {
    let f = &d.r#final;
    outln!(
        "stopped: {} — held-out RMS {} → {} µm, noise floor {} µm ({:.2}× the floor), cross-validated {} µm",
        d.stopped,
        um(d.start_heldout_rms_um),
        um(f.heldout_rms_um),
        um(f.noise_floor_um),
        f.heldout_rms_um / f.noise_floor_um.max(1e-9),
        um(f.cv_rms_um)
    )?;
    outln!(
        "  final model v{} ({}): {}",
        f.version,
        dir.join("calibration.json").display(),
        f.effects.join(", ")
    )?;
    for c in &d.confounded {
        outln!(
            "  confounded on this campaign: {} and {} — to separate them:",
            c.effects[0],
            c.effects[1]
        )?;
        for s in &c.separate_by {
            outln!("    · {s}")?;
        }
    }
    for r in &d.refused {
        outln!("  not taken (held-out data worse): {r}")?;
    }
    if !d.unidentifiable.is_empty() {
        outln!("  {} parameter(s) the campaign cannot determine (kept at their minimum-norm values), e.g. {}", d.unidentifiable.len(), d.unidentifiable.iter().take(3).cloned().collect::<Vec<_>>().join("; "))?;
    }
    for s in &d.unexplained {
        outln!(
            "  left unexplained: {} along {} ({:.3} µm, {:.0} % of the residual)",
            s.kind,
            s.axis,
            s.amplitude_um,
            s.explained * 100.0
        )?;
    }
    Ok(())
}
