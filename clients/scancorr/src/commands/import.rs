//! `scancorr import --csv FILE (--map MAP.json | --col STREAM.FIELD=COLUMN … --time COLUMN
//! --time-unit U) [--machine ID] --out OUT.mcap [--json]`: a user's recorded table — CSV or
//! whitespace columns from a controller's trace tool, a data logger or CMM software — into a
//! bag of the wire contract.
//!
//! Reading the table and the mapping are `scancorr_bag::import`'s. Here: the flags, the
//! batches — packed by `wire::Batcher` and written as `scancorr sim` writes them, each stream's
//! batch closed at `--batch` samples or 100 ms of sample time (a controller's period, so streams
//! at different rates stay interleaved in the bag) — the optional metadata records
//! (`--artifacts`) and the output, written under a temporary name and renamed only when the
//! whole table has been read without an error: a bad table leaves no file.

use crate::shared::output::{refuse_same_file, AtomicOutput};
use anyhow::{bail, Context, Result};
use scancorr_bag::import::{self, Mapping, Record, Sample, Source};
use scancorr_bag::{Artifact, BagHeader, BagWriter, Stream, ARTIFACT_METADATA};
use scancorr_core::wire::{self, Batcher};
use scancorr_proto::v1::{DistanceBatch, StageBatch, StreamKind};
use std::collections::BTreeMap;
use std::path::{Path, PathBuf};

/// The flags of `scancorr import`.
#[derive(clap::Args)]
pub struct ImportArgs {
    /// The table: a header row of column names, then rows; `#` comment lines allowed; cells
    /// separated by commas, semicolons, tabs or whitespace (detected from the header).
    #[arg(long)]
    csv: PathBuf,
    /// Mapping file (JSON: time column and unit, each stream's columns and units; see
    /// README). The flags below add to it or override it.
    #[arg(long)]
    map: Option<PathBuf>,
    /// A field from a column: STREAM.FIELD=COLUMN (repeatable), e.g. command.x=X,
    /// probe.tip_id=Tip, temperature.air=T1, distance.1=D1.
    #[arg(long = "col", value_name = "STREAM.FIELD=COLUMN")]
    col: Vec<String>,
    /// A field as a constant: STREAM.FIELD=VALUE in the stream's unit (repeatable), e.g.
    /// probe.tip_id=1, probe.head_a1_deg=90.
    #[arg(
        long = "const",
        value_name = "STREAM.FIELD=VALUE",
        allow_hyphen_values = true
    )]
    constant: Vec<String>,
    /// A stream's unit: STREAM=UNIT (repeatable): mm, um, m, in for command, scale, probe,
    /// distance, stage (default mm); C or K for temperature (default C).
    #[arg(long = "unit", value_name = "STREAM=UNIT")]
    unit: Vec<String>,
    /// The time column.
    #[arg(long)]
    time: Option<String>,
    /// Its unit: s, ms, us, ns.
    #[arg(long)]
    time_unit: Option<String>,
    /// Added to every time after the conversion, ns (the controller clock at time zero).
    #[arg(long, allow_hyphen_values = true)]
    time_offset_ns: Option<i64>,
    /// Machine id of the samples (overrides the mapping's).
    #[arg(long)]
    machine: Option<String>,
    /// comma, semicolon, tab or whitespace (default: detected from the header row).
    #[arg(long)]
    delimiter: Option<String>,
    /// Refuse a gap longer than this between two samples of a stream (of a sensor, of a
    /// distance probe), s.
    #[arg(long)]
    max_gap: Option<f64>,
    /// Errors to list (every bad row is counted).
    #[arg(long, default_value_t = 20)]
    max_errors: usize,
    /// Metadata records to embed (JSON): an artifact as the bag stores it (`{"kind": "ring",
    /// "diameter_mm": 50, "serial": "R-7"}`) or a list of records `[{"name": …, "entries":
    /// {…}}]` (what `scancorr export --raw` writes beside its table as F.meta.json).
    #[arg(long)]
    artifacts: Option<PathBuf>,
    /// Output bag.
    #[arg(long)]
    out: PathBuf,
    /// Samples per message (at most; a batch also closes after 100 ms of sample time).
    #[arg(long, default_value_t = 100)]
    batch: usize,
    /// Key-expression prefix of the bag's topics.
    #[arg(long, default_value = "cmm")]
    prefix: String,
    /// Print the summary as JSON.
    #[arg(long)]
    json: bool,
}

