//! A measurement campaign planned before it is measured: the program record the simulator
//! (or a user's part program) runs, the lab's prediction of every parameter's uncertainty
//! from the design alone, and a planner that chooses the scans.
//!
//! Prediction (the lab's own least squares, `fit` and `select::Space::fit`, evaluated before
//! any measurement): each scan of the [`Program`] yields its ideal points — a circle at speed v
//! and path radius r has the acceleration v²/r towards its centre and the rotation frequency
//! f = v/2πr, a face scan's deflection and acceleration lie along the face's normal, the
//! probing direction is the surface normal — with the speed ramps the controller commands.
//! Each point gives the row g·r of every parameter of every effect (the effect's hot-path
//! `regressors`, g the artifact fit's gradient) and the placement (nuisance) columns of its
//! feature; with J the matrix of those rows over the points the lab would fit (every other
//! scan of each feature when no held-out bag is measured),
//!
//!   σ_k = s · sqrt( [(JᵀJ)⁺]_kk · (1 + ρ)/(1 − ρ) ),
//!
//! s the noise floor of a point along its normal and ρ the lag-1 correlation of the
//! residuals (the lab's effective number of points n(1 − ρ)/(1 + ρ)). Parameters in the null
//! space of J (or whose column is below 10⁻³ of their effect's strongest, as the lab leaves
//! them) are named undetermined. The lab's smoothing of tables and its ridge are not part of
//! the prediction: for a determined parameter they change little; a table value the data
//! cannot see is reported as undetermined here.
//!
//! Source idea: optimal experimental design (D/A-optimality: Fedorov 1972), the information
//! matrix JᵀJ being additive over scans, so a scan group's worth is known before it is run.

use super::analysis;
use super::dataset::{Dataset, LabPoint, Phase};
use super::fit::{fit_artifacts, nuisance_row, Normal};
use super::program::{FeatureKind, FeatureSpec};
use super::LabError;
use crate::calib::Calibration;
use crate::effects::{Effect, EffectConfig, SensorTable};
use crate::sample::{PointContext, Vec3, MAX_SENSORS};
use crate::stylus::TipPose;
use serde::{Deserialize, Serialize};
use std::f64::consts::{PI, TAU};

/// What an artifact of a program is.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum Artifact {
    /// A ring gauge (scanned inside).
    Ring,
    /// A sphere (scanned on its equator).
    Sphere,
    /// A straightedge or any plane face.
    Straightedge,
}

/// One artifact placement of a program.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct ProgramFeature {
    /// Ring, sphere or straightedge.
    pub artifact: Artifact,
    /// Centre (ring, sphere) or a point of the face (straightedge), machine axes, mm.
    pub center_mm: [f64; 3],
    /// Nominal diameter (ring, sphere), mm.
    #[serde(default)]
    pub nominal_diameter_mm: f64,
    /// Certified diameter (ring, sphere), mm: the lab keeps it fixed.
    #[serde(default)]
    pub certified_diameter_mm: Option<f64>,
    /// Face normal out of the material (straightedge).
    #[serde(default)]
    pub normal: Option<[f64; 3]>,
    /// Length of the face (straightedge), mm.
    #[serde(default)]
    pub length_mm: Option<f64>,
}

/// Kind of a scan.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum ScanKind {
    /// One turn of a ring or a sphere's equator (plus the speed ramps).
    Circle,
    /// A line along a face.
    FaceLine,
    /// The probe held on a face while the machine oscillates along the face's normal,
    /// `amplitude_mm`·sin(2π·`frequency_hz`·t): acceleration along the measured direction
    /// without an arc.
    FaceWeave,
}

fn tip_one() -> u32 {
    1
}

/// One scan of a program.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Scan {
    /// Circle, face line or face weave.
    pub kind: ScanKind,
    /// Index into [`Program::features`].
    pub feature: usize,
    /// Active tip.
    #[serde(default = "tip_one")]
    pub tip: u32,
    /// Head A1, degrees.
    #[serde(default)]
    pub a1_deg: f64,
    /// Head A2, degrees.
    #[serde(default)]
    pub a2_deg: f64,
    /// Nominal probe deflection, mm.
    pub deflection_mm: f64,
    /// Speed (circle, face line), mm/s.
    #[serde(default)]
    pub speed_mm_s: f64,
    /// +1 counter-clockwise, −1 clockwise (circle).
    #[serde(default)]
    pub direction: i32,
    /// Start and end along the face from its point, mm (face line).
    #[serde(default)]
    pub from_mm: f64,
    /// End along the face, mm (face line).
    #[serde(default)]
    pub to_mm: f64,
    /// Where along the face the weave is, mm (face weave).
    #[serde(default)]
    pub at_mm: f64,
    /// Weave amplitude along the normal, mm (face weave).
    #[serde(default)]
    pub amplitude_mm: f64,
    /// Weave frequency, Hz (face weave).
    #[serde(default)]
    pub frequency_hz: f64,
    /// Number of weave cycles (face weave).
    #[serde(default)]
    pub cycles: f64,
    /// Why the scan is in the plan (for people).
    #[serde(default)]
    pub why: String,
}

/// A measurement program: artifact placements and scans, in order.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Program {
    /// Name (the bag's program name).
    pub name: String,
    /// What it is for.
    #[serde(default)]
    pub note: String,
    /// Artifact placements.
    pub features: Vec<ProgramFeature>,
    /// Scans in order.
    pub scans: Vec<Scan>,
}

/// Speed ramp of a circle scan, s (as the simulator and the controller command it).
pub fn circle_ramp_s(speed: f64) -> f64 {
    (speed / 150.0).max(0.4)
}
/// Speed ramp of a face line, s.
pub const LINE_RAMP_S: f64 = 0.4;
/// Speed ramp of a face weave (its frequency rises over this time), s.
pub const WEAVE_RAMP_S: f64 = 0.5;
/// Positioning speed between scans, mm/s.
pub const MOVE_SPEED_MM_S: f64 = 120.0;
/// Dwell before and after each scan, s.
pub const DWELLS_S: f64 = 0.4;

fn fnum(field: &str, v: f64, lo: f64, hi: f64, unit: &str) -> Result<(), String> {
    crate::calib::in_range(field, v, lo, hi, unit)
}

impl Scan {
    /// Peak speed, mm/s (a weave's 2πfA).
    pub fn peak_speed(&self) -> f64 {
        match self.kind {
            ScanKind::FaceWeave => TAU * self.frequency_hz * self.amplitude_mm,
            _ => self.speed_mm_s,
        }
    }
    /// Peak acceleration along the measured direction, mm/s² (circle v²/r, weave A(2πf)²).
    pub fn peak_accel(&self, radius: f64) -> f64 {
        match self.kind {
            ScanKind::Circle => self.speed_mm_s.powi(2) / radius.max(1e-9),
            ScanKind::FaceWeave => self.amplitude_mm * (TAU * self.frequency_hz).powi(2),
            ScanKind::FaceLine => 0.0,
        }
    }
}

