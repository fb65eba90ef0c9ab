//! A user's recorded data — CSV or whitespace columns from a controller's trace tool, a data
//! logger or CMM software — as samples of the wire contract, and the way back
//! ([`export_wide`]: a bag's raw streams as one wide table and the [`Mapping`] that reads it).
//!
//! The table has a header row of column names; `#` comment lines and blank lines are skipped
//! (see [`Delimiter`] for the cells). A [`Mapping`] names the time column and its unit (stored
//! as integer `t_ns`, exactly: decimal arithmetic, not floating point), the columns (or
//! constants) of each stream's fields and the unit of each stream's lengths (converted to mm)
//! and temperatures (to °C). Streams at different rates share one table: a row where all of a
//! stream's columns are empty has no sample of that stream, and a row where only some of them
//! are filled is an error.
//!
//! [`read`] calls its sink with each row's samples, `seq` consecutive per stream from 0, until
//! the first bad row; it reads on to the end to find every bad row (their errors kept up to
//! [`Options::max_errors`]) and then fails, naming file, line, column and what is wrong, so the
//! caller discards what it wrote: an import is complete or it is nothing. What is checked per
//! stream (per sensor and per distance probe within theirs): times rising (strictly within a
//! sensor or probe; a temperature stream may hold several sensors at one time), and no gap
//! longer than the mapping's `max_gap_s`.
//!
//! This module knows the wire contract, not the physics: batching the samples into raw
//! batches and writing them is the caller's (the CLI does it as the simulator does).
mod mapping;
mod number;
mod numeric;
mod table;
mod wide;

pub use mapping::{
    CommandMap, DistanceColumns, DistanceMap, DistanceProbe, LengthUnit, Mapping, MappingError,
    ProbeMap, ScaleMap, Source, StageMap, TemperatureMap, TemperatureUnit, TimeColumn, TimeUnit,
};
pub use numeric::{header, read_columns, Columns};
pub use table::Delimiter;
pub use wide::{export_wide, WideError, WideExport};

use scancorr_proto::v1::{
    CommandSample, DistanceSample, ProbeSample, ScaleSample, StageSample, TemperatureSample,
};
use scancorr_proto::Stream;
use serde::{Deserialize, Serialize};
use std::collections::{BTreeMap, HashMap};
use std::fmt;
use std::io::BufRead;
use table::{Next, Table};

/// One sample of a raw stream, as the wire contract has it (with its machine id and `seq`).
#[derive(Debug, Clone, PartialEq)]
pub enum Sample {
    /// `raw/command`.
    Command(CommandSample),
    /// `raw/scale`.
    Scale(ScaleSample),
    /// `raw/probe`.
    Probe(ProbeSample),
    /// `raw/temperature`.
    Temperature(TemperatureSample),
    /// `raw/distance` (v1.2).
    Distance(DistanceSample),
    /// `raw/stage` (v1.2).
    Stage(StageSample),
}

impl Sample {
    /// Its stream.
    pub fn stream(&self) -> Stream {
        match self {
            Sample::Command(_) => Stream::Command,
            Sample::Scale(_) => Stream::Scale,
            Sample::Probe(_) => Stream::Probe,
            Sample::Temperature(_) => Stream::Temperature,
            Sample::Distance(_) => Stream::Distance,
            Sample::Stage(_) => Stream::Stage,
        }
    }

    /// Its time, ns.
    pub fn t_ns(&self) -> i64 {
        match self {
            Sample::Command(s) => s.t_ns,
            Sample::Scale(s) => s.t_ns,
            Sample::Probe(s) => s.t_ns,
            Sample::Temperature(s) => s.t_ns,
            Sample::Distance(s) => s.t_ns,
            Sample::Stage(s) => s.t_ns,
        }
    }

    /// Its sequence number.
    pub fn seq(&self) -> u64 {
        match self {
            Sample::Command(s) => s.seq,
            Sample::Scale(s) => s.seq,
            Sample::Probe(s) => s.seq,
            Sample::Temperature(s) => s.seq,
            Sample::Distance(s) => s.seq,
            Sample::Stage(s) => s.seq,
        }
    }

