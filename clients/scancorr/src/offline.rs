//! Bags in, the core, bags out: the offline path shared by `correct`, the lab and the tests.

use anyhow::{bail, Context, Result};
use scancorr_bag::{BagHeader, BagReader, BagWriter, Stream};
use scancorr_core::wire;
use scancorr_core::{Calibration, Corrector, Output, Sample, Stats};
use std::collections::BTreeMap;
use std::path::Path;

/// Opens a bag and checks it holds the raw streams of `machine` (or of its only machine).
pub fn open(path: &Path, machine: Option<&str>) -> Result<(BagReader, String, Vec<String>)> {
    let reader =
        BagReader::open(path).with_context(|| format!("reading bag {}", path.display()))?;
    let mut warnings = vec![];
    if let Some(t) = reader.truncation() {
        warnings.push(format!(
            "{}: the bag is cut short ({}); reading the {} of {} bytes that form complete chunks",
            path.display(),
            t.reason,
            t.readable_len,
            t.file_len
        ));
    }
    for u in reader.unknown_channels() {
        warnings.push(format!(
            "{}: skipping channel `{}` (not a scancorr stream)",
            path.display(),
            u.topic
        ));
    }
    let machines: Vec<String> = reader
        .machines()
        .into_iter()
        .map(|s| s.to_string())
        .collect();
    let machine = match machine {
        Some(m) => {
            if !machines.iter().any(|x| x == m) {
                bail!(
                    "{}: no streams of machine `{m}` in this bag (it holds: {})",
                    path.display(),
                    list(&machines)
                );
            }
            m.to_string()
        }
        None => match machines.as_slice() {
            [one] => one.clone(),
            [] => bail!("{}: the bag has no scancorr streams", path.display()),
            many => bail!(
                "{}: the bag holds several machines ({}); name one",
                path.display(),
                many.join(", ")
            ),
        },
    };
    for s in [Stream::Command, Stream::Scale, Stream::Probe] {
        if reader.channel(&machine, s).is_none() {
            bail!(
                "{}: missing channel `{}` for machine `{machine}`",
                path.display(),
                s.key(reader.prefix(), &machine)
            );
        }
    }
    Ok((reader, machine, warnings))
}

fn list(v: &[String]) -> String {
    if v.is_empty() {
        "none".into()
    } else {
        v.join(", ")
    }
}

/// A bag's samples of one machine, decoded again on each replay: the lab corrects a bag many
/// times (each step of `lab discover`), and a 30-minute capture decoded would take gigabytes.
pub struct BagSamples {
    reader: BagReader,
    machine: String,
    sensors: Vec<String>,
}

impl scancorr_core::lab::dataset::Samples for BagSamples {
    fn replay(&self, f: &mut dyn FnMut(Sample)) -> std::result::Result<(), String> {
        let mut batch = vec![];
        for msg in self.reader.messages().map_err(|e| format!("{e:#}"))? {
            let msg = msg.map_err(|e| format!("{e:#}"))?;
            if &*msg.machine != self.machine.as_str() {
                continue;
            }
            let Some(stream) = wire::stream_id(msg.stream) else {
                continue;
            };
            batch.clear();
            if wire::decode_machine(stream, &msg.data, &self.machine, &mut batch).is_ok() {
                for x in batch.drain(..) {
                    f(x);
                }
            }
        }
        Ok(())
    }
    fn sensors(&self) -> Vec<String> {
        self.sensors.clone()
    }
}

/// What a first pass over a bag found, and the replayable samples.
pub struct LazyBag {
    pub samples: BagSamples,
    pub metadata: Vec<(String, BTreeMap<String, String>)>,
    pub warnings: Vec<String>,
}

/// Opens a bag for the lab: one pass checks it (bad messages, samples of other machines,
/// temperature sensors); the samples are decoded again on each replay.
pub fn read_lazy(path: &Path, machine: Option<&str>) -> Result<LazyBag> {
    let (reader, machine, mut warnings) = open(path, machine)?;
    let metadata = reader
        .metadata()
        .iter()
        .map(|m| (m.name.clone(), m.entries.clone()))
        .collect();
    let (mut bad, mut foreign) = (0u64, 0u64);
    let mut sensors: Vec<String> = vec![];
    let mut batch = vec![];
    for msg in reader.messages()? {
        let msg = msg.with_context(|| format!("reading {}", path.display()))?;
        if &*msg.machine != machine.as_str() {
            continue;
        }
        let Some(stream) = wire::stream_id(msg.stream) else {
            continue;
        };
        batch.clear();
        match wire::decode_machine(stream, &msg.data, &machine, &mut batch) {
            Ok(f) => foreign += f,
            Err(_) => bad += 1,
        }
        for x in &batch {
            if let Sample::Temperature(t) = x {
                if !sensors.contains(&t.sensor) {
                    sensors.push(t.sensor.clone());
                }
            }
        }
    }
    if bad > 0 {
        warnings.push(format!(
            "{}: {bad} message(s) could not be decoded: skipped",
            path.display()
        ));
    }
    if foreign > 0 {
        warnings.push(format!(
            "{}: {foreign} sample(s) inside `{machine}`'s messages name another machine: skipped",
            path.display()
        ));
    }
    Ok(LazyBag {
        samples: BagSamples {
            reader,
            machine,
            sensors,
        },
        metadata,
        warnings,
    })
}

