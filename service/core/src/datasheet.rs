//! What a machine's buyer is given, and the nominal calibration made from it.
//!
//! * A [`DataSheet`] is the machine maker's: per axis the time constant the maker states and
//!   the travel, the controller's streaming period, the machine's id on the bus. Stated
//!   values, not measured ones: `scancorr calibrate dynamics` and `scancorr lab discover`
//!   refit the time constants.
//! * A [`Catalogue`] is the probe and stylus catalogue's: per probe type its own response,
//!   per tip (by the id the controller streams) the stylus as listed — shank, bent limbs,
//!   ball radius, and the material's expansion coefficient where the catalogue states one.
//!   Listed lengths, not qualified ones: `scancorr calibrate tips` measures them.
//!
//! [`nominal`] turns them into a version-1 [`Calibration`] with no effects, validated by
//! [`Calibration::build`] — the start of every procedure and of the model lab. Both documents
//! are human-editable JSON (`deny_unknown_fields`); every refusal names its field.

use crate::calib::{Axes, CalibError, Calibration, Geometry, Limits, Nominal};
use crate::stylus::TipGeometry;
use crate::transfer::TransferFunction;
use serde::{Deserialize, Serialize};
use std::collections::{BTreeMap, BTreeSet};

/// Each axis's time constant when no data sheet is given, s: a value for the nominal
/// refit to start from (`calibrate dynamics` and the lab search a factor of 4 either side,
/// 2.5–40 ms), not a statement about any machine.
pub const DEFAULT_TAU_S: f64 = 0.010;

/// The controller's streaming period when no data sheet is given, s (1 kHz).
pub const DEFAULT_SAMPLE_PERIOD_S: f64 = 0.001;

/// The machine maker's data sheet.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct DataSheet {
    /// The machine's id on the bus (the calibration's `machine_id`).
    pub machine_id: String,
    /// What the sheet is: maker, model, document (free text, informative).
    #[serde(default, skip_serializing_if = "String::is_empty")]
    pub note: String,
    /// The controller's streaming period of the command and scale samples, s; 1e-5 … 0.1 s.
    pub sample_period_s: f64,
    /// Per axis.
    pub axes: SheetAxes,
}

/// The three axes of a [`DataSheet`].
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct SheetAxes {
    /// X axis.
    pub x: SheetAxis,
    /// Y axis.
    pub y: SheetAxis,
    /// Z axis.
    pub z: SheetAxis,
}

/// One axis as its maker states it.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct SheetAxis {
    /// The axis's time constant: its position follows the command as a first-order lag
    /// 1/(τs + 1) (the probe's own response apart), s.
    pub tau_s: f64,
    /// Travel, [min, max] in machine coordinates, mm.
    pub travel_mm: [f64; 2],
}

/// The probe and stylus catalogue.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Catalogue {
    /// What the catalogue is (free text, informative).
    #[serde(default, skip_serializing_if = "String::is_empty")]
    pub note: String,
    /// Per probe type (the name tips refer to), its own response.
    pub probes: BTreeMap<String, CatalogueProbe>,
    /// The styli, one per tip id the controller streams.
    pub tips: Vec<CatalogueStylus>,
}

/// A probe type of a [`Catalogue`].
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct CatalogueProbe {
    /// The probe's own response, a first-order lag, s.
    pub tau_s: f64,
}

/// A stylus as the catalogue lists it (lengths at 20 °C).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct CatalogueStylus {
    /// The tip id the controller streams (`ProbeSample.tip_id`).
    pub id: u32,
    /// Probe type carrying it (a key of `probes`).
    pub probe: String,
    /// Shank length along the probe axis, mm.
    pub l1_mm: f64,
    /// Bent limb l2 (in the probe x–z plane), mm.
    #[serde(default)]
    pub l2_mm: f64,
    /// Bend angle β1 of l2 from the probe axis, degrees.
    #[serde(default)]
    pub beta1_deg: f64,
    /// Bent limb l3 (in the probe y–z plane), mm.
    #[serde(default)]
    pub l3_mm: f64,
    /// Bend angle β2 of l3 from the probe axis, degrees.
    #[serde(default)]
    pub beta2_deg: f64,
    /// Ball radius, mm.
    pub radius_mm: f64,
    /// The stylus material's expansion coefficient, 1/K, where the catalogue states one
    /// (informative: the nominal calibration has no effects; `calibrate tips` measures it).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub alpha_per_k: Option<f64>,
}

