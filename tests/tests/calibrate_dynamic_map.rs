//! `scancorr calibrate dynamic-map` end to end (issue 12, the S1/F1/F2 joint method): a ring
//! scanned slowly at d1 (S1) and fast at d2 (F1) and d1 (F2) on a machine no other test uses,
//! from a nominal calibration; then a like part (same nominal bore, same place, another form,
//! the same part program: its fast scan has F2's segment id) from another run, corrected in
//! process with the new calibration and judged against its true surface. The same part program
//! on a bore at another place (the same segment ids at the same speed) gets no map, and
//! `correct` says the map applies to none of its points. The truth file and the part's true
//! surface are read only to judge.

mod common;
use common::*;
use nalgebra::{Matrix2, Vector2, Vector3};
use scancorr_core::{Calibration, Corrector, Output, Sample};
use scancorr_sim::program::{FeatureKind, SegmentKind};
use scancorr_sim::{run, Options, RunResult};
use std::path::Path;

const MACHINE: &str = "61";

fn json(s: &str) -> serde_json::Value {
    serde_json::from_str(s).unwrap_or_else(|e| panic!("not JSON ({e}): {s}"))
}

/// Where the ring (and the like part) stands unless placed, mm (the simulator's default).
const RING_PLACE: [f64; 3] = [400.0, 300.0, -250.0];

/// The like part, run in process (run `seed`; every library effect in the machine), at
/// `position` (none: the ring's place).
fn like_part(seed: u64, position: Option<[f64; 3]>) -> (RunResult, Vec<Sample>) {
    let o = Options {
        program: "dynamic-map-part".into(),
        machine_seed: MACHINE.parse().unwrap(),
        seed,
        position,
        ..Default::default()
    };
    let mut samples = vec![];
    let res = run(&o, |s| samples.push(s)).expect("simulation runs");
    (res, samples)
}

/// Per scan of the part (programmed speed, RMS µm): the corrected points' radial deviation
/// from the bore's true surface at steady speed (the ramps — max(v/150, 0.4) s at each end
/// as the simulator plans them — left out), after the scan's own translation in XY (where a
/// part lies is never known: its size and form are what count).
fn scan_errors(r: &(RunResult, Vec<Sample>), cal: &Calibration) -> Vec<(f64, f64, usize)> {
    let mut c = Corrector::new(cal).unwrap();
    let mut out = Output::default();
    c.push_all(r.1.iter().cloned(), &mut out);
    c.flush(&mut out);
    let feats = &r.0.truth.features;
    let mut rows = vec![];
    for seg in &r.0.program.segments {
        if seg.kind != SegmentKind::Scan {
            continue;
        }
        let f = &feats[seg.feature.unwrap() as usize - 1];
        assert_eq!(f.kind, FeatureKind::Bore);
        let ramp = (seg.speed / 150.0).max(0.4) + 0.05;
        let (t0, t1) = (seg.t0_s + ramp, seg.t1_s - ramp);
        let c0 = Vector3::from(f.center);
        let d: Vec<(f64, Vector2<f64>)> = out
            .points
            .iter()
            .filter(|p| p.segment_id == seg.id && p.estimator_valid)
            .filter(|p| (t0..=t1).contains(&(p.t_ns as f64 * 1e-9)))
            .map(|p| {
                let rel = p.surface - c0;
                let th = rel.y.atan2(rel.x);
                let e = rel.x.hypot(rel.y) - (f.radius_mm + f.form_at(th));
                (e, Vector2::new(rel.x, rel.y).normalize())
            })
            .collect();
        let (mut m, mut b) = (Matrix2::<f64>::zeros(), Vector2::zeros());
        for (e, g) in &d {
            m += g * g.transpose();
            b += g * *e;
        }
        let t = m.try_inverse().map_or(Vector2::zeros(), |mi| mi * b);
        let ss: f64 = d.iter().map(|(e, g)| (e - g.dot(&t)).powi(2)).sum();
        rows.push((
            seg.speed,
            (ss / d.len().max(1) as f64).sqrt() * 1e3,
            d.len(),
        ));
    }
    rows
}

