//! `scancorr lab plan --temp-span-k`: the temperature span in the plan (issue 45, item 3).
//! From a fitted calibration, the plan weighs spans of the room's temperature up to what the
//! user can produce for the thermal effects' σ, writes the span to reach into the program
//! record (`temperature.span_k`) and says why; the simulator runs the record at that span
//! (`sim --program`), and the lab's σ of the scales' expansion coefficients on the bag is
//! within 1.5× of the prediction. The start is the nominal model with the effects a
//! `lab discover` reaches, refitted by `lab fit` on a campaign: the truth only judges.
//! Machine seed 8461, run seeds 84611 and 84612 (no other test uses them).

mod common;
use common::*;
use scancorr_core::effects::{self as fx, EffectConfig};
use scancorr_core::sample::Axis;

fn json(s: &str) -> serde_json::Value {
    assert!(!s.contains("NaN"), "NaN in output: {s}");
    serde_json::from_str(s).unwrap_or_else(|e| panic!("not JSON ({e}): {s}"))
}

/// Not yet met (29 Nov, machine 8461): at the span the plan chose (2 K) the lab's σ of α_y and
/// of the styli's α came within 0.88–1.11× of the prediction, α_x at 1.59× (1.22–1.50× on the
/// same plan with run seeds 84613–84616). Cause, from the parts the lab composes its σ of (`lab
/// plan --program --bag --json` now prints them): σ = √(max(σ_stat, σ_scan, fold spread)² +
/// penalty shift²). α_x's statistical parts agree with the design (σ_stat 1.06–1.12×, σ_scan
/// 0.86–1.14× over the five runs); the fold spread is a one-draw estimate (0.13–1.52×, as
/// random as α_y's 0.02–0.61×); but the penalties move α_x by 0.55–1.0× its predicted σ in
/// every run (α_y 0.13–0.26×), and α_x lies 3.8–4.7e-8 (1.5–1.8 predicted σ) above the truth in
/// all five. The shift follows the start: refitted from starts with α_x at the truth, +3.5e-7
/// and −1.74e-7 (diagnosis only), the shift is 0.13, 1.09 and 0.73 predicted σ and α_x ends
/// 9–10 % of the start's offset back towards it. The fit is pulled towards its start, and this
/// start (the campaign at 0 K) is 7 predicted σ off. That is consistent with what a relative
/// ridge does to a parameter that shares its column (`select`: A_kk·(1 + r), r up to 1e-3; not
/// yet confirmed by switching it off): with a variance inflation V (140 for α_x, 110 for α_y in
/// the design) it is a prior of precision r·V/σ², shrinking the change by r·V/(1 + r·V) ≈ 12 %;
/// α_y's start was 9.2e-8 (2.6 predicted σ) off, hence its smaller shift. The lab's σ covers
/// the bias (it is honest); the design prediction is of the statistical part. Met when the
/// lab's ridge scales with a parameter's own information (1/[A⁻¹]_kk) rather than its column's
/// (A_kk), or is off for a parameter the data determine. Run it with `--ignored`.
#[test]
#[ignore = "α_x's measured σ is 1.59× the prediction: the penalties' shift of it (see the doc)"]
fn the_plan_asks_for_a_temperature_span_and_the_lab_measures_what_it_predicted() {
    let t0 = std::time::Instant::now();
    let d = scratch("lab-plan-thermal");
    let m = ["--machine-seed", "8461"];
    let sim = |args: &[&str]| ok(&d, &[&["sim"][..], args, &m].concat());
    sim(&[
        "--program",
        "campaign",
        "--seed",
        "84611",
        "--out",
        "c.mcap",
        "--datasheet-out",
        "ds.json",
        "--calib-out",
        "sim.json",
    ]);
    // The user's start: nominal, the discovered model's effects at zero, `lab fit`.
    ok(
        &d,
        &[
            "calib",
            "nominal",
            "--datasheet",
            "ds.json",
            "--tips-from",
            "sim.json",
            "--out",
            "nominal.json",
        ],
    );
    let mut cal = scancorr_core::Calibration::from_json(
        &std::fs::read_to_string(d.join("nominal.json")).unwrap(),
    )
    .unwrap();
    let tips: Vec<u32> = cal.geometry.tips.iter().map(|t| t.id).collect();
    let mut guide = fx::guide_straightness::Config::zeros(Axis::X, 150.0, 900.0, 39, true);
    guide.pitch_about = Some(Axis::Z);
    cal.effects = vec![
        EffectConfig::ProbeForce(fx::probe_force::Config::zeros_per_tip(&tips)),
        EffectConfig::GuideStraightness(guide),
        EffectConfig::AccelDeflection(fx::accel_deflection::Config::zeros(1, false)),
        EffectConfig::ServoPhase(fx::servo_phase::Config::zeros(0)),
        EffectConfig::ScaleThermal(fx::scale_thermal::Config::zeros()),
        EffectConfig::StylusThermal(fx::stylus_thermal::Config::zeros(false)),
    ];
    std::fs::write(d.join("start.json"), cal.to_json()).unwrap();
    ok(
        &d,
        &[
            "lab",
            "fit",
            "--bag",
            "c.mcap",
            "--calib",
            "start.json",
            "--out",
            "fitted.json",
        ],
    );
    // The plan, with the span the user can produce (4 K).
    let planned = json(&ok(
        &d,
        &[
            "lab",
            "plan",
            "--calib",
            "fitted.json",
            "--datasheet",
            "ds.json",
            "--artifact",
            "ring:d=50.0012",
            "--artifact",
            "sphere:d=25.0004",
            "--minutes",
            "8",
            "--candidate",
            "none",
            "--temp-span-k",
            "4",
            "--replicates",
            "0",
            "--out",
            "plan.json",
            "--json",
        ],
    ));
    let th = &planned["thermal"];
    let span = th["span_k"].as_f64().unwrap_or_else(|| panic!("{th}"));
    assert!(span > 0.0 && span <= 4.0, "{th}");
    assert!(th["why"].as_str().unwrap().contains(" K"), "{th}");
    let record: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(d.join("plan.json")).unwrap()).unwrap();
    assert_eq!(record["temperature"]["span_k"].as_f64(), Some(span));
    // What the span buys: σ(α_x) at no span against the span chosen.
    let sigma_at = |i: usize, name: &str| {
        th["ladder"][i]["params"]
            .as_array()
            .unwrap()
            .iter()
            .find(|p| p["name"].as_str().unwrap().starts_with(name))
            .and_then(|p| p["sigma"].as_f64())
    };
    let ladder = th["ladder"].as_array().unwrap();
    let chosen = ladder
        .iter()
        .position(|s| s["span_k"].as_f64() == Some(span))
        .unwrap();
    let (s0, s1) = (sigma_at(0, "alpha_x"), sigma_at(chosen, "alpha_x").unwrap());
    assert!(
        s0.is_none_or(|s0| s0 > 1.5 * s1),
        "σ(α_x) {s0:?} at 0 K against {s1:e} at {span} K"
    );
    // The simulator runs the record at its span; the lab fits the bag.
    sim(&[
        "--program",
        "plan.json",
        "--seed",
        "84612",
        "--out",
        "p.mcap",
        "--truth",
        "truth.json",
    ]);
    let truth = json(&std::fs::read_to_string(d.join("truth.json")).unwrap());
    let [lo, hi] = [0, 1].map(|i| truth["temperatures"]["scale_x"][i].as_f64().unwrap());
    assert!(
        (hi - lo - span).abs() < 0.5 * span.max(1.0),
        "the scales spanned {lo:.2}…{hi:.2} °C for a span of {span} K"
    );
    let checked = json(&ok(
        &d,
        &[
            "lab",
            "plan",
            "--calib",
            "fitted.json",
            "--program",
            "plan.json",
            "--bag",
            "p.mcap",
            "--candidate",
            "none",
            "--replicates",
            "0",
            "--json",
        ],
    ));
    let pred = checked["prediction_at_measured_noise"]["params"]
        .as_array()
        .unwrap();
    let meas = checked["measured"].as_array().unwrap();
    let mut ratios = vec![];
    for (p, q) in pred.iter().zip(meas) {
        let name = p["name"].as_str().unwrap();
        if p["effect"] != "scale_thermal" || name.starts_with("alpha_z") {
            continue;
        }
        let ps = p["sigma"].as_f64().unwrap_or_else(|| panic!("{name}: {p}"));
        let ms = q["sigma"].as_f64().unwrap_or_else(|| {
            panic!("{name}: predicted σ {ps:e}, the lab could not determine it")
        });
        ratios.push((name.to_string(), ms / ps));
    }
    eprintln!(
        "lab_plan_thermal: span {span} K, measured σ / predicted σ {ratios:?} ({:.1} s)",
        t0.elapsed().as_secs_f64()
    );
    assert_eq!(ratios.len(), 2, "{ratios:?}");
    for (n, r) in &ratios {
        assert!(
            (1.0 / 1.5..=1.5).contains(r),
            "{n}: measured/predicted σ {r:.2}"
        );
    }
}
