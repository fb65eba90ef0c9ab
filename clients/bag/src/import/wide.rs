//! A bag's raw streams of one machine as one wide table (`scancorr export --raw`): integer
//! `t_ns`, one row per distinct time, each stream's columns — every command field with the arc
//! and the segment id, the scale, the probe with its tip and head angles, one column per
//! temperature sensor, a reading and a spacing column per distance probe, the micro-stage —
//! empty where a stream has no sample at that time; values printed as Rust's shortest
//! round-trip form, so they parse back to the identical f64. With it comes the [`Mapping`]
//! that reads it back (`scancorr import --map`).
//!
//! The bag is read twice: once to find the streams, sensors and probes and to check that a
//! table can hold them (each stream in time order, one sample per sensor, probe or stream at
//! a time, every value finite, sensor names in the project's grammar) — so a refusal comes
//! before anything is written — then once per stream side by side, merged by time, one batch
//! per stream in memory. Samples that name another machine and batches that do not decode are
//! skipped and counted (as `scancorr correct` does).
use super::{
    stream_name, CommandMap, DistanceColumns, DistanceMap, DistanceProbe, LengthUnit, Mapping,
    ProbeMap, Sample, ScaleMap, Source, StageMap, TemperatureMap, TemperatureUnit, TimeColumn,
    TimeUnit, STREAMS,
};
use crate::{BagError, BagMessage, BagReader, Messages, RawBatch, Stream};
use scancorr_proto::names;
use scancorr_proto::v1::{CommandSample, ProbeSample, ScaleSample, TemperatureSample};
use std::collections::{BTreeMap, HashMap, VecDeque};
use std::fmt::Write as _;
use std::io::Write;

/// What [`export_wide`] wrote.
#[derive(Debug, Clone, PartialEq)]
pub struct WideExport {
    /// The mapping that reads the table back.
    pub mapping: Mapping,
    /// The header's columns.
    pub columns: Vec<String>,
    /// Rows written (distinct times).
    pub rows: u64,
    /// Samples per raw stream written (`command`, …).
    pub samples: BTreeMap<String, u64>,
    /// First and last time, ns.
    pub first_t_ns: Option<i64>,
    /// See `first_t_ns`.
    pub last_t_ns: Option<i64>,
    /// Temperature sensors, in the order they first appear (the columns' order).
    pub sensors: Vec<String>,
    /// Distance probe ids, in the order they first appear.
    pub distance_probes: Vec<u32>,
    /// Batches that did not decode (skipped).
    pub bad_batches: u64,
    /// The first of their errors.
    pub first_bad_batch: Option<String>,
    /// Samples inside the machine's batches that name another machine (skipped).
    pub foreign_samples: u64,
}

