//! `scancorr sim`: the simulator writing a bag, its ground truth and its starting calibration.

use crate::shared::output::AtomicOutput;
use anyhow::{bail, Context, Result};
use scancorr_bag::{Artifact, ArtifactKind, BagHeader, BagWriter, Stream};
use scancorr_core::sample::{Sample, StreamId};
use scancorr_core::wire::Batcher;
use scancorr_sim::{Fault, Options};
use std::collections::BTreeMap;
use std::path::{Path, PathBuf};

/// Arguments of `scancorr sim` (see `main.rs` for the flags).
pub struct SimArgs {
    pub options: Options,
    pub out: PathBuf,
    pub truth: Option<PathBuf>,
    pub calib_out: Option<PathBuf>,
    /// The machine's data sheet (what its maker states: not the truth).
    pub datasheet_out: Option<PathBuf>,
    /// The probe and stylus catalogue.
    pub catalogue_out: Option<PathBuf>,
    pub batch: usize,
    pub prefix: String,
    pub json: bool,
}

/// Parses `x,y,z`.
pub fn parse_position(s: &str) -> Result<[f64; 3]> {
    let v: Vec<f64> = s
        .split(',')
        .map(|p| p.trim().parse::<f64>())
        .collect::<Result<_, _>>()
        .with_context(|| format!("--position {s}: expected x,y,z in mm"))?;
    match v.as_slice() {
        [x, y, z] if v.iter().all(|a| a.is_finite()) => Ok([*x, *y, *z]),
        _ => bail!("--position {s}: expected three finite numbers x,y,z in mm"),
    }
}

/// The program record file `--program` names: a value that is not a built-in program and
/// ends in `.json` or names an existing file.
pub fn program_file(program: &str) -> Option<PathBuf> {
    let builtin = scancorr_sim::program::PROGRAMS.contains(&program)
        || scancorr_sim::straightness::PROGRAMS.contains(&program);
    let p = Path::new(program);
    (!builtin && (program.ends_with(".json") || p.is_file())).then(|| p.to_path_buf())
}

/// Parses `EFFECT=SCALE` or `EFFECT`.
pub fn parse_effect(s: &str) -> Result<(String, f64)> {
    match s.split_once('=') {
        Some((k, v)) => Ok((
            k.to_string(),
            v.parse()
                .with_context(|| format!("--effect {s}: scale must be a number"))?,
        )),
        None => Ok((s.to_string(), 1.0)),
    }
}

/// Parses a fault name.
pub fn parse_fault(s: &str) -> Result<Fault> {
    s.parse::<Fault>().map_err(anyhow::Error::msg)
}

fn stream_of(s: StreamId) -> Stream {
    match s {
        StreamId::Command => Stream::Command,
        StreamId::Scale => Stream::Scale,
        StreamId::Probe => Stream::Probe,
        StreamId::Temperature => Stream::Temperature,
    }
}

/// What a simulation wrote, not yet committed: the bag, the ground truth, the calibration,
/// the data sheet and catalogue, and the JSON summary (with `--json`).
pub struct Written {
    pub bag: AtomicOutput,
    truth: Option<AtomicOutput>,
    calib: Option<AtomicOutput>,
    datasheet: Option<AtomicOutput>,
    catalogue: Option<AtomicOutput>,
    json: Option<serde_json::Value>,
}

impl Written {
    /// Commits the truth and the calibration, and the bag when `keep_bag` (otherwise it is
    /// returned, uncommitted: removed when dropped); then prints the JSON summary.
    pub fn commit(self, keep_bag: bool) -> Result<Option<AtomicOutput>> {
        let Written {
            bag,
            truth,
            calib,
            datasheet,
            catalogue,
            json,
        } = self;
        crate::shared::output::commit_all([truth, calib, datasheet, catalogue])?;
        let bag = if keep_bag {
            bag.commit()?;
            None
        } else {
            Some(bag)
        };
        if let Some(j) = json {
            outln!("{j}")?;
        }
        Ok(bag)
    }
}

/// Runs the simulator into a bag, reports on stderr, and commits every output.
pub fn run(a: SimArgs) -> Result<()> {
    simulate(a, true)?.commit(true).map(|_| ())
}

