//! Scan programs: the artifacts on the table and the moves the controller commands.
//!
//! Everything is planned in carriage coordinates (the point the scales measure): a scan's
//! carriage path is its tip-centre path minus the nominal stylus offset, pushed into the
//! surface by the nominal probe deflection.

use crate::machine::{head_rotation, Stylus, TrueMachine, V3};
use serde::{Deserialize, Serialize};
// What the bag says about the program is the lab's contract: the same types, not a copy.
use scancorr_core::lab::plan::{Artifact as RecordArtifact, Program, ScanKind};
pub use scancorr_core::lab::program::{
    FeatureKind, FeatureSpec as FeatureInfo, ProgramSpec as ProgramInfo, SegmentKind,
    SegmentSpec as SegmentInfo,
};
use std::f64::consts::{PI, TAU};

mod builder;
mod dynamics_faces;
mod dynamics_vertical;
mod geometry;
mod thin_wall;

use builder::*;
use geometry::horizontal;
pub use geometry::{Feature, Path, Segment};
pub use thin_wall::{WALL_ARTIFACT, WALL_LENGTH_MM};

/// A planned program: features and segments with start times.
#[derive(Debug, Clone)]
pub struct Plan {
    /// Program name.
    pub name: String,
    /// Features.
    pub features: Vec<Feature>,
    /// Segments in order.
    pub segments: Vec<Segment>,
    /// Start time of each segment, s.
    pub starts: Vec<f64>,
}

/// Programs the simulator knows.
pub const PROGRAMS: [&str; 23] = [
    "ring",
    "ring-speeds",
    "campaign",
    "part",
    "dynamics",
    "dynamics-faces",
    "dynamics-vertical",
    "tips",
    "probe-force",
    "probe-force-quarter",
    "probe-force-approach",
    "probe-force-sine",
    "geometry",
    "straightedge",
    "dynamic-map",
    "dynamic-map-part",
    "dynamic-map-speeds",
    "tips-repeat",
    "tips-one-angle",
    "tips-reference",
    "scales",
    "thin-wall",
    "thin-wall-forces",
];