/// Why a bag cannot be exported as a wide table.
#[derive(Debug, thiserror::Error)]
#[non_exhaustive]
pub enum WideError {
    /// Reading the bag failed.
    #[error(transparent)]
    Bag(#[from] BagError),
    /// Writing the table failed.
    #[error("writing the table: {0}")]
    Write(#[from] std::io::Error),
    /// The bag holds something a wide table cannot hold faithfully.
    #[error("{0}")]
    Unrepresentable(String),
    /// No raw sample of the machine.
    #[error("no raw sample of machine {0} in the bag")]
    Empty(String),
}

/// Decodes one message of `machine` into its samples; batches that do not decode (or whose
/// packed columns have unequal lengths) are an error, samples of other machines are counted.
fn decode(msg: &BagMessage, machine: &str, out: &mut Vec<Sample>) -> Result<u64, String> {
    let batch = msg.decode_checked().map_err(|e| e.to_string())?;
    let malformed = || {
        format!(
            "a packed batch on {} at log time {} with columns of unequal lengths",
            msg.topic, msg.log_time
        )
    };
    let start = out.len();
    // The columns of a packed batch (v1.3) as samples, each field its column's value.
    macro_rules! unpack {
        ($batch:expr, $variant:ident, $ty:ident, [$($f:ident),*] $(, optional $opt:ident)*) => {{
            let b = $batch;
            if b.columns.is_some() && !b.samples.is_empty() {
                return Err(format!(
                    "a batch on {} at log time {} with both samples and columns",
                    msg.topic, msg.log_time
                ));
            }
            out.extend(b.samples.into_iter().map(Sample::$variant));
            if let Some(c) = b.columns {
                let n = c.seq.len();
                if [$(c.$f.len()),*].iter().any(|&l| l != n) {
                    return Err(malformed());
                }
                // Optional columns (v1.5's force): empty, or one value per sample.
                $(if !c.$opt.is_empty() && c.$opt.len() != n {
                    return Err(malformed());
                })*
                for i in 0..n {
                    out.push(Sample::$variant($ty {
                        machine_id: c.machine_id.clone(),
                        seq: c.seq[i],
                        $($f: Clone::clone(&c.$f[i]),)*
                        $($opt: c.$opt.get(i).copied(),)*
                    }));
                }
            }
        }};
    }
    match batch {
        RawBatch::Command(b) => unpack!(
            b,
            Command,
            CommandSample,
            [t_ns, x, y, z, arc_cx, arc_cy, arc_cz, arc_radius, segment_id]
        ),
        RawBatch::Scale(b) => unpack!(b, Scale, ScaleSample, [t_ns, x, y, z]),
        RawBatch::Probe(b) => unpack!(
            b,
            Probe,
            ProbeSample,
            [t_ns, u, v, w, tip_id, head_a1_deg, head_a2_deg],
            optional force_n
        ),
        RawBatch::Temperature(b) => {
            unpack!(b, Temperature, TemperatureSample, [t_ns, sensor, celsius])
        }
        RawBatch::Distance(b) => out.extend(b.samples.into_iter().map(Sample::Distance)),
        RawBatch::Stage(b) => out.extend(b.samples.into_iter().map(Sample::Stage)),
        RawBatch::Points(_) | RawBatch::Alarm(_) => {}
    }
    // Keep this machine's samples, in order.
    let mut kept = start;
    for i in start..out.len() {
        if out[i].machine_id() == machine {
            out.swap(kept, i);
            kept += 1;
        }
    }
    let foreign = (out.len() - kept) as u64;
    out.truncate(kept);
    Ok(foreign)
}

/// The float fields of a sample, named (to check them finite).
fn floats(s: &Sample) -> Vec<(&'static str, f64)> {
    match s {
        Sample::Command(c) => vec![
            ("x", c.x),
            ("y", c.y),
            ("z", c.z),
            ("arc_cx", c.arc_cx),
            ("arc_cy", c.arc_cy),
            ("arc_cz", c.arc_cz),
            ("arc_radius", c.arc_radius),
        ],
        Sample::Scale(c) => vec![("x", c.x), ("y", c.y), ("z", c.z)],
        Sample::Probe(c) => vec![
            ("u", c.u),
            ("v", c.v),
            ("w", c.w),
            ("head_a1_deg", c.head_a1_deg),
            ("head_a2_deg", c.head_a2_deg),
        ],
        Sample::Temperature(c) => vec![("celsius", c.celsius)],
        Sample::Distance(c) => vec![("distance_mm", c.distance_mm), ("spacing_mm", c.spacing_mm)],
        Sample::Stage(c) => vec![("commanded_mm", c.commanded_mm), ("sensor_mm", c.sensor_mm)],
    }
}

/// The group a sample's time order is kept in: its stream, or its sensor or probe.
#[derive(Debug, Clone, PartialEq, Eq, Hash)]
enum Key {
    Stream(usize),
    Sensor(String),
    Probe(u32),
}

fn key(s: &Sample) -> Key {
    match s {
        Sample::Temperature(t) => Key::Sensor(t.sensor.clone()),
        Sample::Distance(d) => Key::Probe(d.probe_id),
        other => Key::Stream(super::stream_index(other.stream())),
    }
}

/// One stream read on its own, in order.
struct Cursor<'a> {
    stream: Stream,
    messages: Messages<'a>,
    queue: VecDeque<Sample>,
    scratch: Vec<Sample>,
}

impl Cursor<'_> {
    fn head_t(&mut self, machine: &str) -> Result<Option<i64>, BagError> {
        while self.queue.is_empty() {
            let Some(m) = self.messages.next() else {
                return Ok(None);
            };
            let m = m?;
            if m.stream != self.stream || &*m.machine != machine {
                continue;
            }
            self.scratch.clear();
            if decode(&m, machine, &mut self.scratch).is_ok() {
                self.queue.extend(self.scratch.drain(..));
            }
        }
        Ok(self.queue.front().map(Sample::t_ns))
    }
}

