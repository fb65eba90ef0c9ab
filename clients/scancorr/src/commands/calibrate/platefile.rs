//! Plate measurement files for `scancorr calibrate plate`, in two formats:
//!
//! * `plug-plate` — the CMM's output for SDSS plug plates (the UW shop's `D<plate>…`
//!   files): header lines `Plug Plate: <id>`, `Date: <date>` (blank lines and `#` comments
//!   allowed), the column header `Meas X  Meas Y  Nom X  Nom Y  Err X  Err Y  Meas D  Nom D
//!   Round`, then one row of those nine numbers (mm) per hole. Holes are named by their row
//!   (1, 2, …).
//! * `csv` — a header naming the columns `id,nominal_x,nominal_y,measured_x,measured_y`
//!   (mm, any order) and optionally `nominal_d,measured_d` (an empty diameter cell: unknown),
//!   then one row per feature; `#` lines and blank lines are not rows.
//!
//! Every bad row is an error naming the file, the line and the column (a non-number, a
//! missing column, a column too many): no row is skipped silently.

use anyhow::{bail, Context, Result};
use scancorr_core::calibrate::plate::Feature;
use std::collections::HashMap;
use std::path::Path;

/// A file's format.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Format {
    PlugPlate,
    Csv,
}

impl Format {
    pub fn name(self) -> &'static str {
        match self {
            Format::PlugPlate => "plug-plate",
            Format::Csv => "csv",
        }
    }
}

impl std::str::FromStr for Format {
    type Err = anyhow::Error;
    fn from_str(s: &str) -> Result<Format> {
        match s {
            "plug-plate" => Ok(Format::PlugPlate),
            "csv" => Ok(Format::Csv),
            _ => bail!("--format {s}: plug-plate or csv"),
        }
    }
}

/// What a file holds.
#[derive(Debug, Clone)]
pub struct PlateFile {
    pub format: Format,
    /// The plate's id (`Plug Plate:`).
    pub plate: Option<String>,
    /// The measurement's date (`Date:`).
    pub date: Option<String>,
    pub features: Vec<Feature>,
}

/// Reads `path` (`format`: as given, or told from its first line).
pub fn read(path: &Path, format: Option<Format>) -> Result<PlateFile> {
    let text = std::fs::read_to_string(path)
        .with_context(|| format!("cannot read the feature file {}", path.display()))?;
    parse(&path.display().to_string(), &text, format)
}

/// Parses `text`, named `name` in errors.
pub fn parse(name: &str, text: &str, format: Option<Format>) -> Result<PlateFile> {
    let lines: Vec<&str> = text.lines().map(|l| l.trim_end_matches('\r')).collect();
    let format = match format {
        Some(f) => f,
        None => detect(name, &lines)?,
    };
    let f = match format {
        Format::PlugPlate => plug_plate(name, &lines)?,
        Format::Csv => csv(name, &lines)?,
    };
    if f.features.is_empty() {
        bail!("{name}: no feature rows ({} format)", format.name());
    }
    Ok(f)
}

fn skip(line: &str) -> bool {
    let t = line.trim();
    t.is_empty() || t.starts_with('#')
}

fn detect(name: &str, lines: &[&str]) -> Result<Format> {
    let Some(first) = lines.iter().find(|l| !skip(l)) else {
        bail!("{name}: empty (no header, no rows)");
    };
    let t = first.trim().to_ascii_lowercase();
    if t.starts_with("plug plate:") || t.starts_with("date:") || t.starts_with("meas x") {
        Ok(Format::PlugPlate)
    } else if t.contains(',') {
        Ok(Format::Csv)
    } else {
        bail!(
            "{name}: cannot tell the format from its first line `{}`: give --format plug-plate \
             or --format csv",
            first.trim()
        )
    }
}

/// A number in a cell: finite, or an error naming the place.
fn number(name: &str, line: usize, col: usize, head: &str, cell: &str) -> Result<f64> {
    let v: f64 = cell.trim().parse().map_err(|_| {
        anyhow::anyhow!(
            "{name}:{line}: column {col} (`{head}`): `{}` is not a number",
            cell.trim()
        )
    })?;
    if !v.is_finite() {
        bail!(
            "{name}:{line}: column {col} (`{head}`): `{}` is not a finite number",
            cell.trim()
        );
    }
    Ok(v)
}

const PLUG_COLUMNS: [&str; 9] = [
    "Meas X", "Meas Y", "Nom X", "Nom Y", "Err X", "Err Y", "Meas D", "Nom D", "Round",
];

