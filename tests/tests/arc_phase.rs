//! The servo phase fitted on commanded arcs is the machine's (issue 45: the commanded-arc
//! description biased φ_y's b1).
//!
//! A machine whose only library effect is the servo phase (the scale readouts' delays; every
//! other effect switched off in the simulator, on a machine and runs no other test uses)
//! measures the default campaign and the ring at four speeds, with the controller's arcs
//! (centre and radius) in the commands. From the user's nominal model with a `servo_phase` at
//! zero, `lab fit` must give φ_y's b1 within 0.5 % of the truth, b0 near zero, and φ_y(f)
//! within 0.2 % of the truth at 0.2, 0.4 and 0.6 Hz (the rings' rotation frequencies); the
//! truth only judges. Before the corrector took f from the estimate's rate about the commanded
//! centre (it took √(A_n/R)/(2π), low by half the polygon bias of A and half the servo's
//! amplitude loss), this machine gave b1 1.08 % steep, b0 7.3e-7 rad and φ 0.33–0.44 % steep.

mod common;
use common::*;
use serde_json::Value;

const OTHERS_OFF: [&str; 10] = [
    "--effect",
    "accel_deflection=0",
    "--effect",
    "guide_straightness=0",
    "--effect",
    "probe_force=0",
    "--effect",
    "scale_thermal=0",
    "--effect",
    "stylus_thermal=0",
];

fn json(dir: &std::path::Path, name: &str) -> Value {
    let s = std::fs::read_to_string(dir.join(name)).unwrap();
    serde_json::from_str(&s).unwrap_or_else(|e| panic!("{name}: {e}"))
}

#[test]
fn the_servo_phase_fitted_on_commanded_arcs_is_the_machines() {
    let dir = scratch("arc-phase");
    let t0 = std::time::Instant::now();
    let mut a = vec![
        "sim",
        "--program",
        "campaign",
        "--machine-seed",
        "6113",
        "--seed",
        "6114",
        "--out",
        "c.mcap",
        "--calib-out",
        "start.json",
        "--truth",
        "truth.json",
    ];
    a.extend(BUYERS_DOCUMENTS);
    a.extend(OTHERS_OFF);
    ok(&dir, &a);
    let mut a = vec![
        "sim",
        "--program",
        "ring-speeds",
        "--machine-seed",
        "6113",
        "--seed",
        "6115",
        "--position",
        "550,300,-250",
        "--out",
        "v.mcap",
    ];
    a.extend(OTHERS_OFF);
    ok(&dir, &a);
    // The user's start: the nominal model from the data sheet, and the effect they expect, at
    // zero.
    nominal_start(&dir, "nominal.json", false);
    let mut model = json(&dir, "nominal.json");
    model["effects"] = serde_json::json!([
        {"kind": "servo_phase", "y": [[0.0, 0.0, 0.0]], "z": [[0.0, 0.0, 0.0]]}
    ]);
    std::fs::write(dir.join("model.json"), model.to_string()).unwrap();
    let printed = ok(
        &dir,
        &[
            "lab",
            "fit",
            "--bag",
            "c.mcap",
            "--bag",
            "v.mcap",
            "--calib",
            "model.json",
            "--out",
            "fit.json",
            "--json",
        ],
    );
    let truth = json(&dir, "truth.json");
    let on: Vec<&str> = truth["effects"]
        .as_object()
        .unwrap()
        .iter()
        .filter(|(_, v)| v.as_f64() != Some(0.0))
        .map(|(k, _)| k.as_str())
        .collect();
    assert_eq!(on, ["servo_phase"], "{}", truth["effects"]);
    let b1_true = truth["params"]["dynamics.phase_y.b1.1_rad_per_hz"]
        .as_f64()
        .unwrap();
    assert!(b1_true < -1e-4, "a phase to measure: b1 {b1_true} rad/Hz");
    let fit = json(&dir, "fit.json");
    let phase: Vec<&Value> = fit["effects"]
        .as_array()
        .unwrap()
        .iter()
        .filter(|e| e["kind"] == "servo_phase")
        .collect();
    assert_eq!(phase.len(), 1, "{fit}");
    let b: Vec<f64> = phase[0]["y"][0]
        .as_array()
        .unwrap()
        .iter()
        .map(|v| v.as_f64().unwrap())
        .collect();
    // `lab fit` says what it fitted, as `lab add` and `lab discover` do: the values it wrote,
    // each with a σ that covers the truth, and the Z phase (horizontal rings) not determined.
    let printed: Value =
        serde_json::from_str(&printed).unwrap_or_else(|e| panic!("{e}: {printed}"));
    let ps = printed["params"]
        .as_array()
        .unwrap()
        .iter()
        .find(|e| e["effect"] == "servo_phase")
        .unwrap_or_else(|| panic!("no servo_phase in lab fit's params: {printed}"))["params"]
        .as_array()
        .unwrap()
        .clone();
    let param = |name: &str| {
        ps.iter()
            .find(|p| p["name"] == name)
            .unwrap_or_else(|| panic!("no `{name}` in {ps:?}"))
    };
    let p1 = param("φ_y b1 (rad/Hz)");
    assert_eq!(p1["value"].as_f64(), Some(b[1]), "printed ≠ written: {p1}");
    let s1 = p1["sigma"]
        .as_f64()
        .unwrap_or_else(|| panic!("b1 without σ: {p1}"));
    assert!(
        (b[1] - b1_true).abs() <= 2.0 * s1 && s1 < 0.05 * b1_true.abs(),
        "b1 {:.4e} ± {s1:.2e} against the truth {b1_true:.4e}",
        b[1]
    );
    for z in ["φ_z b0 (rad)", "φ_z b1 (rad/Hz)", "φ_z b2 (rad/Hz²)"] {
        assert!(
            param(z)["sigma"].is_null(),
            "horizontal rings determine {z}? {}",
            param(z)
        );
    }
    let rel = b[1] / b1_true - 1.0;
    eprintln!(
        "φ_y: b0 {:.3e} rad, b1 {:.6e} rad/Hz (truth {b1_true:.6e}, {:+.3} %), b2 {:.3e} rad/Hz²; {:.1} s",
        b[0],
        b[1],
        100.0 * rel,
        b[2],
        t0.elapsed().as_secs_f64()
    );
    assert!(rel.abs() < 5e-3, "b1 {:+.3} % from the truth", 100.0 * rel);
    assert!(b[0].abs() < 3e-7, "b0 {:.3e} rad (truth 0)", b[0]);
    for f in [0.2, 0.4, 0.6] {
        let r = (b[0] + b[1] * f + b[2] * f * f) / (b1_true * f);
        assert!(
            (r - 1.0).abs() < 2e-3,
            "φ_y({f} Hz) {:+.3} % from the truth",
            100.0 * (r - 1.0)
        );
    }
}