    /// Its machine id.
    pub fn machine_id(&self) -> &str {
        match self {
            Sample::Command(s) => &s.machine_id,
            Sample::Scale(s) => &s.machine_id,
            Sample::Probe(s) => &s.machine_id,
            Sample::Temperature(s) => &s.machine_id,
            Sample::Distance(s) => &s.machine_id,
            Sample::Stage(s) => &s.machine_id,
        }
    }
}

/// The streams in the order of [`Summary::samples`] and of a row's samples.
pub const STREAMS: [Stream; 6] = [
    Stream::Command,
    Stream::Scale,
    Stream::Probe,
    Stream::Temperature,
    Stream::Distance,
    Stream::Stage,
];

/// A raw stream's short name (`command`, …, `stage`), as the mapping names it.
pub fn stream_name(s: Stream) -> &'static str {
    match s {
        Stream::Command => "command",
        Stream::Scale => "scale",
        Stream::Probe => "probe",
        Stream::Temperature => "temperature",
        Stream::Distance => "distance",
        Stream::Stage => "stage",
        Stream::Points => "points",
        Stream::Alarms => "alarms",
    }
}

fn stream_index(s: Stream) -> usize {
    STREAMS.iter().position(|x| *x == s).unwrap_or(0)
}

/// How a table is read.
#[derive(Debug, Clone, PartialEq)]
pub struct Options {
    /// The delimiter; `None`: detected from the header row.
    pub delimiter: Option<Delimiter>,
    /// Errors kept for the report (every bad row is counted).
    pub max_errors: usize,
}

impl Default for Options {
    fn default() -> Self {
        Options {
            delimiter: None,
            max_errors: 20,
        }
    }
}

/// What an import read.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Summary {
    /// The table, as named to [`read`].
    pub file: String,
    /// The machine the samples name.
    pub machine: String,
    /// The delimiter used (`comma`, `semicolon`, `tab`, `whitespace`).
    pub delimiter: String,
    /// Data rows read (not counting the header, comments and blank lines).
    pub rows: u64,
    /// Of them rows without a sample of any stream (every mapped cell empty).
    pub rows_without_samples: u64,
    /// Samples per mapped stream (`command`, `scale`, …).
    pub samples: BTreeMap<String, u64>,
    /// Time of the first and the last sample, ns.
    pub first_t_ns: Option<i64>,
    /// See `first_t_ns`.
    pub last_t_ns: Option<i64>,
    /// `last_t_ns − first_t_ns`, s.
    pub span_s: f64,
    /// Temperature sensors, in column order.
    pub sensors: Vec<String>,
    /// Distance probe ids, in column order.
    pub distance_probes: Vec<u32>,
    /// Header columns the mapping does not use.
    pub unmapped_columns: Vec<String>,
    /// What looks wrong but is not an error (a mapped column that is empty in every row).
    pub warnings: Vec<String>,
}

/// One bad cell or row: its line (1-based) and column (1-based, with its header name) when
/// the problem has one.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct RowError {
    /// Line of the file, 1-based (comments and blank lines counted).
    pub line: usize,
    /// Column, 1-based, and its header name.
    pub column: Option<(usize, String)>,
    /// What is wrong.
    pub message: String,
}

impl RowError {
    fn show(&self, file: &str) -> String {
        match &self.column {
            Some((c, name)) => format!(
                "{file}:{}:{c}: column {}: {}",
                self.line,
                number::shown(name),
                self.message
            ),
            None => format!("{file}:{}: {}", self.line, self.message),
        }
    }
}

/// Why an import failed. Every variant names the file; none leaves a partial result behind
/// that the caller should keep.
#[derive(Debug)]
#[non_exhaustive]
pub enum ImportError {
    /// Reading the table failed.
    Io {
        /// The table.
        file: String,
        /// The OS error.
        error: std::io::Error,
    },
    /// The mapping cannot be used (names its field).
    Mapping(MappingError),
    /// No header row: the file is empty or holds only comments.
    NoHeader {
        /// The table.
        file: String,
    },
    /// The header does not fit the mapping: duplicate names, mapped columns missing.
    Header {
        /// The table.
        file: String,
        /// Each problem, with the header's line.
        errors: Vec<RowError>,
        /// The header's column names.
        columns: Vec<String>,
    },
    /// Rows that cannot be read.
    Rows {
        /// The table.
        file: String,
        /// Rows with at least one error.
        bad_rows: u64,
        /// Data rows in all.
        rows: u64,
        /// The first errors (up to [`Options::max_errors`]).
        errors: Vec<RowError>,
        /// Errors not kept.
        more: u64,
    },
    /// Nothing to import: no row has a sample.
    NoSamples {
        /// The table.
        file: String,
        /// Data rows read.
        rows: u64,
    },
    /// The sink failed (writing the output).
    Sink(Box<dyn std::error::Error + Send + Sync>),
}