/// Why a data sheet or a catalogue was refused, or the calibration made from them.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum SheetError {
    /// Not valid JSON, or not the document's shape (unknown or missing field, wrong type).
    #[error("{doc}, at `{path}`: {msg}")]
    Parse {
        /// `data sheet` or `catalogue`.
        doc: &'static str,
        /// Path of the field.
        path: String,
        /// What is wrong.
        msg: String,
    },
    /// A field has a value no machine or stylus can have.
    #[error("{doc} field `{field}`: {reason}")]
    Invalid {
        /// `data sheet` or `catalogue`.
        doc: &'static str,
        /// Path of the field, e.g. `axes.y.tau_s`.
        field: String,
        /// What is wrong.
        reason: String,
    },
    /// The data sheet names another machine than the one asked for.
    #[error("the data sheet is for machine `{sheet}`, not `{asked}`")]
    WrongMachine {
        /// The data sheet's `machine_id`.
        sheet: String,
        /// The machine asked for.
        asked: String,
    },
    /// The calibration made from them does not validate.
    #[error(transparent)]
    Calibration(#[from] CalibError),
}

fn parse<T: serde::de::DeserializeOwned>(doc: &'static str, text: &str) -> Result<T, SheetError> {
    let mut de = serde_json::Deserializer::from_str(text);
    let v = serde_path_to_error::deserialize(&mut de).map_err(|e| SheetError::Parse {
        doc,
        path: e.path().to_string(),
        msg: e.into_inner().to_string(),
    })?;
    de.end().map_err(|e| SheetError::Parse {
        doc,
        path: ".".into(),
        msg: format!("text after the end of the document ({e})"),
    })?;
    Ok(v)
}

fn positive(doc: &'static str, field: String, v: f64) -> Result<(), SheetError> {
    if v.is_finite() && v > 0.0 {
        Ok(())
    } else {
        Err(SheetError::Invalid {
            doc,
            field,
            reason: "must be a finite number > 0".into(),
        })
    }
}

impl DataSheet {
    /// Parses and validates a data sheet.
    pub fn from_json(text: &str) -> Result<DataSheet, SheetError> {
        let d: DataSheet = parse("data sheet", text)?;
        d.validate()?;
        Ok(d)
    }

    /// Pretty JSON.
    pub fn to_json(&self) -> String {
        serde_json::to_string_pretty(self).expect("a data sheet always serialises")
    }

    /// Checks every value, naming the field.
    pub fn validate(&self) -> Result<(), SheetError> {
        const DOC: &str = "data sheet";
        let bad = |field: &str, reason: &str| SheetError::Invalid {
            doc: DOC,
            field: field.into(),
            reason: reason.into(),
        };
        scancorr_proto::names::check_machine(&self.machine_id)
            .map_err(|e| bad("machine_id", &e.to_string()))?;
        // The calibration's ranges (it must build from the sheet).
        let in_range = |field: &str, v: f64, [lo, hi]: [f64; 2]| {
            crate::checks::in_range(field, v, lo, hi, "s")
                .map_err(|r| bad(field, r.split_once(": ").map_or(r.as_str(), |(_, r)| r)))
        };
        in_range(
            "sample_period_s",
            self.sample_period_s,
            crate::checks::SAMPLE_PERIOD_S,
        )?;
        for (name, a) in self.axes.each() {
            positive(DOC, format!("axes.{name}.tau_s"), a.tau_s)?;
            if a.tau_s >= 10.0 {
                return Err(bad(
                    &format!("axes.{name}.tau_s"),
                    "must be below 10 s (a time constant in seconds, not milliseconds)",
                ));
            }
            in_range(&format!("axes.{name}.tau_s"), a.tau_s, crate::checks::TAU_S)?;
            let [lo, hi] = a.travel_mm;
            if !(lo.is_finite() && hi.is_finite() && lo < hi) {
                return Err(bad(
                    &format!("axes.{name}.travel_mm"),
                    "must be [min, max] with finite min < max",
                ));
            }
        }
        Ok(())
    }
}