/// A batch closes after this much sample time.
const PERIOD_NS: i64 = 100_000_000;

/// The samples into raw batches, into the bag.
struct Writer<'a> {
    w: BagWriter,
    b: Batcher,
    machine: &'a str,
    prefix: &'a str,
    size: usize,
    /// Time of the first sample of each stream's open batch (`import::STREAMS` order).
    first: [Option<i64>; 6],
    last: [i64; 6],
    distance: DistanceBatch,
    stage: StageBatch,
}

fn index(s: Stream) -> usize {
    import::STREAMS.iter().position(|x| *x == s).unwrap_or(0)
}

impl Writer<'_> {
    fn push(&mut self, s: Sample) -> Result<()> {
        let t = s.t_ns();
        for i in 0..self.first.len() {
            if self.first[i].is_some_and(|f| t - f >= PERIOD_NS) {
                self.flush(i)?;
            }
        }
        let i = index(s.stream());
        let full = match s {
            Sample::Command(c) => self.b.push(&wire::command(&c)).is_some(),
            Sample::Scale(c) => self.b.push(&wire::scale(&c)).is_some(),
            Sample::Probe(c) => self.b.push(&wire::probe(&c)).is_some(),
            Sample::Temperature(c) => self.b.push(&wire::temperature(&c)).is_some(),
            Sample::Distance(d) => {
                self.distance.samples.push(d);
                self.distance.samples.len() >= self.size
            }
            Sample::Stage(g) => {
                self.stage.samples.push(g);
                self.stage.samples.len() >= self.size
            }
        };
        self.first[i].get_or_insert(t);
        self.last[i] = t;
        if full {
            self.flush(i)?;
        }
        Ok(())
    }

    /// Writes stream `i`'s open batch, if any; its log time is its last sample's.
    fn flush(&mut self, i: usize) -> Result<()> {
        if self.first[i].take().is_none() {
            return Ok(());
        }
        let log = self.last[i].max(0) as u64;
        let stream = import::STREAMS[i];
        match stream {
            Stream::Distance => {
                self.w
                    .write_msg(self.machine, self.prefix, log, &self.distance)?;
                self.distance.samples.clear();
            }
            Stream::Stage => {
                self.w
                    .write_msg(self.machine, self.prefix, log, &self.stage)?;
                self.stage.samples.clear();
            }
            other => {
                if let Some((bytes, t0, _)) = wire::stream_id(other).and_then(|s| self.b.take(s)) {
                    self.w.write(
                        other,
                        self.machine,
                        self.prefix,
                        log,
                        t0.max(0) as u64,
                        &bytes,
                    )?;
                }
            }
        }
        Ok(())
    }
}

/// `STREAM.FIELD=VALUE` split.
fn spec<'a>(flag: &str, s: &'a str) -> Result<(&'a str, &'a str)> {
    s.split_once('=')
        .filter(|(k, v)| !k.is_empty() && !v.is_empty())
        .with_context(|| format!("{flag} {s}: expected STREAM.FIELD=VALUE"))
}

