//! The calibration document: one machine's versioned model, as human-editable JSON.
//!
//! A [`Calibration`] is what users read, edit, store and send; [`Calibration::build`] turns a
//! valid one into a [`Model`] (discretised nominal models, built effects, filter
//! coefficients) that the [`Corrector`](crate::Corrector) runs. Every refusal names the field.

use crate::biquad;
pub use crate::checks::{
    check_text, escape_text, hidden_char, in_range, shown, SAMPLE_PERIOD_S, TAU_S,
};
use crate::effects::{BuiltEffect, EffectConfig, SensorTable};
use crate::sample::AlarmAction;
use crate::stylus::TipGeometry;
use crate::transfer::{Discrete, TransferFunction};
use serde::{Deserialize, Serialize};
use std::collections::BTreeMap;
use std::sync::Arc;

/// A calibration document.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Calibration {
    /// The machine this calibrates; a document for another machine is refused.
    pub machine_id: String,
    /// Version number, increasing per machine; every corrected point names it.
    pub version: u64,
    /// The version this one was derived from (history of the model lab).
    #[serde(default)]
    pub parent_version: Option<u64>,
    /// What changed and why, in words. Free text ([`check_text`]): no control (but line feeds
    /// and tabs), bidirectional-override or zero-width characters; nor in `created`, the
    /// `metrics` names or a `feature_map`'s `feature`.
    #[serde(default)]
    pub note: String,
    /// Creation time, RFC 3339 (informative; the core keeps no clock).
    #[serde(default)]
    pub created: String,
    /// Sample period of the controller's command and scale streams, s; 1e-5 … 0.1 s (100 kHz
    /// to 10 Hz, [`SAMPLE_PERIOD_S`]).
    pub sample_period_s: f64,
    /// Nominal transfer-function model of the machine (G1 per axis) and probes (G2).
    pub nominal: Nominal,
    /// Stylus and tip geometry.
    pub geometry: Geometry,
    /// Effects corrected, in order (the order of per-effect corrections in each point).
    #[serde(default)]
    pub effects: Vec<EffectConfig>,
    /// Estimator-validity judgement settings.
    #[serde(default)]
    pub judgement: Judgement,
    /// Stream-join settings.
    #[serde(default)]
    pub join: Join,
    /// Plausibility ranges of the machine: input outside them is refused and counted, and no
    /// point outside the machine's volume is ever published.
    #[serde(default)]
    pub limits: Limits,
    /// Figures the model lab measured for this version (e.g. `heldout_rms_um`), so the history
    /// of versions can show the error falling without re-reading the data. Informative (the
    /// service does not read them): any finite number.
    #[serde(default, skip_serializing_if = "BTreeMap::is_empty")]
    pub metrics: BTreeMap<String, f64>,
}

/// Nominal model: G_N = G1(axis)·G2(probe type).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Nominal {
    /// G1 for the x, y and z axes.
    pub axes: Axes,
    /// G2 per probe type, selected by the active tip's `probe`.
    pub probes: BTreeMap<String, TransferFunction>,
}

/// One transfer function per axis.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Axes {
    /// X axis.
    pub x: TransferFunction,
    /// Y axis.
    pub y: TransferFunction,
    /// Z axis.
    pub z: TransferFunction,
}

/// Stylus/tip geometry.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Geometry {
    /// Tips that may be active.
    pub tips: Vec<TipGeometry>,
    /// Below this deflection the contact direction is unknown: the point's normal is zero
    /// and its surface point is the tip centre, mm; 0 … 1 mm and below
    /// `limits.probe_range_mm`.
    #[serde(default = "default_min_contact")]
    pub min_contact_deflection_mm: f64,
}

fn default_min_contact() -> f64 {
    0.005
}