/// Where each stream's columns start.
#[derive(Default)]
struct Layout {
    columns: Vec<String>,
    command: usize,
    scale: usize,
    probe: usize,
    stage: usize,
    sensors: HashMap<String, usize>,
    probes: HashMap<u32, usize>,
}

impl Layout {
    fn add(&mut self, names: &[&str]) -> usize {
        let at = self.columns.len();
        self.columns.extend(names.iter().map(|s| s.to_string()));
        at
    }
}

fn col(s: &str) -> Option<Source> {
    Some(Source::Column(s.to_string()))
}

/// Writes the raw streams of `machine` in `bag` to `out` as one wide comma-separated table
/// (see the module's documentation) and returns the mapping that reads it back.
pub fn export_wide(
    bag: &BagReader,
    machine: &str,
    out: &mut dyn Write,
) -> Result<WideExport, WideError> {
    // First pass: what is there, and can a table hold it?
    let mut present = [false; STREAMS.len()];
    let mut counts = [0u64; STREAMS.len()];
    let mut sensors: Vec<String> = vec![];
    let mut probes: Vec<u32> = vec![];
    let mut last: HashMap<Key, (i64, u64)> = HashMap::new();
    let mut stream_last: [Option<(i64, u64)>; STREAMS.len()] = [None; STREAMS.len()];
    let (mut bad_batches, mut first_bad_batch, mut foreign) = (0u64, None, 0u64);
    let mut batch = vec![];
    for m in bag.messages()? {
        let m = m?;
        if &*m.machine != machine || !STREAMS.contains(&m.stream) {
            continue;
        }
        batch.clear();
        match decode(&m, machine, &mut batch) {
            Ok(f) => foreign += f,
            Err(e) => {
                bad_batches += 1;
                first_bad_batch.get_or_insert(e);
                continue;
            }
        }
        for s in &batch {
            let si = super::stream_index(s.stream());
            let what = || {
                format!(
                    "{} sample seq {} (t_ns {})",
                    s.stream().key(bag.prefix(), machine),
                    s.seq(),
                    s.t_ns()
                )
            };
            for (field, v) in floats(s) {
                if !v.is_finite() {
                    return Err(WideError::Unrepresentable(format!(
                        "{}: {field} is {v}, not a finite number (an import refuses it)",
                        what()
                    )));
                }
            }
            match s {
                Sample::Probe(p) if p.force_n.is_some() => {
                    return Err(WideError::Unrepresentable(format!(
                        "{}: a probing force (force_n, wire v1.5), which a wide table has no column for",
                        what()
                    )));
                }
                Sample::Temperature(t) if !sensors.contains(&t.sensor) => {
                    names::check("sensor name", &t.sensor)
                        .map_err(|e| WideError::Unrepresentable(format!("{}: {e}", what())))?;
                    sensors.push(t.sensor.clone());
                }
                Sample::Distance(d) if !probes.contains(&d.probe_id) => probes.push(d.probe_id),
                _ => {}
            }
            let k = key(s);
            let t = s.t_ns();
            if let Some(&(prev, prev_seq)) = last.get(&k) {
                if t <= prev {
                    let of = match &k {
                        Key::Sensor(n) => format!(" of sensor {n}"),
                        Key::Probe(p) => format!(" of probe {p}"),
                        Key::Stream(_) => String::new(),
                    };
                    return Err(WideError::Unrepresentable(format!(
                        "{}: not after the previous sample{of} (seq {prev_seq}, t_ns {prev}): a wide table holds each stream in time order with one sample{of} per time",
                        what()
                    )));
                }
            }
            if let Some((prev, prev_seq)) = stream_last[si] {
                if t < prev {
                    return Err(WideError::Unrepresentable(format!(
                        "{}: before the stream's previous sample (seq {prev_seq}, t_ns {prev}): a wide table holds each stream in time order",
                        what()
                    )));
                }
            }
            last.insert(k, (t, s.seq()));
            stream_last[si] = Some((t, s.seq()));
            present[si] = true;
            counts[si] += 1;
        }
    }
    if !present.iter().any(|p| *p) {
        return Err(WideError::Empty(machine.to_string()));
    }

    // The columns and the mapping.
    let mut lay = Layout::default();
    lay.add(&["t_ns"]);
    let mut mapping = Mapping {
        machine: Some(machine.to_string()),
        time: Some(TimeColumn {
            column: "t_ns".into(),
            unit: TimeUnit::Ns,
            offset_ns: 0,
        }),
        ..Default::default()
    };
    let has = |s: Stream| present[super::stream_index(s)];
    if has(Stream::Command) {
        let names = [
            "command_x_mm",
            "command_y_mm",
            "command_z_mm",
            "command_arc_cx_mm",
            "command_arc_cy_mm",
            "command_arc_cz_mm",
            "command_arc_radius_mm",
            "command_segment_id",
        ];
        lay.command = lay.add(&names);
        mapping.command = Some(CommandMap {
            unit: LengthUnit::Mm,
            x: col(names[0]),
            y: col(names[1]),
            z: col(names[2]),
            arc_cx: col(names[3]),
            arc_cy: col(names[4]),
            arc_cz: col(names[5]),
            arc_radius: col(names[6]),
            segment_id: col(names[7]),
            max_gap_s: None,
        });
    }
    if has(Stream::Scale) {
        let names = ["scale_x_mm", "scale_y_mm", "scale_z_mm"];
        lay.scale = lay.add(&names);
        mapping.scale = Some(ScaleMap {
            unit: LengthUnit::Mm,
            x: col(names[0]),
            y: col(names[1]),
            z: col(names[2]),
            max_gap_s: None,
        });
    }
    if has(Stream::Probe) {
        let names = [
            "probe_u_mm",
            "probe_v_mm",
            "probe_w_mm",
            "probe_tip_id",
            "probe_head_a1_deg",
            "probe_head_a2_deg",
        ];
        lay.probe = lay.add(&names);
        mapping.probe = Some(ProbeMap {
            unit: LengthUnit::Mm,
            u: col(names[0]),
            v: col(names[1]),
            w: col(names[2]),
            tip_id: col(names[3]),
            head_a1_deg: col(names[4]),
            head_a2_deg: col(names[5]),
            max_gap_s: None,
        });
    }
    if has(Stream::Temperature) {
        let mut map = TemperatureMap {
            unit: TemperatureUnit::C,
            ..Default::default()
        };
        for s in &sensors {
            let name = format!("temperature_{s}_C");
            let at = lay.add(&[name.as_str()]);
            lay.sensors.insert(s.clone(), at);
            map.sensors.insert(s.clone(), name);
        }
        mapping.temperature = Some(map);
    }
    if has(Stream::Distance) {
        let mut map = DistanceMap::default();
        for p in &probes {
            let (reading, spacing) = (
                format!("distance_{p}_mm"),
                format!("distance_{p}_spacing_mm"),
            );
            let at = lay.add(&[reading.as_str(), spacing.as_str()]);
            lay.probes.insert(*p, at);
            map.probes.insert(
                *p,
                DistanceProbe::With(DistanceColumns {
                    column: reading,
                    spacing: Some(Source::Column(spacing)),
                }),
            );
        }
        mapping.distance = Some(map);
    }
    if has(Stream::Stage) {
        let names = ["stage_commanded_mm", "stage_sensor_mm", "stage_probe_id"];
        lay.stage = lay.add(&names);
        mapping.stage = Some(StageMap {
            unit: LengthUnit::Mm,
            commanded: col(names[0]),
            sensor: col(names[1]),
            probe_id: col(names[2]),
            max_gap_s: None,
        });
    }

    // Second pass: the streams side by side, merged by time.
    let mut cursors = vec![];
    for (i, s) in STREAMS.iter().enumerate() {
        if present[i] {
            cursors.push(Cursor {
                stream: *s,
                messages: bag.messages()?,
                queue: VecDeque::new(),
                scratch: vec![],
            });
        }
    }
    let mut w = std::io::BufWriter::with_capacity(256 * 1024, out);
    writeln!(w, "{}", lay.columns.join(","))?;
    let mut cells: Vec<String> = vec![String::new(); lay.columns.len()];
    let mut line = String::new();
    let (mut rows, mut first, mut last_t) = (0u64, None, None);
    loop {
        let mut t: Option<i64> = None;
        for c in &mut cursors {
            if let Some(h) = c.head_t(machine)? {
                t = Some(t.map_or(h, |t: i64| t.min(h)));
            }
        }
        let Some(t) = t else { break };
        for c in &mut cells {
            c.clear();
        }
        let _ = write!(cells[0], "{t}");
        for c in &mut cursors {
            while c.head_t(machine)? == Some(t) {
                let Some(s) = c.queue.pop_front() else { break };
                fill(&lay, &s, &mut cells);
            }
        }
        line.clear();
        for (i, c) in cells.iter().enumerate() {
            if i > 0 {
                line.push(',');
            }
            line.push_str(c);
        }
        writeln!(w, "{line}")?;
        rows += 1;
        first.get_or_insert(t);
        last_t = Some(t);
    }
    w.flush()?;
    let samples = STREAMS
        .iter()
        .enumerate()
        .filter(|(i, _)| present[*i])
        .map(|(i, s)| (stream_name(*s).to_string(), counts[i]))
        .collect();
    Ok(WideExport {
        mapping,
        columns: lay.columns,
        rows,
        samples,
        first_t_ns: first,
        last_t_ns: last_t,
        sensors,
        distance_probes: probes,
        bad_batches,
        first_bad_batch,
        foreign_samples: foreign,
    })
}