/// Summary of an offline correction.
#[derive(Debug, Clone, serde::Serialize)]
pub struct Summary {
    pub machine: String,
    pub calibration_version: u64,
    pub samples: u64,
    pub points: u64,
    pub points_flagged: u64,
    pub dropped: BTreeMap<String, u64>,
    pub alarms: u64,
    pub clock_resets: u64,
    pub bad_messages: u64,
    /// Points each effect contributed to, by effect id.
    pub effect_points: BTreeMap<String, u64>,
    /// Effects with parameters that contributed to no point: inactive for lack of a signal.
    pub inactive_effects: Vec<String>,
    pub seconds: f64,
    pub samples_per_s: f64,
}

fn summary(
    machine: &str,
    cal: &Calibration,
    corr: &scancorr_core::Corrector,
    bad: u64,
    foreign: u64,
    secs: f64,
) -> Summary {
    let st: &Stats = corr.stats();
    let mut dropped: BTreeMap<String, u64> = st
        .dropped_by_name()
        .into_iter()
        .map(|(k, v)| (k.to_string(), v))
        .collect();
    if foreign > 0 {
        dropped.insert("wrong_machine".into(), foreign);
    }
    Summary {
        machine: machine.to_string(),
        calibration_version: cal.version,
        samples: st.samples() + foreign,
        points: st.points_out,
        points_flagged: st.points_invalid,
        dropped,
        alarms: st.alarms_raised,
        clock_resets: st.clock_resets,
        bad_messages: bad,
        effect_points: corr
            .effect_ids()
            .into_iter()
            .zip(st.effect_points.iter().copied())
            .collect(),
        inactive_effects: corr.inactive_effects(),
        seconds: secs,
        samples_per_s: (st.samples() + foreign) as f64 / secs.max(1e-9),
    }
}

/// Loads and validates a calibration file.
pub fn load_calibration(path: &Path) -> Result<Calibration> {
    let text = std::fs::read_to_string(path)
        .with_context(|| format!("reading calibration {}", path.display()))?;
    let cal =
        Calibration::from_json(&text).with_context(|| format!("calibration {}", path.display()))?;
    cal.build()
        .with_context(|| format!("calibration {}", path.display()))?;
    Ok(cal)
}

/// What the corrector thread hands the writer thread.
enum ToWriter {
    Output {
        points: Vec<scancorr_core::CorrectedPoint>,
        alarms: Vec<scancorr_core::Alarm>,
        log_time: u64,
    },
}