/// Judgement (estimator validity) settings.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct Judgement {
    /// |A_est − A_meas| above this (filtered) raises an alarm, mm/s²; 1 … 10⁶ mm/s².
    pub threshold_mm_s2: f64,
    /// ...when it stays above for at least this long, s; 0 … 10 s.
    pub min_duration_s: f64,
    /// Clears when below `clear_fraction × threshold`...; 0 … 1.
    pub clear_fraction: f64,
    /// ...for at least this long, s; 0 … 10 s.
    pub clear_duration_s: f64,
    /// Low-pass cutoff applied to both accelerations, Hz; 0.1 Hz up to half the sample rate.
    pub filter_cutoff_hz: f64,
    /// Butterworth order (2, 4, 6 or 8).
    pub filter_order: usize,
    /// What a raised alarm does to the points.
    pub action: AlarmAction,
}

impl Default for Judgement {
    fn default() -> Self {
        Judgement {
            threshold_mm_s2: 150.0,
            min_duration_s: 0.004,
            clear_fraction: 0.5,
            clear_duration_s: 0.05,
            filter_cutoff_hz: 40.0,
            filter_order: 4,
            action: AlarmAction::Flag,
        }
    }
}

/// Stream-join settings.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct Join {
    /// Consecutive samples of a stream further apart than this many sample periods are a
    /// gap: nothing is interpolated across it; 1 … 1000.
    pub max_gap_periods: f64,
    /// A point at time t uses the temperatures measured up to t − this delay, so the slow
    /// temperature stream never holds the fast ones back, s; 0 … 60 s.
    pub temperature_delay_s: f64,
    /// A held temperature older than this (at t − delay) is stale, s; 0.01 … 86 400 s.
    pub temperature_max_age_s: f64,
    /// Most samples buffered per stream while waiting for the others.
    pub max_pending: usize,
    /// A sample this much earlier than its stream's latest is evidence that the controller's
    /// clock was reset (a reboot), not a late sample, s; 0.001 … 3600 s.
    pub clock_reset_s: f64,
    /// That many such samples of one stream confirm the reset: the machine's join, estimator
    /// and judgement restart in the new time base, and the samples held while confirming are
    /// corrected, not lost. Fewer, followed by a sample in the old time base, are counted as
    /// `out_of_order`.
    pub clock_reset_samples: usize,
    /// A sample whose seq is not above its stream's last while its time runs on is a counter
    /// that wrapped or restarted (or an earlier sample's bogus jump), not a duplicate, once
    /// this many such samples in a row confirm it: the stream's sequence restarts there and
    /// the samples held while confirming are taken. Counted as `seq_resets`.
    pub seq_reset_samples: usize,
}

/// The machine's plausible ranges. Inputs outside are dropped as `implausible`; a point whose
/// surface or tip centre is not finite or lies outside the travel (widened by the longest
/// stylus reach) is dropped as `implausible_output`, never published. The machine's speed,
/// acceleration and head rate bound how far a scale or probe sample can be from its
/// stream's recent past (the corrector's jump gate: `implausible_jump`).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct Limits {
    /// Axis travel, [min, max] per axis (x, y, z), mm: commanded positions, arc centres and
    /// scale readings must lie inside it; min < max, within ±10⁶ mm.
    pub travel_mm: [[f64; 2]; 3],
    /// Largest stylus deflection the probe can measure (each component), mm; 0.01 … 1000 mm.
    pub probe_range_mm: f64,
    /// Temperatures any sensor can plausibly read, [min, max], °C; −273.15 ≤ min < max ≤ 2000.
    pub temperature_c: [f64; 2],
    /// Largest correction of one effect on one axis, mm (a model that predicts more is
    /// broken: its point is dropped as `implausible_output`); 0.001 … 1000 mm. This bounds
    /// the effects' fitted coefficients at run time (they are only required to be finite).
    pub max_correction_mm: f64,
    /// The machine's fastest motion of an axis, mm/s: a scale reading cannot move further
    /// than this in the time since the last, nor a probe's deflection grow faster (the
    /// surface pushes the stylus at most at the machine's speed). The jump gate of the
    /// corrector (`corrector`, "Jump gate"). Absent from documents written before it: the
    /// default, generous for any CMM or machine tool; 1 … 10⁹ mm/s.
    #[serde(
        default = "default_max_speed",
        skip_serializing_if = "is_default_max_speed"
    )]
    pub max_speed_mm_s: f64,
    /// The machine's largest acceleration of an axis, mm/s²: a scale reading cannot leave
    /// the path its last two readings extrapolate by more than this allows. The jump gate;
    /// 10 … 10¹² mm/s².
    #[serde(
        default = "default_max_accel",
        skip_serializing_if = "is_default_max_accel"
    )]
    pub max_accel_mm_s2: f64,
    /// The fastest the probe head turns (A1 and A2), °/s. The jump gate; 1 … 10⁹ °/s.
    #[serde(
        default = "default_max_head_rate",
        skip_serializing_if = "is_default_max_head_rate"
    )]
    pub max_head_rate_deg_s: f64,
    /// The readings' noise the jump gate allows on top of the motion, mm (per reading);
    /// 0 … 1000 mm.
    #[serde(
        default = "default_jump_noise",
        skip_serializing_if = "is_default_jump_noise"
    )]
    pub jump_noise_mm: f64,
    /// A jump the next this many samples of the stream confirm (none of them back on the
    /// old track) is real, not an absurd sample: they are taken and their points flagged.
    /// The jump gate; 1 … 1000 (1: every jump taken, its points flagged).
    #[serde(
        default = "default_jump_confirm",
        skip_serializing_if = "is_default_jump_confirm"
    )]
    pub jump_confirm_samples: usize,
}

