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

use super::candidates;
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

mod greedy;
mod predict;
mod record;
mod thermal;
pub use predict::*;
pub use record::*;
pub use thermal::*;

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

#[derive(Clone)]
struct Group {
    what: String,
    why: String,
    features: Vec<ProgramFeature>,
    /// Scans with `feature` indices local to `features`.
    scans: Vec<Scan>,
    /// The effect kinds it is for (a group for a requested candidate comes before the
    /// others); empty: the base every plan starts with.
    serves: &'static [&'static str],
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

/// Plans a campaign. Groups of scans, each for what it determines: the largest ring at the
/// centre of the travel at four speeds in both directions and three deflections (probe force,
/// the dynamics; every plan starts with it); at the eight corners of a box spanning 70 % of
/// the travel (rigid-body terms, the position dependence of the deflection matrix); face
/// weaves along x, y and z normals (acceleration along the measured direction off arcs:
/// separates `accel_deflection` from `servo_gain`); a second ring diameter or the sphere's
/// equator at three speeds (f = v/2πr and v²/r scale differently); the sphere with every tip
/// and two head angles; the straightedge along x with two tips (the guide). The groups for the
/// requested candidates come first; then, when the rigid body is a candidate or in the model,
/// the ring placed one place at a time where it most reduces the predicted variance of the
/// rigid-body terms per minute (see [`greedy`]) in the time those leave; then the other
/// groups while time is left. When the prediction then leaves a rigid-body term within reach
/// undetermined, the places are chosen again with every stylus along that term's axis.
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
    // The first tip, then every other at head angles 0° and 90° (as on the sphere): the
    // styli a rigid-body place may be scanned with, and their offsets.
    let styli: Vec<(u32, f64, Vec3)> = tips
        .iter()
        .flat_map(|t| {
            let a1s: &[f64] = if t.id == t1.id { &[0.0] } else { &[0.0, 90.0] };
            a1s.iter().map(move |a1| {
                let p = TipPose::new(t, *a1, 0.0);
                (t.id, *a1, p.shank + p.bent)
            })
        })
        .collect();
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
            serves: &[],
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
            serves: &["rigid_body"],
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
                serves: &["servo_gain", "accel_deflection"],
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
            serves: &["servo_gain", "accel_deflection"],
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
            serves: &["stylus_thermal", "probe_force"],
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
            serves: &["guide_straightness"],
        });
    }
    // Take the groups in order while they fit the time.
    let budget = req.minutes * 60.0;
    let tip_r = |id: u32| {
        cal.geometry
            .tips
            .iter()
            .find(|t| t.id == id)
            .map(|t| t.radius_mm)
            .unwrap_or(1.0)
    };
    let kinds: Vec<&str> = req
        .candidates
        .iter()
        .map(|c| c.split(':').next().unwrap_or(c))
        .collect();
    let rigid =
        kinds.contains(&"rigid_body") || cal.effects.iter().any(|e| e.kind() == "rigid_body");
    // The axes whose lines the rigid body's places are scanned along with every stylus: z
    // always; another when a rigid-body term of it within reach is left undetermined (see
    // [`styli_axes_needed`]), and the plan is made again.
    let mut styli_axes: Vec<usize> = vec![2];
    let (program, taken, left_out, used, prediction) = loop {
        let mut program = Program {
            name: "lab-plan".into(),
            note: format!(
                "planned by `scancorr lab plan` for {} v{}",
                cal.machine_id, cal.version
            ),
            features: vec![],
            scans: vec![],
            temperature: None,
        };
        let mut taken = vec![];
        let mut left_out = vec![];
        // The base group, then the groups for the requested candidates, then (for the rigid
        // body) the ring placements chosen one by one, then the others while time is left.
        let (mut first, mut rest): (Vec<Option<Group>>, Vec<Option<Group>>) = (vec![], vec![]);
        let mut later = vec![];
        for g in groups.iter().cloned() {
            if g.serves.is_empty() || g.serves.iter().any(|k| kinds.contains(k)) {
                first.push(Some(g));
            } else {
                later.push(Some(g));
            }
        }
        if rigid {
            first.push(None);
        }
        rest.extend(later);
        let mut used = 0.0;
        // Whether the ring was placed for the rigid body (then what no place reaches is said).
        let mut rigid_placed = false;
        for g in first.into_iter().chain(rest) {
            let (g, for_rigid) = match g {
                Some(g) => (g, false),
                None => {
                    match rigid_group(cal, req, &styli, &styli_axes, big, &program, budget, &tip_r)?
                    {
                        Some(g) => (g, true),
                        None => continue,
                    }
                }
            };
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
                rigid_placed |= for_rigid;
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
        let mut prediction = predict(cal, &program, &req.candidates, &req.assumptions)?;
        if rigid_placed {
            prediction.beyond_reach = beyond_reach(cal, req, &program, &prediction, &styli, big)?;
            let more = styli_axes_needed(&prediction, &styli_axes);
            if !more.is_empty() && styli.len() > 1 {
                styli_axes.extend(more);
                continue;
            }
        }
        break (program, taken, left_out, used, prediction);
    };
    Ok(Planned {
        minutes: used / 60.0,
        program,
        groups: taken,
        left_out,
        prediction,
    })
}

