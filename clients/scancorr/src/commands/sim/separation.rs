//! `scancorr sim --program straightness-…`: the error-separation measurements (distance
//! probes on the X carriage, a micro-stage) written to a bag with their truth. The physics is
//! `scancorr_sim::straightness`.

use crate::shared::output::AtomicOutput;
use anyhow::{bail, Context, Result};
use scancorr_bag::{BagHeader, BagWriter};
use scancorr_proto::v1::{
    DistanceBatch, DistanceSample, ScaleBatch, ScaleSample, StageBatch, StageSample, StreamKind,
};
use scancorr_sim::straightness::{self, Reading, SeparationOptions};
use std::collections::BTreeMap;
use std::path::PathBuf;

/// Arguments of a separation run.
pub struct SepArgs {
    pub options: SeparationOptions,
    pub machine: String,
    pub out: PathBuf,
    pub truth: Option<PathBuf>,
    /// The machine's data sheet and the stylus catalogue (as `sim` writes them for any
    /// program).
    pub datasheet_out: Option<PathBuf>,
    pub catalogue_out: Option<PathBuf>,
    pub batch: usize,
    pub prefix: String,
    pub json: bool,
}

/// Is `program` a separation program?
pub fn is_separation(program: &str) -> bool {
    straightness::PROGRAMS.contains(&program)
}

/// Flags of `scancorr sim` that a separation run does not take, refused by name.
pub fn refuse(flags: &[(&str, bool)], program: &str) -> Result<()> {
    let given: Vec<&str> = flags.iter().filter(|f| f.1).map(|f| f.0).collect();
    if !given.is_empty() {
        bail!(
            "{}: not for `{program}` (a straightness error-separation measurement: distance \
             probes on the X carriage; it takes --machine-seed, --seed, --rate, --effect \
             guide_straightness=F, --reversal, --lines N, --out, --truth, --datasheet-out, \
             --catalogue-out)",
            given.join(", ")
        );
    }
    Ok(())
}

/// Runs the measurement into `out` (and the truth), atomically.
pub fn run(a: SepArgs) -> Result<()> {
    check_args(&a)?;
    let bag_out = AtomicOutput::new("--out", &a.out)?;
    let truth_out = AtomicOutput::optional("--truth", a.truth.as_deref())?;
    let datasheet_out = AtomicOutput::optional("--datasheet-out", a.datasheet_out.as_deref())?;
    let catalogue_out = AtomicOutput::optional("--catalogue-out", a.catalogue_out.as_deref())?;
    let mut w = BagWriter::from_file(bag_out.file()?, bag_out.path(), BagHeader::default())
        .with_context(|| format!("creating {}", a.out.display()))?;
    let m = a.machine.clone();
    let latency_ns: i64 = 1_000_000;
    let log = |t: i64| (t + latency_ns).max(0) as u64;
    let mut scale = ScaleBatch {
        samples: vec![],
        stream: StreamKind::Scale as i32,
        columns: None,
    };
    let mut dist = DistanceBatch {
        samples: vec![],
        stream: StreamKind::Distance as i32,
    };
    let mut stage = StageBatch {
        samples: vec![],
        stream: StreamKind::Stage as i32,
    };
    let mut err: Option<anyhow::Error> = None;
    let counts = std::cell::Cell::new([0u64; 3]);
    let t_start = std::time::Instant::now();
    let truth = straightness::run(&a.options, |r| {
        if err.is_some() {
            return;
        }
        let mut c = counts.get();
        // Adds a sample to its batch, and writes the batch when it is full.
        macro_rules! put {
            ($batch:ident, $k:expr, $t:expr, $sample:expr) => {{
                c[$k] += 1;
                $batch.samples.push($sample);
                if $batch.samples.len() >= a.batch {
                    w.write_msg(&m, &a.prefix, log($t), &$batch)?;
                    $batch.samples.clear();
                }
            }};
        }
        let res = (|| -> Result<()> {
            match r {
                Reading::Scale { seq, t_ns, pos } => put!(
                    scale,
                    0,
                    t_ns,
                    ScaleSample {
                        machine_id: m.clone(),
                        seq,
                        t_ns,
                        x: pos[0],
                        y: pos[1],
                        z: pos[2],
                    }
                ),
                Reading::Distance {
                    seq,
                    t_ns,
                    probe_id,
                    distance_mm,
                    spacing_mm,
                } => put!(
                    dist,
                    1,
                    t_ns,
                    DistanceSample {
                        machine_id: m.clone(),
                        seq,
                        t_ns,
                        probe_id,
                        distance_mm,
                        spacing_mm,
                    }
                ),
                Reading::Stage {
                    seq,
                    t_ns,
                    probe_id,
                    commanded_mm,
                    sensor_mm,
                } => put!(
                    stage,
                    2,
                    t_ns,
                    StageSample {
                        machine_id: m.clone(),
                        seq,
                        t_ns,
                        commanded_mm,
                        sensor_mm,
                        probe_id,
                    }
                ),
            }
            Ok(())
        })();
        counts.set(c);
        if let Err(e) = res {
            err = Some(e);
        }
    })
    .map_err(anyhow::Error::msg)?;
    if let Some(e) = err {
        return Err(e.context(format!("writing {}", a.out.display())));
    }
    // What is left in the batches.
    macro_rules! rest {
        ($batch:ident) => {
            if let Some(t) = $batch.samples.last().map(|s| s.t_ns) {
                w.write_msg(&m, &a.prefix, log(t), &$batch)?;
            }
        };
    }
    rest!(scale);
    rest!(dist);
    rest!(stage);
    let o = &a.options;
    let run_meta = run_metadata(o, &m, &truth);
    w.write_metadata(scancorr_bag::RUN_METADATA, &run_meta)?;
    w.finish()
        .with_context(|| format!("finishing {}", a.out.display()))?;
    write_side_files([&truth_out, &datasheet_out, &catalogue_out], &truth, o, &m)?;
    crate::shared::output::commit_all([Some(bag_out), truth_out, datasheet_out, catalogue_out])?;
    report(&a, &truth, counts.get(), t_start)?;
    Ok(())
}