fn default_max_speed() -> f64 {
    2000.0
}
fn is_default_max_speed(v: &f64) -> bool {
    *v == default_max_speed()
}
fn default_max_accel() -> f64 {
    50_000.0
}
fn is_default_max_accel(v: &f64) -> bool {
    *v == default_max_accel()
}
fn default_max_head_rate() -> f64 {
    360.0
}
fn is_default_max_head_rate(v: &f64) -> bool {
    *v == default_max_head_rate()
}
fn default_jump_noise() -> f64 {
    0.005
}
fn is_default_jump_noise(v: &f64) -> bool {
    *v == default_jump_noise()
}
fn default_jump_confirm() -> usize {
    4
}
fn is_default_jump_confirm(v: &usize) -> bool {
    *v == default_jump_confirm()
}

impl Default for Limits {
    fn default() -> Self {
        Limits {
            travel_mm: [[-5000.0, 5000.0]; 3],
            probe_range_mm: 5.0,
            temperature_c: [-20.0, 80.0],
            max_correction_mm: 5.0,
            max_speed_mm_s: default_max_speed(),
            max_accel_mm_s2: default_max_accel(),
            max_head_rate_deg_s: default_max_head_rate(),
            jump_noise_mm: default_jump_noise(),
            jump_confirm_samples: default_jump_confirm(),
        }
    }
}

impl Default for Join {
    fn default() -> Self {
        Join {
            max_gap_periods: 2.5,
            temperature_delay_s: 0.2,
            temperature_max_age_s: 5.0,
            max_pending: 20_000,
            clock_reset_s: 1.0,
            clock_reset_samples: 50,
            seq_reset_samples: 5,
        }
    }
}

/// Why a calibration document was refused.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum CalibError {
    /// Not valid JSON, or not the document's shape (unknown or missing field, wrong type).
    #[error("calibration document, at `{path}`: {msg}")]
    Parse {
        /// Path of the field, e.g. `effects[0].p`.
        path: String,
        /// What is wrong.
        msg: String,
    },
    /// A field has a value the model cannot use.
    #[error("calibration field `{field}`: {reason}")]
    Invalid {
        /// Path of the field.
        field: String,
        /// What is wrong.
        reason: String,
    },
    /// The document belongs to another machine.
    #[error("calibration is for machine `{document}`, not `{expected}`")]
    WrongMachine {
        /// Machine named in the document.
        document: String,
        /// Machine it was offered for.
        expected: String,
    },
}

fn invalid(field: impl Into<String>, reason: impl Into<String>) -> CalibError {
    CalibError::Invalid {
        field: field.into(),
        reason: reason.into(),
    }
}

