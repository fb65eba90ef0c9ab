//! The mapping of a table's columns onto the wire contract's streams: which column is the
//! time, which columns (or constants) are each stream's fields, and the units they are in.
//!
//! Its JSON form is the mapping file of `scancorr import --map` (and what `scancorr export
//! --raw` writes beside its table); [`Mapping::set`] and [`Mapping::set_unit`] build or amend
//! one from `stream.field=COLUMN` specifications.
use scancorr_proto::names;
use serde::{Deserialize, Serialize};
use std::collections::BTreeMap;
use std::fmt;

/// Where a field's values come from: a column of the table (its header name) or a constant
/// (a number in the mapping, in the stream's unit).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(untagged)]
pub enum Source {
    /// The column with this header name.
    Column(String),
    /// The same value on every sample.
    Constant(f64),
}

impl Source {
    fn column(&self) -> Option<&str> {
        match self {
            Source::Column(c) => Some(c),
            Source::Constant(_) => None,
        }
    }
}

/// The unit of the time column; times are stored as integer nanoseconds (`t_ns`).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
pub enum TimeUnit {
    /// Seconds.
    #[serde(rename = "s")]
    S,
    /// Milliseconds.
    #[serde(rename = "ms")]
    Ms,
    /// Microseconds.
    #[serde(rename = "us", alias = "µs")]
    Us,
    /// Nanoseconds.
    #[serde(rename = "ns")]
    Ns,
}

impl TimeUnit {
    /// Powers of ten from the unit to ns.
    pub(crate) fn exponent(self) -> i32 {
        match self {
            TimeUnit::S => 9,
            TimeUnit::Ms => 6,
            TimeUnit::Us => 3,
            TimeUnit::Ns => 0,
        }
    }
}

impl std::str::FromStr for TimeUnit {
    type Err = String;
    fn from_str(s: &str) -> Result<Self, String> {
        match s {
            "s" => Ok(TimeUnit::S),
            "ms" => Ok(TimeUnit::Ms),
            "us" | "µs" => Ok(TimeUnit::Us),
            "ns" => Ok(TimeUnit::Ns),
            _ => Err(format!("time unit `{s}`: s, ms, us or ns")),
        }
    }
}

/// The unit of a stream's lengths; stored in mm.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, Serialize, Deserialize)]
pub enum LengthUnit {
    /// Millimetres (the wire contract's unit).
    #[default]
    #[serde(rename = "mm")]
    Mm,
    /// Micrometres.
    #[serde(rename = "um", alias = "µm")]
    Um,
    /// Metres.
    #[serde(rename = "m")]
    M,
    /// Inches (25.4 mm).
    #[serde(rename = "in")]
    In,
}

impl LengthUnit {
    /// `v` in mm. Micrometres are divided by 1000 (correctly rounded, where multiplying by
    /// 0.001 would round twice); mm are taken as they are, bit for bit.
    pub(crate) fn to_mm(self, v: f64) -> f64 {
        match self {
            LengthUnit::Mm => v,
            LengthUnit::Um => v / 1000.0,
            LengthUnit::M => v * 1000.0,
            LengthUnit::In => v * 25.4,
        }
    }
}

impl std::str::FromStr for LengthUnit {
    type Err = String;
    fn from_str(s: &str) -> Result<Self, String> {
        match s {
            "mm" => Ok(LengthUnit::Mm),
            "um" | "µm" => Ok(LengthUnit::Um),
            "m" => Ok(LengthUnit::M),
            "in" => Ok(LengthUnit::In),
            _ => Err(format!("length unit `{s}`: mm, um, m or in")),
        }
    }
}

/// The unit of the temperatures; stored in °C.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, Serialize, Deserialize)]
pub enum TemperatureUnit {
    /// Degrees Celsius (the wire contract's unit).
    #[default]
    C,
    /// Kelvin.
    K,
}

impl TemperatureUnit {
    pub(crate) fn to_celsius(self, v: f64) -> f64 {
        match self {
            TemperatureUnit::C => v,
            TemperatureUnit::K => v - 273.15,
        }
    }
}

