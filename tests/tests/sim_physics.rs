//! The simulated machine's own physics outside the corrector's formulas (`--with latching`,
//! `--with probe_lobing`, `--with rigid_body`): each switch, against a run without it with the
//! same seeds, shows in the raw data or in the corrected points as its physics says, with the
//! magnitudes the truth file records.

mod common;
use common::*;
use nalgebra::{DMatrix, DVector, Matrix4, Rotation3, Vector3, Vector4};
use scancorr_core::sample::{Sample, StreamId};
use scancorr_proto::v1::CorrectedPoint;
use serde_json::Value;
use std::collections::HashMap;
use std::path::Path;

type V3 = Vector3<f64>;

/// `scancorr sim --program ring-speeds` into `NAME.mcap`, `NAME.truth.json`, `NAME.cal.json`.
fn sim(dir: &Path, name: &str, with: Option<&str>) -> Value {
    let (bag, truth, cal) = (
        format!("{name}.mcap"),
        format!("{name}.truth.json"),
        format!("{name}.cal.json"),
    );
    let mut args = vec![
        "sim",
        "--program",
        "ring-speeds",
        "--seed",
        "3",
        "--machine-seed",
        "5",
        "--out",
        &bag,
        "--truth",
        &truth,
        "--calib-out",
        &cal,
    ];
    if let Some(w) = with {
        args.extend(["--with", w]);
    }
    ok(dir, &args);
    serde_json::from_slice(&std::fs::read(dir.join(&truth)).unwrap()).unwrap()
}

/// Corrects `NAME.mcap` with `cal` and returns the points.
fn correct(dir: &Path, name: &str, cal: &str) -> Vec<CorrectedPoint> {
    let out = format!("{name}.points.mcap");
    ok(
        dir,
        &[
            "correct",
            "--bag",
            &format!("{name}.mcap"),
            "--calib",
            cal,
            "--out",
            &out,
        ],
    );
    points(&dir.join(out))
}

/// Scale readings by time stamp.
fn scales(bag: &Path) -> Vec<(i64, V3)> {
    let r = scancorr_bag::BagReader::open(bag).unwrap();
    let mut v = vec![];
    for m in r.messages().unwrap() {
        let m = m.unwrap();
        if m.stream == scancorr_bag::Stream::Scale {
            scancorr_core::wire::decode_with(StreamId::Scale, &m.data, |_, s| {
                if let Sample::Scale(s) = s {
                    v.push((s.t_ns, V3::new(s.pos.x, s.pos.y, s.pos.z)));
                }
            })
            .unwrap();
        }
    }
    v.sort_by_key(|s| s.0);
    v
}

fn v3(v: &Option<scancorr_proto::v1::Vec3>) -> V3 {
    let v = v.as_ref().unwrap();
    V3::new(v.x, v.y, v.z)
}

fn f64s(v: &Value) -> Vec<f64> {
    v.as_array()
        .unwrap()
        .iter()
        .map(|x| x.as_f64().unwrap())
        .collect()
}

fn ring_centre(truth: &Value) -> V3 {
    let c = f64s(&truth["features"][0]["center"]);
    V3::new(c[0], c[1], c[2])
}

/// Contact points on the ring (surface within 0.2 mm of the bore), by time stamp.
fn on_ring(pts: &[CorrectedPoint], c: &V3, tip: Option<u32>) -> HashMap<i64, CorrectedPoint> {
    pts.iter()
        .filter(|p| p.estimator_valid && tip.map_or(true, |t| p.tip_id == t))
        .filter(|p| {
            let s = v3(&p.surface) - c;
            (s.x.hypot(s.y) - 25.0).abs() < 0.2 && s.z.abs() < 5.0
        })
        .map(|p| (p.t_ns, p.clone()))
        .collect()
}

/// Least-squares fit of y = X·β.
fn lsq(rows: &[Vec<f64>], y: &[f64]) -> Vec<f64> {
    let x = DMatrix::from_fn(rows.len(), rows[0].len(), |i, j| rows[i][j]);
    let y = DVector::from_column_slice(y);
    let xtx = x.transpose() * &x;
    let xty = x.transpose() * y;
    xtx.lu().solve(&xty).unwrap().iter().copied().collect()
}