/// Refuses clashing outputs and checks the machine, the prefix and the batch size.
fn check_args(a: &SepArgs) -> Result<()> {
    let mut outs: Vec<(&str, &std::path::Path)> = vec![("--out", a.out.as_path())];
    if let Some(p) = &a.truth {
        outs.push(("--truth", p));
    }
    if let Some(p) = &a.datasheet_out {
        outs.push(("--datasheet-out", p));
    }
    if let Some(p) = &a.catalogue_out {
        outs.push(("--catalogue-out", p));
    }
    crate::shared::output::refuse_same_file(&outs, &[])?;
    crate::shared::output::check_machine("--machine", &a.machine)?;
    crate::shared::output::check_prefix(&a.prefix)?;
    anyhow::ensure!(a.batch >= 1, "--batch must be ≥ 1");
    Ok(())
}

/// The bag's run metadata.
fn run_metadata(
    o: &SeparationOptions,
    m: &str,
    truth: &straightness::SeparationTruth,
) -> BTreeMap<String, String> {
    [
        ("program", o.program.clone()),
        ("machine_id", m.to_string()),
        ("seed", o.seed.to_string()),
        ("machine_seed", o.machine_seed.to_string()),
        ("rate_hz", o.rate_hz.to_string()),
        ("reversal", o.reversal.to_string()),
        (
            "probe_resolution_mm",
            truth.instruments.probe_resolution_mm.to_string(),
        ),
        ("source", "scancorr sim".to_string()),
    ]
    .into_iter()
    .map(|(k, v)| (k.to_string(), v))
    .collect()
}

/// Reports the run: JSON on stdout, or a line on stderr. `c` counts the scale, distance and
/// stage samples.
fn report(
    a: &SepArgs,
    truth: &straightness::SeparationTruth,
    c: [u64; 3],
    t_start: std::time::Instant,
) -> Result<()> {
    let o = &a.options;
    let m = &a.machine;
    if a.json {
        outln!(
            "{}",
            serde_json::json!({
                "out": a.out,
                "machine": m,
                "program": o.program,
                "reversal": o.reversal,
                "samples": {"scale": c[0], "distance": c[1], "stage": c[2]},
                "stations": truth.stations_mm.len(),
                "probe_noise_mm": truth.probe_noise_mm,
            })
        )?;
    } else {
        eprintln!(
            "simulated {}{} on machine {} (machine seed {}, seed {}): {} stations, {} distance \
             and {} stage readings → {} in {:.1} s",
            o.program,
            if o.reversal { " (reversal)" } else { "" },
            m,
            o.machine_seed,
            o.seed,
            truth.stations_mm.len(),
            c[1],
            c[2],
            a.out.display(),
            t_start.elapsed().as_secs_f64()
        );
    }
    Ok(())
}

/// Writes the truth, the data sheet and the stylus catalogue into those of their outputs
/// that were asked for.
fn write_side_files(
    [truth_out, datasheet_out, catalogue_out]: [&Option<AtomicOutput>; 3],
    truth: &straightness::SeparationTruth,
    o: &SeparationOptions,
    m: &str,
) -> Result<()> {
    if let Some(t) = truth_out {
        t.write_all(serde_json::to_string_pretty(truth)?)?;
    }
    if let Some(d) = datasheet_out {
        let machine = scancorr_sim::machine::TrueMachine::from_seed(o.machine_seed);
        d.write_all(scancorr_sim::data_sheet(&machine, m, 1.0 / o.rate_hz).to_json())?;
    }
    if let Some(c) = catalogue_out {
        c.write_all(scancorr_sim::stylus_catalogue().to_json())?;
    }
    Ok(())
}