/// (slow, fast) RMS errors of the part's two scans, µm.
fn slow_fast(part: &(RunResult, Vec<Sample>), dir: &Path, cal: &str) -> (f64, f64) {
    let c = Calibration::from_json(&std::fs::read_to_string(dir.join(cal)).unwrap()).unwrap();
    slow_fast_with(part, &c, cal)
}

fn slow_fast_with(part: &(RunResult, Vec<Sample>), c: &Calibration, cal: &str) -> (f64, f64) {
    let e = scan_errors(part, c);
    assert_eq!(e.len(), 2, "{e:?}");
    let (slow, fast) = (e[0], e[1]);
    assert!(slow.0 < fast.0, "{e:?}");
    assert!(slow.2 > 10_000 && fast.2 > 1_000, "{cal}: points {e:?}");
    (slow.1, fast.1)
}

#[test]
fn dynamic_map_corrects_a_like_parts_fast_scan_to_the_slow_scans_error() {
    let dir = scratch("calibrate-dynamic-map");
    // From the nominal start straight away.
    measure_from_nominal(&dir, "dynamic-map", MACHINE, "1", "dm.mcap", true);
    let r = calibrate_json(
        &dir,
        "dynamic-map",
        "dm.mcap",
        "nominal.json",
        "dm-nominal.json",
    );
    // With the stylus bending calibrated first (`probe-force` from the same nominal start),
    // so the slow scan is as good as the machine's static calibration makes it.
    measure_from_nominal(&dir, "probe-force", MACHINE, "2", "pf.mcap", true);
    calibrate_json(&dir, "probe-force", "pf.mcap", "nominal.json", "pf.json");
    let r2 = ok(
        &dir,
        &[
            "calibrate",
            "dynamic-map",
            "--bag",
            "dm.mcap",
            "--calib",
            "pf.json",
            "--out",
            "dm-pf.json",
            "--report",
            "dm.html",
        ],
    );
    eprintln!("{r2}");

    // What it measured, with uncertainties.
    let maps = r["maps"].as_array().unwrap();
    assert_eq!(maps.len(), 1, "{r:#}");
    let m = &maps[0];
    assert_eq!(m["e2_um"].as_array().unwrap().len(), 72);
    assert!(m["e2_u_um"]
        .as_array()
        .unwrap()
        .iter()
        .all(|u| u.as_f64().unwrap() > 0.0));
    assert!(m["speed_mm_s"].as_f64().unwrap() >= 40.0);
    for (name, p) in r["params"].as_object().unwrap() {
        let s = r["uncertainty"][name].as_f64().unwrap();
        eprintln!(
            "{name}: {:.3} ± {:.3} µm",
            p.as_f64().unwrap() * 1e3,
            s * 1e3
        );
        assert!(s.is_finite() && s > 0.0, "{name}: σ {s}");
    }
    let cal = json(&std::fs::read_to_string(dir.join("dm-nominal.json")).unwrap());
    assert_eq!(cal["version"], 2);
    assert!(cal["note"].as_str().unwrap().contains("dynamic-map"));
    let fm = cal["effects"]
        .as_array()
        .unwrap()
        .iter()
        .find(|e| e["kind"] == "feature_map")
        .expect("a feature_map effect");
    assert_eq!(fm["values_mm"].as_array().unwrap().len(), 72);
    let html = std::fs::read_to_string(dir.join("dm.html")).unwrap();
    assert!(html.contains("dynamic-map-e2") && html.contains("HSZD"));

    // The speed search: F1 and F2 at 20, 40 and 80 mm/s; the difference grows with the speed,
    // maps only where it leaves the tolerance.
    measure_from_nominal(&dir, "dynamic-map-speeds", MACHINE, "3", "sp.mcap", true);
    let sp = json(&ok(
        &dir,
        &[
            "calibrate",
            "dynamic-map",
            "--bag",
            "sp.mcap",
            "--calib",
            "pf.json",
            "--out",
            "sp.json",
            "--tolerance-um",
            "1.0",
            "--json",
        ],
    ));
    let search = &sp["speed_search"][0];
    eprintln!("speed search: {search:#}");
    let steps = search["steps"].as_array().unwrap();
    let speeds: Vec<f64> = steps
        .iter()
        .map(|s| s["speed_mm_s"].as_f64().unwrap())
        .collect();
    assert_eq!(speeds, [20.0, 40.0, 80.0], "{search:#}");
    let diff: Vec<f64> = steps
        .iter()
        .map(|s| s["difference_um"].as_f64().unwrap())
        .collect();
    assert!(diff.windows(2).all(|w| w[1] > w[0]), "{diff:?}");
    assert!(diff[0] <= 1.0 && diff[2] > 1.0, "{diff:?}");
    for s in steps {
        let within = s["difference_um"].as_f64().unwrap() <= 1.0;
        assert_eq!(s["within"], within, "{s}");
        assert_eq!(s["mapped"], !within, "{s}");
    }
    let n_mapped = steps.iter().filter(|s| s["mapped"] == true).count();
    assert_eq!(sp["maps"].as_array().unwrap().len(), n_mapped);
    assert!(search["fastest_within_mm_s"].as_f64().unwrap() >= 20.0);

    // The like part, another run.
    let part = like_part(7, None);
    let floor = part.0.truth.noise_floor_um;
    let rows = [
        ("nominal", slow_fast(&part, &dir, "nominal.json")),
        ("nominal + map", slow_fast(&part, &dir, "dm-nominal.json")),
        ("probe-force", slow_fast(&part, &dir, "pf.json")),
        ("probe-force + map", slow_fast(&part, &dir, "dm-pf.json")),
    ];
    for (label, (slow, fast)) in &rows {
        eprintln!(
            "{label:<18} like part: slow scan {slow:.3} µm RMS, fast scan {fast:.3} µm RMS (×{:.2}; noise floor {floor:.3} µm)",
            fast / slow
        );
    }
    let [(_, nom), (_, nom_map), (_, pf), (_, pf_map)] = rows;
    // The map changes nothing of the slow scan (another segment, another speed).
    assert!((nom.0 - nom_map.0).abs() < 1e-9 && (pf.0 - pf_map.0).abs() < 1e-9);
    // Without a map the fast scan is far worse than the slow one once the static
    // calibration is good; with it, within 1.5× (from either start).
    assert!(pf.1 > 3.0 * pf.0, "the fast scan without a map: {pf:?}");
    assert!(pf_map.1 <= 1.5 * pf_map.0, "probe-force + map: {pf_map:?}");
    assert!(nom_map.1 <= 1.5 * nom_map.0, "nominal + map: {nom_map:?}");
    assert!(nom_map.1 < 0.5 * nom.1, "nominal: {nom:?} → {nom_map:?}");

    map_applies_only_at_its_place(&dir, &part);
}