/// The axes (0 x, 1 y) of the rigid-body terms the plan leaves undetermined though a campaign
/// of the pool could determine them (not in `beyond_reach`), beyond those already in `have`.
/// Such a term (e.g. `AZX c1`, the yaw of x varying along x) is one the greedy choice counted
/// as seen by one stylus, where in the joint fit the model's other effects take its shape;
/// between styli of different offsets a rotation moves each ball by its own θ × o. Its lines
/// are then scanned with every stylus (see [`greedy`]).
fn styli_axes_needed(p: &Prediction, have: &[usize]) -> Vec<usize> {
    let mut v = vec![];
    for u in &p.undetermined {
        if !u.starts_with("rigid_body") || p.beyond_reach.contains(u) {
            continue;
        }
        let term = u.split(": ").nth(1).unwrap_or("");
        let code = term.split_whitespace().next().unwrap_or("").as_bytes();
        if code.len() != 3 || !(code[0] == b'A' || code[0] == b'E') {
            continue;
        }
        if let Some(ax) = b"XYZ".iter().position(|c| *c == code[2]) {
            if !have.contains(&ax) && !v.contains(&ax) {
                v.push(ax);
            }
        }
    }
    v
}

/// Parameters no campaign with these artifacts can determine beside this model: those left
/// undetermined by the plan with every place of the rigid body's pool added (the ring at
/// each, with every stylus). With rings in the horizontal plane, an error that
/// moves every stylus's ring alike (the z axis's positioning, EZZ; a squareness to z) is a
/// shift of the ring's centre (the fit's own nuisance), and a term a model effect carries (a
/// guide table's straightness and yaw) is that effect's: no place tells them apart. The plan
/// can only be asked to determine the others.
#[allow(clippy::too_many_arguments)]
fn beyond_reach(
    cal: &Calibration,
    req: &PlanRequest,
    program: &Program,
    planned: &Prediction,
    styli: &[(u32, f64, Vec3)],
    d: f64,
) -> Result<Vec<String>, LabError> {
    // Every place with every stylus: what any campaign of these places could see.
    let (places, _) = rigid_pool(req, styli, &[], d);
    let places: Vec<greedy::Place> = places
        .into_iter()
        .filter(|p| !p.styli)
        .map(|mut p| {
            p.styli = styli.len() > 1;
            p
        })
        .collect();
    let configs: Vec<(u32, f64)> = styli.iter().map(|s| (s.0, s.1)).collect();
    let pool = greedy::pool_program(&places, d, &configs, "every place of the rigid body's pool");
    let mut all = program.clone();
    let base = all.features.len();
    all.features.extend(pool.features);
    all.scans.extend(pool.scans.into_iter().map(|mut s| {
        s.feature += base;
        s
    }));
    // Every 24th point: which columns the design spans, not their σ.
    let a = Assumptions {
        stride: req.assumptions.stride.max(24),
        ..req.assumptions.clone()
    };
    let reach = predict(cal, &all, &req.candidates, &a)?;
    // A parameter the plan itself determines is within reach, whatever the coarser look says.
    Ok(reach
        .undetermined
        .into_iter()
        .filter(|p| planned.undetermined.contains(p))
        .collect())
}

