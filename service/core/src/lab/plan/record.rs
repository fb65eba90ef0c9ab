//! The program record: what a campaign measures (artifacts, scans, speeds, directions, face
//! weaves along a normal), as `sim --program FILE` runs it, checked field by field, and how
//! long each scan takes (the controller's ramps and moves).

use super::*;

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
    /// The temperature span the program should be measured over (see `plan::thermal`);
    /// absent: whatever the room does.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub temperature: Option<TemperatureSpan>,
}

/// The temperature span a program asks for: the room's (and so the scales' and styli's)
/// temperature rising by `span_k` from the first scan to the last, about linearly.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct TemperatureSpan {
    /// Rise from the first scan to the last, K; 0 … 20 K.
    pub span_k: f64,
    /// Why (what it buys), for people.
    #[serde(default)]
    pub why: String,
}

/// Largest temperature span a program may ask for, K.
pub const MAX_SPAN_K: f64 = 20.0;

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

pub(super) fn fnum(field: &str, v: f64, lo: f64, hi: f64, unit: &str) -> Result<(), String> {
    crate::checks::in_range(field, v, lo, hi, unit)
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
    pub(super) fn normal_unit(&self) -> Vec3 {
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
        if let Some(t) = &self.temperature {
            fnum("temperature.span_k", t.span_k, 0.0, MAX_SPAN_K, "K")?;
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
pub(super) fn profile(t: f64, v: f64, tr: f64, l: f64) -> (f64, f64, f64) {
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