/// The map's place: the like part where the master stood gets the map; the same part program
/// (the same segment ids, at the same speed) on a bore elsewhere on the table, or at another
/// height, gets none — and `correct` says so, naming the map. Without its place the map would
/// have applied there (so the check is what keeps it off).
fn map_applies_only_at_its_place(dir: &Path, part: &(RunResult, Vec<Sample>)) {
    let text = std::fs::read_to_string(dir.join("dm-pf.json")).unwrap();
    let cal = Calibration::from_json(&text).unwrap();
    let v = json(&text);
    let fm = v["effects"]
        .as_array()
        .unwrap()
        .iter()
        .find(|e| {
            e["kind"] == "feature_map" && e["id"].as_str().unwrap_or("").starts_with("dynamic_map")
        })
        .expect("the map");
    let id = fm["id"].as_str().unwrap().to_string();
    // The place stored: S1's carriage path (the ring's bore less the tip's radius) at the
    // carriage's height (the stylus's length above the tip's).
    let (radius, z) = (
        fm["radius_mm"].as_f64().unwrap(),
        fm["z_mm"].as_f64().unwrap(),
    );
    eprintln!("the map's place: radius {radius:.3} mm about its centre, z {z:.3} mm");
    assert!((z - RING_PLACE[2]).abs() < 100.0, "z {z}");
    assert!(radius > 10.0 && radius < 25.0, "radius {radius}");
    // The same calibration with this map at no place (as the dynamic maps were before the
    // place check; the sphere's static maps of `probe-force` keep theirs).
    let mut anywhere = v.clone();
    for e in anywhere["effects"].as_array_mut().unwrap() {
        if e["kind"] == "feature_map" && e["id"] == id.as_str() {
            let o = e.as_object_mut().unwrap();
            o.remove("radius_mm");
            o.remove("z_mm");
        }
    }
    let anywhere = Calibration::from_json(&anywhere.to_string()).unwrap();
    let pf =
        Calibration::from_json(&std::fs::read_to_string(dir.join("pf.json")).unwrap()).unwrap();
    // At the master's place: the map is in force.
    let home = slow_fast_with(part, &cal, "dm-pf.json");
    assert!(
        home.1 < 0.5 * slow_fast_with(part, &pf, "pf.json").1,
        "{home:?}"
    );
    assert_eq!(home, slow_fast_with(part, &anywhere, "anywhere"));
    for (what, place) in [
        ("150 mm along X", [550.0, 300.0, -250.0]),
        ("30 mm higher", [400.0, 300.0, -220.0]),
    ] {
        let other = like_part(7, Some(place));
        let (with_map, without) = (
            slow_fast_with(&other, &cal, "dm-pf.json"),
            slow_fast_with(&other, &pf, "pf.json"),
        );
        let unplaced = slow_fast_with(&other, &anywhere, "anywhere");
        eprintln!(
            "the part program {what}: fast scan {:.3} µm RMS with the calibration and its map, \
             {:.3} without the map, {:.3} with the map at no place",
            with_map.1, without.1, unplaced.1
        );
        // Bit for bit what the calibration without the map gives.
        assert_eq!(with_map, without, "{what}: the map applied");
        assert_ne!(
            unplaced.1, without.1,
            "{what}: the map without a place would apply"
        );
    }
    // Said loudly: `correct` on a bag of the part program at the other place names the map,
    // and at the master's place does not.
    for (bag, place, idle) in [
        ("home.mcap", "400,300,-250", false),
        ("away.mcap", "550,300,-250", true),
    ] {
        ok(
            dir,
            &[
                "sim",
                "--program",
                "dynamic-map-part",
                "--machine-seed",
                MACHINE,
                "--seed",
                "9",
                "--position",
                place,
                "--out",
                bag,
            ],
        );
        let o = common::run(dir, &["correct", "--bag", bag, "--calib", "dm-pf.json"]);
        assert!(o.status.success(), "{o:?}");
        let err = String::from_utf8_lossy(&o.stderr);
        let named = err.lines().any(|l| {
            l.starts_with("warning: feature map")
                && l.contains(&id)
                && l.contains("applies to none")
        });
        eprintln!("correct {bag}:\n{err}");
        assert_eq!(named, idle, "{bag}: {err}");
    }
}

#[test]
fn dynamic_map_names_the_scans_a_bag_lacks() {
    let dir = scratch("calibrate-dynamic-map-bad");
    // The ring program: circles at one speed and one deflection: S1 at best, no F1, no F2.
    measure_from_nominal(&dir, "ring", MACHINE, "1", "ring.mcap", false);
    let err = fails(
        &dir,
        &[
            "calibrate",
            "dynamic-map",
            "--bag",
            "ring.mcap",
            "--calib",
            "nominal.json",
            "--out",
            "x.json",
        ],
        &["F1", "F2", "missing", "dynamic-map"],
    );
    assert!(!err.contains("NaN"), "{err}");
    assert!(!dir.join("x.json").exists());
    // A measurement without any circle (the straightedge): S1, F1 and F2 all missing.
    measure_from_nominal(&dir, "straightedge", MACHINE, "1", "se.mcap", false);
    fails(
        &dir,
        &[
            "calibrate",
            "dynamic-map",
            "--bag",
            "se.mcap",
            "--calib",
            "nominal.json",
            "--out",
            "x.json",
        ],
        &["S1, F1 and F2"],
    );
}