impl ProgramFeature {
    fn normal_unit(&self) -> Vec3 {
        self.normal
            .map(Vec3::from)
            .and_then(|n| n.try_normalize(1e-12))
            .unwrap_or(Vec3::new(0.0, -1.0, 0.0))
    }
    /// The direction along a face (n × z; x for a face whose normal is z).
    pub fn along(&self) -> Vec3 {
        along_of(&self.normal_unit())
    }
    /// The feature as the lab's program record says it.
    pub fn spec(&self, id: u32) -> FeatureSpec {
        let (artifact, kind) = match self.artifact {
            Artifact::Ring => ("ring", FeatureKind::Bore),
            Artifact::Sphere => ("sphere", FeatureKind::Boss),
            Artifact::Straightedge => ("straightedge", FeatureKind::Face),
        };
        FeatureSpec {
            id,
            artifact: artifact.into(),
            kind,
            nominal_center: self.center_mm,
            nominal_diameter_mm: self.nominal_diameter_mm,
            certificate_diameter_mm: self.certified_diameter_mm,
            normal: match self.artifact {
                Artifact::Straightedge => self.normal_unit().into(),
                _ => [0.0; 3],
            },
        }
    }
}

/// The direction along a face of normal `n`: n × z, or x when n is along z (as the lab's
/// artifact fit takes it).
pub fn along_of(n: &Vec3) -> Vec3 {
    n.cross(&Vec3::z()).try_normalize(1e-9).unwrap_or(Vec3::x())
}

impl Program {
    /// Parses and validates a program record (errors name the field, e.g.
    /// `scans[3].speed_mm_s`).
    pub fn from_json(s: &str) -> Result<Program, String> {
        let p: Program = serde_json::from_str(s).map_err(|e| e.to_string())?;
        p.validate()?;
        Ok(p)
    }
    /// Pretty JSON.
    pub fn to_json(&self) -> String {
        serde_json::to_string_pretty(self).unwrap_or_default()
    }
    /// Checks every field; the message names it.
    pub fn validate(&self) -> Result<(), String> {
        if self.name.trim().is_empty() {
            return Err("name: must not be empty".into());
        }
        if self.scans.is_empty() {
            return Err("scans: a program needs at least one scan".into());
        }
        for (i, f) in self.features.iter().enumerate() {
            let p = format!("features[{i}]");
            for (k, c) in f.center_mm.iter().enumerate() {
                fnum(&format!("{p}.center_mm[{k}]"), *c, -1e5, 1e5, "mm")?;
            }
            match f.artifact {
                Artifact::Ring | Artifact::Sphere => {
                    fnum(
                        &format!("{p}.nominal_diameter_mm"),
                        f.nominal_diameter_mm,
                        1.0,
                        2000.0,
                        "mm",
                    )?;
                    if let Some(d) = f.certified_diameter_mm {
                        fnum(&format!("{p}.certified_diameter_mm"), d, 1.0, 2000.0, "mm")?;
                        if (d - f.nominal_diameter_mm).abs() > 0.1 {
                            return Err(format!(
                                "{p}.certified_diameter_mm: {d} mm is more than 0.1 mm from the nominal {} mm",
                                f.nominal_diameter_mm
                            ));
                        }
                    }
                    if f.normal.is_some() || f.length_mm.is_some() {
                        return Err(format!(
                            "{p}: `normal` and `length_mm` are for a straightedge"
                        ));
                    }
                }
                Artifact::Straightedge => {
                    let Some(n) = f.normal else {
                        return Err(format!("{p}.normal: a straightedge needs its face normal"));
                    };
                    let nv = Vec3::from(n);
                    if !(nv.iter().all(|v| v.is_finite()) && nv.norm() > 1e-6) {
                        return Err(format!("{p}.normal: must be a finite non-zero vector"));
                    }
                    let Some(l) = f.length_mm else {
                        return Err(format!("{p}.length_mm: a straightedge needs its length"));
                    };
                    fnum(&format!("{p}.length_mm"), l, 10.0, 5000.0, "mm")?;
                }
            }
        }
        for (i, s) in self.scans.iter().enumerate() {
            let p = format!("scans[{i}]");
            let Some(f) = self.features.get(s.feature) else {
                return Err(format!(
                    "{p}.feature: {} is not a feature index (0…{})",
                    s.feature,
                    self.features.len().saturating_sub(1)
                ));
            };
            fnum(&format!("{p}.a1_deg"), s.a1_deg, -360.0, 360.0, "°")?;
            fnum(&format!("{p}.a2_deg"), s.a2_deg, -360.0, 360.0, "°")?;
            fnum(
                &format!("{p}.deflection_mm"),
                s.deflection_mm,
                0.02,
                2.0,
                "mm",
            )?;
            match s.kind {
                ScanKind::Circle => {
                    if f.artifact == Artifact::Straightedge {
                        return Err(format!(
                            "{p}.kind: a circle needs a ring or a sphere, feature {} is a straightedge",
                            s.feature
                        ));
                    }
                    fnum(&format!("{p}.speed_mm_s"), s.speed_mm_s, 0.5, 500.0, "mm/s")?;
                    if s.direction != 1 && s.direction != -1 {
                        return Err(format!(
                            "{p}.direction: 1 (counter-clockwise) or -1 (clockwise)"
                        ));
                    }
                }
                ScanKind::FaceLine | ScanKind::FaceWeave => {
                    if f.artifact != Artifact::Straightedge {
                        return Err(format!(
                            "{p}.kind: a face scan needs a straightedge, feature {} is not one",
                            s.feature
                        ));
                    }
                    let half = f.length_mm.unwrap_or(0.0) / 2.0;
                    if s.kind == ScanKind::FaceLine {
                        fnum(&format!("{p}.speed_mm_s"), s.speed_mm_s, 0.5, 500.0, "mm/s")?;
                        fnum(&format!("{p}.from_mm"), s.from_mm, -half, half, "mm")?;
                        fnum(&format!("{p}.to_mm"), s.to_mm, -half, half, "mm")?;
                        if (s.to_mm - s.from_mm).abs() < 5.0 {
                            return Err(format!(
                                "{p}.to_mm: a face line needs at least 5 mm along the face"
                            ));
                        }
                    } else {
                        fnum(&format!("{p}.at_mm"), s.at_mm, -half, half, "mm")?;
                        fnum(
                            &format!("{p}.amplitude_mm"),
                            s.amplitude_mm,
                            0.005,
                            0.5,
                            "mm",
                        )?;
                        if s.deflection_mm - s.amplitude_mm < 0.02 {
                            return Err(format!(
                                "{p}.amplitude_mm: {} mm would lift the probe off the face (deflection {} mm): keep amplitude ≤ deflection − 0.02 mm",
                                s.amplitude_mm, s.deflection_mm
                            ));
                        }
                        fnum(
                            &format!("{p}.frequency_hz"),
                            s.frequency_hz,
                            0.2,
                            40.0,
                            "Hz",
                        )?;
                        fnum(&format!("{p}.cycles"), s.cycles, 1.0, 5000.0, "")?;
                        if s.cycles / s.frequency_hz < 1.0 {
                            return Err(format!(
                                "{p}.cycles: {} cycles at {} Hz last less than the 1 s a weave needs (its ramps take {WEAVE_RAMP_S} s)",
                                s.cycles, s.frequency_hz
                            ));
                        }
                        if s.cycles.fract() != 0.0 {
                            return Err(format!(
                                "{p}.cycles: a whole number (the weave ends where it began)"
                            ));
                        }
                    }
                }
            }
        }
        Ok(())
    }

    /// Machine time of the scans alone (ramps included), s.
    pub fn scan_time_s(&self, tip_radius: &dyn Fn(u32) -> f64) -> f64 {
        self.scans
            .iter()
            .map(|s| scan_duration(self, s, tip_radius(s.tip)))
            .sum()
    }
}