impl SheetAxes {
    /// (name, axis) for x, y, z.
    pub fn each(&self) -> [(&'static str, &SheetAxis); 3] {
        [("x", &self.x), ("y", &self.y), ("z", &self.z)]
    }
}

impl Catalogue {
    /// The probes and tips of a calibration as a stylus list: styli qualified by `calibrate
    /// tips`, kept for a new nominal model (e.g. after the drives were retuned). A probe model
    /// that is not a first-order lag is refused, naming it.
    pub fn from_calibration(c: &Calibration) -> Result<Catalogue, SheetError> {
        let probes = c
            .nominal
            .probes
            .iter()
            .map(|(name, tf)| match tf {
                TransferFunction::FirstOrder { tau_s } => {
                    Ok((name.clone(), CatalogueProbe { tau_s: *tau_s }))
                }
                _ => Err(SheetError::Invalid {
                    doc: "calibration",
                    field: format!("nominal.probes.{name}"),
                    reason: "only a first-order probe model (`first_order`) can be taken".into(),
                }),
            })
            .collect::<Result<_, _>>()?;
        let cat = Catalogue {
            note: format!(
                "those of machine {}'s calibration version {}",
                c.machine_id, c.version
            ),
            probes,
            tips: c
                .geometry
                .tips
                .iter()
                .map(|t| CatalogueStylus {
                    id: t.id,
                    probe: t.probe.clone(),
                    l1_mm: t.l1_mm,
                    l2_mm: t.l2_mm,
                    beta1_deg: t.beta1_deg,
                    l3_mm: t.l3_mm,
                    beta2_deg: t.beta2_deg,
                    radius_mm: t.radius_mm,
                    alpha_per_k: None,
                })
                .collect(),
        };
        cat.validate()?;
        Ok(cat)
    }

    /// Parses and validates a catalogue.
    pub fn from_json(text: &str) -> Result<Catalogue, SheetError> {
        let c: Catalogue = parse("catalogue", text)?;
        c.validate()?;
        Ok(c)
    }

    /// Pretty JSON.
    pub fn to_json(&self) -> String {
        serde_json::to_string_pretty(self).expect("a catalogue always serialises")
    }