impl std::str::FromStr for TemperatureUnit {
    type Err = String;
    fn from_str(s: &str) -> Result<Self, String> {
        match s {
            "C" => Ok(TemperatureUnit::C),
            "K" => Ok(TemperatureUnit::K),
            _ => Err(format!("temperature unit `{s}`: C or K")),
        }
    }
}

/// The time column.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct TimeColumn {
    /// Its header name.
    pub column: String,
    /// Its unit.
    pub unit: TimeUnit,
    /// Added to every time after the conversion to ns (e.g. the controller clock at the
    /// table's time zero).
    #[serde(default, skip_serializing_if = "is_zero")]
    pub offset_ns: i64,
}

fn is_zero(v: &i64) -> bool {
    *v == 0
}

/// The command stream (`CommandSample`): x, y, z required; the arc (all four or none) and
/// the segment id optional (0 when not mapped).
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
#[allow(missing_docs)]
pub struct CommandMap {
    /// Unit of every length of the stream (columns and constants).
    #[serde(default)]
    pub unit: LengthUnit,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub x: Option<Source>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub y: Option<Source>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub z: Option<Source>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub arc_cx: Option<Source>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub arc_cy: Option<Source>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub arc_cz: Option<Source>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub arc_radius: Option<Source>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub segment_id: Option<Source>,
    /// Largest time between two samples, s (overrides the mapping's `max_gap_s`).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub max_gap_s: Option<f64>,
}

/// The scale stream (`ScaleSample`): x, y, z required.
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
#[allow(missing_docs)]
pub struct ScaleMap {
    /// Unit of every length of the stream.
    #[serde(default)]
    pub unit: LengthUnit,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub x: Option<Source>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub y: Option<Source>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub z: Option<Source>,
    /// Largest time between two samples, s.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub max_gap_s: Option<f64>,
}

/// The probe stream (`ProbeSample`): the deflection u, v, w required (in the stream's unit);
/// the tip id and the head angles (degrees, never converted) optional, 0 when not mapped.
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
#[allow(missing_docs)]
pub struct ProbeMap {
    /// Unit of the deflection.
    #[serde(default)]
    pub unit: LengthUnit,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub u: Option<Source>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub v: Option<Source>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub w: Option<Source>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub tip_id: Option<Source>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub head_a1_deg: Option<Source>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub head_a2_deg: Option<Source>,
    /// Largest time between two samples, s.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub max_gap_s: Option<f64>,
}

/// The temperature stream (`TemperatureSample`): one column per sensor.
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct TemperatureMap {
    /// Unit of every sensor's column.
    #[serde(default)]
    pub unit: TemperatureUnit,
    /// Sensor name (the project's name grammar) → column.
    #[serde(default)]
    pub sensors: BTreeMap<String, String>,
    /// Largest time between two readings of a sensor, s.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub max_gap_s: Option<f64>,
}

/// One distance probe: its reading's column, and its spacing (a column or a constant; 0
/// when not given).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(untagged)]
pub enum DistanceProbe {
    /// The reading's column alone.
    Column(String),
    /// The reading's column and the spacing.
    With(DistanceColumns),
}

/// A distance probe's reading and spacing.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct DistanceColumns {
    /// The reading's column.
    pub column: String,
    /// The probe's spacing along the travel, in the stream's unit.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub spacing: Option<Source>,
}

impl DistanceProbe {
    fn column(&self) -> &str {
        match self {
            DistanceProbe::Column(c) => c,
            DistanceProbe::With(d) => &d.column,
        }
    }
    fn spacing(&self) -> Option<&Source> {
        match self {
            DistanceProbe::Column(_) => None,
            DistanceProbe::With(d) => d.spacing.as_ref(),
        }
    }
}

/// The distance stream (`DistanceSample`, v1.2): one column per probe id.
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct DistanceMap {
    /// Unit of the readings and spacings.
    #[serde(default)]
    pub unit: LengthUnit,
    /// Probe id → its column (or column and spacing).
    #[serde(default)]
    pub probes: BTreeMap<u32, DistanceProbe>,
    /// Largest time between two readings of a probe, s.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub max_gap_s: Option<f64>,
}