/// Path radius of a circle scan's tip centre (free tip): the bore's radius less the tip's
/// plus the deflection, a sphere's plus the tip's less the deflection.
pub fn circle_path_radius(f: &ProgramFeature, tip_r: f64, defl: f64) -> f64 {
    match f.artifact {
        Artifact::Ring => f.nominal_diameter_mm / 2.0 - tip_r + defl,
        _ => f.nominal_diameter_mm / 2.0 + tip_r - defl,
    }
}

/// Duration of one scan segment (ramps included), s, as the simulator plans it.
pub fn scan_duration(p: &Program, s: &Scan, tip_r: f64) -> f64 {
    let Some(f) = p.features.get(s.feature) else {
        return 0.0;
    };
    match s.kind {
        ScanKind::Circle => {
            let r = circle_path_radius(f, tip_r, s.deflection_mm);
            let ramp = circle_ramp_s(s.speed_mm_s);
            TAU * r / s.speed_mm_s + 2.0 * ramp
        }
        ScanKind::FaceLine => {
            let l = (s.to_mm - s.from_mm).abs();
            let v = s.speed_mm_s.min(l / LINE_RAMP_S);
            l / v + LINE_RAMP_S
        }
        ScanKind::FaceWeave => s.cycles / s.frequency_hz + WEAVE_RAMP_S,
    }
}

/// Distance along a path at time t of a segment with cruise speed `v`, ramp `tr`, length `l`
/// (v(t) = v/2·(1 − cos πt/tr) in the ramps), and its first two derivatives.
fn profile(t: f64, v: f64, tr: f64, l: f64) -> (f64, f64, f64) {
    let d = l / v + tr;
    let t = t.clamp(0.0, d);
    let ramp = |t: f64| {
        (
            0.5 * v * (t - tr / PI * (PI * t / tr).sin()),
            0.5 * v * (1.0 - (PI * t / tr).cos()),
            0.5 * v * PI / tr * (PI * t / tr).sin(),
        )
    };
    if t < tr {
        ramp(t)
    } else if t <= d - tr {
        (v * tr / 2.0 + v * (t - tr), v, 0.0)
    } else {
        let (s, sd, sdd) = ramp(d - t);
        (l - s, sd, -sdd)
    }
}

/// How the prediction sees the measurement.
#[derive(Debug, Clone, PartialEq)]
pub struct Assumptions {
    /// Noise of a point along its normal, µm (the calibration's noise floor).
    pub noise_um: f64,
    /// Lag-1 correlation of the residuals.
    pub rho: f64,
    /// Every `stride`-th point of a scan (the lab's `--stride`).
    pub stride: usize,
    /// Every other scan of each feature held out (the lab without `--validate`).
    pub heldout_alternate: bool,
    /// Room temperature at the start, °C, and its rise over the program, K.
    pub temp_c: f64,
    /// Rise over the program, K.
    pub temp_rise_k: f64,
}

impl Default for Assumptions {
    fn default() -> Self {
        Assumptions {
            noise_um: 0.1,
            rho: 0.0,
            stride: 4,
            heldout_alternate: true,
            temp_c: 20.5,
            temp_rise_k: 1.0,
        }
    }
}

impl Assumptions {
    /// The noise floor the calibration's lab figures state (`metrics.noise_floor_um`), else
    /// `fallback`.
    pub fn noise_from(cal: &Calibration, fallback: f64) -> f64 {
        cal.metrics
            .get("noise_floor_um")
            .copied()
            .filter(|v| v.is_finite() && *v > 0.0)
            .unwrap_or(fallback)
    }
}

/// The lab's dataset of the ideal points `program` yields (no measurement: the points lie on
/// the nominal surfaces; their contexts are the commanded motion).
pub fn ideal_dataset(
    cal: &Calibration,
    program: &Program,
    a: &Assumptions,
) -> Result<Dataset, LabError> {
    program
        .validate()
        .map_err(|e| LabError::Data(format!("program: {e}")))?;
    let model = cal.build().map_err(LabError::Calibration)?;
    let mut sensors = model.sensors.clone();
    for s in ["stylus", "scale_x", "scale_y", "scale_z", "air"] {
        sensors.slot(s).map_err(LabError::Data)?;
    }
    let period = cal.sample_period_s;
    if !(period.is_finite() && period > 0.0) {
        return Err(LabError::Data(
            "sample_period_s: the calibration needs a positive sample period".into(),
        ));
    }
    let dt = period * a.stride.max(1) as f64;
    let tip = |id: u32, i: usize| {
        cal.geometry
            .tips
            .iter()
            .find(|t| t.id == id)
            .ok_or_else(|| {
                LabError::Data(format!(
                    "program: scans[{i}].tip: tip {id} is not in the calibration's geometry.tips"
                ))
            })
    };
    let total: f64 = program
        .scans
        .iter()
        .enumerate()
        .map(|(i, s)| tip(s.tip, i).map(|t| scan_duration(program, s, t.radius_mm)))
        .sum::<Result<f64, _>>()?;
    let features: Vec<(usize, FeatureSpec)> = program
        .features
        .iter()
        .enumerate()
        .map(|(i, f)| (0usize, f.spec(i as u32 + 1)))
        .collect();
    let mut points = vec![];
    let mut scan_no = vec![0usize; program.features.len()];
    let mut t_run = 0.0;
    for (i, s) in program.scans.iter().enumerate() {
        let g = tip(s.tip, i)?;
        let f = &program.features[s.feature];
        let pose = TipPose::new(g, s.a1_deg, s.a2_deg);
        let off = pose.shank + pose.bent;
        let rt = g.radius_mm;
        let held = a.heldout_alternate && scan_no[s.feature] % 2 == 1;
        scan_no[s.feature] += 1;
        let d = scan_duration(program, s, rt);
        let c = Vec3::from(f.center_mm);
        let mut t = 0.0;
        while t <= d {
            // carriage, velocity, acceleration, normal out of the material, deflection,
            // surface point, arc (centre, radius, frequency, axis).
            let (car, vel, acc, n, defl, surf, arc) = match s.kind {
                ScanKind::Circle => {
                    let r = circle_path_radius(f, rt, s.deflection_mm);
                    let v = s.speed_mm_s;
                    let ramp = circle_ramp_s(v);
                    let l = TAU * r + v * ramp;
                    let (sp, sd, sdd) = profile(t, v, ramp, l);
                    let dir = s.direction as f64;
                    let th = if s.direction > 0 { 0.0 } else { PI } + dir * sp / r;
                    let u = Vec3::new(th.cos(), th.sin(), 0.0);
                    let tang = Vec3::new(-th.sin(), th.cos(), 0.0) * dir;
                    let cc = c - off;
                    let n = if f.artifact == Artifact::Ring { -u } else { u };
                    (
                        cc + u * r,
                        tang * sd,
                        -u * (sd * sd / r) + tang * sdd,
                        n,
                        s.deflection_mm,
                        c + u * (f.nominal_diameter_mm / 2.0),
                        Some((cc, r, sd / (TAU * r), Vec3::z() * dir)),
                    )
                }
                ScanKind::FaceLine => {
                    let n = f.normal_unit();
                    let al = along_of(&n);
                    let l = (s.to_mm - s.from_mm).abs();
                    let v = s.speed_mm_s.min(l / LINE_RAMP_S);
                    let (sp, sd, sdd) = profile(t, v, LINE_RAMP_S, l);
                    let sign = (s.to_mm - s.from_mm).signum();
                    let pos = s.from_mm + sign * sp;
                    let base = c + n * (rt - s.deflection_mm) - off;
                    (
                        base + al * pos,
                        al * (sign * sd),
                        al * (sign * sdd),
                        n,
                        s.deflection_mm,
                        c + al * pos,
                        None,
                    )
                }
                ScanKind::FaceWeave => {
                    let n = f.normal_unit();
                    let al = along_of(&n);
                    let amp = s.amplitude_mm;
                    let v = s.peak_speed();
                    let l = TAU * amp * s.cycles;
                    let (sp, sd, sdd) = profile(t, v, WEAVE_RAMP_S, l);
                    let ph = sp / amp;
                    let (w, wd) = (sd / amp, sdd / amp);
                    let base = c + n * (rt - s.deflection_mm) - off + al * s.at_mm;
                    (
                        base + n * (amp * ph.sin()),
                        n * (amp * ph.cos() * w),
                        n * (-amp * ph.sin() * w * w + amp * ph.cos() * wd),
                        n,
                        s.deflection_mm - amp * ph.sin(),
                        c + al * s.at_mm,
                        None,
                    )
                }
            };
            let mut ctx = PointContext::at_rest(car);
            let tt = t_run + t;
            ctx.t_ns = (tt * 1e9).round() as i64;
            ctx.est_vel = vel;
            ctx.est_acc = acc;
            if let Some((ac, ar, fz, ax)) = arc {
                if fz > 0.0 {
                    ctx.arc_center = ac;
                    ctx.arc_radius = ar;
                    ctx.f_hz = fz;
                    ctx.rot_axis = ax;
                } else {
                    ctx.arc_center = ac;
                    ctx.arc_radius = ar;
                }
            }
            let dvec = n * defl;
            ctx.deflection = dvec;
            ctx.deflection_probe = pose.machine_from_probe.transpose() * dvec;
            ctx.machine_from_probe = pose.machine_from_probe;
            ctx.tip_shank = pose.shank;
            ctx.tip_bent = pose.bent;
            ctx.tip_radius = rt;
            ctx.tip_id = s.tip;
            ctx.head_a1_deg = s.a1_deg;
            ctx.head_a2_deg = s.a2_deg;
            ctx.segment_id = i as u32 + 1;
            let temp = a.temp_c + a.temp_rise_k * tt / total.max(1e-9);
            ctx.temps = [temp; MAX_SENSORS];
            ctx.temps_valid = (1u16 << MAX_SENSORS) - 1;
            points.push(LabPoint {
                ctx,
                surface: surf,
                normal: n,
                feature: s.feature,
                segment: i as u32 + 1,
                bag: 0,
                speed: s.peak_speed(),
                direction: if s.kind == ScanKind::Circle {
                    s.direction
                } else {
                    0
                },
                phase: Phase::Steady,
                held_out: held,
            });
            t += dt;
        }
        t_run += d;
    }
    Ok(Dataset {
        points,
        features,
        sensors,
        noise_floor_um: a.noise_um,
        tracking: vec![],
        calibration: cal.clone(),
        warnings: vec![],
    })
}