impl fmt::Display for ImportError {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self {
            ImportError::Io { file, error } => write!(f, "{file}: {error}"),
            ImportError::Mapping(e) => write!(f, "mapping: {e}"),
            ImportError::NoHeader { file } => write!(
                f,
                "{file}: no header row (the file is empty or holds only `#` comments)"
            ),
            ImportError::Header {
                file,
                errors,
                columns,
            } => {
                let list: Vec<String> = errors.iter().map(|e| e.show(file)).collect();
                write!(
                    f,
                    "{file}: the header does not fit the mapping:\n  {}\n  the header's columns: {}",
                    list.join("\n  "),
                    columns.join(", ")
                )
            }
            ImportError::Rows {
                file,
                bad_rows,
                rows,
                errors,
                more,
            } => {
                write!(f, "{file}: {bad_rows} bad row(s) of {rows}:")?;
                for e in errors {
                    write!(f, "\n  {}", e.show(file))?;
                }
                if *more > 0 {
                    write!(f, "\n  … and {more} more error(s)")?;
                }
                Ok(())
            }
            ImportError::NoSamples { file, rows } => write!(
                f,
                "{file}: no sample in {rows} data row(s): every mapped cell is empty"
            ),
            ImportError::Sink(e) => write!(f, "{e}"),
        }
    }
}

impl std::error::Error for ImportError {
    fn source(&self) -> Option<&(dyn std::error::Error + 'static)> {
        match self {
            ImportError::Io { error, .. } => Some(error),
            ImportError::Mapping(e) => Some(e),
            _ => None,
        }
    }
}

/// How a field's text becomes its value.
#[derive(Debug, Clone, Copy, PartialEq)]
enum Conv {
    Length(LengthUnit),
    Celsius(TemperatureUnit),
    Plain,
    Id,
}

/// Where a field's value comes from, resolved against the header.
#[derive(Debug, Clone, Copy, PartialEq)]
enum Val {
    Col(usize),
    Const(f64),
}

/// What a group's samples are.
#[derive(Debug, Clone, PartialEq)]
enum GroupKind {
    Command,
    Scale,
    Probe,
    Temperature(String),
    Distance(u32),
    Stage,
}

/// The fields of one stream (or one sensor, one distance probe) and its running state.
#[derive(Debug)]
struct Group {
    kind: GroupKind,
    /// `command`, `temperature.air`, `distance.2`.
    label: String,
    stream: usize,
    /// In the sample's field order; unmapped optional fields are constants 0.
    fields: Vec<(Val, Conv)>,
    /// Column indices of the column fields.
    columns: Vec<usize>,
    max_gap_ns: Option<i64>,
    last: Option<(i64, usize)>,
    samples: u64,
}

impl Group {
    fn new(kind: GroupKind, label: String, fields: Vec<(Val, Conv)>, gap: Option<f64>) -> Group {
        let stream = stream_index(match kind {
            GroupKind::Command => Stream::Command,
            GroupKind::Scale => Stream::Scale,
            GroupKind::Probe => Stream::Probe,
            GroupKind::Temperature(_) => Stream::Temperature,
            GroupKind::Distance(_) => Stream::Distance,
            GroupKind::Stage => Stream::Stage,
        });
        let columns = fields
            .iter()
            .filter_map(|(v, _)| match v {
                Val::Col(i) => Some(*i),
                Val::Const(_) => None,
            })
            .collect();
        Group {
            kind,
            label,
            stream,
            fields,
            columns,
            max_gap_ns: gap.map(|g| (g * 1e9).round() as i64),
            last: None,
            samples: 0,
        }
    }

    /// The first column, to order sensors and probes as the table does.
    fn first_column(&self) -> usize {
        self.columns.iter().copied().min().unwrap_or(usize::MAX)
    }
}

/// Mapped columns the header lacks: (column, the field that maps it).
type Missing = Vec<(String, String)>;