/// Plans a program. `position` places the program's main artifact.
pub fn plan(name: &str, m: &TrueMachine, position: Option<V3>) -> Result<Plan, String> {
    let mut b = Builder::at_home(m);
    match name {
        "ring" => {
            let f = b.feature(ring_feature(
                position.unwrap_or(V3::new(400.0, 300.0, -250.0)),
                0.7,
            ));
            b.circle(f, 30.0, 1.0, 0.3, 0.0);
            b.circle(f, 30.0, -1.0, 0.3, PI);
        }
        "dynamic-map" => {
            // The S1/F1/F2 joint method on the ring gauge (see `dynamic_map_scans`).
            let f = b.feature(ring_feature(
                position.unwrap_or(V3::new(400.0, 300.0, -250.0)),
                0.7,
            ));
            dynamic_map_scans(&mut b, f, false);
        }
        "dynamic-map-speeds" => {
            // The speed search: S1, then F2 and F1 at rising speeds, on the ring.
            let f = b.feature(ring_feature(
                position.unwrap_or(V3::new(400.0, 300.0, -250.0)),
                0.7,
            ));
            b.circle(f, 5.0, 1.0, 0.3, 0.0);
            for v in [20.0, 40.0, 80.0] {
                b.circle(f, v, 1.0, 0.3, 0.0);
                b.circle(f, v, 1.0, 0.5, 0.0);
            }
        }
        "dynamic-map-part" => {
            // A like part: a bore of the ring's nominal size in the ring's place, with a form
            // of its own (a machined part's few µm), scanned by the same part program.
            let f = b.feature(Feature {
                id: 0,
                artifact: "part".into(),
                kind: FeatureKind::Bore,
                center: position.unwrap_or(V3::new(400.0, 300.0, -250.0)).into(),
                radius_mm: 50.003 / 2.0,
                nominal_diameter_mm: 50.0,
                certificate_diameter_mm: None,
                normal: [0.0; 3],
                form: vec![[2.0, 1.2e-3, 0.9], [3.0, 0.8e-3, 2.2], [7.0, 0.3e-3, 0.4]],
            });
            dynamic_map_scans(&mut b, f, true);
        }
        "ring-speeds" => {
            let f = b.feature(ring_feature(
                position.unwrap_or(V3::new(550.0, 300.0, -250.0)),
                1.3,
            ));
            for v in [10.0, 25.0, 50.0, 80.0] {
                b.circle(f, v, 1.0, 0.3, 0.0);
                b.circle(f, v, -1.0, 0.3, PI);
            }
            // The bent stylus at two head angles: its offset's growth and the Abbe lever show.
            for a1 in [0.0, 90.0] {
                b.set_tip(2, a1, 0.0);
                b.circle(f, 30.0, 1.0, 0.3, 0.0);
            }
            b.set_tip(1, 0.0, 0.0);
        }
        "campaign" => {
            let places = [
                V3::new(250.0, 200.0, -300.0),
                V3::new(720.0, 560.0, -150.0),
                V3::new(420.0, 420.0, -420.0),
            ];
            let base = position.unwrap_or(V3::zeros());
            for (i, p) in places.iter().enumerate() {
                let f = b.feature(ring_feature(p + base, 0.4 + i as f64));
                for v in [10.0, 30.0, 60.0, 90.0] {
                    b.circle(f, v, 1.0, 0.3, 0.0);
                    b.circle(f, v, -1.0, 0.3, PI);
                }
                if i == 0 {
                    // Several probe deflections: extrapolation to zero deflection.
                    for d in [0.1, 0.5] {
                        b.circle(f, 30.0, 1.0, d, 0.0);
                        b.circle(f, 30.0, -1.0, d, PI);
                    }
                }
            }
            // Master sphere, equator, two styli and two head angles.
            let sphere = b.feature(Feature {
                id: 0,
                artifact: "sphere".into(),
                kind: FeatureKind::Boss,
                center: (V3::new(620.0, 220.0, -360.0) + base).into(),
                radius_mm: 25.0004 / 2.0,
                nominal_diameter_mm: 25.0,
                certificate_diameter_mm: Some(25.0004),
                normal: [0.0; 3],
                form: vec![[2.0, 0.01e-3, 0.2]],
            });
            for (tip, a1) in [(1u32, 0.0), (2, 0.0), (2, 90.0)] {
                b.set_tip(tip, a1, 0.0);
                b.circle(sphere, 30.0, 1.0, 0.3, 0.0);
                b.circle(sphere, 60.0, -1.0, 0.3, PI);
            }
            // Straightedge along X, pressed from −y; two styli (the bent one shifts the probe
            // 30 mm along x: shifted-probe separation of guide and straightedge form).
            let se = b.feature(Feature {
                id: 0,
                artifact: "straightedge".into(),
                kind: FeatureKind::Face,
                center: (V3::new(500.0, 680.0, -260.0) + base).into(),
                radius_mm: 0.0,
                nominal_diameter_mm: 0.0,
                certificate_diameter_mm: None,
                normal: [0.0, -1.0, 0.0],
                // A calibrated straightedge: its form (a few tens of nm) is below the noise.
                form: vec![[300.0, 0.03e-3, 0.5], [170.0, 0.015e-3, 1.1]],
            });
            for (tip, a1) in [(1u32, 0.0), (2, 0.0)] {
                b.set_tip(tip, a1, 0.0);
                b.face_line(se, 380.0, -380.0, 50.0, 0.3);
                b.face_line(se, -380.0, 380.0, 50.0, 0.3);
            }
            b.set_tip(1, 0.0, 0.0);
        }
        "dynamics" => {
            // The ring-gauge procedure: one ring set up in turn at 7 positions along X, 5
            // along Y and 4 along Z (the others at mid-travel), each scanned once per speed in
            // both directions, spin-up and slow-down included.
            let base = position.unwrap_or(V3::new(500.0, 400.0, -280.0));
            let mut places = vec![];
            for x in [150.0, 270.0, 390.0, 500.0, 620.0, 740.0, 860.0] {
                places.push(V3::new(x, base.y, base.z));
            }
            for y in [150.0, 280.0, 520.0, 650.0] {
                places.push(V3::new(base.x, y, base.z));
            }
            for z in [-130.0, -200.0, -360.0, -430.0] {
                places.push(V3::new(base.x, base.y, z));
            }
            for (i, p) in places.iter().enumerate() {
                let f = b.feature(ring_feature(*p, 0.3 + 0.7 * i as f64));
                for v in [15.0, 40.0, 80.0] {
                    b.circle(f, v, 1.0, 0.3, 0.0);
                    b.circle(f, v, -1.0, 0.3, PI);
                }
            }
        }
        "straightedge" => {
            // A workshop straightedge along X with a form of its own (a bow and waviness of
            // a few µm: not a calibrated one), pressed from −y and scanned slowly along its
            // length by the straight and the bent stylus (whose offset is an Abbe lever for
            // the carriage's yaw), in both directions.
            let c = position.unwrap_or(V3::new(500.0, 680.0, -260.0));
            let se = b.feature(Feature {
                id: 0,
                artifact: "straightedge".into(),
                kind: FeatureKind::Face,
                center: c.into(),
                radius_mm: 0.0,
                nominal_diameter_mm: 0.0,
                certificate_diameter_mm: None,
                normal: [0.0, -1.0, 0.0],
                form: vec![
                    [1500.0, 3.0e-3, 1.4],
                    [170.0, 0.8e-3, 0.4],
                    [95.0, 0.5e-3, 2.1],
                ],
            });
            for tip in [1u32, 2] {
                b.set_tip(tip, 0.0, 0.0);
                b.face_line(se, 290.0, -290.0, 20.0, 0.3);
                b.face_line(se, -290.0, 290.0, 20.0, 0.3);
            }
            b.set_tip(1, 0.0, 0.0);
        }
        "geometry" => {
            // The machine's geometry seen through a ring gauge: one ring stepped by its own
            // diameter along a line in X, in Y and in Z through the base position, so the
            // local slope of every error along each axis is seen over the whole line; one
            // moderate speed, both directions.
            let base = position.unwrap_or(V3::new(500.0, 400.0, -280.0));
            let mut places = vec![base];
            let line = |lo: f64, hi: f64| {
                let n = ((hi - lo) / 50.0).round() as usize;
                (0..=n).map(move |k| lo + 50.0 * k as f64)
            };
            for x in line(150.0, 850.0) {
                places.push(V3::new(x, base.y, base.z));
            }
            for y in line(150.0, 650.0) {
                places.push(V3::new(base.x, y, base.z));
            }
            for z in line(-430.0, -130.0) {
                places.push(V3::new(base.x, base.y, z));
            }
            let mut seen: Vec<V3> = vec![];
            places.retain(|p| {
                let new = seen.iter().all(|q| (p - q).norm() >= 1.0);
                seen.push(*p);
                new
            });
            for p in &places {
                let f = b.feature(ring_feature(*p, 0.9));
                b.circle(f, 30.0, 1.0, 0.3, 0.0);
                b.circle(f, 30.0, -1.0, 0.3, PI);
            }
        }
        "tips" => {
            // Qualification on the master sphere: the reference stylus (tip 1), then the crank
            // (tip 2) at four head angles, the reference again after each, so its drift (the
            // scales' and the styli's growth as the room warms) can be followed; three
            // latitudes per setting fix the centre in z.
            let sphere = b.feature(master_sphere(position));
            let reference = |b: &mut Builder| {
                b.set_tip(1, 0.0, 0.0);
                for lat in [-30.0, 0.0, 30.0] {
                    b.sphere_circle(sphere, 20.0, 1.0, 0.3, lat);
                }
            };
            reference(&mut b);
            for a1 in [0.0, 90.0, 180.0, 270.0] {
                b.set_tip(2, a1, 0.0);
                for lat in [-30.0, 0.0, 30.0] {
                    b.sphere_circle(sphere, 20.0, 1.0, 0.3, lat);
                }
                reference(&mut b);
            }
        }
        "scales" => {
            // The scales' expansion: a ball bar (two spheres of a certified centre distance,
            // their centres on a 0.1 mm grid so the bag's nominal centres state it exactly)
            // along X (600 mm), Y (500 mm) and Z (300 mm), each ball measured by the reference
            // tip at three latitudes, the bars taken in turn four times over the room's drift,
            // so each scale is read at four temperatures.
            let base = position.unwrap_or(V3::new(500.0, 400.0, -300.0));
            let ends = [
                (V3::new(-300.0, 0.0, 0.0), V3::new(300.0, 0.0, 0.0)),
                (V3::new(0.0, -250.0, 0.0), V3::new(0.0, 250.0, 0.0)),
                (V3::new(0.0, 0.0, -150.0), V3::new(0.0, 0.0, 150.0)),
            ];
            let ball = |c: V3| Feature {
                id: 0,
                artifact: "ball-bar".into(),
                kind: FeatureKind::Boss,
                center: ((c * 10.0).map(f64::round) / 10.0).into(),
                radius_mm: 25.0004 / 2.0,
                nominal_diameter_mm: 25.0,
                certificate_diameter_mm: Some(25.0004),
                normal: [0.0; 3],
                form: vec![[2.0, 0.01e-3, 0.2]],
            };
            let bars: Vec<[u32; 2]> = ends
                .iter()
                .map(|(a, z)| [b.feature(ball(base + a)), b.feature(ball(base + z))])
                .collect();
            b.set_tip(1, 0.0, 0.0);
            for _ in 0..4 {
                for bar in &bars {
                    for &f in bar {
                        for lat in [-30.0, 0.0, 30.0] {
                            b.sphere_circle(f, 20.0, 1.0, 0.3, lat);
                        }
                    }
                }
            }
        }
        "tips-reference" => {
            // The reference tip re-qualified alone (a new ball, after a crash): the master
            // sphere three times, three latitudes each.
            let sphere = b.feature(master_sphere(position));
            b.set_tip(1, 0.0, 0.0);
            for _ in 0..3 {
                for lat in [-30.0, 0.0, 30.0] {
                    b.sphere_circle(sphere, 20.0, 1.0, 0.3, lat);
                }
            }
        }
        "tips-repeat" | "tips-one-angle" => {
            // Qualification as `tips`, the crank's head angles visited twice (`tips-repeat`:
            // each head angle at two temperatures of the room's drift, so a stylus's growth is
            // seen against itself, free of the machine's geometry between the carriage
            // positions) or the crank at one head angle only, four times (`tips-one-angle`: a
            // head without rotary axes, the patent's own case).
            let sphere = b.feature(master_sphere(position));
            let reference = |b: &mut Builder| {
                b.set_tip(1, 0.0, 0.0);
                for lat in [-30.0, 0.0, 30.0] {
                    b.sphere_circle(sphere, 20.0, 1.0, 0.3, lat);
                }
            };
            let angles: &[f64] = if name == "tips-repeat" {
                &[0.0, 90.0, 180.0, 270.0, 0.0, 90.0, 180.0, 270.0]
            } else {
                &[0.0, 0.0, 0.0, 0.0]
            };
            reference(&mut b);
            for &a1 in angles {
                b.set_tip(2, a1, 0.0);
                for lat in [-30.0, 0.0, 30.0] {
                    b.sphere_circle(sphere, 20.0, 1.0, 0.3, lat);
                }
                reference(&mut b);
            }
        }
        "probe-force" => {
            // Extrapolation to zero force, variant (a): the same circles on the master sphere
            // at three deflections, each tip at head angles (0, 0); three latitudes, so the
            // deflection has a component along the stylus (w) as well as across it (u, v).
            // The deflections alternate within each latitude, so the room's slow drift does
            // not line up with the deflection. Slowly (5 mm/s): the circle's radius changes with
            // the deflection, and so would any dynamic error that grows with v²/r.
            let sphere = b.feature(master_sphere(position));
            for tip in b.m.styli.iter().map(|s| s.id).collect::<Vec<_>>() {
                b.set_tip(tip, 0.0, 0.0);
                for lat in [-35.0, 0.0, 35.0] {
                    for defl in [0.1, 0.5, 0.3] {
                        b.sphere_circle(sphere, 5.0, 1.0, defl, lat);
                    }
                }
            }
        }
        "probe-force-quarter" => {
            // Variant (c): per tip and latitude a full revolution at 0.3 mm and a quarter at
            // 0.1 mm; across the quarter the deflection turns from X to Y, which separates k_u
            // from k_v, and the full revolution carries the correction round the circle. The
            // quarter is scanned twice at 0.1 mm around one at 0.5 mm (A-B-A): over a quarter
            // turn the sphere's drift (n·Ċ·t, the room warming the scales) has nearly the
            // force's shape, and only the repeat tells a drift linear in time from the force
            // (a single second quarter left k_u 0.3–1.7 % off, the sign following the order;
            // the quarter there and back, k_v 50–70 %: the servo's errors change with the
            // direction).
            let sphere = b.feature(master_sphere(position));
            for tip in b.m.styli.iter().map(|s| s.id).collect::<Vec<_>>() {
                b.set_tip(tip, 0.0, 0.0);
                for lat in [-35.0, 0.0, 35.0] {
                    b.sphere_arc(sphere, 5.0, 1.0, 0.3, lat, 1.0);
                    for defl in [0.1, 0.5, 0.1] {
                        b.sphere_arc(sphere, 5.0, 1.0, defl, lat, 0.25);
                    }
                }
            }
        }
        "probe-force-sine" => {
            // Variant (b): per tip and latitude one circle at a constant 0.3 mm and one whose
            // deflection varies as 0.3 + 0.2·sin(15θ) mm around it — fifteen waves a turn,
            // above the static map's harmonics, so the change of each point with the
            // deflection is seen within the one scan (the real-time form pairs each wave's
            // low and high halves). Slowly (1 mm/s, a wave in 6 s): the wave accelerates the
            // carriage by ω²·0.2 mm in phase with the deflection, and the structure's
            // compliance under that acceleration would pass for a force coefficient.
            let sphere = b.feature(master_sphere(position));
            for tip in b.m.styli.iter().map(|s| s.id).collect::<Vec<_>>() {
                b.set_tip(tip, 0.0, 0.0);
                for lat in [-35.0, 0.0, 35.0] {
                    b.sphere_arc(sphere, 1.0, 1.0, 0.3, lat, 1.0);
                    b.sphere_wave(sphere, 1.0, 1.0, 0.3, lat, 1.0, (0.2, 15.0));
                }
            }
        }
        "probe-force-approach" => {
            // Variant (d): radial approaches from 0.05 to 0.5 mm deflection at two positions
            // 90° apart on the equator, three times each: X and Y only (nothing along the
            // stylus, so k_w is not determined).
            let sphere = b.feature(master_sphere(position));
            for tip in b.m.styli.iter().map(|s| s.id).collect::<Vec<_>>() {
                b.set_tip(tip, 0.0, 0.0);
                for _ in 0..3 {
                    for th in [0.0, std::f64::consts::FRAC_PI_2] {
                        b.sphere_approach(sphere, th, 0.05, 0.5, 0.5);
                    }
                }
            }
        }
        // Faces touched while the carriage oscillates along and across their normals.
        "dynamics-faces" => dynamics_faces::plan(&mut b, position),
        // The ring on its edge: circles in the XZ and YZ planes.
        "dynamics-vertical" => dynamics_vertical::plan(&mut b, position),
        // A thin-walled part at two probing forces (F1, F2) and at three.
        "thin-wall" => thin_wall::plan(&mut b, position, &[0.1, 0.5]),
        "thin-wall-forces" => thin_wall::plan(&mut b, position, &[0.1, 0.3, 0.5]),
        "part" => {
            let base = position.unwrap_or(V3::new(450.0, 350.0, -280.0));
            let bore = b.feature(Feature {
                id: 0,
                artifact: "part".into(),
                kind: FeatureKind::Bore,
                center: (base + V3::new(-60.0, 0.0, 0.0)).into(),
                radius_mm: 15.0,
                nominal_diameter_mm: 30.0,
                certificate_diameter_mm: None,
                normal: [0.0; 3],
                form: vec![[3.0, 0.8e-3, 0.1]],
            });
            let boss = b.feature(Feature {
                id: 0,
                artifact: "part".into(),
                kind: FeatureKind::Boss,
                center: (base + V3::new(70.0, 20.0, 0.0)).into(),
                radius_mm: 20.0,
                nominal_diameter_mm: 40.0,
                certificate_diameter_mm: None,
                normal: [0.0; 3],
                form: vec![[2.0, 1.0e-3, 0.4]],
            });
            let face = b.feature(Feature {
                id: 0,
                artifact: "part".into(),
                kind: FeatureKind::Face,
                center: (base + V3::new(0.0, -80.0, 0.0)).into(),
                radius_mm: 0.0,
                nominal_diameter_mm: 0.0,
                certificate_diameter_mm: None,
                normal: [0.0, -1.0, 0.0],
                form: vec![[120.0, 1.5e-3, 0.0]],
            });
            for v in [40.0, 70.0] {
                b.circle(bore, v, 1.0, 0.3, 0.0);
                b.circle(boss, v, -1.0, 0.3, PI / 2.0);
                b.face_line(face, 120.0, -120.0, v, 0.3);
            }
        }
        other => {
            return Err(format!(
                "unknown program `{other}` (known: {}; straightness error separation: {})",
                PROGRAMS.join(", "),
                crate::straightness::PROGRAMS.join(", ")
            ))
        }
    }
    b.move_to(HOME);
    let mut starts = vec![];
    let mut t = 0.0;
    for s in &b.segs {
        starts.push(t);
        t += s.duration_s;
    }
    Ok(Plan {
        name: name.to_string(),
        features: b.features,
        segments: b.segs,
        starts,
    })
}