fn plug_plate(name: &str, lines: &[&str]) -> Result<PlateFile> {
    let mut plate = None;
    let mut date = None;
    let mut header = false;
    let mut features = Vec::new();
    for (k, raw) in lines.iter().enumerate() {
        let ln = k + 1;
        if skip(raw) {
            continue;
        }
        let t = raw.trim();
        if !header {
            let lower = t.to_ascii_lowercase();
            if let Some(v) = lower.strip_prefix("plug plate:") {
                plate = Some(t[t.len() - v.len()..].trim().to_string());
            } else if let Some(v) = lower.strip_prefix("date:") {
                date = Some(t[t.len() - v.len()..].trim().to_string());
            } else if lower.starts_with("meas x") {
                header = true;
            } else if t.split_whitespace().all(|c| c.parse::<f64>().is_ok()) {
                bail!(
                    "{name}:{ln}: a hole row before the column header `{}`",
                    PLUG_COLUMNS.join("  ")
                );
            } else {
                bail!(
                    "{name}:{ln}: `{t}` is not a plug-plate header line (`Plug Plate: <id>`, \
                     `Date: <date>`, or the column header `{}`)",
                    PLUG_COLUMNS.join("  ")
                );
            }
            continue;
        }
        let cells: Vec<&str> = t.split_whitespace().collect();
        if cells.len() > PLUG_COLUMNS.len() {
            bail!(
                "{name}:{ln}: column {}: `{}` is one too many (a plug-plate row has {} columns: \
                 {})",
                PLUG_COLUMNS.len() + 1,
                cells[PLUG_COLUMNS.len()],
                PLUG_COLUMNS.len(),
                PLUG_COLUMNS.join(", ")
            );
        }
        let mut v = [0.0; 9];
        for (c, head) in PLUG_COLUMNS.iter().enumerate() {
            let Some(cell) = cells.get(c) else {
                bail!(
                    "{name}:{ln}: column {} (`{head}`) missing: the row has {} of {} columns",
                    c + 1,
                    cells.len(),
                    PLUG_COLUMNS.len()
                );
            };
            v[c] = number(name, ln, c + 1, head, cell)?;
        }
        features.push(Feature {
            id: format!("{}", features.len() + 1),
            nominal_mm: [v[2], v[3]],
            measured_mm: [v[0], v[1]],
            nominal_d_mm: Some(v[7]),
            measured_d_mm: Some(v[6]),
        });
    }
    if !header {
        bail!(
            "{name}: no column header `{}` (is it a plug-plate file? --format csv for a CSV)",
            PLUG_COLUMNS.join("  ")
        );
    }
    Ok(PlateFile {
        format: Format::PlugPlate,
        plate,
        date,
        features,
    })
}

const CSV_REQUIRED: [&str; 5] = ["id", "nominal_x", "nominal_y", "measured_x", "measured_y"];
const CSV_OPTIONAL: [&str; 2] = ["nominal_d", "measured_d"];

