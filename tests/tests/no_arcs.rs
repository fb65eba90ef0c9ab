//! A controller streaming circles as points (no arc centre or radius) gets the servo phase
//! and gain corrections from the estimated curvature, within 10 % of the arc-based ones.
//!
//! The same `ring-speeds` run (same machine, same seed: the machine moves the same) is
//! simulated twice, once with `--no-arcs`, and both bags are corrected with the same
//! calibration (the run's starting calibration, which includes servo_phase, with a servo gain
//! added as a user would state one: the simulated machine's own arc gain is its compliance).
//! On the circles at constant speed the per-point corrections of the two effects are compared.

mod common;
use common::*;
use scancorr_core::lab::program::{ProgramSpec, SegmentKind};
use scancorr_proto::v1::CorrectedPoint;
use std::collections::BTreeMap;
use std::path::Path;

/// Per-effect correction of a point, mm (zero when the effect is not listed).
fn correction(p: &CorrectedPoint, effect: &str) -> [f64; 3] {
    p.corrections
        .iter()
        .find(|c| c.effect == effect)
        .map(|c| [c.dx, c.dy, c.dz])
        .unwrap_or([0.0; 3])
}

fn program(bag: &Path) -> ProgramSpec {
    let r = scancorr_bag::BagReader::open(bag).unwrap();
    let json = &r
        .metadata_named("scancorr.program")
        .expect("program record")["json"];
    serde_json::from_str(json).unwrap()
}

#[derive(Default)]
struct Sums {
    n: usize,
    arc2: f64,
    points2: f64,
    diff2: f64,
}

impl Sums {
    fn add(&mut self, a: [f64; 3], b: [f64; 3]) {
        self.n += 1;
        for i in 0..3 {
            self.arc2 += a[i] * a[i];
            self.points2 += b[i] * b[i];
            self.diff2 += (b[i] - a[i]).powi(2);
        }
    }
    fn rms(&self) -> (f64, f64, f64) {
        let n = self.n.max(1) as f64;
        (
            (self.arc2 / n).sqrt(),
            (self.points2 / n).sqrt(),
            (self.diff2 / n).sqrt(),
        )
    }
}

#[test]
fn circles_streamed_as_points_get_phase_and_gain_corrections_from_the_curvature() {
    let dir = scratch("no-arcs");
    let sim = |out: &str, extra: &[&str]| {
        let mut a = vec![
            "sim",
            "--program",
            "ring-speeds",
            "--seed",
            "3",
            "--machine-seed",
            "2",
            "--out",
            out,
        ];
        a.extend_from_slice(extra);
        ok(&dir, &a);
    };
    sim("arcs.mcap", &["--calib-out", "cal.json"]);
    sim("points.mcap", &["--no-arcs"]);
    // A gain of f¹ and f² terms per axis, of the size a ring procedure reports (µm on 25 mm
    // at these speeds).
    let mut doc: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(dir.join("cal.json")).unwrap()).unwrap();
    doc["effects"]
        .as_array_mut()
        .unwrap()
        .push(serde_json::json!({
            "kind": "servo_gain", "powers": [1, 2],
            "x": [2.0e-4, 7.0e-4], "y": [-1.0e-4, -4.7e-4], "z": [0.0, 0.0]
        }));
    std::fs::write(dir.join("cal.json"), doc.to_string()).unwrap();
    let cal = doc.to_string();
    assert!(
        cal.contains("servo_phase") && cal.contains("servo_gain"),
        "{cal}"
    );
    for (bag, out) in [
        ("arcs.mcap", "arcs-c.mcap"),
        ("points.mcap", "points-c.mcap"),
    ] {
        ok(
            &dir,
            &["correct", "--bag", bag, "--calib", "cal.json", "--out", out],
        );
    }
    let arcs = points(&dir.join("arcs-c.mcap"));
    let pts = points(&dir.join("points-c.mcap"));
    assert!(arcs.len() > 50_000, "{} points", arcs.len());
    let by_t: BTreeMap<i64, &CorrectedPoint> = pts.iter().map(|p| (p.t_ns, p)).collect();

    // Circles at constant speed: scan segments on arcs, away from the speed ramps (at most
    // 0.55 s at these speeds) and the estimator's settling.
    let prog = program(&dir.join("arcs.mcap"));
    let margin = 0.8;
    let steady: Vec<(f64, i64, i64)> = prog
        .segments
        .iter()
        .filter(|s| s.kind == SegmentKind::Scan && s.direction != 0)
        .filter(|s| s.t1_s - s.t0_s > 2.0 * margin + 0.5)
        .map(|s| {
            (
                s.speed,
                ((s.t0_s + margin) * 1e9) as i64,
                ((s.t1_s - margin) * 1e9) as i64,
            )
        })
        .collect();
    assert!(steady.len() >= 8, "{} steady circles", steady.len());

    let mut sums: BTreeMap<(&str, i64), Sums> = BTreeMap::new();
    let mut total: BTreeMap<&str, Sums> = BTreeMap::new();
    let mut missing = 0;
    for a in &arcs {
        let Some(&(speed, _, _)) = steady
            .iter()
            .find(|(_, t0, t1)| (*t0..=*t1).contains(&a.t_ns))
        else {
            continue;
        };
        let Some(b) = by_t.get(&a.t_ns) else {
            missing += 1;
            continue;
        };
        for effect in ["servo_phase", "servo_gain"] {
            let (ca, cb) = (correction(a, effect), correction(b, effect));
            sums.entry((effect, speed.round() as i64))
                .or_default()
                .add(ca, cb);
            total.entry(effect).or_default().add(ca, cb);
        }
    }
    assert_eq!(missing, 0, "points corrected with arcs but not without");
    for ((effect, speed), s) in &sums {
        let (ra, rb, rd) = s.rms();
        eprintln!(
            "{effect} at {speed} mm/s: {} points, RMS arc-based {:.3} µm, from curvature {:.3} µm, difference {:.4} µm ({:.2} %)",
            s.n,
            ra * 1e3,
            rb * 1e3,
            rd * 1e3,
            100.0 * rd / ra
        );
    }
    for (effect, s) in &total {
        let (ra, rb, rd) = s.rms();
        eprintln!(
            "{effect}: {} points, RMS arc-based {:.3} µm, from curvature {:.3} µm, difference {:.4} µm ({:.2} %)",
            s.n,
            ra * 1e3,
            rb * 1e3,
            rd * 1e3,
            100.0 * rd / ra
        );
        assert!(s.n > 20_000, "{effect}: {} points", s.n);
        // Non-zero: the effect is there with arcs, and without them.
        assert!(ra > 1e-5, "{effect}: arc-based RMS {ra} mm");
        assert!(rb > 0.5 * ra, "{effect}: {rb} mm from curvature vs {ra} mm");
        assert!(
            rd <= 0.1 * ra,
            "{effect}: RMS difference {rd} mm > 10 % of {ra} mm"
        );
    }
    // Per speed too, where the effect is not negligible.
    for ((effect, speed), s) in &sums {
        let (ra, _, rd) = s.rms();
        if ra > 1e-4 {
            assert!(
                rd <= 0.1 * ra,
                "{effect} at {speed} mm/s: RMS difference {rd} mm > 10 % of {ra} mm"
            );
        }
    }
}