/// Plans a program record (`scancorr sim --program FILE.json`, what `lab plan` writes):
/// its artifacts placed where it says (rings and spheres of their certified size with a few
/// tens of nm of form, straightedges calibrated), its scans in order with the same moves,
/// dwells and ramps as the built-in programs. Refused, naming the scan, when a tip is not on
/// the machine or a carriage path leaves the travel ([`crate::TRAVEL_MM`]).
pub fn plan_record(p: &Program, m: &TrueMachine) -> Result<Plan, String> {
    p.validate()?;
    let mut b = Builder::at_home(m);
    let mut ids = vec![];
    for (i, f) in p.features.iter().enumerate() {
        let c = V3::from(f.center_mm);
        let seed = 0.37 + 0.61 * i as f64;
        let d_true = f.certified_diameter_mm.unwrap_or(f.nominal_diameter_mm);
        let feat = match f.artifact {
            RecordArtifact::Ring => Feature {
                id: 0,
                artifact: "ring".into(),
                kind: FeatureKind::Bore,
                center: c.into(),
                radius_mm: d_true / 2.0,
                nominal_diameter_mm: f.nominal_diameter_mm,
                certificate_diameter_mm: f.certified_diameter_mm,
                normal: [0.0; 3],
                form: vec![
                    [2.0, 0.02e-3, seed],
                    [3.0, 0.015e-3, 2.0 * seed],
                    [5.0, 0.01e-3, 0.3],
                ],
            },
            RecordArtifact::Sphere => Feature {
                id: 0,
                artifact: "sphere".into(),
                kind: FeatureKind::Boss,
                center: c.into(),
                radius_mm: d_true / 2.0,
                nominal_diameter_mm: f.nominal_diameter_mm,
                certificate_diameter_mm: f.certified_diameter_mm,
                normal: [0.0; 3],
                form: vec![[2.0, 0.01e-3, seed]],
            },
            RecordArtifact::Straightedge => Feature {
                id: 0,
                artifact: "straightedge".into(),
                kind: FeatureKind::Face,
                center: c.into(),
                radius_mm: 0.0,
                nominal_diameter_mm: 0.0,
                certificate_diameter_mm: None,
                normal: V3::from(f.normal.unwrap_or([0.0, -1.0, 0.0]))
                    .normalize()
                    .into(),
                // A calibrated straightedge: its form (a few tens of nm) is below the noise.
                form: vec![[300.0, 0.03e-3, 0.5 + seed], [170.0, 0.015e-3, 1.1]],
            },
        };
        ids.push(b.feature(feat));
    }
    let mut scan_segs = vec![];
    for (i, s) in p.scans.iter().enumerate() {
        if m.stylus(s.tip).is_none() {
            return Err(format!(
                "scans[{i}].tip: the machine has no tip {} (its tips: {})",
                s.tip,
                m.styli
                    .iter()
                    .map(|t| t.id.to_string())
                    .collect::<Vec<_>>()
                    .join(", ")
            ));
        }
        b.set_tip(s.tip, s.a1_deg, s.a2_deg);
        let fid = ids[s.feature];
        let first = b.segs.len();
        match s.kind {
            ScanKind::Circle => {
                let start = if s.direction > 0 { 0.0 } else { PI };
                b.circle(
                    fid,
                    s.speed_mm_s,
                    s.direction as f64,
                    s.deflection_mm,
                    start,
                )
            }
            ScanKind::FaceLine => {
                b.face_line(fid, s.from_mm, s.to_mm, s.speed_mm_s, s.deflection_mm)
            }
            ScanKind::FaceWeave => b.face_weave(
                fid,
                s.at_mm,
                s.amplitude_mm,
                s.frequency_hz,
                s.cycles,
                s.deflection_mm,
            ),
        }
        scan_segs.push((i, first, b.segs.len()));
    }
    b.set_tip(1, 0.0, 0.0);
    b.move_to(HOME);
    let mut starts = vec![];
    let mut t = 0.0;
    for s in &b.segs {
        starts.push(t);
        t += s.duration_s;
    }
    // Every carriage position of every scan (and its approach) within the travel.
    for &(i, a, z) in &scan_segs {
        for seg in &b.segs[a..z] {
            let n = (seg.duration_s / 0.01).ceil().max(1.0) as usize;
            for k in 0..=n {
                let q = seg.at(seg.duration_s * k as f64 / n as f64);
                for (ax, [lo, hi]) in crate::TRAVEL_MM.iter().enumerate() {
                    if !(*lo..=*hi).contains(&q[ax]) {
                        return Err(format!(
                            "scans[{i}]: the carriage leaves the machine's travel ({} = {:.1} mm, travel {lo}…{hi} mm)",
                            ["x", "y", "z"][ax],
                            q[ax]
                        ));
                    }
                }
            }
        }
    }
    Ok(Plan {
        name: p.name.clone(),
        features: b.features,
        segments: b.segs,
        starts,
    })
}