/// The micro-stage stream (`StageSample`, v1.2): commanded and sensor required, the probe id
/// optional (0 when not mapped).
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
#[allow(missing_docs)]
pub struct StageMap {
    /// Unit of both positions.
    #[serde(default)]
    pub unit: LengthUnit,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub commanded: Option<Source>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub sensor: Option<Source>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub probe_id: Option<Source>,
    /// Largest time between two samples, s.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub max_gap_s: Option<f64>,
}

/// A table's columns mapped onto the streams of one machine (the mapping file).
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Mapping {
    /// The machine id (the project's name grammar); the command line may give or override it.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub machine: Option<String>,
    /// The time column (required).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub time: Option<TimeColumn>,
    /// Largest time between two samples of any stream, s (a stream's own `max_gap_s` wins).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub max_gap_s: Option<f64>,
    /// `raw/command`.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub command: Option<CommandMap>,
    /// `raw/scale`.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub scale: Option<ScaleMap>,
    /// `raw/probe`.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub probe: Option<ProbeMap>,
    /// `raw/temperature`.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub temperature: Option<TemperatureMap>,
    /// `raw/distance`.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub distance: Option<DistanceMap>,
    /// `raw/stage`.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub stage: Option<StageMap>,
}

/// A mapping that cannot be used, or a specification that does not parse; says which field.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct MappingError(pub String);

impl fmt::Display for MappingError {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(&self.0)
    }
}

impl std::error::Error for MappingError {}

fn err<T>(s: impl Into<String>) -> Result<T, MappingError> {
    Err(MappingError(s.into()))
}

/// The fields of each stream as `stream.field` names, for messages.
const COMMAND_FIELDS: [&str; 8] = [
    "x",
    "y",
    "z",
    "arc_cx",
    "arc_cy",
    "arc_cz",
    "arc_radius",
    "segment_id",
];
const SCALE_FIELDS: [&str; 3] = ["x", "y", "z"];
const PROBE_FIELDS: [&str; 6] = ["u", "v", "w", "tip_id", "head_a1_deg", "head_a2_deg"];
const STAGE_FIELDS: [&str; 3] = ["commanded", "sensor", "probe_id"];