/// A parameter's predicted uncertainty.
#[derive(Debug, Clone, Serialize)]
pub struct ParamSigma {
    /// Effect id (with the candidate's variant for a candidate).
    pub effect: String,
    /// Parameter name with unit.
    pub name: String,
    /// Its current value (0 for a candidate).
    pub value: f64,
    /// Predicted standard uncertainty; None when the design cannot determine it.
    pub sigma: Option<f64>,
}

/// A correlation between two parameters' estimates.
#[derive(Debug, Clone, Serialize)]
pub struct Correlation {
    /// First parameter (`effect: name`).
    pub a: String,
    /// Second.
    pub b: String,
    /// Correlation coefficient.
    pub r: f64,
}

/// What a design will determine.
#[derive(Debug, Clone, Serialize)]
pub struct Prediction {
    /// Every parameter of every effect (model first, then candidates).
    pub params: Vec<ParamSigma>,
    /// The strongest correlations between determined parameters (|r| ≥ 0.9, at most 12).
    pub correlations: Vec<Correlation>,
    /// Parameters the design cannot determine (`effect: name`).
    pub undetermined: Vec<String>,
    /// Points the lab would fit.
    pub points: usize,
    /// The noise and correlation assumed: µm, ρ.
    pub noise_um: f64,
    /// ρ.
    pub rho: f64,
}

impl Prediction {
    /// The predicted σ of `effect: name` (None: undetermined or absent).
    pub fn sigma_of(&self, effect: &str, name: &str) -> Option<f64> {
        self.params
            .iter()
            .find(|p| p.effect == effect && p.name == name)
            .and_then(|p| p.sigma)
    }
}

/// The configs a prediction covers: the model's effects, then each candidate (by library
/// name, e.g. `servo_gain:powers=1+2`, `rigid_body`) not already in the model as that kind.
pub fn configs_for(
    ds: &Dataset,
    candidates: &[String],
) -> Result<Vec<(String, EffectConfig)>, LabError> {
    let mut v: Vec<(String, EffectConfig)> = ds
        .calibration
        .effects
        .iter()
        .map(|c| (c.id(), c.clone()))
        .collect();
    for name in candidates {
        let cfg = analysis::candidate(name, ds)?;
        if v.iter().any(|(_, c)| c.kind() == cfg.kind()) {
            continue;
        }
        v.push((name.clone(), cfg));
    }
    Ok(v)
}

/// Predicts each parameter's σ from the design alone (see the module's equation): the
/// calibration's effects and the `candidates` on the ideal points of `program`.
pub fn predict(
    cal: &Calibration,
    program: &Program,
    candidates: &[String],
    a: &Assumptions,
) -> Result<Prediction, LabError> {
    if !(a.noise_um.is_finite() && a.noise_um > 0.0) {
        return Err(LabError::Data(format!(
            "noise: {} µm is not a positive noise floor",
            a.noise_um
        )));
    }
    if !(a.rho.is_finite() && (0.0..0.99).contains(&a.rho)) {
        return Err(LabError::Data(format!(
            "rho: {} is not a lag-1 correlation in [0, 0.99)",
            a.rho
        )));
    }
    let ds = ideal_dataset(cal, program, a)?;
    let configs = configs_for(&ds, candidates)?;
    predict_on(&ds, &configs, a)
}