/// The mapping from `--map` and the flags.
fn mapping(a: &ImportArgs) -> Result<Mapping> {
    let mut m = match &a.map {
        Some(p) => {
            let text =
                std::fs::read_to_string(p).with_context(|| format!("--map {}", p.display()))?;
            serde_json::from_str::<Mapping>(&text)
                .with_context(|| format!("--map {}: not a mapping", p.display()))?
        }
        None => {
            if a.col.is_empty() {
                bail!("give --map MAP.json, or the columns: --col STREAM.FIELD=COLUMN … --time COLUMN --time-unit s|ms|us|ns");
            }
            Mapping::default()
        }
    };
    if let Some(id) = &a.machine {
        crate::shared::output::check_machine("--machine", id)?;
        m.machine = Some(id.clone());
    }
    if a.time.is_some() || a.time_unit.is_some() || a.time_offset_ns.is_some() {
        let column = a
            .time
            .clone()
            .or_else(|| m.time.as_ref().map(|t| t.column.clone()))
            .context("--time COLUMN: the time column")?;
        let unit = match &a.time_unit {
            Some(u) => u
                .parse()
                .map_err(|e: String| anyhow::anyhow!("--time-unit: {e}"))?,
            None => m
                .time
                .as_ref()
                .map(|t| t.unit)
                .context("--time-unit s|ms|us|ns: the time column's unit")?,
        };
        let offset_ns = a
            .time_offset_ns
            .or_else(|| m.time.as_ref().map(|t| t.offset_ns))
            .unwrap_or(0);
        m.time = Some(import::TimeColumn {
            column,
            unit,
            offset_ns,
        });
    }
    for c in &a.col {
        let (path, column) = spec("--col", c)?;
        m.set(path, Source::Column(column.to_string()))
            .with_context(|| format!("--col {c}"))?;
    }
    for c in &a.constant {
        let (path, value) = spec("--const", c)?;
        let v: f64 = value
            .parse()
            .with_context(|| format!("--const {c}: {value} is not a number"))?;
        m.set(path, Source::Constant(v))
            .with_context(|| format!("--const {c}"))?;
    }
    for u in &a.unit {
        let (stream, unit) = spec("--unit", u)?;
        m.set_unit(stream, unit)
            .with_context(|| format!("--unit {u}"))?;
    }
    if let Some(g) = a.max_gap {
        anyhow::ensure!(
            g.is_finite() && g > 0.0,
            "--max-gap must be a number of seconds > 0"
        );
        m.max_gap_s = Some(g);
    }
    if m.machine.is_none() {
        bail!("give --machine ID (the mapping names none)");
    }
    m.check().context(if a.map.is_some() {
        "the mapping (--map and the flags)"
    } else {
        "the mapping (the flags)"
    })?;
    Ok(m)
}

/// The records of `--artifacts`, checked: an artifact parses as the bag's artifact, a
/// program as the lab's program.
fn records(path: &Path) -> Result<Vec<Record>> {
    let flag = || format!("--artifacts {}", path.display());
    let text = std::fs::read_to_string(path).with_context(flag)?;
    let v: serde_json::Value = serde_json::from_str(&text).with_context(flag)?;
    let list: Vec<Record> = match v {
        serde_json::Value::Array(_) => serde_json::from_value(v)
            .with_context(|| format!("{}: a list of {{\"name\", \"entries\"}} records", flag()))?,
        serde_json::Value::Object(ref o) if o.contains_key("name") && o.contains_key("entries") => {
            vec![serde_json::from_value(v).with_context(flag)?]
        }
        serde_json::Value::Object(o) => {
            // The artifact record's string map, numbers written as numbers or strings.
            let mut entries = BTreeMap::new();
            for (k, v) in o {
                let v = match v {
                    serde_json::Value::String(s) => s,
                    serde_json::Value::Number(n) => n.to_string(),
                    other => bail!(
                        "{}: `{k}` is {other}: an artifact's entries are strings or numbers",
                        flag()
                    ),
                };
                entries.insert(k, v);
            }
            vec![Record {
                name: ARTIFACT_METADATA.to_string(),
                entries,
            }]
        }
        _ => bail!(
            "{}: an artifact (`{{\"kind\": \"ring\", \"diameter_mm\": 50}}`) or a list of records",
            flag()
        ),
    };
    for r in &list {
        anyhow::ensure!(!r.name.is_empty(), "{}: a record without a name", flag());
        if r.name == ARTIFACT_METADATA {
            Artifact::from_metadata(&r.entries)
                .with_context(|| format!("{}: {}", flag(), r.name))?;
        }
        if r.name == "scancorr.program" {
            let j = r
                .entries
                .get("json")
                .with_context(|| format!("{}: scancorr.program without `json`", flag()))?;
            serde_json::from_str::<scancorr_core::lab::program::ProgramSpec>(j)
                .with_context(|| format!("{}: scancorr.program is not a valid program", flag()))?;
        }
    }
    Ok(list)
}