    /// Checks every value, naming the field.
    pub fn validate(&self) -> Result<(), SheetError> {
        const DOC: &str = "catalogue";
        let bad = |field: String, reason: String| SheetError::Invalid {
            doc: DOC,
            field,
            reason,
        };
        if self.probes.is_empty() {
            return Err(bad(
                "probes".into(),
                "at least one probe type is needed".into(),
            ));
        }
        for (name, p) in &self.probes {
            scancorr_proto::names::check("probe type", name)
                .map_err(|e| bad("probes".into(), e.to_string()))?;
            positive(DOC, format!("probes.{name}.tau_s"), p.tau_s)?;
        }
        if self.tips.is_empty() {
            return Err(bad("tips".into(), "at least one tip is needed".into()));
        }
        let mut ids = BTreeSet::new();
        for (i, s) in self.tips.iter().enumerate() {
            let f = |name: &str| format!("tips[{i}].{name}");
            if !ids.insert(s.id) {
                return Err(bad(f("id"), format!("tip id {} appears twice", s.id)));
            }
            if !self.probes.contains_key(&s.probe) {
                return Err(bad(
                    f("probe"),
                    format!("probe type `{}` is not among `probes`", s.probe),
                ));
            }
            for (name, v) in [("l1_mm", s.l1_mm), ("l2_mm", s.l2_mm), ("l3_mm", s.l3_mm)] {
                if !(v.is_finite() && v >= 0.0) {
                    return Err(bad(f(name), "must be a finite number ≥ 0".into()));
                }
            }
            for (name, v) in [("beta1_deg", s.beta1_deg), ("beta2_deg", s.beta2_deg)] {
                if !v.is_finite() {
                    return Err(bad(f(name), "must be a finite number".into()));
                }
            }
            positive(DOC, f("radius_mm"), s.radius_mm)?;
            if let Some(a) = s.alpha_per_k {
                if !(a.is_finite() && a.abs() < 1e-3) {
                    return Err(bad(
                        f("alpha_per_k"),
                        "must be a finite number of magnitude below 1e-3 per K \
                         (steel is 11.5e-6)"
                            .into(),
                    ));
                }
            }
        }
        Ok(())
    }
}

/// Where the nominal calibration's time constants came from.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize)]
#[serde(rename_all = "snake_case")]
pub enum TauSource {
    /// The data sheet's.
    DataSheet,
    /// [`DEFAULT_TAU_S`], to be fitted.
    Default,
}

/// The nominal calibration of `machine` (or of the data sheet's machine when `machine` is
/// `None`): version 1, no effects; each axis a first-order lag with the data sheet's time
/// constant (without one: [`DEFAULT_TAU_S`], to be fitted), the probes and styli of the
/// catalogue, the data sheet's travel as `limits.travel_mm` (without one: the default limits)
/// and streaming period (without one: `sample_period_s`, or [`DEFAULT_SAMPLE_PERIOD_S`]).
/// `created` stamps it (the core keeps no clock). Validated by [`Calibration::build`].
pub fn nominal(
    machine: Option<&str>,
    sheet: Option<&DataSheet>,
    catalogue: &Catalogue,
    sample_period_s: Option<f64>,
    created: &str,
) -> Result<(Calibration, TauSource), SheetError> {
    if let Some(d) = sheet {
        d.validate()?;
    }
    catalogue.validate()?;
    let machine_id = match (machine, sheet) {
        (Some(m), Some(d)) if m != d.machine_id => {
            return Err(SheetError::WrongMachine {
                sheet: d.machine_id.clone(),
                asked: m.to_string(),
            })
        }
        (Some(m), _) => m.to_string(),
        (None, Some(d)) => d.machine_id.clone(),
        (None, None) => {
            return Err(SheetError::Invalid {
                doc: "data sheet",
                field: "machine_id".into(),
                reason: "no data sheet names the machine: give it".into(),
            })
        }
    };
    let tau = |name: &str| {
        let t = sheet.map_or(DEFAULT_TAU_S, |d| match name {
            "x" => d.axes.x.tau_s,
            "y" => d.axes.y.tau_s,
            _ => d.axes.z.tau_s,
        });
        TransferFunction::FirstOrder { tau_s: t }
    };
    let mut limits = Limits::default();
    if let Some(d) = sheet {
        limits.travel_mm = [d.axes.x.travel_mm, d.axes.y.travel_mm, d.axes.z.travel_mm];
    }
    let c = Calibration {
        machine_id,
        version: 1,
        parent_version: None,
        note: format!(
            "nominal model: {}; styli: {}; no effects",
            match sheet {
                Some(_) => "the data sheet's time constants and travel".to_string(),
                None => format!(
                    "time constants {} ms to be fitted (no data sheet)",
                    DEFAULT_TAU_S * 1e3
                ),
            },
            if catalogue.note.is_empty() {
                "the catalogue's"
            } else {
                &catalogue.note
            }
        ),
        created: created.to_string(),
        sample_period_s: sample_period_s
            .or(sheet.map(|d| d.sample_period_s))
            .unwrap_or(DEFAULT_SAMPLE_PERIOD_S),
        nominal: Nominal {
            axes: Axes {
                x: tau("x"),
                y: tau("y"),
                z: tau("z"),
            },
            probes: catalogue
                .probes
                .iter()
                .map(|(k, p)| (k.clone(), TransferFunction::FirstOrder { tau_s: p.tau_s }))
                .collect(),
        },
        geometry: Geometry {
            tips: catalogue
                .tips
                .iter()
                .map(|s| TipGeometry {
                    id: s.id,
                    probe: s.probe.clone(),
                    l1_mm: s.l1_mm,
                    radius_mm: s.radius_mm,
                    l2_mm: s.l2_mm,
                    beta1_deg: s.beta1_deg,
                    l3_mm: s.l3_mm,
                    beta2_deg: s.beta2_deg,
                })
                .collect(),
            ..Calibration::example("m1").geometry
        },
        effects: vec![],
        judgement: Default::default(),
        join: Default::default(),
        limits,
        metrics: BTreeMap::new(),
    };
    c.build()?;
    let source = if sheet.is_some() {
        TauSource::DataSheet
    } else {
        TauSource::Default
    };
    Ok((c, source))
}

#[cfg(test)]
mod tests {
    use super::*;