#[test]
fn latching_shifts_each_scale_by_its_delay_times_velocity() {
    let dir = scratch("sim-physics-latching");
    let truth = sim(&dir, "off", None);
    let truth_on = sim(&dir, "on", Some("latching"));
    assert!(f64s(&truth["machine"]["latching"]["tau_s"])
        .iter()
        .all(|t| *t == 0.0));
    let tau = f64s(&truth_on["machine"]["latching"]["tau_s"]);
    assert!(tau.iter().all(|t| (20e-6..=120e-6).contains(t)), "{tau:?}");
    let (a, b) = (scales(&dir.join("off.mcap")), scales(&dir.join("on.mcap")));
    assert_eq!(a.len(), b.len());
    for ax in 0..2 {
        // Regress (latched − reference) on the reference's scale velocity (central difference).
        let (mut num, mut den) = (0.0, 0.0);
        for i in 1..a.len() - 1 {
            assert_eq!(a[i].0, b[i].0);
            let h = (a[i + 1].0 - a[i - 1].0) as f64 * 1e-9;
            let v = (a[i + 1].1[ax] - a[i - 1].1[ax]) / h;
            let d = b[i].1[ax] - a[i].1[ax];
            num += d * v;
            den += v * v;
        }
        let est = num / den;
        eprintln!(
            "latching axis {ax}: true τ {:.2} µs, recovered {:.2} µs",
            tau[ax] * 1e6,
            est * 1e6
        );
        assert!(
            (est / tau[ax] - 1.0).abs() < 0.05,
            "axis {ax}: recovered τ {est} vs true {}",
            tau[ax]
        );
    }
}

#[test]
fn probe_lobing_puts_its_three_lobes_on_the_corrected_ring() {
    let dir = scratch("sim-physics-lobing");
    let truth = sim(&dir, "off", None);
    let truth_on = sim(&dir, "on", Some("probe_lobing"));
    let lob = &truth_on["machine"]["lobing"];
    let (a, b) = (f64s(&lob["a_mm"]), f64s(&lob["b_mm"]));
    let amp3 = f64s(&lob["amplitude_mm"])[1];
    assert!((0.3e-3..=1.0e-3).contains(&amp3), "{amp3}");
    // Same calibration for both (the one written by the run without lobing).
    let c = ring_centre(&truth);
    let fit3 = |name: &str| -> [f64; 2] {
        let pts = on_ring(&correct(&dir, name, "off.cal.json"), &c, Some(1));
        let ps: Vec<V3> = pts.values().map(|p| v3(&p.surface)).collect();
        // Circle centre by least squares (x² + y² = 2ax + 2by + c).
        let rows: Vec<Vec<f64>> = ps.iter().map(|p| vec![2.0 * p.x, 2.0 * p.y, 1.0]).collect();
        let y: Vec<f64> = ps.iter().map(|p| p.x * p.x + p.y * p.y).collect();
        let q = lsq(&rows, &y);
        let (cx, cy) = (q[0], q[1]);
        let mut rows = vec![];
        let mut res = vec![];
        for p in &ps {
            let th = (p.y - cy).atan2(p.x - cx);
            res.push((p.x - cx).hypot(p.y - cy));
            let mut r = vec![1.0];
            for k in 2..=5 {
                r.push((k as f64 * th).cos());
                r.push((k as f64 * th).sin());
            }
            rows.push(r);
        }
        let f = lsq(&rows, &res);
        [f[3], f[4]]
    };
    let (off, on) = (fit3("off"), fit3("on"));
    let d = [on[0] - off[0], on[1] - off[1]];
    // The probe reports its deflection (towards the centre, φ = θ + π) longer by
    // L(φ) = Σ A_k cos(k(φ − φ_k)), so the radius loses L: Δr = A₃ cos(3θ − 3φ₃), i.e. in the
    // document's convention (a_k = −A_k cos kφ_k, b_k = −A_k sin kφ_k) −a₃ cos 3θ − b₃ sin 3θ.
    let expect = [-a[1], -b[1]];
    let amp = d[0].hypot(d[1]);
    let phase_err = ((d[1].atan2(d[0]) - expect[1].atan2(expect[0]) + 3.0 * std::f64::consts::PI)
        % std::f64::consts::TAU
        - std::f64::consts::PI)
        .abs();
    eprintln!(
        "lobing: 3θ of the corrected radius gained {:.3} µm (recorded {:.3} µm), phase off by {:.3} rad",
        amp * 1e3,
        amp3 * 1e3,
        phase_err
    );
    assert!((amp / amp3 - 1.0).abs() < 0.2, "{amp} vs {amp3}");
    assert!(phase_err < 0.2, "phase off by {phase_err} rad");
}