/// [`in_range`] for a field of the document.
fn range(field: &str, v: f64, lo: f64, hi: f64, unit: &str) -> Result<(), CalibError> {
    in_range(field, v, lo, hi, unit).map_err(|r| {
        let reason = r.split_once(": ").map_or(r.clone(), |(_, r)| r.to_string());
        invalid(field, reason)
    })
}

/// What a built [`Model`] keeps of its calibration document besides what is built into its
/// other fields (effects, tips, discretised nominal models, filter sections). The document
/// itself is not kept: a service holds one model per machine, and the document's effect list,
/// tips and nominal model would take about 4 KB of it twice. The document is in the store it
/// came from.
#[derive(Debug, Clone, PartialEq)]
pub struct Settings {
    /// The document's version: every corrected point names it.
    pub version: u64,
    /// `geometry.min_contact_deflection_mm`.
    pub min_contact_deflection_mm: f64,
    /// Estimator-validity judgement settings.
    pub judgement: Judgement,
    /// Stream-join settings.
    pub join: Join,
    /// Plausibility ranges.
    pub limits: Limits,
}

/// A few entries by key, in key order: a sorted list (a calibration has a few tips and probe
/// types). A service keeps a model per machine, and a `BTreeMap` takes a node of eleven
/// entries for the first one (about 1 KB for one tip).
#[derive(Debug, Clone, PartialEq)]
pub struct Table<K, V>(Vec<(K, V)>);

impl<K: Ord, V> Table<K, V> {
    /// The value of `key`.
    pub fn get<Q: Ord + ?Sized>(&self, key: &Q) -> Option<&V>
    where
        K: std::borrow::Borrow<Q>,
    {
        self.0
            .binary_search_by(|(k, _)| k.borrow().cmp(key))
            .ok()
            .map(|i| &self.0[i].1)
    }
    /// Entries in key order.
    pub fn iter(&self) -> impl Iterator<Item = (&K, &V)> {
        self.0.iter().map(|(k, v)| (k, v))
    }
    /// Values in key order.
    pub fn values(&self) -> impl Iterator<Item = &V> {
        self.0.iter().map(|(_, v)| v)
    }
    /// Number of entries.
    pub fn len(&self) -> usize {
        self.0.len()
    }
    /// Whether there is no entry.
    pub fn is_empty(&self) -> bool {
        self.0.is_empty()
    }
}

impl<K: Ord, V> From<BTreeMap<K, V>> for Table<K, V> {
    fn from(m: BTreeMap<K, V>) -> Self {
        // Already in key order, each key once.
        Table(m.into_iter().collect())
    }
}

impl<K: Ord + std::borrow::Borrow<Q>, Q: Ord + ?Sized, V> std::ops::Index<&Q> for Table<K, V> {
    type Output = V;
    fn index(&self, key: &Q) -> &V {
        self.get(key).expect("a key of the table")
    }
}

/// The built, runnable form of a calibration.
#[derive(Debug)]
pub struct Model {
    /// The document's settings the corrector reads as it runs (the document itself is not
    /// kept: see [`Settings`]).
    pub settings: Settings,
    /// Discretised G_N per probe type, per axis.
    pub nominal: Table<String, Arc<[Discrete; 3]>>,
    /// Tips by id.
    pub tips: Table<u32, TipGeometry>,
    /// Effects in document order.
    pub effects: Vec<BuiltEffect>,
    /// Temperature sensors the effects read, by slot.
    pub sensors: SensorTable,
    /// Judgement filter sections.
    pub filter: Vec<biquad::Coefficients>,
    /// Samples above threshold before raising.
    pub raise_samples: u32,
    /// Samples below the clear level before clearing.
    pub clear_samples: u32,
    /// Gap limit, ns.
    pub max_gap_ns: i64,
    /// Temperature delay, ns.
    pub temperature_delay_ns: i64,
    /// `join.clock_reset_s` in ns.
    pub clock_reset_ns: i64,
    /// Temperature maximum age, ns.
    pub temperature_max_age_ns: i64,
    /// The travel widened by the longest reach of a tip (offset + radius + probe range +
    /// largest total correction): where a surface point or tip centre can plausibly be, mm.
    pub volume_mm: [[f64; 2]; 3],
    /// Largest plausible commanded arc radius: the diagonal of the travel, mm.
    pub max_arc_radius_mm: f64,
}

