//! `scancorr export --bag corrected.mcap --format csv|xyz [--segment N] [--machine M] --out F`:
//! the corrected points of a bag in the ASCII forms vendor CMM software, spreadsheets and
//! numpy read.
//!
//! * `csv`: one row per corrected point, with a header — machine, seq, time, segment, tip,
//!   calibration version, estimator validity, the contact flag (a normal was known), the
//!   surface point, the tip centre, the normal, and per effect of the calibration its
//!   correction (`<effect>_dx_mm`, …; the union of the effects over the bag, empty where a
//!   point's calibration did not have it).
//! * `xyz`: `x y z` rows of the surface points in contact (what `scancorr shape fit` and most
//!   CMM software read), `#` comment lines first saying what they are.
//!
//! The bag is read twice (the effects' names first), so a long recording is never held in
//! memory; the output is written under a temporary name and renamed when complete.
//!
//! `--raw` ([`run_raw`]): the raw streams instead, as one wide CSV (`t_ns`, one row per
//! time; `scancorr_bag::import::export_wide`) with its mapping beside (`F.map.json`, and the
//! bag's metadata records as `F.meta.json`), so `scancorr import --csv F.csv --map
//! F.map.json [--artifacts F.meta.json]` reads it back to the same samples.

use crate::shared::output::{csv_text, header_name, one_line, refuse_same_file, AtomicOutput};
use anyhow::{bail, Context, Result};
use scancorr_bag::{BagReader, Stream};
use scancorr_proto::v1::CorrectedPoint;
use scancorr_proto::Message;
use std::collections::BTreeSet;
use std::io::{BufWriter, Write};
use std::path::{Path, PathBuf};

/// Export formats.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Format {
    /// Comma-separated values with a header.
    Csv,
    /// `x y z` rows of the contact points.
    Xyz,
}

impl std::str::FromStr for Format {
    type Err = anyhow::Error;
    fn from_str(s: &str) -> Result<Self> {
        match s {
            "csv" => Ok(Format::Csv),
            "xyz" => Ok(Format::Xyz),
            other => bail!("--format `{other}`: csv (every point, every field) or xyz (x y z rows of the contact points)"),
        }
    }
}

/// What was exported.
#[derive(Debug, Default)]
pub struct Summary {
    /// Points written.
    pub points: u64,
    /// Of them in contact.
    pub contact: u64,
    /// Segments seen in the output.
    pub segments: BTreeSet<u32>,
    /// Calibration versions seen in the output.
    pub versions: BTreeSet<u64>,
    /// Corrected-point batches that could not be decoded (skipped, counted).
    pub bad_batches: u64,
}

/// Calls `f` with every corrected point of `machine` in the bag, in order; counts batches that
/// do not decode or are malformed (packed columns of unequal lengths).
fn each_point(
    bag: &BagReader,
    machine: &str,
    bad: &mut u64,
    mut f: impl FnMut(&CorrectedPoint) -> Result<()>,
) -> Result<()> {
    for m in bag.messages()? {
        let m = m?;
        if m.stream != Stream::Points || &*m.machine != machine {
            continue;
        }
        match scancorr_proto::v1::CorrectedPointBatch::decode(&*m.data).map(|b| b.into_points()) {
            Ok(Ok(points)) => {
                for p in &points {
                    f(p)?;
                }
            }
            Ok(Err(_)) | Err(_) => *bad += 1,
        }
    }
    Ok(())
}

/// The effects' names in the CSV header: each sanitised ([`header_name`]) and, when two
/// become alike, told apart by `~2`, `~3`, ….
fn header_names(effects: &[String]) -> Vec<String> {
    let mut out: Vec<String> = Vec::with_capacity(effects.len());
    for e in effects {
        let base = header_name(e);
        let mut name = base.clone();
        let mut n = 1;
        while out.contains(&name) {
            n += 1;
            name = format!("{base}~{n}");
        }
        out.push(name);
    }
    out
}

fn v3(v: &Option<scancorr_proto::v1::Vec3>) -> [f64; 3] {
    v.as_ref().map_or([0.0; 3], |v| [v.x, v.y, v.z])
}