impl Mapping {
    /// Sets one field from a specification's path: `command.x`, `scale.y`, `probe.tip_id`,
    /// `temperature.<sensor>`, `distance.<probe id>`, `distance.<probe id>.spacing`,
    /// `stage.sensor`… Temperatures and distance readings take columns only.
    pub fn set(&mut self, path: &str, source: Source) -> Result<(), MappingError> {
        let (stream, field) = path.split_once('.').ok_or_else(|| {
            MappingError(format!(
                "`{path}`: expected STREAM.FIELD (command, scale, probe, temperature, distance, stage)"
            ))
        })?;
        let unknown = |fields: &[&str]| {
            err(format!(
                "`{path}`: {stream} has no field `{field}` (fields: {})",
                fields.join(", ")
            ))
        };
        let column_only = |what: &str| -> Result<String, MappingError> {
            match &source {
                Source::Column(c) => Ok(c.clone()),
                Source::Constant(_) => err(format!("`{path}`: {what} must be a column")),
            }
        };
        match stream {
            "command" => {
                let m = self.command.get_or_insert_with(Default::default);
                let slot = match field {
                    "x" => &mut m.x,
                    "y" => &mut m.y,
                    "z" => &mut m.z,
                    "arc_cx" => &mut m.arc_cx,
                    "arc_cy" => &mut m.arc_cy,
                    "arc_cz" => &mut m.arc_cz,
                    "arc_radius" => &mut m.arc_radius,
                    "segment_id" => &mut m.segment_id,
                    _ => return unknown(&COMMAND_FIELDS),
                };
                *slot = Some(source);
            }
            "scale" => {
                let m = self.scale.get_or_insert_with(Default::default);
                let slot = match field {
                    "x" => &mut m.x,
                    "y" => &mut m.y,
                    "z" => &mut m.z,
                    _ => return unknown(&SCALE_FIELDS),
                };
                *slot = Some(source);
            }
            "probe" => {
                let m = self.probe.get_or_insert_with(Default::default);
                let slot = match field {
                    "u" => &mut m.u,
                    "v" => &mut m.v,
                    "w" => &mut m.w,
                    "tip_id" => &mut m.tip_id,
                    "head_a1_deg" => &mut m.head_a1_deg,
                    "head_a2_deg" => &mut m.head_a2_deg,
                    _ => return unknown(&PROBE_FIELDS),
                };
                *slot = Some(source);
            }
            "stage" => {
                let m = self.stage.get_or_insert_with(Default::default);
                let slot = match field {
                    "commanded" => &mut m.commanded,
                    "sensor" => &mut m.sensor,
                    "probe_id" => &mut m.probe_id,
                    _ => return unknown(&STAGE_FIELDS),
                };
                *slot = Some(source);
            }
            "temperature" => {
                let column = column_only("a temperature sensor")?;
                names::check("sensor name", field)
                    .map_err(|e| MappingError(format!("`{path}`: {e}")))?;
                let m = self.temperature.get_or_insert_with(Default::default);
                m.sensors.insert(field.to_string(), column);
            }
            "distance" => {
                let (id, rest) = match field.split_once('.') {
                    Some((id, rest)) => (id, Some(rest)),
                    None => (field, None),
                };
                let id: u32 = id.parse().map_err(|_| {
                    MappingError(format!(
                        "`{path}`: `{id}` is not a probe id (a whole number from 0)"
                    ))
                })?;
                let m = self.distance.get_or_insert_with(Default::default);
                match rest {
                    None => {
                        let column = column_only("a distance probe's reading")?;
                        let spacing = m.probes.get(&id).and_then(|p| p.spacing().cloned());
                        m.probes.insert(id, probe_entry(column, spacing));
                    }
                    Some("spacing") => {
                        let Some(p) = m.probes.get(&id) else {
                            return err(format!(
                                "`{path}`: map distance.{id}=COLUMN (the reading) before its spacing"
                            ));
                        };
                        let column = p.column().to_string();
                        m.probes.insert(id, probe_entry(column, Some(source)));
                    }
                    Some(other) => {
                        return err(format!(
                            "`{path}`: a distance probe has no field `{other}` (distance.{id} is its reading, distance.{id}.spacing its spacing)"
                        ))
                    }
                }
            }
            _ => {
                return err(format!(
                    "`{path}`: no stream `{stream}` (command, scale, probe, temperature, distance, stage)"
                ))
            }
        }
        Ok(())
    }

    /// Sets a stream's unit: `command`, `scale`, `probe`, `distance`, `stage` take a length
    /// unit (mm, um, m, in), `temperature` C or K.
    pub fn set_unit(&mut self, stream: &str, unit: &str) -> Result<(), MappingError> {
        let length = || unit.parse::<LengthUnit>().map_err(MappingError);
        match stream {
            "command" => self.command.get_or_insert_with(Default::default).unit = length()?,
            "scale" => self.scale.get_or_insert_with(Default::default).unit = length()?,
            "probe" => self.probe.get_or_insert_with(Default::default).unit = length()?,
            "distance" => self.distance.get_or_insert_with(Default::default).unit = length()?,
            "stage" => self.stage.get_or_insert_with(Default::default).unit = length()?,
            "temperature" => {
                self.temperature.get_or_insert_with(Default::default).unit =
                    unit.parse().map_err(MappingError)?
            }
            _ => {
                return err(format!(
                    "unit of `{stream}`: no such stream (command, scale, probe, temperature, distance, stage)"
                ))
            }
        }
        Ok(())
    }