/// Runs the simulator into a bag without a report.
pub fn run_quiet(a: SimArgs) -> Result<()> {
    simulate(a, false)?.commit(true).map(|_| ())
}

/// Runs the simulator: every output goes to a temporary file next to its final name, made
/// before the simulation starts (so an unwritable folder fails at once) and committed by
/// [`Written::commit`]. On an error nothing that existed is touched.
pub fn simulate(mut a: SimArgs, report: bool) -> Result<Written> {
    let record = program_file(&a.options.program);
    if let Some(path) = &record {
        if a.options.program_record.is_none() {
            anyhow::ensure!(
                a.options.position.is_none(),
                "--position: the program record {} places its own artifacts",
                path.display()
            );
            let text = std::fs::read_to_string(path)
                .with_context(|| format!("--program {}: reading", path.display()))?;
            let p = scancorr_core::lab::plan::Program::from_json(&text)
                .map_err(|e| anyhow::anyhow!("--program {}: {e}", path.display()))?;
            a.options.program_record = Some(p);
        }
    }
    {
        let mut outs: Vec<(&str, &Path)> = vec![("--out", a.out.as_path())];
        if let Some(p) = &a.truth {
            outs.push(("--truth", p));
        }
        if let Some(p) = &a.calib_out {
            outs.push(("--calib-out", p));
        }
        if let Some(p) = &a.datasheet_out {
            outs.push(("--datasheet-out", p));
        }
        if let Some(p) = &a.catalogue_out {
            outs.push(("--catalogue-out", p));
        }
        let ins: Vec<(&str, &Path)> = record
            .as_deref()
            .map(|p| ("--program", p))
            .into_iter()
            .collect();
        crate::shared::output::refuse_same_file(&outs, &ins)?;
    }
    crate::shared::output::check_machine("--machine", &a.options.machine_id)?;
    crate::shared::output::check_prefix(&a.prefix)?;
    let bag_out = AtomicOutput::new("--out", &a.out)?;
    let truth_out = AtomicOutput::optional("--truth", a.truth.as_deref())?;
    let calib_out = AtomicOutput::optional("--calib-out", a.calib_out.as_deref())?;
    let datasheet_out = AtomicOutput::optional("--datasheet-out", a.datasheet_out.as_deref())?;
    let catalogue_out = AtomicOutput::optional("--catalogue-out", a.catalogue_out.as_deref())?;
    let machine = a.options.machine_id.clone();
    let mut w = BagWriter::from_file(bag_out.file()?, bag_out.path(), BagHeader::default())
        .with_context(|| format!("creating {}", a.out.display()))?;
    let mut b = Batcher::new(&machine, a.batch);
    let mut err: Option<anyhow::Error> = None;
    let latency_ns = 1_000_000; // transmission: the bag's log time is the receive time
    let write = |w: &mut BagWriter, b: &mut Batcher, s: StreamId| -> Result<()> {
        if let Some((bytes, t0, t1)) = b.take(s) {
            w.write(
                stream_of(s),
                &machine,
                &a.prefix,
                (t1 + latency_ns).max(0) as u64,
                t0.max(0) as u64,
                &bytes,
            )?;
        }
        Ok(())
    };
    let t_start = std::time::Instant::now();
    let res = scancorr_sim::run(&a.options, |s: Sample| {
        if err.is_some() {
            return;
        }
        let full = b.push(&s);
        // Temperatures go out once per reading instant (all sensors of that instant).
        let flush_temp = matches!(&s, Sample::Temperature(t) if t.sensor == scancorr_sim::SENSORS[scancorr_sim::SENSORS.len() - 1]);
        let r = (|| -> Result<()> {
            if let Some(st) = full {
                write(&mut w, &mut b, st)?;
            }
            if flush_temp {
                write(&mut w, &mut b, StreamId::Temperature)?;
            }
            Ok(())
        })();
        if let Err(e) = r {
            err = Some(e);
        }
    })?;
    if let Some(e) = err {
        return Err(e.context(format!("writing {}", a.out.display())));
    }
    for s in StreamId::ALL {
        write(&mut w, &mut b, s)?;
    }
    // What the bag may say: the run, the program (features and segments), the artifact.
    let o = &a.options;
    let run_meta: BTreeMap<String, String> = [
        ("program", o.program.clone()),
        ("machine_id", machine.clone()),
        ("seed", o.seed.to_string()),
        ("machine_seed", o.machine_seed.to_string()),
        ("rate_hz", o.rate_hz.to_string()),
        ("source", "scancorr sim".to_string()),
    ]
    .into_iter()
    .map(|(k, v)| (k.to_string(), v))
    .chain(
        o.no_arcs
            .then(|| ("command_arcs".to_string(), "none".to_string())),
    )
    .collect();
    w.write_metadata(scancorr_bag::RUN_METADATA, &run_meta)?;
    let program_json = serde_json::to_string(&res.program)?;
    w.write_metadata(
        "scancorr.program",
        &[("json".to_string(), program_json)].into(),
    )?;
    for f in &res.program.features {
        let kind = match f.artifact.as_str() {
            "ring" => ArtifactKind::Ring,
            "sphere" => ArtifactKind::Sphere,
            "straightedge" => ArtifactKind::Straightedge,
            _ => ArtifactKind::Part,
        };
        let mut art = Artifact::new(kind);
        if f.nominal_diameter_mm > 0.0 {
            art.diameter_mm = Some(f.nominal_diameter_mm);
        }
        art.certificate_mm = f.certificate_diameter_mm;
        art.center_x_mm = Some(f.nominal_center[0]);
        art.center_y_mm = Some(f.nominal_center[1]);
        art.center_z_mm = Some(f.nominal_center[2]);
        art.extra.insert("feature_id".into(), f.id.to_string());
        art.extra.insert(
            "feature_kind".into(),
            serde_json::to_value(f.kind)?
                .as_str()
                .unwrap_or("")
                .to_string(),
        );
        w.write_artifact(&art)?;
    }
    w.finish()
        .with_context(|| format!("finishing {}", a.out.display()))?;
    if let Some(t) = &truth_out {
        t.write_all(serde_json::to_string_pretty(&res.truth)?)?;
    }
    if let Some(c) = &calib_out {
        c.write_all(res.start_calibration.to_json())?;
    }
    if let Some(d) = &datasheet_out {
        let sheet = scancorr_sim::data_sheet(&res.truth.machine, &machine, 1.0 / o.rate_hz);
        d.write_all(sheet.to_json())?;
    }
    if let Some(c) = &catalogue_out {
        c.write_all(scancorr_sim::stylus_catalogue().to_json())?;
    }
    let secs = t_start.elapsed().as_secs_f64();
    let total: u64 = res.counts.iter().sum();
    let mut json = None;
    if a.json {
        json = Some(serde_json::json!({
                "out": a.out,
                "machine": machine,
                "program": o.program,
                "samples": {"command": res.counts[0], "scale": res.counts[1], "probe": res.counts[2], "temperature": res.counts[3]},
                "duration_s": res.counts[1] as f64 / o.rate_hz,
                "noise_floor_um": res.truth.noise_floor_um,
                "hidden": o.hide,
                "no_arcs": o.no_arcs,
                "faults": res.truth.faults,
        }));
    } else if report {
        eprintln!(
            "simulated {} on machine {} (machine seed {}, seed {}): {:.1} s of scanning, {total} samples → {} in {secs:.1} s",
            o.program,
            machine,
            o.machine_seed,
            o.seed,
            res.counts[1] as f64 / o.rate_hz,
            a.out.display()
        );
        if o.no_arcs {
            eprintln!("  circles streamed as points (commands without arc centre and radius)");
        }
        if !o.hide.is_empty() {
            eprintln!(
                "  hidden from the starting calibration: {}",
                o.hide.join(", ")
            );
        }
        for f in &res.truth.faults {
            eprintln!(
                "  fault {:?} at {:.3} s",
                f.fault,
                f.onset_t_ns as f64 * 1e-9
            );
        }
    }
    Ok(Written {
        bag: bag_out,
        truth: truth_out,
        calib: calib_out,
        datasheet: datasheet_out,
        catalogue: catalogue_out,
        json,
    })
}