/// Prints a sample's fields into its columns' cells.
fn fill(lay: &Layout, s: &Sample, cells: &mut [String]) {
    let mut put = |at: usize, vals: &[&dyn std::fmt::Display]| {
        for (k, v) in vals.iter().enumerate() {
            let _ = write!(cells[at + k], "{v}");
        }
    };
    match s {
        Sample::Command(c) => put(
            lay.command,
            &[
                &c.x,
                &c.y,
                &c.z,
                &c.arc_cx,
                &c.arc_cy,
                &c.arc_cz,
                &c.arc_radius,
                &c.segment_id,
            ],
        ),
        Sample::Scale(c) => put(lay.scale, &[&c.x, &c.y, &c.z]),
        Sample::Probe(c) => put(
            lay.probe,
            &[&c.u, &c.v, &c.w, &c.tip_id, &c.head_a1_deg, &c.head_a2_deg],
        ),
        Sample::Temperature(c) => {
            if let Some(&at) = lay.sensors.get(&c.sensor) {
                put(at, &[&c.celsius]);
            }
        }
        Sample::Distance(c) => {
            if let Some(&at) = lay.probes.get(&c.probe_id) {
                put(at, &[&c.distance_mm, &c.spacing_mm]);
            }
        }
        Sample::Stage(c) => put(lay.stage, &[&c.commanded_mm, &c.sensor_mm, &c.probe_id]),
    }
}