/// Resolves the mapping against the header: the time column and the groups in emission
/// order.
fn plan(mapping: &Mapping, header: &HashMap<&str, usize>) -> Result<(usize, Vec<Group>), Missing> {
    let mut missing = vec![];
    for (col, field) in mapping.named_columns() {
        if !header.contains_key(col.as_str()) && !missing.iter().any(|(c, _)| *c == col) {
            missing.push((col, field));
        }
    }
    if !missing.is_empty() {
        return Err(missing);
    }
    let col = |name: &str| header.get(name).copied().unwrap_or(0);
    let val = |s: &Option<Source>| match s {
        Some(Source::Column(c)) => Val::Col(col(c)),
        Some(Source::Constant(v)) => Val::Const(*v),
        None => Val::Const(0.0),
    };
    let gap = |own: Option<f64>| own.or(mapping.max_gap_s);
    let time = mapping.time.as_ref().map_or(0, |t| col(&t.column));
    let mut groups = vec![];
    if let Some(m) = &mapping.command {
        let l = Conv::Length(m.unit);
        groups.push(Group::new(
            GroupKind::Command,
            "command".into(),
            vec![
                (val(&m.x), l),
                (val(&m.y), l),
                (val(&m.z), l),
                (val(&m.arc_cx), l),
                (val(&m.arc_cy), l),
                (val(&m.arc_cz), l),
                (val(&m.arc_radius), l),
                (val(&m.segment_id), Conv::Id),
            ],
            gap(m.max_gap_s),
        ));
    }
    if let Some(m) = &mapping.scale {
        let l = Conv::Length(m.unit);
        groups.push(Group::new(
            GroupKind::Scale,
            "scale".into(),
            vec![(val(&m.x), l), (val(&m.y), l), (val(&m.z), l)],
            gap(m.max_gap_s),
        ));
    }
    if let Some(m) = &mapping.probe {
        let l = Conv::Length(m.unit);
        groups.push(Group::new(
            GroupKind::Probe,
            "probe".into(),
            vec![
                (val(&m.u), l),
                (val(&m.v), l),
                (val(&m.w), l),
                (val(&m.tip_id), Conv::Id),
                (val(&m.head_a1_deg), Conv::Plain),
                (val(&m.head_a2_deg), Conv::Plain),
            ],
            gap(m.max_gap_s),
        ));
    }
    if let Some(m) = &mapping.temperature {
        let mut sensors: Vec<Group> = m
            .sensors
            .iter()
            .map(|(name, c)| {
                Group::new(
                    GroupKind::Temperature(name.clone()),
                    format!("temperature.{name}"),
                    vec![(Val::Col(col(c)), Conv::Celsius(m.unit))],
                    gap(m.max_gap_s),
                )
            })
            .collect();
        sensors.sort_by_key(Group::first_column);
        groups.extend(sensors);
    }
    if let Some(m) = &mapping.distance {
        let l = Conv::Length(m.unit);
        let mut probes: Vec<Group> = m
            .probes
            .iter()
            .map(|(id, p)| {
                let spacing = match p {
                    DistanceProbe::Column(_) => None,
                    DistanceProbe::With(d) => d.spacing.clone(),
                };
                let reading = match p {
                    DistanceProbe::Column(c) => c,
                    DistanceProbe::With(d) => &d.column,
                };
                Group::new(
                    GroupKind::Distance(*id),
                    format!("distance.{id}"),
                    vec![(Val::Col(col(reading)), l), (val(&spacing), l)],
                    gap(m.max_gap_s),
                )
            })
            .collect();
        probes.sort_by_key(Group::first_column);
        groups.extend(probes);
    }
    if let Some(m) = &mapping.stage {
        let l = Conv::Length(m.unit);
        groups.push(Group::new(
            GroupKind::Stage,
            "stage".into(),
            vec![
                (val(&m.commanded), l),
                (val(&m.sensor), l),
                (val(&m.probe_id), Conv::Id),
            ],
            gap(m.max_gap_s),
        ));
    }
    Ok((time, groups))
}

/// A field's value from its text (or constant).
fn convert(v: f64, conv: Conv) -> f64 {
    match conv {
        Conv::Length(u) => u.to_mm(v),
        Conv::Celsius(u) => u.to_celsius(v),
        Conv::Plain | Conv::Id => v,
    }
}