impl Plan {
    /// Total duration, s.
    pub fn duration(&self) -> f64 {
        self.starts.last().copied().unwrap_or(0.0)
            + self.segments.last().map(|s| s.duration_s).unwrap_or(0.0)
    }

    /// The segment active at `t` (the last one after the end).
    pub fn segment_at(&self, t: f64) -> usize {
        match self.starts.partition_point(|s| *s <= t) {
            0 => 0,
            i => i - 1,
        }
    }

    /// What the lab may know about the program.
    pub fn info(&self, id_offset: u32, t_offset: f64) -> (Vec<FeatureInfo>, Vec<SegmentInfo>) {
        let features = self
            .features
            .iter()
            .map(|f| FeatureInfo {
                id: f.id,
                artifact: f.artifact.clone(),
                kind: f.kind,
                nominal_center: f.center.map(|c| (c * 10.0).round() / 10.0),
                nominal_diameter_mm: f.nominal_diameter_mm,
                certificate_diameter_mm: f.certificate_diameter_mm,
                normal: f.normal,
            })
            .collect();
        let segments = self
            .segments
            .iter()
            .zip(&self.starts)
            .map(|(s, t0)| SegmentInfo {
                id: s.id + id_offset,
                kind: s.kind,
                feature: s.feature,
                speed: s.speed,
                direction: match s.path {
                    Path::Arc { sweep, .. } => sweep.signum() as i32,
                    _ => 0,
                },
                tip: s.tip,
                a1_deg: s.a1_deg,
                a2_deg: s.a2_deg,
                deflection_mm: s.deflection_mm,
                t0_s: t0 + t_offset,
                t1_s: t0 + t_offset + s.duration_s,
            })
            .collect();
        (features, segments)
    }
}