impl Calibration {
    /// The ids of its `feature_map` effects: a map applies only to its own part program's
    /// scans, so one that no scan uses is expected and said as such.
    pub fn feature_map_ids(&self) -> Vec<String> {
        self.effects
            .iter()
            .filter(|e| e.kind() == "feature_map")
            .map(|e| e.id())
            .collect()
    }

    /// Parses a JSON document, naming the field on error. Does not validate values; see
    /// [`Calibration::build`].
    /// Anything after the document but white space is refused.
    pub fn from_json(text: &str) -> Result<Calibration, CalibError> {
        let mut de = serde_json::Deserializer::from_str(text);
        let c = serde_path_to_error::deserialize(&mut de).map_err(|e| {
            let path = e.path().to_string();
            CalibError::Parse {
                path,
                msg: e.into_inner().to_string(),
            }
        })?;
        de.end().map_err(|e| CalibError::Parse {
            path: ".".into(),
            msg: format!("text after the end of the document ({e})"),
        })?;
        Ok(c)
    }

    /// Pretty JSON.
    pub fn to_json(&self) -> String {
        serde_json::to_string_pretty(self).expect("a calibration always serialises")
    }

    /// Parses and validates in one go.
    pub fn parse_valid(text: &str) -> Result<Calibration, CalibError> {
        let c = Calibration::from_json(text)?;
        c.build()?;
        Ok(c)
    }

    /// Refuses a document for another machine.
    pub fn check_machine(&self, machine: &str) -> Result<(), CalibError> {
        if self.machine_id == machine {
            Ok(())
        } else {
            Err(CalibError::WrongMachine {
                document: self.machine_id.clone(),
                expected: machine.to_string(),
            })
        }
    }