/// Runs the import.
pub fn run(a: ImportArgs) -> Result<()> {
    let m = mapping(&a)?;
    crate::shared::output::check_prefix(&a.prefix)?;
    anyhow::ensure!(a.batch >= 1, "--batch must be ≥ 1");
    let delimiter = a
        .delimiter
        .as_deref()
        .map(|d| d.parse::<import::Delimiter>())
        .transpose()
        .map_err(|e| anyhow::anyhow!("--delimiter: {e}"))?;
    let mut inputs: Vec<(&str, &Path)> = vec![("--csv", &a.csv)];
    if let Some(p) = &a.map {
        inputs.push(("--map", p));
    }
    if let Some(p) = &a.artifacts {
        inputs.push(("--artifacts", p));
    }
    refuse_same_file(&[("--out", &a.out)], &inputs)?;
    let extra = a.artifacts.as_deref().map(records).transpose()?;
    let file = std::fs::File::open(&a.csv).with_context(|| format!("--csv {}", a.csv.display()))?;
    let out = AtomicOutput::new("--out", &a.out)?;
    let machine = m.machine.clone().unwrap_or_default();
    let mut w = Writer {
        w: BagWriter::from_file(out.file()?, out.path(), BagHeader::default())
            .with_context(|| format!("creating {}", a.out.display()))?,
        b: Batcher::new(&machine, a.batch),
        machine: &machine,
        prefix: &a.prefix,
        size: a.batch,
        first: [None; 6],
        last: [0; 6],
        distance: DistanceBatch {
            samples: vec![],
            stream: StreamKind::Distance as i32,
        },
        stage: StageBatch {
            samples: vec![],
            stream: StreamKind::Stage as i32,
        },
    };
    let shown = a.csv.display().to_string();
    let summary = import::read(
        std::io::BufReader::with_capacity(256 * 1024, file),
        &shown,
        &m,
        &import::Options {
            delimiter,
            max_errors: a.max_errors,
        },
        |s| w.push(s).map_err(|e| format!("{e:#}").into()),
    )
    .with_context(|| format!("nothing written to {}", a.out.display()))?;
    for i in 0..import::STREAMS.len() {
        w.flush(i)?;
    }
    let mut w = w.w;
    let mut meta: BTreeMap<String, String> = [
        ("source", "scancorr import".to_string()),
        ("csv", shown.clone()),
        ("machine_id", machine.clone()),
        ("rows", summary.rows.to_string()),
        ("mapping", serde_json::to_string(&m)?),
    ]
    .into_iter()
    .map(|(k, v)| (k.to_string(), v))
    .collect();
    if let Some(p) = &a.artifacts {
        meta.insert("artifacts".into(), p.display().to_string());
    }
    w.write_metadata("scancorr.import", &meta)?;
    for r in extra.iter().flatten() {
        w.write_metadata(&r.name, &r.entries)
            .with_context(|| format!("writing the record {}", r.name))?;
    }
    w.finish()
        .with_context(|| format!("writing {}", a.out.display()))?;
    out.commit()?;
    for warning in &summary.warnings {
        eprintln!("warning: {warning}");
    }
    if a.json {
        let mut v = serde_json::to_value(&summary)?;
        v["out"] = serde_json::Value::String(a.out.display().to_string());
        v["records"] = extra
            .iter()
            .flatten()
            .map(|r| serde_json::Value::String(r.name.clone()))
            .collect();
        outln!("{}", serde_json::to_string_pretty(&v)?)?;
    } else {
        outln!("{}", text(&summary, &a.out))?;
    }
    Ok(())
}

/// The summary as text.
fn text(s: &import::Summary, out: &Path) -> String {
    let mut t = format!(
        "{} → {}: machine {}, {} row(s) ({}-separated{})",
        s.file,
        out.display(),
        s.machine,
        s.rows,
        s.delimiter,
        if s.rows_without_samples > 0 {
            format!(", {} without a sample", s.rows_without_samples)
        } else {
            String::new()
        }
    );
    let samples: Vec<String> = import::STREAMS
        .iter()
        .map(|st| import::stream_name(*st))
        .filter_map(|k| s.samples.get(k).map(|v| format!("{k} {v}")))
        .collect();
    t += &format!("\n  samples: {}", samples.join(", "));
    if let (Some(a), Some(b)) = (s.first_t_ns, s.last_t_ns) {
        t += &format!("\n  time: t_ns {a} … {b} ({} s)", s.span_s);
    }
    if !s.sensors.is_empty() {
        t += &format!("\n  sensors: {}", s.sensors.join(", "));
    }
    if !s.distance_probes.is_empty() {
        let ids: Vec<String> = s.distance_probes.iter().map(u32::to_string).collect();
        t += &format!("\n  distance probes: {}", ids.join(", "));
    }
    if !s.unmapped_columns.is_empty() {
        t += &format!("\n  columns not mapped: {}", s.unmapped_columns.join(", "));
    }
    t
}