fn csv(name: &str, lines: &[&str]) -> Result<PlateFile> {
    let mut rows = lines.iter().enumerate().filter(|(_, l)| !skip(l));
    let Some((hk, hline)) = rows.next() else {
        bail!("{name}: empty (no header, no rows)");
    };
    let hl = hk + 1;
    let heads: Vec<String> = hline
        .split(',')
        .map(|h| h.trim().to_ascii_lowercase())
        .collect();
    let mut at: HashMap<&str, usize> = HashMap::new();
    for (c, h) in heads.iter().enumerate() {
        let known = CSV_REQUIRED
            .iter()
            .chain(CSV_OPTIONAL.iter())
            .find(|k| **k == h.as_str());
        let Some(k) = known else {
            bail!(
                "{name}:{hl}: column {} `{h}` is not a plate column (required: {}; optional: {})",
                c + 1,
                CSV_REQUIRED.join(","),
                CSV_OPTIONAL.join(",")
            );
        };
        if at.insert(k, c).is_some() {
            bail!("{name}:{hl}: column {} `{h}` repeats", c + 1);
        }
    }
    for r in CSV_REQUIRED {
        if !at.contains_key(r) {
            bail!(
                "{name}:{hl}: the header lacks column `{r}` (a plate CSV needs {}; optional: {})",
                CSV_REQUIRED.join(","),
                CSV_OPTIONAL.join(",")
            );
        }
    }
    let mut features = Vec::new();
    let mut seen: HashMap<String, usize> = HashMap::new();
    for (k, raw) in rows {
        let ln = k + 1;
        let cells: Vec<&str> = raw.split(',').collect();
        if cells.len() > heads.len() {
            bail!(
                "{name}:{ln}: column {}: more columns than the header's {}",
                heads.len() + 1,
                heads.len()
            );
        }
        let cell = |key: &str| -> Result<(usize, &str)> {
            let c = at[key];
            match cells.get(c) {
                Some(v) => Ok((c, v)),
                None => bail!(
                    "{name}:{ln}: column {} (`{key}`) missing: the row has {} of {} columns",
                    c + 1,
                    cells.len(),
                    heads.len()
                ),
            }
        };
        let num = |key: &str| -> Result<f64> {
            let (c, v) = cell(key)?;
            if v.trim().is_empty() {
                bail!("{name}:{ln}: column {} (`{key}`) is empty", c + 1);
            }
            number(name, ln, c + 1, key, v)
        };
        let opt = |key: &str| -> Result<Option<f64>> {
            if !at.contains_key(key) {
                return Ok(None);
            }
            let (c, v) = cell(key)?;
            if v.trim().is_empty() {
                Ok(None)
            } else {
                number(name, ln, c + 1, key, v).map(Some)
            }
        };
        let (ic, id) = cell("id")?;
        let id = id.trim().to_string();
        if id.is_empty() {
            bail!("{name}:{ln}: column {} (`id`) is empty", ic + 1);
        }
        if let Some(prev) = seen.insert(id.clone(), ln) {
            bail!("{name}:{ln}: id `{id}` repeats line {prev}");
        }
        features.push(Feature {
            nominal_mm: [num("nominal_x")?, num("nominal_y")?],
            measured_mm: [num("measured_x")?, num("measured_y")?],
            nominal_d_mm: opt("nominal_d")?,
            measured_d_mm: opt("measured_d")?,
            id,
        });
    }
    Ok(PlateFile {
        format: Format::Csv,
        plate: None,
        date: None,
        features,
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn plug_plate_rows_and_header() {
        let t = "Plug Plate: 42\r\nDate: 2020-01-02\r\n\r\n    Meas X    Meas Y     Nom X     Nom Y     Err X     Err Y  Meas D   Nom D   Round\r\n  1.001 2.002 1.000 2.000 0.001 0.002 2.170 2.167 0.004\r\n";
        let f = parse("p", t, None).unwrap();
        assert_eq!(f.format, Format::PlugPlate);
        assert_eq!(f.plate.as_deref(), Some("42"));
        assert_eq!(f.date.as_deref(), Some("2020-01-02"));
        assert_eq!(f.features.len(), 1);
        assert_eq!(f.features[0].measured_mm, [1.001, 2.002]);
        assert_eq!(f.features[0].nominal_d_mm, Some(2.167));
    }

    #[test]
    fn plug_plate_errors_name_line_and_column() {
        let head = "Plug Plate: 1\nDate: 2020-01-02\nMeas X Meas Y Nom X Nom Y Err X Err Y Meas D Nom D Round\n";
        let e = parse("p", &format!("{head}1 2 1 2 0 0 2.1 x 0\n"), None).unwrap_err();
        assert_eq!(
            e.to_string(),
            "p:4: column 8 (`Nom D`): `x` is not a number"
        );
        let e = parse("p", &format!("{head}1 2 1 2 0 0 2.1\n"), None).unwrap_err();
        assert_eq!(
            e.to_string(),
            "p:4: column 8 (`Nom D`) missing: the row has 7 of 9 columns"
        );
        let e = parse("p", &format!("{head}1 2 1 2 0 0 2.1 2 0 9\n"), None).unwrap_err();
        assert!(e.to_string().starts_with("p:4: column 10"), "{e}");
        let e = parse("p", "Plug Plate: 1\n1 2 1 2 0 0 2.1 2 0\n", None).unwrap_err();
        assert!(e.to_string().contains("p:2: a hole row before"), "{e}");
    }

    #[test]
    fn csv_rows_any_order_optional_diameters() {
        let t = "# plate\nmeasured_x,id,nominal_x,nominal_y,measured_y,measured_d\n1.5,a,1,2,2.5,\n3,b,3,4,4,2.2\n";
        let f = parse("c.csv", t, None).unwrap();
        assert_eq!(f.format, Format::Csv);
        assert_eq!(f.features[0].id, "a");
        assert_eq!(f.features[0].measured_mm, [1.5, 2.5]);
        assert_eq!(f.features[0].measured_d_mm, None);
        assert_eq!(f.features[1].measured_d_mm, Some(2.2));
    }

    #[test]
    fn csv_errors_name_line_and_column() {
        let h = "id,nominal_x,nominal_y,measured_x,measured_y\n";
        let e = parse("c", &format!("{h}a,1,2,1.1,abc\n"), None).unwrap_err();
        assert_eq!(
            e.to_string(),
            "c:2: column 5 (`measured_y`): `abc` is not a number"
        );
        let e = parse("c", &format!("{h}a,1,2,1.1\n"), None).unwrap_err();
        assert_eq!(
            e.to_string(),
            "c:2: column 5 (`measured_y`) missing: the row has 4 of 5 columns"
        );
        let e = parse("c", "id,nominal_x,nominal_y,measured_x\na,1,2,3\n", None).unwrap_err();
        assert!(e.to_string().contains("lacks column `measured_y`"), "{e}");
        let e = parse("c", &format!("{h}a,1,2,1,2\na,1,2,1,2\n"), None).unwrap_err();
        assert_eq!(e.to_string(), "c:3: id `a` repeats line 2");
        let e = parse("c", &format!("{h}a,1,2,,2\n"), None).unwrap_err();
        assert_eq!(e.to_string(), "c:2: column 4 (`measured_x`) is empty");
        let e = parse("c", &format!("{h}a,1,2,inf,2\n"), None).unwrap_err();
        assert!(e.to_string().contains("not a finite number"), "{e}");
    }
}