/// [`predict`] on a dataset already made, for `configs` (name, config).
pub fn predict_on(
    ds: &Dataset,
    configs: &[(String, EffectConfig)],
    a: &Assumptions,
) -> Result<Prediction, LabError> {
    let surfaces: Vec<Vec3> = ds.points.iter().map(|p| p.surface).collect();
    let all = vec![true; ds.points.len()];
    let art = fit_artifacts(ds, &surfaces, &all);
    let mut sensors: SensorTable = ds.sensors.clone();
    let mut models = vec![];
    let mut offs = vec![];
    let mut k = 0;
    for (name, c) in configs {
        let b = c
            .build(&mut sensors)
            .map_err(|e| LabError::Data(format!("{name}: {e}")))?;
        offs.push(k);
        k += b.model.n_params();
        models.push(b.model);
    }
    let fit_pt: Vec<bool> = ds
        .points
        .iter()
        .map(|p| !p.held_out && art.features[p.feature].is_some())
        .collect();
    let n_fit = fit_pt.iter().filter(|b| **b).count();
    if n_fit < 50 {
        return Err(LabError::Data(
            "the program gives fewer than 50 points to fit: add scans".into(),
        ));
    }
    let nmax = models.iter().map(|m| m.n_params()).max().unwrap_or(0);
    let mut r = vec![Vec3::zeros(); nmax];
    let mut row = vec![0.0; k];
    let rows = |i: usize, r: &mut Vec<Vec3>, row: &mut Vec<f64>| {
        let p = &ds.points[i];
        let g = art.grad[i];
        for (m, &o) in models.iter().zip(&offs) {
            let n = m.n_params();
            m.regressors(&p.ctx, &mut r[..n]);
            for j in 0..n {
                let x = g.dot(&r[j]);
                row[o + j] = if x.is_finite() { x } else { 0.0 };
            }
        }
    };
    // Pass 1: column strength (the lab does not fit a column far weaker than its effect's
    // strongest).
    let mut ss = vec![0.0; k];
    for i in (0..ds.points.len()).filter(|i| fit_pt[*i]) {
        rows(i, &mut r, &mut row);
        for j in 0..k {
            ss[j] += row[j] * row[j];
        }
    }
    let mut keep = vec![true; k];
    for (m, &o) in models.iter().zip(&offs) {
        let n = m.n_params();
        let top = (o..o + n).map(|j| ss[j].sqrt()).fold(0.0, f64::max);
        for j in o..o + n {
            keep[j] = top > 0.0 && ss[j].sqrt() > 1e-3 * top;
        }
    }
    let kept: Vec<usize> = (0..k).filter(|j| keep[*j]).collect();
    let mut ne = Normal::new(kept.len() + art.n_cols);
    let mut dense = vec![0.0; kept.len()];
    let mut nu = vec![];
    for i in (0..ds.points.len()).filter(|i| fit_pt[*i]) {
        rows(i, &mut r, &mut row);
        for (d, &j) in dense.iter_mut().zip(&kept) {
            *d = row[j];
        }
        nuisance_row(&art, &ds.points[i], &ds.points[i].surface, &mut nu);
        ne.add(&dense, &nu, 0.0);
    }
    let sol = ne.solve();
    let infl = (1.0 + a.rho) / (1.0 - a.rho);
    let noise = a.noise_um * 1e-3;
    let mut params = vec![];
    let mut undetermined = vec![];
    let mut label = vec![];
    for ((name, c), &o) in configs.iter().zip(&offs) {
        let effect = if c.kind() == name || c.id() == *name {
            c.id()
        } else {
            name.clone()
        };
        for (j, (pn, v)) in c.param_names().into_iter().zip(c.params()).enumerate() {
            let col = kept.iter().position(|x| *x == o + j);
            let sigma = col.and_then(|cc| {
                (!sol.unidentifiable.contains(&cc))
                    .then(|| noise * (sol.cov[(cc, cc)] * infl).max(0.0).sqrt())
                    .filter(|s| s.is_finite())
            });
            if sigma.is_none() {
                undetermined.push(format!("{effect}: {pn}"));
            }
            if let Some(cc) = col {
                label.push((cc, format!("{effect}: {pn}"), sigma.is_some()));
            }
            params.push(ParamSigma {
                effect: effect.clone(),
                name: pn,
                value: v,
                sigma,
            });
        }
    }
    let mut correlations = vec![];
    for (x, (ci, li, oki)) in label.iter().enumerate() {
        for (cj, lj, okj) in label.iter().skip(x + 1) {
            if !(oki & okj) {
                continue;
            }
            let d = (sol.cov[(*ci, *ci)] * sol.cov[(*cj, *cj)]).sqrt();
            if d > 0.0 {
                let rr = sol.cov[(*ci, *cj)] / d;
                if rr.is_finite() && rr.abs() >= 0.9 {
                    correlations.push(Correlation {
                        a: li.clone(),
                        b: lj.clone(),
                        r: rr,
                    });
                }
            }
        }
    }
    correlations.sort_by(|p, q| {
        q.r.abs()
            .total_cmp(&p.r.abs())
            .then_with(|| p.a.cmp(&q.a))
            .then_with(|| p.b.cmp(&q.b))
    });
    correlations.truncate(12);
    Ok(Prediction {
        params,
        correlations,
        undetermined,
        points: n_fit,
        noise_um: a.noise_um,
        rho: a.rho,
    })
}

/// An artifact the user owns (`ring:d=50`, `sphere:d=25`, `straightedge:l=400`).
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Owned {
    /// What it is.
    pub artifact: Artifact,
    /// Certified diameter (ring, sphere) or length (straightedge), mm.
    pub size_mm: f64,
}

impl Owned {
    /// Parses `ring:d=50.0012`, `sphere:d=25.0004`, `straightedge:l=400`.
    pub fn parse(s: &str) -> Result<Owned, String> {
        let (kind, rest) = s.split_once(':').unwrap_or((s, ""));
        let (artifact, key) = match kind {
            "ring" => (Artifact::Ring, "d"),
            "sphere" => (Artifact::Sphere, "d"),
            "straightedge" => (Artifact::Straightedge, "l"),
            _ => {
                return Err(format!(
                    "`{s}`: unknown artifact `{kind}` (ring:d=…, sphere:d=…, straightedge:l=…)"
                ))
            }
        };
        let mut size = None;
        for kv in rest.split(',').filter(|k| !k.is_empty()) {
            match kv.split_once('=') {
                Some((k, v)) if k == key => {
                    size = v.parse::<f64>().ok().filter(|x| x.is_finite() && *x > 0.0);
                    if size.is_none() {
                        return Err(format!("`{s}`: {k}= must be a positive number of mm"));
                    }
                }
                _ => return Err(format!("`{s}`: `{kv}`: expected {key}=MM")),
            }
        }
        let size_mm = size.ok_or_else(|| format!("`{s}`: give its size, e.g. {kind}:{key}=…"))?;
        let (lo, hi) = match artifact {
            Artifact::Straightedge => (50.0, 3000.0),
            _ => (5.0, 500.0),
        };
        fnum(&format!("`{s}`: {key}"), size_mm, lo, hi, "mm")?;
        Ok(Owned { artifact, size_mm })
    }
}

/// What the planner is asked.
#[derive(Debug, Clone)]
pub struct PlanRequest {
    /// The machine's travel, [min, max] per axis, mm.
    pub travel_mm: [[f64; 2]; 3],
    /// The artifacts the user owns.
    pub owned: Vec<Owned>,
    /// Machine time available, minutes.
    pub minutes: f64,
    /// Candidate effects to make identifiable as well as the model's (library names).
    pub candidates: Vec<String>,
    /// How the prediction sees the measurement.
    pub assumptions: Assumptions,
}

/// A group of scans the plan takes or leaves, with why.
#[derive(Debug, Clone, Serialize)]
pub struct GroupSummary {
    /// What is scanned, where.
    pub what: String,
    /// What it determines.
    pub why: String,
    /// Machine time, minutes (moves and dwells included).
    pub minutes: f64,
}