    /// Checks everything that does not depend on the table: a time column, each mapped
    /// stream's required fields and at least one column per stream, the arc all or nothing,
    /// constants finite (ids whole numbers), gaps positive, names in the project's grammar.
    pub fn check(&self) -> Result<(), MappingError> {
        if let Some(m) = &self.machine {
            names::check_machine(m).map_err(|e| MappingError(format!("machine: {e}")))?;
        }
        if self.time.as_ref().is_none_or(|t| t.column.is_empty()) {
            return err("no time column: give time.column and time.unit (s, ms, us, ns)");
        }
        if self.streams().is_empty() {
            return err(
                "no stream is mapped: map at least one of command, scale, probe, temperature, distance, stage",
            );
        }
        check_gap("max_gap_s", self.max_gap_s)?;
        for s in self.streams() {
            check_gap(&format!("{}.max_gap_s", s.name), s.max_gap_s)?;
            for (field, required, kind) in &s.fields {
                let path = format!("{}.{field}", s.name);
                match s.get(field) {
                    None if *required => {
                        return err(format!("`{path}` is not mapped (a column or a constant)"))
                    }
                    None => {}
                    Some(Source::Column(c)) if c.is_empty() => {
                        return err(format!("`{path}`: an empty column name"))
                    }
                    Some(Source::Column(_)) => {}
                    Some(Source::Constant(v)) => check_constant(&path, *v, *kind)?,
                }
            }
            if s.columns().next().is_none() {
                return err(format!(
                    "`{}` has no column: a stream needs at least one column (its samples are the rows where its columns are filled)",
                    s.name
                ));
            }
        }
        if let Some(c) = &self.command {
            let arc = [&c.arc_cx, &c.arc_cy, &c.arc_cz, &c.arc_radius];
            let n = arc.iter().filter(|a| a.is_some()).count();
            if n != 0 && n != 4 {
                return err(
                    "command: map the arc's four fields (arc_cx, arc_cy, arc_cz, arc_radius) or none",
                );
            }
        }
        if let Some(t) = &self.temperature {
            for (name, col) in &t.sensors {
                names::check("sensor name", name)
                    .map_err(|e| MappingError(format!("temperature.sensors: {e}")))?;
                if col.is_empty() {
                    return err(format!("temperature.sensors.{name}: an empty column name"));
                }
            }
        }
        if let Some(d) = &self.distance {
            for (id, p) in &d.probes {
                if p.column().is_empty() {
                    return err(format!("distance.probes.{id}: an empty column name"));
                }
                match p.spacing() {
                    Some(Source::Constant(v)) => {
                        check_constant(&format!("distance.probes.{id}.spacing"), *v, Kind::Length)?
                    }
                    Some(Source::Column(c)) if c.is_empty() => {
                        return err(format!(
                            "distance.probes.{id}.spacing: an empty column name"
                        ))
                    }
                    _ => {}
                }
            }
        }
        Ok(())
    }