/// Lines of the pool of ring places for the rigid body, as fractions of the travel: along
/// each axis through the centre, and at a second level of each other axis (the Abbe levers:
/// an axis' pitch and roll times the ram's extension or the carriage's position come apart
/// from its translations only at two levels).
const POOL_LINES: [(usize, [f64; 2]); 8] = [
    (0, [0.5, 0.5]),
    (0, [0.5, 0.8]),
    (0, [0.2, 0.5]),
    (1, [0.5, 0.5]),
    (1, [0.5, 0.8]),
    (1, [0.2, 0.5]),
    (2, [0.5, 0.5]),
    (2, [0.2, 0.2]),
];

/// Machine time below which the rigid body's places are not planned, s.
const RIGID_MIN_S: f64 = 180.0;

/// The pool of ring places for the rigid body: the ring stepped by its diameter (at least
/// 40 mm) along the [`POOL_LINES`] over 10–90 % of the travel, where the first stylus
/// (`styli[0]`) reaches; each place once with the first stylus alone and, on the lines along
/// z where every stylus of `styli` keeps the carriage inside the travel, once with all (see
/// [`greedy`]); on the lines along another axis of `styli_axes` (one whose term the first
/// plan left undetermined, see [`styli_axes_needed`]), with all alone where they fit; with
/// each place its line's index, axis and coordinate along it.
#[allow(clippy::type_complexity)]
fn rigid_pool(
    req: &PlanRequest,
    styli: &[(u32, f64, Vec3)],
    styli_axes: &[usize],
    d: f64,
) -> (Vec<greedy::Place>, Vec<(usize, usize, f64)>) {
    let tr = req.travel_mm;
    let off1 = styli.first().map(|s| s.2).unwrap_or_else(Vec3::zeros);
    let step = d.max(40.0);
    let mut places: Vec<greedy::Place> = vec![];
    let mut line_of: Vec<(usize, usize, f64)> = vec![];
    for (li, (ax, fr)) in POOL_LINES.iter().enumerate() {
        let others: Vec<usize> = (0..3).filter(|a| a != ax).collect();
        let mut f = [0.5; 3];
        f[others[0]] = fr[0];
        f[others[1]] = fr[1];
        let span = tr[*ax][1] - tr[*ax][0];
        let n = ((0.8 * span) / step).floor() as usize;
        let lo = tr[*ax][0] + 0.5 * span - 0.5 * n as f64 * step;
        let pos = |f: [f64; 3]| {
            Vec3::new(
                tr[0][0] + f[0] * (tr[0][1] - tr[0][0]),
                tr[1][0] + f[1] * (tr[1][1] - tr[1][0]),
                tr[2][0] + f[2] * (tr[2][1] - tr[2][0]),
            ) + off1
        };
        let c0 = pos(f);
        let name = ["x", "y", "z"];
        let line = format!(
            "{} at {} {:.0}, {} {:.0}",
            name[*ax], name[others[0]], c0[others[0]], name[others[1]], c0[others[1]]
        );
        for k in 0..=n {
            let mut c = c0;
            c[*ax] = lo + k as f64 * step + off1[*ax];
            if places.iter().any(|p| (p.center - c).norm() < 1.0) {
                continue;
            }
            // On the lines along z (the z axis's own errors vary along z alone; elsewhere the
            // Abbe levers of two levels see the other axes' rotations), where every stylus's
            // carriage position stays inside the travel.
            let inside = styli_axes.contains(ax)
                && styli.len() > 1
                && styli.iter().all(|s| {
                    let q = c - s.2;
                    (0..3).all(|a| q[a] >= tr[a][0] && q[a] <= tr[a][1])
                });
            for with in [false, true] {
                if with && !inside {
                    continue;
                }
                // Along a line added for a term seen only between styli, every stylus.
                if !with && inside && *ax != 2 {
                    continue;
                }
                line_of.push((li, *ax, c[*ax]));
                places.push(greedy::Place {
                    center: c,
                    line: line.clone(),
                    styli: with,
                });
            }
        }
    }
    (places, line_of)
}