/// The machine whose corrected points to export: `machine` if the bag has its points, else
/// the bag's only machine with corrected points.
fn pick_machine(bag: &BagReader, bag_path: &Path, machine: Option<&str>) -> Result<String> {
    let with_points: Vec<String> = bag
        .channels()
        .iter()
        .filter(|c| c.stream == Stream::Points)
        .map(|c| c.machine.clone())
        .collect();
    let machine = match (machine, with_points.as_slice()) {
        (_, []) => bail!(
            "{} holds no corrected points (only {}): correct it first, `scancorr correct --bag {} --calib C --out corrected.mcap`",
            bag_path.display(),
            bag.channels()
                .iter()
                .map(|c| c.topic.as_str())
                .collect::<Vec<_>>()
                .join(", "),
            bag_path.display()
        ),
        (Some(m), list) if list.iter().any(|x| x == m) => m.to_string(),
        (Some(m), list) => bail!(
            "--machine {m}: no corrected points of it in {} (machines: {})",
            bag_path.display(),
            list.join(", ")
        ),
        (None, [one]) => one.clone(),
        (None, list) => bail!(
            "{} holds the corrected points of {} machines ({}): name one with --machine",
            bag_path.display(),
            list.len(),
            list.join(", ")
        ),
    };
    Ok(machine)
}

/// The CSV header: the fixed columns, then per effect its correction's columns.
fn csv_header(effects: &[String]) -> String {
    let mut head = String::from(
        "machine,seq,t_ns,segment_id,tip_id,calibration_version,estimator_valid,contact,\
         surface_x_mm,surface_y_mm,surface_z_mm,tip_center_x_mm,tip_center_y_mm,\
         tip_center_z_mm,normal_x,normal_y,normal_z",
    );
    for e in header_names(effects) {
        for a in ["dx", "dy", "dz"] {
            head += &format!(",{}", csv_text(&format!("{e}_{a}_mm")));
        }
    }
    head
}

/// Reports the export on stderr (and any batches that could not be decoded).
fn report(machine: &str, written: u64, sum: &Summary, out: &Path) {
    if sum.bad_batches > 0 {
        eprintln!(
            "warning: {} corrected-point batch(es) of {machine} could not be decoded and were skipped",
            sum.bad_batches
        );
    }
    eprintln!(
        "exported {written} point(s) of machine {machine} ({} in contact of {} corrected; segments {}; calibration version(s) {}) → {}",
        sum.contact,
        sum.points,
        compact(&sum.segments),
        sum.versions
            .iter()
            .map(|v| v.to_string())
            .collect::<Vec<_>>()
            .join(", "),
        out.display()
    );
}