    /// The mapped streams with their fields, in stream order (for checks and planning).
    pub(crate) fn streams(&self) -> Vec<StreamFields<'_>> {
        let mut out = vec![];
        if let Some(m) = &self.command {
            out.push(StreamFields {
                name: "command",
                max_gap_s: m.max_gap_s,
                fields: vec![
                    ("x", true, Kind::Length),
                    ("y", true, Kind::Length),
                    ("z", true, Kind::Length),
                    ("arc_cx", false, Kind::Length),
                    ("arc_cy", false, Kind::Length),
                    ("arc_cz", false, Kind::Length),
                    ("arc_radius", false, Kind::Length),
                    ("segment_id", false, Kind::Id),
                ],
                values: vec![
                    &m.x,
                    &m.y,
                    &m.z,
                    &m.arc_cx,
                    &m.arc_cy,
                    &m.arc_cz,
                    &m.arc_radius,
                    &m.segment_id,
                ],
                extra: vec![],
            });
        }
        if let Some(m) = &self.scale {
            out.push(StreamFields {
                name: "scale",
                max_gap_s: m.max_gap_s,
                fields: vec![
                    ("x", true, Kind::Length),
                    ("y", true, Kind::Length),
                    ("z", true, Kind::Length),
                ],
                values: vec![&m.x, &m.y, &m.z],
                extra: vec![],
            });
        }
        if let Some(m) = &self.probe {
            out.push(StreamFields {
                name: "probe",
                max_gap_s: m.max_gap_s,
                fields: vec![
                    ("u", true, Kind::Length),
                    ("v", true, Kind::Length),
                    ("w", true, Kind::Length),
                    ("tip_id", false, Kind::Id),
                    ("head_a1_deg", false, Kind::Plain),
                    ("head_a2_deg", false, Kind::Plain),
                ],
                values: vec![&m.u, &m.v, &m.w, &m.tip_id, &m.head_a1_deg, &m.head_a2_deg],
                extra: vec![],
            });
        }
        if let Some(m) = &self.temperature {
            out.push(StreamFields {
                name: "temperature",
                max_gap_s: m.max_gap_s,
                fields: vec![],
                values: vec![],
                extra: m.sensors.values().cloned().collect(),
            });
        }
        if let Some(m) = &self.distance {
            out.push(StreamFields {
                name: "distance",
                max_gap_s: m.max_gap_s,
                fields: vec![],
                values: vec![],
                extra: m.probes.values().map(|p| p.column().to_string()).collect(),
            });
        }
        if let Some(m) = &self.stage {
            out.push(StreamFields {
                name: "stage",
                max_gap_s: m.max_gap_s,
                fields: vec![
                    ("commanded", true, Kind::Length),
                    ("sensor", true, Kind::Length),
                    ("probe_id", false, Kind::Id),
                ],
                values: vec![&m.commanded, &m.sensor, &m.probe_id],
                extra: vec![],
            });
        }
        out
    }

    /// Every column the mapping names (time first), with the field that names it.
    pub(crate) fn named_columns(&self) -> Vec<(String, String)> {
        let mut out = vec![];
        if let Some(t) = &self.time {
            out.push((t.column.clone(), "time".to_string()));
        }
        for s in self.streams() {
            for ((field, _, _), v) in s.fields.iter().zip(&s.values) {
                if let Some(Source::Column(c)) = v {
                    out.push((c.clone(), format!("{}.{field}", s.name)));
                }
            }
        }
        if let Some(t) = &self.temperature {
            for (name, c) in &t.sensors {
                out.push((c.clone(), format!("temperature.{name}")));
            }
        }
        if let Some(d) = &self.distance {
            for (id, p) in &d.probes {
                out.push((p.column().to_string(), format!("distance.{id}")));
                if let Some(Source::Column(c)) = p.spacing() {
                    out.push((c.clone(), format!("distance.{id}.spacing")));
                }
            }
        }
        out
    }
}

fn probe_entry(column: String, spacing: Option<Source>) -> DistanceProbe {
    match spacing {
        None => DistanceProbe::Column(column),
        Some(s) => DistanceProbe::With(DistanceColumns {
            column,
            spacing: Some(s),
        }),
    }
}

fn check_gap(what: &str, g: Option<f64>) -> Result<(), MappingError> {
    match g {
        Some(g) if !(g.is_finite() && g > 0.0) => {
            err(format!("{what}: {g} is not a positive number of seconds"))
        }
        _ => Ok(()),
    }
}

fn check_constant(path: &str, v: f64, kind: Kind) -> Result<(), MappingError> {
    if !v.is_finite() {
        return err(format!("`{path}`: the constant {v} is not a finite number"));
    }
    if kind == Kind::Id && crate::import::number::as_id(v).is_none() {
        return err(format!(
            "`{path}`: the constant {v} is not a whole number from 0 to {}",
            u32::MAX
        ));
    }
    Ok(())
}

/// How a field's values are converted.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub(crate) enum Kind {
    /// A length in the stream's unit.
    Length,
    /// Taken as it is (degrees).
    Plain,
    /// A whole number 0..=u32::MAX (tip, segment, probe ids).
    Id,
}

/// One mapped stream's fixed fields (temperature and distance have theirs in `extra`).
pub(crate) struct StreamFields<'a> {
    pub name: &'static str,
    pub max_gap_s: Option<f64>,
    /// (field, required, kind).
    pub fields: Vec<(&'static str, bool, Kind)>,
    pub values: Vec<&'a Option<Source>>,
    /// The columns of the sensors or distance probes.
    pub extra: Vec<String>,
}

impl StreamFields<'_> {
    fn get(&self, field: &str) -> Option<&Source> {
        let i = self.fields.iter().position(|(f, _, _)| *f == field)?;
        self.values[i].as_ref()
    }
    fn columns(&self) -> impl Iterator<Item = &str> {
        self.values
            .iter()
            .filter_map(|v| v.as_ref().and_then(Source::column))
            .chain(self.extra.iter().map(String::as_str))
    }
}
