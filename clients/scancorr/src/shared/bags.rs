//! Bags in, the core, bags out: the offline path shared by `correct`, the lab and the tests.

use anyhow::{bail, Context, Result};
use scancorr_bag::{BagHeader, BagReader, BagWriter, Stream};
use scancorr_core::lab::dataset::BagData;
use scancorr_core::lab::program::ProgramSpec;
use scancorr_core::wire;
use scancorr_core::{Calibration, Corrector, Output, Sample, Stats};
use std::collections::BTreeMap;
use std::path::{Path, PathBuf};

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

/// One `CorrectedPointBatch` message of the output (when it has points) and the alarms raised
/// with it, as the corrector produced them.
#[derive(Default)]
struct Batch {
    points: Vec<scancorr_core::CorrectedPoint>,
    alarms: Vec<scancorr_core::Alarm>,
    log_time: u64,
}

/// Points (and alarms) handed over per wake-up of the writer thread: batches go over in
/// bundles, so the corrector does not pay a thread wake-up per 100-point message.
const BUNDLE_POINTS: usize = 2048;

/// Bundles queued for the writer before the corrector waits for it.
const BUNDLES_QUEUED: usize = 8;

/// The corrector's side of the writer thread: batches are queued in order, handed over in
/// bundles, written by `write` on the writer thread in the same order, and come back with their
/// points so the next batches reuse their lists (no allocation per point, no freeing on the
/// other thread).
struct Pipe<W> {
    tx: Option<std::sync::mpsc::SyncSender<Vec<Batch>>>,
    back: std::sync::mpsc::Receiver<Vec<Batch>>,
    bundle: Vec<Batch>,
    bundle_points: usize,
    spare: Vec<Batch>,
    thread: std::thread::JoinHandle<Result<W>>,
}

impl<W: Send + 'static> Pipe<W> {
    /// Starts the writer thread: it calls `write` for each batch, in order, and stops at its
    /// first error (returned by [`Pipe::finish`]).
    fn spawn(
        mut sink: W,
        mut write: impl FnMut(&mut W, &Batch) -> Result<()> + Send + 'static,
    ) -> Result<Pipe<W>> {
        let (tx, rx) = std::sync::mpsc::sync_channel::<Vec<Batch>>(BUNDLES_QUEUED);
        let (back_tx, back) = std::sync::mpsc::channel::<Vec<Batch>>();
        let thread = std::thread::Builder::new()
            .name("correct-writer".into())
            .spawn(move || -> Result<W> {
                for bundle in rx {
                    for b in &bundle {
                        write(&mut sink, b)?;
                    }
                    // The corrector may be gone already (it failed): nothing to hand back then.
                    let _ = back_tx.send(bundle);
                }
                Ok(sink)
            })
            .context("starting the writer thread")?;
        Ok(Pipe {
            tx: Some(tx),
            back,
            bundle: Vec::new(),
            bundle_points: 0,
            spare: Vec::new(),
            thread,
        })
    }

    /// Queues `output`'s points and alarms as one batch and clears `output`. False when the
    /// writer thread has stopped (on an error, which [`Pipe::finish`] returns): stop feeding it.
    fn push(&mut self, output: &mut Output, log_time: u64) -> bool {
        if output.points.is_empty() && output.alarms.is_empty() {
            output.clear();
            return true;
        }
        if self.spare.is_empty() {
            while let Ok(mut bundle) = self.back.try_recv() {
                self.spare.append(&mut bundle);
            }
        }
        let mut b = self.spare.pop().unwrap_or_default();
        std::mem::swap(&mut b.points, &mut output.points);
        std::mem::swap(&mut b.alarms, &mut output.alarms);
        b.log_time = log_time;
        // `output` now holds the written batch's points: clearing keeps their lists of
        // corrections for the next points.
        output.clear();
        self.bundle_points += b.points.len() + b.alarms.len();
        self.bundle.push(b);
        if self.bundle_points >= BUNDLE_POINTS {
            self.send()
        } else {
            true
        }
    }

    fn send(&mut self) -> bool {
        self.bundle_points = 0;
        if self.bundle.is_empty() {
            return true;
        }
        let bundle = std::mem::take(&mut self.bundle);
        match &self.tx {
            Some(tx) => tx.send(bundle).is_ok(),
            None => false,
        }
    }

    /// Hands over what is queued, waits for the writer thread and returns its sink, or its
    /// first error.
    fn finish(mut self) -> Result<W> {
        self.send();
        drop(self.tx.take());
        self.thread
            .join()
            .map_err(|_| anyhow::anyhow!("the writer thread panicked"))?
    }
}