/// `scancorr correct`: streams a bag through the core and writes points and alarms to `out`
/// (a temporary file renamed when complete; `out` may not be the input bag).
/// Reading, decoding and correcting run on this thread; encoding and writing on another.
pub fn correct(
    bag: &Path,
    cal: &Calibration,
    out: Option<&Path>,
) -> Result<(Summary, Vec<String>)> {
    let t0 = std::time::Instant::now();
    if let Some(o) = out {
        crate::output::refuse_same_file(&[("--out", o)], &[("--bag", bag)])?;
    }
    let out_file = out
        .map(|p| crate::output::AtomicOutput::new("--out", p))
        .transpose()?;
    let (reader, machine, warnings) = open(bag, Some(&cal.machine_id)).map_err(|e| {
        // Name the mismatch plainly when the bag is simply of another machine.
        match BagReader::open(bag) {
            Ok(r) if !r.machines().contains(&cal.machine_id.as_str()) => anyhow::anyhow!(
                "the calibration is for machine `{}`, but {} holds machine(s) {}",
                cal.machine_id,
                bag.display(),
                list(
                    &r.machines()
                        .iter()
                        .map(|s| s.to_string())
                        .collect::<Vec<_>>()
                )
            ),
            _ => e,
        }
    })?;
    let model = std::sync::Arc::new(cal.build()?);
    if !model.sensors.names().is_empty() && reader.channel(&machine, Stream::Temperature).is_none()
    {
        bail!(
            "{}: the calibration needs temperature sensors ({}) but the bag has no `{}` channel",
            bag.display(),
            model.sensors.names().join(", "),
            Stream::Temperature.key(reader.prefix(), &machine)
        );
    }
    let prefix = reader.prefix().to_string();
    let mut corr = Corrector::with_model(model);
    let ids = corr.effect_ids();
    // Corrected points are written at the corrector's pace: lz4 keeps up where zstd would be
    // the bottleneck.
    let writer = match &out_file {
        Some(f) => Some(
            BagWriter::create(
                f.path(),
                BagHeader {
                    compression: scancorr_bag::Compression::Lz4,
                    ..BagHeader::default()
                },
            )
            .with_context(|| format!("creating {}", f.shown().display()))?,
        ),
        None => None,
    };
    let (tx, rx) = std::sync::mpsc::sync_channel::<ToWriter>(256);
    let writer_thread = writer.map(|mut w| {
        let (machine, prefix, ids) = (machine.clone(), prefix.clone(), ids.clone());
        std::thread::spawn(move || -> Result<BagWriter> {
            let mut bytes = vec![];
            for msg in rx {
                let ToWriter::Output {
                    points,
                    alarms,
                    log_time,
                } = msg;
                if let Some(first) = points.first() {
                    // The service's encoder: a `CorrectedPointBatch`'s bytes without building
                    // a message per point.
                    bytes.clear();
                    wire::encode_points(&points, &machine, &ids, &mut bytes);
                    let publish = first.t_ns.max(0) as u64;
                    w.write(Stream::Points, &machine, &prefix, log_time, publish, &bytes)?;
                }
                for a in &alarms {
                    w.write_msg(&machine, &prefix, log_time, &wire::alarm(a, &machine))?;
                }
            }
            Ok(w)
        })
    });
    let mut output = Output::default();
    let (mut bad, mut foreign) = (0u64, 0u64);
    let mut samples = Vec::with_capacity(128);
    let send = |output: &mut Output, log_time: u64| {
        if writer_thread.is_some() && (!output.points.is_empty() || !output.alarms.is_empty()) {
            // A closed channel means the writer failed; its error is reported at the join.
            let _ = tx.send(ToWriter::Output {
                points: std::mem::take(&mut output.points),
                alarms: std::mem::take(&mut output.alarms),
                log_time,
            });
        }
        output.clear();
    };
    let mut last_log = 0;
    let total = reader.message_count().max(1);
    let mut progress = crate::output::Progress::new();
    for (k, msg) in reader.messages()?.enumerate() {
        let msg = msg.with_context(|| format!("reading {}", bag.display()))?;
        progress.tick(|| {
            format!(
                "correcting {}: {:.0} % of {total} messages, {:.1} s",
                bag.display(),
                100.0 * k as f64 / total as f64,
                t0.elapsed().as_secs_f64()
            )
        });
        if &*msg.machine != machine.as_str() {
            continue;
        }
        let Some(stream) = wire::stream_id(msg.stream) else {
            continue;
        };
        last_log = msg.log_time;
        samples.clear();
        match wire::decode_machine(stream, &msg.data, &machine, &mut samples) {
            Ok(f) => foreign += f,
            Err(_) => bad += 1,
        }
        for s in samples.drain(..) {
            corr.push(s, &mut output);
        }
        if output.points.len() >= 100 || !output.alarms.is_empty() {
            send(&mut output, msg.log_time);
        }
    }
    corr.flush(&mut output);
    send(&mut output, last_log);
    progress.finish();

    drop(tx);
    if let Some(h) = writer_thread {
        let mut w = h
            .join()
            .map_err(|_| anyhow::anyhow!("the writer thread panicked"))??;
        for m in reader.metadata() {
            if m.name == scancorr_bag::ARTIFACT_METADATA {
                if let Ok(a) = scancorr_bag::Artifact::from_metadata(&m.entries) {
                    w.write_artifact(&a)?;
                }
            } else {
                w.write_metadata(&m.name, &m.entries)?;
            }
        }
        w.write_metadata(
            "scancorr.correction",
            &[
                ("calibration_version".to_string(), cal.version.to_string()),
                ("source_bag".to_string(), bag.display().to_string()),
            ]
            .into(),
        )?;
        w.finish()?;
    }
    if let Some(f) = out_file {
        f.commit()?;
    }
    let secs = t0.elapsed().as_secs_f64();
    Ok((summary(&machine, cal, &corr, bad, foreign, secs), warnings))
}