/// A plan: the program, its groups, what was left out for time and the prediction.
#[derive(Debug, Clone, Serialize)]
pub struct Planned {
    /// The program record (`sim --program`, or the part program to write).
    pub program: Program,
    /// The groups taken, in order.
    pub groups: Vec<GroupSummary>,
    /// Groups left out for lack of time.
    pub left_out: Vec<GroupSummary>,
    /// Machine time, minutes.
    pub minutes: f64,
    /// Predicted uncertainties.
    pub prediction: Prediction,
}

struct Group {
    what: String,
    why: String,
    features: Vec<ProgramFeature>,
    /// Scans with `feature` indices local to `features`.
    scans: Vec<Scan>,
}

fn circle(feature: usize, speed: f64, dir: i32, defl: f64, tip: u32, a1: f64, why: &str) -> Scan {
    Scan {
        kind: ScanKind::Circle,
        feature,
        tip,
        a1_deg: a1,
        a2_deg: 0.0,
        deflection_mm: defl,
        speed_mm_s: speed,
        direction: dir,
        from_mm: 0.0,
        to_mm: 0.0,
        at_mm: 0.0,
        amplitude_mm: 0.0,
        frequency_hz: 0.0,
        cycles: 0.0,
        why: why.into(),
    }
}

fn ring_at(c: Vec3, d: f64) -> ProgramFeature {
    ProgramFeature {
        artifact: Artifact::Ring,
        center_mm: c.into(),
        nominal_diameter_mm: (d * 10.0).round() / 10.0,
        certified_diameter_mm: Some(d),
        normal: None,
        length_mm: None,
    }
}

/// Weave amplitude, mm, deflection, mm, and frequencies, Hz, of the planned face weaves:
/// 0.1 mm about 0.3 mm of deflection (the probe stays in its range), at 4 and 8 Hz — peak
/// accelerations 63 and 253 mm/s², those of a 50 mm ring at 40 and 80 mm/s, well below the
/// structure's modes (the deflection follows the acceleration).
pub const WEAVE: (f64, f64, [f64; 2]) = (0.1, 0.3, [4.0, 8.0]);