/// `scancorr correct`: streams a bag through the core and writes points and alarms to `out`
/// (a temporary file renamed when complete; `out` may not be the input bag).
/// Reading, decoding and correcting run on this thread; encoding and writing on another.
pub fn correct(
    bag: &Path,
    cal: &Calibration,
    out: Option<&Path>,
) -> Result<(Summary, Vec<String>)> {
    correct_with(bag, cal, out, false)
}

/// [`correct`], with the Foxglove channels (`shared::foxglove`) beside ours when `foxglove`.
pub fn correct_with(
    bag: &Path,
    cal: &Calibration,
    out: Option<&Path>,
    foxglove: bool,
) -> Result<(Summary, Vec<String>)> {
    let t0 = std::time::Instant::now();
    if let Some(o) = out {
        crate::shared::output::refuse_same_file(&[("--out", o)], &[("--bag", bag)])?;
    }
    let out_file = out
        .map(|p| crate::shared::output::AtomicOutput::new("--out", p))
        .transpose()?;
    let (reader, machine, mut warnings) = open(bag, Some(&cal.machine_id)).map_err(|e| {
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
            BagWriter::from_file(
                f.file()?,
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
    let mut fox = match foxglove && writer.is_some() {
        true => {
            let records = reader.metadata().iter();
            let records = records.map(|m| (m.name.as_str(), &m.entries));
            let nominal =
                crate::shared::foxglove::Nominal::from_metadata(records).unwrap_or_else(|e| {
                    warnings.push(format!("{}: {e:#}: no deviations", bag.display()));
                    None
                });
            let s = crate::shared::foxglove::BagSink::new(&prefix, &machine, nominal);
            Some(s)
        }
        false => None,
    };
    let mut pipe = match writer {
        Some(w) => {
            let (machine, prefix, ids) = (machine.clone(), prefix.clone(), ids.clone());
            let mut bytes = vec![];
            Some(Pipe::spawn(w, move |w: &mut BagWriter, b: &Batch| {
                if let Some(f) = &mut fox {
                    f.write(w, b.log_time, &b.points, &b.alarms)?;
                }
                if let Some(first) = b.points.first() {
                    // The service's encoder: a `CorrectedPointBatch`'s bytes without building
                    // a message per point.
                    bytes.clear();
                    wire::encode_points(&b.points, &machine, &ids, &mut bytes);
                    let publish = first.t_ns.max(0) as u64;
                    w.write(
                        Stream::Points,
                        &machine,
                        &prefix,
                        b.log_time,
                        publish,
                        &bytes,
                    )?;
                }
                for a in &b.alarms {
                    w.write_msg(&machine, &prefix, b.log_time, &wire::alarm(a, &machine))?;
                }
                Ok(())
            })?)
        }
        None => None,
    };
    let mut output = Output::default();
    let (mut bad, mut foreign) = (0u64, 0u64);
    let mut samples = Vec::with_capacity(128);
    // False once the writer thread has stopped on an error: reading on would be wasted, and
    // its error is returned at the join.
    let mut send = |output: &mut Output, log_time: u64| match &mut pipe {
        Some(p) => p.push(output, log_time),
        None => {
            output.clear();
            true
        }
    };
    let mut last_log = 0;
    let mut writer_failed = false;
    let total = reader.message_count().max(1);
    let mut progress = crate::shared::output::Progress::new();
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
        if (output.points.len() >= 100 || !output.alarms.is_empty())
            && !send(&mut output, msg.log_time)
        {
            writer_failed = true;
            break;
        }
    }
    if !writer_failed {
        corr.flush(&mut output);
        send(&mut output, last_log);
    }
    progress.finish();

    if let Some(p) = pipe {
        let mut w = p.finish()?;
        // The writer thread stops only on an error, which `finish` returns.
        anyhow::ensure!(!writer_failed, "the writer thread stopped early");
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

#[cfg(test)]
mod tests {
    use super::*;
    use scancorr_core::{CorrectedPoint, Vec3};

    /// What the test writer saw: each batch's log time and its points' (seq, correction).
    type Seen = Vec<(u64, Vec<(u64, f64)>)>;

    fn point(seq: u64) -> CorrectedPoint {
        CorrectedPoint {
            seq,
            t_ns: seq as i64,
            sample_seq: seq,
            surface: Vec3::new(seq as f64, 0.0, 0.0),
            tip_center: Vec3::zeros(),
            normal: Vec3::zeros(),
            corrections: vec![Vec3::new(0.0, seq as f64, 0.0)],
            calibration_version: 1,
            estimator_valid: true,
            segment_id: 0,
            tip_id: 0,
        }
    }

    /// Feeds `batches` batches of `size(k)` points through a pipe whose writer records
    /// (log time, seqs and corrections of each batch); stops feeding when the pipe says so.
    fn feed(pipe: &mut Pipe<Seen>, batches: u64, size: impl Fn(u64) -> u64) -> u64 {
        let mut output = Output::default();
        let mut seq = 0;
        for k in 0..batches {
            for _ in 0..size(k) {
                output.points.push(point(seq));
                seq += 1;
            }
            if !pipe.push(&mut output, k) {
                return k;
            }
            assert!(output.points.is_empty());
        }
        batches
    }

    fn recorder() -> impl FnMut(&mut Seen, &Batch) -> Result<()> + Send + 'static {
        |seen, b| {
            let points = b.points.iter().map(|p| (p.seq, p.corrections[0].y));
            seen.push((b.log_time, points.collect()));
            Ok(())
        }
    }

    #[test]
    fn the_writer_gets_every_batch_in_order_with_its_points() {
        let mut pipe = Pipe::spawn(vec![], recorder()).unwrap();
        // Sizes around the bundle size, empty batches (skipped) among them.
        let size = |k: u64| (k * 37) % 250;
        let n = 2000;
        assert_eq!(feed(&mut pipe, n, size), n);
        let seen = pipe.finish().unwrap();
        let want: Vec<u64> = (0..n).filter(|&k| size(k) > 0).collect();
        assert_eq!(seen.iter().map(|b| b.0).collect::<Vec<_>>(), want);
        let mut seq = 0;
        for (k, points) in &seen {
            assert_eq!(points.len() as u64, size(*k), "batch {k}");
            for &(s, c) in points {
                // Reused lists of corrections carry this point's value, not a stale one.
                assert_eq!((s, c), (seq, seq as f64));
                seq += 1;
            }
        }
    }

    #[test]
    fn alarms_alone_make_a_batch() {
        let mut pipe = Pipe::spawn(vec![], |seen: &mut Vec<(u64, usize)>, b: &Batch| {
            seen.push((b.log_time, b.alarms.len()));
            Ok(())
        })
        .unwrap();
        let mut output = Output::default();
        output.alarms.push(scancorr_core::Alarm {
            seq: 0,
            t_ns: 5,
            raised: true,
            axis: scancorr_core::Axis::X,
            estimated_accel: 1.0,
            measured_accel: 0.0,
            difference: 1.0,
            threshold: 0.5,
            action: scancorr_core::AlarmAction::Flag,
            calibration_version: 1,
        });
        assert!(pipe.push(&mut output, 7));
        assert!(output.alarms.is_empty());
        assert_eq!(pipe.finish().unwrap(), vec![(7, 1)]);
    }

    #[test]
    fn a_writer_error_stops_the_feed_and_is_returned() {
        let mut pipe = Pipe::spawn(vec![], |seen: &mut Vec<u64>, b: &Batch| {
            if b.log_time == 300 {
                anyhow::bail!("disk full at batch {}", b.log_time);
            }
            seen.push(b.log_time);
            Ok(())
        })
        .unwrap();
        let n = 100_000;
        let stopped = {
            let mut output = Output::default();
            let mut k = 0;
            while k < n {
                for s in 0..100 {
                    output.points.push(point(k * 100 + s));
                }
                if !pipe.push(&mut output, k) {
                    break;
                }
                k += 1;
            }
            k
        };
        // The feed stops soon after the failure (the queue is bounded).
        assert!(stopped < 300 + 100 * BUNDLES_QUEUED as u64, "{stopped}");
        let e = pipe.finish().unwrap_err();
        assert!(format!("{e:#}").contains("disk full at batch 300"), "{e:#}");
    }
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
        let input = read_lazy(p, Some(machine))?;
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