    /// Validates every value and builds the runnable model.
    pub fn build(&self) -> Result<Model, CalibError> {
        scancorr_proto::names::check_machine(&self.machine_id)
            .map_err(|e| invalid("machine_id", e.to_string()))?;
        // Free text people read (the history, reports): nothing that reads otherwise than it is.
        let text = |field: &str, t: &str, lines: bool| {
            check_text(field, t, lines).map_err(|r| {
                invalid(
                    field,
                    r.split_once(": ").map_or(r.clone(), |(_, r)| r.into()),
                )
            })
        };
        text("note", &self.note, true)?;
        text("created", &self.created, false)?;
        for k in self.metrics.keys() {
            text(&format!("metrics.{}", escape_text(k)), k, false)?;
        }
        if let Some((k, _)) = self.metrics.iter().find(|(_, v)| !v.is_finite()) {
            return Err(invalid(format!("metrics.{k}"), "must be a finite number"));
        }
        let t = self.sample_period_s;
        let [lo, hi] = SAMPLE_PERIOD_S;
        range("sample_period_s", t, lo, hi, "s")?;
        // Nominal models: G1 per axis × G2 per probe type.
        let mut g1 = vec![];
        for (name, tf) in [
            ("x", &self.nominal.axes.x),
            ("y", &self.nominal.axes.y),
            ("z", &self.nominal.axes.z),
        ] {
            g1.push(
                tf.rational()
                    .map_err(|e| invalid(format!("nominal.axes.{name}"), e.to_string()))?,
            );
        }
        if self.nominal.probes.is_empty() {
            return Err(invalid(
                "nominal.probes",
                "at least one probe type is needed",
            ));
        }
        let mut nominal = BTreeMap::new();
        for (probe, tf) in &self.nominal.probes {
            scancorr_proto::names::check("probe type", probe)
                .map_err(|e| invalid("nominal.probes", e.to_string()))?;
            let field = format!("nominal.probes.{probe}");
            let g2 = tf.rational().map_err(|e| invalid(&field, e.to_string()))?;
            let mut d = vec![];
            for (i, g) in g1.iter().enumerate() {
                d.push(Discrete::new(&g.mul(&g2), t).map_err(|e| {
                    invalid(
                        format!("nominal (axis {} × {field})", ["x", "y", "z"][i]),
                        e.to_string(),
                    )
                })?);
            }
            let arr: [Discrete; 3] = d.try_into().expect("three axes");
            nominal.insert(probe.clone(), Arc::new(arr));
        }
        // Geometry.
        if self.geometry.tips.is_empty() {
            return Err(invalid("geometry.tips", "at least one tip is needed"));
        }
        let mut tips = BTreeMap::new();
        for (i, tip) in self.geometry.tips.iter().enumerate() {
            let field = format!("geometry.tips[{i}]");
            tip.validate(&field).map_err(|e| match e.split_once(": ") {
                Some((f, reason)) if f.starts_with(&field) => invalid(f, reason),
                _ => invalid(&field, e),
            })?;
            if !self.nominal.probes.contains_key(&tip.probe) {
                return Err(invalid(
                    format!("{field}.probe"),
                    format!("probe type `{}` has no model in nominal.probes", tip.probe),
                ));
            }
            if tips.insert(tip.id, tip.clone()).is_some() {
                return Err(invalid(
                    format!("{field}.id"),
                    format!("tip id {} appears twice", tip.id),
                ));
            }
        }
        range(
            "geometry.min_contact_deflection_mm",
            self.geometry.min_contact_deflection_mm,
            0.0,
            1.0,
            "mm",
        )?;
        // Effects.
        let mut sensors = SensorTable::default();
        let mut effects = vec![];
        let mut ids = std::collections::BTreeSet::new();
        for (i, e) in self.effects.iter().enumerate() {
            let b = e.build(&mut sensors).map_err(|r| {
                let (f, reason) = match r.split_once(": ") {
                    Some((f, rest)) if !f.contains(' ') => {
                        (format!("effects[{i}].{f}"), rest.to_string())
                    }
                    _ => (format!("effects[{i}]"), r.clone()),
                };
                invalid(f, reason)
            })?;
            scancorr_proto::names::check("effect id", &b.id)
                .map_err(|e| invalid(format!("effects[{i}]"), e.to_string()))?;
            if !ids.insert(b.id.clone()) {
                return Err(invalid(
                    format!("effects[{i}]"),
                    format!("effect id `{}` appears twice; give one an `id`", b.id),
                ));
            }
            effects.push(b);
        }
        for name in sensors.names() {
            scancorr_proto::names::check("temperature sensor", name)
                .map_err(|e| invalid("effects", e.to_string()))?;
        }
        // Judgement.
        let j = &self.judgement;
        for (n, v, lo, hi, unit) in [
            ("threshold_mm_s2", j.threshold_mm_s2, 1.0, 1e6, "mm/s²"),
            ("min_duration_s", j.min_duration_s, 0.0, 10.0, "s"),
            ("clear_fraction", j.clear_fraction, 0.0, 1.0, ""),
            ("clear_duration_s", j.clear_duration_s, 0.0, 10.0, "s"),
            ("filter_cutoff_hz", j.filter_cutoff_hz, 0.1, 0.5 / t, "Hz"),
        ] {
            range(&format!("judgement.{n}"), v, lo, hi, unit)?;
        }
        let filter = biquad::Coefficients::butterworth(1.0 / t, j.filter_cutoff_hz, j.filter_order).ok_or_else(|| {
            invalid(
                "judgement.filter_cutoff_hz",
                format!("needs 0 < cutoff < {} Hz (half the sample rate) and filter_order 2, 4, 6 or 8", 0.5 / t),
            )
        })?;
        // Join.
        let jn = &self.join;
        for (n, v, lo, hi) in [
            ("max_gap_periods", jn.max_gap_periods, 1.0, 1000.0),
            ("temperature_delay_s", jn.temperature_delay_s, 0.0, 60.0),
            (
                "temperature_max_age_s",
                jn.temperature_max_age_s,
                0.01,
                86_400.0,
            ),
            ("clock_reset_s", jn.clock_reset_s, 0.001, 3600.0),
        ] {
            let unit = if n == "max_gap_periods" {
                "periods"
            } else {
                "s"
            };
            range(&format!("join.{n}"), v, lo, hi, unit)?;
        }
        if jn.max_pending < 16 {
            return Err(invalid("join.max_pending", "must be at least 16"));
        }
        if !(1..=1000).contains(&jn.clock_reset_samples) {
            return Err(invalid("join.clock_reset_samples", "must be 1 … 1000"));
        }
        if !(1..=1000).contains(&jn.seq_reset_samples) {
            return Err(invalid("join.seq_reset_samples", "must be 1 … 1000"));
        }
        // Limits.
        let l = &self.limits;
        for (i, [lo, hi]) in l.travel_mm.iter().enumerate() {
            if !(lo.is_finite() && hi.is_finite() && lo < hi && lo.abs() <= 1e6 && hi.abs() <= 1e6)
            {
                return Err(invalid(
                    format!("limits.travel_mm[{i}]"),
                    format!(
                        "[{}, {}] is not [min, max] with min < max, both within [-1e6, 1e6] mm",
                        shown(*lo),
                        shown(*hi)
                    ),
                ));
            }
        }
        for (n, v, lo) in [
            ("probe_range_mm", l.probe_range_mm, 0.01),
            ("max_correction_mm", l.max_correction_mm, 0.001),
        ] {
            range(&format!("limits.{n}"), v, lo, 1000.0, "mm")?;
        }
        if self.geometry.min_contact_deflection_mm >= l.probe_range_mm {
            return Err(invalid(
                "geometry.min_contact_deflection_mm",
                format!(
                    "{} mm is not below limits.probe_range_mm ({} mm): no deflection would be a contact",
                    shown(self.geometry.min_contact_deflection_mm),
                    shown(l.probe_range_mm)
                ),
            ));
        }
        // The jump gate's: up to far beyond any machine, so a user can set it out of the way.
        for (n, v, lo, hi, unit) in [
            ("max_speed_mm_s", l.max_speed_mm_s, 1.0, 1e9, "mm/s"),
            ("max_accel_mm_s2", l.max_accel_mm_s2, 10.0, 1e12, "mm/s²"),
            (
                "max_head_rate_deg_s",
                l.max_head_rate_deg_s,
                1.0,
                1e9,
                "°/s",
            ),
            ("jump_noise_mm", l.jump_noise_mm, 0.0, 1000.0, "mm"),
        ] {
            range(&format!("limits.{n}"), v, lo, hi, unit)?;
        }
        if !(1..=1000).contains(&l.jump_confirm_samples) {
            return Err(invalid("limits.jump_confirm_samples", "must be 1 … 1000"));
        }
        let [tlo, thi] = l.temperature_c;
        if !(tlo.is_finite() && thi.is_finite() && tlo < thi && tlo >= -273.15 && thi <= 2000.0) {
            return Err(invalid(
                "limits.temperature_c",
                format!(
                    "[{}, {}] is not [min, max] with min < max, both within [-273.15, 2000] °C",
                    shown(tlo),
                    shown(thi)
                ),
            ));
        }
        let reach = tips
            .values()
            .map(|t| t.l1_mm.abs() + t.l2_mm.abs() + t.l3_mm.abs() + t.radius_mm.abs())
            .fold(0.0, f64::max)
            + l.probe_range_mm * 3f64.sqrt()
            + l.max_correction_mm * effects.len() as f64 * 3f64.sqrt();
        let volume_mm = l.travel_mm.map(|[lo, hi]| [lo - reach, hi + reach]);
        let max_arc_radius_mm = l
            .travel_mm
            .iter()
            .map(|[lo, hi]| (hi - lo).powi(2))
            .sum::<f64>()
            .sqrt();
        let ns = |s: f64| (s * 1e9).round() as i64;
        Ok(Model {
            settings: Settings {
                version: self.version,
                min_contact_deflection_mm: self.geometry.min_contact_deflection_mm,
                judgement: self.judgement.clone(),
                join: self.join.clone(),
                limits: self.limits.clone(),
            },
            nominal: nominal.into(),
            tips: tips.into(),
            effects,
            sensors,
            filter,
            raise_samples: ((j.min_duration_s / t).round() as u32).max(1),
            clear_samples: ((j.clear_duration_s / t).round() as u32).max(1),
            max_gap_ns: ns(jn.max_gap_periods * t),
            temperature_delay_ns: ns(jn.temperature_delay_s),
            clock_reset_ns: ns(jn.clock_reset_s),
            temperature_max_age_ns: ns(jn.temperature_max_age_s),
            volume_mm,
            max_arc_radius_mm,
        })
    }