/// The ring placements for the rigid body, chosen one by one (see [`greedy`]) from the ring
/// stepped by its diameter (at least 40 mm) along the [`POOL_LINES`] over 10–90 % of the
/// travel, within the time `program` leaves of `budget` s. None: no gain, or less than
/// [`RIGID_MIN_S`] left.
#[allow(clippy::too_many_arguments)]
fn rigid_group(
    cal: &Calibration,
    req: &PlanRequest,
    styli: &[(u32, f64, Vec3)],
    styli_axes: &[usize],
    d: f64,
    program: &Program,
    budget: f64,
    tip_r: &dyn Fn(u32) -> f64,
) -> Result<Option<Group>, LabError> {
    let left = budget - machine_time_s(program, tip_r);
    // Fewer than about ten places cannot follow each error's shape along its axis: their time
    // goes to the other groups.
    if left < RIGID_MIN_S {
        return Ok(None);
    }
    let step = d.max(40.0);
    let (places, line_of) = rigid_pool(req, styli, styli_axes, d);
    let configs: Vec<(u32, f64)> = styli.iter().map(|s| (s.0, s.1)).collect();
    let mut chosen = greedy::choose(cal, &places, d, &configs, left, &req.assumptions, tip_r)?;
    let why = "rigid-body errors: the ring placed where it most reduces the predicted variance of the rigid-body terms per second (each error's shape along its axis, the lab's spline variant; two levels of the other axes for the Abbe levers; every stylus at some places, for the z axis's own errors), one place at a time";
    // Along the lines in order; the last chosen dropped while the moves make it too long.
    loop {
        if chosen.order.is_empty() {
            return Ok(None);
        }
        let mut ord = chosen.order.clone();
        ord.sort_by(|a, b| {
            line_of[*a]
                .0
                .cmp(&line_of[*b].0)
                .then(line_of[*a].2.total_cmp(&line_of[*b].2))
        });
        let mut g = Group {
            what: String::new(),
            why: why.into(),
            features: vec![],
            scans: vec![],
            serves: &["rigid_body"],
        };
        for (i, f) in ord.iter().enumerate() {
            g.features.push(ring_at(places[*f].center, d));
            // One turn each, the direction alternating along the lines (see [`greedy`]).
            let dir = if i % 2 == 0 { 1 } else { -1 };
            g.scans
                .extend(greedy::place_scans(i, &places[*f], &configs, dir, why));
        }
        let with_styli = ord.iter().filter(|f| places[**f].styli).count();
        let mut trial = program.clone();
        let base = trial.features.len();
        trial.features.extend(g.features.iter().cloned());
        trial.scans.extend(g.scans.iter().cloned().map(|mut s| {
            s.feature += base;
            s
        }));
        if machine_time_s(&trial, tip_r) > budget {
            chosen.order.pop();
            continue;
        }
        let mut per_line: Vec<(String, usize, f64, f64)> = vec![];
        for f in &ord {
            let (l, ax, v) = (
                &places[*f].line,
                line_of[*f].1,
                places[*f].center[line_of[*f].1],
            );
            let _ = ax;
            match per_line.iter_mut().find(|p| &p.0 == l) {
                Some(p) => {
                    p.1 += 1;
                    p.2 = p.2.min(v);
                    p.3 = p.3.max(v);
                }
                None => per_line.push((l.clone(), 1, v, v)),
            }
        }
        g.what = format!(
            "ring d={d} mm at {} places chosen one by one for the rigid body ({} of {} pool places every {step:.0} mm, the last worth {:.1} % of the first per second; its terms seen: {} of {}): {}; {}; at {with_styli} of them every stylus and head angle as well (the z axis's own errors{} are seen only between styli)",
            ord.len(),
            ord.len(),
            places.iter().filter(|p| !p.styli).count(),
            100.0 * chosen.gains.get(ord.len() - 1).copied().unwrap_or(0.0),
            chosen.terms_seen.1,
            chosen.terms_seen.0,
            per_line
                .iter()
                .map(|(l, n, a, b)| format!("along {l}: {n} from {a:.0} to {b:.0}"))
                .collect::<Vec<_>>()
                .join("; "),
            if greedy::ONE_WAY {
                "one turn at 30 mm/s, the direction alternating"
            } else {
                "30 mm/s both ways"
            },
            if styli_axes.len() > 1 {
                format!(
                    ", and along {} the rotations' terms the model's other effects mimic with one stylus",
                    styli_axes
                        .iter()
                        .filter(|a| **a != 2)
                        .map(|a| ["x", "y", "z"][*a])
                        .collect::<Vec<_>>()
                        .join(" and ")
                )
            } else {
                String::new()
            }
        );
        return Ok(Some(g));
    }
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
            temperature: None,
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

    /// The design's ideal points lie on the artifact as the lab's fit holds it (the certified
    /// diameter): noiseless, the lab's artifact fit leaves nothing. On the nominal diameter
    /// (50.0 for a 50.0012 mm ring) every point sat 0.6 µm off, and `predict_by_fit`'s σ was
    /// scaled by that offset (14–30× the design's) instead of by the noise.
    #[test]
    fn the_ideal_points_lie_on_the_certified_artifact() {
        let a = Assumptions::default();
        let ds = ideal_dataset(&cal(), &ring_prog(&[]), &a).unwrap();
        let prep = crate::lab::types::prepare(&ds).unwrap();
        assert!(
            prep.rms_fit_um < 1e-4,
            "noiseless ideal points leave {} µm RMS",
            prep.rms_fit_um
        );
        let by_fit = predict_by_fit(&cal(), &ring_prog(&[]), &[], &a, 2).unwrap();
        let design = predict(&cal(), &ring_prog(&[]), &[], &a).unwrap();
        for (p, q) in by_fit.params.iter().zip(&design.params) {
            if let (Some(f), Some(d)) = (p.sigma, q.sigma_design) {
                assert!(
                    (0.25..=2.0).contains(&(f / d)),
                    "{}: the lab's σ on the design's replicates {f:e} against the design's {d:e}",
                    p.name
                );
            }
        }
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
    fn the_rigid_body_gets_ring_places_chosen_one_by_one_at_two_levels() {
        let mut req = PlanRequest {
            travel_mm: [[0.0, 1000.0], [0.0, 800.0], [-600.0, 0.0]],
            owned: vec![Owned::parse("ring:d=50.0012").unwrap()],
            minutes: 9.0,
            candidates: vec!["rigid_body".into()],
            assumptions: Assumptions {
                stride: 16,
                ..Assumptions::default()
            },
        };
        let p = plan(&cal(), &req).unwrap();
        assert!(p.minutes <= 9.0, "{}", p.minutes);
        let g = p
            .groups
            .iter()
            .find(|g| g.what.contains("chosen one by one for the rigid body"))
            .unwrap_or_else(|| panic!("{:?}", p.groups));
        assert!(g.minutes > 3.0, "{g:?}");
        // The places: rings at the first tip's reach, inside the travel, on more than one
        // level of z and of y (the Abbe levers).
        let rings: Vec<Vec3> = p
            .program
            .features
            .iter()
            .skip(9)
            .map(|f| Vec3::from(f.center_mm))
            .collect();
        assert!(rings.len() >= 10, "{}", rings.len());
        let levels = |a: usize| {
            let mut v: Vec<i64> = rings.iter().map(|c| c[a].round() as i64).collect();
            v.sort();
            v.dedup();
            v.len()
        };
        assert!(levels(2) >= 2 && levels(1) >= 2, "{rings:?}");
        // Without the rigid body asked for, no such group.
        req.candidates = vec!["servo_gain:powers=1+2".into()];
        let q = plan(&cal(), &req).unwrap();
        assert!(!q.groups.iter().any(|g| g.what.contains("rigid body")));
    }

    #[test]
    fn the_planner_stays_within_its_time_and_determines_the_deflection_matrix() {
        let req = PlanRequest {
            travel_mm: [[0.0, 1000.0], [0.0, 800.0], [-600.0, 0.0]],
            owned: ["ring:d=50.0012", "sphere:d=25.0004", "straightedge:l=400"]
                .iter()
                .map(|s| Owned::parse(s).unwrap())
                .collect(),
            minutes: 6.0,
            candidates: vec!["servo_gain:powers=1+2".into()],
            assumptions: Assumptions {
                stride: 16,
                ..Assumptions::default()
            },
        };
        let p = plan(&cal(), &req).unwrap();
        assert!(p.minutes <= 6.0 && p.minutes > 4.0, "{}", p.minutes);
        assert!(!p.left_out.is_empty(), "6 minutes cannot hold every group");
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