fn parse_cell(text: &str, conv: Conv) -> Result<f64, String> {
    match conv {
        Conv::Id => number::id(text).map(f64::from),
        _ => number::value(text).map(|v| convert(v, conv)),
    }
}

fn sample(kind: &GroupKind, machine: &str, seq: u64, t_ns: i64, v: &[f64]) -> Sample {
    let machine_id = machine.to_string();
    let id = |x: f64| x as u32;
    match kind {
        GroupKind::Command => Sample::Command(CommandSample {
            machine_id,
            seq,
            t_ns,
            x: v[0],
            y: v[1],
            z: v[2],
            arc_cx: v[3],
            arc_cy: v[4],
            arc_cz: v[5],
            arc_radius: v[6],
            segment_id: id(v[7]),
        }),
        GroupKind::Scale => Sample::Scale(ScaleSample {
            machine_id,
            seq,
            t_ns,
            x: v[0],
            y: v[1],
            z: v[2],
        }),
        GroupKind::Probe => Sample::Probe(ProbeSample {
            machine_id,
            seq,
            t_ns,
            u: v[0],
            v: v[1],
            w: v[2],
            tip_id: id(v[3]),
            head_a1_deg: v[4],
            head_a2_deg: v[5],
            force_n: None,
        }),
        GroupKind::Temperature(sensor) => Sample::Temperature(TemperatureSample {
            machine_id,
            seq,
            t_ns,
            sensor: sensor.clone(),
            celsius: v[0],
        }),
        GroupKind::Distance(probe_id) => Sample::Distance(DistanceSample {
            machine_id,
            seq,
            t_ns,
            probe_id: *probe_id,
            distance_mm: v[0],
            spacing_mm: v[1],
        }),
        GroupKind::Stage => Sample::Stage(StageSample {
            machine_id,
            seq,
            t_ns,
            commanded_mm: v[0],
            sensor_mm: v[1],
            probe_id: id(v[2]),
        }),
    }
}