    fn sheet() -> serde_json::Value {
        serde_json::json!({
            "machine_id": "m1",
            "sample_period_s": 0.001,
            "axes": {
                "x": {"tau_s": 0.0127, "travel_mm": [0, 1000]},
                "y": {"tau_s": 0.016, "travel_mm": [0, 800]},
                "z": {"tau_s": 0.011, "travel_mm": [-600, 0]}
            }
        })
    }

    fn catalogue() -> serde_json::Value {
        serde_json::json!({
            "probes": {"sp25": {"tau_s": 0.002}},
            "tips": [
                {"id": 1, "probe": "sp25", "l1_mm": 50, "radius_mm": 1.5, "alpha_per_k": 2e-6},
                {"id": 2, "probe": "sp25", "l1_mm": 40, "l2_mm": 40, "beta1_deg": 90, "radius_mm": 1.0}
            ]
        })
    }

    fn sheet_err(v: serde_json::Value) -> String {
        DataSheet::from_json(&v.to_string())
            .unwrap_err()
            .to_string()
    }

    fn cat_err(v: serde_json::Value) -> String {
        Catalogue::from_json(&v.to_string())
            .unwrap_err()
            .to_string()
    }

    #[test]
    fn the_nominal_calibration_takes_the_sheet_and_the_catalogue_and_builds() {
        let d = DataSheet::from_json(&sheet().to_string()).unwrap();
        let c = Catalogue::from_json(&catalogue().to_string()).unwrap();
        let (cal, src) = nominal(None, Some(&d), &c, None, "2026-01-01T00:00:00Z").unwrap();
        assert_eq!(src, TauSource::DataSheet);
        assert_eq!(cal.machine_id, "m1");
        assert_eq!(cal.version, 1);
        assert!(cal.effects.is_empty());
        assert_eq!(
            cal.nominal.axes.y,
            TransferFunction::FirstOrder { tau_s: 0.016 }
        );
        assert_eq!(cal.limits.travel_mm[2], [-600.0, 0.0]);
        assert_eq!(cal.geometry.tips[1].l2_mm, 40.0);
        assert_eq!(cal.geometry.tips[1].beta1_deg, 90.0);
        // The document it makes reads back as a valid calibration.
        assert_eq!(Calibration::parse_valid(&cal.to_json()).unwrap(), cal);
        // The documents round-trip.
        assert_eq!(DataSheet::from_json(&d.to_json()).unwrap(), d);
        assert_eq!(Catalogue::from_json(&c.to_json()).unwrap(), c);
    }