/// Plans a campaign (a fixed design rule, taken in order of what it determines until the
/// time runs out): the largest ring at the centre of the travel at four speeds in both
/// directions and three deflections (probe force, the dynamics); at the eight corners of a box
/// spanning 70 % of the travel (rigid-body terms, the position dependence of the deflection
/// matrix); face weaves along x, y and z normals (acceleration along the measured direction
/// off arcs: separates `accel_deflection` from `servo_gain`); a second ring diameter or the
/// sphere's equator at three speeds (f = v/2πr and v²/r scale differently); the sphere with
/// every tip and two head angles; the straightedge along x with two tips (the guide); then
/// the ring at the edges' midpoints.
pub fn plan(cal: &Calibration, req: &PlanRequest) -> Result<Planned, LabError> {
    let tr = req.travel_mm;
    for (i, [lo, hi]) in tr.iter().enumerate() {
        if !(lo.is_finite() && hi.is_finite() && hi - lo >= 100.0) {
            return Err(LabError::Data(format!(
                "travel[{i}]: {lo}…{hi} mm is not a travel of at least 100 mm"
            )));
        }
    }
    if !(req.minutes.is_finite() && req.minutes > 0.0) {
        return Err(LabError::Data(format!(
            "minutes: {} is not a positive time",
            req.minutes
        )));
    }
    let tips: Vec<&crate::stylus::TipGeometry> = cal.geometry.tips.iter().collect();
    let Some(t1) = tips.first() else {
        return Err(LabError::Data(
            "geometry.tips: the calibration has no tip to plan with".into(),
        ));
    };
    let off1 = {
        let p = TipPose::new(t1, 0.0, 0.0);
        p.shank + p.bent
    };
    // Carriage positions as fractions of the travel; features where the first tip reaches.
    let at = |fx: f64, fy: f64, fz: f64| {
        Vec3::new(
            tr[0][0] + fx * (tr[0][1] - tr[0][0]),
            tr[1][0] + fy * (tr[1][1] - tr[1][0]),
            tr[2][0] + fz * (tr[2][1] - tr[2][0]),
        ) + off1
    };
    let mut rings: Vec<f64> = req
        .owned
        .iter()
        .filter(|o| o.artifact == Artifact::Ring)
        .map(|o| o.size_mm)
        .collect();
    rings.sort_by(|a, b| b.total_cmp(a));
    let sphere = req
        .owned
        .iter()
        .find(|o| o.artifact == Artifact::Sphere)
        .map(|o| o.size_mm);
    let edge = req
        .owned
        .iter()
        .filter(|o| o.artifact == Artifact::Straightedge)
        .map(|o| o.size_mm)
        .fold(None, |a: Option<f64>, l| Some(a.map_or(l, |a| a.max(l))));
    let Some(&big) = rings.first() else {
        return Err(LabError::Data(
            "artifacts: the plan needs a ring gauge (--artifact ring:d=50)".into(),
        ));
    };
    let centre = at(0.5, 0.5, 0.5);
    let mut groups: Vec<Group> = vec![];
    // 1. The ring at the centre.
    {
        let why = "speeds and deflections: the deflection matrix, the servo phase, the probe force";
        let mut scans = vec![];
        for v in [10.0, 30.0, 60.0, 90.0] {
            scans.push(circle(0, v, 1, 0.3, t1.id, 0.0, why));
            scans.push(circle(0, v, -1, 0.3, t1.id, 0.0, why));
        }
        for d in [0.1, 0.5] {
            scans.push(circle(0, 30.0, 1, d, t1.id, 0.0, why));
            scans.push(circle(0, 30.0, -1, d, t1.id, 0.0, why));
        }
        groups.push(Group {
            what: format!(
                "ring d={big} mm at the centre ({:.0}, {:.0}, {:.0}): 10–90 mm/s both ways, deflections 0.1/0.3/0.5 mm",
                centre.x, centre.y, centre.z
            ),
            why: why.into(),
            features: vec![ring_at(centre, big)],
            scans,
        });
    }
    // 2. The ring at the corners.
    {
        let why = "positions spread over the volume: the rigid-body terms, the deflection matrix's position dependence";
        let mut features = vec![];
        let mut scans = vec![];
        for fz in [0.15, 0.85] {
            for fy in [0.15, 0.85] {
                for fx in [0.15, 0.85] {
                    let i = features.len();
                    features.push(ring_at(at(fx, fy, fz), big));
                    scans.push(circle(i, 30.0, 1, 0.3, t1.id, 0.0, why));
                    scans.push(circle(i, 60.0, -1, 0.3, t1.id, 0.0, why));
                }
            }
        }
        groups.push(Group {
            what: format!(
                "ring d={big} mm at the 8 corners of a box over 70 % of the travel: 30 mm/s CCW, 60 mm/s CW"
            ),
            why: why.into(),
            features,
            scans,
        });
    }
    // 3. Face weaves along each axis' normal.
    if let Some(l) = edge {
        let (amp, defl, freqs) = WEAVE;
        for (axis, normal, c) in [
            ("y", [0.0, -1.0, 0.0], at(0.5, 0.75, 0.5)),
            ("x", [-1.0, 0.0, 0.0], at(0.75, 0.5, 0.5)),
            ("z", [0.0, 0.0, 1.0], at(0.5, 0.5, 0.3)),
        ] {
            let why = "acceleration along the measured direction off arcs: accel_deflection (responds) apart from servo_gain (only on arcs)";
            let mut scans = vec![];
            for s in [-l / 3.0, 0.0, l / 3.0] {
                for f in freqs {
                    scans.push(Scan {
                        kind: ScanKind::FaceWeave,
                        at_mm: (s * 10.0).round() / 10.0,
                        amplitude_mm: amp,
                        frequency_hz: f,
                        cycles: (6.0 * f).round(),
                        ..circle(0, 0.0, 0, defl, t1.id, 0.0, why)
                    });
                }
            }
            groups.push(Group {
                what: format!(
                    "straightedge l={l} mm, face normal along {axis}: weaves of ±{amp} mm at {} and {} Hz at three places",
                    freqs[0], freqs[1]
                ),
                why: why.into(),
                features: vec![ProgramFeature {
                    artifact: Artifact::Straightedge,
                    center_mm: c.into(),
                    nominal_diameter_mm: 0.0,
                    certified_diameter_mm: None,
                    normal: Some(normal),
                    length_mm: Some(l),
                }],
                scans,
            });
        }
    }
    // 4. A second diameter: another ring, or the sphere's equator.
    let small = rings
        .get(1)
        .copied()
        .map(|d| (Artifact::Ring, d))
        .or(sphere.map(|d| (Artifact::Sphere, d)));
    if let Some((art, d)) = small {
        let why = "another diameter: the rotation frequency v/2πr and the acceleration v²/r scale differently (servo_gain in f against accel_deflection)";
        let c = at(0.35, 0.35, 0.5);
        let mut scans = vec![];
        for v in [20.0, 40.0, 60.0] {
            scans.push(circle(0, v, 1, 0.3, t1.id, 0.0, why));
            scans.push(circle(0, v, -1, 0.3, t1.id, 0.0, why));
        }
        groups.push(Group {
            what: format!(
                "{} d={d} mm at ({:.0}, {:.0}, {:.0}): 20–60 mm/s both ways",
                if art == Artifact::Ring {
                    "ring"
                } else {
                    "sphere's equator"
                },
                c.x,
                c.y,
                c.z
            ),
            why: why.into(),
            features: vec![ProgramFeature {
                artifact: art,
                ..ring_at(c, d)
            }],
            scans,
        });
    }
    // 5. The sphere with every tip and two head angles.
    if let Some(d) = sphere {
        let why = "every tip and head angle: the styli's offsets, their bending (per-tip force), their expansion";
        let c = at(0.65, 0.35, 0.5);
        let mut scans = vec![];
        for t in &tips {
            for a1 in if t.id == t1.id {
                vec![0.0]
            } else {
                vec![0.0, 90.0]
            } {
                scans.push(circle(0, 30.0, 1, 0.3, t.id, a1, why));
                scans.push(circle(0, 60.0, -1, 0.3, t.id, a1, why));
            }
        }
        groups.push(Group {
            what: format!(
                "sphere d={d} mm at ({:.0}, {:.0}, {:.0}): every tip, head angles 0° and 90°",
                c.x, c.y, c.z
            ),
            why: why.into(),
            features: vec![ProgramFeature {
                artifact: Artifact::Sphere,
                ..ring_at(c, d)
            }],
            scans,
        });
    }
    // 6. The straightedge along x: the guide.
    if let Some(l) = edge {
        let why =
            "the X guide's straightness and yaw (two tips: the bent one's offset is an Abbe lever)";
        let c = at(0.5, 0.85, 0.5);
        let s = (0.4 * l).min(0.4 * (tr[0][1] - tr[0][0]));
        let s = (s * 10.0).round() / 10.0;
        let mut scans = vec![];
        for t in tips.iter().take(2) {
            for (a, b) in [(s, -s), (-s, s)] {
                scans.push(Scan {
                    kind: ScanKind::FaceLine,
                    from_mm: a,
                    to_mm: b,
                    ..circle(0, 50.0, 0, 0.3, t.id, 0.0, why)
                });
            }
        }
        groups.push(Group {
            what: format!(
                "straightedge l={l} mm along x at y {:.0} mm: lines both ways",
                c.y
            ),
            why: why.into(),
            features: vec![ProgramFeature {
                artifact: Artifact::Straightedge,
                center_mm: c.into(),
                nominal_diameter_mm: 0.0,
                certified_diameter_mm: None,
                normal: Some([0.0, -1.0, 0.0]),
                length_mm: Some(l),
            }],
            scans,
        });
    }
    // 7. The ring at the edges' midpoints.
    {
        let why = "more positions: the rigid-body terms' curvature, tighter";
        let mut features = vec![];
        let mut scans = vec![];
        for (fx, fy, fz) in [
            (0.5, 0.15, 0.15),
            (0.5, 0.85, 0.15),
            (0.5, 0.15, 0.85),
            (0.5, 0.85, 0.85),
            (0.15, 0.5, 0.15),
            (0.85, 0.5, 0.15),
            (0.15, 0.5, 0.85),
            (0.85, 0.5, 0.85),
            (0.15, 0.15, 0.5),
            (0.85, 0.15, 0.5),
            (0.15, 0.85, 0.5),
            (0.85, 0.85, 0.5),
        ] {
            let i = features.len();
            features.push(ring_at(at(fx, fy, fz), big));
            scans.push(circle(i, 30.0, 1, 0.3, t1.id, 0.0, why));
            scans.push(circle(i, 30.0, -1, 0.3, t1.id, 0.0, why));
        }
        groups.push(Group {
            what: format!("ring d={big} mm at the 12 edges' midpoints: 30 mm/s both ways"),
            why: why.into(),
            features,
            scans,
        });
    }
    // Take the groups in order while they fit the time.
    let budget = req.minutes * 60.0;
    let mut program = Program {
        name: "lab-plan".into(),
        note: format!(
            "planned by `scancorr lab plan` for {} v{}",
            cal.machine_id, cal.version
        ),
        features: vec![],
        scans: vec![],
    };
    let mut taken = vec![];
    let mut left_out = vec![];
    let tip_r = |id: u32| {
        cal.geometry
            .tips
            .iter()
            .find(|t| t.id == id)
            .map(|t| t.radius_mm)
            .unwrap_or(1.0)
    };
    let mut used = 0.0;
    for g in groups {
        let base = program.features.len();
        let mut trial = program.clone();
        trial.features.extend(g.features.iter().cloned());
        trial.scans.extend(g.scans.iter().cloned().map(|mut s| {
            s.feature += base;
            s
        }));
        let t = machine_time_s(&trial, &tip_r);
        let summary = GroupSummary {
            what: g.what.clone(),
            why: g.why.clone(),
            minutes: (t - used) / 60.0,
        };
        if t <= budget {
            program = trial;
            used = t;
            taken.push(summary);
        } else {
            left_out.push(summary);
        }
    }
    if program.scans.is_empty() {
        return Err(LabError::Data(format!(
            "minutes: {} min is too short for the first group of scans ({:.1} min)",
            req.minutes,
            left_out.first().map(|g| g.minutes).unwrap_or(0.0)
        )));
    }
    program
        .validate()
        .map_err(|e| LabError::Data(format!("the planned program: {e}")))?;
    let prediction = predict(cal, &program, &req.candidates, &req.assumptions)?;
    Ok(Planned {
        minutes: used / 60.0,
        program,
        groups: taken,
        left_out,
        prediction,
    })
}