    /// A minimal valid document: first-order axes, one probe, one straight tip, no effects.
    /// Used by tests, examples and `scancorr` defaults.
    pub fn example(machine_id: &str) -> Calibration {
        Calibration {
            machine_id: machine_id.to_string(),
            version: 1,
            parent_version: None,
            note: "nominal model only".into(),
            created: String::new(),
            sample_period_s: 0.001,
            nominal: Nominal {
                axes: Axes {
                    x: TransferFunction::FirstOrder { tau_s: 0.012 },
                    y: TransferFunction::FirstOrder { tau_s: 0.015 },
                    z: TransferFunction::FirstOrder { tau_s: 0.010 },
                },
                probes: [(
                    "sp25".to_string(),
                    TransferFunction::FirstOrder { tau_s: 0.002 },
                )]
                .into(),
            },
            geometry: Geometry {
                tips: vec![TipGeometry {
                    id: 1,
                    probe: "sp25".into(),
                    l1_mm: 50.0,
                    radius_mm: 1.5,
                    l2_mm: 0.0,
                    beta1_deg: 0.0,
                    l3_mm: 0.0,
                    beta2_deg: 0.0,
                }],
                min_contact_deflection_mm: default_min_contact(),
            },
            effects: vec![],
            judgement: Judgement::default(),
            join: Join::default(),
            limits: Limits::default(),
            metrics: BTreeMap::new(),
        }
    }
}