/// Runs the export.
pub fn run(
    bag_path: &Path,
    format: &str,
    segment: Option<u32>,
    machine: Option<&str>,
    out: &Path,
) -> Result<()> {
    let format: Format = format.parse()?;
    refuse_same_file(&[("--out", out)], &[("--bag", bag_path)])?;
    let bag = BagReader::open(bag_path).with_context(|| format!("--bag {}", bag_path.display()))?;
    let machine = pick_machine(&bag, bag_path, machine)?;
    let keep = |p: &CorrectedPoint| segment.is_none_or(|s| p.segment_id == s);
    // First pass: which effects, which segments (to name them when the one asked for is not
    // there).
    let mut effects: Vec<String> = vec![];
    let mut all_segments = BTreeSet::new();
    let mut bad = 0;
    each_point(&bag, &machine, &mut bad, |p| {
        all_segments.insert(p.segment_id);
        if keep(p) {
            for c in &p.corrections {
                if !effects.iter().any(|e| *e == c.effect) {
                    effects.push(c.effect.clone());
                }
            }
        }
        Ok(())
    })?;
    if let Some(s) = segment {
        if !all_segments.contains(&s) {
            bail!(
                "--segment {s}: no corrected point of segment {s} in {} (segments: {})",
                bag_path.display(),
                compact(&all_segments)
            );
        }
    }
    let file = AtomicOutput::new("--out", out)?;
    let mut w = BufWriter::new(file.stream()?);
    let mut sum = Summary::default();
    let mut bad2 = 0;
    match format {
        Format::Csv => {
            writeln!(w, "{}", csv_header(&effects))?;
            let m = csv_text(&machine);
            each_point(&bag, &machine, &mut bad2, |p| {
                if !keep(p) {
                    return Ok(());
                }
                let n = v3(&p.normal);
                let contact = n.iter().any(|x| *x != 0.0);
                let (s, t) = (v3(&p.surface), v3(&p.tip_center));
                write!(
                    w,
                    "{m},{},{},{},{},{},{},{},{},{},{},{},{},{},{},{},{}",
                    p.seq,
                    p.t_ns,
                    p.segment_id,
                    p.tip_id,
                    p.calibration_version,
                    u8::from(p.estimator_valid),
                    u8::from(contact),
                    s[0],
                    s[1],
                    s[2],
                    t[0],
                    t[1],
                    t[2],
                    n[0],
                    n[1],
                    n[2]
                )?;
                for e in &effects {
                    match p.corrections.iter().find(|c| c.effect == *e) {
                        Some(c) => write!(w, ",{},{},{}", c.dx, c.dy, c.dz)?,
                        None => write!(w, ",,,")?,
                    }
                }
                writeln!(w)?;
                sum.points += 1;
                sum.contact += u64::from(contact);
                sum.segments.insert(p.segment_id);
                sum.versions.insert(p.calibration_version);
                Ok(())
            })?;
        }
        Format::Xyz => {
            writeln!(
                w,
                "# scancorr export: corrected surface points in contact, mm (x y z), machine {}, {}",
                one_line(&machine),
                match segment {
                    Some(s) => format!("segment {s}"),
                    None => "every segment".to_string(),
                }
            )?;
            writeln!(w, "# from {}", one_line(&bag_path.display().to_string()))?;
            each_point(&bag, &machine, &mut bad2, |p| {
                if !keep(p) {
                    return Ok(());
                }
                let n = v3(&p.normal);
                sum.points += 1;
                if n.iter().all(|x| *x == 0.0) {
                    return Ok(());
                }
                let s = v3(&p.surface);
                writeln!(w, "{} {} {}", s[0], s[1], s[2])?;
                sum.contact += 1;
                sum.segments.insert(p.segment_id);
                sum.versions.insert(p.calibration_version);
                Ok(())
            })?;
        }
    }
    sum.bad_batches = bad;
    let written = match format {
        Format::Csv => sum.points,
        Format::Xyz => sum.contact,
    };
    if written == 0 {
        bail!(
            "nothing to export: {} points of machine {machine}{} and none in contact",
            sum.points,
            segment
                .map(|s| format!(" in segment {s}"))
                .unwrap_or_default()
        );
    }
    w.flush()?;
    drop(w);
    file.commit()?;
    report(&machine, written, &sum, out);
    Ok(())
}