/// Reads the table `input` (named `file` in messages) with `mapping` and hands every sample
/// to `sink`, row by row, while no row has been bad; see the module's documentation. The
/// mapping must name the machine ([`Mapping::machine`]).
pub fn read<R: BufRead>(
    input: R,
    file: &str,
    mapping: &Mapping,
    options: &Options,
    mut sink: impl FnMut(Sample) -> Result<(), Box<dyn std::error::Error + Send + Sync>>,
) -> Result<Summary, ImportError> {
    mapping.check().map_err(ImportError::Mapping)?;
    let machine = mapping.machine.clone().ok_or_else(|| {
        ImportError::Mapping(MappingError(
            "no machine id: name it in the mapping (`machine`) or on the command line".into(),
        ))
    })?;
    let Some(time) = &mapping.time else {
        return Err(ImportError::Mapping(MappingError("no time column".into())));
    };
    let (time_unit, offset_ns) = (time.unit, time.offset_ns);
    let io = |error| ImportError::Io {
        file: file.to_string(),
        error,
    };
    let mut table = numeric::open(input, file, options)?;
    let header = table.header.clone();
    let header_line = table.header_line;
    let mut index: HashMap<&str, usize> = HashMap::new();
    let mut header_errors = vec![];
    for (i, name) in header.iter().enumerate() {
        if name.is_empty() {
            continue;
        }
        if let Some(first) = index.insert(name.as_str(), i) {
            index.insert(name.as_str(), first);
            header_errors.push(RowError {
                line: header_line,
                column: Some((i + 1, name.clone())),
                message: format!(
                    "a duplicate column name (also column {}): a mapped name must be unique",
                    first + 1
                ),
            });
        }
    }
    let planned = plan(mapping, &index);
    if let Err(missing) = &planned {
        for (col, field) in missing {
            header_errors.push(RowError {
                line: header_line,
                column: None,
                message: format!("no column {} (mapped as {field})", number::shown(col)),
            });
        }
    }
    let (time_col, mut groups) = match planned {
        Ok(p) if header_errors.is_empty() => p,
        _ => {
            return Err(ImportError::Header {
                file: file.to_string(),
                errors: header_errors,
                columns: header,
            })
        }
    };
    let named: Vec<(String, String)> = mapping.named_columns();
    let unmapped_columns: Vec<String> = header
        .iter()
        .filter(|h| !h.is_empty() && !named.iter().any(|(c, _)| c == *h))
        .cloned()
        .collect();

    let mut seq = [0u64; STREAMS.len()];
    let mut stream_last: [Option<(i64, usize)>; STREAMS.len()] = [None; STREAMS.len()];
    let mut rows = 0u64;
    let mut rows_without_samples = 0u64;
    let mut bad_rows = 0u64;
    let mut errors: Vec<RowError> = vec![];
    let mut more = 0u64;
    let mut first_t: Option<i64> = None;
    let mut last_t: Option<i64> = None;
    let mut row_errors: Vec<RowError> = vec![];
    let mut out: Vec<Sample> = vec![];
    let mut values: Vec<f64> = vec![];
    let n = header.len();
    let at = |line: usize, c: usize, message: String| RowError {
        line,
        column: Some((c + 1, header.get(c).cloned().unwrap_or_default())),
        message,
    };
    loop {
        match table.next_row().map_err(io)? {
            Next::End => break,
            Next::Bad(line, reason) => {
                rows += 1;
                row_errors.push(RowError {
                    line,
                    column: None,
                    message: reason,
                });
            }
            Next::Row(line) => {
                rows += 1;
                read_row(
                    &table,
                    line,
                    n,
                    time_col,
                    time_unit.exponent(),
                    offset_ns,
                    &mut groups,
                    &mut stream_last,
                    &mut seq,
                    &machine,
                    &at,
                    &mut row_errors,
                    &mut out,
                    &mut values,
                    &mut rows_without_samples,
                );
            }
        }
        if !row_errors.is_empty() {
            bad_rows += 1;
            for e in row_errors.drain(..) {
                if errors.len() < options.max_errors.max(1) {
                    errors.push(e);
                } else {
                    more += 1;
                }
            }
            out.clear();
            continue;
        }
        for s in out.drain(..) {
            let t = s.t_ns();
            first_t = Some(first_t.map_or(t, |f| f.min(t)));
            last_t = Some(last_t.map_or(t, |l| l.max(t)));
            if errors.is_empty() {
                sink(s).map_err(ImportError::Sink)?;
            }
        }
    }
    if bad_rows > 0 {
        return Err(ImportError::Rows {
            file: file.to_string(),
            bad_rows,
            rows,
            errors,
            more,
        });
    }
    let mut samples = BTreeMap::new();
    for g in &groups {
        *samples
            .entry(stream_name(STREAMS[g.stream]).to_string())
            .or_insert(0) += g.samples;
    }
    if samples.values().all(|n| *n == 0) {
        return Err(ImportError::NoSamples {
            file: file.to_string(),
            rows,
        });
    }
    let mut warnings = vec![];
    for g in groups.iter().filter(|g| g.samples == 0) {
        let cols: Vec<String> = g
            .columns
            .iter()
            .map(|c| number::shown(&header[*c]))
            .collect();
        warnings.push(format!(
            "{} has no sample: its column(s) {} are empty in every row",
            g.label,
            cols.join(", ")
        ));
    }
    Ok(Summary {
        file: file.to_string(),
        machine,
        delimiter: table.delimiter.name().to_string(),
        rows,
        rows_without_samples,
        samples,
        first_t_ns: first_t,
        last_t_ns: last_t,
        span_s: match (first_t, last_t) {
            (Some(a), Some(b)) => (i128::from(b) - i128::from(a)) as f64 / 1e9,
            _ => 0.0,
        },
        sensors: groups
            .iter()
            .filter_map(|g| match &g.kind {
                GroupKind::Temperature(s) => Some(s.clone()),
                _ => None,
            })
            .collect(),
        distance_probes: groups
            .iter()
            .filter_map(|g| match g.kind {
                GroupKind::Distance(id) => Some(id),
                _ => None,
            })
            .collect(),
        unmapped_columns,
        warnings,
    })
}