    #[test]
    fn without_a_sheet_the_time_constants_are_the_default_and_the_machine_is_needed() {
        let c = Catalogue::from_json(&catalogue().to_string()).unwrap();
        let (cal, src) = nominal(Some("m7"), None, &c, Some(0.0005), "").unwrap();
        assert_eq!(src, TauSource::Default);
        assert_eq!(cal.machine_id, "m7");
        assert_eq!(cal.sample_period_s, 0.0005);
        assert_eq!(
            cal.nominal.axes.x,
            TransferFunction::FirstOrder {
                tau_s: DEFAULT_TAU_S
            }
        );
        assert_eq!(cal.limits, Limits::default());
        let e = nominal(None, None, &c, None, "").unwrap_err().to_string();
        assert!(e.contains("machine_id"), "{e}");
        let d = DataSheet::from_json(&sheet().to_string()).unwrap();
        let e = nominal(Some("m2"), Some(&d), &c, None, "")
            .unwrap_err()
            .to_string();
        assert!(e.contains("for machine `m1`, not `m2`"), "{e}");
    }

    #[test]
    fn a_calibrations_styli_make_the_same_tips_again() {
        let d = DataSheet::from_json(&sheet().to_string()).unwrap();
        let c = Catalogue::from_json(&catalogue().to_string()).unwrap();
        let (cal, _) = nominal(None, Some(&d), &c, None, "").unwrap();
        let again = Catalogue::from_calibration(&cal).unwrap();
        let (cal2, _) = nominal(None, Some(&d), &again, None, "").unwrap();
        assert_eq!(cal2.geometry, cal.geometry);
        assert_eq!(cal2.nominal, cal.nominal);
        let mut cal = cal;
        cal.nominal.probes.insert(
            "ppt".into(),
            TransferFunction::SecondOrder {
                natural_freq_hz: 100.0,
                damping: 0.7,
            },
        );
        let e = Catalogue::from_calibration(&cal).unwrap_err().to_string();
        assert!(e.contains("calibration field `nominal.probes.ppt`"), "{e}");
    }

    #[test]
    fn refusals_name_the_field() {
        let mut v = sheet();
        v["axes"]["y"]["tau_s"] = (-1.0).into();
        assert!(sheet_err(v).contains("data sheet field `axes.y.tau_s`"));
        let mut v = sheet();
        v["axes"]["z"]["tau_s"] = 12.0.into();
        assert!(sheet_err(v).contains("not milliseconds"));
        let mut v = sheet();
        v["axes"]["x"]["travel_mm"] = serde_json::json!([10, -10]);
        assert!(sheet_err(v).contains("`axes.x.travel_mm`"));
        let mut v = sheet();
        v["axes"]["x"]["tau"] = 0.01.into();
        let e = sheet_err(v);
        assert!(e.contains("at `axes.x.tau`: unknown field"), "{e}");
        let mut v = sheet();
        v["machine_id"] = "m 1".into();
        assert!(sheet_err(v).contains("`machine_id`"));
        let mut v = sheet();
        v["sample_period_s"] = 1.5.into();
        assert!(sheet_err(v).contains("`sample_period_s`"));

        let mut v = catalogue();
        v["tips"][1]["probe"] = "ppt".into();
        assert!(cat_err(v).contains("catalogue field `tips[1].probe`"));
        let mut v = catalogue();
        v["tips"][1]["id"] = 1.into();
        assert!(cat_err(v).contains("`tips[1].id`"));
        let mut v = catalogue();
        v["tips"][0]["radius_mm"] = 0.into();
        assert!(cat_err(v).contains("`tips[0].radius_mm`"));
        let mut v = catalogue();
        v["tips"][0]["l2_mm"] = (-3).into();
        assert!(cat_err(v).contains("`tips[0].l2_mm`"));
        let mut v = catalogue();
        v["tips"][0]["alpha_per_k"] = 11.5.into();
        assert!(cat_err(v).contains("`tips[0].alpha_per_k`"));
        let mut v = catalogue();
        v["probes"]["sp25"]["tau_s"] = 0.into();
        assert!(cat_err(v).contains("`probes.sp25.tau_s`"));
        let mut v = catalogue();
        v["tips"] = serde_json::json!([]);
        assert!(cat_err(v).contains("`tips`"));
        let mut v = catalogue();
        v["tips"][0]["length"] = 3.into();
        let e = cat_err(v);
        assert!(e.contains("at `tips[0].length`: unknown field"), "{e}");
    }
}