/// `scancorr export --bag B --raw --out F.csv`: every raw stream of one machine as one wide
/// CSV, its mapping as `F.map.json` and the bag's metadata records as `F.meta.json` beside.
pub fn run_raw(bag_path: &Path, machine: Option<&str>, out: &Path) -> Result<()> {
    let map_path = out.with_extension("map.json");
    let meta_path = out.with_extension("meta.json");
    refuse_same_file(
        &[
            ("--out", out),
            ("the mapping", &map_path),
            ("the records", &meta_path),
        ],
        &[("--bag", bag_path)],
    )?;
    let bag = BagReader::open(bag_path).with_context(|| format!("--bag {}", bag_path.display()))?;
    let mut raw: Vec<String> = vec![];
    for c in bag.channels() {
        if scancorr_bag::import::STREAMS.contains(&c.stream) && !raw.contains(&c.machine) {
            raw.push(c.machine.clone());
        }
    }
    let machine = match (machine, raw.as_slice()) {
        (_, []) => bail!("{} holds no raw stream", bag_path.display()),
        (Some(m), list) if list.iter().any(|x| x == m) => m.to_string(),
        (Some(m), list) => bail!(
            "--machine {m}: no raw stream of it in {} (machines: {})",
            bag_path.display(),
            list.join(", ")
        ),
        (None, [one]) => one.clone(),
        (None, list) => bail!(
            "{} holds the raw streams of {} machines ({}): name one with --machine",
            bag_path.display(),
            list.len(),
            list.join(", ")
        ),
    };
    let file = AtomicOutput::new("--out", out)?;
    let map_file = AtomicOutput::new("the mapping", &map_path)?;
    let records: Vec<scancorr_bag::import::Record> = bag
        .metadata()
        .iter()
        .map(|m| scancorr_bag::import::Record {
            name: m.name.clone(),
            entries: m.entries.clone(),
        })
        .collect();
    let meta_file = (!records.is_empty())
        .then(|| AtomicOutput::new("the records", &meta_path))
        .transpose()?;
    let mut w = file.file()?;
    let ex = scancorr_bag::import::export_wide(&bag, &machine, &mut w)
        .with_context(|| format!("{}: the raw streams of {machine}", bag_path.display()))?;
    drop(w);
    map_file.write_all(serde_json::to_string_pretty(&ex.mapping)? + "\n")?;
    if let Some(f) = &meta_file {
        f.write_all(serde_json::to_string_pretty(&records)? + "\n")?;
    }
    file.commit()?;
    map_file.commit()?;
    if let Some(f) = meta_file {
        f.commit()?;
    }
    if ex.bad_batches > 0 {
        eprintln!(
            "warning: {} raw batch(es) of {machine} could not be decoded and were left out (first: {})",
            ex.bad_batches,
            ex.first_bad_batch.as_deref().unwrap_or("")
        );
    }
    if ex.foreign_samples > 0 {
        eprintln!(
            "warning: {} sample(s) inside {machine}'s batches name another machine and were left out",
            ex.foreign_samples
        );
    }
    let samples: Vec<String> = ex.samples.iter().map(|(k, v)| format!("{k} {v}")).collect();
    eprintln!(
        "exported {} row(s) of machine {machine}'s raw streams ({}) → {}, mapping {}{}; read back with `scancorr import --csv {} --map {}{} --out B.mcap`",
        ex.rows,
        samples.join(", "),
        out.display(),
        map_path.display(),
        if records.is_empty() {
            String::new()
        } else {
            format!(", records {}", meta_path.display())
        },
        out.display(),
        map_path.display(),
        if records.is_empty() {
            String::new()
        } else {
            format!(" --artifacts {}", meta_path.display())
        },
    );
    Ok(())
}

/// `1–4, 7, 9–10`.
fn compact(s: &BTreeSet<u32>) -> String {
    let mut out: Vec<String> = vec![];
    let mut it = s.iter().copied().peekable();
    while let Some(a) = it.next() {
        let mut b = a;
        while it.peek() == Some(&(b + 1)) {
            b = it.next().unwrap_or(b);
        }
        out.push(if a == b {
            a.to_string()
        } else {
            format!("{a}–{b}")
        });
    }
    out.join(", ")
}

/// `scancorr export`: the corrected points as CSV / x y z, or (`--raw`) the raw streams.
pub fn exec(
    bag: PathBuf,
    format: String,
    segment: Option<u32>,
    machine: Option<String>,
    out: PathBuf,
    raw: bool,
) -> Result<()> {
    if let Some(m) = &machine {
        crate::shared::output::check_machine("--machine", m)?;
    }
    if raw {
        anyhow::ensure!(
            segment.is_none() && format == "csv",
            "--raw exports every raw stream as CSV: without --segment or --format"
        );
        return run_raw(&bag, machine.as_deref(), &out);
    }
    run(&bag, &format, segment, machine.as_deref(), &out)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn ranges_and_fields() {
        let s: BTreeSet<u32> = [1, 2, 3, 4, 7, 9, 10].into_iter().collect();
        assert_eq!(compact(&s), "1–4, 7, 9–10");
        assert_eq!(compact(&BTreeSet::new()), "");
        assert_eq!(csv_text("m1"), "m1");
        assert_eq!(csv_text("a,\"b\""), "\"a,\"\"b\"\"\"");
        assert_eq!(csv_text("=1+2"), "\"'=1+2\"");
        assert_eq!(
            header_names(&["a,b".into(), "a_b".into(), "x\ny".into()]),
            ["a_b", "a_b~2", "x_y"]
        );
        assert!("tsv".parse::<Format>().is_err());
    }
}