#[cfg(test)]
mod tests;

/// `unix_secs` (seconds since 1970-01-01 UTC) as RFC 3339 in UTC, to the second — the form of
/// a calibration's `created` and of the service's audit records. The caller reads the clock
/// (the core has none). Civil date by Howard Hinnant's days-from-civil inverse.
pub fn rfc3339_utc(unix_secs: i64) -> String {
    let (days, rem) = (unix_secs.div_euclid(86_400), unix_secs.rem_euclid(86_400));
    let z = days + 719_468;
    let era = z.div_euclid(146_097);
    let doe = z.rem_euclid(146_097);
    let yoe = (doe - doe / 1460 + doe / 36_524 - doe / 146_096) / 365;
    let doy = doe - (365 * yoe + yoe / 4 - yoe / 100);
    let mp = (5 * doy + 2) / 153;
    let d = doy - (153 * mp + 2) / 5 + 1;
    let m = if mp < 10 { mp + 3 } else { mp - 9 };
    let y = yoe + era * 400 + i64::from(m <= 2);
    format!(
        "{y:04}-{m:02}-{d:02}T{:02}:{:02}:{:02}Z",
        rem / 3600,
        rem % 3600 / 60,
        rem % 60
    )
}

#[cfg(test)]
mod rfc3339_tests {
    #[test]
    fn unix_seconds_read_as_utc_dates() {
        use super::rfc3339_utc;
        assert_eq!(rfc3339_utc(0), "1970-01-01T00:00:00Z");
        assert_eq!(rfc3339_utc(951_868_799), "2000-02-29T23:59:59Z");
        assert_eq!(rfc3339_utc(1_795_629_723), "2026-11-25T18:02:03Z");
        assert_eq!(rfc3339_utc(-1), "1969-12-31T23:59:59Z");
    }
}