/// Reads one split row: its errors into `errs`, its samples (in emission order) into `out`.
#[allow(clippy::too_many_arguments)]
fn read_row<R: BufRead>(
    table: &Table<R>,
    line: usize,
    n: usize,
    time_col: usize,
    time_exp: i32,
    offset_ns: i64,
    groups: &mut [Group],
    stream_last: &mut [Option<(i64, usize)>; STREAMS.len()],
    seq: &mut [u64; STREAMS.len()],
    machine: &str,
    at: &impl Fn(usize, usize, String) -> RowError,
    errs: &mut Vec<RowError>,
    out: &mut Vec<Sample>,
    values: &mut Vec<f64>,
    rows_without_samples: &mut u64,
) {
    if table.width() < n {
        errs.push(RowError {
            line,
            column: None,
            message: format!(
                "{} cell(s), the header has {n} (a row holds every column; an empty cell says \"no value\")",
                table.width()
            ),
        });
        return;
    }
    if let Some(extra) = (n..table.width()).find(|&i| !table.cell(i).is_empty()) {
        errs.push(RowError {
            line,
            column: Some((extra + 1, "(beyond the header)".to_string())),
            message: format!("{} cell(s), the header has {n}", table.width()),
        });
        return;
    }
    if groups
        .iter()
        .all(|g| g.columns.iter().all(|&c| table.cell(c).is_empty()))
    {
        *rows_without_samples += 1;
        return;
    }
    let tcell = table.cell(time_col);
    if tcell.is_empty() {
        errs.push(at(
            line,
            time_col,
            "no time, but the row has samples".to_string(),
        ));
        return;
    }
    let t = match number::scaled_integer(tcell, time_exp).and_then(|t| t.checked_add(offset_ns)) {
        Some(t) => t,
        None => {
            errs.push(at(
                line,
                time_col,
                format!(
                    "{} is not a time (a number, within ±292 years in ns)",
                    number::shown(tcell)
                ),
            ));
            return;
        }
    };
    for g in groups.iter_mut() {
        let filled = g
            .columns
            .iter()
            .filter(|&&c| !table.cell(c).is_empty())
            .count();
        if filled == 0 {
            continue;
        }
        if filled < g.columns.len() {
            let empty = g
                .columns
                .iter()
                .copied()
                .find(|&c| table.cell(c).is_empty())
                .unwrap_or(0);
            errs.push(at(
                line,
                empty,
                format!(
                    "empty, but {filled} other column(s) of {} are filled: a row holds all of a stream's columns or none",
                    g.label
                ),
            ));
            continue;
        }
        values.clear();
        let before = errs.len();
        for &(v, conv) in &g.fields {
            match v {
                Val::Const(c) => values.push(convert(c, conv)),
                Val::Col(c) => match parse_cell(table.cell(c), conv) {
                    Ok(x) => values.push(x),
                    Err(m) => errs.push(at(line, c, m)),
                },
            }
        }
        if errs.len() > before {
            continue;
        }
        if let Some((last, last_line)) = g.last {
            if t <= last {
                errs.push(at(
                    line,
                    time_col,
                    format!(
                        "time {tcell} (t_ns {t}) is not after {}'s previous sample (line {last_line}, t_ns {last})",
                        g.label
                    ),
                ));
                continue;
            }
            if let Some(max) = g.max_gap_ns {
                if t - last > max {
                    errs.push(at(
                        line,
                        time_col,
                        format!(
                            "a gap of {} s in {} since its previous sample (line {last_line}), more than the largest gap {} s",
                            (t - last) as f64 / 1e9,
                            g.label,
                            max as f64 / 1e9
                        ),
                    ));
                    continue;
                }
            }
        }
        if let Some((last, last_line)) = stream_last[g.stream] {
            if t < last {
                errs.push(at(
                    line,
                    time_col,
                    format!(
                        "time {tcell} (t_ns {t}) goes back in the {} stream (line {last_line}, t_ns {last})",
                        stream_name(STREAMS[g.stream])
                    ),
                ));
                continue;
            }
        }
        g.last = Some((t, line));
        stream_last[g.stream] = Some((t, line));
        g.samples += 1;
        out.push(sample(&g.kind, machine, seq[g.stream], t, values));
        seq[g.stream] += 1;
    }
}

/// A metadata record in its JSON form (what `--artifacts FILE` takes, what
/// `scancorr export --raw` writes beside its table as `F.meta.json`): the record's name and
/// its string map, as the bag stores it.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Record {
    /// Record name (`scancorr.artifact`, `scancorr.program`, …).
    pub name: String,
    /// Its entries.
    pub entries: BTreeMap<String, String>,
}

#[cfg(test)]
mod tests;