/// The tip for axis positions `p` and stylus offset `off` through the recorded chain
/// T_Y(y)·T_X(x)·T_Z(z), computed here from the truth file's coefficients.
fn chain_tip(rb: &Value, p: &V3, off: &V3) -> V3 {
    let ef = |f: &Value, u: f64| -> f64 {
        let poly = f64s(&f["poly"]);
        let w = &f["wave"];
        let xi = u / 1000.0;
        poly[0] * xi
            + poly[1] * xi * xi
            + w["amplitude"].as_f64().unwrap()
                * (std::f64::consts::TAU * u / w["wavelength_mm"].as_f64().unwrap()
                    + w["phase"].as_f64().unwrap())
                .sin()
    };
    let t = |ax: &Value, u: f64, dir: V3| -> Matrix4<f64> {
        let tr: Vec<f64> = (0..3).map(|j| ef(&ax["translation"][j], u)).collect();
        let ro: Vec<f64> = (0..3).map(|j| ef(&ax["rotation"][j], u)).collect();
        let r = Rotation3::from_euler_angles(ro[0], ro[1], ro[2]);
        let d = dir * u + V3::new(tr[0], tr[1], tr[2]);
        let mut m = r.to_homogeneous();
        m[(0, 3)] = d.x;
        m[(1, 3)] = d.y;
        m[(2, 3)] = d.z;
        m
    };
    let s = |k: &str| rb[k].as_f64().unwrap();
    let dx = V3::new(1.0, s("s_xy"), 0.0).normalize();
    let dz = V3::new(s("s_zx"), s("s_zy"), 1.0).normalize();
    let h = t(&rb["y"], p.y, V3::y())
        * t(&rb["x"], p.x, dx)
        * t(&rb["z"], p.z, dz)
        * Vector4::new(off.x, off.y, off.z, 1.0);
    V3::new(h.x, h.y, h.z)
}

#[test]
fn rigid_body_errors_move_the_corrected_points_as_the_chain_says() {
    let dir = scratch("sim-physics-rigid");
    let truth = sim(&dir, "off", None);
    let truth_on = sim(&dir, "on", Some("rigid_body"));
    let rb = &truth_on["machine"]["rigid_body"];
    let c = ring_centre(&truth);
    let off = on_ring(&correct(&dir, "off", "off.cal.json"), &c, None);
    let on = on_ring(&correct(&dir, "on", "off.cal.json"), &c, None);
    let sc: HashMap<i64, V3> = scales(&dir.join("off.mcap")).into_iter().collect();
    let mut ts: Vec<i64> = off.keys().filter(|t| on.contains_key(t)).copied().collect();
    ts.sort();
    assert!(ts.len() > 1000, "{} common points", ts.len());
    let (mut worst, mut moved, mut n) = (0.0f64, 0.0f64, 0);
    for t in ts.iter().step_by(ts.len() / 60) {
        let (p0, p1) = (&off[t], &on[t]);
        let s0 = v3(&p0.surface);
        let mut nrm = s0 - c;
        nrm.z = 0.0;
        let nrm = nrm.normalize();
        let measured = (v3(&p1.surface) - s0).dot(&nrm);
        // Axis positions from the scales; the stylus offset (with the deflection, a few
        // tenths of a mm, irrelevant for the errors' gradients) from the tip centre.
        let axes = sc[t];
        let stylus = v3(&p0.tip_center) - axes;
        let err = chain_tip(rb, &axes, &stylus) - (axes + stylus);
        let predicted = -err.dot(&nrm);
        worst = worst.max((measured - predicted).abs());
        moved = moved.max(measured.abs());
        n += 1;
    }
    eprintln!(
        "rigid body: {n} points, largest radial shift {:.3} µm, largest mismatch with the chain {:.4} µm",
        moved * 1e3,
        worst * 1e3
    );
    assert!(moved > 1.0e-3, "the points hardly moved: {moved} mm");
    assert!(worst < 0.2e-3, "mismatch {worst} mm");
}