/// Machine time of a program, s: each scan with the move to it (from the end of the last at
/// [`MOVE_SPEED_MM_S`]), its dwells and its ramps.
pub fn machine_time_s(p: &Program, tip_r: &dyn Fn(u32) -> f64) -> f64 {
    let mut last: Option<Vec3> = None;
    let mut t = 0.0;
    for s in &p.scans {
        let Some(f) = p.features.get(s.feature) else {
            continue;
        };
        let c = Vec3::from(f.center_mm);
        if let Some(l) = last {
            let d = (c - l).norm();
            if d > 1.0 {
                t += d / MOVE_SPEED_MM_S + 0.3;
            }
        }
        last = Some(c);
        // The dwells, the scan, and the short move between two scans of one feature.
        t += DWELLS_S + scan_duration(p, s, tip_r(s.tip)) + 0.5;
    }
    t
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::effects::accel_deflection;

    fn ring_prog(weaves: &[[f64; 3]]) -> Program {
        let mut p = Program {
            name: "t".into(),
            note: String::new(),
            features: vec![ring_at(Vec3::new(400.0, 300.0, -300.0), 50.0012)],
            scans: vec![],
        };
        for v in [10.0, 30.0, 60.0, 90.0] {
            for d in [1, -1] {
                p.scans.push(circle(0, v, d, 0.3, 1, 0.0, ""));
            }
        }
        for n in weaves {
            p.features.push(ProgramFeature {
                artifact: Artifact::Straightedge,
                center_mm: [500.0, 400.0, -300.0],
                nominal_diameter_mm: 0.0,
                certified_diameter_mm: None,
                normal: Some(*n),
                length_mm: Some(400.0),
            });
            let f = p.features.len() - 1;
            for at in [-100.0, 100.0] {
                for hz in [4.0, 8.0] {
                    p.scans.push(Scan {
                        kind: ScanKind::FaceWeave,
                        at_mm: at,
                        amplitude_mm: 0.1,
                        frequency_hz: hz,
                        cycles: 6.0 * hz,
                        ..circle(f, 0.0, 0, 0.3, 1, 0.0, "")
                    });
                }
            }
        }
        p
    }

    fn cal() -> Calibration {
        let mut c = Calibration::example("m1");
        c.effects = vec![EffectConfig::AccelDeflection(
            accel_deflection::Config::zeros(0, true),
        )];
        c
    }

    #[test]
    fn a_program_record_names_the_field_it_refuses() {
        let mut p = ring_prog(&[[0.0, -1.0, 0.0]]);
        assert!(p.validate().is_ok());
        p.scans[1].speed_mm_s = 0.0;
        assert!(p.validate().unwrap_err().contains("scans[1].speed_mm_s"));
        let mut p = ring_prog(&[[0.0, -1.0, 0.0]]);
        let w = p.scans.len() - 1;
        p.scans[w].amplitude_mm = 0.29;
        assert!(p
            .validate()
            .unwrap_err()
            .contains(&format!("scans[{w}].amplitude_mm")));
        let mut p = ring_prog(&[]);
        p.scans[0].feature = 5;
        assert!(p.validate().unwrap_err().contains("scans[0].feature"));
        let j = ring_prog(&[]).to_json().replacen("\"why\"", "\"whyy\"", 1);
        assert!(Program::from_json(&j).unwrap_err().contains("whyy"));
        assert!(Program::from_json(&ring_prog(&[[1.0, 0.0, 0.0]]).to_json()).is_ok());
    }

    #[test]
    fn face_weaves_separate_compliance_from_the_servo_gain() {
        let a = Assumptions {
            stride: 16,
            ..Assumptions::default()
        };
        let cands = ["servo_gain".to_string()];
        let rings = predict(&cal(), &ring_prog(&[]), &cands, &a).unwrap();
        let woven = predict(
            &cal(),
            &ring_prog(&[[0.0, -1.0, 0.0], [-1.0, 0.0, 0.0], [0.0, 0.0, 1.0]]),
            &cands,
            &a,
        )
        .unwrap();
        let p_names: Vec<String> = rings
            .params
            .iter()
            .filter(|p| p.effect == "accel_deflection")
            .map(|p| p.name.clone())
            .collect();
        assert_eq!(p_names.len(), 3, "{p_names:?}");
        // On rings alone P_xx and the f² gain along x are nearly one column; P_zz unseen.
        let corr = |pr: &Prediction| {
            pr.correlations
                .iter()
                .filter(|c| c.a.starts_with("accel_deflection") && c.b.starts_with("servo_gain"))
                .map(|c| c.r.abs())
                .fold(0.0, f64::max)
        };
        let lost = |pr: &Prediction| {
            pr.undetermined
                .iter()
                .any(|u| u.contains("P[x][x]") || u.contains("α_x"))
        };
        // (Only the speed ramps' tangential acceleration tells them apart on one ring.)
        assert!(
            corr(&rings) > 0.9 || lost(&rings),
            "{:?} {:?}",
            rings.correlations,
            rings.undetermined
        );
        assert!(rings.sigma_of("accel_deflection", &p_names[2]).is_none());
        // With weaves along x, y and z the correlation falls and P_zz is determined.
        assert!(
            corr(&woven) < 0.9 && !lost(&woven),
            "{:?} {:?}",
            woven.correlations,
            woven.undetermined
        );
        let s1 = woven.sigma_of("accel_deflection", &p_names[0]).unwrap();
        let s0 = rings
            .sigma_of("accel_deflection", &p_names[0])
            .unwrap_or(f64::INFINITY);
        assert!(s1 < s0, "σ(P_xx) {s0:e} → {s1:e}");
        assert!(woven.sigma_of("accel_deflection", &p_names[2]).is_some());
        let gain: Vec<&ParamSigma> = woven
            .params
            .iter()
            .filter(|p| p.effect == "servo_gain")
            .collect();
        assert!(!gain.is_empty());
        // x and y (horizontal circles never move z about a centre).
        assert!(
            gain.iter().filter(|p| p.sigma.is_some()).count() >= 2,
            "{gain:?}"
        );
    }

    #[test]
    fn the_planner_stays_within_its_time_and_determines_the_deflection_matrix() {
        let req = PlanRequest {
            travel_mm: [[0.0, 1000.0], [0.0, 800.0], [-600.0, 0.0]],
            owned: ["ring:d=50.0012", "sphere:d=25.0004", "straightedge:l=400"]
                .iter()
                .map(|s| Owned::parse(s).unwrap())
                .collect(),
            minutes: 8.0,
            candidates: vec!["servo_gain:powers=1+2".into()],
            assumptions: Assumptions {
                stride: 16,
                ..Assumptions::default()
            },
        };
        let p = plan(&cal(), &req).unwrap();
        assert!(p.minutes <= 8.0 && p.minutes > 4.0, "{}", p.minutes);
        assert!(!p.left_out.is_empty(), "8 minutes cannot hold every group");
        assert!(p.program.validate().is_ok());
        for q in p
            .prediction
            .params
            .iter()
            .filter(|q| q.effect == "accel_deflection")
        {
            assert!(q.sigma.is_some(), "{} undetermined", q.name);
        }
        assert!(Owned::parse("ring").unwrap_err().contains("ring:d="));
        assert!(Owned::parse("plate:d=3").is_err());
    }
}
